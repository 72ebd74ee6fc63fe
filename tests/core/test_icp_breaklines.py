"""The breakline-aware spline field and breakline detection (issue #29): the sided basis
against a slow per-point reference, a step field free of penalty, a slab beyond a straight
scarp recovered on both sides (given and detected), a smooth lobe not cut, a line ending
inside the area leaving the field continuous around its tip."""

from __future__ import annotations

import numpy as np
from test_breaklines import _slow_crossings
from test_icp import UTM, cloud, surface

from slipmap.core.breaklines import breaklines, detect_breaklines, distance_m
from slipmap.core.icp import windowed_icp
from slipmap.core.icp_spline import (
    SplineField,
    bspline_weights,
    knot_copies,
    knot_xy,
    sided_second_differences,
    spline_basis,
)

ORIGIN, H, NX, NY = (100.0, -50.0), 2.0, 8, 7


def _slow_basis(xy, parts, copy_index):
    """Per point, per knot: the knot's copy where knot -> point crosses the lines an odd
    number of times (the obvious loops)."""
    kx = NX + 3
    idx, w = [], []
    for p in xy:
        u, v = (p[0] - ORIGIN[0]) / H, (p[1] - ORIGIN[1]) / H
        iu, iv = min(max(int(np.floor(u)), 0), NX - 1), min(max(int(np.floor(v)), 0), NY - 1)
        bu, bv = bspline_weights(np.array([u - iu]))[0], bspline_weights(np.array([v - iv]))[0]
        row_i, row_w = [], []
        for a in range(4):
            for b in range(4):
                k = (iv + a) * kx + iu + b
                kp = np.array([ORIGIN[0] + H * (iu + b - 1), ORIGIN[1] + H * (iv + a - 1)])
                n = _slow_crossings([kp], [p], parts)[0]
                row_i.append(copy_index[k] if copy_index[k] >= 0 and n % 2 else k)
                row_w.append(bv[a] * bu[b])
        idx.append(row_i)
        w.append(row_w)
    return np.array(idx), np.array(w)


def test_the_sided_basis_equals_a_slow_per_point_reference():
    rng = np.random.default_rng(0)
    parts = [
        np.array([[103.0, -52.0], [108.5, -45.0], [111.0, -30.0]]),
        np.array([[112.0, -47.0], [118.0, -44.5]]),
    ]  # fmt: skip  (the second ends inside)
    bl = breaklines(parts)
    ci = knot_copies(ORIGIN, H, NX, NY, bl)
    assert 0 < np.count_nonzero(ci >= 0) < ci.size
    xy = np.c_[rng.uniform(100, 116, 400), rng.uniform(-50, -36, 400)]
    idx, w = spline_basis(xy, origin_xy=ORIGIN, spacing_m=H, n_x=NX, n_y=NY, lines=bl,
                          copy_index=ci)  # fmt: skip
    ref_i, ref_w = _slow_basis(xy, parts, ci)
    np.testing.assert_array_equal(idx, ref_i)
    np.testing.assert_allclose(w, ref_w, atol=1e-14)
    assert np.any(idx >= ci.size)  # some points do take copies
    # a chunk of the points gets the same answer (tiles call the basis per chunk)
    i2, _ = spline_basis(xy[123:200], origin_xy=ORIGIN, spacing_m=H, n_x=NX, n_y=NY,
                         lines=bl, copy_index=ci)  # fmt: skip
    np.testing.assert_array_equal(i2, idx[123:200])


def test_a_step_across_a_line_costs_no_penalty_and_the_field_honours_sides():
    """Knots and copies set to the motion of the side they stand for (a rigid slab beyond a
    line crossing the whole grid): every sided second difference is zero, and the field is
    the step exactly, at any point off the line's support... and everywhere on each side."""
    line = np.array([[105.3, -60.0], [108.1, -20.0]])
    bl = breaklines([line])
    ci = knot_copies(ORIGIN, H, NX, NY, bl)
    pos = knot_xy(ORIGIN, H, NX, NY)

    def east(p):
        return (line[1, 0] - line[0, 0]) * (p[:, 1] - line[0, 1]) - (line[1, 1] - line[0, 1]) * (
            p[:, 0] - line[0, 0]
        ) < 0

    slab = np.array([0.3, -0.2, 0.05])
    grid_c = east(pos)[:, None] * slab
    copies = ~east(pos[ci >= 0])[:, None] * slab  # a copy stands for the other side
    r2 = sided_second_differences(ORIGIN, H, NX, NY, bl, ci)
    c = np.vstack([grid_c, copies])
    for j in range(3):
        assert abs(c[:, j] @ (r2 @ c[:, j])) < 1e-12  # against 0.09 for one wrong pair
    f = SplineField(ORIGIN, H, NX, NY, grid_c.reshape(NY + 3, NX + 3, 3), lines=bl,
                    copy_coefficients=copies)  # fmt: skip
    rng = np.random.default_rng(1)
    xy = np.c_[rng.uniform(100, 116, 2000), rng.uniform(-50, -36, 2000)]
    xy = xy[distance_m(xy, bl) > 1e-6]
    np.testing.assert_allclose(f(xy), east(xy)[:, None] * slab, atol=1e-12)
    np.testing.assert_allclose(f.gradient(xy), 0.0, atol=1e-12)


