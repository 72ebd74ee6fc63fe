"""Point-to-plane ICP and windowed ICP displacement fields (Aryal et al., section 3.2.2).

The study aligns the two epochs on stable ground (masking the moving area), then divides the
second epoch into square cells (5 x 5 m) and registers each cell onto the first epoch's surface
with point-to-plane ICP (Chen & Medioni 1992; linearised as in Low 2004). The rigid motion of a
cell, evaluated at the cell centre, is that cell's displacement.

Conventions
-----------
* The fitted transform ``T`` maps SOURCE (epoch 2, "after") points onto the TARGET (epoch 1,
  "before") surface: ``T(p) = R (p - c) + c + t`` with ``c`` the reference point (``ICPFit.centre``)
  and ``R = exp([r]x)`` the rotation of rotation vector ``r`` (Rodrigues).
* The DISPLACEMENT reported to users is the ground motion from before to after at a point ``p``
  given in epoch-2 coordinates: ``d(p) = p - T(p)`` (so a surface moved by +0.2 m in x gives
  ``dx = +0.2``). :meth:`ICPFit.displacement_at` returns it with its propagated covariance.
* Rotations reported per cell (``rx, ry, rz``) are those of the ground motion, i.e. of ``T``'s
  inverse: ``-r`` (radians, right-handed about x east, y north, z up, through the cell centre).

Uncertainty
-----------
The parameter covariance is ``s0^2 (A'A)^-1`` at the final correspondences, ``A`` the exact
Jacobian of the point-to-plane residuals w.r.t. (rotation vector, translation). ``s0^2`` is
``v'v / (n - 6)`` for least squares, Huber's asymptotic factor ``sum(psi^2) / (n - 6) /
mean(psi')^2`` with robust weights, times the ratio of target-clustered to plain squared
residuals (several source points paired with one target point share its noise; without this
the sigmas of independently sampled clouds are ~20 % too small).

Limitations: the tangent-plane approximation leaves a bias of about ``curvature * spacing^2 / 2``
per pair (sub-millimetre at 200-400 pts/m2 on natural terrain) that the sigmas do not include;
on real vegetated or nearly flat cells, where sub-spacing roughness makes residuals spatially
correlated, the sigmas are optimistic (lone-star split-halves: actual errors 2-4 sigma).

Everything is numpy + ``scipy.spatial.cKDTree``; no file I/O.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Dict, Optional, Sequence, Tuple, Union

import numpy as np

from .errors import DependencyError, InputDataError, InvalidParameterError
from .icp_options import EIG_RTOL, NULL_RTOL, _Options, _weights
from .progress import ProgressCallback, report, scaled
from .rotation import left_jacobian as _left_jacobian
from .rotation import rotation_matrix, rotation_vector
from .threads import single_blas_thread

log = logging.getLogger(__name__)

NORMAL_PLANARITY_RTOL = 1e-10  # neighbourhoods whose middle eigenvalue is below this are lines
PREALIGN_MAX_POINTS = 200_000  # source points sampled for the global pre-alignment
ROBUST_CHOICES = (None, "tukey", "huber")
SIGMA_SCALING_CHOICES = ("field", "region", "formal")
SIGMA_REGION_BY = ("roughness", "density", "sigma")
SIGMA_MODELS = ("blocks", "independent")


# --------------------------------------------------------------------------- rotations


# --------------------------------------------------------------------------- result type


@dataclass(frozen=True)
class ICPFit:
    """A rigid transform fitted by point-to-plane ICP, with its parameter covariance.

    The transform maps source (epoch 2) points onto the target (epoch 1) surface::

        T(p) = R (p - centre) + centre + t,   R = rotation_matrix(params[:3]),  t = params[3:]

    Attributes
    ----------
    rotation : (3, 3) float64
        ``R``.
    translation : (3,) float64
        Translation of the transform written as ``T(p) = R p + translation`` (metres); equal to
        ``centre + t - R centre`` (large when the centre is far from the origin and R != I).
    params : (6,) float64
        ``(rx, ry, rz, tx, ty, tz)``: rotation vector (radians; for small angles the rotations
        about x, y, z) and translation ``t`` about ``centre`` (metres).
    covariance : (6, 6) float64
        Covariance of ``params`` (rad^2, rad m, m^2): the inverse normal matrix of the last
        iteration times the a-posteriori variance factor (``v'v / (n - 6)`` for plain least
        squares; Huber's asymptotic factor with robust weights; times the shared-target
        inflation, see the module notes). A parameter the geometry leaves undetermined (see
        ``null_space``) has variance ``inf`` and NaN covariances.
    centre : (3,) float64
        Reference point of ``params`` (metres), e.g. the cell centre.
    rmse_m : float
        RMS point-to-plane residual of the correspondences used in the last iteration (metres).
    sigma0_m : float
        A-posteriori standard deviation of unit weight (metres).
    n_correspondences : int
        Correspondences used in the last iteration.
    iterations : int
        Iterations run.
    converged : bool
        The last step was below both tolerances.
    condition : float
        Condition number of the normal matrix with rotations scaled by the RMS radius of the
        points (large = weakly constrained; inf for a perfect plane).
    null_space : (6, m) float64
        Unit directions of parameter space left undetermined by the geometry (m = 0 normally;
        e.g. x, y translation and z rotation on a perfect plane). Outputs depending on them
        get infinite variance; the rest of the covariance is that of the determined part.
    """

    rotation: np.ndarray
    translation: np.ndarray
    params: np.ndarray
    covariance: np.ndarray
    centre: np.ndarray
    rmse_m: float
    sigma0_m: float
    n_correspondences: int
    iterations: int
    converged: bool
    condition: float
    null_space: np.ndarray = field(default_factory=lambda: np.zeros((6, 0)))

    @property
    def sigma(self) -> np.ndarray:
        """(6,) standard deviations of ``params`` (radians, metres)."""
        return np.sqrt(np.diag(self.covariance))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points: ``T(p)``.

        Parameters
        ----------
        points : (N, 3) or (3,) float64, metres

        Returns
        -------
        Same shape float64, metres (a new array).
        """
        p = np.asarray(points, dtype=np.float64)
        return (p - self.centre) @ self.rotation.T + (self.centre + self.params[3:])

    def displacement_at(self, xyz: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Ground motion (before -> after) at epoch-2 points and its covariance.

        ``d(p) = p - T(p)``; its covariance is ``J C J'`` with ``C`` the parameter covariance
        and ``J = d d / d params = [ [R u]x J_l(r) , -I ]``, ``u = p - centre``.

        Parameters
        ----------
        xyz : (N, 3) or (3,) float64
            Points in epoch-2 coordinates (metres).

        Returns
        -------
        d : (N, 3) or (3,) float64
            Displacement, metres.
        cov : (N, 3, 3) or (3, 3) float64
            Its covariance, m^2.
        """
        p = np.asarray(xyz, dtype=np.float64)
        single = p.ndim == 1
        p2 = np.atleast_2d(p)
        u = p2 - self.centre
        ru = u @ self.rotation.T
        d = u - ru - self.params[3:]
        jl = _left_jacobian(self.params[:3])
        # [a]x for every row a of ru, then times J_l
        sk = np.zeros((len(ru), 3, 3))
        sk[:, 0, 1], sk[:, 0, 2] = -ru[:, 2], ru[:, 1]
        sk[:, 1, 0], sk[:, 1, 2] = ru[:, 2], -ru[:, 0]
        sk[:, 2, 0], sk[:, 2, 1] = -ru[:, 1], ru[:, 0]
        jac = np.concatenate([sk @ jl, np.broadcast_to(-np.eye(3), sk.shape)], axis=2)
        c = np.where(np.isfinite(self.covariance), self.covariance, 0.0)
        cov = _undetermined(jac @ c @ jac.transpose(0, 2, 1), jac, self.null_space)
        return (d[0], cov[0]) if single else (d, cov)


# --------------------------------------------------------------------------- validation


def _points(name: str, arr, *, allow_empty: bool = False) -> np.ndarray:
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputDataError(f"{name} must be an (N, 3) point array, got shape {a.shape}")
    if a.shape[0] == 0 and not allow_empty:
        raise InputDataError(f"{name} is empty; give at least a few hundred points")
    if not np.all(np.isfinite(a)):
        raise InputDataError(f"{name} contains NaN or infinite coordinates; remove those points")
    return a


def _positive(name: str, value, *, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        need = "a non-negative" if allow_zero else "a positive"
        raise InvalidParameterError(f"{name} must be {need} number, got {value!r}")
    return v


def _int_at_least(name: str, value, lo: int) -> int:
    if isinstance(value, bool) or int(value) != value or value < lo:
        raise InvalidParameterError(f"{name} must be an integer >= {lo}, got {value!r}")
    return int(value)


def _options(
    max_iterations=50,
    tolerance_m=1e-5,
    tolerance_rad=1e-7,
    max_correspondence_m=None,
    trim_fraction=0.0,
    robust="tukey",
    neighbours_k=12,
    tolerance_sigma=0.05,
) -> _Options:
    mc = None
    if max_correspondence_m is not None:
        mc = _positive("max_correspondence_m", max_correspondence_m)
    tf = float(trim_fraction)
    if not (0.0 <= tf < 0.5):
        raise InvalidParameterError(f"trim_fraction must be in [0, 0.5), got {trim_fraction!r}")
    if robust not in ROBUST_CHOICES:
        raise InvalidParameterError(f"robust must be one of {ROBUST_CHOICES}, got {robust!r}")
    return _Options(
        max_iterations=_int_at_least("max_iterations", max_iterations, 1),
        tolerance_m=_positive("tolerance_m", tolerance_m),
        tolerance_rad=_positive("tolerance_rad", tolerance_rad),
        tolerance_sigma=_positive("tolerance_sigma", tolerance_sigma, allow_zero=True),
        max_correspondence_m=mc,
        trim_fraction=tf,
        robust=robust,
        neighbours_k=_int_at_least("neighbours_k", neighbours_k, 3),
    )


# --------------------------------------------------------------------------- normals


def _pca_normals(nb: np.ndarray) -> np.ndarray:
    """(K, k, 3) neighbourhoods -> (K, 3) unit normals (smallest-eigenvalue eigenvector,
    oriented z >= 0); NaN for line-like or degenerate neighbourhoods.

    Closed form, written here because ``np.linalg.eigh`` on K 3 x 3 matrices costs three
    times as much (its per-matrix LAPACK call): the eigenvalues of the symmetric covariance by
    the trigonometric solution of its characteristic cubic (Smith 1961), the eigenvector of
    the smallest as the largest cross product of two rows of ``C - e0 I``. Neighbourhoods
    whose two smallest eigenvalues nearly coincide are left to ``eigh``, so the result is
    :func:`_pca_normals_reference`'s to rounding (tests).
    """
    d = nb - nb.mean(axis=1, keepdims=True)  # centred: no UTM cancellation
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    a00, a11, a22 = (np.einsum("kn,kn->k", u, u) for u in (x, y, z))
    a01, a02, a12 = (np.einsum("kn,kn->k", u, w) for u, w in ((x, y), (x, z), (y, z)))
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt(
        (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0
    )
    det = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    )
    r = np.clip(det / (2.0 * np.where(p > 0, p, 1.0) ** 3), -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    e2 = q + 2.0 * p * np.cos(phi)  # largest
    e0 = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)  # smallest
    e1 = 3.0 * q - e2 - e0
    r0 = np.stack([a00 - e0, a01, a02], axis=1)
    r1 = np.stack([a01, a11 - e0, a12], axis=1)
    r2 = np.stack([a02, a12, a22 - e0], axis=1)
    c = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)
    nn = np.einsum("kij,kij->ki", c, c)
    rows = np.arange(len(c))
    best = np.argmax(nn, axis=1)
    n = c[rows, best] / np.sqrt(np.maximum(nn[rows, best], 1e-300))[:, None]
    n[n[:, 2] < 0] *= -1.0
    # the cubic's roots lose precision where two coincide (lines, repeated points, blobs
    # with no preferred normal): those few go to eigh, so every result is eigh's to rounding
    scale = np.maximum(e2, 1e-300)
    hard = ~((e1 - e0 > 1e-3 * scale) & (e1 > 1e-6 * scale))
    if hard.any():
        n[hard] = _pca_normals_reference(nb[hard])
    return n


def _pca_normals_reference(nb: np.ndarray) -> np.ndarray:
    """Slow obvious :func:`_pca_normals`: ``np.linalg.eigh`` of each covariance."""
    d = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("kni,knj->kij", d, d)
    w, v = np.linalg.eigh(cov)
    n = v[:, :, 0].copy()
    n[n[:, 2] < 0] *= -1.0
    bad = ~(w[:, 1] > NORMAL_PLANARITY_RTOL * np.maximum(w[:, 2], 1e-300))
    n[bad] = np.nan
    return n


class _NormalCache:
    """Target normals computed on demand (only for points used as correspondences)."""

    CHUNK = 100_000

    def __init__(self, points: np.ndarray, tree, k: int, offset: Optional[np.ndarray] = None):
        self.points = points  # coordinates the tree was built on (minus ``offset``)
        self.tree = tree
        self.k = min(int(k), len(points))
        self.offset = offset
        self.normals = np.full((len(points), 3), np.nan)
        self.done = np.zeros(len(points), dtype=bool)
        # an OpenCL GridTargets of the same points (same offset) that computes the normals
        self.device = None

    def __call__(self, idx: np.ndarray) -> np.ndarray:
        self.ensure(idx)
        return self.normals[idx]

    def ensure(self, idx: np.ndarray) -> int:
        """Compute the normals of targets ``idx`` not yet computed (into ``self.normals``);
        returns how many were new."""
        need = idx[~self.done[idx]]
        if need.size:
            need = np.unique(need)
            for s in range(0, need.size, self.CHUNK):
                part = need[s : s + self.CHUNK]
                if self.device is not None:
                    # neighbourhoods and the closed form on the device; its hard cases here
                    n, hard = self.device.normals(part, self.k)
                    if hard.any():
                        n[hard] = _pca_normals_reference(self._neighbourhoods(part[hard]))
                    self.normals[part] = n
                else:
                    self.normals[part] = _pca_normals(self._neighbourhoods(part))
            self.done[need] = True
        return int(need.size)

    def _neighbourhoods(self, part: np.ndarray) -> np.ndarray:
        q = self.points[part] if self.offset is None else self.points[part] - self.offset
        _, nb = self.tree.query(q, k=self.k, workers=-1)
        return self.points[np.asarray(nb).reshape(len(part), self.k)]


def estimate_normals(points: np.ndarray, *, neighbours_k: int = 12, tree=None) -> np.ndarray:
    """Surface normals from k-neighbourhoods (PCA, smallest-eigenvalue eigenvector).

    Parameters
    ----------
    points : (N, 3) float64
        Metres.
    neighbours_k : int
        Neighbourhood size, including the point itself (>= 3).
    tree : scipy.spatial.cKDTree, optional
        A tree built on ``points`` (built here when omitted).

    Returns
    -------
    (N, 3) float64
        Unit normals with z >= 0; NaN where the neighbourhood is a line or a single point.
    """
    p = _points("points", points)
    k = _int_at_least("neighbours_k", neighbours_k, 3)
    offset = None
    if tree is None:
        from scipy.spatial import cKDTree

        offset = p.mean(axis=0)
        tree = cKDTree(p - offset)
    cache = _NormalCache(p, tree, k, offset)
    return cache(np.arange(len(p)))


# --------------------------------------------------------------------------- ICP engine

# match(q_centred (N, 3)) -> (ok (N,) bool, target_centred (K, 3), normals (K, 3),
#                             target ids (K,) int), K = ok.sum()
Matcher = Callable[[np.ndarray], Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def _solve_scaled(
    N: np.ndarray, b: np.ndarray, length_m: float
) -> Tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Solve ``N x = b`` with rotations scaled by ``length_m`` (the RMS radius of the points,
    so that all 6 unknowns are in metres of motion) and eigenvalue truncation. (Scaling by
    the diagonal of N instead would make a tiny, noise-only column look well determined.)

    Returns the step, the inverse of N (the pseudo-inverse when N is singular), the condition
    number and the (6, m) unit directions of parameter space that N leaves undetermined.
    """
    dg = np.array([length_m] * 3 + [1.0] * 3) * math.sqrt(max(float(np.trace(N)), 1e-300))
    Ns = N / np.outer(dg, dg)
    lam, V = np.linalg.eigh(Ns)
    top = max(float(lam[-1]), 1e-300)
    good = lam > EIG_RTOL * top
    inv_l = np.where(good, 1.0 / np.where(good, lam, 1.0), 0.0)
    x = (V @ (inv_l * (V.T @ (b / dg)))) / dg
    cond = top / float(lam[0]) if lam[0] > 0 else math.inf
    Ninv = (V * inv_l) @ V.T / np.outer(dg, dg)
    null = V[:, ~good] / dg[:, None]
    null = null / np.linalg.norm(null, axis=0, keepdims=True) if null.size else null
    return x, Ninv, cond, null


def _icp_engine(
    src: np.ndarray,
    match: Matcher,
    opts: _Options,
    centre: np.ndarray,
    progress: Optional[ProgressCallback] = None,
    t_init: Optional[np.ndarray] = None,
) -> Optional[ICPFit]:
    """Point-to-plane ICP of centred source points; ``None`` when too few correspondences.

    ``t_init`` (3,) is the starting translation of the transform (epoch 2 -> epoch 1), i.e.
    minus the expected ground motion.
    """
    R = np.eye(3)
    t = np.zeros(3) if t_init is None else np.asarray(t_init, dtype=np.float64).copy()
    converged = False
    it = 0
    damping = _Damping()
    for it in range(1, opts.max_iterations + 1):
        report(progress, (it - 1) / opts.max_iterations, f"ICP iteration {it}")
        q = src @ R.T + t
        ok, m, n, _ = match(q)
        q = q[ok]
        good = np.all(np.isfinite(n), axis=1)
        q, m, n = q[good], m[good], n[good]
        if len(q) < 7:
            return None
        v = np.einsum("ij,ij->i", n, q - m)  # signed point-to-plane distance
        keep, w, _ = _weights(v, opts)
        A = np.concatenate([np.cross(q, n), n], axis=1)  # d v / d (omega, dt), left perturbation
        Aw = A[keep] * w[keep, None]
        N = Aw.T @ A[keep]
        b = -(Aw.T @ v[keep])
        radius = _rms_radius(q)
        x, Ninv, _, null = _solve_scaled(N, b, radius)
        x = damping(x, radius)
        dR = rotation_matrix(x[:3])
        R = dR @ R
        t = dR @ t + x[3:]
        if np.linalg.norm(x[:3]) < opts.tolerance_rad and np.linalg.norm(x[3:]) < opts.tolerance_m:
            converged = True
            break
        if opts.tolerance_sigma > 0 and it > 2:
            # statistically negligible step: below tolerance_sigma standard deviations
            used = np.count_nonzero(w[keep] > 0)
            s0sq = float(w[keep] @ v[keep] ** 2) / max(used - 6, 1)
            sig = np.sqrt(s0sq * np.diag(Ninv))
            if null.size == 0 and np.all(np.abs(x) <= opts.tolerance_sigma * sig):
                converged = True
                break
    return _final_fit(src, match, opts, centre, R, t, it, converged)


class _Damping:
    """Step damping against the limit cycles of ICP.

    Two independently sampled clouds have no exact correspondences: near the optimum, a step
    can change enough nearest-neighbour pairs that the next step points straight back, and
    plain ICP then alternates between two transforms forever (or wanders). When a step
    reverses the previous one (cosine < -0.5, rotations scaled to metres by the points' RMS
    radius) the steps, this one and all later ones, are halved: the optimum sits on a pairing
    switch between the two transforms, the halved steps bracket it and shrink geometrically,
    and the convergence tests are met. The factor is never restored: a restored full step
    jumps over the switch again and the cycle resumes (measured on lone-star: 98 % of cells
    converge with restoring, 100 % without, at equal error).
    """

    def __init__(self):
        self.factor = 1.0
        self.previous: Optional[np.ndarray] = None

    def __call__(self, x: np.ndarray, length_m: float) -> np.ndarray:
        scaled = np.concatenate([x[:3] * length_m, x[3:]])
        prev = self.previous
        if prev is not None:
            denom = float(np.linalg.norm(scaled) * np.linalg.norm(prev))
            cosine = float(scaled @ prev) / denom if denom > 0 else 0.0
            if cosine < -0.5:
                self.factor *= 0.5
        self.previous = scaled * self.factor
        return x * self.factor


def _rms_radius(q: np.ndarray) -> float:
    return max(math.sqrt(float(np.mean(np.sum(q * q, axis=1)))), 1e-9)


def _final_fit(src, match, opts, centre, R, t, iterations, converged) -> Optional[ICPFit]:
    """Correspondences, residuals and covariance at the final transform."""
    a = src @ R.T
    ok, m, n, tid = match(a + t)
    a = a[ok]
    good = np.all(np.isfinite(n), axis=1)
    a, m, n, tid = a[good], m[good], n[good], tid[good]
    if len(a) < 7:
        return None
    rv = rotation_vector(R)
    v = np.einsum("ij,ij->i", n, a + t - m)
    keep, w, dpsi = _weights(v, opts)
    # exact Jacobian w.r.t. params (r, t):  d v / d r = (R s x n)' J_l(r),  d v / d t = n'
    A = np.concatenate([np.cross(a, n) @ _left_jacobian(rv), n], axis=1)[keep]
    vk, wk, dk = v[keep], w[keep], dpsi[keep]
    nk = int(keep.sum())
    used = int(np.count_nonzero(wk > 0))
    if used < 7:
        return None
    psi = wk * vk
    dof = max(nk - 6, 1)
    mean_dpsi = float(dk.sum()) / nk
    if mean_dpsi <= 0:
        return None
    # several source points paired with the same target point share its noise: inflate by
    # the ratio of cluster-summed to plain squared residuals (1 for independent residuals)
    ss = float(psi @ psi)
    _, inv = np.unique(tid[keep], return_inverse=True)
    cluster = np.bincount(inv.reshape(-1), weights=psi)
    inflation = max(1.0, float(cluster @ cluster) / ss) if ss > 0 else 1.0
    s0sq = ss / dof / (mean_dpsi * mean_dpsi) * inflation
    _, Ninv, cond, null = _solve_scaled(A.T @ A, np.zeros(6), _rms_radius(a))
    cov = _undetermined(s0sq * Ninv, np.eye(6), null)
    rmse = float(np.sqrt(np.sum(vk[wk > 0] ** 2) / used))
    params = np.concatenate([rv, t])
    return ICPFit(
        rotation=R,
        translation=centre + t - R @ centre,
        params=params,
        covariance=cov,
        centre=np.array(centre, dtype=np.float64),
        rmse_m=rmse,
        sigma0_m=math.sqrt(s0sq),
        n_correspondences=used,
        iterations=int(iterations),
        converged=bool(converged),
        condition=float(cond),
        null_space=null,
    )


def _undetermined(cov: np.ndarray, jac: np.ndarray, null: np.ndarray) -> np.ndarray:
    """Mark outputs that depend on undetermined parameter directions: variance inf, their
    covariances NaN. ``cov`` (..., q, q) of ``jac @ params`` with ``jac`` (..., q, 6)."""
    if null.size == 0:
        return cov
    ju = jac @ null  # (..., q, m)
    scale = np.linalg.norm(jac, axis=-1, keepdims=True)  # (..., q, 1)
    bad = np.any(np.abs(ju) > NULL_RTOL * np.maximum(scale, 1e-300), axis=-1)  # (..., q)
    out = cov.copy()
    pair = bad[..., :, None] | bad[..., None, :]
    out[pair] = np.nan
    i = np.arange(out.shape[-1])
    out[..., i, i] = np.where(bad, np.inf, out[..., i, i])
    return out


def icp_point_to_plane(
    source: np.ndarray,
    target: np.ndarray,
    *,
    target_normals: Optional[np.ndarray] = None,
    target_tree=None,
    centre: Optional[np.ndarray] = None,
    max_iterations: int = 50,
    tolerance_m: float = 1e-5,
    tolerance_rad: float = 1e-7,
    max_correspondence_m: Optional[float] = None,
    trim_fraction: float = 0.0,
    robust: Optional[str] = "tukey",
    neighbours_k: int = 12,
    tolerance_sigma: float = 0.05,
    progress: Optional[ProgressCallback] = None,
) -> ICPFit:
    """Rigid transform registering ``source`` (epoch 2) onto the ``target`` (epoch 1) surface.

    Point-to-plane ICP (Chen & Medioni 1992): each source point is paired with its nearest
    target point, and the sum of squared (robustly weighted) distances from the transformed
    source points to the target tangent planes is minimised with the small-angle linearisation
    (Low 2004) in 6 unknowns (3 rotations, 3 translations). After each step the exact rotation
    (Rodrigues) is applied; iterations stop when a step is below both tolerances. All
    arithmetic is done on coordinates centred on ``centre``.

    Parameters
    ----------
    source : (N, 3) float64
        Points to move (epoch 2), metres.
    target : (M, 3) float64
        Reference surface (epoch 1), metres.
    target_normals : (M, 3) float64, optional
        Unit normals of ``target`` (sign irrelevant); estimated from ``neighbours_k``
        neighbourhoods (PCA) of the target points that are used when omitted.
    target_tree : scipy.spatial.cKDTree, optional
        A tree built on ``target`` (in the same coordinates); built here when omitted.
    centre : (3,) float64, optional
        Reference point of the parameters, metres; the source centroid by default.
    max_iterations : int
        Iteration limit (>= 1).
    tolerance_m, tolerance_rad : float
        Convergence: the last translation step (metres) and rotation step (radians) are both
        below these.
    tolerance_sigma : float
        Also converged when every component of the step is below this many standard
        deviations of that parameter (after 3 iterations): nearest-neighbour pairs of
        independently sampled clouds keep switching, so steps can stall at a small fraction
        of the uncertainty without reaching ``tolerance_m``. 0 disables this test.
    max_correspondence_m : float, optional
        Pairs further apart than this (point to point, metres) are ignored; no limit by default.
    trim_fraction : float
        Fraction in [0, 0.5) of pairs with the largest |residual| dropped at every iteration.
    robust : {"tukey", "huber", None}
        Robust (IRLS) weights with the scale from the median absolute residual; ``None`` for
        plain least squares.
    neighbours_k : int
        Neighbourhood size for target normals (>= 3).
    progress : callable, optional
        ``progress(fraction, message)`` once per iteration; may raise CancelledError.

    Returns
    -------
    ICPFit
        The transform mapping source onto target; see :meth:`ICPFit.displacement_at` for the
        ground motion ``p - T(p)``.

    Raises
    ------
    InputDataError
        Empty or non-finite inputs, or too few correspondences.
    InvalidParameterError
        An option out of range.
    """
    src = _points("source", source)
    tgt = _points("target", target)
    opts = _options(
        max_iterations,
        tolerance_m,
        tolerance_rad,
        max_correspondence_m,
        trim_fraction,
        robust,
        neighbours_k,
        tolerance_sigma,
    )
    if target_normals is not None:
        tn = np.asarray(target_normals, dtype=np.float64)
        if tn.shape != tgt.shape:
            raise InputDataError(
                f"target_normals must have the shape of target {tgt.shape}, got {tn.shape}"
            )
    c = src.mean(axis=0) if centre is None else np.asarray(centre, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(c)):
        raise InvalidParameterError(f"centre must be 3 finite numbers, got {centre!r}")
    tgt_c = tgt - c
    if target_tree is None:
        from scipy.spatial import cKDTree

        tree, off = cKDTree(tgt_c), np.zeros(3)
        norm_src = _NormalCache(tgt_c, tree, opts.neighbours_k)
    else:
        tree, off = target_tree, c
        norm_src = _NormalCache(tgt, tree, opts.neighbours_k)
    normals = (lambda j: tn[j]) if target_normals is not None else norm_src
    gate = math.inf if opts.max_correspondence_m is None else opts.max_correspondence_m
    M = len(tgt)

    def match(q):
        _, j = tree.query(q + off, distance_upper_bound=gate, workers=-1)
        ok = j < M
        j = j[ok]
        return ok, tgt_c[j], normals(j), j

    fit = _icp_engine(src - c, match, opts, c, progress)
    report(progress, 1.0, "ICP done")
    if fit is None:
        raise InputDataError(
            "too few source points have a target point within max_correspondence_m and a "
            "well-defined normal; check that the clouds overlap or raise max_correspondence_m"
        )
    return fit


def _icp_reference(
    source: np.ndarray,
    target: np.ndarray,
    target_normals: np.ndarray,
    *,
    max_iterations: int = 50,
    tolerance_m: float = 1e-5,
    tolerance_rad: float = 1e-7,
) -> Tuple[np.ndarray, np.ndarray]:
    """Slow obvious point-to-plane ICP (plain least squares, brute-force nearest neighbours,
    one explicit row per correspondence), for testing. Returns ``(R, translation)`` with
    ``T(p) = R p + translation`` in the input coordinates."""
    c = source.mean(axis=0)
    s = source - c
    m = target - c
    R = np.eye(3)
    t = np.zeros(3)
    damping = _Damping()
    for _ in range(max_iterations):
        N = np.zeros((6, 6))
        b = np.zeros(6)
        for p in s:
            q = R @ p + t
            j = int(np.argmin(np.sum((m - q) ** 2, axis=1)))
            n = target_normals[j]
            row = np.concatenate([np.cross(q, n), n])
            r = float(n @ (q - m[j]))
            N += np.outer(row, row)
            b -= row * r
        x = damping(np.linalg.solve(N, b), _rms_radius(s @ R.T + t))
        dR = rotation_matrix(x[:3])
        R = dR @ R
        t = dR @ t + x[3:]
        if np.linalg.norm(x[:3]) < tolerance_rad and np.linalg.norm(x[3:]) < tolerance_m:
            break
    return R, c + t - R @ c


# --------------------------------------------------------------------------- polygons


def points_in_polygons(xy: np.ndarray, polygons: Sequence[np.ndarray]) -> np.ndarray:
    """Even-odd point-in-polygon test against any of several polygons (vectorised).

    Parameters
    ----------
    xy : (N, 2) or (N, 3) float64
        Points (only x, y used), metres.
    polygons : sequence of (K, 2) float64
        Vertex rings in map coordinates (closing vertex optional).

    Returns
    -------
    (N,) bool
        True where a point lies inside at least one polygon.
    """
    p = np.asarray(xy, dtype=np.float64)
    inside_any = np.zeros(len(p), dtype=bool)
    for k, poly in enumerate(polygons):
        v = np.asarray(poly, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] < 2 or len(v) < 3 or not np.all(np.isfinite(v[:, :2])):
            raise InvalidParameterError(
                f"polygon {k} must be a (K, 2) array of >= 3 finite vertices, got shape {v.shape}"
            )
        v = v[:, :2]
        lo, hi = v.min(axis=0), v.max(axis=0)
        sel = np.flatnonzero(np.all((p[:, :2] >= lo) & (p[:, :2] <= hi), axis=1))
        if sel.size == 0:
            continue
        x, y = p[sel, 0] - lo[0], p[sel, 1] - lo[1]  # local coordinates: no UTM cancellation
        vx, vy = v[:, 0] - lo[0], v[:, 1] - lo[1]
        inside = np.zeros(sel.size, dtype=bool)
        for i in range(len(v)):
            x1, y1, x2, y2 = vx[i - 1], vy[i - 1], vx[i], vy[i]
            if y1 == y2:
                continue
            crosses = (y1 > y) != (y2 > y)
            xi = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
            inside ^= crosses & (x < xi)
        inside_any[sel] |= inside
    return inside_any


# --------------------------------------------------------------------------- pre-alignment


def _stable_mask(points, exclude_polygons, include_polygons) -> np.ndarray:
    mask = np.ones(len(points), dtype=bool)
    if include_polygons is not None:
        mask &= points_in_polygons(points, include_polygons)
    if exclude_polygons is not None:
        mask &= ~points_in_polygons(points, exclude_polygons)
    return mask


def _prealign(
    before,
    after,
    tree,
    normals,
    opts,
    exclude_polygons,
    include_polygons,
    max_points,
    seed,
    progress=None,
) -> ICPFit:
    sb = _stable_mask(before, exclude_polygons, include_polygons)
    sa = np.flatnonzero(_stable_mask(after, exclude_polygons, include_polygons))
    if sa.size < 7 or np.count_nonzero(sb) < 7:
        raise InputDataError(
            f"the stable area holds {sa.size} after- and {np.count_nonzero(sb)} before-points; "
            "check exclude_polygons / include_polygons (map coordinates of the epochs)"
        )
    if sa.size > max_points:
        sa = np.sort(np.random.default_rng(seed).choice(sa, size=max_points, replace=False))
    src = after[sa]
    c = src.mean(axis=0)
    gate = math.inf if opts.max_correspondence_m is None else opts.max_correspondence_m
    M = len(before)

    def match(q):
        _, j = tree.query(q + c, distance_upper_bound=gate, workers=-1)
        ok = j < M
        ok[ok] = sb[j[ok]]  # targets in the moving area are not used
        j = j[ok]
        return ok, before[j] - c, normals(j), j

    fit = _icp_engine(src - c, match, opts, c, progress)
    if fit is None:
        raise InputDataError(
            "pre-alignment found too few correspondences on stable ground; check the polygons "
            "and that the epochs overlap"
        )
    return fit


def prealign(
    before: np.ndarray,
    after: np.ndarray,
    *,
    exclude_polygons: Optional[Sequence[np.ndarray]] = None,
    include_polygons: Optional[Sequence[np.ndarray]] = None,
    max_points: int = PREALIGN_MAX_POINTS,
    seed: int = 0,
    progress: Optional[ProgressCallback] = None,
    **icp_options,
) -> ICPFit:
    """Global point-to-plane ICP of ``after`` onto ``before`` on stable ground.

    Points inside any ``exclude_polygons`` (the moving area) are left out of both epochs; when
    ``include_polygons`` is given only points inside one of them are used.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        Epochs 1 and 2, metres.
    exclude_polygons, include_polygons : sequence of (K, 2) float64, optional
        Polygons in map coordinates (closing vertex optional), even-odd rule.
    max_points : int
        At most this many stable after-points (a seeded random sample) are registered.
    seed : int
        Seed of that sample.
    progress : callable, optional
        ``progress(fraction, message)``; may raise CancelledError.
    **icp_options
        ``max_iterations, tolerance_m, tolerance_rad, max_correspondence_m, trim_fraction,
        robust, neighbours_k`` as in :func:`icp_point_to_plane`.

    Returns
    -------
    ICPFit
        Transform mapping ``after`` onto ``before``; apply it to ``after`` to align the epochs.
    """
    from scipy.spatial import cKDTree

    b = _points("before", before)
    a = _points("after", after)
    _check_overlap(b, a)
    opts = _options(**icp_options)
    mp = _int_at_least("max_points", max_points, 7)
    off = b.mean(axis=0)
    tree = cKDTree(b - off)
    normals = _NormalCache(b, tree, opts.neighbours_k, offset=off)
    shifted = _OffsetTree(tree, off)
    fit = _prealign(
        b, a, shifted, normals, opts, exclude_polygons, include_polygons, mp, seed, progress
    )
    report(progress, 1.0, "pre-alignment done")
    return fit


class _OffsetTree:
    """A cKDTree built on ``points - offset`` queried with raw coordinates."""

    def __init__(self, tree, offset):
        self.tree, self.offset = tree, offset

    def query(self, q, **kw):
        return self.tree.query(q - self.offset, **kw)


def _check_overlap(before: np.ndarray, after: np.ndarray) -> None:
    lo = np.maximum(before[:, :2].min(axis=0), after[:, :2].min(axis=0))
    hi = np.minimum(before[:, :2].max(axis=0), after[:, :2].max(axis=0))
    if np.any(lo > hi):
        raise InputDataError(
            "the two epochs do not overlap in plan (x, y); check that both use the same CRS"
        )


# --------------------------------------------------------------------------- windowed ICP


_CELL_FIELDS = (
    "x",
    "y",
    "z",
    "dx",
    "dy",
    "dz",
    "sigma_dx",
    "sigma_dy",
    "sigma_dz",
    "rx",
    "ry",
    "rz",
    "sigma_rx",
    "sigma_ry",
    "sigma_rz",
    "rmse",
    "sigma0",
)


@dataclass(frozen=True)
class WindowedICPResult:
    """Per-cell displacements from :func:`windowed_icp` (one entry per fitted cell).

    Cell ``(row, col)`` covers ``x in [x0 + col*s, x0 + (col+1)*s)`` and
    ``y in (y0 - (row+1)*s, y0 - row*s]`` with ``(x0, y0) = origin_xy`` the grid's upper-left
    (north-west) corner and ``s = cell_m``; row 0 is the northernmost row.

    Attributes
    ----------
    x, y : (K,) float64
        Cell centre, metres (in the pre-aligned epoch-2 frame when pre-aligned).
    z : (K,) float64
        Mean height of the cell's after-points, metres.
    dx, dy, dz : (K,) float64
        Ground motion before -> after at ``(x, y, z)``, metres: ``p - T(p)``.
    sigma_dx, sigma_dy, sigma_dz : (K,) float64
        Their 1-sigma, metres (inf where the cell geometry leaves the motion undetermined);
        the formal ones times ``sigma_factor``.
    cov_d : (K, 3, 3) float64
        Full covariance of ``(dx, dy, dz)``, m^2 (formal times ``sigma_factor²``).
    rx, ry, rz, sigma_rx, sigma_ry, sigma_rz : (K,) float64
        Rotation vector of the ground motion (= minus that of ``T``) and 1-sigma, radians.
    rmse : (K,) float64
        RMS point-to-plane residual, metres.
    sigma0 : (K,) float64
        A-posteriori sigma of unit weight, metres.
    n : (K,) int64
        Correspondences used.
    n_after, n_before : (K,) int64
        After-points in the cell, before-points in the cell (unbuffered).
    iterations : (K,) int64
    converged : (K,) bool
    row, col : (K,) int64
        Grid indices.
    origin_xy : (float, float)
        Upper-left corner of the grid, metres.
    cell_m : float
    n_rows, n_cols : int
    skipped : dict
        Counts of cells with after-points that were not fitted, by reason
        (``few_after_points``, ``few_before_points``, ``icp_failed``).
    prealignment : ICPFit or None
        The global stable-ground transform applied to epoch 2 first.
    seconds : float
        Wall time.
    sigma_factor : float
        The factor the formal sigmas were multiplied by (1 when not scaled; with
        ``sigma_scaling="region"`` the median of the cells' factors).
    sigma_factor_estimate : float
        The field's variance factor as estimated (NaN when not estimated or too few cells);
        ``sigma_factor = max(1, sigma_factor_estimate)`` when scaled.
    sigma_factor_cells : int
        Cells that entered the estimate.
    exx, eyy, exy : (K,) float64
        Horizontal strain at the cell centre (dimensionless): ``d(dx)/dx``, ``d(dy)/dy`` and
        ``(d(dx)/dy + d(dy)/dx) / 2`` of the cell's motion model (0 for a rigid cell without
        deformation passes, whose model has no strain).
    flagged : (K,) bool
        The cell failed the normalised median test against its neighbours (a likely wrong
        minimum) even after a restart from their median motion; see ``median_threshold``.
    cell_model : str
        ``"rigid"`` or ``"affine"``.
    deform_passes : int
        Window-deformation passes run after the first.
    field_model : str
        ``"cells"`` (each cell's own transform) or ``"spline"`` (the values, covariances and
        gradients at the centres come from one B-spline field fitted to all points).
    sigma_factor_cell : (K,) float64 or None
        With ``sigma_scaling="region"``: the factor each cell's sigmas were multiplied by.
    sigma_region_factors : tuple of float
        With ``sigma_scaling="region"``: the factor of each region (lowest class first).
    sigma_region : (K,) int64 or None
        With ``sigma_scaling="region"``: each cell's region (-1: none, the field's factor).
    breaklines : Breaklines or None
        The lines the spline field was allowed to jump across (given or detected).
    breaklines_source : str
        ``"given"``, ``"detected"`` or ``"none"``.
    sigma_model : str
        ``"blocks"`` (the covariances count the residuals' spatial correlation, block sums
        of the scores: :mod:`slipmap.core.icp_blocks`) or ``"independent"`` (formal).
    sigma_block_m : float
        The block side chosen from the data, metres (NaN: none, formal covariances).
    sigma_block_ratio : float
        The field's pooled ratio of block to formal variances at that size (the shrinkage
        target of cells with few blocks; NaN: none).
    sigma_n_cap : float
        With ``sigma_model="blocks"`` and neighbour scaling: the most independent
        observations a cell counts as (the cell-wide correlated error,
        :func:`~slipmap.core.icp_blocks.cell_floor`; inf: none needed, NaN: not estimated).
    sigma_floor_factor : float
        With it, the multiplier of every cell's block sigmas (``sqrt(a)``, >= 1).
    sigma_formal : (K, 3) float64 or None
        The formal 1-sigma of ``dx, dy, dz`` (independent residuals, no factor), metres.
    cov_d_formal : (K, 3, 3) float64 or None
        The formal covariance of ``dx, dy, dz`` (rigid and affine cells), m².
    cov_d_blocks : (K, L, 3, 3) float64 or None
        With ``sigma_model="blocks"`` (cells): the unshrunk block covariances per block size
        of :data:`~slipmap.core.icp_blocks.BLOCK_LADDER_M`, so that a tiled run chooses the
        block size over the whole field (:func:`reblock`).
    n_blocks : (K, L) int64 or None
        Their block counts.
    gradient : (K, 3, 3) float64 or None
        The gradient of each cell's motion ``d(p)`` as fitted (dimensionless; a rigid cell's
        ``I - R``): what the breaklines' detector reads, so that a tiled run detects them
        from its cells as the one-file run does.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    dz: np.ndarray
    sigma_dx: np.ndarray
    sigma_dy: np.ndarray
    sigma_dz: np.ndarray
    cov_d: np.ndarray
    rx: np.ndarray
    ry: np.ndarray
    rz: np.ndarray
    sigma_rx: np.ndarray
    sigma_ry: np.ndarray
    sigma_rz: np.ndarray
    rmse: np.ndarray
    sigma0: np.ndarray
    n: np.ndarray
    n_after: np.ndarray
    n_before: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    row: np.ndarray
    col: np.ndarray
    origin_xy: Tuple[float, float]
    cell_m: float
    n_rows: int
    n_cols: int
    skipped: Dict[str, int] = field(default_factory=dict)
    prealignment: Optional[ICPFit] = None
    seconds: float = 0.0
    sigma_factor: float = 1.0
    sigma_factor_estimate: float = math.nan
    sigma_factor_cells: int = 0
    exx: np.ndarray = field(default_factory=lambda: np.zeros(0))
    eyy: np.ndarray = field(default_factory=lambda: np.zeros(0))
    exy: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cell_model: str = "rigid"
    deform_passes: int = 0
    field_model: str = "cells"
    flagged: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    sigma_factor_cell: Optional[np.ndarray] = None
    sigma_region_factors: Tuple[float, ...] = ()
    sigma_region: Optional[np.ndarray] = None
    breaklines: object = None
    breaklines_source: str = "none"
    sigma_model: str = "independent"
    sigma_block_m: float = math.nan
    sigma_block_ratio: float = math.nan
    sigma_formal: Optional[np.ndarray] = None
    sigma_n_cap: float = math.nan
    sigma_floor_factor: float = math.nan
    cov_d_formal: Optional[np.ndarray] = None
    cov_d_blocks: Optional[np.ndarray] = None
    n_blocks: Optional[np.ndarray] = None
    gradient: Optional[np.ndarray] = None
    from_cell: Optional[np.ndarray] = None

    def __len__(self) -> int:
        return int(self.x.size)

    def to_columns(self) -> Dict[str, np.ndarray]:
        """Per-cell columns: ``x, y, z, dx, dy, dz, sigma_dx, sigma_dy, sigma_dz, rmse, n``
        (the CLI's CSV columns, in this order) then ``rx, ry, rz, sigma_rx, sigma_ry,
        sigma_rz, sigma0, n_after, n_before, iterations, converged (0/1), row, col, exx, eyy,
        exy, flagged (0/1), from_cell (0/1)``."""
        names = ["x", "y", "z", "dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_dz", "rmse"]
        cols: Dict[str, np.ndarray] = {k: getattr(self, k) for k in names}
        cols["n"] = self.n
        for k in ("rx", "ry", "rz", "sigma_rx", "sigma_ry", "sigma_rz", "sigma0"):
            cols[k] = getattr(self, k)
        for k in ("n_after", "n_before", "iterations"):
            cols[k] = getattr(self, k)
        cols["converged"] = self.converged.astype(np.int64)
        cols["row"], cols["col"] = self.row, self.col
        for k in ("exx", "eyy", "exy"):
            v = getattr(self, k)
            cols[k] = v if v.size == self.x.size else np.zeros(self.x.size)
        fl = self.flagged if self.flagged.size == self.x.size else np.zeros(self.x.size, bool)
        cols["flagged"] = fl.astype(np.int64)
        fc = self.from_cell
        fc = fc if fc is not None and fc.size == self.x.size else np.zeros(self.x.size, bool)
        cols["from_cell"] = fc.astype(np.int64)
        return cols

    def to_grid(self, name: str) -> np.ndarray:
        """(n_rows, n_cols) float64 raster of a per-cell column, NaN where no cell was fitted.

        Pixel ``(row, col)`` is the cell of that index; the raster's upper-left corner is
        ``origin_xy`` and its pixel size ``cell_m``.
        """
        cols = self.to_columns()
        if name not in cols:
            raise InvalidParameterError(f"name must be one of {sorted(cols)}, got {name!r}")
        g = np.full((self.n_rows, self.n_cols), np.nan)
        g[self.row, self.col] = cols[name]
        return g


def _grid_origin(after: np.ndarray, cell: float, origin_xy) -> Tuple[float, float, int, int]:
    xmin, ymin = after[:, :2].min(axis=0)
    xmax, ymax = after[:, :2].max(axis=0)
    if origin_xy is None:
        ox, oy = 0.0, 0.0
    else:
        ox, oy = (float(v) for v in origin_xy)
        if not (math.isfinite(ox) and math.isfinite(oy)):
            raise InvalidParameterError(f"origin_xy must be two finite numbers, got {origin_xy!r}")
    x0 = ox + math.floor((xmin - ox) / cell) * cell
    y0 = oy + math.ceil((ymax - oy) / cell) * cell
    n_cols = int(math.floor((xmax - x0) / cell)) + 1
    n_rows = int(math.floor((y0 - ymin) / cell)) + 1
    return x0, y0, n_rows, n_cols


def _cell_index(xy: np.ndarray, x0, y0, cell) -> Tuple[np.ndarray, np.ndarray]:
    col = np.floor((xy[:, 0] - x0) / cell).astype(np.int64)
    row = np.floor((y0 - xy[:, 1]) / cell).astype(np.int64)
    return row, col


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on uint64 arrays (wrapping arithmetic)."""
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


#: the lattice (metres) the sample's hash rounds coordinates to: far finer than any survey's
#: resolution, far coarser than the float rounding between two decodings of one stored point
SAMPLE_QUANTUM_M = 1e-5


def sample_priority(xyz: np.ndarray, seed: int = 0) -> np.ndarray:
    """A pseudo-random priority of each point that depends only on its coordinates and
    ``seed``: a hash (SplitMix64) of x, y, z rounded to :data:`SAMPLE_QUANTUM_M`.

    A cell's ``max_points_per_cell`` sample is its points of lowest priority, so it is the
    same set of points whatever order or tiling they arrive in (a generator's draw would
    depend on both); written here because numpy's generators draw by position, not by
    value. The coordinates are rounded before hashing because one stored LAS point decodes
    to floats that differ in the last bits (about 1e-15 m) between a file and its tiles,
    whose offsets differ; points stored at a multiple of 10 µm (LAS scales of 0.01 mm and
    coarser) lie far from the rounding's midpoints, so both decodings hash alike.

    Parameters
    ----------
    xyz : (N, 3) float64
        Points, metres.
    seed : int
        Seed (>= 0).

    Returns
    -------
    (N,) uint64
    """
    q = np.round(np.asarray(xyz, dtype=np.float64).reshape(-1, 3) / SAMPLE_QUANTUM_M)
    bits = np.ascontiguousarray(q.astype(np.int64)).view(np.uint64)
    h = np.full(len(bits), np.uint64((int(seed) * 0x9E3779B97F4A7C15) % 2**64))
    for j in range(3):
        h = _splitmix64(h ^ bits[:, j])
    return h


def _interpolator(res: WindowedICPResult) -> Callable[[np.ndarray], np.ndarray]:
    """Ground motion of a windowed-ICP result at any xy: bilinear between cell centres, the
    nearest fitted cell where a neighbour is missing, zero when no cell was fitted.

    The grid gets a border of empty cells, so that a point beyond the outermost centres takes
    the nearest fitted cell whether the grid ends there or holds unfitted cells: the start of
    a fine cell then does not depend on how far the data (a tiled run's block) reaches.
    """
    from .fields import GriddedField, sample_field

    if len(res) == 0:
        return lambda xy: np.zeros((len(xy), 3))
    x0, y0 = res.origin_xy
    s = res.cell_m
    field = GriddedField(
        origin_xy=(x0 - s, y0 + s),
        spacing_m=(s, s),
        **{k: np.pad(res.to_grid(k), 1, constant_values=np.nan) for k in ("dx", "dy", "dz")},
    )

    def f(xy: np.ndarray) -> np.ndarray:
        out = sample_field(field, xy)
        bad = ~np.all(np.isfinite(out), axis=1)
        if bad.any():
            out[bad] = sample_field(field, xy[bad], method="nearest_valid")
        return out

    return f


CELL_MODELS = ("rigid", "affine")
FIELD_MODELS = ("cells", "spline")
ENGINES = ("batched", "per_cell")
BACKENDS = ("numpy", "numba", "opencl", "auto")


@dataclass(frozen=True)
class _Cells:
    """The cells of a windowed-ICP run: their after-points concatenated cell by cell."""

    points: np.ndarray  # (P,) indices into the after points, grouped by cell
    seg: np.ndarray  # (P,) cell of each point, 0 .. K-1
    centres: np.ndarray  # (K, 3) cell centre x, y and mean z of its points
    boxes: np.ndarray  # (K, 4) xmin, xmax, ymin, ymax of the target points (unmoved)
    row: np.ndarray
    col: np.ndarray
    n_after: np.ndarray
    n_before: np.ndarray

    @classmethod
    def build(cls, a, idx_parts, keys, n_after, n_before, x0, y0, cell, buf, n_cols):
        k = len(idx_parts)
        pts = np.concatenate(idx_parts) if k else np.zeros(0, dtype=np.int64)
        sizes = np.array([len(i) for i in idx_parts], dtype=np.int64)
        seg = np.repeat(np.arange(k), sizes)
        row, col = np.divmod(np.asarray(keys, dtype=np.int64), n_cols)
        zc = np.bincount(seg, weights=a[pts, 2], minlength=k) / np.maximum(sizes, 1)
        # the mean z per cell as np.mean does it (pairwise sums), so that the batched and
        # per-cell runs share their centres exactly
        zc = np.array([float(a[i, 2].mean()) for i in idx_parts]) if k else zc
        cx, cy = x0 + (col + 0.5) * cell, y0 - (row + 0.5) * cell
        boxes = np.column_stack(
            [x0 + col * cell - buf, x0 + (col + 1) * cell + buf,
             y0 - (row + 1) * cell - buf, y0 - row * cell + buf]
        )  # fmt: skip
        return cls(
            points=pts,
            seg=seg,
            centres=np.column_stack([cx, cy, zc]).reshape(k, 3),
            boxes=boxes.reshape(k, 4),
            row=row,
            col=col,
            n_after=np.asarray(n_after, dtype=np.int64),
            n_before=np.asarray(n_before, dtype=np.int64),
        )


def _cells_subset(cells: _Cells, idx: np.ndarray) -> _Cells:
    """The cells ``idx`` (K',) of ``cells``, their points regrouped."""
    mask = np.zeros(len(cells.centres), dtype=bool)
    mask[idx] = True
    pm = mask[cells.seg]
    remap = np.full(len(cells.centres), -1, dtype=np.int64)
    remap[idx] = np.arange(len(idx))
    return replace(
        cells,
        points=cells.points[pm],
        seg=remap[cells.seg[pm]],
        centres=cells.centres[idx],
        boxes=cells.boxes[idx],
        row=cells.row[idx],
        col=cells.col[idx],
        n_after=cells.n_after[idx],
        n_before=cells.n_before[idx],
    )


def _merge_fits(fits: _PassFits, sub: _PassFits, idx: np.ndarray, take: np.ndarray):
    """``fits`` with the cells ``idx[take]`` replaced by ``sub``'s ``take`` entries."""
    out = {}
    for k in fits.__dataclass_fields__:
        a = getattr(fits, k).copy()
        a[idx[take]] = getattr(sub, k)[take]
        out[k] = a
    return _PassFits(**out)


@dataclass(frozen=True)
class _PassFits:
    """One pass over the cells: the fits and what the field needs of them."""

    ok: np.ndarray
    d: np.ndarray  # (K, 3) ground motion at the (moved) centre: -t (+ start for pass 1)
    d_residual: np.ndarray  # (K, 3) -t
    cov_d: np.ndarray
    gradient: np.ndarray  # (K, 3, 3) gradient of the pass's motion model
    rotation: np.ndarray
    sigma_rotation: np.ndarray
    rmse: np.ndarray
    sigma0: np.ndarray
    n: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    cov_d_blocks: np.ndarray  # (K, L, 3, 3) block covariances of d (icp_blocks)
    n_blocks: np.ndarray  # (K, L)
    linear: np.ndarray  # (K, 3, 3) the fitted transform's linear part (icp_cells.CellFits)
    t: np.ndarray  # (K, 3) its translation about the (moved) centre


def _fit_pass(
    cells: _Cells,
    pts: np.ndarray,
    d_start: np.ndarray,
    moved_by: np.ndarray,
    model: str,
    *,
    before,
    tree,
    normals,
    gate,
    opts,
    engine,
    grid=None,
    residual: bool = False,
    progress: Optional[ProgressCallback] = None,
) -> _PassFits:
    """Fit every cell once. ``pts`` (P, 3) are the cells' after-points (pre-moved by the
    field in a deformation pass), ``moved_by`` (K, 3) how far each cell's centre was moved
    back, ``d_start`` (K, 3) the starting ground motion (the target box moves with it)."""
    from .icp_blocks import BLOCK_LADDER_M
    from .icp_cells import fit_cells, ground_rotation

    centres = cells.centres - moved_by
    shift = moved_by if residual else d_start
    boxes = cells.boxes - np.repeat(shift[:, :2], 2, axis=1)
    src = pts - centres[cells.seg]
    t_init = np.zeros_like(d_start) if residual else -d_start
    kw = dict(before=before, tree=tree, normals=normals, boxes=boxes, gate=gate, opts=opts)
    if engine == "batched":
        fits = fit_cells(
            src, cells.seg, centres, model=model, t_init=t_init, progress=progress, grid=grid,
            **kw,
        )  # fmt: skip
    else:
        fits = _fit_cells_per_cell(
            src, cells.seg, centres, model=model, t_init=t_init, progress=progress, **kw
        )
    cov = fits.covariance[:, -3:, -3:]
    k, n_lad = len(cov), len(BLOCK_LADDER_M)
    if fits.block_covariance is None:
        bcov, nblk = np.full((k, n_lad, 3, 3), np.nan), np.zeros((k, n_lad), dtype=np.int64)
    else:
        bcov, nblk = fits.block_covariance[:, :, -3:, -3:], fits.n_blocks
    rot, sig_rot = ground_rotation(fits, model)
    return _PassFits(
        ok=fits.ok,
        d=-fits.t,
        d_residual=-fits.t,
        cov_d=cov,
        gradient=fits.gradient,
        rotation=rot,
        sigma_rotation=sig_rot,
        rmse=fits.rmse,
        sigma0=fits.sigma0,
        n=fits.n,
        iterations=fits.iterations,
        converged=fits.converged,
        cov_d_blocks=bcov,
        n_blocks=nblk,
        linear=fits.linear,
        t=fits.t,
    )


def _zero_starts(cells: _Cells, pts, d0, fits: _PassFits, model: str, fit_kw) -> _PassFits:
    """The seeded pass ``fits`` with each cell whose start ``d0`` (K, 3) is away from zero
    also fitted from zero, and the better fit kept (:mod:`slipmap.core.icp_starts`: a coarse
    cell that straddles a discontinuity must not trap a fine cell in a wrong minimum).
    ``pts`` (P, 3) are the cells' after-points (unmoved)."""
    from .icp_starts import (
        START_EPS_M,
        choose_zero_start,
        point_residuals,
        transformed,
        truncated_costs,
    )

    idx = np.flatnonzero(np.linalg.norm(d0, axis=1) > START_EPS_M)
    if idx.size == 0:
        return fits
    sub = _cells_subset(cells, idx)
    zero = np.zeros((idx.size, 3))
    sub_pts = pts[np.isin(cells.seg, idx)]  # grouped as sub.points (_cells_subset)
    zfit = _fit_pass(sub, sub_pts, zero, zero, model, **fit_kw)
    src = sub_pts - sub.centres[sub.seg]
    res_kw = dict(
        tree=fit_kw["tree"], normals=fit_kw["normals"], gate=fit_kw["gate"],
        n_targets=len(fit_kw["before"]),
    )  # fmt: skip
    world_s = transformed(src, sub.seg, sub.centres, fits.linear[idx], fits.t[idx])
    world_z = transformed(src, sub.seg, sub.centres, zfit.linear, zfit.t)
    cost_s, cost_z, se = truncated_costs(
        point_residuals(world_s, **res_kw), point_residuals(world_z, **res_kw), sub.seg, idx.size
    )
    take = choose_zero_start(cost_s, cost_z, se, fits.ok[idx], zfit.ok)
    log.info(
        "seeded cells: %d of %d also fitted from zero, %d fit better from zero",
        idx.size,
        len(d0),
        int(take.sum()),
    )
    return _merge_fits(fits, zfit, idx, take) if take.any() else fits


def _target_grid(before: np.ndarray, backend: str):
    """The epoch-1 points for the batched matcher's compiled kernels, or None (numpy).

    ``"numba"``: :class:`~slipmap.core.icp_numba.NumbaTargets` (CPU); ``"opencl"``:
    :class:`~slipmap.core.opencl.nearest.GridTargets`; ``"auto"``: OpenCL when a device
    starts (asked in a child process first: some drivers abort instead of raising), else Numba
    when it imports, else numpy."""
    if backend == "numpy":
        return None
    if backend == "numba":
        from .icp_numba import NumbaTargets

        return NumbaTargets(before)
    if backend == "opencl":
        from .opencl.nearest import GridTargets

        return GridTargets(before)
    from .icp_numba import NumbaTargets, unavailable
    from .opencl.backend import probe_runtime

    reason = probe_runtime()
    if reason is None:
        try:
            from .opencl.nearest import GridTargets

            return GridTargets(before)
        except DependencyError as exc:
            reason = str(exc)
    why = unavailable()
    if why is None:
        log.info("OpenCL unavailable (%s); the ICP pairs come from Numba's CPU kernels", reason)
        return NumbaTargets(before)
    log.info("OpenCL unavailable (%s), %s; the ICP pairs come from numpy", reason, why)
    return None


def _near_pairs(row: np.ndarray, col: np.ndarray, *, reach: int) -> np.ndarray:
    """(Q, 2) index pairs ``i < j`` of the cells at most ``reach`` rows and columns apart."""
    from .fields import _neighbour_table

    if np.size(row) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    nb = _neighbour_table(np.asarray(row, np.int64), np.asarray(col, np.int64), reach)
    i, m = np.nonzero(nb > np.arange(len(nb))[:, None])
    return np.column_stack([i, nb[i, m]]).astype(np.int64)


def _fit_cells_per_cell(src, seg, centres, *, before, tree, normals, boxes, gate, opts, model,
                        t_init, progress=None):  # fmt: skip
    """Slow obvious reference of :func:`slipmap.core.icp_cells.fit_cells`: one cell at a time
    (rigid: :func:`_icp_engine` with its own matcher, the pre-issue-#18 loop; affine:
    ``fit_cells`` on one cell, so that the batching itself is what is compared)."""
    from .icp_blocks import BLOCK_LADDER_M, block_meats_reference, sandwich
    from .icp_cells import CellFits, fit_cells, n_params

    k = len(centres)
    p = n_params(model)
    n_lad = len(BLOCK_LADDER_M)
    out = {
        "ok": np.zeros(k, dtype=bool),
        "linear": np.repeat(np.eye(3)[None], k, axis=0),
        "t": np.zeros((k, 3)),
        "params": np.zeros((k, p)),
        "covariance": np.full((k, p, p), np.nan),
        "rmse": np.full(k, np.nan),
        "sigma0": np.full(k, np.nan),
        "n": np.zeros(k, dtype=np.int64),
        "iterations": np.zeros(k, dtype=np.int64),
        "converged": np.zeros(k, dtype=bool),
        "block_covariance": np.full((k, n_lad, p, p), np.nan),
        "n_blocks": np.zeros((k, n_lad), dtype=np.int64),
    }
    bounds = np.concatenate([[0], np.cumsum(np.bincount(seg, minlength=k))])
    M = len(before)
    for ci in range(k):
        report(progress, ci / max(k, 1), f"ICP cell {ci + 1} of {k}")
        s = src[bounds[ci] : bounds[ci + 1]]
        centre = centres[ci]
        if model == "affine":
            one = fit_cells(
                s,
                np.zeros(len(s), dtype=np.int64),
                centre[None],
                before=before,
                tree=tree,
                normals=normals,
                boxes=boxes[ci : ci + 1],
                gate=gate,
                opts=opts,
                model=model,
                t_init=t_init[ci : ci + 1],
            )
            for key in out:
                out[key][ci] = getattr(one, key)[0]
            continue
        bx0, bx1, by0, by1 = boxes[ci]

        def match(q, centre=centre, bx0=bx0, bx1=bx1, by0=by0, by1=by1):
            _, j = tree.query(q + centre, distance_upper_bound=gate, workers=-1)
            ok = j < M
            jj = j[ok]
            tp = before[jj]
            inbox = (tp[:, 0] >= bx0) & (tp[:, 0] <= bx1) & (tp[:, 1] >= by0) & (tp[:, 1] <= by1)
            ok[ok] = inbox
            jj = jj[inbox]
            return ok, tp[inbox] - centre, normals(jj), jj

        fit = _icp_engine(s, match, opts, centre, t_init=t_init[ci])
        if fit is None:
            continue
        out["ok"][ci] = True
        out["linear"][ci] = fit.rotation
        out["t"][ci] = fit.params[3:]
        out["params"][ci] = fit.params
        out["covariance"][ci] = fit.covariance
        out["rmse"][ci] = fit.rmse_m
        out["sigma0"][ci] = fit.sigma0_m
        out["n"][ci] = fit.n_correspondences
        out["iterations"][ci] = fit.iterations
        out["converged"][ci] = fit.converged
        # block covariances at the final transform, as _final_fit forms its residuals
        a = s @ fit.rotation.T
        t = fit.params[3:]
        okm, m, nrm, _ = match(a + t)
        good = np.all(np.isfinite(nrm), axis=1)
        a, m, nrm, xy = a[okm][good], m[good], nrm[good], (s[okm][good] + centre)[:, :2]
        v = np.einsum("ij,ij->i", nrm, a + t - m)
        keep, w, dpsi = _weights(v, opts)
        A = np.concatenate([np.cross(a, nrm) @ _left_jacobian(fit.params[:3]), nrm], axis=1)
        psi = np.where(keep, w * v, 0.0)
        _, Ninv, _, _ = _solve_scaled(A[keep].T @ A[keep], np.zeros(6), _rms_radius(a))
        nk = int(keep.sum())
        scale = nk / max(nk - 6, 1) / (float(dpsi[keep].sum()) / nk) ** 2
        meats, nb = block_meats_reference(A, psi, np.zeros(len(v), np.int64), xy, 1)
        out["block_covariance"][ci] = sandwich(Ninv[None], meats, nb, np.array([scale]))[0]
        out["n_blocks"][ci] = nb[0]
    return CellFits(**out)


def _block_covariances(fits: _PassFits, cov_d: np.ndarray, flagged: np.ndarray):
    """:func:`_choose_and_shrink` of a pass's cells (fitted, converged, not flagged)."""
    return _choose_and_shrink(
        cov_d, fits.cov_d_blocks, fits.n_blocks, fits.ok & fits.converged & ~flagged
    )


def _choose_and_shrink(cov_d, cov_blocks, n_blocks, usable):
    """The cells' covariances of ``d`` with the residuals' spatial correlation: the block
    size chosen over the ``usable`` cells, each cell's block covariance shrunk towards its
    formal one ``cov_d`` times the field's ratio (:mod:`slipmap.core.icp_blocks`).
    Returns the :class:`~slipmap.core.icp_blocks.BlockChoice` and the (K, 3, 3) covariances
    (the formal ones where no block size is eligible)."""
    from .icp_blocks import choose_block_level, shrink_covariance

    fvar = np.diagonal(cov_d, axis1=1, axis2=2)
    bvar = np.diagonal(cov_blocks, axis1=2, axis2=3)
    usable = usable & np.all(np.isfinite(fvar) & (fvar > 0), axis=1)
    choice = choose_block_level(fvar, bvar, n_blocks, usable)
    if choice.level < 0:
        return choice, cov_d
    lev = choice.level
    return choice, shrink_covariance(cov_d, cov_blocks[:, lev], n_blocks[:, lev], choice.kappa)


def _rotation_scale(cov_d: np.ndarray, sigma_formal: np.ndarray) -> np.ndarray:
    """(K,) multiplier of the rotations' formal sigmas: the root mean ratio of the
    translation's variances to the formal ones (1 where undefined)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.sqrt(np.nanmean(np.diagonal(cov_d, axis1=1, axis2=2) / sigma_formal**2, axis=1))
    return np.where(np.isfinite(r), r, 1.0)


def reblock(res: WindowedICPResult) -> WindowedICPResult:
    """``res`` (rigid or affine cells with ``sigma_model="blocks"``, e.g. assembled from
    tiles that each chose their own block size) with the block size chosen and the cells
    shrunk over the whole field, as one run over all cells does; unchanged otherwise."""
    if res.sigma_model != "blocks" or res.cov_d_blocks is None or res.field_model != "cells":
        return res
    usable = np.asarray(res.converged, dtype=bool) & ~np.asarray(res.flagged, dtype=bool)
    choice, cov = _choose_and_shrink(res.cov_d_formal, res.cov_d_blocks, res.n_blocks, usable)
    old = _rotation_scale(res.cov_d, res.sigma_formal)
    new = _rotation_scale(cov, res.sigma_formal)
    sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    rot = {k: getattr(res, k) / old * new for k in ("sigma_rx", "sigma_ry", "sigma_rz")}
    return replace(
        res,
        **rot,
        cov_d=cov,
        sigma_dx=sd[:, 0],
        sigma_dy=sd[:, 1],
        sigma_dz=sd[:, 2],
        sigma_block_m=choice.block_m,
        sigma_block_ratio=math.nan if choice.level < 0 else choice.kappa,
    )


def _spline_blocks(sfit, usable: np.ndarray, near, blocks_kw, *, sigma_scaling, cells):
    """A spline field's covariances with the residuals' spatial correlation.

    ``sfit`` with ``cov_blocks`` (else unchanged): each cell's block covariance shrunk towards
    its formal covariance times the field's pooled ratio (over ``usable``), the pair
    covariances of ``near`` scaled by ``sqrt(r_i r_j)`` (``r`` the cells' variance ratios per
    component). ``cells``: ``(row, col, d, cov_d, n, ok, usable[, cov_formal])`` of the rigid
    or affine cell pass (block covariances; formal ones where given). Unless
    ``sigma_scaling="formal"``:

    * a fit whose data were weighed ``1 / F`` (``sfit.data_weight``, the rigid cells'
      honest-sigma model) carries ``F`` in its covariance already: no share of the rigid
      cells' cell-wide floor on top (:func:`spline_model_variance` adds what the field
      misses instead);
    * an unweighted fit takes a share of the rigid cells' floor
      (:func:`~slipmap.core.icp_blocks.cell_floor`, :data:`~slipmap.core.icp_blocks.
      SPLINE_FLOOR_SHARE`).

    Returns the new ``sfit`` and ``blocks_kw`` for :func:`finish_cells` (the one-file and the
    tiled run share this)."""
    from .icp_blocks import shrink_covariance

    kw = dict(blocks_kw, cov_formal=None, cov_d_blocks=None, n_blocks=None)
    kw["sigma_formal"] = np.sqrt(np.diagonal(sfit.cov[:, :3, :3], axis1=1, axis2=2))
    if sfit.cov_blocks is None:
        return sfit, kw
    weighted = sfit.data_weight is not None
    fvar = np.diagonal(sfit.cov[:, :3, :3], axis1=1, axis2=2)
    bvar = np.diagonal(sfit.cov_blocks[:, :3, :3], axis1=1, axis2=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.mean(bvar / fvar, axis=1)
    m = usable & np.isfinite(ratio)
    kappa = max(1.0, float(np.median(ratio[m]))) if m.any() else 1.0
    c9 = shrink_covariance(sfit.cov, sfit.cov_blocks, sfit.n_blocks, kappa)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(fvar > 0, np.diagonal(c9[:, :3, :3], axis1=1, axis2=2) / fvar, 1.0)
    pair = sfit.pair_cov
    if pair is not None:
        pair = pair * np.sqrt(r[near[:, 0]] * r[near[:, 1]])
    log.info("spline field: block variance ratio %.2f (blocks of %g m)", kappa, kw["sigma_block_m"])
    kw["sigma_block_ratio"] = kappa
    if sigma_scaling != "formal":
        if weighted and sfit.projection is not None:
            # the field's misfit to the rigid cells: what a smooth (per side) field misses
            kw["model_var"] = spline_model_variance(sfit, cells)
        if not weighted:  # the rigid cells' cell-wide error (icp_blocks)
            kw["cells_floor"] = _cells_floor(cells)
    return replace(sfit, cov=c9, pair_cov=pair), kw


def _cells_floor(cells):
    """The rigid (or affine) cells' cell-wide floor (:func:`~slipmap.core.icp_blocks.
    cell_floor`) from the cell pass's ``(row, col, d, cov_d, n, ok, usable)``."""
    from .icp_blocks import cell_floor

    row, col, d, cov_d, n, ok, cu = cells[:7]
    sd_c = np.sqrt(np.diagonal(cov_d, axis1=1, axis2=2))
    return cell_floor(row[ok], col[ok], d[ok], sd_c[ok], n[ok], usable=cu[ok])


def spline_model_variance(sfit, cells) -> np.ndarray:
    """The variance of what a spline field misses at each cell, from the rigid cells.

    A rigid cell measures its own motion independently of the field's smoothing; the field's
    :func:`~slipmap.core.icp_spline.rigid_projection` (what the cell would measure if the
    ground moved as the field, on the same points, normals and weights) differs from it by
    the cell's own error (honest variance ``F σ_formal²``, ``F`` the cell's data-weight model,
    :func:`~slipmap.core.icp_spline.cell_data_weights`) and by the field's model error there:
    a scarp not found (a slump's outline), the step a misplaced breakline gives to the cells
    beside it, a peak smoothed off. Its variance is estimated per cell and component as
    ``max(0, r² - F σ_formal²)``, ``r`` the rigid motion less the projection (a one-sample
    estimate, unbiased for the squared model error where the cell's honest sigma is; zero
    where the field fits). Cells without a rigid fit or projection get zero.

    Parameters
    ----------
    sfit : SplineFit
        With ``projection`` and ``data_weight`` (K cells, the order of ``cells``' row / col
        lookup below).
    cells : tuple
        ``(row, col, d, cov_d, n, ok, usable[, cov_formal])`` of the rigid cells (L of them)
        and, as ``sfit``'s cells, ``row_k, col_k`` of the spline's K cells appended as
        ``cells[8:10]`` when the two orders differ (a tiled run); else the same cells.

    Returns
    -------
    (K, 3) float64
        Metres²; added to the cells' covariances after the floor.
    """
    row, col, d, cov_d, n, ok = cells[:6]
    cov_f = cells[7] if len(cells) > 7 and cells[7] is not None else cov_d
    k = len(sfit.d)
    if len(cells) > 9:
        key = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(row, col))}
        idx = np.array([key.get((int(a), int(b)), -1) for a, b in zip(cells[8], cells[9])])
    else:
        idx = np.arange(k) if len(row) == k else np.full(k, -1)
    out = np.zeros((k, 3))
    have = idx >= 0
    if not have.any():
        return out
    j = idx[have]
    f = 1.0 / np.asarray(sfit.data_weight, dtype=np.float64)[have]
    var_r = f[:, None] * np.diagonal(np.asarray(cov_f)[j], axis1=1, axis2=2)
    resid = np.asarray(d, dtype=np.float64)[j] - sfit.projection[have]
    ex = resid**2 - var_r
    good = np.asarray(ok, dtype=bool)[j][:, None] & np.isfinite(ex)
    out[have] = np.where(good, np.maximum(ex, 0.0), 0.0)
    log.info(
        "spline field's misfit to the rigid cells: %d of %d cells add a model error "
        "(median %.2f cm where they do)", int(np.any(out > 0, axis=1).sum()), k,
        100 * float(np.median(np.sqrt(out.max(axis=1))[np.any(out > 0, axis=1)]))
        if np.any(out > 0) else 0.0,
    )  # fmt: skip
    return out


def _median_flags(cells: _Cells, d, usable, n_rows, n_cols, eps_m, threshold):
    """:func:`slipmap.core.icp_cells.median_test` of a pass's cell motions."""
    from .icp_cells import median_test

    use = usable & np.all(np.isfinite(d), axis=1)
    return median_test(
        cells.row, cells.col, d, use, n_rows=n_rows, n_cols=n_cols, eps_m=eps_m,
        threshold=threshold,
    )  # fmt: skip


def _deformation_field(cells: _Cells, d, usable, n_rows, n_cols, x0, y0, cell):
    """The field of a pass as functions of xy: ``f(xy) -> (K, 3)`` and its gradient
    ``g(xy) -> (K, 3, 3)`` (the z column zero).

    Cubic B-spline through the cell-centre values (missing cells filled from their
    neighbours, the grid extended linearly by two cells). Cubic, not bilinear: a cell's
    residual fit measures the mean of the residual over the cell, and the iteration stops
    where the interpolant's cell means equal the data's; a bilinear interpolant's cell mean
    differs from its centre value by ``h²/8`` times the curvature (a bias twice that of a
    rigid cell's mean, ``h²/24``), a cubic one's by the field's own ``h²/24``, so the centre
    values converge to the true ones (up to ``O(h⁴)``).
    """
    from scipy import ndimage

    from .piv import replace_outliers

    pad = 2
    coefs = []
    for j in range(3):
        g = np.full((n_rows, n_cols), np.nan)
        g[cells.row[usable], cells.col[usable]] = d[usable, j]
        if not np.isfinite(g).any():
            g[:] = 0.0
        g = replace_outliers(g, np.zeros(g.shape, dtype=bool), fill_all=True)
        g = np.pad(g, pad, mode="reflect", reflect_type="odd")
        coefs.append(ndimage.spline_filter(g, order=3, mode="mirror"))

    def f(xy: np.ndarray) -> np.ndarray:
        fr = (y0 - xy[:, 1]) / cell - 0.5 + pad
        fc = (xy[:, 0] - x0) / cell - 0.5 + pad
        return np.column_stack(
            [
                ndimage.map_coordinates(c, [fr, fc], order=3, prefilter=False, mode="nearest")
                for c in coefs
            ]
        )

    def grad(xy: np.ndarray) -> np.ndarray:
        h = 1e-3 * cell
        out = np.zeros((len(xy), 3, 3))
        for j in range(2):
            e = np.zeros(2)
            e[j] = h
            out[:, :, j] = (f(xy + e) - f(xy - e)) / (2 * h)
        return out

    return f, grad


@single_blas_thread()
def windowed_icp(
    before: np.ndarray,
    after: np.ndarray,
    *,
    cell_m: float = 5.0,
    buffer_m: Optional[float] = None,
    min_points: int = 100,
    origin_xy: Optional[Tuple[float, float]] = None,
    prealign: Union[bool, ICPFit] = False,
    exclude_polygons: Optional[Sequence[np.ndarray]] = None,
    include_polygons: Optional[Sequence[np.ndarray]] = None,
    prealign_max_points: int = PREALIGN_MAX_POINTS,
    max_points_per_cell: Optional[int] = None,
    coarse_to_fine: int = 0,
    initial_displacement: Optional[Callable[[np.ndarray], np.ndarray]] = None,
    sigma_scaling: str = "field",
    sigma_regions: int = 3,
    sigma_region_by: str = "roughness",
    sigma_model: str = "blocks",
    deform_passes: int = 0,
    cell_model: str = "rigid",
    field_model: str = "cells",
    spline_spacing_m: Optional[float] = None,
    spline_smoothing: Optional[float] = None,
    breaklines=None,
    detect_breaklines: bool = False,
    cell_choice: bool = False,
    engine: str = "batched",
    backend: str = "auto",
    median_threshold: float = 2.0,
    median_eps_m: float = 0.02,
    median_restart: bool = False,
    seed: int = 0,
    progress: Optional[ProgressCallback] = None,
    **icp_options,
) -> WindowedICPResult:
    """Displacement field from point-to-plane ICP in square cells of epoch 2 (study 3.2.2).

    Epoch 2 (``after``) is divided into ``cell_m`` squares on a grid snapped to multiples of
    ``cell_m`` (or to ``origin_xy``). Each cell's after-points are registered onto the
    epoch-1 surface: nearest neighbours come from ONE KD-tree of ``before`` (built once), and
    only before-points inside the cell grown by ``buffer_m`` are accepted as correspondences.
    Target normals are computed once per used before-point (k-neighbourhood PCA on all of
    ``before``, so cell edges do not bias them). The cell's displacement is the ground motion
    ``p - T(p)`` at its centre ``p = (cell centre x, y, mean z of its after-points)``.

    Optionally epoch 2 is first aligned to epoch 1 on stable ground (``prealign=True``: global
    ICP outside ``exclude_polygons`` / inside ``include_polygons``; or a given
    :class:`ICPFit`); displacements are then relative to that stable frame. The pre-alignment's
    own uncertainty is not added to the cells' covariances.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        Epochs 1 and 2, metres (same CRS).
    cell_m : float
        Cell side, metres (> 0; the study used 5 m).
    buffer_m : float, optional
        Growth of the cell for target points, metres (>= 0); ``0.5 * cell_m`` by default. Must
        exceed the largest expected displacement.
    min_points : int
        Cells with fewer after-points, or fewer before-points inside the cell, are skipped
        (>= 7).
    origin_xy : (float, float), optional
        A grid node to snap to (default: multiples of ``cell_m`` from (0, 0)).
    prealign : bool or ICPFit
        Align epoch 2 on stable ground first (see above).
    exclude_polygons, include_polygons : sequence of (K, 2) float64, optional
        Moving area(s) to leave out of / stable area(s) to restrict the pre-alignment to.
    prealign_max_points : int
        Stable after-points sampled for the pre-alignment.
    max_points_per_cell : int, optional
        Register at most this many after-points per cell: a seeded sample that depends on
        the points' coordinates only (:func:`sample_priority`), so tiled runs draw the same;
        all by default. On lone-star's 5 m cells 5000 points give the accuracy of all (up
        to 45 000) in 40 % of the time (docs/benchmarks.md).
    coarse_to_fine : int
        Number of coarser passes run first, with cells of ``2**k * cell_m`` (k = levels .. 1);
        each pass starts every cell from the motion of the coarser pass interpolated at the
        cell centre, and moves the cell's target box by it. Needed when the motion is not small
        against the cell (e.g. 1 m of motion in 2 m cells): ICP from zero then stops in a
        local minimum. Every cell whose start is away from zero is also fitted from zero and
        the fit that matches epoch 1 better is kept (:mod:`slipmap.core.icp_starts`): a
        coarse cell that straddles a discontinuity predicts a blend of its two sides, which
        trapped stable cells beside a slump block metres off (docs/fields.md). 0 (default)
        starts every cell from zero motion.
    initial_displacement : callable, optional
        ``f(xy (K, 2)) -> (K, 3)`` starting ground motion at cell centres (e.g. from PIV);
        used by the finest pass (or the coarsest, with ``coarse_to_fine``); cells also
        fitted from zero as above.
    sigma_scaling : {"field", "region", "formal"}
        What the agreement of neighbouring cells does to the covariances. With
        ``sigma_model="blocks"`` (the default) and ``"field"`` or ``"region"`` it first
        supplies the error the cells' residuals cannot show, a factor and a cap on the cells'
        effective observations (:func:`~slipmap.core.icp_blocks.cell_floor`: covariances
        times ``a + n / n_cap``; an unweighted spline field takes at least
        :data:`~slipmap.core.icp_blocks.SPLINE_FLOOR_SHARE` of its cells' excess, a weighted
        one, whose covariance carries the cells' ``F``, none but adds its misfit to the rigid
        cells, :func:`spline_model_variance`); the
        field's factor below is then only estimated and recorded as a check
        (``"field"``), or the region factors are applied on top (``"region"``); ``"formal"``
        leaves the block covariances. With ``sigma_model="independent"``:
        ``"field"`` (default): the cells' covariances are multiplied by the square of the
        field's a-posteriori variance factor (:func:`~slipmap.core.fields.
        neighbour_variance_factor` of dx, dy, dz over the converged cells, at least 1): each
        cell's formal covariance assumes independent point residuals, which real surfaces
        (vegetation, scan shadows, the scanner's sampling pattern) break, and on lone-star
        it is 2-3x too small; the factor restores ``err / sigma`` to about 1 there. With
        fewer than 8 cells that have 5 usable neighbours the formal covariances are kept.
        With ``field_model="spline"`` the neighbour agreement counts the formal covariances
        between neighbouring cells (one field: their errors are correlated).
        ``"region"``: one factor per region of cells instead (``sigma_regions`` classes of
        ``sigma_region_by``; :func:`~slipmap.core.icp_sigma.region_variance_factors`), the
        regions' factors found together, shrunk towards the field's factor where a region has
        few cells, estimated without the cells that did not converge or are ``flagged``, and
        multiplied by :data:`~slipmap.core.icp_sigma.REGION_INFLATION` (neighbour agreement
        misses the error neighbouring cells share; calibrated on lone-star, docs/fields.md);
        with ``field_model="spline"`` they count the pair covariances too.
        ``"formal"``: keep the formal covariances.
    sigma_model : {"blocks", "independent"}
        ``"blocks"`` (default): each cell's covariance counts the spatial correlation of its
        point-to-plane residuals, the cluster-robust (sandwich) covariance with sub-cell
        blocks as clusters, the block size chosen from the data and cells with few blocks
        shrunk towards the field's typical ratio (:mod:`slipmap.core.icp_blocks`; rigid,
        affine and spline fields alike); ``sigma_scaling`` then adds the cell-wide error.
        ``"independent"``: the formal covariance (independent residuals).
    sigma_regions : int
        Number of regions (quantile classes) of ``sigma_scaling="region"`` (>= 1).
    sigma_region_by : {"roughness", "density", "sigma"}
        What the regions class: the cells' point-to-plane residual RMS (``rmse``), their
        after-point density, or their formal 3-D sigma (roughness and density together).
    deform_passes : int
        Window-deformation passes after the first (0: none). Each pass moves every cell's
        after-points back by the field of the previous pass (cubic spline through the cell
        centres, as PIV's window deformation), fits the cell's residual motion, and reports
        the field at the centre plus the residual there. A rigid cell can only see the mean
        motion of its points, which on a lobe a few cells wide differs from the motion at
        its centre by centimetres; the deformed passes converge to the centre value.
        Covariances are those of the last residual fit (the previous field taken as known).
    cell_model : {"rigid", "affine"}
        Motion model of a cell: a rigid transform (6 parameters, the study's) or an affine
        one (12: a 3 x 3 matrix and a translation; it follows a straining cell and gives its
        strain). See :mod:`slipmap.core.icp_cells`.
    field_model : {"cells", "spline"}
        ``"cells"`` (default): every cell reports its own motion (the study's model).
        ``"spline"``: after the cell passes, one smooth field, a bicubic B-spline of the
        horizontal position with knots ``spline_spacing_m`` apart, is fitted to the
        point-to-plane residuals of all the cells' points at once, started from the cells'
        field (:func:`slipmap.core.icp_spline.fit_spline_field`); each cell then reports
        the field's value at its centre, its covariance (``sigma0² A⁻¹`` of the penalised
        normal matrix), its gradient (``exx, eyy, exy``, the rotations) and the residuals of
        its points. The field follows a lobe only 3-4 cells wide where a cell's mean motion
        cannot (docs/fields.md); neighbouring cells' values are then correlated.
    spline_spacing_m : float, optional
        Knot spacing of ``field_model="spline"``, metres (default ``cell_m / 2``).
    spline_smoothing : float, optional
        Second-difference penalty of ``field_model="spline"`` relative to the median
        diagonal of its normal matrix (>= 0); None (default): estimated per component by
        variance-component estimation.
    breaklines : Breaklines or sequence of (M, 2) float64, optional
        Lines (scarps, a fault, the edge of a slab; map coordinates of ``after``) across which
        ``field_model="spline"`` may jump: the field is smooth on each side
        (:func:`slipmap.core.icp_spline.fit_spline_field`). Ignored by ``field_model="cells"``.
    detect_breaklines : bool
        With ``field_model="spline"`` and no ``breaklines``: look for them in the cells'
        motions (:func:`slipmap.core.breaklines.detect_breaklines`: edges where the motion
        jumps by far more than the cells' sigmas and the neighbouring edges' differences,
        chained into lines), place them on the points (each point near a line goes to the
        side whose field fits it: :func:`slipmap.core.icp_spline.refine_breaklines`), and fit
        the field smooth on each side. The result's ``breaklines`` holds what was found.
    cell_choice : bool
        With ``field_model="spline"``: a cell whose own rigid (or affine) fit explains its
        points better than the field (:mod:`slipmap.core.icp_choice`: its mean truncated
        point-to-plane cost lower by more than two standard errors, not clearly worse around
        its centre) and whose value differs from the field's beyond their covariances reports
        that fit, with its block covariance and the cells' cell-wide floor; the result's
        ``from_cell``
        marks them. Where the ground moves in a way the field cannot follow and no line was
        found (a rotating slump block), the field smooths and the cells do not.
    median_threshold : float
        Wrong-minimum test (0: off): a cell whose motion differs from the median of its
        8-neighbours by more than this many times their median spread (plus
        ``median_eps_m``), the normalised median test of PIV (Westerweel & Scarano 2005), is
        ``flagged``; with ``median_restart`` it is first fitted again from that median: the
        restart replaces the first fit when its residuals
        are smaller (a wrong minimum fits the surface worse than the right one, and a true
        peak of the field restarts into the same fit), and the cells still failing are
        ``flagged`` in the result. Cells with fewer
        than 3 fitted neighbours are not tested.
    median_eps_m : float
        Noise level of that test, metres.
    median_restart : bool
        Restart flagged cells from their neighbours' median (default off: on lone-star it
        repairs small edge cells whose disagreement had propped up the field's variance
        factor, which then drops from 3.0 to 1.9 and the sigmas of the good cells cover only
        83 % of their errors within 2 sigma instead of 96 %; use it where a wrong cell
        matters more than the sigmas).
    engine : {"batched", "per_cell"}
        ``"batched"`` (default) fits all cells together (one KD-tree query per iteration,
        stacked solves); ``"per_cell"`` is the slow obvious reference, one cell at a time.
    backend : {"auto", "numpy", "numba", "opencl"}
        Where the batched engine finds its pairs: numpy and a KD-tree (the reference),
        compiled CPU kernels through Numba (:mod:`slipmap.core.icp_numba`, an optional
        dependency), or an OpenCL device through PyOpenCL (:mod:`slipmap.core.opencl.nearest`);
        the same pairs, hence the same results up to exact distance ties and rounding.
        ``"auto"`` (default) takes OpenCL when a device starts, else Numba when it is
        installed, else numpy. Only the batched engine uses it.
    seed : int
        Seed of the samples.
    progress : callable, optional
        ``progress(fraction, message)``; may raise CancelledError.
    **icp_options
        ``max_iterations, tolerance_m, tolerance_rad, max_correspondence_m (default:
        buffer_m when > 0), trim_fraction, robust, neighbours_k`` as in
        :func:`icp_point_to_plane`.

    Returns
    -------
    WindowedICPResult

    Raises
    ------
    InvalidParameterError
        Bad options.
    InputDataError
        Empty or non-finite inputs, epochs that do not overlap, or no cell could be fitted.
    """
    from scipy.spatial import cKDTree

    t_start = time.perf_counter()
    b = _points("before", before)
    a = _points("after", after)
    cell = _positive("cell_m", cell_m)
    buf = 0.5 * cell if buffer_m is None else _positive("buffer_m", buffer_m, allow_zero=True)
    minp = _int_at_least("min_points", min_points, 7)
    if "max_correspondence_m" not in icp_options and buf > 0:
        icp_options["max_correspondence_m"] = buf
    opts = _options(**icp_options)
    mpc = None
    if max_points_per_cell is not None:
        mpc = _int_at_least("max_points_per_cell", max_points_per_cell, 7)
    if not isinstance(prealign, (bool, ICPFit)):
        raise InvalidParameterError(
            f"prealign must be True, False or an ICPFit, got {type(prealign).__name__}"
        )
    levels = _int_at_least("coarse_to_fine", coarse_to_fine, 0)
    if sigma_scaling not in SIGMA_SCALING_CHOICES:
        raise InvalidParameterError(
            f"sigma_scaling must be one of {SIGMA_SCALING_CHOICES}, got {sigma_scaling!r}"
        )
    n_regions = _int_at_least("sigma_regions", sigma_regions, 1)
    if sigma_model not in SIGMA_MODELS:
        raise InvalidParameterError(
            f"sigma_model must be one of {SIGMA_MODELS}, got {sigma_model!r}"
        )
    if sigma_region_by not in SIGMA_REGION_BY:
        raise InvalidParameterError(
            f"sigma_region_by must be one of {SIGMA_REGION_BY}, got {sigma_region_by!r}"
        )
    passes = _int_at_least("deform_passes", deform_passes, 0)
    if cell_model not in CELL_MODELS:
        raise InvalidParameterError(f"cell_model must be one of {CELL_MODELS}, got {cell_model!r}")
    model = cell_model
    if field_model not in FIELD_MODELS:
        raise InvalidParameterError(
            f"field_model must be one of {FIELD_MODELS}, got {field_model!r}"
        )
    spline_h = (
        0.5 * cell if spline_spacing_m is None else _positive("spline_spacing_m", spline_spacing_m)
    )
    spline_lam = (
        None
        if spline_smoothing is None
        else _positive("spline_smoothing", spline_smoothing, allow_zero=True)
    )
    from .breaklines import given_breaklines

    lines = given_breaklines(breaklines)
    lines_source = "given" if lines is not None else "none"
    med_thr = _positive("median_threshold", median_threshold, allow_zero=True)
    med_eps = _positive("median_eps_m", median_eps_m, allow_zero=True)
    if engine not in ENGINES:
        raise InvalidParameterError(f"engine must be one of {ENGINES}, got {engine!r}")
    if backend not in BACKENDS:
        raise InvalidParameterError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if initial_displacement is not None and not callable(initial_displacement):
        raise InvalidParameterError("initial_displacement must be a function xy -> (K, 3)")
    _check_overlap(b, a)
    if levels > 0:
        coarse = windowed_icp(
            b,
            a,
            cell_m=2.0 * cell,
            buffer_m=None if buffer_m is None else 2.0 * buf,
            min_points=minp,
            origin_xy=origin_xy,
            prealign=prealign,
            exclude_polygons=exclude_polygons,
            include_polygons=include_polygons,
            prealign_max_points=prealign_max_points,
            max_points_per_cell=max_points_per_cell,
            coarse_to_fine=levels - 1,
            initial_displacement=initial_displacement,
            sigma_scaling="formal",
            sigma_model="independent",
            engine=engine,
            backend=backend,
            median_threshold=median_threshold,
            median_eps_m=median_eps_m,
            median_restart=median_restart,
            seed=seed,
            progress=scaled(progress, 0.0, 0.4),
            **icp_options,
        )
        initial_displacement = _interpolator(coarse)
        if coarse.prealignment is not None:
            prealign = coarse.prealignment  # the same stable frame, not fitted again
        progress = scaled(progress, 0.4, 1.0)

    report(progress, 0.0, "building the epoch-1 KD-tree")
    off = b.mean(axis=0)
    tree = _OffsetTree(cKDTree(b - off), off)
    normals = _NormalCache(b, tree.tree, opts.neighbours_k, offset=off)
    grid = _target_grid(b, backend) if engine == "batched" else None
    if grid is not None and opts.neighbours_k <= grid.MAX_NORMAL_K:
        normals.device = grid

    pre: Optional[ICPFit] = None
    if isinstance(prealign, ICPFit):
        pre = prealign
    elif prealign:
        report(progress, 0.02, "pre-aligning the epochs on stable ground")
        pmp = _int_at_least("prealign_max_points", prealign_max_points, 7)
        pre = _prealign(
            b,
            a,
            tree,
            normals,
            opts,
            exclude_polygons,
            include_polygons,
            pmp,
            seed,
            scaled(progress, 0.02, 0.1),
        )
        log.info(
            "pre-alignment: t=%s m, r=%s rad, rmse %.4f m",
            np.round(pre.params[3:], 4),
            np.round(pre.params[:3], 6),
            pre.rmse_m,
        )
    if pre is not None:
        a = pre.apply(a)

    x0, y0, n_rows, n_cols = _grid_origin(a, cell, origin_xy)
    if field_model == "spline":  # before any cell is fitted (issue #31)
        from .icp_spline import check_spline_size

        check_spline_size(a[:, :2].max(axis=0) - a[:, :2].min(axis=0) + cell, spline_h)
    ra, ca = _cell_index(a, x0, y0, cell)
    keys_a = ra * n_cols + ca
    order = np.argsort(keys_a, kind="stable")
    uk, starts, counts = np.unique(keys_a[order], return_index=True, return_counts=True)
    if field_model == "spline":
        from .icp_spline import MIN_SPLINE_CELLS, SplineCellsError

        full = int(np.sum(counts >= min_points))
        if full < MIN_SPLINE_CELLS:
            raise SplineCellsError(
                f"{full} cell(s) of {cell:g} m hold {minp} points or more; a spline "
                f"field needs {MIN_SPLINE_CELLS} at least",
                cells=full,
            )
    cells, skipped, uk, sel = select_cells(
        a, b, x0=x0, y0=y0, n_rows=n_rows, n_cols=n_cols, cell_m=cell, buffer_m=buf,
        min_points=minp, max_points_per_cell=mpc, seed=seed,
    )  # fmt: skip
    gate = math.inf if opts.max_correspondence_m is None else opts.max_correspondence_m
    # starting motion of every cell in one call (a per-cell call of a sampler is slow)
    start_d = np.zeros((len(uk), 3))
    if initial_displacement is not None and len(uk):
        rows_u, cols_u = np.divmod(uk, n_cols)
        centres_xy = np.column_stack([x0 + (cols_u + 0.5) * cell, y0 - (rows_u + 0.5) * cell])
        start_d = np.asarray(initial_displacement(centres_xy), dtype=np.float64)
        start_d = np.where(np.isfinite(start_d), start_d, 0.0).reshape(len(uk), 3)
    report(progress, 0.1 if pre is not None else 0.02, f"ICP: {len(sel)} cells")
    fit_kw = dict(
        before=b, tree=tree, normals=normals, gate=gate, opts=opts, engine=engine, grid=grid
    )
    n_pass = 1 + passes
    pass_progress = scaled(progress, 0.1 if pre is not None else 0.02, 1.0)
    d0 = start_d[sel]
    fits = _fit_pass(
        cells,
        a[cells.points],
        d0,
        np.zeros((len(sel), 3)),
        model,
        progress=scaled(pass_progress, 0.0, 1.0 / n_pass),
        **fit_kw,
    )
    if initial_displacement is not None:
        fits = _zero_starts(cells, a[cells.points], d0, fits, model, fit_kw)
    report(pass_progress, 1.0 / n_pass, f"ICP pass 1 of {n_pass}")
    d, cov_d, grad = fits.d, fits.cov_d, fits.gradient
    for k in range(passes):
        # window deformation: after-points pre-moved by the field of the previous pass
        usable = fits.ok & np.all(np.isfinite(d), axis=1)
        f_at, f_grad = _deformation_field(cells, d, usable, n_rows, n_cols, x0, y0, cell)
        moved = a[cells.points]
        moved = moved - f_at(moved[:, :2])
        fc = f_at(cells.centres[:, :2])
        fits = _fit_pass(
            cells,
            moved,
            -fc,
            fc,
            model,
            residual=True,
            progress=scaled(pass_progress, (k + 1) / n_pass, (k + 2) / n_pass),
            **fit_kw,
        )
        g_f = f_grad(cells.centres[:, :2])
        d = fc + fits.d_residual
        cov_d = fits.cov_d
        grad = g_f + np.einsum("kij,kjl->kil", fits.gradient, np.eye(3)[None] - g_f)
        report(pass_progress, (k + 2) / n_pass, f"ICP pass {k + 2} of {n_pass}")
    # wrong minima: cells far from their neighbours' median (after the last pass) are
    # restarted from that median; those still off are flagged
    flagged = np.zeros(len(sel), dtype=bool)
    if med_thr > 0:
        flagged, med, _ = _median_flags(cells, d, fits.ok, n_rows, n_cols, med_eps, med_thr)
        idx = np.flatnonzero(flagged & np.all(np.isfinite(med), axis=1))
        if idx.size and median_restart:
            sub = _cells_subset(cells, idx)
            start = med[idx]
            if passes == 0:
                sfit = _fit_pass(
                    sub, a[sub.points], start, np.zeros((idx.size, 3)), model, **fit_kw
                )
                d_new, g_new = sfit.d, sfit.gradient
            else:
                moved = a[sub.points]
                moved = moved - f_at(moved[:, :2])
                fc = f_at(sub.centres[:, :2])
                # start the residual from the neighbours' median, not from the field
                sfit = _fit_pass(sub, moved, start - fc, fc, model, residual=True, **fit_kw)
                g_f = f_grad(sub.centres[:, :2])
                d_new = fc + sfit.d_residual
                g_new = g_f + np.einsum("kij,kjl->kil", sfit.gradient, np.eye(3)[None] - g_f)
            # a wrong minimum fits worse than the right one: keep the restart where its
            # residuals are smaller (a true peak of the field restarts into the same fit)
            old_rmse = np.where(fits.ok[idx], fits.rmse[idx], np.inf)
            closer = sfit.ok & (sfit.rmse < old_rmse)
            fits = _merge_fits(fits, sfit, idx, closer)
            d, grad = d.copy(), grad.copy()
            d[idx[closer]], grad[idx[closer]] = d_new[closer], g_new[closer]
            cov_d = fits.cov_d
            flagged, _, _ = _median_flags(cells, d, fits.ok, n_rows, n_cols, med_eps, med_thr)
            log.info(
                "wrong minima: %d cells restarted from their neighbours, %d fit better, "
                "%d still flagged",
                idx.size,
                int(closer.sum()),
                int(flagged.sum()),
            )
    rmse, sigma0, n_used = fits.rmse, fits.sigma0, fits.n
    ok, rot, sig_rot = fits.ok, fits.rotation, fits.sigma_rotation
    near = pair_src = from_cell = None
    sigma_formal = np.sqrt(np.diagonal(cov_d, axis1=1, axis2=2))
    cov_formal = cov_d
    block, rot_scale = None, np.ones(len(sel))
    if sigma_model == "blocks":
        block, cov_d = _block_covariances(fits, cov_d, flagged)
        rot_scale = _rotation_scale(cov_d, sigma_formal)
    blocks_kw = dict(
        sigma_model=sigma_model,
        sigma_block_m=math.nan if block is None else block.block_m,
        sigma_block_ratio=math.nan if block is None or block.level < 0 else block.kappa,
        cov_formal=cov_formal,
        cov_d_blocks=fits.cov_d_blocks if sigma_model == "blocks" else None,
        n_blocks=fits.n_blocks if sigma_model == "blocks" else None,
    )
    if field_model == "spline":
        from .icp_spline import fit_spline_field

        usable = fits.ok & np.all(np.isfinite(d), axis=1)
        start, _ = _deformation_field(cells, d, usable, n_rows, n_cols, x0, y0, cell)
        report(progress, 0.9, "fitting one spline field to all cells")
        near = _near_pairs(cells.row, cells.col, reach=2)
        spline_kw = dict(
            before=b,
            tree=tree,
            normals=normals,
            initial=start,
            report_xy=cells.centres[:, :2],
            report_seg=cells.seg,
            report_pairs=near,
            spacing_m=spline_h,
            smoothing=spline_lam,
            gate_m=gate,
            opts=opts,
            grid=grid,
        )
        first = None  # the fit with candidate lines, when lines were detected
        if lines is None and detect_breaklines:
            # the formal covariances: the detection's threshold was set with them
            tries = candidate_lines(
                cells, d, usable & ~flagged, cov_formal, (n_rows, n_cols, x0, y0, cell),
                grad=grad, sig_grad=sig_rot,
            )  # fmt: skip

            def fit(candidate):  # one fit with the candidate lines ...
                return fit_spline_field(
                    a[cells.points], breaklines=candidate, progress=scaled(progress, 0.9, 0.95),
                    defer_report=True, **spline_kw,
                )  # fmt: skip

            def confirm(field, straight, again):  # ... then the points confirm and place them
                return confirm_lines(
                    field, a[cells.points], straight, before=b, tree=tree, normals=normals,
                    gate_m=gate, cell_m=cell, again=again,
                )  # fmt: skip

            lines, first = try_candidates(tries, fit, confirm)
            if tries:
                lines_source = "none" if lines is None else "detected"
                progress = scaled(progress, 0.95, 1.0)
        weights = None
        if block is not None and block.level >= 0:
            # each cell's data weighed by its share of independent observations (the rigid
            # cells' honest-sigma model, icp_spline.cell_data_weights)
            from .icp_spline import cell_data_weights

            cu0 = fits.ok & fits.converged & ~flagged

            def weights(projection):
                return cell_data_weights(
                    cells.row, cells.col, d, cov_d, cov_formal, fits.n, usable=cu0,
                    projection=projection, fitted=fits.ok, rmse=fits.rmse,
                )[0]  # fmt: skip

        if first is not None:  # the refit starts where the candidate's fit ended
            spline_kw.update(initial=first.field, smoothing_start=first.smoothing_estimate)
        sfit = fit_spline_field(
            a[cells.points],
            cell_weight=weights,
            breaklines=lines,
            # a detected line is placed to about a metre: the points that close to it are
            # left out (on lone-star's scarp, 5 m cells: 5.6 cm -> 0.6 cm at cells >= 3 m)
            breakline_gap_m=DETECTED_GAP_CELLS * cell if lines_source == "detected" else 0.0,
            progress=scaled(progress, 0.9, 1.0),
            block_m=None if block is None or block.level < 0 else block.block_m,
            **spline_kw,
        )
        cu = fits.ok & fits.converged & ~flagged  # the cell pass's usable cells
        sfit, blocks_kw = _spline_blocks(
            sfit, cu & (sfit.n >= minp), near, blocks_kw, sigma_scaling=sigma_scaling,
            cells=(cells.row, cells.col, d, cov_d, fits.n, fits.ok, cu, cov_formal),
        )  # fmt: skip
        sp = spline_cells(sfit, cells, fits.ok, min_points=minp, median_threshold=med_thr,
                          median_eps_m=med_eps, n_rows=n_rows, n_cols=n_cols)  # fmt: skip
        from .icp_choice import choice_costs, choose_cells, no_worse

        # each cell's points choose between the field and the cell's own fit (icp_choice)
        own = dict(d=d, grad=grad, cov_d=cov_d, rmse=fits.rmse, n=fits.n, sigma0=fits.sigma0,
                   sig_rot=sig_rot * rot_scale[:, None])  # fmt: skip
        take, level, unexplained = np.zeros(len(sel), dtype=bool), None, None
        if cell_choice:
            costs = choice_costs(
                a[cells.points], cells.seg, len(sel), cells.centres, sfit.field, d, grad,
                cell_m=cell, tree=tree, normals=normals, gate=gate, n_targets=len(b),
            )  # fmt: skip
            fitted = fits.ok & fits.converged & (fits.n >= minp)
            take, level = choose_cells(costs, fitted), no_worse(costs, fitted)
            unexplained = costs.unexplained
        sp, blocks_kw, pair_src = take_own_fits(
            sp, take, own, blocks_kw, sfit.pair_cov, near, cells=cells,
            floor_cells=(cells.row, cells.col, own["d"], cov_d, fits.n, fits.ok, cu),
            flag_kw=dict(n_rows=n_rows, n_cols=n_cols, eps_m=med_eps, threshold=med_thr),
            unexplained=unexplained, no_worse=level,
        )  # fmt: skip
        d, grad, cov_d, rmse, n_used = sp["d"], sp["grad"], sp["cov_d"], sp["rmse"], sp["n"]
        sigma0, sig_rot, ok, flagged = sp["sigma0"], sp["sig_rot"], sp["ok"], sp["flagged"]
        from_cell = sp["from_cell"]
    else:  # the blocks' ratio of the translation, for the rotations
        sig_rot = sig_rot * rot_scale[:, None]
        blocks_kw["sigma_formal"] = sigma_formal
    if not (passes == 0 and model == "rigid" and field_model == "cells"):
        rot = None  # from the gradient of the total motion
    return finish_cells(
        cells, ok=ok, d=d, cov_d=cov_d, grad=grad, rot=rot, sig_rot=sig_rot, rmse=rmse,
        sigma0=sigma0, n_used=n_used, iterations=fits.iterations, converged=fits.converged,
        flagged=flagged, skipped=skipped, min_points=minp, max_iterations=opts.max_iterations,
        origin_xy=(float(x0), float(y0)), cell_m=cell, n_rows=n_rows, n_cols=n_cols,
        prealignment=pre, t_start=t_start, cell_model=model, deform_passes=passes,
        field_model=field_model, near=near, pair_cov=pair_src, sigma_scaling=sigma_scaling,
        sigma_regions=n_regions, sigma_region_by=sigma_region_by, lines=lines,
        lines_source=lines_source, from_cell=from_cell, **blocks_kw,
    )  # fmt: skip


def select_cells(
    a: np.ndarray,
    b: np.ndarray,
    *,
    x0: float,
    y0: float,
    n_rows: int,
    n_cols: int,
    cell_m: float,
    buffer_m: float,
    min_points: int,
    max_points_per_cell: Optional[int] = None,
    seed: int = 0,
    owned: Optional[Callable[[np.ndarray], np.ndarray]] = None,
):
    """The cells a windowed-ICP run fits on its lattice: those with ``min_points`` after-
    and before-points, their (sampled) after-points concatenated cell by cell.

    Parameters
    ----------
    a, b : (N2, 3), (N1, 3) float64
        After and before points, metres.
    x0, y0, n_rows, n_cols, cell_m
        The lattice: west edge of column 0, north edge of row 0, its size, the cell side.
    buffer_m, min_points, max_points_per_cell, seed
        As :func:`windowed_icp`.
    owned : callable, optional
        ``owned(xy (K, 2)) -> (K,) bool`` of cell centres: only those cells are taken (and
        counted); a tile block owns the cells whose centre it holds.

    Returns
    -------
    (cells, skipped, uk, sel)
        ``_Cells``; the skipped counts; the lattice keys (``row * n_cols + col``) of the
        cells with after-points and the indices into them of the cells taken.
    """
    cell = float(cell_m)
    ra, ca = _cell_index(a, x0, y0, cell)
    keys_a = ra * n_cols + ca
    order = np.argsort(keys_a, kind="stable")
    uk, starts, counts = np.unique(keys_a[order], return_index=True, return_counts=True)
    if owned is not None and len(uk):
        rows_u, cols_u = np.divmod(uk, n_cols)
        mine = owned(np.column_stack([x0 + (cols_u + 0.5) * cell, y0 - (rows_u + 0.5) * cell]))
        uk, starts, counts = uk[mine], starts[mine], counts[mine]
    rb, cb = _cell_index(b, x0, y0, cell)
    inb = (rb >= 0) & (rb < n_rows) & (cb >= 0) & (cb < n_cols)
    nb_cell = np.bincount(rb[inb] * n_cols + cb[inb], minlength=n_rows * n_cols)
    skipped = {"few_after_points": 0, "few_before_points": 0, "icp_failed": 0}
    sel, idx_parts = [], []
    for ci, (key, s0, cnt) in enumerate(zip(uk, starts, counts)):
        if cnt < min_points:
            skipped["few_after_points"] += 1
            continue
        if nb_cell[key] < min_points:
            skipped["few_before_points"] += 1
            continue
        idx = order[s0 : s0 + cnt]
        if max_points_per_cell is not None and cnt > max_points_per_cell:
            pri = sample_priority(a[idx], seed)
            idx = np.sort(idx[np.argpartition(pri, max_points_per_cell - 1)[:max_points_per_cell]])
        sel.append(ci)
        idx_parts.append(idx)
    sel = np.asarray(sel, dtype=np.int64)
    cells = _Cells.build(
        a, idx_parts, uk[sel], counts[sel], nb_cell[uk[sel]], x0, y0, cell, buffer_m, n_cols
    )
    return cells, skipped, uk, sel


def spline_cells(sfit, cells: _Cells, cells_ok, *, min_points, median_threshold,
                 median_eps_m, n_rows, n_cols) -> Dict[str, np.ndarray]:  # fmt: skip
    """What the cells report from a spline field (:class:`~.icp_spline.SplineFit` at their
    centres): ``d``, ``grad``, ``cov_d``, ``rmse``, ``n``, ``sigma0``, ``sig_rot`` (the
    rotations' sigmas), ``ok`` (``cells_ok`` and ``min_points`` used points) and ``flagged``
    (the median test on the field's values)."""
    d, grad, cov_d = sfit.d, sfit.gradient, sfit.cov[:, :3, :3]
    # the spline's rotations: antisymmetric part of its gradient; rows of sfit.cov are
    # (d, d d/dx, d d/dy) x (x, y, z): rz = (ddy/dx - ddx/dy) / 2, rx = ddz/dy / 2,
    # ry = -ddz/dx / 2
    c9 = sfit.cov
    sig_rot = 0.5 * np.sqrt(
        np.maximum(
            np.column_stack(
                [c9[:, 8, 8], c9[:, 5, 5], c9[:, 4, 4] + c9[:, 6, 6] - 2 * c9[:, 4, 6]]
            ),
            0.0,
        )
    )
    ok = cells_ok & (sfit.n >= min_points) & np.all(np.isfinite(d), axis=1)
    flagged = np.zeros(len(d), dtype=bool)
    if median_threshold > 0:
        flagged, _, _ = _median_flags(cells, d, ok, n_rows, n_cols, median_eps_m, median_threshold)
    return dict(d=d, grad=grad, cov_d=cov_d, rmse=sfit.rmse, n=sfit.n,
                sigma0=np.full(len(d), sfit.sigma0_m), sig_rot=sig_rot, ok=ok,
                flagged=flagged)  # fmt: skip


def take_own_fits(sp, take, own, blocks_kw, pair_cov, near, *, cells, floor_cells, flag_kw,
                  unexplained, no_worse=None):  # fmt: skip
    """The cells ``take`` (K,) of a spline field reporting their own rigid or affine fit.

    ``sp``: :func:`spline_cells`' values; ``own``: the cell pass's ``d``, ``grad``, ``cov_d``
    (block covariances), ``rmse``, ``n``, ``sigma0``, ``sig_rot`` on the same K cells. Of the
    cells ``take`` (their points chose), only those whose own value differs from the field's
    beyond the two covariances report it (:func:`~slipmap.core.icp_choice.differ`). A taken
    cell's covariance is its block covariance times the rigid cells' cell-wide floor (what
    the cells model reports before the field's factor; ``floor_cells``: ``(row, col, d,
    cov_d, n, ok, usable)`` of the cell pass, as :func:`_spline_blocks` takes them), and its
    error is not the field's (``pair_cov`` zero on its pairs ``near``). Its model error
    (``blocks_kw["model_var"]``, added after the floor) is the pull of the points its fit
    leaves ``unexplained`` (K,), a share ``u`` of them: where a cell holds part of another
    motion (beside a scarp or a block's outline), its fit is pulled towards it by about ``u``
    times the jump, measured by the fit's difference from the field, ``(u (d_own -
    d_field))²`` per component; about nothing where the cell holds one motion. The median test
    runs again on the values reported (``flag_kw``: :func:`_median_flags`' ``n_rows,
    n_cols, eps_m, threshold``). Returns ``sp`` (with ``from_cell``), ``blocks_kw``,
    ``pair_cov``; the one-file and the tiled run share this (:mod:`slipmap.core.icp_choice`
    chooses). ``no_worse`` (K,) bool, optional: the cells whose own fit is no worse than the
    field (:func:`~slipmap.core.icp_choice.no_worse`); of them, those where the field's
    covariance is far larger than the cell's report their fit as well, whether or not the two
    values differ (:func:`~slipmap.core.icp_choice.more_precise`)."""
    from .icp_choice import differ, more_precise

    sp = dict(sp, from_cell=np.asarray(take, dtype=bool))
    if not take.any() and (no_worse is None or not no_worse.any()):
        return sp, blocks_kw, pair_cov
    fl = blocks_kw.get("cells_floor")  # an unweighted field's share came from it
    fl = _cells_floor(floor_cells) if fl is None else fl
    g = fl.scale(own["n"]) if math.isfinite(fl.factor) else np.ones(len(take))
    cov_own = own["cov_d"] * g[:, None, None]  # what a taken cell reports
    # only where the two values differ beyond their uncertainty (icp_choice.differ)
    take = take & differ(own["d"], sp["d"], cov_own + sp["cov_d"])
    if no_worse is not None:  # or where the field is barely determined (more_precise)
        take = take | more_precise(no_worse, cov_own, sp["cov_d"])
    sp["from_cell"] = take
    if not take.any():
        return sp, blocks_kw, pair_cov
    u = np.where(np.isfinite(unexplained), unexplained, 1.0)
    pull = (u[:, None] * (own["d"] - sp["d"])) ** 2
    for key in ("d", "grad", "rmse", "n", "sigma0", "sig_rot"):
        t = take.reshape((-1,) + (1,) * (np.ndim(own[key]) - 1))
        sp[key] = np.where(t, own[key], sp[key])
    sp["cov_d"] = np.where(take[:, None, None], cov_own, sp["cov_d"])
    sp["ok"] = sp["ok"] | take
    if flag_kw["threshold"] > 0:
        sp["flagged"] = _median_flags(cells, sp["d"], sp["ok"], flag_kw["n_rows"],
                                      flag_kw["n_cols"], flag_kw["eps_m"],
                                      flag_kw["threshold"])[0]  # fmt: skip
    mv = blocks_kw.get("model_var")
    mv = np.zeros((len(take), 3)) if mv is None else mv
    blocks_kw = dict(blocks_kw, model_var=np.where(take[:, None], pull, mv))
    if pair_cov is not None:
        pair_cov = np.where((take[near[:, 0]] | take[near[:, 1]])[:, None], 0.0, pair_cov)
    log.info("%d of %d cells report their own fit: it fits their points better than the field, "
             "or as well where the field is barely determined",
             int(take.sum()), int(sp["ok"].sum()))  # fmt: skip
    return sp, blocks_kw, pair_cov


def finish_cells(
    cells: _Cells, *, ok, d, cov_d, grad, rot, sig_rot, rmse, sigma0, n_used, iterations,
    converged, flagged, skipped, min_points, max_iterations, origin_xy, cell_m, n_rows,
    n_cols, prealignment, t_start, cell_model, deform_passes, field_model, near=None,
    pair_cov=None, sigma_scaling="field", sigma_regions=3, sigma_region_by="roughness",
    lines=None, lines_source="none", sigma_model="independent", sigma_block_m=math.nan,
    sigma_block_ratio=math.nan, sigma_formal=None, cov_formal=None, cov_d_blocks=None,
    n_blocks=None, cells_floor=None, model_var=None, from_cell=None,
) -> WindowedICPResult:  # fmt: skip
    """The result of a windowed-ICP run from its cells' values (``rot`` None: the
    antisymmetric part of ``grad``), the cells not ``ok`` left out and counted, the sigmas
    scaled as ``sigma_scaling`` says (``near``, ``pair_cov``: the spline field's pairs of
    cells and their covariances). A tiled spline run finishes here too. ``sigma_model`` ..
    ``n_blocks``: the block covariances' record (:class:`WindowedICPResult`; the arrays per
    cell, ``cov_formal`` the formal covariances of rigid or affine cells), ``cells_floor``
    the rigid cells' :class:`~slipmap.core.icp_blocks.CellFloor` of a spline field,
    ``model_var`` (K, 3) the variance of a weighted spline field's misfit to the rigid cells
    (:func:`spline_model_variance`), added after the floor; ``from_cell`` (K,) bool the
    cells of a spline field that report their own fit (:func:`take_own_fits`)."""
    skipped = dict(skipped)
    skipped["icp_failed"] = int(np.count_nonzero(~ok))
    n_ok = int(np.count_nonzero(ok))
    if n_ok == 0:
        why = "; ".join(f"{v} {_SKIP_WORDS[k]}" for k, v in skipped.items() if v)
        raise InputDataError(
            f"no cell could be registered: all {sum(skipped.values())} cells with points were "
            f"skipped ({why}); use a larger cell_m or a smaller min_points (now {min_points})"
        )
    n_fail_nonconv = int(np.count_nonzero(~converged[ok]))
    if n_fail_nonconv:
        log.warning(
            "%d of %d cells did not converge in %d iterations",
            n_fail_nonconv,
            n_ok,
            max_iterations,
        )
    if rot is None:
        # rotation of the total motion: antisymmetric part of its gradient; sigma of the
        # last pass's residual model (or the spline's)
        w = 0.5 * (grad - np.transpose(grad, (0, 2, 1)))
        rot = np.stack([w[:, 2, 1], w[:, 0, 2], w[:, 1, 0]], axis=1)
    sd = np.sqrt(np.diagonal(cov_d, axis1=1, axis2=2))
    res = WindowedICPResult(
        x=cells.centres[ok, 0],
        y=cells.centres[ok, 1],
        z=cells.centres[ok, 2],
        dx=d[ok, 0],
        dy=d[ok, 1],
        dz=d[ok, 2],
        sigma_dx=sd[ok, 0],
        sigma_dy=sd[ok, 1],
        sigma_dz=sd[ok, 2],
        cov_d=cov_d[ok],
        rx=rot[ok, 0],
        ry=rot[ok, 1],
        rz=rot[ok, 2],
        sigma_rx=sig_rot[ok, 0],
        sigma_ry=sig_rot[ok, 1],
        sigma_rz=sig_rot[ok, 2],
        rmse=rmse[ok],
        sigma0=sigma0[ok],
        n=n_used[ok],
        n_after=cells.n_after[ok],
        n_before=cells.n_before[ok],
        iterations=iterations[ok],
        converged=converged[ok],
        row=cells.row[ok],
        col=cells.col[ok],
        origin_xy=origin_xy,
        cell_m=cell_m,
        n_rows=n_rows,
        n_cols=n_cols,
        skipped=skipped,
        prealignment=prealignment,
        seconds=time.perf_counter() - t_start,
        exx=grad[ok, 0, 0],
        eyy=grad[ok, 1, 1],
        exy=0.5 * (grad[ok, 0, 1] + grad[ok, 1, 0]),
        cell_model=cell_model,
        deform_passes=deform_passes,
        field_model=field_model,
        flagged=flagged[ok],
        breaklines=lines if field_model == "spline" else None,
        breaklines_source=lines_source if field_model == "spline" else "none",
        sigma_model=sigma_model,
        sigma_block_m=sigma_block_m,
        sigma_block_ratio=sigma_block_ratio,
        sigma_formal=None if sigma_formal is None else sigma_formal[ok],
        cov_d_formal=None if cov_formal is None else cov_formal[ok],
        cov_d_blocks=None if cov_d_blocks is None else cov_d_blocks[ok],
        n_blocks=None if n_blocks is None else n_blocks[ok],
        gradient=grad[ok],
        from_cell=None if from_cell is None else np.asarray(from_cell, dtype=bool)[ok],
    )
    pairs = None
    if pair_cov is not None:  # the cells share one field: their errors are correlated
        new = np.cumsum(ok) - 1
        both = ok[near[:, 0]] & ok[near[:, 1]]
        pairs = (new[near[both]], pair_cov[both])
    res = _apply_sigma_scaling(
        res,
        sigma_scaling,
        sigma_regions,
        sigma_region_by,
        pairs,
        cells_floor=cells_floor,
        model_var=None if model_var is None else np.asarray(model_var)[ok],
    )
    log.info("windowed ICP: %d cells fitted%s, %.1f s", n_ok, skipped_cells_text(skipped),
             res.seconds)  # fmt: skip
    return res


#: points closer than this many cells to a detected breakline are left out of the final fit
DETECTED_GAP_CELLS = 0.3


def _cell_grid(cells, d, usable, n_rows, n_cols, x0, y0, cell):
    """The cells' motions ``d`` (K, 3) on their (n_rows, n_cols) grid (NaN where no cell),
    which cells are ``usable`` there, and the grid's column x and row y centres (map
    metres, rows north to south), for the detectors of :mod:`slipmap.core.breaklines`."""
    gd = np.full((n_rows, n_cols, 3), np.nan)
    gv = np.zeros((n_rows, n_cols), dtype=bool)
    gd[cells.row, cells.col] = d
    gv[cells.row, cells.col] = usable
    xs = x0 + (np.arange(n_cols) + 0.5) * cell
    ys = y0 - (np.arange(n_rows) + 0.5) * cell
    return gd, gv, xs, ys


def _detect_lines(
    cells, d, usable, cov_d, n_rows, n_cols, x0, y0, cell, *, grad=None, sig_grad=None
):
    """Breaklines of the cells' motions (:func:`slipmap.core.breaklines.detect_breaklines`)
    on the cell grid; None when none is found.

    ``grad`` (K, 3, 3): each cell's own gradient of its motion (a rigid cell's rotation,
    an affine cell's full gradient), so that the detector sees the edge of a block that
    rotates as a whole (its cells differ by the rotation, which their gradients explain);
    ``sig_grad`` (K, 3): the 1-sigma of the cells' rotation vectors (radians), the
    gradients' uncertainty. Both None: the step test alone."""
    from .breaklines import detect_breaklines

    gd, gv, xs, ys = _cell_grid(cells, d, usable, n_rows, n_cols, x0, y0, cell)
    gs = np.full((n_rows, n_cols), np.nan)
    gs[cells.row, cells.col] = np.sqrt(np.maximum(np.trace(cov_d, axis1=1, axis2=2), 0.0))
    kw = {}
    if grad is not None:
        gg = np.full((n_rows, n_cols, 3, 3), np.nan)
        gg[cells.row, cells.col] = grad
        gz = np.full((n_rows, n_cols), np.nan)
        gz[cells.row, cells.col] = cells.centres[:, 2]
        kw = dict(gradient=gg, z=gz)
        if sig_grad is not None:
            sg = np.full((n_rows, n_cols), np.nan)
            sg[cells.row, cells.col] = np.linalg.norm(sig_grad, axis=1)
            kw["sigma_gradient"] = sg
    found = detect_breaklines(gd, x=xs, y=ys, valid=gv, sigma=gs, **kw)
    if found is None:
        log.info("breaklines: none found in the cells' motions")
    else:
        log.info(
            "breaklines: %d found in the cells' motions (%.1f m in all)",
            len(found), found.length_m(),
        )  # fmt: skip
    return found


def candidate_lines(cells, d, usable, cov_formal, lattice, *, grad=None, sig_grad=None):
    """The breaklines the cells' motions propose, for the points to confirm: the edges of
    :func:`_detect_lines`, the straight step of :func:`_scan_line` (a fault across a lobe,
    which the edge test misses or follows only part of the way), or the straight step
    first and the edges second where most of the edges lie along it
    (:data:`SCAN_COVER_SHARE`). ``lattice``: ``(n_rows, n_cols, x0, y0, cell_m)``.
    Returns a list of ``(lines, straight step or None)`` to try in turn until the points
    confirm one (empty: none proposed); the one-file and the tiled run share it."""
    n_rows, n_cols, x0, y0, cell = lattice
    lines = _detect_lines(
        cells, d, usable, cov_formal, n_rows, n_cols, x0, y0, cell, grad=grad, sig_grad=sig_grad
    )
    straight = _scan_line(cells, d, usable, n_rows, n_cols, x0, y0, cell)
    return order_candidates(lines, straight, cell_m=cell)


def order_candidates(lines, straight, *, cell_m: float) -> list:
    """The candidates to try in turn (:func:`candidate_lines`) from the edge test's
    ``lines`` (Breaklines or None) and the scan's ``straight`` step (StraightStep or None):
    ``[(lines, None)]``, ``[(straight.line, straight)]``, both with the straight one first
    where the edges lie along it (:data:`SCAN_COVER_SHARE`), or ``[]``."""
    if straight is None:
        return [] if lines is None else [(lines, None)]
    if lines is None:
        return [(straight.line, straight)]
    from .breaklines import share_within

    along = share_within(lines, straight.line, SCAN_COVER_CELLS * cell_m)
    if along < SCAN_COVER_SHARE:
        return [(lines, None)]  # the edges lie elsewhere: another discontinuity
    log.info(
        "breaklines: %.0f %% of the edges' lines lie along the straight step: the straight "
        "line is the first candidate, the edges' the second", 100.0 * along,
    )  # fmt: skip
    return [(straight.line, straight), (lines, None)]


#: the straight scan's line is tried before the edge test's lines when this share of their
#: length lies within SCAN_COVER_CELLS cells of it (a rotating block's outline, two edge
#: lines at right angles, lies half along a straight line through one of its sides: 53 %
#: in tests/core/test_icp_choice.py's slump): one step seen both ways, which a
#: straight line across the data places better than a chain of cell edges that stops or
#: bends where the ground around the step deforms (a fault across a lobe in a survey larger
#: than the lobe; issue #29, stop 58); the edges' lines are tried next when the points drop
#: the straight one
SCAN_COVER_SHARE = 0.75
SCAN_COVER_CELLS = 1.5


#: a straight candidate cut to the stretch along which the field steps, or dropped on its
#: median jump alone, while its decisive points place a line turned by at least this much,
#: was judged station by station along the unturned line, which leaves the step where the
#: scan's direction is off (7.5°, its angle step, is 4.6 m over 35 m, about a cell): the
#: placed line, across the survey, is fitted and judged again (:func:`try_candidates`;
#: issue #29, stop 59: the ALS slab at a survey's extent). Candidates dropped because they
#: step along too little of their length (a lobe's flank) are not tried again
RETRY_TURN_DEG = 2.0
#: ... or whose line has an end this share of a cell or more off the candidate's line
#: (:func:`departure_m`), turned or not: the scan places its line on a lattice of offsets,
#: and a fault's field fitted along a candidate beside it steps by a fraction of the fault's
#: step at the candidate (the harness's TLS fault, 32 m, seed 5: the candidate 1.5 m beside
#: the fault and turned 1.5°, the field's median jump 0.074 m where the fault steps by 0.3 m,
#: dropped on it; fitted again along the points' line, 0.297 m; docs/fields.md, stop 62)
RETRY_DEPART_CELLS = 0.2


def departure_m(candidate, placed) -> float:
    """How far the straight line ``placed`` (Breaklines, one straight part) departs from the
    straight ``candidate`` (Breaklines) over its length: the larger distance of its two ends
    from the candidate's line (extended), metres."""
    c = np.asarray(candidate.parts[0], dtype=np.float64)
    p = np.asarray(placed.parts[0], dtype=np.float64)
    t = c[-1] - c[0]
    t = t / max(float(np.hypot(*t)), 1e-12)
    rel = p[[0, -1]] - c[0]
    return float(np.max(np.abs(t[0] * rel[:, 1] - t[1] * rel[:, 0])))


def confirm_lines(field, after, straight, *, before, tree, normals, gate_m, cell_m, again=True):
    """The candidate breaklines of a field fitted with them (``field.lines``), confirmed and
    placed by the points within a cell of them (``after``: at least those):
    :func:`~slipmap.core.breakline_points.place_straight_line` for a ``straight`` step
    (:func:`candidate_lines`), else :func:`~slipmap.core.icp_spline.refine_breaklines`.
    ``before``, ``tree``, ``normals``: epoch 1 around them (the one-file run's whole epoch,
    or a tiled run's corridor).

    Returns ``(lines, retry)``: the confirmed lines (None when none is), and, with
    ``again``, for a straight step cut to part of its length or dropped on its median jump
    alone, whose decisive points place a straight line turned by :data:`RETRY_TURN_DEG` or more
    from it or beside it (an end :data:`RETRY_DEPART_CELLS` of a cell or more off its line),
    that line across the scan's box as a new candidate (a
    :class:`~slipmap.core.breaklines.StraightStep`) to fit and judge in its place (None
    otherwise)."""
    from .breaklines import DETECT_FLOOR_M

    near_kw = dict(before=before, tree=tree, normals=normals, gate_m=gate_m, reach_m=cell_m)
    if straight is not None:
        from .breakline_points import place_straight_line
        from .breaklines import SCAN_MAX_JUMP_STEPS, SCAN_MIN_JUMP_STEPS

        step_m = float(np.linalg.norm(straight.step_m))
        placed = place_straight_line(
            field, after, station_jump_m=DETECT_FLOOR_M,
            min_jump_m=max(DETECT_FLOOR_M, SCAN_MIN_JUMP_STEPS * step_m),
            max_jump_m=SCAN_MAX_JUMP_STEPS * step_m, **near_kw,
        )  # fmt: skip
        retry = None
        moved = placed.on_points is not None and (
            abs(placed.turn_deg) >= RETRY_TURN_DEG
            or departure_m(field.lines, placed.on_points) >= RETRY_DEPART_CELLS * cell_m
        )  # fmt: skip
        if again and moved and (placed.cut or placed.line is None):
            retry = _across(straight, placed.on_points)
        return placed.line, retry
    from .icp_spline import refine_breaklines

    return refine_breaklines(field, after, min_jump_m=DETECT_FLOOR_M, **near_kw), None


def _across(straight, placed):
    """The straight step ``straight`` moved onto the line ``placed`` (one straight part, cut
    to part of the survey), drawn across the scan's box; None without a box."""
    import dataclasses

    from .breaklines import straight_across

    if straight.box_m is None or placed is None:
        return None
    e0, e1 = placed.parts[0][0], placed.parts[0][-1]
    line = straight_across(0.5 * (e0 + e1), e1 - e0, straight.box_m)
    if line is None:
        return None
    ang = float(np.degrees(np.arctan2(e1[1] - e0[1], e1[0] - e0[0]))) % 180.0
    return dataclasses.replace(straight, line=line, angle_deg=ang)


def try_candidates(tries, fit, confirm):
    """Fit the field with each candidate of ``tries`` (:func:`candidate_lines`) in turn and
    let the points confirm it, until they confirm one; the one-file and the tiled run share
    it. ``fit(lines)`` fits the field with candidate lines and returns the fit (its
    ``.field``); ``confirm(field, straight, again)`` is :func:`confirm_lines` on the
    run's points. A straight candidate placed on part of its length, or dropped, whose
    decisive points place a line turned from it or beside it (:data:`RETRY_TURN_DEG`,
    :data:`RETRY_DEPART_CELLS`) is fitted and
    judged once more along that line across the survey, and taken where the points confirm
    it there; else the cut line stands (or the candidate stays dropped).

    Returns ``(lines, first)``: the confirmed lines (None when none is) and the fit with
    the candidate they came from (the last one tried when none is; None without
    candidates), where the final fit starts."""
    lines = first = None
    for candidate, straight in tries:
        first = fit(candidate)
        lines, retry = confirm(first.field, straight, True)
        if retry is not None:
            log.info(
                "breaklines: the points place the straight candidate turned (%s): fitted "
                "again along their line, across the survey",
                "on part of it" if lines is not None else "it was dropped",
            )  # fmt: skip
            second = fit(retry.line)
            across, _ = confirm(second.field, retry, False)
            if across is not None:
                lines, first = across, second
        if lines is not None:
            break
    return lines, first


def _scan_line(cells, d, usable, n_rows, n_cols, x0, y0, cell):
    """The straight line across which the cells' motions step most clearly
    (:func:`slipmap.core.breaklines.scan_straight_step`), a candidate for the points to
    confirm; None when none is proposed."""
    from .breaklines import scan_straight_step

    gd, gv, xs, ys = _cell_grid(cells, d, usable, n_rows, n_cols, x0, y0, cell)
    found = scan_straight_step(gd, x=xs, y=ys, valid=gv)
    if found is not None:
        log.info(
            "breaklines: a straight step proposed at %.1f° (%.3f m, residuals %.3f m), for "
            "the points to confirm", found.angle_deg, float(np.linalg.norm(found.step_m)),
            found.rms_m,
        )  # fmt: skip
    return found


#: words for the reasons a cell is skipped (the keys of the ``skipped`` counts)
_SKIP_WORDS = {
    "few_before_points": "too few points in the first epoch",
    "few_after_points": "too few points in the second epoch",
    "icp_failed": "no usable ICP fit",
}


def skipped_cells_text(skipped: Dict[str, int]) -> str:
    """``, 3 skipped (1 with too few points in the second epoch, 2 …)`` ("" when none):
    the counts of skipped cells in words, for a log line."""
    parts = [f"{n} {_SKIP_WORDS.get(k, k.replace('_', ' '))}" for k, n in skipped.items() if n]
    if not parts:
        return ""
    total = sum(skipped.values())
    return f", {total} skipped ({'; '.join(parts)})"


def _scale_sigmas_by_region(
    res: WindowedICPResult, n_regions: int, by: str, pair_cov=None
) -> WindowedICPResult:
    """``res`` with covariances scaled by one variance factor per region (see windowed_icp).
    ``pair_cov``: as in :func:`_scale_sigmas`."""
    from .icp_sigma import REGION_INFLATION, quantile_regions, region_variance_factors

    sig = np.column_stack([res.sigma_dx, res.sigma_dy, res.sigma_dz])
    score = {
        "roughness": res.rmse,
        "density": res.n_after / (res.cell_m * res.cell_m),
        "sigma": np.linalg.norm(sig, axis=1),
    }[by]
    usable = np.asarray(res.converged, dtype=bool).copy()
    if np.size(res.flagged) == usable.size:  # (the columns of a tiled run are 0/1 ints)
        usable &= ~np.asarray(res.flagged, dtype=bool)
    region = quantile_regions(score, n_regions=n_regions, usable=usable)
    est = region_variance_factors(
        res.row,
        res.col,
        np.column_stack([res.dx, res.dy, res.dz]),
        sig,
        region,
        usable=usable,
        inflation=REGION_INFLATION,
        pair_covariance=pair_cov,
    )
    n_tested = int(est.n_cells.sum())
    res = replace(res, sigma_factor_estimate=est.field_factor, sigma_factor_cells=n_tested)
    if not math.isfinite(est.field_factor):
        log.warning(
            "only %d cells have 5 usable neighbours: the regions' variance factors cannot be "
            "estimated and the cells' sigmas are the formal ones (likely too small on real "
            "surfaces); use smaller cells or a larger area",
            n_tested,
        )
        return res
    f = np.maximum(1.0, est.cell_factor)
    log.info(
        "variance factors by %s region (%s): %s from %s cells",
        by,
        n_regions,
        np.round(np.maximum(1.0, est.factors), 2).tolist(),
        est.n_cells.tolist(),
    )
    scaled_cols = {
        k: getattr(res, k) * f
        for k in ("sigma_dx", "sigma_dy", "sigma_dz", "sigma_rx", "sigma_ry", "sigma_rz")
    }
    return replace(
        res,
        **scaled_cols,
        cov_d=res.cov_d * (f * f)[:, None, None],
        sigma_factor=float(np.median(f)),
        sigma_factor_cell=f,
        sigma_region_factors=tuple(float(v) for v in np.maximum(1.0, est.factors)),
        sigma_region=region,
    )


def _apply_sigma_scaling(
    res: WindowedICPResult,
    sigma_scaling: str,
    sigma_regions: int = 3,
    sigma_region_by: str = "roughness",
    pair_cov=None,
    cells_floor=None,
    model_var=None,
) -> WindowedICPResult:
    """``res`` with its covariances scaled as ``sigma_scaling`` says (see windowed_icp; the
    tiled run assembles its result and scales it here too). ``pair_cov``: the formal
    covariances between cells of a correlated field (spline), for the field's factor.
    With ``sigma_model="blocks"`` the cell-wide floor comes first and the field's factor
    after it is applied where it exceeds 1 (about 1 on lone-star's TLS cells; 1.3-2 on
    sparse airborne cells, whose block sigmas fell short)."""
    if sigma_scaling != "formal" and res.sigma_model == "blocks":
        res = _apply_floor(res, pair_cov, cells_floor, model_var)
    if sigma_scaling == "field":
        # with block sigmas the neighbour factor is applied only where it exceeds 1 (as for
        # any model): on lone-star (TLS) it is about 1 and changes little, but on sparse
        # airborne cells the block sigmas and the floor alone held 61-81 % of the errors
        # within 2 sigma (benchmarks/validate_landslides.py, 2026-11-27)
        return _scale_sigmas(res, pair_cov, apply=True)
    if sigma_scaling == "region":
        return _scale_sigmas_by_region(res, int(sigma_regions), sigma_region_by, pair_cov)
    return res


def _apply_floor(
    res: WindowedICPResult, pair_cov=None, cells_floor=None, model_var=None
) -> WindowedICPResult:
    """``res`` with each cell's covariance times ``a + n / n_cap`` (the cell-wide error its
    residuals cannot show, :func:`slipmap.core.icp_blocks.cell_floor`); ``pair_cov`` is
    kept (the floor is uncorrelated between cells). ``cells_floor``: the rigid cells' floor
    of the same run (a spline field): the multiplier is at least
    ``1 + SPLINE_FLOOR_SHARE (g_cells - 1)`` (:data:`~slipmap.core.icp_blocks.
    SPLINE_FLOOR_SHARE`) (an unweighted spline fit). ``model_var`` (K, 3): a weighted spline
    field's misfit to the rigid cells (:func:`spline_model_variance`), added to the
    variances after the floor (a model error does not scale with the residuals). The floor
    grows each cell by its surface share (:func:`~slipmap.core.icp_blocks.surface_share`,
    from the cells' residual RMS)."""
    from .icp_blocks import cell_floor, surface_share

    usable = np.asarray(res.converged, dtype=bool).copy()
    if np.size(res.flagged) == usable.size:
        usable &= ~np.asarray(res.flagged, dtype=bool)
    share = surface_share(res.rmse, usable)
    fl = cell_floor(
        res.row,
        res.col,
        np.column_stack([res.dx, res.dy, res.dz]),
        np.column_stack([res.sigma_dx, res.sigma_dy, res.sigma_dz]),
        res.n,
        usable=usable,
        pair_covariance=pair_cov,
        separated=_separated_neighbours(res),
        share=share,
    )
    res = replace(res, sigma_n_cap=fl.n_cap, sigma_floor_factor=fl.factor)
    if not math.isfinite(fl.factor):
        log.warning(
            "only %d cells have 5 usable neighbours: the cell-wide error cannot be estimated "
            "and the sigmas count only the residuals' correlation within each cell (likely "
            "too small on real surfaces); use smaller cells or a larger area",
            fl.n_cells,
        )
        if model_var is None:
            return res
    g = fl.scale(res.n, share)
    if cells_floor is not None and math.isfinite(cells_floor.factor):
        from .icp_blocks import SPLINE_FLOOR_SHARE

        g = np.maximum(g, 1.0 + SPLINE_FLOOR_SHARE * (cells_floor.scale(res.n) - 1.0))
    f = np.sqrt(g)
    scaled_cols = {
        k: getattr(res, k) * f
        for k in ("sigma_dx", "sigma_dy", "sigma_dz", "sigma_rx", "sigma_ry", "sigma_rz")
    }
    cov_d = res.cov_d * g[:, None, None]
    if model_var is not None:
        mv = np.where(np.isfinite(model_var), model_var, 0.0)
        cov_d = cov_d + mv[:, :, None] * np.eye(3)[None]
        sd = np.sqrt(np.diagonal(cov_d, axis1=1, axis2=2))
        scaled_cols.update(sigma_dx=sd[:, 0], sigma_dy=sd[:, 1], sigma_dz=sd[:, 2])
    return replace(res, **scaled_cols, cov_d=cov_d)


def _separated_neighbours(res: WindowedICPResult) -> Optional[np.ndarray]:
    """(K, 8) bool: True where the segment from a cell's centre to its neighbour's (in
    :func:`slipmap.core.fields.neighbour_variance_factor`'s order of the offsets) crosses
    one of the field's breaklines, given or detected (``res.breaklines``); None without
    lines. The neighbour tests of the sigmas leave such neighbours out: across a line the
    field may jump, and the jump is not the cells' error."""
    from .breaklines import crossings
    from .fields import _OFFSETS

    lines = res.breaklines
    if lines is None or getattr(lines, "empty", True) or not len(res.row):
        return None
    x0, y0 = res.origin_xy
    h = float(res.cell_m)
    cx = x0 + (res.col + 0.5) * h
    cy = y0 - (res.row + 0.5) * h  # rows run south
    off = np.asarray(_OFFSETS, dtype=np.float64)  # (8, 2): rows, columns
    p = np.repeat(np.column_stack([cx, cy]), 8, axis=0)
    q = p + np.tile(np.column_stack([off[:, 1] * h, -off[:, 0] * h]), (len(cx), 1))
    return (crossings(p, q, lines) > 0).reshape(len(cx), 8)


#: a cell component whose neighbour residual is more than this many of its (factor-scaled)
#: standard deviations takes the residual's excess as its own variance
#: (:func:`_widen_neighbour_outliers`); None: no such widening
NEIGHBOUR_OUTLIER_Z = 3.0


def _scale_sigmas(res: WindowedICPResult, pair_cov=None, apply: bool = True) -> WindowedICPResult:
    """``res`` with covariances scaled by the field's variance factor (see windowed_icp).
    ``pair_cov`` ((Q, 2) cell pairs, (Q, 3) covariances): the cells' formal errors are
    correlated (one spline field); neighbour agreement must know it. ``apply=False``: the
    factor is estimated and recorded only (a check of honest sigmas)."""
    from .fields import neighbour_variance_factor

    est = neighbour_variance_factor(
        res.row,
        res.col,
        np.column_stack([res.dx, res.dy, res.dz]),
        np.column_stack([res.sigma_dx, res.sigma_dy, res.sigma_dz]),
        usable=res.converged,
        pair_covariance=pair_cov,
        separated=_separated_neighbours(res),
    )
    res = replace(res, sigma_factor_estimate=est.factor, sigma_factor_cells=est.n_cells)
    if not math.isfinite(est.factor):
        log.warning(
            "only %d cells have 5 usable neighbours: the field's variance factor cannot be "
            "estimated and the cells' sigmas are the formal ones (likely too small on real "
            "surfaces); use smaller cells or a larger area",
            est.n_cells,
        )
        return res
    f = max(1.0, est.factor)
    if not apply:
        log.info(
            "check of the sigmas: the field's neighbour variance factor is %.2f from %d cells "
            "(1: honest; not applied)",
            est.factor,
            est.n_cells,
        )
        return res
    log.info(
        "field variance factor %.2f from %d cells: sigmas multiplied by %.2f",
        est.factor,
        est.n_cells,
        f,
    )
    scaled_cols = {
        k: getattr(res, k) * f
        for k in ("sigma_dx", "sigma_dy", "sigma_dz", "sigma_rx", "sigma_ry", "sigma_rz")
    }
    res = replace(res, **scaled_cols, cov_d=res.cov_d * (f * f), sigma_factor=f)
    return _widen_neighbour_outliers(res, est, f)


def _widen_neighbour_outliers(res: WindowedICPResult, est, f: float) -> WindowedICPResult:
    """``res`` (its sigmas already times ``f``) with the components that fail the neighbour
    test widened: where ``r² > z² f² var(r)`` (``z`` = NEIGHBOUR_OUTLIER_Z; ``est``: the
    :func:`~slipmap.core.fields.neighbour_variance_factor` of the unscaled sigmas), the
    cell's variance gains ``r² - z² f² var(r)``, the residual's excess over what the test
    accepts (nil at the threshold, so a cell just past it is not tripled; about ``r²`` for
    a cell far past it).

    One factor for the field fits its typical cell. A cell that straddles a discontinuity
    no line marks (a slump's outline, a scarp the detection missed) reports a blend of two
    motions; its own points fit that blend, so its sigma cannot show the error, but its
    neighbours disagree with it. The test's excess is a variance estimate with one degree
    of freedom, as a robust adjustment widens an observation that fails its test instead
    of trusting it (docs/fields.md, stop 56). Its neighbours' residuals carry a share of
    its error (``h_j`` of it, 1/8 with all eight present) and may be widened with it. A cell
    that reports its own fit instead of the field (``from_cell``) is not widened: it
    differs from the field's cells around it because its points refute the field there
    (tests/core/test_icp_choice.py: such cells 0.1-1 cm off, the field 1.2 cm)."""
    if NEIGHBOUR_OUTLIER_Z is None or est.variance is None:
        return res
    var = est.variance * (f * f)
    with np.errstate(invalid="ignore"):
        r2 = est.normalised**2 * var
        accepted = NEIGHBOUR_OUTLIER_Z**2 * var
        out = np.isfinite(r2) & (r2 > accepted)
    if res.from_cell is not None and np.size(res.from_cell) == len(out):
        # a cell that reports its own fit chose it because its points refute the field
        # there: its disagreement with the field's cells around it is theirs, not its own
        out &= ~np.asarray(res.from_cell, dtype=bool)[:, None]
    if not out.any():
        return res
    extra = np.where(out, r2 - accepted, 0.0)  # (K, 3), positive where out
    sig = np.column_stack([res.sigma_dx, res.sigma_dy, res.sigma_dz])
    wide = np.sqrt(sig**2 + extra)
    log.info(
        "%d cells disagree with their neighbours beyond %g sigma: their sigmas take the "
        "excess (%d components)",
        int(out.any(axis=1).sum()),
        NEIGHBOUR_OUTLIER_Z,
        int(out.sum()),
    )
    return replace(
        res,
        sigma_dx=wide[:, 0],
        sigma_dy=wide[:, 1],
        sigma_dz=wide[:, 2],
        cov_d=res.cov_d + extra[:, :, None] * np.eye(3)[None],
    )
