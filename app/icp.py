"""Job ``icp``: 3D displacement field by windowed point-to-plane ICP (Aryal et al., section
3.2.2).

The after epoch is cut into square cells and each cell's points are registered onto the
before surface (:func:`slipmap.core.icp.windowed_icp`); the cells are written as a CSV, a
GeoPackage (cells and vectors), a multi-band GeoTIFF, a figure and ``icp.json``.

To add an option of :func:`~slipmap.core.icp.windowed_icp`: declare it in :data:`SPEC` under
the core's keyword and list the key in :data:`CORE_KEYS`. New result columns of
``WindowedICPResult.to_columns()`` reach the CSV, the GeoPackage and the QGIS layers by
themselves (:func:`layer_columns`).
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any, Callable, Dict, List, Mapping, Optional

import numpy as np

from .._version import __version__
from ..core.errors import SlipMapError
from .fields import (
    ARYAL,
    JSON_FILTER,
    PNG_FILTER,
    breaklines_option,
    check_overlap,
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
from .job import JobResult, Progress
from .options import JobSpec, Option, OptionError
from .outputs import OutputPlan
from .styles import gpkg_styles, write_raster_style
from .summaries import icp_summary, json_text
from .tiled_fields import check_fields_tiled, tiled_refusal

log = logging.getLogger("slipmap.app")

CITATION = (
    f"{ARYAL}, section 3.2.2 (windowed ICP); point-to-plane ICP: Chen, Y. and Medioni, G. "
    "(1992), Object modelling by registration of multiple range images, Image and Vision "
    "Computing 10(3), 145-155"
)
_GROUP = "windowed ICP"
#: bands of icp.tif
BANDS = ("dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_dz", "rmse", "n")


def _opt(key, type_, help_, label, **kw):
    return Option(key, type_, help_, label=label, group=_GROUP, **kw)


#: options that need both epochs in one place, refused for tiled inputs (key -> what to do)
CHECK_TILED = {
    "stable_mask": "the stable-ground pre-alignment is one fit over both whole epochs; align "
    "the epochs first (e.g. with a global ICP) or run on one file per epoch",
    "prealign": "the pre-alignment is one fit over both whole epochs; align the epochs first "
    "or run on one file per epoch",
}
#: the field model when field_model is not set (too few cells: cells, with a warning)
DEFAULT_FIELD_MODEL = "spline"
#: after-points registered per cell by default (0: all). docs/benchmarks.md "Stop 39": on
#: the landslide harness 2000 and 5000 (about every point at its density) differ by less
#: than two draws of 2000 points do; the lone-star lobe takes 0.39x the time of every point
DEFAULT_MAX_POINTS_PER_CELL = 2000

SPEC = JobSpec(
    name="icp",
    title="Displacement field (windowed ICP)",
    description=(
        "3D displacement field by point-to-plane ICP in square cells: each cell of the after "
        "epoch is registered rigidly onto the before surface; the cell's displacement is the "
        "ground motion at its centre, with 1-sigma from the adjustment scaled by the field's "
        "variance factor."
    ),
    options=(
        *pair_options(accepts_tiles=True),
        _opt(
            "cell_m",
            "float",
            "side of the square cells, metres (the study used 5)",
            "Cell size (m)",
            default=5.0,
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
        _opt(
            "buffer_m",
            "float",
            "before-points this far around each cell are matched, metres (default half a "
            "cell); must exceed the largest displacement",
            "Buffer around each cell (m; default half a cell)",
            minimum=0,
            metavar="M",
            advanced=True,
        ),
        _opt(
            "min_points",
            "int",
            "cells with fewer after- or before-points are skipped",
            "Smallest cell (points)",
            default=100,
            minimum=7,
            metavar="N",
            advanced=True,
        ),
        _opt(
            "max_points_per_cell",
            "int",
            "register at most this many after-points per cell (a seeded sample that depends "
            "on the points only, the same from tiles; 0: every point). By default 2000: on "
            "dense TLS cells more points make the run slower, not the motion more accurate "
            "(their errors are shared within the cell)",
            "Most points per cell (0: all)",
            default=DEFAULT_MAX_POINTS_PER_CELL,
            minimum=0,
            metavar="N",
            advanced=True,
        ),
        _opt(
            "coarse_to_fine",
            "int",
            "coarser passes (cells 2x, 4x, ...) that start each cell from the coarser motion "
            "(and from zero, keeping the better fit); needed when the motion is not small "
            "against the cell (0: off)",
            "Coarse-to-fine levels",
            default=1,
            minimum=0,
            metavar="LEVELS",
            advanced=True,
        ),
        _opt(
            "deform_passes",
            "int",
            "window-deformation passes after the first: each cell's after-points are moved "
            "back by the previous pass's field (cubic spline through the cell centres) and "
            "the residual is fitted, so the cell reports the motion at its centre, not the "
            "mean over a straining cell (0: off)",
            "Window-deformation passes",
            default=0,
            minimum=0,
            metavar="PASSES",
            advanced=True,
        ),
        _opt(
            "cell_model",
            "choice",
            "motion model of a cell: rigid (6 parameters, the study's) or affine (12: a 3x3 "
            "matrix and a translation; follows a straining cell and gives its strain)",
            "Cell model",
            default="rigid",
            choices=("rigid", "affine"),
            advanced=True,
        ),
        _opt(
            "field_model",
            "choice",
            "what each cell reports: spline (after the cells, one B-spline field fitted to "
            "all points at once, smooth on each side of the breaklines and free to jump "
            "across them; each cell gives the field at its centre, with its covariance and "
            "strain; follows a landslide lobe only 3-4 cells wide; on tiles the blocks' shares "
            "of each iteration's normal equations are summed: the one-file run's field) or "
            "cells (each cell's own transform, the study's). Default spline; cells where fewer "
            "than 4 cells hold points (with a warning)",
            "Field model (default spline)",
            choices=("cells", "spline"),
            unset_text="spline",
            advanced=True,
        ),
        _opt(
            "spline_spacing_m",
            "float",
            "knot spacing of the spline field, metres (default half a cell; smaller follows "
            "narrower lobes and is noisier)",
            "Spline knot spacing (m; default half a cell)",
            minimum=0,
            exclusive=True,
            metavar="M",
            advanced=True,
        ),
        _opt(
            "spline_smoothing",
            "float",
            "second-difference penalty of the spline field relative to its data (larger: "
            "smoother and less noisy, flatter peaks); by default estimated from the data "
            "(variance components)",
            "Spline smoothing (default: estimated)",
            minimum=0,
            metavar="W",
            advanced=True,
        ),
        breaklines_option(
            "the spline field is smooth on each side and may jump across them (given, "
            "nothing is detected); written to the GeoPackage's breaklines layer"
        ),
        _opt(
            "detect_breaklines",
            "bool",
            "with the spline field and no breaklines given: find them in the cells' motions "
            "(edges where neighbouring cells step by far more than their sigmas and than the "
            "neighbouring edges), place them on the points and fit the field smooth on each "
            "side",
            "Detect breaklines (when none are given)",
            default=True,
            advanced=True,
        ),
        _opt(
            "cell_choice",
            "bool",
            "with the spline field: a cell whose own rigid fit explains its points better "
            "than the field (its point-to-plane cost lower by more than two standard errors) "
            "and differs from it beyond their sigmas reports that fit, as does one that "
            "explains them as well where the field is barely determined (its sigma over 4x "
            "the cell's: a scan shadow); the from_cell column says so; where the ground moves in a "
            "way the field cannot follow and no breakline was found (a rotating slump block), "
            "the field smooths and the cells do not",
            "Cells keep their own fit where it fits better",
            default=True,
            advanced=True,
        ),
        _opt(
            "median_threshold",
            "float",
            "normalised median test of each cell against its 8 neighbours (Westerweel & "
            "Scarano 2005): cells above it are flagged as likely wrong minima (0: off)",
            "Wrong-minimum test threshold",
            default=2.0,
            minimum=0,
            metavar="R",
            advanced=True,
        ),
        _opt(
            "median_restart",
            "bool",
            "restart flagged cells from their neighbours' median motion and keep the restart "
            "where it fits better",
            "Restart flagged cells",
            default=False,
            advanced=True,
        ),
        _opt(
            "backend",
            "choice",
            "where the cells' point pairs are found: numpy (the reference), compiled CPU "
            "kernels through Numba, or an OpenCL device through PyOpenCL (the same pairs and "
            "results, faster on many points); auto uses OpenCL when a device is available, "
            "else Numba when installed, else numpy",
            "Backend",
            default="auto",
            choices=("numpy", "opencl", "auto", "numba"),
            advanced=True,
        ),
        _opt(
            "sigma_regions",
            "int",
            "variance factors per region: the cells are split into this many classes of "
            "SIGMA_REGION_BY (quantiles) and each class gets its own factor from the agreement "
            "of neighbouring cells, without flagged cells (1: one factor for the field)",
            "Variance-factor regions",
            default=1,
            minimum=1,
            metavar="N",
            advanced=True,
        ),
        _opt(
            "sigma_region_by",
            "choice",
            "what the variance-factor regions class: roughness (the cells' point-to-plane "
            "residual RMS), density (after-points per m²) or sigma (the formal sigma: both)",
            "Variance-factor regions by",
            default="roughness",
            choices=("roughness", "density", "sigma"),
            advanced=True,
        ),
        _opt(
            "formal_sigma",
            "bool",
            "report the cells' formal sigmas (independent point residuals, 2-4x too small on "
            "real surfaces; the spline field then weighs every point as one independent "
            "observation); by default each cell's covariance counts the spatial correlation "
            "of its residuals (sub-cell blocks) and the cell-wide error that the agreement of "
            "neighbouring cells shows, and the spline field weighs each cell's points by "
            "their independent share",
            "Formal sigmas only",
            default=False,
            advanced=True,
        ),
        Option(
            "stable_mask",
            "path",
            "polygon file of the MOVING area: the after epoch is first aligned on the points "
            "outside it (stable ground; the study's masked global alignment) and displacements "
            "are relative to that stable frame",
            label="Moving area (left out of the stable-ground pre-alignment)",
            role="input",
            group=_GROUP,
            qgis=None,  # QGIS gives a polygon layer (the algorithm reads it)
            pdal=None,
            metavar="FILE",
            unset_text="none",
        ),
        _opt(
            "prealign",
            "bool",
            "align the after epoch on all points first (a global pre-alignment without a mask)",
            "Pre-align on all points (no mask)",
            default=False,
            advanced=True,
        ),
        control_option(),
        output_option("table", "the cells (icp.csv)", "ICP cells (CSV)"),
        output_option("layers", "cells and vectors (icp.gpkg)", "ICP cells and vectors"),
        output_option("raster", "bands dx ... n (icp.tif)", "ICP raster"),
        output_option(
            "summary", "summary (icp.json)", "ICP summary", qgis="SUMMARY", file_filter=JSON_FILTER
        ),
        output_option(
            "plot", "figure (icp.png)", "ICP figure (PNG)", qgis="PLOT", file_filter=PNG_FILTER
        ),
    ),
    citation=CITATION,
    check=lambda opts: _check(opts),
)


def _check(opts) -> None:
    """The tiled-input refusals, and the spline options' consistency."""
    from .options import warn_option

    check_fields_tiled(opts, refused=CHECK_TILED)
    if opts.get("spline_spacing_m") is not None and opts.get("field_model") == "cells":
        warn_option(
            "{spline_spacing_m} is set but {field_model} is not spline: the knot spacing is "
            "not used; set {field_model} to spline for the spline field"
        )
    if opts.get("breaklines") and opts.get("field_model") == "cells":
        warn_option(
            "{breaklines} is given but {field_model} is cells: the cells do not use them; "
            "set {field_model} to spline for a field that may jump across them"
        )


