"""Output shaping shared by the adapters (CLI, QGIS, PDAL): JSON-safe values, statistics of
finite values, horizontal magnitude/azimuth, strip rows, the slip's stochastic-model summary
(console lines, report tables, per-plane fields). No science and no QGIS/PDAL here."""

from __future__ import annotations

import math
from typing import Any, Dict, Iterable, List, Optional, Tuple

import numpy as np


def finite(value) -> Optional[float]:
    """``float(value)``, or None when it is NaN or infinite (JSON has no NaN)."""
    v = float(value)
    return v if math.isfinite(v) else None


def json_safe(obj: Any) -> Any:
    """NaN/inf -> None, numpy scalars -> Python, recursively, so the JSON is standard."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return finite(obj)
    return obj


def json_text(payload: Any) -> str:
    """``payload`` as standard JSON text (NaN/inf as null, numpy values as Python), indented.

    The one JSON policy of every face and job."""
    import json

    return json.dumps(json_safe(payload), indent=2, allow_nan=False, default=_plain) + "\n"


def _plain(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    return str(obj)


def finite_stats(values) -> Dict[str, float]:
    """n, mean, median, std, min, max of the finite values (``{"n": 0}`` when none)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if not v.size:
        return {"n": 0}
    return {
        "n": int(v.size),
        "mean": float(v.mean()),
        "median": float(np.median(v)),
        "std": float(v.std()),
        "min": float(v.min()),
        "max": float(v.max()),
    }


