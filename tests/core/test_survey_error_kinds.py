"""Tests of issue #30's survey error terms (slipmap.core.synthetic): the MLS lever arm that
turns with the heading, the drive path's azimuth, the ALS boresight roll, the TLS setup
count, the smooth error field of short wavelength, and the true-surface reference fit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import j0

from slipmap.core.errors import InvalidParameterError
from slipmap.core.rotation import rotation_matrix
from slipmap.core.synthetic import (
    SurveyError,
    apply_survey_error,
    fit_true_surfaces,
    make_fault_pair,
    make_scene,
)

UTM = (500000.0, 4200000.0, 100.0)


@pytest.fixture(scope="module")
def mls_scene():
    return make_scene("mls", seed=12, n_buildings=3, extent_m=60.0, density_pts_m2=10.0)


@pytest.fixture(scope="module")
def ground_scene():
    """Ground only, 200 m square, about 20,000 points (no buildings, no trees)."""
    return make_scene(
        "als", seed=4, n_buildings=0, extent_m=200.0, density_pts_m2=0.5, vegetation=False,
        origin=UTM,
    )  # fmt: skip


def _rot90(v: np.ndarray) -> np.ndarray:
    """Horizontal vectors (..., 2) turned 90° counter-clockwise."""
    return np.stack([-v[..., 1], v[..., 0]], axis=-1)


# --- MLS lever arm and drive path ----------------------------------------------------------


def test_lever_arm_flips_with_heading(mls_scene):
    lever = SurveyError(kind="mls", lever_arm_m=0.002)
    draw = apply_survey_error(mls_scene, lever, seed=3)
    ids = draw.point_source_id
    passes = np.unique(ids)
    assert passes.size >= 3
    per_pass = []
    for pid in passes:
        e = draw.error[ids == pid]
        # a constant vector of the vehicle's frame: one error for all points of a pass
        np.testing.assert_allclose(e, np.broadcast_to(e[0], e.shape), atol=1e-15)
        per_pass.append(e[0])
    per_pass = np.array(per_pass)
    assert np.linalg.norm(per_pass[0, :2]) > 1e-4
    # passes alternate direction (serpentine): the horizontal part flips, the vertical stays
    np.testing.assert_allclose(per_pass[1:, :2], -per_pass[:-1, :2], atol=1e-15)
    np.testing.assert_allclose(per_pass[:, 2], per_pass[0, 2], atol=1e-15)

    # the crossing streets (lines along y) turn the first pass's heading by +90°: the
    # same body-frame vector (same seed) turns with it
    crossing = apply_survey_error(
        mls_scene, SurveyError(kind="mls", lever_arm_m=0.002, path_azimuth_deg=0.0), seed=3
    )
    first = crossing.error[crossing.point_source_id == 1][0]
    np.testing.assert_allclose(first[:2], _rot90(per_pass[0, :2]), atol=1e-15)
    assert first[2] == pytest.approx(per_pass[0, 2], abs=1e-15)


def test_lever_arm_adds_to_the_drift(mls_scene):
    drift = apply_survey_error(mls_scene, SurveyError(kind="mls", level_m=0.003), seed=5)
    both = apply_survey_error(
        mls_scene, SurveyError(kind="mls", level_m=0.003, lever_arm_m=0.002), seed=5
    )
    lever = apply_survey_error(mls_scene, SurveyError(kind="mls", lever_arm_m=0.002), seed=5)
    np.testing.assert_allclose(both.error, drift.error + lever.error, atol=1e-15)
    np.testing.assert_array_equal(both.gps_time, drift.gps_time)


def test_path_azimuth_turns_the_streets(mls_scene):
    local = mls_scene.points - np.asarray(mls_scene.origin)
    along_x = apply_survey_error(mls_scene, SurveyError(kind="mls"), seed=1)
    along_y = apply_survey_error(mls_scene, SurveyError(kind="mls", path_azimuth_deg=0.0), seed=1)
    for draw, across in ((along_x, 1), (along_y, 0)):
        ids = draw.point_source_id
        # passes are bands across the streets: their ranges of the across coordinate are
        # disjoint and ordered, and each spans most of the scene along the streets
        spans = [(local[ids == p, across].min(), local[ids == p, across].max()) for p in
                 np.unique(ids)]  # fmt: skip
        lows = sorted(lo for lo, _ in spans)
        highs = sorted(hi for _, hi in spans)
        assert all(h <= lo + 1e-9 for h, lo in zip(highs[:-1], lows[1:]))
        along = 1 - across
        for p in np.unique(ids):
            assert np.ptp(local[ids == p, along]) > 40.0


# --- ALS boresight roll ---------------------------------------------------------------------


def test_boresight_roll_tilts_with_cross_track_distance(ground_scene):
    width = 40.0
    model = SurveyError(kind="als", boresight_roll_rad=1e-3, strip_width_m=width)
    draw = apply_survey_error(ground_scene, model, seed=8)
    local = ground_scene.points - np.asarray(ground_scene.origin)
    height = 0.5 * width / math.tan(math.radians(30.0))  # documented flying height
    h = height - local[:, 2]
    horiz = draw.error[:, :2]
    # cross-track shift ~ roll * h: one magnitude per point, all parallel
    roll = np.linalg.norm(horiz, axis=1) / h
    assert np.ptp(roll) < 2e-3 * roll.mean()
    assert 1e-5 < roll.mean() < 5e-3
    cross = horiz[:, 0] * horiz[0, 1] - horiz[:, 1] * horiz[0, 0]
    assert np.abs(cross).max() < 1e-9
    direction = horiz[0] / np.linalg.norm(horiz[0])  # across the flight lines
    slopes = []
    for sid in np.unique(draw.point_source_id):
        m = draw.point_source_id == sid
        q = local[m, :2] @ direction
        dz = draw.error[m, 2]
        slope, intercept = np.polyfit(q, dz, 1)
        # vertical error proportional to the cross-track distance from the nadir line
        assert np.abs(dz - (slope * q + intercept)).max() < 0.01 * np.abs(dz).max()
        assert abs(slope) == pytest.approx(roll.mean(), rel=0.01)
        # the nadir line (dz = 0) lies inside the strip
        assert q.min() < -intercept / slope < q.max()
        slopes.append(slope)
    # strips flown in alternate directions: the tilt alternates in map coordinates
    assert len(slopes) >= 3
    signs = np.sign(slopes)
    assert np.all(signs[1:] == -signs[:-1])


def test_boresight_roll_adds_to_strip_offsets(ground_scene):
    kw = dict(kind="als", level_m=0.01, rotation_rad=1e-4, strip_width_m=40.0)
    plain = apply_survey_error(ground_scene, SurveyError(**kw), seed=2)
    rolled = apply_survey_error(ground_scene, SurveyError(**kw, boresight_roll_rad=2e-4), seed=2)
    only = apply_survey_error(
        ground_scene, SurveyError(kind="als", boresight_roll_rad=2e-4, strip_width_m=40.0), seed=2
    )
    np.testing.assert_allclose(rolled.error, plain.error + only.error, atol=1e-15)
    np.testing.assert_array_equal(rolled.point_source_id, plain.point_source_id)


# --- TLS setups ------------------------------------------------------------------------------


@pytest.mark.parametrize(("count", "grid"), [(6, (2, 3)), (4, (2, 2)), (7, (1, 7))])
def test_tls_setup_count(count, grid):
    scene = make_scene(
        "tls", seed=3, n_buildings=4, extent_m=150.0, density_pts_m2=2.0, vegetation=False
    )
    draw = apply_survey_error(scene, SurveyError(kind="tls", n_setups=count), seed=1)
    ids = draw.point_source_id
    assert np.unique(ids).size == count
    # an nx x ny grid of cells: the setups' points split the x and y ranges that way
    xs = np.array([scene.points[ids == i, 0].mean() for i in np.unique(ids)])
    ys = np.array([scene.points[ids == i, 1].mean() for i in np.unique(ids)])
    nx, ny = grid
    assert np.unique(np.round(xs / (150.0 / nx) - 0.5)).size == nx
    assert np.unique(np.round(ys / (150.0 / ny) - 0.5)).size == ny


def test_tls_issue30_registration_error():
    """2 mm and 0.05 mrad per setup: each setup rigid, the spread as drawn."""
    scene = make_scene(
        "tls", seed=3, n_buildings=6, extent_m=150.0, density_pts_m2=2.0, vegetation=False
    )
    model = SurveyError(kind="tls", level_m=0.002, rotation_rad=5e-5, n_setups=6)
    draw = apply_survey_error(scene, model, seed=4)
    for sid in np.unique(draw.point_source_id):
        m = draw.point_source_id == sid
        e = draw.error[m]
        p = scene.points[m]
        # rigid: error = t + (R - I)(p - c), affine in p with a near-skew linear part
        design = np.column_stack([p - p.mean(axis=0), np.ones(m.sum())])
        sol, *_ = np.linalg.lstsq(design, e, rcond=None)
        assert np.abs(design @ sol - e).max() < 1e-9
        lin = sol[:3].T
        assert np.abs(lin + lin.T).max() < 1e-7  # R - I = [w]x + O(w²)
        assert 0.0 < np.abs(lin).max() < 5 * 5e-5
        assert np.abs(e).max() < 0.02


# --- smooth error field of short wavelength ------------------------------------------------


def _field_correlation(r: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Documented correlation: mean of J0(2 pi r / wavelength), wavelength uniform."""
    wl = np.linspace(lo, hi, 401)
    return j0(2.0 * math.pi * np.asarray(r)[:, None] / wl[None, :]).mean(axis=1)


