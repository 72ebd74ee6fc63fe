"""The covariance of the two sides' motions (issue #30 item 1): survey error shared across the
trace cancels in the relative displacement and in its σ (core/stochastic.cross_covariance,
core/displacement.relative_covariance)."""

from __future__ import annotations

import numpy as np
import pytest

from slipmap.core import stochastic as sto
from slipmap.core.adjustment import adjust_rigid
from slipmap.core.displacement import SideResult, _relative_covariance, relative_covariance

SLIP = np.array([0.0, -0.018, 0.0])  # right side's motion; the left side stays
SIGMA = 0.002  # point noise, m


def _geometry(seed=7, n_per_side=16):
    """Plane centres and unit normals of both sides: left x in [-60, -12], right x in
    [12, 60], y in [-30, 30]; a third roofs, a third walls, a third oblique."""
    rng = np.random.default_rng(seed)
    out = {}
    for side, sgn in (("left", -1.0), ("right", 1.0)):
        c = np.column_stack(
            [sgn * rng.uniform(12, 60, n_per_side), rng.uniform(-30, 30, n_per_side),
             rng.uniform(0, 8, n_per_side)]
        )  # fmt: skip
        nrm = []
        for i in range(n_per_side):
            kind = i % 3
            if kind == 0:
                v = np.array([*rng.normal(0, 0.3, 2), 1.0])
            elif kind == 1:
                az = rng.uniform(0, np.pi)
                v = np.array([np.sin(az), np.cos(az), 0.0])
            else:
                v = rng.normal(size=3)
            nrm.append(v / np.linalg.norm(v))
        out[side] = (c, np.array(nrm))
    return out


