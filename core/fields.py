"""Regular gridded displacement fields (PIV, ICP, strain, comparisons).

A :class:`GriddedField` is a north-up regular grid of displacement vectors, row 0 to the
north, the layout of a GeoTIFF: the cell in row ``r`` and column ``c`` has its centre at

    x = origin_x + (c + 0.5) * sx,        y = origin_y - (r + 0.5) * sy,

so ``origin_xy`` is the upper-left corner of the upper-left cell. Displacements are metres,
``dx`` positive east, ``dy`` positive north, ``dz`` positive up; NaN marks a cell without a
vector (a cell has a vector when both ``dx`` and ``dy`` are finite).

The module also rebuilds such a grid from the scattered rows of a vector CSV
(:func:`field_from_columns`), samples it at arbitrary points (:func:`sample_field`) and
compares an estimated field with control points (GPS, feature tracking:
:func:`compare_with_control`) or with a known synthetic truth (:func:`compare_with_truth`).
No file I/O here (formats live in ``core/io``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from typing import Any, Callable, Optional, Tuple

import numpy as np

from .errors import InputDataError, InvalidParameterError

__all__ = [
    "FieldComparison",
    "GriddedField",
    "NeighbourVarianceFactor",
    "compare_with_control",
    "compare_with_truth",
    "field_from_columns",
    "neighbour_variance_factor",
    "sample_field",
]

logger = logging.getLogger(__name__)

_DEFAULT_LATTICE_TOLERANCE = 0.05  # fraction of a cell a coordinate may sit off the lattice
_MAX_EMPTY_RATIO = 100  # a rebuilt grid may hold at most this many cells per vector ...
_MAX_SPARSE_CELLS = 10_000_000  # ... unless it is smaller than this anyway
_MERGE_FRACTION = 1e-9  # gaps below this fraction of the coordinates' size are rounding noise


# --------------------------------------------------------------------------- the grid


def _frozen_array(a: Any, name: str) -> np.ndarray:
    arr = np.array(a, dtype=np.float64, copy=True)
    if arr.ndim != 2:
        raise InputDataError(
            f"GriddedField.{name} must be a 2-D (n_rows, n_cols) array, got shape {arr.shape}."
        )
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class GriddedField:
    """A north-up regular grid of displacement vectors (row 0 = north).

    Attributes
    ----------
    origin_xy : tuple of float
        ``(x, y)`` of the upper-left corner of the upper-left cell (metres, map CRS).
    spacing_m : tuple of float
        ``(sx, sy)`` cell size along x (east) and y (north), metres, both > 0.
    dx, dy : numpy.ndarray
        (n_rows, n_cols) float64 displacement east and north (metres); NaN = no vector.
    dz : numpy.ndarray or None
        (n_rows, n_cols) float64 vertical displacement (metres, up), or None for a 2-D field.

    Notes
    -----
    The arrays are copied on construction and made read-only, so a field never changes
    after it is built (use :func:`dataclasses.replace` with new arrays).
    """

    origin_xy: tuple[float, float]
    spacing_m: tuple[float, float]
    dx: np.ndarray
    dy: np.ndarray
    dz: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        ox, oy = (float(v) for v in self.origin_xy)
        if not (math.isfinite(ox) and math.isfinite(oy)):
            raise InvalidParameterError(f"origin_xy must be finite, got {self.origin_xy!r}.")
        sx, sy = (float(v) for v in self.spacing_m)
        if not (math.isfinite(sx) and math.isfinite(sy) and sx > 0 and sy > 0):
            raise InvalidParameterError(
                f"spacing_m must be two finite cell sizes > 0 (metres), got {self.spacing_m!r}."
            )
        dx = _frozen_array(self.dx, "dx")
        dy = _frozen_array(self.dy, "dy")
        if dy.shape != dx.shape:
            raise InputDataError(
                f"GriddedField.dy has shape {dy.shape}, dx has {dx.shape}; they must match."
            )
        dz = None
        if self.dz is not None:
            dz = _frozen_array(self.dz, "dz")
            if dz.shape != dx.shape:
                raise InputDataError(
                    f"GriddedField.dz has shape {dz.shape}, dx has {dx.shape}; they must match."
                )
        if dx.size == 0:
            raise InputDataError("GriddedField must have at least one cell (got an empty grid).")
        object.__setattr__(self, "origin_xy", (ox, oy))
        object.__setattr__(self, "spacing_m", (sx, sy))
        object.__setattr__(self, "dx", dx)
        object.__setattr__(self, "dy", dy)
        object.__setattr__(self, "dz", dz)

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_rows, n_cols)``."""
        return (int(self.dx.shape[0]), int(self.dx.shape[1]))

    @property
    def x(self) -> np.ndarray:
        """(n_rows, n_cols) x of the cell centres (metres)."""
        n_rows, n_cols = self.shape
        xc = self.origin_xy[0] + (np.arange(n_cols) + 0.5) * self.spacing_m[0]
        return np.broadcast_to(xc, (n_rows, n_cols)).copy()

    @property
    def y(self) -> np.ndarray:
        """(n_rows, n_cols) y of the cell centres (metres); decreases with the row."""
        n_rows, n_cols = self.shape
        yc = self.origin_xy[1] - (np.arange(n_rows) + 0.5) * self.spacing_m[1]
        return np.broadcast_to(yc[:, None], (n_rows, n_cols)).copy()

    @property
    def valid(self) -> np.ndarray:
        """(n_rows, n_cols) bool: the cell has a horizontal vector (finite dx and dy)."""
        return np.isfinite(self.dx) & np.isfinite(self.dy)

    def to_columns(self, *, valid_only: bool = True) -> dict[str, np.ndarray]:
        """Flatten to CSV-like columns, row-major (north row first).

        Parameters
        ----------
        valid_only : bool
            Keep only cells with a vector (see :attr:`valid`).

        Returns
        -------
        dict
            ``"x"``, ``"y"``, ``"dx"``, ``"dy"`` and, when the field has it, ``"dz"``: (K,)
            float64 arrays (metres).
        """
        keep = self.valid.ravel() if valid_only else np.ones(self.dx.size, dtype=bool)
        cols = {
            "x": self.x.ravel()[keep],
            "y": self.y.ravel()[keep],
            "dx": self.dx.ravel()[keep].copy(),
            "dy": self.dy.ravel()[keep].copy(),
        }
        if self.dz is not None:
            cols["dz"] = self.dz.ravel()[keep].copy()
        return cols


