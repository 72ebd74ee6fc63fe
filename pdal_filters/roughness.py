"""PDAL stage ``roughness``: grid roughness per point (``Roughness`` double, metres).

Pipeline stage (the script is ``slipmap_stages.py``, see :mod:`slipmap.pdal_filters`)::

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_roughness", "function": "roughness", "add_dimension": "Roughness",
     "pdalargs": {"cell": 0.5, "method": "odr"}}

The roughness job (:mod:`slipmap.app.roughness`) on each point view: the grid of cubic cells
of ``cell`` metres (the first value when several are given) and each point its cell's value:
``theta_odr`` (``method`` "odr") or ``theta_ols`` ("ols"); NaN for points in cells with fewer
than ``min_points`` points or degenerate cells. Options: :func:`options_table`, docs/pdal.md.
"""

import numpy as np

from slipmap.app.roughness import SPEC, compute, per_point
from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import OptionTable

STAGE = "slipmap roughness"
OUTPUTS = {"Roughness": "float64"}


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md): the roughness job's."""
    return OptionTable.from_spec(STAGE, SPEC)


TABLE = options_table()


def outputs(opts):
    """{dimension: dtype} written (declare them in add_dimension)."""
    return OUTPUTS


def run(ins, outs, *, opts, inputs):
    """Roughness per point into ``outs``; returns the metadata node."""
    job_opts = _stage.job_options(SPEC, opts)
    n = _stage.n_points(ins)
    values = np.full(n, np.nan)
    children = [_stage.metadata_node("n_points", n)]
    if n > 0:
        pts = _stage.points_from(ins, STAGE)
        res = compute(pts, {**job_opts, "cell_sizes_m": job_opts["cell_sizes_m"][:1]})
        grid = res.grids[0]
        values = per_point(pts, grid, job_opts["method"])
        children += [
            _stage.metadata_node("method", job_opts["method"]),
            _stage.metadata_node("n_cells", len(grid)),
            _stage.metadata_node("n_cells_skipped", grid.n_cells_skipped),
            _stage.metadata_node("cell_size_m", float(grid.cell_size_m)),
            _stage.metadata_node("ols_axis", grid.ols_axis),
        ]
    _stage.set_output(outs, "Roughness", values, np.float64, n, STAGE)
    return _stage.stage_node("roughness", "SlipMap grid roughness (m)", children)
