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
diagonal of the normal matrix.

Written here, not taken from a library: the registration libraries at hand (Open3D, py4dgeo,
scipy) offer rigid or per-point motion only, and the B-spline basis is a few lines of numpy.
The normal matrix is sparse (each point touches 16 knots x 3 components); it is assembled
per knot interval with one dense product each and solved with SciPy's sparse LU.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from .errors import InputDataError, InvalidParameterError
from .icp_options import MAD_TO_SIGMA, _Options, _shared_target_inflation, _weights
from .progress import ProgressCallback, report

log = logging.getLogger(__name__)

#: the fit stops when the field's RMS change at the points falls below this share of the
#: residuals' robust spread, or stops falling for STALL_ITERATIONS iterations
CHANGE_FLOOR = 0.02
STALL_ITERATIONS = 3
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


__all__ = ["SplineField", "SplineFit", "fit_spline_field", "bspline_weights"]


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


@dataclass(frozen=True)
class SplineField:
    """A bicubic B-spline displacement field of the horizontal position.

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
    """

    origin_xy: tuple
    spacing_m: float
    n_x: int
    n_y: int
    coefficients: np.ndarray

    def _basis(self, xy: np.ndarray, slopes: bool = False):
        h = self.spacing_m
        u = (xy[:, 0] - self.origin_xy[0]) / h
        v = (xy[:, 1] - self.origin_xy[1]) / h
        iu = np.clip(np.floor(u).astype(np.int64), 0, self.n_x - 1)
        iv = np.clip(np.floor(v).astype(np.int64), 0, self.n_y - 1)
        fu, fv = u - iu, v - iv
        kx = self.n_x + 3
        rows = iv[:, None] + np.arange(4)
        idx = rows[:, :, None] * kx + (iu[:, None] + np.arange(4))[:, None, :]
        bu, bv = bspline_weights(fu), bspline_weights(fv)
        w = (bv[:, :, None] * bu[:, None, :]).reshape(-1, 16)
        if not slopes:
            return idx.reshape(-1, 16), w
        du, dv = _bspline_slopes(fu) / h, _bspline_slopes(fv) / h
        wx = (bv[:, :, None] * du[:, None, :]).reshape(-1, 16)
        wy = (dv[:, :, None] * bu[:, None, :]).reshape(-1, 16)
        return idx.reshape(-1, 16), w, wx, wy

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        """(K, 2) map positions -> (K, 3) displacements, metres."""
        idx, w = self._basis(np.asarray(xy, dtype=np.float64))
        return np.einsum("pk,pkj->pj", w, self.coefficients.reshape(-1, 3)[idx])

    def gradient(self, xy: np.ndarray) -> np.ndarray:
        """(K, 2) map positions -> (K, 3, 3) gradient ``d(d_i)/d(x_j)`` (z column zero)."""
        idx, _, wx, wy = self._basis(np.asarray(xy, dtype=np.float64), slopes=True)
        c = self.coefficients.reshape(-1, 3)[idx]
        out = np.zeros((len(idx), 3, 3))
        out[:, :, 0] = np.einsum("pk,pkj->pj", wx, c)
        out[:, :, 1] = np.einsum("pk,pkj->pj", wy, c)
        return out


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


def _second_differences(kx: int, ky: int):
    """Penalty matrix ``RᵀR`` of the second differences of a (ky, kx) knot grid along x and
    y, sparse (kx ky, kx ky)."""
    import scipy.sparse as sp

    def d2(n):
        return sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(max(n - 2, 0), n))

    r = sp.vstack([sp.kron(sp.identity(ky), d2(kx)), sp.kron(d2(ky), sp.identity(kx))])
    return (r.T @ r).tocsr()


def _assemble(order, bounds, idx16, w16, nrm, v, wt, n_k):
    """Normal matrix (3K, 3K, sparse) and right-hand side (3K,) of the weighted point-to-plane
    residuals, one dense (48, 48) product per knot interval (``order`` sorts the points by
    interval, ``bounds`` delimit them; ``order=None``: already sorted)."""
    import scipy.sparse as sp

    rows, cols, vals = [], [], []
    rhs = np.zeros(3 * n_k)
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
    if not rows:
        return sp.csr_matrix((3 * n_k, 3 * n_k)), rhs
    n = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(3 * n_k, 3 * n_k),
    )
    return n, rhs


