"""``slipmap:planes``: the planes job (:mod:`slipmap.app.planes`) as a Processing algorithm."""

from __future__ import annotations

from qgis.core import (
    QgsProcessingOutputNumber,
    QgsProcessingParameterFileDestination,
)

from ...app import planes as job
from ._base import (
    SlipMapAlgorithm,
    add_parameters,
)

THRESHOLD_HELP = (
    "Segmentation thresholds (advanced) left empty are estimated from the data (point spacing "
    "and noise from surface-like octree nodes); the values used are written to the summary."
)


class PlanesAlgorithm(SlipMapAlgorithm):
    _id = "planes"
    _name = "Planar segmentation"
    _group = "Segmentation"
    _group_id = "segmentation"
    spec = job.SPEC

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            f"{job.SPEC.description}\n\n"
            "Input: a LAS/LAZ file in a projected CRS (metres). Ground (class 2) is left out "
            "of a classified cloud unless classes are given.\n\n"
            f"{THRESHOLD_HELP}\n\n"
            "Outputs: a LAS/LAZ copy with the PlaneId dimension, a JSON summary (one record "
            "per plane: centroid, normal, number of points, RMS in m) and the number of "
            f"planes.\n\nMethod: {job.CITATION}."
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        add_parameters(self, job.SPEC, roles=("input", "setting"))
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "OUTPUT", job.SPEC["labelled_cloud"].dialog_label, "LAS (*.las);;LAZ (*.laz)"
            )
        )
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "SUMMARY", job.SPEC["summary"].dialog_label, "JSON (*.json)"
            )
        )
        self.addOutput(QgsProcessingOutputNumber("N_PLANES", "Number of planes"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        opts = self.job_options(parameters, context)
        outputs = {
            "labelled_cloud": self.parameterAsFileOutput(parameters, "OUTPUT", context),
            "summary": self.parameterAsFileOutput(parameters, "SUMMARY", context),
        }
        result = self.run_job(job, opts, outputs, feedback)
        planes = result.data[0]
        return {
            "OUTPUT": outputs["labelled_cloud"],
            "SUMMARY": outputs["summary"],
            "N_PLANES": len(planes),
        }
