"""The OpenCL kernels give the numpy kernels' results (needs PyOpenCL and an OpenCL device)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyopencl", reason="PyOpenCL is not installed")

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from slipmap.core.errors import DependencyError, InvalidParameterError  # noqa: E402
from slipmap.core.octree import build_octree  # noqa: E402
from slipmap.core.planes import NumpyKernels, segment_planes  # noqa: E402

pytestmark = pytest.mark.opencl

UTM = np.array([512_345.678, 4_123_456.789, 312.5])


@pytest.fixture(scope="module")
def ocl():
    from slipmap.core.opencl.backend import OpenCLKernels

    try:
        return OpenCLKernels()
    except DependencyError as exc:
        pytest.skip(f"no usable OpenCL device: {exc}")


@pytest.fixture(scope="module")
def ref():
    return NumpyKernels()


def _small_buffers(monkeypatch, ocl, points: int) -> None:
    """Make the device buffers hold only ``points`` points, to exercise chunking."""
    monkeypatch.setattr(ocl._rt, "max_alloc", 24 * points)


# --------------------------------------------------------------------------- encode


def _encode_cases():
    rng = np.random.default_rng(11)
    pts = rng.uniform(-50.0, 50.0, size=(20_000, 3)) + UTM
    pts -= 0.5 * (pts.min(axis=0) + pts.max(axis=0))  # centred, as segment_planes does
    for depth in (1, 7, 15, 21):
        lo = pts.min(axis=0)
        root = float(np.max(pts.max(axis=0) - lo)) * (1.0 + 1e-9)
        cells = 1 << depth
        yield pts, lo, cells / root, cells
    # boundary values: the corners, exact cell edges, just below/above them, outside the cube
    lo = np.array([-3.0, 2.0, -0.125])
    cells = 1 << 10
    scale = cells / 8.0
    edges = lo + np.arange(0, cells + 1)[:, None] / scale
    nudged = np.concatenate(
        [edges, np.nextafter(edges, -np.inf), np.nextafter(edges, np.inf), edges[::-1]]
    )
    special = np.array(
        [lo, lo - 1.0, lo + 8.0, lo + 100.0, [-np.inf, np.inf, 0.0], [1e300, -1e300, 0.0]]
    )
    yield np.concatenate([nudged, special]), lo, scale, cells


def test_encode_bit_identical(ocl, ref):
    for pts, lo, scale, cells in _encode_cases():
        got = ocl.encode(pts, lo, scale, cells)
        assert got.dtype == np.uint64 and got.shape == (pts.shape[0],)
        np.testing.assert_array_equal(got, ref.encode(pts, lo, scale, cells))


def test_encode_chunked_and_empty(ocl, ref, monkeypatch):
    pts, lo, scale, cells = next(_encode_cases())
    _small_buffers(monkeypatch, ocl, 3001)
    np.testing.assert_array_equal(
        ocl.encode(pts, lo, scale, cells), ref.encode(pts, lo, scale, cells)
    )
    out = ocl.encode(np.empty((0, 3)), lo, scale, cells)
    assert out.dtype == np.uint64 and out.shape == (0,)


def test_encode_as_octree_encoder(ocl):
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(5000, 3)) * [30.0, 20.0, 2.0]
    a = build_octree(pts)
    b = build_octree(pts, encoder=ocl.encode)
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_array_equal(a.order, b.order)


# --------------------------------------------------------------------------- node_fit


def _groups(seed: int, sizes=(1, 3, 2, 7, 8, 9, 40, 128, 129, 130, 1000, 5000)):
    """Points grouped by node: noisy planes in random orientations at UTM offsets, centred."""
    rng = np.random.default_rng(seed)
    counts = np.concatenate([sizes, rng.integers(1, 80, size=400)]).astype(np.int64)
    rng.shuffle(counts)
    parts = []
    for c in counts:
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        u = np.cross(n, [0.3, 0.5, 0.8])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        ab = rng.uniform(-1.0, 1.0, size=(c, 2)) * rng.uniform(0.2, 5.0)
        off = rng.normal(0.0, 0.02, size=(c, 1))
        parts.append(UTM + rng.uniform(-200, 200, 3) + ab[:, :1] * u + ab[:, 1:] * v + off * n)
    pts = np.concatenate(parts)
    pts -= 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    return pts, np.cumsum(counts) - counts, counts


def _check_fit(got, want, sub, starts, counts, thr):
    mean, evals, normal, n_within, within = got
    w_mean, w_evals, w_normal, w_nw, w_within = want
    m, n = starts.size, sub.shape[0]
    for a, shape, dtype in (
        (mean, (m, 3), np.float64),
        (evals, (m, 3), np.float64),
        (normal, (m, 3), np.float64),
        (n_within, (m,), np.int64),
        (within, (n,), np.bool_),
    ):
        assert a.shape == shape and a.dtype == dtype
    scale = np.abs(sub).max()
    np.testing.assert_allclose(mean, w_mean, rtol=1e-12, atol=1e-12 * scale)
    np.testing.assert_allclose(evals, w_evals, rtol=1e-12, atol=1e-12 * w_evals[:, 2:].max())
    # normals: defined (up to sign) where the smallest eigenvalue is well separated
    gap = (w_evals[:, 1] - w_evals[:, 0]) > 1e-6 * w_evals[:, 2]
    dot = np.abs(np.einsum("ij,ij->i", normal, w_normal))
    assert np.all(dot[gap] >= 1.0 - 1e-12)
    # within: identical except for points at the threshold (to rounding)
    node_of = np.repeat(np.arange(m), counts)
    dist = np.abs(np.einsum("ij,ij->i", sub - w_mean[node_of], w_normal[node_of]))
    clear = np.abs(dist - thr) > 1e-12 * max(thr, 1.0)
    np.testing.assert_array_equal(within[clear], w_within[clear])
    np.testing.assert_array_equal(n_within, np.add.reduceat(within.astype(np.int64), starts))
    sure = np.add.reduceat((~clear).astype(np.int64), starts) == 0
    np.testing.assert_array_equal(n_within[sure], w_nw[sure])


@pytest.mark.parametrize("seed", [0, 1])
def test_node_fit_matches_numpy(ocl, ref, seed):
    sub, starts, counts = _groups(seed)
    for thr in (0.0, 0.01, 0.03):
        got = ocl.node_fit(sub, starts, counts, thr)
        want = ref.node_fit(sub, starts, counts, thr)
        _check_fit(got, want, sub, starts, counts, thr)
        if thr > 0:
            assert 0 < got[3].sum() < sub.shape[0]


def test_node_fit_large_node_and_chunks(ocl, ref, monkeypatch):
    rng = np.random.default_rng(5)
    counts = np.array([70_000, 1, 3, 20_001, 40, 40, 40], dtype=np.int64)
    sub = rng.normal(size=(int(counts.sum()), 3)) * [5.0, 3.0, 0.01]
    starts = np.cumsum(counts) - counts
    want = ref.node_fit(sub, starts, counts, 0.01)
    _check_fit(ocl.node_fit(sub, starts, counts, 0.01), want, sub, starts, counts, 0.01)
    _small_buffers(monkeypatch, ocl, 100)  # every node on its own (one larger than a buffer)
    _check_fit(ocl.node_fit(sub, starts, counts, 0.01), want, sub, starts, counts, 0.01)


def test_plane_within_matches_numpy(ocl, ref, monkeypatch):
    sub, starts, counts = _groups(4)
    mean, _, normal, _, _ = ref.node_fit(sub, starts, counts, 0.02)
    origin = mean + 0.003  # any point per plane
    want = ref.plane_within(sub, starts, counts, origin, normal, 0.02)
    for max_points in (None, 500):
        if max_points:
            _small_buffers(monkeypatch, ocl, max_points)
        nw, w = ocl.plane_within(sub, starts, counts, origin, normal, 0.02)
        assert nw.dtype == np.int64 and w.dtype == np.bool_ and w.shape == (sub.shape[0],)
        np.testing.assert_array_equal(w, want[1])
        np.testing.assert_array_equal(nw, want[0])


def test_node_fit_empty_and_invalid(ocl):
    mean, evals, normal, n_within, within = ocl.node_fit(
        np.empty((0, 3)), np.empty(0, np.int64), np.empty(0, np.int64), 0.1
    )
    assert mean.shape == evals.shape == normal.shape == (0, 3)
    assert n_within.shape == within.shape == (0,)
    assert n_within.dtype == np.int64 and within.dtype == np.bool_
    nw, w = ocl.plane_within(
        np.empty((0, 3)), np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, 3)),
        np.empty((0, 3)), 0.1,
    )  # fmt: skip
    assert nw.shape == w.shape == (0,)
    with pytest.raises(InvalidParameterError):
        ocl.node_fit(np.zeros((5, 3)), np.array([0, 3]), np.array([2, 2]), 0.1)


# --------------------------------------------------------------------------- propagate_labels


def _csr(n: int, pairs: np.ndarray):
    """CSR of the symmetric graph of ``pairs``, as segment_planes builds it."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    code = np.unique(i * n + j)
    ei, ej = code // n, code % n
    nodes, first = np.unique(ei, return_index=True)
    return np.append(first, ei.size), ej, nodes


