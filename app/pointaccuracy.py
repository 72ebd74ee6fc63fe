"""Point-accuracy settings → per-point covariances, for the adapters (CLI, PDAL, QGIS).

Reads what a model needs (trajectory files, scanner specifications, LAS columns) through
``core.io`` and calls the models of ``core.accuracy``. Settings are a plain dict, so the CLI,
a JSON config file (``--pa-config``) and the other adapters share one vocabulary:

=====================  ==========================================================
key                    meaning
=====================  ==========================================================
``model``              constant | axis | columns | propagated (default constant)
``sigma``              isotropic σ, metres (constant)
``sigma_xyz``          [SX, SY, SZ], metres (axis)
``columns``            [X, Y, Z] names of per-point σ dimensions (columns; default
                       SigmaX, SigmaY, SigmaZ)
``trajectory``         SBET or CSV file: platform position and attitude (propagated)
``trajectory_accuracy`` SMRMSG or CSV file: their RMS against GPS time (propagated)
``scanner``            a name of ``core.accuracy.SCANNERS`` or a JSON file
``scanner_position``   [X, Y, Z] of a static (TLS) scanner, map CRS (propagated)
``footprint``          add the beam-footprint term (default true for propagated)
=====================  ==========================================================
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import numpy as np

from ..core.errors import InputDataError, InvalidParameterError

log = logging.getLogger("slipmap.accuracy")

MODELS = ("constant", "axis", "columns", "propagated")
KEYS = {
    "model",
    "sigma",
    "sigma_xyz",
    "columns",
    "trajectory",
    "trajectory_accuracy",
    "scanner",
    "scanner_position",
    "footprint",
}


def check_settings(settings: Mapping[str, Any]) -> Dict[str, Any]:
    """Validate a settings dict; unknown keys and models are errors naming them."""
    unknown = set(settings) - KEYS
    if unknown:
        raise InvalidParameterError(
            f"unknown point-accuracy setting(s) {sorted(unknown)}; known: {sorted(KEYS)}"
        )
    s = dict(settings)
    s.setdefault("model", "constant")
    if s["model"] not in MODELS:
        raise InvalidParameterError(f"--pa must be one of {MODELS}, got {s['model']!r}")
    return s


def load_config(path: str) -> Dict[str, Dict[str, Any]]:
    """A ``--pa-config`` JSON file: ``{"before": {...}, "after": {...}}`` (or one dict for
    both epochs)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InvalidParameterError(
            f"--pa-config {path!r} is not a readable JSON file: {exc}"
        ) from None
    if not isinstance(data, dict):
        raise InvalidParameterError(f"--pa-config {path!r}: expected a JSON object")
    if set(data) <= {"before", "after"} and data:
        return {k: check_settings(data.get(k, {})) for k in ("before", "after")}
    return {"before": check_settings(data), "after": check_settings(data)}


