"""Two starts for the cells of a seeded windowed-ICP pass: the seed and zero (issue #29).

A coarse-to-fine pass (or a PIV field given as ``initial_displacement``) starts every fine cell
from the coarser field at its centre. Where a coarse cell straddles a discontinuity (the edge
of a slump block, a scarp), that prediction is a blend of the two sides and can be wrong by
most of the jump for a fine cell on one side; started there, with its target box moved by it,
the fine cell converges into a wrong minimum: on the landslide harness's TLS slump (seed 0,
docs/fields.md) a stable cell 3.3 m beside the block reported 1.4 m of motion, its
point-to-plane RMS 1.9 cm against 1.0 cm when started from zero, the start Open3D's per-cell
ICP uses.

So every cell whose seed is away from zero (more than :data:`START_EPS_M`) is also fitted from
zero, and the fit whose converged transform fits the epoch-1 surface better is kept. Why this
and not the alternatives the issue named:

* rejecting coarse cells that straddle a discontinuity (bimodal residuals) needs a
  bimodality test per coarse cell and still leaves the fine cell a wrong seed from its
  interpolation between neighbouring coarse cells; the two-start test judges the fine cell's
  own fit, whatever made its seed wrong (a coarse cell, a PIV outlier);
* the neighbours' fine results (the median restart, ``median_restart``) are themselves
  seeded by the same coarse field beside a block edge, where several neighbours share the
  wrong seed; zero is a start no coarse field can spoil. Where the motion is large against the
  cell, the start from zero is the one that fails, fits worse and is dropped: the coarse
  pass keeps its purpose.

The criterion is objective and the same for both fits: each transform's point-to-plane
residuals of the cell's points against their nearest epoch-1 point (all of epoch 1, no
target box: the boxes of the two starts differ) within the pass's gate, in a truncated
quadratic ``min(v², c²) / c²`` (1 where a point has no target: the overlap counts), ``c``
Tukey's ``4.685`` robust sigmas of both fits' residuals pooled (one scale for both). The
cell takes the zero start only when its mean cost is lower by more than
:data:`SWITCH_Z` standard errors of the paired per-point differences (the same points
under both transforms), so fits that reached the same minimum keep the seeded one.

:func:`truncated_costs` is the vectorised kernel; :func:`truncated_costs_reference` the slow
obvious per-cell loop it is tested against.
"""

from __future__ import annotations

import math

import numpy as np

from .icp_options import MAD_TO_SIGMA, TUKEY_C

__all__ = [
    "START_EPS_M",
    "SWITCH_Z",
    "choose_zero_start",
    "paired_means",
    "point_costs",
    "point_residuals",
    "transformed",
    "tree_points",
    "truncated_costs",
    "truncated_costs_reference",
]

#: a seed closer to zero than this (metres) is zero: the cell is not fitted twice
START_EPS_M = 0.02
#: the zero start replaces the seeded fit when its mean cost is lower by this many standard
#: errors of the paired per-point cost differences
SWITCH_Z = 2.0


def transformed(src: np.ndarray, seg: np.ndarray, centres, linear, t) -> np.ndarray:
    """(P, 3) map coordinates ``L (s) + t + c`` of the cells' centred points ``src`` (P, 3)
    under each cell's transform (``linear`` (K, 3, 3), ``t`` (K, 3)) about ``centres`` (K, 3)."""
    return np.einsum("pij,pj->pi", linear[seg], src) + t[seg] + centres[seg]


def point_residuals(world: np.ndarray, *, tree, normals, gate: float, n_targets: int):
    """Point-to-plane residual (P,) of each point ``world`` (P, 3) against its nearest epoch-1
    point (``tree``: query in map coordinates; ``normals(ids) -> (J, 3)``) within ``gate``
    metres; NaN where there is none or its normal is undefined."""
    v = np.full(len(world), np.nan)
    if len(world) == 0:
        return v
    ub = gate if math.isfinite(gate) else np.inf
    _, j = tree.query(world, distance_upper_bound=ub, workers=-1)
    j = np.asarray(j).reshape(len(world))
    ok = j < n_targets
    if ok.any():
        jj = j[ok]
        nrm = normals(jj)
        tp = tree_points(tree, jj)
        v[ok] = np.einsum("ij,ij->i", nrm, world[ok] - tp)
    return v


def tree_points(tree, idx: np.ndarray) -> np.ndarray:
    """Map coordinates of the tree's points ``idx`` (an ``_OffsetTree`` or a cKDTree)."""
    inner = getattr(tree, "tree", tree)
    off = getattr(tree, "offset", None)
    p = inner.data[idx]
    return p if off is None else p + off


def _costs(v: np.ndarray, c: float) -> np.ndarray:
    """``min(v², c²) / c²``, 1 where ``v`` is NaN (no target)."""
    with np.errstate(invalid="ignore"):
        u = np.minimum((v / c) ** 2, 1.0) if c > 0 else (v != 0).astype(np.float64)
    return np.where(np.isfinite(v), u, 1.0)


