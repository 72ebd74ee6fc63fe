"""Planar segmentation: octree leaves, least-squares planes, planarity test and region growing.

Kusari et al. (2019), section II.B–C, with these refinements (see docs/methods.md):

* Adaptive octree: nodes are tested top-down from ``max_node_size_m``; a planar node becomes a
  leaf, a non-planar one is split until ``min_node_size_m``. Large flat surfaces are fitted with
  many points, clutter is resolved finely. Neighbours are found across levels.
* Per-leaf plane from the covariance of the leaf's points centred on its centroid (Eq. 5-6),
  smallest-eigenvalue normal; the planarity test of Algorithm 1 (fraction of points within
  ``planarity_threshold_m`` reaches ``planarity_ratio``) plus a guard against line-like leaves.
* Region growing by connected-component labelling (Algorithm 2): planar leaves that touch
  (26-neighbourhood) join when normals agree (Eq. 7) and each centroid lies near the other's
  plane (Eq. 8, both ways); labels propagate to the minimum, with pointer jumping, until stable.
  Segments are gathered by sort + unique.
* Points of a planar leaf that fail its distance test, and points of non-planar leaves, join the
  nearest plane of a touching planar leaf when within ``planarity_threshold_m`` (boundaries).
* Automatic parameters from the data: point spacing from octree occupancy and noise from a robust
  quantile of leaf-fit residuals; every value can be overridden.

Everything is vectorised numpy; the OpenCL backend (``core/opencl``) runs the same steps as
kernels and gives the same labels.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from .errors import InputDataError, InvalidParameterError
from .octree import Octree, bounds, build_octree, leaf_neighbours, run_boundaries
from .progress import ProgressCallback, report

log = logging.getLogger(__name__)

_U3 = np.uint64(3)
NOISE_SAMPLE_POINTS = 200_000  # points used to estimate the noise (whole nodes, Morton-spread)

TARGET_LEAF_POINTS = 40  # points per leaf the automatic node size aims at
NOISE_QUANTILE = 25.0  # percentile of leaf residual scales taken as the noise (robust to clutter)
NOISE_QUANTILE_BIAS = 1.12  # that percentile is ~0.89 sigma for 40-point Gaussian leaves
PLANARITY_SIGMAS = 3.0  # planarity threshold = 3 noise sigmas
CONTAMINATED = 0.98  # planar nodes with fewer inliers than this share are refitted on inliers
ADAPTIVE_LEVELS = 2  # automatic max node size = min node size * 2**ADAPTIVE_LEVELS
MIN_PLANE_LEAVES = 3  # automatic min_plane_points = this many typical leaves


@dataclass(frozen=True)
class SegmentationParameters:
    """The parameters a segmentation used (given or estimated from the data).

    All lengths in metres, angles in degrees.
    """

    min_node_size_m: float
    max_node_size_m: float
    planarity_threshold_m: float
    planarity_ratio: float
    angle_threshold_deg: float
    distance_threshold_m: float
    min_plane_points: int
    min_leaf_points: int
    backend: str
    point_spacing_m: float
    noise_m: float
    automatic: Tuple[str, ...] = ()

    def to_dict(self) -> Dict[str, object]:
        d = asdict(self)
        d["automatic"] = list(self.automatic)
        for k, v in d.items():
            if isinstance(v, float):
                d[k] = float(f"{v:.6g}")
        return d


@dataclass(frozen=True)
class PlaneSet:
    """Planes found in a point cloud.

    Attributes
    ----------
    normals : (P, 3) float64
        Unit normals, oriented upward (nz > 0); vertical planes towards +y, then +x.
    offsets : (P,) float64
        Hessian offsets d (metres): ``normals[k] @ p + offsets[k] == 0`` on plane k.
    centroids : (P, 3) float64
        Centroid of each plane's points, input coordinates (metres).
    n_points : (P,) int64
        Points per plane.
    rms : (P,) float64
        RMS of the orthogonal residuals (metres).
    covariances : (P, 3, 3) float64
        Covariance (scatter / n) of each plane's points, m².
    extent_min, extent_max : (P, 3) float64
        Bounding box of each plane's points.
    labels : (N,) int32
        Plane id of every input point, -1 for none (``PlaneId``).
    planarity : (N,) float32
        Fraction of the point's octree leaf within the planarity threshold of the leaf's plane
        (NaN where the leaf had too few points to fit).
    parameters : SegmentationParameters
    n_leaves : int
        Octree leaves examined; ``n_planar_leaves`` of them passed the planarity test.
    """

    normals: np.ndarray
    offsets: np.ndarray
    centroids: np.ndarray
    n_points: np.ndarray
    rms: np.ndarray
    covariances: np.ndarray
    extent_min: np.ndarray
    extent_max: np.ndarray
    labels: np.ndarray
    planarity: np.ndarray
    parameters: SegmentationParameters
    n_leaves: int = 0
    n_planar_leaves: int = 0
    timings_s: Dict[str, float] = field(default_factory=dict, compare=False)

    def __len__(self) -> int:
        return int(self.normals.shape[0])

    def point_indices(self, plane_id: int) -> np.ndarray:
        """Indices (into the input points) of the points of plane ``plane_id``."""
        return np.flatnonzero(self.labels == plane_id)

    def to_records(self) -> List[Dict[str, object]]:
        """One JSON-ready dict per plane (``id, normal, d, centroid, n_points, rms, ...``)."""
        out = []
        for k in range(len(self)):
            out.append(
                {
                    "id": k,
                    "normal": [float(v) for v in self.normals[k]],
                    "d": float(self.offsets[k]),
                    "centroid": [float(v) for v in self.centroids[k]],
                    "n_points": int(self.n_points[k]),
                    "rms": float(self.rms[k]),
                    "extent_min": [float(v) for v in self.extent_min[k]],
                    "extent_max": [float(v) for v in self.extent_max[k]],
                }
            )
        return out


# --------------------------------------------------------------------------- kernels


class NumpyKernels:
    """The reference implementation of the per-node kernels (vectorised numpy)."""

    name = "numpy"

    def encode(self, pts: np.ndarray, lo: np.ndarray, scale: float, cells: int) -> np.ndarray:
        from .octree import quantise_encode

        return quantise_encode(pts, lo, scale, cells)

    def node_fit(
        self, sub: np.ndarray, starts: np.ndarray, counts: np.ndarray, threshold: float
    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Plane fit and planarity count of every node.

        Parameters
        ----------
        sub : (n, 3) float64
            Points, grouped by node (node k is ``sub[starts[k]:starts[k] + counts[k]]``).
        starts, counts : (M,) int64
        threshold : float
            Planarity distance, metres.

        Returns
        -------
        mean : (M, 3) centroids; evals : (M, 3) ascending eigenvalues of the covariance;
        normal : (M, 3) smallest-eigenvalue eigenvectors; n_within : (M,) int64 points within
        ``threshold`` of their node's plane; within : (n,) bool per point.
        """
        m = starts.size
        node_of = np.repeat(np.arange(m), counts)
        mean = np.add.reduceat(sub, starts, axis=0) / counts[:, None]
        d = sub - np.take(mean, node_of, axis=0)  # two-pass: centred on each node's centroid
        cov = np.empty((m, 3, 3))
        for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
            c = np.add.reduceat(d[:, a] * d[:, b], starts) / counts
            cov[:, a, b] = c
            cov[:, b, a] = c
        evals, evecs = np.linalg.eigh(cov)
        normal = np.ascontiguousarray(evecs[:, :, 0])
        within = np.abs(np.einsum("ij,ij->i", d, np.take(normal, node_of, axis=0))) <= threshold
        n_within = np.add.reduceat(within.view(np.uint8), starts, dtype=np.int64)
        return mean, evals, normal, n_within, within

    def plane_within(
        self,
        sub: np.ndarray,
        starts: np.ndarray,
        counts: np.ndarray,
        origin: np.ndarray,
        normal: np.ndarray,
        threshold: float,
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Points within ``threshold`` of given node planes.

        Parameters
        ----------
        sub : (n, 3) float64, grouped by node; starts, counts : (M,) int64
        origin, normal : (M, 3) float64
            A point on each node's plane and its unit normal.
        threshold : float, metres

        Returns
        -------
        n_within : (M,) int64; within : (n,) bool
        """
        off = -np.einsum("ij,ij->i", normal, origin)
        dist = np.repeat(off, counts)
        for a in range(3):
            dist += sub[:, a] * np.repeat(normal[:, a], counts)
        within = np.abs(dist) <= threshold
        n_within = np.add.reduceat(within.view(np.uint8), starts, dtype=np.int64)
        return n_within, within

    def propagate_labels(
        self, indptr: np.ndarray, indices: np.ndarray, nodes: np.ndarray, n: int
    ) -> np.ndarray:
        """Connected-component labels by min-label propagation with pointer jumping.

        Parameters
        ----------
        indptr, indices : CSR adjacency of the nodes that have edges (rows ``nodes``).
        nodes : (K,) int64
            Nodes (of ``n``) that have at least one edge, ascending.
        n : int
            Number of nodes.

        Returns
        -------
        (n,) int64: the smallest node index of each node's component.
        """
        lab = np.arange(n, dtype=np.int64)
        if nodes.size == 0:
            return lab
        starts = indptr[:-1]
        while True:
            nb = np.minimum.reduceat(lab[indices], starts)
            new = lab.copy()
            new[nodes] = np.minimum(lab[nodes], nb)
            # hooking: a node's current label (a root) also takes the smaller neighbour label,
            # so long chains collapse in a few rounds instead of one round per link
            np.minimum.at(new, lab[nodes], nb)
            # pointer jumping: follow labels to their own label until stable
            while True:
                jumped = new[new]
                if np.array_equal(jumped, new):
                    break
                new = jumped
            if np.array_equal(new, lab):
                return lab
            lab = new


def node_fit_reference(
    sub: np.ndarray, starts: np.ndarray, counts: np.ndarray, threshold: float
) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Slow, obvious per-node loop (two-pass centred covariance) for testing ``node_fit``."""
    m = starts.size
    mean = np.empty((m, 3))
    evals = np.empty((m, 3))
    normal = np.empty((m, 3))
    n_within = np.empty(m, dtype=np.int64)
    within = np.empty(sub.shape[0], dtype=bool)
    for k in range(m):
        pts = sub[starts[k] : starts[k] + counts[k]]
        c = pts.mean(axis=0)
        d = pts - c
        w, v = np.linalg.eigh(d.T @ d / len(pts))
        mean[k], evals[k], normal[k] = c, w, v[:, 0]
        inside = np.abs(d @ v[:, 0]) <= threshold
        within[starts[k] : starts[k] + counts[k]] = inside
        n_within[k] = inside.sum()
    return mean, evals, normal, n_within, within


def get_kernels(backend: str):
    """The kernel set for ``backend`` ('numpy', 'opencl' or 'auto')."""
    if backend == "numpy":
        return NumpyKernels()
    if backend in ("opencl", "auto"):
        try:
            from .opencl.backend import OpenCLKernels

            return OpenCLKernels()
        except Exception as exc:  # noqa: BLE001 - any OpenCL failure falls back for 'auto'
            if backend == "auto":
                log.info("OpenCL unavailable (%s); using the numpy backend", exc)
                return NumpyKernels()
            raise
    raise InvalidParameterError(f"backend must be 'numpy', 'opencl' or 'auto', got {backend!r}")


# --------------------------------------------------------------------------- helpers


def _validate_points(points: np.ndarray) -> Tuple[np.ndarray, Tuple[np.ndarray, np.ndarray]]:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidParameterError(f"points must have shape (N, 3), got {pts.shape}")
    if pts.shape[0] < 3:
        raise InputDataError(
            f"points has {pts.shape[0]} point(s); a plane needs at least 3 — check the "
            "input file and the class filters"
        )
    pts = pts.astype(np.float64, copy=False)
    if not np.all(np.isfinite(pts)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(pts), axis=1)))
        raise InputDataError(
            f"points contain {bad} point(s) with NaN or infinite coordinates; remove them first"
        )
    lo, hi = bounds(pts)
    if np.all(hi - lo == 0):
        raise InputDataError("all points are identical; there is no surface to segment")
    return pts, (lo, hi)


