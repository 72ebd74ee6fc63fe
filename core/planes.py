"""Planar segmentation: octree leaves, least-squares planes, planarity test and region growing.

Kusari et al. (2019), section II.B–C, with these refinements (see docs/methods.md):

* Adaptive octree: nodes are tested top-down from ``max_node_size_m``; a planar node becomes a
  leaf, a non-planar one is split until ``min_node_size_m``, and once more where that finds a
  planar child (fine leaves: at airborne density a leaf is as wide as a wall). Large flat
  surfaces are fitted with many points, clutter is resolved finely. Neighbours are found
  across levels.
* Per-leaf plane from the covariance of the leaf's points centred on its centroid (Eq. 5-6),
  smallest-eigenvalue normal; the planarity test of Algorithm 1 (fraction of points within
  ``planarity_threshold_m`` reaches ``planarity_ratio``) plus a guard against line-like leaves.
* Region growing by connected-component labelling (Algorithm 2): planar leaves that touch
  (26-neighbourhood) join when normals agree (Eq. 7) and each centroid lies near the other's
  plane (Eq. 8, both ways); labels propagate to the minimum, with pointer jumping, until stable.
  Segments are gathered by sort + unique.
* Segment refinement: segments no plane fits are split; touching segments, and segments that
  touch one free leaf, merge when one plane fits both (RMS, or a chi-square test of the added
  residuals for small pieces).
* Points of a planar leaf that fail its distance test, and points of non-planar leaves, join the
  nearest plane of a touching planar leaf when within ``planarity_threshold_m`` (boundaries),
  unless the leaf's points near that plane scatter like vegetation (the vegetation test).
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

TARGET_LEAF_POINTS = 30  # points per leaf the automatic node size aims at
NOISE_QUANTILE = 25.0  # percentile of leaf residual scales taken as the noise (robust to clutter)
NOISE_QUANTILE_BIAS = 1.12  # that percentile is ~0.89 sigma for 40-point Gaussian leaves
PLANARITY_SIGMAS = 3.0  # planarity threshold = 3 noise sigmas
PLANARITY_RATIO = 0.9  # Algorithm 1's share of a leaf within the threshold, less the clutter
MIN_PLANARITY_RATIO = 0.6  # ... but never below this
RELEASE_THRESHOLDS = 2.0  # labelled points beyond this many thresholds of their plane go
SURFACE_CORE_SHARE = 0.5  # of the points within 3 sigmas of a plane, those within 1 sigma
REFIT_FLATNESS = 0.5  # failing leaves refitted when sqrt(l0) <= this * sqrt(l1) (not blobs)
CLUTTER_RATIO_FACTOR = 3.0  # leaves hold up to ~3x the median clutter share of surface cells
CONTAMINATED = 0.98  # planar nodes with fewer inliers than this share are refitted on inliers
ADAPTIVE_LEVELS = 2  # automatic max node size = min node size * 2**ADAPTIVE_LEVELS
MIN_PLANE_LEAVES = 3  # automatic min_plane_points = this many typical leaves
REFINE_RMS_SIGMAS = 1.3  # one plane: its inlier points' RMS is at most this many noise sigmas
SPLIT_RMS_SIGMAS = 1.5  # segments whose inlier RMS exceeds this many sigmas are split
FINE_MIN_POINTS = 6  # failing leaves are split once more; those children need this many
MERGE_CHI2 = 16.27  # chi-square(3) at 99.9 %: one plane for two adds at most this (sigma^2)
PLANE_SUPPORT_SHARE = 1.0 / 3.0  # of min_plane_points, from planar-leaf inliers
MERGE_RMS_SDS = 1.0  # ... and the union's RMS within the tolerance plus this many of its sds


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
    scale_node_size_m: float = float("nan")
    surface_share: float = float("nan")
    scale_method: str = ""

    def to_dict(self) -> Dict[str, object]:
        d = asdict(self)
        d["automatic"] = list(self.automatic)
        for k, v in d.items():
            if isinstance(v, float):
                d[k] = float(f"{v:.6g}") if math.isfinite(v) else None
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


def _band_refit(fit, pts, counts, mean, evals, normal, *, floor, tiny, min_points):
    """Planes of consecutive groups of ``pts`` refitted twice on the points near them.

    Each time the points within max(k sqrt(max(l0, ``tiny``)), ``floor``) of the current plane
    are refitted with ``fit`` (a kernel's ``node_fit``), k = 2 then 3: clutter inflates the
    first l0, so the first band is narrower; the refitted plane is no longer tilted by it, so
    the second band holds the surface's noise and sheds the clutter. Groups left with fewer
    than ``min_points`` in a band keep their previous plane. No sort: a median per group cost
    more than the whole planarity test.

    Returns mean, evals, normal (copies, updated), the inliers per group and per point of the
    last band, whether each group was refitted there (``ok``) and each point's group.
    """
    owner = np.repeat(np.arange(counts.size), counts)
    mean, evals, normal = mean.copy(), evals.copy(), normal.copy()
    n_in = counts.astype(np.int64)
    inlier = np.ones(pts.shape[0], dtype=bool)
    ok = n_in >= min_points
    for width in (2.0, 3.0):
        r = np.abs(np.einsum("ij,ij->i", pts - mean[owner], normal[owner]))
        band = np.maximum(width * np.sqrt(np.maximum(evals[:, 0], tiny)), floor)
        inlier = r <= band[owner]
        n_in = np.bincount(owner, weights=inlier, minlength=counts.size).astype(np.int64)
        ok = n_in >= min_points
        if not ok.any():
            break
        sel = np.flatnonzero(inlier & ok[owner])
        c2 = n_in[ok]
        m2, e2, n2, _, _ = fit(pts[sel], np.cumsum(c2) - c2, c2, floor)
        mean[ok], evals[ok], normal[ok] = m2, e2, n2
    return mean, evals, normal, n_in, ok, inlier, owner


def _refit_robust(kernels, sub, starts, counts, nodes, thr, mean, evals, normal, n_within, within):
    """Robust planes for ``nodes`` (indices into ``starts``/``counts``), in place; returns the
    share (K,) of each node's points within ``thr`` of its plane that lie within ``thr / 3``.

    The bands of :func:`_band_refit`, never narrower than ``thr``. A refit is kept where it
    puts at least as many points within ``thr`` as the plane before (so clean corners keep the
    old behaviour: the inliers' plane). Uses only the backend's kernels, so both backends
    agree.
    """
    cnt = counts[nodes]
    pos = _ranges_to_index(starts[nodes], cnt)
    pts = np.take(sub, pos, axis=0)
    st = np.cumsum(cnt) - cnt
    m, e, nrm, _, _, _, owner = _band_refit(
        kernels.node_fit, pts, cnt, mean[nodes], evals[nodes], normal[nodes],
        floor=thr, tiny=0.0, min_points=3,
    )  # fmt: skip
    nw, w = kernels.plane_within(pts, st, cnt, m, nrm, thr)
    better = nw >= n_within[nodes]
    take = nodes[better]
    mean[take], evals[take], normal[take], n_within[take] = (
        m[better],
        e[better],
        nrm[better],
        nw[better],
    )
    within[pos[better[owner]]] = w[better[owner]]
    # share of the points within the threshold that lie within a third of it (one sigma):
    # 0.68 for a surface (a Gaussian cut at 3 sigma), 0.33 for clutter filling the band evenly
    r = np.abs(np.einsum("ij,ij->i", pts - mean[nodes][owner], normal[nodes][owner]))
    inband = within[pos]
    core = np.bincount(owner, weights=inband & (r <= thr / 3.0), minlength=nodes.size)
    den = np.bincount(owner, weights=inband, minlength=nodes.size)
    return core / np.maximum(den, 1.0)


def get_kernels(backend: str):
    """The kernel set for ``backend`` ('numpy', 'opencl' or 'auto')."""
    if backend == "numpy":
        return NumpyKernels()
    if backend in ("opencl", "auto"):
        try:
            from .opencl.backend import OpenCLKernels

            return OpenCLKernels(fallback=NumpyKernels())
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
            f"{pts.shape[0]} point(s) given; a plane needs at least 3 — check the "
            "input file, its extent and the class filters"
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


# --------------------------------------------------------------------------- scales


SCALE_SAMPLE_POINTS = 30_000  # points analysed for spacing and noise (whole blocks)
SCALE_BLOCK_POINTS = 2_000  # points per sampled block (a few leaves of every scale)
SURFACE_FLATNESS = 0.15  # a node is surface-like when sqrt(l0) <= this * sqrt(l1) ...
SURFACE_SPREAD = 0.15  # ... and sqrt(l1) >= this * its edge (spread across it, not a line)
NOISE_FLATNESS = 0.25  # nodes whose residual scale enters the noise median
SURFACE_SHARE_OF_BEST = 0.7  # the finest scale holding this share of the best scale's share
MIN_SCALE_NODE_POINTS = 12  # nodes fitted in the scale analysis
MIN_SURFACE_NODES = 30  # surface-like nodes a level needs to count ...
MIN_SURFACE_NODES_SMALL = 8  # ... or a tenth of its fitted nodes, at least this many
MIN_SURFACE_SHARE = 0.02  # ... and hold this share of the sampled points
NOISE_CLEARANCE_SIGMAS = 3.0  # noise nodes: their plane this far from the node's faces


@dataclass(frozen=True)
class ScaleLevel:
    """One octree level of the scale analysis (on the sampled blocks).

    ``surface_share``: fraction of the sampled points in surface-like nodes (locally planar
    with the points spread across the node); ``median_points``: median points per
    surface-like node; ``noise_m``: median residual scale of near-planar nodes (metres).
    """

    node_size_m: float
    n_nodes: int
    n_surface_nodes: int
    n_fitted_nodes: int
    surface_share: float
    median_points: float
    noise_m: float


@dataclass(frozen=True)
class ScaleEstimate:
    """Point spacing and noise of a cloud's surfaces, from local neighbourhoods.

    ``point_spacing_m`` (metres between neighbouring points on a surface), ``noise_m``
    (1 sigma across the surface), the node edge they were read at, the share of sampled
    points in surface-like nodes there (``1 - surface_share`` is clutter, edges and curved
    ground at that scale), ``method`` ("surface nodes", or "occupancy" when no surface was
    found) and every level examined.
    """

    point_spacing_m: float
    noise_m: float
    node_size_m: float
    surface_share: float
    n_sampled: int
    method: str
    outlier_share: float = float("nan")
    levels: Tuple[ScaleLevel, ...] = ()

    def describe(self) -> str:
        return (
            f"point spacing {self.point_spacing_m:.3g} m and noise {self.noise_m:.3g} m from "
            f"{self.method} of {self.node_size_m:.3g} m ({self.surface_share:.0%} of "
            f"{self.n_sampled} sampled points in surface-like nodes, "
            f"{self.outlier_share:.1%} outliers in them)"
        )


@dataclass(frozen=True)
class _RobustFit:
    """Plane fits of point groups with their clutter set aside (see :func:`_robust_fit`)."""

    mean: np.ndarray  # (K, 3)
    normal: np.ndarray  # (K, 3)
    scales: np.ndarray  # (K, 3) square roots of the ascending eigenvalues
    n_inliers: np.ndarray  # (K,) int64
    ok: np.ndarray  # (K,) bool: at least MIN_SCALE_NODE_POINTS inliers
    inlier: np.ndarray  # (n,) bool per point


def _robust_fit(p: np.ndarray, counts: np.ndarray, kern) -> _RobustFit:
    """Least-squares planes of consecutive groups of ``p``, refitted on their inliers.

    The bands of :func:`_band_refit`, so clutter (vegetation, noise points) neither tilts a
    group's plane nor inflates its scale. Groups left with fewer than
    ``MIN_SCALE_NODE_POINTS`` inliers are not ``ok``.
    """
    starts = np.cumsum(counts) - counts
    mean, evals, normal, _, _ = kern.node_fit(p, starts, counts, 0.0)
    mean, evals, normal, n_in, ok, inlier, _ = _band_refit(
        kern.node_fit, p, counts, mean, evals, normal,
        floor=0.0, tiny=1e-24, min_points=MIN_SCALE_NODE_POINTS,
    )  # fmt: skip
    return _RobustFit(mean, normal, np.sqrt(np.maximum(evals, 0.0)), n_in, ok, inlier)


def _noise_at(pts: np.ndarray, size: float, origin: np.ndarray, kern) -> Tuple[float, float]:
    """Noise (metres) and outlier share from cubic cells of edge ``size`` on two grids.

    Each cell with enough points gets a least-squares plane, then a robust one: points within
    3 MAD-sigmas of the first plane are refitted, so clutter in the cell (vegetation, noise
    points) neither tilts the plane nor inflates its scale. Near-planar cells (robust
    sqrt(l0) <= 0.25 sqrt(l1), spread across the cell) give the noise, their median robust
    scale times sqrt(m / (m - 3)) for m-point fits, and the outlier share, the median share of
    their points beyond 3 sigmas. A surface lying along a cell face leaves one side of its
    noise distribution in the cell (a flat floor on the octree's mid-plane: the half-normal's
    scale is 0.6 sigma), so cells whose plane lies within 3 sigmas of their faces along its
    normal do not count; the grid shifted by half a cell holds such a surface in mid-cell.
    The grids are the octree's (``origin`` its root corner), so the estimate is as invariant
    as the octree (translations, quarter turns). NaN, NaN without any near-planar cell.
    """
    lo = np.asarray(origin, dtype=np.float64) - size  # one cell of margin: indices >= 0
    scales, shares = [], []
    for offset in (0.0, 0.5 * size):
        ijk = np.floor((pts - lo + offset) / size).astype(np.int64)
        dims = ijk.max(axis=0) + 1
        key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        order = np.argsort(key, kind="stable")
        cells, starts, counts = run_boundaries(key[order])
        fit = counts >= MIN_SCALE_NODE_POINTS
        if not fit.any():
            continue
        st, ct = starts[fit], counts[fit]
        p = pts[order[_ranges_to_index(st, ct)]]
        fitq = _robust_fit(p, ct, kern)
        ev = fitq.scales
        near = fitq.ok & (ev[:, 1] >= SURFACE_SPREAD * size) & (2 * fitq.n_inliers >= ct)
        near &= ev[:, 0] <= NOISE_FLATNESS * ev[:, 1]
        c = cells[fit]
        corner = (
            lo
            - offset
            + size
            * np.column_stack([c // (dims[1] * dims[2]), (c // dims[2]) % dims[1], c % dims[2]])
        )
        room = _room_along_normal(fitq.mean, fitq.normal, corner, size)
        good = near & (room >= NOISE_CLEARANCE_SIGMAS * ev[:, 0])
        m = fitq.n_inliers[good]
        scales.append(ev[good, 0] * np.sqrt(m / np.maximum(m - 3.0, 1.0)))
        # outliers of each good cell: beyond 3 sigmas of its robust plane
        owner = np.repeat(np.arange(ct.size), ct)
        d = np.abs(np.einsum("ij,ij->i", p - fitq.mean[owner], fitq.normal[owner]))
        far = np.bincount(owner, weights=d > 3.0 * ev[owner, 0], minlength=ct.size)
        shares.append(far[good] / ct[good])
    both = np.concatenate(scales) if scales else np.empty(0)
    if not both.size:
        return float("nan"), float("nan")
    return float(np.median(both)), float(np.median(np.concatenate(shares)))


def _room_along_normal(
    mean: np.ndarray, normal: np.ndarray, lo: np.ndarray, size: float
) -> np.ndarray:
    """Distance (K,) from each node's centroid to its box's faces along its normal, the nearer
    way (``lo`` (K, 3) the boxes' lower corners, ``size`` their edge)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        up = np.where(normal > 0, (lo + size - mean) / normal, (lo - mean) / normal)
        down = np.where(normal > 0, (mean - lo) / normal, (mean - lo - size) / normal)
    up = np.where(np.abs(normal) > 1e-12, up, np.inf).min(axis=1)
    down = np.where(np.abs(normal) > 1e-12, down, np.inf).min(axis=1)
    return np.minimum(up, down)


def _sample_blocks(
    tree: Octree, target: int = SCALE_SAMPLE_POINTS, block_points: int = SCALE_BLOCK_POINTS
) -> Tuple[np.ndarray, int]:
    """Sorted positions of whole octree blocks spread through the cloud (all points when few),
    and the blocks' level (0 for the whole cloud): coarser levels say nothing of the cloud.

    Blocks are the nodes of the deepest level whose typical block (point-weighted median)
    holds at least ``block_points``; about ``target`` points in all. They
    are chosen by a hash of their point count, so the sample does not depend on the input
    order, and a translation or quarter turn of the cloud (which maps the octree onto itself)
    picks the same blocks.
    """
    n = tree.keys.size
    if n <= target:
        return np.arange(n, dtype=np.int64), 0
    guess = tree.root_size_m * math.sqrt(16.0 / n)  # ~16 points per node on a surface
    level = min(tree.depth, max(1, tree.level_for_size(guess) + 1))
    keys, starts, counts = tree.nodes(level)  # one pass over the keys, then aggregate
    while level > 1 and _weighted_median(counts) < block_points:
        keys, first, _ = run_boundaries(keys >> _U3)
        counts = np.add.reduceat(counts, first)
        starts = starts[first]
        level -= 1
    frac = target / n
    mixed = counts.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing
    take = (mixed >> np.uint64(40)) < np.uint64(int(frac * (1 << 24)))
    if counts[take].sum() < 0.5 * target:  # few distinct counts: every k-th block
        take = np.zeros(counts.size, dtype=bool)
        take[:: max(1, int(round(1.0 / frac)))] = True
    return _ranges_to_index(starts[take], counts[take]), level


def _weighted_median(counts: np.ndarray) -> float:
    """The node count of the median point (point-weighted median of node counts)."""
    c = np.sort(counts)
    return float(c[np.searchsorted(np.cumsum(c), 0.5 * c.sum())])


def _scale_levels(
    tree: Octree, keys: np.ndarray, pts: np.ndarray, kern, *, first_level: int = 1
) -> List[ScaleLevel]:
    """The scale analysis of one sample (sorted ``keys`` and ``pts``), level by level from
    ``first_level`` (the level below the sampled blocks) down."""
    levels: List[ScaleLevel] = []
    for lv in range(max(1, first_level), tree.depth + 1):
        _, starts, counts = run_boundaries(keys >> np.uint64(3 * (tree.depth - lv)))
        fit = counts >= MIN_SCALE_NODE_POINTS
        if not fit.any():
            break
        if counts.size == 1 and lv < tree.depth:
            continue  # one block: too coarse to say anything
        st, ct = starts[fit], counts[fit]
        fitq = _robust_fit(pts[_ranges_to_index(st, ct)], ct, kern)
        ev, n_in = fitq.scales, fitq.n_inliers
        a = tree.cell_size_m(lv)
        # surface-like: flat and spread across the node once its clutter is set aside, and
        # most of its points on that plane
        spread = fitq.ok & (ev[:, 1] >= SURFACE_SPREAD * a) & (2 * n_in >= ct)
        surface = spread & (ev[:, 0] <= SURFACE_FLATNESS * ev[:, 1])
        near = spread & (ev[:, 0] <= NOISE_FLATNESS * ev[:, 1])
        share = float(n_in[surface].sum()) / max(keys.size, 1)
        med = float(np.median(n_in[surface])) if surface.any() else float("nan")
        if near.any():
            m = float(np.median(n_in[near]))
            noise = float(np.median(ev[near, 0])) * math.sqrt(m / max(m - 3.0, 1.0))
        else:
            noise = float("nan")
        levels.append(
            ScaleLevel(a, int(counts.size), int(surface.sum()), int(ct.size), share, med, noise)
        )
        if float(np.max(counts)) < 4 * MIN_SCALE_NODE_POINTS:
            break  # deeper nodes are too small to fit
    return levels


def _speaks(level: ScaleLevel) -> bool:
    """Enough surface-like nodes: 30, or in a small sample a twentieth of the fitted (>= 8),
    holding at least 2 % of the sampled points."""
    need = min(MIN_SURFACE_NODES, max(MIN_SURFACE_NODES_SMALL, 0.05 * level.n_fitted_nodes))
    return level.n_surface_nodes >= need and level.surface_share >= MIN_SURFACE_SHARE


def estimate_scales(
    tree: Octree, ps: np.ndarray, *, grid_origin: Optional[np.ndarray] = None
) -> ScaleEstimate:
    """Point spacing and noise of the surfaces in a cloud, robust to clutter.

    ``ps`` are the tree's points in sorted order, in the tree's coordinates shifted so that
    the root corner is at ``grid_origin`` (default ``tree.origin``: unshifted).

    Whole blocks of the cloud are sampled (:func:`_sample_blocks`). At every octree level
    from the blocks down, each node with at least 12 points gets a plane fit (eigenvalues
    l0 <= l1 <= l2 of its covariance); it is *surface-like* when sqrt(l0) <= 0.15 sqrt(l1)
    and sqrt(l1) >= 0.15 of its edge. Clutter (vegetation, noise points) and nodes smaller
    than the noise are not surface-like, so the analysis reads the surfaces, not the clutter,
    whatever the clutter's share, and at several scales: the level used is the finest whose
    surface share reaches 70 % of the best level's (levels with fewer than 30 surface-like
    nodes, or in a small sample a twentieth of the fitted ones and at least 8, do not count). There

    * spacing = edge / sqrt(median points of the surface-like nodes) (a surface crossing a
      node of edge a holds about a² / s² points);
    * noise = median sqrt(l0) of the near-planar nodes (sqrt(l0) <= 0.25 sqrt(l1)) whose
      plane lies at least 3 sqrt(l0) from the node's faces along its normal (a plane along a
      face leaves half its noise distribution in the node), with the small-sample factor
      sqrt(m / (m - 3)) of an m-point plane fit.

    Written by hand: nearest-neighbour statistics on a k-d tree of the whole cloud cost more
    than the segmentation itself at millions of points, while the octree is already sorted;
    the numpy kernel is used whatever the backend, so both backends get the same parameters.
    """

    kern = NumpyKernels()
    target = SCALE_SAMPLE_POINTS
    while True:
        grow = target // SCALE_SAMPLE_POINTS  # bigger samples of bigger blocks
        idx, block_level = _sample_blocks(tree, target, SCALE_BLOCK_POINTS * grow)
        keys, pts = tree.keys[idx], np.take(ps, idx, axis=0)
        levels = _scale_levels(tree, keys, pts, kern, first_level=block_level + 1)
        eligible = [k for k, v in enumerate(levels) if _speaks(v)]
        raw = [v.surface_share for v in levels]
        best_raw = int(np.argmax(raw)) if raw else 0
        best_ok = max((levels[k].surface_share for k in eligible), default=0.0)
        # surfaces seen clearly only at a scale with too few nodes in the sample, or not at
        # all (dense and noisy clouds: a node must be ~25 noise sigmas wide): sample more
        # points in bigger blocks
        unclear = not eligible or (best_raw not in eligible and raw[best_raw] > 1.3 * best_ok)
        # the best scale at the coarsest level the blocks hold: it may lie beyond them
        unclear |= block_level > 0 and bool(raw) and best_raw == 0
        if raw and unclear and idx.size < tree.keys.size and target < 16 * SCALE_SAMPLE_POINTS:
            target *= 4
            continue
        break
    # a level speaks only with enough surface-like nodes (a few big nodes say little)
    shares = np.array([lvl.surface_share if _speaks(lvl) else 0.0 for lvl in levels])
    if shares.size == 0 or shares.max() < MIN_SURFACE_SHARE:
        nan = float("nan")
        return ScaleEstimate(nan, nan, nan, 0.0, int(idx.size), "occupancy", levels=tuple(levels))
    good = np.flatnonzero(shares >= SURFACE_SHARE_OF_BEST * shares.max())
    k = int(good.max())  # the finest such level
    chosen = levels[k]
    spacing = chosen.node_size_m / math.sqrt(max(chosen.median_points, 1.0))
    corner = tree.origin if grid_origin is None else np.asarray(grid_origin, np.float64)
    noise, outliers = _noise_at(pts, chosen.node_size_m, corner, kern)
    if not np.isfinite(noise):
        noise = chosen.noise_m
    if not np.isfinite(noise):
        noise = float(np.nanmedian([lvl.noise_m for lvl in levels]))
    return ScaleEstimate(
        point_spacing_m=float(spacing),
        noise_m=float(noise),
        node_size_m=float(chosen.node_size_m),
        surface_share=float(chosen.surface_share),
        n_sampled=int(idx.size),
        method="surface-like nodes",
        outlier_share=float(outliers),
        levels=tuple(levels),
    )


def _typical_leaf_points(tree: Octree, level: int, min_points: int) -> float:
    """Median points per fitted node (at least ``min_points``, and 6) at ``level``."""
    _, _, counts = tree.nodes(level)
    ok = counts[counts >= max(min_points, 6)]
    return float(np.median(ok)) if ok.size else float("nan")


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
    quiet: bool = False,
) -> PlaneSet:
    """Find the planar surfaces of a point cloud.

    Parameters
    ----------
    points : (N, 3) float64
        Coordinates, metres (any offset: they are centred internally). Not modified.
    min_node_size_m : float, optional
        Smallest octree leaf edge, metres (leaves are ``root / 2**k``, so the edge used lies in
        ``[min_node_size_m, 2 * min_node_size_m)``). Default: from the point spacing, so that a
        leaf on a surface holds about 30 points.
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
        Smallest reported plane, in points, a third of them inliers of its planar leaves
        (boundary points join planes but do not make them). Default: 3 nominal leaves (30
        points, or 8 noise sigmas wide; at least 30 points), so that single curved patches
        (spheres, tree crowns) are not reported as planes.
    min_leaf_points : int, optional
        Smallest leaf that is fitted. Default 10.
    backend : {'numpy', 'opencl', 'auto'}
        Kernel implementation; both give the same labels.
    progress : callable, optional
        ``progress(fraction, message)``.
    quiet : bool
        Log the estimated scales (spacing, noise, leaf) at DEBUG instead of INFO: for callers
        that segment many pieces (tiles, sides) and log one summary line themselves.

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

    if planarity_ratio is not None and not 0.0 < planarity_ratio <= 1.0:
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
    scales = estimate_scales(tree, ps, grid_origin=tree.origin - centre)
    if scales.method == "occupancy":  # no surface-like node anywhere: the old estimate
        spacing = estimate_point_spacing(tree, occupancy_by_level(tree))
    else:
        spacing = scales.point_spacing_m
    if min_node_size_m is None:
        target = spacing * math.sqrt(TARGET_LEAF_POINTS)
        level = int(round(math.log2(tree.root_size_m / target)))
        leaf_level = max(1, min(tree.depth, level))
        automatic.append("min_node_size_m")
    else:
        leaf_level = max(1, tree.level_for_size(min_node_size_m))
    noise = scales.noise_m
    if not np.isfinite(noise):
        noise, _ = _estimate_noise(tree, ps, leaf_level, min_leaf_points, kernels)
    if min_node_size_m is None and np.isfinite(noise):
        # a leaf must be wide compared with the noise, or its normal is meaningless
        while leaf_level > 1 and tree.cell_size_m(leaf_level) < 8.0 * noise:
            leaf_level -= 1
    leaf_size = tree.cell_size_m(leaf_level)
    typical_n = _typical_leaf_points(tree, leaf_level, min_leaf_points)
    if not np.isfinite(noise):
        noise = 0.01 * leaf_size
        typical_n = float(min_leaf_points)
        log.warning("too few points per leaf to estimate the noise; assuming %.3g m", noise)
    log.log(logging.DEBUG if quiet else logging.INFO, "%s; leaf %.3g m", scales.describe(),
            leaf_size)  # fmt: skip
    if planarity_ratio is None:
        # clutter inside surface leaves (vegetation, noise points) must not fail them
        share = scales.outlier_share if np.isfinite(scales.outlier_share) else 0.0
        planarity_ratio = float(
            np.clip(PLANARITY_RATIO - CLUTTER_RATIO_FACTOR * share, MIN_PLANARITY_RATIO, 0.9)
        )
        automatic.append("planarity_ratio")
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
        # three leaves of the nominal size (30 points, or 8 noise sigmas wide), the smallest
        # resolvable surface of docs/benchmarks.md: not the power-of-two leaf's count, up to
        # 2.8x more or less (and the median leaf is clutter's in a cluttered cloud)
        nominal_n = (max(spacing * math.sqrt(TARGET_LEAF_POINTS), 8.0 * noise) / spacing) ** 2
        min_plane_points = max(30, int(round(MIN_PLANE_LEAVES * nominal_n)))
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
        scale_node_size_m=float(scales.node_size_m),
        surface_share=float(scales.surface_share),
        scale_method=scales.method,
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
    fine_level = min(tree.depth, leaf_level + 1)  # one level of fine leaves (see below) ...
    if tree.cell_size_m(fine_level) < 8.0 * params.noise_m:
        fine_level = leaf_level  # ... wide compared with the noise, as leaves are
    pending: Dict[str, np.ndarray] = {}
    fine_min = min(min_leaf_points, FINE_MIN_POINTS)
    for level in range(top_level, fine_level + 1):
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
        fitted = counts >= (min_leaf_points if level <= leaf_level else fine_min)
        # planar: enough points within the threshold, and spread in two directions (not a line)
        planar = fitted & (n_within >= planarity_ratio * counts)
        planar &= np.sqrt(np.maximum(evals[:, 1], 0.0)) > thr
        # Refit contaminated nodes robustly, so the up to (1 - ratio) points of another surface
        # (at corners and edges) or of clutter (vegetation, noise points) do not tilt the
        # plane; then test again.
        # Above the leaf level only nodes with a majority on their first plane: the others
        # split anyway, and their leaves get the robust refit.
        last = level == fine_level
        flat = evals[:, 0] <= (REFIT_FLATNESS**2) * evals[:, 1]  # not a blob of clutter
        pl = np.flatnonzero(
            fitted
            & (n_within < CONTAMINATED * counts)
            & (planar | (2 * n_within >= counts) | ((level >= leaf_level) & flat))
        )
        if pl.size:
            core = _refit_robust(
                kernels, sub, starts, counts, pl, thr, mean, evals, normal, n_within, within
            )
            planar[pl] = (
                (n_within[pl] >= planarity_ratio * counts[pl])
                & (np.sqrt(np.maximum(evals[pl, 1], 0)) > thr)
                # a surface, not clutter filling the band (vegetation at a low ratio)
                & (core >= SURFACE_CORE_SHARE)
            )
        ratio = np.where(fitted, n_within / counts, np.nan)
        leaf = planar | ~fitted | last
        gstart = starts if active is None else active[starts]
        rec = {
            "key": nkeys,
            "level": np.full(nkeys.size, level, dtype=np.int64),
            "start": gstart,
            "count": counts,
            "planar": planar,
            "mean": mean,
            "normal": normal,
            "ratio": ratio,
            "n_within": np.where(planar, n_within, 0),
        }
        if level > leaf_level:
            # the fine level: a leaf none of whose children is planar (clutter, a tree crown)
            # stays one leaf, so the fine pass adds leaves only where it found a surface
            parent = nkeys >> _U3
            hit = np.unique(parent[planar])
            back = ~np.isin(pending["key"], hit)
            leaf &= np.isin(parent, hit)
            for k in names:
                leaves[k].append(pending[k][back])
        for k in names:
            leaves[k].append(rec[k][leaf])
        if level == leaf_level and fine_level > leaf_level:
            pending = {k: v[~leaf] for k, v in rec.items()}  # split once more below
        pos = np.flatnonzero(np.repeat(planar, counts) & within)
        inlier[pos if active is None else active[pos]] = True
        if not last:
            keep = np.repeat(~leaf, counts)
            active = np.flatnonzero(keep) if active is None else active[keep]
            if active.size == 0:
                break
        report(progress, 0.3 + 0.3 * (level - top_level + 1) / (fine_level - top_level + 1), "")
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
    nseg = roots.size
    seg_of_leaf[planar_ids] = seg
    timings["segments"] = time.perf_counter() - t0
    report(progress, 0.78, "segment refinement")

    # ---- segment refinement: a segment no plane fits is split; touching segments one plane
    # fits are merged (both judged by the RMS of their inlier points against the noise);
    # segments with too little support drop
    t0 = time.perf_counter()
    tol = REFINE_RMS_SIGMAS * params.noise_m
    w_seg, m_seg, c_seg = _segment_moments(
        ps, _inlier_labels(seg_of_leaf, leaf_count, inlier), nseg
    )
    rms_seg = np.sqrt(np.maximum(np.linalg.eigvalsh(c_seg)[:, 0], 0.0))
    bad = np.flatnonzero(rms_seg > SPLIT_RMS_SIGMAS * params.noise_m)
    n_split = 0
    if bad.size and np.isfinite(tol):
        before = nseg
        nseg, pieces = _split_segments(ps, inlier, lv, seg_of_leaf, ni, nj, bad, nseg, tol)
        n_split = nseg - before
        if pieces:
            w_seg = np.concatenate([w_seg, np.zeros(n_split)])
            m_seg = np.concatenate([m_seg, np.zeros((n_split, 3))])
            c_seg = np.concatenate([c_seg, np.zeros((n_split, 3, 3))])
            for sid, (wp, mp, cp) in pieces.items():
                w_seg[sid], m_seg[sid], c_seg[sid] = wp, mp, cp
    seg = seg_of_leaf[planar_ids].astype(np.int64)
    group, g_mean, g_cov = _merge_coplanar(
        seg_of_leaf, ni, nj, w_seg, m_seg, c_seg, tol, noise_m=params.noise_m
    )
    # support = inliers of the plane's planar leaves; boundary points do not make a plane
    sizes = np.bincount(seg, weights=lv["n_within"][planar_ids], minlength=nseg)
    group_size = np.bincount(group, weights=sizes, minlength=nseg)
    # a plane needs min_plane_points in the end (boundary points included, below), and a
    # third of them (one leaf's worth) from its planar leaves: boundary points join planes
    # but do not make them. (Counting only planar-leaf inliers lost sparse walls a leaf or
    # two high, where most leaves hold an edge: 2 pts/m2, 5 m walls of 210 points.)
    min_support = max(3.0, PLANE_SUPPORT_SHARE * params.min_plane_points)
    roots_kept = (group == np.arange(nseg)) & (group_size >= min_support)
    # final ids in Morton order of each group's first leaf
    first_leaf = np.full(nseg, n_leaves, dtype=np.int64)
    np.minimum.at(first_leaf, group[seg], planar_ids)
    kept = np.flatnonzero(roots_kept)
    kept = kept[np.argsort(first_leaf[kept], kind="stable")]
    final_of_root = np.full(nseg, -1, dtype=np.int32)
    final_of_root[kept] = np.arange(kept.size, dtype=np.int32)
    n_merged = int(nseg - np.unique(group).size)
    seg_of_leaf[planar_ids] = final_of_root[group[seg]]
    # the kept planes (from their inliers' moments), in final order
    k_mean, k_normal = g_mean[kept], np.linalg.eigh(g_cov[kept])[1][:, :, 0]
    timings["refinement"] = time.perf_counter() - t0
    report(progress, 0.8, "boundaries")

    # ---- boundaries: unlabelled points (and those of dropped fragments) join a touching plane
    t0 = time.perf_counter()
    lab_sorted = _inlier_labels(seg_of_leaf, leaf_count, inlier)
    # the candidates are measured against their segment's plane (not a neighbour leaf's,
    # whose extension can reach points far from the surface)
    on = planar_ids[seg_of_leaf[planar_ids] >= 0]
    seg_plane = {
        "mean": lv["mean"].copy(),
        "normal": lv["normal"].copy(),
        "count": leaf_count,
        "start": lv["start"],
    }
    seg_plane["mean"][on] = k_mean[seg_of_leaf[on]]
    seg_plane["normal"][on] = k_normal[seg_of_leaf[on]]
    lab_all = lab_sorted.copy()
    _assign_boundaries(
        ps, lab_sorted, lab_sorted >= 0, seg_plane, seg_of_leaf, ni, nj, thr, lab_all=lab_all
    )
    # every labelled point lies within two thresholds of its segment's plane: inliers of a
    # leaf that joined at an angle, and far from the leaf, are let go (two, not one: the noise
    # is one figure for the cloud, and a cloud noisier in parts than the estimate must not
    # have its residuals cut at 3 estimated sigmas). And a plane is a
    # surface when its points crowd its middle like noise does: of those within 3 sigmas,
    # 68 % lie within 1 sigma for Gaussian noise, 33 % for clutter filling the band evenly (a
    # vegetation patch that passed leaf by leaf); such planes are let go.
    extra = np.flatnonzero((lab_all >= 0) & (lab_sorted < 0))  # kept out by the vegetation test
    on = np.flatnonzero(lab_sorted >= 0)
    f = lab_sorted[on]
    dist = np.abs(np.einsum("ij,ij->i", ps[on] - k_mean[f], k_normal[f]))
    far = dist > RELEASE_THRESHOLDS * thr
    # the surface test judges a plane by every point within two thresholds that its touching
    # leaves hold, also those the vegetation test kept out: a patch of crown that passed leaf
    # by leaf shows as clutter only with the crown around it
    fe = lab_all[extra]
    de = np.abs(np.einsum("ij,ij->i", ps[extra] - k_mean[fe], k_normal[fe]))
    fa, da = np.concatenate([f[~far], fe]), np.concatenate([dist[~far], de])
    band = da <= RELEASE_THRESHOLDS * thr
    close = np.bincount(fa[band], weights=da[band] <= thr / PLANARITY_SIGMAS, minlength=kept.size)
    share = close / np.maximum(np.bincount(fa[band], minlength=kept.size), 1)
    # a plane whose points scatter more than the split rule allows (small planes with many
    # boundary points, on rough ground) keeps only those within one threshold
    ms = np.bincount(f, weights=np.where(far, 0.0, dist**2), minlength=kept.size) / np.maximum(
        np.bincount(f, weights=~far, minlength=kept.size), 1.0
    )
    loose = ms > (SPLIT_RMS_SIGMAS * params.noise_m) ** 2
    far |= loose[f] & (dist > thr)
    lab_sorted[on[far]] = -1
    n_final = np.bincount(f[~far], minlength=kept.size)
    clutter = (share < SURFACE_CORE_SHARE) | (n_final < params.min_plane_points)
    if clutter.any():
        renum = np.full(kept.size + 1, -1, dtype=np.int32)
        renum[:-1][~clutter] = np.arange(int((~clutter).sum()), dtype=np.int32)
        lab_sorted = renum[lab_sorted]
        kept = kept[~clutter]
    timings["boundaries"] = time.perf_counter() - t0
    report(progress, 0.85, "plane fits")

    # ---- least-squares planes of the final segments
    t0 = time.perf_counter()
    log.debug(
        "%d segments after %d splits, %d merged into others, %d kept",
        nseg,
        n_split,
        n_merged,
        kept.size,
    )
    planes = _fit_planes(ps, lab_sorted, int(kept.size), centre)
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


def _label_runs(lab: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Runs of equal labels in Morton-ordered ``lab``: the labels of the labelled runs, every
    run's start, which runs are labelled, and the labelled runs' lengths."""
    run_lab, starts, run_n = run_boundaries(lab)
    ok = run_lab >= 0
    return run_lab[ok], starts, ok, run_n[ok]


def _segment_moments(
    ps: np.ndarray, lab: np.ndarray, nseg: int, runs=None
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Count (S,), mean (S, 3) and centred covariance (S, 3, 3) of the points of each label.

    ``lab`` in Morton order, where labels come in long runs: sums are taken per run
    (``reduceat``) and then per label (``bincount``), so no sort of the points is needed; two
    passes (mean, then centred products) for precision. ``runs``: :func:`_label_runs` of
    ``lab`` when the caller has them.
    """
    if nseg == 0 or lab.size == 0:
        return np.zeros(nseg), np.zeros((nseg, 3)), np.zeros((nseg, 3, 3))
    rl, starts, ok, run_n = runs if runs is not None else _label_runs(lab)
    cnt = np.bincount(rl, weights=run_n, minlength=nseg).astype(np.float64)
    safe = np.maximum(cnt, 1.0)

    def per(values: np.ndarray) -> np.ndarray:
        sums = np.add.reduceat(values, starts)[ok]
        return np.bincount(rl, weights=sums, minlength=nseg).astype(np.float64)

    mean = np.stack([per(np.ascontiguousarray(ps[:, a])) for a in range(3)], axis=1)
    mean /= safe[:, None]
    table = np.vstack([mean, np.zeros((1, 3))])  # label -1 -> the zero row (ignored)
    d = [ps[:, a] - table[lab, a] for a in range(3)]
    cov = np.empty((nseg, 3, 3))
    for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
        v = per(d[a] * d[b]) / safe
        cov[:, a, b] = v
        cov[:, b, a] = v
    return cnt, mean, cov


def _inlier_labels(seg_of_leaf: np.ndarray, leaf_count: np.ndarray, inlier: np.ndarray):
    """Segment of each sorted point that is an inlier of a planar leaf, else -1."""
    lab = np.repeat(seg_of_leaf, leaf_count)
    lab[~inlier] = -1
    return lab


def _leaf_moments(
    ps: np.ndarray, inlier: np.ndarray, lv: Dict[str, np.ndarray], leaves: np.ndarray
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inlier count (K,), mean (K, 3) and centred covariance (K, 3, 3) of the given leaves."""
    pos = _ranges_to_index(lv["start"][leaves], lv["count"][leaves])
    owner = np.repeat(np.arange(leaves.size), lv["count"][leaves])
    keep = inlier[pos]
    pos, owner = pos[keep], owner[keep]
    k = leaves.size
    cnt = np.bincount(owner, minlength=k).astype(np.float64)
    safe = np.maximum(cnt, 1.0)
    pts = np.take(ps, pos, axis=0)
    mean = np.stack([np.bincount(owner, weights=pts[:, a], minlength=k) for a in range(3)], 1)
    mean /= safe[:, None]
    d = pts - mean[owner]
    cov = np.empty((k, 3, 3))
    for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)):
        v = np.bincount(owner, weights=d[:, a] * d[:, b], minlength=k) / safe
        cov[:, a, b] = v
        cov[:, b, a] = v
    return cnt, mean, cov


def _combine(wa, ma, ca, wb, mb, cb) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weight (K,), mean (K, 3) and centred covariance (K, 3, 3) of two weighted point sets
    united, from theirs (parallel-axis theorem; covariances are scatter / weight)."""
    w = wa + wb
    m = (wa[:, None] * ma + wb[:, None] * mb) / w[:, None]
    da, db = ma - m, mb - m
    cov = (
        wa[:, None, None] * (ca + da[:, :, None] * da[:, None, :])
        + wb[:, None, None] * (cb + db[:, :, None] * db[:, None, :])
    ) / w[:, None, None]
    return w, m, cov


def _union(w, m, c, i: int, j: int) -> None:
    """Moments of set i := set i united with set j (in place)."""
    w[i : i + 1], m[i : i + 1], c[i : i + 1] = _combine(
        w[i : i + 1], m[i : i + 1], c[i : i + 1], w[j : j + 1], m[j : j + 1], c[j : j + 1]
    )


def _split_segments(
    ps: np.ndarray,
    inlier: np.ndarray,
    lv: Dict[str, np.ndarray],
    seg_of_leaf: np.ndarray,
    ni: np.ndarray,
    nj: np.ndarray,
    bad: np.ndarray,
    nseg: int,
    tolerance_m: float,
) -> Tuple[int, Dict[int, Tuple[float, np.ndarray, np.ndarray]]]:
    """Split segments that are not one plane into pieces that are (``seg_of_leaf`` in place).

    Region growing compares each leaf with its neighbour only, so a curved surface (ground,
    a vault, a cone) or a ridge strip can chain into one segment that no plane fits. Each
    segment of ``bad`` is grown again from its best leaf (most inliers): a touching leaf of
    the segment joins the piece when one plane still fits all the piece's inlier points
    with an RMS of at most ``tolerance_m``; then the next piece starts from the best leaf left.
    Pieces get new segment ids from ``nseg`` on (the first keeps the segment's); returns the
    new number of segments and ``{segment id: (inlier count, mean, centred covariance)}`` of
    every piece, from the leaves' moments (no pass over the points).
    """
    pieces: Dict[int, Tuple[float, np.ndarray, np.ndarray]] = {}
    for s in bad:
        leaves = np.flatnonzero(seg_of_leaf == s)
        if leaves.size < 2:
            continue
        w, m, c = _leaf_moments(ps, inlier, lv, leaves)
        wl, ml, cl = w.tolist(), m.tolist(), c.tolist()
        local = {int(g): k for k, g in enumerate(leaves)}
        sel = np.isin(ni, leaves) & np.isin(nj, leaves)
        adj: Dict[int, List[int]] = {}
        for x, y in zip(ni[sel].tolist(), nj[sel].tolist()):
            adj.setdefault(local[x], []).append(local[y])
        left = np.ones(leaves.size, dtype=bool)
        order = np.argsort(-w, kind="stable")
        first = True
        for seed in order:
            if not left[seed]:
                continue
            left[seed] = False
            pw, pm, pc = wl[seed], ml[seed], cl[seed]
            members, queue = [seed], list(adj.get(seed, []))
            while queue:
                j = queue.pop(0)
                if not left[j]:
                    continue
                tw, tm, tc = _combine_one(pw, pm, pc, wl[j], ml[j], cl[j])
                if math.sqrt(_lambda_min(tc)) > tolerance_m:
                    continue  # another neighbour may still bring it in later
                pw, pm, pc = tw, tm, tc
                left[j] = False
                members.append(j)
                queue.extend(adj.get(j, []))
            piece = (float(pw), np.array(pm), np.array(pc))
            if first:
                pieces[int(s)] = piece
            else:
                seg_of_leaf[leaves[members]] = nseg
                pieces[nseg] = piece
                nseg += 1
            first = False
    return nseg, pieces


def _merge_coplanar(
    seg_of_leaf: np.ndarray,
    ni: np.ndarray,
    nj: np.ndarray,
    counts: np.ndarray,
    means: np.ndarray,
    covs: np.ndarray,
    tolerance_m: float,
    *,
    noise_m: float = float("nan"),
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge touching segments that are one plane.

    Returns each segment's group (its root, (S,) int64) and the groups' inlier means and
    centred covariances at their roots ((S, 3), (S, 3, 3)).

    A surface is split into fragments where leaf normals, noisy over one leaf, disagree by
    more than the angle threshold. Two touching segments (a leaf of one is a neighbour of a
    leaf of the other) are one plane when a single plane fits the inlier points of both with
    an RMS of at most ``tolerance_m``, computed exactly from the segments' moments (``counts``
    (S,), ``means`` (S, 3), centred ``covs`` (S, 3, 3)). Pairs are merged greedily from the
    best fit, always testing the whole groups, so a small fragment at a corner joins the wall
    that fits it and never chains two walls together. Backend independent.

    With ``noise_m`` (sigma), a union whose RMS exceeds the tolerance still merges when one
    plane instead of two adds no more to the residual sum of squares than noise does: at most
    ``MERGE_CHI2`` sigma² (the 99.9 % point of chi-square with 3 degrees of freedom, the
    parameters one plane fewer frees). The RMS of a few dozen points scatters by ~10 %, so
    small pieces of one sparse wall failed the RMS rule by chance; two surfaces at an angle
    or apart add far more.
    """
    nseg = counts.size
    group = np.arange(nseg, dtype=np.int64)
    if nseg < 2 or not np.isfinite(tolerance_m):
        return group, means, covs
    a_seg, b_seg = seg_of_leaf[ni].astype(np.int64), seg_of_leaf[nj].astype(np.int64)
    touch = (a_seg >= 0) & (b_seg >= 0) & (a_seg < b_seg)
    ba, bb = _bridged_pairs(seg_of_leaf, ni, nj, nseg)
    if ba.size:
        # pieces of one surface have normals within the widest angle threshold (15 deg);
        # on rough ground a free leaf reaches many segments at all angles
        nrm = np.linalg.eigh(covs)[1][:, :, 0]
        keep = np.abs(np.einsum("ij,ij->i", nrm[ba], nrm[bb])) >= math.cos(math.radians(15.0))
        ba, bb = ba[keep], bb[keep]
    if not touch.any() and not ba.size:
        return group, means, covs
    pair = np.unique(np.concatenate([a_seg[touch] * nseg + b_seg[touch], ba * nseg + bb]))
    pa, pb = pair // nseg, pair % nseg
    w, m, c = counts.astype(np.float64).copy(), means.copy(), covs.copy()
    ok = (w[pa] > 0) & (w[pb] > 0)
    pa, pb = pa[ok], pb[ok]
    rms, ok = _merge_test(w[pa], m[pa], c[pa], w[pb], m[pb], c[pb], tolerance_m, noise_m)
    cand = np.flatnonzero(ok)
    cand = cand[np.argsort(rms[cand], kind="stable")]

    def find(i: int) -> int:
        while group[i] != i:
            group[i] = group[group[i]]
            i = int(group[i])
        return i

    # the greedy loop tests one pair at a time: plain floats, not 1-element arrays
    wl, ml, cl = w.tolist(), m.tolist(), c.tolist()
    ll = [_lambda_min(x) for x in cl]
    noise2 = noise_m**2 if np.isfinite(noise_m) and noise_m > 0 else -1.0
    for k in cand:
        ra, rb = find(int(pa[k])), find(int(pb[k]))
        if ra == rb:
            continue
        lo, hi = min(ra, rb), max(ra, rb)
        wu, mu, cu = _combine_one(wl[lo], ml[lo], cl[lo], wl[hi], ml[hi], cl[hi])
        lam = _lambda_min(cu)
        rms = math.sqrt(lam)
        fits = rms <= tolerance_m
        if not fits and noise2 > 0:
            extra = wu * lam - wl[lo] * ll[lo] - wl[hi] * ll[hi]
            spread = 1.0 + MERGE_RMS_SDS / math.sqrt(2.0 * max(wu, 1.0))
            fits = extra <= MERGE_CHI2 * noise2 and rms <= tolerance_m * spread
        if not fits:
            continue
        wl[lo], ml[lo], cl[lo], ll[lo] = wu, mu, cu, lam
        group[hi] = lo
    w[:] = wl
    m[:] = np.array(ml).reshape(-1, 3)
    c[:] = np.array(cl).reshape(-1, 3, 3)
    return np.array([find(i) for i in range(nseg)], dtype=np.int64), m, c


def _bridged_pairs(
    seg_of_leaf: np.ndarray, ni: np.ndarray, nj: np.ndarray, nseg: int
) -> Tuple[np.ndarray, np.ndarray]:
    """Pairs (a < b) of segments that both touch one leaf of no segment.

    Where few points fill a leaf (airborne densities: a wall a leaf or two high), the leaves
    along an edge, a window or a tree fail the planarity test and cut one surface into pieces
    that do not touch; such pieces are merge candidates too (the merge's test decides).
    """
    from scipy import sparse

    s = seg_of_leaf.astype(np.int64)
    n = s.size
    e = (s[ni] < 0) & (s[nj] >= 0)
    if not e.any():
        return np.empty(0, np.int64), np.empty(0, np.int64)
    touch = sparse.csr_matrix(
        (np.ones(int(e.sum()), dtype=np.int32), (ni[e], s[nj[e]])), shape=(n, nseg)
    )
    reach = touch.tocsr()
    reach.sum_duplicates()
    reach.sort_indices()
    size = np.diff(reach.indptr)
    seg = reach.indices.astype(np.int64)
    first = reach.indptr[:-1]
    rank = np.arange(seg.size) - np.repeat(first, size)
    later = np.repeat(size, size) - rank - 1  # partners after each element in its row
    a = np.repeat(np.arange(seg.size), later)
    step = np.arange(a.size) - np.repeat(np.cumsum(later) - later, later) + 1
    code = np.unique(seg[a] * nseg + seg[a + step])
    return code // nseg, code % nseg


def _merge_test(wa, ma, ca, wb, mb, cb, tolerance_m, noise_m):
    """RMS (K,) of each pair's union about its best plane, and whether the pair is one plane:
    that RMS within ``tolerance_m``, or (``noise_m`` finite) one plane for both adds at most
    ``MERGE_CHI2`` noise variances to the residual sum of squares of two."""
    cov = _combine(wa, ma, ca, wb, mb, cb)[2]
    lam = np.maximum(np.linalg.eigvalsh(cov)[:, 0], 0.0)
    rms = np.sqrt(lam)
    ok = rms <= tolerance_m
    if np.isfinite(noise_m) and noise_m > 0:
        la = np.maximum(np.linalg.eigvalsh(ca)[:, 0], 0.0)
        lb = np.maximum(np.linalg.eigvalsh(cb)[:, 0], 0.0)
        extra = (wa + wb) * lam - wa * la - wb * lb
        # ... as far as the RMS of so few points scatters (relative sd 1 / sqrt(2 n))
        spread = 1.0 + MERGE_RMS_SDS / np.sqrt(2.0 * np.maximum(wa + wb, 1.0))
        ok |= (extra <= MERGE_CHI2 * noise_m**2) & (rms <= tolerance_m * spread)
    return rms, ok


def _combine_one(wa, ma, ca, wb, mb, cb):
    """:func:`_combine` of one pair given as floats and nested lists (the greedy loop)."""
    w = wa + wb
    m = [(wa * ma[i] + wb * mb[i]) / w for i in range(3)]
    da = [ma[i] - m[i] for i in range(3)]
    db = [mb[i] - m[i] for i in range(3)]
    c = [
        [(wa * (ca[i][j] + da[i] * da[j]) + wb * (cb[i][j] + db[i] * db[j])) / w for j in range(3)]
        for i in range(3)
    ]
    return w, m, c


def _lambda_min(c) -> float:
    """Smallest eigenvalue of a symmetric 3x3 matrix (nested lists), closed form (Smith 1961):
    numpy's eigvalsh on one 3x3 costs ~20 us of call overhead, this ~2 us; agrees to 1e-12
    of the largest eigenvalue (tested)."""
    a, b, d = c[0][0], c[1][1], c[2][2]
    p1 = c[0][1] ** 2 + c[0][2] ** 2 + c[1][2] ** 2
    q = (a + b + d) / 3.0
    p2 = (a - q) ** 2 + (b - q) ** 2 + (d - q) ** 2 + 2.0 * p1
    if p2 <= 0.0:
        return max(q, 0.0)
    p = math.sqrt(p2 / 6.0)
    b00, b11, b22 = (a - q) / p, (b - q) / p, (d - q) / p
    b01, b02, b12 = c[0][1] / p, c[0][2] / p, c[1][2] / p
    det = (
        b00 * (b11 * b22 - b12 * b12)
        - b01 * (b01 * b22 - b12 * b02)
        + b02 * (b01 * b12 - b11 * b02)
    )
    r = min(max(det / 2.0, -1.0), 1.0)
    phi = math.acos(r) / 3.0
    return max(q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0), 0.0)


def _merged_rms(wa, ma, ca, wb, mb, cb) -> np.ndarray:
    """RMS about the best plane of two weighted point sets given by their moments.

    ``w`` (K,) weights, ``m`` (K, 3) means, ``c`` (K, 3, 3) centred covariances (/ w).
    """
    cov = _combine(wa, ma, ca, wb, mb, cb)[2]
    return np.sqrt(np.maximum(np.linalg.eigvalsh(cov)[:, 0], 0.0))


def _assign_boundaries(
    ps: np.ndarray,
    lab: np.ndarray,
    inlier: np.ndarray,
    lv: Dict[str, np.ndarray],
    seg_of_leaf: np.ndarray,
    ni: np.ndarray,
    nj: np.ndarray,
    threshold: float,
    lab_all: Optional[np.ndarray] = None,
) -> None:
    """Unlabelled points join the closest plane of a touching planar leaf (in place).

    For every leaf, only one planar neighbour per segment is tried: the one whose centroid is
    nearest the leaf's. A point joins the segment whose plane is nearest, if within
    ``threshold``, unless the vegetation test turns the leaf's points away from that plane;
    ``lab_all`` (optional, in place) gets the assignment without that test (what the final
    surface test of a plane judges it by).
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
    pair = np.repeat(ptr[cl], cnt) + rank  # index of (leaf, segment) in bi, bj
    j = bj[pair]
    pos = cand[rep]
    dist = np.abs(
        ps[pos, 0] * nrm[j, 0]
        + ps[pos, 1] * nrm[j, 1]
        + ps[pos, 2] * nrm[j, 2]
        - np.einsum("ij,ij->i", cen, nrm)[j]
    )
    dist[dist > threshold] = np.inf
    # vegetation test: a leaf gives a plane its points only when those within the threshold
    # crowd the plane like a surface's noise (of those within 3 sigmas, half within 1 sigma:
    # 68 % for a surface, 33 % for a tree crown filling the band), so canopy beside a roof or
    # over the ground does not join it
    if lab_all is not None:
        _nearest_into(lab_all, cand, rep, j, cnt, dist, seg_of_leaf)
    band = np.isfinite(dist)
    if band.any():
        n3 = np.bincount(pair[band], minlength=bj.size)
        n1 = np.bincount(
            pair[band], weights=dist[band] <= threshold / PLANARITY_SIGMAS, minlength=bj.size
        )
        crowd = n1 >= SURFACE_CORE_SHARE * n3 - 0.5  # half a point: one point proves nothing
        dist = np.where(band & ~crowd[pair], np.inf, dist)
    _nearest_into(lab, cand, rep, j, cnt, dist, seg_of_leaf)


def _nearest_into(lab, cand, rep, j, cnt, dist, seg_of_leaf) -> None:
    """Each candidate (pairs grouped by candidate) takes the segment of its nearest finite pair."""
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
    """Least-squares planes of the labelled points (moments: :func:`_segment_moments`)."""
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
    runs = _label_runs(lab)
    rl, starts, ok, _ = runs
    counts, mean, cov = _segment_moments(ps, lab, nplanes, runs)
    evals, evecs = np.linalg.eigh(cov)
    normals = orient_normals(evecs[:, :, 0])
    centroids = mean + centre
    ext_min = np.full((nplanes, 3), np.inf)
    ext_max = np.full((nplanes, 3), -np.inf)
    for a in range(3):
        col = np.ascontiguousarray(ps[:, a])
        np.minimum.at(ext_min[:, a], rl, np.minimum.reduceat(col, starts)[ok])
        np.maximum.at(ext_max[:, a], rl, np.maximum.reduceat(col, starts)[ok])
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
