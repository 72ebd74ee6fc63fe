"""Grid roughness by ODR (Pollyea & Fairley 2011): known answers, the reference oracle,
invariances, bad input, maps and semivariograms. Runs in both venvs (numpy only)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipmap.core import roughness as rg
from slipmap.core.errors import CancelledError, InputDataError, InvalidParameterError

UTM = np.array([512_345.0, 4_780_123.0, 1_234.0])
ABS_FACTOR = math.sqrt(1.0 - 2.0 / math.pi)  # std of |N(0, s^2)| / s
MID = (0.5, 0.5, 0.5)  # a cell centre of the unit grid


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _plane_basis(normal: np.ndarray):
    n = _unit(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _unit(np.cross(n, helper))
    e2 = np.cross(n, e1)
    return n, e1, e2


def noisy_plane(rng, normal, *, n_points, half_size, sigma, centre=(0.0, 0.0, 0.0)):
    """Points uniform on a square patch of the plane through ``centre`` + Gaussian noise along n."""
    n, e1, e2 = _plane_basis(normal)
    a = rng.uniform(-half_size, half_size, (n_points, 2))
    noise = rng.normal(0.0, sigma, n_points)
    return np.asarray(centre) + a[:, :1] * e1 + a[:, 1:] * e2 + noise[:, None] * n


def bumpy_surface(rng, n_points=12_000, size=3.0, sigma=0.01):
    xy = rng.uniform(0.0, size, (n_points, 2))
    z = 0.25 * np.sin(1.3 * xy[:, 0]) + 0.15 * np.cos(0.9 * xy[:, 1]) + 0.1 * xy[:, 0]
    z = z + rng.normal(0.0, sigma, n_points) * (1.0 + (xy[:, 0] > size / 2))
    return np.column_stack([xy, z])


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def with_sentinels(pts: np.ndarray, centre, c: float) -> np.ndarray:
    """Add 2 lone points 1.2 cells from ``centre``: the cloud's extent exceeds one cell (the
    API refuses cells larger than the extent) and the lone points' cells are skipped."""
    off = 1.2 * c * np.ones(3)
    return np.vstack([pts, np.asarray(centre) + off, np.asarray(centre) - off])


def _assert_same_grid(fast: rg.RoughnessGrid, ref: rg.RoughnessGrid, rtol=1e-9):
    np.testing.assert_array_equal(fast.index, ref.index)
    np.testing.assert_array_equal(fast.n_points, ref.n_points)
    np.testing.assert_array_equal(fast.degenerate, ref.degenerate)
    assert fast.n_cells_skipped == ref.n_cells_skipped
    assert fast.n_points_skipped == ref.n_points_skipped
    np.testing.assert_allclose(fast.centroid_m, ref.centroid_m, rtol=0, atol=1e-9)
    scale = ref.eigenvalues_m2[:, 2:3]
    np.testing.assert_allclose(fast.eigenvalues_m2 / scale, ref.eigenvalues_m2 / scale, atol=1e-9)
    ok = ~ref.degenerate
    np.testing.assert_allclose(fast.normal[ok], ref.normal[ok], atol=1e-9)
    for name in ("theta_odr", "theta_ols", "e_ols"):
        np.testing.assert_allclose(
            getattr(fast, name), getattr(ref, name), rtol=rtol, atol=1e-12, err_msg=name
        )


# --------------------------------------------------------------------------- reference oracle


@pytest.mark.parametrize("signed", [False, True])
@pytest.mark.parametrize("ols_axis", ["x", "y", "z"])
def test_vectorised_equals_per_cell_svd_loop(ols_axis, signed):
    rng = np.random.default_rng(7)
    pts = bumpy_surface(rng) + UTM
    kw = dict(cell_size_m=0.5, min_points=12, ols_axis=ols_axis, signed=signed)
    ref = rg.grid_roughness_reference(pts, **kw)
    fast = rg.grid_roughness(pts, chunk_points=1500, **kw)  # many chunks: boundaries tested
    assert len(ref) > 30 and ref.n_cells_skipped > 0
    _assert_same_grid(fast, ref)


def test_argsort_path_equals_packed_path():
    rng = np.random.default_rng(8)
    pts = bumpy_surface(rng, n_points=6000) + UTM
    kw = dict(c=0.4, min_points=10, a=2, signed=False, origin_m=None, progress=None)
    packed = rg._grid_roughness(pts, chunk_points=700, packed=True, **kw)
    argsorted = rg._grid_roughness(pts, chunk_points=700, packed=False, **kw)
    _assert_same_grid(argsorted, packed, rtol=1e-12)


