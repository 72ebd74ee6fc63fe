"""``slipmap:windowedicp``: 3D displacement field by point-to-plane ICP in square cells."""

from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingException,
    QgsProcessingParameterBoolean,
    QgsProcessingParameterFeatureSink,
    QgsProcessingParameterFeatureSource,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
)
from qgis.PyQt.QtCore import QVariant

from ._base import (
    LAS_FILTER,
    SlipMapAlgorithm,
    apply_style_on_load,
    is_set,
    optional_number,
    progress_callback,
    slipmap_errors,
    source_parts,
    write_json,
)
from ._fields import (
    CONTROL_HELP,
    FIELDS_GROUP,
    ICP_CITATION,
    add_control_parameter,
    advanced,
    control_comparison,
    horizontal,
    icp_summary,
    json_safe,
    qgs_crs,
    read_pair,
    write_point_sink,
    write_polygon_sink,
)

ICP_SINK_FIELDS = tuple(
    (name, QVariant.Int if name == "n" else QVariant.Double)
    for name in (
        "x",
        "y",
        "z",
        "dx",
        "dy",
        "dz",
        "sigma_dx",
        "sigma_dy",
        "sigma_dz",
        "rmse",
        "n",
        "magnitude",
        "azimuth_deg",
    )
)


def polygon_rings(source, target_crs, context):
    """Exterior rings (K, 2) of every polygon part of ``source`` in ``target_crs`` (holes
    ignored, as ``core.io.vector.read_polygons``)."""
    return source_parts(source, target_crs, context, parameter="STABLE_MASK", polygons=True)


def cell_rings(res):
    """(5, 2) closed ring of every fitted cell of a ``WindowedICPResult``."""
    import numpy as np

    x0, y0 = res.origin_xy
    s = res.cell_m
    out = []
    for r, c in zip(res.row.tolist(), res.col.tolist()):
        left, top = x0 + c * s, y0 - r * s
        out.append(
            np.array(
                [[left, top], [left + s, top], [left + s, top - s], [left, top - s], [left, top]]
            )
        )
    return out


