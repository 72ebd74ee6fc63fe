"""SlipMap's PDAL ``filters.python`` stages: one script, one function per job.

    {"type": "filters.python", "script": "pdal_filters/slipmap_stages.py",
     "module": "slipmap_planes", "function": "planes",
     "add_dimension": ["PlaneId=int32", "Planarity"], "pdalargs": {"min_plane_points": 50}}

Functions: ``planes``, ``roughness``, ``accuracy``, ``displacement``, ``icp``,
``piv`` (docs/pdal.md). Where this file is: ``python -m slipmap.pdal_filters``.

PDAL compiles this file on its own, under the ``module`` name and without its path, and puts
``pdalargs``, ``spatialreference``, ``schema`` and ``metadata`` into its globals before each
call. So all this file does is find the ``slipmap`` package (installed in PDAL's Python, or
where ``pdalargs["slipmap_path"]`` says: the one place that option is read) and hand the call
to ``slipmap.pdal_filters``, which sets ``out_metadata``. Standard library only.
"""

import importlib
import importlib.util
import os
import sys

out_metadata = {}


def planes(ins, outs):
    """Plane segmentation: PlaneId (int32), Planarity."""
    return _run("planes", ins, outs)


def roughness(ins, outs):
    """Grid roughness: Roughness (m)."""
    return _run("roughness", ins, outs)


def accuracy(ins, outs):
    """Per-point accuracy: SigmaX, SigmaY, SigmaZ (m), optionally the covariance (m²)."""
    return _run("accuracy", ins, outs)


def displacement(ins, outs):
    """Fault slip between two merged epochs: PlaneId (int32), Residual (m), summary."""
    return _run("displacement", ins, outs)


def icp(ins, outs):
    """Displacement field between two merged epochs: DisplacementX/Y/Z (m), IcpCell (int32)."""
    return _run("icp", ins, outs)


def piv(ins, outs):
    """PIV field between two merged epochs: DisplacementX/Y/Z (m), PivVector (int32)."""
    return _run("piv", ins, outs)


def _run(job, ins, outs):
    global out_metadata
    _find_slipmap(globals().get("pdalargs"), job)
    stage = importlib.import_module("slipmap.pdal_filters." + job)
    from slipmap.pdal_filters._stage import run_stage

    out_metadata = run_stage(stage, ins, outs, globals())
    return True


def _find_slipmap(pdalargs, job):
    """Import ``slipmap``: already imported or installed, else from ``slipmap_path``."""
    if "slipmap" in sys.modules:
        return
    path = None
    if isinstance(pdalargs, str) and "slipmap_path" in pdalargs:
        import json

        try:
            pdalargs = json.loads(pdalargs)
        except ValueError:
            pdalargs = None  # the stage reports the bad JSON once slipmap is found
    if isinstance(pdalargs, dict):
        path = pdalargs.get("slipmap_path")
    if path:
        root = os.path.abspath(os.path.expanduser(str(path)))
        init = os.path.join(root, "__init__.py")
        if os.path.isfile(init) and os.path.isdir(os.path.join(root, "core")):
            # the package root itself, whatever its folder is called (a git checkout)
            spec = importlib.util.spec_from_file_location(
                "slipmap", init, submodule_search_locations=[root]
            )
            module = importlib.util.module_from_spec(spec)
            sys.modules["slipmap"] = module
            try:
                spec.loader.exec_module(module)
            except BaseException:
                del sys.modules["slipmap"]
                raise
            return
        if not os.path.isdir(os.path.join(root, "slipmap")):
            raise RuntimeError(
                f"slipmap {job}: option 'slipmap_path': {root!r} holds no slipmap package; "
                "give the folder containing 'slipmap' or a SlipMap checkout"
            )
        if root not in sys.path:
            sys.path.insert(0, root)
    try:
        importlib.import_module("slipmap")
    except ImportError as e:
        raise RuntimeError(
            f"slipmap {job}: cannot import slipmap ({e}). Install it into PDAL's Python "
            "(python -m pip install slipmap, in the conda environment that has PDAL) or set "
            'pdalargs {"slipmap_path": "/path/to/slipmap"}'
        ) from None
