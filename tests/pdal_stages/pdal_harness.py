"""Run SlipMap's stage script the way PDAL 2.8's filters.python does, without PDAL.

What real PDAL (2.8.4, pdal-plugins 1.6.5) does, and this stand-in copies (tests/pdal_stages/
test_real_pdal.py checks the copy against real PDAL where it is installed):

* reads the script and compiles it with ``Py_CompileString(source, <module name>)`` and
  ``PyImport_ExecCodeModule(<module name>)``: the module is registered in ``sys.modules``
  under the ``module`` option, and ``__file__`` is that name, not the script's path;
* before each call puts into the module's globals ``pdalargs`` (the option parsed as JSON: a
  dict, also when the pipeline gives JSON text; None without the option), ``schema``
  (``{"schema": {"dimensions": [{"name", "size", "type"}, ...]}}``), ``spatialreference``
  (the view's SRS metadata ``{"srs": {"wkt": ..., "compoundwkt": ..., ...}}``, empty strings
  without an SRS) and ``metadata`` (the pipeline's metadata tree);
* calls ``function(ins, outs)`` per view (``ins``: copies of every dimension, PDAL-typed;
  ``outs`` starts empty) and reads ``out_metadata`` back with :func:`read_back`'s rules.
"""

from __future__ import annotations

import json
import math
import sys
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
#: PDAL and the CLI compute roughness in another order of floating-point sums: equal to this
ROUGHNESS_ATOL_M = 1e-12
STAGE_DIR = ROOT / "pdal_filters"
SCRIPT = STAGE_DIR / "slipmap_stages.py"
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
    "Epoch": np.float64,  # filters.ferry "=>Epoch" creates a double
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


def srs_metadata(wkt: str | None = None) -> dict:
    """``spatialreference`` as PDAL 2.8 passes it: ``{"srs": {...}}``; empty without an SRS."""
    if not wkt:
        return {
            "srs": {
                "compoundwkt": "",
                "horizontal": "",
                "isgeocentric": False,
                "isgeographic": False,
                "json": {},
                "prettycompoundwkt": "",
                "prettywkt": "",
                "proj4": "",
                "units": {"horizontal": "unknown", "vertical": ""},
                "vertical": "",
                "wkt": "",
            }
        }
    import pyproj

    crs = pyproj.CRS.from_user_input(wkt)
    horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
    vertical = crs.sub_crs_list[1].to_wkt() if crs.is_compound else ""
    text = crs.to_wkt(pyproj.enums.WktVersion.WKT1_GDAL) or crs.to_wkt()
    return {
        "srs": {
            "compoundwkt": text,
            "horizontal": horizontal.to_wkt(pyproj.enums.WktVersion.WKT1_GDAL) or "",
            "isgeocentric": bool(crs.is_geocentric),
            "isgeographic": bool(crs.is_geographic),
            "json": crs.to_json_dict(),
            "prettycompoundwkt": crs.to_wkt(pretty=True),
            "prettywkt": crs.to_wkt(pretty=True),
            "proj4": _proj4(crs),
            "units": {"horizontal": "metre", "vertical": ""},
            "vertical": vertical,
            "wkt": text,
        }
    }


def _schema(ins: dict) -> dict:
    kinds = {"f": "floating", "u": "unsigned", "i": "signed"}
    return {
        "schema": {
            "dimensions": [
                {"name": k, "size": int(v.dtype.itemsize), "type": kinds[v.dtype.kind]}
                for k, v in ins.items()
            ]
        }
    }


def load_stage(job: str, pdalargs=None, spatialreference=None, module_name: str | None = None):
    """Compile the stage script as filters.python does; ``call`` then runs ``job`` on a view.

    ``pdalargs`` is the pipeline's option (dict or JSON text, as written in the pipeline);
    ``spatialreference`` a WKT (converted to PDAL's dict) or an already PDAL-shaped dict.
    """
    name = module_name or f"slipmap_{job}"
    code = compile(SCRIPT.read_text(), name, "exec")  # Py_CompileString(source, module)
    module = sys.modules.get(name)
    if not isinstance(module, types.ModuleType) or getattr(module, "__file__", None) != name:
        module = types.ModuleType(name)
        module.__file__ = name  # PyImport_ExecCodeModule sets it from co_filename
        sys.modules[name] = module
    exec(code, module.__dict__)
    module.__dict__.pop("out_metadata", None)
    module.out_metadata = {}
    module._harness = {
        "job": job,
        "pdalargs": _parsed(pdalargs),
        "spatialreference": (
            spatialreference
            if isinstance(spatialreference, dict)
            else srs_metadata(spatialreference)
        ),
    }
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


