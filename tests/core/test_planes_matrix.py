"""Known-answer matrix of the automatic plane segmentation (slipmap.core.planetruth).

(a) the case generator: labels on their planes, clutter share, reproducibility, the resolvable
rule, the sub-area rule; (b) a representative subset of the density x noise x size x clutter
matrix, segmented with automatic parameters; (c) the two-walls case of a bug report.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from slipmap.core.errors import InvalidParameterError
from slipmap.core.planes import segment_planes
from slipmap.core.planetruth import (
    MIN_RESOLVABLE_POINTS,
    make_plane_case,
    make_two_walls_case,
    min_resolvable_extent_m,
    resolvable_surfaces,
    score_case,
)

UTM = (512345.0, 4231234.0, 85.0)


def _case(**kw):
    args = {"density_pts_m2": 10.0, "noise_m": 0.01, "size_m": 100.0, "clutter_fraction": 0.3}
    args.update(kw)
    args.setdefault("seed", 0)
    return make_plane_case(**args)


def _residuals(case):
    """Signed distance of every surface point to its own true plane."""
    on = case.labels >= 0
    lab = case.labels[on]
    # centre on the origin before the dot product: UTM-sized coordinates lose digits otherwise
    local = case.points[on] - case.origin
    d = case.offsets + case.normals @ case.origin
    return np.einsum("ij,ij->i", local, case.normals[lab]) + d[lab], lab


# --------------------------------------------------------------------- (a) the generator


@pytest.mark.parametrize("size", [10.0, 100.0])
def test_labels_lie_on_their_planes_within_5_sigma(size):
    case = _case(size_m=size, density_pts_m2=20.0, noise_m=0.01, seed=3, origin=UTM)
    r, lab = _residuals(case)
    assert np.max(np.abs(r)) <= 5 * case.noise_m
    # per surface: zero mean, standard deviation = noise (all surfaces pooled: 5 %)
    assert abs(np.std(r) / case.noise_m - 1.0) < 0.05
    assert abs(np.mean(r)) < 5 * case.noise_m / math.sqrt(r.size)
    counts = np.bincount(lab, minlength=case.n_surfaces)
    assert np.array_equal(counts, case.n_points)
    # every surface gets round(density * area) points
    assert np.array_equal(case.n_points, np.round(case.density_pts_m2 * case.areas_m2))
    # unit normals, upward or horizontal by convention
    assert np.allclose(np.linalg.norm(case.normals, axis=1), 1.0)
    assert np.all(case.normals[:, 2] >= -1e-12)


def test_noise_free_points_are_exactly_on_their_planes():
    case = _case(noise_m=0.0, clutter_fraction=0.0, origin=UTM)
    r, _ = _residuals(case)
    assert np.max(np.abs(r)) < 1e-6
    # offsets are for the shifted coordinates: n @ p + d == 0 (to float precision at UTM size)
    on = case.labels >= 0
    r_utm = np.einsum("ij,ij->i", case.points[on], case.normals[case.labels[on]])
    assert np.max(np.abs(r_utm + case.offsets[case.labels[on]])) < 1e-6


def test_scene_contents_scale_with_size():
    small = _case(size_m=10.0, clutter_fraction=0.0)
    assert small.kinds.count("ground") == 1 and small.kinds.count("wall") == 2
    assert small.kinds.count("roof") == 1
    walls = [i for i, k in enumerate(small.kinds) if k == "wall"]
    assert abs(small.normals[walls[0]] @ small.normals[walls[1]]) < 1e-12  # perpendicular
    # 10 m x 5 m above the ground at the centre; the 2-degree ground cuts up to 0.24 m off
    assert np.allclose(small.areas_m2[walls], 48.8, atol=0.4)
    ground = small.normals[small.kinds.index("ground")]
    assert math.degrees(math.acos(ground[2])) == pytest.approx(2.0, abs=1e-9)
    town = _case(size_m=100.0, density_pts_m2=1.0, clutter_fraction=0.0)
    n_roofs = town.kinds.count("roof")
    assert town.kinds.count("wall") == 24  # 6 buildings x 4 walls
    assert 6 <= n_roofs <= 12


@pytest.mark.parametrize("size", [10.0, 100.0])
@pytest.mark.parametrize("clutter", [0.0, 0.3, 0.6])
def test_clutter_fraction_within_2_percent(size, clutter):
    case = _case(size_m=size, clutter_fraction=clutter, density_pts_m2=4.0)
    assert abs(case.n_clutter / case.points.shape[0] - clutter) <= 0.02
    if clutter:
        # scattered clutter stays in the scene box grown by 20 %; vegetation in the footprint
        cl = case.points[case.labels < 0] - case.origin
        x0, y0, x1, y1 = case.footprint_m
        grow = 0.1 * (x1 - x0) + 1e-9
        assert np.all((cl[:, 0] >= x0 - grow) & (cl[:, 0] <= x1 + grow))
        assert np.all((cl[:, 1] >= y0 - grow) & (cl[:, 1] <= y1 + grow))
        assert case.notes == ""  # a tree in the scene: half of the clutter is vegetation


def test_same_arguments_same_arrays_and_seed_matters():
    a = _case(seed=7, clutter_fraction=0.6)
    b = _case(seed=7, clutter_fraction=0.6)
    for name in ("points", "labels", "normals", "offsets", "areas_m2", "n_points", "resolvable"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    c = _case(seed=8, clutter_fraction=0.6)
    assert a.points.shape != c.points.shape or not np.array_equal(a.points, c.points)


def test_same_town_at_every_density_and_origin():
    lo = _case(density_pts_m2=1.0, noise_m=0.002)
    hi = _case(density_pts_m2=50.0, noise_m=0.05, origin=UTM)
    assert np.array_equal(lo.normals, hi.normals)
    assert np.allclose(lo.offsets, hi.offsets + hi.normals @ np.asarray(UTM), atol=1e-6)
    assert np.array_equal(lo.areas_m2, hi.areas_m2)
    shifted = _case(origin=UTM)
    plain = _case()
    assert np.array_equal(shifted.labels, plain.labels)
    assert np.allclose(shifted.points - np.asarray(UTM), plain.points, atol=1e-8, rtol=0)


def test_resolvable_rule_on_hand_made_surfaces():
    # density 4: spacing 0.5 m, a leaf sqrt(30) * 0.5 = 2.74 m (8 sigmas = 0.4 m): need 8.2 m
    assert min_resolvable_extent_m(density_pts_m2=4.0, noise_m=0.05) == pytest.approx(
        3 * math.sqrt(30) * 0.5
    )
    # density 300: a leaf of 0.316 m, but 8 sigmas = 0.4 m: the noise decides, 1.2 m
    assert min_resolvable_extent_m(density_pts_m2=300.0, noise_m=0.05) == pytest.approx(1.2)
    got = resolvable_surfaces(
        n_points=np.array([200, 200, 89, 90, 90]),
        min_extent_m=np.array([8.2, 8.3, 10.0, 10.0, 8.25]),
        density_pts_m2=4.0,
        noise_m=0.05,
    )
    assert got.tolist() == [False, True, False, True, True]
    assert MIN_RESOLVABLE_POINTS == 90
    with pytest.raises(InvalidParameterError):
        resolvable_surfaces(
            n_points=np.array([1]), min_extent_m=np.array([1.0, 2.0]), density_pts_m2=1, noise_m=0
        )


def test_resolvable_rule_in_the_corner_scene():
    # at 4 pts/m2 a surface needs 8.2 m across: the 10 m ground only (walls are 5 m high);
    # at 300 pts/m2 and 2 mm, 0.95 m: everything, the 1.83 m canopy included; at 0.1 m of
    # noise 2.4 m: not the canopy
    def canopy(case):
        return case.kinds.index("roof")

    sparse = _case(size_m=10.0, density_pts_m2=4.0, noise_m=0.01, clutter_fraction=0.0)
    assert not sparse.resolvable[canopy(sparse)]
    assert sparse.min_extent_m[canopy(sparse)] == pytest.approx(1.8 / math.cos(math.radians(10)))
    assert sparse.resolvable.sum() == 1  # the ground
    dense = _case(size_m=10.0, density_pts_m2=300.0, noise_m=0.002, clutter_fraction=0.0)
    assert dense.resolvable.all()
    noisy = _case(size_m=10.0, density_pts_m2=300.0, noise_m=0.1, clutter_fraction=0.0)
    assert not noisy.resolvable[canopy(noisy)] and noisy.resolvable.sum() == 3
    # and the flags are the rule applied to the case's own counts and extents
    assert np.array_equal(
        dense.resolvable,
        resolvable_surfaces(
            n_points=dense.n_points,
            min_extent_m=dense.min_extent_m,
            density_pts_m2=300.0,
            noise_m=0.002,
        ),
    )


def test_sub_area_keeps_density_and_planes_of_the_town():
    budget = 300_000
    full = make_plane_case(
        density_pts_m2=1.0, noise_m=0.01, size_m=1000.0, clutter_fraction=0.0, seed=2
    )
    assert not full.subsampled_area and full.notes == ""
    sub = make_plane_case(
        density_pts_m2=300.0,
        noise_m=0.01,
        size_m=1000.0,
        clutter_fraction=0.3,
        seed=2,
        max_points=budget,
    )
    assert sub.subsampled_area and "sub-area" in sub.notes
    n = sub.points.shape[0]
    assert 0.7 * budget <= n <= budget
    x0, y0, x1, y1 = sub.footprint_m
    assert x1 - x0 == pytest.approx(y1 - y0) and x1 - x0 < 1000.0
    assert 0 <= x0 and x1 <= 1000.0 and 0 <= y0 and y1 <= 1000.0
    # density kept: every surface has round(300 * its area in the window) points
    assert np.array_equal(sub.n_points, np.round(300.0 * sub.areas_m2))
    assert sub.areas_m2.sum() <= full.areas_m2.sum()
    on = sub.points[sub.labels >= 0]
    tol = 5 * sub.noise_m  # walls facing x or y get their noise across the window's edge
    assert np.all((on[:, 0] >= x0 - tol) & (on[:, 0] <= x1 + tol))
    assert np.all((on[:, 1] >= y0 - tol) & (on[:, 1] <= y1 + tol))
    # a building and vegetation in the window, clutter share kept
    assert sub.kinds.count("wall") >= 1 and sub.kinds.count("roof") >= 1
    assert abs(sub.n_clutter / n - 0.3) <= 0.02
    # a window of the same town: each of its planes is one of the town's planes
    for nrm, d in zip(sub.normals, sub.offsets):
        match = (np.abs(full.normals @ nrm - 1.0) < 1e-12) & (np.abs(full.offsets - d) < 1e-9)
        assert match.any()


def test_bad_arguments():
    for kw in (
        {"density_pts_m2": 0.0},
        {"noise_m": -0.01},
        {"size_m": 1.0},
        {"clutter_fraction": 0.99},
        {"seed": -1},
        {"origin": (0.0, 0.0)},
        {"max_points": 10},
    ):
        with pytest.raises(InvalidParameterError):
            _case(**kw)


def test_score_case_counts_only_resolvable_surfaces_for_recall():
    # density 50, noise 0.15: surfaces need 3.6 m; the 1.8 m canopy is not resolvable
    case = _case(size_m=10.0, density_pts_m2=50.0, noise_m=0.15, clutter_fraction=0.3)
    canopy = case.kinds.index("roof")
    assert not case.resolvable[canopy]
    perfect = case.labels.copy()
    s = score_case(case, perfect)
    assert s["recall"] == 1.0 and s["precision"] == 1.0 and s["n_merged"] == 0
    assert s["n_planes"] == case.n_surfaces and s["n_resolvable"] == 3
    # the non-resolvable canopy left unlabelled: no loss
    pred = perfect.copy()
    pred[case.labels == canopy] = -1
    assert score_case(case, pred)["recall"] == 1.0
    # a wall lost: recall 2/3; clutter labelled: precision drops
    wall = case.kinds.index("wall")
    pred[case.labels == wall] = -1
    pred[case.labels < 0] = 0
    s = score_case(case, pred)
    assert s["recall"] == pytest.approx(2 / 3, abs=1e-4) and s["missed"] == [wall]
    assert s["precision"] < 1.0
    # two walls under one label: merged
    pred = perfect.copy()
    pred[case.labels == wall] = case.kinds.index("wall", wall + 1)
    assert score_case(case, pred)["n_merged"] == 1


# --------------------------------------------------------------------- (b) matrix subset

# A half fraction of {4, 50, 300} x {0.002, 0.05} x {10, 100} x {0, 0.6}: for each density,
# four (noise, size, clutter) corners, each level of each factor twice.
SUBSET = [
    (4.0, 0.002, 10.0, 0.0),
    (4.0, 0.002, 100.0, 0.6),
    (4.0, 0.05, 10.0, 0.6),
    (4.0, 0.05, 100.0, 0.0),
    (50.0, 0.002, 10.0, 0.6),
    (50.0, 0.002, 100.0, 0.0),
    (50.0, 0.05, 10.0, 0.0),
    (50.0, 0.05, 100.0, 0.6),
    (300.0, 0.002, 10.0, 0.0),
    (300.0, 0.002, 100.0, 0.6),
    (300.0, 0.05, 10.0, 0.6),
    (300.0, 0.05, 100.0, 0.0),
]


@pytest.mark.slow
@pytest.mark.parametrize(
    "density, noise, size, clutter",
    SUBSET,
    ids=[f"d{d:g}-n{n:g}-s{s:g}-c{c:g}" for d, n, s, c in SUBSET],
)
def test_matrix_subset_known_answer(density, noise, size, clutter):
    case = make_plane_case(
        density_pts_m2=density, noise_m=noise, size_m=size, clutter_fraction=clutter, seed=0
    )
    res = segment_planes(case.points)
    s = score_case(case, res.labels)
    p = res.parameters
    info = (
        f"{s}; spacing est {p.point_spacing_m:.4g} (true {case.point_spacing_m:.4g}), "
        f"noise est {p.noise_m:.4g} (true {noise:g}), {case.points.shape[0]} points"
    )
    assert s["recall"] >= 0.9, info
    assert s["precision"] >= 0.95, info
    assert s["n_merged"] == 0, info


# --------------------------------------------------------------------- (c) bug report


def test_two_walls_with_scattered_clutter():
    case = make_two_walls_case(
        density_pts_m2=80.0,
        noise_m=0.005,
        n_clutter=500,
        clutter_box=((-20.0, 30.0), (-20.0, 30.0), (-5.0, 20.0)),
        seed=0,
    )
    assert case.n_points.tolist() == [4000, 4000] and case.n_clutter == 500
    assert case.resolvable.all()
    res = segment_planes(case.points)
    s = score_case(case, res.labels)
    p = res.parameters
    info = (
        f"{s}; spacing est {p.point_spacing_m:.4g} (true {case.point_spacing_m:.4g}), "
        f"noise est {p.noise_m:.4g} (true 0.005)"
    )
    assert len(res) == 2, info
    assert s["recall"] == 1.0, info
    assert s["precision"] >= 0.95, info
