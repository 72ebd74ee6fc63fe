"""Tests of the correlated survey error generator (slipmap.core.synthetic.apply_survey_error)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from slipmap.core.errors import InvalidParameterError
from slipmap.core.synthetic import (
    PROFILES,
    SURVEY_ERROR_KINDS,
    SurveyError,
    apply_survey_error,
    make_fault_pair,
    make_scene,
    plane_distances,
)

MLS_SPEED_M_S = 5.0  # documented vehicle speed of the MLS drive path
UTM = (500000.0, 4200000.0, 100.0)


@pytest.fixture(scope="module")
def mls_scene():
    return make_scene("mls", seed=12, n_buildings=3, extent_m=60.0, density_pts_m2=10.0)


@pytest.fixture(scope="module")
def sparse_mls_scene():
    """About 2,000 points: cheap enough for a few hundred draws."""
    return make_scene(
        "mls", seed=12, n_buildings=3, extent_m=60.0, density_pts_m2=1.0, vegetation=False
    )


def _pairs_rigid(before: np.ndarray, after: np.ndarray, rng: np.random.Generator) -> float:
    """Largest change of the distance between random pairs of points (metres)."""
    i = rng.integers(0, before.shape[0], 500)
    j = rng.integers(0, before.shape[0], 500)
    d0 = np.linalg.norm(before[i] - before[j], axis=1)
    d1 = np.linalg.norm(after[i] - after[j], axis=1)
    return float(np.max(np.abs(d1 - d0)))


# --- no error ------------------------------------------------------------------------------


def test_none_leaves_points_unchanged(mls_scene):
    original = mls_scene.points.copy()
    draw = apply_survey_error(mls_scene, SurveyError(), seed=3)
    assert draw.points is not mls_scene.points
    np.testing.assert_array_equal(draw.points, original)
    np.testing.assert_array_equal(mls_scene.points, original)
    assert not np.any(draw.error)
    assert draw.point_source_id.dtype == np.uint16 and np.all(draw.point_source_id == 1)
    assert draw.gps_time.dtype == np.float64 and not np.any(draw.gps_time)
    assert draw.model == SurveyError(kind="none")
    assert SURVEY_ERROR_KINDS == ("none", "mls", "als", "tls", "field")


@pytest.mark.parametrize("kind", ["mls", "als", "tls"])
def test_zero_level_keeps_points_and_gives_layout(mls_scene, kind):
    original = mls_scene.points.copy()
    draw = apply_survey_error(mls_scene, SurveyError(kind=kind, strip_width_m=20.0), seed=3)
    np.testing.assert_array_equal(draw.points, original)
    np.testing.assert_array_equal(mls_scene.points, original)
    assert np.unique(draw.point_source_id).size >= 2
    assert np.all(draw.gps_time > 0.0)


# --- MLS trajectory drift ------------------------------------------------------------------


def test_mls_drift_std_and_correlation(sparse_mls_scene):
    scene, level, ell = sparse_mls_scene, 0.004, 30.0
    model = SurveyError(kind="mls", level_m=level, correlation_length_m=ell)
    s = apply_survey_error(scene, model, seed=0).gps_time * MLS_SPEED_M_S  # path length + const
    a = int(np.argmin(np.abs(s - np.median(s))))
    far = int(np.argmin(np.abs(s - s[a] - 3.0 * ell)))
    near = int(np.argmin(np.abs(s - s[a] - 0.1 * ell)))
    assert abs(s[far] - s[a] - 3.0 * ell) < 10.0  # correlation < exp(-80**2 / 1800) = 0.03
    assert abs(s[near] - s[a] - 0.1 * ell) < 2.0  # correlation > exp(-5**2 / 1800) = 0.986
    # points on other lines, far along the path, for the marginal std
    spread = np.argsort(s)[:: max(1, s.size // 8)]
    errs, e_a, e_far, e_near = [], [], [], []
    for seed in range(300):
        e = apply_survey_error(scene, model, seed=seed).error
        errs.append(e[spread])
        e_a.append(e[a])
        e_far.append(e[far])
        e_near.append(e[near])
    errs = np.concatenate(errs)
    np.testing.assert_allclose(errs.std(axis=0), level, rtol=0.15)
    np.testing.assert_allclose(errs.mean(axis=0), 0.0, atol=0.15 * level)
    e_a, e_far, e_near = (np.ravel(v) for v in (e_a, e_far, e_near))
    assert abs(np.corrcoef(e_a, e_far)[0, 1]) < 0.2  # exp(-4.5) = 0.011
    assert np.corrcoef(e_a, e_near)[0, 1] > 0.95  # exp(-0.005) = 0.995


def test_mls_drift_is_smooth_along_the_path(mls_scene):
    level = 0.005
    model = SurveyError(kind="mls", level_m=level, correlation_length_m=30.0)
    draw = apply_survey_error(mls_scene, model, seed=5)
    order = np.argsort(draw.gps_time)
    ds = np.diff(draw.gps_time[order]) * MLS_SPEED_M_S
    de = np.linalg.norm(np.diff(draw.error[order], axis=0), axis=1)
    close = ds < 0.5
    assert close.sum() > 0.9 * ds.size
    assert de[close].max() < 0.15 * level
    # over the whole path the error does vary by about its std
    assert draw.error.std(axis=0).min() > 0.2 * level


def test_mls_passes_give_ids_and_different_errors(mls_scene):
    model = SurveyError(kind="mls", level_m=0.004)
    draw = apply_survey_error(mls_scene, model, seed=2)
    ids = draw.point_source_id
    assert set(np.unique(ids)) == {1, 2, 3}  # 60 m: three streets 20 m apart
    # passes are lines along x: a pass covers a band of y
    y = mls_scene.points[:, 1]
    for k in (1, 2, 3):
        band = y[ids == k]
        assert band.min() >= 20.0 * (k - 1) - 0.1 and band.max() <= 20.0 * k + 0.1
    seen_twice = 0
    for surface in mls_scene.surfaces:
        if surface.kind != "facade":
            continue
        mask = mls_scene.labels == surface.id
        passes = np.unique(ids[mask])
        if passes.size < 2:
            continue
        seen_twice += 1
        m1 = draw.error[mask & (ids == passes[0])].mean(axis=0)
        m2 = draw.error[mask & (ids == passes[1])].mean(axis=0)
        assert np.abs(m1 - m2).max() > 1e-5
    assert seen_twice >= 1


# --- ALS strips ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def als_scene():
    return make_scene("als", seed=5, n_buildings=3, extent_m=60.0, vegetation=False)


def test_als_strips_translate_rigidly_with_overlap(als_scene):
    width = 20.0
    model = SurveyError(kind="als", level_m=0.02, strip_width_m=width)
    draw = apply_survey_error(als_scene, model, seed=4)
    ids = draw.point_source_id
    strips = np.unique(ids)
    assert strips[0] >= 1 and strips.size >= 3
    shifts = []
    for k in strips:
        e = draw.error[ids == k]
        assert np.all(e == e[0])  # one translation per strip
        shifts.append(e[0])
    assert np.unique(np.array(shifts), axis=0).shape[0] == strips.size
    # the flight line: time grows linearly along it (a plausible aircraft speed)
    xy = als_scene.points[:, :2]
    sel = ids == strips[0]
    design = np.column_stack([np.ones(sel.sum()), xy[sel]])
    coef, *_ = np.linalg.lstsq(design, draw.gps_time[sel], rcond=None)
    np.testing.assert_allclose(design @ coef, draw.gps_time[sel], atol=1e-6)
    speed = 1.0 / np.linalg.norm(coef[1:])
    assert 30.0 < speed < 100.0
    along = coef[1:] / np.linalg.norm(coef[1:])
    q = xy @ np.array([-along[1], along[0]])  # across-track coordinate
    ranges = sorted((q[ids == k].min(), q[ids == k].max(), k) for k in strips)
    for lo, hi, _ in ranges:
        assert hi - lo <= width + 1e-6
    # neighbouring strips overlap by 30 %; a point there belongs to either at random
    best = max(zip(ranges[:-1], ranges[1:]), key=lambda p: np.sum(ids == p[0][2]))
    (_, hi_a, k_a), (lo_b, _, k_b) = best
    assert hi_a - lo_b == pytest.approx(0.3 * width, abs=0.3)
    zone = (q > lo_b) & (q < hi_a)
    assert set(np.unique(ids[zone])) == {k_a, k_b}
    assert np.mean(ids[zone] == k_a) == pytest.approx(0.5, abs=0.08)


def test_als_strips_with_rotation_are_rigid(als_scene):
    model = SurveyError(kind="als", level_m=0.02, strip_width_m=20.0, rotation_rad=1e-3)
    draw = apply_survey_error(als_scene, model, seed=4)
    rng = np.random.default_rng(0)
    for k in np.unique(draw.point_source_id):
        sel = draw.point_source_id == k
        assert np.ptp(draw.error[sel], axis=0).max() > 1e-4  # rotated, not only shifted
        assert _pairs_rigid(als_scene.points[sel], draw.points[sel], rng) < 1e-9
    # the same seed gives the same translations with and without rotation
    flat = apply_survey_error(
        als_scene, SurveyError(kind="als", level_m=0.02, strip_width_m=20.0), seed=4
    )
    np.testing.assert_array_equal(flat.point_source_id, draw.point_source_id)


# --- TLS setups ----------------------------------------------------------------------------


def test_tls_setups_are_rigid_and_nearest():
    scene = make_scene("tls", seed=2, n_buildings=2, extent_m=60.0, density_pts_m2=20.0, origin=UTM)
    model = SurveyError(kind="tls", level_m=0.003, strip_width_m=20.0, rotation_rad=2e-4)
    draw = apply_survey_error(scene, model, seed=8)
    ids = draw.point_source_id
    assert set(np.unique(ids)) == set(range(1, 10))  # a 3 x 3 grid of setups
    nodes = np.stack(np.meshgrid([10.0, 30.0, 50.0], [10.0, 30.0, 50.0]), -1).reshape(-1, 2)
    xy = scene.points[:, :2] - np.asarray(UTM)[:2]
    _, cell = cKDTree(nodes).query(xy)
    rng = np.random.default_rng(1)
    blocks = []
    for k in range(1, 10):
        sel = ids == k
        assert np.unique(cell[sel]).size == 1  # every point of a setup is in its cell
        assert _pairs_rigid(scene.points[sel], draw.points[sel], rng) < 1e-8
        blocks.append((draw.gps_time[sel].min(), draw.gps_time[sel].max()))
    assert np.unique(cell).size == 9
    blocks.sort()
    assert all(a[1] < b[0] for a, b in zip(blocks[:-1], blocks[1:]))  # one block per setup


# --- non-flat surfaces ---------------------------------------------------------------------


def test_nonflat_std_and_vegetation():
    scene = make_scene("mls", seed=3, n_buildings=3, extent_m=60.0, density_pts_m2=20.0)
    draw = apply_survey_error(scene, SurveyError(nonflat_m=0.01), seed=1)
    assert not np.any(draw.error[scene.labels < 0])
    ground = scene.labels == 0
    assert scene.surfaces[0].kind == "ground"
    np.testing.assert_allclose(draw.error[ground, :2], 0.0)
    assert draw.error[ground, 2].std() == pytest.approx(0.01, rel=0.2)
    # along the normal only: the in-plane position is kept
    for surface in scene.surfaces:
        e = draw.error[scene.labels == surface.id]
        in_plane = e - np.outer(e @ surface.normal, surface.normal)
        assert np.abs(in_plane).max() < 1e-15


def test_nonflat_is_the_same_in_both_epochs():
    amp = 0.01
    pair = make_fault_pair(
        "mls",
        seed=3,
        n_buildings=3,
        extent_m=60.0,
        density_pts_m2=30.0,
        noise_m=0.0,
        vegetation=False,
        right_offset_m=(0.0, 0.0, 0.0),
        error_before=SurveyError(nonflat_m=amp),
        error_after=SurveyError(nonflat_m=amp),
    )
    before, after = pair.before, pair.after
    d_before, d_after = plane_distances(before), plane_distances(after)
    checked = 0
    for surface in before.surfaces:
        pb = before.labels == surface.id
        pa = after.labels == surface.id
        if pb.sum() < 50 or pa.sum() < 50:
            continue
        dist, nn = cKDTree(before.points[pb]).query(after.points[pa])
        ok = dist < 0.3
        x, y = d_after[pa][ok], d_before[pb][nn[ok]]
        assert np.median(np.abs(x - y)) < 0.1 * amp
        assert np.corrcoef(x, y)[0, 1] > 0.95
        checked += 1
    assert checked >= 5
    # without noise, a point's distance to its plane is its bump, the error along the normal
    for surface in before.surfaces:
        pb = before.labels == surface.id
        np.testing.assert_allclose(d_before[pb], pair.error_before[pb] @ surface.normal, atol=1e-9)


def test_nonflat_same_across_profiles():
    """MLS before, ALS after: the same roofs get the same bumps (surface ids differ)."""
    pair = make_fault_pair(
        "mls",
        seed=3,
        n_buildings=3,
        extent_m=60.0,
        density_pts_m2=30.0,
        noise_m=0.0,
        vegetation=False,
        right_offset_m=(0.0, 0.0, 0.0),
        after_profile="als",
        error_before=SurveyError(nonflat_m=0.01),
        error_after=SurveyError(nonflat_m=0.01),
    )
    before, after = pair.before, pair.after
    checked = 0
    for sb in before.surfaces:
        if sb.kind != "roof":
            continue
        sa = next(
            s
            for s in after.surfaces
            if s.kind == "roof" and s.building == sb.building and np.allclose(s.normal, sb.normal)
        )
        pb, pa = before.labels == sb.id, after.labels == sa.id
        dist, nn = cKDTree(before.points[pb]).query(after.points[pa])
        ok = dist < 0.5
        bump_b = pair.error_before[pb] @ sb.normal
        bump_a = pair.error_after[pa] @ sa.normal
        assert np.corrcoef(bump_a[ok], bump_b[nn[ok]])[0, 1] > 0.95
        checked += 1
    assert checked >= 3


# --- reproducibility and options -----------------------------------------------------------


@pytest.mark.parametrize("kind", ["mls", "als", "tls"])
def test_same_seed_same_draw(mls_scene, kind):
    model = SurveyError(kind=kind, level_m=0.003, strip_width_m=25.0, nonflat_m=0.002)
    a = apply_survey_error(mls_scene, model, seed=9)
    b = apply_survey_error(mls_scene, model, seed=9)
    c = apply_survey_error(mls_scene, model, seed=10)
    for name in ("points", "error", "point_source_id", "gps_time"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.error, c.error)
    # the bumps follow surface_seed, not the error seed
    bumps = SurveyError(nonflat_m=0.002)
    d1 = apply_survey_error(mls_scene, bumps, seed=1, surface_seed=7)
    d2 = apply_survey_error(mls_scene, bumps, seed=2, surface_seed=7)
    np.testing.assert_array_equal(d1.error, d2.error)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"kind": "gnss"}, "kind"),
        ({"kind": 3}, "kind"),
        ({"kind": "mls", "level_m": -0.001}, "level_m"),
        ({"kind": "mls", "level_m": float("nan")}, "level_m"),
        ({"level_m": 0.001}, "level_m"),
        ({"kind": "mls", "correlation_length_m": 0.0}, "correlation_length_m"),
        ({"kind": "als", "strip_width_m": -40.0}, "strip_width_m"),
        ({"kind": "als", "rotation_rad": -1e-3}, "rotation_rad"),
        ({"kind": "mls", "rotation_rad": 1e-3}, "rotation_rad"),
        ({"nonflat_m": -0.01}, "nonflat_m"),
        ({"nonflat_m": "a lot"}, "nonflat_m"),
    ],
)
def test_bad_options_raise(kwargs, name):
    with pytest.raises(InvalidParameterError, match=name):
        SurveyError(**kwargs)


def test_bad_call_arguments_raise(mls_scene):
    with pytest.raises(InvalidParameterError, match="seed"):
        apply_survey_error(mls_scene, SurveyError(), seed=-1)
    with pytest.raises(InvalidParameterError, match="surface_seed"):
        apply_survey_error(mls_scene, SurveyError(), seed=1, surface_seed=-2)
    with pytest.raises(InvalidParameterError, match="model"):
        apply_survey_error(mls_scene, "mls", seed=1)
    with pytest.raises(InvalidParameterError, match="nonflat_m"):
        make_fault_pair(
            "mls", seed=1, n_buildings=1, extent_m=40.0, error_before=SurveyError(nonflat_m=0.01)
        )
    with pytest.raises(InvalidParameterError, match="error_after"):
        make_fault_pair("mls", seed=1, n_buildings=1, extent_m=40.0, error_after="mls")
    with pytest.raises(InvalidParameterError, match="after_profile|profile"):
        make_fault_pair("mls", seed=1, n_buildings=1, extent_m=40.0, after_profile="sonar")


# --- make_fault_pair -----------------------------------------------------------------------

PAIR = {
    "seed": 6,
    "n_buildings": 3,
    "extent_m": 60.0,
    "density_pts_m2": 20.0,
    "origin": UTM,
    "right_offset_m": (0.01, -0.02, 0.003),
    "left_offset_m": (0.001, 0.0, 0.0),
}


def test_fault_pair_after_profile():
    pair = make_fault_pair("mls", after_profile="als", **PAIR)
    assert pair.before.profile == "mls" and pair.after.profile == "als"
    assert pair.before.buildings == pair.after.buildings
    assert pair.before.density_pts_m2 == 20.0
    assert pair.after.density_pts_m2 == PROFILES["als"].density_pts_m2
    assert pair.after.noise_m == PROFILES["als"].noise_m
    assert not any(s.kind == "facade" for s in pair.after.surfaces)
    assert pair.source_after is None and pair.error_before is None
    plain = make_fault_pair("mls", **PAIR)
    np.testing.assert_array_equal(plain.before.points, pair.before.points)


def test_fault_pair_errors_are_survey_error_not_motion():
    plain = make_fault_pair("mls", **PAIR)
    assert plain.source_before is None and plain.gps_time_after is None
    assert plain.error_before is None and plain.error_after is None
    model = SurveyError(kind="mls", level_m=0.004, nonflat_m=0.003)
    pair = make_fault_pair("mls", error_before=model, error_after=model, **PAIR)
    np.testing.assert_array_equal(pair.side_before, plain.side_before)
    np.testing.assert_array_equal(pair.side_after, plain.side_after)
    offset = np.where(
        (pair.side_after < 0)[:, None], pair.left_offset_m[None], pair.right_offset_m[None]
    )
    np.testing.assert_allclose(
        pair.after.points - pair.error_after - offset, plain.after.points - offset, atol=1e-8
    )
    np.testing.assert_allclose(
        pair.before.points - pair.error_before, plain.before.points, atol=1e-8
    )
    n_b, n_a = plain.before.n_points, plain.after.n_points
    assert pair.source_before.shape == (n_b,) and pair.source_before.dtype == np.uint16
    assert pair.gps_time_after.shape == (n_a,) and pair.gps_time_after.dtype == np.float64
    assert pair.error_after.shape == (n_a, 3)
    # independent draws of the drift in the two epochs
    drift_b = (
        pair.error_before
        - apply_survey_error(
            plain.before, SurveyError(nonflat_m=0.003), seed=0, surface_seed=PAIR["seed"]
        ).error
    )
    assert np.abs(drift_b).max() > 1e-3
    assert not np.allclose(pair.error_before.mean(axis=0), pair.error_after.mean(axis=0))
    # error_seed changes the draws, not the scenes
    other = make_fault_pair("mls", error_before=model, error_after=model, error_seed=99, **PAIR)
    assert not np.array_equal(other.error_after, pair.error_after)
    np.testing.assert_allclose(
        other.after.points - other.error_after, pair.after.points - pair.error_after, atol=1e-8
    )


def test_fault_pair_mixed_kinds():
    """MLS drift before, ALS strips after (the after epoch sampled as ALS)."""
    pair = make_fault_pair(
        "mls",
        after_profile="als",
        error_before=SurveyError(kind="mls", level_m=0.003),
        error_after=SurveyError(kind="als", level_m=0.02, strip_width_m=20.0),
        **PAIR,
    )
    assert np.unique(pair.source_after).size >= 3
    assert pair.error_after.shape == pair.after.points.shape
    assert np.abs(pair.error_after).max() > 5e-3
