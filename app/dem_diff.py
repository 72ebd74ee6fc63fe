"""Job ``dem-diff``: vertical change by DEM differencing (the simple baseline; Aryal 2014,
chapter 3, section 3.1).

Both epochs are gridded on one grid over their overlap (mean z per cell, no extrapolation)
and ``dz = z_after - z_before`` is written as a 3-band GeoTIFF, a figure and
``dem_diff.json``.
"""

from __future__ import annotations

import logging
from typing import Any, Dict, Mapping, Optional

import numpy as np

from .._version import __version__
from .fields import (
    JSON_FILTER,
    PNG_FILTER,
    TIF_FILTER,
    common_grid_of,
    figures,
    output_option,
    pair_inputs,
    pair_options,
    read_pair,
    write_tif,
)
from .job import JobResult, Progress
from .options import JobSpec, Option
from .outputs import OutputPlan
from .styles import write_raster_style
from .summaries import finite_stats, json_text
from .tiled_fields import check_fields_tiled

log = logging.getLogger("slipmap.app")

#: working memory per DEM cell (bytes): per epoch while gridding the counts, sums and means
#: (24), the two DEMs and dz kept (24), dz's finite values (8), the 3-band stack written (24)
BYTES_PER_CELL = 80
BANDS = ("dz", "z_before", "z_after")

SPEC = JobSpec(
    name="dem-diff",
    title="DEM difference",
    description=(
        "Vertical change between two epochs by DEM differencing: both clouds are gridded on "
        "one grid over their overlap (mean z per cell, no extrapolation) and dz = z_after - "
        "z_before. A vertical-only measure: it cannot resolve horizontal motion (use PIV or "
        "windowed ICP)."
    ),
    options=(
        *pair_options(accepts_tiles=True),
        Option(
            "grid_m",
            "float",
            "DEM cell size, metres",
            label="Grid size (m)",
            default=0.25,
            required=True,
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
        output_option(
            "raster",
            "dz, z_before, z_after GeoTIFF (dem_diff.tif)",
            "DEM difference (dz, z_before, z_after)",
            qgis="OUTPUT",
            file_filter=TIF_FILTER,
        ),
        output_option(
            "summary",
            "summary (dem_diff.json)",
            "DEM difference summary",
            qgis="SUMMARY",
            file_filter=JSON_FILTER,
        ),
        output_option(
            "plot",
            "figure (dem_diff.png)",
            "DEM difference figure (PNG)",
            qgis="PLOT",
            file_filter=PNG_FILTER,
        ),
    ),
    check=lambda opts: check_fields_tiled(opts, refused={}),
)


def default_names(opts: Mapping[str, Any]) -> Dict[str, str]:
    return {"raster": "dem_diff.tif", "summary": "dem_diff.json", "plot": "dem_diff.png"}


def run(
    opts: Mapping[str, Any],
    outputs: Mapping[str, Any],
    *,
    progress: Optional[Progress] = None,
) -> JobResult:
    """Read both epochs, grid and difference them, write.

    ``outputs``: ``{"out": folder}`` or ``{"raster": path, "summary": path, "plot": path}``
    (None: not written). ``data`` of the result: the
    :class:`~slipmap.core.dem.DemDifference`.
    """
    from ..core.dem import dem_difference
    from .tiled import is_tiled

    tiled = is_tiled(opts, "before", "after")
    plan = OutputPlan.for_outputs(
        inputs=pair_inputs(opts, "before", "after"),
        outputs=outputs,
        default_names=default_names(opts),
    )
    plan.check()
    if tiled:
        return _run_tiled(opts, plan, progress)
    with plan:
        if progress is not None:
            progress(0.0, "reading both epochs")
        before, after, crs = read_pair(opts)
        grid = common_grid_of(
            before, after, opts["grid_m"], key="grid_m", bytes_per_cell=BYTES_PER_CELL
        )
        if progress is not None:
            progress(0.5, "gridding and differencing")
        res = dem_difference(before, after, grid=grid)
        del before, after
        g = res.grid
        if plan.wants("raster"):
            write_tif(
                plan.file("raster"),
                np.stack([res.dz, res.z_before, res.z_after]),
                origin_xy=g.origin_xy,
                pixel_m=g.cell_m,
                crs=crs,
                names=BANDS,
                metadata={"method": "DEM difference, dz = z_after - z_before"},
            )
            write_raster_style(plan, "dem_diff", "raster", res.dz)
        report = figures() if plan.wants("plot") else None
        if report is not None:
            report.plot_raster_panels(
                plan.file("plot"),
                {"dz = after - before (m)": res.dz, "z before (m)": res.z_before},
                extent=(g.x_min, g.x_max, g.y_min, g.y_max),
                diverging=("dz = after - before (m)",),
                columns=2,
            )
        summary = _summary(opts, g, finite_stats(res.dz), plan, crs)
        if plan.wants("summary"):
            plan.file("summary").write_text(json_text(summary), encoding="utf-8")
        if progress is not None:
            progress(1.0, "DEM difference done")
    lines = [
        f"DEM difference: {res.n_valid} cells of {g.cell_m:g} m, mean dz {res.mean_m:+.4f} m "
        f"(std {res.std_m:.4f} m)"
    ]
    files = {
        k: plan.final(k)
        for k in ("raster", "plot", "summary")
        if plan.wants(k) and plan.final(k).exists()
    }
    return JobResult(summary, lines, files, data=res)


def _run_tiled(opts: Mapping[str, Any], plan: OutputPlan, progress) -> JobResult:
    """Tiled inputs or a Dask run: blocks of the grid (exact; app/tiled_fields.py), the raster
    written block by block as a Cloud-Optimized GeoTIFF. No figure: the whole raster is never
    in memory (the COG's overviews show it in QGIS)."""
    from .tiled_fields import dem_for_job

    with plan:
        res, crs = dem_for_job(
            opts,
            plan.file("raster") if plan.wants("raster") else None,
            bands=BANDS,
            metadata={"method": "DEM difference, dz = z_after - z_before"},
            bytes_per_cell=BYTES_PER_CELL,
            progress=progress,
        )
        g = res.grid
        write_raster_style(plan, "dem_diff", "raster")  # its range read from the COG
        if plan.wants("plot"):
            log.info("no figure for tiled inputs: open the GeoTIFF (a COG with overviews)")
        summary = _summary(opts, g, res.stats(), plan, crs)
        if plan.wants("summary"):
            plan.file("summary").write_text(json_text(summary), encoding="utf-8")
    lines = [
        f"DEM difference: {res.n_valid} cells of {g.cell_m:g} m, mean dz {res.mean_m:+.4f} m "
        f"(std {res.std_m:.4f} m), tiled"
    ]
    files = {
        k: plan.final(k) for k in ("raster", "summary") if plan.wants(k) and plan.final(k).exists()
    }
    return JobResult(summary, lines, files, data=res)


def _summary(opts: Mapping[str, Any], g, dz_stats, plan: OutputPlan, crs) -> Dict[str, Any]:
    """``dem_diff.json`` (before it names itself): inputs, grid, dz statistics, files."""
    return {
        "command": "dem-diff",
        "before": str(opts["before"]),
        "after": str(opts["after"]),
        "grid_m": g.cell_m,
        "shape": list(g.shape),
        "origin_xy": list(g.origin_xy),
        "dz_m": dz_stats,
        "files": plan.written_names(("raster", "plot")),
        "crs": None if crs is None else crs.to_wkt(),
        "slipmap_version": __version__,
    }
