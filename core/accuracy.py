"""Point accuracy (PA): a 3x3 covariance per point (Kusari et al. 2019, Sec. II.E, Eq. 12-13).

Every model returns an ``(N, 3, 3)`` float64 array in m² in the map frame, ready for the
``sigma_before`` / ``sigma_after`` arguments of :func:`slipmap.core.adjustment.register_planes`
and :func:`slipmap.core.displacement.estimate_slip`:

* :func:`constant_covariance` - one isotropic sigma for all points;
* :func:`axis_covariance` - one sigma per map axis (Eq. 12, diagonal weights);
* :func:`columns_covariance` - per-point sigmas, e.g. from the LAS extra dimensions
  ``SigmaX`` / ``SigmaY`` / ``SigmaZ`` (reading them is :mod:`slipmap.core.io`'s job);
* :func:`georeferencing_covariance` - the *nominal* PA: first-order propagation of the GNSS
  position, IMU attitude, boresight, lever-arm, range and scan-angle variances through the
  LiDAR georeferencing equation (Glennie 2007), for kinematic (ALS / MLS) data;
* :func:`tls_covariance` - the nominal PA of a static (TLS) scan from a scanner position;
* :func:`footprint_covariance` - the *surface* term: the beam cone meets the local plane in an
  ellipse that the incidence angle stretches (Schaer et al. 2007; Bray et al.);
* :func:`total_covariance` - ``C_total = C_nominal + C_surface`` (Eq. 13).

:func:`covariance_to_sigmas` and :func:`covariance_to_six` turn covariances back into columns
(``SigmaX/Y/Z`` or the six unique entries) for LAS extra dimensions.

Frames and conventions (used consistently by every function here)
-----------------------------------------------------------------
* **Map frame**: a local Cartesian ENU frame, x = east, y = north, z = up (a projected CRS such
  as UTM with ellipsoidal heights is treated as ENU; meridian convergence is ignored).
* **Navigation (local-level) frame**: NED, x = north, y = east, z = down. ``T_ENU<-NED`` =
  ``[[0, 1, 0], [1, 0, 0], [0, 0, -1]]``.
* **Body (IMU) frame**: x forward, y right, z down. ``R_nav = Rz(heading) Ry(pitch) Rx(roll)``
  (aerospace z-y-x Euler angles, radians; heading clockwise from north).
* **Scanner frame**: aligned with the body frame up to the boresight rotation
  ``R_bs = Rz(b_z) Ry(b_y) Rx(b_x)`` (``boresight_rad = (b_x, b_y, b_z)``); the lever arm is the
  scanner origin minus the GNSS/IMU reference point, in the body frame (metres).
* **Scanner measurement** (a nadir-looking line scanner, ALS; also a profiler MLS head mounted
  looking down): ``r_s = range * (0, sin(scan), cos(scan))`` in the scanner frame, i.e. the
  beam sweeps in the body y-z plane, scan angle 0 = straight down, positive to the right.

Georeferencing equation::

    p = p_gnss + T_ENU<-NED @ R_nav(roll, pitch, heading) @ (R_bs @ r_s(range, scan) + lever_arm)

The Jacobian w.r.t. the 14 error sources ``[p_gnss (3), roll, pitch, heading, boresight (3),
lever arm (3), range, scan angle]`` is analytic (``dRx(t)/dt = Rx(t) [e_x]x`` etc.), evaluated for
all points at once; the covariance is ``C = J Σ Jᵀ`` with a diagonal ``Σ`` (the error sources are
uncorrelated and zero mean, as in the paper). It is checked against Monte Carlo in the tests.
Beam divergence is *not* added to the scan-angle variance: it is the footprint term.

Footprint (surface) model
-------------------------
A beam of full divergence ``γ`` at range ``ρ`` has radius ``w = ρ tan(γ/2)``. On a plane at
incidence angle ``θ`` (between the beam and the plane normal) it makes an ellipse with semi-axes
``a = w / cos θ`` (along the incidence direction) and ``b = w`` (across). A return may come from
anywhere on the footprint; with uniform illumination of the ellipse, the in-plane offset along the
incidence direction has variance ``a² / 4`` and the depth along the beam of that point is
``offset * sin θ``. The footprint thus spreads the measured range with standard deviation::

    σ_fp = ρ tan(γ/2) tan(θ) / 2

which is 0 at normal incidence and grows as ``tan θ``. Following the paper ("the 2-D ellipse
gives the covariance in the direction of the normal, which is then rotated to the map frame"),
the surface covariance is ``C_surface = σ_fp² n nᵀ`` with ``n`` the local plane normal in the map
frame (``direction="beam"`` puts it along the beam instead: ``σ_fp² u uᵀ``). ``θ`` is capped at
``max_incidence_deg`` (default 85°) so grazing returns stay finite.

Scanner specifications
----------------------
:data:`SCANNERS` holds nominal values for three instruments; they are *defaults to start from*,
not calibrations: use the numbers of your own system's calibration report where you have them
(:func:`scanner_spec_from_dict` reads a small JSON-like dict, keys with units in their names).

* ``riegl-vz400`` (MLS): RIEGL VZ-400 datasheet: range accuracy 5 mm (precision 3 mm), beam
  divergence 0.35 mrad, angular step resolution better than 0.0005° (used as the encoder σ).
  Mounting: boresight σ 0.005° per axis and lever-arm σ 5 mm (assumed, typical of a calibrated
  MLS mount).
* ``leica-als60`` (ALS): Leica ALS60 datasheet beam divergence 0.22 mrad (1/e²); range σ 2 cm,
  scan-angle encoder σ 0.001°, boresight σ 0.001° (roll, pitch) and 0.004° (heading), lever-arm
  σ 2 cm: assumed, of the order used by Glennie (2007) for ALS systems of that generation.
* ``optech-orion`` (ALS): Optech ALTM Orion beam divergence 0.25 mrad (1/e); range σ 1.5 cm,
  scan-angle σ 0.001°, boresight and lever-arm σ as the ALS60 (assumed, same source).

References: Glennie, C. (2007), Rigorous 3D error analysis of kinematic scanning LIDAR
systems, J. Appl. Geodesy 1, 147-157. Schaer, P., Skaloud, J., Landtwing, S., Legat, K. (2007),
Accuracy estimation for laser point cloud including scanning geometry, MMT 2007.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict

import numpy as np
from scipy.spatial import cKDTree

from slipmap.core.errors import InputDataError, InvalidParameterError

__all__ = [
    "SCANNERS",
    "ScannerSpec",
    "axis_covariance",
    "columns_covariance",
    "constant_covariance",
    "covariance_to_sigmas",
    "covariance_to_six",
    "footprint_covariance",
    "georeference_points",
    "georeferencing_covariance",
    "local_normals",
    "scanner_spec_from_dict",
    "tls_covariance",
    "total_covariance",
]

_CHUNK = 262_144  # points per vectorised block (memory bound, not a per-point loop)
T_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_SKEW = np.array(
    [
        [[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],  # [e_x]x
        [[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]],  # [e_y]x
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]],  # [e_z]x
    ]
)

# --------------------------------------------------------------------------- validation


def _count(name: str, n) -> int:
    try:
        k = int(n)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"{name} must be a non-negative integer, got {n!r}") from None
    if k != n or k < 0:
        raise InvalidParameterError(f"{name} must be a non-negative integer, got {n!r}")
    return k


def _sigmas(name: str, value, shape=None) -> np.ndarray:
    """Finite, non-negative float64 array (optionally broadcast to ``shape``)."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"{name} must be numeric, got {value!r}") from None
    if not np.all(np.isfinite(a)):
        raise InvalidParameterError(f"{name} contains NaN or infinite values")
    if np.any(a < 0):
        raise InvalidParameterError(f"{name} must be >= 0")
    if shape is not None:
        try:
            a = np.broadcast_to(a, shape)
        except ValueError:
            raise InvalidParameterError(
                f"{name} must broadcast to shape {shape}, got shape {a.shape}"
            ) from None
    return a


