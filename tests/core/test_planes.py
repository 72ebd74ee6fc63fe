"""Planar segmentation: hand-placed cases, synthetic scenes with truth, invariances, bad input."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from slipmap.core.errors import InputDataError, InvalidParameterError
from slipmap.core.evaluation import score_segmentation
from slipmap.core.planes import NumpyKernels, segment_planes
from slipmap.core.synthetic import make_scene

UTM = np.array([512345.0, 4231234.0, 85.0])


def _plane(rng, n, size, noise, normal=(0, 0, 1), centre=(0, 0, 0)):
    """n points on a square of edge ``size`` around ``centre`` in the plane of ``normal``."""
    nrm = np.asarray(normal, float) / np.linalg.norm(normal)
    helper = np.array([1.0, 0, 0]) if abs(nrm[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(nrm, helper)
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    ab = rng.uniform(-size / 2, size / 2, (n, 2))
    return (
        np.asarray(centre, float)
        + ab[:, :1] * u
        + ab[:, 1:] * v
        + rng.normal(0, noise, (n, 1)) * nrm
    )


def _agreement(a, b):
    """Fraction of points whose labels agree under the best one-to-one matching of labels."""
    from scipy.optimize import linear_sum_assignment

    m = (a >= 0) | (b >= 0)
    ua, ia = np.unique(a[m], return_inverse=True)
    ub, ib = np.unique(b[m], return_inverse=True)
    table = np.zeros((ua.size, ub.size))
    np.add.at(table, (ia, ib), 1)
    r, c = linear_sum_assignment(-table)
    return table[r, c].sum() / m.sum()


# --------------------------------------------------------------------- hand-placed cases


def test_single_plane():
    rng = np.random.default_rng(0)
    pts = _plane(rng, 8000, 10.0, 0.01, normal=(0.2, -0.1, 1.0)) + UTM
    res = segment_planes(pts)
    assert len(res) == 1
    true_n = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    assert abs(res.normals[0] @ true_n) > 1 - 1e-5
    assert res.normals[0, 2] > 0
    assert np.mean(res.labels == 0) > 0.99
    assert res.rms[0] == pytest.approx(0.01, rel=0.05)
    # Hessian form holds at the centroid, in input (UTM) coordinates
    assert res.normals[0] @ res.centroids[0] + res.offsets[0] == pytest.approx(0, abs=1e-6)
    assert np.allclose(res.centroids[0], pts.mean(axis=0), atol=0.05)
    assert res.parameters.noise_m == pytest.approx(0.01, rel=0.2)


def test_two_perpendicular_planes_sharing_an_edge():
    rng = np.random.default_rng(1)
    floor = _plane(rng, 10000, 10.0, 0.01, normal=(0, 0, 1), centre=(0, 0, 0))
    wall = _plane(rng, 10000, 10.0, 0.01, normal=(1, 0, 0), centre=(5.0, 0, 5.0))
    pts = np.vstack([floor, wall])
    truth = np.repeat([0, 1], 10000)
    res = segment_planes(pts)
    assert len(res) == 2
    assert abs(res.normals[0] @ res.normals[1]) < 1e-3
    assert _agreement(truth, res.labels.astype(int)) > 0.98
    s = score_segmentation(truth, res.labels)
    assert s.n_merged == 0 and s.precision == 1.0


def test_plane_with_sphere_clutter():
    rng = np.random.default_rng(2)
    plane = _plane(rng, 10000, 10.0, 0.01)
    # a boulder-sized ball, curved at leaf scale, at twice the plane's density
    d = rng.normal(size=(1000, 3))
    r = 0.6 + rng.normal(0, 0.01, (1000, 1))
    sphere = d / np.linalg.norm(d, axis=1, keepdims=True) * r + [1.0, -2.0, 2.0]
    res = segment_planes(np.vstack([plane, sphere]))
    assert len(res) == 1
    assert np.mean(res.labels[:10000] == 0) > 0.98
    assert np.mean(res.labels[10000:] == -1) > 0.95


def test_parallel_planes_close_together_are_not_merged():
    rng = np.random.default_rng(5)
    a = _plane(rng, 8000, 8.0, 0.01, centre=(0, 0, 0))
    b = _plane(rng, 8000, 8.0, 0.01, centre=(8.0, 0, 0.3))  # a 30 cm step, touching
    res = segment_planes(np.vstack([a, b]))
    truth = np.repeat([0, 1], 8000)
    assert score_segmentation(truth, res.labels).n_merged == 0
    assert _agreement(truth, res.labels.astype(int)) > 0.97


def test_no_planes_is_a_warning_and_empty_result(caplog):
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 10, (3000, 3))
    with caplog.at_level("WARNING"):
        res = segment_planes(pts)
    assert len(res) == 0
    assert np.all(res.labels == -1)
    assert res.normals.shape == (0, 3) and res.to_records() == []
    assert "no planes" in caplog.text


def test_explicit_parameters_are_used():
    rng = np.random.default_rng(4)
    pts = _plane(rng, 4000, 10.0, 0.01)
    res = segment_planes(
        pts,
        min_node_size_m=0.8,
        planarity_threshold_m=0.05,
        planarity_ratio=0.8,
        angle_threshold_deg=10,
        distance_threshold_m=0.06,
        min_plane_points=50,
        min_leaf_points=8,
    )
    p = res.parameters
    assert 0.8 <= p.min_node_size_m < 1.6
    assert (p.planarity_threshold_m, p.planarity_ratio, p.angle_threshold_deg) == (0.05, 0.8, 10)
    assert (p.distance_threshold_m, p.min_plane_points, p.min_leaf_points) == (0.06, 50, 8)
    assert p.automatic == ("max_node_size_m",)
    assert len(res) == 1


# --------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "pts",
    [
        np.empty((0, 3)),
        np.zeros((1, 3)),
        np.zeros((2, 3)),
        np.ones((100, 3)),
        np.array([[0.0, 0, 0], [1, np.nan, 0], [2, 0, 0], [3, 1, 0]]),
        np.array([[0.0, 0, 0], [1, np.inf, 0], [2, 0, 0], [3, 1, 0]]),
    ],
)
def test_bad_points(pts):
    with pytest.raises(InputDataError):
        segment_planes(pts)


@pytest.mark.parametrize(
    "kw",
    [
        {"planarity_ratio": 0},
        {"planarity_ratio": 1.5},
        {"min_node_size_m": -1},
        {"planarity_threshold_m": 0},
        {"angle_threshold_deg": 95},
        {"distance_threshold_m": float("nan")},
        {"min_plane_points": 2},
        {"min_leaf_points": 1},
        {"backend": "cuda"},
    ],
)
def test_bad_parameters(kw):
    rng = np.random.default_rng(0)
    with pytest.raises(InvalidParameterError, match=next(iter(kw))):
        segment_planes(_plane(rng, 500, 5, 0.01), **kw)


def test_wrong_shape():
    with pytest.raises(InvalidParameterError, match="shape"):
        segment_planes(np.zeros((10, 2)))


def test_input_not_modified():
    rng = np.random.default_rng(0)
    pts = _plane(rng, 3000, 5, 0.01) + UTM
    before = pts.copy()
    segment_planes(pts)
    assert np.array_equal(pts, before)


# --------------------------------------------------------------------- region growing


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 300), density=st.floats(0.001, 0.05))
def test_label_propagation_equals_connected_components(seed, n, density):
    rng = np.random.default_rng(seed)
    m = max(1, int(density * n * n))
    a = rng.integers(0, n, m)
    b = rng.integers(0, n, m)
    keep = a != b
    a, b = a[keep], b[keep]
    code = np.unique(np.concatenate([a * n + b, b * n + a]))
    i, j = code // n, code % n
    nodes, first = np.unique(i, return_index=True)
    indptr = np.append(first, i.size)
    lab = NumpyKernels().propagate_labels(indptr, j, nodes, n)
    _, ref = connected_components(coo_matrix((np.ones(i.size), (i, j)), shape=(n, n)))
    # same partition, and each label is the smallest member of its component
    for c in np.unique(ref):
        members = np.flatnonzero(ref == c)
        assert np.all(lab[members] == members.min())


# --------------------------------------------------------------------- synthetic scenes


@pytest.fixture(scope="module")
def mls_scene():
    return make_scene("mls", seed=11, noise_m=0.02, origin=UTM)


@pytest.fixture(scope="module")
def mls_result(mls_scene):
    return segment_planes(mls_scene.points)


def test_mls_scene_known_answer(mls_scene, mls_result):
    s = score_segmentation(mls_scene.labels, mls_result.labels, min_surface_points=200)
    assert s.n_surfaces >= 20
    assert s.recall >= 0.90, s
    assert s.precision >= 0.95, s
    assert s.n_merged == 0, s
    assert s.purity >= 0.98, s
    # automatic noise estimate close to the truth
    assert mls_result.parameters.noise_m == pytest.approx(0.02, rel=0.25)


def test_mls_planes_match_true_planes(mls_scene, mls_result):
    truth = {s.id: s for s in mls_scene.surfaces}
    checked = 0
    for k in range(len(mls_result)):
        t = mls_scene.labels[mls_result.labels == k]
        t = t[t >= 0]
        if t.size < 500:
            continue
        s = truth[int(np.bincount(t).argmax())]
        assert abs(mls_result.normals[k] @ s.normal) > math.cos(math.radians(1.0))
        # the fitted plane passes through the true plane at the centroid (within 1 cm)
        assert abs(s.normal @ mls_result.centroids[k] + s.d) < 0.01
        checked += 1
    assert checked >= 15


def test_als_roofs_known_answer():
    scene = make_scene("als", seed=12, density_pts_m2=10.0, noise_m=0.05, ground=False)
    res = segment_planes(scene.points)
    s = score_segmentation(scene.labels, res.labels, min_surface_points=200)
    assert s.n_surfaces >= 6
    assert s.recall >= 0.90, s
    assert s.precision >= 0.95, s
    assert s.n_merged == 0, s


# --------------------------------------------------------------------- invariances


@pytest.fixture(scope="module")
def small_scene():
    return make_scene("mls", seed=21, n_buildings=2, extent_m=55.0, vegetation=True)


@pytest.fixture(scope="module")
def small_result(small_scene):
    return segment_planes(small_scene.points)


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**31))
def test_permuting_points_permutes_labels(small_scene, small_result, seed):
    perm = np.random.default_rng(seed).permutation(small_scene.points.shape[0])
    res = segment_planes(small_scene.points[perm])
    assert np.array_equal(res.labels, small_result.labels[perm])
    assert np.allclose(res.normals, small_result.normals, atol=1e-9)


@settings(max_examples=5, deadline=None)
@given(
    quarter_turns=st.integers(0, 3),
    shift=st.tuples(*[st.floats(-1e6, 1e6, allow_nan=False)] * 2, st.floats(-1e3, 1e3)),
)
def test_grid_symmetric_rigid_motion_leaves_segmentation_unchanged(
    small_scene, small_result, quarter_turns, shift
):
    """Translations and quarter turns about z map the octree onto itself: same labels."""
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][quarter_turns]
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)
    t = np.array(shift)
    moved = small_scene.points @ rot.T + t
    res = segment_planes(moved)
    assert _agreement(res.labels.astype(int), small_result.labels.astype(int)) > 0.999
    # planes move with the points: match by point sets
    for k in range(len(small_result)):
        m = small_result.labels == k
        k2 = np.bincount(res.labels[m][res.labels[m] >= 0]).argmax()
        assert abs(res.normals[k2] @ (rot @ small_result.normals[k])) > 1 - 1e-9
        assert np.allclose(res.centroids[k2], rot @ small_result.centroids[k] + t, atol=1e-5)


@settings(max_examples=4, deadline=None)
@given(
    angles=st.tuples(st.floats(-np.pi, np.pi), st.floats(-0.3, 0.3), st.floats(-0.3, 0.3)),
    shift=st.tuples(*[st.floats(-1e5, 1e5, allow_nan=False)] * 3),
)
def test_any_rigid_motion_transforms_planes(small_scene, small_result, angles, shift):
    """A general rotation changes the octree grid, so boundary points may move between planes;
    the planes themselves must transform with the points."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("zyx", angles).as_matrix()
    t = np.array(shift)
    moved = small_scene.points @ rot.T + t
    res = segment_planes(moved)
    assert _agreement(res.labels.astype(int), small_result.labels.astype(int)) > 0.97
    big = np.flatnonzero(small_result.n_points >= 500)
    for k in big:
        m = small_result.labels == k
        k2 = np.bincount(res.labels[m][res.labels[m] >= 0]).argmax()
        assert abs(res.normals[k2] @ (rot @ small_result.normals[k])) > math.cos(math.radians(0.5))
        dist = res.normals[k2] @ (rot @ small_result.centroids[k] + t) + res.offsets[k2]
        assert abs(dist) < 0.01


