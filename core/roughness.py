"""Surface roughness on a regular 3D grid by orthogonal distance regression (ODR).

Implements Pollyea & Fairley (2011), *Estimating surface roughness of terrestrial laser scan
data using orthogonal distance regression*, Geology 39(7), 623-626:

1. the cloud is segmented with a regular 3D grid of cell size ``c``;
2. in each cell with at least ``min_points`` points, the ODR (total least-squares) plane is the
   plane through the centroid whose normal is the smallest right singular vector of the centred
   points, i.e. the eigenvector of the smallest eigenvalue of their covariance;
3. the orthogonal distances are ``D_i = |n . v_i|`` (Eq. 3) and the roughness is their
   population standard deviation ``theta = sqrt(mean((D_i - mean(D))**2))`` (Eq. 4, ``1/N``,
   i.e. ``ddof=0``). Because ``D_i`` are *absolute* distances, for Gaussian noise of standard
   deviation ``sigma`` about a plane the published definition gives
   ``sigma * sqrt(1 - 2/pi) ~ 0.603 sigma``; ``signed=True`` gives the standard deviation of the
   signed distances (``sigma``), the quantity most users mean by "RMS roughness";
4. for comparison, the ordinary least-squares (OLS) plane ``a = b0 + b1 u + b2 w`` along one
   coordinate axis ``a``; its roughness uses the residuals along ``a`` with the same definition,
   and ``E_OLS = |theta_OLS - theta_ODR|`` (Eq. 5).

Two implementations give the same numbers: :func:`grid_roughness` (vectorised: one sort of
packed integer cell keys, per-cell moments with ``np.add.reduceat`` on chunks of points sorted by
cell, batched ``eigh``; memory bounded by processing chunks) and
:func:`grid_roughness_reference` (an obvious per-cell loop with ``np.linalg.svd``), used as the
test oracle.

Maps, histograms and semivariograms of the per-cell values are in this module too
(:func:`choose_map_plane`, :func:`rasterize_cells`, :func:`semivariogram_raster`); writing them
to files is the adapters' job (``core.io.raster``, ``app.report``).

All coordinates are metres (or the input CRS unit); every covariance is computed on coordinates
relative to the cell centre, so survey coordinates with 1e5-1e6 m offsets keep full precision.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Dict, Sequence, Tuple, Union

import numpy as np

from .errors import InputDataError, InvalidParameterError
from .octree import bounds
from .progress import ProgressCallback, report, scaled

log = logging.getLogger(__name__)

__all__ = [
    "AXIS_NAMES",
    "MapPlane",
    "MapRaster",
    "PrincipalFrame",
    "RoughnessGrid",
    "RoughnessStats",
    "RoughnessSummary",
    "Semivariogram",
    "binary_transform",
    "choose_map_plane",
    "grid_roughness",
    "grid_roughness_multi",
    "grid_roughness_reference",
    "normalise_range",
    "odr_plane_closed_form",
    "principal_frame",
    "rasterize_cells",
    "resolve_ols_axis",
    "roughness_histogram",
    "roughness_per_point",
    "roughness_stats",
    "semivariogram_raster",
    "summarize_roughness",
]

#: axis names in index order
AXIS_NAMES = ("x", "y", "z")

#: a cell is *degenerate* (collinear or coincident points: no unique plane) when the middle
#: eigenvalue of its covariance is at most this fraction of the largest one
DEGENERATE_EIGEN_RATIO = 1e-10

#: OLS normal equations are solved in closed form unless det(S_bb) <= this * trace(S_bb)**2;
#: then a pseudo-inverse gives the (unique) least-squares residuals
_OLS_SINGULAR_RATIO = 1e-12

_DEFAULT_MIN_POINTS = 10
_MAX_CHUNK = 1 << 20
_MIN_CHUNK = 1 << 16


# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class RoughnessGrid:
    """Per-cell roughness on one regular 3D grid (cells with enough points only).

    Cells are sorted by their packed key (``ix`` slowest, ``iz`` fastest).

    Attributes
    ----------
    cell_size_m : float
        Edge of the cubic cells.
    origin_m : numpy.ndarray, shape (3,)
        Lower corner of cell ``(0, 0, 0)`` (the grid is aligned to multiples of the cell size
        unless an origin was given).
    shape : tuple of int
        ``(nx, ny, nz)`` number of cells of the bounding grid along each axis.
    index : numpy.ndarray, shape (M, 3), int64
        Cell indices ``(ix, iy, iz)`` relative to ``origin_m``.
    n_points : numpy.ndarray, shape (M,), int64
        Points in each cell.
    centroid_m : numpy.ndarray, shape (M, 3)
        Mean of the cell's points (a point of the ODR plane).
    normal : numpy.ndarray, shape (M, 3)
        Unit normal of the ODR plane, oriented so that its last non-zero component (z, else y,
        else x) is positive. NaN-free; meaningless where ``degenerate``.
    eigenvalues_m2 : numpy.ndarray, shape (M, 3)
        Eigenvalues of the cell covariance (population, ``1/n``), ascending.
    theta_odr, theta_ols, e_ols : numpy.ndarray, shape (M,)
        Roughness by ODR (Eq. 4), by OLS along ``ols_axis``, and ``|theta_ols - theta_odr|``
        (Eq. 5), metres. NaN where ``degenerate``.
    degenerate : numpy.ndarray, shape (M,), bool
        Collinear or coincident points: no unique plane (see ``DEGENERATE_EIGEN_RATIO``).
    n_cells_skipped, n_points_skipped : int
        Occupied cells with fewer than ``min_points`` points, and their points.
    n_points_total : int
        Points in the input.
    min_points : int
    ols_axis : str
        ``"x"``, ``"y"`` or ``"z"``.
    signed : bool
        True: standard deviation of signed distances; False: of absolute distances (Eq. 4).
    """

    cell_size_m: float
    origin_m: np.ndarray
    shape: Tuple[int, int, int]
    index: np.ndarray
    n_points: np.ndarray
    centroid_m: np.ndarray
    normal: np.ndarray
    eigenvalues_m2: np.ndarray
    theta_odr: np.ndarray
    theta_ols: np.ndarray
    e_ols: np.ndarray
    degenerate: np.ndarray
    n_cells_skipped: int
    n_points_skipped: int
    n_points_total: int
    min_points: int
    ols_axis: str
    signed: bool

    def __len__(self) -> int:
        return int(self.index.shape[0])

    @property
    def centre_m(self) -> np.ndarray:
        """Cell centres, shape (M, 3), in the input coordinates."""
        return self.origin_m + (self.index + 0.5) * self.cell_size_m

    @property
    def keys(self) -> np.ndarray:
        """Packed cell keys ``(ix * ny + iy) * nz + iz``, shape (M,), int64, ascending."""
        return _pack_index(self.index, self.shape)

    @property
    def n_degenerate(self) -> int:
        return int(np.count_nonzero(self.degenerate))


@dataclass(frozen=True)
class RoughnessStats:
    """Table 1 statistics of one roughness variable over the cells (finite values only).

    ``variance`` and ``std`` are population values (``ddof=0``). Units: metres (``variance``
    square metres).
    """

    n: int
    minimum: float
    maximum: float
    mean: float
    variance: float
    std: float

    def to_dict(self) -> Dict[str, float | None]:
        return {k: _json_float(v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class RoughnessSummary:
    """The study's Table 1 for one cell size (plus the counts of skipped/degenerate cells)."""

    cell_size_m: float
    n_cells: int
    mean_points_per_cell: float
    n_cells_skipped: int
    n_points_skipped: int
    n_degenerate: int
    odr: RoughnessStats
    ols: RoughnessStats
    e_ols: RoughnessStats
    ols_axis: str
    signed: bool
    min_points: int

    def to_dict(self) -> Dict[str, object]:
        out: Dict[str, object] = {}
        for k, v in self.__dict__.items():
            out[k] = v.to_dict() if isinstance(v, RoughnessStats) else _json_float(v)
        return out


