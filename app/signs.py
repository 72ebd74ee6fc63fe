"""The one sign convention of the fault-slip job's outputs (docs/methods.md, "Sign convention").

Every along-strike number a person sees (JSON keys, GeoPackage fields, raster bands, legends,
plot axes, the report, console and log lines, PDAL metadata) is given in its *shear sense*,
whatever direction the trace was digitised in:

* relative motion (the right side of the digitised trace minus the left side):
  ``right_lateral = -fault_parallel`` (+ = dextral), ``opening = fault_normal`` (+ = the sides
  move apart), ``dz`` (+ = the right side up against the left);
* one side's motion (a side, a tile, a strip, a window): ``right_lateral = +fault_parallel``
  on the left side and ``-fault_parallel`` on the right side, ``opening = -fault_normal`` on
  the left side and ``+fault_normal`` on the right side (motion away from the trace = +),
  ``dz`` as measured (+ = up). Right-lateral shear reads + on both sides, and a left and a
  right value add up to the relative value.

``fault_parallel`` (along the digitised direction) and ``fault_normal`` (towards the right
side) stay inside :mod:`slipmap.core.displacement`; this module turns them into the names
above. Reversing the trace's digitised direction leaves every ``right_lateral`` and
``opening`` unchanged; the relative dx, dy, dz change sign (right minus left becomes the
other way round) and the outputs name the right side by its compass direction.
"""

from __future__ import annotations

import math
from typing import Any, Dict, Mapping, Optional

import numpy as np

#: the convention in one line (JSON ``fault.sign_convention``, legends, the report)
CONVENTION = (
    "+ right_lateral = right-lateral (dextral) shear; + opening = the sides move apart; "
    "dz + = up (relative: the right side up against the left)"
)
#: the keys of one motion in the convention (metres)
KEYS = ("right_lateral", "sigma_right_lateral", "opening", "sigma_opening", "dz", "sigma_dz")

_COMPASS = (
    "north",
    "north-east",
    "east",
    "south-east",
    "south",
    "south-west",
    "west",
    "north-west",
)


def side_factor(side: str) -> float:
    """+1 for the left side, -1 for the right side: a side's ``right_lateral`` is
    ``side_factor * fault_parallel`` and its ``opening`` is ``-side_factor * fault_normal``."""
    if side == "left":
        return 1.0
    if side == "right":
        return -1.0
    raise ValueError(f"side must be 'left' or 'right', not {side!r}")


def _axes(strike_rad: float):
    s, c = math.sin(strike_rad), math.cos(strike_rad)
    return np.array([s, c, 0.0]), np.array([c, -s, 0.0])


def _sigma(j: np.ndarray, cov: np.ndarray) -> float:
    var = float(j @ cov @ j)
    return math.sqrt(max(var, 0.0)) if math.isfinite(var) else math.nan


def motion(displacement, covariance, strike_rad: float, side: Optional[str]) -> Dict[str, float]:
    """One motion in the convention.

    Parameters
    ----------
    displacement : (3,) float64
        dx, dy, dz (east, north, up), metres: the relative motion (right minus left) when
        ``side`` is None, else the motion of one side's material (a side, tile, strip or
        window).
    covariance : (3, 3) float64
        Its covariance, m².
    strike_rad : float
        The trace's strike (clockwise from north, along the digitised direction), radians.
    side : {"left", "right"} or None
        None: the relative motion.

    Returns
    -------
    dict
        :data:`KEYS`, metres (NaN where the input is not finite).
    """
    d = np.asarray(displacement, dtype=np.float64).reshape(3)
    c = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
    jp, jn = _axes(strike_rad)
    f = -1.0 if side is None else side_factor(side)  # relative: like the right side
    return {
        "right_lateral": float(f * (jp @ d)),
        "sigma_right_lateral": _sigma(jp, c),
        "opening": float(-f * (jn @ d)),
        "sigma_opening": _sigma(jn, c),
        "dz": float(d[2]),
        "sigma_dz": float(math.sqrt(c[2, 2])) if c[2, 2] >= 0 else math.nan,
    }


def strip_motion(strip) -> Optional[Dict[str, float]]:
    """A :class:`~slipmap.core.displacement.StripResult`'s own motion (its ``displacement``
    and ``covariance``) in the convention (:func:`motion`); None when it was skipped."""
    c = np.asarray(strip.covariance, dtype=np.float64)
    if strip.status != "ok" or not np.all(np.isfinite(c)):
        return None
    return motion(strip.displacement, c, strip.strike_rad, strip.side)


