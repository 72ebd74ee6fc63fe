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

__all__ = [
    "Breaklines",
    "breaklines",
    "crossings",
    "same_side",
    "distance_m",
    "share_within",
    "from_sequence",
    "given_breaklines",
    "detect_breaklines",
    "step_edges",
    "StraightStep",
    "scan_straight_step",
    "straight_across",
]


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


def share_within(lines: Breaklines, line: Breaklines, within_m: float) -> float:
    """Share of the length of ``lines`` within ``within_m`` (metres) of ``line``, sampled
    every tenth of ``within_m`` along each segment."""
    pts = []
    for part in lines.parts:
        seg = np.diff(part, axis=0)
        n = np.maximum(np.ceil(np.hypot(seg[:, 0], seg[:, 1]) / (0.1 * within_m)), 1)
        for p0, dv, k in zip(part[:-1], seg, n.astype(int)):
            pts.append(p0 + (np.arange(k) + 0.5)[:, None] / k * dv)
    return float(np.mean(distance_m(np.vstack(pts), line) <= within_m))


def from_sequence(parts: Sequence[np.ndarray] | Breaklines | None) -> Breaklines | None:
    """``None``/empty -> ``None``; polylines -> :class:`Breaklines`; Breaklines unchanged."""
    if parts is None:
        return None
    if isinstance(parts, Breaklines):
        return None if parts.empty else parts
    bl = breaklines(parts)
    return None if bl.empty else bl


def given_breaklines(parts) -> Breaklines | None:
    """A run's ``breaklines`` option checked (:func:`from_sequence`; errors name the
    option): one check for the one-file and the tiled windowed ICP."""
    try:
        lines = from_sequence(parts)
    except InvalidParameterError as exc:
        raise InvalidParameterError(f"breaklines: {exc}") from exc
    if parts is not None and not isinstance(parts, (Breaklines, list, tuple)):
        raise InvalidParameterError("breaklines must be a Breaklines or a list of (M, 2) arrays")
    return lines


# --------------------------------------------------------------------------- detection

#: a jump counts when it exceeds this many times the larger jump of the parallel edges on
#: either side (a step sits on one edge; a smooth field's differences change slowly)
DETECT_RATIO = 3.0
#: ... and this many sigmas of the difference (the cells' sigmas, inflated as they come)
DETECT_SIGMAS = 5.0
#: ... and this many metres (the noise floor of a "jump")
DETECT_FLOOR_M = 0.05
#: with the vectors' gradients (a rotating block), the neighbouring differences that a step
#: must exceed ``ratio`` times are at least this share of the raw ones: the cells' gradients
#: are trusted to explain no more than 70 % of them (on the harness's slump, 5 m rigid cells
#: inside the 3° block report 2.5-3.1°, those at its edge 0.05-0.4°; a rigid cell reports a
#: lobe's rotation, not its strain)
DETECT_GRADIENT_SHARE = 0.3
#: a line is kept when its cell edges span this many cells at least (a single wrong cell
#: is boxed by 4 jumping edges over 1.4 cells)
DETECT_MIN_CELLS = 3.0
#: a detected line is extended by this many cells at both ends
DETECT_EXTEND_CELLS = 2.0
#: ... and to the edge of the vectors (one cell beyond) where that is at most this far
DETECT_REACH_EDGE_CELLS = 4.0


