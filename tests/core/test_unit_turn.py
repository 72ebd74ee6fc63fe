"""Acquisition units that turn about their origins as well as translate (issue #30, stop 44;
core.stochastic UNIT_LEVERS_M): the design against the rigid motion it stands for, the
origins, the contrast rows' positions and their frames, and REML choosing a lever where the
units turn and none where they only translate (known answers)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from slipmap.core import stochastic as sto
from slipmap.core.unit_contrasts import ContrastRows, epoch_rows, unit_contrasts


def test_turn_design_is_the_rigid_motion_along_the_normal():
    """The design's columns times (s_u, L ω_u) per unit are Σ_u share nᵀ(s_u + ω_u × (c − o_u))
    for random shares, positions, origins and motions."""
    rng = np.random.default_rng(1)
    n, v, lever = 40, 4, 37.0
    shares = rng.uniform(-1, 1, (n, v))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    pos = rng.uniform(-80, 80, (n, 3))
    org = rng.uniform(-80, 80, (v, 3))
    s = rng.normal(0, 0.003, (v, 3))
    w = rng.normal(0, 1e-4, (v, 3))
    z = sto._share_design(shares, nrm, pos, org, lever)
    assert z.shape == (n, 6 * v)
    got = z @ np.concatenate([s, lever * w], axis=1).ravel()
    want = np.zeros(n)
    for i in range(n):
        for u in range(v):
            want[i] += shares[i, u] * nrm[i] @ (s[u] + np.cross(w[u], pos[i] - org[u]))
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    # no lever (or no positions): the translations alone, as before
    np.testing.assert_array_equal(sto._share_design(shares, nrm), sto._share_design(
        shares, nrm, pos, org, math.inf))  # fmt: skip


def test_unit_origins_are_the_share_weighted_centroids_of_planes_and_rows():
    rng = np.random.default_rng(2)
    c = rng.uniform(-50, 50, (6, 3))
    nrm = np.tile([0.0, 0.0, 1.0], (6, 1))
    sb = np.array([[1, 0], [1, 0], [0.5, 0.5], [0, 1], [0, 1], [0, 1.0]])
    rows = ContrastRows(
        np.zeros(1), np.ones(1), nrm[:1], np.array([[1.0, -1.0]]), None,
        position=np.array([[10.0, 20.0, 30.0]]),
    )  # fmt: skip
    model = sto.PlaneModel(c, nrm, sb, None, contrasts=rows)
    o = model.unit_origins("unit_before")
    w = np.vstack([sb, [[1.0, 1.0]]])
    cc = np.vstack([c, rows.position])
    np.testing.assert_allclose(o, (w.T @ cc) / w.sum(axis=0)[:, None], rtol=1e-12)
    assert model.unit_origins("unit_after") is None


def _two_unit_planes(rng, b=5, per=200):
    pts, lab, unit = [], [], []
    for j in range(b):
        c = rng.uniform(-30, 30, 3)
        a, bb = rng.uniform(-3, 3, (2, 2 * per))
        x = c + np.column_stack([a, bb, 0.1 * a + rng.normal(0, 0.003, a.size)])
        pts.append(x)
        lab.append(np.full(x.shape[0], j))
        unit.append(np.repeat([1, 2], per))
    return np.vstack(pts), np.concatenate(lab), np.concatenate(unit)


def test_row_positions_are_the_mean_of_the_two_groups_centroids():
    rng = np.random.default_rng(3)
    x, lab, unit = _two_unit_planes(rng)
    con = unit_contrasts(lab, x, unit, 5)
    assert con.size == 5
    for r, p in enumerate(con.plane):
        m = lab == p
        want = 0.5 * (x[m & (unit == 1)].mean(axis=0) + x[m & (unit == 2)].mean(axis=0))
        np.testing.assert_allclose(con.position[r], want, atol=1e-9)
    # the rows in a frame centred on ``centre``: the positions less it
    rows = epoch_rows((con, None), (np.array([1, 2]), None), centre=np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(rows.position, con.position - [1.0, 2.0, 3.0])


def _turning_problem(rng, lever_true, k=60, units=6, m=60):
    """Planes over a 200 m square seen by ``units`` setups each (the nearest's share 1), unit
    errors of 3 mm and, when ``lever_true`` is finite, a turn of 3 mm / lever_true rad per
    axis about the unit's points' centroid; rows between neighbouring setups."""
    c = np.column_stack([rng.uniform(0, 200, k), rng.uniform(0, 200, k), rng.uniform(0, 15, k)])
    nrm = rng.normal(size=(k, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    site = np.column_stack([rng.uniform(20, 180, units), rng.uniform(20, 180, units)])

    def owner(xy):
        return np.argmin(((xy[:, None, :] - site[None]) ** 2).sum(axis=2), axis=1)

    sb = np.eye(units)[owner(c[:, :2])]
    sa = np.eye(units)[owner(c[:, :2] + rng.normal(0, 30, (k, 2)))]
    rp = np.column_stack([rng.uniform(0, 200, (m, 2)), rng.uniform(0, 15, m)])
    rn = rng.normal(size=(m, 3))
    rn /= np.linalg.norm(rn, axis=1)[:, None]
    cb, ca = np.zeros((m, units)), np.zeros((m, units))
    for r in range(m):
        d = ((rp[r, :2] - site) ** 2).sum(axis=1)
        u, w = np.argsort(d)[:2]
        (cb if r % 2 else ca)[r, [u, w]] = (1.0, -1.0)
    rows = ContrastRows(np.zeros(m), np.full(m, 1e-6), rn, cb, ca, position=rp)
    model = sto.PlaneModel(c, nrm, sb, sa, contrasts=rows)
    p = np.full(k, 1e-6)
    theta = {"plane": 1e-6, "unit_before": 9e-6, "unit_after": 9e-6}
    truth = model.with_unit_lever(lever_true)
    idx = np.arange(k)
    v = sto.covariance_with_contrasts(truth, idx, p, theta, float("nan"), None, rows)
    y = np.linalg.cholesky(v) @ rng.normal(size=v.shape[0])
    model = replace(model, contrasts=replace(rows, value=y[k:]))
    x = np.column_stack([np.cross(c - c.mean(axis=0), nrm), nrm])
    return model, idx, y[:k], x, p


@pytest.mark.parametrize("lever_true", [30.0, math.inf])
def test_reml_chooses_a_lever_where_the_units_turn_and_none_where_they_translate(
    lever_true, monkeypatch
):
    """Twelve draws of each: units that turn by 0.1 mrad beside a 3 mm translation (lever
    30 m) take a lever of 15-60 m in at least 10; units that only translate keep none in at
    least 10 (the margin of UNIT_INTERVAL_MARGIN in −2 log L). With the turn switched off
    (UNIT_TURN False) no lever is ever chosen."""
    kw = dict(which=("plane", "unit_before", "unit_after"), fixed={})
    levers = []
    for seed in range(12):
        rng = np.random.default_rng(700 + seed)
        model, idx, e, x, p = _turning_problem(rng, lever_true)
        est = sto.estimate_components(model, idx, e, x, np.zeros((6, 6)), p, **kw)
        levers.append(est.unit_lever_m)
    levers = np.array(levers)
    if math.isfinite(lever_true):
        assert np.sum((levers >= 15.0) & (levers <= 60.0)) >= 10, levers
    else:
        assert np.sum(np.isinf(levers)) >= 10, levers
    monkeypatch.setattr(sto, "UNIT_TURN", False)
    est = sto.estimate_components(model, idx, e, x, np.zeros((6, 6)), p, **kw)
    assert math.isinf(est.unit_lever_m)


def test_a_held_lever_is_kept_and_checked():
    rng = np.random.default_rng(9)
    model, idx, e, x, p = _turning_problem(rng, 30.0)
    kw = dict(which=("plane", "unit_before", "unit_after"))
    est = sto.estimate_components(
        model, idx, e, x, np.zeros((6, 6)), p, fixed={"unit_lever_m": 120.0}, **kw
    )
    assert est.unit_lever_m == 120.0
    assert sto.check_components({"unit_lever_m": 40})["unit_lever_m"] == 40.0
    with pytest.raises(sto.InvalidParameterError, match="unit_lever_m must be > 0 metres"):
        sto.check_components({"unit_lever_m": 0})


def _strip_planes(rng, n, per, jitter_m):
    """:func:`random_planes` seen by four 25 m strips along x whose edges are blurred by
    ``jitter_m``: the points (N, 3), their planes and their strips (0-3)."""
    from test_unit_contrasts import random_planes

    planes = random_planes(rng, n, per)
    p = np.vstack(planes)
    lab = np.repeat(np.arange(n), per)
    unit = np.clip(np.floor((p[:, 0] + rng.normal(0, jitter_m, p.shape[0])) / 25.0), 0, 3)
    return p, lab, unit.astype(np.int64)


def test_own_and_given_contrasts_are_one_model_in_the_adjustment():
    """The adjustment's own rows (positions in its centred frame) and the same rows given
    in the points' frame (the survey's, estimate_slip) make the same model: the same lever
    and the same motion, on strips that turn."""
    from slipmap.core.adjustment import adjust_rigid

    rng = np.random.default_rng(5)
    p, lab, unit = _strip_planes(rng, 30, 600, 2.0)
    w = rng.normal(0, 2e-4, (4, 3))
    turn = np.cross(w[unit], p - np.array([[12.5 + 25 * u, 20, 5] for u in range(4)])[unit])
    before = p + rng.normal(0, 0.004, p.shape) + [500000.0, 4200000.0, 10.0]
    after = p + rng.normal(0, 0.004, p.shape) + turn + [500000.0, 4200000.0, 10.0]
    kw = dict(sigma_before=0.004, sigma_after=0.004, stochastic_model="full",
              unit_before=unit, unit_after=unit)  # fmt: skip
    own = adjust_rigid(before, lab, after, lab, **kw)
    given = tuple(unit_contrasts(lab, x, unit, 30) for x in (before, after))
    res = adjust_rigid(before, lab, after, lab, unit_contrasts=given, **kw)
    vo, vg = own.variance_components, res.variance_components
    assert vo.n_contrasts == vg.n_contrasts and vo.n_contrasts[1] > 0
    assert vo.unit_lever_m == vg.unit_lever_m
    np.testing.assert_allclose(res.params, own.params, atol=1e-9)
    np.testing.assert_allclose(res.sigma, own.sigma, rtol=1e-6)


def _strips_two_sides(seed, turn_rad=2e-4):
    """Planes over 100 m seen by four 25 m strips with overlaps, split at x = 50 m into two
    sides; the after epoch's strips offset by 1 cm and turned by ``turn_rad`` per axis."""
    rng = np.random.default_rng(seed)
    p, lab, unit = _strip_planes(rng, 40, 500, 3.0)
    origin = np.array([[12.5 + 25 * u, 20.0, 5.0] for u in range(4)])
    s, w = rng.normal(0, 0.01, (4, 3)), rng.normal(0, turn_rad, (4, 3))
    off = [500000.0, 4200000.0, 10.0]
    before = p + rng.normal(0, 0.004, p.shape) + off
    after = p + rng.normal(0, 0.004, p.shape) + s[unit] + np.cross(w[unit], p - origin[unit])
    after += off
    centre = np.array([np.mean(p[lab == j, 0]) for j in range(40)])
    return before, after, lab, unit, centre < 50.0


