"""PDAL ``filters.python`` stage: grid roughness per point (``Roughness`` double, metres).

Pipeline stage::

    {"type": "filters.python", "script": "pdal_filters/roughness.py",
     "module": "slipmap_roughness", "function": "run", "add_dimension": "Roughness",
     "pdalargs": {"cell": 0.5, "method": "odr"}}

Each point view gets :func:`slipmap.core.roughness.grid_roughness` on cubic cells of ``cell``
metres, and each point its cell's value (:func:`slipmap.core.roughness.roughness_per_point`):
``theta_odr`` (``method`` "odr") or ``theta_ols`` ("ols"); NaN for points in cells with fewer
than ``min_points`` points or degenerate cells. Options: :func:`options_table`, docs/pdal.md.
"""

import json
import os
import sys

STAGE = "slipmap roughness"
OUTPUTS = {"Roughness": "float64"}
out_metadata = {}


def _bootstrap():
    """Make ``slipmap`` importable: PDAL compiles this file standalone (cf. _stage)."""
    if "slipmap" in sys.modules:
        return
    args = globals().get("pdalargs")
    if isinstance(args, str):
        try:
            args = json.loads(args) if args.strip() else {}
        except ValueError:
            args = {}
    path = args.get("slipmap_path") if isinstance(args, dict) else None
    if path:
        p = os.path.abspath(os.path.expanduser(str(path)))
        init = os.path.join(p, "__init__.py")
        if os.path.isfile(init) and os.path.isdir(os.path.join(p, "core")):
            import importlib.util

            spec = importlib.util.spec_from_file_location(
                "slipmap", init, submodule_search_locations=[p]
            )
            module = importlib.util.module_from_spec(spec)
            sys.modules["slipmap"] = module
            spec.loader.exec_module(module)
        elif p not in sys.path:
            sys.path.insert(0, p)
    try:
        import slipmap  # noqa: F401
    except ImportError as e:
        raise RuntimeError(
            f"{STAGE}: cannot import slipmap ({e}); install it in PDAL's Python "
            '(pip install slipmap) or pass pdalargs {"slipmap_path": "/dir/containing/slipmap"}'
        ) from None


def options_table():
    from slipmap.pdal_filters._stage import Option, OptionTable

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
                "z",
                "Dependent axis of the OLS plane (`auto`: closest to the cloud's normal).",
                choices=("x", "y", "z", "auto"),
            ),
        ],
    )


_TABLE = []


def run(ins, outs):
    """filters.python entry point: adds Roughness to the view."""
    global out_metadata
    _bootstrap()
    import numpy as np

    from slipmap.pdal_filters import _stage

    if not _TABLE:
        _TABLE.append(options_table())
    opts = _TABLE[0].parse(globals().get("pdalargs"))
    n = _stage.n_points(ins)
    values = np.full(n, np.nan)
    children = [_stage.metadata_node("n_points", n)]
    if n > 0:
        from slipmap.core.errors import SlipMapError
        from slipmap.core.roughness import grid_roughness, roughness_per_point

        pts = _stage.points_from(ins, STAGE)
        try:
            grid = grid_roughness(
                pts,
                cell_size_m=opts["cell"],
                min_points=opts["min_points"],
                ols_axis=opts["ols_axis"],
                signed=opts["signed"],
            )
            values = roughness_per_point(pts, grid, value="theta_" + opts["method"])
        except SlipMapError as e:
            raise _stage.wrap_errors(STAGE, e) from e
        children += [
            _stage.metadata_node("n_cells", len(grid)),
            _stage.metadata_node("n_cells_skipped", grid.n_cells_skipped),
            _stage.metadata_node("cell_size_m", float(grid.cell_size_m)),
            _stage.metadata_node("ols_axis", grid.ols_axis),
        ]
    _stage.set_output(outs, "Roughness", values, np.float64, n, STAGE)
    out_metadata = _stage.metadata_node(
        "slipmap_roughness", opts["method"], "SlipMap grid roughness", children
    )
    return True
