"""``slipmap:strain``: horizontal infinitesimal strain from a gridded displacement field."""

from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingException,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterCrs,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
    QgsWkbTypes,
)

from ._base import SlipMapAlgorithm, optional_number, progress_callback, slipmap_errors, write_json
from ._fields import (
    ARYAL,
    FIELDS_GROUP,
    advanced,
    apply_diverging_style_on_load,
    finite_stats,
    json_safe,
    write_raster,
)

BAND_HELP = (
    "exx, eyy, exy (tensor shear), rotation_rad (counter-clockwise), e1, e2 (principal, "
    "e1 >= e2), e1_azimuth_deg (clockwise from north), max_shear = (e1 - e2)/2, dilatation "
    "= exx + eyy"
)


def _number(value):
    """A float from an attribute value (NULL, '' or text that is not a number -> NaN)."""
    if value is None:
        return float("nan")
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


def read_vectors(source, valid_only):
    """Columns x, y, dx, dy[, dz] (float64) of a point layer or a table with x, y columns.

    Positions come from the point geometry when the layer has one, else from the x and y
    attributes (e.g. ``piv.csv`` / ``icp.csv`` opened as a table). Field names are matched
    case-insensitively; rows without a position are dropped.
    """
    import numpy as np

    names = {f.name().lower(): i for i, f in enumerate(source.fields())}
    missing = [k for k in ("dx", "dy") if k not in names]
    geometry = QgsWkbTypes.geometryType(source.wkbType())
    if geometry not in (QgsWkbTypes.PointGeometry, QgsWkbTypes.NullGeometry):
        raise QgsProcessingException(
            "FIELD must be a point layer or a table (CSV) of vectors, got "
            f"{QgsWkbTypes.displayString(source.wkbType())}"
        )
    use_geometry = geometry == QgsWkbTypes.PointGeometry
    if not use_geometry:
        missing += [k for k in ("x", "y") if k not in names]
    if missing:
        raise QgsProcessingException(
            f"FIELD has no {', '.join(missing)} field(s): give the vectors output of "
            "slipmap:piv / slipmap:windowedicp or a CSV with x, y, dx, dy[, dz] columns "
            f"(fields found: {', '.join(f.name() for f in source.fields())})"
        )
    want = ["dx", "dy"] + [k for k in ("dz", "valid") if k in names]
    rows = {k: [] for k in ["x", "y", *want]}
    for feature in source.getFeatures():
        attrs = feature.attributes()
        if use_geometry:
            geom = feature.geometry()
            if geom is None or geom.isEmpty():
                continue
            p = geom.constGet()
            x, y = p.x(), p.y()
        else:
            x, y = _number(attrs[names["x"]]), _number(attrs[names["y"]])
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        rows["x"].append(x)
        rows["y"].append(y)
        for k in want:
            rows[k].append(_number(attrs[names[k]]))
    cols = {k: np.asarray(v, dtype=np.float64) for k, v in rows.items()}
    if not cols["x"].size:
        raise QgsProcessingException("FIELD has no vector with a position")
    valid = None
    if valid_only and "valid" in cols:
        valid = cols["valid"] > 0.5
    return cols, valid


