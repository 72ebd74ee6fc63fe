"""LAS/LAZ point clouds (laspy + lazrs): read, read in chunks, read the header, write.

Points come out as an ``(N, 3)`` float64 array of map coordinates (the file's scaled
integers) plus a dictionary of per-point attributes under PDAL's dimension names
(``Classification``, ``GpsTime``, ``ScanAngle``, ...; extra-bytes dimensions by their own
names). The laspy record is kept inside the :class:`PointCloud`, so :func:`write_las` can write
every original dimension, the header and the VLRs back, with new dimensions added.

Units are those of the file's CRS (often metres, sometimes feet: see
:func:`slipmap.core.io.crs.crs_units`); ``ScanAngle`` is in degrees.
"""

from __future__ import annotations

import copy
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import (
    TYPE_CHECKING,
    Any,
    Dict,
    Iterable,
    Iterator,
    List,
    Mapping,
    Sequence,
    Tuple,
    Union,
)

try:
    import laspy
except ImportError:  # PDAL's Python may lack it: PointCloud itself works without laspy
    laspy = None
import numpy as np

from ..errors import DependencyError, InvalidParameterError, SlipMapError, SlipMapFileError
from .atomic import atomic_path, check_not_input, ensure_output_dir
from .crs import crs_from_las, parse_crs, same_crs

if TYPE_CHECKING:  # pragma: no cover
    import pyproj

logger = logging.getLogger(__name__)

PathLike = Union[str, "os.PathLike[str]"]

__all__ = [
    "DEFAULT_ATTRIBUTES",
    "LasHeaderInfo",
    "PointCloud",
    "available_attributes",
    "iter_las_chunks",
    "read_las",
    "read_las_header",
    "write_las",
    "write_las_chunked",
]

#: PDAL dimension name -> (laspy dimension name, dtype of the attribute array).
_STANDARD: Dict[str, Tuple[str, np.dtype[Any]]] = {
    "Intensity": ("intensity", np.dtype(np.uint16)),
    "ReturnNumber": ("return_number", np.dtype(np.uint8)),
    "NumberOfReturns": ("number_of_returns", np.dtype(np.uint8)),
    "ScanDirectionFlag": ("scan_direction_flag", np.dtype(np.uint8)),
    "EdgeOfFlightLine": ("edge_of_flight_line", np.dtype(np.uint8)),
    "Classification": ("classification", np.dtype(np.uint8)),
    "Synthetic": ("synthetic", np.dtype(np.uint8)),
    "KeyPoint": ("key_point", np.dtype(np.uint8)),
    "Withheld": ("withheld", np.dtype(np.uint8)),
    "Overlap": ("overlap", np.dtype(np.uint8)),
    "ScanChannel": ("scanner_channel", np.dtype(np.uint8)),
    "ScanAngleRank": ("scan_angle_rank", np.dtype(np.int8)),
    "UserData": ("user_data", np.dtype(np.uint8)),
    "PointSourceId": ("point_source_id", np.dtype(np.uint16)),
    "GpsTime": ("gps_time", np.dtype(np.float64)),
    "Red": ("red", np.dtype(np.uint16)),
    "Green": ("green", np.dtype(np.uint16)),
    "Blue": ("blue", np.dtype(np.uint16)),
    "Infrared": ("nir", np.dtype(np.uint16)),
}
_LASPY_TO_PDAL = {lname: pname for pname, (lname, _) in _STANDARD.items()}

#: Attributes :func:`read_las` returns by default (those the file has), before the extra dims.
DEFAULT_ATTRIBUTES: Tuple[str, ...] = (
    "Classification",
    "GpsTime",
    "ScanAngle",
    "ScanAngleRank",
    "Intensity",
    "ReturnNumber",
    "NumberOfReturns",
    "PointSourceId",
)

#: Unit of the raw ``scan_angle`` field of point formats 6-10, in degrees.
SCAN_ANGLE_STEP_DEG = 0.006

_COORDS = ("X", "Y", "Z", "x", "y", "z")
_NEW_DIM_KINDS = "iuf"
_WRITE_BATCH = 1_000_000
_INT32 = np.iinfo(np.int32)


# --------------------------------------------------------------------------------------------
# data classes


@dataclass
class LasHeaderInfo:
    """What SlipMap needs from a LAS header (the file's values, not a subset's).

    Attributes
    ----------
    version : str
        LAS version, e.g. ``"1.2"``.
    point_format : int
        Point data record format id (0-10).
    scales, offsets : numpy.ndarray
        ``(3,)`` float64; stored integer ``X = round((x - offset) / scale)``.
    n_points : int
        Number of points in the file.
    mins, maxs : numpy.ndarray
        ``(3,)`` float64 bounding box recorded in the header (CRS units).
    """

    version: str
    point_format: int
    scales: np.ndarray
    offsets: np.ndarray
    n_points: int
    mins: np.ndarray
    maxs: np.ndarray


