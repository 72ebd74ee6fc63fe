"""Commands not yet moved onto the application layer (being migrated: see app/).

Exit codes: 0 success, 2 bad input or options (one-line message; ``--debug`` for the
traceback), 1 unexpected failure, 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np

from .._version import __version__
from ..app.summaries import json_safe, slip_summary_lines, strip_rows
from ..core.errors import InvalidParameterError, SlipMapError
from ._args import ProgressBar as _ProgressBar
from ._args import command

log = logging.getLogger("slipmap")

# --------------------------------------------------------------------------- helpers


def _check_output_dir(directory: Path) -> None:
    """Fail early (before long work) when ``directory`` could not be created or written."""
    import os

    d = Path(directory).absolute()
    probe = d
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise SlipMapError(f"--out: {str(probe)!r} exists and is not a directory")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise SlipMapError(f"--out: directory {str(probe)!r} is not writable; choose another --out")


def _positive(kind: type, name: str):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not value > 0:
            raise argparse.ArgumentTypeError(f"{name} must be > 0, got {text}")
        return value

    return parse


def _write_json(path: Path, payload: dict) -> None:
    from ..core.io.atomic import write_text_atomic

    write_text_atomic(path, json.dumps(payload, indent=2, allow_nan=False) + "\n")


def _add_crs_argument(
    p: argparse.ArgumentParser,
    help: str = "CRS of the input when the file lacks one or declares a wrong one (e.g. "
    "EPSG:32611): it replaces the file's CRS (nothing is reprojected) and the outputs carry it",
) -> None:
    """The ``--crs`` option (parsed by :func:`parse_crs_option`), with a command's help."""
    p.add_argument("--crs", help=help)


def parse_crs_option(value):
    """The ``pyproj.CRS`` of a ``--crs`` value (``None`` when not given); a bad value is an
    :class:`InvalidParameterError` naming ``--crs``."""
    from ..core.io.crs import parse_crs

    try:
        return parse_crs(value)
    except InvalidParameterError as exc:
        raise InvalidParameterError(f"--crs: {exc}") from None


def read_cloud(path, crs=None):
    """One LAS/LAZ cloud, refused when empty. ``crs`` (``--crs``, a string or a CRS) replaces
    the file's CRS (for a file without one, or with a wrong one); nothing is reprojected and
    every output (LAS, GeoTIFF, GeoPackage, JSON) carries it."""
    from ..core.io.las import read_las

    crs = parse_crs_option(crs)  # before the read: a bad value fails at once
    cloud = read_las(path)
    if len(cloud) == 0:
        raise SlipMapError(f"{cloud.source}: the file has no points")
    if crs is not None:
        cloud.crs = crs
    return cloud


# --------------------------------------------------------------------------- planes


def _add_selection_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("point selection")
    g.add_argument(
        "--classes",
        type=int,
        nargs="+",
        metavar="C",
        help="keep only these ASPRS classifications (e.g. 6 for buildings)",
    )
    g.add_argument(
        "--exclude-classes",
        type=int,
        nargs="+",
        metavar="C",
        help="drop these classifications (default: 2, ground, when the file has classes and "
        "--classes is not given; the method removes ground first). Use --exclude-classes "
        "with no ground code, e.g. --exclude-classes 7, to keep ground.",
    )


def _add_plane_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "segmentation (defaults are estimated from the data; the values used are logged)"
    )
    g.add_argument(
        "--min-node-size",
        type=_positive(float, "--min-node-size"),
        metavar="M",
        help="smallest octree leaf edge, metres",
    )
    g.add_argument(
        "--planarity-threshold",
        type=_positive(float, "--planarity-threshold"),
        metavar="M",
        help="point-to-plane distance for the planarity test, metres",
    )
    g.add_argument(
        "--planarity-ratio",
        type=float,
        metavar="R",
        help="fraction of a leaf's points within the threshold for it to be planar "
        "(0-1, default 0.9)",
    )
    g.add_argument(
        "--angle-threshold",
        type=_positive(float, "--angle-threshold"),
        metavar="DEG",
        help="largest angle between normals of joined leaves, degrees",
    )
    g.add_argument(
        "--distance-threshold",
        type=_positive(float, "--distance-threshold"),
        metavar="M",
        help="largest centroid-to-plane distance of joined leaves, metres",
    )
    g.add_argument(
        "--min-points",
        type=_positive(int, "--min-points"),
        metavar="N",
        help="smallest number of points of a reported plane",
    )
    g.add_argument(
        "--min-leaf-points",
        type=_positive(int, "--min-leaf-points"),
        metavar="N",
        help="smallest number of points in a leaf for a plane fit (default 10)",
    )
    g.add_argument(
        "--backend",
        choices=("numpy", "opencl", "auto"),
        default="numpy",
        help="numpy (reference) or OpenCL via PyOpenCL; auto uses OpenCL when a "
        "device is available (default numpy)",
    )


