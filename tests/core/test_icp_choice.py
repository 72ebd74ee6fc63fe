"""The field or the cell, chosen per cell by its points (issue #29 item 1,
:mod:`slipmap.core.icp_choice`): the costs against known motions, and the spline field's
cells that its smoothing puts wrong reporting their own fits (a rotating slump block with no
line found around it, a slab beyond a scarp with no line given), while a smooth lobe keeps
its field."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_icp import UTM, cloud
from test_icp_breaklines import _scarp_errors, _scarp_pair

from slipmap.core.icp import _OffsetTree, estimate_normals, windowed_icp
from slipmap.core.icp_choice import (
    CENTRE_SHARE_OF_CELL,
    MIN_CENTRE_POINTS,
    centre_points,
    choice_costs,
    choose_cells,
)
from slipmap.core.synthetic import LobeField, SlumpField, material_motion


def _patch(seed=0):
    """Epoch 1 on rough terrain; epoch 2 sampled again and moved by a rigid motion per 5 m
    cell of a 2 x 2 grid (a translation and a small rotation about the cell centre)."""
    rng = np.random.default_rng(seed)
    before = cloud(rng, -2.0, 12.0, 200, 0.002)
    after = cloud(rng, 0.0, 10.0, 200, 0.002)
    seg = (after[:, 0] >= 5.0).astype(np.int64) + 2 * (after[:, 1] >= 5.0)
    centres = np.array([[2.5, 2.5, 0.0], [7.5, 2.5, 0.0], [2.5, 7.5, 0.0], [7.5, 7.5, 0.0]])
    d = np.array([[0.03, -0.02, 0.01], [0.05, 0.0, -0.02], [-0.01, 0.04, 0.0], [0.0, 0.0, 0.03]])
    w = np.array([0.0, 0.0, 0.004])  # 4 mrad about the vertical
    grad = np.broadcast_to(np.array([[0, -w[2], 0], [w[2], 0, 0], [0, 0, 0]]), (4, 3, 3))
    # the first-order map of choice_costs, inverted: a cell's points are its epoch-1 surface
    # moved by d + G (p - c)
    after = after + d[seg] + np.einsum("pij,pj->pi", grad[seg], after - centres[seg])
    normals = estimate_normals(before, tree=cKDTree(before))
    tree = _OffsetTree(cKDTree(before - 1.0), np.ones(3))  # the run's tree: map coordinates
    return before, after, seg, centres, d, grad.copy(), tree, (lambda ids: normals[ids])


def _costs(after, seg, centres, field, d, grad, before, tree, normals):
    return choice_costs(
        after, seg, 4, centres, field, d, grad, cell_m=5.0, tree=tree, normals=normals,
        gate=0.5, n_targets=len(before),
    )  # fmt: skip


def test_a_cell_whose_field_is_off_reports_its_own_fit_and_exact_fields_keep_the_field():
    before, after, seg, centres, d, grad, tree, normals = _patch()
    # a field equal to each cell's motion at each of its points (looked up by position)
    at = cKDTree(after[:, :2])
    own = d[seg] + np.einsum("pij,pj->pi", grad[seg], after - centres[seg])

    def exact(xy):
        return own[at.query(xy)[1]]

    usable = np.ones(4, dtype=bool)
    c = _costs(after, seg, centres, exact, d, grad, before, tree, normals)
    assert not choose_cells(c, usable).any()
    np.testing.assert_allclose(c.field, c.cell, atol=1e-9)
    np.testing.assert_allclose(c.centre_field, c.centre_cell, atol=1e-9)
    assert np.all(c.centre_unexplained < 0.02)  # white noise: nothing beyond the truncation

    def off(xy):  # the field 4 cm too low in cell 1 and 3 cm east in cell 2
        k = seg[at.query(xy)[1]]
        return (
            exact(xy)
            + np.where((k == 1)[:, None], [0, 0, -0.04], 0.0)
            + np.where((k == 2)[:, None], [0.03, 0, 0], 0.0)
        )

    c = _costs(after, seg, centres, off, d, grad, before, tree, normals)
    assert choose_cells(c, usable).tolist() == [False, True, True, False]
    # a cell that is not usable (not converged, too few points) keeps the field
    assert not choose_cells(c, np.zeros(4, bool)).any()
    # a cell whose own fit leaves a fifth of the points around its centre unexplained holds
    # two motions there: it keeps the field
    c.centre_unexplained[1] = 0.2
    assert choose_cells(c, usable).tolist() == [False, False, True, False]
    # a cell without a motion of its own has no cost and keeps the field
    d_nan = d.copy()
    d_nan[1] = np.nan
    c = _costs(after, seg, centres, off, d_nan, grad, before, tree, normals)
    assert np.isnan(c.cell[1]) and np.isnan(c.centre_cell[1])
    assert choose_cells(c, usable).tolist() == [False, False, True, False]


def test_a_cell_whose_centre_the_field_fits_better_keeps_the_field():
    """A cell whose own motion is right on most of its points but wrong around its centre
    (it straddles a step and its fit follows the larger side): the field, right around the
    centre, is kept though the cell fits the whole cell better."""
    before, after, seg, centres, d, grad, tree, normals = _patch()
    s = after - centres[seg]
    inner = (seg == 0) & (np.hypot(s[:, 0], s[:, 1]) <= 1.25)
    after = after + np.where(inner[:, None], [0.0, 0.0, 0.04], 0.0)  # the centre's side
    at = cKDTree(after[:, :2])
    own = d[seg] + np.einsum("pij,pj->pi", grad[seg], s)

    def field(xy):  # right around cell 0's centre, 3 cm off on the rest of it (smoothed)
        i = at.query(xy)[1]
        return own[i] + np.where(
            inner[i, None], [0.0, 0.0, 0.04], np.where((seg[i] == 0)[:, None], [0, 0, 0.03], 0.0)
        )

    c = _costs(after, seg, centres, field, d, grad, before, tree, normals)
    # over the whole cell the cell's motion explains more points than the field ...
    assert c.field[0] - c.cell[0] > 2 * c.se[0]
    # ... but not those around its centre
    assert c.centre_cell[0] - c.centre_field[0] > 3 * c.centre_se[0]
    assert not choose_cells(c, np.ones(4, bool))[0]


def test_centre_points_are_the_disc_or_where_it_is_empty_the_nearest_fifth():
    """The points around a centre: the disc of a quarter of the cell's side; in a cell with
    fewer than MIN_CENTRE_POINTS there, its nearest points, the disc's share of the area
    (pi / 16) of them, against a per-cell sort written out."""
    rng = np.random.default_rng(5)
    k, cell = 3, 5.0
    r = np.concatenate([
        rng.uniform(0.0, 3.5, 400),  # a full cell
        rng.uniform(1.3, 3.5, 300),  # a hole at its centre
        np.r_[rng.uniform(0.0, 1.2, MIN_CENTRE_POINTS - 1), rng.uniform(1.3, 3.5, 50)],
    ])  # fmt: skip
    seg = np.repeat(np.arange(k), [400, 300, MIN_CENTRE_POINTS - 1 + 50])
    perm = rng.permutation(r.size)  # the cells' points interleaved
    r, seg = r[perm], seg[perm]
    got = centre_points(r, seg, k, cell_m=cell)
    disc = r <= CENTRE_SHARE_OF_CELL * cell
    want = disc.copy()
    for c in (1, 2):
        idx = np.flatnonzero(seg == c)
        m = int(np.ceil(np.pi * CENTRE_SHARE_OF_CELL**2 * idx.size))
        want[idx] = False
        want[idx[np.argsort(r[idx], kind="stable")[:m]]] = True
    np.testing.assert_array_equal(got, want)
    assert got[seg == 0].sum() == disc[seg == 0].sum() >= MIN_CENTRE_POINTS
    assert got[seg == 1].sum() == 59  # ceil(0.196 * 300)


def test_a_cell_with_an_empty_centre_reports_its_own_fit_where_the_field_is_off():
    """A cell whose centre holds no point (a vent, a shadow) and whose field is off over
    all its points reports its own fit, judged around the centre on its nearest points;
    with the field right it keeps the field (until stop 61 it kept the field always)."""
    before, after, seg, centres, d, grad, tree, normals = _patch()
    s = after - centres[seg]
    keep = ~((seg == 1) & (np.hypot(s[:, 0], s[:, 1]) <= 1.6))  # a hole at cell 1's centre
    after, seg = after[keep], seg[keep]
    at = cKDTree(after[:, :2])
    own = d[seg] + np.einsum("pij,pj->pi", grad[seg], after - centres[seg])

    def exact(xy):
        return own[at.query(xy)[1]]

    def off(xy):  # 5 cm too low in cell 1
        return exact(xy) + np.where((seg[at.query(xy)[1]] == 1)[:, None], [0, 0, -0.05], 0.0)

    usable = np.ones(4, dtype=bool)
    c = _costs(after, seg, centres, off, d, grad, before, tree, normals)
    assert np.isfinite(c.centre_cell[1]) and c.centre_unexplained[1] < 0.02
    assert choose_cells(c, usable).tolist() == [False, True, False, False]
    c = _costs(after, seg, centres, exact, d, grad, before, tree, normals)
    assert not choose_cells(c, usable).any()


def test_the_costs_are_the_reference_costs_of_the_two_residual_sets():
    """choice_costs against the slow reference: residuals point by point, then
    truncated_costs_reference over all points, and over the points around the centres."""
    from slipmap.core.icp_starts import point_residuals, truncated_costs_reference

    before, after, seg, centres, d, grad, tree, normals = _patch(seed=3)

    def field(xy):
        return np.c_[0.02 * np.sin(xy[:, 0]), 0.01 * xy[:, 1] / 10.0, np.full(len(xy), 0.02)]

    got = _costs(after, seg, centres, field, d, grad, before, tree, normals)
    kw = dict(tree=tree, normals=normals, gate=0.5, n_targets=len(before))
    v_f = point_residuals(after - field(after[:, :2]), **kw)
    world_c = np.array([p - d[k] - grad[k] @ (p - centres[k]) for p, k in zip(after, seg)])
    v_c = point_residuals(world_c, **kw)
    want = truncated_costs_reference(v_f, v_c, seg, 4)
    for g, w in zip((got.field, got.cell, got.se), want):
        np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-12)
    around = np.hypot(*(after - centres[seg])[:, :2].T) <= 1.25
    for i in range(4):
        m = seg == i
        # the centre's costs use the whole cell's scale: scale the reference's with it
        ua, ub = _reference_point_costs(v_f[m], v_c[m])
        a, b = ua[around[m]], ub[around[m]]
        np.testing.assert_allclose(got.centre_field[i], a.mean(), rtol=1e-9)
        np.testing.assert_allclose(got.centre_cell[i], b.mean(), rtol=1e-9)
        np.testing.assert_allclose(got.centre_se[i], np.sqrt((a - b).var(ddof=1) / a.size),
                                   rtol=1e-9)  # fmt: skip
        np.testing.assert_allclose(got.centre_unexplained[i], np.mean(b >= 1.0), atol=1e-12)


def _reference_point_costs(v_a, v_b):
    """One cell's per-point truncated costs, the obvious way."""
    from slipmap.core.icp_options import MAD_TO_SIGMA, TUKEY_C

    both = np.abs(np.concatenate([v_a, v_b]))
    c = TUKEY_C * MAD_TO_SIGMA * float(np.median(both[np.isfinite(both)]))

    def cost(v):
        return np.where(np.isfinite(v), np.minimum((v / c) ** 2, 1.0), 1.0)

    return cost(v_a), cost(v_b)


