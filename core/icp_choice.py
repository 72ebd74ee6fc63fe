"""The field or the cell, chosen per cell by its points (issue #29 item 1).

The default field is one B-spline surface, smooth on each side of its breaklines. Where the
ground moves in a way it cannot follow and no breakline was found, it smooths: on the
landslide harness's rotational slump (docs/fields.md) no line is found around the rotating
block, and the field spreads the block's motion into the stable ground beside it and flattens
the block's rotation, decimetres off in cells whose own rigid fit is right to a centimetre.
The rigid cell pass that starts the field has fitted every cell on its own points already.

So each cell's points judge the two motions: the field's (each point moved by the field at
its position) and the cell's rigid transform. Both are scored as the two starts of a seeded
cell are (:mod:`slipmap.core.icp_starts`): the point-to-plane residual of each point against
its nearest epoch-1 point within the gate, in the truncated quadratic
``min(v², c²) / c²`` with one robust scale ``c`` for both, and the cell reports its rigid fit
only when that fit's mean cost is lower by more than :data:`~slipmap.core.icp_starts.
SWITCH_Z` standard errors of the paired differences. A field that follows its ground as well
as the cell, or better (a straining lobe, which a rigid cell cannot follow), keeps the field.

The rigid cell's motion there is a first-order map of its transform: a point ``p`` of the
cell maps to ``p - d - G (p - c)`` (``d`` the motion at the centre ``c``, ``G`` the motion's
gradient). For a rigid or affine cell without window deformation this is its fitted
transform exactly (``linear = I - G``, ``t = -d``, :class:`~slipmap.core.icp_cells.CellFits`);
the tiled run has only ``d`` and ``G`` of its cells, so both runs use this form and choose
alike.

A cell whose own fit and the field agree within their uncertainty keeps the field, however
its costs compare: the choice only matters where the two values differ, and a test on
thousands of points whose residuals are correlated finds "better" fits too readily (on a
uniform shift of lone-star, cells that chose their own fits at 2.0-2.7 standard errors moved
1-3 cm from a field right to 1 mm). They differ when ``(d_own - d_field)ᵀ (C_own +
C_field)⁻¹ (d_own - d_field)`` exceeds :data:`DIFFER_CHI2` (χ²₃'s 95 % point).

A cell reports its value at its centre. Where it straddles a scarp or the outline of a
block, its points hold two motions and its rigid fit follows the larger part, which need not
be the part its centre lies in: on the harness's slump such a cell fitted its points better
than the field and was 0.55 m off at its centre with a sigma of 1.4 cm (seed 0, TLS,
docs/fields.md). So the points around the centre, within :data:`CENTRE_SHARE_OF_CELL` of
the cell's side, must agree: there the cell's own fit may not be clearly worse than the
field (by more than :data:`CENTRE_Z` standard errors: the per-point standard errors ignore
the residuals' correlation, and a field that is off along the surface can fit the points
around the centre as well as a right cell), and it may leave at most
:data:`MAX_UNEXPLAINED_SHARE` of them unexplained (beyond the truncation, or without a
target). A cell with (almost) no points around its centre judges it on its points nearest
the centre instead (:func:`centre_points`; until stop 61 it kept the field). A straddling
cell whose centre lies in the part its fit follows keeps its fit (a cell of the synthetic
slump with a fifth of its points beyond the block's edge: right to 6 mm where the field was
0.8 m off).

Where the points cannot tell the two apart (the cell's own fit no worse than the field, over
the cell and around its centre) but the field is barely determined at the centre, the cell
reports its own fit too: the field's covariance there has more than :data:`PRECISION_RATIO`
times the trace of the cell's (:func:`more_precise`). That is a cell in a scan shadow or at
the edge of the data, where the field's local penalty lets it bend freely and nothing holds
its value at the centre, while the rigid cell's motion is held by all its points. On the
harness's slump (TLS, seed 1) such a cell's field was 40 cm off vertically with a sigma of
29 cm; its own fit 9 cm, sigma 2.4 cm. Of two fits that explain the points equally, the one
that the data determine better is reported, with its own covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from .icp_starts import SWITCH_Z, paired_means, point_costs, point_residuals

__all__ = [
    "CENTRE_SHARE_OF_CELL",
    "CENTRE_Z",
    "DIFFER_CHI2",
    "MAX_UNEXPLAINED_SHARE",
    "MIN_CENTRE_POINTS",
    "PRECISION_RATIO",
    "ChoiceCosts",
    "centre_points",
    "choice_costs",
    "choose_cells",
    "differ",
    "more_precise",
    "no_worse",
]

#: a cell whose own fit leaves more than this share of the points around its centre
#: unexplained keeps the field
MAX_UNEXPLAINED_SHARE = 0.15
#: the points around a cell's centre: within this share of the cell's side (horizontally)
CENTRE_SHARE_OF_CELL = 0.25
#: a cell with fewer points than this around its centre judges its centre on its points
#: nearest it instead (:func:`centre_points`)
MIN_CENTRE_POINTS = 10
#: the cell's own fit and the field differ when their Mahalanobis distance² exceeds this
#: (χ²₃'s 95 % point)
DIFFER_CHI2 = 7.815
#: a cell whose own fit is no worse than the field (:func:`no_worse`) reports it when the
#: field's covariance at its centre has more than this many times its own trace (the field's
#: RMS sigma 4x the cell's): the field is then barely determined there (TLS slump: far cells
#: 6.65 -> 4.24 cm on seeds 0-2, 6.23 -> 2.16 cm on seeds 3-5, no other case changed; a ratio
#: of 4 cost the ALS cells' 2-sigma coverage 94 -> 92 %: docs/fields.md, "The more precise
#: of two equal fits")
PRECISION_RATIO = 16.0
#: around its centre the cell's own fit may be worse than the field by at most this many
#: standard errors of the paired per-point cost differences
CENTRE_Z = 3.0


@dataclass(frozen=True)
class ChoiceCosts:
    """What each cell's points say of the field and of the cell's own motion (all (K,)
    float64, NaN where a cell has no such points or no motion of its own).

    Attributes
    ----------
    field, cell : mean truncated point-to-plane cost of the field and of the cell's motion
        over the cell's points (:func:`~slipmap.core.icp_starts.point_costs`).
    se : standard error of the mean of their paired per-point differences.
    unexplained : share of the cell's points that the cell's motion leaves unexplained
        (cost 1: beyond the truncation or without a target).
    centre_field, centre_cell, centre_se : the same over the points around the centre.
    centre_unexplained : share of the points around the centre that the cell's motion leaves
        unexplained.
    """

    field: np.ndarray
    cell: np.ndarray
    se: np.ndarray
    unexplained: np.ndarray
    centre_field: np.ndarray
    centre_cell: np.ndarray
    centre_se: np.ndarray
    centre_unexplained: np.ndarray

    @classmethod
    def empty(cls, k: int) -> ChoiceCosts:
        """K cells with no costs (NaN), to be filled with :meth:`put`."""
        return cls(*(np.full(int(k), np.nan) for _ in fields(cls)))

    def put(self, idx: np.ndarray, part: ChoiceCosts) -> None:
        """Copy ``part``'s cells into cells ``idx`` of this one (in place: a tiled run
        assembles its blocks' costs)."""
        for f in fields(self):
            getattr(self, f.name)[idx] = getattr(part, f.name)


