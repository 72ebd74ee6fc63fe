"""Fault slip from two epochs by planar registration on each side of a fault trace.

Kusari et al. (2019), section II.D and IV: per side of the trace (points within a buffer of
it excluded), planes are extracted in both epochs, matched, and a Gauss-Helmert adjustment
gives the rigid motion of that side at its centroid; the relative displacement is right minus
left, with propagated covariance, resolved along and across the fault's strike.

This module holds the joint (one adjustment per side) workflow and the study's refinements
(section IV): square tiles for plane extraction (``estimate_slip(tile_size_m=...)``), strips
along the trace (:func:`strip_profile`, the slip profile of Fig. 5) and moving windows
(:func:`window_field`, the local displacement maps of Fig. 11).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional, Tuple

import numpy as np

from .adjustment import PackedCovariance, RigidResult, adjust_rigid
from .errors import InputDataError, InvalidParameterError
from .fault import FaultTrace, fault_geometry, mean_strike_rad, side_masks, trace_in_data_check
from .matching import PlaneMatches, match_planes
from .planes import PlaneSet, segment_planes
from .progress import ProgressCallback, report, scaled
from .stochastic import (
    DEFAULT_STOCHASTIC_MODEL,
    JointComponents,
    check_components,
    check_random_tilt,
    check_stochastic_model,
    check_units,
    cross_covariance,
    joint_covariance,
)
from .unit_drift import check_unit_time

log = logging.getLogger(__name__)

SIDES = ("left", "right")
COMBINE_MODES = ("joint", "tiles")


def _segment_epoch(points, side: str, epoch: str, **options) -> PlaneSet:
    """:func:`.planes.segment_planes` of one side's points of one epoch; an input error says
    which side and epoch it is about ("right side, after epoch: 0 point(s) given; …")."""
    try:
        return segment_planes(points, quiet=True, **options)
    except InputDataError as exc:
        raise InputDataError(f"{side} side, {epoch} epoch: {exc}") from exc


def strike_axes(strike_rad: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors (3,) of the fault frame: along the strike ``(sin s, cos s, 0)``, normal to
    it towards the right side ``(cos s, -sin s, 0)``, and up ``(0, 0, 1)``."""
    s, c = math.sin(strike_rad), math.cos(strike_rad)
    return np.array([s, c, 0.0]), np.array([c, -s, 0.0]), np.array([0.0, 0.0, 1.0])


def fault_frame(displacement, covariance, strike_rad: float) -> Dict[str, float]:
    """A displacement in the fault frame, with its 1σ.

    Parameters
    ----------
    displacement : (3,) float64
        dx, dy, dz, metres.
    covariance : (3, 3) float64
        Its covariance, m².
    strike_rad : float
        Strike of the trace (clockwise from north), radians.

    Returns
    -------
    dict
        ``fault_parallel``, ``sigma_fault_parallel``, ``fault_normal``, ``sigma_fault_normal``,
        ``dz``, ``sigma_dz`` (metres; NaN where the input is not finite).
    """
    d = np.asarray(displacement, dtype=np.float64)
    c = np.asarray(covariance, dtype=np.float64)
    out: Dict[str, float] = {}
    for name, j in zip(("fault_parallel", "fault_normal", "dz"), strike_axes(strike_rad)):
        v = float(j @ d)
        var = float(j @ c @ j)
        out[name] = v
        out["sigma_" + name] = math.sqrt(max(var, 0.0)) if math.isfinite(var) else math.nan
    return out


@dataclass(frozen=True)
class TileResult:
    """Registration of one square tile of one side (``estimate_slip(tile_size_m=...)``).

    Attributes
    ----------
    side : str
        "left" or "right".
    ix, iy : int
        Tile indices: the tile covers ``[ix * size, (ix + 1) * size)`` in map x and
        ``[iy * size, (iy + 1) * size)`` in map y (metres, the points' CRS).
    bounds : tuple of 4 float
        ``(xmin, ymin, xmax, ymax)`` of the tile, metres.
    n_planes : int
        Matched planes in the tile.
    displacement : (3,) float64
        Motion of the material at the tile's centroid of used points, metres (NaN when the
        tile was not adjusted).
    covariance : (3, 3) float64
        Covariance of ``displacement``, m² (NaN when not adjusted).
    status : str
        "ok", or "skipped: <reason>".
    """

    side: str
    ix: int
    iy: int
    bounds: Tuple[float, float, float, float]
    n_planes: int
    displacement: np.ndarray
    covariance: np.ndarray
    status: str

    @property
    def adjusted(self) -> bool:
        return self.status == "ok"

    def fault_frame(self, strike_rad: float) -> Dict[str, float]:
        """The tile's own motion in the fault frame (:func:`fault_frame`); NaN when the tile
        was not adjusted."""
        if not self.adjusted:
            return {k: math.nan for k in _FRAME_KEYS}
        return fault_frame(self.displacement, self.covariance, strike_rad)


_FRAME_KEYS = (
    "fault_parallel",
    "sigma_fault_parallel",
    "fault_normal",
    "sigma_fault_normal",
    "dz",
    "sigma_dz",
)

#: points enter the adjustment only from octree leaves with at least this share of points on
#: their plane: leaves at edges and corners hold points of the adjoining surface, whose
#: one-sided offsets would bias the plane (a 3-sigma band holds 99.7 % of Gaussian noise)
CLEAN_LEAF_RATIO = 0.97
#: the "full" model with units: planes seen by two units in one epoch tie the units
#: (:mod:`.unit_contrasts`): on by default (docs/accuracy.md, "Units tied on the planes they
#: share")
DEFAULT_UNIT_CONTRASTS = True

#: unmatched planes of each epoch are observed by the other epoch's points (:mod:`.transfer`);
#: on: a sparse airborne epoch beside a mobile one gains the walls it cannot segment (10 pairs:
#: 13.0 / 8.7 / 6.4 -> 7.7 / 4.4 / 5.0 mm, ICP 8.7 / 5.0 / 6.3), and where nothing is
#: transferred (every kind of issue #30's table) nothing changes (docs/accuracy.md,
#: "Transferred planes"); it was off until the robust start's scale weighed each plane's own
#: white part (stochastic._mad_scale)
DEFAULT_TRANSFER_PLANES = True
#: gatherings of the transferred planes' points, each with the motion of the last adjustment
TRANSFER_ROUNDS = 2


@dataclass(frozen=True)
class SideResult:
    """The registration of one side of the fault.

    Attributes
    ----------
    side : str
        "left" or "right" of the digitised trace.
    rigid : RigidResult
        Motion of the side from the first to the second epoch at ``rigid.centre``.
    planes_before, planes_after : PlaneSet
        Planes of the side's points in each epoch (labels index the side's points).
    matches : PlaneMatches
    combined_displacement, combined_covariance : (3,), (3, 3) float64 or None
        With ``combine="tiles"``: the information-weighted mean of the tile displacements and
        its covariance (metres, m²); None otherwise. :attr:`displacement` returns it when set,
        else ``rigid.displacement``.
    plane_mean_residual_m : (P,) float64 or None
        Mean misclosure of each matched plane's after-epoch points, metres.
    before_index, after_index : (K1,), (K2,) int64 or None
        Indices of the side's points into the epochs given to :func:`estimate_slip` (the
        points ``planes_before.labels`` / ``planes_after.labels`` label); None when the
        result was not made from whole arrays (tiled inputs).
    """

    side: str
    rigid: RigidResult
    planes_before: PlaneSet
    planes_after: PlaneSet
    matches: PlaneMatches
    combined_displacement: Optional[np.ndarray] = None
    combined_covariance: Optional[np.ndarray] = None
    plane_mean_residual_m: Optional[np.ndarray] = None
    before_index: Optional[np.ndarray] = None
    after_index: Optional[np.ndarray] = None

    @property
    def displacement(self) -> np.ndarray:
        """(3,) displacement of the side used for the slip, metres."""
        if self.combined_displacement is not None:
            return np.array(self.combined_displacement, dtype=np.float64)
        return self.rigid.displacement

    @property
    def displacement_covariance(self) -> np.ndarray:
        """(3, 3) covariance of :attr:`displacement`, m²."""
        if self.combined_covariance is not None:
            return np.array(self.combined_covariance, dtype=np.float64)
        return self.rigid.displacement_covariance

    def to_dict(self) -> Dict[str, object]:
        r = self.rigid
        d, s = self.displacement, np.sqrt(np.diag(self.displacement_covariance))
        return {
            "dx": float(d[0]),
            "dy": float(d[1]),
            "dz": float(d[2]),
            "sigma_dx": float(s[0]),
            "sigma_dy": float(s[1]),
            "sigma_dz": float(s[2]),
            "rx": float(r.params[0]),
            "ry": float(r.params[1]),
            "rz": float(r.params[2]),
            "centroid": [float(v) for v in r.centre],
            "n_planes": int(r.n_planes),
            "n_points": int(r.n_points),
            "variance_factor": float(r.variance_factor),
            "iterations": int(r.iterations),
            "rejected_planes": [
                {"plane": int(p), "reason": str(why)} for p, why in r.rejected_planes
            ],
            "weak_directions": list(r.weak_directions),
            "stochastic_model": r.stochastic_model,
            **_stochastic_dict(r),
        }


def _stochastic_dict(r: RigidResult) -> Dict[str, object]:
    """The variance components and down-weighted planes of a side (stochastic models)."""
    vc = r.variance_components
    if vc is None:
        return {}
    return {
        "variance_components": vc.to_dict(),
        "sigma_white_dx": float(vc.sigma_white_m[0]),
        "sigma_white_dy": float(vc.sigma_white_m[1]),
        "sigma_white_dz": float(vc.sigma_white_m[2]),
        "downweighted_planes": [
            {
                "plane": int(p),
                "weight": float(w),
                "reason": "IGG-III: |w| between the down-weighting and rejection limits",
            }
            for p, w in r.downweighted_planes
        ],  # fmt: skip
    }