@dataclass(frozen=True)
class PrincipalFrame:
    """Principal axes of a point cloud.

    Attributes
    ----------
    centroid_m : numpy.ndarray, shape (3,)
    axes : numpy.ndarray, shape (3, 3)
        Rows are unit vectors ``e1, e2, e3`` by decreasing variance; ``e3`` is the normal of the
        principal plane. Each row's largest-magnitude component is positive.
    eigenvalues_m2 : numpy.ndarray, shape (3,)
        Variances along the axes, descending.
    """

    centroid_m: np.ndarray
    axes: np.ndarray
    eigenvalues_m2: np.ndarray

    @property
    def normal(self) -> np.ndarray:
        return self.axes[2]


@dataclass(frozen=True)
class MapPlane:
    """A 2D map frame: map coordinates ``u = (p - origin) . u_axis``, ``v = (p - origin) . v_axis``.

    ``name`` is ``"xy"``, ``"xz"``, ``"yz"`` (coordinate planes: origin 0, so ``u``/``v`` are
    input coordinates, and ``xy`` keeps the CRS) or ``"principal"`` (a local engineering frame
    on the cloud's principal plane, origin at the cloud centroid).
    """

    name: str
    origin_m: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    normal: np.ndarray
    axis_labels: Tuple[str, str] = ("u (m)", "v (m)")

    @property
    def georeferenced(self) -> bool:
        """True when ``u, v`` are the input CRS's easting/northing (the ``xy`` plane)."""
        return self.name == "xy"

    def project(self, points_m: np.ndarray) -> np.ndarray:
        """Map coordinates ``(N, 2)`` of points ``(N, 3)``."""
        p = np.asarray(points_m, dtype=np.float64) - self.origin_m
        return np.stack([p @ self.u_axis, p @ self.v_axis], axis=1)

    def to_dict(self) -> Dict[str, object]:
        return {
            "name": self.name,
            "origin_m": [float(x) for x in self.origin_m],
            "u_axis": [float(x) for x in self.u_axis],
            "v_axis": [float(x) for x in self.v_axis],
            "normal": [float(x) for x in self.normal],
            "georeferenced": self.georeferenced,
        }


@dataclass(frozen=True)
class MapRaster:
    """Per-pixel mean of cell values in a map plane.

    Attributes
    ----------
    values : numpy.ndarray, shape (bands, rows, cols)
        Mean of the finite cell values in each pixel; NaN where none. Row 0 is the top
        (largest ``v``).
    count : numpy.ndarray, shape (rows, cols), int64
        Cells whose centre falls in each pixel.
    origin_uv_m : tuple of float
        ``(u_left, v_top)``: the upper-left corner of the raster.
    pixel_size_m : float
    plane : MapPlane
    """

    values: np.ndarray
    count: np.ndarray
    origin_uv_m: Tuple[float, float]
    pixel_size_m: float
    plane: MapPlane

    @property
    def extent(self) -> Tuple[float, float, float, float]:
        """``(left, right, bottom, top)`` in map coordinates (for matplotlib ``imshow``)."""
        rows, cols = self.count.shape
        u0, v0 = self.origin_uv_m
        return (u0, u0 + cols * self.pixel_size_m, v0 - rows * self.pixel_size_m, v0)


@dataclass(frozen=True)
class Semivariogram:
    """Isotropic experimental semivariogram.

    Attributes
    ----------
    lag_m : numpy.ndarray, shape (K,)
        Mean separation of the pairs in each lag class (NaN for empty classes).
    lag_edges_m : numpy.ndarray, shape (K + 1,)
        Class ``k`` holds the pairs with ``lag_edges_m[k] < h <= lag_edges_m[k + 1]``.
    n_pairs : numpy.ndarray, shape (K,), int64
        Unordered pairs in each class.
    gamma : numpy.ndarray, shape (K,)
        ``sum((z_i - z_j)**2) / (2 n_pairs)``, units of the values squared.
    variance : float
        Population variance of the values used (the sill of an uncorrelated field).
    """

    lag_m: np.ndarray
    lag_edges_m: np.ndarray
    n_pairs: np.ndarray
    gamma: np.ndarray
    variance: float

    @property
    def normalised(self) -> np.ndarray:
        """``gamma / variance`` (NaN when the variance is 0)."""
        if not self.variance > 0:
            return np.full_like(self.gamma, np.nan)
        return self.gamma / self.variance


# --------------------------------------------------------------------------- validation helpers


def _json_float(v):
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


def _as_points(points, name: str = "points") -> np.ndarray:
    a = np.asarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputDataError(
            f"{name}: expected an (N, 3) array of x, y, z coordinates, got shape {a.shape}"
        )
    return a


def _check_cell_size(cell_size_m: float) -> float:
    try:
        c = float(cell_size_m)
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"cell_size_m must be a number of metres, got {cell_size_m!r}"
        ) from None
    if not (math.isfinite(c) and c > 0):
        raise InvalidParameterError(f"cell_size_m must be > 0 metres, got {cell_size_m!r}")
    return c


def _check_min_points(min_points: int) -> int:
    if isinstance(min_points, (bool, np.bool_)) or int(min_points) != min_points:
        raise InvalidParameterError(f"min_points must be an integer, got {min_points!r}")
    m = int(min_points)
    if m < 3:
        raise InvalidParameterError(
            f"min_points must be >= 3 (a plane needs 3 points; roughness needs more), got {m}"
        )
    return m


def _axis_index(ols_axis: Union[str, int]) -> int:
    if isinstance(ols_axis, (int, np.integer)) and not isinstance(ols_axis, bool):
        if 0 <= int(ols_axis) <= 2:
            return int(ols_axis)
    elif isinstance(ols_axis, str) and ols_axis.lower() in AXIS_NAMES:
        return AXIS_NAMES.index(ols_axis.lower())
    raise InvalidParameterError(
        f"ols_axis must be 'x', 'y', 'z' (or 'auto' where accepted), got {ols_axis!r}"
    )


