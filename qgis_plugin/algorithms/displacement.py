"""``slipmap:displacement``: fault slip between two epochs by planar registration."""

from __future__ import annotations

import json
import math

from qgis.core import (
    QgsFeature,
    QgsFeatureSink,
    QgsFields,
    QgsGeometry,
    QgsMapLayerType,
    QgsPoint,
    QgsProcessing,
    QgsProcessingException,
    QgsProcessingOutputHtml,
    QgsProcessingOutputNumber,
    QgsProcessingOutputString,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFeatureSink,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
    QgsProcessingParameterString,
    QgsProcessingUtils,
    QgsRectangle,
    QgsWkbTypes,
)
from qgis.PyQt.QtCore import QVariant

from ...app.stochasticmodel import (
    DEFAULT_GPS_GAP_S,
    DEFAULT_MODEL,
    MODEL_HELP,
    MODELS,
    UNIT_SOURCES,
    UNITS_HELP,
    parse_fixed_components,
)
from ...app.summaries import finite as _finite
from ...app.summaries import (
    json_safe,
    plane_fields,
    slip_summary_lines,
    stochastic_outputs,
    stochastic_tables,
    strip_rows,
)
from ...core.errors import InvalidParameterError
from ..compat import make_field
from ._base import (
    LAS_FILTER,
    PLANES_CITATION,
    SlipMapAlgorithm,
    advanced,
    apply_diverging_style_on_load,
    apply_style_on_load,
    is_set,
    optional_number,
    progress_callback,
    read_cloud,
    select_points,
    slipmap_errors,
    source_parts,
    write_json,
)
from .accuracy import (
    PA_HELP,
    add_pa_parameters,
    cloud_crs,
    pa_config,
    pa_errors,
    pa_settings,
)
from .planes import THRESHOLD_HELP, add_plane_parameters, plane_options

COMBINE = ("joint", "tiles")
TILE_FIELDS = (
    ("side", QVariant.String),
    ("ix", QVariant.Int),
    ("iy", QVariant.Int),
    ("n_planes", QVariant.Int),
    ("dx", QVariant.Double),
    ("dy", QVariant.Double),
    ("dz", QVariant.Double),
    ("sigma_dx", QVariant.Double),
    ("sigma_dy", QVariant.Double),
    ("sigma_dz", QVariant.Double),
    ("fault_parallel", QVariant.Double),
    ("sigma_fp", QVariant.Double),
    ("status", QVariant.String),
)
STRIP_FIELDS = (
    ("side", QVariant.String),
    ("along_start_m", QVariant.Double),
    ("along_end_m", QVariant.Double),
    ("along_centre_m", QVariant.Double),
    ("n_planes", QVariant.Int),
    ("fault_parallel", QVariant.Double),
    ("sigma_fp", QVariant.Double),
    ("fault_normal", QVariant.Double),
    ("sigma_fn", QVariant.Double),
    ("dz", QVariant.Double),
    ("sigma_dz", QVariant.Double),
    ("status", QVariant.String),
)
#: bands of the WINDOWS GeoTIFF; fault_parallel_m = (dx, dy) along the mean strike (band 1, the
#: one the bundled style shows)
WINDOW_BANDS = (
    "fault_parallel_m",
    "dx_m",
    "dy_m",
    "dz_m",
    "sigma_dx_m",
    "sigma_dy_m",
    "n_planes",
)

SINK_FIELDS = (
    ("side", QVariant.String),
    ("plane_before", QVariant.Int),
    ("plane_after", QVariant.Int),
    ("n_points", QVariant.Int),
    ("normal_x", QVariant.Double),
    ("normal_y", QVariant.Double),
    ("normal_z", QVariant.Double),
    ("weight", QVariant.Double),
    ("w_test", QVariant.Double),
    ("offset_mm", QVariant.Double),
    ("misclosure_mm", QVariant.Double),
)
STOCHASTIC_HELP = (
    "<b>Stochastic model</b> of the slip's σ: "
    + "; ".join(f"<i>{m}</i>: {MODEL_HELP[m]}" for m in MODELS)
    + ". <b>Acquisition units</b>: "
    + UNITS_HELP
    + " (<b>GPS gap</b>, s, advanced, default 1). <b>Fixed components</b> (advanced): "
    "plane-level components held fixed instead of estimated, as name=value pairs separated by "
    "commas: plane, spatial, unit_before, unit_after (σ in metres), spatial_range_m (metres), "
    "e.g. <tt>plane=0.002,unit_after=0.003</tt>."
)


