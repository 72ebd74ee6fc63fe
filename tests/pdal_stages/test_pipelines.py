"""The example pipelines: valid JSON, known stages, scripts and dimensions consistent.

The last test runs them with real PDAL (conda-forge pdal + python-pdal + pdal-plugins-python);
it is skipped where PDAL or its filters.python plugin is missing (as on the dev machine).
"""

import importlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from pdal_harness import PIPELINE_DIR, ROOT, load_stage, parse_add_dimension, pipeline_stages

# PDAL stage names the pipelines may use (PDAL 2.x)
PDAL_STAGES = {
    "readers.las",
    "readers.copc",
    "readers.text",
    "readers.numpy",
    "writers.las",
    "writers.copc",
    "writers.text",
    "filters.python",
    "filters.assign",
    "filters.ferry",
    "filters.merge",
    "filters.range",
    "filters.expression",
    "filters.smrf",
    "filters.csf",
    "filters.pmf",
    "filters.outlier",
    "filters.elm",
    "filters.reprojection",
    "filters.crop",
    "filters.sort",
    "filters.voxelcenternearestneighbor",
}

PIPELINES = sorted(PIPELINE_DIR.glob("*.json"))


def test_four_pipelines_exist():
    names = {p.stem for p in PIPELINES}
    assert {
        "planes_buildings",
        "roughness_outcrop",
        "accuracy_propagation",
        "displacement_fault",
    } <= names


@pytest.mark.parametrize("path", PIPELINES, ids=lambda p: p.stem)
def test_pipeline_is_consistent(path):
    stages = pipeline_stages(path)
    tags = set()
    for s in stages:
        assert s["type"] in PDAL_STAGES, s["type"]
        for ref in s.get("inputs", []):
            assert ref in tags, f"{path.name}: input {ref!r} before its stage"
        if "tag" in s:
            tags.add(s["tag"])
    assert stages[0]["type"].startswith("readers.") and stages[-1]["type"].startswith("writers.")
    py = [s for s in stages if s["type"] == "filters.python"]
    assert len(py) == 1
    for s in py:
        script = ROOT / s["script"]
        assert script.is_file(), script
        mod = load_stage(script, s["module"], s.get("pdalargs"))
        assert callable(getattr(mod, s["function"]))
        declared = parse_add_dimension(s.get("add_dimension"))
        opts = mod.options_table().parse(s.get("pdalargs"))  # the example options are valid
        outputs = mod.outputs(opts) if hasattr(mod, "outputs") else mod.OUTPUTS
        written = {k: np.dtype(v) for k, v in outputs.items()}
        assert declared == written
    for s in stages:
        if s["type"] == "writers.las":
            assert s.get("extra_dims") == "all" and s.get("forward") == "all"


def test_displacement_pipeline_tags_epochs():
    stages = pipeline_stages(PIPELINE_DIR / "displacement_fault.json")
    assigns = [s["value"].replace(" ", "") for s in stages if s["type"] == "filters.assign"]
    assert assigns == ["Epoch=1", "Epoch=2"]
    merge = next(s for s in stages if s["type"] == "filters.merge")
    assert merge["inputs"] == ["before", "after"]


def _import_real_pdal():
    """Import PDAL's bindings, not this folder: with tests/ on sys.path, tests/pdal would be
    found as a namespace package called ``pdal``."""
    tests_dir = Path(__file__).resolve().parents[1]
    mod = sys.modules.get("pdal")
    if mod is not None and getattr(mod, "__file__", None) is None:
        del sys.modules["pdal"]
    saved = sys.path[:]
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != tests_dir]
    try:
        return importlib.import_module("pdal")
    except ImportError as e:
        pytest.skip(f"PDAL's Python bindings (python-pdal) cannot be imported: {e}")
    finally:
        sys.path[:] = saved


def _pdal_with_python():
    pdal = _import_real_pdal()
    if not hasattr(getattr(pdal, "Filter", None), "python"):
        pytest.skip(
            "PDAL has no filters.python (install pdal-plugins-python, set PDAL_DRIVER_PATH)"
        )
    return pdal


def _write_las(path, points, classification):
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.offsets = points.min(axis=0)
    header.scales = [0.001, 0.001, 0.001]
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    las.classification = classification
    las.write(str(path))


def test_pipelines_with_real_pdal(tmp_path, monkeypatch):
    pdal = _pdal_with_python()
    from slipmap.core.synthetic import make_fault_pair, make_scene

    origin = (500000.0, 4200000.0, 10.0)
    scene = make_scene("als", seed=3, n_buildings=3, extent_m=60.0, origin=origin)
    _write_las(tmp_path / "b.las", scene.points, np.full(scene.n_points, 6, np.uint8))
    fp = make_fault_pair("mls", seed=7, origin=origin, vegetation=False, density_pts_m2=30.0)
    _write_las(tmp_path / "e1.las", fp.before.points, np.ones(len(fp.before.points), np.uint8))
    _write_las(tmp_path / "e2.las", fp.after.points, np.ones(len(fp.after.points), np.uint8))
    (x0, y0), (x1, y1) = fp.trace_xy
    files = {
        "INPUT_buildings.laz": tmp_path / "b.las",
        "INPUT_outcrop.laz": tmp_path / "b.las",
        "INPUT_mls_epoch.laz": tmp_path / "b.las",
        "INPUT_epoch1.laz": tmp_path / "e1.las",
        "INPUT_epoch2.laz": tmp_path / "e2.las",
    }
    monkeypatch.chdir(ROOT)  # "script" paths are relative to the working directory
    for path in PIPELINES:
        doc = json.loads(path.read_text())
        for s in doc["pipeline"]:
            if s.get("filename") in files:
                s["filename"] = str(files[s["filename"]])
            elif s.get("filename", "").startswith("OUTPUT_"):
                s["filename"] = str(tmp_path / s["filename"])
            if s["type"] == "filters.python":
                s["pdalargs"]["slipmap_path"] = str(ROOT)
                if s["module"] == "slipmap_accuracy":  # no GpsTime here: the static model
                    s["pdalargs"] = {
                        "model": "propagated",
                        "scanner": "riegl-vz400",
                        "scanner_position": [origin[0] + 30.0, origin[1] - 20.0, 15.0],
                        "full_covariance": True,
                        "slipmap_path": str(ROOT),
                    }
                if "trace" in s["pdalargs"]:
                    s["pdalargs"]["trace"] = f"LINESTRING ({x0:.6f} {y0:.6f}, {x1:.6f} {y1:.6f})"
            if s["type"] == "filters.smrf":  # synthetic scene: ground is class 1, keep all
                s["ignore"] = "Classification[0:255]"
        pipeline = pdal.Pipeline(json.dumps(doc))
        assert pipeline.execute() > 0, path.name
        arr = pipeline.arrays[0]
        for name in ("PlaneId", "Planarity", "Roughness", "Residual", "SigmaX", "CovYZ"):
            if name in arr.dtype.names:
                assert arr[name].shape == (len(arr),)


@pytest.mark.parametrize("name", ["planes", "roughness", "accuracy", "displacement"])
def test_docs_tables_match_option_tables(name):
    doc = (ROOT / "docs" / "pdal.md").read_text()
    mod = load_stage(ROOT / "pdal_filters" / f"{name}.py", f"slipmap_{name}", {})
    assert mod.options_table().markdown() in doc
