"""The random tilt per plane of the plane-level model (core/stochastic.py, issue #30 item 1):
the fast algebra against its slow reference, the GLS with it against a direct GLS of the
offsets and the tilts, σ_t recovered from synthetic planes with known random tilts, and the
old system exactly when σ_t = 0."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_stochastic import _normals

from slipmap.core import adjustment as adj
from slipmap.core import stochastic as sto
from slipmap.core.adjustment import adjust_rigid, adjust_rigid_dense
from slipmap.core.errors import InvalidParameterError

OFFSET = np.array([500000.0, 4200000.0, 100.0])
T_TRUE = np.array([0.05, -0.12, 0.03])
W_TRUE = np.array([3e-4, -5e-4, 1e-3])


def make_tilted_pair(seed, *, n_planes=60, n_per=300, sigma=0.003, tilt_sigma=0.0,
                     plane_sigma=0.001, half=4.0):  # fmt: skip
    """Square patches (``2 half`` m across) in two epochs, after = R before + t, whose after
    epoch carries a known random tilt per plane (a rotation of the patch about its centre,
    ``tilt_sigma`` rad on each of the two axes in the plane) and a random offset along the
    normal (``plane_sigma``)."""
    rng = np.random.default_rng(seed)
    nrm = _normals(n_planes, rng)
    centres = OFFSET + rng.uniform(-50, 50, (n_planes, 3)) * [1, 1, 0.2]
    r = Rotation.from_rotvec(W_TRUE).as_matrix()
    out = []
    tilts = rng.normal(0, tilt_sigma, (n_planes, 2)) if tilt_sigma else np.zeros((n_planes, 2))
    offs = rng.normal(0, plane_sigma, n_planes) if plane_sigma else np.zeros(n_planes)
    for ep in range(2):
        pts, lab = [], []
        for i, n in enumerate(nrm):
            e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(n, e1)
            ab = rng.uniform(-half, half, (n_per, 2))
            loc = ab[:, :1] * e1 + ab[:, 1:] * e2
            if ep == 1:
                rot = Rotation.from_rotvec(tilts[i, 0] * e1 + tilts[i, 1] * e2).as_matrix()
                p = centres[i] + loc @ rot.T + offs[i] * n
                p = (p - OFFSET) @ r.T + OFFSET + T_TRUE
            else:
                p = centres[i] + loc
            pts.append(p + rng.normal(0, sigma, p.shape))
            lab.append(np.full(n_per, i))
        out += [np.concatenate(pts), np.concatenate(lab)]
    return out


def _random_tilt_info(rng, k):
    """(k, 3, 3) rank-2 tilt informations (null along a random normal) and (k, 3) right-hand
    sides in their range."""
    a, r = np.zeros((k, 3, 3)), np.zeros((k, 3))
    for j in range(k):
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        e = np.linalg.svd(np.eye(3) - np.outer(n, n))[0][:, :2]
        m = rng.normal(size=(2, 2))
        w = m @ m.T + 0.3 * np.eye(2)
        a[j] = 1e6 * e @ w @ e.T
        r[j] = a[j] @ (e @ rng.normal(0, 1e-4, 2))
    return a, r


@pytest.mark.parametrize("tilt_var", [0.0, 1e-9, 1e-7, 1e-4])
def test_tilt_information_equals_reference(tilt_var):
    rng = np.random.default_rng(1)
    a, r = _random_tilt_info(rng, 12)
    at, rt = sto.tilt_information(a, r, tilt_var)
    ar, rr = sto.tilt_information_reference(a, r, tilt_var)
    np.testing.assert_allclose(at, ar, rtol=1e-8, atol=1e-9 * np.abs(a).max())
    np.testing.assert_allclose(rt, rr, rtol=1e-8, atol=1e-9 * np.abs(r).max())
    if tilt_var == 0:
        assert at is a and rt is r  # the old system exactly


def test_tilt_information_limits():
    """σ_t² → ∞: no tilt information; the normal stays a null direction."""
    rng = np.random.default_rng(2)
    a, r = _random_tilt_info(rng, 5)
    at, rt = sto.tilt_information(a, r, 1e6)
    assert np.abs(at).max() < 1e-5 and np.abs(rt).max() < 1e-5
    at, _ = sto.tilt_information(a, r, 1e-8)
    for j in range(5):
        n = np.linalg.eigh(a[j])[1][:, 0]
        assert np.abs(at[j] @ n).max() < 1e-6 * np.abs(at[j]).max()


def _capture_plane_level(monkeypatch):
    cap = {}
    orig = adj._PlaneLevel.__init__

    def init(self, g_mat, g_vec):
        orig(self, g_mat, g_vec)
        cap["pl"] = self

    monkeypatch.setattr(adj._PlaneLevel, "__init__", init)
    return cap


def test_plane_gls_with_random_tilt_equals_direct_gls(monkeypatch):
    """The block GLS with the random tilt (``nred = Σ ã_j + HᵀV⁻¹H``) against a direct GLS of
    one stacked observation vector: the offsets ``y`` (covariance ``V``) and each plane's
    2-D tilt ``z_j`` (covariance ``C_j + σ_t² I``, from its tangent axes), by dense matrices."""
    cap = _capture_plane_level(monkeypatch)
    b, lb, a, la = make_tilted_pair(4, n_planes=15, n_per=80, tilt_sigma=2e-4)
    adjust_rigid(b, lb, a, la, centre=OFFSET, sigma_before=0.003, sigma_after=0.003,
                 stochastic_model="plane", components={"plane": 0.002})  # fmt: skip
    pl = cap["pl"]
    s0sq, s = 1.3, 4e-8
    p = s0sq * pl.p
    v = np.diag(p) + 0.002**2 * np.eye(p.size)
    vih = np.linalg.solve(v, pl.h)
    t_s, rt_s = pl.tilt(s0sq, s)
    n_fast = t_s + pl.h.T @ vih
    x_fast = np.linalg.solve(n_fast, rt_s + vih.T @ pl.y)
    # direct: stacked observations and a block-diagonal covariance
    rows, obs, covs = [pl.h], [pl.y], [v]
    for j in range(pl.y.size):
        aj = pl.tr[j] / s0sq
        w, vec = np.linalg.eigh(aj)
        e = vec[:, 1:]  # the two tangent axes (the normal is null)
        c = np.diag(1.0 / w[1:])
        jm = np.zeros((2, 6))
        jm[:, :3] = e.T
        rows.append(jm)
        obs.append(c @ e.T @ (pl.rtr[j] / s0sq))
        covs.append(c + s * np.eye(2))
    big_a = np.vstack(rows)
    big_y = np.concatenate(obs)
    big_c = np.zeros((big_y.size, big_y.size))
    o = 0
    for c in covs:
        big_c[o : o + c.shape[0], o : o + c.shape[0]] = c
        o += c.shape[0]
    ci = np.linalg.inv(big_c)
    n_dir = big_a.T @ ci @ big_a
    x_dir = np.linalg.solve(n_dir, big_a.T @ ci @ big_y)
    assert np.abs(pl.t[3:, :]).max() < 1e-8 * np.abs(pl.t).max()  # tilts: rotation only
    np.testing.assert_allclose(n_fast, n_dir, rtol=1e-7, atol=1e-7 * np.abs(n_dir).max())
    np.testing.assert_allclose(x_fast, x_dir, rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tilt_sigma_recovered(seed, monkeypatch):
    """60 planes with random tilts of 0.2 mrad (point noise of a plane's tilt ≈ 0.02 mrad):
    σ_t within 25 % of the truth; the motion's σ then covers its error."""
    monkeypatch.setattr(sto, "RANDOM_TILT", True)
    b, lb, a, la = make_tilted_pair(10 + seed, tilt_sigma=2e-4)
    r = adjust_rigid(b, lb, a, la, centre=OFFSET, sigma_before=0.003, sigma_after=0.003,
                     stochastic_model="plane")  # fmt: skip
    tilt = r.variance_components.tilt
    assert tilt.source == "estimated"
    assert tilt.sigma_rad == pytest.approx(2e-4, rel=0.25)
    assert r.variance_components.to_dict()["random_tilt"]["source"] == "estimated"
    assert r.variance_components.fixed()["tilt_rad"] == pytest.approx(tilt.sigma_rad)


def test_tilt_sigma_nil_without_tilts(monkeypatch):
    """No random tilt in the data: σ_t well below the planes' point-noise tilt σ."""
    monkeypatch.setattr(sto, "RANDOM_TILT", True)
    b, lb, a, la = make_tilted_pair(20, tilt_sigma=0.0)
    r = adjust_rigid(b, lb, a, la, centre=OFFSET, sigma_before=0.003, sigma_after=0.003,
                     stochastic_model="plane")  # fmt: skip
    # a plane's point-noise tilt: σ / (half √(n/3)) per epoch ≈ 0.05 mrad for these patches
    assert r.variance_components.tilt.sigma_rad < 2e-5


def test_rotation_sigma_honest_with_random_tilts(monkeypatch):
    """Planes whose tilts carry the rotation (1 cm random offsets): tilts held as precise
    make the rotation's σ far too small under random tilts of 0.3 mrad; with the random tilt
    its error lies within 3.5σ on each of 8 pairs, and RMS(err/σ) in [0.45, 1.4] (2.3 without)."""
    z_on, z_off = [], []
    for seed in range(8):
        b, lb, a, la = make_tilted_pair(30 + seed, n_planes=40, n_per=400, tilt_sigma=3e-4,
                                        plane_sigma=0.01)  # fmt: skip
        for on, z in ((True, z_on), (False, z_off)):
            monkeypatch.setattr(sto, "RANDOM_TILT", on)
            r = adjust_rigid(b, lb, a, la, centre=OFFSET, sigma_before=0.003,
                             sigma_after=0.003, stochastic_model="plane")  # fmt: skip
            err = r.params[:3] - W_TRUE
            z.append(err / np.sqrt(np.diag(r.covariance)[:3]))
    z_on, z_off = np.array(z_on), np.array(z_off)
    assert np.sqrt(np.mean(z_off**2)) > 2.0
    assert np.abs(z_on).max() < 3.5
    assert 0.45 < np.sqrt(np.mean(z_on**2)) < 1.4


def test_zero_tilt_is_the_old_system(monkeypatch):
    """``tilt_rad`` 0 (and the option off) give the adjustment without the random tilt
    bit for bit; the dense reference refuses a random tilt."""
    b, lb, a, la = make_tilted_pair(5, n_planes=20, n_per=60, tilt_sigma=1e-4)
    kw = dict(centre=OFFSET, sigma_before=0.003, sigma_after=0.003, stochastic_model="full")
    monkeypatch.setattr(sto, "RANDOM_TILT", False)
    r0 = adjust_rigid(b, lb, a, la, **kw)
    r1 = adjust_rigid(b, lb, a, la, components={"tilt_rad": 0.0}, **kw)
    np.testing.assert_array_equal(r0.params, r1.params)
    np.testing.assert_array_equal(r0.covariance, r1.covariance)
    assert r0.variance_components.tilt.source == "off"
    assert "random_tilt" not in r0.variance_components.to_dict()
    with pytest.raises(InvalidParameterError, match="tilt_rad"):
        adjust_rigid_dense(b, lb, a, la, components={"tilt_rad": 1e-4}, **kw)
    with pytest.raises(InvalidParameterError, match="tilt_rad"):
        adjust_rigid(b, lb, a, la, components={"tilt_rad": -1.0}, **kw)


def test_estimate_tilt_variance_plane_level():
    """The estimator alone on plane-level tilts: k planes with known point-noise tilt
    covariances and random tilts of σ_t; offsets absent (their information nil)."""
    rng = np.random.default_rng(7)
    k, st = 400, 1e-3
    a, _ = _random_tilt_info(rng, k)
    r = np.zeros((k, 3))
    w_true = np.array([1e-3, -2e-3, 5e-4])
    for j in range(k):
        w, vec = np.linalg.eigh(a[j])
        e = vec[:, 1:]
        c = np.diag(1.0 / w[1:])
        z = e.T @ w_true + rng.multivariate_normal(np.zeros(2), c + st**2 * np.eye(2))
        r[j] = e @ np.linalg.solve(c, z)  # a_j v_j with v_j = E z
    est = sto.estimate_tilt_variance(a, r, np.zeros((6, 6)), np.zeros(6))
    assert est.converged
    assert est.sigma_rad == pytest.approx(st, rel=0.1)
    assert est.sd > 0
    est0 = sto.estimate_tilt_variance(a[:4], r[:4], np.zeros((6, 6)), np.zeros(6))
    assert est0.source == "off" and est0.var == 0.0


def test_random_tilt_keyword_is_the_switch(monkeypatch):
    """``random_tilt=True`` is the module default switched on, bit for bit; ``False`` turns a
    default of on off; the moments' adjustment (tiles) takes the keyword too; the dense
    reference refuses it."""
    from slipmap.core.planemoments import PlaneMoments, adjust_rigid_moments

    b, lb, a, la = make_tilted_pair(11, n_planes=30, n_per=200, tilt_sigma=2e-4)
    kw = dict(centre=OFFSET, sigma_before=0.003, sigma_after=0.003, stochastic_model="plane")
    monkeypatch.setattr(sto, "RANDOM_TILT", False)
    r_kw = adjust_rigid(b, lb, a, la, random_tilt=True, **kw)
    r_off = adjust_rigid(b, lb, a, la, **kw)
    assert r_kw.variance_components.tilt.source == "estimated"
    assert r_kw.variance_components.tilt.sigma_rad == pytest.approx(2e-4, rel=0.35)
    assert r_off.variance_components.tilt.source == "off"
    monkeypatch.setattr(sto, "RANDOM_TILT", True)
    r_mod = adjust_rigid(b, lb, a, la, **kw)
    np.testing.assert_array_equal(r_kw.params, r_mod.params)
    np.testing.assert_array_equal(r_kw.covariance, r_mod.covariance)
    r_no = adjust_rigid(b, lb, a, la, random_tilt=False, **kw)
    np.testing.assert_array_equal(r_no.params, r_off.params)
    np.testing.assert_array_equal(r_no.covariance, r_off.covariance)
    monkeypatch.setattr(sto, "RANDOM_TILT", False)
    n = int(max(lb.max(), la.max())) + 1
    mb = PlaneMoments.from_points(b, lb, n, origin_m=OFFSET)
    ma = PlaneMoments.from_points(a, la, n, origin_m=OFFSET)
    m_kw = adjust_rigid_moments(mb, ma, random_tilt=True, **kw)
    assert m_kw.variance_components.tilt.sigma_rad == pytest.approx(
        r_kw.variance_components.tilt.sigma_rad, rel=1e-6
    )
    np.testing.assert_allclose(m_kw.params, r_kw.params, rtol=0, atol=1e-9)
    with pytest.raises(InvalidParameterError, match="random_tilt"):
        adjust_rigid_dense(b, lb, a, la, random_tilt=True, **kw)
