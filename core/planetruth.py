"""Known-answer cases for the automatic plane segmentation: scenes with exact planes.

:func:`make_plane_case` builds a point cloud of planar surfaces (a gently tilted ground, box
buildings with flat or gable roofs and vertical facades) at a given density and noise, with
clutter (vegetation blobs and scattered points), and returns every true plane with its label,
area, point count and whether a segmentation can be expected to find it
(:func:`resolvable_surfaces`). :func:`score_case` scores predicted plane labels against it,
counting recall over the resolvable surfaces only. Benchmarks
(``benchmarks/bench_planes_matrix.py``) and tests cross density, noise, scene size and
clutter with these two functions.

Conventions
-----------
- Local frame: the footprint is ``[0, size_m] x [0, size_m]``; every point is then shifted by
  ``origin`` (``points = local + origin``); :attr:`PlaneCase.offsets` refer to the shifted
  points (``normals[s] @ p + offsets[s] == 0`` on surface ``s``).
- A surface is a planar convex polygon (the ground: a polygon with the building footprints as
  holes). Its points are uniform by area, ``round(density * area)`` of them, each moved along
  the surface normal by Gaussian noise of standard deviation ``noise_m``.
- Randomness: the layout (buildings, trees) comes from ``seed`` and ``size_m`` only, the
  sampling from ``seed``; so cases of one seed and size but different densities are the same
  town, and a reduced case (see ``max_points``) is a window cut from it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import numpy as np

from .errors import InvalidParameterError
from .evaluation import score_segmentation

__all__ = [
    "AIRBORNE_MIN_SURFACE_POINTS",
    "GROUND_TILT_DEG",
    "MIN_RESOLVABLE_POINTS",
    "PlaneCase",
    "make_airborne_case",
    "make_plane_case",
    "make_two_walls_case",
    "min_resolvable_extent_m",
    "resolvable_surfaces",
    "score_case",
]

log = logging.getLogger(__name__)

MIN_RESOLVABLE_POINTS = 90  # three leaves of the segmenter's ~30 points
"""Fewest points of a surface for it to count as resolvable (and in recall)."""
RESOLVABLE_LEAVES = 3.0  # a resolvable surface spans at least this many leaves across ...
LEAF_SPACINGS = math.sqrt(30.0)  # ... a leaf being sqrt(30) point spacings (~30 points) ...
LEAF_NOISES = 8.0  # ... and at least 8 noise sigmas wide (the segmenter's automatic leaf)
GROUND_TILT_DEG = 2.0  # slope of the ground plane
GROUND_TILT_AZIMUTH_DEG = 35.0  # direction of steepest ascent, from +x counter-clockwise
CORNER_SCENE_MAX_M = 50.0  # footprints smaller than this get the courtyard-corner scene
BUILDING_SIDE_M = (8.0, 25.0)
EAVE_HEIGHT_M = (4.0, 12.0)
ROOF_PITCH_DEG = (20.0, 40.0)
CROWN_WIDTH_M = (3.0, 10.0)
SCATTER_MARGIN = 0.2  # scattered clutter fills the scene's box grown by this fraction
SCATTER_HEADROOM_M = 5.0  # ... from the ground to this far above the highest roof
MAX_WINDOW_TRIES = 40


@dataclass(frozen=True)
class PlaneCase:
    """A point cloud of known planar surfaces and clutter.

    Attributes
    ----------
    points : (N, 3) float64
        Coordinates, metres, shifted by ``origin``; in random order.
    labels : (N,) int32
        True surface id of each point, -1 for clutter.
    normals : (S, 3) float64
        Unit normals of the true surfaces (``nz > 0``; vertical ones towards +y, then +x).
    offsets : (S,) float64
        Hessian offsets: ``normals[s] @ p + offsets[s] == 0`` on surface ``s`` (shifted frame).
    areas_m2 : (S,) float64
        In-plane area of each surface (inside the footprint or window), square metres.
    n_points : (S,) int64
        Points sampled on each surface.
    min_extent_m : (S,) float64
        Narrowest in-plane width of each surface's outline, metres.
    resolvable : (S,) bool
        Whether a segmentation can be expected to find the surface (:func:`resolvable_surfaces`).
    kinds : tuple of str
        ``"ground"``, ``"roof"`` or ``"wall"`` per surface.
    density_pts_m2, noise_m, size_m, clutter_fraction : float
        The parameters the case was made with (``size_m``: requested footprint edge).
    seed : int
    origin : (3,) float64
        Shift added to the local coordinates.
    footprint_m : (4,) float64
        ``(xmin, ymin, xmax, ymax)`` of the area actually sampled, local frame: the whole
        footprint, or the window of a reduced case.
    subsampled_area : bool
        True when only a square window of the footprint was sampled, to keep the case within
        ``max_points`` at the requested density.
    notes : str
        Human-readable remarks (the window, missing vegetation), empty if none.
    min_resolvable_points : int
        The point-count part of the resolvable rule, :data:`MIN_RESOLVABLE_POINTS`.
    """

    points: np.ndarray
    labels: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    areas_m2: np.ndarray
    n_points: np.ndarray
    min_extent_m: np.ndarray
    resolvable: np.ndarray
    kinds: Tuple[str, ...]
    density_pts_m2: float
    noise_m: float
    size_m: float
    clutter_fraction: float
    seed: int
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    footprint_m: np.ndarray = field(default_factory=lambda: np.zeros(4))
    subsampled_area: bool = False
    notes: str = ""
    min_resolvable_points: int = MIN_RESOLVABLE_POINTS

    @property
    def n_surfaces(self) -> int:
        """Number of true surfaces S."""
        return int(self.normals.shape[0])

    @property
    def n_clutter(self) -> int:
        """Number of clutter points (label -1)."""
        return int(np.count_nonzero(self.labels < 0))

    @property
    def point_spacing_m(self) -> float:
        """Nominal point spacing on the surfaces, ``1 / sqrt(density)``, metres."""
        return 1.0 / math.sqrt(self.density_pts_m2)


# --------------------------------------------------------------------------- resolvable rule


def min_resolvable_extent_m(*, density_pts_m2: float, noise_m: float) -> float:
    """Narrowest in-plane width a surface needs to be resolvable, metres.

    ``3 * max(sqrt(30) * spacing, 8 * noise_m)`` with ``spacing = 1 / sqrt(density_pts_m2)``:
    three of the segmenter's automatic leaves across the surface (the octree's leaves are
    not aligned with it, so two across rarely hold two whole leaves) (a leaf holds about 30 points
    and is at least 8 noise sigmas wide, or its normal is meaningless).
    """
    _check_positive("density_pts_m2", density_pts_m2)
    _check_non_negative("noise_m", noise_m)
    spacing = 1.0 / math.sqrt(density_pts_m2)
    return RESOLVABLE_LEAVES * max(LEAF_SPACINGS * spacing, LEAF_NOISES * noise_m)


def resolvable_surfaces(
    *,
    n_points: np.ndarray,
    min_extent_m: np.ndarray,
    density_pts_m2: float,
    noise_m: float,
    min_points: int = MIN_RESOLVABLE_POINTS,
) -> np.ndarray:
    """Which surfaces a segmentation can be expected to find.

    A surface is resolvable when it has at least ``min_points`` (90: three leaves of about
    30 points, the smallest plane the segmenter reports) **and** its narrowest in-plane width
    is at least ``3 * max(sqrt(30) * spacing, 8 * noise_m)`` with
    ``spacing = 1 / sqrt(density_pts_m2)`` (:func:`min_resolvable_extent_m`): three automatic
    leaves across, each wide compared with the noise. Recall (:func:`score_case`) counts
    resolvable surfaces only.

    Parameters
    ----------
    n_points : (S,) int
        Points per surface.
    min_extent_m : (S,) float
        Narrowest in-plane width of each surface, metres.
    density_pts_m2 : float
        Point density on the surfaces, points per square metre.
    noise_m : float
        Standard deviation of the noise along the normals, metres.
    min_points : int
        Fewest points.

    Returns
    -------
    (S,) bool
    """
    n = np.asarray(n_points)
    ext = np.asarray(min_extent_m, dtype=np.float64)
    if n.shape != ext.shape:
        raise InvalidParameterError(
            f"n_points and min_extent_m must have one shape, got {n.shape} and {ext.shape}"
        )
    need = min_resolvable_extent_m(density_pts_m2=density_pts_m2, noise_m=noise_m)
    # a hair of tolerance so that an extent of exactly the limit is not lost to rounding
    return (n >= min_points) & (ext >= need * (1.0 - 1e-9))


# --------------------------------------------------------------------------- scoring


def score_case(
    case: PlaneCase, labels_pred: np.ndarray, *, min_surface_points: Optional[int] = None
) -> dict:
    """Score predicted plane labels against a :class:`PlaneCase`.

    Uses :func:`slipmap.core.evaluation.score_segmentation`. Recall counts only the resolvable
    surfaces (with ``min_surface_points``: the surfaces of at least that many points, the
    airborne cases' rule, whatever their width); points of surfaces not counted are neither
    recall nor precision errors (a labelled point of any true surface counts as correct for
    precision). A clutter point within 3 noise sigmas of the true plane of the surface its
    predicted plane mostly holds lies on that surface as far as any segmentation can tell: it
    is left out of precision.

    Parameters
    ----------
    case : PlaneCase
    labels_pred : (N,) int
        Predicted plane id per point, -1 for none.

    Returns
    -------
    dict
        ``recall``: share of resolvable surfaces with at least 70 % of their points under one
        label; ``precision``: share of labelled points that belong to a true surface (any);
        ``n_merged``: predicted planes holding at least 20 % of each of two or more true
        surfaces, with 50 or more points there; ``n_planes``: predicted planes;
        ``n_resolvable``, ``n_recovered``, ``n_surfaces``; ``purity`` and
        ``labelled_fraction`` (see :class:`~slipmap.core.evaluation.SegmentationScores`);
        ``missed``: ids of the resolvable surfaces not recovered; ``n_clutter_labelled``:
        clutter points under a plane label (all of them, also those within 3 sigmas of a
        surface), ``n_planes_with_clutter``: predicted planes holding any such point.
    """
    truth = np.asarray(case.labels).astype(np.int64)
    pred = np.asarray(labels_pred).astype(np.int64)
    if pred.shape != truth.shape:
        raise InvalidParameterError(f"labels_pred must have shape {truth.shape}, got {pred.shape}")
    # clutter inside the noise band of the surface its plane stands for: indistinguishable
    lab_clutter = np.flatnonzero((truth < 0) & (pred >= 0))
    n_clutter_labelled = int(lab_clutter.size)
    n_planes_with_clutter = int(np.unique(pred[lab_clutter]).size)
    if lab_clutter.size:
        on = (truth >= 0) & (pred >= 0)
        npred = int(pred.max()) + 1
        tab = np.zeros((npred, case.n_surfaces), dtype=np.int64)
        np.add.at(tab, (pred[on], truth[on]), 1)
        major = np.where(tab.sum(axis=1) > 0, tab.argmax(axis=1), -1)
        srf = major[pred[lab_clutter]]
        has = srf >= 0
        k, sidx = lab_clutter[has], srf[has]
        d = np.abs(np.einsum("ij,ij->i", case.points[k], case.normals[sidx]) + case.offsets[sidx])
        inside = k[d <= 3.0 * case.noise_m]
        pred = pred.copy()
        pred[inside] = -1  # neither a correct nor a wrong label
    full = score_segmentation(truth, pred, min_surface_points=1)
    counted = (
        case.resolvable
        if min_surface_points is None
        else np.asarray(case.n_points) >= int(min_surface_points)
    )
    res_ids = np.flatnonzero(counted)
    remap = np.full(case.n_surfaces + 1, -1, dtype=np.int64)  # index -1 (clutter) -> -1
    remap[res_ids] = np.arange(res_ids.size)
    truth_res = remap[truth]
    rec = score_segmentation(truth_res, pred, min_surface_points=1)
    missed: List[int] = []
    if res_ids.size:
        both = (truth_res >= 0) & (pred >= 0)
        npred = int(pred.max()) + 1 if pred.size and pred.max() >= 0 else 0
        table = np.zeros((res_ids.size, max(npred, 1)), dtype=np.int64)
        np.add.at(table, (truth_res[both], pred[both]), 1)
        sizes = np.bincount(truth_res[truth_res >= 0], minlength=res_ids.size)
        lost = table.max(axis=1) < 0.7 * sizes
        missed = [int(s) for s in res_ids[lost]]
    return {
        "recall": round(rec.recall, 4),
        "precision": round(full.precision, 4),
        "n_merged": full.n_merged,
        "n_planes": full.n_planes,
        "n_resolvable": int(res_ids.size),
        "n_recovered": rec.n_recovered,
        "n_surfaces": case.n_surfaces,
        "purity": round(full.purity, 4),
        "labelled_fraction": round(full.labelled_fraction, 4),
        "missed": missed,
        "n_clutter_labelled": n_clutter_labelled,
        "n_planes_with_clutter": n_planes_with_clutter,
    }


# --------------------------------------------------------------------------- geometry


@dataclass
class _Surface:
    """A planar convex polygon (3-D vertices, in order) with convex holes on its plane."""

    kind: str
    verts: np.ndarray
    holes: List[np.ndarray] = field(default_factory=list)


@dataclass
class _Layout:
    surfaces: List[_Surface]
    trees: np.ndarray  # (T, 5): cx, cy, cz, horizontal semi-axis, vertical semi-axis
    centres: np.ndarray  # (B, 2) building centres, may be empty
    anchors: np.ndarray  # (B, 2) window centre for each building: between it and its tree


def _ground_z(x: np.ndarray, y: np.ndarray, centre: float) -> np.ndarray:
    """Height of the tilted ground at (x, y), zero at the footprint centre."""
    slope = math.tan(math.radians(GROUND_TILT_DEG))
    az = math.radians(GROUND_TILT_AZIMUTH_DEG)
    return slope * ((x - centre) * math.cos(az) + (y - centre) * math.sin(az))


def _with_ground(xy: np.ndarray, centre: float) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([xy, _ground_z(xy[:, 0], xy[:, 1], centre)])


def _frame(verts: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit normal (Newell, right-handed with the vertex order) and in-plane axes u, v."""
    nxt = np.roll(verts, -1, axis=0)
    n = np.cross(verts, nxt).sum(axis=0)
    n /= np.linalg.norm(n)
    u = verts[1] - verts[0]
    u -= (u @ n) * n
    u /= np.linalg.norm(u)
    return n, u, np.cross(n, u)


def _ccw(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    signed = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    return poly if signed >= 0 else poly[::-1]


def _area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


def _min_width(poly: np.ndarray) -> float:
    """Narrowest width of a convex 2-D polygon (one side of the narrowest strip is an edge)."""
    best = math.inf
    for i in range(poly.shape[0]):
        e = poly[(i + 1) % poly.shape[0]] - poly[i]
        length = math.hypot(e[0], e[1])
        if length < 1e-12:
            continue
        d = np.abs(e[0] * (poly[:, 1] - poly[i, 1]) - e[1] * (poly[:, 0] - poly[i, 0])) / length
        best = min(best, float(d.max()))
    return best if math.isfinite(best) else 0.0


def _inside(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(n,) bool: points inside the counter-clockwise convex polygon ``poly`` (edges included)."""
    ok = np.ones(pts.shape[0], dtype=bool)
    for i in range(poly.shape[0]):
        a, b = poly[i], poly[(i + 1) % poly.shape[0]]
        ok &= (b[0] - a[0]) * (pts[:, 1] - a[1]) - (b[1] - a[1]) * (pts[:, 0] - a[0]) >= 0
    return ok


def _clip(verts: np.ndarray, axis: int, value: float, keep_ge: bool) -> np.ndarray:
    """Sutherland-Hodgman: the part of a convex polygon with ``coord[axis] >= value`` (or <=)."""
    s = verts[:, axis] - value
    if not keep_ge:
        s = -s
    out = []
    k = verts.shape[0]
    for i in range(k):
        j = (i + 1) % k
        if s[i] >= 0:
            out.append(verts[i])
        if (s[i] >= 0) != (s[j] >= 0):
            t = s[i] / (s[i] - s[j])
            out.append(verts[i] + t * (verts[j] - verts[i]))
    return np.array(out, dtype=np.float64).reshape(-1, 3)


def _clip_box(verts: np.ndarray, box: Sequence[float]) -> np.ndarray:
    x0, y0, x1, y1 = box
    for axis, value, keep_ge in ((0, x0, True), (0, x1, False), (1, y0, True), (1, y1, False)):
        if verts.shape[0] < 3:
            break
        verts = _clip(verts, axis, value, keep_ge)
    return verts


def _orient(n: np.ndarray) -> np.ndarray:
    """Sign convention of :attr:`PlaneCase.normals`: nz > 0, else ny > 0, else nx > 0."""
    for c in (2, 1, 0):
        if abs(n[c]) > 1e-12:
            return n if n[c] > 0 else -n
    return n


# --------------------------------------------------------------------------- layouts


def _building_surfaces(
    centre_xy: np.ndarray,
    length: float,
    width: float,
    rot: float,
    eave_h: float,
    roof: str,
    pitch: float,
    gc: float,
) -> Tuple[List[_Surface], np.ndarray]:
    """Roof plane(s) and four walls of a box building; and its footprint on the ground."""
    u = np.array([math.cos(rot), math.sin(rot)])
    v = np.array([-math.sin(rot), math.cos(rot)])
    hl, hw = 0.5 * length, 0.5 * width  # length >= width: the ridge runs along u
    c = np.asarray(centre_xy, dtype=np.float64)
    corners = np.array([c - hl * u - hw * v, c + hl * u - hw * v, c + hl * u + hw * v])
    corners = np.vstack([corners, c - hl * u + hw * v])  # counter-clockwise
    z_eave = float(_ground_z(c[0], c[1], gc)) + eave_h
    ground = _with_ground(corners, gc)
    top = np.column_stack([corners, np.full(4, z_eave)])
    out: List[_Surface] = []
    if roof == "gable":
        z_ridge = z_eave + hw * math.tan(pitch)
        r0 = np.append(c - hl * u, z_ridge)
        r1 = np.append(c + hl * u, z_ridge)
        out.append(_Surface("roof", np.array([top[0], top[1], r1, r0])))
        out.append(_Surface("roof", np.array([top[2], top[3], r0, r1])))
    else:
        out.append(_Surface("roof", top.copy()))
    for i in range(4):
        j = (i + 1) % 4
        wall = [ground[i], ground[j], top[j]]
        if roof == "gable" and i in (1, 3):  # the short sides are gable ends
            mid = 0.5 * (corners[i] + corners[j])
            wall.append(np.append(mid, z_eave + hw * math.tan(pitch)))
        wall.append(top[i])
        out.append(_Surface("wall", np.array(wall)))
    return out, ground


def _box_row(centre: np.ndarray, rot: float, length: float, width: float) -> np.ndarray:
    """A building footprint as ``(cx, cy, rotation, half length, half width)``."""
    return np.array([centre[0], centre[1], rot, 0.5 * length, 0.5 * width])


def _distance_to_footprints(xy: np.ndarray, boxes: np.ndarray) -> float:
    """Smallest horizontal distance from a point to the rectangles ``boxes`` (B, 5)."""
    if boxes.size == 0:
        return math.inf
    d = xy[None, :] - boxes[:, :2]
    cu = np.abs(d[:, 0] * np.cos(boxes[:, 2]) + d[:, 1] * np.sin(boxes[:, 2])) - boxes[:, 3]
    cv = np.abs(-d[:, 0] * np.sin(boxes[:, 2]) + d[:, 1] * np.cos(boxes[:, 2])) - boxes[:, 4]
    return float(np.min(np.hypot(np.maximum(cu, 0.0), np.maximum(cv, 0.0))))


def _corner_layout(size: float, rng: np.random.Generator) -> _Layout:
    """Courtyard corner: ground, two perpendicular walls meeting at (size, size), a canopy.

    At ``size = 10``: walls 10 m long and 5 m high (above the ground at the centre) along the
    north and east edges, a lean-to canopy 4 m x 1.8 m sloping 10 degrees at 3 m height on
    the north wall, one tree of 3-4 m crown in the open part of the yard. Everything scales
    with ``size / 10``.
    """
    k = size / 10.0
    gc = 0.5 * size
    ground = _Surface("ground", _with_ground([[0, 0], [size, 0], [size, size], [0, size]], gc))
    z_top = 5.0 * k
    north = _with_ground([[size, size], [0.0, size]], gc)
    wall_n = np.vstack([north, [[0.0, size, z_top], [size, size, z_top]]])
    east = _with_ground([[size, 0.0], [size, size]], gc)
    wall_e = np.vstack([east, [[size, size, z_top], [size, 0.0, z_top]]])
    z0 = 3.0 * k
    depth = 1.8 * k
    z1 = z0 - depth * math.tan(math.radians(10.0))
    x0, x1 = 3.0 * k, 7.0 * k
    canopy = np.array([[x0, size - depth, z1], [x1, size - depth, z1], [x1, size, z0]])
    canopy = np.vstack([canopy, [[x0, size, z0]]])
    surfaces = [
        ground,
        _Surface("wall", wall_n),
        _Surface("wall", wall_e),
        _Surface("roof", canopy),
    ]
    a = 0.5 * rng.uniform(3.0, 4.0) * k
    c = a * rng.uniform(0.6, 1.0)
    cx, cy = rng.uniform(0.25, 0.4, 2) * size
    cz = float(_ground_z(cx, cy, gc)) + 1.5 * k + c
    trees = np.array([[cx, cy, cz, a, c]])
    mid = np.array([[0.5 * size, 0.5 * size]])
    return _Layout(surfaces, trees, mid, mid.copy())


def _town_layout(
    size: float,
    rng: np.random.Generator,
    *,
    eave_m: Tuple[float, float] = EAVE_HEIGHT_M,
    gable_share: float = 0.5,
    per_100m: float = 6.0,
) -> _Layout:
    """Ground with box buildings (8-25 m sides, ``eave_m`` eaves (4-12 m), flat or gable
    roofs, a share ``gable_share`` gable), one tree (3-10 m crown) next to each building.
    About ``per_100m`` (6) buildings per 100 m scene, ~38 per km at the default."""
    gc = 0.5 * size
    n_target = max(1, int(round(per_100m * (size / 100.0) ** 0.8)))
    boxes: List[np.ndarray] = []
    params = []
    for _ in range(n_target):
        for _attempt in range(500):
            length, width = np.sort(rng.uniform(*BUILDING_SIDE_M, 2))[::-1]
            rot = rng.uniform(0.0, 0.5 * math.pi)
            radius = 0.5 * math.hypot(length, width)
            margin = radius + 1.0
            if size <= 2 * margin:
                continue
            centre = rng.uniform(margin, size - margin, 2)
            if boxes and any(
                math.dist(centre, b[:2]) < radius + math.hypot(b[3], b[4]) + 3.0 for b in boxes
            ):
                continue
            eave = rng.uniform(*eave_m)
            roof = "gable" if rng.random() < gable_share else "flat"
            pitch = math.radians(rng.uniform(*ROOF_PITCH_DEG))
            boxes.append(_box_row(centre, rot, length, width))
            params.append((centre, length, width, rot, eave, roof, pitch))
            break
    if len(params) < n_target:
        log.debug("placed %d of %d buildings in a %g m scene", len(params), n_target, size)
    box_arr = np.array(boxes).reshape(-1, 5)
    corners = _with_ground([[0, 0], [size, 0], [size, size], [0, size]], gc)
    ground = _Surface("ground", corners)
    surfaces = [ground]
    for p in params:
        surf, foot = _building_surfaces(*p, gc=gc)
        surfaces.extend(surf)
        ground.holes.append(foot)
    trees = []
    anchors = []
    for centre, length, width, *_ in params:
        anchors.append(np.asarray(centre, dtype=np.float64))
        a = 0.5 * rng.uniform(*CROWN_WIDTH_M)
        c = a * rng.uniform(0.6, 1.0)
        for _attempt in range(50):
            ang = rng.uniform(0.0, 2.0 * math.pi)
            reach = 0.5 * max(length, width) + a + rng.uniform(1.0, 3.0)
            xy = np.asarray(centre) + reach * np.array([math.cos(ang), math.sin(ang)])
            if not (a <= xy[0] <= size - a and a <= xy[1] <= size - a):
                continue
            if _distance_to_footprints(xy, box_arr) < a + 1.0:
                continue
            cz = float(_ground_z(xy[0], xy[1], gc)) + rng.uniform(1.5, 3.0) + c
            trees.append([xy[0], xy[1], cz, a, c])
            anchors[-1] = 0.5 * (anchors[-1] + xy)
            break
    centres = np.array([p[0] for p in params]).reshape(-1, 2)
    return _Layout(
        surfaces, np.array(trees).reshape(-1, 5), centres, np.array(anchors).reshape(-1, 2)
    )


def _layout(size: float, seed: int) -> _Layout:
    rng = np.random.default_rng([seed, 1, int(round(size * 1000))])
    return _corner_layout(size, rng) if size < CORNER_SCENE_MAX_M else _town_layout(size, rng)


# --------------------------------------------------------------------------- sampling


@dataclass
class _Prepared:
    """A surface clipped to the sampled area, in its own 2-D frame."""

    kind: str
    origin: np.ndarray
    normal: np.ndarray
    u: np.ndarray
    v: np.ndarray
    poly: np.ndarray
    holes: List[np.ndarray]
    area: float
    min_extent: float
    zmin: float
    zmax: float


def _prepare(surfaces: Sequence[_Surface], box: Sequence[float]) -> List[_Prepared]:
    out = []
    for s in surfaces:
        verts = _clip_box(s.verts, box)
        if verts.shape[0] < 3:
            continue
        n, u, v = _frame(s.verts)
        o = s.verts[0]
        poly = _ccw(np.column_stack([(verts - o) @ u, (verts - o) @ v]))
        area = _area(poly)
        if area < 1e-6:
            continue
        holes = []
        for h in s.holes:
            hv = _clip_box(h, box)
            if hv.shape[0] < 3:
                continue
            hp = _ccw(np.column_stack([(hv - o) @ u, (hv - o) @ v]))
            area -= _area(hp)  # holes are disjoint and inside the outline
            holes.append(hp)
        if area < 1e-6:
            continue
        out.append(
            _Prepared(
                s.kind,
                o,
                n,
                u,
                v,
                poly,
                holes,
                area,
                _min_width(poly),
                float(verts[:, 2].min()),
                float(verts[:, 2].max()),
            )
        )
    return out


def _sample_polygon(
    rng: np.random.Generator, poly: np.ndarray, holes: Sequence[np.ndarray], area: float, n: int
) -> np.ndarray:
    """``n`` points uniform in a convex polygon minus convex holes, by rejection."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    accept = max(area / max(float(np.prod(hi - lo)), 1e-12), 0.01)
    parts, got = [], 0
    while got < n:
        m = min(int((n - got) / accept * 1.1) + 64, 8_000_000)
        cand = lo + rng.random((m, 2)) * (hi - lo)
        ok = _inside(cand, poly)
        for h in holes:
            hlo, hhi = h.min(axis=0), h.max(axis=0)
            near = np.flatnonzero(ok & np.all((cand >= hlo) & (cand <= hhi), axis=1))
            ok[near[_inside(cand[near], h)]] = False
        cand = cand[ok]
        parts.append(cand)
        got += cand.shape[0]
    return np.concatenate(parts)[:n]


def _sample_crowns(
    rng: np.random.Generator, trees: np.ndarray, box: Sequence[float], n: int
) -> np.ndarray:
    """``n`` points uniform in the union of ellipsoid crowns (weighted by volume), in ``box``."""
    x0, y0, x1, y1 = box
    w = trees[:, 3] ** 2 * trees[:, 4]
    w = w / w.sum()
    parts, got = [], 0
    while got < n:
        m = int((n - got) * 1.5) + 64
        k = rng.choice(trees.shape[0], size=m, p=w)
        d = rng.normal(size=(m, 3))
        d *= (rng.random(m) ** (1.0 / 3.0) / np.linalg.norm(d, axis=1))[:, None]
        t = trees[k]
        p = t[:, :3] + d * t[:, [3, 3, 4]]
        p = p[(p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)]
        parts.append(p)
        got += p.shape[0]
    return np.concatenate(parts)[:n]


def _counts(prepared: Sequence[_Prepared], density: float, wall_factor: float = 1.0) -> np.ndarray:
    """Points per surface: ``density`` per square metre (walls: times ``wall_factor``)."""
    return np.array(
        [int(round(density * (wall_factor if p.kind == "wall" else 1.0) * p.area))
         for p in prepared],
        dtype=np.int64,
    )  # fmt: skip


def _n_clutter(n_surface: int, clutter_fraction: float) -> int:
    return int(round(clutter_fraction / (1.0 - clutter_fraction) * n_surface))


def _window(
    layout: _Layout, size: float, density: float, clutter: float, max_points: int
) -> Tuple[Tuple[float, float, float, float], List[_Prepared], bool]:
    """The sampled area: the footprint, or the largest tried square window whose points fit."""
    full = (0.0, 0.0, size, size)
    prepared = _prepare(layout.surfaces, full)

    def total(prep: Sequence[_Prepared]) -> int:
        ns = int(_counts(prep, density).sum())
        return ns + _n_clutter(ns, clutter)

    n_full = total(prepared)
    if n_full <= max_points:
        return full, prepared, False
    # anchor: between the building nearest the footprint centre and its tree, so that the
    # window holds a building and vegetation, not just ground
    anchor = np.array([0.5 * size, 0.5 * size])
    if layout.centres.size:
        anchor = layout.anchors[np.argmin(np.linalg.norm(layout.centres - anchor, axis=1))]
    side = size * math.sqrt(max_points / n_full) * 0.98
    for _ in range(MAX_WINDOW_TRIES):
        half = 0.5 * min(side, size)
        cx = float(np.clip(anchor[0], half, size - half))
        cy = float(np.clip(anchor[1], half, size - half))
        box = (cx - half, cy - half, cx + half, cy + half)
        prepared = _prepare(layout.surfaces, box)
        n = total(prepared)
        if n <= max_points:
            return box, prepared, True
        side *= 0.98 * math.sqrt(max_points / n)
    raise InvalidParameterError(
        f"could not fit the case in max_points={max_points} (last window {side:.3g} m)"
    )


def _assemble(
    *,
    prepared: Sequence[_Prepared],
    trees: np.ndarray,
    box: Tuple[float, float, float, float],
    density: float,
    noise: float,
    n_veg: int,
    n_scatter: int,
    scatter_box: Optional[np.ndarray],
    origin: np.ndarray,
    rng: np.random.Generator,
    wall_factor: float = 1.0,
) -> Tuple[np.ndarray, ...]:
    """Sample every surface and the clutter; return points, labels and the per-surface truth."""
    counts = _counts(prepared, density, wall_factor)
    blocks, labels = [], []
    normals = np.empty((len(prepared), 3))
    offsets = np.empty(len(prepared))
    for sid, (p, n) in enumerate(zip(prepared, counts)):
        uv = _sample_polygon(rng, p.poly, p.holes, p.area, int(n))
        pts = p.origin + uv[:, :1] * p.u + uv[:, 1:] * p.v
        pts += rng.normal(0.0, noise, (pts.shape[0], 1)) * p.normal if noise > 0 else 0.0
        blocks.append(pts)
        labels.append(np.full(pts.shape[0], sid, dtype=np.int32))
        nrm = _orient(p.normal)
        normals[sid] = nrm
        offsets[sid] = -float(nrm @ p.origin)
    if n_veg:
        blocks.append(_sample_crowns(rng, trees, box, n_veg))
        labels.append(np.full(n_veg, -1, dtype=np.int32))
    if n_scatter:
        lo, hi = scatter_box
        blocks.append(lo + rng.random((n_scatter, 3)) * (hi - lo))
        labels.append(np.full(n_scatter, -1, dtype=np.int32))
    points = np.concatenate(blocks) if blocks else np.empty((0, 3))
    lab = np.concatenate(labels) if labels else np.empty(0, dtype=np.int32)
    perm = rng.permutation(points.shape[0])
    points = points[perm]
    points += origin
    lab = lab[perm]
    offsets -= normals @ origin
    return points, lab, normals, offsets, counts


# --------------------------------------------------------------------------- public makers


def make_plane_case(
    *,
    density_pts_m2: float,
    noise_m: float,
    size_m: float,
    clutter_fraction: float,
    seed: int,
    max_points: int = 4_000_000,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> PlaneCase:
    """A synthetic scene of known planes at a given density, noise, size and clutter.

    Scene (local frame, footprint ``[0, size_m]^2``): a ground plane tilted 2 degrees, plus

    - ``size_m < 50`` (e.g. 10 m): a courtyard corner: two perpendicular walls ``size_m`` long
      and ``size_m / 2`` high meeting at ``(size_m, size_m)``, and a small lean-to canopy roof
      on one wall (4 m x 1.8 m at 10 m);
    - larger: box buildings with 8-25 m sides, 4-12 m eaves and flat or gable (20-40 degree)
      roofs, about 6 in a 100 m scene and a few dozen (38) in 1 km, randomly placed and
      rotated, not overlapping.

    Walls stop at the ground (following its slope) and at the roof; the ground has the building
    footprints as holes. Every surface is sampled uniformly by area at ``density_pts_m2`` with
    Gaussian noise of ``noise_m`` along its normal.

    Clutter: ``clutter_fraction / (1 - clutter_fraction)`` times the surface points, half as
    vegetation (points filling tree-crown ellipsoids 3-10 m wide, 1-3 m from a building) and
    half scattered uniformly in the scene's box (footprint, ground to the highest roof + 5 m)
    grown by 20 % on each axis (10 % on each side). Without a tree in the area, all clutter
    is scattered (noted in ``notes``).

    If the case would exceed ``max_points`` points, only a square window of the footprint is
    sampled (at the same density: never fewer points per square metre), centred as near as
    possible on the midpoint between the building nearest the footprint centre and its tree,
    so the case is a smaller scene cut from the same town; ``subsampled_area`` is then True
    and ``notes`` and ``footprint_m`` describe the window. Surfaces cut by the window keep
    their planes.

    Each surface gets a ``resolvable`` flag (:func:`resolvable_surfaces`): at least
    :data:`MIN_RESOLVABLE_POINTS` (90) points and a narrowest in-plane width of at least
    ``3 * max(sqrt(30) * spacing, 8 * noise_m)``, ``spacing = 1 / sqrt(density_pts_m2)``.

    Parameters
    ----------
    density_pts_m2 : float
        Points per square metre on every surface.
    noise_m : float
        Standard deviation of the noise along the normals, metres (0 for none).
    size_m : float
        Edge of the square footprint, metres (at least 5).
    clutter_fraction : float
        Fraction of all points that are clutter, in [0, 0.95].
    seed : int
        Non-negative seed; the same arguments give the same arrays.
    max_points : int
        Most points in the case.
    origin : (3,) float
        Shift added to all coordinates (e.g. UTM-like ``(500000, 4200000, 100)``).

    Returns
    -------
    PlaneCase

    Raises
    ------
    InvalidParameterError
        A parameter out of range.
    """
    density = _check_positive("density_pts_m2", density_pts_m2)
    noise = _check_non_negative("noise_m", noise_m)
    size = _check_positive("size_m", size_m)
    if size < 5.0:
        raise InvalidParameterError(f"size_m must be at least 5, got {size_m}")
    clutter = _check_non_negative("clutter_fraction", clutter_fraction)
    if clutter > 0.95:
        raise InvalidParameterError(f"clutter_fraction must be at most 0.95, got {clutter}")
    seed = _check_seed(seed)
    if int(max_points) < 1000:
        raise InvalidParameterError(f"max_points must be at least 1000, got {max_points}")
    org = _check_origin(origin)

    layout = _layout(size, seed)
    box, prepared, reduced = _window(layout, size, density, clutter, int(max_points))
    notes = []
    if reduced:
        notes.append(
            f"sub-area {box[2] - box[0]:.1f} m x {box[3] - box[1]:.1f} m at "
            f"({box[0]:.1f}, {box[1]:.1f}) of the {size:g} m footprint, to stay within "
            f"{int(max_points)} points at {density:g} pts/m2"
        )
    n_surface = int(_counts(prepared, density).sum())
    n_clutter = _n_clutter(n_surface, clutter)
    x0, y0, x1, y1 = box
    trees = layout.trees
    if trees.size:
        r = trees[:, 3]
        keep = (
            (trees[:, 0] + r >= x0)
            & (trees[:, 0] - r <= x1)
            & (trees[:, 1] + r >= y0)
            & (trees[:, 1] - r <= y1)
        )
        trees = trees[keep]
    n_veg = n_clutter // 2 if trees.size else 0
    if n_clutter and not trees.size:
        notes.append("no tree in the area: all clutter scattered")
    n_scatter = n_clutter - n_veg
    z_lo = min(p.zmin for p in prepared if p.kind == "ground")
    z_hi = max(p.zmax for p in prepared) + SCATTER_HEADROOM_M
    lo = np.array([x0, y0, z_lo])
    hi = np.array([x1, y1, z_hi])
    grow = 0.5 * SCATTER_MARGIN * (hi - lo)
    rng = np.random.default_rng([seed, 2])
    points, labels, normals, offsets, counts = _assemble(
        prepared=prepared,
        trees=trees,
        box=box,
        density=density,
        noise=noise,
        n_veg=n_veg,
        n_scatter=n_scatter,
        scatter_box=(lo - grow, hi + grow),
        origin=org,
        rng=rng,
    )
    if notes:
        log.info("plane case: %s", "; ".join(notes))
    return _plane_case(
        prepared,
        (points, labels, normals, offsets, counts),
        density_pts_m2=density,
        noise_m=noise,
        size_m=size,
        clutter_fraction=clutter,
        seed=seed,
        origin=org,
        footprint_m=np.array(box, dtype=np.float64),
        subsampled_area=reduced,
        notes="; ".join(notes),
    )


def _plane_case(prepared, assembled, *, density_pts_m2, noise_m, **meta) -> PlaneCase:
    """A :class:`PlaneCase` from the prepared surfaces and :func:`_assemble`'s arrays: areas,
    extents, kinds and the resolvable rule from the surfaces, the rest from ``meta``."""
    points, labels, normals, offsets, counts = assembled
    extents = np.array([p.min_extent for p in prepared])
    return PlaneCase(
        points=points,
        labels=labels,
        normals=normals,
        offsets=offsets,
        areas_m2=np.array([p.area for p in prepared]),
        n_points=counts,
        min_extent_m=extents,
        resolvable=resolvable_surfaces(
            n_points=counts,
            min_extent_m=extents,
            density_pts_m2=density_pts_m2,
            noise_m=noise_m,
        ),
        kinds=tuple(p.kind for p in prepared),
        density_pts_m2=density_pts_m2,
        noise_m=noise_m,
        **meta,
    )


def make_two_walls_case(
    *,
    density_pts_m2: float = 80.0,
    noise_m: float = 0.005,
    n_clutter: int = 500,
    clutter_box: Sequence[Sequence[float]] = ((-20.0, 30.0), (-20.0, 30.0), (-5.0, 20.0)),
    seed: int = 0,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> PlaneCase:
    """Two perpendicular 10 m x 5 m walls meeting at a corner, with scattered clutter.

    The walls are ``y = 0, 0 <= x <= 10`` and ``x = 0, 0 <= y <= 10``, both ``0 <= z <= 5``;
    ``n_clutter`` points are uniform in ``clutter_box`` (``((x0, x1), (y0, y1), (z0, z1))``).
    No ground. ``clutter_fraction`` of the result is the actual share of clutter.
    """
    density = _check_positive("density_pts_m2", density_pts_m2)
    noise = _check_non_negative("noise_m", noise_m)
    seed = _check_seed(seed)
    org = _check_origin(origin)
    if int(n_clutter) < 0:
        raise InvalidParameterError(f"n_clutter must be >= 0, got {n_clutter}")
    cb = np.asarray(clutter_box, dtype=np.float64)
    if cb.shape != (3, 2) or not np.all(cb[:, 1] > cb[:, 0]):
        raise InvalidParameterError(f"clutter_box must be ((x0, x1), (y0, y1), (z0, z1)), got {cb}")
    walls = [
        _Surface("wall", np.array([[0, 0, 0], [10, 0, 0], [10, 0, 5], [0, 0, 5]], float)),
        _Surface("wall", np.array([[0, 10, 0], [0, 0, 0], [0, 0, 5], [0, 10, 5]], float)),
    ]
    box = (-1e9, -1e9, 1e9, 1e9)
    prepared = _prepare(walls, box)
    points, labels, normals, offsets, counts = _assemble(
        prepared=prepared,
        trees=np.empty((0, 5)),
        box=box,
        density=density,
        noise=noise,
        n_veg=0,
        n_scatter=int(n_clutter),
        scatter_box=(cb[:, 0], cb[:, 1]),
        origin=org,
        rng=np.random.default_rng([seed, 3]),
    )
    return _plane_case(
        prepared,
        (points, labels, normals, offsets, counts),
        density_pts_m2=density,
        noise_m=noise,
        size_m=10.0,
        clutter_fraction=float(np.mean(labels < 0)) if labels.size else 0.0,
        seed=seed,
        origin=org,
        footprint_m=np.array([0.0, 0.0, 10.0, 10.0]),
    )


AIRBORNE_EAVE_M = (3.0, 8.0)  # short walls: one- and two-storey buildings
AIRBORNE_GABLE_SHARE = 0.75  # most roofs gable, at any azimuth
AIRBORNE_BUILDINGS_PER_100M = 10.0
AIRBORNE_MIN_SURFACE_POINTS = 200  # recall of the airborne cases: surfaces of >= this many


def make_airborne_case(
    *,
    density_pts_m2: float,
    noise_m: float = 0.05,
    size_m: float = 150.0,
    vegetation_fraction: float = 0.3,
    wall_density_factor: float = 1.0,
    seed: int = 0,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> PlaneCase:
    """A town seen from the air: short walls, gable roofs, trees, at 1-10 pts/m².

    The layout of :func:`make_plane_case`'s town (a ground tilted 2 degrees, box buildings
    with 8-25 m sides at any rotation, one tree of 3-10 m crown beside each), with
    one- and two-storey buildings (eaves 3-8 m: short walls), three in four roofs gable (20-40
    degree pitch, ridges at the buildings' random azimuths) and about 10 buildings per 100 m.
    Roofs and ground are sampled at ``density_pts_m2``, walls at ``wall_density_factor``
    times it (an airborne scanner sees walls obliquely: 1 as dense as the roofs, as in an
    oblique or multi-strip survey; 0.3 a nadir survey's side looks; 0 not at all). Clutter
    is vegetation only: ``vegetation_fraction`` of all points fill the crowns (no scattered
    points; with no tree in the scene, none).

    Recall on these cases is counted over the surfaces of at least
    :data:`AIRBORNE_MIN_SURFACE_POINTS` (200) points (``score_case(...,
    min_surface_points=200)``); ``resolvable`` keeps the general rule.

    Parameters
    ----------
    density_pts_m2 : float
        Points per square metre on roofs and ground.
    noise_m : float
        Standard deviation of the noise along the normals, metres.
    size_m : float
        Edge of the square footprint, metres (at least 50).
    vegetation_fraction : float
        Share of all points in the tree crowns, in [0, 0.9].
    wall_density_factor : float
        Wall density relative to ``density_pts_m2``, in [0, 1].
    seed : int
    origin : (3,) float

    Returns
    -------
    PlaneCase
        ``clutter_fraction`` is the vegetation share actually sampled.
    """
    density = _check_positive("density_pts_m2", density_pts_m2)
    noise = _check_non_negative("noise_m", noise_m)
    size = _check_positive("size_m", size_m)
    if size < CORNER_SCENE_MAX_M:
        raise InvalidParameterError(f"size_m must be at least {CORNER_SCENE_MAX_M:g}, got {size_m}")
    veg = _check_non_negative("vegetation_fraction", vegetation_fraction)
    if veg > 0.9:
        raise InvalidParameterError(f"vegetation_fraction must be at most 0.9, got {veg}")
    wall = _check_non_negative("wall_density_factor", wall_density_factor)
    if wall > 1.0:
        raise InvalidParameterError(f"wall_density_factor must be at most 1, got {wall}")
    seed = _check_seed(seed)
    org = _check_origin(origin)
    rng = np.random.default_rng([seed, 4, int(round(size * 1000))])
    layout = _town_layout(
        size,
        rng,
        eave_m=AIRBORNE_EAVE_M,
        gable_share=AIRBORNE_GABLE_SHARE,
        per_100m=AIRBORNE_BUILDINGS_PER_100M,
    )
    box = (0.0, 0.0, size, size)
    prepared = [p for p in _prepare(layout.surfaces, box) if wall > 0 or p.kind != "wall"]
    n_surface = int(_counts(prepared, density, wall).sum())
    n_veg = _n_clutter(n_surface, veg) if layout.trees.size else 0
    points, labels, normals, offsets, counts = _assemble(
        prepared=prepared,
        trees=layout.trees,
        box=box,
        density=density,
        noise=noise,
        n_veg=n_veg,
        n_scatter=0,
        scatter_box=None,
        origin=org,
        rng=np.random.default_rng([seed, 5]),
        wall_factor=wall,
    )
    return _plane_case(
        prepared,
        (points, labels, normals, offsets, counts),
        density_pts_m2=density,
        noise_m=noise,
        size_m=size,
        clutter_fraction=float(np.mean(labels < 0)) if labels.size else 0.0,
        seed=seed,
        origin=org,
        footprint_m=np.array(box, dtype=np.float64),
        notes=f"airborne: eaves 3-8 m, walls at {wall:g} x the density",
    )


# --------------------------------------------------------------------------- checks


def _check_positive(name: str, value: float) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise InvalidParameterError(f"{name} must be a positive number, got {value!r}")
    return v


def _check_non_negative(name: str, value: float) -> float:
    v = float(value)
    if not (math.isfinite(v) and v >= 0):
        raise InvalidParameterError(f"{name} must be a non-negative number, got {value!r}")
    return v


def _check_seed(seed: int) -> int:
    if isinstance(seed, bool) or int(seed) != seed or int(seed) < 0:
        raise InvalidParameterError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def _check_origin(origin: Sequence[float]) -> np.ndarray:
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise InvalidParameterError(f"origin must be 3 finite numbers, got {origin!r}")
    return o