def _check_labels(ocl, ref, n, pairs):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    indptr, indices, nodes = _csr(n, pairs)
    got = ocl.propagate_labels(indptr, indices, nodes, n)
    assert got.dtype == np.int64 and got.shape == (n,)
    np.testing.assert_array_equal(got, ref.propagate_labels(indptr, indices, nodes, n))
    rows = np.repeat(nodes, np.diff(indptr))
    graph = coo_matrix((np.ones(rows.size), (rows, indices)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    smallest = np.full(comp.max() + 1, n)
    np.minimum.at(smallest, comp, np.arange(n))
    np.testing.assert_array_equal(got, smallest[comp])


@st.composite
def _graphs(draw):
    n = draw(st.integers(1, 60))
    edges = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=3 * n))
    return n, np.array(edges, dtype=np.int64).reshape(-1, 2)


@settings(
    max_examples=30,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(graph=_graphs())
def test_propagate_labels_property(ocl, ref, graph):
    n, pairs = graph
    _check_labels(ocl, ref, n, pairs)


def test_propagate_labels_long_paths_and_random(ocl, ref):
    rng = np.random.default_rng(9)
    n = 20_000
    perm = rng.permutation(n)  # long paths with random node numbers: worst case for min-label
    paths = np.c_[perm[:-1], perm[1:]]
    paths = paths[rng.random(n - 1) > 0.001]  # cut into ~20 paths
    _check_labels(ocl, ref, n, paths)
    _check_labels(ocl, ref, n, rng.integers(0, n, size=(n // 2, 2)))
    _check_labels(ocl, ref, 5, np.empty((0, 2)))  # no edges
    lab = ocl.propagate_labels(np.zeros(1, np.int64), np.empty(0, np.int64), np.empty(0), 0)
    assert lab.shape == (0,) and lab.dtype == np.int64


# --------------------------------------------------------------------------- end to end


def _scene(seed: int = 21) -> np.ndarray:
    """Two perpendicular noisy planes (ground, wall) and a tilted one (roof), UTM offsets."""
    rng = np.random.default_rng(seed)
    n1, n2, n3 = 14_000, 8_000, 8_000
    ground = np.c_[rng.uniform(0, 40, n1), rng.uniform(0, 40, n1), rng.normal(0, 0.01, n1)]
    wall = np.c_[20 + rng.normal(0, 0.01, n2), rng.uniform(0, 40, n2), rng.uniform(0.5, 12, n2)]
    t = np.radians(30.0)
    u, v = rng.uniform(0, 15, n3), rng.uniform(0, 30, n3)
    roof = np.c_[22 + u * np.cos(t), 5 + v, 12 + u * np.sin(t)]
    roof += rng.normal(0, 0.01, (n3, 1)) * np.array([-np.sin(t), 0.0, np.cos(t)])
    pts = np.concatenate([ground, wall, roof]) + UTM
    return pts[rng.permutation(pts.shape[0])]


def test_segment_planes_same_as_numpy(ocl):
    pts = _scene()
    a = segment_planes(pts, backend="numpy")
    b = segment_planes(pts, backend="opencl")
    assert b.parameters.backend == "opencl" and a.parameters.backend == "numpy"
    assert len(a) == len(b) >= 3
    # labels identical up to renumbering: the contingency of (numpy, opencl) labels is a bijection
    pairs = np.unique(np.c_[a.labels, b.labels], axis=0)
    assert np.unique(pairs[:, 0]).size == pairs.shape[0] == np.unique(pairs[:, 1]).size
    assert np.all((pairs[:, 0] == -1) == (pairs[:, 1] == -1))
    to_b = dict(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist()))
    ib = np.array([to_b[k] for k in range(len(a))])
    np.testing.assert_allclose(b.normals[ib], a.normals, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b.offsets[ib], a.offsets, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b.centroids[ib], a.centroids, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(b.n_points[ib], a.n_points)
    pa = a.parameters.to_dict()
    pb = b.parameters.to_dict()
    pa.pop("backend"), pb.pop("backend")
    assert pa == pb


@pytest.mark.parametrize(
    "case",
    ["two-walls", "d50-n0.01-s10-c0.6", "d300-n0.05-s10-c0.6", "d4-n0.002-s100-c0.3"],
)
def test_same_labels_on_clutter_and_refinement(ocl, case):
    """The clutter paths (robust leaf refits, split, merge, released and dropped planes) give
    both backends the same labels (issue #16)."""
    from slipmap.core.planetruth import make_plane_case, make_two_walls_case

    if case == "two-walls":
        pts = make_two_walls_case(seed=0).points
    else:
        d, n, sz, c = (float(v[1:]) for v in case.split("-"))
        pts = make_plane_case(
            density_pts_m2=d, noise_m=n, size_m=sz, clutter_fraction=c, seed=0
        ).points
    a = segment_planes(pts, backend="numpy")
    b = segment_planes(pts, backend="opencl")
    assert len(a) == len(b) >= 2
    np.testing.assert_array_equal(a.labels, b.labels)


def test_segment_planes_auto_uses_opencl(ocl):
    res = segment_planes(_scene(3)[:6000], backend="auto")
    assert res.parameters.backend == "opencl"


def test_device_choice_env(ocl, monkeypatch):
    from slipmap.core.opencl import backend
    from slipmap.core.planes import get_kernels

    name = ocl.device_name
    monkeypatch.setattr(backend, "_state", None)
    monkeypatch.setenv(backend.DEVICE_ENV, "no-such-opencl-device")
    with pytest.raises(DependencyError, match="no-such-opencl-device"):
        backend.OpenCLKernels()
    assert get_kernels("auto").name == "numpy"
    monkeypatch.setenv(backend.DEVICE_ENV, name[: max(3, len(name) // 2)].upper())
    assert backend.OpenCLKernels().device_name == name