def _unit_of(c):
    """After-epoch unit of a plane: four strips across y, each crossing the trace (x = 0)."""
    return np.clip(((c[:, 1] + 30.0) // 15.0).astype(np.int64), 0, 3)


def _draw(geom, rng, *, unit_sigma, plane_sigma, spatial_sigma=0.0, spatial_range=40.0,
          n_per=40):  # fmt: skip
    """Points of both epochs of both sides; the after epoch carries a rigid translation per
    unit (shared by the two sides), an offset per plane and a spatial field over both sides
    (one field). Returns {side: (before, lb, after, la, unit_after)}."""
    units = rng.normal(0, unit_sigma, (4, 3))
    allc = np.concatenate([geom[s][0] for s in ("left", "right")])
    field = np.zeros_like(allc)
    if spatial_sigma:
        h = np.linalg.norm(allc[:, None] - allc[None], axis=-1)
        cov = spatial_sigma**2 * sto.spherical_correlation(h, spatial_range)
        field = np.linalg.cholesky(cov + 1e-12 * np.eye(len(allc))) @ rng.normal(size=allc.shape)
    out = {}
    off = 0
    for side in ("left", "right"):
        c, nrm = geom[side]
        u = _unit_of(c)
        move = SLIP if side == "right" else np.zeros(3)
        pts = {0: [], 1: []}
        lab = {0: [], 1: []}
        uid = []
        for i, n in enumerate(nrm):
            e1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(n, e1)
            err = n @ (units[u[i]] + field[off + i]) + rng.normal(0, plane_sigma)
            for ep in (0, 1):
                ab = rng.uniform(-3, 3, (n_per, 2))
                p = c[i] + ab[:, :1] * e1 + ab[:, 1:] * e2
                if ep:
                    p = p + move + err * n
                pts[ep].append(p + rng.normal(0, SIGMA, p.shape))
                lab[ep].append(np.full(n_per, i))
            uid.append(np.full(n_per, u[i]))
        off += len(nrm)
        out[side] = (
            np.concatenate(pts[0]), np.concatenate(lab[0]), np.concatenate(pts[1]),
            np.concatenate(lab[1]), np.concatenate(uid),
        )  # fmt: skip
    return out


def _sides(data, components, model="full"):
    res = {}
    for side, (b, lb, a, la, ua) in data.items():
        r = adjust_rigid(
            b, lb, a, la, sigma_before=SIGMA, sigma_after=SIGMA, stochastic_model=model,
            unit_after=ua, components=components, reject_outlier_planes=False,
        )  # fmt: skip
        res[side] = SideResult(side, r, None, None, None)
    return res


def test_ball_cross_correlation_is_spherical_for_equal_ranges_and_valid():
    h = np.linspace(0.0, 120.0, 241)
    np.testing.assert_allclose(
        sto.ball_cross_correlation(h, 50.0, 50.0), sto.spherical_correlation(h, 50.0), atol=1e-12
    )
    # at h = 0: (r_min / r_max)^(3/2); zero beyond the mean range; symmetric in the ranges
    assert sto.ball_cross_correlation(np.array(0.0), 20.0, 80.0) == pytest.approx(0.125)
    assert sto.ball_cross_correlation(np.array(50.0), 20.0, 80.0) == 0.0
    np.testing.assert_allclose(
        sto.ball_cross_correlation(h, 20.0, 80.0), sto.ball_cross_correlation(h, 80.0, 20.0)
    )
    # the joint covariance of two fields of ranges 20 and 80 m on random sites is PSD
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 100, (60, 3))
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    joint = np.block([
        [sto.spherical_correlation(d, 20.0), sto.ball_cross_correlation(d, 20.0, 80.0)],
        [sto.ball_cross_correlation(d, 80.0, 20.0), sto.spherical_correlation(d, 80.0)],
    ])  # fmt: skip
    assert np.linalg.eigvalsh(joint).min() > -1e-10


def test_gain_moves_the_translation_with_a_common_shift():
    """A translation of every after-epoch plane along its normal moves the motion estimate by
    that translation: Σ_j K_j n_jᵀ is ∓ the identity on the translation rows, 0 on rotations
    (so a unit seen by every plane of both sides cancels exactly in the difference)."""
    geom = _geometry()
    data = _draw(geom, np.random.default_rng(3), unit_sigma=0.003, plane_sigma=0.001)
    comps = {"plane": 0.001, "unit_after": 0.003, "spatial": 0.0}
    for side in _sides(data, comps).values():
        g = side.rigid.plane_gain
        m = g.gain @ g.normals  # (6, 3)
        np.testing.assert_allclose(np.abs(m[3:]), np.eye(3), atol=2e-3)
        np.testing.assert_allclose(m[:3], 0.0, atol=2e-5)


def test_one_unit_over_both_sides_leaves_the_relative_sigma():
    """A rigid error of one unit that covers every plane of both sides (an ALS strip across
    the whole scene) is a translation of both sides: it widens each side's σ, and the
    relative σ is what it is without it (to 2 %)."""
    geom = _geometry()
    data = _draw(geom, np.random.default_rng(4), unit_sigma=0.0, plane_sigma=0.001)
    for side in data:
        data[side] = data[side][:4] + (np.zeros_like(data[side][4]),)  # one unit
    base = _sides(data, {"plane": 0.001, "spatial": 0.0})
    with_unit = _sides(data, {"plane": 0.001, "spatial": 0.0, "unit_after": 0.01})
    c0, x0 = relative_covariance(base["left"], base["right"])
    c1, x1 = relative_covariance(with_unit["left"], with_unit["right"])
    assert x0 is not None and np.abs(x0).max() < 1e-12  # nugget only: no cross term
    side_var = np.diag(with_unit["left"].displacement_covariance)
    assert np.all(side_var > 0.9e-4)  # each side carries the 1 cm unit
    np.testing.assert_allclose(np.sqrt(np.diag(c1)), np.sqrt(np.diag(c0)), rtol=0.02)
    assert np.all(np.sqrt(np.diag(c1)) < 0.002)


def test_white_model_sides_independent():
    geom = _geometry()
    data = _draw(geom, np.random.default_rng(5), unit_sigma=0.003, plane_sigma=0.001)
    sides = _sides(data, None, model="white")
    cov, cross = relative_covariance(sides["left"], sides["right"])
    assert cross is None
    np.testing.assert_array_equal(
        cov, sides["right"].displacement_covariance + sides["left"].displacement_covariance
    )


def test_swapping_sides_keeps_the_covariance():
    geom = _geometry()
    data = _draw(geom, np.random.default_rng(6), unit_sigma=0.004, plane_sigma=0.001,
                 spatial_sigma=0.002)  # fmt: skip
    sides = _sides(data, {"plane": 0.001, "unit_after": 0.004, "spatial": 0.002,
                          "spatial_range_m": 40.0})  # fmt: skip
    c_lr, x_lr = relative_covariance(sides["left"], sides["right"])
    c_rl, x_rl = relative_covariance(sides["right"], sides["left"])
    np.testing.assert_allclose(c_lr, c_rl, rtol=1e-9, atol=1e-18)
    np.testing.assert_allclose(x_lr, x_rl.T, rtol=1e-9, atol=1e-18)
    d_lr = sides["right"].displacement - sides["left"].displacement
    d_rl = sides["left"].displacement - sides["right"].displacement
    np.testing.assert_allclose(d_lr, -d_rl)


@pytest.mark.parametrize("spatial, old_max", [(0.0, 0.55), (0.003, 0.85)])
def test_monte_carlo_spread_matches_relative_sigma(spatial, old_max):
    """30 draws of a fixed scene with 4 mm unit translations shared across the trace (and a
    3 mm spatial field of range 40 m over both sides): RMS(error/σ) of the relative
    displacement, pooled over x, y, z, is in [0.75, 1.3] with the cross term (sampling sd
    ~0.075; measured 0.98 and 1.02 with 40 draws), while the sides taken as independent give a
    σ too wide (measured RMS 0.47 and 0.75)."""
    geom = _geometry()
    comps = {"plane": 0.001, "unit_after": 0.004, "spatial": spatial}
    if spatial:
        comps["spatial_range_m"] = 40.0
    rng = np.random.default_rng(11)
    z_new, z_old = [], []
    for _ in range(30):
        data = _draw(geom, rng, unit_sigma=0.004, plane_sigma=0.001, spatial_sigma=spatial,
                     n_per=30)  # fmt: skip
        sides = _sides(data, comps)
        err = sides["right"].displacement - sides["left"].displacement - SLIP
        cov, _ = relative_covariance(sides["left"], sides["right"])
        old = sides["right"].displacement_covariance + sides["left"].displacement_covariance
        z_new.append(err / np.sqrt(np.diag(cov)))
        z_old.append(err / np.sqrt(np.diag(old)))
    rms_new = float(np.sqrt(np.mean(np.square(z_new))))
    rms_old = float(np.sqrt(np.mean(np.square(z_old))))
    assert 0.75 <= rms_new <= 1.3, rms_new
    assert rms_old < old_max, rms_old


def test_estimated_components_joint_over_both_sides():
    """Components estimated (REML), not given: 12 planes a side (each side alone below
    MIN_PLANES_VCE: a conservative prior), one set on both sides' 24 planes together
    (stochastic.joint_covariance). 16 draws of 4 mm unit translations shared across the
    trace and 1 mm plane offsets: pooled RMS(error/σ) in [0.65, 1.4] (sampling sd ~0.1 and
    the components' own estimation noise; measured 0.84 over 20 draws), and the joint unit
    component within a factor 2 of the truth in the median (measured 3.8 mm)."""
    geom = _geometry(n_per_side=12)
    rng = np.random.default_rng(21)
    z, unit_sd = [], []
    for _ in range(16):
        data = _draw(geom, rng, unit_sigma=0.004, plane_sigma=0.001, n_per=20)
        sides = _sides(data, None)
        cov, cross, joint = _relative_covariance(sides["left"], sides["right"])
        assert joint is not None and joint.n_planes == 24 and cross is not None
        err = sides["right"].displacement - sides["left"].displacement - SLIP
        z.append(err / np.sqrt(np.diag(cov)))
        unit_sd.append(np.sqrt(joint.theta["unit_after"]))
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.65 <= rms <= 1.4, rms
    assert 0.002 <= float(np.median(unit_sd)) <= 0.008, np.median(unit_sd)


def test_plane_model_sides_independent_exactly():
    """The "plane" model has only the nugget, which no two planes share: the relative
    covariance is the sum of the sides' covariances, exactly."""
    geom = _geometry()
    data = _draw(geom, np.random.default_rng(8), unit_sigma=0.0, plane_sigma=0.002)
    sides = _sides(data, None, model="plane")
    cov, cross = relative_covariance(sides["left"], sides["right"])
    np.testing.assert_array_equal(cross, 0.0)
    np.testing.assert_array_equal(
        cov, sides["right"].displacement_covariance + sides["left"].displacement_covariance
    )
