"""Coordinate reference systems (pyproj): read them from LAS headers, compare, describe.

A LAS file carries its CRS either as an OGC WKT VLR or as GeoTIFF keys; laspy parses both
(``LasHeader.parse_crs``). Broken or implausible CRS records never crash a read: they give a
logged warning and ``None`` ("CRS unknown"), and callers decide what to do.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Tuple

import numpy as np
import pyproj
from pyproj.exceptions import CRSError

from ..errors import InputDataError, InvalidParameterError

logger = logging.getLogger(__name__)

__all__ = ["crs_from_las", "crs_to_wkt", "crs_units", "parse_crs", "same_crs"]


def parse_crs(value: Any) -> pyproj.CRS | None:
    """Turn anything pyproj understands into a :class:`pyproj.CRS`.

    Parameters
    ----------
    value : pyproj.CRS, str, int, dict or None
        A CRS, an "EPSG:xxxx" / "ESRI:xxxx" code, an integer EPSG code, WKT, a PROJ string or
        PROJ JSON; ``None`` (or an empty string) means "no CRS".

    Returns
    -------
    pyproj.CRS or None

    Raises
    ------
    InvalidParameterError
        If pyproj cannot make a CRS of ``value``.
    """
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    if isinstance(value, pyproj.CRS):
        return value
    try:
        return pyproj.CRS.from_user_input(value)
    except (CRSError, TypeError, ValueError) as exc:
        raise InvalidParameterError(
            f"cannot understand the CRS {str(value)[:80]!r}: {exc}; give an EPSG code "
            "such as 'EPSG:32612', WKT or a PROJ string"
        ) from exc


def _horizontal(crs: pyproj.CRS) -> pyproj.CRS:
    """The horizontal part of a (bound, compound) CRS."""
    if crs.is_bound and crs.source_crs is not None:
        crs = crs.source_crs
    if crs.is_compound and crs.sub_crs_list:
        crs = crs.sub_crs_list[0]
        if crs.is_bound and crs.source_crs is not None:
            crs = crs.source_crs
    return crs


def crs_from_las(las_header: Any, *, source: Any = None) -> pyproj.CRS | None:
    """The CRS of a LAS/LAZ file, from its WKT VLR or its GeoTIFF keys.

    The WKT VLR is preferred when both are present (laspy's ``parse_crs`` order). A CRS that
    cannot be parsed, or a geographic CRS (degrees) although the header's bounds are far
    outside longitude/latitude ranges (a mislabelled file: PDAL's ``lone-star.laz`` declares
    EPSG:4326 for UTM coordinates), gives a logged warning and ``None``.

    Parameters
    ----------
    las_header : laspy.LasHeader or laspy.LasData
        The header (a ``LasData`` is accepted and its header used).
    source : path-like, optional
        The file name, only for the warning messages.

    Returns
    -------
    pyproj.CRS or None
        ``None`` when the file has no (usable) CRS.
    """
    header = getattr(las_header, "header", las_header)
    where = f"{source}: " if source is not None else ""
    try:
        crs = header.parse_crs()
    except Exception as exc:  # laspy/pyproj raise many types on malformed VLRs
        logger.warning(
            "%sthe CRS records of the file cannot be parsed (%s); CRS unknown", where, exc
        )
        return None
    if crs is None:
        return None
    try:
        horiz = _horizontal(crs)
        if horiz.is_geographic and int(getattr(header, "point_count", 0)) > 0:
            mins = np.asarray(header.mins, dtype=np.float64)
            maxs = np.asarray(header.maxs, dtype=np.float64)
            lon_ok = -360.0 <= mins[0] and maxs[0] <= 360.0
            lat_ok = -90.0 <= mins[1] and maxs[1] <= 90.0
            if not (lon_ok and lat_ok):
                logger.warning(
                    "%sthe file declares the geographic CRS %r (degrees) but its coordinates "
                    "(x %.6g..%.6g, y %.6g..%.6g) are not longitudes/latitudes; the CRS is "
                    "ignored (unknown) — give the correct CRS explicitly",
                    where,
                    crs.name,
                    mins[0],
                    maxs[0],
                    mins[1],
                    maxs[1],
                )
                return None
    except Exception as exc:  # a CRS pyproj cannot introspect is as good as none
        logger.warning("%sthe CRS of the file cannot be used (%s); CRS unknown", where, exc)
        return None
    return crs


def same_crs(a: Any, b: Any) -> bool:
    """Whether two CRSs are equivalent (axis order ignored: LAS x/y are always east/north).

    Parameters
    ----------
    a, b : pyproj.CRS, str, int or None
        Anything :func:`parse_crs` accepts. Two ``None`` are the same; ``None`` and a CRS are
        not.

    Returns
    -------
    bool
    """
    ca, cb = parse_crs(a), parse_crs(b)
    if ca is None or cb is None:
        return ca is None and cb is None
    try:
        return bool(ca.equals(cb, ignore_axis_order=True))
    except TypeError:  # very old pyproj without ignore_axis_order
        return bool(ca == cb)


def crs_units(crs: Any) -> Tuple[str, float]:
    """The horizontal linear unit of a CRS and its length in metres.

    Parameters
    ----------
    crs : pyproj.CRS, str or int
        A projected (or compound / geocentric / engineering) CRS.

    Returns
    -------
    name : str
        pyproj's unit name, e.g. ``"metre"``, ``"foot"`` (international, 0.3048 m) or
        ``"US survey foot"`` (0.30480060960121924 m).
    metres_per_unit : float
        Length of one unit in metres.

    Raises
    ------
    InvalidParameterError
        If ``crs`` is ``None`` (unknown CRS: units cannot be told).
    InputDataError
        If the CRS is geographic (degrees): SlipMap needs planar coordinates; reproject the
        data to a projected CRS (e.g. UTM).
    """
    c = parse_crs(crs)
    if c is None:
        raise InvalidParameterError(
            "the CRS is unknown, so its units cannot be told; give the CRS explicitly"
        )
    horiz = _horizontal(c)
    if horiz.is_geographic:
        raise InputDataError(
            f"the CRS {horiz.name!r} is geographic (angles in degrees); SlipMap needs planar "
            "coordinates — reproject the data to a projected CRS such as UTM"
        )
    axes = horiz.axis_info or c.axis_info
    if not axes:
        raise InputDataError(f"the CRS {c.name!r} has no axes; its units cannot be told")
    axis = axes[0]
    factor = float(axis.unit_conversion_factor)
    if not math.isfinite(factor) or factor <= 0:
        raise InputDataError(f"the CRS {c.name!r} has an unusable unit {axis.unit_name!r}")
    return str(axis.unit_name), factor


def crs_to_wkt(crs: Any, *, version: str = "WKT2_2019", pretty: bool = False) -> str | None:
    """WKT of a CRS (``None`` for an unknown CRS).

    Parameters
    ----------
    crs : pyproj.CRS, str, int or None
        Anything :func:`parse_crs` accepts.
    version : str
        pyproj WKT version name: ``"WKT2_2019"`` (default, lossless) or ``"WKT1_GDAL"``
        (what LAS 1.4 WKT VLRs and older GDAL expect).
    pretty : bool
        Multi-line, indented output.

    Returns
    -------
    str or None
    """
    c = parse_crs(crs)
    if c is None:
        return None
    wkt = c.to_wkt(version=version, pretty=pretty)
    if wkt is None:
        raise InvalidParameterError(f"the CRS {c.name!r} cannot be written as {version} WKT")
    return wkt


def reproject_points(xyz: Any, source: Any, target: Any) -> Any:
    """Coordinates (N, 3) float64 transformed from CRS ``source`` to ``target`` (pyproj,
    traditional GIS axis order: x = easting/longitude). Heights pass through unchanged unless
    both CRSs are 3D. Returns a new array; the input is not modified."""
    src, dst = parse_crs(source), parse_crs(target)
    if src is None or dst is None:
        raise InvalidParameterError("reproject_points needs both a source and a target CRS")
    tr = pyproj.Transformer.from_crs(src, dst, always_xy=True)
    a = np.asarray(xyz, dtype=np.float64)
    x, y, z = tr.transform(a[:, 0], a[:, 1], a[:, 2])
    out = np.column_stack([x, y, z])
    if not np.all(np.isfinite(out)):
        raise InvalidParameterError(
            f"points cannot be reprojected from {src.name!r} to {dst.name!r} (outside the "
            "target CRS's area); give both epochs in one CRS"
        )
    return out
