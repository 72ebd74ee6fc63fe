"""Job ``roughness``: ODR roughness on a regular 3D grid, with the OLS comparison (Pollyea and
Fairley 2011).

The options are declared once in :data:`SPEC`; :func:`compute` (the grids of one cloud) and
:func:`per_point` (each point's cell value) are the computation on arrays, used by PDAL;
:func:`run` reads the cloud (or tiles), computes and writes, per cell size, the cells' CSV,
the map-plane GeoTIFF, the semivariograms and the figures, plus ``summary.json`` and the
optional per-point copy, all through one :class:`~.outputs.OutputPlan`: every check runs
before anything is written, and a failed run leaves the output folder as it was.
"""

from __future__ import annotations

import io
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple

import numpy as np

from .._version import __version__
from .inputs import cloud_option, crs_option, out_dir_option, read_cloud
from .job import NO_MATPLOTLIB, JobResult, Progress, matplotlib_available, scaled
from .options import JobSpec, Option, OptionError
from .outputs import OutputPlan
from .resources import check_grid_memory
from .summaries import json_text
from .tiled import check_scale, input_files, is_tiled, scale_options

log = logging.getLogger("slipmap.app")

CITATION = (
    "Pollyea and Fairley (2011), Estimating surface roughness of terrestrial laser scan data "
    "using orthogonal distance regression, Geology 39(7), Eq. 4"
)
#: the cells' CSV: one header, one writer (full precision) for every face
CSV_HEADER = "ix,iy,iz,x,y,z,n,theta_odr,theta_ols,e_ols,degenerate"
_CSV_FORMAT = ["%d", "%d", "%d", "%.6f", "%.6f", "%.6f", "%d", "%.17g", "%.17g", "%.17g", "%d"]
BANDS = (
    "theta_odr_m",
    "theta_ols_m",
    "e_ols_m",
    "theta_odr_normalised",
    "theta_ols_normalised",
    "binary_odr",
    "binary_ols",
)
#: working memory per raster pixel: 5 float64 values + count + 7 float64 bands + the float32
#: copy written + temporaries of the binary transform, rounded up
RASTER_BYTES_PER_PIXEL = 200.0
#: file names of one cell size's outputs in the output folder ({label}: the cell size)
NAMES = {
    "csv": "roughness_{label}.csv",
    "geotiff": "roughness_{label}.tif",
    "semivariogram_csv": "semivariogram_{label}.csv",
    "binary_map_png": "roughness_{label}_binary.png",
    "map_png": "roughness_{label}_map.png",
    "histogram_png": "roughness_{label}_hist.png",
}
_FIGURES = ("binary_map_png", "map_png", "histogram_png")
LAS_SUFFIXES = (".las", ".laz")


def _check(opts: Mapping[str, Any]) -> None:
    check_scale(opts)
    pts = opts.get("points_out")
    if pts is not None:
        if Path(str(pts)).suffix.lower() not in LAS_SUFFIXES:
            raise OptionError(
                "points_out",
                f"{str(pts)!r} does not end in .las or .laz; the per-point copy is a LAS/LAZ "
                "file: give a name ending in .las (or .laz)",
            )
        if opts.get("input") is not None and is_tiled(opts, "input"):
            raise OptionError(
                "points_out",
                "needs the points in one place; it is not available for tiled inputs or Dask "
                "runs: leave it out, or give one file as {input}",
                also=("input",),
            )


