"""Fault-trace geometry: side of the trace, distance, along-strike chainage and local strike.

Pure numpy (scipy's ``cKDTree`` for traces with many segments); file formats live in
:mod:`slipmap.core.io.vector`, which turns any OGR vector into a :class:`FaultTrace`.

Conventions
-----------
Coordinates are map coordinates in metres: ``x`` = easting, ``y`` = (grid) northing.

* **Direction.** The trace has a direction: the order in which it was digitised. A
  MultiLineString gives several parts; they are used in their order, each in its own
  digitised direction, and no segment joins the end of one part to the start of the next.
* **Side.** Looking along the digitised direction, points on the left have ``side = -1``,
  points on the right ``side = +1``. A trace digitised towards the north has its right side
  to the east. Only points lying exactly on the trace (or exactly on the straight extension
  of an end segment) get ``side = 0``.
* **Strike.** Azimuth of the digitised direction, radians clockwise from grid north (+y),
  in ``[0, 2π)``: a trace digitised towards the east has strike ``π/2``. The unit strike
  vector is ``s = (sin θ, cos θ)``; the unit normal towards the right side is
  ``n = (cos θ, -sin θ)`` (``s`` rotated 90° clockwise).
* **Relative displacement** is ``r = d_right - d_left`` (displacement of the right side
  minus that of the left side). ``fault_parallel = r·s`` and ``fault_normal = r·n``
  (positive = the sides move apart: opening / extension across the trace).
* **Right-lateral (dextral) slip.** In dextral motion the far side moves to the right, as
  seen from either side. Seen from the left side (looking across the trace towards the
  right side, i.e. along ``n``), "to the right" is ``-s``; so dextral motion has
  ``r·s < 0`` and ``right_lateral_slip = -fault_parallel`` is positive for dextral and
  negative for sinistral motion. Example: a trace digitised towards the north has its
  right side to the east; dextral motion moves the east side south relative to the west
  side, ``r = (0, -v)``, ``fault_parallel = -v``, ``right_lateral_slip = +v``.

Nearest point
-------------
Every point is attached to the nearest point of the polyline (all parts): ``distance_m`` is
the distance to it and ``along_strike_m`` its chainage, i.e. the length along the trace from
the first vertex of the first part, with the parts' lengths concatenated in order (the gaps
between parts do not count). When the nearest point is an interior vertex of a part, the side
uses the *pseudo-normal* (the bisector of the two segments' right normals) and the strike is
the azimuth of the bisector of the two segments' directions, so both are continuous around
the vertex and independent of which of the two equidistant segments is reported. Points
beyond the ends of a part are at their distance from the end vertex, but their side comes
from the end segment's infinite straight line (and their strike is the end segment's).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Iterable, Optional, Tuple

import numpy as np

from .errors import InputDataError, InvalidParameterError
from .progress import ProgressCallback, report

logger = logging.getLogger(__name__)

__all__ = [
    "FaultGeometry",
    "FaultTrace",
    "fault_geometry",
    "fault_parallel_normal",
    "fault_trace",
    "mean_strike_rad",
    "right_lateral_slip",
    "side_masks",
    "trace_in_data_check",
]

#: Traces with fewer segments use brute-force broadcasting; more use a KD-tree of samples.
BRUTE_FORCE_MAX_SEGMENTS = 2000
#: Number of (point, segment) pairs evaluated at once in the brute-force search.
_PAIRS_PER_BLOCK = 1 << 21
_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True, eq=False)
class FaultTrace:
    """A fault trace: one or more polylines in map coordinates (metres).

    Build it with :func:`fault_trace`, which validates the vertices.

    Attributes
    ----------
    parts : tuple of numpy.ndarray
        Each part is an ``(M_k, 2)`` float64 array of vertices ``(x, y)`` in metres, in
        digitised order (``M_k >= 2``, no repeated consecutive vertices).
    """

    parts: Tuple[np.ndarray, ...]

    @property
    def vertices(self) -> np.ndarray:
        """All vertices of all parts stacked, shape ``(sum M_k, 2)`` (e.g. for extents)."""
        return np.concatenate(self.parts, axis=0)

    def length_m(self) -> float:
        """Total length of the trace in metres (sum over parts)."""
        return float(sum(np.hypot(*np.diff(p, axis=0).T).sum() for p in self.parts))

    def reversed(self) -> FaultTrace:
        """The same trace digitised in the opposite direction (parts and vertices reversed)."""
        return FaultTrace(tuple(p[::-1].copy() for p in reversed(self.parts)))


def fault_trace(parts: Iterable[np.ndarray] | np.ndarray) -> FaultTrace:
    """Validate vertex arrays and build a :class:`FaultTrace`.

    Parameters
    ----------
    parts : array_like, shape (M, 2) or (M, 3), or sequence of such arrays
        One polyline (a single ``(M, 2|3)`` array) or several (a MultiLineString), vertices
        in digitised order, metres. A third (z) column is dropped. Repeated consecutive
        vertices are removed.

    Returns
    -------
    FaultTrace

    Raises
    ------
    InvalidParameterError
        If there are no parts, a part is not an ``(M, 2|3)`` array, has a non-finite
        coordinate, or has fewer than 2 distinct vertices.
    """
    if isinstance(parts, np.ndarray) and parts.ndim == 2:
        raw = [parts]
    else:
        raw = list(parts)
        if raw and np.ndim(raw[0]) == 1:  # a single polyline given as a list of vertices
            raw = [np.asarray(raw, dtype=np.float64)]
    if not raw:
        raise InvalidParameterError("fault trace: no parts (the trace has no vertices)")
    out = []
    for k, part in enumerate(raw):
        try:
            a = np.asarray(part, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InvalidParameterError(
                f"fault trace part {k}: vertices are not numbers ({exc})"
            ) from exc
        if a.ndim != 2 or a.shape[1] not in (2, 3):
            raise InvalidParameterError(
                f"fault trace part {k}: vertices must be an (M, 2) array of x, y, got shape "
                f"{a.shape}"
            )
        a = a[:, :2]
        if not np.all(np.isfinite(a)):
            raise InvalidParameterError(
                f"fault trace part {k}: has non-finite (NaN/inf) vertex coordinates"
            )
        if len(a) > 1:
            keep = np.ones(len(a), dtype=bool)
            keep[1:] = np.any(a[1:] != a[:-1], axis=1)
            a = a[keep]
        if len(a) < 2:
            raise InvalidParameterError(
                f"fault trace part {k}: needs at least 2 distinct vertices, got {len(a)}; "
                "a fault trace is a line"
            )
        a = np.ascontiguousarray(a)
        a.setflags(write=False)
        out.append(a)
    return FaultTrace(tuple(out))


@dataclass(frozen=True, eq=False)
class FaultGeometry:
    """Per-point geometry relative to a fault trace (see the module docstring).

    Attributes
    ----------
    side : numpy.ndarray, shape (N,), int8
        -1 left, +1 right of the digitised direction (0 only exactly on the trace line).
    distance_m : numpy.ndarray, shape (N,), float64
        Unsigned horizontal distance to the nearest point of the trace, metres.
    along_strike_m : numpy.ndarray, shape (N,), float64
        Chainage of that nearest point from the first vertex (parts concatenated), metres.
    strike_rad : numpy.ndarray, shape (N,), float64
        Local strike at that point: azimuth of the digitised direction, radians clockwise
        from grid north, in ``[0, 2π)``.
    segment : numpy.ndarray, shape (N,), int64
        Index of the nearest segment, counting the segments of all parts in order.
    """

    side: np.ndarray
    distance_m: np.ndarray
    along_strike_m: np.ndarray
    strike_rad: np.ndarray
    segment: np.ndarray


class _Segments:
    """Segment arrays of a trace, relative to an origin (the first vertex) for precision."""

    def __init__(self, trace: FaultTrace):
        self.origin = trace.parts[0][0].copy()
        starts, ends, first, last = [], [], [], []
        for p in trace.parts:
            q = p - self.origin
            starts.append(q[:-1])
            ends.append(q[1:])
            n = len(p) - 1
            f = np.zeros(n, dtype=bool)
            f[0] = True
            la = np.zeros(n, dtype=bool)
            la[-1] = True
            first.append(f)
            last.append(la)
        self.a = np.concatenate(starts)  # (S, 2)
        b = np.concatenate(ends)
        self.d = b - self.a  # (S, 2) direction vectors
        self.len2 = np.einsum("ij,ij->i", self.d, self.d)
        self.len = np.sqrt(self.len2)
        self.u = self.d / self.len[:, None]  # unit directions
        self.chain0 = np.concatenate([[0.0], np.cumsum(self.len)[:-1]])
        self.is_first = np.concatenate(first)  # first segment of its part
        self.is_last = np.concatenate(last)  # last segment of its part
        self.n = len(self.a)


def _azimuth(v: np.ndarray) -> np.ndarray:
    """Azimuth clockwise from +y of vectors ``(..., 2)``, in ``[0, 2π)``."""
    az = np.arctan2(v[..., 0], v[..., 1])
    az = np.where(az < 0, az + _TWO_PI, az)
    return np.where(az >= _TWO_PI, 0.0, az)


def _take(arr: np.ndarray, idx: np.ndarray, single: bool):
    """``arr[idx]`` (a gather), or the scalar ``arr[0]`` when the trace has one segment."""
    return arr[0] if single else arr[idx]


def _project(p: np.ndarray, seg: _Segments, idx: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Clamped parameter ``t`` and squared distance of points ``p`` (n, 2) to segments idx.

    Column arithmetic (no (n, 2) temporaries); a one-segment trace needs no gathers."""
    one = seg.n == 1
    dx, dy = _take(seg.d[:, 0], idx, one), _take(seg.d[:, 1], idx, one)
    rx = p[:, 0] - _take(seg.a[:, 0], idx, one)
    ry = p[:, 1] - _take(seg.a[:, 1], idx, one)
    t = (rx * dx + ry * dy) / _take(seg.len2, idx, one)
    np.clip(t, 0.0, 1.0, out=t)
    rx -= t * dx
    ry -= t * dy
    return t, rx * rx + ry * ry


