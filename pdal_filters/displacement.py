"""PDAL stage ``displacement``: the slip job (:mod:`slipmap.app.slip`) on two merged epochs.

The two epochs arrive as one point view, tagged by an epoch dimension (``Epoch``: 1 = before,
2 = after, e.g. from ``filters.assign`` on each reader followed by ``filters.merge``).
:func:`slipmap.app.slip.compute` registers each side of the fault trace between the epochs;
the summary (:func:`slipmap.app.slip.summary_payload`: ``right_lateral`` + = dextral,
``opening`` + = apart, ``dz`` + = the right side up; docs/methods.md "Sign convention") goes to
``out_metadata`` and every point gets, from the
result (:meth:`slipmap.core.displacement.SlipResult.point_planes`):

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

Options: the job's (:data:`slipmap.app.slip.SPEC`) that PDAL shows, plus the trace and the
epoch tagging (:func:`options_table`, docs/pdal.md).
"""

import logging

import numpy as np

from slipmap.app import slip as job
from slipmap.app.signs import CONVENTION
from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import Option, OptionTable

STAGE = "slipmap displacement"
SPEC = job.SPEC
OUTPUTS = {"PlaneId": "int32", "Residual": "float64"}
EPOCHS = ("before", "after")
#: the sign convention (slipmap.app.signs), stated in the stage's metadata
SIGNS = "signs: " + CONVENTION
_MEANING = {
    "right_lateral_slip": "metres, + = right-lateral (dextral)",
    "right_lateral": "metres, + = right-lateral (dextral)",
    "opening": "metres, + = the sides move apart",
    "dz": "metres, + = the right side of the trace (as digitised) up",
}
log = logging.getLogger(__name__)


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md): the trace, the epoch tagging, and the job's."""
    return OptionTable.from_spec(
        STAGE,
        SPEC,
        extra=[
            Option(
                "trace",
                "str",
                None,
                "Fault trace in the points' CRS: WKT `LINESTRING`/`MULTILINESTRING`, or the path "
                "of an OGR vector file (reprojected to the view's spatial reference; needs GDAL).",
                required=True,
            ),
            Option("trace_layer", "str", None, "Layer of the trace file (default: first line)."),
            *_stage.EPOCH_OPTIONS,
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
    path, crs = _stage.lines_file(text, "trace", STAGE, inputs)
    from slipmap.core.io.vector import read_fault_trace

    return read_fault_trace(path, target_crs=crs, layer=opts["trace_layer"])


def run(ins, outs, *, opts, inputs):
    """Slip summary as the metadata node; PlaneId and Residual into ``outs``."""
    from slipmap.app.pointaccuracy import covariances
    from slipmap.app.stochasticmodel import units_for_job
    from slipmap.app.summaries import stochastic_outputs
    from slipmap.core.io.las import PointCloud

    o = _stage.job_options(SPEC, opts)
    n = _stage.n_points(ins)
    labels = np.full(n, -1, dtype=np.int32)
    residual = np.full(n, np.nan)
    if n == 0:
        _stage.set_output(outs, "PlaneId", labels, np.int32, n, STAGE)
        _stage.set_output(outs, "Residual", residual, np.float64, n, STAGE)
        return _stage.stage_node("displacement", "empty point view")

    idx = _stage.epochs(ins, opts, STAGE)
    pts = _stage.points_from(ins, STAGE)
    dim = opts["epoch_dimension"]
    label = {key: f"{key} epoch ({dim} == {opts[key]})" for key in EPOCHS}
    clouds = {
        key: PointCloud(
            xyz=pts[ix],
            attributes={d: np.asarray(v)[ix] for d, v in ins.items() if d not in ("X", "Y", "Z")},
            source=label[key],
        )
        for key, ix in idx.items()
    }
    settings = job.point_accuracy(o)
    sigma = {key: covariances(clouds[key], None, settings[key]) for key in EPOCHS}
    units, record = units_for_job(
        o,
        {
            key: (
                label[key],
                clouds[key].attributes.get("PointSourceId"),
                clouds[key].attributes.get("GpsTime"),
            )
            for key in EPOCHS
        },
    )
    trace = _trace(opts, inputs)
    slip = job.compute(
        clouds["before"].xyz,
        clouds["after"].xyz,
        trace,
        o,
        sigma_before=sigma["before"],
        sigma_after=sigma["after"],
        unit_before=units["before"].units,
        unit_after=units["after"].units,
        unit_time_before=units["before"].time_s,
        unit_time_after=units["after"].time_s,
    )
    res = slip.result
    for key, ix in idx.items():
        lab, r = res.point_planes(clouds[key].xyz, key)
        labels[ix], residual[ix] = lab, r
    _stage.set_output(outs, "PlaneId", labels, np.int32, n, STAGE)
    _stage.set_output(outs, "Residual", residual, np.float64, n, STAGE)
    summary = job.summary_payload(res)
    summary["parameters"]["acquisition_unit_sources"] = record
    rel = summary["relative"]
    slip_m, sig = rel.get("right_lateral_slip"), rel.get("sigma_right_lateral")
    headline = (
        f"right-lateral slip {1e3 * slip_m:+.2f} ± {1e3 * sig:.2f} mm (+ = dextral)"
        if slip_m is not None and sig is not None and np.isfinite(slip_m) and np.isfinite(sig)
        else "no slip estimate"
    )
    return _stage.stage_node(
        "displacement",
        "SlipMap relative displacement across the fault (right minus left), metres; " + SIGNS,
        [
            _stage.metadata_node("headline", headline, "right-lateral slip ± 1 sigma"),
            *(_stage.metadata_node(k, v, _MEANING.get(k, "")) for k, v in rel.items()),
            _stage.metadata_node("stochastic_model", o["stochastic_model"], "white, plane or full"),
            _stage.metadata_node(
                "variance_components",
                stochastic_outputs(summary),
                "per side: n_eff, the spatial range and each component's sigma (m) and "
                "source; the right-lateral sigma of the model and of the white model",
            ),
            _stage.metadata_node(
                "acquisition_units", record, "per epoch: where the units came from and how many"
            ),
            _stage.metadata_node("summary", summary, "displacement.json's summary"),
        ],
    )
