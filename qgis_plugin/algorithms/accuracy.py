"""``slipmap:pointaccuracy``: per-point accuracy written into a LAS copy, and the point-accuracy
parameters shared with ``slipmap:displacement``.

The parameters map one to one onto the settings dict of ``slipmap.app.pointaccuracy`` (the CLI's
``--pa`` flags and ``--pa-config`` file), which turns them into covariances.
"""

from __future__ import annotations

import contextlib

from qgis.core import (
    QgsProcessingException,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterPoint,
    QgsProcessingParameterString,
)

from ._base import (
    LAS_FILTER,
    LAS_OUTPUT_FILTER,
    SlipMapAlgorithm,
    advanced,
    is_set,
    progress_callback,
    read_cloud,
    slipmap_errors,
)

MODELS = ("constant", "axis", "columns", "propagated")
#: names of ``core.accuracy.SCANNERS`` (a test keeps them equal; not imported from the core,
#: which would load numpy and scipy each time QGIS builds the algorithm)
SCANNER_NAMES = ("leica-als60", "optech-orion", "riegl-vz400")
SCANNER_FROM_FILE = "JSON file (Scanner specification file)"
TRAJECTORY_FILTER = "Trajectory (*.sbet *.out *.csv *.txt);;All files (*.*)"
ACCURACY_FILTER = "Trajectory accuracy (*.smrmsg *.csv *.txt);;All files (*.*)"
COV_NAMES = ("CovXX", "CovYY", "CovZZ", "CovXY", "CovXZ", "CovYZ")

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
    "<b>Point-accuracy configuration</b>: a JSON file as "
    'the CLI\'s --pa-config ({"before": {...}, "after": {...}} or one object for both, keys '
    "model, sigma, sigma_xyz, columns, trajectory, trajectory_accuracy, scanner, "
    "scanner_position, footprint); when given it replaces all the other point-accuracy "
    "parameters."
)


#: the CLI flags that ``slipmap.app.pointaccuracy`` messages name, and the parameters here
FLAGS = (
    ("--trajectory-accuracy", "TRAJECTORY_ACCURACY"),
    ("--trajectory", "TRAJECTORY"),
    ("--sigma-columns", "SIGMA_COLUMNS"),
    ("--sigma-xyz", "SIGMA_X/Y/Z"),
    ("--scanner-spec", "SCANNER / SCANNER_FILE"),
    ("--scanner-position", "SCANNER_POSITION"),
    ("--pa-config", "PA_CONFIG"),
    ("--pa ", "the point-accuracy model "),
)


@contextlib.contextmanager
def pa_errors():
    """:func:`slipmap_errors` with the CLI flags in point-accuracy messages replaced by the
    names of these parameters."""
    try:
        with slipmap_errors():
            yield
    except QgsProcessingException as exc:
        text = str(exc)
        for flag, name in FLAGS:
            text = text.replace(flag, name)
        raise QgsProcessingException(text) from exc


def _sigma(name, label, default, optional=False):
    return QgsProcessingParameterNumber(
        name,
        label,
        QgsProcessingParameterNumber.Double,
        defaultValue=default,
        minValue=1e-9,
        optional=optional,
    )