def test_default_grid_is_aligned_to_multiples_of_the_cell():
    rng = np.random.default_rng(9)
    pts = bumpy_surface(rng, n_points=3000) + UTM
    g = rg.grid_roughness(pts, cell_size_m=0.25)
    np.testing.assert_array_equal(np.round(g.origin_m / 0.25), g.origin_m / 0.25)
    # every point lies in its reported cell
    per_point = rg.roughness_per_point(pts, g)
    ijk = np.floor((pts - g.origin_m) / 0.25).astype(int)
    keys = rg._pack_index(ijk, g.shape)
    pos = np.searchsorted(g.keys, keys)
    hit = (pos < len(g)) & (g.keys[np.minimum(pos, len(g) - 1)] == keys)
    np.testing.assert_array_equal(per_point[hit], g.theta_odr[pos[hit]])
    assert np.all(np.isnan(per_point[~hit]))


# --------------------------------------------------------------------------- known answers


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_noisy_plane_at_any_orientation_gives_the_analytic_roughness(seed):
    rng = np.random.default_rng(seed)
    normal = _unit(rng.normal(size=3))
    sigma = 0.004
    pts = noisy_plane(rng, normal, n_points=40_000, half_size=1.5, sigma=sigma)
    pts += rng.uniform(-1e5, 1e5, 3)
    g = rg.grid_roughness(pts, cell_size_m=1.0, min_points=300)
    assert len(g) >= 4
    # D_i = |n . v_i|: the published Eq. 4 gives sigma * sqrt(1 - 2/pi)
    weights = g.n_points / g.n_points.sum()
    assert np.sum(weights * g.theta_odr) == pytest.approx(sigma * ABS_FACTOR, rel=0.02)
    # every cell's normal is the plane's normal (small corner patches least precisely)
    cos = np.abs(g.normal @ normal)
    assert np.all(cos > 0.99) and np.sum(weights * cos) > 0.9999
    signed = rg.grid_roughness(pts, cell_size_m=1.0, min_points=300, signed=True)
    assert np.sum(weights * signed.theta_odr) == pytest.approx(sigma, rel=0.02)


def test_single_cell_known_answer_and_ddof0():
    rng = np.random.default_rng(3)
    pts = noisy_plane(rng, [0.3, -0.2, 1.0], n_points=200_000, half_size=0.4, sigma=0.01)
    pts += [0.5, 0.5, 0.5]
    g = rg.grid_roughness(with_sentinels(pts, 0.5, 1.0), cell_size_m=1.0)
    assert len(g) == 1 and g.n_cells_skipped == 2
    assert g.theta_odr[0] == pytest.approx(0.01 * ABS_FACTOR, rel=0.01)
    # ddof = 0 exactly: population std of the absolute distances to the SVD plane
    q = pts - pts.mean(axis=0)
    d = np.abs(q @ np.linalg.svd(q, full_matrices=False)[2][-1])
    assert g.theta_odr[0] == pytest.approx(np.std(d, ddof=0), rel=1e-10)
    assert g.theta_odr[0] != pytest.approx(np.std(d, ddof=1), rel=1e-7)