def choice_costs(pts, seg, k, centres, field, d, grad, *, cell_m, tree, normals, gate,
                 n_targets) -> ChoiceCosts:  # fmt: skip
    """The costs of the field and of each cell's own motion on the cell's points.

    Parameters
    ----------
    pts : (P, 3) float64
        The cells' after-points (the sample the fits used), map coordinates, metres.
    seg : (P,) int64
        Cell of each point, 0 .. ``k`` - 1.
    k : int
        Number of cells.
    centres : (k, 3) float64
        Cell centres, metres.
    field : callable
        ``field(xy (N, 2)) -> (N, 3)`` ground motion of the field, metres (a
        :class:`~slipmap.core.icp_spline.SplineField`).
    d : (k, 3) float64
        Each cell's own motion at its centre, metres (NaN: none).
    grad : (k, 3, 3) float64
        Its gradient (rigid cells: ``R - I``), dimensionless.
    cell_m : float
        The cells' side, metres (the points around a centre: :func:`centre_points`).
    tree, normals, gate, n_targets
        The epoch-1 nearest-plane objects (:func:`~slipmap.core.icp_starts.point_residuals`).

    Returns
    -------
    ChoiceCosts
    """
    pts = np.asarray(pts, dtype=np.float64)
    seg = np.asarray(seg, dtype=np.int64)
    k = int(k)
    kw = dict(tree=tree, normals=normals, gate=gate, n_targets=n_targets)
    own = np.all(np.isfinite(d), axis=1) & np.all(np.isfinite(grad), axis=(1, 2))
    keep = own[seg]  # the points of cells with a motion of their own
    pts, seg = pts[keep], seg[keep]
    if seg.size == 0:
        return ChoiceCosts.empty(k)
    s = pts - centres[seg]
    world_f = pts - np.asarray(field(pts[:, :2]), dtype=np.float64)
    world_c = pts - d[seg] - np.einsum("pij,pj->pi", grad[seg], s)
    u_f, u_c = point_costs(
        point_residuals(world_f, **kw), point_residuals(world_c, **kw), seg, k
    )  # fmt: skip
    around = centre_points(np.hypot(s[:, 0], s[:, 1]), seg, k, cell_m=cell_m)
    out_c, none = (u_c >= 1.0).astype(np.float64), np.zeros(u_c.size)
    return ChoiceCosts(
        *paired_means(u_f, u_c, seg, k),
        paired_means(out_c, none, seg, k)[0],
        *paired_means(u_f, u_c, seg, k, where=around),
        paired_means(out_c, none, seg, k, where=around)[0],
    )  # fmt: skip


