"""Run a SlipMap stage script the way PDAL's filters.python does, without PDAL.

filters.python reads the script, compiles it under its file name into a fresh module named by
the "module" option, injects ``pdalargs`` / ``schema`` / ``spatialreference`` / ``metadata``
as module globals, calls ``function(ins, outs)`` once per point view (``ins``: copies of the
view's dimensions; ``outs``: starts empty) and reads ``out_metadata`` back.
"""

from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
STAGE_DIR = ROOT / "pdal_filters"
PIPELINE_DIR = STAGE_DIR / "pipelines"

# PDAL's types for the LAS dimensions the stages may see
PDAL_TYPES = {
    "X": np.float64,
    "Y": np.float64,
    "Z": np.float64,
    "Intensity": np.uint16,
    "ReturnNumber": np.uint8,
    "NumberOfReturns": np.uint8,
    "Classification": np.uint8,
    "ScanAngleRank": np.float32,
    "UserData": np.uint8,
    "PointSourceId": np.uint16,
    "GpsTime": np.float64,
    "Epoch": np.float64,  # filters.assign on a dimension added as double
}

# add_dimension "Name" (no type) gives a double; "Name=type" that type
PDAL_NAMED_TYPES = {
    "double": np.float64,
    "float": np.float32,
    "int8": np.int8,
    "int16": np.int16,
    "int32": np.int32,
    "int64": np.int64,
    "uint8": np.uint8,
    "uint16": np.uint16,
    "uint32": np.uint32,
    "uint64": np.uint64,
}


def parse_add_dimension(value) -> dict:
    """{name: numpy dtype} of an add_dimension option (a string or a list of strings)."""
    items = [value] if isinstance(value, str) else list(value or [])
    out = {}
    for item in items:
        name, _, typ = item.partition("=")
        out[name.strip()] = np.dtype(PDAL_NAMED_TYPES[typ.strip().lower() or "double"])
    return out


def load_stage(script: Path, module_name: str, pdalargs=None, spatialreference: str = ""):
    """Compile and exec ``script`` as filters.python does; returns the module."""
    source = Path(script).read_text()
    code = compile(source, str(script), "exec")
    module = types.ModuleType(module_name)
    if pdalargs is not None:
        module.pdalargs = pdalargs
    module.schema = {"schema": {"dimensions": []}}
    module.spatialreference = spatialreference
    module.metadata = {}
    exec(code, module.__dict__)
    return module


def make_ins(points: np.ndarray, **extra) -> dict:
    """A PDAL-typed ``ins`` dict: X/Y/Z float64 plus the given dimensions (copies)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = pts.shape[0]
    ins = {
        "X": pts[:, 0].copy(),
        "Y": pts[:, 1].copy(),
        "Z": pts[:, 2].copy(),
        "Intensity": np.zeros(n, np.uint16),
        "Classification": np.full(n, 6, np.uint8),
        "GpsTime": np.linspace(0.0, 1.0, n),
    }
    for k, v in extra.items():
        ins[k] = np.asarray(v).astype(PDAL_TYPES.get(k, np.float64)).copy()
    return ins


def call(module, ins: dict, declared: dict, function: str = "run") -> dict:
    """Call the stage on one view and check the filters.python output contract."""
    outs: dict = {}
    r = getattr(module, function)({k: v.copy() for k, v in ins.items()}, outs)
    assert type(r) is bool and r is True, f"{function} returned {r!r}"
    n = len(next(iter(ins.values()))) if ins else 0
    for name, arr in outs.items():
        assert name in declared or name in ins, f"undeclared output dimension {name!r}"
        want = declared.get(name, ins[name].dtype if name in ins else None)
        assert isinstance(arr, np.ndarray), name
        assert arr.dtype == want, (name, arr.dtype, want)
        assert arr.shape == (n,), (name, arr.shape, n)
    json.dumps(getattr(module, "out_metadata", {}))  # PDAL must be able to read it back
    return outs


def pipeline_stages(path: Path) -> list:
    doc = json.loads(Path(path).read_text())
    stages = doc["pipeline"] if isinstance(doc, dict) else doc
    return [s if isinstance(s, dict) else {"type": "readers.las", "filename": s} for s in stages]