# --------------------------------------------------------------------------- from CSV rows


def _axis_lattice(
    values: np.ndarray, spacing: Optional[float], tolerance: float, axis: str
) -> tuple[Optional[float], float]:
    """Spacing (None if not inferable) and first lattice value of one coordinate axis."""
    u = np.unique(values)
    span = float(u[-1] - u[0])
    if spacing is None:
        gaps = np.diff(u)
        noise = _MERGE_FRACTION * max(float(np.max(np.abs(u))), span, 1.0)
        gaps = gaps[gaps > noise]
        if gaps.size == 0:
            return None, float(u[0])
        step = float(gaps.min())
    else:
        step = float(spacing)
    k = np.rint((u - u[0]) / step)
    if spacing is None and k[-1] > 0:
        step = span / float(k[-1])  # refine on the whole span (least noisy)
        k = np.rint((u - u[0]) / step)
    off = (u - u[0]) / step - k
    start = float(u[0]) + float(np.mean(off)) * step
    off = (u - start) / step - k
    worst = int(np.argmax(np.abs(off)))
    if abs(off[worst]) > tolerance:
        how = "given" if spacing is not None else "inferred"
        sign = -1.0 if axis == "y" else 1.0  # the y lattice is built on -y (rows run south)
        raise InputDataError(
            f"The {axis} coordinates are not on a regular lattice: "
            f"{axis} = {float(sign * u[worst])!r} "
            f"lies {abs(off[worst]):.3f} cells off the lattice of spacing {step:g} m ({how}) "
            f"through {axis} = {sign * start!r} (tolerance {tolerance:g} cells). Give the grid "
            "spacing with spacing_m, or check that the file holds one vector per cell centre "
            "of a regular grid."
        )
    return step, start


