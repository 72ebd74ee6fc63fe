"""``slipmap:pointaccuracy``: the accuracy job (:mod:`slipmap.app.accuracy`) as a Processing
algorithm, and the point-accuracy parameters shared with ``slipmap:displacement``.

The point-accuracy options are declared once (:func:`slipmap.app.pointaccuracy.pa_options`);
most become parameters as they are. Four are QGIS widgets of their own, mapped back onto the
options' keys by :func:`pa_values`: the model enum (``MODEL``, or one per epoch), the per-axis
sigmas (``SIGMA_X``/``SIGMA_Y``/``SIGMA_Z``), the scanner (a list of the built-in ones plus
"JSON file" and ``SCANNER_FILE``) and the static scanner's position (a map point in any CRS,
reprojected to the cloud's, plus ``SCANNER_HEIGHT``).
"""

from __future__ import annotations

from qgis.core import (
    QgsCoordinateReferenceSystem,
    QgsProcessingException,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterPoint,
)

from ...app import accuracy as job
from ...app.options import JobSpec
from ...app.pointaccuracy import MODELS, PA_KEYS, SCANNER_NAMES, pa_options
from ._base import (
    SlipMapAlgorithm,
    add_parameters,
    advanced,
    is_set,
    options_from,
)

SCANNER_FROM_FILE = "JSON file (Scanner specification file)"
COV_NAMES = job.COVS
#: the point-accuracy options alone (their dialog labels in messages)
PA_SPEC = JobSpec("pointaccuracy", "Point accuracy", "", pa_options())
#: options QGIS shows as widgets of its own (see :func:`add_pa_parameters`)
_OWN_WIDGETS = ("pa_model", "sigma_xyz_m", "scanner", "scanner_position")
_SCANNER_FILE_LABEL = "Scanner specification file (JSON)"

PA_HELP = (
    "<b>Point accuracy</b> (Kusari, Glennie, Brooks and Ericksen 2019, IEEE TGRS 57(6), "
    "section II.E; Glennie 2007 for the propagated model): "
    "<i>constant</i> = the same isotropic <b>Sigma</b> (m, default 0.05 as the study) for "
    "every point; <i>axis</i> = <b>Sigma X / Y / Z</b> (m) per axis; <i>columns</i> = per-point "
    "sigmas (m) read from the LAS dimensions named in <b>Sigma columns</b> (comma-separated X,Y,Z "
    "names, default SigmaX,SigmaY,SigmaZ, e.g. written by this algorithm); <i>propagated</i> = "
    "covariance propagated from the scanner's range/angle accuracy, the beam footprint and, "
    "for a mobile/airborne survey, the <b>Trajectory</b> (SBET or CSV) and <b>Trajectory "
    "accuracy</b> (SMRMSG or CSV) interpolated at each point's GpsTime (needs GpsTime and "
    "ScanAngle dimensions), or, for a static (TLS) scan, the <b>Scanner position</b> (map "
    "point, any CRS; reprojected to the point cloud's) and <b>Scanner height</b> (m, "
    "elevation of the scanner origin in the cloud's vertical datum). <b>Scanner</b>: one of "
    "the built-in specifications or a <b>Scanner specification file</b> (JSON, units in the "
    "key names, e.g. range_sigma_m). <b>Beam footprint term</b>: add the incidence-angle "
    "footprint covariance (Schaer et al. 2007; default yes). "
    "<b>Point-accuracy configuration</b>: a JSON file "
    '({"before": {...}, "after": {...}} or one object for both, keys '
    "model, sigma, sigma_xyz, columns, trajectory, trajectory_accuracy, scanner, "
    "scanner_position, footprint); when given it replaces all the other point-accuracy "
    "parameters."
)


def _sigma(name, label, default):
    p = QgsProcessingParameterNumber(
        name, label, QgsProcessingParameterNumber.Double, defaultValue=default, minValue=1e-9
    )
    p.setHelp(PA_SPEC["sigma_xyz_m"].help)
    return p


def add_pa_parameters(alg, model_names, advanced_models=False):
    """The point-accuracy parameters: one model enum per name in ``model_names`` (e.g.
    ``{"MODEL": "Model"}``), then the settings shared by them (advanced except Sigma)."""
    for name, label in model_names.items():
        p = QgsProcessingParameterEnum(name, label, options=list(MODELS), defaultValue=0)
        p.setHelp(PA_SPEC["pa_model"].help)
        alg.addParameter(advanced(p) if advanced_models else p)
    add_parameters(alg, PA_SPEC, roles=("setting",), skip=_OWN_WIDGETS + ("footprint",))
    for axis in "XYZ":
        alg.addParameter(advanced(_sigma(f"SIGMA_{axis}", f"Sigma {axis}, axis model (m)", 0.05)))
    add_parameters(alg, PA_SPEC, roles=("input",), skip=("pa_config",))
    scanner = QgsProcessingParameterEnum(
        "SCANNER",
        PA_SPEC["scanner"].dialog_label,
        options=list(SCANNER_NAMES) + [SCANNER_FROM_FILE],
        defaultValue=0,
    )
    scanner.setHelp(PA_SPEC["scanner"].help)
    alg.addParameter(advanced(scanner))
    alg.addParameter(
        advanced(
            QgsProcessingParameterFile(
                "SCANNER_FILE", _SCANNER_FILE_LABEL, fileFilter="JSON (*.json)", optional=True
            )
        )
    )
    position = QgsProcessingParameterPoint(
        "SCANNER_POSITION", PA_SPEC["scanner_position"].dialog_label, optional=True
    )
    position.setHelp(PA_SPEC["scanner_position"].help)
    alg.addParameter(advanced(position))
    alg.addParameter(
        advanced(
            QgsProcessingParameterNumber(
                "SCANNER_HEIGHT",
                "Scanner height, static scan (m)",
                QgsProcessingParameterNumber.Double,
                defaultValue=0.0,
            )
        )
    )
    add_parameters(
        alg, PA_SPEC, roles=("setting",), skip=tuple(k for k in PA_KEYS if k != "footprint")
    )
    add_parameters(
        alg, PA_SPEC, roles=("input",), skip=tuple(k for k in PA_KEYS if k != "pa_config")
    )


