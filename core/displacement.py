"""Fault slip from two epochs by planar registration on each side of a fault trace.

Kusari et al. (2019), section II.D and IV: per side of the trace (points within a buffer of
it excluded), planes are extracted in both epochs, matched, and a Gauss-Helmert adjustment
gives the rigid motion of that side at its centroid; the relative displacement is right minus
left, with propagated covariance, resolved along and across the fault's strike.

This module is the joint (one adjustment per side) workflow; tiles, strips and moving windows
build on it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Dict, Optional

import numpy as np

from .adjustment import RigidResult, adjust_rigid
from .errors import InputDataError
from .fault import FaultTrace, fault_geometry, mean_strike_rad, side_masks, trace_in_data_check
from .matching import PlaneMatches, match_planes
from .planes import PlaneSet, segment_planes
from .progress import ProgressCallback, report, scaled

log = logging.getLogger(__name__)

SIDES = ("left", "right")


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
    """

    side: str
    rigid: RigidResult
    planes_before: PlaneSet
    planes_after: PlaneSet
    matches: PlaneMatches

    def to_dict(self) -> Dict[str, object]:
        r = self.rigid
        d, s = r.displacement, np.sqrt(np.diag(r.displacement_covariance))
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
        }


@dataclass(frozen=True)
class SlipResult:
    """Relative displacement across a fault (right side minus left side), metres.

    ``fault_parallel`` is the component along the trace's digitised direction (unit vector
    ``(sin strike, cos strike)``), ``fault_normal`` along the direction 90° clockwise from it
    (towards the right side); ``right_lateral_slip = -fault_parallel`` is positive for dextral
    motion. Sigmas are 1σ from the adjustments' a-posteriori covariances (sides independent).
    """

    left: SideResult
    right: SideResult
    relative: np.ndarray
    relative_covariance: np.ndarray
    strike_rad: float
    buffer_m: float
    parameters: Dict[str, object] = field(default_factory=dict)

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
        }

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
            "note": "displacements in metres, rotations in radians; each side's displacement "
            "is the motion of the material at that side's centroid (first to second epoch)",
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
) -> SideResult:
    """Planes, matches and the rigid adjustment for the points of one side.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The side's points in each epoch (metres).
    sigma_before, sigma_after
        Point accuracy: scalar, (3,) per axis, or (N, 3, 3) per point (metres).
    """
    opts = dict(plane_options or {})
    pb = segment_planes(before, progress=scaled(progress, 0.0, 0.35), **opts)
    pa = segment_planes(after, progress=scaled(progress, 0.35, 0.7), **opts)
    m = match_planes(pb, pa, **(match_options or {}))
    log.info("%s side: %d / %d planes, %d matched", side, len(pb), len(pa), len(m))
    if len(m) < 3:
        raise InputDataError(
            f"{side} side: only {len(m)} matched planes (need at least 3 with several "
            "orientations); check that the epochs overlap on this side, or relax the matching "
            "thresholds"
        )
    lb = _labels_for_matches(pb.labels, m.before)
    la = _labels_for_matches(pa.labels, m.after)

    def pick(sig, mask):
        a = np.asarray(sig, dtype=np.float64)
        return a[mask] if a.ndim == 3 else a

    kb, ka = lb >= 0, la >= 0
    rigid = adjust_rigid(
        before[kb],
        lb[kb],
        after[ka],
        la[ka],
        sigma_before=pick(sigma_before, kb),
        sigma_after=pick(sigma_after, ka),
    )
    report(progress, 1.0, f"{side} side done")
    return SideResult(side=side, rigid=rigid, planes_before=pb, planes_after=pa, matches=m)


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
    progress: Optional[ProgressCallback] = None,
) -> SlipResult:
    """Relative displacement across ``trace`` between two epochs (joint adjustment per side).

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

    Returns
    -------
    SlipResult
    """
    for name, arr in (("before", before), ("after", after)):
        a = np.asarray(arr)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] == 0:
            raise InputDataError(f"{name} must be a non-empty (N, 3) point array, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputDataError(f"{name} contains NaN or infinite coordinates; remove them")
    lo = np.maximum(before[:, :2].min(axis=0), after[:, :2].min(axis=0))
    hi = np.minimum(before[:, :2].max(axis=0), after[:, :2].max(axis=0))
    if np.any(lo >= hi):
        raise InputDataError("the two epochs do not overlap in plan; check their CRSs and extents")
    trace_in_data_check(trace, before[:, :2], buffer_m=buffer_m)
    gb = fault_geometry(before[:, :2], trace)
    ga = fault_geometry(after[:, :2], trace)
    lb, rb = side_masks(gb, buffer_m=buffer_m)
    la, ra = side_masks(ga, buffer_m=buffer_m)

    def per_point(sig, mask):
        a = np.asarray(sig, dtype=np.float64)
        return a[mask] if a.ndim == 3 else a

    results = {}
    for k, (side, mb, ma) in enumerate((("left", lb, la), ("right", rb, ra))):
        results[side] = register_side(
            before[mb],
            after[ma],
            side=side,
            sigma_before=per_point(sigma_before, mb),
            sigma_after=per_point(sigma_after, ma),
            plane_options=plane_options,
            match_options=match_options,
            progress=scaled(progress, 0.5 * k, 0.5 * (k + 1)),
        )
    left, right = results["left"], results["right"]
    rel = right.rigid.displacement - left.rigid.displacement
    cov = right.rigid.displacement_covariance + left.rigid.displacement_covariance
    return SlipResult(
        left=left,
        right=right,
        relative=rel,
        relative_covariance=cov,
        strike_rad=mean_strike_rad(trace),
        buffer_m=float(buffer_m),
        parameters={
            "buffer_m": float(buffer_m),
            "combine": "joint",
            "plane_options": dict(plane_options or {}),
            "match_options": dict(match_options or {}),
        },
    )