def fault_parts(source, target_crs, context):
    """Vertices (x, y) of every line part of ``source``, transformed to ``target_crs``."""
    return source_parts(source, target_crs, context, parameter="FAULT", polygons=False)


def cloud_path(alg, parameters, name, context):
    """A LAS/LAZ path from a file parameter. A value that is not a file but the id or name of
    a point-cloud layer of the project (QGIS >= 3.18) resolves to that layer's source file."""
    import os

    path = alg.parameterAsFile(parameters, name, context)
    if path and not os.path.isfile(path):
        layer = QgsProcessingUtils.mapLayerFromString(path, context)
        kind = getattr(QgsMapLayerType, "PointCloudLayer", None)
        if layer is not None and kind is not None and layer.type() == kind:
            return layer.source().split("|")[0]
    return path


def _length(name, label, default=None, optional=True, is_advanced=False):
    p = QgsProcessingParameterNumber(
        name,
        label,
        QgsProcessingParameterNumber.Double,
        defaultValue=default,
        optional=optional,
        minValue=1e-6,
    )
    return advanced(p) if is_advanced else p


def _sigma_of(cov, j):
    """1σ of ``j @ d`` for a (3, 3) covariance ``cov`` of ``d`` (None when not finite)."""
    v = float(j @ cov @ j)
    return math.sqrt(max(v, 0.0)) if math.isfinite(v) else None


def _with_help(param, text):
    """``param`` with a tooltip help text (QGIS >= 3.16)."""
    if hasattr(param, "setHelp"):
        param.setHelp(text)
    return param


def _fields(spec):
    fields = QgsFields()
    for name, kind in spec:
        fields.append(make_field(name, kind))
    return fields


