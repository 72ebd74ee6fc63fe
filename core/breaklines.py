"""Breaklines: lines across which a displacement field may jump (scarps, faults, slab edges).

A displacement field is smooth on each side of a breakline and may be discontinuous across
it. The fields' methods (the windowed-ICP spline field, PIV's window deformation) ask two
questions of a set of breaklines, answered here on arrays:

* does the straight segment from ``p`` to ``q`` cross a breakline (``p`` and ``q`` are then
  on different sides as far as a smooth field is concerned, even where the line ends inside
  the area and the field is continuous around its tip)?
* how far is a point from the nearest breakline (vectors near one are flagged)?

Pure numpy; the lines come from a vector file through :mod:`slipmap.core.io.vector` or from a
detection on the data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, List, Sequence

import numpy as np

from .errors import InvalidParameterError

__all__ = ["Breaklines", "breaklines", "crossings", "same_side", "distance_m", "from_sequence"]


@dataclass(frozen=True)
class Breaklines:
    """A set of breaklines as straight segments.

    Attributes
    ----------
    parts : tuple of ndarray
        The polylines, each ``(M, 2)`` vertices (map units, metres).
    segments : ndarray, shape (S, 4)
        Every segment ``x0, y0, x1, y1`` of every part.
    """

    parts: tuple
    segments: np.ndarray

    def __len__(self) -> int:
        return len(self.parts)

    @property
    def empty(self) -> bool:
        return len(self.segments) == 0

    def length_m(self) -> float:
        s = self.segments
        return float(np.hypot(s[:, 2] - s[:, 0], s[:, 3] - s[:, 1]).sum())


def breaklines(parts: Iterable[np.ndarray]) -> Breaklines:
    """Build :class:`Breaklines` from polylines.

    Parameters
    ----------
    parts : iterable of array_like, each (M, 2) or (M, 3)
        Vertices in the points' CRS (metres); z is dropped; repeated vertices are removed.

    Returns
    -------
    Breaklines

    Raises
    ------
    InvalidParameterError
        If a part has fewer than 2 distinct vertices or non-finite coordinates.
    """
    kept: List[np.ndarray] = []
    segs: List[np.ndarray] = []
    for i, part in enumerate(parts):
        v = np.asarray(part, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] < 2:
            raise InvalidParameterError(f"breakline {i}: vertices must be (M, 2), got {v.shape}")
        v = v[:, :2]
        if not np.isfinite(v).all():
            raise InvalidParameterError(f"breakline {i}: non-finite vertex coordinates")
        keep = np.ones(len(v), dtype=bool)
        keep[1:] = np.any(np.diff(v, axis=0) != 0.0, axis=1)
        v = v[keep]
        if len(v) < 2:
            raise InvalidParameterError(f"breakline {i} has fewer than 2 distinct vertices")
        kept.append(v)
        segs.append(np.hstack([v[:-1], v[1:]]))
    seg = np.vstack(segs) if segs else np.empty((0, 4))
    return Breaklines(parts=tuple(kept), segments=seg)


def _as_xy(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return a.reshape(-1, a.shape[-1])[:, :2]


def crossings(p: np.ndarray, q: np.ndarray, lines: Breaklines, *, chunk: int = 65536) -> np.ndarray:
    """Number of breakline segments that the segment ``p -> q`` crosses.

    Parameters
    ----------
    p, q : ndarray, shape (N, 2) (or (N, 3); z is ignored)
        Segment ends, metres. ``q`` may be ``(2,)`` (one end shared by every segment).
    lines : Breaklines
    chunk : int
        Pairs handled at once (memory: ``chunk x S`` booleans).

    Returns
    -------
    ndarray of int, shape (N,)
        Proper crossings (an end exactly on a breakline counts as a crossing of that
        segment, so a point on the line is never "on the same side" as both neighbours;
        segments that only touch collinearly are not counted).

    Notes
    -----
    The standard orientation test (two signs of cross products per pair of segments),
    vectorised over pairs x breakline segments; a bounding-box prefilter keeps it to the
    segments near each pair.
    """
    p = _as_xy(p)
    q = np.broadcast_to(_as_xy(q), p.shape) if np.ndim(q) == 1 else _as_xy(q)
    out = np.zeros(len(p), dtype=np.int64)
    s = lines.segments
    if len(s) == 0 or len(p) == 0:
        return out
    a, b = s[:, 0:2], s[:, 2:4]
    smin = np.minimum(a, b)
    smax = np.maximum(a, b)
    for lo in range(0, len(p), chunk):
        pp = p[lo : lo + chunk, None, :]
        qq = q[lo : lo + chunk, None, :]
        near = (np.minimum(pp, qq) <= smax[None]).all(axis=2) & (
            np.maximum(pp, qq) >= smin[None]
        ).all(axis=2)
        if not near.any():
            continue
        i, j = np.nonzero(near)
        pi, qi = p[lo + i], q[lo + i]
        aj, bj = a[j], b[j]
        d1 = _orient(aj, bj, pi)
        d2 = _orient(aj, bj, qi)
        d3 = _orient(pi, qi, aj)
        d4 = _orient(pi, qi, bj)
        hit = (d1 * d2 <= 0) & (d3 * d4 < 0) & ~((d1 == 0) & (d2 == 0))
        np.add.at(out, lo + i[hit], 1)
    return out


def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Sign of the cross product (b - a) x (c - a): +1 left, -1 right, 0 collinear."""
    v = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    return np.sign(v)


def same_side(p: np.ndarray, q: np.ndarray, lines: Breaklines) -> np.ndarray:
    """True where the segment ``p -> q`` crosses no breakline.

    Parameters
    ----------
    p, q : ndarray, shape (N, 2)
        Segment ends, metres (``q`` may be one ``(2,)`` point).

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    return crossings(p, q, lines) == 0


def distance_m(points: np.ndarray, lines: Breaklines, *, chunk: int = 65536) -> np.ndarray:
    """Horizontal distance of each point to the nearest breakline, metres.

    Parameters
    ----------
    points : ndarray, shape (N, 2) or (N, 3)
    lines : Breaklines

    Returns
    -------
    ndarray, shape (N,)
        ``inf`` where there are no breaklines.
    """
    p = _as_xy(points)
    s = lines.segments
    out = np.full(len(p), np.inf)
    if len(s) == 0:
        return out
    a = s[:, 0:2]
    d = s[:, 2:4] - a
    dd = np.maximum((d * d).sum(axis=1), 1e-300)
    for lo in range(0, len(p), max(1, chunk // max(1, len(s)))):
        pp = p[lo : lo + max(1, chunk // max(1, len(s))), None, :]
        t = np.clip((((pp - a[None]) * d[None]).sum(axis=2)) / dd[None], 0.0, 1.0)
        foot = a[None] + t[..., None] * d[None]
        out[lo : lo + len(pp)] = np.sqrt(((pp - foot) ** 2).sum(axis=2)).min(axis=1)
    return out


def from_sequence(parts: Sequence[np.ndarray] | Breaklines | None) -> Breaklines | None:
    """``None``/empty -> ``None``; polylines -> :class:`Breaklines`; Breaklines unchanged."""
    if parts is None:
        return None
    if isinstance(parts, Breaklines):
        return None if parts.empty else parts
    bl = breaklines(parts)
    return None if bl.empty else bl
