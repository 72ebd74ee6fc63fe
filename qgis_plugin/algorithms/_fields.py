"""What the "Displacement fields" algorithms (``piv``, ``windowedicp``, ``demdiff``,
``strain``) share that is QGIS's own: the help text made from a job's options, vector sinks,
CRS conversion and the on-load styles. The jobs themselves live in :mod:`slipmap.app`."""

from __future__ import annotations

import numpy as np
from qgis.core import (
    QgsCoordinateReferenceSystem,
    QgsFeature,
    QgsFeatureSink,
    QgsFields,
    QgsGeometry,
    QgsPointXY,
    QgsProcessingException,
    QgsProcessingParameterFileDestination,
    QgsWkbTypes,
)
from qgis.PyQt.QtCore import QVariant

from ...app.summaries import finite
from ..compat import make_field
from ._base import (  # noqa: F401  (apply_*_style_on_load re-exported for the algorithms)
    apply_diverging_style_on_load,
    apply_style_on_load,
)

FIELDS_GROUP = ("Displacement fields", "fields")


def help_text(spec, outputs, *, sections=(), citation=None):
    """The algorithm's help as plain-text paragraphs (QGIS's dialog makes each line a
    paragraph; ``qgis_process help`` prints it as it is): the job's description, ``sections``
    (``(title, text)`` pairs), the outputs and the method's citation (``citation`` or the
    job's), once. Each parameter's own help is its tooltip in the dialog and its line under
    "Arguments" in ``qgis_process help``, so it is not repeated here."""
    parts = [spec.description]
    parts += [f"{title}: {text}" for title, text in sections]
    parts.append(f"Outputs: {outputs}")
    cite = citation or spec.citation
    if cite:
        parts.append(f"Method: {cite.rstrip('.')}.")
    return "\n\n".join(parts)


def add_optional_file_output(alg, spec, key):
    """An optional file destination of output ``key`` (e.g. a figure), not created by
    default."""
    opt = spec[key]
    p = QgsProcessingParameterFileDestination(
        opt.name_in("qgis"), opt.dialog_label, opt.file_filter, optional=True
    )
    p.setCreateByDefault(False)
    alg.addParameter(p)


def file_outputs(alg, parameters, context, spec, keys):
    """``{output key: path or None}`` of the destinations of outputs ``keys`` (rasters and
    files; an optional one left empty is None)."""
    from qgis.core import QgsProcessingParameterDefinition

    from ._base import is_set, raster_output

    out = {}
    for key in keys:
        name = spec[key].name_in("qgis")
        p = alg.parameterDefinition(name)
        optional = bool(p.flags() & QgsProcessingParameterDefinition.FlagOptional)
        if optional and not is_set(parameters, name, context):
            out[key] = None
        elif p.type() == "rasterDestination":
            out[key] = raster_output(alg, parameters, name, context)
        else:
            out[key] = alg.parameterAsFileOutput(parameters, name, context) or None
    return out


def qgs_crs(crs):
    """A ``QgsCoordinateReferenceSystem`` of a pyproj CRS (invalid when None)."""
    if crs is None:
        return QgsCoordinateReferenceSystem()
    return QgsCoordinateReferenceSystem.fromWkt(crs.to_wkt())


def sink_kinds(columns):
    """``(name, QVariant type)`` of every column: text as String, integers and booleans as
    Int, others Double."""
    kinds = []
    for name, values in columns.items():
        k = np.asarray(values).dtype.kind
        kinds.append(
            (
                name,
                QVariant.String if k in "OUS" else QVariant.Int if k in "iub" else QVariant.Double,
            )
        )
    return tuple(kinds)


def write_point_sink(alg, parameters, name, context, crs, x, y, columns):
    """Point features at (x, y) with ``columns`` (name -> (K,) array) as attributes.

    Non-finite numbers are written as NULL. Returns the sink's id (None: not requested).
    """
    return write_sink(
        alg,
        parameters,
        name,
        context,
        crs,
        QgsWkbTypes.Point,
        [QgsGeometry.fromPointXY(QgsPointXY(float(a), float(b))) for a, b in zip(x, y)],
        columns,
    )


def write_polygon_sink(alg, parameters, name, context, crs, rings, columns):
    """Polygon features (one (K, 2) ring each) with attributes, as :func:`write_point_sink`."""
    geoms = [QgsGeometry.fromPolygonXY([[QgsPointXY(*map(float, p)) for p in r]]) for r in rings]
    return write_sink(alg, parameters, name, context, crs, QgsWkbTypes.Polygon, geoms, columns)


def write_sink(alg, parameters, name, context, crs, wkb, geometries, columns):
    """Features (``geometries``, QgsGeometry) with the job's ``columns`` (name -> (K,) array:
    text, integer or real; NaN written as NULL) into the sink ``name``; its id, or None when
    it is not asked for."""
    kinds = sink_kinds(columns)
    fields = QgsFields()
    for key, kind in kinds:
        fields.append(make_field(key, kind))
    sink, dest_id = alg.parameterAsSink(parameters, name, context, fields, wkb, crs)
    if sink is None:
        return None
    cols = [np.asarray(columns[key]) for key, _ in kinds]
    for i, geom in enumerate(geometries):
        f = QgsFeature(fields)
        f.setGeometry(geom)
        f.setAttributes(
            [
                str(col[i])
                if kind == QVariant.String
                else (int(col[i]) if kind == QVariant.Int else finite(col[i]))
                for (_, kind), col in zip(kinds, cols)
            ]
        )
        if not sink.addFeature(f, QgsFeatureSink.FastInsert):
            raise QgsProcessingException(f"{name}: cannot write feature {i}")
    return dest_id
