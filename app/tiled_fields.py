"""Displacement fields on tiled inputs: DEM difference, PIV and windowed ICP per block of the
job's global raster, in process or on Dask (issue #17).

The jobs' rasters (the DEM grid of ``dem-diff`` and ``piv``, the cell lattice of ``icp``) are
defined once for the whole survey, from the tiles' header bounds, exactly as the one-file run
defines them from the points. They are cut into square blocks of about ``tile_size_m``; a task
reads one block plus a halo from both epochs' tiles (:class:`~slipmap.core.io.tiles.
TileCollection`), computes on it with the whole-cloud kernels and returns only what its block
owns. No point cloud travels to the driver.

* DEM difference (:func:`dem_difference_tiled`): exact. A cell's mean is over the points in
  it, indexed on the global grid (:func:`~slipmap.core.dem.grid_points` ``window``); blocks
  are written into the output GeoTIFF as they arrive (:class:`~slipmap.core.io.raster.
  RasterBlockWriter`: a COG), so the driver never holds the whole raster.
* PIV (:func:`piv_tiled`): the windows of every pass are placed as on the whole DEM
  (:func:`~slipmap.core.piv.piv` ``window_frame``); a block's halo covers, for every pass,
  the window, its search margin and three vector steps (the median test and the predictor's
  interpolation), plus 24 px for the cubic warper's prefilter (its influence decays by 0.27
  per pixel). The vectors a block owns are then the whole run's up to rounding, except where
  an outlier's replacement reaches further than the halo (a hole of more than three vectors
  next to a block's edge).
* Windowed ICP (:func:`icp_tiled`): cells on the whole run's lattice; a block's halo covers
  the target buffer and three cells (median test, deformation passes), doubled per coarse
  level. Cells are fitted with formal covariances and the field's variance factor is
  estimated once over all cells, as the one-file run does. Equal to the one-file run up to
  rounding (``max_points_per_cell`` samples by the points' coordinates, so a cell draws the
  same points from tiles); the stable-ground pre-alignment is refused on tiled inputs (it
  needs one fit over both whole epochs).
* The ICP's spline field (``field_model="spline"``, :func:`_icp_spline_tiled`): one field
  over all blocks, not one per block, smooth on each side of the ``breaklines`` (every
  block's chunk is built on the frame with the lines). Lines not given are detected as the
  one-file run detects them (``detect_breaklines``): the tiled cell pass's motions propose
  candidates, the blocks fit the field with them, each block sends the points within reach
  of a candidate (each point from one block), the driver confirms and places the lines on
  them and the blocks fit the field again (:func:`_confirm_lines_tiled`). The
  tiled cell pass starts it; then each Gauss-Newton iteration is two rounds over the
  blocks: every block returns the ``|v|`` of its points (the robust weights' scale is a
  median over all of them), then its share of the normal equations (the sparse
  normal-matrix entries of the knots its points touch, the right-hand side, the sums the
  variance-component smoothing and the stop test need); the driver adds the shares, solves
  once and hands the new coefficients back
  (:func:`~slipmap.core.icp_spline.fit_spline_chunks`, the one-file run's code with one
  chunk). A block owns the cells whose centres it holds (each after-point in one block) and
  reads the before-points two gates and a cell around (its points' targets and their normals
  are the one-file run's). It keeps its points, KD-tree and pairs in its process between
  iterations (:data:`SPLINE_CACHE_BYTES`; a block read again gives the same result). Equal to
  the one-file run up to rounding (tests: 1e-16 m); the driver holds the sparse normal
  equations and 8 bytes per after-point per iteration, checked from the headers
  (:func:`check_spline_memory`).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections import OrderedDict
from dataclasses import dataclass, fields, replace
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..core.errors import InputDataError, InvalidParameterError
from ..core.io.tiles import Region, TileCollection
from ..core.progress import ProgressCallback, report, scaled
from .engine import Engine, InProcess
from .tiled import DEFAULT_TILE_SIZE_M, Selection

log = logging.getLogger("slipmap.app")

__all__ = [
    "dem_difference_tiled",
    "icp_tiled",
    "open_pair",
    "pair_grid",
    "piv_tiled",
]

#: pixels of halo for the cubic warper's spline prefilter (0.268 ** 24 ~ 2e-14)
SPLINE_HALO_PX = 24
#: extra cells of halo with ICP deformation passes: the field's cubic spline ties every cell
#: to all others, its influence falling 3.7x per cell (0.268 ** 12 ~ 1e-7; 6 cells left 0.6 mm
#: on the 5 m cells of tests/app/test_tiled_fields.py, 12 cells 4e-11 m)
DEFORM_HALO_CELLS = 12
#: bytes per final vector the PIV driver holds (dx, dy, dz, snr float64, valid, the lattice)
_PIV_DRIVER_BYTES = 48.0
#: bytes per cell of the ICP's lattice (the per-cell counts, the median test's and the
#: deformation field's rasters: about a dozen float64 arrays over the lattice)
ICP_LATTICE_BYTES = 96.0
#: every point (no class selection)
_ALL = Selection()


# --------------------------------------------------------------------------- shared


def open_pair(opts, *, keys: Tuple[str, str] = ("before", "after")):
    """Both epochs' tiles (errors name the option), refused when their CRSs differ or they
    do not overlap. Returns ``(before, after, selection)``."""
    from ..core.io.crs import same_crs
    from .options import OptionError
    from .outputs import refuse_same_inputs
    from .tiled import open_input

    refuse_same_inputs([(keys[0], opts[keys[0]]), (keys[1], opts[keys[1]])])
    before = open_input(opts, keys[0], what="before epoch", crs=opts.get("crs"))
    after = open_input(opts, keys[1], what="after epoch", crs=opts.get("crs"))
    for key, coll in zip(keys, (before, after)):
        if coll.n_points == 0:
            raise OptionError(key, f"{coll.label}: the tiles hold no point")
    if before.crs is not None and after.crs is not None and not same_crs(before.crs, after.crs):
        raise OptionError(
            keys[1],
            "the before and after tiles are in different CRSs; tiled inputs are not "
            "reprojected: reproject one epoch, or give {crs} if both files declare a wrong one",
            also=("crs",),
        )
    (lo_b, hi_b), (lo_a, hi_a) = before.bounds, after.bounds
    if np.any(np.maximum(lo_b[:2], lo_a[:2]) > np.minimum(hi_b[:2], hi_a[:2])):
        raise OptionError(
            keys[1],
            f"the epochs' tiles do not overlap in x, y (before x {lo_b[0]:.2f}..{hi_b[0]:.2f}, "
            f"y {lo_b[1]:.2f}..{hi_b[1]:.2f}; after x {lo_a[0]:.2f}..{hi_a[0]:.2f}, y "
            f"{lo_a[1]:.2f}..{hi_a[1]:.2f}): check that both are in the same CRS",
            also=("crs",),
        )
    selection = Selection(
        classes=tuple(opts["classes"]) if opts.get("classes") else None,
        exclude_classes=(
            tuple(opts["exclude_classes"]) if opts.get("exclude_classes") is not None else None
        ),
    )
    return before, after, selection


def pair_grid(before: TileCollection, after: TileCollection, cell_m: float):
    """The DEM grid of the epochs' overlap: :func:`~slipmap.core.dem.common_grid` of the
    points, from the tiles' header bounds."""
    from ..core.dem import grid_for_bounds

    (lo_b, hi_b), (lo_a, hi_a) = before.bounds, after.bounds
    return grid_for_bounds(np.maximum(lo_b, lo_a), np.minimum(hi_b, hi_a), cell_m=cell_m)


def _kept_bounds(coll: TileCollection) -> Tuple[np.ndarray, np.ndarray]:
    """The union of the tiles' header boxes without the outlying ones (a stray point's)."""
    from .tiled import outlying_tiles

    lo, hi, full = coll._boxes()
    rest = np.setdiff1d(np.flatnonzero(full), outlying_tiles(coll))
    if not rest.size:
        return coll.bounds
    return lo[rest].min(axis=0), hi[rest].max(axis=0)


def _cells_over(lo, hi, cell: float) -> float:
    span = np.maximum(np.asarray(hi, float)[:2] - np.asarray(lo, float)[:2], 0.0)
    return float(np.prod(np.floor(span / cell) + 1))