def test_field_spread_and_correlation(ground_scene):
    level = 0.003
    model = SurveyError(kind="field", level_m=level)
    assert model.wavelength_range_m == (37.0, 53.0)
    local = ground_scene.points[:, :2] - np.asarray(ground_scene.origin)[:2]
    rng = np.random.default_rng(0)
    i = rng.integers(0, local.shape[0], 200_000)
    j = rng.integers(0, local.shape[0], 200_000)
    dist = np.linalg.norm(local[i] - local[j], axis=1)
    edges = np.array([0.0, 3.0, 8.0, 12.0, 15.0, 19.0, 23.0, 27.0, 32.0])
    which = np.digitize(dist, edges) - 1
    ok = (which >= 0) & (which < edges.size - 1)
    sums = np.zeros(edges.size - 1)
    counts = np.zeros(edges.size - 1)
    var = []
    for seed in range(12):
        draw = apply_survey_error(ground_scene, model, seed=seed)
        e = draw.error
        var.append((e**2).mean())
        prod = (e[i] * e[j]).mean(axis=1)
        np.add.at(sums, which[ok], prod[ok])
        np.add.at(counts, which[ok], 1.0)
        # a function of the horizontal position only, the same for every axis' spread
        assert np.all(draw.point_source_id >= 1) and np.unique(draw.point_source_id).size > 3
    # spread: level_m per axis (12 draws of 64 waves over 4-5 wavelengths: within 10 %)
    assert math.sqrt(np.mean(var)) == pytest.approx(level, rel=0.1)
    mid = np.array(
        [dist[ok][which[ok] == k].mean() for k in range(edges.size - 1)]
    )  # mean lag of each bin
    measured = sums / counts / level**2
    expected = _field_correlation(mid, 37.0, 53.0)
    np.testing.assert_allclose(measured, expected, atol=0.12)
    # correlation length: the first zero crossing near 0.383 x the mean wavelength (~17 m)
    assert measured[0] > 0.85 and measured[4] < 0.2 and measured[-1] < 0.0


