"""Variance factors of a gridded field per region of cells (issue #18, item 4).

Windowed ICP's formal covariances assume independent point residuals; on real surfaces they
are too small by a factor that depends on the ground (vegetation, scan shadows, range). One
a-posteriori factor per field (:func:`slipmap.core.fields.neighbour_variance_factor`) fits the
typical cell: rough cells get too small a sigma, smooth ones too large. Here the cells are split
into regions (e.g. classes of roughness, :func:`quantile_regions`) and each region gets its own
factor from the same neighbour agreement, estimated robustly (median) and only from cells
allowed in the estimate (converged, not flagged as wrong minima).

A cell's neighbour residual ``r = v - plane(neighbours)`` mixes the cell's error with its
neighbours', which may sit in other regions: ``var(r) = f_i² sigma_i² + sum h_j² f_j²
sigma_j²``. The factors are therefore found together, by a fixed-point iteration: each
region's factor is multiplied by ``sqrt(median(r² / var) / median(chi²₁))`` over its cells
until nothing changes.

Neighbour agreement misses the part of the error that neighbouring cells share (their target
boxes overlap, survey errors are spatially correlated), so it underestimates the factor.
``inflation`` multiplies the estimated factors by a calibrated constant (see
:data:`REGION_INFLATION` and docs/fields.md for how it was measured).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from .errors import InvalidParameterError
from .fields import CHI2_1_MEDIAN, neighbour_variance_factor

log = logging.getLogger(__name__)

#: Multiplier of the per-region factors of windowed ICP (``sigma_scaling="region"``): the
#: neighbour agreement misses the error that neighbouring cells share, and the errors have
#: heavier tails than a Gaussian. Calibrated on lone-star's uniform shift (3 seeds, 2 m and
#: 5 m cells, with and without restarts: the multiplier that puts 95 % of the error
#: components of each roughness tercile within 2 sigma was 1.00-1.46 before it, 1.25
#: pooled; docs/fields.md).
REGION_INFLATION = 1.25


@dataclass(frozen=True)
class RegionVarianceFactors:
    """Variance factors of a gridded field per region.

    Attributes
    ----------
    factors : (R,) float64
        Factor of each region, times ``inflation``: the number its cells' formal sigmas must
        be multiplied by. A region with fewer than ``min_cells`` tested cells gets the field's
        single factor. NaN when the field's factor cannot be estimated.
    n_cells : (R,) int64
        Tested cells of each region (cells with enough usable neighbours).
    field_factor : float
        The field's single factor (as :func:`~slipmap.core.fields.neighbour_variance_factor`
        over the same usable cells), NaN when too few cells.
    cell_factor : (K,) float64
        ``factors[region]`` per cell (the field factor for cells in no region, ``region < 0``).
    iterations : int
        Fixed-point iterations run.
    inflation : float
        The constant the estimates were multiplied by (``factors`` include it).
    """

    factors: np.ndarray
    n_cells: np.ndarray
    field_factor: float
    cell_factor: np.ndarray
    iterations: int
    inflation: float = 1.0


def quantile_regions(
    score: np.ndarray, *, n_regions: int = 3, usable: Optional[np.ndarray] = None
) -> np.ndarray:
    """Classes of cells by the quantiles of a score (e.g. terciles of the residual RMS).

    Parameters
    ----------
    score : (K,) float64
        Per-cell score (e.g. the point-to-plane residual RMS, metres).
    n_regions : int
        Number of classes (>= 1).
    usable : (K,) bool, optional
        Cells whose scores define the quantiles (default: all with a finite score); every cell
        with a finite score is classed.

    Returns
    -------
    (K,) int64
        Class 0 (lowest scores) .. ``n_regions - 1``; -1 where the score is not finite.
    """
    n = int(n_regions)
    if n < 1:
        raise InvalidParameterError(f"n_regions must be at least 1, got {n_regions}")
    score = np.asarray(score, dtype=np.float64).reshape(-1)
    finite = np.isfinite(score)
    ref = finite if usable is None else finite & np.asarray(usable, dtype=bool).reshape(-1)
    out = np.full(score.size, -1, dtype=np.int64)
    if not ref.any():
        return out
    edges = np.quantile(score[ref], np.linspace(0.0, 1.0, n + 1)[1:-1])
    out[finite] = np.searchsorted(edges, score[finite], side="right")
    return out


def region_variance_factors(
    row: np.ndarray,
    col: np.ndarray,
    values: np.ndarray,
    sigmas: np.ndarray,
    region: np.ndarray,
    *,
    usable: Optional[np.ndarray] = None,
    min_cells: int = 8,
    prior_cells: float = 10.0,
    inflation: float = 1.0,
    max_iterations: int = 50,
    tolerance: float = 1e-4,
    pair_covariance: Optional[Tuple[np.ndarray, np.ndarray]] = None,
) -> RegionVarianceFactors:
    """Variance factor of the formal sigmas of a gridded field, one per region of cells.

    Parameters
    ----------
    row, col : (K,) int
        Grid indices of the cells (each cell at most once).
    values, sigmas : (K,) or (K, q) float64
        Field components (e.g. dx, dy, dz, metres) and their formal 1-sigma.
    region : (K,) int
        Region of each cell, 0 .. R-1 (R = ``region.max() + 1``); negative: in no region
        (such cells still serve as neighbours, with the field's factor).
    usable : (K,) bool, optional
        Cells allowed in the estimate, as centre or neighbour (e.g. converged and not
        flagged); see :func:`~slipmap.core.fields.neighbour_variance_factor`.
    min_cells : int
        A region needs this many tested cells for a factor of its own (>= 1); the field's
        factor needs as many in all.
    prior_cells : float
        Shrinkage towards the field's factor (>= 0): a region's factor is the geometric mean
        of its own estimate (weight: its tested cells ``n``) and the field's (weight
        ``prior_cells``), so a region of a few cells, whose median is noisy, stays near the
        field's factor and a large region speaks for itself. 0: no shrinkage.
    inflation : float
        Multiplier of the estimated factors (> 0; 1: none).
    max_iterations : int
        Limit of the fixed-point iteration.
    tolerance : float
        Stop when no factor changes by more than this fraction.
    pair_covariance : ((P, 2) int, (P, q) float64), optional
        Formal covariances between cells of a correlated field (e.g. one spline fitted to all
        cells), as in :func:`~slipmap.core.fields.neighbour_variance_factor`. A covariance
        between cells ``i`` and ``j`` is scaled by ``f_i f_j`` with their regions' factors.
        Without it a positively correlated field's factors come out too small.

    Returns
    -------
    RegionVarianceFactors
    """
    if int(min_cells) < 1:
        raise InvalidParameterError(f"min_cells must be at least 1, got {min_cells}")
    if not (math.isfinite(prior_cells) and prior_cells >= 0):
        raise InvalidParameterError(f"prior_cells must be >= 0, got {prior_cells}")
    if not (math.isfinite(inflation) and inflation > 0):
        raise InvalidParameterError(f"inflation must be a positive number, got {inflation}")
    region = np.asarray(region, dtype=np.int64).reshape(-1)
    values = np.asarray(values, dtype=np.float64)
    sigmas = np.asarray(sigmas, dtype=np.float64)
    k = region.size
    if np.shape(values)[0] != k:
        raise InvalidParameterError(f"region must have one entry per cell ({k} vs {len(values)})")
    n_reg = int(region.max()) + 1 if k and region.max() >= 0 else 0
    if pair_covariance is not None:
        pairs = np.asarray(pair_covariance[0], dtype=np.int64).reshape(-1, 2)
        pcov = np.asarray(pair_covariance[1], dtype=np.float64).reshape(len(pairs), -1)
    base = neighbour_variance_factor(
        row,
        col,
        values,
        sigmas,
        usable=usable,
        min_cells=min_cells,
        pair_covariance=pair_covariance,
    )
    field_f = base.factor
    if not math.isfinite(field_f) or n_reg == 0:
        return RegionVarianceFactors(
            factors=np.full(n_reg, field_f * inflation),
            n_cells=np.zeros(n_reg, dtype=np.int64),
            field_factor=field_f,
            cell_factor=np.full(k, field_f * inflation),
            iterations=0,
            inflation=float(inflation),
        )
    sig2d = sigmas.reshape(k, -1)
    f = np.full(n_reg, field_f)
    tested = np.all(np.isfinite(base.normalised.reshape(k, -1)), axis=1)
    n_cells = np.bincount(region[tested & (region >= 0)], minlength=n_reg).astype(np.int64)
    own = n_cells >= int(min_cells)
    it = 0
    change = np.zeros(n_reg)
    for _ in range(int(max_iterations)):
        it += 1
        cf = np.where(region >= 0, f[np.maximum(region, 0)], field_f)
        scaled = None
        if pair_covariance is not None:  # cov(f_i e_i, f_j e_j) = f_i f_j c_ij
            scaled = (pairs, pcov * (cf[pairs[:, 0]] * cf[pairs[:, 1]])[:, None])
        est = neighbour_variance_factor(
            row,
            col,
            values,
            sig2d * cf[:, None],
            usable=usable,
            min_cells=1,
            pair_covariance=scaled,
        )
        z2 = est.normalised.reshape(k, -1) ** 2
        step = np.ones(n_reg)
        for r in np.flatnonzero(own):
            m = tested & (region == r)
            step[r] = math.sqrt(float(np.median(z2[m])) / CHI2_1_MEDIAN)
        # shrink each region's new estimate towards the field's factor (log scale)
        w = n_cells / (n_cells + float(prior_cells))
        new = np.exp(w * np.log(f * step) + (1.0 - w) * math.log(field_f))
        new = np.where(own, new, field_f)
        change = np.abs(new / f - 1.0)
        f = new
        if np.all(change <= tolerance):
            break
    else:
        log.warning(
            "region variance factors: no fixed point in %d iterations (last changes %s)",
            max_iterations,
            np.round(change, 4),
        )
    factors = f * inflation
    cell = np.where(region >= 0, factors[np.maximum(region, 0)], field_f * inflation)
    return RegionVarianceFactors(
        factors=factors,
        n_cells=n_cells,
        field_factor=field_f,
        cell_factor=cell,
        iterations=it,
        inflation=float(inflation),
    )