@pytest.mark.parametrize("lever", [math.inf, 40.0])
def test_cross_side_fallback_is_the_joint_models_cross_block(lever):
    """Two sides of one strip survey, their units tied on the survey's rows and their
    components held alike: the fallback cross term (cross_covariance, used beside fewer than
    15 or more than 1500 planes) equals the joint model's cross block K̃_a V K̃_bᵀ over planes
    and rows (one copy of the rows, the units' turn about one origin), to rounding."""
    from slipmap.core.adjustment import adjust_rigid

    before, after, lab, unit, left = _strips_two_sides(4)
    given = tuple(unit_contrasts(lab, x, unit, 40) for x in (before, after))
    comps = {"plane": 0.001, "spatial": 0.0, "unit_before": 0.004, "unit_after": 0.008}
    if math.isfinite(lever):
        comps["unit_lever_m"] = lever
    gains = []
    for side in (left, ~left):
        m = side[lab]
        sub = np.cumsum(side) - 1  # the side's planes renumbered
        res = adjust_rigid(
            before[m], sub[lab[m]], after[m], sub[lab[m]], sigma_before=0.004,
            sigma_after=0.004, stochastic_model="full", unit_before=unit[m],
            unit_after=unit[m], components=comps, unit_contrasts=given,
        )  # fmt: skip
        assert res.variance_components.unit_lever_m == lever
        gains.append(res.plane_gain)
    ga, gb = gains
    assert ga.contrasts.same_rows(gb.contrasts) and ga.contrast_gain is not None
    rows, shared = sto._union_contrasts(ga, gb)
    assert shared
    model = sto.PlaneModel(
        np.vstack([ga.centroids, gb.centroids]), np.vstack([ga.normals, gb.normals]),
        sto._union_shares(ga, gb, "before"), sto._union_shares(ga, gb, "after"),
        contrasts=rows, unit_lever_m=lever,
    )  # fmt: skip
    theta = {n: ga.theta[n] for n in ("plane", "unit_before", "unit_after")}
    assert all(gb.theta[n] == pytest.approx(v) for n, v in theta.items())
    theta[sto.CONTRAST_NUGGET] = math.sqrt(
        ga.theta.get(sto.CONTRAST_NUGGET, 0.0) * gb.theta.get(sto.CONTRAST_NUGGET, 0.0)
    )
    ka, kb = ga.gain.shape[1], gb.gain.shape[1]
    k = ka + kb
    v = sto.covariance_with_contrasts(
        model, np.arange(k), np.zeros(k), theta, float("nan"), None, rows
    )
    kj = np.zeros((12, k + rows.size))
    kj[:6, :ka], kj[6:, ka:k] = ga.gain, gb.gain
    kj[:6, k:], kj[6:, k:] = ga.contrast_gain, gb.contrast_gain
    want = (kj @ v @ kj.T)[:6, 6:]
    got = sto.cross_covariance(ga, gb) / math.sqrt(ga.small_sample_factor * gb.small_sample_factor)
    scale = np.sqrt(np.outer(np.diag(kj[:6] @ v @ kj[:6].T), np.diag(kj[6:] @ v @ kj[6:].T)))
    np.testing.assert_allclose(got / scale, want / scale, atol=1e-9)
    assert np.abs(want[3:, 3:]).max() > 1e-7  # the units carry a cross term at all