def orient_normals(normals: np.ndarray) -> np.ndarray:
    """Flip normals to the convention: nz > 0; vertical ones towards +y, then +x."""
    n = normals.copy()
    tol = 1e-12
    key = np.where(
        np.abs(n[:, 2]) > tol, n[:, 2], np.where(np.abs(n[:, 1]) > tol, n[:, 1], n[:, 0])
    )
    n[key < 0] *= -1.0
    return n


def _ranges_to_index(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenate ``arange(s, s + c)`` for every (s, c)."""
    total = int(counts.sum())
    if total == 0:
        return np.empty(0, dtype=np.int64)
    offs = np.repeat(starts - (np.cumsum(counts) - counts), counts)
    return offs + np.arange(total, dtype=np.int64)


def occupancy_by_level(tree: Octree, min_median: float = 16.0) -> Dict[int, np.ndarray]:
    """Points per occupied node, by level, around the deepest level whose median occupancy
    reaches ``min_median``.

    The search starts where a surface-like cloud of the footprint's area would put about
    ``min_median`` points in a node, goes finer while the median stays above ``min_median``
    and coarser (each level from the one below, cheaply) until it reaches it.
    """
    n = tree.keys.size
    guess = tree.root_size_m * math.sqrt(min_median / max(n, 1))
    level = min(tree.depth, max(1, tree.level_for_size(guess) + 1))
    out: Dict[int, np.ndarray] = {}

    def at(lv: int):
        return run_boundaries(tree.keys >> np.uint64(3 * (tree.depth - lv)))

    keys, _, counts = at(level)
    out[level] = counts
    while level < tree.depth and np.median(counts) >= min_median:
        level += 1
        keys, _, counts = at(level)
        out[level] = counts
    while level > 1 and np.median(counts) < min_median:
        keys, starts, _ = run_boundaries(keys >> _U3)
        counts = np.add.reduceat(counts, starts)
        level -= 1
        out[level] = counts
    return out


def estimate_point_spacing(
    tree: Octree, occupancy: Optional[Dict[int, np.ndarray]] = None
) -> float:
    """Typical point spacing (metres) of a surface-like cloud from octree occupancy.

    The deepest level whose median points per occupied node is at least 16 is taken; a
    surface crossing a node of edge a holds about a² / s² points, so s = a / sqrt(median).
    Depends only on the set of points, not their order.
    """
    occ = occupancy if occupancy is not None else occupancy_by_level(tree)
    level = (
        max(lv for lv, c in occ.items() if np.median(c) >= 16.0)
        if any(np.median(c) >= 16.0 for c in occ.values())
        else min(occ)
    )
    med = float(np.median(occ[level]))
    return tree.cell_size_m(level) / math.sqrt(max(med, 1.0))


def _estimate_noise(
    tree: Octree, ps: np.ndarray, level: int, min_points: int, kernels
) -> Tuple[float, float]:
    """Robust noise (metres) from leaf fits at ``level``, and the median points per fitted node.

    Uses whole nodes taken evenly in Morton order (independent of point order), about
    ``NOISE_SAMPLE_POINTS`` points in all.
    """
    keys, starts, counts = tree.nodes(level)
    ok = np.flatnonzero(counts >= max(min_points, 6))
    if ok.size == 0:
        return float("nan"), float("nan")
    typical = float(np.median(counts[ok]))
    step = max(1, int(counts[ok].sum()) // NOISE_SAMPLE_POINTS)
    ok = ok[::step]
    st, ct = starts[ok], counts[ok]
    idx = _ranges_to_index(st, ct)
    sub_starts = np.cumsum(ct) - ct
    _, evals, _, _, _ = kernels.node_fit(ps[idx], sub_starts, ct, 0.0)
    scale = np.sqrt(np.maximum(evals[:, 0], 0.0))
    return float(np.percentile(scale, NOISE_QUANTILE) * NOISE_QUANTILE_BIAS), typical


# --------------------------------------------------------------------------- main function


def segment_planes(
    points: np.ndarray,
    *,
    min_node_size_m: Optional[float] = None,
    max_node_size_m: Optional[float] = None,
    planarity_threshold_m: Optional[float] = None,
    planarity_ratio: Optional[float] = None,
    angle_threshold_deg: Optional[float] = None,
    distance_threshold_m: Optional[float] = None,
    min_plane_points: Optional[int] = None,
    min_leaf_points: Optional[int] = None,
    backend: str = "numpy",
    progress: Optional[ProgressCallback] = None,
) -> PlaneSet:
    """Find the planar surfaces of a point cloud.

    Parameters
    ----------
    points : (N, 3) float64
        Coordinates, metres (any offset: they are centred internally). Not modified.
    min_node_size_m : float, optional
        Smallest octree leaf edge, metres (leaves are ``root / 2**k``, so the edge used lies in
        ``[min_node_size_m, 2 * min_node_size_m)``). Default: from the point spacing, so that a
        leaf on a surface holds about 40 points.
    max_node_size_m : float, optional
        Largest leaf edge, metres: nodes are tested from this size down. Default 4x the leaf.
    planarity_threshold_m : float, optional
        Distance to a leaf's plane within which a point counts as on it. Default 3x the noise.
    planarity_ratio : float, optional
        Fraction of a leaf's points that must be within the threshold (Algorithm 1). Default 0.9.
    angle_threshold_deg : float, optional
        Largest angle between the normals of two joined leaves (Eq. 7). Default from the noise
        and leaf size, in [4, 15] degrees.
    distance_threshold_m : float, optional
        Largest distance of a leaf's centroid to its neighbour's plane (Eq. 8). Default: the
        planarity threshold.
    min_plane_points : int, optional
        Smallest reported plane, counted over the points of its planar leaves (boundary points
        join planes but do not make them). Default: 3 typical leaves (at least 30 points), so
        that single curved patches (spheres, tree crowns) are not reported as planes.
    min_leaf_points : int, optional
        Smallest leaf that is fitted. Default 10.
    backend : {'numpy', 'opencl', 'auto'}
        Kernel implementation; both give the same labels.
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    PlaneSet

    Raises
    ------
    InputDataError
        Fewer than 3 points, NaN/inf coordinates, or all points identical.
    InvalidParameterError
        A parameter out of range.
    """
    t_start = time.perf_counter()
    timings: Dict[str, float] = {}
    pts_in, box = _validate_points(points)
    kernels = get_kernels(backend)
    automatic: List[str] = []

    if planarity_ratio is None:
        planarity_ratio = 0.9
        automatic.append("planarity_ratio")
    if not 0.0 < planarity_ratio <= 1.0:
        raise InvalidParameterError(f"planarity_ratio must be in (0, 1], got {planarity_ratio}")
    if min_leaf_points is None:
        min_leaf_points = 10
        automatic.append("min_leaf_points")
    if min_leaf_points < 3:
        raise InvalidParameterError(f"min_leaf_points must be >= 3, got {min_leaf_points}")
    if min_plane_points is not None and min_plane_points < 3:
        raise InvalidParameterError(f"min_plane_points must be >= 3, got {min_plane_points}")
    for name, value in (
        ("min_node_size_m", min_node_size_m),
        ("max_node_size_m", max_node_size_m),
        ("planarity_threshold_m", planarity_threshold_m),
        ("angle_threshold_deg", angle_threshold_deg),
        ("distance_threshold_m", distance_threshold_m),
    ):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise InvalidParameterError(f"{name} must be a positive number, got {value}")
    if angle_threshold_deg is not None and angle_threshold_deg >= 90:
        raise InvalidParameterError(
            f"angle_threshold_deg must be below 90, got {angle_threshold_deg}"
        )

    # Centre (order-independent: bounding-box centre) for precision at UTM offsets.
    centre = 0.5 * (box[0] + box[1])
    report(progress, 0.02, "octree")

    t0 = time.perf_counter()
    tree = build_octree(
        pts_in, min_node_size_m=min_node_size_m, encoder=kernels.encode, point_bounds=box
    )
    ps = np.take(pts_in, tree.order, axis=0)
    ps -= centre
    timings["octree"] = time.perf_counter() - t0
    report(progress, 0.2, "parameters")

    # ---- parameters
    t0 = time.perf_counter()
    occupancy = occupancy_by_level(tree)
    spacing = estimate_point_spacing(tree, occupancy)
    if min_node_size_m is None:
        target = spacing * math.sqrt(TARGET_LEAF_POINTS)
        level = int(round(math.log2(tree.root_size_m / target)))
        leaf_level = max(1, min(tree.depth, level))
        automatic.append("min_node_size_m")
    else:
        leaf_level = max(1, tree.level_for_size(min_node_size_m))
    noise, typical_n = _estimate_noise(tree, ps, leaf_level, min_leaf_points, kernels)
    if min_node_size_m is None and np.isfinite(noise):
        # a leaf must be wide compared with the noise, or its normal is meaningless
        while leaf_level > 1 and tree.cell_size_m(leaf_level) < 8.0 * noise:
            leaf_level -= 1
            noise, typical_n = _estimate_noise(tree, ps, leaf_level, min_leaf_points, kernels)
    leaf_size = tree.cell_size_m(leaf_level)
    if not np.isfinite(noise):
        noise = 0.01 * leaf_size
        typical_n = float(min_leaf_points)
        log.warning("too few points per leaf to estimate the noise; assuming %.3g m", noise)
    if planarity_threshold_m is None:
        planarity_threshold_m = max(PLANARITY_SIGMAS * noise, 1e-4 * leaf_size)
        automatic.append("planarity_threshold_m")
    if distance_threshold_m is None:
        distance_threshold_m = planarity_threshold_m
        automatic.append("distance_threshold_m")
    if angle_threshold_deg is None:
        sd_normal = noise * math.sqrt(12.0) / (leaf_size * math.sqrt(max(typical_n, 3.0)))
        angle_threshold_deg = float(np.clip(math.degrees(4.0 * math.sqrt(2.0) * sd_normal), 4, 15))
        automatic.append("angle_threshold_deg")
    if min_plane_points is None:
        # a plane spans a few leaves: single curved patches (spheres, trees) stay unlabelled
        min_plane_points = max(30, int(round(MIN_PLANE_LEAVES * typical_n)))
        automatic.append("min_plane_points")
    if max_node_size_m is None:
        top_level = max(1, leaf_level - ADAPTIVE_LEVELS)
        automatic.append("max_node_size_m")
    else:
        top_level = max(1, min(leaf_level, tree.level_for_size(max_node_size_m)))
    params = SegmentationParameters(
        min_node_size_m=leaf_size,
        max_node_size_m=tree.cell_size_m(top_level),
        planarity_threshold_m=float(planarity_threshold_m),
        planarity_ratio=float(planarity_ratio),
        angle_threshold_deg=float(angle_threshold_deg),
        distance_threshold_m=float(distance_threshold_m),
        min_plane_points=int(min_plane_points),
        min_leaf_points=int(min_leaf_points),
        backend=kernels.name,
        point_spacing_m=float(spacing),
        noise_m=float(noise),
        automatic=tuple(automatic),
    )
    log.debug("segmentation parameters: %s", params.to_dict())
    timings["parameters"] = time.perf_counter() - t0
    report(progress, 0.3, "planarity test")

    # ---- adaptive octree: planarity test top-down
    t0 = time.perf_counter()
    n = ps.shape[0]
    thr = params.planarity_threshold_m
    inlier = np.zeros(n, dtype=bool)
    names = ("key", "level", "start", "count", "planar", "mean", "normal", "ratio", "n_within")
    leaves: Dict[str, List[np.ndarray]] = {k: [] for k in names}
    active = None  # sorted positions of the points still to test; None = all
    for level in range(top_level, leaf_level + 1):
        keys_l = tree.keys >> np.uint64(3 * (tree.depth - level))
        if active is None:
            nkeys, starts, counts = run_boundaries(keys_l)
            sub = ps
        else:
            nkeys, starts, counts = run_boundaries(keys_l[active])
            sub = np.take(ps, active, axis=0)
        if starts.size == 0:
            break
        mean, evals, normal, n_within, within = kernels.node_fit(sub, starts, counts, thr)
        fitted = counts >= min_leaf_points
        # planar: enough points within the threshold, and spread in two directions (not a line)
        planar = fitted & (n_within >= planarity_ratio * counts)
        planar &= np.sqrt(np.maximum(evals[:, 1], 0.0)) > thr
        # Refit contaminated planar nodes on their inliers, so the up to (1 - ratio) points of
        # another surface (at corners and edges) do not tilt the plane; then test again.
        pl = np.flatnonzero(planar & (n_within < CONTAMINATED * counts))
        if pl.size:
            pts_pl = _ranges_to_index(starts[pl], counts[pl])
            inl = pts_pl[within[pts_pl]]
            in_starts = np.cumsum(n_within[pl]) - n_within[pl]
            m2, e2, n2, _, _ = kernels.node_fit(
                np.take(sub, inl, axis=0), in_starts, n_within[pl], thr
            )
            pl_starts = np.cumsum(counts[pl]) - counts[pl]
            nw2, w2 = kernels.plane_within(
                np.take(sub, pts_pl, axis=0), pl_starts, counts[pl], m2, n2, thr
            )
            mean[pl], evals[pl], normal[pl], n_within[pl] = m2, e2, n2, nw2
            within[pts_pl] = w2
            planar[pl] = (nw2 >= planarity_ratio * counts[pl]) & (
                np.sqrt(np.maximum(e2[:, 1], 0)) > thr
            )
        ratio = np.where(fitted, n_within / counts, np.nan)
        last = level == leaf_level
        leaf = planar | ~fitted | last
        gstart = starts if active is None else active[starts]
        for k, v in (
            ("key", nkeys[leaf]),
            ("level", np.full(int(leaf.sum()), level, dtype=np.int64)),
            ("start", gstart[leaf]),
            ("count", counts[leaf]),
            ("planar", planar[leaf]),
            ("mean", mean[leaf]),
            ("normal", normal[leaf]),
            ("ratio", ratio[leaf]),
            ("n_within", np.where(planar, n_within, 0)[leaf]),
        ):
            leaves[k].append(v)
        pos = np.flatnonzero(np.repeat(planar, counts) & within)
        inlier[pos if active is None else active[pos]] = True
        if not last:
            keep = np.repeat(~leaf, counts)
            active = np.flatnonzero(keep) if active is None else active[keep]
            if active.size == 0:
                break
        report(progress, 0.3 + 0.3 * (level - top_level + 1) / (leaf_level - top_level + 1), "")
    lv = {k: np.concatenate(v) for k, v in leaves.items()}
    order = np.argsort(lv["start"], kind="stable")
    lv = {k: v[order] for k, v in lv.items()}
    n_leaves = lv["start"].size
    leaf_count = lv["count"]
    timings["planarity"] = time.perf_counter() - t0
    report(progress, 0.6, "region growing")

    # ---- region growing over touching planar leaves (Eq. 7 and Eq. 8 both ways)
    t0 = time.perf_counter()
    ni, nj = leaf_neighbours(lv["key"], lv["level"], tree.depth)
    planar_leaf = lv["planar"]
    both = planar_leaf[ni] & planar_leaf[nj]
    ei, ej = ni[both], nj[both]
    cos_thr = math.cos(math.radians(params.angle_threshold_deg))
    nrm, cen = lv["normal"], lv["mean"]
    agree = np.abs(np.einsum("ij,ij->i", nrm[ei], nrm[ej])) >= cos_thr
    dc = cen[ej] - cen[ei]
    agree &= np.abs(np.einsum("ij,ij->i", nrm[ei], dc)) <= params.distance_threshold_m
    agree &= np.abs(np.einsum("ij,ij->i", nrm[ej], dc)) <= params.distance_threshold_m
    ei, ej = ei[agree], ej[agree]  # symmetric, sorted by ei
    nodes, first = np.unique(ei, return_index=True)
    indptr = np.append(first, ei.size)
    root = kernels.propagate_labels(indptr, ej, nodes, n_leaves)
    timings["region_growing"] = time.perf_counter() - t0
    report(progress, 0.75, "boundaries")

    # ---- segments: gather by sort + unique over the roots of planar leaves
    t0 = time.perf_counter()
    seg_of_leaf = np.full(n_leaves, -1, dtype=np.int32)
    planar_ids = np.flatnonzero(planar_leaf)
    roots, seg = np.unique(root[planar_ids], return_inverse=True)
    seg_of_leaf[planar_ids] = seg
    lab_sorted = np.repeat(seg_of_leaf, leaf_count)
    lab_sorted[~inlier] = -1
    _assign_boundaries(ps, lab_sorted, inlier, lv, seg_of_leaf, ni, nj, thr)
    timings["boundaries"] = time.perf_counter() - t0
    report(progress, 0.85, "plane fits")

    # ---- drop small segments, renumber in Morton order of their first leaf, refit
    t0 = time.perf_counter()
    nseg = roots.size
    # support = inliers of the plane's planar leaves; boundary points do not make a plane
    sizes = np.bincount(seg, weights=lv["n_within"][planar_ids], minlength=nseg)
    keep_seg = sizes >= params.min_plane_points
    new_id = np.full(nseg + 1, -1, dtype=np.int32)  # index -1 (unlabelled) maps to -1
    new_id[:nseg][keep_seg] = np.arange(int(keep_seg.sum()), dtype=np.int32)
    lab_sorted = new_id[lab_sorted]
    planes = _fit_planes(ps, lab_sorted, int(keep_seg.sum()), centre)
    labels = np.empty(n, dtype=np.int32)
    labels[tree.order] = lab_sorted
    planarity = np.empty(n, dtype=np.float32)
    planarity[tree.order] = np.repeat(lv["ratio"].astype(np.float32), leaf_count)
    timings["fit"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    if planes["normals"].shape[0] == 0:
        log.warning("no planes found (%d leaves, %d planar)", n_leaves, int(planar_leaf.sum()))
    report(progress, 1.0, "done")
    return PlaneSet(
        labels=labels,
        planarity=planarity,
        parameters=params,
        n_leaves=int(n_leaves),
        n_planar_leaves=int(planar_leaf.sum()),
        timings_s=timings,
        **planes,
    )


def _assign_boundaries(
    ps: np.ndarray,
    lab: np.ndarray,
    inlier: np.ndarray,
    lv: Dict[str, np.ndarray],
    seg_of_leaf: np.ndarray,
    ni: np.ndarray,
    nj: np.ndarray,
    threshold: float,
) -> None:
    """Unlabelled points join the closest plane of a touching planar leaf (in place).

    For every leaf, only one planar neighbour per segment is tried: the one whose centroid is
    nearest the leaf's. A point joins the segment whose plane is nearest, if within
    ``threshold``.
    """
    keep = seg_of_leaf[nj] >= 0
    bi, bj = ni[keep], nj[keep]
    if bi.size == 0:
        return
    cen, nrm = lv["mean"], lv["normal"]
    gap = np.einsum("ij,ij->i", cen[bj] - cen[bi], cen[bj] - cen[bi])
    o = np.lexsort((bj, gap, seg_of_leaf[bj], bi))
    bi, bj = bi[o], bj[o]
    sj = seg_of_leaf[bj]
    first = np.r_[True, (bi[1:] != bi[:-1]) | (sj[1:] != sj[:-1])]
    bi, bj = bi[first], bj[first]  # sorted by leaf
    n_leaves = seg_of_leaf.size
    deg = np.bincount(bi, minlength=n_leaves)
    ptr = np.cumsum(deg) - deg
    leaf_count = lv["count"]
    cand = np.flatnonzero(~inlier & np.repeat(deg > 0, leaf_count))
    if cand.size == 0:
        return
    cl = np.searchsorted(lv["start"], cand, side="right") - 1
    cnt = deg[cl]
    rep = np.repeat(np.arange(cand.size), cnt)  # candidate of each pair; pairs grouped by it
    rank = np.arange(rep.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    j = bj[np.repeat(ptr[cl], cnt) + rank]
    pos = cand[rep]
    dist = np.abs(
        ps[pos, 0] * nrm[j, 0]
        + ps[pos, 1] * nrm[j, 1]
        + ps[pos, 2] * nrm[j, 2]
        - np.einsum("ij,ij->i", cen, nrm)[j]
    )
    dist[dist > threshold] = np.inf
    group = np.cumsum(cnt) - cnt
    best = np.minimum.reduceat(dist, group)  # nearest plane of each candidate
    hit = np.isfinite(best)
    is_best = (dist == best[rep]) & hit[rep]
    k = np.flatnonzero(is_best)
    if k.size == 0:
        return
    k = k[np.r_[True, rep[k][1:] != rep[k][:-1]]]  # first nearest (lowest segment on ties)
    lab[cand[rep[k]]] = seg_of_leaf[j[k]]


def _fit_planes(ps: np.ndarray, lab: np.ndarray, nplanes: int, centre: np.ndarray) -> dict:
    """Least-squares planes of the labelled points (two-pass centred moments).

    ``lab`` is in Morton order, where labels come in long runs: sums are taken per run
    (``reduceat``) and then per plane (``bincount``), so no sort of the points is needed.
    """
    if nplanes == 0:
        z3 = np.empty((0, 3))
        return dict(
            normals=z3,
            offsets=np.empty(0),
            centroids=z3,
            n_points=np.empty(0, dtype=np.int64),
            rms=np.empty(0),
            covariances=np.empty((0, 3, 3)),
            extent_min=z3,
            extent_max=z3,
        )
    run_lab, starts, run_n = run_boundaries(lab)
    ok = run_lab >= 0
    rl = run_lab[ok]

    def per_plane(values: np.ndarray) -> np.ndarray:
        return np.bincount(rl, weights=np.add.reduceat(values, starts)[ok], minlength=nplanes)

    counts = np.bincount(rl, weights=run_n[ok], minlength=nplanes)
    cols = [np.ascontiguousarray(ps[:, a]) for a in range(3)]
    mean = np.stack([per_plane(c) for c in cols], axis=1) / counts[:, None]
    table = np.vstack([mean, np.zeros((1, 3))])  # label -1 -> row nplanes (ignored)
    d = [cols[a] - table[lab, a] for a in range(3)]
    cov = np.empty((nplanes, 3, 3))
    for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
        c = per_plane(d[a] * d[b]) / counts
        cov[:, a, b] = c
        cov[:, b, a] = c
    evals, evecs = np.linalg.eigh(cov)
    normals = orient_normals(evecs[:, :, 0])
    centroids = mean + centre
    ext_min = np.full((nplanes, 3), np.inf)
    ext_max = np.full((nplanes, 3), -np.inf)
    for a in range(3):
        np.minimum.at(ext_min[:, a], rl, np.minimum.reduceat(cols[a], starts)[ok])
        np.maximum.at(ext_max[:, a], rl, np.maximum.reduceat(cols[a], starts)[ok])
    return dict(
        normals=normals,
        offsets=-np.einsum("ij,ij->i", normals, centroids),
        centroids=centroids,
        n_points=counts.astype(np.int64),
        rms=np.sqrt(np.maximum(evals[:, 0], 0.0)),
        covariances=cov,
        extent_min=ext_min + centre,
        extent_max=ext_max + centre,
    )