def _field_scene(fld, seed):
    rng = np.random.default_rng(seed)
    b = cloud(rng, 0.0, 40.0, 60, 0.003)
    a = cloud(rng, 0.0, 40.0, 60, 0.003)
    return b + UTM, a + np.asarray(fld(a[:, :2])) + UTM


def _rmse(res, fld):
    c = np.c_[res.x, res.y] - UTM[:2]
    e = np.linalg.norm(np.c_[res.dx, res.dy, res.dz] - material_motion(fld, c), axis=1)
    full = (res.n_after > 0.8 * np.median(res.n_after)) & np.isfinite(e)
    return float(np.sqrt(np.mean(e[full] ** 2)))


KW = dict(cell_m=4.0, coarse_to_fine=1, field_model="spline", detect_breaklines=True)


def test_a_rotating_slump_block_is_recovered_where_the_field_smooths_it():
    """A 16 m block rotating 3 deg about a horizontal axis 8 m up (head down 0.3 m, toe out
    and up), stable ground around: no line is found around all of it and the field smooths
    the block into the ground beside it (measured 9.2 cm RMS over the full 4 m cells); the
    cells whose rigid fits explain their points better, and differ from the field, report
    them (measured 2.4 cm, 8 of 120 cells)."""
    fld = SlumpField((20.0, 20.0), azimuth_deg=180.0, head_m=8.0, toe_m=8.0, width_m=16.0)
    before, after = _field_scene(fld, 1)
    field_only = windowed_icp(before, after, cell_choice=False, **KW)
    chosen = windowed_icp(before, after, cell_choice=True, **KW)
    e_field, e_chosen = _rmse(field_only, fld), _rmse(chosen, fld)
    assert e_field > 0.06, e_field
    assert e_chosen < 0.045 and e_chosen < 0.5 * e_field, (e_chosen, e_field)
    assert not field_only.from_cell.any()
    assert 4 <= int(chosen.from_cell.sum()) <= 30
    # where the cells report their own fit, they are right where the field was wrong
    c = np.c_[chosen.x, chosen.y] - UTM[:2]
    truth = material_motion(fld, c)
    k = chosen.from_cell & np.all(np.isfinite(truth), axis=1)
    e_own = np.linalg.norm(np.c_[chosen.dx, chosen.dy, chosen.dz][k] - truth[k], axis=1)
    same = np.isin(field_only.row * 1000 + field_only.col, chosen.row[k] * 1000 + chosen.col[k])
    e_was = np.linalg.norm(
        np.c_[field_only.dx, field_only.dy, field_only.dz][same] - material_motion(
            fld, np.c_[field_only.x, field_only.y][same] - UTM[:2]
        ), axis=1,
    )  # fmt: skip
    assert np.sqrt(np.mean(e_own**2)) < 0.5 * np.sqrt(np.mean(e_was**2)), (e_own, e_was)
    # their sigmas are their own: the cell-wide floor of the rigid cells, no field pairs
    assert np.all(np.isfinite(chosen.sigma_dz[chosen.from_cell]))


