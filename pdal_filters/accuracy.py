"""PDAL stage ``accuracy``: per-point accuracy ``SigmaX/SigmaY/SigmaZ`` (double, metres).

Pipeline stage (the script is ``slipmap_stages.py``, see :mod:`slipmap.pdal_filters`)::

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_accuracy", "function": "accuracy",
     "add_dimension": ["SigmaX", "SigmaY", "SigmaZ"],
     "pdalargs": {"model": "propagated", "trajectory": "sbet.out",
                  "trajectory_accuracy": "smrmsg.out", "scanner": "riegl-vz400"}}

The accuracy job (:mod:`slipmap.app.accuracy`) on the point view: the same options and
models as ``slipmap accuracy`` and QGIS's Point accuracy. With ``full_covariance`` the six
entries ``CovXX CovYY CovZZ CovXY CovXZ CovYZ`` (m²) are written too; declare them in
``add_dimension``. The propagated model reads ``GpsTime`` and ``ScanAngleRank`` (degrees,
PDAL's name) from the view and the view's spatial reference (``spatialreference``).
Options: :func:`options_table`, docs/pdal.md.
"""

import numpy as np

from slipmap.app.accuracy import COVS, SIGMAS, SPEC, dimensions, model_of, outputs_of
from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import OptionTable

STAGE = "slipmap accuracy"


def outputs(options):
    """{dimension: dtype} the stage writes with these parsed options (declare them all)."""
    return {name: "float64" for name in outputs_of(options)}


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md): the accuracy job's."""
    return OptionTable.from_spec(STAGE, SPEC)


TABLE = options_table()


def _cloud(ins, pts, inputs):
    """The view as a core.io PointCloud (PDAL names; ScanAngleRank is PDAL's scan angle)."""
    from pathlib import Path

    from slipmap.core.io.las import PointCloud

    attrs = {k: v for k, v in ins.items() if k not in ("X", "Y", "Z")}
    if "ScanAngle" not in attrs and "ScanAngleRank" in attrs:
        attrs["ScanAngle"] = attrs["ScanAngleRank"]
    crs = inputs.crs(STAGE)
    return PointCloud(pts, attributes=attrs, crs=crs, source=Path("PDAL point view"))


def run(ins, outs, *, opts, inputs):
    """SigmaX/SigmaY/SigmaZ (and Cov* with full_covariance) into ``outs``; the metadata node."""
    job_opts = _stage.job_options(SPEC, opts)
    n = _stage.n_points(ins)
    names = outputs_of(job_opts)
    values = {name: np.full(n, np.nan) for name in names}
    children = [
        _stage.metadata_node("n_points", n),
        _stage.metadata_node("model", model_of(job_opts)),
    ]
    if n > 0:
        pts = _stage.points_from(ins, STAGE)
        values = dimensions(_cloud(ins, pts, inputs), job_opts)
        med = np.median(np.column_stack([values[k] for k in SIGMAS]), axis=0)
        children += [
            _stage.metadata_node(f"median_{k.lower()}_m", float(v)) for k, v in zip(SIGMAS, med)
        ]
    for name in names:
        _stage.set_output(outs, name, values[name], np.float64, n, STAGE)
    return _stage.stage_node("accuracy", "SlipMap per-point accuracy (m)", children)


__all__ = ["COVS", "SIGMAS", "STAGE", "TABLE", "options_table", "outputs", "run"]
