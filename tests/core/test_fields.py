"""Tests of gridded displacement fields (slipmap.core.fields)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import chi2

from slipmap.core.errors import InputDataError, InvalidParameterError
from slipmap.core.fields import (
    FieldComparison,
    GriddedField,
    _neighbour_variance_factor_reference,
    compare_with_control,
    compare_with_truth,
    field_from_columns,
    neighbour_variance_factor,
    sample_field,
)

UTM = (515369.0, 4918340.0)


def _linear(xy, a=(0.01, -0.02, 0.3), b=(0.005, 0.015, -0.2), c=(0.002, 0.001, 0.05)):
    """(M, 3) displacement linear in x, y (relative to UTM): exact under bilinear sampling."""
    x = xy[:, 0] - UTM[0]
    y = xy[:, 1] - UTM[1]
    return np.column_stack([a[k] * x + b[k] * y + c[k] for k in range(3)])


def _grid(n_rows=6, n_cols=8, spacing=(2.0, 1.5), origin=(UTM[0] - 3.0, UTM[1] + 20.0), fn=_linear):
    sx, sy = spacing
    xc = origin[0] + (np.arange(n_cols) + 0.5) * sx
    yc = origin[1] - (np.arange(n_rows) + 0.5) * sy
    X, Y = np.meshgrid(xc, yc)
    d = fn(np.column_stack([X.ravel(), Y.ravel()])).reshape(n_rows, n_cols, 3)
    return GriddedField(origin, spacing, d[..., 0], d[..., 1], d[..., 2])


# --- GriddedField ------------------------------------------------------------------------


def test_cell_centres_follow_the_geotiff_convention():
    f = GriddedField((100.0, 200.0), (2.0, 3.0), np.zeros((2, 3)), np.zeros((2, 3)))
    assert f.shape == (2, 3)
    np.testing.assert_array_equal(f.x[0], [101.0, 103.0, 105.0])
    np.testing.assert_array_equal(f.y[:, 0], [198.5, 195.5])  # row 0 = north
    assert f.dz is None


def test_gridded_field_copies_and_freezes_inputs():
    dx = np.zeros((2, 2))
    f = GriddedField((0.0, 0.0), (1.0, 1.0), dx, dx)
    dx[0, 0] = 5.0
    assert f.dx[0, 0] == 0.0
    with pytest.raises(ValueError):
        f.dx[0, 0] = 1.0


@pytest.mark.parametrize("spacing", [(0.0, 1.0), (1.0, -1.0), (math.nan, 1.0)])
def test_gridded_field_rejects_bad_spacing(spacing):
    with pytest.raises(InvalidParameterError, match="spacing_m"):
        GriddedField((0.0, 0.0), spacing, np.zeros((2, 2)), np.zeros((2, 2)))


def test_gridded_field_rejects_mismatched_shapes():
    with pytest.raises(InputDataError, match="dy"):
        GriddedField((0.0, 0.0), (1.0, 1.0), np.zeros((2, 2)), np.zeros((2, 3)))


# --- field_from_columns -------------------------------------------------------------------


def test_round_trip_with_missing_rows_shuffled_order():
    f = _grid()
    cols = f.to_columns(valid_only=False)
    rng = np.random.default_rng(3)
    keep = rng.random(cols["x"].size) > 0.3
    # keep the four corners so the bounding box (and thus the grid) is the same
    n_rows, n_cols = f.shape
    for r, c in [(0, 0), (0, n_cols - 1), (n_rows - 1, 0), (n_rows - 1, n_cols - 1)]:
        keep[r * n_cols + c] = True
    order = rng.permutation(np.flatnonzero(keep))
    g = field_from_columns(
        cols["x"][order], cols["y"][order], cols["dx"][order], cols["dy"][order], cols["dz"][order]
    )
    assert g.shape == f.shape
    np.testing.assert_allclose(g.spacing_m, f.spacing_m, rtol=1e-12)
    np.testing.assert_allclose(g.origin_xy, f.origin_xy, rtol=0, atol=1e-8)
    kept = keep.reshape(f.shape)
    np.testing.assert_array_equal(g.valid, kept)
    np.testing.assert_array_equal(g.dx[kept], f.dx[kept])
    np.testing.assert_array_equal(g.dz[kept], f.dz[kept])
    assert np.all(np.isnan(g.dx[~kept]))


def test_whole_missing_columns_do_not_fool_spacing_inference():
    f = _grid(n_rows=4, n_cols=7, spacing=(0.5, 0.5))
    cols = f.to_columns()
    c_index = np.tile(np.arange(7), 4)
    keep = ~np.isin(c_index, [1, 2, 4])  # columns 0, 3, 5, 6 remain: gaps of 3, 2, 1 cells
    g = field_from_columns(*(cols[k][keep] for k in ("x", "y", "dx", "dy")))
    assert g.shape == (4, 7)
    assert g.spacing_m == pytest.approx((0.5, 0.5), rel=1e-12)
    assert g.dz is None


def test_rounded_csv_coordinates_are_accepted():
    f = _grid(spacing=(0.25, 0.25), origin=(UTM[0] + 0.0004, UTM[1] + 0.0007))
    cols = f.to_columns()
    g = field_from_columns(np.round(cols["x"], 3), np.round(cols["y"], 3), cols["dx"], cols["dy"])
    assert g.shape == f.shape
    assert g.spacing_m == pytest.approx((0.25, 0.25), abs=1e-4)


def test_single_column_takes_the_other_axis_spacing():
    x = np.full(4, 10.5)
    y = np.array([3.5, 2.5, 1.5, 0.5])
    g = field_from_columns(x, y, np.ones(4), np.ones(4))
    assert g.shape == (4, 1)
    assert g.spacing_m == (1.0, 1.0)
    assert g.origin_xy == pytest.approx((10.0, 4.0))


def test_given_spacing_is_used_and_checked():
    x = np.array([0.5, 1.5, 3.5])
    y = np.zeros(3)
    g = field_from_columns(x, y, np.ones(3), np.ones(3), spacing_m=1.0)
    assert g.shape == (1, 4)
    with pytest.raises(InputDataError, match="x coordinates are not on a regular lattice"):
        field_from_columns(x, y, np.ones(3), np.ones(3), spacing_m=0.8)


def test_off_lattice_points_are_named():
    x = np.array([0.0, 1.0, 2.0, 2.3, 4.0])
    with pytest.raises(InputDataError, match="not on a regular lattice"):
        field_from_columns(x, np.zeros(5), np.ones(5), np.ones(5))
    y = np.array([0.0, 1.0, 2.37, 3.0])
    with pytest.raises(InputDataError, match="y coordinates"):
        field_from_columns(np.zeros(4), y, np.ones(4), np.ones(4))


def test_duplicate_cells_and_bad_columns_are_refused():
    with pytest.raises(InputDataError, match="already used grid cell"):
        field_from_columns([0.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1, 2, 3], [1, 2, 3])
    with pytest.raises(InputDataError, match="dy has 2 values"):
        field_from_columns([0.0, 1.0, 2.0], [0.0, 0.0, 0.0], [1, 2, 3], [1, 2])
    with pytest.raises(InputDataError, match="non-finite x or y"):
        field_from_columns([0.0, np.nan], [0.0, 0.0], [1, 2], [1, 2])
    with pytest.raises(InputDataError, match="empty"):
        field_from_columns([], [], [], [])
    with pytest.raises(InputDataError, match="spacing_m"):
        field_from_columns([5.0], [5.0], [1.0], [1.0])
    with pytest.raises(InvalidParameterError, match="spacing_m"):
        field_from_columns([0.0, 1.0], [0.0, 0.0], [1, 2], [1, 2], spacing_m=-1.0)
    with pytest.raises(InputDataError, match="stray coordinates"):
        field_from_columns([0.0, 1.0, 1e6], [0.0, 1.0, 1e6], [1, 2, 3], [1, 2, 3])


def test_valid_mask_blanks_rows_but_keeps_their_cells():
    g = field_from_columns(
        [0.5, 1.5, 2.5], [0.5, 0.5, 0.5], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0], valid=[1, 1, 0]
    )
    assert g.shape == (1, 3)
    np.testing.assert_array_equal(g.valid, [[True, True, False]])


@given(
    st.floats(-1e3, 1e3),
    st.floats(-1e3, 1e3),
    st.sampled_from([0.1, 0.25, 1.0, 5.0]),
    st.integers(0, 2**31 - 1),
)
def test_translation_of_coordinates_translates_origin(tx, ty, spacing, seed):
    """Property: shifting the centres shifts the origin, nothing else."""
    f = _grid(n_rows=5, n_cols=6, spacing=(spacing, spacing))
    cols = f.to_columns()
    rng = np.random.default_rng(seed)
    order = rng.permutation(cols["x"].size)
    a = field_from_columns(*(cols[k][order] for k in ("x", "y", "dx", "dy")))
    b = field_from_columns(
        cols["x"][order] + tx, cols["y"][order] + ty, cols["dx"][order], cols["dy"][order]
    )
    assert b.shape == a.shape
    np.testing.assert_allclose(b.spacing_m, a.spacing_m, rtol=1e-9)
    np.testing.assert_allclose(np.subtract(b.origin_xy, a.origin_xy), [tx, ty], atol=1e-6)
    np.testing.assert_array_equal(b.dx, a.dx)


# --- sample_field -----------------------------------------------------------------------


def test_bilinear_is_exact_for_linear_fields_and_hits_centres():
    f = _grid()
    rng = np.random.default_rng(0)
    x0, y0 = f.x[0, 0], f.y[-1, 0]
    x1, y1 = f.x[0, -1], f.y[0, 0]
    xy = np.column_stack([rng.uniform(x0, x1, 200), rng.uniform(y0, y1, 200)])
    np.testing.assert_allclose(sample_field(f, xy), _linear(xy), rtol=0, atol=1e-10)
    centres = np.column_stack([f.x.ravel(), f.y.ravel()])
    got = sample_field(f, centres)
    np.testing.assert_allclose(got[:, 0], f.dx.ravel(), atol=1e-12)
    np.testing.assert_allclose(got[:, 2], f.dz.ravel(), atol=1e-12)


def test_bilinear_edges_gaps_and_outside():
    f = _grid(n_rows=3, n_cols=3, spacing=(1.0, 1.0), origin=(0.0, 3.0))
    dx = f.dx.copy()
    dx[1, 1] = np.nan
    g = dataclasses.replace(f, dx=dx)
    pts = np.array(
        [
            [0.5, 2.5],  # a centre next to the gap: gap has weight 0 -> value
            [1.0, 2.0],  # between four centres incl. the gap -> NaN
            [0.2, 2.9],  # outer half cell: clamped to the corner value
            [-0.1, 1.0],  # outside the grid
            [3.2, 1.0],
        ]
    )
    got = sample_field(g, pts)
    assert got[0, 0] == pytest.approx(f.dx[0, 0])
    assert math.isnan(got[1, 0]) and not math.isnan(got[1, 1])  # dy has no gap
    assert got[2, 0] == pytest.approx(f.dx[0, 0])
    assert np.all(np.isnan(got[3:])), got[3:]


def test_nearest_valid():
    f = _grid(n_rows=3, n_cols=3, spacing=(1.0, 1.0), origin=(0.0, 3.0))
    dx = f.dx.copy()
    dx[0, 0] = np.nan
    g = dataclasses.replace(f, dx=dx)
    got = sample_field(g, [[0.4, 2.6], [10.0, 10.0]], method="nearest_valid")
    assert got[0, 0] in (f.dx[0, 1], f.dx[1, 0])
    assert got[1, 0] == pytest.approx(f.dx[2, 2])
    got = sample_field(g, [[10.0, 10.0]], method="nearest_valid", max_distance_m=1.0)
    assert np.all(np.isnan(got))
    with pytest.raises(InvalidParameterError, match="method"):
        sample_field(g, [[0.0, 0.0]], method="cubic")


def test_sample_without_dz_gives_nan_dz():
    f = _grid()
    g = GriddedField(f.origin_xy, f.spacing_m, f.dx, f.dy)
    assert np.all(np.isnan(sample_field(g, [[f.x[1, 1], f.y[1, 1]]])[:, 2]))


# --- comparisons ---------------------------------------------------------------------------


def test_compare_with_control_known_errors():
    f = _grid()
    cols = f.to_columns()
    rng = np.random.default_rng(1)
    ctrl = np.column_stack(
        [rng.uniform(f.x[0, 0], f.x[0, -1], 50), rng.uniform(f.y[-1, 0], f.y[0, 0], 50)]
    )
    truth = _linear(ctrl)
    offset = np.array([0.03, -0.04, 0.02])
    res = compare_with_control(
        cols["x"], cols["y"], cols["dx"], cols["dy"], cols["dz"], ctrl, truth - offset
    )
    assert isinstance(res, FieldComparison)
    assert res.n_compared == 50 and res.n_missing == 0 and res.valid_fraction == 1.0
    assert res.rmse_horizontal_m == pytest.approx(0.05, abs=1e-9)
    assert res.rmse_dx_m == pytest.approx(0.03, abs=1e-9)
    assert res.bias_dy_m == pytest.approx(-0.04, abs=1e-9)
    assert res.bias_dz_m == pytest.approx(0.02, abs=1e-9)
    assert res.max_abs_horizontal_m == pytest.approx(0.05, abs=1e-9)
    d = res.to_dict()
    assert d["n_compared"] == 50 and set(d) >= {"rmse_dz_m", "valid_fraction"}


def test_compare_with_control_counts_missing_and_outside():
    f = _grid(n_rows=3, n_cols=3, spacing=(1.0, 1.0), origin=(0.0, 3.0))
    ctrl = np.array([[1.5, 1.5], [100.0, 100.0]])
    ref = np.array([[f.dx[1, 1], f.dy[1, 1], np.nan], [0.0, 0.0, 0.0]])
    res = compare_with_control(None, None, None, None, None, ctrl, ref, field=f)
    assert res.n_compared == 1 and res.n_missing == 1 and res.valid_fraction == 0.5
    assert res.rmse_horizontal_m == pytest.approx(0.0, abs=1e-12)
    assert res.n_compared_dz == 0 and math.isnan(res.rmse_dz_m)


def test_compare_with_truth_exact_and_masked():
    rng = np.random.default_rng(2)
    xy = np.column_stack([rng.uniform(0, 10, 30) + UTM[0], rng.uniform(0, 10, 30) + UTM[1]])
    est = _linear(xy)
    res = compare_with_truth(xy, est, _linear)
    assert res.n_compared == 30 and res.rmse_horizontal_m == 0.0 and res.rmse_dz_m == 0.0
    est[:5] = np.nan
    est[5:, 1] += 0.1
    res = compare_with_truth(xy, est, _linear)
    assert res.n_missing == 5 and res.n_compared == 25
    assert res.rmse_dy_m == pytest.approx(0.1) and res.bias_dy_m == pytest.approx(0.1)
    mask = np.zeros(30, dtype=bool)
    mask[5:10] = True
    res = compare_with_truth(xy, est, _linear, mask=mask)
    assert res.n_compared == 5 and res.n_missing == 0
    with pytest.raises(InputDataError, match="mask"):
        compare_with_truth(xy, est, _linear, mask=mask[:3])
    with pytest.raises(InputDataError, match="est_d"):
        compare_with_truth(xy, est[:3], _linear)


def test_jittered_centres_need_the_spacing_and_a_tolerance():
    """Centres off the lattice by ~2 cm (e.g. window centroids) cannot infer the spacing."""
    rng = np.random.default_rng(0)
    X, Y = np.meshgrid(np.arange(10) + UTM[0] + 0.5, np.arange(8) + UTM[1] + 0.5)
    x = X.ravel() + rng.uniform(-0.02, 0.02, 80)
    y = Y.ravel() + rng.uniform(-0.02, 0.02, 80)
    with pytest.raises(InputDataError, match="not on a regular lattice"):
        field_from_columns(x, y, np.zeros(80), np.zeros(80))
    g = field_from_columns(x, y, np.zeros(80), np.zeros(80), spacing_m=1.0, lattice_tolerance=0.1)
    assert g.shape == (8, 10) and np.all(g.valid)


# --------------------------------------------------------------------------- variance factor


def _noisy_plane_field(seed, true_factor, *, shape=(30, 40), keep=0.85):
    """A planar 3-component field on a grid with gaps; per-cell formal sigmas vary 4x and the
    actual noise is ``true_factor`` times them."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    sel = rng.random(rr.size) < keep
    row, col = rr.ravel()[sel], cc.ravel()[sel]
    sig = rng.uniform(0.001, 0.004, (row.size, 3))
    trend = np.column_stack([0.02 * col - 0.01 * row, 0.5 + 0.003 * row, -0.2 + 0 * row])
    values = trend + true_factor * sig * rng.standard_normal((row.size, 3))
    return row, col, values, sig