def step_edges(
    d: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    sigma: np.ndarray | None = None,
    ratio: float = DETECT_RATIO,
    n_sigma: float = DETECT_SIGMAS,
    floor_m: float = DETECT_FLOOR_M,
    gradient: np.ndarray | None = None,
    spacing_m: tuple | None = None,
    z: np.ndarray | None = None,
    sigma_gradient: np.ndarray | None = None,
):
    """Edges of a regular grid of vectors across which the field steps.

    The edge between neighbours ``i`` and ``i + 1`` (along rows or along columns) carries
    the difference ``J_i = d_(i+1) - d_i``; a smooth field's differences change slowly from
    one edge to the next, a step puts its whole jump on one edge. An edge is a step when

    * ``|J_i - (J_(i-1) + J_(i+1)) / 2| > max(n_sigma s, floor_m)`` (``s``: the sigma of
      that combination from the vectors' sigmas, as if independent), and
    * ``|J_i| > ratio * max(|J_(i-1)|, |J_(i+1)|)``

    (the parallel edges on either side; one missing is left out, both missing: no test).
    A cell that straddles a step takes a motion between the two sides' and splits the jump
    over its two edges: the same test on the pair of edges (``J_i + J_(i+1)``, in the same
    direction, against ``J_(i-1)`` and ``J_(i+2)``) marks the pair's larger edge.

    **A block that moves rigidly** (translation and rotation: a rotational slump) breaks the
    second test: a rotation ``w`` changes the motion by ``w x Δp`` from one cell to the next
    (3° over 5 m cells: 0.26 m), as much as the jump across the block's outline, so no edge
    stands out. Where the vectors come with their own ``gradient`` (ICP cells estimate it
    from their points: a rigid cell's rotation, an affine cell's full gradient), the same two
    tests are also run on the part of each difference that the two cells' gradients do not
    explain,

        ``E_i = J_i - (G_i + G_(i+1)) / 2 · Δp_i``

    (``Δp_i``: the step between the two cells' centres, their mean heights ``z`` included;
    the mean of the two gradients makes ``E`` vanish for any field whose gradient changes
    linearly, a quadratic field included). Inside a rigid block, and anywhere the cells'
    gradients describe the field, ``E`` is the cells' noise; across the block's outline it
    is the jump less half the block's rotation over one cell. An edge is a step when either
    difference passes (``J``: a translating slab, the steps of cells whose gradients are
    poorly determined; ``E``: a rotating block). What the cells' gradients do not hold
    (a rigid cell's strain on a lobe) stays in ``E`` and changes slowly there, so the ratio
    test still keeps smooth fields whole; and as a cell's gradient is less certain than its
    motion (one that straddles an edge reports a blend), the neighbours' ``|E|`` that the
    ratio test compares with is taken as at least :data:`DETECT_GRADIENT_SHARE` of their
    ``|J|``. On the lobes that the step test leaves alone, with their exact gradients or
    only their rotations, ``E`` adds no line (tests/core/test_breaklines_rigid.py); where
    the step test already cuts a lobe 2-3 cells in radius, so does ``E``, and the points
    drop the line (``refine_breaklines``). The sigma of ``E`` adds the gradients' own,
    ``|Δp| sigma_gradient / 2`` per cell. The pair test on ``E`` takes the two outer cells'
    gradients over the two cells, so it also runs where the middle cell is missing (a
    straddling cell that the median test or the point count removed; the step is then put
    on the pair's first edge). This uses the cells' rotations rather than a plane fitted to
    each side's neighbours: around a small block (18 m on 5 m cells) a side holds two or
    three usable cells, too few for a local affine fit, while every cell carries its own.

    Parameters
    ----------
    d : (R, C, K) float64
        The vectors (K components, e.g. dx, dy, dz), metres.
    valid : (R, C) bool, optional
        Usable vectors (default: all finite).
    sigma : (R, C) or (R, C, K) float64, optional
        1-sigma of the vectors (per component or one value), metres; default 0.
    gradient : (R, C, K, 3) float64, optional
        Each vector's gradient ``∂d_k / ∂(x, y, z)`` (dimensionless); NaN where unknown
        (that cell's edges get the step test on ``J`` only).
    spacing_m : (float, float), optional
        ``(x[c + 1] - x[c], y[r + 1] - y[r])``, metres (signed); required with ``gradient``.
    z : (R, C) float64, optional
        The vectors' heights (an ICP cell's mean z), metres; default: level (0).
    sigma_gradient : (R, C) float64, optional
        1-sigma of each gradient (its rotation vector's norm, radians); default 0.

    Returns
    -------
    along_rows : (R, C - 1) bool
        Step between ``(r, c)`` and ``(r, c + 1)``.
    along_cols : (R - 1, C) bool
        Step between ``(r, c)`` and ``(r + 1, c)``.
    """
    d = np.asarray(d, dtype=np.float64)
    if d.ndim == 2:
        d = d[:, :, None]
    ok = np.all(np.isfinite(d), axis=2)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    if sigma is None:
        s2 = np.zeros(ok.shape)
    else:
        sg = np.asarray(sigma, dtype=np.float64)
        s2 = np.sum(sg**2, axis=2) if sg.ndim == 3 else sg**2
        s2 = np.where(np.isfinite(s2), s2, np.inf)
    d = np.where(ok[:, :, None], d, np.nan)
    rows = _steps_along(d, s2, ratio, n_sigma, floor_m)
    cols = _steps_along(np.transpose(d, (1, 0, 2)), s2.T, ratio, n_sigma, floor_m).T
    if gradient is None:
        return rows, cols
    if spacing_m is None:
        raise InvalidParameterError("step_edges: spacing_m is required with gradient")
    g = np.asarray(gradient, dtype=np.float64)
    if g.shape != d.shape + (3,):
        raise InvalidParameterError(f"gradient must be {d.shape + (3,)}, got {g.shape}")
    g = np.where(ok[:, :, None, None], g, np.nan)
    zz = np.zeros(ok.shape) if z is None else np.asarray(z, dtype=np.float64)
    zz = np.where(np.isfinite(zz), zz, np.nan)
    if sigma_gradient is None:
        sgg = np.zeros(ok.shape)
    else:
        sgg = np.asarray(sigma_gradient, dtype=np.float64) ** 2
        sgg = np.where(np.isfinite(sgg), sgg, np.inf)
    sx, sy = float(spacing_m[0]), float(spacing_m[1])
    t = (1, 0, 2)
    rows |= _steps_along(d, s2, ratio, n_sigma, floor_m, grad=(g, zz, sgg, sx, 0.0))
    cols |= _steps_along(
        np.transpose(d, t), s2.T, ratio, n_sigma, floor_m,
        grad=(np.transpose(g, (1, 0, 2, 3)), zz.T, sgg.T, 0.0, sy),
    ).T  # fmt: skip
    return rows, cols


