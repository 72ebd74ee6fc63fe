"""Plane-level stochastic model of planar registration: variance components, REML, robust tests.

Why a plane level. Each matched plane contributes hundreds to tens of thousands of point
conditions per epoch. Errors that are common to a plane's points — trajectory drift over
the plane, an ALS strip or TLS setup offset, a surface that is not quite flat, edge effects —
do not shrink with the number of points. Under a white (independent point) model a plane's
mean misclosure has a variance ``σ²/n``: a 3 mm common error is then tens of "σ", data
snooping rejects good planes, and the slip's σ stays ~1/√(points) however large the common
error (see ``shared/docs/honest-slip.md`` and issue #13).

The model. One random effect per plane ``δ_j`` on its after-epoch conditions (the before
epoch's common error is absorbed by the plane's free offset ``d_j``, so ``δ_j`` is the
difference of the two epochs' common errors along the plane normal)::

    Cov(δ) = σ_p² I                                     plane component (nugget)
           + σ_c² ρ̄_jk(a) n_jᵀ n_k                       spatial (spherical, range a)
           + σ_b² Z_b Z_bᵀ + σ_a² Z_a Z_aᵀ               acquisition units, before / after

``ρ`` is a correlation family chosen by the data (:class:`SpatialKernel`: spherical,
exponential, Gaussian, the "wave" hole effect with negative lobes, or "wave_h", the hole
effect of a field of the horizontal position; all positive definite in 3-D and of compact
support, the long-tailed ones tapered), each at its range ``a``.
The spatial part is a smooth 3-D error FIELD ``s(p)`` (trajectory drift:
each axis a stationary process of variance ``σ_c²``) seen along each plane's normal and
AVERAGED over the plane, ``δ_j = n_jᵀ mean_{p ∈ j} s(p)``: hence the factor ``n_jᵀ n_k`` (a
Schur product of two positive semi-definite matrices, so positive semi-definite) and the
change of support (block-to-block covariance, Journel & Huijbregts 1978 §II.E) ``ρ̄_jk =
Σ_s Σ_t w_js w_kt ρ(|p_js − p_kt|; a)`` over sample points ``p`` of each plane with weights
``w`` (:class:`PlaneModel` ``samples``; :func:`effective_samples` picks per plane and range
the coarsest grid whose cells are at most ``a/4`` across, so a plane less than ``a/2`` across
is its centroid and this is the centroid model ``ρ(|c_j − c_k|)``). A ground piece of 150 m
under a field of 20 m range averages the field over many correlation lengths: the centroid
model gave it the variance of a 10 m roof, the GLS then weighted the few horizontal planes
alike and the vertical followed the roofs' errors (issue #30 item 3). A scalar
field along the normals would not be physical: the sign of a normal is a convention.
``Z_e`` (planes × 3·units) holds,
for plane ``j`` and unit ``u`` of epoch ``e``, the share of the plane's epoch-``e`` points from
that unit times the plane normal: a random rigid translation ``s_u ~ N(0, σ_e² I₃)`` per unit
and epoch moves the plane along its normal by ``n_jᵀ s_u``. A unit's error is a rigid motion:
a TLS setup registered to 2 mm and 0.05 mrad also turns about the instrument, moving a
facade 40 m away by 2 mm more. With a lever ``L`` (:attr:`PlaneModel.unit_lever_m`, chosen
by REML from :data:`UNIT_LEVERS_M` or none) each unit also turns, ``ω_u ~ N(0, (σ_e/L)²
I₃)`` about its origin ``o_u`` (the centroid of the planes and contrast rows it holds),
and ``Z_e`` gains three columns per unit, the share times ``(c_j − o_u) × n_j / L``.

Reduction to a plane-level GLS. :mod:`.adjustment` carries ``δ_j`` as an eleventh column of
the after-epoch rows and eliminates each plane's own parameters (``a, b, c, d`` with the unit
normal constraint). What is left per plane is a 7x7 block over the motion ``x`` (6) and
``δ_j``. Its ``δ`` row defines a scalar plane observation ``y_j = q_j / D_j`` with design row
``h_j = c_j / D_j`` and white variance ``p_j = σ0² / D_j``, and ``T = Σ (G_xx − c cᵀ / D)`` is
the information on the motion that the plane's tilt gives whatever its offset. Eliminating
``δ`` with the prior ``δ ~ N(0, Σ_δ)`` gives (Woodbury, with ``V = Σ_δ + diag(p)``)::

    N_red = T / σ0² + H V⁻¹ Hᵀ        r_red = r_T / σ0² + H V⁻¹ y        δ̂ = Σ_δ V⁻¹ (y − Hᵀ x)

With ``Σ_δ = 0`` this is the white model's reduced system exactly.

A random tilt per plane (:data:`RANDOM_TILT`, on by default). ``T`` is a sum over planes of
rank-2 blocks on the rotation, ``T_j = E_j C_j⁻¹ E_jᵀ`` (``C_j`` the point-noise covariance of
the plane's tilt on two axes ``E_j`` in the plane; the translation is not in it: with the
offset free a translation only moves a plane along its normal). A survey-error field tilts
each plane too (3 mm over 40 m: 0.1 mrad), so its tilt is not point-noise precise: with a
random tilt ``τ_j ~ N(0, σ_t² I₂)``, white across planes, each block becomes ``E_j (C_j + σ_t²
I₂)⁻¹ E_jᵀ = T_j (I + σ_t² T_j)⁻¹`` (:func:`tilt_information`). ``σ_t²`` is estimated by
REML from the planes' tilt misclosures (:func:`estimate_tilt_variance`, with a χ² test of each
plane's tilt) in each robust round, after the offsets' components; ``components={"tilt_rad":
σ_t}`` holds it fixed. With ``σ_t = 0`` the system is the one above exactly.

Estimation of the components (:func:`estimate_components`). The point-level factor ``σ0²``
is the a-posteriori variance factor of the point residuals once each plane's ``δ̂`` is
removed (redundancy ≈ points − 5 planes − 6). The plane-level components are estimated by
restricted maximum likelihood (REML) on the plane misclosures, with the iterated
MINQUE / Helmert–Förstner fixed point (Fisher scoring of the REML score, Koch 1999 §3.6;
Förstner 1979): ``F θ = q`` with ``F_ik = ½ tr(Π V_i Π V_k)``, ``q_i = ½ eᵀ Π V_i Π e
− ½ tr(Π V_i Π V₀)`` and ``Π = V⁻¹ − V⁻¹ X (Xᵀ V⁻¹ X + T)⁻¹ Xᵀ V⁻¹`` (the tilt information
``T`` enters as prior information on the motion). Negative solutions are set to zero and that
component removed (the non-negative fixed point). The positive components are then tested
together against none (:func:`_test_plane_level`, a likelihood ratio against χ²_k given the
k estimates that left their boundary, :data:`COMPONENT_TEST_ALPHA`; with a spatial component
whose range was profiled, also against Davies' bound for that search, :func:`search_p_value`)
and all set to zero when the misclosures show no error beyond the point noise. The standard
deviation of each component is from ``F⁻¹``. The family and range ``a`` are chosen by
profile REML over a geometric grid of ranges per family (least −2 log L; another family
than the spherical one must beat it by :data:`FAMILY_MARGIN`; by default the spherical
family and the horizontal wave, :data:`DEFAULT_FAMILIES`).
The profile can be made with the motion a free fixed effect of the offsets alone (the tilts'
information left out, :data:`REML_TILT_SHARE` 0: the field tilts the planes, and tilts held
as precise pin the rotation to a biased value whose lever-arm trend REML reads as a long
range), the components' values then estimated at that kernel with the tilts; not the
default, as it makes the σ too small under trajectory drift (docs/accuracy.md). Components
whose Fisher information is nil (e.g. one acquisition unit covering the whole side: its
error is a translation of the whole side, indistinguishable from the motion) are not
estimable: they keep the prior the caller gives (default: left out, with a note).

Robustness (:func:`plane_tests`). Plane misclosures are tested with the w-test of correlated
observations ``w_j = (Π e)_j / √Π_jj`` — against the plane-level spread (the components), not
the white point noise. Planes beyond ``k_reject`` are rejected; planes between ``k_weight`` and
``k_reject`` are down-weighted by the IGG-III weight, applied as an inflation of their
variance in ``V``. The first pass starts from a robust scale (a MAD of the misclosures;
among many imprecise planes each standardised by its own white part: :func:`_mad_scale`) so that
gross outliers (renovated buildings) cannot inflate the components and mask themselves.

Cost. Dense ``V`` (planes × planes) with one Cholesky per Gauss–Helmert iteration, and
REML on at most :data:`VCE_MAX_PLANES` planes (beyond, the spatially contiguous block of
planes nearest to a seeded random plane: the components are global scalars, which a few
hundred planes pin down well, and a contiguous block keeps the close plane pairs that the
spatial component is seen in). The spatial term's pairs are pairs of plane samples within
the range (a k-d tree over the samples), so large planes add samples, not planes².
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.spatial import cKDTree
from scipy.special import j0

from .errors import InputDataError, InvalidParameterError
from .unit_contrasts import ContrastRows, union_rows
from .unit_drift import UNIT_INTERVAL_MARGIN

log = logging.getLogger(__name__)

__all__ = [
    "COMPONENT_NAMES",
    "STOCHASTIC_MODELS",
    "DEFAULT_STOCHASTIC_MODEL",
    "Component",
    "VarianceComponents",
    "check_components",
    "check_random_tilt",
    "check_stochastic_model",
    "cross_covariance",
    "joint_covariance",
    "JointComponents",
    "PlaneGain",
    "spherical_correlation",
    "SpatialKernel",
    "SPATIAL_FAMILIES",
    "DEFAULT_FAMILIES",
    "as_kernel",
    "RANDOM_TILT",
    "TiltEstimate",
    "tilt_information",
    "tilts_given_offsets",
    "estimate_tilt_variance",
    "tilts_marginal",
    "tilt_gains",
]

#: the models: "white" = independent point errors only (the study's model, data snooping
#: against the white σ); "plane" = white + one random offset per plane; "full" = plane +
#: spatially correlated offsets + rigid errors per acquisition unit (where units are given)
STOCHASTIC_MODELS = ("white", "plane", "full")
DEFAULT_STOCHASTIC_MODEL = "full"
#: plane-level components, in the order of the estimation vector
COMPONENT_NAMES = ("plane", "spatial", "unit_before", "unit_after")
DENSE_MAX_PLANES = 1500  # dense V (Cholesky) up to this many planes, sparse + Woodbury beyond
VCE_MAX_PLANES = 200  # REML on a spatially contiguous subset of planes beyond this
VCE_MAX_CONTRASTS = 300  # REML on a seeded subset of the unit contrast rows beyond this
#: the variance (m²) of the unit contrast rows' own misfit, estimated by REML beside the
#: components when the rows are there (:mod:`.unit_contrasts`); not a survey component
CONTRAST_NUGGET = "contrast"
#: levers (metres) of a unit's turn about its origin that REML may choose
#: (:attr:`PlaneModel.unit_lever_m`): a unit's error is a rigid motion, a translation ``s``
#: and a turn ``ω`` about the unit's points' centroid ``o``, moving a plane at ``c`` by
#: ``nᵀ(s + ω × (c − o))`` with ``ω ~ N(0, (σ_e / L)² I₃)``: a TLS setup registered to
#: 2 mm and 0.05 mrad has ``L`` = 40 m, an ALS strip of 1 cm with a 0.17 mrad roll 60 m.
#: The likeliest is taken when it beats the translation alone by
#: :data:`.unit_drift.UNIT_INTERVAL_MARGIN` in −2 log L (docs/accuracy.md, "Units that
#: turn")
UNIT_LEVERS_M: Tuple[float, ...] = (15.0, 30.0, 60.0, 120.0)
#: whether REML may choose a lever (False: the units translate only, as before stop 44)
UNIT_TURN = True
MIN_PLANES_VCE = 15  # fewer planes than this cannot pin the plane component down
K_WEIGHT = 3.0  # |w| above which a plane is down-weighted (IGG-III)
K_REJECT_MIN = 4.0  # |w| above which a plane is rejected (at least; Bonferroni may raise it)
GROSS_MAD = 8.0  # first pass: misclosures beyond this many robust std are gross outliers
VCE_MAX_ITER = 40
VCE_TOL = 2e-3  # relative change of the components at which REML stops
N_RANGES = 6  # spatial ranges tried by profile REML
#: share of the planes' tilt information REML takes as prior information on the motion when it
#: profiles the kernel (0: the kernel is chosen from the offsets alone, see
#: :func:`estimate_components`). 1 by default: the tilt-free profile gets the field kind's
#: vertical right (1.98 -> 0.33 mm) but makes the σ too small on trajectory drift (the
#: renovated kind pooled RMS(err/σ) 0.81 -> 1.85 in sample; docs/accuracy.md, "Spatial
#: correlation family and range chosen by the data"); the random tilt per plane
#: (:data:`RANDOM_TILT`) reconciles both, with the units' drift along GpsTime
#: (:mod:`.unit_drift`) for the σ under trajectory drift (docs/accuracy.md)
REML_TILT_SHARE = 1.0
_FLOOR = 1e-14  # m², numerical floor of a variance component
#: a random tilt per plane (:func:`tilt_information`, :func:`estimate_tilt_variance`): the
#: survey-error field tilts each plane, so its tilt information is not point-noise precise;
#: when True the adjustment estimates the tilt variance σ_t² (rad²) from the planes' tilt
#: misclosures and weighs each plane's tilt by ``(C_j + σ_t² I₂)⁻¹`` (docs/accuracy.md,
#: "A random tilt per plane"). The default since the units' drift along GpsTime
#: (:mod:`.unit_drift`) keeps the σ honest under trajectory drift: on 30 pairs of each of
#: issue #30's kinds it is within sampling of ICP's error or better on all seven, and no
#: pair's σ is 8 times too small any more (docs/accuracy.md, "Acquisition units that drift
#: along GpsTime")
RANDOM_TILT = True
#: whether the plane-level components (REML) and the plane tests use the tilts weighed by
#: the random tilt (True) or point-noise precise (False: the random tilt in the motion only)
REML_RANDOM_TILT = True
TILT_MAX_ITER = 200  # Helmert / Förstner iterations of the tilt variance
TILT_TOL = 1e-4  # relative change of the tilt variance at which they stop
#: a tilt variance below this share of the planes' median point-noise tilt variance is nil
TILT_NEGLIGIBLE = 1e-6
MIN_PLANES_TILT = 6  # fewer planes than this: the tilt variance is not estimated
TILT_ALPHA = 0.01  # family-wise level of the test of the planes' tilts (Bonferroni)
#: level of the test of the plane-level components together against none
#: (:func:`_test_plane_level`; ``None``: every positive REML value is kept, the positive part)
COMPONENT_TEST_ALPHA: Optional[float] = 0.05


def check_stochastic_model(model: str, *, option: str = "stochastic_model") -> str:
    """Return ``model`` if it is one of :data:`STOCHASTIC_MODELS`, else raise."""
    if model not in STOCHASTIC_MODELS:
        raise InvalidParameterError(
            f"{option} must be one of {', '.join(STOCHASTIC_MODELS)}; got {model!r}"
        )
    return model


def check_random_tilt(random_tilt: Optional[bool], model: str) -> Optional[bool]:
    """``random_tilt`` as a bool (None stays None: the default, :data:`RANDOM_TILT`); raise
    when it is asked of the white model, which has no plane level to tilt."""
    if random_tilt and model == "white":
        raise InvalidParameterError(
            "random_tilt needs a plane-level stochastic model (plane or full): the white model "
            "has no plane-level components"
        )
    return None if random_tilt is None else bool(random_tilt)


def check_components(components: Optional[Mapping[str, float]], *, option: str = "components"):
    """Validate fixed components ``{name: sigma_m, "spatial_range_m": a, "spatial_family":
    family, "tilt_rad": σ_t}`` (the family one of :data:`SPATIAL_FAMILIES`; a range without it
    is spherical; ``tilt_rad`` the random tilt per plane, radians, :data:`RANDOM_TILT`);
    returns a dict."""
    if components is None:
        return {}
    out = {}
    names = COMPONENT_NAMES + ("spatial_range_m", "spatial_family", "tilt_rad")
    for k, v in dict(components).items():
        if k in ("unit_interval_s", "unit_lever_m"):
            # a side's drift and turn held by its strips / windows / tiles
            try:
                f = float(v)
            except (TypeError, ValueError):
                f = float("nan")
            if not f > 0:
                what = (
                    "seconds (inf: rigid units)" if k == "unit_interval_s"
                    else "metres (inf: units that translate only)"
                )  # fmt: skip
                raise InvalidParameterError(f"{option}: {k} must be > 0 {what}; got {v!r}")
            out[k] = f
            continue
        if k not in names:
            raise InvalidParameterError(
                f"{option}: unknown component {k!r}; use {', '.join(names)}"
            )
        if k == "spatial_family":
            if v not in SPATIAL_FAMILIES:
                raise InvalidParameterError(
                    f"{option}: spatial_family must be one of {', '.join(SPATIAL_FAMILIES)};"
                    f" got {v!r}"
                )
            out[k] = str(v)
            continue
        try:
            f = float(v)
        except (TypeError, ValueError):
            unit = "radians" if k == "tilt_rad" else "metres"
            raise InvalidParameterError(f"{option}: {k} must be a number ({unit})") from None
        if not math.isfinite(f) or f < 0 or (k == "spatial_range_m" and f <= 0):
            raise InvalidParameterError(
                f"{option}: {k} must be a finite number {'> 0' if k.endswith('_m') else '>= 0'}"
                f" ({'radians' if k == 'tilt_rad' else 'metres'}); got {v!r}"
            )
        out[k] = f
    return out


def check_units(unit, n: int, name: str) -> Optional[np.ndarray]:
    """(n,) int64 acquisition unit per point (PointSourceId, trajectory segment, TLS setup),
    or None; ``name`` is the option as the caller spells it."""
    if unit is None:
        return None
    u = np.asarray(unit)
    if u.shape != (n,):
        raise InputDataError(
            f"{name} must have one acquisition unit per point, shape ({n},); got {u.shape}"
        )
    if u.size and not np.issubdtype(u.dtype, np.integer):
        raise InputDataError(f"{name} must hold integer unit ids, got {u.dtype}")
    return u.astype(np.int64, copy=False)


def spherical_correlation(h: np.ndarray, range_m: float) -> np.ndarray:
    """Spherical correlation ``1 − 1.5 h/a + 0.5 (h/a)³`` for ``h < a``, else 0 (any shape)."""
    r = np.minimum(np.asarray(h, dtype=np.float64) / range_m, 1.0)
    return 1.0 - 1.5 * r + 0.5 * r**3


#: families of the spatial correlation (:class:`SpatialKernel`)
SPATIAL_FAMILIES = ("spherical", "exponential", "gaussian", "wave", "wave_h")
#: the families REML chooses from by default: the spherical one and the horizontal wave
#: ("wave_h", since stop 45: a field of the map position whose lobes cancel over large
#: planes; on the short-wavelength kind RMS(err/σ) ∥ 0.63 → 0.84, docs/accuracy.md "A field
#: of the horizontal position"). The 3-D "wave" is not chosen even for a wave field with the
#: tilts in the profile (docs/accuracy.md); pass ``families=("spherical", "wave")`` with
#: :data:`REML_TILT_SHARE` 0 for the tilt-free choice measured there. The exponential and
#: Gaussian ones differ from the spherical one in the shape near the origin only, which a
#: few dozen planes hardly see; each family costs a profile of REML fits, so they are
#: offered through ``families=`` and ``spatial_family``.
DEFAULT_FAMILIES = ("spherical", "wave_h")
#: the families whose range is a wavelength (their own grid of candidates,
#: :func:`_candidate_ranges`; reports name it so)
WAVELENGTH_FAMILIES = ("wave", "wave_h")
#: taper of the families without compact support, in units of their range (wavelength)
TAPER_RANGES = {"spherical": 1.0, "exponential": 2.0, "gaussian": 2.0, "wave": 3.0, "wave_h": 3.0}
#: −2 log L by which another family must beat the spherical one to be chosen (a family with
#: negative lobes averages a large plane's error away: it has to be seen in the data, not
#: chosen by the noise of a few dozen planes)
FAMILY_MARGIN = 2.0
N_WAVELENGTHS = 8  # wavelengths tried by profile REML for the "wave" and "wave_h" families


@dataclass(frozen=True)
class SpatialKernel:
    """Correlation of the spatial term: a family and its range (metres).

    Every family is positive definite in 3-D and of compact support (so the sparse path of
    :class:`CovarianceOperator` holds for all): the ones without it are multiplied by a
    spherical taper of range ``TAPER_RANGES[family] × range_m`` (the product of two positive
    definite functions is positive definite, Schur's product theorem; covariance tapering,
    Furrer, Genton & Nychka 2006)::

        spherical    1 − 1.5 r + 0.5 r³                  r = h / a, zero beyond a
        exponential  exp(−3 h / a) · sph(h; 2a)          a: practical range (5 %)
        gaussian     exp(−3 (h / a)²) · sph(h; 2a)
        wave         sin(2π h / λ) / (2π h / λ) · sph(h; 3λ)      λ = range_m, a wavelength
        wave_h       J0(2π h_xy / λ) · sph(h_xy; 3λ)              h_xy the horizontal distance

    The "wave" (hole-effect, cardinal sine) family is the correlation of a field made of
    plane waves of ONE wavelength λ in every 3-D direction (its spectrum is uniform on the
    sphere ``|k| = 2π/λ``): positive definite in up to three dimensions, NOT a valid
    correlation in four or more, and its negative lobe (−0.22 at 0.72 λ) is the deepest an
    isotropic 3-D correlation can have (the cosine ``cos(2π h/λ)`` with lobes of −1 is valid in
    1-D only, ``J0`` of the 2-D waves of a horizontal field in 2-D only). The taper damps the
    lobes beyond the first two, as a spread of wavelengths does. It is the family of a survey
    error that oscillates over tens of metres (a smooth drift of short wavelength): averaged
    over a plane several wavelengths across it nearly cancels, which a family without
    negative lobes cannot express (the spherical one then fits a long range, and a large
    ground plane keeps most of the field's variance).

    The "wave_h" family is the correlation of a field of the HORIZONTAL position made of
    plane waves of one wavelength in every horizontal direction (``J0``, lobe −0.40 at
    0.61 λ): a function of the map distance only, so positive definite on 3-D points, and
    the same error for a wall's foot and its top. A mobile or airborne survey's error is
    where the platform was when it saw a point, and the points it sees at one moment lie on
    one vertical more than on one sphere: averaged over a ground piece several wavelengths
    across, such a field cancels far more than a 3-D one of the same wavelength would (the
    3-D "wave" restricted to a plane keeps spectral power near zero wavenumber), and the
    3-D families give that piece a σ two to three times too wide (docs/accuracy.md, "A field
    of the horizontal position").

    Hand-written: scipy has no covariance families (scikit-learn's Gaussian-process kernels
    lack the hole effect and the taper, and would be a new dependency).
    """

    family: str = "spherical"
    range_m: float = float("nan")

    def __post_init__(self):
        if self.family not in SPATIAL_FAMILIES:
            raise InvalidParameterError(
                f"spatial_family must be one of {', '.join(SPATIAL_FAMILIES)}; got {self.family!r}"
            )

    @property
    def active(self) -> bool:
        """A finite positive range (a spatial term to build)."""
        return bool(self.range_m == self.range_m and self.range_m > 0)

    @property
    def support_m(self) -> float:
        """Distance beyond which the correlation is nil, metres."""
        return TAPER_RANGES[self.family] * float(self.range_m)

    def __float__(self) -> float:
        return float(self.range_m)

    def __call__(self, h) -> np.ndarray:
        """Correlation at distances ``h`` (any shape, metres; for a :attr:`horizontal` family
        the horizontal distances, as :func:`support_correlation` measures them)."""
        h = np.asarray(h, dtype=np.float64)
        a = float(self.range_m)
        if self.family == "spherical":
            return spherical_correlation(h, a)
        taper = spherical_correlation(h, self.support_m)
        if self.family == "exponential":
            return np.exp(-3.0 * h / a) * taper
        if self.family == "gaussian":
            return np.exp(-3.0 * (h / a) ** 2) * taper
        if self.family == "wave_h":
            return j0(2.0 * math.pi * h / a) * taper
        return np.sinc(2.0 * h / a) * taper  # numpy's sinc(x) = sin(πx)/(πx)

    @property
    def horizontal(self) -> bool:
        """A correlation of the horizontal distance (the field does not vary with height)."""
        return self.family == "wave_h"


def as_kernel(kernel) -> SpatialKernel:
    """A :class:`SpatialKernel` from a kernel, a range in metres (the spherical family, as
    before the families) or None / NaN (no spatial term)."""
    if isinstance(kernel, SpatialKernel):
        return kernel
    return SpatialKernel("spherical", float("nan") if kernel is None else float(kernel))


def ball_cross_correlation(h: np.ndarray, range_a: float, range_b: float) -> np.ndarray:
    """Cross-correlation of two spherical-model fields made from one white noise.

    A spherical correlation of range ``a`` is the overlap volume of two balls of radius
    ``a/2`` at distance ``h``, divided by the ball's volume: the field is white noise averaged
    over a ball of radius ``a/2``. Two fields averaged from the SAME noise over balls of radii
    ``r_a = a/2`` and ``r_b = b/2`` have the cross-correlation ``|B(r_a) ∩ B(r_b, h)| /
    √(|B(r_a)| |B(r_b)|)``, with ``|B(r_a) ∩ B(r_b, h)| = π (r_a + r_b − h)² (h² + 2h(r_a +
    r_b) − 3(r_a − r_b)²) / (12 h)`` for ``|r_a − r_b| < h < r_a + r_b``, the smaller ball's
    volume below and 0 beyond (zero past ``(a + b)/2``). For ``a = b`` it is
    :func:`spherical_correlation`; at ``h = 0`` it is ``(min/max)^(3/2)`` of the radii. Each
    field keeps its own spherical correlation, so the pair is a valid (positive
    semi-definite) bivariate model whatever the two ranges (any shape of ``h``, metres).
    """
    h = np.asarray(h, dtype=np.float64)
    ra, rb = 0.5 * float(range_a), 0.5 * float(range_b)
    small = min(ra, rb)
    with np.errstate(divide="ignore", invalid="ignore"):
        lens = (
            math.pi
            * (ra + rb - h) ** 2
            * (h * h + 2.0 * h * (ra + rb) - 3.0 * (ra - rb) ** 2)
            / (12.0 * h)
        )
    vol = np.where(h <= abs(ra - rb), 4.0 / 3.0 * math.pi * small**3, lens)
    vol = np.where(h >= ra + rb, 0.0, vol)
    return vol / (4.0 / 3.0 * math.pi * math.sqrt(ra**3 * rb**3))


def block_correlation_reference(corr, sa, wa, sb, wb) -> np.ndarray:
    """Mean correlation between the supports of plane pairs (change of support): the slow,
    obvious reference of :func:`support_correlation` (a double loop over sample pairs).

    ``ρ̄_m = Σ_s Σ_t wa[m, s] wb[m, t] corr(|sa[m, s] − sb[m, t]|)``.

    Parameters
    ----------
    corr : callable
        Correlation of a distance (metres).
    sa, sb : (m, S, 3) float64
        Sample points of the first and second plane of each pair, metres.
    wa, wb : (m, S) float64
        Their weights (rows sum to 1; zero for padding).

    Returns
    -------
    (m,) float64
    """
    out = np.zeros(sa.shape[0])
    axes = 2 if getattr(corr, "horizontal", False) else 3  # a field of the horizontal position
    for m in range(sa.shape[0]):
        tot = 0.0
        for s in range(sa.shape[1]):
            for t in range(sb.shape[1]):
                h = math.sqrt(float(((sa[m, s, :axes] - sb[m, t, :axes]) ** 2).sum()))
                tot += float(wa[m, s]) * float(wb[m, t]) * float(corr(np.array(h)))
        out[m] = tot
    return out


def _support_of(centroids, samples, weights):
    """(k, S, 3) samples, (k, S) weights and (k,) radius (largest distance of a weighted
    sample from the centroid) of planes; no samples: the centroid alone (radius 0)."""
    if samples is None:
        k = centroids.shape[0]
        return centroids[:, None, :], np.ones((k, 1)), np.zeros(k)
    smp = np.asarray(samples, dtype=np.float64)
    w = (
        np.full(smp.shape[:2], 1.0 / smp.shape[1])
        if weights is None
        else np.asarray(weights, dtype=np.float64)
    )
    r = np.sqrt(((smp - centroids[:, None, :]) ** 2).sum(-1))
    r = np.where(w > 0, r, 0.0).max(axis=1)
    return smp, w, r


def _coarsen(smp, w, m_from, m_to):
    """Merge the ``m_from × m_from`` grid of samples (row-major) into ``m_to × m_to`` cells:
    weights summed, positions their weighted means."""
    k, f = smp.shape[0], m_from // m_to
    s6 = smp.reshape(k, m_to, f, m_to, f, 3)
    w5 = w.reshape(k, m_to, f, m_to, f)
    ws = w5.sum(axis=(2, 4))
    ps = (s6 * w5[..., None]).sum(axis=(2, 4)) / np.maximum(ws, 1e-300)[..., None]
    return ps.reshape(k, m_to * m_to, 3), ws.reshape(k, m_to * m_to)


def effective_samples(centroids, samples, weights, range_m: float):
    """The sample points a spatial term of range ``range_m`` uses for each plane, flattened.

    Samples laid out as an ``m × m`` grid (``S = m²``, ``m`` a power of two, row-major, as
    :func:`.adjustment._plane_samples` makes them) are merged per plane to the coarsest grid
    whose cells are at most a quarter of the range across (``m_j`` the least power of two
    ``≥ 4 r_j / a``, ``r_j`` the plane's radius): a plane less than half the range across is
    its centroid, as in the centroid model, and a large plane is sampled finely enough for
    the field's correlation to be resolved; the cost stays with the pairs of samples within
    the range. Other layouts are used as given. Each plane's field value is then a weighted
    mean of the field at its samples, so the block covariance is positive semi-definite
    whatever the mix of levels.

    Returns
    -------
    pts : (N, 3) float64, owner : (N,) int64 (plane of each sample, 0..k-1), wt : (N,) float64
    """
    k = centroids.shape[0]
    smp, w, r = _support_of(centroids, samples, weights)
    ns = smp.shape[1]
    m = int(round(math.sqrt(ns)))
    if ns > 1 and m * m == ns and (m & (m - 1)) == 0:
        need = 4.0 * r / max(float(range_m), 1e-300)
        level = np.ones(k, dtype=np.int64)
        while True:
            more = (level < m) & (level < need)
            if not np.any(more):
                break
            level[more] *= 2
        parts = []
        for lv in np.unique(level):
            sel = np.flatnonzero(level == lv)
            if lv == 1:
                ps, ws = centroids[sel][:, None, :], np.ones((sel.size, 1))
            elif lv == m:
                ps, ws = smp[sel], w[sel]
            else:
                ps, ws = _coarsen(smp[sel], w[sel], m, int(lv))
            own = np.repeat(sel, ps.shape[1])
            parts.append((ps.reshape(-1, 3), own, ws.ravel()))
        pts = np.concatenate([q[0] for q in parts])
        owner = np.concatenate([q[1] for q in parts])
        wt = np.concatenate([q[2] for q in parts])
    else:
        pts, owner, wt = smp.reshape(-1, 3), np.repeat(np.arange(k), ns), w.ravel()
    keep = wt > 0
    return pts[keep], owner[keep], wt[keep]


def support_correlation(corr, base_m, a, b=None):
    """Block correlations of plane pairs whose supports come within ``base_m``.

    ``a`` and ``b`` are :func:`effective_samples` triples (``b`` None: ``a`` with itself);
    returns (i, j, ρ̄) over the plane pairs with a sample pair within ``base_m`` (the
    correlation's support), ``ρ̄_ij = Σ w_s w_t corr(|p_s − q_t|)`` summed over those sample
    pairs (a k-d tree of the samples: linear in samples for a fixed density within range).
    """
    pa, oa, wa = a
    pb, ob, wb = a if b is None else b
    if getattr(corr, "horizontal", False):
        pa, pb = pa[:, :2], pb[:, :2]
    ta = cKDTree(pa)
    tb = ta if b is None else cKDTree(pb)
    pairs = ta.sparse_distance_matrix(tb, base_m, output_type="ndarray")
    i, j, h = pairs["i"], pairs["j"], pairs["v"]
    val = wa[i] * wb[j] * corr(h)
    kb = int(ob.max(initial=-1)) + 1
    key = oa[i].astype(np.int64) * kb + ob[j]
    uk, inv = np.unique(key, return_inverse=True)
    rho = np.bincount(inv.ravel(), val, uk.size)
    return uk // kb, uk % kb, rho


@dataclass(frozen=True)
class PlaneGain:
    """What one side's stochastic adjustment gives the covariance with another side.

    The motion estimate of a stochastic adjustment is the plane-level GLS ``x̂ = Q (T/σ0² r
    + Hᵀ V⁻¹ y)``: linear in the plane observations ``y``, whose plane-level random part is
    ``δ`` (module docstring). ``gain = ∂x̂/∂δ = Q Hᵀ V⁻¹`` with the ``V`` the estimate used
    (down-weighting included), so the covariance of two adjustments whose ``δ`` are
    correlated is ``gain_a Cov(δ_a, δ_b) gain_bᵀ`` (:func:`cross_covariance`).

    Attributes
    ----------
    gain : (6, k) float64
        ``∂ params / ∂ δ`` of the ``k`` active planes (rad/m for the rotation rows, 1 for the
        translation rows: the displacement at the adjustment's centre).
    centroids : (k, 3) float64
        Plane centroids in the input frame (both epochs' points), metres.
    normals : (k, 3) float64
        Unit plane normals.
    shares_before, shares_after : (k, U) float64 or None
        Share of each plane's points of that epoch per acquisition unit.
    units_before, units_after : (U,) int64 or None
        The unit ids of the shares' columns (None: not known, no cross term through units).
    theta : dict
        The plane-level components in force (variances, m²; estimated, prior or fixed).
    range_m : float
        Range of the spatial component, metres (NaN when off).
    family : str
        Family of its correlation (:class:`SpatialKernel`).
    small_sample_factor : float
        The factor the adjustment's covariance was scaled by (see
        :class:`VarianceComponents`).
    model : str
        The stochastic model ("plane" or "full").
    fixed : dict
        The components the caller held fixed (``components=``: sigmas, metres).
    e, p, inflation : (k,) float64
        Plane misclosures at the solution, their white variance and the down-weighting
        inflation, m² (scaled by the point-level factor; see :func:`estimate_components`).
    h : (k, 6) float64
        Their design rows.
    t, rt : (6, 6), (6,) float64
        The tilt information and its right-hand side (scaled).
    q : (6, 6) float64
        ``(T + Hᵀ V⁻¹ H)⁻¹``, the adjustment's covariance before the small-sample factor.
    prior_plane_var : float
        The adjustment's floor of a plane component that cannot be estimated, m².
    samples : (k, S, 3) float64, optional
        Sample points spread over each plane's extent (input frame, metres), for the change
        of support of the spatial term (:class:`PlaneModel`); None: the centroids.
    sample_weights : (k, S) float64, optional
        Their weights (shares of the plane's points; rows sum to 1).
    unit_options : dict, optional
        ``{interval_s: (shares_before, shares_after, units_before, units_after)}`` of the
        units' drift along GpsTime (:mod:`.unit_drift`; ``math.inf``: the rigid unit), for the
        joint estimate of two sides (:func:`joint_covariance`) to choose the knot spacing on
        both; None without acquisition times.
    unit_interval_s : float
        The knot spacing this side's adjustment chose (inf: rigid; NaN: no times); the
        shares and units above are its.
    """

    gain: np.ndarray
    centroids: np.ndarray
    normals: np.ndarray
    shares_before: Optional[np.ndarray]
    shares_after: Optional[np.ndarray]
    units_before: Optional[np.ndarray]
    units_after: Optional[np.ndarray]
    theta: Dict[str, float]
    range_m: float
    small_sample_factor: float = 1.0
    model: str = "full"
    fixed: Dict[str, float] = field(default_factory=dict)
    e: Optional[np.ndarray] = None
    p: Optional[np.ndarray] = None
    inflation: Optional[np.ndarray] = None
    h: Optional[np.ndarray] = None
    t: Optional[np.ndarray] = None
    rt: Optional[np.ndarray] = None
    q: Optional[np.ndarray] = None
    prior_plane_var: float = 0.0
    samples: Optional[np.ndarray] = None
    sample_weights: Optional[np.ndarray] = None
    family: str = "spherical"
    unit_options: Optional[Dict[float, tuple]] = None
    unit_interval_s: float = float("nan")
    #: the side's within-epoch unit contrasts (:mod:`.unit_contrasts`), planes numbered as
    #: the ``k`` above and shares in the columns of ``units_before`` / ``units_after`` (of
    #: each drift of ``unit_options``); None: none
    contrasts: Optional[ContrastRows] = None
    #: (6, m) ``∂ params / ∂ c`` of the contrast rows (the motion takes the units' errors
    #: they predict off the misclosures, :class:`ContrastCondition`); None: not used
    contrast_gain: Optional[np.ndarray] = None
    #: the lever of the units' turn the adjustment chose (:data:`UNIT_LEVERS_M`; inf: none)
    unit_lever_m: float = math.inf
    #: ``{interval_s: (tilts_before, tilts_after)}``: each plane's (k, U, 3) tilt per unit
    #: column of ``unit_options`` (:func:`.unit_drift.hat_unit_tilt_shares`; an epoch without
    #: units None) when the units' errors tilt the planes (``UNIT_DRIFT_TILTS``); else None
    unit_tilt_options: Optional[Dict[float, tuple]] = None
    #: (6, k, 3) the motion's gain on each plane's tilt and (6, 6) the covariance the tilts'
    #: own noise gives (:func:`tilt_gains`), when the units' errors tilt the planes; None:
    #: the tilts on their own (``q t q``)
    tilt_gain: Optional[np.ndarray] = None
    tilt_noise: Optional[np.ndarray] = None

    def support(self):
        """(k, S, 3) samples, (k, S) weights and (k,) radii (see :class:`PlaneModel`)."""
        return _support_of(self.centroids, self.samples, self.sample_weights)

    @property
    def kernel(self) -> SpatialKernel:
        """The spatial correlation in force (:class:`SpatialKernel`)."""
        return SpatialKernel(self.family, float(self.range_m))


def _union_shares(a: PlaneGain, b: PlaneGain, epoch: str) -> Optional[np.ndarray]:
    """(ka + kb, U) shares of both adjustments' planes over the union of their unit ids."""
    ua, ub = getattr(a, "units_" + epoch), getattr(b, "units_" + epoch)
    sa, sb = getattr(a, "shares_" + epoch), getattr(b, "shares_" + epoch)
    return _union_of(sa, ua, sb, ub)


def _union_options(a: PlaneGain, b: PlaneGain):
    """``{interval_s: (shares_before, shares_after)}`` over both adjustments' planes of each
    drift both have (:attr:`PlaneGain.unit_options`), or None."""
    if not a.unit_options or not b.unit_options:
        return None
    out = {}
    for dt in set(a.unit_options) & set(b.unit_options):
        sa_b, sa_a, ua_b, ua_a = a.unit_options[dt]
        sb_b, sb_a, ub_b, ub_a = b.unit_options[dt]
        out[dt] = (_union_of(sa_b, ua_b, sb_b, ub_b), _union_of(sa_a, ua_a, sb_a, ub_a))
    return out if math.inf in out else None


def _union_contrasts(a: PlaneGain, b: PlaneGain):
    """Both adjustments' contrast rows over the union of their unit ids (one copy when both
    hold the same survey's rows, else ``a``'s then ``b``'s): (rows or None, shared)."""
    if a.contrasts is None and b.contrasts is None:
        return None, False

    def codes(g, which, interval_s):
        if interval_s is None or not g.unit_options or interval_s not in g.unit_options:
            return getattr(g, "units_" + which)
        return g.unit_options[interval_s][2 if which == "before" else 3]

    def union(which, sa, sb, interval_s):
        ua, ub = codes(a, which, interval_s), codes(b, which, interval_s)
        if ua is None or ub is None:
            return None
        sa = np.zeros((0, ua.size)) if sa is None else sa
        sb = np.zeros((0, ub.size)) if sb is None else sb
        return _union_of(sa, ua, sb, ub)

    return union_rows(a.contrasts, b.contrasts, union)


def _union_of(sa, ua, sb, ub) -> Optional[np.ndarray]:
    if ua is None or ub is None or sa is None or sb is None:
        return None
    codes = np.union1d(ua, ub)
    out = np.zeros((sa.shape[0] + sb.shape[0], codes.size) + sa.shape[2:])
    out[: sa.shape[0], np.searchsorted(codes, ua)] = sa
    out[sa.shape[0] :, np.searchsorted(codes, ub)] = sb
    return out


@dataclass(frozen=True)
class JointComponents:
    """The plane-level components estimated on two adjustments' planes together
    (:func:`joint_covariance`).

    Attributes
    ----------
    theta : dict
        Variances (m²) of :data:`COMPONENT_NAMES`.
    source : dict
        "estimated", "fixed", "prior" or "off" per component.
    range_m : float
        Spatial range, metres (NaN when off).
    n_planes : int
        Planes of both adjustments.
    family : str
        Family of the spatial correlation chosen on both sides' planes together.
    small_sample_factor : float
        ``ν/(ν − 2)`` with ``ν`` the fewer of ``planes − 12`` and the Satterthwaite degrees
        of freedom of the slip's variance, at least 3 (1 when every component was fixed).
    unit_interval_s : float
        Knot spacing of the units' drift along GpsTime chosen on both sides' planes together,
        seconds (inf: rigid units; NaN: no acquisition times).
    unit_lever_m : float
        Lever of the units' turn chosen on both sides together, metres (inf: none;
        :data:`UNIT_LEVERS_M`).
    """

    theta: Dict[str, float]
    source: Dict[str, str]
    range_m: float
    n_planes: int
    small_sample_factor: float
    family: str = "spherical"
    unit_interval_s: float = float("nan")
    unit_lever_m: float = math.inf

    def to_dict(self) -> Dict[str, object]:
        return {
            **(
                {"unit_drift_interval_s": _num(self.unit_interval_s)}
                if self.unit_interval_s == self.unit_interval_s
                else {}
            ),
            **(
                {"unit_turn_lever_m": _num(self.unit_lever_m)}
                if math.isfinite(self.unit_lever_m)
                else {}
            ),
            "components": {
                n: {
                    "sigma_m": math.sqrt(max(self.theta.get(n, 0.0), 0.0)),
                    "source": self.source.get(n, "off"),
                }
                for n in COMPONENT_NAMES
            },  # fmt: skip
            "spatial_range_m": _num(self.range_m),
            "spatial_family": self.family,
            "n_planes": int(self.n_planes),
            "small_sample_factor": _num(self.small_sample_factor),
        }


def joint_covariance(a: PlaneGain, b: PlaneGain, *, seed: int = 0):
    """(12, 6 + 6) covariance of the motions of two adjustments of one survey, under ONE set
    of plane-level components estimated on both adjustments' planes together.

    The components of one side are estimated from its own planes: a dozen planes cannot
    split a survey error between a spatial field, the units of each epoch and the nugget,
    and two sides of the same survey then split the same error differently (one side a
    unit component, the other a spatial one) or take a conservative prior; the cross term
    of :func:`cross_covariance` is then lost and each side's σ is wide. Here REML
    (:func:`estimate_components`) runs on the misclosures of both sides' planes with a
    block-diagonal motion design (each side keeps its own 6 motion parameters and its tilt
    information, so nothing of the motion leaks between the sides), one spatial field over
    both (centroid distances across the trace included) and the acquisition units by id
    over both. The motions themselves stay each side's own estimates (each side's GLS
    with its own components and robust weights); their joint covariance is the sandwich
    ``Q_s (T_s + H_sᵀ V_s⁻¹ V_J V_s⁻¹ H_s) Q_s`` within a side and ``K_a V_J(a, b) K_bᵀ``
    across (``K = Q Hᵀ V⁻¹``, ``V_J`` the joint model), which is the exact covariance of
    the estimates actually made if the joint model holds, and is positive semi-definite.
    The small-sample factor ``ν/(ν − 2)`` uses the fewer of ``planes − 12`` and the
    Satterthwaite degrees of freedom of the slip's variance (:func:`_satterthwaite_dof`):
    two dozen planes estimate four components poorly, and where the slip's σ rests on a
    poorly determined component the factor grows (up to 3).

    Returns None when the joint estimate is not made: a "plane" model (no shared term), fewer
    than :data:`MIN_PLANES_VCE` or more than :data:`DENSE_MAX_PLANES` planes together, unit
    shares without unit ids, or missing pieces (the caller then uses
    :func:`cross_covariance`). Else ``(cov, joint)``
    with ``cov`` (12, 12) over ``(params_a, params_b)`` and ``joint`` a
    :class:`JointComponents`.
    """
    if a.model != "full" or b.model != "full":
        return None
    if any(getattr(g, n) is None for g in (a, b) for n in ("e", "p", "h", "t", "q")):
        return None
    for g in (a, b):  # unit shares whose ids are not known cannot be matched across sides
        for ep in ("before", "after"):
            if getattr(g, "shares_" + ep) is not None and getattr(g, "units_" + ep) is None:
                return None
    ka, kb = a.e.size, b.e.size
    k = ka + kb
    if k < MIN_PLANES_VCE or k > DENSE_MAX_PLANES:
        return None
    samples = weights = None
    if a.samples is not None or b.samples is not None:
        (sa, wa, _), (sb, wb, _) = a.support(), b.support()
        ns = max(sa.shape[1], sb.shape[1])
        samples = np.concatenate([_pad(sa, ns, a.centroids), _pad(sb, ns, b.centroids)])
        weights = np.concatenate([_pad(wa, ns), _pad(wb, ns)])
    options = _union_options(a, b)
    model = PlaneModel(
        np.concatenate([a.centroids, b.centroids]),
        np.concatenate([a.normals, b.normals]),
        options[math.inf][0] if options else _union_shares(a, b, "before"),
        options[math.inf][1] if options else _union_shares(a, b, "after"),
        samples=samples,
        sample_weights=weights,
        unit_options=options,
    )
    joint_rows, shared_rows = _union_contrasts(a, b)
    if joint_rows is not None:
        model = replace(model, contrasts=joint_rows)
    idx = np.arange(k)
    x = np.zeros((k, 12))
    x[:ka, :6], x[ka:, 6:] = a.h, b.h
    t = np.zeros((12, 12))
    t[:6, :6], t[6:, 6:] = a.t, b.t
    rt = np.concatenate([a.rt, b.rt])
    e = np.concatenate([a.e, b.e])
    p = np.concatenate([a.p, b.p])
    infl = np.concatenate([a.inflation, b.inflation])
    fixed = dict(a.fixed)
    est = estimate_components(
        model, idx, e, x, t, p, which=COMPONENT_NAMES, fixed=fixed, inflation=infl,
        seed=seed, prior_plane_var=max(a.prior_plane_var, b.prior_plane_var), rt=rt,
    )  # fmt: skip
    theta = {n: v for n, v in est.theta.items() if v > 0}
    model = model.with_unit_interval(est.unit_interval_s).with_unit_lever(est.unit_lever_m)
    rows = model.contrasts
    if rows is not None and (a.contrast_gain is not None or b.contrast_gain is not None):
        # each side's motion takes the units' errors its contrast rows predict off its
        # misclosures: its gain runs over the planes and the rows (a's rows, then b's)
        ma = 0 if shared_rows or a.contrasts is None else a.contrasts.size
        v = covariance_with_contrasts(model, idx, p, theta, est.kernel, infl, rows)
        kj = np.zeros((12, k + rows.size))
        kj[:6, :ka], kj[6:, ka:k] = a.gain, b.gain
        if a.contrast_gain is not None:
            kj[:6, k : k + a.contrast_gain.shape[1]] = a.contrast_gain
        if b.contrast_gain is not None:
            kj[6:, k + ma :] = b.contrast_gain
    else:
        rows = None
        v = covariance(model, idx, p, theta, est.kernel, infl)
        kj = np.zeros((12, k))
        kj[:6, :ka], kj[6:, ka:] = a.gain, b.gain
    cov = kj @ v @ kj.T
    tilt = _joint_tilt_path(a, b, model, idx, theta, rows, kj, est.unit_interval_s)
    if tilt is not None:
        cov += tilt
    cov[:6, :6] += a.q @ a.t @ a.q if a.tilt_noise is None else a.tilt_noise
    cov[6:, 6:] += b.q @ b.t @ b.q if b.tilt_noise is None else b.tilt_noise
    nu = max(k - 12.0, 3.0)
    if any(src == "estimated" for src in est.source.values()):
        nu = min(nu, _satterthwaite_dof(model, idx, est, kj, cov, rows))
        small = nu / (nu - 2.0)
    else:
        small = 1.0
    joint = JointComponents(
        theta=dict(est.theta), source=dict(est.source), range_m=float(est.range_m),
        n_planes=int(k), small_sample_factor=float(small), family=est.kernel.family,
        unit_interval_s=float(est.unit_interval_s), unit_lever_m=float(est.unit_lever_m),
    )  # fmt: skip
    return small * 0.5 * (cov + cov.T), joint


def _joint_tilt_path(
    a: PlaneGain, b: PlaneGain, model: PlaneModel, idx, theta, rows, kj, interval_s
):
    """(12, 12) the part of :func:`joint_covariance` that runs through the planes' tilts
    when the units' errors tilt them (a side's :attr:`PlaneGain.tilt_gain`), or None.

    Under the joint model the tilts' random part is ``Z_t c`` plus their own noise, ``c`` the
    units' errors at the joint knot spacing (covariance ``θ I`` per epoch) and ``Z_t``
    (:meth:`PlaneModel.unit_tilt_design`) from each side's tilt shares over the union of
    the units. With ``K_t`` the motions' gains on the tilts and ``Z`` the units' design in
    the misclosures and contrast rows (``kj``'s columns), this is ``θ (K_t Z_t)(K_t Z_t)ᵀ +
    θ (kj Z)(K_t Z_t)ᵀ + θ (K_t Z_t)(kj Z)ᵀ`` summed over the epochs: the tilts' share of
    the drift, and its covariance with the offsets' share of it, which is negative where
    the tilts take the drift out. Their own noise is the sides' ``tilt_noise``."""
    if a.tilt_gain is None and b.tilt_gain is None:
        return None
    ka = a.e.size
    k = idx.size
    kt = np.zeros((12, k, 3))
    if a.tilt_gain is not None:
        kt[:6, :ka] = a.tilt_gain
    if b.tilt_gain is not None:
        kt[6:, ka:] = b.tilt_gain
    out = np.zeros((12, 12))
    for e, name in enumerate(("unit_before", "unit_after")):
        th = float(theta.get(name, 0.0))
        om = _union_tilts(a, b, e, interval_s)
        if th <= 0 or om is None:
            continue
        zt = model.unit_tilt_design(name, idx, om, rows)
        if zt is None:
            continue
        if rows is None:
            z = (1.0 if e == 0 else -1.0) * model.unit_basis(name, idx)
        else:
            z = np.vstack(model.unit_designs(name, idx, rows))
        g_t = np.einsum("cki,kir->cr", kt, zt)
        g_o = kj @ z
        out += th * (g_t @ g_t.T + g_o @ g_t.T + g_t @ g_o.T)
    return out


def _union_tilts(a: PlaneGain, b: PlaneGain, epoch: int, interval_s):
    """(ka + kb, U, 3) both sides' tilt shares of one epoch at the knot spacing
    ``interval_s`` over the union of their unit columns (a side without them: zeros), or
    None when neither has them."""
    parts = []
    for g in (a, b):
        opt = g.unit_options.get(interval_s) if g.unit_options else None
        tl = g.unit_tilt_options.get(interval_s) if g.unit_tilt_options else None
        if opt is None:
            return None
        codes = opt[2 + epoch]
        om = None if tl is None else tl[epoch]
        if codes is None:
            return None
        if om is None:
            om = np.zeros((g.e.size, codes.size, 3))
        parts.append((om, codes))
    (oa, ua), (ob, ub) = parts
    return _union_of(oa, ua, ob, ub)


def _pad(arr, ns, centroids=None):
    """Pad samples (k, S, 3) with the centroid or weights (k, S) with 0 to ``ns`` columns."""
    k, s0 = arr.shape[0], arr.shape[1]
    if s0 == ns:
        return arr
    if arr.ndim == 3:
        fill = np.repeat(centroids[:, None, :], ns - s0, axis=1)
    else:
        fill = np.zeros((k, ns - s0))
    return np.concatenate([arr, fill], axis=1)


def _satterthwaite_dof(model, idx, est, kj, cov, rows=None) -> float:
    """Satterthwaite's degrees of freedom of the variance of ``params_a − params_b``'s
    translation (the slip), the fewest over its principal directions, at least 3.

    Along a direction ``u`` the variance ``s² = uᵀ C u`` is a sum of the estimated components
    times their weights ``w_i = (uᵀ K_d) V_i (K_dᵀ u)`` (``K_d`` the difference of the two
    gains) plus terms taken as known (point noise, tilts); with the REML covariance of the
    components ``F⁻¹`` (components set to zero by the non-negative fixed point left out),
    ``ν = 2 s⁴ / wᵀ F⁻¹ w`` (Satterthwaite 1946; Giesbrecht & Burns 1985). A few planes can
    pin a component down poorly, and the σ of a slip carried by it then follows a t
    distribution of few degrees of freedom, whose variance is ``ν/(ν − 2)`` times the
    normal one."""
    kd = kj[3:6] - kj[9:12]
    rel = cov[3:6, 3:6] + cov[9:12, 9:12] - cov[3:6, 9:12] - cov[9:12, 3:6]
    bases = model.bases(idx, est.kernel)
    if rows is not None:  # the gains run over the contrast rows too
        bases = model.contrast_bases(idx, rows, bases)
    free = [n for n in COMPONENT_NAMES if (n, n) in est.cov and n in bases]
    if not free:
        return float("inf")
    fcov = np.array([[est.cov.get((a, b), 0.0) for b in free] for a in free])
    _, evec = np.linalg.eigh(0.5 * (rel + rel.T))
    nu = float("inf")
    for u in evec.T:
        g = u @ kd
        s2 = float(u @ rel @ u)
        w = np.array([float(g @ bases[n] @ g) for n in free])
        var = float(w @ fcov @ w)
        if var > 0 and s2 > 0:
            nu = min(nu, 2.0 * s2 * s2 / var)
    return max(nu, 3.0)


def cross_covariance(a: PlaneGain, b: PlaneGain) -> np.ndarray:
    """(6, 6) covariance ``Cov(x̂_a, x̂_b)`` of the motions of two adjustments on disjoint
    planes of the same survey (the two sides of a fault), rad/m/m² as ``params``.

    The survey error that the plane-level model describes is a property of the SURVEY, not of
    a side: a trajectory drift or an ALS strip that crosses the trace moves the planes of
    both sides alike. The joint model of ``δ_a, δ_b`` keeps each side's own model and
    components (its estimate and its covariance stay what that side's adjustment gives) and
    shares the random effects:

    * spatial: both sides' fields are averages of ONE white noise over balls of radius half
      their range, scaled by each side's ``σ_c``: ``Cov(δ_a,j, δ_b,k) = σ_c,a σ_c,b
      ρ_ab(|c_j − c_k|) n_jᵀ n_k`` with ``ρ_ab`` = :func:`ball_cross_correlation` (the
      spherical correlation when the ranges agree); two sides of one kernel (family and
      range, :class:`SpatialKernel`) share it; two different families are taken as
      independent fields (no cross term);
    * acquisition units: a unit present on both sides (the same id in the same epoch) has one
      rigid translation ``ξ_u ~ N(0, I₃)``, seen scaled by each side's ``σ_e``:
      ``σ_e,a σ_e,b G_a,u G_b,uᵀ`` with ``G = K Z + K_c Z_c``, the side's gain on the unit
      through its misclosures and through the contrast rows its motion is conditioned on
      (:class:`ContrastCondition`); when both sides' units turn (:data:`UNIT_LEVERS_M`), one
      turn per unit about one origin (:func:`_common_origins`) beside it, scaled by each
      side's ``σ_e / L``;
    * the contrast rows, when both sides hold the same survey's rows: their own noise once,
      ``K_c,a diag(var + √(ν_a ν_b)) K_c,bᵀ`` (``ν`` each side's nugget of the rows);
    * the plane component (nugget) and the point noise: independent, no cross term.

    Why combine the two sides' estimates rather than estimate one set on both sides: each
    side's components are estimated where its planes are (REML with that side's robust
    tests), and its σ is unchanged; the joint model above is a valid one for any two sets of
    components (each marginal is the side's own model, and both are built from one noise,
    so the joint covariance of the two motions is positive semi-definite and the variance of
    their difference is never negative), it is exactly "one field and one set of units"
    when the two sides' estimates agree, and where they differ (estimation noise) the part
    ``(σ_a − σ_b)²`` of a shared error, and the part a range mismatch decorrelates, stays in
    the σ of the difference: the error of the estimated components makes the σ wider, never
    narrower.

    Both adjustments' small-sample factors ``s`` scale the result by ``√(s_a s_b)`` (the
    joint covariance scaled by ``diag(√s_a, √s_b)`` on both sides stays positive
    semi-definite). Cost: pairs of planes within the spatial support (a k-d tree) and the
    shared units, linear in planes.
    """
    out = np.zeros((a.gain.shape[0], b.gain.shape[0]))
    ta, tb = float(a.theta.get("spatial", 0.0)), float(b.theta.get("spatial", 0.0))
    ka, kb = a.kernel, b.kernel
    if ka == kb:  # one field: its own correlation
        corr, support = ka, ka.support_m
    elif ka.family == kb.family == "spherical":
        corr = lambda d: ball_cross_correlation(d, a.range_m, b.range_m)  # noqa: E731
        support = 0.5 * (a.range_m + b.range_m)
    else:
        # two families: no bivariate model built from one noise is at hand; the fields are
        # taken as independent (joint_covariance, which estimates one kernel for both sides,
        # is the path that shares them)
        corr = None
    if ta > 0 and tb > 0 and ka.active and kb.active and corr is not None:
        fa = effective_samples(a.centroids, a.samples, a.sample_weights, a.range_m)
        fb = effective_samples(b.centroids, b.samples, b.sample_weights, b.range_m)
        i, j, rho = support_correlation(corr, support, fa, fb)
        if i.size:
            val = math.sqrt(ta * tb) * rho
            val = val * np.einsum("ij,ij->i", a.normals[i], b.normals[j])
            out += (a.gain[:, i] * val) @ b.gain[:, j].T
    rows_a = a.contrasts if a.contrast_gain is not None else None
    rows_b = b.contrasts if b.contrast_gain is not None else None
    shared_rows = rows_a is not None and rows_a.same_rows(rows_b)
    for name in ("unit_before", "unit_after"):
        epoch = name.split("_")[1]
        ta, tb = float(a.theta.get(name, 0.0)), float(b.theta.get(name, 0.0))
        ua, ub = getattr(a, "units_" + epoch), getattr(b, "units_" + epoch)
        sa, sb = getattr(a, "shares_" + epoch), getattr(b, "shares_" + epoch)
        if ta <= 0 or tb <= 0 or ua is None or ub is None or sa is None or sb is None:
            continue
        common, ia, ib = np.intersect1d(ua, ub, return_indices=True)
        if common.size == 0:
            continue
        sign = 1.0 if epoch == "before" else -1.0
        turn = math.isfinite(a.unit_lever_m) and math.isfinite(b.unit_lever_m)
        origins = _common_origins(a, b, epoch, ia, ib, shared_rows) if turn else None
        # ∂x̂/∂(unit errors) of each side for the shared units, through its misclosures and
        # through the contrast rows its motion is conditioned on: (6, units, 3 or 6)
        ga = _unit_gain(a, epoch, ia, sign, rows_a, origins)
        gb = _unit_gain(b, epoch, ib, sign, rows_b, origins)
        scale = np.ones(ga.shape[2])
        if turn:  # the turn's columns carry σ_e / L of each side
            scale[3:] = 1.0 / (a.unit_lever_m * b.unit_lever_m)
        out += math.sqrt(ta * tb) * np.einsum("pmd,qmd,d->pq", ga, gb, scale)
    if shared_rows:
        # one survey's rows in both motions: their own noise once
        na = max(float(a.theta.get(CONTRAST_NUGGET, 0.0)), 0.0)
        nb = max(float(b.theta.get(CONTRAST_NUGGET, 0.0)), 0.0)
        d = rows_a.var + math.sqrt(na * nb)
        out += (a.contrast_gain * d) @ b.contrast_gain.T
    return math.sqrt(a.small_sample_factor * b.small_sample_factor) * out


def _common_origins(a: PlaneGain, b: PlaneGain, epoch: str, ia, ib, shared_rows) -> np.ndarray:
    """(units, 3) origins of the units shared by two sides (their columns ``ia`` of ``a`` and
    ``ib`` of ``b``): the centroid of both sides' planes and contrast rows (once when they
    hold the same survey's rows), weighed by the shares (:meth:`PlaneModel.unit_origins` over
    the union; one origin for both, so the two sides' turns and translations are one
    unit's)."""
    w, c = [], []
    for g, cols in ((a, ia), (b, ib)):
        w.append(getattr(g, "shares_" + epoch)[:, cols])
        c.append(g.centroids)
        rows = None if (g is b and shared_rows) else g.contrasts
        rs = None if rows is None else getattr(rows, "shares_" + epoch)
        if rs is not None and rows.position is not None:
            w.append(rs[:, cols])
            c.append(rows.position)
    return _share_centroids(np.vstack(w), np.vstack(c))


def _share_centroids(w: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(U, 3) the centroid of the points ``c`` (n, 3) weighed by each column of the shares
    ``w`` (n, U) taken absolute (a contrast row's shares are signed); rows of ``c`` that are
    not finite (a plane without points) left out."""
    ok = np.all(np.isfinite(c), axis=1)
    w, c = np.abs(w[ok]), c[ok]
    tot = w.sum(axis=0)
    return (w.T @ c) / np.where(tot > 0, tot, 1.0)[:, None]


def _unit_gain(g: PlaneGain, epoch: str, cols, sign: float, rows, origins) -> np.ndarray:
    """(6, units, q) ``K Z`` of the unit columns ``cols`` of one side: its gain on the
    misclosures times their unit design (``sign``: + before, − after), plus its gain on the
    contrast rows ``rows`` (None: not conditioned) times theirs; q = 3 (translations) or 6
    with ``origins`` (units, 3): the turn's columns, unscaled by the lever."""
    lever = math.inf if origins is None else 1.0

    def design(shares, normals, where):  # (n, units, q): the columns of each unit together
        z = _share_design(shares, normals, where, origins, lever)
        return z.reshape(shares.shape[0], shares.shape[1], -1)

    out = sign * np.einsum(
        "pk,kmd->pmd", g.gain, design(getattr(g, "shares_" + epoch)[:, cols], g.normals,
                                      g.centroids)
    )  # fmt: skip
    rs = None if rows is None else getattr(rows, "shares_" + epoch)
    if rs is not None and (origins is None or rows.position is not None):
        out += np.einsum("pr,rmd->pmd", g.contrast_gain, design(rs[:, cols], rows.normal,
                                                                 rows.position))  # fmt: skip
    return out


@dataclass(frozen=True)
class Component:
    """One variance component of the slip's stochastic model.

    Attributes
    ----------
    name : str
        "white" (point noise), "plane", "spatial", "unit_before", "unit_after".
    sigma_m : float
        Its standard deviation, metres (for "white": the a-posteriori σ of one point
        condition of median a-priori σ).
    sd_m : float
        Standard deviation of ``sigma_m`` from the REML information (NaN when not estimated).
    source : str
        "estimated", "fixed" (given by the caller), "prior" (too few planes / not estimable:
        a conservative value), or "off" (not part of the model or no data for it).
    note : str
        Why a component is a prior or off; empty otherwise.
    variance_factor : float
        "white" only: the point-level a-posteriori variance factor σ0² (NaN for others).
    """

    name: str
    sigma_m: float
    sd_m: float = float("nan")
    source: str = "estimated"
    note: str = ""
    variance_factor: float = float("nan")

    def to_dict(self) -> Dict[str, object]:
        out: Dict[str, object] = {
            "sigma_m": _num(self.sigma_m),
            "sd_m": _num(self.sd_m),
            "source": self.source,
        }
        if self.name == "white":
            out["variance_factor"] = _num(self.variance_factor)
        if self.note:
            out["note"] = self.note
        return out


def _num(v: float):
    return float(v) if v == v and math.isfinite(v) else None


@dataclass(frozen=True)
class VarianceComponents:
    """The stochastic model of one adjustment and its estimated components.

    Attributes
    ----------
    model : str
        One of :data:`STOCHASTIC_MODELS`.
    method : str
        How the components were estimated.
    components : tuple of Component
        "white" first, then the plane-level components.
    spatial_range_m : float
        Range of the spatial correlation, metres (NaN when off; for the "wave" family its
        wavelength).
    n_planes : int
        Planes in the plane-level model.
    n_eff : float
        Effective number of independent planes: ``(Σw)²/Σw²`` of the plane weights
        ``w = 1/diag(V)``, times the ratio of the translation information with the full ``V``
        to that with its diagonal alone.
    covariance_white : (3, 3) float64
        Covariance of the translation under the white model (m², its own variance factor) at
        the same solution, to show beside the full model's (:attr:`sigma_white_m`).
    small_sample_factor : float
        ``ν/(ν − 2)`` with ``ν = max(planes − 6, 3)``, the factor the covariance was scaled by
        because its components are estimated, not known (1 when every component was fixed).
    notes : tuple of str
        Warnings (few planes, components not estimable, REML not converged).
    spatial_family : str
        Family of the spatial correlation (:class:`SpatialKernel`, chosen by REML).
    tilt : TiltEstimate
        The random tilt per plane (:data:`RANDOM_TILT`; source "off" when not modelled).
    unit_interval_s : float
        Knot spacing of the units' drift along GpsTime, seconds (:mod:`.unit_drift`, chosen by
        REML); ``math.inf``: one rigid error per unit; NaN: no acquisition times.
    n_contrasts : (int, int)
        The within-epoch unit contrasts (before, after) that tie the units in this
        adjustment (:mod:`.unit_contrasts`; (0, 0): none, or no unit component in force).
    contrast_misfit_m : float
        The contrasts' own misfit beside their point noise (1σ, metres; REML), NaN when not
        estimated.
    unit_lever_m : float
        Lever of the units' turn about their origins, metres (:data:`UNIT_LEVERS_M`, chosen
        by REML): the turn's 1σ per axis is the unit component's over it; ``math.inf``:
        the units translate only.
    """

    model: str
    method: str
    components: Tuple[Component, ...]
    spatial_range_m: float
    n_planes: int
    n_eff: float
    covariance_white: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    small_sample_factor: float = 1.0
    notes: Tuple[str, ...] = ()
    spatial_family: str = "spherical"
    tilt: TiltEstimate = field(default_factory=lambda: TiltEstimate())
    unit_interval_s: float = float("nan")
    n_contrasts: Tuple[int, int] = (0, 0)
    contrast_misfit_m: float = float("nan")
    unit_lever_m: float = math.inf

    @property
    def sigma_white_m(self) -> np.ndarray:
        """(3,) 1σ of the translation under the white model, metres."""
        return np.sqrt(np.clip(np.diag(self.covariance_white), 0.0, None))

    def component(self, name: str) -> Optional[Component]:
        for c in self.components:
            if c.name == name:
                return c
        return None

    def fixed(self) -> Dict[str, float]:
        """The plane-level components as ``components=`` for another adjustment (e.g. a strip
        or window of this side): every estimated, fixed or prior component and the range."""
        out = {
            c.name: float(c.sigma_m)
            for c in self.components
            if c.name in COMPONENT_NAMES and c.source != "off" and c.sigma_m == c.sigma_m
        }
        if self.spatial_range_m == self.spatial_range_m and "spatial" in out:
            out["spatial_range_m"] = float(self.spatial_range_m)
            if self.spatial_family != "spherical":
                out["spatial_family"] = self.spatial_family
        if self.tilt.source != "off":
            out["tilt_rad"] = float(self.tilt.sigma_rad)
        if self.unit_interval_s == self.unit_interval_s:
            out["unit_interval_s"] = float(self.unit_interval_s)
        if math.isfinite(self.unit_lever_m):
            out["unit_lever_m"] = float(self.unit_lever_m)
        return out

    def to_dict(self) -> Dict[str, object]:
        return {
            "model": self.model,
            "method": self.method,
            "components": {c.name: c.to_dict() for c in self.components},
            "spatial_range_m": _num(self.spatial_range_m),
            "spatial_family": self.spatial_family,
            "n_planes": int(self.n_planes),
            "n_eff": _num(self.n_eff),
            "sigma_white_m": [_num(v) for v in self.sigma_white_m],
            "small_sample_factor": _num(self.small_sample_factor),
            "notes": list(self.notes),
            **({"random_tilt": self.tilt.to_dict()} if self.tilt.source != "off" else {}),
            **(
                {"unit_drift_interval_s": _num(self.unit_interval_s)}
                if self.unit_interval_s == self.unit_interval_s
                else {}
            ),
            **(
                {
                    "unit_contrasts": {
                        "before": int(self.n_contrasts[0]),
                        "after": int(self.n_contrasts[1]),
                        "misfit_m": _num(self.contrast_misfit_m),
                    }
                }
                if any(self.n_contrasts)
                else {}
            ),
            **(
                {"unit_turn_lever_m": _num(self.unit_lever_m)}
                if math.isfinite(self.unit_lever_m)
                else {}
            ),
        }


# --------------------------------------------------------------------------- the model


@dataclass
class PlaneModel:
    """Structure of ``Σ_δ`` for a set of planes (everything but the component values).

    centroids : (b, 3) plane centroids (centred frame, metres); normals : (b, 3) unit normals;
    shares_before, shares_after : (b, U) shares of each plane's points per unit, or None;
    samples : (b, S, 3) points spread over each plane's extent (centred frame, metres) and
    sample_weights : (b, S) their shares of the plane's points (rows sum to 1; None: equal),
    for the change of support of the spatial term (module docstring); samples None: each
    plane is its centroid.
    """

    centroids: np.ndarray
    normals: np.ndarray
    shares_before: Optional[np.ndarray] = None
    shares_after: Optional[np.ndarray] = None
    samples: Optional[np.ndarray] = None
    sample_weights: Optional[np.ndarray] = None
    #: the unit shares of each drift along GpsTime REML may choose: ``{interval_s:
    #: (shares_before, shares_after)}`` (:mod:`.unit_drift`; ``math.inf``: the rigid unit,
    #: whose shares are the ones above); None: the rigid unit only
    unit_options: Optional[Dict[float, Tuple[Optional[np.ndarray], Optional[np.ndarray]]]] = None
    #: the planes' within-epoch unit contrasts (:mod:`.unit_contrasts`), rows beside the
    #: misclosures in the REML of the unit components; None: none
    contrasts: Optional[ContrastRows] = None
    #: the lever (metres) of the units' turn about their origins (:data:`UNIT_LEVERS_M`;
    #: ``math.inf``: translations only)
    unit_lever_m: float = math.inf

    @property
    def unit_intervals(self) -> Tuple[float, ...]:
        """The finite knot spacings of a drift the units may take (seconds), or ()."""
        return tuple(sorted(k for k in (self.unit_options or {}) if math.isfinite(k)))

    def with_unit_interval(self, interval_s: float) -> PlaneModel:
        """The model with the unit shares of the drift of knot spacing ``interval_s``
        (``math.inf``: the rigid unit); the same arrays otherwise (the normals are shared, so
        the adjustment's updates reach every variant)."""
        opts = self.unit_options or {}
        if interval_s not in opts:
            return self
        sb, sa = opts[interval_s]
        con = None if self.contrasts is None else self.contrasts.with_interval(interval_s)
        return replace(self, shares_before=sb, shares_after=sa, contrasts=con)

    def with_unit_lever(self, lever_m: float) -> PlaneModel:
        """The model whose units turn with lever ``lever_m`` (``math.inf``: they do not)."""
        if lever_m == self.unit_lever_m or not lever_m == lever_m:
            return self
        return replace(self, unit_lever_m=float(lever_m))

    def unit_origins(self, which: str) -> Optional[np.ndarray]:
        """(U, 3) each unit column's origin: the centroid of the planes and contrast rows it
        holds, weighed by its shares (a TLS setup's points lie around the instrument, an ALS
        strip's along its flight line); None without shares."""
        s = self.shares_before if which == "unit_before" else self.shares_after
        if s is None:
            return None
        w, c = s, self.centroids
        rows = self.contrasts
        if rows is not None and rows.position is not None:
            rs = rows.shares_before if which == "unit_before" else rows.shares_after
            if rs is not None:
                w = np.vstack([w, rs])
                c = np.vstack([c, rows.position])
        return _share_centroids(w, c)

    @property
    def unit_turns(self) -> bool:
        """Whether the units' design has their turn beside their translation: a lever, and
        every contrast row a position (rows without: translations only)."""
        rows = self.contrasts
        return math.isfinite(self.unit_lever_m) and (rows is None or rows.position is not None)

    def unit_columns(
        self, which: str, idx: np.ndarray, rows: Optional[ContrastRows] = None
    ) -> Optional[np.ndarray]:
        """(U,) bool: the columns of unit component ``which`` that the planes ``idx`` see, or
        with ``rows`` that they or the contrast rows see; None without shares (of the planes,
        or of the rows' epoch)."""
        s = self.shares_before if which == "unit_before" else self.shares_after
        if s is None:
            return None
        if rows is None:
            return s[idx].sum(axis=0) > 0
        c = rows.shares_before if which == "unit_before" else rows.shares_after
        if c is None:
            return None
        return np.any(s[idx] != 0.0, axis=0) | np.any(c != 0.0, axis=0)

    def unit_tilt_design(
        self, which: str, idx: np.ndarray, omega: np.ndarray, rows: Optional[ContrastRows] = None
    ) -> Optional[np.ndarray]:
        """(k, 3, r) the unit component ``which``'s design in the tilts of the planes ``idx``
        (rotation, radians per unit coefficient), in the columns of its design in their
        misclosures (:meth:`unit_basis`, or :meth:`unit_designs` with ``rows``), or None.

        ``omega`` (b, U, 3): each plane's tilt per metre of a unit column's error along its
        normal (:func:`.unit_drift.hat_unit_tilt_shares`). A unit's translation ``s`` tilts
        plane ``j`` by ``Ω_jv (n_jᵀ s)``; its turn ``ψ`` (coefficient ``L ψ``) turns its
        share of the plane, ``share · P_j ψ`` (``P_j`` the projector on the plane). The after
        epoch's errors act as the motion does, the before epoch's against it: the sign is
        that of the motion's rotation, opposite to the misclosures' (``+nᵀs`` before)."""
        keep = self.unit_columns(which, idx, rows)
        if keep is None or not np.any(keep):
            return None
        nrm = self.normals[idx]
        o = omega[idx][:, keep]  # (k, V, 3)
        blocks = [o[:, :, :, None] * nrm[:, None, None, :]]  # (k, V, 3 rot, 3 axis)
        if self.unit_turns and (rows is None or rows.position is not None):
            sub = (self.shares_before if which == "unit_before" else self.shares_after)[idx]
            proj = np.eye(3)[None] - nrm[:, :, None] * nrm[:, None, :]
            blocks.append(sub[:, keep][:, :, None, None] * proj[:, None] / self.unit_lever_m)
        blk = np.concatenate(blocks, axis=3)  # (k, V, 3, q)
        sign = -1.0 if which == "unit_before" else 1.0
        return sign * blk.transpose(0, 2, 1, 3).reshape(idx.size, 3, -1)

    def _unit_design(self, which, shares, normals, positions, keep):
        """:func:`_share_design` of the unit columns ``keep`` with the units' turn when the
        model has one (:attr:`unit_turns`) and the rows positions."""
        if not self.unit_turns or positions is None:
            return _share_design(shares, normals)
        origins = self.unit_origins(which)[keep]
        return _share_design(shares, normals, positions, origins, self.unit_lever_m)

    def contrast_rows(self) -> Optional[ContrastRows]:
        """The contrast rows beside any of the planes (all of them: a within-epoch contrast
        is not tied to a plane of the adjustment), or None when there are none."""
        if self.contrasts is None or not self.contrasts.size:
            return None
        return self.contrasts

    def unit_designs(self, which: str, idx: np.ndarray, rows: ContrastRows):
        """The unit component ``which``'s design in the misclosures of the planes ``idx``
        (k, r) and in the contrast rows (m, r), over the units either sees (r = 3 × them),
        or None. A unit error moves a misclosure by ``+nᵀs`` (before) or ``−nᵀs`` (after), a
        contrast of either epoch by ``+nᵀs`` (:mod:`.unit_contrasts`)."""
        keep = self.unit_columns(which, idx, rows)
        if keep is None or not np.any(keep):
            return None
        sm = (self.shares_before if which == "unit_before" else self.shares_after)[idx]
        c = rows.shares_before if which == "unit_before" else rows.shares_after
        sign = 1.0 if which == "unit_before" else -1.0
        turn = rows.position is not None  # rows without positions: translations only
        return (
            sign * self._unit_design(
                which, sm[:, keep], self.normals[idx], self.centroids[idx] if turn else None,
                keep,
            ),
            self._unit_design(which, c[:, keep], rows.normal, rows.position, keep),
        )  # fmt: skip

    def contrast_bases(self, idx: np.ndarray, rows: ContrastRows, bases: Dict[str, np.ndarray]):
        """``bases`` (k, k) of the planes ``idx`` extended by the contrast rows ``rows``
        (k + m, k + m): the unit components' over both (the misclosures' and the contrasts'
        shares in the same columns), the others nil on the contrast rows."""
        k, m = idx.size, rows.size
        out = {}
        for name, b in bases.items():
            zz = (
                self.unit_designs(name, idx, rows)
                if name in ("unit_before", "unit_after")
                else None
            )
            if zz is None:
                ext = np.zeros((k + m, k + m))
                ext[:k, :k] = b
            else:
                z = np.vstack(zz)
                ext = z @ z.T
            out[name] = ext
        return out

    def support(self, idx: np.ndarray):
        """(k, S, 3) samples, (k, S) weights and (k,) radii of the planes ``idx``."""
        return _support_of(
            self.centroids[idx],
            None if self.samples is None else self.samples[idx],
            None if self.samples is None or self.sample_weights is None
            else self.sample_weights[idx],
        )  # fmt: skip

    def effective(self, idx: np.ndarray, range_m: float):
        """:func:`effective_samples` of the planes ``idx`` (owners 0..k-1)."""
        s_, w_ = self.samples, self.sample_weights
        return effective_samples(
            self.centroids[idx],
            None if s_ is None else s_[idx],
            None if s_ is None or w_ is None else w_[idx],
            range_m,
        )

    def spatial_pairs(self, idx: np.ndarray, range_m):
        """(i, j, ρ̄ n_iᵀ n_j) of the plane pairs of ``idx`` (both orders, diagonal included)
        whose supports come within the kernel's support; ``range_m`` a :class:`SpatialKernel`
        or a spherical range (metres)."""
        kern = as_kernel(range_m)
        i, j, rho = support_correlation(kern, kern.support_m, self.effective(idx, kern.range_m))
        nrm = self.normals[idx]
        return i, j, rho * np.einsum("ij,ij->i", nrm[i], nrm[j])

    def spatial_correlation(self, idx: np.ndarray, range_m) -> np.ndarray:
        """Dense (k, k) ``ρ̄`` of the planes ``idx``: the kernel's correlation (a
        :class:`SpatialKernel`, or a spherical range in metres) averaged over each pair's
        samples (:func:`effective_samples`; the centroids' correlation where both planes are
        points)."""
        k = idx.size
        kern = as_kernel(range_m)
        i, j, rho = support_correlation(kern, kern.support_m, self.effective(idx, kern.range_m))
        out = np.zeros((k, k))
        out[i, j] = rho
        return 0.5 * (out + out.T)

    def unit_basis(self, which: str, idx: np.ndarray) -> Optional[np.ndarray]:
        """(k, 3U) ``Z`` of the planes ``idx`` for unit component ``which``."""
        keep = self.unit_columns(which, idx)
        if keep is None or not np.any(keep):
            return None
        sub = (self.shares_before if which == "unit_before" else self.shares_after)[idx]
        return self._unit_design(which, sub[:, keep], self.normals[idx], self.centroids[idx], keep)

    def n_units(self, which: str, idx: np.ndarray) -> int:
        keep = self.unit_columns(which, idx)
        return 0 if keep is None else int(np.count_nonzero(keep))

    def bases(self, idx: np.ndarray, range_m) -> Dict[str, np.ndarray]:
        """Dense (k, k) ``V_i`` of each plane-level component for planes ``idx``
        (``range_m``: a :class:`SpatialKernel` or a spherical range, metres)."""
        k = idx.size
        out = {"plane": np.eye(k)}
        if as_kernel(range_m).active:
            nrm = self.normals[idx]
            out["spatial"] = self.spatial_correlation(idx, range_m) * (nrm @ nrm.T)
        for name in ("unit_before", "unit_after"):
            z = self.unit_basis(name, idx)
            if z is not None:
                out[name] = z @ z.T
        return out


@dataclass(frozen=True)
class ContrastCondition:
    """The acquisition units' errors given the planes' within-epoch unit contrasts
    (:mod:`.unit_contrasts`), for the GLS of the motion.

    The misclosures and the contrast rows, stacked, are one GLS problem with no motion in the
    contrast rows; eliminating them (a Schur complement) leaves the misclosures with the
    units' predicted errors taken off (``shift``) and the units' covariance ``Λ`` replaced by
    their covariance given the contrasts ``Λ' = (Λ⁻¹ + Z_cᵀ P_c⁻¹ Z_c)⁻¹``: a strip
    adjustment of the units inside the slip's. The motion is then the stacked GLS exactly.

    Attributes
    ----------
    z : (k, r) float64
        The units' design in the misclosures (``+nᵀ`` share for the before epoch, ``−nᵀ``
        for the after epoch; r = 3 × the virtual units of both epochs with a component).
    info : (r, r) float64
        ``Λ'⁻¹ = Λ⁻¹ + Z_cᵀ P_c⁻¹ Z_c``.
    lam : (r, r) float64
        ``Λ'``, m².
    g : (r, m) float64
        The units' prediction from the contrast values, ``Λ' Z_cᵀ P_c⁻¹``.
    shift : (k,) float64
        ``z g c``: the misclosures' part the contrasts predict (m).
    rows : ContrastRows
        The contrast rows of the planes (numbered as positions among them).
    """

    z: np.ndarray
    info: np.ndarray
    lam: np.ndarray
    g: np.ndarray
    shift: np.ndarray
    rows: ContrastRows


def condition_on_contrasts(
    model: PlaneModel, idx: np.ndarray, theta: Mapping[str, float]
) -> Optional[ContrastCondition]:
    """The :class:`ContrastCondition` of the planes ``idx`` (sorted) under the components
    ``theta`` (variances, m²), or None (no contrast row, or no unit component in force)."""
    rows = model.contrast_rows()
    if rows is None:
        return None
    zm, zc, lam = [], [], []
    for name in ("unit_before", "unit_after"):
        t = float(theta.get(name, 0.0))
        zz = model.unit_designs(name, idx, rows) if t > 0 else None
        if zz is None:
            continue
        zm.append(zz[0])
        zc.append(zz[1])
        lam.append(np.full(zz[0].shape[1], t))
    if not zm:
        return None
    z, zcm, lam_d = np.hstack(zm), np.hstack(zc), np.concatenate(lam)
    pinv = 1.0 / (rows.var + max(float(theta.get(CONTRAST_NUGGET, 0.0)), 0.0))
    info = np.diag(1.0 / lam_d) + zcm.T @ (zcm * pinv[:, None])
    info = 0.5 * (info + info.T)
    cf = cho_factor(info, lower=True, check_finite=False)
    lam_p = cho_solve(cf, np.eye(info.shape[0]), check_finite=False)
    lam_p = 0.5 * (lam_p + lam_p.T)
    g = lam_p @ (zcm.T * pinv[None, :])
    return ContrastCondition(z, info, lam_p, g, z @ (g @ rows.value), rows)


def covariance_with_contrasts(
    model: PlaneModel,
    idx: np.ndarray,
    p: np.ndarray,
    theta: Mapping[str, float],
    range_m,
    inflation: Optional[np.ndarray],
    rows: ContrastRows,
) -> np.ndarray:
    """``V`` (k + m, k + m) of the misclosures of the planes ``idx`` and their contrast
    rows ``rows`` stacked (m²): :func:`covariance` on the planes, the contrasts' white
    variance, and the unit components over both."""
    k = idx.size
    bases = model.bases(idx, range_m if theta.get("spatial", 0.0) > 0 else float("nan"))
    bases = model.contrast_bases(idx, rows, bases)
    v = np.zeros((k + rows.size, k + rows.size))
    for name, b in bases.items():
        t = float(theta.get(name, 0.0))
        if t > 0:
            v += t * b
    nug = max(float(theta.get(CONTRAST_NUGGET, 0.0)), 0.0)
    d = np.concatenate([p + (0.0 if inflation is None else inflation), rows.var + nug])
    v[np.diag_indices_from(v)] += d
    return v


def _share_design(
    shares: np.ndarray,
    normals: np.ndarray,
    positions: Optional[np.ndarray] = None,
    origins: Optional[np.ndarray] = None,
    lever_m: float = math.inf,
) -> np.ndarray:
    """(n, 3V) design of V units' 3-D errors along each row's normal: ``shares`` (n, V)
    times ``normals`` (n, 3), the columns (unit, axis). With a finite ``lever_m`` and the
    rows' ``positions`` (n, 3) and the units' ``origins`` (V, 3) (metres, one frame), (n, 6V):
    each unit's columns are its translation then its turn scaled by the lever,
    ``((c − o_v) × n) / L`` (:data:`UNIT_LEVERS_M`)."""
    tr = shares[:, :, None] * normals[:, None, :]
    if not math.isfinite(lever_m) or positions is None or origins is None:
        return tr.reshape(shares.shape[0], -1)
    arm = positions[:, None, :] - origins[None, :, :]  # (n, V, 3)
    turn = shares[:, :, None] * np.cross(arm, normals[:, None, :]) / float(lever_m)
    return np.concatenate([tr, turn], axis=2).reshape(shares.shape[0], -1)


def covariance(
    model: PlaneModel,
    idx: np.ndarray,
    p: np.ndarray,
    theta: Mapping[str, float],
    range_m,
    inflation: Optional[np.ndarray] = None,
) -> np.ndarray:
    """``V = diag(p (+ inflation)) + Σ θ_i V_i`` (k, k), m²; ``theta`` holds variances (m²);
    ``range_m`` the spatial term's :class:`SpatialKernel` (or a spherical range, metres)."""
    v = np.zeros((idx.size, idx.size))
    bases = model.bases(idx, range_m if theta.get("spatial", 0.0) > 0 else float("nan"))
    for name, b in bases.items():
        t = float(theta.get(name, 0.0))
        if t > 0:
            v += t * b
    v[np.diag_indices_from(v)] += p + (0.0 if inflation is None else inflation)
    return v


class CovarianceOperator:
    """``V`` of the planes ``idx`` with solves, dense or sparse.

    Up to :data:`DENSE_MAX_PLANES` planes ``V`` is dense and factored by Cholesky. Beyond,
    nothing of size planes² is formed: every family's correlation is zero past its support
    (:attr:`SpatialKernel.support_m`: the range, or the taper's for the tapered families), so
    ``A = diag(p + θ_p + inflation) + θ_c ρ∘NNᵀ`` is sparse (pairs within the range from a
    k-d tree) and factored by SuperLU, and the unit components, of rank 3 × units, enter by
    the Woodbury identity ``V⁻¹ = A⁻¹ − A⁻¹ Z (Λ⁻¹ + Zᵀ A⁻¹ Z)⁻¹ Zᵀ A⁻¹``. Cost and memory
    are then linear in planes for a fixed density of planes within the range.
    """

    def __init__(self, model, idx, p, theta, range_m, inflation=None, condition=None):
        if condition is not None:
            # the units' covariance given the contrasts replaces their own (ContrastCondition)
            theta = {n: v for n, v in theta.items() if n not in ("unit_before", "unit_after")}
        self.k = idx.size
        diag = p + (0.0 if inflation is None else inflation) + float(theta.get("plane", 0.0))
        self.sparse = self.k > DENSE_MAX_PLANES
        self._diag_v = diag.copy()
        if not self.sparse:
            self.v = covariance(model, idx, p, theta, range_m, inflation)
            if condition is not None:
                self.v += condition.z @ condition.lam @ condition.z.T
                self.v = 0.5 * (self.v + self.v.T)
            self.cf = cho_factor(self.v, lower=True, check_finite=False)
            self._diag_v = np.diag(self.v).copy()
            return
        from scipy.sparse import coo_matrix, diags
        from scipy.sparse.linalg import splu

        a = diags(diag).tocsc()
        tc = float(theta.get("spatial", 0.0))
        if tc > 0 and as_kernel(range_m).active:
            i, j, val = model.spatial_pairs(idx, range_m)
            sp = coo_matrix((tc * val, (i, j)), shape=(self.k, self.k)).tocsc()
            sp = 0.5 * (sp + sp.T)
            a = a + sp
            self._diag_v += sp.diagonal()
        self.lu = splu(a.tocsc(), permc_spec="MMD_AT_PLUS_A")
        zs, lam = [], []
        for name in ("unit_before", "unit_after"):
            t = float(theta.get(name, 0.0))
            z = model.unit_basis(name, idx) if t > 0 else None
            if z is not None:
                zs.append(z)
                lam.append(np.full(z.shape[1], t))
                self._diag_v += t * (z * z).sum(axis=1)
        self.z = np.hstack(zs) if zs else None
        if condition is not None:
            # Woodbury with the units' full covariance given the contrasts: Λ'⁻¹ = info
            self.z = condition.z
            self._diag_v += np.einsum("ij,jk,ik->i", self.z, condition.lam, self.z)
            self.aiz = self.lu.solve(self.z)
            cap = condition.info + self.z.T @ self.aiz
            self.cap = cho_factor(0.5 * (cap + cap.T), lower=True, check_finite=False)
        elif self.z is not None:
            lam = np.concatenate(lam)
            self.aiz = self.lu.solve(self.z)
            cap = np.diag(1.0 / lam) + self.z.T @ self.aiz
            self.cap = cho_factor(0.5 * (cap + cap.T), lower=True, check_finite=False)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``V⁻¹ b`` for (k,) or (k, m) ``b``."""
        if not self.sparse:
            return cho_solve(self.cf, b, check_finite=False)
        aib = self.lu.solve(np.asarray(b, dtype=np.float64))
        if self.z is None:
            return aib
        return aib - self.aiz @ cho_solve(self.cap, self.z.T @ aib, check_finite=False)

    def diag(self) -> np.ndarray:
        """(k,) diagonal of ``V``."""
        return self._diag_v


# --------------------------------------------------------------------------- GLS algebra


class PlaneGLS:
    """Cholesky of ``V`` and the REML pieces for misclosures ``e`` (k,), design ``x`` (k, 6),
    tilt information ``t`` (6, 6) and its right-hand side ``rt`` (6,): the planes' tilts
    say ``t β = rt`` about the motion increment ``β``, whatever the offsets (at a converged
    solution ``rt`` balances the offsets' pull and the increment is nil)."""

    def __init__(self, v: np.ndarray, x: np.ndarray, t: np.ndarray, rt=None):
        self.v = v
        self.x = x
        self.t = t
        self.rt = np.zeros(x.shape[1]) if rt is None else rt
        self.cf = cho_factor(v, lower=True, check_finite=False)
        self.vix = cho_solve(self.cf, x, check_finite=False)  # V^-1 X
        self.m = x.T @ self.vix + t  # X^T V^-1 X + T
        self.m = 0.5 * (self.m + self.m.T)

    def logdet_v(self) -> float:
        return 2.0 * float(np.log(np.diag(self.cf[0])).sum())

    def vinv(self) -> np.ndarray:
        li = solve_triangular(self.cf[0], np.eye(self.v.shape[0]), lower=True, check_finite=False)
        return li.T @ li

    def pi_matrix(self) -> np.ndarray:
        """Π = V⁻¹ − V⁻¹X M⁻¹ XᵀV⁻¹ (k, k)."""
        mi = np.linalg.pinv(self.m, hermitian=True)
        return self.vinv() - self.vix @ mi @ self.vix.T

    def beta(self, e: np.ndarray) -> np.ndarray:
        """GLS increment of the motion (6,) from the offsets and the tilts."""
        vie = cho_solve(self.cf, e, check_finite=False)
        return np.linalg.lstsq(self.m, self.x.T @ vie + self.rt, rcond=None)[0]

    def pi_e(self, e: np.ndarray) -> np.ndarray:
        """``V⁻¹ (e − X β̂)``, the weighted residuals (``Π e`` when ``rt`` is 0)."""
        return cho_solve(self.cf, e - self.x @ self.beta(e), check_finite=False)

    def reml(self, e: np.ndarray) -> float:
        """−2 × restricted log-likelihood (up to a constant)."""
        sign, ld_m = np.linalg.slogdet(self.m)
        if sign <= 0:
            ld_m = float(np.log(np.abs(np.linalg.eigvalsh(self.m)).clip(1e-300)).sum())
        b = self.beta(e)
        r = e - self.x @ b
        quad = float(r @ cho_solve(self.cf, r, check_finite=False))
        quad += float(b @ self.t @ b - 2.0 * b @ self.rt)
        return self.logdet_v() + ld_m + quad


# --------------------------------------------------------------------------- estimation


@dataclass(frozen=True)
class Estimate:
    """Result of :func:`estimate_components`: variances (m²), their sds, sources, range."""

    theta: Dict[str, float]
    sd: Dict[str, float]
    source: Dict[str, str]
    notes: Dict[str, str]
    range_m: float
    iterations: int
    converged: bool
    cov: Dict[Tuple[str, str], float] = field(default_factory=dict)
    #: the spatial correlation chosen (family and range; NaN range when off)
    kernel: SpatialKernel = field(default_factory=SpatialKernel)
    #: −2 log L (REML) of the best range of each family tried, for the report
    family_m2ll: Dict[str, float] = field(default_factory=dict)
    #: knot spacing of the units' drift along GpsTime, seconds (:mod:`.unit_drift`;
    #: ``math.inf``: the rigid unit; NaN: no acquisition times)
    unit_interval_s: float = float("nan")
    #: lever of the units' turn about their origins, metres (:data:`UNIT_LEVERS_M`;
    #: ``math.inf``: translations only)
    unit_lever_m: float = math.inf


def _reml_fixed_point(e, x, t, p, bases, theta0, fixed, inflation, rt=None):
    """Iterated MINQUE / Fisher scoring of REML for the free components; returns (theta, sd,
    iterations, converged, -2 log L, covariances of the estimated variances by name pair)."""
    names = [n for n in bases if n not in fixed]
    theta = dict(theta0)
    converged = False
    sd = {n: float("nan") for n in names}
    pair_cov: Dict[Tuple[str, str], float] = {}
    v0 = np.diag(p + (0.0 if inflation is None else inflation))
    for n, t_fixed in fixed.items():
        if n in bases and t_fixed > 0:
            v0 = v0 + t_fixed * bases[n]
    free = list(names)

    def gls_at() -> PlaneGLS:
        v = v0.copy()
        for n in free:
            v += max(theta.get(n, 0.0), 0.0) * bases[n]
        return PlaneGLS(v, x, t, rt)

    it = 0
    while it < VCE_MAX_ITER:
        it += 1
        gls = gls_at()
        if not free:
            converged = True
            break
        pi = gls.pi_matrix()
        pie = gls.pi_e(e)
        piv = {n: pi @ bases[n] for n in free}
        f = np.empty((len(free), len(free)))
        q = np.empty(len(free))
        piv0 = pi @ v0
        for a, na in enumerate(free):
            q[a] = 0.5 * float(pie @ bases[na] @ pie) - 0.5 * float(np.sum(piv[na] * piv0.T))
            for c in range(a, len(free)):
                f[a, c] = f[c, a] = 0.5 * float(np.sum(piv[na] * piv[free[c]].T))
        try:
            new = np.linalg.solve(f, q)
        except np.linalg.LinAlgError:
            new = np.linalg.lstsq(f, q, rcond=None)[0]
        old = np.array([theta.get(n, 0.0) for n in free])
        if np.any(new < 0):
            # the non-negative fixed point: drop the most negative component and redo
            worst = free[int(np.argmin(new))]
            theta[worst] = 0.0
            free.remove(worst)
            sd[worst] = float("nan")
            continue
        for n, val in zip(free, new):
            theta[n] = float(val)
        try:
            cov = np.linalg.inv(f)
            for a, n in enumerate(free):
                sd[n] = float(math.sqrt(max(cov[a, a], 0.0)))
            pair_cov = {(na, nc): float(cov[i, j]) for i, na in enumerate(free)
                        for j, nc in enumerate(free)}  # fmt: skip
        except np.linalg.LinAlgError:
            pass
        scale = max(float(np.max(np.abs(new))), float(np.median(p)) if p.size else 0.0, _FLOOR)
        if float(np.max(np.abs(new - old))) <= VCE_TOL * scale:
            converged = True
            break
    # final likelihood at the estimate
    pair_cov = {k: v for k, v in pair_cov.items() if k[0] in free and k[1] in free}
    return theta, sd, it, converged, gls_at().reml(e), pair_cov


def component_test_critical(k: int, alpha: float) -> float:
    """Upper ``alpha`` point of χ²_k: the critical value of the likelihood ratio of the ``k``
    components REML set positive against none of them, given that ``k`` are positive.

    Why not the χ̄² mixture ``Σ_j C(k, j) 2⁻ᵏ χ²_j`` of ``k`` variances on their boundary
    (Self & Liang 1987; the test's null until stop 46): it is the null of the ratio before
    one knows how many estimates leave the boundary. Given that ``k`` did, the ratio is
    χ²_k, and the mixture's point (2.71 for one component, the 10 % point of χ²₁) rejects
    twice as often as the level says: on white-noise pairs a component passed on 18 of 84
    sides (issue #30, stop 46). Conditioned on ``k``, the test's size is
    ``alpha`` times the chance that any estimate is positive, at most ``alpha``, whatever the
    correlation of the components' estimates (which the mixture's binomial weights ignore).

    Parameters
    ----------
    k : int
        Number of components REML set positive (≥ 1).
    alpha : float
        Level of the test (0 < alpha < 1).
    """
    from scipy.stats import chi2

    return float(chi2.isf(alpha, k))


def search_p_value(lr: float, k: int, paths: Sequence[np.ndarray]) -> float:
    """Upper bound of the null probability that the likelihood ratio, maximised over the
    spatial ranges and families profile REML searched, reaches ``lr`` (Davies 1987).

    Why: REML profiles the spatial component's range over a grid per family and keeps the
    likeliest, so the ratio tested is the largest of many correlated χ²_k ratios, not one.
    Against χ²_k alone, a spatial component passed on 7 of 84 sides of white-noise pairs
    (issue #30, stop 46), and a long-range field moves a side like the motion. Davies' bound
    for a χ²_k process along a path of the nuisance parameter is
    ``P(χ²_k > u) + V u^((k-1)/2) e^(-u/2) / (2^(k/2) Γ(k/2))``, with ``V`` the total
    variation of the ratio's square root along the path; one such bound per family, summed.
    Written here because scipy has no such bound; the path is the profile REML computed
    anyway, so it costs nothing more.

    Parameters
    ----------
    lr : float
        The likelihood ratio tested (the components against none), ≥ 0.
    k : int
        Number of components REML set positive (≥ 1).
    paths : sequence of (r,) float64
        −2 log L of each family's candidate ranges, in the order of its range grid. The
        ratio along a path is ``lr`` less each candidate's distance from the best of all.

    Returns
    -------
    float
        The bound, in [0, 1].
    """
    from scipy.special import gammaln
    from scipy.stats import chi2

    u = float(lr)
    if u <= 0.0:
        return 1.0
    best = min(float(np.min(p)) for p in paths)
    v = 0.0
    for p in paths:
        root = np.sqrt(np.clip(u - (np.asarray(p, dtype=float) - best), 0.0, None))
        v += float(np.abs(np.diff(root)).sum())
    log_term = (k - 1) / 2 * math.log(u) - u / 2 - k / 2 * math.log(2.0) - gammaln(k / 2)
    return float(min(1.0, len(paths) * chi2.sf(u, k) + v * math.exp(log_term)))


def _test_plane_level(problem, fit, theta0, paths=None):
    """The REML likelihood ratio of the estimated plane-level components against none of them;
    all are set to zero when it is below the :data:`COMPONENT_TEST_ALPHA` point of its null
    given how many REML set positive (:func:`component_test_critical`), and, when one is the
    spatial component whose range REML searched, when the search's bound
    (:func:`search_p_value`) exceeds that level.

    Why: REML's non-negative estimate of a variance whose truth is zero is positive about half
    the time (the positive part of an unbiased estimate). On white-noise pairs it set a spatial
    or plane component of 0.1-0.3 mm on most sides, and a long-range spatial term moves a side
    like the motion, so the slip's σ came out 1.5x its error (issue #30). The components are
    tested together, not one by one: one by one, a correlated field is often as likely as a
    nugget of the same variance (a 3 mm field of 30 m waves on 150 planes: likelihood ratio
    1.6 against the nugget alone), and a nugget averages down over the planes where the field
    does not, so removing the field would make σ too small. Together, the test asks only
    whether the misclosures hold any error beyond the point noise at all.

    Parameters
    ----------
    problem : tuple
        ``(e, x, t, p, bases, fixed, inflation, rt)`` as :func:`_reml_fixed_point` takes them.
    fit : tuple
        ``(theta, sd, iterations, converged, -2 log L, pair covariances)`` of the full model.
    theta0 : dict
        The start of each free component.
    paths : sequence of (r,) float64, optional
        −2 log L along each family's range grid when profile REML searched the spatial range
        (:func:`search_p_value`): a ratio that holds a spatial component must then also
        pass the search's bound.

    Returns
    -------
    (theta, sd, iterations, converged, pair covariances, likelihood ratio or None, names)
        The fit, with every free component zero when the ratio is below the critical value
        (the ratio and the names of the components set to zero returned then; None and ()
        when the components are kept or none was positive).
    """
    e, x, t, p, bases, fixed, inflation, rt = problem
    th, sd, it, conv, m2ll, pc = fit
    live = [n for n in bases if n not in fixed and th.get(n, 0.0) > 0]
    if not live:
        return th, sd, it, conv, pc, None, ()
    sub = {k: b for k, b in bases.items() if k in fixed}
    m2ll0 = _reml_fixed_point(e, x, t, p, sub, {}, fixed, inflation, rt)[4]
    lr = float(m2ll0 - m2ll)
    crit = component_test_critical(len(live), COMPONENT_TEST_ALPHA)
    log.debug("plane-level components %s: likelihood ratio %.3f (critical %.3f)", live, lr, crit)
    if lr >= crit:
        if "spatial" not in live or paths is None:
            return th, sd, it, conv, pc, None, ()
        p_search = search_p_value(lr, len(live), paths)
        log.debug("the spatial search's p-value bound %.4f", p_search)
        if p_search <= COMPONENT_TEST_ALPHA:
            return th, sd, it, conv, pc, None, ()
    th = dict(th, **{n: 0.0 for n in live})
    sd = dict(sd, **{n: float("nan") for n in live})
    return th, sd, it, conv, {}, max(lr, 0.0), tuple(live)


def _candidate_ranges(c: np.ndarray, subset: bool = False, family: str = "spherical"):
    """Geometric grid of ranges from 3x the median nearest-plane distance to the extent (to
    the radius of a contiguous subset of a larger problem: beyond it the subset says little,
    and the sparse covariance of the whole problem would fill in).

    For the "wave" family the range is a wavelength: from 2x the median nearest-plane
    distance (planes closer than half a wavelength see the lobes) to half the extent (two
    wavelengths across the planes at least), :data:`N_WAVELENGTHS` of them (its likelihood
    is less smooth in the range than the monotone families')."""
    if c.shape[0] < 3:
        return np.zeros(0)
    dist, _ = cKDTree(c).query(c, k=2)
    nn = float(np.median(dist[:, 1]))
    ext = 2.0 * float(np.linalg.norm(c - c.mean(axis=0), axis=1).max())  # rotation-invariant
    if subset:
        ext *= 0.5
    if family in WAVELENGTH_FAMILIES:
        lo = max(2.0 * nn, 1.0)
        hi = 0.5 * ext
        if hi < 1.5 * lo:
            return np.zeros(0)
        return np.geomspace(lo, hi, N_WAVELENGTHS)
    lo = max(3.0 * nn, 1.0)
    hi = max(ext, 2.0 * lo)
    return np.geomspace(lo, hi, N_RANGES)


def _candidate_kernels(c, subset, fixed, families):
    """The (family, range) pairs profile REML tries: the caller's range and family when
    fixed (a range alone: the spherical family, as before the families), else each family's
    grid (:func:`_candidate_ranges`)."""
    fams = tuple(families)
    if "spatial_family" in fixed:
        fams = (str(fixed["spatial_family"]),)
    if "spatial_range_m" in fixed:
        fam = fams[0] if "spatial_family" in fixed else "spherical"
        return [SpatialKernel(fam, float(fixed["spatial_range_m"]))]
    return [SpatialKernel(f, float(r)) for f in fams
            for r in _candidate_ranges(c, subset, f)]  # fmt: skip


def _likelier(candidates, fit_at, ref, what: str):
    """The candidate shape (a knot spacing, a lever) whose REML fit ``fit_at(candidate)``
    (a tuple whose [4] is −2 log L) is the likeliest and beats ``ref`` by
    :data:`UNIT_INTERVAL_MARGIN`, or None."""
    trials = [(fit_at(c), c) for c in candidates]
    f, c = min(trials, key=lambda t: t[0][4])
    log.debug("REML %s: %s", what, {d: round(t[4], 2) for t, d in trials})
    return c if f[4] < ref[4] - UNIT_INTERVAL_MARGIN else None


def estimate_components(
    model: PlaneModel,
    idx: np.ndarray,
    e: np.ndarray,
    x: np.ndarray,
    t: np.ndarray,
    p: np.ndarray,
    *,
    which: Sequence[str],
    fixed: Mapping[str, float],
    inflation: Optional[np.ndarray] = None,
    seed: int = 0,
    prior_plane_var: float = 0.0,
    rt: Optional[np.ndarray] = None,
    families: Optional[Sequence[str]] = None,
) -> Estimate:
    """REML estimates of the plane-level components ``which`` (see the module docstring).

    Parameters
    ----------
    model : PlaneModel
    idx : (k,) int
        Planes in the model (indices into ``model``).
    e : (k,) float64
        Plane misclosures at the solution (m).
    x : (k, 6) float64
        Their design rows.
    t : (6, 6) float64
        Tilt information on the motion (scaled by the point-level factor).
    rt : (6,) float64, optional
        Its right-hand side (see :class:`PlaneGLS`; default 0).
    p : (k,) float64
        White variance of each misclosure (m², scaled).
    which : sequence of str
        Components to include (subset of :data:`COMPONENT_NAMES`).
    fixed : mapping
        Components given by the caller: ``{name: sigma_m}`` and optionally ``spatial_range_m``
        and ``spatial_family`` (one of :data:`SPATIAL_FAMILIES`; a range without a family is
        spherical).
    inflation : (k,) float64, optional
        Extra variance of down-weighted planes (m²).
    seed : int
        Seed of the subset drawn when there are more than :data:`VCE_MAX_PLANES` planes.
    prior_plane_var : float
        Floor of the plane component (m²) when there are fewer than :data:`MIN_PLANES_VCE`
        planes (then nothing is estimated reliably: with 6 or fewer planes the motion absorbs
        every misclosure).
    families : sequence of str
        Families of the spatial correlation to choose from (:class:`SpatialKernel`; default
        :data:`DEFAULT_FAMILIES`): the one
        of least −2 log L (REML, each at its best range; the same number of parameters, so
        AIC orders them alike), a family other than the spherical one only when it beats the
        spherical one by :data:`FAMILY_MARGIN`.
    """
    k = idx.size
    sub = np.arange(k)
    if k > VCE_MAX_PLANES:
        # a spatially contiguous block (the planes nearest to a seeded random plane) keeps
        # the local density of plane pairs that the spatial component is estimated from
        c = model.centroids[idx]
        first = int(np.random.default_rng(seed).integers(k))
        _, near = cKDTree(c).query(c[first], k=VCE_MAX_PLANES)
        sub = np.sort(np.asarray(near))
    es, xs, ps = e[sub], x[sub], p[sub]
    inf_s = None if inflation is None else inflation[sub]
    # the motion is a free fixed effect of the offsets alone (REML_TILT_SHARE = 0): the tilts'
    # information is point-noise precise, but the survey-error field tilts the planes too (3 mm
    # over 40 m is 0.1 mrad on every roof); held as a prior on the rotation it pins the
    # rotation to a biased value, the offsets' residuals then carry the lever arm's linear
    # trend, and REML reads it as a field of long range (issue #30, the "field" kind: 135-155 m
    # spherical ranges for a 37-53 m field; with the offsets alone 30-40 m)
    ts_full = t * (sub.size / k)  # the subset's share of the tilt information
    rts_full = None if rt is None else rt * (sub.size / k)
    ts = ts_full * REML_TILT_SHARE
    rts = None if rt is None or REML_TILT_SHARE == 0 else rts_full * REML_TILT_SHARE
    ids = idx[sub]
    theta: Dict[str, float] = {}
    source: Dict[str, str] = {}
    notes: Dict[str, str] = {}
    fixed_var = {n: float(fixed[n]) ** 2 for n in COMPONENT_NAMES if n in fixed}
    for n, v in fixed_var.items():
        theta[n] = v
        source[n] = "fixed"
    free = [n for n in which if n not in fixed_var]
    # the units' drift along GpsTime (unit_drift): the rigid unit first, a knot spacing
    # profiled below; a fixed "unit_interval_s" (a strip or window of a side) is held
    lever = float(fixed["unit_lever_m"]) if "unit_lever_m" in fixed else math.inf
    model = model.with_unit_lever(lever)  # held, or chosen below after the drift
    base_model = model
    interval = math.inf if model.unit_options else float("nan")
    if "unit_interval_s" in fixed and model.unit_options:
        interval = float(fixed["unit_interval_s"])
        model = model.with_unit_interval(interval)
    elif model.unit_options:
        model = model.with_unit_interval(math.inf)
    # units: estimable only with at least two units holding planes
    for n in ("unit_before", "unit_after"):
        if n in free and model.n_units(n, ids) < 2:
            free.remove(n)
            theta[n] = 0.0
            source[n] = "off"
            nu = model.n_units(n, ids)
            notes[n] = (
                "no acquisition units given"
                if nu == 0
                else "one acquisition unit holds every plane: its rigid error moves the whole "
                "side like the motion and cannot be estimated; give it as a fixed component"
            )
    few = k < MIN_PLANES_VCE
    turn = (
        UNIT_TURN
        and "unit_lever_m" not in fixed
        and not few
        and any(n in free for n in ("unit_before", "unit_after"))
    )
    drift = ()
    if (
        "unit_interval_s" not in fixed
        and not few
        and any(n in free for n in ("unit_before", "unit_after"))
    ):
        drift = model.unit_intervals
    start_var = max(float(np.mean(es * es) - np.mean(ps)), float(np.median(ps)), _FLOOR)
    # a cold start every time: warm starts from the adjustment's last round settled on worse
    # fixed points in the calibration (a spatial component of 25 mm where this found 4 mm)
    theta0 = {n: start_var / max(len(free), 1) for n in free}
    kernels = [SpatialKernel()]
    if "spatial" in free or "spatial" in fixed_var:
        fams = DEFAULT_FAMILIES if families is None else families
        kernels = _candidate_kernels(model.centroids[ids], sub.size < k, fixed, fams) or [
            SpatialKernel()
        ]
        if not kernels[0].active:
            free = [n for n in free if n != "spatial"]
            theta["spatial"], source["spatial"] = 0.0, "off"
            notes["spatial"] = "fewer than 3 planes"

    # the planes' within-epoch unit contrasts (unit_contrasts): rows beside the misclosures,
    # no motion in them, their unit shares beside the planes'
    rows = model.contrast_rows() if any(n in free for n in ("unit_before", "unit_after")) else None
    sel_rows = None
    if rows is not None and rows.size > VCE_MAX_CONTRASTS:
        # a seeded subset keeps REML's matrices small; the motion uses every row
        sel_rows = np.sort(
            np.random.default_rng(seed).choice(rows.size, VCE_MAX_CONTRASTS, replace=False)
        )
        rows = rows.take(sel_rows)
    planes_only = (es, xs, ps, inf_s)
    es_planes = es
    if rows is not None:
        # their own misfit (a unit's error is no translation: a TLS setup turns about the
        # instrument, an ALS strip rolls) is a nugget of the rows, estimated beside the units
        # and carried to the motion's conditioning (condition_on_contrasts)
        theta0[CONTRAST_NUGGET] = max(float(np.median(rows.var)), _FLOOR)
        m_rows = rows.size
        es = np.concatenate([es, rows.value])
        xs = np.vstack([xs, np.zeros((m_rows, xs.shape[1]))])
        ps = np.concatenate([ps, rows.var])
        if inf_s is not None:
            inf_s = np.concatenate([inf_s, np.zeros(m_rows)])

    def fit(mdl, kern, with_rows=True):
        bases = mdl.bases(ids, kern)
        bases = {n: b for n, b in bases.items() if n in free or n in fixed_var}
        if rows is None or not with_rows:
            fx = {n: fixed_var[n] for n in fixed_var if n in bases}
            e_, x_, p_, i_ = planes_only
            th0 = {n: v for n, v in theta0.items() if n != CONTRAST_NUGGET}
            th, sd, it, conv, m2ll, pc = _reml_fixed_point(e_, x_, ts, p_, bases, th0, fx, i_, rts)
            return (th, sd, it, conv, m2ll, kern, pc, bases, fx)
        if rows is not None:
            rr = mdl.contrast_rows()
            rr = rr if sel_rows is None else rr.take(sel_rows)
            bases = mdl.contrast_bases(ids, rr, bases)
            bases[CONTRAST_NUGGET] = np.diag(np.concatenate([np.zeros(ids.size), np.ones(rr.size)]))
        fx = {n: fixed_var[n] for n in fixed_var if n in bases}
        th, sd, it, conv, m2ll, pc = _reml_fixed_point(
            es, xs, ts, ps, bases, theta0, fx, inf_s, rts
        )
        log.debug("REML %s %.3g m: %s, -2logL %.6g", kern.family, kern.range_m, th, m2ll)
        return (th, sd, it, conv, m2ll, kern, pc, bases, fx)

    # -2 log L of each family's candidate ranges in the last profile, in grid order (the
    # search the component test accounts for)
    trail: Dict[str, List[float]] = {}

    def profile(mdl):
        # each fit keeps its kernel's bases: the chosen one's serve the refit with the tilts
        # and the test of the components below (a spatial basis is the costly part of a fit)
        fits: Dict[str, tuple] = {}
        trail.clear()
        for kern in kernels:
            f = fit(mdl, kern)
            trail.setdefault(kern.family, []).append(float(f[4]))
            if kern.family not in fits or f[4] < fits[kern.family][4]:
                fits[kern.family] = f
        best = min(fits.values(), key=lambda f: f[4])
        sph = fits.get("spherical")
        if sph is not None and best[4] > sph[4] - FAMILY_MARGIN:
            best = sph
        # a spatial component that REML set to zero says nothing of the family
        if len(fits) > 1 and best[0].get("spatial", 0.0) <= 0 and sph is not None:
            best = sph
        return best, fits

    best, fits = profile(model)
    if drift:
        # the units' drift along GpsTime (unit_drift): each knot spacing at the kernel just
        # chosen, the likeliest taken when it beats the rigid unit by UNIT_INTERVAL_MARGIN,
        # and the kernel profiled again under it
        # chosen on the misclosures alone: the contrast rows see a unit's error within one
        # epoch, where a TLS setup's turn about the instrument reads as a drift along the
        # scan's time (docs/accuracy.md, "Units tied on the planes they share")
        ref = best if rows is None else fit(model, best[5], with_rows=False)
        kern = best[5]
        dt = _likelier(
            drift,
            lambda d: fit(base_model.with_unit_interval(d), kern, with_rows=False),
            ref,
            "unit drift",
        )  # fmt: skip
        if dt is not None:
            interval = dt
            model = base_model.with_unit_interval(dt)
            best, fits = profile(model)
    if turn and not math.isfinite(interval):
        # the units' turn about their origins (UNIT_LEVERS_M), for rigid units (a drift
        # along GpsTime is the trajectory's own model; on MLS pairs a turn of each knot's
        # stretch was taken where none was drawn, docs/accuracy.md "Units that turn"): each
        # lever at the kernel chosen, with the contrast rows (a turn moves two units' points
        # on one plane apart by what their positions say), the likeliest taken when it beats
        # translations alone
        kern = best[5]
        lv = _likelier(UNIT_LEVERS_M, lambda v: fit(model.with_unit_lever(v), kern), best, "lever")
        if lv is not None:
            lever = lv
            model = model.with_unit_lever(lv)
            best, fits = profile(model)
    th, sd, it, conv, m2ll_best, kern, pc, bases, fx = best
    if REML_TILT_SHARE < 1.0 and np.any(ts_full) and (len(kernels) > 1 or REML_TILT_SHARE > 0):
        # the kernel is chosen from the offsets; the components' values are then estimated
        # with the tilts' information as the adjustment and its plane tests use it (else the
        # w-tests, made with the tilts, would hold the components for too small and reject)
        th, sd, it, conv, m2ll_best, pc = _reml_fixed_point(
            es, xs, ts_full, ps, bases, theta0, fx, inf_s, rts_full
        )
    if COMPONENT_TEST_ALPHA is not None and not few:
        th, sd, it, conv, pc, lr, zeroed = _test_plane_level(
            (es, xs, ts_full, ps, bases, fx, inf_s, rts_full),
            (th, sd, it, conv, m2ll_best, pc),
            theta0,
            paths=[np.array(v) for v in trail.values()] if len(kernels) > 1 else None,
        )
        if lr is not None:
            notes["plane_level"] = (
                f"no plane-level error beyond the point noise: REML likelihood ratio {lr:.2f} "
                f"of the components {', '.join(zeroed)} against none is below the "
                f"{COMPONENT_TEST_ALPHA:.0%} point of its null (with a spatial range "
                "searched: of the search's bound); they are set to 0"
            )
            for n in zeroed:
                notes[n] = "set to 0: not significant (see the notes)"
    rng_m = kern.range_m
    sds = {}
    for n in free:
        theta[n] = float(th.get(n, 0.0))
        source[n] = "estimated"
        sds[n] = float(sd.get(n, float("nan")))
    if rows is not None:
        theta[CONTRAST_NUGGET] = float(th.get(CONTRAST_NUGGET, 0.0))
        source[CONTRAST_NUGGET] = "estimated"
    if few and "plane" in free:
        # a handful of planes cannot pin the plane component down: take the conservative
        # mean square misclosure (white part included) or the caller's floor, unless REML
        # found more
        prior = max(float(np.mean(es_planes**2)), theta.get("plane", 0.0), float(prior_plane_var))
        theta["plane"] = prior
        source["plane"] = "prior"
        notes["plane"] = (
            f"only {k} planes (< {MIN_PLANES_VCE}): the plane component is a conservative "
            "prior (the mean square misclosure, at least a quarter of the point noise), not an "
            "estimate"
        )
    if not conv:
        notes["reml"] = f"REML did not converge in {VCE_MAX_ITER} iterations"
    for n in COMPONENT_NAMES:
        theta.setdefault(n, 0.0)
        source.setdefault(n, "off")
    if theta.get("spatial", 0.0) <= 0:
        rng_m = float("nan") if "spatial_range_m" not in fixed else rng_m
    kern = SpatialKernel(kern.family, float(rng_m))
    pc = {k: v for k, v in pc.items() if source.get(k[0]) == source.get(k[1]) == "estimated"}
    m2ll = {f: float(v[4]) for f, v in fits.items()}
    if interval == interval and not any(
        source.get(n) != "off" and theta.get(n, 0.0) > 0 for n in ("unit_before", "unit_after")
    ):
        interval = math.inf  # no unit component in force: nothing drifts
        lever = math.inf
    return Estimate(
        theta,
        sds,
        source,
        notes,
        float(rng_m),
        int(it),
        bool(conv),
        pc,
        kern,
        m2ll,
        float(interval),
        float(lever),
    )


# --------------------------------------------------------------------------- random tilt


def tilt_information(a: np.ndarray, r: np.ndarray, tilt_var: float):
    """Each plane's tilt information on the rotation with a random tilt of variance
    ``tilt_var`` per plane (rad², on each of the normal's two degrees of freedom).

    A plane's tilt is seen with the point-noise covariance ``C_j`` (2x2 on two orthonormal
    axes ``E_j`` (3, 2) in the plane: a rotation about the normal tilts nothing), so its
    information on the motion's rotation is ``a_j = E_j C_j⁻¹ E_jᵀ`` (3x3, rank 2) and its
    right-hand side ``r_j = a_j v_j`` (``v_j`` the tilt misclosure: the plane's own rotation
    less the motion's). A random tilt ``τ_j ~ N(0, σ_t² I₂)`` — what a survey-error field's
    gradient over the plane does — makes them ``E_j (C_j + σ_t² I₂)⁻¹ E_jᵀ = a_j (I₃ + σ_t²
    a_j)⁻¹`` and ``(I₃ + σ_t² a_j)⁻¹ r_j`` (``a_j`` and ``(I₃ + σ_t² a_j)⁻¹`` commute, and the
    normal, null for ``a_j``, stays null): one batched 3x3 solve per plane, no tangent basis.
    :func:`tilt_information_reference` is the slow, obvious form.

    Parameters
    ----------
    a : (k, 3, 3) float64
        Tilt information of each plane on the rotation, rad⁻² (scaled by the point-level
        factor).
    r : (k, 3) float64
        Its right-hand side, rad⁻¹.
    tilt_var : float
        ``σ_t²``, rad².

    Returns
    -------
    a_t : (k, 3, 3) float64, r_t : (k, 3) float64
        ``a`` and ``r`` themselves (the same arrays) when ``tilt_var <= 0``.
    """
    if not tilt_var > 0:
        return a, r
    m = np.eye(3) + float(tilt_var) * a
    sol = np.linalg.solve(m, np.concatenate([a, r[:, :, None]], axis=2))
    at = sol[:, :, :3]
    return 0.5 * (at + at.transpose(0, 2, 1)), sol[:, :, 3]


def _tilt_woodbury(at, zt, cov):
    """The pieces of ``(D + Z_t C Z_tᵀ)⁻¹ = D⁻¹ − F K Fᵀ`` on the tilt information ``at =
    D⁻¹`` (k, 3, 3), rank 2 per plane, without inverting ``C`` (r, r): ``F = D⁻¹ Z_t`` (k, 3,
    r), ``G = Z_tᵀ D⁻¹ Z_t`` (r, r) and ``K = C (I + G C)⁻¹`` (r, r)."""
    f = np.einsum("kij,kjr->kir", at, zt)
    g = np.einsum("kir,kis->rs", zt, f)
    g = 0.5 * (g + g.T)
    k_mat = np.linalg.solve(np.eye(g.shape[0]) + cov @ g, cov)
    return f, g, 0.5 * (k_mat + k_mat.T)


def tilts_given_offsets(at, rtl, zt, z_o, lam, mean, viz, h, y_o):
    """The planes' tilts' information on the motion (6, 6) and its right-hand side (6,) when
    the units' errors move the planes' offsets and tilt them too (the offsets' own terms
    ``Hᵀ V⁻¹ H``, ``Hᵀ V⁻¹ y_o`` not included).

    The offsets ``y_o = H x + Z_o c + ε_o`` (``Cov = V``, the units' part ``Z_o Λ Z_oᵀ``
    included) and the tilts ``y_t = R x + Z_t c + ε_t`` (``R`` the rotation; ``Cov ε_t = D``,
    each plane's point-noise tilt with its random tilt) share the units' errors ``c ~ N(μ,
    Λ)``. Given the offsets the tilts are ``ỹ_t = y_t − Z_t a = R̃ x + ε`` with ``a = μ + Λ
    Z_oᵀ V⁻¹ y_o``, ``R̃ = R − Z_t Λ Z_oᵀ V⁻¹ H`` and ``Cov ε = D + Z_t P Z_tᵀ``, ``P = Λ −
    Λ Z_oᵀ V⁻¹ Z_o Λ``, so the joint GLS is the offsets' plus ``R̃ᵀ W R̃`` and ``R̃ᵀ W ỹ_t``
    with ``W = (D + Z_t P Z_tᵀ)⁻¹`` by Woodbury on the information ``D⁻¹`` (rank 2 per
    plane: the normal's turn is not seen) without inverting ``P``:
    ``W = D⁻¹ − F P (I + G P)⁻¹ Fᵀ``, ``F = D⁻¹ Z_t``, ``G = Z_tᵀ D⁻¹ Z_t``.

    Parameters
    ----------
    at : (k, 3, 3) float64
        Each plane's tilt information ``D_j⁻¹`` on the rotation (rad⁻²).
    rtl : (k, 3) float64
        Its right-hand side ``D_j⁻¹ y_t,j``.
    zt : (k, 3, r) float64
        The units' errors' design in the tilts (rad per unit of ``c``).
    z_o : (k, r) float64
        Their design in the offsets.
    lam : (r, r) float64
        Their covariance ``Λ``; ``mean`` (r,) their mean ``μ``.
    viz : (k, r) float64
        ``V⁻¹ Z_o``.
    h : (k, 6) float64
        The offsets' design ``H``; ``y_o`` (k,) the offsets less the units' mean, ``y_o −
        Z_o μ`` (the misclosures less the contrasts' shift, :class:`ContrastCondition`).

    Returns
    -------
    info : (6, 6) float64
    rhs : (6,) float64
    wz : (6, r) float64
        ``R̃ᵀ W Z_t``: the right-hand side's change per unit error through the tilts (its
        change per offset is ``−wz Λ Z_oᵀ V⁻¹``), for the motion's gains.
    """
    return _given_offsets(at, rtl, zt, mean, viz, y_o, lam, _offset_parts(at, zt, z_o, lam, viz, h))


class _OffsetParts(NamedTuple):
    """The pieces of the tilts given the offsets (:func:`tilts_given_offsets`) that do not
    depend on the observations: ``B = Λ Z_oᵀ V⁻¹ H`` (r, 6), ``F = D⁻¹ Z_t`` (k, 3, r),
    ``G`` and ``K = P (I + G P)⁻¹`` (r, r), ``Fᵀ R`` and ``Fᵀ R̃`` (r, 6)."""

    bmat: np.ndarray
    f: np.ndarray
    g: np.ndarray
    k_mat: np.ndarray
    ftr: np.ndarray
    ftr_t: np.ndarray


def _offset_parts(at, zt, z_o, lam, viz, h) -> _OffsetParts:
    bmat = lam @ (viz.T @ h)  # (r, 6)
    p = lam - lam @ (z_o.T @ viz) @ lam
    f, g, k_mat = _tilt_woodbury(at, zt, p)  # K = P (I + G P)⁻¹
    ftr = np.zeros((zt.shape[2], 6))
    ftr[:, :3] = f.sum(axis=0).T  # Fᵀ R
    return _OffsetParts(bmat, f, g, k_mat, ftr, ftr - g @ bmat)  # Fᵀ R̃


def _given_offsets(at, rtl, zt, mean, viz, y_o, lam, parts: _OffsetParts):
    """:func:`tilts_given_offsets` from its :class:`_OffsetParts`."""
    bmat, f, g, k_mat, ftr, ftr_t = parts
    a = mean + lam @ (viz.T @ y_o)
    rdr = np.zeros((6, 6))
    rdr[:3, :3] = at.sum(axis=0)
    info = rdr - ftr.T @ bmat - bmat.T @ ftr + bmat.T @ g @ bmat  # R̃ᵀ D⁻¹ R̃
    fyt = np.einsum("kir,ki->r", zt, rtl) - g @ a  # Fᵀ ỹ_t
    rhs = np.zeros(6)
    rhs[:3] = rtl.sum(axis=0) - np.einsum("kir,r->i", f, a)
    rhs -= bmat.T @ fyt  # R̃ᵀ D⁻¹ ỹ_t
    info = info - ftr_t.T @ k_mat @ ftr_t
    rhs = rhs - ftr_t.T @ k_mat @ fyt
    wz = ftr_t.T - (ftr_t.T @ k_mat) @ g  # R̃ᵀ D⁻¹ Z_t − (Fᵀ R̃)ᵀ K G
    return 0.5 * (info + info.T), rhs, wz


def tilts_marginal(at, rtl, zt, lam, mean):
    """The planes' tilts' information on the motion's rotation (3, 3) and its right-hand
    side (3,) when the units' errors ``c ~ N(μ, Λ)`` tilt them, taken on their own (not
    given the offsets, :func:`tilts_given_offsets`): ``Rᵀ W R`` and ``Rᵀ W (y_t − Z_t μ)``
    with ``W = (D + Z_t Λ Z_tᵀ)⁻¹ = D⁻¹ − F Λ (I + G Λ)⁻¹ Fᵀ``, ``F = D⁻¹ Z_t``, ``G =
    Z_tᵀ D⁻¹ Z_t`` (Woodbury on the tilt information). This is what the plane-level
    components (REML of the offsets) and the plane tests take as the tilts' information on
    the motion: the tilts weighed as the drift makes them, without their correlation with
    the offsets (which the adjustment itself uses).

    Parameters
    ----------
    at : (k, 3, 3) float64
        Each plane's tilt information ``D_j⁻¹`` on the rotation (rad⁻²).
    rtl : (k, 3) float64
        Its right-hand side ``D_j⁻¹ y_t,j``.
    zt : (k, 3, r) float64
        The units' errors' design in the tilts.
    lam : (r, r) float64
        Their covariance; ``mean`` (r,) their mean.

    Returns
    -------
    info : (3, 3) float64
    rhs : (3,) float64
    """
    f, _, k_mat = _tilt_woodbury(at, zt, lam)  # K = Λ (I + G Λ)⁻¹
    fs = f.sum(axis=0)  # (3, r): Rᵀ F
    d = rtl - np.einsum("kir,r->ki", f, mean)  # D⁻¹ (y_t − Z_t μ)
    fy = np.einsum("kir,ki->r", zt, d)
    info = at.sum(axis=0) - fs @ k_mat @ fs.T
    rhs = d.sum(axis=0) - fs @ (k_mat @ fy)
    return 0.5 * (info + info.T), rhs


def tilt_information_reference(a: np.ndarray, r: np.ndarray, tilt_var: float, rel_tol=1e-9):
    """The slow, obvious form of :func:`tilt_information`: per plane, the tangent axes ``E``
    and the point-noise covariance ``C`` of the tilt from the eigenvectors of ``a`` (its
    eigenvalues above ``rel_tol`` × the largest), the tilt misclosure ``v = E C Eᵀ r``, and
    ``E (C + σ_t² I)⁻¹ Eᵀ`` and ``E (C + σ_t² I)⁻¹ Eᵀ v`` (a loop over planes)."""
    k = a.shape[0]
    at, rt = np.zeros((k, 3, 3)), np.zeros((k, 3))
    for j in range(k):
        w, vec = np.linalg.eigh(0.5 * (a[j] + a[j].T))
        keep = w > rel_tol * w.max()
        e = vec[:, keep]
        c = np.diag(1.0 / w[keep])
        v = e @ c @ e.T @ r[j]
        wt = np.linalg.inv(c + float(tilt_var) * np.eye(int(keep.sum())))
        at[j] = e @ wt @ e.T
        rt[j] = at[j] @ v
    return at, rt


@dataclass(frozen=True)
class TiltEstimate:
    """The random tilt per plane (:func:`estimate_tilt_variance`).

    Attributes
    ----------
    var : float
        ``σ_t²``, rad² (0 when off or nil).
    sd : float
        Standard deviation of ``var`` from the REML information, rad² (NaN when not
        estimated).
    source : str
        "estimated", "fixed" or "off".
    iterations : int
    converged : bool
    note : str
        Why it is off or nil, and the tilts left out; empty otherwise.
    keep : (k,) bool, optional
        Planes whose tilt is used (False: left out by the tilt test); None: all.
    """

    var: float = 0.0
    sd: float = float("nan")
    source: str = "off"
    iterations: int = 0
    converged: bool = True
    note: str = ""
    keep: Optional[np.ndarray] = None

    @property
    def sigma_rad(self) -> float:
        """``σ_t``, rad."""
        return math.sqrt(max(self.var, 0.0))

    def to_dict(self) -> Dict[str, object]:
        sd = self.sd / (2.0 * self.sigma_rad) if self.sigma_rad > 0 else float("nan")
        out: Dict[str, object] = {
            "sigma_rad": _num(self.sigma_rad), "sd_rad": _num(sd), "source": self.source,
        }  # fmt: skip
        if self.note:
            out["note"] = self.note
        return out


def _tilt_pinv(a: np.ndarray) -> np.ndarray:
    """(k, 3, 3) pseudo-inverses of the tilt informations ``a`` (k, 3, 3) on their range:
    each plane's point-noise tilt covariance ``C_j`` in the rotation's coordinates."""
    w, vec = np.linalg.eigh(0.5 * (a + a.transpose(0, 2, 1)))
    big = (w > 1e-9 * w.max(axis=1, keepdims=True)) & (w > 0)
    inv = np.divide(1.0, w, out=np.zeros_like(w), where=big)
    return np.einsum("kij,kj,klj->kil", vec, inv, vec)


def _tilt_gls(a, r, hvh, hvy, s):
    """The GLS with the random tilt ``s`` (rad²): ``Q`` (6, 6), the increment ``β`` (6,),
    the weighted tilt residuals ``g`` (k, 3) and the projector's blocks ``Π_jj`` (k, 3, 3)."""
    at, rtl = tilt_information(a, r, s)
    n = np.array(hvh, dtype=np.float64, copy=True)
    n[:3, :3] += at.sum(axis=0)
    rhs = np.array(hvy, dtype=np.float64, copy=True)
    rhs[:3] += rtl.sum(axis=0)
    q = np.linalg.pinv(0.5 * (n + n.T), hermitian=True)  # a motion the planes leave free: 0
    beta = q @ rhs
    g = np.linalg.solve(np.eye(3) + s * a, (r - a @ beta[:3])[:, :, None])[:, :, 0]
    return q, beta, g, at - at @ q[:3, :3] @ at


def _tilt_weighted_design(at, parts: _OffsetParts):
    """``(W R̃)_j`` (k, 3, 6) of the tilts given the offsets (:func:`tilts_given_offsets`):
    ``W R̃ = D⁻¹ R̃ − F K Fᵀ R̃``, ``D⁻¹ R̃_j = a_j [I 0] − F_j B``. The motion's gain on the
    tilt of plane ``j`` is ``Q (W R̃)_jᵀ``."""
    wr = np.zeros((at.shape[0], 3, 6))
    wr[:, :, :3] = at
    wr -= np.einsum("kir,rc->kic", parts.f, parts.bmat + parts.k_mat @ parts.ftr_t)
    return wr


def tilt_gains(at, zt, z_o, lam, viz, h, q):
    """The motion's gain on each plane's tilt and the covariance its tilts' own noise gives,
    when the units' errors tilt the planes (:func:`tilts_given_offsets`), for the
    covariance with another adjustment (:func:`joint_covariance`).

    Parameters
    ----------
    at, zt, z_o, lam, viz, h
        As :func:`tilts_given_offsets`.
    q : (6, 6) float64
        The motion's covariance ``Q`` (the inverse of the offsets' and tilts' information).

    Returns
    -------
    gain : (6, k, 3) float64
        ``∂x̂/∂y_t,j = Q (W R̃)_jᵀ`` (rad per rad for the rotation rows, m per rad for the
        translation rows).
    noise : (6, 6) float64
        ``Q R̃ᵀ W D W R̃ Q = Σ_j gain_j D_j gain_jᵀ``, ``D_j`` each plane's tilt covariance
        without the units (point noise and random tilt; the pseudo-inverse of ``at_j``):
        what replaces ``Q T Q`` of the tilts taken on their own.
    """
    wr = _tilt_weighted_design(at, _offset_parts(at, zt, z_o, lam, viz, h))
    gain = np.einsum("cd,kid->cki", q, wr)
    noise = np.einsum("cki,kij,dkj->cd", gain, _tilt_pinv(at), gain)
    return gain, 0.5 * (noise + noise.T)


def _tilt_gls_drift(a, r, hvh, hvy, s, drift):
    """:func:`_tilt_gls` when the units' errors tilt the planes too (``drift``, the
    arguments of :func:`tilts_given_offsets` after ``at, rtl``: ``zt, z_o, lam, mean, viz,
    h, y_o``): the tilts given the offsets, ``Cov = D(s) + Z_t P Z_tᵀ``, with ``W`` by
    Woodbury as there. Returns ``Q`` (6, 6), ``β`` (6,), the weighted tilt residuals ``u =
    W ẽ`` (k, 3) and the projector's diagonal blocks ``Π_jj = W_jj − (W R̃)_j Q (W
    R̃)_jᵀ`` (k, 3, 3)."""
    zt, z_o, lam, mean, viz, h, y_o = drift
    at, rtl = tilt_information(a, r, s)
    parts = _offset_parts(at, zt, z_o, lam, viz, h)
    info, rhs_t, _ = _given_offsets(at, rtl, zt, mean, viz, y_o, lam, parts)
    n = np.array(hvh, dtype=np.float64, copy=True) + info
    q = np.linalg.pinv(0.5 * (n + n.T), hermitian=True)
    beta = q @ (np.asarray(hvy, dtype=np.float64) + rhs_t)
    wr = _tilt_weighted_design(at, parts)
    f, k_mat = parts.f, parts.k_mat
    # D⁻¹ ẽ, ẽ_j = y_j − Z_t,j a − (R̃ β)_j = y_j − β_rot − Z_t,j (a − B β)
    shift = beta[None, :3] + np.einsum("kir,r->ki", zt, _drift_mean(drift, beta))
    d = rtl - np.einsum("kij,kj->ki", at, shift)
    u = d - np.einsum("kir,r->ki", f, k_mat @ np.einsum("kir,ki->r", zt, d))
    wjj = at - np.einsum("kir,rs,kjs->kij", f, k_mat, f)
    pjj = wjj - np.einsum("kic,cd,kjd->kij", wr, q, wr)
    return q, beta, u, pjj


def _drift_mean(drift, beta):
    """(r,) the units' errors the offsets predict at the motion ``β``: ``μ + Λ Z_oᵀ V⁻¹ (y_o −
    H β)`` (``drift`` as :func:`_tilt_gls_drift` takes it)."""
    _, _, lam, mean, viz, h, y_o = drift
    return mean + lam @ (viz.T @ (y_o - h @ beta))


def _tilt_helmert(a, r, hvh, hvy, s, floor, drift=None):
    """The Helmert / Förstner iteration of :func:`estimate_tilt_variance` from ``s``: (s,
    sd, iterations, converged); ``s`` 0 when it falls below ``floor``."""
    converged, it, fisher = False, 0, float("nan")
    while it < TILT_MAX_ITER:
        it += 1
        if drift is None:
            _, _, g, pjj = _tilt_gls(a, r, hvh, hvy, s)
        else:
            _, _, g, pjj = _tilt_gls_drift(a, r, hvh, hvy, s, drift)
        num = float((g * g).sum())
        den = float(np.trace(pjj, axis1=1, axis2=2).sum())
        fisher = float(np.einsum("kij,kji->", pjj, pjj))
        s_new = s * num / den if den > 0 else 0.0
        if s_new < floor:
            return 0.0, float("nan"), it, True
        done = abs(s_new - s) <= TILT_TOL * s
        s = s_new
        if done:
            converged = True
            break
    sd = math.sqrt(2.0 / fisher) if fisher > 0 else float("nan")
    return float(s), sd, it, converged


def estimate_tilt_variance(
    a: np.ndarray,
    r: np.ndarray,
    hvh: np.ndarray,
    hvy: np.ndarray,
    *,
    start: float = 0.0,
    drift: Optional[tuple] = None,
    left_out: Optional[np.ndarray] = None,
) -> TiltEstimate:
    """REML estimate of the random tilt's variance ``σ_t²`` (rad²) from the planes' tilt
    misclosures, the offsets' part of the model held at its current components, with a
    test of each plane's tilt.

    The tilt of plane ``j`` is an observation of the motion's rotation with covariance
    ``C_j + σ_t² I₂`` (:func:`tilt_information`); the offsets give the information ``HᵀV⁻¹H``
    and right-hand side ``HᵀV⁻¹y`` on the motion. For a given ``σ_t²`` the GLS increment is
    ``β = Q (Σ r̃_j + HᵀV⁻¹y)``, ``Q = (Σ ã_j + HᵀV⁻¹H)⁻¹``, the weighted tilt residuals
    ``g_j = (C_j + σ_t² I)⁻¹ (v_j − β_rot) = (I + σ_t² a_j)⁻¹ (r_j − a_j β_rot)`` and the
    diagonal blocks of the REML projector ``Π_jj = ã_j − ã_j Q_rot ã_j``. The REML equation
    of the one component is ``Σ |g_j|² = Σ tr Π_jj``; it is solved by the Helmert / Förstner
    iteration ``σ_t² ← σ_t² Σ |g_j|² / Σ tr Π_jj`` (Förstner 1979; Koch 1999 §3.6), which
    stays positive and takes the large steps from the point-noise level a field's tilts need.
    A variance below :data:`TILT_NEGLIGIBLE` × the median point-noise tilt variance is nil.
    The standard deviation is ``√(2 / Σ tr Π_jj²)`` (the Fisher information with the planes'
    leverage cross terms left out).

    Robustness: one plane whose tilt is grossly off (a mismatched or rebuilt surface: 23 mrad
    where the others scatter by 0.1 mrad, on a renovated pair) would set ``σ_t`` alone. The
    iteration starts from a robust value (the median over planes of ``|v_j|² / (2 ln 2) −
    c_j``, ``c_j`` the point-noise tilt variance: ``|v_j|² / (c_j + σ_t²)`` is χ² with two
    degrees of freedom), and each plane's tilt is tested by ``q_j = g_jᵀ (C_j + σ_t² I) g_j``
    (χ²₂) against ``max(K_REJECT_MIN², −2 ln(TILT_ALPHA / k))`` (Bonferroni); the tilts beyond
    are left out of the estimate and of the motion (:attr:`TiltEstimate.keep`), and the
    estimate and test are repeated until the set settles. Cost: batched 3x3 solves, linear
    in planes.

    Parameters
    ----------
    a : (k, 3, 3) float64
        Point-noise tilt information of each plane on the rotation, rad⁻² (scaled).
    r : (k, 3) float64
        Its right-hand side at the current motion, rad⁻¹.
    hvh : (6, 6) float64
        ``HᵀV⁻¹H`` of the offsets.
    hvy : (6,) float64
        ``HᵀV⁻¹y`` of the offsets at the current motion.
    start : float
        Starting value (rad²); <= 0: the robust value above.
    drift : tuple, optional
        When the units' errors tilt the planes too: ``(zt (k, 3, r), z_o (k_o, r), lam (r,
        r), mean (r,), viz (k_o, r), h (k_o, 6), y_o (k_o,))`` as
        :func:`tilts_given_offsets` takes them (the offsets' ``hvh``, ``hvy`` as above). The
        tilts are then taken given the offsets, with covariance ``D(σ_t²) + Z_t P Z_tᵀ``, so
        that the drift's tilts are not counted a second time in ``σ_t``; the REML equation
        is the same with ``g = W ẽ`` and ``Π`` of that covariance
        (:func:`_tilt_gls_drift`), and each plane's tilt test is against its misclosure
        less the drift's predicted tilt. Cost: ``O(k r²)``.
    left_out : (k,) bool, optional
        Planes whose tilt an earlier call left out: they stay out (the caller's rounds of
        components and tilts then cannot cycle on one plane's borderline test).

    Returns
    -------
    TiltEstimate
    """
    k = a.shape[0]
    if k < MIN_PLANES_TILT:
        return TiltEstimate(note=f"only {k} planes (< {MIN_PLANES_TILT}): no random tilt")
    cinv = _tilt_pinv(a)
    cpt = 0.5 * np.trace(cinv, axis1=1, axis2=2)
    c_med = float(np.median(cpt))
    if not c_med > 0:
        return TiltEstimate(note="no tilt information")
    floor = TILT_NEGLIGIBLE * c_med
    crit = max(K_REJECT_MIN**2, -2.0 * math.log(TILT_ALPHA / k))
    keep = np.ones(k, dtype=bool) if left_out is None else ~np.asarray(left_out, dtype=bool)
    s = float(start)
    if not s > floor:
        v = np.einsum("kij,kj->ki", cinv, r)
        s = max(float(np.median((v * v).sum(axis=1) / (2.0 * math.log(2.0)) - cpt)), c_med)
    sd, it, conv = float("nan"), 0, True
    for _ in range(5):
        dk = None if drift is None else (drift[0][keep],) + tuple(drift[1:])
        s, sd, n_it, conv = _tilt_helmert(a[keep], r[keep], hvh, hvy, max(s, c_med), floor, dk)
        it += n_it
        # every plane's tilt tested against the GLS of the kept ones
        if drift is None:
            q, beta, _, _ = _tilt_gls(a[keep], r[keep], hvh, hvy, s)
            res = r - a @ beta[:3]
        else:  # less the drift's tilt the offsets predict
            q, beta, _, _ = _tilt_gls_drift(a[keep], r[keep], hvh, hvy, s, dk)
            shift = beta[None, :3] + np.einsum("kir,r->ki", drift[0], _drift_mean(drift, beta))
            res = r - np.einsum("kij,kj->ki", a, shift)
        g = np.linalg.solve(np.eye(3) + s * a, res[:, :, None])[:, :, 0]
        qj = np.einsum("ki,kij,kj->k", g, cinv, g) + s * (g * g).sum(axis=1)
        new = qj <= crit
        if left_out is not None:
            new &= ~left_out
        if int(new.sum()) < MIN_PLANES_TILT or np.array_equal(new, keep):
            break
        keep = new
    notes = []
    if s <= 0:
        notes.append("the planes' tilts agree within their point noise")
    if not conv:
        notes.append(f"the tilt variance did not converge in {TILT_MAX_ITER} iterations")
    n_out = int((~keep).sum())
    if n_out:
        whose = "1 plane's tilt" if n_out == 1 else f"{n_out} planes' tilts"
        notes.append(f"{whose} left out (χ² of the tilt misclosure beyond {crit:.1f})")
    return TiltEstimate(float(s), sd, "estimated", it, conv, "; ".join(notes), keep)


# --------------------------------------------------------------------------- robustness


def igg3_weight(w: np.ndarray, k0: float, k1: float) -> np.ndarray:
    """IGG-III weights of standardised residuals: 1 below ``k0``, 0 beyond ``k1``, and
    ``(k0/|w|) ((k1 − |w|)/(k1 − k0))²`` between (Yang 1994)."""
    a = np.abs(w)
    out = np.ones_like(a)
    mid = (a > k0) & (a <= k1)
    out[mid] = (k0 / a[mid]) * ((k1 - a[mid]) / (k1 - k0)) ** 2
    out[a > k1] = 0.0
    return out


def w_statistics(gls: PlaneGLS, e: np.ndarray) -> np.ndarray:
    """w-test statistics of correlated plane misclosures ``(Π e)_j / √Π_jj`` (k,)."""
    pi = gls.pi_matrix()
    d = np.sqrt(np.clip(np.diag(pi), 1e-300, None))
    return gls.pi_e(e) / d


def w_statistics_large(op: CovarianceOperator, e: np.ndarray, x: np.ndarray, t: np.ndarray,
                       rt: Optional[np.ndarray] = None):  # fmt: skip
    """Beyond :data:`DENSE_MAX_PLANES`: ``(Π e)_j`` from solves, standardised with
    ``diag(Π) ≈ 1 / diag(V)`` (exact for uncorrelated planes; the fixed-effect projection and
    the correlation are left out of the scale)."""
    vix = op.solve(x)
    vie = op.solve(e)
    m = x.T @ vix + t
    rhs = x.T @ vie + (0.0 if rt is None else rt)
    beta = np.linalg.lstsq(0.5 * (m + m.T), rhs, rcond=None)[0]
    pie = vie - vix @ beta
    return pie * np.sqrt(op.diag())


def robust_start(e: np.ndarray, x: np.ndarray, t: np.ndarray, p: np.ndarray, k_gross: float,
                 rt: Optional[np.ndarray] = None):  # fmt: skip
    """Gross outliers before any component is estimated: an IRLS fit of the misclosures with
    a MAD scale (diagonal model ``p + s²``), started from a least-median-of-squares fit (a
    fit that still holds several renovated buildings is pulled by decimetres, and a MAD of
    its residuals then masks them), and the planes whose standardised residual exceeds
    ``k_gross``. Returns (bool (k,) gross, robust plane sigma s (m))."""
    r = e - x @ _lms_start(e, x, p)
    rt = np.zeros(x.shape[1]) if rt is None else rt
    for _ in range(10):
        s2, z = _mad_scale(r, p)
        w = igg3_weight(z, 2.0, max(k_gross, 3.0))
        wt = w / (p + s2 + _FLOOR)
        m = x.T @ (wt[:, None] * x) + t
        beta = np.linalg.lstsq(m, x.T @ (wt * e) + rt, rcond=None)[0]
        r_new = e - x @ beta
        if np.allclose(r_new, r, atol=1e-12, rtol=0):
            r = r_new
            break
        r = r_new
    s2, z = _mad_scale(r, p)
    return np.abs(z) > k_gross, math.sqrt(s2)


#: median of the χ² distribution with one degree of freedom: a standardised residual's square
#: is below it half of the time
_CHI2_1_MEDIAN = 0.454936423119572


def _mad_scale(r: np.ndarray, p: np.ndarray):
    """Robust plane-level variance ``s²`` (MAD of the residuals less the median white part)
    and the residuals standardised by ``√(p + s²)``.

    ``MAD² − median(p)`` takes the median plane's white part for every plane. Among many
    imprecise planes (transferred ALS walls, ``p`` of several mm²) it falls below 0: ``s``
    was then 0 and a ground plane known to a fraction of a millimetre, standardised by its own
    tiny ``p``, was rejected (docs/accuracy.md, "Transferred planes"). There (only) ``s²`` is
    where the median of ``u_j = d_j² / (p_j + s²)`` (``d = r − median r``) is the median of
    χ²₁, each plane weighted by ``1 / (p_j + m²)`` (``m²`` the plain MAD²): each plane is
    standardised by its own white part, and a plane whose white part dwarfs the spread
    weighs little (:func:`_own_scale`). Where the former rule is positive it is kept: the
    per-plane rule everywhere changed sides of a dozen planes, whose median is of an almost
    exact fit (an ALS pair lost three sound roofs out of sample; docs/accuracy.md).
    """
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    s2 = mad * mad - float(np.median(p))
    if s2 <= 0.0 and r.size:
        s2 = _own_scale(r, p)
    s2 = max(s2, 0.0)
    return s2, r / np.sqrt(p + s2 + _FLOOR)


def _own_scale(r: np.ndarray, p: np.ndarray) -> float:
    """``s²`` ≥ 0 at which the weighted median of ``d_j² / (p_j + s²)`` is the median of χ²₁
    (weights ``1 / (p_j + m²)``, fixed at the plain MAD² ``m²`` so that the median falls
    monotonically with ``s²``: weights taken at the trial ``s²`` hand the median to the
    ground near ``s = 0`` and have spurious roots there), by bisection of
    ``[0, max d² / median(χ²₁)]``. With one ``p`` for all planes it is ``MAD² − p``."""
    d2 = (r - np.median(r)) ** 2
    pp = p + _FLOOR
    w = 1.0 / (pp + float(np.median(d2)) / _CHI2_1_MEDIAN)
    w = w / w.sum()

    def excess(s2: float) -> float:
        return _weighted_median(d2 / (pp + s2), w) - _CHI2_1_MEDIAN

    if excess(0.0) <= 0.0:
        return 0.0
    lo, hi = 0.0, float(d2.max()) / _CHI2_1_MEDIAN
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if excess(mid) > 0.0:
            lo = mid
        else:
            hi = mid
    return hi


LMS_SUBSETS = 500  # random elemental subsets of the least-median-of-squares start
LMS_SIZE = 8  # planes per subset (6 motion parameters, and room for poor geometry)


def _lms_start(e: np.ndarray, x: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Least median of squares (Rousseeuw 1984) of the plane misclosures by random subsets:
    the motion increment (6,) whose median squared residual is smallest (50 % breakdown).
    The offsets alone (no tilts: the tilts' information is centred on a solution that the
    outliers have pulled). Subsets are drawn with a fixed seed over the plane order, so the
    start is reproducible. Hand-written: scipy has no LMS / LTS regression."""
    k = e.size
    if k <= LMS_SIZE + 2:
        return np.zeros(x.shape[1])
    rng = np.random.default_rng(20190101)
    best, beta_best = np.inf, np.zeros(x.shape[1])
    wt = 1.0 / (p + _FLOOR)
    share = _direction_shares(x)
    for _ in range(LMS_SUBSETS):
        sub = rng.choice(k, LMS_SIZE, replace=False)
        xs = x[sub]
        m = xs.T @ (wt[sub, None] * xs)
        if np.linalg.cond(m) > 1e12:
            continue
        try:
            beta = np.linalg.solve(m, xs.T @ (wt[sub] * e[sub]))
        except np.linalg.LinAlgError:
            continue
        crit = _balanced_median((e - x @ beta) ** 2, share)
        if crit < best:
            best, beta_best = crit, beta
    return beta_best


def _direction_shares(x: np.ndarray) -> np.ndarray:
    """(k, 3) share of each plane in the translation information along x, y and z: the
    squared translation columns of the plane-level design (the plane normals), each column
    normalised to sum 1 (a direction no plane sees gets zeros)."""
    w = x[:, 3:6] ** 2
    tot = w.sum(axis=0)
    return np.divide(w, tot, out=np.zeros_like(w), where=tot > 0)


def _weighted_median(v: np.ndarray, w: np.ndarray) -> float:
    """Median of ``v`` with weights ``w`` (>= 0, sum 1): the smallest value whose cumulative
    weight reaches one half."""
    order = np.argsort(v)
    c = np.cumsum(w[order])
    return float(v[order][min(int(np.searchsorted(c, 0.5)), v.size - 1)])


def _balanced_median(r2: np.ndarray, share: np.ndarray) -> float:
    """The least-median-of-squares criterion per translation direction, summed.

    A plain median over planes is decided by the direction most planes see: in a town the
    walls outnumber the horizontal planes several times, so the median of the squared
    residuals does not depend on the vertical at all, and a subset holding one renovated
    building's sloped roof sets the vertical of the start by decimetres (the seed-1017 pair of
    the renovated-buildings case: the ground and four flat roofs were then rejected and the
    vertical was off by 184 mm). Here each direction's median is taken with the planes'
    shares in that direction as weights, so the planes that see a direction decide it, each
    with a 50 % breakdown point, and the three medians are summed.
    """
    return sum(
        _weighted_median(r2, share[:, d]) for d in range(share.shape[1]) if share[:, d].any()
    )


def effective_planes(v: CovarianceOperator, x: np.ndarray) -> float:
    """``n_eff``: ``(Σw)²/Σw²`` of ``w = 1/diag V`` times the ratio of the translation
    information with the full ``V`` to that with its diagonal alone."""
    dv = v.diag()
    w = 1.0 / dv
    n_w = float(w.sum() ** 2 / (w * w).sum())
    xt = x[:, 3:]
    info_full = xt.T @ v.solve(xt)
    info_diag = xt.T @ (w[:, None] * xt)
    tr_d = float(np.trace(info_diag))
    ratio = float(np.trace(info_full)) / tr_d if tr_d > 0 else 1.0
    return float(min(n_w * min(ratio, 1.0), v.k))
