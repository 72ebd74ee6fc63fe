"""Roughness, planes and slip on tiled inputs, tile by tile, in process or on Dask workers.

Each job reads its epochs as :class:`~slipmap.core.io.tiles.TileCollection` s and cuts the
survey into square processing tiles (a regular grid aligned to multiples of the tile size,
independent of how the files are cut). A task reads one tile (plus a halo) by streaming the
files that overlap it, computes, and returns a small result; the driver folds the results in
the tiles' order (:mod:`.engine`). No point cloud travels to the driver.

* Roughness (:func:`roughness_tiled`): exact. Cells come from the global grid (the same origin
  and cell index as :func:`~slipmap.core.roughness.grid_roughness` on the whole cloud); a cell
  belongs to the tile that holds its lower corner, and a halo of one cell brings all of its
  points into that tile. The cells are the whole-cloud kernel's (``_process_cells``), so the
  values equal the in-memory result up to the order of summation (1e-12 relative).
* Slip (:func:`slip_tiled`): the study's tiles (Kusari et al. 2019, section IV; planes never
  span two tiles), i.e. :func:`~slipmap.core.displacement.estimate_slip` with
  ``tile_size_m``. A task segments and matches the planes of its tile on each side of the
  trace and returns, per matched plane and epoch, the point count, centroid, scatter and
  points per acquisition unit (:class:`~slipmap.core.planemoments.PlaneMoments`): every block
  of the adjustment's normal equations is a sum over points of these
  (:func:`~slipmap.core.planemoments.adjust_rigid_moments`). What travels per matched plane:
  4 + 3 + 9 numbers and one count per unit, plus the planes' parameters for the report.
  Per-point residuals are not formed (the result's ``residuals_*`` are empty).
* Planes (:func:`planes_tiled`): each tile is segmented with a halo around it and the
  parameters estimated once, on a pilot tile; a plane keeps the moments of the points its tile
  owns; planes of neighbouring tiles that one plane fits (normals within the angle threshold,
  each centroid within the distance threshold of the other plane, and the merged moments' RMS
  within half the planarity threshold) are merged.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..core.errors import InputDataError, InvalidParameterError, SlipMapFileError
from ..core.io.tiles import Region, TileCollection, region_grid
from ..core.planemoments import PlaneMoments
from ..core.progress import ProgressCallback, report, scaled
from .engine import Engine, InProcess

log = logging.getLogger("slipmap.app")

__all__ = [
    "DEFAULT_TILE_SIZE_M",
    "Selection",
    "TiledPlanes",
    "planes_tiled",
    "principal_frame_tiled",
    "roughness_tiled",
    "slip_tiled",
]

#: default processing tile edge (metres): the study's MLS tiles were 20-100 m
DEFAULT_TILE_SIZE_M = 100.0
_CHUNK = 1 << 20


@dataclass(frozen=True)
class Selection:
    """Class selection of a tiled run (as :func:`.inputs.select_points`, tile by tile)."""

    classes: Optional[Tuple[int, ...]] = None
    exclude_classes: Optional[Tuple[int, ...]] = None
    ground_default: bool = False

    @property
    def needs_classes(self) -> bool:
        return bool(self.classes) or self.exclude_classes is not None or self.ground_default

    def indices(self, cloud) -> np.ndarray:
        """Indices of the kept points of a tile (no error when none is left)."""
        n = len(cloud)
        cls = cloud.attributes.get("Classification")
        if cls is None or not self.needs_classes:
            return np.arange(n)
        cls = np.asarray(cls)
        keep = np.ones(n, dtype=bool)
        if self.classes:
            keep &= np.isin(cls, np.asarray(self.classes))
        if self.exclude_classes is not None:
            if len(self.exclude_classes):
                keep &= ~np.isin(cls, np.asarray(self.exclude_classes))
        elif self.ground_default and not self.classes:
            keep &= cls != 2  # the whole-cloud rule drops class 2 when present: same result
        return np.flatnonzero(keep)


def _owned(xy: np.ndarray, region: Region, t: float) -> np.ndarray:
    """Mask of the points whose tile (``floor(xy / t)``) is ``region``'s (exact ownership)."""
    return (np.floor(xy[:, 0] / t) == region.ix) & (np.floor(xy[:, 1] / t) == region.iy)


def _engine(engine: Optional[Engine]) -> Engine:
    return engine if engine is not None else InProcess()


def _check_tile(tile_size_m) -> float:
    t = float(tile_size_m)
    if not (math.isfinite(t) and t > 0):
        raise InvalidParameterError(f"tile_size_m must be a positive number, got {tile_size_m!r}")
    return t


def _reference(*colls: TileCollection) -> np.ndarray:
    """A reference point for moments: the lower corner of the data, floored to the metre."""
    lo = np.min([c.bounds[0] for c in colls], axis=0)
    return np.floor(lo)


def _bounds_of(*colls: TileCollection) -> Tuple[np.ndarray, np.ndarray]:
    return (
        np.min([c.bounds[0] for c in colls], axis=0),
        np.max([c.bounds[1] for c in colls], axis=0),
    )


# --------------------------------------------------------------------------- guards


def _fmt_box(lo, hi) -> str:
    return f"x {lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f}"


def outlying_tiles(coll: TileCollection) -> np.ndarray:
    """Indices (into ``coll.files``) of the non-empty tiles whose header box lies far from
    all the others or spans far more than they do (:func:`~.resources.outlying_boxes`)."""
    from .resources import outlying_boxes

    lo, hi, full = coll._boxes()
    idx = np.flatnonzero(full)
    return idx[outlying_boxes(lo[idx], hi[idx])]


def refuse_outlying_tiles(
    inputs: Sequence[Tuple[str, TileCollection]], why: str, *, also: Sequence[str] = ()
) -> None:
    """Refuse, naming the input option, a collection holding a tile whose header box lies far
    from all the others or spans far more than they do (a stray point); ``why``: what it
    would cost. Nothing happens when no tile stands out.

    Raises
    ------
    OptionError
        The input's key; the outlying tile's file, its header box and the others' extent.
    """
    from .options import OptionError

    for key, coll in inputs:
        odd = outlying_tiles(coll)
        if not odd.size:
            continue
        lo, hi, full = coll._boxes()
        rest = np.setdiff1d(np.flatnonzero(full), odd)
        i = odd[0]
        others = _fmt_box(lo[rest].min(axis=0), hi[rest].max(axis=0))
        more = f" (and {odd.size - 1} more)" if odd.size > 1 else ""
        raise OptionError(
            key,
            f"{coll.label + ': ' if coll.label and coll.label != key else ''}tile "
            f"{coll.files[i].path.name}{more} has its header box at "
            f"{_fmt_box(lo[i], hi[i])}, far from or far larger than the other tiles "
            f"({others}): a stray point? {why}; remove it from the file (e.g. PDAL "
            "filters.crop or filters.outlier) or leave the file out",
            also=also,
        )


