"""Variance factors per region of cells (core/icp_sigma.py, windowed ICP's
``sigma_scaling="region"``) on synthetic gridded fields with known noise levels."""

from __future__ import annotations

import numpy as np
import pytest
from test_icp import UTM, cloud

from slipmap.core.errors import InvalidParameterError
from slipmap.core.icp import windowed_icp
from slipmap.core.icp_sigma import (
    REGION_INFLATION,
    quantile_regions,
    region_variance_factors,
)


def gridded_field(seed, region, true_factor, *, n=30, sigma=0.004):
    """A locally planar field on an n x n grid (3 components), formal sigma ``sigma`` (with a
    spread of 0.5-2x), and errors ``true_factor[region]`` times larger than the formal."""
    rng = np.random.default_rng(seed)
    row, col = np.divmod(np.arange(n * n), n)
    plane = np.column_stack([0.01 * col, -0.02 * row, 0.003 * (row + col)])
    s = sigma * rng.uniform(0.5, 2.0, (n * n, 3))
    err = rng.standard_normal((n * n, 3)) * s * np.asarray(true_factor)[region][:, None]
    return row, col, plane + err, s, err


def halves(n=30):
    return (np.arange(n * n) % n >= n // 2).astype(np.int64)


def checkerboard(n=30):
    row, col = np.divmod(np.arange(n * n), n)
    return ((row + col) % 2).astype(np.int64)


@pytest.mark.parametrize("layout", [halves, checkerboard])
def test_each_region_recovers_its_noise_ratio(layout):
    region = layout()
    row, col, v, s, _ = gridded_field(0, region, [1.0, 3.0])
    est = region_variance_factors(row, col, v, s, region)
    # the checkerboard couples the regions in every neighbourhood: the fixed point untangles it
    np.testing.assert_allclose(est.factors, [1.0, 3.0], rtol=0.12)
    assert est.n_cells.sum() == 30 * 30 - 4  # all but the corners (3 neighbours)
    assert 1.0 < est.field_factor < 3.0
    np.testing.assert_array_equal(est.cell_factor, est.factors[region])


def test_coverage_is_calibrated_in_each_region_over_seeds():
    region = checkerboard()
    inside = {0: [], 1: []}
    for seed in range(12):
        row, col, v, s, err = gridded_field(seed, region, [1.0, 3.0])
        f = region_variance_factors(row, col, v, s, region).cell_factor
        z = np.abs(err) / (s * f[:, None])
        for r in (0, 1):
            inside[r].append(z[region == r] < 2)
    for r in (0, 1):
        frac = np.concatenate(inside[r]).mean()
        assert 0.93 < frac < 0.97, (r, frac)


def test_regions_of_a_correlated_field_need_its_pair_covariances():
    """A field whose errors are correlated between neighbouring cells (one spline fitted to
    all cells): errors 1x and 3x the formal sigmas in the two halves. With the formal pair
    covariances (scaled by the regions' factors in the fixed point) each half gets its factor;
    without them neighbour agreement looks too good in both."""
    from test_fields import _correlated_field

    with_cov, without = [], []
    for seed in range(4):
        row, col, v, s, pc = _correlated_field(seed)
        region = (col >= col.max() // 2 + 1).astype(np.int64)
        trend = np.column_stack([0.01 * col, 0 * row, 0.1 + 0 * row])
        v = trend + np.array([1.0, 3.0])[region][:, None] * (v - trend)
        with_cov.append(region_variance_factors(row, col, v, s, region, pair_covariance=pc).factors)
        without.append(region_variance_factors(row, col, v, s, region).factors)
    np.testing.assert_allclose(np.mean(with_cov, axis=0), [1.0, 3.0], rtol=0.12)
    assert np.all(np.mean(without, axis=0) < 0.6 * np.array([1.0, 3.0]))


def test_one_factor_per_field_misses_both_regions():
    # the point of regions: one factor over-covers the quiet region and under-covers the noisy
    region = halves()
    row, col, v, s, err = gridded_field(1, region, [1.0, 3.0])
    one = region_variance_factors(row, col, v, s, np.zeros_like(region)).factors[0]
    z = np.abs(err) / (s * one)
    assert (z[region == 0] < 2).mean() > 0.99 and (z[region == 1] < 2).mean() < 0.85


def test_unusable_cells_do_not_enter_the_estimate():
    region = halves()
    row, col, v, s, _ = gridded_field(2, region, [1.0, 2.0])
    rng = np.random.default_rng(5)
    bad = rng.random(len(row)) < 0.08
    v_bad = v.copy()
    v_bad[bad] += rng.choice([-1, 1], (bad.sum(), 3)) * 0.5  # wrong minima, 0.5 m off
    polluted = region_variance_factors(row, col, v_bad, s, region).factors
    clean = region_variance_factors(row, col, v_bad, s, region, usable=~bad).factors
    np.testing.assert_allclose(clean, [1.0, 2.0], rtol=0.15)
    assert np.all(polluted > 1.2 * clean)  # wrong cells inflate their neighbours' residuals


def test_small_regions_shrink_to_the_field_factor():
    n = 30
    region = np.zeros(n * n, dtype=np.int64)
    region[[n * 10 + 10, n * 20 + 20, n * 15 + 5]] = 1  # three isolated cells
    row, col, v, s, _ = gridded_field(3, region, [2.0, 10.0])
    est = region_variance_factors(row, col, v, s, region, min_cells=8)
    assert est.n_cells[1] == 3
    assert est.factors[1] == pytest.approx(est.field_factor)
    # with enough cells of its own a region moves off the field's factor; shrinkage keeps a
    # region of n cells at weight n / (n + prior_cells)
    est0 = region_variance_factors(row, col, v, s, region, min_cells=1, prior_cells=0.0)
    est10 = region_variance_factors(row, col, v, s, region, min_cells=1, prior_cells=10.0)
    assert est0.factors[1] > 4 * est.field_factor
    assert est.field_factor < est10.factors[1] < est0.factors[1]


def test_inflation_multiplies_and_bad_options():
    region = halves()
    row, col, v, s, _ = gridded_field(4, region, [1.0, 2.0])
    a = region_variance_factors(row, col, v, s, region)
    b = region_variance_factors(row, col, v, s, region, inflation=1.5)
    np.testing.assert_allclose(b.factors, 1.5 * a.factors)
    with pytest.raises(InvalidParameterError, match="inflation"):
        region_variance_factors(row, col, v, s, region, inflation=0.0)
    with pytest.raises(InvalidParameterError, match="prior_cells"):
        region_variance_factors(row, col, v, s, region, prior_cells=-1.0)
    with pytest.raises(InvalidParameterError, match="region"):
        region_variance_factors(row, col, v, s, region[:-1])
    # too few cells: NaN factors, as the field's
    few = region_variance_factors(row[:20], col[:20], v[:20], s[:20], region[:20])
    assert np.all(np.isnan(few.factors)) and np.isnan(few.field_factor)


def test_quantile_regions():
    score = np.array([5.0, 1.0, 3.0, np.nan, 2.0, 4.0, 6.0])
    np.testing.assert_array_equal(
        quantile_regions(score, n_regions=3), [2, 0, 1, -1, 0, 1, 2]
    )  # terciles of 1..6: edges at 8/3 and 13/3
    np.testing.assert_array_equal(quantile_regions(score, n_regions=1), [0, 0, 0, -1, 0, 0, 0])
    # the quantiles come from the usable cells only; every finite cell is classed
    usable = np.array([True, True, True, False, True, False, False])
    np.testing.assert_array_equal(
        quantile_regions(score, n_regions=2, usable=usable), [1, 0, 1, -1, 0, 1, 1]
    )
    with pytest.raises(InvalidParameterError, match="n_regions"):
        quantile_regions(score, n_regions=0)


def test_windowed_icp_region_scaling_by_roughness():
    # 30 x 20 m, 2 m cells: the west half sampled with 2 mm noise, the east half with 8 mm;
    # the noise is independent, so each cell's formal sigma (from its own residuals) is
    # honest and both regions' factors are about 1 (times the calibrated inflation)
    rng = np.random.default_rng(7)

    def epoch():
        quiet = cloud(rng, 0.0, 30.0, 60, 0.002, xy_hi=20.0)
        rough = cloud(rng, 0.0, 30.0, 60, 0.008, xy_hi=20.0)
        return np.vstack([quiet[quiet[:, 0] < 15], rough[rough[:, 0] >= 15]]) + UTM

    shift = np.array([0.03, -0.02, 0.01])
    before, after = epoch(), epoch() + shift
    kw = dict(cell_m=2.0, median_threshold=2.0, sigma_model="independent")  # formal sigmas
    formal = windowed_icp(before, after, sigma_scaling="formal", **kw)
    res = windowed_icp(before, after, sigma_scaling="region", sigma_regions=2, **kw)
    np.testing.assert_array_equal(res.dx, formal.dx)
    east = res.x - UTM[0] > 15
    assert np.mean(res.sigma_region[east] == 1) > 0.9
    assert np.mean(res.sigma_region[~east] == 0) > 0.9
    assert len(res.sigma_region_factors) == 2
    for f in res.sigma_region_factors:
        assert 0.8 * REGION_INFLATION < f < 1.5 * REGION_INFLATION
    np.testing.assert_allclose(res.sigma_dx, formal.sigma_dx * res.sigma_factor_cell)
    np.testing.assert_allclose(res.cov_d, formal.cov_d * res.sigma_factor_cell[:, None, None] ** 2)
    err = np.c_[res.dx, res.dy, res.dz] - shift
    assert np.mean(np.abs(err) < 2 * np.c_[res.sigma_dx, res.sigma_dy, res.sigma_dz]) > 0.9
    with pytest.raises(InvalidParameterError, match="sigma_region_by"):
        windowed_icp(before, after, cell_m=5.0, sigma_scaling="region", sigma_region_by="x")
    with pytest.raises(InvalidParameterError, match="sigma_regions"):
        windowed_icp(before, after, cell_m=5.0, sigma_scaling="region", sigma_regions=0)


def test_spline_field_region_factors_get_the_fields_pair_covariances(monkeypatch):
    """``field_model="spline"`` with ``sigma_scaling="region"``: the region factors are
    estimated with the formal covariances of neighbouring cells (one field: positive between
    adjacent cells), as the field's single factor is."""
    from slipmap.core import icp_sigma

    seen = {}
    real = icp_sigma.region_variance_factors

    def spy(*args, **kw):
        seen.update(kw)
        return real(*args, **kw)

    monkeypatch.setattr(icp_sigma, "region_variance_factors", spy)
    rng = np.random.default_rng(5)
    before = cloud(rng, -3.0, 23.0, 50, 0.003)
    src = before[np.all((before[:, :2] > 0.0) & (before[:, :2] < 20.0), axis=1)]
    after = src + np.array([0.05, -0.03, 0.01]) + rng.normal(0.0, 0.003, src.shape)
    res = windowed_icp(
        before + UTM, after + UTM, cell_m=5.0, field_model="spline", sigma_scaling="region",
        sigma_regions=2,
    )  # fmt: skip
    pairs, cov = seen["pair_covariance"]
    assert pairs.shape[1] == 2 and cov.shape == (len(pairs), 3) and len(pairs) > 0
    assert pairs.min() >= 0 and pairs.max() < len(res)
    adjacent = (np.abs(res.row[pairs[:, 0]] - res.row[pairs[:, 1]]) <= 1) & (
        np.abs(res.col[pairs[:, 0]] - res.col[pairs[:, 1]]) <= 1
    )
    assert adjacent.any() and np.all(cov[adjacent] > 0)