def _values(name: str, value, shape) -> np.ndarray:
    """Finite float64 array broadcast to ``shape`` (any sign)."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"{name} must be numeric, got {value!r}") from None
    if not np.all(np.isfinite(a)):
        raise InputDataError(f"{name} contains NaN or infinite values")
    try:
        return np.broadcast_to(a, shape)
    except ValueError:
        raise InvalidParameterError(
            f"{name} must have shape {shape} (or broadcast to it), got {a.shape}"
        ) from None


def _points(name: str, value) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputDataError(f"{name} must be an (N, 3) array, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputDataError(f"{name} contains NaN or infinite coordinates")
    return a


def _diag(var: np.ndarray) -> np.ndarray:
    """(N, 3) variances -> (N, 3, 3) diagonal covariances."""
    out = np.zeros(var.shape[:-1] + (3, 3))
    idx = np.arange(3)
    out[..., idx, idx] = var
    return out


# --------------------------------------------------------------------------- simple models


def constant_covariance(n: int, sigma_m: float) -> np.ndarray:
    """``(n, 3, 3)`` isotropic covariances ``sigma_m² I`` (sigma in metres, >= 0)."""
    n = _count("n", n)
    s = _sigmas("sigma_m", sigma_m)
    if s.ndim != 0:
        raise InvalidParameterError(f"sigma_m must be a scalar (metres), got shape {s.shape}")
    return _diag(np.full((n, 3), float(s) ** 2))


def axis_covariance(n: int, sigma_xyz_m) -> np.ndarray:
    """``(n, 3, 3)`` diagonal covariances from one sigma per map axis (Eq. 12), metres."""
    n = _count("n", n)
    s = _sigmas("sigma_xyz_m", sigma_xyz_m)
    if s.shape != (3,):
        raise InvalidParameterError(f"sigma_xyz_m must have shape (3,), got {s.shape}")
    return _diag(np.broadcast_to(s * s, (n, 3)))


def columns_covariance(sx, sy, sz) -> np.ndarray:
    """``(N, 3, 3)`` diagonal covariances from per-point sigmas (e.g. LAS ``SigmaX/Y/Z``).

    ``sx``, ``sy``, ``sz`` are (N,) arrays in metres (finite, >= 0) of the same length.
    """
    cols = [_sigmas(name, v) for name, v in (("sx", sx), ("sy", sy), ("sz", sz))]
    for name, c in zip(("sx", "sy", "sz"), cols):
        if c.ndim != 1:
            raise InvalidParameterError(f"{name} must be a 1-D per-point array, got {c.shape}")
    if not (cols[0].shape == cols[1].shape == cols[2].shape):
        raise InvalidParameterError(
            f"sx, sy, sz must have the same length, got {[c.shape[0] for c in cols]}"
        )
    s = np.stack(cols, axis=1)
    return _diag(s * s)


# --------------------------------------------------------------------------- scanner spec


@dataclass(frozen=True)
class ScannerSpec:
    """Stochastic specification of a scanner and its mount (SI units: metres, radians).

    Attributes
    ----------
    name : str
    range_sigma_m : float
        Range noise (1 σ).
    angle_sigma_rad : float
        Angular encoder noise (1 σ): the scan angle (kinematic) or each of the horizontal and
        vertical angles (static TLS).
    beam_divergence_rad : float
        Full beam divergence (footprint diameter / range).
    boresight_sigma_rad : (3,) float
        σ of the boresight angles (about scanner x, y, z).
    lever_arm_sigma_m : (3,) float
        σ of the lever-arm components (body x, y, z).
    lever_arm_m, boresight_rad : (3,) float
        Nominal lever arm and boresight angles (default 0; they barely change the covariance).
    """

    name: str
    range_sigma_m: float
    angle_sigma_rad: float
    beam_divergence_rad: float
    boresight_sigma_rad: tuple = (0.0, 0.0, 0.0)
    lever_arm_sigma_m: tuple = (0.0, 0.0, 0.0)
    lever_arm_m: tuple = field(default=(0.0, 0.0, 0.0))
    boresight_rad: tuple = field(default=(0.0, 0.0, 0.0))

    def __post_init__(self):
        for attr in ("range_sigma_m", "angle_sigma_rad", "beam_divergence_rad"):
            v = _sigmas(attr, getattr(self, attr))
            if v.ndim != 0:
                raise InvalidParameterError(f"{attr} must be a scalar, got shape {v.shape}")
            object.__setattr__(self, attr, float(v))
        for attr in ("boresight_sigma_rad", "lever_arm_sigma_m"):
            v = _sigmas(attr, getattr(self, attr), (3,))
            object.__setattr__(self, attr, tuple(float(x) for x in v))
        for attr in ("lever_arm_m", "boresight_rad"):
            try:
                v = _values(attr, getattr(self, attr), (3,))
            except InputDataError as exc:
                raise InvalidParameterError(str(exc)) from None
            object.__setattr__(self, attr, tuple(float(x) for x in v))
        object.__setattr__(self, "name", str(self.name))


_DEG = math.pi / 180.0

SCANNERS: Dict[str, ScannerSpec] = {
    "riegl-vz400": ScannerSpec(
        name="riegl-vz400",
        range_sigma_m=0.005,
        angle_sigma_rad=0.0005 * _DEG,
        beam_divergence_rad=0.35e-3,
        boresight_sigma_rad=(0.005 * _DEG,) * 3,
        lever_arm_sigma_m=(0.005,) * 3,
    ),
    "leica-als60": ScannerSpec(
        name="leica-als60",
        range_sigma_m=0.02,
        angle_sigma_rad=0.001 * _DEG,
        beam_divergence_rad=0.22e-3,
        boresight_sigma_rad=(0.001 * _DEG, 0.001 * _DEG, 0.004 * _DEG),
        lever_arm_sigma_m=(0.02,) * 3,
    ),
    "optech-orion": ScannerSpec(
        name="optech-orion",
        range_sigma_m=0.015,
        angle_sigma_rad=0.001 * _DEG,
        beam_divergence_rad=0.25e-3,
        boresight_sigma_rad=(0.001 * _DEG, 0.001 * _DEG, 0.004 * _DEG),
        lever_arm_sigma_m=(0.02,) * 3,
    ),
}

# quantity -> (kind, vector?)
_SPEC_FIELDS = {
    "range_sigma": ("length", False),
    "angle_sigma": ("angle", False),
    "beam_divergence": ("angle", False),
    "boresight_sigma": ("angle", True),
    "lever_arm_sigma": ("length", True),
    "lever_arm": ("length", True),
    "boresight": ("angle", True),
}
_UNITS = {
    "length": {"m": 1.0, "cm": 0.01, "mm": 0.001},
    "angle": {"rad": 1.0, "mrad": 1e-3, "urad": 1e-6, "deg": _DEG},
}
_SI = {"length": "m", "angle": "rad"}


def scanner_spec_from_dict(d: dict) -> ScannerSpec:
    """A :class:`ScannerSpec` from a JSON-like dict with units in the key names.

    Keys are ``<quantity>_<unit>``: quantities ``range_sigma``, ``angle_sigma``,
    ``beam_divergence`` (scalars), ``boresight_sigma``, ``lever_arm_sigma``, ``lever_arm``,
    ``boresight`` (a scalar for all three axes or a list of 3); length units ``m``, ``cm``,
    ``mm``; angle units ``rad``, ``mrad``, ``urad``, ``deg``. ``name`` (optional) names the spec
    and ``base`` (optional) names an entry of :data:`SCANNERS` whose values the other keys
    override. Without ``base``, ``range_sigma``, ``angle_sigma`` and ``beam_divergence`` are
    required. Example: ``{"name": "my-mls", "range_sigma_mm": 5, "angle_sigma_deg": 0.0005,
    "beam_divergence_mrad": 0.35, "boresight_sigma_deg": 0.005, "lever_arm_sigma_m": 0.005}``.

    Raises
    ------
    InvalidParameterError
        Unknown keys, a unit that does not fit the quantity, a quantity given twice, a missing
        required quantity, an unknown ``base`` or a bad value.
    """
    if not isinstance(d, dict):
        raise InvalidParameterError(f"scanner spec must be a dict, got {type(d).__name__}")
    values: dict = {}
    name = d.get("name", None)
    base = d.get("base", None)
    if base is not None:
        if base not in SCANNERS:
            raise InvalidParameterError(
                f"scanner spec 'base' must be one of {sorted(SCANNERS)}, got {base!r}"
            )
        b = SCANNERS[base]
        values = {q: getattr(b, f"{q}_{_SI[k]}") for q, (k, _) in _SPEC_FIELDS.items()}
        name = name if name is not None else b.name
    seen = set()
    for key, raw in d.items():
        if key in ("name", "base"):
            continue
        quantity, unit = None, None
        for q in sorted(_SPEC_FIELDS, key=len, reverse=True):
            if key.startswith(q + "_"):
                quantity, unit = q, key[len(q) + 1 :]
                break
        if quantity is None:
            raise InvalidParameterError(
                f"unknown scanner spec key {key!r}; known quantities: {sorted(_SPEC_FIELDS)} "
                "with a unit suffix (e.g. range_sigma_m, beam_divergence_mrad)"
            )
        kind, vector = _SPEC_FIELDS[quantity]
        if unit not in _UNITS[kind]:
            raise InvalidParameterError(
                f"scanner spec key {key!r}: unit {unit!r} is not a {kind} unit; use one of "
                f"{sorted(_UNITS[kind])}"
            )
        if quantity in seen:
            raise InvalidParameterError(f"scanner spec gives {quantity!r} more than once")
        seen.add(quantity)
        try:
            v = np.asarray(raw, dtype=np.float64) * _UNITS[kind][unit]
        except (TypeError, ValueError):
            raise InvalidParameterError(
                f"scanner spec {key!r} must be numeric, got {raw!r}"
            ) from None
        if vector:
            if v.shape not in ((), (3,)):
                raise InvalidParameterError(
                    f"scanner spec {key!r} must be a number or a list of 3, got shape {v.shape}"
                )
            v = tuple(float(x) for x in np.broadcast_to(v, (3,)))
        else:
            if v.shape != ():
                raise InvalidParameterError(f"scanner spec {key!r} must be a single number")
            v = float(v)
        values[quantity] = v
    missing = [q for q in ("range_sigma", "angle_sigma", "beam_divergence") if q not in values]
    if missing:
        raise InvalidParameterError(
            f"scanner spec is missing {missing} (e.g. 'range_sigma_m'); or give a 'base' scanner"
        )
    kw = {f"{q}_{_SI[_SPEC_FIELDS[q][0]]}": v for q, v in values.items()}
    return ScannerSpec(name=str(name if name is not None else "custom"), **kw)


# --------------------------------------------------------------------------- georeferencing


def _rot(axis: int, t: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices about body axis ``axis`` (0 x, 1 y, 2 z) by angles ``t``."""
    c, s = np.cos(t), np.sin(t)
    out = np.zeros(np.shape(t) + (3, 3))
    i, j = [(1, 2), (0, 2), (0, 1)][axis]
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    if axis == 1:  # Ry = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        out[..., i, j] = s
        out[..., j, i] = -s
    else:
        out[..., i, j] = -s
        out[..., j, i] = s
    return out


