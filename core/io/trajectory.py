"""Platform trajectories (SBET) and their accuracy (SMRMSG), binary or text.

Binary layouts (as read by PDAL's ``readers.sbet`` and ``readers.smrmsg``), little-endian
float64, no header:

* SBET, 17 values (136 bytes) per record: GPS time (s), latitude, longitude (rad), altitude
  (m), x/y/z velocity (m/s), roll, pitch, platform heading, wander angle (rad), x/y/z body
  acceleration (m/s²), x/y/z body angular rate (rad/s).
* SMRMSG, 10 values (80 bytes) per record: GPS time (s), north/east/down position RMS (m),
  north/east/down velocity RMS (m/s), roll/pitch/heading RMS (arc-minutes).

Inside SlipMap everything is SI: seconds, metres, radians. Attitude RMS read in arc-minutes
is converted to radians by the binary and the text readers alike.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from ..errors import InputDataError, InvalidParameterError, SlipMapFileError
from .atomic import PathLike

logger = logging.getLogger(__name__)

__all__ = [
    "SBET_FIELDS",
    "SMRMSG_FIELDS",
    "Trajectory",
    "TrajectoryAccuracy",
    "read_accuracy_csv",
    "read_sbet",
    "read_smrmsg",
    "read_trajectory",
    "read_trajectory_accuracy",
    "read_trajectory_csv",
]

#: Field names of one SBET record, in file order.
SBET_FIELDS: Tuple[str, ...] = (
    "time",
    "latitude",
    "longitude",
    "altitude",
    "x_velocity",
    "y_velocity",
    "z_velocity",
    "roll",
    "pitch",
    "heading",
    "wander",
    "x_acceleration",
    "y_acceleration",
    "z_acceleration",
    "x_angular_rate",
    "y_angular_rate",
    "z_angular_rate",
)

#: Field names of one SMRMSG record, in file order.
SMRMSG_FIELDS: Tuple[str, ...] = (
    "time",
    "north_position_rms",
    "east_position_rms",
    "down_position_rms",
    "north_velocity_rms",
    "east_velocity_rms",
    "down_velocity_rms",
    "roll_rms",
    "pitch_rms",
    "heading_rms",
)

_SBET_RECORD_BYTES = 8 * len(SBET_FIELDS)  # 136
_SMRMSG_RECORD_BYTES = 8 * len(SMRMSG_FIELDS)  # 80

#: Radians per unit for the angle units the readers accept.
_ANGLE_UNITS: Dict[str, float] = {
    "rad": 1.0,
    "deg": math.pi / 180.0,
    "arcmin": math.pi / (180.0 * 60.0),
    "arcsec": math.pi / (180.0 * 3600.0),
}

_TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------- helpers


def _angle_factor(angle_units: str, allowed: Sequence[str]) -> float:
    """Radians per ``angle_units``; InvalidParameterError for a unit not in ``allowed``."""
    unit = str(angle_units).strip().lower()
    if unit not in allowed:
        raise InvalidParameterError(
            f"angle_units={angle_units!r} is not supported; use one of {', '.join(allowed)}"
        )
    return _ANGLE_UNITS[unit]


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi) (radians)."""
    return (a + math.pi) % _TWO_PI - math.pi


def _check_time(time_s: np.ndarray, what: str) -> np.ndarray:
    """Validate a (M,) strictly increasing, finite time column; return it as float64."""
    t = np.asarray(time_s, dtype=np.float64)
    if t.ndim != 1:
        raise InputDataError(f"{what}: time must be one-dimensional, got shape {t.shape}")
    if t.size == 0:
        raise InputDataError(f"{what}: no records")
    if not np.all(np.isfinite(t)):
        raise InputDataError(f"{what}: time holds NaN or infinite values")
    if t.size > 1:
        d = np.diff(t)
        bad = np.flatnonzero(d <= 0)
        if bad.size:
            i = int(bad[0])
            raise InputDataError(
                f"{what}: time must be strictly increasing, but record {i + 1} "
                f"({t[i + 1]!r} s) does not follow record {i} ({t[i]!r} s); "
                f"{bad.size} such step(s)"
            )
    return t


def _column(values: Any, m: int, name: str, what: str) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64)
    if a.shape != (m,):
        raise InputDataError(f"{what}: {name} has shape {a.shape}, expected ({m},)")
    return a


