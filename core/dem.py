"""Gridding point clouds into elevation rasters (DEMs) and differencing two DEMs.

A :class:`Grid` is a north-up raster: row 0 is the northern-most row, column 0 the western-most
column, cells are squares of side ``cell_m``. Cell ``(i, j)`` covers
``x_min + j * cell_m <= x < x_min + (j + 1) * cell_m`` and
``y_max - (i + 1) * cell_m < y <= y_max - i * cell_m``; its centre is
``(x_min + (j + 0.5) * cell_m, y_max - (i + 0.5) * cell_m)``.

:func:`grid_elevation` averages the z values of the points falling into each cell (step 1 of
the PIV workflow of Aryal, section 3.2.1: "each grid-value contains average z-values ...
gridding should be done without data extrapolation"); empty cells are NaN. It is one
``np.bincount`` over flat cell indices, with z taken relative to a reference elevation before
summing so that sums of large elevations keep full precision.

:func:`dem_difference` grids two epochs on one common grid and returns ``after - before``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from .errors import InputDataError, InvalidParameterError

log = logging.getLogger(__name__)

__all__ = [
    "DemDifference",
    "GriddedElevation",
    "Grid",
    "common_grid",
    "dem_difference",
    "grid_elevation",
    "grid_points",
    "grid_for_bounds",
]


def _check_cell(cell_m: float, name: str = "cell_m") -> float:
    try:
        c = float(cell_m)
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"{name} must be a positive number of metres, got {cell_m!r}"
        ) from None
    if not math.isfinite(c) or c <= 0.0:
        raise InvalidParameterError(
            f"{name} must be a positive, finite number of metres (e.g. 0.25), got {cell_m!r}"
        )
    return c


@dataclass(frozen=True)
class Grid:
    """A north-up raster grid (row 0 = north).

    Attributes
    ----------
    x_min : float
        West edge of column 0 (map units, m).
    y_max : float
        North edge of row 0 (map units, m).
    cell_m : float
        Cell side (m).
    n_rows, n_cols : int
        Raster shape.
    """

    x_min: float
    y_max: float
    cell_m: float
    n_rows: int
    n_cols: int

    def __post_init__(self) -> None:
        _check_cell(self.cell_m)
        if int(self.n_rows) < 1 or int(self.n_cols) < 1:
            raise InvalidParameterError(
                f"Grid needs n_rows >= 1 and n_cols >= 1, got ({self.n_rows}, {self.n_cols})"
            )
        if not (math.isfinite(self.x_min) and math.isfinite(self.y_max)):
            raise InvalidParameterError("Grid x_min and y_max must be finite numbers")

    @property
    def origin_xy(self) -> Tuple[float, float]:
        """Upper-left corner ``(x_min, y_max)`` (m)."""
        return (float(self.x_min), float(self.y_max))

    @property
    def shape(self) -> Tuple[int, int]:
        """``(n_rows, n_cols)``."""
        return (int(self.n_rows), int(self.n_cols))

    @property
    def x_max(self) -> float:
        """East edge of the last column (m)."""
        return float(self.x_min + self.n_cols * self.cell_m)

    @property
    def y_min(self) -> float:
        """South edge of the last row (m)."""
        return float(self.y_max - self.n_rows * self.cell_m)

    def centres(self) -> Tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates.

        Returns
        -------
        x : (n_cols,) float64
            Increasing x of the column centres (m).
        y : (n_rows,) float64
            Decreasing y of the row centres (m).
        """
        x = self.x_min + (np.arange(self.n_cols, dtype=np.float64) + 0.5) * self.cell_m
        y = self.y_max - (np.arange(self.n_rows, dtype=np.float64) + 0.5) * self.cell_m
        return x, y

    def index(self, xy: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Cell indices of points.

        Parameters
        ----------
        xy : (N, >=2) array_like
            Map coordinates (m); only the first two columns are used.

        Returns
        -------
        rows, cols : (N,) int64
            Cell row and column; both are -1 for points outside the grid (or with non-finite
            coordinates).
        """
        a = np.asarray(xy, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] < 2:
            raise InvalidParameterError(f"xy must have shape (N, 2) or (N, 3), got {a.shape}")
        with np.errstate(invalid="ignore"):
            fc = np.floor((a[:, 0] - self.x_min) / self.cell_m)
            fr = np.floor((self.y_max - a[:, 1]) / self.cell_m)
            inside = (fc >= 0) & (fc < self.n_cols) & (fr >= 0) & (fr < self.n_rows)
        rows = np.where(inside, fr, -1).astype(np.int64)
        cols = np.where(inside, fc, -1).astype(np.int64)
        return rows, cols

    def window(self, row0: int, col0: int, n_rows: int, n_cols: int) -> Grid:
        """The sub-grid of ``n_rows`` x ``n_cols`` cells whose first cell is
        ``(row0, col0)`` of this grid (it may reach outside this grid)."""
        return Grid(
            x_min=float(self.x_min + int(col0) * self.cell_m),
            y_max=float(self.y_max - int(row0) * self.cell_m),
            cell_m=self.cell_m,
            n_rows=int(n_rows),
            n_cols=int(n_cols),
        )

    def xy_of(self, rows, cols) -> Tuple[np.ndarray, np.ndarray]:
        """Map coordinates of (possibly fractional) cell positions.

        Parameters
        ----------
        rows, cols : array_like (same shape)
            Row and column positions; integer values are cell centres, fractions are sub-cell
            positions (``rows = 0.5`` is the boundary between rows 0 and 1).

        Returns
        -------
        x, y : float64 arrays of the broadcast shape (m).
        """
        r = np.asarray(rows, dtype=np.float64)
        c = np.asarray(cols, dtype=np.float64)
        x = self.x_min + (c + 0.5) * self.cell_m
        y = self.y_max - (r + 0.5) * self.cell_m
        return x, y


def _as_points(points, name: str) -> np.ndarray:
    a = np.asarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputDataError(f"{name} must be an (N, 3) array of x, y, z; got shape {a.shape}")
    if a.shape[0] == 0:
        raise InputDataError(f"{name} is empty: give at least one point")
    if not np.isfinite(a).all():
        raise InputDataError(
            f"{name} has NaN or infinite coordinates: remove those points before gridding"
        )
    return a


def common_grid(*point_sets, cell_m: float, overlap: str = "intersection") -> Grid:
    """A grid covering the XY extent shared by (or the union of) several point sets.

    The edges are multiples of ``cell_m`` (so grids of different data sets with the same cell
    size line up), and every point of the covered extent falls inside the grid.

    Parameters
    ----------
    *point_sets : (N_k, 3) float64 arrays
        Point clouds (m).
    cell_m : float
        Cell side (m), > 0.
    overlap : {"intersection", "union"}
        Cover the XY bounding-box intersection of all sets, or their union.

    Returns
    -------
    Grid

    Raises
    ------
    InvalidParameterError
        Bad ``cell_m`` or ``overlap``, or no point set given.
    InputDataError
        Empty/non-finite point sets, or bounding boxes that do not overlap.
    """
    c = _check_cell(cell_m)
    if overlap not in ("intersection", "union"):
        raise InvalidParameterError(f"overlap must be 'intersection' or 'union', got {overlap!r}")
    if not point_sets:
        raise InvalidParameterError("common_grid needs at least one point set")
    mins = []
    maxs = []
    for k, p in enumerate(point_sets):
        a = _as_points(p, f"point set {k}")
        mins.append(a[:, :2].min(axis=0))
        maxs.append(a[:, :2].max(axis=0))
    mins_a = np.array(mins)
    maxs_a = np.array(maxs)
    if overlap == "intersection":
        lo = mins_a.max(axis=0)
        hi = maxs_a.min(axis=0)
        if np.any(hi < lo):
            raise InputDataError(
                "the point sets do not overlap in XY (bounding boxes are disjoint): check that "
                "they are in the same CRS, or use overlap='union'"
            )
    else:
        lo = mins_a.min(axis=0)
        hi = maxs_a.max(axis=0)
    return grid_for_bounds(lo, hi, cell_m=c)


def grid_for_bounds(lo, hi, *, cell_m: float) -> Grid:
    """The grid :func:`common_grid` gives for the XY box ``lo``..``hi`` (edges on multiples of
    ``cell_m``; a point on the box falls inside). Used where only the bounds are known (the
    headers of a tiled survey), so that a tiled run grids on the whole-cloud run's grid.

    Parameters
    ----------
    lo, hi : (2,) float
        South-west and north-east corners (m), ``lo <= hi``.
    cell_m : float
        Cell side (m).
    """
    c = _check_cell(cell_m)
    lo = np.asarray(lo, dtype=np.float64)[:2]
    hi = np.asarray(hi, dtype=np.float64)[:2]
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.any(hi < lo):
        raise InputDataError(f"grid bounds must be finite with lo <= hi, got {lo} .. {hi}")
    x_min = math.floor(lo[0] / c) * c
    if x_min > lo[0]:  # rounding
        x_min -= c
    y_max = math.ceil(hi[1] / c) * c
    if y_max < hi[1]:
        y_max += c
    n_cols = int(math.floor((hi[0] - x_min) / c)) + 1
    n_rows = int(math.floor((y_max - lo[1]) / c)) + 1
    # the last column/row can be empty when hi sits exactly on an edge; keep it (harmless)
    return Grid(x_min=float(x_min), y_max=float(y_max), cell_m=c, n_rows=n_rows, n_cols=n_cols)


@dataclass(frozen=True)
class GriddedElevation:
    """Mean elevation per cell and number of points per cell.

    Attributes
    ----------
    grid : Grid
    z : (n_rows, n_cols) float64
        Mean z of the points in each cell (m); NaN where empty.
    count : (n_rows, n_cols) int64
        Number of points per cell.
    """

    grid: Grid
    z: np.ndarray
    count: np.ndarray


def grid_points(
    points, *, grid: Grid, window: Optional[Tuple[int, int, int, int]] = None
) -> GriddedElevation:
    """Mean z and point count per cell (no extrapolation, empty cells NaN).

    Parameters
    ----------
    points : (N, 3) float64
        Points (m). Points outside ``grid`` (or ``window``) are ignored.
    grid : Grid
    window : (row0, col0, n_rows, n_cols), optional
        Grid only this window of ``grid`` (the result's grid is ``grid.window(...)``). The
        points are indexed on ``grid`` itself, so a block of a tiled run gets exactly the
        cells of the whole-grid run (a sub-grid's own origin could round a point on an edge
        into the other cell).

    Returns
    -------
    GriddedElevation
    """
    a = _as_points(points, "points")
    rows, cols = grid.index(a)
    if window is not None:
        r0, c0, nr, nc = (int(v) for v in window)
        grid = grid.window(r0, c0, nr, nc)
        rows, cols = rows - r0, cols - c0
        keep = (rows >= 0) & (rows < nr) & (cols >= 0) & (cols < nc)
        rows = np.where(keep, rows, -1)
    inside = rows >= 0
    flat = rows[inside] * grid.n_cols + cols[inside]
    z = a[inside, 2]
    n = grid.n_rows * grid.n_cols
    z_ref = float(z[0]) if z.size else 0.0
    count = np.bincount(flat, minlength=n)
    sums = np.bincount(flat, weights=z - z_ref, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = sums / count + z_ref
    mean[count == 0] = np.nan
    if not z.size and window is None:  # a block of a larger grid may be empty
        log.warning("no point falls inside the grid: the elevation raster is all NaN")
    return GriddedElevation(
        grid=grid,
        z=mean.reshape(grid.shape),
        count=count.astype(np.int64).reshape(grid.shape),
    )


def grid_elevation(points, *, grid: Grid) -> np.ndarray:
    """Mean z per cell of ``grid`` (m); ``(n_rows, n_cols)`` float64, NaN where empty.

    See :func:`grid_points` for the point counts as well.
    """
    return grid_points(points, grid=grid).z


@dataclass(frozen=True)
class DemDifference:
    """Two DEMs on one grid and their difference.

    Attributes
    ----------
    grid : Grid
    z_before, z_after : (n_rows, n_cols) float64
        Mean elevations (m), NaN where empty.
    dz : (n_rows, n_cols) float64
        ``z_after - z_before`` (m); NaN where either is empty.
    mean_m, std_m : float
        Mean and (population) standard deviation of the finite ``dz`` (NaN if none).
    n_valid : int
        Number of finite ``dz`` cells.
    """

    grid: Grid
    z_before: np.ndarray
    z_after: np.ndarray
    dz: np.ndarray
    mean_m: float
    std_m: float
    n_valid: int


def dem_difference(before, after, *, cell_m: float | None = None, grid: Grid | None = None):
    """Grid two epochs on one grid and difference them (``after - before``).

    Parameters
    ----------
    before, after : (N, 3) float64
        Point clouds of the two epochs (m).
    cell_m : float, optional
        Cell side (m). Needed when ``grid`` is not given; must equal ``grid.cell_m`` if both.
    grid : Grid, optional
        Grid to use; default: :func:`common_grid` of both sets (XY intersection).

    Returns
    -------
    DemDifference
    """
    if grid is None:
        if cell_m is None:
            raise InvalidParameterError("give cell_m (cell size in metres) or a grid")
        grid = common_grid(before, after, cell_m=cell_m)
    elif cell_m is not None and not math.isclose(float(cell_m), grid.cell_m, rel_tol=1e-12):
        raise InvalidParameterError(
            f"cell_m={cell_m} differs from grid.cell_m={grid.cell_m}: give only one of them"
        )
    zb = grid_elevation(before, grid=grid)
    za = grid_elevation(after, grid=grid)
    dz = za - zb
    ok = np.isfinite(dz)
    n = int(ok.sum())
    mean = float(dz[ok].mean()) if n else float("nan")
    std = float(dz[ok].std()) if n else float("nan")
    return DemDifference(
        grid=grid, z_before=zb, z_after=za, dz=dz, mean_m=mean, std_m=std, n_valid=n
    )