# --------------------------------------------------------------------------- fits

A, B = np.array([21.3, -5.0]), np.array([23.3, 45.0])  # an oblique scarp, off the cell edges
SLAB = np.array([0.1, -0.4, -0.1])


def _east(xy):
    return ((B[0] - A[0]) * (xy[:, 1] - A[1]) - (B[1] - A[1]) * (xy[:, 0] - A[0])) < 0


def _scarp_pair(seed=0, n=60_000):
    """Rough terrain (40 m square, 3 mm noise) sampled twice; the second sampling's points
    east of a straight scarp moved by a rigid slab (0.42 m)."""
    rng = np.random.default_rng(seed)

    def sample():
        xy = rng.uniform(0.0, 40.0, (n, 2))
        return np.c_[xy, surface(xy) + rng.normal(0.0, 0.003, n)]

    b, a = sample(), sample()
    a = a + _east(a[:, :2])[:, None] * SLAB
    return b + UTM, a + UTM


def _scarp_errors(res, reach_m):
    """RMS 3-D error of the full cells at least ``reach_m`` from the scarp."""
    c = np.c_[res.x, res.y] - UTM[:2]
    truth = _east(c - SLAB[:2])[:, None] * SLAB
    e = np.linalg.norm(np.c_[res.dx, res.dy, res.dz] - truth, axis=1)
    far = distance_m(c, breaklines([np.array([A, B])])) >= reach_m
    full = res.n_after > 0.8 * np.median(res.n_after)
    return float(np.sqrt(np.mean(e[far & full] ** 2))), int(np.count_nonzero(far & full))


def test_a_slab_beyond_a_given_scarp_is_recovered_on_both_sides():
    """4 m cells, knots 2 m: the smooth spline smears the 0.42 m step over the cells next to
    it (measured 12 mm RMS at cells >= 2 m from it); told the scarp, the field is smooth on
    each side and recovers both (measured 0.9 mm)."""
    before, after = _scarp_pair()
    kw = dict(cell_m=4.0, coarse_to_fine=1, field_model="spline")
    smooth, n = _scarp_errors(windowed_icp(before, after, **kw), 2.0)
    res = windowed_icp(before, after, breaklines=[np.array([A, B]) + UTM[:2]], **kw)
    sided, _ = _scarp_errors(res, 2.0)
    assert n >= 60
    assert sided < 0.003, sided
    assert smooth > 3 * sided and smooth > 0.006, (smooth, sided)
    assert res.breaklines_source == "given" and len(res.breaklines) == 1


def test_a_scarp_is_detected_placed_and_the_slab_recovered():
    before, after = _scarp_pair()
    res = windowed_icp(
        before, after, cell_m=4.0, coarse_to_fine=1, field_model="spline", detect_breaklines=True
    )
    assert res.breaklines_source == "detected" and len(res.breaklines) == 1
    line = res.breaklines.parts[0] - UTM[:2]
    # placed on the points: within 0.5 m of the scarp over the data (a cell is 4 m)
    inside = np.linspace(0, 1, 50)[:, None] * (line[-1] - line[0]) + line[0]
    inside = inside[(inside[:, 1] > 0) & (inside[:, 1] < 40)]
    assert len(inside) > 20
    assert distance_m(inside, breaklines([np.array([A, B])])).max() < 0.5
    err, _ = _scarp_errors(res, 2.0)
    assert err < 0.004, err  # measured 0.9-1.2 mm (given: 0.9 mm)