def check_tiles(
    inputs: Sequence[Tuple[str, TileCollection]],
    tile_size_m: float,
    *,
    key: str = "tile_size_m",
    min_tile_m: Optional[float] = None,
    min_why: str = "",
    grow_low_m: float = 0.0,
) -> float:
    """The guards of a tiled run, from the tiles' headers before any point is read: the
    processing tile is at least ``min_tile_m`` (``min_why`` names what needs it) and cuts the
    inputs into at most :data:`~.resources.MAX_TILES` tiles; when a stray tile (see
    :func:`refuse_outlying_tiles`) makes the count, that tile is named instead.

    ``inputs``: (option key, collection) pairs; ``grow_low_m``: the tiles' boxes grown
    towards low x, y by this (roughness: a cell's lower corner may lie before its points).
    Returns the tile size. Raises OptionError naming ``key`` (or the input's key).
    """
    from .options import OptionError
    from .resources import MAX_TILES, _nice_up, box_counts, check_tile_budget

    t = _check_tile(tile_size_m)
    if min_tile_m is not None and t < min_tile_m:
        raise OptionError(
            key,
            f"= {t:g} m is smaller than {min_why} ({min_tile_m:g} m); choose "
            f"{_nice_up(min_tile_m):g} m or more",
        )
    boxes, kept = [], []
    for _, coll in inputs:
        lo, hi, full = coll._boxes()
        boxes.append((lo[full] - grow_low_m, hi[full]))
        rest = np.setdiff1d(np.flatnonzero(full), outlying_tiles(coll))
        kept.append((lo[rest] - grow_low_m, hi[rest]))

    def count(s: float, boxes=boxes) -> float:  # the tiles the boxes meet (busiest input's)
        return max((float(box_counts(lo, hi, s).sum()) for lo, hi in boxes), default=0.0)

    n = count(t)
    if n > MAX_TILES:
        if count(t, kept) <= MAX_TILES:  # one stray tile makes it: name that tile
            refuse_outlying_tiles(
                inputs, f"{{{key}}} = {t:g} m would cut the data into {n:.3g} tiles", also=(key,)
            )
        check_tile_budget(key, count, t, what="tiles")
    return t


# --------------------------------------------------------------------------- roughness


@dataclass(frozen=True)
class _RoughTask:
    coll: TileCollection
    region: Region
    tile_size_m: float
    sizes: Tuple[float, ...]
    origins: Tuple[Tuple[float, float, float], ...]
    shapes: Tuple[Tuple[int, int, int], ...]
    min_points: int
    axis: int
    signed: bool
    selection: Selection


def _read_selected(coll: TileCollection, region: Region, halo_m: float, selection: Selection,
                   extra: Sequence[str] = ()):  # fmt: skip
    attrs = (("Classification",) if selection.needs_classes else ()) + tuple(extra)
    cloud = coll.read_region(region, halo_m=halo_m, attributes=attrs)
    sel = selection.indices(cloud)
    return cloud, sel


def _roughness_tile(task: _RoughTask):
    """Cells owned by one tile, for every cell size: the kernel's accumulator arrays."""
    from ..core import roughness as rough

    r = task.region
    halo = 1.01 * max(task.sizes) + 1e-6 * task.tile_size_m
    cloud, sel = _read_selected(task.coll, r, halo, task.selection)
    pts = cloud.xyz[sel] if sel.size < len(cloud) else cloud.xyz
    out = []
    t = task.tile_size_m
    for c, origin, shape in zip(task.sizes, task.origins, task.shapes):
        origin = np.asarray(origin)
        acc = rough._Accumulator()
        ijk = rough._cell_index(pts, origin, c) if pts.shape[0] else np.zeros((0, 3), np.int64)
        corner_x = origin[0] + ijk[:, 0] * c
        corner_y = origin[1] + ijk[:, 1] * c
        own = (np.floor(corner_x / t) == r.ix) & (np.floor(corner_y / t) == r.iy)
        idx = np.flatnonzero(own)
        ok = np.all((ijk[idx] >= 0) & (ijk[idx] < np.asarray(shape)), axis=1)
        if not np.all(ok):
            raise SlipMapFileError(
                f"{r.name}: points lie outside the tiles' header bounds (a stale header?); "
                "rewrite the tiles' headers (e.g. with pdal translate) and run again"
            )
        keys = rough._pack_index(ijk[idx], shape)
        order = np.argsort(keys, kind="stable")
        idx, keys = idx[order], keys[order]
        n = idx.size
        s = 0
        while s < n:
            e = min(n, s + _CHUNK)
            if e < n:  # whole cells per chunk
                e = int(np.searchsorted(keys, keys[e - 1], side="right"))
            rough._process_cells(
                pts, idx[s:e], keys[s:e], origin=origin, c=c, shape=shape,
                min_points=task.min_points, a=task.axis, signed=task.signed, acc=acc,
            )  # fmt: skip
            s = e
        parts = {
            "keys": acc.cat("keys", (0,), np.int64),
            "n": acc.cat("n", (0,), np.int64),
            "centroid": acc.cat("centroid", (0, 3)),
            "normal": acc.cat("normal", (0, 3)),
            "eig": acc.cat("eig", (0, 3)),
            "odr": acc.cat("odr", (0,)),
            "ols": acc.cat("ols", (0,)),
            "degenerate": acc.cat("degenerate", (0,), bool),
        }
        out.append((parts, acc.n_cells_skipped, acc.n_points_skipped, int(n)))
    return out


@dataclass(frozen=True)
class _FrameTask:
    coll: TileCollection
    region: Region
    tile_size_m: float
    ref: Tuple[float, float, float]
    selection: Selection


def _frame_tile(task: _FrameTask):
    """(n, sum(x - ref), sum (x - ref)(x - ref)^T) of a tile's owned, selected points."""
    cloud, sel = _read_selected(task.coll, task.region, 1e-6 * task.tile_size_m, task.selection)
    pts = cloud.xyz[sel]
    pts = pts[_owned(pts, task.region, task.tile_size_m)]
    q = pts - np.asarray(task.ref)
    return pts.shape[0], q.sum(axis=0), q.T @ q


def principal_frame_tiled(
    coll: TileCollection,
    *,
    selection: Selection = Selection(),
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    engine: Optional[Engine] = None,
    progress: Optional[ProgressCallback] = None,
):
    """:func:`~slipmap.core.roughness.principal_frame` of a tiled cloud (one pass of sums)."""
    from ..core import roughness as rough

    eng = _engine(engine)
    t = check_tiles([("input", coll)], tile_size_m)
    lo, hi = coll.bounds
    regions = region_grid((lo, hi), t, collections=[coll])
    ref = tuple(0.5 * (lo + hi))
    tasks = [_FrameTask(coll.restricted(r, 1e-3 * t), r, t, ref, selection) for r in regions]
    parts = eng.map(_frame_tile, tasks, names=[r.name for r in regions], progress=progress)
    n = sum(p[0] for p in parts)
    if n == 0:
        raise InputDataError("no point is left by the class selection; choose other classes")
    s1 = np.sum([p[1] for p in parts], axis=0)
    s2 = np.sum([p[2] for p in parts], axis=0)
    mean = s1 / n
    cov = s2 / n - np.outer(mean, mean)
    evals, evecs = np.linalg.eigh(cov)
    return rough.PrincipalFrame(
        centroid_m=np.asarray(ref) + mean,
        axes=rough._orient_largest(evecs[:, ::-1].T.copy()),
        eigenvalues_m2=evals[::-1].copy(),
    )


def check_roughness_tiles(
    coll: TileCollection, tile_size_m: float, cell_sizes_m: Sequence[float], key: str = "input"
) -> float:
    """:func:`check_tiles` for roughness: a tile at least the largest cell, the files' boxes
    grown one cell lower (a cell belongs to the tile of its lower corner)."""
    grow = max(float(c) for c in cell_sizes_m)
    return check_tiles(
        [(key, coll)], tile_size_m, min_tile_m=grow, min_why="the largest cell",
        grow_low_m=grow,
    )  # fmt: skip


