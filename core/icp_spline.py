"""One smooth displacement field fitted to all points at once: point-to-plane ICP of a cubic
B-spline free-form deformation (issue #18).

A windowed-ICP cell moves rigidly (or affinely), so it measures the mean motion of its points.
On a lobe a few cells wide that mean differs from the motion at the cell's centre by
centimetres, and window deformation (a spline through the cells' values, then a residual
fit per cell) converges to a field whose cell *means* match the data's; with three or four
cells across a lobe that spline cannot hold the lobe's curvature, and 1-2 cm stay (docs/
fields.md). Here the field itself is the unknown: a bicubic B-spline of the horizontal
position, one 3-vector of coefficients per knot, with knots ``spacing_m`` apart
(half a cell by default), fitted by Gauss-Newton to the point-to-plane residuals of every
point of epoch 2 moved back by the field,

    v_p = n_p . (a_p - u(a_p) - b_p),        u(x, y) = sum_k B_k(x, y) c_k,

with a penalty on the coefficients' second differences (it fixes knots without data and
damps the noise; it also flattens a field's sharpest peaks a little: docs/fields.md). Its
weight per component is estimated from the data by variance-component estimation (the
geodetic way to weigh observations against a prior), or given relative to the median
diagonal of the normal matrix. With the honest-σ model (:func:`cell_data_weights`) each
cell's points are weighed by their share of independent observations and the penalty's
weight is estimated per second difference, from the rows around it (docs/fields.md, "The
spline's data weights and a local penalty").

Written here, not taken from a library: the registration libraries at hand (Open3D, py4dgeo,
scipy) offer rigid or per-point motion only, and the B-spline basis is a few lines of numpy.
The normal matrix is sparse (each point touches 16 knots x 3 components); it is assembled
per knot interval with one dense product each and solved with SciPy's sparse LU.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple

import numpy as np

from .errors import InputDataError, InvalidParameterError
from .icp_options import (
    MAD_TO_SIGMA,
    _Options,
    _robust_weights,
    _shared_target_inflation,
)
from .progress import ProgressCallback, report, scaled
from .threads import single_blas_thread

log = logging.getLogger(__name__)

#: the fit stops when the field's RMS change at the points falls below this share of the
#: residuals' robust spread, or stops falling for STALL_ITERATIONS iterations
CHANGE_FLOOR = 0.02
STALL_ITERATIONS = 3
#: once a step is no smaller than the smallest so far (the nearest-neighbour pairs jitter as
#: the field moves), the pairs and their robust weights are held and the iterations go on
#: on that quadratic problem (:meth:`SplineChunk.held_normal_equations`); only once the
#: step is below HOLD_SHARE of the residuals' robust spread (a field still moving towards a
#: step or a lobe makes a larger step now and then, which is not the pairs' jitter)
HOLD_PAIRS = True
HOLD_SHARE = 0.25
#: ``smoothing=None``: the penalty weights are estimated (variance components) from this start
AUTO_START = 0.01
TRACE_EXACT_MAX = 300
#: the estimated weights are kept once no component moves by more than this share
AUTO_SETTLED = 0.02
#: bounds of the estimated weights, relative to the median diagonal of the normal matrix
AUTO_RANGE = (1e-6, 1e4)
TRACE_PROBES = 32
#: most knots of one spline field: the sparse normal matrix has 3 x knots unknowns and its
#: LU factor grows faster than that (250 000 knots: 750 000 unknowns, gigabytes)
MAX_KNOTS = 250_000
#: fewest cells with points a spline field is fitted to (its start is interpolated from them)
MIN_SPLINE_CELLS = 4
#: widths (in knot spacings) of the local penalty's Gaussian kernel
#: (:func:`_local_variance_components`) compared by their restricted likelihood
#: (:func:`_restricted_score`) when the smoothing is estimated with cell weights; one width:
#: no choice. Half a knot spacing (each second difference's variance from itself and its
#: nearest rows: the field bends where the data bend) against two (a cell at the default
#: spacing): on the harness the likelihood takes the narrow kernel on the lobes, the slump
#: and the fault, the wide one on the near-uniform shift (seed 0: lobes 1.01 / 1.25 / 1.77
#: -> 0.68 / 1.10 / 1.31 cm, slump 10.3 -> 3.2 cm, shift 0.24 cm kept; the fault 1.42 ->
#: 1.86 cm): docs/fields.md, "The local penalty's width chosen by the likelihood"
LOCAL_WIDTHS_KNOTS: Tuple[float, ...] = (0.5, 2.0)
#: how the penalty weighs the horizontal components: "axes", one weight for x and one for
#: y; "pooled", one for both; "principal", a 2 x 2 weight matrix (the horizontal second
#: differences' precision) estimated in the frame of the motion itself, so that a field
#: turned about the vertical is penalised alike and a motion along one direction still
#: leaves the other held (:func:`_horizontal_update`)
#: "principal" is the default since stop 54: over six seeds and the motion turned 0°, 20°
#: and 45° (18 scenes a case) the TLS lobes gain 9-17 % of far-cell RMSE (lobe-round 1.14
#: -> 0.99 cm, lobe-small 1.15 -> 0.94, lobe-long 1.41 -> 1.28), the other cases and every
#: ALS case stay level (ratios 0.99-1.11, each 90 % interval holding 1), and the estimate no
#: longer depends on how the map grid is turned against the motion ("axes" flattened a
#: component only when the motion had none along that grid axis): docs/fields.md, "The
#: penalty in the motion's own frame"
HORIZONTAL_MODEL = "principal"


class SplineSizeError(InvalidParameterError):
    """The knot spacing gives more knots than one fit can hold (``knots``; ``smallest_m``:
    the smallest spacing that fits, metres)."""

    def __init__(self, text: str, *, knots: int, smallest_m: float):
        super().__init__(text)
        self.knots = knots
        self.smallest_m = smallest_m


class SplineCellsError(InputDataError):
    """Too few cells with points for a spline field (``cells``: how many there are)."""

    def __init__(self, text: str, *, cells: int):
        super().__init__(text)
        self.cells = cells


def n_knots(span_xy, spacing_m: float) -> int:
    """Knots of a bicubic spline field of ``spacing_m`` over a ``span_xy`` (w, h) metres."""
    n = np.maximum(np.ceil(np.asarray(span_xy, dtype=np.float64) / spacing_m), 1) + 3
    return int(float(n[0]) * float(n[1]))


def check_spline_size(span_xy, spacing_m: float) -> None:
    """Refuse a knot spacing that gives more than :data:`MAX_KNOTS` knots over ``span_xy``
    (w, h) metres, before anything is allocated.

    Raises
    ------
    SplineSizeError
        With the knot count and the smallest spacing that fits (two significant digits).
    """
    k = n_knots(span_xy, spacing_m)
    if k <= MAX_KNOTS:
        return
    h = float(spacing_m)
    while n_knots(span_xy, h) > MAX_KNOTS:
        h = float(f"{h * 1.05:.2g}") if float(f"{h * 1.05:.2g}") > h else h * 1.05
    w, d = (float(v) for v in span_xy)
    raise SplineSizeError(
        f"a knot spacing of {spacing_m:g} m gives {k:.3g} knots over the data's "
        f"{w:.1f} x {d:.1f} m, more than the {MAX_KNOTS} one spline field can hold; use "
        f"{h:.2g} m or more",
        knots=k,
        smallest_m=h,
    )


__all__ = [
    "bspline_weights",
    "cell_data_weights",
    "ChunkNormals",
    "ChunkReport",
    "fit_spline_chunks",
    "fit_spline_field",
    "knot_copies",
    "knot_frame",
    "rigid_projection",
    "sided_second_differences",
    "spline_basis",
    "SplineChunk",
    "SplineField",
    "SplineFit",
    "Weighting",
]


def bspline_weights(t: np.ndarray) -> np.ndarray:
    """Uniform cubic B-spline weights of the 4 knots around fractional position ``t``.

    Parameters
    ----------
    t : (P,) float64
        Position within the knot interval, 0 <= t < 1.

    Returns
    -------
    (P, 4) float64
        Weights of knots ``i-1, i, i+1, i+2`` (sum 1).
    """
    t2, t3 = t * t, t * t * t
    return np.stack(
        [(1 - t) ** 3 / 6, (3 * t3 - 6 * t2 + 4) / 6, (-3 * t3 + 3 * t2 + 3 * t + 1) / 6, t3 / 6],
        axis=1,
    )


def _bspline_slopes(t: np.ndarray) -> np.ndarray:
    """d/dt of :func:`bspline_weights`, (P, 4)."""
    t2 = t * t
    return np.stack(
        [-((1 - t) ** 2) / 2, (3 * t2 - 4 * t) / 2, (-3 * t2 + 2 * t + 1) / 2, t2 / 2], axis=1
    )


def knot_xy(origin_xy, spacing_m: float, n_x: int, n_y: int) -> np.ndarray:
    """(ky kx, 2) map positions of the knots of a field, row-major (coefficient ``(j, i)``
    sits at ``origin + spacing (i - 1, j - 1)``)."""
    kx, ky = n_x + 3, n_y + 3
    gx, gy = np.meshgrid(np.arange(kx) - 1.0, np.arange(ky) - 1.0)
    return np.column_stack(
        [origin_xy[0] + spacing_m * gx.ravel(), origin_xy[1] + spacing_m * gy.ravel()]
    )


def knot_copies(origin_xy, spacing_m: float, n_x: int, n_y: int, lines) -> np.ndarray:
    """Which knots get a second copy for the far side of a breakline.

    A knot's basis function reaches ``2 spacing_m`` along x and y; a breakline that passes
    within ``2 sqrt(2) spacing_m`` of the knot may cut its support, and the points beyond the
    line (the segment from the knot to the point crosses it an odd number of times) then use
    the knot's copy. Depends on the geometry alone, so any chunk of points (a tile) finds the
    same copies.

    Parameters
    ----------
    origin_xy, spacing_m, n_x, n_y
        The field's lattice (:class:`SplineField`).
    lines : Breaklines or None

    Returns
    -------
    (ky kx,) int64
        Index of each knot's copy in the field's coefficient list (``ky kx + j`` for the
        j-th copy), -1 for a knot without one.
    """
    from .breaklines import distance_m

    n_grid = (n_x + 3) * (n_y + 3)
    out = np.full(n_grid, -1, dtype=np.int64)
    if lines is None or lines.empty:
        return out
    near = distance_m(knot_xy(origin_xy, spacing_m, n_x, n_y), lines) < 2.0 * np.sqrt(2.0) * (
        spacing_m * (1.0 + 1e-9)
    )
    k = np.flatnonzero(near)
    out[k] = n_grid + np.arange(k.size)
    return out


def spline_basis(
    xy: np.ndarray,
    *,
    origin_xy,
    spacing_m: float,
    n_x: int,
    n_y: int,
    lines=None,
    copy_index: Optional[np.ndarray] = None,
    slopes: bool = False,
):
    """The 16 knots and weights of a (breakline-aware) bicubic B-spline at each position.

    Works on any chunk of points: the answer for a point depends on its position and the
    field's geometry (lattice, breaklines) only.

    Parameters
    ----------
    xy : (P, 2) float64
        Map positions, metres.
    origin_xy, spacing_m, n_x, n_y
        The lattice (:class:`SplineField`).
    lines : Breaklines, optional
        Breaklines; with ``copy_index``, each of a point's knots that has a copy is replaced
        by its copy where the segment from the knot's position to the point crosses the
        lines an odd number of times (the point lies on the knot's far side).
    copy_index : (ky kx,) int64, optional
        :func:`knot_copies` of the same lattice and lines.
    slopes : bool
        Also return the weights' x and y derivatives (per metre).

    Returns
    -------
    idx : (P, 16) int64
        Coefficient indices (grid knots row-major, then the copies).
    w : (P, 16) float64
        Weights (sum 1).
    wx, wy : (P, 16) float64
        Only with ``slopes``.
    """
    h = spacing_m
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    u = (xy[:, 0] - origin_xy[0]) / h
    v = (xy[:, 1] - origin_xy[1]) / h
    iu = np.clip(np.floor(u).astype(np.int64), 0, n_x - 1)
    iv = np.clip(np.floor(v).astype(np.int64), 0, n_y - 1)
    fu, fv = u - iu, v - iv
    kx = n_x + 3
    rows = iv[:, None] + np.arange(4)
    idx = (rows[:, :, None] * kx + (iu[:, None] + np.arange(4))[:, None, :]).reshape(-1, 16)
    if lines is not None and copy_index is not None and not lines.empty:
        idx = _sided(idx, xy, origin_xy, h, kx, lines, copy_index)
    bu, bv = bspline_weights(fu), bspline_weights(fv)
    w = (bv[:, :, None] * bu[:, None, :]).reshape(-1, 16)
    if not slopes:
        return idx, w
    du, dv = _bspline_slopes(fu) / h, _bspline_slopes(fv) / h
    wx = (bv[:, :, None] * du[:, None, :]).reshape(-1, 16)
    wy = (dv[:, :, None] * bu[:, None, :]).reshape(-1, 16)
    return idx, w, wx, wy


def _sided(idx, xy, origin_xy, h, kx, lines, copy_index):
    """``idx`` with each knot that has a copy replaced by it where the point lies beyond a
    breakline as seen from the knot (odd crossings of knot -> point)."""
    from .breaklines import crossings

    has = copy_index[idx] >= 0
    p, k = np.nonzero(has)
    if p.size == 0:
        return idx
    g = idx[p, k]
    kxy = np.column_stack([origin_xy[0] + h * (g % kx - 1.0), origin_xy[1] + h * (g // kx - 1.0)])
    odd = crossings(kxy, xy[p], lines) % 2 == 1
    out = idx.copy()
    out[p[odd], k[odd]] = copy_index[g[odd]]
    return out


@dataclass(frozen=True)
class SplineField:
    """A bicubic B-spline displacement field of the horizontal position, smooth on each side
    of its breaklines and free to jump across them.

    Attributes
    ----------
    origin_xy : (float, float)
        Map position of knot interval (0, 0)'s lower-left corner, metres.
    spacing_m : float
        Knot spacing, metres.
    n_x, n_y : int
        Knot intervals along x and y.
    coefficients : (n_y + 3, n_x + 3, 3) float64
        Control vectors (dx, dy, dz), metres.
    lines : Breaklines or None
        Breaklines the field may jump across.
    copy_coefficients : (C, 3) float64 or None
        Control vectors of the knots' far-side copies (:func:`knot_copies`, in its order).
    """

    origin_xy: tuple
    spacing_m: float
    n_x: int
    n_y: int
    coefficients: np.ndarray
    lines: object = None
    copy_coefficients: Optional[np.ndarray] = None

    @property
    def copy_index(self) -> np.ndarray:
        """:func:`knot_copies` of this field's lattice and lines."""
        return knot_copies(self.origin_xy, self.spacing_m, self.n_x, self.n_y, self.lines)

    def all_coefficients(self) -> np.ndarray:
        """(ky kx + C, 3): the grid's control vectors, row-major, then the copies'."""
        c = self.coefficients.reshape(-1, 3)
        if self.copy_coefficients is None or len(self.copy_coefficients) == 0:
            return c
        return np.vstack([c, self.copy_coefficients])

    def _basis(self, xy: np.ndarray, slopes: bool = False, copy_index=None):
        lines = self.lines
        if lines is not None and copy_index is None:
            copy_index = self.copy_index
        return spline_basis(
            xy, origin_xy=self.origin_xy, spacing_m=self.spacing_m, n_x=self.n_x,
            n_y=self.n_y, lines=lines, copy_index=copy_index, slopes=slopes,
        )  # fmt: skip

    def both_sides(self, xy: np.ndarray):
        """(K, 2) map positions -> ``(own, other)``, each (K, 3) displacements, metres: the
        field of the position's own side of the breaklines and that of the far side (the
        knots that have a far-side copy swapped for it, and a copy for its original)."""
        ci = self.copy_index
        n_grid = ci.size
        idx, w = self._basis(np.asarray(xy, dtype=np.float64), copy_index=ci)
        copy_of = np.flatnonzero(ci >= 0)
        flip = idx.copy()
        main = idx < n_grid
        has = main & (ci[np.where(main, idx, 0)] >= 0)
        flip[has] = ci[idx[has]]
        flip[~main] = copy_of[idx[~main] - n_grid]
        coef = self.all_coefficients()
        return (
            np.einsum("pk,pkj->pj", w, coef[idx]),
            np.einsum("pk,pkj->pj", w, coef[flip]),
        )

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """(K, 2) map positions -> (K, 3) displacements, metres (each position takes the
        knots of its own side of the breaklines)."""
        idx, w = self._basis(np.asarray(xy, dtype=np.float64))
        return np.einsum("pk,pkj->pj", w, self.all_coefficients()[idx])

    def gradient(self, xy: np.ndarray) -> np.ndarray:
        """(K, 2) map positions -> (K, 3, 3) gradient ``d(d_i)/d(x_j)`` (z column zero), on
        the position's side."""
        idx, _, wx, wy = self._basis(np.asarray(xy, dtype=np.float64), slopes=True)
        c = self.all_coefficients()[idx]
        out = np.zeros((len(idx), 3, 3))
        out[:, :, 0] = np.einsum("pk,pkj->pj", wx, c)
        out[:, :, 1] = np.einsum("pk,pkj->pj", wy, c)
        return out


@dataclass(frozen=True)
class DeferredFit:
    """A spline fit whose report (covariances, block sums, sigma0) is not made yet: its
    ``field``, its ``smoothing_estimate`` (as :class:`SplineFit`'s) and ``finish()``, which
    makes the :class:`SplineFit` exactly as the fit would have returned it."""

    field: SplineField
    smoothing_estimate: Optional[np.ndarray]
    finish: Callable[[], SplineFit]


@dataclass(frozen=True)
class SplineFit:
    """A :class:`SplineField` fitted by :func:`fit_spline_field`, with what it reports at
    the requested positions.

    Attributes
    ----------
    field : SplineField
    d : (K, 3) float64
        Displacement at the requested positions, metres.
    gradient : (K, 3, 3) float64
        Its gradient (z column zero).
    cov : (K, 9, 9) float64
        Covariance of ``(d, d d/dx, d d/dy)`` (the displacement and its two horizontal
        derivatives, components x, y, z each), m² and m²/m: ``sigma0² A⁻¹`` of the penalised
        normal matrix ``A`` (the regularised estimate's posterior).
    rmse : (K,) float64
        RMS point-to-plane residual of the points around each position (its cell), metres.
    n : (K,) int64
        Correspondences used in each cell.
    sigma0_m : float
        A-posteriori standard deviation of unit weight of the whole fit, metres.
    iterations : int
    converged : bool
    n_coefficients : int
        Knots carrying data (x 3 components).
    pair_cov : (Q, 3) float64 or None
        Covariances between the displacements at the ``report_pairs`` positions, per
        component (x with x, y with y, z with z), m²: the field is one estimate, so nearby
        positions' errors are correlated. ``None`` without ``report_pairs``.
    cov_blocks : (K, 9, 9) float64 or None
        With ``block_m``: the covariance of the same rows with the residuals' spatial
        correlation (block sums of the scores, :func:`slipmap.core.icp_blocks.
        spline_block_covariance`), m² and m²/m.
    n_blocks : (K,) int64 or None
        With ``block_m``: blocks with used points in each cell (``report_seg``).
    data_weight : (K,) float64 or None
        The cells' data weights ``1 / F`` of a weighted fit (``cell_weight``); None: every
        point counted as independent.
    projection : (K, 3) float64 or None
        With ``data_weight``: :func:`rigid_projection` of the fitted field, metres.
    penalty_width_m : float or None
        Width of the local penalty's kernel, metres (None: one penalty weight per component).
    restricted_score : float or None
        With the local penalty: minus twice the restricted log-likelihood of the final
        weighted fit, up to a constant (:func:`_restricted_score`; lower is likelier).
    smoothing_estimate : (3,) or (4,) float64 or None
        With one penalty weight per component estimated (``smoothing=None``, no cell
        weights): the weights reached (x, y, z, and with :data:`HORIZONTAL_MODEL`
        "principal" the horizontal cross weight), relative to the median diagonal of the
        normal matrix (as ``smoothing``), for ``smoothing_start`` of a refit; None
        otherwise.
    """

    field: SplineField
    d: np.ndarray
    gradient: np.ndarray
    cov: np.ndarray
    rmse: np.ndarray
    n: np.ndarray
    sigma0_m: float
    iterations: int
    converged: bool
    n_coefficients: int
    pair_cov: Optional[np.ndarray] = None
    cov_blocks: Optional[np.ndarray] = None
    n_blocks: Optional[np.ndarray] = None
    data_weight: Optional[np.ndarray] = None
    projection: Optional[np.ndarray] = None
    penalty_width_m: Optional[float] = None
    restricted_score: Optional[float] = None
    smoothing_estimate: Optional[np.ndarray] = None


def _second_differences(kx: int, ky: int):
    """Penalty matrix ``RᵀR`` of the second differences of a (ky, kx) knot grid along x and
    y, sparse (kx ky, kx ky)."""
    import scipy.sparse as sp

    def d2(n):
        return sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(max(n - 2, 0), n))

    r = sp.vstack([sp.kron(sp.identity(ky), d2(kx)), sp.kron(d2(ky), sp.identity(kx))])
    return (r.T @ r).tocsr()