def _plane_options(args: argparse.Namespace) -> dict:
    return dict(
        min_node_size_m=args.min_node_size,
        planarity_threshold_m=args.planarity_threshold,
        planarity_ratio=args.planarity_ratio,
        angle_threshold_deg=args.angle_threshold,
        distance_threshold_m=args.distance_threshold,
        min_plane_points=args.min_points,
        min_leaf_points=args.min_leaf_points,
        backend=args.backend,
    )


def _select_points(cloud, classes: Optional[Sequence[int]], exclude: Optional[Sequence[int]]):
    """Indices of the points kept by the class filters (see ``--classes``)."""
    import numpy as np

    n = len(cloud)
    cls = cloud.attributes.get("Classification")
    if cls is None or (classes is None and exclude is None and not np.any(cls == 2)):
        if classes:
            raise InvalidParameterError(
                "--classes: the input has no Classification dimension; remove --classes"
            )
        return np.arange(n)
    keep = np.ones(n, dtype=bool)
    if classes:
        keep &= np.isin(cls, np.asarray(classes))
    if exclude is not None:
        keep &= ~np.isin(cls, np.asarray(exclude))
    elif not classes:
        keep &= cls != 2
        log.info("excluding ground (class 2) points; pass --exclude-classes to change this")
    return np.flatnonzero(keep)


def run_planes_on_cloud(cloud, args, out_dir: Path, *, progress=None):
    """Segment ``cloud`` with the CLI's options and write planes.json and the labelled LAS.

    Returns ``(PlaneSet, labels of every input point (N,) int32, planes.json payload)``.
    """
    import numpy as np

    from ..core.io.atomic import ensure_output_dir
    from ..core.io.las import write_las
    from ..core.planes import segment_planes

    if len(cloud) == 0:
        raise SlipMapError(f"{cloud.source}: the file has no points")
    sel = _select_points(cloud, args.classes, args.exclude_classes)
    log.info("%d of %d points selected", sel.size, len(cloud))
    t0 = time.perf_counter()
    if progress is None:
        with _ProgressBar("planes", enabled=not args.quiet) as bar:
            planes = segment_planes(cloud.xyz[sel], progress=bar, **_plane_options(args))
    else:
        planes = segment_planes(cloud.xyz[sel], progress=progress, **_plane_options(args))
    runtime = time.perf_counter() - t0
    labels = np.full(len(cloud), -1, dtype=np.int32)
    labels[sel] = planes.labels
    params = planes.parameters.to_dict()
    for key, value in params.items():
        log.info("  %-24s %s", key, value)
    n_lab = int(np.count_nonzero(labels >= 0))
    log.info(
        "%d planes, %d of %d points labelled (%.1f %%), %.2f s",
        len(planes),
        n_lab,
        len(cloud),
        100.0 * n_lab / max(1, len(cloud)),
        runtime,
    )
    ensure_output_dir(out_dir)
    payload = {
        "planes": planes.to_records(),
        "n_points": int(len(cloud)),
        "n_selected": int(sel.size),
        "n_labelled": n_lab,
        "parameters": params,
        "runtime_s": round(runtime, 4),
        "input": str(cloud.source) if cloud.source else None,
        "crs": cloud.crs.to_wkt() if cloud.crs is not None else None,
        "slipmap_version": __version__,
    }
    _write_json(out_dir / "planes.json", payload)
    src = Path(cloud.source) if cloud.source else Path("points.las")
    suffix = ".laz" if src.suffix.lower() == ".laz" else ".las"
    las_out = out_dir / f"{src.stem}_planes{suffix}"
    write_las(las_out, cloud, extra_dims={"PlaneId": labels}, inputs=[cloud.source])
    log.info("wrote %s and %s", out_dir / "planes.json", las_out)
    return planes, labels, payload


# --------------------------------------------------------------------------- demo