def roughness_tiled(
    coll: TileCollection,
    *,
    cell_sizes_m: Sequence[float],
    min_points: int = 10,
    ols_axis="z",
    signed: bool = False,
    selection: Selection = Selection(),
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    engine: Optional[Engine] = None,
    progress: Optional[ProgressCallback] = None,
):
    """:func:`~slipmap.core.roughness.grid_roughness_multi` of a tiled cloud, tile by tile.

    Parameters
    ----------
    coll : TileCollection
    cell_sizes_m, min_points, ols_axis, signed
        As ``grid_roughness_multi`` (``ols_axis="auto"`` takes one extra pass for the
        cloud's principal frame).
    selection : Selection
        Class selection, applied per tile.
    tile_size_m : float
        Processing tile edge (metres); memory per task is about a tile plus a one-cell halo.
    engine : Engine, optional
        In-process by default.

    Returns
    -------
    tuple of RoughnessGrid
        One per cell size, cells sorted by key, as the whole-cloud function gives them (the
        grid's origin from the tiles' header bounds, which laspy and PDAL write exactly).
    """
    from ..core import roughness as rough

    eng = _engine(engine)
    sizes = tuple(rough._check_cell_size(c) for c in cell_sizes_m)
    if not sizes:
        raise InvalidParameterError("cell_sizes_m: give at least one cell size")
    mp = rough._check_min_points(min_points)
    if coll.n_points == 0:
        raise InputDataError(f"{coll.label or 'input'}: the tiles hold no point")
    # a cell belongs to the tile of its lower corner: that tile may hold none of its points
    # (before the data's lower edge or in a gap between files), so the files' boxes reach
    # one cell lower when the tiles are chosen; a tile smaller than a cell would read each
    # cell's points from many tiles' halos
    grow = max(sizes)
    t = check_roughness_tiles(coll, tile_size_m, sizes)
    lo, hi = coll.bounds
    geos = [rough._grid_geometry(lo, hi, c, None) for c in sizes]
    regions = region_grid((lo, hi), t, collections=[coll], grow_low_m=grow)
    names = [r.name for r in regions]
    sub = progress
    if isinstance(ols_axis, str) and ols_axis.lower() == "auto":
        frame = principal_frame_tiled(
            coll, selection=selection, tile_size_m=t, engine=eng,
            progress=scaled(progress, 0, 0.3),
        )  # fmt: skip
        ols_axis = rough.resolve_ols_axis(frame, "auto")
        sub = scaled(progress, 0.3, 1.0)
    a = rough._axis_index(ols_axis)
    task = _RoughTask(
        coll, regions[0] if regions else None, t, sizes,
        tuple(tuple(float(v) for v in g[0]) for g in geos), tuple(g[1] for g in geos),
        mp, a, bool(signed), selection,
    )  # fmt: skip
    halo = 1.02 * max(sizes) + 1e-3 * t
    tasks = [replace(task, region=r, coll=coll.restricted(r, halo)) for r in regions]
    results = eng.map(_roughness_tile, tasks, names=names, progress=sub)
    grids = []
    for k, (c, (origin, shape)) in enumerate(zip(sizes, geos)):
        acc = rough._Accumulator()
        cat = {key: [] for key in ("keys", "n", "centroid", "normal", "eig", "odr", "ols",
                                  "degenerate")}  # fmt: skip
        n_total = 0
        for res in results:
            parts, skc, skp, n_own = res[k]
            for key in cat:
                cat[key].append(parts[key])
            acc.n_cells_skipped += skc
            acc.n_points_skipped += skp
            n_total += n_own
        if n_total == 0:
            raise InputDataError("no point is left by the class selection; choose other classes")
        arrays = {key: np.concatenate(v) for key, v in cat.items()}
        order = np.argsort(arrays["keys"], kind="stable")
        acc.add(**{key: v[order] for key, v in arrays.items()})
        grids.append(
            rough._finish(
                acc,
                c=c,
                origin=origin,
                shape=shape,
                n_total=n_total,
                min_points=mp,
                a=a,
                signed=bool(signed),
            )  # fmt: skip
        )
    return tuple(grids)


# --------------------------------------------------------------------------- slip


@dataclass(frozen=True)
class _SlipTask:
    before: TileCollection
    after: TileCollection
    region: Region
    tile_size_m: float
    trace: Any
    buffer_m: float
    plane_options: Dict[str, Any]
    match_options: Dict[str, Any]
    selection: Selection
    units: bool
    origin: Tuple[float, float, float]


def _light(ps):
    """A PlaneSet without its per-point arrays (what the report needs of a tile's planes)."""
    return replace(
        ps, labels=np.zeros(0, np.int32), planarity=np.zeros(0, np.float32), timings_s={}
    )


def _slip_tile(task: _SlipTask):
    """Planes, matches and per-plane moments of one tile, on each side of the trace."""
    from ..core.displacement import CLEAN_LEAF_RATIO, SIDES, _labels_for_matches
    from ..core.fault import fault_geometry, side_masks
    from ..core.matching import match_planes
    from ..core.planes import segment_planes

    r, t = task.region, task.tile_size_m
    extra = ("PointSourceId",) if task.units else ()
    epochs = []
    for coll in (task.before, task.after):
        cloud, sel = _read_selected(coll, r, 1e-6 * t, task.selection, extra)
        pts = cloud.xyz[sel]
        own = _owned(pts, r, t)
        pts = pts[own]
        unit = None
        if task.units:
            psid = np.asarray(cloud.attributes["PointSourceId"])[sel][own]
            unit = psid.astype(np.int64)
        if pts.shape[0]:
            g = fault_geometry(pts[:, :2], task.trace)
            left, right = side_masks(g, buffer_m=task.buffer_m)
        else:
            left = right = np.zeros(0, bool)
        epochs.append((pts, unit, {"left": left, "right": right}))
    out = {"codes": [np.unique(e[1]) if e[1] is not None else None for e in epochs]}
    for side in SIDES:
        (pb_pts, ub, mb), (pa_pts, ua, ma) = epochs[0], epochs[1]
        b_pts, a_pts = pb_pts[mb[side]], pa_pts[ma[side]]
        if b_pts.shape[0] == 0 and a_pts.shape[0] == 0:
            continue
        ubs = ub[mb[side]] if ub is not None else None
        uas = ua[ma[side]] if ua is not None else None
        entry = {"status": "ok", "k": 0}
        try:
            if b_pts.shape[0] < 3 or a_pts.shape[0] < 3:
                raise InputDataError(
                    f"{b_pts.shape[0]} / {a_pts.shape[0]} points in the two epochs"
                )
            pb = segment_planes(b_pts, quiet=True, **task.plane_options)
            pa = segment_planes(a_pts, quiet=True, **task.plane_options)
        except InputDataError as exc:
            entry["status"] = f"skipped: no planes ({exc})"
            out[side] = entry
            continue
        m = match_planes(pb, pa, quiet=True, **task.match_options)
        k = len(m)
        lb = _labels_for_matches(pb.labels, m.before)
        la = _labels_for_matches(pa.labels, m.after)
        lb = np.where(pb.planarity >= CLEAN_LEAF_RATIO, lb, -1)
        la = np.where(pa.planarity >= CLEAN_LEAF_RATIO, la, -1)
        entry.update(
            k=k,
            planes_before=_light(pb),
            planes_after=_light(pa),
            matches=m,
            before=PlaneMoments.from_points(b_pts, lb, k, origin_m=task.origin, units=ubs),
            after=PlaneMoments.from_points(a_pts, la, k, origin_m=task.origin, units=uas),
        )
        out[side] = entry
    return out


def _mean_after_misclosure(rigid, after: PlaneMoments) -> np.ndarray:
    """Mean after-epoch misclosure per plane (as ``_adjust_labelled``'s), from moments."""
    from scipy.spatial.transform import Rotation

    b = rigid.plane_params.shape[0]
    rot = Rotation.from_rotvec(rigid.params[:3]).as_matrix()
    q = after.origin_m + after.mean_m[:b]  # mean after point per plane
    p = (q - rigid.centre - rigid.params[3:]) @ rot + rigid.centre  # R^T (q - c - t) + c
    with np.errstate(invalid="ignore"):
        f = np.einsum("ij,ij->i", rigid.plane_params[:, :3], p) + rigid.plane_params[:, 3]
    out = np.full(len(after), np.nan)
    has = after.count[:b] > 0
    out[:b][has] = f[has]
    return out