def _nearest_brute(p: np.ndarray, seg: _Segments) -> np.ndarray:
    """Index of the nearest segment of each point, by broadcasting over all segments."""
    out = np.empty(len(p), dtype=np.int64)
    block = max(1, _PAIRS_PER_BLOCK // seg.n)
    ax, ay = seg.a[:, 0], seg.a[:, 1]
    dx, dy = seg.d[:, 0], seg.d[:, 1]
    for i in range(0, len(p), block):
        q = p[i : i + block]
        rx = q[:, 0:1] - ax  # (n, S)
        ry = q[:, 1:2] - ay
        t = (rx * dx + ry * dy) / seg.len2
        np.clip(t, 0.0, 1.0, out=t)
        rx -= t * dx
        ry -= t * dy
        out[i : i + block] = np.argmin(rx * rx + ry * ry, axis=1)
    return out


class _SampleTree:
    """KD-tree of points sampled along every segment (both ends included, spacing <= h)."""

    def __init__(self, seg: _Segments):
        from scipy.spatial import cKDTree

        h = float(np.median(seg.len))
        # bound the number of samples: a few very long segments must not explode it
        h = max(h, float(seg.len.sum()) / seg.n)
        counts = np.ceil(seg.len / h).astype(np.int64) + 1  # samples per segment
        seg_of = np.repeat(np.arange(seg.n), counts)
        start = np.repeat(np.cumsum(counts) - counts, counts)
        frac = (np.arange(len(seg_of)) - start) / (counts[seg_of] - 1)
        samples = seg.a[seg_of] + frac[:, None] * seg.d[seg_of]
        self.h = float(np.max(seg.len / (counts - 1)))  # actual largest spacing
        self.seg_of = seg_of
        self.tree = cKDTree(samples)
        self.k = int(min(24, len(samples)))


def _kdtree_pass(
    p: np.ndarray, seg: _Segments, st: _SampleTree, k: int
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best of the segments owning the k nearest samples: ``(best, radius, complete)``."""
    n = len(p)
    dist, ii = st.tree.query(p, k=k)
    if k == 1:
        dist, ii = dist[:, None], ii[:, None]
    cand = st.seg_of[ii]  # (n, k)
    rows = np.repeat(np.arange(n), k)
    _, d2 = _project(p[rows], seg, cand.ravel())
    d2 = d2.reshape(n, k)
    j = np.argmin(d2, axis=1)
    best = cand[np.arange(n), j]
    radius = np.sqrt(d2[np.arange(n), j]) + 0.5 * st.h
    radius = radius * (1.0 + 1e-12) + 1e-9  # rounding margin
    complete = (dist[:, -1] > radius) | (k >= st.tree.n)
    return best, radius, complete


def _nearest_kdtree(p: np.ndarray, seg: _Segments, st: _SampleTree) -> np.ndarray:
    """Exact nearest segment using KD-tree candidates.

    Any segment at the minimum distance ``d*`` has a sample within ``h/2`` of its nearest
    point, so all such segments have a sample within ``d_best + h/2`` of the point, where
    ``d_best >= d*`` is the best exact distance among the candidates. When the k-th nearest
    sample is farther than that, the candidates are complete; otherwise (mostly points far
    from the trace) all samples in that ball are taken as candidates.
    """
    best, radius, complete = _kdtree_pass(p, seg, st, st.k)
    incomplete = np.flatnonzero(~complete)
    if len(incomplete):
        balls = st.tree.query_ball_point(p[incomplete], radius[incomplete])
        lens = np.fromiter((len(b) for b in balls), dtype=np.int64, count=len(balls))
        flat = np.fromiter((i for b in balls for i in b), dtype=np.int64, count=int(lens.sum()))
        owner = np.repeat(np.arange(len(incomplete)), lens)
        pairs = np.unique(np.stack([owner, st.seg_of[flat]], axis=1), axis=0)
        _, pd2 = _project(p[incomplete[pairs[:, 0]]], seg, pairs[:, 1])
        order = np.lexsort((pairs[:, 1], pd2, pairs[:, 0]))  # by owner, then distance
        first = np.ones(len(order), dtype=bool)
        first[1:] = pairs[order[1:], 0] != pairs[order[:-1], 0]
        winners = order[first]
        best[incomplete[pairs[winners, 0]]] = pairs[winners, 1]
    return best


def _finish(p: np.ndarray, seg: _Segments, idx: np.ndarray) -> Tuple[np.ndarray, ...]:
    """Side, distance, chainage and strike of points p (n, 2) given their nearest segment."""
    one = seg.n == 1
    t, d2 = _project(p, seg, idx)
    # offset of the point from its nearest point on the trace
    ox = p[:, 0] - (_take(seg.a[:, 0], idx, one) + t * _take(seg.d[:, 0], idx, one))
    oy = p[:, 1] - (_take(seg.a[:, 1], idx, one) + t * _take(seg.d[:, 1], idx, one))
    tx = np.broadcast_to(_take(seg.u[:, 0], idx, one), t.shape).copy()
    ty = np.broadcast_to(_take(seg.u[:, 1], idx, one), t.shape).copy()
    # at an interior vertex of a part, use the bisector of the two segments' directions
    at_end = (t >= 1.0) & ~seg.is_last[idx]
    at_start = (t <= 0.0) & ~seg.is_first[idx]
    if np.any(at_end):
        k = idx[at_end]
        tx[at_end] = seg.u[k, 0] + seg.u[k + 1, 0]
        ty[at_end] = seg.u[k, 1] + seg.u[k + 1, 1]
    if np.any(at_start):
        k = idx[at_start]
        tx[at_start] = seg.u[k - 1, 0] + seg.u[k, 0]
        ty[at_start] = seg.u[k - 1, 1] + seg.u[k, 1]
    if np.any(at_end) or np.any(at_start):
        norm = np.hypot(tx, ty)
        degenerate = norm < 1e-12  # the trace turns back by 180°: keep the segment's direction
        if np.any(degenerate):
            tx[degenerate] = seg.u[idx[degenerate], 0]
            ty[degenerate] = seg.u[idx[degenerate], 1]
            norm[degenerate] = 1.0
        tx /= norm
        ty /= norm
    # right normal of the tangent is (ty, -tx)
    side = np.sign(ty * ox - tx * oy).astype(np.int8)
    chain = _take(seg.chain0, idx, one) + t * _take(seg.len, idx, one)
    return side, np.sqrt(d2), chain, _azimuth(np.stack([tx, ty], axis=-1))


def fault_geometry(
    points_xy: np.ndarray,
    trace: FaultTrace,
    *,
    chunk_points: int = 1_000_000,
    method: str = "auto",
    progress: Optional[ProgressCallback] = None,
) -> FaultGeometry:
    """Side, distance, along-strike chainage and local strike of points relative to a trace.

    Parameters
    ----------
    points_xy : numpy.ndarray, shape (N, 2) or (N, 3)
        Point coordinates in metres, same CRS as the trace (a z column is ignored).
    trace : FaultTrace
        The fault trace (see :func:`fault_trace`).
    chunk_points : int, default 1_000_000
        Points processed per chunk (bounds memory; results do not depend on it).
    method : {"auto", "brute", "kdtree"}
        Nearest-segment search. ``"brute"`` computes distances to all segments by
        broadcasting; ``"kdtree"`` picks candidate segments from a KD-tree of samples along
        the segments and then computes exact distances (same result). ``"auto"`` uses
        brute force below :data:`BRUTE_FORCE_MAX_SEGMENTS` segments.
    progress : callable, optional
        Progress callback ``(fraction, message)``, called once per chunk.

    Returns
    -------
    FaultGeometry
        Per-point arrays of length N; conventions in the module docstring.

    Raises
    ------
    InvalidParameterError
        For a bad ``points_xy`` shape, ``chunk_points < 1`` or an unknown ``method``.
    InputDataError
        If a point coordinate is not finite.
    """
    pts = np.asarray(points_xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise InvalidParameterError(
            f"fault_geometry: points_xy must be (N, 2) or (N, 3), got shape {pts.shape}"
        )
    if int(chunk_points) < 1:
        raise InvalidParameterError(f"chunk_points must be >= 1, got {chunk_points}")
    if method not in ("auto", "brute", "kdtree"):
        raise InvalidParameterError(
            f"fault_geometry: method must be 'auto', 'brute' or 'kdtree', got {method!r}"
        )
    if not isinstance(trace, FaultTrace):
        trace = fault_trace(trace)
    pts = pts[:, :2]
    if not np.all(np.isfinite(pts)):
        raise InputDataError("fault_geometry: points have non-finite (NaN/inf) x/y coordinates")
    seg = _Segments(trace)
    use_tree = method == "kdtree" or (method == "auto" and seg.n >= BRUTE_FORCE_MAX_SEGMENTS)
    tree = _SampleTree(seg) if use_tree else None
    n = len(pts)
    side = np.zeros(n, dtype=np.int8)
    dist = np.zeros(n, dtype=np.float64)
    chain = np.zeros(n, dtype=np.float64)
    strike = np.zeros(n, dtype=np.float64)
    segment = np.zeros(n, dtype=np.int64)
    chunk = int(chunk_points)
    for i in range(0, n, chunk):
        p = pts[i : i + chunk] - seg.origin
        if seg.n == 1:
            idx = np.zeros(len(p), dtype=np.int64)
        elif tree is not None:
            idx = _nearest_kdtree(p, seg, tree)
        else:
            idx = _nearest_brute(p, seg)
        sl = slice(i, i + len(p))
        side[sl], dist[sl], chain[sl], strike[sl] = _finish(p, seg, idx)
        segment[sl] = idx
        report(progress, (i + len(p)) / n, "fault geometry")
    return FaultGeometry(side, dist, chain, strike, segment)


def side_masks(geom: FaultGeometry, *, buffer_m: float = 10.0) -> Tuple[np.ndarray, np.ndarray]:
    """Masks of the points on each side of the trace, outside a buffer around it.

    Parameters
    ----------
    geom : FaultGeometry
        From :func:`fault_geometry`.
    buffer_m : float, default 10.0
        Points with ``distance_m <= buffer_m`` are in neither mask (metres, >= 0).

    Returns
    -------
    left_mask, right_mask : numpy.ndarray, shape (N,), bool
    """
    b = float(buffer_m)
    if not (b >= 0.0 and math.isfinite(b)):
        raise InvalidParameterError(f"buffer_m must be a finite number >= 0, got {buffer_m}")
    outside = geom.distance_m > b
    return (geom.side < 0) & outside, (geom.side > 0) & outside


def mean_strike_rad(trace: FaultTrace) -> float:
    """Length-weighted circular mean of the segments' azimuths (the trace's mean strike).

    Parameters
    ----------
    trace : FaultTrace

    Returns
    -------
    float
        Radians clockwise from grid north, in ``[0, 2π)``, in the digitised direction.

    Raises
    ------
    InputDataError
        If the segments' directions cancel out (e.g. a trace that doubles back on itself).
    """
    seg = _Segments(trace)
    total = seg.d.sum(axis=0)  # sum of length * unit direction
    if np.hypot(*total) <= 1e-9 * seg.len.sum():
        raise InputDataError(
            "the fault trace's segment directions cancel out (it doubles back on itself); "
            "its mean strike is undefined"
        )
    return float(_azimuth(total))


def fault_parallel_normal(
    vector_xy: np.ndarray, strike_rad: float | np.ndarray
) -> Tuple[np.ndarray, np.ndarray]:
    """Components of horizontal vectors along the strike and towards the right side.

    Parameters
    ----------
    vector_xy : array_like, shape (..., 2) (or (..., 3), z ignored)
        Horizontal vectors ``(east, north)`` in metres, e.g. the relative displacement
        ``r = d_right - d_left``.
    strike_rad : float or array_like broadcastable to ``vector_xy.shape[:-1]``
        Strike, radians clockwise from grid north, in the digitised direction.

    Returns
    -------
    parallel : numpy.ndarray, shape (...)
        ``v·s`` with ``s = (sin θ, cos θ)``, the unit vector along the digitised direction.
    normal : numpy.ndarray, shape (...)
        ``v·n`` with ``n = (cos θ, -sin θ)``, ``s`` rotated 90° clockwise (towards the
        right side). For ``r = d_right - d_left``, positive means opening.

    Notes
    -----
    Reversing the digitised direction adds π to the strike and swaps the sides, so ``r``
    changes sign too: ``parallel`` is then unchanged; for a fixed vector with the strike
    flipped by π alone, both components change sign. See :func:`right_lateral_slip`.
    """
    v = np.asarray(vector_xy, dtype=np.float64)
    if v.shape[-1:] not in ((2,), (3,)):
        raise InvalidParameterError(
            f"fault_parallel_normal: vectors must have 2 (or 3) components in the last axis, "
            f"got shape {v.shape}"
        )
    th = np.asarray(strike_rad, dtype=np.float64)
    s, c = np.sin(th), np.cos(th)
    return v[..., 0] * s + v[..., 1] * c, v[..., 0] * c - v[..., 1] * s


def right_lateral_slip(relative_xy: np.ndarray, strike_rad: float | np.ndarray) -> np.ndarray:
    """Right-lateral (dextral) slip, positive for dextral and negative for sinistral motion.

    Parameters
    ----------
    relative_xy : array_like, shape (..., 2)
        Relative displacement ``r = d_right - d_left`` (metres), sides as digitised.
    strike_rad : float or array_like
        Strike of the trace in its digitised direction (radians clockwise from north).

    Returns
    -------
    numpy.ndarray, shape (...)
        ``-(r·s)`` in metres (the far side moves to the right as seen from either side).
    """
    parallel, _ = fault_parallel_normal(relative_xy, strike_rad)
    return -parallel


def _segments_hit_box(seg: _Segments, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether any segment intersects the axis-aligned box [lo, hi] (Liang-Barsky)."""
    t0 = np.zeros(seg.n)
    t1 = np.ones(seg.n)
    ok = np.ones(seg.n, dtype=bool)
    for ax in range(2):
        a, d = seg.a[:, ax], seg.d[:, ax]
        zero = d == 0
        ok &= ~zero | ((a >= lo[ax]) & (a <= hi[ax]))
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (lo[ax] - a) / d
            tb = (hi[ax] - a) / d
        tmin = np.where(zero, -np.inf, np.minimum(ta, tb))
        tmax = np.where(zero, np.inf, np.maximum(ta, tb))
        t0 = np.maximum(t0, tmin)
        t1 = np.minimum(t1, tmax)
    return bool(np.any(ok & (t0 <= t1)))


def trace_in_data_check(
    trace: FaultTrace,
    points_xy: np.ndarray,
    *,
    buffer_m: float = 10.0,
    geometry: Optional[FaultGeometry] = None,
    quiet: bool = False,
) -> FaultGeometry:
    """Check that a trace runs through the data and that the data lie on both of its sides.

    Parameters
    ----------
    trace : FaultTrace
    points_xy : numpy.ndarray, shape (N, 2) or (N, 3)
        Point coordinates (metres, the trace's CRS).
    buffer_m : float, default 10.0
        Buffer excluded around the trace (metres); only points outside it are counted.
    geometry : FaultGeometry, optional
        The points' geometry if already computed (else it is computed here).
    quiet : bool, default False
        Do not log the counts per side (a caller checking ahead of the computation, which
        logs them itself).

    Returns
    -------
    FaultGeometry
        The points' geometry (``geometry`` when given).

    Raises
    ------
    InputDataError
        If there are no points, the trace does not cross the points' x/y extent, or all
        points outside the buffer are on one side of the trace (or none is outside it).
    """
    pts = np.asarray(points_xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3) or len(pts) == 0:
        raise InputDataError(
            f"no points to check the fault trace against (points shape {pts.shape})"
        )
    pts = pts[:, :2]
    lo, hi = np.nanmin(pts, axis=0), np.nanmax(pts, axis=0)
    seg = _Segments(trace)
    if not _segments_hit_box(seg, lo - seg.origin, hi - seg.origin):
        v = trace.vertices
        tlo, thi = v.min(axis=0), v.max(axis=0)
        raise InputDataError(
            "the fault trace does not cross the data's extent: trace x "
            f"{tlo[0]:.3f}..{thi[0]:.3f}, y {tlo[1]:.3f}..{thi[1]:.3f}; points x "
            f"{lo[0]:.3f}..{hi[0]:.3f}, y {lo[1]:.3f}..{hi[1]:.3f}; check the trace or its CRS"
        )
    geom = geometry if geometry is not None else fault_geometry(pts, trace)
    left, right = side_masks(geom, buffer_m=buffer_m)
    n_left, n_right = int(left.sum()), int(right.sum())
    (logger.debug if quiet else logger.info)(
        "fault trace: %d points on the left, %d on the right, %d within %g m",
        n_left,
        n_right,
        len(pts) - n_left - n_right,
        buffer_m,
    )
    if n_left == 0 and n_right == 0:
        raise InputDataError(
            f"all {len(pts)} points are within the {buffer_m:g} m buffer around the fault "
            "trace; reduce buffer_m or check the trace"
        )
    if n_right == 0 or n_left == 0:
        which = "left" if n_right == 0 else "right"
        raise InputDataError(
            f"fault trace has all {n_left + n_right} points (outside its {buffer_m:g} m "
            f"buffer) on its {which} side; check the trace or its CRS"
        )
    return geom


def point_at_chainage(trace: FaultTrace, along_m: float) -> np.ndarray:
    """Map position (2,) at chainage ``along_m`` (metres from the first vertex, parts in
    order, gaps between parts not counted; clamped to the trace's ends)."""
    done = 0.0
    last = trace.parts[-1][-1]
    for part in trace.parts:
        seg = np.diff(part, axis=0)
        lengths = np.hypot(seg[:, 0], seg[:, 1])
        for k, length in enumerate(lengths):
            if along_m <= done + length and length > 0:
                f = max(0.0, (along_m - done) / length)
                return part[k] + f * seg[k]
            done += length
    return np.array(last, dtype=np.float64)
