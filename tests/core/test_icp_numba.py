"""The compiled CPU matcher of the batched windowed ICP (issue #29, ``backend="numba"``)
gives a fresh KD-tree query's pairs, the numpy closed-form normals and normal equations, and
``windowed_icp`` the numpy backend's field (needs Numba, an optional dependency)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba", reason="Numba is not installed")

from scipy.spatial import cKDTree  # noqa: E402
from test_icp import UTM, field_pair  # noqa: E402
from test_icp_cells import assert_same_field  # noqa: E402

from slipmap.core import icp_numba  # noqa: E402
from slipmap.core.icp import windowed_icp  # noqa: E402


def _clouds(seed, n_before=4000, n_src=700):
    """Targets on 10 x 10 m (0.1 m of relief) at a UTM offset, and source points inside."""
    rng = np.random.default_rng(seed)
    before = rng.uniform(0.0, 10.0, (n_before, 3)) * [1.0, 1.0, 0.1] + UTM
    src = rng.uniform(1.0, 9.0, (n_src, 3)) * [1.0, 1.0, 0.1] + UTM
    return rng, before, src


@pytest.fixture(params=[False, True], ids=["one-thread", "thread-pool"])
def pool(request, monkeypatch):
    """Kernels on the calling thread, or split in chunks over the thread pool."""
    if request.param:
        monkeypatch.setattr(icp_numba, "_cores", lambda: 3)
        monkeypatch.setitem(icp_numba._run.__kwdefaults__, "parallel_min", 1)
    return request.param


@pytest.mark.parametrize("gate", [np.inf, 0.12])
def test_pairs_equal_a_fresh_kdtree_query_over_small_and_large_moves(gate, pool):
    """Within the cached margins, beyond them (searched again), through the gate; two cells,
    each with its own centre, the coordinates at a UTM offset."""
    rng, before, src = _clouds(3)
    tree = cKDTree(before)
    seg = (src[:, 0] - UTM[0] > 5.0).astype(np.int64)
    centres = np.array([[2.5, 5.0, 0.0], [7.5, 5.0, 0.0]]) + UTM
    match = icp_numba.NumbaTargets(before).matcher(before, None, gate, None, centres, len(src))
    gi = np.arange(len(src))
    q = src.copy()
    for step in (0.0, 0.002, 0.01, 0.05, 0.3, 0.001, 0.0005):
        q = q + rng.normal(0.0, step, q.shape)
        d, ref = tree.query(q, distance_upper_bound=gate)
        j = match.nearest(q - centres[seg], seg, gi)
        found = j >= 0
        np.testing.assert_array_equal(found, np.isfinite(d))
        # the same target, or one at exactly the same distance (a tie)
        dj = np.linalg.norm(before[j[found]] - q[found], axis=1)
        np.testing.assert_allclose(dj, d[found], rtol=0, atol=1e-12)


def test_grid_knn_equals_the_kdtree_k_nearest():
    """The column search's k nearest (k = 4 and 12) are the KD-tree's, distances sorted,
    on uneven density (a dense patch in sparse ground) and for queries off the grid."""
    from slipmap.core.target_grid import target_grid

    rng = np.random.default_rng(11)
    sparse = rng.uniform(0.0, 20.0, (3000, 3)) * [1.0, 1.0, 0.2]
    dense = rng.uniform(5.0, 6.0, (4000, 3)) * [1.0, 1.0, 0.05]
    pts = np.vstack([sparse, dense]) + UTM
    g = target_grid(pts)
    q = np.vstack([rng.uniform(-3.0, 23.0, (500, 3)), rng.uniform(4.8, 6.2, (500, 3))])
    q = q * [1.0, 1.0, 0.2] + UTM - g.offset
    tree = cKDTree(g.points)
    for k in (4, 12):
        dref, _ = tree.query(q, k=k)
        d, j = np.empty(k), np.empty(k, dtype=np.int64)
        for i, (x, y, z) in enumerate(q):
            icp_numba._grid_knn(
                g.points, g.colstart, g.nx, g.ny, g.lo[0], g.lo[1], g.h, x, y, z, k, d, j
            )
            np.testing.assert_allclose(np.sqrt(d), dref[i], rtol=0, atol=1e-12)
            np.testing.assert_allclose(np.linalg.norm(g.points[j] - q[i], axis=1), dref[i],
                                       rtol=0, atol=1e-12)  # fmt: skip


def test_outside_the_grid_far_points_and_the_cells_box(pool):
    """Queries far beyond the targets' extent find the true nearest; a target outside the
    cell's box is refused (-1), as by the numpy matcher."""
    from slipmap.core.icp_cells import _Matcher

    rng, before, _ = _clouds(5, n_before=500)
    q = np.vstack([UTM + [-50.0, 3.0, 0.0], UTM + [30.0, 40.0, 5.0], UTM + [5.0, 5.0, 9.0]])
    q = np.vstack([q, rng.uniform(0.0, 10.0, (200, 3)) * [1.0, 1.0, 0.1] + UTM])
    tree = cKDTree(before)
    seg = np.zeros(len(q), dtype=np.int64)
    centre = np.array([[5.0, 5.0, 0.0]]) + UTM
    boxes = np.array([[2.0, 8.0, 1.0, 9.0]]) + UTM[[0, 0, 1, 1]]
    gi = np.arange(len(q))
    fast = icp_numba.NumbaTargets(before).matcher(before, None, np.inf, boxes, centre, len(q))
    ref = _Matcher(before, tree, None, np.inf, boxes, centre, len(q))
    j_fast = fast.nearest(q - centre, seg, gi)
    j_ref = ref._nearest(q, gi)
    tp = before[np.minimum(j_ref, len(before) - 1)]
    inbox = (tp[:, 0] >= boxes[0, 0]) & (tp[:, 0] <= boxes[0, 1])
    inbox &= (tp[:, 1] >= boxes[0, 2]) & (tp[:, 1] <= boxes[0, 3])
    np.testing.assert_array_equal(j_fast, np.where(inbox, j_ref, -1))
    assert np.all(j_fast[:2] < 0) and j_fast[2] >= 0 and (j_fast >= 0).sum() > 50