def test_ols_grows_with_tilt_from_the_ols_axis_while_odr_does_not():
    """The study's Table 1 pattern: theta_OLS = theta_ODR / cos(tilt) for a tilted plane."""
    sigma = 0.005
    odr, ols = [], []
    tilts = [0.0, 20.0, 40.0, 60.0]
    for k, tilt in enumerate(tilts):
        rng = np.random.default_rng(100 + k)
        t = math.radians(tilt)
        normal = np.array([math.sin(t), 0.0, math.cos(t)])  # tilt away from the z axis
        # through cell centres: a plane along a cell face would split its noise between cells
        pts = noisy_plane(rng, normal, n_points=60_000, half_size=1.9, sigma=sigma, centre=MID)
        g = rg.grid_roughness(pts, cell_size_m=1.0, min_points=500, ols_axis="z")
        w = g.n_points / g.n_points.sum()
        odr.append(np.sum(w * g.theta_odr))
        ols.append(np.sum(w * g.theta_ols))
        assert ols[-1] / odr[-1] == pytest.approx(1.0 / math.cos(t), rel=0.02)
        assert np.all(g.e_ols == pytest.approx(np.abs(g.theta_ols - g.theta_odr)))
    assert np.all(np.diff(ols) > 0)
    np.testing.assert_allclose(odr, sigma * ABS_FACTOR, rtol=0.02)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_rigid_motion_leaves_theta_odr_unchanged(seed):
    rng = np.random.default_rng(seed)
    patch = noisy_plane(rng, rng.normal(size=3), n_points=3000, half_size=0.8, sigma=0.02)
    patch[:, 2] += 0.2 * np.sin(3 * patch[:, 0])  # not a plane: a rough, curved patch
    c = 10.0
    here = with_sentinels(patch - patch.mean(axis=0) + 5.0, 5.0, c)
    rot = random_rotation(rng)
    centre = (rng.integers(40_000, 60_000, 3) + 0.5) * c  # survey-size offsets, still 1 cell
    moved = with_sentinels((patch - patch.mean(axis=0)) @ rot.T + centre, centre, c)
    for signed in (False, True):
        a = rg.grid_roughness(here, cell_size_m=c, signed=signed)
        b = rg.grid_roughness(moved, cell_size_m=c, signed=signed)
        assert len(a) == len(b) == 1
        assert a.theta_odr[0] > 0
        assert b.theta_odr[0] == pytest.approx(a.theta_odr[0], rel=1e-7)


def test_eq2_closed_form_agrees_with_the_svd_plane_for_non_vertical_planes():
    rng = np.random.default_rng(11)
    for normal in ([0.1, 0.2, 1.0], [0.7, -0.4, 0.6], [1.0, 1.0, 0.3]):
        pts = noisy_plane(rng, normal, n_points=500, half_size=0.5, sigma=0.01)
        pts += [3.0, -2.0, 7.0]
        b0, b1, b2 = rg.odr_plane_closed_form(pts, centred=True)
        n_eq2 = _unit([b1, b2, -1.0])
        q = pts - pts.mean(axis=0)
        n_svd = np.linalg.svd(q, full_matrices=False)[2][-1]
        assert abs(n_eq2 @ n_svd) == pytest.approx(1.0, abs=1e-12)
        # the centroid lies on the plane of Eq. 1
        c = pts.mean(axis=0)
        assert c[2] == pytest.approx(b0 + b1 * c[0] + b2 * c[1], abs=1e-9)


def test_eq2_read_literally_with_an_intercept_column_is_not_the_odr_plane():
    rng = np.random.default_rng(12)
    pts = noisy_plane(rng, [0.3, 0.1, 1.0], n_points=500, half_size=0.5, sigma=0.05)
    near = rg.odr_plane_closed_form(pts, centred=False)  # centroid at the origin: agrees
    ok = rg.odr_plane_closed_form(pts, centred=True)
    np.testing.assert_allclose(near[1:], ok[1:], atol=2e-3)
    far = pts + [10.0, 10.0, 0.0]  # same shape, far from the origin: it does not
    lit = rg.odr_plane_closed_form(far, centred=False)
    good = rg.odr_plane_closed_form(far, centred=True)
    np.testing.assert_allclose(good[1:], ok[1:], atol=1e-9)  # centred form is shift-invariant
    assert np.max(np.abs(lit[1:] - good[1:])) > 1e-2


def test_vertical_plane_is_fine_for_odr_but_not_representable_by_eq1():
    rng = np.random.default_rng(13)
    pts = noisy_plane(rng, [0, 1, 0], n_points=20_000, half_size=1.9, sigma=0.003, centre=MID)
    g = rg.grid_roughness(pts, cell_size_m=1.0, min_points=200, ols_axis="z")
    w = g.n_points / g.n_points.sum()
    assert np.sum(w * g.theta_odr) == pytest.approx(0.003 * ABS_FACTOR, rel=0.03)
    # OLS along z of a plane containing the z axis: no information, huge roughness
    assert np.all(g.theta_ols > 20 * g.theta_odr)
    g_y = rg.grid_roughness(pts, cell_size_m=1.0, min_points=200, ols_axis="y")
    np.testing.assert_allclose(g_y.theta_ols, g_y.theta_odr, rtol=0.02)