def _differences(dd, ss, k, grad):
    """Differences over ``k`` cells along axis 1 and their variances: ``J`` (no ``grad``)
    or ``E`` (``grad = (G, z, sigma_G², step_x, step_y)``, see :func:`step_edges`)."""
    j = dd[:, k:] - dd[:, :-k]
    js = ss[:, k:] + ss[:, :-k]
    if grad is None:
        return j, js
    g, zz, sgg, step_x, step_y = grad
    dz = zz[:, k:] - zz[:, :-k]
    dp = np.stack(
        [np.full(dz.shape, k * step_x), np.full(dz.shape, k * step_y), np.nan_to_num(dz)],
        axis=-1,
    )
    gm = 0.5 * (g[:, k:] + g[:, :-k])
    e = j - np.einsum("...ij,...j->...i", gm, dp)
    es = js + 0.25 * np.sum(dp**2, axis=-1) * (sgg[:, k:] + sgg[:, :-k])
    return e, es


def _both_finite(a, b):
    """Both of two (2-stacked) neighbour differences finite: (2, R, C')."""
    return np.all(np.isfinite(np.stack([a, b])), axis=3)


def _steps_along(dd, ss, ratio, n_sigma, floor_m, grad=None):
    """The step test of :func:`step_edges` between neighbours along axis 1: ``(R, C - 1)``
    bool, on ``J`` (``grad`` None) or on ``E``."""
    j, js = _differences(dd, ss, 1, grad)  # (R, C-1, K)
    pad = np.full_like(j[:, :1], np.nan)
    prev = np.concatenate([pad, j[:, :-1]], axis=1)
    nxt = np.concatenate([j[:, 1:], pad], axis=1)
    both = np.stack([prev, nxt])
    have = np.all(np.isfinite(both), axis=3)  # (2, R, C-1)
    # with gradients: the neighbours' E, but at least a share of their J (the cells'
    # gradients are trusted to explain no more than 1 - DETECT_GRADIENT_SHARE of it)
    floor_other = np.zeros(j.shape[:2])
    if grad is not None:
        jr, _ = _differences(dd, ss, 1, None)
        prev_r = np.concatenate([pad, jr[:, :-1]], axis=1)
        next_r = np.concatenate([jr[:, 1:], pad], axis=1)
        raw = np.linalg.norm(np.stack([prev_r, next_r]), axis=3)
        floor_other = DETECT_GRADIENT_SHARE * np.max(np.where(have, raw, 0.0), axis=0)
    n_have = have.sum(axis=0)
    bg = np.where(
        n_have[..., None] > 0,
        np.nansum(both, axis=0) / np.maximum(n_have, 1)[..., None],
        np.nan,
    )
    dev = np.linalg.norm(j - bg, axis=2)
    # variance of J - mean(J_prev, J_next): the edge's two vectors enter with weight
    # 1.5, the outer ones with 0.5 (both neighbours), roughly 1.25 x var(J)
    sd = np.sqrt(1.25 * js)
    mag = np.linalg.norm(j, axis=2)
    other = np.nanmax(np.where(have, np.linalg.norm(both, axis=3), -np.inf), axis=0)
    other = np.maximum(other, floor_other)
    with np.errstate(invalid="ignore"):
        step = (
            (n_have > 0)
            & np.isfinite(mag)
            & (dev > np.maximum(n_sigma * sd, floor_m))
            & (mag > ratio * other)
        )
    if j.shape[1] < 2:
        return step
    # a cell that straddles the step takes a motion between the sides' and splits the
    # jump over its two edges: the same test on the pair (J_i + J_(i+1) against J_(i-1)
    # and J_(i+2)), the step put on the pair's larger edge
    if grad is None:
        j2 = j[:, :-1] + j[:, 1:]  # (R, C-2, K)
        js2 = js[:, :-1] + js[:, 1:]
        same_way = np.sum(j[:, :-1] * j[:, 1:], axis=2) > 0
    else:  # over the two cells with the outer cells' gradients: the middle may be missing
        j2, js2 = _differences(dd, ss, 2, grad)
        raw2 = np.stack([prev_r[:, :-1], next_r[:, 1:]])
        floor2 = DETECT_GRADIENT_SHARE * np.max(
            np.where(_both_finite(prev[:, :-1], nxt[:, 1:]), np.linalg.norm(raw2, axis=3), 0.0),
            axis=0,
        )
        dot = np.sum(j[:, :-1] * j[:, 1:], axis=2)
        same_way = ~np.isfinite(dot) | (dot > 0)
    prev2, next2 = prev[:, :-1], nxt[:, 1:]
    both2 = np.stack([prev2, next2])
    have2 = np.all(np.isfinite(both2), axis=3)
    n2 = have2.sum(axis=0)
    bg2 = np.where(
        n2[..., None] > 0, np.nansum(both2, axis=0) / np.maximum(n2, 1)[..., None], np.nan
    )
    dev2 = np.linalg.norm(j2 - 2.0 * bg2, axis=2)
    mag2 = np.linalg.norm(j2, axis=2)
    other2 = np.nanmax(np.where(have2, np.linalg.norm(both2, axis=3), -np.inf), axis=0)
    other2 = np.maximum(other2, floor_other[:, :-1] if grad is None else floor2)
    with np.errstate(invalid="ignore"):
        pair = (
            (n2 > 0)
            & np.isfinite(mag2)
            & same_way
            & (dev2 > np.maximum(n_sigma * np.sqrt(1.25 * js2), floor_m))
            & (mag2 > 2.0 * ratio * other2)
        )
    r_i, c_i = np.nonzero(pair)
    with np.errstate(invalid="ignore"):
        second = mag[r_i, c_i + 1] > mag[r_i, c_i]
    step[r_i, np.where(second, c_i + 1, c_i)] = True
    return step