def horizontal(dx, dy) -> Tuple[np.ndarray, np.ndarray]:
    """Horizontal magnitude (m) and azimuth (degrees clockwise from north, in [0, 360))."""
    dx, dy = np.asarray(dx, dtype=np.float64), np.asarray(dy, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.hypot(dx, dy), np.degrees(np.arctan2(dx, dy)) % 360.0


def strip_rows(strips: Iterable) -> List[Dict[str, Any]]:
    """One JSON row per :class:`~slipmap.core.displacement.StripResult`: the strip's own
    motion in the sign convention of :mod:`.signs` (``right_lateral`` + = dextral on either
    side, ``opening`` + = away from the trace, ``dz`` + = up; metres; null when skipped)."""
    from . import signs

    rows = []
    for st in strips:
        m = signs.strip_motion(st) or {}
        rows.append(
            {
                "side": st.side,
                "along_start_m": st.along_start_m,
                "along_end_m": st.along_end_m,
                "n_planes": int(st.n_planes),
                **{k: finite(m[k]) if m else None for k in signs.KEYS},
                "status": st.status,
            }
        )
    return rows


def icp_summary(res) -> Dict[str, Any]:
    """The JSON summary of a ``WindowedICPResult`` shared by the CLI (``icp.json``) and the
    QGIS algorithm: cell counts, motion and sigma statistics, the field's variance factor
    and the pre-alignment (NaN/inf are left to :func:`json_safe`)."""
    mag, _ = horizontal(res.dx, res.dy)
    pre = res.prealignment
    return {
        "cell_m": res.cell_m,
        # the cells' motion model, and whether the values come from one spline field
        "model": {
            "cell": res.cell_model,
            "field": res.field_model,
            "deform_passes": res.deform_passes,
            # spline field: cells that report their own rigid fit, which fits their points
            # better (core.icp_choice)
            "cells_from_own_fit": int(np.count_nonzero(res.from_cell))
            if res.from_cell is not None
            else 0,
        },
        "n_cells": len(res),
        "skipped": dict(res.skipped),
        "converged": int(np.count_nonzero(res.converged)),
        "horizontal_m": finite_stats(mag),
        "dz_m": finite_stats(res.dz),
        "sigma_horizontal_m": finite_stats(np.hypot(res.sigma_dx, res.sigma_dy)),
        "sigma_factor": {
            "applied": res.sigma_factor,
            "estimate": res.sigma_factor_estimate,
            "cells": res.sigma_factor_cells,
            # one factor per region with sigma_scaling="region" (lowest class first)
            "regions": [float(v) for v in res.sigma_region_factors],
        },
        # issue #29: the cells' covariances with the residuals' correlation (blocks) and
        # the cell-wide error from neighbour agreement (sigmas x sqrt(a + n / n_cap))
        "sigma_model": {
            "model": res.sigma_model,
            "block_m": res.sigma_block_m,
            "block_ratio": res.sigma_block_ratio,
            "floor_factor": res.sigma_floor_factor,
            "n_cap": res.sigma_n_cap,
        },
        "rmse_m": finite_stats(res.rmse),
        "prealignment": None
        if pre is None
        else {
            # T(p) = R (p - c) + c + t maps epoch 2 onto epoch 1: the epochs' offset at the
            # centre c is -t (a translation "about the origin" would be mostly lever arm)
            "centre_m": np.asarray(pre.centre).tolist(),
            "offset_at_centre_m": (-np.asarray(pre.params[3:])).tolist(),
            "rotation_rad": np.asarray(pre.params[:3]).tolist(),
            "rmse_m": float(pre.rmse_m),
        },
        "seconds": res.seconds,
    }


# --------------------------------------------------------------------------- slip: stochastic model


def _mm(value) -> Optional[float]:
    """metres -> millimetres (None stays None; NaN/inf -> None)."""
    if value is None:
        return None
    v = float(value)
    return 1000.0 * v if math.isfinite(v) else None


def _fmt_mm(value, digits: int = 2) -> str:
    v = _mm(value)
    return "n/a" if v is None else f"{v:.{digits}f}"


def slip_model(payload: Dict[str, Any]) -> str:
    """The stochastic model of a ``SlipResult.to_dict()`` payload ("white" when absent)."""
    model = (payload.get("parameters") or {}).get("stochastic_model")
    if model is None:
        model = (payload.get("left") or {}).get("stochastic_model", "white")
    return str(model)


#: how the console names the spatial term's families whose range is a wavelength (every
#: one of core.stochastic.WAVELENGTH_FAMILIES, tests/cli/test_stochastic_options.py)
WAVE_FAMILIES = {"wave": "3-D waves", "wave_h": "waves of the map position"}


def component_text(
    name: str, comp: Dict[str, Any], range_m=None, drift_s=False, lever_m=None, family=None
) -> str:
    """One variance component for a console line, e.g. ``spatial 2.56 mm (sd 1.10, estimated,
    range 27 m)``, or ``(…, waves of the map position, wavelength 45 m)`` for the hole-effect
    families (``family``); ``unit_after off`` for a component that is not in the model. ``drift_s``:
    the units' drift along GpsTime (its knot spacing in seconds, None: rigid units; False:
    no acquisition times); ``lever_m``: the lever of the units' turn (None: they do not
    turn), shown as the turn's 1σ per axis."""
    source = comp.get("source", "")
    if source == "off":
        return f"{name} off"
    extra = []
    if comp.get("sd_m") is not None and _mm(comp.get("sd_m")) is not None:
        extra.append(f"sd {_fmt_mm(comp['sd_m'])}")
    extra.append(source)
    if name == "white" and comp.get("variance_factor") is not None:
        extra.append(f"σ0² {float(comp['variance_factor']):.2f}")
    if name == "spatial" and range_m is not None and math.isfinite(float(range_m)):
        if family in WAVE_FAMILIES:
            extra.append(f"{WAVE_FAMILIES[family]}, wavelength {float(range_m):.0f} m")
        elif family not in (None, "spherical"):
            extra.append(f"{family}, range {float(range_m):.0f} m")
        else:
            extra.append(f"range {float(range_m):.0f} m")
    if name.startswith("unit_") and drift_s is not False:
        extra.append(
            "rigid per unit"
            if drift_s is None
            else f"drifting along GpsTime, knots every {float(drift_s):g} s"
        )
    if name.startswith("unit_") and lever_m is not None and _mm(comp.get("sigma_m")) is not None:
        turn = float(comp["sigma_m"]) / float(lever_m) * 1000.0
        extra.append(f"turning {turn:.3f} mrad about its origin (lever {float(lever_m):g} m)")
    return f"{name} {_fmt_mm(comp.get('sigma_m'))} mm ({', '.join(e for e in extra if e)})"


def side_component_line(side: str, side_dict: Dict[str, Any]) -> Optional[str]:
    """``left side: 15 planes, n_eff 13.3; white 19.91 mm (estimated, σ0² 0.99); …`` or None
    for the white model (no components)."""
    vc = side_dict.get("variance_components")
    if not vc:
        return None
    n_eff = vc.get("n_eff")
    head = f"{side} side: {vc.get('n_planes', side_dict.get('n_planes'))} planes, n_eff " + (
        "n/a" if n_eff is None else f"{float(n_eff):.1f}"
    )
    drift = vc["unit_drift_interval_s"] if "unit_drift_interval_s" in vc else False
    lever = vc.get("unit_turn_lever_m")
    comps = [
        component_text(name, c, vc.get("spatial_range_m"), drift, lever, vc.get("spatial_family"))
        for name, c in (vc.get("components") or {}).items()
    ]
    tied = vc.get("unit_contrasts")
    if tied:
        head += (
            f", units tied on {tied.get('before', 0)} / {tied.get('after', 0)} shared planes "
            "(before / after)"
        )
    return head + "; " + "; ".join(comps)


def _fmt_signed_mm(value, digits: int = 2) -> str:
    v = _mm(value)
    return "n/a" if v is None else f"{v:+.{digits}f}"


def slip_summary_lines(payload: Dict[str, Any]) -> List[str]:
    """Console summary of a slip payload (:func:`slipmap.app.slip.summary_payload`), in the
    sign convention of :mod:`.signs`: the relative motion of the right side (named by compass
    direction) against the left, each component ± its σ (the model's) with the white-noise σ
    beside it, what + means, the right-lateral slip, then one line per side with its own
    right-lateral motion, and with the variance components and n_eff (stochastic models)."""
    from . import signs

    rel = payload["relative"]
    model = slip_model(payload)
    fault = payload.get("fault") or {}
    names = {s: fault[f"{s}_side"] for s in ("left", "right") if fault.get(f"{s}_side")}

    def pm(value, sigma, white=None) -> str:
        text = f"{_fmt_signed_mm(value):>8} ± {_fmt_mm(sigma)} mm"
        if model != "white" and white is not None:
            text += f"   (white noise only ± {_fmt_mm(white)} mm)"
        return text

    right, left = signs.side_label("right", names), signs.side_label("left", names)
    lines = [
        f"relative motion of the {right} against the {left}, stochastic model {model}:",
        "  right-lateral  "
        + pm(
            rel["right_lateral"],
            rel["sigma_right_lateral"],
            rel.get("sigma_right_lateral_white"),
        )
        + "   (+ = dextral)",
        "  opening        " + pm(rel["opening"], rel["sigma_opening"]) + "   (+ = apart)",
        "  dz             "
        + pm(rel["dz"], rel["sigma_dz"], rel.get("sigma_dz_white"))
        + f"   ({signs.dz_meaning(names)})",
        f"  right-lateral slip {_fmt_signed_mm(rel['right_lateral_slip'])} ± "
        f"{_fmt_mm(rel['sigma_right_lateral'])} mm",
    ]
    for side in ("left", "right"):
        sd = payload.get(side) or {}
        if sd.get("right_lateral") is not None:
            lines.append(
                f"  {signs.side_label(side, names)} moved: right-lateral "
                f"{_fmt_signed_mm(sd['right_lateral'])} ± {_fmt_mm(sd.get('sigma_right_lateral'))}"
                f" mm, opening {_fmt_signed_mm(sd.get('opening'))} mm, dz "
                f"{_fmt_signed_mm(sd.get('dz'))} mm"
            )
    for side in ("left", "right"):
        line = side_component_line(side, payload.get(side) or {})
        if line is not None:
            lines.append("  " + line)
    for row in payload.get("weak_components") or ():
        lines.append(f"  weakly determined: {row['text']}")
    return lines


def stochastic_tables(payload: Dict[str, Any]) -> Dict[str, Any]:
    """The report's tables of the stochastic model (``write_html_report`` ``tables``):

    * "Stochastic model": the model, the right-lateral and vertical σ of the model and of the
      white model, and per side n_planes, n_eff, the spatial range and the notes;
    * "Stochastic model: components per side" (rows): side, component, σ (mm), sd (mm),
      source, notes;
    * "Rejected and down-weighted planes" (rows): side, plane, status, weight, reason.
    """
    rel = payload["relative"]
    model = slip_model(payload)
    head: Dict[str, Any] = {"model": model}
    head["σ right-lateral (mm)"] = _mm(rel.get("sigma_right_lateral"))
    if model != "white":
        head["σ right-lateral, white noise only (mm)"] = _mm(rel.get("sigma_right_lateral_white"))
    head["σ vertical (mm)"] = _mm(rel.get("sigma_dz"))
    if model != "white":
        head["σ vertical, white noise only (mm)"] = _mm(rel.get("sigma_dz_white"))
    units = (payload.get("parameters") or {}).get("acquisition_unit_sources") or {}
    rows, planes = [], []
    for side in ("left", "right"):
        sd = payload.get(side) or {}
        vc = sd.get("variance_components")
        if vc:
            head[f"{side}: planes"] = vc.get("n_planes")
            head[f"{side}: n_eff"] = vc.get("n_eff")
            head[f"{side}: spatial range (m)"] = vc.get("spatial_range_m")
            fam = vc.get("spatial_family")
            if fam in WAVE_FAMILIES:
                head[f"{side}: spatial family (range: its wavelength)"] = fam
            elif fam not in (None, "spherical"):
                head[f"{side}: spatial family"] = fam
            if "unit_drift_interval_s" in vc:
                head[f"{side}: unit drift knots (s; empty: rigid units)"] = vc[
                    "unit_drift_interval_s"
                ]
            if vc.get("unit_turn_lever_m") is not None:
                head[f"{side}: unit turn lever (m; empty: units translate only)"] = vc[
                    "unit_turn_lever_m"
                ]
            if vc.get("unit_contrasts"):
                tied = vc["unit_contrasts"]
                head[f"{side}: unit contrasts (before / after)"] = (
                    f"{tied.get('before', 0)} / {tied.get('after', 0)}"
                )
            if vc.get("notes"):
                head[f"{side}: notes"] = "; ".join(vc["notes"])
            for name, c in (vc.get("components") or {}).items():
                rows.append(
                    {
                        "side": side,
                        "component": name,
                        "σ (mm)": _mm(c.get("sigma_m")),
                        "sd (mm)": _mm(c.get("sd_m")),
                        "source": c.get("source", ""),
                        "σ0² (white)": c.get("variance_factor"),
                        "notes": c.get("note", ""),
                    }
                )
        for r in sd.get("rejected_planes") or []:
            planes.append(
                {
                    "side": side,
                    "plane": r["plane"],
                    "status": "rejected",
                    "weight": 0.0,
                    "reason": r["reason"],
                }
            )
        for r in sd.get("downweighted_planes") or []:
            planes.append(
                {
                    "side": side,
                    "plane": r["plane"],
                    "status": "down-weighted",
                    "weight": r["weight"],
                    "reason": r["reason"],
                }
            )
    for epoch in ("before", "after"):
        if epoch in units:
            u = units[epoch]
            head[f"acquisition units, {epoch}"] = (
                f"{u['n_units']} from {u['source']}" if u.get("n_units") else u.get("note", "none")
            )
    tables: Dict[str, Any] = {"Stochastic model": head}
    if rows:
        tables["Stochastic model: components per side"] = rows
    tables["Rejected and down-weighted planes"] = planes or {"planes": "none"}
    return tables


def plane_fields(side) -> Dict[str, np.ndarray]:
    """Per matched plane of a :class:`~slipmap.core.displacement.SideResult` (in match order):
    ``weight`` (1 full, (0, 1) down-weighted, 0 rejected, NaN unused), ``w_test`` (w-test of
    its misclosure against the plane-level spread), ``offset_mm`` (predicted plane offset δ
    along the normal) and ``misclosure_mm``. The white model has weights 1 / 0 (rejected) and
    NaN for the rest."""
    n = len(side.matches)
    r = side.rigid

    def padded(values, scale=1.0):
        out = np.full(n, np.nan)
        if values is not None:
            v = np.asarray(values, dtype=np.float64).ravel()
            k = min(n, v.size)
            out[:k] = v[:k] * scale
        return out

    if r.plane_weights is None:
        weight = np.ones(n)
        for p, _ in r.rejected_planes:
            if 0 <= p < n:
                weight[p] = 0.0
    else:
        weight = padded(r.plane_weights)
    return {
        "weight": weight,
        "w_test": padded(r.plane_w),
        "offset_mm": padded(r.plane_offset_m, 1000.0),
        "misclosure_mm": padded(r.plane_misclosure_m, 1000.0),
    }


def stochastic_outputs(payload: Dict[str, Any]) -> Dict[str, Any]:
    """Compact per-side components ``{side: {"n_eff", "spatial_range_m", name: sigma_m, …}}``
    and the model's and white σ of the right-lateral slip, for outputs that hold one value
    (QGIS outputs, PDAL metadata)."""
    rel = payload["relative"]
    out: Dict[str, Any] = {
        "model": slip_model(payload),
        "sigma_right_lateral": rel.get("sigma_right_lateral"),
        "sigma_right_lateral_white": rel.get("sigma_right_lateral_white"),
    }
    for side in ("left", "right"):
        vc = (payload.get(side) or {}).get("variance_components")
        if not vc:
            continue
        d: Dict[str, Any] = {"n_eff": vc.get("n_eff"), "spatial_range_m": vc.get("spatial_range_m")}
        for name, c in (vc.get("components") or {}).items():
            d[f"{name}_m"] = c.get("sigma_m")
            d[f"{name}_source"] = c.get("source")
        out[side] = d
    return out