def _query_times(gps_time: Any, t: np.ndarray, what: str) -> np.ndarray:
    """GPS times as float64 (1-D view of any shape), all within ``t``'s span."""
    q = np.asarray(gps_time, dtype=np.float64)
    if q.size == 0:
        return q
    if not np.all(np.isfinite(q)):
        raise InputDataError(f"GpsTime holds NaN or infinite values; cannot interpolate {what}")
    t0, t1 = float(t[0]), float(t[-1])
    outside = (q < t0) | (q > t1)
    n = int(np.count_nonzero(outside))
    if n:
        raise InputDataError(
            f"GpsTime {float(q.min()):.3f}–{float(q.max()):.3f} s outside the {what}'s span "
            f"{t0:.3f}–{t1:.3f} s ({n} points outside); check that the point cloud and the "
            f"{what} are from the same flight and use the same GPS time convention "
            "(GPS week seconds vs adjusted standard GPS time)"
        )
    return q


def _interp(q: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    if t.size == 1:  # a single record: every in-span query time is that record's time
        return np.full(q.shape, v[0], dtype=np.float64)
    return np.interp(q.ravel(), t, v).reshape(q.shape)


def _interp_angle(q: np.ndarray, t: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Linear interpolation of an angle (rad) along its unwrapped series, wrapped to [-pi, pi)."""
    return _wrap(_interp(q, t, np.unwrap(a)))


def _check_path(path: PathLike) -> Path:
    p = Path(os.fspath(path))
    if not p.exists():
        raise SlipMapFileError(f"trajectory file {str(p)!r} does not exist")
    if not p.is_file():
        raise SlipMapFileError(f"trajectory file {str(p)!r} is not a regular file")
    return p


def _read_records(path: PathLike, nfields: int, kind: str) -> Tuple[Path, np.ndarray]:
    """(path, (M, nfields) float64) from a headerless little-endian float64 file."""
    p = _check_path(path)
    record = 8 * nfields
    try:
        size = p.stat().st_size
    except OSError as exc:
        raise SlipMapFileError(f"cannot read {kind} file {str(p)!r}: {exc}") from exc
    if size == 0:
        raise SlipMapFileError(f"{kind} file {str(p)!r} is empty (0 bytes)")
    if size % record:
        raise SlipMapFileError(
            f"{kind} file {str(p)!r} is truncated or not a {kind} file: {size} bytes is not a "
            f"multiple of the {record}-byte record ({nfields} float64 values); "
            f"{size // record} whole record(s) and {size % record} extra byte(s)"
        )
    try:
        data = np.fromfile(p, dtype="<f8")
    except (OSError, ValueError) as exc:
        raise SlipMapFileError(f"cannot read {kind} file {str(p)!r}: {exc}") from exc
    if data.size * 8 != size:
        raise SlipMapFileError(
            f"{kind} file {str(p)!r}: read {data.size * 8} of {size} bytes; the file changed "
            "or could not be read completely"
        )
    data = data.reshape(-1, nfields).astype(np.float64, copy=False)
    logger.debug("read %d %s records from %s", data.shape[0], kind, p)
    return p, data


# --------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Platform position and attitude against GPS time.

    Position is geodetic (``lat_rad``, ``lon_rad``, ``height_m``), projected (``xyz``), or
    both; at least one of the two must be given.

    Attributes
    ----------
    time_s : numpy.ndarray
        (M,) GPS time of each record, seconds, strictly increasing.
    lat_rad, lon_rad : numpy.ndarray or None
        (M,) geodetic latitude and longitude, radians.
    height_m : numpy.ndarray or None
        (M,) ellipsoidal height (SBET altitude), metres.
    roll_rad, pitch_rad, heading_rad : numpy.ndarray
        (M,) attitude, radians. SBET heading is the platform heading.
    wander_rad : numpy.ndarray or None
        (M,) wander angle, radians (SBET only).
    xyz : numpy.ndarray or None
        (M, 3) projected coordinates (metres), when the source gave them.
    source : str or None
        The file the trajectory was read from, for messages.
    """

    time_s: np.ndarray
    lat_rad: Optional[np.ndarray]
    lon_rad: Optional[np.ndarray]
    height_m: Optional[np.ndarray]
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    heading_rad: np.ndarray
    wander_rad: Optional[np.ndarray] = None
    xyz: Optional[np.ndarray] = None
    source: Optional[str] = None

    def __post_init__(self) -> None:
        what = f"trajectory {self.source!r}" if self.source else "trajectory"
        t = _check_time(self.time_s, what)
        m = t.size
        object.__setattr__(self, "time_s", t)
        geo = (self.lat_rad, self.lon_rad, self.height_m)
        if any(g is not None for g in geo) and any(g is None for g in geo):
            raise InputDataError(f"{what}: give all of latitude, longitude and height, or none")
        if self.lat_rad is None and self.xyz is None:
            raise InputDataError(f"{what}: needs a position (latitude/longitude/height or x/y/z)")
        for name in (
            "lat_rad",
            "lon_rad",
            "height_m",
            "roll_rad",
            "pitch_rad",
            "heading_rad",
            "wander_rad",
        ):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, _column(v, m, name, what))
        if self.xyz is not None:
            xyz = np.asarray(self.xyz, dtype=np.float64)
            if xyz.shape != (m, 3):
                raise InputDataError(f"{what}: xyz has shape {xyz.shape}, expected ({m}, 3)")
            object.__setattr__(self, "xyz", xyz)

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def span_s(self) -> Tuple[float, float]:
        """(first, last) GPS time, seconds."""
        return float(self.time_s[0]), float(self.time_s[-1])

    def interpolate(self, gps_time: Any) -> Dict[str, np.ndarray]:
        """Position and attitude at ``gps_time`` (linear in time; angles along the short way).

        Parameters
        ----------
        gps_time : array_like
            GPS times, seconds (any shape), all within :attr:`span_s`.

        Returns
        -------
        dict of str to numpy.ndarray
            ``time_s``, ``roll_rad``, ``pitch_rad``, ``heading_rad`` (radians, wrapped to
            [-pi, pi)), and where the trajectory has them ``lat_rad``, ``lon_rad``,
            ``height_m``, ``wander_rad`` (same shape as ``gps_time``) and ``xyz``
            (shape + (3,), metres).

        Raises
        ------
        InputDataError
            If a time is NaN or outside the trajectory's span (the message gives both spans
            and the number of points outside).
        """
        t = self.time_s
        q = _query_times(gps_time, t, "trajectory")
        out: Dict[str, np.ndarray] = {"time_s": q.copy()}
        if self.lat_rad is not None:
            out["lat_rad"] = _interp(q, t, self.lat_rad)
            out["lon_rad"] = _interp_angle(q, t, self.lon_rad)
            out["height_m"] = _interp(q, t, self.height_m)
        if self.xyz is not None:
            out["xyz"] = np.stack([_interp(q, t, self.xyz[:, k]) for k in range(3)], axis=-1)
        out["roll_rad"] = _interp_angle(q, t, self.roll_rad)
        out["pitch_rad"] = _interp_angle(q, t, self.pitch_rad)
        out["heading_rad"] = _interp_angle(q, t, self.heading_rad)
        if self.wander_rad is not None:
            out["wander_rad"] = _interp_angle(q, t, self.wander_rad)
        return out


@dataclass(frozen=True, eq=False)
class TrajectoryAccuracy:
    """Trajectory RMS (1 sigma) against GPS time, SI units.

    Attributes
    ----------
    time_s : numpy.ndarray
        (M,) GPS time, seconds, strictly increasing.
    north_m, east_m, down_m : numpy.ndarray
        (M,) position RMS, metres.
    roll_rad, pitch_rad, heading_rad : numpy.ndarray
        (M,) attitude RMS, radians (SMRMSG stores arc-minutes).
    velocity_ned_mps : numpy.ndarray or None
        (M, 3) north/east/down velocity RMS, m/s, when the source has it.
    source : str or None
        The file it was read from, for messages.
    """

    time_s: np.ndarray
    north_m: np.ndarray
    east_m: np.ndarray
    down_m: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    heading_rad: np.ndarray
    velocity_ned_mps: Optional[np.ndarray] = None
    source: Optional[str] = None

    _COLUMNS = ("north_m", "east_m", "down_m", "roll_rad", "pitch_rad", "heading_rad")

    def __post_init__(self) -> None:
        what = f"trajectory accuracy {self.source!r}" if self.source else "trajectory accuracy"
        t = _check_time(self.time_s, what)
        m = t.size
        object.__setattr__(self, "time_s", t)
        for name in self._COLUMNS:
            object.__setattr__(self, name, _column(getattr(self, name), m, name, what))
        if self.velocity_ned_mps is not None:
            v = np.asarray(self.velocity_ned_mps, dtype=np.float64)
            if v.shape != (m, 3):
                raise InputDataError(
                    f"{what}: velocity_ned_mps has shape {v.shape}, expected ({m}, 3)"
                )
            object.__setattr__(self, "velocity_ned_mps", v)

    def __len__(self) -> int:
        return int(self.time_s.size)

    @property
    def span_s(self) -> Tuple[float, float]:
        """(first, last) GPS time, seconds."""
        return float(self.time_s[0]), float(self.time_s[-1])

    def interpolate(self, gps_time: Any) -> Dict[str, np.ndarray]:
        """RMS values at ``gps_time``, linear in time.

        Parameters
        ----------
        gps_time : array_like
            GPS times, seconds (any shape), all within :attr:`span_s`.

        Returns
        -------
        dict of str to numpy.ndarray
            ``time_s``, ``north_m``, ``east_m``, ``down_m`` (metres), ``roll_rad``,
            ``pitch_rad``, ``heading_rad`` (radians), each the shape of ``gps_time``, and
            ``velocity_ned_mps`` (shape + (3,), m/s) where available.

        Raises
        ------
        InputDataError
            If a time is NaN or outside the span (the message gives both spans).
        """
        t = self.time_s
        q = _query_times(gps_time, t, "trajectory accuracy")
        out: Dict[str, np.ndarray] = {"time_s": q.copy()}
        for name in self._COLUMNS:
            out[name] = _interp(q, t, getattr(self, name))
        if self.velocity_ned_mps is not None:
            v = self.velocity_ned_mps
            out["velocity_ned_mps"] = np.stack([_interp(q, t, v[:, k]) for k in range(3)], -1)
        return out


# --------------------------------------------------------------------------- binary readers


def read_sbet(path: PathLike) -> Trajectory:
    """Read a binary SBET (POSPac smoothed best estimate of trajectory) file.

    Parameters
    ----------
    path : str or os.PathLike
        The file: headerless little-endian float64, 17 values (136 bytes) per record.

    Returns
    -------
    Trajectory
        Geodetic position (radians, metres), roll/pitch/heading and wander angle (radians).

    Raises
    ------
    SlipMapFileError
        If the file is missing, empty, or its size is not a whole number of records.
    InputDataError
        If the times are not strictly increasing or not finite.
    """
    p, d = _read_records(path, len(SBET_FIELDS), "SBET")
    return Trajectory(
        time_s=d[:, 0],
        lat_rad=d[:, 1],
        lon_rad=d[:, 2],
        height_m=d[:, 3],
        roll_rad=d[:, 7],
        pitch_rad=d[:, 8],
        heading_rad=d[:, 9],
        wander_rad=d[:, 10],
        source=str(p),
    )


def read_smrmsg(path: PathLike) -> TrajectoryAccuracy:
    """Read a binary SMRMSG (POSPac smoothed RMS) accuracy file.

    Parameters
    ----------
    path : str or os.PathLike
        The file: headerless little-endian float64, 10 values (80 bytes) per record; attitude
        RMS in arc-minutes.

    Returns
    -------
    TrajectoryAccuracy
        Position RMS (metres), velocity RMS (m/s) and attitude RMS converted to radians.

    Raises
    ------
    SlipMapFileError
        If the file is missing, empty, or its size is not a whole number of records.
    InputDataError
        If the times are not strictly increasing or not finite.
    """
    p, d = _read_records(path, len(SMRMSG_FIELDS), "SMRMSG")
    k = _ANGLE_UNITS["arcmin"]
    return TrajectoryAccuracy(
        time_s=d[:, 0],
        north_m=d[:, 1],
        east_m=d[:, 2],
        down_m=d[:, 3],
        roll_rad=d[:, 7] * k,
        pitch_rad=d[:, 8] * k,
        heading_rad=d[:, 9] * k,
        velocity_ned_mps=d[:, 4:7],
        source=str(p),
    )


# --------------------------------------------------------------------------- text readers


def _norm(name: str) -> str:
    """Header name reduced to lower-case letters and digits (``"Gps_Time"`` -> ``"gpstime"``)."""
    return re.sub(r"[^a-z0-9]", "", name.strip().strip("\"'").lower())


_TRAJ_ALIASES: Dict[str, Tuple[str, ...]] = {
    "time": ("time", "gpstime", "times", "t", "timestamp", "gpstimes", "sow"),
    "x": ("x", "easting", "xm"),
    "y": ("y", "northing", "ym"),
    "z": ("z", "elevation", "zm"),
    "lat": ("lat", "latitude", "latdeg", "latrad"),
    "lon": ("lon", "long", "longitude", "londeg", "lonrad"),
    "height": ("height", "h", "alt", "altitude", "ellipsoidheight", "heightm", "ellheight"),
    "roll": ("roll", "rolldeg", "rollrad"),
    "pitch": ("pitch", "pitchdeg", "pitchrad"),
    "heading": ("heading", "yaw", "headingdeg", "headingrad", "platformheading"),
    "wander": ("wander", "wanderangle", "wanderdeg", "wanderrad"),
}

_ACC_ALIASES: Dict[str, Tuple[str, ...]] = {
    "time": ("time", "gpstime", "times", "t", "timestamp"),
    "north": ("northpositionrms", "northrms", "north", "northm", "sigmanorth"),
    "east": ("eastpositionrms", "eastrms", "east", "eastm", "sigmaeast"),
    "down": ("downpositionrms", "downrms", "down", "downm", "sigmadown"),
    "north_vel": ("northvelocityrms", "northvelrms"),
    "east_vel": ("eastvelocityrms", "eastvelrms"),
    "down_vel": ("downvelocityrms", "downvelrms"),
    "roll": ("rollrms", "roll", "sigmaroll"),
    "pitch": ("pitchrms", "pitch", "sigmapitch"),
    "heading": ("headingrms", "heading", "yawrms", "sigmaheading"),
}


def _read_table(path: PathLike, kind: str) -> Tuple[Path, List[str], np.ndarray]:
    """(path, header names, (M, K) float64) of a delimited text file with one header line.

    The delimiter (comma, semicolon, tab or whitespace) is taken from the header line; names
    may be quoted. Lines starting with ``#`` and blank lines are skipped.
    """
    p = _check_path(path)
    try:
        with open(p, newline="", encoding="utf-8-sig") as fh:
            lines = [ln for ln in fh if ln.strip() and not ln.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise SlipMapFileError(f"cannot read {kind} file {str(p)!r}: {exc}") from exc
    if not lines:
        raise SlipMapFileError(f"{kind} file {str(p)!r} is empty")
    head = lines[0]
    delim = next((d for d in (",", ";", "\t") if d in head), None)
    if delim is None:
        rows = [ln.split() for ln in lines]
    else:
        rows = [[c.strip() for c in r] for r in csv.reader(lines, delimiter=delim)]
    names = [c.strip().strip("\"'") for c in rows[0]]
    body = rows[1:]
    if not body:
        raise SlipMapFileError(f"{kind} file {str(p)!r} has a header but no records")
    k = len(names)
    for i, r in enumerate(body):
        if len(r) != k:
            raise SlipMapFileError(
                f"{kind} file {str(p)!r}: line {i + 2} has {len(r)} values, the header {k}"
            )
    try:
        data = np.array(body, dtype=np.float64)
    except ValueError as exc:
        raise SlipMapFileError(
            f"{kind} file {str(p)!r} holds a value that is not a number: {exc}"
        ) from exc
    return p, names, data


def _find_columns(
    names: Sequence[str],
    aliases: Mapping[str, Sequence[str]],
    columns: Optional[Mapping[str, str]],
    p: Path,
    kind: str,
) -> Dict[str, int]:
    """Map each canonical key to a column index: explicit ``columns`` first, then aliases."""
    normed = [_norm(n) for n in names]
    found: Dict[str, int] = {}
    for key, name in (columns or {}).items():
        if key not in aliases:
            raise InvalidParameterError(
                f"columns: unknown key {key!r}; known keys are {', '.join(aliases)}"
            )
        if name in names:
            found[key] = names.index(name)
        elif _norm(name) in normed:
            found[key] = normed.index(_norm(name))
        else:
            raise InvalidParameterError(
                f"columns: {kind} file {str(p)!r} has no column {name!r} (for {key!r}); "
                f"its columns are {', '.join(names)}"
            )
    for key, alias in aliases.items():
        if key in found:
            continue
        for a in alias:
            if a in normed and normed.index(a) not in found.values():
                found[key] = normed.index(a)
                break
    return found


def read_trajectory_csv(
    path: PathLike,
    *,
    columns: Optional[Mapping[str, str]] = None,
    angle_units: str = "deg",
) -> Trajectory:
    """Read a trajectory from a delimited text file with a header line.

    Parameters
    ----------
    path : str or os.PathLike
        Text file; comma, semicolon, tab or whitespace separated; one header line.
    columns : mapping of str to str, optional
        Column names in the file for the keys ``time``, ``x``, ``y``, ``z`` (projected,
        metres) or ``lat``, ``lon``, ``height`` (geodetic; angles in ``angle_units``,
        height in metres), ``roll``, ``pitch``, ``heading`` and optionally ``wander``.
        Keys not given are found by common names (``GpsTime``, ``Easting``, ``Latitude``,
        ``Yaw``, ...), case-insensitively.
    angle_units : {"deg", "rad"}
        Units of the attitude (and latitude/longitude) columns.

    Returns
    -------
    Trajectory
        In seconds, metres and radians.

    Raises
    ------
    InvalidParameterError
        For an unknown angle unit or a ``columns`` entry the file does not have.
    SlipMapFileError
        If the file is missing, empty, ragged, non-numeric, or lacks required columns.
    InputDataError
        If the times are not strictly increasing.
    """
    k = _angle_factor(angle_units, ("deg", "rad"))
    p, names, d = _read_table(path, "trajectory")
    idx = _find_columns(names, _TRAJ_ALIASES, columns, p, "trajectory")
    has_xyz = all(c in idx for c in ("x", "y", "z"))
    has_geo = all(c in idx for c in ("lat", "lon", "height"))
    missing = [c for c in ("time", "roll", "pitch", "heading") if c not in idx]
    if not (has_xyz or has_geo):
        missing.append("x/y/z or lat/lon/height")
    if missing:
        raise SlipMapFileError(
            f"trajectory file {str(p)!r} lacks column(s) for {', '.join(missing)}; its "
            f"columns are {', '.join(names)} (name them with the columns option)"
        )

    def col(key: str) -> np.ndarray:
        return d[:, idx[key]]

    return Trajectory(
        time_s=col("time"),
        lat_rad=col("lat") * k if has_geo else None,
        lon_rad=col("lon") * k if has_geo else None,
        height_m=col("height") if has_geo else None,
        roll_rad=col("roll") * k,
        pitch_rad=col("pitch") * k,
        heading_rad=col("heading") * k,
        wander_rad=col("wander") * k if "wander" in idx else None,
        xyz=np.column_stack([col("x"), col("y"), col("z")]) if has_xyz else None,
        source=str(p),
    )


def read_accuracy_csv(
    path: PathLike,
    *,
    columns: Optional[Mapping[str, str]] = None,
    angle_units: str = "arcmin",
) -> TrajectoryAccuracy:
    """Read trajectory accuracy (RMS) from a delimited text file with a header line.

    Reads the text export of an SMRMSG file (header ``GpsTime``, ``NorthPositionRMS``,
    ``EastPositionRMS``, ``DownPositionRMS``, ``North/East/DownVelocityRMS``, ``RollRMS``,
    ``PitchRMS``, ``HeadingRMS``) as well as simpler tables.

    Parameters
    ----------
    path : str or os.PathLike
        Text file; comma, semicolon, tab or whitespace separated; one header line.
    columns : mapping of str to str, optional
        Column names for the keys ``time``, ``north``, ``east``, ``down`` (metres), ``roll``,
        ``pitch``, ``heading`` (``angle_units``) and optionally ``north_vel``, ``east_vel``,
        ``down_vel`` (m/s); others are found by common names.
    angle_units : {"arcmin", "arcsec", "deg", "rad"}
        Units of the attitude RMS columns (SMRMSG: arc-minutes).

    Returns
    -------
    TrajectoryAccuracy
        In seconds, metres, m/s and radians.

    Raises
    ------
    InvalidParameterError
        For an unknown angle unit or a ``columns`` entry the file does not have.
    SlipMapFileError
        If the file is missing, empty, ragged, non-numeric, or lacks required columns.
    InputDataError
        If the times are not strictly increasing.
    """
    k = _angle_factor(angle_units, ("arcmin", "arcsec", "deg", "rad"))
    p, names, d = _read_table(path, "trajectory accuracy")
    idx = _find_columns(names, _ACC_ALIASES, columns, p, "trajectory accuracy")
    required = ("time", "north", "east", "down", "roll", "pitch", "heading")
    missing = [c for c in required if c not in idx]
    if missing:
        raise SlipMapFileError(
            f"trajectory accuracy file {str(p)!r} lacks column(s) for {', '.join(missing)}; "
            f"its columns are {', '.join(names)} (name them with the columns option)"
        )
    vel_keys = ("north_vel", "east_vel", "down_vel")
    vel = d[:, [idx[c] for c in vel_keys]] if all(c in idx for c in vel_keys) else None
    return TrajectoryAccuracy(
        time_s=d[:, idx["time"]],
        north_m=d[:, idx["north"]],
        east_m=d[:, idx["east"]],
        down_m=d[:, idx["down"]],
        roll_rad=d[:, idx["roll"]] * k,
        pitch_rad=d[:, idx["pitch"]] * k,
        heading_rad=d[:, idx["heading"]] * k,
        velocity_ned_mps=vel,
        source=str(p),
    )


# --------------------------------------------------------------------------- dispatch

_SBET_EXT = (".sbet", ".out", ".bin")
_SMRMSG_EXT = (".smrmsg", ".out", ".bin")
_TEXT_EXT = (".csv", ".txt")


def _no_options(kw: Mapping[str, Any], fmt: str, p: Path) -> None:
    if kw:
        raise InvalidParameterError(
            f"{', '.join(sorted(kw))}: option(s) apply to text files only, not the {fmt} "
            f"file {str(p)!r}"
        )


def read_trajectory(path: PathLike, **kw: Any) -> Trajectory:
    """Read a trajectory, choosing the reader by file extension.

    ``.sbet``, ``.out``, ``.bin``: :func:`read_sbet`; ``.csv``, ``.txt``:
    :func:`read_trajectory_csv` (``kw`` are passed on to it).

    Raises
    ------
    InvalidParameterError
        For an unsupported extension, or options given for a binary file.
    """
    p = Path(os.fspath(path))
    ext = p.suffix.lower()
    if ext in _SBET_EXT:
        _no_options(kw, "SBET", p)
        return read_sbet(p)
    if ext in _TEXT_EXT:
        return read_trajectory_csv(p, **kw)
    raise InvalidParameterError(
        f"trajectory file {str(p)!r}: unknown extension {ext!r}; use "
        f"{', '.join(_SBET_EXT)} (SBET) or {', '.join(_TEXT_EXT)} (text)"
    )


def read_trajectory_accuracy(path: PathLike, **kw: Any) -> TrajectoryAccuracy:
    """Read trajectory accuracy, choosing the reader by file extension.

    ``.smrmsg``, ``.out``, ``.bin``: :func:`read_smrmsg`; ``.csv``, ``.txt``:
    :func:`read_accuracy_csv` (``kw`` are passed on to it).

    Raises
    ------
    InvalidParameterError
        For an unsupported extension, or options given for a binary file.
    """
    p = Path(os.fspath(path))
    ext = p.suffix.lower()
    if ext in _SMRMSG_EXT:
        _no_options(kw, "SMRMSG", p)
        return read_smrmsg(p)
    if ext in _TEXT_EXT:
        return read_accuracy_csv(p, **kw)
    raise InvalidParameterError(
        f"trajectory accuracy file {str(p)!r}: unknown extension {ext!r}; use "
        f"{', '.join(_SMRMSG_EXT)} (SMRMSG) or {', '.join(_TEXT_EXT)} (text)"
    )