def detect_breaklines(
    d: np.ndarray,
    *,
    x: np.ndarray,
    y: np.ndarray,
    valid: np.ndarray | None = None,
    sigma: np.ndarray | None = None,
    ratio: float = DETECT_RATIO,
    n_sigma: float = DETECT_SIGMAS,
    floor_m: float = DETECT_FLOOR_M,
    min_cells: float = DETECT_MIN_CELLS,
    gradient: np.ndarray | None = None,
    z: np.ndarray | None = None,
    sigma_gradient: np.ndarray | None = None,
) -> Breaklines | None:
    """Breaklines of a regular grid of displacement vectors (ICP cells, PIV vectors).

    The step edges (:func:`step_edges`) are chained through the grid's cell corners into
    connected sets; a set that spans ``min_cells`` cells or more becomes one line: the
    longest chain of corners through it (a graph's diameter, by SciPy's shortest paths),
    smoothed by a running mean of three corners, simplified (Douglas-Peucker, a quarter
    of a cell) and extended by :data:`DETECT_EXTEND_CELLS` cells at both ends (the chain
    stops at the last pair of cells that both pass the test), or to the edge of the valid
    vectors where that is at most :data:`DETECT_REACH_EDGE_CELLS` cells away. Smooth fields
    (a lobe whose differences grow and shrink over several cells) give no step edges; a
    lone wrong vector boxes itself in with four and is dropped by ``min_cells``.

    Parameters
    ----------
    d : (R, C, K) float64
        Vectors, metres; ``d[r, c]`` sits at ``(x[c], y[r])``.
    x : (C,) float64
        Column positions (equally spaced, either direction), metres.
    y : (R,) float64
        Row positions (equally spaced, either direction), metres.
    valid, sigma, ratio, n_sigma, floor_m
        As in :func:`step_edges`.
    min_cells : float
        Smallest extent of a line, in cells.
    gradient, z, sigma_gradient : optional
        The vectors' own gradients ``(R, C, K, 3)``, heights ``(R, C)`` (metres) and the
        gradients' 1-sigma ``(R, C)`` (radians), as in :func:`step_edges`: the edge of a
        block that moves rigidly (translation and rotation) is found too.

    Returns
    -------
    Breaklines or None
        None when no line is found.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, shortest_path

    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    d = np.asarray(d, dtype=np.float64)
    if d.ndim == 2:
        d = d[:, :, None]
    n_r, n_c = d.shape[:2]
    if len(x) != n_c or len(y) != n_r:
        raise InvalidParameterError(f"x, y must have {n_c} and {n_r} positions")
    if n_r < 2 and n_c < 2:
        return None
    sx = float(x[1] - x[0]) if n_c > 1 else float(abs(y[1] - y[0]))
    sy = float(y[1] - y[0]) if n_r > 1 else float(abs(sx))
    rows, cols = step_edges(
        d, valid=valid, sigma=sigma, ratio=ratio, n_sigma=n_sigma, floor_m=floor_m,
        gradient=gradient, spacing_m=(sx, sy), z=z, sigma_gradient=sigma_gradient,
    )  # fmt: skip
    # corners (i, j), i = 0..R, j = 0..C, at x[0] + (j - 0.5) sx, y[0] + (i - 0.5) sy
    n_cc = n_c + 1
    r, c = np.nonzero(rows)  # edge between (r, c), (r, c+1): corners (r, c+1)-(r+1, c+1)
    e0 = [r * n_cc + c + 1]
    e1 = [(r + 1) * n_cc + c + 1]
    r, c = np.nonzero(cols)  # between (r, c), (r+1, c): corners (r+1, c)-(r+1, c+1)
    e0.append((r + 1) * n_cc + c)
    e1.append((r + 1) * n_cc + c + 1)
    a, b = np.concatenate(e0), np.concatenate(e1)
    if a.size == 0:
        return None
    n_nodes = (n_r + 1) * n_cc
    g = coo_matrix((np.ones(a.size), (a, b)), shape=(n_nodes, n_nodes)).tocsr()
    g = g + g.T
    _, label = connected_components(g, directed=False)
    used = np.unique(np.concatenate([a, b]))
    have = np.all(np.isfinite(d), axis=2) if valid is None else np.asarray(valid, bool)
    rr, cc = np.nonzero(have)
    box_pos = _corner_xy(
        np.concatenate([rr * n_cc + cc, (rr + 1) * n_cc + cc + 1]), n_cc, x[0], y[0], sx, sy
    )
    box_lo, box_hi = box_pos.min(axis=0), box_pos.max(axis=0)
    cell = float(np.hypot(sx, sy) / np.sqrt(2.0))
    parts = []
    for lab in np.unique(label[used]):
        nodes = used[label[used] == lab]
        pos = _corner_xy(nodes, n_cc, x[0], y[0], sx, sy)
        span = np.max(np.ptp(pos, axis=0)) / cell
        if span < min_cells - 1e-9:
            continue
        sub = g[nodes][:, nodes]
        far = shortest_path(sub, directed=False, unweighted=True, indices=0)
        s0 = int(np.argmax(np.where(np.isfinite(far), far, -1)))
        dist, pred = shortest_path(
            sub, directed=False, unweighted=True, indices=s0, return_predecessors=True
        )
        s1 = int(np.argmax(np.where(np.isfinite(dist), dist, -1)))
        path = [s1]
        while path[-1] != s0:
            path.append(int(pred[path[-1]]))
        line = pos[np.asarray(path)]
        if len(line) > 2:  # running mean of three corners, ends kept
            inner = (line[:-2] + line[1:-1] + line[2:]) / 3.0
            line = np.vstack([line[:1], inner, line[-1:]])
        line = _douglas_peucker(line, 0.25 * cell)
        # the chain stops at the last pair of cells that both pass the test; the scarp goes
        # on under the cells beyond (the partial cells at the data's edge, a cell that
        # straddles it with a mixed motion): two cells; beyond a scarp's true tip the field's
        # two sides then meet the same data and agree. To the edge of the vectors (and a cell
        # beyond) where that is at most DETECT_REACH_EDGE_CELLS away
        for end, inner in ((0, 1), (-1, -2)):
            t = line[end] - line[inner]
            t = t / max(np.hypot(*t), 1e-12)
            to_edge = _exit_distance(line[end], t, box_lo, box_hi)
            reach = DETECT_EXTEND_CELLS * cell
            if to_edge <= DETECT_REACH_EDGE_CELLS * cell:
                reach = max(reach, to_edge + cell)
            line[end] = line[end] + reach * t
        parts.append(line)
    return from_sequence(parts) if parts else None


#: the straight-line scan (:func:`scan_straight_step`): the band on either side of a
#: candidate line whose cells it fits, in cells
SCAN_BAND_CELLS = 3.0
#: ... cells closer than this to the candidate are left out (they straddle it), in cells
SCAN_GAP_CELLS = 0.25
#: ... the candidates: directions every this many degrees, offsets every this many cells
SCAN_ANGLE_STEP_DEG = 7.5
SCAN_OFFSET_STEP_CELLS = 0.5
#: ... a candidate is proposed when its step is at least this many times ``floor_m``
SCAN_MIN_STEP_FLOORS = 2.0
#: ... and this many times the RMS of the band's residuals
SCAN_MIN_STEP_RMS = 3.0
#: ... and each side holds this many cells at least
SCAN_MIN_SIDE_CELLS = 4
#: a band longer than this (in cells; lone-star's 32 m x 41 m scene spans 10.4 cells of 5 m
#: on its diagonal) is fitted by the quadratic plus hat functions along the line, times
#: (1, across), with knots every SCAN_ALONG_KNOT_CELLS: across a survey larger than its
#: landslide, one quadratic along 100 m of the line cannot follow a lobe 30 m wide, its
#: residuals swamp the step and the fault is not proposed (issue #29, stop 58)
SCAN_QUADRATIC_CELLS = 12.0
SCAN_ALONG_KNOT_CELLS = 4.0
#: on the points, the field fitted with the candidate may jump across it by at most this
#: many times the step the cells saw, at every station along it (more: the two sides'
#: fields are carried over ground the line cuts wrongly, e.g. a straight line through a
#: block that ends inside the area)
SCAN_MAX_JUMP_STEPS = 2.0
#: ... and by at least this share of it (median over the points near it): the cells see a
#: lobe's flank on the cells' scale as a step, the points resolve it (lone-star's 1 m lobe
#: of radius 10.8 m: 0.83 m on the cells, 0.12 m on the points; the harness's fault: 0.29 m
#: on the cells, 0.10-0.26 m on the points)
SCAN_MIN_JUMP_STEPS = 0.25


@dataclass(frozen=True)
class StraightStep:
    """The straight line across which a grid of vectors steps most clearly
    (:func:`scan_straight_step`).

    Attributes
    ----------
    line : Breaklines
        One straight part, from one edge of the vectors' box (and a cell beyond) to the
        other, metres.
    angle_deg : float
        Its direction, degrees counter-clockwise from the x axis, in [0, 180).
    step_m : ndarray, shape (K,)
        The fitted step (left side minus right side as seen along the line), metres.
    rms_m : float
        RMS of the band's residuals about the fit with the step, metres.
    f_stat : float
        The F statistic of the step (the residuals' reduction per component, over the
        residual variance).
    n_cells : int
        Cells in the band.
    box_m : ndarray, shape (2, 2), optional
        The box the line crosses (its lower and upper x, y corners: the vectors' box and a
        cell beyond), metres; :func:`straight_across` draws another line across it.
    """

    line: Breaklines
    angle_deg: float
    step_m: np.ndarray
    rms_m: float
    f_stat: float
    n_cells: int
    box_m: np.ndarray | None = None


def _poly2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Design of a quadratic in (u, v): 1, u, v, u², u v, v²."""
    return np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])


