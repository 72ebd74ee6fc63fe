"""Job ``displacement``: fault slip between two epochs by planar registration on each side of a
fault trace (Kusari et al. 2019, sections II-IV).

The options are declared once in :data:`SPEC` (the CLI's ``slipmap displacement``, QGIS's
``slipmap:displacement``, the PDAL ``displacement`` stage); :func:`compute` is the
computation on arrays (used by PDAL), :func:`run` reads both epochs and the trace, selects
the points, computes and writes ``displacement.json``, the GeoPackage, the window rasters,
the figures and ``report.html`` through an :class:`~.outputs.OutputPlan`.

The layers' columns (:func:`plane_columns`, :func:`tile_columns`, :func:`strip_columns`,
:func:`window_bands`) and the summary (:func:`summary_payload`) carry the motions in the one
sign convention of :mod:`.signs` (``right_lateral`` + = dextral, ``opening`` + = apart,
``dz`` + = up), so every face writes the same attributes with the same signs.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Dict, List, Mapping, Optional, Tuple

import numpy as np

from .._version import __version__
from ..core.errors import SlipMapError
from . import pointaccuracy as pa
from .inputs import (
    cloud_option,
    crs_option,
    out_dir_option,
    read_epoch_pair,
    select_points,
    selection_options,
)
from .job import JobResult, Progress, plotting, scaled
from .options import JobSpec, Option, OptionError
from .outputs import OutputPlan
from .planes import core_kwargs as plane_kwargs
from .planes import plane_options
from .stochasticmodel import check_stochastic, random_tilt_of, stochastic_options, units_for_job
from .summaries import json_safe, slip_summary_lines, stochastic_tables, strip_rows
from .tiled import scale_options

log = logging.getLogger("slipmap.app")

CITATION = (
    "Kusari, Glennie, Brooks and Ericksen (2019), Precise registration of laser mapping data "
    "by planar feature extraction for deformation monitoring, IEEE TGRS 57(6): sections II-III "
    "(tiles, strips: Fig. 5; windows: Fig. 11)"
)
_TSW = "tiles, strips and windows"
_MATCH = "plane matching"
#: bands of the windows GeoTIFF (``windows.tif``; QGIS's WINDOWS output)
#: (each window's own motion; ``right_lateral_m`` + = dextral on both sides, see :mod:`.signs`)
WINDOW_BANDS = (
    "right_lateral_m",
    "dx_m",
    "dy_m",
    "dz_m",
    "sigma_dx_m",
    "sigma_dy_m",
    "n_planes",
    "sigma_right_lateral_m",
)


def _length(key, help_, label, *, group=_TSW, **kw) -> Option:
    return Option(
        key, "float", help_, label=label, minimum=0, exclusive=True, group=group, metavar="M", **kw
    )


def _pa_rows() -> Tuple[Option, ...]:
    """The point-accuracy options; in PDAL a per-epoch σ and per-point σ dimensions only (the
    models that read files need the whole cloud)."""
    rows = []
    for o in pa.pa_options():
        pdal = "sigma_dimensions" if o.key == "sigma_columns" else None
        rows.append(replace(o, pdal=pdal))
    return (
        *rows,
        Option(
            "pa_model_after",
            "choice",
            "point-accuracy model of the after epoch when it differs from the before epoch's",
            label="Point accuracy, after",
            choices=pa.MODELS,
            cli=None,
            qgis=None,  # QGIS shows one model per epoch (PA_BEFORE, PA_AFTER)
            pdal=None,
            unset_text="the before epoch's",
        ),
        Option(
            "sigma_before_m",
            "float",
            "point accuracy of the first epoch, 1 sigma (m)",
            label="Sigma, before epoch (m)",
            default=None,
            minimum=0,
            exclusive=True,
            cli=None,
            qgis=None,
            pdal="sigma_before",
            unset_text="0.05",
        ),
        Option(
            "sigma_after_m",
            "float",
            "point accuracy of the second epoch, 1 sigma (m)",
            label="Sigma, after epoch (m)",
            default=None,
            minimum=0,
            exclusive=True,
            cli=None,
            qgis=None,
            pdal="sigma_after",
            unset_text="0.05",
        ),
    )


def _output(key: str, help_: str, label: str) -> Option:
    """An output (named in the output folder on the CLI; QGIS and PDAL map their own)."""
    return Option(key, "path", help_, label=label, role="output", cli=None, qgis=None, pdal=None)


def _check(opts: Mapping[str, Any]) -> None:
    """Cross-option checks of :data:`SPEC` (every face, before anything is read)."""
    from .tiled import check_scale, is_tiled

    check_stochastic(opts)
    if opts.get("combine") == "tiles" and opts.get("tile_size_m") is None:
        raise OptionError(
            "combine",
            "tiles combines per-tile adjustments: give {tile_size_m} too, or combine joint",
            also=("tile_size_m",),
        )
    if opts.get("window_step_m") is not None and opts.get("window_size_m") is None:
        raise OptionError(
            "window_step_m",
            "is the step of the moving windows: give {window_size_m} too",
            also=("window_size_m",),
        )
    _pa_check(opts)
    check_scale(opts)
    if is_tiled(opts, "before", "after"):
        check_tiled(opts)  # strips, windows, per-point models, GpsTime units refused


def _pa_check(opts: Mapping[str, Any]) -> None:
    o = _pa_opts(opts)
    pa.check_options(o)
    if o.get("pa_model_after") and not o.get("pa_config"):
        try:
            pa.check_options({**o, "pa_model": o["pa_model_after"]})
        except OptionError as exc:
            key = "pa_model_after" if exc.key == "pa_model" else exc.key
            raise OptionError(key, f"(after epoch) {exc.text}", also=exc.also) from None


def _pa_opts(opts: Mapping[str, Any]) -> Dict[str, Any]:
    """The options with the model implied by per-point σ dimensions (PDAL's
    ``sigma_dimensions``; ``--sigma-columns`` without ``--pa``)."""
    o = dict(opts)
    if o.get("pa_model") is None and o.get("sigma_columns") and o.get("sigma_xyz_m") is None:
        o["pa_model"] = "columns"
    return o


SPEC = JobSpec(
    name="displacement",
    title="Fault slip (displacement)",
    description=(
        "Relative displacement across a fault between two LiDAR epochs: planes are extracted "
        "on each side of the trace, matched between epochs and a rigid least-squares "
        "adjustment (point-to-plane, Gauss-Helmert) gives each side's displacement; the "
        "right-lateral slip of the right side against the left (+ = dextral, whatever "
        "direction the trace was digitised in) comes with its σ under the stochastic model."
    ),
    options=(
        cloud_option("before", "first epoch, LAS/LAZ in a projected CRS (metres)", "Before epoch"),
        cloud_option(
            "after",
            "second epoch, LAS/LAZ (reprojected to the first's CRS when they differ)",
            "After epoch",
        ),
        Option(
            "fault",
            "path",
            "fault trace: any OGR line file, any CRS (reprojected to the epochs' CRS)",
            label="Fault trace",
            required=True,
            role="input",
            cli="--fault",
            qgis=None,  # QGIS gives a line layer (the algorithm reads it)
            pdal=None,  # PDAL gives the trace as WKT or a file (the stage reads it)
            metavar="FILE",
        ),
        out_dir_option("output folder (created when missing)"),
        crs_option(
            "CRS of both epochs when the files lack one or declare a wrong one (e.g. "
            "EPSG:32611): the trace is reprojected into it and the outputs carry it"
        ),
        Option(
            "buffer_m",
            "float",
            "points closer than this to the trace are left out, metres (default 10, as the study)",
            label="Buffer around the trace (m)",
            default=10.0,
            minimum=0,
            metavar="M",
        ),
        _length(
            "tile_size_m",
            "extract planes in square tiles of this size, metres (the study: 20-100 m)",
            "Tile size (m)",
            unset_text="none",
        ),
        Option(
            "combine",
            "choice",
            "joint: one adjustment per side on all matched planes (the study's approach); "
            "tiles: information-weighted mean of the per-tile adjustments",
            label="Combine tiles",
            default="joint",
            choices=("joint", "tiles"),
            group=_TSW,
            advanced=True,
        ),
        _length(
            "strip_width_m",
            "profile of each side's right-lateral motion in strips of this width along the "
            "trace, metres (the study: 50-100 m)",
            "Strip width (m)",
            pdal=None,
            unset_text="none",
        ),
        _length(
            "window_size_m",
            "moving-window displacement maps with windows of this size, metres (the study: 400 m)",
            "Moving-window size (m)",
            pdal=None,
            unset_text="none",
        ),
        _length(
            "window_step_m",
            "step of the moving windows, metres (default a quarter of the size)",
            "Moving-window step (m; default size / 4)",
            pdal=None,
            advanced=True,
            unset_text="size / 4",
        ),
        Option(
            "reference_slip_m",
            "float",
            "independent right-lateral slip (e.g. an alinement array), metres, positive "
            "dextral: adds the study's Table X figures (scale, relative scale) to the summary",
            label="Reference right-lateral slip (m)",
            group=_TSW,
            advanced=True,
            pdal=None,
            metavar="M",
            unset_text="none",
        ),
        *_pa_rows(),
        *stochastic_options(),
        Option(
            "match_angle_deg",
            "float",
            "largest angle between matched normals, degrees",
            label="Match angle (degrees)",
            default=3.0,
            minimum=0,
            exclusive=True,
            group=_MATCH,
            advanced=True,
            metavar="DEG",
        ),
        Option(
            "match_distance_m",
            "float",
            "largest centroid-to-plane distance of matched planes, metres, above the largest "
            "expected displacement",
            label="Match distance (m)",
            default=0.5,
            minimum=0,
            exclusive=True,
            group=_MATCH,
            advanced=True,
            metavar="M",
        ),
        Option(
            "transfer_planes",
            "bool",
            "planes of one epoch without a match are observed by the other epoch's points that "
            "lie on them (a sparse airborne epoch beside a mobile one: walls it cannot segment) "
            "and adjusted like matched planes; whole sides only, not tiles",
            label="Transferred planes",
            default=True,
            group=_MATCH,
            advanced=True,
        ),
        *selection_options(ground_default=True),
        *plane_options(),
        *scale_options(tile_option=False),
        _output("summary", "summary (displacement.json)", "Summary"),
        _output("report", "HTML report (report.html)", "Report"),
        _output("layers", "matched planes, tiles, strips, trace (displacement.gpkg)", "Layers"),
        _output("windows", "moving windows, 8 bands (windows.tif)", "Moving windows"),
        _output("windows_dx", "moving windows dx and its σ (windows_dx.tif)", "Windows dx"),
        _output("windows_dy", "moving windows dy and its σ (windows_dy.tif)", "Windows dy"),
        _output("tiles", "tiles layer", "Tiles"),
        _output("strips", "strips layer", "Strips"),
    ),
    check=_check,
    citation=CITATION,
)

#: the output keys :func:`run` writes (figures beside the report: see :func:`_figure_names`)
FILE_KEYS = ("summary", "layers", "windows", "windows_dx", "windows_dy", "report")
FIGURES = ("residuals", "normals", "plane_residuals", "strips")


# --------------------------------------------------------------------------- settings


def point_accuracy(opts: Mapping[str, Any]) -> Dict[str, Dict[str, Any]]:
    """``{"before": settings, "after": settings}`` of :mod:`.pointaccuracy` from the options
    (the ``pa_config`` file's when given)."""
    o = _pa_opts(opts)
    both = pa.settings_from_options(o)
    if o.get("pa_config"):
        return both
    out = {}
    for epoch in ("before", "after"):
        s = dict(both[epoch])
        if epoch == "after" and o.get("pa_model_after"):
            s["model"] = o["pa_model_after"]
        if o.get(f"sigma_{epoch}_m") is not None:
            s["sigma"] = o[f"sigma_{epoch}_m"]
        out[epoch] = pa.check_settings(s)
    return out


def core_options(opts: Mapping[str, Any]) -> Dict[str, Any]:
    """The keywords every core call of the job shares (buffer, plane and match options,
    stochastic model)."""
    return {
        "buffer_m": opts["buffer_m"],
        "plane_options": plane_kwargs(opts),
        "match_options": {
            "angle_threshold_deg": opts["match_angle_deg"],
            "distance_threshold_m": opts["match_distance_m"],
        },
        "stochastic_model": opts["stochastic_model"],
    }


def fixed_components(opts: Mapping[str, Any]) -> Optional[Dict[str, float]]:
    return check_stochastic(opts) or None


@dataclass(frozen=True)
class SlipRun:
    """What :func:`compute` gives: the slip, the strips and the windows (None when not asked
    for); ``tile_planes``: with a tile size and ``combine="joint"`` on one file per epoch,
    the joint adjustment of the planes extracted tile by tile (the tiles' own estimate, which
    tiled inputs give as their headline; the headline here is the whole side's)."""

    result: Any
    strips: Optional[Tuple[Any, ...]] = None
    windows: Optional[Any] = None
    tile_planes: Optional[Any] = None


def headline_text(parameters: Mapping[str, Any], *, tiled_inputs: bool = False) -> str:
    """One sentence saying which estimate the headline slip is, from the result's
    ``parameters`` (``combine``, ``tile_size_m``): the log, the JSON (``estimate``) and the
    report say it in the same words.

    The headline depends on the planes it adjusts: planes extracted over the whole side
    (one file per epoch, with or without tiles: tiles are then a map beside it), planes
    extracted tile by tile (tiled inputs or Dask: no plane spans two tiles, a different set of
    planes), or the tiles' adjustments combined (``combine`` tiles)."""
    tile = parameters.get("tile_size_m")
    if parameters.get("combine") == "tiles" and tile is not None:
        return (
            f"headline: information-weighted mean of the {tile:g} m tiles' adjustments "
            "(combine tiles), a different estimate from the joint adjustment of each side"
        )
    if tiled_inputs:
        return (
            f"headline: one adjustment per side of the planes extracted tile by tile "
            f"({tile:g} m tiles, tiled inputs: no plane spans two tiles); a one-file run "
            "extracts planes over each whole side and may differ within its sigma"
        )
    text = "headline: one adjustment per side of the planes extracted over the whole side"
    if tile is not None:
        text += (
            f"; the {tile:g} m tiles are a map beside it (planes extracted per tile) and do "
            "not change it"
        )
    return text


def compute(
    before: np.ndarray,
    after: np.ndarray,
    trace,
    opts: Mapping[str, Any],
    *,
    sigma_before=0.05,
    sigma_after=0.05,
    unit_before: Optional[np.ndarray] = None,
    unit_after: Optional[np.ndarray] = None,
    windows: bool = True,
    progress: Optional[Progress] = None,
    unit_time_before: Optional[np.ndarray] = None,
    unit_time_after: Optional[np.ndarray] = None,
) -> SlipRun:
    """The slip, strips and windows of two epochs' points.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) float64
        The selected points of each epoch in one projected CRS, metres.
    trace : FaultTrace
        In that CRS.
    opts
        :data:`SPEC`'s options, parsed.
    sigma_before, sigma_after
        Point accuracy: scalar, (3,), (N, 3) or (N, 3, 3), metres (see
        :func:`point_accuracy` and :func:`.pointaccuracy.covariances`).
    unit_before, unit_after : (N1,), (N2,) int, optional
        Acquisition units (full model).
    unit_time_before, unit_time_after : (N1,), (N2,) float64, optional
        Their points' GpsTime (seconds): the units' error may drift along it
        (:mod:`..core.unit_drift`).
    windows
        Compute the moving windows when ``window_size_m`` is set (QGIS only when its output
        is asked for).
    """
    from ..core.displacement import estimate_slip, strip_profile, window_field

    common = dict(
        core_options(opts),
        sigma_before=sigma_before,
        sigma_after=sigma_after,
        unit_before=unit_before,
        unit_after=unit_after,
        unit_time_before=unit_time_before,
        unit_time_after=unit_time_after,
    )
    tied = bool(opts.get("unit_contrasts", True))  # the slip's adjustments only
    want_strips = opts.get("strip_width_m") is not None
    want_windows = windows and opts.get("window_size_m") is not None
    tile = opts.get("tile_size_m")
    combine = opts.get("combine") or "joint"
    # with tiles and the joint adjustment, the tiles are a map: the headline stays the whole
    # side's adjustment (tiles cut planes at their borders: another set of planes, another
    # estimate, e.g. 16.37 ± 2.97 mm against 16.32 ± 4.03 mm on the demo with 50 m tiles)
    map_tiles = tile is not None and combine == "joint"
    if tile is not None:  # a budget on the tiles before any is segmented (issue #31)
        from .resources import check_point_tiles

        check_point_tiles("tile_size_m", (before, after), tile)
    parts = iter(_phase_progress(progress, before, opts, map_tiles, want_strips, want_windows))
    result = estimate_slip(
        before,
        after,
        trace,
        tile_size_m=None if map_tiles else tile,
        combine=combine,
        components=fixed_components(opts),
        progress=next(parts),
        transfer_planes=bool(opts.get("transfer_planes")),
        random_tilt=random_tilt_of(opts),
        unit_contrasts=tied,
        **common,
    )
    tile_planes = None
    if map_tiles:
        tile_planes = estimate_slip(
            before,
            after,
            trace,
            tile_size_m=tile,
            combine="joint",
            components=fixed_components(opts),
            progress=next(parts),
            random_tilt=random_tilt_of(opts),
            **common,
        )
        result = replace(
            result,
            tiles=tile_planes.tiles,
            parameters={**result.parameters, "tile_size_m": tile_planes.parameters["tile_size_m"]},
        )
    strips = wf = None
    if want_strips:
        strips = strip_profile(
            before,
            after,
            trace,
            result,
            strip_width_m=opts["strip_width_m"],
            progress=next(parts),
            **common,
        )
    if want_windows:
        wf = window_field(
            before,
            after,
            trace,
            result,
            window_size_m=opts["window_size_m"],
            window_step_m=opts.get("window_step_m") or opts["window_size_m"] / 4,
            progress=next(parts),
            **common,
        )
    return SlipRun(result, strips, wf, tile_planes)


def _phase_progress(progress, before, opts, map_tiles: bool, want_strips: bool, want_windows: bool):
    """One progress callback per phase (slip, the tile map, strips, windows), each its share
    of the bar by its cost (``core.displacement``'s cost model; the tile map is a second
    adjustment of each side, costed as the first), so the bar matches the log: with 2115
    windows the window loop holds most of the bar, not its last sixth."""
    from ..core.displacement import STRIPS_COST, window_count, window_progress_shares

    costs = [1.0]
    if map_tiles:
        costs.append(1.0)
    if want_strips:
        costs.append(STRIPS_COST)
    if want_windows:
        step = opts.get("window_step_m") or opts["window_size_m"] / 4
        n = window_count(np.asarray(before)[:, :2], opts["window_size_m"], step)
        costs.append(window_progress_shares(n)[2])
    total, edge, out = sum(costs), 0.0, []
    for c in costs:
        out.append(scaled(progress, edge / total, (edge + c) / total))
        edge += c
    return out


# --------------------------------------------------------------------------- columns


def plane_columns(side) -> Dict[str, np.ndarray]:
    """Attributes of a side's matched planes (one row per match, at the before-epoch plane
    centroid): ids, points, unit normal, match angle and distance, and the stochastic model's
    per-plane weight, w-test, predicted offset and misclosure."""
    from .summaries import plane_fields

    pb, m = side.planes_before, side.matches
    return {
        "side": np.array([side.side] * len(m), dtype=object),
        "plane_before": m.before.astype(np.int64),
        "plane_after": m.after.astype(np.int64),
        "n_points": pb.n_points[m.before].astype(np.int64),
        "normal_x": pb.normals[m.before, 0],
        "normal_y": pb.normals[m.before, 1],
        "normal_z": pb.normals[m.before, 2],
        "angle_deg": np.degrees(m.angle_rad),
        "distance_m": np.asarray(m.distance_m, dtype=np.float64),
        **plane_fields(side),
    }


def _signed_columns(motions, displacements, covariances) -> Dict[str, np.ndarray]:
    """The signed columns of one-side motions (tiles, strips): ``right_lateral``,
    ``opening``, ``dz``, ``dx``, ``dy`` (metres) and their σ; NaN where ``motions[k]`` is
    None (not adjusted)."""
    n = len(motions)
    d = np.asarray(displacements, dtype=np.float64).reshape(n, 3)
    c = np.asarray(covariances, dtype=np.float64).reshape(n, 3, 3)
    with np.errstate(invalid="ignore"):
        s = np.sqrt(np.abs(np.diagonal(c, axis1=1, axis2=2)))
    ok = np.array([m is not None for m in motions], dtype=bool)
    d[~ok] = np.nan
    s[~ok] = np.nan
    out = {
        k: np.array([m[k] if m is not None else np.nan for m in motions], dtype=np.float64)
        for k in ("right_lateral", "sigma_right_lateral", "opening", "sigma_opening")
    }
    out.update(
        dz=d[:, 2], sigma_dz=s[:, 2], dx=d[:, 0], sigma_dx=s[:, 0], dy=d[:, 1], sigma_dy=s[:, 1]
    )
    return out


def tile_columns(result) -> Dict[str, np.ndarray]:
    """Attributes of the tiles: each tile's own motion in the sign convention of
    :mod:`.signs` (``right_lateral`` + = dextral on either side, ``opening`` + = away from
    the trace, ``dz`` + = up, ``dx``, ``dy`` + = east, north) and σ, metres; NaN for a tile
    that was not adjusted (its ``status`` says why)."""
    from . import signs

    tiles = result.tiles
    motions = [
        signs.motion(t.displacement, t.covariance, result.strike_rad, t.side)
        if t.adjusted
        else None
        for t in tiles
    ]
    return {
        "side": np.array([t.side for t in tiles], dtype=object),
        "ix": np.array([t.ix for t in tiles], dtype=np.int64),
        "iy": np.array([t.iy for t in tiles], dtype=np.int64),
        "n_planes": np.array([t.n_planes for t in tiles], dtype=np.int64),
        **_signed_columns(
            motions,
            [t.displacement for t in tiles],
            [t.covariance for t in tiles],
        ),
        "status": np.array([t.status for t in tiles], dtype=object),
    }


def tile_rings(result) -> List[np.ndarray]:
    """(4, 2) corners of every tile (map units)."""
    out = []
    for t in result.tiles:
        x0, y0, x1, y1 = (float(v) for v in t.bounds)
        out.append(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))
    return out