@dataclass(eq=False)
class PointCloud:
    """A point cloud: coordinates, per-point attributes, CRS and the header it came from.

    Attributes
    ----------
    xyz : numpy.ndarray
        ``(N, 3)`` float64, C-contiguous map coordinates (CRS units).
    attributes : dict of str to numpy.ndarray
        Per-point arrays of length ``N`` under PDAL dimension names (see :func:`read_las`).
    crs : pyproj.CRS or None
        ``None`` when the file has no usable CRS.
    header : LasHeaderInfo or None
        The source file's header (``None`` for a cloud made in memory).
    source : pathlib.Path or None
        The file the points were read from.

    Notes
    -----
    The laspy record (``_las``) is kept privately so that :func:`write_las` can write every
    original dimension, the header and the VLRs back.
    """

    xyz: np.ndarray
    attributes: Dict[str, np.ndarray] = field(default_factory=dict)
    crs: pyproj.CRS | None = None
    header: LasHeaderInfo | None = None
    source: Path | None = None
    _las: laspy.LasData | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        xyz = np.asarray(self.xyz, dtype=np.float64)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise InvalidParameterError(f"xyz must have shape (N, 3); got {xyz.shape}")
        self.xyz = np.ascontiguousarray(xyz)
        n = xyz.shape[0]
        attrs: Dict[str, np.ndarray] = {}
        for name, values in dict(self.attributes or {}).items():
            arr = np.asarray(values)
            if arr.ndim == 0 or arr.shape[0] != n:
                raise InvalidParameterError(
                    f"attribute {name!r} has shape {arr.shape}; the cloud has {n} points"
                )
            attrs[str(name)] = arr
        self.attributes = attrs
        if self.source is not None:
            self.source = Path(self.source)
        if self._las is not None and len(self._las) != n:
            raise InvalidParameterError(
                f"the LAS record has {len(self._las)} points but xyz has {n}"
            )

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    def subset(self, mask_or_index: Any) -> PointCloud:
        """A new cloud with the selected points (in the order given); ``self`` is unchanged.

        Parameters
        ----------
        mask_or_index : array_like or slice
            A boolean mask of shape ``(N,)``, a 1-D array of integer indices, or a slice.

        Returns
        -------
        PointCloud
            Copies of the selected coordinates, attributes and LAS record; the same header,
            CRS and source.
        """
        idx = _as_index(mask_or_index, len(self))
        las = None
        if self._las is not None:
            las = laspy.LasData(copy.deepcopy(self._las.header), points=self._las.points[idx])
        return PointCloud(
            xyz=self.xyz[idx],
            attributes={k: v[idx] for k, v in self.attributes.items()},
            crs=self.crs,
            header=self.header,
            source=self.source,
            _las=las,
        )


def _as_index(selector: Any, n: int) -> np.ndarray:
    """Integer index array (copying selection) from a mask, indices or a slice."""
    if isinstance(selector, slice):
        return np.arange(n)[selector]
    arr = np.asarray(selector)
    if arr.dtype == np.bool_:
        if arr.shape != (n,):
            raise InvalidParameterError(
                f"boolean mask has shape {arr.shape}; the cloud has {n} points, expected ({n},)"
            )
        return np.flatnonzero(arr)
    if arr.ndim != 1:
        raise InvalidParameterError(
            f"subset needs a 1-D boolean mask or index array; got shape {arr.shape}"
        )
    if arr.size == 0:
        return np.zeros(0, dtype=np.intp)
    if arr.dtype.kind not in "iu":
        raise InvalidParameterError(
            f"subset indices must be integers or booleans; got dtype {arr.dtype}"
        )
    if arr.min() < -n or arr.max() >= n:
        raise InvalidParameterError(f"subset index out of range for a cloud of {n} points")
    return arr.astype(np.intp)


# --------------------------------------------------------------------------------------------
# reading