def test_exactly_singular_ols_design_uses_the_unique_least_squares_residuals():
    rng = np.random.default_rng(17)
    # exactly x = const: the OLS design [1, x, y] for axis z is rank-deficient
    yz = rng.uniform(0.05, 1.95, (4000, 2))
    pts = np.column_stack([np.full(4000, 0.5), yz[:, 0], yz[:, 1] ** 2])
    pts = with_sentinels(pts, (0.5, 1.0, 1.0), 2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fast = rg.grid_roughness(pts, cell_size_m=1.0, ols_axis="z")
    ref = rg.grid_roughness_reference(pts, cell_size_m=1.0, ols_axis="z")
    np.testing.assert_allclose(fast.theta_ols, ref.theta_ols, rtol=1e-9)
    assert np.all(fast.theta_ols > 0.01) and np.all(fast.theta_odr < 1e-9)


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("cell", [0.0, -1.0, float("nan"), float("inf"), "a"])
def test_bad_cell_size(cell):
    pts = np.random.default_rng(0).random((100, 3))
    with pytest.raises(InvalidParameterError, match="cell_size_m"):
        rg.grid_roughness(pts, cell_size_m=cell)


def test_cell_larger_than_extent():
    pts = np.random.default_rng(0).random((100, 3))
    with pytest.raises(InvalidParameterError, match="larger than the extent"):
        rg.grid_roughness(pts, cell_size_m=5.0)
    with pytest.raises(InvalidParameterError, match="larger than the extent"):
        rg.grid_roughness_multi(pts, cell_sizes_m=[0.5, 5.0])


def test_empty_and_malformed_input():
    with pytest.raises(InputDataError, match="empty"):
        rg.grid_roughness(np.zeros((0, 3)), cell_size_m=1.0)
    with pytest.raises(InputDataError, match=r"\(N, 3\)"):
        rg.grid_roughness(np.zeros((10, 2)), cell_size_m=1.0)
    pts = np.random.default_rng(0).random((100, 3))
    pts[5, 1] = np.nan
    with pytest.raises(InputDataError, match="NaN"):
        rg.grid_roughness(pts, cell_size_m=0.5)
    pts[5, 1] = np.inf
    with pytest.raises(InputDataError, match="NaN or infinite"):
        rg.grid_roughness(pts, cell_size_m=0.5)


def test_bad_options():
    pts = np.random.default_rng(0).random((100, 3))
    with pytest.raises(InvalidParameterError, match="min_points"):
        rg.grid_roughness(pts, cell_size_m=0.5, min_points=2)
    with pytest.raises(InvalidParameterError, match="ols_axis"):
        rg.grid_roughness(pts, cell_size_m=0.5, ols_axis="w")
    with pytest.raises(InvalidParameterError, match="origin_m"):
        rg.grid_roughness(pts, cell_size_m=0.5, origin_m=[0.5, 0.5, 0.5])
    with pytest.raises(InvalidParameterError, match="cutoff"):
        rg.binary_transform(np.zeros(3), cutoff=1.5)


def test_cells_with_too_few_points_are_skipped_and_counted():
    rng = np.random.default_rng(1)
    dense = noisy_plane(rng, [0, 0, 1], n_points=4000, half_size=0.45, sigma=0.01) + 0.5
    sparse = rng.uniform(0, 1, (7, 3)) * 0.9 + [3.05, 3.05, 3.05]  # 7 points, one cell
    few = rng.uniform(0, 1, (4, 3)) * 0.9 + [1.05, 3.05, 0.05]  # 4 points, another cell
    pts = np.vstack([dense, sparse, few])
    g = rg.grid_roughness(pts, cell_size_m=1.0, min_points=10, origin_m=[0, 0, 0])
    assert len(g) == 1
    assert g.n_cells_skipped == 2 and g.n_points_skipped == 11
    assert g.n_points.sum() + g.n_points_skipped == g.n_points_total == pts.shape[0]
    s = rg.summarize_roughness(g)
    assert s.n_cells == 1 and s.n_cells_skipped == 2
    per_point = rg.roughness_per_point(pts, g)
    assert np.all(np.isfinite(per_point[:4000])) and np.all(np.isnan(per_point[4000:]))


def test_degenerate_cells_are_flagged_not_nan_crashing():
    rng = np.random.default_rng(2)
    good = noisy_plane(rng, [0, 0, 1], n_points=500, half_size=0.45, sigma=0.01) + 0.5
    t = rng.uniform(0, 1, 50)
    line = np.column_stack([1.1 + 0.8 * t, 0.2 + 0.5 * t, 0.3 + 0.1 * t])  # collinear
    same = np.tile([[2.5, 0.5, 0.5]], (30, 1))  # 30 coincident points
    pts = np.vstack([good, line, same])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        g = rg.grid_roughness(pts, cell_size_m=1.0, origin_m=[0, 0, 0])
        ref = rg.grid_roughness_reference(pts, cell_size_m=1.0, origin_m=[0, 0, 0])
        s = rg.summarize_roughness(g)
    assert len(g) == 3
    np.testing.assert_array_equal(g.degenerate, [False, True, True])
    np.testing.assert_array_equal(ref.degenerate, g.degenerate)
    assert np.all(np.isnan(g.theta_odr[1:])) and np.all(np.isnan(g.e_ols[1:]))
    assert np.all(np.isfinite(g.normal))
    assert s.n_degenerate == 2 and s.odr.n == 1 and math.isfinite(s.odr.mean)
    assert s.to_dict()["odr"]["n"] == 1


def test_inputs_are_not_modified_and_float32_is_accepted():
    rng = np.random.default_rng(4)
    pts = bumpy_surface(rng, n_points=3000)
    before = pts.copy()
    g64 = rg.grid_roughness(pts, cell_size_m=0.5)
    np.testing.assert_array_equal(pts, before)
    g32 = rg.grid_roughness(pts.astype(np.float32), cell_size_m=0.5)
    assert len(g32) > 0 and np.isfinite(g32.theta_odr).all()
    assert len(g64) > 0


def test_multi_equals_single_sizes_and_progress_and_cancel():
    rng = np.random.default_rng(5)
    pts = bumpy_surface(rng, n_points=5000)
    seen = []
    grids = rg.grid_roughness_multi(
        pts, cell_sizes_m=[1.0, 0.5], progress=lambda f, m="": seen.append(f)
    )
    for g, c in zip(grids, (1.0, 0.5)):
        _assert_same_grid(g, rg.grid_roughness(pts, cell_size_m=c), rtol=1e-12)
    assert seen and seen[-1] == pytest.approx(1.0) and all(0 <= f <= 1 for f in seen)
    assert all(b >= a - 1e-12 for a, b in zip(seen, seen[1:]))

    def cancel(fraction, message=""):
        if fraction > 0.2:
            raise CancelledError("stop")

    with pytest.raises(CancelledError):
        rg.grid_roughness(pts, cell_size_m=0.5, progress=cancel)


def test_auto_ols_axis_is_the_exposure_normal_axis():
    rng = np.random.default_rng(6)
    wall = noisy_plane(rng, [0.05, 1.0, 0.0], n_points=5000, half_size=2.0, sigma=0.01)
    frame = rg.principal_frame(wall)
    assert rg.resolve_ols_axis(frame, "auto") == "y"
    assert rg.resolve_ols_axis(frame, "z") == "z"
    g = rg.grid_roughness(wall, cell_size_m=1.0, ols_axis="auto")
    assert g.ols_axis == "y"


# --------------------------------------------------------------------------- maps, statistics


def test_normalise_binary_and_histogram():
    v = np.array([1.0, 2.0, np.nan, 3.0, 5.0, 9.0]) / 8.0
    n = rg.normalise_range(v)
    np.testing.assert_allclose(n, [0.0, 0.125, np.nan, 0.25, 0.5, 1.0])
    b = rg.binary_transform(n, cutoff=0.25)
    np.testing.assert_array_equal(b, [0.0, 0.0, np.nan, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(rg.normalise_range(np.full(3, 2.0)), 0.0)
    edges, frac = rg.roughness_histogram(n, bin_width=0.25)
    np.testing.assert_allclose(edges, [0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(frac, [0.4, 0.2, 0.2, 0.2])  # 1.0 counts in the last bin


def test_stats_are_population_and_skip_nan():
    s = rg.roughness_stats(np.array([1.0, 2.0, 3.0, np.nan]))
    assert (s.n, s.minimum, s.maximum, s.mean) == (3, 1.0, 3.0, 2.0)
    assert s.variance == pytest.approx(2.0 / 3.0) and s.std == pytest.approx(math.sqrt(2 / 3))
    assert rg.roughness_stats(np.array([np.nan])).to_dict()["mean"] is None


def test_map_planes():
    rng = np.random.default_rng(14)
    outcrop = noisy_plane(rng, [0.1, 1.0, 0.05], n_points=4000, half_size=3.0, sigma=0.01)
    assert rg.choose_map_plane(rg.principal_frame(outcrop)).name == "xz"
    ground = noisy_plane(rng, [0.1, 0.05, 1.0], n_points=4000, half_size=3.0, sigma=0.01)
    plane = rg.choose_map_plane(rg.principal_frame(ground))
    assert plane.name == "xy" and plane.georeferenced
    slope = noisy_plane(rng, [1.0, 0.0, 1.0], n_points=4000, half_size=3.0, sigma=0.01)
    frame = rg.principal_frame(slope)
    p = rg.choose_map_plane(frame, "auto")
    assert p.name == "principal" and not p.georeferenced
    assert abs(p.normal @ _unit([1, 0, 1])) == pytest.approx(1.0, abs=1e-3)
    uv = p.project(slope)
    assert np.ptp(uv[:, 0]) > 5 and np.ptp(uv[:, 1]) > 5
    assert rg.choose_map_plane(frame, "yz").name == "yz"
    with pytest.raises(InvalidParameterError, match="map plane"):
        rg.choose_map_plane(frame, "ab")


def test_rasterize_cells_xy_places_and_averages_stacked_cells():
    plane = rg.choose_map_plane(rg.principal_frame(np.random.default_rng(0).random((50, 3))), "xy")
    c = 0.5
    # two cells stacked in z at column (ix=1, iy=0), one cell at (ix=0, iy=2)
    centres = np.array([[0.75, 0.25, 0.25], [0.75, 0.25, 0.75], [0.25, 1.25, 0.25]]) + [100, 200, 0]
    vals = np.array([1.0, 3.0, 5.0])
    r = rg.rasterize_cells(centres, vals, plane, pixel_size_m=c)
    assert r.values.shape == (1, 3, 2)
    assert r.origin_uv_m == (100.0, 201.5)
    expected = np.array([[5.0, np.nan], [np.nan, np.nan], [np.nan, 2.0]])
    np.testing.assert_array_equal(r.values[0], expected)
    np.testing.assert_array_equal(r.count, [[1, 0], [0, 0], [0, 2]])
    assert r.extent == (100.0, 101.0, 200.0, 201.5)


def _brute_semivariogram(z, px, edges):
    rows, cols = np.nonzero(np.isfinite(z))
    vals = z[rows, cols]
    k = edges.size - 1
    num, cnt = np.zeros(k), np.zeros(k, dtype=np.int64)
    for i in range(vals.size):
        h = np.hypot(rows[i + 1 :] - rows[i], cols[i + 1 :] - cols[i]) * px
        d2 = (vals[i + 1 :] - vals[i]) ** 2
        ok = (h > 0) & (h <= edges[-1])
        cls = np.clip(np.searchsorted(edges, h[ok], side="left") - 1, 0, k - 1)
        np.add.at(num, cls, d2[ok])
        np.add.at(cnt, cls, 1)
    with np.errstate(invalid="ignore"):
        return cnt, num / (2 * cnt)


def test_semivariogram_fft_equals_brute_force_pairs():
    rng = np.random.default_rng(15)
    z = rng.normal(size=(17, 23)).cumsum(axis=1) * 0.01 + 0.5
    z[rng.random(z.shape) < 0.3] = np.nan
    sv = rg.semivariogram_raster(z, pixel_size_m=0.25, max_lag_m=3.0, n_lags=12)
    cnt, gamma = _brute_semivariogram(z, 0.25, sv.lag_edges_m)
    np.testing.assert_array_equal(sv.n_pairs, cnt)
    np.testing.assert_allclose(sv.gamma, gamma, rtol=1e-9)
    assert sv.variance == pytest.approx(np.nanvar(z))


def test_semivariogram_of_white_noise_is_flat_at_one_and_of_a_trend_grows():
    rng = np.random.default_rng(16)
    noise = rng.normal(size=(80, 80))
    sv = rg.semivariogram_raster(noise, pixel_size_m=1.0)
    np.testing.assert_allclose(sv.normalised, 1.0, atol=0.05)
    trend = np.add.outer(np.zeros(40), np.arange(60.0))
    sv = rg.semivariogram_raster(trend, pixel_size_m=1.0)
    assert np.all(np.diff(sv.gamma) > 0)
    empty = rg.semivariogram_raster(np.full((5, 5), np.nan), pixel_size_m=1.0)
    assert np.all(np.isnan(empty.gamma)) and np.all(empty.n_pairs == 0)