def centre_points(r, seg, k, *, cell_m) -> np.ndarray:
    """(P,) bool: the points around their cell's centre.

    Those within ``CENTRE_SHARE_OF_CELL * cell_m`` of it horizontally; in a cell with fewer
    than :data:`MIN_CENTRE_POINTS` there (its centre in a scan shadow, a vent, a gap), its
    points nearest the centre instead, as large a share of them as that disc is of the
    cell's area (about a fifth). Such a cell used to keep the field whatever its points
    said: on the harness's rigid slump (TLS, seeds 4 and 5) the one far cell inside the
    block has no point within 1.25 m of its centre, and its own fit, right to 2 mm and
    15 standard errors better than the field over its 3900 points, lost to a field 0.9-1.2 m
    off (docs/fields.md, stop 61).

    Parameters
    ----------
    r : (P,) float64
        Each point's horizontal distance from its cell's centre, metres.
    seg : (P,) int64
        Cell of each point, 0 .. ``k`` - 1.
    k : int
        Number of cells.
    cell_m : float
        The cells' side, metres.
    """
    r = np.asarray(r, dtype=np.float64)
    seg = np.asarray(seg, dtype=np.int64)
    around = r <= CENTRE_SHARE_OF_CELL * float(cell_m)
    n_in = np.bincount(seg[around], minlength=k)
    sparse = (n_in < MIN_CENTRE_POINTS)[seg]
    if not sparse.any():
        return around
    n_all = np.bincount(seg, minlength=k)
    order = np.lexsort((r, seg))  # by cell, then by distance from the centre
    first = np.concatenate([[0], np.cumsum(n_all)[:-1]])
    rank = np.empty(seg.size, dtype=np.int64)
    rank[order] = np.arange(seg.size) - first[seg[order]]
    share = math.pi * CENTRE_SHARE_OF_CELL**2  # the disc's share of the cell's area
    nearest = rank < np.ceil(share * n_all[seg])
    return np.where(sparse, nearest, around)


