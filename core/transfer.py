"""Transferred planes: planes found in one epoch, observed by the other epoch's points.

A sparse or noisy epoch (airborne laser scanning beside mobile mapping) is segmented on its
own, and surfaces the dense epoch resolves (walls, small roofs) are often not found as planes
in it: they are never matched and carry nothing to the adjustment, although the sparse epoch's
points on them are there. For a plane of one epoch (the *source*) without a match, this module
gathers the other epoch's (the *target*'s) points that lie on it after the current motion
estimate:

1. the source plane is moved into the target epoch with the motion
   ``target = R (source - centre) + centre + t``;
2. target points within ``band_m`` of the moved plane (a band of a few target noise σ) and
   inside the source plane's convex hull in the plane, *shrunk* by ``edge_margin_m`` (points
   near an edge may belong to the adjoining surface: a roof at a wall's top, the ground at its
   foot, a gable roof along a gable wall's sloping edges), are gathered;
3. safeguards against points of another surface: at least ``min_points`` points; the
   least-squares plane of the gathered points has a normal within ``angle_threshold_deg`` of
   the moved plane's, an RMS residual within ``max_rms_factor`` of the target noise, and a mean
   offset from the moved plane within ``max_offset_m``.

The gathered points then enter the same Gauss-Helmert adjustment as a matched plane (the
plane's parameters are estimated from both epochs' points); the plane-level stochastic model
and robust tests treat the pair like any other. :func:`.displacement.register_side` iterates
the gathering with the motion.

The convex hull is scipy's (Qhull); the in-plane test and the gathering are vectorised numpy
on a kd-tree (scipy) query per plane. :func:`gather_plane_points_reference` is the slow,
obvious reference (every target point against every plane, by loops) the tests compare with.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from .errors import InvalidParameterError
from .matching import TRANSFERRED_TO_AFTER, TRANSFERRED_TO_BEFORE, PlaneMatches
from .planes import PlaneSet

log = logging.getLogger(__name__)

#: band half-width in target-noise σ (Gaussian points: 99.7 % within 3 σ)
BAND_SIGMAS = 3.0
#: gathered points' RMS about their own plane may reach this many target-noise σ (a band of
#: ±3 σ truncates a Gaussian: its RMS is at most σ; a second surface inflates it)
MAX_RMS_FACTOR = 1.5
#: fewest gathered points of a transferred plane
MIN_POINTS = 20


@dataclass(frozen=True)
class TransferredPlanes:
    """Target-epoch points gathered on source-epoch planes.

    Attributes
    ----------
    source : (T,) int64
        Plane ids in the source epoch's :class:`PlaneSet` (only planes that passed).
    point_index : (M,) int64
        Indices into the target points of the gathered points.
    plane : (M,) int64
        Position ``0 .. T-1`` in ``source`` of each gathered point's plane.
    n_points : (T,) int64
        Points gathered per plane.
    rms_m : (T,) float64
        RMS residual of each plane's gathered points about their own least-squares plane
        (metres).
    offset_m : (T,) float64
        Mean signed distance of each plane's gathered points to the moved source plane
        (metres).
    n_tried, n_rejected : int
        Source planes examined, and those whose gathered points failed a safeguard (too few
        points, normal, RMS or offset).
    """

    source: np.ndarray
    point_index: np.ndarray
    plane: np.ndarray
    n_points: np.ndarray
    rms_m: np.ndarray
    offset_m: np.ndarray
    n_tried: int = 0
    n_rejected: int = 0

    def __len__(self) -> int:
        return int(self.source.size)


def empty_transfer(n_tried: int = 0) -> TransferredPlanes:
    e = np.empty(0, np.int64)
    return TransferredPlanes(e, e, e, e, np.empty(0), np.empty(0), n_tried, n_tried)


def move_planes(
    normals: np.ndarray,
    offsets: np.ndarray,
    *,
    rotation: np.ndarray,
    translation: np.ndarray,
    centre: np.ndarray,
) -> Tuple[np.ndarray, np.ndarray]:
    """Planes ``n . p + d = 0`` moved by ``q = R (p - centre) + centre + t``.

    Parameters
    ----------
    normals : (P, 3) float64
    offsets : (P,) float64
        Metres.
    rotation : (3, 3) float64
    translation, centre : (3,) float64
        Metres.

    Returns
    -------
    normals, offsets : (P, 3), (P,) float64
        ``n' = R n`` and ``d' = d + n . c - n' . (c + t)``.
    """
    n2 = normals @ np.asarray(rotation).T
    c = np.asarray(centre, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    return n2, offsets + normals @ c - n2 @ (c + t)


def inverse_motion(rotation, translation, centre):
    """The motion ``p = R' (q - c') + c' + t'`` undoing ``q = R (p - c) + c + t``:
    ``R' = Rᵀ, c' = c + t, t' = -t``."""
    r = np.asarray(rotation, dtype=np.float64)
    c = np.asarray(centre, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    return r.T, -t, c + t


def _in_plane_axes(normal: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal axes spanning the plane of ``normal``."""
    a = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u)])


def _hull_halfplanes(xy: np.ndarray) -> Optional[np.ndarray]:
    """(H, 3) unit half-planes ``a x + b y + c <= 0`` of the convex hull of ``xy``; None when
    the points are degenerate (fewer than 3 or collinear)."""
    from scipy.spatial import ConvexHull, QhullError

    if xy.shape[0] < 3:
        return None
    try:
        return ConvexHull(xy).equations
    except (QhullError, ValueError):
        return None


def _plane_fit(pts: np.ndarray) -> Tuple[np.ndarray, float]:
    """Least-squares plane of ``pts``: unit normal and RMS orthogonal residual (metres)."""
    c = pts.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((pts - c).T, bias=True))
    return v[:, 0], math.sqrt(max(w[0], 0.0))


def _check_options(band_m, edge_margin_m, min_points, angle_threshold_deg, max_rms_m, max_offset_m):
    if not band_m > 0:
        raise InvalidParameterError(f"band_m must be > 0, got {band_m}")
    if not edge_margin_m >= 0:
        raise InvalidParameterError(f"edge_margin_m must be >= 0, got {edge_margin_m}")
    if int(min_points) < 3:
        raise InvalidParameterError(f"min_points must be >= 3, got {min_points}")
    if not 0 < angle_threshold_deg < 90:
        raise InvalidParameterError(
            f"angle_threshold_deg must be in (0, 90), got {angle_threshold_deg}"
        )
    if not (max_rms_m > 0 and max_offset_m > 0):
        raise InvalidParameterError("max_rms_m and max_offset_m must be > 0")


def _accept(pts, r, normal, angle_threshold_deg, max_rms_m, max_offset_m, min_points):
    """The safeguards: (ok, rms, mean offset) of one plane's gathered points ``pts`` with
    signed distances ``r`` to the moved plane of unit ``normal``."""
    if pts.shape[0] < min_points:
        return False, math.nan, math.nan
    nfit, rms = _plane_fit(pts)
    off = float(r.mean())
    cosang = min(1.0, abs(float(nfit @ normal)))
    ok = (
        math.degrees(math.acos(cosang)) <= angle_threshold_deg
        and rms <= max_rms_m
        and abs(off) <= max_offset_m
    )
    return ok, rms, off


def gather_plane_points(
    source: PlaneSet,
    source_points: np.ndarray,
    plane_ids: np.ndarray,
    target_points: np.ndarray,
    candidates: np.ndarray,
    *,
    rotation: np.ndarray,
    translation: np.ndarray,
    centre: np.ndarray,
    band_m: float,
    edge_margin_m: float,
    min_points: int = MIN_POINTS,
    angle_threshold_deg: float = 3.0,
    max_rms_m: float,
    max_offset_m: float,
    source_mask: Optional[np.ndarray] = None,
) -> TransferredPlanes:
    """Target points on source planes moved by the current motion estimate.

    Parameters
    ----------
    source : PlaneSet
        The source epoch's planes (labels index ``source_points``).
    source_points : (N1, 3) float64
        The source epoch's points, metres.
    plane_ids : (P,) int
        The source planes to transfer (those without a match).
    target_points : (N2, 3) float64
        The target epoch's points, metres.
    candidates : (N2,) bool
        Target points that may be gathered (those on no matched plane); each is given to
        one plane at most (the nearest along the normal).
    rotation, translation, centre
        The motion source -> target, ``target = R (source - centre) + centre + t`` (metres).
    band_m : float
        Largest distance of a gathered point to the moved plane, metres.
    edge_margin_m : float
        The source plane's convex hull (in its plane) is shrunk by this much, metres.
    min_points : int
        Fewest gathered points per plane.
    angle_threshold_deg : float
        Largest angle between the moved normal and the gathered points' own plane's.
    max_rms_m : float
        Largest RMS of the gathered points about their own plane, metres.
    max_offset_m : float
        Largest mean distance of the gathered points to the moved plane, metres.
    source_mask : (N1,) bool, optional
        Source points that outline the planes (default all labelled points).

    Returns
    -------
    TransferredPlanes
    """
    from scipy.spatial import cKDTree

    _check_options(band_m, edge_margin_m, min_points, angle_threshold_deg, max_rms_m, max_offset_m)
    plane_ids = np.asarray(plane_ids, dtype=np.int64)
    if plane_ids.size == 0 or not np.any(candidates):
        return empty_transfer(int(plane_ids.size))
    normals, offsets = move_planes(
        source.normals[plane_ids],
        source.offsets[plane_ids],
        rotation=rotation,
        translation=translation,
        centre=centre,
    )
    r = np.asarray(rotation, dtype=np.float64)
    c = np.asarray(centre, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    lab = np.asarray(source.labels)
    if source_mask is not None:
        lab = np.where(source_mask, lab, -1)
    order = np.argsort(lab, kind="stable")
    starts = np.searchsorted(lab[order], plane_ids, side="left")
    ends = np.searchsorted(lab[order], plane_ids, side="right")
    cand = np.flatnonzero(candidates)
    tp = np.asarray(target_points, dtype=np.float64)[cand]
    origin = tp.mean(axis=0)
    tree = cKDTree(tp - origin)

    # per plane: the candidate points in band and in the shrunk hull, with their distance
    owner_pt, owner_pl, owner_r = [], [], []
    for k in range(plane_ids.size):
        sp = np.asarray(source_points)[order[starts[k] : ends[k]]]
        if sp.shape[0] < 3:
            continue
        moved = (sp - c) @ r.T + c + t
        axes = _in_plane_axes(normals[k])
        mc = moved.mean(axis=0)
        xy = (moved - mc) @ axes.T
        hull = _hull_halfplanes(xy)
        if hull is None:
            continue
        radius = float(np.sqrt((xy**2).sum(axis=1).max())) + band_m
        near = np.asarray(tree.query_ball_point(mc - origin, radius), dtype=np.int64)
        if near.size == 0:
            continue
        q = tp[near]
        d = q @ normals[k] + offsets[k]
        inb = np.abs(d) <= band_m
        qxy = (q[inb] - mc) @ axes.T
        inside = np.all(qxy @ hull[:, :2].T + hull[:, 2] <= -edge_margin_m, axis=1)
        sel = near[inb][inside]
        owner_pt.append(sel)
        owner_pl.append(np.full(sel.size, k, dtype=np.int64))
        owner_r.append(d[inb][inside])
    if not owner_pt:
        return empty_transfer(int(plane_ids.size))
    pt = np.concatenate(owner_pt)
    pl = np.concatenate(owner_pl)
    rr = np.concatenate(owner_r)
    # one plane per point: the nearest along the normal (then the lower plane position)
    o = np.lexsort((pl, np.abs(rr), pt))
    first = np.ones(o.size, dtype=bool)
    first[1:] = pt[o][1:] != pt[o][:-1]
    pt, pl, rr = pt[o][first], pl[o][first], rr[o][first]

    keep_pl, keep_pts, keep_n, keep_rms, keep_off = [], [], [], [], []
    for k in np.unique(pl):
        m = pl == k
        ok, rms, off = _accept(
            tp[pt[m]], rr[m], normals[k], angle_threshold_deg, max_rms_m, max_offset_m,
            min_points,
        )  # fmt: skip
        if not ok:
            continue
        keep_pl.append(k)
        keep_pts.append(pt[m])
        keep_n.append(int(m.sum()))
        keep_rms.append(rms)
        keep_off.append(off)
    if not keep_pl:
        return empty_transfer(int(plane_ids.size))
    out = TransferredPlanes(
        source=plane_ids[np.array(keep_pl, dtype=np.int64)],
        point_index=cand[np.concatenate(keep_pts)],
        plane=np.repeat(np.arange(len(keep_pl), dtype=np.int64), keep_n),
        n_points=np.array(keep_n, dtype=np.int64),
        rms_m=np.array(keep_rms),
        offset_m=np.array(keep_off),
        n_tried=int(plane_ids.size),
        n_rejected=int(plane_ids.size) - len(keep_pl),
    )
    return out


def gather_plane_points_reference(
    source: PlaneSet,
    source_points: np.ndarray,
    plane_ids: np.ndarray,
    target_points: np.ndarray,
    candidates: np.ndarray,
    *,
    rotation: np.ndarray,
    translation: np.ndarray,
    centre: np.ndarray,
    band_m: float,
    edge_margin_m: float,
    min_points: int = MIN_POINTS,
    angle_threshold_deg: float = 3.0,
    max_rms_m: float,
    max_offset_m: float,
    source_mask: Optional[np.ndarray] = None,
) -> TransferredPlanes:
    """Slow, obvious reference of :func:`gather_plane_points` (loops over planes and points,
    the moved plane and the hull recomputed from their definitions); tests only."""
    from scipy.spatial import ConvexHull

    _check_options(band_m, edge_margin_m, min_points, angle_threshold_deg, max_rms_m, max_offset_m)
    r = np.asarray(rotation, dtype=np.float64)
    c = np.asarray(centre, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    sp_all = np.asarray(source_points, dtype=np.float64)
    tp_all = np.asarray(target_points, dtype=np.float64)
    lab = np.asarray(source.labels)
    if source_mask is not None:
        lab = np.where(source_mask, lab, -1)
    best = {}  # target point -> (|distance|, plane position, distance)
    for k, pid in enumerate(np.asarray(plane_ids, dtype=np.int64)):
        sp = sp_all[lab == pid]
        if sp.shape[0] < 3:
            continue
        moved = np.array([r @ (p - c) + c + t for p in sp])
        n = r @ source.normals[pid]
        p0 = -source.offsets[pid] * source.normals[pid]  # a point of the source plane
        d0 = -float(n @ (r @ (p0 - c) + c + t))
        axes = _in_plane_axes(n)
        mc = moved.mean(axis=0)
        xy = np.array([[float(a @ (p - mc)) for a in axes] for p in moved])
        try:
            hull = ConvexHull(xy)
        except Exception:  # noqa: BLE001 - degenerate outline: no transfer
            continue
        for i in np.flatnonzero(candidates):
            q = tp_all[i]
            dist = float(n @ q) + d0
            if abs(dist) > band_m:
                continue
            qxy = np.array([float(a @ (q - mc)) for a in axes])
            if all(float(e[:2] @ qxy + e[2]) <= -edge_margin_m for e in hull.equations):
                cur = best.get(int(i))
                if cur is None or (abs(dist), k) < cur[:2]:
                    best[int(i)] = (abs(dist), k, dist)
    pids = np.asarray(plane_ids, dtype=np.int64)
    keep_pl, keep_pts, keep_rms, keep_off = [], [], [], []
    for k in range(pids.size):
        pts = sorted(i for i, v in best.items() if v[1] == k)
        if not pts:
            continue
        rr = np.array([best[i][2] for i in pts])
        n = r @ source.normals[pids[k]]
        ok, rms, off = _accept(
            tp_all[pts], rr, n, angle_threshold_deg, max_rms_m, max_offset_m, min_points
        )
        if ok:
            keep_pl.append(k)
            keep_pts.append(np.array(pts, dtype=np.int64))
            keep_rms.append(rms)
            keep_off.append(off)
    if not keep_pl:
        return empty_transfer(int(pids.size))
    n_points = np.array([p.size for p in keep_pts], dtype=np.int64)
    return TransferredPlanes(
        source=pids[np.array(keep_pl, dtype=np.int64)],
        point_index=np.concatenate(keep_pts),
        plane=np.repeat(np.arange(len(keep_pl), dtype=np.int64), n_points),
        n_points=n_points,
        rms_m=np.array(keep_rms),
        offset_m=np.array(keep_off),
        n_tried=int(pids.size),
        n_rejected=int(pids.size) - len(keep_pl),
    )


def append_planes(
    planes: PlaneSet, points: np.ndarray, point_index: np.ndarray, plane: np.ndarray
) -> PlaneSet:
    """``planes`` with one plane appended per group of ``points[point_index]`` (grouped by
    ``plane``, ``0 .. T-1``): its least-squares parameters, moments and extent, and those
    points' labels set to the new ids ``len(planes) + plane``. Planarity is kept.

    Points must not be on any of ``planes`` (labels -1): the other planes' figures stay true.
    """
    from dataclasses import replace

    from .planes import orient_normals

    pts = np.asarray(points, dtype=np.float64)
    idx = np.asarray(point_index, dtype=np.int64)
    grp = np.asarray(plane, dtype=np.int64)
    t = int(grp.max(initial=-1)) + 1
    if t == 0:
        return planes
    if np.any(np.asarray(planes.labels)[idx] >= 0):
        raise InvalidParameterError("append_planes: points already on a plane")
    cen, cov, n, ext_lo, ext_hi = [], [], [], [], []
    for k in range(t):
        p = pts[idx[grp == k]]
        cen.append(p.mean(axis=0))
        cov.append(np.cov((p - cen[-1]).T, bias=True))
        n.append(p.shape[0])
        ext_lo.append(p.min(axis=0))
        ext_hi.append(p.max(axis=0))
    cen, cov = np.array(cen), np.array(cov)
    w, v = np.linalg.eigh(cov)
    normals = orient_normals(v[:, :, 0])
    labels = np.array(planes.labels, copy=True)
    labels[idx] = (len(planes) + grp).astype(labels.dtype)
    return replace(
        planes,
        normals=np.concatenate([planes.normals, normals]),
        offsets=np.concatenate([planes.offsets, -np.einsum("ij,ij->i", normals, cen)]),
        centroids=np.concatenate([planes.centroids, cen]),
        n_points=np.concatenate([planes.n_points, np.array(n, dtype=np.int64)]),
        rms=np.concatenate([planes.rms, np.sqrt(np.maximum(w[:, 0], 0.0))]),
        covariances=np.concatenate([planes.covariances, cov]),
        extent_min=np.concatenate([planes.extent_min, np.array(ext_lo)]),
        extent_max=np.concatenate([planes.extent_max, np.array(ext_hi)]),
        labels=labels,
    )


@dataclass(frozen=True)
class TransferOutcome:
    """The planes and pairs of a side with transferred planes added.

    Attributes
    ----------
    planes_before, planes_after : PlaneSet
        Each epoch's planes, with the planes fitted to gathered points appended.
    matches : PlaneMatches
        The matched pairs followed by the transferred pairs (``transferred`` 1 or 2).
    gathered_before, gathered_after : (N1,), (N2,) bool
        Points gathered on a plane of the other epoch (they enter the adjustment whatever
        their octree leaf's planarity: the safeguards of :func:`gather_plane_points` stand
        for it).
    """

    planes_before: PlaneSet
    planes_after: PlaneSet
    matches: PlaneMatches
    gathered_before: np.ndarray
    gathered_after: np.ndarray


def transfer_unmatched(
    before: np.ndarray,
    after: np.ndarray,
    planes_before: PlaneSet,
    planes_after: PlaneSet,
    matches,
    *,
    rotation: np.ndarray,
    translation: np.ndarray,
    centre: np.ndarray,
    source_before: Optional[np.ndarray] = None,
    source_after: Optional[np.ndarray] = None,
    angle_threshold_deg: float = 3.0,
    min_points: int = MIN_POINTS,
) -> TransferOutcome:
    """Transfer every unmatched plane of each epoch to the other epoch's free points.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The side's points, metres.
    planes_before, planes_after : PlaneSet
        Their segmentations.
    matches : PlaneMatches
        The matched pairs (no transferred ones).
    rotation, translation, centre
        The current motion estimate before -> after (``after = R (before - centre) + centre
        + t``, metres).
    source_before, source_after : (N1,), (N2,) bool, optional
        Points that outline the source planes (the clean leaves' points); default all.
    angle_threshold_deg : float
        The matching's normal-angle threshold, also the safeguard's.
    min_points : int
        Fewest gathered points of a transferred plane.

    Returns
    -------
    TransferOutcome
        Band, edge margin and safeguards from each target epoch's segmentation: band
        ``BAND_SIGMAS`` noise σ, hull shrunk by the band plus the source's point spacing, RMS
        within ``MAX_RMS_FACTOR`` noise σ, mean offset within one noise σ, at least
        ``min_points`` points. Target points are those on no plane (labels -1).
    """
    pb, pa = planes_before, planes_after
    un_b = np.setdiff1d(np.arange(len(pb)), matches.before)
    un_a = np.setdiff1d(np.arange(len(pa)), matches.after)
    inv = inverse_motion(rotation, translation, centre)

    def settings(src: PlaneSet, tgt: PlaneSet) -> dict:
        noise = float(tgt.parameters.noise_m)
        band = BAND_SIGMAS * noise
        return dict(
            band_m=band,
            edge_margin_m=band + float(src.parameters.point_spacing_m),
            min_points=min_points,
            angle_threshold_deg=angle_threshold_deg,
            max_rms_m=MAX_RMS_FACTOR * noise,
            max_offset_m=noise,
        )

    to_after = gather_plane_points(
        pb, before, un_b, after, np.asarray(pa.labels) < 0,
        rotation=rotation, translation=translation, centre=centre,
        source_mask=source_before, **settings(pb, pa),
    )  # fmt: skip
    to_before = gather_plane_points(
        pa, after, un_a, before, np.asarray(pb.labels) < 0,
        rotation=inv[0], translation=inv[1], centre=inv[2],
        source_mask=source_after, **settings(pa, pb),
    )  # fmt: skip
    pa2 = append_planes(pa, after, to_after.point_index, to_after.plane)
    pb2 = append_planes(pb, before, to_before.point_index, to_before.plane)
    new_a = len(pa) + np.arange(len(to_after), dtype=np.int64)
    new_b = len(pb) + np.arange(len(to_before), dtype=np.int64)
    i = np.concatenate([matches.before, to_after.source, new_b]).astype(np.int64)
    j = np.concatenate([matches.after, new_a, to_before.source]).astype(np.int64)
    cosang = np.abs(np.einsum("ij,ij->i", pb2.normals[i], pa2.normals[j]))
    d12 = np.abs(np.einsum("ij,ij->i", pb2.normals[i], pa2.centroids[j]) + pb2.offsets[i])
    d21 = np.abs(np.einsum("ij,ij->i", pa2.normals[j], pb2.centroids[i]) + pa2.offsets[j])
    kind = np.concatenate(
        [
            matches.kind,
            np.full(len(to_after), TRANSFERRED_TO_AFTER, dtype=np.int8),
            np.full(len(to_before), TRANSFERRED_TO_BEFORE, dtype=np.int8),
        ]
    )
    m2 = PlaneMatches(
        before=i,
        after=j,
        angle_rad=np.arccos(np.clip(cosang, -1.0, 1.0)),
        distance_m=np.maximum(d12, d21),
        transferred=kind,
    )
    gb = np.zeros(len(pb.labels), dtype=bool)
    gb[to_before.point_index] = True
    ga = np.zeros(len(pa.labels), dtype=bool)
    ga[to_after.point_index] = True
    log.debug(
        "transferred planes: %d of %d unmatched first-epoch planes observed by %d second-epoch "
        "points, %d of %d the other way (%d points)",
        len(to_after), un_b.size, to_after.point_index.size,
        len(to_before), un_a.size, to_before.point_index.size,
    )  # fmt: skip
    return TransferOutcome(pb2, pa2, m2, gb, ga)
