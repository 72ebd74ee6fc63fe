"""Job ``piv``: 3D displacement field by multi-pass PIV on gridded elevation (Aryal et al.,
section 3.2.1).

Both epochs are gridded on one common grid (mean z per cell), the elevation images are
cross-correlated window by window in passes of shrinking windows (:func:`slipmap.core.piv.piv`)
and the vectors are written as a CSV, dx/dy/dz GeoTIFFs, a figure and ``piv.json``.
"""

from __future__ import annotations

import logging
from typing import Any, Dict, Mapping, Optional

import numpy as np

from .._version import __version__
from .fields import (
    ARYAL,
    JSON_FILTER,
    PNG_FILTER,
    TIF_FILTER,
    breaklines_option,
    check_windows_fit,
    common_grid_of,
    compare_control,
    control_option,
    field_of_columns,
    figures,
    horizontal_columns,
    output_option,
    pair_inputs,
    pair_options,
    read_breaklines,
    read_control,
    read_pair,
    write_tif,
)
from .job import JobResult, Progress, scaled
from .options import JobSpec, Option
from .outputs import OutputPlan
from .styles import write_raster_style
from .summaries import finite_stats, json_text
from .tiled_fields import check_fields_tiled

log = logging.getLogger("slipmap.app")

CITATION = f"{ARYAL}, section 3.2.1 (PIV on gridded elevation)"
#: working memory per DEM cell (bytes): the two DEMs (16), their masks and the ref-shifted
#: images (18), the warper's spline coefficients, support and distance-transform indices while
#: it is built (40), a warp's coordinate stack, its rows/cols and two outputs (64), the
#: predictor fields (16); rounded up
BYTES_PER_CELL = 160
_GROUP = "PIV"


def _num(key, type_, help_, label, **kw):
    return Option(key, type_, help_, label=label, group=_GROUP, **kw)