@dataclass(frozen=True)
class SlipResult:
    """Relative displacement across a fault (right side minus left side), metres.

    ``fault_parallel`` is the component along the trace's digitised direction (unit vector
    ``(sin strike, cos strike)``), ``fault_normal`` along the direction 90° clockwise from it
    (towards the right side); ``right_lateral_slip = -fault_parallel`` is positive for dextral
    motion. Sigmas are 1σ of :attr:`relative_covariance`, ``C_R + C_L − C_RL − C_RLᵀ`` from
    the two sides' a-posteriori covariances and their cross-covariance ``C_RL`` (see
    :func:`relative_covariance`): under the "full" model the survey error that crosses the
    trace (a spatial drift, acquisition units of both sides) is shared and cancels in the
    difference; under the "white" and "plane" models, and for ``combine="tiles"``, the sides
    are independent (``C_RL = 0``). ``tiles`` holds the per-tile registrations when
    ``tile_size_m`` was given (else empty).

    Attributes
    ----------
    side_cross_covariance : (3, 3) float64 or None
        ``C_RL = Cov(d_right, d_left)``, m², when it was modelled (else None: independent).
    joint_components : JointComponents or None
        The plane-level components estimated on both sides' planes together, which the
        relative covariance is under (None: each side's own; see :func:`relative_covariance`).
    """

    left: SideResult
    right: SideResult
    relative: np.ndarray
    relative_covariance: np.ndarray
    strike_rad: float
    buffer_m: float
    parameters: Dict[str, object] = field(default_factory=dict)
    tiles: Tuple[TileResult, ...] = ()
    side_cross_covariance: Optional[np.ndarray] = None
    joint_components: Optional[JointComponents] = None

    @property
    def horizontal(self) -> float:
        return float(math.hypot(self.relative[0], self.relative[1]))

    def _component(self, j: np.ndarray):
        value = float(j @ self.relative)
        return value, float(math.sqrt(max(j @ self.relative_covariance @ j, 0.0)))

    def components(self) -> Dict[str, float]:
        s = math.sin(self.strike_rad), math.cos(self.strike_rad)
        par, s_par = self._component(np.array([s[0], s[1], 0.0]))
        nor, s_nor = self._component(np.array([s[1], -s[0], 0.0]))
        h = self.horizontal
        if h > 0:
            _, s_h = self._component(np.array([self.relative[0] / h, self.relative[1] / h, 0.0]))
        else:
            s_h = float(math.sqrt(max(np.trace(self.relative_covariance[:2, :2]) / 2, 0.0)))
        sig = np.sqrt(np.diag(self.relative_covariance))
        white = self.relative_covariance_white
        extra: Dict[str, float] = {}
        if white is not None:
            jp = np.array([s[0], s[1], 0.0])
            extra = {
                "sigma_fault_parallel_white": float(math.sqrt(max(jp @ white @ jp, 0.0))),
                "sigma_dz_white": float(math.sqrt(max(white[2, 2], 0.0))),
            }
        return {
            "dx": float(self.relative[0]),
            "dy": float(self.relative[1]),
            "dz": float(self.relative[2]),
            "sigma_dx": float(sig[0]),
            "sigma_dy": float(sig[1]),
            "sigma_dz": float(sig[2]),
            "horizontal": h,
            "sigma_horizontal": s_h,
            "fault_parallel": par,
            "sigma_fault_parallel": s_par,
            "fault_normal": nor,
            "sigma_fault_normal": s_nor,
            "right_lateral_slip": -par,
            **extra,
        }

    @property
    def relative_covariance_white(self) -> Optional[np.ndarray]:
        """(3, 3) covariance of :attr:`relative` under the white model (m²), or None when the
        white model was the one used (then it is :attr:`relative_covariance`)."""
        vl = self.left.rigid.variance_components
        vr = self.right.rigid.variance_components
        if vl is None or vr is None:
            return None
        return vl.covariance_white + vr.covariance_white

    def reference_comparison(self, reference_slip_m: float) -> Dict[str, float]:
        """The study's Table X figures against an independent slip (e.g. an alinement array).

        ``reference_slip_m`` is right-lateral slip (positive dextral), metres. Returns
        ``delta_displacement`` ΔD = right_lateral_slip − reference, the relative displacement's
        ``sigma_x, sigma_y, sigma_z``, ``scale`` = (|ΔD|/√2) / √(σx² + σy² + σz²),
        ``variance_left``/``variance_right`` (σ0² of each side) and ``relative_scale`` =
        (|ΔD|/2) / (σ0² √(σx² + σy² + σz²)) with σ0² the mean of the two sides' — as in Table
        X, where a reasonable accuracy estimate gives a scale near 0.68.
        """
        comp = self.components()
        delta = comp["right_lateral_slip"] - float(reference_slip_m)
        norm = math.sqrt(comp["sigma_dx"] ** 2 + comp["sigma_dy"] ** 2 + comp["sigma_dz"] ** 2)
        vl, vr = self.left.rigid.variance_factor, self.right.rigid.variance_factor
        s0 = 0.5 * (vl + vr)
        return {
            "reference_slip": float(reference_slip_m),
            "delta_displacement": delta,
            "sigma_x": comp["sigma_dx"],
            "sigma_y": comp["sigma_dy"],
            "sigma_z": comp["sigma_dz"],
            "scale": abs(delta) / math.sqrt(2.0) / norm if norm > 0 else float("inf"),
            "variance_left": float(vl),
            "variance_right": float(vr),
            "relative_scale": abs(delta) / 2.0 / (s0 * norm) if norm > 0 else float("inf"),
        }

    def point_planes(self, points: np.ndarray, epoch: str) -> Tuple[np.ndarray, np.ndarray]:
        """Each point's plane and signed distance to it, for one epoch.

        Parameters
        ----------
        points : (N, 3) float64
            The epoch's points as given to :func:`estimate_slip`, metres.
        epoch : {"before", "after"}

        Returns
        -------
        labels : (N,) int32
            The point's plane in its side's segmentation of this epoch (ids per side and
            epoch: both sides start at 0); -1 for points in no plane or inside the buffer.
        residual : (N,) float64
            Signed orthogonal distance ``n . p + d`` to that plane, metres; NaN where the
            label is -1.

        Raises
        ------
        InvalidParameterError
            ``epoch`` is neither, or the result holds no point indices (tiled inputs).
        """
        if epoch not in ("before", "after"):
            raise InvalidParameterError(f"epoch must be 'before' or 'after', got {epoch!r}")
        pts = np.asarray(points, dtype=np.float64)
        n = pts.shape[0]
        labels = np.full(n, -1, dtype=np.int32)
        residual = np.full(n, np.nan)
        for side in (self.left, self.right):
            ix = getattr(side, f"{epoch}_index")
            ps = getattr(side, f"planes_{epoch}")
            if ix is None:
                raise InvalidParameterError(
                    "this slip result holds no per-point indices (tiled inputs)"
                )
            lab = np.asarray(ps.labels, dtype=np.int32)
            labels[ix] = lab
            on = lab >= 0
            k = lab[on]
            residual[ix[on]] = np.einsum("ij,ij->i", pts[ix[on]], ps.normals[k]) + ps.offsets[k]
        return labels, residual

    def to_dict(self) -> Dict[str, object]:
        return {
            "left": self.left.to_dict(),
            "right": self.right.to_dict(),
            "relative": self.components(),
            "fault": {
                "strike_deg": float(math.degrees(self.strike_rad) % 360.0),
                "buffer_m": float(self.buffer_m),
            },
            "parameters": dict(self.parameters),
            **(
                {"tiles": [_tile_dict(t, self.strike_rad) for t in self.tiles]}
                if self.tiles
                else {}
            ),
            **(
                {"joint_components": self.joint_components.to_dict()}
                if self.joint_components is not None
                else {}
            ),
            "note": "displacements in metres, rotations in radians; each side's displacement "
            "is the motion of the material at that side's centroid (first to second epoch)",
        }


def _tile_dict(t: TileResult, strike_rad: float) -> Dict[str, object]:
    adjusted = t.status == "ok"
    sig = np.sqrt(np.diag(t.covariance)) if adjusted else np.full(3, np.nan)
    frame = t.fault_frame(strike_rad)
    return {
        "side": t.side,
        "ix": int(t.ix),
        "iy": int(t.iy),
        "bounds": [float(v) for v in t.bounds],
        "n_planes": int(t.n_planes),
        "dx": float(t.displacement[0]) if adjusted else None,
        "dy": float(t.displacement[1]) if adjusted else None,
        "dz": float(t.displacement[2]) if adjusted else None,
        "sigma_dx": float(sig[0]) if adjusted else None,
        "sigma_dy": float(sig[1]) if adjusted else None,
        "sigma_dz": float(sig[2]) if adjusted else None,
        "fault_parallel": frame["fault_parallel"] if adjusted else None,
        "sigma_fault_parallel": frame["sigma_fault_parallel"] if adjusted else None,
        "fault_normal": frame["fault_normal"] if adjusted else None,
        "sigma_fault_normal": frame["sigma_fault_normal"] if adjusted else None,
        "status": t.status,
    }


def _labels_for_matches(labels: np.ndarray, plane_ids: np.ndarray) -> np.ndarray:
    """Map plane labels to match indices (-1 for unmatched planes)."""
    lut = np.full(int(labels.max(initial=-1)) + 2, -1, dtype=np.int64)
    lut[plane_ids] = np.arange(plane_ids.size)
    return lut[labels]  # label -1 maps to the last entry, which stays -1