@pytest.mark.parametrize("true_factor", [1.0, 3.0])
def test_variance_factor_recovers_the_known_noise_scale(true_factor):
    est = [
        neighbour_variance_factor(*_noisy_plane_field(seed, true_factor)).factor
        for seed in range(5)
    ]
    # ~1000 cells x 3 components each: the median estimator is within a few per cent
    np.testing.assert_allclose(est, true_factor, rtol=0.1)


def test_variance_factor_fast_equals_loop_reference():
    row, col, values, sig = _noisy_plane_field(7, 2.0, shape=(12, 15), keep=0.75)
    usable = np.random.default_rng(1).random(row.size) < 0.9
    for mn in (3, 5, 7):
        kw = dict(usable=usable, min_neighbours=mn, min_cells=1)
        fast = neighbour_variance_factor(row, col, values, sig, **kw)
        ref = _neighbour_variance_factor_reference(row, col, values, sig, **kw)
        assert fast.n_cells == ref.n_cells > 0
        assert fast.factor == pytest.approx(ref.factor, rel=1e-12)
        np.testing.assert_allclose(fast.normalised, ref.normalised, rtol=1e-10)
        np.testing.assert_allclose(fast.variance, ref.variance, rtol=1e-10)
        assert np.isfinite(fast.normalised).all(axis=1).sum() == fast.n_cells