def _input_path(path: PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise SlipMapFileError(f"LAS/LAZ file not found: {p}")
    if not p.is_file():
        raise SlipMapFileError(f"{p} is not a file; expected a LAS/LAZ file")
    return p


def _not_readable(p: Path, exc: BaseException) -> SlipMapError:
    if isinstance(exc, PermissionError):
        return SlipMapFileError(f"cannot read {p}: permission denied")
    msg = str(exc)
    if "LazBackend" in msg and not laspy.LazBackend.detect_available():
        return DependencyError(
            f"reading {p} needs a LAZ backend; install it with: pip install lazrs"
        )
    return SlipMapFileError(f"{p} is not a readable LAS/LAZ file ({type(exc).__name__}: {msg})")


def _require_laspy(what: str) -> None:
    if laspy is None:
        raise DependencyError(
            f"{what} needs the 'laspy' and 'lazrs' packages; install them: "
            "python -m pip install laspy lazrs"
        )


def _open_reader(p: Path) -> laspy.LasReader:
    _require_laspy(f"reading {p}")
    try:
        reader = laspy.open(p, mode="r")
    except Exception as exc:  # laspy raises LaspyException, ValueError, OSError, ...
        raise _not_readable(p, exc) from exc
    scales = np.asarray(reader.header.scales, dtype=np.float64)
    if not np.all(np.isfinite(scales) & (scales > 0)):
        reader.close()
        raise SlipMapFileError(
            f"{p} is not a usable LAS/LAZ file: its header's scale factors "
            f"{scales.tolist()} must be finite and > 0 (coordinates are integer * scale + "
            "offset); rewrite the file with a valid scale (e.g. 0.001)"
        )
    return reader


def _header_info(header: laspy.LasHeader) -> LasHeaderInfo:
    return LasHeaderInfo(
        version=f"{header.version.major}.{header.version.minor}",
        point_format=int(header.point_format.id),
        scales=np.array(header.scales, dtype=np.float64),
        offsets=np.array(header.offsets, dtype=np.float64),
        n_points=int(header.point_count),
        mins=np.array(header.mins, dtype=np.float64),
        maxs=np.array(header.maxs, dtype=np.float64),
    )


def available_attributes(point_format: Union[laspy.PointFormat, int]) -> List[str]:
    """Attribute names :func:`read_las` can return for a point format.

    Parameters
    ----------
    point_format : laspy.PointFormat or int
        The file's point format (with its extra dimensions).

    Returns
    -------
    list of str
        PDAL names of the standard dimensions, ``"ScanAngle"`` (degrees, derived), then the
        extra-bytes dimensions by name.
    """
    _require_laspy("listing a point format's dimensions")
    pf = (
        point_format
        if isinstance(point_format, laspy.PointFormat)
        else laspy.PointFormat(int(point_format))
    )
    std = set(pf.standard_dimension_names)
    names = [pname for pname, (lname, _) in _STANDARD.items() if lname in std]
    names.insert(names.index("Classification") + 1, "ScanAngle")
    names.extend(n for n in pf.extra_dimension_names if n not in names)
    return names


def _resolve_attributes(
    requested: Sequence[str] | None, pf: laspy.PointFormat, where: Path
) -> List[str]:
    available = available_attributes(pf)
    if requested is None:
        names = [n for n in DEFAULT_ATTRIBUTES if n in available]
        names.extend(n for n in pf.extra_dimension_names if n not in names)
        return names
    if isinstance(requested, str):
        requested = [requested]
    names = []
    for name in requested:
        if name in ("X", "Y", "Z"):
            continue  # always read, into xyz
        if name not in available:
            raise InvalidParameterError(
                f"{where}: the file has no point attribute {name!r}; it has: {', '.join(available)}"
            )
        if name not in names:
            names.append(name)
    return names


def _extract(points: laspy.ScaleAwarePointRecord, name: str) -> np.ndarray:
    """One attribute as a new contiguous array."""
    pf = points.point_format
    if name == "ScanAngle":
        if "scan_angle" in set(pf.dimension_names):
            return np.asarray(points["scan_angle"], dtype=np.float64) * SCAN_ANGLE_STEP_DEG
        return np.array(np.asarray(points["scan_angle_rank"]), dtype=np.float64)
    if name in _STANDARD:
        lname, dtype = _STANDARD[name]
        return np.array(np.asarray(points[lname]), dtype=dtype)
    return np.array(np.asarray(points[name]))  # extra bytes (scaled ones as float64)


def _cloud_from_las(
    las: laspy.LasData,
    names: Sequence[str],
    info: LasHeaderInfo,
    crs: pyproj.CRS | None,
    source: Path | None,
) -> PointCloud:
    points = las.points
    n = len(points)
    xyz = np.empty((n, 3), dtype=np.float64)
    xyz[:, 0] = np.asarray(points["x"], dtype=np.float64)
    xyz[:, 1] = np.asarray(points["y"], dtype=np.float64)
    xyz[:, 2] = np.asarray(points["z"], dtype=np.float64)
    attrs = {name: _extract(points, name) for name in names}
    return PointCloud(xyz=xyz, attributes=attrs, crs=crs, header=info, source=source, _las=las)


def read_las_header(path: PathLike) -> Tuple[LasHeaderInfo, pyproj.CRS | None]:
    """Read a LAS/LAZ header and CRS without reading the points.

    Parameters
    ----------
    path : path-like
        LAS or LAZ file.

    Returns
    -------
    header : LasHeaderInfo
    crs : pyproj.CRS or None

    Raises
    ------
    SlipMapFileError
        If the file is missing or not a readable LAS/LAZ file.
    """
    p = _input_path(path)
    with _open_reader(p) as reader:
        header = reader.header
        return _header_info(header), crs_from_las(header, source=p)


def read_las(
    path: PathLike, *, attributes: Sequence[str] | None = None, crs: Any = None
) -> PointCloud:
    """Read a LAS/LAZ file.

    Parameters
    ----------
    path : path-like
        LAS or LAZ file (LAZ decompressed with lazrs).
    attributes : sequence of str, optional
        Attributes to return. ``None`` returns those of :data:`DEFAULT_ATTRIBUTES` the file
        has — ``Classification`` (uint8), ``GpsTime`` (float64 s; absent for point formats 0
        and 2), ``ScanAngle`` (float64 degrees, from ``scan_angle`` for point formats >= 6,
        else from ``scan_angle_rank``), ``ScanAngleRank`` (int8 degrees, point formats < 6),
        ``Intensity`` (uint16), ``ReturnNumber`` and ``NumberOfReturns`` (uint8),
        ``PointSourceId`` (uint16) — plus every extra-bytes dimension by its name. Any other
        standard dimension (``UserData``, ``Withheld``, ``Red``, ...) can be asked for by its
        PDAL name. ``X``/``Y``/``Z`` are always read into ``xyz``.
    crs : pyproj.CRS, str or int, optional
        The CRS the user gave for the file: it replaces the file's own, which is then not
        parsed (no warning about a missing or wrong CRS in the file: the user has answered
        it).

    Returns
    -------
    PointCloud
        ``xyz`` ``(N, 3)`` float64 (the scaled integers, CRS units); a file with no points
        gives ``N = 0``.

    Raises
    ------
    SlipMapFileError
        If the file is missing or not a readable LAS/LAZ file.
    InvalidParameterError
        If an attribute is unknown (the message lists what the file has).
    """
    p = _input_path(path)
    with _open_reader(p) as reader:
        header = reader.header
        names = _resolve_attributes(attributes, header.point_format, p)
        info = _header_info(header)
        crs = crs_from_las(header, source=p) if crs is None else parse_crs(crs)
        try:
            las = reader.read()
        except Exception as exc:
            raise _not_readable(p, exc) from exc
    if len(las.points) != info.n_points:
        raise SlipMapFileError(
            f"{p} is not a readable LAS/LAZ file: the header announces {info.n_points} points "
            f"but {len(las.points)} could be read (truncated file?)"
        )
    cloud = _cloud_from_las(las, names, info, crs, p)
    logger.debug("read %d points from %s", len(cloud), p)
    return cloud


def iter_las_chunks(
    path: PathLike,
    *,
    chunk_points: int = 2_000_000,
    attributes: Sequence[str] | None = None,
) -> Iterator[PointCloud]:
    """Read a LAS/LAZ file in chunks of at most ``chunk_points`` points (for large files).

    The file is checked (exists, readable header, known attributes) when this function is
    called; the points are read lazily, one chunk per iteration step.

    Parameters
    ----------
    path : path-like
        LAS or LAZ file.
    chunk_points : int
        Maximum number of points per chunk (> 0).
    attributes : sequence of str, optional
        As in :func:`read_las`.

    Yields
    ------
    PointCloud
        Consecutive chunks in file order; each has the file's header info, CRS and source,
        and can be written with :func:`write_las` or :func:`write_las_chunked`.

    Raises
    ------
    SlipMapFileError
        If the file is missing or not readable (also while iterating, for corrupt data).
    InvalidParameterError
        If ``chunk_points`` is not a positive integer or an attribute is unknown.
    """
    if isinstance(chunk_points, bool) or not isinstance(chunk_points, (int, np.integer)):
        raise InvalidParameterError(
            f"chunk_points must be a positive integer; got {chunk_points!r}"
        )
    if chunk_points <= 0:
        raise InvalidParameterError(f"chunk_points must be > 0; got {chunk_points}")
    p = _input_path(path)
    with _open_reader(p) as reader:
        header = reader.header
        names = _resolve_attributes(attributes, header.point_format, p)
        info = _header_info(header)
        crs = crs_from_las(header, source=p)
    return _iter_chunks(p, int(chunk_points), names, info, crs)


def _iter_chunks(
    p: Path,
    chunk_points: int,
    names: Sequence[str],
    info: LasHeaderInfo,
    crs: pyproj.CRS | None,
) -> Iterator[PointCloud]:
    with _open_reader(p) as reader:
        header = reader.header
        it = reader.chunk_iterator(chunk_points)
        n_read = 0
        while True:
            try:
                points = next(it)
            except StopIteration:
                break
            except Exception as exc:
                raise _not_readable(p, exc) from exc
            n_read += len(points)
            las = laspy.LasData(copy.deepcopy(header), points=points)
            yield _cloud_from_las(las, names, info, crs, p)
    if n_read != info.n_points:
        raise SlipMapFileError(
            f"{p} is not a readable LAS/LAZ file: the header announces {info.n_points} points "
            f"but {n_read} could be read (truncated file?)"
        )


# --------------------------------------------------------------------------------------------
# writing


@dataclass
class _Assign:
    """One dimension to set in the output records."""

    lname: str  # laspy dimension name in the output point format
    values: np.ndarray  # (N,) or (N, k), already converted to the stored dtype/unit
    scaled: bool = False  # a scaled extra-bytes dimension (laspy applies scale/offset)


def _dim_dtype(pf: laspy.PointFormat, lname: str) -> Tuple[np.dtype, int | None]:
    """Stored (base) dtype of a dimension and, for bit fields, its maximum value."""
    info = pf.dimension_by_name(lname)
    if info.kind.name == "BitField":
        return np.dtype(np.uint8), (1 << int(info.num_bits)) - 1
    dtype = pf.dtype().fields[lname][0]
    if dtype.subdtype is not None:
        dtype = dtype.subdtype[0]
    return np.dtype(dtype), None


def _check_values(name: str, values: Any, n: int, label: str, ncols: int = 1) -> np.ndarray:
    arr = np.asarray(values)
    shape_ok = arr.ndim == 1 if ncols == 1 else arr.ndim == 2 and arr.shape[1] == ncols
    if not shape_ok or arr.shape[0] != n:
        want = f"({n},)" if ncols == 1 else f"({n}, {ncols})"
        raise InvalidParameterError(
            f"{label} {name!r} has shape {arr.shape}; expected {want} (one value per point)"
        )
    if arr.dtype.kind == "b":
        arr = arr.astype(np.uint8)
    if arr.dtype.kind not in _NEW_DIM_KINDS:
        raise InvalidParameterError(
            f"{label} {name!r} has dtype {arr.dtype}; point dimensions must be integer or float"
        )
    return arr


def _fit(name: str, arr: np.ndarray, dtype: np.dtype, max_value: int | None) -> np.ndarray:
    """Convert ``arr`` to an existing dimension's dtype, refusing lossy conversions."""
    if dtype.kind in "iu":
        if arr.dtype.kind == "f":
            raise InvalidParameterError(
                f"dimension {name!r} stores integers ({dtype}) but the new values are "
                f"floating point ({arr.dtype}); round and cast them first"
            )
        lo, hi = int(np.iinfo(dtype).min), int(np.iinfo(dtype).max)
        if max_value is not None:
            hi = min(hi, max_value)
        if arr.size and (int(arr.min()) < lo or int(arr.max()) > hi):
            raise InvalidParameterError(
                f"values for dimension {name!r} range {arr.min()}..{arr.max()}, outside "
                f"what it can store ({lo}..{hi})"
            )
    return arr.astype(dtype, copy=False)


def _plan(
    pf: laspy.PointFormat, n: int, updates: Mapping[str, Any], label: str
) -> Tuple[List[Tuple[str, np.dtype]], List[_Assign]]:
    """Work out new extra dims and per-dimension assignments for the ``updates``."""
    std = set(pf.standard_dimension_names)
    extra = set(pf.extra_dimension_names)
    new_dims: List[Tuple[str, np.dtype]] = []
    assigns: Dict[str, _Assign] = {}
    upd = dict(updates)
    has_rank = "scan_angle_rank" in std
    if "ScanAngle" in upd and "ScanAngleRank" in upd and has_rank:
        sa = np.asarray(upd["ScanAngle"], dtype=np.float64)
        sar = np.asarray(upd["ScanAngleRank"])
        if sa.shape != sar.shape or not np.array_equal(np.round(sa), sar.astype(np.float64)):
            raise InvalidParameterError(
                "ScanAngle and ScanAngleRank disagree; change both, or give only one of them"
            )
        del upd["ScanAngle"]
    for name, values in upd.items():
        if not isinstance(name, str) or not name:
            raise InvalidParameterError(f"dimension names must be non-empty strings; got {name!r}")
        if name in _COORDS:
            raise InvalidParameterError(
                f"{label} {name!r}: coordinates cannot be given as a dimension; use xyz="
            )
        if name == "ScanAngle":
            arr = _check_values(name, values, n, label).astype(np.float64)
            if not np.all(np.isfinite(arr)):
                raise InvalidParameterError("ScanAngle has NaN or infinite values")
            if has_rank:
                field_name, raw, dt = "scan_angle_rank", np.round(arr), np.dtype(np.int8)
            else:
                field_name, dt = "scan_angle", np.dtype(np.int16)
                raw = np.round(arr / SCAN_ANGLE_STEP_DEG)
            limits = np.iinfo(dt)
            if raw.size and (raw.min() < limits.min or raw.max() > limits.max):
                raise InvalidParameterError(
                    f"ScanAngle values {arr.min()}..{arr.max()} degrees do not fit the "
                    f"{field_name} field of point format {pf.id}"
                )
            assigns[field_name] = _Assign(field_name, raw.astype(dt))
            continue
        lname: str | None = None
        if name in _STANDARD:
            lname = _STANDARD[name][0]
            if lname not in std:
                raise InvalidParameterError(
                    f"{label} {name!r}: point format {pf.id} has no {name} dimension; "
                    "choose another name"
                )
        elif name in std or name in extra:
            lname = name
        if lname is not None:
            info = pf.dimension_by_name(lname)
            ncols = int(info.num_elements)
            arr = _check_values(name, values, n, label, ncols)
            if not info.is_standard and info.scales is not None:
                arr = arr.astype(np.float64)
                if not np.all(np.isfinite(arr)):
                    raise InvalidParameterError(f"{label} {name!r} has NaN or infinite values")
                assigns[lname] = _Assign(lname, arr, scaled=True)
            else:
                dtype, max_value = _dim_dtype(pf, lname)
                assigns[lname] = _Assign(lname, _fit(name, arr, dtype, max_value))
            continue
        # a new extra-bytes dimension
        try:
            encoded = name.encode("ascii")
        except UnicodeEncodeError:
            encoded = b""
        if not encoded or len(encoded) > 32:
            raise InvalidParameterError(
                f"{label} {name!r}: LAS extra-dimension names are ASCII, 1 to 32 characters"
            )
        lower = {d.lower() for d in std} | {p.lower() for p in _STANDARD} | {"scanangle"}
        if name.lower() in lower:
            raise InvalidParameterError(
                f"{label} {name!r} differs only in letter case from a standard LAS dimension; "
                "choose another name"
            )
        arr = _check_values(name, values, n, label)
        dtype = np.dtype(f"{arr.dtype.kind}{arr.dtype.itemsize}")
        if dtype.kind == "f" and dtype.itemsize not in (4, 8):
            raise InvalidParameterError(
                f"{label} {name!r} has dtype {arr.dtype}; use float32 or float64"
            )
        new_dims.append((name, dtype))
        assigns[name] = _Assign(name, arr.astype(dtype, copy=False))
    return new_dims, list(assigns.values())


def _out_header(
    src: laspy.LasHeader,
    new_dims: Sequence[Tuple[str, np.dtype]],
    crs: pyproj.CRS | None = None,
) -> laspy.LasHeader:
    hdr = copy.deepcopy(src)
    if new_dims:
        hdr.add_extra_dims(
            [laspy.ExtraBytesParams(name=name, type=dtype) for name, dtype in new_dims]
        )
    if crs is not None:
        _declare_crs(hdr, crs)
    return hdr


_CRS_RECORDS = (
    "WktCoordinateSystemVlr",
    "GeoKeyDirectoryVlr",
    "GeoAsciiParamsVlr",
    "GeoDoubleParamsVlr",
)


def _drop_crs(hdr: laspy.LasHeader) -> None:
    """Remove the CRS records of ``hdr`` (in place): a cloud read with its file's CRS ignored
    (geographic with metre coordinates, or unreadable) is written without it, as the job
    said, rather than with the records it declared wrong."""
    for records in (hdr.vlrs, hdr.evlrs):
        if records is None:
            continue
        for name in _CRS_RECORDS:
            records.extract(name)


def _declare_crs(hdr: laspy.LasHeader, crs: pyproj.CRS) -> None:
    """Make ``crs`` the CRS records of ``hdr`` (in place) unless they already declare it.

    Nothing is reprojected: a cloud whose ``crs`` was set by the caller (a file without a CRS
    or with a wrong one) is written with that CRS instead of the source file's records.
    """
    try:
        current = hdr.parse_crs()
    except Exception:  # malformed records are replaced
        current = None
    if current is not None and same_crs(current, crs):
        return
    if hdr.evlrs is not None:
        for name in _CRS_RECORDS:  # laspy's add_crs replaces only the VLRs
            hdr.evlrs.extract(name)
    try:
        hdr.add_crs(crs)
    except Exception as exc:
        raise InvalidParameterError(
            f"cannot store the CRS {crs.name!r} in a LAS {hdr.version} header ({exc}); "
            "LAS < 1.4 needs a CRS with an EPSG code"
        ) from exc


def _check_xyz(xyz: Any, n: int, scales: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    arr = np.asarray(xyz, dtype=np.float64)
    if arr.shape != (n, 3):
        raise InvalidParameterError(f"xyz has shape {arr.shape}; expected ({n}, 3)")
    if n == 0:
        return arr
    if not np.all(np.isfinite(arr)):
        raise InvalidParameterError("xyz has NaN or infinite coordinates; LAS cannot store them")
    q_lo = np.round((arr.min(axis=0) - offsets) / scales)
    q_hi = np.round((arr.max(axis=0) - offsets) / scales)
    q = np.concatenate([q_lo, q_hi])
    if q.min() < _INT32.min or q.max() > _INT32.max:
        raise InvalidParameterError(
            f"coordinates do not fit the file's scale {scales.tolist()} and offset "
            f"{offsets.tolist()}: LAS stores round((x - offset) / scale) as int32; the "
            "new coordinates are too far from the offset"
        )
    return arr


def _quantize(xyz: np.ndarray, scales: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    return np.round((xyz - offsets) / scales).astype(np.int32)


def _records(
    hdr: laspy.LasHeader,
    n: int,
    src_arrays: Iterable[np.ndarray | None],
    xyz: np.ndarray | None,
    assigns: Sequence[_Assign],
    where: Any,
) -> Iterator[laspy.ScaleAwarePointRecord]:
    """Output records batch by batch: raw copy of the source, then xyz, then assignments.

    ``src_arrays`` yields consecutive raw structured arrays of the source, or ``None`` per
    batch of at most ``_WRITE_BATCH`` points when there is no source record.
    """
    scales = np.asarray(hdr.scales, dtype=np.float64)
    offsets = np.asarray(hdr.offsets, dtype=np.float64)
    pos = 0
    for src in src_arrays:
        count = len(src) if src is not None else min(_WRITE_BATCH, n - pos)
        if pos + count > n:
            break
        rec = laspy.ScaleAwarePointRecord.zeros(count, header=hdr)
        if src is not None:
            for fname in src.dtype.names:
                rec.array[fname] = src[fname]
        sl = slice(pos, pos + count)
        if xyz is not None:
            q = _quantize(xyz[sl], scales, offsets)
            rec.array["X"], rec.array["Y"], rec.array["Z"] = q[:, 0], q[:, 1], q[:, 2]
        for a in assigns:
            vals = a.values[sl]
            try:
                if a.scaled:
                    rec[a.lname][:] = vals
                else:
                    rec[a.lname] = vals
            except OverflowError as exc:
                raise InvalidParameterError(
                    f"values for dimension {a.lname!r} do not fit it: {exc}"
                ) from exc
        pos += count
        yield rec
    if pos != n:
        raise SlipMapFileError(
            f"{where} is not a readable LAS/LAZ file: the header announces {n} points but "
            f"{pos} could be read (truncated file?)"
        )


def _batches(array: np.ndarray) -> Iterator[np.ndarray]:
    for s in range(0, len(array), _WRITE_BATCH):
        yield array[s : s + _WRITE_BATCH]


def _laz_backend() -> laspy.LazBackend:
    for backend in (laspy.LazBackend.LazrsParallel, laspy.LazBackend.Lazrs):
        if backend.is_available():
            return backend
    raise DependencyError("writing LAZ needs the 'lazrs' package; install it: pip install lazrs")


def _write_records(
    out: Path,
    hdr: laspy.LasHeader,
    records: Iterable[laspy.ScaleAwarePointRecord],
) -> int:
    """Write records atomically to ``out`` (LAZ if the suffix is .laz); return the count."""
    is_laz = out.suffix.lower() == ".laz"
    backend = _laz_backend() if is_laz else None
    ensure_output_dir(out.parent if str(out.parent) else Path("."))
    count = 0
    with atomic_path(out) as tmp:
        try:
            with open(tmp, "wb") as fh:
                writer = laspy.LasWriter(
                    fh, hdr, do_compress=is_laz, laz_backend=backend, closefd=False
                )
                for rec in records:
                    writer.write_points(rec)
                    count += len(rec)
                evlrs = hdr.evlrs
                if evlrs is not None and len(evlrs) > 0 and hdr.version.minor >= 4:
                    writer.write_evlrs(evlrs)
                writer.close()
        except SlipMapError:
            raise
        except Exception as exc:  # OSError (disk full), laspy/lazrs errors
            raise SlipMapFileError(f"cannot write {out}: {type(exc).__name__}: {exc}") from exc
    logger.info("wrote %d points to %s", count, out)
    return count


def _cloud_updates(cloud: PointCloud, extra_dims: Mapping[str, Any] | None) -> Dict[str, Any]:
    updates: Dict[str, Any] = dict(cloud.attributes)
    if extra_dims:
        for name, values in extra_dims.items():
            updates[name] = values
            if name == "ScanAngleRank":
                updates.pop("ScanAngle", None)  # the derived value follows the new ranks
    return updates


def _new_header(cloud: PointCloud, xyz: np.ndarray) -> laspy.LasHeader:
    """Header for a cloud made in memory (no LAS record)."""
    info = cloud.header
    if info is not None:
        version, pf_id = info.version, int(info.point_format)
        scales = np.asarray(info.scales, dtype=np.float64)
        offsets = np.asarray(info.offsets, dtype=np.float64)
    else:
        version, pf_id = "1.4", 6
        scales = np.full(3, 0.001)
        offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    try:
        hdr = laspy.LasHeader(version=version, point_format=pf_id)
    except Exception as exc:
        raise InvalidParameterError(
            f"cannot make a LAS {version} header with point format {pf_id}: {exc}"
        ) from exc
    hdr.scales = scales
    hdr.offsets = offsets
    return hdr  # the CRS is declared by _out_header, as for a file's header


def write_las(
    path: PathLike,
    source: Union[PointCloud, PathLike],
    *,
    extra_dims: Mapping[str, Any] | None = None,
    xyz: np.ndarray | None = None,
    inputs: Sequence[PathLike] | None = None,
) -> Path:
    """Write a point cloud as LAS (or LAZ when ``path`` ends in ``.laz``), atomically.

    Every point of ``source`` is written in input order with all its original dimensions and
    its header (version, point format, scales, offsets, VLRs/EVLRs including the CRS; for a
    :class:`PointCloud` whose ``crs`` was set to another CRS, that one replaces the file's
    CRS records, nothing reprojected), then:

    * coordinates: ``xyz`` if given, else (for a :class:`PointCloud`) ``source.xyz``, stored
      with the original scales/offsets (unchanged coordinates give the same integers);
    * dimensions: for a :class:`PointCloud`, its ``attributes`` (so edits to them are
      written), then ``extra_dims``. A name that is an existing dimension (PDAL name such as
      ``Classification``, laspy name, or extra-bytes name) overwrites it after a dtype/range
      check; ``ScanAngle`` (degrees) is stored in the raw scan-angle field; any other name
      becomes a new extra-bytes dimension with the array's dtype (bool stored as uint8).
      For point formats < 6 ``ScanAngle`` and ``ScanAngleRank`` are the same field: edit
      both, or drop one from ``attributes``, else the write is refused as inconsistent.

    Parameters
    ----------
    path : path-like
        Output file; its directory is created if needed.
    source : PointCloud or path-like
        The points (a path is streamed in batches, never fully read into memory).
    extra_dims : mapping of str to numpy.ndarray, optional
        Name -> ``(N,)`` array (e.g. ``PlaneId`` int32, ``Planarity`` float64).
    xyz : numpy.ndarray, optional
        ``(N, 3)`` replacement coordinates; must fit the int32 range for the file's
        scale/offset.
    inputs : sequence of path-like, optional
        Input files that must not be overwritten (``source.source`` is always protected).

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    InvalidParameterError
        Wrong lengths/dtypes, values that do not fit a dimension, coordinates out of range,
        or ``path`` being an input file.
    SlipMapFileError
        Unreadable source, or output that cannot be written.
    """
    out = Path(path)
    _require_laspy(f"writing {out}")
    if isinstance(source, PointCloud):
        check_not_input(out, [*(inputs or []), source.source])
        cloud = source
        n = len(cloud)
        updates = _cloud_updates(cloud, extra_dims)
        if cloud._las is not None:
            src_header = cloud._las.header
            src_array: np.ndarray | None = cloud._las.points.array
        else:
            src_array = None
            src_header = _new_header(cloud, cloud.xyz)
        new_dims, assigns = _plan(src_header.point_format, n, updates, "attribute")
        hdr = _out_header(src_header, new_dims, cloud.crs)
        if cloud.crs is None and cloud._las is not None:
            _drop_crs(hdr)  # the reader ignored the file's CRS (implausible): do not copy it
        coords = _check_xyz(
            cloud.xyz if xyz is None else xyz,
            n,
            np.asarray(hdr.scales, dtype=np.float64),
            np.asarray(hdr.offsets, dtype=np.float64),
        )
        if src_array is not None:
            arrays: Iterable[np.ndarray | None] = _batches(src_array)
        else:
            arrays = (None for _ in range(0, n, _WRITE_BATCH))
        _write_records(out, hdr, _records(hdr, n, arrays, coords, assigns, "the cloud"))
        return out

    src = _input_path(source)
    check_not_input(out, [*(inputs or []), src])
    with _open_reader(src) as reader:
        src_header = reader.header
        n = int(src_header.point_count)
        new_dims, assigns = _plan(src_header.point_format, n, dict(extra_dims or {}), "extra dim")
        hdr = _out_header(src_header, new_dims)
        coords = None
        if xyz is not None:
            coords = _check_xyz(
                xyz,
                n,
                np.asarray(hdr.scales, dtype=np.float64),
                np.asarray(hdr.offsets, dtype=np.float64),
            )

        def raw_chunks() -> Iterator[np.ndarray]:
            it = reader.chunk_iterator(_WRITE_BATCH)
            while True:
                try:
                    points = next(it)
                except StopIteration:
                    return
                except Exception as exc:
                    raise _not_readable(src, exc) from exc
                yield points.array

        _write_records(out, hdr, _records(hdr, n, raw_chunks(), coords, assigns, src))
    return out


def write_las_chunked(
    path: PathLike,
    chunks: Iterable[Union[PointCloud, Tuple[PointCloud, Mapping[str, Any] | None]]],
    *,
    inputs: Sequence[PathLike] | None = None,
) -> Path:
    """Write a sequence of clouds (e.g. from :func:`iter_las_chunks`) into one file.

    Each item is a :class:`PointCloud` or a ``(PointCloud, extra_dims)`` pair, written as by
    :func:`write_las`. The first chunk fixes the output header (its LAS record's header, or a
    new one); every chunk must have the same point format, scales/offsets and the same set of
    new dimensions (names and dtypes). Only one chunk is held in memory at a time.

    Parameters
    ----------
    path : path-like
        Output file (LAZ when it ends in ``.laz``).
    chunks : iterable
        The chunks, in output order. At least one is needed (it may be empty).
    inputs : sequence of path-like, optional
        Input files that must not be overwritten (each chunk's source is also protected).

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    out = Path(path)
    _require_laspy(f"writing {out}")
    iterator = iter(chunks)

    def split(item: Any) -> Tuple[PointCloud, Mapping[str, Any] | None]:
        if isinstance(item, PointCloud):
            return item, None
        if isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], PointCloud):
            return item[0], item[1]
        raise InvalidParameterError(
            "write_las_chunked needs PointCloud items or (PointCloud, extra_dims) pairs; "
            f"got {type(item).__name__}"
        )

    try:
        first = split(next(iterator))
    except StopIteration:
        raise InvalidParameterError("write_las_chunked got no chunks; nothing to write") from None
    check_not_input(out, [*(inputs or []), first[0].source])
    base = (
        first[0]._las.header if first[0]._las is not None else _new_header(first[0], first[0].xyz)
    )

    def prepare(cloud: PointCloud, extra: Mapping[str, Any] | None) -> Tuple[Any, ...]:
        if cloud._las is not None:
            src_header = cloud._las.header
            if (
                src_header.point_format != base.point_format
                or not np.array_equal(src_header.scales, base.scales)
                or not np.array_equal(src_header.offsets, base.offsets)
            ):
                raise InvalidParameterError(
                    "all chunks must share the first chunk's point format, scales and offsets"
                )
            array: np.ndarray | None = cloud._las.points.array
        else:
            array = None
        n = len(cloud)
        new_dims, assigns = _plan(base.point_format, n, _cloud_updates(cloud, extra), "attribute")
        return new_dims, assigns, array, n

    new_dims0, assigns0, array0, n0 = prepare(*first)
    hdr = _out_header(base, new_dims0, first[0].crs)
    scales = np.asarray(hdr.scales, dtype=np.float64)
    offsets = np.asarray(hdr.offsets, dtype=np.float64)

    def records() -> Iterator[laspy.ScaleAwarePointRecord]:
        cloud, (new_dims, assigns, array, n) = first[0], (new_dims0, assigns0, array0, n0)
        while True:
            if [(a, b.str) for a, b in new_dims] != [(a, b.str) for a, b in new_dims0]:
                raise InvalidParameterError(
                    "every chunk must add the same new dimensions (names and dtypes) as the "
                    f"first: {[d for d, _ in new_dims0]}; got {[d for d, _ in new_dims]}"
                )
            coords = _check_xyz(cloud.xyz, n, scales, offsets)
            if array is not None:
                arrays: Iterable[np.ndarray | None] = _batches(array)
            else:
                arrays = (None for _ in range(0, n, _WRITE_BATCH))
            yield from _records(hdr, n, arrays, coords, assigns, "a chunk")
            try:
                item = next(iterator)
            except StopIteration:
                return
            cloud, extra = split(item)
            check_not_input(out, [cloud.source])
            new_dims, assigns, array, n = prepare(cloud, extra)

    _write_records(out, hdr, records())
    return out