def register_side(
    before: np.ndarray,
    after: np.ndarray,
    *,
    side: str,
    sigma_before=0.05,
    sigma_after=0.05,
    plane_options: Optional[dict] = None,
    match_options: Optional[dict] = None,
    progress: Optional[ProgressCallback] = None,
    stochastic: Optional[dict] = None,
    transfer_planes: bool = DEFAULT_TRANSFER_PLANES,
    planes: Optional[Tuple[PlaneSet, PlaneSet]] = None,
) -> SideResult:
    """Planes, matches and the rigid adjustment for the points of one side.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The side's points in each epoch (metres).
    sigma_before, sigma_after
        Point accuracy: scalar, (3,) per axis, or (N, 3, 3) per point (metres).
    stochastic : dict, optional
        ``stochastic_model``, ``unit_before``/``unit_after`` ((N1,), (N2,) acquisition units of
        the side's points) and ``components`` for :func:`.adjustment.adjust_rigid`.
    transfer_planes : bool
        Also adjust the unmatched planes of each epoch observed by the other epoch's points
        (:mod:`.transfer`; :func:`_with_transferred`).
    planes : (PlaneSet, PlaneSet), optional
        The side's planes of each epoch when already segmented (:func:`_segment_side`).
    """
    pb, pa = (
        planes
        if planes is not None
        else _segment_side(before, after, side=side, plane_options=plane_options, progress=progress)
    )
    m = match_planes(pb, pa, quiet=True, **(match_options or {}))
    log.info("%s", side_summary(side, pb, pa, len(m)))
    if len(m) < 3:
        raise InputDataError(
            f"{side} side: only {len(m)} matched planes (need at least 3 with several "
            "orientations); check that the epochs overlap on this side, or relax the matching "
            "thresholds"
        )
    lb = _labels_for_matches(pb.labels, m.before)
    la = _labels_for_matches(pa.labels, m.after)

    rigid, mean_res = _adjust_labelled(
        before, lb, after, la, sigma_before, sigma_after, pb.planarity, pa.planarity, stochastic
    )
    if transfer_planes:
        report(progress, 0.85, f"{side} side: transferred planes")
        pb, pa, m, rigid, mean_res = _with_transferred(
            before, after, pb, pa, m, rigid, mean_res, sigma_before, sigma_after, stochastic,
            side=side, angle_threshold_deg=(match_options or {}).get("angle_threshold_deg", 3.0),
        )  # fmt: skip
    report(progress, 1.0, f"{side} side done")
    return SideResult(
        side=side,
        rigid=rigid,
        planes_before=pb,
        planes_after=pa,
        matches=m,
        plane_mean_residual_m=mean_res,
    )


def _segment_side(before, after, *, side, plane_options=None, progress=None):
    """The planes (PlaneSet, PlaneSet) of one side's two epochs."""
    opts = dict(plane_options or {})
    pb = _segment_epoch(before, side, "before", progress=scaled(progress, 0.0, 0.35), **opts)
    pa = _segment_epoch(after, side, "after", progress=scaled(progress, 0.35, 0.7), **opts)
    return pb, pa


def _survey_contrasts(sides, stochastic):
    """Each epoch's within-epoch unit contrasts over every plane found on both sides
    (:func:`.unit_contrasts.unit_contrasts` on the clean planar points of each side,
    joined): what ties the acquisition units across the fault (an ALS strip's overlaps with
    its neighbours, a pass seen on a wall from two streets). ``sides``: per side the points
    (before, after), their index into the epochs and their planes (pb, pa). None without
    the "full" model and units."""
    from .unit_contrasts import concat_contrasts, screen_contrasts, unit_contrasts

    st = stochastic or {}
    if st.get("stochastic_model") != "full":
        return None
    out = []
    for e, name in enumerate(("before", "after")):
        unit, time = st.get(f"unit_{name}"), st.get(f"unit_time_{name}")
        if unit is None:
            out.append(None)
            continue
        parts = []
        for pts, index, planes in sides:
            ps = planes[e]
            keep = (ps.labels >= 0) & (np.asarray(ps.planarity) >= CLEAN_LEAF_RATIO)
            rows = index[e][keep]
            parts.append(
                unit_contrasts(
                    ps.labels[keep].astype(np.int64),
                    pts[e][keep],
                    np.asarray(unit)[rows].astype(np.int64),
                    int(ps.normals.shape[0]),
                    time_s=None if time is None else np.asarray(time)[rows],
                )  # fmt: skip
            )
        out.append(screen_contrasts(concat_contrasts(parts)))
    return tuple(out) if any(c is not None for c in out) else None


class _Rows:
    """Rows of a per-point sigma array, selected lazily: masks compose on the index and the
    one gather happens when the adjustment converts it with ``np.asarray``."""

    def __init__(self, base: np.ndarray, idx: np.ndarray):
        self.base, self.idx = base, idx

    @property
    def shape(self):
        return (self.idx.size,) + self.base.shape[1:]

    @property
    def ndim(self):
        return self.base.ndim

    def __array__(self, dtype=None, copy=None):
        out = np.take(self.base, self.idx, axis=0)
        return out if dtype is None else out.astype(dtype, copy=False)


def _packed(sig, name: str):
    """Per-point covariances ((N, 3, 3) or (N, 6)) validated and packed once; others pass."""
    if isinstance(sig, (PackedCovariance, _Rows)):
        return sig
    a = np.asarray(sig)
    if a.ndim == 3 or (a.ndim == 2 and a.shape[1] == 6):
        return PackedCovariance.from_array(a, name=name)
    return sig


def _per_point(sig, mask: np.ndarray):
    """Subset per-point sigmas ((N, 3), (N, 3, 3), (N, 6) or packed) with ``mask``; scalars
    and (3,) per-axis sigmas pass."""
    if isinstance(sig, PackedCovariance):
        return sig.take(mask)
    if isinstance(sig, _Rows):
        return _Rows(sig.base, sig.idx[mask])
    a = np.asarray(sig, dtype=np.float64)
    if a.ndim == 3 or (a.ndim == 2 and a.shape[1] == 6):
        return PackedCovariance.from_array(a).take(mask)
    if a.ndim == 2 and a.shape[0] == mask.shape[0]:
        return _Rows(a, np.flatnonzero(mask) if mask.dtype == bool else np.asarray(mask))
    return a


def _check_epochs(before: np.ndarray, after: np.ndarray) -> None:
    for name, arr in (("before", before), ("after", after)):
        a = np.asarray(arr)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
            raise InputDataError(f"{name} must be a non-empty (N, 3) point array, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputDataError(f"{name} contains NaN or infinite coordinates; remove them")
    lo = np.array([max(before[:, a].min(), after[:, a].min()) for a in range(2)])
    hi = np.array([min(before[:, a].max(), after[:, a].max()) for a in range(2)])
    if np.any(lo >= hi):
        raise InputDataError("the two epochs do not overlap in plan; check their CRSs and extents")


def _positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"{name} must be a positive number (metres), got {value!r}"
        ) from None
    if not (math.isfinite(v) and v > 0):
        raise InvalidParameterError(f"{name} must be a positive number (metres), got {value!r}")
    return v


def _stochastic_kw(stochastic: Optional[dict]) -> dict:
    """adjust_rigid's stochastic-model keywords from the options of a run or subset."""
    st = dict(stochastic or {})
    return {
        "stochastic_model": st.get("stochastic_model", DEFAULT_STOCHASTIC_MODEL),
        "components": st.get("components"),
        "unit_before": st.get("unit_before"),
        "unit_after": st.get("unit_after"),
        "random_tilt": st.get("random_tilt"),
        "unit_time_before": st.get("unit_time_before"),
        "unit_time_after": st.get("unit_time_after"),
        "unit_contrasts": st.get("unit_contrasts"),
    }


def _sub_stochastic(stochastic: Optional[dict], mb, ma, components=None) -> dict:
    """The stochastic options of a subset of points (masks or indices ``mb``, ``ma``)."""
    st = dict(stochastic or {})
    for name, m in (("unit_before", mb), ("unit_after", ma), ("unit_time_before", mb),
                    ("unit_time_after", ma)):  # fmt: skip
        if st.get(name) is not None:
            st[name] = np.asarray(st[name])[m]
    if components is not None:
        st["components"] = components
    return st


def _adjust_labelled(
    before, lb, after, la, sigma_before, sigma_after, planarity_before, planarity_after,
    stochastic=None, force_before=None, force_after=None,
) -> Tuple[RigidResult, np.ndarray]:  # fmt: skip
    """adjust_rigid on the labelled points (labels = match indices) of clean planar leaves
    (see CLEAN_LEAF_RATIO) and the points ``force_*`` (gathered on transferred planes); also
    returns the mean after-epoch misclosure per match (metres)."""
    kb = (lb >= 0) & (planarity_before >= CLEAN_LEAF_RATIO)
    ka = (la >= 0) & (planarity_after >= CLEAN_LEAF_RATIO)
    if force_before is not None:
        kb |= (lb >= 0) & force_before
    if force_after is not None:
        ka |= (la >= 0) & force_after
    rigid = adjust_rigid(
        before[kb],
        lb[kb],
        after[ka],
        la[ka],
        sigma_before=_per_point(sigma_before, kb),
        sigma_after=_per_point(sigma_after, ka),
        **_stochastic_kw(_sub_stochastic(stochastic, kb, ka)),
    )
    r = rigid.residuals_after
    ok = np.isfinite(r)
    idx = la[ka][ok]
    size = int(max(lb.max(initial=-1), la.max(initial=-1))) + 1
    n = np.bincount(idx, minlength=size).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_res = np.bincount(idx, weights=r[ok], minlength=size) / n
    return rigid, mean_res