def _kinematic_inputs(roll, pitch, heading, range_m, scan_angle_rad):
    r = np.asarray(range_m, dtype=np.float64)
    if r.ndim != 1:
        raise InputDataError(f"range_m must be a 1-D (N,) array, got shape {r.shape}")
    n = r.shape[0]
    rng = _values("range_m", r, (n,))
    if np.any(rng < 0):
        raise InputDataError("range_m must be >= 0 (metres)")
    angles = [
        _values(nm, v, (n,))
        for nm, v in (
            ("roll", roll),
            ("pitch", pitch),
            ("heading", heading),
            ("scan_angle_rad", scan_angle_rad),
        )
    ]
    return n, rng, angles


def _scanner_vector(rng, scan):
    return rng[:, None] * np.stack([np.zeros_like(scan), np.sin(scan), np.cos(scan)], axis=1)


def georeference_points(
    *,
    platform_xyz,
    roll,
    pitch,
    heading,
    range_m,
    scan_angle_rad,
    lever_arm_m=(0.0, 0.0, 0.0),
    boresight_rad=(0.0, 0.0, 0.0),
) -> np.ndarray:
    """Map (ENU) coordinates of the returns by the georeferencing equation (module docstring).

    ``platform_xyz`` (N, 3) map coordinates of the GNSS/IMU reference point; ``roll``,
    ``pitch``, ``heading``, ``scan_angle_rad`` (N,) radians; ``range_m`` (N,) metres;
    ``lever_arm_m`` (3,) or (N, 3) body frame metres; ``boresight_rad`` (3,) or (N, 3).
    """
    n, rng, (ro, pi, he, sc) = _kinematic_inputs(roll, pitch, heading, range_m, scan_angle_rad)
    p0 = _values("platform_xyz", platform_xyz, (n, 3))
    la = _values("lever_arm_m", lever_arm_m, (n, 3))
    bs = _values("boresight_rad", boresight_rad, (n, 3))
    r_bs = _rot(2, bs[:, 2]) @ _rot(1, bs[:, 1]) @ _rot(0, bs[:, 0])
    r_nav = _rot(2, he) @ _rot(1, pi) @ _rot(0, ro)
    v = np.einsum("nij,nj->ni", r_bs, _scanner_vector(rng, sc)) + la
    return p0 + np.einsum("ij,njk,nk->ni", T_ENU_NED, r_nav, v)