def test_field_wavelengths_set_the_scale(ground_scene):
    short = SurveyError(kind="field", level_m=0.003, wavelength_range_m=(8.0, 8.0))
    e = apply_survey_error(ground_scene, short, seed=1).error
    local = ground_scene.points[:, :2] - np.asarray(ground_scene.origin)[:2]
    # one wavelength: the correlation at half a wavelength is J0(pi) = -0.30
    rng = np.random.default_rng(1)
    i = rng.integers(0, local.shape[0], 300_000)
    j = rng.integers(0, local.shape[0], 300_000)
    d = np.linalg.norm(local[i] - local[j], axis=1)
    m = np.abs(d - 4.0) < 0.5
    corr = (e[i[m]] * e[j[m]]).mean() / (e**2).mean()
    assert corr == pytest.approx(float(j0(math.pi)), abs=0.12)


# --- options ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"kind": "mls", "lever_arm_m": -0.001}, "lever_arm_m"),
        ({"kind": "mls", "lever_arm_m": float("inf")}, "lever_arm_m"),
        ({"kind": "als", "lever_arm_m": 0.001}, "lever_arm_m"),
        ({"kind": "mls", "path_azimuth_deg": float("nan")}, "path_azimuth_deg"),
        ({"kind": "tls", "path_azimuth_deg": 0.0}, "path_azimuth_deg"),
        ({"kind": "als", "boresight_roll_rad": -1e-4}, "boresight_roll_rad"),
        ({"kind": "mls", "boresight_roll_rad": 1e-4}, "boresight_roll_rad"),
        ({"kind": "tls", "n_setups": -1}, "n_setups"),
        ({"kind": "tls", "n_setups": 2.5}, "n_setups"),
        ({"kind": "als", "n_setups": 6}, "n_setups"),
        ({"kind": "field", "wavelength_range_m": (0.0, 10.0)}, "wavelength_range_m"),
        ({"kind": "field", "wavelength_range_m": (53.0, 37.0)}, "wavelength_range_m"),
        ({"kind": "field", "wavelength_range_m": "long"}, "wavelength_range_m"),
        ({"kind": "field", "wavelength_range_m": (1.0, 2.0, 3.0)}, "wavelength_range_m"),
        ({"kind": "field", "rotation_rad": 1e-4}, "rotation_rad"),
    ],
)
def test_bad_options_raise(kwargs, name):
    with pytest.raises(InvalidParameterError, match=name):
        SurveyError(**kwargs)