class StrainAlgorithm(SlipMapAlgorithm):
    _id = "strain"
    _name = "Strain from a displacement field"
    _group, _group_id = FIELDS_GROUP

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "Horizontal infinitesimal strain of a gridded displacement field: the vectors are "
            "put back on their regular grid, the displacement gradient is taken by central "
            "differences (one-sided next to gaps and edges) and the strain tensor, rotation "
            "and principal strains follow (extension positive).<br>"
            "<b>Displacement field</b>: the vectors output of slipmap:piv or "
            "slipmap:windowedicp (points with dx, dy[, dz] fields, m), or a CSV table "
            "(piv.csv / icp.csv of the command line: columns x, y, dx, dy[, dz, valid]). "
            "Positions must be in a projected CRS in metres and lie on a regular grid. "
            "<b>Vector spacing</b> (m, optional): the grid spacing; default inferred from the "
            "positions. <b>Valid vectors only</b> (advanced): leave out the vectors with "
            "valid = 0 (missing or replaced outliers of PIV). <b>CRS</b> (optional): the "
            "output CRS for a table without one.<br>"
            "<b>Outputs</b>: a 9-band GeoTIFF on the field's grid (" + BAND_HELP + "; "
            "dimensionless, NaN where the gradient is unknown), band 1 styled with a diverging "
            "ramp centred on 0; a JSON summary with statistics per band.<br>"
            "Strain fields from TLS displacement fields as in " + ARYAL + "."
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFeatureSource(
                "FIELD",
                "Displacement field (vectors layer or CSV)",
                [QgsProcessing.TypeVectorPoint, QgsProcessing.TypeVector],
            )
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                "SPACING",
                "Vector spacing (m; default inferred)",
                QgsProcessingParameterNumber.Double,
                optional=True,
                minValue=1e-9,
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterBoolean(
                    "VALID_ONLY", "Valid vectors only", defaultValue=False
                )
            )
        )
        self.addParameter(
            advanced(QgsProcessingParameterCrs("CRS", "CRS of a table field", optional=True))
        )
        self.addParameter(QgsProcessingParameterRasterDestination("OUTPUT", "Strain"))
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", "Strain summary", "JSON (*.json)")
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        import numpy as np

        source = self.parameterAsSource(parameters, "FIELD", context)
        if source is None:
            raise QgsProcessingException("FIELD: the layer or table cannot be read")
        spacing = optional_number(self, parameters, "SPACING", context)
        valid_only = self.parameterAsBoolean(parameters, "VALID_ONLY", context)
        crs = source.sourceCrs()
        if not crs.isValid() or QgsWkbTypes.geometryType(source.wkbType()) == (
            QgsWkbTypes.NullGeometry
        ):
            crs = self.parameterAsCrs(parameters, "CRS", context)
        if crs.isValid() and crs.isGeographic():
            raise QgsProcessingException(
                f"FIELD is in a geographic CRS ({crs.authid()}): strain needs positions in "
                "metres; reproject the vectors to a projected CRS first"
            )
        out = self.parameterAsOutputLayer(parameters, "OUTPUT", context)
        summary_path = self.parameterAsFileOutput(parameters, "SUMMARY", context)
        with slipmap_errors():
            import pyproj

            from ...core.fields import field_from_columns
            from ...core.strain import strain_field

            progress = progress_callback(feedback)
            progress(0.0, "reading the vectors")
            cols, valid = read_vectors(source, valid_only)
            field = field_from_columns(
                cols["x"],
                cols["y"],
                cols["dx"],
                cols["dy"],
                cols.get("dz"),
                spacing_m=spacing,
                valid=valid,
            )
            progress(0.5, "strain")
            bands = strain_field(field).bands()
            out_crs = pyproj.CRS.from_wkt(crs.toWkt()) if crs.isValid() else None
            write_raster(
                out,
                np.stack(list(bands.values())),
                field.origin_xy,
                field.spacing_m,
                out_crs,
                list(bands),
                {"strain": "infinitesimal, extension positive; max_shear = (e1-e2)/2"},
            )
            summary = {
                "command": "strain",
                "n_vectors": int(cols["x"].size),
                "shape": list(field.shape),
                "origin_xy": list(field.origin_xy),
                "spacing_m": list(field.spacing_m),
                "bands": {k: finite_stats(v) for k, v in bands.items()},
            }
            write_json(summary_path, json_safe(summary))
            progress(1.0, "strain done")
        apply_diverging_style_on_load(context, out, "strain")
        feedback.pushInfo(
            f"strain: {field.shape[0]} x {field.shape[1]} cells of "
            f"{field.spacing_m[0]:g} x {field.spacing_m[1]:g} m"
        )
        return {"OUTPUT": out, "SUMMARY": summary_path}
