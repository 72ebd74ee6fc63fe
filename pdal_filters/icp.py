"""PDAL stage ``icp``: the displacement field (:mod:`slipmap.app.icp`) of two merged epochs.

The two epochs arrive as one point view tagged by an epoch dimension (``Epoch``: 1 = before,
2 = after, as for the ``displacement`` stage). :func:`slipmap.app.icp.compute` cuts the
after epoch into square cells and registers each onto the before surface, with the job's
defaults (one spline field, smooth on either side of the breaklines, which are found in the
data unless given). Breaklines are given as ``breaklines``: WKT ``LINESTRING`` /
``MULTILINESTRING`` in the points' CRS, or the path of an OGR line file (reprojected to the
view's spatial reference).

Every point gets its cell's ground motion, before to after, in metres (the values at the
cell's centre, as the CLI's table; a point in no fitted cell gets NaN):

* ``DisplacementX``, ``DisplacementY``, ``DisplacementZ`` (double): east, north, up;
* ``IcpCell`` (int32): the cell's row in the metadata's ``cells`` table; -1 for none.

``out_metadata`` holds a headline, ``icp.json``'s summary (``summary``, the breaklines'
source and vertices among it) and ``cells``, the CLI's table as columns (``x``, ``y``,
``dx``, ``dy``, ``dz``, ``sigma_dx`` …).

Pipeline stage (the script is ``slipmap_stages.py``, see :mod:`slipmap.pdal_filters`)::

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_icp", "function": "icp",
     "add_dimension": ["DisplacementX", "DisplacementY", "DisplacementZ", "IcpCell=int32"],
     "pdalargs": {"cell_m": 5, "breaklines": "LINESTRING (500000 4200000, 500100 4200050)"}}

Options: the job's (:data:`slipmap.app.icp.SPEC`) that PDAL shows, plus the breaklines and
the epoch tagging (:func:`options_table`, docs/pdal.md).
"""

import numpy as np

from slipmap.app import icp as job
from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import OptionTable

STAGE = "slipmap icp"
SPEC = job.SPEC
OUTPUTS = _stage.field_outputs("IcpCell")


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md): the breaklines, the epoch tagging, the job's."""
    return OptionTable.from_spec(
        STAGE,
        SPEC,
        extra=_stage.field_options(
            "Lines the field may jump across (scarps, a fault), in the points' CRS: WKT "
            "`LINESTRING`/`MULTILINESTRING`, or the path of an OGR line file (reprojected "
            "to the view's spatial reference; needs GDAL). Unset: found in the data "
            "(`detect_breaklines`)."
        ),
    )


TABLE = options_table()


def outputs(opts):
    """{dimension: dtype} written (declare them in add_dimension)."""
    return OUTPUTS


def point_cells(res, xy: np.ndarray) -> np.ndarray:
    """(N,) int32: the row of ``res`` (its cells' order) of the cell each point ``xy`` (N, 2)
    lies in, -1 where that cell was not fitted or lies outside the grid."""
    k = np.full(res.n_rows * res.n_cols, -1, dtype=np.int32)
    k[res.row * res.n_cols + res.col] = np.arange(len(res), dtype=np.int32)
    flat = _stage.raster_index(xy, res.origin_xy, res.cell_m, (res.n_rows, res.n_cols))
    return np.where(flat >= 0, k[np.maximum(flat, 0)], -1).astype(np.int32)


def run(ins, outs, *, opts, inputs):
    """The field's cells as metadata; each point's cell and its motion into ``outs``."""
    from slipmap.app.summaries import icp_summary

    o = _stage.job_options(SPEC, opts)
    n = _stage.n_points(ins)
    if n == 0:
        _stage.set_field_outputs(outs, np.empty(0), np.empty((0, 3)), index_dim="IcpCell",
                                 stage=STAGE)  # fmt: skip
        return _stage.stage_node("icp", "empty point view")
    idx = _stage.epochs(ins, opts, STAGE)
    pts = _stage.points_from(ins, STAGE)
    lines = _stage.lines_option(opts["breaklines"], "breaklines", STAGE, inputs)
    res = job.compute(pts[idx["before"]], pts[idx["after"]], o, lines=lines)
    _stage.set_field_outputs(
        outs, point_cells(res, pts[:, :2]), np.column_stack([res.dx, res.dy, res.dz]),
        index_dim="IcpCell", stage=STAGE,
    )  # fmt: skip
    summary = {
        **icp_summary(res),
        "breaklines": job.breaklines_summary(res, _stage.lines_file_name(opts["breaklines"])),
    }
    mag = np.hypot(res.dx, res.dy)
    sig = np.hypot(res.sigma_dx, res.sigma_dy)
    headline = (
        f"windowed ICP: {len(res)} cells of {res.cell_m:g} m, median horizontal motion "
        f"{np.nanmedian(mag):.4f} m (median 1-sigma {np.nanmedian(sig):.4f} m), breaklines "
        f"{res.breaklines_source}"
        if len(res)
        else "windowed ICP: no cell fitted"
    )
    return _stage.stage_node(
        "icp",
        "SlipMap displacement field by windowed ICP: ground motion before -> after, metres "
        "(x east, y north, z up)",
        [
            _stage.metadata_node("headline", headline, "cells, median motion and 1-sigma"),
            _stage.metadata_node("summary", summary, "icp.json's summary"),
            _stage.metadata_node(
                "cells",
                {k: np.asarray(v).tolist() for k, v in job.layer_columns(res).items()},
                "the cells as columns (the CLI's icp.csv): x, y, z centre, dx, dy, dz and "
                "their 1-sigma (m), ...; IcpCell indexes them",
            ),
        ],
    )