SPEC = JobSpec(
    name="roughness",
    title="Surface roughness",
    description=(
        "Roughness of a point cloud on a regular 3D grid: in every cell an orthogonal (ODR) "
        "plane is fitted and theta_ODR is the population standard deviation of the absolute "
        "orthogonal point-to-plane distances; the OLS plane along one axis is the comparison."
    ),
    options=(
        cloud_option(
            "input",
            "LAS/LAZ point cloud in a projected CRS (metres); or tiles: a folder, a glob "
            "(quoted) or files separated by commas (the cells are the whole cloud's)",
            "Input point cloud",
        ),
        out_dir_option(),
        crs_option(),
        Option(
            "cell_sizes_m",
            "floats",
            "grid cell edge, metres; several values for several grids (the study: 1, 0.5, "
            "0.25, 0.125); the per-point output uses the first",
            label="Cell size (m)",
            default=(0.5,),
            minimum=0,
            exclusive=True,
            nargs="+",
            cli="--cell",
            qgis=None,  # one number in QGIS (its outputs are one raster and one table)
            pdal="cell",
            metavar="M",
        ),
        Option(
            "min_points",
            "int",
            "cells with fewer points are skipped and counted (NaN per point); at least 3",
            label="Smallest cell (points)",
            default=10,
            minimum=3,
            metavar="N",
        ),
        Option(
            "signed",
            "bool",
            "roughness = std of signed distances (RMS) instead of the study's std of absolute "
            "distances (Eq. 4)",
            label="Signed distances (RMS) instead of absolute (Eq. 4)",
            default=False,
            advanced=True,
        ),
        Option(
            "ols_axis",
            "choice",
            "dependent axis of the OLS comparison plane; auto = the axis closest to the normal "
            "of the cloud's principal plane (the study: y, exposure-normal)",
            label="OLS dependent axis",
            default="auto",
            choices=("auto", "x", "y", "z"),
            advanced=True,
        ),
        Option(
            "map_plane",
            "choice",
            "plane of the maps: xy (map view, keeps the CRS), xz, yz, principal (local frame on "
            "the cloud's principal plane); auto = principal, snapped to a coordinate plane "
            "within 15 degrees",
            label="Map plane of the raster",
            default="auto",
            choices=("auto", "xy", "xz", "yz", "principal"),
            advanced=True,
            pdal=None,
        ),
        Option(
            "cutoff",
            "float",
            "binary-map cutoff of normalised roughness, 0-1",
            label="Binary-map cutoff (0-1)",
            default=0.05,
            minimum=0,
            maximum=1,
            advanced=True,
            pdal=None,
            metavar="F",
        ),
        Option(
            "method",
            "choice",
            "roughness written per point: theta_ODR (Eq. 4) or theta_OLS",
            label="Roughness per point",
            default="odr",
            choices=("odr", "ols"),
            cli="--points-method",
            qgis=None,
        ),
        Option(
            "points_out",
            "path",
            "also write the cloud with a Roughness dimension (the cell's value at the first "
            "cell size; NaN in skipped or degenerate cells)",
            label="Point cloud with Roughness",
            role="output",
            qgis=None,
            pdal=None,
            metavar="FILE.las",
            unset_text="none",
            file_filter="LAS (*.las);;LAZ (*.laz)",
        ),
        Option(
            "geotiff",
            "path",
            "GeoTIFF of one cell size on the map plane (bands " + ", ".join(BANDS) + ")",
            label="Roughness (GeoTIFF)",
            role="output",
            cli=None,  # the CLI writes roughness_<cell>.tif into --out
            qgis="OUTPUT",
            pdal=None,
            file_filter="GeoTIFF (*.tif)",
        ),
        Option(
            "csv",
            "path",
            "one row per evaluated cell: " + CSV_HEADER,
            label="Roughness per cell",
            role="output",
            cli=None,
            pdal=None,
            file_filter="CSV (*.csv)",
        ),
        Option(
            "summary",
            "path",
            "summary (JSON): options, map plane, Table 1 per cell size",
            label="Roughness summary",
            role="output",
            cli=None,
            pdal=None,
            file_filter="JSON (*.json)",
        ),
        Option(
            "figures",
            "bool",
            "write the PNG figures (needs matplotlib)",
            label="Figures",
            default=True,
            qgis=None,
            pdal=None,
        ),
        *scale_options(),
    ),
    check=_check,
    citation=CITATION,
)


# --------------------------------------------------------------------------- on arrays


