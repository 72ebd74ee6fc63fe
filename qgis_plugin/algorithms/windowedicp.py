"""``slipmap:windowedicp``: the windowed-ICP job (:mod:`slipmap.app.icp`) as a Processing
algorithm."""

from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingException,
    QgsProcessingParameterFeatureSink,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFileDestination,
)

from ...app import icp as job
from ..compat import speedup_message
from ._base import (
    SlipMapAlgorithm,
    add_parameters,
    is_set,
    source_parts,
)
from ._fields import (
    FIELDS_GROUP,
    add_optional_file_output,
    apply_style_on_load,
    file_outputs,
    help_text,
    qgs_crs,
    write_point_sink,
    write_polygon_sink,
)

_FILES = ("summary", "plot")


class WindowedICPAlgorithm(SlipMapAlgorithm):
    _id = "windowedicp"
    _name = "Displacement field (windowed ICP)"
    _group, _group_id = FIELDS_GROUP
    spec = job.SPEC

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return help_text(
            job.SPEC,
            "cells (one square polygon per fitted cell) and vectors (a point at each cell "
            "centre), both in the point cloud's CRS with the cell's columns: x, y, z (cell "
            "centre, mean after height, m), dx, dy, dz (m, east/north/up), sigma_dx, sigma_dy, "
            "sigma_dz (1-sigma, m), rmse (point-to-plane, m), n (correspondences), the "
            "rotations and their sigmas, the iterations, magnitude (horizontal, m) and "
            "azimuth_deg (clockwise from north); a JSON summary; optionally a figure (PNG). "
            "The moving area may be a polygon layer in any CRS (reprojected to the clouds'). "
            "Breaklines (optional line layer, any CRS): scarps, faults or slab edges across "
            "which the default spline field may jump; left empty, they are detected in the "
            "cells' motions (the summary lists them).",
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        add_parameters(self, job.SPEC, roles=("input", "setting"))
        mask = job.SPEC["stable_mask"]
        p = QgsProcessingParameterFeatureSource(
            "STABLE_MASK", mask.dialog_label, [QgsProcessing.TypeVectorPolygon], optional=True
        )
        p.setHelp(mask.help)
        self.addParameter(p)
        lines = job.SPEC["breaklines"]
        p = QgsProcessingParameterFeatureSource(
            "BREAKLINES", lines.dialog_label, [QgsProcessing.TypeVectorLine], optional=True
        )
        p.setHelp(lines.help)
        self.addParameter(p)
        self.addParameter(
            QgsProcessingParameterFeatureSink("CELLS", "ICP cells", QgsProcessing.TypeVectorPolygon)
        )
        self.addParameter(
            QgsProcessingParameterFeatureSink(
                "VECTORS", "ICP vectors", QgsProcessing.TypeVectorPoint
            )
        )
        opt = job.SPEC["summary"]
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", opt.dialog_label, opt.file_filter)
        )
        add_optional_file_output(self, job.SPEC, "plot")

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        opts = self.job_options(parameters, context)
        speedups = ("numba",) if opts.get("backend", "auto") in ("auto", "numba") else ()
        for name in speedups + ("threadpoolctl",):
            hint = speedup_message(name)
            if hint:
                feedback.pushInfo(hint)
        outputs = file_outputs(self, parameters, context, job.SPEC, _FILES)
        stable_mask = None
        if is_set(parameters, "STABLE_MASK", context):
            source = self.parameterAsSource(parameters, "STABLE_MASK", context)
            label = f'"{job.SPEC["stable_mask"].dialog_label}"'
            if source is None:
                raise QgsProcessingException(f"{label}: the layer cannot be read")

            def stable_mask(crs):
                return source_parts(source, qgs_crs(crs), context, parameter=label, polygons=True)

        breaklines = None
        if is_set(parameters, "BREAKLINES", context):
            lines = self.parameterAsSource(parameters, "BREAKLINES", context)
            lines_label = f'"{job.SPEC["breaklines"].dialog_label}"'
            if lines is None:
                raise QgsProcessingException(f"{lines_label}: the layer cannot be read")

            def breaklines(crs):
                return source_parts(lines, qgs_crs(crs), context, parameter=lines_label,
                                    polygons=False)  # fmt: skip

        result = self.run_job(
            job, opts, outputs, feedback, stable_mask=stable_mask, breaklines=breaklines
        )
        res, cols, crs = result.data["result"], result.data["columns"], qgs_crs(result.data["crs"])
        cells_id = write_polygon_sink(
            self, parameters, "CELLS", context, crs, result.data["rings"], cols
        )
        vectors_id = write_point_sink(self, parameters, "VECTORS", context, crs, res.x, res.y, cols)
        if cells_id is not None:
            apply_style_on_load(context, cells_id, "icp_cells", columns=cols, alg=self)
        if vectors_id is not None:
            apply_style_on_load(context, vectors_id, "icp_vectors", columns=cols, alg=self)
        return {
            "CELLS": cells_id,
            "VECTORS": vectors_id,
            "SUMMARY": outputs["summary"],
            "PLOT": outputs["plot"],
        }