def _band_design(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The smooth part of the scan's band model, ``u`` along the line and ``v`` across it
    (cells; ``v`` scaled to the band): the quadratic of :func:`_poly2` on ``u`` scaled to
    the band's length, and where the band is longer than :data:`SCAN_QUADRATIC_CELLS`, hat
    functions of ``u`` (knots every :data:`SCAN_ALONG_KNOT_CELLS`, the band's ends left to
    the quadratic) times 1 and ``v``."""
    span = float(np.ptp(u)) if u.size else 0.0
    us = (u - u.mean()) / max(span, 1.0)
    x0 = _poly2(us, v)
    if span <= SCAN_QUADRATIC_CELLS:
        return x0
    k = SCAN_ALONG_KNOT_CELLS
    knots = float(u.min()) + k * np.arange(1, int(span // k) + 1)
    knots = knots[knots < float(u.max())]
    hats = np.clip(1.0 - np.abs(u[:, None] - knots[None, :]) / k, 0.0, None)
    return np.column_stack([x0, hats, hats * v[:, None]])


def scan_straight_step(
    d: np.ndarray,
    *,
    x: np.ndarray,
    y: np.ndarray,
    valid: np.ndarray | None = None,
    floor_m: float = DETECT_FLOOR_M,
    band_cells: float = SCAN_BAND_CELLS,
    angle_step_deg: float = SCAN_ANGLE_STEP_DEG,
) -> StraightStep | None:
    """The straight line across which a grid of vectors steps most clearly, if any.

    The edge test of :func:`step_edges` compares each difference with its parallel
    neighbours; where the field itself changes fast (a fault across a lobe whose motion
    changes by 0.2 m from cell to cell, as much as the fault's 0.3 m) a step does not stand
    out on any one edge, and where a straight line crosses the grid diagonally its cells
    straddle it one after the other, so the edges that do pass do not chain. This scan
    weighs the whole line at once: for every straight line (directions every
    ``angle_step_deg``, offsets every half cell), the cells within ``band_cells`` of it
    (leaving out those within :data:`SCAN_GAP_CELLS` of it, which straddle it) are fitted,
    per component, by a quadratic in the line's coordinates (on a band longer than
    :data:`SCAN_QUADRATIC_CELLS`, plus hat functions along the line times 1 and the offset
    across it: :func:`_band_design`) with and without a step across the line (least
    squares); the line whose step reduces the residuals most (F statistic)
    is kept, and proposed when its step is at least :data:`SCAN_MIN_STEP_FLOORS` ×
    ``floor_m`` and :data:`SCAN_MIN_STEP_RMS` × the RMS of the band's residuals.

    The grid alone cannot tell a step from a lobe steep on the cells' scale (on 5 m cells a
    lobe 7 m wide rises by 0.4 m from one cell to the next): a proposed line is a candidate
    for the points to confirm and place (:func:`slipmap.core.breakline_points.place_straight_line`).

    Parameters
    ----------
    d : (R, C, K) float64
        Vectors, metres; ``d[r, c]`` sits at ``(x[c], y[r])``.
    x, y : (C,), (R,) float64
        Column and row positions (equally spaced, equal spacing in x and y), metres.
    valid : (R, C) bool, optional
        Usable vectors (default: all finite).
    floor_m : float
        The noise floor of a jump, metres (the step must be twice it).
    band_cells : float
        Half-width of the band fitted on either side of a candidate, cells.
    angle_step_deg : float
        Spacing of the candidates' directions, degrees.

    Returns
    -------
    StraightStep or None
        None when no candidate passes (or the grid holds too few vectors).

    Notes
    -----
    Plain loops over the candidates with ``numpy.linalg.lstsq`` (a few hundred small fits
    on a grid of tens of cells): there is no fast kernel to check against. The line is
    straight: a fault or a straight scarp; the edge test of :func:`detect_breaklines` stays
    the one for lines that bend or end inside the area.
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    d = np.asarray(d, dtype=np.float64)
    if d.ndim == 2:
        d = d[:, :, None]
    if len(x) < 2 or len(y) < 2:
        return None
    ok = np.all(np.isfinite(d), axis=2)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    r, c = np.nonzero(ok)
    if len(r) < 2 * SCAN_MIN_SIDE_CELLS + 7:
        return None
    cell = float(abs(x[1] - x[0]))
    pos = np.column_stack([x[c], y[r]])
    vec = d[r, c]
    n_k = vec.shape[1]
    ctr = pos.mean(axis=0)
    q = (pos - ctr) / cell  # in cells
    r_max = float(np.max(np.hypot(q[:, 0], q[:, 1])))

    best = None
    for th in np.radians(np.arange(0.0, 180.0, angle_step_deg)):
        t = np.array([np.cos(th), np.sin(th)])
        nrm = np.array([-t[1], t[0]])
        u_all, v_all = q @ t, q @ nrm
        for rho in np.arange(-r_max, r_max + 1e-9, SCAN_OFFSET_STEP_CELLS):
            v = v_all - rho
            band = (np.abs(v) <= band_cells) & (np.abs(v) >= SCAN_GAP_CELLS)
            side = np.sign(v[band])
            n_l, n_r = int(np.sum(side > 0)), int(np.sum(side < 0))
            if min(n_l, n_r) < SCAN_MIN_SIDE_CELLS:
                continue
            x0 = _band_design(u_all[band], v[band] / band_cells)
            x1 = np.column_stack([x0, 0.5 * side])
            obs = vec[band]
            dof = n_k * (len(obs) - x1.shape[1])
            if dof <= 0:
                continue
            c0 = np.linalg.lstsq(x0, obs, rcond=None)[0]
            c1 = np.linalg.lstsq(x1, obs, rcond=None)[0]
            rss0 = float(np.sum((obs - x0 @ c0) ** 2))
            rss1 = float(np.sum((obs - x1 @ c1) ** 2))
            f = (rss0 - rss1) / n_k / max(rss1 / dof, 1e-300)
            if best is None or f > best[0]:
                best = (f, th, rho, c1[-1], np.sqrt(rss1 / dof), int(band.sum()))
    if best is None:
        return None
    f, th, rho, step, rms, n_band = best
    mag = float(np.linalg.norm(step))
    if mag < SCAN_MIN_STEP_FLOORS * floor_m or mag < SCAN_MIN_STEP_RMS * rms:
        return None
    t = np.array([np.cos(th), np.sin(th)])
    nrm = np.array([-t[1], t[0]])
    mid = ctr + rho * cell * nrm
    # across the vectors' box and a cell beyond, both ways
    box = np.array([pos.min(axis=0) - cell, pos.max(axis=0) + cell])
    line = straight_across(mid, t, box)
    if line is None:
        return None
    return StraightStep(line=line, angle_deg=float(np.degrees(th)), step_m=np.asarray(step),
                        rms_m=float(rms), f_stat=float(f), n_cells=n_band,
                        box_m=box)  # fmt: skip


