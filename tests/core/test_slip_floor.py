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