def _bounds(points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    if points.shape[0] == 0:
        raise InputDataError("points: the cloud is empty; nothing to compute roughness on")
    lo, hi = bounds(points)
    # NaN propagates through min/max and inf shows as inf: one check covers both
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise InputDataError(
            "points: coordinates contain NaN or infinite values; remove those points first"
        )
    return lo, hi


def _default_chunk(n: int, chunk_points: int | None) -> int:
    if chunk_points is not None:
        if int(chunk_points) < 1:
            raise InvalidParameterError(f"chunk_points must be >= 1, got {chunk_points!r}")
        return int(chunk_points)
    return int(min(_MAX_CHUNK, max(_MIN_CHUNK, n // 16)))


def _grid_geometry(
    lo: np.ndarray, hi: np.ndarray, c: float, origin_m: Sequence[float] | None
) -> Tuple[np.ndarray, Tuple[int, int, int]]:
    extent = float(np.max(hi - lo))
    if c > extent:
        raise InvalidParameterError(
            f"cell_size_m = {c:g} m is larger than the extent of the cloud ({extent:.6g} m "
            "along its longest axis); choose a smaller cell size"
        )
    if origin_m is None:
        origin = np.floor(lo / c) * c
    else:
        origin = np.asarray(origin_m, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(origin)) or np.any(origin > lo):
            raise InvalidParameterError(
                "origin_m must be finite and at or below the smallest coordinates of the cloud"
            )
    span = np.floor((hi - origin) / c) + 1
    if np.any(span > 2.0**62):
        raise InvalidParameterError(
            f"cell_size_m = {c:g} m is too small for the extent of the cloud; use a larger cell"
        )
    shape = tuple(int(s) for s in span)
    if shape[0] * shape[1] * shape[2] >= 2**63:
        raise InvalidParameterError(
            f"cell_size_m = {c:g} m gives more than 2**63 grid cells over the cloud's bounding "
            "box; crop the cloud or use a larger cell"
        )
    return origin, shape  # type: ignore[return-value]


def _cell_index(points: np.ndarray, origin: np.ndarray, c: float) -> np.ndarray:
    """``floor((p - origin) / c)`` as int64, shape (n, 3).

    Column by column: long 1-D loops instead of a broadcast over rows of 3 (same values).
    """
    out = np.empty((points.shape[0], 3), dtype=np.int64)
    q = np.empty(points.shape[0])
    for k in range(3):
        np.subtract(points[:, k], origin[k], out=q)
        q /= c
        np.floor(q, out=q)
        out[:, k] = q
    return out


def _pack_index(ijk: np.ndarray, shape: Tuple[int, int, int]) -> np.ndarray:
    ijk = np.asarray(ijk, dtype=np.int64)
    return (ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]


def _unpack_keys(keys: np.ndarray, shape: Tuple[int, int, int]) -> np.ndarray:
    keys = np.asarray(keys, dtype=np.int64)
    iz = keys % shape[2]
    rest = keys // shape[2]
    return np.stack([rest // shape[1], rest % shape[1], iz], axis=1)


def _orient(vectors: np.ndarray) -> np.ndarray:
    """Flip unit vectors (M, 3) so that the last non-zero component (z, else y, else x) is > 0."""
    v = vectors
    ref = np.where(v[:, 2] != 0, v[:, 2], np.where(v[:, 1] != 0, v[:, 1], v[:, 0]))
    return np.where((ref < 0)[:, None], -v, v)


def _orient_largest(vectors: np.ndarray) -> np.ndarray:
    """Flip vectors (K, 3) so that their largest-magnitude component is positive."""
    idx = np.argmax(np.abs(vectors), axis=1)
    s = np.sign(vectors[np.arange(vectors.shape[0]), idx])
    s[s == 0] = 1.0
    return vectors * s[:, None]


def _ols_coefficients(cov: np.ndarray, a: int) -> np.ndarray:
    """Slopes ``(b1, b2)`` of ``a = b0 + b1 u + b2 w`` from centred covariances (M, 3, 3).

    Closed form of the 2x2 normal equations; a pseudo-inverse where they are singular (then the
    least-squares residuals are still unique).
    """
    u, w = [k for k in range(3) if k != a]
    suu, sww, suw = cov[:, u, u], cov[:, w, w], cov[:, u, w]
    sau, saw = cov[:, a, u], cov[:, a, w]
    det = suu * sww - suw * suw
    tr = suu + sww
    ok = det > _OLS_SINGULAR_RATIO * tr * tr
    beta = np.zeros((cov.shape[0], 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        beta[:, 0] = np.where(ok, (sww * sau - suw * saw) / np.where(ok, det, 1.0), 0.0)
        beta[:, 1] = np.where(ok, (suu * saw - suw * sau) / np.where(ok, det, 1.0), 0.0)
    bad = np.flatnonzero(~ok)
    if bad.size:
        sbb = np.stack(
            [np.stack([suu[bad], suw[bad]], -1), np.stack([suw[bad], sww[bad]], -1)], axis=-2
        )
        sab = np.stack([sau[bad], saw[bad]], axis=-1)
        pinv = np.linalg.pinv(sbb, rcond=1e-10)
        beta[bad] = np.einsum("mij,mj->mi", pinv, sab)
    return beta


# --------------------------------------------------------------------------- the fast kernel


_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


class _Accumulator:
    def __init__(self) -> None:
        self.parts: Dict[str, list] = {
            k: [] for k in ("keys", "n", "centroid", "normal", "eig", "odr", "ols", "degenerate")
        }
        self.n_cells_skipped = 0
        self.n_points_skipped = 0

    def add(self, **arrays) -> None:
        for k, v in arrays.items():
            self.parts[k].append(v)

    def cat(self, key: str, empty_shape: Tuple[int, ...], dtype=np.float64) -> np.ndarray:
        parts = self.parts[key]
        if not parts:
            return np.zeros(empty_shape, dtype=dtype)
        return np.concatenate(parts, axis=0)


def _process_cells(
    points: np.ndarray,
    idx: np.ndarray,
    keys: np.ndarray,
    *,
    origin: np.ndarray,
    c: float,
    shape: Tuple[int, int, int],
    min_points: int,
    a: int,
    signed: bool,
    acc: _Accumulator,
) -> None:
    """Roughness of the cells whose points are ``points[idx]`` (``keys`` sorted, whole cells)."""
    n = idx.shape[0]
    if n == 0:
        return
    brk = np.flatnonzero(keys[1:] != keys[:-1]) + 1
    starts = np.concatenate(([0], brk))
    counts = np.diff(np.append(starts, n))
    cell_keys = keys[starts]
    keep = counts >= min_points
    if not np.all(keep):
        acc.n_cells_skipped += int(np.count_nonzero(~keep))
        acc.n_points_skipped += int(counts[~keep].sum())
        idx = idx[np.repeat(keep, counts)]
        counts = counts[keep]
        cell_keys = cell_keys[keep]
        if counts.size == 0:
            return
        starts = np.concatenate(([0], np.cumsum(counts[:-1])))
    m = counts.shape[0]
    centre = origin + (_unpack_keys(cell_keys, shape) + 0.5) * c  # (m, 3)

    # pass 1: first and second moments about the cell centre
    r = np.take(points, idx, axis=0)
    r -= np.repeat(centre, counts, axis=0)
    s1 = np.add.reduceat(r, starts, axis=0)
    prod = np.empty((r.shape[0], 6))  # the 6 distinct second moments, column by column
    for j, (k, k2) in enumerate(_PAIRS):
        np.multiply(r[:, k], r[:, k2], out=prod[:, j])
    s2 = np.add.reduceat(prod, starts, axis=0)
    del prod
    cnt = counts.astype(np.float64)
    mean = s1 / cnt[:, None]
    cov = np.empty((m, 3, 3))
    for j, (k, k2) in enumerate(_PAIRS):
        cov[:, k, k2] = s2[:, j] / cnt - mean[:, k] * mean[:, k2]
        cov[:, k2, k] = cov[:, k, k2]
    evals, evecs = np.linalg.eigh(cov)
    normal = _orient(evecs[:, :, 0])
    degenerate = ~((evals[:, 1] > DEGENERATE_EIGEN_RATIO * evals[:, 2]) & (evals[:, 2] > 0))

    # pass 2: per-point distances d = r.n - mean.n and OLS residuals
    # e = r_a - b.r_uw - (mean_a - b.mean_uw)
    u, w = [k for k in range(3) if k != a]
    beta = _ols_coefficients(cov, a)
    coef = np.empty((m, 6))
    coef[:, 0:3] = normal
    coef[:, 3] = np.einsum("ij,ij->i", mean, normal)
    coef[:, 4:6] = beta
    k_ols = mean[:, a] - beta[:, 0] * mean[:, u] - beta[:, 1] * mean[:, w]
    rep = np.repeat(coef, counts, axis=0)
    stats = np.empty((r.shape[0], 4))
    d = stats[:, 0]
    np.einsum("ij,ij->i", r, rep[:, 0:3], out=d)
    d -= rep[:, 3]
    e = stats[:, 2]
    np.multiply(r[:, u], rep[:, 4], out=e)
    e += r[:, w] * rep[:, 5]
    np.subtract(r[:, a], e, out=e)
    e -= np.repeat(k_ols, counts)
    del rep
    np.multiply(d, d, out=stats[:, 1])
    np.multiply(e, e, out=stats[:, 3])
    if not signed:
        np.abs(d, out=d)
        np.abs(e, out=e)
    sums = np.add.reduceat(stats, starts, axis=0) / cnt[:, None]
    with np.errstate(invalid="ignore"):
        theta_odr = np.sqrt(np.maximum(sums[:, 1] - sums[:, 0] ** 2, 0.0))
        theta_ols = np.sqrt(np.maximum(sums[:, 3] - sums[:, 2] ** 2, 0.0))
    theta_odr[degenerate] = np.nan
    theta_ols[degenerate] = np.nan
    acc.add(
        keys=cell_keys,
        n=counts.astype(np.int64),
        centroid=centre + mean,
        normal=normal,
        eig=evals,
        odr=theta_odr,
        ols=theta_ols,
        degenerate=degenerate,
    )


def _finish(
    acc: _Accumulator,
    *,
    c: float,
    origin: np.ndarray,
    shape: Tuple[int, int, int],
    n_total: int,
    min_points: int,
    a: int,
    signed: bool,
) -> RoughnessGrid:
    keys = acc.cat("keys", (0,), np.int64)
    theta_odr = acc.cat("odr", (0,))
    theta_ols = acc.cat("ols", (0,))
    return RoughnessGrid(
        cell_size_m=c,
        origin_m=origin,
        shape=shape,
        index=_unpack_keys(keys, shape),
        n_points=acc.cat("n", (0,), np.int64),
        centroid_m=acc.cat("centroid", (0, 3)),
        normal=acc.cat("normal", (0, 3)),
        eigenvalues_m2=acc.cat("eig", (0, 3)),
        theta_odr=theta_odr,
        theta_ols=theta_ols,
        e_ols=np.abs(theta_ols - theta_odr),
        degenerate=acc.cat("degenerate", (0,), bool),
        n_cells_skipped=acc.n_cells_skipped,
        n_points_skipped=acc.n_points_skipped,
        n_points_total=n_total,
        min_points=min_points,
        ols_axis=AXIS_NAMES[a],
        signed=bool(signed),
    )


def _grid_roughness(
    pts: np.ndarray,
    *,
    c: float,
    min_points: int,
    a: int,
    signed: bool,
    origin_m: Sequence[float] | None,
    chunk_points: int | None,
    progress: ProgressCallback | None,
    packed: bool | None = None,
) -> RoughnessGrid:
    n = pts.shape[0]
    lo, hi = _bounds(pts)
    origin, shape = _grid_geometry(lo, hi, c, origin_m)
    chunk = _default_chunk(n, chunk_points)
    n_cells_box = shape[0] * shape[1] * shape[2]
    key_bits = max(1, (n_cells_box - 1).bit_length())
    idx_bits = max(1, (n - 1).bit_length())
    if packed is None:
        packed = key_bits + idx_bits <= 64
    elif packed and key_bits + idx_bits > 64:
        raise InvalidParameterError("packed keys do not fit in 64 bits for this cloud")

    # 1. integer cell keys, in chunks of the input (bounded temporaries)
    report(progress, 0.0, f"cell keys ({c:g} m)")
    if packed:
        sort_buf = np.empty(n, dtype=np.uint64)
    else:
        sort_buf = np.empty(n, dtype=np.int64)
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        # lo <= p <= hi and float subtraction/division are monotone, so 0 <= ijk < shape
        k = _pack_index(_cell_index(pts[s:e], origin, c), shape)
        if packed:
            kk = k.astype(np.uint64)
            kk <<= np.uint64(idx_bits)
            kk |= np.arange(s, e, dtype=np.uint64)
            sort_buf[s:e] = kk
        else:
            sort_buf[s:e] = k
        report(progress, 0.15 * e / n)

    # 2. one sort: packed (key << idx_bits | index) sorts in place; else a stable argsort
    report(progress, 0.15, f"sorting {n} cell keys")
    if packed:
        sort_buf.sort()
        order = None
    else:
        order = np.argsort(sort_buf, kind="stable")
    report(progress, 0.4, "cell statistics")

    # 3. whole cells per chunk of the sorted order
    acc = _Accumulator()
    mask = np.uint64((1 << idx_bits) - 1)
    shift = np.uint64(idx_bits)
    s = 0
    while s < n:
        e = min(n, s + chunk)
        if packed:
            if e < n:
                last = sort_buf[e - 1] >> shift
                e = int(np.searchsorted(sort_buf, (last + np.uint64(1)) << shift, side="left"))
            block = sort_buf[s:e]
            idx = (block & mask).astype(np.int64)
            keys = (block >> shift).astype(np.int64)
        else:
            if e < n:
                e = _cell_boundary(sort_buf, order, e, chunk)
            idx = order[s:e]
            keys = sort_buf[idx]
        _process_cells(
            pts,
            idx,
            keys,
            origin=origin,
            c=c,
            shape=shape,
            min_points=min_points,
            a=a,
            signed=signed,
            acc=acc,
        )
        s = e
        report(progress, 0.4 + 0.6 * e / n)
    del sort_buf, order
    return _finish(
        acc, c=c, origin=origin, shape=shape, n_total=n, min_points=min_points, a=a, signed=signed
    )


def _cell_boundary(keys: np.ndarray, order: np.ndarray, e: int, step: int) -> int:
    """Smallest ``p >= e`` where ``keys[order[p]]`` differs from ``keys[order[e - 1]]`` (or N)."""
    n = order.shape[0]
    last = keys[order[e - 1]]
    while e < n:
        seg = keys[order[e : e + step]]
        p = int(np.searchsorted(seg, last, side="right"))
        if p < seg.shape[0]:
            return e + p
        e += seg.shape[0]
    return n


def grid_roughness(
    points: np.ndarray,
    *,
    cell_size_m: float,
    min_points: int = _DEFAULT_MIN_POINTS,
    ols_axis: Union[str, int] = "z",
    signed: bool = False,
    origin_m: Sequence[float] | None = None,
    chunk_points: int | None = None,
    progress: ProgressCallback | None = None,
) -> RoughnessGrid:
    """ODR and OLS roughness of every cell of a regular 3D grid (Pollyea & Fairley 2011).

    Parameters
    ----------
    points : numpy.ndarray, shape (N, 3)
        Coordinates, metres (any offsets: moments are taken about each cell's centre). Not
        modified.
    cell_size_m : float
        Cell edge, metres; > 0 and not larger than the cloud's longest extent.
    min_points : int, default 10
        Cells with fewer points are skipped and counted (``n_cells_skipped``). At least 3.
    ols_axis : {"x", "y", "z", "auto"} or int, default "z"
        Dependent axis of the OLS comparison plane (the study used the exposure-normal axis
        ``y``). ``"auto"``: the coordinate axis closest to the normal of the cloud's principal
        plane (see :func:`resolve_ols_axis`).
    signed : bool, default False
        False: Eq. 4 as published, the population standard deviation of the *absolute*
        distances. True: of the signed distances (the RMS distance to the plane).
    origin_m : sequence of 3 float, optional
        Lower corner of cell (0, 0, 0). Default: the minimum coordinates floored to a multiple of
        the cell size (so grids of sizes c and c/2 nest).
    chunk_points : int, optional
        Points processed at once (memory bound); default ``min(2**20, max(2**16, N // 16))``.
    progress : ProgressCallback, optional

    Returns
    -------
    RoughnessGrid
        Cells sorted by key; ``theta_odr``, ``theta_ols``, ``e_ols`` in metres.

    Raises
    ------
    InputDataError
        Empty cloud, wrong shape, NaN or infinite coordinates.
    InvalidParameterError
        ``cell_size_m <= 0`` or larger than the extent, ``min_points < 3``, bad ``ols_axis``.

    Notes
    -----
    One sort of ``N`` 64-bit integers: the cell key (``(ix*ny + iy)*nz + iz``) and the point
    index packed in one ``uint64`` when they fit (else a stable argsort of the keys). Cells
    are then processed in chunks of whole cells: per-cell first and second moments with
    ``np.add.reduceat`` on coordinates relative to the cell centre, batched
    ``np.linalg.eigh`` of the (M, 3, 3) covariances, and a second pass over the chunk's points
    for the distance statistics ``sqrt(E[D^2] - E[D]^2)``. Extra memory: 8 bytes per point plus
    one chunk.
    """
    pts = _as_points(points)
    c = _check_cell_size(cell_size_m)
    mp = _check_min_points(min_points)
    if isinstance(ols_axis, str) and ols_axis.lower() == "auto":
        if pts.shape[0] == 0:
            _bounds(pts)
        ols_axis = resolve_ols_axis(principal_frame(pts, chunk_points=chunk_points), "auto")
    a = _axis_index(ols_axis)
    return _grid_roughness(
        pts,
        c=c,
        min_points=mp,
        a=a,
        signed=bool(signed),
        origin_m=origin_m,
        chunk_points=chunk_points,
        progress=progress,
    )


def grid_roughness_multi(
    points: np.ndarray,
    *,
    cell_sizes_m: Sequence[float],
    min_points: int = _DEFAULT_MIN_POINTS,
    ols_axis: Union[str, int] = "z",
    signed: bool = False,
    chunk_points: int | None = None,
    progress: ProgressCallback | None = None,
) -> Tuple[RoughnessGrid, ...]:
    """:func:`grid_roughness` at several cell sizes (the study: 1, 0.5, 0.25, 0.125 m).

    All sizes are validated before any work. Returns one :class:`RoughnessGrid` per size, in the
    order given. Other parameters as :func:`grid_roughness`.
    """
    pts = _as_points(points)
    sizes = [_check_cell_size(c) for c in cell_sizes_m]
    if not sizes:
        raise InvalidParameterError("cell_sizes_m: give at least one cell size")
    lo, hi = _bounds(pts)
    for c in sizes:
        _grid_geometry(lo, hi, c, None)
    mp = _check_min_points(min_points)
    if isinstance(ols_axis, str) and ols_axis.lower() == "auto":
        ols_axis = resolve_ols_axis(principal_frame(pts, chunk_points=chunk_points), "auto")
    a = _axis_index(ols_axis)
    out = []
    for i, c in enumerate(sizes):
        out.append(
            _grid_roughness(
                pts,
                c=c,
                min_points=mp,
                a=a,
                signed=bool(signed),
                origin_m=None,
                chunk_points=chunk_points,
                progress=scaled(progress, i / len(sizes), (i + 1) / len(sizes)),
            )
        )
    return tuple(out)


# --------------------------------------------------------------------------- the reference


def grid_roughness_reference(
    points: np.ndarray,
    *,
    cell_size_m: float,
    min_points: int = _DEFAULT_MIN_POINTS,
    ols_axis: Union[str, int] = "z",
    signed: bool = False,
    origin_m: Sequence[float] | None = None,
) -> RoughnessGrid:
    """Slow, obvious per-cell loop with ``np.linalg.svd`` and ``np.linalg.lstsq`` (test oracle).

    Same parameters and result as :func:`grid_roughness` (``ols_axis`` must be x/y/z). Per
    cell: subtract the grid origin, then the cell centroid; the normal is the last right
    singular vector; ``D = |Q n|``; ``theta = np.std(D)`` (ddof=0); OLS by ``lstsq`` on
    ``[1, u, w]``.
    """
    pts = _as_points(points)
    c = _check_cell_size(cell_size_m)
    mp = _check_min_points(min_points)
    a = _axis_index(ols_axis)
    u, w = [k for k in range(3) if k != a]
    lo, hi = _bounds(pts)
    origin, shape = _grid_geometry(lo, hi, c, origin_m)
    keys = _pack_index(_cell_index(pts, origin, c), shape)
    order = np.argsort(keys, kind="stable")
    uniq, starts = np.unique(keys[order], return_index=True)
    groups = np.split(order, starts[1:])
    rows = []
    skipped_cells = skipped_points = 0
    for key, members in zip(uniq, groups):
        if members.size < mp:
            skipped_cells += 1
            skipped_points += members.size
            continue
        p = pts[members] - origin
        centroid = p.mean(axis=0)
        q = p - centroid
        _, sv, vt = np.linalg.svd(q, full_matrices=False)
        normal = _orient(vt[-1][None, :])[0]
        evals = np.sort(sv**2 / members.size)
        degenerate = not (evals[1] > DEGENERATE_EIGEN_RATIO * evals[2] and evals[2] > 0)
        dist = q @ normal
        design = np.column_stack([np.ones(members.size), p[:, u], p[:, w]])
        coef, *_ = np.linalg.lstsq(design, p[:, a], rcond=None)
        resid = p[:, a] - design @ coef
        if not signed:
            dist, resid = np.abs(dist), np.abs(resid)
        t_odr, t_ols = float(np.std(dist)), float(np.std(resid))
        if degenerate:
            t_odr = t_ols = np.nan
        rows.append((key, members.size, centroid + origin, normal, evals, t_odr, t_ols, degenerate))
    m = len(rows)
    keys_out = np.array([r[0] for r in rows], dtype=np.int64)
    theta_odr = np.array([r[5] for r in rows], dtype=np.float64)
    theta_ols = np.array([r[6] for r in rows], dtype=np.float64)
    return RoughnessGrid(
        cell_size_m=c,
        origin_m=origin,
        shape=shape,
        index=_unpack_keys(keys_out, shape),
        n_points=np.array([r[1] for r in rows], dtype=np.int64),
        centroid_m=np.array([r[2] for r in rows]).reshape(m, 3),
        normal=np.array([r[3] for r in rows]).reshape(m, 3),
        eigenvalues_m2=np.array([r[4] for r in rows]).reshape(m, 3),
        theta_odr=theta_odr,
        theta_ols=theta_ols,
        e_ols=np.abs(theta_ols - theta_odr),
        degenerate=np.array([r[7] for r in rows], dtype=bool),
        n_cells_skipped=skipped_cells,
        n_points_skipped=skipped_points,
        n_points_total=pts.shape[0],
        min_points=mp,
        ols_axis=AXIS_NAMES[a],
        signed=bool(signed),
    )


def odr_plane_closed_form(points: np.ndarray, *, centred: bool = True) -> np.ndarray:
    """The study's Eq. 2, ``beta = (X^T X - sigma^2 I)^-1 X^T z``, for one set of points.

    Parameters
    ----------
    points : numpy.ndarray, shape (n, 3)
    centred : bool, default True
        True: ``X = [x - mean(x), y - mean(y)]`` and ``z - mean(z)`` (2 unknown slopes, then
        ``beta0 = mean(z) - beta1 mean(x) - beta2 mean(y)``): this *is* the orthogonal
        regression plane. False: Eq. 2 read literally with ``X = [1, x, y]`` and ``sigma`` the
        smallest singular value of ``[1, x, y, z]``; this treats the column of ones as noisy
        data and is *not* the orthogonal regression plane unless the centroid is at the origin.

    Returns
    -------
    numpy.ndarray, shape (3,)
        ``(beta0, beta1, beta2)`` of ``z = beta0 + beta1 x + beta2 y`` (Eq. 1). Undefined
        (huge or inf) for planes containing the z direction, which Eq. 1 cannot represent.
    """
    p = _as_points(points)
    if centred:
        mean = p.mean(axis=0)
        q = p - mean
        x = q[:, :2]
        z = q[:, 2]
        sigma = np.linalg.svd(q, compute_uv=False)[-1]
        slopes = np.linalg.solve(x.T @ x - sigma**2 * np.eye(2), x.T @ z)
        return np.array([mean[2] - slopes @ mean[:2], slopes[0], slopes[1]])
    x = np.column_stack([np.ones(p.shape[0]), p[:, 0], p[:, 1]])
    z = p[:, 2]
    sigma = np.linalg.svd(np.column_stack([x, z]), compute_uv=False)[-1]
    return np.linalg.solve(x.T @ x - sigma**2 * np.eye(3), x.T @ z)


# --------------------------------------------------------------------------- per point


def roughness_per_point(
    points: np.ndarray,
    grid: RoughnessGrid,
    *,
    value: str = "theta_odr",
    chunk_points: int | None = None,
) -> np.ndarray:
    """Each point's cell value (the ``Roughness`` dimension of LAS and PDAL outputs).

    Parameters
    ----------
    points : numpy.ndarray, shape (N, 3)
        Usually the cloud the grid was computed from (any points work).
    grid : RoughnessGrid
    value : {"theta_odr", "theta_ols", "e_ols"}
    chunk_points : int, optional

    Returns
    -------
    numpy.ndarray, shape (N,), float64
        The value of the point's cell; NaN for points outside the grid, in skipped cells (fewer
        than ``min_points``) or in degenerate cells.
    """
    if value not in ("theta_odr", "theta_ols", "e_ols"):
        raise InvalidParameterError(
            f"value must be 'theta_odr', 'theta_ols' or 'e_ols', got {value!r}"
        )
    pts = _as_points(points)
    n = pts.shape[0]
    out = np.full(n, np.nan)
    if n == 0 or len(grid) == 0:
        return out
    values = getattr(grid, value)
    cell_keys = grid.keys
    shape = np.asarray(grid.shape, dtype=np.int64)
    chunk = _default_chunk(n, chunk_points)
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        with np.errstate(invalid="ignore"):
            ijk = _cell_index(pts[s:e], grid.origin_m, grid.cell_size_m)
        inside = np.all((ijk >= 0) & (ijk < shape), axis=1)
        k = _pack_index(ijk, grid.shape)
        pos = np.searchsorted(cell_keys, k)
        pos_c = np.minimum(pos, cell_keys.size - 1)
        hit = inside & (cell_keys[pos_c] == k)
        out[s:e] = np.where(hit, values[pos_c], np.nan)
    return out


# --------------------------------------------------------------------------- statistics


def roughness_stats(values: np.ndarray) -> RoughnessStats:
    """Min, max, mean, population variance and std of the finite values (NaN if none)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if v.size == 0:
        nan = float("nan")
        return RoughnessStats(0, nan, nan, nan, nan, nan)
    var = float(np.var(v))
    return RoughnessStats(
        n=int(v.size),
        minimum=float(v.min()),
        maximum=float(v.max()),
        mean=float(v.mean()),
        variance=var,
        std=math.sqrt(var),
    )


def summarize_roughness(grid: RoughnessGrid) -> RoughnessSummary:
    """The study's Table 1 for one grid: cells, mean points per cell, and the ODR / OLS stats.

    ``n_cells`` counts the cells evaluated (at least ``min_points`` points, degenerate ones
    included); the statistics use the non-degenerate cells.
    """
    n_cells = len(grid)
    return RoughnessSummary(
        cell_size_m=grid.cell_size_m,
        n_cells=n_cells,
        mean_points_per_cell=float(grid.n_points.mean()) if n_cells else float("nan"),
        n_cells_skipped=grid.n_cells_skipped,
        n_points_skipped=grid.n_points_skipped,
        n_degenerate=grid.n_degenerate,
        odr=roughness_stats(grid.theta_odr),
        ols=roughness_stats(grid.theta_ols),
        e_ols=roughness_stats(grid.e_ols),
        ols_axis=grid.ols_axis,
        signed=grid.signed,
        min_points=grid.min_points,
    )


def normalise_range(values: np.ndarray) -> np.ndarray:
    """``(v - min) / (max - min)`` over the finite values (the study's "normalised over range").

    NaN stays NaN; a constant field maps to 0.
    """
    v = np.asarray(values, dtype=np.float64)
    fin = np.isfinite(v)
    out = np.full(v.shape, np.nan)
    if not np.any(fin):
        return out
    lo, hi = float(v[fin].min()), float(v[fin].max())
    out[fin] = (v[fin] - lo) / (hi - lo) if hi > lo else 0.0
    return out


def binary_transform(normalised: np.ndarray, *, cutoff: float = 0.05) -> np.ndarray:
    """1.0 where ``normalised >= cutoff``, 0.0 below, NaN where NaN (the study's Fig. 2).

    Raises
    ------
    InvalidParameterError
        If ``cutoff`` is not within [0, 1].
    """
    if not (0.0 <= float(cutoff) <= 1.0):
        raise InvalidParameterError(f"cutoff must be within [0, 1] (normalised), got {cutoff!r}")
    v = np.asarray(normalised, dtype=np.float64)
    out = np.where(v >= cutoff, 1.0, 0.0)
    out[~np.isfinite(v)] = np.nan
    return out


def roughness_histogram(
    normalised: np.ndarray, *, bin_width: float = 0.05
) -> Tuple[np.ndarray, np.ndarray]:
    """Histogram of normalised roughness on [0, 1] (the study's Fig. 3).

    Returns
    -------
    edges : numpy.ndarray, shape (K + 1,)
    fraction : numpy.ndarray, shape (K,)
        Fraction of the finite values in each bin (the last bin includes 1).
    """
    if not (0 < bin_width <= 1):
        raise InvalidParameterError(f"bin_width must be within (0, 1], got {bin_width!r}")
    v = np.asarray(normalised, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    k = int(round(1.0 / bin_width))
    edges = np.linspace(0.0, 1.0, k + 1)
    counts, _ = np.histogram(v, bins=edges)
    frac = counts / v.size if v.size else np.zeros(k)
    return edges, frac


# --------------------------------------------------------------------------- frames and maps


def principal_frame(points: np.ndarray, *, chunk_points: int | None = None) -> PrincipalFrame:
    """Principal axes of a cloud (covariance accumulated in chunks about the bounding-box centre).

    Parameters
    ----------
    points : numpy.ndarray, shape (N, 3)

    Returns
    -------
    PrincipalFrame
    """
    pts = _as_points(points)
    lo, hi = _bounds(pts)
    ref = 0.5 * (lo + hi)
    n = pts.shape[0]
    chunk = _default_chunk(n, chunk_points)
    s1 = np.zeros(3)
    s2 = np.zeros((3, 3))
    for s in range(0, n, chunk):
        q = pts[s : s + chunk] - ref
        s1 += q.sum(axis=0)
        s2 += q.T @ q
    mean = s1 / n
    cov = s2 / n - np.outer(mean, mean)
    evals, evecs = np.linalg.eigh(cov)
    axes = _orient_largest(evecs[:, ::-1].T.copy())
    return PrincipalFrame(centroid_m=ref + mean, axes=axes, eigenvalues_m2=evals[::-1].copy())


def resolve_ols_axis(frame: PrincipalFrame, ols_axis: Union[str, int] = "auto") -> str:
    """``ols_axis`` as "x"/"y"/"z"; ``"auto"`` is the axis closest to the principal normal.

    For an outcrop exported parallel to the xz plane (the study) that is ``"y"``; for map-view
    surveys ``"z"``.
    """
    if isinstance(ols_axis, str) and ols_axis.lower() == "auto":
        return AXIS_NAMES[int(np.argmax(np.abs(frame.normal)))]
    return AXIS_NAMES[_axis_index(ols_axis)]


_PLANES = {
    "xy": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), ("x (m)", "y (m)")),
    "xz": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), ("x (m)", "z (m)")),
    "yz": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0), ("y (m)", "z (m)")),
}


def choose_map_plane(
    frame: PrincipalFrame, plane: str = "auto", *, snap_angle_deg: float = 15.0
) -> MapPlane:
    """The map plane for rasters and figures.

    Parameters
    ----------
    frame : PrincipalFrame
        Of the whole cloud.
    plane : {"auto", "xy", "xz", "yz", "principal"}
        ``"auto"``: the principal plane of the cloud (its two largest principal axes), snapped
        to the coordinate plane whose normal is within ``snap_angle_deg`` of the principal normal
        (so map-view surveys get a georeferenced ``xy`` raster and outcrops exported parallel to
        ``xz`` an ``x``/``z`` raster); ``"principal"`` never snaps.
    snap_angle_deg : float, default 15

    Returns
    -------
    MapPlane
    """
    name = str(plane).lower()
    if name not in ("auto", "xy", "xz", "yz", "principal"):
        raise InvalidParameterError(
            f"map plane must be 'auto', 'xy', 'xz', 'yz' or 'principal', got {plane!r}"
        )
    if name == "auto":
        k = int(np.argmax(np.abs(frame.normal)))
        angle = math.degrees(math.acos(min(1.0, abs(float(frame.normal[k])))))
        if angle <= snap_angle_deg:
            name = ("yz", "xz", "xy")[k]
        else:
            name = "principal"
        log.debug("map plane: %s (principal normal %.1f deg from %s)", name, angle, "xyz"[k])
    if name in _PLANES:
        u, v, labels = _PLANES[name]
        ua, va = np.array(u), np.array(v)
        return MapPlane(name, np.zeros(3), ua, va, np.cross(ua, va), labels)
    u_axis, v_axis = frame.axes[0].copy(), frame.axes[1].copy()
    return MapPlane(
        "principal",
        frame.centroid_m.copy(),
        u_axis,
        v_axis,
        np.cross(u_axis, v_axis),
        ("u, principal axis 1 (m)", "v, principal axis 2 (m)"),
    )


def rasterize_cells(
    centres_m: np.ndarray,
    values: np.ndarray,
    plane: MapPlane,
    *,
    pixel_size_m: float,
) -> MapRaster:
    """Average cell values over the cells stacked along the map normal, on a north-up raster.

    Parameters
    ----------
    centres_m : numpy.ndarray, shape (M, 3)
        Cell centres.
    values : numpy.ndarray, shape (M,) or (M, B)
        One or B values per cell; NaN values are ignored.
    plane : MapPlane
    pixel_size_m : float
        Usually the cell size. Pixel edges are multiples of it in map coordinates, so the
        pixels of a coordinate plane coincide with the grid columns.

    Returns
    -------
    MapRaster
        ``values`` shape (B, rows, cols) (B = 1 for 1-D input).
    """
    px = _check_cell_size(pixel_size_m)
    vals = np.asarray(values, dtype=np.float64)
    if vals.ndim == 1:
        vals = vals[:, None]
    uv = plane.project(centres_m)
    if uv.shape[0] != vals.shape[0]:
        raise InvalidParameterError("rasterize_cells: centres_m and values differ in length")
    if uv.shape[0] == 0:
        return MapRaster(
            np.full((vals.shape[1], 0, 0), np.nan),
            np.zeros((0, 0), np.int64),
            (0.0, 0.0),
            px,
            plane,
        )
    col_i = np.floor(uv[:, 0] / px).astype(np.int64)
    row_i = np.floor(uv[:, 1] / px).astype(np.int64)
    c0, r1 = int(col_i.min()), int(row_i.max())
    cols = int(col_i.max()) - c0 + 1
    rows = r1 - int(row_i.min()) + 1
    col = col_i - c0
    row = r1 - row_i
    flat = row * cols + col
    size = rows * cols
    count = np.bincount(flat, minlength=size).reshape(rows, cols)
    out = np.full((vals.shape[1], rows, cols), np.nan)
    for b in range(vals.shape[1]):
        fin = np.isfinite(vals[:, b])
        num = np.bincount(flat[fin], weights=vals[fin, b], minlength=size)
        den = np.bincount(flat[fin], minlength=size)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[b] = np.where(den > 0, num / np.maximum(den, 1), np.nan).reshape(rows, cols)
    return MapRaster(out, count, (c0 * px, (r1 + 1) * px), px, plane)


_FFT_MAX_ELEMENTS = 1 << 25


def semivariogram_raster(
    values: np.ndarray,
    *,
    pixel_size_m: float,
    max_lag_m: float | None = None,
    n_lags: int | None = None,
) -> Semivariogram:
    """Experimental isotropic semivariogram of a raster with gaps, over all pixel pairs (FFT).

    ``gamma(h) = sum over pairs at separation in class h of (z_i - z_j)^2 / (2 N(h))`` computed
    exactly with FFT cross-correlations of the value and indicator rasters (Marcotte 1996).

    Parameters
    ----------
    values : numpy.ndarray, shape (rows, cols)
        NaN = no data.
    pixel_size_m : float
    max_lag_m : float, optional
        Largest separation; default half the raster's largest dimension.
    n_lags : int, optional
        Number of equal lag classes; default ``min(40, max_lag / pixel)``.

    Returns
    -------
    Semivariogram

    Notes
    -----
    Rasters whose padded FFT would exceed 2**25 elements are first block-averaged by an integer
    factor (logged), which coarsens the pixel accordingly.
    """
    z = np.asarray(values, dtype=np.float64)
    if z.ndim != 2:
        raise InvalidParameterError("semivariogram_raster: values must be a 2-D raster")
    px = _check_cell_size(pixel_size_m)
    factor = 1
    while (2 * math.ceil(z.shape[0] / factor)) * (2 * math.ceil(z.shape[1] / factor)) > (
        _FFT_MAX_ELEMENTS
    ):
        factor += 1
    if factor > 1:
        log.info("semivariogram: raster block-averaged by %d to bound the FFT size", factor)
        z = _block_mean(z, factor)
        px *= factor
    rows, cols = z.shape
    ind = np.isfinite(z)
    nvalid = int(ind.sum())
    if max_lag_m is None:
        max_lag_m = 0.5 * max(rows, cols) * px
    max_lag_m = float(max_lag_m)
    if not max_lag_m > 0:
        raise InvalidParameterError(f"max_lag_m must be > 0, got {max_lag_m!r}")
    if n_lags is None:
        n_lags = int(max(1, min(40, round(max_lag_m / px))))
    edges = np.linspace(0.0, max_lag_m, int(n_lags) + 1)
    if nvalid < 2:
        k = edges.size - 1
        return Semivariogram(
            np.full(k, np.nan), edges, np.zeros(k, np.int64), np.full(k, np.nan), float("nan")
        )
    mean = float(z[ind].mean())
    variance = float(np.var(z[ind]))
    zc = np.where(ind, z - mean, 0.0)
    fi = ind.astype(np.float64)
    shape = (2 * rows, 2 * cols)
    f_i = np.fft.rfft2(fi, shape)
    f_z = np.fft.rfft2(zc, shape)
    f_z2 = np.fft.rfft2(zc * zc, shape)

    def corr(fa, fb):  # sum_x a(x) b(x + h) for every lag h (circular on the padded grid)
        return np.fft.irfft2(np.conj(fa) * fb, shape)

    npairs = np.rint(corr(f_i, f_i))
    # sum over ordered pairs (x, x+h) of (z(x+h) - z(x))^2
    sq = corr(f_i, f_z2) + corr(f_z2, f_i) - 2.0 * corr(f_z, f_z)
    dy = np.fft.fftfreq(shape[0], 1.0 / shape[0])[:, None]
    dx = np.fft.fftfreq(shape[1], 1.0 / shape[1])[None, :]
    h = np.hypot(dy, dx) * px
    sel = (npairs > 0.5) & (h > 0) & (h <= max_lag_m)
    cls = np.clip(np.searchsorted(edges, h[sel], side="left") - 1, 0, edges.size - 2)
    k = edges.size - 1
    n_ord = np.bincount(cls, weights=npairs[sel], minlength=k)
    s_ord = np.bincount(cls, weights=sq[sel], minlength=k)
    h_sum = np.bincount(cls, weights=npairs[sel] * h[sel], minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        gamma = np.where(n_ord > 0, np.maximum(s_ord, 0.0) / (2.0 * n_ord), np.nan)
        lag = np.where(n_ord > 0, h_sum / n_ord, np.nan)
    # each unordered pair appears at h and -h
    return Semivariogram(lag, edges, np.rint(n_ord / 2).astype(np.int64), gamma, variance)


def _block_mean(z: np.ndarray, f: int) -> np.ndarray:
    rows, cols = z.shape
    r2, c2 = math.ceil(rows / f) * f, math.ceil(cols / f) * f
    pad = np.full((r2, c2), np.nan)
    pad[:rows, :cols] = z
    blocks = pad.reshape(r2 // f, f, c2 // f, f)
    fin = np.isfinite(blocks)
    num = np.where(fin, blocks, 0.0).sum(axis=(1, 3))
    den = fin.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.maximum(den, 1), np.nan)