def field_from_columns(
    x: Any,
    y: Any,
    dx: Any,
    dy: Any,
    dz: Any = None,
    *,
    spacing_m: Optional[Any] = None,
    valid: Any = None,
    lattice_tolerance: float = _DEFAULT_LATTICE_TOLERANCE,
) -> GriddedField:
    """Rebuild a regular grid from scattered rows of vectors (e.g. ``piv.csv``, ``icp.csv``).

    Each row is one vector at one cell centre of a regular north-up lattice; rows may come
    in any order and some (even whole rows or columns of the grid) may be missing. The grid
    spans the bounding box of the given centres; cells without a row get NaN.

    Parameters
    ----------
    x, y : array-like
        (K,) cell-centre coordinates (metres, map CRS); must be finite.
    dx, dy : array-like
        (K,) horizontal displacement (metres); NaN allowed (cell kept, no vector).
    dz : array-like, optional
        (K,) vertical displacement (metres); None gives a field with ``dz=None``.
    spacing_m : float or (2,) array-like, optional
        Cell size ``sx`` or ``(sx, sy)`` (metres). Default: inferred per axis from the
        coordinates (the smallest gap between distinct values, refined over the span, so
        missing vectors do not matter); an axis with a single distinct value takes the other
        axis's spacing.
    valid : array-like of bool, optional
        (K,) rows to use as vectors; rows with False still place their cell on the grid but
        get NaN displacements.
    lattice_tolerance : float
        How far (fraction of a cell) a coordinate may sit off the lattice, e.g. rounding in
        the CSV. Default 0.05.

    Returns
    -------
    GriddedField

    Raises
    ------
    InputDataError
        Mismatched lengths, no rows, non-finite coordinates, points off a regular lattice,
        two rows on the same cell, or a spacing that cannot be inferred (a single point).
    InvalidParameterError
        ``spacing_m`` or ``lattice_tolerance`` out of range.
    """
    xs = np.asarray(x, dtype=np.float64).ravel()
    ys = np.asarray(y, dtype=np.float64).ravel()
    cols = {"dx": dx, "dy": dy}
    if dz is not None:
        cols["dz"] = dz
    arrays = {k: np.asarray(v, dtype=np.float64).ravel() for k, v in cols.items()}
    n = xs.size
    for name, arr in [("y", ys), *arrays.items()]:
        if arr.size != n:
            raise InputDataError(
                f"field_from_columns: {name} has {arr.size} values, x has {n}; they must match."
            )
    if n == 0:
        raise InputDataError("field_from_columns: no vectors given (x is empty).")
    if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(ys))):
        bad = int(np.count_nonzero(~(np.isfinite(xs) & np.isfinite(ys))))
        raise InputDataError(
            f"field_from_columns: {bad} rows have non-finite x or y; drop them first."
        )
    if not (0.0 < float(lattice_tolerance) < 0.5):
        raise InvalidParameterError(
            f"lattice_tolerance must be in (0, 0.5) cells, got {lattice_tolerance!r}."
        )
    sx_in: Optional[float] = None
    sy_in: Optional[float] = None
    if spacing_m is not None:
        sp = np.atleast_1d(np.asarray(spacing_m, dtype=np.float64))
        if sp.size not in (1, 2) or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
            raise InvalidParameterError(
                f"spacing_m must be a cell size > 0 or (sx, sy) in metres, got {spacing_m!r}."
            )
        sx_in, sy_in = float(sp[0]), float(sp[-1])
    tol = float(lattice_tolerance)
    sx, x0 = _axis_lattice(xs, sx_in, tol, "x")
    sy, y0 = _axis_lattice(-ys, sy_in, tol, "y")  # rows run south: lattice on -y
    if sx is None and sy is None:
        raise InputDataError(
            "field_from_columns: all vectors share one x and one y, so the grid spacing cannot "
            "be inferred; give spacing_m."
        )
    if sx is None:
        sx, x0 = _axis_lattice(xs, sy, tol, "x")
    if sy is None:
        sy, y0 = _axis_lattice(-ys, sx, tol, "y")
    assert sx is not None and sy is not None
    col = np.rint((xs - x0) / sx).astype(np.int64)
    row = np.rint((-ys - y0) / sy).astype(np.int64)
    n_rows, n_cols = int(row.max()) + 1, int(col.max()) + 1
    if n_rows * n_cols > max(_MAX_EMPTY_RATIO * n, _MAX_SPARSE_CELLS):
        raise InputDataError(
            f"field_from_columns: {n} vectors span a grid of {n_rows} x {n_cols} cells of "
            f"{sx:g} x {sy:g} m, almost all empty; check for stray coordinates or give spacing_m."
        )
    flat = row * n_cols + col
    uniq, counts = np.unique(flat, return_counts=True)
    if np.any(counts > 1):
        dup = int(uniq[np.argmax(counts > 1)])
        r, c = divmod(dup, n_cols)
        raise InputDataError(
            f"field_from_columns: {int(np.sum(counts[counts > 1]))} rows fall on an already used "
            f"grid cell (e.g. {int(counts.max())} rows at the cell centred on "
            f"x={x0 + c * sx:.6f}, y={-(y0 + r * sy):.6f}); each cell must hold one vector."
        )
    use = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool).ravel()
    if use.size != n:
        raise InputDataError(
            f"field_from_columns: valid has {use.size} values, x has {n}; they must match."
        )
    grids = {}
    for name, arr in arrays.items():
        g = np.full(n_rows * n_cols, np.nan)
        g[flat[use]] = arr[use]
        grids[name] = g.reshape(n_rows, n_cols)
    origin = (x0 - 0.5 * sx, -y0 + 0.5 * sy)
    return GriddedField(origin, (sx, sy), grids["dx"], grids["dy"], grids.get("dz"))


# --------------------------------------------------------------------------- sampling


def _as_xy(xy: Any, name: str) -> np.ndarray:
    arr = np.asarray(xy, dtype=np.float64)
    if arr.ndim == 1 and arr.size == 2:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] < 2:
        raise InputDataError(
            f"{name} must be an (M, 2) array of x, y (metres), got shape {arr.shape}."
        )
    return arr[:, :2]


def _components(field: GriddedField) -> list[np.ndarray]:
    dz = field.dz if field.dz is not None else np.full(field.shape, np.nan)
    return [field.dx, field.dy, dz]


