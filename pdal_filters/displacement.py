"""PDAL stage ``displacement``: fault slip between two merged epochs.

The two epochs arrive as one point view, tagged by an epoch dimension (``Epoch``: 1 = before,
2 = after, e.g. from ``filters.assign`` on each reader followed by ``filters.merge``).
:func:`slipmap.core.displacement.estimate_slip` registers each side of the fault trace between
the epochs; the summary (``SlipResult.to_dict()``) goes to ``out_metadata`` and every point gets

* ``PlaneId`` (int32): its plane in its own epoch's segmentation of its own side (ids are per
  side and epoch, so the left and right sides both start at 0); -1 for points in no plane,
  inside the buffer, or with another epoch value;
* ``Residual`` (double, metres): signed orthogonal distance of the point to that plane
  (``n . p + d``); NaN where ``PlaneId`` is -1.

Pipeline stage (the script is ``slipmap_stages.py``, see :mod:`slipmap.pdal_filters`)::

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_displacement", "function": "displacement",
     "add_dimension": ["PlaneId=int32", "Residual"],
     "pdalargs": {"trace": "LINESTRING (500 0, 500 1000)", "buffer_m": 10}}

Options: :func:`options_table`, docs/pdal.md.
"""

import logging
import os

import numpy as np

from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import Option, OptionTable

