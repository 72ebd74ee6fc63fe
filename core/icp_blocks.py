"""Honest ICP covariances from block sums of the residual scores (issue #29, item 3).

The formal covariance of a point-to-plane fit, ``s0² N⁻¹``, assumes independent point
residuals. On real surfaces neighbouring points share their error (the scanner's sampling
pattern, vegetation, the target surface's own noise, normals estimated from overlapping
neighbourhoods), so the effective number of independent observations of a cell is far
smaller than its point count and the formal sigmas shrink as ``1/sqrt(n)`` where the true
error does not: on lone-star's densest cells (>= 10 000 points) the formal sigmas are 3-5x
too small (docs/fields.md).

Here the residuals' spatial correlation enters the covariance through the cluster-robust
("sandwich") estimator with sub-cell blocks as clusters (batch means):

    C_b = c N⁻¹ (sum_b g_b g_bᵀ) N⁻¹,     g_b = sum_{p in b} a_p psi_p,

``a_p`` the point's Jacobian row, ``psi_p = w_p v_p`` its (robustly weighted) residual, the sum
over the square blocks ``b`` of side ``block_m`` the cell's points fall in, and
``c = B / (B - 1) * n / (n - P) / mean(psi')²`` (the small-sample factors of the cluster-robust
and least-squares estimates, and the M-estimator's). With independent residuals its
expectation is the formal covariance; with residuals correlated over less than a block it is
the covariance of the estimate. Larger blocks see more of the correlation but are fewer per
cell, so the estimate gets noisier (a ``B``-block estimate has about ``B`` degrees of
freedom).

* **Block size from the data** (:func:`choose_block_level`): the block estimates are computed
  for a ladder of sizes (:data:`BLOCK_LADDER_M`, nested squares on a grid of map
  coordinates). As the blocks grow past the residuals' correlation length the pooled ratio of
  block to formal variances stops growing (the blocking method of Flyvbjerg & Petersen 1989):
  the chosen size is the smallest whose pooled ratio is within :data:`PLATEAU` of the largest
  among the sizes with at least :data:`MIN_BLOCKS` blocks in the median cell.
* **Few blocks** (:func:`shrink_covariance`): a cell's block covariance is shrunk towards its
  formal covariance times the field's pooled ratio ``kappa``, with weights ``B`` and
  :data:`PRIOR_BLOCKS`: ``C = (B C_b + B0 kappa C_f) / (B + B0)``. A cell of a few blocks
  takes mostly the field's typical correlation, a cell of many blocks its own.

* **What the residuals cannot show** (:func:`cell_floor`): the part of a cell's error common
  to all its points is absorbed by the fit (a constant offset of the residuals moves the
  translation). It is modelled as ``C (a + n / n_cap)``, a cap ``n_cap`` on the cell's
  independent observations, the field's ``a`` and ``n_cap`` from the agreement of
  neighbouring cells. On lone-star it carries most of the correction (docs/fields.md).

The same blocks serve the spline field (:func:`spline_block_covariance`): its scores are
sums over all points of a block, and the covariance of the penalised estimate is
``A⁻¹ (c M + s0² P) A⁻¹`` (``P`` the penalty, ``M = sum_b g_b g_bᵀ``), which is the formal
``s0² A⁻¹`` when the residuals are independent.

Written here (numpy, a few bincounts): statsmodels has cluster-robust covariances for linear
models fitted by it, not for a normal matrix assembled elsewhere, and a second dependency for
a dozen lines is not worth it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

log = logging.getLogger(__name__)

#: block sides tried, metres (nested: each a 2 x 2 of the previous one)
BLOCK_LADDER_M = (0.125, 0.25, 0.5, 1.0, 2.0, 4.0)
#: a block size is eligible when the median cell holds at least this many blocks with points
MIN_BLOCKS = 8
#: the chosen size is the smallest whose pooled variance ratio is within this share of the
#: largest eligible one (the ratio grows with the block size up to the correlation length)
PLATEAU = 0.1
#: shrinkage weight of the field's pooled ratio, in blocks
PRIOR_BLOCKS = 8.0
#: a spline field's neighbours share one field, so their agreement misses most of the
#: cell-wide error: an UNWEIGHTED spline fit's variance multiplier is at least
#: ``1 + SPLINE_FLOOR_SHARE (g - 1)`` with ``g`` the rigid cells' multiplier of the same run
#: (their neighbours are independent fits). Calibrated on lone-star, seeds 0-2 (docs/fields.md,
#: "Honest sigma"). A fit whose data were weighed ``1 / F`` (the default where the floor can
#: be estimated) carries ``F`` in its covariance and takes no share (core.icp._spline_blocks).
SPLINE_FLOOR_SHARE = 0.3
#: quantile of the squared normalised neighbour residuals the cell floor matches to chi²₁'s:
#: below the median, so that cells next to a discontinuity or a wrong minimum (a large
#: residual however honest the sigmas) weigh less
FLOOR_QUANTILE = 0.3
#: the points' noise, for the cells' surface share of the floor (:func:`surface_share`): this
#: quantile of the usable cells' residual RMS; None: the floor applies to every cell alike
#: (the model until stop 65)
NOISE_QUANTILE: Optional[float] = 0.05


def block_index(xy: np.ndarray, seg: np.ndarray, block_m: float) -> Tuple[np.ndarray, np.ndarray]:
    """Blocks of side ``block_m`` (on the grid of map coordinates) within each segment.

    Parameters
    ----------
    xy : (P, 2) float64
        Map positions of the points, metres.
    seg : (P,) int64
        Segment (cell) of each point, >= 0.
    block_m : float
        Block side, metres (> 0).

    Returns
    -------
    inverse : (P,) int64
        Block of each point, 0 .. B-1 (blocks of different segments are different).
    block_seg : (B,) int64
        Segment of each block.
    """
    if len(xy) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    bx = np.floor(xy[:, 0] / block_m).astype(np.int64)
    by = np.floor(xy[:, 1] / block_m).astype(np.int64)
    bx -= bx.min()
    by -= by.min()
    ny = int(by.max()) + 1
    nx = int(bx.max()) + 1
    key = (np.asarray(seg, dtype=np.int64) * nx + bx) * ny + by
    uniq, inverse = np.unique(key, return_inverse=True)
    return inverse.reshape(-1), uniq // (nx * ny)


def block_meats(
    A: np.ndarray,
    psi: np.ndarray,
    seg: np.ndarray,
    xy: np.ndarray,
    k: int,
    ladder=BLOCK_LADDER_M,
) -> Tuple[np.ndarray, np.ndarray]:
    """``M_k = sum_b g_b g_bᵀ`` per cell and block size, ``g_b`` the block's summed scores.

    Parameters
    ----------
    A : (P, q) float64
        Jacobian rows of the points' residuals.
    psi : (P,) float64
        Weighted residuals ``w v`` (0 for points not used), metres.
    seg : (P,) int64
        Cell of each point, 0 .. k-1.
    xy : (P, 2) float64
        Map positions, metres.
    k : int
        Number of cells.
    ladder : sequence of float
        Block sides, metres.

    Returns
    -------
    meats : (k, L, q, q) float64
    n_blocks : (k, L) int64
        Blocks with a used point per cell and size.
    """
    q = A.shape[1]
    L = len(ladder)
    meats = np.zeros((k, L, q, q))
    n_blocks = np.zeros((k, L), dtype=np.int64)
    used = psi != 0
    if not used.any():
        return meats, n_blocks
    S = A[used] * psi[used, None]
    sg = np.asarray(seg, dtype=np.int64)[used]
    sxy = xy[used]
    # the finest blocks once (one sort of the points); the coarser ones are unions of them
    b0 = float(ladder[0])
    ratios = [int(round(float(b) / b0)) for b in ladder]
    if any(abs(r * b0 - float(b)) > 1e-9 * float(b) for r, b in zip(ratios, ladder)):
        raise ValueError("block sizes must be integer multiples of the smallest")
    top = max(ratios)
    bx = np.floor(sxy[:, 0] / b0).astype(np.int64)
    by = np.floor(sxy[:, 1] / b0).astype(np.int64)
    bx -= (bx.min() // top) * top  # a multiple of every ratio: the grid stays aligned
    by -= (by.min() // top) * top
    nx, ny = int(bx.max()) + 1, int(by.max()) + 1
    ukey, inv0 = np.unique((sg * nx + bx) * ny + by, return_inverse=True)
    inv0 = inv0.reshape(-1)
    nb0 = len(ukey)
    g0 = np.stack([np.bincount(inv0, weights=S[:, j], minlength=nb0) for j in range(q)], 1)
    fseg, rest = np.divmod(ukey, nx * ny)
    fbx, fby = np.divmod(rest, ny)
    iu, ju = np.triu_indices(q)
    for li, r in enumerate(ratios):
        if r == 1:
            g, bseg = g0, fseg
        else:
            nxl, nyl = (nx - 1) // r + 1, (ny - 1) // r + 1
            uk, inv = np.unique((fseg * nxl + fbx // r) * nyl + fby // r, return_inverse=True)
            inv = inv.reshape(-1)
            g = np.stack(
                [np.bincount(inv, weights=g0[:, j], minlength=len(uk)) for j in range(q)], 1
            )
            bseg = uk // (nxl * nyl)
        prod = g[:, iu] * g[:, ju]
        for c, (i, j) in enumerate(zip(iu, ju)):
            sm = np.bincount(bseg, weights=prod[:, c], minlength=k)
            meats[:, li, i, j] = sm
            meats[:, li, j, i] = sm
        n_blocks[:, li] = np.bincount(bseg, minlength=k)
    return meats, n_blocks


def block_meats_reference(A, psi, seg, xy, k, ladder=BLOCK_LADDER_M):
    """Slow obvious :func:`block_meats`: per cell and block size, a loop over the blocks."""
    q = A.shape[1]
    meats = np.zeros((k, len(ladder), q, q))
    n_blocks = np.zeros((k, len(ladder)), dtype=np.int64)
    for c in range(k):
        m = (np.asarray(seg) == c) & (psi != 0)
        for li, bm in enumerate(ladder):
            cells = {}
            for a, p, (x, y) in zip(A[m], psi[m], xy[m]):
                key = (int(np.floor(x / bm)), int(np.floor(y / bm)))
                cells[key] = cells.get(key, 0.0) + a * p
            for g in cells.values():
                meats[c, li] += np.outer(g, g)
            n_blocks[c, li] = len(cells)
    return meats, n_blocks


def sandwich(ninv: np.ndarray, meats: np.ndarray, n_blocks: np.ndarray, scale: np.ndarray):
    """Block covariances ``scale B/(B-1) N⁻¹ M N⁻¹`` per cell and block size.

    Parameters
    ----------
    ninv : (k, q, q) float64
        (Pseudo-)inverse normal matrices (NaN rows allowed: not fitted).
    meats : (k, L, q, q) float64
    n_blocks : (k, L) int64
    scale : (k,) float64
        ``n / (n - q) / mean(psi')²`` per cell.

    Returns
    -------
    (k, L, q, q) float64
        NaN where a cell has fewer than 2 blocks.
    """
    nb = n_blocks.astype(np.float64)
    corr = np.where(nb >= 2, nb / np.maximum(nb - 1, 1), np.nan) * scale[:, None]
    out = np.einsum("kij,kljm,kmn->klin", ninv, meats, ninv)
    return out * corr[:, :, None, None]


@dataclass(frozen=True)
class BlockChoice:
    """The block size chosen for a field and its pooled variance ratios.

    Attributes
    ----------
    level : int
        Index into the ladder (-1: none eligible; the formal covariances stand).
    block_m : float
        Chosen block side, metres (NaN when none).
    ratios : (L,) float64
        Median over the usable cells of the block-to-formal variance ratio (translation
        components), per block size (NaN where not eligible).
    median_blocks : (L,) float64
        Blocks in the median usable cell, per size.
    kappa : float
        The ratio at the chosen size (the shrinkage target), >= 1.
    """

    level: int
    block_m: float
    ratios: np.ndarray
    median_blocks: np.ndarray
    kappa: float


def choose_block_level(
    formal_var: np.ndarray,
    block_var: np.ndarray,
    n_blocks: np.ndarray,
    usable: np.ndarray,
    *,
    ladder=BLOCK_LADDER_M,
    min_blocks: int = MIN_BLOCKS,
    plateau: float = PLATEAU,
) -> BlockChoice:
    """Block size of a field: the smallest on the plateau of the pooled variance ratio.

    Parameters
    ----------
    formal_var : (k, q) float64
        Formal variances (e.g. of dx, dy, dz), m².
    block_var : (k, L, q) float64
        Block variances per size.
    n_blocks : (k, L) int64
    usable : (k,) bool
        Cells that enter the choice (fitted, finite variances).
    ladder, min_blocks, plateau
        See the module's constants.

    Returns
    -------
    BlockChoice
    """
    L = block_var.shape[1]
    ratios = np.full(L, np.nan)
    med_b = np.full(L, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.mean(block_var / formal_var[:, None, :], axis=2)  # (k, L)
    for li in range(L):
        m = usable & np.isfinite(r[:, li]) & (n_blocks[:, li] >= 2)
        if not m.any():
            continue
        med_b[li] = float(np.median(n_blocks[usable, li])) if usable.any() else 0.0
        if med_b[li] >= min_blocks:
            ratios[li] = float(np.median(r[m, li]))
    if not np.any(np.isfinite(ratios)):
        return BlockChoice(-1, float("nan"), ratios, med_b, 1.0)
    top = np.nanmax(ratios)
    level = int(np.flatnonzero(ratios >= (1.0 - plateau) * top)[0])
    kappa = max(1.0, float(ratios[level]))
    log.info(
        "residual correlation: block variance ratios %s for blocks of %s m; %g m blocks "
        "chosen (ratio %.2f)",
        np.round(ratios, 2).tolist(),
        list(ladder),
        ladder[level],
        kappa,
    )
    return BlockChoice(level, float(ladder[level]), ratios, med_b, kappa)


def shrink_covariance(
    formal: np.ndarray,
    block: np.ndarray,
    n_blocks: np.ndarray,
    kappa: float,
    *,
    prior_blocks: float = PRIOR_BLOCKS,
) -> np.ndarray:
    """``(B C_b + B0 kappa C_f) / (B + B0)`` per cell; ``C_f`` where ``C_b`` is not finite.

    Parameters
    ----------
    formal, block : (k, q, q) float64
        Formal and block covariances.
    n_blocks : (k,) int64
    kappa : float
        The field's pooled block-to-formal ratio (the target of the shrinkage).
    prior_blocks : float
        ``B0``, the weight of the target in blocks (>= 0).

    Returns
    -------
    (k, q, q) float64
    """
    nb = np.asarray(n_blocks, dtype=np.float64)
    fin = np.all(np.isfinite(block), axis=(1, 2)) & (nb >= 2)
    w = np.where(fin, nb / (nb + prior_blocks), 0.0)[:, None, None]
    b = np.where(fin[:, None, None], block, 0.0)
    out = w * b + (1.0 - w) * kappa * np.where(np.isfinite(formal), formal, 0.0)
    return np.where(np.isfinite(formal), out, formal)  # undetermined stays inf / NaN


@dataclass(frozen=True)
class CellFloor:
    """What the cells' residuals cannot show, from the agreement of neighbouring cells
    (:func:`cell_floor`): each cell's block covariance is multiplied by
    ``factor² + n / n_cap``.

    Attributes
    ----------
    factor : float
        Multiplier of every cell's sigmas (>= 1; 1: the block sigmas of the sparser cells
        are honest). NaN when too few cells have enough neighbours.
    n_cap : float
        The most independent observations a cell's error behaves as if it had (the error
        common to all its points, which does not shrink with their number); ``inf``: none.
    n_cells : int
        Cells that entered the estimate.
    factor_before : float
        The field's neighbour variance factor of the block sigmas (1: honest already).
    """

    factor: float
    n_cap: float
    n_cells: int
    factor_before: float

    def scale(self, n: np.ndarray, share: Optional[np.ndarray] = None) -> np.ndarray:
        """Per-cell variance multiplier (K,): ``factor² + n / n_cap``, or with the cells'
        surface ``share`` (K,) (:func:`surface_share`) ``1 + (factor² - 1) share + share n /
        n_cap``."""
        n = np.asarray(n, dtype=np.float64)
        if not np.isfinite(self.factor):
            return np.ones(n.shape)
        return _floor_scale(self.factor**2, self.n_cap, n, share)


def _floor_scale(a: float, n_cap: float, n: np.ndarray, share=None) -> np.ndarray:
    """The floor's variance multiplier (K,) at ``a``, ``n_cap`` (see :class:`CellFloor`)."""
    extra = n / n_cap if np.isfinite(n_cap) else np.zeros(np.shape(n))
    if share is None:
        return a + extra
    share = np.asarray(share, dtype=np.float64)
    return 1.0 + (a - 1.0) * share + extra * share


