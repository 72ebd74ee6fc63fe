"""A straight breakline proposed on the cells, confirmed and placed on the points.

:func:`slipmap.core.breaklines.scan_straight_step` proposes the straight line across which
the cells' motions step most clearly; on the cells alone a fault across a strongly
deforming lobe and a lobe steep on the cells' scale look alike. The points tell them apart.
The spline field is fitted once with the candidate (``windowed_icp``); then, for every point
within ``reach_m`` (a cell) of it:

* the two sides' fields at the point's foot on the candidate differ by the field's jump
  there: where the data are continuous, both sides' fields follow them up to the line and
  meet (on the harness's lobes 1-2 cm), where they step they do not (its fault: 0.1-0.35 m);
* it is moved back by the field of the line's left side and by that of its right side (the
  knots' copies swapped, as :func:`slipmap.core.icp_spline.refine_breaklines` does), and
  its point-to-plane residual against epoch 1 says which side's motion it follows where the
  two residuals differ by more than twice their robust spread (a *decisive* point).

The candidate is dropped when the median jump is below ``min_jump_m`` or reaches it at fewer
than ``min_along_share`` of the stations along the line (the scan proposes lines across the
whole area: a step along a short part of it is the edge test's to find), when some station's
jump exceeds ``max_jump_m`` (the two sides' fields carried over ground the line cuts
wrongly: a straight line through a block that ends inside the area), or when no straight
line puts more than ``1 - max_wrong_share`` of the decisive points on their side. Before the
along-share or the largest-jump test drops it, a candidate is cut to the longest stretch of
consecutive stations that step within those bounds, when that spans
:data:`PLACE_MIN_RUN_STATIONS` cells (stations with data on both sides only), and judged
there: a scarp that ends inside a survey larger than itself, or beyond which one side holds
no points (issue #29, stop 57; on airborne density at a survey's extent the edge test finds
no line and this is the path). Otherwise the line is the straight line, turned by up to
``angle_range_deg`` and shifted by up to ``reach_m``, that puts the fewest decisive points
on the wrong side. ``refine_breaklines`` places a line station by station, judging each
point by the field a cell and a half away, which on a lobe whose motion changes by 0.2 m a
cell differs from the field at the point by as much as a 0.3 m fault (on the harness's
fault it moved the line's west end 6 m off); a straight line fitted to all the decisive
points at once is held by the stretches where the step is clear.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import numpy as np

from .breaklines import Breaklines, distance_m, from_sequence
from .icp_options import MAD_TO_SIGMA
from .icp_spline import nearest_plane_residuals

log = logging.getLogger(__name__)

__all__ = ["StraightPlacement", "place_straight_line"]

#: turns tried about the candidate's direction, degrees (the scan's step is 7.5°)
PLACE_ANGLE_RANGE_DEG = 10.0
PLACE_ANGLE_STEP_DEG = 0.5
#: offsets tried across the candidate (within ``reach_m``)
PLACE_N_OFFSETS = 41
#: the best straight line may leave at most this share of the decisive points on the wrong
#: side (a step seen by the points: a few percent; a lobe's flank: no consistent side)
PLACE_MAX_WRONG_SHARE = 0.25
#: fewest decisive points that confirm a line
PLACE_MIN_DECISIVE = 200
#: the field must jump by ``min_jump_m`` at this share of the stations along the line (every
#: ``reach_m``, those with PLACE_MIN_STATION_POINTS points near the line): the scan proposes
#: a line across the whole area (a fault); a step only along part of it (the side of a block
#: that ends inside the area) is the edge test's to find
PLACE_MIN_ALONG_SHARE = 0.75
PLACE_MIN_STATION_POINTS = 20
#: a candidate that fails the along-share or the largest-jump test is cut to the longest
#: stretch of consecutive stations whose jumps lie between the station floor and
#: ``max_jump_m``, when that spans this many stations (cells) at least, and judged there:
#: the scan proposes a line across the whole area, and a scarp may step along part of it
#: only (where it ends inside the area, or beyond which one side holds no data). Shorter
#: stretches are left to the edge test: on the harness's lobes, steep flanks step by 0.1-0.25
#: m over three stations (15 m) and their points take sides as a scarp's do
PLACE_TRIM = True
PLACE_MIN_RUN_STATIONS = 6


@dataclass(frozen=True)
class StraightPlacement:
    """What the points said about a straight candidate.

    Attributes
    ----------
    line : Breaklines or None
        The placed line; None when the candidate is dropped.
    jump_m : float
        Median jump of the field across the candidate at the points near it, metres.
    n_decisive : int
        Points whose residuals chose a side.
    wrong_share : float
        Share of the decisive points on the wrong side of the placed line (NaN without).
    shift_m : float
        Offset of the placed line from the candidate at the data's middle, metres.
    turn_deg : float
        Its turn from the candidate's direction, degrees.
    cut : bool
        The candidate was cut to the stretch along which the field steps (judged station by
        station along the candidate, before it was turned).
    on_points : Breaklines or None
        The straight line the decisive points place (``line`` where the candidate is
        kept), also where the candidate is dropped on its median jump alone (its stations
        step along ``min_along_share`` of it) while those points take sides along a straight
        line (at most ``max_wrong_share`` on the wrong one); None otherwise.
    """

    line: Optional[Breaklines]
    jump_m: float
    n_decisive: int
    wrong_share: float
    shift_m: float
    turn_deg: float
    cut: bool = False
    on_points: Optional[Breaklines] = None


def _stepping_run(st_med, n_st, n_left, st_min, max_jump_m) -> Optional[Tuple[int, int]]:
    """The longest stretch of consecutive stations along a candidate whose median jump
    ``st_med`` (per station, NaN where it has fewer than PLACE_MIN_STATION_POINTS points)
    lies within ``[st_min, max_jump_m]``, counting only stations with half of those points
    at least on either side (``n_st`` points, ``n_left`` of them left; where a side holds no
    data its field is the penalty's extrapolation, not a motion): ``(first, end)`` station
    numbers, None when it spans fewer than :data:`PLACE_MIN_RUN_STATIONS`."""
    if not PLACE_TRIM or len(n_st) == 0:
        return None
    half = 0.5 * PLACE_MIN_STATION_POINTS
    hi = np.inf if max_jump_m is None else max_jump_m
    with np.errstate(invalid="ignore"):
        good = (n_left >= half) & (n_st - n_left >= half) & (st_med >= st_min) & (st_med <= hi)
    best, i = (0, 0), 0
    while i < len(good):
        j = i
        while j < len(good) and good[j]:
            j += 1
        if j - i > best[1] - best[0]:
            best = (i, j)
        i = j + 1
    if best[1] - best[0] < PLACE_MIN_RUN_STATIONS:
        return None
    return best


def place_straight_line(
    field,
    after: np.ndarray,
    *,
    before: np.ndarray,
    tree,
    normals: Callable[[np.ndarray], np.ndarray],
    gate_m: float,
    reach_m: float,
    min_jump_m: float,
    angle_range_deg: float = PLACE_ANGLE_RANGE_DEG,
    max_wrong_share: float = PLACE_MAX_WRONG_SHARE,
    min_along_share: float = PLACE_MIN_ALONG_SHARE,
    max_jump_m: Optional[float] = None,
    station_jump_m: Optional[float] = None,
) -> StraightPlacement:
    """Confirm and place a straight candidate line on the points (see the module).

    Parameters
    ----------
    field : SplineField
        The spline field fitted with the candidate as its only line (``field.lines``: one
        straight part), best with the points within ``reach_m`` of it left out.
    after : (P, 3) float64
        Epoch-2 points (the frame of the field), metres.
    before, tree, normals, gate_m
        Epoch 1, its nearest-neighbour structure (``tree.query``), the normals of its
        points by index, and the pairs' gate (metres), as in
        :func:`slipmap.core.icp_spline.fit_spline_field`.
    reach_m : float
        How far from the candidate points are looked at and the line may move, metres.
    min_jump_m : float
        Smallest median jump across the candidate that keeps it, metres.
    min_along_share : float
        Share of the stations along the line (every ``reach_m``) whose median jump must
        reach ``station_jump_m``.
    max_jump_m : float, optional
        Largest jump allowed at any station, metres (none: no limit).
    station_jump_m : float, optional
        The jump a station must reach, metres (default ``min_jump_m``).
    angle_range_deg : float
        The line may turn by up to this much from the candidate's direction, degrees.
    max_wrong_share : float
        Largest share of the decisive points the placed line may leave on the wrong side.

    Returns
    -------
    StraightPlacement
    """
    lines = field.lines
    none = StraightPlacement(None, 0.0, 0, float("nan"), 0.0, 0.0)
    if lines is None or lines.empty:
        return none
    part = lines.parts[0]
    e0, e1 = part[0], part[-1]
    t0 = (e1 - e0) / max(float(np.hypot(*(e1 - e0))), 1e-12)
    a = np.asarray(after, dtype=np.float64)
    a = a[distance_m(a, lines) < reach_m]
    if len(a) < PLACE_MIN_DECISIVE:
        log.info("straight breakline dropped: %d points near it", len(a))
        return none
    # each point's motion by the field of either side: its 16 knots, and their copies
    # swapped (copies of the knots that have one; the copy's original for a copy)
    u_own, u_flip = field.both_sides(a[:, :2])
    # the jump at the line: both sides' fields at the foot of each point on the candidate
    foot = e0 + ((a[:, :2] - e0) @ t0)[:, None] * t0
    n0 = np.array([-t0[1], t0[0]])
    eps = 1e-3 * reach_m
    jumps = np.linalg.norm(field(foot + eps * n0) - field(foot - eps * n0), axis=1)
    jump = float(np.median(jumps))
    # ... and along the line, every reach_m (stations with PLACE_MIN_STATION_POINTS points)
    rel = a[:, :2] - e0
    left = (t0[0] * rel[:, 1] - t0[1] * rel[:, 0]) > 0
    ell = rel @ t0
    k_st = np.floor((ell - ell.min()) / reach_m).astype(np.int64)
    n_st = np.bincount(k_st)
    st_med = np.full(len(n_st), np.nan)  # each station's median jump, where it has points
    for k in np.flatnonzero(n_st >= PLACE_MIN_STATION_POINTS):
        st_med[k] = np.median(jumps[k_st == k])
    st_jump = st_med[n_st >= PLACE_MIN_STATION_POINTS]
    st_min = min_jump_m if station_jump_m is None else station_jump_m
    along = float(np.mean(st_jump >= st_min)) if st_jump.size else 0.0
    log.debug("straight breakline: jumps at the stations %s", np.round(st_jump, 3))
    too_big = st_jump.size and max_jump_m is not None and float(st_jump.max()) > max_jump_m
    run = None
    if too_big or along < min_along_share:
        n_left = np.bincount(k_st, weights=left, minlength=len(n_st))
        run = _stepping_run(st_med, n_st, n_left, st_min, max_jump_m)
    if run is not None:
        # the step holds along part of the candidate only (a scarp that ends inside the
        # area, or beyond which a side holds no data, the scan's line reaching across all
        # of it): the candidate is cut to that stretch, and the points there decide
        lo_m, hi_m = ell.min() + run[0] * reach_m, ell.min() + run[1] * reach_m
        inside = (ell >= lo_m) & (ell < hi_m)
        log.info(
            "straight breakline: the field steps along %.0f m of the candidate's %.0f m",
            hi_m - lo_m, float(np.ptp(ell)),
        )  # fmt: skip
        e0, e1 = e0 + lo_m * t0, e0 + hi_m * t0
        a, u_own, u_flip, left, jumps = (v[inside] for v in (a, u_own, u_flip, left, jumps))
        jump, along, too_big = float(np.median(jumps)), 1.0, False
    u_left = np.where(left[:, None], u_own, u_flip)
    u_right = np.where(left[:, None], u_flip, u_own)

    def residual(q):  # |v|, inf where no epoch-1 point within the gate
        v = nearest_plane_residuals(q, before=before, tree=tree, normals=normals, gate_m=gate_m)
        return np.where(np.isnan(v), np.inf, np.abs(v))

    v_l = residual(a - u_left)
    v_r = residual(a - u_right)
    both = np.fmin(v_l, v_r)
    fin = np.isfinite(both)
    spread = MAD_TO_SIGMA * float(np.median(both[fin])) if fin.any() else 0.0
    with np.errstate(invalid="ignore"):
        decisive = fin & (np.abs(v_l - v_r) > 2.0 * spread)
    n_dec = int(decisive.sum())
    if too_big:
        log.info(
            "straight breakline dropped: the field jumps by up to %.3f m across it, more than "
            "the %.3f m the cells allow", float(st_jump.max()), max_jump_m,
        )  # fmt: skip
        return StraightPlacement(None, jump, 0, float("nan"), 0.0, 0.0)
    if n_dec < PLACE_MIN_DECISIVE:
        log.info("straight breakline dropped: %d decisive points", n_dec)
        return StraightPlacement(None, jump, n_dec, float("nan"), 0.0, 0.0)
    side = np.where(v_l[decisive] < v_r[decisive], 1.0, -1.0)  # +1: left
    placed, fewest, off, dt = _best_line(a[decisive, :2], side, e0, e1, reach_m, angle_range_deg)
    share = fewest / n_dec
    turn = float(np.degrees(dt))
    if jump < min_jump_m or along < min_along_share:
        log.info(
            "straight breakline dropped: the field jumps by %.3f m across it (median; "
            "%.3f m needed) and by %.3f m along %.0f %% of it (%.0f %% needed), %d decisive "
            "points (the best straight line on them: turned %.1f°, %.0f %% on the wrong "
            "side)", jump, min_jump_m, st_min, 100.0 * along, 100.0 * min_along_share, n_dec,
            turn, 100.0 * share,
        )  # fmt: skip
        # a step along the line whose median jump fell short (the candidate off the step's
        # direction or beside it, the jumps at the points' feet diluted) keeps its points'
        # line; one along too little of it is a lobe's flank (the harness's lobes: 38-56 %)
        steps = along >= min_along_share and share <= max_wrong_share
        return StraightPlacement(
            None, jump, n_dec, share, off, turn, on_points=placed if steps else None,
        )  # fmt: skip
    if share > max_wrong_share:
        log.info(
            "straight breakline dropped: the best straight line leaves %.0f %% of %d decisive "
            "points on the wrong side", 100.0 * share, n_dec,
        )  # fmt: skip
        return StraightPlacement(None, jump, n_dec, share, 0.0, 0.0)
    log.info(
        "straight breakline placed on %d decisive points (%.1f %% on the wrong side): "
        "shifted %.2f m, turned %.1f°, the field jumps by %.3f m (%.0f %% of its stations)",
        n_dec, 100.0 * share, off, turn, jump, 100.0 * along,
    )  # fmt: skip
    return StraightPlacement(
        placed, jump, n_dec, share, off, turn, cut=run is not None, on_points=placed
    )


def _best_line(p, side, e0, e1, reach_m, angle_range_deg):
    """The straight line, turned by up to ``angle_range_deg`` from the candidate ``e0`` ->
    ``e1`` about the decisive points' middle on it and shifted by up to ``reach_m``, that
    leaves the fewest of the decisive points ``p`` (D, 2) off their ``side`` (D,: +1 left,
    -1 right): ``(line, fewest, shift_m, turn_rad)``, the line as far along as the
    candidate reached; of several best (turn, shift) pairs, the middle one."""
    t0 = (e1 - e0) / max(float(np.hypot(*(e1 - e0))), 1e-12)
    mid = e0 + float(np.median((p - e0) @ t0)) * t0
    th0 = float(np.arctan2(t0[1], t0[0]))
    turns = np.radians(np.arange(-angle_range_deg, angle_range_deg + 1e-9, PLACE_ANGLE_STEP_DEG))
    offsets = np.linspace(-reach_m, reach_m, PLACE_N_OFFSETS)
    rel = p - mid
    wrong = np.empty((len(turns), len(offsets)), dtype=np.int64)
    for i, dt in enumerate(turns):
        n = np.array([-np.sin(th0 + dt), np.cos(th0 + dt)])
        s = rel @ n
        # a point is on the wrong side of the line at offset o when sign(s - o) != side
        wrong[i] = [np.count_nonzero(np.sign(s - o) != side) for o in offsets]
    fewest = int(wrong.min())
    ii, jj = np.nonzero(wrong == fewest)
    k = int(
        np.argmin(
            np.abs(turns[ii] - np.median(turns[ii]))
            + np.abs(offsets[jj] - np.median(offsets[jj])) / max(reach_m, 1e-12)
        )
    )
    dt, off = float(turns[ii[k]]), float(offsets[jj[k]])
    t = np.array([np.cos(th0 + dt), np.sin(th0 + dt)])
    centre = mid + off * np.array([-t[1], t[0]])
    reach_0 = float((e0 - mid) @ t0)
    reach_1 = float((e1 - mid) @ t0)
    placed = from_sequence([np.array([centre + reach_0 * t, centre + reach_1 * t])])
    return placed, fewest, off, dt