def straight_across(
    point: np.ndarray, direction: np.ndarray, box_m: np.ndarray
) -> Breaklines | None:
    """The straight line through ``point`` (2,) along ``direction`` (2,), from one side of
    the box ``box_m`` (2, 2: lower and upper x, y corners, metres) to the other; None when
    the point lies outside the box."""
    p = np.asarray(point, dtype=np.float64)
    t = np.asarray(direction, dtype=np.float64)
    t = t / max(float(np.hypot(*t)), 1e-12)
    lo, hi = np.asarray(box_m, dtype=np.float64)
    if np.any(p < lo) or np.any(p > hi):
        return None
    ends = np.array([p - _exit_distance(p, -t, lo, hi) * t, p + _exit_distance(p, t, lo, hi) * t])
    return from_sequence([ends])


def _exit_distance(p, t, lo, hi) -> float:
    """How far from ``p`` along the unit direction ``t`` the box ``[lo, hi]`` is left."""
    out = np.inf
    for k in range(2):
        if t[k] > 1e-12:
            out = min(out, (hi[k] - p[k]) / t[k])
        elif t[k] < -1e-12:
            out = min(out, (lo[k] - p[k]) / t[k])
    return max(float(out), 0.0)


def _corner_xy(nodes, n_cc, x0, y0, sx, sy):
    i, j = np.divmod(nodes, n_cc)
    return np.column_stack([x0 + (j - 0.5) * sx, y0 + (i - 0.5) * sy])