def sided_second_differences(
    origin_xy,
    spacing_m: float,
    n_x: int,
    n_y: int,
    lines,
    copy_index: np.ndarray,
    rows: bool = False,
):
    """Penalty matrix ``RᵀR`` of the second differences of a knot grid with far-side copies,
    sparse ((ky kx + C), (ky kx + C)).

    Each knot version (the knot itself, or its copy for the far side of a breakline) is the
    middle of one second difference along x and one along y, taken with the versions of its
    two neighbours that lie on the same side as seen from the middle knot: for the knot
    itself, a neighbour across the line (odd crossings of the segment between their
    positions) enters by its copy; for the copy, a neighbour across the line enters as itself
    and one on the knot's own side by its copy. A difference whose neighbour version does not
    exist is left out. Without lines this is :func:`_second_differences`.

    With ``rows``: the rows ``R`` themselves (sparse (T, ky kx + C)) and the map position
    of each row's middle knot (T, 2) instead.
    """
    import scipy.sparse as sp

    from .breaklines import crossings

    kx, ky = n_x + 3, n_y + 3
    n_grid = kx * ky
    n_tot = n_grid + int(np.count_nonzero(copy_index >= 0))
    pos = knot_xy(origin_xy, spacing_m, n_x, n_y)
    grid = np.arange(n_grid).reshape(ky, kx)
    triples = [
        np.column_stack([grid[:, :-2].ravel(), grid[:, 1:-1].ravel(), grid[:, 2:].ravel()]),
        np.column_stack([grid[:-2, :].ravel(), grid[1:-1, :].ravel(), grid[2:, :].ravel()]),
    ]
    t = np.vstack(triples)  # (T, 3): left, middle, right
    sided = lines is not None and not lines.empty
    rows_idx = [t]
    if sided:
        odd = np.zeros((len(t), 2), dtype=bool)
        for s, col in enumerate((0, 2)):
            has = (copy_index[t[:, 1]] >= 0) | (copy_index[t[:, col]] >= 0)
            j = np.flatnonzero(has)
            odd[j, s] = crossings(pos[t[j, 1]], pos[t[j, col]], lines) % 2 == 1
        out = []
        # the middle knot itself: neighbours across the line by their copies
        main = t.copy()
        for s, col in enumerate((0, 2)):
            main[odd[:, s], col] = copy_index[t[odd[:, s], col]]
        out.append(main)
        # the middle knot's copy: neighbours on its own side by their copies
        m = copy_index[t[:, 1]] >= 0
        cp = t[m].copy()
        cp[:, 1] = copy_index[t[m, 1]]
        for s, col in enumerate((0, 2)):
            same = ~odd[m, s]
            cp[same, col] = copy_index[t[m][same, col]]
        out.append(cp)
        rows_idx = [np.vstack(out)]
    r_idx = rows_idx[0]
    r_idx = r_idx[np.all(r_idx >= 0, axis=1)]
    n_r = len(r_idx)
    r = sp.csr_matrix(
        (np.tile([1.0, -2.0, 1.0], n_r), (np.repeat(np.arange(n_r), 3), r_idx.ravel())),
        shape=(n_r, n_tot),
    )
    if rows:
        # each row's place: its middle knot's (a copy sits where its knot does)
        mid = r_idx[:, 1]
        grid_of = np.r_[np.arange(n_grid), np.flatnonzero(copy_index >= 0)]
        return r.tocsr(), pos[grid_of[mid]]
    return (r.T @ r).tocsr()


def _assemble(order, bounds, idx16, w16, nrm, v, wt, n_k, ok=None):
    """Normal matrix (3K, 3K, sparse) and right-hand side (3K,) of the weighted point-to-plane
    residuals, one dense (48, 48) product per knot interval (``order`` sorts the points by
    interval, ``bounds`` delimit them; ``order=None``: already sorted). With ``ok`` (P,) bool,
    also the Gram matrix (K, K, sparse) ``sum b_p b_pᵀ`` of the basis rows of the ``ok``
    points (the field's RMS change at them is ``sqrt(sum_j dc_jᵀ G dc_j / n_ok)``)."""
    import scipy.sparse as sp

    rows, cols, vals = [], [], []
    g_rows, g_cols, g_vals = [], [], []
    rhs = np.zeros(3 * n_k)
    okf = None if ok is None else ok.astype(np.float64)
    for s0, s1 in zip(bounds[:-1], bounds[1:]):
        if s1 <= s0:
            continue
        sel = slice(s0, s1) if order is None else order[s0:s1]
        first = s0 if order is None else order[s0]
        m = (nrm[sel][:, :, None] * w16[sel][:, None, :]).reshape(-1, 48)
        mw = m * wt[sel, None]
        gidx = (np.arange(3)[:, None] * n_k + idx16[first][None, :]).reshape(48)
        nblk = mw.T @ m
        rhs[gidx] += mw.T @ v[sel]
        rows.append(np.repeat(gidx, 48))
        cols.append(np.tile(gidx, 48))
        vals.append(nblk.reshape(-1))
        if okf is not None:
            wb = w16[sel]
            g_rows.append(np.repeat(idx16[first], 16))
            g_cols.append(np.tile(idx16[first], 16))
            g_vals.append(((wb * okf[sel, None]).T @ wb).reshape(-1))

    def matrix(r, c, x, n):
        if not r:
            return sp.csr_matrix((n, n))
        return sp.csr_matrix(
            (np.concatenate(x), (np.concatenate(r), np.concatenate(c))), shape=(n, n)
        )

    n = matrix(rows, cols, vals, 3 * n_k)
    if okf is None:
        return n, rhs
    return n, rhs, matrix(g_rows, g_cols, g_vals, n_k)


def _row_groups(idx: np.ndarray) -> np.ndarray:
    """(P,) int64: each row's rank among the distinct rows of ``idx`` (P, M) in lexicographic
    order, as ``np.unique(idx, axis=0, return_inverse=True)[1]`` (the reference, several
    times slower: it sorts a structured view)."""
    if len(idx) == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort(idx.T[::-1])
    srt = idx[order]
    new = np.r_[True, np.any(srt[1:] != srt[:-1], axis=1)]
    out = np.empty(len(idx), dtype=np.int64)
    out[order] = np.cumsum(new) - 1
    return out


#: the six distinct products ``n_i n_j`` of a target normal's components (i <= j)
_NORMAL_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _kron_maps():
    """Index maps of :func:`_assemble_kron`: for each entry ``(i k, j l)`` of a (48, 48)
    interval block (component ``i``, basis function ``k = 4 r + c``) its place among the
    interval's 7 x 100 distinct sums (6 normal products and the Gram matrix, each over the
    10 x 10 distinct products ``bv_r bv_s bu_c bu_d``): (48, 48) and (16, 16) int64."""
    sym4 = np.zeros((4, 4), dtype=np.int64)
    iu, ju = np.triu_indices(4)
    sym4[iu, ju] = sym4[ju, iu] = np.arange(10)
    r, c = np.divmod(np.arange(16), 4)
    e16 = sym4[r[:, None], r[None, :]] * 10 + sym4[c[:, None], c[None, :]]
    pair = np.zeros((3, 3), dtype=np.int64)
    for a, (i, j) in enumerate(_NORMAL_PAIRS):
        pair[i, j] = pair[j, i] = a
    e48 = pair[:, None, :, None] * 100 + e16[None, :, None, :]
    return e48.reshape(48, 48), 600 + e16


_E48, _E16 = _kron_maps()
_KRON_BLOCK = 1024  # points per product in _assemble_kron