#: options passed to ``windowed_icp`` under their own key (add new core options here)
CORE_KEYS = (
    "cell_m",
    "buffer_m",
    "min_points",
    "max_points_per_cell",
    "coarse_to_fine",
    "deform_passes",
    "cell_model",
    "spline_spacing_m",
    "spline_smoothing",
    "median_threshold",
    "median_restart",
    "backend",
)
_KEYS = ("table", "layers", "raster", "plot", "summary")


def core_kwargs(opts: Mapping[str, Any]) -> Dict[str, Any]:
    """``windowed_icp`` keywords of the options (unset ones left to the core's default; a
    tiled run takes the same, :func:`.tiled_fields.icp_tiled`)."""
    kw = {k: opts[k] for k in CORE_KEYS if opts.get(k) is not None}
    if kw.get("max_points_per_cell") == 0:  # every point
        del kw["max_points_per_cell"]
    kw["field_model"] = field_model_of(opts)
    if kw["field_model"] == "spline":
        kw["detect_breaklines"] = bool(opts.get("detect_breaklines", True))
        kw["cell_choice"] = bool(opts.get("cell_choice", True))
    regions = int(opts.get("sigma_regions") or 1)
    if opts.get("formal_sigma"):
        kw["sigma_scaling"] = "formal"
        kw["sigma_model"] = "independent"
    elif regions > 1:
        kw["sigma_scaling"] = "region"
        kw["sigma_regions"] = regions
        kw["sigma_region_by"] = opts.get("sigma_region_by") or "roughness"
    else:
        kw["sigma_scaling"] = "field"
    return kw


