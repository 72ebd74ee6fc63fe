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

#: the four point-accuracy models and their settings, compact plain text (help sections)
PA_HELP = (
    "constant = one isotropic Sigma (m; default 0.05, as the study) for every point; "
    "axis = Sigma X, Y and Z (m); "
    "columns = per-point sigmas (m) from the LAS dimensions named in Sigma columns (default "
    "SigmaX,SigmaY,SigmaZ, as Point accuracy writes them); "
    "propagated = from the Scanner's range and angle accuracy and the beam footprint, plus "
    "the Trajectory and its accuracy at each point's GpsTime (mobile or airborne; needs "
    "GpsTime and ScanAngle) or the Scanner position and height (a static scan). "
    "A Point-accuracy configuration (JSON) replaces all of these settings and may give each "
    "epoch its own."
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
    if is_set(parameters, "SCANNER_POSITION", context):
        crs = crs if crs is not None else QgsCoordinateReferenceSystem()
        pt = alg.parameterAsPoint(parameters, "SCANNER_POSITION", context, crs)
        z = alg.parameterAsDouble(parameters, "SCANNER_HEIGHT", context)
        values["scanner_position"] = [pt.x(), pt.y(), z]
    return values


def _input_crs(alg, parameters, context):
    """The CRS the points will be in: the CRS parameter, else the file's (header only)."""
    if is_set(parameters, "CRS", context):
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
        from ._fields import help_text

        return help_text(
            job.SPEC,
            "a LAS/LAZ copy with the extra-bytes dimensions SigmaX, SigmaY, SigmaZ (m) and, "
            "with Full covariance, the six covariance entries (m²; the propagated model's "
            "axes are correlated); the input is not modified.",
            sections=[("Point accuracy models", PA_HELP)],
            citation=job.CITATION,
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
