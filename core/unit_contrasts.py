"""Acquisition units seen apart on one plane: within-epoch unit contrasts.

The misclosures of a side's planes (:mod:`.stochastic`) see an acquisition unit's error (an
ALS strip's offset, an MLS pass's drift, a TLS setup's registration) only where it differs
from plane to plane and the side's rigid motion does not absorb it. With a few strips per
side, a rotation and a translation absorb most of the strips' errors: the misclosures then
say nothing of them, REML puts the unit components at zero, and the slip's σ leaves out the
one error that dominates it (issue #30: an airborne pair 4.5σ off with 10 planes a side).

A plane seen by two units in ONE epoch says more: the two units' points lie on the same
surface, so the offset between them along the plane's normal is the difference of the units'
errors, whatever the ground did between the epochs. This is what an ALS strip adjustment
reads from the strips' overlaps. For each plane and epoch whose points come from two or more
units (each with at least :data:`MIN_GROUP_POINTS` points), the plane is fitted with one
tilt and one offset per unit, and the difference of the offsets of its two largest units is
one "contrast" row::

    c = (d_a − d_b)  =  nᵀ (s_a − s_b) + ε,      Var ε = σ² (1/n_a + 1/n_b + Δmᵀ M⁻¹ Δm)

with ``s_u`` the unit errors (or their drift along GpsTime, through the groups' shares of
the virtual units, :mod:`.unit_drift`), ``σ²`` the plane's residual variance about the fit,
``Δm`` the difference of the two groups' mean in-plane coordinates and ``M`` the within-group
scatter of the in-plane coordinates (the tilt's normal matrix). The rows enter the REML of
the components beside the misclosures, with no motion in them and their unit shares beside
the planes' (:func:`.stochastic.estimate_components`): the unit components are then
identified from the planes each unit sees. The motion's own estimate uses the misclosures
only, as before.

Hand-written: a plane fit with one offset per group is a fixed-effects regression, solved
here for all planes at once through within-group demeaning (Frisch-Waugh); no library fits
thousands of such small regressions in a few vectorised passes.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Dict, Optional, Tuple

import numpy as np

from .unit_drift import hat_unit_shares

#: points a unit needs on a plane in one epoch for its offset there to count
MIN_GROUP_POINTS = 30
#: robust std from the median beyond which a contrast is a blunder (:func:`screen_contrasts`)
GROSS_CONTRAST_K = 5.0

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class UnitContrasts:
    """The within-epoch unit contrasts of one epoch's planes (module docstring).

    Attributes
    ----------
    plane : (m,) int64
        Plane index of each row (0 .. b-1 of the planes given; for a report only).
    value : (m,) float64
        Offset of the plane's largest unit minus its second largest, along the normal (m).
    var : (m,) float64
        White variance of ``value`` from the plane's scatter about its fit (m²).
    normal : (m, 3) float64
        The plane's unit normal in this epoch.
    row_groups : (m, 2) int64
        The groups (first, second) of each row, 0 .. G-1.
    point_index : (n_g,) int64
        The points of those groups, indices into the points given.
    point_group, point_unit : (n_g,) int64
        Their group and acquisition unit.
    point_time : (n_g,) float64 or None
        Their acquisition time (GpsTime, seconds), for the drift's shares.
    position : (m, 3) float64 or None
        Where each row is measured: the mean of its two groups' centroids, in the frame of
        the points given (metres); a unit's turn about its origin moves the row by
        ``nᵀ(ω × (position − origin))`` (:attr:`.stochastic.PlaneModel.unit_lever_m`).
    """

    plane: np.ndarray
    value: np.ndarray
    var: np.ndarray
    normal: np.ndarray
    row_groups: np.ndarray
    point_index: np.ndarray
    point_group: np.ndarray
    point_unit: np.ndarray
    point_time: Optional[np.ndarray] = None
    position: Optional[np.ndarray] = None
    #: :meth:`shares` per knot spacing, computed once (every side's adjustment and every
    #: transfer round of a slip asks for the same survey's rows)
    _shares: Dict[float, Tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    @property
    def size(self) -> int:
        return int(self.value.size)

    def shares(self, interval_s: float) -> Tuple[np.ndarray, np.ndarray]:
        """(m, V) share differences of each row's two groups per virtual unit and the (V,)
        virtual unit ids (:func:`.unit_drift.hat_unit_shares`; ``math.inf``, or no times:
        the rigid units)."""
        if self.point_time is None:
            interval_s = math.inf
        if interval_s not in self._shares:
            n_groups = int(self.point_group.max(initial=-1)) + 1
            count = np.bincount(self.point_group, minlength=n_groups).astype(np.float64)
            s, ids = hat_unit_shares(
                self.point_group, self.point_unit, self.point_time, count, interval_s=interval_s
            )
            self._shares[interval_s] = (s[self.row_groups[:, 0]] - s[self.row_groups[:, 1]], ids)
        return self._shares[interval_s]


def screen_contrasts(con: Optional[UnitContrasts], *, k_gross: float = GROSS_CONTRAST_K):
    """The rows of ``con`` without gross ones: a row further than ``k_gross`` from the rows'
    median, in units of ``√(var + s²)`` with ``s`` the rows' robust spread (1.4826 MAD), is
    left out (a car parked on a wall's foot in one pass, a plane whose two units saw two
    different surfaces). The unit errors are then what the other rows say; as the robust
    start of the planes (:func:`.stochastic.robust_start`), a coarse screen of blunders,
    not a test."""
    if con is None or con.size < 5:
        return con
    med = float(np.median(con.value))
    s = 1.4826 * float(np.median(np.abs(con.value - med)))
    z = np.abs(con.value - med) / np.sqrt(con.var + s * s)
    keep = z <= k_gross
    if bool(np.all(keep)):
        return con
    log.info(
        "unit contrasts: %d of %d left out as gross (more than %.0f robust std from the "
        "median offset %.1f mm)", int((~keep).sum()), con.size, k_gross, med * 1000.0,
    )  # fmt: skip
    return replace(
        con, plane=con.plane[keep], value=con.value[keep], var=con.var[keep],
        normal=con.normal[keep], row_groups=con.row_groups[keep],
        position=None if con.position is None else con.position[keep],
    )  # fmt: skip


def concat_contrasts(parts) -> Optional[UnitContrasts]:
    """The rows of several :class:`UnitContrasts` of one epoch (e.g. the two sides of a
    fault) as one; None when none has a row. ``point_index`` is left per part (meaningless
    once joined) and ``plane`` keeps each part's numbering."""
    parts = [p for p in parts if p is not None and p.size]
    if not parts:
        return None
    offs = np.cumsum([0] + [int(p.point_group.max(initial=-1)) + 1 for p in parts])
    times = [p.point_time for p in parts]
    where = [p.position for p in parts]
    return UnitContrasts(
        plane=np.concatenate([p.plane for p in parts]),
        value=np.concatenate([p.value for p in parts]),
        var=np.concatenate([p.var for p in parts]),
        normal=np.vstack([p.normal for p in parts]),
        row_groups=np.vstack([p.row_groups + o for p, o in zip(parts, offs)]),
        point_index=np.concatenate([p.point_index for p in parts]),
        point_group=np.concatenate([p.point_group + o for p, o in zip(parts, offs)]),
        point_unit=np.concatenate([p.point_unit for p in parts]),
        point_time=None if any(t is None for t in times) else np.concatenate(times),
        position=None if any(w is None for w in where) else np.vstack(where),
    )