def field_model_of(opts: Mapping[str, Any]) -> str:
    """The field model of a run: ``field_model`` when set, else :data:`DEFAULT_FIELD_MODEL`
    (one-file and tiled inputs alike)."""
    chosen = opts.get("field_model")
    if chosen:
        return chosen
    return DEFAULT_FIELD_MODEL


def default_names(opts: Mapping[str, Any]) -> Dict[str, str]:
    return {
        "table": "icp.csv",
        "layers": "icp.gpkg",
        "raster": "icp.tif",
        "summary": "icp.json",
        "plot": "icp.png",
    }


def layer_columns(res) -> Dict[str, np.ndarray]:
    """The cells' attribute columns of every layer (GeoPackage, QGIS sinks): the result's
    columns but the grid indices, then the horizontal magnitude and azimuth."""
    cols = {k: np.asarray(v) for k, v in res.to_columns().items() if k not in ("row", "col")}
    cols.update(horizontal_columns(res.dx, res.dy))
    return cols


def cell_rings(res) -> List[np.ndarray]:
    """(5, 2) closed ring of every fitted cell (map units)."""
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


def check_lattice(after: np.ndarray, cell_m: float) -> None:
    """The cell lattice of a one-file run, before it is allocated: refused naming ``cell_m``
    when a few stray points make its extent (the others fill under 1 % of it) or when it
    would not fit in memory (issue #31)."""
    from .resources import check_grid_memory, check_sparse_grid, stray_points
    from .tiled_fields import ICP_LATTICE_BYTES

    xy = np.asarray(after)[:, :2]
    if not len(xy):
        return
    c = float(cell_m)
    lo, hi = xy.min(axis=0), xy.max(axis=0)

    def cells(a, b):
        return float(np.prod(np.floor((np.asarray(b) - np.asarray(a)) / c) + 2))

    n = cells(lo, hi)
    r_lo, r_hi, n_out = stray_points(xy)
    if n_out:
        inside = np.all((xy >= r_lo) & (xy <= r_hi), axis=1)
        k_lo, k_hi = xy[inside].min(axis=0), xy[inside].max(axis=0)
        far = xy[~inside][0]
        check_sparse_grid(
            "cell_m",
            n,
            cells(k_lo, k_hi),
            what="cell lattice",
            where=(
                f"{n_out} point(s) of the after epoch lie far from the others (e.g. at x "
                f"{far[0]:.1f}, y {far[1]:.1f}; the others span x {k_lo[0]:.1f}..{k_hi[0]:.1f}, "
                f"y {k_lo[1]:.1f}..{k_hi[1]:.1f})"
            ),
        )
    check_grid_memory("cell_m", n, bytes_per_cell=ICP_LATTICE_BYTES, what="cell lattice")