def test_target_normals_equal_the_numpy_closed_form_and_eigh(pool):
    """Normals from the grid's neighbourhoods equal ``_pca_normals`` of the KD-tree's (rough
    terrain, a flat patch, collinear points whose normal is undefined: NaN on both)."""
    from slipmap.core.icp import _NormalCache

    rng = np.random.default_rng(9)
    xy = rng.uniform(0.0, 10.0, (3000, 2))
    terrain = np.c_[xy, 0.3 * np.sin(xy[:, 0]) + 0.02 * rng.normal(size=len(xy))]
    flat = np.c_[rng.uniform(20.0, 22.0, (300, 2)), np.zeros(300)]
    line = np.c_[np.linspace(30.0, 32.0, 40), np.full(40, 30.0), np.zeros(40)]
    before = np.vstack([terrain, flat, line]) + UTM
    off = before.mean(axis=0)
    tree = cKDTree(before - off)
    ids = np.arange(len(before))
    ref = _NormalCache(before, tree, 12, offset=off)(ids)
    cache = _NormalCache(before, tree, 12, offset=off)
    cache.device = icp_numba.NumbaTargets(before)
    got = cache(ids)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    assert np.isnan(ref[-40:]).all() and np.isfinite(ref[:-40]).all()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


@pytest.mark.parametrize("p", [6, 12])
def test_normal_matrices_equal_the_numpy_reference(p):
    """The one-pass per-cell sums equal ``icp_cells._normal_matrices`` (an empty cell, zero
    weights; 12 parameters go to the reference itself)."""
    from slipmap.core.icp_cells import _normal_matrices

    rng = np.random.default_rng(4)
    seg = np.sort(rng.integers(0, 9, 5000))
    seg[seg == 3] = 4
    A, v, w = rng.normal(size=(5000, p)), rng.standard_t(3, 5000), rng.random(5000)
    w[::7] = 0.0
    for got, ref in zip(icp_numba.normal_matrices(A, w, v, seg, 10),
                        _normal_matrices(A, w, v, seg, 10)):  # fmt: skip
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize(
    "extra",
    [dict(cell_model="rigid", deform_passes=1), dict(cell_model="affine", deform_passes=1),
     dict(field_model="spline")],
    ids=["rigid", "affine", "spline"],
)  # fmt: skip
def test_windowed_icp_with_numba_equals_numpy(extra):
    """The whole field (passes, coarse level, the spline field) with the compiled pairs equals
    the numpy one: the same pairs, iterations and point counts."""
    before, after = field_pair(21, shift_left=np.array([0.08, -0.04, 0.02]), density=40)
    kw = dict(cell_m=5.0, min_points=200, coarse_to_fine=1, **extra)
    fast = windowed_icp(before, after, backend="numba", **kw)
    ref = windowed_icp(before, after, backend="numpy", **kw)
    # the same pairs; sums in another order (1e-15)
    assert_same_field(fast, ref, atol=1e-10)