@dataclass(frozen=True)
class Grids:
    """The grids of one cloud: one :class:`~slipmap.core.roughness.RoughnessGrid` per cell
    size, the principal frame, the OLS axis used and the map plane."""

    grids: Tuple[Any, ...]
    frame: Any
    ols_axis: str
    plane: Any


def _check_cells(cells: Sequence[float], lo: np.ndarray, hi: np.ndarray) -> None:
    extent = float(np.max(hi - lo))
    for c in cells:
        if c > extent:
            raise OptionError(
                "cell_sizes_m",
                f"{c:g} m is larger than the extent of the cloud ({extent:.6g} m along its "
                "longest axis); choose a smaller cell size",
            )


def check_raster_memory(cells: Sequence[float], uv: np.ndarray) -> None:
    """Refuse cell sizes whose map raster would not fit in memory (before allocating it).

    ``uv`` ``(K, 2)``: points (or cell centres) on the map plane, metres.
    """
    if uv.shape[0] == 0:
        return
    span = uv.max(axis=0) - uv.min(axis=0)
    for c in cells:
        n_pixels = float(np.prod(np.floor(span / c) + 2))
        check_grid_memory(
            "cell_sizes_m",
            n_pixels,
            bytes_per_cell=RASTER_BYTES_PER_PIXEL,
            what=f"roughness raster of {c:g} m",
        )


def compute(
    points: np.ndarray,
    opts: Mapping[str, Any],
    *,
    rasters: bool = False,
    progress: Optional[Progress] = None,
) -> Grids:
    """The roughness grids of ``points`` ``(N, 3)`` float64 (metres) under the job's options.

    With ``rasters`` the map rasters' memory is checked first (:func:`check_raster_memory`).

    Raises
    ------
    OptionError
        A cell size larger than the cloud, or rasters that would not fit in memory.
    """
    from ..core import roughness as rg

    cells = tuple(opts["cell_sizes_m"])
    _check_cells(cells, points.min(axis=0), points.max(axis=0))
    frame = rg.principal_frame(points)
    axis = rg.resolve_ols_axis(frame, opts.get("ols_axis") or "auto")
    plane = rg.choose_map_plane(frame, opts.get("map_plane") or "auto")
    if rasters:
        check_raster_memory(cells, plane.project(points))
    grids = rg.grid_roughness_multi(
        points,
        cell_sizes_m=cells,
        min_points=opts["min_points"],
        ols_axis=axis,
        signed=bool(opts.get("signed")),
        progress=progress,
    )
    return Grids(tuple(grids), frame, axis, plane)


def per_point(points: np.ndarray, grid, method: str = "odr") -> np.ndarray:
    """``(N,)`` each point's cell value (``theta_odr`` or ``theta_ols``, metres; NaN outside
    evaluated cells)."""
    from ..core.roughness import roughness_per_point

    return roughness_per_point(points, grid, value="theta_" + method)


def csv_text(grid) -> str:
    """The cells' CSV (:data:`CSV_HEADER`; values at full precision)."""
    centre = grid.centre_m
    cols = [
        grid.index[:, 0],
        grid.index[:, 1],
        grid.index[:, 2],
        centre[:, 0],
        centre[:, 1],
        centre[:, 2],
        grid.n_points,
        grid.theta_odr,
        grid.theta_ols,
        grid.e_ols,
        grid.degenerate.astype(np.int64),
    ]
    table = np.empty((len(grid), len(cols)), dtype=object)
    for j, col in enumerate(cols):
        table[:, j] = col
    buf = io.StringIO()
    buf.write(CSV_HEADER + "\n")
    if len(grid):
        np.savetxt(buf, table, fmt=_CSV_FORMAT, delimiter=",")
    return buf.getvalue()


def cell_label(cell_m: float) -> str:
    return f"{cell_m:g}"


# --------------------------------------------------------------------------- outputs


