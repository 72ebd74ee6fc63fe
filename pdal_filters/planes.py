"""PDAL stage ``planes``: plane segmentation (``PlaneId`` int32, ``Planarity`` double).

Pipeline stage (the script is ``slipmap_stages.py``, see :mod:`slipmap.pdal_filters`)::

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_planes", "function": "planes",
     "add_dimension": ["PlaneId=int32", "Planarity"], "pdalargs": {"min_plane_points": 50}}

Each point view is segmented on its own with :func:`slipmap.core.planes.segment_planes`;
``PlaneId`` is the plane of each point (-1: none), ``Planarity`` the fraction of the point's
octree leaf within the planarity threshold (NaN where the leaf was too small to fit).
``out_metadata`` holds the segmentation parameters and plane count. Options: see
:func:`options_table` (and docs/pdal.md).
"""

import numpy as np

from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import Option, OptionTable

STAGE = "slipmap planes"
OUTPUTS = {"PlaneId": "int32", "Planarity": "float64"}


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md)."""
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


TABLE = options_table()


def outputs(opts):
    """{dimension: dtype} written (declare them in add_dimension)."""
    return OUTPUTS


def run(ins, outs, *, opts, inputs):
    """Segment the view; PlaneId and Planarity into ``outs``; returns the metadata node."""
    n = _stage.n_points(ins)
    labels = np.full(n, -1, dtype=np.int32)
    planarity = np.full(n, np.nan)
    n_planes = 0
    params = {}
    if n > 0:
        from slipmap.core.planes import segment_planes

        pts = _stage.points_from(ins, STAGE)
        kw = {k: v for k, v in opts.items() if k != "slipmap_path" and v is not None}
        ps = segment_planes(pts, **kw)
        labels, planarity = ps.labels, ps.planarity
        n_planes, params = len(ps), ps.parameters.to_dict()
    _stage.set_output(outs, "PlaneId", labels, np.int32, n, STAGE)
    _stage.set_output(outs, "Planarity", planarity, np.float64, n, STAGE)
    return _stage.stage_node(
        "planes",
        "SlipMap plane segmentation",
        [
            _stage.metadata_node("n_points", n),
            _stage.metadata_node("n_planes", n_planes),
            _stage.metadata_node("parameters", params, "segment_planes parameters"),
        ],
    )
