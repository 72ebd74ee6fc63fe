"""``slipmap:strain``: the strain job (:mod:`slipmap.app.strain`) as a Processing algorithm;
it reads the vectors of a point layer or a table itself (QGIS's features)."""

from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingException,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterRasterDestination,
    QgsWkbTypes,
)

from ...app import strain as job
from ._base import (
    SlipMapAlgorithm,
    add_parameters,
    options_from,
)
from ._fields import (
    FIELDS_GROUP,
    add_optional_file_output,
    apply_diverging_style_on_load,
    file_outputs,
    help_text,
)

_FILES = ("raster", "summary", "plot")
_LABEL = f'"{job.SPEC["field"].dialog_label}"'


def _number(value):
    """A float from an attribute value (NULL, '' or text that is not a number -> NaN)."""
    if value is None:
        return float("nan")
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def read_vectors(source):
    """Columns x, y, dx, dy[, dz, valid] (float64) of a point layer or a table with x, y.

    Positions come from the point geometry when the layer has one, else from the x and y
    attributes (e.g. ``piv.csv`` / ``icp.csv`` opened as a table). Field names are matched
    case-insensitively; rows without a position are dropped (and counted in the log).
    """
    import numpy as np

    names = {f.name().lower(): i for i, f in enumerate(source.fields())}
    missing = [k for k in ("dx", "dy") if k not in names]
    geometry = QgsWkbTypes.geometryType(source.wkbType())
    if geometry not in (QgsWkbTypes.PointGeometry, QgsWkbTypes.NullGeometry):
        raise QgsProcessingException(
            f"{_LABEL} must be a point layer or a table (CSV) of vectors, got "
            f"{QgsWkbTypes.displayString(source.wkbType())}"
        )
    use_geometry = geometry == QgsWkbTypes.PointGeometry
    if not use_geometry:
        missing += [k for k in ("x", "y") if k not in names]
    if missing:
        raise QgsProcessingException(
            f"{_LABEL} has no {', '.join(missing)} field(s): give the vectors output of "
            "slipmap:piv / slipmap:windowedicp or a CSV with x, y, dx, dy[, dz] columns "
            f"(fields found: {', '.join(f.name() for f in source.fields())})"
        )
    want = ["dx", "dy"] + [k for k in ("dz", "valid") if k in names]
    rows = {k: [] for k in ["x", "y", *want]}
    dropped = 0
    for feature in source.getFeatures():
        attrs = feature.attributes()
        if use_geometry:
            geom = feature.geometry()
            if geom is None or geom.isEmpty():
                dropped += 1
                continue
            p = geom.constGet()
            x, y = p.x(), p.y()
        else:
            x, y = _number(attrs[names["x"]]), _number(attrs[names["y"]])
        if not (np.isfinite(x) and np.isfinite(y)):
            dropped += 1
            continue
        rows["x"].append(x)
        rows["y"].append(y)
        for k in want:
            rows[k].append(_number(attrs[names[k]]))
    cols = {k: np.asarray(v, dtype=np.float64) for k, v in rows.items()}
    if not cols["x"].size:
        raise QgsProcessingException(f"{_LABEL} has no vector with a position")
    return cols, dropped


class StrainAlgorithm(SlipMapAlgorithm):
    _id = "strain"
    _name = "Strain from a displacement field"
    _group, _group_id = FIELDS_GROUP
    spec = job.SPEC

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return help_text(
            job.SPEC,
            "a 9-band GeoTIFF on the field's grid (" + job.BAND_HELP + "; dimensionless, NaN "
            "where the gradient is unknown), band 1 styled with a diverging ramp centred on 0; "
            "a JSON summary with statistics per band; optionally a figure (PNG). The field is "
            "the vectors output of slipmap:piv or slipmap:windowedicp, or a CSV table "
            "(piv.csv / icp.csv: columns x, y, dx, dy[, dz, valid]); positions in a projected "
            "CRS in metres on a regular grid.",
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        field = job.SPEC["field"]
        p = QgsProcessingParameterFeatureSource(
            "FIELD", field.dialog_label, [QgsProcessing.TypeVectorPoint, QgsProcessing.TypeVector]
        )
        p.setHelp(  # the CLI's option also reads GeoTIFFs (with --dy): not this layer's
            "the displacement field: the vectors layer of slipmap:piv or slipmap:windowedicp, "
            "or a CSV table (piv.csv / icp.csv: columns x, y, dx, dy[, dz, valid])"
        )
        self.addParameter(p)
        add_parameters(self, job.SPEC, roles=("input", "setting"))
        self.addParameter(
            QgsProcessingParameterRasterDestination("OUTPUT", job.SPEC["raster"].dialog_label)
        )
        opt = job.SPEC["summary"]
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", opt.dialog_label, opt.file_filter)
        )
        add_optional_file_output(self, job.SPEC, "plot")

    def job_extra(self, parameters, context):
        return {"out": "-", "field": "-"}

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        source = self.parameterAsSource(parameters, "FIELD", context)
        if source is None:
            raise QgsProcessingException(f"{_LABEL}: the layer or table cannot be read")
        name = source.sourceName() or "the field"
        opts = options_from(self, parameters, context, job.SPEC, extra={"out": "-", "field": name})
        outputs = file_outputs(self, parameters, context, job.SPEC, _FILES)
        layer_crs = source.sourceCrs()
        crs = None
        if layer_crs.isValid() and QgsWkbTypes.geometryType(source.wkbType()) != (
            QgsWkbTypes.NullGeometry
        ):
            import pyproj

            crs = pyproj.CRS.from_wkt(layer_crs.toWkt())
        cols, dropped = read_vectors(source)
        if dropped:
            feedback.pushWarning(f"{name}: {dropped} feature(s) without a position left out")
        self.run_job(job, opts, outputs, feedback, columns=cols, crs=crs, what=name)
        apply_diverging_style_on_load(context, outputs["raster"], "strain")
        return {"OUTPUT": outputs["raster"], "SUMMARY": outputs["summary"], "PLOT": outputs["plot"]}
