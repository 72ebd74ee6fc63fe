"""What the windowed ICP's engines share (:mod:`.icp`, the per-cell fits and their reference;
:mod:`.icp_cells`, the batched cells; :mod:`.icp_spline`, the spline field): tuning
constants, the fit options and the robust weights of residuals. A module of its own so that
no engine imports another at module level."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

__all__ = ["EIG_RTOL", "HUBER_K", "MAD_TO_SIGMA", "NULL_RTOL", "TUKEY_C"]

TUKEY_C = 4.685  # Tukey biweight tuning constant (95 % Gaussian efficiency), in robust sigmas
HUBER_K = 1.345  # Huber tuning constant (95 % Gaussian efficiency), in robust sigmas
EIG_RTOL = 1e-10  # directions of the (Jacobi-scaled) normal matrix below this are degenerate
NULL_RTOL = 1e-6  # an output depends on an undetermined direction above this relative size


@dataclass(frozen=True)
class _Options:
    max_iterations: int
    tolerance_m: float
    tolerance_rad: float
    tolerance_sigma: float
    max_correspondence_m: Optional[float]
    trim_fraction: float
    robust: Optional[str]
    neighbours_k: int


MAD_TO_SIGMA = 1.4826


def _weights(v: np.ndarray, opts: _Options) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals -> (keep mask, weights w, psi'(v)) for trimming / robust M-estimation."""
    keep = np.ones(v.size, dtype=bool)
    if opts.trim_fraction > 0 and v.size > 20:
        keep = np.abs(v) <= np.quantile(np.abs(v), 1.0 - opts.trim_fraction)
    if opts.robust is None:
        w = keep.astype(np.float64)
        return keep, w, w
    scale = MAD_TO_SIGMA * float(np.median(np.abs(v[keep])))
    w, dpsi = _robust_weights(v, max(scale, 1e-12), keep, opts.robust)
    return keep, w, dpsi


def _robust_weights(v: np.ndarray, scale, keep: np.ndarray, robust: str):
    """(w, psi'(v)) of residuals ``v`` (P,) at robust ``scale`` (scalar or (P,)), zero where
    not ``keep``: Tukey's biweight or Huber's M-estimator (``robust``)."""
    if robust == "tukey":
        u = v / (TUKEY_C * scale)
        inside = (np.abs(u) < 1.0) & keep
        u2 = np.where(inside, u * u, 1.0)
        w = np.where(inside, (1.0 - u2) ** 2, 0.0)
        dpsi = np.where(inside, (1.0 - u2) * (1.0 - 5.0 * u2), 0.0)
    else:  # huber
        a = np.abs(v) / (HUBER_K * scale)
        inside = a <= 1.0
        w = np.where(inside, 1.0, 1.0 / np.maximum(a, 1e-300)) * keep
        dpsi = (inside & keep).astype(np.float64)
    return w, dpsi


def _shared_target_inflation(psi, keep, seg, tid, ss) -> np.ndarray:
    """Per segment, the variance of the kept ``psi`` summed per (segment, target point) over
    that of ``psi`` (``ss``, (K,)), at least 1: points paired with one target point share its
    error, which independent residuals would miss. ``psi`` (P,) is zero where not ``keep``;
    ``seg`` (P,) the segments, ``tid`` (P,) the target points. 1 where ``ss`` is 0."""
    k = len(ss)
    key = seg.astype(np.int64) * (int(tid.max()) + 1 if tid.size else 1) + tid
    _, inv = np.unique(key[keep], return_inverse=True)
    cl = np.bincount(inv.reshape(-1), weights=psi[keep])
    cl_seg = np.zeros(cl.size, dtype=np.int64)
    cl_seg[inv.reshape(-1)] = seg[keep]
    cl_ss = np.bincount(cl_seg, weights=cl * cl, minlength=k)
    return np.where(ss > 0, np.maximum(1.0, cl_ss / np.where(ss > 0, ss, 1.0)), 1.0)
