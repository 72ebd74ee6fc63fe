"""Fault slip on synthetic fault pairs with a known offset (Kusari et al. 2019 workflow)."""

import numpy as np
import pytest

from slipmap.core.displacement import estimate_slip
from slipmap.core.errors import InputDataError
from slipmap.core.fault import fault_trace
from slipmap.core.synthetic import make_fault_pair

ORIGIN = (500000.0, 4200000.0, 10.0)
NLOD = 0.0181  # the study's alinement-array slip (m)


def _run(fp, sigma, **kw):
    return estimate_slip(
        fp.before.points,
        fp.after.points,
        fault_trace([fp.trace_xy]),
        sigma_before=sigma,
        sigma_after=sigma,
        **kw,
    )


@pytest.fixture(scope="module")
def mls_pair():
    return make_fault_pair(
        "mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -NLOD, 0.0), vegetation=False
    )


@pytest.fixture(scope="module")
def mls_result(mls_pair):
    return _run(mls_pair, 0.02)


def test_mls_dextral_slip_to_a_millimetre(mls_pair, mls_result):
    rel = mls_result.components()
    assert abs(rel["right_lateral_slip"] - NLOD) < 0.001
    assert abs(rel["fault_normal"]) < 0.001 and abs(rel["dz"]) < 0.001
    assert np.allclose(mls_result.relative, mls_pair.relative_offset_m, atol=0.001)
    assert rel["sigma_fault_parallel"] < 0.001
    assert mls_result.to_dict()["fault"]["strike_deg"] == pytest.approx(0.0, abs=1e-6)


def test_reversed_trace_flips_sides_not_the_slip(mls_pair, mls_result):
    rev = fault_trace([mls_pair.trace_xy[::-1]])
    res = estimate_slip(
        mls_pair.before.points, mls_pair.after.points, rev, sigma_before=0.02, sigma_after=0.02
    )
    a, b = mls_result.components(), res.components()
    assert b["right_lateral_slip"] == pytest.approx(a["right_lateral_slip"], abs=1e-9)
    assert np.allclose(res.relative, -mls_result.relative, atol=1e-9)


def test_both_sides_moving():
    fp = make_fault_pair(
        "mls",
        seed=8,
        origin=ORIGIN,
        vegetation=False,
        left_offset_m=(0.03, 0.01, -0.005),
        right_offset_m=(0.03, -0.008, -0.002),
    )
    res = _run(fp, 0.02)
    assert np.allclose(res.left.rigid.displacement, fp.left_offset_m, atol=0.0015)
    assert np.allclose(res.relative, fp.relative_offset_m, atol=0.001)


def test_als_roofs_within_4_mm():
    fp = make_fault_pair(
        "als",
        seed=9,
        origin=ORIGIN,
        n_buildings=24,
        extent_m=220.0,
        density_pts_m2=10.0,
        noise_m=0.05,
        ground=False,
        vegetation=False,
        right_offset_m=(0.0, -NLOD, 0.0),
        roof_kinds=("gable",),  # roofs only: horizontal slip comes from sloping roof planes
    )
    res = _run(fp, 0.05)
    rel = res.components()
    assert abs(rel["right_lateral_slip"] - NLOD) < 0.004
    assert abs(rel["right_lateral_slip"] - NLOD) < 3 * rel["sigma_fault_parallel"]


def test_moved_buildings_are_rejected():
    fp = make_fault_pair(
        "mls",
        seed=10,
        origin=ORIGIN,
        n_buildings=8,
        extent_m=120.0,
        vegetation=False,
        right_offset_m=(0.0, -NLOD, 0.0),
        blunder_fraction=0.1,
        blunder_offset_m=(0.5, 0, 0),
    )
    res = _run(fp, 0.02, match_options={"distance_threshold_m": 1.0})
    assert abs(res.components()["right_lateral_slip"] - NLOD) < 0.0015


