"""``slipmap:demdiff``: vertical change by DEM differencing (the simple baseline)."""

from __future__ import annotations

from qgis.core import (
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
)

from ._base import LAS_FILTER, SlipMapAlgorithm, progress_callback, slipmap_errors, write_json
from ._fields import (
    FIELDS_GROUP,
    apply_diverging_style_on_load,
    finite_stats,
    json_safe,
    read_pair,
    write_raster,
)

BANDS = ("dz", "z_before", "z_after")


class DemDifferenceAlgorithm(SlipMapAlgorithm):
    _id = "demdiff"
    _name = "DEM difference"
    _group, _group_id = FIELDS_GROUP

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "Vertical change between two epochs by DEM differencing: both clouds are gridded "
            "on one common grid covering their overlap (mean z of the points in each cell, no "
            "extrapolation; empty cells are no data) and dz = z_after - z_before. A scalar, "
            "vertical-only measure: it cannot resolve horizontal motion (use PIV or windowed "
            "ICP), see Aryal (2014), chapter 3, section 3.1.<br>"
            "<b>Before / After</b>: LAS/LAZ epochs in a projected CRS (metres); after is "
            "reprojected to before's CRS if they differ. "
            "<b>Grid size</b> (m): DEM cell (default 0.25).<br>"
            "<b>Outputs</b>: a 3-band GeoTIFF in the point cloud's CRS (band 1 dz, band 2 "
            "z_before, band 3 z_after, metres; NaN = no data), styled with a diverging ramp "
            "centred on 0; a JSON summary (mean, median, std of dz)."
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFile("BEFORE", "Before epoch", fileFilter=LAS_FILTER)
        )
        self.addParameter(QgsProcessingParameterFile("AFTER", "After epoch", fileFilter=LAS_FILTER))
        self.addParameter(
            QgsProcessingParameterNumber(
                "GRID",
                "Grid size (m)",
                QgsProcessingParameterNumber.Double,
                defaultValue=0.25,
                minValue=1e-6,
            )
        )
        self.addParameter(
            QgsProcessingParameterRasterDestination(
                "OUTPUT", "DEM difference (dz, z_before, z_after)"
            )
        )
        self.addParameter(
            QgsProcessingParameterFileDestination(
                "SUMMARY", "DEM difference summary", "JSON (*.json)"
            )
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        import numpy as np

        before_path = self.parameterAsFile(parameters, "BEFORE", context)
        after_path = self.parameterAsFile(parameters, "AFTER", context)
        grid_m = self.parameterAsDouble(parameters, "GRID", context)
        out = self.parameterAsOutputLayer(parameters, "OUTPUT", context)
        summary_path = self.parameterAsFileOutput(parameters, "SUMMARY", context)
        with slipmap_errors():
            from ...core.dem import dem_difference

            progress = progress_callback(feedback)
            progress(0.0, "reading both epochs")
            before, after, crs = read_pair(before_path, after_path)
            progress(0.5, "gridding and differencing")
            res = dem_difference(before, after, cell_m=grid_m)
            g = res.grid
            write_raster(
                out,
                np.stack([res.dz, res.z_before, res.z_after]),
                g.origin_xy,
                g.cell_m,
                crs,
                BANDS,
                {"method": "DEM difference, dz = z_after - z_before"},
            )
            summary = {
                "command": "dem-diff",
                "before": before_path,
                "after": after_path,
                "grid_m": g.cell_m,
                "shape": list(g.shape),
                "origin_xy": list(g.origin_xy),
                "dz_m": finite_stats(res.dz),
            }
            write_json(summary_path, json_safe(summary))
            progress(1.0, "DEM difference done")
        apply_diverging_style_on_load(context, out, "diverging")
        feedback.pushInfo(
            f"DEM difference: {res.n_valid} cells, mean dz {res.mean_m:+.4f} m "
            f"(std {res.std_m:.4f} m)"
        )
        return {"OUTPUT": out, "SUMMARY": summary_path}