class _Sink:
    """Where each output goes: named files in the output folder (CLI) or the face's own
    paths, one cell size (QGIS); ``None`` when the output is not wanted."""

    def __init__(self, plan: OutputPlan, files: Optional[Mapping[str, Any]], labels, figures):
        self.plan, self.files = plan, files
        if files is None:
            for label in labels:
                for kind, name in NAMES.items():
                    if figures or kind not in _FIGURES:
                        plan.expect(name.format(label=label))
            plan.expect("summary.json", *(["semivariograms.png"] if figures else []))
            for label in labels:  # each GeoTIFF's style, beside it (app/styles.py)
                plan.expect(_style_name(label))

    def path(self, kind: str, label: str = "") -> Optional[Path]:
        if self.files is None:
            name = {"summary": "summary.json", "semivariograms_png": "semivariograms.png"}.get(
                kind
            ) or NAMES[kind].format(label=label)
            return self.plan.path(name)
        return self.plan.path(kind) if self.files.get(kind) else None

    def style_path(self, label: str = "") -> Optional[Path]:
        """Where the GeoTIFF's style (the ``.qml`` QGIS reads beside it) is staged."""
        if self.files is None:
            return self.plan.path(_style_name(label))
        return self.plan.beside("geotiff", ".qml") if self.files.get("geotiff") else None

    def name(self, kind: str, label: str = "") -> Optional[str]:
        if self.files is None:
            return NAMES[kind].format(label=label)
        return Path(str(self.files[kind])).name if self.files.get(kind) else None


def _style_name(label: str) -> str:
    """The name of the style QGIS reads beside the GeoTIFF of cell size ``label``."""
    from ..core.io.raster import style_sidecar

    return style_sidecar(NAMES["geotiff"].format(label=label)).name


def _write_style(sink: _Sink, label: str, geotiff: Path, theta_odr: np.ndarray) -> None:
    """The roughness GeoTIFF's style beside it (the one :data:`.styles.OUTPUT_STYLES`
    declares: band 1, theta_ODR, viridis from 0 to the roughest cell), so it opens as a map,
    not a 7-band RGB picture, wherever it is opened."""
    from ..core.io.raster import write_raster_style
    from .styles import OUTPUT_STYLES, raster_qml

    target = sink.style_path(label)
    if target is None:
        return
    style = OUTPUT_STYLES["roughness"]["geotiff"]
    written = write_raster_style(geotiff, raster_qml(style, theta_odr))
    assert written == target, (written, target)  # staged beside the staged GeoTIFF


def _local_frame_wkt(plane) -> str:
    return (
        f'LOCAL_CS["SlipMap {plane.name} map plane (u, v in the input CRS units)",'
        'LOCAL_DATUM["SlipMap map plane",0],UNIT["metre",1],'
        'AXIS["u",EAST],AXIS["v",NORTH]]'
    )


def _fraction(values: np.ndarray) -> Optional[float]:
    from ..core import roughness as rg

    return rg._json_float(np.nanmean(values)) if np.isfinite(values).any() else None


