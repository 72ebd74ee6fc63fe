"""Honest ICP sigmas (issue #29, item 3): block (cluster-robust) covariances from sub-cell
blocks of the residual scores, the block size chosen from the data, few-block cells shrunk,
and the cell-wide floor from neighbour agreement. Known answers: residuals from a Gaussian
random field of known range (the spread of the estimates over many cells is the truth),
independent residuals (the formal sigma is right), a field with a known extra error."""

from __future__ import annotations

import numpy as np
import pytest
from test_icp import field_pair

from slipmap.core.errors import InvalidParameterError
from slipmap.core.icp import windowed_icp
from slipmap.core.icp_blocks import (
    BLOCK_LADDER_M,
    block_meats,
    block_meats_reference,
    cell_floor,
    choose_block_level,
    sandwich,
    shrink_covariance,
)

SIDE_M = 4.0
N_POINTS = 1500


def _normals(xy):
    """Unit normals of the rough surface z = 0.3 sin(2x) cos(1.5y) + 0.2 sin(x + 2y)
    (every translation component determined)."""
    x, y = xy[:, 0], xy[:, 1]
    gx = 0.6 * np.cos(2 * x) * np.cos(1.5 * y) + 0.2 * np.cos(x + 2 * y)
    gy = -0.45 * np.sin(2 * x) * np.sin(1.5 * y) + 0.4 * np.cos(x + 2 * y)
    n = np.column_stack([-gx, -gy, np.ones_like(x)])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _grf(rng, xy, range_m, sigma_m, modes=400):
    """Gaussian random field with covariance ``sigma² exp(-h² / (2 range²))`` at ``xy``
    (random Fourier features: exact covariance in expectation over the modes)."""
    k = rng.normal(0.0, 1.0 / range_m, (modes, 2))
    phase = rng.uniform(0.0, 2 * np.pi, modes)
    return sigma_m * np.sqrt(2.0 / modes) * np.cos(xy @ k.T + phase).sum(axis=1)


