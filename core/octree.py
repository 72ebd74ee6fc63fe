"""Linear octree on 64-bit Morton keys (Kusari et al. 2019, section II.A).

Points are quantised on a cube of ``2**depth`` cells per axis and each cell gets a Morton
(Z-order) key: the bits of its integer coordinates interleaved, x in bit 0, y in bit 1,
z in bit 2 of every triplet, up to 21 bits per axis (63 bits). Sorting the keys sorts the
points so that every octree node, at every level, is one contiguous run: the node of a key
at level ``l`` is ``key >> 3 * (depth - l)``. No pointer tree is built.

Leaves may sit at different levels (an adaptive tree); :func:`leaf_neighbours` finds the
26-neighbourhood of such leaves, including neighbours that are larger or smaller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import numpy as np

from .errors import InputDataError, InvalidParameterError

MAX_DEPTH = 21  # bits per axis in a 64-bit key

_U = np.uint64

# Magic-number bit spreading: put bit i of a 21-bit integer at bit 3*i.
_SPREAD = (
    (32, 0x1F00000000FFFF),
    (16, 0x1F0000FF0000FF),
    (8, 0x100F00F00F00F00F),
    (4, 0x10C30C30C30C30C3),
    (2, 0x1249249249249249),
)


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Spread the low 21 bits of uint64 ``v`` so that bit i lands at bit 3*i."""
    x = v & _U(0x1FFFFF)
    for shift, mask in _SPREAD:
        x = (x | (x << _U(shift))) & _U(mask)
    return x


