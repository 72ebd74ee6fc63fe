"""Vector files (GDAL/OGR): read fault traces, write GeoPackage layers.

GDAL's Python bindings (``osgeo.ogr`` / ``osgeo.osr``) are imported inside the functions:
without them the rest of SlipMap works and these functions raise
:class:`~slipmap.core.errors.DependencyError`.

Coordinates are always handled in "traditional GIS order" (x = easting / longitude,
y = northing / latitude), whatever axis order the CRS definition declares.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from ..errors import (
    DependencyError,
    InputDataError,
    InvalidParameterError,
    SlipMapFileError,
)
from ..fault import FaultTrace, fault_trace
from .atomic import PathLike, atomic_path
from .crs import parse_crs

logger = logging.getLogger(__name__)

__all__ = [
    "VectorLayer",
    "gpkg_layer_names",
    "read_fault_trace",
    "read_gpkg_layer",
    "read_polygons",
    "write_gpkg_layers",
    "write_gpkg_styles",
]

_INSTALL_HINT = (
    "install python3-gdal (Debian/Ubuntu) or 'gdal' from conda-forge (GDAL's Python bindings, "
    "osgeo.ogr)"
)


def _ogr():
    """``(ogr, osr)`` with exceptions enabled, or DependencyError."""
    try:
        from osgeo import ogr, osr
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DependencyError(f"reading/writing vector files needs GDAL: {_INSTALL_HINT}") from exc
    ogr.UseExceptions()
    osr.UseExceptions()
    return ogr, osr


def _srs_from(crs: Any, osr) -> Any:
    """An ``osr.SpatialReference`` (traditional GIS axis order) of anything parse_crs takes."""
    c = parse_crs(crs)
    if c is None:
        return None
    srs = osr.SpatialReference()
    try:
        srs.ImportFromWkt(c.to_wkt())
    except RuntimeError:  # an older GDAL that does not read WKT2: fall back to WKT1
        srs.ImportFromWkt(c.to_wkt(version="WKT1_GDAL"))
    srs.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    return srs


# ---------------------------------------------------------------------------------------------
# reading fault traces


_UNDEFINED_SRS_NAMES = ("Undefined geographic SRS", "Undefined cartesian SRS")


def _line_parts(geom, ogr) -> Optional[List[np.ndarray]]:
    """Vertex arrays of a (multi)line geometry, or None if it is not a line type."""
    flat = ogr.GT_Flatten(geom.GetGeometryType())
    if flat in (ogr.wkbCircularString, ogr.wkbCompoundCurve, ogr.wkbMultiCurve):
        geom = geom.GetLinearGeometry()
        flat = ogr.GT_Flatten(geom.GetGeometryType())
    if flat == ogr.wkbLineString:
        return [np.array([geom.GetPoint_2D(i) for i in range(geom.GetPointCount())]).reshape(-1, 2)]
    if flat == ogr.wkbMultiLineString:
        out = []
        for i in range(geom.GetGeometryCount()):
            sub = _line_parts(geom.GetGeometryRef(i), ogr)
            out.extend(sub or [])
        return out
    return None


def _pick_layer(ds, layer: Union[str, int, None], ogr, path: Path, polygons: bool = False):
    count = ds.GetLayerCount()
    if count == 0:
        raise InputDataError(f"vector file {str(path)!r} has no layers")
    if layer is None:
        if count == 1:
            return ds.GetLayer(0)
        if polygons:
            types, kind = (ogr.wkbPolygon, ogr.wkbMultiPolygon), "polygon"
        else:
            types, kind = (ogr.wkbLineString, ogr.wkbMultiLineString), "line"
        for i in range(count):
            lyr = ds.GetLayer(i)
            if ogr.GT_Flatten(lyr.GetGeomType()) in types:
                return lyr
        names = [ds.GetLayer(i).GetName() for i in range(count)]
        raise InputDataError(
            f"vector file {str(path)!r} has {count} layers ({', '.join(names)}) and none is a "
            f"{kind} layer; name the layer to use"
        )
    lyr = ds.GetLayer(layer) if isinstance(layer, int) else ds.GetLayerByName(str(layer))
    if lyr is None:
        names = [ds.GetLayer(i).GetName() for i in range(count)]
        raise InvalidParameterError(
            f"vector file {str(path)!r} has no layer {layer!r}; its layers: {', '.join(names)}"
        )
    return lyr


def _read_parts(path, target_crs, layer, what, extract, expected, *, polygons=False):
    """Geometry parts of a vector layer, reprojected to ``target_crs`` (shared reader).

    ``extract(geom)`` returns a list of vertex arrays or None for a wrong geometry type (then
    the error says ``expected``); ``polygons`` picks a polygon layer (else a line layer) when
    the file has several and none is named. Returns ``(parts, n_features, layer_name)``.
    """
    ogr, osr = _ogr()
    p = Path(path)
    if not p.exists():
        raise SlipMapFileError(f"{what} {str(p)!r} does not exist")
    try:
        ds = ogr.Open(str(p), 0)
    except RuntimeError as exc:
        raise SlipMapFileError(f"cannot read {what} {str(p)!r}: {exc}") from exc
    if ds is None:
        raise SlipMapFileError(f"cannot read {what} {str(p)!r}: not a vector file")
    try:
        lyr = _pick_layer(ds, layer, ogr, p, polygons=polygons)
        dst = _srs_from(target_crs, osr)
        src = lyr.GetSpatialRef()
        if src is not None and src.GetName() in _UNDEFINED_SRS_NAMES:
            src = None  # GeoPackage's placeholders for "no CRS" (srs_id 0 and -1)
        transform = None
        if src is None:
            if dst is not None:
                logger.warning(
                    what + " %r has no CRS; assuming it is in the target CRS %r",
                    str(p),
                    dst.GetName(),
                )
        else:
            src = src.Clone()
            src.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
            if dst is None:
                if src.IsGeographic():
                    raise InputDataError(
                        f"{what} {str(p)!r} is in the geographic CRS "
                        f"{src.GetName()!r} (degrees); give the point clouds' projected CRS "
                        "as target_crs so it is reprojected"
                    )
            elif not src.IsSame(dst):
                try:
                    transform = osr.CoordinateTransformation(src, dst)
                except RuntimeError as exc:
                    raise InputDataError(
                        f"cannot reproject {what} {str(p)!r} from "
                        f"{src.GetName()!r} to {dst.GetName()!r}: {exc}"
                    ) from exc
        parts: List[np.ndarray] = []
        n_features = 0
        lyr.ResetReading()
        for feat in lyr:
            n_features += 1
            geom = feat.GetGeometryRef()
            if geom is None or geom.IsEmpty():
                logger.warning(
                    what + " %r: feature %d has no geometry; skipped",
                    str(p),
                    feat.GetFID(),
                )
                continue
            geom = geom.Clone()
            if transform is not None:
                try:
                    geom.Transform(transform)
                except RuntimeError as exc:
                    raise InputDataError(
                        f"cannot reproject {what} {str(p)!r} (feature {feat.GetFID()}): {exc}"
                    ) from exc
            got = extract(geom)
            if got is None:
                raise InputDataError(
                    f"{what} {str(p)!r} holds a {geom.GetGeometryName()} geometry "
                    f"(feature {feat.GetFID()}); {expected}"
                )
            parts.extend(got)
        lyr_name = lyr.GetName()
    finally:
        ds = None  # noqa: F841 - closes the dataset
    return parts, n_features, lyr_name


def read_fault_trace(
    path: PathLike,
    *,
    target_crs: Any = None,
    layer: Union[str, int, None] = None,
) -> FaultTrace:
    """Read a fault trace from any OGR vector file (GeoPackage, GeoJSON, Shapefile, ...).

    Parameters
    ----------
    path : str or os.PathLike
        The vector file.
    target_crs : pyproj.CRS, str or int, optional
        CRS of the point clouds (projected, metres): the trace is reprojected into it
        (a trace in a geographic CRS is reprojected, never refused). ``None`` keeps the
        file's coordinates.
    layer : str or int, optional
        Layer name or index; by default the only layer, or the first line layer.

    Returns
    -------
    FaultTrace
        One part per LineString (several per MultiLineString), features in file order;
        z is dropped; ``(M, 2)`` vertices in ``target_crs`` units.

    Raises
    ------
    SlipMapFileError
        If the file is missing or GDAL cannot open it.
    InputDataError
        If the layer holds non-line geometries (points, polygons), no features, a part with
        fewer than 2 distinct vertices, or the trace is geographic (degrees) while no
        ``target_crs`` is given.
    InvalidParameterError
        If ``layer`` does not exist or ``target_crs`` cannot be understood.
    DependencyError
        If GDAL's Python bindings are not installed.

    Notes
    -----
    A file without a CRS is assumed to be in ``target_crs`` (with a logged warning).
    """
    ogr, _ = _ogr()
    parts, n_features, lyr_name = _read_parts(
        path,
        target_crs,
        layer,
        "fault-trace file",
        lambda g: _line_parts(g, ogr),
        "a fault trace must be LineString or MultiLineString",
    )
    p = Path(path)
    if not parts:
        raise InputDataError(
            f"fault-trace file {str(p)!r} (layer {lyr_name!r}) has no line geometries "
            f"({n_features} features)"
        )
    try:
        trace = fault_trace(parts)
    except InvalidParameterError as exc:
        raise InputDataError(f"fault-trace file {str(p)!r}: {exc}") from exc
    logger.info(
        "fault trace %r: %d part(s), %d vertices, %.1f m",
        str(p),
        len(trace.parts),
        len(trace.vertices),
        trace.length_m(),
    )
    return trace


def read_lines(
    path: PathLike,
    *,
    target_crs: Any = None,
    layer: Union[str, int, None] = None,
    what: str = "line file",
) -> List[np.ndarray]:
    """Every line of a vector file (breaklines, scarps), reprojected to ``target_crs``.

    Parameters
    ----------
    path : str or os.PathLike
        Any OGR vector file with LineString / MultiLineString features.
    target_crs : pyproj.CRS, str or int, optional
        CRS of the point clouds (metres); ``None`` keeps the file's coordinates.
    layer : str or int, optional
        Layer name or index; by default the only layer, or the first line layer.
    what : str
        How errors name the file ("breakline file").

    Returns
    -------
    list of ndarray, each (M, 2)
        One array per LineString part, file order, z dropped.

    Raises
    ------
    SlipMapFileError, InputDataError, InvalidParameterError, DependencyError
        As :func:`read_fault_trace`; also when the layer has no line.
    """
    ogr, _ = _ogr()
    parts, n_features, lyr_name = _read_parts(
        path,
        target_crs,
        layer,
        what,
        lambda g: _line_parts(g, ogr),
        "lines must be LineString or MultiLineString",
    )
    if not parts:
        raise InputDataError(
            f"{what} {str(path)!r} (layer {lyr_name!r}) has no line geometries "
            f"({n_features} features)"
        )
    out = [np.asarray(v, dtype=np.float64)[:, :2] for v in parts]
    logger.info("%s %r: %d line(s), %d vertices", what, str(path), len(out), sum(map(len, out)))
    return out


def _polygon_rings(geom, ogr) -> Optional[List[np.ndarray]]:
    """Exterior rings of a (multi)polygon geometry (holes ignored), or None otherwise."""
    flat = ogr.GT_Flatten(geom.GetGeometryType())
    if flat in (ogr.wkbCurvePolygon, ogr.wkbMultiSurface):
        geom = geom.GetLinearGeometry()
        flat = ogr.GT_Flatten(geom.GetGeometryType())
    if flat == ogr.wkbPolygon:
        ring = geom.GetGeometryRef(0)
        if ring is None or ring.GetPointCount() < 3:
            return []
        return [np.array([ring.GetPoint_2D(i) for i in range(ring.GetPointCount())])]
    if flat == ogr.wkbMultiPolygon:
        out = []
        for i in range(geom.GetGeometryCount()):
            out.extend(_polygon_rings(geom.GetGeometryRef(i), ogr) or [])
        return out
    return None


def read_polygons(
    path: PathLike, *, target_crs: Any = None, layer: Union[str, int, None] = None
) -> List[np.ndarray]:
    """Exterior rings of the polygons of a vector file (e.g. a stable-area / moving-area mask).

    Parameters
    ----------
    path : str or os.PathLike
        Any OGR vector file with Polygon / MultiPolygon features.
    target_crs : pyproj.CRS, str or int, optional
        CRS of the point clouds: the polygons are reprojected into it (None keeps the file's).
    layer : str or int, optional
        Layer name or index (default: the first).

    Returns
    -------
    list of (M, 2) float64
        One ring per polygon part (holes are ignored), map units.

    Raises
    ------
    SlipMapFileError, InputDataError, InvalidParameterError, DependencyError
        As :func:`read_fault_trace` (non-polygon geometries are refused).
    """
    ogr, _ = _ogr()
    parts, n_features, name = _read_parts(
        path,
        target_crs,
        layer,
        "polygon file",
        lambda g: _polygon_rings(g, ogr),
        "a mask must hold Polygon or MultiPolygon features",
        polygons=True,
    )
    if not parts:
        raise InputDataError(
            f"polygon file {str(path)!r} (layer {name!r}) has no polygons ({n_features} features)"
        )
    return parts


# ---------------------------------------------------------------------------------------------
# GeoPackage layers

_GEOMETRY_TYPES = ("Point", "LineString", "Polygon")


@dataclass
class VectorLayer:
    """One layer to write with :func:`write_gpkg_layers`.

    Attributes
    ----------
    name : str
        Layer (table) name.
    geometry_type : {"Point", "LineString", "Polygon"}
    geometries : list of numpy.ndarray
        Per feature: ``(2,)`` or ``(3,)`` for points, ``(M, 2|3)`` for lines, ``(M, 2)``
        exterior ring for polygons (closed automatically if open). Map units (metres).
    fields : dict of str to numpy.ndarray
        Attribute columns, one value per geometry: float -> Real (NaN written as NULL),
        int -> Integer64, bool -> Integer (boolean subtype), str/object -> String.
    """

    name: str
    geometry_type: str
    geometries: List[np.ndarray]
    fields: Dict[str, np.ndarray] = field(default_factory=dict)


def _field_kind(values: np.ndarray) -> str:
    kind = values.dtype.kind
    if kind == "b":
        return "bool"
    if kind in "iu":
        return "int"
    if kind == "f":
        return "float"
    if kind in "USO":
        return "str"
    raise InvalidParameterError(f"unsupported field dtype {values.dtype}")


def _check_layer(layer: VectorLayer) -> Tuple[Dict[str, np.ndarray], int]:
    if not layer.name or not isinstance(layer.name, str):
        raise InvalidParameterError(f"vector layer name must be a non-empty string: {layer.name!r}")
    if layer.geometry_type not in _GEOMETRY_TYPES:
        raise InvalidParameterError(
            f"layer {layer.name!r}: geometry_type must be one of {', '.join(_GEOMETRY_TYPES)}, "
            f"got {layer.geometry_type!r}"
        )
    n = len(layer.geometries)
    fields = {}
    for k, v in layer.fields.items():
        a = np.asarray(v)
        if a.ndim != 1 or len(a) != n:
            raise InvalidParameterError(
                f"layer {layer.name!r}: field {k!r} has shape {a.shape}, expected ({n},)"
            )
        fields[str(k)] = a
    dim = 2
    for i, g in enumerate(layer.geometries):
        a = np.asarray(g, dtype=np.float64)
        ok = (
            a.shape in ((2,), (3,))
            if layer.geometry_type == "Point"
            else (a.ndim == 2 and a.shape[1] in (2, 3) and len(a) >= 2)
        )
        if not ok:
            raise InvalidParameterError(
                f"layer {layer.name!r}: geometry {i} has shape {a.shape}, not a "
                f"{layer.geometry_type}"
            )
        dim = max(dim, a.shape[-1])
    return fields, dim


def _make_geometry(kind: str, coords: np.ndarray, dim: int, ogr):
    a = np.asarray(coords, dtype=np.float64)
    if kind == "Point":
        g = ogr.Geometry(ogr.wkbPoint25D if dim == 3 else ogr.wkbPoint)
        if dim == 3:
            g.AddPoint(float(a[0]), float(a[1]), float(a[2]) if len(a) > 2 else 0.0)
        else:
            g.AddPoint_2D(float(a[0]), float(a[1]))
        return g

    def fill(line, pts):
        for row in pts:
            if dim == 3:
                line.AddPoint(float(row[0]), float(row[1]), float(row[2]) if len(row) > 2 else 0.0)
            else:
                line.AddPoint_2D(float(row[0]), float(row[1]))

    if kind == "LineString":
        g = ogr.Geometry(ogr.wkbLineString25D if dim == 3 else ogr.wkbLineString)
        fill(g, a)
        return g
    if len(a) and np.any(a[0] != a[-1]):
        a = np.vstack([a, a[:1]])  # close the ring
    ring = ogr.Geometry(ogr.wkbLinearRing)
    fill(ring, a)
    g = ogr.Geometry(ogr.wkbPolygon25D if dim == 3 else ogr.wkbPolygon)
    g.AddGeometry(ring)
    return g


def write_gpkg_layers(
    path: PathLike,
    layers: Sequence[VectorLayer],
    *,
    crs: Any = None,
    styles: Optional[Mapping[str, str]] = None,
) -> Path:
    """Write several layers into one GeoPackage, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Output ``.gpkg``; replaced only once the new file is complete.
    layers : sequence of VectorLayer
        Layers with distinct names.
    crs : pyproj.CRS, str or int, optional
        CRS of all layers (WKT, "EPSG:xxxx" or an EPSG integer); None writes none.
    styles : mapping of str to str, optional
        ``{layer name: QML text}``: each layer's default style, stored in the GeoPackage's
        ``layer_styles`` table (:func:`write_gpkg_styles`) before the file is moved in, so
        QGIS opens the layer styled wherever it is opened.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    InvalidParameterError
        For bad layers (unknown geometry type, field lengths, duplicate names).
    SlipMapFileError
        If the file cannot be written.
    """
    ogr, osr = _ogr()
    checked = [_check_layer(lyr) for lyr in layers]
    names = [lyr.name for lyr in layers]
    if len(set(n.lower() for n in names)) != len(names):
        raise InvalidParameterError(f"GeoPackage layer names must be distinct: {names}")
    srs = _srs_from(crs, osr)
    driver = ogr.GetDriverByName("GPKG")
    base_types = {"Point": ogr.wkbPoint, "LineString": ogr.wkbLineString, "Polygon": ogr.wkbPolygon}
    with atomic_path(path, suffix=".gpkg") as tmp:
        tmp.unlink()  # the GPKG driver creates the file itself
        try:
            ds = driver.CreateDataSource(str(tmp))
        except RuntimeError as exc:
            raise SlipMapFileError(f"cannot write GeoPackage {str(path)!r}: {exc}") from exc
        try:
            for lyr, (fields, dim) in zip(layers, checked):
                gtype = base_types[lyr.geometry_type]
                if dim == 3:
                    gtype = ogr.GT_SetZ(gtype)
                out = ds.CreateLayer(lyr.name, srs, gtype, ["SPATIAL_INDEX=YES"])
                kinds = {}
                for fname, values in fields.items():
                    kind = _field_kind(values)
                    kinds[fname] = kind
                    ftype = {
                        "float": ogr.OFTReal,
                        "int": ogr.OFTInteger64,
                        "bool": ogr.OFTInteger,
                        "str": ogr.OFTString,
                    }[kind]
                    defn = ogr.FieldDefn(fname, ftype)
                    if kind == "bool":
                        defn.SetSubType(ogr.OFSTBoolean)
                    out.CreateField(defn)
                layer_defn = out.GetLayerDefn()
                index = {fname: layer_defn.GetFieldIndex(fname) for fname in fields}
                out.StartTransaction()
                for i, coords in enumerate(lyr.geometries):
                    feat = ogr.Feature(layer_defn)
                    feat.SetGeometry(_make_geometry(lyr.geometry_type, coords, dim, ogr))
                    for fname, values in fields.items():
                        v = values[i]
                        kind = kinds[fname]
                        fi = index[fname]
                        if kind == "float":
                            fv = float(v)
                            if math.isnan(fv):
                                feat.SetFieldNull(fi)
                            else:
                                feat.SetField(fi, fv)
                        elif kind == "int":
                            feat.SetFieldInteger64(fi, int(v))
                        elif kind == "bool":
                            feat.SetField(fi, int(bool(v)))
                        elif v is None:
                            feat.SetFieldNull(fi)
                        else:
                            feat.SetField(fi, str(v))
                    out.CreateFeature(feat)
                out.CommitTransaction()
                logger.debug("GeoPackage layer %r: %d features", lyr.name, len(lyr.geometries))
        except RuntimeError as exc:
            raise SlipMapFileError(f"cannot write GeoPackage {str(path)!r}: {exc}") from exc
        finally:
            ds = None  # noqa: F841 - closes (and flushes) the dataset
        if styles:
            _store_styles(tmp, styles, str(path))
    return Path(path)


#: QGIS's ``layer_styles`` table (as its OGR provider creates it in a GeoPackage)
_STYLE_FIELDS = (
    ("f_table_catalog", "str", 256),
    ("f_table_schema", "str", 256),
    ("f_table_name", "str", 256),
    ("f_geometry_column", "str", 256),
    ("styleName", "str", 30),
    ("styleQML", "str", 0),
    ("styleSLD", "str", 0),
    ("useAsDefault", "bool", 0),
    ("description", "str", 0),
    ("owner", "str", 30),
    ("ui", "str", 30),
    ("update_time", "datetime", 0),
)


def gpkg_layer_names(path: PathLike) -> List[str]:
    """The data layers of a GeoPackage (its ``layer_styles`` table left out)."""
    ogr, _ = _ogr()
    try:
        ds = ogr.Open(str(path), 0)
    except RuntimeError as exc:
        raise SlipMapFileError(f"cannot read GeoPackage {str(path)!r}: {exc}") from exc
    try:
        names = [ds.GetLayer(i).GetName() for i in range(ds.GetLayerCount())]
    finally:
        ds = None  # noqa: F841
    return [n for n in names if n != "layer_styles"]


def write_gpkg_styles(
    path: PathLike,
    styles: Mapping[str, str],
    *,
    style_name: str = "SlipMap",
    description: str = "SlipMap's style",
) -> Path:
    """Store each layer's default style in an existing GeoPackage (one transaction).

    QGIS reads a GeoPackage layer's default style from the file's ``layer_styles`` table (its
    schema: ``f_table_catalog``, ``f_table_schema``, ``f_table_name``, ``f_geometry_column``,
    ``styleName``, ``styleQML``, ``styleSLD``, ``useAsDefault``, ``description``, ``owner``,
    ``ui``, ``update_time``), so a layer opened by drag and drop, from the browser or by
    ``QgsVectorLayer(path)`` is drawn with it. The table is created when missing; a row of the
    same layer and ``style_name`` is replaced, and the other rows of that layer stop being
    the default.

    Parameters
    ----------
    path : str or os.PathLike
        A GeoPackage holding the layers (e.g. one QGIS has just written).
    styles : mapping of str to str
        ``{layer name: QML text}`` (QGIS's own style format, e.g. ``QgsMapLayer.saveNamedStyle``).
    style_name, description : str
        The row's ``styleName`` (30 characters at most) and ``description``.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    InvalidParameterError
        If a layer named in ``styles`` is not in the file.
    SlipMapFileError
        If the file cannot be read or written.
    """
    p = Path(path)
    if not p.is_file():
        raise SlipMapFileError(f"GeoPackage {str(p)!r} does not exist")
    # in place (the rows go in as one SQLite transaction): a copy moved over the file would
    # leave a program that holds it open (QGIS) reading the old one
    _store_styles(p, styles, str(p), style_name=style_name, description=description)
    return p


def _store_styles(
    path: Path,
    styles: Mapping[str, str],
    shown: str,
    *,
    style_name: str = "SlipMap",
    description: str = "SlipMap's style",
) -> None:
    """Insert (replace) the default-style rows of ``styles`` into the GeoPackage ``path``
    (``shown``: the name in error messages)."""
    import datetime

    ogr, _ = _ogr()
    try:
        ds = ogr.Open(str(path), 1)
    except RuntimeError as exc:
        raise SlipMapFileError(f"cannot write styles into {shown!r}: {exc}") from exc
    try:
        columns = {}
        for name in styles:
            lyr = ds.GetLayerByName(str(name))
            if lyr is None:
                raise InvalidParameterError(f"GeoPackage {shown!r} has no layer {name!r}")
            columns[str(name)] = lyr.GetGeometryColumn() or ""
        table = ds.GetLayerByName("layer_styles")
        if table is None:
            table = ds.CreateLayer("layer_styles", None, ogr.wkbNone, ["FID=id"])
            for fname, kind, width in _STYLE_FIELDS:
                ftype = {"str": ogr.OFTString, "bool": ogr.OFTInteger}.get(kind, ogr.OFTDateTime)
                defn = ogr.FieldDefn(fname, ftype)
                if width:
                    defn.SetWidth(width)
                if kind == "bool":
                    defn.SetSubType(ogr.OFSTBoolean)
                if kind == "datetime":
                    defn.SetDefault("CURRENT_TIMESTAMP")
                table.CreateField(defn)
        now = datetime.datetime.now(datetime.timezone.utc)
        stamp = (now.year, now.month, now.day, now.hour, now.minute, float(now.second), 100)
        table.StartTransaction()
        for name, qml in styles.items():
            quoted = str(name).replace("'", "''")
            table.SetAttributeFilter(f"f_table_name = '{quoted}'")
            old = [(f.GetFID(), f.GetField("styleName")) for f in table]
            table.SetAttributeFilter(None)
            for fid, old_name in old:
                feat = table.GetFeature(fid)
                if old_name == style_name:
                    table.DeleteFeature(fid)
                elif feat is not None:
                    feat.SetField("useAsDefault", 0)
                    table.SetFeature(feat)
            feat = ogr.Feature(table.GetLayerDefn())
            for fname, value in (
                ("f_table_catalog", ""),
                ("f_table_schema", ""),
                ("f_table_name", str(name)),
                ("f_geometry_column", columns[str(name)]),
                ("styleName", style_name[:30]),
                ("styleQML", str(qml)),
                ("styleSLD", ""),
                ("useAsDefault", 1),
                ("description", description),
                ("owner", ""),
                ("ui", ""),
            ):
                feat.SetField(fname, value)
            feat.SetField("update_time", *stamp)
            table.CreateFeature(feat)
        table.CommitTransaction()
    except RuntimeError as exc:
        raise SlipMapFileError(f"cannot write styles into {shown!r}: {exc}") from exc
    finally:
        ds = None  # noqa: F841 - closes (and flushes) the dataset


def _geometry_coords(geom, ogr) -> np.ndarray:
    flat = ogr.GT_Flatten(geom.GetGeometryType())
    dim = 3 if geom.Is3D() else 2
    if flat == ogr.wkbPoint:
        return np.array(geom.GetPoint()[:dim], dtype=np.float64)
    if flat == ogr.wkbPolygon:
        geom = geom.GetGeometryRef(0)  # exterior ring
    return np.asarray(geom.GetPoints(), dtype=np.float64).reshape(-1, dim)


def read_gpkg_layer(path: PathLike, name: str) -> Tuple[List[np.ndarray], Dict[str, np.ndarray]]:
    """Read one layer of a GeoPackage (mainly for tests).

    Parameters
    ----------
    path : str or os.PathLike
    name : str
        Layer name.

    Returns
    -------
    geometries : list of numpy.ndarray
        As written by :func:`write_gpkg_layers`: ``(2|3,)`` points, ``(M, 2|3)`` lines,
        ``(M, 2|3)`` closed exterior rings (first vertex repeated at the end).
    fields : dict of str to numpy.ndarray
        Real -> float64 (NULL as NaN), Integer64 -> int64, boolean Integer -> bool,
        Integer -> int64, String -> object.
    """
    ogr, _ = _ogr()
    p = Path(path)
    if not p.is_file():
        raise SlipMapFileError(f"GeoPackage {str(p)!r} does not exist")
    try:
        ds = ogr.Open(str(p), 0)
    except RuntimeError as exc:
        raise SlipMapFileError(f"cannot read GeoPackage {str(p)!r}: {exc}") from exc
    try:
        lyr = ds.GetLayerByName(name)
        if lyr is None:
            raise InvalidParameterError(f"GeoPackage {str(p)!r} has no layer {name!r}")
        defn = lyr.GetLayerDefn()
        fdefs = [defn.GetFieldDefn(i) for i in range(defn.GetFieldCount())]
        geoms: List[np.ndarray] = []
        values: Dict[str, list] = {fd.GetName(): [] for fd in fdefs}
        for feat in lyr:
            g = feat.GetGeometryRef()
            geoms.append(_geometry_coords(g, ogr) if g is not None else np.empty(0))
            for fi, fd in enumerate(fdefs):
                col = values[fd.GetName()]
                ftype = fd.GetType()
                if not feat.IsFieldSetAndNotNull(fi):
                    col.append(np.nan if ftype == ogr.OFTReal else None)
                elif ftype == ogr.OFTReal:
                    col.append(feat.GetFieldAsDouble(fi))
                elif ftype in (ogr.OFTInteger, ogr.OFTInteger64):
                    col.append(feat.GetFieldAsInteger64(fi))
                else:
                    col.append(feat.GetFieldAsString(fi))
        fields: Dict[str, np.ndarray] = {}
        for fd in fdefs:
            fname, ftype = fd.GetName(), fd.GetType()
            vals = values[fname]
            if ftype == ogr.OFTReal:
                fields[fname] = np.asarray(vals, dtype=np.float64)
            elif ftype == ogr.OFTInteger and fd.GetSubType() == ogr.OFSTBoolean:
                fields[fname] = np.asarray([bool(v) for v in vals], dtype=bool)
            elif ftype in (ogr.OFTInteger, ogr.OFTInteger64) and None not in vals:
                fields[fname] = np.asarray(vals, dtype=np.int64)
            else:
                fields[fname] = np.asarray(vals, dtype=object)
    finally:
        ds = None  # noqa: F841
    return geoms, fields