def georeferencing_jacobian(*, roll, pitch, heading, range_m, scan_angle_rad, spec: ScannerSpec):
    """``(N, 3, 14)`` Jacobian of the georeferenced point w.r.t. the error sources.

    Columns: position x, y, z (map), roll, pitch, heading, boresight x, y, z, lever arm x, y, z
    (body), range, scan angle. Analytic; evaluated at the nominal boresight and lever arm of
    ``spec``.
    """
    n, rng, (ro, pi, he, sc) = _kinematic_inputs(roll, pitch, heading, range_m, scan_angle_rad)
    bs = np.asarray(spec.boresight_rad)
    la = np.asarray(spec.lever_arm_m)
    bx, by, bz = (_rot(a, np.asarray(bs[a])) for a in range(3))
    r_bs = bz @ by @ bx
    rx, ry, rz = _rot(0, ro), _rot(1, pi), _rot(2, he)
    m = T_ENU_NED @ (rz @ ry @ rx)  # body -> map, (N, 3, 3)
    rs = _scanner_vector(rng, sc)  # (N, 3) scanner frame
    v = rs @ r_bs.T + la  # body frame vector
    jac = np.zeros((n, 3, 14))
    jac[:, :, 0:3] = np.eye(3)
    # attitude: d(Rz Ry Rx)/d(roll) = Rz Ry Rx [ex]x, d/d(pitch) = Rz Ry [ey]x Rx,
    # d/d(heading) = Rz [ez]x Ry Rx (a rotation commutes with its own generator)
    jac[:, :, 3] = np.einsum("nij,jk,nk->ni", m, _SKEW[0], v)
    rxv = np.einsum("nij,nj->ni", rx, v)
    t_rz_ry = T_ENU_NED @ (rz @ ry)
    jac[:, :, 4] = np.einsum("nij,jk,nk->ni", t_rz_ry, _SKEW[1], rxv)
    jac[:, :, 5] = np.einsum(
        "ij,nj->ni", T_ENU_NED @ _SKEW[2], np.einsum("nij,nj->ni", rz @ ry, rxv)
    )
    # boresight: the same structure on R_bs = Bz By Bx acting on r_s
    jac[:, :, 6] = np.einsum("nij,jk,nk->ni", m, r_bs @ _SKEW[0], rs)
    jac[:, :, 7] = np.einsum("nij,jk,nk->ni", m, bz @ by @ _SKEW[1] @ bx, rs)
    jac[:, :, 8] = np.einsum("nij,jk,nk->ni", m, _SKEW[2] @ r_bs, rs)
    # lever arm
    jac[:, :, 9:12] = m
    # range and scan angle
    drs_drange = np.stack([np.zeros_like(sc), np.sin(sc), np.cos(sc)], axis=1)
    drs_dscan = rng[:, None] * np.stack([np.zeros_like(sc), np.cos(sc), -np.sin(sc)], axis=1)
    jac[:, :, 12] = np.einsum("nij,jk,nk->ni", m, r_bs, drs_drange)
    jac[:, :, 13] = np.einsum("nij,jk,nk->ni", m, r_bs, drs_dscan)
    return jac


