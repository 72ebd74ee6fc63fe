"""Job ``strain``: horizontal infinitesimal strain of a gridded displacement field.

The field is a vector table (``piv.csv`` / ``icp.csv``: columns x, y, dx, dy[, dz, valid]),
a dx GeoTIFF (two bands dx, dy, or one band with a dy GeoTIFF beside it), or columns a face
read itself (a QGIS layer). The vectors are put back on their grid
(:func:`~slipmap.core.fields.field_from_columns`) and :func:`~slipmap.core.strain.strain_field`
gives the tensor, rotation and principal strains, written as a 9-band GeoTIFF, a figure and
``strain.json``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

from .._version import __version__
from ..core.errors import SlipMapError
from .fields import (
    ARYAL,
    JSON_FILTER,
    PNG_FILTER,
    TIF_FILTER,
    field_of_columns,
    figures,
    output_option,
    write_tif,
)
from .inputs import as_crs, out_dir_option
from .job import JobResult, Progress
from .options import JobSpec, Option, OptionError
from .outputs import OutputPlan
from .styles import write_raster_style
from .summaries import finite_stats, json_text

log = logging.getLogger("slipmap.app")

BAND_HELP = (
    "exx, eyy, exy (tensor shear), rotation_rad (counter-clockwise), e1, e2 (principal, "
    "e1 >= e2), e1_azimuth_deg (clockwise from north), max_shear = (e1 - e2)/2, dilatation "
    "= exx + eyy"
)
EXPECTED = (
    "give a vector table (piv.csv / icp.csv: columns x, y, dx, dy[, dz, valid]) or a dx "
    "GeoTIFF (two bands dx, dy, or one band and {dy})"
)
_TABLES = (".csv", ".txt")
_RASTERS = (".tif", ".tiff")

SPEC = JobSpec(
    name="strain",
    title="Strain from a displacement field",
    description=(
        "Horizontal infinitesimal strain of a gridded displacement field: the vectors are put "
        "back on their regular grid, the displacement gradient is taken by central "
        "differences (one-sided next to gaps and edges) and the strain tensor, rotation and "
        "principal strains follow (extension positive)."
    ),
    options=(
        Option(
            "field",
            "path",
            "the displacement field: piv.csv / icp.csv (columns x, y, dx, dy[, dz, valid]), "
            "or a dx GeoTIFF (two bands dx, dy, or one band with --dy)",
            label="Displacement field (vectors layer or CSV)",
            required=True,
            role="input",
            cli="field",
            qgis=None,  # QGIS gives a layer or table (the algorithm reads its features)
            pdal=None,
        ),
        out_dir_option(),
        Option(
            "dy",
            "path",
            "dy GeoTIFF when the field is a one-band dx GeoTIFF",
            label="dy GeoTIFF",
            role="input",
            qgis=None,
            pdal=None,
            metavar="TIF",
            file_filter=TIF_FILTER,
            unset_text="none",
        ),
        Option(
            "spacing_m",
            "float",
            "vector spacing of a table field, metres (default: inferred from the positions)",
            label="Vector spacing (m; default inferred)",
            minimum=0,
            exclusive=True,
            metavar="M",
            unset_text="inferred",
        ),
        Option(
            "valid_only",
            "bool",
            "a table with a valid column: use only the valid vectors (not the missing or "
            "replaced outliers of PIV)",
            label="Valid vectors only",
            default=False,
            advanced=True,
        ),
        Option(
            "crs",
            "crs",
            "CRS of the field's positions (e.g. EPSG:32612) when the field has none or a wrong "
            "one; the outputs carry it",
            label="CRS of the field (when it has none or a wrong one)",
            advanced=True,
            pdal=None,
            metavar="CRS",
            unset_text="the field's",
        ),
        output_option(
            "raster",
            f"9-band strain GeoTIFF (strain.tif): {BAND_HELP}",
            "Strain",
            qgis="OUTPUT",
            file_filter=TIF_FILTER,
        ),
        output_option(
            "summary",
            "summary (strain.json)",
            "Strain summary",
            qgis="SUMMARY",
            file_filter=JSON_FILTER,
        ),
        output_option(
            "plot",
            "figure (strain.png)",
            "Strain figure (PNG)",
            qgis="PLOT",
            file_filter=PNG_FILTER,
        ),
    ),
    citation=f"strain fields from TLS displacement fields as in {ARYAL}",
)


def default_names(opts: Mapping[str, Any]) -> Dict[str, str]:
    return {"raster": "strain.tif", "summary": "strain.json", "plot": "strain.png"}


# --------------------------------------------------------------------------- reading


def _is_las(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(4) == b"LASF"
    except OSError:
        return False


def read_table(path, *, key: str = "field") -> Dict[str, np.ndarray]:
    """Columns x, y, dx, dy[, dz, valid] of a vector table, errors naming ``key``."""
    from ..core.io.table import read_csv_columns

    try:
        return read_csv_columns(path, required=("x", "y", "dx", "dy"), optional=("dz", "valid"))
    except UnicodeDecodeError:
        raise OptionError(key, f"{path} is not a text table; {EXPECTED}", also=("dy",)) from None
    except SlipMapError as exc:
        raise OptionError(key, f"{exc}; {EXPECTED}", also=("dy",)) from exc


def _read_raster(path, key):
    from ..core.io.raster import read_geotiff

    try:
        arr, gt, wkt = read_geotiff(path)
    except SlipMapError as exc:
        raise OptionError(key, f"{exc}; {EXPECTED}", also=("dy",)) from exc
    return np.asarray(arr, dtype=np.float64), gt, wkt


def read_field(opts: Mapping[str, Any]) -> Tuple[Any, Optional[str], int]:
    """The :class:`~slipmap.core.fields.GriddedField` of ``opts["field"]``, the CRS WKT a
    GeoTIFF declares (None otherwise) and the number of vectors.

    Raises
    ------
    OptionError
        Naming the field (or ``dy``) option: not a table or GeoTIFF, missing columns, one
        band without ``dy``, grids that differ, a raster that is not north-up.
    """
    from ..core.fields import GriddedField

    path = Path(str(opts["field"]))
    if not path.is_file():
        raise OptionError("field", f"{path} does not exist; {EXPECTED}", also=("dy",))
    suffix = path.suffix.lower()
    if _is_las(path) or suffix in (".las", ".laz"):
        raise OptionError(
            "field",
            f"{path} is a LAS/LAZ point cloud, not a displacement field: compute one with the "
            f"piv or icp job first, then {EXPECTED}",
            also=("dy",),
        )
    if suffix in _RASTERS:
        arr, gt, wkt = _read_raster(path, "field")
        if opts.get("dy"):
            dy_arr, gt2, _ = _read_raster(opts["dy"], "dy")
            if tuple(gt2) != tuple(gt) or dy_arr.shape[-2:] != arr.shape[-2:]:
                raise OptionError(
                    "dy",
                    f"{opts['dy']}: its grid differs from {path}'s; give the dy raster of the "
                    "same field",
                )
            dx = arr[0] if arr.ndim == 3 else arr
            dy = dy_arr[0] if dy_arr.ndim == 3 else dy_arr
        elif arr.ndim == 3 and arr.shape[0] >= 2:
            dx, dy = arr[0], arr[1]
        else:
            raise OptionError(
                "field",
                f"{path} has one band only; give the dy raster with {{dy}} (or a 2-band dx, "
                "dy file)",
                also=("dy",),
            )
        if gt[2] != 0 or gt[4] != 0 or gt[5] >= 0:
            raise OptionError(
                "field", f"{path} is not a north-up raster; warp it north-up (gdalwarp) first"
            )
        field = GriddedField(
            origin_xy=(gt[0], gt[3]), spacing_m=(gt[1], -gt[5]), dx=dx, dy=dy, dz=None
        )
        return field, (wkt or None), int(np.count_nonzero(field.valid))
    if suffix not in _TABLES:
        log.info("%s: read as a CSV table (suffix %r)", path, suffix)
    if opts.get("dy"):
        raise OptionError("dy", "applies to a one-band dx GeoTIFF only; leave it out for a table")
    cols = read_table(path)
    return _table_field(cols, opts, what=str(path)), None, int(cols["x"].size)


def _table_field(cols: Mapping[str, np.ndarray], opts: Mapping[str, Any], *, what: str):
    x, y = np.asarray(cols["x"], dtype=np.float64), np.asarray(cols["y"], dtype=np.float64)
    if not x.size:
        raise OptionError("field", f"{what} has no vector; {EXPECTED}", also=("dy",))
    valid = None
    if opts.get("valid_only") and "valid" in cols:
        valid = np.asarray(cols["valid"]) > 0.5
    return field_of_columns(
        x,
        y,
        cols["dx"],
        cols["dy"],
        cols.get("dz"),
        spacing_m=opts.get("spacing_m"),
        valid=valid,
        key="field",
        what=what,
    )


# --------------------------------------------------------------------------- run


def run(
    opts: Mapping[str, Any],
    outputs: Mapping[str, Any],
    *,
    columns: Optional[Mapping[str, np.ndarray]] = None,
    crs=None,
    what: str = "",
    progress: Optional[Progress] = None,
) -> JobResult:
    """Read the field, compute strain, write.

    Parameters
    ----------
    opts
        :data:`SPEC`'s options, parsed.
    outputs
        ``{"out": folder}`` or ``{"raster": path, "summary": path, "plot": path}``.
    columns, crs, what
        The vectors as columns ``x, y, dx, dy[, dz, valid]`` (a face that read a layer:
        ``opts["field"]`` then only names it), the layer's CRS (pyproj, or None) and how
        messages name the layer.

    The ``crs`` option, when given, replaces the field's own CRS. A geographic CRS is refused
    (strain needs positions in metres).
    """
    from ..core.strain import strain_field

    plan = OutputPlan.for_outputs(
        inputs={"field": opts.get("field") if columns is None else None, "dy": opts.get("dy")},
        outputs=outputs,
        default_names=default_names(opts),
    )
    plan.check()
    with plan:
        if progress is not None:
            progress(0.0, "reading the vectors")
        if columns is None:
            field, wkt, n_vectors = read_field(opts)
            crs = as_crs(wkt) if wkt else None
        else:
            field = _table_field(columns, opts, what=what or "the field")
            n_vectors = int(np.asarray(columns["x"]).size)
        crs_key = "field"
        if opts.get("crs") is not None:
            crs, crs_key = as_crs(opts["crs"]), "crs"
        if crs is not None and crs.is_geographic:
            raise OptionError(
                crs_key,
                f"the field's CRS {crs.name!r} is geographic (degrees): strain needs positions "
                "in metres; reproject the vectors to a projected CRS first",
            )
        if progress is not None:
            progress(0.5, "strain")
        bands = strain_field(field).bands()
        sx, sy = field.spacing_m
        if plan.wants("raster"):
            write_tif(
                plan.file("raster"),
                np.stack(list(bands.values())),
                origin_xy=field.origin_xy,
                pixel_m=(sx, sy),
                crs=crs,
                names=list(bands),
                metadata={"strain": "infinitesimal, extension positive; max_shear = (e1-e2)/2"},
            )
            write_raster_style(plan, "strain", "raster", next(iter(bands.values())))
        report = figures() if plan.wants("plot") else None
        if report is not None:
            x0, y0 = field.origin_xy
            report.plot_raster_panels(
                plan.file("plot"),
                bands,
                extent=(x0, x0 + field.shape[1] * sx, y0 - field.shape[0] * sy, y0),
                diverging=("exx", "eyy", "exy", "rotation_rad", "e1", "e2", "dilatation"),
                cyclic=("e1_azimuth_deg",),
            )
        summary = {
            "command": "strain",
            "field": str(opts.get("field") or what),
            "n_vectors": n_vectors,
            "shape": list(field.shape),
            "origin_xy": list(field.origin_xy),
            "spacing_m": [sx, sy],
            "bands": {k: finite_stats(v) for k, v in bands.items()},
            "files": plan.written_names(("raster", "plot")),
            "crs": None if crs is None else crs.to_wkt(),
            "slipmap_version": __version__,
        }
        if plan.wants("summary"):
            plan.file("summary").write_text(json_text(summary), encoding="utf-8")
        if progress is not None:
            progress(1.0, "strain done")
    lines = [
        f"strain: {field.shape[0]} x {field.shape[1]} cells of {sx:g} x {sy:g} m, dilatation "
        f"median {summary['bands']['dilatation'].get('median', float('nan')):.2e}, max shear "
        f"max {summary['bands']['max_shear'].get('max', float('nan')):.2e}"
    ]
    files = {
        k: plan.final(k)
        for k in ("raster", "plot", "summary")
        if plan.wants(k) and plan.final(k).exists()
    }
    return JobResult(summary, lines, files, data={"field": field, "bands": bands, "crs": crs})
