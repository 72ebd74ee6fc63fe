"""Plane correspondences between two epochs (Kusari et al. 2019, section II.D).

For every plane of the first epoch, the plane of the second epoch with a similar normal, a
small centroid-to-plane distance (both ways) and an overlapping extent; one-to-one. Rotations
between epochs are assumed below 1°, so normals are compared directly.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .errors import InvalidParameterError
from .planes import PlaneSet

log = logging.getLogger(__name__)

#: :attr:`PlaneMatches.transferred` codes
MATCHED, TRANSFERRED_TO_AFTER, TRANSFERRED_TO_BEFORE = 0, 1, 2


@dataclass(frozen=True)
class PlaneMatches:
    """Matched plane pairs.

    Attributes
    ----------
    before, after : (K,) int64
        Plane ids in the first and second epoch's :class:`PlaneSet`.
    angle_rad : (K,) float64
        Angle between the two normals.
    distance_m : (K,) float64
        Larger of the two centroid-to-plane distances (metres).
    transferred : (K,) int8, optional
        How the pair was made: 0 (:data:`MATCHED`) both epochs' segmentations found the
        plane; 1 (:data:`TRANSFERRED_TO_AFTER`) a first-epoch plane whose second-epoch points
        were gathered on it, 2 (:data:`TRANSFERRED_TO_BEFORE`) the converse (the other
        epoch's plane is fitted to the gathered points; :mod:`.transfer`). None: all 0.
    """

    before: np.ndarray
    after: np.ndarray
    angle_rad: np.ndarray
    distance_m: np.ndarray
    transferred: Optional[np.ndarray] = None

    @property
    def kind(self) -> np.ndarray:
        """(K,) int8: :attr:`transferred`, zeros when None."""
        if self.transferred is None:
            return np.zeros(self.before.size, dtype=np.int8)
        return np.asarray(self.transferred, dtype=np.int8)

    @property
    def n_transferred(self) -> int:
        """Pairs made by transfer (either way)."""
        return int(np.count_nonzero(self.kind))

    def __len__(self) -> int:
        return int(self.before.size)


def _boxes_overlap(lo1, hi1, lo2, hi2, margin):
    return np.all((lo1 <= hi2 + margin) & (lo2 <= hi1 + margin), axis=-1)


def match_planes(
    before: PlaneSet,
    after: PlaneSet,
    *,
    angle_threshold_deg: float = 3.0,
    distance_threshold_m: float = 0.5,
    overlap_margin_m: Optional[float] = None,
    quiet: bool = False,
) -> PlaneMatches:
    """One-to-one correspondences between the planes of two epochs.

    Parameters
    ----------
    before, after : PlaneSet
        Planes of the first and second epoch, in the same coordinate frame.
    angle_threshold_deg : float
        Largest angle between matched normals, degrees (default 3: the study assumes
        rotations below 1°; plane normals of a few hundred points scatter by a fraction of a
        degree).
    distance_threshold_m : float
        Largest distance of each plane's centroid to the other plane, metres. It must exceed
        the largest expected displacement along the normals (default 0.5 m).
    overlap_margin_m : float, optional
        The bounding boxes of matched planes must overlap when grown by this margin (default:
        ``distance_threshold_m``), so that coplanar but separate surfaces (two roofs at the
        same height) are not paired.
    quiet : bool
        Log the count at DEBUG instead of INFO (callers that log one summary line).

    Returns
    -------
    PlaneMatches
        Pairs sorted by ``before`` id. When several candidates compete, the pair with the
        smallest distance (then angle) is taken first (greedy on a global ordering, so the
        result does not depend on plane order beyond ties).
    """
    if not 0 < angle_threshold_deg < 90:
        raise InvalidParameterError(
            f"angle_threshold_deg must be in (0, 90), got {angle_threshold_deg}"
        )
    if not distance_threshold_m > 0:
        raise InvalidParameterError(f"distance_threshold_m must be > 0, got {distance_threshold_m}")
    margin = distance_threshold_m if overlap_margin_m is None else float(overlap_margin_m)
    if margin < 0:
        raise InvalidParameterError(f"overlap_margin_m must be >= 0, got {overlap_margin_m}")
    empty = PlaneMatches(np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0), np.empty(0))
    if len(before) == 0 or len(after) == 0:
        return empty

    from scipy.spatial import cKDTree

    # candidates: after-planes whose centroid is within reach of a before-plane's box
    half1 = 0.5 * np.linalg.norm(before.extent_max - before.extent_min, axis=1)
    half2 = 0.5 * np.linalg.norm(after.extent_max - after.extent_min, axis=1)
    centre = before.centroids.mean(axis=0)
    tree = cKDTree(after.centroids - centre)
    reach = half1 + half2.max() + margin + distance_threshold_m
    lists = tree.query_ball_point(before.centroids - centre, reach)
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    if counts.sum() == 0:
        return empty
    i = np.repeat(np.arange(len(before)), counts)
    j = np.fromiter((k for x in lists for k in x), dtype=np.int64, count=int(counts.sum()))

    cosang = np.abs(np.einsum("ij,ij->i", before.normals[i], after.normals[j]))
    ok = cosang >= math.cos(math.radians(angle_threshold_deg))
    d12 = np.abs(np.einsum("ij,ij->i", before.normals[i], after.centroids[j]) + before.offsets[i])
    d21 = np.abs(np.einsum("ij,ij->i", after.normals[j], before.centroids[i]) + after.offsets[j])
    dist = np.maximum(d12, d21)
    ok &= dist <= distance_threshold_m
    ok &= _boxes_overlap(
        before.extent_min[i], before.extent_max[i], after.extent_min[j], after.extent_max[j], margin
    )
    i, j, dist, cosang = i[ok], j[ok], dist[ok], cosang[ok]
    angle = np.arccos(np.clip(cosang, -1.0, 1.0))
    order = np.lexsort((j, i, angle, dist))
    used1 = np.zeros(len(before), dtype=bool)
    used2 = np.zeros(len(after), dtype=bool)
    keep = []
    for k in order:  # greedy one-to-one; pairs are few (one per plane at most)
        if not used1[i[k]] and not used2[j[k]]:
            used1[i[k]] = used2[j[k]] = True
            keep.append(k)
    keep = np.array(sorted(keep, key=lambda k: i[k]), dtype=np.int64)
    if keep.size == 0:
        return empty
    log.log(
        logging.DEBUG if quiet else logging.INFO,
        "%d plane pairs matched (%d planes in the first epoch, %d in the second)",
        keep.size,
        len(before),
        len(after),
    )
    return PlaneMatches(i[keep], j[keep], angle[keep], dist[keep])