def georeferencing_covariance(
    *,
    platform_xyz=None,
    roll,
    pitch,
    heading,
    range_m,
    scan_angle_rad,
    sigma_position_m,
    sigma_attitude_rad,
    spec: ScannerSpec,
) -> np.ndarray:
    """Nominal point covariance of kinematic LiDAR by first-order propagation (Glennie 2007).

    Parameters
    ----------
    platform_xyz : (N, 3) float or None
        Trajectory positions at each point's time (map ENU). The covariance does not depend on
        them (the equation is linear in the position); only used to check N when given.
    roll, pitch, heading : (N,) float
        Attitude at each point's time, radians (see the module docstring for conventions).
    range_m, scan_angle_rad : (N,) float
        Measured range (m) and scan angle (rad, 0 = nadir, positive to the right).
    sigma_position_m : (N, 3) or (3,) float
        σ of the trajectory position in the **map frame**: x = east, y = north, z = up (a
        trajectory file's N, E, D sigmas must be reordered to E, N, D; the sign of an axis does
        not change a σ).
    sigma_attitude_rad : (N, 3) or (3,) float
        σ of roll, pitch, heading (radians).
    spec : ScannerSpec
        Range, scan-angle, boresight and lever-arm σ and the nominal boresight / lever arm.

    Returns
    -------
    (N, 3, 3) float64
        ``C = J Σ Jᵀ`` in m² (map frame).
    """
    if not isinstance(spec, ScannerSpec):
        raise InvalidParameterError(f"spec must be a ScannerSpec, got {type(spec).__name__}")
    n, rng, (ro, pi, he, sc) = _kinematic_inputs(roll, pitch, heading, range_m, scan_angle_rad)
    if platform_xyz is not None:
        _values("platform_xyz", platform_xyz, (n, 3))
    sp = _sigmas("sigma_position_m", sigma_position_m, (n, 3))
    sa = _sigmas("sigma_attitude_rad", sigma_attitude_rad, (n, 3))
    out = np.empty((n, 3, 3))
    for lo in range(0, n, _CHUNK):  # chunks of points bound the (chunk, 3, 14) Jacobian
        sl = slice(lo, min(lo + _CHUNK, n))
        jac = georeferencing_jacobian(
            roll=ro[sl], pitch=pi[sl], heading=he[sl], range_m=rng[sl], scan_angle_rad=sc[sl],
            spec=spec,
        )  # fmt: skip
        s = np.empty((jac.shape[0], 14))
        s[:, 0:3] = sp[sl]
        s[:, 3:6] = sa[sl]
        s[:, 6:9] = spec.boresight_sigma_rad
        s[:, 9:12] = spec.lever_arm_sigma_m
        s[:, 12] = spec.range_sigma_m
        s[:, 13] = spec.angle_sigma_rad
        js = jac * s[:, None, :]
        out[sl] = np.einsum("nik,njk->nij", js, js)
    return out