@contextlib.contextmanager
def spline_errors():
    """The spline field's size refusals from the core, as the options that make them."""
    from ..core.icp_spline import SplineCellsError, SplineSizeError

    try:
        yield
    except SplineSizeError as exc:
        raise OptionError("spline_spacing_m", str(exc)) from exc
    except SplineCellsError as exc:
        raise OptionError(
            "cell_m", f"{exc}: too few cells for a spline field; use a smaller cell"
        ) from exc


def run(
    opts: Mapping[str, Any],
    outputs: Mapping[str, Any],
    *,
    stable_mask: Optional[Callable[[Any], List[np.ndarray]]] = None,
    breaklines: Optional[Callable[[Any], Any]] = None,
    progress: Optional[Progress] = None,
) -> JobResult:
    """Read both epochs, run windowed ICP, compare with control points and write.

    Parameters
    ----------
    opts
        :data:`SPEC`'s options, parsed.
    outputs
        ``{"out": folder}`` or ``{output key: path or None}`` (``table``, ``layers``,
        ``raster``, ``summary``, ``plot``).
    stable_mask
        ``f(crs) -> [ring (K, 2)]``: the moving-area polygons in the clouds' CRS (QGIS gives
        its layer this way); default: read ``opts["stable_mask"]``.
    breaklines
        ``f(crs) -> [polyline (M, 2)]``: the breaklines in the clouds' CRS (QGIS gives its
        line layer this way); default: read ``opts["breaklines"]``.

    Returns
    -------
    JobResult
        ``data``: ``{"result": WindowedICPResult, "columns": layer_columns, "rings":
        cell_rings, "crs": pyproj CRS or None}``.
    """
    from .tiled import is_tiled

    tiled = is_tiled(opts, "before", "after")
    if tiled and stable_mask is not None:  # QGIS gives the moving area as a layer
        raise tiled_refusal("stable_mask", CHECK_TILED["stable_mask"])
    plan = OutputPlan.for_outputs(
        inputs=pair_inputs(opts, "before", "after", "control", "stable_mask", "breaklines"),
        outputs=outputs,
        default_names=default_names(opts),
    )
    plan.check()
    with plan:
        control = read_control(opts.get("control"))
        if tiled:  # blocks of cells (app/tiled_fields.py)
            from .tiled_fields import icp_for_job

            with spline_errors():
                res, crs = icp_for_job(
                    opts, core_kwargs(opts), progress=progress,
                    breaklines_of=lambda crs: _breaklines_of(opts, breaklines, crs),
                )  # fmt: skip
            before = None
        else:
            before, after, crs = read_pair(opts)
            exclude = None
            if stable_mask is None and opts.get("stable_mask"):
                stable_mask = _mask_reader(opts["stable_mask"])
            if stable_mask is not None:
                exclude = stable_mask(crs)
            lines = _breaklines_of(opts, breaklines, crs)
            res = compute(before, after, opts, lines=lines, exclude=exclude, progress=progress)
        comparison = None
        if control is not None:
            field = field_of_columns(
                res.x,
                res.y,
                res.dx,
                res.dy,
                res.dz,
                spacing_m=res.cell_m,
                key="control",
                what="the ICP field",
            )
            comparison = compare_control(control, field)
        summary = {
            "command": "icp",
            "before": str(opts["before"]),
            "after": str(opts["after"]),
            "buffer_m": opts.get("buffer_m"),
            "min_points": opts["min_points"],
            "coarse_to_fine": opts["coarse_to_fine"],
            **icp_summary(res),
            "breaklines": breaklines_summary(res, opts.get("breaklines")),
            "control": comparison,
            "crs": None if crs is None else crs.to_wkt(),
            "slipmap_version": __version__,
        }
        columns = layer_columns(res)
        rings = cell_rings(res)
        _write(plan, res, columns, rings, crs, before)
        summary["files"] = plan.written_names(_KEYS[:-1])
        if plan.wants("summary"):
            plan.file("summary").write_text(json_text(summary), encoding="utf-8")
    lines = [
        f"windowed ICP: {len(res)} cells of {res.cell_m:g} m ({sum(res.skipped.values())} "
        f"skipped), median horizontal {summary['horizontal_m'].get('median', float('nan')):.4f}"
        f" m, median sigma {summary['sigma_horizontal_m'].get('median', float('nan')):.4f} m"
    ]
    if comparison is not None:
        lines.append(
            f"control points: {comparison['n_compared']} of {comparison['n_rows']} compared, "
            f"horizontal RMSE {comparison['rmse_horizontal_m']:.4f} m"
        )
    files = {k: plan.final(k) for k in _KEYS if plan.wants(k) and plan.final(k).exists()}
    data = {"result": res, "columns": columns, "rings": rings, "crs": crs}
    return JobResult(summary, lines, files, data=data)