def _one_size(grid, plane, crs, opts, sink: _Sink, figures: bool) -> Tuple[dict, Any]:
    """Write the CSV, GeoTIFF, semivariogram CSV and figures of one cell size; returns its
    record (Table 1 + files) and its semivariograms."""
    from ..core import roughness as rg
    from ..core.errors import DependencyError
    from ..core.io.raster import write_geotiff

    label = cell_label(grid.cell_size_m)
    cutoff = opts["cutoff"]
    record = rg.summarize_roughness(grid).to_dict()
    files: Dict[str, Optional[str]] = {}
    path = sink.path("csv", label)
    if path is not None:
        path.write_text(csv_text(grid), encoding="utf-8")
        files["csv"] = sink.name("csv", label)
    norm_odr = rg.normalise_range(grid.theta_odr)
    norm_ols = rg.normalise_range(grid.theta_ols)
    _, hist_odr = rg.roughness_histogram(norm_odr)
    _, hist_ols = rg.roughness_histogram(norm_ols)
    record["fraction_first_histogram_bin"] = {
        "odr": float(hist_odr[0]) if len(grid) else None,
        "ols": float(hist_ols[0]) if len(grid) else None,
    }
    record["fraction_cells_at_or_above_cutoff"] = {
        "odr": _fraction(rg.binary_transform(norm_odr, cutoff=cutoff)),
        "ols": _fraction(rg.binary_transform(norm_ols, cutoff=cutoff)),
    }
    record["files"] = files
    if len(grid) == 0:
        log.warning("cell %s m: no cell has %d or more points", label, grid.min_points)
        return record, None

    values = np.column_stack([grid.theta_odr, grid.theta_ols, grid.e_ols, norm_odr, norm_ols])
    raster = rg.rasterize_cells(grid.centre_m, values, plane, pixel_size_m=grid.cell_size_m)
    bands = np.empty((len(BANDS),) + raster.count.shape)
    bands[:5] = raster.values
    bands[5] = rg.binary_transform(raster.values[3], cutoff=cutoff)
    bands[6] = rg.binary_transform(raster.values[4], cutoff=cutoff)
    if plane.georeferenced:
        crs_wkt = crs.to_wkt() if crs is not None else None
    else:
        crs_wkt = _local_frame_wkt(plane)
    meta = {
        "SLIPMAP_MAP_PLANE": plane.name,
        "SLIPMAP_PLANE_ORIGIN": " ".join(f"{v:.6f}" for v in plane.origin_m),
        "SLIPMAP_U_AXIS": " ".join(f"{v:.9f}" for v in plane.u_axis),
        "SLIPMAP_V_AXIS": " ".join(f"{v:.9f}" for v in plane.v_axis),
        "SLIPMAP_CELL_SIZE_M": f"{grid.cell_size_m:g}",
        "SLIPMAP_CUTOFF": f"{cutoff:g}",
        "SLIPMAP_SIGNED": str(bool(opts.get("signed"))),
        "SLIPMAP_OLS_AXIS": grid.ols_axis,
    }
    path = sink.path("geotiff", label)
    if path is not None:
        try:
            write_geotiff(
                path,
                bands.astype(np.float32),
                origin_xy=raster.origin_uv_m,
                pixel_size_m=raster.pixel_size_m,
                crs_wkt=crs_wkt,
                band_names=BANDS,
                metadata=meta,
            )
            files["geotiff"] = sink.name("geotiff", label)
            _write_style(sink, label, path, bands[0])
        except DependencyError as exc:
            log.warning("no GeoTIFF written: %s", exc)
            files["geotiff"] = None

    variograms = {}
    for name, band in (("theta_odr", 0), ("theta_ols", 1), ("e_ols", 2)):
        variograms[name] = rg.semivariogram_raster(
            raster.values[band], pixel_size_m=raster.pixel_size_m
        )
    path = sink.path("semivariogram_csv", label)
    if path is not None:
        lines = [
            "lag_m,n_pairs_odr,gamma_odr,gamma_odr_normalised,n_pairs_ols,gamma_ols,"
            "gamma_ols_normalised,n_pairs_e_ols,gamma_e_ols,gamma_e_ols_normalised"
        ]
        ref = variograms["theta_odr"]
        for k in range(ref.gamma.size):
            cells = [f"{ref.lag_m[k]:.6g}"]
            for sv in variograms.values():
                cells += [f"{sv.n_pairs[k]:d}", f"{sv.gamma[k]:.17g}", f"{sv.normalised[k]:.17g}"]
            lines.append(",".join(cells))
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        files["semivariogram_csv"] = sink.name("semivariogram_csv", label)
    record["semivariogram_variance_m2"] = {
        k: rg._json_float(v.variance) for k, v in variograms.items()
    }

    if figures:
        from . import report

        title = f"{label} m grid ({plane.name} map plane)"
        report.plot_roughness_map(
            sink.path("binary_map_png", label),
            {"A: OLS": bands[4], "B: ODR": bands[3]},
            extent=raster.extent,
            cutoff=cutoff,
            axis_labels=plane.axis_labels,
            title=f"Normalised roughness, binary transform at {cutoff:g}: {title}",
        )
        report.plot_roughness_map(
            sink.path("map_png", label),
            {"theta ODR": bands[0], "theta OLS": bands[1]},
            extent=raster.extent,
            axis_labels=plane.axis_labels,
            title=f"Roughness: {title}",
        )
        report.plot_roughness_histograms(
            sink.path("histogram_png", label),
            {"OLS": norm_ols, "ODR": norm_odr},
            title=f"Normalised roughness: {title}",
        )
        for kind in _FIGURES:
            files[kind] = sink.name(kind, label)
    return record, variograms


