"""Tests of the synthetic scene generator (slipmap.core.synthetic)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipmap.core.errors import InvalidParameterError
from slipmap.core.synthetic import (
    ASPRS_BUILDING,
    ASPRS_GROUND,
    ASPRS_HIGH_VEGETATION,
    PROFILES,
    Building,
    make_scene,
    make_scene_n_points,
    plane_distances,
)

UTM = np.array([500000.0, 4200000.0, 100.0])


@pytest.fixture(scope="module")
def mls_scene():
    return make_scene("mls", seed=7, n_buildings=3, extent_m=70.0)


def _small(profile: str, **kw):
    opts = {"seed": 1, "n_buildings": 2, "extent_m": 60.0}
    opts.update(kw)
    return make_scene(profile, **opts)


def _surface_points(scene, surface):
    return scene.points[scene.labels == surface.id]


# --- determinism ---------------------------------------------------------------------


def test_same_seed_same_scene():
    a, b = _small("mls", seed=3), _small("mls", seed=3)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.classification, b.classification)
    assert [s.n_points for s in a.surfaces] == [s.n_points for s in b.surfaces]


def test_different_seed_different_scene():
    a, b = _small("mls", seed=3), _small("mls", seed=4)
    assert a.buildings != b.buildings
    assert a.points.shape != b.points.shape or not np.array_equal(a.points, b.points)


def test_buildings_do_not_depend_on_other_options():
    full = make_scene("mls", seed=5, n_buildings=3, extent_m=80.0)
    bare = make_scene("mls", seed=5, n_buildings=3, extent_m=80.0, vegetation=False, ground=False)
    fewer = make_scene("mls", seed=5, n_buildings=2, extent_m=80.0)
    assert full.buildings == bare.buildings
    assert full.buildings[:2] == fewer.buildings
    roof = [s for s in full.surfaces if s.kind == "roof"][0]
    roof_bare = [s for s in bare.surfaces if s.building == roof.building and s.kind == "roof"][0]
    np.testing.assert_array_equal(
        np.sort(_surface_points(full, roof), axis=0),
        np.sort(_surface_points(bare, roof_bare), axis=0),
    )


# --- geometry truth ------------------------------------------------------------------


@pytest.mark.parametrize("profile", ["als", "mls", "tls"])
@pytest.mark.parametrize("isotropic", [False, True])
def test_labelled_points_lie_on_their_planes(profile, isotropic):
    density = {"als": 10.0, "mls": 60.0, "tls": 100.0}[profile]
    scene = _small(profile, density_pts_m2=density, isotropic_noise=isotropic)
    dist = plane_distances(scene)
    planar = scene.planar_mask()
    assert planar.sum() > 1000
    assert np.all(np.isfinite(dist[planar]))
    assert np.all(np.isnan(dist[~planar]))
    assert np.max(np.abs(dist[planar])) <= 5.0 * scene.noise_m


def test_surfaces_metadata(mls_scene):
    s = mls_scene
    n = s.points.shape[0]
    assert s.points.shape == (n, 3) and s.points.dtype == np.float64
    assert s.labels.dtype == np.int32 and s.labels.shape == (n,)
    assert s.classification.dtype == np.uint8 and s.building_ids.dtype == np.int32
    ids = [surf.id for surf in s.surfaces]
    assert ids == list(range(len(s.surfaces)))
    assert set(np.unique(s.labels)) <= set(ids) | {-1}
    counts = np.bincount(s.labels[s.labels >= 0], minlength=len(ids))
    assert [surf.n_points for surf in s.surfaces] == counts.tolist()
    for surf in s.surfaces:
        assert surf.normal.shape == (3,)
        assert abs(np.linalg.norm(surf.normal) - 1.0) < 1e-12
        assert surf.normal[2] >= 0.0
        assert surf.kind in ("ground", "roof", "facade")
        assert (surf.building == -1) == (surf.kind == "ground")
        mask = s.labels == surf.id
        assert np.all(s.building_ids[mask] == surf.building)
    kinds = {surf.kind for surf in s.surfaces}
    assert kinds == {"ground", "roof", "facade"}
    # 1 ground + per building 1 or 2 roofs + 4 walls
    roofs = sum(1 if b.roof == "flat" else 2 for b in s.buildings)
    assert len(s.surfaces) == 1 + roofs + 4 * len(s.buildings)


def test_classification_codes(mls_scene):
    s = mls_scene
    kind_of = np.array([surf.kind for surf in s.surfaces])
    clutter = s.labels < 0
    assert clutter.sum() > 0
    assert np.all(s.classification[clutter] == ASPRS_HIGH_VEGETATION)
    assert np.all(s.building_ids[clutter] == -1)
    kinds = kind_of[s.labels[~clutter]]
    cls = s.classification[~clutter]
    assert np.all(cls[kinds == "ground"] == ASPRS_GROUND)
    assert np.all(cls[kinds != "ground"] == ASPRS_BUILDING)


def test_facade_normals_point_out_of_their_building(mls_scene):
    s = mls_scene
    for surf in s.surfaces:
        if surf.kind != "facade":
            continue
        assert surf.normal[2] == 0.0
        b = s.buildings[surf.building]
        outward = _surface_points(s, surf).mean(axis=0)[:2] - np.array(b.center_xy_m)
        assert outward @ surf.normal[:2] > 0.5 * min(b.length_m, b.width_m) * 0.99


def test_profiles_kinds():
    als = _small("als")
    assert {s.kind for s in als.surfaces} == {"ground", "roof"}
    assert np.all(als.classification[als.labels >= 0] != 0)
    tls = _small("tls", density_pts_m2=50.0)
    facade_pts = sum(s.n_points for s in tls.surfaces if s.kind == "facade")
    assert facade_pts > 0.5 * tls.points.shape[0]
    assert {s.kind for s in tls.surfaces} == {"ground", "roof", "facade"}
    no_ground = _small("mls", ground=False, vegetation=False)
    assert {s.kind for s in no_ground.surfaces} == {"roof", "facade"}
    assert np.all(no_ground.labels >= 0)


def test_default_densities_and_noise():
    scene = _small("als")
    assert scene.density_pts_m2 == PROFILES["als"].density_pts_m2 == 10.0
    assert scene.noise_m == PROFILES["als"].noise_m == 0.05
    assert PROFILES["mls"].density_pts_m2 == 100.0 and PROFILES["mls"].noise_m == 0.02
    assert PROFILES["tls"].density_pts_m2 == 500.0 and PROFILES["tls"].noise_m == 0.005


# --- densities on hand-placed buildings ----------------------------------------------


def test_density_flat_box_hand_placed():
    box = Building((30.0, 30.0), 20.0, 12.0, 8.0, rotation_rad=0.3, roof="flat")
    density = 200.0
    scene = make_scene(
        "mls", seed=2, extent_m=60.0, buildings=[box], density_pts_m2=density, vegetation=False
    )
    spec = PROFILES["mls"]
    expected_area = {"roof": [20.0 * 12.0], "facade": sorted([20.0 * 8.0] * 2 + [12.0 * 8.0] * 2)}
    for kind, factor in (("roof", spec.roof_factor), ("facade", spec.facade_factor)):
        surfs = [s for s in scene.surfaces if s.kind == kind]
        assert sorted(s.area_m2 for s in surfs) == pytest.approx(expected_area[kind])
        for surf in surfs:
            assert surf.density_pts_m2 == pytest.approx(density * factor)
            expected = density * factor * surf.area_m2
            assert abs(surf.n_points / expected - 1.0) < 0.15
    ground = [s for s in scene.surfaces if s.kind == "ground"][0]
    ground_area = 60.0**2 - 20.0 * 12.0
    assert ground.area_m2 == pytest.approx(ground_area)
    assert abs(ground.n_points / (density * spec.ground_factor * ground_area) - 1) < 0.15
    # no ground under the building
    gp = _surface_points(scene, ground)[:, :2] - box.center_xy_m
    u = np.array([math.cos(0.3), math.sin(0.3)])
    v = np.array([-u[1], u[0]])
    inside = (np.abs(gp @ u) < 10.0 - 0.01) & (np.abs(gp @ v) < 6.0 - 0.01)
    assert not inside.any()


def test_density_als_roof_hand_placed():
    box = Building((40.0, 40.0), 25.0, 20.0, 10.0, roof="flat")
    scene = make_scene("als", seed=4, extent_m=80.0, buildings=[box], vegetation=False)
    roof = [s for s in scene.surfaces if s.kind == "roof"][0]
    assert abs(roof.n_points / (10.0 * 25.0 * 20.0) - 1.0) < 0.15
    assert not any(s.kind == "facade" for s in scene.surfaces)


def test_gable_surfaces_hand_placed():
    pitch = math.radians(30.0)
    h, length, width = 6.0, 18.0, 10.0
    house = Building((25.0, 25.0), length, width, h, roof="gable", roof_pitch_rad=pitch)
    density, noise = 300.0, 0.01
    scene = make_scene(
        "mls",
        seed=3,
        extent_m=50.0,
        buildings=[house],
        density_pts_m2=density,
        noise_m=noise,
        vegetation=False,
        ground=False,
    )
    rise = 0.5 * width * math.tan(pitch)
    assert house.ridge_height_m == pytest.approx(h + rise)
    roofs = [s for s in scene.surfaces if s.kind == "roof"]
    assert len(roofs) == 2
    for roof in roofs:
        assert math.acos(roof.normal[2]) == pytest.approx(pitch)
        area = length * 0.5 * width / math.cos(pitch)
        assert roof.area_m2 == pytest.approx(area)
        assert abs(roof.n_points / (density * 0.25 * area) - 1.0) < 0.15
        z = _surface_points(scene, roof)[:, 2]
        assert z.max() == pytest.approx(h + rise, abs=0.1)
        assert z.min() == pytest.approx(h, abs=0.1)
    # end walls (normal along x, the long axis): pentagons = rectangle + triangle
    ends = [s for s in scene.surfaces if s.kind == "facade" and abs(s.normal[0]) > 0.99]
    assert len(ends) == 2
    pentagon = width * h + 0.5 * width * rise
    for wall in ends:
        assert wall.area_m2 == pytest.approx(pentagon)
        assert abs(wall.n_points / (density * pentagon) - 1.0) < 0.15
        pts = _surface_points(scene, wall)
        t = np.abs(pts[:, 1] - 25.0)  # distance from the ridge line, across the wall
        top = h + (0.5 * width - t) * math.tan(pitch)
        assert np.all(t <= 0.5 * width + 5 * noise)
        assert np.all(pts[:, 2] <= top + 5 * noise) and np.all(pts[:, 2] >= -5 * noise)
        frac_triangle = np.mean(pts[:, 2] > h)
        assert frac_triangle == pytest.approx(0.5 * width * rise / pentagon, abs=0.02)
    sides = [s for s in scene.surfaces if s.kind == "facade" and abs(s.normal[1]) > 0.99]
    assert sorted(s.area_m2 for s in sides) == pytest.approx([length * h] * 2)


# --- noise ---------------------------------------------------------------------------


@pytest.mark.parametrize("isotropic", [False, True])
def test_noise_std_along_normal(isotropic):
    scene = make_scene(
        "als", seed=11, n_buildings=1, noise_m=0.03, vegetation=False, isotropic_noise=isotropic
    )
    ground = [s for s in scene.surfaces if s.kind == "ground"][0]
    assert ground.n_points > 50_000
    dist = plane_distances(scene)[scene.labels == ground.id]
    assert np.std(dist) == pytest.approx(0.03, rel=0.1)
    assert abs(np.mean(dist)) < 0.003
    # positions are drawn before the noise: without noise the same seed gives the same
    # in-plane coordinates, which along-normal noise leaves untouched
    exact = make_scene("als", seed=11, n_buildings=1, noise_m=0.0, vegetation=False)
    assert exact.points.shape == scene.points.shape
    moved_xy = np.abs(scene.points[:, :2] - exact.points[:, :2]).max()
    if isotropic:
        assert moved_xy > 0.05
    else:
        assert moved_xy == 0.0


def test_zero_noise_is_exact():
    scene = _small("mls", noise_m=0.0, density_pts_m2=50.0)
    dist = plane_distances(scene)
    assert np.nanmax(np.abs(dist)) < 1e-9


# --- origin --------------------------------------------------------------------------


def test_origin_shift_exact():
    local = _small("mls", seed=9, density_pts_m2=60.0)
    shifted = _small("mls", seed=9, density_pts_m2=60.0, origin=tuple(UTM))
    np.testing.assert_array_equal(shifted.points, local.points + UTM)
    np.testing.assert_array_equal(shifted.labels, local.labels)
    for a, b in zip(local.surfaces, shifted.surfaces):
        np.testing.assert_array_equal(a.normal, b.normal)
        assert b.d == pytest.approx(a.d - a.normal @ UTM, abs=1e-6)
    np.testing.assert_allclose(plane_distances(shifted), plane_distances(local), atol=1e-6)
    # the same distances computed naively from the Hessian form
    planar = shifted.planar_mask()
    normals = np.array([s.normal for s in shifted.surfaces])[shifted.labels[planar]]
    ds = np.array([s.d for s in shifted.surfaces])[shifted.labels[planar]]
    naive = np.einsum("ij,ij->i", shifted.points[planar], normals) + ds
    np.testing.assert_allclose(naive, plane_distances(local)[planar], atol=1e-6)


# --- layout --------------------------------------------------------------------------


def _min_gap(poly_a, poly_b, step=0.2):
    """Smallest distance between the outlines of two polygons, by dense edge sampling."""

    def outline(poly):
        pts = []
        for a, b in zip(poly, np.roll(poly, -1, axis=0)):
            n = int(np.ceil(np.linalg.norm(b - a) / step)) + 1
            pts.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
        return np.concatenate(pts)

    oa, ob = outline(poly_a), outline(poly_b)
    return np.min(np.linalg.norm(oa[:, None] - ob[None], axis=-1))


def test_random_buildings_inside_extent_and_apart():
    scene = make_scene("als", seed=21, n_buildings=8, extent_m=110.0, density_pts_m2=1.0)
    assert len(scene.buildings) == 8
    polys = [b.footprint_xy() for b in scene.buildings]
    for b, poly in zip(scene.buildings, polys):
        assert 8.0 <= b.length_m <= 25.0 and 8.0 <= b.width_m <= 25.0
        assert 4.0 <= b.height_m <= 15.0
        assert poly.min() >= 0.0 and poly.max() <= 110.0
    for i in range(len(polys)):
        for j in range(i + 1, len(polys)):
            # sampled outlines overestimate the gap by at most ~step / 2
            assert _min_gap(polys[i], polys[j]) >= 3.0
            for a, b in ((i, j), (j, i)):  # no footprint inside another
                rel = np.array(scene.buildings[a].center_xy_m) - polys[b].mean(axis=0)
                edges = polys[b][1:3] - polys[b][0:2]
                along = np.abs(edges @ rel) / np.linalg.norm(edges, axis=1)
                assert np.any(along > 0.5 * np.linalg.norm(edges, axis=1))


def test_trees_are_clutter_and_clear_of_buildings(mls_scene):
    s = mls_scene
    veg = s.points[s.labels < 0]
    assert veg.shape[0] > 100
    assert veg[:, 2].min() > 1.0
    for b in s.buildings:
        c, (length, width) = np.array(b.center_xy_m), (b.length_m, b.width_m)
        a = b.rotation_rad
        u, v = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
        rel = veg[:, :2] - c
        inside = (np.abs(rel @ u) < 0.5 * length) & (np.abs(rel @ v) < 0.5 * width)
        assert not inside.any()
    bare = make_scene("mls", seed=7, n_buildings=3, extent_m=70.0, vegetation=False)
    assert np.all(bare.labels >= 0)


def test_hand_placed_building_validation():
    ok = Building((20.0, 20.0), 10.0, 8.0, 5.0)
    with pytest.raises(InvalidParameterError, match="extent_m"):
        make_scene("als", buildings=[Building((2.0, 2.0), 10.0, 8.0, 5.0)], extent_m=40.0)
    with pytest.raises(InvalidParameterError, match="overlap"):
        make_scene("als", buildings=[ok, Building((25.0, 20.0), 10.0, 8.0, 5.0)], extent_m=40.0)
    with pytest.raises(InvalidParameterError, match="roof"):
        make_scene("als", buildings=[Building((20.0, 20.0), 10.0, 8.0, 5.0, roof="dome")])


# --- scaling -------------------------------------------------------------------------


@pytest.mark.parametrize("profile", ["mls", "als"])
def test_make_scene_n_points_hits_target(profile):
    scene = make_scene_n_points(200_000, profile, seed=0)
    assert abs(scene.points.shape[0] / 200_000 - 1.0) < 0.10
    assert len(scene.buildings) >= 1
    assert scene.density_pts_m2 == PROFILES[profile].density_pts_m2


def test_make_scene_n_points_refuses_layout_options():
    with pytest.raises(InvalidParameterError, match="extent_m"):
        make_scene_n_points(100_000, extent_m=50.0)
    with pytest.raises(InvalidParameterError, match="n_points"):
        make_scene_n_points(0)
    with pytest.raises(InvalidParameterError, match="n_points"):
        make_scene_n_points(1000, "tls")  # one TLS building alone has far more points


# --- bad parameters ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"profile": "uav"}, "profile"),
        ({"density_pts_m2": 0.0}, "density_pts_m2"),
        ({"density_pts_m2": -5.0}, "density_pts_m2"),
        ({"density_pts_m2": float("nan")}, "density_pts_m2"),
        ({"noise_m": -0.01}, "noise_m"),
        ({"extent_m": 0.0}, "extent_m"),
        ({"extent_m": -10.0}, "extent_m"),
        ({"n_buildings": -1}, "n_buildings"),
        ({"n_buildings": 2.5}, "n_buildings"),
        ({"seed": -1}, "seed"),
        ({"origin": (1.0, 2.0)}, "origin"),
        ({"origin": (1.0, 2.0, float("inf"))}, "origin"),
        ({"roof_kinds": ("flat", "dome")}, "roof_kinds"),
        ({"roof_kinds": ()}, "roof_kinds"),
        ({"n_trees": -2}, "n_trees"),
    ],
)
def test_bad_parameters_raise(kwargs, name):
    kwargs = dict(kwargs)
    profile = kwargs.pop("profile", "als")
    with pytest.raises(InvalidParameterError, match=name):
        make_scene(profile, **kwargs)


def test_too_many_buildings_raise_with_advice():
    with pytest.raises(InvalidParameterError, match="n_buildings=40.*increase extent_m"):
        make_scene("als", n_buildings=40, extent_m=60.0)
