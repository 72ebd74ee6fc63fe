"""``slipmap:pointaccuracy``: per-point accuracy SigmaX/Y/Z written into a LAS copy."""

from __future__ import annotations

from qgis.core import (
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
)

from ._base import (
    LAS_FILTER,
    LAS_OUTPUT_FILTER,
    SlipMapAlgorithm,
    progress_callback,
    read_cloud,
    slipmap_errors,
)

MODELS = ("constant", "axis")


def _sigma(name, label, default):
    return QgsProcessingParameterNumber(
        name, label, QgsProcessingParameterNumber.Double, defaultValue=default, minValue=0.0
    )


class PointAccuracyAlgorithm(SlipMapAlgorithm):
    _id = "pointaccuracy"
    _name = "Point accuracy"
    _group = "Accuracy"
    _group_id = "accuracy"

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "Writes a copy of a point cloud with the per-point accuracy dimensions SigmaX, "
            "SigmaY, SigmaZ (m), the a-priori point accuracy of the planar registration "
            "(Kusari, Glennie, Brooks and Ericksen 2019, IEEE TGRS 57(6), section II.E).<br>"
            "<b>Input point cloud</b>: LAS/LAZ. <b>Model</b>: constant = the same isotropic "
            "sigma for every axis; axis = one sigma per axis. <b>Sigma</b> (m): isotropic "
            "accuracy of the constant model (default 0.05, as the study). <b>Sigma X / Y / Z</b> "
            "(m): per-axis accuracy of the axis model.<br><b>Output</b>: LAS/LAZ copy with "
            "SigmaX/SigmaY/SigmaZ extra-bytes dimensions."
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFile("INPUT", "Input point cloud", fileFilter=LAS_FILTER)
        )
        self.addParameter(
            QgsProcessingParameterEnum("MODEL", "Model", options=list(MODELS), defaultValue=0)
        )
        self.addParameter(_sigma("SIGMA", "Sigma, constant model (m)", 0.05))
        self.addParameter(_sigma("SIGMA_X", "Sigma X, axis model (m)", 0.05))
        self.addParameter(_sigma("SIGMA_Y", "Sigma Y, axis model (m)", 0.05))
        self.addParameter(_sigma("SIGMA_Z", "Sigma Z, axis model (m)", 0.05))
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "OUTPUT", "Point cloud with SigmaX/Y/Z", LAS_OUTPUT_FILTER
            )
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        path = self.parameterAsFile(parameters, "INPUT", context)
        out = self.parameterAsFileOutput(parameters, "OUTPUT", context)
        model = MODELS[self.parameterAsEnum(parameters, "MODEL", context)]
        settings = {"model": model}
        if model == "constant":
            settings["sigma"] = self.parameterAsDouble(parameters, "SIGMA", context)
        else:
            settings["sigma_xyz"] = [
                self.parameterAsDouble(parameters, k, context)
                for k in ("SIGMA_X", "SIGMA_Y", "SIGMA_Z")
            ]
        progress = progress_callback(feedback)
        with slipmap_errors():
            from ...core.accuracy import covariance_to_sigmas
            from ...core.io.atomic import check_not_input
            from ...core.io.las import write_las
            from ...pointaccuracy import covariance_matrices

            check_not_input(out, [path])
            cloud = read_cloud(path)
            progress(0.2, "point accuracy")
            cov = covariance_matrices(cloud, None, settings)
            sig = covariance_to_sigmas(cov)
            progress(0.5, "writing")
            extra = {"SigmaX": sig[:, 0], "SigmaY": sig[:, 1], "SigmaZ": sig[:, 2]}
            write_las(out, cloud, extra_dims=extra, inputs=[path])
        return {"OUTPUT": out}
