"""Synthetic LiDAR scenes with known planar surfaces.

A scene is flat ground (the plane ``z = 0``) with box buildings (flat or gable roofs) and
a few trees, sampled as an airborne ("als"), mobile ("mls") or terrestrial ("tls") survey
would roughly see it. Every planar surface (the ground, each roof plane, each wall) is a
:class:`Surface` with its exact plane, so tests and benchmarks of the plane-segmentation
engine can score recovered planes against the truth, and :func:`plane_distances` gives each
point's signed distance to its true plane.

Conventions
-----------
- Coordinates are metres, ``(N, 3)`` float64. The scene is built in a local frame whose
  ground covers ``[0, extent_m] x [0, extent_m]`` at ``z = 0``, then every point is shifted
  by ``origin`` (``points = local + origin``, so a shifted scene equals the unshifted one
  plus ``origin`` bit for bit). :attr:`Surface.d` refers to the shifted points.
- Sampling is uniform by area: a surface of area ``A`` sampled at density ``rho`` gets a
  Poisson number of points with mean ``rho * A``. Each surface kind has a density relative
  to the scene's nominal density (see :data:`PROFILES`), e.g. MLS sees roofs and ground
  more sparsely than facades; :attr:`Surface.density_pts_m2` is the density actually used.
- Noise: by default Gaussian noise of standard deviation ``noise_m`` is added **along the
  surface normal** only, so the true plane stays exactly the plane of the noise-free points
  and a point's truth distance is its noise draw. ``isotropic_noise=True`` adds the noise
  on all three axes instead (the distance to the plane still has standard deviation
  ``noise_m``, but points also move within the plane, e.g. across surface edges).
- Labels: ``Scene.labels`` holds the :attr:`Surface.id` of each point, ``-1`` for clutter
  (vegetation). ``Scene.classification`` uses ASPRS codes: 2 ground, 6 building (roofs and
  facades), 5 high vegetation.
- Randomness: everything derives from ``seed`` through :class:`numpy.random.SeedSequence`
  with a fixed spawn key per purpose (building sizes, building placement, tree sizes, tree
  placement, one key per surface, shuffling). So the same seed gives the same scene, and
  switching off e.g. vegetation or the ground leaves the buildings and their points
  unchanged; building ``i`` has the same size whatever ``n_buildings`` is.
- Survey error: :func:`apply_survey_error` adds the errors real surveys share between
  many points (MLS trajectory drift, ALS strip offsets, TLS setup registration) and a
  smooth non-flatness of the true surfaces, with point source ids and GPS times;
  :func:`make_fault_pair` applies one :class:`SurveyError` per epoch.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from .errors import InvalidParameterError

__all__ = [
    "ASPRS_BUILDING",
    "ASPRS_GROUND",
    "ASPRS_HIGH_VEGETATION",
    "PROFILES",
    "SURVEY_ERROR_KINDS",
    "Building",
    "LobeField",
    "LobePair",
    "ProfileSpec",
    "Scene",
    "Surface",
    "SurveyError",
    "SurveyErrorDraw",
    "TrueSurfaceFit",
    "apply_survey_error",
    "fit_true_surfaces",
    "make_lobe_pair",
    "make_scene",
    "make_scene_n_points",
    "AlsSampling",
    "FaultField",
    "LandslidePair",
    "SlabField",
    "SlumpField",
    "SumField",
    "field_breaklines",
    "make_landslide_pair",
    "material_motion",
    "plane_distances",
]

ASPRS_GROUND = 2
"""ASPRS classification code of ground points."""
ASPRS_HIGH_VEGETATION = 5
"""ASPRS classification code of vegetation (clutter) points."""
ASPRS_BUILDING = 6
"""ASPRS classification code of roof and facade points."""

SURFACE_KINDS = ("ground", "roof", "facade")
ROOF_KINDS = ("flat", "gable")

# Random building layout.
_FOOTPRINT_RANGE_M = (8.0, 25.0)  # each side of a random footprint
_HEIGHT_RANGE_M = (4.0, 15.0)  # eave height of a random building
_PITCH_RANGE_RAD = (math.radians(20.0), math.radians(40.0))  # gable roof pitch
_GAP_M = 3.0  # minimum gap between two random footprints
_BORDER_M = 1.5  # minimum distance of a random footprint to the extent's border
_MAX_FILL = 0.55  # (footprint + gap) area over extent area beyond which placement is refused
_BATCH = 64  # candidate positions drawn at once in rejection sampling
_MAX_BATCHES = 40  # batches tried per building before giving up

# Vegetation.
_TREES_PER_M2 = 6e-4  # default tree density (6 per hectare)
_TREE_RADIUS_RANGE_M = (2.0, 4.0)  # horizontal crown semi-axis
_TREE_ASPECT_RANGE = (1.0, 1.5)  # vertical / horizontal crown semi-axis
_TREE_BASE_RANGE_M = (1.5, 3.0)  # height of the crown's bottom above the ground
_TREE_SHELL = 0.75  # crown points lie between this fraction and 1 of the crown's radius
_TREE_CLEARANCE_M = 1.0  # minimum horizontal gap between a crown and a footprint

# Scene scaling in make_scene_n_points.
_BUILDINGS_PER_M2 = 6e-4  # the default 6 buildings per 100 m x 100 m

_GROUND_TILE_M = 50.0  # ground is sampled tile by tile (cheap footprint exclusion)

# SeedSequence spawn keys, one per purpose.
_KEY_BUILDING_PARAMS = 1
_KEY_BUILDING_PLACE = 2
_KEY_TREE_PARAMS = 3
_KEY_TREE_PLACE = 4
_KEY_SURFACE = 5
_KEY_TREE_POINTS = 6
_KEY_SHUFFLE = 7


# --------------------------------------------------------------------------------------
# Public data types
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ProfileSpec:
    """Acquisition profile: nominal density, noise and what the sensor sees.

    Attributes
    ----------
    name : str
        "als", "mls" or "tls".
    density_pts_m2 : float
        Default nominal density (points per square metre).
    typical_density_pts_m2 : tuple of float
        Usual range of the nominal density for this kind of survey (informative only; any
        positive density is accepted).
    noise_m : float
        Default range noise standard deviation (metres).
    ground_factor, roof_factor, facade_factor, vegetation_factor : float
        Density of each surface kind relative to ``density_pts_m2``; 0 means the kind is
        not sampled at all (no :class:`Surface` is created for it).
    """

    name: str
    density_pts_m2: float
    typical_density_pts_m2: tuple[float, float]
    noise_m: float
    ground_factor: float
    roof_factor: float
    facade_factor: float
    vegetation_factor: float

    def relative_density(self, kind: str) -> float:
        """Density factor of a surface kind ("ground", "roof", "facade", "vegetation")."""
        return float(getattr(self, f"{kind}_factor"))


PROFILES: Mapping[str, ProfileSpec] = MappingProxyType(
    {
        # Airborne: roofs and ground at the nominal density, no facades.
        "als": ProfileSpec("als", 10.0, (1.0, 20.0), 0.05, 1.0, 1.0, 0.0, 1.0),
        # Mobile: facades at the nominal density; roofs (seen from the street) and the
        # ground (kept sparse so the default scene stays test-sized) thinner.
        "mls": ProfileSpec("mls", 100.0, (50.0, 300.0), 0.02, 0.15, 0.25, 1.0, 0.5),
        # Terrestrial: mostly facades; roofs and ground seen at grazing angles.
        "tls": ProfileSpec("tls", 500.0, (100.0, 2000.0), 0.005, 0.05, 0.1, 1.0, 0.2),
    }
)
"""The acquisition profiles accepted by :func:`make_scene`, by name."""


@dataclass(frozen=True)
class Building:
    """A box building on the ground, with a flat or gable roof.

    Attributes
    ----------
    center_xy_m : tuple of float
        (2,) footprint centre in the scene's local frame (metres, before ``origin``).
    length_m, width_m : float
        Footprint side lengths (metres); ``length_m`` runs along ``rotation_rad``.
    height_m : float
        Eave height: height of the walls' horizontal top edge above the ground (metres).
    rotation_rad : float
        Counter-clockwise angle from the +x axis to the ``length_m`` side (radians).
    roof : str
        "flat" or "gable". A gable's ridge runs along the footprint's longer side.
    roof_pitch_rad : float
        Slope of the two gable roof planes (radians); unused for flat roofs.
    """

    center_xy_m: tuple[float, float]
    length_m: float
    width_m: float
    height_m: float
    rotation_rad: float = 0.0
    roof: str = "flat"
    roof_pitch_rad: float = math.radians(30.0)

    def _frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Centre (3,), long-axis unit vector u (3,), v = z x u (3,), long and short sides."""
        a = float(self.rotation_rad)
        long_side, short_side = float(self.length_m), float(self.width_m)
        if short_side > long_side:
            long_side, short_side = short_side, long_side
            a += 0.5 * math.pi
        u = np.array([math.cos(a), math.sin(a), 0.0])
        v = np.array([-math.sin(a), math.cos(a), 0.0])
        c = np.array([float(self.center_xy_m[0]), float(self.center_xy_m[1]), 0.0])
        return c, u, v, long_side, short_side

    def footprint_xy(self) -> np.ndarray:
        """Footprint corners, counter-clockwise, shape (4, 2), metres (local frame)."""
        c, u, v, long_side, short_side = self._frame()
        hl, hw = 0.5 * long_side, 0.5 * short_side
        corners = [c - hl * u - hw * v, c + hl * u - hw * v, c + hl * u + hw * v]
        corners.append(c - hl * u + hw * v)
        return np.array(corners)[:, :2]

    @property
    def footprint_area_m2(self) -> float:
        """Footprint area (square metres)."""
        return float(self.length_m) * float(self.width_m)

    @property
    def ridge_height_m(self) -> float:
        """Highest point of the roof above the ground (metres)."""
        if self.roof != "gable":
            return float(self.height_m)
        short_side = min(float(self.length_m), float(self.width_m))
        return float(self.height_m) + 0.5 * short_side * math.tan(float(self.roof_pitch_rad))


@dataclass(frozen=True, eq=False)
class Surface:
    """One true planar surface of a scene.

    Attributes
    ----------
    id : int
        Label of the surface's points in :attr:`Scene.labels`.
    kind : str
        "ground", "roof" or "facade".
    normal : numpy.ndarray
        (3,) unit normal with ``normal[2] >= 0``; horizontal normals (facades) point out of
        the building.
    d : float
        Hessian offset (metres): ``normal @ p + d == 0`` for noise-free points ``p`` of the
        surface, in the scene's (shifted) coordinates.
    n_points : int
        Number of points sampled on the surface.
    building : int
        Index of the building in :attr:`Scene.buildings`, -1 for the ground.
    area_m2 : float
        Area of the surface (square metres); for the ground, the extent minus footprints.
    density_pts_m2 : float
        Nominal sampling density of the surface (points per square metre): the scene's
        density times the profile's factor for this kind.
    """

    id: int
    kind: str
    normal: np.ndarray
    d: float
    n_points: int
    building: int
    area_m2: float = float("nan")
    density_pts_m2: float = float("nan")


@dataclass(frozen=True, eq=False)
class Scene:
    """A synthetic point cloud with its ground truth.

    Attributes
    ----------
    points : numpy.ndarray
        (N, 3) float64 coordinates (metres), shifted by ``origin``.
    labels : numpy.ndarray
        (N,) int32 true surface id (:attr:`Surface.id`), -1 for clutter (vegetation).
    classification : numpy.ndarray
        (N,) uint8 ASPRS class: 2 ground, 6 building, 5 high vegetation.
    surfaces : tuple of Surface
        The true planar surfaces; ``surfaces[i].id == i``.
    building_ids : numpy.ndarray
        (N,) int32 building index of each point, -1 for ground and clutter.
    noise_m : float
        Standard deviation of the added Gaussian noise (metres).
    density_pts_m2 : float
        Nominal density (points per square metre); see :attr:`Surface.density_pts_m2`.
    profile : str
        Acquisition profile ("als", "mls", "tls").
    seed : int
        Seed the scene was generated from.
    buildings : tuple of Building
        The buildings, in the local frame (before ``origin``).
    extent_m : float
        Side of the square scene (metres).
    origin : numpy.ndarray
        (3,) shift added to the local coordinates (metres).
    isotropic_noise : bool
        Whether noise was added on all axes rather than along the normals.
    """

    points: np.ndarray
    labels: np.ndarray
    classification: np.ndarray
    surfaces: tuple[Surface, ...]
    building_ids: np.ndarray
    noise_m: float
    density_pts_m2: float
    profile: str
    seed: int
    buildings: tuple[Building, ...] = ()
    extent_m: float = float("nan")
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    isotropic_noise: bool = False

    def planar_mask(self) -> np.ndarray:
        """(N,) bool: True where the point belongs to a true planar surface (label >= 0)."""
        return self.labels >= 0

    @property
    def n_points(self) -> int:
        """Number of points N."""
        return int(self.points.shape[0])


# --------------------------------------------------------------------------------------
# Public functions
# --------------------------------------------------------------------------------------


def make_scene(
    profile: str = "mls",
    *,
    seed: int = 0,
    n_buildings: int = 6,
    extent_m: float = 100.0,
    density_pts_m2: float | None = None,
    noise_m: float | None = None,
    ground: bool = True,
    vegetation: bool = True,
    origin: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    roof_kinds: Sequence[str] = ROOF_KINDS,
    isotropic_noise: bool = False,
    n_trees: int | None = None,
    buildings: Sequence[Building] | None = None,
    shuffle: bool = True,
) -> Scene:
    """Generate a synthetic LiDAR scene with known planar surfaces.

    Parameters
    ----------
    profile : str
        Acquisition profile, a key of :data:`PROFILES`: "als" (airborne: roofs and ground,
        no facades; 10 pts/m², 0.05 m), "mls" (mobile: facades, thinner roofs and ground;
        100 pts/m², 0.02 m) or "tls" (terrestrial: mostly facades; 500 pts/m², 0.005 m).
    seed : int
        Non-negative seed; the same seed and options give the same scene.
    n_buildings : int
        Number of random buildings (footprints 8–25 m by 8–25 m, eave heights 4–15 m, any
        rotation, at least 3 m apart). Ignored when ``buildings`` is given.
    extent_m : float
        Side of the square scene (metres); the ground covers ``[0, extent_m]²``.
    density_pts_m2 : float, optional
        Nominal density (points per square metre); default: the profile's.
    noise_m : float, optional
        Gaussian noise standard deviation (metres); default: the profile's.
    ground : bool
        Sample the ground plane (outside the footprints).
    vegetation : bool
        Add trees (ellipsoidal crowns, label -1, class 5) that do not touch buildings.
    origin : array-like
        (3,) shift added to all coordinates (metres), e.g. ``(500000, 4200000, 100)``.
    roof_kinds : sequence of str
        Roof kinds random buildings draw from, uniformly: "flat", "gable".
    isotropic_noise : bool
        Add the noise on all three axes instead of along the surface normal.
    n_trees : int, optional
        Number of trees to try to place; default 6 per hectare. Trees that find no room
        are left out.
    buildings : sequence of Building, optional
        Hand-placed buildings (local frame) used instead of random ones; they must lie
        inside the extent and must not overlap.
    shuffle : bool
        Shuffle the points (default); otherwise points come surface by surface (in id
        order), then vegetation.

    Returns
    -------
    Scene
        Points (N, 3), labels, classification, building ids and the true surfaces.

    Raises
    ------
    InvalidParameterError
        For an unknown profile, a non-positive density or extent, a negative noise, a
        bad origin or roof kind, or buildings that do not fit in the extent.
    """
    spec = _check_profile(profile)
    seed = _check_int("seed", seed, minimum=0)
    extent = _check_positive("extent_m", extent_m)
    if density_pts_m2 is None:
        density = spec.density_pts_m2
    else:
        density = _check_positive("density_pts_m2", density_pts_m2)
    noise = spec.noise_m if noise_m is None else _check_non_negative("noise_m", noise_m)
    origin_arr = _check_origin(origin)
    kinds = _check_roof_kinds(roof_kinds)
    if buildings is None:
        count = _check_int("n_buildings", n_buildings, minimum=0)
        params = _random_building_params(seed, count, kinds)
        blds = _place_buildings(seed, params, extent)
    else:
        blds = _check_buildings(buildings, extent)
    if vegetation:
        if n_trees is None:
            tree_count = _default_tree_count(extent)
        else:
            tree_count = _check_int("n_trees", n_trees, minimum=0)
        trees = _place_trees(seed, _random_tree_params(seed, tree_count), extent, blds)
    else:
        trees = np.zeros((0, 5))
    return _render(
        spec=spec,
        seed=seed,
        extent=extent,
        density=density,
        noise=noise,
        isotropic=bool(isotropic_noise),
        origin=origin_arr,
        buildings=blds,
        trees=trees,
        ground=bool(ground),
        shuffle=bool(shuffle),
    )