@command("demo", "run the main job (fault slip) on an embedded case and compare with the truth")
def _run_demo(args: argparse.Namespace) -> int:
    from ..demo import run_planes_demo, run_slip_demo

    out = Path(args.out)
    _check_output_dir(out)
    run = run_slip_demo if args.job == "slip" else run_planes_demo
    with _ProgressBar("demo", enabled=not args.quiet) as bar:
        summary = run(out, seed=args.seed, progress=bar if not args.quiet else None)
    for line in summary.lines():
        log.warning("%s", line) if args.quiet else log.info("%s", line)
    return 0


@_run_demo.arguments
def _demo_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_output", help="output directory (default demo_output)")
    p.add_argument("--seed", type=int, default=2019, help="seed of the synthetic scene")
    p.add_argument(
        "--job",
        choices=("slip", "planes"),
        default="slip",
        help="slip: two epochs across a fault (default); planes: segmentation of one scene",
    )


# --------------------------------------------------------------------------- displacement


def read_epoch_pair(before, after, crs=None):
    """Both epochs' clouds and the second's xyz reprojected to the first one's CRS.

    ``crs`` (``--crs``) replaces the CRS of both files (for files without one, or with a wrong
    one): both are then taken to be in it and nothing is reprojected.
    """
    from ..core.io.crs import reproject_points, same_crs

    crs = parse_crs_option(crs)
    first, second = read_cloud(before, crs), read_cloud(after, crs)
    if crs is not None:
        return first, second, second.xyz
    xyz2 = second.xyz
    if first.crs is not None and second.crs is not None and not same_crs(first.crs, second.crs):
        log.info("reprojecting %s from %s to %s", second.source, second.crs.name, first.crs.name)
        xyz2 = reproject_points(second.xyz, second.crs, first.crs)
    elif (first.crs is None) != (second.crs is None):
        log.warning("only one epoch declares a CRS; both are taken to be in the same CRS")
    return first, second, xyz2


def _read_epochs(args):
    """Both epochs, the second reprojected to the first one's CRS when they differ."""
    first, second, xyz2 = read_epoch_pair(args.before, args.after, getattr(args, "crs", None))
    sel1 = _select_points(first, args.classes, args.exclude_classes)
    sel2 = _select_points(second, args.classes, args.exclude_classes)
    return first, second, sel1, sel2, first.xyz[sel1], xyz2[sel2]


def _pa_settings(args) -> dict:
    """Point-accuracy settings of both epochs from the flags, or from --pa-config."""
    from ..app.pointaccuracy import check_settings, load_config

    if getattr(args, "pa_config", None):
        return load_config(args.pa_config)
    model = args.pa or ("axis" if args.sigma_xyz is not None else "constant")
    s = {
        "model": model,
        "sigma": args.sigma,
        "sigma_xyz": args.sigma_xyz,
        "columns": args.sigma_columns,
        "trajectory": args.trajectory,
        "trajectory_accuracy": args.trajectory_accuracy,
        "scanner": args.scanner_spec,
        "scanner_position": args.scanner_position,
        "footprint": not args.no_footprint,
    }
    s = check_settings({k: v for k, v in s.items() if v is not None})
    return {"before": s, "after": s}


def _add_pa_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("point accuracy (Kusari et al. 2019, section II.E)")
    g.add_argument(
        "--pa",
        choices=("constant", "axis", "columns", "propagated"),
        help="model: constant (--sigma), axis (--sigma-xyz), columns (per-point "
        "SigmaX/Y/Z dimensions), propagated (trajectory + scanner, or TLS position)",
    )
    g.add_argument(
        "--sigma",
        type=_positive(float, "--sigma"),
        default=0.05,
        metavar="M",
        help="isotropic point accuracy, metres (default 0.05, as the study)",
    )
    g.add_argument(
        "--sigma-xyz",
        type=_positive(float, "--sigma-xyz"),
        nargs=3,
        metavar=("SX", "SY", "SZ"),
        help="per-axis point accuracy, metres",
    )
    g.add_argument(
        "--sigma-columns",
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="dimension names of per-point sigmas (default SigmaX SigmaY SigmaZ)",
    )
    g.add_argument(
        "--trajectory",
        metavar="FILE",
        help="platform trajectory: SBET (.sbet/.out) or CSV with named columns",
    )
    g.add_argument(
        "--trajectory-accuracy",
        metavar="FILE",
        help="trajectory accuracy: SMRMSG (.smrmsg) or CSV (attitude in arc-minutes)",
    )
    g.add_argument(
        "--scanner-spec",
        metavar="NAME|FILE",
        help="riegl-vz400, leica-als60, optech-orion, or a JSON specification",
    )
    g.add_argument(
        "--scanner-position",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="position of a static (TLS) scanner, map coordinates",
    )
    g.add_argument(
        "--no-footprint",
        action="store_true",
        help="leave out the beam-footprint (incidence) term of the propagated model",
    )
    g.add_argument(
        "--pa-config",
        metavar="FILE",
        help='JSON {"before": {...}, "after": {...}} with the keys model, sigma, '
        "sigma_xyz, columns, trajectory, trajectory_accuracy, scanner, "
        "scanner_position, footprint: one model per epoch (e.g. ALS then MLS)",
    )


