"""Stochastic-model options of the slip → core keywords, for the adapters (CLI, PDAL, QGIS).

One vocabulary for the three faces (as :mod:`.pointaccuracy` is for the point accuracy):

=====================  ==========================================================
option                 meaning
=====================  ==========================================================
stochastic model       white | plane | full (:data:`MODELS`, help in :data:`MODEL_HELP`)
acquisition units      auto | PointSourceId | GpsTime | none (:data:`UNIT_SOURCES`): the
                       unit of each point for the "full" model's rigid error per unit
GPS gap                seconds: GpsTime segments are split where consecutive (sorted)
                       times jump by more than this (separate passes / scans)
fixed components       ``name=sigma_m`` for ``plane``, ``spatial``, ``unit_before``,
                       ``unit_after`` (σ in metres) and ``spatial_range_m`` (metres), held
                       fixed instead of estimated (:func:`parse_fixed_components`)
=====================  ==========================================================

The science (REML, robust tests) is :mod:`.core.stochastic`; nothing here imports scipy, so the
faces can build their parameters without it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Sequence, Union

import numpy as np

from ..core.errors import InputDataError, InvalidParameterError

log = logging.getLogger("slipmap.stochastic")

#: the models, as :data:`slipmap.core.stochastic.STOCHASTIC_MODELS` (a test checks they agree)
MODELS = ("white", "plane", "full")
DEFAULT_MODEL = "full"
MODEL_HELP = {
    "white": "independent point errors only (the study's model): the σ shrinks as "
    "1/√points and ignores errors shared by a plane's points, so it is too small for real "
    "surveys",
    "plane": "white noise plus one random offset per plane (errors common to a plane's "
    "points: trajectory error over it, a surface that is not quite flat)",
    "full": "plane plus spatially correlated plane offsets and a rigid error per acquisition "
    "unit (ALS strip, MLS pass, TLS setup; see the units option); components estimated by "
    "REML (default)",
}
#: plane-level components that can be held fixed (σ in metres) and the spatial range (metres),
#: as :data:`slipmap.core.stochastic.COMPONENT_NAMES` + ``spatial_range_m``
COMPONENTS = ("plane", "spatial", "unit_before", "unit_after", "spatial_range_m")
#: where the acquisition unit of each point comes from
UNIT_SOURCES = ("auto", "PointSourceId", "GpsTime", "none")
UNITS_HELP = (
    "acquisition unit of each point, for the full model's rigid error per unit: auto = "
    "PointSourceId when an epoch has more than one distinct value, else none; PointSourceId "
    "(ALS strips, MLS passes); GpsTime = segments of the sorted GPS times split at jumps "
    "larger than the GPS gap (separate passes or scans); none. Before and after are read "
    "separately"
)
DEFAULT_GPS_GAP_S = 1.0
#: more units than this in one epoch is suspicious (a GPS gap below the scan's own gaps)
MANY_UNITS = 1000


# --------------------------------------------------------------------------- fixed components


def _component_value(name: str, text: Any) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number (metres), got {text!r}") from None
    if not math.isfinite(v) or v < 0 or (name == "spatial_range_m" and v <= 0):
        bound = "> 0" if name == "spatial_range_m" else ">= 0"
        raise ValueError(f"{name} must be a finite number {bound} (metres), got {text!r}")
    return v


def _items(value: Any):
    """(name, value) pairs of a mapping, a "name=value,…" text or a sequence of such texts."""
    if isinstance(value, Mapping):
        return [(str(k).strip(), v) for k, v in value.items()]
    texts = [value] if isinstance(value, str) else list(value)
    pairs = []
    for text in texts:
        if not isinstance(text, str):
            raise ValueError(f"expected NAME=SIGMA_M, got {text!r}")
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            name, sep, num = part.partition("=")
            if not sep or not name.strip() or not num.strip():
                raise ValueError(f"expected NAME=SIGMA_M (e.g. plane=0.002), got {part!r}")
            pairs.append((name.strip(), num.strip()))
    return pairs


def fixed_components_or_error(value: Any) -> Dict[str, float]:
    """:func:`parse_fixed_components` raising a bare ``ValueError`` (for argparse types)."""
    out: Dict[str, float] = {}
    for name, num in _items(value):
        if name not in COMPONENTS:
            raise ValueError(f"unknown component {name!r}; use {', '.join(COMPONENTS)}")
        if name in out:
            raise ValueError(f"{name} is given twice")
        out[name] = _component_value(name, num)
    return out


def parse_fixed_components(
    value: Union[None, str, Mapping[str, Any], Sequence[str]], *, option: str
) -> Dict[str, float]:
    """Fixed plane-level components ``{name: metres}`` from a mapping, a ``"name=value,…"``
    text, or a sequence of such texts (e.g. a repeated command-line option).

    ``None`` or an empty text gives ``{}``. Names are :data:`COMPONENTS`; σ values must be
    finite and >= 0, ``spatial_range_m`` > 0. Errors are :class:`InvalidParameterError`
    messages starting with ``option`` (the name of the option as the user's face spells it).
    """
    if value is None or (isinstance(value, str) and not value.strip()):
        return {}
    try:
        return fixed_components_or_error(value)
    except ValueError as exc:
        raise InvalidParameterError(f"{option}: {exc}") from None


# --------------------------------------------------------------------------- units


@dataclass(frozen=True)
class EpochUnits:
    """The acquisition units of one epoch's selected points.

    Attributes
    ----------
    units : (N,) int or None
        Unit id of each point (None: no units).
    source : str
        "PointSourceId", "GpsTime" or "none".
    n_units : int
        Distinct units (0 for none).
    note : str
        Why (e.g. "auto: PointSourceId has a single value").
    time_s : (N,) float64 or None
        GpsTime of each point (seconds), for a unit error that drifts along time
        (:mod:`slipmap.core.unit_drift`; the ``unit_drift`` option); None: rigid units.
    """

    units: Optional[np.ndarray]
    source: str
    n_units: int
    note: str = ""
    time_s: Optional[np.ndarray] = None

    def to_dict(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {"source": self.source, "n_units": int(self.n_units)}
        if self.note:
            out["note"] = self.note
        if self.units is not None:
            out["gps_time"] = self.time_s is not None
        return out


def gps_time_segments(gps_time: Any, gap_s: float = DEFAULT_GPS_GAP_S) -> np.ndarray:
    """(N,) int64 segment of each point: the sorted GPS times are split where consecutive
    times jump by more than ``gap_s`` seconds; segments are numbered from 0 in time order.

    Raises :class:`InvalidParameterError` for a gap that is not > 0 and
    :class:`InputDataError` for non-finite times.
    """
    gap = float(gap_s)
    if not (math.isfinite(gap) and gap > 0):
        raise InvalidParameterError(f"the GPS gap must be > 0 seconds, got {gap_s!r}")
    t = np.asarray(gps_time, dtype=np.float64).ravel()
    if t.size == 0:
        return np.zeros(0, dtype=np.int64)
    if not np.all(np.isfinite(t)):
        raise InputDataError("GpsTime holds NaN or infinite values")
    s = np.sort(t)
    starts = s[1:][np.diff(s) > gap]  # first time of every segment but the first
    return np.searchsorted(starts, t, side="right").astype(np.int64)


def epoch_units(
    how: str,
    *,
    point_source_id: Any = None,
    gps_time: Any = None,
    gap_s: float = DEFAULT_GPS_GAP_S,
    epoch: str = "epoch",
    option: str = "units",
    spelling: Optional[Mapping[str, str]] = None,
) -> EpochUnits:
    """The acquisition units of one epoch from its (selected points') dimensions.

    Parameters
    ----------
    how : str
        One of :data:`UNIT_SOURCES`.
    point_source_id, gps_time : (N,) array or None
        The epoch's dimensions for the points that enter the adjustment; None when the
        file or view has no such dimension.
    gap_s : float
        GPS gap for ``how="GpsTime"`` (seconds).
    epoch : str
        The epoch as messages name it (e.g. "before epoch (a.laz)").
    option, spelling
        The option's name and its values as the user's face spells them (e.g. "--units",
        ``{"GpsTime": "gps-time"}``), for messages.

    Raises
    ------
    InvalidParameterError
        An explicit source whose dimension the epoch lacks (the message names ``option``).
    """
    spell = dict(spelling or {})
    name = lambda src: spell.get(src, src)  # noqa: E731
    if how not in UNIT_SOURCES:
        raise InvalidParameterError(
            f"{option} must be one of {', '.join(name(s) for s in UNIT_SOURCES)}; got {how!r}"
        )
    if how == "none":
        return EpochUnits(None, "none", 0, "no units asked for")
    others = ", ".join(name(s) for s in UNIT_SOURCES if s != how)
    if how == "auto":
        if point_source_id is None:
            return EpochUnits(None, "none", 0, "auto: no PointSourceId dimension")
        ids = np.asarray(point_source_id)
        n = int(np.unique(ids).size)
        if n <= 1:
            return EpochUnits(None, "none", 0, "auto: PointSourceId has a single value")
        return EpochUnits(ids, "PointSourceId", n, "auto")
    dim, values = (
        ("PointSourceId", point_source_id) if how == "PointSourceId" else ("GpsTime", gps_time)
    )
    if values is None:
        why = " (LAS point formats 0 and 2 have none)" if dim == "GpsTime" else ""
        raise InvalidParameterError(
            f"{option} {name(how)}: the {epoch} has no {dim} dimension{why}; use {option} {others}"
        )
    if dim == "PointSourceId":
        units = np.asarray(values)
        if not np.issubdtype(units.dtype, np.integer):
            if not np.all(np.isfinite(units)) or np.any(units != np.round(units)):
                raise InvalidParameterError(
                    f"{option} {name(how)}: the {epoch}'s PointSourceId holds non-integer values"
                )
            units = units.astype(np.int64)
    else:
        try:
            units = gps_time_segments(values, gap_s)
        except InputDataError as exc:
            raise InputDataError(f"{option} {name(how)}: the {epoch}'s {exc}") from None
    n = int(np.unique(units).size)
    note = ""
    if n <= 1:
        note = "a single unit: its rigid error cannot be told from the motion (not estimable)"
        from .options import in_face_words

        log.warning("%s: %s %s gives %s", epoch, in_face_words(option), name(how), note)
    elif n > MANY_UNITS:
        log.warning(
            "%s: %d acquisition units from %s; is the GPS gap (%g s) below the gaps within "
            "one pass?",
            epoch,
            n,
            dim,
            gap_s,
        )
    return EpochUnits(units, dim, n, note)


def log_units(epoch: str, units: EpochUnits) -> None:
    if units.units is None:
        log.info("%s: no acquisition units (%s)", epoch, units.note)
    else:
        log.info("%s: %d acquisition unit(s) from %s", epoch, units.n_units, units.source)


# --------------------------------------------------------------------------- job options

GROUP = "stochastic model (the slip's σ; variance components estimated by REML)"
#: how the CLI spells the unit sources (its historical flags); every face accepts any spelling
CLI_UNITS = "{auto,point-source-id,gps-time,none}"


def stochastic_options(*, group: str = GROUP) -> tuple:
    """The stochastic-model options of the slip job, declared once for every face."""
    from .options import Option

    return (
        Option(
            "stochastic_model",
            "choice",
            "; ".join(f"{m}: {MODEL_HELP[m]}" for m in MODELS),
            label="Stochastic model",
            default=DEFAULT_MODEL,
            choices=MODELS,
            group=group,
        ),
        Option(
            "units",
            "choice",
            UNITS_HELP,
            label="Acquisition units",
            default="auto",
            choices=UNIT_SOURCES,
            group=group,
            metavar=CLI_UNITS,
        ),
        Option(
            "gps_gap_s",
            "float",
            "with GpsTime units: a new unit starts where consecutive GPS times jump by more "
            f"than this, seconds (default {DEFAULT_GPS_GAP_S:g})",
            label="GPS gap between acquisition units (s)",
            default=DEFAULT_GPS_GAP_S,
            minimum=0,
            exclusive=True,
            group=group,
            advanced=True,
            metavar="S",
        ),
        Option(
            "unit_drift",
            "bool",
            "each acquisition unit's error may drift along the points' GpsTime (a mobile "
            "mapper's trajectory error over tens of seconds: one pass crossing the fault errs "
            "differently on each side) instead of one rigid error per unit; the knot spacing "
            "(3-24 s) or none is chosen by restricted likelihood per side and for both sides "
            "together; needs GpsTime and units (full model); tiled inputs keep rigid units",
            label="Unit errors drift along GpsTime",
            default=True,
            group=group,
            advanced=True,
        ),
        Option(
            "unit_contrasts",
            "bool",
            "planes seen by two acquisition units in one epoch (where two ALS strips overlap, a "
            "wall seen from two streets) tie those units: their offset there identifies the unit "
            "components, and each side's motion takes the units' errors it predicts off, over "
            "every plane found on both sides (a strip adjustment inside the slip's; "
            'docs/accuracy.md, "Units tied on the planes they share"); full model with units; '
            "tiled inputs have none",
            label="Tie units on the planes they share",
            default=True,
            group=group,
            advanced=True,
        ),
        Option(
            "random_tilt",
            "bool",
            "each plane is also tilted by the survey error (a random tilt per plane, its "
            "variance estimated per side), so the planes' tilts pin the rotation only as far as "
            "the survey allows: more accurate on airborne, mixed mobile/airborne and "
            'short-wavelength drift pairs (docs/accuracy.md, "Acquisition units that drift '
            'along GpsTime"); plane and full models only (the white model ignores it)',
            label="Random tilt per plane",
            default=True,
            group=group,
            advanced=True,
        ),
        Option(
            "fixed_components",
            "keyvalues",
            "plane-level components held fixed instead of estimated, NAME=SIGMA_M: plane, "
            "spatial, unit_before, unit_after (σ in metres) or spatial_range_m (metres), e.g. "
            "plane=0.002,unit_after=0.003",
            label="Fixed components (name=sigma_m, …)",
            group=group,
            advanced=True,
            cli="--fixed-component",
            qgis="FIXED_COMPONENTS",
            metavar="NAME=SIGMA_M",
            unset_text="none",
        ),
    )


def random_tilt_of(opts: Mapping[str, Any]) -> bool:
    """The ``random_tilt`` option as the core takes it: the white model has no plane level to
    tilt, so it ignores the option (on by default)."""
    return bool(opts.get("random_tilt", True)) and opts.get("stochastic_model") != "white"


def check_stochastic(opts: Mapping[str, Any]) -> Dict[str, float]:
    """Cross-option check of :func:`stochastic_options`; returns the fixed components
    ``{name: metres}`` (empty when none).

    Raises
    ------
    OptionError
        Bad fixed components, or fixed components with the white model.
    """
    from .options import OptionError, warn_option

    value = opts.get("fixed_components")
    try:
        fixed = fixed_components_or_error(value) if value else {}
    except ValueError as exc:
        raise OptionError("fixed_components", str(exc)) from None
    units_fixed = [k for k in ("unit_before", "unit_after") if k in fixed]
    if units_fixed and opts.get("units") == "none":
        raise OptionError(
            "fixed_components",
            f"{' and '.join(units_fixed)} fixed, but {{units}} is none: there is no "
            "acquisition unit for it to act on; set {units} to auto, PointSourceId or GpsTime, "
            f"or leave {' and '.join(units_fixed)} out",
            also=("units",),
        )
    gap = opts.get("gps_gap_s")
    if gap is not None and gap != DEFAULT_GPS_GAP_S and opts.get("units") != "GpsTime":
        warn_option(
            "{gps_gap_s} is set but {units} is not GpsTime: the GPS gap is not used; set "
            "{units} to GpsTime to split the epochs at GPS time gaps"
        )
    if fixed and opts.get("stochastic_model") == "white":
        raise OptionError(
            "fixed_components",
            "the white model has no plane-level components; set {stochastic_model} to plane "
            "or full",
            also=("stochastic_model",),
        )
    return fixed


def units_for_job(opts: Mapping[str, Any], epochs: Mapping[str, Any]) -> tuple:
    """The acquisition units of each epoch for the slip job, and what was used (the JSON's
    ``acquisition_unit_sources``).

    Parameters
    ----------
    opts
        The job's options (``stochastic_model``, ``units``, ``gps_gap_s``).
    epochs
        ``{"before": (label, PointSourceId or None, GpsTime or None), "after": ...}``: the
        epoch as messages name it and its selected points' dimensions.

    Returns
    -------
    (dict, dict)
        ``{"before": EpochUnits, "after": EpochUnits}`` and the record.

    Raises
    ------
    OptionError
        An explicit source the epoch lacks, naming ``units`` and the epoch.
    """
    from .options import OptionError

    model, how = opts.get("stochastic_model", DEFAULT_MODEL), opts.get("units", "auto")
    record: Dict[str, Any] = {"units_option": how}
    out: Dict[str, EpochUnits] = {}
    if model != "full":
        if how not in ("auto", "none"):
            log.warning("the units option (%s) is not used by the %s model", how, model)
        for epoch in epochs:
            out[epoch] = EpochUnits(None, "none", 0, f"not used by the {model} model")
            record[epoch] = out[epoch].to_dict()
        return out, record
    if how == "GpsTime":
        record["gps_gap_s"] = opts.get("gps_gap_s", DEFAULT_GPS_GAP_S)
    record["unit_drift"] = bool(opts.get("unit_drift", True))
    record["unit_contrasts"] = bool(opts.get("unit_contrasts", True))
    for epoch, (label, psid, gps) in epochs.items():
        try:
            u = epoch_units(
                how,
                point_source_id=psid,
                gps_time=gps,
                gap_s=opts.get("gps_gap_s", DEFAULT_GPS_GAP_S),
                epoch=label,
                option="{units}",
            )
        except (InvalidParameterError, InputDataError) as exc:
            text = str(exc).removeprefix("{units} ")
            raise OptionError("units", text, also=("units",)) from None
        if opts.get("unit_drift", True) and u.units is not None and gps is not None:
            from dataclasses import replace

            u = replace(u, time_s=np.asarray(gps, dtype=np.float64))
        log_units(label, u)
        out[epoch] = u
        record[epoch] = u.to_dict()
    return out, record