def _check_trace(before: TileCollection, after: TileCollection, trace, t: float):
    """The processing tiles of two epochs, after checking that the trace crosses them (on the
    tiles' centres and the overlap's corners: no point is read). Raises InputDataError."""
    from ..core.fault import trace_in_data_check

    (lo_b, hi_b), (lo_a, hi_a) = before.bounds, after.bounds
    lo, hi = np.maximum(lo_b, lo_a), np.minimum(hi_b, hi_a)
    regions = region_grid(_bounds_of(before, after), t, collections=[before, after])
    if np.any(lo[:2] >= hi[:2]):
        return regions  # slip_tiled says the epochs do not overlap
    centres = np.array([[0.5 * (r.xmin + r.xmax), 0.5 * (r.ymin + r.ymax)] for r in regions])
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [lo[0], hi[1]], [hi[0], hi[1]]])
    # tile centres and corners, not points: the "N points on each side" line would mislead
    trace_in_data_check(trace, np.concatenate([centres, corners]), buffer_m=0.0, quiet=True)
    return regions


def slip_tiled(
    before: TileCollection,
    after: TileCollection,
    trace,
    *,
    tile_size_m: float,
    buffer_m: float = 10.0,
    sigma_before=0.05,
    sigma_after=0.05,
    plane_options: Optional[dict] = None,
    match_options: Optional[dict] = None,
    combine: str = "joint",
    stochastic_model: str = "full",
    units: str = "auto",
    components: Optional[dict] = None,
    random_tilt: Optional[bool] = None,
    selection: Selection = Selection(),
    engine: Optional[Engine] = None,
    progress: Optional[ProgressCallback] = None,
):
    """:func:`~slipmap.core.displacement.estimate_slip` with ``tile_size_m``, tile by tile.

    Parameters
    ----------
    before, after : TileCollection
        The epochs, in the same CRS (metres).
    trace : FaultTrace
        In that CRS.
    tile_size_m : float
        The study's tile (planes never span two tiles), also the processing tile.
    sigma_before, sigma_after : float or (3,)
        Point sigma, metres (per-point sigmas need the points in one place).
    units : {"auto", "PointSourceId", "none"}
        Acquisition units of the "full" model: "auto" = PointSourceId when an epoch's
        selected points have more than one value (as the whole-cloud job). Units from GPS
        time gaps need the whole epoch sorted by time and are not available tiled.
    Other parameters
        As ``estimate_slip``; ``selection`` is the class selection.

    Returns
    -------
    SlipResult
        As ``estimate_slip(..., tile_size_m=...)`` (the same numbers to 1e-9 relative), with
        the sides' PlaneSets holding no per-point labels and the adjustments no per-point
        residuals.
    """
    from ..core.displacement import (
        COMBINE_MODES,
        SIDES,
        SideResult,
        SlipResult,
        _merge_planesets,
        relative_covariance,
        side_summary,
        tile_adjustments,
    )
    from ..core.fault import mean_strike_rad
    from ..core.matching import PlaneMatches
    from ..core.planemoments import adjust_rigid_moments
    from ..core.stochastic import check_components, check_random_tilt, check_stochastic_model

    if combine not in COMBINE_MODES:
        raise InvalidParameterError(f"combine must be one of {COMBINE_MODES}, got {combine!r}")
    if units not in ("auto", "PointSourceId", "none"):
        raise InvalidParameterError(
            "units: with tiled inputs the acquisition units come from PointSourceId (auto, "
            "point-source-id) or none; GPS-time gaps need the whole epoch in one place"
        )
    for name, s in (("sigma_before", sigma_before), ("sigma_after", sigma_after)):
        if np.ndim(s) > 1:
            raise InvalidParameterError(
                f"{name}: tiled inputs take a scalar or per-axis sigma, not per-point sigmas"
            )
    model = check_stochastic_model(stochastic_model)
    components = check_components(components)
    random_tilt = check_random_tilt(random_tilt, model)
    eng = _engine(engine)
    for coll in (before, after):
        if coll.n_points == 0:
            raise InputDataError(f"{coll.label or 'input'}: the tiles hold no point")
    t = check_tiles([("before", before), ("after", after)], tile_size_m)
    if before.crs is not None and after.crs is not None:
        from ..core.io.crs import same_crs

        if not same_crs(before.crs, after.crs):
            raise InvalidParameterError(
                "the before and after tiles are in different CRSs; tiled inputs are not "
                "reprojected: reproject one epoch, or give the CRS option if both are wrong"
            )
    (lo_b, hi_b), (lo_a, hi_a) = before.bounds, after.bounds
    lo, hi = np.maximum(lo_b, lo_a), np.minimum(hi_b, hi_a)
    if np.any(lo[:2] >= hi[:2]):
        raise InputDataError("the two epochs do not overlap in plan; check their CRSs and extents")
    regions = _check_trace(before, after, trace, t)
    origin = tuple(float(v) for v in _reference(before, after))
    h = 1e-3 * t  # the tasks read with a hair of halo: ownership is decided by floor(x / t)
    tasks = [
        _SlipTask(before.restricted(r, h), after.restricted(r, h), r, t, trace, float(buffer_m),
                  dict(plane_options or {}), dict(match_options or {}), selection,
                  units != "none", origin)
        for r in regions
    ]  # fmt: skip
    results = eng.map(
        _slip_tile, tasks, names=[r.name for r in regions], progress=scaled(progress, 0, 0.85)
    )
    use_units = False
    n_units = {}
    if units != "none":
        for e, name in enumerate(("before", "after")):
            codes = [res["codes"][e] for res in results if res["codes"][e] is not None]
            allc = np.unique(np.concatenate(codes)) if codes else np.zeros(0)
            n_units[name] = int(allc.size)
        use_units = units == "PointSourceId" or any(v > 1 for v in n_units.values())
    sides = {}
    tiles_all = []
    for si, side in enumerate(SIDES):
        tile_info, mom_b, mom_a, parts_b, parts_a = [], [], [], [], []
        mb_ids, ma_ids, m_ang, m_dist = [], [], [], []
        n_matched = off_b = off_a = 0
        for r, res in zip(regions, results):
            entry = res.get(side)
            if entry is None:
                continue
            k = entry["k"]
            if entry["status"] == "ok":
                m = entry["matches"]
                pb, pa = entry["planes_before"], entry["planes_after"]
                parts_b.append((np.zeros(0, np.int64), pb))
                parts_a.append((np.zeros(0, np.int64), pa))
                mom_b.append(entry["before"])
                mom_a.append(entry["after"])
                mb_ids.append(m.before + off_b)
                ma_ids.append(m.after + off_a)
                m_ang.append(m.angle_rad)
                m_dist.append(m.distance_m)
                off_b += len(pb)
                off_a += len(pa)
            tile_info.append((r.ix, r.iy, n_matched, k, entry["status"]))
            n_matched += k
        pb_all = _merge_planesets(parts_b, 0)
        pa_all = _merge_planesets(parts_a, 0)

        def cat(v, dt):
            return np.concatenate(v).astype(dt) if v else np.zeros(0, dtype=dt)

        matches = PlaneMatches(
            before=cat(mb_ids, np.int64),
            after=cat(ma_ids, np.int64),
            angle_rad=cat(m_ang, np.float64),
            distance_m=cat(m_dist, np.float64),
        )
        log.debug("%s", side_summary(side, pb_all, pa_all, len(matches),
                                     f"{len(tile_info)} tiles of {t:g} m, "))  # fmt: skip
        if len(matches) < 3:
            raise InputDataError(
                f"{side} side: only {len(matches)} matched planes over all tiles of {t:g} m "
                "(need at least 3); use bigger tiles or relax the matching thresholds"
            )
        all_b, all_a = PlaneMoments.concat(mom_b), PlaneMoments.concat(mom_a)
        kw = dict(
            sigma_before=sigma_before, sigma_after=sigma_after, stochastic_model=model,
            use_units=use_units, random_tilt=random_tilt,
        )  # fmt: skip
        report(progress, 0.85 + 0.07 * si, f"{side} side: adjustment")
        rigid = adjust_rigid_moments(all_b, all_a, components=components, **kw)
        vc = rigid.variance_components
        tile_fixed = vc.fixed() if vc is not None else None

        def adjust_tile(first, k, all_b=all_b, all_a=all_a, tile_fixed=tile_fixed, kw=kw):
            sl = np.arange(first, first + k)
            return adjust_rigid_moments(all_b.take(sl), all_a.take(sl), components=tile_fixed, **kw)

        tl, comb_d, comb_c = tile_adjustments(
            tile_info, adjust_tile, side=side, tile_size_m=t, combine=combine, joint=rigid
        )
        tiles_all.extend(tl)
        sides[side] = SideResult(
            side=side,
            rigid=rigid,
            planes_before=pb_all,
            planes_after=pa_all,
            matches=matches,
            combined_displacement=comb_d,
            combined_covariance=comb_c,
            plane_mean_residual_m=_mean_after_misclosure(rigid, all_a),
        )
    left, right = sides["left"], sides["right"]
    report(progress, 1.0, "slip done")
    return SlipResult(
        left=left,
        right=right,
        relative=right.displacement - left.displacement,
        # the survey error shared across the trace cancels in the slip (issue #30 item 1):
        # the spatial field here, as plane moments carry no acquisition units
        relative_covariance=relative_covariance(left, right)[0],
        strike_rad=mean_strike_rad(trace),
        buffer_m=float(buffer_m),
        parameters={
            "buffer_m": float(buffer_m),
            "combine": combine,
            "tile_size_m": t,
            "plane_options": dict(plane_options or {}),
            "match_options": dict(match_options or {}),
            "stochastic_model": model,
            "acquisition_units": n_units if use_units else {},
            **({"components": dict(components)} if components else {}),
            **({"random_tilt": bool(random_tilt)} if random_tilt is not None else {}),
            "engine": eng.describe(),
        },
        tiles=tuple(tiles_all),
    )