@dataclass(frozen=True)
class NormalPattern:
    """The sparsity pattern of a chunk's normal and Gram matrices (fixed by its points'
    knots, not by the iteration), and where each interval block's entries land in it.

    ``slot48`` (G, 48, 48) / ``slot16`` (G, 16, 16): the position in ``data`` of the
    interval's entry; ``indptr``/``indices``: the CSR structure, (3K, 3K) and (K, K)."""

    n_k: int
    indptr48: np.ndarray
    indices48: np.ndarray
    slot48: np.ndarray
    indptr16: np.ndarray
    indices16: np.ndarray
    slot16: np.ndarray

    @classmethod
    def of(cls, bounds: np.ndarray, idx16: np.ndarray, n_k: int) -> NormalPattern:
        """The pattern of the intervals ``bounds`` (G + 1,) with knots ``idx16`` (P, 16)."""
        first = idx16[np.asarray(bounds[:-1], dtype=np.int64)]  # (G, 16)
        g48 = (np.arange(3)[None, :, None] * n_k + first[:, None, :]).reshape(-1, 48)

        def csr(gidx, n):
            m = gidx.shape[1]
            key = (gidx[:, :, None] * n + gidx[:, None, :]).reshape(-1)
            uniq, inv = np.unique(key, return_inverse=True)
            indptr = np.searchsorted(uniq // n, np.arange(n + 1)).astype(np.int64)
            return indptr, (uniq % n).astype(np.int64), inv.reshape(-1, m, m)

        p48, i48, s48 = csr(g48, 3 * n_k)
        p16, i16, s16 = csr(first, n_k)
        return cls(int(n_k), p48, i48, s48, p16, i16, s16)


def _assemble_kron(bounds, idx16, w16, bu, bv, nrm, v, wt, n_k, ok, pattern=None):
    """:func:`_assemble` (with ``order=None`` and ``ok``) from the basis' Kronecker structure:
    a point's 16 weights are ``bv_r bu_c`` (:func:`spline_basis`), so its (48, 48) block
    ``w (n nᵀ) ⊗ (b bᵀ)`` has only 6 x 100 distinct entries (``n_i n_j``, i <= j; and
    ``bv_r bv_s bu_c bu_d``, r <= s, c <= d), 100 more for the Gram matrix: one
    (7, P) x (P, 100) product per knot interval instead of a (48, P) x (P, 48) one, and the
    blocks scattered into a CSR pattern that is fixed for the chunk (``pattern``,
    :class:`NormalPattern`, built when not given) instead of a COO sort per call. Same
    sums in another order (tests/core/test_icp_spline_kron.py: 1e-12 relative).

    Parameters
    ----------
    bounds : (G + 1,) int64
        Interval slices of the points (sorted by interval, all with the same 16 knots).
    idx16, w16 : (P, 16) int64, (P, 16) float64
        Coefficient indices and weights.
    bu, bv : (P, 4) float64
        The cubic B-spline weights along x and along y (``w16 = bv ⊗ bu``, row-major).
    nrm, v, wt, n_k, ok
        As :func:`_assemble`.
    pattern : NormalPattern, optional
        ``NormalPattern.of(bounds, idx16, n_k)``, to reuse between calls.
    """
    import scipy.sparse as sp

    if pattern is None:
        pattern = NormalPattern.of(bounds, idx16, n_k)
    n_pts = len(v)
    coef = np.empty((n_pts, 7))
    for a, (i, j) in enumerate(_NORMAL_PAIRS):
        coef[:, a] = wt * nrm[:, i] * nrm[:, j]
    coef[:, 6] = ok
    wv_n = (wt * v)[:, None] * nrm  # (P, 3)
    iu, ju = np.triu_indices(4)
    qu = bu[:, iu] * bu[:, ju]  # (P, 10)
    qv = bv[:, iu] * bv[:, ju]
    n_g = len(bounds) - 1
    sums = np.empty((n_g, 700))
    rhs16 = np.empty((n_g, 3, 16))
    for g in range(n_g):
        s0, s1 = int(bounds[g]), int(bounds[g + 1])
        acc = np.zeros((7, 100))
        # in blocks of points whose (n, 100) products stay in the cache (1.5x faster)
        for t0 in range(s0, s1, _KRON_BLOCK):
            t1 = min(t0 + _KRON_BLOCK, s1)
            q = (qv[t0:t1, :, None] * qu[t0:t1, None, :]).reshape(t1 - t0, 100)
            acc += coef[t0:t1].T @ q
        sums[g] = acc.reshape(700)
        rhs16[g] = wv_n[s0:s1].T @ w16[s0:s1]
    n3 = 3 * n_k
    first = idx16[np.asarray(bounds[:-1], dtype=np.int64)]
    rhs_idx = np.arange(3)[None, :, None] * n_k + first[:, None, :]
    rhs = np.bincount(rhs_idx.ravel(), weights=rhs16.ravel(), minlength=n3)
    d48 = np.bincount(
        pattern.slot48.ravel(), weights=sums[:, _E48].ravel(), minlength=len(pattern.indices48)
    )
    d16 = np.bincount(
        pattern.slot16.ravel(), weights=sums[:, _E16].ravel(), minlength=len(pattern.indices16)
    )
    nmat = sp.csr_matrix((d48, pattern.indices48, pattern.indptr48), shape=(n3, n3))
    gram = sp.csr_matrix((d16, pattern.indices16, pattern.indptr16), shape=(n_k, n_k))
    return nmat, rhs, gram


def factor_spd(a):
    """Sparse LU of the symmetric positive definite ``a`` (n, n) (the penalised normal
    matrix ``N + P`` with its ridge): SuperLU in its symmetric mode, a minimum-degree
    ordering of ``A + Aᵀ`` applied to rows and columns alike, and the diagonal taken as
    pivot. For such a matrix that is Cholesky's elimination, stable without row
    interchanges. Its fill is what a symmetric ordering gives rather than what
    COLAMD's column ordering with partial pivoting gives: on the lone-star lobe's fields
    (1080-1389 unknowns) 18 % less fill, the factorisation 1.5× and the solves 1.4× faster,
    the same solutions to 1e-12 (``scipy.sparse.linalg.splu`` with its defaults is the reference,
    ``tests/core/test_icp_spline_factor.py``). Written here because scipy has no sparse
    Cholesky (CHOLMOD, through scikit-sparse, is not a dependency)."""
    from scipy.sparse.linalg import splu

    return splu(
        a.tocsc(),
        permc_spec="MMD_AT_PLUS_A",
        diag_pivot_thresh=0.0,
        options=dict(SymmetricMode=True),
    )


def _trace_inv_block(factor, r2, j: int, n_k: int, seed: int = 0, rows=None) -> np.ndarray:
    """``tr(A⁻¹[k, j] RᵀR)`` of component ``j`` for each ``k`` of ``rows`` (default ``(j,)``;
    the same solves serve them all) from ``A``'s sparse LU: exact (``n_k`` solves) up to
    TRACE_EXACT_MAX knots, else Hutchinson's estimate with TRACE_PROBES Rademacher probes."""
    rows = (j,) if rows is None else rows
    if n_k <= TRACE_EXACT_MAX:
        rhs = np.zeros((3 * n_k, n_k))
        rhs[j * n_k + np.arange(n_k), np.arange(n_k)] = 1.0
        x = factor.solve(rhs)
        return np.array([float(r2.multiply(x[k * n_k : (k + 1) * n_k]).sum()) for k in rows])
    rng = np.random.default_rng(seed + j)
    z = rng.choice([-1.0, 1.0], size=(n_k, TRACE_PROBES))
    rhs = np.zeros((3 * n_k, TRACE_PROBES))
    rhs[j * n_k : (j + 1) * n_k] = r2 @ z
    x = factor.solve(rhs)
    return np.array([float(np.mean(np.sum(z * x[k * n_k : (k + 1) * n_k], axis=0))) for k in rows])


def _weight_groups():
    """The components whose penalty weight each gets by the scalar update, per
    :data:`HORIZONTAL_MODEL` (with "principal" x and y get theirs from
    :func:`_horizontal_update`), and the rows ``k`` of ``A⁻¹[k, j]`` each component ``j``
    needs (the x-y blocks only with "principal")."""
    if HORIZONTAL_MODEL == "principal":
        return ([2],), ((0, 1), (0, 1), (2,))
    groups = ([0], [1], [2]) if HORIZONTAL_MODEL == "axes" else ([0, 1], [2])
    return groups, ((0,), (1,), (2,))


def _sym2(a: np.ndarray) -> np.ndarray:
    """``(..., 2, 2)`` from the stored ``(xx, yy, xy)`` along the first axis."""
    out = np.empty(a.shape[1:] + (2, 2))
    out[..., 0, 0], out[..., 1, 1] = a[0], a[1]
    out[..., 0, 1] = out[..., 1, 0] = a[2]
    return out


def _clip_sym(b: np.ndarray, lo) -> np.ndarray:
    """The symmetric part of ``b`` (..., 2, 2) with its eigenvalues kept at least ``lo``
    (...,). A redundancy matrix ``n I - G Λ`` is not symmetric where ``G`` and ``Λ`` do not
    share their axes; its symmetric part keeps the update stable (the exact matrix, clipped
    in ``Λ``'s whitened frame, made the local weights wander on a lobe moving at 45° to the
    grid: 6.9 cm against 1.3 cm) at the price of a fixed point that is the restricted
    likelihood's only where ``G`` and ``Λ`` share their axes. A redundancy below nil means
    none is left."""
    w, v = np.linalg.eigh(0.5 * (b + np.swapaxes(b, -1, -2)))
    w = np.maximum(w, np.asarray(lo, dtype=np.float64)[..., None])
    return (v * w[..., None, :]) @ np.swapaxes(v, -1, -2)


def _lyapunov2(b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """The symmetric ``Σ`` (..., 2, 2) of ``B Σ + Σ Bᵀ = 2 M``: ``B⁻¹ M`` where that is
    symmetric (at the variance components' fixed point, or where ``B`` and ``M`` commute),
    and positive semi-definite whenever ``B``'s eigenvalues are positive and ``M`` is, which
    the plain symmetric part of ``B⁻¹ M`` need not be."""
    a, bb, cc, d = b[..., 0, 0], b[..., 0, 1], b[..., 1, 0], b[..., 1, 1]
    zero = np.zeros_like(a)
    lhs = np.stack(
        [np.stack([a, zero, bb], -1), np.stack([zero, d, cc], -1), np.stack([cc, bb, a + d], -1)],
        -2,
    )
    rhs = np.stack([m[..., 0, 0], m[..., 1, 1], m[..., 0, 1] + m[..., 1, 0]], -1)
    p, q, r = np.moveaxis(np.linalg.solve(lhs, rhs[..., None])[..., 0], -1, 0)
    return _sym2(np.stack([p, q, r]))


def _precision(sig: np.ndarray, s0sq) -> np.ndarray:
    """``(xx, yy, xy)`` (3, ...) of ``s0² Σ⁻¹``, ``Σ`` (..., 2, 2) with its eigenvalues kept
    at least 1e-12 of its largest (the weights are then clipped to AUTO_RANGE)."""
    w, v = np.linalg.eigh(sig)
    w = np.maximum(w, 1e-12 * np.maximum(w[..., -1:], 1e-300))
    out = (v / w[..., None, :]) @ np.swapaxes(v, -1, -2) * np.asarray(s0sq)
    return np.stack([out[..., 0, 0], out[..., 1, 1], out[..., 0, 1]])


def _horizontal_update(lam: np.ndarray, red_gain: np.ndarray, rough: np.ndarray, n_r, s0sq):
    """New horizontal penalty weights ``(xx, yy, xy)`` (3, ...) by Förstner's update
    generalised to a 2 x 2 precision: ``B Σ + Σ Bᵀ = 2 M`` (:func:`_lyapunov2`),
    ``Λ = s0² Σ⁻¹``.

    ``lam`` (3, ...) the current weights ``Λ``; ``red_gain`` (..., 2, 2) ``G`` with
    ``G_ab = tr(A⁻¹_ab RᵀR)`` (or its rows' share); ``rough`` (..., 2, 2) ``M``, the
    horizontal second differences' cross products; ``n_r`` (...,) the pseudo-observations.
    ``B = n_r I - G Λ`` is the redundancy matrix (its symmetric part, its eigenvalues kept
    at least ``n_r / 1000``: :func:`_clip_sym`). Where ``G`` and ``Λ`` share their axes
    the fixed point is the restricted likelihood's, ``n_r Σ = M + s0² G``; with ``Λ`` and
    ``G`` diagonal it is the update of each axis alone. Every term turns with the field, so
    the estimate does."""
    n_r = np.asarray(n_r, dtype=np.float64)
    b = _clip_sym(n_r[..., None, None] * np.eye(2) - red_gain @ _sym2(lam), 1e-3 * n_r)
    return _precision(_lyapunov2(b, rough), s0sq)


def _clip_weights(lam: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The penalty weights ``(xx, yy, z, xy)`` (4, ...) kept within ``[lo, hi]``: z alone,
    the horizontal 2 x 2 by its eigenvalues (a weight along a direction, not an entry)."""
    out = lam.copy()
    out[2] = np.clip(lam[2], lo, hi)
    w, v = np.linalg.eigh(_sym2(lam[[0, 1, 3]]))
    m = (v * np.clip(w, lo, hi)[..., None, :]) @ np.swapaxes(v, -1, -2)
    out[0], out[1], out[3] = m[..., 0, 0], m[..., 1, 1], m[..., 0, 1]
    return out


def _weights_moved(new: np.ndarray, old: np.ndarray) -> float:
    """Largest relative move of the weights (4, ...): x, y and z against themselves, the
    cross weight against the geometric mean of x's and y's."""
    rel = np.abs(new[:3] / old[:3] - 1.0)
    cross = np.abs(new[3] - old[3]) / np.sqrt(old[0] * old[1])
    return float(max(np.max(rel), np.max(cross)))


def _penalty_blocks(lam: np.ndarray, rmat, r2):
    """The penalty ``P`` (3K, 3K) of the weights (4,) on ``RᵀR`` or (4, T) per row of ``R``
    (``xx, yy, z, xy``)."""
    import scipy.sparse as sp

    def block(w):
        return w * r2 if lam.ndim == 1 else rmat.T @ sp.diags(w) @ rmat

    blk = [block(w) for w in lam[:3]]
    cross = block(lam[3]) if np.any(lam[3] != 0) else None  # none with one weight per axis
    return sp.bmat(
        [[blk[0], cross, None], [cross, blk[1], None], [None, None, blk[2]]], format="csr"
    )


def _variance_components(factor, r2, lam_abs, c, wvv: float, n_obs: int) -> np.ndarray:
    """New penalty weights ``sigma0² / sigma_j²`` by variance-component estimation
    (Förstner's iteration, as Helmert's for two groups): the observations' variance from
    their weighted residuals over their redundancy, each component's prior variance of
    second differences from ``c_jᵀ RᵀR c_j`` over the pseudo-observations' redundancy
    ``n_R - lam_j tr(A⁻¹_jj RᵀR)``."""
    n_k = r2.shape[0]
    n_r = float(np.count_nonzero(r2.diagonal() > 0))  # pseudo-observations, about n_k
    groups, rows = _weight_groups()
    tr = np.zeros((3, 3))  # [k, j]: the blocks the model needs
    for j in range(3):
        tr[list(rows[j]), j] = _trace_inv_block(factor, r2, j, n_k, rows=rows[j])
    t = lam_abs[:3] * np.diagonal(tr)  # redundancy the prior gives away per component
    given = float(np.sum(t) + 2.0 * lam_abs[3] * tr[0, 1])
    r_obs = max(n_obs - (3 * n_k - given), 1.0)
    s0sq = wvv / r_obs
    out = lam_abs.copy()
    r2c = r2 @ c
    rough = np.array([float(c[:, j] @ r2c[:, j]) for j in range(3)])
    if HORIZONTAL_MODEL == "principal" and rough[0] + rough[1] > 0:
        gain = 0.5 * (tr[:2, :2] + tr[:2, :2].T)
        cross = float(c[:, 0] @ r2c[:, 1])
        m = np.array([[rough[0], cross], [cross, rough[1]]])
        out[[0, 1, 3]] = _horizontal_update(lam_abs[[0, 1, 3]], gain, m, n_r, s0sq)
    for group in groups:
        rg = float(np.sum(rough[group]))
        eg = float(np.sum(np.maximum(n_r - t[group], 1.0)))
        if rg > 0:
            out[group] = s0sq / (rg / eg)
    log.debug("spline field: variance components -> weights %s", np.array2string(out))
    return out


def _local_variance_components(
    factor, rmat, kernel, lam_rows, c, wvv: float, n_obs: int, n_nominal: float
) -> np.ndarray:
    """Penalty weights per second-difference row and component, ``sigma0² / sigma_j²(x)``:
    :func:`_variance_components` with the prior variance of the second differences
    estimated locally, each row's from the rows around it (``kernel`` (T, T) sparse, rows
    summing to 1 or not: only ratios matter), ``sum_s K_rs (R c_j)_s² / sum_s K_rs e_s``
    with ``e_s`` each row's redundancy, its share ``n_nominal / T`` of the pseudo-
    observations less ``lam_s (R A⁻¹_jj Rᵀ)_ss``. A kernel of ones is the global estimate."""
    n_rows, n_k = rmat.shape
    groups, rows = _weight_groups()
    dg = np.zeros((3, 3, n_rows))  # [k, j]: the blocks the model needs
    for j in range(3):
        dg[list(rows[j]), j] = _diag_r_inv_rt(factor, rmat, j, n_k, rows=rows[j])
    diag = np.array([dg[j, j] for j in range(3)])  # (3, T)
    # redundancy the prior gives away per component (and through the cross weight)
    given = float(np.sum(lam_rows[:3] * diag) + 2.0 * np.sum(lam_rows[3] * dg[0, 1]))
    r_obs = max(n_obs - (3 * n_k - given), 1.0)
    s0sq = wvv / r_obs
    share = n_nominal / n_rows
    out = lam_rows.copy()
    rc = np.stack([rmat @ c[:, j] for j in range(3)])  # (3, T)
    floor = 1e-3 * (kernel @ np.full(n_rows, share))
    if HORIZONTAL_MODEL == "principal":
        pair = np.stack([rc[0] * rc[0], rc[1] * rc[1], rc[0] * rc[1]])
        num = np.stack([kernel @ q for q in pair])  # (3, T): xx, yy, xy
        gain = _sym2(np.stack([dg[0, 0], dg[1, 1], 0.5 * (dg[0, 1] + dg[1, 0])]))
        red = _clip_sym(share * np.eye(2) - gain @ _sym2(lam_rows[[0, 1, 3]]), 0.0)  # (T, 2, 2)
        # B Σ + Σ Bᵀ = 2 M, B the rows' redundancy matrices smoothed as M is
        bsm = np.empty_like(red)
        for a in range(2):
            for b in range(2):
                bsm[:, a, b] = kernel @ red[:, a, b]
        bsm = _clip_sym(bsm, floor)
        good = num[0] + num[1] > 0
        out[np.ix_([0, 1, 3], good)] = _precision(_lyapunov2(bsm[good], _sym2(num)[good]), s0sq)
    for group in groups:
        rc2 = sum(rc[j] ** 2 for j in group)
        red = sum(np.maximum(share - lam_rows[j] * diag[j], 0.0) for j in group)
        num = kernel @ rc2
        den = np.maximum(kernel @ red, len(group) * floor)
        good = num > 0
        for j in group:
            out[j, good] = s0sq / (num[good] / den[good])
    log.debug(
        "spline field: local variance components -> weights (median) %s",
        np.array2string(np.median(out, axis=1)),
    )
    return out


def _restricted_score(
    factor, penalty, c: np.ndarray, wvv: float, wvv_weighted: float, n_obs: int
) -> float:
    """Minus twice the restricted log-likelihood of a penalised fit, up to a constant that
    the same data and knots share, ``log|A| - log|P| + (vᵀWv + cᵀPc) / s0²``: ``A = N + P``
    the penalised normal matrix (``factor``, its sparse LU), ``P`` the penalty (with its
    ridge, which stands in for the null space of the second differences: the same for every
    kernel, so it cancels between them), ``vᵀWv`` the weighted residuals with the cells' data
    weights (``wvv_weighted``), ``c`` (K, 3) the coefficients and ``s0²`` the points' variance
    from the unweighted ``wvv`` over ``n_obs - 3K``, as in :func:`_variance_components`.
    Lower is likelier (Patterson and Thompson's REML of a linear mixed model, the penalty
    the random effects' precision; Wood 2011 for smoothing parameters). Written here: the
    log-determinants come from the sparse LU factors (SuperLU's ``L`` has a unit diagonal)."""
    from scipy.sparse.linalg import splu

    n_k = c.shape[0]
    lda = float(np.sum(np.log(np.abs(factor.U.diagonal()))))
    ldp = float(np.sum(np.log(np.abs(splu(penalty.tocsc()).U.diagonal()))))
    cv = c.T.reshape(-1)
    s0sq = wvv / max(n_obs - 3 * n_k, 1)
    return lda - ldp + (wvv_weighted + float(cv @ (penalty @ cv))) / max(s0sq, 1e-300)


def _diag_r_inv_rt(factor, rmat, j: int, n_k: int, seed: int = 0, rows=None) -> np.ndarray:
    """``diag(R A⁻¹_kj Rᵀ)`` (len(rows), T) of component ``j`` for each ``k`` of ``rows``
    (default ``(j,)``; the same solves serve them all): exact up to TRACE_EXACT_MAX knots,
    else Hutchinson's diagonal estimate with TRACE_PROBES Rademacher probes."""
    rows = (j,) if rows is None else rows
    if n_k <= TRACE_EXACT_MAX:
        rhs = np.zeros((3 * n_k, n_k))
        rhs[j * n_k + np.arange(n_k), np.arange(n_k)] = 1.0
        x = factor.solve(rhs)
        return np.array(
            [
                np.asarray(rmat.multiply(rmat @ x[k * n_k : (k + 1) * n_k]).sum(axis=1)).ravel()
                for k in rows
            ]
        )
    rng = np.random.default_rng(seed + j)
    z = rng.choice([-1.0, 1.0], size=(rmat.shape[0], TRACE_PROBES))
    rhs = np.zeros((3 * n_k, TRACE_PROBES))
    rhs[j * n_k : (j + 1) * n_k] = rmat.T @ z
    x = factor.solve(rhs)
    return np.array([np.mean(z * (rmat @ x[k * n_k : (k + 1) * n_k]), axis=1) for k in rows])


def knot_frame(
    points_lo_xy, points_hi_xy, report_xy: np.ndarray, spacing_m: float, lines=None
) -> SplineField:
    """The knot lattice of a spline field over points spanning ``points_lo_xy`` ..
    ``points_hi_xy`` (x, y metres) and the report positions ``report_xy`` (K, 2): a
    :class:`SplineField` of zero coefficients. A tiled run gives the extremes of its blocks'
    points and gets the one-file run's lattice.

    Raises
    ------
    InvalidParameterError
        ``spacing_m`` not positive.
    SplineCellsError
        Fewer than :data:`MIN_SPLINE_CELLS` report positions.
    SplineSizeError
        More than :data:`MAX_KNOTS` knots.

    ``lines`` (:class:`~slipmap.core.breaklines.Breaklines`, optional): the field's
    breaklines; the lattice's knots get their far-side copies (:func:`knot_copies`).
    """
    h = float(spacing_m)
    if not (np.isfinite(h) and h > 0):
        raise InvalidParameterError(f"spline_spacing_m must be > 0, got {spacing_m!r}")
    rxy = np.asarray(report_xy, dtype=np.float64).reshape(-1, 2)
    if len(rxy) < MIN_SPLINE_CELLS:
        raise SplineCellsError(
            f"{len(rxy)} cell(s) with points, a spline field needs {MIN_SPLINE_CELLS} at least",
            cells=len(rxy),
        )
    lo = np.minimum(np.asarray(points_lo_xy, np.float64), rxy.min(axis=0)) - 1e-6 * h
    hi = np.maximum(np.asarray(points_hi_xy, np.float64), rxy.max(axis=0))
    check_spline_size(hi - lo, h)
    n_x, n_y = (int(v) for v in np.maximum(np.ceil((hi - lo) / h), 1))
    bl = None if lines is None or lines.empty else lines
    return SplineField(
        (float(lo[0]), float(lo[1])), h, n_x, n_y, np.zeros((n_y + 3, n_x + 3, 3)), lines=bl
    )


@dataclass(frozen=True)
class Weighting:
    """The robust weights of one iteration, from the residuals of every chunk together (as
    :func:`~.icp_options._weights` finds them from one array): points with ``|v| <=
    threshold_m`` are kept (trimming), and weighed at robust ``scale_m``.

    Attributes
    ----------
    threshold_m : float
        Largest kept ``|v|``, metres (inf: no trimming).
    scale_m : float
        Robust scale (MAD of the kept residuals), metres.
    robust : str or None
        ``"tukey"``, ``"huber"`` or None (unit weights).
    median_abs_m : float
        Median ``|v|`` of all paired points, metres (the stop test's floor).
    """

    threshold_m: float
    scale_m: float
    robust: Optional[str]
    median_abs_m: float

    @classmethod
    def of(cls, abs_v: np.ndarray, opts: _Options) -> Weighting:
        """From the ``|v|`` (N,) of every paired point of every chunk (their order is free:
        only quantiles are taken)."""
        av = np.asarray(abs_v, dtype=np.float64)
        thr = np.inf
        if opts.trim_fraction > 0 and av.size > 20:
            thr = float(np.quantile(av, 1.0 - opts.trim_fraction))
        scale = np.nan
        if opts.robust is not None:
            scale = MAD_TO_SIGMA * float(np.median(av[av <= thr]))
        return cls(thr, scale, opts.robust, float(np.median(av)))

    def numbers(self) -> np.ndarray:
        """(3,) its threshold, scale and median ``|v|`` (NaN scale without robust weights)."""
        return np.array([self.threshold_m, self.scale_m, self.median_abs_m])

    def apply(self, v: np.ndarray):
        """Residuals ``v`` (N,) of a chunk -> (keep, w, psi'(v)), equal to
        :func:`~.icp_options._weights` of all chunks' residuals together."""
        keep = np.abs(v) <= self.threshold_m
        if self.robust is None:
            w = keep.astype(np.float64)
            return keep, w, w
        w, dpsi = _robust_weights(v, max(self.scale_m, 1e-12), keep, self.robust)
        return keep, w, dpsi


@dataclass(frozen=True)
class ChunkNormals:
    """One chunk's share of an iteration's normal equations (sums over its points).

    Attributes
    ----------
    nmat : (3K, 3K) scipy.sparse matrix
        ``sum w_p a_p a_pᵀ`` (component-major unknowns), m⁻²·m².
    rhs : (3K,) float64
        ``sum w_p a_p v_p``.
    gram : (K, K) scipy.sparse matrix
        ``sum b_p b_pᵀ`` of the paired points' basis rows.
    wvv : float
        ``sum w_p v_p²``, m².
    n_obs : int
        Points of non-zero weight.
    n_ok : int
        Paired points.
    wvv_weighted : float
        ``sum w_p dw_p v_p²`` with the cells' data weights ``dw_p``, m² (``wvv`` without
        them).
    """

    nmat: object
    rhs: np.ndarray
    gram: object
    wvv: float
    n_obs: int
    n_ok: int
    wvv_weighted: float = float("nan")


@dataclass(frozen=True)
class ChunkReport:
    """One chunk's share of the final fit's sums.

    Attributes
    ----------
    ss_psi : float
        ``sum psi²`` of the weighted residuals, m².
    used : int
        Points kept with non-zero weight.
    sum_dpsi : float
        ``sum psi'`` over the kept points.
    n_ok : int
        Paired points.
    knots : (J,) int64
        Knots touched by paired points.
    targets : (T, 3) float64
        Target (epoch-1) points of the kept points, map metres (their identity across chunks).
    target_psi : (T,) float64
        ``sum psi`` per target.
    cells : (C,) int64
        Report positions (cells) of the chunk's used points.
    cell_n : (C,) int64
        Used points per cell.
    cell_ss : (C,) float64
        ``sum v²`` per cell, m².
    sum_w : float
        ``sum w`` of the robust weights of the paired points (0 where not kept).
    block_scores : BlockScores or None
        With a block side: the chunk's summed scores per block and 16-knot group
        (:func:`slipmap.core.icp_blocks.spline_block_scores`).
    """

    ss_psi: float
    used: int
    sum_dpsi: float
    n_ok: int
    knots: np.ndarray
    targets: np.ndarray
    target_psi: np.ndarray
    cells: np.ndarray
    cell_n: np.ndarray
    cell_ss: np.ndarray
    sum_w: float = 0.0
    block_scores: object = None


class SplineChunk:
    """The after-points of one chunk of a spline fit (all of a one-file run's, or the points
    a tile block owns: each point in exactly one chunk) with their basis rows and their
    matcher; the fit's per-point work is a function of (chunk, current coefficients).

    Parameters
    ----------
    after : (P, 3) float64
        The chunk's epoch-2 points, metres.
    frame : SplineField
        The knot lattice (:func:`knot_frame`; coefficients unused).
    before, tree, normals, gate_m, grid
        As :func:`fit_spline_field`; ``before`` must hold every epoch-1 point within the gate
        (and their normals' neighbourhoods) of the chunk's moved points.
    seg : (P,) int64, optional
        Report position (cell) of each point, for the per-cell ``rmse`` and ``n`` (-1: none).
    """

    def __init__(self, after, *, frame, before, tree, normals, gate_m=np.inf, seg=None,
                 grid=None, breakline_gap_m: float = 0.0):  # fmt: skip
        a = np.asarray(after, dtype=np.float64).reshape(-1, 3)
        kx = frame.n_x + 3
        n_grid = kx * (frame.n_y + 3)
        lines = frame.lines
        copy_index = None if lines is None else frame.copy_index
        self.origin_xy = (float(frame.origin_xy[0]), float(frame.origin_xy[1]))
        self.n_k = n_grid + (0 if copy_index is None else int(np.count_nonzero(copy_index >= 0)))
        idx16, w16 = frame._basis(a[:, :2], copy_index=copy_index)
        # the points sorted by their 16 knots (the knot interval, and with breaklines the
        # side of each knot), so that the points sharing them are one slice
        if lines is None:
            cell_of = (idx16[:, 0] // kx) * frame.n_x + idx16[:, 0] % kx
        else:
            cell_of = _row_groups(idx16)
        perm = np.argsort(cell_of, kind="stable")
        self.a, self.idx16, self.w16 = a[perm], idx16[perm], w16[perm]
        # points closer than breakline_gap_m to a line carry no weight (a line placed from
        # the data is known to about that much: they would pull the wrong side's field)
        self.gap = np.zeros(len(a), dtype=bool)
        if lines is not None and breakline_gap_m > 0:
            from .breaklines import distance_m

            self.gap = distance_m(self.a, lines) < breakline_gap_m
        self.seg = None if seg is None else np.asarray(seg, dtype=np.int64)[perm]
        c_sorted = cell_of[perm]
        starts = np.flatnonzero(np.r_[len(a) > 0, c_sorted[1:] != c_sorted[:-1]])
        self.bounds = np.append(starts, len(a))
        # the weights along x and y (w16 = bv ⊗ bu; each sums to 1) for _assemble_kron,
        # and its CSR pattern (built at the first iteration, the same for every one)
        w4 = self.w16.reshape(-1, 4, 4)
        self._bu, self._bv = w4.sum(axis=1), w4.sum(axis=2)
        self._pattern = None
        self.before, self.normals = before, normals
        m_pts = len(before)
        self.m_pts = m_pts
        if grid is None:
            from .icp_cells import _Matcher

            self._matcher = _Matcher(before, tree, normals, gate_m, None, np.zeros((1, 3)), len(a))
            self._nearest = self._matcher._nearest
        else:
            # the compiled matchers (Numba on the CPU, OpenCL) over the same targets
            matcher = grid.matcher(before, normals, gate_m, None, np.zeros((1, 3)), len(a))
            one_cell = np.zeros(len(a), dtype=np.int64)

            def nearest(q, gi):
                j = matcher.nearest(q, one_cell, gi)
                return np.where(j < m_pts, j, m_pts)

            self._nearest = nearest
        self._at = None  # coefficients of the cached pairs
        self._rigid_key = None  # coefficients and cells' z of the cached rigid rows
        self._pairs = None
        self._held_key = None  # (pairs_at, weighting, cell_weight) of the held pairs
        self._held = None
        import scipy.sparse as sp

        # the field at the points is basis @ c: a sparse product, 8x faster than gathering
        # c[idx16] (P, 16, 3) each iteration (issue #29)
        self._basis_pts = sp.csr_matrix(
            (self.w16.ravel(), self.idx16.ravel(), np.arange(0, self.idx16.size + 1, 16)),
            shape=(len(a), self.n_k),
        )

    def __len__(self) -> int:
        return len(self.a)

    def moved(self, c: np.ndarray) -> np.ndarray:
        """The points moved back by the field of coefficients ``c`` (K, 3)."""
        return self.a - self._basis_pts @ c

    def pairs(self, c: np.ndarray):
        """``(ok, normals, v, target)`` of the points moved by coefficients ``c``: paired
        (P,) bool, the target normals (P, 3) and point-to-plane residuals (P,) (zero where
        not paired), the target indices into ``before`` (P,)."""
        c = np.asarray(c, dtype=np.float64)
        if self._at is not None and np.array_equal(self._at, c):
            return self._pairs
        q = self.moved(c)
        n = len(q)
        j = self._nearest(q, np.arange(n))
        ok = j < self.m_pts
        nrm = np.zeros((n, 3))
        nn = self.normals(j[ok])
        good = np.all(np.isfinite(nn), axis=1)
        ok[ok] = good
        nrm[ok] = nn[good]
        v = np.zeros(n)
        v[ok] = np.einsum("ij,ij->i", nrm[ok], q[ok] - self.before[j[ok]])
        self._at, self._pairs = c.copy(), (ok, nrm, v, j)
        return self._pairs

    def residuals(self, c: np.ndarray) -> np.ndarray:
        """``|v|`` (N,) of the paired points at coefficients ``c`` (for :meth:`Weighting.of`)."""
        ok, _, v, _ = self.pairs(c)
        return np.abs(v[ok])

    def data_weight(self, cell_weight: Optional[np.ndarray]) -> np.ndarray:
        """(P,) each point's data weight: its cell's ``cell_weight`` (K,) (1 for points
        without a cell, or without weights)."""
        dw = np.ones(len(self.a))
        if cell_weight is None or self.seg is None:
            return dw
        inside = self.seg >= 0
        dw[inside] = np.asarray(cell_weight, dtype=np.float64)[self.seg[inside]]
        return np.where(np.isfinite(dw) & (dw > 0), dw, 1.0)

    def normal_equations(
        self,
        c: np.ndarray,
        weighting: Weighting,
        cell_weight: Optional[np.ndarray] = None,
        pairs_at: Optional[np.ndarray] = None,
    ) -> ChunkNormals:
        """The chunk's share of the normal equations at coefficients ``c``; with
        ``cell_weight`` (K,) each point's row weighed by its cell's data weight
        (:func:`cell_data_weights`), ``wvv`` still the unweighted ``sum w v²`` (the points'
        own variance, for the variance components). With ``pairs_at`` (K, 3) the pairs,
        their target normals and the robust weights are those of the points moved by
        ``pairs_at`` (:meth:`held_normal_equations`)."""
        if pairs_at is not None:
            return self.held_normal_equations(c, weighting, cell_weight, pairs_at)
        ok, nrm, v, _, wt, dw, nmat, rhs, gram = self._assembled(c, weighting, cell_weight)
        return ChunkNormals(
            nmat, rhs, gram, float(np.sum(wt * v * v)), int(np.count_nonzero(wt)),
            int(np.count_nonzero(ok)), float(np.sum(dw * v * v)),
        )  # fmt: skip

    def _assembled(self, c: np.ndarray, weighting: Weighting, cell_weight):
        """``(ok, nrm, v, target index, robust weights, row weights, nmat, rhs, gram)`` of
        the pairs at coefficients ``c`` (:meth:`pairs`, :func:`_assemble_kron`)."""
        ok, nrm, v, j = self.pairs(c)
        keep, wv, _ = weighting.apply(v[ok])
        wt = np.zeros(len(v))
        wt[ok] = np.where(keep, wv, 0.0)
        wt[self.gap] = 0.0
        dw = wt * self.data_weight(cell_weight)
        if self._pattern is None:
            self._pattern = NormalPattern.of(self.bounds, self.idx16, self.n_k)
        nmat, rhs, gram = _assemble_kron(
            self.bounds, self.idx16, self.w16, self._bu, self._bv, nrm, v, dw, self.n_k, ok,
            self._pattern,
        )  # fmt: skip
        return ok, nrm, v, j, wt, dw, nmat, rhs, gram

    def held_normal_equations(
        self,
        c: np.ndarray,
        weighting: Weighting,
        cell_weight: Optional[np.ndarray],
        pairs_at: np.ndarray,
    ) -> ChunkNormals:
        """:meth:`normal_equations` at ``c`` with the pairs held: each point keeps the target
        point, the normal and the robust weight it had at ``pairs_at`` (K, 3), and only its
        residual ``v = n · (moved point - target)`` follows ``c``. The point-to-plane problem
        is then quadratic in ``c``: the normal and Gram matrices are those of ``pairs_at``
        (kept between calls with the same ``pairs_at``, ``weighting`` and ``cell_weight``;
        a chunk made anew computes them again, the same), the right-hand side
        ``sum w a (n · ...)`` one sparse product per component. The pairs do not jitter
        with the field, so the fit converges where the nearest-neighbour pairs of a moving
        field wander (docs/fields.md, "Pairs held once the steps stop shrinking")."""
        pairs_at = np.asarray(pairs_at, dtype=np.float64)
        cw = None if cell_weight is None else np.asarray(cell_weight, dtype=np.float64)
        key = self._held_key
        hit = (
            key is not None
            and np.array_equal(key[0], pairs_at)
            and key[1].robust == weighting.robust
            and np.array_equal(key[1].numbers(), weighting.numbers(), equal_nan=True)
            and ((key[2] is None and cw is None) or (
                key[2] is not None and cw is not None and np.array_equal(key[2], cw)))
        )  # fmt: skip
        if not hit:
            ok, nrm, v0, j, wt, dw, nmat, _, gram = self._assembled(pairs_at, weighting, cw)
            target = np.zeros((len(v0), 3))
            target[ok] = self.before[j[ok]]
            self._held_key = (pairs_at.copy(), weighting, None if cw is None else cw.copy())
            self._held = (ok, nrm, target, wt, dw, nmat, gram)
        ok, nrm, target, wt, dw, nmat, gram = self._held
        v = np.einsum("ij,ij->i", nrm, self.moved(np.asarray(c, dtype=np.float64)) - target)
        v[~ok] = 0.0
        rhs = np.asarray(self._basis_pts.T @ ((dw * v)[:, None] * nrm)).T.reshape(-1)
        return ChunkNormals(
            nmat, rhs, gram, float(np.sum(wt * v * v)), int(np.count_nonzero(wt)),
            int(np.count_nonzero(ok)), float(np.sum(dw * v * v)),
        )  # fmt: skip

    def report(
        self,
        c: np.ndarray,
        weighting: Weighting,
        block_m: Optional[float] = None,
        cell_weight: Optional[np.ndarray] = None,
    ) -> ChunkReport:
        """The chunk's share of the final sums at coefficients ``c``; with ``block_m``
        (metres) its block sums of the scores too (:mod:`slipmap.core.icp_blocks`). With
        ``cell_weight`` the scores are ``psi sqrt(dw)``: a cell of data weight ``dw = 1/F``
        enters the normal equations as ``dw`` times its points, whose summed scores vary as
        ``F`` times independent ones (the model of the weights)."""
        ok, nrm, v, tid = self.pairs(c)
        keep, wv, dpsi = weighting.apply(v[ok])
        psi = np.where(keep, wv * v[ok], 0.0)
        tk = tid[ok][keep]
        ut, inv = np.unique(tk, return_inverse=True)
        target_psi = np.bincount(inv.reshape(-1), weights=psi[keep], minlength=ut.size)
        good = ok.copy()
        good[ok] = keep & (wv > 0)
        cells = np.zeros(0, dtype=np.int64)
        cell_n = np.zeros(0, dtype=np.int64)
        cell_ss = np.zeros(0)
        if self.seg is not None:
            s, vs = self.seg[good], v[good]
            inside = s >= 0
            cells, ci = np.unique(s[inside], return_inverse=True)
            ci = ci.reshape(-1)
            cell_n = np.bincount(ci, minlength=cells.size).astype(np.int64)
            cell_ss = np.bincount(ci, weights=vs[inside] ** 2, minlength=cells.size)
        scores = None
        if block_m is not None:
            from .icp_blocks import spline_block_scores

            psi_all = np.zeros(len(v))
            psi_all[ok] = psi * np.sqrt(self.data_weight(cell_weight)[ok])
            psi_all[self.gap] = 0.0  # no weight in the fit: no score
            scores = spline_block_scores(
                xy=self.a[:, :2], psi=psi_all, nrm=nrm, idx16=self.idx16, w16=self.w16,
                block_m=block_m, origin_xy=self.origin_xy, seg=self.seg,
                group=np.repeat(np.arange(len(self.bounds) - 1), np.diff(self.bounds)),
            )  # fmt: skip
        return ChunkReport(
            ss_psi=float(np.sum(psi * psi)),
            used=int(np.count_nonzero(keep & (wv > 0))),
            sum_dpsi=float(np.sum(np.where(keep, dpsi, 0.0))),
            n_ok=int(np.count_nonzero(ok)),
            knots=np.unique(self.idx16[ok].reshape(-1)),
            targets=self.before[ut],
            target_psi=target_psi,
            cells=cells,
            cell_n=cell_n,
            cell_ss=cell_ss,
            sum_w=float(np.sum(np.where(keep, wv, 0.0))),
            block_scores=scores,
        )

    def rigid_misfits(self, c: np.ndarray, report_xy: np.ndarray, x: np.ndarray, zc: np.ndarray):
        """The residuals a rigid cell fit ``x`` would leave at its paired points, were the
        ground moved by the field of coefficients ``c`` (:func:`rigid_projection`):
        ``v + n . u - r . x``, ``v`` the point's residual at the field, ``u`` the field at it,
        ``r = (n, q x n)`` its row with ``q`` its offset from the cell's (x, y) and the cell's
        mean z ``zc`` (K,), ``x`` (K, 6) each cell's translation and rotation there.

        Returns
        -------
        (cells (M,) int64, t (M,) float64)
            The cells of the chunk's paired points in a cell, and their residuals.
        """
        s, v, nu, rows = self._rigid_terms(c, report_xy, zc)
        return s, v + nu - np.einsum("ij,ij->i", rows, x[s])

    def _rigid_terms(self, c, report_xy, zc):
        """``(cells (M,), v (M,), n . u (M,), rows (M, 6))`` of the paired points in a cell
        at coefficients ``c``, the rows about each cell's (x, y) and ``zc`` (kept for the
        same ``c`` and ``zc``: :func:`rigid_projection` iterates on them)."""
        key = self._rigid_key
        if key is not None and np.array_equal(key[0], c) and np.array_equal(key[1], zc):
            return self._rigid_cache
        if self.seg is None:
            e = np.zeros(0)
            return np.zeros(0, np.int64), e, e, np.zeros((0, 6))
        ok, nrm, v, _ = self.pairs(c)
        sel = ok & ~self.gap & (self.seg >= 0)
        s = self.seg[sel]
        n, u = nrm[sel], self._basis_pts[sel] @ c
        q = self.a[sel] - np.c_[np.asarray(report_xy, dtype=np.float64)[s], zc[s]]
        rows = np.c_[n, np.cross(q, n)]
        out = (s, v[sel], np.einsum("ij,ij->i", n, u), rows)
        self._rigid_key, self._rigid_cache = (np.array(c, copy=True), np.array(zc, copy=True)), out
        return out

    def _own_rows(self, c, report_xy, x, zc, thr, scale, robust):
        """:meth:`rigid_rows` with the rigid cells' own weights (its ``own``)."""
        s, v, nu, rows = self._rigid_terms(c, report_xy, zc)
        t = v + nu - np.einsum("ij,ij->i", rows, x[s])
        keep = np.abs(t) <= thr[s]
        if robust is None:
            w = keep.astype(np.float64)
        else:
            w = _robust_weights(t, scale[s], keep, robust)[0]
        use = w > 0
        if not use.any():
            z = np.zeros(0)
            return np.zeros(0, np.int64), np.zeros((0, 6, 6)), np.zeros((0, 6)), z, z
        s, w, rows, nu = s[use], w[use], rows[use], nu[use]
        cells, ci = np.unique(s, return_inverse=True)
        ci = ci.reshape(-1)
        count = np.bincount(ci, minlength=cells.size).astype(np.float64)
        nm, rhs = _cell_normal_sums(ci, cells.size, w, rows, nu)
        return cells, nm, rhs, zc[cells] * count, count

    def rigid_rows(self, c: np.ndarray, weighting: Weighting, report_xy: np.ndarray, own=None):
        """The chunk's share of each cell's rigid fit to the field of coefficients ``c``
        (:func:`rigid_projection`): per cell with points, the linearised point-to-plane
        normal matrix ``sum w r rᵀ`` (6, 6) and right-hand side ``sum w r (n . u)`` (6,) of
        the rows ``r = (n, q x n)``, ``q`` the point's offset from the cell's (x, y) and the
        mean z of the chunk's points of the cell, ``u`` the field at the point, ``n`` its
        target normal, ``w`` its robust weight; and the cell's sum of z and count of those
        points. ``w`` is the field's ``weighting``, or with ``own = (x, zc, threshold,
        scale, robust)`` the rigid cells' own: each cell's trimming ``threshold`` (K,) and
        robust ``scale`` (K,) applied to the residuals the cell's fit ``x`` (K, 6) leaves
        (:meth:`rigid_misfits`); the rows are then about the cells' mean z ``zc`` (K,), and
        their sum of z is ``zc`` times their count.

        Returns
        -------
        (cells (C,) int64, nm (C, 6, 6), rhs (C, 6), sum_z (C,), count (C,))
        """
        if own is not None:
            return self._own_rows(c, report_xy, *own)
        w = np.zeros(len(self.a))
        ok, nrm, v, _ = self.pairs(c)
        keep, wv, _ = weighting.apply(v[ok])
        w[ok] = np.where(keep, wv, 0.0)
        w[self.gap] = 0.0
        sel = (w > 0) if self.seg is None else (w > 0) & (self.seg >= 0)
        if self.seg is None or not np.any(sel):
            z = np.zeros(0)
            return np.zeros(0, np.int64), np.zeros((0, 6, 6)), np.zeros((0, 6)), z, z
        u = self._basis_pts[sel] @ c
        n, p, s, ws = nrm[sel], self.a[sel], self.seg[sel], w[sel]
        cells, ci = np.unique(s, return_inverse=True)
        ci = ci.reshape(-1)
        sum_z = np.bincount(ci, weights=p[:, 2], minlength=cells.size)
        count = np.bincount(ci, minlength=cells.size).astype(np.float64)
        q = p - np.c_[np.asarray(report_xy, dtype=np.float64)[s], (sum_z / count)[ci]]
        rows = np.c_[n, np.cross(q, n)]
        nm, rhs = _cell_normal_sums(ci, cells.size, ws, rows, np.einsum("ij,ij->i", n, u))
        return cells, nm, rhs, sum_z, count


def _cell_normal_sums(ci, n_cells: int, w, rows, y):
    """Per cell ``sum w r rᵀ`` (C, 6, 6) and ``sum w r y`` (C, 6) of the points' rows ``r``
    (M, 6), weights ``w`` and observations ``y`` (M,), ``ci`` (M,) their cell in 0..C-1
    (by bincount: np.add.at's sums in the same order, ~10x faster)."""
    nm_p = w[:, None, None] * rows[:, :, None] * rows[:, None, :]
    nm = np.bincount(
        (ci[:, None] * 36 + np.arange(36)).ravel(), weights=nm_p.ravel(),
        minlength=n_cells * 36,
    ).reshape(n_cells, 6, 6)  # fmt: skip
    rhs_p = (w * y)[:, None] * rows
    rhs = np.bincount(
        (ci[:, None] * 6 + np.arange(6)).ravel(), weights=rhs_p.ravel(), minlength=n_cells * 6
    ).reshape(n_cells, 6)  # fmt: skip
    return nm, rhs


#: ``run(stage, *args) -> [result of every chunk]``: the chunks' methods ``residuals``,
#: ``normal_equations`` and ``report`` run on every chunk, in process or on tile blocks
ChunkRunner = Callable[..., Sequence]


def fit_spline_field(
    after: np.ndarray,
    *,
    before: np.ndarray,
    tree,
    normals: Callable[[np.ndarray], np.ndarray],
    initial: Callable[[np.ndarray], np.ndarray],
    report_xy: np.ndarray,
    report_seg: Optional[np.ndarray] = None,
    report_pairs: Optional[np.ndarray] = None,
    spacing_m: float,
    smoothing: Optional[float] = None,
    gate_m: float = np.inf,
    opts: _Options,
    progress: Optional[ProgressCallback] = None,
    grid=None,
    breaklines=None,
    breakline_gap_m: float = 0.0,
    block_m: Optional[float] = None,
    cell_weight: Optional[np.ndarray] = None,
    smoothing_start: Optional[np.ndarray] = None,
    defer_report: bool = False,
):
    """Fit a bicubic B-spline displacement field to two epochs by point-to-plane ICP.

    One chunk of all the points through :func:`fit_spline_chunks` (a tiled run gives it one
    chunk per tile block: the same code).

    Parameters
    ----------
    after : (P, 3) float64
        Epoch-2 points, metres (centred: small coordinates).
    before : (M, 3) float64
        Epoch-1 points, same frame.
    tree
        Nearest-neighbour structure over ``before`` with ``query(xyz, workers=)`` in the same
        frame (:class:`scipy.spatial.cKDTree` or the windowed ICP's offset tree).
    normals : callable
        ``normals(ids (J,)) -> (J, 3)`` unit normals of epoch-1 points (NaN: unusable).
    initial : callable
        ``initial(xy (K, 2)) -> (K, 3)`` starting field (e.g. the cells' motions), metres.
    report_xy : (K, 2) float64
        Positions to report the field at (the cell centres).
    report_seg : (P,) int64, optional
        Cell (index into ``report_xy``) of each after-point, for the per-cell ``rmse`` and
        ``n`` (-1: none).
    report_pairs : (Q, 2) int64, optional
        Pairs of report positions (indices into ``report_xy``) whose covariances are wanted
        (``SplineFit.pair_cov``; e.g. neighbouring cells, for their variance factor).
    spacing_m : float
        Knot spacing, metres (> 0).
    smoothing : float, optional
        Weight of the second-difference penalty relative to the median diagonal of the
        normal matrix (>= 0). None (default): estimated from the data, one weight per
        component, by variance-component estimation (:func:`_variance_components`): the
        ratio of the observations' variance to that of the field's second differences,
        each over its redundancy. A field without curvature (a uniform shift) is then
        smoothed hard and one with a lobe less.
    gate_m : float
        Largest point-to-point distance of a correspondence, metres.
    opts
        ICP options: ``max_iterations``, ``tolerance_m`` (RMS change of the field at the
        points), ``robust``, ``trim_fraction``.
    progress : callable, optional
        ``progress(fraction, message)`` per iteration; may raise CancelledError.
    grid : slipmap.core.icp_numba.NumbaTargets or slipmap.core.opencl.nearest.GridTargets, optional
        ``before`` for compiled kernels (CPU or OpenCL): the pairs are found there (the same
        pairs).
    breaklines : Breaklines, optional
        Lines the field may jump across (:mod:`slipmap.core.breaklines`, in the frame of
        ``after``): every knot whose support a line may cut gets a copy for the line's far
        side (:func:`knot_copies`), each point and report position takes, of its 16 knots,
        the versions on its own side (:func:`spline_basis`), and the penalty's second
        differences join only versions on one side (:func:`sided_second_differences`). The
        field is then smooth on each side and free to jump across a line; around the tip of
        a line that ends inside the area the penalty ties the copies to the other side's
        knots, so the field stays continuous there (as far as the data let it). Copies that no
        point uses are held by the penalty and a small ridge.
    breakline_gap_m : float
        Points closer than this to a breakline are left out (a line placed from the data is
        known to this much only: the points between it and the scarp would pull the wrong
        side's field).
    block_m : float, optional
        Block side (metres) of the block covariance ``SplineFit.cov_blocks``
        (:mod:`slipmap.core.icp_blocks`); None: not computed.
    cell_weight : (K,) float64 or callable, optional
        Data weight of each report cell's points, ``1 / F`` with ``F`` the cell's honest over
        formal variance (its points' share of independent observations), or a callable
        ``cell_weight(projection (K, 3)) -> (K,) or None`` that makes them from the
        :func:`rigid_projection` of the unweighted field (:func:`cell_data_weights`; the field
        is then fitted without weights first and again, from there, with them; None: the
        unweighted fit). The variance components take the points' own variance and, with
        the smoothing estimated, a penalty weight per second difference
        (:func:`_local_variance_components`). None: every point counts as independent.
    smoothing_start : (3,) or (4,) float64, optional
        With ``smoothing=None``: where the estimate of the unweighted fit's penalty weights
        starts (relative, as ``smoothing``; e.g. ``SplineFit.smoothing_estimate`` of a fit
        of the same points), instead of :data:`AUTO_START`. With ``initial`` that fit's
        field, a refit (other breaklines) starts where the first one ended and needs a
        few iterations instead of its own 20-odd (issue #29 item 5). The weighted fits'
        local weights start at :data:`AUTO_START` as before.
    defer_report : bool
        As :func:`fit_spline_chunks`: a :class:`DeferredFit` (e.g. the fit with candidate
        breaklines, whose field alone is used).

    Returns
    -------
    SplineFit or DeferredFit

    Raises
    ------
    InvalidParameterError
        ``spacing_m`` not positive or ``smoothing`` negative.
    InputDataError
        Too few correspondences for the knots.
    """
    a = np.asarray(after, dtype=np.float64)
    _check_smoothing(smoothing)
    frame = knot_frame(
        a[:, :2].min(axis=0), a[:, :2].max(axis=0), report_xy, spacing_m, lines=breaklines
    )
    chunk = SplineChunk(
        a, frame=frame, before=before, tree=tree, normals=normals, gate_m=gate_m,
        seg=report_seg, grid=grid, breakline_gap_m=breakline_gap_m,
    )  # fmt: skip

    def run(stage, *args):
        return [getattr(chunk, stage)(*args)]

    return fit_spline_chunks(
        run, frame=frame, initial=initial, report_xy=report_xy, report_pairs=report_pairs,
        smoothing=smoothing, gate_m=gate_m, opts=opts, progress=progress, block_m=block_m,
        cell_weight=cell_weight, smoothing_start=smoothing_start, defer_report=defer_report,
    )  # fmt: skip


def _check_smoothing(smoothing) -> float:
    lam = AUTO_START if smoothing is None else float(smoothing)
    if not (np.isfinite(lam) and lam >= 0):
        raise InvalidParameterError(f"spline_smoothing must be >= 0, got {smoothing!r}")
    return lam


def _sum_sparse(parts, n: int):
    import scipy.sparse as sp

    out = sp.csr_matrix((n, n))
    for p in parts:
        out = out + p
    return out.tocsr()


@single_blas_thread()
def fit_spline_chunks(
    run: ChunkRunner,
    *,
    frame: SplineField,
    initial: Callable[[np.ndarray], np.ndarray],
    report_xy: np.ndarray,
    report_pairs: Optional[np.ndarray] = None,
    smoothing: Optional[float] = None,
    gate_m: float = np.inf,
    opts: _Options,
    progress: Optional[ProgressCallback] = None,
    block_m: Optional[float] = None,
    cell_weight=None,
    penalty_width_knots: Optional[float] = None,
    smoothing_start: Optional[np.ndarray] = None,
    defer_report: bool = False,
):
    """:func:`fit_spline_field` over chunks of points: the Gauss-Newton normal equations,
    the weights' scale and the final sums are sums (or quantiles) over the after-points, so
    each chunk (:class:`SplineChunk`) gives its share and this driver adds them, solves once
    per iteration and hands the new coefficients back.

    Parameters
    ----------
    run : callable
        ``run(stage, *args) -> [result per chunk]``, ``stage`` one of :class:`SplineChunk`'s
        ``residuals(c)``, ``normal_equations(c, weighting)``, ``report(c, weighting)``; every
        after-point in exactly one chunk, each chunk's ``seg`` indexing ``report_xy``.
    frame : SplineField
        The knot lattice (:func:`knot_frame` of all chunks' points).
    initial, report_xy, report_pairs, smoothing, gate_m, opts, progress, block_m, cell_weight,
    smoothing_start
        As :func:`fit_spline_field` (with ``block_m`` every chunk's ``report`` gives its
        block sums, :class:`~slipmap.core.icp_blocks.BlockScores`, added here).
    penalty_width_knots : float, optional
        Width of the local penalty's Gaussian kernel in knot spacings (with cell weights and
        the smoothing estimated). None: each of :data:`LOCAL_WIDTHS_KNOTS` iterated from the
        same start, the one of the lowest :func:`_restricted_score` kept and only it reported
        (the data choose how local the smoothing is, as they choose how strong).

    Returns
    -------
    SplineFit
    """
    import scipy.sparse as sp

    if callable(cell_weight):  # weights from the unweighted field (cell_data_weights)
        first = fit_spline_chunks(
            run, frame=frame, initial=initial, report_xy=report_xy, report_pairs=report_pairs,
            smoothing=smoothing, gate_m=gate_m, opts=opts, progress=progress, block_m=block_m,
            smoothing_start=smoothing_start, defer_report=True,
        )  # fmt: skip
        c1 = first.field.all_coefficients()
        wgt1 = Weighting.of(np.concatenate([np.asarray(p) for p in run("residuals", c1)]), opts)
        cell_weight = cell_weight(rigid_projection(run, c1, wgt1, report_xy, opts))
        if cell_weight is None:  # no model of the cells' shared error: the unweighted fit
            return first.finish()
        cell_weight = np.asarray(cell_weight, dtype=np.float64)
        initial = first.field
    lam = _check_smoothing(smoothing)
    rxy = np.asarray(report_xy, dtype=np.float64).reshape(-1, 2)
    h, n_x, n_y = frame.spacing_m, frame.n_x, frame.n_y
    lo = np.asarray(frame.origin_xy, dtype=np.float64)
    kx, ky = n_x + 3, n_y + 3
    n_grid = kx * ky
    bl = frame.lines
    copy_index = knot_copies((float(lo[0]), float(lo[1])), h, n_x, n_y, bl)
    n_k = n_grid + int(np.count_nonzero(copy_index >= 0))  # grid knots, then their copies
    # start: least-squares fit of the initial field on a 4-per-interval lattice
    gx, gy = np.meshgrid(
        lo[0] + h * np.arange(4 * n_x + 1) / 4, lo[1] + h * np.arange(4 * n_y + 1) / 4
    )
    field = SplineField((float(lo[0]), float(lo[1])), h, n_x, n_y, np.zeros((ky, kx, 3)), lines=bl)
    gxy = np.column_stack([gx.ravel(), gy.ravel()])
    gi, gw = field._basis(gxy, copy_index=copy_index)
    bmat = sp.csr_matrix(
        (gw.ravel(), gi.ravel(), np.arange(0, gi.size + 1, 16)), shape=(len(gxy), n_k)
    )
    f0 = np.asarray(initial(gxy), dtype=np.float64).reshape(-1, 3)
    f0 = np.where(np.isfinite(f0), f0, 0.0)
    rmat, rpos = sided_second_differences(field.origin_xy, h, n_x, n_y, bl, copy_index, rows=True)
    r2 = (rmat.T @ rmat).tocsr()
    # with the data weighed by their independent share (cell_weight), the penalty's weights
    # are estimated locally (_local_variance_components): a lobe keeps its curvature where
    # the ground around it is held flat. Without weights the points count as independent
    # and a local estimate would follow their shared errors further: one weight per
    # component there, as before.
    local = smoothing is None and cell_weight is not None
    n_nominal = float(np.count_nonzero(r2.diagonal() > 0)) if local else None
    lhs0 = (bmat.T @ bmat + 1e-6 * r2 + 1e-9 * sp.identity(n_k)).tocsc()
    c0 = factor_spd(lhs0).solve(np.asarray(bmat.T @ f0))  # (K, 3)

    def weighting_at(c):
        absv = np.concatenate([np.asarray(p, dtype=np.float64) for p in run("residuals", c)])
        if absv.size < 3 * 16:
            raise InputDataError(
                f"spline field: only {absv.size} correspondences within "
                f"{gate_m:g} m; use a larger spline_spacing_m or check the epochs' overlap"
            )
        return Weighting.of(absv, opts)

    def local_kernel(width):  # Gaussian of the given width, cut at three widths
        from scipy.spatial import cKDTree

        kt = cKDTree(rpos)
        kd = kt.sparse_distance_matrix(kt, 3.0 * width, output_type="coo_matrix")
        return sp.csr_matrix(
            (np.exp(-0.5 * (kd.data / width) ** 2), (kd.row, kd.col)), shape=(len(rpos),) * 2
        ) + sp.identity(len(rpos), format="csr")

    def iterate(c, kernel, progress):
        """The Gauss-Newton iterations from ``c`` (with ``kernel``: the local penalty):
        ``(c, factor, penalty, iterations, converged, restricted score or None)``."""
        auto = smoothing is None
        lam_abs = None  # absolute penalty weight per component, set at the first iteration
        converged, it = False, 0
        factor = None
        best, since_best = np.inf, 0
        held = None  # the coefficients whose pairs are held (HOLD_PAIRS)
        wgt = None
        for it in range(1, opts.max_iterations + 1):
            report(progress, (it - 1) / opts.max_iterations, f"spline field: iteration {it}")
            if held is None:
                wgt = weighting_at(c)
                parts = run("normal_equations", c, wgt, cell_weight)
            else:
                if wgt is None:  # the robust weights of the held pairs
                    wgt = weighting_at(held)
                parts = run("normal_equations", c, wgt, cell_weight, held)
            nmat = _sum_sparse([p.nmat for p in parts], 3 * n_k)
            gram = _sum_sparse([p.gram for p in parts], n_k)
            rhs = np.sum([p.rhs for p in parts], axis=0)
            wvv = float(sum(p.wvv for p in parts))
            wvv_weighted = float(sum(p.wvv_weighted for p in parts))
            n_obs = int(sum(p.n_obs for p in parts))
            n_ok = int(sum(p.n_ok for p in parts))
            if lam_abs is None:
                dg = nmat.diagonal()
                scale = float(np.median(dg[dg > 0])) if np.any(dg > 0) else 1.0
                warm = smoothing is None and not local and smoothing_start is not None
                start = smoothing_start if warm else lam
                start = np.asarray(start, dtype=np.float64).ravel()
                start = np.repeat(start, 3) if start.size == 1 else start
                lam_abs = np.append(start[:3], start[3] if start.size > 3 else 0.0) * scale
                ridge = sp.identity(3 * n_k, format="csr") * (1e-12 * scale)
                if n_k > n_grid:  # copies no point uses: held by the penalty and a small ridge
                    idle = nmat.diagonal().reshape(3, n_k).sum(axis=0) <= 0
                    idle[:n_grid] = False
                    ridge = ridge + sp.diags(np.tile(idle * (1e-6 * scale), 3), format="csr")
            if local:
                if np.ndim(lam_abs) == 1:
                    lam_abs = np.repeat(np.asarray(lam_abs)[:, None], rmat.shape[0], axis=1)
            penalty = _penalty_blocks(lam_abs, rmat, r2) + ridge
            cvec = c.T.reshape(-1)  # component-major
            factor = factor_spd(nmat + penalty)
            step = factor.solve(rhs - penalty @ cvec)
            dc = step.reshape(3, n_k).T
            c = c + dc
            if auto and local:
                new = _local_variance_components(
                    factor, rmat, kernel, lam_abs, c, wvv, n_obs, n_nominal
                )
                new = _clip_weights(new, AUTO_RANGE[0] * scale, AUTO_RANGE[1] * scale)
                auto = _weights_moved(new, lam_abs) > AUTO_SETTLED
                lam_abs = new
            elif auto:
                new = _variance_components(factor, r2, lam_abs, c, wvv, n_obs)
                new = _clip_weights(new, AUTO_RANGE[0] * scale, AUTO_RANGE[1] * scale)
                auto = _weights_moved(new, lam_abs) > AUTO_SETTLED
                lam_abs = new
            # RMS change of the field at the paired points: sum_j dc_j' G dc_j over their count
            du2 = sum(float(dc[:, j] @ (gram @ dc[:, j])) for j in range(3))
            rms_du = float(np.sqrt(max(du2, 0.0) / max(n_ok, 1)))
            log.debug("spline field: iteration %d, RMS change %.2e m", it, rms_du)
            # the nearest-neighbour pairs flip as the field moves and the steps shrink slowly
            # (by ~0.8 an iteration on lone-star) towards a jitter: stop at CHANGE_FLOOR of the
            # residuals' robust spread (or at tolerance_m), or when the change stalls
            floor = CHANGE_FLOOR * MAD_TO_SIGMA * wgt.median_abs_m
            best, since_best = (rms_du, 0) if rms_du < best else (best, since_best + 1)
            if rms_du < max(opts.tolerance_m, floor) or since_best >= STALL_ITERATIONS:
                converged = True
                break
            if (
                HOLD_PAIRS
                and held is None
                and since_best >= 1
                and rms_du < HOLD_SHARE * (MAD_TO_SIGMA * wgt.median_abs_m)
            ):
                # the steps stopped shrinking: the pairs jitter as the field moves. Hold
                # them (and their robust weights) from here, so that the penalty's weights
                # settle on one quadratic problem instead of a wandering one
                held, wgt = c.copy(), None
                best, since_best = np.inf, 0
                log.debug("spline field: pairs held from iteration %d", it + 1)
        score = _restricted_score(factor, penalty, c, wvv, wvv_weighted, n_obs) if local else None
        global_estimate = lam_abs / scale if smoothing is None and not local else None
        if global_estimate is not None and HORIZONTAL_MODEL != "principal":
            global_estimate = global_estimate[:3]
        return c, factor, penalty, it, converged, score, global_estimate

    if not local:
        width = None
        c, factor, penalty, it, converged, score, estimate = iterate(c0, None, progress)
    else:
        # the local penalty's width: the given one, or each of LOCAL_WIDTHS_KNOTS iterated
        # from the same start and the likeliest (lowest restricted score) kept; only it is
        # reported below
        widths = LOCAL_WIDTHS_KNOTS if penalty_width_knots is None else (penalty_width_knots,)
        tried = []
        for i, wk in enumerate(widths):
            width = float(wk) * h
            part = scaled(progress, i / len(widths), (i + 1) / len(widths))
            tried.append((width, *iterate(c0, local_kernel(width), part)))
        width, c, factor, penalty, it, converged, score, estimate = min(tried, key=lambda t: t[-2])
        if len(tried) > 1:
            log.info(
                "spline field: local penalty of %.2f m (restricted likelihood: %s)",
                width, ", ".join(f"{t[0]:g} m {t[-2]:.1f}" for t in tried),
            )  # fmt: skip
    field = SplineField(
        field.origin_xy, h, n_x, n_y, c[:n_grid].reshape(ky, kx, 3), lines=bl,
        copy_coefficients=c[n_grid:] if n_k > n_grid else None,
    )  # fmt: skip

    def finish() -> SplineFit:
        # final residuals, sigma0 and the report
        wgt = weighting_at(c)
        bm = None if block_m is None else float(block_m)
        parts = run("report", c, wgt, bm, cell_weight)
        ss = float(sum(p.ss_psi for p in parts))
        used = int(sum(p.used for p in parts))
        n_ok = int(sum(p.n_ok for p in parts))
        data_knots = np.unique(np.concatenate([p.knots for p in parts])).size
        dof = max(used - 3 * data_knots, 1)
        mean_dpsi = float(sum(p.sum_dpsi for p in parts)) / n_ok if n_ok else 1.0
        # points sharing a target point share its error, as in the cells' sigma0; a target is
        # known by its coordinates (chunks of tile blocks share the targets of their halos)
        targets = np.concatenate([p.targets for p in parts]).reshape(-1, 3)
        t_psi = np.concatenate([p.target_psi for p in parts])
        _, tid = np.unique(targets, axis=0, return_inverse=True)
        tid = tid.reshape(-1)
        one = np.zeros(t_psi.size, dtype=np.int64)
        every = np.ones(t_psi.size, dtype=bool)
        inflation = float(_shared_target_inflation(t_psi, every, one, tid, np.array([ss]))[0])
        s0sq = ss / dof / max(mean_dpsi, 1e-12) ** 2 * inflation
        ridx, rw, rwx, rwy = field._basis(rxy, slopes=True, copy_index=copy_index)
        k = len(rxy)
        # rows of (d, d/dx, d/dy) x 3 components against the component-major coefficients
        g = np.zeros((k, 9, 3, 16))
        for comp in range(3):
            g[:, comp, comp] = rw
            g[:, 3 + comp, comp] = rwx
            g[:, 6 + comp, comp] = rwy
        cols = (np.arange(3)[:, None] * n_k + ridx[:, None, :]).reshape(k, 48)
        cov = np.zeros((k, 9, 9))
        pairs = None if report_pairs is None else np.asarray(report_pairs, np.int64).reshape(-1, 2)
        pair_cov = None if pairs is None else np.full((len(pairs), 3), np.nan)
        from .icp_blocks import solve_report_rows

        chunk = 64
        for s0 in range(0, k, chunk):
            part = slice(s0, min(s0 + chunk, k))
            kk = part.stop - part.start
            rows_g, sol = solve_report_rows(factor, g[part], cols[part], 3 * n_k)  # (3K, kk*9)
            full = np.asarray(rows_g @ sol).reshape(kk, 9, kk, 9)
            cov[part] = s0sq * full[np.arange(kk), :, np.arange(kk), :]
            if pairs is not None:  # g_d(j) A^-1 g_d(i)' for the pairs whose first cell is here
                sel = np.flatnonzero((pairs[:, 0] >= part.start) & (pairs[:, 0] < part.stop))
                pj = pairs[sel, 1]
                for comp in range(3):
                    column = (pairs[sel, 0] - part.start) * 9 + comp
                    vals = sol[comp * n_k + ridx[pj], column[:, None]]  # (S, 16)
                    pair_cov[sel, comp] = s0sq * np.sum(vals * rw[pj], axis=1)
        cov_blocks = n_blocks = None
        if block_m is not None:  # the residuals' spatial correlation (issue #29, icp_blocks)
            from .icp_blocks import spline_block_covariance

            c_scale = (
                float(sum(p.sum_w for p in parts)) / max(n_ok, 1) / max(mean_dpsi, 1e-12) ** 2
                * used / dof
            )  # fmt: skip
            cov_blocks, n_blocks = spline_block_covariance(
                [p.block_scores for p in parts], rows=g.reshape(k, 9, 48), cols=cols,
                factor=factor, penalty=penalty, s0sq=s0sq, scale=c_scale,
            )  # fmt: skip
        projection = None
        if cell_weight is not None:
            # what each cell would measure as a rigid cell if the ground moved as this field:
            # the rigid cells' motions less it are the field's misfit (honest sigma, icp.py)
            projection = rigid_projection(run, c, wgt, rxy, opts)
        n_used = np.zeros(k, dtype=np.int64)
        ss_cell = np.zeros(k)
        for p in parts:
            np.add.at(n_used, p.cells, p.cell_n)
            np.add.at(ss_cell, p.cells, p.cell_ss)
        rmse = np.where(n_used > 0, np.sqrt(ss_cell / np.maximum(n_used, 1)), np.nan)
        log.info(
            "spline field: %d knots of %.2f m, %d iterations%s, sigma0 %.4f m (shared-target "
            "inflation %.2f)",
            data_knots, h, it, "" if converged else " (not converged)", np.sqrt(s0sq), inflation,
        )  # fmt: skip
        return SplineFit(
            field=field,
            d=field(rxy),
            gradient=field.gradient(rxy),
            cov=cov,
            rmse=rmse,
            n=n_used,
            sigma0_m=float(np.sqrt(s0sq)),
            iterations=it,
            converged=converged,
            n_coefficients=3 * data_knots,
            pair_cov=pair_cov,
            cov_blocks=cov_blocks,
            n_blocks=n_blocks,
            data_weight=cell_weight,
            projection=projection,
            penalty_width_m=width,
            restricted_score=score,
            smoothing_estimate=estimate,
        )

    if defer_report:
        log.info(
            "spline field: %d iterations%s (its report not made: the field alone is used)",
            it, "" if converged else " (not converged)",
        )  # fmt: skip
        return DeferredFit(field, estimate, finish)
    return finish()


def nearest_plane_residuals(
    q: np.ndarray, *, before: np.ndarray, tree, normals: Callable, gate_m: float
) -> np.ndarray:
    """(P,) signed point-to-plane residual of each point ``q`` (P, 3) against its nearest
    epoch-1 point ``before[j]`` (``tree`` over ``before``, ``normals(j) -> (P, 3)``), metres;
    NaN where that point is farther than ``gate_m`` or its normal is undefined. Used to judge
    which side's field moves a point near a breakline back onto epoch 1
    (:func:`refine_breaklines`, :func:`slipmap.core.breakline_points.place_straight_line`)."""
    dist, j = tree.query(q)
    j = np.asarray(j)
    nn = normals(j)
    v = np.einsum("ij,ij->i", nn, q - before[j])
    return np.where((np.asarray(dist) <= gate_m) & np.all(np.isfinite(nn), axis=1), v, np.nan)


def refine_breaklines(
    field: SplineField,
    after: np.ndarray,
    *,
    before: np.ndarray,
    tree,
    normals: Callable[[np.ndarray], np.ndarray],
    gate_m: float,
    reach_m: float,
    step_m: Optional[float] = None,
    min_jump_m: float = 0.0,
):
    """Move a field's breaklines to where the points say its sides change, and drop those
    across which the field does not jump.

    A line found on a grid of cells lies on a cell edge, up to a cell from the scarp. Each
    point within ``reach_m`` of a line is moved back by the field of its own side and by
    that of the other side (its knots' copies swapped), and its point-to-plane residual
    against epoch 1 says which side it belongs to (where the two differ by more than twice
    the residuals' robust spread). Along each line, every ``step_m`` (default ``reach_m``),
    the line is shifted across by the offset that puts the fewest such points on the wrong
    side (searched over ``±reach_m`` in 41 steps; the middle of the offsets within 1 % of the
    fewest; none where those span more than half the reach, e.g. a scan shadow; the median of
    three neighbouring offsets kept). The side a point belongs to is the one whose field, a
    cell and a half from the line, fits it better (a point on the wrong side bends its side's
    field near the line, not there). The shifted stations make the new line, continued
    straight to the old line's reach. A line across which the two sides'
    fields differ by less than ``min_jump_m`` at the median point near it is dropped: the
    smooth field explains the data there (a steep lobe's flank that the cells took for a
    step).

    Parameters
    ----------
    field : SplineField
        A field fitted with the lines (``field.lines``).
    after : (P, 3) float64
        Epoch-2 points (the frame of the field).
    before, tree, normals, gate_m
        Epoch 1, its nearest-neighbour structure, normals and the pairs' gate, as in
        :func:`fit_spline_field`.
    reach_m : float
        How far from a line points are looked at and the line may move, metres.
    step_m : float, optional
        Spacing of the stations along a line, metres.
    min_jump_m : float
        Smallest median jump of the field across a line that keeps it, metres.

    Returns
    -------
    Breaklines or None
        None when every line is dropped.
    """
    from .breaklines import _douglas_peucker, breaklines, distance_m

    lines = field.lines
    if lines is None or lines.empty:
        return lines
    step = float(reach_m if step_m is None else step_m)
    a = np.asarray(after, dtype=np.float64)
    a = a[distance_m(a, lines) < reach_m]
    if len(a) < 50:
        return lines
    u_own, u_flip = field.both_sides(a[:, :2])

    def residual(q):
        return nearest_plane_residuals(q, before=before, tree=tree, normals=normals, gate_m=gate_m)

    jump = np.linalg.norm(u_own - u_flip, axis=1)
    near_part = np.argmin(np.vstack([distance_m(a, breaklines([p])) for p in lines.parts]), axis=0)
    keep_part = [
        bool(np.any(near_part == k)) and float(np.median(jump[near_part == k])) >= min_jump_m
        for k in range(len(lines))
    ]
    for k, kept in enumerate(keep_part):
        if not kept:
            log.info(
                "breakline %d dropped: the field jumps by %.3f m across it (median), less "
                "than %.3f m", k, float(np.median(jump[near_part == k])) if np.any(
                    near_part == k) else 0.0, min_jump_m,
            )  # fmt: skip
    if not any(keep_part):
        return None
    offsets = np.linspace(-reach_m, reach_m, 41)
    far = 1.5 * reach_m  # where each side's field is not bent by points put on the wrong side
    out, n_decisive, largest = [], 0, 0.0
    for k, part in enumerate(lines.parts):
        if not keep_part[k]:
            continue
        pts = a[near_part == k]
        pxy = pts[:, :2]
        seg_a, seg_b = part[:-1], part[1:]
        seg_d = seg_b - seg_a
        seg_len = np.hypot(seg_d[:, 0], seg_d[:, 1])
        cum = np.r_[0.0, np.cumsum(seg_len)]
        # each point's nearest segment, its arc position and signed offset (left +)
        rel = pxy[:, None, :] - seg_a[None]
        t = np.clip(np.sum(rel * seg_d[None], axis=2) / (seg_len**2)[None], 0.0, 1.0)
        foot = seg_a[None] + t[..., None] * seg_d[None]
        j = np.argmin(np.sum((pxy[:, None, :] - foot) ** 2, axis=2), axis=1)
        dj = seg_d[j] / seg_len[j, None]
        r = pxy - seg_a[j]
        s = dj[:, 0] * r[:, 1] - dj[:, 1] * r[:, 0]
        ell = cum[j] + t[np.arange(len(j)), j] * seg_len[j]
        # which side's motion fits each point: the field a cell and a half to its left and
        # to its right of the line (a point put on the wrong side bends its side's field
        # near the line, not there)
        nrm = np.c_[-dj[:, 1], dj[:, 0]]
        v_left = np.abs(residual(pts - field(pxy + (far - s)[:, None] * nrm)))
        v_right = np.abs(residual(pts - field(pxy - (far + s)[:, None] * nrm)))
        spread = MAD_TO_SIGMA * float(np.nanmedian(np.fmin(v_left, v_right)))
        vl = np.where(np.isfinite(v_left), v_left, np.inf)
        vr = np.where(np.isfinite(v_right), v_right, np.inf)
        decisive = (np.abs(vl - vr) > 2.0 * spread) & (np.isfinite(vl) | np.isfinite(vr))
        n_decisive += int(decisive.sum())
        s, ell = s[decisive], ell[decisive]
        true_side = np.where(vl[decisive] < vr[decisive], 1.0, -1.0)
        n_st = max(int(np.ceil(cum[-1] / step)), 1)
        st = np.linspace(0.0, cum[-1], n_st + 1)
        shift = np.full(len(st), np.nan)
        for i, e in enumerate(st):
            sel = np.abs(ell - e) <= 0.5 * step + 1e-9
            if np.count_nonzero(sel) < 20:
                continue
            wrong = [np.count_nonzero(np.sign(s[sel] - o) != true_side[sel]) for o in offsets]
            wrong = np.asarray(wrong)
            best = np.flatnonzero(wrong <= wrong.min() + 0.01 * sel.sum())
            if np.ptp(offsets[best]) > 0.5 * reach_m:
                continue  # no points across the candidates (a scan shadow): the line goes
                # on as its neighbouring stations place it
            shift[i] = offsets[best[np.argmin(np.abs(offsets[best] - np.median(offsets[best])))]]
        if not np.any(np.isfinite(shift)):
            out.append(part)
            continue
        log.debug("breakline %d: stations %s, shifts %s", k, np.round(st, 1), shift)
        good = np.flatnonzero(np.isfinite(shift))
        if good.size < 2:
            out.append(part)
            continue
        sh = shift[good]
        if sh.size >= 3:
            sh = np.r_[sh[0], np.median(np.c_[sh[:-2], sh[1:-1], sh[2:]], axis=1), sh[-1]]
        # stations with points, on the line and shifted along its left normal there
        seg_of = np.clip(np.searchsorted(cum, st, side="right") - 1, 0, len(seg_len) - 1)
        tt = (st - cum[seg_of]) / seg_len[seg_of]
        base = seg_a[seg_of] + tt[:, None] * seg_d[seg_of]
        dirs = seg_d[seg_of] / seg_len[seg_of, None]
        normal = np.c_[-dirs[:, 1], dirs[:, 0]]
        placed = base[good] + sh[:, None] * normal[good]
        # beyond the first and last stations with points the line goes on straight, along
        # the placed line's end (over up to three stations), as far as it reached before
        k_end = min(2, len(placed) - 1)
        ends = []
        for reach, tip, back in (
            (st[good[0]] - st[0], placed[0], placed[k_end]),
            (st[-1] - st[good[-1]], placed[-1], placed[-1 - k_end]),
        ):
            t = tip - back
            ends.append(tip + reach * t / max(float(np.hypot(*t)), 1e-12))
        line = np.vstack([ends[0], placed, ends[1]])
        out.append(_douglas_peucker(line, 0.1 * step))
        largest = max(largest, float(np.nanmax(np.abs(shift))))
    log.info(
        "breaklines placed on the points: %d decisive points, shifts up to %.2f m",
        n_decisive,
        largest,
    )
    return breaklines(out)


#: iterations of the rigid cells' own robust weights in :func:`rigid_projection` (0: the
#: field's weights only, the default), ended early once no cell's translation moves by more
#: than :data:`PROJECTION_TOLERANCE_M`. The robust scale and the fit converge together,
#: slowly: on the landslide harness's elongated lobe (TLS, seed 0) all but two cells move
#: by less than 0.3 mm after five iterations, those two by 3-4 mm per iteration after ten;
#: on the synthetic lobe of the tests the rigid cells less the projection are 2.4 sigmas
#: RMS after five iterations, 1.2 after ten, 0.4 after twenty. Each costs about 25 ms on
#: lone-star's 80 000 paired points. Ten, measured over the harness (docs/fields.md, stop
#: 63): the data weights' floor falls from the rigid cells' model error to their error
#: (lobe-long F 13 -> 3), the scarp cases gain (the fault 1.83 -> 1.71 cm) and the smooth
#: lobes lose (lobe-long 1.11 -> 1.22 cm); not the default
PROJECTION_ITERATIONS = 0
PROJECTION_TOLERANCE_M = 1e-4


def rigid_projection(run: ChunkRunner, c: np.ndarray, weighting: Weighting, report_xy, opts=None):
    """What each cell would measure as a rigid cell if the ground moved as the field of
    coefficients ``c``: the translation, at the cell's centre (its x, y and the mean z of
    its points), of the linearised point-to-plane rigid fit of the field's motion at the
    cell's paired points (their target normals and robust weights).

    A rigid cell measures a weighted mean of the motion over its points, not the motion at
    its centre; on a lobe a few cells wide the two differ by centimetres (the rigid cells'
    model error). The field's own rigid projection has the same model error, so the rigid
    cells' motions less this projection keep the cells' errors (and the field's misfit)
    and lose the field's shape (:func:`cell_data_weights`).

    The points are weighed as the field weighs them, or, with ``opts`` and
    :data:`PROJECTION_ITERATIONS` above 0 (an option, off by default), as the rigid cell
    weighs them: a rigid cell on a straining lobe leaves residuals of centimetres at its
    corners, and its robust weights (each cell's own scale,
    :func:`~slipmap.core.icp_cells.seg_scales`) take them down, so it measures another mean
    than the field's weights would. The fit is then iterated with the weights the residuals
    ``v + n . u - r . x`` of its own fit ``x`` give (:meth:`SplineChunk.rigid_misfits`), as
    the cell's ICP weighs them. Measured on the landslide harness's elongated lobe (TLS,
    seed 0): the rigid cells' motions less the projection with the field's weights were 2-8
    times the cells' sigmas on the straining cells, and with their own weights as much as
    on the still cells (docs/fields.md, stop 63).

    Parameters
    ----------
    run : ChunkRunner
        As :func:`fit_spline_chunks` (every chunk's ``seg`` indexing ``report_xy``).
    c : (n_k, 3) float64
        The field's coefficients.
    weighting : Weighting
        The robust weights at ``c``.
    report_xy : (K, 2) float64
        The cell centres, metres.
    opts : _Options, optional
        The fit's options (their ``robust`` and ``trim_fraction``): the rigid cells' own
        weights. None: the field's ``weighting``.

    Returns
    -------
    (K, 3) float64
        Metres; NaN for a cell whose rigid fit is singular or has no points.
    """
    rxy = np.asarray(report_xy, dtype=np.float64).reshape(-1, 2)
    x, zc = _rigid_solve(list(run("rigid_rows", c, weighting, rxy)), len(rxy))
    if opts is None:
        return x[:, :3]
    from .icp_cells import seg_scales

    for _ in range(int(PROJECTION_ITERATIONS)):
        xf = np.where(np.isfinite(x), x, 0.0)
        parts = list(run("rigid_misfits", c, rxy, xf, zc))
        s = np.concatenate([p[0] for p in parts] + [np.zeros(0, np.int64)])
        t = np.concatenate([p[1] for p in parts] + [np.zeros(0)])
        order = np.argsort(s, kind="stable")
        thr, scale = seg_scales(t[order], s[order], len(rxy), opts)
        own = (xf, zc, thr, scale, opts.robust)
        new, _ = _rigid_solve(list(run("rigid_rows", c, weighting, rxy, own)), len(rxy))
        step = np.nanmax(np.abs(new[:, :3] - x[:, :3]), initial=0.0)
        x = new
        if not step > PROJECTION_TOLERANCE_M:
            break
    return x[:, :3]


def _rigid_solve(parts, k: int):
    """The chunks' :meth:`SplineChunk.rigid_rows` summed and solved per cell: ``(x (K, 6),
    zc (K,))`` each cell's translation and rotation at its (x, y) and mean z ``zc`` (NaN
    where singular or without points)."""
    sz, cnt = np.zeros(k), np.zeros(k)
    for cells, _, _, z, m in parts:
        np.add.at(sz, cells, z)
        np.add.at(cnt, cells, m)
    zc = sz / np.maximum(cnt, 1.0)
    # each chunk's rows are about its own mean z of the cell: moved to the cell's mean z
    # (rows (n, q x n) about an origin moved by delta become (n, q x n - delta x n))
    nm, rhs = np.zeros((k, 6, 6)), np.zeros((k, 6))
    for cells, n6, r6, z, m in parts:
        dz = zc[cells] - z / np.maximum(m, 1.0)
        t = np.tile(np.eye(6), (len(cells), 1, 1))
        # -[delta]x for delta = (0, 0, dz): rows 3..5, columns 0..2
        t[:, 3, 1] = dz
        t[:, 4, 0] = -dz
        np.add.at(nm, cells, t @ n6 @ np.transpose(t, (0, 2, 1)))
        np.add.at(rhs, cells, np.einsum("cij,cj->ci", t, r6))
    out = np.full((k, 6), np.nan)
    for i in np.flatnonzero(cnt > 0):
        if np.linalg.cond(nm[i]) < 1e12:
            out[i] = np.linalg.solve(nm[i], rhs[i])
    return out, zc


def rigid_projection_reference(
    field, after, seg, report_xy, weights, normals_at, *, v=None, paired=None, opts=None
):
    """Slow reference of :func:`rigid_projection`: one least-squares solve per cell with
    ``numpy.linalg.lstsq`` on the explicit rows (``weights`` (P,) and ``normals_at`` (P, 3):
    each after-point's robust weight and target normal). With ``opts``, ``v`` (P,) the
    points' residuals at the field and ``paired`` (P,) bool the points paired (outside the
    breaklines' gap): the rigid cells' own weights, per cell from the residuals its fit
    leaves (:func:`~slipmap.core.icp_options._weights` of the cell's alone), iterated as
    :func:`rigid_projection` iterates them."""
    from .icp_options import _weights

    rxy = np.asarray(report_xy, dtype=np.float64)
    u = field(after[:, :2])
    k = len(rxy)

    def solve(w, z_at=None):  # z_at: the cells' z of the rows (default their points' mean)
        x, zc = np.full((k, 6), np.nan), np.zeros(k)
        for i in range(k):
            m = (seg == i) & (w > 0)
            if not m.any():
                continue
            p = after[m]
            zc[i] = float(np.mean(p[:, 2])) if z_at is None else z_at[i]
            q = p - np.r_[rxy[i], zc[i]]
            n = normals_at[m]
            rows = np.c_[n, np.cross(q, n)] * np.sqrt(w[m])[:, None]
            y = np.einsum("ij,ij->i", n, u[m]) * np.sqrt(w[m])
            x[i] = np.linalg.lstsq(rows, y, rcond=None)[0]
        return x, zc

    x, zc = solve(np.asarray(weights, dtype=np.float64))
    if opts is None:
        return x[:, :3]
    for _ in range(int(PROJECTION_ITERATIONS)):
        xf = np.where(np.isfinite(x), x, 0.0)
        w = np.zeros(len(after))
        for i in range(k):
            m = (seg == i) & paired
            if not m.any():
                continue
            n = normals_at[m]
            q = after[m] - np.r_[rxy[i], zc[i]]
            t = v[m] + np.einsum("ij,ij->i", n, u[m]) - np.c_[n, np.cross(q, n)] @ xf[i]
            w[m] = _weights(t, opts)[1]
        new, _ = solve(w, zc)
        step = np.nanmax(np.abs(new[:, :3] - x[:, :3]), initial=0.0)
        x = new
        if not step > PROJECTION_TOLERANCE_M:
            break
    return x[:, :3]


def cell_data_weights(
    row, col, d, cov_honest, cov_formal, n, *, usable, projection, fitted=None, rmse=None
) -> Tuple[np.ndarray, object]:
    """Each cell's data weight ``1 / F`` for the spline field: the share of its points'
    count that behaves as independent observations, from the honest-σ model of the rigid
    cells (:mod:`slipmap.core.icp_blocks`).

    A cell's points share part of their error (the point-to-plane bias of a curved, sampled
    surface, errors correlated over more than a block): the variance of the cell's motion
    is ``F`` times the formal one, ``F = kappa_c (a + n / n_cap)`` (its shrunk block ratio
    and the cell-wide floor; with the cells' residual RMS, ``rmse``, the floor grows each
    cell by its surface share ``s_c``: ``F = kappa_c (1 + (a - 1) s_c + s_c n / n_cap)``,
    :func:`~slipmap.core.icp_blocks.surface_share`). Weighed as independent points, the
    cells' data outweigh the penalty ``F``-fold, the variance components take the shared
    errors for the field's curvature, and the field follows them (on a uniform 0.65 m
    shift of lone-star the field's error was twice the rigid cells'). Weighed ``1/F`` a
    cell counts as ``n / F`` points. The floor comes from the agreement of neighbouring rigid cells
    (:func:`~slipmap.core.icp_blocks.cell_floor`), here of their motions less the rigid
    projection of the unweighted field (:func:`rigid_projection`): a rigid cell's model
    error on a straining lobe (its weighted mean motion is not the motion at its centre)
    would count as noise otherwise.

    Parameters
    ----------
    row, col : (K,) int
        The cells' grid indices.
    d : (K, 3) float64
        The rigid cells' motions, metres.
    cov_honest, cov_formal : (K, 3, 3) float64
        Their block covariances (shrunk, no floor) and formal covariances, m².
    n : (K,) int
        Their correspondences.
    usable : (K,) bool
        Cells allowed in the floor's estimate (converged, not flagged).
    projection : (K, 3) float64
        :func:`rigid_projection` of the unweighted field, metres (NaN: left out).
    fitted : (K,) bool, optional
        Cells with a rigid fit (default: all); the others take the median ``F`` of these.
    rmse : (K,) float64, optional
        The rigid cells' residual RMS, metres: the floor by each cell's surface share
        (without it, alike for every cell).

    Returns
    -------
    weights : (K,) float64 or None
        ``1 / F`` in (0, 1]; None where the floor cannot be estimated (too few cells with
        neighbours, e.g. a sparse airborne survey): no model, no weights.
    floor : CellFloor
        The floor of the cells' residual motions.
    """
    from .icp_blocks import cell_floor, surface_share

    fh = np.diagonal(np.asarray(cov_honest), axis1=1, axis2=2)
    ff = np.diagonal(np.asarray(cov_formal), axis1=1, axis2=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.nanmean(np.where(ff > 0, fh / ff, np.nan), axis=1)
    ratio = np.where(np.isfinite(ratio) & (ratio > 0), ratio, 1.0)
    fitted = np.ones(len(ratio), dtype=bool) if fitted is None else np.asarray(fitted, bool)
    resid = np.asarray(d, dtype=np.float64) - np.asarray(projection, dtype=np.float64)
    resid[~fitted] = np.nan
    sd = np.sqrt(fh)
    ok = np.all(np.isfinite(resid), axis=1) & np.all(np.isfinite(sd) & (sd > 0), axis=1)
    usable = np.asarray(usable, dtype=bool)
    share = None if rmse is None else surface_share(rmse, usable & ok)
    fl = cell_floor(
        np.asarray(row)[ok], np.asarray(col)[ok], resid[ok], sd[ok], np.asarray(n)[ok],
        usable=usable[ok], share=None if share is None else share[ok],
    )  # fmt: skip
    if not np.isfinite(fl.factor):
        log.info("spline data weights: no cell-wide floor (%d cells tested): none", fl.n_cells)
        return None, fl
    f = np.maximum(ratio * fl.scale(n, share), 1.0)
    f[~fitted] = float(np.median(f[fitted])) if fitted.any() else 1.0
    log.info(
        "spline data weights: the rigid cells' floor about the field a %.2f, n_cap %.0f; "
        "F median %.2f (%.2f-%.2f)", fl.factor**2, fl.n_cap, float(np.median(f)),
        float(f.min()), float(f.max()),
    )  # fmt: skip
    return 1.0 / f, fl