def test_progress_is_reported_and_cancellation_stops():
    from slipmap.core.errors import CancelledError

    rng = np.random.default_rng(9)
    pts = _plane(rng, 5000, 10.0, 0.01)
    seen = []
    segment_planes(pts, progress=lambda f, m: seen.append(f))
    assert seen[-1] == 1.0 and all(0 <= f <= 1 for f in seen)
    assert all(b >= a for a, b in zip(seen, seen[1:]))

    def cancel(fraction, message):
        if fraction > 0.25:
            raise CancelledError("stop")

    with pytest.raises(CancelledError):
        segment_planes(pts, progress=cancel)


@pytest.mark.parametrize("seed", [0, 1])
def test_numpy_node_fit_equals_the_slow_reference(seed):
    """The vectorised node fit (NumpyKernels.node_fit) against the per-node loop beside it
    (node_fit_reference): noisy planes in random orientations, centred, groups of 1-300."""
    from slipmap.core.planes import NumpyKernels, node_fit_reference

    rng = np.random.default_rng(seed)
    counts = rng.integers(1, 300, size=120).astype(np.int64)
    parts = []
    for c in counts:
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        u = np.cross(n, [0.3, 0.5, 0.8])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        ab = rng.uniform(-2.0, 2.0, size=(c, 2))
        off = rng.normal(0.0, 0.02, size=(c, 1))
        parts.append(rng.uniform(-50, 50, 3) + ab[:, :1] * u + ab[:, 1:] * v + off * n)
    sub = np.concatenate(parts)
    starts = np.cumsum(counts) - counts
    got = NumpyKernels().node_fit(sub, starts, counts, 0.03)
    want = node_fit_reference(sub, starts, counts, 0.03)
    mean, evals, normal, n_within, within = got
    np.testing.assert_allclose(mean, want[0], rtol=0, atol=1e-11)
    np.testing.assert_allclose(evals, want[1], rtol=1e-9, atol=1e-14)
    gap = (want[1][:, 1] - want[1][:, 0]) > 1e-6 * want[1][:, 2]
    dot = np.abs(np.einsum("ij,ij->i", normal, want[2]))
    assert np.all(dot[gap] >= 1.0 - 1e-9)
    node_of = np.repeat(np.arange(counts.size), counts)
    dist = np.abs(np.einsum("ij,ij->i", sub - want[0][node_of], want[2][node_of]))
    clear = np.abs(dist - 0.03) > 1e-9
    np.testing.assert_array_equal(within[clear], want[4][clear])
    sure = np.add.reduceat((~clear).astype(np.int64), starts) == 0
    np.testing.assert_array_equal(n_within[sure], want[3][sure])