def compute(before, after, opts, *, lines=None, exclude=None, progress=None):
    """Windowed ICP of one epoch pair in memory (the CLI's, QGIS's and PDAL's one-file run).

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The epochs' points, metres, one CRS.
    opts
        :data:`SPEC`'s options, parsed.
    lines : Breaklines, optional
        Given breaklines (the spline field jumps across them).
    exclude : list of (K, 2) float64, optional
        Moving-area polygons left out of the pre-alignment.

    Returns
    -------
    WindowedICPResult
        With too few cells for the default spline field, the cells' field and a warning
        naming ``cell_m``.
    """
    from ..core.icp import windowed_icp

    check_overlap(before, after)
    check_lattice(after, opts["cell_m"])
    kw = core_kwargs(opts)
    if kw["field_model"] == "spline":
        kw["breaklines"] = lines
    run_kw = dict(
        prealign=bool(exclude) or bool(opts.get("prealign")),
        exclude_polygons=exclude,
        progress=progress,
    )
    try:
        with spline_errors():
            return windowed_icp(before, after, **run_kw, **kw)
    except OptionError as exc:
        if opts.get("field_model") or exc.key != "cell_m":
            raise
        from .options import warn_option

        warn_option(
            "too few cells for the default spline field (%s): the field is the cells'; use a "
            "smaller {cell_m}, or set {field_model} to cells to silence this",
            str(exc),
        )
        kw.update(field_model="cells")
        for k in ("breaklines", "detect_breaklines", "cell_choice"):
            kw.pop(k, None)
        return windowed_icp(before, after, **run_kw, **kw)