# --------------------------------------------------------------------------- planes


@dataclass(frozen=True)
class TiledPlanes:
    """Planes of a tiled cloud after the merge across tile borders.

    Attributes
    ----------
    normals, offsets, centroids, n_points, rms, covariances, extent_min, extent_max
        As :class:`~slipmap.core.planes.PlaneSet` (from the merged moments of each plane's
        points; each point counted once, in the tile that owns it).
    tiles : (P,) int
        Number of tiles each plane spans.
    parameters : SegmentationParameters
        Estimated once on the pilot tile, then used for every tile.
    n_points_total : int
        Selected points over all tiles.
    n_tile_planes : int
        Planes found in the tiles before the merge.
    """

    normals: np.ndarray
    offsets: np.ndarray
    centroids: np.ndarray
    n_points: np.ndarray
    rms: np.ndarray
    covariances: np.ndarray
    extent_min: np.ndarray
    extent_max: np.ndarray
    tiles: np.ndarray
    parameters: Any
    n_points_total: int
    n_tile_planes: int

    def __len__(self) -> int:
        return int(self.normals.shape[0])

    def to_records(self) -> List[Dict[str, object]]:
        return [
            {
                "id": k,
                "normal": [float(v) for v in self.normals[k]],
                "d": float(self.offsets[k]),
                "centroid": [float(v) for v in self.centroids[k]],
                "n_points": int(self.n_points[k]),
                "rms": float(self.rms[k]),
                "extent_min": [float(v) for v in self.extent_min[k]],
                "extent_max": [float(v) for v in self.extent_max[k]],
                "tiles": int(self.tiles[k]),
            }
            for k in range(len(self))
        ]


@dataclass(frozen=True)
class _PlaneTask:
    coll: TileCollection
    region: Region
    tile_size_m: float
    halo_m: float
    options: Dict[str, Any]
    selection: Selection
    origin: Tuple[float, float, float]


def _pilot_tile(task: _PlaneTask):
    """The segmentation parameters estimated on one tile (with its halo)."""
    from ..core.planes import segment_planes

    cloud, sel = _read_selected(task.coll, task.region, task.halo_m, task.selection)
    if sel.size < 3:
        return None
    return segment_planes(cloud.xyz[sel], **task.options).parameters


def _planes_tile(task: _PlaneTask):
    """Segment a tile with its halo; each plane's moments and extent over owned points."""
    from ..core.planes import segment_planes

    r, t = task.region, task.tile_size_m
    cloud, sel = _read_selected(task.coll, r, task.halo_m, task.selection)
    pts = cloud.xyz[sel]
    own = _owned(pts, r, t)
    n_own = int(np.count_nonzero(own))
    if pts.shape[0] < 3 or n_own == 0:
        return n_own, None
    try:
        ps = segment_planes(pts, quiet=True, **task.options)
    except InputDataError:
        return n_own, None
    lab = np.where(own, ps.labels, -1)
    k = len(ps)
    mom = PlaneMoments.from_points(pts, lab, k, origin_m=task.origin)
    keep = mom.count > 0
    if not np.any(keep):
        return n_own, None
    idx = np.flatnonzero(keep)
    lo = np.full((k, 3), np.inf)
    hi = np.full((k, 3), -np.inf)
    m = lab >= 0
    for d in range(3):
        np.minimum.at(lo[:, d], lab[m], pts[m, d])
        np.maximum.at(hi[:, d], lab[m], pts[m, d])
    fit = (ps.normals[idx], ps.offsets[idx], ps.centroids[idx])  # fits over tile + halo
    return n_own, (mom.take(idx), lo[idx], hi[idx], fit, idx, k)


_LABEL_ATTRIBUTES = (
    "Classification", "Intensity", "ReturnNumber", "NumberOfReturns", "PointSourceId", "GpsTime",
)  # fmt: skip


@dataclass(frozen=True)
class _LabelTask:
    plane: _PlaneTask
    lut: np.ndarray  # tile plane id -> final plane id (-1: none); last entry for label -1
    path: str


def _label_tile(task: _LabelTask) -> int:
    """Write a tile's own points with their final PlaneId (the tile segmented again: the same
    points, parameters and order give the same labels as in the first pass)."""
    from ..core.io.las import PointCloud, write_las
    from ..core.planes import segment_planes

    pt = task.plane
    r, t = pt.region, pt.tile_size_m
    attrs = tuple(dict.fromkeys(_LABEL_ATTRIBUTES))
    cloud = pt.coll.read_region(r, halo_m=pt.halo_m, attributes=attrs)
    own_all = _owned(cloud.xyz, r, t)
    if not np.any(own_all):
        return 0
    sel = pt.selection.indices(cloud)
    labels = np.full(len(cloud), -1, dtype=np.int32)
    pts = cloud.xyz[sel]
    if pts.shape[0] >= 3:
        try:
            local = segment_planes(pts, quiet=True, **pt.options).labels
        except InputDataError:
            local = np.full(pts.shape[0], -1)
        lut = task.lut
        labels[sel] = lut[np.where((local >= 0) & (local < lut.size - 1), local, lut.size - 1)]
    out = PointCloud(
        cloud.xyz[own_all], {k: v[own_all] for k, v in cloud.attributes.items()}, cloud.crs
    )
    write_las(task.path, out, extra_dims={"PlaneId": labels[own_all]})
    return int(np.count_nonzero(own_all))