def test_a_smooth_lobe_keeps_its_field():
    """A lobe the field follows (12 m x 9 m, 0.57 m peak): its cells keep the field's values
    (measured: no cell of 120 takes its own fit)."""
    fld = LobeField(centre_xy=(20.0, 20.0), radius_x_m=12.0, radius_y_m=9.0,
                    max_d_m=(0.2, -0.5, -0.2))  # fmt: skip
    before, after = _field_scene(fld, 1)
    field_only = windowed_icp(before, after, cell_choice=False, **KW)
    chosen = windowed_icp(before, after, cell_choice=True, **KW)
    assert int(chosen.from_cell.sum()) <= 3
    assert _rmse(chosen, fld) <= _rmse(field_only, fld) + 5e-4
    assert _rmse(chosen, fld) < 0.005


def test_a_slab_beyond_an_unknown_scarp_without_detection():
    """The slab of tests/core/test_icp_breaklines.py with no line given and detection off:
    the smooth field smears the step (measured 10.3 mm at cells >= 2 m from it); the cells
    beside the scarp report their own fits (measured 4.4 mm, 11 cells)."""
    before, after = _scarp_pair()
    kw = dict(cell_m=4.0, coarse_to_fine=1, field_model="spline")
    smooth, _ = _scarp_errors(windowed_icp(before, after, cell_choice=False, **kw), 2.0)
    res = windowed_icp(before, after, cell_choice=True, **kw)
    chosen, _ = _scarp_errors(res, 2.0)
    assert smooth > 0.008 and chosen < 0.006, (smooth, chosen)
    assert res.from_cell.any()