def check_grid_guards(
    inputs: Sequence[Tuple[str, TileCollection]],
    *,
    cell: float,
    cell_key: str,
    n_cells: float,
    blocks: Any,
    tile_size_m: float,
    what: str,
    bytes_per_cell: float = 0.0,
    overlap: bool = True,
) -> None:
    """The guards of a field job's global grid, from the tiles' headers before any point is
    read: a grid whose extent one stray tile makes (the data fill under 1 % of it) is refused
    naming the tile; then at most :data:`~.resources.MAX_TILES` blocks (``blocks(size)``:
    the blocks a ``tile_size_m`` of ``size`` gives) and, with ``bytes_per_cell``, the memory
    of the arrays the driver holds over the grid's ``n_cells`` cells.

    ``overlap``: the grid covers the inputs' overlap (DEM difference, PIV), else the union
    of the last input's tiles (the ICP's after epoch).
    """
    from .resources import (
        SPARSE_MIN_CELLS,
        SPARSE_SHARE,
        check_grid_memory,
        check_tile_budget,
    )
    from .tiled import refuse_outlying_tiles

    kept = [_kept_bounds(c) for _, c in inputs]
    if overlap:
        lo = np.max([k[0] for k in kept], axis=0)
        hi = np.min([k[1] for k in kept], axis=0)
    else:
        lo, hi = kept[-1]
    robust = _cells_over(lo, hi, cell)
    if n_cells >= SPARSE_MIN_CELLS and robust <= SPARSE_SHARE * n_cells:
        refuse_outlying_tiles(
            inputs,
            f"the {what} of {{{cell_key}}} = {cell:g} m would span {n_cells:.3g} cells, the data "
            f"fill {robust:.3g} of them",
            also=(cell_key,),
        )
    check_tile_budget("tile_size_m", blocks, float(tile_size_m), what=f"blocks of the {what}")
    if bytes_per_cell:
        check_grid_memory(cell_key, n_cells, bytes_per_cell=bytes_per_cell, what=what)


@contextlib.contextmanager
def _quiet_core():
    """The core's per-run INFO lines off while a block runs (one line per block and pass
    would bury the job's own); warnings still show."""
    core = logging.getLogger("slipmap.core")
    level = core.level
    if core.getEffectiveLevel() < logging.WARNING:
        core.setLevel(logging.WARNING)
    try:
        yield
    finally:
        core.setLevel(level)


def _engine(engine: Optional[Engine]) -> Engine:
    return engine if engine is not None else InProcess()


def _spans(n: int, size: int) -> List[Tuple[int, int]]:
    """``[lo, hi)`` index spans of ``size`` covering ``0..n``."""
    size = max(1, int(size))
    return [(s, min(n, s + size)) for s in range(0, n, size)]


def _read(coll: TileCollection, box: Region, selection: Selection) -> np.ndarray:
    attrs = ("Classification",) if selection.needs_classes else ()
    cloud = coll.read_region(box, attributes=attrs)
    sel = selection.indices(cloud)
    return cloud.xyz[sel] if sel.size < len(cloud) else cloud.xyz


def _pixel_box(grid, r0: int, r1: int, c0: int, c1: int) -> Region:
    """Map box of the pixels rows ``r0..r1-1``, cols ``c0..c1-1`` of ``grid``, grown by one
    cell (the gridding keeps only the points of the window's cells)."""
    c = grid.cell_m
    return Region(
        grid.x_min + (c0 - 1) * c,
        grid.y_max - (r1 + 1) * c,
        grid.x_min + (c1 + 1) * c,
        grid.y_max - (r0 - 1) * c,
    )


def _block_dems(task) -> Tuple[np.ndarray, np.ndarray]:
    """Both epochs' mean z on a task's window of the global grid (NaN where empty)."""
    from ..core.dem import grid_points

    r0, c0, nr, nc = task.window
    box = _pixel_box(task.grid, r0, r0 + nr, c0, c0 + nc)
    out = []
    for coll in (task.before, task.after):
        pts = _read(coll, box, task.selection)
        if len(pts):
            out.append(grid_points(pts, grid=task.grid, window=task.window).z)
        else:
            out.append(np.full((nr, nc), np.nan))
    return out[0], out[1]


# --------------------------------------------------------------------------- DEM difference


@dataclass(frozen=True)
class _DemTask:
    before: TileCollection
    after: TileCollection
    grid: Any
    window: Tuple[int, int, int, int]
    selection: Selection


def _dem_block(task: _DemTask):
    zb, za = _block_dems(task)
    return task.window, np.stack([za - zb, zb, za])


@dataclass(frozen=True)
class TiledDem:
    """What a tiled DEM difference gives the job (the raster itself is in the file)."""

    grid: Any
    n_valid: int
    mean_dz: float
    m2_dz: float  # sum of squared deviations from the mean (Chan et al.'s pairwise update)
    min_dz: float
    max_dz: float
    dz_sample: np.ndarray  # every k-th valid dz of each block (for the median)
    sample_every: int

    @property
    def mean_m(self) -> float:
        return self.mean_dz if self.n_valid else float("nan")

    @property
    def std_m(self) -> float:
        """Standard deviation of dz (ddof 0, as the one-file run)."""
        if not self.n_valid:
            return float("nan")
        return math.sqrt(max(self.m2_dz / self.n_valid, 0.0))

    def stats(self) -> Dict[str, Any]:
        """The summary's ``dz_m`` (:func:`~.summaries.finite_stats`'s keys); the median comes
        from the sample when ``sample_every > 1`` (``median_from_every``)."""
        if not self.n_valid:
            return {"n": 0}
        out = {
            "n": self.n_valid,
            "mean": self.mean_m,
            "median": float(np.median(self.dz_sample)) if self.dz_sample.size else float("nan"),
            "std": self.std_m,
            "min": self.min_dz,
            "max": self.max_dz,
        }
        if self.sample_every > 1:
            out["median_from_every"] = self.sample_every
        return out


def dem_difference_tiled(
    before: TileCollection,
    after: TileCollection,
    *,
    cell_m: float,
    writer_factory,
    selection: Selection = _ALL,
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    engine: Optional[Engine] = None,
    progress: Optional[ProgressCallback] = None,
    sample_every: Optional[int] = None,
    check_block=None,
) -> TiledDem:
    """DEM difference of two tiled epochs, block by block (exact).

    Parameters
    ----------
    before, after : TileCollection
    cell_m : float
        DEM cell (m).
    writer_factory : callable
        ``f(grid) -> writer`` with ``write(block (3, r, c), row0, col0)`` (bands dz,
        z_before, z_after); None writes nothing.
    tile_size_m : float
        Block edge (m), rounded to whole cells.
    check_block : callable, optional
        ``f(n_cells)``, called with a block's cell count before any is read (the job's
        memory check).
    sample_every : int, optional
        Keep every k-th valid dz of each block for the summary's median (default: about a
        million values in all; 1 keeps every value, the median is then exact).

    Returns
    -------
    TiledDem
    """
    grid = pair_grid(before, after, cell_m)

    def n_blocks(size: float) -> float:
        bs = max(8, int(round(float(size) / grid.cell_m)))
        return math.ceil(grid.n_rows / bs) * math.ceil(grid.n_cols / bs)

    check_grid_guards(
        [("before", before), ("after", after)], cell=grid.cell_m, cell_key="grid_m",
        n_cells=float(grid.n_rows) * grid.n_cols, blocks=n_blocks, tile_size_m=tile_size_m,
        what="DEM grid",
    )  # fmt: skip
    b = max(8, int(round(float(tile_size_m) / grid.cell_m)))
    if check_block is not None:
        check_block(min(b, grid.n_rows) * min(b, grid.n_cols))
    windows = [
        (r0, c0, r1 - r0, c1 - c0)
        for r0, r1 in _spans(grid.n_rows, b)
        for c0, c1 in _spans(grid.n_cols, b)
    ]
    tasks = []
    for w in windows:
        box = _pixel_box(grid, w[0], w[0] + w[2], w[1], w[1] + w[3])
        tb, ta = before.restricted(box), after.restricted(box)
        if len(tb) and len(ta):
            tasks.append(_DemTask(tb, ta, grid, w, selection))
    writer = writer_factory(grid) if writer_factory is not None else None
    try:
        out = _dem_blocks(grid, tasks, writer, b, engine, progress, sample_every)
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    if writer is not None:
        report(progress, 1.0, "writing the Cloud-Optimized GeoTIFF")
        writer.close()
    return out