def add_pa_parameters(alg, model_names, advanced_models=False):
    """The point-accuracy parameters: one model enum per name in ``model_names`` (e.g.
    ``{"MODEL": "Model"}``), then the model settings shared by them (advanced except SIGMA)."""
    for name, label in model_names.items():
        p = QgsProcessingParameterEnum(name, label, options=list(MODELS), defaultValue=0)
        alg.addParameter(advanced(p) if advanced_models else p)
    alg.addParameter(_sigma("SIGMA", "Sigma, constant model (m)", 0.05))
    for axis in "XYZ":
        alg.addParameter(advanced(_sigma(f"SIGMA_{axis}", f"Sigma {axis}, axis model (m)", 0.05)))
    alg.addParameter(
        advanced(
            QgsProcessingParameterString(
                "SIGMA_COLUMNS",
                "Sigma columns, columns model (X,Y,Z dimension names)",
                defaultValue="SigmaX,SigmaY,SigmaZ",
                optional=True,
            )
        )
    )
    alg.addParameter(
        advanced(
            QgsProcessingParameterFile(
                "TRAJECTORY",
                "Trajectory, propagated model (SBET or CSV)",
                fileFilter=TRAJECTORY_FILTER,
                optional=True,
            )
        )
    )
    alg.addParameter(
        advanced(
            QgsProcessingParameterFile(
                "TRAJECTORY_ACCURACY",
                "Trajectory accuracy, propagated model (SMRMSG or CSV)",
                fileFilter=ACCURACY_FILTER,
                optional=True,
            )
        )
    )
    names = list(SCANNER_NAMES) + [SCANNER_FROM_FILE]
    alg.addParameter(
        advanced(
            QgsProcessingParameterEnum(
                "SCANNER", "Scanner, propagated model", options=names, defaultValue=0
            )
        )
    )
    alg.addParameter(
        advanced(
            QgsProcessingParameterFile(
                "SCANNER_FILE",
                "Scanner specification file (JSON)",
                fileFilter="JSON (*.json)",
                optional=True,
            )
        )
    )
    alg.addParameter(
        advanced(
            QgsProcessingParameterPoint(
                "SCANNER_POSITION", "Scanner position, static (TLS) scan", optional=True
            )
        )
    )
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
    alg.addParameter(
        advanced(
            QgsProcessingParameterBoolean(
                "FOOTPRINT", "Beam footprint term, propagated model", defaultValue=True
            )
        )
    )
    alg.addParameter(
        advanced(
            QgsProcessingParameterFile(
                "PA_CONFIG",
                "Point-accuracy configuration (JSON, as the CLI's --pa-config)",
                fileFilter="JSON (*.json)",
                optional=True,
            )
        )
    )


def pa_settings(alg, parameters, context, model_name, crs):
    """The ``slipmap.app.pointaccuracy`` settings dict of the model chosen in ``model_name``.

    ``crs`` is the point cloud's ``QgsCoordinateReferenceSystem`` (the scanner position is
    reprojected to it). Raises ``QgsProcessingException`` naming the parameter at fault.
    """
    model = MODELS[alg.parameterAsEnum(parameters, model_name, context)]
    s = {"model": model}
    if model == "constant":
        s["sigma"] = alg.parameterAsDouble(parameters, "SIGMA", context)
    elif model == "axis":
        s["sigma_xyz"] = [alg.parameterAsDouble(parameters, f"SIGMA_{a}", context) for a in "XYZ"]
    elif model == "columns":
        text = alg.parameterAsString(parameters, "SIGMA_COLUMNS", context) or ""
        names = [c.strip() for c in text.split(",") if c.strip()]
        if names and len(names) != 3:
            raise QgsProcessingException(
                f"SIGMA_COLUMNS: give three comma-separated dimension names (X,Y,Z), got {text!r}"
            )
        if names:
            s["columns"] = names
    else:
        names = list(SCANNER_NAMES)
        k = alg.parameterAsEnum(parameters, "SCANNER", context)
        if k < len(names):
            s["scanner"] = names[k]
        else:
            spec = alg.parameterAsFile(parameters, "SCANNER_FILE", context)
            if not spec:
                raise QgsProcessingException(
                    "SCANNER_FILE: choose a scanner specification JSON file, or pick a built-in "
                    f"SCANNER ({', '.join(names)})"
                )
            s["scanner"] = spec
        s["footprint"] = alg.parameterAsBoolean(parameters, "FOOTPRINT", context)
        if is_set(parameters, "SCANNER_POSITION"):
            pt = alg.parameterAsPoint(parameters, "SCANNER_POSITION", context, crs)
            z = alg.parameterAsDouble(parameters, "SCANNER_HEIGHT", context)
            s["scanner_position"] = [pt.x(), pt.y(), z]
        else:
            traj = alg.parameterAsFile(parameters, "TRAJECTORY", context)
            acc = alg.parameterAsFile(parameters, "TRAJECTORY_ACCURACY", context)
            if not traj or not acc:
                raise QgsProcessingException(
                    f"{model_name} propagated: set TRAJECTORY and TRAJECTORY_ACCURACY (mobile or "
                    "airborne survey) or SCANNER_POSITION (static scan)"
                )
            s["trajectory"], s["trajectory_accuracy"] = traj, acc
    return s


