"""PDAL stage ``roughness``: grid roughness per point (``Roughness`` double, metres).

Pipeline stage (the script is ``slipmap_stages.py``, see :mod:`slipmap.pdal_filters`)::

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_roughness", "function": "roughness", "add_dimension": "Roughness",
     "pdalargs": {"cell": 0.5, "method": "odr"}}

Each point view gets :func:`slipmap.core.roughness.grid_roughness` on cubic cells of ``cell``
metres, and each point its cell's value (:func:`slipmap.core.roughness.roughness_per_point`):
``theta_odr`` (``method`` "odr") or ``theta_ols`` ("ols"); NaN for points in cells with fewer
than ``min_points`` points or degenerate cells. Options: :func:`options_table`, docs/pdal.md.
"""

import numpy as np

from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import Option, OptionTable

STAGE = "slipmap roughness"
OUTPUTS = {"Roughness": "float64"}


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md)."""
    return OptionTable(
        STAGE,
        [
            Option("cell", "float", 0.5, "Cubic cell edge (m).", minimum=0, exclusive=True),
            Option(
                "method",
                "choice",
                "odr",
                "Roughness written: ODR plane (Eq. 4) or OLS plane along `ols_axis`.",
                choices=("odr", "ols"),
            ),
            Option(
                "signed",
                "bool",
                False,
                "false: std of absolute distances (as published); true: of signed distances.",
            ),
            Option("min_points", "int", 10, "Cells with fewer points get NaN.", minimum=3),
            Option(
                "ols_axis",
                "choice",
                "auto",
                "Dependent axis of the OLS plane (`auto`: closest to the cloud's normal, as "
                "the CLI and QGIS).",
                choices=("x", "y", "z", "auto"),
            ),
        ],
    )


TABLE = options_table()


def outputs(opts):
    """{dimension: dtype} written (declare them in add_dimension)."""
    return OUTPUTS


def run(ins, outs, *, opts, inputs):
    """Roughness per point into ``outs``; returns the metadata node."""
    n = _stage.n_points(ins)
    values = np.full(n, np.nan)
    children = [_stage.metadata_node("n_points", n)]
    if n > 0:
        from slipmap.core.roughness import grid_roughness, roughness_per_point

        pts = _stage.points_from(ins, STAGE)
        grid = grid_roughness(
            pts,
            cell_size_m=opts["cell"],
            min_points=opts["min_points"],
            ols_axis=opts["ols_axis"],
            signed=opts["signed"],
        )
        values = roughness_per_point(pts, grid, value="theta_" + opts["method"])
        children += [
            _stage.metadata_node("method", opts["method"]),
            _stage.metadata_node("n_cells", len(grid)),
            _stage.metadata_node("n_cells_skipped", grid.n_cells_skipped),
            _stage.metadata_node("cell_size_m", float(grid.cell_size_m)),
            _stage.metadata_node("ols_axis", grid.ols_axis),
        ]
    _stage.set_output(outs, "Roughness", values, np.float64, n, STAGE)
    return _stage.stage_node("roughness", "SlipMap grid roughness (m)", children)
