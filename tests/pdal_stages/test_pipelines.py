"""The example pipelines: valid JSON, known stages, scripts and dimensions consistent.

test_real_pdal.py runs them in real PDAL where it is installed.
"""

import importlib

import numpy as np
import pytest
from pdal_harness import (
    PIPELINE_DIR,
    ROOT,
    SCRIPT,
    load_stage,
    parse_add_dimension,
    pipeline_stages,
)

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


def test_the_pipelines_exist():
    names = {p.stem for p in PIPELINES}
    assert {
        "planes_buildings",
        "roughness_outcrop",
        "accuracy_propagation",
        "displacement_fault",
        "icp_landslide",
        "piv_landslide",
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
        assert script == SCRIPT
        mod = load_stage(s["function"], s.get("pdalargs"), module_name=s["module"])
        assert callable(getattr(mod, s["function"]))
        job = importlib.import_module("slipmap.pdal_filters." + s["function"])
        declared = parse_add_dimension(s.get("add_dimension"))
        opts = job.TABLE.parse(s.get("pdalargs"))  # the example options are valid
        written = {k: np.dtype(v) for k, v in job.outputs(opts).items()}
        assert declared == written
    for s in stages:
        if s["type"] == "writers.las":
            assert s.get("extra_dims") == "all" and s.get("forward") == "all"


@pytest.mark.parametrize("name", ["displacement_fault", "icp_landslide", "piv_landslide"])
def test_two_epoch_pipelines_tag_epochs(name):
    stages = pipeline_stages(PIPELINE_DIR / f"{name}.json")
    assigns = [s["value"].replace(" ", "") for s in stages if s["type"] == "filters.assign"]
    assert assigns == ["Epoch=1", "Epoch=2"]
    merge = next(s for s in stages if s["type"] == "filters.merge")
    assert merge["inputs"] == ["before", "after"]


@pytest.mark.parametrize("name", ["planes", "roughness", "accuracy", "displacement", "icp", "piv"])
def test_docs_tables_match_option_tables(name):
    doc = (ROOT / "docs" / "pdal.md").read_text()
    job = importlib.import_module("slipmap.pdal_filters." + name)
    assert job.options_table().markdown() in doc