def unit_contrasts(
    plane: np.ndarray,
    points: np.ndarray,
    unit: np.ndarray,
    b: int,
    *,
    time_s: Optional[np.ndarray] = None,
    min_points: int = MIN_GROUP_POINTS,
) -> UnitContrasts:
    """Within-epoch contrasts of the acquisition units seen on each plane.

    Parameters
    ----------
    plane : (n,) int64
        Plane index of each point, 0 .. b-1.
    points : (n, 3) float64
        The points (metres, any frame; not modified).
    unit : (n,) int64
        Acquisition unit of each point.
    b : int
        Number of planes.
    time_s : (n,) float64, optional
        Acquisition time of each point (GpsTime, seconds), for the shares of a drift.
    min_points : int
        Points a unit needs on a plane to count there.

    Returns
    -------
    UnitContrasts
        One row per plane seen by two or more units (the two largest).
    """
    plane = np.asarray(plane, dtype=np.int64)
    unit = np.asarray(unit, dtype=np.int64)
    n = plane.size
    empty = UnitContrasts(
        np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros((0, 3)),
        np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
        np.zeros(0, np.int64), None if time_s is None else np.zeros(0), np.zeros((0, 3)),
    )  # fmt: skip
    if n == 0:
        return empty
    # groups (plane, unit) with enough points, on planes with two or more of them
    u0 = int(unit.min())
    span = int(unit.max()) - u0 + 1
    code, inv = np.unique(plane * span + (unit - u0), return_inverse=True)  # 1-D: fast
    inv = inv.ravel()
    key = np.stack([code // span, code % span + u0], axis=1)
    cnt = np.bincount(inv, minlength=key.shape[0])
    ok = cnt >= int(min_points)
    per_plane = np.bincount(key[ok, 0], minlength=b)
    ok &= per_plane[key[:, 0]] >= 2
    if not np.any(ok):
        return empty
    gid = np.full(key.shape[0], -1, np.int64)
    gid[ok] = np.arange(int(ok.sum()))
    g_plane = key[ok, 0]
    group = gid[inv]
    sel = group >= 0
    gp, x, pl = group[sel], np.asarray(points, dtype=np.float64)[sel], plane[sel]
    ng = int(ok.sum())
    n_g = np.bincount(gp, minlength=ng).astype(np.float64)
    # each plane's normal and tangents from the scatter of its grouped points
    n_p = np.bincount(pl, minlength=b).astype(np.float64)
    safe = np.maximum(n_p, 1.0)
    cen = np.stack([np.bincount(pl, x[:, k], b) for k in range(3)], axis=1) / safe[:, None]
    d = x - cen[pl]
    scat = np.zeros((b, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            scat[:, i, j] = scat[:, j, i] = np.bincount(pl, d[:, i] * d[:, j], b)
    _, vec = np.linalg.eigh(scat + np.eye(3)[None] * 1e-30)
    nrm, t1, t2 = vec[:, :, 0], vec[:, :, 1], vec[:, :, 2]
    r = np.einsum("ij,ij->i", d, nrm[pl])
    q = np.stack([np.einsum("ij,ij->i", d, t1[pl]), np.einsum("ij,ij->i", d, t2[pl])], axis=1)
    # one tilt per plane, one offset per group (within-group demeaning)
    r_g = np.bincount(gp, r, ng) / n_g
    q_g = np.stack([np.bincount(gp, q[:, k], ng) for k in range(2)], axis=1) / n_g[:, None]
    rt, qt = r - r_g[gp], q - q_g[gp]
    mm = np.zeros((b, 2, 2))
    mv = np.zeros((b, 2))
    for i in range(2):
        mv[:, i] = np.bincount(pl, qt[:, i] * rt, b)
        for j in range(i, 2):
            mm[:, i, j] = mm[:, j, i] = np.bincount(pl, qt[:, i] * qt[:, j], b)
    det = mm[:, 0, 0] * mm[:, 1, 1] - mm[:, 0, 1] ** 2
    good = det > 1e-12 * np.maximum(mm[:, 0, 0] * mm[:, 1, 1], 1e-300)
    minv = np.zeros_like(mm)
    minv[good, 0, 0] = mm[good, 1, 1] / det[good]
    minv[good, 1, 1] = mm[good, 0, 0] / det[good]
    minv[good, 0, 1] = minv[good, 1, 0] = -mm[good, 0, 1] / det[good]
    tilt = np.einsum("pij,pj->pi", minv, mv)
    off = r_g - np.einsum("gi,gi->g", q_g, tilt[g_plane])
    res = rt - np.einsum("ij,ij->i", qt, tilt[pl])
    n_groups_p = np.bincount(g_plane, minlength=b)
    dof = np.maximum(n_p - n_groups_p - 2.0, 1.0)
    s2 = np.bincount(pl, res * res, b) / dof
    # the two largest groups of each plane (ties: the lower unit id first)
    order = np.lexsort((np.arange(ng), -n_g, g_plane))
    first = np.ones(ng, bool)
    first[1:] = g_plane[order][1:] != g_plane[order][:-1]
    start = np.flatnonzero(first)
    ga, gb = order[start], order[start + 1]
    rows_plane = g_plane[ga]
    keep = good[rows_plane]
    ga, gb, rows_plane = ga[keep], gb[keep], rows_plane[keep]
    dm = q_g[ga] - q_g[gb]
    var = s2[rows_plane] * (
        1.0 / n_g[ga] + 1.0 / n_g[gb] + np.einsum("ri,rij,rj->r", dm, minv[rows_plane], dm)
    )
    value = off[ga] - off[gb]
    x_g = np.stack([np.bincount(gp, x[:, k], ng) for k in range(3)], axis=1) / n_g[:, None]
    # the groups' ids renumbered to the rows' groups only
    used = np.unique(np.concatenate([ga, gb]))
    remap = np.full(ng, -1, np.int64)
    remap[used] = np.arange(used.size)
    pidx = np.flatnonzero(sel)
    pg = remap[gp]
    inrow = pg >= 0
    return UnitContrasts(
        plane=rows_plane.astype(np.int64),
        value=value,
        var=var,
        normal=nrm[rows_plane],
        row_groups=np.stack([remap[ga], remap[gb]], axis=1),
        point_index=pidx[inrow],
        point_group=pg[inrow],
        point_unit=unit[sel][inrow],
        point_time=None if time_s is None else np.asarray(time_s, dtype=np.float64)[sel][inrow],
        position=0.5 * (x_g[ga] + x_g[gb]),
    )


def unit_contrasts_reference(plane, points, unit, b, *, min_points=MIN_GROUP_POINTS):
    """Slow reference of :func:`unit_contrasts`: per plane, an explicit least-squares fit of
    the offsets along the normal on [in-plane coordinates, one indicator per unit] and its
    covariance ``σ² (AᵀA)⁻¹``. Returns ``{plane: (value, var, normal)}``."""
    out: Dict[int, Tuple[float, float, np.ndarray]] = {}
    plane, unit = np.asarray(plane), np.asarray(unit)
    points = np.asarray(points, dtype=float)
    for p in range(b):
        m = plane == p
        us, cs = np.unique(unit[m], return_counts=True)
        ok = us[cs >= min_points]
        if ok.size < 2:
            continue
        mm = m & np.isin(unit, ok)
        x, u = points[mm], unit[mm]
        d = x - x.mean(axis=0)
        _, vec = np.linalg.eigh(d.T @ d)
        r = d @ vec[:, 0]
        a = np.column_stack([d @ vec[:, 1], d @ vec[:, 2]] + [(u == k).astype(float) for k in ok])
        coef, *_ = np.linalg.lstsq(a, r, rcond=None)
        res = r - a @ coef
        s2 = float(res @ res) / max(len(r) - a.shape[1], 1)
        cov = s2 * np.linalg.inv(a.T @ a)
        cnt = np.array([(u == k).sum() for k in ok])
        order = sorted(range(ok.size), key=lambda i: (-cnt[i], ok[i]))
        i, j = 2 + order[0], 2 + order[1]
        value = coef[i] - coef[j]
        var = cov[i, i] + cov[j, j] - 2.0 * cov[i, j]
        out[p] = (float(value), float(var), vec[:, 0])
    return out


def aligned(shares: np.ndarray, ids: np.ndarray, codes: Optional[np.ndarray]) -> np.ndarray:
    """(m, len(codes)) the contrast shares ``shares`` (m, V) of virtual units ``ids`` in the
    columns ``codes`` of the epoch's plane shares (every id of a contrast is among them: its
    points are the plane's)."""
    if codes is None:
        return np.zeros((shares.shape[0], 0))
    out = np.zeros((shares.shape[0], codes.size))
    if ids.size:
        out[:, np.searchsorted(codes, ids)] = shares
    return out


@dataclass(frozen=True)
class ContrastRows:
    """Both epochs' contrast rows as a plane-level model carries them
    (:class:`.stochastic.PlaneModel`, :class:`.stochastic.PlaneGain`): not tied to the
    model's planes (a within-epoch contrast holds whatever the ground did, so a plane the
    adjustment rejects, or one of the other side of a fault, still ties its units).

    Attributes
    ----------
    value, var : (m,) float64
        :attr:`UnitContrasts.value` and :attr:`UnitContrasts.var` (m, m²).
    normal : (m, 3) float64
        The plane's normal each row is measured along.
    shares_before, shares_after : (m, U) float64 or None
        Share differences per unit in the model's ``shares_before`` / ``shares_after``
        columns (zero rows for the other epoch's contrasts); None where the model has none.
    options : dict or None
        ``{interval_s: (shares_before, shares_after)}`` for each drift along GpsTime of the
        model's ``unit_options``, in its columns.
    position : (m, 3) float64 or None
        Where each row is measured (:attr:`UnitContrasts.position`), in the frame of the
        model's centroids; None: not known (the units' turn is then not seen in the rows).
    """

    value: np.ndarray
    var: np.ndarray
    normal: np.ndarray
    shares_before: Optional[np.ndarray]
    shares_after: Optional[np.ndarray]
    options: Optional[Dict[float, Tuple[Optional[np.ndarray], Optional[np.ndarray]]]] = None
    #: rows of each epoch (before, after), for the report
    counts: Tuple[int, int] = (0, 0)
    position: Optional[np.ndarray] = None

    @property
    def size(self) -> int:
        return int(self.value.size)

    def with_interval(self, interval_s: float) -> ContrastRows:
        """The rows with the shares of the drift of knot spacing ``interval_s``."""
        opts = self.options or {}
        if interval_s not in opts:
            return self
        sb, sa = opts[interval_s]
        return replace(self, shares_before=sb, shares_after=sa)

    def take(self, sel: np.ndarray) -> ContrastRows:
        """The rows ``sel``."""

        def cut(s):
            return None if s is None else s[sel]

        return ContrastRows(
            value=self.value[sel], var=self.var[sel], normal=self.normal[sel],
            shares_before=cut(self.shares_before), shares_after=cut(self.shares_after),
            options=None if self.options is None
            else {dt: (cut(sb), cut(sa)) for dt, (sb, sa) in self.options.items()},
            counts=self.counts,  # the set's, for the report
            position=cut(self.position),
        )  # fmt: skip

    def shifted(self, offset: np.ndarray) -> ContrastRows:
        """The rows with their positions moved by ``offset`` (3,) metres (another frame)."""
        if self.position is None:
            return self
        return replace(self, position=self.position + np.asarray(offset, dtype=np.float64))

    def same_rows(self, other: Optional[ContrastRows]) -> bool:
        """Whether ``other`` holds the same contrasts (two sides given one survey's rows)."""
        return (
            other is not None
            and other.size == self.size
            and np.array_equal(other.value, self.value)
            and np.array_equal(other.normal, self.normal)
        )


def padded(shares, codes, extra):
    """``shares`` (b, U) in columns ``codes`` (U,) widened to ``codes ∪ extra`` (zero columns
    for the new ids); returns the shares and the sorted codes. None shares stay None."""
    if shares is None or codes is None:
        return shares, codes
    allc = np.union1d(codes, extra)
    if allc.size == codes.size:
        return shares, codes
    out = np.zeros((shares.shape[0], allc.size))
    out[:, np.searchsorted(allc, codes)] = shares
    return out, allc


def with_contrast_units(contrasts, pairs, drift):
    """The epochs' unit shares and codes (``pairs``: per epoch (shares, codes)) and each
    drift's (``drift``: ``{interval_s: ((sb, sa), (cb, ca))}`` or None) widened by the units
    the contrasts see (an ALS strip of the other side of a fault); returns both."""

    def widen(shares, codes, interval_s):
        out_s, out_c = [], []
        for e, (s_, c_) in enumerate(zip(shares, codes)):
            con = contrasts[e]
            if con is not None and con.size and c_ is not None:
                _, ids = con.shares(interval_s)
                s_, c_ = padded(s_, c_, ids)
            out_s.append(s_)
            out_c.append(c_)
        return tuple(out_s), tuple(out_c)

    sh, cd = widen([p[0] for p in pairs], [p[1] for p in pairs], math.inf)
    pairs = list(zip(sh, cd))
    if drift:
        drift = {dt: widen(s_, c_, dt) for dt, (s_, c_) in drift.items()}
    return pairs, drift


def epoch_rows(contrasts, codes, drift=None, centre=None) -> Optional[ContrastRows]:
    """Both epochs' contrasts (before, after: :class:`UnitContrasts` or None) as one
    :class:`ContrastRows`, their shares in the columns ``codes`` of each epoch's rigid unit
    shares and, for each drift of ``drift`` (``{interval_s: (shares, codes)}``), in that
    drift's columns (an epoch without times keeps its rigid shares); their positions less
    ``centre`` (3,) (the model's frame; None: as given). None when neither epoch has a
    contrast (or the epoch's model has no unit columns)."""
    parts = [(e, c) for e, c in enumerate(contrasts) if c is not None and c.size]
    parts = [(e, c) for e, c in parts if codes[e] is not None]
    if not parts:
        return None

    def shares_for(interval_s, cols):
        out = []
        for which in (0, 1):
            if cols[which] is None:
                out.append(None)
                continue
            blocks = []
            for e, c in parts:
                if e != which:
                    blocks.append(np.zeros((c.size, cols[which].size)))
                    continue
                s, ids = c.shares(interval_s)
                blocks.append(aligned(s, ids, cols[which]))
            out.append(np.vstack(blocks))
        return tuple(out)

    sb, sa = shares_for(math.inf, codes)
    options = None
    if drift:
        options = {dt: shares_for(dt, cd) for dt, (_, cd) in drift.items()}
    where = None
    if all(c.position is not None for _, c in parts):
        where = np.vstack([c.position for _, c in parts])
        if centre is not None:
            where = where - np.asarray(centre, dtype=np.float64)
    return ContrastRows(
        value=np.concatenate([c.value for _, c in parts]),
        var=np.concatenate([c.var for _, c in parts]),
        normal=np.vstack([c.normal for _, c in parts]),
        shares_before=sb,
        shares_after=sa,
        options=options,
        counts=tuple(sum(c.size for e, c in parts if e == w) for w in (0, 1)),
        position=where,
    )


def union_rows(a: Optional[ContrastRows], b: Optional[ContrastRows], union):
    """Two sides' rows as one: one copy when both hold the same survey's rows, else ``a``'s
    then ``b``'s. ``union(which, sa, sb, interval_s)`` puts two sides' share blocks (None: no
    rows of that side) in the union's columns. Returns (rows or None, shared)."""
    if a is None and b is None:
        return None, False
    shared = a is not None and a.same_rows(b)
    if shared:
        b = None
    rows = [r for r in (a, b) if r is not None]

    def both(which, interval_s):
        def pick(r):
            if r is None:
                return None
            rr = r.with_interval(interval_s) if interval_s is not None else r
            return getattr(rr, "shares_" + which)

        return union(which, pick(a), pick(b), interval_s)

    opts = None
    keys = set(rows[0].options or {})
    for r in rows[1:]:
        keys &= set(r.options or {})
    if keys:
        opts = {dt: (both("before", dt), both("after", dt)) for dt in keys}
    out = ContrastRows(
        value=np.concatenate([r.value for r in rows]),
        var=np.concatenate([r.var for r in rows]),
        normal=np.vstack([r.normal for r in rows]),
        shares_before=both("before", None),
        shares_after=both("after", None),
        options=opts,
        counts=tuple(sum(r.counts[w] for r in rows) for w in (0, 1)),
        position=None
        if any(r.position is None for r in rows)
        else np.vstack([r.position for r in rows]),
    )
    return out, shared