class DisplacementAlgorithm(SlipMapAlgorithm):
    _id = "displacement"
    _name = "Fault slip (displacement)"
    _group = "Slip"
    _group_id = "slip"

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "Relative displacement across a fault between two LiDAR epochs: planes are "
            "extracted on each side of the trace, matched between epochs and a rigid "
            "least-squares adjustment (point-to-plane, Gauss-Helmert) gives each side's "
            "displacement; the right-lateral slip is minus the fault-parallel component of "
            "right minus left (as the CLI's <tt>slipmap displacement</tt>).<br>"
            "<b>Before / After</b>: LAS/LAZ epochs in a projected CRS (metres; the second is "
            "reprojected to the first's CRS when they differ). The id or name of a point-cloud "
            "layer of the project is accepted too (its source file is read). "
            "<b>Fault trace</b>: a line layer in any CRS, reprojected to the point cloud's CRS. "
            "<b>Buffer</b> (m): points closer than this to the trace are left out (default 10, "
            "as the study). <b>Leave out ground</b>: skip class 2 points (default yes).<br>"
            "<b>Point accuracy, before / after</b>: the model of each epoch. "
            + PA_HELP
            + "<br><b>Tile size</b> (m, optional): extract planes in square tiles of this size "
            "(the study used 20-100 m); <b>Combine</b>: joint = one adjustment per side on all "
            "matched planes (default, the study's approach), tiles = information-weighted mean "
            "of the per-tile adjustments. <b>Strip width</b> (m, optional): profile of the "
            "fault-parallel displacement in strips along the trace (study: 50-100 m). "
            "<b>Window size / step</b> (m, optional; step defaults to a quarter of the size): "
            "moving-window displacement maps (study: 400 m stepped by 20 m). "
            "<b>Match angle</b> (degrees, default 3) and <b>match distance</b> (m, default 0.5, "
            "above the largest expected displacement): plane matching between epochs. "
            "<b>Reference slip</b> (m, optional, positive dextral): an independent measurement "
            "(e.g. an alinement array); adds the study's Table X figures to the summary.<br>"
            + STOCHASTIC_HELP
            + "<br>"
            + THRESHOLD_HELP
            + "<br><b>Outputs</b>: JSON summary; HTML report (tables and plots, beside the "
            "JSON; with the stochastic model's components per side, n_eff, the white-noise σ "
            "beside the model's, rejected and down-weighted planes); matched planes (points at "
            "the before-epoch plane centroids: side, plane ids, n_points, unit normal, weight "
            "= 1 full / below 1 down-weighted / 0 rejected, w_test, offset_mm = predicted "
            "plane offset, misclosure_mm); tiles (polygons: side, ix, iy, n_planes, dx, dy, dz "
            "= the tile's own motion and sigma_dx/dy/dz in m, fault_parallel and sigma_fp = its "
            "component along the mean strike, status); strips (points on the trace at the "
            "strip's centre chainage: side, along_start_m/along_end_m/along_centre_m, "
            "n_planes, fault_parallel, fault_normal, dz and their sigmas in m, all relative to "
            "the left side's global displacement, status); windows (GeoTIFF, one pixel per "
            "window centre, bands fault_parallel_m, dx_m, dy_m, dz_m, sigma_dx_m, sigma_dy_m "
            "relative to the left side, and n_planes; styled on fault_parallel_m); "
            "right_lateral_slip, sigma_fault_parallel and sigma_fault_parallel_white (m), "
            "n_eff of each side, the model and the variance components (JSON text).<br>"
            "Method: Kusari, Glennie, Brooks and Ericksen (2019), Precise registration of "
            "laser mapping data by planar feature extraction for deformation monitoring, "
            "IEEE TGRS 57(6): sections II-III (tiles, strips: Fig. 5; windows: Fig. 11). "
            + PLANES_CITATION
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFile("BEFORE", "Before epoch", fileFilter=LAS_FILTER)
        )
        self.addParameter(QgsProcessingParameterFile("AFTER", "After epoch", fileFilter=LAS_FILTER))
        self.addParameter(
            QgsProcessingParameterFeatureSource(
                "FAULT", "Fault trace", [QgsProcessing.TypeVectorLine]
            )
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                "BUFFER",
                "Buffer around the trace (m)",
                QgsProcessingParameterNumber.Double,
                defaultValue=10.0,
                minValue=0.0,
            )
        )
        add_pa_parameters(
            self, {"PA_BEFORE": "Point accuracy, before", "PA_AFTER": "Point accuracy, after"}
        )
        self.addParameter(
            QgsProcessingParameterBoolean(
                "EXCLUDE_GROUND", "Leave out ground (class 2) points", defaultValue=True
            )
        )
        self.addParameter(_length("TILE_SIZE", "Tile size (m)"))
        self.addParameter(
            advanced(
                QgsProcessingParameterEnum(
                    "COMBINE", "Combine tiles", options=list(COMBINE), defaultValue=0
                )
            )
        )
        self.addParameter(_length("STRIP_WIDTH", "Strip width (m)"))
        self.addParameter(_length("WINDOW_SIZE", "Moving-window size (m)"))
        self.addParameter(
            _length("WINDOW_STEP", "Moving-window step (m; default size / 4)", is_advanced=True)
        )
        self.addParameter(
            _length("MATCH_ANGLE", "Match angle (degrees)", 3.0, optional=False, is_advanced=True)
        )
        self.addParameter(
            _length("MATCH_DISTANCE", "Match distance (m)", 0.5, optional=False, is_advanced=True)
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterNumber(
                    "REFERENCE_SLIP",
                    "Reference right-lateral slip (m)",
                    QgsProcessingParameterNumber.Double,
                    optional=True,
                )
            )
        )
        self.addParameter(
            _with_help(
                QgsProcessingParameterEnum(
                    "STOCHASTIC_MODEL",
                    "Stochastic model",
                    options=list(MODELS),
                    defaultValue=MODELS.index(DEFAULT_MODEL),
                ),
                "; ".join(f"{m}: {MODEL_HELP[m]}" for m in MODELS),
            )
        )
        self.addParameter(
            _with_help(
                QgsProcessingParameterEnum(
                    "UNITS", "Acquisition units", options=list(UNIT_SOURCES), defaultValue=0
                ),
                UNITS_HELP,
            )
        )
        self.addParameter(
            advanced(
                _with_help(
                    QgsProcessingParameterNumber(
                        "GPS_GAP",
                        "GPS gap between acquisition units (s)",
                        QgsProcessingParameterNumber.Double,
                        defaultValue=DEFAULT_GPS_GAP_S,
                        minValue=1e-6,
                    ),
                    "With Acquisition units = GpsTime: a new unit starts where consecutive GPS "
                    "times jump by more than this (seconds)",
                )
            )
        )
        self.addParameter(
            advanced(
                _with_help(
                    QgsProcessingParameterString(
                        "FIXED_COMPONENTS",
                        "Fixed components (name=sigma_m, …)",
                        optional=True,
                    ),
                    "Plane-level components held fixed instead of estimated: plane, spatial, "
                    "unit_before, unit_after (σ, m) and spatial_range_m (m), e.g. "
                    "plane=0.002,unit_after=0.003",
                )
            )
        )
        add_plane_parameters(self)
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
            QgsProcessingOutputNumber("SIGMA_FAULT_PARALLEL", "Sigma of fault-parallel slip (m)")
        )
        self.addOutput(
            QgsProcessingOutputNumber(
                "SIGMA_FAULT_PARALLEL_WHITE",
                "Sigma of fault-parallel slip under the white-noise model (m)",
            )
        )
        self.addOutput(QgsProcessingOutputString("STOCHASTIC_MODEL", "Stochastic model"))
        self.addOutput(QgsProcessingOutputNumber("N_EFF_LEFT", "Effective planes, left side"))
        self.addOutput(QgsProcessingOutputNumber("N_EFF_RIGHT", "Effective planes, right side"))
        self.addOutput(
            QgsProcessingOutputString("VARIANCE_COMPONENTS", "Variance components (JSON)")
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        opts = self._options(parameters, context)
        if opts["window_size_m"] is not None and not opts["windows_path"]:
            feedback.pushInfo("WINDOW_SIZE is set but no WINDOWS output is asked for: no windows")
        source = self.parameterAsSource(parameters, "FAULT", context)
        if source is None:
            raise QgsProcessingException("FAULT: the layer cannot be read")
        with slipmap_errors():
            run = self._run(parameters, context, feedback, source, opts)
            summary, report = self._write_summary(run, opts)
        results = {"SUMMARY": summary, "REPORT": report}
        results["PLANES"] = self._write_planes(parameters, context, run["result"], run["crs"])
        if run["result"].tiles and is_set(parameters, "TILES"):
            results["TILES"] = self._write_tiles(parameters, context, run)
            apply_style_on_load(context, results["TILES"], "slip_tiles")
        if run["strips"] is not None and is_set(parameters, "STRIPS"):
            results["STRIPS"] = self._write_strips(parameters, context, run)
            apply_style_on_load(context, results["STRIPS"], "slip_strips")
        if run["windows"] is not None:
            with slipmap_errors():
                results["WINDOWS"] = self._write_windows(run, opts["windows_path"])
            apply_diverging_style_on_load(context, results["WINDOWS"])
        payload = run["payload"]
        rel = payload["relative"]
        for line in slip_summary_lines(payload):
            feedback.pushInfo(line)
        stoch = stochastic_outputs(payload)
        results["RIGHT_LATERAL_SLIP"] = rel["right_lateral_slip"]
        results["SIGMA_FAULT_PARALLEL"] = rel["sigma_fault_parallel"]
        # the white model's σ is its own σ
        white = rel.get("sigma_fault_parallel_white")
        results["SIGMA_FAULT_PARALLEL_WHITE"] = (
            rel["sigma_fault_parallel"] if white is None else white
        )
        results["STOCHASTIC_MODEL"] = stoch["model"]
        for side in ("left", "right"):
            results[f"N_EFF_{side.upper()}"] = (stoch.get(side) or {}).get("n_eff")
        results["VARIANCE_COMPONENTS"] = json.dumps(json_safe(stoch))
        return results

    # ------------------------------------------------------------------ parameters

    def _options(self, parameters, context):
        """Plain values of the parameters, checked; nothing is kept on ``self``."""
        number = lambda name: optional_number(self, parameters, name, context)  # noqa: E731
        opts = {
            "before": cloud_path(self, parameters, "BEFORE", context),
            "after": cloud_path(self, parameters, "AFTER", context),
            "buffer_m": self.parameterAsDouble(parameters, "BUFFER", context),
            "exclude": self.parameterAsBoolean(parameters, "EXCLUDE_GROUND", context),
            "plane": plane_options(self, parameters, context),
            "match": {
                "angle_threshold_deg": self.parameterAsDouble(parameters, "MATCH_ANGLE", context),
                "distance_threshold_m": self.parameterAsDouble(
                    parameters, "MATCH_DISTANCE", context
                ),
            },
            "tile_size_m": number("TILE_SIZE"),
            "combine": COMBINE[self.parameterAsEnum(parameters, "COMBINE", context)],
            "strip_width_m": number("STRIP_WIDTH"),
            "window_size_m": number("WINDOW_SIZE"),
            "window_step_m": number("WINDOW_STEP"),
            "reference_slip": number("REFERENCE_SLIP"),
            "summary": self.parameterAsFileOutput(parameters, "SUMMARY", context),
            "pa_config": pa_config(self, parameters, context),
            "windows_path": None,
            "stochastic_model": MODELS[
                self.parameterAsEnum(parameters, "STOCHASTIC_MODEL", context)
            ],
            "units": UNIT_SOURCES[self.parameterAsEnum(parameters, "UNITS", context)],
            "gps_gap_s": self.parameterAsDouble(parameters, "GPS_GAP", context),
            "components": None,
        }
        try:
            fixed = parse_fixed_components(
                self.parameterAsString(parameters, "FIXED_COMPONENTS", context),
                option="FIXED_COMPONENTS",
            )
        except InvalidParameterError as exc:
            raise QgsProcessingException(str(exc)) from None
        if fixed and opts["stochastic_model"] == "white":
            raise QgsProcessingException(
                "FIXED_COMPONENTS: the white model has no plane-level components; set "
                "STOCHASTIC_MODEL to plane or full"
            )
        opts["components"] = fixed or None
        if not opts["gps_gap_s"] > 0:
            raise QgsProcessingException(f"GPS_GAP must be > 0 s, got {opts['gps_gap_s']}")
        for name, key in (
            ("TILE_SIZE", "tile_size_m"),
            ("STRIP_WIDTH", "strip_width_m"),
            ("WINDOW_SIZE", "window_size_m"),
            ("WINDOW_STEP", "window_step_m"),
        ):
            if opts[key] is not None and not opts[key] > 0:
                raise QgsProcessingException(f"{name} must be > 0 m, got {opts[key]}")
        for sink, key, name in (
            ("TILES", "tile_size_m", "TILE_SIZE"),
            ("STRIPS", "strip_width_m", "STRIP_WIDTH"),
            ("WINDOWS", "window_size_m", "WINDOW_SIZE"),
        ):
            if is_set(parameters, sink) and opts[key] is None:
                raise QgsProcessingException(
                    f"{sink} is requested but {name} is not set: give {name} (m) or leave "
                    f"{sink} out"
                )
        if opts["window_size_m"] is not None:
            if opts["window_step_m"] is None:
                opts["window_step_m"] = opts["window_size_m"] / 4
            if is_set(parameters, "WINDOWS"):
                opts["windows_path"] = self.parameterAsOutputLayer(parameters, "WINDOWS", context)
        return opts

    # ------------------------------------------------------------------ core

    def _run(self, parameters, context, feedback, source, opts):
        from ...app.pointaccuracy import covariances
        from ...core.displacement import estimate_slip, strip_profile, window_field
        from ...core.fault import fault_trace
        from ...core.io.crs import reproject_points, same_crs
        from ...core.progress import scaled

        progress = progress_callback(feedback)
        first, second = read_cloud(opts["before"]), read_cloud(opts["after"])
        crs = cloud_crs(first)
        pa = opts["pa_config"] or {
            "before": pa_settings(self, parameters, context, "PA_BEFORE", crs),
            "after": pa_settings(
                self,
                parameters,
                context,
                "PA_AFTER",
                cloud_crs(second) if second.crs is not None else crs,
            ),
        }
        trace = fault_trace(fault_parts(source, crs, context))
        xyz2 = second.xyz
        if first.crs is not None and second.crs is not None and not same_crs(first.crs, second.crs):
            xyz2 = reproject_points(second.xyz, second.crs, first.crs)
        sel1, sel2 = select_points(first, opts["exclude"]), select_points(second, opts["exclude"])
        before, after = first.xyz[sel1], xyz2[sel2]
        units, unit_record = self._units(opts, first, second, sel1, sel2, feedback)
        with pa_errors():
            sigma_before = covariances(first, sel1, pa["before"])
            sigma_after = covariances(second, sel2, pa["after"])
        common = dict(
            buffer_m=opts["buffer_m"],
            sigma_before=sigma_before,
            sigma_after=sigma_after,
            plane_options=opts["plane"],
            match_options=opts["match"],
            stochastic_model=opts["stochastic_model"],
            unit_before=units["before"],
            unit_after=units["after"],
        )
        # the windows are only computed for their GeoTIFF (the summary does not hold them)
        n_steps = 1 + (opts["strip_width_m"] is not None) + bool(opts["windows_path"])
        step = iter(range(n_steps))

        def part():
            k = next(step)
            return scaled(progress, k / n_steps, (k + 1) / n_steps)

        result = estimate_slip(
            before,
            after,
            trace,
            tile_size_m=opts["tile_size_m"],
            combine=opts["combine"],
            progress=part(),
            components=opts["components"],
            **common,
        )
        strips = windows = None
        if opts["strip_width_m"] is not None:
            strips = strip_profile(
                before,
                after,
                trace,
                result,
                strip_width_m=opts["strip_width_m"],
                progress=part(),
                **common,
            )
        if opts["windows_path"]:
            windows = window_field(
                before,
                after,
                trace,
                result,
                window_size_m=opts["window_size_m"],
                window_step_m=opts["window_step_m"],
                progress=part(),
                **common,
            )
        payload = result.to_dict()
        payload["parameters"].update(
            {
                "point_accuracy": pa,
                "before": opts["before"],
                "after": opts["after"],
                "acquisition_unit_sources": unit_record,
            }
        )
        if opts["reference_slip"] is not None:
            payload["reference"] = result.reference_comparison(opts["reference_slip"])
        if strips is not None:
            payload["strips"] = strip_rows(strips)
        return {
            "result": result,
            "strips": strips,
            "windows": windows,
            "trace": trace,
            "crs": crs,
            "crs_wkt": first.crs.to_wkt() if first.crs is not None else None,
            "payload": json_safe(payload),
        }

    @staticmethod
    def _units(opts, first, second, sel1, sel2, feedback):
        """Acquisition units of each epoch's selected points (full model only) and what was
        used, for the summary."""
        from ...app.stochasticmodel import cloud_units

        units = {"before": None, "after": None}
        record = {"units_option": opts["units"]}
        if opts["stochastic_model"] != "full":
            if opts["units"] not in ("auto", "none"):
                feedback.pushInfo(
                    f"UNITS {opts['units']} is not used by the {opts['stochastic_model']} model"
                )
            return units, record
        if opts["units"] == "GpsTime":
            record["gps_gap_s"] = opts["gps_gap_s"]
        for epoch, cloud, sel in (("before", first, sel1), ("after", second, sel2)):
            u = cloud_units(
                cloud,
                sel,
                opts["units"],
                gap_s=opts["gps_gap_s"],
                epoch=f"{epoch} epoch ({opts[epoch]})",
                option="UNITS",
            )
            units[epoch] = u.units
            record[epoch] = u.to_dict()
            feedback.pushInfo(
                f"{epoch} epoch: {u.n_units} acquisition unit(s) from {u.source}"
                if u.units is not None
                else f"{epoch} epoch: no acquisition units ({u.note})"
            )
        return units, record

    # ------------------------------------------------------------------ outputs

    def _write_summary(self, run, opts):
        """The JSON summary and the HTML report (with PNG plots beside it when matplotlib is
        there); returns both paths."""
        from ...core.errors import DependencyError
        from ...app.report import write_html_report

        summary, payload, result = opts["summary"], run["payload"], run["result"]
        write_json(summary, payload)  # json_safe: NaN written as null
        stem = summary.rsplit(".", 1)[0]
        tables = {"relative (right - left), m": payload["relative"]}
        for side in ("left", "right"):
            tables[f"{side} side"] = {
                k: v for k, v in payload[side].items() if not isinstance(v, (list, dict))
            }
        tables.update(stochastic_tables(payload))
        if "reference" in payload:
            tables["against the reference slip"] = payload["reference"]
        images = []
        try:
            images = _plots(stem, result, run["strips"])
        except DependencyError:
            pass  # no matplotlib in QGIS's Python: tables only
        report = stem + ".html"
        write_html_report(report, "SlipMap displacement", tables, images)
        return summary, report

    def _write_planes(self, parameters, context, result, crs):
        fields = _fields(SINK_FIELDS)
        sink, sink_id = self.parameterAsSink(
            parameters, "PLANES", context, fields, QgsWkbTypes.PointZ, crs
        )
        if sink is None:
            return None
        for side in (result.left, result.right):
            pb, m = side.planes_before, side.matches
            diag = plane_fields(side)
            keys = ("weight", "w_test", "offset_mm", "misclosure_mm")
            for k, (i, j) in enumerate(zip(m.before, m.after)):
                f = QgsFeature(fields)
                c = pb.centroids[i]
                f.setGeometry(QgsGeometry(QgsPoint(float(c[0]), float(c[1]), float(c[2]))))
                n = pb.normals[i]
                f.setAttributes(
                    [side.side, int(i), int(j), int(pb.n_points[i])]
                    + [float(v) for v in n]
                    + [_finite(diag[key][k]) for key in keys]
                )
                sink.addFeature(f, QgsFeatureSink.FastInsert)
        return sink_id

    def _write_tiles(self, parameters, context, run):
        import numpy as np

        result = run["result"]
        fields = _fields(TILE_FIELDS)
        sink, sink_id = self.parameterAsSink(
            parameters, "TILES", context, fields, QgsWkbTypes.Polygon, run["crs"]
        )
        if sink is None:
            return None
        j = np.array([math.sin(result.strike_rad), math.cos(result.strike_rad), 0.0])
        for t in result.tiles:
            x0, y0, x1, y1 = (float(v) for v in t.bounds)
            f = QgsFeature(fields)
            f.setGeometry(QgsGeometry.fromRect(QgsRectangle(x0, y0, x1, y1)))
            ok = t.status == "ok"
            d = [_finite(v) if ok else None for v in t.displacement]
            s = [_finite(math.sqrt(max(t.covariance[k, k], 0.0))) if ok else None for k in range(3)]
            fp = _finite(j @ t.displacement) if ok else None
            sfp = _sigma_of(t.covariance, j) if ok else None
            f.setAttributes(
                [t.side, int(t.ix), int(t.iy), int(t.n_planes), *d, *s, fp, sfp, t.status]
            )
            sink.addFeature(f, QgsFeatureSink.FastInsert)
        return sink_id

    def _write_strips(self, parameters, context, run):
        import numpy as np

        from ...core.fault import point_at_chainage

        result = run["result"]
        fields = _fields(STRIP_FIELDS)
        sink, sink_id = self.parameterAsSink(
            parameters, "STRIPS", context, fields, QgsWkbTypes.Point, run["crs"]
        )
        if sink is None:
            return None
        s, c = math.sin(result.strike_rad), math.cos(result.strike_rad)
        jn, jz = np.array([c, -s, 0.0]), np.array([0.0, 0.0, 1.0])
        ref_d = result.left.displacement
        for st in run["strips"]:
            ok = st.status == "ok"
            rel = st.displacement - ref_d
            xy = point_at_chainage(run["trace"], st.along_centre_m)
            f = QgsFeature(fields)
            f.setGeometry(QgsGeometry(QgsPoint(float(xy[0]), float(xy[1]))))
            f.setAttributes(
                [
                    st.side,
                    float(st.along_start_m),
                    float(st.along_end_m),
                    float(st.along_centre_m),
                    int(st.n_planes),
                    _finite(st.fault_parallel),
                    _finite(st.sigma_fault_parallel),
                    _finite(jn @ rel) if ok else None,
                    _sigma_of(st.relative_covariance, jn) if ok else None,
                    _finite(jz @ rel) if ok else None,
                    _sigma_of(st.relative_covariance, jz) if ok else None,
                    st.status,
                ]
            )
            sink.addFeature(f, QgsFeatureSink.FastInsert)
        return sink_id

    def _write_windows(self, run, path):
        """One multi-band GeoTIFF: bands :data:`WINDOW_BANDS`, pixels on the window centres."""
        import numpy as np

        from ...core.io.raster import write_geotiff

        w = run["windows"]
        half = 0.5 * w.step_m
        strike = run["result"].strike_rad
        fp = math.sin(strike) * w.dx + math.cos(strike) * w.dy
        bands = [fp, w.dx, w.dy, w.dz, w.sigma_dx, w.sigma_dy, w.n_planes]
        write_geotiff(
            path,
            np.stack([np.asarray(b, dtype=np.float64) for b in bands]),
            origin_xy=(w.x0 - half, w.y0 + half),
            pixel_size_m=w.step_m,
            crs_wkt=run["crs_wkt"],
            band_names=list(WINDOW_BANDS),
            metadata={"SLIPMAP_WINDOW_SIZE_M": f"{w.window_size_m:g}"},
        )
        return path


def _plots(stem, result, strips):
    """Residual, normal and strip-profile PNGs beside the report; their relative names."""
    import os

    from ...app.report import (
        plot_normals_polar,
        plot_plane_residual_polar,
        plot_residual_histograms,
        plot_strip_profile,
    )

    sides = (result.left, result.right)
    res = {f"{s.side} before": s.rigid.residuals_before for s in sides}
    res.update({f"{s.side} after": s.rigid.residuals_after for s in sides})
    names = []
    plot_residual_histograms(stem + "_residuals.png", res, title="Point-to-plane residuals")
    names.append("_residuals.png")
    normals = {s.side: s.planes_before.normals[s.matches.before] for s in sides}
    plot_normals_polar(stem + "_normals.png", normals, title="Matched plane normals")
    names.append("_normals.png")
    if all(s.plane_mean_residual_m is not None for s in sides):
        plot_plane_residual_polar(
            stem + "_plane_residuals.png",
            {s.side: (normals[s.side], s.plane_mean_residual_m) for s in sides},
        )
        names.append("_plane_residuals.png")
    if strips:
        plot_strip_profile(
            stem + "_strips.png",
            [st.along_centre_m for st in strips],
            [st.fault_parallel for st in strips],
            [st.sigma_fault_parallel for st in strips],
            [st.side for st in strips],
        )
        names.append("_strips.png")
    base = os.path.basename(stem)
    return [base + n for n in names]