@pytest.mark.parametrize("seed", [10, 11])
def test_moved_buildings_with_drift_rejected_and_sigma_honest(seed):
    """10 % of buildings renovated (moved 0.4 m) on top of 1 mm of MLS trajectory drift: the
    moved planes are rejected against the plane-level spread, the slip stays within 1.5 mm
    and within 2.5 σ of the truth."""
    from slipmap.core.synthetic import SurveyError

    err = SurveyError(kind="mls", level_m=0.001)
    fp = make_fault_pair(
        "mls", seed=seed, origin=ORIGIN, n_buildings=8, extent_m=120.0, vegetation=False,
        right_offset_m=(0.0, -NLOD, 0.0), blunder_fraction=0.1, blunder_offset_m=(0.3, 0.25, 0),
        error_before=err, error_after=err,
    )  # fmt: skip
    res = estimate_slip(
        fp.before.points, fp.after.points, fault_trace([fp.trace_xy]), sigma_before=0.02,
        sigma_after=0.02, match_options={"distance_threshold_m": 1.0},
        unit_before=fp.source_before.astype(int), unit_after=fp.source_after.astype(int),
    )  # fmt: skip
    c = res.components()
    e = c["right_lateral_slip"] - NLOD
    assert abs(e) < 0.0015
    assert abs(e) <= 2.5 * c["sigma_fault_parallel"]
    assert any(why.startswith("outlier") for s in (res.left, res.right)
               for _, why in s.rigid.rejected_planes)  # fmt: skip


def test_trace_outside_the_data_is_refused(mls_pair):
    far = fault_trace([mls_pair.trace_xy + 10_000.0])
    with pytest.raises(InputDataError):
        estimate_slip(mls_pair.before.points, mls_pair.after.points, far)


def test_no_overlap_and_nan_are_refused(mls_pair):
    tr = fault_trace([mls_pair.trace_xy])
    with pytest.raises(InputDataError, match="overlap"):
        estimate_slip(mls_pair.before.points, mls_pair.after.points + [5000.0, 0, 0], tr)
    bad = mls_pair.after.points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputDataError, match="NaN"):
        estimate_slip(mls_pair.before.points, bad, tr)


def test_uncertainty_is_honest_over_seeds():
    """A few seeds of the calibration study (benchmarks/accuracy_slip.py; docs/accuracy.md
    holds the full table): with 3 mm of MLS trajectory drift per epoch, the white model's σ is
    several times too small, the full model's error/σ has about unit spread; without drift
    the white model's σ0² is 1 when the assumed σ is the true white noise."""
    from slipmap.core.synthetic import SurveyError

    z = {"white": [], "full": []}
    for seed in range(1000, 1006):
        err = SurveyError(kind="mls", level_m=0.003)
        fp = make_fault_pair("mls", seed=seed, origin=ORIGIN, n_buildings=8, extent_m=110.0,
                             vegetation=False, error_before=err, error_after=err)  # fmt: skip
        units = dict(
            unit_before=fp.source_before.astype(int), unit_after=fp.source_after.astype(int)
        )
        for model in z:
            res = estimate_slip(
                fp.before.points, fp.after.points, fault_trace([fp.trace_xy]),
                sigma_before=0.02, sigma_after=0.02, stochastic_model=model,
                **(units if model == "full" else {}),
            )  # fmt: skip
            c = res.components()
            z[model].append((c["right_lateral_slip"] - 0.0181) / c["sigma_fault_parallel"])
    rms = {m: float(np.sqrt(np.mean(np.square(v)))) for m, v in z.items()}
    assert rms["white"] > 3.0, rms
    assert 0.3 <= rms["full"] <= 1.6, rms
    assert np.all(np.abs(z["full"]) <= 3.0), z


def test_reference_comparison_table_x(mls_result):
    c = mls_result.components()
    ref = mls_result.reference_comparison(0.0181)
    norm = np.sqrt(c["sigma_dx"] ** 2 + c["sigma_dy"] ** 2 + c["sigma_dz"] ** 2)
    delta = c["right_lateral_slip"] - 0.0181
    assert ref["delta_displacement"] == pytest.approx(delta)
    assert ref["scale"] == pytest.approx(abs(delta) / np.sqrt(2) / norm)
    s0 = 0.5 * (ref["variance_left"] + ref["variance_right"])
    assert ref["relative_scale"] == pytest.approx(abs(delta) / 2 / (s0 * norm))


def test_random_tilt_option_reaches_both_sides(mls_pair):
    """``random_tilt=True``: each side's plane-level model estimates a random tilt (not a
    fixed or absent one), the run's parameters say so, and the slip stays within the
    millimetre of the default; the white model, which has no plane level, refuses it."""
    from slipmap.core.errors import InvalidParameterError

    res = _run(mls_pair, 0.02, random_tilt=True)
    assert res.parameters["random_tilt"] is True
    for side in (res.left, res.right):
        tilt = side.rigid.variance_components.tilt
        assert tilt.source == "estimated"
        assert 0.0 <= tilt.sigma_rad < 1e-3
    rel = res.components()
    assert abs(rel["right_lateral_slip"] - NLOD) < 0.001
    with pytest.raises(InvalidParameterError, match="random_tilt"):
        _run(mls_pair, 0.02, random_tilt=True, stochastic_model="white")