SPEC = JobSpec(
    name="piv",
    title="Displacement field (PIV)",
    description=(
        "3D displacement field between two epochs by particle image velocimetry on gridded "
        "elevation: both clouds are gridded on one grid, the elevation images are "
        "cross-correlated window by window in passes of shrinking windows, outliers are "
        "replaced by their neighbours' mean and dz is the mean elevation change over the "
        "final window after the horizontal shift."
    ),
    options=(
        *pair_options(accepts_tiles=True),
        _num(
            "grid_m",
            "float",
            "DEM grid size GR, metres (the study used 0.04)",
            "Grid size GR (m)",
            default=0.25,
            required=True,
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
        _num(
            "windows_px",
            "ints",
            "interrogation window side WC of each pass, pixels; every window must fit in the "
            "DEM (default 64 32 16 16 16: repeating the last size halves the error in "
            "deforming areas)",
            "Interrogation windows per pass (pixels)",
            default=(64, 32, 16, 16, 16),
            nargs="+",
            minimum=4,
            cli="--window",
            qgis="WINDOWS",
            metavar="PX",
            advanced=True,
        ),
        _num(
            "passes",
            "int",
            "number of passes: the window list is cut, or its last size repeated, to reach it",
            "Number of passes",
            minimum=1,
            metavar="N",
            advanced=True,
            unset_text="one per window",
        ),
        _num(
            "overlap",
            "float",
            "window overlap (0-0.95); a vector every WC (1 - overlap) pixels of the last pass",
            "Window overlap (0-0.95)",
            default=0.5,
            minimum=0,
            maximum=0.95,
            advanced=True,
        ),
        _num(
            "search_px",
            "int",
            "first-pass search margin on each side, pixels (default from the largest expected "
            "displacement, else a quarter window)",
            "First-pass search margin (pixels)",
            minimum=1,
            cli="--search-px",
            qgis="SEARCH_PX",
            metavar="PX",
            advanced=True,
        ),
        _num(
            "max_displacement_m",
            "float",
            "largest expected displacement d_max, metres: sets the search margin (the study's "
            "rule of thumb is WC >= 2 d_max)",
            "Largest expected displacement d_max (m)",
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
        _num(
            "snr_min",
            "float",
            "signal-to-noise threshold: vectors with a weaker correlation peak are outliers "
            "(0: off)",
            "Signal-to-noise threshold",
            default=1.2,
            minimum=0,
            advanced=True,
        ),
        _num(
            "median_threshold",
            "float",
            "normalised median test threshold (0: off; 2 in Westerweel & Scarano 2005, 1.5 "
            "removes more of the clustered wrong vectors of sparse DEMs)",
            "Normalised median test threshold (0: off)",
            default=1.5,
            minimum=0,
            advanced=True,
        ),
        _num(
            "vertical_compensation",
            "bool",
            "remove the elevation change measured by the previous pass from the deformed "
            "after-DEM before each correlation: a change that varies across a window (a "
            "lobe's flank) otherwise reads as a horizontal shift",
            "Compensate the elevation change between passes",
            default=True,
            advanced=True,
        ),
        breaklines_option(
            "the windows are deformed per side, a window crossed by a line is correlated on its "
            "centre's side only, outliers are tested against and replaced by neighbours on "
            "their side, and the vectors whose window a line crosses are flagged (near_break)"
        ),
        control_option(),
        Option(
            "write_dems",
            "bool",
            "also write the two DEMs (dems.tif)",
            label="Write the DEMs",
            default=False,
            qgis=None,
            pdal=None,
        ),
        output_option("table", "the vectors (piv.csv)", "PIV vectors (CSV)"),
        output_option("dx", "dx GeoTIFF, m", "PIV dx (m)", qgis="DX", file_filter=TIF_FILTER),
        output_option("dy", "dy GeoTIFF, m", "PIV dy (m)", qgis="DY", file_filter=TIF_FILTER),
        output_option("dz", "dz GeoTIFF, m", "PIV dz (m)", qgis="DZ", file_filter=TIF_FILTER),
        output_option("dems", "both DEMs (dems.tif)", "DEMs"),
        output_option(
            "summary", "summary (piv.json)", "PIV summary", qgis="SUMMARY", file_filter=JSON_FILTER
        ),
        output_option(
            "plot", "figure (piv.png)", "PIV figure (PNG)", qgis="PLOT", file_filter=PNG_FILTER
        ),
    ),
    citation=CITATION,
    check=lambda opts: check_fields_tiled(
        opts,
        refused={
            "write_dems": "`slipmap dem-diff` writes both DEMs of tiled inputs (bands z_before, "
            "z_after of a Cloud-Optimized GeoTIFF)"
        },
    ),
)


def windows(opts: Mapping[str, Any]) -> list:
    """The window sizes of the passes: ``windows_px`` cut, or its last size repeated, to
    ``passes``."""
    w = list(opts["windows_px"])
    n = opts.get("passes")
    if n is not None:
        w = w[:n] + [w[-1]] * max(0, n - len(w))
    return w


def default_names(opts: Mapping[str, Any]) -> Dict[str, str]:
    """File names of the outputs in an output folder (the CLI's ``--out``)."""
    names = {
        "table": "piv.csv",
        "dx": "piv_dx.tif",
        "dy": "piv_dy.tif",
        "dz": "piv_dz.tif",
        "summary": "piv.json",
        "plot": "piv.png",
    }
    if opts.get("write_dems"):
        names["dems"] = "dems.tif"
    return names


def run(
    opts: Mapping[str, Any],
    outputs: Mapping[str, Any],
    *,
    progress: Optional[Progress] = None,
    breaklines=None,
) -> JobResult:
    """Read both epochs, grid them, run PIV, compare with control points and write.

    Parameters
    ----------
    opts
        :data:`SPEC`'s options, parsed.
    outputs
        ``{"out": folder}`` (every output under :func:`default_names`) or ``{output key:
        path or None}`` (``table``, ``dx``, ``dy``, ``dz``, ``dems``, ``summary``, ``plot``).
    breaklines : callable, optional
        ``f(crs)`` -> the breaklines as polylines ((K, 2) vertex arrays in ``crs``, the
        epochs' CRS): a face's line layer (QGIS), used instead of the ``breaklines`` file.

    Returns
    -------
    JobResult
        ``data``: ``{"result": PIVResult, "columns": vectors' columns with magnitude and
        azimuth_deg, "crs": pyproj CRS or None}``.
    """
    from .tiled import is_tiled

    plan = OutputPlan.for_outputs(
        inputs=pair_inputs(opts, "before", "after", "control", "breaklines"),
        outputs=outputs,
        default_names=default_names(opts),
    )
    plan.check()
    wins = windows(opts)
    with plan:
        control = read_control(opts.get("control"))
        if progress is not None:
            progress(0.0, "reading both epochs")
        if is_tiled(opts, "before", "after"):  # blocks of windows (app/tiled_fields.py)
            from .tiled_fields import piv_for_job

            res, grid, crs = piv_for_job(
                opts,
                wins,
                bytes_per_cell=BYTES_PER_CELL,
                progress=scaled(progress, 0.0, 0.95),
                breaklines_of=lambda crs: _lines(opts, crs, breaklines),
            )
            zb = za = None
        else:
            res, grid, crs, zb, za = _compute(opts, wins, progress, breaklines)
        cols = res.to_columns()
        comparison = None
        if control is not None:
            field = field_of_columns(
                cols["x"],
                cols["y"],
                cols["dx"],
                cols["dy"],
                cols["dz"],
                spacing_m=res.spacing_m,
                key="control",
                what="the PIV field",
            )
            comparison = compare_control(control, field)
        ok = np.isfinite(res.dx) & np.isfinite(res.dy)
        summary = {
            "command": "piv",
            "before": str(opts["before"]),
            "after": str(opts["after"]),
            "grid_m": grid.cell_m,
            "dem_shape": list(grid.shape),
            "windows_px": list(res.windows_px),
            "overlap": opts["overlap"],
            "search_px": res.search_px,
            "vector_spacing_m": res.spacing_m,
            "n_vectors": int(res.dx.size),
            "n_with_value": int(ok.sum()),
            "valid_fraction": float(res.valid.mean()) if res.valid.size else 0.0,
            "breaklines": (
                "line layer"
                if breaklines is not None
                else opts.get("breaklines") and str(opts["breaklines"])
            ),
            "n_near_break": int(res.near_break_or_false().sum()),
            "horizontal_m": finite_stats(np.hypot(res.dx, res.dy)),
            "dz_m": finite_stats(res.dz),
            "control": comparison,
            "crs": None if crs is None else crs.to_wkt(),
            "slipmap_version": __version__,
        }
        if progress is not None:
            progress(0.96, "writing")
        _write(plan, res, cols, zb, za, grid, crs)
        summary["files"] = plan.written_names(_KEYS[:-1])
        if plan.wants("summary"):
            plan.file("summary").write_text(json_text(summary), encoding="utf-8")
        if progress is not None:
            progress(1.0, "PIV done")
    lines = [
        f"PIV: {summary['n_vectors']} vectors every {res.spacing_m:g} m "
        f"({100 * summary['valid_fraction']:.0f} % valid), median horizontal "
        f"{summary['horizontal_m'].get('median', float('nan')):.4f} m"
    ]
    if comparison is not None:
        lines.append(
            f"control points: {comparison['n_compared']} of {comparison['n_rows']} compared, "
            f"horizontal RMSE {comparison['rmse_horizontal_m']:.4f} m"
        )
    files = {k: plan.final(k) for k in _KEYS if plan.wants(k) and plan.final(k).exists()}
    columns = dict(cols, **horizontal_columns(cols["dx"], cols["dy"]))
    return JobResult(summary, lines, files, data={"result": res, "columns": columns, "crs": crs})


_KEYS = ("table", "dx", "dy", "dz", "dems", "plot", "summary")


def _lines(opts: Mapping[str, Any], crs, given):
    """The run's :class:`~slipmap.core.breaklines.Breaklines` (or None): a face's line layer
    ``given(crs)``, else the ``breaklines`` file reprojected to ``crs``."""
    if given is not None:
        from ..core.breaklines import from_sequence

        return from_sequence(list(given(crs)))
    return read_breaklines(opts.get("breaklines"), crs)


def _compute(opts: Mapping[str, Any], wins, progress, given_lines=None):
    """One file per epoch: both read whole, gridded (:func:`dems`; the points are let go
    before the PIV), PIV (:func:`piv_of_dems`). Returns ``(PIVResult, grid, crs, z_before,
    z_after)``."""
    before, after, crs = read_pair(opts)
    lines = _lines(opts, crs, given_lines)
    grid, zb, za = dems(before, after, opts, wins, progress=progress)
    del before, after
    return piv_of_dems(zb, za, grid, opts, wins, lines=lines, progress=progress), grid, crs, zb, za


def dems(before, after, opts: Mapping[str, Any], wins, *, progress=None):
    """Both epochs gridded on one grid (the CLI's, QGIS's and PDAL's one-file run).

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The epochs' points, metres, one CRS.
    opts
        :data:`SPEC`'s options, parsed; ``wins`` their window sizes (:func:`windows`).

    Returns
    -------
    (grid, z_before, z_after)
        The grid and both DEMs, (n_rows, n_cols) float64 metres, NaN where no point is.
    """
    from ..core.dem import grid_elevation

    grid = common_grid_of(
        before, after, opts["grid_m"], key="grid_m", bytes_per_cell=BYTES_PER_CELL
    )
    check_windows_fit(wins, grid)
    if progress is not None:
        progress(0.02, "gridding both epochs")
    zb = grid_elevation(before, grid=grid)
    za = grid_elevation(after, grid=grid)
    log.info("DEMs: %d x %d cells of %.3f m", grid.n_rows, grid.n_cols, grid.cell_m)
    return grid, zb, za


def piv_of_dems(zb, za, grid, opts: Mapping[str, Any], wins, *, lines=None, progress=None):
    """:func:`~slipmap.core.piv.piv` of the two DEMs of :func:`dems` with the job's options
    and the given ``lines`` (Breaklines or None: windows are not smeared across them)."""
    from ..core.piv import piv

    return piv(
        zb,
        za,
        grid=grid,
        windows_px=wins,
        overlap=opts["overlap"],
        search_px=opts.get("search_px"),
        expected_max_displacement_m=opts.get("max_displacement_m"),
        snr_min=opts["snr_min"],
        median_threshold=opts["median_threshold"],
        breaklines=lines,
        vertical_compensation=bool(opts.get("vertical_compensation", True)),
        progress=scaled(progress, 0.05, 0.95),
    )


def _write(plan: OutputPlan, res, cols, zb, za, grid, crs) -> None:
    if plan.wants("table"):
        from ..core.io.table import write_csv_columns

        write_csv_columns(plan.file("table"), cols)
    meta = {"method": "PIV", "windows_px": " ".join(map(str, res.windows_px))}
    for comp in ("dx", "dy", "dz"):
        if plan.wants(comp):
            write_tif(
                plan.file(comp),
                getattr(res, comp),
                origin_xy=res.origin_xy,
                pixel_m=res.spacing_m,
                crs=crs,
                names=[comp],
                metadata=meta,
            )
            write_raster_style(plan, "piv", comp, getattr(res, comp))
    if plan.wants("dems"):
        write_tif(
            plan.file("dems"),
            np.stack([zb, za]),
            origin_xy=grid.origin_xy,
            pixel_m=grid.cell_m,
            crs=crs,
            names=["z_before", "z_after"],
        )
    report = figures() if plan.wants("plot") else None
    if report is not None:
        report.plot_vector_field(
            plan.file("plot"),
            x=cols["x"],
            y=cols["y"],
            dx=cols["dx"],
            dy=cols["dy"],
            valid=cols["valid"],
            colour=cols["dz"],
            background=None if zb is None else report.hillshade(zb, cell_m=grid.cell_m),
            extent=(grid.x_min, grid.x_max, grid.y_min, grid.y_max),
            title=f"PIV, GR {grid.cell_m:g} m, windows {list(res.windows_px)} px",
        )