def test_auto_backend_takes_numba_when_opencl_cannot_start(monkeypatch, caplog):
    """Without an OpenCL device ``backend="auto"`` takes the compiled CPU kernels."""
    from slipmap.core.opencl import backend

    monkeypatch.setattr(backend, "probe_runtime", lambda **kw: "no OpenCL device (test)")
    before, after = field_pair(4, shift_left=np.array([0.05, 0.0, 0.01]), density=20)
    kw = dict(cell_m=5.0, min_points=100)
    with caplog.at_level("INFO", logger="slipmap.core.icp"):
        auto = windowed_icp(before, after, backend="auto", **kw)
    ref = windowed_icp(before, after, backend="numpy", **kw)
    assert "no OpenCL device (test)" in caplog.text and "Numba" in caplog.text
    np.testing.assert_allclose(np.c_[auto.dx, auto.dy, auto.dz], np.c_[ref.dx, ref.dy, ref.dz],
                               rtol=0, atol=1e-10)  # fmt: skip


def test_a_forked_child_makes_its_own_thread_pool(monkeypatch):
    """The pool's threads do not survive a fork (Dask's or multiprocessing's workers): a
    child process starts a new pool instead of waiting on the parent's forever."""
    import multiprocessing as mp

    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork here")
    monkeypatch.setattr(icp_numba, "_cores", lambda: 2)
    monkeypatch.setitem(icp_numba._run.__kwdefaults__, "parallel_min", 1)
    _, before, src = _clouds(7, n_before=500, n_src=100)
    centre = np.array([[5.0, 5.0, 0.0]]) + UTM
    seg, gi = np.zeros(len(src), dtype=np.int64), np.arange(len(src))
    grid = icp_numba.NumbaTargets(before)
    ref = grid.matcher(before, None, np.inf, None, centre, len(src)).nearest(src - centre, seg, gi)
    with mp.get_context("fork").Pool(1) as pool:  # the parent's pool exists now
        got = pool.apply_async(_nearest_in_child, (before, src, centre)).get(timeout=120)
    np.testing.assert_array_equal(got, ref)


def _nearest_in_child(before, src, centre):
    icp_numba._cores = lambda: 2
    icp_numba._run.__kwdefaults__["parallel_min"] = 1
    seg, gi = np.zeros(len(src), dtype=np.int64), np.arange(len(src))
    m = icp_numba.NumbaTargets(before).matcher(before, None, np.inf, None, centre, len(src))
    return m.nearest(src - centre, seg, gi)
