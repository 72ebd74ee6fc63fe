"""``slipmap:roughness``: ODR roughness per grid cell, as a map-view GeoTIFF and a CSV."""

from __future__ import annotations

from qgis.core import (
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
)

from ._base import LAS_FILTER, SlipMapAlgorithm, progress_callback, read_cloud, slipmap_errors

CSV_HEADER = "ix,iy,iz,x,y,z,n,theta_odr,theta_ols,e_ols,degenerate"


class RoughnessAlgorithm(SlipMapAlgorithm):
    _id = "roughness"
    _name = "Surface roughness"
    _group = "Roughness"
    _group_id = "roughness"

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "Roughness of a point cloud on a regular 3D grid: in every cell an orthogonal "
            "(ODR) plane is fitted and theta_ODR is the population standard deviation of the "
            "absolute orthogonal point-to-plane distances (Pollyea and Fairley 2011, Estimating "
            "surface roughness of terrestrial laser scan data using orthogonal distance "
            "regression, Geology 39(7), Eq. 4).<br>"
            "<b>Input point cloud</b>: LAS/LAZ in a projected CRS (metres). "
            "<b>Cell size</b> (m): edge of the grid cells and of the raster pixels (the study: "
            "1, 0.5, 0.25, 0.125). <b>Smallest cell</b> (points, at least 3): cells with fewer "
            "points are skipped (default 10).<br>"
            "<b>Outputs</b>: a GeoTIFF of theta_ODR (m) on the xy map plane in the point "
            "cloud's CRS (cells stacked vertically are averaged; NaN = no data) and a CSV with "
            "one row per cell (" + CSV_HEADER + ")."
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFile("INPUT", "Input point cloud", fileFilter=LAS_FILTER)
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                "CELL",
                "Cell size (m)",
                QgsProcessingParameterNumber.Double,
                defaultValue=1.0,
                minValue=1e-6,
            )
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                "MIN_POINTS",
                "Smallest cell (points)",
                QgsProcessingParameterNumber.Integer,
                defaultValue=10,
                minValue=3,
            )
        )
        self.addParameter(
            QgsProcessingParameterRasterDestination("OUTPUT", "Roughness theta_ODR (m)")
        )
        self.addParameter(
            QgsProcessingParameterFileDestination("CSV", "Roughness per cell", "CSV (*.csv)")
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        path = self.parameterAsFile(parameters, "INPUT", context)
        cell = self.parameterAsDouble(parameters, "CELL", context)
        min_points = self.parameterAsInt(parameters, "MIN_POINTS", context)
        out = self.parameterAsOutputLayer(parameters, "OUTPUT", context)
        csv_path = self.parameterAsFileOutput(parameters, "CSV", context)
        with slipmap_errors():
            import numpy as np

            from ...core import roughness as rg
            from ...core.errors import InputDataError
            from ...core.io.atomic import write_text_atomic
            from ...core.io.raster import write_geotiff

            cloud = read_cloud(path)
            frame = rg.principal_frame(cloud.xyz)
            grid = rg.grid_roughness(
                cloud.xyz,
                cell_size_m=cell,
                min_points=min_points,
                ols_axis=rg.resolve_ols_axis(frame, "auto"),
                progress=progress_callback(feedback),
            )
            if len(grid) == 0:
                raise InputDataError(f"no cell of {cell:g} m has {min_points} or more points")
            table = np.column_stack(
                [
                    grid.index,
                    grid.centre_m,
                    grid.n_points,
                    grid.theta_odr,
                    grid.theta_ols,
                    grid.e_ols,
                    grid.degenerate.astype(np.int64),
                ]
            )
            rows = [CSV_HEADER]
            for r in table:
                rows.append(
                    ",".join([f"{int(v)}" for v in r[:3]] + [f"{v:.6f}" for v in r[3:6]])
                    + f",{int(r[6])},{r[7]:.6g},{r[8]:.6g},{r[9]:.6g},{int(r[10])}"
                )
            write_text_atomic(csv_path, "\n".join(rows) + "\n")
            plane = rg.choose_map_plane(frame, "xy")
            raster = rg.rasterize_cells(grid.centre_m, grid.theta_odr, plane, pixel_size_m=cell)
            write_geotiff(
                out,
                raster.values.astype(np.float32),
                origin_xy=raster.origin_uv_m,
                pixel_size_m=raster.pixel_size_m,
                crs_wkt=cloud.crs.to_wkt() if cloud.crs is not None else None,
                band_names=["theta_odr"],
                metadata={"SLIPMAP_CELL_SIZE_M": f"{cell:g}", "SLIPMAP_MAP_PLANE": "xy"},
            )
        feedback.pushInfo(f"{len(grid)} cells; wrote {out} and {csv_path}")
        return {"OUTPUT": out, "CSV": csv_path}