STAGE = "slipmap displacement"
OUTPUTS = {"PlaneId": "int32", "Residual": "float64"}
log = logging.getLogger(__name__)


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md)."""
    return OptionTable(
        STAGE,
        [
            Option(
                "trace",
                "str",
                None,
                "Fault trace in the points' CRS: WKT `LINESTRING`/`MULTILINESTRING`, or the path "
                "of an OGR vector file (reprojected to the view's spatial reference; needs GDAL).",
                required=True,
            ),
            Option("trace_layer", "str", None, "Layer of the trace file (default: first line)."),
            Option("epoch_dimension", "str", "Epoch", "Dimension tagging each point's epoch."),
            Option("before", "int", 1, "Epoch value of the first (before) epoch."),
            Option("after", "int", 2, "Epoch value of the second (after) epoch."),
            Option(
                "buffer_m",
                "float",
                10.0,
                "Points this close to the trace are left out (m).",
                minimum=0,
            ),
            Option(
                "sigma_before",
                "float",
                0.05,
                "Point accuracy of the first epoch, 1 sigma (m).",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "sigma_after",
                "float",
                0.05,
                "Point accuracy of the second epoch, 1 sigma (m).",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "sigma_dimensions",
                "names",
                None,
                "Per-point σ dimensions (m), e.g. `SigmaX,SigmaY,SigmaZ` from the accuracy "
                "stage; when set they replace `sigma_before`/`sigma_after`.",
            ),
            Option(
                "tile_size_m",
                "float",
                None,
                "Square tiles (m) for per-tile planes and matching; none: whole sides.",
                minimum=0,
                exclusive=True,
                unset_text="none",
            ),
            Option(
                "combine",
                "choice",
                "joint",
                "With tiles: one adjustment per side, or the weighted mean of tile results.",
                choices=("joint", "tiles"),
            ),
            Option(
                "stochastic_model",
                "choice",
                "full",
                "Stochastic model of the slip's σ: `white` = independent point errors only "
                "(the study's; too small a σ for real surveys), `plane` = plus one random "
                "offset per plane, `full` = plus spatially correlated plane offsets and a "
                "rigid error per acquisition unit (`units`); components estimated by REML.",
                choices=("white", "plane", "full"),
            ),
            Option(
                "units",
                "choice",
                "auto",
                "Acquisition unit of each point (full model), per epoch: `auto` = "
                "`PointSourceId` when the epoch has more than one distinct value, else none; "
                "`PointSourceId` (ALS strips, MLS passes); `GpsTime` = segments of the sorted "
                "GPS times split at jumps > `gps_gap_s` (passes, scans); `none`. "
                "Case-insensitive.",
                choices=("auto", "PointSourceId", "GpsTime", "none"),
            ),
            Option(
                "gps_gap_s",
                "float",
                1.0,
                "With `units` GpsTime: a new unit starts where consecutive GPS times jump by "
                "more than this (s).",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "fixed_components",
                "keyvalues",
                None,
                "Plane-level components held fixed instead of estimated: `plane`, `spatial`, "
                "`unit_before`, `unit_after` (σ, m) and `spatial_range_m` (m), e.g. "
                '`"plane=0.002,unit_after=0.003"` or `{"plane": 0.002}`.',
            ),
            Option("plane_options", "object", {}, "Keyword options of `segment_planes`."),
            Option("match_options", "object", {}, "Keyword options of the plane matching."),
        ],
    )


TABLE = options_table()


def outputs(opts):
    """{dimension: dtype} written (declare them in add_dimension)."""
    return OUTPUTS


def _trace(opts, inputs):
    from slipmap.core.fault import fault_trace

    text = opts["trace"]
    if _stage.is_wkt_line(text):
        return fault_trace(_stage.parse_wkt_lines(text, "trace"))
    path = os.path.expanduser(text)
    if not os.path.isfile(path):
        raise _stage.StageError(
            f"{STAGE}: option 'trace' is neither a WKT LINESTRING nor an existing file: {text!r}"
        )
    from slipmap.core.io.vector import read_fault_trace

    crs = inputs.crs(STAGE)
    if crs is None:
        log.warning(
            "%s: the point view has no spatial reference; the trace %s is read in its own CRS, "
            "not reprojected (set the readers' spatialreference if the two differ)",
            STAGE,
            path,
        )
    return read_fault_trace(path, target_crs=crs, layer=opts["trace_layer"])


def run(ins, outs, *, opts, inputs):
    """Slip summary as the metadata node; PlaneId and Residual into ``outs``."""
    if opts["before"] == opts["after"]:
        raise _stage.StageError(f"{STAGE}: options 'before' and 'after' must differ")
    n = _stage.n_points(ins)
    labels = np.full(n, -1, dtype=np.int32)
    residual = np.full(n, np.nan)
    if n == 0:
        _stage.set_output(outs, "PlaneId", labels, np.int32, n, STAGE)
        _stage.set_output(outs, "Residual", residual, np.float64, n, STAGE)
        return _stage.stage_node("displacement", "empty point view")

    from slipmap.app.summaries import stochastic_outputs
    from slipmap.core.displacement import estimate_slip

    stochastic = _stochastic_options(opts)

    dim = opts["epoch_dimension"]
    if dim not in ins:
        raise _stage.StageError(
            f"{STAGE}: option 'epoch_dimension': the view has no {dim!r} dimension (tag the "
            f"epochs with filters.assign before filters.merge); it has {', '.join(sorted(ins))}"
        )
    pts = _stage.points_from(ins, STAGE)
    epoch = np.asarray(ins[dim])
    idx = {
        "before": np.flatnonzero(epoch == opts["before"]),
        "after": np.flatnonzero(epoch == opts["after"]),
    }
    for key, ix in idx.items():
        if ix.size == 0:
            raise _stage.StageError(
                f"{STAGE}: no point has {dim} == {opts[key]} (option {key!r}); "
                f"values present: {np.unique(epoch)[:10].tolist()}"
            )
    trace = _trace(opts, inputs)
    before, after = pts[idx["before"]], pts[idx["after"]]
    sigma = {"before": opts["sigma_before"], "after": opts["sigma_after"]}
    names = opts["sigma_dimensions"]
    if names is not None:
        missing = [d for d in names if d not in ins]
        if missing:
            raise _stage.StageError(
                f"{STAGE}: option 'sigma_dimensions': the view has no {missing} "
                "dimension(s); add them with the slipmap accuracy stage before this one"
            )
        per_point = np.column_stack([np.asarray(ins[d], dtype=np.float64) for d in names])
        sigma = {key: per_point[ix] for key, ix in idx.items()}
    units = _units(opts, ins, idx, stochastic["stochastic_model"])
    res = estimate_slip(
        before,
        after,
        trace,
        buffer_m=opts["buffer_m"],
        sigma_before=sigma["before"],
        sigma_after=sigma["after"],
        plane_options=opts["plane_options"] or None,
        match_options=opts["match_options"] or None,
        tile_size_m=opts["tile_size_m"],
        combine=opts["combine"],
        unit_before=units["before"].units,
        unit_after=units["after"].units,
        **stochastic,
    )
    _per_point(
        res, {"before": before, "after": after}, idx, trace, opts["buffer_m"], labels, residual
    )
    _stage.set_output(outs, "PlaneId", labels, np.int32, n, STAGE)
    _stage.set_output(outs, "Residual", residual, np.float64, n, STAGE)
    summary = res.to_dict()
    summary["parameters"]["acquisition_unit_sources"] = {
        "units_option": opts["units"],
        **{key: u.to_dict() for key, u in units.items()},
    }
    rel = summary["relative"]
    slip, sig = rel.get("right_lateral_slip"), rel.get("sigma_fault_parallel")
    headline = (
        f"right-lateral slip {1e3 * slip:.2f} ± {1e3 * sig:.2f} mm"
        if slip is not None and sig is not None and np.isfinite(slip) and np.isfinite(sig)
        else "no slip estimate"
    )
    return _stage.stage_node(
        "displacement",
        "SlipMap relative displacement across the fault (right minus left), metres",
        [
            _stage.metadata_node("headline", headline, "fault-parallel slip ± 1 sigma"),
            *(_stage.metadata_node(k, v) for k, v in rel.items()),
            _stage.metadata_node(
                "stochastic_model", stochastic["stochastic_model"], "white, plane or full"
            ),
            _stage.metadata_node(
                "variance_components",
                stochastic_outputs(summary),
                "per side: n_eff, the spatial range and each component's sigma (m) and "
                "source; the fault-parallel sigma of the model and of the white model",
            ),
            _stage.metadata_node(
                "acquisition_units",
                summary["parameters"]["acquisition_unit_sources"],
                "per epoch: where the units came from and how many",
            ),
            _stage.metadata_node("summary", summary, "SlipResult.to_dict()"),
        ],
    )


def _per_point(res, clouds, idx, trace, buffer_m, labels, residual):
    """Each point's plane (its epoch and side's segmentation) and signed distance to it."""
    from slipmap.core.fault import fault_geometry, side_masks

    for key, cloud in clouds.items():
        left, right = side_masks(fault_geometry(cloud[:, :2], trace), buffer_m=buffer_m)
        for side, mask in (("left", left), ("right", right)):
            ps = getattr(getattr(res, side), "planes_" + key)
            ix = idx[key][mask]
            lab = np.asarray(ps.labels, dtype=np.int32)
            if lab.shape != ix.shape:
                raise _stage.StageError(  # pragma: no cover - programming error
                    f"{STAGE}: internal: {side}/{key} has {lab.size} labels for {ix.size} points"
                )
            labels[ix] = lab
            on = lab >= 0
            k = lab[on]
            residual[ix[on]] = np.einsum("ij,ij->i", cloud[mask][on], ps.normals[k]) + ps.offsets[k]


def _stochastic_options(opts):
    """estimate_slip's ``stochastic_model`` and ``components`` from the options."""
    from slipmap.app.stochasticmodel import parse_fixed_components
    from slipmap.core.errors import InvalidParameterError

    try:
        fixed = parse_fixed_components(
            opts["fixed_components"], option=f"{STAGE}: option 'fixed_components'"
        )
    except InvalidParameterError as e:
        raise _stage.StageError(str(e)) from None
    if fixed and opts["stochastic_model"] == "white":
        raise _stage.StageError(
            f"{STAGE}: option 'fixed_components': the white model has no plane-level "
            "components; set stochastic_model to plane or full"
        )
    return {"stochastic_model": opts["stochastic_model"], "components": fixed or None}


def _units(opts, ins, idx, model):
    """Acquisition units of each epoch (``EpochUnits``) from the view's dimensions."""
    import numpy as np

    from slipmap.app.stochasticmodel import EpochUnits, epoch_units, log_units

    out = {}
    for key, ix in idx.items():
        if model != "full":
            out[key] = EpochUnits(None, "none", 0, f"not used by the {model} model")
            continue
        dims = {
            d: (np.asarray(ins[d])[ix] if d in ins else None) for d in ("PointSourceId", "GpsTime")
        }
        out[key] = epoch_units(
            opts["units"],
            point_source_id=dims["PointSourceId"],
            gps_time=dims["GpsTime"],
            gap_s=opts["gps_gap_s"],
            epoch=f"{key} epoch ({opts['epoch_dimension']} == {opts[key]})",
            option="option 'units'",
        )
        log_units(f"{STAGE}: {key} epoch", out[key])
    return out