class WindowedICPAlgorithm(SlipMapAlgorithm):
    _id = "windowedicp"
    _name = "Displacement field (windowed ICP)"
    _group, _group_id = FIELDS_GROUP

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "3D displacement field by point-to-plane ICP in square cells: the after epoch is "
            "cut into cells on a grid snapped to multiples of the cell size; each cell's "
            "points are registered rigidly onto the before surface (nearest neighbours within "
            "the cell grown by the buffer, point-to-plane distances to PCA normals, robust "
            "weights); the cell's displacement is the ground motion at its centre, with 1-sigma "
            "from the adjustment's covariance.<br>"
            "<b>Before / After</b>: LAS/LAZ epochs in a projected CRS (metres); after is "
            "reprojected to before's CRS if they differ. "
            "<b>Cell size</b> (m): side of the square cells (default 5, as the study). "
            "<b>Buffer</b> (m, advanced, optional): before-points this far around a cell are "
            "matched (default half a cell); must exceed the largest displacement. "
            "<b>Smallest cell</b> (points, advanced, >= 7): cells with fewer after- or "
            "before-points are skipped (default 100). "
            "<b>Coarse-to-fine levels</b> (advanced): coarser passes (2x, 4x ... cells) whose "
            "motion starts each finer cell; needed when the motion is not small against the "
            "cell (default 1, 0 = off). "
            "<b>Formal sigmas only</b> (advanced): by default the cells' 1-sigma are multiplied "
            "by the field's variance factor, estimated from how well each cell agrees with the "
            "plane through its neighbours (formal sigmas assume independent point residuals "
            "and are 2-4x too small on real surfaces); tick to keep the formal ones. "
            "<b>Moving area</b> (optional polygon layer, any CRS, reprojected to the clouds' "
            "CRS): the after epoch is first aligned on the points OUTSIDE these polygons "
            "(stable ground; the study's masked global alignment), and displacements are "
            "relative to that stable frame. <b>Pre-align on all points</b> (advanced): a "
            "global pre-alignment without a mask. "
            + CONTROL_HELP
            + "<br><b>Outputs</b>: cells (one square polygon per fitted cell) and vectors (a "
            "point at each cell centre), both in the point cloud's CRS with x, y, z (cell "
            "centre, mean after height, m), dx, dy, dz (m, east/north/up), sigma_dx, sigma_dy, "
            "sigma_dz (1-sigma, m), rmse (point-to-plane, m), n (correspondences), magnitude "
            "(horizontal, m) and azimuth_deg (clockwise from north); a JSON summary.<br>"
            + ICP_CITATION
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFile("BEFORE", "Before epoch", fileFilter=LAS_FILTER)
        )
        self.addParameter(QgsProcessingParameterFile("AFTER", "After epoch", fileFilter=LAS_FILTER))
        self.addParameter(
            QgsProcessingParameterNumber(
                "CELL",
                "Cell size (m)",
                QgsProcessingParameterNumber.Double,
                defaultValue=5.0,
                minValue=1e-6,
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterNumber(
                    "BUFFER",
                    "Buffer around each cell (m; default half a cell)",
                    QgsProcessingParameterNumber.Double,
                    optional=True,
                    minValue=0.0,
                )
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterNumber(
                    "MIN_POINTS",
                    "Smallest cell (points)",
                    QgsProcessingParameterNumber.Integer,
                    defaultValue=100,
                    minValue=7,
                )
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterNumber(
                    "COARSE_TO_FINE",
                    "Coarse-to-fine levels",
                    QgsProcessingParameterNumber.Integer,
                    defaultValue=1,
                    minValue=0,
                )
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterBoolean(
                    "FORMAL_SIGMA", "Formal sigmas only", defaultValue=False
                )
            )
        )
        self.addParameter(
            QgsProcessingParameterFeatureSource(
                "STABLE_MASK",
                "Moving area (left out of the stable-ground pre-alignment)",
                [QgsProcessing.TypeVectorPolygon],
                optional=True,
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterBoolean(
                    "PREALIGN", "Pre-align on all points (no mask)", defaultValue=False
                )
            )
        )
        add_control_parameter(self)
        self.addParameter(
            QgsProcessingParameterFeatureSink("CELLS", "ICP cells", QgsProcessing.TypeVectorPolygon)
        )
        self.addParameter(
            QgsProcessingParameterFeatureSink(
                "VECTORS", "ICP vectors", QgsProcessing.TypeVectorPoint
            )
        )
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", "ICP summary", "JSON (*.json)")
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)

        before_path = self.parameterAsFile(parameters, "BEFORE", context)
        after_path = self.parameterAsFile(parameters, "AFTER", context)
        cell = self.parameterAsDouble(parameters, "CELL", context)
        buffer_m = optional_number(self, parameters, "BUFFER", context)
        min_points = self.parameterAsInt(parameters, "MIN_POINTS", context)
        levels = self.parameterAsInt(parameters, "COARSE_TO_FINE", context)
        prealign = self.parameterAsBoolean(parameters, "PREALIGN", context)
        formal = self.parameterAsBoolean(parameters, "FORMAL_SIGMA", context)
        mask_source = None
        if is_set(parameters, "STABLE_MASK"):
            mask_source = self.parameterAsSource(parameters, "STABLE_MASK", context)
            if mask_source is None:
                raise QgsProcessingException("STABLE_MASK: the layer cannot be read")
        control = self.parameterAsFile(parameters, "CONTROL", context)
        summary_path = self.parameterAsFileOutput(parameters, "SUMMARY", context)
        with slipmap_errors():
            from ...core.icp import windowed_icp

            before, after, crs = read_pair(before_path, after_path)
            exclude = None
            if mask_source is not None:
                exclude = polygon_rings(mask_source, qgs_crs(crs), context)
            res = windowed_icp(
                before,
                after,
                cell_m=cell,
                buffer_m=buffer_m,
                min_points=min_points,
                prealign=bool(exclude) or prealign,
                exclude_polygons=exclude,
                coarse_to_fine=levels,
                sigma_scaling="formal" if formal else "field",
                progress=progress_callback(feedback),
            )
            cols = res.to_columns()
            mag, az = horizontal(res.dx, res.dy)
            summary = {
                "command": "icp",
                "before": before_path,
                "after": after_path,
                "buffer_m": buffer_m,
                "min_points": min_points,
                "coarse_to_fine": levels,
                **icp_summary(res),
                "control": control_comparison(
                    control, res.x, res.y, res.dx, res.dy, res.dz, res.cell_m
                ),
            }
            write_json(summary_path, json_safe(summary))
        columns = dict(cols, magnitude=mag, azimuth_deg=az)
        crs_q = qgs_crs(crs)
        cells_id = write_polygon_sink(
            self, parameters, "CELLS", context, crs_q, cell_rings(res), columns, ICP_SINK_FIELDS
        )
        vectors_id = write_point_sink(
            self, parameters, "VECTORS", context, crs_q, res.x, res.y, columns, ICP_SINK_FIELDS
        )
        if cells_id is not None:
            apply_style_on_load(context, cells_id, "icp_cells")
        if vectors_id is not None:
            apply_style_on_load(context, vectors_id, "icp_vectors")
        feedback.pushInfo(
            f"windowed ICP: {len(res)} cells of {res.cell_m:g} m "
            f"({sum(res.skipped.values())} skipped), median horizontal "
            f"{summary['horizontal_m'].get('median', float('nan')):.4f} m, median sigma "
            f"{summary['sigma_horizontal_m'].get('median', float('nan')):.4f} m"
        )
        return {"CELLS": cells_id, "VECTORS": vectors_id, "SUMMARY": summary_path}