def sample_field(
    field: GriddedField,
    xy: Any,
    *,
    method: str = "bilinear",
    max_distance_m: Optional[float] = None,
) -> np.ndarray:
    """Displacement of a gridded field at arbitrary points.

    Parameters
    ----------
    field : GriddedField
    xy : array-like
        (M, 2) points (metres, same CRS as the field); extra columns are ignored.
    method : str
        ``"bilinear"`` (default): bilinear interpolation between the four surrounding cell
        centres, each component on its own; NaN where a neighbour with non-zero weight has
        no value. Points in the outer half cell of the grid (between the outermost centres
        and the grid's edge) take the edge values (clamped); points outside the grid get NaN.
        ``"nearest_valid"``: the vector of the nearest cell that has one (``dx`` and ``dy``
        finite), NaN beyond ``max_distance_m``.
    max_distance_m : float, optional
        For ``"nearest_valid"`` only: largest distance to the chosen cell centre (metres);
        default unlimited.

    Returns
    -------
    numpy.ndarray
        (M, 3) float64 ``(dx, dy, dz)`` (metres); ``dz`` is NaN when the field has none.
    """
    pts = _as_xy(xy, "xy")
    m = pts.shape[0]
    out = np.full((m, 3), np.nan)
    if m == 0:
        return out
    comps = _components(field)
    if method == "nearest_valid":
        from scipy.spatial import cKDTree

        valid = field.valid
        if not np.any(valid):
            return out
        centre = np.array([field.origin_xy[0], field.origin_xy[1]])
        cxy = np.column_stack([field.x[valid], field.y[valid]]) - centre
        bound = np.inf if max_distance_m is None else float(max_distance_m)
        if not bound >= 0:
            raise InvalidParameterError(
                f"max_distance_m must be >= 0 metres, got {max_distance_m!r}."
            )
        finite = np.all(np.isfinite(pts), axis=1)
        dist, idx = cKDTree(cxy).query(pts[finite] - centre, distance_upper_bound=bound)
        hit = np.isfinite(dist)
        rows = np.flatnonzero(finite)[hit]
        for k, comp in enumerate(comps):
            out[rows, k] = comp[valid][idx[hit]]
        return out
    if method != "bilinear":
        raise InvalidParameterError(
            f"method must be 'bilinear' or 'nearest_valid', got {method!r}."
        )
    if max_distance_m is not None:
        raise InvalidParameterError("max_distance_m applies to method='nearest_valid' only.")
    n_rows, n_cols = field.shape
    sx, sy = field.spacing_m
    fc = (pts[:, 0] - field.origin_xy[0]) / sx - 0.5  # fractional column of the centres
    fr = (field.origin_xy[1] - pts[:, 1]) / sy - 0.5  # fractional row
    inside = (fc >= -0.5) & (fc <= n_cols - 0.5) & (fr >= -0.5) & (fr <= n_rows - 0.5)
    fc = np.clip(np.where(inside, fc, 0.0), 0.0, n_cols - 1)
    fr = np.clip(np.where(inside, fr, 0.0), 0.0, n_rows - 1)
    c0 = np.minimum(np.floor(fc).astype(np.int64), max(n_cols - 2, 0))
    r0 = np.minimum(np.floor(fr).astype(np.int64), max(n_rows - 2, 0))
    c1 = np.minimum(c0 + 1, n_cols - 1)
    r1 = np.minimum(r0 + 1, n_rows - 1)
    tc, tr = fc - c0, fr - r0
    corners = [
        (r0, c0, (1 - tr) * (1 - tc)),
        (r0, c1, (1 - tr) * tc),
        (r1, c0, tr * (1 - tc)),
        (r1, c1, tr * tc),
    ]
    with np.errstate(invalid="ignore"):
        for k, comp in enumerate(comps):
            acc = np.zeros(m)
            for r, c, w in corners:
                acc += np.where(w == 0.0, 0.0, w * comp[r, c])
            out[:, k] = np.where(inside, acc, np.nan)
    return out


# --------------------------------------------------------------------------- comparisons


@dataclass(frozen=True)
class FieldComparison:
    """Agreement of an estimated displacement field with reference displacements.

    Errors are ``estimate - reference``. Horizontal statistics use the pairs where both
    have finite dx and dy; vertical ones the pairs where both have a finite dz.

    Attributes
    ----------
    n_compared : int
        Pairs with a horizontal estimate and reference.
    n_missing : int
        Reference points with a horizontal reference but no estimate there.
    valid_fraction : float
        ``n_compared / (n_compared + n_missing)`` (NaN when both are 0).
    rmse_horizontal_m : float
        ``sqrt(mean(ex² + ey²))`` (metres).
    rmse_dx_m, rmse_dy_m, rmse_dz_m : float
        Root-mean-square error per component (metres; NaN without pairs).
    bias_dx_m, bias_dy_m, bias_dz_m : float
        Mean error per component (metres).
    max_abs_horizontal_m : float
        Largest horizontal error length (metres).
    n_compared_dz : int
        Pairs with a vertical estimate and reference.
    """

    n_compared: int
    n_missing: int
    valid_fraction: float
    rmse_horizontal_m: float
    rmse_dx_m: float
    rmse_dy_m: float
    rmse_dz_m: float
    bias_dx_m: float
    bias_dy_m: float
    bias_dz_m: float
    max_abs_horizontal_m: float
    n_compared_dz: int = 0

    def to_dict(self) -> dict[str, Any]:
        """Plain ``dict`` of the fields (ints and floats; JSON-ready except NaN)."""
        return asdict(self)


def _as_d(d: Any, name: str, m: int) -> np.ndarray:
    arr = np.asarray(d, dtype=np.float64)
    if arr.ndim == 1 and m == 1 and arr.size in (2, 3):
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[0] != m or arr.shape[1] not in (2, 3):
        raise InputDataError(
            f"{name} must be an ({m}, 3) array of dx, dy, dz (metres), got shape {arr.shape}."
        )
    if arr.shape[1] == 2:
        arr = np.column_stack([arr, np.full(m, np.nan)])
    return arr


