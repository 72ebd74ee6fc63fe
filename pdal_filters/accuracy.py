"""PDAL ``filters.python`` stage: per-point accuracy ``SigmaX/SigmaY/SigmaZ`` (double, metres).

Pipeline stage::

    {"type": "filters.python", "script": "pdal_filters/accuracy.py",
     "module": "slipmap_accuracy", "function": "run",
     "add_dimension": ["SigmaX", "SigmaY", "SigmaZ"],
     "pdalargs": {"model": "propagated", "trajectory": "sbet.out",
                  "trajectory_accuracy": "smrmsg.out", "scanner": "riegl-vz400"}}

The point-accuracy models of :mod:`slipmap.core.accuracy` (constant, per-axis, per-point
columns, georeferencing propagation with the beam-footprint term), chosen and fed exactly as
``slipmap accuracy`` does (:mod:`slipmap.pointaccuracy`). With ``full_covariance`` the six
entries ``CovXX CovYY CovZZ CovXY CovXZ CovYZ`` (m²) are written too; declare them in
``add_dimension``. The propagated model reads ``GpsTime`` and ``ScanAngleRank`` (degrees,
PDAL's name) from the view and the view's spatial reference. Options: :func:`options_table`,
docs/pdal.md.
"""

import json
import os
import sys

STAGE = "slipmap accuracy"
SIGMAS = ("SigmaX", "SigmaY", "SigmaZ")
COVS = ("CovXX", "CovYY", "CovZZ", "CovXY", "CovXZ", "CovYZ")


def outputs(options):
    """{dimension: dtype} the stage writes with these parsed options (declare them all)."""
    names = SIGMAS + (COVS if options.get("full_covariance") else ())
    return {name: "float64" for name in names}


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


_TABLE = []


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


def _cloud(ins, pts):
    """The view as a core.io PointCloud (PDAL names; ScanAngleRank is PDAL's scan angle)."""
    from pathlib import Path

    from slipmap.core.io.las import PointCloud

    attrs = {k: v for k, v in ins.items() if k not in ("X", "Y", "Z")}
    if "ScanAngle" not in attrs and "ScanAngleRank" in attrs:
        attrs["ScanAngle"] = attrs["ScanAngleRank"]
    crs = None
    wkt = globals().get("spatialreference") or ""
    if isinstance(wkt, str) and wkt.strip():
        import pyproj

        crs = pyproj.CRS.from_user_input(wkt)
    return PointCloud(pts, attributes=attrs, crs=crs, source=Path("PDAL point view"))


def run(ins, outs):
    """filters.python entry point: adds SigmaX/SigmaY/SigmaZ (and Cov* with full_covariance)."""
    global out_metadata
    _bootstrap()
    import numpy as np

    from slipmap.pdal_filters import _stage

    if not _TABLE:
        _TABLE.append(options_table())
    opts = _TABLE[0].parse(globals().get("pdalargs"))
    n = _stage.n_points(ins)
    sig = np.full((n, 3), np.nan)
    six = np.full((n, 6), np.nan)
    children = [_stage.metadata_node("n_points", n)]
    if n > 0:
        from slipmap.core.accuracy import covariance_to_sigmas, covariance_to_six
        from slipmap.core.errors import SlipMapError
        from slipmap.pointaccuracy import covariance_matrices

        pts = _stage.points_from(ins, STAGE)
        try:
            cov = covariance_matrices(_cloud(ins, pts), None, _settings(opts))
            sig = covariance_to_sigmas(cov)
            if opts["full_covariance"]:
                six = covariance_to_six(cov)
        except SlipMapError as e:
            raise _stage.wrap_errors(STAGE, e) from e
        med = np.median(sig, axis=0)
        children += [
            _stage.metadata_node(f"median_{k.lower()}_m", float(v)) for k, v in zip(SIGMAS, med)
        ]
    for k, name in enumerate(SIGMAS):
        _stage.set_output(outs, name, sig[:, k], np.float64, n, STAGE)
    if opts["full_covariance"]:
        for k, name in enumerate(COVS):
            _stage.set_output(outs, name, six[:, k], np.float64, n, STAGE)
    out_metadata = _stage.metadata_node(
        "slipmap_accuracy", opts["model"], "SlipMap per-point accuracy (m)", children
    )
    return True