def _plane_fit(mom: PlaneMoments):
    """Normals (oriented as PlaneSet's), offsets, centroids, rms and covariances."""
    from ..core.planes import orient_normals

    cnt = np.maximum(mom.count, 1.0)
    cov = mom.scatter_m2 / cnt[:, None, None]
    evals, evecs = np.linalg.eigh(cov)
    normals = orient_normals(np.ascontiguousarray(evecs[:, :, 0]))
    cen = mom.origin_m + mom.mean_m
    offsets = -np.einsum("ij,ij->i", normals, cen)
    rms = np.sqrt(np.maximum(evals[:, 0], 0.0))
    return normals, offsets, cen, rms, cov


def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def planes_tiled(
    coll: TileCollection,
    *,
    options: Optional[dict] = None,
    selection: Selection = Selection(ground_default=True),
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    halo_m: Optional[float] = None,
    labelled_path: Optional[Any] = None,
    engine: Optional[Engine] = None,
    progress: Optional[ProgressCallback] = None,
) -> TiledPlanes:
    """Planar segmentation of a tiled cloud, tile by tile, planes merged across borders.

    Parameters
    ----------
    coll : TileCollection
    options : dict
        ``segment_planes`` keywords; those not given are estimated on the pilot tile (the
        tile nearest the data's centre that has points) and then held for every tile.
    tile_size_m : float
        Processing tile edge, metres.
    halo_m : float, optional
        Margin read around each tile for context (default twice the largest octree node,
        at least 2 m).
    labelled_path : callable, optional
        ``labelled_path(region)`` gives the path of a LAS/LAZ file to write the region's own
        points to, with their final ``PlaneId`` (a second pass: each tile is segmented
        again, with the same result); the workers write the files, so the path must be
        reachable from them.
    """
    eng = _engine(engine)
    if coll.n_points == 0:
        raise InputDataError(f"{coll.label or 'input'}: the tiles hold no point")
    t = check_tiles([("input", coll)], tile_size_m)
    opts = dict(options or {})
    lo, hi = coll.bounds
    regions = region_grid((lo, hi), t, collections=[coll])
    origin = tuple(float(v) for v in _reference(coll))
    centre = 0.5 * (lo[:2] + hi[:2])
    by_dist = sorted(
        regions,
        key=lambda r: (
            (0.5 * (r.xmin + r.xmax) - centre[0]) ** 2 + (0.5 * (r.ymin + r.ymax) - centre[1]) ** 2,
            r.ix,
            r.iy,
        ),
    )
    pilot_halo = halo_m if halo_m is not None else 2.0
    params = None
    for r in by_dist[:8]:
        pilot = _PlaneTask(coll.restricted(r, pilot_halo), r, t, pilot_halo, opts, selection,
                           origin)  # fmt: skip
        params = eng.map(_pilot_tile, [pilot], names=[f"pilot {r.name}"], what="pilot")[0]
        if params is not None:
            break
    if params is None:
        tried = ", ".join(r.name for r in by_dist[:8])
        raise InputDataError(
            f"the segmentation parameters are estimated on a pilot tile near the data's "
            f"centre ({centre[0]:.1f}, {centre[1]:.1f}), but none of the {len(by_dist[:8])} "
            f"nearest processing tiles ({tried}) holds enough selected points: the tiles' "
            "header boxes span much more than the points (a stray point far away?) or the "
            "class selection leaves too few points; check the tiles' extents and the classes, "
            "or give a larger tile size"
        )
    fixed = {
        k: getattr(params, k)
        for k in (
            "min_node_size_m", "max_node_size_m", "planarity_threshold_m", "planarity_ratio",
            "angle_threshold_deg", "distance_threshold_m", "min_plane_points", "min_leaf_points",
        )
    }  # fmt: skip
    fixed["backend"] = opts.get("backend", "numpy")
    halo = halo_m if halo_m is not None else max(2.0, 2.0 * fixed["max_node_size_m"])
    report(progress, 0.05, "parameters from the pilot tile")
    tasks = [
        _PlaneTask(coll.restricted(r, halo), r, t, halo, fixed, selection, origin) for r in regions
    ]
    results = eng.map(
        _planes_tile, tasks, names=[r.name for r in regions], progress=scaled(progress, 0.05, 0.9)
    )
    n_total = sum(res[0] for res in results)
    if n_total == 0:
        raise InputDataError("no point is left by the class selection; choose other classes")
    moms, los, his, fits, tile_of, local = [], [], [], [], [], {}
    for i, (r, (_, part)) in enumerate(zip(regions, results)):
        if part is None:
            continue
        mom, lo_p, hi_p, fit, idx, k = part
        local[i] = (sum(len(m) for m in moms), idx, k)
        moms.append(mom)
        los.append(lo_p)
        his.append(hi_p)
        fits.append(fit)
        tile_of.extend([(r.ix, r.iy)] * len(mom))
    if not moms:
        return _empty_planes(params, n_total)
    allm = PlaneMoments.concat(moms)
    lo_all, hi_all = np.concatenate(los), np.concatenate(his)
    fit_all = tuple(np.concatenate([f[k] for f in fits]) for k in range(3))
    tile_of = np.asarray(tile_of, dtype=np.int64)
    groups = _merge_groups(allm, lo_all, hi_all, fit_all, tile_of, fixed)
    ng = int(groups.max()) + 1
    merged = allm.merge_planes(groups, ng)
    # a fragment that no neighbour's plane took and that is too small on its own is let go
    big = merged.count >= fixed["min_plane_points"]
    keep_g = np.flatnonzero(big)
    remap = np.full(ng, -1)
    remap[keep_g] = np.arange(keep_g.size)
    sel_p = remap[groups] >= 0
    n_orig = len(allm)
    allm, lo_all, hi_all = allm.take(np.flatnonzero(sel_p)), lo_all[sel_p], hi_all[sel_p]
    groups = remap[groups][sel_p]
    ng = int(keep_g.size)
    if ng == 0:
        return _empty_planes(params, n_total)
    merged = merged.take(keep_g)
    normals, offsets, cen, rms, cov = _plane_fit(merged)
    ext_lo = np.full((ng, 3), np.inf)
    ext_hi = np.full((ng, 3), -np.inf)
    np.minimum.at(ext_lo, groups, lo_all)
    np.maximum.at(ext_hi, groups, hi_all)
    tile_kept = tile_of[sel_p]
    pairs = np.unique(np.column_stack([groups, tile_kept]), axis=0)
    ntiles = np.bincount(pairs[:, 0], minlength=ng)
    order = np.lexsort((cen[:, 1], cen[:, 0], -merged.count))  # biggest first, then position
    if labelled_path is not None:
        final = np.full(n_orig, -1, dtype=np.int32)
        rank = np.empty(ng, dtype=np.int32)
        rank[order] = np.arange(ng)
        final[np.flatnonzero(sel_p)] = rank[groups]
        label_tasks = []
        for i, task in enumerate(tasks):  # a tile without own points writes no file
            lut = np.full(1, -1, dtype=np.int32)
            if i in local:
                start, idx, k = local[i]
                lut = np.full(k + 1, -1, dtype=np.int32)
                lut[idx] = final[start : start + idx.size]
            label_tasks.append(_LabelTask(task, lut, str(labelled_path(task.region))))
        eng.map(_label_tile, label_tasks, names=[x.plane.region.name for x in label_tasks],
                progress=scaled(progress, 0.9, 1.0), what="labelled tile")  # fmt: skip
    report(progress, 1.0, f"{ng} planes ({len(allm)} tile planes merged)")
    return TiledPlanes(
        normals=normals[order],
        offsets=offsets[order],
        centroids=cen[order],
        n_points=merged.count[order].astype(np.int64),
        rms=rms[order],
        covariances=cov[order],
        extent_min=ext_lo[order],
        extent_max=ext_hi[order],
        tiles=ntiles[order],
        parameters=params,
        n_points_total=int(n_total),
        n_tile_planes=len(allm),
    )


