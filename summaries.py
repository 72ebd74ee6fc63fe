"""Output shaping shared by the adapters (CLI, QGIS, PDAL): JSON-safe values, statistics of
finite values, horizontal magnitude/azimuth, strip rows. No science and no QGIS/PDAL here."""

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
    """One JSON row per :class:`~slipmap.core.displacement.StripResult`."""
    return [
        {
            "side": st.side,
            "along_start_m": st.along_start_m,
            "along_end_m": st.along_end_m,
            "n_planes": int(st.n_planes),
            "fault_parallel": finite(st.fault_parallel),
            "sigma_fault_parallel": finite(st.sigma_fault_parallel),
            "status": st.status,
        }
        for st in strips
    ]


def icp_summary(res) -> Dict[str, Any]:
    """The JSON summary of a ``WindowedICPResult`` shared by the CLI (``icp.json``) and the
    QGIS algorithm: cell counts, motion and sigma statistics, the field's variance factor
    and the pre-alignment (NaN/inf are left to :func:`json_safe`)."""
    mag, _ = horizontal(res.dx, res.dy)
    pre = res.prealignment
    return {
        "cell_m": res.cell_m,
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
