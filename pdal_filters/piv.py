"""PDAL stage ``piv``: the PIV displacement field (:mod:`slipmap.app.piv`) of two merged epochs.

The two epochs arrive as one point view tagged by an epoch dimension (``Epoch``: 1 = before,
2 = after, as for the ``displacement`` and ``icp`` stages). Both are gridded into elevation
models on one grid of ``grid_m`` and correlated window by window
(:func:`slipmap.app.piv.dems`, :func:`slipmap.app.piv.piv_of_dems`, the CLI's one-file
run). Breaklines (scarps, a fault) are given as ``breaklines``: WKT ``LINESTRING`` /
``MULTILINESTRING`` in the points' CRS, or the path of an OGR line file (reprojected to the
view's spatial reference); windows are then not smeared across them and the vectors whose
window crosses one are flagged (``near_break``).

Every point gets the vector whose square (the vector spacing around it) it lies in:

* ``DisplacementX``, ``DisplacementY``, ``DisplacementZ`` (double, metres): east, north, up,
  before to after; NaN where the vector has none (too little data) or for a point outside
  the vector grid;
* ``PivVector`` (int32): the vector's row in the metadata's ``vectors`` table; -1 for none.

``out_metadata`` holds a headline, the summary (grid, windows, vector counts, the valid
share, the vectors near a breakline) and ``vectors``, the CLI's table as columns.

Pipeline stage (the script is ``slipmap_stages.py``, see :mod:`slipmap.pdal_filters`)::

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_piv", "function": "piv",
     "add_dimension": ["DisplacementX", "DisplacementY", "DisplacementZ", "PivVector=int32"],
     "pdalargs": {"grid_m": 0.15, "breaklines": "scarps.gpkg"}}

Options: the job's (:data:`slipmap.app.piv.SPEC`) that PDAL shows, plus the breaklines and
the epoch tagging (:func:`options_table`, docs/pdal.md).
"""

import numpy as np

from slipmap.app import piv as job
from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import OptionTable

STAGE = "slipmap piv"
SPEC = job.SPEC
OUTPUTS = _stage.field_outputs("PivVector")


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md): the breaklines, the epoch tagging, the job's."""
    return OptionTable.from_spec(
        STAGE,
        SPEC,
        extra=_stage.field_options(
            "Lines the windows must not be smeared across (scarps, a fault), in the points' "
            "CRS: WKT `LINESTRING`/`MULTILINESTRING`, or the path of an OGR line file "
            "(reprojected to the view's spatial reference; needs GDAL)."
        ),
    )


TABLE = options_table()


def outputs(opts):
    """{dimension: dtype} written (declare them in add_dimension)."""
    return OUTPUTS


def run(ins, outs, *, opts, inputs):
    """The vectors as metadata; each point's vector and its motion into ``outs``."""
    from slipmap.app.fields import horizontal_columns
    from slipmap.app.summaries import finite_stats

    o = _stage.job_options(SPEC, opts)
    n = _stage.n_points(ins)
    if n == 0:
        _stage.set_field_outputs(outs, np.empty(0), np.empty((0, 3)), index_dim="PivVector",
                                 stage=STAGE)  # fmt: skip
        return _stage.stage_node("piv", "empty point view")
    idx = _stage.epochs(ins, opts, STAGE)
    pts = _stage.points_from(ins, STAGE)
    lines = _stage.lines_option(opts["breaklines"], "breaklines", STAGE, inputs)
    wins = job.windows(o)
    grid, zb, za = job.dems(pts[idx["before"]], pts[idx["after"]], o, wins)
    res = job.piv_of_dems(zb, za, grid, o, wins, lines=lines)
    cols = res.to_columns()
    _stage.set_field_outputs(
        outs, _stage.raster_index(pts[:, :2], res.origin_xy, res.spacing_m, res.shape),
        np.column_stack([cols["dx"], cols["dy"], cols["dz"]]), index_dim="PivVector",
        stage=STAGE,
    )  # fmt: skip
    mag = np.hypot(res.dx, res.dy)
    summary = {
        "grid_m": grid.cell_m,
        "dem_shape": list(grid.shape),
        "windows_px": list(res.windows_px),
        "overlap": o["overlap"],
        "search_px": res.search_px,
        "vector_spacing_m": res.spacing_m,
        "n_vectors": int(res.dx.size),
        "n_with_value": int(np.count_nonzero(np.isfinite(res.dx) & np.isfinite(res.dy))),
        "valid_fraction": float(res.valid.mean()) if res.valid.size else 0.0,
        "breaklines": _stage.lines_file_name(opts["breaklines"]) if lines is not None else None,
        "breaklines_given": lines is not None,
        "n_near_break": int(res.near_break_or_false().sum()),
        "horizontal_m": finite_stats(mag),
        "dz_m": finite_stats(res.dz),
    }
    headline = (
        f"PIV: {res.dx.size} vectors every {res.spacing_m:g} m "
        f"({100 * summary['valid_fraction']:.0f} % valid), median horizontal "
        f"{summary['horizontal_m'].get('median', float('nan')):.4f} m"
    )
    table = dict(cols, **horizontal_columns(cols["dx"], cols["dy"]))
    return _stage.stage_node(
        "piv",
        "SlipMap displacement field by PIV on gridded elevation: ground motion before -> "
        "after, metres (x east, y north, z up)",
        [
            _stage.metadata_node("headline", headline, "vectors, valid share, median motion"),
            _stage.metadata_node("summary", summary, "piv.json's summary"),
            _stage.metadata_node(
                "vectors",
                {k: np.asarray(v).tolist() for k, v in table.items()},
                "the vectors as columns (the CLI's piv.csv, row-major, north first): x, y, "
                "dx, dy, dz (m), snr, valid, near_break, magnitude, azimuth_deg; PivVector "
                "indexes them",
            ),
        ],
    )