@pytest.mark.parametrize("surface", ["plane", "quadratic"])
def test_variance_factor_fast_equals_loop_reference_per_surface(surface):
    row, col, values, sig = _noisy_plane_field(8, 1.5, shape=(12, 15), keep=0.7)
    usable = np.random.default_rng(3).random(row.size) < 0.9
    sep = np.random.default_rng(4).random((row.size, 8)) < 0.1
    for mn in (3, 5, 8):
        kw = dict(usable=usable, min_neighbours=mn, min_cells=1, separated=sep, surface=surface)
        fast = neighbour_variance_factor(row, col, values, sig, **kw)
        ref = _neighbour_variance_factor_reference(row, col, values, sig, **kw)
        assert fast.n_cells == ref.n_cells > 0
        np.testing.assert_allclose(fast.normalised, ref.normalised, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fast.variance, ref.variance, rtol=1e-9)


def test_a_curved_field_is_no_error_to_the_quadratic_neighbour_test():
    """A smooth undulating field whose curvature over 3 x 3 cells is several times the
    cells' noise: the plane through the neighbours calls it error (factor well over 1), the
    quadratic does not (the known noise scale back within 5 % on the interior cells); with
    every neighbour the
    quadratic predicts by edges 1/2 and corners -1/4."""
    plane, quad = [], []
    for seed in range(4):
        row, col, values, sig = _noisy_plane_field(seed, 1.0, keep=1.0)  # no gaps
        # undulations of 5 m over 10 cells: second differences of up to 5 cm per cell, fourth
        # differences (what a quadratic misses) of up to 0.5 mm
        wave = 5.0 * np.cos(col / 10.0) * np.cos(row / 10.0)
        curved = values + np.column_stack([wave, -0.5 * wave, 0.2 * wave])
        plane.append(neighbour_variance_factor(row, col, curved, sig, surface="plane").factor)
        est = neighbour_variance_factor(row, col, curved, sig, surface="quadratic")
        # the grid's border cells have 5 neighbours, too few for a quadratic: they keep the
        # plane (measured: the whole grid's factor 1.10-1.13)
        inner = (row > 0) & (row < row.max()) & (col > 0) & (col < col.max())
        z2 = est.normalised[inner] ** 2
        quad.append((est.factor, math.sqrt(np.median(z2) / chi2.ppf(0.5, 1))))
    assert min(plane) > 2.0, (plane, quad)
    np.testing.assert_allclose([q[1] for q in quad], 1.0, rtol=0.05)
    assert max(q[0] for q in quad) < 1.2
    # the weights with all 8 neighbours: one cell on a field that is a known quadratic
    rr, cc = np.mgrid[0:3, 0:3]
    row, col = rr.ravel(), cc.ravel()
    q = lambda r, c: 1.0 + 2.0 * c - r + 0.5 * c * c + 0.25 * r * c - 0.75 * r * r  # noqa: E731
    vals = np.asarray(q(row - 1.0, col - 1.0), dtype=np.float64)
    vals[4] += 0.01  # the centre off the quadratic by 1 cm
    est = neighbour_variance_factor(
        row, col, vals, np.full(9, 0.01), min_cells=1, surface="quadratic"
    )
    # r = 0.01, var(r) = 0.01² (1 + 4 (1/2)² + 4 (1/4)²) = 2.25 x 0.01²
    assert est.normalised[4, 0] == pytest.approx(1.0 / 1.5, rel=1e-9)


