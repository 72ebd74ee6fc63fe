"""PDAL stage ``accuracy``: per-point accuracy ``SigmaX/SigmaY/SigmaZ`` (double, metres).

Pipeline stage (the script is ``slipmap_stages.py``, see :mod:`slipmap.pdal_filters`)::

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_accuracy", "function": "accuracy",
     "add_dimension": ["SigmaX", "SigmaY", "SigmaZ"],
     "pdalargs": {"model": "propagated", "trajectory": "sbet.out",
                  "trajectory_accuracy": "smrmsg.out", "scanner": "riegl-vz400"}}

The point-accuracy models of :mod:`slipmap.core.accuracy` (constant, per-axis, per-point
columns, georeferencing propagation with the beam-footprint term), chosen and fed exactly as
``slipmap accuracy`` does (:mod:`slipmap.app.pointaccuracy`). With ``full_covariance`` the six
entries ``CovXX CovYY CovZZ CovXY CovXZ CovYZ`` (m²) are written too; declare them in
``add_dimension``. The propagated model reads ``GpsTime`` and ``ScanAngleRank`` (degrees,
PDAL's name) from the view and the view's spatial reference (``spatialreference``).
Options: :func:`options_table`, docs/pdal.md.
"""

import numpy as np

from slipmap.pdal_filters import _stage
from slipmap.pdal_filters._stage import Option, OptionTable

STAGE = "slipmap accuracy"
SIGMAS = ("SigmaX", "SigmaY", "SigmaZ")
COVS = ("CovXX", "CovYY", "CovZZ", "CovXY", "CovXZ", "CovYZ")


def outputs(options):
    """{dimension: dtype} the stage writes with these parsed options (declare them all)."""
    names = SIGMAS + (COVS if options.get("full_covariance") else ())
    return {name: "float64" for name in names}


def options_table() -> OptionTable:
    """The stage's options (docs/pdal.md)."""
    return OptionTable(
        STAGE,
        [
            Option(
                "model",
                "choice",
                "constant",
                "Point-accuracy model: constant σ, per-axis σ, per-point σ dimensions, or "
                "georeferencing propagation (+ beam footprint).",
                choices=("constant", "axis", "columns", "propagated"),
            ),
            Option(
                "sigma",
                "float",
                0.05,
                "Isotropic σ (m), model `constant`.",
                minimum=0,
                exclusive=True,
            ),
            Option(
                "sigma_xyz",
                "vector3",
                None,
                "Per-axis σ [SX, SY, SZ] (m), model `axis`.",
                minimum=0,
            ),
            Option(
                "columns",
                "names",
                None,
                "Dimensions holding per-point σ (m), model `columns` "
                "(default SigmaX, SigmaY, SigmaZ).",
            ),
            Option(
                "trajectory",
                "str",
                None,
                "SBET or CSV trajectory file (model `propagated`, mobile/airborne).",
            ),
            Option(
                "trajectory_accuracy",
                "str",
                None,
                "SMRMSG or CSV trajectory accuracy file (model `propagated`).",
            ),
            Option(
                "scanner",
                "str",
                None,
                "Scanner specification: riegl-vz400, leica-als60, optech-orion or a JSON "
                "file (model `propagated`).",
            ),
            Option(
                "scanner_position",
                "vector3",
                None,
                "Static (TLS) scanner position [X, Y, Z] in the view's CRS, instead of a "
                "trajectory (model `propagated`).",
            ),
            Option(
                "footprint",
                "bool",
                True,
                "Add the beam-footprint (surface geometry) term, model `propagated`.",
            ),
            Option(
                "full_covariance",
                "bool",
                False,
                "Also write CovXX CovYY CovZZ CovXY CovXZ CovYZ (m²); declare them in "
                "add_dimension.",
            ),
        ],
    )


TABLE = options_table()


def _settings(opts):
    keys = (
        "model",
        "sigma",
        "sigma_xyz",
        "columns",
        "trajectory",
        "trajectory_accuracy",
        "scanner",
        "scanner_position",
        "footprint",
    )
    return {k: opts[k] for k in keys if opts[k] is not None}


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
    n = _stage.n_points(ins)
    sig = np.full((n, 3), np.nan)
    six = np.full((n, 6), np.nan)
    children = [_stage.metadata_node("n_points", n), _stage.metadata_node("model", opts["model"])]
    if n > 0:
        from slipmap.app.pointaccuracy import covariance_matrices
        from slipmap.core.accuracy import covariance_to_sigmas, covariance_to_six

        pts = _stage.points_from(ins, STAGE)
        cov = covariance_matrices(_cloud(ins, pts, inputs), None, _settings(opts))
        sig = covariance_to_sigmas(cov)
        if opts["full_covariance"]:
            six = covariance_to_six(cov)
        med = np.median(sig, axis=0)
        children += [
            _stage.metadata_node(f"median_{k.lower()}_m", float(v)) for k, v in zip(SIGMAS, med)
        ]
    for k, name in enumerate(SIGMAS):
        _stage.set_output(outs, name, sig[:, k], np.float64, n, STAGE)
    if opts["full_covariance"]:
        for k, name in enumerate(COVS):
            _stage.set_output(outs, name, six[:, k], np.float64, n, STAGE)
    return _stage.stage_node("accuracy", "SlipMap per-point accuracy (m)", children)