# --------------------------------------------------------------------------- TLS


def tls_covariance(
    points, scanner_position, spec: ScannerSpec, *, position_sigma_m=0.0
) -> np.ndarray:
    """Nominal covariance of a static scan from its scanner position.

    Polar measurement: ``p = s + ρ (cos e cos a, cos e sin a, sin e)`` (map ENU; ``a`` the
    horizontal angle from +x, ``e`` the elevation), with independent errors in ``ρ``
    (``spec.range_sigma_m``), ``a`` and ``e`` (each ``spec.angle_sigma_rad``) and optionally in
    the scanner position (``position_sigma_m``, scalar or (3,), map axes). Range error lies
    along the line of sight; angular errors across it (``ρ cos e σ_a`` horizontally,
    ``ρ σ_e`` vertically).
    """
    if not isinstance(spec, ScannerSpec):
        raise InvalidParameterError(f"spec must be a ScannerSpec, got {type(spec).__name__}")
    p = _points("points", points)
    s = _values("scanner_position", scanner_position, (3,))
    if np.asarray(scanner_position).shape != (3,):
        raise InvalidParameterError("scanner_position must have shape (3,)")
    ps = _sigmas("position_sigma_m", position_sigma_m, (3,))
    d = p - s
    rho = np.linalg.norm(d, axis=1)
    if np.any(rho == 0):
        raise InputDataError("points coincide with scanner_position (range 0)")
    u = d / rho[:, None]
    horiz = np.hypot(d[:, 0], d[:, 1])
    az = np.arctan2(d[:, 1], d[:, 0])
    el = np.arctan2(d[:, 2], horiz)
    ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
    ja = rho[:, None] * np.stack([-ce * sa, ce * ca, np.zeros_like(az)], axis=1)
    je = rho[:, None] * np.stack([-se * ca, -se * sa, ce], axis=1)
    sr2, sg2 = spec.range_sigma_m**2, spec.angle_sigma_rad**2
    cov = (
        sr2 * np.einsum("ni,nj->nij", u, u)
        + sg2 * np.einsum("ni,nj->nij", ja, ja)
        + sg2 * np.einsum("ni,nj->nij", je, je)
    )
    return cov + np.diag(ps * ps)