def test_a_line_ending_inside_keeps_a_smooth_field_continuous_around_its_tip():
    """A linear field lies in the spline space on each side; a breakline that ends in the
    middle of the area must not break it: the field is recovered everywhere, and around the
    line's tip it has no jump."""
    rng = np.random.default_rng(4)
    before = cloud(rng, -3.0, 23.0, 60, 0.0)
    src = before[np.all((before[:, :2] > 0.0) & (before[:, :2] < 20.0), axis=1)]
    d0 = np.array([0.12, -0.08, 0.03])
    J = np.array([[0.008, -0.004], [0.003, -0.006], [0.002, 0.004]])
    after = src + d0 + (src[:, :2] - 10.0) @ J.T
    tip = np.array([11.3, 9.1])
    line = np.array([[-5.0, 2.0], tip]) + UTM[:2]
    res = windowed_icp(
        before + UTM, after + UTM, cell_m=5.0, field_model="spline", sigma_scaling="formal",
        tolerance_m=1e-10, robust=None, max_iterations=60, breaklines=[line],
    )  # fmt: skip
    c = np.c_[res.x, res.y] - UTM[:2]
    pxy = np.linalg.solve(np.eye(2) + J[:2], (c - d0[:2] + 10.0 * J[:2].sum(axis=1)).T).T
    truth = d0 + (pxy - 10.0) @ J.T
    full = res.n_after >= 0.9 * res.n_after.max()
    # exact up to the iteration's stop: 0.5-1.5e-5 m depending on numpy/SciPy and the
    # matcher's backend; a jump at the tip would be millimetres
    assert np.abs(np.c_[res.dx, res.dy, res.dz][full] - truth[full]).max() < 5e-5


def _grid(field, n=10, cell=4.0, noise=0.002, seed=0):
    rng = np.random.default_rng(seed)
    x = (np.arange(n) + 0.5) * cell
    y = 40.0 - (np.arange(n) + 0.5) * cell  # north-up rows, as the ICP's cells
    gx, gy = np.meshgrid(x, y)
    d = field(np.c_[gx.ravel(), gy.ravel()]).reshape(n, n, 3)
    return d + rng.normal(0, noise, d.shape), x, y


def test_detection_finds_a_straight_scarp_and_leaves_smooth_lobes_alone():
    from test_icp_cells import LobeField

    for step in (0.3, 0.6, 1.0):
        slab = np.array([0.0, -step, -0.2 * step])
        d, x, y = _grid(lambda p, s=slab: _east(p)[:, None] * s)
        found = detect_breaklines(d, x=x, y=y, sigma=np.full(d.shape[:2], 0.004))
        assert found is not None and len(found) == 1, step
        # on the cell edges next to the scarp: within a cell of it along the data
        seg = found.parts[0]
        pts = np.linspace(0, 1, 40)[:, None] * (seg[-1] - seg[0]) + seg[0]
        pts = pts[(pts[:, 1] > 0) & (pts[:, 1] < 40)]
        assert distance_m(pts, breaklines([np.array([A, B])])).max() < 4.0
    # lobes 2-3 cells in radius (8-11 m on 4 m cells) rise over two cells like a step that a
    # straddling cell splits: the grid alone cannot tell, the points can (the jump of the
    # sided field, test_a_steep_lobe_is_not_cut_by_detection); these it leaves alone
    for radius, peak in ((6.0, 0.5), (16.0, 0.6), (16.0, 1.0)):
        lobe = LobeField(centre_xy=(20.0, 20.0), radius_x_m=radius, radius_y_m=0.8 * radius,
                         max_d_m=(0.0, -peak, -0.4 * peak))  # fmt: skip
        d, x, y = _grid(lobe)
        assert detect_breaklines(d, x=x, y=y, sigma=np.full(d.shape[:2], 0.004)) is None, radius
    # a lone wrong vector is boxed by four step edges: not a line
    d, x, y = _grid(lambda p: np.zeros((len(p), 3)))
    d[4, 6] = [0.5, 0.3, 0.0]
    assert detect_breaklines(d, x=x, y=y) is None


def test_a_steep_lobe_is_not_cut_by_detection():
    """A lobe of radius 9 m (0.6 m peak) on 4 m cells: the cells' grid shows two-cell rises
    a straddled step would also show; fitted with such a line, the two sides' fields meet
    across it (no jump), so the line is dropped and the field is the smooth one."""
    from test_icp_cells import LobeField, lobe_errors

    rng = np.random.default_rng(0)

    def sample(n):
        xy = rng.uniform(0.0, 40.0, (n, 2))
        return np.c_[xy, surface(xy) + rng.normal(0.0, 0.003, n)]

    before, after = sample(60_000), sample(60_000)
    lobe = LobeField(centre_xy=(20.0, 20.0), radius_x_m=9.0, radius_y_m=7.2,
                     max_d_m=(0.0, -0.6, -0.24))  # fmt: skip
    before, after = before + UTM, after + lobe(after[:, :2]) + UTM
    kw = dict(cell_m=4.0, coarse_to_fine=1, field_model="spline")
    res = windowed_icp(before, after, detect_breaklines=True, **kw)
    assert res.breaklines_source == "none" and res.breaklines is None
    smooth = windowed_icp(before, after, **kw)
    np.testing.assert_allclose(res.dx, smooth.dx, atol=1e-9)
    in_lobe, _, _ = lobe_errors(res, lobe)
    assert in_lobe < 0.01, in_lobe
