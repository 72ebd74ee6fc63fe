"""Morton keys, linear octree and the mixed-level 26-neighbourhood."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipmap.core.errors import InputDataError, InvalidParameterError
from slipmap.core.octree import (
    build_octree,
    leaf_neighbours,
    leaf_neighbours_reference,
    morton_decode,
    morton_encode,
    neighbour_offsets,
)


def test_morton_known_values():
    ijk = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 0, 0], [0, 0, 2]])
    assert morton_encode(ijk).tolist() == [0, 1, 2, 4, 7, 8, 32]
    top = np.array([[2**21 - 1] * 3])
    assert int(morton_encode(top)[0]) == 2**63 - 1


@given(seed=st.integers(0, 2**32 - 1), bits=st.integers(1, 21))
def test_morton_roundtrip(seed, bits):
    ijk = np.random.default_rng(seed).integers(0, 2**bits, (200, 3))
    keys = morton_encode(ijk)
    assert np.array_equal(morton_decode(keys), ijk)
    assert int(keys.max()) < 2 ** (3 * bits)


def test_neighbour_offsets():
    off = neighbour_offsets()
    assert off.shape == (26, 3)
    assert len({tuple(o) for o in off}) == 26
    assert not np.any(np.all(off == 0, axis=1))


def test_octree_sorted_and_nodes_contain_points():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-50, 50, (5000, 3))
    tree = build_octree(pts, min_node_size_m=1.0)
    assert np.all(np.diff(tree.keys.astype(np.float64)) >= 0)
    assert np.array_equal(np.sort(tree.order), np.arange(5000))
    level = tree.level_for_size(1.0)
    assert tree.cell_size_m(level) >= 1.0 > tree.cell_size_m(level + 1)
    keys = tree.node_keys(level)
    size = tree.cell_size_m(level)
    lo = tree.origin + morton_decode(keys) * size
    p = pts[tree.order]
    assert np.all(p >= lo - 1e-9) and np.all(p <= lo + size + 1e-9)
    nkeys, starts, counts = tree.nodes(level)
    assert counts.sum() == 5000 and np.all(np.diff(nkeys.astype(np.float64)) > 0)


def test_packed_sort_equals_argsort_path():
    rng = np.random.default_rng(4)
    pts = rng.uniform(0, 100, (20000, 3))
    packed = build_octree(pts, depth=10)  # 30 key bits + 15 index bits: packed sort
    plain = build_octree(pts, depth=21)  # 63 key bits: argsort
    lvl_plain = plain.keys >> np.uint64(3 * 11)
    assert np.array_equal(packed.keys, lvl_plain)
    # same multiset of (key, point) pairs
    a = np.lexsort((packed.order, packed.keys))
    b = np.lexsort((plain.order, lvl_plain))
    assert np.array_equal(packed.order[a], plain.order[b])


def test_octree_bad_input():
    with pytest.raises(InputDataError):
        build_octree(np.empty((0, 3)))
    with pytest.raises(InputDataError):
        build_octree(np.array([[0.0, np.nan, 0.0], [1.0, 1.0, 1.0]]))
    with pytest.raises(InvalidParameterError):
        build_octree(np.zeros((4, 2)))
    with pytest.raises(InvalidParameterError, match="min_node_size_m"):
        build_octree(np.array([[0.0, 0, 0], [1e6, 0, 0]]), min_node_size_m=1e-4)


def _random_leaves(rng, depth, p_split, p_drop):
    """Adaptive leaf set: random subdivision of the root down to ``depth``; some dropped."""
    leaves = []
    stack = [(np.zeros(3, dtype=np.int64), 0)]
    while stack:
        ijk, level = stack.pop()
        if level < depth and (level < 1 or rng.random() < p_split):
            for c in range(8):
                child = ijk * 2 + np.array([c & 1, (c >> 1) & 1, (c >> 2) & 1])
                stack.append((child, level + 1))
        elif rng.random() >= p_drop:
            leaves.append((ijk, level))
    keys = morton_encode(np.array([x[0] for x in leaves]).reshape(-1, 3))
    levels = np.array([x[1] for x in leaves], dtype=np.int64)
    return keys, levels


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), p_split=st.floats(0.2, 0.8), p_drop=st.floats(0.0, 0.5))
def test_leaf_neighbours_match_brute_force(seed, p_split, p_drop):
    rng = np.random.default_rng(seed)
    keys, levels = _random_leaves(rng, 4, p_split, p_drop)
    fast = leaf_neighbours(keys, levels, 6)
    ref = leaf_neighbours_reference(keys, levels, 6)
    assert np.array_equal(fast[0], ref[0]) and np.array_equal(fast[1], ref[1])


def test_leaf_neighbours_uniform_grid_degrees():
    ijk = np.array([[i, j, k] for i in range(3) for j in range(3) for k in range(3)])
    i, j = leaf_neighbours(morton_encode(ijk), np.full(27, 2), 2)
    deg = np.bincount(i, minlength=27)
    centre = int(np.flatnonzero(np.all(ijk == 1, axis=1))[0])
    assert deg[centre] == 26
    corner = int(np.flatnonzero(np.all(ijk == 0, axis=1))[0])
    assert deg[corner] == 7


def test_leaf_neighbours_coarse_and_fine():
    # one coarse leaf (level 1, cell 0) and the 8 fine leaves of its +x neighbour (level 2)
    coarse = morton_encode(np.array([[0, 0, 0]]))
    fine_ijk = np.array([[2 + a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)])
    keys = np.concatenate([coarse, morton_encode(fine_ijk)])
    levels = np.array([1] + [2] * 8)
    i, j = leaf_neighbours(keys, levels, 3)
    touching = set(j[i == 0].tolist())
    expected = {1 + k for k, f in enumerate(fine_ijk) if f[0] == 2}  # only the face at x = 2
    assert touching == expected


def test_leaf_neighbours_rejects_overlap():
    keys = np.array([0, 0], dtype=np.uint64)
    with pytest.raises(InvalidParameterError, match="overlap"):
        leaf_neighbours(keys, np.array([1, 2]), 3)
