"""``slipmap:displacement``: the slip job (:mod:`slipmap.app.slip`) as a Processing algorithm.

The job reads both epochs, computes and writes the summary, report, figures and the windows'
GeoTIFF; this algorithm maps its parameters onto the job's options (the fault trace is a line
layer, the point-accuracy model one per epoch) and the job's columns onto its vector sinks.
"""

from __future__ import annotations

import json

import numpy as np
from qgis.core import (
    QgsGeometry,
    QgsPoint,
    QgsPointXY,
    QgsProcessing,
    QgsProcessingException,
    QgsProcessingOutputHtml,
    QgsProcessingOutputNumber,
    QgsProcessingOutputString,
    QgsProcessingParameterFeatureSink,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterRasterDestination,
    QgsWkbTypes,
)

from ...app import slip as job
from ...app.pointaccuracy import MODELS, PA_KEYS
from ...app.summaries import stochastic_outputs
from ._base import (
    SlipMapAlgorithm,
    add_parameters,
    apply_diverging_style_on_load,
    apply_style_on_load,
    cloud_path,
    is_set,
    options_from,
    progress_callback,
    raster_output,
    slipmap_errors,
    source_parts,
)
from ._fields import help_text, qgs_crs, write_sink
from .accuracy import PA_HELP, add_pa_parameters, pa_values

#: options this algorithm shows as widgets of its own (point accuracy: see accuracy.py)
_OWN = PA_KEYS + ("pa_model_after",)
#: vector sinks -> the job's output key (their "asked for" checks)
_SINKS = {"TILES": "tiles", "STRIPS": "strips"}


def _before_crs(path):
    """The before epoch's CRS from its header (the scanner position is reprojected to it)."""
    from qgis.core import QgsCoordinateReferenceSystem

    try:
        from ...core.io.las import read_las_header

        _, crs = read_las_header(path)
    except Exception:  # noqa: BLE001 - the job reports an unreadable epoch by its label
        return QgsCoordinateReferenceSystem()
    return qgs_crs(crs)


