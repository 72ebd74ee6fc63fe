"""``slipmap`` subcommands for displacement fields: piv, icp, dem-diff, strain, synth-lobe.

A thin adapter (as :mod:`slipmap.cli`): read files through ``core.io``, call ``core.dem``,
``core.piv``, ``core.icp``, ``core.strain``, ``core.fields`` and ``core.synthetic``, write
CSV / GeoTIFF / GeoPackage / PNG / JSON outputs. Registered in :func:`slipmap.cli.build_parser`.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Optional

import numpy as np

from ..app.summaries import finite_stats, horizontal, icp_summary, json_safe
from ..core.errors import InputDataError, InvalidParameterError
from .legacy import (
    _add_crs_argument,
    _check_output_dir,
    _have_matplotlib,
    _positive,
    _ProgressBar,
    _write_json,
    command,
    parse_crs_option,
    read_cloud,
    read_epoch_pair,
)

log = logging.getLogger("slipmap")


# --------------------------------------------------------------------------- shared


def _add_field_selection(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("point selection (default: every point)")
    g.add_argument("--classes", type=int, nargs="+", metavar="C", help="keep only these classes")
    g.add_argument(
        "--exclude-classes", type=int, nargs="+", metavar="C", help="drop these classes (e.g. 7)"
    )
    _add_crs_argument(
        p,
        "CRS of both epochs when the files lack one or declare a wrong one (e.g. "
        "EPSG:32612); written to the outputs",
    )


def _select(cloud, args) -> np.ndarray:
    keep = np.ones(len(cloud), dtype=bool)
    cls = cloud.attributes.get("Classification")
    if (args.classes or args.exclude_classes) and cls is None:
        raise InvalidParameterError(
            f"{cloud.source}: --classes/--exclude-classes given but the file has no "
            "Classification dimension"
        )
    if args.classes:
        keep &= np.isin(cls, args.classes)
    if args.exclude_classes:
        keep &= ~np.isin(cls, args.exclude_classes)
    if not keep.any():
        raise InputDataError(f"{cloud.source}: no point left after the class selection")
    return keep


def _read_pair(args):
    """Both epochs (after reprojected to before's CRS if they differ), selected points, CRS."""
    first, second, xyz2 = read_epoch_pair(args.before, args.after, getattr(args, "crs", None))
    crs = first.crs if first.crs is not None else second.crs
    return first.xyz[_select(first, args)], xyz2[_select(second, args)], crs


def _wkt(crs) -> Optional[str]:
    return None if crs is None else crs.to_wkt()


def _tif(path: Path, array, *, origin_xy, pixel_m, crs, names, metadata=None) -> str:
    from ..core.io.raster import write_geotiff

    write_geotiff(
        path,
        np.asarray(array, dtype=np.float64),
        origin_xy=origin_xy,
        pixel_size_m=pixel_m,
        crs_wkt=_wkt(crs),
        band_names=names,
        metadata=metadata,
    )
    return path.name


def _control(args, x, y, dx, dy, dz, *, spacing_m=None) -> Optional[dict]:
    """Compare a field with --control points; logged and returned as a dict."""
    if not getattr(args, "control", None):
        return None
    from ..core.fields import compare_with_control
    from ..core.io.table import read_control_points

    cxy, cd = read_control_points(args.control)
    comp = compare_with_control(x, y, dx, dy, dz, cxy, cd, spacing_m=spacing_m)
    d = comp.to_dict()
    log.info(
        "control points (%s): %d compared, %d without estimate; horizontal RMSE %.4f m, "
        "bias dx %+.4f dy %+.4f m, dz RMSE %.4f m",
        args.control,
        d["n_compared"],
        d["n_missing"],
        d["rmse_horizontal_m"],
        d["bias_dx_m"],
        d["bias_dy_m"],
        d["rmse_dz_m"],
    )
    return d


# --------------------------------------------------------------------------- piv


@command("piv", "3D displacement field by PIV on gridded elevation (Aryal et al., 3.2.1)")
def _run_piv(args: argparse.Namespace) -> int:
    from ..core.dem import common_grid, grid_elevation
    from ..core.io.table import write_csv_columns
    from ..core.piv import piv

    out = Path(args.out)
    _check_output_dir(out)
    windows = _windows(args)  # bad --passes fails before reading
    before, after, crs = _read_pair(args)
    grid = common_grid(before, after, cell_m=args.grid)
    zb = grid_elevation(before, grid=grid)
    za = grid_elevation(after, grid=grid)
    log.info("DEMs: %d x %d cells of %.3f m", grid.n_rows, grid.n_cols, grid.cell_m)
    with _ProgressBar("piv", enabled=not args.no_progress) as bar:
        res = piv(
            zb,
            za,
            grid=grid,
            windows_px=windows,
            overlap=args.overlap,
            search_px=args.search_px,
            expected_max_displacement_m=args.max_displacement,
            snr_min=args.snr_min,
            median_threshold=args.median_threshold,
            progress=bar,
        )
    out.mkdir(parents=True, exist_ok=True)
    cols = res.to_columns()
    files = [write_csv_columns(out / "piv.csv", cols).name]
    meta = {"method": "PIV", "windows_px": " ".join(map(str, res.windows_px))}
    for comp in ("dx", "dy", "dz"):
        files.append(
            _tif(
                out / f"piv_{comp}.tif",
                getattr(res, comp),
                origin_xy=res.origin_xy,
                pixel_m=res.spacing_m,
                crs=crs,
                names=[comp],
                metadata=meta,
            )
        )
    if args.write_dems:
        stack = np.stack([zb, za])
        files.append(
            _tif(
                out / "dems.tif",
                stack,
                origin_xy=grid.origin_xy,
                pixel_m=grid.cell_m,
                crs=crs,
                names=["z_before", "z_after"],
            )
        )
    if _have_matplotlib():
        from ..core.report import hillshade, plot_vector_field

        extent = (grid.x_min, grid.x_max, grid.y_min, grid.y_max)
        plot_vector_field(
            out / "piv.png",
            x=cols["x"],
            y=cols["y"],
            dx=cols["dx"],
            dy=cols["dy"],
            valid=cols["valid"],
            colour=cols["dz"],
            background=hillshade(zb, cell_m=grid.cell_m),
            extent=extent,
            title=f"PIV, GR {grid.cell_m:g} m, windows {list(res.windows_px)} px",
        )
        files.append("piv.png")
    ok = np.isfinite(res.dx) & np.isfinite(res.dy)
    summary = {
        "command": "piv",
        "before": str(args.before),
        "after": str(args.after),
        "grid_m": grid.cell_m,
        "dem_shape": list(grid.shape),
        "windows_px": list(res.windows_px),
        "search_px": res.search_px,
        "vector_spacing_m": res.spacing_m,
        "n_vectors": int(res.dx.size),
        "n_with_value": int(ok.sum()),
        "valid_fraction": float(res.valid.mean()) if res.valid.size else 0.0,
        "horizontal_m": finite_stats(np.hypot(res.dx, res.dy)),
        "dz_m": finite_stats(res.dz),
        "control": _control(
            args, cols["x"], cols["y"], cols["dx"], cols["dy"], cols["dz"], spacing_m=res.spacing_m
        ),
        "files": files,
    }
    _write_json(out / "piv.json", json_safe(summary))
    log.info(
        "PIV: %d vectors (%.0f %% valid), median horizontal %.4f m; wrote %s",
        summary["n_vectors"],
        100 * summary["valid_fraction"],
        summary["horizontal_m"].get("median", float("nan")),
        out,
    )
    return 0


@_run_piv.arguments
def _piv_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("before", help="first-epoch LAS/LAZ")
    p.add_argument("after", help="second-epoch LAS/LAZ")
    p.add_argument(
        "--grid",
        type=_positive(float, "--grid"),
        required=True,
        help="DEM grid size GR (m; the study used 0.04)",
    )
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument(
        "--window",
        type=int,
        nargs="+",
        default=[64, 32, 16, 16],
        metavar="PX",
        help="interrogation window per pass (pixels; default 64 32 16 16: the last size is "
        "repeated once, which halves the error in deforming areas)",
    )
    p.add_argument(
        "--passes",
        type=int,
        default=None,
        help="number of passes: repeat the last --window size to reach it",
    )
    p.add_argument("--overlap", type=float, default=0.5, help="window overlap (default 0.5)")
    p.add_argument("--search-px", type=int, default=None, help="first-pass search margin (pixels)")
    p.add_argument(
        "--max-displacement",
        type=_positive(float, "--max-displacement"),
        default=None,
        help="largest expected displacement d_max (m): sets the search margin; the study's "
        "rule of thumb is WC >= 2 d_max",
    )
    p.add_argument("--snr-min", type=float, default=1.2, help="signal-to-noise threshold")
    p.add_argument(
        "--median-threshold", type=float, default=2.0, help="normalised median test threshold"
    )
    p.add_argument("--control", help="CSV of control points x,y,dx,dy[,dz] to compare with")
    p.add_argument("--write-dems", action="store_true", help="also write dems.tif")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_field_selection(p)


def _windows(args) -> list:
    """--window sizes, cut or extended (last size repeated) to --passes."""
    w = list(args.window)
    if args.passes is not None:
        if args.passes < 1:
            raise InvalidParameterError(f"--passes must be >= 1, got {args.passes}")
        w = w[: args.passes] + [w[-1]] * max(0, args.passes - len(w))
    return w


# --------------------------------------------------------------------------- icp


def _cell_polygons(res) -> list:
    x0, y0 = res.origin_xy
    s = res.cell_m
    out = []
    for r, c in zip(res.row.tolist(), res.col.tolist()):
        left, top = x0 + c * s, y0 - r * s
        out.append(np.array([[left, top], [left + s, top], [left + s, top - s], [left, top - s]]))
    return out


@command("icp", "3D displacement field by windowed point-to-plane ICP (Aryal et al., 3.2.2)")
def _run_icp(args: argparse.Namespace) -> int:
    from ..core.icp import windowed_icp
    from ..core.io.table import write_csv_columns
    from ..core.io.vector import VectorLayer, read_polygons, write_gpkg_layers

    out = Path(args.out)
    _check_output_dir(out)
    before, after, crs = _read_pair(args)
    exclude = None
    if args.stable_mask:
        exclude = read_polygons(args.stable_mask, target_crs=crs)
    with _ProgressBar("icp", enabled=not args.no_progress) as bar:
        res = windowed_icp(
            before,
            after,
            cell_m=args.cell,
            buffer_m=args.buffer,
            min_points=args.min_points,
            prealign=bool(exclude) or args.prealign,
            exclude_polygons=exclude,
            coarse_to_fine=args.coarse_to_fine,
            sigma_scaling="formal" if args.formal_sigma else "field",
            progress=bar,
        )
    out.mkdir(parents=True, exist_ok=True)
    cols = res.to_columns()
    files = [write_csv_columns(out / "icp.csv", cols).name]
    mag, az = horizontal(res.dx, res.dy)
    fields = {k: np.asarray(v) for k, v in cols.items() if k not in ("row", "col")}
    fields.update({"magnitude": mag, "azimuth_deg": az})
    write_gpkg_layers(
        out / "icp.gpkg",
        [
            VectorLayer("cells", "Polygon", _cell_polygons(res), fields),
            VectorLayer(
                "vectors",
                "LineString",
                [
                    np.array([[x, y], [x + dx, y + dy]])
                    for x, y, dx, dy in zip(res.x, res.y, res.dx, res.dy)
                ],
                fields,
            ),
        ],
        crs=crs,
    )
    files.append("icp.gpkg")
    bands = ["dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_dz", "rmse", "n"]
    files.append(
        _tif(
            out / "icp.tif",
            np.stack([res.to_grid(b) for b in bands]),
            origin_xy=res.origin_xy,
            pixel_m=res.cell_m,
            crs=crs,
            names=bands,
            metadata={"method": "windowed point-to-plane ICP", "cell_m": f"{res.cell_m:g}"},
        )
    )
    if _have_matplotlib():
        from ..core.dem import common_grid, grid_elevation
        from ..core.report import hillshade, plot_vector_field

        cell = max(res.cell_m / 20.0, 0.05)
        grid = common_grid(before, cell_m=cell, overlap="union")
        extent = (grid.x_min, grid.x_max, grid.y_min, grid.y_max)
        plot_vector_field(
            out / "icp.png",
            x=res.x,
            y=res.y,
            dx=res.dx,
            dy=res.dy,
            colour=res.dz,
            background=hillshade(grid_elevation(before, grid=grid), cell_m=cell),
            extent=extent,
            title=f"windowed ICP, {res.cell_m:g} m cells",
        )
        files.append("icp.png")
    summary = {
        "command": "icp",
        "before": str(args.before),
        "after": str(args.after),
        **icp_summary(res),
        "control": _control(args, res.x, res.y, res.dx, res.dy, res.dz, spacing_m=res.cell_m),
        "files": files,
    }
    _write_json(out / "icp.json", json_safe(summary))
    log.info(
        "ICP: %d cells (%s skipped), median horizontal %.4f m, median sigma %.4f m; wrote %s",
        len(res),
        sum(res.skipped.values()),
        summary["horizontal_m"].get("median", float("nan")),
        summary["sigma_horizontal_m"].get("median", float("nan")),
        out,
    )
    return 0


@_run_icp.arguments
def _icp_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("before", help="first-epoch LAS/LAZ")
    p.add_argument("after", help="second-epoch LAS/LAZ")
    p.add_argument(
        "--cell", type=_positive(float, "--cell"), default=5.0, help="cell size (m; default 5)"
    )
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument(
        "--buffer",
        type=float,
        default=None,
        help="epoch-1 points this far around each cell are used (m; default half a cell)",
    )
    p.add_argument(
        "--min-points", type=int, default=100, help="cells with fewer points are skipped"
    )
    p.add_argument(
        "--stable-mask",
        help="polygon file of the MOVING area: epoch 2 is first aligned on the points "
        "outside it (the study's masked global alignment)",
    )
    p.add_argument(
        "--prealign", action="store_true", help="global ICP pre-alignment on all points first"
    )
    p.add_argument(
        "--coarse-to-fine",
        type=int,
        default=1,
        metavar="LEVELS",
        help="coarser passes (cells 2x, 4x, ...) that start each cell from the coarser motion; "
        "needed when the motion is not small against the cell (default 1; 0 to disable)",
    )
    p.add_argument(
        "--formal-sigma",
        action="store_true",
        help="report the cells' formal sigmas; by default they are multiplied by the field's "
        "variance factor from the agreement of neighbouring cells (formal sigmas assume "
        "independent point residuals and are 2-4x too small on real surfaces)",
    )
    p.add_argument("--control", help="CSV of control points x,y,dx,dy[,dz] to compare with")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _add_field_selection(p)


# --------------------------------------------------------------------------- dem-diff


@command("dem-diff", "vertical change by DEM differencing (the simple baseline)")
def _run_dem_diff(args: argparse.Namespace) -> int:
    from ..core.dem import dem_difference

    out = Path(args.out)
    _check_output_dir(out)
    before, after, crs = _read_pair(args)
    res = dem_difference(before, after, cell_m=args.grid)
    g = res.grid
    out.mkdir(parents=True, exist_ok=True)
    files = [
        _tif(
            out / "dem_diff.tif",
            np.stack([res.dz, res.z_before, res.z_after]),
            origin_xy=g.origin_xy,
            pixel_m=g.cell_m,
            crs=crs,
            names=["dz", "z_before", "z_after"],
        )
    ]
    if _have_matplotlib():
        from ..core.report import plot_raster_panels

        extent = (g.x_min, g.x_max, g.y_min, g.y_max)
        plot_raster_panels(
            out / "dem_diff.png",
            {"dz = after - before (m)": res.dz, "z before (m)": res.z_before},
            extent=extent,
            diverging=("dz = after - before (m)",),
            columns=2,
        )
        files.append("dem_diff.png")
    summary = {
        "command": "dem-diff",
        "grid_m": g.cell_m,
        "shape": list(g.shape),
        "dz_m": finite_stats(res.dz),
        "files": files,
    }
    _write_json(out / "dem_diff.json", json_safe(summary))
    log.info(
        "DEM difference: %d cells, mean dz %+.4f m (std %.4f); wrote %s",
        res.n_valid,
        res.mean_m,
        res.std_m,
        out,
    )
    return 0


@_run_dem_diff.arguments
def _dem_diff_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("before", help="first-epoch LAS/LAZ")
    p.add_argument("after", help="second-epoch LAS/LAZ")
    p.add_argument("--grid", type=_positive(float, "--grid"), required=True, help="cell (m)")
    p.add_argument("--out", required=True, help="output directory")
    _add_field_selection(p)


# --------------------------------------------------------------------------- strain


def _field_from_file(args):
    """A GriddedField from piv.csv / icp.csv, or a dx GeoTIFF (+ --dy, or a 2-band file)."""
    from ..core.fields import GriddedField, field_from_columns

    path = Path(args.field)
    if path.suffix.lower() in (".tif", ".tiff"):
        from ..core.io.raster import read_geotiff

        arr, gt, wkt = read_geotiff(path)
        arr = np.asarray(arr, dtype=np.float64)
        if arr.ndim == 3 and arr.shape[0] >= 2 and not args.dy:
            dx, dy = arr[0], arr[1]
        elif args.dy:
            dy_arr, gt2, _ = read_geotiff(args.dy)
            if tuple(gt2) != tuple(gt):
                raise InputDataError(f"{args.dy}: its grid differs from {path}'s")
            dx, dy = (arr[0] if arr.ndim == 3 else arr), np.asarray(dy_arr, dtype=np.float64)
            dy = dy[0] if dy.ndim == 3 else dy
        else:
            raise InvalidParameterError(
                f"{path}: one band only; give the dy raster with --dy (or a dx, dy 2-band file)"
            )
        if gt[2] != 0 or gt[4] != 0 or gt[5] >= 0:
            raise InputDataError(f"{path}: only north-up rasters are supported")
        field = GriddedField(
            origin_xy=(gt[0], gt[3]), spacing_m=(gt[1], -gt[5]), dx=dx, dy=dy, dz=None
        )
        return field, (wkt or None)
    from ..core.io.table import read_csv_columns

    cols = read_csv_columns(path, required=("x", "y", "dx", "dy"), optional=("dz", "valid"))
    valid = None
    if "valid" in cols and args.valid_only:
        valid = cols["valid"] > 0.5
    field = field_from_columns(
        cols["x"],
        cols["y"],
        cols["dx"],
        cols["dy"],
        cols.get("dz"),
        spacing_m=args.spacing,
        valid=valid,
    )
    return field, None


@command("strain", "horizontal strain from a displacement field (PIV/ICP CSV or GeoTIFFs)")
def _run_strain(args: argparse.Namespace) -> int:
    from ..core.io.crs import parse_crs
    from ..core.strain import strain_field

    out = Path(args.out)
    _check_output_dir(out)
    given_crs = parse_crs_option(args.crs)
    field, wkt = _field_from_file(args)
    crs = given_crs if given_crs is not None else parse_crs(wkt)
    s = strain_field(field)
    bands = s.bands()
    out.mkdir(parents=True, exist_ok=True)
    sx, sy = field.spacing_m
    files = [
        _tif(
            out / "strain.tif",
            np.stack(list(bands.values())),
            origin_xy=field.origin_xy,
            pixel_m=(sx, sy),
            crs=crs,
            names=list(bands),
            metadata={"strain": "infinitesimal, extension positive; max_shear = (e1-e2)/2"},
        )
    ]
    if _have_matplotlib():
        from ..core.report import plot_raster_panels

        x0, y0 = field.origin_xy
        extent = (x0, x0 + field.shape[1] * sx, y0 - field.shape[0] * sy, y0)
        plot_raster_panels(
            out / "strain.png",
            bands,
            extent=extent,
            diverging=("exx", "eyy", "exy", "rotation_rad", "e1", "e2", "dilatation"),
            cyclic=("e1_azimuth_deg",),
        )
        files.append("strain.png")
    summary = {
        "command": "strain",
        "field": str(args.field),
        "shape": list(field.shape),
        "spacing_m": [sx, sy],
        "bands": {k: finite_stats(v) for k, v in bands.items()},
        "files": files,
    }
    _write_json(out / "strain.json", json_safe(summary))
    log.info(
        "strain: %d x %d cells, dilatation median %.2e, max shear max %.2e; wrote %s",
        field.shape[0],
        field.shape[1],
        summary["bands"]["dilatation"].get("median", float("nan")),
        summary["bands"]["max_shear"].get("max", float("nan")),
        out,
    )
    return 0


@_run_strain.arguments
def _strain_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("field", help="piv.csv / icp.csv, or a dx GeoTIFF (2-band dx,dy, or --dy)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--dy", help="dy GeoTIFF when FIELD is a one-band dx GeoTIFF")
    p.add_argument(
        "--spacing",
        type=_positive(float, "--spacing"),
        default=None,
        help="vector spacing of a CSV field (m; default: inferred)",
    )
    p.add_argument(
        "--valid-only",
        action="store_true",
        help="CSV with a valid column: use only valid (not replaced) vectors",
    )
    _add_crs_argument(p, "CRS of the outputs (e.g. EPSG:32612) for a CSV field")


# --------------------------------------------------------------------------- synth-lobe


@command("synth-lobe", "inject a known landslide lobe into a real cloud (validation pair)")
def _run_synth_lobe(args: argparse.Namespace) -> int:
    from ..core.io.atomic import check_not_input
    from ..core.io.las import write_las
    from ..core.io.table import write_csv_columns
    from ..core.synthetic import make_lobe_pair

    out = Path(args.out)
    _check_output_dir(out)
    cloud = read_cloud(args.input)
    ext = (
        Path(args.input).suffix.lower()
        if Path(args.input).suffix.lower() in (".las", ".laz")
        else ".laz"
    )
    paths = {k: out / f"{k}{ext}" for k in ("before", "after")}
    for p in paths.values():
        check_not_input(p, [args.input])
    pair = make_lobe_pair(
        cloud.xyz,
        max_dx_m=args.max_dx,
        max_dy_m=args.max_dy,
        max_dz_m=args.max_dz,
        centre_xy=args.centre,
        radius_m=None
        if not args.radius
        else (args.radius[0] if len(args.radius) == 1 else tuple(args.radius[:2])),
        azimuth_deg=args.azimuth,
        seed=args.seed,
    )
    out.mkdir(parents=True, exist_ok=True)
    write_las(paths["before"], cloud.subset(pair.before_index), inputs=[args.input])
    write_las(paths["after"], cloud.subset(pair.after_index), xyz=pair.after, inputs=[args.input])
    # the truth as control points on a regular grid covering the cloud
    lo, hi = cloud.xyz[:, :2].min(axis=0), cloud.xyz[:, :2].max(axis=0)
    step = args.truth_spacing
    gx = np.arange(lo[0] + step / 2, hi[0], step)
    gy = np.arange(lo[1] + step / 2, hi[1], step)
    xx, yy = np.meshgrid(gx, gy)
    xy = np.column_stack([xx.ravel(), yy.ravel()])
    d = pair.field(xy)
    interior = pair.field.interior_mask(xy)
    write_csv_columns(
        out / "truth.csv",
        {"x": xy[:, 0], "y": xy[:, 1], "dx": d[:, 0], "dy": d[:, 1], "dz": d[:, 2]},
    )
    write_csv_columns(
        out / "truth_interior.csv",
        {
            "x": xy[interior, 0],
            "y": xy[interior, 1],
            "dx": d[interior, 0],
            "dy": d[interior, 1],
            "dz": d[interior, 2],
        },
    )
    f = pair.field
    _write_json(
        out / "lobe.json",
        json_safe(
            {
                "command": "synth-lobe",
                "input": str(args.input),
                "centre_xy": list(map(float, f.centre_xy)),
                "radius_x_m": float(f.radius_x_m),
                "radius_y_m": float(f.radius_y_m),
                "azimuth_deg": float(f.azimuth_deg),
                "max_d_m": list(map(float, f.max_d_m)),
                "profile": "d = max_d (1 - r^2)^2 for r < 1 (elliptical radius), 0 outside",
                "seed": args.seed,
                "n_before": int(len(pair.before)),
                "n_after": int(len(pair.after)),
                "files": [
                    paths["before"].name,
                    paths["after"].name,
                    "truth.csv",
                    "truth_interior.csv",
                ],
            }
        ),
    )
    log.info(
        "lobe at (%.2f, %.2f), radii %.1f x %.1f m, max d %s m: %d before / %d after points; "
        "wrote %s",
        *f.centre_xy,
        f.radius_x_m,
        f.radius_y_m,
        list(map(float, f.max_d_m)),
        len(pair.before),
        len(pair.after),
        out,
    )
    return 0


@_run_synth_lobe.arguments
def _synth_lobe_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="real LAS/LAZ cloud to split and deform")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--max-dx", type=float, default=0.0, help="peak east displacement (m)")
    p.add_argument("--max-dy", type=float, default=-1.0, help="peak north displacement (m)")
    p.add_argument("--max-dz", type=float, default=-0.4, help="peak vertical displacement (m)")
    p.add_argument("--centre", type=float, nargs=2, metavar=("X", "Y"), help="lobe centre")
    p.add_argument(
        "--radius",
        type=_positive(float, "--radius"),
        nargs="+",
        metavar="R",
        help="lobe radius (m), or two radii RX RY (default: a third of the smaller extent)",
    )
    p.add_argument("--azimuth", type=float, default=0.0, help="azimuth of the RY axis (deg)")
    p.add_argument("--seed", type=int, default=0, help="random split seed")
    p.add_argument(
        "--truth-spacing",
        type=_positive(float, "--truth-spacing"),
        default=1.0,
        help="spacing of the truth.csv control grid (m)",
    )