def _compact_bits(v: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_spread_bits`: gather bits 0, 3, 6, ... into the low 21 bits."""
    x = v & _U(0x1249249249249249)
    for shift, mask in (
        (2, 0x10C30C30C30C30C3),
        (4, 0x100F00F00F00F00F),
        (8, 0x1F0000FF0000FF),
        (16, 0x1F00000000FFFF),
        (32, 0x1FFFFF),
    ):
        x = (x | (x >> _U(shift))) & _U(mask)
    return x


def morton_encode(ijk: np.ndarray) -> np.ndarray:
    """Morton keys of integer cell coordinates.

    Parameters
    ----------
    ijk : (N, 3) integer array
        Cell coordinates, each in ``[0, 2**21)``.

    Returns
    -------
    (N,) uint64
        Keys with x in bit 0, y in bit 1 and z in bit 2 of every bit triplet.
    """
    ijk = np.asarray(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise InvalidParameterError(f"ijk must have shape (N, 3), got {ijk.shape}")
    u = ijk.astype(np.uint64, copy=False)
    return (
        _spread_bits(u[:, 0]) | (_spread_bits(u[:, 1]) << _U(1)) | (_spread_bits(u[:, 2]) << _U(2))
    )


def morton_decode(keys: np.ndarray) -> np.ndarray:
    """Integer cell coordinates (N, 3) int64 of Morton ``keys`` (inverse of ``morton_encode``)."""
    k = np.asarray(keys, dtype=np.uint64)
    out = np.empty((k.size, 3), dtype=np.int64)
    out[:, 0] = _compact_bits(k)
    out[:, 1] = _compact_bits(k >> _U(1))
    out[:, 2] = _compact_bits(k >> _U(2))
    return out


def neighbour_offsets() -> np.ndarray:
    """The 26 offsets (26, 3) int64 of the cells sharing a face, an edge or a corner."""
    r = np.array([-1, 0, 1])
    g = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3)
    return g[np.any(g != 0, axis=1)].astype(np.int64)


@dataclass(frozen=True)
class Octree:
    """A linear octree: points sorted by Morton key.

    Attributes
    ----------
    origin : (3,) float64
        Minimum corner of the root cube (centred on the points' bounding box), in the
        coordinates the tree was built from.
    root_size_m : float
        Edge of the root cube, metres.
    depth : int
        Level of the keys: cells of ``root_size_m / 2**depth``.
    keys : (N,) uint64
        Sorted Morton keys at ``depth``.
    order : (N,) int64
        ``order[i]`` is the index of the input point with key ``keys[i]``.
    """

    origin: np.ndarray
    root_size_m: float
    depth: int
    keys: np.ndarray
    order: np.ndarray

    def cell_size_m(self, level: int) -> float:
        """Edge of the nodes at ``level``, metres."""
        return self.root_size_m / float(1 << level)

    def level_for_size(self, size_m: float) -> int:
        """Deepest level whose nodes are at least ``size_m`` wide (clamped to [0, depth])."""
        if size_m >= self.root_size_m:
            return 0
        level = int(math.floor(math.log2(self.root_size_m / size_m) + 1e-12))
        return max(0, min(self.depth, level))

    def node_keys(self, level: int) -> np.ndarray:
        """Key at ``level`` of every (sorted) point, (N,) uint64."""
        return self.keys >> _U(3 * (self.depth - level))

    def nodes(self, level: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The occupied nodes of ``level``.

        Returns
        -------
        keys : (M,) uint64
            Node keys at ``level``, ascending.
        starts : (M,) int64
            First sorted-point position of each node.
        counts : (M,) int64
            Points per node.
        """
        return run_boundaries(self.node_keys(level))

    def node_centres(self, keys: np.ndarray, level: int) -> np.ndarray:
        """Centres (M, 3) float64 of the nodes ``keys`` at ``level``."""
        size = self.cell_size_m(level)
        return self.origin + (morton_decode(keys).astype(np.float64) + 0.5) * size


def run_boundaries(sorted_keys: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs of equal values in a sorted array: (values, starts, counts)."""
    n = sorted_keys.size
    if n == 0:
        e = np.empty(0, dtype=np.int64)
        return sorted_keys[:0], e, e
    change = np.flatnonzero(sorted_keys[1:] != sorted_keys[:-1]) + 1
    starts = np.empty(change.size + 1, dtype=np.int64)
    starts[0] = 0
    starts[1:] = change
    counts = np.diff(np.append(starts, n))
    return sorted_keys[starts], starts, counts


_LUT_BITS = 11
_SPREAD_LUT = None


def _spread_lut() -> np.ndarray:
    global _SPREAD_LUT
    if _SPREAD_LUT is None:
        _SPREAD_LUT = _spread_bits(np.arange(1 << _LUT_BITS, dtype=np.uint64))
    return _SPREAD_LUT


def quantise_encode(pts: np.ndarray, lo: np.ndarray, scale: float, cells: int) -> np.ndarray:
    """Morton keys of points: cell ``floor((p - lo) * scale)`` clipped to ``[0, cells)``.

    Parameters
    ----------
    pts : (N, 3) float64
    lo : (3,) float64
        Minimum corner of the root cube.
    scale : float
        Cells per metre.
    cells : int
        Cells per axis (``2**depth``).

    Returns
    -------
    (N,) uint64, equal to ``morton_encode`` of the cells (table look-up, 11 bits at a time).
    """
    lut = _spread_lut()
    keys = np.zeros(pts.shape[0], dtype=np.uint64)
    wide = cells > (1 << _LUT_BITS)
    for a in range(3):
        col = np.floor((pts[:, a] - lo[a]) * scale)
        np.clip(col, 0, cells - 1, out=col)
        c = col.astype(np.int64)
        part = lut[c & ((1 << _LUT_BITS) - 1)]
        if wide:
            part |= lut[c >> _LUT_BITS] << _U(3 * _LUT_BITS)
        if a:
            part <<= _U(a)
        keys |= part
    return keys


def bounds(points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Per-axis minimum and maximum (3,) of (N, 3) points (column by column: fast)."""
    lo = np.array([points[:, a].min() for a in range(3)], dtype=np.float64)
    hi = np.array([points[:, a].max() for a in range(3)], dtype=np.float64)
    return lo, hi


def build_octree(
    points: np.ndarray,
    *,
    depth: Optional[int] = None,
    min_node_size_m: Optional[float] = None,
    encoder: Optional[Callable[[np.ndarray, np.ndarray, float, int], np.ndarray]] = None,
    point_bounds: Optional[Tuple[np.ndarray, np.ndarray]] = None,
) -> Octree:
    """Sort ``points`` into a linear octree.

    Parameters
    ----------
    points : (N, 3) float64
        Coordinates, metres. Centre them first when they carry large offsets.
    depth : int, optional
        Key level (1 to 21). Default: the deepest level that lets the sort carry the point
        index in the same 64-bit word (fast path), at least the level of ``min_node_size_m``.
    min_node_size_m : float, optional
        Smallest node edge the caller will use, metres; the keys resolve at least this.
    encoder : callable, optional
        ``encoder(points, lo, scale, cells) -> keys`` replacing :func:`quantise_encode`
        (the OpenCL backend passes its kernel).
    point_bounds : (lo, hi), optional
        The points' per-axis minima and maxima when the caller already has them.

    Returns
    -------
    Octree
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidParameterError(f"points must have shape (N, 3), got {pts.shape}")
    n = pts.shape[0]
    if n == 0:
        raise InputDataError("points is empty; an octree needs at least one point")
    lo, hi = point_bounds if point_bounds is not None else bounds(pts)
    extent = float(np.max(hi - lo))
    if not np.isfinite(extent):
        raise InputDataError("points contain NaN or infinite coordinates; remove them first")
    root = extent * (1.0 + 1e-9) if extent > 0 else 1.0
    # The root cube is centred on the bounding box: translations, quarter turns and mirrors of
    # the cloud then map the cells onto cells (the grid is independent of such motions).
    lo = 0.5 * (lo + hi) - 0.5 * root
    index_bits = max(1, int(n - 1).bit_length())
    packed_depth = (64 - index_bits) // 3
    need = 0
    if min_node_size_m is not None:
        if not min_node_size_m > 0:
            raise InvalidParameterError(f"min_node_size_m must be > 0, got {min_node_size_m}")
        need = max(0, int(math.floor(math.log2(root / min_node_size_m) + 1e-12)))
        if need > MAX_DEPTH:
            raise InvalidParameterError(
                f"min_node_size_m={min_node_size_m:g} is below the data extent / 2**21 "
                f"({root / 2**MAX_DEPTH:.3g} m); raise it or cut the data into tiles"
            )
    if depth is None:
        depth = max(min(MAX_DEPTH, packed_depth), need, 1)
    if not 1 <= depth <= MAX_DEPTH:
        raise InvalidParameterError(f"depth must be in [1, {MAX_DEPTH}], got {depth}")
    cells = 1 << depth
    scale = cells / root
    keys = (encoder or quantise_encode)(pts, lo, scale, cells)
    if 3 * depth + index_bits <= 64:
        # Sort key and index together: np.sort is much faster than np.argsort.
        packed = (keys << _U(index_bits)) | np.arange(n, dtype=np.uint64)
        packed.sort()
        order = (packed & _U((1 << index_bits) - 1)).astype(np.int64)
        keys = packed >> _U(index_bits)
    else:
        order = np.argsort(keys, kind="stable")
        keys = keys[order]
    return Octree(origin=lo, root_size_m=root, depth=depth, keys=keys, order=order)


def _box_bounds(keys: np.ndarray, levels: np.ndarray, depth: int) -> Tuple[np.ndarray, np.ndarray]:
    """Integer boxes [lo, hi) at ``depth`` of nodes ``keys`` at ``levels``."""
    scale = np.left_shift(np.int64(1), (depth - levels).astype(np.int64))
    lo = morton_decode(keys) * scale[:, None]
    return lo, lo + scale[:, None]


def leaf_neighbours(
    leaf_keys: np.ndarray, leaf_levels: np.ndarray, depth: int
) -> Tuple[np.ndarray, np.ndarray]:
    """All pairs of leaves that touch (share a face, edge or corner).

    Parameters
    ----------
    leaf_keys : (L,) uint64
        Key of each leaf at its own level. Leaves must not overlap.
    leaf_levels : (L,) integer
        Level of each leaf (0 = root); leaves may sit at different levels.
    depth : int
        The octree's key depth (>= every level).

    Returns
    -------
    i, j : (E,) int64
        Symmetric pairs (both (i, j) and (j, i) are listed), sorted by i then j; no i == j.
    """
    keys = np.asarray(leaf_keys, dtype=np.uint64)
    levels = np.asarray(leaf_levels, dtype=np.int64)
    nleaf = keys.size
    empty = (np.empty(0, np.int64), np.empty(0, np.int64))
    if nleaf < 2:
        return empty
    shift = (3 * (depth - levels)).astype(np.uint64)
    start = keys << shift
    span = np.left_shift(np.uint64(1), shift)  # keys covered by a leaf at full depth
    order = np.argsort(start, kind="stable")
    s_start = start[order]
    s_end = s_start + span[order]
    if np.any(s_start[1:] < s_end[:-1]):
        raise InvalidParameterError("leaf_keys overlap: leaves must be disjoint octree nodes")

    lo, hi = _box_bounds(keys, levels, depth)
    offs = neighbour_offsets()
    ijk = morton_decode(keys)
    cells = np.left_shift(np.int64(1), levels)
    src = []
    dst = []
    for off in offs:
        q = ijk + off
        ok = np.all((q >= 0) & (q < cells[:, None]), axis=1)
        ids = np.flatnonzero(ok)
        if ids.size == 0:
            continue
        qk = morton_encode(q[ids]) << shift[ids]
        qe = qk + span[ids]
        # a leaf at the same or a coarser level containing the neighbour cell
        j = np.searchsorted(s_start, qk, side="right") - 1
        hit = (j >= 0) & (s_end[np.maximum(j, 0)] >= qe) & (s_start[np.maximum(j, 0)] <= qk)
        src.append(ids[hit])
        dst.append(order[j[hit]])
        # finer leaves inside the neighbour cell: keep those that touch the leaf
        a = np.searchsorted(s_start, qk, side="left")
        b = np.searchsorted(s_start, qe, side="left")
        nfine = b - a
        fine = (nfine > 0) & ~hit
        if np.any(fine):
            f_ids = ids[fine]
            f_a = a[fine]
            f_n = nfine[fine]
            rep = np.repeat(np.arange(f_ids.size), f_n)
            first = np.repeat(f_a - np.cumsum(f_n) + f_n, f_n)
            cand = order[first + np.arange(rep.size)]
            ii = f_ids[rep]
            touch = np.all((lo[ii] <= hi[cand]) & (lo[cand] <= hi[ii]), axis=1)
            src.append(ii[touch])
            dst.append(cand[touch])
    if not src:
        return empty
    i = np.concatenate(src)
    j = np.concatenate(dst)
    # symmetrise and deduplicate
    i, j = np.concatenate([i, j]), np.concatenate([j, i])
    keep = i != j
    code = np.unique(i[keep].astype(np.int64) * nleaf + j[keep])
    return code // nleaf, code % nleaf


def leaf_neighbours_reference(
    leaf_keys: np.ndarray, leaf_levels: np.ndarray, depth: int
) -> Tuple[np.ndarray, np.ndarray]:
    """Obvious O(L**2) version of :func:`leaf_neighbours`: every pair of boxes tested."""
    keys = np.asarray(leaf_keys, dtype=np.uint64)
    levels = np.asarray(leaf_levels, dtype=np.int64)
    lo, hi = _box_bounds(keys, levels, depth)
    touch = np.all(lo[:, None, :] <= hi[None, :, :], axis=2) & np.all(
        lo[None, :, :] <= hi[:, None, :], axis=2
    )
    np.fill_diagonal(touch, False)
    i, j = np.nonzero(touch)  # row-major: sorted by i, then j
    return i.astype(np.int64), j.astype(np.int64)
