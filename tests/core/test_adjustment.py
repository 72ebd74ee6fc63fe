"""Tests of the block Gauss-Helmert rigid adjustment (core/adjustment.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipmap.core.adjustment import PackedCovariance, adjust_rigid, adjust_rigid_dense
from slipmap.core.errors import InputDataError, InvalidParameterError

OFFSET = np.array([500000.0, 4200000.0, 100.0])


def _rot(w):
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    th = np.linalg.norm(w)
    if th == 0:
        return np.eye(3)
    return np.eye(3) + np.sin(th) / th * k + (1 - np.cos(th)) / th**2 * (k @ k)


def _normals(n_planes, rng, vertical_azimuths=None):
    """Horizontal, vertical (several azimuths) and inclined unit normals."""
    out = []
    for i in range(n_planes):
        kind = i % 3
        if kind == 0:  # roof / ground, nearly horizontal
            v = np.array([*rng.normal(0, 0.3, 2), 1.0])
        elif kind == 1:  # wall
            if vertical_azimuths is not None:
                az = vertical_azimuths[i % len(vertical_azimuths)]
            else:
                az = rng.uniform(0, np.pi)
            v = np.array([np.sin(az), np.cos(az), 0.0])
        else:  # inclined
            v = rng.normal(size=3)
        out.append(v / np.linalg.norm(v))
    return np.array(out)


def make_problem(
    n_planes=8,
    n_per=400,
    sigma=0.02,
    t=(0.05, -0.12, 0.08),
    w=(3e-4, -5e-4, 1e-3),
    seed=0,
    normals=None,
    size=10.0,
    spread=60.0,
    outlier=None,
):
    """Random planar patches sampled independently in both epochs; after = R before + t."""
    rng = np.random.default_rng(seed)
    normals = _normals(n_planes, rng) if normals is None else normals
    centres = OFFSET + rng.uniform(-spread, spread, (len(normals), 3)) * [1, 1, 0.2]
    r = _rot(np.asarray(w, dtype=float))
    c_motion = OFFSET
    epochs = []
    for ep in range(2):
        pts, lab = [], []
        for i, n in enumerate(normals):
            e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(n, e1)
            ab = rng.uniform(-size / 2, size / 2, (n_per, 2))
            p = centres[i] + ab[:, :1] * e1 + ab[:, 1:] * e2
            if ep == 1:
                p = (p - c_motion) @ r.T + c_motion + np.asarray(t)
                if outlier is not None and i == outlier:
                    p = p + 0.5 * (r @ n)
            pts.append(p + rng.normal(0, sigma, p.shape))
            lab.append(np.full(n_per, i))
        epochs.append((np.concatenate(pts), np.concatenate(lab)))
    return epochs[0][0], epochs[0][1], epochs[1][0], epochs[1][1], np.asarray(t), r


def test_recovers_translation_and_rotation():
    b, bl, a, al, t, r = make_problem(n_planes=12, n_per=500, sigma=0.02, seed=1)
    res = adjust_rigid(b, bl, a, al, sigma_before=0.02, sigma_after=0.02, centre=OFFSET)
    assert res.converged and res.rejected_planes == ()
    err = res.displacement - t
    assert np.all(np.abs(err) < 1e-3)
    assert np.all(np.abs(err) < 4 * res.sigma[3:])
    assert np.allclose(res.params[:3], [3e-4, -5e-4, 1e-3], atol=5e-5)
    assert res.redundancy == 12000 + 12 - 6 - 48
    assert res.n_planes == 12 and res.n_points == 12000
    assert np.allclose(res.centre, OFFSET)
    # adjusted planes in the input frame: before points lie on them
    pp = res.plane_params
    assert np.allclose(np.linalg.norm(pp[:, :3], axis=1), 1.0)
    d = np.einsum("ij,ij->i", b, pp[bl, :3]) + pp[bl, 3]
    assert np.allclose(d, res.residuals_before, atol=1e-6)
    assert 0.015 < np.std(res.residuals_after) < 0.025


def test_default_centre_is_centroid():
    b, bl, a, al, *_ = make_problem(n_planes=6, n_per=100, seed=2)
    res = adjust_rigid(b, bl, a, al)
    assert np.allclose(res.centre, np.concatenate([b, a]).mean(axis=0))


def test_dense_reference_equals_block():
    b, bl, a, al, *_ = make_problem(n_planes=4, n_per=8, sigma=0.01, seed=3)
    kw = dict(sigma_before=0.01, sigma_after=(0.01, 0.02, 0.015), reject_outlier_planes=False)
    r1 = adjust_rigid(b, bl, a, al, **kw)
    r2 = adjust_rigid_dense(b, bl, a, al, **kw)
    assert r1.iterations == r2.iterations
    np.testing.assert_allclose(r1.params, r2.params, rtol=0, atol=1e-10)
    np.testing.assert_allclose(r1.cofactor, r2.cofactor, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(r1.plane_params[:, :3], r2.plane_params[:, :3], rtol=0, atol=1e-10)
    # uncentred offsets are ~1e6 m: compare relative to their size
    np.testing.assert_allclose(r1.plane_params[:, 3], r2.plane_params[:, 3], rtol=1e-13)
    assert r1.variance_factor == pytest.approx(r2.variance_factor, rel=1e-8)
    # per-point covariance path too
    rng = np.random.default_rng(0)
    m = rng.normal(0, 0.01, (a.shape[0], 3, 3))
    cov = np.einsum("nij,nkj->nik", m, m) + 1e-4 * np.eye(3)
    r3 = adjust_rigid(b, bl, a, al, sigma_after=cov, reject_outlier_planes=False)
    r4 = adjust_rigid_dense(b, bl, a, al, sigma_after=cov, reject_outlier_planes=False)
    np.testing.assert_allclose(r3.params, r4.params, rtol=0, atol=1e-10)
    np.testing.assert_allclose(r3.covariance, r4.covariance, rtol=1e-8, atol=1e-16)


def test_variance_factor_and_calibration():
    vf, z = [], []
    for seed in range(20):
        b, bl, a, al, t, _ = make_problem(n_planes=6, n_per=150, sigma=0.02, seed=100 + seed)
        res = adjust_rigid(b, bl, a, al, sigma_before=0.02, sigma_after=0.02)
        vf.append(res.variance_factor)
        # true displacement at the estimated centre
        zc = (res.displacement - _truth_at(res.centre, t)) / res.sigma[3:]
        z.extend(zc)
    assert np.mean(vf[:5]) == pytest.approx(1.0, abs=0.1)
    assert 0.7 <= np.std(z) <= 1.35


def _truth_at(centre, t, w=(3e-4, -5e-4, 1e-3)):
    r = _rot(np.asarray(w))
    return (centre - OFFSET) @ r.T + OFFSET + t - centre


def test_sigma_forms_agree():
    b, bl, a, al, *_ = make_problem(n_planes=6, n_per=100, seed=4)
    r0 = adjust_rigid(b, bl, a, al, sigma_before=0.03, sigma_after=0.03)
    r1 = adjust_rigid(b, bl, a, al, sigma_before=(0.03, 0.03, 0.03), sigma_after=[0.03] * 3)
    cb = np.broadcast_to(0.03**2 * np.eye(3), (b.shape[0], 3, 3))
    ca = np.broadcast_to(0.03**2 * np.eye(3), (a.shape[0], 3, 3))
    r2 = adjust_rigid(b, bl, a, al, sigma_before=cb, sigma_after=ca)
    r3 = adjust_rigid(b, bl, a, al, sigma_before=np.full(b.shape, 0.03), sigma_after=0.03)
    for r in (r1, r2, r3):
        np.testing.assert_allclose(r.params, r0.params, rtol=0, atol=1e-10)
        np.testing.assert_allclose(r.covariance, r0.covariance, rtol=1e-7)


def test_outlier_plane_rejected():
    b, bl, a, al, t, _ = make_problem(n_planes=12, n_per=1000, sigma=0.02, seed=5, outlier=4)
    res = adjust_rigid(b, bl, a, al, sigma_before=0.02, sigma_after=0.02)
    assert [p for p, _ in res.rejected_planes] == [4]
    assert "outlier" in res.rejected_planes[0][1]
    assert res.n_planes == 11
    assert np.all(np.abs(res.displacement - _truth_at(res.centre, t)) < 1.5e-3)
    assert np.nanmedian(np.abs(res.residuals_after[al == 4])) > 0.2


def test_parallel_normals_raise_naming_direction():
    normals = np.tile([[0.0, 0.0, 1.0]], (5, 1))
    b, bl, a, al, *_ = make_problem(normals=normals, n_per=50, seed=6)
    with pytest.raises(InputDataError, match="translation along .*horizontal"):
        adjust_rigid(b, bl, a, al)


def test_weak_direction_warning():
    rng = np.random.default_rng(7)
    normals = _normals(9, rng, vertical_azimuths=[np.radians(37.0)])
    # remove the horizontal part of the inclined normals so only one wall direction is seen
    normals[2::3] = [0.0, 0.0, 1.0]
    normals[0::3, :2] = 0.0
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[1::3] += rng.normal(0, 1e-2, (3, 3)) * [1, 1, 0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    b, bl, a, al, *_ = make_problem(normals=normals, n_per=100, seed=7)
    res = adjust_rigid(b, bl, a, al, reject_outlier_planes=False)
    assert len(res.weak_directions) == 1
    assert "azimuth 127°" in res.weak_directions[0] and "horizontal" in res.weak_directions[0]


def test_inputs_not_modified_and_errors():
    b, bl, a, al, *_ = make_problem(n_planes=5, n_per=50, seed=8)
    copies = [x.copy() for x in (b, bl, a, al)]
    bl2 = bl.copy()
    bl2[:10] = -1  # ignored points
    res = adjust_rigid(b, bl2, a, al)
    assert np.isnan(res.residuals_before[:10]).all()
    for x, c in zip((b, bl, a, al), copies):
        np.testing.assert_array_equal(x, c)
    with pytest.raises(InputDataError, match="fewer than 3 matched planes"):
        adjust_rigid(b[bl < 2], bl[bl < 2], a[al < 2], al[al < 2])
    bad = b.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputDataError, match="NaN"):
        adjust_rigid(bad, bl, a, al)
    with pytest.raises(InvalidParameterError):
        adjust_rigid(b, bl, a, al, sigma_before=(0.1, 0.2))
    with pytest.raises(InvalidParameterError):
        adjust_rigid(b, bl, a, al, sigma_after=-0.1)


@settings(max_examples=10)
@given(st.tuples(*[st.floats(-1000, 1000) for _ in range(3)]))
def test_common_translation_leaves_motion_unchanged(shift):
    b, bl, a, al, *_ = make_problem(n_planes=5, n_per=60, seed=9)
    r0 = adjust_rigid(b, bl, a, al, reject_outlier_planes=False)
    s = np.asarray(shift)
    r1 = adjust_rigid(b + s, bl, a + s, al, reject_outlier_planes=False)
    np.testing.assert_allclose(r1.params, r0.params, rtol=0, atol=1e-8)
    np.testing.assert_allclose(r1.centre, r0.centre + s, rtol=0, atol=1e-6)


def test_progress_and_unmatched_plane_reported():
    b, bl, a, al, t, _ = make_problem(n_planes=7, n_per=100, seed=10)
    keep = al != 6  # plane 6 has no after points
    calls = []
    res = adjust_rigid(b, bl, a[keep], al[keep], progress=lambda f, m: calls.append(f))
    assert res.rejected_planes == ((6, "no points in the after epoch"),)
    assert res.n_planes == 6
    assert np.all(np.isfinite(res.plane_params[6]))  # its before-epoch fit
    assert calls[-1] == 1.0 and all(0.0 <= f <= 1.0 for f in calls)
    assert calls == sorted(calls)


def test_anisotropic_per_point_covariance_recovers_motion():
    rng = np.random.default_rng(11)
    b, bl, a, al, t, _ = make_problem(n_planes=9, n_per=600, sigma=0.0, seed=11)
    sig = np.array([0.01, 0.01, 0.04])  # vertical noise 4x the horizontal
    b = b + rng.normal(0, 1, b.shape) * sig
    a = a + rng.normal(0, 1, a.shape) * sig
    cov = np.broadcast_to(np.diag(sig**2), (a.shape[0], 3, 3))
    res = adjust_rigid(b, bl, a, al, sigma_before=sig, sigma_after=cov)
    err = res.displacement - _truth_at(res.centre, t)
    assert np.all(np.abs(err) < 4 * res.sigma[3:])
    assert res.variance_factor == pytest.approx(1.0, abs=0.15)


def _random_spd(n, rng):
    """(n, 3, 3) random symmetric positive-definite covariances (m²), full off-diagonals."""
    g = rng.normal(size=(n, 3, 3)) * 0.01
    return g @ g.transpose(0, 2, 1) + np.eye(3) * 1e-5


def test_packed_covariance_forms_agree_with_matrices_and_dense():
    rng = np.random.default_rng(21)
    b, bl, a, al, *_ = make_problem(n_planes=6, n_per=80, seed=21)
    bl = bl.copy()
    bl[::17] = -1  # unused points: the packed rows must be subset like the points
    cb, ca = _random_spd(b.shape[0], rng), _random_spd(a.shape[0], rng)
    six = lambda c: c.reshape(-1, 9)[:, [0, 4, 8, 1, 2, 5]]  # noqa: E731
    r_mat = adjust_rigid(b, bl, a, al, sigma_before=cb, sigma_after=ca)
    r_six = adjust_rigid(b, bl, a, al, sigma_before=six(cb), sigma_after=six(ca))
    r_pk = adjust_rigid(
        b,
        bl,
        a,
        al,
        sigma_before=PackedCovariance.from_array(cb),
        sigma_after=PackedCovariance.from_array(six(ca)),
    )
    r_dense = adjust_rigid_dense(b, bl, a, al, sigma_before=cb, sigma_after=ca)
    for r in (r_six, r_pk, r_dense):
        np.testing.assert_allclose(r.params, r_mat.params, rtol=0, atol=1e-9)
        np.testing.assert_allclose(r.covariance, r_mat.covariance, rtol=1e-6)


def test_packed_covariance_take_matrices_and_errors():
    rng = np.random.default_rng(3)
    c = _random_spd(50, rng)
    pk = PackedCovariance.from_array(c, name="sigma_after")
    assert pk.shape == (50, 6) and len(pk) == 50
    np.testing.assert_array_equal(pk.matrices(), c)
    sub = pk.take(np.arange(50) % 3 == 0).take([1, 4])  # masks compose
    np.testing.assert_array_equal(sub.matrices(), c[np.flatnonzero(np.arange(50) % 3 == 0)[[1, 4]]])
    bad = c.copy()
    bad[7, 0, 1] += 1e-3
    with pytest.raises(InvalidParameterError, match="sigma_after.*symmetric"):
        PackedCovariance.from_array(bad, name="sigma_after")
    bad = c.copy()
    bad[9, 2, 1] = np.nan
    with pytest.raises(InvalidParameterError, match="sigma_after"):
        PackedCovariance.from_array(bad, name="sigma_after")
    bad = c.copy()
    bad[3, 1, 1] = 0.0
    with pytest.raises(InvalidParameterError, match="diagonals must be > 0"):
        PackedCovariance.from_array(bad, name="sigma_after")
    with pytest.raises(InvalidParameterError, match=r"\(N, 6\)"):
        PackedCovariance.from_array(np.ones((5, 4)), name="sigma_after")
    assert np.all(c[7] == pk.matrices()[7])  # the input was not modified