def pa_config(alg, parameters, context):
    """``{"before": settings, "after": settings}`` from PA_CONFIG, or None when it is unset."""
    path = alg.parameterAsFile(parameters, "PA_CONFIG", context)
    if not path:
        return None
    with pa_errors():
        from ...app.pointaccuracy import load_config

        return load_config(path)


def cloud_crs(cloud):
    """The ``QgsCoordinateReferenceSystem`` of a ``PointCloud`` (invalid when it has none)."""
    from qgis.core import QgsCoordinateReferenceSystem

    if cloud.crs is None:
        return QgsCoordinateReferenceSystem()
    return QgsCoordinateReferenceSystem.fromWkt(cloud.crs.to_wkt())


class PointAccuracyAlgorithm(SlipMapAlgorithm):
    _id = "pointaccuracy"
    _name = "Point accuracy"
    _group = "Accuracy"
    _group_id = "accuracy"

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "Writes a copy of a point cloud with the per-point accuracy dimensions SigmaX, "
            "SigmaY, SigmaZ (m) and, optionally, the full covariance CovXX, CovYY, CovZZ, CovXY, "
            "CovXZ, CovYZ (m²): the a-priori point accuracy that weights the planar "
            "registration of <i>Fault slip</i> (as the CLI's <tt>slipmap accuracy</tt>).<br>"
            "<b>Input point cloud</b>: LAS/LAZ in a projected CRS (metres). <b>Model</b>: "
            "constant, axis, columns or propagated. "
            + PA_HELP
            + "<br><b>Full covariance</b>: also write the six covariance entries (default no; "
            "the propagated model has correlated axes that SigmaX/Y/Z alone lose).<br>"
            "<b>Output</b>: LAS/LAZ copy with the extra-bytes dimensions (the input is not "
            "modified)."
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFile("INPUT", "Input point cloud", fileFilter=LAS_FILTER)
        )
        add_pa_parameters(self, {"MODEL": "Model"})
        self.addParameter(
            QgsProcessingParameterBoolean(
                "FULL_COVARIANCE", "Full covariance (CovXX..CovYZ, m²)", defaultValue=False
            )
        )
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "OUTPUT", "Point cloud with SigmaX/Y/Z", LAS_OUTPUT_FILTER
            )
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        path = self.parameterAsFile(parameters, "INPUT", context)
        out = self.parameterAsFileOutput(parameters, "OUTPUT", context)
        full = self.parameterAsBoolean(parameters, "FULL_COVARIANCE", context)
        config = pa_config(self, parameters, context)
        progress = progress_callback(feedback)
        with slipmap_errors():
            import numpy as np

            from ...app.pointaccuracy import covariance_matrices
            from ...core.accuracy import covariance_to_sigmas, covariance_to_six
            from ...core.io.atomic import check_not_input
            from ...core.io.las import write_las

            check_not_input(out, [path])
            cloud = read_cloud(path)
            settings = (
                config["before"]
                if config is not None
                else pa_settings(self, parameters, context, "MODEL", cloud_crs(cloud))
            )
            progress(0.2, f"point accuracy ({settings['model']})")
            with pa_errors():
                cov = covariance_matrices(cloud, None, settings)
            sig = covariance_to_sigmas(cov)
            progress(0.6, "writing")
            extra = {"SigmaX": sig[:, 0], "SigmaY": sig[:, 1], "SigmaZ": sig[:, 2]}
            if full:
                six = covariance_to_six(cov)
                extra.update({name: six[:, k] for k, name in enumerate(COV_NAMES)})
            write_las(out, cloud, extra_dims=extra, inputs=[path])
        med = np.median(sig, axis=0)
        feedback.pushInfo(
            f"point accuracy ({settings['model']}): median sigma x {med[0]:.4f}, "
            f"y {med[1]:.4f}, z {med[2]:.4f} m; wrote {out}"
        )
        return {"OUTPUT": out}
