"""A cell that fails the neighbour test takes the residual's excess as its own variance
(core/icp.py ``_widen_neighbour_outliers``, issue #29 item 3, stop 56)."""

from __future__ import annotations

import numpy as np

from slipmap.core import icp
from slipmap.core.icp import WindowedICPResult, _scale_sigmas

SIGMA = 0.002  # m, every cell's honest 1-sigma


def _field(seed: int, shape=(14, 14)) -> WindowedICPResult:
    """A uniform motion (0.1, -0.3, -0.05) m on a grid of 5 m cells, each cell's error
    drawn with its stated 2 mm."""
    rng = np.random.default_rng(seed)
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    row, col = rr.ravel(), cc.ravel()
    k = row.size
    d = np.array([0.1, -0.3, -0.05]) + rng.normal(0.0, SIGMA, (k, 3))
    s = np.full(k, SIGMA)
    zeros, ones = np.zeros(k), np.ones(k, dtype=bool)
    return WindowedICPResult(
        x=col * 5.0 + 2.5, y=-row * 5.0 - 2.5, z=zeros, dx=d[:, 0], dy=d[:, 1], dz=d[:, 2],
        sigma_dx=s, sigma_dy=s, sigma_dz=s, cov_d=np.repeat(np.eye(3)[None] * SIGMA**2, k, 0),
        rx=zeros, ry=zeros, rz=zeros, sigma_rx=s, sigma_ry=s, sigma_rz=s, rmse=zeros + 0.01,
        sigma0=zeros + 0.01, n=np.full(k, 500), n_after=np.full(k, 500),
        n_before=np.full(k, 500), iterations=np.full(k, 5), converged=ones, row=row, col=col,
        origin_xy=(0.0, 0.0), cell_m=5.0, n_rows=shape[0], n_cols=shape[1], skipped={},
    )  # fmt: skip


def _sig(res):
    return np.column_stack([res.sigma_dx, res.sigma_dy, res.sigma_dz])


def test_a_blended_cell_is_widened_to_its_error_and_the_honest_cells_are_not():
    for seed in range(6):
        res = _field(seed)
        blend = 6 * 14 + 7  # an inner cell reports 4 cm of another motion in y
        bad = res.dy.copy()
        bad[blend] += 0.04
        res = WindowedICPResult(**{**res.__dict__, "dy": bad})
        got = _scale_sigmas(res)
        sig = _sig(got)
        assert got.sigma_factor < 1.3  # one cell does not move the field's factor
        # its y sigma now covers its 4 cm (20 of its stated sigmas); x and z stay near the
        # factor's (a chance rejection past 3 sigma widens a component only by its excess)
        assert 0.02 < sig[blend, 1] < 0.06
        assert abs(bad[blend] + 0.3) <= 2.0 * sig[blend, 1]
        assert np.all(sig[blend, [0, 2]] < 2.0 * SIGMA * got.sigma_factor)
        # the covariance carries the same variance
        np.testing.assert_allclose(got.cov_d[blend, 1, 1], sig[blend, 1] ** 2, rtol=1e-12)
        # cells beyond its neighbours keep the factor's sigmas, save the test's chance
        # rejections (about 0.3 % of honest components at 3 sigma)
        far = (np.abs(res.row - 6) > 1) | (np.abs(res.col - 7) > 1)
        scaled = np.isclose(sig[far], SIGMA * got.sigma_factor, rtol=1e-12)
        assert scaled.mean() > 0.98


def test_widening_only_ever_widens_and_can_be_switched_off(monkeypatch):
    res = _field(11)
    bad = res.dz.copy()
    bad[[20, 100, 150]] += [0.03, -0.05, 0.02]
    res = WindowedICPResult(**{**res.__dict__, "dz": bad})
    on = _sig(_scale_sigmas(res))
    monkeypatch.setattr(icp, "NEIGHBOUR_OUTLIER_Z", None)
    off = _sig(_scale_sigmas(res))
    assert np.all(on >= off)
    assert np.all(on[[20, 100, 150], 2] > 5 * off[[20, 100, 150], 2])
