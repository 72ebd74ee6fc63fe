"""The OpenCL matcher of the batched windowed ICP (issue #18) gives a fresh KD-tree query's
pairs, and ``windowed_icp(backend="opencl")`` the numpy backend's field (needs PyOpenCL and
an OpenCL device)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyopencl", reason="PyOpenCL is not installed")

from scipy.spatial import cKDTree  # noqa: E402
from test_icp import UTM, field_pair  # noqa: E402
from test_icp_cells import assert_same_field  # noqa: E402

from slipmap.core.errors import DependencyError, InvalidParameterError  # noqa: E402
from slipmap.core.icp import windowed_icp  # noqa: E402

pytestmark = pytest.mark.opencl


def _grid(before):
    from slipmap.core.opencl.nearest import GridTargets

    try:
        return GridTargets(before)
    except DependencyError as exc:
        pytest.skip(f"no usable OpenCL device: {exc}")


def _clouds(seed, n_before=4000, n_src=700):
    """Targets on 10 x 10 m (0.1 m of relief) at a UTM offset, and source points inside."""
    rng = np.random.default_rng(seed)
    before = rng.uniform(0.0, 10.0, (n_before, 3)) * [1.0, 1.0, 0.1] + UTM
    src = rng.uniform(1.0, 9.0, (n_src, 3)) * [1.0, 1.0, 0.1] + UTM
    return rng, before, src


@pytest.mark.parametrize("gate", [np.inf, 0.12])
def test_pairs_equal_a_fresh_kdtree_query_over_small_and_large_moves(gate):
    """Within the cached margins, beyond them (searched again), through the gate; two cells,
    each with its own centre, the coordinates at a UTM offset."""
    from slipmap.core.opencl.nearest import CellNearest

    rng, before, src = _clouds(3)
    tree = cKDTree(before)
    seg = (src[:, 0] - UTM[0] > 5.0).astype(np.int64)
    centres = np.array([[2.5, 5.0, 0.0], [7.5, 5.0, 0.0]]) + UTM
    grid = _grid(before)
    match = CellNearest(before, grid, None, gate, None, centres, len(src))
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


def test_outside_the_grid_far_points_and_the_cells_box():
    """Queries far beyond the targets' extent find the true nearest; a target outside the
    cell's box is refused (-1), as by the numpy matcher."""
    from slipmap.core.icp_cells import _Matcher
    from slipmap.core.opencl.nearest import CellNearest

    rng, before, _ = _clouds(5, n_before=500)
    q = np.vstack([UTM + [-50.0, 3.0, 0.0], UTM + [30.0, 40.0, 5.0], UTM + [5.0, 5.0, 9.0]])
    q = np.vstack([q, rng.uniform(0.0, 10.0, (200, 3)) * [1.0, 1.0, 0.1] + UTM])
    tree = cKDTree(before)
    seg = np.zeros(len(q), dtype=np.int64)
    centre = np.array([[5.0, 5.0, 0.0]]) + UTM
    boxes = np.array([[2.0, 8.0, 1.0, 9.0]]) + UTM[[0, 0, 1, 1]]
    gi = np.arange(len(q))
    cl = CellNearest(before, _grid(before), None, np.inf, boxes, centre, len(q))
    ref = _Matcher(before, tree, None, np.inf, boxes, centre, len(q))
    j_cl = cl.nearest(q - centre, seg, gi)
    j_ref = ref._nearest(q, gi)
    tp = before[np.minimum(j_ref, len(before) - 1)]
    inbox = (tp[:, 0] >= boxes[0, 0]) & (tp[:, 0] <= boxes[0, 1])
    inbox &= (tp[:, 1] >= boxes[0, 2]) & (tp[:, 1] <= boxes[0, 3])
    np.testing.assert_array_equal(j_cl, np.where(inbox, j_ref, -1))
    assert np.all(j_cl[:2] < 0) and j_cl[2] >= 0 and (j_cl >= 0).sum() > 50


def test_target_normals_equal_the_numpy_closed_form_and_eigh():
    """Normals from the device's neighbourhoods equal ``_pca_normals`` of the KD-tree's (rough
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
    cache.device = _grid(before)
    got = cache(ids)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
    assert np.isnan(ref[-40:]).all() and np.isfinite(ref[:-40]).all()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    "extra",
    [dict(cell_model="rigid", deform_passes=1), dict(cell_model="affine", deform_passes=1),
     dict(field_model="spline")],
    ids=["rigid", "affine", "spline"],
)  # fmt: skip
def test_windowed_icp_on_opencl_equals_numpy(extra):
    """The whole field (passes, coarse level, the spline field) with the OpenCL pairs equals
    the numpy one."""
    before, after = field_pair(21, shift_left=np.array([0.08, -0.04, 0.02]), density=40)
    kw = dict(cell_m=5.0, min_points=200, coarse_to_fine=1, **extra)
    try:
        fast = windowed_icp(before, after, backend="opencl", **kw)
    except DependencyError as exc:
        pytest.skip(f"no usable OpenCL device: {exc}")
    ref = windowed_icp(before, after, backend="numpy", **kw)
    # the same pairs; the normals' neighbourhoods summed in another order (1e-15). The
    # spline's data weights differ from cell to cell by their surface share (icp_blocks.
    # surface_share; F 1-48 on lone-star's lobe), and its solve carries that rounding to
    # 1-5e-10 m of the motions and sigmas (2-4e-11 m with weights alike): a nanometre bound
    assert_same_field(fast, ref, atol=1e-9)


def test_unknown_backend_is_refused_by_name():
    before, after = field_pair(1, shift_left=np.zeros(3), density=10)
    with pytest.raises(InvalidParameterError, match="backend"):
        windowed_icp(before, after, backend="cuda")