def _empty_planes(params, n_total) -> TiledPlanes:
    z3 = np.zeros((0, 3))
    return TiledPlanes(
        z3, np.zeros(0), z3, np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3, 3)), z3, z3,
        np.zeros(0, np.int64), params, int(n_total), 0,
    )  # fmt: skip


def _merge_groups(mom: PlaneMoments, lo, hi, fit, tile_of, p) -> np.ndarray:
    """Union of tile planes that one plane fits (neighbouring tiles, touching extents).

    Angles and distances use each tile plane's fit over its tile and halo (``fit``: normals,
    offsets, centroids), which is defined even for a fragment with a few owned points; the
    merged RMS uses the owned points' moments."""
    normals, offsets, cen = fit
    n = len(mom)
    parent = np.arange(n)
    cos_max = math.cos(math.radians(p["angle_threshold_deg"]))
    gap = 2.0 * p["min_node_size_m"]
    dist = p["distance_threshold_m"]
    rms_max = 0.5 * p["planarity_threshold_m"]
    # candidate pairs: planes of different, neighbouring tiles whose boxes touch
    for i in range(n):
        near = np.flatnonzero(
            (np.abs(tile_of[:, 0] - tile_of[i, 0]) <= 1)
            & (np.abs(tile_of[:, 1] - tile_of[i, 1]) <= 1)
            & np.any(tile_of != tile_of[i], axis=1)
            & (np.arange(n) > i)
        )
        if near.size == 0:
            continue
        touch = np.all((lo[near] <= hi[i] + gap) & (hi[near] >= lo[i] - gap), axis=1)
        near = near[touch]
        cosang = np.abs(normals[near] @ normals[i])
        near = near[cosang >= cos_max]
        for j in near:
            d_ij = abs(normals[i] @ cen[j] + offsets[i])
            d_ji = abs(normals[j] @ cen[i] + offsets[j])
            if d_ij > dist or d_ji > dist:
                continue
            pair = mom.take([i, j]).merge_planes(np.array([0, 0]), 1)
            if _plane_fit(pair)[3][0] > rms_max:
                continue
            a, b = _find(parent, i), _find(parent, j)
            if a != b:
                parent[max(a, b)] = min(a, b)
    roots = np.array([_find(parent, i) for i in range(n)])
    _, groups = np.unique(roots, return_inverse=True)
    return groups.ravel()


# --------------------------------------------------------------------------- job wiring

_SCALE = "scale: tiled inputs and Dask"


def scale_options(*, tile_option: bool = True, group: str = _SCALE) -> tuple:
    """The options every tiled job declares once: ``workers``, ``scheduler`` and (unless the
    job has its own) the processing tile ``tile_size_m``.

    QGIS runs in process or against a scheduler (an advanced parameter): it does not start
    local clusters (its Python is the QGIS process), so ``workers`` is CLI/API only.
    """
    from .options import KEEP_DUPLICATE_POINTS, Option

    opts = (
        Option(
            "workers",
            "int",
            "run the tiles on a local Dask cluster of this many worker processes (needs "
            "dask[distributed]); the result is the same as in process",
            label="Local Dask workers",
            minimum=1,
            advanced=True,
            group=group,
            qgis=None,
            pdal=None,
            metavar="N",
            unset_text="in process",
        ),
        Option(
            "scheduler",
            "str",
            "address of a running Dask scheduler (tcp://host:8786) to run the tiles on; its "
            "workers must read the input files at the same paths",
            label="Dask scheduler address (tcp://host:port)",
            advanced=True,
            group=group,
            pdal=None,
            metavar="ADDRESS",
            unset_text="none",
        ),
    )
    opts += (KEEP_DUPLICATE_POINTS,)  # tile sets as delivered (issue #31)
    if tile_option:
        opts += (
            Option(
                "tile_size_m",
                "float",
                "edge of the square processing tiles of a tiled or Dask run, metres (memory "
                f"per task: one tile and its halo; default {DEFAULT_TILE_SIZE_M:g})",
                label="Processing tile size (m)",
                minimum=0,
                exclusive=True,
                advanced=True,
                group=group,
                pdal=None,
                metavar="M",
                unset_text=f"{DEFAULT_TILE_SIZE_M:g}",
            ),
        )
    return opts


def check_scale(opts) -> None:
    """Cross-option check of :func:`scale_options` (for a JobSpec's ``check``)."""
    from .options import OptionError

    if opts.get("workers") is not None and opts.get("scheduler"):
        raise OptionError(
            "workers", "cannot be given with {scheduler}; give one of them", also=("scheduler",)
        )
    addr = opts.get("scheduler")
    if addr:  # scheme, host and port, before anything connects (issue #31)
        from .engine import check_scheduler_address

        check_scheduler_address(addr)


def split_inputs(value):
    """An input option's value as a collection spec: a list as given; a text that names no
    existing file and holds commas as several files; else the text (file, folder, glob)."""
    if isinstance(value, (list, tuple)):
        return list(value)
    text = str(value)
    from pathlib import Path

    if "," in text and not Path(text).exists():
        return [t.strip() for t in text.split(",") if t.strip()]
    return text


def is_tiled(opts, *keys: str) -> bool:
    """Whether a run goes the tiled way: an input names several files (a folder, a glob, a
    comma-separated list) or Dask is asked for."""
    from ..core.io.tiles import is_collection_spec

    if opts.get("workers") is not None or opts.get("scheduler"):
        return True
    return any(opts.get(k) is not None and is_collection_spec(split_inputs(opts[k])) for k in keys)


def open_input(opts, key: str, *, what: str = "", crs=None) -> TileCollection:
    """The tiles an input option names; errors as OptionError naming the option.

    Tile sets as delivered: unless ``keep_duplicate_points``, a file that is a copy of
    another is left out with a warning naming both, and overlapping tiles are read so that
    each point counts once (:func:`~slipmap.core.io.tiles.open_collection`)."""
    from ..core.errors import SlipMapError
    from ..core.io.tiles import open_collection
    from .options import OptionError, warn_option

    keep = bool(opts.get("keep_duplicate_points"))
    try:
        coll = open_collection(
            split_inputs(opts[key]), crs=crs, label=what or key, keep_duplicates=keep
        )
    except SlipMapError as exc:
        raise OptionError(key, str(exc)) from exc
    name = what or key
    for copy, kept in coll.duplicates:
        warn_option(
            "%s: %s and %s are the same tile (the same header and point records): read "
            "once; give {keep_duplicate_points} if both are distinct data",
            name, kept, copy,
        )  # fmt: skip
    if coll.dedupe:
        n = len({id(f) for pair in coll.overlap_pairs() for f in pair})
        log.info(
            "%s: %d tile(s) overlap (header boxes): a point found in several tiles counts "
            "once (GpsTime and coordinates)", name, n,
        )  # fmt: skip
    return coll


def engine_from(opts) -> Engine:
    """The engine the options ask for (close it after use: it is a context manager)."""
    from ..core.errors import DependencyError, SlipMapError
    from .engine import make_engine
    from .options import OptionError

    key = "scheduler" if opts.get("scheduler") else "workers"
    try:
        return make_engine(workers=opts.get("workers"), scheduler=opts.get("scheduler") or None)
    except DependencyError as exc:
        raise OptionError(key, str(exc)) from exc
    except SlipMapError as exc:
        if key == "scheduler":
            raise OptionError(key, str(exc)) from exc
        raise