def _with_transferred(
    before, after, pb, pa, m, rigid, mean_res, sigma_before, sigma_after, stochastic, *,
    side, angle_threshold_deg,
):  # fmt: skip
    """The side's adjustment with transferred planes (:func:`.transfer.transfer_unmatched`):
    the unmatched planes of each epoch observed by the other epoch's free points after the
    motion ``rigid``, adjusted with the matched pairs; gathered again with the new motion
    until the gathered points repeat (at most :data:`TRANSFER_ROUNDS` rounds). Returns the
    planes, pairs, adjustment and mean misclosures; the given ones when nothing is gathered
    or the adjustment with transferred planes fails."""
    from .rotation import rotation_matrix
    from .transfer import transfer_unmatched

    clean_b = np.asarray(pb.planarity) >= CLEAN_LEAF_RATIO
    clean_a = np.asarray(pa.planarity) >= CLEAN_LEAF_RATIO
    best = (pb, pa, m, rigid, mean_res)
    seen = None
    for _ in range(TRANSFER_ROUNDS):
        cur = best[3]
        out = transfer_unmatched(
            before, after, pb, pa, m,
            rotation=rotation_matrix(cur.params[:3]), translation=cur.params[3:],
            centre=cur.centre, source_before=clean_b, source_after=clean_a,
            angle_threshold_deg=angle_threshold_deg,
        )  # fmt: skip
        key = (np.flatnonzero(out.gathered_before), np.flatnonzero(out.gathered_after))
        if out.matches.n_transferred == 0 or (
            seen is not None and all(np.array_equal(a, b) for a, b in zip(key, seen))
        ):
            break
        seen = key
        lb = _labels_for_matches(out.planes_before.labels, out.matches.before)
        la = _labels_for_matches(out.planes_after.labels, out.matches.after)
        try:
            r2, mr2 = _adjust_labelled(
                before, lb, after, la, sigma_before, sigma_after, pb.planarity, pa.planarity,
                stochastic, force_before=out.gathered_before, force_after=out.gathered_after,
            )  # fmt: skip
        except InputDataError as exc:  # keep the matched planes' adjustment
            log.warning("%s side: transferred planes not used (%s)", side, exc)
            break
        best = (out.planes_before, out.planes_after, out.matches, r2, mr2)
    if best[2] is not m:
        k = best[2].kind
        log.info(
            "%s side: %d transferred planes (%d first-epoch planes observed by second-epoch "
            "points, %d the other way)",
            side, int(np.count_nonzero(k)), int((k == 1).sum()), int((k == 2).sum()),
        )  # fmt: skip
    return best


def side_summary(side: str, pb: PlaneSet, pa: PlaneSet, n_matched: int, tiles: str = "") -> str:
    """The one log line of a side: planes per epoch, matched pairs, and the scales the
    segmentation estimated (point spacing, noise, leaf; before / after epoch), e.g.
    ``left side: 22 planes before, 22 after, 22 matched (point spacing 0.106 / 0.118 m,
    noise 18.7 / 18.5 mm, leaf 0.757 / 0.746 m)``; ``tiles`` (``"3 tiles of 50 m, "``) is put
    after the side."""
    text = f"{side} side: {tiles}{len(pb)} planes before, {len(pa)} after, {n_matched} matched"
    p, q = pb.parameters, pa.parameters
    if p is not None and q is not None and not tiles:
        text += (
            f" (point spacing {p.point_spacing_m:.3g} / {q.point_spacing_m:.3g} m, noise "
            f"{1e3 * p.noise_m:.3g} / {1e3 * q.noise_m:.3g} mm, leaf {p.min_node_size_m:.3g} / "
            f"{q.min_node_size_m:.3g} m)"
        )
    return text


def _skip_reason(status: str) -> str:
    """A skipped tile's reason in a few words (for the side's log line)."""
    if status.startswith("skipped: no planes"):
        return "no planes"
    if "matched planes (need 3)" in status:
        return "fewer than 3 matched planes"
    return "no regular adjustment"


def skipped_text(statuses) -> str:
    """``2 skipped: 1 with no planes, 1 with fewer than 3 matched planes`` ("" when none)."""
    counts: Dict[str, int] = {}
    for st in statuses:
        if st != "ok":
            why = _skip_reason(st)
            counts[why] = counts.get(why, 0) + 1
    if not counts:
        return ""
    parts = ", ".join(f"{n} with {why}" for why, n in counts.items())
    return f"{sum(counts.values())} skipped: {parts}"


def _merge_planesets(parts, n_points: int) -> PlaneSet:
    """One PlaneSet for a side from per-tile PlaneSets ``[(point_index, PlaneSet), ...]``."""
    labels = np.full(n_points, -1, dtype=np.int32)
    planarity = np.full(n_points, np.nan, dtype=np.float32)
    off = 0
    arrays: Dict[str, List[np.ndarray]] = {
        k: []
        for k in (
            "normals",
            "offsets",
            "centroids",
            "n_points",
            "rms",
            "covariances",
            "extent_min",
            "extent_max",
        )
    }
    params = None
    n_leaves = n_planar = 0
    for idx, ps in parts:
        lab = ps.labels.astype(np.int64)
        labels[idx] = np.where(lab >= 0, lab + off, -1)
        planarity[idx] = ps.planarity
        for k in arrays:
            arrays[k].append(np.asarray(getattr(ps, k)))
        params = params or ps.parameters
        n_leaves += ps.n_leaves
        n_planar += ps.n_planar_leaves
        off += len(ps)
    empty = {
        "normals": (0, 3),
        "offsets": (0,),
        "centroids": (0, 3),
        "n_points": (0,),
        "rms": (0,),
        "covariances": (0, 3, 3),
        "extent_min": (0, 3),
        "extent_max": (0, 3),
    }
    cat = {
        k: (np.concatenate(v) if v else np.zeros(empty[k], dtype=np.float64))
        for k, v in arrays.items()
    }
    if params is None:
        raise InputDataError("no tile had enough points to extract planes")
    return PlaneSet(
        **cat,
        labels=labels,
        planarity=planarity,
        parameters=params,
        n_leaves=n_leaves,
        n_planar_leaves=n_planar,
    )


