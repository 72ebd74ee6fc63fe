"""Point-accuracy options and settings → per-point covariances, for every job and face.

The options are declared once, in :func:`pa_options` (the accuracy job's and the slip job's);
:func:`settings_from_options` turns parsed options into the settings of each epoch, and
:func:`covariances` reads what a model needs (trajectory files, scanner specifications, LAS
columns) through ``core.io`` and calls the models of ``core.accuracy``. Settings are a plain
dict, so the options and a JSON config file (the ``pa_config`` option) share one vocabulary:

=====================  ==========================================================
key                    meaning
=====================  ==========================================================
``model``              constant | axis | columns | propagated (default constant, or
                       axis when ``sigma_xyz`` is given)
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

Errors are :class:`~slipmap.app.options.OptionError` naming the option's key (each face
renders its own name: ``--sigma-xyz``, "Sigma X, Y, Z, axis model (m)", ``sigma_xyz``);
settings read from a ``pa_config`` file name ``pa_config`` and the setting.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

from .options import Option, OptionError

log = logging.getLogger("slipmap.accuracy")

MODELS = ("constant", "axis", "columns", "propagated")
#: settings vocabulary (``pa_config`` files) -> option key (before any prefix)
OPTION_KEYS = {
    "model": "pa_model",
    "sigma": "sigma_m",
    "sigma_xyz": "sigma_xyz_m",
    "columns": "sigma_columns",
    "trajectory": "trajectory",
    "trajectory_accuracy": "trajectory_accuracy",
    "scanner": "scanner",
    "scanner_position": "scanner_position",
    "footprint": "footprint",
}
KEYS = set(OPTION_KEYS)
#: every option key of :func:`pa_options` (before any prefix)
PA_KEYS = tuple(OPTION_KEYS.values()) + ("pa_config",)
#: names of ``core.accuracy.SCANNERS`` (a test keeps them equal; not imported from the core
#: here, which would load scipy when a face builds its parameters)
SCANNER_NAMES = ("leica-als60", "optech-orion", "riegl-vz400")
GROUP = "point accuracy (Kusari et al. 2019, section II.E)"
TRAJECTORY_FILTER = "Trajectory (*.sbet *.out *.csv *.txt);;All files (*.*)"
ACCURACY_FILTER = "Trajectory accuracy (*.smrmsg *.csv *.txt);;All files (*.*)"


def pa_options(
    prefix: str = "", *, group: str = GROUP, advanced: bool = True
) -> Tuple[Option, ...]:
    """The point-accuracy options, declared once (the accuracy and slip jobs).

    Parameters
    ----------
    prefix
        Put in front of every key and face name (``"after_"`` gives ``after_sigma_m``,
        ``--after-sigma``, ``AFTER_SIGMA``, ``after_sigma``); ``""`` gives the accuracy job's
        names: ``pa_model`` (``--pa``, ``MODEL``, ``model``), ``sigma_m`` (``--sigma``,
        ``SIGMA``, ``sigma``), ``sigma_xyz_m``, ``sigma_columns`` (PDAL ``columns``),
        ``trajectory``, ``trajectory_accuracy``, ``scanner`` (CLI ``--scanner-spec``),
        ``scanner_position``, ``footprint`` and ``pa_config`` (not in PDAL).
    group, advanced
        CLI heading and QGIS "advanced" flag (``sigma_m`` and the model are never advanced).

    QGIS builds the model, ``sigma_xyz_m``, ``scanner`` and ``scanner_position`` as its own
    widgets (an enum with a default, three numbers, a scanner list plus a file, a map point
    plus a height): they are left out of QGIS here (``qgis=None``) and the face passes their
    values under these keys; messages still name them by their dialog labels.
    """
    p = prefix

    def names(key: str, cli: str, qgis: Optional[str], pdal: Optional[str]) -> Dict[str, Any]:
        return {
            "cli": "--" + (p + cli).replace("_", "-"),
            "qgis": None if qgis is None else (p + qgis).upper(),
            "pdal": None if pdal is None else p + pdal,
        }

    return (
        Option(
            p + "pa_model",
            "choice",
            "point-accuracy model: constant (sigma), axis (sigma-xyz), columns (per-point "
            "SigmaX/Y/Z dimensions), propagated (trajectory + scanner, or a static scanner's "
            "position)",
            label="Point-accuracy model",
            choices=MODELS,
            group=group,
            unset_text="constant (axis when sigma_xyz is given)",
            **names("pa_model", "pa", None, "model"),
        ),
        Option(
            p + "sigma_m",
            "float",
            "isotropic point accuracy of the constant model, metres (default 0.05, as the study)",
            label="Sigma, constant model (m)",
            default=0.05,
            minimum=0,
            exclusive=True,
            group=group,
            metavar="M",
            **names("sigma_m", "sigma", "SIGMA", "sigma"),
        ),
        Option(
            p + "sigma_xyz_m",
            "vector3",
            "per-axis point accuracy [SX, SY, SZ] of the axis model, metres",
            label="Sigma X, Y, Z, axis model (m)",
            minimum=0,
            exclusive=True,
            group=group,
            advanced=advanced,
            metavar=("SX", "SY", "SZ"),
            unset_text="none",
            **names("sigma_xyz_m", "sigma_xyz", None, "sigma_xyz"),
        ),
        Option(
            p + "sigma_columns",
            "strs",
            "dimension names X Y Z of per-point sigmas (metres) of the columns model",
            label="Sigma columns, columns model (X,Y,Z dimension names)",
            nargs=3,
            group=group,
            advanced=advanced,
            metavar=("X", "Y", "Z"),
            unset_text="SigmaX SigmaY SigmaZ",
            **names("sigma_columns", "sigma_columns", "SIGMA_COLUMNS", "columns"),
        ),
        Option(
            p + "trajectory",
            "path",
            "platform trajectory of the propagated model: SBET (.sbet/.out) or CSV with named "
            "columns",
            label="Trajectory, propagated model (SBET or CSV)",
            role="input",
            group=group,
            advanced=advanced,
            metavar="FILE",
            unset_text="none",
            file_filter=TRAJECTORY_FILTER,
            **names("trajectory", "trajectory", "TRAJECTORY", "trajectory"),
        ),
        Option(
            p + "trajectory_accuracy",
            "path",
            "trajectory accuracy of the propagated model: SMRMSG (.smrmsg) or CSV (attitude "
            "in arc-minutes)",
            label="Trajectory accuracy, propagated model (SMRMSG or CSV)",
            role="input",
            group=group,
            advanced=advanced,
            metavar="FILE",
            unset_text="none",
            file_filter=ACCURACY_FILTER,
            **names(
                "trajectory_accuracy",
                "trajectory_accuracy",
                "TRAJECTORY_ACCURACY",
                "trajectory_accuracy",
            ),
        ),
        Option(
            p + "scanner",
            "str",
            "scanner of the propagated model: " + ", ".join(SCANNER_NAMES) + " or a JSON "
            "specification file (units in the key names, e.g. range_sigma_m)",
            label="Scanner, propagated model",
            group=group,
            advanced=advanced,
            metavar="NAME|FILE",
            unset_text="none",
            **names("scanner", "scanner_spec", None, "scanner"),
        ),
        Option(
            p + "scanner_position",
            "vector3",
            "position [X, Y, Z] of a static (TLS) scanner in the point cloud's CRS, instead of "
            "a trajectory (propagated model)",
            label="Scanner position, static (TLS) scan",
            group=group,
            advanced=advanced,
            metavar=("X", "Y", "Z"),
            unset_text="none",
            **names("scanner_position", "scanner_position", None, "scanner_position"),
        ),
        Option(
            p + "footprint",
            "bool",
            "add the beam-footprint (incidence) term of the propagated model",
            label="Beam footprint term, propagated model",
            default=True,
            group=group,
            advanced=advanced,
            **names("footprint", "footprint", "FOOTPRINT", "footprint"),
        ),
        Option(
            p + "pa_config",
            "path",
            'JSON {"before": {...}, "after": {...}} (or one object for both epochs) with the '
            "keys model, sigma, sigma_xyz, columns, trajectory, trajectory_accuracy, scanner, "
            "scanner_position, footprint; when given it replaces the other point-accuracy "
            "options",
            label="Point-accuracy configuration (JSON)",
            role="input",
            group=group,
            advanced=advanced,
            metavar="FILE",
            unset_text="none",
            file_filter="JSON (*.json)",
            **names("pa_config", "pa_config", "PA_CONFIG", None),
        ),
    )


def settings_from_options(opts: Mapping[str, Any], prefix: str = "") -> Dict[str, Dict[str, Any]]:
    """``{"before": settings, "after": settings}`` from parsed :func:`pa_options` options:
    the ``pa_config`` file's when given, else the options' (the same for both epochs).

    Raises
    ------
    OptionError
        Naming the option (or ``pa_config``) at fault.
    """
    config = opts.get(prefix + "pa_config")
    if config:
        return load_config(config, key=prefix + "pa_config")
    s: Dict[str, Any] = {}
    for name, key in OPTION_KEYS.items():
        value = opts.get(prefix + key)
        if value is not None:
            s[name] = list(value) if isinstance(value, tuple) else value
    if "model" not in s:
        s["model"] = "axis" if s.get("sigma_xyz") is not None else "constant"
    s = check_settings(s, prefix=prefix)
    return {"before": s, "after": s}


#: the settings each model reads (beside ``model``), with the defaults it then uses
MODEL_SETTINGS: Dict[str, Dict[str, Any]] = {
    "constant": {"sigma": 0.05},
    "axis": {"sigma_xyz": None},
    "columns": {"columns": ["SigmaX", "SigmaY", "SigmaZ"]},
    "propagated": {
        "scanner": None,
        "scanner_position": None,
        "trajectory": None,
        "trajectory_accuracy": None,
        "footprint": True,
    },
}


def settings_in_effect(settings: Mapping[str, Any]) -> Dict[str, Any]:
    """The settings the model uses, for the record of a run (JSON, report): the model and
    what it reads, its defaults filled in; none of another model (a dialog's defaults for the
    scanner or the footprint mean nothing to the constant model). A static scan's
    ``scanner_position`` leaves the trajectory files out.

    Parameters
    ----------
    settings : mapping
        As :func:`settings_from_options` gives per epoch.

    Returns
    -------
    dict
        ``{"model": name, setting: value, ...}``.
    """
    model = settings.get("model", "constant")
    out: Dict[str, Any] = {"model": model}
    for name, default in MODEL_SETTINGS.get(model, {}).items():
        value = settings.get(name)
        if value is None:
            value = default
        if value is not None:
            out[name] = value
    if model == "propagated" and out.get("scanner_position") is not None:
        out.pop("trajectory", None)
        out.pop("trajectory_accuracy", None)
    return out


def check_options(opts: Mapping[str, Any], prefix: str = "") -> None:
    """Cross-option check of :func:`pa_options` (for a JobSpec's ``check``): what the model
    needs that can be known before reading the point cloud.

    Raises
    ------
    OptionError
        The model's missing option, named by its key.
    """
    if opts.get(prefix + "pa_config"):
        return
    s = settings_from_options(opts, prefix)["before"]
    _needs(s, prefix=prefix, config_key=None)


def _where(name: str, prefix: str, config_key: Optional[str]):
    """(option key, text head) of a setting: the option, or the config file naming it."""
    if config_key:
        return config_key, f"setting {name!r}: "
    return prefix + OPTION_KEYS[name], ""


def _needs(s: Mapping[str, Any], *, prefix: str, config_key: Optional[str]) -> None:
    model = s["model"]

    def missing(name: str, text: str, also: Tuple[str, ...] = ()) -> OptionError:
        key, head = _where(name, prefix, config_key)
        if config_key:
            text = text.replace("{", "").replace("}", "")
            return OptionError(key, head + text)
        return OptionError(key, text, also=tuple(prefix + OPTION_KEYS[a] for a in also))

    if model == "axis" and s.get("sigma_xyz") is None:
        raise missing("sigma_xyz", "is needed by the axis model; give SX SY SZ in metres")
    if model == "propagated":
        if s.get("scanner") is None:
            raise missing(
                "scanner",
                "is needed by the propagated model: one of "
                + ", ".join(SCANNER_NAMES)
                + " or a JSON specification file",
            )
        if s.get("scanner_position") is None and (
            s.get("trajectory") is None or s.get("trajectory_accuracy") is None
        ):
            name = "trajectory" if s.get("trajectory") is None else "trajectory_accuracy"
            raise missing(
                name,
                "is needed by the propagated model: give {trajectory} and "
                "{trajectory_accuracy} (mobile or airborne survey) or {scanner_position} "
                "(static scan)",
                also=("trajectory", "trajectory_accuracy", "scanner_position"),
            )


def check_settings(
    settings: Mapping[str, Any], *, prefix: str = "", config_key: Optional[str] = None
) -> Dict[str, Any]:
    """Validate a settings dict; unknown keys and models are errors naming them."""
    where = config_key or prefix + "pa_model"
    unknown = set(settings) - KEYS
    if unknown:
        raise OptionError(
            config_key or prefix + "pa_config",
            f"unknown point-accuracy setting(s) {sorted(unknown)}; known: {sorted(KEYS)}",
        )
    s = dict(settings)
    s.setdefault("model", "axis" if s.get("sigma_xyz") is not None else "constant")
    if s["model"] not in MODELS:
        head = "setting 'model' " if config_key else ""
        raise OptionError(where, f"{head}must be one of {', '.join(MODELS)}; got {s['model']!r}")
    if config_key:  # the values of a file, converted by the options' own rules
        opts = {o.key: o for o in pa_options()}
        for name, value in list(s.items()):
            if name == "model" or value is None:
                continue
            try:
                s[name] = opts[OPTION_KEYS[name]].convert(value)
            except OptionError as exc:
                raise OptionError(config_key, f"setting {name!r} {exc.text}") from None
            if isinstance(s[name], tuple):
                s[name] = list(s[name])
    return s


def load_config(path, *, key: str = "pa_config") -> Dict[str, Dict[str, Any]]:
    """A ``pa_config`` JSON file: ``{"before": {...}, "after": {...}}`` (or one dict for
    both epochs). Errors name ``key``."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise OptionError(key, f"{str(path)!r} is not a readable JSON file: {exc}") from None
    if not isinstance(data, dict):
        raise OptionError(key, f"{str(path)!r}: expected a JSON object")
    if set(data) <= {"before", "after"} and data:
        out = {}
        for epoch in ("before", "after"):
            s = check_settings(data.get(epoch, {}), config_key=key)
            _needs(s, prefix="", config_key=key)
            out[epoch] = s
        return out
    s = check_settings(data, config_key=key)
    _needs(s, prefix="", config_key=key)
    return {"before": s, "after": s}


def _scanner(value, key: str):
    from ..core.accuracy import SCANNERS, scanner_spec_from_dict

    if value is None:
        raise OptionError(
            key,
            f"is needed by the propagated model: one of {', '.join(sorted(SCANNERS))} or a "
            "JSON file",
        )
    if str(value) in SCANNERS:
        return SCANNERS[str(value)]
    try:
        d = json.loads(Path(value).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise OptionError(
            key,
            f"{value!r} is neither a known scanner ({', '.join(sorted(SCANNERS))}) nor a "
            f"readable JSON file: {exc}",
        ) from None
    try:
        return scanner_spec_from_dict(d)
    except (ValueError, TypeError, KeyError) as exc:
        raise OptionError(key, f"{value!r} is not a scanner specification: {exc}") from None


def covariances(
    cloud,
    index: Optional[np.ndarray],
    settings: Mapping[str, Any],
    *,
    prefix: str = "",
    config_key: Optional[str] = None,
):
    """Point accuracy of ``cloud.xyz[index]`` under ``settings``.

    Returns a scalar σ (constant), a (3,) σ (axis), (n, 3) per-point σ (columns) or an
    (n, 3, 3) covariance array (propagated), in the forms ``core.adjustment.adjust_rigid``
    accepts. ``prefix`` is that of the options the settings came from (or ``config_key`` the
    option of the config file they were read from): errors name them.

    Raises
    ------
    OptionError
        A setting the model needs is missing, or the cloud lacks what the model reads.
    """
    from ..core import accuracy as pa

    s = check_settings(settings, prefix=prefix)
    _needs(s, prefix=prefix, config_key=config_key)

    def key_of(name):
        return _where(name, prefix, config_key)

    idx = np.arange(len(cloud)) if index is None else np.asarray(index)
    model = s["model"]
    if model == "constant":
        return float(s.get("sigma", 0.05))
    if model == "axis":
        return np.asarray(s["sigma_xyz"], dtype=np.float64)
    if model == "columns":
        names = list(s.get("columns") or ["SigmaX", "SigmaY", "SigmaZ"])
        key, head = key_of("columns")
        missing = [c for c in names if c not in cloud.attributes]
        if missing:
            raise OptionError(
                key,
                f"{head}{cloud.source} has no dimension(s) {', '.join(missing)} for the columns "
                "model; write them with the accuracy job or name the right ones",
            )
        cols = [np.asarray(cloud.attributes[c], dtype=np.float64)[idx] for c in names]
        for name, col in zip(names, cols):
            if not np.all(np.isfinite(col) & (col > 0)):
                raise OptionError(
                    key,
                    f"{head}dimension {name} of {cloud.source} must hold sigmas > 0 in metres; "
                    "it has zero, negative or NaN values",
                )
        return np.column_stack(cols)  # (n, 3) per-point sigmas: no (n, 3, 3) needed
    # propagated
    spec = _scanner(s.get("scanner"), key_of("scanner")[0])
    pts = cloud.xyz[idx]
    if s.get("scanner_position") is not None:
        pos = np.asarray(s["scanner_position"], dtype=np.float64)
        cov = pa.tls_covariance(pts, pos, spec)
        sensors = np.broadcast_to(pos, pts.shape)
    else:
        cov, sensors = _propagated_mobile(cloud, idx, pts, s, spec, key_of)
    if s.get("footprint", True):
        cov = pa.total_covariance(cov, pa.footprint_covariance(pts, sensors, spec))
    return cov


def covariance_matrices(cloud, index: Optional[np.ndarray], settings: Mapping[str, Any], **kw):
    """:func:`covariances` as an (n, 3, 3) array (m²) whatever the model, for writing
    SigmaX/Y/Z or the six covariance entries (the accuracy job)."""
    cov = np.asarray(covariances(cloud, index, settings, **kw), dtype=np.float64)
    n = len(cloud) if index is None else int(np.asarray(index).size)
    if cov.ndim == 0:
        return np.broadcast_to(np.eye(3) * float(cov) ** 2, (n, 3, 3))
    if cov.ndim == 1:
        return np.broadcast_to(np.diag(cov**2), (n, 3, 3))
    if cov.ndim == 2:  # (n, 3) per-point sigmas
        return cov[:, :, None] ** 2 * np.eye(3)
    return cov


def _read_table(reader, path, where):
    """A trajectory (accuracy) file; read errors as an OptionError naming its option."""
    from ..core.errors import SlipMapError

    key, head = where
    try:
        return reader(path)
    except SlipMapError as exc:
        raise OptionError(key, f"{head}{exc}") from exc


def _propagated_mobile(cloud, idx, pts, s, spec, key_of):
    import pyproj

    from ..core import accuracy as pa
    from ..core.errors import InputDataError
    from ..core.io.trajectory import read_trajectory, read_trajectory_accuracy

    if "GpsTime" not in cloud.attributes:
        raise InputDataError(
            f"{cloud.source}: no GpsTime dimension; the propagated model interpolates the "
            "trajectory at each point's GPS time (a static scan needs the scanner position "
            "instead)"
        )
    t = np.asarray(cloud.attributes["GpsTime"], dtype=np.float64)[idx]
    traj = _read_table(read_trajectory, s["trajectory"], key_of("trajectory")).interpolate(t)
    acc = _read_table(
        read_trajectory_accuracy, s["trajectory_accuracy"], key_of("trajectory_accuracy")
    ).interpolate(t)
    if traj.get("xyz") is not None:
        platform = np.asarray(traj["xyz"], dtype=np.float64)
    else:
        if cloud.crs is None:
            raise InputDataError(
                f"{cloud.source}: the file has no CRS, so the geodetic trajectory cannot be "
                "put in the points' frame; give the point cloud's CRS"
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
