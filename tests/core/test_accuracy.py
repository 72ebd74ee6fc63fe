"""Point-accuracy models (core.accuracy): shapes, Monte Carlo checks, footprint law, effect."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipmap.core import accuracy as A
from slipmap.core.errors import InputDataError, InvalidParameterError


def _assert_psd(cov, rtol=1e-10):
    cov = np.asarray(cov)
    assert cov.ndim == 3 and cov.shape[1:] == (3, 3)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), atol=1e-15 + 1e-12 * np.abs(cov).max())
    ev = np.linalg.eigvalsh(cov)
    scale = max(float(np.abs(cov).max()), 1e-300)
    assert np.all(ev >= -rtol * scale)


def _mc_check(c_mc, c_an, tol=0.05):
    """Diagonal within tol (relative); off-diagonals within tol of sqrt(C_ii C_jj)."""
    d = np.sqrt(np.diag(c_an))
    np.testing.assert_allclose(np.diag(c_mc), np.diag(c_an), rtol=tol)
    assert np.all(np.abs(c_mc - c_an) <= tol * np.outer(d, d) + 1e-18)


SPEC = A.ScannerSpec(
    name="test",
    range_sigma_m=0.01,
    angle_sigma_rad=2e-4,
    beam_divergence_rad=1e-3,
    boresight_sigma_rad=(3e-4, 4e-4, 5e-4),
    lever_arm_sigma_m=(0.01, 0.02, 0.015),
    lever_arm_m=(0.3, -0.2, 0.5),
    boresight_rad=(0.002, -0.001, 0.003),
)


# --------------------------------------------------------------------------- simple models


def test_constant_axis_columns():
    c = A.constant_covariance(4, 0.02)
    assert c.shape == (4, 3, 3)
    np.testing.assert_allclose(c, np.broadcast_to(0.0004 * np.eye(3), (4, 3, 3)))
    a = A.axis_covariance(2, (0.01, 0.02, 0.03))
    np.testing.assert_allclose(a[1], np.diag([1e-4, 4e-4, 9e-4]))
    sx, sy, sz = np.array([0.01, 0.02]), np.array([0.03, 0.04]), np.array([0.0, 0.05])
    col = A.columns_covariance(sx, sy, sz)
    assert col.shape == (2, 3, 3)
    np.testing.assert_allclose(A.covariance_to_sigmas(col), np.stack([sx, sy, sz], 1))
    six = A.covariance_to_six(col)
    assert six.shape == (2, 6)
    np.testing.assert_allclose(six[:, :3], np.stack([sx, sy, sz], 1) ** 2)
    np.testing.assert_allclose(six[:, 3:], 0.0)
    assert A.constant_covariance(0, 0.1).shape == (0, 3, 3)
    for x in (c, a, col):
        _assert_psd(x)


@pytest.mark.parametrize(
    "call, word",
    [
        (lambda: A.constant_covariance(3, -0.1), "sigma_m"),
        (lambda: A.constant_covariance(3, np.nan), "sigma_m"),
        (lambda: A.constant_covariance(-1, 0.1), "n"),
        (lambda: A.axis_covariance(3, (0.1, 0.2)), "sigma_xyz_m"),
        (lambda: A.columns_covariance([0.1], [0.1, 0.2], [0.1]), "same length"),
        (lambda: A.columns_covariance([0.1], [np.inf], [0.1]), "sy"),
        (lambda: A.columns_covariance([0.1], [0.1], [-0.1]), "sz"),
        (lambda: A.total_covariance(np.zeros((2, 3, 3)), np.zeros((3, 3, 3))), "same N"),
        (lambda: A.total_covariance(np.zeros((2, 3))), "part 0"),
        (lambda: A.total_covariance(), "at least one"),
    ],
)
def test_bad_parameters(call, word):
    with pytest.raises(InvalidParameterError, match=word):
        call()


def test_covariance_to_six_order():
    c = np.array([[[1.0, 2.0, 3.0], [2.0, 4.0, 5.0], [3.0, 5.0, 6.0]]])
    np.testing.assert_allclose(A.covariance_to_six(c), [[1, 4, 6, 2, 3, 5]])


def test_total_is_sum():
    rng = np.random.default_rng(1)
    m = rng.normal(size=(5, 3, 3))
    c1 = m @ np.swapaxes(m, 1, 2)
    c2 = A.constant_covariance(5, 0.1)
    t = A.total_covariance(c1, c2)
    np.testing.assert_allclose(t, c1 + c2)
    assert t is not c1
    _assert_psd(t)


# --------------------------------------------------------------------------- spec


def test_scanner_presets():
    assert set(A.SCANNERS) == {"riegl-vz400", "leica-als60", "optech-orion"}
    vz = A.SCANNERS["riegl-vz400"]
    assert vz.range_sigma_m == pytest.approx(0.005)
    assert vz.beam_divergence_rad == pytest.approx(0.35e-3)
    assert A.SCANNERS["leica-als60"].beam_divergence_rad == pytest.approx(0.22e-3)
    assert A.SCANNERS["optech-orion"].beam_divergence_rad == pytest.approx(0.25e-3)
    for s in A.SCANNERS.values():
        assert len(s.boresight_sigma_rad) == 3 and len(s.lever_arm_sigma_m) == 3


def test_spec_from_dict_units():
    s = A.scanner_spec_from_dict(
        {
            "name": "mine",
            "range_sigma_mm": 5,
            "angle_sigma_deg": 0.001,
            "beam_divergence_mrad": 0.35,
            "boresight_sigma_deg": [0.001, 0.002, 0.003],
            "lever_arm_sigma_cm": 2,
            "lever_arm_m": [0.1, 0.2, 0.3],
            "boresight_rad": 0.001,
        }
    )
    assert s.name == "mine"
    assert s.range_sigma_m == pytest.approx(0.005)
    assert s.angle_sigma_rad == pytest.approx(math.radians(0.001))
    assert s.beam_divergence_rad == pytest.approx(0.35e-3)
    np.testing.assert_allclose(s.boresight_sigma_rad, np.radians([0.001, 0.002, 0.003]))
    np.testing.assert_allclose(s.lever_arm_sigma_m, [0.02] * 3)
    np.testing.assert_allclose(s.lever_arm_m, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(s.boresight_rad, [0.001] * 3)
    b = A.scanner_spec_from_dict({"base": "leica-als60", "range_sigma_cm": 3})
    assert b.range_sigma_m == pytest.approx(0.03)
    assert b.beam_divergence_rad == pytest.approx(0.22e-3)
    assert b.name == "leica-als60"


@pytest.mark.parametrize(
    "d, word",
    [
        (
            {"range_sigma_m": 0.01, "angle_sigma_rad": 1e-4, "beam_divergence_rad": 1e-3, "x": 1},
            "x",
        ),
        ({"range_sigma_deg": 0.01, "angle_sigma_rad": 1e-4, "beam_divergence_rad": 1e-3}, "unit"),
        ({"range_sigma_m": 0.01, "angle_sigma_m": 1e-4, "beam_divergence_rad": 1e-3}, "unit"),
        ({"range_sigma": 0.01, "angle_sigma_rad": 1e-4, "beam_divergence_rad": 1e-3}, "unknown"),
        ({"range_sigma_m": 0.01, "range_sigma_mm": 10, "angle_sigma_rad": 1e-4}, "more than once"),
        ({"range_sigma_m": 0.01}, "missing"),
        ({"range_sigma_m": -0.01, "angle_sigma_rad": 1e-4, "beam_divergence_rad": 1e-3}, ">= 0"),
        ({"base": "nope"}, "base"),
        ({"base": "leica-als60", "lever_arm_m": [1, 2]}, "lever_arm_m"),
    ],
)
def test_spec_from_dict_errors(d, word):
    with pytest.raises(InvalidParameterError, match=word):
        A.scanner_spec_from_dict(d)


# --------------------------------------------------------------------------- georeferencing


def test_georeference_conventions():
    # level platform heading north: scan angle > 0 looks right = east, range goes down
    p = A.georeference_points(
        platform_xyz=[[10.0, 20.0, 100.0]], roll=[0.0], pitch=[0.0], heading=[0.0],
        range_m=[50.0], scan_angle_rad=[math.radians(20)],
    )  # fmt: skip
    np.testing.assert_allclose(
        p[0], [10 + 50 * math.sin(math.radians(20)), 20, 100 - 50 * math.cos(math.radians(20))]
    )
    # heading east: right = south
    p = A.georeference_points(
        platform_xyz=[[0.0, 0.0, 0.0]], roll=[0.0], pitch=[0.0], heading=[math.pi / 2],
        range_m=[10.0], scan_angle_rad=[math.pi / 2],
    )  # fmt: skip
    np.testing.assert_allclose(p[0], [0, -10, 0], atol=1e-12)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    n = 7
    ro, pi, he = rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-3, 3, n)
    r, sc = rng.uniform(5, 200, n), rng.uniform(-0.6, 0.6, n)
    jac = A.georeferencing_jacobian(
        roll=ro, pitch=pi, heading=he, range_m=r, scan_angle_rad=sc, spec=SPEC
    )
    x0 = np.zeros((n, 14))
    x0[:, 3], x0[:, 4], x0[:, 5] = ro, pi, he
    x0[:, 6:9], x0[:, 9:12], x0[:, 12], x0[:, 13] = SPEC.boresight_rad, SPEC.lever_arm_m, r, sc

    def f(x):
        return A.georeference_points(
            platform_xyz=x[:, :3], roll=x[:, 3], pitch=x[:, 4], heading=x[:, 5],
            boresight_rad=x[:, 6:9], lever_arm_m=x[:, 9:12], range_m=x[:, 12],
            scan_angle_rad=x[:, 13],
        )  # fmt: skip

    h = 1e-6
    for k in range(14):
        xp, xm = x0.copy(), x0.copy()
        xp[:, k] += h
        xm[:, k] -= h
        np.testing.assert_allclose(jac[:, :, k], (f(xp) - f(xm)) / (2 * h), atol=1e-6)


@pytest.mark.parametrize(
    "roll, pitch, heading, scan_deg",
    [(0.0, 0.0, 0.0, 20.0), (0.05, -0.03, 1.2, 20.0), (-0.1, 0.08, -2.5, -35.0)],
)
def test_georeferencing_covariance_monte_carlo(roll, pitch, heading, scan_deg):
    rng = np.random.default_rng(11)
    m = 20_000
    sig_pos = np.array([0.02, 0.03, 0.05])
    sig_att = np.array([2e-4, 3e-4, 8e-4])
    scan = math.radians(scan_deg)
    cov = A.georeferencing_covariance(
        platform_xyz=[[500.0, 600.0, 120.0]], roll=[roll], pitch=[pitch], heading=[heading],
        range_m=[50.0], scan_angle_rad=[scan], sigma_position_m=[sig_pos],
        sigma_attitude_rad=[sig_att], spec=SPEC,
    )[0]  # fmt: skip
    z = rng.normal(size=(m, 14))
    s = np.concatenate(
        [sig_pos, sig_att, SPEC.boresight_sigma_rad, SPEC.lever_arm_sigma_m,
         [SPEC.range_sigma_m, SPEC.angle_sigma_rad]]
    )  # fmt: skip
    e = z * s
    pts = A.georeference_points(
        platform_xyz=np.array([500.0, 600.0, 120.0]) + e[:, :3], roll=roll + e[:, 3],
        pitch=pitch + e[:, 4], heading=heading + e[:, 5],
        boresight_rad=np.asarray(SPEC.boresight_rad) + e[:, 6:9],
        lever_arm_m=np.asarray(SPEC.lever_arm_m) + e[:, 9:12], range_m=50.0 + e[:, 12],
        scan_angle_rad=scan + e[:, 13],
    )  # fmt: skip
    _mc_check(np.cov(pts.T), cov)
    _assert_psd(cov[None])


def test_georeferencing_covariance_vectorised_and_broadcast():
    n = 50
    rng = np.random.default_rng(3)
    kw = dict(
        roll=rng.uniform(-0.1, 0.1, n), pitch=rng.uniform(-0.1, 0.1, n),
        heading=rng.uniform(-3, 3, n), range_m=rng.uniform(10, 300, n),
        scan_angle_rad=rng.uniform(-0.5, 0.5, n),
    )  # fmt: skip
    c = A.georeferencing_covariance(
        **kw, sigma_position_m=(0.02, 0.02, 0.04), sigma_attitude_rad=(1e-4, 1e-4, 3e-4),
        spec=A.SCANNERS["leica-als60"],
    )  # fmt: skip
    assert c.shape == (n, 3, 3)
    _assert_psd(c)
    one = A.georeferencing_covariance(
        **{k: v[7:8] for k, v in kw.items()}, sigma_position_m=[[0.02, 0.02, 0.04]],
        sigma_attitude_rad=[[1e-4, 1e-4, 3e-4]], spec=A.SCANNERS["leica-als60"],
    )  # fmt: skip
    np.testing.assert_allclose(one[0], c[7], rtol=1e-12)
    # the position variance alone enters as a diagonal
    z = A.ScannerSpec("zero", 0.0, 0.0, 0.0)
    c0 = A.georeferencing_covariance(
        **kw, sigma_position_m=(0.01, 0.02, 0.03), sigma_attitude_rad=0.0, spec=z
    )
    np.testing.assert_allclose(c0, A.axis_covariance(n, (0.01, 0.02, 0.03)), atol=1e-18)
    with pytest.raises(InvalidParameterError, match="sigma_attitude_rad"):
        A.georeferencing_covariance(
            **kw, sigma_position_m=0.01, sigma_attitude_rad=np.zeros((n, 2)), spec=z
        )
    with pytest.raises(InvalidParameterError, match="sigma_position_m"):
        A.georeferencing_covariance(**kw, sigma_position_m=-0.01, sigma_attitude_rad=0.0, spec=z)
    with pytest.raises(InvalidParameterError, match="roll"):
        A.georeferencing_covariance(
            **{**kw, "roll": np.zeros(3)}, sigma_position_m=0.01, sigma_attitude_rad=0.0, spec=z
        )
    with pytest.raises(InvalidParameterError, match="spec"):
        A.georeferencing_covariance(**kw, sigma_position_m=0.01, sigma_attitude_rad=0.0, spec={})


# --------------------------------------------------------------------------- TLS


def test_tls_covariance_monte_carlo():
    rng = np.random.default_rng(5)
    spec = A.ScannerSpec("tls", range_sigma_m=0.005, angle_sigma_rad=3e-4, beam_divergence_rad=0)
    s = np.array([100.0, 200.0, 5.0])
    targets = np.array([[130.0, 240.0, 2.0], [60.0, 190.0, 25.0], [100.0, 150.0, -3.0]])
    cov = A.tls_covariance(targets, s, spec)
    assert cov.shape == (3, 3, 3)
    _assert_psd(cov)
    m = 20_000
    for t, c in zip(targets, cov):
        d = t - s
        rho = np.linalg.norm(d)
        az, el = math.atan2(d[1], d[0]), math.atan2(d[2], math.hypot(d[0], d[1]))
        r = rho + spec.range_sigma_m * rng.normal(size=m)
        a = az + spec.angle_sigma_rad * rng.normal(size=m)
        e = el + spec.angle_sigma_rad * rng.normal(size=m)
        pts = s + r[:, None] * np.stack(
            [np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], 1
        )
        _mc_check(np.cov(pts.T), c)
        # range error along the line of sight
        u = d / rho
        assert u @ c @ u == pytest.approx(spec.range_sigma_m**2, rel=1e-9)
    c2 = A.tls_covariance(targets, s, spec, position_sigma_m=0.01)
    np.testing.assert_allclose(c2 - cov, A.constant_covariance(3, 0.01), atol=1e-15)
    with pytest.raises(InputDataError, match="scanner_position"):
        A.tls_covariance(s[None], s, spec)
    with pytest.raises(InputDataError, match="points"):
        A.tls_covariance(np.zeros((3, 2)), s, spec)


# --------------------------------------------------------------------------- footprint


def _tilted_plane(beta, half=2.0, step=0.1):
    """Grid on the plane through the origin with normal (0, -sin b, cos b) (tilted about x)."""
    g = np.arange(-half, half + 1e-9, step)
    u, v = np.meshgrid(g, g)
    u, v = u.ravel(), v.ravel()
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.array([0.0, math.cos(beta), math.sin(beta)])
    pts = u[:, None] * e1 + v[:, None] * e2
    return pts, np.array([0.0, -math.sin(beta), math.cos(beta)])


def test_footprint_zero_at_normal_incidence():
    pts, n = _tilted_plane(math.radians(30))
    sensors = pts + 80.0 * n  # every beam along the normal
    c = A.footprint_covariance(pts, sensors, SPEC)
    np.testing.assert_allclose(c, 0.0, atol=1e-15)  # rounding: sigma < 1e-7 m


def test_footprint_grows_as_tan_incidence():
    h = 100.0
    gamma = SPEC.beam_divergence_rad
    centre = None
    sig = []
    betas = np.radians([0, 10, 20, 30, 45, 60, 75])
    for beta in betas:
        pts, n = _tilted_plane(beta)
        centre = int(np.argmin(np.linalg.norm(pts, axis=1)))
        sensor = np.array([0.0, 0.0, h])  # straight above the centre point: incidence = beta
        c = A.footprint_covariance(pts, sensor, SPEC, k_neighbours=12)
        _assert_psd(c)
        # along the normal only
        cn = c[centre]
        assert n @ cn @ n == pytest.approx(np.trace(cn), rel=1e-6, abs=1e-20)
        sig.append(math.sqrt(np.trace(cn)))
        expect = A.footprint_sigma(h, beta, gamma)
        assert sig[-1] == pytest.approx(expect, rel=1e-6, abs=1e-15)
        assert expect == pytest.approx(0.5 * h * math.tan(gamma / 2) * math.tan(beta), abs=1e-15)
        # every point: sigma from its own range and incidence, with the given normals too
        d = pts - sensor
        rho = np.linalg.norm(d, axis=1)
        theta = np.arccos(np.abs(d @ n) / rho)
        np.testing.assert_allclose(
            np.sqrt(np.trace(c, axis1=1, axis2=2)), A.footprint_sigma(rho, theta, gamma),
            rtol=1e-6, atol=1e-12,
        )  # fmt: skip
        cg = A.footprint_covariance(pts, sensor, SPEC, normals=np.broadcast_to(-3 * n, pts.shape))
        np.testing.assert_allclose(cg, c, rtol=1e-6, atol=1e-15)
    sig = np.array(sig)
    assert sig[0] == pytest.approx(0.0, abs=1e-12)
    assert np.all(np.diff(sig) > 0)
    np.testing.assert_allclose(sig[1:] / sig[1], np.tan(betas[1:]) / np.tan(betas[1]), rtol=1e-6)


def test_footprint_beam_direction_and_cap():
    pts, n = _tilted_plane(math.radians(89.5))
    sensor = np.array([0.0, 0.0, 50.0])
    c = A.footprint_covariance(pts, sensor, SPEC, normals=np.broadcast_to(n, pts.shape))
    assert np.all(np.isfinite(c))
    rho = np.linalg.norm(pts - sensor, axis=1)
    cap = A.footprint_sigma(rho, math.radians(85), SPEC.beam_divergence_rad)
    sig = np.sqrt(np.trace(c, axis1=1, axis2=2))
    assert np.all(sig <= cap * (1 + 1e-9))
    assert np.isclose(sig, cap).any()  # grazing beams sit on the cap
    cb = A.footprint_covariance(
        pts, sensor, SPEC, normals=np.broadcast_to(n, pts.shape), direction="beam"
    )
    np.testing.assert_allclose(np.trace(cb, axis1=1, axis2=2), np.trace(c, axis1=1, axis2=2))
    with pytest.raises(InvalidParameterError, match="direction"):
        A.footprint_covariance(pts, sensor, SPEC, direction="x")
    with pytest.raises(InvalidParameterError, match="max_incidence_deg"):
        A.footprint_covariance(pts, sensor, SPEC, max_incidence_deg=90)
    with pytest.raises(InvalidParameterError, match="k_neighbours"):
        A.footprint_covariance(pts, sensor, SPEC, k_neighbours=2)
    with pytest.raises(InvalidParameterError, match="sensor_positions"):
        A.footprint_covariance(pts, np.zeros((2, 3)), SPEC)


def test_total_nominal_plus_surface():
    pts, n = _tilted_plane(math.radians(40))
    sensor = np.array([0.0, -30.0, 60.0])
    cn = A.tls_covariance(pts, sensor, SPEC)
    cs = A.footprint_covariance(pts, sensor, SPEC)
    t = A.total_covariance(cn, cs)
    np.testing.assert_allclose(t, cn + cs)
    _assert_psd(t)
    assert A.covariance_to_sigmas(t).shape == (pts.shape[0], 3)


# --------------------------------------------------------------------------- effect


def test_effect_heteroscedastic_slip():
    """Per-point PA matching the true noise calibrates the adjustment (sigma0² ~ 1)."""
    from slipmap.core.displacement import estimate_slip
    from slipmap.core.fault import fault_trace
    from slipmap.core.synthetic import make_fault_pair

    fp = make_fault_pair(
        "mls", seed=7, origin=(500000, 4200000, 10), right_offset_m=(0, -0.0181, 0),
        vegetation=False, noise_m=0.004,
    )  # fmt: skip
    before, after = fp.before.points, fp.after.points
    # extra isotropic noise varying 5x across the scene, within each side of the (N-S) fault
    cy = 0.5 * (after[:, 1].min() + after[:, 1].max())
    extra = np.where(after[:, 1] < cy, 0.005, 0.025)
    after = after + np.random.default_rng(0).normal(size=after.shape) * extra[:, None]
    true_sigma = np.sqrt(extra**2 + 0.004**2)
    trace = fault_trace([fp.trace_xy])
    const = float(np.sqrt(np.mean(true_sigma**2)))
    pa = A.columns_covariance(true_sigma, true_sigma, true_sigma)
    res = {}
    for name, sa in (("constant", const), ("pa", pa)):
        r = estimate_slip(before, after, trace, sigma_before=0.004, sigma_after=sa)
        err = r.relative - fp.relative_offset_m
        sig = np.sqrt(np.diag(r.relative_covariance))
        s0 = [r.left.rigid.variance_factor, r.right.rigid.variance_factor]
        res[name] = (err, sig, s0)
    err, sig, s0 = res["pa"]
    assert np.all(np.abs(err) / sig < 3.0)
    assert np.all(np.abs(err) < 1e-3)
    # the matching model is statistically consistent: sigma0² close to 1 on both sides, and
    # closer than the constant model's wherever that one is off (by more than 0.1)
    assert all(abs(v - 1.0) < 0.1 for v in s0)
    off = [(v_pa, v_c) for v_pa, v_c in zip(s0, res["constant"][2]) if abs(v_c - 1.0) > 0.1]
    assert off  # the constant model is wrong somewhere in this scene
    for v_pa, v_c in off:
        assert abs(v_pa - 1.0) < abs(v_c - 1.0)


def test_chunking_gives_same_result(monkeypatch):
    rng = np.random.default_rng(9)
    n = 40
    kw = dict(
        roll=rng.uniform(-0.1, 0.1, n), pitch=rng.uniform(-0.1, 0.1, n),
        heading=rng.uniform(-3, 3, n), range_m=rng.uniform(10, 300, n),
        scan_angle_rad=rng.uniform(-0.5, 0.5, n), sigma_position_m=rng.uniform(0, 0.05, (n, 3)),
        sigma_attitude_rad=rng.uniform(0, 1e-3, (n, 3)), spec=SPEC,
    )  # fmt: skip
    pts = rng.uniform(0, 10, (n, 3)) * [1, 1, 0.01]
    full_c = A.georeferencing_covariance(**kw)
    full_n = A.local_normals(pts, 8)
    monkeypatch.setattr(A, "_CHUNK", 7)
    np.testing.assert_allclose(A.georeferencing_covariance(**kw), full_c, rtol=1e-12)
    np.testing.assert_allclose(np.abs(A.local_normals(pts, 8)), np.abs(full_n), atol=1e-12)
