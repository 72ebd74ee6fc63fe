"""Acquisition units whose error drifts along the acquisition time (GpsTime).

The "full" stochastic model (:mod:`.stochastic`) gives each acquisition unit (an MLS pass, an
ALS strip, a TLS setup) one random rigid translation ``s_u ~ N(0, σ_e² I₃)``. A mobile
mapper's trajectory error is not rigid over a pass: the INS/GNSS solution drifts over tens of
seconds, so one pass that crosses the fault carries one error on one side and another on the
other. A rigid unit error then cancels in the relative slip and its σ, while the drift does
not (issue #30: a renovated MLS pair 8.3σ off with the random tilt, docs/accuracy.md).

The drift of unit ``u`` is modelled on a linear B-spline ("hat") basis in time with knots
every ``Δ`` seconds (absolute GpsTime, so that both sides of a fault, adjusted apart, give the
same knot the same id)::

    s_u(t) = Σ_k B_k(t / Δ) c_uk,        c_uk ~ N(0, σ_e² I₃) independent

A plane's points average it: plane ``j`` moves along its normal by ``n_jᵀ Σ_uk z_juk c_uk``
with ``z_juk = (1 / n_j) Σ_{i ∈ j, unit u} B_k(t_i / Δ)`` (exact for the basis: the average of
a linear combination is the combination of the averages). Each (unit, knot) is a "virtual
unit" whose share ``z_juk`` takes the place of the unit share of the rigid model in ``Z_e``,
so the covariance algebra (dense, sparse with Woodbury, across sides by unit id) is the
rigid model's. Two points of one unit ``|t − t'|`` apart are correlated as
``Σ_k B_k(t) B_k(t')``: 1 at one knot, 0 beyond ``Δ``; the variance is ``σ_e²`` at the knots
and ``σ_e²/2`` midway (a low-rank approximation of a stationary drift, as a spline is). With
``Δ = ∞`` every point of a unit shares one coefficient: the rigid model exactly.

``Δ`` is chosen by restricted likelihood (:func:`.stochastic.estimate_components`) among
:data:`UNIT_INTERVALS_S` and ``∞``; a drift must beat the rigid unit by
:data:`UNIT_INTERVAL_MARGIN` in −2 log L to be taken. A TLS setup registered as a rigid body
keeps ``∞`` (docs/accuracy.md, "Acquisition units that drift along GpsTime").

Hand-written: the shares are a weighted ``bincount``; no library computes block averages of
a spline basis per plane and unit.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

import numpy as np

from .errors import InputDataError, InvalidParameterError

#: knot spacings (seconds) of the drift tried by restricted likelihood beside the rigid unit
#: (Δ = ∞). A mobile mapper at 5-15 m/s covers 15-360 m in them; an INS/GNSS trajectory
#: error decorrelates over tens of seconds (docs/accuracy.md)
UNIT_INTERVALS_S: Tuple[float, ...] = (3.0, 6.0, 12.0, 24.0)
#: −2 log L by which a drift must beat the rigid unit (as FAMILY_MARGIN for the spatial
#: family): four candidate spacings, one chosen by the noise of a few dozen planes
UNIT_INTERVAL_MARGIN = 2.0
#: the knot index is stored in the low 32 bits of a virtual unit id (offset by 2**31)
_KNOT_BITS = 32
_KNOT_OFFSET = 1 << 31
#: unit ids must fit beside it in an int64
_UNIT_LIMIT = 1 << 30


def check_unit_time(time_s, n: int, name: str) -> Optional[np.ndarray]:
    """(n,) float64 acquisition time of each point (GpsTime, seconds), or None.

    Raises :class:`InputDataError` for a wrong shape or non-finite times."""
    if time_s is None:
        return None
    t = np.asarray(time_s)
    if t.shape != (n,):
        raise InputDataError(
            f"{name} must have one GPS time per point, shape ({n},); got {t.shape}"
        )
    if not np.issubdtype(t.dtype, np.number) or np.issubdtype(t.dtype, np.complexfloating):
        raise InputDataError(f"{name} must hold numbers (seconds), got {t.dtype}")
    t = t.astype(np.float64, copy=False)
    if not np.all(np.isfinite(t)):
        raise InputDataError(f"{name} holds NaN or infinite GPS times; give finite seconds")
    return t


def virtual_unit_ids(unit: np.ndarray, knot: np.ndarray) -> np.ndarray:
    """(N,) int64 id of the virtual unit (``unit``, ``knot``): both sides of a fault give the
    same pair the same id."""
    u = np.asarray(unit, dtype=np.int64)
    k = np.asarray(knot, dtype=np.int64) + _KNOT_OFFSET
    if u.size and (int(u.min()) < -_UNIT_LIMIT or int(u.max()) >= _UNIT_LIMIT):
        raise InputDataError(
            f"acquisition unit ids must lie within ±{_UNIT_LIMIT} for a drift along GpsTime; "
            "renumber the units"
        )
    if k.size and (int(k.min()) < 0 or int(k.max()) >= (1 << _KNOT_BITS)):
        raise InputDataError("GPS times too large for the drift's knots; give seconds")
    return (u << _KNOT_BITS) | k


def _hat_terms(unit: np.ndarray, time_s, interval_s: float):
    """The hat basis's non-zero terms of each point: virtual unit id, weight ``B_v(t_i)``
    and the point's index, two terms a point (its knots ``⌊t/Δ⌋`` and the next), one for
    ``math.inf`` (the unit itself, weight 1)."""
    n = unit.size
    if math.isinf(interval_s):
        return unit, np.ones(n), np.arange(n)
    x = np.asarray(time_s, dtype=np.float64) / float(interval_s)
    k = np.floor(x)
    w = x - k
    k = k.astype(np.int64)
    vid = np.concatenate([virtual_unit_ids(unit, k), virtual_unit_ids(unit, k + 1)])
    return vid, np.concatenate([1.0 - w, w]), np.concatenate([np.arange(n), np.arange(n)])


def hat_unit_shares(
    plane: np.ndarray,
    unit: np.ndarray,
    time_s: np.ndarray,
    count: np.ndarray,
    *,
    interval_s: float,
) -> Tuple[np.ndarray, np.ndarray]:
    """Share of each plane's points per virtual unit (unit, knot) of a drift along time.

    Parameters
    ----------
    plane : (N,) int64
        Plane index of each point, 0 .. b-1 (``b = len(count)``).
    unit : (N,) int64
        Acquisition unit of each point.
    time_s : (N,) float64 or None
        Its acquisition time, seconds (GpsTime); not read for ``math.inf``.
    count : (b,) float64
        Points per plane (the denominator of the shares; at least the points given).
    interval_s : float
        Knot spacing ``Δ`` of the hat basis, seconds (> 0); ``math.inf``: one knot per unit,
        the rigid unit's shares.

    Returns
    -------
    shares : (b, V) float64
        ``z_jv = (1 / n_j) Σ_{i ∈ j} B_v(t_i)``; each row sums to the share of its plane's
        points given (1 when ``count`` counts them all).
    ids : (V,) int64
        The virtual units' ids (:func:`virtual_unit_ids`; the unit id itself for ``∞``),
        sorted, those with a non-zero column only.
    """
    plane = np.asarray(plane, dtype=np.int64)
    unit = np.asarray(unit, dtype=np.int64)
    b = int(np.asarray(count).size)
    denom = np.maximum(np.asarray(count, dtype=np.float64), 1.0)
    if not (interval_s > 0):
        raise InvalidParameterError(f"interval_s must be > 0 seconds, got {interval_s!r}")
    vid, wt, take = _hat_terms(unit, time_s, interval_s)
    idx = plane[take]
    ids, inv = np.unique(vid, return_inverse=True)
    nv = ids.size
    if nv == 0:
        return np.zeros((b, 0)), ids
    cnt = np.bincount(idx * nv + inv.ravel(), weights=wt, minlength=b * nv).reshape(b, nv)
    keep = cnt.sum(axis=0) > 0
    return cnt[:, keep] / denom[:, None], ids[keep]


def hat_unit_shares_reference(plane, unit, time_s, count, *, interval_s):
    """Slow reference of :func:`hat_unit_shares`: a loop over points and the two knots
    around each, a dict of columns."""
    cols = {}
    b = len(count)
    for p, u, t in zip(np.asarray(plane), np.asarray(unit), np.asarray(time_s, dtype=float)):
        if math.isinf(interval_s):
            terms = [(int(u), 1.0)]
        else:
            k = math.floor(t / interval_s)
            w = t / interval_s - k
            terms = [
                (int(virtual_unit_ids(np.array([u]), np.array([k]))[0]), 1.0 - w),
                (int(virtual_unit_ids(np.array([u]), np.array([k + 1]))[0]), w),
            ]
        for vid, wt in terms:
            cols.setdefault(vid, np.zeros(b))[int(p)] += wt
    ids = np.array(sorted(v for v, c in cols.items() if c.sum() > 0), dtype=np.int64)
    if ids.size == 0:
        return np.zeros((b, 0)), ids
    out = np.column_stack([cols[int(v)] for v in ids])
    return out / np.maximum(np.asarray(count, dtype=float), 1.0)[:, None], ids


def hat_unit_tilt_shares(
    plane: np.ndarray,
    unit: np.ndarray,
    time_s: Optional[np.ndarray],
    offsets_m: np.ndarray,
    normals: np.ndarray,
    ids: np.ndarray,
    *,
    interval_s: float,
) -> np.ndarray:
    """Tilt of each plane's least-squares fit per unit of drift along its normal, per virtual
    unit: the tilt shares beside :func:`hat_unit_shares`' offset shares.

    A drift that changes along a plane tilts it as well as moving it. With the drift along
    the plane's normal ``f_i = Σ_v B_v(t_i) a_v`` at its points, the least-squares plane fit's
    gradient is ``g = M⁺ Σ_i ũ_i f_i`` (``ũ_i`` the point's offset from the plane's
    centroid projected into the plane, ``M = Σ ũ_i ũ_iᵀ`` of rank 2), the rotation that
    tilts the plane so is ``g × n`` (in the plane: a rotation about the normal tilts
    nothing), so each virtual unit ``v`` tilts plane ``j`` by ``Ω_jv a_v`` with::

        Ω_jv = (M_j⁺ Σ_{i ∈ j} ũ_i B_v(t_i)) × n_j        (radians per metre of drift)

    Parameters
    ----------
    plane, unit, time_s, interval_s
        As :func:`hat_unit_shares` (``time_s`` not read for ``math.inf``).
    offsets_m : (N, 3) float64
        Each point's offset from its plane's centroid (the centroid of the points given of
        that plane), metres.
    normals : (b, 3) float64
        Unit plane normals.
    ids : (V,) int64
        The virtual units of the columns (:func:`hat_unit_shares`' ``ids``).

    Returns
    -------
    (b, V, 3) float64
        ``Ω_jv``, rad/m; zero for a plane whose points do not span two directions.
    """
    plane = np.asarray(plane, dtype=np.int64)
    unit = np.asarray(unit, dtype=np.int64)
    nrm = np.asarray(normals, dtype=np.float64)
    b, nv = nrm.shape[0], int(np.asarray(ids).size)
    if not (interval_s > 0):
        raise InvalidParameterError(f"interval_s must be > 0 seconds, got {interval_s!r}")
    u = np.asarray(offsets_m, dtype=np.float64)
    n_i = nrm[plane]
    u = u - n_i * np.einsum("ij,ij->i", u, n_i)[:, None]  # into the plane
    # each plane's scatter in the plane and its pseudo-inverse (rank 2; a plane whose points
    # are collinear keeps the rank its points give)
    m = np.zeros((b, 3, 3))
    for k in range(3):
        for q in range(k, 3):
            m[:, k, q] = m[:, q, k] = np.bincount(plane, u[:, k] * u[:, q], minlength=b)
    lam, vec = np.linalg.eigh(m)
    big = lam > 1e-9 * np.maximum(lam[:, -1:], 1e-300)
    inv = np.where(big, 1.0 / np.where(big, lam, 1.0), 0.0)
    m_pinv = np.einsum("bij,bj,bkj->bik", vec, inv, vec)
    vid, wt, take = _hat_terms(unit, time_s, interval_s)
    idx, uu = plane[take], u[take]
    ids = np.asarray(ids, dtype=np.int64)
    col = np.searchsorted(ids, vid)
    ok = (col < nv) & (ids[np.minimum(col, max(nv - 1, 0))] == vid) if nv else np.zeros(0, bool)
    s = np.zeros((b, nv, 3))
    if nv:
        flat = idx[ok] * nv + col[ok]
        for k in range(3):
            s[:, :, k] = np.bincount(flat, wt[ok] * uu[ok, k], minlength=b * nv).reshape(b, nv)
    g = np.einsum("bik,bvk->bvi", m_pinv, s)
    return np.cross(g, nrm[:, None, :])


def hat_unit_tilt_shares_reference(plane, unit, time_s, offsets_m, normals, ids, *, interval_s):
    """Slow reference of :func:`hat_unit_tilt_shares`: per plane and virtual unit, the drift
    ``B_v(t_i)`` along the normal at the plane's points, a least-squares plane fit to it
    (``lstsq`` on an offset and two in-plane axes), and the rotation that tilts the plane so
    (``g × n``)."""
    plane = np.asarray(plane)
    normals = np.asarray(normals, dtype=float)
    b, nv = normals.shape[0], len(ids)
    out = np.zeros((b, nv, 3))
    for j in range(b):
        sel = np.flatnonzero(plane == j)
        if sel.size < 3:
            continue
        n = normals[j]
        ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        e1 = np.cross(n, ref)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        uu = np.asarray(offsets_m, dtype=float)[sel]
        a = np.column_stack([np.ones(sel.size), uu @ e1, uu @ e2])
        for v, vid in enumerate(ids):
            f = np.zeros(sel.size)
            for i_, i in enumerate(sel):
                u_, t = int(unit[i]), None if time_s is None else float(time_s[i])
                if math.isinf(interval_s):
                    f[i_] = 1.0 if u_ == vid else 0.0
                    continue
                k = math.floor(t / interval_s)
                w = t / interval_s - k
                for kk, ww in ((k, 1.0 - w), (k + 1, w)):
                    if int(virtual_unit_ids(np.array([u_]), np.array([kk]))[0]) == vid:
                        f[i_] += ww
            coef = np.linalg.lstsq(a, f, rcond=None)[0]
            g = coef[1] * e1 + coef[2] * e2
            out[j, v] = np.cross(g, n)
    return out
