"""Shared pieces of the displacement-field jobs (``piv``, ``icp``, ``dem-diff``, ``strain``,
``synth-lobe``): the epoch-pair options and reading, the control-point comparison, GeoTIFF
writing of fields and the figures module.

Each job (:mod:`.piv`, :mod:`.icp`, :mod:`.dem_diff`, :mod:`.strain`, :mod:`.synthetic`)
declares its options once and writes through an :class:`~.outputs.OutputPlan`; what they
share lives here so that no face carries a copy.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

from ..core.errors import SlipMapError
from .inputs import (
    cloud_option,
    crs_option,
    out_dir_option,
    read_epoch_pair,
    select_points,
    selection_options,
)
from .job import plotting
from .options import Option, OptionError

log = logging.getLogger("slipmap.app")

ARYAL = (
    "Aryal et al., Determining ground displacement fields of small spatial extent using "
    "terrestrial laser scanner data: a comparison of 3D methods applied to landslide "
    "monitoring (Aryal 2014, Landslide deformation character inferred from terrestrial laser "
    "scanner data, PhD dissertation, chapter 3)"
)
CSV_FILTER = "CSV (*.csv *.txt)"
TIF_FILTER = "GeoTIFF (*.tif *.tiff)"
JSON_FILTER = "JSON (*.json)"
PNG_FILTER = "PNG (*.png)"


# --------------------------------------------------------------------------- option rows


TILES_HELP = (
    "; or tiles: a folder, a glob (quoted) or files separated by commas, read block by block "
    "(also on Dask: {workers}, {scheduler})"
)


def pair_options(*, accepts_tiles: bool = False) -> Tuple[Option, ...]:
    """Both epochs (positionals ``BEFORE AFTER`` on the CLI), ``--out``, ``--crs`` and the
    class selection (every point by default: fields use the ground); with ``accepts_tiles``
    the epochs may be tile collections and the Dask options follow."""
    from .tiled import scale_options

    tiles = TILES_HELP if accepts_tiles else ""
    return (
        cloud_option(
            "before",
            f"first-epoch LAS/LAZ point cloud in a projected CRS (metres){tiles}",
            "Before epoch",
        ),
        cloud_option(
            "after",
            "second-epoch LAS/LAZ point cloud; reprojected to the first epoch's CRS when "
            f"they differ (tiles are not reprojected){tiles}",
            "After epoch",
        ),
        out_dir_option(),
        crs_option(
            "CRS of both epochs when the files lack one or declare a wrong one (e.g. "
            "EPSG:32612): it replaces the files' CRS (nothing is reprojected) and the outputs "
            "carry it"
        ),
        *selection_options(ground_default=False),
        *(scale_options() if accepts_tiles else ()),
    )


def pair_inputs(opts: Mapping[str, Any], *keys: str) -> Dict[str, Any]:
    """The input paths of an OutputPlan: every tile file of a tiled epoch, else the path, for
    ``before``, ``after`` and the other input options ``keys``."""
    from .tiled import input_files, is_tiled

    tiled = is_tiled(opts, "before", "after")
    out = {}
    for k in keys:
        out[k] = input_files(opts, k) if tiled and k in ("before", "after") else opts.get(k)
    return out


def control_option() -> Option:
    return Option(
        "control",
        "path",
        "CSV of control points with columns x,y,dx,dy[,dz] (metres, in the clouds' CRS; e.g. "
        "GPS or feature tracking): the field is sampled bilinearly at them and the errors "
        "(estimate - control: RMSE, bias) go to the summary",
        label="Control points x,y,dx,dy[,dz] (CSV)",
        role="input",
        pdal=None,
        metavar="CSV",
        file_filter=CSV_FILTER,
        unset_text="none",
    )


def breaklines_option(what: str) -> Option:
    """``--breaklines FILE``: lines across which the field may jump (scarps, a fault, the
    edge of a slab); ``what`` says what the job does with them."""
    return Option(
        "breaklines",
        "path",
        "line file (any OGR format and CRS, reprojected to the epochs' CRS) of scarps, faults "
        "or slab edges across which the field may jump: " + what,
        label="Breaklines (scarps, faults; optional line layer)",
        role="input",
        qgis=None,  # QGIS gives a line layer (the algorithm reads it)
        pdal=None,  # PDAL stages take a file path option of their own
        metavar="FILE",
        unset_text="none",
    )


def read_breaklines(path, crs, *, key: str = "breaklines"):
    """The :class:`~slipmap.core.breaklines.Breaklines` of a line file, reprojected to
    ``crs``; None when ``path`` is not given. Errors name ``key``."""
    if not path:
        return None
    from ..core.breaklines import breaklines
    from ..core.io.vector import read_lines

    try:
        return breaklines(read_lines(path, target_crs=crs, what="breakline file"))
    except SlipMapError as exc:
        raise OptionError(key, f"{exc}; give a line layer (LineString) in any CRS") from exc


def output_option(key: str, help: str, label: str, *, qgis: Optional[str] = None, **kw) -> Option:
    """An output file of a field job: named in the output folder on the CLI (``cli=None``),
    a destination parameter in QGIS when ``qgis`` is given."""
    return Option(
        key, "path", help, label=label, role="output", cli=None, qgis=qgis, pdal=None, **kw
    )


# --------------------------------------------------------------------------- inputs


def read_pair(opts: Mapping[str, Any]):
    """Both epochs' selected points and the outputs' CRS.

    Returns
    -------
    before : (N1, 3) float64
    after : (N2, 3) float64
        In the before epoch's CRS.
    crs : pyproj.CRS or None
    """
    pair = read_epoch_pair(opts["before"], opts["after"], crs=opts.get("crs"))
    kw = dict(classes=opts.get("classes"), exclude_classes=opts.get("exclude_classes"))
    sb = select_points(pair.before, what="the before epoch", **kw)
    sa = select_points(pair.after, what="the after epoch", **kw)
    if sb.size < len(pair.before) or sa.size < len(pair.after):
        log.info(
            "class selection: %d of %d before-epoch and %d of %d after-epoch points kept",
            sb.size,
            len(pair.before),
            sa.size,
            len(pair.after),
        )
    return pair.before.xyz[sb], pair.after_xyz[sa], pair.crs


def check_overlap(before, after) -> None:
    """Refuse epochs whose x, y bounding boxes are disjoint (naming the after epoch and the
    CRS option)."""
    lo_b, hi_b = before[:, :2].min(axis=0), before[:, :2].max(axis=0)
    lo_a, hi_a = after[:, :2].min(axis=0), after[:, :2].max(axis=0)
    if np.any(np.maximum(lo_b, lo_a) > np.minimum(hi_b, hi_a)):
        raise OptionError(
            "after",
            f"the epochs do not overlap in x, y (before x {lo_b[0]:.2f}..{hi_b[0]:.2f}, y "
            f"{lo_b[1]:.2f}..{hi_b[1]:.2f}; after x {lo_a[0]:.2f}..{hi_a[0]:.2f}, y "
            f"{lo_a[1]:.2f}..{hi_a[1]:.2f}): check that both are in the same CRS ({{crs}} "
            "replaces a wrong one) and cover the same area",
            also=("crs",),
        )


def common_grid_of(before, after, cell_m: float, *, key: str, bytes_per_cell: float):
    """The DEM grid both epochs share, refused when its working arrays would not fit in memory.

    ``key`` is the option that sets the cell size (named in the memory error).
    """
    from ..core.dem import common_grid
    from .resources import check_grid_memory

    check_overlap(before, after)
    grid = common_grid(before, after, cell_m=cell_m)
    check_grid_memory(
        key, grid.n_rows * grid.n_cols, bytes_per_cell=bytes_per_cell, what="DEM grid"
    )
    return grid


def check_windows_fit(windows_px, grid) -> None:
    """Refuse PIV windows larger than the DEM (naming ``windows_px`` and ``grid_m``)."""
    if max(windows_px) > min(grid.shape):
        raise OptionError(
            "windows_px",
            f"a window of {max(windows_px)} px does not fit in the {grid.n_rows} x "
            f"{grid.n_cols} px DEM ({grid.cell_m:g} m cells over the epochs' overlap); use "
            "smaller windows or a smaller {grid_m}",
            also=("grid_m",),
        )


# --------------------------------------------------------------------------- control points


@dataclass(frozen=True)
class Control:
    """Control points read from a CSV (:func:`read_control`)."""

    path: str
    xy: np.ndarray  # (M, 2) metres
    d: np.ndarray  # (M, 3) dx, dy, dz metres (NaN: unknown)


def read_control(path, *, key: str = "control") -> Optional[Control]:
    """The control points of ``path`` (None when not given), read before anything is computed.

    Raises
    ------
    OptionError
        Naming ``key``: the file is missing, unreadable, lacks columns or has no row.
    """
    if not path:
        return None
    from ..core.io.table import read_control_points

    try:
        xy, d = read_control_points(path)
    except SlipMapError as exc:
        raise OptionError(key, f"{exc}; give a CSV with columns x,y,dx,dy[,dz]") from exc
    n_ref = int(np.count_nonzero(np.isfinite(d[:, 0]) & np.isfinite(d[:, 1])))
    if n_ref == 0:
        raise OptionError(
            key,
            f"{path}: none of its {len(xy)} row(s) has a finite dx and dy; give the control "
            "displacements in metres",
        )
    return Control(str(path), xy, d)


def compare_control(
    control: Optional[Control],
    field,
    *,
    key: str = "control",
) -> Optional[Dict[str, Any]]:
    """Compare a :class:`~slipmap.core.fields.GriddedField` with the control points.

    Says how many rows were read, how many have no finite dx/dy, fall outside the field or
    where the field has no vector, and how many were compared.

    Raises
    ------
    OptionError
        Naming ``key`` when no control point can be compared (so the run writes nothing).
    """
    if control is None:
        return None
    from ..core.fields import compare_with_control

    n = len(control.xy)
    ref_ok = np.isfinite(control.d[:, 0]) & np.isfinite(control.d[:, 1])
    x0, y0 = field.origin_xy
    sx, sy = field.spacing_m
    n_rows, n_cols = field.shape
    x1, y1 = x0 + n_cols * sx, y0 - n_rows * sy
    cx, cy = control.xy[:, 0], control.xy[:, 1]
    inside = (cx >= x0) & (cx <= x1) & (cy >= y1) & (cy <= y0)
    comp = compare_with_control(None, None, None, None, None, control.xy, control.d, field=field)
    n_invalid = int(np.count_nonzero(~ref_ok))
    n_outside = int(np.count_nonzero(ref_ok & ~inside))
    n_no_vector = int(comp.n_missing) - n_outside
    counts = (
        f"{n} row(s) read, {n_invalid} without a finite dx/dy, {n_outside} outside the field "
        f"(x {x0:.2f}..{x1:.2f}, y {y1:.2f}..{y0:.2f}), {n_no_vector} where the field has no "
        "vector"
    )
    if comp.n_compared == 0:
        raise OptionError(
            key,
            f"{control.path}: no control point can be compared with the field ({counts}); "
            "check that the points lie in the surveyed area and in the clouds' CRS",
        )
    d = comp.to_dict()
    d.update(
        file=control.path,
        n_rows=n,
        n_without_reference=n_invalid,
        n_outside=n_outside,
        n_without_vector=n_no_vector,
    )
    log.info(
        "control points (%s): %s; %d compared: horizontal RMSE %.4f m, bias dx %+.4f dy %+.4f "
        "m, dz RMSE %.4f m",
        control.path,
        counts,
        d["n_compared"],
        d["rmse_horizontal_m"],
        d["bias_dx_m"],
        d["bias_dy_m"],
        d["rmse_dz_m"],
    )
    return d


def field_of_columns(x, y, dx, dy, dz=None, *, spacing_m=None, valid=None, key: str, what: str):
    """:func:`~slipmap.core.fields.field_from_columns` with errors naming the input ``key``
    (``what`` says which file or layer) and the spacing option as ``{spacing_m}``."""
    from ..core.fields import field_from_columns

    try:
        return field_from_columns(x, y, dx, dy, dz, spacing_m=spacing_m, valid=valid)
    except SlipMapError as exc:
        text = str(exc).replace("field_from_columns: ", "").replace("spacing_m", "{spacing_m}")
        raise OptionError(key, f"{what}: {text}", also=("spacing_m",)) from exc


# --------------------------------------------------------------------------- outputs


def write_tif(path, array, *, origin_xy, pixel_m, crs, names, metadata=None):
    """A float64 GeoTIFF (NaN = no data) of ``array`` ``(rows, cols)`` or ``(bands, rows,
    cols)``; ``crs`` a pyproj CRS or None."""
    from ..core.io.raster import write_geotiff

    write_geotiff(
        path,
        np.asarray(array, dtype=np.float64),
        origin_xy=origin_xy,
        pixel_size_m=pixel_m,
        crs_wkt=None if crs is None else crs.to_wkt(),
        band_names=list(names),
        metadata=metadata,
    )


def figures():
    """The figures module, or None with a warning when matplotlib is missing."""
    return plotting()


def horizontal_columns(dx, dy) -> Dict[str, np.ndarray]:
    """``magnitude`` (m) and ``azimuth_deg`` (clockwise from north) of horizontal vectors."""
    from .summaries import horizontal

    mag, az = horizontal(dx, dy)
    return {"magnitude": mag, "azimuth_deg": az}