def run(
    opts: Mapping[str, Any], outputs: Mapping[str, Any], *, progress: Optional[Progress] = None
) -> JobResult:
    """Read, grid, write.

    Parameters
    ----------
    opts
        :data:`SPEC`'s options, parsed (:meth:`JobSpec.parse`).
    outputs
        ``{"out": folder, "points_out": path or None}`` (every cell size's files under
        :data:`NAMES` and ``summary.json``), or the face's own paths for one cell size:
        ``{"geotiff": path, "csv": path, "semivariogram_csv": path or None, "summary": path
        or None, "points_out": path or None}``.
    """
    from ..core import roughness as rg

    _check(opts)
    cells = tuple(opts["cell_sizes_m"])
    outputs = dict(outputs)
    points_out = outputs.pop("points_out", None)
    folder = outputs.pop("out", None)
    if folder is None and len(cells) != 1:
        raise OptionError("cell_sizes_m", "give one cell size when the outputs are named files")
    inputs = {"input": input_files(opts, "input") if is_tiled(opts, "input") else opts.get("input")}
    files = {"points_out": points_out}
    if folder is None:
        files.update(outputs)
    plan = OutputPlan(
        inputs=inputs, out_dir=("out", folder) if folder is not None else None, files=files
    )
    want_figures = bool(opts.get("figures")) and folder is not None
    figures = want_figures and matplotlib_available()
    sink = _Sink(plan, None if folder is not None else outputs, map(cell_label, cells), figures)
    plan.check()
    tiled = is_tiled(opts, "input")
    t0 = time.perf_counter()
    with plan:
        cloud = None
        if tiled:
            from .tiled import roughness_for_job

            tr = roughness_for_job(
                opts,
                cell_sizes_m=cells,
                min_points=opts["min_points"],
                ols_axis=opts["ols_axis"],
                signed=bool(opts["signed"]),
                progress=scaled(progress, 0.0, 0.7),
            )
            plane = rg.choose_map_plane(tr.frame, opts["map_plane"])
            centres = np.vstack([g.centre_m for g in tr.grids])
            check_raster_memory(cells, plane.project(centres))
            res = Grids(tuple(tr.grids), tr.frame, tr.ols_axis, plane)
            crs, n_points, source = tr.crs, tr.n_points, ",".join(tr.paths)
            log.info("%d tile file(s), %s", len(tr.paths), tr.engine)
        else:
            cloud = read_cloud(opts["input"], key="input", crs=opts.get("crs"))
            res = compute(cloud.xyz, opts, rasters=True, progress=scaled(progress, 0.0, 0.7))
            crs, n_points = cloud.crs, len(cloud)
            source = str(cloud.source) if cloud.source else None
        if all(len(g) == 0 for g in res.grids):
            raise OptionError(
                "min_points",
                f"no cell of {', '.join(map(cell_label, cells))} m has {opts['min_points']} or "
                "more points; choose a larger cell size or a smaller minimum",
                also=("cell_sizes_m",),
            )
        plane = res.plane
        angle = math.degrees(math.acos(min(1.0, abs(float(res.frame.normal @ plane.normal)))))
        log.info(
            "OLS axis %s; map plane %s (%.1f deg from the cloud's principal plane)",
            res.ols_axis,
            plane.name,
            angle,
        )
        if want_figures and not figures:
            log.warning(NO_MATPLOTLIB)  # once the run is past every check: only writing is left
        records, panels = [], []
        for k, grid in enumerate(res.grids):
            rec, variograms = _one_size(grid, plane, crs, opts, sink, figures)
            records.append(rec)
            _log_size(grid)
            if variograms:
                panels.append(
                    (
                        f"{cell_label(grid.cell_size_m)} m grid",
                        {
                            name: (variograms[key].lag_m, variograms[key].normalised)
                            for name, key in (
                                ("ODR", "theta_odr"),
                                ("OLS", "theta_ols"),
                                ("E_OLS", "e_ols"),
                            )
                        },
                    )
                )
            if progress is not None:
                progress(0.7 + 0.25 * (k + 1) / len(res.grids), f"cell {grid.cell_size_m:g} m")
        semivariogram_png = None
        if panels and figures:
            from . import report

            report.plot_semivariograms(
                sink.path("semivariograms_png"),
                panels,
                title="Normalised experimental semivariograms of roughness",
            )
            semivariogram_png = "semivariograms.png"
        if points_out is not None:
            from ..core.io.las import write_las

            values = per_point(cloud.xyz, res.grids[0], opts["method"])
            write_las(
                plan.path("points_out"),
                cloud,
                extra_dims={"Roughness": values},
                inputs=[cloud.source],
            )
        summary = {
            "input": source,
            "crs": crs.to_wkt() if crs is not None else None,
            "n_points": int(n_points),
            "method": "Pollyea & Fairley (2011): ODR plane per grid cell; theta = population "
            "std "
            + (
                "of signed distances"
                if opts["signed"]
                else "of absolute orthogonal distances (Eq. 4)"
            ),
            "options": {
                "cell_sizes_m": [float(c) for c in cells],
                "min_points": opts["min_points"],
                "signed": bool(opts["signed"]),
                "ols_axis": res.ols_axis,
                "cutoff": opts["cutoff"],
                "map_plane": opts["map_plane"],
            },
            "map_plane": plane.to_dict(),
            "principal_frame": {
                "centroid_m": [float(v) for v in res.frame.centroid_m],
                "axes": [[float(v) for v in row] for row in res.frame.axes],
                "eigenvalues_m2": [float(v) for v in res.frame.eigenvalues_m2],
            },
            "cell_sizes": records,
            "semivariograms_png": semivariogram_png,
            "points_out": str(points_out) if points_out else None,
            "points_out_cell_m": float(res.grids[0].cell_size_m) if points_out else None,
            "points_out_value": f"theta_{opts['method']}" if points_out else None,
            "slipmap_version": __version__,
        }
        path = sink.path("summary")
        if path is not None:
            summary["runtime_s"] = round(time.perf_counter() - t0, 4)
            path.write_text(json_text(summary), encoding="utf-8")
        if progress is not None:
            progress(1.0, "written")
    written = {str(p.name): p for p in plan.written}
    lines = [
        f"cell {cell_label(g.cell_size_m)} m: {len(g)} cells, {g.n_cells_skipped} skipped "
        f"(< {g.min_points} points)"
        for g in res.grids
    ]
    return JobResult(summary, lines, written, data=res)


def _log_size(grid) -> None:
    from ..core import roughness as rg

    s = rg.summarize_roughness(grid)
    log.info(
        "cell %s m: %d cells (%.0f points/cell; %d skipped < %d points, %d degenerate)",
        cell_label(grid.cell_size_m),
        s.n_cells,
        s.mean_points_per_cell,
        s.n_cells_skipped,
        grid.min_points,
        s.n_degenerate,
    )
    for name, st in (("ODR", s.odr), ("OLS", s.ols)):
        log.info(
            "  %s  min %.4g  max %.4g  mean %.4g  var %.3g  std %.4g m",
            name,
            st.minimum,
            st.maximum,
            st.mean,
            st.variance,
            st.std,
        )