def _compare(est: np.ndarray, ref: np.ndarray) -> FieldComparison:
    """Statistics of est - ref, both (M, 3)."""
    ref_h = np.isfinite(ref[:, 0]) & np.isfinite(ref[:, 1])
    est_h = np.isfinite(est[:, 0]) & np.isfinite(est[:, 1])
    pair = ref_h & est_h
    n_cmp = int(np.count_nonzero(pair))
    n_miss = int(np.count_nonzero(ref_h & ~est_h))
    nan = float("nan")
    frac = n_cmp / (n_cmp + n_miss) if (n_cmp + n_miss) else nan
    err = est - ref
    if n_cmp:
        ex, ey = err[pair, 0], err[pair, 1]
        h2 = ex * ex + ey * ey
        rmse_h = float(np.sqrt(np.mean(h2)))
        rmse_x, rmse_y = float(np.sqrt(np.mean(ex * ex))), float(np.sqrt(np.mean(ey * ey)))
        bias_x, bias_y = float(np.mean(ex)), float(np.mean(ey))
        max_h = float(np.sqrt(np.max(h2)))
    else:
        logger.warning(
            "No estimate/reference pair to compare (%d references without estimate).", n_miss
        )
        rmse_h = rmse_x = rmse_y = bias_x = bias_y = max_h = nan
    zpair = np.isfinite(est[:, 2]) & np.isfinite(ref[:, 2])
    n_z = int(np.count_nonzero(zpair))
    if n_z:
        ez = err[zpair, 2]
        rmse_z, bias_z = float(np.sqrt(np.mean(ez * ez))), float(np.mean(ez))
    else:
        rmse_z = bias_z = nan
    return FieldComparison(
        n_compared=n_cmp,
        n_missing=n_miss,
        valid_fraction=float(frac),
        rmse_horizontal_m=rmse_h,
        rmse_dx_m=rmse_x,
        rmse_dy_m=rmse_y,
        rmse_dz_m=rmse_z,
        bias_dx_m=bias_x,
        bias_dy_m=bias_y,
        bias_dz_m=bias_z,
        max_abs_horizontal_m=max_h,
        n_compared_dz=n_z,
    )


def compare_with_control(
    x: Any,
    y: Any,
    dx: Any,
    dy: Any,
    dz: Any,
    control_xy: Any,
    control_d: Any,
    *,
    field: Optional[GriddedField] = None,
    spacing_m: Optional[Any] = None,
) -> FieldComparison:
    """Compare an estimated gridded field with control points (GPS, feature tracking).

    The estimate (rows of a vector CSV) is rebuilt into its grid with
    :func:`field_from_columns` and sampled bilinearly (:func:`sample_field`) at the control
    positions; statistics are over the control points where both are available.

    Parameters
    ----------
    x, y, dx, dy : array-like
        (K,) the estimate's cell centres and horizontal displacements (metres).
    dz : array-like or None
        (K,) the estimate's vertical displacements (metres), or None.
    control_xy : array-like
        (M, 2) control positions (metres, same CRS).
    control_d : array-like
        (M, 3) control displacements ``(dx, dy, dz)`` (metres); NaN for an unknown
        component (e.g. feature tracking without dz); (M, 2) is accepted.
    field : GriddedField, optional
        The already rebuilt grid; when given, x ... dz are ignored (pass None).
    spacing_m : float or (2,), optional
        Passed to :func:`field_from_columns`.

    Returns
    -------
    FieldComparison
        Errors are ``estimate - control``.
    """
    cxy = _as_xy(control_xy, "control_xy")
    cd = _as_d(control_d, "control_d", cxy.shape[0])
    if field is None:
        field = field_from_columns(x, y, dx, dy, dz, spacing_m=spacing_m)
    est = sample_field(field, cxy)
    return _compare(est, cd)


def compare_with_truth(
    est_xy: Any,
    est_d: Any,
    truth_fn: Callable[[np.ndarray], np.ndarray],
    *,
    mask: Any = None,
) -> FieldComparison:
    """Compare estimated vectors with a known (synthetic) displacement function.

    Parameters
    ----------
    est_xy : array-like
        (M, 2) positions of the estimates (metres), e.g. cell centres.
    est_d : array-like
        (M, 3) estimated ``(dx, dy, dz)`` (metres); NaN = no estimate (counted in
        ``n_missing``); (M, 2) accepted.
    truth_fn : callable
        Maps (K, 2) positions to (K, 3) true displacements (metres), e.g. a
        :class:`slipmap.core.synthetic.LobeField`.
    mask : array-like of bool, optional
        (M,) estimates to score (e.g. ``lobe.interior_mask(xy)``); default all.

    Returns
    -------
    FieldComparison
        Errors are ``estimate - truth``.
    """
    xy = _as_xy(est_xy, "est_xy")
    d = _as_d(est_d, "est_d", xy.shape[0])
    if mask is not None:
        keep = np.asarray(mask, dtype=bool).ravel()
        if keep.size != xy.shape[0]:
            raise InputDataError(
                f"mask has {keep.size} values, est_xy has {xy.shape[0]} rows; they must match."
            )
        xy, d = xy[keep], d[keep]
    truth = _as_d(truth_fn(xy.copy()), "truth_fn(est_xy)", xy.shape[0])
    return _compare(d, truth)


