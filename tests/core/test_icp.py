"""Point-to-plane ICP and windowed ICP on synthetic surfaces and lone-star.laz, with known truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipmap.core.errors import CancelledError, InputDataError, InvalidParameterError
from slipmap.core.icp import (
    _icp_reference,
    estimate_normals,
    icp_point_to_plane,
    points_in_polygons,
    prealign,
    rotation_matrix,
    rotation_vector,
    windowed_icp,
)

DATA = Path(__file__).resolve().parents[1] / "data"
UTM = np.array([512_345.0, 4_912_345.0, 850.0])


def surface(xy: np.ndarray) -> np.ndarray:
    """Rough, non-planar terrain (all 6 DOF constrained in a 5 m patch), metres."""
    x, y = xy[:, 0], xy[:, 1]
    return (
        0.3 * np.sin(2 * np.pi * x / 4.3)
        + 0.25 * np.cos(2 * np.pi * y / 3.7)
        + 0.15 * np.sin(2 * np.pi * (x + 2 * y) / 6.1)
        + 0.1 * x
    )


def cloud(rng, lo, hi, density, noise_m, *, xy_hi=None):
    """Independent random sampling of ``surface`` over [lo, hi]^2 (or [lo, hi] x [lo, xy_hi])."""
    yhi = hi if xy_hi is None else xy_hi
    n = int(density * (hi - lo) * (yhi - lo))
    xy = np.c_[rng.uniform(lo, hi, n), rng.uniform(lo, yhi, n)]
    return np.c_[xy, surface(xy) + rng.normal(0.0, noise_m, n)]


def move(points, rotvec, t, centre):
    """Ground motion: rotate about ``centre`` then translate (epoch 1 -> epoch 2)."""
    return (points - centre) @ rotation_matrix(rotvec).T + centre + t


def truth_params(rotvec, t):
    """Parameters of T = inverse motion (epoch 2 -> epoch 1) about the same centre."""
    R = rotation_matrix(rotvec)
    return np.r_[-np.asarray(rotvec), -R.T @ t]


# --------------------------------------------------------------------------- single ICP


def test_rotation_vector_round_trip():
    rng = np.random.default_rng(0)
    for rv in [np.zeros(3), np.array([1e-9, 0, 0]), *rng.normal(0, 0.3, (5, 3))]:
        R = rotation_matrix(rv)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(rotation_vector(R), rv, atol=1e-13)


def test_recovers_a_known_rigid_motion_on_independent_samples():
    rng = np.random.default_rng(1)
    L = 10.0
    before = cloud(rng, -1.0, L + 1.0, 200, 0.001)
    rv, t = np.array([0.002, -0.003, 0.004]), np.array([0.05, -0.03, 0.02])
    c = np.array([L / 2, L / 2, 0.0])
    after = move(cloud(rng, 0.0, L, 200, 0.001), rv, t, c)  # no shared points
    fit = icp_point_to_plane(after, before, centre=c)
    err = fit.params - truth_params(rv, t)
    assert fit.converged
    assert np.abs(err[3:]).max() < 1e-3  # < 1 mm
    # limited by the point-to-plane discretisation bias (~ curvature * spacing^2), see methods
    assert np.abs(err[:3]).max() < 5e-5
    d, cov = fit.displacement_at(c)
    np.testing.assert_allclose(d, t, atol=1e-3)  # ground motion at the centre = t
    np.testing.assert_allclose(cov, fit.covariance[3:, 3:], rtol=1e-12)  # d = -t at the centre
    # apply() maps the after points back onto their positions before the motion
    back = fit.apply(after)
    np.testing.assert_allclose(
        back, move(after, -rv, np.zeros(3), c) - rotation_matrix(-rv) @ t, atol=2e-3
    )


def test_sigma_is_calibrated_over_seeds():
    z = []
    c = np.array([2.5, 2.5, 0.0])
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        before = cloud(rng, -1.0, 6.0, 80, 0.01)
        rv, t = rng.normal(0, 0.003, 3), rng.normal(0, 0.05, 3)
        after = move(cloud(rng, 0.0, 5.0, 80, 0.01), rv, t, c)
        fit = icp_point_to_plane(after, before, centre=c)
        z.append((fit.params - truth_params(rv, t)) / fit.sigma)
    z = np.array(z)
    assert np.all(z.std(axis=0) > 0.6) and np.all(z.std(axis=0) < 1.5), z.std(axis=0)
    assert np.all(np.abs(z.mean(axis=0)) < 1.2), z.mean(axis=0)


@settings(max_examples=8)
@given(
    ox=st.floats(1e5, 9e5),
    oy=st.floats(1e6, 9e6),
    oz=st.floats(-500, 3000),
    tx=st.floats(-0.1, 0.1),
    rz=st.floats(-0.01, 0.01),
)
def test_utm_offset_gives_the_same_answer(ox, oy, oz, tx, rz):
    rng = np.random.default_rng(7)
    before = cloud(rng, -1.0, 6.0, 60, 0.003)
    c = np.array([2.5, 2.5, 0.0])
    rv, t = np.array([0.001, -0.002, rz]), np.array([tx, 0.02, -0.01])
    after = move(cloud(rng, 0.0, 5.0, 60, 0.003), rv, t, c)
    off = np.array([ox, oy, oz])
    local = icp_point_to_plane(after, before, centre=c)
    utm = icp_point_to_plane(after + off, before + off, centre=c + off)
    np.testing.assert_allclose(utm.params, local.params, atol=1e-7)
    np.testing.assert_allclose(utm.covariance, local.covariance, rtol=1e-5, atol=1e-15)
    d0, _ = local.displacement_at(c)
    d1, _ = utm.displacement_at(c + off)
    np.testing.assert_allclose(d1, d0, atol=1e-7)


def test_reference_loop_agrees_with_fast_path():
    rng = np.random.default_rng(3)
    before = cloud(rng, -0.5, 3.5, 60, 0.002)
    normals = estimate_normals(before)
    c = np.array([1.5, 1.5, 0.0])
    after = move(cloud(rng, 0.0, 3.0, 30, 0.002), [0.003, 0.002, -0.004], [0.04, -0.02, 0.01], c)
    fast = icp_point_to_plane(
        after + UTM, before + UTM, target_normals=normals, robust=None, tolerance_sigma=0
    )
    R, trans = _icp_reference(after + UTM, before + UTM, normals)
    np.testing.assert_allclose(fast.rotation, R, atol=1e-10)
    np.testing.assert_allclose(fast.translation, trans, atol=1e-6)  # includes R @ UTM
    probe = after[:5] + UTM
    np.testing.assert_allclose(fast.apply(probe), probe @ R.T + trans, atol=1e-8)


def test_normals_are_unit_and_perpendicular_to_a_plane():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 2, (500, 2))
    pts = np.c_[xy, 0.2 * xy[:, 0] - 0.1 * xy[:, 1]] + UTM
    n = estimate_normals(pts, neighbours_k=8)
    expect = np.array([-0.2, 0.1, 1.0]) / np.linalg.norm([-0.2, 0.1, 1.0])
    np.testing.assert_allclose(n, np.broadcast_to(expect, n.shape), atol=1e-6)


def test_outliers_are_down_weighted():
    rng = np.random.default_rng(5)
    c = np.array([2.5, 2.5, 0.0])
    before = cloud(rng, -1.0, 6.0, 150, 0.002)
    after = move(cloud(rng, 0.0, 5.0, 150, 0.002), [0, 0, 0.002], [0.03, 0.01, -0.02], c)
    bad = rng.random(len(after)) < 0.1  # 10 % "vegetation" 0.2-0.5 m above ground
    after[bad, 2] += rng.uniform(0.2, 0.5, bad.sum())
    fit = icp_point_to_plane(after, before, centre=c, max_correspondence_m=1.0)
    d, _ = fit.displacement_at(c)
    np.testing.assert_allclose(d, [0.03, 0.01, -0.02], atol=2e-3)


def test_flat_patch_reports_undetermined_parameters():
    rng = np.random.default_rng(6)
    before = np.c_[rng.uniform(-1, 6, (3000, 2)), np.zeros(3000)] + UTM
    after = np.c_[rng.uniform(0, 5, (2000, 2)), np.full(2000, 0.01)] + UTM
    fit = icp_point_to_plane(after, before, robust=None)
    # x, y and the rotation about z are not constrained by a plane: infinite sigma
    assert fit.null_space.shape == (6, 3)
    s = fit.sigma
    assert np.all(np.isinf(s[[2, 3, 4]])) and np.all(np.isfinite(s[[0, 1, 5]]))
    d, cov = fit.displacement_at(after.mean(axis=0))
    assert abs(d[2] - 0.01) < 1e-9  # epoch 2 is 1 cm higher: the ground moved up
    assert np.isinf(cov[0, 0]) and np.isinf(cov[1, 1]) and np.isfinite(cov[2, 2])


# --------------------------------------------------------------------------- windowed


def field_pair(seed, *, shift_left, density=60, noise=0.003):
    """30 x 20 m terrain; epoch 2 moved by ``shift_left`` where x < 15 m, unmoved elsewhere."""
    rng = np.random.default_rng(seed)
    before = cloud(rng, 0.0, 30.0, density, noise, xy_hi=20.0)
    after = cloud(rng, 0.0, 30.0, density, noise, xy_hi=20.0)
    left = after[:, 0] < 15.0
    after[left] += shift_left
    inner = np.all((after[:, :2] > 0.2) & (after[:, :2] < [29.8, 19.8]), axis=1)
    return before + UTM, after[inner] + UTM


def test_windowed_recovers_a_piecewise_field_and_counts_skipped_cells():
    shift = np.array([0.10, -0.05, 0.03])
    before, after = field_pair(11, shift_left=shift)
    # empty most of one cell of epoch 2 and one of epoch 1 -> skipped with their reason
    loc_a = after - UTM
    after = after[
        ~((loc_a[:, 0] > 20.3) & (loc_a[:, 0] < 24.7) & (loc_a[:, 1] > 0.3) & (loc_a[:, 1] < 4.7))
    ]
    loc_b = before - UTM
    before = before[
        ~((loc_b[:, 0] > 25.2) & (loc_b[:, 0] < 29.8) & (loc_b[:, 1] > 15.2) & (loc_b[:, 1] < 19.8))
    ]
    calls = []
    res = windowed_icp(
        before, after, cell_m=5.0, min_points=800, progress=lambda f, m: calls.append(f)
    )
    assert calls and calls[-1] == 1.0
    assert res.skipped["few_after_points"] == 1 and res.skipped["few_before_points"] == 1
    # grid snapped to multiples of 5 m
    assert res.origin_xy[0] % 5 == 0 and res.origin_xy[1] % 5 == 0
    assert len(res) == res.n_rows * res.n_cols - 2 == 22  # 6 x 4 grid
    cx = res.x - UTM[0]
    d = np.c_[res.dx, res.dy, res.dz]
    left, right = cx < 15, cx > 15
    np.testing.assert_allclose(d[left], np.broadcast_to(shift, d[left].shape), atol=4e-3)
    np.testing.assert_allclose(d[right], 0.0, atol=4e-3)
    assert np.all(res.sigma_dx > 0) and np.all(res.converged)
    # grid: row 0 north, NaN where no cell
    g = res.to_grid("dx")
    assert g.shape == (res.n_rows, res.n_cols) and np.isnan(g).sum() == 2
    north = res.row == 0
    np.testing.assert_allclose(res.y[north], res.origin_xy[1] - 2.5)
    np.testing.assert_allclose(g[res.row, res.col], res.dx)
    cols = res.to_columns()
    assert list(cols)[:11] == [
        "x", "y", "z", "dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_dz", "rmse", "n",
    ]  # fmt: skip
    assert all(len(v) == len(res) for v in cols.values())


def test_translating_both_epochs_translates_the_cells_not_the_displacements():
    before, after = field_pair(12, shift_left=np.array([0.05, 0.0, 0.0]), density=40)
    a = windowed_icp(before, after, cell_m=10.0, origin_xy=(UTM[0], UTM[1]))
    b = windowed_icp(
        before + [7.0, -3.0, 2.0],
        after + [7.0, -3.0, 2.0],
        cell_m=10.0,
        origin_xy=(UTM[0] + 7.0, UTM[1] - 3.0),
    )
    np.testing.assert_allclose(b.x, a.x + 7.0)
    np.testing.assert_allclose(b.z, a.z + 2.0)
    np.testing.assert_allclose(np.c_[b.dx, b.dy, b.dz], np.c_[a.dx, a.dy, a.dz], atol=1e-6)


def test_prealign_on_stable_ground_with_a_moving_polygon():
    glob = np.array([0.04, -0.03, 0.02])
    rng = np.random.default_rng(13)
    before = cloud(rng, 0.0, 30.0, 40, 0.003, xy_hi=20.0) + UTM
    after = cloud(rng, 0.0, 30.0, 40, 0.003, xy_hi=20.0) + UTM
    poly = np.array([[10.0, 5.0], [20.0, 5.0], [20.0, 15.0], [10.0, 15.0]]) + UTM[:2]
    inside = points_in_polygons(after, [poly])
    after = after + glob
    after[inside] += [0.25, 0.0, -0.05]  # the landslide moves on top of the global offset
    fit = prealign(before, after, exclude_polygons=[poly])
    c = after.mean(axis=0)
    d, _ = fit.displacement_at(c)
    np.testing.assert_allclose(d, glob, atol=2e-3)
    # without the mask the landslide drags a plain least-squares fit
    bad, _ = prealign(before, after, robust=None).displacement_at(c)
    assert abs(bad[0] - glob[0]) > 0.01
    res = windowed_icp(before, after, cell_m=5.0, prealign=True, exclude_polygons=[poly])
    assert res.prealignment is not None
    inner = points_in_polygons(np.c_[res.x, res.y], [poly])
    np.testing.assert_allclose(res.dx[inner], 0.25, atol=5e-3)
    np.testing.assert_allclose(res.dx[~inner], 0.0, atol=5e-3)
    # a given pre-alignment is applied as is
    given = windowed_icp(before, after, cell_m=5.0, prealign=fit)
    assert given.prealignment is fit
    np.testing.assert_allclose(given.dx, res.dx, atol=1e-3)


def test_points_in_polygons_even_odd():
    L = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 4], [0, 4], [0, 0]], dtype=float) + UTM[:2]
    pts = np.array([[0.5, 0.5], [3, 0.5], [3, 3], [0.5, 3], [-1, 2], [5, 5]]) + UTM[:2]
    np.testing.assert_array_equal(points_in_polygons(pts, [L]), [1, 1, 0, 1, 0, 0])
    sq = np.array([[2.5, 2.5], [3.5, 2.5], [3.5, 3.5], [2.5, 3.5]]) + UTM[:2]
    np.testing.assert_array_equal(points_in_polygons(pts, [L, sq]), [1, 1, 1, 1, 0, 0])


@pytest.mark.slow
def test_lone_star_split_halves_recover_a_known_shift():
    from slipmap.core.io.las import read_las

    xyz = read_las(DATA / "lone-star.laz").xyz
    rng = np.random.default_rng(0)
    half = rng.random(len(xyz)) < 0.5
    shift = np.array([0.2, -0.4, 0.05])
    res = windowed_icp(xyz[half], xyz[~half] + shift, cell_m=5.0)
    big = res.n >= 500
    assert big.sum() >= 30
    err = np.c_[res.dx, res.dy, res.dz][big] - shift
    rmse = np.sqrt(np.mean(np.sum(err**2, axis=1)))
    assert rmse <= 0.01, rmse  # measured 8.7 mm (3-D), 4.0 / 7.1 / 3.0 mm per axis
    # honest sigmas (issue #29): the formal ones (independent residuals) cover only 59 % of
    # the errors within 2 sigma on this real surface; with the block covariances and the
    # cell-wide floor from neighbour agreement (no truth used) 88 % on this seed (0.93-0.98
    # pooled over seeds, docs/fields.md); the field's neighbour factor is applied where it
    # exceeds 1 (sparse airborne cells need it; here it widens the sigmas, the safe side)
    z = np.abs(err) / np.c_[res.sigma_dx, res.sigma_dy, res.sigma_dz][big]
    assert res.sigma_model == "blocks"
    assert res.sigma_factor == pytest.approx(max(1.0, res.sigma_factor_estimate))
    assert res.sigma_floor_factor >= 1.0 and res.sigma_factor_cells >= 20
    assert np.mean(z < 2) >= 0.85, np.mean(z < 2)
    assert np.mean(np.abs(err) / res.sigma_formal[big] < 2) <= 0.75
    # without step damping 21 % of the cells cycled between two transforms until the
    # iteration limit
    assert res.converged.mean() >= 0.95, res.converged.mean()


def test_damping_halves_reversed_steps_for_good():
    from slipmap.core.icp import _Damping

    d = _Damping()
    step = np.array([0.0, 0.0, 0.0, 1e-3, 0.0, 0.0])
    np.testing.assert_allclose(d(step, 1.0), step)
    np.testing.assert_allclose(d(-step, 1.0), -0.5 * step)  # reversal: halved
    np.testing.assert_allclose(d(step, 1.0), 0.25 * step)  # again
    np.testing.assert_allclose(d(step, 1.0), 0.25 * step)  # same direction: kept
    np.testing.assert_allclose(d(-step, 1.0), -0.125 * step)
    # rotations are compared in metres at the given radius: a rotation reversing a
    # translation of the same size counts; orthogonal steps keep the factor
    e = _Damping()
    rot = np.array([0.0, 0.0, 1e-4, 0.0, 0.0, 0.0])
    e(rot, 10.0)
    np.testing.assert_allclose(e(step, 10.0), step)


def test_period_two_cycle_of_plain_icp_converges_with_damping():
    """Two transforms that map each other's pairings onto each other: a 1-D model of the
    cycles seen on lone-star (steps +x, -x, +x, ... forever). Damped steps bracket the
    switch and shrink geometrically."""
    from slipmap.core.icp import _Damping

    def plain_step(q):  # pairing switches at 0.3 mm: below it the target is 1 mm, above it 0
        return np.array([0, 0, 0, (1e-3 if q < 3e-4 else 0.0) - q, 0, 0])

    q, d = 0.0, _Damping()
    steps = []
    for _ in range(40):
        x = d(plain_step(q), 1.0)
        q += x[3]
        steps.append(abs(x[3]))
    assert steps[-1] < 1e-8 and abs(q - 3e-4) < 1e-7


# --------------------------------------------------------------------------- bad input


def test_bad_inputs():
    before, after = field_pair(14, shift_left=np.zeros(3), density=20)
    with pytest.raises(InvalidParameterError, match="cell_m"):
        windowed_icp(before, after, cell_m=0)
    with pytest.raises(InvalidParameterError, match="cell_m"):
        windowed_icp(before, after, cell_m=-5)
    with pytest.raises(InvalidParameterError, match="min_points"):
        windowed_icp(before, after, cell_m=5, min_points=3)
    with pytest.raises(InvalidParameterError, match="robust"):
        windowed_icp(before, after, cell_m=5, robust="cauchy")
    with pytest.raises(InvalidParameterError, match="sigma_scaling"):
        windowed_icp(before, after, cell_m=5, sigma_scaling="empirical")
    with pytest.raises(InputDataError, match="overlap"):
        windowed_icp(before, after + [1000.0, 0, 0], cell_m=5)
    with pytest.raises(InputDataError, match="empty"):
        windowed_icp(before, after[:0], cell_m=5)
    with pytest.raises(InputDataError, match="empty"):
        icp_point_to_plane(after[:0], before)
    nan = after.copy()
    nan[3, 1] = np.nan
    with pytest.raises(InputDataError, match="NaN"):
        windowed_icp(before, nan, cell_m=5)
    with pytest.raises(InputDataError, match=r"\(N, 3\)"):
        icp_point_to_plane(after[:, :2], before)
    with pytest.raises(InputDataError, match=r"skipped.*larger cell_m.*min_points"):
        windowed_icp(before, after, cell_m=5, min_points=10_000)
    before_c = before.copy()
    windowed_icp(before, after, cell_m=10, min_points=50)
    np.testing.assert_array_equal(before, before_c)  # inputs are not modified


def test_progress_can_cancel():
    before, after = field_pair(15, shift_left=np.zeros(3), density=20)

    def cancel(fraction, message):
        if fraction > 0.3:
            raise CancelledError("stop")

    with pytest.raises(CancelledError):
        windowed_icp(before, after, cell_m=5.0, min_points=50, progress=cancel)


def test_coarse_to_fine_recovers_motion_large_against_the_cell():
    """1.6 m of motion in 2 m cells: from zero, ICP stops in local minima (the surface's
    wavelengths are 3.7-6.1 m); started from a coarser pass it recovers every full cell."""
    rng = np.random.default_rng(5)
    shift = np.array([1.1, -1.15, 0.2])
    before = cloud(rng, -3.0, 15.0, 80, 0.002) + UTM
    after = cloud(rng, 0.0, 12.0, 80, 0.002)
    after = np.c_[after[:, :2] + shift[:2], after[:, 2] + shift[2]] + UTM
    kw = dict(cell_m=2.0, buffer_m=2.0, min_points=200)
    plain = windowed_icp(before, after, **kw)
    c2f = windowed_icp(before, after, coarse_to_fine=2, **kw)
    full = c2f.n_after >= 0.9 * c2f.n_after.max()
    err = np.column_stack([c2f.dx, c2f.dy, c2f.dz])[full] - shift
    assert np.abs(err).max() < 0.01
    plain_err = np.column_stack([plain.dx, plain.dy, plain.dz]) - shift
    assert np.abs(plain_err).max() > 0.1  # the reason for coarse_to_fine
    # a given starting field (e.g. from PIV) works the same way
    guess = windowed_icp(
        before, after, initial_displacement=lambda xy: np.tile(shift * 0.9, (len(xy), 1)), **kw
    )
    full = guess.n_after >= 0.9 * guess.n_after.max()
    assert np.abs(np.column_stack([guess.dx, guess.dy, guess.dz])[full] - shift).max() < 0.01
    with pytest.raises(InvalidParameterError, match="coarse_to_fine"):
        windowed_icp(before, after, coarse_to_fine=-1, **kw)
    with pytest.raises(InvalidParameterError, match="initial_displacement"):
        windowed_icp(before, after, initial_displacement=3.0, **kw)


def test_closed_form_normals_equal_eigh():
    """``_pca_normals`` (closed-form 3 x 3 eigen) against ``eigh``: rough planes at UTM
    offsets, steep and flat, lines and repeated points marked NaN by both."""
    from slipmap.core.icp import _pca_normals, _pca_normals_reference

    rng = np.random.default_rng(11)
    k = 4000
    xy = rng.uniform(-0.2, 0.2, (k, 12, 2))
    slope = rng.normal(0.0, 3.0, (k, 1, 2))
    z = np.sum(slope * xy, axis=2) + rng.normal(0.0, 0.003, (k, 12))
    nb = np.concatenate([xy, z[..., None]], axis=2) + UTM
    nb[:10, :, 1] = nb[:10, :1, 1]  # lines (x and z vary, y constant with x... degenerate)
    nb[:10, :, 2] = nb[:10, :1, 2]
    nb[10:15] = nb[10:15, :1]  # one point repeated
    fast, ref = _pca_normals(nb), _pca_normals_reference(nb)
    np.testing.assert_array_equal(np.isnan(fast), np.isnan(ref))
    assert np.isnan(fast[:15]).all()
    ok = ~np.isnan(ref[:, 0])
    np.testing.assert_allclose(fast[ok], ref[ok], atol=1e-9)