def _register_side_tiled(
    before: np.ndarray,
    after: np.ndarray,
    *,
    side: str,
    tile_size_m: float,
    combine: str,
    sigma_before,
    sigma_after,
    plane_options: Optional[dict],
    match_options: Optional[dict],
    progress: Optional[ProgressCallback],
    stochastic: Optional[dict] = None,
) -> Tuple[SideResult, Tuple[TileResult, ...]]:
    """Tiled plane extraction and matching; joint or per-tile-combined adjustment.

    The joint adjustment runs first; with a stochastic model each tile then holds the side's
    estimated plane-level components fixed (a tile has too few planes to estimate them)."""
    opts = dict(plane_options or {})
    t = tile_size_m
    kb = np.floor(before[:, :2] / t).astype(np.int64)
    ka = np.floor(after[:, :2] / t).astype(np.int64)
    keys, inv = np.unique(np.concatenate([kb, ka]), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    # each tile's points by one sort (a mask over all points per tile was O(tiles x points))
    nt = keys.shape[0]
    inv_b, inv_a = inv[: kb.shape[0]], inv[kb.shape[0] :]
    ob, oa = np.argsort(inv_b, kind="stable"), np.argsort(inv_a, kind="stable")
    sb = np.searchsorted(inv_b[ob], np.arange(nt + 1))
    sa = np.searchsorted(inv_a[oa], np.arange(nt + 1))
    lb = np.full(before.shape[0], -1, dtype=np.int64)  # global match index per point
    la = np.full(after.shape[0], -1, dtype=np.int64)
    parts_b, parts_a = [], []
    mb_ids, ma_ids, m_ang, m_dist = [], [], [], []
    off_b = off_a = 0
    n_matched = 0
    tile_info = []  # (ix, iy, first match id, n matches, status)
    for n, (ix, iy) in enumerate(keys):
        ib = ob[sb[n] : sb[n + 1]]  # ascending, as np.flatnonzero of the tile's mask
        ia = oa[sa[n] : sa[n + 1]]
        status = "ok"
        k = 0
        try:
            if ib.size < 3 or ia.size < 3:
                raise InputDataError(f"{ib.size} / {ia.size} points in the two epochs")
            pb = segment_planes(before[ib], quiet=True, **opts)
            pa = segment_planes(after[ia], quiet=True, **opts)
        except InputDataError as exc:
            status = f"skipped: no planes ({exc})"
        else:
            m = match_planes(pb, pa, quiet=True, **(match_options or {}))
            k = len(m)
            parts_b.append((ib, pb))
            parts_a.append((ia, pa))
            lbt = _labels_for_matches(pb.labels, m.before)
            lat = _labels_for_matches(pa.labels, m.after)
            lb[ib] = np.where(lbt >= 0, lbt + n_matched, -1)
            la[ia] = np.where(lat >= 0, lat + n_matched, -1)
            mb_ids.append(m.before + off_b)
            ma_ids.append(m.after + off_a)
            m_ang.append(m.angle_rad)
            m_dist.append(m.distance_m)
            off_b += len(pb)
            off_a += len(pa)
        tile_info.append((int(ix), int(iy), n_matched, k, status))
        n_matched += k
        report(progress, 0.7 * (n + 1) / len(keys), f"{side} side: tile {n + 1}/{len(keys)}")
    pb_all = _merge_planesets(parts_b, before.shape[0])
    pa_all = _merge_planesets(parts_a, after.shape[0])

    def cat(v, dt):
        return np.concatenate(v).astype(dt) if v else np.zeros(0, dtype=dt)

    matches = PlaneMatches(
        before=cat(mb_ids, np.int64),
        after=cat(ma_ids, np.int64),
        angle_rad=cat(m_ang, np.float64),
        distance_m=cat(m_dist, np.float64),
    )
    log.debug(
        "%s", side_summary(side, pb_all, pa_all, len(matches), f"{len(keys)} tiles of {t:g} m, ")
    )  # the side's INFO line comes with the tiles' adjustments (tile_adjustments)

    # only points of clean planar leaves enter the adjustments (see CLEAN_LEAF_RATIO)
    lb = np.where(pb_all.planarity >= CLEAN_LEAF_RATIO, lb, -1)
    la = np.where(pa_all.planarity >= CLEAN_LEAF_RATIO, la, -1)

    if len(matches) < 3:
        raise InputDataError(
            f"{side} side: only {len(matches)} matched planes over all tiles of {t:g} m "
            "(need at least 3); use bigger tiles or relax the matching thresholds"
        )
    rigid, mean_res = _adjust_labelled(
        before, lb, after, la, sigma_before, sigma_after, pb_all.planarity, pa_all.planarity,
        stochastic,
    )  # fmt: skip
    vc = rigid.variance_components
    tile_fixed = vc.fixed() if vc is not None else None

    def adjust_tile(first, k):
        sb = (lb >= first) & (lb < first + k)
        sa = (la >= first) & (la < first + k)
        return adjust_rigid(
            before[sb],
            lb[sb] - first,
            after[sa],
            la[sa] - first,
            sigma_before=_per_point(sigma_before, sb),
            sigma_after=_per_point(sigma_after, sa),
            **_stochastic_kw(_sub_stochastic(stochastic, sb, sa, tile_fixed)),
        )

    tiles, comb_d, comb_c = tile_adjustments(
        tile_info, adjust_tile, side=side, tile_size_m=t, combine=combine, joint=rigid
    )
    report(progress, 1.0, f"{side} side done")
    res = SideResult(
        side=side,
        rigid=rigid,
        planes_before=pb_all,
        planes_after=pa_all,
        matches=matches,
        combined_displacement=comb_d,
        combined_covariance=comb_c,
        plane_mean_residual_m=mean_res,
    )
    return res, tuple(tiles)


def tile_adjustments(tile_info, adjust_tile, *, side, tile_size_m, combine, joint):
    """Per-tile adjustments of one side and, with ``combine="tiles"``, their combination.

    ``tile_info``: ``[(ix, iy, first match id, n matches, status), ...]``;
    ``adjust_tile(first, k)`` returns the :class:`RigidResult` of the tile's matches
    ``first .. first + k - 1`` (with the side's components fixed) or raises InputDataError.
    ``joint`` is the side's joint adjustment. Returns ``(tiles, combined displacement or None,
    combined covariance or None)``. Shared by the in-memory tiles and the tiled reading of
    :mod:`slipmap.app.tiled`.
    """
    t = tile_size_m
    vc = joint.variance_components
    # per-tile adjustments (reporting for "joint", the estimate for "tiles")
    tiles: List[TileResult] = []
    nan3, nan33 = np.full(3, np.nan), np.full((3, 3), np.nan)
    n_skipped = 0
    for ix, iy, first, k, status in tile_info:
        d, c = nan3, nan33
        if status == "ok":
            if k < 3:
                status = f"skipped: {k} matched planes (need 3)"
            else:
                try:
                    r = adjust_tile(first, k)
                    d, c = r.displacement, r.displacement_covariance
                    if not np.all(np.isfinite(c)) or np.linalg.matrix_rank(c) < 3:
                        raise InputDataError("singular displacement covariance")
                except InputDataError as exc:
                    d, c = nan3, nan33
                    status = f"skipped: {exc}"
        if status != "ok":
            n_skipped += 1
        tiles.append(
            TileResult(
                side=side,
                ix=ix,
                iy=iy,
                bounds=(ix * t, iy * t, (ix + 1) * t, (iy + 1) * t),
                n_planes=int(k),
                displacement=np.asarray(d, dtype=np.float64),
                covariance=np.asarray(c, dtype=np.float64),
                status=status,
            )
        )
    skipped = skipped_text(x.status for x in tiles)
    log.info(
        "%s side: %d tiles of %g m, %d matched planes; %d adjusted%s",
        side,
        len(tiles),
        t,
        sum(int(x.n_planes) for x in tiles),
        len(tiles) - n_skipped,
        f", {skipped}" if skipped else "",
    )

    comb_d = comb_c = None
    if combine == "tiles":
        ok = [x for x in tiles if x.status == "ok"]
        if not ok:
            raise InputDataError(
                f"{side} side: no tile of {t:g} m has 3 matched planes and a regular "
                'adjustment; use bigger tiles or combine="joint"'
            )
        info = np.zeros((3, 3))
        vec = np.zeros(3)
        for x in ok:
            w = np.linalg.inv(x.covariance)
            info += w
            vec += w @ x.displacement
        comb_c = np.linalg.inv(info)
        comb_c = 0.5 * (comb_c + comb_c.T)
        comb_d = comb_c @ vec
        if vc is not None:
            comb_c = _honest_tile_covariance(ok, comb_d, comb_c, joint.displacement_covariance)
        log.info("%s side: %d tiles combined", side, len(ok))
    return tuple(tiles), comb_d, comb_c


def _honest_tile_covariance(tiles, mean, cov, joint_cov):
    """Covariance of the tiles' information-weighted mean under a stochastic model.

    The mean treats tiles as independent, which spatially correlated and unit errors make
    them not. Two corrections, both conservative: the Birge ratio ``χ²/(n − 1)`` of the tile
    displacements about their mean scales the covariance when above 1 (the tiles scatter more
    than their σ say), and the result is raised to at least the joint adjustment's
    covariance, which uses every plane with the full correlation and so bounds any linear
    combination of the same data from below (Gauss-Markov)."""
    n = len(tiles)
    if n > 1:
        chi2 = sum(
            float((x.displacement - mean) @ np.linalg.solve(x.covariance, x.displacement - mean))
            for x in tiles
        )
        birge = chi2 / (3.0 * (n - 1))
        if birge > 1.0:
            cov = cov * birge
    return cov + _positive_part(joint_cov - cov)


def _positive_part(m: np.ndarray) -> np.ndarray:
    """The positive semi-definite part of a symmetric matrix (negative eigenvalues set to 0),
    symmetrised."""
    ev, evec = np.linalg.eigh(m)
    out = (evec * np.clip(ev, 0.0, None)) @ evec.T
    return 0.5 * (out + out.T)


def _side_points(before, after, trace, buffer_m):
    """Geometry and side masks of both epochs (validated)."""
    _check_epochs(before, after)
    gb = trace_in_data_check(trace, before[:, :2], buffer_m=buffer_m)
    ga = fault_geometry(after[:, :2], trace)
    lb, rb = side_masks(gb, buffer_m=buffer_m)
    la, ra = side_masks(ga, buffer_m=buffer_m)
    return gb, ga, {"left": (lb, la), "right": (rb, ra)}


def estimate_slip(
    before: np.ndarray,
    after: np.ndarray,
    trace: FaultTrace,
    *,
    buffer_m: float = 10.0,
    sigma_before=0.05,
    sigma_after=0.05,
    plane_options: Optional[dict] = None,
    match_options: Optional[dict] = None,
    tile_size_m: Optional[float] = None,
    combine: str = "joint",
    progress: Optional[ProgressCallback] = None,
    stochastic_model: str = DEFAULT_STOCHASTIC_MODEL,
    unit_before: Optional[np.ndarray] = None,
    unit_after: Optional[np.ndarray] = None,
    components: Optional[dict] = None,
    transfer_planes: bool = DEFAULT_TRANSFER_PLANES,
    random_tilt: Optional[bool] = None,
    unit_time_before: Optional[np.ndarray] = None,
    unit_time_after: Optional[np.ndarray] = None,
    unit_contrasts: bool = DEFAULT_UNIT_CONTRASTS,
) -> SlipResult:
    """Relative displacement across ``trace`` between two epochs.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The two epochs in the same projected CRS (metres). Not modified.
    trace : FaultTrace
        In the points' CRS.
    buffer_m : float
        Points closer than this to the trace are left out (default 10 m, as the study).
    sigma_before, sigma_after
        Point accuracy of each epoch: scalar (isotropic), (3,) per axis, or (N, 3, 3).
    tile_size_m : float, optional
        When given, each side's points are cut into square tiles of this size (metres; grid
        aligned to multiples of ``tile_size_m`` in map x / y) and planes are extracted and
        matched per tile and epoch: no plane spans two tiles (the study used 20-100 m).
    combine : {"joint", "tiles"}
        With tiles: "joint" (default, the study's main approach) adjusts all matched planes of
        a side at once; "tiles" adjusts each tile with at least 3 matched planes and takes the
        information-weighted mean ``(Σ Cᵢ⁻¹)⁻¹ Σ Cᵢ⁻¹ dᵢ`` of the tile displacements (with
        covariance ``(Σ Cᵢ⁻¹)⁻¹``); tiles that are skipped are counted in the log. Per-tile
        results are in :attr:`SlipResult.tiles` for both modes. Ignored without tiles. With a
        stochastic model the tiles hold the side's components fixed and the combined
        covariance is made honest (see ``_honest_tile_covariance``).
    stochastic_model : {"white", "plane", "full"}
        The stochastic model of each side's adjustment (:mod:`.stochastic`; default "full").
    unit_before, unit_after : (N1,), (N2,) int, optional
        Acquisition unit of each point (PointSourceId, trajectory segment, TLS setup), for
        the "full" model's error per unit.
    unit_time_before, unit_time_after : (N1,), (N2,) float64, optional
        Acquisition time of each point (GpsTime, seconds), with the units: a unit's error
        may then drift along time, the knot spacing (or one rigid error) chosen by
        restricted likelihood (:mod:`.unit_drift`; :func:`.adjustment.adjust_rigid`).
        Strips and windows hold the side's choice; tiles keep rigid units.
    unit_contrasts : bool
        With units ("full" model): each plane seen by two units in one epoch ties them
        (:mod:`.unit_contrasts`, a strip adjustment inside the slip's): the unit components
        are identified from those within-epoch offsets, and each side's motion takes the
        units' errors they predict off its misclosures, over every plane found on both
        sides (default :data:`DEFAULT_UNIT_CONTRASTS`). Strips and windows hold the side's
        components without them (:func:`strip_profile`, :func:`window_field`); tiles none.
    components : dict, optional
        Plane-level components held fixed instead of estimated (sigmas in metres, see
        :func:`.adjustment.adjust_rigid`), for both sides.
    transfer_planes : bool
        Planes of one epoch without a match are observed by the other epoch's points that lie
        on them (:mod:`.transfer`) and adjusted like matched planes (default off:
        :data:`DEFAULT_TRANSFER_PLANES`). Whole sides only: tiles adjust matched planes.
    random_tilt : bool, optional
        Each plane is also tilted by the survey error, with a variance estimated per side
        (:func:`.adjustment.adjust_rigid`); strips, windows and tiles hold the side's value.
        None: :data:`.stochastic.RANDOM_TILT` (on). Not with the white model.

    Returns
    -------
    SlipResult

    Raises
    ------
    InputDataError
        Bad or non-overlapping epochs, a trace outside the data, too few matched planes.
    InvalidParameterError
        ``tile_size_m <= 0`` or an unknown ``combine``.
    """
    if combine not in COMBINE_MODES:
        raise InvalidParameterError(f"combine must be one of {COMBINE_MODES}, got {combine!r}")
    if tile_size_m is not None:
        tile_size_m = _positive("tile_size_m", tile_size_m)
    stochastic = _stochastic_options(
        before, after, stochastic_model, unit_before, unit_after, components, random_tilt,
        unit_time_before, unit_time_after, bool(unit_contrasts),
    )  # fmt: skip
    _, _, masks = _side_points(before, after, trace, buffer_m)
    sigma_before = _packed(sigma_before, "sigma_before")
    sigma_after = _packed(sigma_after, "sigma_after")

    results = {}
    tiles: List[TileResult] = []
    planes = {}
    if (
        tile_size_m is None
        and unit_contrasts
        and stochastic.get("stochastic_model") == "full"
        and any(stochastic.get(f"unit_{e}") is not None for e in ("before", "after"))
    ):
        # every plane of both sides first: their unit contrasts tie the units across the
        # fault in each side's adjustment (a strip adjustment inside the slip's)
        # (the progress in order: both sides' planes to 0.7, then their adjustments)
        for k, side in enumerate(SIDES):
            mb, ma = masks[side]
            planes[side] = _segment_side(
                before[mb], after[ma], side=side, plane_options=plane_options,
                progress=scaled(progress, 0.35 * k, 0.35 * k + 0.5),
            )  # fmt: skip
        contrasts = _survey_contrasts(
            [((before[masks[s][0]], after[masks[s][1]]),
              (np.flatnonzero(masks[s][0]), np.flatnonzero(masks[s][1])), planes[s])
             for s in SIDES],
            stochastic,
        )  # fmt: skip
        if contrasts is not None:
            stochastic = dict(stochastic, unit_contrasts=contrasts)
    elif tile_size_m is not None:
        # tiles as the tiled run (plane moments, app/tiled.py) adjusts them: untied units
        stochastic = dict(stochastic, unit_contrasts=(None, None))
    for k, side in enumerate(SIDES):
        mb, ma = masks[side]
        sub = scaled(progress, 0.5 * k, 0.5 * (k + 1))
        if planes:
            # segmented above: register_side's own 0.7 - 1 (its adjustment) falls on this
            # side's share of 0.7 - 1 of the whole
            sub = scaled(progress, 0.35 + 0.15 * k, 0.85 + 0.15 * k)
        kw = dict(
            side=side,
            sigma_before=_per_point(sigma_before, mb),
            sigma_after=_per_point(sigma_after, ma),
            plane_options=plane_options,
            match_options=match_options,
            progress=sub,
            stochastic=_sub_stochastic(stochastic, mb, ma),
        )
        if tile_size_m is None:
            results[side] = register_side(
                before[mb], after[ma], transfer_planes=transfer_planes,
                planes=planes.get(side), **kw,
            )  # fmt: skip
        else:
            results[side], tl = _register_side_tiled(
                before[mb], after[ma], tile_size_m=tile_size_m, combine=combine, **kw
            )
            tiles.extend(tl)
    for side in SIDES:  # which input points each side's labels refer to
        mb, ma = masks[side]
        results[side] = replace(
            results[side], before_index=np.flatnonzero(mb), after_index=np.flatnonzero(ma)
        )
    left, right = results["left"], results["right"]
    rel = right.displacement - left.displacement
    cov, cross, joint = _relative_covariance(left, right)
    return SlipResult(
        left=left,
        right=right,
        relative=rel,
        relative_covariance=cov,
        side_cross_covariance=cross,
        joint_components=joint,
        strike_rad=mean_strike_rad(trace),
        buffer_m=float(buffer_m),
        parameters={
            "buffer_m": float(buffer_m),
            "combine": combine if tile_size_m is not None else "joint",
            **({"tile_size_m": tile_size_m} if tile_size_m is not None else {}),
            "plane_options": dict(plane_options or {}),
            "match_options": dict(match_options or {}),
            "transfer_planes": bool(transfer_planes) and tile_size_m is None,
            **({"random_tilt": bool(random_tilt)} if random_tilt is not None else {}),
            "stochastic_model": stochastic["stochastic_model"],
            "acquisition_units": {
                e: int(np.unique(stochastic[f"unit_{e}"]).size)
                for e in ("before", "after")
                if stochastic.get(f"unit_{e}") is not None
            },
            **({"components": dict(stochastic["components"])} if stochastic["components"] else {}),
        },
        tiles=tuple(tiles),
    )


def relative_covariance(
    left: SideResult, right: SideResult
) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """Covariance of ``right.displacement − left.displacement`` and the sides' cross term.

    Each side's displacement (at its centroid) is linear in its plane misclosures (the
    plane-level GLS of :mod:`.stochastic`, after the robust weights have settled), so with
    the gains ``K = ∂x̂/∂δ`` of both sides' adjustments (:class:`.stochastic.PlaneGain`) the
    cross-covariance is ``C_RL = K_R Σ_δ(R, L) K_Lᵀ`` (translation rows), where ``Σ_δ(R, L)``
    holds the survey error shared across the trace: the spatial field between planes on
    opposite sides by centroid distance, and the acquisition units present on both sides
    (the same PointSourceId in the same epoch); the nugget has no cross term
    Then ``C_rel = C_R + C_L − C_RL − C_RLᵀ``.

    One set of components for the cross term: they are estimated once more on both sides'
    planes together (:func:`.stochastic.joint_covariance`: a dozen planes a side cannot split
    a survey error between field, units and nugget, and two sides of one survey split it
    differently), and ``C_R``, ``C_L``, ``C_RL`` are the covariances of the sides' own
    estimates under that joint model; with too few or too many planes together, each side's
    own components are combined instead (:func:`.stochastic.cross_covariance`).

    With the white model, or when either side's displacement is not its joint adjustment's
    (``combine="tiles"``: an information-weighted mean of tiles, not the GLS whose gain is
    known), the sides are taken as independent: ``C_rel = C_R + C_L`` and the cross term is
    None.

    Returns
    -------
    covariance : (3, 3) float64
        ``C_rel``, m².
    cross : (3, 3) float64 or None
        ``C_RL = Cov(d_right, d_left)``, m², or None when not modelled.
    """
    cov, cross, _ = _relative_covariance(left, right)
    return cov, cross


def _relative_covariance(left: SideResult, right: SideResult):
    """:func:`relative_covariance` and the joint components (or None)."""
    total = right.displacement_covariance + left.displacement_covariance
    gr, gl = right.rigid.plane_gain, left.rigid.plane_gain
    tiled = right.combined_covariance is not None or left.combined_covariance is not None
    if gr is None or gl is None or tiled:
        return total, None, None
    joint = joint_covariance(gr, gl)
    if joint is not None:
        j, comps = joint
        c_r, c_l, cross = j[3:6, 3:6], j[9:12, 9:12], j[3:6, 9:12]
        cov = c_r + c_l - cross - cross.T
    else:
        comps = None
        cross = cross_covariance(gr, gl)[3:, 3:]
        if not np.any(cross):  # nothing shared (the "plane" model): the sum, exactly
            return total, cross, None
        cov = total - cross - cross.T
    # positive semi-definite by construction (stochastic.joint_covariance and
    # cross_covariance); the floor guards against rounding only
    return _positive_part(cov), cross, comps


def _stochastic_options(
    before, after, model, unit_before, unit_after, components, random_tilt=None,
    unit_time_before=None, unit_time_after=None, unit_contrasts=DEFAULT_UNIT_CONTRASTS,
) -> dict:  # fmt: skip
    """Validated stochastic-model options of a whole run."""
    check_stochastic_model(model)
    n_b, n_a = np.asarray(before).shape[0], np.asarray(after).shape[0]
    return {
        # off: no contrast rows in any adjustment (None: each adjustment's own planes')
        **({} if unit_contrasts else {"unit_contrasts": (None, None)}),
        "random_tilt": check_random_tilt(random_tilt, model),
        "stochastic_model": model,
        "components": check_components(components),
        "unit_before": check_units(unit_before, n_b, "unit_before"),
        "unit_after": check_units(unit_after, n_a, "unit_after"),
        "unit_time_before": check_unit_time(unit_time_before, n_b, "unit_time_before"),
        "unit_time_after": check_unit_time(unit_time_after, n_a, "unit_time_after"),
    }


# --------------------------------------------------------------------------- strips


@dataclass(frozen=True)
class StripResult:
    """Registration of one strip of one side along the trace (:func:`strip_profile`).

    Attributes
    ----------
    side : str
        "left" or "right".
    along_start_m, along_end_m, along_centre_m : float
        Chainage range of the strip along the trace from its first vertex, metres.
    n_planes : int
        Matched planes in the strip (planes were extracted from the strip's points only).
    displacement : (3,) float64
        Motion of the material at the strip's centroid, metres (NaN when skipped).
    covariance : (3, 3) float64
        Covariance of ``displacement``, m² (NaN when skipped).
    fault_parallel : float
        Component along the trace's mean strike of ``displacement`` minus the LEFT side's
        global displacement (``slip.left.displacement``), metres; negative = dextral for
        the right side. NaN when skipped.
    sigma_fault_parallel : float
        1σ of ``fault_parallel``: ``√(jᵀ C_rel j)`` with ``C_rel`` =
        :attr:`relative_covariance`, metres.
    status : str
        "ok" or "skipped: <reason>".
    relative_covariance : (3, 3) float64
        Covariance of ``displacement`` minus the left side's global displacement, m²: the
        two added (white model, right-side strips), or for a left-side strip under a
        stochastic model ``C_strip − C_left`` floored at ``C_strip / 4`` (see
        :func:`strip_profile`). NaN when skipped.
    relative_displacement : (3,) float64
        ``displacement`` minus the left side's global displacement, metres (NaN when
        skipped).
    strike_rad : float
        The trace's mean strike, radians (the frame of :meth:`fault_frame`).
    """

    side: str
    along_start_m: float
    along_end_m: float
    along_centre_m: float
    n_planes: int
    displacement: np.ndarray
    covariance: np.ndarray
    fault_parallel: float
    sigma_fault_parallel: float
    status: str
    relative_covariance: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    relative_displacement: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    strike_rad: float = math.nan

    def fault_frame(self) -> Dict[str, float]:
        """The strip's motion relative to the left side's global motion in the fault frame
        (:func:`fault_frame` of :attr:`relative_displacement` and
        :attr:`relative_covariance`); ``fault_parallel`` and its σ are the strip's own
        fields. NaN when skipped."""
        if self.status != "ok" or not math.isfinite(self.strike_rad):
            return {k: math.nan for k in _FRAME_KEYS}
        out = fault_frame(self.relative_displacement, self.relative_covariance, self.strike_rad)
        out["fault_parallel"] = float(self.fault_parallel)
        out["sigma_fault_parallel"] = float(self.sigma_fault_parallel)
        return out


def _strike_vector(slip: SlipResult) -> np.ndarray:
    return np.array([math.sin(slip.strike_rad), math.cos(slip.strike_rad), 0.0])


def strip_profile(
    before: np.ndarray,
    after: np.ndarray,
    trace: FaultTrace,
    slip: SlipResult,
    *,
    strip_width_m: float,
    buffer_m: float = 10.0,
    sigma_before=0.05,
    sigma_after=0.05,
    plane_options: Optional[dict] = None,
    match_options: Optional[dict] = None,
    progress: Optional[ProgressCallback] = None,
    stochastic_model: Optional[str] = None,
    unit_before: Optional[np.ndarray] = None,
    unit_after: Optional[np.ndarray] = None,
    unit_time_before: Optional[np.ndarray] = None,
    unit_time_after: Optional[np.ndarray] = None,
) -> Tuple[StripResult, ...]:
    """Slip profile along the trace from strips of each side (Kusari et al. 2019, Fig. 5).

    Each side's points (outside ``buffer_m``) are cut into strips by their chainage along the
    trace (``fault_geometry(...).along_strike_m``): strip ``k`` holds chainages in
    ``[k w, (k + 1) w)``. Per strip and side, planes are extracted and matched from the
    strip's points only and the rigid motion is adjusted (as :func:`register_side`); strips
    with fewer than 3 matched planes or a singular system are kept with a "skipped" status.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The two epochs, metres (same CRS as ``trace``).
    trace : FaultTrace
    slip : SlipResult
        The global result; its left side's displacement and covariance are subtracted.
    strip_width_m : float
        Strip width along the trace, metres (> 0; the study used 50 and 100 m).
    buffer_m, sigma_before, sigma_after, plane_options, match_options
        As :func:`estimate_slip`.
    progress : callable, optional
    stochastic_model, unit_before, unit_after, unit_time_before, unit_time_after
        As :func:`estimate_slip` (default: the model of ``slip``). A strip holds its side's
        global plane-level components fixed (a strip has too few planes to estimate them).
        A strip of the LEFT side shares its data with the left side's global estimate that
        is subtracted: the variance of the difference is ``C_strip − C_left`` (the global
        estimate is the efficient one, so its covariance with any other unbiased estimate
        from the same data is its own covariance; Hausman 1978), floored at a quarter of
        ``C_strip``; a right-side strip adds ``C_left``. With the white model both add, as
        the study did. :attr:`StripResult.relative_covariance` holds the whole matrix.

    Returns
    -------
    tuple of StripResult
        Ordered by side (left, right), then chainage.
    """
    w = _positive("strip_width_m", strip_width_m)
    stochastic = _stochastic_options(
        before, after, stochastic_model or _model_of(slip), unit_before, unit_after, None,
        None, unit_time_before, unit_time_after, False,
    )  # fmt: skip
    gb, ga, masks = _side_points(before, after, trace, buffer_m)
    sigma_before = _packed(sigma_before, "sigma_before")
    sigma_after = _packed(sigma_after, "sigma_after")
    ref_d, ref_c = slip.left.displacement, slip.left.displacement_covariance
    j = _strike_vector(slip)
    jobs = []
    for side in SIDES:
        mb, ma = masks[side]
        sb = np.floor(gb.along_strike_m[mb] / w).astype(np.int64)
        sa = np.floor(ga.along_strike_m[ma] / w).astype(np.int64)
        for k in np.unique(np.concatenate([sb, sa])):
            jobs.append((side, int(k), np.flatnonzero(mb)[sb == k], np.flatnonzero(ma)[sa == k]))
    out: List[StripResult] = []
    nan3, nan33 = np.full(3, np.nan), np.full((3, 3), np.nan)
    for n, (side, k, ib, ia) in enumerate(jobs):
        d, c, npl, status = nan3, nan33, 0, "ok"
        try:
            if ib.size < 3 or ia.size < 3:
                raise InputDataError(f"{ib.size} / {ia.size} points in the two epochs")
            r = register_side(
                before[ib],
                after[ia],
                side=side,
                sigma_before=_per_point(sigma_before, _mask(ib, before.shape[0])),
                sigma_after=_per_point(sigma_after, _mask(ia, after.shape[0])),
                plane_options=plane_options,
                match_options=match_options,
                stochastic=_sub_stochastic(stochastic, ib, ia, _fixed_of(slip, side)),
            )
            npl = len(r.matches)
            d, c = r.rigid.displacement, r.rigid.displacement_covariance
            if not np.all(np.isfinite(c)):
                raise InputDataError("non-finite covariance")
        except InputDataError as exc:
            d, c, status = nan3, nan33, f"skipped: {exc}"
        rel_c = np.full((3, 3), np.nan)
        if status == "ok":
            rel_c = _difference_covariance(c, ref_c, side, stochastic)
            fp = float(j @ (d - ref_d))
            sfp = float(math.sqrt(max(float(j @ rel_c @ j), 0.0)))
        else:
            fp = sfp = float("nan")
        out.append(
            StripResult(
                side=side,
                along_start_m=k * w,
                along_end_m=(k + 1) * w,
                along_centre_m=(k + 0.5) * w,
                n_planes=int(npl),
                displacement=np.asarray(d, dtype=np.float64),
                covariance=np.asarray(c, dtype=np.float64),
                fault_parallel=fp,
                sigma_fault_parallel=sfp,
                status=status,
                relative_covariance=rel_c,
                relative_displacement=np.asarray(d, dtype=np.float64) - ref_d,
                strike_rad=float(slip.strike_rad),
            )
        )
        report(progress, (n + 1) / len(jobs), f"strip {n + 1}/{len(jobs)}")
    skipped = sum(s.status != "ok" for s in out)
    log.info("strip profile: %d strips of %g m, %d skipped", len(out), w, skipped)
    return tuple(out)


def _model_of(slip: SlipResult) -> str:
    return str(slip.parameters.get("stochastic_model", "white"))


def _fixed_of(slip: SlipResult, side: str) -> Optional[dict]:
    """The side's global plane-level components, to hold fixed in its strips and windows."""
    vc = getattr(slip, side).rigid.variance_components
    return vc.fixed() if vc is not None else None


def _difference_covariance(c, ref_c, side: str, stochastic: dict) -> np.ndarray:
    """(3, 3) covariance of ``d_local − d_left_global`` (see :func:`strip_profile`): the sum,
    or for a left-side strip or window under a stochastic model ``C − C_left`` floored at
    ``C / 4`` (in the positive semi-definite order: ``C/4 + max(¾ C − C_left, 0)``)."""
    if stochastic["stochastic_model"] == "white" or side != "left":
        return c + ref_c
    return 0.25 * c + _positive_part(0.75 * c - ref_c)


def _mask(idx: np.ndarray, n: int) -> np.ndarray:
    m = np.zeros(n, dtype=bool)
    m[idx] = True
    return m


# --------------------------------------------------------------------------- moving windows


@dataclass(frozen=True)
class WindowField:
    """Local displacement maps from moving windows (:func:`window_field`, Fig. 11).

    Grids are (ny, nx). Row ``r``, column ``c`` is the window centred at
    ``(x0 + c * step_m, y0 - r * step_m)``: row 0 is the NORTHERNMOST row (rows run north to
    south, columns west to east), as a north-up raster; a GeoTIFF's top-left corner is
    ``(x0 - step_m / 2, y0 + step_m / 2)`` with pixel size ``step_m`` (pixels centred on the
    window centres; the windows themselves are ``window_size_m`` wide and overlap).

    Attributes
    ----------
    x0, y0 : float
        Centre of the first (north-west) window, metres.
    step_m : float
        Window step = grid spacing, metres.
    window_size_m : float
        Window side, metres.
    dx, dy, dz : (ny, nx) float64
        Displacement of the window's side at the window's centroid minus the left side's global
        displacement, metres; NaN where the window has fewer than ``min_planes`` matched
        planes, lies on the trace, or its adjustment is singular.
    sigma_dx, sigma_dy : (ny, nx) float64
        1σ of ``dx``, ``dy`` (window and global-left covariances added), metres.
    n_planes : (ny, nx) int64
        Matched planes whose before-epoch centroid lies in the window (of the centre's side).
    side : (ny, nx) int8
        Side of the window centre: -1 left, +1 right, 0 on the trace.
    strike_rad : float
        The trace's mean strike, radians (the direction of :attr:`fault_parallel`).
    sigma_fault_parallel : (ny, nx) float64 or None
        1σ of :attr:`fault_parallel` from the window's relative covariance, metres.
    covariance : (ny, nx, 3, 3) float64 or None
        Covariance of each window's OWN displacement (before the left side's global
        displacement is subtracted), m²; NaN where the window was not adjusted.
    reference_m : (3,) float64 or None
        The left side's global displacement subtracted from ``dx``, ``dy``, ``dz``, metres:
        a window's own motion is ``(dx, dy, dz) + reference_m``.
    """

    x0: float
    y0: float
    step_m: float
    window_size_m: float
    dx: np.ndarray
    dy: np.ndarray
    dz: np.ndarray
    sigma_dx: np.ndarray
    sigma_dy: np.ndarray
    n_planes: np.ndarray
    side: np.ndarray
    strike_rad: float = math.nan
    sigma_fault_parallel: Optional[np.ndarray] = None
    covariance: Optional[np.ndarray] = None
    reference_m: Optional[np.ndarray] = None

    @property
    def fault_parallel(self) -> np.ndarray:
        """(ny, nx) component of (dx, dy) along the trace's mean strike, metres (negative =
        dextral for right-side windows)."""
        return math.sin(self.strike_rad) * self.dx + math.cos(self.strike_rad) * self.dy

    @property
    def shape(self) -> Tuple[int, int]:
        return tuple(self.dx.shape)

    def centres(self) -> Tuple[np.ndarray, np.ndarray]:
        """(ny, nx) x and y of the window centres, metres."""
        ny, nx = self.dx.shape
        xs = self.x0 + self.step_m * np.arange(nx)
        ys = self.y0 - self.step_m * np.arange(ny)
        return np.meshgrid(xs, ys)


#: progress cost of one phase, in units of one :func:`estimate_slip` on the same points
#: (measured on the synthetic mls pair, 2 cores: the planes of both sides and epochs 0.65,
#: one moving window 0.025, the strips of a trace 2.5 together)
WINDOW_PLANES_COST, WINDOW_COST, STRIPS_COST = 0.65, 0.025, 2.5


def window_progress_shares(n_windows: int):
    """``(planes, window loop)`` shares of :func:`window_field`'s progress for ``n_windows``
    windows, and its cost in units of one :func:`estimate_slip` (third item)."""
    loop = WINDOW_COST * max(1, int(n_windows))
    total = WINDOW_PLANES_COST + loop
    return WINDOW_PLANES_COST / total, loop / total, total


def window_count(points_xy: np.ndarray, window_size_m: float, window_step_m: float) -> int:
    """How many windows :func:`window_field` lays over points ``(N, 2)`` (the bounding box
    of both sides, without the buffer: a close upper bound for the progress weights)."""
    lo, hi = points_xy.min(axis=0), points_xy.max(axis=0)
    size, step = float(window_size_m), float(window_step_m)
    nx = max(1, int(math.ceil((hi[0] - lo[0] - size) / step - 1e-9)) + 1)
    ny = max(1, int(math.ceil((hi[1] - lo[1] - size) / step - 1e-9)) + 1)
    return nx * ny


def window_field(
    before: np.ndarray,
    after: np.ndarray,
    trace: FaultTrace,
    slip: SlipResult,
    *,
    window_size_m: float,
    window_step_m: float,
    buffer_m: float = 10.0,
    sigma_before=0.05,
    sigma_after=0.05,
    plane_options: Optional[dict] = None,
    match_options: Optional[dict] = None,
    min_planes: int = 3,
    progress: Optional[ProgressCallback] = None,
    stochastic_model: Optional[str] = None,
    unit_before: Optional[np.ndarray] = None,
    unit_after: Optional[np.ndarray] = None,
    unit_time_before: Optional[np.ndarray] = None,
    unit_time_after: Optional[np.ndarray] = None,
) -> WindowField:
    """Moving-window displacement maps relative to the left side's global motion.

    Planes are extracted ONCE per epoch and side (on the whole side outside ``buffer_m``) and
    matched once; each window then uses the matched planes of the side of its centre whose
    before-epoch centroid lies in the window (half-open ``[c - s/2, c + s/2)`` in x and y), and
    adjusts the rigid motion on those planes' points. A window thus holds points of ONE side
    only (the buffer is excluded), but a plane near the window edge keeps all its points.
    The grid covers the bounding box of both sides' points: the first window's south-west
    corner is at the box's (xmin, ymax - s) and windows are added every ``window_step_m`` until
    the box is covered.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The two epochs, metres.
    trace : FaultTrace
    slip : SlipResult
        The global result: ``slip.left.displacement`` (and its covariance) is subtracted.
    window_size_m, window_step_m : float
        Window side and step, metres (> 0; the study used 400 m stepped by 20 m).
    buffer_m, sigma_before, sigma_after, plane_options, match_options
        As :func:`estimate_slip`.
    min_planes : int
        Fewest matched planes for a window to be adjusted (>= 3).
    progress : callable, optional
    stochastic_model, unit_before, unit_after, unit_time_before, unit_time_after
        As :func:`strip_profile`: windows hold their side's global components fixed, and a
        left-side window's σ accounts for its correlation with the left global estimate.

    Returns
    -------
    WindowField
    """
    size = _positive("window_size_m", window_size_m)
    step = _positive("window_step_m", window_step_m)
    if int(min_planes) != min_planes or min_planes < 3:
        raise InvalidParameterError(f"min_planes must be an integer >= 3, got {min_planes!r}")
    min_planes = int(min_planes)
    stochastic = _stochastic_options(
        before, after, stochastic_model or _model_of(slip), unit_before, unit_after, None,
        None, unit_time_before, unit_time_after, False,
    )  # fmt: skip
    _, _, masks = _side_points(before, after, trace, buffer_m)
    sigma_before = _packed(sigma_before, "sigma_before")
    sigma_after = _packed(sigma_after, "sigma_after")
    opts = dict(plane_options or {})

    # the window grid first: the bar's share of the planes and of the window loop follows
    # their cost (window_progress_shares), so "window k/N" reads where the bar stands
    pts = np.concatenate([before[masks[s][0], :2] for s in SIDES])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    nx = max(1, int(math.ceil((hi[0] - lo[0] - size) / step - 1e-9)) + 1)
    ny = max(1, int(math.ceil((hi[1] - lo[1] - size) / step - 1e-9)) + 1)
    planes_share = window_progress_shares(nx * ny)[0]

    # planes once per side and epoch
    sides = {}
    for k, side in enumerate(SIDES):
        mb, ma = masks[side]
        sub = scaled(progress, planes_share / 2 * k, planes_share / 2 * (k + 1))
        bp, ap = before[mb], after[ma]
        try:
            pb = segment_planes(bp, progress=scaled(sub, 0.0, 0.5), quiet=True, **opts)
            pa = segment_planes(ap, progress=scaled(sub, 0.5, 1.0), quiet=True, **opts)
        except InputDataError as exc:
            log.info("%s side: no planes (%s)", side, exc)
            continue
        m = match_planes(pb, pa, quiet=True, **(match_options or {}))
        lb = _labels_for_matches(pb.labels, m.before)
        la = _labels_for_matches(pa.labels, m.after)
        kb = (lb >= 0) & (pb.planarity >= CLEAN_LEAF_RATIO)
        ka = (la >= 0) & (pa.planarity >= CLEAN_LEAF_RATIO)
        sides[side] = dict(
            xy=pb.centroids[m.before, :2],
            before=bp[kb],
            lb=lb[kb],
            after=ap[ka],
            la=la[ka],
            sb=_per_point(_per_point(sigma_before, mb), kb),
            sa=_per_point(_per_point(sigma_after, ma), ka),
            st=_sub_stochastic(_sub_stochastic(stochastic, mb, ma), kb, ka, _fixed_of(slip, side)),
        )
        log.info("%s side: %d matched planes for the windows", side, len(m))

    x0, y0 = lo[0] + size / 2, hi[1] - size / 2
    xs = x0 + step * np.arange(nx)
    ys = y0 - step * np.arange(ny)
    cx, cy = np.meshgrid(xs, ys)
    cside = fault_geometry(np.column_stack([cx.ravel(), cy.ravel()]), trace).side.reshape(ny, nx)

    shape = (ny, nx)
    out = {
        k: np.full(shape, np.nan)
        for k in ("dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_fault_parallel")
    }
    jp = _strike_vector(slip)
    own_cov = np.full(shape + (3, 3), np.nan)
    nplanes = np.zeros(shape, dtype=np.int64)
    ref_d, ref_c = slip.left.displacement, slip.left.displacement_covariance
    half = size / 2
    n_done = 0
    for r in range(ny):
        for c in range(nx):
            n_done += 1
            report(
                progress,
                planes_share + (1 - planes_share) * n_done / (nx * ny),
                f"window {n_done}/{nx * ny}",
            )
            s = int(cside[r, c])
            if s == 0 or SIDES[(s + 1) // 2] not in sides:
                continue
            d = sides[SIDES[(s + 1) // 2]]
            xy = d["xy"]
            inside = (
                (xy[:, 0] >= cx[r, c] - half)
                & (xy[:, 0] < cx[r, c] + half)
                & (xy[:, 1] >= cy[r, c] - half)
                & (xy[:, 1] < cy[r, c] + half)
            )
            ids = np.flatnonzero(inside)
            nplanes[r, c] = ids.size
            if ids.size < min_planes:
                continue
            kb = np.isin(d["lb"], ids)
            ka = np.isin(d["la"], ids)
            lut = np.full(xy.shape[0], -1, dtype=np.int64)
            lut[ids] = np.arange(ids.size)
            try:
                res = adjust_rigid(
                    d["before"][kb],
                    lut[d["lb"][kb]],
                    d["after"][ka],
                    lut[d["la"][ka]],
                    sigma_before=_per_point(d["sb"], kb),
                    sigma_after=_per_point(d["sa"], ka),
                    min_planes=min_planes,
                    **_stochastic_kw(_sub_stochastic(d["st"], kb, ka)),
                )
            except InputDataError as exc:
                log.debug("window (%d, %d) not adjusted: %s", r, c, exc)
                continue
            disp = res.displacement - ref_d
            cov = res.displacement_covariance
            if not np.all(np.isfinite(cov)):
                continue
            rel_c = _difference_covariance(cov, ref_c, SIDES[(s + 1) // 2], stochastic)
            out["dx"][r, c], out["dy"][r, c], out["dz"][r, c] = disp
            own_cov[r, c] = cov
            out["sigma_dx"][r, c] = math.sqrt(max(rel_c[0, 0], 0.0))
            out["sigma_dy"][r, c] = math.sqrt(max(rel_c[1, 1], 0.0))
            out["sigma_fault_parallel"][r, c] = math.sqrt(max(float(jp @ rel_c @ jp), 0.0))
    log.info(
        "window field: %d x %d windows of %g m stepped %g m, %d adjusted",
        ny,
        nx,
        size,
        step,
        int(np.count_nonzero(np.isfinite(out["dx"]))),
    )
    return WindowField(
        x0=float(x0),
        y0=float(y0),
        step_m=step,
        window_size_m=size,
        n_planes=nplanes,
        side=cside.astype(np.int8),
        strike_rad=float(slip.strike_rad),
        covariance=own_cov,
        reference_m=np.array(ref_d, dtype=np.float64),
        **out,
    )