class DisplacementAlgorithm(SlipMapAlgorithm):
    _id = "displacement"
    _name = "Fault slip (displacement)"
    _group = "Slip"
    _group_id = "slip"
    spec = job.SPEC

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return help_text(
            job.SPEC,
            "a JSON summary and an HTML report beside it (tables, plots); Matched planes "
            "(before-epoch centroids: side, plane ids, normal, weight 1 full / below 1 "
            "down-weighted / 0 rejected, w_test, offset_mm, misclosure_mm); Tiles (polygons) "
            "and Strips (points on the trace), each with its own motion right_lateral, opening, "
            "dz, dx, dy and their sigmas in m, status; Moving windows (GeoTIFF, one pixel per "
            "window, bands " + ", ".join(job.WINDOW_BANDS) + ", each window's own motion); "
            "the right-lateral slip and its sigma (m, the model's and the white-noise one), "
            "n_eff per side and the variance components.",
            sections=[
                ("Point accuracy models (one per epoch)", PA_HELP),
                (
                    "Sign convention",
                    "right_lateral + = right-lateral (dextral) shear, whatever direction the "
                    "trace was digitised in: the slip of the right side against the left, and "
                    "on each side's tiles, strips and windows that side's own motion in the "
                    "same sense (a left and a right value add up to the slip); opening + = the "
                    "sides move apart; dz + = up (the slip: the right side of the trace as "
                    "digitised up; the report names it by compass direction). See "
                    "docs/methods.md, 'Sign convention'.",
                ),
                (
                    "Stochastic model",
                    "white = independent point errors (the study's; too small a sigma for "
                    "real surveys); plane = plus one offset per plane; full = plus spatially "
                    "correlated offsets and a rigid error per acquisition unit (default).",
                ),
                (
                    "Colours",
                    "red = right-lateral (+), blue = left-lateral (-), white = 0 on Tiles, "
                    "Strips and Moving windows (right_lateral, band right_lateral_m); ramps "
                    "span plus and minus the largest value.",
                ),
            ],
            citation=job.SPEC.citation + "; point accuracy: section II.E, Glennie (2007), "
            "Schaer et al. (2007)",
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        add_parameters(self, job.SPEC, roles=("input",), skip=_OWN)
        fault = QgsProcessingParameterFeatureSource(
            "FAULT", job.SPEC["fault"].dialog_label, [QgsProcessing.TypeVectorLine]
        )
        fault.setHelp(job.SPEC["fault"].help)
        self.addParameter(fault)
        add_pa_parameters(
            self,
            {"PA_BEFORE": "Point accuracy, before", "PA_AFTER": "Point accuracy, after"},
        )
        add_parameters(self, job.SPEC, roles=("setting",), skip=_OWN)
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", "Summary", "JSON (*.json)")
        )
        self.addParameter(
            QgsProcessingParameterFeatureSink(
                "PLANES", "Matched planes", QgsProcessing.TypeVectorPoint
            )
        )
        for name, label, kind in (
            ("TILES", "Tiles", QgsProcessing.TypeVectorPolygon),
            ("STRIPS", "Strips", QgsProcessing.TypeVectorPoint),
        ):
            self.addParameter(
                QgsProcessingParameterFeatureSink(
                    name, label, kind, optional=True, createByDefault=False
                )
            )
        self.addParameter(
            QgsProcessingParameterRasterDestination(
                "WINDOWS", "Moving windows", optional=True, createByDefault=False
            )
        )
        self.addOutput(QgsProcessingOutputHtml("REPORT", "Report"))
        self.addOutput(QgsProcessingOutputNumber("RIGHT_LATERAL_SLIP", "Right-lateral slip (m)"))
        self.addOutput(
            QgsProcessingOutputNumber("SIGMA_RIGHT_LATERAL", "Sigma of the right-lateral slip (m)")
        )
        self.addOutput(
            QgsProcessingOutputNumber(
                "SIGMA_RIGHT_LATERAL_WHITE",
                "Sigma of the right-lateral slip under the white-noise model (m)",
            )
        )
        self.addOutput(QgsProcessingOutputString("STOCHASTIC_MODEL", "Stochastic model"))
        self.addOutput(QgsProcessingOutputNumber("N_EFF_LEFT", "Effective planes, left side"))
        self.addOutput(QgsProcessingOutputNumber("N_EFF_RIGHT", "Effective planes, right side"))
        self.addOutput(
            QgsProcessingOutputString("VARIANCE_COMPONENTS", "Variance components (JSON)")
        )

    # ------------------------------------------------------------------ parameters

    def _extra(self, parameters, context):
        """What the algorithm reads itself: resolved epoch paths, the point-accuracy widgets
        (one model per epoch), and the outputs asked for."""
        before = cloud_path(self, parameters, "BEFORE", context)
        extra = {
            "before": before,
            "after": cloud_path(self, parameters, "AFTER", context),
            "out": "-",
            **pa_values(self, parameters, context, "PA_BEFORE", _before_crs(before)),
        }
        extra["pa_model_after"] = MODELS[self.parameterAsEnum(parameters, "PA_AFTER", context)]
        return extra

    def _options(self, parameters, context):
        opts = options_from(
            self, parameters, context, job.SPEC, extra=self._extra(parameters, context)
        )
        wanted = [key for name, key in _SINKS.items() if is_set(parameters, name, context)]
        wanted += ["windows"] if is_set(parameters, "WINDOWS", context) else []
        with slipmap_errors(job.SPEC):
            job.check_outputs(opts, wanted)
        return opts

    def check_options(self, parameters, context):
        self._options(parameters, context)

    # ------------------------------------------------------------------ run

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        opts = self._options(parameters, context)
        source = self.parameterAsSource(parameters, "FAULT", context)
        label = f'"{job.SPEC["fault"].dialog_label}"'
        if source is None:
            raise QgsProcessingException(f"{label}: the layer cannot be read")

        def trace(crs):
            from ...core.fault import fault_trace

            return fault_trace(
                source_parts(source, qgs_crs(crs), context, parameter=label, polygons=False)
            )

        summary = self.parameterAsFileOutput(parameters, "SUMMARY", context)
        windows = None
        if is_set(parameters, "WINDOWS", context):
            windows = raster_output(self, parameters, "WINDOWS", context)
        wanted = [key for name, key in _SINKS.items() if is_set(parameters, name, context)]
        for note in job.unused_settings(opts, wanted + (["windows"] if windows else [])):
            _warn(feedback, job.SPEC.render_error(note, "qgis"))
        outputs = {
            "summary": summary,
            "report": summary.rsplit(".", 1)[0] + ".html",
            "windows": windows,
        }
        with slipmap_errors(job.SPEC):
            result = job.run(
                opts,
                outputs,
                trace=trace,
                trace_source=fault_source(self, parameters, context),
                progress=progress_callback(feedback),
            )
        for line in result.lines:
            feedback.pushInfo(line)
        return self._results(parameters, context, result, outputs)

    def _results(self, parameters, context, result, outputs):
        data, payload = result.data, result.summary
        crs = qgs_crs(data["crs"])
        res = data["run"].result
        results = {"SUMMARY": outputs["summary"], "REPORT": outputs["report"]}
        centroids, columns = [], None
        for side in (res.left, res.right):
            pb = side.planes_before
            centroids += [pb.centroids[i] for i in side.matches.before]
            cols = data["planes"][side.side]
            columns = cols if columns is None else _concat(columns, cols)
        results["PLANES"] = write_sink(
            self,
            parameters,
            "PLANES",
            context,
            crs,
            QgsWkbTypes.PointZ,
            [QgsGeometry(QgsPoint(*map(float, c[:3]))) for c in centroids],
            columns,
        )
        apply_style_on_load(context, results["PLANES"], "slip_planes", columns=columns, alg=self)
        if data["tiles"] is not None and is_set(parameters, "TILES", context):
            rings = [
                QgsGeometry.fromPolygonXY([[QgsPointXY(*map(float, p)) for p in r]])
                for r in data["tile_rings"]
            ]
            results["TILES"] = write_sink(
                self, parameters, "TILES", context, crs, QgsWkbTypes.Polygon, rings, data["tiles"]
            )
            apply_style_on_load(
                context, results["TILES"], "slip_tiles", columns=data["tiles"], alg=self
            )
        if data["strips"] is not None and is_set(parameters, "STRIPS", context):
            points = [QgsGeometry(QgsPoint(float(x), float(y))) for x, y in data["strip_points"]]
            results["STRIPS"] = write_sink(
                self, parameters, "STRIPS", context, crs, QgsWkbTypes.Point, points, data["strips"]
            )
            apply_style_on_load(
                context, results["STRIPS"], "slip_strips", columns=data["strips"], alg=self
            )
        if outputs["windows"] and "windows" in result.files:
            results["WINDOWS"] = outputs["windows"]
            apply_diverging_style_on_load(  # + = right-lateral (red), as tiles and strips
                context,
                results["WINDOWS"],
                "slip_windows",
                scale=1000.0,
                unit="mm",
                ends=("left-lateral", "right-lateral"),
            )
        rel = payload["relative"]
        stoch = stochastic_outputs(payload)
        results["RIGHT_LATERAL_SLIP"] = rel["right_lateral_slip"]
        results["SIGMA_RIGHT_LATERAL"] = rel["sigma_right_lateral"]
        white = rel.get("sigma_right_lateral_white")  # the white model's σ is its own σ
        results["SIGMA_RIGHT_LATERAL_WHITE"] = (
            rel["sigma_right_lateral"] if white is None else white
        )
        results["STOCHASTIC_MODEL"] = stoch["model"]
        for side in ("left", "right"):
            results[f"N_EFF_{side.upper()}"] = (stoch.get(side) or {}).get("n_eff")
        # compact (no blank): the dialog's log prints the results with pprint, which cuts a
        # text at its blanks into one line per word group (20 lines of JSON before)
        results["VARIANCE_COMPONENTS"] = json.dumps(stoch, separators=(",", ":"))
        return results


def _warn(feedback, text):
    push = getattr(feedback, "pushWarning", None) or feedback.pushInfo  # pushWarning: 3.20+
    push(text)


def fault_source(alg, parameters, context):
    """The fault layer's source for the record of the run (JSON, report): its file (with the
    GeoPackage layer, as QGIS writes it: ``f.gpkg|layername=trace``), or, for a layer held in
    memory, ``memory layer 'name' (not saved to a file)``; None when it cannot be told."""
    try:
        layer = alg.parameterAsVectorLayer(parameters, "FAULT", context)
    except Exception:  # noqa: BLE001 - the record is best effort; the run reads the source
        layer = None
    if layer is None:
        value = parameters.get("FAULT")
        return str(value) if isinstance(value, str) and value else None
    if layer.providerType() == "memory":
        return f"memory layer {layer.name()!r} (not saved to a file)"
    return layer.source() or layer.name()


def _concat(a, b):
    return {k: np.concatenate([np.asarray(a[k]), np.asarray(b[k])]) for k in a}