def _scanner(value):
    from ..core.accuracy import SCANNERS, scanner_spec_from_dict

    if value is None:
        raise InvalidParameterError(
            f"the propagated model needs --scanner-spec (one of {sorted(SCANNERS)} or a JSON file)"
        )
    if str(value) in SCANNERS:
        return SCANNERS[str(value)]
    try:
        d = json.loads(Path(value).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InvalidParameterError(
            f"--scanner-spec {value!r} is neither a known scanner ({sorted(SCANNERS)}) nor a "
            f"readable JSON file: {exc}"
        ) from None
    return scanner_spec_from_dict(d)


def covariances(cloud, index: Optional[np.ndarray], settings: Mapping[str, Any]):
    """Point accuracy of ``cloud.xyz[index]`` under ``settings``.

    Returns a scalar σ (constant), a (3,) σ (axis), (n, 3) per-point σ (columns) or an
    (n, 3, 3) covariance array (propagated), in the forms ``core.adjustment.adjust_rigid``
    accepts.
    """
    from ..core import accuracy as pa

    s = check_settings(settings)
    idx = np.arange(len(cloud)) if index is None else np.asarray(index)
    model = s["model"]
    if model == "constant":
        return float(s.get("sigma", 0.05))
    if model == "axis":
        if s.get("sigma_xyz") is None:
            raise InvalidParameterError("--pa axis needs --sigma-xyz SX SY SZ")
        return np.asarray(s["sigma_xyz"], dtype=np.float64)
    if model == "columns":
        names = s.get("columns") or ["SigmaX", "SigmaY", "SigmaZ"]
        missing = [c for c in names if c not in cloud.attributes]
        if missing:
            raise InputDataError(
                f"{cloud.source}: no dimension(s) {missing} for --pa columns; write them with "
                "`slipmap accuracy` or name the right ones with --sigma-columns"
            )
        cols = [np.asarray(cloud.attributes[c], dtype=np.float64)[idx] for c in names]
        for name, col in zip(names, cols):
            if not np.all(np.isfinite(col) & (col > 0)):
                raise InputDataError(
                    f"{cloud.source}: dimension {name} (--pa columns) must hold sigmas > 0 "
                    "in metres; it has zero, negative or NaN values"
                )
        return np.column_stack(cols)  # (n, 3) per-point sigmas: no (n, 3, 3) needed
    # propagated
    spec = _scanner(s.get("scanner"))
    pts = cloud.xyz[idx]
    if s.get("scanner_position") is not None:
        pos = np.asarray(s["scanner_position"], dtype=np.float64)
        cov = pa.tls_covariance(pts, pos, spec)
        sensors = np.broadcast_to(pos, pts.shape)
    else:
        cov, sensors = _propagated_mobile(cloud, idx, pts, s, spec)
    if s.get("footprint", True):
        cov = pa.total_covariance(cov, pa.footprint_covariance(pts, sensors, spec))
    return cov


def covariance_matrices(cloud, index: Optional[np.ndarray], settings: Mapping[str, Any]):
    """:func:`covariances` as an (n, 3, 3) array (m²) whatever the model, for writing
    SigmaX/Y/Z or the six covariance entries (CLI ``accuracy``, PDAL and QGIS stages)."""
    cov = np.asarray(covariances(cloud, index, settings), dtype=np.float64)
    n = len(cloud) if index is None else int(np.asarray(index).size)
    if cov.ndim == 0:
        return np.broadcast_to(np.eye(3) * float(cov) ** 2, (n, 3, 3))
    if cov.ndim == 1:
        return np.broadcast_to(np.diag(cov**2), (n, 3, 3))
    if cov.ndim == 2:  # (n, 3) per-point sigmas
        return cov[:, :, None] ** 2 * np.eye(3)
    return cov


def _propagated_mobile(cloud, idx, pts, s, spec):
    import pyproj

    from ..core import accuracy as pa
    from ..core.io.trajectory import read_trajectory, read_trajectory_accuracy

    if s.get("trajectory") is None or s.get("trajectory_accuracy") is None:
        raise InvalidParameterError(
            "the propagated model needs --trajectory and --trajectory-accuracy (or "
            "--scanner-position for a static scan)"
        )
    if "GpsTime" not in cloud.attributes:
        raise InputDataError(
            f"{cloud.source}: no GpsTime dimension; the propagated model interpolates the "
            "trajectory at each point's GPS time"
        )
    t = np.asarray(cloud.attributes["GpsTime"], dtype=np.float64)[idx]
    traj = read_trajectory(s["trajectory"]).interpolate(t)
    acc = read_trajectory_accuracy(s["trajectory_accuracy"]).interpolate(t)
    if traj.get("xyz") is not None:
        platform = np.asarray(traj["xyz"], dtype=np.float64)
    else:
        if cloud.crs is None:
            raise InputDataError(
                f"{cloud.source}: the file has no CRS, so the geodetic trajectory cannot be "
                "put in the points' frame"
            )
        tr = pyproj.Transformer.from_crs("EPSG:4979", cloud.crs, always_xy=True)
        x, y, z = tr.transform(
            np.degrees(traj["lon_rad"]), np.degrees(traj["lat_rad"]), traj["height_m"]
        )
        platform = np.column_stack([x, y, z])
    rng = np.linalg.norm(pts - platform, axis=1)
    if "ScanAngle" in cloud.attributes:
        scan = np.radians(np.asarray(cloud.attributes["ScanAngle"], dtype=np.float64)[idx])
    else:
        raise InputDataError(f"{cloud.source}: no ScanAngle dimension for the propagated model")
    # core.accuracy takes map-frame (x = east, y = north, z = up) position sigmas
    sig_pos = np.column_stack([acc["east_m"], acc["north_m"], acc["down_m"]])
    sig_att = np.column_stack([acc["roll_rad"], acc["pitch_rad"], acc["heading_rad"]])
    cov = pa.georeferencing_covariance(
        platform_xyz=platform,
        roll=traj["roll_rad"],
        pitch=traj["pitch_rad"],
        heading=traj["heading_rad"],
        range_m=rng,
        scan_angle_rad=scan,
        sigma_position_m=sig_pos,
        sigma_attitude_rad=sig_att,
        spec=spec,
    )
    return cov, platform