def pa_values(alg, parameters, context, model_name, crs=None):
    """The values of the point-accuracy options QGIS shows as its own widgets, by option key:
    ``pa_model`` (from ``model_name``), ``sigma_xyz_m``, ``scanner``, ``scanner_position``
    (reprojected to ``crs``, the cloud's ``QgsCoordinateReferenceSystem``)."""
    model = MODELS[alg.parameterAsEnum(parameters, model_name, context)]
    values = {
        "pa_model": model,
        "sigma_xyz_m": [alg.parameterAsDouble(parameters, f"SIGMA_{a}", context) for a in "XYZ"],
    }
    k = alg.parameterAsEnum(parameters, "SCANNER", context)
    if k < len(SCANNER_NAMES):
        values["scanner"] = SCANNER_NAMES[k]
    else:
        spec = alg.parameterAsFile(parameters, "SCANNER_FILE", context)
        if spec:
            values["scanner"] = spec
        elif model == "propagated":
            raise QgsProcessingException(
                f'"{_SCANNER_FILE_LABEL}": choose a scanner specification JSON file, or pick a '
                f'built-in "{PA_SPEC["scanner"].dialog_label}" ({", ".join(SCANNER_NAMES)})'
            )
    if is_set(parameters, "SCANNER_POSITION"):
        crs = crs if crs is not None else QgsCoordinateReferenceSystem()
        pt = alg.parameterAsPoint(parameters, "SCANNER_POSITION", context, crs)
        z = alg.parameterAsDouble(parameters, "SCANNER_HEIGHT", context)
        values["scanner_position"] = [pt.x(), pt.y(), z]
    return values


def _input_crs(alg, parameters, context):
    """The CRS the points will be in: the CRS parameter, else the file's (header only)."""
    if is_set(parameters, "CRS"):
        crs = alg.parameterAsCrs(parameters, "CRS", context)
        if crs.isValid():
            return crs
    try:
        from ...core.io.las import read_las_header

        _, crs = read_las_header(alg.parameterAsFile(parameters, "INPUT", context))
    except Exception:  # noqa: BLE001 - the job reports an unreadable input by its label
        return QgsCoordinateReferenceSystem()
    return QgsCoordinateReferenceSystem.fromWkt(crs.to_wkt()) if crs is not None else None


class PointAccuracyAlgorithm(SlipMapAlgorithm):
    _id = "pointaccuracy"
    _name = "Point accuracy"
    _group = "Accuracy"
    _group_id = "accuracy"
    spec = job.SPEC

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            f"{job.SPEC.description}<br>"
            "<b>Input point cloud</b>: LAS/LAZ in a projected CRS (metres). <b>Model</b>: "
            "constant, axis, columns or propagated. "
            + PA_HELP
            + "<br><b>Full covariance</b>: also write the six covariance entries (default no; "
            "the propagated model has correlated axes that SigmaX/Y/Z alone lose).<br>"
            "<b>Output</b>: LAS/LAZ copy with the extra-bytes dimensions (the input is not "
            f"modified).<br>Method: {job.CITATION}."
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        add_parameters(self, job.SPEC, roles=("input",), skip=PA_KEYS)
        add_pa_parameters(self, {"MODEL": "Model"})
        add_parameters(self, job.SPEC, roles=("setting",), skip=PA_KEYS)
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "OUTPUT", job.SPEC["output_cloud"].dialog_label, "LAS (*.las);;LAZ (*.laz)"
            )
        )

    def _extra(self, parameters, context, crs=None):
        extra = pa_values(self, parameters, context, "MODEL", crs)
        extra["output_cloud"] = self.parameterAsFileOutput(parameters, "OUTPUT", context)
        return extra

    def job_extra(self, parameters, context):
        return self._extra(parameters, context)

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        extra = self._extra(parameters, context, _input_crs(self, parameters, context))
        opts = options_from(self, parameters, context, job.SPEC, extra=extra)
        result = self.run_job(job, opts, {"output_cloud": extra["output_cloud"]}, feedback)
        return {"OUTPUT": str(result.files["output_cloud"])}