def test_differ_is_a_chi_square_test_of_the_two_values():
    from slipmap.core.icp_choice import DIFFER_CHI2, differ

    cov = np.broadcast_to(np.diag([1e-4, 4e-4, 1e-6]), (5, 3, 3)).copy()  # 1 cm, 2 cm, 1 mm
    a = np.zeros((5, 3))
    b = np.array(
        [[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.06, 0.0], [0.0, 0.0, 0.003], [np.nan, 0, 0]]
    )
    # distances² 0, 4, 9, 9 (then NaN): above chi²_3's 95 % point (7.8) only for 9
    assert DIFFER_CHI2 == pytest.approx(7.815, abs=1e-3)
    assert differ(a, b, cov).tolist() == [False, False, True, True, False]
    cov[2] = 0.0  # singular: no claim
    assert not differ(a, b, cov)[2]


def test_no_worse_and_more_precise_pick_cells_whose_field_is_barely_determined():
    """Of the cells whose own fit is no worse than the field (over the cell and around its
    centre), those where the field's covariance has more than PRECISION_RATIO times the
    trace of the cell's report their fit (a scan shadow: the field free to bend, the rigid
    cell held by its points)."""
    from slipmap.core.icp_choice import (
        PRECISION_RATIO,
        ChoiceCosts,
        more_precise,
        no_worse,
    )

    nan = np.nan
    # cells: equal costs; own 1 se worse; own 3 se worse; worse around the centre;
    # too much unexplained around the centre; no points around the centre
    c = ChoiceCosts(
        field=np.array([0.10, 0.10, 0.10, 0.10, 0.10, 0.10]),
        cell=np.array([0.10, 0.11, 0.13, 0.10, 0.10, 0.10]),
        se=np.full(6, 0.01),
        unexplained=np.zeros(6),
        centre_field=np.array([0.10, 0.10, 0.10, 0.10, 0.10, nan]),
        centre_cell=np.array([0.10, 0.10, 0.10, 0.20, 0.10, nan]),
        centre_se=np.array([0.01, 0.01, 0.01, 0.01, 0.01, nan]),
        centre_unexplained=np.array([0.0, 0.0, 0.0, 0.0, 0.5, nan]),
    )
    usable = np.ones(6, dtype=bool)
    assert no_worse(c, usable).tolist() == [True, True, False, False, False, False]
    usable[0] = False
    assert not no_worse(c, usable)[0]

    own = np.broadcast_to(np.diag([1e-4, 1e-4, 4e-4]), (4, 3, 3)).copy()
    ratio = np.array([0.5, 0.99, 1.01, 1.01]) * PRECISION_RATIO
    field = own * ratio[:, None, None]
    cand = np.array([True, True, True, False])
    assert more_precise(cand, own, field).tolist() == [False, False, True, False]
    field[2, 0, 0] = np.nan  # no claim where a covariance is not finite
    assert not more_precise(cand, own, field)[2]