def test_new_defaults_keep_the_old_models(mls_scene):
    """The new options at their defaults give the draws of before (the same streams)."""
    model = SurveyError(kind="mls", level_m=0.003, path_azimuth_deg=90, lever_arm_m=0)
    assert model == SurveyError(kind="mls", level_m=0.003)
    field = SurveyError(kind="field", level_m=0.003, wavelength_range_m=[37, 53])
    assert field.wavelength_range_m == (37.0, 53.0)


@pytest.mark.parametrize(
    "model",
    [
        SurveyError(kind="mls", level_m=0.003, lever_arm_m=0.002, path_azimuth_deg=30.0),
        SurveyError(kind="als", level_m=0.01, boresight_roll_rad=2e-4, strip_width_m=25.0),
        SurveyError(kind="tls", level_m=0.002, rotation_rad=5e-5, n_setups=6),
        SurveyError(kind="field", level_m=0.003),
    ],
)
def test_same_seed_same_draw(mls_scene, model):
    a = apply_survey_error(mls_scene, model, seed=9)
    b = apply_survey_error(mls_scene, model, seed=9)
    c = apply_survey_error(mls_scene, model, seed=10)
    for name in ("points", "error", "point_source_id", "gps_time"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.error, c.error)
    assert np.all(np.isfinite(a.error)) and np.abs(a.error).max() < 0.1


# --- the true-surface reference fit ---------------------------------------------------------