def _trace_inv_block(factor, r2, j: int, n_k: int, seed: int = 0) -> float:
    """``tr(A⁻¹[j, j] RᵀR)`` of component ``j`` from ``A``'s sparse LU: exact (``n_k``
    solves) up to TRACE_EXACT_MAX knots, else Hutchinson's estimate with TRACE_PROBES
    Rademacher probes."""
    if n_k <= TRACE_EXACT_MAX:
        rhs = np.zeros((3 * n_k, n_k))
        rhs[j * n_k + np.arange(n_k), np.arange(n_k)] = 1.0
        x = factor.solve(rhs)[j * n_k : (j + 1) * n_k]
        return float(r2.multiply(x).sum())
    rng = np.random.default_rng(seed + j)
    z = rng.choice([-1.0, 1.0], size=(n_k, TRACE_PROBES))
    rhs = np.zeros((3 * n_k, TRACE_PROBES))
    rhs[j * n_k : (j + 1) * n_k] = r2 @ z
    x = factor.solve(rhs)[j * n_k : (j + 1) * n_k]
    return float(np.mean(np.sum(z * x, axis=0)))


def _variance_components(factor, r2, lam_abs, c, wvv: float, n_obs: int) -> np.ndarray:
    """New penalty weights ``sigma0² / sigma_j²`` by variance-component estimation
    (Förstner's iteration, as Helmert's for two groups): the observations' variance from
    their weighted residuals over their redundancy, each component's prior variance of
    second differences from ``c_jᵀ RᵀR c_j`` over the pseudo-observations' redundancy
    ``n_R - lam_j tr(A⁻¹_jj RᵀR)``."""
    n_k = r2.shape[0]
    n_r = float(np.count_nonzero(r2.diagonal() > 0))  # pseudo-observations, about n_k
    traces = np.array([_trace_inv_block(factor, r2, j, n_k) for j in range(3)])
    t = lam_abs * traces  # redundancy the prior gives away per component
    r_obs = max(n_obs - (3 * n_k - float(np.sum(t))), 1.0)
    s0sq = wvv / r_obs
    out = lam_abs.copy()
    for j in range(3):
        cj = c[:, j]
        rough = float(cj @ (r2 @ cj))
        r_j = max(n_r - t[j], 1.0)
        if rough > 0:
            out[j] = s0sq / (rough / r_j)
    log.debug("spline field: variance components -> weights %s", np.array2string(out))
    return out


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
    block_m: Optional[float] = None,
) -> SplineFit:
    """Fit a bicubic B-spline displacement field to two epochs by point-to-plane ICP.

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
    grid : slipmap.core.opencl.nearest.GridTargets, optional
        ``before`` on an OpenCL device: the pairs are found there (the same pairs).
    block_m : float, optional
        Block side (metres) of the block covariance ``SplineFit.cov_blocks``
        (:mod:`slipmap.core.icp_blocks`); None: not computed.

    Returns
    -------
    SplineFit

    Raises
    ------
    InvalidParameterError
        ``spacing_m`` not positive or ``smoothing`` negative.
    InputDataError
        Too few correspondences for the knots.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from .icp_cells import _Matcher

    h = float(spacing_m)
    if not (np.isfinite(h) and h > 0):
        raise InvalidParameterError(f"spline_spacing_m must be > 0, got {spacing_m!r}")
    auto = smoothing is None
    lam = AUTO_START if auto else float(smoothing)
    if not (np.isfinite(lam) and lam >= 0):
        raise InvalidParameterError(f"spline_smoothing must be >= 0, got {smoothing!r}")
    lam_abs = None  # absolute penalty weight per component, set at the first iteration
    a = np.asarray(after, dtype=np.float64)
    rxy = np.asarray(report_xy, dtype=np.float64).reshape(-1, 2)
    if len(rxy) < MIN_SPLINE_CELLS:
        raise SplineCellsError(
            f"{len(rxy)} cell(s) with points, a spline field needs {MIN_SPLINE_CELLS} at least",
            cells=len(rxy),
        )
    lo = np.minimum(a[:, :2].min(axis=0), rxy.min(axis=0)) - 1e-6 * h
    hi = np.maximum(a[:, :2].max(axis=0), rxy.max(axis=0))
    check_spline_size(hi - lo, h)
    n_x, n_y = (int(v) for v in np.maximum(np.ceil((hi - lo) / h), 1))
    kx, ky = n_x + 3, n_y + 3
    n_k = kx * ky
    # start: least-squares fit of the initial field on a 4-per-interval lattice
    gx, gy = np.meshgrid(
        lo[0] + h * np.arange(4 * n_x + 1) / 4, lo[1] + h * np.arange(4 * n_y + 1) / 4
    )
    field = SplineField((float(lo[0]), float(lo[1])), h, n_x, n_y, np.zeros((ky, kx, 3)))
    gxy = np.column_stack([gx.ravel(), gy.ravel()])
    gi, gw = field._basis(gxy)
    bmat = sp.csr_matrix(
        (gw.ravel(), gi.ravel(), np.arange(0, gi.size + 1, 16)), shape=(len(gxy), n_k)
    )
    f0 = np.asarray(initial(gxy), dtype=np.float64).reshape(-1, 3)
    f0 = np.where(np.isfinite(f0), f0, 0.0)
    r2 = _second_differences(kx, ky)
    lhs0 = (bmat.T @ bmat + 1e-6 * r2 + 1e-9 * sp.identity(n_k)).tocsc()
    c = splu(lhs0).solve(np.asarray(bmat.T @ f0))  # (K, 3)

    idx16, w16 = field._basis(a[:, :2])
    # the points sorted by knot interval, so that each interval's points are one slice
    cell_of = (idx16[:, 0] // kx) * n_x + idx16[:, 0] % kx
    perm = np.argsort(cell_of, kind="stable")
    a, idx16, w16 = a[perm], idx16[perm], w16[perm]
    seg_sorted = None if report_seg is None else np.asarray(report_seg)[perm]
    bounds = np.searchsorted(cell_of[perm], np.arange(n_x * n_y + 1))
    converged, it = False, 0
    m_pts = len(before)
    factor = None
    every = np.arange(len(a))
    # nearest targets re-queried only for points that may have changed pair
    if grid is None:
        matcher = _Matcher(before, tree, normals, gate_m, None, np.zeros((1, 3)), len(a))
        nearest = matcher._nearest
    else:
        from .opencl.nearest import CellNearest

        matcher = CellNearest(before, grid, normals, gate_m, None, np.zeros((1, 3)), len(a))
        one_cell = np.zeros(len(a), dtype=np.int64)

        def nearest(q, gi):
            j = matcher.nearest(q, one_cell, gi)
            return np.where(j < 0, m_pts, j)

    def pairs(q):
        j = nearest(q, every)
        ok = j < m_pts
        nrm = np.zeros((len(a), 3))
        nn = normals(j[ok])
        good = np.all(np.isfinite(nn), axis=1)
        ok[ok] = good
        nrm[ok] = nn[good]
        v = np.zeros(len(a))
        v[ok] = np.einsum("ij,ij->i", nrm[ok], q[ok] - before[j[ok]])
        return ok, nrm, v, j

    best, since_best = np.inf, 0
    for it in range(1, opts.max_iterations + 1):
        report(progress, (it - 1) / opts.max_iterations, f"spline field: iteration {it}")
        q = a - np.einsum("pk,pkj->pj", w16, c[idx16])
        ok, nrm, v, _ = pairs(q)
        if np.count_nonzero(ok) < 3 * 16:
            raise InputDataError(
                f"spline field: only {int(np.count_nonzero(ok))} correspondences within "
                f"{gate_m:g} m; use a larger spline_spacing_m or check the epochs' overlap"
            )
        keep, wv, _ = _weights(v[ok], opts)
        wt = np.zeros(len(a))
        wt[ok] = np.where(keep, wv, 0.0)
        nmat, rhs = _assemble(None, bounds, idx16, w16, nrm, v, wt, n_k)
        if lam_abs is None:
            dg = nmat.diagonal()
            scale = float(np.median(dg[dg > 0])) if np.any(dg > 0) else 1.0
            lam_abs = np.full(3, lam * scale)
            ridge = sp.identity(3 * n_k, format="csr") * (1e-12 * scale)
        penalty = sp.block_diag([w * r2 for w in lam_abs], format="csr") + ridge
        cvec = c.T.reshape(-1)  # component-major
        factor = splu((nmat + penalty).tocsc())
        step = factor.solve(rhs - penalty @ cvec)
        dc = step.reshape(3, n_k).T
        c = c + dc
        if auto:
            new = _variance_components(
                factor, r2, lam_abs, c, float(np.sum(wt * v * v)), int(np.count_nonzero(wt))
            )
            new = np.clip(new, AUTO_RANGE[0] * scale, AUTO_RANGE[1] * scale)
            auto = bool(np.any(np.abs(new / lam_abs - 1.0) > AUTO_SETTLED))
            lam_abs = new
        du = np.einsum("pk,pkj->pj", w16, dc[idx16])
        rms_du = float(np.sqrt(np.mean(np.sum(du[ok] ** 2, axis=1))))
        log.debug("spline field: iteration %d, RMS change %.2e m", it, rms_du)
        # the nearest-neighbour pairs flip as the field moves and the steps shrink slowly
        # (by ~0.8 an iteration on lone-star) towards a jitter: stop at CHANGE_FLOOR of the
        # residuals' robust spread (or at tolerance_m), or when the change stalls
        floor = CHANGE_FLOOR * MAD_TO_SIGMA * float(np.median(np.abs(v[ok])))
        best, since_best = (rms_du, 0) if rms_du < best else (best, since_best + 1)
        if rms_du < max(opts.tolerance_m, floor) or since_best >= STALL_ITERATIONS:
            converged = True
            break
    # final residuals, sigma0 and the report
    ok, nrm, v, tid = pairs(a - np.einsum("pk,pkj->pj", w16, c[idx16]))
    keep, wv, dpsi = _weights(v[ok], opts)
    psi = np.where(keep, wv * v[ok], 0.0)
    used = int(np.count_nonzero(keep & (wv > 0)))
    data_knots = np.unique(idx16[ok].reshape(-1)).size
    dof = max(used - 3 * data_knots, 1)
    mean_dpsi = float(np.mean(np.where(keep, dpsi, 0.0))) if keep.size else 1.0
    # points sharing a target point share its error, as in the cells' sigma0
    ss = float(np.sum(psi * psi))
    one = np.zeros(psi.size, dtype=np.int64)
    inflation = float(_shared_target_inflation(psi, keep, one, tid[ok], np.array([ss]))[0])
    s0sq = ss / dof / max(mean_dpsi, 1e-12) ** 2 * inflation
    field = SplineField(field.origin_xy, h, n_x, n_y, c.reshape(ky, kx, 3))
    ridx, rw, rwx, rwy = field._basis(rxy, slopes=True)
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
    chunk = 64
    for s0 in range(0, k, chunk):
        part = slice(s0, min(s0 + chunk, k))
        kk = part.stop - part.start
        rows_g = sp.csr_matrix(
            (g[part].reshape(kk * 9, 48).ravel(), np.repeat(cols[part], 9, axis=0).ravel(),
             np.arange(0, kk * 9 * 48 + 1, 48)),
            shape=(kk * 9, 3 * n_k),
        )  # fmt: skip
        sol = factor.solve(np.asarray(rows_g.T.todense()))  # (3K, kk*9)
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
    if block_m is not None:  # the residuals' spatial correlation (issue #29)
        from .icp_blocks import spline_block_covariance

        psi_all = np.zeros(len(a))
        psi_all[ok] = psi
        kw = np.where(keep, wv, 0.0)
        c_scale = float(np.mean(kw)) / max(mean_dpsi, 1e-12) ** 2 * used / dof
        cov_blocks, n_blocks = spline_block_covariance(
            xy=a[:, :2], psi=psi_all, nrm=nrm, idx16=idx16, w16=w16,
            rows=g.reshape(k, 9, 48), cols=cols, factor=factor, penalty=penalty, s0sq=s0sq,
            scale=c_scale, block_m=block_m, seg=seg_sorted,
        )  # fmt: skip
    rmse = np.full(k, np.nan)
    n_used = np.zeros(k, dtype=np.int64)
    if seg_sorted is not None:
        seg = seg_sorted
        good = ok.copy()
        good[ok] = keep & (wv > 0)
        s = seg[good]
        vs = v[good]
        inside = s >= 0
        n_used = np.bincount(s[inside], minlength=k).astype(np.int64)
        ss = np.bincount(s[inside], weights=vs[inside] ** 2, minlength=k)
        rmse = np.where(n_used > 0, np.sqrt(ss / np.maximum(n_used, 1)), np.nan)
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
    )