def surface_share(rmse: np.ndarray, usable: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
    """Each cell's share of its residual variance that the surface's departure from the
    local planes makes, not the points' noise: ``1 - (s / rmse)²`` in [0, 1], ``s`` the
    :data:`NOISE_QUANTILE` quantile of the usable cells' residual RMS (the smoothest
    cells' residuals are mostly the instrument's noise).

    The error a cell's residuals cannot show (:func:`cell_floor`) is the surface's: the
    point-to-plane residual of a curved, sampled surface is biased alike over the cell (a
    plane fitted to the first epoch's points near a convex bump lies above the second
    epoch's points there), while the points' own noise is independent from point to point
    and already in the block sigmas. So the floor grows a cell's variance by its surface
    share: a smooth cell, whose residuals are noise, keeps nearly its block sigma, a rough
    one takes more. Measured on the landslide harness (docs/fields.md, "The surface's share
    of the floor"): the rigid slump beside the rough cone 1.75 -> 1.32 cm over twelve
    seeds, the other cases level.

    Parameters
    ----------
    rmse : (K,) float64
        The cells' residual RMS, metres (NaN: no fit).
    usable : (K,) bool, optional
        Cells that set the noise level (default: all with a finite, positive RMS).

    Returns
    -------
    (K,) float64 or None
        The shares (1 where the RMS is not finite); None when :data:`NOISE_QUANTILE` is None
        or no cell is usable (the floor then applies to every cell alike, as before).
    """
    if NOISE_QUANTILE is None:
        return None
    rm = np.asarray(rmse, dtype=np.float64)
    ok = np.isfinite(rm) & (rm > 0)
    good = ok if usable is None else ok & np.asarray(usable, dtype=bool)
    if not good.any():
        return None
    noise = float(np.quantile(rm[good], float(NOISE_QUANTILE)))
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(ok, np.clip(1.0 - (noise / np.where(ok, rm, 1.0)) ** 2, 0.0, 1.0), 1.0)
    log.info(
        "cells' surface share of their residuals: point noise %.2f cm (the %g quantile of "
        "the cells' RMS), share median %.2f", 100 * noise, NOISE_QUANTILE,
        float(np.median(share[good])),
    )  # fmt: skip
    return share


def cell_floor(
    row: np.ndarray,
    col: np.ndarray,
    values: np.ndarray,
    sigmas: np.ndarray,
    n: np.ndarray,
    *,
    usable: Optional[np.ndarray] = None,
    pair_covariance=None,
    min_cells: int = 8,
    iterations: int = 8,
    separated: Optional[np.ndarray] = None,
    share: Optional[np.ndarray] = None,
) -> CellFloor:
    """The error a cell's residuals cannot show, from neighbour agreement: a factor and a
    cap on the cell's effective observations.

    A fit absorbs the part of the error that is common to all its points (a constant offset
    of the residuals moves the cell's translation and leaves no trace in them): the bias of
    the point-to-plane residuals of a curved, sampled surface, errors correlated over more
    than a cell. It does not shrink with the number of points. The cells' variances are
    modelled as ``C_blocks (a + n / n_cap)``: a cell of ``n`` points behaves as
    ``n / (a + n / n_cap) < n_cap`` independent ones. With the cells' surface ``share``
    (:func:`surface_share`) the excess is the surface's and grows with it: ``C_blocks (1 +
    (a - 1) share + share n / n_cap)``. The two numbers are the field's: ``a``
    (>= 1) makes the sparser half of the tested cells (by ``n``) agree with their neighbours
    as their sigmas say (the :data:`FLOOR_QUANTILE` quantile of their squared normalised
    neighbour residuals that of chi²₁, below the median so that cells next to a scarp weigh
    less; :func:`slipmap.core.fields.neighbour_variance_factor`), ``n_cap`` (>= 1 or inf)
    the denser half; each by bisection in its logarithm, the two in turn (a cell's
    neighbours may sit in the other half). Dense cells, whose sigmas shrink most as
    ``1 / sqrt(n)``, get the most; a field whose neighbours agree already gets ``a = 1``
    and ``n_cap = inf``.

    Parameters
    ----------
    row, col : (K,) int
        Grid indices of the cells.
    values, sigmas : (K, q) float64
        The cells' motions and their 1-sigma (with the block correlation), metres.
    n : (K,) int
        Points (correspondences) of each cell.
    usable : (K,) bool, optional
        Cells allowed in the estimate (converged, not flagged).
    pair_covariance : ((P, 2) int, (P, q) float64), optional
        Covariances between the cells' values (a spline field), scaled with the cells'
        factors as :func:`slipmap.core.icp_sigma.region_variance_factors` does.
    min_cells : int
        Fewer tested cells give NaN (no change).
    iterations : int
        Alternations of the two bisections.
    separated : (K, 8) bool, optional
        Neighbours across a breakline, left out of each cell's prediction
        (:func:`slipmap.core.fields.neighbour_variance_factor`).
    share : (K,) float64, optional
        Each cell's surface share of its residual variance (:func:`surface_share`); None:
        the floor is alike for every cell.

    Returns
    -------
    CellFloor
    """
    from scipy.stats import chi2

    from .fields import neighbour_variance_factor

    q = float(FLOOR_QUANTILE)
    target = float(chi2.ppf(q, 1))

    n = np.asarray(n, dtype=np.float64)
    sig = np.asarray(sigmas, dtype=np.float64)
    if pair_covariance is not None:
        pairs = np.asarray(pair_covariance[0], dtype=np.int64).reshape(-1, 2)
        pcov = np.asarray(pair_covariance[1], dtype=np.float64).reshape(len(pairs), -1)

    def z2(a, n_cap):
        g = _floor_scale(a, n_cap, n, share)
        pc = None
        if pair_covariance is not None:
            pc = (pairs, pcov * np.sqrt(g[pairs[:, 0]] * g[pairs[:, 1]])[:, None])
        est = neighbour_variance_factor(
            row, col, values, sig * np.sqrt(g)[:, None], usable=usable, min_cells=1,
            pair_covariance=pc, separated=separated,
        )  # fmt: skip
        return est.normalised.reshape(len(n), -1) ** 2

    z = z2(1.0, np.inf)
    tested = np.all(np.isfinite(z), axis=1)
    cells = int(tested.sum())
    if cells < int(min_cells):
        return CellFloor(float("nan"), float("nan"), cells, float("nan"))
    f0 = float(np.sqrt(np.quantile(z[tested], q) / target))
    split = np.median(n[tested])
    low, high = tested & (n <= split), tested & (n > split)
    if not high.any():
        high = low

    def excess(a, n_cap, m):  # > 0: sigmas still too small in group m
        return float(np.quantile(z2(a, n_cap)[m], q)) - target

    def bisect(fn, lo, hi):  # fn decreasing in the log-parameter... see callers
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if fn(mid):
                lo = mid
            else:
                hi = mid
            if hi - lo < 2e-3:
                break
        return 0.5 * (lo + hi)

    top = float(np.log(max(float(np.max(n)), 1.0) * 1e4))
    a, n_cap = 1.0, np.inf
    for _ in range(int(iterations)):
        old = (a, n_cap)
        # the sparse half: a (variance multiplier), larger a -> smaller excess
        if excess(1.0, n_cap, low) <= 0:
            a = 1.0
        else:
            a = float(np.exp(bisect(lambda la, c=n_cap: excess(np.exp(la), c, low) > 0, 0.0, 12.0)))
        # the dense half: n_cap, larger n_cap -> larger excess
        if excess(a, np.inf, high) <= 0:
            n_cap = np.inf
        elif excess(a, 1.0, high) > 0:
            n_cap = 1.0
        else:
            n_cap = float(
                np.exp(bisect(lambda ln, f=a: excess(f, np.exp(ln), high) <= 0, 0.0, top))
            )
        same_cap = (np.isinf(n_cap) and np.isinf(old[1])) or (
            np.isfinite(n_cap) and np.isfinite(old[1]) and abs(np.log(n_cap / old[1])) < 0.01
        )
        if abs(np.log(a / old[0])) < 0.01 and same_cap:
            break
    log.info(
        "cell-wide error from neighbour agreement: factor %.2f with the block sigmas -> "
        "sigmas x sqrt(%.2f + n / %.0f)", f0, a, n_cap,
    )  # fmt: skip
    return CellFloor(float(np.sqrt(a)), float(n_cap), cells, f0)


@dataclass(frozen=True)
class BlockScores:
    """One chunk's share of a spline field's block sums (:func:`spline_block_scores`): the
    summed scores per (block, 16-knot group), as sparse triplets with global block keys, so
    that the chunks of a tiled fit add up to the one-file fit's sums.

    Attributes
    ----------
    keys : (G, 2) int64
        Block of each group, ``floor((x - x0) / block_m), floor((y - y0) / block_m)``
        (``x0, y0`` the knot frame's origin: the same blocks in every chunk).
    knots : (G, 16) int64
        The group's 16 knots (with breaklines, copies among them).
    vals : (G, 48) float64
        ``sum psi n_c w_j`` of the group's points, component-major (``16 c + j``).
    cell_blocks : (C, 3) int64
        Distinct ``(cell, bx, by)`` of the used points with a cell (for the block counts).
    """

    keys: np.ndarray
    knots: np.ndarray
    vals: np.ndarray
    cell_blocks: np.ndarray


def spline_block_scores(
    *,
    xy: np.ndarray,
    psi: np.ndarray,
    nrm: np.ndarray,
    idx16: np.ndarray,
    w16: np.ndarray,
    block_m: float,
    origin_xy=(0.0, 0.0),
    seg: Optional[np.ndarray] = None,
    group: Optional[np.ndarray] = None,
) -> BlockScores:
    """The summed scores of a spline fit's points per (block, 16-knot group).

    Points of one block and one 16-knot row share their 48 coefficients; they are grouped
    by the full row (with breaklines a point's knots may include copies, so the first knot
    does not name the row).

    Parameters
    ----------
    xy : (P, 2) float64
        Map positions of the points, metres.
    psi : (P,) float64
        Weighted residuals ``w v`` (0: not used), metres.
    nrm : (P, 3) float64
        Target normals.
    idx16, w16 : (P, 16) int64, float64
        The points' knots and B-spline weights.
    block_m : float
        Block side, metres.
    origin_xy : (2,) float
        Origin of the block grid (the knot frame's), metres.
    seg : (P,) int64, optional
        Reported cell of each point (-1: none).
    group : (P,) int64, optional
        Each point's 16-knot row as a number (equal rows, equal numbers: a
        :class:`~slipmap.core.icp_spline.SplineChunk` has them sorted); None: found here.

    Returns
    -------
    BlockScores
    """
    used = np.asarray(psi) != 0
    p_xy, p_psi, p_nrm = xy[used], psi[used], nrm[used]
    p_idx, p_w = np.asarray(idx16)[used], w16[used]
    bx = np.floor((p_xy[:, 0] - float(origin_xy[0])) / float(block_m)).astype(np.int64)
    by = np.floor((p_xy[:, 1] - float(origin_xy[1])) / float(block_m)).astype(np.int64)
    cell_blocks = np.zeros((0, 3), dtype=np.int64)
    if seg is not None:
        ps = np.asarray(seg, dtype=np.int64)[used]
        inside = ps >= 0
        cell_blocks = np.unique(np.column_stack([ps, bx, by])[inside], axis=0).reshape(-1, 3)
    if not p_psi.size:
        z = np.zeros((0, 2), dtype=np.int64)
        return BlockScores(z, np.zeros((0, 16), dtype=np.int64), np.zeros((0, 48)), cell_blocks)
    if group is None:
        _, gid = np.unique(p_idx, axis=0, return_inverse=True)
    else:
        gid = np.asarray(group)[used]
    gid = gid.reshape(-1).astype(np.int64)
    rx, ry = bx - bx.min(), by - by.min()
    nx, ny = int(rx.max()) + 1, int(ry.max()) + 1
    _, first, kinv = np.unique((gid * ny + ry) * nx + rx, return_index=True, return_inverse=True)
    kinv = kinv.reshape(-1)
    g = len(first)
    vals = np.empty((g, 48))
    for c in range(3):
        pc = p_psi * p_nrm[:, c]
        for j in range(16):
            vals[:, 16 * c + j] = np.bincount(kinv, weights=pc * p_w[:, j], minlength=g)
    keys = np.column_stack([bx[first], by[first]])
    return BlockScores(keys, p_idx[first].astype(np.int64), vals, cell_blocks)


def solve_report_rows(factor, rows: np.ndarray, cols: np.ndarray, n3: int):
    """The report rows of ``kk`` positions (``rows`` (kk, 9, 48): value, x- and y-slope of
    each component against their 48 coefficients ``cols`` (kk, 48)) as a sparse
    (kk * 9, n3) matrix ``G``, and ``A⁻¹ Gᵀ`` from the normal matrix's LU ``factor``
    (dense, (n3, kk * 9)): the spline field's covariances at those positions are
    ``G A⁻¹ Gᵀ``."""
    import scipy.sparse as sp

    kk = len(rows)
    rows_g = sp.csr_matrix(
        (np.asarray(rows).reshape(kk * 9, 48).ravel(), np.repeat(cols, 9, axis=0).ravel(),
         np.arange(0, kk * 9 * 48 + 1, 48)),
        shape=(kk * 9, n3),
    )  # fmt: skip
    return rows_g, factor.solve(np.asarray(rows_g.T.todense()))


def spline_block_covariance(
    scores,
    *,
    rows: np.ndarray,
    cols: np.ndarray,
    factor,
    penalty,
    s0sq: float,
    scale: float,
    chunk: int = 64,
) -> Tuple[np.ndarray, np.ndarray]:
    """Block covariance of a spline field's reported rows: ``R A⁻¹ (c M + s0² P) A⁻¹ Rᵀ``.

    ``M = sum_b g_b g_bᵀ`` with ``g_b`` the summed scores of the points of block ``b``
    (squares of the block side on the knot frame's grid; every chunk's share of a block
    added, :func:`spline_block_scores`), ``P`` the penalty, ``A = N + P`` the penalised
    normal matrix; with independent residuals ``c M`` is ``s0² N`` and this is the formal
    ``s0² A⁻¹``.

    Parameters
    ----------
    scores : sequence of BlockScores
        Every chunk's share (each point in one chunk).
    rows : (K, 9, 48) float64
        Rows of the reported quantities against the 48 coefficients of each position.
    cols : (K, 48) int64
        Those coefficients' indices (component-major).
    factor
        Sparse LU of ``A`` (``solve``).
    penalty : (3 n_k, 3 n_k) sparse
        The penalty matrix in ``A``.
    s0sq : float
        The formal variance of unit weight, m².
    scale : float
        ``c`` (``mean(w) / mean(psi')² * n / (n - u)``).
    chunk : int
        Reported positions per solve.

    ``R A⁻¹ (c M + s0² P) A⁻¹ Rᵀ`` is formed with ``c M + s0² P`` once, as a sparse matrix
    on the coefficients (``M = Sᵀ S``, ``S`` the blocks' summed scores): each chunk of
    positions then needs one sparse product over the coefficients instead of one over the
    blocks (of 0.125 m, tens of thousands on a TLS scene: 0.45 s of the default run on
    lone-star's lobe before, stop 55). :func:`_spline_block_covariance_reference` sums
    ``z_b z_bᵀ`` block by block, as the formula reads; they agree to rounding (tests).

    Returns
    -------
    cov : (K, 9, 9) float64
    n_blocks : (K,) int64
        Blocks with used points in each cell.
    """
    import scipy.sparse as sp

    scores = list(scores)
    k, n3 = len(rows), penalty.shape[0]
    S = _block_score_matrix(scores, n3)
    meat = (scale * (S.T @ S) + s0sq * sp.csr_matrix(penalty)).tocsr()  # (n3, n3)
    cov = np.zeros((k, 9, 9))
    for s0 in range(0, k, chunk):
        part = slice(s0, min(s0 + chunk, k))
        kk = part.stop - part.start
        _, sol = solve_report_rows(factor, rows[part], cols[part], n3)  # (3 n_k, kk * 9)
        ms = np.asarray(meat @ sol).reshape(n3, kk, 9)
        cov[part] = np.einsum("nki,nkj->kij", sol.reshape(n3, kk, 9), ms)
    return cov, _blocks_per_cell(scores, k)


def _spline_block_covariance_reference(
    scores,
    *,
    rows: np.ndarray,
    cols: np.ndarray,
    factor,
    penalty,
    s0sq: float,
    scale: float,
    chunk: int = 64,
) -> Tuple[np.ndarray, np.ndarray]:
    """The slow, obvious form of :func:`spline_block_covariance` (the reference its tests
    hold it to): per chunk of positions, every block's summed score ``z_b = g_bᵀ A⁻¹ Rᵀ``
    and the sum of ``z_b z_bᵀ`` over the blocks. Same parameters and returns."""
    scores = list(scores)
    k, n3 = len(rows), penalty.shape[0]
    S = _block_score_matrix(scores, n3)
    nb = S.shape[0]
    cov = np.zeros((k, 9, 9))
    for s0 in range(0, k, chunk):
        part = slice(s0, min(s0 + chunk, k))
        kk = part.stop - part.start
        _, sol = solve_report_rows(factor, rows[part], cols[part], n3)  # (3 n_k, kk * 9)
        z = np.asarray(S @ sol).reshape(nb, kk, 9)
        ps = np.asarray(penalty @ sol).reshape(n3, kk, 9)
        sr = sol.reshape(n3, kk, 9)
        cov[part] = scale * np.einsum("bki,bkj->kij", z, z) + s0sq * np.einsum(
            "nki,nkj->kij", sr, ps
        )
    return cov, _blocks_per_cell(scores, k)


def _block_score_matrix(scores, n3: int):
    """(blocks, n3) sparse ``S``: each block's summed scores on the coefficients (the
    chunks' shares of one block, and its groups', added)."""
    import scipy.sparse as sp

    n_k = n3 // 3
    keys = np.concatenate([s.keys for s in scores]).reshape(-1, 2)
    knots = np.concatenate([s.knots for s in scores]).reshape(-1, 16)
    vals = np.concatenate([s.vals for s in scores]).reshape(-1, 48)
    if len(keys):
        _, binv = np.unique(keys, axis=0, return_inverse=True)
        binv = binv.reshape(-1)
        nb = int(binv.max()) + 1
    else:
        binv, nb = np.zeros(0, dtype=np.int64), 0
    rr = (np.arange(3)[None, :, None] * n_k + knots[:, None, :]).reshape(-1, 48)
    return sp.csr_matrix((vals.ravel(), (np.repeat(binv, 48), rr.ravel())), shape=(nb, n3))


def _blocks_per_cell(scores, k: int) -> np.ndarray:
    """(k,) int64: blocks with used points in each cell."""
    cb = np.concatenate([s.cell_blocks for s in scores]).reshape(-1, 3)
    cb = np.unique(cb, axis=0).reshape(-1, 3) if len(cb) else cb
    return np.bincount(cb[:, 0], minlength=k).astype(np.int64)[:k]
