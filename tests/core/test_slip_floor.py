"""The slip's error floor (benchmarks/slip_floor.py, issue #30): the Woodbury algebra against
dense matrices, and the Gauss-Markov order of the fits on one synthetic TLS pair."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import slip_floor as F  # noqa: E402


def _dense(x, z, w, known):
    """Covariance under Σ = I / w + Z Zᵀ of the GLS fit with Σ_k = I / w + Z_k Z_kᵀ."""
    n = x.shape[0]
    sigma = np.eye(n) / w + z @ z.T
    zk = z[:, known]
    sk_inv = np.linalg.inv(np.eye(n) / w + zk @ zk.T)
    m = np.linalg.inv(x.T @ sk_inv @ x) @ x.T @ sk_inv
    return m @ sigma @ m.T


@pytest.mark.parametrize("which", ["all", "none", "part"])
def test_misspecified_matches_dense(which):
    rng = np.random.default_rng(4)
    x = rng.normal(size=(120, 5))
    z = rng.normal(size=(120, 7)) * 0.3
    w = 25.0
    known = {"all": np.ones(7, bool), "none": np.zeros(7, bool)}.get(which)
    if known is None:
        known = np.array([1, 0, 1, 1, 0, 0, 1], bool)
    got = F._misspecified(x.T @ x, x.T @ z, z.T @ z, w, known)
    want = _dense(x, z, w, known)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-14)


def test_full_model_is_gls():
    """Knowing every effect, the sandwich is the GLS covariance itself."""
    rng = np.random.default_rng(5)
    x = rng.normal(size=(80, 4))
    z = rng.normal(size=(80, 6)) * 0.5
    w = 10.0
    sigma = np.eye(80) / w + z @ z.T
    gls = np.linalg.inv(x.T @ np.linalg.inv(sigma) @ x)
    got = F._misspecified(x.T @ x, x.T @ z, z.T @ z, w, np.ones(6, bool))
    np.testing.assert_allclose(got, gls, rtol=1e-9)


def test_model_cov_matches_dense():
    """A model of other effects than the truth's (a hat basis in place of the drift): the
    sandwich against dense matrices, and the GLS covariance when the model is the truth."""
    rng = np.random.default_rng(6)
    x = rng.normal(size=(100, 4))
    zt = rng.normal(size=(100, 5)) * 0.4
    zm = rng.normal(size=(100, 3)) * 0.6
    w = 16.0
    z = np.hstack([zt, zm])
    truth = np.r_[np.ones(5, bool), np.zeros(3, bool)]
    got = F._model_cov(x.T @ x, x.T @ z, z.T @ z, w, ~truth, truth)
    sigma = np.eye(100) / w + zt @ zt.T
    sm_inv = np.linalg.inv(np.eye(100) / w + zm @ zm.T)
    m = np.linalg.inv(x.T @ sm_inv @ x) @ x.T @ sm_inv
    np.testing.assert_allclose(got, m @ sigma @ m.T, rtol=1e-9, atol=1e-14)
    same = np.hstack([zt, zt])
    first = np.r_[np.ones(5, bool), np.zeros(5, bool)]
    got = F._model_cov(x.T @ x, x.T @ same, same.T @ same, w, ~first, first)
    gls = np.linalg.inv(x.T @ np.linalg.inv(sigma) @ x)
    np.testing.assert_allclose(got, gls, rtol=1e-9)


def test_model_beta_is_the_dense_gls_estimate_and_sides_copies_split_the_columns():
    """The realised estimate of a model fit (``_model_beta``) against the dense GLS with the
    model's covariance; ``:sides`` copies are zero on the other side's rows and sum to the
    hat's columns, ``:split`` doubles each copy."""
    rng = np.random.default_rng(8)
    x = rng.normal(size=(80, 4))
    z = rng.normal(size=(80, 6)) * 0.5
    y = x @ rng.normal(size=4) + z @ rng.normal(size=6) + rng.normal(0, 0.25, 80)
    w = 16.0
    model = np.r_[np.zeros(2, bool), np.ones(4, bool)]
    got = F._model_beta(x.T @ x, x.T @ y, x.T @ z, z.T @ y, z.T @ z, w, model)
    zm = z[:, model]
    sm_inv = np.linalg.inv(np.eye(80) / w + zm @ zm.T)
    want = np.linalg.solve(x.T @ sm_inv @ x, x.T @ sm_inv @ y)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    side = rng.integers(0, 2, 80)
    cp = F._hat_copies(z, ["sides"], side)
    assert cp.shape == (80, 12)
    assert not np.any(cp[side == 1, :6]) and not np.any(cp[side == 0, 6:])
    np.testing.assert_array_equal(cp[:, :6] + cp[:, 6:], z)
    assert F._hat_copies(z, ["split", "sides"], side).shape == (80, 24)
    assert F._copies(["offset"]) == 1 and F._copies(["split", "sides"]) == 4


def test_tls_floor_below_least_squares():
    """On one TLS pair of the harness: the floor (every setup's error modelled) is the
    smallest σ on every axis, least squares' is larger, and the floor's error is of its σ's
    size (within 4σ: a single draw)."""
    row = F.one("tls-6-setups", 3000)
    floor = np.array(row["floor"]["sigma"])
    ols = np.array(row["knowing_only"]["none"])
    assert np.all(floor > 0.0005) and np.all(floor < 0.01)  # millimetres, as the kind's
    assert np.all(floor <= ols * (1 + 1e-9))
    np.testing.assert_allclose(row["knowing_only"]["setups"], floor, rtol=1e-9)
    assert np.all(np.abs(row["floor"]["err"]) < 4 * floor)
    assert row["planes_n"] >= 20


def test_patch_means_lose_nothing_when_rows_share_their_design():
    """Group means are sufficient when every row of a group has the same design: the GLS
    covariance and estimate on the means (``_patch_means``) equal those on the rows."""
    import scipy.sparse as sp

    rng = np.random.default_rng(9)
    group = rng.integers(0, 25, 300)
    xg, zg = rng.normal(size=(25, 4)), rng.normal(size=(25, 5)) * 0.3
    x, z = xg[group], zg[group]
    y = x @ rng.normal(size=4) + z @ rng.normal(size=5) + rng.normal(0, 0.1, 300)
    w = 100.0

    def gls(x, z, y):
        sigma = np.eye(len(y)) / w + z @ z.T
        si = np.linalg.inv(sigma)
        cov = np.linalg.inv(x.T @ si @ x)
        return cov, cov @ x.T @ si @ y

    xm, zm, ym = F._patch_means(sp.csr_matrix(x), z, y, group)
    c0, b0 = gls(x, z, y)
    c1, b1 = gls(xm.toarray(), np.asarray(zm), np.asarray(ym))
    np.testing.assert_allclose(c1, c0, rtol=1e-8)
    np.testing.assert_allclose(b1, b0, rtol=1e-8, atol=1e-10)


def test_tls_floor_on_patches():
    """Patches of 0.1 mm hold one point each: the point floor. Patches of 2 m can only lose
    information: a σ at least the point floor's on every axis."""
    point = np.array(F.one("tls-6-setups", 3000)["floor"]["sigma"])
    tiny = np.array(F.one("tls-6-setups", 3000, patch_m=1e-4)["floor"]["sigma"])
    wide = np.array(F.one("tls-6-setups", 3000, patch_m=2.0)["floor"]["sigma"])
    np.testing.assert_allclose(tiny, point, rtol=1e-6)
    assert np.all(wide >= point * (1 - 1e-9))