def _douglas_peucker(line: np.ndarray, tol: float) -> np.ndarray:
    """Douglas-Peucker simplification of an (M, 2) polyline (a dozen lines of numpy; the
    geometry libraries at hand, OGR through GDAL, belong to core.io, not to core)."""
    if len(line) <= 2:
        return line
    a, b = line[0], line[-1]
    ab = b - a
    n = np.hypot(*ab)
    rel = line - a
    if n == 0:
        dist = np.hypot(rel[:, 0], rel[:, 1])
    else:
        dist = np.abs(ab[0] * rel[:, 1] - ab[1] * rel[:, 0]) / n
    k = int(np.argmax(dist))
    if dist[k] <= tol:
        return np.vstack([a, b])
    left = _douglas_peucker(line[: k + 1], tol)
    right = _douglas_peucker(line[k:], tol)
    return np.vstack([left[:-1], right])


def _step_edges_reference(
    d, *, valid=None, sigma=None, ratio=DETECT_RATIO, n_sigma=DETECT_SIGMAS,
    floor_m=DETECT_FLOOR_M, gradient=None, spacing_m=None, z=None, sigma_gradient=None,
):  # fmt: skip
    """Slow, obvious reference of :func:`step_edges`: one edge at a time, in loops."""
    d = np.asarray(d, dtype=np.float64)
    if d.ndim == 2:
        d = d[:, :, None]
    n_r, n_c, n_k = d.shape
    ok = np.all(np.isfinite(d), axis=2)
    if valid is not None:
        ok &= np.asarray(valid, dtype=bool)
    s2 = np.zeros((n_r, n_c))
    if sigma is not None:
        sg = np.asarray(sigma, dtype=np.float64)
        s2 = np.sum(sg**2, axis=2) if sg.ndim == 3 else sg**2
        s2 = np.where(np.isfinite(s2), s2, np.inf)
    sgg = np.zeros((n_r, n_c))
    if sigma_gradient is not None:
        sgg = np.where(np.isfinite(sigma_gradient), np.asarray(sigma_gradient) ** 2, np.inf)
    zz = np.zeros((n_r, n_c)) if z is None else np.asarray(z, dtype=np.float64)

    def diff(a, b, step, use_grad):  # cells a -> b (r, c), ``step`` (dx, dy) between them
        if not (ok[a] and ok[b]):
            return None, None
        j = d[b] - d[a]
        var = s2[a] + s2[b]
        if use_grad:
            dz = zz[b] - zz[a]
            dp = np.array([step[0], step[1], dz if np.isfinite(dz) else 0.0])
            gm = 0.5 * (gradient[a] + gradient[b])
            j = j - gm @ dp
            var = var + 0.25 * float(dp @ dp) * (sgg[a] + sgg[b])
        if not np.all(np.isfinite(j)):
            return None, None
        return j, var

    def test(jd, js, others, scale, raw=()):
        if jd is None or not others:
            return False
        bg = np.mean(others, axis=0)
        dev = np.linalg.norm(jd - scale * bg)
        mag = np.linalg.norm(jd)
        other = max(np.linalg.norm(o) for o in others)
        if raw:  # the share of the raw differences the gradients may leave unexplained
            other = max(other, DETECT_GRADIENT_SHARE * max(np.linalg.norm(o) for o in raw))
        return bool(
            dev > max(n_sigma * np.sqrt(1.25 * js), floor_m) and mag > scale * ratio * other
        )

    out = []
    for axis, (n_line, n_along) in enumerate(((n_r, n_c), (n_c, n_r))):
        steps = np.zeros((n_line, n_along - 1), dtype=bool)
        passes = [False] if gradient is None else [False, True]
        for use_grad in passes:
            for line in range(n_line):

                def cell(i, line=line, axis=axis):
                    return (line, i) if axis == 0 else (i, line)

                unit = (spacing_m[0], 0.0) if axis == 0 else (0.0, spacing_m[1])
                if spacing_m is None:
                    unit = (0.0, 0.0)

                def one(i, use_grad=use_grad, cell=cell, unit=unit, n_along=n_along):
                    if i < 0 or i >= n_along - 1:
                        return None, None
                    return diff(cell(i), cell(i + 1), unit, use_grad)

                def raw(idx, use_grad=use_grad, one=one, cell=cell):
                    if not use_grad:
                        return ()
                    out = []
                    for i in idx:
                        if one(i)[0] is not None:
                            out.append(diff(cell(i), cell(i + 1), (0.0, 0.0), False)[0])
                    return tuple(out)

                for i in range(n_along - 1):
                    jd, js = one(i)
                    others = [o for o in (one(i - 1)[0], one(i + 1)[0]) if o is not None]
                    if test(jd, js, others, 1.0, raw((i - 1, i + 1))):
                        steps[line, i] = True
                for i in range(n_along - 2):
                    a, b = one(i)[0], one(i + 1)[0]
                    if use_grad:
                        step2 = (2 * unit[0], 2 * unit[1])
                        j2, js2 = diff(cell(i), cell(i + 2), step2, True)
                        if a is not None and b is not None and float(a @ b) <= 0:
                            continue
                    else:
                        if a is None or b is None or float(a @ b) <= 0:
                            continue
                        j2, js2 = a + b, one(i)[1] + one(i + 1)[1]
                    others = [o for o in (one(i - 1)[0], one(i + 2)[0]) if o is not None]
                    if test(j2, js2, others, 2.0, raw((i - 1, i + 2))):
                        second = a is not None and b is not None
                        second = second and np.linalg.norm(b) > np.linalg.norm(a)
                        steps[line, i + 1 if second else i] = True
        out.append(steps if axis == 0 else steps.T)
    return out[0], out[1]