def choose_cells(costs: ChoiceCosts, usable) -> np.ndarray:
    """(K,) bool: the cell reports its own fit instead of the field's. It is ``usable``
    (fitted, converged, enough points); its mean cost is lower than the field's by more than
    :data:`~slipmap.core.icp_starts.SWITCH_Z` standard errors (and by more than rounding);
    around its centre its cost is not higher than the field's by more than :data:`CENTRE_Z`
    standard errors, and it leaves at most :data:`MAX_UNEXPLAINED_SHARE` of the points there
    unexplained."""
    c = costs
    diff = c.field - c.cell
    with np.errstate(invalid="ignore"):
        better = np.isfinite(diff) & (diff > SWITCH_Z * c.se) & (diff > 1e-12)
    return np.asarray(usable, dtype=bool) & better & _centre_ok(c)


def _centre_ok(c: ChoiceCosts) -> np.ndarray:
    """(K,) bool: around its centre the cell's own fit is not worse than the field by more
    than :data:`CENTRE_Z` standard errors and leaves at most :data:`MAX_UNEXPLAINED_SHARE`
    of the points there unexplained (False where it has no points there)."""
    with np.errstate(invalid="ignore"):
        return (c.centre_cell - c.centre_field <= CENTRE_Z * c.centre_se) & (
            c.centre_unexplained <= MAX_UNEXPLAINED_SHARE
        )


def no_worse(costs: ChoiceCosts, usable) -> np.ndarray:
    """(K,) bool: the cell is ``usable`` and its own fit is no worse than the field: over its
    points (by at most :data:`~slipmap.core.icp_starts.SWITCH_Z` standard errors) and around
    its centre (:data:`CENTRE_Z`, :data:`MAX_UNEXPLAINED_SHARE`, as :func:`choose_cells`). A
    cell with no points around its centre is not."""
    c = costs
    with np.errstate(invalid="ignore"):
        level = c.cell - c.field <= SWITCH_Z * c.se
    return np.asarray(usable, dtype=bool) & level & _centre_ok(c)


def more_precise(candidates, cov_own, cov_field) -> np.ndarray:
    """(K,) bool: of the cells ``candidates`` (K,) bool (:func:`no_worse`), those where the
    field's covariance at the centre ``cov_field`` (K, 3, 3), m², has more than
    :data:`PRECISION_RATIO` times the trace of the cell's own ``cov_own`` (K, 3, 3), m²;
    False where either is not finite."""
    to = np.trace(np.asarray(cov_own, dtype=np.float64), axis1=1, axis2=2)
    tf = np.trace(np.asarray(cov_field, dtype=np.float64), axis1=1, axis2=2)
    fin = np.isfinite(to) & np.isfinite(tf)
    out = np.zeros(len(to), dtype=bool)
    out[fin] = tf[fin] > PRECISION_RATIO * to[fin]
    return np.asarray(candidates, dtype=bool) & out


def differ(d_a: np.ndarray, d_b: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(K,) bool: two estimates ``d_a``, ``d_b`` (K, 3) of each cell's motion (metres)
    differ, their difference's squared Mahalanobis distance under ``cov`` (K, 3, 3), the
    covariance of the difference (m²), above :data:`DIFFER_CHI2`; False where any of them
    is not finite or ``cov`` is singular."""
    delta = np.asarray(d_a, dtype=np.float64) - np.asarray(d_b, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    out = np.zeros(len(delta), dtype=bool)
    fin = np.all(np.isfinite(delta), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
    fin &= np.linalg.det(np.where(fin[:, None, None], cov, np.eye(3))) > 0
    if fin.any():
        x = np.linalg.solve(cov[fin], delta[fin][:, :, None])[:, :, 0]
        out[fin] = np.einsum("ki,ki->k", delta[fin], x) > DIFFER_CHI2
    return out