def _cells(seed, k, *, range_m, grf_m, white_m):
    """``k`` cells of a translation-only point-to-plane fit (true motion 0) with residuals
    ``GRF + white noise``. Returns the estimates (k, 3), formal and block covariances and the
    block choice."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, SIDE_M, (k, N_POINTS, 2)) + (np.arange(k) * 10.0)[:, None, None]
    A = _normals(xy.reshape(-1, 2))
    v = np.concatenate(
        [
            (_grf(rng, c, range_m, grf_m) if grf_m > 0 else 0.0)
            + rng.normal(0.0, white_m, N_POINTS)
            for c in xy
        ]
    )
    seg = np.repeat(np.arange(k), N_POINTS)
    N = np.einsum("pi,pj->pij", A, A).reshape(k, N_POINTS, 3, 3).sum(axis=1)
    Ninv = np.linalg.inv(N)
    b = np.einsum("pi,p->pi", A, v).reshape(k, N_POINTS, 3).sum(axis=1)
    est = np.einsum("kij,kj->ki", Ninv, b)
    psi = v - np.einsum("pi,pi->p", A, est[seg])
    s0sq = np.bincount(seg, psi * psi) / (N_POINTS - 3)
    formal = s0sq[:, None, None] * Ninv
    meats, nb = block_meats(A, psi, seg, xy.reshape(-1, 2), k)
    scale = np.full(k, N_POINTS / (N_POINTS - 3))
    bcov = sandwich(Ninv, meats, nb, scale)
    fvar = np.diagonal(formal, axis1=1, axis2=2)
    bvar = np.diagonal(bcov, axis1=2, axis2=3)
    choice = choose_block_level(fvar, bvar, nb, np.ones(k, bool))
    honest = shrink_covariance(formal, bcov[:, choice.level], nb[:, choice.level], choice.kappa)
    return est, formal, honest, choice


def _z(est, cov):
    return est / np.sqrt(np.diagonal(cov, axis1=1, axis2=2))


def test_block_meats_agree_with_the_per_block_loop():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-3.0, 3.0, (400, 2)) + [512_000.0, 4_918_000.0]
    A = rng.normal(size=(400, 6))
    psi = rng.normal(size=400) * (rng.random(400) > 0.1)  # some points unused
    seg = np.sort(rng.integers(0, 3, 400))
    fast, nf = block_meats(A, psi, seg, xy, 3)
    ref, nr = block_meats_reference(A, psi, seg, xy, 3)
    np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(nf, nr)
    assert fast.shape == (3, len(BLOCK_LADDER_M), 6, 6)


def test_correlated_residuals_the_blocks_recover_the_spread_the_formal_sigma_misses():
    """Residuals = Gaussian random field (range 0.1 m, 4 mm) + 1 mm white noise on 4 m cells
    of 1500 points: the formal sigma is 2-3x too small; the block sigma's normalised errors
    have an RMS of 1 to 12 % and hold 95 % within 2 sigma to 4 points, over 240 cells."""
    est, formal, honest, choice = _cells(1, 240, range_m=0.1, grf_m=0.004, white_m=0.001)
    z_formal, z_block = _z(est, formal), _z(est, honest)
    assert np.sqrt(np.mean(z_formal**2)) > 2.0
    assert np.mean(np.abs(z_formal) < 2) < 0.7
    assert 0.88 <= np.sqrt(np.mean(z_block**2)) <= 1.12
    assert 0.91 <= np.mean(np.abs(z_block) < 2) <= 0.99
    # the block size from the data: beyond the correlation range (0.1 m), at most 1 m
    assert 0.25 <= choice.block_m <= 1.0
    assert choice.kappa > 3.0


def test_independent_residuals_the_block_sigma_is_the_formal_one():
    est, formal, honest, choice = _cells(2, 120, range_m=0.1, grf_m=0.0, white_m=0.003)
    assert 0.9 <= choice.kappa <= 1.15
    z_formal, z_block = _z(est, formal), _z(est, honest)
    assert 0.9 <= np.sqrt(np.mean(z_formal**2)) <= 1.1
    assert 0.9 <= np.sqrt(np.mean(z_block**2)) <= 1.1
    ratio = np.diagonal(honest, axis1=1, axis2=2) / np.diagonal(formal, axis1=1, axis2=2)
    assert 0.8 <= np.median(ratio) <= 1.2


def test_few_blocks_are_shrunk_towards_the_fields_ratio():
    formal = np.repeat(np.eye(3)[None] * 1e-6, 3, axis=0)
    block = formal * np.array([10.0, 10.0, 1.0])[:, None, None]
    out = shrink_covariance(formal, block, np.array([2, 200, 8]), 4.0, prior_blocks=8.0)
    # 2 blocks: mostly the field's ratio (4); 200 blocks: its own (10); 8: half-way
    np.testing.assert_allclose(
        out[:, 0, 0] / 1e-6, [0.2 * 10 + 0.8 * 4, 200 / 208 * 10 + 8 / 208 * 4, 2.5]
    )
    undetermined = formal.copy()
    undetermined[0, 2, 2] = np.inf
    assert np.isinf(shrink_covariance(undetermined, block, np.array([50, 50, 50]), 2.0)[0, 2, 2])


def _grid_field(seed, a, n_cap, *, shape=(24, 24)):
    rng = np.random.default_rng(seed)
    rows, cols = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    row, col = rows.ravel(), cols.ravel()
    k = row.size
    n = np.exp(rng.uniform(np.log(300), np.log(30_000), k))
    sig = rng.uniform(0.001, 0.003, (k, 3)) * np.sqrt(1000.0 / n)[:, None]
    g = a + (n / n_cap if np.isfinite(n_cap) else np.zeros(k))
    values = 0.05 + rng.normal(size=(k, 3)) * sig * np.sqrt(g)[:, None]
    return row, col, values, sig, n


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_cell_floor_recovers_a_known_factor_and_cap(seed):
    """Cell errors with variance ``sigma² (a + n / n_cap)``, a = 2.25 and n_cap = 2000, on
    576 cells of 300-30 000 points: a within 30 %, n_cap within a factor 1.6 (the two trade
    off: seeds 0-5 gave a 1.75-2.81, n_cap 1512-3096), 95 % +- 3 within 2 sigma."""
    row, col, values, sig, n = _grid_field(seed, 2.25, 2000.0)
    fl = cell_floor(row, col, values, sig, n)
    assert fl.factor_before > 1.7
    assert 2.25 / 1.3 <= fl.factor**2 <= 2.25 * 1.3
    assert 2000 / 1.6 <= fl.n_cap <= 2000 * 1.6
    z = (values - 0.05) / (sig * np.sqrt(fl.scale(n))[:, None])
    assert 0.92 <= np.mean(np.abs(z) < 2) <= 0.98


def test_honest_sigmas_need_no_floor():
    row, col, values, sig, n = _grid_field(3, 1.0, np.inf)
    fl = cell_floor(row, col, values, sig, n)
    assert fl.factor == pytest.approx(1.0, abs=0.2)
    assert fl.n_cap > 50_000  # a cap far above the cells' points changes nothing
    assert np.all(fl.scale(n) < 1.6)


def test_windowed_icp_blocks_on_independent_noise_keep_the_formal_sigma():
    """Synthetic terrain with independent 3 mm noise: the block ratio is about 1 for the cells
    and the spline field; ``sigma_model="independent"`` reports the formal sigmas."""
    before, after = field_pair(5, shift_left=np.array([0.06, -0.03, 0.02]), density=40)
    kw = dict(cell_m=5.0, min_points=200, sigma_scaling="formal")
    blocks = windowed_icp(before, after, **kw)
    formal = windowed_icp(before, after, sigma_model="independent", **kw)
    assert blocks.sigma_model == "blocks" and formal.sigma_model == "independent"
    assert 0.8 <= blocks.sigma_block_ratio <= 1.3
    np.testing.assert_allclose(formal.sigma_dx, formal.sigma_formal[:, 0])
    r = blocks.sigma_dx / blocks.sigma_formal[:, 0]
    assert 0.8 <= np.median(r) <= 1.3
    spline = windowed_icp(before, after, field_model="spline", **kw)
    # the spline weighs each cell's data by its independent share (icp_spline.
    # cell_data_weights): smoother, it leaves the step at x = 15 m (no breakline here) in the
    # residuals of the cells beside it, which the blocks see (1.31; far cells 3.3 -> 0.9 mm)
    assert 0.8 <= spline.sigma_block_ratio <= 1.5
    rs = spline.sigma_dx / spline.sigma_formal[:, 0]
    assert 0.8 <= np.median(rs) <= 1.3
    with pytest.raises(InvalidParameterError, match="sigma_model"):
        windowed_icp(before, after, sigma_model="kriging")


def test_the_surface_share_is_the_residual_variance_above_the_noise(monkeypatch):
    """The smoothest cells' RMS is the points' noise: a cell twice as rough has three
    quarters of its residual variance from the surface; no fit, no share estimate (1)."""
    from slipmap.core import icp_blocks

    rmse = np.r_[np.full(10, 0.004), np.full(90, 0.008), np.nan]
    share = icp_blocks.surface_share(rmse)
    np.testing.assert_allclose(share, np.r_[np.zeros(10), np.full(90, 0.75), 1.0])
    # the noise from the usable cells only: here the rough ones
    usable = np.r_[np.zeros(10, bool), np.ones(91, bool)]
    np.testing.assert_allclose(icp_blocks.surface_share(rmse, usable)[:100], np.r_[np.zeros(100)])
    monkeypatch.setattr(icp_blocks, "NOISE_QUANTILE", None)
    assert icp_blocks.surface_share(rmse) is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_cell_floor_by_surface_share_covers_smooth_and_rough_cells(seed):
    """Cell errors with variance ``sigma² (1 + (a - 1) s)``, a = 9, ``s`` each cell's surface
    share (uniform in [0, 1], independent of its points): ``a`` within 30 %, and the cells
    of low and of high share each at RMS(error / sigma) 0.85-1.15 (seeds 0-5: 0.93-1.01).
    The floor alike for every cell (no share) is too wide on the smooth half (below 0.9;
    0.76-0.85) and too narrow on the rough one (above 1.1; 1.15-1.30). A share of 1
    everywhere is the model without shares."""
    rng = np.random.default_rng(100 + seed)
    row, col, _, sig, n = _grid_field(seed, 1.0, np.inf)
    share = rng.uniform(0.0, 1.0, len(n))
    values = 0.05 + rng.normal(size=sig.shape) * sig * np.sqrt(1.0 + 8.0 * share)[:, None]
    low = share < 0.5

    def rms(fl, s):
        z = (values - 0.05) / (sig * np.sqrt(fl.scale(n, s))[:, None])
        return np.sqrt(np.mean(z[low] ** 2)), np.sqrt(np.mean(z[~low] ** 2))

    fl = cell_floor(row, col, values, sig, n, share=share)
    assert 9.0 / 1.3 <= fl.factor**2 <= 9.0 * 1.3
    assert all(0.85 <= r <= 1.15 for r in rms(fl, share))
    smooth, rough = rms(cell_floor(row, col, values, sig, n), None)
    assert smooth < 0.9 and rough > 1.1
    np.testing.assert_allclose(fl.scale(n, np.ones(len(n))), fl.scale(n))