def make_scene_n_points(n_points: int, profile: str = "mls", seed: int = 0, **kw: Any) -> Scene:
    """Generate a scene of about ``n_points`` points by scaling its extent and buildings.

    The scene keeps the default layout density (6 buildings and, with vegetation, 6 trees
    per hectare) and grows ``extent_m`` and ``n_buildings`` together; the ground then fine
    tunes the count. The expected count (Poisson mean) is matched to within 3 %, so the
    actual count is within a few percent of ``n_points`` for any target above the smallest
    one-building scene (depending on the seed about 0.1 M points for "mls", 0.3-0.5 M for
    "tls" and 10⁴ for "als" at their default densities).

    Parameters
    ----------
    n_points : int
        Target number of points (> 0).
    profile : str
        Acquisition profile (see :func:`make_scene`); its default density is used unless
        ``density_pts_m2`` is given in ``kw``.
    seed : int
        Non-negative seed.
    **kw
        Other keyword options of :func:`make_scene`, except ``extent_m``, ``n_buildings``
        and ``buildings``, which this function chooses.

    Returns
    -------
    Scene
        The scene; ``scene.extent_m`` and ``len(scene.buildings)`` tell the chosen layout.

    Raises
    ------
    InvalidParameterError
        For bad options, or a target too small for one building at this density (or not
        reachable at all, e.g. with ``ground=False`` and ``vegetation=False``).
    """
    for name in ("extent_m", "n_buildings", "buildings"):
        if name in kw:
            raise InvalidParameterError(
                f"make_scene_n_points chooses {name} itself; call make_scene to set it"
            )
    target = _check_int("n_points", n_points, minimum=1)
    spec = _check_profile(profile)
    seed = _check_int("seed", seed, minimum=0)
    density = kw.get("density_pts_m2")
    density = spec.density_pts_m2 if density is None else _check_positive("density_pts_m2", density)
    kinds = _check_roof_kinds(kw.get("roof_kinds", ROOF_KINDS))
    n_trees = kw.get("n_trees")
    if n_trees is not None:
        n_trees = _check_int("n_trees", n_trees, minimum=0)
    model = _CountModel(
        seed=seed,
        spec=spec,
        density=density,
        roof_kinds=kinds,
        ground=bool(kw.get("ground", True)),
        vegetation=bool(kw.get("vegetation", True)),
        n_trees=n_trees,
    )

    def coupled(extent: float) -> float:
        return model.expected(model.buildings_for(extent), extent)

    extent0 = _solve_increasing(coupled, target, 10.0)
    n0 = model.buildings_for(extent0)
    candidates = [n0]
    for step in range(1, 4):
        candidates += [n0 - step, n0 + step]
    for count in candidates:
        if count < 1:
            continue
        lo = model.min_extent(count)
        if model.ground_rho > 0.0 or model.veg_rho > 0.0:
            extent = _solve_increasing(lambda e, c=count: model.expected(c, e), target, lo)
        else:  # only buildings: the count does not depend on the extent
            extent = max(lo, math.sqrt(count / _BUILDINGS_PER_M2))
        if abs(model.expected(count, extent) / target - 1.0) > 0.03:
            continue
        try:
            return make_scene(profile, seed=seed, n_buildings=count, extent_m=extent, **kw)
        except _LayoutError:  # placement failed at this size: try another building count
            continue
    smallest = model.expected(1, model.min_extent(1))
    if target < smallest:
        why = f"the smallest scene, with one building, has about {smallest:.0f} points"
    else:
        why = "without ground and vegetation only whole buildings change the count"
    raise InvalidParameterError(
        f"n_points={target} cannot be reached within 3 % with profile {spec.name!r} at "
        f"density_pts_m2={density:g}: {why}; choose another n_points or density_pts_m2, "
        "or call make_scene directly"
    )


def plane_distances(scene: Scene) -> np.ndarray:
    """Signed distance of each point to its true surface plane.

    Parameters
    ----------
    scene : Scene
        A scene from :func:`make_scene`.

    Returns
    -------
    numpy.ndarray
        (N,) float64 distances ``normal @ p + d`` (metres), positive on the normal's side;
        NaN for clutter (label -1).
    """
    n = scene.points.shape[0]
    out = np.full(n, np.nan)
    if not scene.surfaces or n == 0:
        return out
    ids = np.array([s.id for s in scene.surfaces], dtype=np.int64)
    lookup = np.full(int(ids.max()) + 1, -1, dtype=np.int64)
    lookup[ids] = np.arange(ids.size)
    normals = np.array([s.normal for s in scene.surfaces], dtype=np.float64)
    ref = np.asarray(scene.origin, dtype=np.float64)
    offsets = np.array([s.d for s in scene.surfaces], dtype=np.float64) + normals @ ref
    mask = scene.labels >= 0
    idx = lookup[scene.labels[mask]]
    local = scene.points[mask] - ref
    out[mask] = np.einsum("ij,ij->i", local, normals[idx]) + offsets[idx]
    return out


# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------


def _check_profile(profile: Any) -> ProfileSpec:
    if not isinstance(profile, str) or profile.lower() not in PROFILES:
        allowed = ", ".join(repr(p) for p in PROFILES)
        raise InvalidParameterError(f"profile={profile!r} is unknown; use one of {allowed}")
    return PROFILES[profile.lower()]


def _check_int(name: str, value: Any, *, minimum: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InvalidParameterError(f"{name}={value!r} must be an integer >= {minimum}")
    if value < minimum:
        raise InvalidParameterError(f"{name}={value!r} must be an integer >= {minimum}")
    return int(value)


def _check_float(name: str, value: Any) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"{name}={value!r} must be a number") from None
    if not math.isfinite(out):
        raise InvalidParameterError(f"{name}={value!r} must be finite")
    return out


def _check_positive(name: str, value: Any) -> float:
    out = _check_float(name, value)
    if out <= 0.0:
        raise InvalidParameterError(f"{name}={value!r} must be > 0")
    return out


def _check_non_negative(name: str, value: Any) -> float:
    out = _check_float(name, value)
    if out < 0.0:
        raise InvalidParameterError(f"{name}={value!r} must be >= 0")
    return out


