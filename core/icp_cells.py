"""Batched point-to-plane fits of many windowed-ICP cells at once (issue #18).

:func:`fit_cells` runs the same Gauss-Newton point-to-plane iterations as
:func:`slipmap.core.icp._icp_engine` (robust weights, step damping, the two convergence tests,
the final covariance with the shared-target inflation), but for every cell of a field in one
pass: one KD-tree query of all active cells' points per iteration, normal matrices summed per
cell with ``np.bincount`` and the small (K, P, P) systems solved together with
``np.linalg.eigh``. The per-cell loop in :func:`slipmap.core.icp.windowed_icp`
(``engine="per_cell"``) is the slow obvious reference it is tested against.

Two cell models:

* ``"rigid"`` (6 parameters, rotation vector ``r`` and translation ``t`` about the cell
  centre): ``T(s) = R s + t``, the study's model.
* ``"affine"`` (12 parameters, a 3 x 3 matrix ``G`` and ``t``): ``T(s) = (I + G) s + t``. It
  follows a linearly straining cell (stretch, shear, rotation), gives the cell's displacement
  gradient ``-G`` (hence its strain), and its value at the cell centre is not biased by an
  uneven spread of the points over the cell. ``G`` is updated additively (the residuals are
  linear in ``G`` and ``t``).

``s`` are source (epoch 2) coordinates centred on the cell's reference point, so the ground
motion at that point is ``-t`` for both models and its covariance the ``t`` block.

Everything is numpy + ``scipy.spatial.cKDTree`` (the pairs optionally from compiled kernels:
:mod:`slipmap.core.icp_numba`, :mod:`slipmap.core.opencl.nearest`); no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .icp_blocks import block_meats, sandwich
from .icp_options import (
    EIG_RTOL,
    MAD_TO_SIGMA,
    NULL_RTOL,
    _Options,
    _robust_weights,
    _shared_target_inflation,
)
from .progress import report
from .rotation import left_jacobian, rotation_matrix, rotation_vector

MODELS = ("rigid", "affine")
_MIN_PAIRS = 7


@dataclass(frozen=True)
class CellFits:
    """Result of :func:`fit_cells` for K cells (P = 6 rigid, 12 affine parameters).

    Attributes
    ----------
    ok : (K,) bool
        The cell was fitted (enough correspondences with normals).
    linear : (K, 3, 3) float64
        Linear part of ``T``: ``R`` (rigid) or ``I + G`` (affine).
    t : (K, 3) float64
        Translation of ``T`` about the cell's reference point, metres.
    params : (K, P) float64
        ``(r, t)`` (rigid) or ``(G row-major, t)`` (affine).
    covariance : (K, P, P) float64
        Parameter covariance (formal); ``inf`` variance and NaN covariances for parameters
        the geometry leaves undetermined.
    rmse, sigma0 : (K,) float64
        RMS residual of the used pairs and a-posteriori sigma of unit weight, metres.
    n : (K,) int64
        Correspondences used.
    iterations : (K,) int64
    converged : (K,) bool
    block_covariance : (K, L, P, P) float64 or None
        Cluster-robust covariance with sub-cell blocks of each size of
        :data:`slipmap.core.icp_blocks.BLOCK_LADDER_M` as clusters (the residuals' spatial
        correlation; NaN where a cell has fewer than 2 blocks), see
        :mod:`slipmap.core.icp_blocks`.
    n_blocks : (K, L) int64 or None
        Blocks with used points per cell and block size.
    """

    ok: np.ndarray
    linear: np.ndarray
    t: np.ndarray
    params: np.ndarray
    covariance: np.ndarray
    rmse: np.ndarray
    sigma0: np.ndarray
    n: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    block_covariance: Optional[np.ndarray] = None
    n_blocks: Optional[np.ndarray] = None

    @property
    def gradient(self) -> np.ndarray:
        """(K, 3, 3) gradient of the ground motion ``d(p) = p - T(p)``: ``I - linear``."""
        return np.eye(3)[None] - self.linear


def n_params(model: str) -> int:
    """Parameters of a cell model: 6 (rigid) or 12 (affine)."""
    return 6 if model == "rigid" else 12


def _seg_sum(values: np.ndarray, seg: np.ndarray, k: int) -> np.ndarray:
    """Per-segment sums of (P,) or (P, q) values -> (K,) or (K, q)."""
    if values.ndim == 1:
        return np.bincount(seg, weights=values, minlength=k)
    return np.stack(
        [np.bincount(seg, weights=values[:, j], minlength=k) for j in range(values.shape[1])],
        axis=1,
    )


_LOOP_MIN_MEAN = 64  # mean points per segment from which a loop over segments beats bincount
_BLAS_ROWS = 8192  # rows per matrix product of the normal equations


def _blocks(seg: np.ndarray, k: int):
    """``(start, stop)`` per segment of a sorted ``seg`` (K, 2), and whether a Python loop
    over the non-empty segments is the faster way (few, large segments: one BLAS product or
    sort per segment instead of a pass over all points per output entry)."""
    counts = np.bincount(seg, minlength=k)
    stop = np.cumsum(counts)
    bounds = np.stack([stop - counts, stop], axis=1)
    nonempty = int(np.count_nonzero(counts))
    return bounds, counts, len(seg) >= _LOOP_MIN_MEAN * max(nonempty, 1)


def _transform(lin: np.ndarray, s: np.ndarray, seg: np.ndarray, k: int) -> np.ndarray:
    """``lin[seg] @ s`` per point: (K, 3, 3) linear parts applied to (P, 3) points of the
    sorted segments ``seg`` (per segment one product when the segments are large)."""
    bounds, counts, loop = _blocks(seg, k)
    if not loop:
        return np.einsum("pij,pj->pi", lin[seg], s)
    out = np.empty_like(s)
    for i in np.flatnonzero(counts):
        a0, a1 = bounds[i]
        out[a0:a1] = s[a0:a1] @ lin[i].T
    return out


def _normal_matrices(A: np.ndarray, w: np.ndarray, v: np.ndarray, seg: np.ndarray, k: int):
    """``N_k = sum w a a'`` and ``b_k = -sum w a v`` per segment, (K, P, P) and (K, P).

    ``seg`` is sorted. Few large segments: one matrix product per segment; many small ones:
    one weighted ``bincount`` per entry (the reference; they agree to rounding)."""
    p = A.shape[1]
    Aw = A * w[:, None]
    bounds, counts, loop = _blocks(seg, k)
    if loop:
        N = np.zeros((k, p, p))
        b = np.zeros((k, p))
        for i in np.flatnonzero(counts):
            # in slices: a thin product over tens of thousands of rows makes OpenBLAS start
            # its threads, 4-10x slower than one thread on a small machine (measured)
            for a0 in range(bounds[i, 0], bounds[i, 1], _BLAS_ROWS):
                a1 = min(a0 + _BLAS_ROWS, bounds[i, 1])
                N[i] += Aw[a0:a1].T @ A[a0:a1]
                b[i] -= Aw[a0:a1].T @ v[a0:a1]
        return N, b
    N = np.zeros((k, p, p))
    for i in range(p):
        for j in range(i, p):
            s = np.bincount(seg, weights=Aw[:, i] * A[:, j], minlength=k)
            N[:, i, j] = s
            N[:, j, i] = s
    b = -_seg_sum(Aw * v[:, None], seg, k)
    return N, b


def _solve_scaled_batch(N: np.ndarray, b: np.ndarray, length_m: np.ndarray, n_lin: int):
    """Batched :func:`slipmap.core.icp._solve_scaled`: the first ``n_lin`` unknowns (rotations
    or gradient entries) are scaled by ``length_m`` (K,), the rest (translations) are metres;
    eigenvalues below ``EIG_RTOL`` of the largest are truncated.

    Returns the steps (K, P), the (pseudo-)inverses (K, P, P), the condition numbers (K,) and
    a (K, P) mask of the parameters that touch an undetermined direction.
    """
    k, p = b.shape
    tr = np.maximum(np.trace(N, axis1=1, axis2=2), 1e-300)
    dg = np.ones((k, p))
    dg[:, :n_lin] = length_m[:, None]
    dg = dg * np.sqrt(tr)[:, None]
    Ns = N / (dg[:, :, None] * dg[:, None, :])
    lam, V = np.linalg.eigh(Ns)
    top = np.maximum(lam[:, -1], 1e-300)
    good = lam > EIG_RTOL * top[:, None]
    inv_l = np.where(good, 1.0 / np.where(good, lam, 1.0), 0.0)
    x = np.einsum("kij,kj->ki", V, inv_l * np.einsum("kji,kj->ki", V, b / dg)) / dg
    cond = np.where(lam[:, 0] > 0, top / np.where(lam[:, 0] > 0, lam[:, 0], 1.0), np.inf)
    Ninv = np.einsum("kij,kj,klj->kil", V, inv_l, V) / (dg[:, :, None] * dg[:, None, :])
    U = V / dg[:, :, None]
    U = U / np.linalg.norm(U, axis=1, keepdims=True)
    undet = np.any((np.abs(U) > NULL_RTOL) & ~good[:, None, :], axis=2)
    return x, Ninv, cond, undet


def mark_undetermined(cov: np.ndarray, undet: np.ndarray) -> np.ndarray:
    """``cov`` (K, q, q) with ``inf`` variances and NaN covariances where ``undet`` (K, q)."""
    out = cov.copy()
    pair = undet[:, :, None] | undet[:, None, :]
    out[pair] = np.nan
    i = np.arange(out.shape[-1])
    out[:, i, i] = np.where(undet, np.inf, out[:, i, i])
    return out


def _seg_weights(v: np.ndarray, seg: np.ndarray, k: int, opts: _Options):
    """:func:`slipmap.core.icp_options._weights` per segment: (keep, w, psi') of (P,) residuals
    (``seg`` sorted; :func:`seg_scales`)."""
    thr, scale = seg_scales(v, seg, k, opts)
    keep = np.abs(v) <= thr[seg]
    if opts.robust is None:
        w = keep.astype(np.float64)
        return keep, w, w
    w, dpsi = _robust_weights(v, scale[seg], keep, opts.robust)
    return keep, w, dpsi


def seg_scales(v: np.ndarray, seg: np.ndarray, k: int, opts: _Options):
    """Each segment's trimming threshold and robust scale, as
    :func:`slipmap.core.icp_options._weights` finds them from the segment's residuals alone.

    The per-segment quantile (trimming) and median (robust scale) are order statistics of |v|
    within each segment of the sorted ``seg``; they equal numpy's ``quantile`` (linear) and
    ``median`` of each segment. Many small segments: one ``lexsort`` of all; few large ones:
    ``np.partition`` per segment (linear time, the same order statistics).

    Returns
    -------
    threshold : (K,) float64
        Largest kept ``|v|`` of each segment (inf: no trimming, or 20 residuals or fewer).
    scale : (K,) float64
        ``MAD_TO_SIGMA`` times the median ``|v|`` of the kept, at least 1e-12 (NaN without
        robust weights).
    """
    a = np.abs(v)
    bounds, counts, loop = _blocks(seg, k)
    trimming = opts.trim_fraction > 0
    # positions of the trimming quantile in each segment's sorted |v|
    pos = (counts - 1) * (1.0 - opts.trim_fraction)
    qlo = np.floor(pos).astype(np.int64)
    qhi = np.minimum(qlo + 1, np.maximum(counts - 1, 0))
    q = np.full(k, np.inf)
    ml, mh = np.zeros(k), np.zeros(k)
    if loop:  # few large segments: partitions per segment
        for i in np.flatnonzero(counts):
            a0, a1 = bounds[i]
            x = a[a0:a1]
            nk = a1 - a0
            if trimming:
                x = np.partition(x, [qlo[i], qhi[i]])
                q[i] = x[qlo[i]] + (x[qhi[i]] - x[qlo[i]]) * (pos[i] - qlo[i])
                if nk > 20:
                    nk = int(np.count_nonzero(x <= q[i]))
            if opts.robust is not None:  # median of the kept (the nk smallest)
                lo, hi = max((nk - 1) // 2, 0), max(nk // 2, 0)
                x = np.partition(x, [lo, hi])
                ml[i], mh[i] = x[lo], x[hi]
    else:
        sa = a[np.lexsort((a, seg))]
        starts = bounds[:, 0]
        last = max(sa.size - 1, 0)
        if trimming:
            ql = sa[np.minimum(starts + qlo, last)]
            qh = sa[np.minimum(starts + qhi, last)]
            q = ql + (qh - ql) * (pos - qlo)
    thr = np.where(trimming & (counts > 20), q, np.inf)
    if opts.robust is None:
        return thr, np.full(k, np.nan)
    if not loop:  # median of |v| over the kept residuals (kept = the smallest ones)
        keep = a <= thr[seg]
        nk = np.bincount(seg, weights=keep.astype(np.float64), minlength=k).astype(np.int64)
        lo = np.maximum((nk - 1) // 2, 0)
        hi = np.maximum(nk // 2, 0)
        ml = sa[np.minimum(starts + lo, last)]
        mh = sa[np.minimum(starts + hi, last)]
    return thr, np.maximum(MAD_TO_SIGMA * 0.5 * (ml + mh), 1e-12)


def _jacobian(model: str, q: np.ndarray, s: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Rows d v / d (step) of point-to-plane residuals: left rotation and translation
    (rigid), or ``G`` row-major and translation (affine)."""
    if model == "rigid":  # [q x n, n], the cross product by columns (np.cross: 2x slower)
        A = np.empty((len(q), 6))
        A[:, 0] = q[:, 1] * n[:, 2] - q[:, 2] * n[:, 1]
        A[:, 1] = q[:, 2] * n[:, 0] - q[:, 0] * n[:, 2]
        A[:, 2] = q[:, 0] * n[:, 1] - q[:, 1] * n[:, 0]
        A[:, 3:] = n
        return A
    return np.concatenate([(n[:, :, None] * s[:, None, :]).reshape(-1, 9), n], axis=1)


class _Matcher:
    """Nearest before-point of each moved source point within the gate and its cell's box.

    Each source point remembers where it was last queried and its ``CANDIDATES`` nearest
    targets there, at distances ``d1 <= d2 <= ... <= dc``. When it has moved by less than
    ``(dc - d1) / 2`` since, its nearest target is one of them (triangle inequality: the old
    nearest is within ``d1 + move``, every other target beyond ``dc - move``) and is found
    among them by direct distances; by less than ``(d2 - d1) / 2``, it is still the first.
    Only the other points are queried again. The pairs are
    exactly those of a fresh query (up to ties), at a fraction of the tree queries: with four
    candidates the margin ``dc - d1`` is several point spacings, where ``d2 - d1`` (two) is
    often nearly zero for a point between two targets (lone-star lobe: 5x fewer queries).
    """

    PARALLEL_MIN = 20_000  # smaller queries run on one thread (thread start-up dominates)
    CANDIDATES = 4

    def __init__(self, before, tree, normals, gate, boxes, centres, n_points):
        self.before, self.tree, self.normals = before, tree, normals
        self.gate, self.boxes, self.centres = gate, boxes, centres
        self.M = len(before)
        self.c = min(self.CANDIDATES, max(self.M, 1))
        self.last = np.full((n_points, 3), np.nan)
        self.cand = np.full((n_points, self.c), self.M, dtype=np.int64)
        # (d2 - d1) / 2 and (dc - d1) / 2 at the last query (-inf: query again)
        self.margin1 = np.full(n_points, -np.inf)
        self.marginc = np.full(n_points, -np.inf)
        self.queried = 0
        # the target each point was last paired with, whether it is usable, its normal
        self.jc = np.full(n_points, -1, dtype=np.int64)
        self.okc = np.zeros(n_points, dtype=bool)
        self.nc = np.full((n_points, 3), np.nan)

    def _nearest(self, world: np.ndarray, gi: np.ndarray):
        with np.errstate(invalid="ignore"):  # never queried: NaN, stale
            move2 = np.sum((world - self.last[gi]) ** 2, axis=1)
            m1, mc = self.margin1[gi], self.marginc[gi]
            # nearest unchanged (first candidate); among the candidates; query again
            first = (move2 < m1 * m1) & (m1 > 0)
            among = ~first & (move2 < mc * mc) & (mc > 0)
        stale = ~(first | among)
        if stale.any():
            w = world[stale]
            workers = -1 if len(w) >= self.PARALLEL_MIN else 1
            dist, jj = self.tree.query(w, k=self.c, workers=workers)
            dist = np.asarray(dist).reshape(len(w), self.c)
            jj = np.asarray(jj).reshape(len(w), self.c)
            g = gi[stale]
            self.last[g], self.cand[g] = w, jj
            with np.errstate(invalid="ignore"):  # inf - inf: fewer targets than candidates
                self.margin1[g] = np.nan_to_num(0.5 * (dist[:, 1] - dist[:, 0]), nan=-np.inf)
                self.marginc[g] = np.nan_to_num(0.5 * (dist[:, -1] - dist[:, 0]), nan=-np.inf)
            self.queried += int(stale.sum())
        j = self.cand[gi, 0]
        if among.any():
            cand = self.cand[gi[among]]
            tp = self.before[np.minimum(cand, self.M - 1)]
            d2 = np.sum((tp - world[among, None, :]) ** 2, axis=2)
            d2[cand >= self.M] = np.inf
            j[among] = cand[np.arange(len(cand)), np.argmin(d2, axis=1)]
        if np.isfinite(self.gate):  # within the gate: the distance now
            dnow2 = np.sum((world - self.before[np.minimum(j, self.M - 1)]) ** 2, axis=1)
            j = np.where(dnow2 <= self.gate * self.gate, j, self.M)
        return j

    def __call__(self, q: np.ndarray, seg: np.ndarray, gi: np.ndarray):
        """q (P', 3) centred per cell, their cells and global point indices -> ok (P',),
        target (J, 3) centred, normals (J, 3), target ids (J,).

        A source point's cell (and box) never changes, so whether its target is usable (in
        the box, with a normal) is decided once per new target and remembered."""
        world = q + self.centres[seg]
        j = self._nearest(world, gi)
        new = j != self.jc[gi]
        if new.any():
            g, jn = gi[new], j[new]
            okn = jn < self.M
            jv = jn[okn]
            if self.boxes is not None:
                tp = self.before[jv]
                bx = self.boxes[seg[new][okn]]
                okn[okn] = (
                    (tp[:, 0] >= bx[:, 0])
                    & (tp[:, 0] <= bx[:, 1])
                    & (tp[:, 1] >= bx[:, 2])
                    & (tp[:, 1] <= bx[:, 3])
                )
            nrm = np.full((len(jn), 3), np.nan)
            nrm[okn] = self.normals(jn[okn])
            okn &= np.all(np.isfinite(nrm), axis=1)
            self.jc[g], self.okc[g], self.nc[g] = jn, okn, nrm
        ok = self.okc[gi]
        jj = j[ok]
        return ok, self.before[jj] - self.centres[seg[ok]], self.nc[gi[ok]], jj


def fit_cells(
    src: np.ndarray,
    seg: np.ndarray,
    centres: np.ndarray,
    *,
    before: np.ndarray,
    tree,
    normals,
    boxes: Optional[np.ndarray],
    gate: float,
    opts: _Options,
    model: str = "rigid",
    t_init: Optional[np.ndarray] = None,
    progress=None,
    grid=None,
) -> CellFits:
    """Point-to-plane ICP of K cells at once.

    Parameters
    ----------
    src : (P, 3) float64
        Source (epoch 2) points, each minus its cell's reference point, metres; sorted by
        ``seg``.
    seg : (P,) int64
        Cell of each point, 0 .. K-1, non-decreasing.
    centres : (K, 3) float64
        Reference points of the cells (metres, map coordinates).
    before : (M, 3) float64
        Target (epoch 1) points, metres.
    tree
        Nearest-neighbour structure with ``query(xyz, distance_upper_bound, workers)`` in map
        coordinates over ``before``.
    normals : callable
        ``normals(ids (J,)) -> (J, 3)`` unit normals of target points (NaN: unusable).
    boxes : (K, 4) float64 or None
        ``(xmin, xmax, ymin, ymax)`` of the target points a cell may use, metres.
    gate : float
        Largest point-to-point distance of a pair, metres (inf: none).
    opts
        The ICP options (iterations, tolerances, robust weights, trimming).
    model : {"rigid", "affine"}
    t_init : (K, 3) float64, optional
        Starting translations (minus the expected ground motion), metres.
    progress : callable, optional
        ``progress(fraction, message)`` once per iteration; may raise CancelledError.
    grid : slipmap.core.icp_numba.NumbaTargets or slipmap.core.opencl.nearest.GridTargets, optional
        ``before`` for compiled kernels (on the CPU through Numba, or on an OpenCL device):
        the pairs are found there (``grid.matcher``, the same pairs up to exact ties).

    Returns
    -------
    CellFits
    """
    k = len(centres)
    p = n_params(model)
    n_lin = p - 3
    lin = np.repeat(np.eye(3)[None], k, axis=0)
    t = np.zeros((k, 3)) if t_init is None else np.array(t_init, dtype=np.float64).reshape(k, 3)
    active = np.ones(k, dtype=bool)
    failed = np.zeros(k, dtype=bool)
    converged = np.zeros(k, dtype=bool)
    iters = np.zeros(k, dtype=np.int64)
    factor = np.ones(k)
    prev = np.zeros((k, p))
    has_prev = np.zeros(k, dtype=bool)
    if grid is None:
        match = _Matcher(before, tree, normals, gate, boxes, centres, len(src))
    else:  # compiled (Numba) or OpenCL kernels
        match = grid.matcher(before, normals, gate, boxes, centres, len(src))
    # the kernels' normal equations where they have them (numpy's are the reference)
    normal_eqs = getattr(match, "normal_matrices", _normal_matrices)
    # rigid cells with a normal cache: each iteration's rows come from the kernels
    fused = grid is not None and model == "rigid" and hasattr(normals, "ensure")
    if fused:
        match.load_sources(src, seg)
    counts_all = np.bincount(seg, minlength=k)
    every = np.arange(len(src))
    active &= counts_all >= _MIN_PAIRS
    failed |= counts_all < _MIN_PAIRS
    for it in range(1, opts.max_iterations + 1):
        if not active.any():
            break
        report(
            progress,
            (it - 1) / opts.max_iterations,
            f"ICP iteration {it}: {int(active.sum())} of {k} cells",
        )
        if active.all():  # no gathers while every cell iterates
            pm, sg = every, seg
        else:
            pm = np.flatnonzero(active[seg])
            sg = seg[pm]
        if fused:  # pairs, residuals and Jacobian rows on the device
            ok, v, A, qq = match.step(lin, t, pm)
            sg = sg[ok]
        else:
            s = src if pm is every else src[pm]
            q = _transform(lin, s, sg, k) + t[sg]
            ok, m, nrm, _ = match(q, sg, pm)
            q, sg = q[ok], sg[ok]
            v = np.einsum("ij,ij->i", nrm, q - m)
            A = _jacobian(model, q, s[ok] if model != "rigid" else None, nrm)
            qq = np.einsum("ij,ij->i", q, q)
        cnt = np.bincount(sg, minlength=k)
        few = active & (cnt < _MIN_PAIRS)
        if few.any():
            failed |= few
            active &= ~few
            keep_pts = active[sg]
            sg, v, A, qq = sg[keep_pts], v[keep_pts], A[keep_pts], qq[keep_pts]
            cnt = np.bincount(sg, minlength=k)
        ia = np.flatnonzero(active)
        if ia.size == 0:
            break
        iters[ia] = it
        keep, w, _ = _seg_weights(v, sg, k, opts)
        wk = np.where(keep, w, 0.0)
        N, b = normal_eqs(A, wk, v, sg, k)
        radius = np.sqrt(_seg_sum(qq, sg, k) / np.maximum(cnt, 1))
        radius = np.maximum(radius, 1e-9)
        x, Ninv, _, undet = _solve_scaled_batch(N[ia], b[ia], radius[ia], n_lin)
        # step damping (slipmap.core.icp._Damping), per cell
        sc = x.copy()
        sc[:, :n_lin] *= radius[ia, None]
        pv = prev[ia]
        denom = np.linalg.norm(sc, axis=1) * np.linalg.norm(pv, axis=1)
        cosine = np.where(
            denom > 0, np.einsum("ij,ij->i", sc, pv) / np.where(denom > 0, denom, 1), 0
        )
        halve = has_prev[ia] & (cosine < -0.5)
        factor[ia] = np.where(halve, factor[ia] * 0.5, factor[ia])
        prev[ia] = sc * factor[ia, None]
        has_prev[ia] = True
        x = x * factor[ia, None]
        if model == "rigid":
            dR = rotation_matrix(x[:, :3]).reshape(-1, 3, 3)
            lin[ia] = dR @ lin[ia]
            t[ia] = np.einsum("kij,kj->ki", dR, t[ia]) + x[:, 3:]
        else:
            lin[ia] = lin[ia] + x[:, :9].reshape(-1, 3, 3)
            t[ia] = t[ia] + x[:, 9:]
        done = (np.linalg.norm(x[:, :n_lin], axis=1) < opts.tolerance_rad) & (
            np.linalg.norm(x[:, n_lin:], axis=1) < opts.tolerance_m
        )
        if opts.tolerance_sigma > 0 and it > 2:
            wv2 = _seg_sum(wk * v * v, sg, k)[ia]
            used = np.bincount(sg, weights=(keep & (w > 0)).astype(np.float64), minlength=k)[ia]
            s0sq = wv2 / np.maximum(used - p, 1)
            sig = np.sqrt(np.maximum(s0sq[:, None] * np.diagonal(Ninv, axis1=1, axis2=2), 0.0))
            small = np.all(np.abs(x) <= opts.tolerance_sigma * sig, axis=1) & ~undet.any(axis=1)
            done |= ~done & small
        converged[ia[done]] = True
        active[ia[done]] = False
    return _final(src, seg, centres, lin, t, match, opts, model, failed, iters, converged)


def _final(src, seg, centres, lin, t, match, opts, model, failed, iters, converged) -> CellFits:
    """Correspondences, residuals and covariance at the final transforms (as
    :func:`slipmap.core.icp._final_fit`, per cell)."""
    k = len(centres)
    p = n_params(model)
    n_lin = p - 3
    use = ~failed
    pm = np.flatnonzero(use[seg])
    s, sg = src[pm], seg[pm]
    a = _transform(lin, s, sg, k)
    ok, m, nrm, tid = match(a + t[sg], sg, pm)
    a, s, sg = a[ok], s[ok], sg[ok]
    v = np.einsum("ij,ij->i", nrm, a + t[sg] - m)
    keep, w, dpsi = _seg_weights(v, sg, k, opts)
    if model == "rigid":
        rv = rotation_vector(lin).reshape(k, 3) if k else np.zeros((0, 3))
        jl = np.stack([left_jacobian(r) for r in rv]) if k else np.zeros((0, 3, 3))
        A = np.concatenate([np.einsum("pi,pij->pj", np.cross(a, nrm), jl[sg]), nrm], axis=1)
        params = np.concatenate([rv, t], axis=1)
    else:
        A = _jacobian(model, a, s, nrm)
        params = np.concatenate([(lin - np.eye(3)).reshape(k, 9), t], axis=1)
    kf = keep.astype(np.float64)
    nk = np.bincount(sg, weights=kf, minlength=k)
    used_mask = keep & (w > 0)
    used = np.bincount(sg, weights=used_mask.astype(np.float64), minlength=k)
    psi = np.where(keep, w * v, 0.0)
    ss = np.bincount(sg, weights=psi * psi, minlength=k)
    mean_dpsi = np.bincount(sg, weights=np.where(keep, dpsi, 0.0), minlength=k) / np.maximum(nk, 1)
    inflation = _shared_target_inflation(psi, keep, sg, tid, ss)
    dof = np.maximum(nk - p, 1)
    good = use & (used >= _MIN_PAIRS) & (mean_dpsi > 0)
    s0sq = ss / dof / np.where(mean_dpsi > 0, mean_dpsi, 1.0) ** 2 * inflation
    cnt = np.bincount(sg, minlength=k)
    radius = np.maximum(
        np.sqrt(_seg_sum(np.einsum("ij,ij->i", a, a), sg, k) / np.maximum(cnt, 1)), 1e-9
    )
    N, _ = _normal_matrices(A, kf, np.zeros(len(v)), sg, k)
    gi = np.flatnonzero(good)
    cov = np.full((k, p, p), np.nan)
    ninv = np.full((k, p, p), np.nan)
    if gi.size:
        _, Ninv, _, undet = _solve_scaled_batch(N[gi], np.zeros((gi.size, p)), radius[gi], n_lin)
        cov[gi] = mark_undetermined(s0sq[gi, None, None] * Ninv, undet)
        ninv[gi] = Ninv
    # the residuals' spatial correlation: block sums of the scores (icp_blocks)
    meats, n_blocks = block_meats(A, psi, sg, s[:, :2] + centres[sg, :2], k)
    scale = nk / dof / np.where(mean_dpsi > 0, mean_dpsi, 1.0) ** 2
    bcov = sandwich(ninv, meats, n_blocks, scale)
    vv = np.bincount(sg, weights=np.where(used_mask, v * v, 0.0), minlength=k)
    rmse = np.sqrt(vv / np.maximum(used, 1))
    return CellFits(
        ok=good,
        linear=lin,
        t=t,
        params=params,
        covariance=cov,
        rmse=np.where(good, rmse, np.nan),
        sigma0=np.where(good, np.sqrt(s0sq), np.nan),
        n=np.where(good, used, 0).astype(np.int64),
        iterations=iters,
        converged=converged & good,
        block_covariance=bcov,
        n_blocks=n_blocks,
    )


def ground_rotation(fits: CellFits, model: str):
    """Rotation vector of the ground motion per cell and its 1-sigma, radians, (K, 3) each.

    Rigid: minus the transform's rotation vector. Affine: the antisymmetric part of the
    motion's gradient ``-G``, ``w = (G_zy - G_yz, G_xz - G_zx, G_yx - G_xy) / 2``.
    """
    k = len(fits.ok)
    if model == "rigid":
        rot = -fits.params[:, :3]
        sig = np.sqrt(np.diagonal(fits.covariance, axis1=1, axis2=2)[:, :3])
        return rot, sig
    # G row-major: index 3*i + j
    J = np.zeros((3, 12))
    for row, (i1, j1, i2, j2) in enumerate(((2, 1, 1, 2), (0, 2, 2, 0), (1, 0, 0, 1))):
        J[row, 3 * i1 + j1] += 0.5
        J[row, 3 * i2 + j2] -= 0.5
    rot = fits.params @ J.T
    c = np.where(np.isfinite(fits.covariance), fits.covariance, 0.0)
    var = np.einsum("ij,kjl,il->ki", J, c, J)
    dvar = np.diagonal(fits.covariance, axis1=1, axis2=2)
    bad = np.isinf(dvar) @ (J != 0).T.astype(np.int64) > 0 if k else np.zeros((0, 3), bool)
    return rot, np.where(bad, np.inf, np.sqrt(np.maximum(var, 0.0)))


def median_test(
    row: np.ndarray,
    col: np.ndarray,
    values: np.ndarray,
    usable: np.ndarray,
    *,
    n_rows: int,
    n_cols: int,
    eps_m: float,
    threshold: float,
    min_neighbours: int = 3,
):
    """Normalised median test of a cell field (Westerweel & Scarano 2005, as PIV's).

    For each cell and component, ``r = |u - u_m| / (r_m + eps_m)`` with ``u_m`` the median
    of its usable 8-neighbours and ``r_m`` the median of their ``|u_i - u_m|``. A cell is
    flagged when ``r > threshold`` for any component and it has at least ``min_neighbours``
    usable neighbours. Robust: a wrong cell does not move its neighbours' medians much, so
    good neighbours of a bad cell are not flagged (unlike a test against a fitted plane).

    Parameters
    ----------
    row, col : (K,) int64
        Grid indices of the cells.
    values : (K, q) float64
        The cells' motion, metres.
    usable : (K,) bool
        Cells that may serve as neighbours (and be tested).
    n_rows, n_cols : int
        Grid shape.
    eps_m : float
        Noise level added to ``r_m``, metres.
    threshold : float
        2 in Westerweel & Scarano (2005).
    min_neighbours : int
        Cells with fewer usable neighbours are not tested.

    Returns
    -------
    flagged : (K,) bool
    neighbour_median : (K, q) float64
        ``u_m`` per component (NaN where a cell has no usable neighbour).
    score : (K,) float64
        Largest ``r`` over the components (NaN where not tested).
    """
    from .piv import _nanmedian0, _neighbours

    k, q = values.shape
    flagged = np.zeros(k, dtype=bool)
    med = np.full((k, q), np.nan)
    score = np.full(k, np.nan)
    if k == 0:
        return flagged, med, score
    for j in range(q):
        g = np.full((n_rows, n_cols), np.nan)
        g[row[usable], col[usable]] = values[usable, j]
        nb = _neighbours(g)
        m, cnt = _nanmedian0(nb)
        rm, _ = _nanmedian0(np.abs(nb - m[None]))
        with np.errstate(invalid="ignore"):
            r = np.abs(values[:, j] - m[row, col]) / (rm[row, col] + eps_m)
        tested = usable & (cnt[row, col] >= min_neighbours) & np.isfinite(r)
        med[:, j] = m[row, col]
        score = np.where(tested, np.fmax(score, r), score)
    with np.errstate(invalid="ignore"):
        flagged = score > threshold
    return flagged, med, score