def run_planes_job(
    opts, outputs, *, plane_options: dict, progress: Optional[ProgressCallback] = None
):
    """The planes job (:mod:`.planes`) on tiled inputs: ``planes.json`` of the merged planes
    and, into an output folder, one labelled LAZ per processing tile (``planes_IX_IY.laz``:
    the tile's own points with the main dimensions and PlaneId). A single labelled-cloud
    destination (QGIS) is not written for tiled inputs (a warning says so).
    ``plane_options``: the keywords of :func:`~slipmap.core.planes.segment_planes` (the job's
    ``core_kwargs``)."""
    from .._version import __version__
    from .job import JobResult, Timer
    from .outputs import OutputPlan
    from .summaries import json_text

    outputs = dict(outputs)
    if outputs.get("labelled_cloud") is not None:
        log.warning(
            "tiled input: the labelled point cloud is written only into an output folder "
            "(one file per tile); here planes.json only"
        )
        outputs["labelled_cloud"] = None
    folder = outputs.get("out") is not None
    coll = open_input(opts, "input", what="input", crs=opts.get("crs"))
    plan = OutputPlan.for_outputs(
        inputs={
            "input": spec_folders(split_inputs(opts["input"])) + [str(p) for p in coll.paths()]
        },
        outputs=outputs,
        default_names={"summary": "planes.json"},
    )
    plan.check()
    sel = Selection(opts.get("classes"), opts.get("exclude_classes"), ground_default=True)
    check_tiles([("input", coll)], opts.get("tile_size_m") or DEFAULT_TILE_SIZE_M)
    with plan:
        with engine_from(opts) as eng, Timer() as t:
            planes = planes_tiled(
                coll,
                options=plane_options,
                selection=sel,
                tile_size_m=opts.get("tile_size_m") or DEFAULT_TILE_SIZE_M,
                labelled_path=(lambda r: plan.path(f"planes_{r.ix}_{r.iy}.laz"))
                if folder
                else None,
                engine=eng,
                progress=progress,
            )
            how = eng.describe()
        params = planes.parameters.to_dict()
        n_lab = int(planes.n_points.sum())
        summary = {
            "planes": planes.to_records(),
            "n_points": coll.n_points,
            "n_selected": planes.n_points_total,
            "n_labelled": n_lab,
            "parameters": params,
            "runtime_s": round(t.seconds, 4),
            "input": [str(p) for p in coll.paths()],
            "crs": coll.crs_wkt,
            "tiles": {
                "tile_size_m": opts.get("tile_size_m") or DEFAULT_TILE_SIZE_M,
                "files": len(coll),
                "tile_planes_before_merge": planes.n_tile_planes,
                "engine": how,
            },
            "slipmap_version": __version__,
        }
        if plan.wants("summary"):
            plan.file("summary").write_text(json_text(summary), encoding="utf-8")
    lines = [
        f"{len(planes)} planes ({planes.n_tile_planes} in the tiles before merging), {n_lab} "
        f"of {planes.n_points_total} selected points on a plane, {len(coll)} file(s), "
        f"{t.seconds:.2f} s ({how})"
    ]
    written = {"summary": plan.final("summary")} if plan.wants("summary") else {}
    tiles_written = [p for p in plan.written if p.suffix == ".laz"]
    if tiles_written:
        written["labelled_cloud"] = tiles_written[0].parent
        lines.append(f"{len(tiles_written)} labelled tile(s) planes_IX_IY.laz")
    return JobResult(summary, lines, written, data=(planes, None))


@dataclass(frozen=True)
class TiledRoughness:
    """What the roughness job needs of a tiled input (see :func:`roughness_for_job`)."""

    grids: Tuple[Any, ...]
    frame: Any
    ols_axis: str
    n_points: int
    crs: Any
    paths: Tuple[str, ...]
    engine: str


def roughness_for_job(
    opts,
    *,
    cell_sizes_m: Sequence[float],
    min_points: int,
    ols_axis: str,
    signed: bool,
    selection: Selection = Selection(),
    input_key: str = "input",
    progress: Optional[ProgressCallback] = None,
) -> TiledRoughness:
    """The roughness job's computation on tiled inputs: the principal frame (one pass) and
    the grids (exact), on the engine the options ask for; the job then writes its outputs
    from the cells as for one file. Per-point outputs need the points in one place: the job
    refuses them for tiled inputs."""
    from ..core import roughness as rough

    coll = open_input(opts, input_key, what="input", crs=opts.get("crs"))
    t = opts.get("tile_size_m") or DEFAULT_TILE_SIZE_M
    check_roughness_tiles(coll, t, cell_sizes_m, input_key)  # before any worker starts
    with engine_from(opts) as eng:
        frame = principal_frame_tiled(
            coll, selection=selection, tile_size_m=t, engine=eng, progress=scaled(progress, 0, 0.2)
        )
        axis = rough.resolve_ols_axis(frame, ols_axis)
        grids = roughness_tiled(
            coll, cell_sizes_m=cell_sizes_m, min_points=min_points, ols_axis=axis, signed=signed,
            selection=selection, tile_size_m=t, engine=eng, progress=scaled(progress, 0.2, 1.0),
        )  # fmt: skip
        how = eng.describe()
    return TiledRoughness(
        grids, frame, axis, coll.n_points, coll.crs, tuple(str(p) for p in coll.paths()), how
    )


def slip_for_job(
    opts,
    trace,
    *,
    keys: Tuple[str, str] = ("before", "after"),
    selection: Selection = Selection(),
    progress: Optional[ProgressCallback] = None,
    **kw,
):
    """The slip job's computation on tiled inputs: both epochs' tiles, the engine the options
    ask for, :func:`slip_tiled` with ``kw`` (sigmas, plane/match options, stochastic model,
    units, components, combine). The study's tile size (``tile_size_m``) is the processing
    tile; without it, :data:`DEFAULT_TILE_SIZE_M`.

    ``trace``: a FaultTrace, or ``f(crs) -> FaultTrace`` called with the before tiles' CRS;
    a trace away from the tiles is refused naming the ``fault`` option before any tile is
    read. Returns ``(crs, trace, SlipResult)``.
    """
    from .outputs import refuse_same_inputs

    refuse_same_inputs([(keys[0], opts[keys[0]]), (keys[1], opts[keys[1]])])
    before = open_input(opts, keys[0], what="before epoch", crs=opts.get("crs"))
    after = open_input(opts, keys[1], what="after epoch", crs=opts.get("crs"))
    fault = trace(before.crs) if callable(trace) else trace
    t = opts.get("tile_size_m") or DEFAULT_TILE_SIZE_M
    check_tiles([(keys[0], before), (keys[1], after)], t)  # before any tile is read
    try:
        _check_trace(before, after, fault, t)
    except InputDataError as exc:
        from .options import OptionError

        raise OptionError("fault", str(exc)) from exc
    with engine_from(opts) as eng:
        result = slip_tiled(
            before, after, fault, tile_size_m=t, selection=selection, engine=eng,
            progress=progress, **kw,
        )  # fmt: skip
    return before.crs, fault, result


def input_files(opts, key: str):
    """The files an input option names (a file, a folder, a glob, comma-separated files), as
    a list for :class:`~.outputs.OutputPlan`'s input checks; errors name the option."""
    from ..core.errors import SlipMapError
    from ..core.io.tiles import expand_paths
    from .options import OptionError

    value = opts.get(key)
    if value is None:
        return None
    try:
        files = [str(p) for p in expand_paths(split_inputs(value))]
    except SlipMapError as exc:
        raise OptionError(key, str(exc)) from exc
    return spec_folders(split_inputs(value)) + files


def spec_folders(spec) -> list:
    """The folders a collection spec reads tiles from: a folder given, a glob's folder (the
    part before its first wildcard); for OutputPlan, which writes nothing inside them."""
    import glob as _glob
    from pathlib import Path

    out = []
    for item in spec if isinstance(spec, (list, tuple)) else [spec]:
        p = Path(str(item))
        if p.is_dir():
            out.append(str(p))
        elif _glob.has_magic(str(p)):
            fixed = []
            for part in p.parts:
                if _glob.has_magic(part):
                    break
                fixed.append(part)
            base = Path(*fixed) if fixed else Path(".")
            if base.is_dir():
                out.append(str(base))
    return out