# --------------------------------------------------------------------------- footprint


def local_normals(points, k_neighbours: int = 12) -> np.ndarray:
    """(N, 3) unit normals of the local plane through each point's ``k`` nearest neighbours.

    The eigenvector of the smallest eigenvalue of the neighbours' covariance (batched
    ``eigh``); the sign is arbitrary.
    """
    p = _points("points", points)
    k = _count("k_neighbours", k_neighbours)
    if k < 3:
        raise InvalidParameterError(f"k_neighbours must be >= 3, got {k_neighbours!r}")
    if p.shape[0] < k:
        raise InputDataError(f"need at least k_neighbours={k} points, got {p.shape[0]}")
    q = p - p.mean(axis=0)
    tree = cKDTree(q)
    out = np.empty_like(q)
    for lo in range(0, q.shape[0], _CHUNK):  # chunks bound the (chunk, k, 3) neighbour array
        sl = slice(lo, min(lo + _CHUNK, q.shape[0]))
        _, idx = tree.query(q[sl], k=k, workers=-1)
        nb = q[idx]  # (chunk, k, 3)
        nb = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", nb, nb) / k
        _, vec = np.linalg.eigh(cov)
        out[sl] = vec[:, :, 0]
    return out


def footprint_covariance(
    points,
    sensor_positions,
    spec: ScannerSpec,
    *,
    k_neighbours: int = 12,
    normals=None,
    direction: str = "normal",
    max_incidence_deg: float = 85.0,
) -> np.ndarray:
    """Surface (footprint) covariance of each point, map frame (module docstring).

    Parameters
    ----------
    points : (N, 3)
    sensor_positions : (N, 3) or (3,)
        Scanner origin at each shot (kinematic: the georeferenced scanner position; TLS: the
        scanner position).
    spec : ScannerSpec
        Its ``beam_divergence_rad`` (full angle) is used.
    k_neighbours : int
        Neighbours for the local plane when ``normals`` is not given.
    normals : (N, 3), optional
        Local surface normals (any length and sign, normalised here).
    direction : {"normal", "beam"}
        Put ``σ_fp²`` along the local normal (the paper's model, default) or along the beam.
    max_incidence_deg : float
        Incidence angles are capped here (0 < value < 90).

    Returns
    -------
    (N, 3, 3) float64
        ``σ_fp² n nᵀ`` with ``σ_fp = ρ tan(γ/2) tan(θ) / 2``.
    """
    if not isinstance(spec, ScannerSpec):
        raise InvalidParameterError(f"spec must be a ScannerSpec, got {type(spec).__name__}")
    if direction not in ("normal", "beam"):
        raise InvalidParameterError(f"direction must be 'normal' or 'beam', got {direction!r}")
    try:
        cap = float(max_incidence_deg)
    except (TypeError, ValueError):
        cap = float("nan")
    if not 0.0 < cap < 90.0:
        raise InvalidParameterError(
            f"max_incidence_deg must be in (0, 90) degrees, got {max_incidence_deg!r}"
        )
    p = _points("points", points)
    n = p.shape[0]
    s = _values("sensor_positions", sensor_positions, (n, 3))
    if normals is None:
        nrm = local_normals(p, k_neighbours)
    else:
        nrm = _values("normals", normals, (n, 3))
        length = np.linalg.norm(nrm, axis=1)
        if np.any(length == 0):
            raise InputDataError("normals contains zero-length vectors")
        nrm = nrm / length[:, None]
    d = p - s
    rho = np.linalg.norm(d, axis=1)
    if np.any(rho == 0):
        raise InputDataError("points coincide with sensor_positions (range 0)")
    u = d / rho[:, None]
    cos_t = np.clip(np.abs(np.einsum("ni,ni->n", u, nrm)), math.cos(math.radians(cap)), 1.0)
    tan_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0)) / cos_t
    sigma = 0.5 * rho * math.tan(0.5 * spec.beam_divergence_rad) * tan_t
    axis = nrm if direction == "normal" else u
    return (sigma * sigma)[:, None, None] * np.einsum("ni,nj->nij", axis, axis)