def call(module, ins: dict, declared: dict, function: str | None = None) -> dict:
    """Call the stage on one view as PDAL does and check the filters.python output contract."""
    h = module._harness
    g = module.__dict__
    g["metadata"] = {"name": "root", "value": "", "type": "", "description": "", "children": []}
    g["pdalargs"] = h["pdalargs"]
    g["schema"] = _schema(ins)
    g["spatialreference"] = h["spatialreference"]
    outs: dict = {}
    r = getattr(module, function or h["job"])({k: v.copy() for k, v in ins.items()}, outs)
    assert type(r) is bool and r is True, f"{function} returned {r!r}"
    n = len(next(iter(ins.values()))) if ins else 0
    for name, arr in outs.items():
        assert name in declared or name in ins, f"undeclared output dimension {name!r}"
        want = declared.get(name, ins[name].dtype if name in ins else None)
        assert isinstance(arr, np.ndarray), name
        assert arr.dtype == want, (name, arr.dtype, want)
        assert arr.shape == (n,), (name, arr.shape, n)
    read_back(module)  # PDAL must be able to read it back
    return outs


def _typed(value: str, typ: str):
    if typ == "json":
        return json.loads(value)
    if typ == "double":
        v = float(value)
        assert math.isfinite(v), value
        return v
    if typ in ("integer", "nonNegativeInteger"):
        return int(value)
    if typ == "boolean":
        assert value in ("true", "false"), value
        return value == "true"
    assert typ == "string", typ
    return value


def read_back(module) -> dict:
    """``out_metadata`` as ``pdal pipeline --metadata`` shows it under the stage.

    pdal-plugins 1.6 (``addMetadata``) adds the root node to the stage's metadata as
    ``name: value`` and the root's children as ``name: value`` entries of a sibling node
    named ``children``; values are read with ``str()`` and typed by ``type``.
    """
    md = getattr(module, "out_metadata", None)
    assert isinstance(md, dict), "out_metadata must be a dict"
    if not md.get("name"):
        return {}
    for key in ("name", "value", "type", "description"):
        assert isinstance(md[key], str), (key, md[key])
    out = {md["name"]: _typed(md["value"], md["type"])}
    children = md.get("children", [])
    assert isinstance(children, list), "children must be a list"
    if children:
        kids = {}
        for c in children:
            for key in ("name", "value", "type", "description"):
                assert isinstance(c[key], str), (c.get("name"), key, c[key])
            assert not c.get("children"), "grandchildren are filed under 'children' by PDAL"
            assert c["name"] not in kids, f"duplicate metadata node {c['name']!r}"
            kids[c["name"]] = _typed(c["value"], c["type"])
        out["children"] = kids
    return out


def nodes(module) -> dict:
    """The stage's metadata values by name (``read_back(module)["children"]``)."""
    return read_back(module).get("children", {})


def pipeline_stages(path: Path) -> list:
    doc = json.loads(Path(path).read_text())
    stages = doc["pipeline"] if isinstance(doc, dict) else doc
    return [s if isinstance(s, dict) else {"type": "readers.las", "filename": s} for s in stages]


def _proj4(crs) -> str:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "you will likely lose information"
        return crs.to_proj4() or ""


def _parsed(pdalargs):
    """PDAL parses the option as JSON (text that is not JSON: PDAL itself refuses the pipeline,
    so the stand-in passes the text on for the stage to refuse)."""
    if isinstance(pdalargs, str):
        try:
            return json.loads(pdalargs)
        except ValueError:
            return pdalargs
    return pdalargs


def demo_runner():
    """The demo's slip job (``slipmap.app.demo.run_slip_demo``), which the real-PDAL tests
    run. Resolved here, in the helpers they share with the stand-in tests, and checked by a
    stand-in test (``test_stages.test_real_pdal_helpers_resolve``) on every run: a moved
    module breaks every run of the suite, not only machines with PDAL (issue #31). Imported
    when called: the harness itself must load without SlipMap installed (``slipmap_path``)."""
    from slipmap.app.demo import run_slip_demo

    return run_slip_demo


def make_demo_pair(out: Path) -> Path:
    """The demo's epochs (UTM, PointSourceId, GpsTime), its WGS 84 fault and the CLI's slip,
    written into ``out`` (``slipmap demo``'s slip job)."""
    demo_runner()(out)
    return out