def _correlated_field(seed, *, shape=(24, 30), length_cells=1.5, sigma=0.002):
    """A 3-component field of correlated Gaussian errors (squared-exponential covariance,
    ``length_cells`` grid cells) on a plane; the pairs within 2 cells and their covariances."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    row, col = rr.ravel(), cc.ravel()
    d2 = (row[:, None] - row[None]) ** 2 + (col[:, None] - col[None]) ** 2
    C = sigma**2 * np.exp(-0.5 * d2 / length_cells**2)
    L = np.linalg.cholesky(C + 1e-12 * sigma**2 * np.eye(row.size))
    values = (L @ rng.standard_normal((row.size, 3))) + np.column_stack(
        [0.01 * col, 0 * row, 0.1 + 0 * row]
    )
    near = (np.abs(row[:, None] - row[None]) <= 2) & (np.abs(col[:, None] - col[None]) <= 2)
    i, j = np.nonzero(np.triu(near, 1))
    pairs = np.column_stack([i, j])
    cov = np.repeat(C[i, j][:, None], 3, axis=1)
    return row, col, values, np.full((row.size, 3), sigma), (pairs, cov)


def test_variance_factor_of_a_correlated_field_needs_its_pair_covariances():
    """Honest sigmas of a field whose errors are correlated between neighbours: with the
    pair covariances the factor is 1; without them neighbour agreement looks too good."""
    with_cov, without = [], []
    for seed in range(4):
        row, col, values, sig, pc = _correlated_field(seed)
        with_cov.append(neighbour_variance_factor(row, col, values, sig, pair_covariance=pc).factor)
        without.append(neighbour_variance_factor(row, col, values, sig).factor)
    np.testing.assert_allclose(np.mean(with_cov), 1.0, rtol=0.1)
    assert np.mean(without) < 0.5


def test_variance_factor_with_pair_covariances_fast_equals_loop_reference():
    row, col, values, sig, pc = _correlated_field(3, shape=(9, 11))
    usable = np.random.default_rng(2).random(row.size) < 0.85
    kw = dict(usable=usable, min_neighbours=5, min_cells=1, pair_covariance=pc)
    fast = neighbour_variance_factor(row, col, values, sig, **kw)
    ref = _neighbour_variance_factor_reference(row, col, values, sig, **kw)
    assert fast.n_cells == ref.n_cells > 0
    np.testing.assert_allclose(fast.normalised, ref.normalised, rtol=1e-9)
    np.testing.assert_allclose(fast.variance, ref.variance, rtol=1e-9)


@given(
    a=st.floats(-5, 5),
    b=st.floats(-1, 1),
    c=st.floats(-1, 1),
    shift_r=st.integers(-1000, 1000),
    shift_c=st.integers(-1000, 1000),
)
def test_variance_factor_ignores_a_planar_trend_and_the_grid_origin(a, b, c, shift_r, shift_c):
    row, col, values, sig = _noisy_plane_field(3, 2.0, shape=(10, 12))
    base = neighbour_variance_factor(row, col, values, sig).factor
    moved = values + (a + b * col + c * row)[:, None]
    got = neighbour_variance_factor(row + shift_r, col + shift_c, moved, sig).factor
    assert got == pytest.approx(base, rel=1e-6)


def test_variance_factor_too_few_cells_and_bad_arguments():
    row, col, values, sig = _noisy_plane_field(0, 1.0, shape=(3, 3), keep=1.0)
    one = neighbour_variance_factor(row, col, values, sig)
    assert math.isnan(one.factor) and one.n_cells == 5  # the centre and the 4 edge middles
    sig_inf = sig.copy()
    sig_inf[4] = np.inf  # an undetermined cell never enters: the edges keep 4 neighbours
    assert neighbour_variance_factor(row, col, values, sig_inf, min_cells=1).n_cells == 0
    with pytest.raises(InvalidParameterError, match="min_neighbours"):
        neighbour_variance_factor(row, col, values, sig, min_neighbours=2)
    with pytest.raises(InvalidParameterError, match="sigmas"):
        neighbour_variance_factor(row, col, values, sig[:, :2])
    with pytest.raises(InvalidParameterError, match="at most once"):
        neighbour_variance_factor(
            np.r_[row, 0], np.r_[col, 0], np.r_[values, values[:1]], np.r_[sig, sig[:1]]
        )
    empty = neighbour_variance_factor([], [], np.zeros((0, 3)), np.zeros((0, 3)))
    assert math.isnan(empty.factor) and empty.n_cells == 0


def _step_field(seed, shape=(14, 16), step=0.1):
    """A noisy plane (honest sigmas of 1-4 mm) with a step of ``step`` m in every component
    between columns 7 and 8, and the (K, 8) mask of the neighbours across it."""
    from slipmap.core.fields import _OFFSETS

    row, col, values, sig = _noisy_plane_field(seed, 1.0, shape=shape, keep=1.0)
    right = col >= 8
    values = values + step * right[:, None]
    off = np.asarray(_OFFSETS)
    separated = (col[:, None] + off[None, :, 1] >= 8) != right[:, None]
    return row, col, values, sig, separated


def test_neighbours_across_a_discontinuity_left_out_of_the_prediction():
    """A field with a 10 cm step (25-100 of its sigmas): cells beside it fail the test;
    with the neighbours across the step left out they agree as the others do."""
    for seed in range(3):
        row, col, values, sig, sep = _step_field(seed)
        plain = neighbour_variance_factor(row, col, values, sig)
        kept = neighbour_variance_factor(row, col, values, sig, separated=sep)
        beside = (col == 7) | (col == 8)
        z_plain = np.abs(plain.normalised[beside])
        z_kept = np.abs(kept.normalised[beside])
        assert np.nanmin(z_plain) > 5.0
        assert np.nanmax(z_kept) < 5.0
        assert kept.factor == pytest.approx(1.0, rel=0.25)
        # the cells beside the step keep their five neighbours on their own side
        assert np.isfinite(kept.normalised[beside & (row > 0) & (row < 13)]).all()


def test_separated_neighbours_fast_equals_loop_reference():
    row, col, values, sig, sep = _step_field(4, shape=(9, 11))
    usable = np.random.default_rng(3).random(row.size) < 0.9
    kw = dict(usable=usable, min_neighbours=3, min_cells=1, separated=sep)
    fast = neighbour_variance_factor(row, col, values, sig, **kw)
    ref = _neighbour_variance_factor_reference(row, col, values, sig, **kw)
    assert fast.n_cells == ref.n_cells > 0
    np.testing.assert_allclose(fast.normalised, ref.normalised, rtol=1e-10)
    np.testing.assert_allclose(fast.variance, ref.variance, rtol=1e-10)