def _breaklines_of(opts, reader, crs):
    """The run's breaklines in the clouds' CRS: QGIS's layer (``reader``) or the file of
    ``opts["breaklines"]``; None when neither is given."""
    if reader is not None:
        from ..core.breaklines import from_sequence

        return from_sequence(reader(crs))
    return read_breaklines(opts.get("breaklines"), crs)


def breaklines_summary(res, path=None) -> Dict[str, Any]:
    """``icp.json``'s ``breaklines``: where they came from (``given``, ``detected``,
    ``none``), how many lines, their length (m), the file given and each line's vertices."""
    lines = getattr(res, "breaklines", None)
    src = getattr(res, "breaklines_source", "none")
    if lines is None or lines.empty:
        return {"source": src, "count": 0, "length_m": 0.0, "file": path}
    return {
        "source": src,
        "count": len(lines),
        "length_m": round(lines.length_m(), 3),
        "file": None if path is None else str(path),
        "lines": [np.round(p, 3).tolist() for p in lines.parts],
    }


def breaklines_columns(res) -> Dict[str, np.ndarray]:
    """Attribute columns of the ``breaklines`` layer: ``source`` (given/detected) and
    ``length_m`` of each line."""
    parts = res.breaklines.parts
    return {
        "source": np.array([res.breaklines_source] * len(parts), dtype=object),
        "length_m": np.array([float(np.hypot(*np.diff(p, axis=0).T).sum()) for p in parts]),
    }


def _mask_reader(path) -> Callable[[Any], List[np.ndarray]]:
    def read(crs) -> List[np.ndarray]:
        from ..core.io.vector import read_polygons

        try:
            rings = read_polygons(path, target_crs=crs)
        except SlipMapError as exc:
            raise OptionError(
                "stable_mask", f"{exc}; give a polygon file of the moving area"
            ) from exc
        if not rings:
            raise OptionError("stable_mask", f"{path} has no polygon; give the moving area")
        return rings

    return read


def _write(plan: OutputPlan, res, columns, rings, crs, before) -> None:
    if plan.wants("table"):
        from ..core.io.table import write_csv_columns

        write_csv_columns(plan.file("table"), res.to_columns())
    if plan.wants("layers"):
        from ..core.io.vector import VectorLayer, write_gpkg_layers

        vectors = [
            np.array([[x, y], [x + dx, y + dy]])
            for x, y, dx, dy in zip(res.x, res.y, res.dx, res.dy)
        ]
        layers = [
            VectorLayer("cells", "Polygon", [r[:-1] for r in rings], columns),
            VectorLayer("vectors", "LineString", vectors, columns),
        ]
        if getattr(res, "breaklines", None) is not None and not res.breaklines.empty:
            layers.append(
                VectorLayer(
                    "breaklines", "LineString", list(res.breaklines.parts), breaklines_columns(res)
                )
            )
        write_gpkg_layers(plan.file("layers"), layers, crs=crs, styles=gpkg_styles("icp", layers))
    if plan.wants("raster"):
        write_tif(
            plan.file("raster"),
            np.stack([res.to_grid(b) for b in BANDS]),
            origin_xy=res.origin_xy,
            pixel_m=res.cell_m,
            crs=crs,
            names=BANDS,
            metadata={"method": "windowed point-to-plane ICP", "cell_m": f"{res.cell_m:g}"},
        )
        write_raster_style(plan, "icp", "raster", res.to_grid("dz"))
    report = figures() if plan.wants("plot") else None
    if report is not None:
        from ..core.dem import common_grid, grid_elevation

        background, extent = None, None
        if before is not None:  # tiled inputs: the cells alone (no epoch in memory)
            cell = max(res.cell_m / 20.0, 0.05)
            grid = common_grid(before, cell_m=cell, overlap="union")
            background = report.hillshade(grid_elevation(before, grid=grid), cell_m=cell)
            extent = (grid.x_min, grid.x_max, grid.y_min, grid.y_max)
        report.plot_vector_field(
            plan.file("plot"),
            x=res.x,
            y=res.y,
            dx=res.dx,
            dy=res.dy,
            colour=res.dz,
            background=background,
            extent=extent,
            title=f"windowed ICP, {res.cell_m:g} m cells",
        )
