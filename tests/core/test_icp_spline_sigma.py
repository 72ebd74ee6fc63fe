"""Honest sigma of the default spline field (issue #29, item 3): a fit whose data were weighed
by the cells' independent share carries the cell-wide error already (no share of the rigid
cells' floor on top), and the field's misfit to the rigid cells supplies what a smooth (per
side) field misses beside a discontinuity."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from test_icp_breaklines import SLAB, UTM, A, B, _east, _scarp_pair

from slipmap.core.breaklines import breaklines, distance_m
from slipmap.core.icp import _spline_blocks, spline_model_variance, windowed_icp
from slipmap.core.icp_spline import SplineFit


def _cells(k, d, cov):
    row, col = np.divmod(np.arange(k), 10)
    ok = np.ones(k, dtype=bool)
    return (row, col, d, cov, np.full(k, 1500), ok, ok, cov)


def test_the_misfit_variance_is_the_squared_model_error_less_the_cells_noise():
    """Rigid cells see the truth with honest noise ``sqrt(F) s``; the field misses a known
    model error ``b`` at some cells. ``max(0, r² - F s²)`` is about ``b²`` on average where
    the field misses (the one-sample estimate is unbiased there), small where it fits, and
    with it the field's sigma hold 93-99 % of the errors within 2 sigma over a range of
    misses (without it the cells that miss by more than 2 sigma fall out)."""
    rng = np.random.default_rng(3)
    k = 4000
    s = 0.004  # formal sigma of a rigid cell, m
    f = rng.uniform(1.0, 4.0, k)  # its variance ratio (the data weight is 1 / F)
    truth = rng.normal(0.0, 0.3, (k, 3))
    b = np.zeros((k, 3))
    miss = rng.random(k) < 0.3
    b[miss] = rng.normal(0.0, 1.0, (miss.sum(), 3)) * rng.uniform(0.002, 0.08, (miss.sum(), 1))
    sig_field = 0.002  # the field's own sampling sigma (it pools many cells)
    field = truth + b + rng.normal(0.0, sig_field, (k, 3))
    rigid = truth + rng.normal(0.0, 1.0, (k, 3)) * (np.sqrt(f) * s)[:, None]
    # the projection of a field that is the truth plus its error: the field's value (rigid
    # motions here, so the projection of the field's motion is its value)
    sfit = SimpleNamespace(d=field, projection=field, data_weight=1.0 / f)
    cov = np.tile(np.eye(3) * s**2, (k, 1, 1))
    v = spline_model_variance(sfit, _cells(k, rigid, cov))
    assert v.shape == (k, 3) and np.all(v >= 0)
    big = miss[:, None] & (np.abs(b) > 0.02)
    ratio = v[big].mean() / (b[big] ** 2).mean()
    assert 0.85 < ratio < 1.2, ratio
    # where the field fits, the estimate is a fraction of the misfit's noise: E max(0, z² - 1)
    # = 0.48 of it for a chi²₁ z² (the clipping at zero; measured 0.54 with the field's noise)
    noise = f[~miss].mean() * s**2 + sig_field**2
    assert v[~miss].mean() < 0.6 * noise, v[~miss].mean() / noise
    err = np.abs(field - truth)
    within = err <= 2.0 * np.sqrt(sig_field**2 + v)
    without = err <= 2.0 * sig_field
    assert 0.93 <= within.mean() <= 0.99, within.mean()  # measured 0.944
    # misses of more than 4 times the rigid cell's noise are seen (measured 0.998); those
    # of 1-2 times it are not resolved by one cell (measured 0.62)
    seen = np.abs(b) > 4.0 * (np.sqrt(f) * s)[:, None]
    assert within[seen].mean() >= 0.97, within[seen].mean()
    assert without[seen].mean() < 0.1, without[seen].mean()


def test_cells_without_a_rigid_fit_add_nothing():
    k = 20
    d = np.full((k, 3), 0.1)
    sfit = SimpleNamespace(d=np.zeros((k, 3)), projection=np.zeros((k, 3)), data_weight=np.ones(k))
    cells = list(_cells(k, d, np.tile(np.eye(3) * 1e-6, (k, 1, 1))))
    cells[5] = np.arange(k) >= 10  # ok: only the second half has a rigid fit
    v = spline_model_variance(sfit, tuple(cells))
    np.testing.assert_array_equal(v[:10], 0.0)
    np.testing.assert_allclose(v[10:], 0.01 - 1e-6)
    # the projection undetermined (NaN): nothing either
    sfit.projection = np.full((k, 3), np.nan)
    np.testing.assert_array_equal(spline_model_variance(sfit, tuple(cells)), 0.0)


def test_a_weighted_fit_takes_no_share_of_the_rigid_cells_floor():
    """The weighted fit's covariance carries the cells' F: the rigid cells' cell-wide floor
    is not applied again (it is for an unweighted fit) and the misfit term is handed on."""
    rng = np.random.default_rng(1)
    k = 100
    row, col = np.divmod(np.arange(k), 10)
    d = rng.normal(0.0, 0.01, (k, 3))  # rigid cells that disagree far beyond their sigmas
    cov = np.tile(np.eye(3) * 1e-6, (k, 1, 1))
    ok = np.ones(k, dtype=bool)
    cells = (row, col, d, cov, np.full(k, 2000), ok, ok, cov)
    cov9 = np.tile(np.eye(9) * 1e-6, (k, 1, 1))

    def sfit(weighted):
        return SplineFit(
            field=None, d=np.zeros((k, 3)), gradient=np.zeros((k, 3, 3)), cov=cov9,
            rmse=np.full(k, 0.003), n=np.full(k, 2000), sigma0_m=0.003, iterations=3,
            converged=True, n_coefficients=300, cov_blocks=cov9, n_blocks=np.full(k, 400),
            data_weight=np.ones(k) if weighted else None,
            projection=np.zeros((k, 3)) if weighted else None,
        )  # fmt: skip

    kw0 = dict(sigma_model="blocks", sigma_block_m=0.125, sigma_block_ratio=np.nan)
    _, kw = _spline_blocks(sfit(False), ok, None, kw0, sigma_scaling="field", cells=cells)
    assert kw["cells_floor"].factor > 2 and "model_var" not in kw
    _, kw = _spline_blocks(sfit(True), ok, None, kw0, sigma_scaling="field", cells=cells)
    assert "cells_floor" not in kw
    np.testing.assert_allclose(kw["model_var"], np.maximum(d**2 - 1e-6, 0.0))
    _, kw = _spline_blocks(sfit(True), ok, None, kw0, sigma_scaling="formal", cells=cells)
    assert "cells_floor" not in kw and "model_var" not in kw


def test_sigmas_beside_a_detected_scarp_cover_the_error_and_far_ones_stay_small():
    """A slab 0.42 m beyond a straight scarp, the spline with breaklines found from the data
    (the default's model): the cells beside the line (< 3 m) and those far from it hold
    their errors within 2 sigma, and the far cells' sigmas stay at the millimetre their
    errors have (measured: RMS error 0.6 / 0.3 mm, median sigma 0.7 / 0.5 mm near / far)."""
    before, after = _scarp_pair()
    res = windowed_icp(
        before, after, cell_m=4.0, coarse_to_fine=1, field_model="spline", detect_breaklines=True
    )
    assert res.breaklines_source == "detected"
    c = np.c_[res.x, res.y] - UTM[:2]
    truth = _east(c - SLAB[:2])[:, None] * SLAB
    e = np.c_[res.dx, res.dy, res.dz] - truth
    s = np.c_[res.sigma_dx, res.sigma_dy, res.sigma_dz]
    dist = distance_m(c, breaklines([np.array([A, B])]))
    full = res.n_after > 0.8 * np.median(res.n_after)
    near, far = full & (dist < 3.0), full & (dist >= 6.0)
    assert near.sum() >= 10 and far.sum() >= 40
    inside = np.abs(e) <= 2.0 * s
    assert inside[near].mean() >= 0.93, inside[near].mean()
    assert inside[far].mean() >= 0.93, inside[far].mean()
    assert np.median(s[far]) < 3.0 * np.sqrt(np.mean(e[far] ** 2)) + 2e-4, np.median(s[far])