#: --units values -> the dimension they read (stochasticmodel.UNIT_SOURCES)
_UNITS = {
    "auto": "auto",
    "point-source-id": "PointSourceId",
    "gps-time": "GpsTime",
    "none": "none",
}
_UNITS_SPELLING = {v: k for k, v in _UNITS.items()}


def _fixed_component(text: str) -> Dict[str, float]:
    """argparse type of ``--fixed-component NAME=SIGMA_M`` (bad syntax or names: exit 2)."""
    from ..app.stochasticmodel import fixed_components_or_error

    try:
        return fixed_components_or_error(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _add_stochastic_arguments(p: argparse.ArgumentParser) -> None:
    from ..app.stochasticmodel import DEFAULT_GPS_GAP_S, DEFAULT_MODEL, MODEL_HELP, MODELS

    g = p.add_argument_group(
        "stochastic model (the slip's σ; variance components estimated by REML)"
    )
    g.add_argument(
        "--stochastic-model",
        choices=MODELS,
        default=DEFAULT_MODEL,
        help="; ".join(f"{m}: {MODEL_HELP[m]}" for m in MODELS),
    )
    g.add_argument(
        "--units",
        choices=tuple(_UNITS),
        default="auto",
        help="acquisition unit of each point, per epoch, for the full model's rigid error per "
        "unit: auto = PointSourceId when an epoch has more than one distinct value, else "
        "none (default); point-source-id (ALS strips, MLS passes); gps-time = segments of the "
        "sorted GpsTime split at jumps larger than --gps-gap (separate passes or scans); none",
    )
    g.add_argument(
        "--gps-gap",
        type=_positive(float, "--gps-gap"),
        default=DEFAULT_GPS_GAP_S,
        metavar="S",
        help=f"with --units gps-time: a new unit starts where consecutive GPS times jump by "
        f"more than this, seconds (default {DEFAULT_GPS_GAP_S:g})",
    )
    g.add_argument(
        "--fixed-component",
        type=_fixed_component,
        action="append",
        metavar="NAME=SIGMA_M",
        help="hold a plane-level component fixed instead of estimating it (repeatable): "
        "plane, spatial, unit_before, unit_after (σ in metres) or spatial_range_m (metres), "
        "e.g. --fixed-component unit_after=0.003",
    )


def _stochastic_settings(args, first, second, sel1, sel2) -> dict:
    """estimate_slip's stochastic keywords from the options, and what was used (for the JSON)."""
    from ..app.stochasticmodel import cloud_units

    model = args.stochastic_model
    fixed: Dict[str, float] = {}
    for item in args.fixed_component or []:
        for name, value in item.items():
            if name in fixed:
                raise InvalidParameterError(f"--fixed-component: {name} is given twice")
            fixed[name] = value
    if fixed and model == "white":
        raise InvalidParameterError(
            "--fixed-component: the white model has no plane-level components; use "
            "--stochastic-model plane or full"
        )
    units = {"before": None, "after": None}
    used = {}
    how = _UNITS[args.units]
    if model != "full":
        if how not in ("auto", "none"):
            log.warning("--units %s is not used by --stochastic-model %s", args.units, model)
    else:
        for epoch, cloud, sel in (("before", first, sel1), ("after", second, sel2)):
            u = cloud_units(
                cloud,
                sel,
                how,
                gap_s=args.gps_gap,
                epoch=f"{epoch} epoch ({Path(str(cloud.source)).name})",
                option="--units",
                spelling=_UNITS_SPELLING,
            )
            units[epoch] = u.units
            used[epoch] = u.to_dict()
    return {
        "kwargs": {
            "stochastic_model": model,
            "unit_before": units["before"],
            "unit_after": units["after"],
        },
        "components": fixed or None,
        "record": {
            "units_option": args.units,
            **({"gps_gap_s": args.gps_gap} if args.units == "gps-time" else {}),
            **used,
        },
    }


def _window_rasters(windows, crs, out_dir: Path) -> List[str]:
    """windows_dx.tif and windows_dy.tif (north-up, one pixel per window centre)."""
    from ..core.errors import DependencyError
    from ..core.io.raster import write_geotiff

    half = 0.5 * windows.step_m
    files = []
    for name, band, sig in (
        ("dx", windows.dx, windows.sigma_dx),
        ("dy", windows.dy, windows.sigma_dy),
    ):
        try:
            write_geotiff(
                out_dir / f"windows_{name}.tif",
                np.stack([band, sig]).astype(np.float64),
                origin_xy=(windows.x0 - half, windows.y0 + half),
                pixel_size_m=windows.step_m,
                crs_wkt=crs.to_wkt() if crs is not None else None,
                band_names=[f"{name}_m (relative to the left side)", f"sigma_{name}_m"],
                metadata={"SLIPMAP_WINDOW_SIZE_M": f"{windows.window_size_m:g}"},
            )
            files.append(f"windows_{name}.tif")
        except DependencyError as exc:
            log.warning("no window GeoTIFF written: %s", exc)
            break
    return files


def _displacement_outputs(
    result, trace, crs, out_dir: Path, *, strips=None, payload=None
) -> List[str]:
    """Matched-plane GeoPackage, residual and normal plots, HTML page; returns file names.

    ``payload``: the JSON summary written (default ``result.to_dict()``), for the report."""
    from ..app.summaries import plane_fields, stochastic_tables
    from ..core.errors import DependencyError

    files: List[str] = []
    try:
        from ..core.io.vector import VectorLayer, write_gpkg_layers

        layers = []
        for side in (result.left, result.right):
            pb, m = side.planes_before, side.matches
            layers.append(
                VectorLayer(
                    name=f"planes_{side.side}",
                    geometry_type="Point",
                    geometries=[pb.centroids[i] for i in m.before],
                    fields={
                        "plane_before": m.before.astype(np.int64),
                        "plane_after": m.after.astype(np.int64),
                        "n_points": pb.n_points[m.before].astype(np.int64),
                        "normal_x": pb.normals[m.before, 0],
                        "normal_y": pb.normals[m.before, 1],
                        "normal_z": pb.normals[m.before, 2],
                        "angle_deg": np.degrees(m.angle_rad),
                        "distance_m": m.distance_m,
                        **plane_fields(side),
                    },
                )
            )
        if result.tiles:
            tiles = result.tiles
            layers.append(
                VectorLayer(
                    name="tiles",
                    geometry_type="Polygon",
                    geometries=[
                        np.array(
                            [
                                [t.bounds[0], t.bounds[1]],
                                [t.bounds[2], t.bounds[1]],
                                [t.bounds[2], t.bounds[3]],
                                [t.bounds[0], t.bounds[3]],
                            ]
                        )
                        for t in tiles
                    ],
                    fields={
                        "side": np.array([t.side for t in tiles], dtype=object),
                        "n_planes": np.array([t.n_planes for t in tiles], dtype=np.int64),
                        "dx": np.array([t.displacement[0] for t in tiles]),
                        "dy": np.array([t.displacement[1] for t in tiles]),
                        "dz": np.array([t.displacement[2] for t in tiles]),
                        "sigma_dx": np.array([np.sqrt(t.covariance[0, 0]) for t in tiles]),
                        "sigma_dy": np.array([np.sqrt(t.covariance[1, 1]) for t in tiles]),
                        "sigma_dz": np.array([np.sqrt(t.covariance[2, 2]) for t in tiles]),
                        "status": np.array([t.status for t in tiles], dtype=object),
                    },
                )
            )
        if strips:
            from ..core.fault import point_at_chainage

            layers.append(
                VectorLayer(
                    name="strips",
                    geometry_type="Point",
                    geometries=[point_at_chainage(trace, st.along_centre_m) for st in strips],
                    fields={
                        "side": np.array([st.side for st in strips], dtype=object),
                        "along_start_m": np.array([st.along_start_m for st in strips]),
                        "along_end_m": np.array([st.along_end_m for st in strips]),
                        "fault_parallel": np.array([st.fault_parallel for st in strips]),
                        "sigma_fp": np.array([st.sigma_fault_parallel for st in strips]),
                        "n_planes": np.array([st.n_planes for st in strips], dtype=np.int64),
                        "status": np.array([st.status for st in strips], dtype=object),
                    },
                )
            )
        layers.append(
            VectorLayer(
                name="fault_trace",
                geometry_type="LineString",
                geometries=list(trace.parts),
                fields={"part": np.arange(len(trace.parts), dtype=np.int64)},
            )
        )
        write_gpkg_layers(out_dir / "displacement.gpkg", layers, crs=crs)
        files.append("displacement.gpkg")
    except DependencyError as exc:
        log.warning("no GeoPackage written: %s", exc)
    try:
        from ..core.report import plot_normals_polar, plot_residual_histograms, write_html_report

        res = {f"{s.side} before": s.rigid.residuals_before for s in (result.left, result.right)}
        res.update(
            {f"{s.side} after": s.rigid.residuals_after for s in (result.left, result.right)}
        )
        plot_residual_histograms(out_dir / "residuals.png", res, title="Point-to-plane residuals")
        plot_normals_polar(
            out_dir / "normals.png",
            {
                s.side: s.planes_before.normals[s.matches.before]
                for s in (result.left, result.right)
            },
            title="Matched plane normals",
        )
        from ..core.report import plot_plane_residual_polar

        plot_plane_residual_polar(
            out_dir / "plane_residuals.png",
            {
                s.side: (s.planes_before.normals[s.matches.before], s.plane_mean_residual_m)
                for s in (result.left, result.right)
            },
        )
        files += ["residuals.png", "normals.png", "plane_residuals.png"]
        if strips:
            from ..core.report import plot_strip_profile

            plot_strip_profile(
                out_dir / "strips.png",
                [st.along_centre_m for st in strips],
                [st.fault_parallel for st in strips],
                [st.sigma_fault_parallel for st in strips],
                [st.side for st in strips],
            )
            files.append("strips.png")
        summary = payload if payload is not None else json_safe(result.to_dict())
        tables = {"relative (right - left), m": summary["relative"]}
        for side in ("left", "right"):
            tables[f"{side} side"] = {
                k: v for k, v in summary[side].items() if not isinstance(v, (list, dict))
            }
        tables.update(stochastic_tables(summary))
        if "reference" in summary:
            tables["against the reference slip"] = summary["reference"]
        images = [f for f in files if f.endswith(".png")]
        write_html_report(out_dir / "report.html", "SlipMap displacement", tables, images)
        files.append("report.html")
    except DependencyError as exc:
        log.warning("no figures written: %s", exc)
    return files


@command("displacement", "fault slip between two epochs by planar registration on each side")
def _run_displacement(args: argparse.Namespace) -> int:
    from ..core.displacement import estimate_slip
    from ..core.io.atomic import ensure_output_dir
    from ..core.io.vector import read_fault_trace

    out = Path(args.out)
    _check_output_dir(out)
    from ..app.pointaccuracy import covariances

    first, second, sel1, sel2, before, after = _read_epochs(args)
    stoch = _stochastic_settings(args, first, second, sel1, sel2)
    pa = _pa_settings(args)
    sigma_b = covariances(first, sel1, pa["before"])
    sigma_a = covariances(second, sel2, pa["after"])
    trace = read_fault_trace(args.fault, target_crs=first.crs)
    t0 = time.perf_counter()
    plane_opts = {k: v for k, v in _plane_options(args).items() if v is not None}
    match_opts = {
        "angle_threshold_deg": args.match_angle,
        "distance_threshold_m": args.match_distance,
    }
    with _ProgressBar("displacement", enabled=not args.quiet) as bar:
        result = estimate_slip(
            before,
            after,
            trace,
            buffer_m=args.buffer,
            sigma_before=sigma_b,
            sigma_after=sigma_a,
            plane_options=plane_opts,
            match_options=match_opts,
            tile_size_m=args.tile_size,
            combine=args.combine,
            progress=bar,
            components=stoch["components"],
            **stoch["kwargs"],
        )
        common = dict(
            buffer_m=args.buffer,
            sigma_before=sigma_b,
            sigma_after=sigma_a,
            plane_options=plane_opts,
            match_options=match_opts,
            **stoch["kwargs"],
        )
        strips = windows = None
        if args.strip_width:
            from ..core.displacement import strip_profile

            strips = strip_profile(
                before, after, trace, result, strip_width_m=args.strip_width, **common
            )
        if args.window_size:
            from ..core.displacement import window_field

            windows = window_field(
                before,
                after,
                trace,
                result,
                window_size_m=args.window_size,
                window_step_m=args.window_step or args.window_size / 4,
                **common,
            )
    runtime = time.perf_counter() - t0
    payload = result.to_dict()
    payload["parameters"].update(
        {
            "point_accuracy": pa,
            "before": str(args.before),
            "after": str(args.after),
            "fault": str(args.fault),
            "acquisition_unit_sources": stoch["record"],
        }
    )
    payload["runtime_s"] = round(runtime, 3)
    payload["slipmap_version"] = __version__
    ensure_output_dir(out)
    if args.reference_slip is not None:
        payload["reference"] = result.reference_comparison(args.reference_slip)
        ref = payload["reference"]
        log.info(
            "against the reference slip %.4f m: ΔD %+.4f m, scale %.3f, relative scale %.3f",
            ref["reference_slip"],
            ref["delta_displacement"],
            ref["scale"],
            ref["relative_scale"],
        )
    if strips is not None:
        payload["strips"] = strip_rows(strips)
    payload = json_safe(payload)  # NaN (e.g. a component's sd) -> null: standard JSON
    _write_json(out / "displacement.json", payload)
    files = _displacement_outputs(result, trace, first.crs, out, strips=strips, payload=payload)
    if windows is not None:
        files += _window_rasters(windows, first.crs, out)
    for line in slip_summary_lines(payload):
        log.info("%s", line)
    log.info("wrote %s", ", ".join(["displacement.json"] + files))
    return 0


@_run_displacement.arguments
def _displacement_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("before", help="first epoch, LAS/LAZ")
    p.add_argument("after", help="second epoch, LAS/LAZ (reprojected to the first's CRS)")
    p.add_argument("--fault", required=True, help="fault trace: any OGR line file, any CRS")
    p.add_argument("--out", required=True, help="output directory")
    _add_crs_argument(
        p,
        "CRS of both epochs when the files lack one or declare a wrong one (e.g. "
        "EPSG:32611): the trace is reprojected into it and the outputs carry it",
    )
    p.add_argument(
        "--buffer",
        type=_positive(float, "--buffer"),
        default=10.0,
        metavar="M",
        help="points closer than this to the trace are left out (default 10 m)",
    )
    g = p.add_argument_group("tiles, strips and windows")
    g.add_argument(
        "--tile-size",
        type=_positive(float, "--tile-size"),
        metavar="M",
        help="extract planes in square tiles of this size (the study: 20-100 m)",
    )
    g.add_argument(
        "--combine",
        choices=("joint", "tiles"),
        default="joint",
        help="joint: one adjustment per side (default); tiles: covariance-weighted "
        "mean of per-tile adjustments",
    )
    g.add_argument(
        "--strip-width",
        type=_positive(float, "--strip-width"),
        metavar="M",
        help="profile of fault-parallel displacement in strips along the trace",
    )
    g.add_argument(
        "--window-size",
        type=_positive(float, "--window-size"),
        metavar="M",
        help="moving windows of this size: windows_dx.tif, windows_dy.tif",
    )
    g.add_argument(
        "--window-step",
        type=_positive(float, "--window-step"),
        metavar="M",
        help="step of the moving windows (default a quarter of the size)",
    )
    g.add_argument(
        "--reference-slip",
        type=float,
        metavar="M",
        help="independent right-lateral slip (e.g. an alinement array), metres: "
        "adds the study's Table X figures (scale, relative scale) to the summary",
    )
    _add_pa_arguments(p)
    _add_stochastic_arguments(p)
    g = p.add_argument_group("plane matching")
    g.add_argument(
        "--match-angle",
        type=_positive(float, "--match-angle"),
        default=3.0,
        metavar="DEG",
        help="largest angle between matched normals (default 3)",
    )
    g.add_argument(
        "--match-distance",
        type=_positive(float, "--match-distance"),
        default=0.5,
        metavar="M",
        help="largest centroid-to-plane distance of matched planes, "
        "above the largest expected displacement (default 0.5 m)",
    )
    _add_selection_arguments(p)
    _add_plane_arguments(p)