def _on_planes(scene):
    """The scene's planar points projected onto their true planes (noise-free), labels."""
    keep = scene.labels >= 0
    pts, lab = scene.points[keep], scene.labels[keep]
    n = np.array([s.normal for s in scene.surfaces])[lab]
    d = np.array([s.d for s in scene.surfaces])[lab]
    return pts - (np.einsum("ij,ij->i", n, pts) + d)[:, None] * n, lab


@pytest.mark.parametrize(
    ("rotvec", "shift"),
    [
        ((0.0, 0.0, 0.0), (0.004, -0.0181, 0.002)),
        ((1e-3, -2e-3, 5e-3), (0.01, -0.02, 0.03)),
        ((0.02, 0.01, -0.05), (-0.3, 0.2, 0.1)),  # far from small-angle: still exact
    ],
)
def test_true_surface_fit_recovers_a_rigid_motion(mls_scene, rotvec, shift):
    x, lab = _on_planes(mls_scene)
    centre = x.mean(axis=0) + np.array([3.0, -2.0, 1.0])
    rot = rotation_matrix(np.array(rotvec))
    p = (x - centre) @ rot.T + centre + np.array(shift)
    fit = fit_true_surfaces(p, lab, mls_scene.surfaces, centre=centre, iterations=20)
    np.testing.assert_allclose(fit.translation_m, shift, atol=1e-10)
    np.testing.assert_allclose(fit.rotation_rad, rotvec, atol=1e-12)
    assert fit.n_points == lab.size and fit.rms_m < 1e-10


def test_true_surface_fit_ignores_clutter_and_reports_undetermined(mls_scene):
    x, lab = _on_planes(mls_scene)
    centre = x.mean(axis=0)
    clutter = np.vstack([x, x[:50] + 5.0])
    labels = np.concatenate([lab, np.full(50, -1)])
    fit = fit_true_surfaces(clutter + [0.0, 0.01, 0.0], labels, mls_scene.surfaces, centre=centre)
    np.testing.assert_allclose(fit.translation_m, [0.0, 0.01, 0.0], atol=1e-10)
    assert fit.n_points == lab.size
    # the ground alone leaves the horizontal translation and the vertical axis free
    ground = [s.id for s in mls_scene.surfaces if s.kind == "ground"]
    only = np.isin(lab, ground)
    assert only.sum() > 100
    nan = fit_true_surfaces(x[only], lab[only], mls_scene.surfaces, centre=centre)
    assert np.all(np.isnan(nan.translation_m)) and np.all(np.isnan(nan.rotation_rad))
    few = fit_true_surfaces(x[:5], lab[:5], mls_scene.surfaces, centre=centre)
    assert np.all(np.isnan(few.translation_m)) and few.n_points == 5


def test_true_surface_fit_on_a_fault_pair_sees_the_survey_error():
    """Without survey error the fit gives the side offsets to the point noise; with it, the
    error of the fit is the survey error's rigid part on the side."""
    kw = dict(seed=5, n_buildings=4, extent_m=80.0, density_pts_m2=10.0, origin=UTM,
              right_offset_m=(0.0, -0.0181, 0.0), vegetation=False)  # fmt: skip
    fp = make_fault_pair("mls", **kw)
    for s, offset in ((-1, fp.left_offset_m), (1, fp.right_offset_m)):
        m = fp.side_after == s
        c = fp.after.points[m].mean(axis=0)
        fit = fit_true_surfaces(fp.after.points[m], fp.after.labels[m], fp.after.surfaces, centre=c)
        np.testing.assert_allclose(fit.translation_m, offset, atol=5e-4)
    err = SurveyError(kind="tls", level_m=0.01, n_setups=1)  # one setup: a rigid shift
    fp = make_fault_pair("mls", error_after=err, **kw)
    shift = fp.error_after[0]
    m = fp.side_after > 0
    c = fp.after.points[m].mean(axis=0)
    fit = fit_true_surfaces(fp.after.points[m], fp.after.labels[m], fp.after.surfaces, centre=c)
    np.testing.assert_allclose(fit.translation_m, fp.right_offset_m + shift, atol=5e-4)