def strip_columns(strips) -> Dict[str, np.ndarray]:
    """Attributes of the strips: chainage range, planes, and the strip's own motion in the
    sign convention (as :func:`tile_columns`; a left and a right strip at one chainage add up
    to the local relative slip), metres."""
    from . import signs

    return {
        "side": np.array([st.side for st in strips], dtype=object),
        "along_start_m": np.array([st.along_start_m for st in strips], dtype=np.float64),
        "along_end_m": np.array([st.along_end_m for st in strips], dtype=np.float64),
        "along_centre_m": np.array([st.along_centre_m for st in strips], dtype=np.float64),
        "n_planes": np.array([st.n_planes for st in strips], dtype=np.int64),
        **_signed_columns(
            [signs.strip_motion(st) for st in strips],
            [st.displacement for st in strips],
            [st.covariance for st in strips],
        ),
        "status": np.array([st.status for st in strips], dtype=object),
    }


def strip_points(strips, trace) -> np.ndarray:
    """(K, 2) point on the trace at each strip's centre chainage."""
    from ..core.fault import point_at_chainage

    return np.array([point_at_chainage(trace, st.along_centre_m) for st in strips]).reshape(-1, 2)


def window_motion(windows) -> Dict[str, np.ndarray]:
    """Each window's own motion, (ny, nx) grids in metres: ``dx``, ``dy``, ``dz``, their σ,
    ``right_lateral`` (+ = dextral on either side) and its σ (:mod:`.signs`)."""
    from . import signs

    w = windows
    ref = np.zeros(3) if w.reference_m is None else np.asarray(w.reference_m, dtype=np.float64)
    out = {"dx": w.dx + ref[0], "dy": w.dy + ref[1], "dz": w.dz + ref[2]}
    c = np.full(w.dx.shape + (3, 3), np.nan) if w.covariance is None else w.covariance
    c = np.asarray(c, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        for k, name in enumerate(("sigma_dx", "sigma_dy", "sigma_dz")):
            out[name] = np.sqrt(np.abs(c[..., k, k]))
    out["sigma_right_lateral"] = signs.sigma_along_grid(c, w.strike_rad)
    out["right_lateral"] = signs.right_lateral_grid(out["dx"], out["dy"], w.strike_rad, w.side)
    return out


def window_bands(windows) -> np.ndarray:
    """(8, ny, nx) bands :data:`WINDOW_BANDS` of the windows (each window's own motion)."""
    m = window_motion(windows)
    bands = [
        m["right_lateral"],
        m["dx"],
        m["dy"],
        m["dz"],
        m["sigma_dx"],
        m["sigma_dy"],
        windows.n_planes,
        m["sigma_right_lateral"],
    ]
    return np.stack([np.asarray(b, dtype=np.float64) for b in bands])


def weak_components_of(result):
    """:func:`slipmap.core.determination.weak_components` of a slip result: each side's
    displacement covariance and the normals of its adjusted (not rejected) planes."""
    from ..core.determination import weak_components
    from ..core.displacement import SIDES, strike_axes

    covariances, normals = [], []
    for name in SIDES:
        side = getattr(result, name)
        rigid = side.rigid
        n = np.array(rigid.plane_params[:, :3], dtype=np.float64)
        rejected = [int(j) for j, _ in rigid.rejected_planes if 0 <= int(j) < len(n)]
        n[rejected] = np.nan
        covariances.append(side.displacement_covariance)
        normals.append(n)
    return weak_components(covariances, normals, strike_axes(result.strike_rad), sides=SIDES)


def summary_payload(result) -> Dict[str, Any]:
    """``SlipResult.to_dict()`` in the sign convention of :mod:`.signs` (the summary every
    face writes: ``displacement.json``, QGIS's outputs, PDAL's metadata).

    ``relative``: ``right_lateral_slip`` = ``right_lateral`` (+ = dextral), ``opening``,
    ``dz`` (+ = the right side up), dx, dy, horizontal and their σ; each side gains its own
    ``right_lateral`` and ``opening`` (a left and a right value add up to the relative one);
    ``fault`` names each side by compass direction and states the convention; tiles carry
    the signed names. No ``fault_parallel`` / ``fault_normal``."""
    from ..core.displacement import SIDES
    from . import signs

    p = result.to_dict()
    strike = result.strike_rad
    p["relative"] = signs.relative(p["relative"])
    for name in SIDES:
        side = getattr(result, name)
        m = signs.motion(side.displacement, side.displacement_covariance, strike, name)
        p[name] = {
            **{
                k: m[k]
                for k in ("right_lateral", "sigma_right_lateral", "opening", "sigma_opening")
            },
            **p[name],
        }
    names = signs.side_names(p["fault"]["strike_deg"])
    p["fault"].update({f"{s}_side": names.get(s) for s in SIDES}, sign_convention=signs.CONVENTION)
    if "tiles" in p:
        rows = []
        for t, row in zip(result.tiles, p["tiles"]):
            row = {k: v for k, v in row.items() if "fault_" not in k}
            m = signs.motion(t.displacement, t.covariance, strike, t.side) if t.adjusted else None
            for k in ("right_lateral", "sigma_right_lateral", "opening", "sigma_opening"):
                row[k] = None if m is None else m[k]
            rows.append(row)
        p["tiles"] = rows
    p["weak_components"] = signs.weak_components(weak_components_of(result), names)
    for row in p["weak_components"]:
        log.warning("%s", row["text"])
    p["note"] = (
        "displacements in metres, rotations in radians; each side's displacement is the motion "
        "of the material at that side's centroid (first to second epoch); signs: "
        + signs.CONVENTION
    )
    return p


# --------------------------------------------------------------------------- the job


def default_names(opts: Mapping[str, Any]) -> Dict[str, str]:
    """File names of the outputs in an output folder (the CLI's ``--out``)."""
    names = {
        "summary": "displacement.json",
        "layers": "displacement.gpkg",
        "report": "report.html",
        **{f"figure_{f}": f"{f}.png" for f in FIGURES if f != "strips"},
    }
    if opts.get("strip_width_m") is not None:
        names["figure_strips"] = "strips.png"
    if opts.get("window_size_m") is not None:
        names.update(
            windows="windows.tif", windows_dx="windows_dx.tif", windows_dy="windows_dy.tif"
        )
    return names


def _with_figures(outputs: Mapping[str, Any]) -> Dict[str, Any]:
    """File-by-file outputs (QGIS) plus the figures beside the report (``<stem>_<name>.png``)."""
    out = {k: v for k, v in outputs.items()}
    report = out.get("report")
    for f in FIGURES:
        key = f"figure_{f}"
        if key not in out:
            out[key] = None if not report else str(Path(report).with_suffix("")) + f"_{f}.png"
    return out


#: outputs that need an option: output key -> the option
_OUTPUT_NEEDS = {"tiles": "tile_size_m", "strips": "strip_width_m", "windows": "window_size_m"}


def check_outputs(opts: Mapping[str, Any], wanted) -> None:
    """Refuse an output asked for without the option that makes it (tiles without a tile
    size, except for tiled inputs, which always run on tiles; strips without a strip width,
    windows without a window size).

    Raises
    ------
    OptionError
        Naming the output and the option.
    """
    from .tiled import is_tiled

    tiled = is_tiled(opts, "before", "after")
    for key in wanted:
        need = _OUTPUT_NEEDS.get(key)
        if key == "tiles" and tiled:  # tiled inputs always run on tiles (default 100 m)
            continue
        if need is not None and opts.get(need) is None:
            raise OptionError(
                key,
                f"is asked for but no {{{need}}} is given: give it or leave this output out",
                also=(need,),
            )


def unused_settings(opts: Mapping[str, Any], wanted) -> List[OptionError]:
    """Settings given for an output that is not asked for (QGIS: its sinks are optional; the
    CLI's folder gets every output of a setting, PDAL has neither setting), as OptionErrors
    for :meth:`.options.JobSpec.render_error` to word as the face does; the face shows them
    as warnings. A strip width without the Strips output still gives the strips in the
    summary JSON and the report's profile (they cost little); a window size without the
    Moving windows output computes no windows (they cost much).

    Parameters
    ----------
    opts
        The parsed options.
    wanted
        The output keys asked for (``strips``, ``windows``, …).
    """
    wanted = set(wanted)
    notes = []
    if opts.get("strip_width_m") is not None and "strips" not in wanted:
        notes.append(
            OptionError(
                "strip_width_m",
                "is set but no {strips} output is asked for: the strips go only into the "
                "summary JSON and the report; ask for {strips} to get the layer",
                also=("strips",),
            )
        )
    if opts.get("window_size_m") is not None and "windows" not in wanted:
        notes.append(
            OptionError(
                "window_size_m",
                "is set but no {windows} output is asked for: no windows are computed; ask "
                "for {windows} to get them",
                also=("windows",),
            )
        )
    return notes


def input_paths(opts: Mapping[str, Any], *, tiled: bool = False) -> Dict[str, Any]:
    """Every input path of the options (``tiled``: every tile file of each epoch), for
    :class:`~.outputs.OutputPlan`'s checks."""
    from .tiled import input_files

    keys = ("before", "after", "fault", "trajectory", "trajectory_accuracy", "pa_config")
    paths = {k: opts.get(k) for k in keys}
    if tiled:
        paths.update({k: input_files(opts, k) for k in ("before", "after")})
    return paths


def check_trace(fault, before: np.ndarray, opts: Mapping[str, Any]) -> None:
    """The fault trace against the before epoch's points (it crosses their extent, points lie
    on both sides outside the buffer), before any computation; errors name the ``fault``
    option (the trace is what users get wrong: a wrong file, layer or CRS)."""
    from ..core.errors import InputDataError
    from ..core.fault import trace_in_data_check

    try:
        trace_in_data_check(fault, before[:, :2], buffer_m=opts.get("buffer_m", 10.0), quiet=True)
    except InputDataError as exc:
        raise OptionError("fault", str(exc)) from exc


def read_trace(path, crs):
    """The fault trace of a file, reprojected to ``crs``; errors name the ``fault`` option."""
    from ..core.io.vector import read_fault_trace

    try:
        return read_fault_trace(path, target_crs=crs)
    except OptionError:
        raise
    except SlipMapError as exc:
        raise OptionError("fault", str(exc)) from exc


def run(
    opts: Mapping[str, Any],
    outputs: Mapping[str, Any],
    *,
    trace: Optional[Callable[[Any], Any]] = None,
    trace_source: Optional[str] = None,
    progress: Optional[Progress] = None,
) -> JobResult:
    """Read, select, compute and write.

    Parameters
    ----------
    opts
        :data:`SPEC`'s options, parsed (:meth:`JobSpec.parse`).
    outputs
        ``{"out": folder}`` for every output under :func:`default_names`; or
        ``{key: path or None}`` of ``summary``, ``report``, ``layers``, ``windows``,
        ``windows_dx``, ``windows_dy`` (figures go beside the report).
    trace
        ``f(crs) -> FaultTrace`` in the epochs' CRS (QGIS gives its layer this way); default:
        read ``opts["fault"]``.
    trace_source
        Where ``trace`` comes from, for the record (the JSON's ``parameters.fault`` and the
        report): the layer's file or name (QGIS); default ``opts["fault"]``.

    Returns
    -------
    JobResult
        ``data``: ``{"run": SlipRun, "trace", "crs", "planes": {side: columns}, "tiles",
        "strips", "strip_points", "tile_rings", "windows": bands or None}``.
    """
    from ..core.displacement import SIDES
    from .tiled import is_tiled

    outputs = dict(outputs)
    folder = outputs.get("out") is not None
    if not folder:
        outputs = _with_figures(outputs)
        check_outputs(opts, [k for k in ("windows",) if outputs.get(k) is not None])
    tiled = is_tiled(opts, "before", "after")
    if tiled:
        check_tiled(opts)  # before any output is touched
    plan = OutputPlan.for_outputs(
        inputs=input_paths(opts, tiled=tiled),
        outputs=outputs,
        default_names=default_names(opts),
    )
    plan.check()
    want_windows = folder or plan.wants("windows")
    with plan:
        if tiled:  # tile by tile, in process or on Dask (app/tiled.py)
            crs, fault, slip, settings, unit_record, runtime = _compute_tiled(
                opts, trace, scaled(progress, 0.0, 0.95)
            )
        else:
            crs, fault, slip, settings, unit_record, runtime = _compute_whole(
                opts, trace, want_windows, scaled(progress, 0.0, 0.95)
            )
        result = slip.result
        from . import signs as _signs

        payload = summary_payload(result)
        source = trace_source or (str(opts["fault"]) if opts.get("fault") else None)
        payload["parameters"].update(
            {
                "point_accuracy": {e: pa.settings_in_effect(s) for e, s in settings.items()},
                "before": str(opts["before"]),
                "after": str(opts["after"]),
                **({"fault": source} if source else {}),
                "acquisition_unit_sources": unit_record,
            }
        )
        payload["headline"] = headline_text(result.parameters, tiled_inputs=tiled)
        log.info("%s", payload["headline"])
        if slip.tile_planes is not None:
            payload["tile_planes_estimate"] = {
                "note": "the joint adjustment of the planes extracted tile by tile (what "
                "tiled inputs give); not the headline",
                **_signs.relative(slip.tile_planes.components()),
                "n_planes": {
                    side: int(getattr(slip.tile_planes, side).rigid.n_planes) for side in SIDES
                },
            }
        payload["runtime_s"] = round(runtime, 3)
        payload["slipmap_version"] = __version__
        if opts.get("reference_slip_m") is not None:
            payload["reference"] = result.reference_comparison(opts["reference_slip_m"])
        if slip.strips is not None:
            payload["strips"] = strip_rows(slip.strips)
        payload = json_safe(payload)  # NaN (e.g. a component's sd) -> null: standard JSON
        data = {
            "run": slip,
            "trace": fault,
            "crs": crs,
            "planes": {s: plane_columns(getattr(result, s)) for s in SIDES},
            "tiles": tile_columns(result) if result.tiles else None,
            "tile_rings": tile_rings(result) if result.tiles else None,
            "strips": strip_columns(slip.strips) if slip.strips is not None else None,
            "strip_points": strip_points(slip.strips, fault) if slip.strips else None,
            "windows": window_bands(slip.windows) if slip.windows is not None else None,
            "window_motion": window_motion(slip.windows) if slip.windows is not None else None,
        }
        _write(plan, payload, data)
        if progress is not None:
            progress(1.0, "written")
    lines = slip_summary_lines(payload)
    if tiled:
        prm = payload["parameters"]
        lines.append(f"tiled inputs: tiles of {prm['tile_size_m']:g} m, {prm.get('engine')}")
    ref = payload.get("reference")
    if ref is not None:
        lines.append(
            f"against the reference slip {ref['reference_slip']:.4f} m: ΔD "
            f"{ref['delta_displacement']:+.4f} m, scale {ref['scale']:.3f}, relative scale "
            f"{ref['relative_scale']:.3f}"
        )
    files = {k: p for k in _all_keys(plan) if (p := plan.final(k)).exists()}
    return JobResult(payload, lines, files, data=data)


def _compute_whole(opts, trace, want_windows: bool, progress):
    """Read both epochs whole, select, and compute: ``(crs, trace, SlipRun, point-accuracy
    settings, units record, seconds)``."""
    pair = read_epoch_pair(opts["before"], opts["after"], crs=opts.get("crs"))
    clouds = {"before": pair.before, "after": pair.after}
    sel, label = {}, {}
    for epoch, cloud in clouds.items():
        label[epoch] = f"{epoch} epoch ({Path(str(cloud.source)).name})"
        sel[epoch] = select_points(
            cloud,
            classes=opts.get("classes"),
            exclude_classes=opts.get("exclude_classes"),
            ground_default=True,
            what=f"the {epoch} epoch",
        )
    settings = point_accuracy(opts)
    sigma = {e: pa.covariances(clouds[e], sel[e], settings[e]) for e in clouds}
    units, unit_record = units_for_job(
        opts,
        {
            e: (
                label[e],
                _dim(clouds[e], "PointSourceId", sel[e]),
                _dim(clouds[e], "GpsTime", sel[e]),
            )
            for e in clouds
        },
    )
    fault = trace(pair.crs) if trace is not None else read_trace(opts["fault"], pair.crs)
    before = pair.before.xyz[sel["before"]]
    after = pair.after_xyz[sel["after"]]
    check_trace(fault, before, opts)
    t0 = time.perf_counter()
    slip = compute(
        before,
        after,
        fault,
        opts,
        sigma_before=sigma["before"],
        sigma_after=sigma["after"],
        unit_before=units["before"].units,
        unit_after=units["after"].units,
        unit_time_before=units["before"].time_s,
        unit_time_after=units["after"].time_s,
        windows=want_windows,
        progress=progress,
    )
    return pair.crs, fault, slip, settings, unit_record, time.perf_counter() - t0


def check_tiled(opts: Mapping[str, Any]):
    """Refuse what the job cannot do on tiled inputs or Dask, naming the option: strips and
    moving windows, per-point accuracy models (columns, propagated), acquisition units from
    GPS time (all need the points of an epoch in one place).

    Returns
    -------
    settings, sigma
        The point-accuracy settings per epoch and each epoch's sigma for
        :func:`.tiled.slip_tiled` (a float, or (3,) per axis, metres).

    Raises
    ------
    OptionError
    """
    for key in ("strip_width_m", "window_size_m"):
        if opts.get(key) is not None:
            raise OptionError(
                key,
                "needs the points in one place; it is not available for tiled inputs or Dask "
                "runs: leave it out, or give one file per epoch",
            )
    if opts.get("stochastic_model", "full") == "full" and opts.get("units") == "GpsTime":
        raise OptionError(
            "units",
            "GpsTime splits each epoch at time gaps, which needs the whole epoch in one place; "
            "with tiled inputs or Dask use PointSourceId, auto or none",
        )
    settings = point_accuracy(opts)
    sigma = {}
    for epoch, s in settings.items():
        if s["model"] not in ("constant", "axis"):
            key = "pa_model"
            if opts.get("pa_config"):
                key = "pa_config"
            elif epoch == "after" and opts.get("pa_model_after"):
                key = "pa_model_after"
            raise OptionError(
                key,
                f"{s['model']} ({epoch} epoch) is a per-point accuracy model, which needs the "
                "points in one place; tiled inputs and Dask take a constant or per-axis sigma",
            )
        sigma[epoch] = (
            float(s.get("sigma", 0.05))
            if s["model"] == "constant"
            else np.asarray(s["sigma_xyz"], dtype=np.float64)
        )
    return settings, sigma


def _compute_tiled(opts, trace, progress):
    """Tile by tile, in process or on Dask (:func:`.tiled.slip_for_job`; no epoch is read
    whole): ``(crs, trace, SlipRun, point-accuracy settings, units record, seconds)``.
    ``progress`` may raise to cancel (between tiles)."""
    from .tiled import Selection, slip_for_job

    settings, sigma = check_tiled(opts)
    how = (opts.get("units") or "auto") if opts["stochastic_model"] == "full" else "none"
    if how != "none" and opts.get("unit_drift", True):
        log.info("tiled inputs: one rigid error per acquisition unit (no drift along GpsTime)")
    if how != "none" and opts.get("unit_contrasts", True):
        log.info(
            "tiled inputs: the acquisition units are not tied by their planes' within-epoch "
            "contrasts (plane moments carry no unit per point)"
        )
    t0 = time.perf_counter()
    crs, fault, result = slip_for_job(
        opts,
        trace if trace is not None else (lambda crs: read_trace(opts["fault"], crs)),
        selection=Selection(opts.get("classes"), opts.get("exclude_classes"), ground_default=True),
        progress=progress,
        sigma_before=sigma["before"],
        sigma_after=sigma["after"],
        combine=opts.get("combine") or "joint",
        units=how,
        components=fixed_components(opts),
        random_tilt=random_tilt_of(opts),
        **core_options(opts),
    )
    runtime = time.perf_counter() - t0
    n_units = result.parameters.get("acquisition_units") or {}
    record = {
        "units_option": opts.get("units", "auto"),
        **{
            e: {"source": "PointSourceId" if n_units else "none", "n_units": n_units.get(e, 0)}
            for e in ("before", "after")
        },
        "tiled": True,
        "unit_drift": False,
        "unit_contrasts": False,
    }
    return crs, fault, SlipRun(result), settings, record, runtime


def _all_keys(plan: OutputPlan) -> List[str]:
    keys = ["summary", "layers", *(f"figure_{f}" for f in FIGURES), "report", "windows"]
    keys += ["windows_dx", "windows_dy"]
    return [k for k in keys if plan.wants(k)]


def _dim(cloud, name: str, sel) -> Optional[np.ndarray]:
    values = cloud.attributes.get(name)
    return None if values is None else np.asarray(values)[sel]


def _write(plan: OutputPlan, payload: Dict[str, Any], data: Dict[str, Any]) -> None:
    """Everything but the per-face sinks: JSON, GeoPackage, rasters, figures, report."""
    from ..core.errors import DependencyError
    from .summaries import json_text

    slip = data["run"]
    crs = data["crs"]
    if plan.wants("summary"):
        plan.file("summary").write_text(json_text(payload), encoding="utf-8")
    if plan.wants("layers"):
        try:
            _write_layers(plan.file("layers"), slip.result, data, crs)
        except DependencyError as exc:
            log.warning("no GeoPackage written: %s", exc)
    if slip.windows is not None:
        try:
            _write_windows(plan, slip.windows, data, crs)
        except DependencyError as exc:
            log.warning("no window GeoTIFF written: %s", exc)
    images = _figures(plan, slip) if plan.wants("report") else []
    if plan.wants("report"):
        from .report import write_html_report

        lead, tables = report_tables(payload, data.get("crs"))
        write_html_report(plan.file("report"), "SlipMap fault slip", tables, images, lead=lead)


def _motion_rows_spec(dz_sign: str):
    """Report rows of a motion (relative or one side): JSON key -> (label, scale to the
    unit); the signed rows say what + means (:mod:`.signs`)."""
    return (
        ("right_lateral", "right-lateral (mm, + = dextral)", 1e3),
        ("sigma_right_lateral", "σ right-lateral (mm)", 1e3),
        ("sigma_right_lateral_white", "σ right-lateral, white noise only (mm)", 1e3),
        ("opening", "opening (mm, + = apart)", 1e3),
        ("sigma_opening", "σ opening (mm)", 1e3),
        ("dz", f"dz (mm, {dz_sign})", 1e3),
        ("sigma_dz", "σ dz (mm)", 1e3),
        ("sigma_dz_white", "σ dz, white noise only (mm)", 1e3),
        ("horizontal", "horizontal (mm)", 1e3),
        ("sigma_horizontal", "σ horizontal (mm)", 1e3),
        ("dx", "dx (mm, + = east)", 1e3),
        ("sigma_dx", "σ dx (mm)", 1e3),
        ("dy", "dy (mm, + = north)", 1e3),
        ("sigma_dy", "σ dy (mm)", 1e3),
        ("rx", "rx (mrad)", 1e3),
        ("ry", "ry (mrad)", 1e3),
        ("rz", "rz (mrad)", 1e3),
        ("sigma_white_dx", "σ dx, white noise only (mm)", 1e3),
        ("sigma_white_dy", "σ dy, white noise only (mm)", 1e3),
        ("sigma_white_dz", "σ dz, white noise only (mm)", 1e3),
        ("n_planes", "matched planes", 1),
        ("n_points", "points", 1),
        ("variance_factor", "variance factor", 1),
        ("iterations", "iterations", 1),
    )


def _motion_rows(values: Mapping[str, Any], dz_sign: str = "+ = up") -> Dict[str, Any]:
    out = {}
    for key, label, scale in _motion_rows_spec(dz_sign):
        v = values.get(key)
        if v is None or isinstance(v, (list, dict, str)):
            continue
        out[label] = v * scale if scale != 1 else v
    return out


def _source_name(source: Optional[str]) -> str:
    """A fault source for the report: the file's name (``f.gpkg``), a GeoPackage layer
    after it (``f.gpkg (layername=trace)``), or the text as given (a memory layer)."""
    if not source:
        return "(not recorded)"
    path, _, rest = str(source).partition("|")
    name = Path(path).name or str(source)
    return f"{name} ({rest})" if rest else name


def report_tables(payload: Mapping[str, Any], crs=None) -> Tuple[str, Dict[str, Any]]:
    """The HTML report's lead sentence and tables, in the units a geodesist reads: the
    result in mm with its σ and model first, then the inputs, the settings used, each side's
    motion (mm, mrad), the stochastic model and, when given, the reference comparison.
    Every signed value follows :mod:`.signs` and its row says what + means; the sides are
    named by compass direction.

    Parameters
    ----------
    payload
        The job's summary (``displacement.json``).
    crs
        The epochs' CRS (pyproj) or None.

    Returns
    -------
    (str, dict)
        The lead sentence and ``{title: table}`` for :func:`.report.write_html_report`.
    """
    from . import signs

    rel = payload.get("relative", {})
    params = payload.get("parameters", {})
    fault = payload.get("fault", {})
    names = {s: fault.get(f"{s}_side") for s in ("left", "right") if fault.get(f"{s}_side")}
    if not names:
        names = signs.side_names(fault.get("strike_deg"))
    model = params.get("stochastic_model", "white")
    slip, sig = rel.get("right_lateral_slip"), rel.get("sigma_right_lateral")
    if slip is None or sig is None:
        lead = "No slip estimate."
    else:
        lead = f"Right-lateral slip {1e3 * slip:+.2f} ± {1e3 * sig:.2f} mm (1σ, {model} model)"
        white = rel.get("sigma_right_lateral_white")
        if white is not None and model != "white":
            lead += f"; white noise alone would claim ± {1e3 * white:.2f} mm"
        lead += "."
    for row in payload.get("weak_components") or ():
        text = row["text"]
        lead += f" Weakly determined: {text[0].upper()}{text[1:]}."
    lead += (
        f" Signs: + right-lateral = dextral; + opening = the sides move apart; relative dz "
        f"{signs.dz_meaning(names)} (the {signs.side_label('right', names)} of the trace as "
        "digitised); each side's right-lateral and opening are its own motion in the same "
        "sense (left + right = relative)."
    )
    inputs = {
        "before epoch": Path(str(params.get("before", ""))).name or None,
        "after epoch": Path(str(params.get("after", ""))).name or None,
        "fault trace": _source_name(params.get("fault")),
        "CRS": getattr(crs, "name", None) or ("none" if crs is None else str(crs)),
    }
    for side in ("left", "right"):
        n = payload.get(side, {}).get("n_points")
        if n is not None:
            inputs[f"points used, {signs.side_label(side, names)} (both epochs)"] = n
    settings: Dict[str, Any] = {
        "headline estimate": payload.get("headline"),
        "buffer around the trace (m)": params.get("buffer_m"),
        "tile size (m)": params.get("tile_size_m"),
        "combine": params.get("combine"),
        "stochastic model": model,
    }
    units = params.get("acquisition_unit_sources") or {}
    if units:
        settings["acquisition units"] = units.get("units_option")
    for epoch, s in (params.get("point_accuracy") or {}).items():
        if isinstance(s, Mapping):
            text = ", ".join(f"{k} {v}" for k, v in s.items() if not isinstance(v, dict))
            settings[f"point accuracy, {epoch}"] = text
    for key in ("plane_options", "match_options", "components"):
        if params.get(key):
            settings[key.replace("_", " ")] = ", ".join(
                f"{k} {v}" for k, v in dict(params[key]).items()
            )
    right, left = signs.side_label("right", names), signs.side_label("left", names)
    tables: Dict[str, Any] = {
        f"Result: relative motion of the {right} against the {left}": _motion_rows(
            rel, signs.dz_meaning(names)
        ),
        "Inputs": inputs,
        "Settings": {k: v for k, v in settings.items() if v is not None},
    }
    for side in ("left", "right"):
        title = signs.side_label(side, names)
        tables[f"{title[0].upper()}{title[1:]}: after against before"] = _motion_rows(
            payload.get(side, {})
        )
    tables.update(stochastic_tables(dict(payload)))
    if "reference" in payload:
        tables["Against the reference slip"] = payload["reference"]
    return lead, tables


def _write_layers(path: Path, result, data: Dict[str, Any], crs) -> None:
    from ..core.io.vector import VectorLayer, write_gpkg_layers
    from .styles import gpkg_styles

    layers = []
    for side in (result.left, result.right):
        pb, m = side.planes_before, side.matches
        layers.append(
            VectorLayer(
                name=f"planes_{side.side}",
                geometry_type="Point",
                geometries=[pb.centroids[i] for i in m.before],
                fields=data["planes"][side.side],
            )
        )
    if data["tiles"] is not None:
        layers.append(VectorLayer("tiles", "Polygon", data["tile_rings"], data["tiles"]))
    if data["strips"] is not None:
        layers.append(VectorLayer("strips", "Point", list(data["strip_points"]), data["strips"]))
    trace = data["trace"]
    layers.append(
        VectorLayer(
            name="fault_trace",
            geometry_type="LineString",
            geometries=list(trace.parts),
            fields={"part": np.arange(len(trace.parts), dtype=np.int64)},
        )
    )
    write_gpkg_layers(path, layers, crs=crs, styles=gpkg_styles("slip", layers))


def _write_windows(plan: OutputPlan, w, data: Dict[str, Any], crs) -> None:
    """``windows`` (:data:`WINDOW_BANDS`) and ``windows_dx`` / ``windows_dy`` (value and σ):
    north-up, one pixel per window centre, each window's own motion; the metadata states the
    sign convention."""
    from ..core.io.raster import write_geotiff
    from . import signs
    from .styles import write_raster_style

    half = 0.5 * w.step_m
    common = dict(
        origin_xy=(w.x0 - half, w.y0 + half),
        pixel_size_m=w.step_m,
        crs_wkt=crs.to_wkt() if crs is not None else None,
        metadata={
            "SLIPMAP_WINDOW_SIZE_M": f"{w.window_size_m:g}",
            "SLIPMAP_SIGN_CONVENTION": signs.CONVENTION,
            "SLIPMAP_MOTION": "each window's own motion (first to second epoch), metres",
        },
    )
    if plan.wants("windows"):
        write_geotiff(
            plan.file("windows"), data["windows"], band_names=list(WINDOW_BANDS), **common
        )
    m = data["window_motion"]
    for name in ("dx", "dy"):
        if plan.wants(f"windows_{name}"):
            write_geotiff(
                plan.file(f"windows_{name}"),
                np.stack([m[name], m[f"sigma_{name}"]]).astype(np.float64),
                band_names=[f"{name}_m", f"sigma_{name}_m"],
                **common,
            )
    for key, values in (
        ("windows", data["windows"][0]),
        ("windows_dx", m["dx"]),
        ("windows_dy", m["dy"]),
    ):
        write_raster_style(plan, "slip", key, values)  # the .qml QGIS opens the raster with


def _figures(plan: OutputPlan, slip: SlipRun) -> List[str]:
    """Residual, normal, plane-residual and strip-profile PNGs; their names beside the
    report (none without matplotlib)."""
    from ..core.errors import DependencyError

    report = plotting()
    if report is None:
        return []

    result = slip.result
    sides = (result.left, result.right)
    written = []
    try:
        if plan.wants("figure_residuals") and all(
            s.rigid.residuals_before is not None and np.size(s.rigid.residuals_before)
            for s in sides  # a tiled run forms no per-point residuals
        ):
            res = {f"{s.side} before": s.rigid.residuals_before for s in sides}
            res.update({f"{s.side} after": s.rigid.residuals_after for s in sides})
            report.plot_residual_histograms(
                plan.file("figure_residuals"), res, title="Point-to-plane residuals"
            )
            written.append("figure_residuals")
        normals = {s.side: s.planes_before.normals[s.matches.before] for s in sides}
        if plan.wants("figure_normals"):
            report.plot_normals_polar(
                plan.file("figure_normals"), normals, title="Matched plane normals"
            )
            written.append("figure_normals")
        if plan.wants("figure_plane_residuals") and all(
            s.plane_mean_residual_m is not None for s in sides
        ):
            report.plot_plane_residual_polar(
                plan.file("figure_plane_residuals"),
                {s.side: (normals[s.side], s.plane_mean_residual_m) for s in sides},
            )
            written.append("figure_plane_residuals")
        if slip.strips and plan.wants("figure_strips"):
            from . import signs

            st = slip.strips
            motions = [signs.strip_motion(s) or {} for s in st]
            report.plot_strip_profile(
                plan.file("figure_strips"),
                [s.along_centre_m for s in st],
                [m.get("right_lateral", np.nan) for m in motions],
                [m.get("sigma_right_lateral", np.nan) for m in motions],
                [s.side for s in st],
                side_names=signs.side_names(np.degrees(result.strike_rad) % 360.0),
            )
            written.append("figure_strips")
    except DependencyError as exc:
        log.warning("no figures written: %s", exc)
    return [plan.final(k).name for k in written]