def _dem_blocks(grid, tasks, writer, b, engine, progress, sample_every) -> TiledDem:
    acc = {"n": 0, "mean": 0.0, "m2": 0.0, "lo": math.inf, "hi": -math.inf, "sample": []}
    if sample_every is None:  # about a million values for the median
        sample_every = max(1, (grid.n_rows * grid.n_cols) // 1_000_000)

    def each(i, value):
        (r0, c0, _, _), block = value
        if writer is not None:
            writer.write(block, r0, c0)
        dz = block[0][np.isfinite(block[0])]
        if dz.size:  # mean and squared deviations combined block by block (stable)
            n_b, m_b = dz.size, float(dz.mean())
            m2_b = float(np.dot(dz - m_b, dz - m_b))
            n = acc["n"] + n_b
            delta = m_b - acc["mean"]
            acc["mean"] += delta * n_b / n
            acc["m2"] += m2_b + delta * delta * acc["n"] * n_b / n
            acc["n"] = n
            acc["lo"], acc["hi"] = min(acc["lo"], float(dz.min())), max(acc["hi"], float(dz.max()))
        acc["sample"].append(dz[:: max(1, int(sample_every))])
        return None

    report(progress, 0.0, f"DEM difference: {len(tasks)} block(s) of {b} x {b} cells")
    _engine(engine).map(
        _dem_block,
        tasks,
        names=[f"DEM block at row {t.window[0]}, col {t.window[1]}" for t in tasks],
        progress=progress,
        what="block",
        each=each,
    )
    sample = np.concatenate(acc["sample"]) if acc["sample"] else np.zeros(0)
    return TiledDem(
        grid, int(acc["n"]), acc["mean"], acc["m2"], acc["lo"], acc["hi"], sample, int(sample_every)
    )


# --------------------------------------------------------------------------- PIV


@dataclass(frozen=True)
class _PivTask:
    before: TileCollection
    after: TileCollection
    grid: Any
    window: Tuple[int, int, int, int]  # the DEM block read and gridded (with its halo)
    core: Tuple[int, int, int, int]  # the final vectors it owns: rows i0..i1-1, cols j0..j1-1
    first_xy: Tuple[float, float]  # centre of the whole run's first final vector
    spacing_m: float
    piv_kw: Dict[str, Any]
    selection: Selection


def _piv_block(task: _PivTask):
    from ..core.piv import piv

    r0, c0, nr, nc = task.window
    zb, za = _block_dems(task)
    if not (np.isfinite(zb).any() and np.isfinite(za).any()):
        return task.core, None
    frame = (task.grid.n_rows, task.grid.n_cols, r0, c0)
    try:
        with _quiet_core():
            res = piv(
                zb, za, grid=task.grid.window(*task.window), window_frame=frame, **task.piv_kw
            )
    except InputDataError as exc:  # no window with data, no valid vector: a gap of the survey
        log.debug("PIV block at (%d, %d): %s", r0, c0, exc)
        return task.core, None
    s = task.spacing_m
    i = np.rint((task.first_xy[1] - res.y[:, 0]) / s).astype(np.int64)
    j = np.rint((res.x[0, :] - task.first_xy[0]) / s).astype(np.int64)
    i0, i1, j0, j1 = task.core
    ri = np.flatnonzero((i >= i0) & (i < i1))
    cj = np.flatnonzero((j >= j0) & (j < j1))
    take = np.ix_(ri, cj)
    part = {k: getattr(res, k)[take] for k in ("dx", "dy", "dz", "snr", "valid")}
    part["near_break"] = res.near_break_or_false()[take]
    return (int(i[ri[0]]) if ri.size else i0, int(j[cj[0]]) if cj.size else j0), (
        part,
        res.search_px,
    )


def piv_halo_px(windows_px: Sequence[int], overlap: float, margin1: int, refine: Optional[int]):
    """Halo (pixels) a PIV block needs (see the module docstring)."""
    h = SPLINE_HALO_PX
    for k, w in enumerate(windows_px):
        step = max(1, int(round(w * (1.0 - float(overlap)))))
        margin = margin1 if k == 0 else (int(refine) if refine is not None else max(3, w // 8))
        h += w + margin + 3 * step
    return int(h)


def piv_tiled(
    before: TileCollection,
    after: TileCollection,
    *,
    grid_m: float,
    windows_px: Sequence[int],
    overlap: float = 0.5,
    search_px: Optional[int] = None,
    expected_max_displacement_m: Optional[float] = None,
    snr_min: float = 1.2,
    median_threshold: float = 1.5,
    breaklines=None,
    vertical_compensation: bool = True,
    selection: Selection = _ALL,
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    engine: Optional[Engine] = None,
    progress: Optional[ProgressCallback] = None,
    check_block=None,
):
    """Multi-pass PIV of two tiled epochs, block by block of the final vectors.

    Parameters
    ----------
    before, after : TileCollection
    grid_m, windows_px, overlap, search_px, expected_max_displacement_m, snr_min,
    median_threshold, breaklines, vertical_compensation
        As :func:`~slipmap.core.piv.piv` (``grid_m`` the DEM cell, m); every block gets the
        breaklines (those that miss it change nothing there).
    tile_size_m : float
        Edge of the blocks of final vectors a task owns (m, rounded to whole vector steps);
        each task grids its block plus the halo of :func:`piv_halo_px`.
    check_block : callable, optional
        ``f(n_cells)``, called with the largest block's cell count before any is read (the
        job's memory check).

    Returns
    -------
    (PIVResult, Grid)
        The whole field on the whole run's vector grid, and the DEM grid.
    """
    from ..core.piv import PIVResult, _check_windows, _layout

    grid = pair_grid(before, after, grid_m)
    wins = _check_windows(windows_px, grid.shape)
    cell = grid.cell_m
    w_last = wins[-1]
    step = max(1, int(round(w_last * (1.0 - float(overlap)))))
    lay = _layout(grid.n_rows, grid.n_cols, w_last, step)
    ny, nx = lay.r0.size, lay.c0.size

    def n_blocks(size: float) -> float:
        k = max(1, int(round(float(size) / (step * cell))))
        return math.ceil(ny / k) * math.ceil(nx / k)

    check_grid_guards(
        [("before", before), ("after", after)], cell=cell, cell_key="grid_m",
        n_cells=float(grid.n_rows) * grid.n_cols, blocks=n_blocks, tile_size_m=tile_size_m,
        what="DEM grid", bytes_per_cell=_PIV_DRIVER_BYTES / max(1, step * step),
    )  # fmt: skip
    if search_px is not None:
        margin1 = int(search_px)
    elif expected_max_displacement_m is not None:
        margin1 = int(math.ceil(float(expected_max_displacement_m) / cell)) + 2
    else:
        margin1 = max(2, wins[0] // 4)
    halo = piv_halo_px(wins, overlap, margin1, None)
    nb = max(1, int(round(float(tile_size_m) / (step * cell))))
    first_x, first_y = grid.xy_of(lay.rc[0], lay.cc[0])
    piv_kw = dict(
        windows_px=wins,
        overlap=overlap,
        search_px=search_px,
        expected_max_displacement_m=expected_max_displacement_m,
        snr_min=snr_min,
        median_threshold=median_threshold,
        breaklines=breaklines,
        vertical_compensation=vertical_compensation,
        workers=1,
    )
    tasks = []
    biggest = 0
    for i0, i1 in _spans(ny, nb):
        for j0, j1 in _spans(nx, nb):
            r_lo = max(0, int(lay.r0[i0]) - halo)
            r_hi = min(grid.n_rows, int(lay.r0[i1 - 1]) + w_last + halo)
            c_lo = max(0, int(lay.c0[j0]) - halo)
            c_hi = min(grid.n_cols, int(lay.c0[j1 - 1]) + w_last + halo)
            window = (r_lo, c_lo, r_hi - r_lo, c_hi - c_lo)
            box = _pixel_box(grid, r_lo, r_hi, c_lo, c_hi)
            tb, ta = before.restricted(box), after.restricted(box)
            biggest = max(biggest, window[2] * window[3])
            if len(tb) and len(ta):
                tasks.append(
                    _PivTask(
                        tb,
                        ta,
                        grid,
                        window,
                        (i0, i1, j0, j1),
                        (float(first_x), float(first_y)),
                        float(step * cell),
                        piv_kw,
                        selection,
                    )  # fmt: skip
                )
    if check_block is not None:
        check_block(biggest)
    log.info(
        "PIV on %d block(s) of %d x %d vectors (halo %d px), DEM %d x %d cells of %g m",
        len(tasks), nb, nb, halo, grid.n_rows, grid.n_cols, cell,
    )  # fmt: skip
    out = {k: np.full((ny, nx), np.nan) for k in ("dx", "dy", "dz", "snr")}
    out["valid"] = np.zeros((ny, nx), dtype=bool)
    out["near_break"] = np.zeros((ny, nx), dtype=bool)
    found = {"search_px": margin1}

    def each(i, value):
        (i0, j0), payload = value
        if payload is None:
            return None
        part, search = payload
        found["search_px"] = search
        r, c = part["dx"].shape
        for k in out:
            out[k][i0 : i0 + r, j0 : j0 + c] = part[k]
        return None

    _engine(engine).map(
        _piv_block,
        tasks,
        names=[f"PIV block of vectors ({t.core[0]}, {t.core[2]})" for t in tasks],
        progress=progress,
        what="block",
        each=each,
    )
    if not np.isfinite(out["dx"]).any():
        raise InputDataError(
            "PIV found no valid displacement in any block: check that the epochs overlap, "
            "increase the search margin / largest expected displacement or the windows"
        )
    rr, cc = np.meshgrid(lay.rc, lay.cc, indexing="ij")
    x, y = grid.xy_of(rr, cc)
    spacing = step * cell
    res = PIVResult(
        x=x,
        y=y,
        dx=out["dx"],
        dy=out["dy"],
        dz=out["dz"],
        snr=out["snr"],
        valid=out["valid"],
        spacing_m=float(spacing),
        origin_xy=(float(x[0, 0] - spacing / 2.0), float(y[0, 0] + spacing / 2.0)),
        windows_px=wins,
        search_px=int(found["search_px"]),
        cell_m=float(cell),
        near_break=out["near_break"],
    )
    return res, grid


# --------------------------------------------------------------------------- windowed ICP


@dataclass(frozen=True)
class _IcpTask:
    before: TileCollection
    after: TileCollection
    block: Region  # the cells it owns: centres inside
    halo_m: float
    x0: float  # the whole run's lattice: west edge of column 0
    y0: float  # north edge of row 0
    origin_xy: Optional[Tuple[float, float]]  # the lattices' node (coarse levels too)
    icp_kw: Dict[str, Any]
    selection: Selection


def _per_cell(res) -> List[str]:
    k = len(res.x)
    return [
        f.name
        for f in fields(res)
        if isinstance(getattr(res, f.name), np.ndarray) and len(getattr(res, f.name)) == k
    ]


def _icp_block(task: _IcpTask):
    from ..core.icp import windowed_icp

    box = task.block.grown(task.halo_m)
    b = _read(task.before, box, task.selection)
    a = _read(task.after, box, task.selection)
    cell = float(task.icp_kw["cell_m"])
    minp = int(task.icp_kw.get("min_points", 100))
    # the cells this block owns and why some are not fitted (as the one-file run counts them)
    ra = np.floor((task.y0 - a[:, 1]) / cell).astype(np.int64)
    ca = np.floor((a[:, 0] - task.x0) / cell).astype(np.int64)
    cx = task.x0 + (ca + 0.5) * cell
    cy = task.y0 - (ra + 0.5) * cell
    own = task.block.contains(np.column_stack([cx, cy]))
    keys_a, n_after = np.unique(np.column_stack([ra[own], ca[own]]), axis=0, return_counts=True)
    rb = np.floor((task.y0 - b[:, 1]) / cell).astype(np.int64)
    cb = np.floor((b[:, 0] - task.x0) / cell).astype(np.int64)
    kb, nbc = np.unique(np.column_stack([rb, cb]), axis=0, return_counts=True)
    nb_of = dict(zip(map(tuple, kb.tolist()), nbc.tolist()))
    n_before = np.array([nb_of.get(tuple(k), 0) for k in keys_a.tolist()], dtype=np.int64)
    few_a = n_after < minp
    few_b = ~few_a & (n_before < minp)
    counts = {
        "few_after_points": int(few_a.sum()),
        "few_before_points": int(few_b.sum()),
        "icp_failed": 0,
    }
    n_fit = int((~few_a & ~few_b).sum())
    if n_fit == 0 or len(b) == 0:
        return counts, None
    try:
        with _quiet_core():
            res = windowed_icp(
                b, a, origin_xy=task.origin_xy, sigma_scaling="formal", **task.icp_kw
            )
    except InputDataError as exc:
        log.debug("ICP block %s: %s", task.block.as_tuple(), exc)
        counts["icp_failed"] = n_fit
        return counts, None
    mine = task.block.contains(np.column_stack([res.x, res.y]))
    counts["icp_failed"] = n_fit - int(mine.sum())
    part = {k: getattr(res, k)[mine] for k in _per_cell(res)}
    return counts, part


def icp_tiled(
    before: TileCollection,
    after: TileCollection,
    *,
    cell_m: float,
    buffer_m: Optional[float] = None,
    coarse_to_fine: int = 0,
    sigma_scaling: str = "field",
    origin_xy: Optional[Tuple[float, float]] = None,
    selection: Selection = _ALL,
    tile_size_m: float = DEFAULT_TILE_SIZE_M,
    engine: Optional[Engine] = None,
    progress: Optional[ProgressCallback] = None,
    **icp_kw,
):
    """Windowed ICP of two tiled epochs, block by block of cells.

    Parameters
    ----------
    before, after : TileCollection
    cell_m, buffer_m, coarse_to_fine, sigma_scaling, origin_xy, **icp_kw
        As :func:`~slipmap.core.icp.windowed_icp` (``prealign`` is not accepted: it needs one
        global fit).
    tile_size_m : float
        Block edge (m), rounded to whole cells.

    Returns
    -------
    WindowedICPResult
        All cells of the whole run's lattice, in its order (row, then column).
    """
    from ..core.breaklines import given_breaklines
    from ..core.icp import WindowedICPResult, _apply_sigma_scaling, reblock

    if icp_kw.get("prealign"):
        raise InvalidParameterError("prealign is not available on tiled inputs")
    icp_kw.pop("prealign", None)
    spline = icp_kw.get("field_model", "cells") == "spline"
    icp_kw["field_model"] = "cells"  # the blocks fit the cells; the spline is fitted over them
    spline_kw = {
        "spacing_m": icp_kw.pop("spline_spacing_m", None),
        "smoothing": icp_kw.pop("spline_smoothing", None),
        "lines": given_breaklines(icp_kw.pop("breaklines", None)) if spline else None,
    }
    spline_kw["detect"] = bool(icp_kw.pop("detect_breaklines", False)) and spline
    spline_kw["cell_choice"] = bool(icp_kw.pop("cell_choice", False)) and spline
    cell = float(cell_m)
    if not (math.isfinite(cell) and cell > 0):
        raise InvalidParameterError(f"cell_m must be a positive number, got {cell_m!r}")
    buf = 0.5 * cell if buffer_m is None else float(buffer_m)
    levels = int(coarse_to_fine)
    ring = 3 + (DEFORM_HALO_CELLS if int(icp_kw.get("deform_passes") or 0) > 0 else 0)
    halo = (2**levels) * (buf + ring * cell)
    lo, hi = after.bounds
    ox, oy = (0.0, 0.0) if origin_xy is None else (float(origin_xy[0]), float(origin_xy[1]))
    x0 = ox + math.floor((lo[0] - ox) / cell) * cell
    y0 = oy + math.ceil((hi[1] - oy) / cell) * cell
    n_cols = int(math.floor((hi[0] - x0) / cell)) + 1
    n_rows = int(math.floor((y0 - lo[1]) / cell)) + 1

    def n_blocks(size: float) -> float:
        k = max(1, int(round(float(size) / cell)))
        return math.ceil(n_rows / k) * math.ceil(n_cols / k)

    check_grid_guards(
        [("before", before), ("after", after)], cell=cell, cell_key="cell_m",
        n_cells=float(n_rows) * n_cols, blocks=n_blocks, tile_size_m=tile_size_m,
        what="cell lattice", bytes_per_cell=ICP_LATTICE_BYTES, overlap=False,
    )  # fmt: skip
    if spline:  # the knots and the driver's memory, from the headers (issue #31)
        from ..core.icp_spline import check_spline_size, n_knots

        if spline_kw["spacing_m"] is None:
            spline_kw["spacing_m"] = 0.5 * cell
        h = float(spline_kw["spacing_m"])
        if not (math.isfinite(h) and h > 0):
            raise InvalidParameterError(f"spline_spacing_m must be > 0, got {h!r}")
        span = np.asarray(hi[:2], float) - np.asarray(lo[:2], float) + cell
        check_spline_size(span, h)
        check_spline_memory(n_knots(span, h), after.n_points)
    nb = max(1, int(round(float(tile_size_m) / cell)))
    kw = dict(icp_kw, cell_m=cell, buffer_m=buffer_m, coarse_to_fine=levels)
    tasks = []
    for r0, r1 in _spans(n_rows, nb):
        for c0, c1 in _spans(n_cols, nb):
            block = Region(x0 + c0 * cell, y0 - r1 * cell, x0 + c1 * cell, y0 - r0 * cell)
            # the lattice's rows are closed to the north, regions open: test with the halo
            ta = after.restricted(block, halo)
            if not len(ta) or not after.restricted(block, 1e-6 * cell):
                continue
            tb = before.restricted(block, halo)
            tasks.append(_IcpTask(tb, ta, block, halo, x0, y0, origin_xy, kw, selection))
    log.info(
        "windowed ICP on %d block(s) of %d x %d cells of %g m (halo %.1f m)",
        len(tasks), nb, nb, cell, halo,
    )  # fmt: skip
    results = _engine(engine).map(
        _icp_block,
        tasks,
        names=[f"ICP block at x {t.block.xmin:.1f}, y {t.block.ymin:.1f}" for t in tasks],
        progress=scaled(progress, 0.0, 0.5) if spline else progress,
        what="block",
    )
    skipped = {"few_after_points": 0, "few_before_points": 0, "icp_failed": 0}
    parts = []
    for counts, part in results:
        for k in skipped:
            skipped[k] += counts[k]
        if part is not None and len(part["x"]):
            parts.append(part)
    if not parts:
        why = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in skipped.items() if v)
        raise InputDataError(
            f"no cell could be registered: all {sum(skipped.values())} cells with points were "
            f"skipped ({why}); use a larger cell_m or a smaller min_points"
        )
    cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    row = np.rint((y0 - cols["y"]) / cell - 0.5).astype(np.int64)
    col = np.rint((cols["x"] - x0) / cell - 0.5).astype(np.int64)
    order = np.lexsort((col, row))
    cols = {k: v[order] for k, v in cols.items()}
    cols["row"], cols["col"] = row[order], col[order]
    names = {f.name for f in fields(WindowedICPResult)}
    res = WindowedICPResult(
        **{k: v for k, v in cols.items() if k in names},
        origin_xy=(float(x0), float(y0)),
        cell_m=cell,
        n_rows=n_rows,
        n_cols=n_cols,
        skipped=skipped,
        prealignment=None,
        seconds=0.0,
        cell_model=icp_kw.get("cell_model", "rigid"),
        deform_passes=int(icp_kw.get("deform_passes", 0)),
        # the tiles' block covariances (each tile's block size); the floor comes here
        sigma_model=icp_kw.get("sigma_model", "blocks"),
    )
    res = reblock(res)  # the block size over the whole field, as one run chooses it
    sigma_kw = dict(
        sigma_scaling=sigma_scaling,
        sigma_regions=icp_kw.get("sigma_regions", 3),
        sigma_region_by=icp_kw.get("sigma_region_by", "roughness"),
    )
    if spline:
        res = _icp_spline_tiled(
            res, tasks, engine=engine, progress=progress, lattice=(x0, y0, n_rows, n_cols, cell),
            buffer_m=buffer_m, spline_kw=spline_kw, sigma_kw=sigma_kw,
            icp_kw={k: v for k, v in icp_kw.items() if k not in sigma_kw},
        )  # fmt: skip
        return replace(res, seconds=0.0)
    res = _apply_sigma_scaling(res, **sigma_kw)
    return replace(res, seconds=0.0)


def _largest_motion(frame, c: np.ndarray, n_grid: int, xy: np.ndarray) -> float:
    """The largest motion (m) of the spline field with coefficients ``c`` (the grid's, then
    the knot copies') on ``frame`` at ``xy`` (the cell centres): a knot no point uses may
    stray further in an iteration without moving any point."""
    field = replace(
        frame, coefficients=c[:n_grid].reshape(frame.n_y + 3, frame.n_x + 3, 3),
        copy_coefficients=c[n_grid:] if len(c) > n_grid else None,
    )  # fmt: skip
    return float(np.max(np.linalg.norm(field(xy), axis=1), initial=0.0))


def _on_cells(k: int, at: np.ndarray, values, fill=np.nan) -> np.ndarray:
    """``values`` of the tiled cell pass's cells placed on the spline run's ``k`` cells."""
    v = np.asarray(values)
    out = np.full((k,) + v.shape[1:], fill, dtype=np.result_type(v, type(fill)))
    out[at] = v
    return out


def _candidate_lines(cells, d, usable, at, cells_res, lattice):
    """The breaklines the tiled cell pass's motions propose, to try in turn
    (:func:`~slipmap.core.icp.candidate_lines` on the values the one-file run reads: formal
    covariances, the cells' fitted gradients and the formal sigmas of their rotations)."""
    from ..core.icp import _rotation_scale, candidate_lines

    x0, y0, n_rows, n_cols, cell = lattice
    k = len(d)
    sig_rot = np.column_stack([cells_res.sigma_rx, cells_res.sigma_ry, cells_res.sigma_rz])
    if cells_res.sigma_model == "blocks" and cells_res.sigma_formal is not None:
        # the cells' rotation sigmas carry their block ratio (core.icp._rotation_scale)
        sig_rot = sig_rot / _rotation_scale(cells_res.cov_d, cells_res.sigma_formal)[:, None]
    grad = None if cells_res.gradient is None else _on_cells(k, at, cells_res.gradient)
    return candidate_lines(
        cells, d, usable, _on_cells(k, at, cells_res.cov_d_formal), (n_rows, n_cols, x0, y0, cell),
        grad=grad, sig_grad=_on_cells(k, at, sig_rot),
    )  # fmt: skip


def _cell_weights(cells, d, ok, converged, flagged, at, cells_res):
    """Each cell's data weight from the tiled cell pass's block covariances, as the one-file
    run makes it (:func:`~slipmap.core.icp_spline.cell_data_weights`): a callable of the
    field's rigid projection."""
    from ..core.icp import _choose_and_shrink
    from ..core.icp_spline import cell_data_weights

    k = len(d)
    u_res = np.asarray(cells_res.converged, bool) & ~np.asarray(cells_res.flagged, bool)
    _, cov_h = _choose_and_shrink(
        cells_res.cov_d_formal, cells_res.cov_d_blocks, cells_res.n_blocks, u_res
    )
    cov_hk, cov_fk = _on_cells(k, at, cov_h), _on_cells(k, at, cells_res.cov_d_formal)
    n_k = _on_cells(k, at, cells_res.n, fill=0)
    rmse_k = _on_cells(k, at, cells_res.rmse)

    def weights(projection):
        return cell_data_weights(
            cells.row, cells.col, d, cov_hk, cov_fk, n_k, projection=projection,
            usable=ok & converged & ~flagged, fitted=ok, rmse=rmse_k,
        )[0]  # fmt: skip

    return weights


#: bytes of the driver per point near candidate breaklines (coordinates, KD-tree, normals)
CORRIDOR_POINT_BYTES = 200.0


def _confirm_lines_tiled(field, straight, blocks, *, engine, gate_m, cell_m, again, progress):
    """Candidate breaklines (``field.lines``) confirmed and placed by the points near them, as
    the one-file run does (:func:`~slipmap.core.icp.confirm_lines`): each block returns its
    after-points within a cell of the lines and the epoch-1 points within reach of their
    targets and of the targets' normal neighbourhoods (a cell, two gates and a cell), each
    point from one block; the driver counts them first (refused, naming
    ``detect_breaklines``, when they would not fit), then confirms on them alone."""
    from ..core.icp import confirm_lines
    from .resources import _SHARE, available_bytes

    lines = field.lines
    reach_a = float(cell_m)
    reach_b = reach_a + 2.0 * float(gate_m) + float(cell_m)
    boxes = [b.block.grown(b.halo_m) for b in blocks]
    names = [f"breakline corridor at x {b.block.xmin:.1f}, y {b.block.ymin:.1f}" for b in blocks]

    def gather(count_only: bool):
        calls = [_SplineCall(b, "corridor", (lines, reach_a, reach_b, boxes[:i], count_only))
                 for i, b in enumerate(blocks)]  # fmt: skip
        return _engine(engine).map(
            _spline_block, calls, names=names, what="block", progress=progress
        )

    n = float(sum(gather(True)))
    need, avail = n * CORRIDOR_POINT_BYTES, available_bytes()
    if avail is not None and need > _SHARE * avail:
        from .options import OptionError

        raise OptionError(
            "detect_breaklines",
            f"the {n:.3g} points near the candidate breaklines need {need / 2**30:.1f} GiB, "
            f"more than the {_SHARE * avail / 2**30:.1f} GiB this machine can give them; give "
            "the breaklines instead, or turn the detection off",
        )
    parts = gather(False)
    a = np.concatenate([pa for pa, _ in parts]).reshape(-1, 3)
    b = np.concatenate([pb for _, pb in parts]).reshape(-1, 3)
    blk = blocks[0]
    tree, normals, _ = _matcher_of(b, blk.neighbours_k, blk.backend)
    log.info(
        "breaklines: %d after- and %d before-points near the candidates, from %d block(s)",
        len(a), len(b), len(blocks),
    )  # fmt: skip
    return confirm_lines(
        field, a, straight, before=b, tree=tree, normals=normals, gate_m=gate_m, cell_m=cell_m,
        again=again,
    )  # fmt: skip


# --------------------------------------------------------------------------- the jobs


def check_fields_tiled(opts, *, refused: Dict[str, str]) -> None:
    """Cross-option check of a field job (its JobSpec ``check``): the Dask options' check and,
    for tiled inputs or Dask runs, the options that need both epochs in one place, refused
    naming them (``refused``: option key -> what to do instead)."""
    from .tiled import check_scale, is_tiled

    check_scale(opts)
    if not is_tiled(opts, "before", "after"):
        return
    for key, why in refused.items():
        if opts.get(key):
            raise tiled_refusal(key, why)


def tiled_refusal(key: str, why: str):
    """The OptionError refusing option ``key`` for tiled inputs (``why``: what to do)."""
    from .options import OptionError

    return OptionError(key, f"is not available for tiled inputs or Dask runs: {why}")


def _tile(opts) -> float:
    return float(opts.get("tile_size_m") or DEFAULT_TILE_SIZE_M)


def _wkt(crs) -> Optional[str]:
    return None if crs is None else crs.to_wkt()


def _memory_check(bytes_per_cell: float, what: str):
    """A block's memory check, refusing a ``--tile-size`` whose blocks would not fit."""
    from .resources import check_grid_memory

    def check(n_cells):
        check_grid_memory("tile_size_m", n_cells, bytes_per_cell=bytes_per_cell, what=what)

    return check


def dem_for_job(opts, raster_path, *, bands, metadata, bytes_per_cell: float, progress=None):
    """The dem-diff job on tiled inputs: the raster (bands dz, z_before, z_after) written
    block by block as a COG at ``raster_path`` (None: not written). Returns
    ``(TiledDem, crs)``."""
    from ..core.io.raster import RasterBlockWriter
    from .tiled import engine_from

    before, after, selection = open_pair(opts)

    def writer(grid):
        if raster_path is None:
            return None
        return RasterBlockWriter(
            raster_path,
            (3, grid.n_rows, grid.n_cols),
            origin_xy=grid.origin_xy,
            pixel_size_m=grid.cell_m,
            crs_wkt=_wkt(before.crs),
            band_names=bands,
            metadata=metadata,
        )

    with engine_from(opts) as eng:
        res = dem_difference_tiled(
            before, after, cell_m=opts["grid_m"], writer_factory=writer, selection=selection,
            tile_size_m=_tile(opts), engine=eng, progress=progress,
            check_block=_memory_check(bytes_per_cell, "DEM block"),
        )  # fmt: skip
    return res, before.crs


def piv_for_job(opts, windows_px, *, bytes_per_cell: float, progress=None, breaklines_of=None):
    """The piv job on tiled inputs. Returns ``(PIVResult, Grid, crs)``. ``breaklines_of(crs)``
    gives the breaklines (default: the ``breaklines`` file reprojected to the epochs' CRS)."""
    from .fields import check_windows_fit, read_breaklines
    from .tiled import engine_from

    before, after, selection = open_pair(opts)
    check_windows_fit(windows_px, pair_grid(before, after, opts["grid_m"]))
    if breaklines_of is None:
        lines = read_breaklines(opts.get("breaklines"), before.crs)
    else:
        lines = breaklines_of(before.crs)
    with engine_from(opts) as eng:
        res, grid = piv_tiled(
            before, after, grid_m=opts["grid_m"], windows_px=windows_px,
            overlap=opts["overlap"], search_px=opts.get("search_px"),
            expected_max_displacement_m=opts.get("max_displacement_m"),
            snr_min=opts["snr_min"], median_threshold=opts["median_threshold"],
            breaklines=lines, vertical_compensation=bool(opts.get("vertical_compensation", True)),
            selection=selection, tile_size_m=_tile(opts), engine=eng,
            progress=progress,
            check_block=_memory_check(bytes_per_cell, "DEM block with its halo"),
        )  # fmt: skip
    return res, grid, before.crs


def icp_for_job(opts, core_kwargs: Dict[str, Any], *, progress=None, breaklines_of=None):
    """The icp job on tiled inputs (``core_kwargs``: the job's windowed_icp keywords;
    ``breaklines_of(crs)``: the given breaklines in the epochs' CRS, for the spline field).
    Returns ``(WindowedICPResult, crs)``."""
    from .tiled import engine_from

    before, after, selection = open_pair(opts)
    if breaklines_of is not None and core_kwargs.get("field_model") == "spline":
        core_kwargs = dict(core_kwargs, breaklines=breaklines_of(before.crs))
    with engine_from(opts) as eng:
        res = icp_tiled(
            before, after, selection=selection, tile_size_m=_tile(opts), engine=eng,
            progress=progress, **core_kwargs,
        )  # fmt: skip
    return res, before.crs


# --------------------------------------------------------------------------- the spline field

#: entries per knot of the penalised normal matrix (3 components x 7 x 7 neighbouring knots x
#: 3 components) and of its sparse LU factor per square root of the knots: SciPy's SuperLU
#: (COLAMD) on the lattice's pattern held 4 044 entries per knot at 3 969 knots and 7 893 at
#: 15 129 (measured 2026-11-27: 64 sqrt(K)); 12 bytes each (value and index)
SPLINE_MATRIX_ENTRIES = 430.0
SPLINE_LU_ENTRIES_PER_SQRT_KNOT = 64.0
#: bytes of the driver per after-point: the |v| of every paired point, gathered each
#: iteration for the robust weights' median (and its copies while sorting)
SPLINE_POINT_BYTES = 24.0
#: a process keeps its blocks' points, KD-tree and pairs between iterations up to this many
#: bytes (least recently used dropped first; a dropped block is read again: the same result)
SPLINE_CACHE_BYTES = 2 << 30
_CHUNKS: OrderedDict[tuple, Tuple[Any, float]] = OrderedDict()


@dataclass(frozen=True)
class _SplineBlock:
    """One block of a tiled spline fit: it owns the cells whose centres it holds and reads
    their points with the before-points ``halo_m`` around (the gate, the field's largest
    motion and the target normals' neighbourhoods)."""

    before: TileCollection
    after: TileCollection
    block: Region
    halo_m: float
    lattice: Tuple[float, float, int, int, float]  # x0, y0, n_rows, n_cols, cell_m
    buffer_m: float
    min_points: int
    max_points_per_cell: Optional[int]
    seed: int
    neighbours_k: int
    gate_m: float
    backend: str
    selection: Selection
    key: Tuple[str, int]  # (run token, block index): the process cache's key


@dataclass(frozen=True)
class _SplineCall:
    block: _SplineBlock
    stage: str  # "cells" or a SplineChunk method
    args: tuple = ()
    # the fit's knot frame (origin, spacing, n_x, n_y), breaklines, their gap (m) and its name
    frame: Optional[Tuple[Tuple[float, float], float, int, int, Any, float, str]] = None
    cell_index: Optional[np.ndarray] = None  # the run's index of each of the block's cells


def _spline_cells_of(blk: _SplineBlock):
    """The block's points and the cells it owns (as the one-file run selects them)."""
    from ..core.icp import select_cells

    box = blk.block.grown(blk.halo_m)
    b = _read(blk.before, box, blk.selection)
    a = _read(blk.after, box, blk.selection)
    x0, y0, n_rows, n_cols, cell = blk.lattice
    cells, skipped, uk, _ = select_cells(
        a, b, x0=x0, y0=y0, n_rows=n_rows, n_cols=n_cols, cell_m=cell, buffer_m=blk.buffer_m,
        min_points=blk.min_points, max_points_per_cell=blk.max_points_per_cell, seed=blk.seed,
        owned=blk.block.contains,
    )  # fmt: skip
    return cells, skipped, a, b


def _spline_survey(blk: _SplineBlock):
    """The cells a block owns (lattice keys, centres, counts) and the extent of their points."""
    from ..core.icp import _cell_index

    cells, _, a, b = _spline_cells_of(blk)
    _keep(blk.key + ("cells",), (cells, a, b), 64.0 * len(a) + 24.0 * len(b))  # for the fit
    x0, y0, n_rows, n_cols, cell = blk.lattice
    ra, ca = _cell_index(a, x0, y0, cell)
    cx, cy = x0 + (ca + 0.5) * cell, y0 - (ra + 0.5) * cell
    own = blk.block.contains(np.column_stack([cx, cy]))
    _, full = np.unique(ra[own] * n_cols + ca[own], return_counts=True)
    pts = a[cells.points, :2]
    return {
        "keys": cells.row * n_cols + cells.col,
        "centres": cells.centres,
        "n_after": cells.n_after,
        "n_before": cells.n_before,
        "lo": pts.min(axis=0) if len(pts) else np.full(2, np.inf),
        "hi": pts.max(axis=0) if len(pts) else np.full(2, -np.inf),
        "full": int(np.sum(full >= blk.min_points)),
    }


def _matcher_of(b: np.ndarray, neighbours_k: int, backend: str):
    """The one-file run's nearest-plane objects over epoch-1 points ``b``: their KD-tree
    (queried with map coordinates), lazily computed normals and the compiled matcher's grid
    (None: numpy)."""
    from scipy.spatial import cKDTree

    from ..core.icp import _NormalCache, _OffsetTree, _target_grid

    off = b.mean(axis=0) if len(b) else np.zeros(3)
    tree = _OffsetTree(cKDTree(b - off), off)
    normals = _NormalCache(b, tree.tree, neighbours_k, offset=off)
    grid = _target_grid(b, backend) if len(b) else None
    if grid is not None and neighbours_k <= grid.MAX_NORMAL_K:
        normals.device = grid
    return tree, normals, grid


def _block_data(blk: _SplineBlock):
    """The block's cells, points and matcher ``(cells, a, b, tree, normals, grid)``, from this
    process's cache or read and built (the survey's read of this block, when it is here)."""
    key = blk.key + ("data",)
    hit = _CHUNKS.get(key)
    if hit is not None:
        _CHUNKS.move_to_end(key)
        return hit[0]
    read = _CHUNKS.pop(blk.key + ("cells",), None)
    if read is not None:  # the survey's read of this block, in this process
        cells, a, b = read[0]
    else:
        cells, _, a, b = _spline_cells_of(blk)
    data = (cells, a, b) + _matcher_of(b, blk.neighbours_k, blk.backend)
    _keep(key, data, 64.0 * len(a) + 150.0 * len(b))
    return data


def _spline_chunk(call: _SplineCall):
    """The block's :class:`~slipmap.core.icp_spline.SplineChunk` of one fit (its knot frame,
    breaklines and gap), from this process's cache or built on :func:`_block_data` (the
    one-file run's objects over the block). A detected-breakline run fits twice: a block
    keeps one fit's chunk at a time."""
    from ..core.icp_spline import SplineChunk, SplineField

    blk = call.block
    origin, h, n_x, n_y, lines, gap_m, fit = call.frame
    key = blk.key + ("chunk", fit)
    hit = _CHUNKS.get(key)
    if hit is not None:
        _CHUNKS.move_to_end(key)
        return hit[0]
    for k in [k for k in _CHUNKS if k[:2] == blk.key and k[2:3] == ("chunk",)]:
        del _CHUNKS[k]  # the block's chunk of an earlier fit
    cells, a, b, tree, normals, grid = _block_data(blk)
    frame = SplineField(origin, h, n_x, n_y, np.zeros((n_y + 3, n_x + 3, 3)), lines=lines)
    chunk = SplineChunk(
        a[cells.points], frame=frame, before=b, tree=tree, normals=normals,
        gate_m=blk.gate_m, seg=np.asarray(call.cell_index)[cells.seg], grid=grid,
        breakline_gap_m=gap_m,
    )  # fmt: skip
    _keep(key, chunk, 400.0 * len(chunk))
    return chunk


def _spline_corridor(call: _SplineCall):
    """The block's points around candidate breaklines, for the driver to confirm and place
    them (:func:`~slipmap.core.icp.confirm_lines`): its cells' after-points (the sample the
    fit uses) within ``reach_after_m`` of the lines, and the epoch-1 points within
    ``reach_before_m`` that no live block before it in ``boxes`` read (so each point comes
    once). ``count_only``: their number alone."""
    from ..core.breaklines import distance_m

    lines, reach_after_m, reach_before_m, boxes, count_only = call.args
    cells, a, b = _block_data(call.block)[:3]
    pa = a[cells.points]
    pa = pa[distance_m(pa, lines) < reach_after_m]
    mine = distance_m(b, lines) < reach_before_m
    for box in boxes:  # the live blocks before this one: their reads own these points
        mine &= ~box.contains(b)
    if count_only:
        return len(pa) + int(mine.sum())
    return pa, b[mine]


def _spline_choice(call: _SplineCall):
    """The block's cells' costs under the fitted field and under their own motion
    (:func:`~slipmap.core.icp_choice.choice_costs` on the one-file run's objects; ``args``:
    the field and the cell pass's ``d`` (K, 3) and gradient (K, 3, 3) on the run's cells).
    Returns the run's index of each of the block's cells and their
    :class:`~slipmap.core.icp_choice.ChoiceCosts`."""
    from ..core.icp_choice import choice_costs

    field, d, grad = call.args
    cells, a, b, tree, normals, _ = _block_data(call.block)
    idx = np.asarray(call.cell_index)
    costs = choice_costs(
        a[cells.points], cells.seg, len(idx), cells.centres, field, d[idx], grad[idx],
        cell_m=call.block.lattice[4], tree=tree, normals=normals, gate=call.block.gate_m,
        n_targets=len(b),
    )  # fmt: skip
    return idx, costs


def _keep(key, value, size: float) -> None:
    """Keep ``value`` in this process's cache of spline blocks (an earlier run's entries and
    the least recently used dropped to stay within :data:`SPLINE_CACHE_BYTES`)."""
    for k in [k for k in _CHUNKS if k[0] != key[0]]:  # an earlier run's blocks
        del _CHUNKS[k]
    while _CHUNKS and sum(v[1] for v in _CHUNKS.values()) + size > SPLINE_CACHE_BYTES:
        _CHUNKS.popitem(last=False)
    if size <= SPLINE_CACHE_BYTES:
        _CHUNKS[key] = (value, size)


def _spline_block(call: _SplineCall):
    """One stage of a tiled spline fit on one block (see :func:`_icp_spline_tiled`)."""
    with _quiet_core():
        if call.stage == "cells":
            return _spline_survey(call.block)
        if call.stage == "corridor":
            return _spline_corridor(call)
        if call.stage == "choice":
            return _spline_choice(call)
        chunk = _spline_chunk(call)
        return getattr(chunk, call.stage)(*call.args)


def _drop_chunks(token: str) -> None:
    for k in [k for k in _CHUNKS if k[0] == token]:
        del _CHUNKS[k]


def check_spline_memory(n_knots: float, n_points: float) -> None:
    """A tiled spline field's driver memory from the headers (knots, after-points), before
    anything is read: the normal matrix twice (the blocks' shares in flight and their sum),
    its LU factor and the residuals of every point; refused naming ``spline_spacing_m``."""
    from .resources import check_grid_memory

    k = max(float(n_knots), 1.0)
    entries = 2.0 * SPLINE_MATRIX_ENTRIES + SPLINE_LU_ENTRIES_PER_SQRT_KNOT * math.sqrt(k)
    per_knot = 12.0 * entries + SPLINE_POINT_BYTES * float(n_points) / k
    check_grid_memory(
        "spline_spacing_m", k, bytes_per_cell=per_knot,
        what="spline field (its normal equations, their factor and every point's residual)",
    )  # fmt: skip


def _icp_spline_tiled(
    cells_res, tasks: List[_IcpTask], *, engine, progress, lattice, buffer_m, spline_kw,
    sigma_kw, icp_kw,
):  # fmt: skip
    """The spline field of a tiled run: the cells' motions (``cells_res``, the tiled cell
    pass) start one B-spline field fitted over every block's points; each Gauss-Newton
    iteration adds the blocks' shares of the normal equations
    (:func:`~slipmap.core.icp_spline.fit_spline_chunks`), so the field, and every value the
    cells report, are the one-file run's."""
    import uuid

    from ..core.icp import (
        DETECTED_GAP_CELLS,
        _Cells,
        _deformation_field,
        _near_pairs,
        _options,
        _spline_blocks,
        finish_cells,
        spline_cells,
        take_own_fits,
        try_candidates,
    )
    from ..core.icp_choice import ChoiceCosts, choose_cells, no_worse
    from ..core.icp_spline import MIN_SPLINE_CELLS, SplineCellsError, fit_spline_chunks, knot_frame

    x0, y0, n_rows, n_cols, cell = lattice
    kw = dict(icp_kw)
    minp = int(kw.pop("min_points", 100))
    mpc = kw.pop("max_points_per_cell", None)
    seed = int(kw.pop("seed", 0))
    med_thr = float(kw.pop("median_threshold", 2.0))
    med_eps = float(kw.pop("median_eps_m", 0.02))
    backend = kw.pop("backend", "numpy")
    option_keys = ("max_iterations", "tolerance_m", "tolerance_rad", "max_correspondence_m",
                   "trim_fraction", "robust", "neighbours_k", "tolerance_sigma")  # fmt: skip
    o_kw = {k: kw[k] for k in option_keys if k in kw}
    buf = 0.5 * cell if buffer_m is None else float(buffer_m)
    if "max_correspondence_m" not in o_kw and buf > 0:
        o_kw["max_correspondence_m"] = buf
    opts = _options(**o_kw)
    gate = math.inf if opts.max_correspondence_m is None else opts.max_correspondence_m
    reach = gate if math.isfinite(gate) else buf
    # a point moves by less than the gate (else it pairs with nothing): its target lies within
    # two gates of its cell, the target's normal neighbourhood (k nearest points) within a
    # cell more (a cell holds min_points or more)
    halo = 2.0 * reach + cell
    token = uuid.uuid4().hex
    blocks = [
        _SplineBlock(
            t.before.restricted(t.block, halo),
            t.after.restricted(t.block, halo),
            t.block,
            halo,
            lattice,
            buf,
            minp,
            mpc,
            seed,
            opts.neighbours_k,
            gate,
            backend,
            t.selection,
            (token, i),
        )  # fmt: skip
        for i, t in enumerate(tasks)
    ]
    state = {"f": 0.0}

    def cancel_only(_fraction, message):  # the engine's per-block ticks: cancel between them
        report(progress, state["f"], message)

    def outer(fraction, message):
        state["f"] = fraction
        report(progress, fraction, message)

    outer(0.5, "spline field: the cells of every block")
    survey = _engine(engine).map(
        _spline_block, [_SplineCall(b, "cells") for b in blocks],
        names=[f"spline block at x {b.block.xmin:.1f}, y {b.block.ymin:.1f}" for b in blocks],
        progress=cancel_only if progress is not None else None, what="block",
    )  # fmt: skip
    full = sum(s["full"] for s in survey)
    if full < MIN_SPLINE_CELLS:
        raise SplineCellsError(
            f"{full} cell(s) of {cell:g} m hold {minp} points or more; a spline field needs "
            f"{MIN_SPLINE_CELLS} at least",
            cells=full,
        )
    keys = np.concatenate([s["keys"] for s in survey]).astype(np.int64)
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    row, col = np.divmod(keys, n_cols)
    k = len(keys)
    cells = _Cells(
        points=np.zeros(0, dtype=np.int64), seg=np.zeros(0, dtype=np.int64),
        centres=np.concatenate([s["centres"] for s in survey]).reshape(-1, 3)[order],
        boxes=np.zeros((k, 4)), row=row, col=col,
        n_after=np.concatenate([s["n_after"] for s in survey])[order],
        n_before=np.concatenate([s["n_before"] for s in survey])[order],
    )  # fmt: skip
    # the cell pass's values on these cells (the cells it could not fit are not ok)
    done = (cells_res.row * n_cols + cells_res.col).astype(np.int64)
    at = np.searchsorted(keys, done)
    if not (np.all(at < k) and np.array_equal(keys[np.minimum(at, k - 1)], done)):
        raise InputDataError("the tiled cell pass and the spline blocks disagree on the cells")
    ok = _on_cells(k, at, np.ones(len(at), dtype=bool), fill=False)
    d = _on_cells(k, at, np.column_stack([cells_res.dx, cells_res.dy, cells_res.dz]))
    iterations = _on_cells(k, at, np.asarray(cells_res.iterations, dtype=np.int64), fill=0)
    converged = _on_cells(k, at, np.asarray(cells_res.converged, dtype=bool), fill=False)
    flagged_c = _on_cells(k, at, np.asarray(cells_res.flagged, dtype=bool), fill=False)
    blocks_model = kw.pop("sigma_model", "blocks")
    block_m = cells_res.sigma_block_m if blocks_model == "blocks" else math.nan
    usable = ok & np.all(np.isfinite(d), axis=1)
    start, _ = _deformation_field(cells, d, usable, n_rows, n_cols, x0, y0, cell)
    near = _near_pairs(cells.row, cells.col, reach=2)
    lo = np.min([s["lo"] for s in survey], axis=0)
    hi = np.max([s["hi"] for s in survey], axis=0)
    h = spline_kw["spacing_m"]
    lines = spline_kw.get("lines")  # given breaklines
    lines_source = "none" if lines is None else "given"
    live = [i for i, s in enumerate(survey) if len(s["keys"])]
    index_of = {i: np.searchsorted(keys, survey[i]["keys"]) for i in live}
    names = [f"spline block at x {blocks[i].block.xmin:.1f}, y {blocks[i].block.ymin:.1f}"
             for i in live]  # fmt: skip
    warned = []

    def fitter(fit_lines, gap_m: float, name: str):
        """The knot frame with ``fit_lines`` and the chunk runner of one fit."""
        frame = knot_frame(lo, hi, cells.centres[:, :2], h, lines=fit_lines)
        frame_t = (frame.origin_xy, frame.spacing_m, frame.n_x, frame.n_y, fit_lines,
                   float(gap_m), name)  # fmt: skip

        n_grid = (frame.n_x + 3) * (frame.n_y + 3)

        def run(stage, *args):
            # every new set of coefficients goes through "residuals" first: checked there once
            if (
                stage == "residuals"
                and not warned
                and _largest_motion(frame, np.asarray(args[0]), n_grid, cells.centres[:, :2])
                > reach
            ):
                warned.append(True)
                log.warning(
                    "the spline field moves by more than the %.2f m gate somewhere: tiled "
                    "blocks may differ from the one-file run at their edges; give a larger "
                    "buffer_m", reach,
                )  # fmt: skip
            calls = [_SplineCall(blocks[i], stage, args, frame_t, index_of[i]) for i in live]
            return _engine(engine).map(
                _spline_block, calls, names=names, what="block",
                progress=cancel_only if progress is not None else None,
            )  # fmt: skip

        return frame, run

    log.info(
        "spline field on %d block(s): %d cells, knots %g m apart (halo %.1f m)",
        len(live), k, h, halo,
    )  # fmt: skip
    fit_kw = dict(
        report_xy=cells.centres[:, :2], report_pairs=near, smoothing=spline_kw["smoothing"],
        gate_m=gate, opts=opts,
    )  # fmt: skip
    pg = outer if progress is not None else None
    try:
        first, span = None, (0.55, 1.0)
        if lines is None and spline_kw.get("detect"):
            tries = _candidate_lines(cells, d, usable & ~flagged_c, at, cells_res, lattice)

            def fit(candidate):  # as the one-file run: fit, confirm, refit
                frame, run = fitter(candidate, 0.0, "candidate")
                return fit_spline_chunks(
                    run, frame=frame, initial=start, progress=scaled(pg, 0.55, 0.75),
                    defer_report=True, **fit_kw,
                )  # fmt: skip

            def confirm(field, straight, again):
                outer(0.75, "breaklines: the points near the candidates")
                return _confirm_lines_tiled(
                    field, straight, [blocks[i] for i in live], engine=engine, gate_m=gate,
                    cell_m=cell, again=again, progress=cancel_only if progress else None,
                )  # fmt: skip

            lines, first = try_candidates(tries, fit, confirm)
            if tries:
                lines_source = "none" if lines is None else "detected"
                span = (0.8, 1.0)
        weights = None
        if math.isfinite(block_m) and cells_res.cov_d_blocks is not None:
            # each cell's data weighed by its independent share, as the one-file run
            weights = _cell_weights(cells, d, ok, converged, flagged_c, at, cells_res)
        start_kw = dict(initial=start)
        if first is not None:  # the refit starts where the candidate's fit ended
            start_kw = dict(initial=first.field, smoothing_start=first.smoothing_estimate)
        gap = DETECTED_GAP_CELLS * cell if lines_source == "detected" else 0.0
        frame, run = fitter(lines, gap, "final")
        sfit = fit_spline_chunks(
            run, frame=frame, progress=scaled(pg, *span),
            block_m=float(block_m) if math.isfinite(block_m) else None, cell_weight=weights,
            **start_kw, **fit_kw,
        )  # fmt: skip
        # each cell's points choose between the field and the cell's own fit (icp_choice)
        own_grad = (
            np.full((k, 3, 3), np.nan) if cells_res.gradient is None
            else _on_cells(k, at, cells_res.gradient)
        )  # fmt: skip
        costs = ChoiceCosts.empty(k)
        if spline_kw.get("cell_choice"):
            for idx, part in _engine(engine).map(
                _spline_block,
                [_SplineCall(blocks[i], "choice", (sfit.field, d, own_grad), None, index_of[i])
                 for i in live],
                names=names, what="block",
                progress=cancel_only if progress is not None else None,
            ):  # fmt: skip
                costs.put(idx, part)
    finally:
        _drop_chunks(token)
    # the block covariances and the cells' floor share, as the one-file run (core.icp)
    c_ok = np.asarray(cells_res.converged, dtype=bool) & ~np.asarray(cells_res.flagged, bool)
    c_all = np.ones(len(cells_res.x), dtype=bool)
    sfit, blocks_kw = _spline_blocks(
        sfit, ok & converged & ~flagged_c & (sfit.n >= minp), near,
        dict(sigma_model=blocks_model, sigma_block_m=cells_res.sigma_block_m,
             sigma_block_ratio=math.nan),
        sigma_scaling=sigma_kw["sigma_scaling"],
        cells=(cells_res.row, cells_res.col,
               np.column_stack([cells_res.dx, cells_res.dy, cells_res.dz]), cells_res.cov_d,
               cells_res.n, c_all, c_ok, cells_res.cov_d_formal, cells.row, cells.col),
    )  # fmt: skip
    sp = spline_cells(sfit, cells, ok, min_points=minp, median_threshold=med_thr,
                      median_eps_m=med_eps, n_rows=n_rows, n_cols=n_cols)  # fmt: skip
    n_own = _on_cells(k, at, cells_res.n, fill=0)
    own = dict(
        d=d, grad=own_grad, cov_d=_on_cells(k, at, cells_res.cov_d),
        rmse=_on_cells(k, at, cells_res.rmse), n=n_own, sigma0=_on_cells(k, at, cells_res.sigma0),
        sig_rot=_on_cells(
            k, at, np.column_stack([cells_res.sigma_rx, cells_res.sigma_ry, cells_res.sigma_rz])
        ),
    )  # fmt: skip
    fitted = ok & converged & (n_own >= minp)
    take, level = choose_cells(costs, fitted), no_worse(costs, fitted)
    sp, blocks_kw, pair_cov = take_own_fits(
        sp, take, own, blocks_kw, sfit.pair_cov, near, cells=cells,
        floor_cells=(cells_res.row, cells_res.col,
                     np.column_stack([cells_res.dx, cells_res.dy, cells_res.dz]),
                     cells_res.cov_d, cells_res.n, c_all, c_ok),
        flag_kw=dict(n_rows=n_rows, n_cols=n_cols, eps_m=med_eps, threshold=med_thr),
        unexplained=costs.unexplained, no_worse=level,
    )  # fmt: skip
    return finish_cells(
        cells, ok=sp["ok"], d=sp["d"], cov_d=sp["cov_d"], grad=sp["grad"], rot=None,
        sig_rot=sp["sig_rot"], rmse=sp["rmse"], sigma0=sp["sigma0"], n_used=sp["n"],
        iterations=iterations, converged=converged, flagged=sp["flagged"],
        skipped=cells_res.skipped, min_points=minp, max_iterations=opts.max_iterations,
        origin_xy=(float(x0), float(y0)), cell_m=cell, n_rows=n_rows, n_cols=n_cols,
        prealignment=None, t_start=0.0, cell_model=cells_res.cell_model,
        deform_passes=cells_res.deform_passes, field_model="spline", near=near,
        pair_cov=pair_cov, lines=lines, lines_source=lines_source, from_cell=sp["from_cell"],
        **sigma_kw, **blocks_kw,
    )  # fmt: skip