def test_cells_where_the_field_is_barely_determined_report_their_own_fits(monkeypatch):
    """The rotating block of the test above: besides the cells whose fits explain their
    points better, cells whose fits explain them as well while the field's covariance at
    their centre has more than PRECISION_RATIO times their trace report their fits
    (measured: 6 more cells; the field 1.2 cm RMS off there, their own fits 0.5 cm)."""
    import slipmap.core.icp_choice as choice

    fld = SlumpField((20.0, 20.0), azimuth_deg=180.0, head_m=8.0, toe_m=8.0, width_m=16.0)
    before, after = _field_scene(fld, 1)
    monkeypatch.setattr(choice, "PRECISION_RATIO", np.inf)  # the cost rule alone
    costs_only = windowed_icp(before, after, cell_choice=True, **KW)
    monkeypatch.undo()
    both = windowed_icp(before, after, cell_choice=True, **KW)
    assert np.array_equal(both.row, costs_only.row) and np.array_equal(both.col, costs_only.col)
    assert not np.any(costs_only.from_cell & ~both.from_cell)
    new = both.from_cell & ~costs_only.from_cell
    assert 1 <= int(new.sum()) <= 15
    truth = material_motion(fld, np.c_[both.x, both.y][new] - UTM[:2])
    e_field = np.c_[costs_only.dx, costs_only.dy, costs_only.dz][new] - truth
    e_own = np.c_[both.dx, both.dy, both.dz][new] - truth
    rms = lambda e: float(np.sqrt(np.mean(np.sum(e**2, axis=1))))  # noqa: E731
    assert rms(e_own) < 0.6 * rms(e_field), (rms(e_own), rms(e_field))
    # their sigmas are their own fits': smaller than the field's there
    var = lambda r: r.sigma_dx[new] ** 2 + r.sigma_dy[new] ** 2 + r.sigma_dz[new] ** 2  # noqa: E731
    assert np.all(var(both) < var(costs_only))