# --------------------------------------------------------------------------- variance factor

CHI2_1_MEDIAN = 0.454936423119572  # median of the chi-square distribution with 1 dof


@dataclass(frozen=True)
class NeighbourVarianceFactor:
    """A-posteriori variance factor of a gridded field from the agreement of neighbours.

    Attributes
    ----------
    factor : float
        ``sqrt(median(r² / var(r)) / median(chi²₁))`` over every usable cell and component:
        the number the cells' formal sigmas must be multiplied by so that the residuals ``r``
        of each cell against the plane through its neighbours are standard normal (robustly).
        NaN when fewer than ``min_cells`` cells had enough neighbours.
    n_cells : int
        Cells that entered the estimate.
    normalised : (K, q) float64
        ``r / sqrt(var)`` of every cell and component (NaN for cells not tested): about
        ``factor`` times a standard normal for a consistent cell, an outlier test statistic.
    variance : (K, q) float64 or None
        ``var(r)`` of every cell and component from the formal sigmas (NaN for cells not
        tested), metres².
    """

    factor: float
    n_cells: int
    normalised: np.ndarray
    variance: Optional[np.ndarray] = None


def _neighbour_table(row: np.ndarray, col: np.ndarray, reach: int = 1) -> np.ndarray:
    """(K, (2 reach + 1)² - 1) index of each cell's neighbours up to ``reach`` rows and
    columns away (-1 where there is none); ``reach=1``: the 8 neighbours in ``_OFFSETS``
    order."""
    offsets = _OFFSETS if reach == 1 else [
        (a, b) for a in range(-reach, reach + 1) for b in range(-reach, reach + 1) if a or b
    ]  # fmt: skip
    r0, c0 = int(row.min()), int(col.min())
    rr, cc = row - r0 + reach, col - c0 + reach  # an empty ring around the grid
    grid = np.full((int(rr.max()) + reach + 1, int(cc.max()) + reach + 1), -1, dtype=np.int64)
    grid[rr, cc] = np.arange(row.size)
    return np.stack([grid[rr + a, cc + b] for a, b in offsets], axis=1)


_OFFSETS = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
#: the neighbour tests' prediction of a cell (:func:`neighbour_variance_factor` ``surface``)
NEIGHBOUR_SURFACE = "plane"


def _quadratic_design(off: np.ndarray) -> np.ndarray:
    """(8, 6) columns ``1, dc, dr, dc², dc dr, dr²`` of the 8 neighbour offsets (rows,
    columns)."""
    dr, dc = off[:, 0], off[:, 1]
    return np.column_stack([np.ones(len(off)), dc, dr, dc * dc, dc * dr, dr * dr])


def _quadratic_weights(W: np.ndarray, off: np.ndarray, h_plane: np.ndarray) -> np.ndarray:
    """(M, 8) prediction weights of the least-squares quadratic through the present
    neighbours (``W`` (M, 8) 0/1) at the centre; ``h_plane`` (M, 8) where they determine no
    quadratic."""
    Xq = _quadratic_design(off)
    A = np.einsum("ki,ij,il->kjl", W, Xq, Xq)  # (M, 6, 6), integer entries
    full = np.abs(np.linalg.det(A)) > 0.5  # an integer determinant: 0 where not determined
    h = h_plane.copy()
    if full.any():
        e1 = np.zeros((int(full.sum()), 6, 1))
        e1[:, 0, 0] = 1.0
        gq = np.linalg.solve(A[full], e1)[..., 0]
        h[full] = W[full] * (gq @ Xq.T)
    return h


def _neighbour_args(row, col, values, sigmas, usable):
    row = np.asarray(row, dtype=np.int64).reshape(-1)
    col = np.asarray(col, dtype=np.int64).reshape(-1)
    k = row.size
    if col.size != k:
        raise InvalidParameterError(f"row and col must have the same length ({k}, {col.size})")
    values = np.asarray(values, dtype=np.float64).reshape(k, -1)
    sigmas = np.asarray(sigmas, dtype=np.float64).reshape(k, -1)
    if sigmas.shape != values.shape:
        raise InvalidParameterError(
            f"sigmas must have the shape of values {values.shape}, got {sigmas.shape}"
        )
    ok = np.all(np.isfinite(values), axis=1) & np.all(np.isfinite(sigmas) & (sigmas > 0), axis=1)
    if usable is not None:
        ok &= np.asarray(usable, dtype=bool).reshape(k)
    if np.unique(np.column_stack([row, col]), axis=0).shape[0] != k:
        raise InvalidParameterError("row, col must name each grid cell at most once")
    return row, col, values, sigmas, ok


