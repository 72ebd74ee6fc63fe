"""Change of support of the spatial term (issue #30 item 3): planes average the survey-error
field over their extent (block-to-block covariance), known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipmap.core import stochastic as sto


def _corr(a):
    return lambda d: sto.spherical_correlation(d, a)


def _grid(centre, u, v, half_u, half_v, m):
    """(m*m, 3) cell centres of an m x m grid on a rectangle (axes u, v, half-widths)."""
    f = (np.arange(m) + 0.5) / m * 2.0 - 1.0
    fa, fb = np.meshgrid(f, f, indexing="ij")
    return (
        np.asarray(centre, dtype=float)
        + fa.ravel()[:, None] * half_u * np.asarray(u, dtype=float)
        + fb.ravel()[:, None] * half_v * np.asarray(v, dtype=float)
    )


def test_support_correlation_matches_reference():
    """The k-d tree kernel over sample pairs = the double loop, for a correlation of compact
    support (pairs beyond it are nil) and for the cross-correlation of two ranges."""
    rng = np.random.default_rng(3)
    ka, kb, ns = 7, 6, 5
    sa = rng.uniform(-20, 20, (ka, ns, 3))
    sb = rng.uniform(-20, 20, (kb, ns, 3))
    wa = rng.uniform(0, 1, (ka, ns))
    wb = rng.uniform(0, 1, (kb, ns))
    wa[:, -1] = 0.0  # padding
    wa /= wa.sum(1, keepdims=True)
    wb /= wb.sum(1, keepdims=True)
    ea = (sa.reshape(-1, 3), np.repeat(np.arange(ka), ns), wa.ravel())
    eb = (sb.reshape(-1, 3), np.repeat(np.arange(kb), ns), wb.ravel())
    for corr, base in ((_corr(15.0), 15.0),
                       (lambda d: sto.ball_cross_correlation(d, 10.0, 25.0), 17.5)):  # fmt: skip
        i, j, rho = sto.support_correlation(corr, base, ea, eb)
        got = np.zeros((ka, kb))
        got[i, j] = rho
        ii, jj = np.meshgrid(np.arange(ka), np.arange(kb), indexing="ij")
        ref = sto.block_correlation_reference(
            corr, sa[ii.ravel()], wa[ii.ravel()], sb[jj.ravel()], wb[jj.ravel()]
        ).reshape(ka, kb)
        assert np.count_nonzero(ref) > 0
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-15)


def _two_set_model(rng, k=12, ns=9):
    c = rng.uniform(-30, 30, (k, 3)) * [1, 1, 0.2]
    n = rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ext = rng.choice([0.0, 2.0, 25.0], k)  # points, small planes, large planes
    s = c[:, None, :] + rng.uniform(-1, 1, (k, ns, 3)) * ext[:, None, None]
    w = rng.uniform(0.2, 1, (k, ns))
    w /= w.sum(1, keepdims=True)
    c = np.einsum("ks,ksd->kd", w, s)  # the centroid is the weighted mean of the samples
    return sto.PlaneModel(c, n, samples=s, sample_weights=w)


def _grid_model(rng, k=14):
    """Planes with an 8 x 8 grid of samples (the adjustment's layout), of 0.5-80 m."""
    c = rng.uniform(-40, 40, (k, 3)) * [1, 1, 0.2]
    n = rng.normal(size=(k, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    half = rng.choice([0.25, 3.0, 12.0, 40.0], k)
    s = np.stack([_grid(c[j], [1, 0, 0], [0, 1, 0], half[j], 0.5 * half[j], 8)
                  for j in range(k)])  # fmt: skip
    w = rng.uniform(0.2, 1, (k, 64))
    w /= w.sum(1, keepdims=True)
    c = np.einsum("ks,ksd->kd", w, s)
    return sto.PlaneModel(c, n, samples=s, sample_weights=w)


@pytest.mark.parametrize("make", [_two_set_model, _grid_model])
def test_dense_spatial_term_matches_double_loop_reference(make):
    model = make(np.random.default_rng(5))
    k = model.centroids.shape[0]
    idx = np.arange(k)
    a = 18.0
    got = model.bases(idx, a)["spatial"]
    pts, own, wt = model.effective(idx, a)
    ns = np.bincount(own, minlength=k).max()
    sp = np.zeros((k, ns, 3))
    ws = np.zeros((k, ns))
    for j in range(k):
        sp[j, : np.sum(own == j)] = pts[own == j]
        ws[j, : np.sum(own == j)] = wt[own == j]
    np.testing.assert_allclose(ws.sum(1), 1.0, rtol=1e-12)
    ref = np.empty((k, k))
    for j in range(k):
        for m in range(k):
            rho = sto.block_correlation_reference(
                _corr(a), sp[j : j + 1], ws[j : j + 1], sp[m : m + 1], ws[m : m + 1]
            )[0]
            ref[j, m] = rho * float(model.normals[j] @ model.normals[m])
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-14)
    assert np.linalg.eigvalsh(got).min() > -1e-10  # positive semi-definite


def test_grid_levels_follow_the_range():
    """A plane less than half the range across is its centroid; a large one keeps the full
    8 x 8 grid under a short range and fewer samples under a long one."""
    model = _grid_model(np.random.default_rng(2))
    idx = np.arange(model.centroids.shape[0])
    _, r = model.support(idx)[1:]
    for a in (5.0, 30.0, 200.0):
        _, own, _ = model.effective(idx, a)
        count = np.bincount(own, minlength=idx.size)
        assert np.all(count[2 * r < 0.5 * a] == 1)
        assert np.all(count <= 64)
    _, own5, _ = model.effective(idx, 5.0)
    _, own200, _ = model.effective(idx, 200.0)
    big = int(np.argmax(r))
    assert np.bincount(own5)[big] == 64 and np.bincount(own200)[big] < 64


def test_sparse_operator_matches_dense(monkeypatch):
    model = _two_set_model(np.random.default_rng(6), k=30)
    idx = np.arange(30)
    p = np.full(30, 1e-6)
    theta = {"plane": 1e-6, "spatial": 9e-6}
    dense = sto.CovarianceOperator(model, idx, p, theta, 20.0)
    monkeypatch.setattr(sto, "DENSE_MAX_PLANES", 5)
    sparse = sto.CovarianceOperator(model, idx, p, theta, 20.0)
    assert sparse.sparse and not dense.sparse
    np.testing.assert_allclose(sparse.diag(), dense.diag(), rtol=1e-12)
    b = np.random.default_rng(0).normal(size=(30, 2))
    np.testing.assert_allclose(sparse.solve(b), dense.solve(b), rtol=1e-8)


def test_identical_small_planes_reduce_to_the_centroid_model():
    """Two small planes (0.2 m) 5 m apart under a 30 m range: the block covariance is the
    centroid model's to 1 %; without samples it is the centroid model exactly."""
    n = np.array([[0, 0, 1.0], [0, 0, 1.0]])
    c = np.array([[0, 0, 0.0], [5, 0, 0.0]])
    s = np.stack([_grid(ci, [1, 0, 0], [0, 1, 0], 0.1, 0.1, 4) for ci in c])
    idx = np.arange(2)
    block = sto.PlaneModel(c, n, samples=s).bases(idx, 30.0)["spatial"]
    plain = sto.PlaneModel(c, n).bases(idx, 30.0)["spatial"]
    rho = float(sto.spherical_correlation(5.0, 30.0))
    np.testing.assert_allclose(plain, [[1.0, rho], [rho, 1.0]], rtol=0, atol=1e-15)
    np.testing.assert_allclose(block, plain, rtol=0.01)


def test_long_line_averages_a_short_range_field():
    """A line of length L = 100 m under a spherical field of range a = 5 m: the variance of
    its mean is ``(2/L²) ∫₀ᵃ (L − h) ρ(h) dh = 0.75 a/L − 0.2 a²/L²`` (0.037), within 2 %
    with 1000 samples (0.1 m apart)."""
    big_l, a = 100.0, 5.0
    x = (np.arange(1000) + 0.5) * big_l / 1000
    s = np.zeros((1, 1000, 3))
    s[0, :, 0] = x
    c = s.mean(axis=1)
    model = sto.PlaneModel(c, np.array([[0, 0, 1.0]]), samples=s)
    got = model.bases(np.arange(1), a)["spatial"][0, 0]
    want = 0.75 * a / big_l - 0.2 * a * a / big_l**2
    assert got == pytest.approx(want, rel=0.02)


def test_cross_covariance_uses_the_planes_supports():
    """cross_covariance with samples = gain_a ρ̄_ab gain_bᵀ from the double-loop reference,
    planes whose supports overlap beyond the centroids' reach included."""
    rng = np.random.default_rng(9)
    ma, mb = _two_set_model(rng, k=6), _two_set_model(rng, k=5)
    ga, gb = rng.normal(size=(6, 6)), rng.normal(size=(6, 5))
    ra, rb = 12.0, 20.0

    def gain(g, m, r):
        return sto.PlaneGain(
            gain=g, centroids=m.centroids, normals=m.normals, shares_before=None,
            shares_after=None, units_before=None, units_after=None,
            theta={"spatial": 4e-6}, range_m=r, samples=m.samples,
            sample_weights=m.sample_weights,
        )  # fmt: skip

    got = sto.cross_covariance(gain(ga, ma, ra), gain(gb, mb, rb))
    c = np.empty((6, 5))
    for j in range(6):
        for k in range(5):
            rho = sto.block_correlation_reference(
                lambda d: sto.ball_cross_correlation(d, ra, rb),
                ma.samples[j : j + 1], ma.sample_weights[j : j + 1],
                mb.samples[k : k + 1], mb.sample_weights[k : k + 1],
            )[0]  # fmt: skip
            c[j, k] = 4e-6 * rho * float(ma.normals[j] @ mb.normals[k])
    np.testing.assert_allclose(got, ga @ c @ gb.T, rtol=1e-10, atol=1e-18)


def _wave_field(rng, pts, n_waves=64, lam=(37.0, 53.0), sigma=1.0):
    """A smooth scalar field of plane waves (random directions, wavelengths in ``lam``) at
    ``pts`` (n, 3): unit variance times ``sigma²``, correlation zero at about 17 m."""
    az = rng.uniform(0, 2 * math.pi, n_waves)
    kk = 2 * math.pi / rng.uniform(*lam, n_waves)
    ph = rng.uniform(0, 2 * math.pi, n_waves)
    arg = np.outer(pts[:, 0], kk * np.cos(az)) + np.outer(pts[:, 1], kk * np.sin(az)) + ph
    return sigma * math.sqrt(2.0 / n_waves) * np.cos(arg).sum(axis=1)


def test_gls_vertical_follows_the_large_ground_not_the_small_roofs():
    """One large ground plane (150 m x 75 m) and five 10 m roofs, all horizontal, under a
    smooth field of 37-53 m wavelength: each plane's error is the field's mean over its points.
    The plane-level GLS of the vertical with the block covariance weights the ground, whose
    mean error is small, and its RMS error over 300 draws is within 1.5x that of the ground's
    mean alone; the centroid model weights the six planes alike and is several times worse."""
    ground = np.stack(np.meshgrid(np.arange(-75, 75, 1.5), np.arange(-37.5, 37.5, 1.5)), -1)
    ground = np.column_stack([ground.reshape(-1, 2), np.zeros(ground.size // 2)])
    roof_c = np.array([[-50, -20, 8.0], [-10, 25, 9.0], [20, -15, 7.0], [45, 20, 10.0],
                       [60, -25, 6.0]])  # fmt: skip
    r = np.stack(np.meshgrid(np.arange(-5, 5, 1.0), np.arange(-5, 5, 1.0)), -1).reshape(-1, 2)
    roofs = [rc + np.column_stack([r, np.zeros(len(r))]) for rc in roof_c]
    planes = [ground] + roofs
    cents = np.array([p.mean(axis=0) for p in planes])
    samples = np.stack([_grid(p.mean(0), [1, 0, 0], [0, 1, 0], *(0.5 * np.ptp(p[:, :2], 0)), 8)
                        for p in planes])  # fmt: skip
    n = np.tile([0, 0, 1.0], (6, 1))
    idx = np.arange(6)
    a = 20.0  # spherical range of about the field's correlation length
    x = np.ones((6, 1))
    nug = 1e-4 * np.eye(6)
    errs = {}
    for name, model in (("block", sto.PlaneModel(cents, n, samples=samples)),
                        ("centroid", sto.PlaneModel(cents, n))):  # fmt: skip
        v = model.bases(idx, a)["spatial"] + nug
        vi = np.linalg.solve(v, x)
        errs[name] = (vi / (x.T @ vi).item()).ravel()  # GLS weights of the six planes
    draws = np.array([[float(_wave_field(np.random.default_rng(1000 + d), p).mean())
                       for p in planes] for d in range(300)])  # fmt: skip
    rms = {k: float(np.sqrt(np.mean((draws @ w) ** 2))) for k, w in errs.items()}
    rms_ground = float(np.sqrt(np.mean(draws[:, 0] ** 2)))
    rms_roof = float(np.sqrt(np.mean(draws[:, 1:] ** 2)))
    assert rms_ground < 0.2 * rms_roof  # the ground averages the field out
    assert rms["block"] < 1.5 * rms_ground
    assert rms["centroid"] > 3.0 * rms["block"]