def footprint_sigma(range_m, incidence_rad, beam_divergence_rad) -> np.ndarray:
    """The analytic footprint σ ``ρ tan(γ/2) tan(θ) / 2`` (metres), for reference and tests."""
    r = np.asarray(range_m, dtype=np.float64)
    t = np.asarray(incidence_rad, dtype=np.float64)
    return 0.5 * r * np.tan(0.5 * float(beam_divergence_rad)) * np.tan(t)


# --------------------------------------------------------------------------- combine / export


def _covs(name: str, c) -> np.ndarray:
    a = np.asarray(c, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (3, 3):
        raise InvalidParameterError(f"{name} must be an (N, 3, 3) covariance array, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputDataError(f"{name} contains NaN or infinite values")
    return a


def total_covariance(*parts) -> np.ndarray:
    """``C_total = Σ parts`` (Eq. 13: ``C_nominal + C_surface``); all (N, 3, 3), same N."""
    if not parts:
        raise InvalidParameterError("total_covariance needs at least one (N, 3, 3) part")
    arrs = [_covs(f"part {i}", c) for i, c in enumerate(parts)]
    ns = {a.shape[0] for a in arrs}
    if len(ns) != 1:
        raise InvalidParameterError(
            f"total_covariance parts must have the same N, got {[a.shape[0] for a in arrs]}"
        )
    out = arrs[0].copy()
    for a in arrs[1:]:
        out += a
    return out


def covariance_to_sigmas(cov) -> np.ndarray:
    """(N, 3) ``sqrt`` of the diagonals (``SigmaX/Y/Z``, metres)."""
    c = _covs("cov", cov)
    return np.sqrt(np.maximum(np.diagonal(c, axis1=1, axis2=2), 0.0))


def covariance_to_six(cov) -> np.ndarray:
    """(N, 6) unique entries ``xx, yy, zz, xy, xz, yz`` (m²), e.g. for LAS extra dimensions."""
    c = _covs("cov", cov)
    return np.stack(
        [c[:, 0, 0], c[:, 1, 1], c[:, 2, 2], c[:, 0, 1], c[:, 0, 2], c[:, 1, 2]], axis=1
    )
