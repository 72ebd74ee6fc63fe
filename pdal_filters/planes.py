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

from slipmap.app.planes import SPEC, segment
from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import OptionTable

STAGE = "slipmap planes"
OUTPUTS = {"PlaneId": "int32", "Planarity": "float64"}


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md): the planes job's segmentation options."""
    return OptionTable.from_spec(STAGE, SPEC)


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
        pts = _stage.points_from(ins, STAGE)
        ps = segment(pts, _stage.job_options(SPEC, opts))
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
