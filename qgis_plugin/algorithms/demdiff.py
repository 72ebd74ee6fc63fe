"""``slipmap:demdiff``: the DEM-difference job (:mod:`slipmap.app.dem_diff`) as a Processing
algorithm."""

from __future__ import annotations

from qgis.core import QgsProcessingParameterFileDestination, QgsProcessingParameterRasterDestination

from ...app import dem_diff as job
from ._base import (
    SlipMapAlgorithm,
    add_parameters,
)
from ._fields import (
    FIELDS_GROUP,
    add_optional_file_output,
    apply_diverging_style_on_load,
    file_outputs,
    help_text,
)

_FILES = ("raster", "summary", "plot")


class DemDifferenceAlgorithm(SlipMapAlgorithm):
    _id = "demdiff"
    _name = "DEM difference"
    _group, _group_id = FIELDS_GROUP
    spec = job.SPEC

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return help_text(
            job.SPEC,
            "a 3-band GeoTIFF in the point cloud's CRS (band 1 dz, band 2 z_before, band 3 "
            "z_after, metres; NaN = no data), styled with a diverging ramp centred on 0; a "
            "JSON summary (mean, median, std of dz); optionally a figure (PNG).",
            citation="Aryal (2014), chapter 3, section 3.1",
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        add_parameters(self, job.SPEC, roles=("input", "setting"))
        opt = job.SPEC["raster"]
        self.addParameter(QgsProcessingParameterRasterDestination("OUTPUT", opt.dialog_label))
        opt = job.SPEC["summary"]
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", opt.dialog_label, opt.file_filter)
        )
        add_optional_file_output(self, job.SPEC, "plot")

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        opts = self.job_options(parameters, context)
        outputs = file_outputs(self, parameters, context, job.SPEC, _FILES)
        self.run_job(job, opts, outputs, feedback)
        apply_diverging_style_on_load(context, outputs["raster"], "diverging")
        return {"OUTPUT": outputs["raster"], "SUMMARY": outputs["summary"], "PLOT": outputs["plot"]}