def right_lateral_grid(dx, dy, strike_rad: float, side_grid) -> np.ndarray:
    """(ny, nx) right-lateral motion of one-side cells (moving windows), metres: ``dx``,
    ``dy`` are each cell's own motion, ``side_grid`` -1 left, +1 right, 0 on the trace (NaN)."""
    jp, _ = _axes(strike_rad)
    fp = jp[0] * np.asarray(dx, dtype=np.float64) + jp[1] * np.asarray(dy, dtype=np.float64)
    side = np.asarray(side_grid)
    factor = np.where(side < 0, 1.0, np.where(side > 0, -1.0, np.nan))
    return factor * fp


def sigma_along_grid(covariance, strike_rad: float) -> np.ndarray:
    """(ny, nx) 1σ of the along-strike motion from (ny, nx, 3, 3) covariances, metres."""
    jp, _ = _axes(strike_rad)
    c = np.asarray(covariance, dtype=np.float64)
    var = np.einsum("i,...ij,j->...", jp, c, jp)
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.where(var >= 0, var, np.nan))


def compass(azimuth_deg: float) -> str:
    """The 8-point compass name of an azimuth (degrees clockwise from north): ``east``."""
    return _COMPASS[int(math.floor(((azimuth_deg % 360.0) + 22.5) / 45.0)) % 8]


def side_names(strike_deg: Optional[float]) -> Dict[str, str]:
    """``{"left": "west", "right": "east"}`` for a trace of that strike (the right side lies
    90° clockwise from the digitised direction); ``{}`` when the strike is unknown."""
    if strike_deg is None or not math.isfinite(float(strike_deg)):
        return {}
    return {"left": compass(strike_deg - 90.0), "right": compass(strike_deg + 90.0)}


def side_label(side: str, names: Mapping[str, str]) -> str:
    """``right (east) side``, or ``right side`` without names."""
    name = names.get(side)
    return f"{side} ({name}) side" if name else f"{side} side"


def dz_meaning(names: Mapping[str, str]) -> str:
    """What + means for the relative dz: ``+ = east side up`` (``+ = right side up``)."""
    return f"+ = {names['right']} side up" if names.get("right") else "+ = right side up"


def relative(components: Mapping[str, Any]) -> Dict[str, Any]:
    """The relative motion of :meth:`SlipResult.components` in the convention: the keys a
    person reads (``right_lateral_slip`` kept beside ``right_lateral``; no
    ``fault_parallel`` / ``fault_normal``)."""
    c = dict(components)
    out: Dict[str, Any] = {
        "right_lateral_slip": -c["fault_parallel"],
        "right_lateral": -c["fault_parallel"],
        "sigma_right_lateral": c["sigma_fault_parallel"],
    }
    if "sigma_fault_parallel_white" in c:
        out["sigma_right_lateral_white"] = c["sigma_fault_parallel_white"]
    out.update(opening=c["fault_normal"], sigma_opening=c["sigma_fault_normal"])
    out.update(dz=c["dz"], sigma_dz=c["sigma_dz"])
    if "sigma_dz_white" in c:
        out["sigma_dz_white"] = c["sigma_dz_white"]
    for key in ("dx", "dy", "sigma_dx", "sigma_dy", "horizontal", "sigma_horizontal"):
        out[key] = c[key]
    return out


#: the fault-frame components of :mod:`slipmap.core.determination` by their names here
COMPONENT_NAMES = {"fault_parallel": "right_lateral", "fault_normal": "opening", "dz": "dz"}
_COMPONENT_WORDS = {
    "right_lateral": "right-lateral slip",
    "opening": "opening",
    "dz": "vertical motion (dz)",
}
_AXIS_WORDS = {
    "right_lateral": "the trace's strike",
    "opening": "the direction across the trace",
    "dz": "the vertical",
}


def weak_components(weak, names: Mapping[str, str]) -> list:
    """The weak components of :func:`slipmap.core.determination.weak_components` in the
    convention: one dict per component (``component`` by its name here, ``side`` and its
    label, σ in metres) with ``text``, the sentence the faces show beside the headline."""
    rows = []
    for w in weak:
        name = COMPONENT_NAMES[w.component]
        label = side_label(w.side, names)
        text = (
            f"the {_COMPONENT_WORDS[name]} is barely determined by the {label}'s planes: ± "
            f"{1e3 * w.sigma_m:.1f} mm there, {w.ratio:.0f}× its best direction's ± "
            f"{1e3 * w.best_sigma_m:.1f} mm: the normals of its {w.n_planes} adjusted planes "
            f"give {_AXIS_WORDS[name]} {100 * w.share:.1f} % of their weight (a set facing every "
            f"way gives 33 %); the relative {name}'s σ is what these data hold, and the other "
            "components keep their own σ"
        )
        rows.append(
            {
                "component": name,
                "side": w.side,
                "side_label": label,
                "sigma_m": w.sigma_m,
                "best_sigma_m": w.best_sigma_m,
                "share": w.share,
                "n_planes": w.n_planes,
                "text": text,
            }
        )
    return rows
