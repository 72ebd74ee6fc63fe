"""``slipmap:displacement``: fault slip between two epochs by planar registration."""

from __future__ import annotations

from qgis.core import (
    QgsCoordinateReferenceSystem,
    QgsCoordinateTransform,
    QgsFeature,
    QgsFeatureSink,
    QgsField,
    QgsFields,
    QgsGeometry,
    QgsPoint,
    QgsProcessing,
    QgsProcessingException,
    QgsProcessingOutputHtml,
    QgsProcessingOutputNumber,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterFeatureSink,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsWkbTypes,
)
from qgis.PyQt.QtCore import QVariant

from ._base import (
    LAS_FILTER,
    PLANES_CITATION,
    SlipMapAlgorithm,
    progress_callback,
    read_cloud,
    select_points,
    slipmap_errors,
    write_json,
)
from .planes import THRESHOLD_HELP, add_plane_parameters, plane_options

SINK_FIELDS = (
    ("side", QVariant.String),
    ("plane_before", QVariant.Int),
    ("plane_after", QVariant.Int),
    ("n_points", QVariant.Int),
    ("normal_x", QVariant.Double),
    ("normal_y", QVariant.Double),
    ("normal_z", QVariant.Double),
)


def fault_parts(source, target_crs, context):
    """Vertices (x, y) of every line part of ``source``, transformed to ``target_crs``."""
    import numpy as np

    if QgsWkbTypes.geometryType(source.wkbType()) != QgsWkbTypes.LineGeometry:
        raise QgsProcessingException(
            "FAULT must be a line layer (the fault trace), got "
            f"{QgsWkbTypes.displayString(source.wkbType())}"
        )
    transform = None
    if target_crs.isValid() and source.sourceCrs().isValid():
        transform = QgsCoordinateTransform(
            source.sourceCrs(), target_crs, context.transformContext()
        )
    parts = []
    for feature in source.getFeatures():
        geom = QgsGeometry(feature.geometry())
        if geom.isEmpty():
            continue
        if transform is not None:
            geom.transform(transform)
        lines = geom.asMultiPolyline() if geom.isMultipart() else [geom.asPolyline()]
        parts += [np.array([[p.x(), p.y()] for p in line]) for line in lines if len(line) > 1]
    if not parts:
        raise QgsProcessingException("FAULT has no line with two or more vertices")
    return parts


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
            "right minus left.<br>"
            "<b>Before / After</b>: LAS/LAZ epochs in the same projected CRS (metres). "
            "<b>Fault trace</b>: a line layer in any CRS, reprojected to the point cloud's CRS. "
            "<b>Buffer</b> (m): points closer than this to the trace are left out (default 10). "
            "<b>Point accuracy sigma</b> (m): isotropic accuracy of every point (default 0.05). "
            "<b>Leave out ground</b>: skip class 2 points (default yes). "
            + THRESHOLD_HELP
            + "<br><b>Outputs</b>: JSON summary, HTML report, matched planes (points at the "
            "before-epoch plane centroids: side, plane ids, n_points, unit normal), "
            "right_lateral_slip and sigma_fault_parallel (m).<br>"
            "Method: Kusari, Glennie, Brooks and Ericksen (2019), IEEE TGRS 57(6). "
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
        self.addParameter(
            QgsProcessingParameterNumber(
                "SIGMA",
                "Point accuracy sigma (m)",
                QgsProcessingParameterNumber.Double,
                defaultValue=0.05,
                minValue=1e-6,
            )
        )
        self.addParameter(
            QgsProcessingParameterBoolean(
                "EXCLUDE_GROUND", "Leave out ground (class 2) points", defaultValue=True
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
        self.addOutput(QgsProcessingOutputHtml("REPORT", "Report"))
        self.addOutput(QgsProcessingOutputNumber("RIGHT_LATERAL_SLIP", "Right-lateral slip (m)"))
        self.addOutput(
            QgsProcessingOutputNumber("SIGMA_FAULT_PARALLEL", "Sigma of fault-parallel slip (m)")
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        before_path = self.parameterAsFile(parameters, "BEFORE", context)
        after_path = self.parameterAsFile(parameters, "AFTER", context)
        source = self.parameterAsSource(parameters, "FAULT", context)
        if source is None:
            raise QgsProcessingException("FAULT: the layer cannot be read")
        buffer_m = self.parameterAsDouble(parameters, "BUFFER", context)
        sigma = self.parameterAsDouble(parameters, "SIGMA", context)
        exclude = self.parameterAsBoolean(parameters, "EXCLUDE_GROUND", context)
        opts = plane_options(self, parameters, context)
        summary_path = self.parameterAsFileOutput(parameters, "SUMMARY", context)
        with slipmap_errors():
            from ...core.displacement import estimate_slip
            from ...core.fault import fault_trace
            from ...core.io.crs import reproject_points, same_crs

            first, second = read_cloud(before_path), read_cloud(after_path)
            crs = QgsCoordinateReferenceSystem()
            if first.crs is not None:
                crs = QgsCoordinateReferenceSystem.fromWkt(first.crs.to_wkt())
            trace = fault_trace(fault_parts(source, crs, context))
            xyz2 = second.xyz
            if (
                first.crs is not None
                and second.crs is not None
                and not same_crs(first.crs, second.crs)
            ):
                xyz2 = reproject_points(second.xyz, second.crs, first.crs)
            sel1, sel2 = select_points(first, exclude), select_points(second, exclude)
            result = estimate_slip(
                first.xyz[sel1],
                xyz2[sel2],
                trace,
                buffer_m=buffer_m,
                sigma_before=sigma,
                sigma_after=sigma,
                plane_options=opts,
                progress=progress_callback(feedback),
            )
            payload = result.to_dict()
            payload["parameters"].update(
                {"before": before_path, "after": after_path, "sigma": sigma}
            )
            write_json(summary_path, payload)
            report_path = summary_path.rsplit(".", 1)[0] + ".html"
            from ...core.report import write_html_report

            tables = {"relative (right - left), m": payload["relative"]}
            for side in ("left", "right"):
                tables[f"{side} side"] = {
                    k: v for k, v in payload[side].items() if not isinstance(v, (list, dict))
                }
            write_html_report(report_path, "SlipMap displacement", tables, [])
        sink_id = self._write_planes(parameters, context, result, crs)
        rel = payload["relative"]
        feedback.pushInfo(
            f"right-lateral slip {rel['right_lateral_slip']:.4f} ± "
            f"{rel['sigma_fault_parallel']:.4f} m"
        )
        return {
            "SUMMARY": summary_path,
            "REPORT": report_path,
            "PLANES": sink_id,
            "RIGHT_LATERAL_SLIP": rel["right_lateral_slip"],
            "SIGMA_FAULT_PARALLEL": rel["sigma_fault_parallel"],
        }

    def _write_planes(self, parameters, context, result, crs):
        fields = QgsFields()
        for name, kind in SINK_FIELDS:
            fields.append(QgsField(name, kind))
        sink, sink_id = self.parameterAsSink(
            parameters, "PLANES", context, fields, QgsWkbTypes.PointZ, crs
        )
        if sink is None:
            return None
        for side in (result.left, result.right):
            pb, m = side.planes_before, side.matches
            for i, j in zip(m.before, m.after):
                f = QgsFeature(fields)
                c = pb.centroids[i]
                f.setGeometry(QgsGeometry(QgsPoint(float(c[0]), float(c[1]), float(c[2]))))
                n = pb.normals[i]
                f.setAttributes(
                    [
                        side.side,
                        int(i),
                        int(j),
                        int(pb.n_points[i]),
                        float(n[0]),
                        float(n[1]),
                        float(n[2]),
                    ]
                )
                sink.addFeature(f, QgsFeatureSink.FastInsert)
        return sink_id
