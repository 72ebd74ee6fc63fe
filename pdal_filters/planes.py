"""PDAL ``filters.python`` stage: plane segmentation (``PlaneId`` int32, ``Planarity`` double).

Pipeline stage::

    {"type": "filters.python", "script": "pdal_filters/planes.py", "module": "slipmap_planes",
     "function": "run", "add_dimension": ["PlaneId=int32", "Planarity"],
     "pdalargs": {"min_plane_points": 50}}

Each point view is segmented on its own with :func:`slipmap.core.planes.segment_planes`;
``PlaneId`` is the plane of each point (-1: none), ``Planarity`` the fraction of the point's
octree leaf within the planarity threshold (NaN where the leaf was too small to fit).
``out_metadata`` holds the segmentation parameters and plane count. Options: see
:func:`options_table` (and docs/pdal.md).
"""

import json
import os
import sys

STAGE = "slipmap planes"
OUTPUTS = {"PlaneId": "int32", "Planarity": "float64"}
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
            Option(
                "min_node_size_m",
                "float",
                None,
                "Smallest octree leaf edge (m).",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "max_node_size_m",
                "float",
                None,
                "Largest leaf edge tested (m); default 4x the leaf.",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "planarity_threshold_m",
                "float",
                None,
                "Distance to a leaf's plane counted as on it (m); default 3x the noise.",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "planarity_ratio",
                "float",
                None,
                "Fraction of a leaf's points within the threshold; default 0.9.",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "angle_threshold_deg",
                "float",
                None,
                "Largest angle between joined leaves' normals (degrees).",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "distance_threshold_m",
                "float",
                None,
                "Largest leaf-centroid to neighbour-plane distance (m); default: the planarity "
                "threshold.",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "min_plane_points",
                "int",
                None,
                "Smallest reported plane (points); default 3 typical leaves, >= 30.",
                minimum=1,
            ),
            Option(
                "min_leaf_points",
                "int",
                None,
                "Smallest leaf that is fitted; default 10.",
                minimum=3,
            ),
            Option(
                "backend",
                "choice",
                "numpy",
                "Kernel implementation (same labels).",
                choices=("numpy", "opencl", "auto"),
            ),
        ],
    )


_TABLE = []


def run(ins, outs):
    """filters.python entry point: adds PlaneId and Planarity to the view."""
    global out_metadata
    _bootstrap()
    import numpy as np

    from slipmap.pdal_filters import _stage

    if not _TABLE:
        _TABLE.append(options_table())
    opts = _TABLE[0].parse(globals().get("pdalargs"))
    n = _stage.n_points(ins)
    labels = np.full(n, -1, dtype=np.int32)
    planarity = np.full(n, np.nan)
    n_planes = 0
    params = {}
    if n > 0:
        from slipmap.core.errors import SlipMapError
        from slipmap.core.planes import segment_planes

        pts = _stage.points_from(ins, STAGE)
        kw = {k: v for k, v in opts.items() if k != "slipmap_path" and v is not None}
        try:
            ps = segment_planes(pts, **kw)
        except SlipMapError as e:
            raise _stage.wrap_errors(STAGE, e) from e
        labels, planarity = ps.labels, ps.planarity
        n_planes, params = len(ps), ps.parameters.to_dict()
    _stage.set_output(outs, "PlaneId", labels, np.int32, n, STAGE)
    _stage.set_output(outs, "Planarity", planarity, np.float64, n, STAGE)
    out_metadata = _stage.metadata_node(
        "slipmap_planes",
        "",
        "SlipMap plane segmentation",
        [
            _stage.metadata_node("n_points", n),
            _stage.metadata_node("n_planes", n_planes),
            _stage.metadata_node("parameters", params, "segment_planes parameters (JSON)"),
        ],
    )
    return True