def _check_origin(origin: Any) -> np.ndarray:
    try:
        arr = np.array(origin, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidParameterError(f"origin={origin!r} must be 3 numbers (x, y, z)") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise InvalidParameterError(f"origin={origin!r} must be 3 finite numbers (x, y, z)")
    return arr


def _check_roof_kinds(roof_kinds: Any) -> tuple[str, ...]:
    if isinstance(roof_kinds, str):
        roof_kinds = (roof_kinds,)
    try:
        kinds = tuple(roof_kinds)
    except TypeError:
        kinds = ()
    if not kinds or any(k not in ROOF_KINDS for k in kinds):
        raise InvalidParameterError(
            f"roof_kinds={roof_kinds!r} must be a non-empty sequence of {ROOF_KINDS}"
        )
    return kinds


def _check_buildings(buildings: Sequence[Building], extent: float) -> tuple[Building, ...]:
    """Validate hand-placed buildings: sizes, roof, inside the extent, no overlap."""
    out = tuple(buildings)
    for i, b in enumerate(out):
        if not isinstance(b, Building):
            raise InvalidParameterError(f"buildings[{i}] must be a Building, not {type(b)}")
        for attr in ("length_m", "width_m", "height_m"):
            _check_positive(f"buildings[{i}].{attr}", getattr(b, attr))
        _check_float(f"buildings[{i}].rotation_rad", b.rotation_rad)
        if b.roof not in ROOF_KINDS:
            raise InvalidParameterError(
                f"buildings[{i}].roof={b.roof!r} must be one of {ROOF_KINDS}"
            )
        pitch = _check_float(f"buildings[{i}].roof_pitch_rad", b.roof_pitch_rad)
        if b.roof == "gable" and not 0.0 < pitch < 0.5 * math.pi:
            raise InvalidParameterError(
                f"buildings[{i}].roof_pitch_rad={pitch!r} must be in (0, pi/2)"
            )
        corners = b.footprint_xy()
        if corners.min() < 0.0 or corners.max() > extent or not np.all(np.isfinite(corners)):
            raise InvalidParameterError(
                f"buildings[{i}] does not lie inside extent_m={extent:g} "
                f"(footprint x {corners[:, 0].min():.2f}..{corners[:, 0].max():.2f}, "
                f"y {corners[:, 1].min():.2f}..{corners[:, 1].max():.2f})"
            )
    if len(out) > 1:
        polys = np.array([b.footprint_xy() for b in out])
        first, second = np.triu_indices(len(out), k=1)
        bad = np.flatnonzero(_polygon_gaps(polys[first], polys[second]) <= 0.0)
        if bad.size:
            i, j = first[bad[0]], second[bad[0]]
            raise InvalidParameterError(
                f"buildings[{i}] and buildings[{j}] overlap; move them apart"
            )
    return out


# --------------------------------------------------------------------------------------
# Random layout: buildings and trees
# --------------------------------------------------------------------------------------


class _LayoutError(InvalidParameterError):
    """Random buildings do not fit in the extent (make_scene_n_points retries on it)."""


def _rng(seed: int, *key: int) -> np.random.Generator:
    """Generator for one purpose: independent of every other key's stream."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=key))


def _random_building_params(
    seed: int, count: int, roof_kinds: tuple[str, ...]
) -> list[dict[str, Any]]:
    """Sizes, rotation and roof of ``count`` random buildings (no position yet).

    Building ``i`` depends only on ``seed`` and ``i`` (``Generator.random`` fills row by
    row, so the first rows do not depend on ``count``).
    """
    u = _rng(seed, _KEY_BUILDING_PARAMS).random((count, 6))
    lo, hi = _FOOTPRINT_RANGE_M
    hlo, hhi = _HEIGHT_RANGE_M
    plo, phi = _PITCH_RANGE_RAD
    out = []
    for row in u:
        out.append(
            {
                "length_m": lo + (hi - lo) * row[0],
                "width_m": lo + (hi - lo) * row[1],
                "height_m": hlo + (hhi - hlo) * row[2],
                "rotation_rad": math.pi * row[3],
                "roof": roof_kinds[min(int(row[4] * len(roof_kinds)), len(roof_kinds) - 1)],
                "roof_pitch_rad": plo + (phi - plo) * row[5],
            }
        )
    return out


def _half_extents(length: float, width: float, angle: float) -> tuple[float, float]:
    """Half sizes (x, y) of the axis-aligned box around a rotated rectangle."""
    c, s = abs(math.cos(angle)), abs(math.sin(angle))
    return 0.5 * (length * c + width * s), 0.5 * (length * s + width * c)


def _place_buildings(
    seed: int, params: list[dict[str, Any]], extent: float
) -> tuple[Building, ...]:
    """Place buildings one by one by rejection sampling, ``_GAP_M`` apart."""
    if not params:
        return ()
    need = sum((p["length_m"] + _GAP_M) * (p["width_m"] + _GAP_M) for p in params)
    advice = (
        f"increase extent_m (to at least ~{math.sqrt(need / _MAX_FILL) + 2 * _BORDER_M:.0f} m) "
        "or lower n_buildings"
    )
    if need > _MAX_FILL * extent**2:
        raise _LayoutError(
            f"n_buildings={len(params)} random buildings (footprints "
            f"{_FOOTPRINT_RANGE_M[0]:g}-{_FOOTPRINT_RANGE_M[1]:g} m, {_GAP_M:g} m apart) "
            f"do not fit in extent_m={extent:g}; {advice}"
        )
    rng = _rng(seed, _KEY_BUILDING_PLACE)
    placed: list[Building] = []
    polys = np.zeros((0, 4, 2))
    radii = np.zeros(0)
    centers = np.zeros((0, 2))
    for i, p in enumerate(params):
        hx, hy = _half_extents(p["length_m"], p["width_m"], p["rotation_rad"])
        span_x = extent - 2.0 * (_BORDER_M + hx)
        span_y = extent - 2.0 * (_BORDER_M + hy)
        if span_x < 0.0 or span_y < 0.0:
            raise _LayoutError(
                f"random building {i} ({p['length_m']:.1f} m x {p['width_m']:.1f} m) does "
                f"not fit in extent_m={extent:g}; {advice}"
            )
        radius = 0.5 * math.hypot(p["length_m"], p["width_m"])
        template = Building((0.0, 0.0), **{k: p[k] for k in p}).footprint_xy()
        chosen = None
        for _ in range(_MAX_BATCHES):
            cand = rng.random((_BATCH, 2)) * [span_x, span_y] + [_BORDER_M + hx, _BORDER_M + hy]
            ok = np.ones(_BATCH, dtype=bool)
            if centers.shape[0]:
                dist = np.linalg.norm(cand[:, None, :] - centers[None, :, :], axis=-1)
                rows, cols = np.nonzero(dist < radius + radii[None, :] + _GAP_M)
                if rows.size:  # exact test only for pairs whose circles are close
                    gaps = _polygon_gaps(cand[rows, None, :] + template[None], polys[cols])
                    ok[rows[gaps < _GAP_M]] = False
            hits = np.flatnonzero(ok)
            if hits.size:
                chosen = cand[hits[0]]
                break
        if chosen is None:
            raise _LayoutError(
                f"could place only {i} of n_buildings={len(params)} random buildings in "
                f"extent_m={extent:g} with a {_GAP_M:g} m gap; {advice}"
            )
        b = Building((float(chosen[0]), float(chosen[1])), **{k: p[k] for k in p})
        placed.append(b)
        polys = np.concatenate([polys, b.footprint_xy()[None]])
        radii = np.append(radii, radius)
        centers = np.concatenate([centers, chosen[None]])
    return tuple(placed)


def _default_tree_count(extent: float) -> int:
    return max(1, int(round(_TREES_PER_M2 * extent**2)))


def _random_tree_params(seed: int, count: int) -> np.ndarray:
    """(count, 3): crown horizontal semi-axis, vertical semi-axis, crown base height (m)."""
    u = _rng(seed, _KEY_TREE_PARAMS).random((count, 3))
    r = _TREE_RADIUS_RANGE_M[0] + np.diff(_TREE_RADIUS_RANGE_M) * u[:, 0]
    aspect = _TREE_ASPECT_RANGE[0] + np.diff(_TREE_ASPECT_RANGE) * u[:, 1]
    base = _TREE_BASE_RANGE_M[0] + np.diff(_TREE_BASE_RANGE_M) * u[:, 2]
    return np.column_stack([r, r * aspect, base])


def _ellipsoid_area(a: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Surface area (m²) of spheroids with semi-axes (a, a, c) (Thomsen, error < 1.1 %)."""
    p = 1.6075
    return 4.0 * math.pi * ((a ** (2 * p) + 2.0 * (a * c) ** p) / 3.0) ** (1.0 / p)


def _place_trees(
    seed: int, params: np.ndarray, extent: float, buildings: tuple[Building, ...]
) -> np.ndarray:
    """Place tree crowns clear of buildings and of each other; unplaceable ones are dropped.

    Returns
    -------
    numpy.ndarray
        (T, 5) crown centre x, y, z (local, metres), horizontal and vertical semi-axes.
    """
    rng = _rng(seed, _KEY_TREE_PLACE)
    polys = np.array([b.footprint_xy() for b in buildings]).reshape(-1, 4, 2)
    centers = polys.mean(axis=1)
    radii = np.array([0.5 * math.hypot(b.length_m, b.width_m) for b in buildings])
    rows: list[list[float]] = []
    for r, rz, base in params:
        margin = r + _TREE_CLEARANCE_M
        span = extent - 2.0 * margin
        if span <= 0.0:
            continue
        for _ in range(_MAX_BATCHES // 4):
            cand = margin + span * rng.random((_BATCH, 2))
            ok = np.ones(_BATCH, dtype=bool)
            if polys.shape[0]:
                dist = np.linalg.norm(cand[:, None, :] - centers[None, :, :], axis=-1)
                near_c, near_b = np.nonzero(dist < radii[None, :] + margin)
                if near_c.size:  # exact test only where the building's circle is close
                    gap = _point_polygon_distance(cand[near_c], polys[near_b])
                    ok[near_c[gap < margin]] = False
            if rows:
                prev = np.array(rows)
                dist = np.linalg.norm(cand[:, None, :] - prev[None, :, :2], axis=-1)
                ok &= np.all(dist >= r + prev[None, :, 3], axis=1)
            hits = np.flatnonzero(ok)
            if hits.size:
                x, y = cand[hits[0]]
                rows.append([x, y, base + rz, r, rz])
                break
    return np.array(rows, dtype=np.float64).reshape(-1, 5)


def _edge_normals(polys: np.ndarray) -> np.ndarray:
    """(..., 4, 2) polygons -> (..., 4, 2) edge normals (not normalised)."""
    e = np.roll(polys, -1, axis=-2) - polys
    return np.stack([-e[..., 1], e[..., 0]], axis=-1)


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points p to segments [a, b]; all (..., 2), broadcast."""
    ab = b - a
    t = np.einsum("...i,...i->...", p - a, ab) / np.einsum("...i,...i->...", ab, ab)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def _polygon_gaps(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Gaps between pairs of convex quadrilaterals: (P, 4, 2), (P, 4, 2) -> (P,), 0 if overlapping.

    Separating-axis test for overlap; otherwise the smallest vertex-to-edge distance.
    """
    axes = np.concatenate([_edge_normals(p), _edge_normals(q)], axis=-2)  # (P, 8, 2)
    proj_p = np.einsum("kad,kvd->kav", axes, p)
    proj_q = np.einsum("kad,kvd->kav", axes, q)
    separated = np.any(
        (proj_p.max(-1) < proj_q.min(-1)) | (proj_q.max(-1) < proj_p.min(-1)), axis=-1
    )
    q_end, p_end = np.roll(q, -1, axis=-2), np.roll(p, -1, axis=-2)
    d_pq = _point_segment_distance(p[:, :, None], q[:, None], q_end[:, None]).min(axis=(1, 2))
    d_qp = _point_segment_distance(q[:, :, None], p[:, None], p_end[:, None]).min(axis=(1, 2))
    return np.where(separated, np.minimum(d_pq, d_qp), 0.0)


def _point_polygon_distance(pts: np.ndarray, polys: np.ndarray) -> np.ndarray:
    """Pairs of points and counter-clockwise convex quadrilaterals: (P, 2), (P, 4, 2) -> (P,).

    The distance is 0 for a point inside its polygon.
    """
    a, b, p = polys, np.roll(polys, -1, axis=-2), pts[:, None, :]
    e, w = b - a, p - a
    inside = np.all(e[..., 0] * w[..., 1] - e[..., 1] * w[..., 0] >= 0.0, axis=-1)
    dist = _point_segment_distance(p, a, b).min(axis=-1)
    return np.where(inside, 0.0, dist)


# --------------------------------------------------------------------------------------
# Surface geometry (local frame): each planar surface is a union of patches
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Patch:
    """Parallelogram ``o + a e1 + b e2`` (a, b in [0, 1]) or triangle (a + b <= 1)."""

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    triangle: bool = False

    @property
    def area(self) -> float:
        full = float(np.linalg.norm(np.cross(self.e1, self.e2)))
        return 0.5 * full if self.triangle else full


@dataclass(frozen=True, eq=False)
class _PlaneGeom:
    """A true planar surface before sampling (local frame)."""

    kind: str
    building: int  # -1 for the ground
    role: int  # index of the surface within its building (spawn key)
    patches: tuple[_Patch, ...]
    normal: np.ndarray
    d: float
    area_m2: float


def _plane_geom(
    kind: str, building: int, role: int, patches: list[_Patch], outward: np.ndarray
) -> _PlaneGeom:
    """Normal (nz >= 0; horizontal ones along ``outward``), offset and area of patches."""
    first = patches[0]
    normal = np.cross(first.e1, first.e2)
    normal = normal / np.linalg.norm(normal)
    if normal[2] < -1e-12 or (abs(normal[2]) <= 1e-12 and normal @ outward < 0.0):
        normal = -normal
    if abs(normal[2]) <= 1e-12:
        normal[2] = 0.0
    d = -float(normal @ first.origin)
    area = float(sum(p.area for p in patches))
    return _PlaneGeom(kind, building, role, tuple(patches), normal, d, area)


def _ground_geom(extent: float, buildings: tuple[Building, ...]) -> _PlaneGeom:
    """The ground square; its area excludes the footprints (not sampled under buildings)."""
    patch = _Patch(np.zeros(3), np.array([extent, 0.0, 0.0]), np.array([0.0, extent, 0.0]))
    g = _plane_geom("ground", -1, 0, [patch], np.zeros(3))
    area = extent**2 - sum(b.footprint_area_m2 for b in buildings)
    return _PlaneGeom("ground", -1, 0, g.patches, g.normal, g.d, area)


def _roof_geoms(b: Building, index: int) -> list[_PlaneGeom]:
    """One flat roof rectangle, or the two rectangles of a gable roof (ridge along u)."""
    c, u, v, long_side, short_side = b._frame()
    z = np.array([0.0, 0.0, 1.0])
    h = float(b.height_m)
    if b.roof == "flat":
        o = c - 0.5 * long_side * u - 0.5 * short_side * v + h * z
        return [_plane_geom("roof", index, 0, [_Patch(o, long_side * u, short_side * v)], z)]
    rise = 0.5 * short_side * math.tan(float(b.roof_pitch_rad))
    ridge_start = c - 0.5 * long_side * u + (h + rise) * z
    out = []
    for role, side in enumerate((1.0, -1.0)):
        e2 = side * 0.5 * short_side * v - rise * z
        out.append(
            _plane_geom("roof", index, role, [_Patch(ridge_start, long_side * u, e2)], side * v)
        )
    return out


def _facade_geoms(b: Building, index: int) -> list[_PlaneGeom]:
    """Four walls: two rectangles along the long sides, two end walls (pentagons if gable)."""
    c, u, v, long_side, short_side = b._frame()
    z = np.array([0.0, 0.0, 1.0])
    h = float(b.height_m)
    hl, hw = 0.5 * long_side, 0.5 * short_side
    out = []
    for k, side in enumerate((1.0, -1.0)):  # long walls at +-v
        o = c - hl * u + side * hw * v
        out.append(_plane_geom("facade", index, 2 + k, [_Patch(o, long_side * u, h * z)], side * v))
    for k, side in enumerate((1.0, -1.0)):  # end walls at +-u
        o = c + side * hl * u - hw * v
        patches = [_Patch(o, short_side * v, h * z)]
        if b.roof == "gable":
            rise = hw * math.tan(float(b.roof_pitch_rad))
            patches.append(_Patch(o + h * z, short_side * v, hw * v + rise * z, triangle=True))
        out.append(_plane_geom("facade", index, 4 + k, patches, side * u))
    return out


def _building_geoms(b: Building, index: int, spec: ProfileSpec) -> list[_PlaneGeom]:
    """The surfaces of one building that the profile samples."""
    out: list[_PlaneGeom] = []
    if spec.roof_factor > 0.0:
        out += _roof_geoms(b, index)
    if spec.facade_factor > 0.0:
        out += _facade_geoms(b, index)
    return out


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------


def _sample_patches(
    rng: np.random.Generator, patches: tuple[_Patch, ...], density: float
) -> np.ndarray:
    """Uniform points on a union of patches, Poisson count of mean density * area: (n, 3)."""
    areas = np.array([p.area for p in patches])
    n = int(rng.poisson(density * areas.sum()))
    counts = rng.multinomial(n, areas / areas.sum()) if len(patches) > 1 else [n]
    out = []
    for patch, count in zip(patches, counts):
        ab = rng.random((int(count), 2))
        if patch.triangle:
            flip = ab.sum(axis=1) > 1.0
            ab[flip] = 1.0 - ab[flip]
        out.append(patch.origin + ab[:, :1] * patch.e1 + ab[:, 1:] * patch.e2)
    return np.concatenate(out) if out else np.zeros((0, 3))


def _sample_ground(
    rng: np.random.Generator, extent: float, buildings: tuple[Building, ...], density: float
) -> np.ndarray:
    """Uniform points on the ground square outside the footprints: (n, 3), z = 0.

    The square is split in tiles; each tile draws a Poisson count over its whole area and
    drops points inside the footprints that touch it (thinning keeps the count Poisson with
    mean density * remaining area).
    """
    n_tiles = max(1, int(math.ceil(extent / _GROUND_TILE_M)))
    edges = np.linspace(0.0, extent, n_tiles + 1)
    frames = [b._frame() for b in buildings]
    boxes = np.array([b.footprint_xy() for b in buildings]).reshape(-1, 4, 2)
    lo, hi = boxes.min(axis=1), boxes.max(axis=1)
    out = []
    for i in range(n_tiles):
        for j in range(n_tiles):
            x0, x1, y0, y1 = edges[i], edges[i + 1], edges[j], edges[j + 1]
            n = int(rng.poisson(density * (x1 - x0) * (y1 - y0)))
            xy = rng.random((n, 2)) * [x1 - x0, y1 - y0] + [x0, y0]
            keep = np.ones(n, dtype=bool)
            touching = np.flatnonzero(
                (lo[:, 0] < x1) & (hi[:, 0] > x0) & (lo[:, 1] < y1) & (hi[:, 1] > y0)
            )
            for k in touching:
                c, u, v, long_side, short_side = frames[k]
                rel = xy - c[:2]
                inside = (np.abs(rel @ u[:2]) < 0.5 * long_side) & (
                    np.abs(rel @ v[:2]) < 0.5 * short_side
                )
                keep &= ~inside
            xy = xy[keep]
            out.append(np.column_stack([xy, np.zeros(xy.shape[0])]))
    return np.concatenate(out)


def _sample_trees(rng: np.random.Generator, trees: np.ndarray, density: float) -> np.ndarray:
    """Points in a shell (radius fraction 0.75-1) of each spheroidal crown: (n, 3)."""
    if trees.shape[0] == 0 or density <= 0.0:
        return np.zeros((0, 3))
    area = _ellipsoid_area(trees[:, 3], trees[:, 4])
    counts = rng.poisson(density * area)
    rows = np.repeat(np.arange(trees.shape[0]), counts)
    direction = rng.normal(size=(rows.size, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    scale = _TREE_SHELL + (1.0 - _TREE_SHELL) * rng.random(rows.size)
    axes = trees[rows][:, [3, 3, 4]]
    return trees[rows, :3] + (scale[:, None] * direction) * axes


def _add_noise(
    rng: np.random.Generator, pts: np.ndarray, normal: np.ndarray, noise: float, isotropic: bool
) -> np.ndarray:
    """Gaussian noise of std ``noise`` along ``normal`` (or on all axes): (n, 3)."""
    if isotropic:
        return pts + rng.normal(0.0, noise, size=pts.shape)
    return pts + rng.normal(0.0, noise, size=(pts.shape[0], 1)) * normal


def _render(
    *,
    spec: ProfileSpec,
    seed: int,
    extent: float,
    density: float,
    noise: float,
    isotropic: bool,
    origin: np.ndarray,
    buildings: tuple[Building, ...],
    trees: np.ndarray,
    ground: bool,
    shuffle: bool,
) -> Scene:
    """Sample every surface and the vegetation, add noise, label, shift and shuffle."""
    geoms: list[_PlaneGeom] = []
    if ground and spec.ground_factor > 0.0:
        geoms.append(_ground_geom(extent, buildings))
    for index, b in enumerate(buildings):
        geoms += _building_geoms(b, index, spec)

    chunks, labels, classes, bids, surfaces = [], [], [], [], []
    for sid, g in enumerate(geoms):
        rng = _rng(seed, _KEY_SURFACE, g.building + 1, g.role)
        rho = density * spec.relative_density(g.kind)
        if g.kind == "ground":
            pts = _sample_ground(rng, extent, buildings, rho)
        else:
            pts = _sample_patches(rng, g.patches, rho)
        pts = _add_noise(rng, pts, g.normal, noise, isotropic)
        n = pts.shape[0]
        chunks.append(pts)
        labels.append(np.full(n, sid, dtype=np.int32))
        code = ASPRS_GROUND if g.kind == "ground" else ASPRS_BUILDING
        classes.append(np.full(n, code, dtype=np.uint8))
        bids.append(np.full(n, g.building, dtype=np.int32))
        normal = g.normal.copy()
        normal.flags.writeable = False
        d = g.d - float(normal @ origin)
        surfaces.append(Surface(sid, g.kind, normal, d, n, g.building, g.area_m2, rho))

    rng = _rng(seed, _KEY_TREE_POINTS)
    veg = _sample_trees(rng, trees, density * spec.vegetation_factor)
    if isotropic and veg.shape[0]:
        veg = veg + rng.normal(0.0, noise, size=veg.shape)
    chunks.append(veg)
    labels.append(np.full(veg.shape[0], -1, dtype=np.int32))
    classes.append(np.full(veg.shape[0], ASPRS_HIGH_VEGETATION, dtype=np.uint8))
    bids.append(np.full(veg.shape[0], -1, dtype=np.int32))

    points = np.concatenate(chunks)
    label_arr = np.concatenate(labels)
    class_arr = np.concatenate(classes)
    bid_arr = np.concatenate(bids)
    if shuffle:
        order = _rng(seed, _KEY_SHUFFLE).permutation(points.shape[0])
        points, label_arr = points[order], label_arr[order]
        class_arr, bid_arr = class_arr[order], bid_arr[order]
    points += origin
    return Scene(
        points=points,
        labels=label_arr,
        classification=class_arr,
        surfaces=tuple(surfaces),
        building_ids=bid_arr,
        noise_m=noise,
        density_pts_m2=density,
        profile=spec.name,
        seed=seed,
        buildings=buildings,
        extent_m=extent,
        origin=origin.copy(),
        isotropic_noise=isotropic,
    )


# --------------------------------------------------------------------------------------
# Expected point counts (for make_scene_n_points)
# --------------------------------------------------------------------------------------


class _CountModel:
    """Expected point count of a random scene as a function of (n_buildings, extent_m).

    Building sizes and tree sizes do not depend on placement (own random streams), so the
    expected count is exact for a given layout, assuming every tree finds room.
    """

    def __init__(
        self,
        *,
        seed: int,
        spec: ProfileSpec,
        density: float,
        roof_kinds: tuple[str, ...],
        ground: bool,
        vegetation: bool,
        n_trees: int | None,
    ) -> None:
        self.seed, self.spec, self.density, self.roof_kinds = seed, spec, density, roof_kinds
        self.ground_rho = density * spec.ground_factor if ground else 0.0
        self.veg_rho = density * spec.vegetation_factor if vegetation else 0.0
        self.n_trees = n_trees
        self._params: list[dict[str, Any]] = []
        self._bpts = np.zeros(1)  # cumulative building points, [0] = 0
        self._bfoot = np.zeros(1)  # cumulative footprint areas
        self._bneed = np.zeros(1)  # cumulative (footprint + gap) areas
        self._tree_pts = np.zeros(1)  # cumulative tree points

    def _grow_buildings(self, count: int) -> None:
        if count < len(self._params):
            return
        size = max(count + 1, 2 * len(self._params), 16)
        self._params = _random_building_params(self.seed, size, self.roof_kinds)
        pts, foot, need = [0.0], [0.0], [0.0]
        for p in self._params:
            b = Building((0.0, 0.0), **p)
            geoms = _building_geoms(b, 0, self.spec)
            pts.append(
                sum(self.density * self.spec.relative_density(g.kind) * g.area_m2 for g in geoms)
            )
            foot.append(b.footprint_area_m2)
            need.append((p["length_m"] + _GAP_M) * (p["width_m"] + _GAP_M))
        self._bpts, self._bfoot, self._bneed = np.cumsum(pts), np.cumsum(foot), np.cumsum(need)

    def _trees_points(self, count: int) -> float:
        if count >= self._tree_pts.size:
            size = max(count + 1, 2 * self._tree_pts.size, 16)
            params = _random_tree_params(self.seed, size)
            area = _ellipsoid_area(params[:, 0], params[:, 1])
            self._tree_pts = np.concatenate([[0.0], np.cumsum(self.veg_rho * area)])
        return float(self._tree_pts[count])

    def buildings_for(self, extent: float) -> int:
        """Building count at the default layout density for this extent (>= 1)."""
        return max(1, int(round(_BUILDINGS_PER_M2 * extent**2)))

    def min_extent(self, count: int) -> float:
        """Smallest extent the placement accepts for the first ``count`` buildings."""
        self._grow_buildings(count)
        fill = math.sqrt(self._bneed[count] / _MAX_FILL)
        biggest = max(math.hypot(p["length_m"], p["width_m"]) for p in self._params[:count])
        return max(fill, biggest + 2.0 * _BORDER_M)

    def expected(self, count: int, extent: float) -> float:
        """Expected number of points with ``count`` buildings in ``extent`` x ``extent``."""
        self._grow_buildings(count)
        n = self._bpts[count] + self.ground_rho * (extent**2 - self._bfoot[count])
        if self.veg_rho > 0.0:
            trees = _default_tree_count(extent) if self.n_trees is None else self.n_trees
            n += self._trees_points(trees)
        return float(n)


def _solve_increasing(func: Any, target: float, lo: float) -> float:
    """Smallest-ish x >= lo with func(x) ~= target, for a non-decreasing func (bisection).

    Returns ``lo`` if func(lo) >= target and the last upper bound tried if func never
    reaches the target.
    """
    if func(lo) >= target:
        return lo
    hi = 2.0 * lo
    while func(hi) < target:
        if hi > 1e6:
            return hi
        lo, hi = hi, 2.0 * hi
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if func(mid) < target:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-6 * hi:
            break
    return hi


# --------------------------------------------------------------------------- survey error

SURVEY_ERROR_KINDS = ("none", "mls", "als", "tls", "field")
"""Kinds of correlated survey error accepted by :class:`SurveyError`."""

# SeedSequence spawn keys: (_KEY_SURVEY, purpose) from the error seed, (_KEY_NONFLAT, building
# + 1, role) from the surface seed (the same key as the surface's sampling, other stream).
_KEY_SURVEY = 21
_KEY_NONFLAT = 22
_SUB_GPS = 1  # start time of the survey
_SUB_MLS_DRIFT = 2  # random Fourier features of the trajectory drift
_SUB_ALS_LAYOUT = 3  # flight heading
_SUB_ALS_ASSIGN = 4  # strip of each point in an overlap
_SUB_UNIT_ERROR = 5  # rigid error of each strip / setup
_SUB_LEVER_ARM = 6  # MLS lever-arm error in the vehicle's frame
_SUB_BORESIGHT = 7  # ALS boresight roll
_SUB_FIELD = 8  # plane waves of the smooth error field

_MLS_LINE_SPACING_M = 22.0  # nominal spacing of the parallel streets of the drive path
_MLS_SPEED_M_S = 5.0  # vehicle speed
_MLS_PATH_STEP_M = 0.5  # sampling step of the drive path (finer for short correlations)
_MLS_MAX_PATH_SAMPLES = 2_000_000
_N_FOURIER = 64  # random Fourier features per axis of the MLS drift
_ALS_OVERLAP = 0.30  # side overlap of neighbouring strips (share of the strip width)
_ALS_SPEED_M_S = 60.0  # aircraft ground speed
_ALS_TURN_S = 120.0  # time between two strips
_ALS_HALF_FOV_RAD = math.radians(30.0)  # half scan angle: flying height = half width / tan
_ALS_MIN_DEPTH_M = 1.0  # smallest height of the aircraft above a point (boresight geometry)
_N_FIELD_WAVES = 64  # plane waves per axis of the "field" kind
_DEFAULT_PATH_AZIMUTH_DEG = 90.0  # MLS drive lines along x (east-west)
_DEFAULT_WAVELENGTHS_M = (37.0, 53.0)
_TLS_HEIGHT_M = 1.7  # instrument height above the ground (rotation centre of a setup)
_TLS_SCAN_S = 300.0  # duration of one scan (the head turns once)
_TLS_MOVE_S = 600.0  # time between the end of a scan and the start of the next
_GPS_START_MAX_S = 302_400.0  # a survey starts in the first half of the GPS week
_NONFLAT_WAVES = 8  # sinusoids per surface
_NONFLAT_WAVELENGTH_M = (3.0, 15.0)
_MAX_UNITS = 65_535  # point source ids are uint16


@dataclass(frozen=True)
class SurveyError:
    """Correlated error model of one survey epoch (see :func:`apply_survey_error`).

    Range noise (:attr:`Scene.noise_m`) is independent from point to point; real surveys
    also have errors shared by many points: the drift of a mobile mapper's trajectory, the
    offset of an airborne strip, the registration of a terrestrial setup. They are what
    limits the comparison of two epochs at the millimetre level. The true surfaces are not
    perfect planes either (``nonflat_m``).

    Attributes
    ----------
    kind : str
        "none" (no correlated error, ``level_m`` must be 0), "mls" (trajectory drift along
        a serpentine drive path), "als" (a rigid error per flight strip), "tls" (a rigid
        registration error per setup) or "field" (a smooth error field of the horizontal
        position, of short wavelength, seen by a mobile mapper); see
        :data:`SURVEY_ERROR_KINDS`.
    level_m : float
        Standard deviation of the correlated error on each axis (metres, >= 0): typically
        0-5 mm of MLS drift, up to 3 cm of ALS strip offset, a few mm of TLS registration.
    correlation_length_m : float
        MLS: correlation length ``l`` of the drift along the drive path (metres of path
        travelled, > 0); the correlation of two points ``ds`` apart along the path is
        ``exp(-ds**2 / (2 l**2))`` (0.61 at ``l``, 0.011 at ``3 l``).
    strip_width_m : float
        ALS: width of one flight strip (metres, > 0; neighbouring strips overlap by 30 %).
        TLS: spacing of the grid of setups (metres, > 0).
    rotation_rad : float
        ALS / TLS: standard deviation of a small random rotation (about each axis) of each
        strip about its centre on the ground, or of each setup about the instrument
        (radians, >= 0); 0 (default) gives pure translations. Must be 0 for the other kinds.
    nonflat_m : float
        Standard deviation (metres, >= 0) of the smooth non-flatness of every planar
        surface: the true surface is a plane plus a random bump field (sinusoids of 3-15 m
        wavelength in the surface's own coordinates) applied along its normal. It belongs to
        the surfaces, so two epochs of the same buildings get the same bumps.
    lever_arm_m : float
        MLS: standard deviation (metres, >= 0) of each component of the lever-arm error, a
        constant vector in the vehicle's frame (forward, left, up) drawn once per survey.
        In map coordinates its horizontal part turns with the vehicle's heading: it flips
        sign between two passes driven in opposite directions and turns by 90° between
        crossing streets (``path_azimuth_deg``); its vertical part is a constant offset.
        Must be 0 for the other kinds.
    path_azimuth_deg : float
        MLS / field: azimuth of the parallel streets of the drive path (degrees clockwise
        from north, finite): 90 (default) drives along x, 0 along y (streets crossing the
        default's). Must be 90 for the other kinds.
    boresight_roll_rad : float
        ALS: standard deviation (radians, >= 0) of the boresight roll error, a rotation of
        the scanner about the flight direction drawn once per survey (a calibration error
        of the system, the same in every strip). A point at cross-track distance ``c`` from
        its strip's nadir line and ``h`` below the aircraft is measured at scan angle
        ``atan2(c, h) + roll`` with its true range: it moves up by about ``roll * c`` and
        cross-track by about ``roll * h``. Strips are flown alternately in the two
        directions, so the tilt alternates from strip to strip in map coordinates. The
        flying height is ``strip_width_m / 2 / tan(30°)`` (a ±30° scan). Must be 0 for the
        other kinds.
    n_setups : int
        TLS: number of setups (>= 0); 0 (default) puts them on a grid of spacing about
        ``strip_width_m``, ``n`` > 0 on an ``nx`` × ``ny`` grid with ``nx * ny == n`` of
        the aspect closest to the area's (6 on a square: 2 × 3). Must be 0 for the other
        kinds.
    wavelength_range_m : (2,) tuple of float
        Field: the smallest and largest wavelength of the plane waves of the error field
        (metres, ``0 < lo <= hi``); default (37, 53).

    Raises
    ------
    InvalidParameterError
        For an unknown kind, a negative or non-finite level, rotation, non-flatness, lever
        arm or boresight roll, a non-positive length, a bad wavelength range or setup
        count, or an option the kind does not use.
    """

    kind: str = "none"
    level_m: float = 0.0
    correlation_length_m: float = 30.0
    strip_width_m: float = 40.0
    rotation_rad: float = 0.0
    nonflat_m: float = 0.0
    lever_arm_m: float = 0.0
    path_azimuth_deg: float = _DEFAULT_PATH_AZIMUTH_DEG
    boresight_roll_rad: float = 0.0
    n_setups: int = 0
    wavelength_range_m: tuple[float, float] = _DEFAULT_WAVELENGTHS_M

    def __post_init__(self) -> None:
        kind = self.kind
        if not isinstance(kind, str) or kind.lower() not in SURVEY_ERROR_KINDS:
            allowed = ", ".join(repr(k) for k in SURVEY_ERROR_KINDS)
            raise InvalidParameterError(f"kind={kind!r} is unknown; use one of {allowed}")
        kind = kind.lower()
        object.__setattr__(self, "kind", kind)
        for name in ("level_m", "rotation_rad", "nonflat_m", "lever_arm_m", "boresight_roll_rad"):
            object.__setattr__(self, name, _check_non_negative(name, getattr(self, name)))
        object.__setattr__(
            self, "path_azimuth_deg", _check_float("path_azimuth_deg", self.path_azimuth_deg)
        )
        object.__setattr__(self, "n_setups", _check_int("n_setups", self.n_setups, minimum=0))
        object.__setattr__(self, "wavelength_range_m", _check_wavelengths(self.wavelength_range_m))
        for name in ("correlation_length_m", "strip_width_m"):
            object.__setattr__(self, name, _check_positive(name, getattr(self, name)))
        if kind == "none" and self.level_m > 0.0:
            raise InvalidParameterError(
                f"level_m={self.level_m!r} needs a correlated error kind; set kind to 'mls', "
                "'als' or 'tls', or level_m=0"
            )
        if kind in ("none", "mls", "field") and self.rotation_rad > 0.0:
            raise InvalidParameterError(
                f"rotation_rad={self.rotation_rad!r} applies to ALS strips and TLS setups "
                f"only; set rotation_rad=0 for kind={kind!r}"
            )
        if kind != "mls" and self.lever_arm_m > 0.0:
            raise InvalidParameterError(
                f"lever_arm_m={self.lever_arm_m!r} applies to MLS trajectories only; set "
                f"lever_arm_m=0 for kind={kind!r}, or kind='mls'"
            )
        if kind not in ("mls", "field") and self.path_azimuth_deg != _DEFAULT_PATH_AZIMUTH_DEG:
            raise InvalidParameterError(
                f"path_azimuth_deg={self.path_azimuth_deg!r} sets the MLS drive path; leave it "
                f"at {_DEFAULT_PATH_AZIMUTH_DEG} for kind={kind!r}, or kind='mls' / 'field'"
            )
        if kind != "als" and self.boresight_roll_rad > 0.0:
            raise InvalidParameterError(
                f"boresight_roll_rad={self.boresight_roll_rad!r} applies to ALS strips only; "
                f"set boresight_roll_rad=0 for kind={kind!r}, or kind='als'"
            )
        if kind != "tls" and self.n_setups > 0:
            raise InvalidParameterError(
                f"n_setups={self.n_setups!r} applies to TLS only; set n_setups=0 for "
                f"kind={kind!r}, or kind='tls'"
            )


def _check_wavelengths(value: Any) -> tuple[float, float]:
    """``wavelength_range_m`` as two floats ``0 < lo <= hi`` (metres)."""
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"wavelength_range_m={value!r} must be two numbers (lo, hi) in metres"
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
        raise InvalidParameterError(
            f"wavelength_range_m={value!r} must be two finite wavelengths 0 < lo <= hi (metres)"
        )
    return (lo, hi)


@dataclass(frozen=True, eq=False)
class SurveyErrorDraw:
    """One random draw of a :class:`SurveyError` on a scene.

    Attributes
    ----------
    points : numpy.ndarray
        (N, 3) float64 the scene's points plus ``error`` (metres); a new array.
    error : numpy.ndarray
        (N, 3) float64 error vector added to each point (metres): the correlated survey
        error plus the non-flatness along the surface normal.
    point_source_id : numpy.ndarray
        (N,) uint16 acquisition unit of each point, from 1: the MLS pass (line of the drive
        path), the ALS strip, the TLS setup; all 1 for kind "none".
    gps_time : numpy.ndarray
        (N,) float64 plausible GPS time of each point (seconds of the GPS week): MLS the
        time along the drive path, ALS the time along its strip's flight line, TLS a block of
        time per setup (the scanner head turns once per scan); all 0 for kind "none".
    model : SurveyError
        The error model drawn.
    """

    points: np.ndarray
    error: np.ndarray
    point_source_id: np.ndarray
    gps_time: np.ndarray
    model: SurveyError


def apply_survey_error(
    scene: Scene, model: SurveyError, *, seed: int, surface_seed: int | None = None
) -> SurveyErrorDraw:
    """Add one random draw of correlated survey error to a scene's points.

    Physics of each kind (see :class:`SurveyError` for the options):

    - "mls": the vehicle drives a serpentine of parallel streets along x, about 22 m apart
      (lines at the middle of equal bands of the scene, joined outside the scene), at 5 m/s.
      Each point is seen from the nearest point of the path in the horizontal plane, which
      gives its path length ``s``, its time and its pass (the line, ``point_source_id``).
      The trajectory drift is a stationary Gaussian process of ``s``, independent on each
      axis, of standard deviation ``level_m`` and squared-exponential correlation of length
      ``correlation_length_m`` (64 random Fourier features per axis: every point's error is
      exactly Gaussian of variance ``level_m**2``). A wall between two streets is seen from
      both, with different errors. ``path_azimuth_deg`` turns the streets (0: along y).
      With ``lever_arm_m > 0`` a lever-arm error ``b`` (forward, left, up; drawn once from
      ``N(0, lever_arm_m**2 I3)``) is added in the vehicle's frame at the heading of the
      path where the point was seen: ``b_f h + b_l (z × h) + b_u z`` for the unit heading
      ``h``; passes driven in opposite directions get opposite horizontal errors.
    - "als": parallel flight strips at a random heading, ``strip_width_m`` wide, 30 % side
      overlap, covering the scene; a point in an overlap belongs to either strip at random
      (real returns come from both). Each strip moves rigidly: a translation drawn from
      ``N(0, level_m**2 I3)`` and a rotation (rotation vector from ``N(0, rotation_rad**2
      I3)``) about the strip's centre on the ground. Strips are flown alternately in the
      two directions at 60 m/s. With ``boresight_roll_rad > 0`` one roll error of the
      scanner (drawn from ``N(0, boresight_roll_rad**2)``) turns every beam about the flight
      line (flying height ``strip_width_m / 2 / tan 30°`` above the ground): each point is
      placed at its true range and its scan angle plus the roll, exactly (no small-angle
      approximation).
    - "tls": setups on a grid of spacing about ``strip_width_m`` through the scene, 1.7 m
      above the ground, numbered along a serpentine; each point belongs to the nearest setup
      (horizontally), which moves rigidly as an ALS strip does (rotation about the
      instrument). ``n_setups > 0`` sets their count instead (an ``nx`` × ``ny`` grid).
    - "field": a smooth error field of the horizontal position (the same for all points
      above one spot, not along a path), independent on each axis: per axis a sum of 64
      plane waves of random direction and phase and wavelength uniform in
      ``wavelength_range_m``, scaled to the standard deviation ``level_m``; the covariance
      of two points a horizontal distance ``r`` apart is ``level_m**2`` times the mean of
      ``J0(2 pi r / wavelength)`` over the wavelengths (0 near ``r = 0.38 wavelength``).
      Pass ids and times come from the MLS drive path (the sensor is a mobile mapper).
    - any kind with ``nonflat_m > 0``: every planar surface gets a smooth bump along its
      normal, a sum of 8 sinusoids of random direction, phase and wavelength (3-15 m) in the
      surface's own 2-D coordinates, with amplitudes giving a standard deviation of
      ``nonflat_m`` over a large surface. The bumps depend on ``surface_seed`` and on the
      surface's building and place in it only (not on the profile or the epoch's sampling),
      so two epochs of the same buildings given the same ``surface_seed`` get the same
      bumps. Vegetation (label -1) gets none.

    Parameters
    ----------
    scene : Scene
        A scene from :func:`make_scene`; not modified. The survey layout (path, strips,
        setups) covers its square ``[0, extent_m]²`` (shifted by ``origin``), or the
        points' bounding box when ``extent_m`` is not finite.
    model : SurveyError
        The error model of this epoch.
    seed : int
        Non-negative seed of the survey error (same seed, same draw).
    surface_seed : int, optional
        Non-negative seed of the non-flatness; default ``seed``. Give the seed of the scene
        that made the buildings to every epoch of them.

    Returns
    -------
    SurveyErrorDraw
        Points (N, 3) with the error, the error (N, 3), source ids (N,) and GPS times (N,).

    Raises
    ------
    InvalidParameterError
        For a model that is not a :class:`SurveyError`, a negative seed, or a layout with
        more than 65535 passes, strips or setups.

    Notes
    -----
    The cost is linear in the points (plus a k-d tree query for "mls" and "tls"): about a
    second for a million points.
    """
    if not isinstance(model, SurveyError):
        raise InvalidParameterError(
            f"model must be a SurveyError, not {type(model).__name__}; "
            "build one with SurveyError(kind=..., level_m=...)"
        )
    seed = _check_int("seed", seed, minimum=0)
    surface_seed = (
        seed if surface_seed is None else _check_int("surface_seed", surface_seed, minimum=0)
    )
    pts = np.asarray(scene.points, dtype=np.float64)
    n = pts.shape[0]
    origin = np.asarray(scene.origin, dtype=np.float64)
    error = np.zeros((n, 3))
    ids = np.ones(n, dtype=np.uint16)
    gps = np.zeros(n)
    if n and model.kind != "none":
        local = pts - origin
        lo, hi = _survey_area(scene, local)
        t0 = float(_rng(seed, _KEY_SURVEY, _SUB_GPS).uniform(0.0, _GPS_START_MAX_S))
        if model.kind in ("mls", "field"):
            error, unit, gps = _mls_error(local, lo, hi, model, seed)
        else:
            layout = _als_layout if model.kind == "als" else _tls_layout
            unit, centres, gps = layout(local, lo, hi, model, seed)
            error = _rigid_unit_errors(local, unit, centres, model, seed)
            if model.kind == "als" and model.boresight_roll_rad > 0.0:
                error = error + _boresight_roll_error(local, unit, centres, model, seed)
        ids = (unit + 1).astype(np.uint16)
        gps = gps + t0
    if n and model.nonflat_m > 0.0:
        error = error + _nonflat_error(scene, model.nonflat_m, surface_seed)
    points = pts + error if (model.kind != "none" or model.nonflat_m > 0.0) else pts.copy()
    return SurveyErrorDraw(
        points=points, error=error, point_source_id=ids, gps_time=gps, model=model
    )


def _survey_area(scene: Scene, local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local xy bounds lo, hi (2,) of the surveyed area: the scene's square, else the box."""
    extent = float(scene.extent_m)
    if math.isfinite(extent) and extent > 0.0:
        return np.zeros(2), np.full(2, extent)
    return local[:, :2].min(axis=0), local[:, :2].max(axis=0)


def _check_units(count: int, what: str, option: str) -> None:
    if count > _MAX_UNITS:
        raise InvalidParameterError(
            f"the survey layout has {count} {what}, more than the {_MAX_UNITS} point source "
            f"ids a LAS file can hold; increase {option}"
        )


def _serpentine(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drive path: vertices (V, 2) of parallel lines along x joined outside the area.

    Returns the vertices and, per segment (V - 1,), the index of its line (a connector
    counts with the line it leads to).
    """
    height = float(hi[1] - lo[1])
    n_lines = max(1, int(round(height / _MLS_LINE_SPACING_M)))
    _check_units(n_lines, "drive lines", "the scene's extent or use fewer, longer lines")
    band = height / n_lines
    ys = lo[1] + (np.arange(n_lines) + 0.5) * band
    # connectors farther from the area than any point is from its nearest line
    margin = max(_MLS_LINE_SPACING_M, band)
    x0, x1 = float(lo[0]) - margin, float(hi[0]) + margin
    verts = []
    for k, y in enumerate(ys):
        ends = [(x0, y), (x1, y)] if k % 2 == 0 else [(x1, y), (x0, y)]
        verts += ends
    line_of_segment = np.arange(2 * n_lines - 1) // 2
    line_of_segment[1::2] += 1  # connectors
    return np.array(verts, dtype=np.float64), line_of_segment


def _mls_path(
    local: np.ndarray, lo: np.ndarray, hi: np.ndarray, model: SurveyError
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Where the vehicle saw each point from: path length ``s`` (N,), pass (N,) from 0, unit
    heading (N, 2) in map coordinates, the path's total length and its sampling step."""
    from scipy.spatial import cKDTree

    ell = model.correlation_length_m
    xy = local[:, :2]
    frame = None
    if model.path_azimuth_deg != _DEFAULT_PATH_AZIMUTH_DEG:
        # path frame: rows (along the streets, across them); the default is the identity
        az = math.radians(model.path_azimuth_deg)
        frame = np.array([[math.sin(az), math.cos(az)], [-math.cos(az), math.sin(az)]])
        corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        corners = corners @ frame.T
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        xy = xy @ frame.T
    verts, line_of_segment = _serpentine(lo, hi)
    start, end = verts[:-1], verts[1:]
    lengths = np.linalg.norm(end - start, axis=1)
    total = float(lengths.sum())
    step = min(_MLS_PATH_STEP_M, ell / 10.0, total)
    step = max(step, total / _MLS_MAX_PATH_SAMPLES)
    counts = np.maximum(1, np.ceil(lengths / step).astype(np.int64))
    seg = np.repeat(np.arange(lengths.size), counts)
    k = np.arange(seg.size) - np.repeat(np.cumsum(counts) - counts, counts)
    frac = (k + 0.5) / counts[seg]
    samples = start[seg] + frac[:, None] * (end - start)[seg]
    tangent = (end - start) / lengths[:, None]
    s_start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    s_samples = s_start[seg] + frac * lengths[seg]
    half = 0.5 * lengths[seg] / counts[seg]

    _, idx = cKDTree(samples).query(xy)
    heading = tangent[seg[idx]]
    along = np.einsum("ij,ij->i", xy - samples[idx], heading)
    s = s_samples[idx] + np.clip(along, -half[idx], half[idx])
    if frame is not None:
        heading = heading @ frame  # back to map coordinates
    return s, line_of_segment[seg[idx]], heading, total, step


def _mls_error(
    local: np.ndarray, lo: np.ndarray, hi: np.ndarray, model: SurveyError, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Error (N, 3), pass index (N,) from 0 and time since the start (N,) of MLS points:
    the trajectory drift plus the lever-arm error ("mls") or the smooth field ("field")."""
    s, line, heading, total, step = _mls_path(local, lo, hi, model)
    if model.kind == "field":
        return _field_error(local, model, seed), line, s / _MLS_SPEED_M_S

    # stationary Gaussian drift: random Fourier features of the squared-exponential kernel
    ell = model.correlation_length_m
    rng = _rng(seed, _KEY_SURVEY, _SUB_MLS_DRIFT)
    omega = rng.normal(0.0, 1.0 / ell, size=_N_FOURIER)
    a = rng.normal(size=(_N_FOURIER, 3))
    b = rng.normal(size=(_N_FOURIER, 3))
    grid = np.linspace(0.0, total, max(2, int(math.ceil(total / step)) + 1))
    phase = np.outer(grid, omega)
    drift = (np.cos(phase) @ a + np.sin(phase) @ b) * (model.level_m / math.sqrt(_N_FOURIER))
    error = np.column_stack([np.interp(s, grid, drift[:, axis]) for axis in range(3)])
    if model.lever_arm_m > 0.0:
        error = error + _lever_arm_error(heading, model, seed)
    return error, line, s / _MLS_SPEED_M_S


def _lever_arm_error(heading: np.ndarray, model: SurveyError, seed: int) -> np.ndarray:
    """(N, 3) lever-arm error of points seen at unit headings (N, 2): a constant vector
    (forward, left, up) in the vehicle's frame, turned into map coordinates."""
    fwd, left, up = _rng(seed, _KEY_SURVEY, _SUB_LEVER_ARM).normal(size=3) * model.lever_arm_m
    out = np.empty((heading.shape[0], 3))
    out[:, 0] = fwd * heading[:, 0] - left * heading[:, 1]
    out[:, 1] = fwd * heading[:, 1] + left * heading[:, 0]
    out[:, 2] = up
    return out


def _field_error(local: np.ndarray, model: SurveyError, seed: int) -> np.ndarray:
    """(N, 3) smooth error field of the horizontal position: per axis a sum of plane waves
    of random direction, phase and wavelength (uniform in ``wavelength_range_m``), of
    standard deviation ``level_m`` (random Fourier features of an isotropic field)."""
    rng = _rng(seed, _KEY_SURVEY, _SUB_FIELD)
    lo_w, hi_w = model.wavelength_range_m
    scale = model.level_m * math.sqrt(2.0 / _N_FIELD_WAVES)
    out = np.zeros((local.shape[0], 3))
    x, y = local[:, 0], local[:, 1]
    for axis in range(3):
        wavenumber = 2.0 * math.pi / rng.uniform(lo_w, hi_w, _N_FIELD_WAVES)
        direction = rng.uniform(0.0, 2.0 * math.pi, _N_FIELD_WAVES)
        phase = rng.uniform(0.0, 2.0 * math.pi, _N_FIELD_WAVES)
        kx, ky = wavenumber * np.cos(direction), wavenumber * np.sin(direction)
        for j in range(_N_FIELD_WAVES):  # wave by wave: no (N, waves) temporary
            out[:, axis] += np.cos(kx[j] * x + ky[j] * y + phase[j])
    return out * scale


def _als_heading(seed: int) -> float:
    """Heading of the flight lines (radians counter-clockwise from +x, in [0, pi))."""
    return float(_rng(seed, _KEY_SURVEY, _SUB_ALS_LAYOUT).uniform(0.0, math.pi))


def _boresight_roll_error(
    local: np.ndarray, strip: np.ndarray, centres: np.ndarray, model: SurveyError, seed: int
) -> np.ndarray:
    """(N, 3) error of ALS points from one boresight roll of the scanner (exact geometry).

    Strip ``j``'s nadir line runs through ``centres[j]`` along the flight heading; even
    strips are flown along it, odd ones against it. A point ``c`` to the right of the
    aircraft and ``h`` below it is seen at scan angle ``atan2(c, h)``; with the roll it is
    placed at that angle plus the roll, at its true range.
    """
    roll = float(_rng(seed, _KEY_SURVEY, _SUB_BORESIGHT).normal()) * model.boresight_roll_rad
    heading = _als_heading(seed)
    along = np.array([math.cos(heading), math.sin(heading)])
    right_of_even = np.array([along[1], -along[0]])  # right of an aircraft flying along +along
    sign = np.where(strip % 2 == 0, 1.0, -1.0)
    right = sign[:, None] * right_of_even
    c = np.einsum("ij,ij->i", local[:, :2] - centres[strip, :2], right)
    height = 0.5 * model.strip_width_m / math.tan(_ALS_HALF_FOV_RAD)
    h = np.maximum(height - local[:, 2], _ALS_MIN_DEPTH_M)
    rng_m = np.hypot(c, h)
    angle = np.arctan2(c, h) + roll
    out = np.empty((local.shape[0], 3))
    out[:, :2] = (rng_m * np.sin(angle) - c)[:, None] * right
    out[:, 2] = h - rng_m * np.cos(angle)
    return out


def _als_layout(
    local: np.ndarray, lo: np.ndarray, hi: np.ndarray, model: SurveyError, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Strip index (N,) from 0, strip centres (S, 3) and time since the start (N,)."""
    heading = _als_heading(seed)
    along_dir = np.array([math.cos(heading), math.sin(heading)])
    across_dir = np.array([-math.sin(heading), math.cos(heading)])
    corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
    q_lo, q_hi = (corners @ across_dir).min(), (corners @ across_dir).max()
    a_lo, a_hi = (corners @ along_dir).min(), (corners @ along_dir).max()
    width = model.strip_width_m
    spacing = (1.0 - _ALS_OVERLAP) * width
    n_strips = 1 if q_hi - q_lo <= width else int(math.ceil((q_hi - q_lo - width) / spacing)) + 1
    _check_units(n_strips, "flight strips", "strip_width_m")
    first = 0.5 * (q_lo + q_hi) - 0.5 * (n_strips - 1) * spacing
    q = local[:, :2] @ across_dir
    j_lo = np.clip(np.ceil((q - first - 0.5 * width) / spacing), 0, n_strips - 1)
    j_hi = np.clip(np.floor((q - first + 0.5 * width) / spacing), 0, n_strips - 1)
    j_hi = np.maximum(j_hi, j_lo)  # at most two strips cover a point (overlap < 50 %)
    pick = _rng(seed, _KEY_SURVEY, _SUB_ALS_ASSIGN).random(q.size) < 0.5
    strip = np.where(pick, j_hi, j_lo).astype(np.int64)
    centre_q = first + spacing * np.arange(n_strips)
    centres = np.zeros((n_strips, 3))
    centres[:, :2] = 0.5 * (a_lo + a_hi) * along_dir + centre_q[:, None] * across_dir
    along = local[:, :2] @ along_dir
    duration = (a_hi - a_lo) / _ALS_SPEED_M_S
    flown = np.where(strip % 2 == 0, along - a_lo, a_hi - along) / _ALS_SPEED_M_S
    return strip, centres, strip * (duration + _ALS_TURN_S) + flown


def _tls_layout(
    local: np.ndarray, lo: np.ndarray, hi: np.ndarray, model: SurveyError, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Setup index (N,) from 0, setup positions (S, 3) and time since the start (N,)."""
    from scipy.spatial import cKDTree

    size = hi - lo
    if model.n_setups > 0:
        nx, ny = _grid_shape(model.n_setups, float(size[0]), float(size[1]))
    else:
        nx, ny = (max(1, int(round(float(v) / model.strip_width_m))) for v in size)
    _check_units(nx * ny, "setups", "strip_width_m")
    xs = lo[0] + (np.arange(nx) + 0.5) * size[0] / nx
    ys = lo[1] + (np.arange(ny) + 0.5) * size[1] / ny
    rows = [[(x, y) for x in (xs if j % 2 == 0 else xs[::-1])] for j, y in enumerate(ys)]
    setups = np.zeros((nx * ny, 3))
    setups[:, :2] = np.array(rows).reshape(-1, 2)
    setups[:, 2] = _TLS_HEIGHT_M
    _, setup = cKDTree(setups[:, :2]).query(local[:, :2])
    rel = local[:, :2] - setups[setup, :2]
    azimuth = np.mod(np.arctan2(rel[:, 1], rel[:, 0]), 2.0 * math.pi)
    time = setup * (_TLS_SCAN_S + _TLS_MOVE_S) + azimuth / (2.0 * math.pi) * _TLS_SCAN_S
    return setup.astype(np.int64), setups, time


def _grid_shape(count: int, width: float, height: float) -> tuple[int, int]:
    """``(nx, ny)`` with ``nx * ny == count`` whose aspect ``nx / ny`` is closest (in log)
    to ``width / height``; the first (smaller ``nx``) on a tie."""
    aspect = math.log(width / height) if width > 0 and height > 0 else 0.0
    best, best_cost = (count, 1), math.inf
    for nx in range(1, count + 1):
        if count % nx == 0:
            cost = abs(math.log(nx / (count // nx)) - aspect)
            if cost < best_cost - 1e-12:
                best, best_cost = (nx, count // nx), cost
    return best


def _rotation_minus_identity(rotvec: np.ndarray) -> np.ndarray:
    """(U, 3) rotation vectors (radians) -> (U, 3, 3) ``R - I`` (0 for no turn)."""
    from .icp import rotation_matrix

    return rotation_matrix(rotvec) - np.eye(3)


def _rigid_unit_errors(
    local: np.ndarray, unit: np.ndarray, centres: np.ndarray, model: SurveyError, seed: int
) -> np.ndarray:
    """(N, 3) error of points moved with their unit: ``t + (R - I) (p - centre)``."""
    rng = _rng(seed, _KEY_SURVEY, _SUB_UNIT_ERROR)
    count = centres.shape[0]
    shift = rng.normal(size=(count, 3)) * model.level_m
    rotvec = rng.normal(size=(count, 3)) * model.rotation_rad
    error = shift[unit]
    if model.rotation_rad > 0.0:
        turn = _rotation_minus_identity(rotvec)
        error = error + np.einsum("nij,nj->ni", turn[unit], local - centres[unit])
    return error


def _surface_keys(scene: Scene) -> list[tuple[int, ...]]:
    """Spawn key of each surface's bumps: (building + 1, role), as its sampling key.

    The role (place of the surface in its building) is found by matching the normal to the
    building's geometry, so it does not depend on the profile (which numbers the surfaces
    differently). Surfaces without a known building get a key from their id.
    """
    keys: list[tuple[int, ...]] = []
    for s in scene.surfaces:
        if s.kind == "ground":
            keys.append((0, 0))
        elif s.kind in ("roof", "facade") and 0 <= s.building < len(scene.buildings):
            b = scene.buildings[s.building]
            geoms = _roof_geoms(b, s.building) if s.kind == "roof" else _facade_geoms(b, s.building)
            normal = np.asarray(s.normal, dtype=np.float64)
            best = geoms[int(np.argmax([float(g.normal @ normal) for g in geoms]))]
            keys.append((s.building + 1, best.role))
        else:
            keys.append((1_000_000 + s.id, 0))
    return keys


def _surface_frame(normal: np.ndarray) -> np.ndarray:
    """(2, 3) unit in-plane axes of a surface (horizontal first for walls and roofs)."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(normal[2]) >= 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = np.cross(ref, normal)
    e1 /= np.linalg.norm(e1)
    return np.array([e1, np.cross(normal, e1)])


def _nonflat_error(scene: Scene, amplitude: float, surface_seed: int) -> np.ndarray:
    """(N, 3) bump of each point along its surface's normal (metres); 0 for clutter."""
    out = np.zeros((scene.points.shape[0], 3))
    labels = np.asarray(scene.labels)
    if not scene.surfaces:
        return out
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    origin = np.asarray(scene.origin, dtype=np.float64)
    lo_w, hi_w = _NONFLAT_WAVELENGTH_M
    scale = amplitude * math.sqrt(2.0 / _NONFLAT_WAVES)
    for surface, key in zip(scene.surfaces, _surface_keys(scene)):
        first, last = np.searchsorted(sorted_labels, [surface.id, surface.id + 1])
        if first == last:
            continue
        idx = order[first:last]
        normal = np.asarray(surface.normal, dtype=np.float64)
        uv = (scene.points[idx] - origin) @ _surface_frame(normal).T
        rng = _rng(surface_seed, _KEY_NONFLAT, *key)
        wavelength = rng.uniform(lo_w, hi_w, _NONFLAT_WAVES)
        direction = rng.uniform(0.0, 2.0 * math.pi, _NONFLAT_WAVES)
        phase = rng.uniform(0.0, 2.0 * math.pi, _NONFLAT_WAVES)
        wave = (2.0 * math.pi / wavelength)[:, None] * np.array(
            [np.cos(direction), np.sin(direction)]
        ).T
        bump = scale * np.cos(uv @ wave.T + phase).sum(axis=1)
        out[idx] = bump[:, None] * normal
    return out


# --------------------------------------------------------------------------- fault pairs


@dataclass(frozen=True)
class FaultPair:
    """Two epochs of the same scene with a known rigid offset on each side of a fault.

    Attributes
    ----------
    before, after : Scene
        The epochs; ``after`` is sampled independently (other points, other noise, possibly
        another profile) from the same buildings, then each side is moved by its offset
        (``after.surfaces`` still describe the unmoved geometry). With survey error models
        their points include the drawn errors.
    trace_xy : (2, 2) float64
        The fault trace (two vertices, map coordinates incl. ``origin``), digitised from the
        first to the second vertex.
    left_offset_m, right_offset_m : (3,) float64
        Displacement of the material left and right of the digitised trace (metres).
    side_before, side_after : (N,) int8
        -1 left, +1 right of each point; every point moves with its side.
    moved_buildings : tuple of int
        Buildings given an extra ``blunder_offset_m`` (renovated / rebuilt: not the signal).
    source_before, source_after : (N,) uint16, optional
        Point source id (MLS pass, ALS strip, TLS setup) of each point of an epoch drawn
        with a :class:`SurveyError`; None for an epoch without one.
    gps_time_before, gps_time_after : (N,) float64, optional
        GPS time of each point (seconds) of an epoch with an error model; None otherwise.
    error_before, error_after : (N, 3) float64, optional
        Survey error (incl. non-flatness) added to each point of an epoch (metres), before
        the side offsets; None for an epoch without an error model.
    """

    before: Scene
    after: Scene
    trace_xy: np.ndarray
    left_offset_m: np.ndarray
    right_offset_m: np.ndarray
    side_before: np.ndarray
    side_after: np.ndarray
    moved_buildings: tuple = ()
    source_before: Optional[np.ndarray] = None
    source_after: Optional[np.ndarray] = None
    gps_time_before: Optional[np.ndarray] = None
    gps_time_after: Optional[np.ndarray] = None
    error_before: Optional[np.ndarray] = None
    error_after: Optional[np.ndarray] = None

    @property
    def relative_offset_m(self) -> np.ndarray:
        """Right minus left (3,), metres."""
        return self.right_offset_m - self.left_offset_m


def _side_of_line(xy: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    cross = d[0] * (xy[:, 1] - a[1]) - d[1] * (xy[:, 0] - a[0])
    return np.where(cross > 0, -1, 1).astype(np.int8)  # positive cross = left


def make_fault_pair(
    profile: str = "mls",
    *,
    seed: int = 0,
    right_offset_m: Sequence[float] = (0.0, -0.0181, 0.0),
    left_offset_m: Sequence[float] = (0.0, 0.0, 0.0),
    fault_azimuth_deg: float = 0.0,
    reverse_trace: bool = False,
    blunder_fraction: float = 0.0,
    blunder_offset_m: Sequence[float] = (0.5, 0.0, 0.0),
    after_seed: Optional[int] = None,
    error_before: Optional[SurveyError] = None,
    error_after: Optional[SurveyError] = None,
    after_profile: Optional[str] = None,
    error_seed: Optional[int] = None,
    **scene_options: Any,
) -> FaultPair:
    """Two epochs of a synthetic scene cut by a straight fault through its centre.

    Parameters
    ----------
    profile : str
        As :func:`make_scene`.
    seed : int
        Seed of the first epoch (the buildings); the second epoch samples the same buildings
        with ``after_seed`` (default ``seed + 1_000_003``): no point is shared.
    right_offset_m, left_offset_m : (3,) array-like
        Rigid displacement of each side, metres (default: 18.1 mm of dextral slip on a
        north-striking fault — the study's NLOD value — as the right (east) side moving south).
    fault_azimuth_deg : float
        Strike of the trace, degrees clockwise from north (+y).
    reverse_trace : bool
        Digitise the trace the other way (left and right swap; offsets follow the sides).
    blunder_fraction : float
        Share of buildings (at least one when > 0) moved by ``blunder_offset_m`` on top of
        their side's offset.
    blunder_offset_m : (3,) array-like
        Extra displacement of the blundered buildings (metres).
    after_seed : int, optional
        Seed of the second epoch's sampling; default ``seed + 1_000_003``.
    error_before, error_after : SurveyError, optional
        Correlated survey error of each epoch (see :func:`apply_survey_error`), added before
        the side offsets (it is survey error, not motion); None (default) leaves the epoch
        as without it, bit for bit. Both epochs get the same non-flatness (drawn with
        ``surface_seed=seed``, the buildings' seed), so their ``nonflat_m`` must agree (a
        missing model counts as 0).
    after_profile : str, optional
        Acquisition profile of the second epoch (default ``profile``), e.g. "als" after an
        "mls" first epoch: the same buildings seen by another sensor. With another profile,
        ``density_pts_m2`` and ``noise_m`` of ``scene_options`` apply to the first epoch
        only; the second uses its profile's defaults.
    error_seed : int, optional
        Seed of the survey errors (default ``seed``): the first epoch's draw uses
        ``error_seed``, the second's ``error_seed + 1_000_003`` (independent draws).
    **scene_options
        Passed to :func:`make_scene` (``n_buildings``, ``extent_m``, ``density_pts_m2``,
        ``noise_m``, ``origin``, ``ground``, ``vegetation``, ...).

    Returns
    -------
    FaultPair

    Raises
    ------
    InvalidParameterError
        For bad scene options, an error model that is not a :class:`SurveyError`, models
        whose ``nonflat_m`` differ, or a negative ``error_seed``.
    """
    for name, model in (("error_before", error_before), ("error_after", error_after)):
        if model is not None and not isinstance(model, SurveyError):
            raise InvalidParameterError(
                f"{name} must be a SurveyError or None, not {type(model).__name__}"
            )
    nonflat = [0.0 if m is None else m.nonflat_m for m in (error_before, error_after)]
    if nonflat[0] != nonflat[1]:
        raise InvalidParameterError(
            f"error_before.nonflat_m={nonflat[0]!r} and error_after.nonflat_m={nonflat[1]!r} "
            "differ, but the non-flatness belongs to the buildings both epochs see; give both "
            "models the same nonflat_m"
        )
    spec_before = _check_profile(profile)
    spec_after = spec_before if after_profile is None else _check_profile(after_profile)
    if error_seed is not None:
        error_seed = _check_int("error_seed", error_seed, minimum=0)
    before = make_scene(profile, seed=seed, **scene_options)
    opts = dict(scene_options)
    opts.pop("n_buildings", None)
    opts.pop("buildings", None)
    if spec_after.name != spec_before.name:
        opts.pop("density_pts_m2", None)
        opts.pop("noise_m", None)
    after_seed = seed + 1_000_003 if after_seed is None else int(after_seed)
    after_name = profile if after_profile is None else spec_after.name
    after = make_scene(after_name, seed=after_seed, buildings=before.buildings, **opts)
    origin = np.asarray(before.origin, dtype=np.float64)
    half = 0.5 * before.extent_m
    az = math.radians(fault_azimuth_deg)
    direction = np.array([math.sin(az), math.cos(az)])
    centre = origin[:2] + half
    a, b = centre - 2 * half * direction, centre + 2 * half * direction
    if reverse_trace:
        a, b = b, a
    right = np.asarray(right_offset_m, dtype=np.float64)
    left = np.asarray(left_offset_m, dtype=np.float64)
    if reverse_trace:  # the same ground motion, seen with the sides swapped
        right, left = left, right
    n_blunder = 0
    if blunder_fraction > 0 and len(before.buildings):
        n_blunder = max(1, int(round(blunder_fraction * len(before.buildings))))
    moved = tuple(int(k) for k in _rng(seed, 9_999).permutation(len(before.buildings))[:n_blunder])

    def sides(scene: Scene) -> np.ndarray:
        # every point moves with its own side: a building across the trace is torn, as the
        # ground is (the slip workflow leaves out a buffer around the trace)
        return _side_of_line(scene.points[:, :2], a, b)

    # the side (the motion) of a point follows its true position, not the surveyed one
    side_b, side_a = sides(before), sides(after)
    base_seed = seed if error_seed is None else error_seed
    draw_b = draw_a = None
    if error_before is not None:
        draw_b = apply_survey_error(before, error_before, seed=base_seed, surface_seed=before.seed)
        before = dataclasses.replace(before, points=draw_b.points)
    if error_after is not None:
        draw_a = apply_survey_error(
            after, error_after, seed=base_seed + 1_000_003, surface_seed=before.seed
        )
        after = dataclasses.replace(after, points=draw_a.points)
    pts = after.points.copy()
    pts[side_a < 0] += left
    pts[side_a > 0] += right
    if moved:
        pts[np.isin(after.building_ids, moved)] += np.asarray(blunder_offset_m, dtype=np.float64)
    after = dataclasses.replace(after, points=pts)
    return FaultPair(
        before=before,
        after=after,
        trace_xy=np.array([a, b]),
        left_offset_m=left,
        right_offset_m=right,
        side_before=side_b,
        side_after=side_a,
        moved_buildings=moved,
        source_before=None if draw_b is None else draw_b.point_source_id,
        source_after=None if draw_a is None else draw_a.point_source_id,
        gps_time_before=None if draw_b is None else draw_b.gps_time,
        gps_time_after=None if draw_a is None else draw_a.gps_time,
        error_before=None if draw_b is None else draw_b.error,
        error_after=None if draw_a is None else draw_a.error,
    )


@dataclass(frozen=True)
class TrueSurfaceFit:
    """Rigid motion of points relative to their true surfaces (see :func:`fit_true_surfaces`).

    Attributes
    ----------
    translation_m : (3,) float64
        Displacement of the material at ``centre`` (metres).
    rotation_rad : (3,) float64
        Rotation vector about ``centre`` (radians).
    n_points : int
        Points used (those on a true surface).
    rms_m : float
        RMS distance of the points to their true surfaces after the motion is removed
        (metres).
    """

    translation_m: np.ndarray
    rotation_rad: np.ndarray
    n_points: int
    rms_m: float


def fit_true_surfaces(
    points: np.ndarray,
    labels: np.ndarray,
    surfaces: Sequence[Surface],
    *,
    centre: Sequence[float],
    iterations: int = 8,
) -> TrueSurfaceFit:
    """Least-squares rigid motion that best moves the true surfaces onto the points.

    The reference that knows the truth: each point ``p`` lies on its true plane
    (``normal @ x + d == 0``) moved by a rigid motion ``p = R (x - centre) + centre + t``
    plus error; ``(R, t)`` minimise the sum of squared distances of ``R^T (p - centre - t) +
    centre`` to the points' own planes. Gauss-Newton on the rotation vector (the
    point-to-plane step of an ICP with known correspondences), from the identity: exact,
    not small-angle, so noise-free points of a rigidly moved scene give the motion back to
    rounding. What is left is what the survey error (and the point noise) permits.

    Parameters
    ----------
    points : (N, 3) float64
        Observed points (metres), e.g. one side of an epoch of a :class:`FaultPair`.
    labels : (N,) int
        True surface id of each point (:attr:`Scene.labels`); points with a label < 0
        (clutter) are left out.
    surfaces : sequence of Surface
        The true surfaces, ``surfaces[i].id == i`` (:attr:`Scene.surfaces`), in the points'
        coordinates.
    centre : (3,) array-like
        Where the translation is reported and the rotation is about (metres).
    iterations : int
        Gauss-Newton steps (>= 1); it stops earlier once a step is below 1e-12.

    Returns
    -------
    TrueSurfaceFit
        NaN motion when the points do not fix all six parameters (fewer than six points or
        too few surface orientations).
    """
    pts = np.asarray(points, dtype=np.float64)
    lab = np.asarray(labels)
    keep = lab >= 0
    pts, lab = pts[keep], lab[keep].astype(np.int64)
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    normals = np.array([np.asarray(sf.normal, dtype=np.float64) for sf in surfaces]).reshape(-1, 3)
    offsets = np.array([float(sf.d) for sf in surfaces])
    nan = TrueSurfaceFit(np.full(3, np.nan), np.full(3, np.nan), int(pts.shape[0]), math.nan)
    if pts.shape[0] < 6:
        return nan
    n, d = normals[lab], offsets[lab]
    from .rotation import rotation_matrix, rotation_vector

    rot, t = np.eye(3), np.zeros(3)
    x = pts
    for _ in range(max(1, int(iterations))):
        x = (pts - c - t) @ rot + c  # R^T (p - c - t) + c, row-wise
        r = np.einsum("ij,ij->i", n, x) + d
        # x moved by dt + w x (x - c): distance grows by n.dt + w.((x - c) x n)
        a = np.hstack([n, np.cross(x - c, n)])
        step, _, rank, _ = np.linalg.lstsq(a, -r, rcond=None)
        if rank < 6:
            return nan
        # the step moves x (the unmoved estimate) by S (x - c) + c + dt onto its planes:
        # R^T becomes S R^T and t becomes t - R S^T dt
        rot = rot @ rotation_matrix(step[3:]).T
        t = t - rot @ step[:3]
        if float(np.abs(step).max()) < 1e-12:
            break
    x = (pts - c - t) @ rot + c
    rms = float(np.sqrt(np.mean((np.einsum("ij,ij->i", n, x) + d) ** 2)))
    return TrueSurfaceFit(t, rotation_vector(rot), int(pts.shape[0]), rms)


# --------------------------------------------------------------------------- landslide lobe

_KEY_LOBE_SPLIT = 11  # SeedSequence spawn key of the lobe pair's random split


@dataclass(frozen=True, eq=False)
class LobeField:
    """A smooth landslide-like displacement bump on an ellipse (study section 3.2.3).

    The displacement is ``max_d_m * w(r)`` with ``w = (1 - r**2)**2`` for ``r < 1`` and 0
    outside, where ``r`` is the normalised elliptical radius

        r**2 = (s / radius_x_m)**2 + (t / radius_y_m)**2,

    ``(s, t)`` being the offset from ``centre_xy`` along the ellipse's x and y axes. ``w`` is
    1 at the centre, falls monotonically to exactly 0 on the ellipse, stays 0 outside, and is
    continuously differentiable everywhere (its gradient also vanishes on the edge); inside
    it is a polynomial in x and y, so :meth:`gradient` is exact.

    Attributes
    ----------
    centre_xy : tuple of float
        (2,) centre of the lobe (metres, map coordinates, e.g. UTM).
    radius_x_m, radius_y_m : float
        Semi-axes of the ellipse (metres, > 0).
    azimuth_deg : float
        Azimuth of the ``radius_y_m`` axis, degrees clockwise from north; 0 (default) puts
        ``radius_y_m`` along north and ``radius_x_m`` along east.
    max_d_m : tuple of float
        (3,) displacement ``(dx, dy, dz)`` at the centre (metres); the study used
        ``(0, -1.0, -0.4)``.
    """

    centre_xy: tuple[float, float]
    radius_x_m: float
    radius_y_m: float
    azimuth_deg: float = 0.0
    max_d_m: tuple[float, float, float] = (0.0, -1.0, -0.4)

    def __post_init__(self) -> None:
        c = tuple(float(v) for v in np.asarray(self.centre_xy, dtype=np.float64).ravel())
        d = tuple(float(v) for v in np.asarray(self.max_d_m, dtype=np.float64).ravel())
        if len(c) != 2 or not all(math.isfinite(v) for v in c):
            raise InvalidParameterError(
                f"centre_xy must be two finite numbers (metres), got {self.centre_xy!r}."
            )
        if len(d) != 3 or not all(math.isfinite(v) for v in d):
            raise InvalidParameterError(
                "max_d_m must be three finite displacements (dx, dy, dz) in metres, "
                f"got {self.max_d_m!r}."
            )
        for name in ("radius_x_m", "radius_y_m"):
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise InvalidParameterError(
                    f"{name} must be a finite radius > 0 (metres), got {value!r}."
                )
            object.__setattr__(self, name, value)
        if not math.isfinite(float(self.azimuth_deg)):
            raise InvalidParameterError(f"azimuth_deg must be finite, got {self.azimuth_deg!r}.")
        object.__setattr__(self, "azimuth_deg", float(self.azimuth_deg))
        object.__setattr__(self, "centre_xy", c)
        object.__setattr__(self, "max_d_m", d)

    def _axes(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit vectors (2,) of the ellipse's x and y axes in map coordinates."""
        a = math.radians(self.azimuth_deg)
        return np.array([math.cos(a), -math.sin(a)]), np.array([math.sin(a), math.cos(a)])

    def _local(self, xy: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, t, r**2) of (M, 2) points; coordinates are centred before anything else."""
        pts = np.asarray(xy, dtype=np.float64)
        if pts.ndim == 1 and pts.size in (2, 3):
            pts = pts[None, :]
        if pts.ndim != 2 or pts.shape[1] < 2:
            raise InvalidParameterError(
                f"xy must be an (M, 2) array of x, y (metres), got shape {pts.shape}."
            )
        off = pts[:, :2] - np.asarray(self.centre_xy)
        ax, ay = self._axes()
        s, t = off @ ax, off @ ay
        return s, t, (s / self.radius_x_m) ** 2 + (t / self.radius_y_m) ** 2

    def weight(self, xy: Any) -> np.ndarray:
        """(M,) bump ``(1 - r**2)**2`` inside the ellipse, 0 outside (dimensionless)."""
        _, _, q = self._local(xy)
        return np.where(q < 1.0, (1.0 - np.minimum(q, 1.0)) ** 2, 0.0)

    def __call__(self, xy: Any) -> np.ndarray:
        """(M, 3) displacement ``(dx, dy, dz)`` (metres) at (M, 2) points (x, y; more ignored)."""
        return self.weight(xy)[:, None] * np.asarray(self.max_d_m)[None, :]

    def gradient(self, xy: Any) -> np.ndarray:
        """Exact spatial gradient (M, 3, 2): ``[k, i, j] = d(d_i)/d(x_j)`` with x_j = (x, y).

        E.g. ``[:, 0, 1]`` is d(dx)/dy; use it as the true horizontal displacement gradient
        when validating strain maps.
        """
        s, t, q = self._local(xy)
        ax, ay = self._axes()
        inside = q < 1.0
        # w = (1 - q)^2, dw/dq = -2 (1 - q); dq/dxy = 2 s/rx^2 ax + 2 t/ry^2 ay
        dwdq = np.where(inside, -2.0 * (1.0 - np.minimum(q, 1.0)), 0.0)
        dq = (
            2.0 * (s / self.radius_x_m**2)[:, None] * ax
            + 2.0 * (t / self.radius_y_m**2)[:, None] * ay
        )
        dw = dwdq[:, None] * dq  # (M, 2)
        return np.asarray(self.max_d_m)[None, :, None] * dw[:, None, :]

    def interior_mask(self, xy: Any, fraction: float = 0.5) -> np.ndarray:
        """(M,) bool: points with normalised elliptical radius ``r <= fraction``.

        ``fraction=0.5`` keeps the core of the lobe, where the displacement is at least
        ``(1 - 0.25)**2 = 56 %`` of the maximum.
        """
        if not (math.isfinite(float(fraction)) and float(fraction) > 0):
            raise InvalidParameterError(f"fraction must be > 0, got {fraction!r}.")
        _, _, q = self._local(xy)
        return q <= float(fraction) ** 2


@dataclass(frozen=True, eq=False)
class LobePair:
    """Two epochs of a real cloud with a synthetic lobe in the second (study Fig. 3.2 style).

    The epochs share no point: the input points are split at random into two disjoint sets.

    Attributes
    ----------
    before : numpy.ndarray
        (N1, 3) float64 unmoved points ``points[before_index]``.
    after : numpy.ndarray
        (N2, 3) float64 moved points ``points[after_index] + after_truth``.
    field : LobeField
        The displacement field applied.
    after_truth : numpy.ndarray
        (N2, 3) displacement actually applied to each after point, stored as
        ``after - points[after_index]`` (so that identity is exact); it equals
        ``field(points[after_index])`` up to the rounding of the coordinates (about 1e-10 m
        at UTM magnitudes).
    before_index, after_index : numpy.ndarray
        (N1,) and (N2,) int64 indices into the input points, each increasing (input order
        kept); disjoint and together covering all points.
    """

    before: np.ndarray
    after: np.ndarray
    field: LobeField
    after_truth: np.ndarray
    before_index: np.ndarray
    after_index: np.ndarray


def make_lobe_pair(
    points: Any,
    *,
    max_dy_m: float = -1.0,
    max_dz_m: float = -0.4,
    max_dx_m: float = 0.0,
    centre_xy: Optional[Sequence[float]] = None,
    radius_m: Optional[Any] = None,
    azimuth_deg: float = 0.0,
    split: str = "half",
    after_fraction: float = 0.5,
    seed: int = 0,
) -> LobePair:
    """Inject a synthetic landslide lobe into a real point cloud (study section 3.2.3).

    The study added a smooth displacement of at most -1 m in y and -0.4 m in z to one TLS
    epoch and recovered it with PIV and ICP. Re-using the very same points in both epochs
    would make matching trivially exact, so here the cloud is split at random (seeded) into
    two disjoint sets, as two real scans never hit the same spots (study Fig. 3.2): the
    first set is the "before" epoch, unchanged; the second is the "after" epoch, each point
    moved by the lobe's displacement at its original position.

    Parameters
    ----------
    points : array-like
        (N, 3) float64 points (metres; UTM coordinates are fine), N >= 2; not modified.
    max_dx_m, max_dy_m, max_dz_m : float
        Displacement at the lobe's centre (metres); defaults are the study's (0, -1, -0.4).
    centre_xy : (2,) array-like, optional
        Lobe centre (metres); default the centre of the points' bounding box.
    radius_m : float or (2,) array-like, optional
        Semi-axis, or ``(radius_x_m, radius_y_m)`` (metres, > 0); default one third of the
        smaller side of the bounding box.
    azimuth_deg : float
        Azimuth of the ``radius_y_m`` axis (degrees clockwise from north), see
        :class:`LobeField`.
    split : str
        How the epochs are re-sampled; only ``"half"`` (a random split into two disjoint
        sets, see Notes for why there is no ``"jitter"``).
    after_fraction : float
        Share of the points that go to the after epoch, in (0, 1); default a half.
    seed : int
        Seed of the random split (same seed, same split).

    Returns
    -------
    LobePair

    Raises
    ------
    InvalidParameterError
        Radius <= 0, ``after_fraction`` outside (0, 1), ``split`` not "half", non-finite
        options.
    InputDataError
        Fewer than 2 points, points not (N, 3), non-finite coordinates, a zero-size bounding
        box when a default radius is needed, or a lobe that covers none of the after points.

    Notes
    -----
    Only a split is offered, no "jitter" of shared points: moving a point sideways on a
    rough surface without changing its z creates a false vertical signal of about
    slope × jitter, which would pollute the truth. If the input has duplicate points (some
    scanners emit them), identical coordinates can land in both epochs outside the lobe.
    """
    from .errors import InputDataError

    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputDataError(
            f"points must be an (N, 3) array of x, y, z (metres), got shape {pts.shape}."
        )
    n = pts.shape[0]
    if n < 2:
        raise InputDataError(
            f"make_lobe_pair needs at least 2 points to split into two epochs, got {n}."
        )
    if not np.all(np.isfinite(pts)):
        raise InputDataError("points contain NaN or infinite coordinates; drop them first.")
    if split != "half":
        raise InvalidParameterError(
            f"split must be 'half' (a random split into two disjoint epochs), got {split!r}; "
            "jittering shared points is not offered (see make_lobe_pair's notes)."
        )
    frac = float(after_fraction)
    if not (0.0 < frac < 1.0):
        raise InvalidParameterError(f"after_fraction must be in (0, 1), got {after_fraction!r}.")
    lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    centre = 0.5 * (lo + hi) if centre_xy is None else np.asarray(centre_xy, dtype=np.float64)
    if radius_m is None:
        side = float(np.min(hi - lo))
        if not side > 0:
            raise InputDataError(
                "The points' bounding box has zero width or height, so there is no default lobe "
                "radius; give radius_m."
            )
        rx = ry = side / 3.0
    else:
        r = np.atleast_1d(np.asarray(radius_m, dtype=np.float64)).ravel()
        if r.size not in (1, 2):
            raise InvalidParameterError(
                f"radius_m must be a radius or (radius_x_m, radius_y_m), got {radius_m!r}."
            )
        rx, ry = float(r[0]), float(r[-1])
    lobe = LobeField(
        centre_xy=tuple(centre),
        radius_x_m=rx,
        radius_y_m=ry,
        azimuth_deg=azimuth_deg,
        max_d_m=(max_dx_m, max_dy_m, max_dz_m),
    )
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(_KEY_LOBE_SPLIT,)))
    order = rng.permutation(n)
    n_after = min(n - 1, max(1, int(round(frac * n))))
    after_index = np.sort(order[:n_after]).astype(np.int64)
    before_index = np.sort(order[n_after:]).astype(np.int64)
    original = pts[after_index]
    disp = lobe(original[:, :2])
    if not np.any(disp != 0.0) and any(v != 0.0 for v in lobe.max_d_m):
        raise InputDataError(
            f"The lobe (centre {lobe.centre_xy}, radii {rx:g} x {ry:g} m) covers none of the "
            "points; move centre_xy or enlarge radius_m."
        )
    after = original + disp
    return LobePair(
        before=pts[before_index].copy(),
        after=after,
        field=lobe,
        after_truth=after - original,
        before_index=before_index,
        after_index=after_index,
    )


# --------------------------------------------------------------------------------------
# Landslide geometries with discontinuities (issue #29): a translating slab behind a scarp,
# a rotational slump, a field crossed by a fault; TLS halves or an ALS-like resampling.
# --------------------------------------------------------------------------------------

_KEY_LANDSLIDE_SPLIT = 12  # SeedSequence spawn key of the landslide pair's random split
_KEY_ALS = 13  # ... of the ALS-like resampling (one child per epoch)


def _xy_of(xy: Any) -> np.ndarray:
    """(M, 2) float64 x, y of (M, 2+) points or one point (further columns ignored)."""
    pts = np.asarray(xy, dtype=np.float64)
    if pts.ndim == 1 and pts.size in (2, 3):
        pts = pts[None, :]
    if pts.ndim != 2 or pts.shape[1] < 2:
        raise InvalidParameterError(
            f"xy must be an (M, 2) array of x, y (metres), got shape {pts.shape}."
        )
    return pts[:, :2]


def _trace(name: str, value: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Start point (2,), unit direction u (2,) and left normal v = z x u (2,) of a trace
    given as two distinct finite points."""
    t = np.asarray(value, dtype=np.float64)
    if t.shape != (2, 2) or not np.all(np.isfinite(t)):
        raise InvalidParameterError(f"{name} must be two points ((x0, y0), (x1, y1)) in metres.")
    d = t[1] - t[0]
    n = float(np.hypot(d[0], d[1]))
    if not n > 0:
        raise InvalidParameterError(f"{name} must be two distinct points, got {value!r}.")
    u = d / n
    return t[0], u, np.array([-u[1], u[0]])


def _vec3(name: str, value: Any) -> tuple[float, float, float]:
    d = tuple(float(v) for v in np.asarray(value, dtype=np.float64).ravel())
    if len(d) != 3 or not all(math.isfinite(v) for v in d):
        raise InvalidParameterError(
            f"{name} must be three finite displacements (dx, dy, dz) in metres, got {value!r}."
        )
    return d


@dataclass(frozen=True)
class SlabField:
    """A rigid slab translating behind a straight scarp: a step field.

    With the scarp trace from ``p0`` to ``p1`` (unit direction ``u``, left normal
    ``v = (-u_y, u_x)``), the displacement is

        d(p) = d_m   if (p - p0) . v > 0   (the slab, left of the trace)
        d(p) = 0     otherwise             (stable ground),

    so the field jumps by ``d_m`` across the scarp and is constant on each side. A slab
    moving away from the scarp (``d_m . v > 0``) opens a gap behind it where no material of
    the after epoch lies (:func:`material_motion` gives NaN there).

    Attributes
    ----------
    scarp_xy : tuple
        ((x0, y0), (x1, y1)) two points of the scarp trace (metres, map coordinates); the
        side test uses the infinite line through them, the breakline is the segment.
    d_m : tuple of float
        (3,) motion (dx, dy, dz) of the slab (metres).
    """

    scarp_xy: tuple
    d_m: tuple[float, float, float] = (0.0, -0.5, -0.2)

    def __post_init__(self) -> None:
        _trace("scarp_xy", self.scarp_xy)
        t = np.asarray(self.scarp_xy, dtype=np.float64)
        object.__setattr__(self, "scarp_xy", tuple(tuple(float(v) for v in r) for r in t))
        object.__setattr__(self, "d_m", _vec3("d_m", self.d_m))

    def on_slab(self, xy: Any) -> np.ndarray:
        """(M,) bool: points on the moving side of the scarp."""
        p0, _, v = _trace("scarp_xy", self.scarp_xy)
        return (_xy_of(xy) - p0) @ v > 0.0

    def __call__(self, xy: Any) -> np.ndarray:
        """(M, 3) displacement (metres) at (M, 2) points."""
        return self.on_slab(xy)[:, None] * np.asarray(self.d_m)[None, :]

    @property
    def breaklines(self) -> tuple[np.ndarray, ...]:
        """The scarp trace, one (2, 2) polyline (metres)."""
        return (np.asarray(self.scarp_xy, dtype=np.float64),)


@dataclass(frozen=True)
class SlumpField:
    """A rotational slump: a block rotating rigidly about a horizontal axis behind its head
    scarp.

    Local frame: ``n = (sin a, cos a)`` the downslope azimuth ``a`` (clockwise from north),
    ``w = (cos a, -sin a)`` the axis (strike) direction, ``s = (p - c) . n`` and
    ``t = (p - c) . w`` the offsets of a point from the axis point ``c = axis_xy``. The ground
    is the reference slope ``h(s) = -H - s tan(beta)`` below the axis (``H = axis_height_m``,
    ``beta = slope_deg``), so the field depends on map position alone (as the lobe's does; the
    real relief would add about ``theta * dz``). With ``ground`` the block rotates rigidly
    over the real relief instead: the axis lies ``H`` above ``ground(axis_xy)`` and ``h`` is a
    point's own height above the axis (its ``z`` when the points have three columns, else
    ``ground(xy)``), so every point of the block moves by one rotation. Inside the block
    (``-head_m <= s <= toe_m``, ``|t| <= width_m / 2``) a rotation by ``theta =
    rotation_deg`` that moves the material below the axis downslope,

        s' = s cos(theta) - h sin(theta),      h' = s sin(theta) + h cos(theta),
        d = (s' - s) n + (h' - h) z,

    so the head (``s < 0``) drops and moves out little, the toe (``s > 0``) rises and moves
    out more: horizontal and vertical motion vary linearly with the distance from the axis.
    Outside the block ``d = 0``. The field jumps on the block's outline: the head scarp
    (``s = -head_m``), the flanks and the toe.

    Attributes
    ----------
    axis_xy : tuple of float
        (2,) map position of the axis (metres).
    azimuth_deg : float
        Downslope direction, degrees clockwise from north.
    head_m, toe_m : float
        Distance from the axis to the head scarp (upslope) and to the toe (downslope), m.
    width_m : float
        Width of the block along the axis (metres).
    axis_height_m : float
        Height ``H`` of the axis above the ground at ``s = 0`` (metres).
    slope_deg : float
        Ground slope ``beta`` (degrees; the ground descends downslope).
    rotation_deg : float
        Rotation ``theta`` (degrees; positive: head down, toe out and up).
    ground : callable, optional
        ``ground(xy (M, 2)) -> (M,)`` height of the ground before the slide (metres). None
        (the default): the reference slope, the field a function of map position.
    """

    axis_xy: tuple[float, float]
    azimuth_deg: float = 180.0
    head_m: float = 9.0
    toe_m: float = 9.0
    width_m: float = 18.0
    axis_height_m: float = 8.0
    slope_deg: float = 20.0
    rotation_deg: float = 3.0
    ground: Optional[Any] = None

    def __post_init__(self) -> None:
        if self.ground is not None and not callable(self.ground):
            raise InvalidParameterError("ground must be a callable ground(xy) -> heights (m).")
        c = _xy_of(self.axis_xy)
        if c.shape != (1, 2) or not np.all(np.isfinite(c)):
            raise InvalidParameterError(f"axis_xy must be (x, y) in metres, got {self.axis_xy!r}.")
        object.__setattr__(self, "axis_xy", (float(c[0, 0]), float(c[0, 1])))
        for name in ("head_m", "toe_m", "width_m", "axis_height_m"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise InvalidParameterError(f"{name} must be a finite length > 0 (m), got {v!r}.")
            object.__setattr__(self, name, v)
        for name in ("azimuth_deg", "slope_deg", "rotation_deg"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise InvalidParameterError(f"{name} must be finite, got {v!r}.")
            object.__setattr__(self, name, v)

    def _axes(self) -> tuple[np.ndarray, np.ndarray]:
        a = math.radians(self.azimuth_deg)
        return np.array([math.sin(a), math.cos(a)]), np.array([math.cos(a), -math.sin(a)])

    def _local(self, xy: Any) -> tuple[np.ndarray, np.ndarray]:
        off = _xy_of(xy) - np.asarray(self.axis_xy)
        n, w = self._axes()
        return off @ n, off @ w

    def in_block(self, xy: Any) -> np.ndarray:
        """(M,) bool: points in the rotating block."""
        s, t = self._local(xy)
        return (s >= -self.head_m) & (s <= self.toe_m) & (np.abs(t) <= 0.5 * self.width_m)

    def _height(self, xy: Any, s: np.ndarray) -> np.ndarray:
        """(M,) height of the points above the axis (metres, negative below it)."""
        if self.ground is None:
            return -self.axis_height_m - s * math.tan(math.radians(self.slope_deg))
        axis_z = float(np.ravel(self.ground(np.array([self.axis_xy])))[0]) + self.axis_height_m
        pts = np.asarray(xy, dtype=np.float64)
        if pts.ndim == 2 and pts.shape[1] >= 3:
            z = pts[:, 2]
        else:
            z = np.asarray(self.ground(_xy_of(xy)), dtype=np.float64).reshape(-1)
        return z - axis_z

    def __call__(self, xy: Any) -> np.ndarray:
        """(M, 3) displacement (metres) at (M, 2) points, or (M, 3) points when ``ground``
        is given (each point then rotates by its own height)."""
        s, t = self._local(xy)
        inside = (s >= -self.head_m) & (s <= self.toe_m) & (np.abs(t) <= 0.5 * self.width_m)
        th = math.radians(self.rotation_deg)
        h = self._height(xy, s)
        ds = s * (math.cos(th) - 1.0) - h * math.sin(th)
        dh = s * math.sin(th) + h * (math.cos(th) - 1.0)
        n, _ = self._axes()
        out = np.column_stack([ds * n[0], ds * n[1], dh])
        return np.where(inside[:, None], out, 0.0)

    @property
    def breaklines(self) -> tuple[np.ndarray, ...]:
        """The block's outline (head scarp, flank, toe, flank), one closed (5, 2) polyline."""
        n, w = self._axes()
        c, hw = np.asarray(self.axis_xy), 0.5 * self.width_m
        ring = [c - self.head_m * n - hw * w, c - self.head_m * n + hw * w]
        ring += [c + self.toe_m * n + hw * w, c + self.toe_m * n - hw * w]
        return (np.array(ring + [ring[0]]),)


@dataclass(frozen=True)
class FaultField:
    """A smooth field crossed by a fault: a strike-slip offset (and a small throw) added to a
    smooth ``base`` field.

    With the trace from ``p0`` to ``p1`` (unit direction ``u``, left normal ``v``) and
    ``side(p) = +1`` left of it (``(p - p0) . v > 0``), ``-1`` otherwise,

        d(p) = base(p) + side(p) * (slip_m / 2 * u + throw_m / 2 * z),

    so the left side moves ``slip_m`` along ``u`` (and ``throw_m`` up) relative to the right
    side: a left-lateral offset of ``slip_m`` (right-lateral for ``slip_m < 0``). The motion is
    parallel to the trace, so the sides neither open nor overlap.

    Attributes
    ----------
    trace_xy : tuple
        ((x0, y0), (x1, y1)) two points of the fault trace (metres).
    slip_m : float
        Offset along the trace, left side relative to right (metres).
    throw_m : float
        Vertical offset, left side relative to right (metres).
    base : callable, optional
        ``base(xy) -> (M, 3)`` smooth field (metres), e.g. a :class:`LobeField`; none: 0.
    """

    trace_xy: tuple
    slip_m: float = 0.3
    throw_m: float = 0.0
    base: Any = None

    def __post_init__(self) -> None:
        _trace("trace_xy", self.trace_xy)
        t = np.asarray(self.trace_xy, dtype=np.float64)
        object.__setattr__(self, "trace_xy", tuple(tuple(float(v) for v in r) for r in t))
        for name in ("slip_m", "throw_m"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise InvalidParameterError(f"{name} must be finite (m), got {v!r}.")
            object.__setattr__(self, name, v)
        if self.base is not None and not callable(self.base):
            raise InvalidParameterError("base must be a field: xy (M, 2) -> (M, 3) metres.")

    def side(self, xy: Any) -> np.ndarray:
        """(M,) +1 left of the trace, -1 on it or right of it."""
        p0, _, v = _trace("trace_xy", self.trace_xy)
        return np.where((_xy_of(xy) - p0) @ v > 0.0, 1.0, -1.0)

    def __call__(self, xy: Any) -> np.ndarray:
        """(M, 3) displacement (metres) at (M, 2) points."""
        p = _xy_of(xy)
        _, u, _ = _trace("trace_xy", self.trace_xy)
        step = np.array([0.5 * self.slip_m * u[0], 0.5 * self.slip_m * u[1], 0.5 * self.throw_m])
        out = self.side(p)[:, None] * step[None, :]
        if self.base is not None:
            out = out + np.asarray(self.base(p), dtype=np.float64)
        return out

    @property
    def breaklines(self) -> tuple[np.ndarray, ...]:
        """The fault trace, one (2, 2) polyline (metres)."""
        return (np.asarray(self.trace_xy, dtype=np.float64),)


@dataclass(frozen=True)
class SumField:
    """The sum of fields (e.g. a lobe beside a slab); breaklines of all parts.

    Attributes
    ----------
    parts : tuple of callable
        Fields ``f(xy) -> (M, 3)`` (metres).
    """

    parts: tuple

    def __call__(self, xy: Any) -> np.ndarray:
        """(M, 3) displacement (metres) at (M, 2) points."""
        p = _xy_of(xy)
        out = np.zeros((len(p), 3))
        for f in self.parts:  # the points as given: a part may use their height
            out += np.asarray(f(xy), dtype=np.float64)
        return out

    @property
    def breaklines(self) -> tuple[np.ndarray, ...]:
        return tuple(b for f in self.parts for b in field_breaklines(f))


def field_breaklines(field: Any) -> tuple[np.ndarray, ...]:
    """The discontinuity lines of a synthetic field (its ``breaklines``; none for a smooth
    field such as :class:`LobeField`), each an (M, 2) polyline in metres."""
    return tuple(np.asarray(b, dtype=np.float64) for b in getattr(field, "breaklines", ()))


def material_motion(
    field: Any, centres_xy: Any, *, iterations: int = 60, tol_m: float = 1e-6
) -> np.ndarray:
    """The motion of the material now (after epoch) at each centre: ``field(p0)`` with
    ``p0 + field(p0)[:2] = c`` (in 3-D, ``p0 + field(p0) = c``, for (M, 3) centres: a field
    that depends on height, such as :class:`SlumpField` with ``ground``).

    A windowed-ICP cell reports the motion of the ground now at its centre, so the truth at
    a centre ``c`` is the field at the material's original place ``p0``, found by the
    fixed-point iteration ``p0 <- c - field(p0)[:2]`` from ``p0 = c`` (a contraction where
    the field's horizontal gradient is below 1). Where it does not settle to ``tol_m`` -- a
    gap a slab or slump opened, where no material of the after epoch lies -- the truth is
    NaN.

    Parameters
    ----------
    field : callable
        ``field(xy) -> (M, 3)`` displacement (metres).
    centres_xy : (M, 2) or (M, 3) array-like
        Centres (metres, after epoch); with three columns ``p0`` is found in 3-D.
    iterations : int
        Most fixed-point steps.
    tol_m : float
        Largest ``|p0 + field(p0) - c|`` accepted (metres).

    Returns
    -------
    numpy.ndarray
        (M, 3) motion (metres), NaN rows where no material is found.
    """
    raw = np.asarray(centres_xy, dtype=np.float64)
    dim = 3 if raw.ndim == 2 and raw.shape[1] >= 3 else 2
    c = raw[:, :3].copy() if dim == 3 else _xy_of(centres_xy).copy()
    p0 = c.copy()
    for _ in range(int(iterations)):
        p0 = c - np.asarray(field(p0), dtype=np.float64)[:, :dim]
    d = np.asarray(field(p0), dtype=np.float64)
    miss = np.linalg.norm(p0 + d[:, :dim] - c, axis=1) > float(tol_m)
    d[miss] = np.nan
    return d


@dataclass(frozen=True)
class AlsSampling:
    """An airborne-like resampling of a dense cloud: parallel flight strips of zig-zag scan
    lines.

    Each strip is flown along ``heading_deg`` (clockwise from north); its scan lines run
    across the track every ``line_spacing_m`` along it, with a footprint every
    ``point_spacing_m`` across. An oscillating mirror slants successive lines alternately by
    half a line spacing from one strip edge to the other (a zig-zag: footprints bunch at the
    edges of the swath). The strips cover the cloud side by side, neighbours overlapping by
    ``overlap`` of a strip's width (the overlaps get twice the density). Each footprint is
    jittered by ``jitter_m`` (Gaussian, per axis) and takes the cloud's nearest point within
    half the smaller spacing (none: no return, e.g. a scan shadow). Nominal density of one
    strip: ``1 / (line_spacing_m * point_spacing_m)`` (5 pts/m² with the defaults, 10 in
    overlaps). Each epoch is flown with its own line phase and a heading off by a few degrees
    (``heading_spread_deg``), as two surveys are.

    Attributes
    ----------
    heading_deg, heading_spread_deg : float
        Flight direction and the standard deviation of its change per epoch (degrees).
    line_spacing_m, point_spacing_m : float
        Spacing of scan lines along the track, of footprints along a line (metres).
    strips : int
        Number of strips across the cloud.
    overlap : float
        Overlap of neighbouring strips, fraction of a strip's width in [0, 0.9].
    jitter_m : float
        Footprint position jitter (metres).
    noise_m : float
        Gaussian vertical noise added to the kept points (metres), ALS ranging noise.
    """

    heading_deg: float = 20.0
    heading_spread_deg: float = 3.0
    line_spacing_m: float = 0.5
    point_spacing_m: float = 0.4
    strips: int = 2
    overlap: float = 0.3
    jitter_m: float = 0.05
    noise_m: float = 0.02

    def __post_init__(self) -> None:
        for name in ("line_spacing_m", "point_spacing_m"):
            if not float(getattr(self, name)) > 0:
                raise InvalidParameterError(f"{name} must be > 0 (m).")
        if int(self.strips) < 1 or not (0.0 <= float(self.overlap) <= 0.9):
            raise InvalidParameterError("strips must be >= 1 and overlap in [0, 0.9].")

    def sample(self, xy: Any, rng: np.random.Generator) -> np.ndarray:
        """Sorted indices (K,) of the points of (N, 2+) ``xy`` the survey returns."""
        from scipy.spatial import cKDTree

        p = _xy_of(xy)
        if not len(p):
            return np.zeros(0, dtype=np.int64)
        h = math.radians(self.heading_deg + self.heading_spread_deg * rng.standard_normal())
        along = np.array([math.sin(h), math.cos(h)])
        across = np.array([math.cos(h), -math.sin(h)])
        centre = p.mean(axis=0)
        a, c = (p - centre) @ along, (p - centre) @ across
        ls, ps = float(self.line_spacing_m), float(self.point_spacing_m)
        k = int(self.strips)
        width = (c.max() - c.min()) / (k - (k - 1) * float(self.overlap))
        foot = []
        for strip in range(k):
            c0 = c.min() + strip * width * (1.0 - float(self.overlap))
            lines = np.arange(a.min() + ls * rng.random(), a.max() + ls, ls)
            across_c = c0 + ps * (np.arange(int(np.ceil(width / ps))) + 0.5)
            frac = (across_c - c0) / width - 0.5  # -0.5 .. 0.5 across the swath
            sign = np.where(np.arange(len(lines)) % 2 == 0, 1.0, -1.0)
            ua = lines[:, None] + 0.5 * ls * sign[:, None] * frac[None, :]
            uc = np.broadcast_to(across_c[None, :], ua.shape)
            foot.append(np.column_stack([ua.ravel(), uc.ravel()]))
        f = np.concatenate(foot)
        f = f + float(self.jitter_m) * rng.standard_normal(f.shape)
        fxy = centre + f[:, :1] * along + f[:, 1:] * across
        dist, idx = cKDTree(p).query(fxy, distance_upper_bound=0.5 * min(ls, ps))
        return np.unique(idx[np.isfinite(dist)]).astype(np.int64)


@dataclass(frozen=True, eq=False)
class LandslidePair:
    """Two epochs of a real cloud with a synthetic landslide field in the second.

    Attributes
    ----------
    before, after : numpy.ndarray
        (N1, 3), (N2, 3) float64 points; ``after = points[after_index] + after_truth``
        (plus the ALS noise when resampled so).
    field : callable
        The field applied, ``field(xy) -> (M, 3)`` metres (:func:`material_motion` gives
        the truth at cell centres).
    after_truth : numpy.ndarray
        (N2, 3) motion applied to each after point (metres).
    breaklines : tuple of numpy.ndarray
        The field's discontinuity lines, each (M, 2) (metres); empty for a smooth field.
    before_index, after_index : numpy.ndarray
        Indices into the input points (disjoint, increasing).
    """

    before: np.ndarray
    after: np.ndarray
    field: Any
    after_truth: np.ndarray
    breaklines: tuple
    before_index: np.ndarray
    after_index: np.ndarray


def make_landslide_pair(
    points: Any,
    field: Any,
    *,
    seed: int = 0,
    after_fraction: float = 0.5,
    als: Optional[AlsSampling] = None,
) -> LandslidePair:
    """Two epochs of a real cloud, the second moved by a landslide ``field``.

    As :func:`make_lobe_pair`: the cloud is split at random (seeded) into two disjoint sets,
    the before epoch and the after epoch, each after point moved by ``field`` at its original
    place. With ``als``, each epoch is then resampled as an airborne survey would see it
    (:class:`AlsSampling`; the after epoch in its moved position) and ALS noise is added.

    Parameters
    ----------
    points : (N, 3) array-like
        The cloud (metres); not modified.
    field : callable
        ``field(points) -> (M, 3)`` displacement (metres) at the after points' original
        places, given as (M, 3) x, y, z (the fields of map position read x, y only):
        :class:`LobeField`, :class:`SlabField`, :class:`SlumpField`, :class:`FaultField`,
        :class:`SumField`...
    seed : int
        Seed of the split and the resampling.
    after_fraction : float
        Share of the points in the after epoch, in (0, 1).
    als : AlsSampling, optional
        Resample both epochs ALS-like (default: the halves at the cloud's density).

    Returns
    -------
    LandslidePair
    """
    from .errors import InputDataError

    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.all(np.isfinite(pts)):
        raise InputDataError("points must be an (N, 3) array of finite x, y, z, N >= 2.")
    frac = float(after_fraction)
    if not (0.0 < frac < 1.0):
        raise InvalidParameterError(f"after_fraction must be in (0, 1), got {after_fraction!r}.")
    rng = np.random.default_rng(
        np.random.SeedSequence(int(seed), spawn_key=(_KEY_LANDSLIDE_SPLIT,))
    )
    order = rng.permutation(len(pts))
    n_after = min(len(pts) - 1, max(1, int(round(frac * len(pts)))))
    after_index = np.sort(order[:n_after]).astype(np.int64)
    before_index = np.sort(order[n_after:]).astype(np.int64)
    disp = np.asarray(field(pts[after_index]), dtype=np.float64)  # x, y, z: a field may use z
    after = pts[after_index] + disp
    before = pts[before_index].copy()
    if als is not None:
        rb, ra = (
            np.random.default_rng(s)
            for s in np.random.SeedSequence(int(seed), spawn_key=(_KEY_ALS,)).spawn(2)
        )
        kb, ka = als.sample(before, rb), als.sample(after, ra)
        before_index, before = before_index[kb], before[kb]
        after_index, after, disp = after_index[ka], after[ka], disp[ka]
        before[:, 2] += float(als.noise_m) * rb.standard_normal(len(before))
        after[:, 2] += float(als.noise_m) * ra.standard_normal(len(after))
    return LandslidePair(
        before=before,
        after=after,
        field=field,
        after_truth=disp,
        breaklines=field_breaklines(field),
        before_index=before_index,
        after_index=after_index,
    )
