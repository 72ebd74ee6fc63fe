"""``slipmap:planes``: planar segmentation of one LAS/LAZ point cloud."""

from __future__ import annotations

from qgis.core import (
    QgsProcessingOutputNumber,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterDefinition,
    QgsProcessingParameterEnum,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
)

from ._base import (
    LAS_FILTER,
    LAS_OUTPUT_FILTER,
    PLANES_CITATION,
    SlipMapAlgorithm,
    optional_number,
    progress_callback,
    read_cloud,
    select_points,
    slipmap_errors,
    write_json,
)

BACKENDS = ("numpy", "opencl", "auto")
# (parameter name, segment_planes keyword, label, integer?)
THRESHOLDS = (
    ("MIN_NODE_SIZE", "min_node_size_m", "Smallest octree node size (m)", False),
    ("PLANARITY_THRESHOLD", "planarity_threshold_m", "Planarity threshold (m)", False),
    ("PLANARITY_RATIO", "planarity_ratio", "Planarity ratio (0-1)", False),
    ("ANGLE_THRESHOLD", "angle_threshold_deg", "Angle threshold (degrees)", False),
    ("DISTANCE_THRESHOLD", "distance_threshold_m", "Distance threshold (m)", False),
    ("MIN_POINTS", "min_plane_points", "Smallest plane (points)", True),
    ("MIN_LEAF_POINTS", "min_leaf_points", "Smallest leaf for a plane fit (points)", True),
)

THRESHOLD_HELP = (
    "<b>Smallest octree node size</b> (m): nodes are not split below this size. "
    "<b>Planarity threshold</b> (m): largest point-to-plane distance of a planar leaf. "
    "<b>Planarity ratio</b> (0-1): share of a leaf's points within the threshold for it to be "
    "planar. <b>Angle threshold</b> (degrees): largest angle between normals of joined leaves. "
    "<b>Distance threshold</b> (m): largest centroid-to-plane distance of joined leaves. "
    "<b>Smallest plane</b> (points): planes with fewer points are dropped. "
    "<b>Smallest leaf</b> (points): leaves with fewer points are not fitted. "
    "Left empty, each takes the core's default (see docs/qgis.md)."
)


def add_plane_parameters(alg):
    """The optional segmentation thresholds (advanced) and the backend enum."""
    for name, _, label, integer in THRESHOLDS:
        p = QgsProcessingParameterNumber(
            name,
            label,
            QgsProcessingParameterNumber.Integer
            if integer
            else QgsProcessingParameterNumber.Double,
            optional=True,
            minValue=0,
        )
        p.setFlags(p.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
        alg.addParameter(p)
    p = QgsProcessingParameterEnum("BACKEND", "Backend", options=list(BACKENDS), defaultValue=0)
    p.setFlags(p.flags() | QgsProcessingParameterDefinition.FlagAdvanced)
    alg.addParameter(p)


def plane_options(alg, parameters, context):
    """``segment_planes`` keywords from the parameters (unset thresholds left out)."""
    opts = {}
    for name, key, _, integer in THRESHOLDS:
        value = optional_number(alg, parameters, name, context, integer=integer)
        if value is not None:
            opts[key] = value
    opts["backend"] = BACKENDS[alg.parameterAsEnum(parameters, "BACKEND", context)]
    return opts


class PlanesAlgorithm(SlipMapAlgorithm):
    _id = "planes"
    _name = "Planar segmentation"
    _group = "Segmentation"
    _group_id = "segmentation"

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "Finds the planar surfaces of a point cloud and labels every point with the id of "
            "its plane (PlaneId, -1 = no plane).<br><b>Input point cloud</b>: LAS/LAZ file in a "
            "projected CRS (metres). <b>Leave out ground</b>: skip class 2 points, as the "
            "SlipMap CLI does (default yes). "
            + THRESHOLD_HELP
            + " <b>Backend</b>: numpy (reference), opencl (PyOpenCL), auto.<br>"
            "<b>Outputs</b>: a LAS/LAZ copy with the PlaneId dimension, a JSON summary "
            "(one record per plane: centroid, normal, number of points, RMS in m) and the "
            "number of planes.<br>" + PLANES_CITATION
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFile("INPUT", "Input point cloud", fileFilter=LAS_FILTER)
        )
        self.addParameter(
            QgsProcessingParameterBoolean(
                "EXCLUDE_GROUND", "Leave out ground (class 2) points", defaultValue=True
            )
        )
        add_plane_parameters(self)
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "OUTPUT", "Labelled point cloud (PlaneId)", LAS_OUTPUT_FILTER
            )
        )
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", "Planes summary", "JSON (*.json)")
        )
        self.addOutput(QgsProcessingOutputNumber("N_PLANES", "Number of planes"))

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        path = self.parameterAsFile(parameters, "INPUT", context)
        out = self.parameterAsFileOutput(parameters, "OUTPUT", context)
        summary = self.parameterAsFileOutput(parameters, "SUMMARY", context)
        exclude = self.parameterAsBoolean(parameters, "EXCLUDE_GROUND", context)
        opts = plane_options(self, parameters, context)
        with slipmap_errors():
            import numpy as np

            from ...core.io.las import write_las
            from ...core.planes import segment_planes

            cloud = read_cloud(path)
            sel = select_points(cloud, exclude)
            planes = segment_planes(cloud.xyz[sel], progress=progress_callback(feedback), **opts)
            labels = np.full(len(cloud), -1, dtype=np.int32)
            labels[sel] = planes.labels
            write_las(out, cloud, extra_dims={"PlaneId": labels}, inputs=[path])
            write_json(
                summary,
                {
                    "planes": planes.to_records(),
                    "n_points": int(len(cloud)),
                    "n_selected": int(sel.size),
                    "n_labelled": int(np.count_nonzero(labels >= 0)),
                    "parameters": planes.parameters.to_dict(),
                    "input": path,
                    "crs": cloud.crs.to_wkt() if cloud.crs is not None else None,
                },
            )
        feedback.pushInfo(f"{len(planes)} planes; wrote {out} and {summary}")
        return {"OUTPUT": out, "SUMMARY": summary, "N_PLANES": len(planes)}