class _PairCovariance:
    """Look-up of given pair covariances ``c(i, j)`` (symmetric; 0 for pairs not given and for
    ``i == j``, whose variances are the sigmas)."""

    def __init__(self, pairs: np.ndarray, cov: np.ndarray, k: int):
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        cov = np.asarray(cov, dtype=np.float64).reshape(len(pairs), -1)
        i = np.concatenate([pairs[:, 0], pairs[:, 1]])
        j = np.concatenate([pairs[:, 1], pairs[:, 0]])
        key = i * k + j
        order = np.argsort(key, kind="stable")
        self.key, self.cov, self.k = key[order], np.concatenate([cov, cov])[order], k

    def __call__(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        i, j = np.broadcast_arrays(i, j)
        key = i * self.k + j
        pos = np.minimum(np.searchsorted(self.key, key), max(len(self.key) - 1, 0))
        out = np.zeros(key.shape + (self.cov.shape[1],))
        if len(self.key):
            hit = (self.key[pos] == key) & (i != j)
            out[hit] = self.cov[pos[hit]]
        return out


def neighbour_variance_factor(
    row: np.ndarray,
    col: np.ndarray,
    values: np.ndarray,
    sigmas: np.ndarray,
    *,
    usable: Optional[np.ndarray] = None,
    min_neighbours: int = 5,
    min_cells: int = 8,
    pair_covariance: Optional[Tuple[np.ndarray, np.ndarray]] = None,
    separated: Optional[np.ndarray] = None,
    surface: Optional[str] = None,
) -> NeighbourVarianceFactor:
    """Variance factor of the formal sigmas of a gridded field, from neighbour agreement.

    Each usable cell with at least ``min_neighbours`` usable cells among its 8 neighbours is
    predicted by the least-squares plane through them (in grid units; with all 8 present
    that is their mean); ``r = value - prediction`` has the formal variance
    ``sigma² + sum(h_j² sigma_j²)`` (``h`` the prediction weights), and
    ``factor² = median(r² / var) / median(chi²₁)`` over all such cells and components. A field
    that is locally planar over 3 x 3 cells and whose sigmas are honest gives 1; errors that
    the formal sigmas miss (correlated residuals of the points, unmodelled surface) raise it;
    real curvature of the field over 3 x 3 cells raises it too, so the factor errs on the
    large, safe side. Robust (median): a few outlier cells do not move it.

    Parameters
    ----------
    row, col : (K,) int
        Grid indices of the cells (each cell at most once).
    values, sigmas : (K,) or (K, q) float64
        Field components (e.g. dx, dy, dz, metres) and their formal 1-sigma.
    usable : (K,) bool, optional
        Cells allowed in the estimate (as centre or neighbour); cells with a non-finite value
        or a non-finite or zero sigma never are.
    min_neighbours : int
        At least 3 (a plane), at most 8.
    min_cells : int
        Fewer cells with enough neighbours give ``factor`` NaN.
    pair_covariance : ((P, 2) int, (P, q) float64), optional
        Formal covariances between cells (indices into ``row``), per component, of a field
        whose values are correlated (e.g. one spline fitted to all cells): then
        ``var(r) = sigma_i² - 2 sum h_j c_ij + sum h_j h_k c_jk``. Pairs not given are
        uncorrelated. Without it a positively correlated field's ``var(r)`` is overstated and
        its factor too small.
    separated : (K, 8) bool, optional
        True where a cell's neighbour (in the order of the eight offsets ``(-1, -1), (-1, 0),
        ... (1, 1)`` in rows, columns) lies across a discontinuity of the field (a breakline
        between their centres): that neighbour does not predict the cell, whose motion may
        jump there.
    surface : {"plane", "quadratic"}, optional
        The prediction: the plane through the neighbours, or the quadratic surface (six
        coefficients) where the present neighbours determine one (the plane elsewhere); with
        all 8 present that is the mean of the two row neighbours plus the mean of the two
        column neighbours less the mean of the four corners (weights ``1/2`` and ``-1/4``).
        A smooth field's curvature over 3 x 3 cells is no
        error of its cells; the quadratic leaves it out of ``r`` (at 2.25 times a cell's
        variance for ``var(r)`` instead of 1.125). Default :data:`NEIGHBOUR_SURFACE`.

    Returns
    -------
    NeighbourVarianceFactor
    """
    surface = NEIGHBOUR_SURFACE if surface is None else surface
    if surface not in ("plane", "quadratic"):
        raise InvalidParameterError(f"surface must be 'plane' or 'quadratic', got {surface!r}")
    if not 3 <= int(min_neighbours) <= 8:
        raise InvalidParameterError(f"min_neighbours must be within [3, 8], got {min_neighbours}")
    if np.size(row) == 0:
        return NeighbourVarianceFactor(float("nan"), 0, np.zeros((0, np.shape(values)[-1])))
    row, col, values, sigmas, ok = _neighbour_args(row, col, values, sigmas, usable)
    normalised = np.full(values.shape, np.nan)
    nb = _neighbour_table(row, col)
    present = (nb >= 0) & ok[np.maximum(nb, 0)]
    if separated is not None:
        present &= ~np.asarray(separated, dtype=bool).reshape(row.size, 8)
    # plane z = a + b*dc + c*dr through the present neighbours, evaluated at (0, 0): weights
    # h = e1' (X'WX)^-1 X'W with W the 0/1 presence mask; collinear neighbours (possible with
    # min_neighbours < 5) define no plane and leave the cell out
    off = np.array(_OFFSETS, dtype=np.float64)  # (8, 2): row, col offsets
    X = np.column_stack([np.ones(8), off[:, 1], off[:, 0]])  # (8, 3)
    W = present.astype(np.float64)
    XtWX = np.einsum("ki,ij,il->kjl", W, X, X)  # (K, 3, 3), integer entries
    planar = np.linalg.det(XtWX) > 0.5  # an integer determinant: 0 when collinear
    centre = ok & (present.sum(axis=1) >= int(min_neighbours)) & planar
    nb, W, XtWX = nb[centre], W[centre], XtWX[centre]
    rhs = np.broadcast_to(np.array([1.0, 0.0, 0.0]), (W.shape[0], 3))
    g = np.linalg.solve(XtWX, rhs[..., None])[..., 0]  # (M, 3) = (X'WX)^-1 e1
    h = W * (g @ X.T)  # (M, 8)
    if surface == "quadratic":
        h = _quadratic_weights(W, off, h)
    idx = np.maximum(nb, 0)
    pred = np.einsum("kj,kjq->kq", h, values[idx])
    var = sigmas[centre] ** 2 + np.einsum("kj,kjq->kq", h * h, sigmas[idx] ** 2)
    if pair_covariance is not None:
        cov = _PairCovariance(*pair_covariance, row.size)
        ci = np.flatnonzero(centre)
        c_in = cov(np.repeat(ci[:, None], 8, axis=1), idx)  # (M, 8, q)
        c_nn = cov(idx[:, :, None], idx[:, None, :])  # (M, 8, 8, q), zero diagonal
        var = var - 2.0 * np.einsum("kj,kjq->kq", h, c_in) + np.einsum("kj,kl,kjlq->kq", h, h, c_nn)
        var = np.maximum(var, 1e-6 * sigmas[centre] ** 2)  # rounding of nearly equal values
    normalised[centre] = (values[centre] - pred) / np.sqrt(var)
    variance = np.full(values.shape, np.nan)
    variance[centre] = var
    if nb.shape[0] < int(min_cells):
        return NeighbourVarianceFactor(float("nan"), int(nb.shape[0]), normalised, variance)
    ratio = normalised[centre] ** 2
    return NeighbourVarianceFactor(
        float(math.sqrt(np.median(ratio) / CHI2_1_MEDIAN)), int(nb.shape[0]), normalised,
        variance,
    )  # fmt: skip


def _neighbour_variance_factor_reference(
    row,
    col,
    values,
    sigmas,
    *,
    usable=None,
    min_neighbours=5,
    min_cells=8,
    pair_covariance=None,
    separated=None,
    surface="plane",
) -> NeighbourVarianceFactor:
    """Slow obvious version of :func:`neighbour_variance_factor` (a loop over cells with
    ``np.linalg.lstsq`` per cell), for testing."""
    row, col, values, sigmas, ok = _neighbour_args(row, col, values, sigmas, usable)
    where = {(int(r), int(c)): i for i, (r, c) in enumerate(zip(row, col)) if ok[i]}
    normalised = np.full(values.shape, np.nan)
    variance = np.full(values.shape, np.nan)
    for (r, c), i in where.items():
        nbs = [
            (a, b, where[(r + a, c + b)])
            for o, (a, b) in enumerate(_OFFSETS)
            if (r + a, c + b) in where and not (separated is not None and separated[i][o])
        ]
        X = np.array([[1.0, b, a] for a, b, _ in nbs]).reshape(-1, 3)
        if len(nbs) < min_neighbours or np.linalg.matrix_rank(X) < 3:
            continue
        j = [k for _, _, k in nbs]
        h = np.linalg.lstsq(X, np.eye(len(j)), rcond=None)[0][0]  # prediction at (0, 0)
        if surface == "quadratic":
            Xq = np.array([[1.0, b, a, b * b, a * b, a * a] for a, b, _ in nbs]).reshape(-1, 6)
            if np.linalg.matrix_rank(Xq) == 6:
                h = np.linalg.lstsq(Xq, np.eye(len(j)), rcond=None)[0][0]
        r_i = values[i] - h @ values[j]
        # var(r) = var(e_i - h' e_J) from the full covariance of (cell, neighbours)
        members = [i] + j
        c = np.zeros((len(members), len(members), values.shape[1]))
        for a, m in enumerate(members):
            c[a, a] = sigmas[m] ** 2
        if pair_covariance is not None:
            for (p, q), cv in zip(np.asarray(pair_covariance[0]), np.asarray(pair_covariance[1])):
                if p in members and q in members and p != q:
                    c[members.index(p), members.index(q)] = cv
                    c[members.index(q), members.index(p)] = cv
        u = np.concatenate([[1.0], -h])
        var = np.maximum(np.einsum("a,b,abq->q", u, u, c), 1e-6 * sigmas[i] ** 2)
        normalised[i] = r_i / np.sqrt(var)
        variance[i] = var
    tested = np.all(np.isfinite(normalised), axis=1)
    n = int(tested.sum())
    if n < min_cells:
        return NeighbourVarianceFactor(float("nan"), n, normalised, variance)
    return NeighbourVarianceFactor(
        float(math.sqrt(np.median(normalised[tested] ** 2) / CHI2_1_MEDIAN)), n, normalised,
        variance,
    )  # fmt: skip
