"""Helpers shared by the "Displacement fields" algorithms (``piv``, ``windowedicp``,
``demdiff``, ``strain``): reading both epochs, vector sinks, rasters, JSON-safe statistics,
citations and the diverging raster style centred on zero."""

from __future__ import annotations

from qgis.core import (
    QgsCoordinateReferenceSystem,
    QgsFeature,
    QgsFeatureSink,
    QgsFields,
    QgsGeometry,
    QgsPointXY,
    QgsProcessingException,
    QgsProcessingParameterFile,
    QgsWkbTypes,
)
from qgis.PyQt.QtCore import QVariant

from ...app.summaries import (  # noqa: F401  (re-exported for the field algorithms)
    finite,
    finite_stats,
    horizontal,
    icp_summary,
    json_safe,
)
from ..compat import make_field
from ._base import (  # noqa: F401  (advanced, apply_diverging_style_on_load re-exported)
    advanced,
    apply_diverging_style_on_load,
    read_cloud,
)

FIELDS_GROUP = ("Displacement fields", "fields")
CSV_FILTER = "CSV (*.csv *.txt)"
ARYAL = (
    "Aryal et al., Determining ground displacement fields of small spatial extent using "
    "terrestrial laser scanner data: a comparison of 3D methods applied to landslide "
    "monitoring (Aryal 2014, Landslide deformation character inferred from terrestrial laser "
    "scanner data, PhD dissertation, chapter 3)"
)
PIV_CITATION = f"Method: {ARYAL}, section 3.2.1 (PIV on gridded elevation)."
ICP_CITATION = (
    f"Method: {ARYAL}, section 3.2.2 (windowed ICP); point-to-plane ICP: Chen, Y. and "
    "Medioni, G. (1992), Object modelling by registration of multiple range images, Image and "
    "Vision Computing 10(3), 145-155."
)
CONTROL_HELP = (
    "<b>Control points</b> (optional): CSV with columns x,y,dx,dy[,dz] (m, the point cloud's "
    "CRS), e.g. GPS or feature tracking; the field is sampled bilinearly at them and the "
    "errors (estimate - control: RMSE, bias) go to the summary."
)

PIV_SINK_FIELDS = (
    ("dx", QVariant.Double),
    ("dy", QVariant.Double),
    ("dz", QVariant.Double),
    ("magnitude", QVariant.Double),
    ("azimuth_deg", QVariant.Double),
    ("snr", QVariant.Double),
    ("valid", QVariant.Int),
)


# --------------------------------------------------------------------------- shared helpers


def read_pair(before_path, after_path):
    """Both epochs as (N, 3) arrays (after reprojected to before's CRS), and the pyproj CRS."""
    from ...core.io.crs import reproject_points, same_crs

    first, second = read_cloud(before_path), read_cloud(after_path)
    xyz2 = second.xyz
    if first.crs is not None and second.crs is not None and not same_crs(first.crs, second.crs):
        xyz2 = reproject_points(second.xyz, second.crs, first.crs)
    crs = first.crs if first.crs is not None else second.crs
    return first.xyz, xyz2, crs


def qgs_crs(crs):
    """A ``QgsCoordinateReferenceSystem`` of a pyproj CRS (invalid when None)."""
    if crs is None:
        return QgsCoordinateReferenceSystem()
    return QgsCoordinateReferenceSystem.fromWkt(crs.to_wkt())


def crs_wkt(crs):
    return None if crs is None else crs.to_wkt()


def control_comparison(control_path, x, y, dx, dy, dz, spacing_m):
    """``compare_with_control`` of a field against a control CSV, as a dict (None: no CSV)."""
    if not control_path:
        return None
    from ...core.fields import compare_with_control
    from ...core.io.table import read_control_points

    cxy, cd = read_control_points(control_path)
    return compare_with_control(x, y, dx, dy, dz, cxy, cd, spacing_m=spacing_m).to_dict()


def add_control_parameter(alg):
    alg.addParameter(
        QgsProcessingParameterFile(
            "CONTROL",
            "Control points x,y,dx,dy[,dz] (CSV)",
            extension="",
            fileFilter=CSV_FILTER,
            optional=True,
        )
    )


def write_point_sink(alg, parameters, name, context, crs, x, y, columns, kinds):
    """Point features at (x, y) with ``columns`` (name -> (K,) array) as attributes.

    Non-finite numbers are written as NULL. Returns the sink's id (None: not requested).
    """
    return _write_sink(
        alg,
        parameters,
        name,
        context,
        crs,
        QgsWkbTypes.Point,
        [QgsGeometry.fromPointXY(QgsPointXY(float(a), float(b))) for a, b in zip(x, y)],
        columns,
        kinds,
    )


def _write_sink(alg, parameters, name, context, crs, wkb, geometries, columns, kinds):
    fields = QgsFields()
    for key, kind in kinds:
        fields.append(make_field(key, kind))
    sink, dest_id = alg.parameterAsSink(parameters, name, context, fields, wkb, crs)
    if sink is None:
        return None
    cols = [columns[key] for key, _ in kinds]
    for i, geom in enumerate(geometries):
        f = QgsFeature(fields)
        f.setGeometry(geom)
        attrs = []
        for (_, kind), col in zip(kinds, cols):
            attrs.append(int(col[i]) if kind == QVariant.Int else finite(col[i]))
        f.setAttributes(attrs)
        if not sink.addFeature(f, QgsFeatureSink.FastInsert):
            raise QgsProcessingException(f"{name}: cannot write feature {i}")
    return dest_id


def write_polygon_sink(alg, parameters, name, context, crs, rings, columns, kinds):
    """Polygon features (one (K, 2) ring each) with attributes, as :func:`write_point_sink`."""
    geoms = [QgsGeometry.fromPolygonXY([[QgsPointXY(*map(float, p)) for p in r]]) for r in rings]
    return _write_sink(
        alg, parameters, name, context, crs, QgsWkbTypes.Polygon, geoms, columns, kinds
    )


def write_raster(path, array, origin_xy, pixel_m, crs, names, metadata=None):
    """A float64 GeoTIFF (NaN = no data) through ``core.io.raster.write_geotiff``."""
    import numpy as np

    from ...core.io.raster import write_geotiff

    write_geotiff(
        path,
        np.asarray(array, dtype=np.float64),
        origin_xy=origin_xy,
        pixel_size_m=pixel_m,
        crs_wkt=crs_wkt(crs),
        band_names=list(names),
        metadata=metadata,
    )


def parse_windows(text):
    """Window sizes (pixels) from ``"64 32 16"`` / ``"64,32,16"``."""
    parts = str(text or "").replace(",", " ").replace(";", " ").split()
    try:
        wins = [int(p) for p in parts]
    except ValueError:
        raise QgsProcessingException(
            f"WINDOWS must be whole numbers of pixels separated by spaces (e.g. '64 32 16'), "
            f"got {text!r}"
        ) from None
    if not wins:
        raise QgsProcessingException(
            "WINDOWS: give at least one window size (pixels), e.g. 64 32 16"
        )
    return wins
