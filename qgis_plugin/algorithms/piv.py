"""``slipmap:piv``: 3D displacement field by multi-pass PIV on gridded elevation (DEMs)."""

from __future__ import annotations

from qgis.core import (
    QgsProcessing,
    QgsProcessingParameterFeatureSink,
    QgsProcessingParameterFile,
    QgsProcessingParameterFileDestination,
    QgsProcessingParameterNumber,
    QgsProcessingParameterRasterDestination,
    QgsProcessingParameterString,
)

from ._base import (
    LAS_FILTER,
    SlipMapAlgorithm,
    apply_style_on_load,
    progress_callback,
    slipmap_errors,
    write_json,
)
from ._fields import (
    CONTROL_HELP,
    FIELDS_GROUP,
    PIV_CITATION,
    PIV_SINK_FIELDS,
    add_control_parameter,
    advanced,
    apply_diverging_style_on_load,
    control_comparison,
    finite_stats,
    horizontal,
    json_safe,
    parse_windows,
    qgs_crs,
    read_pair,
    write_point_sink,
    write_raster,
)


class PIVAlgorithm(SlipMapAlgorithm):
    _id = "piv"
    _name = "Displacement field (PIV)"
    _group, _group_id = FIELDS_GROUP

    def shortHelpString(self):  # noqa: N802 (QGIS API name)
        return (
            "3D displacement field between two epochs by particle image velocimetry on "
            "gridded elevation: both clouds are gridded on one common grid (mean z per cell, no "
            "extrapolation), the elevation images are cross-correlated window by window "
            "(masked normalised cross-correlation, sub-pixel Gaussian peak) in several passes "
            "of shrinking windows, each pass warping the after-image by the previous field; "
            "outliers (low signal-to-noise or failing the normalised median test) are replaced "
            "by their neighbours' mean; dz is the mean elevation change over the final window "
            "after the horizontal shift.<br>"
            "<b>Before / After</b>: LAS/LAZ epochs in a projected CRS (metres); after is "
            "reprojected to before's CRS if they differ. "
            "<b>Grid size</b> GR (m): DEM cell (default 0.25; the study used 0.04). "
            "<b>Windows</b> (pixels, advanced): interrogation window side WC of each pass, "
            "e.g. '64 32 16 16' (default; repeating the last size refines the field once more); "
            "every window must fit in the DEM. "
            "<b>Overlap</b> (advanced, 0-0.95): window overlap; vectors every "
            "WC (1 - overlap) pixels of the last pass. "
            "<b>Largest expected displacement</b> d_max (m, optional): sets the first search "
            "margin (the study's rule of thumb: WC >= 2 d_max). "
            "<b>SNR threshold</b> and <b>median test threshold</b> (advanced): outlier tests. "
            + CONTROL_HELP
            + "<br><b>Outputs</b>: vectors (points at the window centres, in the point cloud's "
            "CRS, with dx, dy, dz (m, east/north/up), magnitude (horizontal, m), azimuth_deg "
            "(clockwise from north), snr (NULL: no second peak) and valid (0 = missing or "
            "replaced outlier)); dx, dy "
            "and dz GeoTIFFs (one pixel per vector); a JSON summary.<br>" + PIV_CITATION
        )

    def initAlgorithm(self, config=None):  # noqa: N802 (QGIS API name)
        self.addParameter(
            QgsProcessingParameterFile("BEFORE", "Before epoch", fileFilter=LAS_FILTER)
        )
        self.addParameter(QgsProcessingParameterFile("AFTER", "After epoch", fileFilter=LAS_FILTER))
        self.addParameter(
            QgsProcessingParameterNumber(
                "GRID",
                "Grid size GR (m)",
                QgsProcessingParameterNumber.Double,
                defaultValue=0.25,
                minValue=1e-6,
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterString(
                    "WINDOWS", "Interrogation windows per pass (pixels)", defaultValue="64 32 16 16"
                )
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterNumber(
                    "OVERLAP",
                    "Window overlap (0-0.95)",
                    QgsProcessingParameterNumber.Double,
                    defaultValue=0.5,
                    minValue=0.0,
                    maxValue=0.95,
                )
            )
        )
        self.addParameter(
            QgsProcessingParameterNumber(
                "MAX_DISPLACEMENT",
                "Largest expected displacement d_max (m)",
                QgsProcessingParameterNumber.Double,
                optional=True,
                minValue=0.0,
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterNumber(
                    "SNR_MIN",
                    "Signal-to-noise threshold",
                    QgsProcessingParameterNumber.Double,
                    defaultValue=1.2,
                    minValue=0.0,
                )
            )
        )
        self.addParameter(
            advanced(
                QgsProcessingParameterNumber(
                    "MEDIAN_THRESHOLD",
                    "Normalised median test threshold (0: off)",
                    QgsProcessingParameterNumber.Double,
                    defaultValue=2.0,
                    minValue=0.0,
                )
            )
        )
        add_control_parameter(self)
        self.addParameter(
            QgsProcessingParameterFeatureSink(
                "VECTORS", "PIV vectors", QgsProcessing.TypeVectorPoint
            )
        )
        for comp in ("DX", "DY", "DZ"):
            self.addParameter(
                QgsProcessingParameterRasterDestination(comp, f"PIV {comp.lower()} (m)")
            )
        self.addParameter(
            QgsProcessingParameterFileDestination("SUMMARY", "PIV summary", "JSON (*.json)")
        )

    def processAlgorithm(self, parameters, context, feedback):  # noqa: N802 (QGIS API name)
        import numpy as np

        from ._base import optional_number

        before_path = self.parameterAsFile(parameters, "BEFORE", context)
        after_path = self.parameterAsFile(parameters, "AFTER", context)
        grid_m = self.parameterAsDouble(parameters, "GRID", context)
        windows = parse_windows(self.parameterAsString(parameters, "WINDOWS", context))
        overlap = self.parameterAsDouble(parameters, "OVERLAP", context)
        d_max = optional_number(self, parameters, "MAX_DISPLACEMENT", context)
        snr_min = self.parameterAsDouble(parameters, "SNR_MIN", context)
        median = self.parameterAsDouble(parameters, "MEDIAN_THRESHOLD", context)
        control = self.parameterAsFile(parameters, "CONTROL", context)
        rasters = {
            c: self.parameterAsOutputLayer(parameters, c, context) for c in ("DX", "DY", "DZ")
        }
        summary_path = self.parameterAsFileOutput(parameters, "SUMMARY", context)
        with slipmap_errors():
            from ...core.dem import common_grid, grid_elevation
            from ...core.piv import piv
            from ...core.progress import scaled

            progress = progress_callback(feedback)
            before, after, crs = read_pair(before_path, after_path)
            progress(0.0, "gridding both epochs")
            grid = common_grid(before, after, cell_m=grid_m)
            zb = grid_elevation(before, grid=grid)
            za = grid_elevation(after, grid=grid)
            res = piv(
                zb,
                za,
                grid=grid,
                windows_px=windows,
                overlap=overlap,
                expected_max_displacement_m=d_max,
                snr_min=snr_min,
                median_threshold=median,
                progress=scaled(progress, 0.05, 0.95),
            )
            cols = res.to_columns()
            meta = {"method": "PIV", "windows_px": " ".join(map(str, res.windows_px))}
            for comp, path in rasters.items():
                c = comp.lower()
                write_raster(path, getattr(res, c), res.origin_xy, res.spacing_m, crs, [c], meta)
            mag, az = horizontal(cols["dx"], cols["dy"])
            ok = np.isfinite(res.dx) & np.isfinite(res.dy)
            summary = {
                "command": "piv",
                "before": before_path,
                "after": after_path,
                "grid_m": grid.cell_m,
                "dem_shape": list(grid.shape),
                "windows_px": list(res.windows_px),
                "overlap": overlap,
                "search_px": res.search_px,
                "vector_spacing_m": res.spacing_m,
                "n_vectors": int(res.dx.size),
                "n_with_value": int(ok.sum()),
                "valid_fraction": float(res.valid.mean()) if res.valid.size else 0.0,
                "horizontal_m": finite_stats(mag),
                "dz_m": finite_stats(res.dz),
                "control": control_comparison(
                    control, cols["x"], cols["y"], cols["dx"], cols["dy"], cols["dz"], res.spacing_m
                ),
            }
            write_json(summary_path, json_safe(summary))
            progress(1.0, "PIV done")
        columns = dict(cols, magnitude=mag, azimuth_deg=az)
        sink_id = write_point_sink(
            self,
            parameters,
            "VECTORS",
            context,
            qgs_crs(crs),
            cols["x"],
            cols["y"],
            columns,
            PIV_SINK_FIELDS,
        )
        if sink_id is not None:
            apply_style_on_load(context, sink_id, "piv_vectors")
        for path in rasters.values():
            apply_diverging_style_on_load(context, path)
        feedback.pushInfo(
            f"PIV: {summary['n_vectors']} vectors every {res.spacing_m:g} m "
            f"({100 * summary['valid_fraction']:.0f} % valid), median horizontal "
            f"{summary['horizontal_m'].get('median', float('nan')):.4f} m"
        )
        return {"VECTORS": sink_id, **rasters, "SUMMARY": summary_path}
