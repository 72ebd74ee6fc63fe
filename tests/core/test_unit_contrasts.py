"""Acquisition units seen apart on one plane (issue #30, core.unit_contrasts): the fast fit
against a slow least-squares reference, known offsets recovered with an honest variance, the
shares of the rows, and an airborne pair whose σ left out the strips' error (known answers)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipmap.core.unit_contrasts import (
    MIN_GROUP_POINTS,
    epoch_rows,
    unit_contrasts,
    unit_contrasts_reference,
    with_contrast_units,
)
from slipmap.core.unit_drift import hat_unit_shares_reference


def _planes(rng, b=8, per=(20, 300), n_units=3, offsets=None, noise=0.003, tilt=True):
    """Points of ``b`` planes of random orientation, each seen by 1-3 units whose points are
    moved by the units' ``offsets`` (U, 3); returns plane, points, unit, normals."""
    nrm = rng.normal(size=(b, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    offsets = np.zeros((n_units, 3)) if offsets is None else offsets
    plane, pts, unit = [], [], []
    for j in range(b):
        t1 = np.cross(nrm[j], [0.3, 0.2, 1.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(nrm[j], t1)
        centre = rng.uniform(-50, 50, 3)
        us = rng.choice(n_units, rng.integers(1, n_units + 1), replace=False)
        for u in us:
            n = int(rng.integers(*per))
            a, c = rng.uniform(-5, 5, (2, n))
            if tilt:  # each unit sees its own part of the plane (a tilt must not absorb it)
                a = a * 0.5 + (2.0 if u % 2 else -2.0)
            x = centre + a[:, None] * t1 + c[:, None] * t2
            x += offsets[u] + rng.normal(0, noise, (n, 1)) * nrm[j]
            plane.append(np.full(n, j))
            pts.append(x)
            unit.append(np.full(n, u + 1))
    return np.concatenate(plane), np.vstack(pts), np.concatenate(unit), nrm


def test_fast_fit_matches_the_slow_least_squares():
    rng = np.random.default_rng(4)
    plane, pts, unit, _ = _planes(rng, b=14, offsets=rng.normal(0, 0.01, (3, 3)))
    con = unit_contrasts(plane, pts, unit, 14)
    ref = unit_contrasts_reference(plane, pts, unit, 14)
    assert con.size == len(ref) > 3
    assert set(con.plane.tolist()) == set(ref)
    for p, v, var, n in zip(con.plane, con.value, con.var, con.normal):
        rv, rvar, rn = ref[int(p)]
        sign = float(rn @ n)  # the normal's sign is free: the offset along it
        assert abs(sign) == pytest.approx(1.0, abs=1e-9)
        assert v * sign == pytest.approx(rv, rel=1e-9, abs=1e-12)
        assert var == pytest.approx(rvar, rel=1e-9)


def test_small_groups_and_one_unit_planes_give_no_row():
    rng = np.random.default_rng(5)
    plane, pts, unit, _ = _planes(rng, b=10, per=(5, MIN_GROUP_POINTS))
    con = unit_contrasts(plane, pts, unit, 10)
    assert con.size == 0 and con.point_index.size == 0


def test_known_offsets_recovered_with_an_honest_variance():
    """Offsets of known units along each plane's normal, over 40 draws: the rows' errors
    over their σ have RMS 1 (within sampling), and a tilt does not absorb the offset of two
    units that see two halves of a plane."""
    z = []
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        off = rng.normal(0, 0.02, (3, 3))
        plane, pts, unit, nrm = _planes(rng, b=6, offsets=off, noise=0.004)
        con = unit_contrasts(plane, pts, unit, 6)
        for r in range(con.size):
            ga, gb = con.row_groups[r]
            ua = con.point_unit[con.point_group == ga][0]
            ub = con.point_unit[con.point_group == gb][0]
            truth = con.normal[r] @ (off[ua - 1] - off[ub - 1])
            z.append((con.value[r] - truth) / math.sqrt(con.var[r]))
    z = np.asarray(z)
    assert z.size > 60
    assert 0.8 < math.sqrt(np.mean(z**2)) < 1.2
    assert np.max(np.abs(z)) < 4.5


@pytest.mark.parametrize("interval", [math.inf, 6.0])
def test_row_shares_are_the_groups_share_differences(interval):
    rng = np.random.default_rng(6)
    plane, pts, unit, _ = _planes(rng, b=9)
    time = 300_000.0 + 40.0 * unit + rng.uniform(0, 20, unit.size)
    con = unit_contrasts(plane, pts, unit, 9, time_s=time)
    s, ids = con.shares(interval)
    i = con.point_index
    np.testing.assert_array_equal(con.point_unit, unit[i])
    np.testing.assert_array_equal(con.point_time, time[i])
    g_count = np.bincount(con.point_group).astype(float)
    ref, ref_ids = hat_unit_shares_reference(
        con.point_group, unit[i], time[i], g_count, interval_s=interval
    )
    np.testing.assert_array_equal(ids, ref_ids)
    np.testing.assert_allclose(s, ref[con.row_groups[:, 0]] - ref[con.row_groups[:, 1]])
    np.testing.assert_allclose(s.sum(axis=1), 0.0, atol=1e-12)  # a contrast of two groups
    # each row's groups are one unit of one plane
    for ga, gb in con.row_groups:
        for g in (ga, gb):
            assert np.unique(con.point_unit[con.point_group == g]).size == 1
            assert np.unique(plane[i][con.point_group == g]).size == 1


def test_rows_in_the_epochs_columns_and_widened_by_the_contrasts_units():
    """The rows' shares sit in the epoch's unit columns; a unit the contrasts see that no
    plane of the adjustment holds (a strip of the other side of a fault) gets a column of
    its own, zero on the planes."""
    rng = np.random.default_rng(7)
    plane, pts, unit, _ = _planes(rng, b=9)
    con = unit_contrasts(plane, pts, unit, 9)
    seen = np.unique(con.point_unit)
    codes = seen[:-1]  # the adjustment's planes lack the last unit the contrasts see
    shares = np.ones((4, codes.size)) / codes.size
    pairs, drift = with_contrast_units((con, None), [(shares, codes), (None, None)], None)
    (sb, cb), (sa, ca) = pairs
    np.testing.assert_array_equal(cb, seen)
    np.testing.assert_allclose(sb[:, :-1], shares)
    assert np.all(sb[:, -1] == 0) and sa is None and drift is None
    rows = epoch_rows((con, None), (cb, None))
    assert rows.shares_after is None and rows.size == con.size
    s, ids = con.shares(math.inf)
    np.testing.assert_allclose(rows.shares_before[:, np.searchsorted(cb, ids)], s)


@pytest.mark.slow
def test_airborne_pair_strips_tied_across_the_fault():
    """The airborne pair of seed 2024 (issue #30's ALS kind, docs/accuracy.md "Units tied on
    the planes they share"): with 10 planes on one side, the strips' errors were absorbed by
    the sides' motions, REML put the unit components at zero, and the slip's vertical error
    of 17.5 mm had σ 3.9 mm (4.5σ). Tied on the roofs their overlaps share, the strips'
    errors are estimated and taken off: the vertical error falls below 10 mm, every
    component within 2.5σ, the joint unit components estimated."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import accuracy_slip as A

    from slipmap.core.displacement import estimate_slip
    from slipmap.core.fault import fault_trace

    fp = A.draw_pair("als-1cm-roll", 2024)
    out = {}
    for tied in (False, True):
        res = estimate_slip(
            fp.before.points, fp.after.points, fault_trace([fp.trace_xy]),
            sigma_before=fp.before.noise_m, sigma_after=fp.after.noise_m,
            unit_before=fp.source_before.astype(np.int64),
            unit_after=fp.source_after.astype(np.int64),
            unit_time_before=fp.gps_time_before, unit_time_after=fp.gps_time_after,
            unit_contrasts=tied,
        )  # fmt: skip
        comp = res.components()
        err = np.asarray(A._errors(res.relative, fp.relative_offset_m, res.strike_rad))
        sig = np.array([comp["sigma_fault_parallel"], comp["sigma_fault_normal"], comp["sigma_dz"]])
        out[tied] = (err, sig, res)
    err, sig, _ = out[False]
    assert abs(err[2]) > 0.015 and abs(err[2] / sig[2]) > 4.0  # the false claim, untied
    err, sig, res = out[True]
    assert abs(err[2]) < 0.010
    assert np.all(np.abs(err / sig) < 2.5)
    jc = res.joint_components
    assert jc.source["unit_before"] == "estimated"
    assert math.sqrt(jc.theta["unit_before"]) + math.sqrt(jc.theta["unit_after"]) > 5e-3
    for side in (res.left, res.right):
        assert min(side.rigid.variance_components.n_contrasts) > 0


def _conditioned_problem(rng, k=24, m=30, units=5):
    from slipmap.core import stochastic as sto
    from slipmap.core.unit_contrasts import ContrastRows

    c = rng.uniform(-50, 50, (k, 3))
    nrm = rng.normal(size=(k, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]

    def shares(n):
        s = rng.uniform(size=(n, units)) * (rng.uniform(size=(n, units)) < 0.5)
        s[np.arange(n), rng.integers(units, size=n)] += 0.5
        return s / s.sum(axis=1)[:, None]

    sb, sa = shares(k), shares(k)
    cb = np.zeros((m, units))
    ca = np.zeros((m, units))
    for r in range(m):  # a row of either epoch: the difference of two units' shares
        u, w = rng.choice(units, 2, replace=False)
        (cb if r % 2 else ca)[r, [u, w]] = (1.0, -1.0)

    cn = rng.normal(size=(m, 3))
    cn /= np.linalg.norm(cn, axis=1)[:, None]
    rows = ContrastRows(rng.normal(0, 0.01, m), rng.uniform(1e-6, 4e-6, m), cn, cb, ca)
    model = sto.PlaneModel(c, nrm, sb, sa, contrasts=rows)
    theta = {"plane": 1e-6, "unit_before": 4e-5, "unit_after": 9e-5, "spatial": 4e-6,
             sto.CONTRAST_NUGGET: 2e-6}  # fmt: skip
    x = rng.normal(size=(k, 6))
    e = rng.normal(0, 0.01, k)
    p = rng.uniform(1e-6, 3e-6, k)
    return sto, model, rows, theta, x, e, p


@pytest.mark.parametrize("sparse", [False, True])
def test_conditioned_gls_is_the_stacked_gls(sparse, monkeypatch):
    """The motion from the misclosures with the units' predicted errors taken off and their
    covariance given the contrasts (ContrastCondition, dense and sparse Woodbury) equals the
    slow stacked GLS of misclosures and contrast rows (zero design on the rows, the rows'
    misfit nugget on their diagonal), estimate and covariance."""
    rng = np.random.default_rng(8)
    sto, model, rows, theta, x, e, p = _conditioned_problem(rng)
    k = e.size
    idx = np.arange(k)
    kern = sto.SpatialKernel("spherical", 40.0)
    v_ext = sto.covariance_with_contrasts(model, idx, p, theta, kern, None, rows)
    x_ext = np.vstack([x, np.zeros((rows.size, 6))])
    vi = np.linalg.inv(v_ext)
    n_ref = x_ext.T @ vi @ x_ext
    b_ref = np.linalg.solve(n_ref, x_ext.T @ vi @ np.concatenate([e, rows.value]))
    if sparse:
        monkeypatch.setattr(sto, "DENSE_MAX_PLANES", 5)
    cond = sto.condition_on_contrasts(model, idx, theta)
    op = sto.CovarianceOperator(model, idx, p, theta, kern, None, condition=cond)
    assert op.sparse == sparse
    vix = op.solve(x)
    n_c = x.T @ vix
    b_c = np.linalg.solve(n_c, vix.T @ (e - cond.shift))
    np.testing.assert_allclose(b_c, b_ref, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(np.linalg.inv(n_c), np.linalg.inv(n_ref), rtol=1e-8)
    # the gain on the rows (-K z g) is the stacked GLS's on them
    gain = np.linalg.inv(n_c) @ vix.T
    k_ref = np.linalg.inv(n_ref) @ x_ext.T @ vi
    np.testing.assert_allclose(gain, k_ref[:, :k], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(-gain @ cond.z @ cond.g, k_ref[:, k:], rtol=1e-7, atol=1e-9)


def random_planes(rng, n=30, per=600):
    """``n`` square planes of 8 m (``per`` points each, no noise) of random upward-facing
    normals, their centres over 100 × 40 × 10 m."""
    out = []
    for _ in range(n):
        nrm = rng.normal(size=3)
        nrm[2] = abs(nrm[2]) + 0.5
        nrm /= np.linalg.norm(nrm)
        t1 = np.cross(nrm, [0.0, 0.0, 1.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(nrm, t1)
        c = np.array([rng.uniform(5, 95), rng.uniform(0, 40), rng.uniform(0, 10)])
        a, b = rng.uniform(-4, 4, (2, per))
        out.append(c + a[:, None] * t1 + b[:, None] * t2)
    return out


def _strip_scene(seed, offsets_m, n=30):
    """``n`` planes over 100 m seen by four 25 m strips with 5 m overlaps; the after epoch's
    strips offset by ``offsets_m`` (4, 3); no ground motion."""
    rng = np.random.default_rng(seed)
    pts, lab, unit = [], [], []
    for j, x in enumerate(random_planes(rng, n)):
        u = np.clip(np.floor(x[:, 0] / 25.0), 0, 3).astype(int)
        edge = np.abs(x[:, 0] - 25.0 * np.round(x[:, 0] / 25.0)) < 2.5
        near = np.clip(np.round(x[:, 0] / 25.0).astype(int), 1, 3)
        flip = edge & (rng.uniform(size=x.shape[0]) < 0.5)
        u = np.where(flip, np.where(u == near, near - 1, near), u)
        pts.append(x)
        lab.append(np.full(x.shape[0], j))
        unit.append(u + 1)
    p, lab, unit = np.vstack(pts), np.concatenate(lab), np.concatenate(unit)
    before = p + rng.normal(0, 0.005, p.shape)
    after = p + rng.normal(0, 0.005, p.shape) + offsets_m[unit - 1]
    return before, after, lab, unit


def test_strip_offsets_tied_across_a_fault_by_the_planes_overlaps():
    """A strip adjustment inside the slip's: four after-epoch strips offset by 1.5 cm each
    across two sides of a fault (x < 50 m, x > 50 m), 80 planes, no ground motion. Each side's
    motion absorbs its strips' mean, so the slip (right minus left, at one centre) carries
    their difference; the planes the strips share in their overlaps, on both sides, tie
    them, and the slip's error falls to a fraction, within its σ, over eight draws."""
    from slipmap.core import stochastic as sto
    from slipmap.core.adjustment import adjust_rigid

    centre = np.array([50.0, 20.0, 5.0])
    err_with, err_without, z = [], [], []
    for seed in range(8):
        off = np.random.default_rng(50 + seed).normal(0, 0.015, (4, 3))
        before, after, lab, unit = _strip_scene(seed, off, n=80)
        survey = tuple(
            unit_contrasts(lab, pts, unit, 80) for pts in (before, after)
        )  # every plane of both sides
        # the random tilt (the default) lets the planes a strip boundary crosses, whose
        # fitted tilt the two strips' offsets bend, disagree with the rotation
        kw = dict(sigma_before=0.005, sigma_after=0.005, stochastic_model="full",
                  centre=centre)  # fmt: skip
        slip = {}
        for contrasts in (survey, (None, None)):
            res = []
            left = np.isin(lab, np.flatnonzero(_plane_x(before, lab) < 50.0))
            for m in (left, ~left):
                res.append(adjust_rigid(before[m], lab[m], after[m], lab[m],
                                        unit_before=unit[m], unit_after=unit[m],
                                        unit_contrasts=contrasts, **kw))  # fmt: skip
            d = res[1].params[3:] - res[0].params[3:]
            # both sides' covariance under one joint model, the contrasts' gains included
            c12, _ = sto.joint_covariance(res[0].plane_gain, res[1].plane_gain)
            cov = c12[3:6, 3:6] + c12[9:12, 9:12] - c12[3:6, 9:12] - c12[9:12, 3:6]
            slip[contrasts is survey] = (d, cov)
        d, cov = slip[True]
        err_with.append(np.linalg.norm(d))
        err_without.append(np.linalg.norm(slip[False][0]))
        z.extend(d / np.sqrt(np.diag(cov)))
    rms_with = math.sqrt(np.mean(np.square(err_with)))
    rms_without = math.sqrt(np.mean(np.square(err_without)))
    assert rms_with < 0.25 * rms_without
    assert 0.2 < math.sqrt(np.mean(np.square(z))) < 1.5


def _plane_x(points, lab):
    """(b,) x of each plane's centroid."""
    return np.bincount(lab, points[:, 0]) / np.bincount(lab)


def test_a_gross_contrast_is_left_out():
    """A car parked on one plane in one unit's pass: its contrast 0.3 m off is left out, the
    others kept; rows within the spread are never touched."""
    from dataclasses import replace

    from slipmap.core.unit_contrasts import screen_contrasts

    rng = np.random.default_rng(9)
    plane, pts, unit, _ = _planes(rng, b=16, offsets=rng.normal(0, 0.01, (3, 3)))
    con = unit_contrasts(plane, pts, unit, 16)
    assert con.size >= 6
    assert screen_contrasts(con) is con  # nothing gross
    bad = con.value.copy()
    bad[2] += 0.3
    out = screen_contrasts(replace(con, value=bad))
    assert out.size == con.size - 1
    np.testing.assert_array_equal(out.value, np.delete(bad, 2))
    np.testing.assert_array_equal(out.row_groups, np.delete(con.row_groups, 2, axis=0))


def test_reml_recovers_the_unit_components_from_the_contrasts():
    """Known components drawn over misclosures and contrast rows together (the stacked
    covariance): REML on both recovers the unit components (truth 5 and 3 mm) within 35 %
    in the median of 12 draws, where the 12 planes' misclosures alone, each side's motion
    absorbing most of the units, set them to zero or far off more often."""
    from dataclasses import replace

    from slipmap.core import stochastic as sto

    truth = {"plane": 1e-6, "unit_before": 2.5e-5, "unit_after": 0.9e-5}
    got, alone = [], []
    for seed in range(12):
        rng = np.random.default_rng(300 + seed)
        _, model, rows, _, x, _, p = _conditioned_problem(rng, k=12, m=80, units=5)
        idx = np.arange(p.size)
        v = sto.covariance_with_contrasts(model, idx, p, truth, float("nan"), None, rows)
        y = np.linalg.cholesky(v) @ rng.normal(size=v.shape[0])
        e, c = y[: p.size], y[p.size :]
        model = replace(model, contrasts=replace(rows, value=c))
        kw = dict(which=("plane", "unit_before", "unit_after"), fixed={})
        est = sto.estimate_components(model, idx, e, x, np.zeros((6, 6)), p, **kw)
        got.append([est.theta["unit_before"], est.theta["unit_after"]])
        est0 = sto.estimate_components(replace(model, contrasts=None), idx, e, x,
                                       np.zeros((6, 6)), p, **kw)  # fmt: skip
        alone.append([est0.theta["unit_before"], est0.theta["unit_after"]])
    med = np.sqrt(np.median(np.asarray(got), axis=0))
    np.testing.assert_allclose(med, [5e-3, 3e-3], rtol=0.35)
    err = np.abs(np.log(np.sqrt(np.maximum(got, 1e-12)) / [5e-3, 3e-3]))
    err0 = np.abs(np.log(np.sqrt(np.maximum(alone, 1e-12)) / [5e-3, 3e-3]))
    assert np.median(err) < np.median(err0)


def test_the_slip_progress_runs_forward_when_both_sides_are_segmented_first():
    """Tying the units segments both sides before either is adjusted; the progress a QGIS
    dialog shows still only moves forward, from the first report to 1."""
    from slipmap.core.displacement import estimate_slip
    from slipmap.core.fault import fault_trace
    from slipmap.core.synthetic import SurveyError, make_fault_pair

    err = SurveyError(kind="mls", level_m=0.003)
    fp = make_fault_pair(
        "mls", seed=11, origin=(500000.0, 4200000.0, 10.0), n_buildings=4, extent_m=70.0,
        right_offset_m=(0.0, -0.0181, 0.0), error_before=err, error_after=err,
    )  # fmt: skip
    seen = []
    res = estimate_slip(
        fp.before.points, fp.after.points, fault_trace([fp.trace_xy]),
        sigma_before=0.02, sigma_after=0.02, unit_before=fp.source_before.astype(np.int64),
        unit_after=fp.source_after.astype(np.int64), progress=lambda f, m: seen.append(f),
    )  # fmt: skip
    assert min(res.left.rigid.variance_components.n_contrasts) > 0  # the tied path
    assert len(seen) > 10 and seen[-1] == pytest.approx(1.0)
    assert all(b >= a for a, b in zip(seen, seen[1:]))