def point_costs(v_a: np.ndarray, v_b: np.ndarray, seg: np.ndarray, k: int):
    """Per-point truncated costs ``min(v², c²) / c²`` (P,) of two residual sets of the same
    points (1 where a point has no target), ``c = TUKEY_C * MAD_TO_SIGMA * median |v|`` of
    both sets of each cell pooled (one scale for both); see :func:`truncated_costs`."""
    seg = np.asarray(seg, dtype=np.int64)
    # the pooled robust scale per cell: median |v| of both residual sets (sorted per cell)
    av = np.abs(np.concatenate([v_a, v_b]))
    sg2 = np.concatenate([seg, seg])
    fin = np.isfinite(av)
    av, sg2 = av[fin], sg2[fin]
    order = np.lexsort((av, sg2))
    av, sg2 = av[order], sg2[order]
    cnt = np.bincount(sg2, minlength=k)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    med = np.zeros(k)
    has = cnt > 0
    lo = start + (cnt - 1) // 2
    hi = start + cnt // 2
    med[has] = 0.5 * (av[lo[has]] + av[hi[has]])
    c = TUKEY_C * MAD_TO_SIGMA * med
    cp = c[seg]
    with np.errstate(invalid="ignore", divide="ignore"):
        ua = np.where(cp > 0, np.minimum((v_a / cp) ** 2, 1.0), (v_a != 0).astype(np.float64))
        ub = np.where(cp > 0, np.minimum((v_b / cp) ** 2, 1.0), (v_b != 0).astype(np.float64))
    return np.where(np.isfinite(v_a), ua, 1.0), np.where(np.isfinite(v_b), ub, 1.0)


def paired_means(u_a: np.ndarray, u_b: np.ndarray, seg: np.ndarray, k: int, where=None):
    """Per-cell means (K,) of two per-point cost sets ``u_a``, ``u_b`` (P,) over the points
    where ``where`` (P,) bool holds (default: all), and the standard error of the mean of
    their paired differences; NaN for a cell without such points."""
    seg = np.asarray(seg, dtype=np.int64)
    w = np.ones(seg.size) if where is None else np.asarray(where, dtype=np.float64)
    cost_a, cost_b, se = np.full(k, np.nan), np.full(k, np.nan), np.full(k, np.nan)
    n = np.bincount(seg, weights=w, minlength=k)
    some = n > 0
    nn = np.where(some, n, 1.0)
    cost_a[some] = (np.bincount(seg, weights=w * u_a, minlength=k) / nn)[some]
    cost_b[some] = (np.bincount(seg, weights=w * u_b, minlength=k) / nn)[some]
    dd = u_a - u_b
    mean_d = np.bincount(seg, weights=w * dd, minlength=k) / nn
    ss = np.bincount(seg, weights=w * (dd - mean_d[seg]) ** 2, minlength=k)
    var = ss / np.maximum(n - 1.0, 1.0) / nn
    se[some] = np.sqrt(var[some])
    return cost_a, cost_b, se


def truncated_costs(v_a: np.ndarray, v_b: np.ndarray, seg: np.ndarray, k: int):
    """Mean truncated costs of two transforms per cell and the standard error of their
    difference.

    Parameters
    ----------
    v_a, v_b : (P,) float64
        Residuals of the same points under the two transforms, metres (NaN: no target).
    seg : (P,) int64
        Cell of each point, 0 .. K-1 (need not be sorted).
    k : int
        Number of cells.

    Returns
    -------
    cost_a, cost_b : (K,) float64
        Mean of ``min(v², c²) / c²`` over each cell's points (1 for a point without a
        target), ``c = TUKEY_C * MAD_TO_SIGMA * median |v|`` of both transforms' residuals of
        the cell pooled; NaN for a cell without points.
    se : (K,) float64
        Standard error of the mean of the per-point differences ``cost_a - cost_b``.
    """
    seg = np.asarray(seg, dtype=np.int64)
    if seg.size == 0:
        return np.full(k, np.nan), np.full(k, np.nan), np.full(k, np.nan)
    return paired_means(*point_costs(v_a, v_b, seg, k), seg, k)


def truncated_costs_reference(v_a: np.ndarray, v_b: np.ndarray, seg: np.ndarray, k: int):
    """Slow obvious reference of :func:`truncated_costs`: one cell at a time."""
    cost_a = np.full(k, np.nan)
    cost_b = np.full(k, np.nan)
    se = np.full(k, np.nan)
    for i in range(k):
        m = seg == i
        if not m.any():
            continue
        a, b = v_a[m], v_b[m]
        both = np.abs(np.concatenate([a, b]))
        both = both[np.isfinite(both)]
        c = TUKEY_C * MAD_TO_SIGMA * float(np.median(both)) if both.size else 0.0
        ua, ub = _costs(a, c), _costs(b, c)
        cost_a[i], cost_b[i] = ua.mean(), ub.mean()
        d = ua - ub
        se[i] = math.sqrt(d.var(ddof=1) / d.size) if d.size > 1 else 0.0
    return cost_a, cost_b, se


def choose_zero_start(cost_seeded, cost_zero, se, ok_seeded, ok_zero) -> np.ndarray:
    """(K,) bool: keep the fit from zero instead of the seeded one. It fitted and the seeded
    one did not, or both fitted and its mean cost is lower by more than :data:`SWITCH_Z`
    standard errors (and by more than rounding)."""
    diff = cost_seeded - cost_zero
    with np.errstate(invalid="ignore"):
        better = np.isfinite(diff) & (diff > SWITCH_Z * se) & (diff > 1e-12)
    return ok_zero & (~ok_seeded | better)
