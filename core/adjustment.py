"""Gauss-Helmert adjustment of a rigid motion from point-on-plane conditions (block-reduced).

Kusari et al. (2019), section II.D (Eq. 9-11) and Appendix (Eq. 14-17), with these choices:

* Model. Before-epoch points ``p`` and after-epoch points ``q`` of plane ``i`` lie on the same
  plane ``n_i . x + d_i = 0`` once the motion ``q = R p + t`` is undone. Conditions (one per
  point, coordinates centred on ``centre``)::

      before:  f = n_i . p + d_i                       = 0     B = n_i
      after:   f = (R n_i) . (q - t) + d_i             = 0     B = m_i = R n_i

  plus one hard constraint per plane ``|n_i|^2 - 1 = 0`` (Eq. 15-16).
* Unknowns. ``x1 = (alpha, beta, gamma, tx, ty, tz)`` and ``x2_i = (a, b, c, d)``. The rotation
  is kept as a proper rotation matrix ``R0``; each iteration linearises the small-angle form
  ``R = (I + [dw]x) R0`` (Eq. 9's matrix applied to the increment) and updates
  ``R0 <- exp([dw]x) R0`` (Rodrigues). The reported angles are the rotation vector of ``R0``,
  equal to Eq. 9's ``alpha, beta, gamma`` to first order.
* Linearisation (after point, ``x = q - t0``, ``m = R0 n``)::

      A1 = [ m x x ,  -m ]   (1x6)     A2 = [ R0^T x , 1 ]   (1x4)     w = m . x + d

  (before point: ``A1 = 0``, ``A2 = [p, 1]``, ``w = n . p + d``). The condition is linear in the
  observations, so the misclosure at the observed coordinates is exact; ``A`` is evaluated at
  the observed coordinates (for isotropic covariances this has the same fixed point as the
  rigorous Gauss-Helmert iteration: orthogonal regression).
* Weights. Each condition has variance ``B C B^T`` (scalar), weight ``1 / (B C B^T)``.
* Normal equations (Eq. 17 with a hard constraint):
  ``[[N11, N12, 0], [N12^T, N22, G^T], [0, G, 0]] [d1; d2; k] = -[u1; u2; wc]``,
  ``G_i = [2 n_i, 0]``, ``wc_i = |n_i|^2 - 1``. Every plane's 4x4 ``N22_i`` is bordered by its
  constraint into a 5x5 block, solved for all planes at once (stacked ``np.linalg.solve``) and
  Schur-complemented into the 6x6 reduced system
  ``Nred = N11 - sum_i N12_i K_i^-1 N12_i^T``; plane corrections are back-substituted.
* Linear cost. All rows of one plane and epoch are affine in the point's offset ``u`` from the
  plane's centroid, so every block follows from the weighted moments ``sum w``, ``sum w u``,
  ``sum w u u^T`` per plane and epoch (``np.bincount``). With a scalar or per-axis sigma the
  weights are constant per plane and epoch, so the moments are computed once and an iteration
  costs O(planes); with per-point covariances each iteration recomputes them in O(points).
* Robustness: after convergence each plane's difference of weighted mean misclosures (after -
  before) is tested against a Bonferroni-corrected normal quantile (``alpha / planes``,
  two-sided), scaled by the a-posteriori variance factor; the worst significant plane is
  removed and the adjustment repeated (data snooping).
* Observation strength: the 3x3 translation block of the reduced normal matrix is
  eigen-decomposed; directions with eigenvalue below ``WEAK_RATIO`` x the largest are reported.
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass, replace
from statistics import NormalDist
from typing import List, Optional, Tuple

import numpy as np

from . import stochastic as _stoch
from .errors import InputDataError, InvalidParameterError
from .planes import orient_normals
from .progress import ProgressCallback, report
from .rotation import rotation_matrix, rotation_vector
from .rotation import skew as _skew
from .stochastic import PlaneModel, VarianceComponents
from .unit_contrasts import epoch_rows, screen_contrasts, unit_contrasts, with_contrast_units
from .unit_drift import UNIT_INTERVALS_S, check_unit_time, hat_unit_shares, hat_unit_tilt_shares

log = logging.getLogger(__name__)

__all__ = ["PackedCovariance", "RigidResult", "adjust_rigid", "adjust_rigid_dense"]

WEAK_RATIO = 1e-3  # translation eigenvalue ratio below which a direction is weakly constrained
SINGULAR_RATIO = 1e-6  # ... and below which it is unconstrained (singular system)
DENSE_MAX_UNKNOWNS = 2000  # adjust_rigid_dense refuses bigger problems
MAX_REJECTED_SHARE = 0.5  # data snooping stops before rejecting more than this share of planes
NCOL = 11  # row columns: motion (6), plane a b c d (4), plane offset δ (1)
_XD = [0, 1, 2, 3, 4, 5, 10]  # motion and δ columns
MAX_OUTER = 8  # stochastic models: rounds of (adjustment, components, plane tests)
MAX_GROSS_PASSES = 5  # robust-start passes (gross outliers) before the components
#: with too few planes to estimate it, the plane component is at least this share of the
#: a-priori point σ (a survey-level error of a quarter of the point noise: 5 mm for 2 cm MLS)
PRIOR_PLANE_SHARE = 0.25


@dataclass(frozen=True)
class RigidResult:
    """Result of :func:`adjust_rigid`.

    Attributes
    ----------
    params : (6,) float64
        ``alpha, beta, gamma`` (radians, rotation vector of the before->after rotation about the
        x, y, z axes through ``centre``) and ``tx, ty, tz`` (metres, displacement of the
        material at ``centre``): ``after = R (before - centre) + centre + t``.
    covariance : (6, 6) float64
        A-posteriori covariance (rad², rad·m, m²): ``variance_factor * cofactor`` for the
        white model; the inverse of the plane-level GLS normal matrix with the estimated
        components for the "plane" and "full" models.
    cofactor : (6, 6) float64
        ``Qxx``: inverse of the reduced normal matrix (white: a-priori covariance of
        ``params``; stochastic models: equal to ``covariance``).
    sigma : (6,) float64
        Square roots of the diagonal of ``covariance``.
    variance_factor : float
        ``sigma0² = v^T P v / redundancy`` of the point residuals (NaN if the redundancy is 0);
        stochastic models: with each plane's offset removed (the white point-noise component).
    redundancy : int
        Conditions + constraints - unknowns.
    iterations : int
        Gauss-Helmert iterations of the final adjustment.
    converged : bool
        Whether the last increment was below the tolerance.
    centre : (3,) float64
        Centre of the coordinates (metres, input frame).
    n_planes : int
        Planes used in the final adjustment.
    n_points : int
        Points (both epochs) used in the final adjustment.
    plane_params : (b, 4) float64
        ``a, b, c, d`` of every plane in the input (uncentred) frame of the before epoch:
        ``a x + b y + c z + d = 0``. Rejected planes hold their before-epoch fit; planes without
        points hold NaN.
    residuals_before, residuals_after : (N1,), (N2,) float64
        Signed orthogonal point-to-plane misclosures after the adjustment (metres; after points
        are first moved back by the motion). NaN for ignored points (plane index < 0).
    rejected_planes : tuple of (int, str)
        Planes left out, with the reason (and the test statistic for outliers).
    translation_eigenvalues : (3,) float64
        Ascending eigenvalues of the translation block of the reduced normal matrix (1/m²).
    translation_eigenvectors : (3, 3) float64
        The corresponding unit eigenvectors, as columns.
    weak_directions : tuple of str
        Warnings about weakly constrained translation directions.
    stochastic_model : str
        "white", "plane" or "full" (see :mod:`.stochastic`).
    variance_components : VarianceComponents or None
        The estimated components (None for the white model).
    plane_weights : (b,) float64 or None
        Stochastic models: 1 for a plane used at full weight, its IGG-III weight (0, 1) when
        down-weighted, 0 when rejected, NaN when never used.
    plane_w : (b,) float64 or None
        w-test statistic of each active plane's misclosure against the plane-level spread.
    plane_offset_m : (b,) float64 or None
        Predicted (BLUP) after-epoch offset ``δ`` of each active plane along its normal, m.
    plane_misclosure_m : (b,) float64 or None
        After-minus-before mean misclosure of each plane along its normal, metres.
    downweighted_planes : tuple of (int, float)
        Planes kept with a weight below 1, and the weight.
    plane_gain : PlaneGain or None
        Stochastic models: the motion's linear dependence on the plane-level random effects
        and the components in force, for the covariance with another adjustment of the same
        survey (:func:`.stochastic.cross_covariance`; the two sides of a fault).
    """

    params: np.ndarray
    covariance: np.ndarray
    cofactor: np.ndarray
    sigma: np.ndarray
    variance_factor: float
    redundancy: int
    iterations: int
    converged: bool
    centre: np.ndarray
    n_planes: int
    n_points: int
    plane_params: np.ndarray
    residuals_before: np.ndarray
    residuals_after: np.ndarray
    rejected_planes: Tuple[Tuple[int, str], ...]
    translation_eigenvalues: np.ndarray
    translation_eigenvectors: np.ndarray
    weak_directions: Tuple[str, ...]
    stochastic_model: str = "white"
    variance_components: Optional[VarianceComponents] = None
    plane_weights: Optional[np.ndarray] = None
    plane_w: Optional[np.ndarray] = None
    plane_offset_m: Optional[np.ndarray] = None
    plane_misclosure_m: Optional[np.ndarray] = None
    downweighted_planes: Tuple[Tuple[int, float], ...] = ()
    plane_gain: Optional[_stoch.PlaneGain] = None

    @property
    def displacement(self) -> np.ndarray:
        """(3,) translation ``tx, ty, tz`` in metres."""
        return self.params[3:].copy()

    @property
    def displacement_covariance(self) -> np.ndarray:
        """(3, 3) covariance of :attr:`displacement`, m²."""
        return self.covariance[3:, 3:].copy()


# --------------------------------------------------------------------------- helpers


def _describe_direction(v: np.ndarray) -> str:
    """'azimuth 37° (horizontal)' for a unit vector (azimuth clockwise from +y = north)."""
    v = v if (v[2] > 0 or (v[2] == 0 and v[1] >= 0)) else -v
    elev = math.degrees(math.asin(min(1.0, abs(float(v[2])))))
    if elev > 80:
        return "the vertical"
    az = math.degrees(math.atan2(float(v[0]), float(v[1]))) % 180.0
    kind = "horizontal" if elev < 10 else f"inclined {elev:.0f}° from the horizontal"
    return f"azimuth {az:.0f}° ({kind})"


# --------------------------------------------------------------------------- inputs


#: per-point covariances: a condition's weight 1/(B C B^T) is re-evaluated only when a plane
#: normal has turned by more than this (radians) since it was computed. Reused weights only
#: slow the convergence a little: once the iteration converges on reused weights, one more
#: step with weights evaluated at the solution is taken (``_iterate``), so the result is that
#: of fresh weights. A converged adjustment then needs two or three passes over the points
#: instead of one per iteration.
WEIGHT_REUSE_RAD = 1e-2
#: the units' drift tilts the planes as well as moving them (:func:`.unit_drift.
#: hat_unit_tilt_shares`): when True the tilts enter the motion's GLS jointly with the
#: offsets through the units' errors (:func:`_drift_tilt_terms`); a prototype, off
UNIT_DRIFT_TILTS = False


class _Epoch:
    """One epoch's valid points, grouped by plane through moments.

    idx : (n,) int64 plane of each valid point; u : (n, 3) offset from its plane's centroid
    (centred frame); g : (b, 3) plane centroids (centred frame); count : (b,) points per plane;
    var : (3,) per-axis variance (uniform mode) or None; cov : per-point (n, 3) variances or
    (n, 3, 3) covariances, or None; U1, U2 : unweighted moments (uniform mode).
    """

    def __init__(self, pts, labels, sigma, b, centre, name):
        valid = labels >= 0
        self.valid = valid
        self.all_valid = bool(valid.all())
        self.idx = labels[valid].astype(np.int64) if not self.all_valid else labels.astype(np.int64)
        x = pts[valid] if not self.all_valid else pts
        x = x - centre  # new array: inputs are never modified
        self.count = np.bincount(self.idx, minlength=b).astype(np.float64)
        safe = np.maximum(self.count, 1.0)
        self.g = np.stack([np.bincount(self.idx, x[:, k], b) / safe for k in range(3)], axis=1)
        x -= self.g[self.idx]
        self.u = x
        self.var, self.cov, self.packed = _parse_sigma(
            sigma, pts.shape[0], valid, self.all_valid, name
        )
        self.U1 = self.U2 = None
        if self.var is not None:
            self.U1, self.U2 = _moments(self.idx, self.u, None, b)

    def of_valid(self, a):
        """A per-point array of the epoch's input restricted to its valid points (None
        passes)."""
        return a if a is None or self.all_valid else a[self.valid]

    def weighted(self, bvec: np.ndarray, b: int):
        """Weighted moments S0 (b,), S1 (b, 3), S2 (b, 3, 3) for condition directions bvec."""
        if self.var is not None:
            w = 1.0 / ((bvec * bvec) @ self.var)
            return self.count * w, self.U1 * w[:, None], self.U2 * w[:, None, None]
        cached = getattr(self, "_cache", None)
        if cached is not None and cached[0].shape == bvec.shape:
            turned = np.max(np.abs(bvec - cached[0]), initial=0.0)
            if turned <= WEIGHT_REUSE_RAD:
                self.stale = True
                return cached[1]
        out = self._weighted_points(bvec, b)
        self._cache = (bvec.copy(), out)
        self.stale = False
        return out

    def refresh(self) -> None:
        """Forget cached per-point weights (the next step evaluates them afresh)."""
        self._cache = None
        self.stale = False

    def _weighted_points(self, bvec: np.ndarray, b: int):
        if not self.packed:
            s = np.einsum("ij,ij->i", bvec[self.idx] ** 2, self.cov)
        else:
            # b C b^T of a symmetric C from its six packed rows, per plane first: the products
            # of the plane's direction components are (b,) arrays, gathered once per term
            b0, b1, b2 = bvec[:, 0], bvec[:, 1], bvec[:, 2]
            terms = (b0 * b0, b1 * b1, b2 * b2, 2.0 * b0 * b1, 2.0 * b0 * b2, 2.0 * b1 * b2)
            s = terms[0][self.idx] * self.cov[0]
            for k in range(1, 6):
                s += terms[k][self.idx] * self.cov[k]
        w = 1.0 / s
        s1, s2 = _moments(self.idx, self.u, w, b)
        return np.bincount(self.idx, w, b), s1, s2


class _MomentEpoch:
    """One epoch given by its per-plane moments instead of its points (scalar or per-axis
    sigma): the uniform branch of :class:`_Epoch` (see :func:`adjust_rigid_moments`).

    count : (b,) points per plane; g : (b, 3) plane centroids (centred frame); U2 : (b, 3, 3)
    scatter about the centroid; U1 is zero by construction. No per-point data (``idx``, ``u``
    are None), so the result has no per-point residuals.
    """

    cov = None
    packed = False
    idx = None
    u = None
    all_valid = True
    stale = False

    def __init__(self, count, g, scatter, sigma, name):
        self.count = np.asarray(count, dtype=np.float64)
        self.g = np.asarray(g, dtype=np.float64)
        self.U1 = np.zeros_like(self.g)
        self.U2 = np.asarray(scatter, dtype=np.float64)
        s = np.asarray(sigma, dtype=np.float64)
        if s.ndim not in (0, 1):
            raise InvalidParameterError(
                f"sigma_{name}: planes given by their moments take a scalar or (3,) per-axis "
                "sigma, not per-point sigmas"
            )
        self.var, _, _ = _parse_sigma(sigma, 0, None, True, name)

    def weighted(self, bvec: np.ndarray, b: int):
        w = 1.0 / ((bvec * bvec) @ self.var)
        return self.count * w, self.U1 * w[:, None], self.U2 * w[:, None, None]

    def refresh(self) -> None:
        pass


def _moments(idx, u, w, b):
    """Per-plane sum(w u) (b, 3) and sum(w u u^T) (b, 3, 3) (w=None: unit weights)."""
    s1 = np.empty((b, 3))
    s2 = np.empty((b, 3, 3))
    wu = [u[:, k] if w is None else u[:, k] * w for k in range(3)]
    for k in range(3):
        s1[:, k] = np.bincount(idx, wu[k], b)
        for j in range(k, 3):
            s2[:, k, j] = s2[:, j, k] = np.bincount(idx, wu[k] * u[:, j], b)
    return s1, s2


_PACK_CHUNK = 1 << 15  # rows per validation chunk of PackedCovariance.from_array


class PackedCovariance:
    """Per-point 3x3 covariances packed as six contiguous rows, validated once.

    ``rows`` is a C-contiguous (6, N) float64 array ``xx, yy, zz, xy, xz, yz`` (m²); row
    selections (:meth:`take`) compose lazily and gather once, when the adjustment reads them.
    The adjustment only needs ``b C b^T`` per condition, which six rows give with contiguous
    reads, so per-point accuracy costs little more than a constant sigma.

    Build one with :meth:`from_array` from an (N, 3, 3) covariance array or an (N, 6) array
    of the six entries (SlipMap's ``CovXX .. CovYZ`` LAS dimensions in that order).
    """

    __slots__ = ("_rows", "_idx")

    def __init__(self, rows: np.ndarray, idx: Optional[np.ndarray] = None):
        self._rows = rows
        self._idx = idx

    @classmethod
    def from_array(cls, cov, *, name: str = "sigma") -> PackedCovariance:
        """Validate and pack ``cov``: (N, 3, 3) symmetric, or (N, 6) ``xx yy zz xy xz yz``."""
        c = np.asarray(cov, dtype=np.float64)
        if c.ndim == 3 and c.shape[1:] == (3, 3):
            flat = c.reshape(c.shape[0], 9)
            cols, lower_cols = [0, 4, 8, 1, 2, 5], [3, 6, 7]
        elif c.ndim == 2 and c.shape[1] == 6:
            flat, cols, lower_cols = c, list(range(6)), None
        else:
            raise InvalidParameterError(
                f"{name} must be an (N, 3, 3) covariance array or (N, 6) packed covariances "
                f"(xx, yy, zz, xy, xz, yz; m²); got shape {c.shape}"
            )
        n = flat.shape[0]
        rows = np.empty((6, n))
        # validate and transpose in cache-sized chunks: no full-size temporaries
        for lo in range(0, n, _PACK_CHUNK):
            six = np.take(flat[lo : lo + _PACK_CHUNK], cols, axis=1)
            if not np.isfinite(six).all():
                raise InvalidParameterError(f"{name} contains NaN or infinite values")
            if np.any(six[:, :3] <= 0):
                raise InvalidParameterError(f"{name}: covariance diagonals must be > 0 (m²)")
            if lower_cols is not None:
                lower = np.take(flat[lo : lo + _PACK_CHUNK], lower_cols, axis=1)
                tol = 1e-12 * float(six[:, :3].max(initial=0.0))
                if not np.all(np.abs(six[:, 3:] - lower) <= tol):
                    raise InvalidParameterError(
                        f"{name}: covariance matrices must be symmetric (and finite)"
                    )
            rows[:, lo : lo + _PACK_CHUNK] = six.T
        return cls(rows)

    def __len__(self) -> int:
        return int(self._rows.shape[1] if self._idx is None else self._idx.size)

    @property
    def shape(self) -> Tuple[int, int]:
        """``(N, 6)``, the number of points and packed entries."""
        return (len(self), 6)

    def take(self, rows) -> PackedCovariance:
        """The covariances of points ``rows`` (int indices or a boolean mask), lazily."""
        r = np.asarray(rows)
        r = np.flatnonzero(r) if r.dtype == bool else r.astype(np.int64, copy=False)
        return PackedCovariance(self._rows, r if self._idx is None else self._idx[r])

    @property
    def rows(self) -> np.ndarray:
        """(6, N) contiguous rows ``xx, yy, zz, xy, xz, yz`` (gathered on first access)."""
        if self._idx is not None:
            self._rows, self._idx = np.take(self._rows, self._idx, axis=1), None
        return self._rows

    def matrices(self) -> np.ndarray:
        """(N, 3, 3) covariance matrices."""
        xx, yy, zz, xy, xz, yz = self.rows
        return np.stack(
            [np.stack([xx, xy, xz], 1), np.stack([xy, yy, yz], 1), np.stack([xz, yz, zz], 1)], 1
        )


def _parse_sigma(sigma, n, valid, all_valid, name):
    """``(var (3,), None, False)`` for a scalar / per-axis sigma, ``(None, (n, 3) variances,
    False)`` for per-point sigmas, ``(None, (6, n) packed covariance rows, True)`` for
    per-point covariances."""
    label = f"sigma_{name}"
    if isinstance(sigma, PackedCovariance):
        if len(sigma) != n:
            raise InvalidParameterError(f"{label} has {len(sigma)} covariances for {n} points")
        return None, (sigma if all_valid else sigma.take(valid)).rows, True
    s = np.asarray(sigma, dtype=np.float64)
    if s.shape in ((n, 3, 3), (n, 6)):
        return _parse_sigma(PackedCovariance.from_array(s, name=label), n, valid, all_valid, name)
    if not np.all(np.isfinite(s)):
        raise InvalidParameterError(f"{label} contains NaN or infinite values")
    if s.ndim == 0 or s.shape == (3,):
        if np.any(s <= 0):
            raise InvalidParameterError(f"{label} must be > 0 (metres), got {sigma!r}")
        return np.broadcast_to(s * s, (3,)).astype(np.float64), None, False
    if s.shape == (n, 3):
        if np.any(s <= 0):
            raise InvalidParameterError(f"{label}: per-point sigmas must be > 0 (metres)")
        v = s * s
        return None, (v if all_valid else v[valid]), False
    raise InvalidParameterError(
        f"{label} must be a scalar, a (3,) per-axis sigma, an (N, 3) per-point sigma, an "
        f"(N, 3, 3) covariance array or (N, 6) packed covariances with N = {n}; got shape "
        f"{s.shape}"
    )


def _check_points(pts, labels, name):
    pts = np.asarray(pts)
    labels = np.asarray(labels)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputDataError(f"{name} must be an (N, 3) array of points, got shape {pts.shape}")
    if labels.shape != (pts.shape[0],):
        raise InputDataError(
            f"{name}_plane must have shape ({pts.shape[0]},) (one plane index per point), "
            f"got {labels.shape}"
        )
    if labels.size and not np.issubdtype(labels.dtype, np.integer):
        raise InputDataError(f"{name}_plane must hold integer plane indices, got {labels.dtype}")
    pts = pts.astype(np.float64, copy=False)
    if not np.all(np.isfinite(pts)):
        raise InputDataError(f"{name} contains NaN or infinite coordinates; remove those points")
    return pts, labels


# --------------------------------------------------------------------------- blocks


class _State:
    """Current estimate: rotation matrix R (3, 3), translation t (3,), planes n (b, 3), d (b,)."""

    def __init__(self, r, t, n, d, delta=None):
        self.r, self.t, self.n, self.d = r, t, n, d
        self.delta = np.zeros(d.shape[0]) if delta is None else delta

    def copy(self):
        return _State(self.r.copy(), self.t.copy(), self.n.copy(), self.d.copy(), self.delta.copy())


def _epoch_rows(state: _State, g: np.ndarray, after: bool):
    """Affine row model per plane: rows ``a0 + M u`` (b, 11) / (b, 11, 3), misclosure
    ``f0 + bvec . u`` (b,) / (b, 3). Columns: motion (6), plane ``a, b, c, d`` (4) and the
    plane's after-epoch offset ``δ`` (1, after rows only; see :mod:`.stochastic`)."""
    b = g.shape[0]
    a0 = np.zeros((b, NCOL))
    mm = np.zeros((b, NCOL, 3))
    a0[:, 9] = 1.0
    if after:
        a0[:, 10] = 1.0
        bvec = state.n @ state.r.T  # m = R n
        e = g - state.t
        a0[:, 0:3] = np.cross(bvec, e)
        a0[:, 3:6] = -bvec
        a0[:, 6:9] = e @ state.r  # R^T e
        mm[:, 0:3, :] = _skew(bvec)
        mm[:, 6:9, :] = state.r.T
    else:
        bvec = state.n
        e = g
        a0[:, 6:9] = e
        mm[:, 6:9, :] = np.eye(3)
    f0 = np.einsum("ij,ij->i", bvec, e) + state.d
    return a0, mm, f0, bvec


def _blocks(state: _State, epochs, b: int):
    """Per-plane normal blocks N (b, 11, 11), right-hand sides A^T W w (b, 11), v^T P v (b,),
    and per-epoch (sum w, weighted mean misclosure) for the outlier test."""
    nn = np.zeros((b, NCOL, NCOL))
    rhs = np.zeros((b, NCOL))
    vpv = np.zeros(b)
    stats = []
    for ep, after in zip(epochs, (False, True)):
        a0, mm, f0, bvec = _epoch_rows(state, ep.g, after)
        s0, s1, s2 = ep.weighted(bvec, b)
        ms1 = np.einsum("bkj,bj->bk", mm, s1)
        nn += s0[:, None, None] * a0[:, :, None] * a0[:, None, :]
        nn += a0[:, :, None] * ms1[:, None, :] + ms1[:, :, None] * a0[:, None, :]
        nn += np.einsum("bkj,bjl,bml->bkm", mm, s2, mm)
        s1m = np.einsum("bj,bj->b", s1, bvec)
        s2m = np.einsum("bjl,bl->bj", s2, bvec)
        rhs += a0 * (s0 * f0 + s1m)[:, None]
        rhs += np.einsum("bkj,bj->bk", mm, s1 * f0[:, None] + s2m)
        vpv += s0 * f0 * f0 + 2.0 * f0 * s1m + np.einsum("bj,bj->b", bvec, s2m)
        with np.errstate(invalid="ignore", divide="ignore"):
            stats.append((s0, (s0 * f0 + s1m) / s0))
    return nn, rhs, vpv, stats


def _reduce(state: _State, epochs, active: np.ndarray, b: int):
    """Eliminate each active plane's ``a, b, c, d`` (with its unit-normal constraint).

    Returns ``G`` (k, 7, 7) and ``g`` (k, 7), the plane's reduced normal block and right-hand
    side over (motion (6), δ), and ``x`` (k, 5, 8), the solved plane block for the
    back-substitution ``d2 = x[:4, 7] - x[:4, :6] d1 - x[:4, 6] δ``."""
    nn, rhs, _, _ = _blocks(state, epochs, b)
    nn, rhs = nn[active], rhs[active]
    n = state.n[active]
    k = n.shape[0]
    kk = np.zeros((k, 5, 5))
    kk[:, :4, :4] = nn[:, 6:10, 6:10]
    kk[:, 4, :3] = kk[:, :3, 4] = 2.0 * n
    cols = np.zeros((k, 5, 8))
    cols[:, :4, :7] = nn[:, 6:10, _XD]
    cols[:, :4, 7] = -rhs[:, 6:10]
    cols[:, 4, 7] = -(np.einsum("ij,ij->i", n, n) - 1.0)
    try:
        x = np.linalg.solve(kk, cols)
    except np.linalg.LinAlgError as exc:
        raise InputDataError(
            "a plane's points are degenerate (collinear or too few): its 4x4 block is singular"
        ) from exc
    cross = nn[:, _XD, 6:10]  # (k, 7, 4)
    g_mat = nn[:, _XD][:, :, _XD] - np.einsum("kij,kjl->kil", cross, x[:, :4, :7])
    g_vec = -rhs[:, _XD] - np.einsum("kij,kj->ki", cross, x[:, :4, 7])
    return g_mat, g_vec, x


class _PlaneLevel:
    """Plane-level GLS pieces of the active planes (see :mod:`.stochastic`), unscaled:
    ``y`` (k,), ``h`` (k, 6), ``p`` (k,) = 1/D, tilt information ``t`` (6, 6) and ``rt`` (6,)
    summed over the planes, and per plane its rotation block ``tr`` (k, 3, 3) and ``rtr``
    (k, 3) (a plane's tilt says nothing of the translation: with its offset free, a
    translation only moves it along its normal), for the random tilt per plane."""

    def __init__(self, g_mat, g_vec):
        dd = g_mat[:, 6, 6]
        c = g_mat[:, :6, 6]
        q = g_vec[:, 6]
        self.p = 1.0 / dd
        self.h = c / dd[:, None]
        self.y = q / dd
        tj = g_mat[:, :6, :6] - c[:, :, None] * c[:, None, :] / dd[:, None, None]
        rtj = g_vec[:, :6] - c * (q / dd)[:, None]
        self.t = tj.sum(0)
        self.t = 0.5 * (self.t + self.t.T)
        self.rt = rtj.sum(0)
        self.tr = 0.5 * (tj[:, :3, :3] + tj[:, :3, :3].transpose(0, 2, 1))
        self.rtr = rtj[:, :3]
        self.n_white = g_mat[:, :6, :6].sum(0)

    def tilt_blocks(self, s0sq: float, tilt_var: float = 0.0, keep=None):
        """Each plane's rotation information (k, 3, 3) and right-hand side (k, 3) scaled by the
        point-level factor, weighed with the random tilt ``tilt_var`` (rad²,
        :func:`.stochastic.tilt_information`), zero for the planes not in ``keep`` (k,)."""
        at, rtl = _stoch.tilt_information(self.tr / s0sq, self.rtr / s0sq, tilt_var)
        if keep is not None:
            at, rtl = at * keep[:, None, None], rtl * keep[:, None]
        return at, rtl

    def tilt(self, s0sq: float, tilt_var: float = 0.0, keep: Optional[np.ndarray] = None):
        """The tilt information (6, 6) and right-hand side (6,) scaled by the point-level
        factor, the planes' :meth:`tilt_blocks` summed; ``tilt_var`` 0 and every plane kept:
        ``t / s0sq``, ``rt / s0sq``."""
        if not tilt_var > 0 and (keep is None or bool(np.all(keep))):
            return self.t / s0sq, self.rt / s0sq
        at, rtl = self.tilt_blocks(s0sq, tilt_var, keep)
        t = self.t / s0sq
        rt = self.rt / s0sq
        t[:3, :3] = at.sum(axis=0)
        rt[:3] = rtl.sum(axis=0)
        return t, rt


class _StochasticConfig:
    """The plane-level model in force: components ``theta`` (variances, m²), the spatial
    correlation ``kernel`` (family and range, :class:`.stochastic.SpatialKernel`),
    point-level factor ``s0sq``, per-plane variance ``inflation`` (b,) of down-weighted
    planes, the random tilt per plane ``tilt_var`` (rad², 0: the tilts point-noise precise)
    and the structure ``model`` (:class:`.stochastic.PlaneModel`)."""

    def __init__(self, model: PlaneModel, b: int):
        self.model = model
        self.theta: dict = {}
        self.kernel = _stoch.SpatialKernel()  # no spatial term until one is estimated
        self.s0sq = 1.0
        self.inflation = np.zeros(b)
        self.tilt_var = 0.0
        self.tilt_keep = np.ones(b, dtype=bool)  # planes whose tilt is used
        self.gain = np.zeros((6, 0))  # Q Hᵀ V⁻¹ of the final solution (see _stochastic)
        self.gain_idx = np.zeros(0, dtype=np.int64)
        self.small = 1.0
        self.gain_extra: dict = {}
        #: the units' drift along GpsTime: its options (see _solve) and the knot spacing in
        #: force (inf: the rigid unit; NaN: no times)
        self.unit_drift: Optional[dict] = None
        self.unit_interval = float("nan")
        #: condition the units on the planes' within-epoch contrasts (unit_contrasts)
        self.use_contrasts = True
        self._cond_key = self._cond_model = self._cond = None

    def condition(self, active: np.ndarray) -> Optional[_stoch.ContrastCondition]:
        """The units given the contrast rows of the active planes under the components in
        force (:func:`.stochastic.condition_on_contrasts`), or None; cached."""
        if not self.use_contrasts or self.model.contrasts is None:
            return None
        idx = np.flatnonzero(active)
        key = (idx.tobytes(), tuple(sorted(self.theta.items())))
        if key != self._cond_key or self._cond_model is not self.model:
            self._cond_key, self._cond_model = key, self.model
            self._cond = _stoch.condition_on_contrasts(self.model, idx, self.theta)
        return self._cond

    def shift(self, active: np.ndarray) -> np.ndarray:
        """(k,) the misclosures' part the contrasts predict (0 without a condition)."""
        c = self.condition(active)
        return 0.0 if c is None else c.shift

    def v_matrix(self, active: np.ndarray, p: np.ndarray) -> np.ndarray:
        idx = np.flatnonzero(active)
        return _stoch.covariance(
            self.model, idx, self.s0sq * p, self.theta, self.kernel, self.inflation[idx]
        )

    def v_operator(
        self, active: np.ndarray, p: np.ndarray, inflated: bool = True
    ) -> _stoch.CovarianceOperator:
        """``V`` of the active planes; ``inflated=False`` leaves out the down-weighting."""
        idx = np.flatnonzero(active)
        infl = self.inflation[idx] if inflated else None
        return _stoch.CovarianceOperator(
            self.model, idx, self.s0sq * p, self.theta, self.kernel, infl,
            condition=self.condition(active),
        )  # fmt: skip


def _step_block(state: _State, epochs, active: np.ndarray, b: int, cfg=None):
    """One Gauss-Helmert step by plane-block elimination. Returns (d1 (6,), d2 (k, 4), Nred,
    Qxx) for the active planes; ``cfg`` (a :class:`_StochasticConfig`) adds the plane-level
    random offsets (their BLUP is left in ``state.delta``), None is the white model."""
    g_mat, g_vec, x = _reduce(state, epochs, active, b)
    if cfg is None:
        nred = g_mat[:, :6, :6].sum(axis=0)
        rred = g_vec[:, :6].sum(axis=0)
        delta = np.zeros(g_mat.shape[0])
    else:
        pl = _PlaneLevel(g_mat, g_vec)
        vop = cfg.v_operator(active, pl.p)
        vih = vop.solve(pl.h)
        t_s, rt_s = pl.tilt(cfg.s0sq, cfg.tilt_var, cfg.tilt_keep[active])
        shift = cfg.shift(active)  # the units' errors the contrasts predict
        nred = t_s + pl.h.T @ vih
        rred = rt_s + vih.T @ (pl.y - shift)
        if UNIT_DRIFT_TILTS:  # the units' errors tilt the planes too
            terms = _drift_tilt_terms(cfg, pl, vop, vih, active, pl.y - shift)
            if terms is not None:
                nred = nred + terms[0]
                rred = rred + terms[1]
    nred = 0.5 * (nred + nred.T)
    _check_singular(nred)
    qxx = np.linalg.inv(nred)
    d1 = qxx @ rred
    if cfg is not None:
        e = pl.y - pl.h @ d1 - shift
        delta = shift + e - cfg.s0sq * pl.p * vop.solve(e)  # Σ_δ V⁻¹ e
    d2 = x[:, :4, 7] - np.einsum("kij,j->ki", x[:, :4, :6], d1) - x[:, :4, 6] * delta[:, None]
    state.delta = np.zeros(b)
    state.delta[active] = delta
    return d1, d2, nred, 0.5 * (qxx + qxx.T)


def _unit_columns(cfg, active):
    """The units' errors in force over the active planes: ``(z_o (k, r), lam (r, r), mean
    (r,), z_t (k, 3, r))``, their design in the misclosures (as the covariance operator's),
    their covariance and mean (given the contrasts when the model is conditioned on them) and
    their design in the planes' tilts (rotation, radians per unit coefficient); None when
    no unit component is in force or no tilt shares are known."""
    tilts = getattr(cfg, "unit_tilts", None)
    if not tilts or cfg.unit_interval not in tilts:
        return None
    m = cfg.model
    idx = np.flatnonzero(active)
    cond = cfg.condition(active)
    rows = None if cond is None else cond.rows
    zo, zt, lam = [], [], []
    for e, name in enumerate(("unit_before", "unit_after")):
        th = float(cfg.theta.get(name, 0.0))
        om = tilts[cfg.unit_interval][e]
        z = None if th <= 0 or om is None else m.unit_tilt_design(name, idx, om, rows)
        if z is None:
            continue
        if cond is None:
            zo.append((1.0 if e == 0 else -1.0) * m.unit_basis(name, idx))
            lam.append(np.full(zo[-1].shape[1], th))
        zt.append(z)
    if not zt:
        return None
    zt = np.concatenate(zt, axis=2)
    if cond is not None:
        z_o, lam_m, mean = cond.z, cond.lam, cond.g @ rows.value
    else:
        z_o, lam_m = np.hstack(zo), np.diag(np.concatenate(lam))
        mean = np.zeros(z_o.shape[1])
    if z_o.shape[1] != zt.shape[2]:
        raise AssertionError("the units' tilt design does not match their offset design")
    return z_o, lam_m, mean, zt


def _drift_tilt_terms(cfg, pl, vop, vih, active, y_o):
    """The change to the motion's normal matrix (6, 6) and right-hand side (6,) when the
    units' errors tilt the planes (:data:`UNIT_DRIFT_TILTS`), or None: the tilts' terms given
    the offsets (:func:`.stochastic.tilts_given_offsets`) in place of their own."""
    cols = _unit_columns(cfg, active)
    if cols is None:
        return None
    z_o, lam, mean, zt = cols
    at, rtl = pl.tilt_blocks(cfg.s0sq, cfg.tilt_var, cfg.tilt_keep[active])
    viz = vop.solve(z_o)
    info, rhs, wz = _stoch.tilts_given_offsets(at, rtl, zt, z_o, lam, mean, viz, pl.h, y_o)
    info[:3, :3] -= at.sum(axis=0)
    rhs[:3] -= rtl.sum(axis=0)
    # the right-hand side's change per offset through the units' errors the offsets predict,
    # and per unit error through the tilts; the pieces of the gain on the tilts
    return info, rhs, -(wz @ lam) @ viz.T, wz, (at, zt, z_o, lam, viz)


def _component_tilts(cfg, pl, active, keep, cols=False):
    """The tilts' information (6, 6) and right-hand side (6,) the plane-level components and
    the plane tests take: :meth:`_PlaneLevel.tilt`, and where the units' errors tilt the
    planes (:data:`UNIT_DRIFT_TILTS`) the tilts weighed with the drift's tilts too
    (:func:`.stochastic.tilts_marginal`): precise tilts that the drift moves would otherwise
    pin the motion and push the drift's part into the offsets' components. ``cols``: the
    caller's :func:`_unit_columns` under the components in force (False: found here)."""
    t, rt = pl.tilt(cfg.s0sq, cfg.tilt_var, keep)
    if cols is False:
        cols = _unit_columns(cfg, active) if UNIT_DRIFT_TILTS else None
    if cols is None:
        return t, rt
    _, lam, mean, zt = cols
    at, rtl = pl.tilt_blocks(cfg.s0sq, cfg.tilt_var, keep)
    t, rt = t.copy(), rt.copy()
    t[:3, :3], rt[:3] = _stoch.tilts_marginal(at, rtl, zt, lam, mean)
    return t, rt


def _step_dense(state: _State, epochs, active: np.ndarray, b: int, cfg=None):
    """The same step from the full Gauss-Helmert matrices (A, B, W, G) of every point.

    With ``cfg`` the plane offsets ``δ`` are explicit unknowns (one column per plane on its
    after-epoch conditions) with the pseudo-observations ``δ ~ N(0, Σ_δ)``: the mixed model in
    its direct form, against the block step's Woodbury form. Needs ``Σ_δ`` regular (a plane
    component > 0)."""
    act = np.flatnonzero(active)
    col = np.full(b, -1)
    col[act] = np.arange(act.size)
    k = act.size
    use_delta = cfg is not None and (
        any(v > 0 for v in cfg.theta.values()) or bool(np.any(cfg.inflation[act] > 0))
    )
    nd = k if use_delta else 0
    nu = 6 + 4 * k + nd
    rows_a, ws, wv = [], [], []
    r, t = state.r, state.t
    for ep, after in zip(epochs, (False, True)):
        keep = active[ep.idx]
        idx = ep.idx[keep]
        x = ep.g[idx] + ep.u[keep]  # centred observed coordinates
        n = state.n[idx]
        a = np.zeros((idx.size, nu))
        c = col[idx]
        if after:
            m = n @ r.T
            x = x - t
            a[:, 0:3] = np.cross(m, x)
            a[:, 3:6] = -m
            bmat = m
            xa = x @ r
        else:
            bmat = n
            xa = x
        for j in range(3):
            a[np.arange(idx.size), 6 + 4 * c + j] = xa[:, j]
        a[np.arange(idx.size), 6 + 4 * c + 3] = 1.0
        if after and use_delta:
            a[np.arange(idx.size), 6 + 4 * k + c] = 1.0
        w = np.einsum("ij,ij->i", bmat, xa if not after else x) + state.d[idx]
        if ep.var is not None:
            cov = np.broadcast_to(np.diag(ep.var), (idx.size, 3, 3))
        elif not ep.packed:
            cov = np.einsum("ij,jk->ijk", ep.cov[keep], np.eye(3))
        else:
            cov = PackedCovariance(ep.cov).take(keep).matrices()
        bcb = np.einsum("ij,ijk,ik->i", bmat, cov, bmat)  # B C B^T, one scalar per condition
        rows_a.append(a)
        ws.append(w)
        wv.append(1.0 / bcb)
    a = np.concatenate(rows_a)
    w = np.concatenate(ws)
    weight = np.concatenate(wv)
    gmat = np.zeros((k, nu))
    wc = np.zeros(k)
    for i, p in enumerate(act):
        gmat[i, 6 + 4 * i : 9 + 4 * i] = 2.0 * state.n[p]
        wc[i] = state.n[p] @ state.n[p] - 1.0
    if cfg is not None:
        weight = weight / cfg.s0sq
    big = np.zeros((nu + k, nu + k))
    big[:nu, :nu] = a.T @ (weight[:, None] * a)
    if use_delta:
        # prior of the plane offsets (their misclosure is 0: each step solves for all of δ)
        v = cfg.v_matrix(active, np.zeros(k))
        big[nu - nd : nu, nu - nd : nu] += np.linalg.inv(v)
    big[:nu, nu:] = gmat.T
    big[nu:, :nu] = gmat
    rhs = np.concatenate([-(a.T @ (weight * w)), -wc])
    try:
        inv = np.linalg.inv(big)
        ok = bool(np.linalg.cond(big) < 1e15)
    except np.linalg.LinAlgError:
        ok = False
    if not ok:
        _step_block(state, epochs, active, b, cfg)  # raises the error naming the direction
        raise InputDataError("the Gauss-Helmert normal system is singular")
    q = 0.5 * (inv[:6, :6] + inv[:6, :6].T)
    _check_singular(np.linalg.inv(q))
    sol = np.linalg.solve(big, rhs)
    state.delta = np.zeros(b)
    if use_delta:
        state.delta[active] = sol[nu - nd : nu]
    return sol[:6], sol[6 : 6 + 4 * k].reshape(k, 4), np.linalg.inv(q), q


def _check_singular(nred: np.ndarray) -> None:
    """Raise InputDataError naming the unconstrained directions of a singular reduced system."""
    tt = nred[3:, 3:]
    ev, evec = np.linalg.eigh(tt)
    top = max(float(ev[-1]), 0.0)
    bad = [evec[:, j] for j in range(3) if not top > 0 or ev[j] < SINGULAR_RATIO * top]
    if bad:
        names = ", ".join(f"translation along {_describe_direction(v)}" for v in bad)
        raise InputDataError(
            f"the reduced normal system is singular: {names} unconstrained; all matched plane "
            "normals are (nearly) parallel or lie in one plane - need planes with several "
            "orientations (e.g. roofs, walls of different directions and ground)"
        )
    dsc = 1.0 / np.sqrt(np.abs(np.diag(nred)))
    ev_s, evec_s = np.linalg.eigh(nred * dsc[:, None] * dsc[None, :])
    if not ev_s[0] > SINGULAR_RATIO * ev_s[-1]:
        v = evec_s[:3, 0]
        axis = v / (np.linalg.norm(v) or 1.0)
        raise InputDataError(
            "the reduced normal system is singular: rotation about the axis "
            f"{_describe_direction(axis)} through the centre is unconstrained; need planes "
            "with several orientations spread around the centre"
        )


# --------------------------------------------------------------------------- driver


def _both_epochs_centroids(epochs) -> np.ndarray:
    """(b, 3) centroid of each plane's points of both epochs (centred frame)."""
    e0, e1 = epochs
    tot = np.maximum(e0.count + e1.count, 1)[:, None]
    return (e0.g * e0.count[:, None] + e1.g * e1.count[:, None]) / tot


#: sample points per side of a plane's grid for the change of support of the spatial term
#: (``SUPPORT_GRID²`` samples per plane; see :func:`_plane_samples`)
SUPPORT_GRID = 8


def _plane_samples(epochs, gc: np.ndarray, b: int, m: int = SUPPORT_GRID):
    """(b, m², 3) sample points spread over each plane's extent and (b, m²) their weights,
    centred frame, for the block covariance of the spatial term
    (:class:`.stochastic.PlaneModel`): an ``m × m`` grid of equal weights (row-major) on
    the rectangle whose in-plane second moments are those of the plane's points of both
    epochs (half-widths ``√3 σ`` along its principal directions).

    From the moments alone, so the points' adjustment and the one from per-plane moments
    (:mod:`.planemoments`, tiled inputs) build the same model; the grid is symmetric under
    a sign change of either principal direction, so it is equivariant under rigid
    transforms. A ground piece with holes is represented by the rectangle of the same
    spread, which is what the variance of its mean depends on first.
    """
    tot = np.zeros(b)
    scat = np.zeros((b, 3, 3))
    for ep in epochs:
        dg = ep.g - gc
        u1 = np.zeros_like(ep.g) if ep.U1 is None else ep.U1
        u2 = ep.U2
        if u2 is None:  # per-point covariances: the unweighted scatter from the points
            u1, u2 = _moments(ep.idx, ep.u, None, b)
        scat += (
            u2
            + u1[:, :, None] * dg[:, None, :]
            + dg[:, :, None] * u1[:, None, :]
            + ep.count[:, None, None] * dg[:, :, None] * dg[:, None, :]
        )
        tot += ep.count
    lam, vec = np.linalg.eigh(scat / np.maximum(tot, 1.0)[:, None, None])
    half = np.sqrt(3.0 * np.clip(lam[:, 1:], 0.0, None))  # (b, 2): second, first axis
    f = (np.arange(m) + 0.5) / m * 2.0 - 1.0
    fa, fb = np.meshgrid(f, f, indexing="ij")
    off = (fa.ravel()[None, :, None] * half[:, 1, None, None]) * vec[:, None, :, 2] + (
        fb.ravel()[None, :, None] * half[:, 0, None, None]
    ) * vec[:, None, :, 1]
    return gc[:, None, :] + off, np.full((b, m * m), 1.0 / (m * m))


def _initial_planes(epochs, b):
    """Plane (n, d) per plane (centred frame) from the before points (both epochs if fewer
    than 3 before points), smallest-eigenvalue normal of the scatter."""
    e0, e1 = epochs
    c0 = e0.count
    u1, u2 = _moments(e0.idx, e0.u, None, b) if e0.U1 is None else (e0.U1, e0.U2)
    scat = u2 - (u1[:, :, None] * u1[:, None, :]) / np.maximum(c0, 1)[:, None, None]
    g = e0.g.copy()
    few = c0 < 3
    if np.any(few):
        v1, v2 = _moments(e1.idx, e1.u, None, b) if e1.U1 is None else (e1.U1, e1.U2)
        gc = _both_epochs_centroids(epochs)
        both = np.zeros((b, 3, 3))
        for ep, m1, m2 in ((e0, u1, u2), (e1, v1, v2)):
            dg = ep.g - gc
            both += (
                m2
                + m1[:, :, None] * dg[:, None, :]
                + dg[:, :, None] * m1[:, None, :]
                + ep.count[:, None, None] * dg[:, :, None] * dg[:, None, :]
            )
        scat = np.where(few[:, None, None], both, scat)
        g = np.where(few[:, None], gc, g)
    _, vec = np.linalg.eigh(scat)
    n = orient_normals(np.ascontiguousarray(vec[:, :, 0]))
    d = -np.einsum("ij,ij->i", n, g)
    return n, d


def _iterate(state, epochs, active, b, step, max_iterations, tolerance, progress, base):
    converged = False
    it = 0
    nred = qxx = None
    for it in range(1, max_iterations + 1):
        d1, d2, nred, qxx = step(state, epochs, active, b)
        state.r = rotation_matrix(d1[:3]) @ state.r
        state.t = state.t + d1[3:]
        state.n[active] += d2[:, :3]
        state.d[active] += d2[:, 3]
        inc = max(float(np.abs(d1).max()), float(np.abs(d2).max()) if d2.size else 0.0)
        log.debug("adjustment iteration %d: max increment %.3g", it, inc)
        report(progress, min(0.95, base + 0.9 * it / max_iterations), f"iteration {it}")
        if inc < tolerance:
            if any(getattr(e, "stale", False) for e in epochs):
                # converged on reused weights: one more step with weights at the solution
                for e in epochs:
                    e.refresh()
                continue
            converged = True
            break
    return it, converged, nred, qxx


def _check_options(max_iterations, tolerance, alpha, min_planes, stochastic_model, components):
    """The adjustment's options checked; returns the stochastic model and fixed components."""
    if int(max_iterations) < 1:
        raise InvalidParameterError(f"max_iterations must be >= 1, got {max_iterations}")
    if not (tolerance > 0):
        raise InvalidParameterError(f"tolerance must be > 0, got {tolerance}")
    if not (0 < alpha < 1):
        raise InvalidParameterError(f"alpha must be in (0, 1), got {alpha}")
    if int(min_planes) < 1:
        raise InvalidParameterError(f"min_planes must be >= 1, got {min_planes}")
    model = _stoch.check_stochastic_model(stochastic_model)
    return model, _stoch.check_components(components)


def _run(
    before,
    before_plane,
    after,
    after_plane,
    *,
    sigma_before,
    sigma_after,
    centre,
    max_iterations,
    tolerance,
    reject_outlier_planes,
    alpha,
    min_planes,
    progress,
    dense,
    stochastic_model="white",
    unit_before=None,
    unit_after=None,
    components=None,
    random_tilt=None,
    unit_time_before=None,
    unit_time_after=None,
    unit_contrasts=None,
):
    before, before_plane = _check_points(before, before_plane, "before")
    after, after_plane = _check_points(after, after_plane, "after")
    model, fixed = _check_options(
        max_iterations, tolerance, alpha, min_planes, stochastic_model, components
    )
    units = [
        _stoch.check_units(unit_before, before_plane.shape[0], "unit_before"),
        _stoch.check_units(unit_after, after_plane.shape[0], "unit_after"),
    ]
    times = [
        check_unit_time(unit_time_before, before_plane.shape[0], "unit_time_before"),
        check_unit_time(unit_time_after, after_plane.shape[0], "unit_time_after"),
    ]
    b = int(max(before_plane.max(initial=-1), after_plane.max(initial=-1))) + 1
    if centre is None:
        pts = [p[lab >= 0] for p, lab in ((before, before_plane), (after, after_plane))]
        allp = np.concatenate(pts)
        if allp.shape[0] == 0:
            raise InputDataError("no points with a plane index >= 0 in either epoch")
        centre = allp.mean(axis=0)
        del allp, pts
    else:
        centre = np.asarray(centre, dtype=np.float64)
        if centre.shape != (3,) or not np.all(np.isfinite(centre)):
            raise InvalidParameterError(f"centre must be 3 finite coordinates, got {centre!r}")
    report(progress, 0.0, "plane moments")
    epochs = (
        _Epoch(before, before_plane, sigma_before, b, centre, "before"),
        _Epoch(after, after_plane, sigma_after, b, centre, "after"),
    )
    shares = codes = drift = contrasts = None
    if model != "white":
        pairs = [_unit_shares(ep, u, b) for ep, u in zip(epochs, units)]
        if model == "full":
            drift = _unit_drift_options(epochs, units, times, pairs)
            # rows given are in the frame of the points given; the own rows in the model's
            given = None if unit_contrasts is None else centre
            if unit_contrasts is None and not dense:
                unit_contrasts = _own_contrasts(epochs, units, times, b)
            if unit_contrasts and any(c is not None and c.size for c in unit_contrasts):
                # the units the contrasts see widen the shares' columns (zero on the planes)
                pairs, drift = with_contrast_units(unit_contrasts, pairs, drift)
                contrasts = epoch_rows(
                    unit_contrasts, tuple(p_[1] for p_ in pairs), drift, centre=given
                )
        shares = [p_[0] for p_ in pairs]
        codes = [p_[1] for p_ in pairs]
    tilts = None
    if UNIT_DRIFT_TILTS and drift and not dense:
        tilts = _unit_tilt_options(epochs, units, times, drift, _initial_planes(epochs, b)[0])
    return _solve(
        epochs, b, centre, shares, dense=dense, model=model, fixed=fixed,
        max_iterations=max_iterations, tolerance=tolerance, alpha=alpha, min_planes=min_planes,
        reject_outlier_planes=reject_outlier_planes, progress=progress,
        labels=(before_plane, after_plane), unit_codes=codes, random_tilt=random_tilt,
        unit_drift=drift, contrasts=contrasts, unit_tilts=tilts,
    )  # fmt: skip


def _unit_tilt_options(epochs, units, times, drift, normals):
    """``{interval_s: (tilts_b, tilts_a)}``: each epoch's (b, V, 3) tilt shares
    (:func:`.unit_drift.hat_unit_tilt_shares`) in the columns of its shares of ``drift``
    (:func:`_unit_drift_options`), or None for an epoch without units."""
    out = {}
    for dt, (_, cd) in drift.items():
        per = []
        for ep, u, t, c in zip(epochs, units, times, cd):
            if u is None or c is None or ep.idx is None:
                per.append(None)
                continue
            step = dt if t is not None else math.inf
            per.append(
                hat_unit_tilt_shares(
                    ep.idx, ep.of_valid(u), ep.of_valid(t), ep.u, normals, c, interval_s=step
                )
            )
        out[dt] = tuple(per)
    return out


def _solve(
    epochs, b, centre, shares, *, dense, model, fixed, max_iterations, tolerance, alpha,
    min_planes, reject_outlier_planes, progress, labels, unit_codes=None, random_tilt=None,
    unit_drift=None, contrasts=None, unit_tilts=None,
):  # fmt: skip
    """The adjustment of two epochs (:class:`_Epoch` or :class:`_MomentEpoch`); ``shares``:
    each epoch's (b, U) acquisition-unit shares or None (stochastic models only);
    ``unit_codes``: each epoch's (U,) unit ids of the shares' columns, or None (unknown:
    the result's :class:`.stochastic.PlaneGain` then has no units to share); ``random_tilt``:
    estimate a random tilt per plane (None: :data:`.stochastic.RANDOM_TILT`); ``unit_drift``:
    ``{interval_s: ((shares_b, shares_a), (codes_b, codes_a))}`` of the units' drift along
    GpsTime, ``math.inf`` the rigid unit (:func:`_unit_drift_options`), or None;
    ``contrasts``: the planes' within-epoch unit contrasts (:func:`_contrast_rows`) or None."""
    before_plane, after_plane = labels
    if dense and (float(fixed.get("tilt_rad", 0.0)) > 0 or random_tilt):
        raise InvalidParameterError(
            "adjust_rigid_dense does not model the random tilt per plane: leave out "
            "components['tilt_rad'] (or give 0) and random_tilt, or use adjust_rigid"
        )
    if dense and 6 + 5 * b > DENSE_MAX_UNKNOWNS:
        raise InvalidParameterError(
            f"adjust_rigid_dense is a reference for small problems ({6 + 5 * b} unknowns); "
            "use adjust_rigid"
        )
    c0, c1 = epochs[0].count, epochs[1].count
    rejected: List[Tuple[int, str]] = []
    for p in np.flatnonzero((c0 == 0) | (c1 == 0) | (c0 + c1 < 4)):
        if c0[p] == 0 and c1[p] == 0:
            continue  # no points: not a plane of this problem
        why = (
            "no points in the before epoch"
            if c0[p] == 0
            else "no points in the after epoch"
            if c1[p] == 0
            else f"too few points ({int(c0[p] + c1[p])} < 4)"
        )
        rejected.append((int(p), why))
    active = (c0 > 0) & (c1 > 0) & (c0 + c1 >= 4)
    if int(active.sum()) < min_planes:
        raise InputDataError(
            f"fewer than {min_planes} matched planes with points in both epochs "
            f"({int(active.sum())} found); need planes with several orientations"
        )
    n0, d0 = _initial_planes(epochs, b)
    state = _State(np.eye(3), np.zeros(3), n0.copy(), d0.copy())
    step = _step_dense if dense else _step_block
    z_crit = NormalDist().inv_cdf(1.0 - alpha / (2.0 * max(int(active.sum()), 1)))
    opts = (int(max_iterations), tolerance, progress)
    if model == "white":
        out = _white(state, epochs, active, b, step, z_crit, rejected, reject_outlier_planes,
                     min_planes, opts)  # fmt: skip
        stoch = None
    else:
        gc = _both_epochs_centroids(epochs)
        samples, weights = _plane_samples(epochs, gc, b)
        options = {dt: sh for dt, (sh, _) in unit_drift.items()} if unit_drift else None
        plane_model = PlaneModel(
            gc, n0.copy(), shares[0], shares[1], samples, weights, unit_options=options,
            contrasts=contrasts,
        )  # fmt: skip
        cfg = _StochasticConfig(plane_model, b)
        cfg.unit_drift = unit_drift
        cfg.unit_tilts = unit_tilts
        tilt = _stoch.RANDOM_TILT if random_tilt is None else bool(random_tilt)
        out, stoch = _stochastic(state, epochs, active, b, step, cfg, model, fixed, z_crit,
                                 rejected, reject_outlier_planes, min_planes, opts,
                                 random_tilt=tilt)  # fmt: skip
        stoch = stoch + (_plane_gain(cfg, centre, unit_codes or (None, None)),)
    state, active, it, converged, nred, qxx, s0, redundancy, n_cond, cov = out
    report(progress, 0.97, "residuals")
    return _finish(
        state, epochs, active, b, centre, it, converged, nred, qxx, s0, redundancy, n_cond,
        rejected, n0, d0, before_plane, after_plane, progress, cov, model, stoch,
    )  # fmt: skip


def _unit_drift_options(epochs, units, times, rigid):
    """``{interval_s: ((shares_b, shares_a), (codes_b, codes_a))}`` of the units' drift along
    GpsTime (:func:`.unit_drift.hat_unit_shares`) for each knot spacing of
    :data:`.unit_drift.UNIT_INTERVALS_S`, and ``math.inf``: the rigid unit, each epoch's
    ``rigid`` (shares, codes) of :func:`_unit_shares`, which an epoch without units or times
    also keeps at every spacing. None when neither epoch has both."""
    if not any(u is not None and t is not None for u, t in zip(units, times)):
        return None
    out = {math.inf: tuple(zip(*rigid))}
    for dt in UNIT_INTERVALS_S:
        sh, cd = [], []
        for ep, u, t, (s_, c_) in zip(epochs, units, times, rigid):
            if u is not None and t is not None:
                s_, c_ = hat_unit_shares(
                    ep.idx, ep.of_valid(u), ep.of_valid(t), ep.count, interval_s=dt
                )
            sh.append(s_)
            cd.append(c_)
        out[dt] = (tuple(sh), tuple(cd))
    return out


def _own_contrasts(epochs, units, times, b):
    """Each epoch's within-epoch unit contrasts of the adjustment's own planes
    (:func:`.unit_contrasts.unit_contrasts`), or None."""
    out = []
    for ep, u, t in zip(epochs, units, times):
        if u is None or not ep.idx.size:
            out.append(None)
            continue
        con = unit_contrasts(ep.idx, ep.u, ep.of_valid(u), b, time_s=ep.of_valid(t))
        # the points are each plane's less its centroid: the rows' positions in the
        # centred frame (the model's) are those plus the plane's centroid
        con = replace(con, position=con.position + ep.g[con.plane])
        out.append(screen_contrasts(con))
    return tuple(out)


def _unit_shares(ep: _Epoch, unit, b: int):
    """(b, U) share of each plane's points of this epoch per acquisition unit and the (U,)
    unit ids of its columns (:func:`.unit_drift.hat_unit_shares` with one knot per unit), or
    (None, None)."""
    if unit is None:
        return None, None
    u = ep.of_valid(unit)
    if u.size == 0:
        return None, None
    return hat_unit_shares(ep.idx, u, None, ep.count, interval_s=math.inf)


def _plane_gain(cfg, centre, codes) -> _stoch.PlaneGain:
    """The :class:`.stochastic.PlaneGain` of a finished stochastic adjustment (``cfg.gain``
    and ``cfg.gain_idx`` set by :func:`_stochastic`)."""
    idx = cfg.gain_idx
    m = cfg.model

    def sub(shares):
        return None if shares is None else shares[idx]

    drift = None
    if cfg.unit_drift:
        drift = {
            dt: (sub(sh[0]), sub(sh[1]), cd[0], cd[1]) for dt, (sh, cd) in cfg.unit_drift.items()
        }
        if cfg.unit_interval in cfg.unit_drift:  # NaN until a component estimate is made
            codes = cfg.unit_drift[cfg.unit_interval][1]
    return _stoch.PlaneGain(
        gain=cfg.gain,
        centroids=m.centroids[idx] + np.asarray(centre, dtype=np.float64),
        normals=m.normals[idx].copy(),
        samples=None if m.samples is None else m.samples[idx] + np.asarray(centre, dtype=float),
        sample_weights=None if m.sample_weights is None else m.sample_weights[idx].copy(),
        shares_before=sub(m.shares_before),
        shares_after=sub(m.shares_after),
        units_before=None if m.shares_before is None else codes[0],
        units_after=None if m.shares_after is None else codes[1],
        theta={n: float(v) for n, v in cfg.theta.items()},
        range_m=float(cfg.kernel.range_m),
        family=cfg.kernel.family,
        small_sample_factor=float(cfg.small),
        unit_options=drift,
        unit_interval_s=float(cfg.unit_interval),
        # already the drift's in force (cfg.model); positions in the input frame
        contrasts=None if m.contrasts is None else m.contrasts.shifted(centre),
        contrast_gain=getattr(cfg, "contrast_gain", None),
        unit_lever_m=float(m.unit_lever_m),
        unit_tilt_options=_sub_tilts(getattr(cfg, "unit_tilts", None), idx),
        **cfg.gain_extra,
    )


def _sub_tilts(tilts, idx):
    """``{interval_s: (tilts_b, tilts_a)}`` of :func:`_unit_tilt_options` on the planes
    ``idx`` (an epoch's None kept), or None."""
    if not tilts:
        return None
    return {dt: tuple(None if om is None else om[idx] for om in pair) for dt, pair in tilts.items()}


def _white(state, epochs, active, b, step, z_crit, rejected, reject, min_planes, opts):
    """The white model: the study's adjustment with data snooping against the white σ."""
    max_iterations, tolerance, progress = opts
    c0, c1 = epochs[0].count, epochs[1].count
    n_start = int(active.sum())
    while True:
        it, converged, nred, qxx = _iterate(
            state, epochs, active, b, step, max_iterations, tolerance, progress, 0.05
        )
        _, _, vpv_b, stats = _blocks(state, epochs, b)
        n_cond = int(c0[active].sum() + c1[active].sum())
        k = int(active.sum())
        redundancy = n_cond + k - (6 + 4 * k)
        vpv = float(vpv_b[active].sum())
        s0 = vpv / redundancy if redundancy > 0 else float("nan")
        if not reject or k <= min_planes:
            break
        n_out = sum(1 for r in rejected if r[1].startswith("outlier"))
        if n_out >= MAX_REJECTED_SHARE * n_start:
            log.warning("data snooping stopped after %d rejected planes", n_out)
            break
        (w0, f0), (w1, f1) = stats
        with np.errstate(invalid="ignore", divide="ignore"):
            z = (f1 - f0) / np.sqrt((s0 if s0 == s0 else 1.0) * (1.0 / w0 + 1.0 / w1))
        z = np.where(active, np.abs(z), 0.0)
        worst = int(np.argmax(z))
        if not z[worst] > z_crit:
            break
        trial = active.copy()
        trial[worst] = False
        reason = (
            f"outlier: after-before mean misclosure {f1[worst] - f0[worst]:+.4f} m, "
            f"|w| = {z[worst]:.1f} > {z_crit:.2f} (alpha, Bonferroni, white model, "
            f"sigma0²={s0:.3g})"
        )
        log.info("rejecting plane %d: %s", worst, reason)
        if not _can_drop(state, epochs, trial, b, [worst]):
            break
        active = trial
        rejected.append((worst, reason))
    cov = (s0 if s0 == s0 else 1.0) * qxx
    return state, active, it, converged, nred, qxx, s0, redundancy, n_cond, cov


def _can_drop(state, epochs, trial, b, planes) -> bool:
    """Whether the adjustment stays regular without ``planes`` (state unchanged)."""
    saved = state.copy()
    try:
        _check_singular(_step_block(saved, epochs, trial, b)[2])
    except InputDataError:
        log.warning("plane(s) %s not rejected: without them the system is singular", planes)
        return False
    return True


def _point_factor(state, epochs, active, b):
    """Point-level a-posteriori variance factor with each plane's offset δ removed, the white
    model's factor at the same solution, the former's redundancy, the conditions and the
    after-epoch mean misclosures (f1 - f0) per plane."""
    c0, c1 = epochs[0].count, epochs[1].count
    _, _, vpv_b, stats = _blocks(state, epochs, b)
    (w0, f0), (w1, f1) = stats
    delta = state.delta
    with np.errstate(invalid="ignore"):
        vpv_d = vpv_b + np.where(active, 2.0 * delta * w1 * f1 + delta * delta * w1, 0.0)
    n_cond = int(c0[active].sum() + c1[active].sum())
    k = int(active.sum())
    red_w = n_cond + k - (6 + 4 * k)
    red_d = red_w - k
    s0w = float(vpv_b[active].sum()) / red_w if red_w > 0 else float("nan")
    s0d = float(vpv_d[active].sum()) / red_d if red_d > 0 else float("nan")
    with np.errstate(invalid="ignore"):
        mis = f1 - f0
    return s0d, s0w, red_d, n_cond, mis


def _with_cfg(step, cfg, state, epochs, active, b):
    return step(state, epochs, active, b, cfg)


def _stochastic(state, epochs, active, b, step, cfg, model, fixed, z_crit, rejected, reject,
                min_planes, opts, *, random_tilt=False):  # fmt: skip
    """Plane-level variance components (REML), robust plane tests and the GLS adjustment,
    iterated to a fixed point (see :mod:`.stochastic`); ``random_tilt``: estimate a random
    tilt per plane (unless ``fixed`` holds ``tilt_rad``)."""
    max_iterations, tolerance, progress = opts
    which = ("plane",) if model == "plane" else _stoch.COMPONENT_NAMES
    k_reject = max(_stoch.K_REJECT_MIN, z_crit)
    n_start = int(active.sum())
    weights = np.where(active, 1.0, np.nan)
    wstat = np.full(b, np.nan)
    est = None
    theta_old = None
    s0d = s0w = float("nan")
    it, converged = 0, False
    gross_done = not reject
    gross_passes = 0
    notes: List[str] = []
    apri = _apriori_condition_variance(epochs, active, cfg.model.normals, b)
    # the random tilt per plane: estimated (random_tilt) or given (tilt_rad)
    tilt_est = _stoch.TiltEstimate()
    if "tilt_rad" in fixed:
        cfg.tilt_var = float(fixed["tilt_rad"]) ** 2
        tilt_est = _stoch.TiltEstimate(cfg.tilt_var, source="fixed")
    # adjust_rigid_dense, the reference of the mixed model, has no random tilt
    tilt_free = random_tilt and "tilt_rad" not in fixed and step is _step_block
    for outer in range(MAX_OUTER + MAX_GROSS_PASSES):
        it, converged, nred, qxx = _iterate(
            state, epochs, active, b, functools.partial(_with_cfg, step, cfg if outer else None),
            max_iterations, tolerance, progress, 0.05 + 0.1 * outer / MAX_OUTER,
        )  # fmt: skip
        s0d, _, _, _, mis = _point_factor(state, epochs, active, b)
        cfg.s0sq = s0d if s0d == s0d and s0d > 0 else 1.0
        g_mat, g_vec, _ = _reduce(state, epochs, active, b)
        pl = _PlaneLevel(g_mat, g_vec)
        idx = np.flatnonzero(active)
        e = pl.y  # at convergence the increment is nil: y is the misclosure residual
        xd = pl.h
        t_s, rt_s = _component_tilts(cfg, pl, active, cfg.tilt_keep[active])
        p_s = cfg.s0sq * pl.p
        cfg.model.normals[idx] = state.n[idx] / np.linalg.norm(state.n[idx], axis=1)[:, None]
        if not gross_done:
            # repeated until a pass finds none: several gross outliers mask each other in a
            # fit that still holds them
            gross_passes += 1
            gross_done = gross_passes >= MAX_GROSS_PASSES
            gross, s_rob = _stoch.robust_start(e, xd, t_s, p_s, _stoch.GROSS_MAD, rt_s)
            drop = [int(idx[j]) for j in np.flatnonzero(gross)]
            n_out = sum(1 for r in rejected if r[1].startswith("outlier"))
            drop = drop[: max(0, int(MAX_REJECTED_SHARE * n_start) - n_out)]
            if not drop:
                gross_done = True
            else:
                trial = active.copy()
                trial[drop] = False
                if int(trial.sum()) >= max(min_planes, 3) and _can_drop(
                    state, epochs, trial, b, drop
                ):
                    for j in drop:
                        jj = int(np.searchsorted(idx, j))
                        zj = abs(e[jj] - np.median(e)) / math.sqrt(p_s[jj] + s_rob**2)
                        rejected.append((j, f"outlier: after-before mean misclosure "
                                         f"{mis[j]:+.4f} m, {zj:.1f} robust std from the "
                                         f"plane-level spread (robust start, plane σ "
                                         f"{s_rob * 1000:.2f} mm)"))  # fmt: skip
                        weights[j] = 0.0
                    active = trial
                    log.info(
                        "robust start: %d gross outlier plane%s rejected",
                        len(drop),
                        "" if len(drop) == 1 else "s",
                    )
                    continue
        if not _stoch.REML_RANDOM_TILT:
            # the components and the plane tests with the tilts point-noise precise; the
            # random tilt weighs them in the adjustment only
            t_s, rt_s = pl.tilt(cfg.s0sq)
        est = _stoch.estimate_components(
            cfg.model, idx, e, xd, t_s, p_s, which=which, fixed=fixed,
            inflation=cfg.inflation[idx], prior_plane_var=PRIOR_PLANE_SHARE**2 * apri, rt=rt_s,
        )  # fmt: skip
        cfg.theta = {n: v for n, v in est.theta.items() if v > 0}
        cfg.kernel = est.kernel
        cfg.unit_interval = est.unit_interval_s
        cfg.model = cfg.model.with_unit_interval(est.unit_interval_s).with_unit_lever(
            est.unit_lever_m
        )
        tilt_moved = False
        if tilt_free:
            # the tilts' misclosures against their point noise, with the offsets' model as
            # just estimated (stochastic.estimate_tilt_variance)
            vop = cfg.v_operator(active, pl.p)
            vih = vop.solve(xd)
            y_o = e - cfg.shift(active)
            drift = None
            cols = _unit_columns(cfg, active) if UNIT_DRIFT_TILTS else None
            if cols is not None:  # σ_t beside the drift's tilts, not counting them again
                z_o, lam, mean, zt = cols
                drift = (zt, z_o, lam, mean, vop.solve(z_o), xd, y_o)
            tilt_est = _stoch.estimate_tilt_variance(
                pl.tr / cfg.s0sq, pl.rtr / cfg.s0sq, xd.T @ vih, vih.T @ y_o,
                start=cfg.tilt_var, drift=drift,
                left_out=None if drift is None else ~cfg.tilt_keep[idx],
            )  # fmt: skip
            old_tv, cfg.tilt_var = cfg.tilt_var, tilt_est.var
            tilt_moved = abs(cfg.tilt_var - old_tv) > 0.02 * max(cfg.tilt_var, old_tv)
            keep = np.ones(idx.size, dtype=bool) if tilt_est.keep is None else tilt_est.keep
            tilt_moved = tilt_moved or not np.array_equal(keep, cfg.tilt_keep[idx])
            cfg.tilt_keep[:] = True
            cfg.tilt_keep[idx] = keep
            if _stoch.REML_RANDOM_TILT:
                t_s, rt_s = _component_tilts(cfg, pl, active, keep, cols)
        changed = False
        if reject and idx.size > min_planes:
            # the test is against the model, not the last weights
            vop = cfg.v_operator(active, pl.p, inflated=False)
            e_c = e - cfg.shift(active)
            if vop.sparse:
                w = _stoch.w_statistics_large(vop, e_c, xd, t_s, rt_s)
            else:
                w = _stoch.w_statistics(_stoch.PlaneGLS(vop.v, xd, t_s, rt_s), e_c)
            dv = vop.diag()
            wstat[:] = np.nan
            wstat[idx] = w
            bad = np.flatnonzero(np.abs(w) > k_reject)
            n_out = sum(1 for r in rejected if r[1].startswith("outlier"))
            room = int(MAX_REJECTED_SHARE * n_start) - n_out
            if bad.size and room > 0 and idx.size - 1 >= min_planes:
                order = bad[np.argsort(-np.abs(w[bad]))][: max(1, min(room, bad.size))]
                order = order[: max(1, idx.size - min_planes)]
                drop = [int(idx[j]) for j in order]
                trial = active.copy()
                trial[drop] = False
                if _can_drop(state, epochs, trial, b, drop):
                    for j, jj in zip(drop, order):
                        rejected.append((j, f"outlier: after-before mean misclosure "
                                         f"{mis[j]:+.4f} m, |w| = {abs(w[jj]):.1f} > "
                                         f"{k_reject:.2f} against the plane-level spread "
                                         f"(stochastic model {model!r})"))  # fmt: skip
                        weights[j] = 0.0
                        cfg.inflation[j] = 0.0
                    active = trial
                    changed = True
            if not changed:
                wt = _stoch.igg3_weight(w, _stoch.K_WEIGHT, k_reject)
                new_infl = np.zeros(b)
                with np.errstate(divide="ignore"):
                    new_infl[idx] = np.where(wt > 0, dv * (1.0 / np.maximum(wt, 1e-12) - 1.0), 0)
                old_w = weights[idx].copy()
                weights[idx] = wt
                if np.max(np.abs(old_w - wt), initial=0.0) > 0.05:
                    changed = True
                cfg.inflation = new_infl
        theta_now = np.array([est.theta.get(n, 0.0) for n in _stoch.COMPONENT_NAMES])
        if theta_old is not None and not changed and not tilt_moved:
            scale = max(float(np.max(theta_now)), float(np.median(p_s)), 1e-14)
            if float(np.max(np.abs(theta_now - theta_old))) <= 0.02 * scale:
                break
        theta_old = theta_now
    else:
        notes.append(f"components and plane tests did not settle in {MAX_OUTER} rounds")
    # the solution and covariance with the final components
    it, converged, nred, qxx = _iterate(
        state, epochs, active, b, functools.partial(_with_cfg, step, cfg), max_iterations,
        tolerance, progress, 0.9,
    )  # fmt: skip
    _, s0w, red_d, n_cond, mis = _point_factor(state, epochs, active, b)
    g_mat, g_vec, _ = _reduce(state, epochs, active, b)
    pl = _PlaneLevel(g_mat, g_vec)
    idx = np.flatnonzero(active)
    vop = cfg.v_operator(active, pl.p)
    n_eff = _stoch.effective_planes(vop, pl.h)
    # the motion's gain on the plane-level random effects, Q Hᵀ V⁻¹ (6, k), for the
    # covariance with another adjustment of the same survey (stochastic.cross_covariance)
    vih = vop.solve(pl.h)
    t_fin, rt_fin = pl.tilt(cfg.s0sq, cfg.tilt_var, cfg.tilt_keep[active])
    n_fin = t_fin + pl.h.T @ vih
    k_o, wz, terms = vih.T, None, None
    if UNIT_DRIFT_TILTS:  # the tilts given the offsets
        terms = _drift_tilt_terms(cfg, pl, vop, vih, active, pl.y - cfg.shift(active))
        if terms is not None:
            n_fin = n_fin + terms[0]
            k_o, wz = k_o + terms[2], terms[3]
    q_fin = np.linalg.inv(0.5 * (n_fin + n_fin.T))
    # the tilts the joint components see (as this side's components saw them)
    t_c, rt_c, tilt_extra = t_fin, rt_fin, {}
    if terms is not None:  # the gain on each plane's tilt, for the other side's covariance
        at_f, zt_f, zo_f, lam_f, viz_f = terms[4]
        t_c, rt_c = _component_tilts(cfg, pl, active, cfg.tilt_keep[active])
        tg, tn = _stoch.tilt_gains(at_f, zt_f, zo_f, lam_f, viz_f, pl.h, q_fin)
        tilt_extra = dict(tilt_gain=tg, tilt_noise=tn)
    cfg.gain = q_fin @ k_o
    cfg.gain_idx = idx
    cond = cfg.condition(active)
    # the motion's gain on the contrast rows: x̂ takes Q Hᵀ V⁻¹ (y − Z g c)
    cfg.contrast_gain = None if cond is None else -cfg.gain @ cond.z @ cond.g
    if cond is not None and wz is not None:  # and through the tilts: μ moves ỹ_t by −Z_t μ
        cfg.contrast_gain = cfg.contrast_gain - q_fin @ wz @ cond.g
    cfg.gain_extra = dict(
        model=model, fixed=dict(fixed), e=pl.y.copy(), p=cfg.s0sq * pl.p, h=pl.h.copy(),
        inflation=cfg.inflation[idx].copy(), t=t_c, rt=rt_c,
        q=0.5 * (q_fin + q_fin.T), prior_plane_var=PRIOR_PLANE_SHARE**2 * apri, **tilt_extra,
    )  # fmt: skip
    # estimated components make the GLS covariance optimistic (Kackar & Harville 1984): the
    # slip then follows about a t distribution with the plane-level residual degrees of
    # freedom nu = planes - 6, whose variance is nu / (nu - 2) times the normal one
    estimated = est is not None and any(v_ == "estimated" for v_ in est.source.values())
    nu = max(idx.size - 6.0, 3.0)
    small = nu / (nu - 2.0) if estimated else 1.0
    qxx = qxx * small
    cfg.small = small
    qw = np.linalg.inv(0.5 * (pl.n_white + pl.n_white.T))
    sig_white = (s0w if s0w == s0w else 1.0) * qw[3:, 3:]
    stoch = _components_result(model, est, epochs, active, cfg, idx.size, n_eff, sig_white,
                               notes, weights, wstat, state.delta, mis, b, small,
                               tilt_est)  # fmt: skip
    cov = 0.5 * (qxx + qxx.T)
    return (state, active, it, converged, nred, qxx, cfg.s0sq, red_d, n_cond, cov), stoch


def _apriori_condition_variance(epochs, active, normals, b) -> float:
    """Median over planes of the a-priori variance of one point condition (m²)."""
    s_w = []
    for ep in epochs:
        s0, _, _ = ep.weighted(normals, b)
        with np.errstate(divide="ignore", invalid="ignore"):
            s_w.append((ep.count / s0)[active])
    return float(np.median(np.concatenate(s_w))) if active.any() else float("nan")


def _components_result(model, est, epochs, active, cfg, k, n_eff, sig_white, notes, weights,
                       wstat, delta, mis, b, small=1.0, tilt=None):  # fmt: skip
    """VarianceComponents and the per-plane diagnostics of a stochastic adjustment."""
    apri = _apriori_condition_variance(epochs, active, cfg.model.normals, b)
    comps = [
        _stoch.Component(
            "white",
            math.sqrt(cfg.s0sq * apri) if apri == apri else float("nan"),
            source="estimated",
            variance_factor=float(cfg.s0sq),
            note="point noise: a-posteriori variance factor of the point residuals with each "
            "plane's offset removed",
        )
    ]
    est_notes = dict(est.notes) if est is not None else {}
    for name in _stoch.COMPONENT_NAMES:
        if model == "plane" and name != "plane":
            comps.append(_stoch.Component(name, 0.0, source="off", note="not in the 'plane' model"))
            continue
        th = est.theta.get(name, 0.0) if est is not None else 0.0
        sd_var = est.sd.get(name, float("nan")) if est is not None else float("nan")
        sig = math.sqrt(max(th, 0.0))
        sd = sd_var / (2.0 * sig) if sig > 0 and sd_var == sd_var else float("nan")
        src = est.source.get(name, "off") if est is not None else "off"
        comps.append(_stoch.Component(name, sig, sd, src, est_notes.get(name, "")))
    all_notes = list(notes) + [v for k_, v in est_notes.items() if k_ in ("reml", "plane_level")]
    if tilt is not None and tilt.note:
        all_notes.append(f"random tilt per plane: {tilt.note}")
    if k < _stoch.MIN_PLANES_VCE:
        all_notes.append(f"only {k} planes: the components are poorly determined")
    vc = _stoch.VarianceComponents(
        model=model,
        method="point level: a-posteriori variance factor; plane level: REML (iterated "
        "MINQUE / Helmert-Förstner fixed point), spatial correlation family and range by "
        "profile REML; "
        "robust: w-tests of correlated plane misclosures, IGG-III weights; covariance "
        "scaled by nu/(nu-2), nu = planes - 6, for the estimated components",
        components=tuple(comps),
        spatial_range_m=float(est.range_m) if est is not None else float("nan"),
        spatial_family=est.kernel.family if est is not None else "spherical",
        n_planes=int(k),
        n_eff=float(n_eff),
        covariance_white=sig_white,
        small_sample_factor=float(small),
        notes=tuple(all_notes),
        tilt=tilt if tilt is not None else _stoch.TiltEstimate(),
        unit_interval_s=float(cfg.unit_interval),
        unit_lever_m=float(cfg.model.unit_lever_m),
        n_contrasts=(
            (0, 0)
            if cfg.model.contrasts is None or cfg.condition(active) is None
            else cfg.model.contrasts.counts
        ),
        contrast_misfit_m=(
            math.sqrt(max(est.theta[_stoch.CONTRAST_NUGGET], 0.0))
            if est is not None and _stoch.CONTRAST_NUGGET in est.theta
            else float("nan")
        ),
    )
    delta_out = np.where(active, delta, np.nan)
    return vc, weights, wstat, delta_out, mis


def _finish(
    state, epochs, active, b, centre, it, converged, nred, qxx, s0, redundancy, n_cond,
    rejected, n0, d0, before_plane, after_plane, progress, cov, model, stoch,
):  # fmt: skip
    n = np.where(active[:, None], state.n, n0)
    d = np.where(active, state.d, d0)
    norm = np.linalg.norm(n, axis=1)
    n = n / norm[:, None]
    d = d / norm
    resid = []
    for ep, lab, after in zip(epochs, (before_plane, after_plane), (False, True)):
        if ep.u is None:  # planes given by moments: no per-point residuals
            resid.append(np.zeros(0))
            continue
        st = _State(state.r, state.t, n, d)
        _, _, f0, bvec = _epoch_rows(st, ep.g, after)
        f = f0[ep.idx] + np.einsum("ij,ij->i", bvec[ep.idx], ep.u)
        if ep.all_valid:
            resid.append(f)
        else:
            out = np.full(lab.shape[0], np.nan)
            out[ep.valid] = f
            resid.append(out)
    has = (epochs[0].count + epochs[1].count) > 0
    plane_params = np.full((b, 4), np.nan)
    plane_params[has, :3] = n[has]
    plane_params[has, 3] = d[has] - n[has] @ centre
    params = np.concatenate([rotation_vector(state.r), state.t])
    ev, evec = np.linalg.eigh(nred[3:, 3:])
    weak = []
    for j in range(3):
        if ev[j] < WEAK_RATIO * ev[-1]:
            msg = (
                f"translation along {_describe_direction(evec[:, j])} is weakly constrained "
                f"(normal-matrix eigenvalue ratio {ev[j] / ev[-1]:.1e}): all matched normals "
                "are nearly perpendicular to it"
            )
            log.warning(msg)
            weak.append(msg)
    report(progress, 1.0, "done")
    return RigidResult(
        params=params,
        covariance=cov,
        cofactor=qxx,
        sigma=np.sqrt(np.diag(cov)),
        variance_factor=float(s0),
        redundancy=int(redundancy),
        iterations=int(it),
        converged=bool(converged),
        centre=np.array(centre, dtype=np.float64),
        n_planes=int(active.sum()),
        n_points=int(n_cond),
        plane_params=plane_params,
        residuals_before=resid[0],
        residuals_after=resid[1],
        rejected_planes=tuple(sorted(rejected)),
        translation_eigenvalues=ev,
        translation_eigenvectors=evec,
        weak_directions=tuple(weak),
        stochastic_model=model,
        **_plane_diagnostics(stoch, b, active),
    )


def _plane_diagnostics(stoch, b, active):
    """RigidResult's per-plane fields of a stochastic adjustment (defaults for "white")."""
    if stoch is None:
        return {}
    vc, weights, wstat, delta, mis, gain = stoch
    down = tuple(
        (int(j), float(weights[j]))
        for j in np.flatnonzero(active & (weights < 1.0) & (weights > 0.0))
    )
    return {
        "variance_components": vc,
        "plane_weights": weights,
        "plane_w": wstat,
        "plane_offset_m": delta,
        "plane_misclosure_m": np.where(np.isfinite(weights), mis, np.nan),
        "downweighted_planes": down,
        "plane_gain": gain,
    }


def adjust_rigid(
    before: np.ndarray,
    before_plane: np.ndarray,
    after: np.ndarray,
    after_plane: np.ndarray,
    *,
    sigma_before=0.05,
    sigma_after=0.05,
    centre: Optional[np.ndarray] = None,
    max_iterations: int = 20,
    tolerance: float = 1e-10,
    reject_outlier_planes: bool = True,
    alpha: float = 0.001,
    min_planes: int = 3,
    progress: Optional[ProgressCallback] = None,
    stochastic_model: str = "white",
    unit_before: Optional[np.ndarray] = None,
    unit_after: Optional[np.ndarray] = None,
    components: Optional[dict] = None,
    random_tilt: Optional[bool] = None,
    unit_time_before: Optional[np.ndarray] = None,
    unit_time_after: Optional[np.ndarray] = None,
    unit_contrasts: Optional[tuple] = None,
) -> RigidResult:
    """Estimate the rigid motion before -> after from points on matched planes.

    Gauss-Helmert adjustment with plane blocks eliminated (cost linear in points and planes);
    see the module docstring for the equations.

    Parameters
    ----------
    before : (N1, 3) float64
        Before-epoch points, metres.
    before_plane : (N1,) int
        Plane index ``0 .. b-1`` of each before point; negative = ignored.
    after : (N2, 3) float64
        After-epoch points, metres.
    after_plane : (N2,) int
        Plane index of each after point (same numbering as ``before_plane``).
    sigma_before, sigma_after : float, (3,), (N, 3) or (N, 3, 3)
        Point precision per epoch: a scalar sigma (m), a per-axis sigma (m), per-point
        per-axis sigmas (m) or per-point covariance matrices (m²).
    centre : (3,) float64, optional
        Centre of the coordinates (default: centroid of all used points of both epochs). The
        translation is the displacement of the material at the centre.
    max_iterations : int
        Gauss-Helmert iterations per adjustment.
    tolerance : float
        Convergence when every parameter increment is below it (rad, m).
    reject_outlier_planes : bool
        Remove planes that moved differently (data snooping, see module docstring).
    alpha : float
        Significance level of the outlier test (over all planes, Bonferroni).
    min_planes : int
        Fewest planes with points in both epochs.
    progress : callable, optional
        ``progress(fraction, message)``.
    stochastic_model : {"white", "plane", "full"}
        "white": independent point errors only, data snooping against the white σ (the
        study's model). "plane": plus one random offset per plane. "full": plus spatially
        correlated plane offsets and a rigid error per acquisition unit (when ``unit_*`` are
        given). Components are estimated by REML; see :mod:`.stochastic`.
    unit_before, unit_after : (N1,), (N2,) int, optional
        Acquisition unit of each point (PointSourceId of ALS strips or MLS passes, trajectory
        segments, TLS setups), for the "full" model.
    unit_time_before, unit_time_after : (N1,), (N2,) float64, optional
        Acquisition time of each point (GpsTime, seconds), with the units: each unit's error
        may then drift along time (:mod:`.unit_drift`; the knot spacing, or none, chosen by
        restricted likelihood). None: one rigid error per unit.
    components : dict, optional
        Plane-level components to hold fixed instead of estimating them, as standard
        deviations in metres: ``plane``, ``spatial``, ``unit_before``, ``unit_after`` and
        ``spatial_range_m`` (e.g. a side's global estimate for a strip or window), and
        ``tilt_rad``, the random tilt per plane in radians (:data:`.stochastic.RANDOM_TILT`;
        not with :func:`adjust_rigid_dense`, which has no random tilt).
    random_tilt : bool, optional
        Plane-level models: each plane is also tilted by the survey error, a random tilt
        whose variance is estimated by REML from the planes' tilt misclosures
        (:func:`.stochastic.estimate_tilt_variance`), so the tilts inform the rotation only as
        far as the survey lets them (docs/accuracy.md, "A random tilt per plane"). None: the
        default, :data:`.stochastic.RANDOM_TILT`. Not with :func:`adjust_rigid_dense`.
    unit_contrasts : (2,) tuple of UnitContrasts or None, optional
        The "full" model with units: each epoch's within-epoch unit contrasts
        (:mod:`.unit_contrasts`; the two units' offset on a plane both see), which identify
        the unit components and take the units' errors they predict off the misclosures
        (a strip adjustment inside this one). None (default): those of this adjustment's own
        planes; give a survey's (both sides of a fault, every plane found) to tie the units
        across it; ``(None, None)``: none.

    Returns
    -------
    RigidResult

    Raises
    ------
    InputDataError
        Too few matched planes, NaN/inf coordinates, or a singular system (names the
        unconstrained direction).
    InvalidParameterError
        Bad sigma shapes or values, or bad options.
    """
    return _run(
        before, before_plane, after, after_plane, sigma_before=sigma_before,
        sigma_after=sigma_after, centre=centre, max_iterations=max_iterations,
        tolerance=tolerance, reject_outlier_planes=reject_outlier_planes, alpha=alpha,
        min_planes=min_planes, progress=progress, dense=False,
        stochastic_model=stochastic_model, unit_before=unit_before, unit_after=unit_after,
        components=components, random_tilt=random_tilt, unit_time_before=unit_time_before,
        unit_time_after=unit_time_after, unit_contrasts=unit_contrasts,
    )  # fmt: skip


def adjust_rigid_dense(
    before: np.ndarray,
    before_plane: np.ndarray,
    after: np.ndarray,
    after_plane: np.ndarray,
    *,
    sigma_before=0.05,
    sigma_after=0.05,
    centre: Optional[np.ndarray] = None,
    max_iterations: int = 20,
    tolerance: float = 1e-10,
    reject_outlier_planes: bool = True,
    alpha: float = 0.001,
    min_planes: int = 3,
    progress: Optional[ProgressCallback] = None,
    stochastic_model: str = "white",
    unit_before: Optional[np.ndarray] = None,
    unit_after: Optional[np.ndarray] = None,
    components: Optional[dict] = None,
    random_tilt: Optional[bool] = None,
    unit_time_before: Optional[np.ndarray] = None,
    unit_time_after: Optional[np.ndarray] = None,
) -> RigidResult:
    """Reference solver: :func:`adjust_rigid` with the full Gauss-Helmert matrices.

    Forms ``A`` (conditions x (6 + 4b)), ``B C B^T`` per condition, ``G`` and the full bordered
    normal matrix of Eq. 17 from every point, and solves it densely. Small problems only
    (at most ``DENSE_MAX_UNKNOWNS`` unknowns). Same parameters, result and errors as
    :func:`adjust_rigid`.
    """
    return _run(
        before, before_plane, after, after_plane, sigma_before=sigma_before,
        sigma_after=sigma_after, centre=centre, max_iterations=max_iterations,
        tolerance=tolerance, reject_outlier_planes=reject_outlier_planes, alpha=alpha,
        min_planes=min_planes, progress=progress, dense=True,
        stochastic_model=stochastic_model, unit_before=unit_before, unit_after=unit_after,
        components=components, random_tilt=random_tilt, unit_time_before=unit_time_before,
        unit_time_after=unit_time_after,
    )  # fmt: skip
