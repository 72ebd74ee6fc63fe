"""``slipmap:roughness``: the roughness job (:mod:`slipmap.app.roughness`) as a Processing
algorithm: one cell size, its GeoTIFF and cells' CSV (the job's writers), optionally the
summary and the per-point copy."""

from __future__ import annotations

from qgis.core import (
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
)

from ...app import roughness as job
from ._base import SlipMapAlgorithm, add_parameters, apply_style_on_load, raster_output

_CELL = job.SPEC["cell_sizes_m"]
_POINTS = job.SPEC["points_out"]


class RoughnessAlgorithm(SlipMapAlgorithm):
    _id = "roughness"
    _name = "Surface roughness"
    _group = "Roughness"
    _group_id = "roughness"
    spec = job.SPEC

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        from ._fields import help_text

        return help_text(
            job.SPEC,
            "a GeoTIFF on the map plane (bands "
            + ", ".join(job.BANDS)
            + "; the point cloud's CRS; cells stacked along the map normal are averaged; NaN "
            "= no data), a CSV with one row per cell ("
            + job.CSV_HEADER
            + "), optionally the JSON summary (Table 1 per cell size) and a copy of the point "
            "cloud with a Roughness dimension.",
            sections=[("Input", "a LAS/LAZ file in a projected CRS (metres).")],
            citation=job.CITATION,
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        add_parameters(self, job.SPEC, roles=("input",))
        cell = QgsProcessingParameterNumber(
            "CELL",
            _CELL.dialog_label,
            QgsProcessingParameterNumber.Double,
            defaultValue=_CELL.default[0],
            minValue=1e-6,
        )
        cell.setHelp(_CELL.help)
        self.addParameter(cell)
        add_parameters(self, job.SPEC, roles=("setting",))
        self.addParameter(QgsProcessingParameterRasterDestination("OUTPUT", "Roughness (GeoTIFF)"))
        self.addParameter(
            QgsProcessingParameterFileDestination("CSV", "Roughness per cell", "CSV (*.csv)")
        )
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "SUMMARY",
                "Roughness summary",
                "JSON (*.json)",
                optional=True,
                createByDefault=False,
            )
        )
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "POINTS",
                _POINTS.dialog_label,
                _POINTS.file_filter,
                optional=True,
                createByDefault=False,
            )
        )

    def _outputs(self, parameters, context):
        def dest(name):
            return self.parameterAsFileOutput(parameters, name, context) or None

        return {
            "geotiff": raster_output(self, parameters, "OUTPUT", context),
            "csv": dest("CSV"),
            "summary": dest("SUMMARY"),
            "points_out": dest("POINTS"),
        }

    def job_extra(self, parameters, context):
        return {
            "cell_sizes_m": [self.parameterAsDouble(parameters, "CELL", context)],
            "points_out": self._outputs(parameters, context)["points_out"],
        }

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        opts = self.job_options(parameters, context)
        outputs = self._outputs(parameters, context)
        self.run_job(job, opts, outputs, feedback)
        if outputs["geotiff"]:  # the .qml the job wrote beside it: band 1 on its ramp
            apply_style_on_load(context, outputs["geotiff"], "roughness")
        return {
            "OUTPUT": outputs["geotiff"],
            "CSV": outputs["csv"],
            "SUMMARY": outputs["summary"],
            "POINTS": outputs["points_out"],
        }
