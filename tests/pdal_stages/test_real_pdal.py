"""SlipMap's stages and example pipelines in real PDAL, against the CLI on the same files.

Runs where PDAL is installed: the ``pdal`` command on PATH and/or PDAL's Python bindings
(``import pdal``), with the filters.python plugin found through PDAL_DRIVER_PATH or, as
``python -m pdal --pdal-plugin-path`` does, in the bindings' package folder. Elsewhere each
test is skipped with a one-line reason. Checked on PDAL 2.8.4 with pdal-plugins 1.6.5 and
python-pdal 3.5.3.

The pipelines run exactly as docs/pdal.md shows them (file names and ``pdalargs`` given on
the command line, ``slipmap_path`` where slipmap is not installed in PDAL's Python) and must
give the CLI's numbers: identical PlaneId, roughness and sigmas, slip within 0.01 mm.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pdal_harness import (
    PIPELINE_DIR,
    ROOT,
    ROUGHNESS_ATOL_M,
    SCRIPT,
    call,
    load_stage,
    make_demo_pair,
    make_ins,
    parse_add_dimension,
    read_back,
    srs_metadata,
)

DATA = ROOT / "tests" / "data"
PLUGIN = "libpdal_plugin_filter_python"

PROBE = """
import sys
seen = {}
def probe(ins, outs):
    seen["file"] = globals().get("__file__")
    seen["in_sys_modules"] = sys.modules.get(__name__) is sys.modules[__name__]
    for k in ("pdalargs", "spatialreference", "schema", "metadata"):
        seen[k] = globals().get(k)
    seen["ins"] = {k: v.dtype.str for k, v in ins.items()}
    seen["numpy"] = __import__("numpy").__version__
    global out_metadata
    out_metadata = {"name": "probe", "value": "", "type": "string", "description": "",
                    "children": [{"name": "seen", "value": __import__("json").dumps(seen,
                                  default=str), "type": "json", "description": ""}]}
    return True
"""


def _plugin_dir() -> str | None:
    """PDAL_DRIVER_PATH, else the bindings' folder holding filters.python (pdal-plugins)."""
    if os.environ.get("PDAL_DRIVER_PATH"):
        return os.environ["PDAL_DRIVER_PATH"]
    spec = importlib.util.find_spec("pdal")
    for folder in (spec.submodule_search_locations or []) if spec else []:
        if any(f.startswith(PLUGIN) for f in os.listdir(folder)):
            return folder
    return None


@pytest.fixture(scope="module")
def pdal_command():
    """(pdal executable, environment) for running pipelines with the ``pdal`` command."""
    exe = shutil.which("pdal")
    if exe is None:
        pytest.skip("no `pdal` command on PATH (PDAL is not installed)")
    env = dict(os.environ)
    plugins = _plugin_dir()
    if plugins:
        env["PDAL_DRIVER_PATH"] = plugins
    r = subprocess.run([exe, "--drivers"], capture_output=True, text=True, env=env)
    if "filters.python" not in r.stdout:
        pytest.skip("PDAL has no filters.python (install pdal-plugins; set PDAL_DRIVER_PATH)")
    return exe, env


@pytest.fixture(scope="module")
def pdal_py():
    """PDAL's Python bindings with filters.python (PDAL_DRIVER_PATH set for this module)."""
    saved = os.environ.get("PDAL_DRIVER_PATH")
    plugins = _plugin_dir()
    if plugins:
        os.environ["PDAL_DRIVER_PATH"] = plugins
    tests_dir = str(Path(__file__).resolve().parents[1])
    mod = sys.modules.get("pdal")
    if mod is not None and getattr(mod, "__file__", None) is None:
        del sys.modules["pdal"]  # tests/pdal... namespace package, not PDAL
    path = sys.path[:]
    sys.path[:] = [p for p in sys.path if str(Path(p or ".").resolve()) != tests_dir]
    try:
        pdal = importlib.import_module("pdal")
    except ImportError as e:
        pytest.skip(f"PDAL's Python bindings cannot be imported: {e}")
    finally:
        sys.path[:] = path
    if not hasattr(getattr(pdal, "Filter", None), "python"):
        pytest.skip("PDAL has no filters.python (install pdal-plugins; set PDAL_DRIVER_PATH)")
    yield pdal
    if saved is None:
        os.environ.pop("PDAL_DRIVER_PATH", None)
    else:
        os.environ["PDAL_DRIVER_PATH"] = saved


def _run_command(pdal_command, pipeline: Path, *args: str, cwd=ROOT):
    """``pdal pipeline PIPELINE ARGS`` from the repository root, as docs/pdal.md says."""
    exe, env = pdal_command
    r = subprocess.run(
        [exe, "pipeline", str(pipeline), *args], capture_output=True, text=True, env=env, cwd=cwd
    )
    assert r.returncode == 0, r.stderr[-3000:]
    return r


@pytest.fixture(scope="module")
def same_python(pdal_command, tmp_path_factory):
    """The `pdal` command, once checked to run this interpreter's numpy (a CLI comparison is
    skipped otherwise: it would cross numpy versions)."""
    tmp_path = tmp_path_factory.mktemp("probe")
    script = tmp_path / "probe.py"
    script.write_text(PROBE)
    md = tmp_path / "probe.json"
    doc = {
        "pipeline": [
            {"type": "readers.las", "filename": str(DATA / "autzen_trim.laz"), "count": 10},
            {"type": "filters.python", "script": str(script), "module": "p", "function": "probe"},
        ]
    }
    (tmp_path / "probe_pipeline.json").write_text(json.dumps(doc))
    _run_command(pdal_command, tmp_path / "probe_pipeline.json", f"--metadata={md}")
    seen = json.loads(md.read_text())["stages"]["filters.python"]["children"]["seen"]
    if seen["numpy"] != np.__version__:
        pytest.skip(
            f"PDAL's Python has numpy {seen['numpy']}, this one {np.__version__}: the CLI "
            "comparison would cross numpy versions"
        )
    return pdal_command


def _slipmap_path(args: dict) -> dict:
    """pdalargs with slipmap_path (the `pdal` command's Python need not have slipmap)."""
    return {**args, "slipmap_path": str(ROOT)}


def _las(path):
    laspy = pytest.importorskip("laspy")
    return laspy.read(str(path))


def _cli(*argv):
    from slipmap.cli import main

    assert main(["-q", *argv]) == 0


# --------------------------------------------------------------------------- the contract


def test_stand_in_passes_what_real_pdal_passes(pdal_py, tmp_path):
    """The harness's globals, module and metadata read-back are real PDAL's."""
    script = tmp_path / "probe.py"
    script.write_text(PROBE)
    pipe = pdal_py.Reader.las(str(DATA / "autzen_trim.laz"), count=50) | pdal_py.Filter.python(
        script=str(script), module="slipmap_probe", function="probe", pdalargs='{"a": [1, 2]}'
    )
    pipe.execute()
    seen = pipe.metadata["metadata"]["filters.python"]["children"]["seen"]
    assert seen["file"] == "slipmap_probe" and seen["in_sys_modules"]
    assert seen["pdalargs"] == {"a": [1, 2]}  # JSON text in the pipeline arrives as a dict
    srs = seen["spatialreference"]
    assert set(srs) == {"srs"} and set(srs["srs"]) == set(srs_metadata("EPSG:32611")["srs"])
    assert srs["srs"]["wkt"] and srs["srs"]["compoundwkt"]
    dims = seen["schema"]["schema"]["dimensions"]
    assert {d["name"] for d in dims} == set(seen["ins"])
    assert {"name", "size", "type"} <= set(dims[0])
    assert seen["metadata"]["name"] == "root"
    # the same roughness stage on the same points: real PDAL's metadata == the read-back
    pipe = pdal_py.Reader.las(str(DATA / "lone-star.laz"), count=5000) | pdal_py.Filter.python(
        script=str(SCRIPT),
        module="slipmap_roughness",
        function="roughness",
        add_dimension="Roughness",
        pdalargs=json.dumps({"cell": 1.0, "signed": True}),
    )
    pipe.execute()
    arr = pipe.arrays[0]
    mod = load_stage("roughness", {"cell": 1.0, "signed": True})
    ins = make_ins(np.column_stack([arr["X"], arr["Y"], arr["Z"]]))
    outs = call(mod, ins, parse_add_dimension("Roughness"))
    np.testing.assert_array_equal(outs["Roughness"], arr["Roughness"])
    assert pipe.metadata["metadata"]["filters.python"] == read_back(mod)


def test_srs_without_one_and_errors_in_real_pdal(pdal_py, tmp_path):
    laspy = pytest.importorskip("laspy")
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = [0.001] * 3
    las = laspy.LasData(header)
    rng = np.random.default_rng(0)
    las.x, las.y, las.z = rng.uniform(0, 10, (3, 200))
    las.write(str(tmp_path / "nocrs.las"))
    script = tmp_path / "probe.py"
    script.write_text(PROBE)
    pipe = pdal_py.Reader.las(str(tmp_path / "nocrs.las")) | pdal_py.Filter.python(
        script=str(script), module="p2", function="probe"
    )
    pipe.execute()
    seen = pipe.metadata["metadata"]["filters.python"]["children"]["seen"]
    assert seen["pdalargs"] is None
    assert seen["spatialreference"] == srs_metadata(None)
    # a bad option stops the pipeline with the stage's message
    pipe = pdal_py.Reader.las(str(tmp_path / "nocrs.las")) | pdal_py.Filter.python(
        script=str(SCRIPT),
        module="slipmap_roughness",
        function="roughness",
        add_dimension="Roughness",
        pdalargs=json.dumps({"cell": -1}),
    )
    with pytest.raises(RuntimeError, match="option 'cell' must be > 0"):
        pipe.execute()


# --------------------------------------------------------------------------- the pipelines


@pytest.fixture(scope="module")
def demo_pair(tmp_path_factory):
    """The demo's epochs (UTM, PointSourceId, GpsTime), its WGS 84 fault and the CLI's slip."""
    return make_demo_pair(tmp_path_factory.mktemp("demo"))


def _pipeline_doc(name: str, files: dict, pdalargs: dict | None = None) -> str:
    """An example pipeline with its INPUT_/OUTPUT_ names replaced, as JSON text."""
    doc = json.loads((PIPELINE_DIR / f"{name}.json").read_text())
    for s in doc["pipeline"]:
        if s.get("filename") in files:
            s["filename"] = str(files[s["filename"]])
        if s["type"] == "filters.python" and pdalargs is not None:
            s["pdalargs"] = pdalargs
    return json.dumps(doc)


def test_planes_pipeline_equals_cli(pdal_py, same_python, demo_pair, tmp_path):
    """planes_buildings on the demo epoch: identical PlaneId, by bindings and by command."""
    src = demo_pair / "demo_before.laz"
    _cli("planes", str(src), "--classes", "6", "--min-points", "50", "--out", str(tmp_path))
    cli = _las(tmp_path / "demo_before_planes.laz")
    keep = np.asarray(cli.classification) == 6
    ref = np.asarray(cli.PlaneId)[keep]
    assert ref.max() > 10  # the demo town's roofs and walls
    args = _slipmap_path({"min_plane_points": 50, "backend": "numpy"})
    _run_command(
        same_python,
        PIPELINE_DIR / "planes_buildings.json",
        f"--readers.las.filename={src}",
        f"--writers.las.filename={tmp_path / 'cmd.laz'}",
        f"--filters.python.pdalargs={json.dumps(args)}",
    )
    out = _las(tmp_path / "cmd.laz")
    np.testing.assert_array_equal(np.asarray(out.PlaneId), ref)
    np.testing.assert_array_equal(np.asarray(out.x), np.asarray(cli.x)[keep])
    text = _pipeline_doc(
        "planes_buildings",
        {"INPUT_buildings.laz": src, "OUTPUT_planes.laz": tmp_path / "py.laz"},
    )
    pipe = pdal_py.Pipeline(text)
    assert pipe.execute() == keep.sum()
    np.testing.assert_array_equal(pipe.arrays[0]["PlaneId"], ref)
    md = pipe.metadata["metadata"]["filters.python"]
    assert md["slipmap"] == "planes"
    assert md["children"]["n_planes"] == len(np.unique(ref[ref >= 0]))


def test_roughness_pipeline_equals_cli(same_python, tmp_path):
    """roughness_outcrop on lone-star: the CLI on the points that reached the stage agrees."""
    out = tmp_path / "rough.laz"
    md = tmp_path / "md.json"
    _run_command(
        same_python,
        PIPELINE_DIR / "roughness_outcrop.json",
        f"--readers.las.filename={DATA / 'lone-star.laz'}",
        f"--writers.las.filename={out}",
        f"--filters.python.pdalargs={json.dumps(_slipmap_path({'cell': 0.5}))}",
        f"--metadata={md}",
    )
    _cli(
        "roughness", str(out), "--cell", "0.5", "--out", str(tmp_path / "cli"),
        "--points-out", str(tmp_path / "cli.las"), "--no-figures",
    )  # fmt: skip
    a = np.asarray(_las(out).Roughness)
    b = np.asarray(_las(tmp_path / "cli.las").Roughness)
    assert np.isfinite(a).mean() > 0.5
    # the same cells and points; sums in another order differ in the last bits (1.9e-16 m)
    np.testing.assert_allclose(a, b, rtol=0, atol=ROUGHNESS_ATOL_M)
    assert np.array_equal(np.isnan(a), np.isnan(b))
    stage = json.loads(md.read_text())["stages"]["filters.python"]
    assert stage["slipmap"] == "roughness"
    assert stage["children"]["cell_size_m"] == 0.5 and stage["children"]["n_points"] == a.size


@pytest.mark.parametrize(
    "args, cli_args",
    [
        ({"model": "constant", "sigma": 0.04}, ["--pa", "constant", "--sigma", "0.04"]),
        (
            {"model": "axis", "sigma_xyz": [0.03, 0.03, 0.05], "full_covariance": True},
            ["--pa", "axis", "--sigma-xyz", "0.03", "0.03", "0.05", "--full-covariance"],
        ),
    ],
    ids=["constant", "axis"],
)
def test_accuracy_pipeline_equals_cli(same_python, tmp_path, args, cli_args):
    """accuracy_propagation on autzen_trim with the constant and axis models."""
    src = DATA / "autzen_trim.laz"
    out = tmp_path / "acc.laz"
    _run_command(
        same_python,
        PIPELINE_DIR / "accuracy_propagation.json",
        f"--readers.las.filename={src}",
        f"--writers.las.filename={out}",
        f"--filters.python.pdalargs={json.dumps(_slipmap_path(args))}",
    )
    _cli("accuracy", str(src), *cli_args, "--out", str(tmp_path / "cli.laz"))
    a, b = _las(out), _las(tmp_path / "cli.laz")
    names = ["SigmaX", "SigmaY", "SigmaZ"]
    if args.get("full_covariance"):
        names += ["CovXX", "CovYY", "CovZZ", "CovXY", "CovXZ", "CovYZ"]
    for name in names:
        np.testing.assert_array_equal(np.asarray(a[name]), np.asarray(b[name]), err_msg=name)


def _slip_args(demo_pair) -> dict:
    return {"trace": str(demo_pair / "demo_fault.geojson"), "sigma_before": 0.02,
            "sigma_after": 0.02}  # fmt: skip


def _assert_cli_slip(relative: dict, demo_pair):
    cli = json.loads((demo_pair / "displacement.json").read_text())["relative"]
    for key in ("right_lateral_slip", "sigma_right_lateral", "dz", "sigma_dz"):
        assert relative[key] == pytest.approx(cli[key], abs=1e-5), key  # 0.01 mm
    assert abs(relative["right_lateral_slip"] - 0.0181) < 4 * relative["sigma_right_lateral"]


def test_displacement_pipeline_command_equals_cli(same_python, demo_pair, tmp_path):
    """The two-reader slip pipeline by the `pdal` command on the georeferenced demo pair; the
    WGS 84 trace file is reprojected to the views' SRS (PDAL passes it as a dict)."""
    md = tmp_path / "slip.json"
    _run_command(
        same_python,
        PIPELINE_DIR / "displacement_fault.json",
        f"--stage.epoch1.filename={demo_pair / 'demo_before.laz'}",
        f"--stage.epoch2.filename={demo_pair / 'demo_after.laz'}",
        f"--writers.las.filename={tmp_path / 'slip.laz'}",
        f"--filters.python.pdalargs={json.dumps(_slipmap_path(_slip_args(demo_pair)))}",
        f"--metadata={md}",
    )
    stage = json.loads(md.read_text())["stages"]["filters.python"]
    assert stage["slipmap"] == "displacement"
    kids = stage["children"]
    _assert_cli_slip(kids, demo_pair)
    # the view's GpsTime reaches the units' drift (the unit_drift option, on by default)
    assert kids["acquisition_units"]["before"] == {
        "source": "PointSourceId",
        "n_units": 5,
        "note": "auto",
        "gps_time": True,
    }
    assert kids["acquisition_units"]["unit_drift"] is True
    assert kids["summary"]["relative"]["right_lateral_slip"] == kids["right_lateral_slip"]
    assert kids["headline"].startswith("right-lateral slip ")
    out = _las(tmp_path / "slip.laz")
    plane = np.asarray(out.PlaneId)
    residual = np.asarray(out.Residual)
    assert (plane >= 0).mean() > 0.2
    assert np.isnan(residual[plane < 0]).all() and np.abs(residual[plane >= 0]).max() < 0.5


def test_displacement_pipeline_bindings_equals_cli(pdal_py, demo_pair, tmp_path):
    files = {
        "INPUT_epoch1.laz": demo_pair / "demo_before.laz",
        "INPUT_epoch2.laz": demo_pair / "demo_after.laz",
        "OUTPUT_slip.laz": tmp_path / "slip.laz",
    }
    pipe = pdal_py.Pipeline(_pipeline_doc("displacement_fault", files, _slip_args(demo_pair)))
    pipe.execute()
    _assert_cli_slip(pipe.metadata["metadata"]["filters.python"]["children"], demo_pair)


def test_displacement_pipeline_random_tilt_equals_cli(pdal_py, demo_pair, tmp_path):
    """``random_tilt`` as a JSON boolean in real PDAL's pdalargs reaches the adjustment: the
    slip and its σ equal the CLI's ``--random-tilt`` run on the same epochs, and the stage's
    metadata records it."""
    out = tmp_path / "cli"
    _cli("displacement", str(demo_pair / "demo_before.laz"), str(demo_pair / "demo_after.laz"),
         "--fault", str(demo_pair / "demo_fault.geojson"), "--sigma", "0.02", "--random-tilt",
         "--out", str(out))  # fmt: skip
    cli = json.loads((out / "displacement.json").read_text())
    assert cli["parameters"]["random_tilt"] is True
    files = {
        "INPUT_epoch1.laz": demo_pair / "demo_before.laz",
        "INPUT_epoch2.laz": demo_pair / "demo_after.laz",
        "OUTPUT_slip.laz": tmp_path / "slip.laz",
    }
    args = dict(_slip_args(demo_pair), random_tilt=True)
    pipe = pdal_py.Pipeline(_pipeline_doc("displacement_fault", files, args))
    pipe.execute()
    kids = pipe.metadata["metadata"]["filters.python"]["children"]
    for key in ("right_lateral_slip", "sigma_right_lateral", "dz", "sigma_dz"):
        assert kids[key] == pytest.approx(cli["relative"][key], abs=1e-5), key
    assert kids["summary"]["parameters"]["random_tilt"] is True


# --------------------------------------------------------------------------- icp


#: the part of the demo's epochs the field pipeline runs on (40 m x 60 m across the fault,
#: which runs north at x = 498 060): 96 cells of 5 m
FIELD_BOX = (498040.0, 4234030.0, 498080.0, 4234090.0)
FIELD_COLUMNS = ("x", "y", "dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_dz", "n")


@pytest.fixture(scope="module")
def field_pair(demo_pair, tmp_path_factory):
    """The demo's epochs cut to FIELD_BOX (LAS files, header and CRS kept) and the CLI's
    ``slipmap icp`` on them with the demo's WGS 84 fault as the breakline, numpy backend
    (``auto`` takes Numba where the Python has it, and PDAL's need not: on this town's flat
    ground, which barely shows horizontal motion at 5 m cells, σ 12-14 cm, two backends'
    last bits lead the fits apart by their σ)."""
    laspy = pytest.importorskip("laspy")
    out = tmp_path_factory.mktemp("field")
    x0, y0, x1, y1 = FIELD_BOX
    for name in ("demo_before", "demo_after"):
        las = laspy.read(str(demo_pair / f"{name}.laz"))
        x, y = np.asarray(las.x), np.asarray(las.y)
        las.points = las.points[(x >= x0) & (x < x1) & (y >= y0) & (y < y1)]
        las.write(str(out / f"{name}.las"))
    fault = str(demo_pair / "demo_fault.geojson")
    _cli("icp", str(out / "demo_before.las"), str(out / "demo_after.las"),
         "--breaklines", fault, "--backend", "numpy", "--out", str(out / "cli"))  # fmt: skip
    return out


def _field_args(demo_pair) -> dict:
    return {"breaklines": str(demo_pair / "demo_fault.geojson"), "cell_m": 5.0, "backend": "numpy"}


def _assert_cli_field(kids: dict, field_pair):
    """The stage's cells are the CLI's icp.csv: same points, same code, to 1 µm (measured
    0.15 µm at most: the fits' iterations carry the last bits of sums taken in another order
    in PDAL's embedded Python, and this ground barely determines the horizontal motion)."""
    import csv

    with open(field_pair / "cli" / "icp.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    cli = {k: np.array([float(r[k]) for r in rows]) for k in FIELD_COLUMNS}
    cells = {k: np.asarray(kids["cells"][k], dtype=float) for k in FIELD_COLUMNS}
    assert len(cells["x"]) == len(cli["x"]) > 60
    for k in FIELD_COLUMNS:
        np.testing.assert_allclose(cells[k], cli[k], rtol=0, atol=1e-6, err_msg=k)
    given = json.loads((field_pair / "cli" / "icp.json").read_text())["breaklines"]
    assert kids["summary"]["breaklines"]["source"] == given["source"] == "given"
    # the WGS 84 file reprojected to the views' UTM: the fault at x = 498 060
    line = np.asarray(kids["summary"]["breaklines"]["lines"][0])
    assert np.abs(line[:, 0] - 498060.0).max() < 0.05
    np.testing.assert_allclose(line, given["lines"][0], atol=1e-3)


def test_icp_pipeline_command_equals_cli(same_python, field_pair, demo_pair, tmp_path):
    """The two-reader field pipeline by the `pdal` command, the breakline a WGS 84 file (PDAL
    passes the views' SRS as a dict): the CLI's cells, and each point its cell's motion."""
    md = tmp_path / "field.json"
    _run_command(
        same_python,
        PIPELINE_DIR / "icp_landslide.json",
        f"--stage.epoch1.filename={field_pair / 'demo_before.las'}",
        f"--stage.epoch2.filename={field_pair / 'demo_after.las'}",
        f"--writers.las.filename={tmp_path / 'field.laz'}",
        f"--filters.python.pdalargs={json.dumps(_slipmap_path(_field_args(demo_pair)))}",
        f"--metadata={md}",
    )
    stage = json.loads(md.read_text())["stages"]["filters.python"]
    assert stage["slipmap"] == "icp"
    kids = stage["children"]
    _assert_cli_field(kids, field_pair)
    assert kids["headline"].startswith("windowed ICP: ")
    out = _las(tmp_path / "field.laz")
    k = np.asarray(out.IcpCell)
    has = k >= 0
    assert has.mean() > 0.9
    dx = np.asarray(kids["cells"]["dx"], dtype=float)
    # LAS extra bytes keep doubles: each point carries its cell's dx exactly
    np.testing.assert_array_equal(np.asarray(out.DisplacementX)[has], dx[k[has]])
    assert np.isnan(np.asarray(out.DisplacementZ)[~has]).all()


def test_icp_pipeline_bindings_equals_cli(pdal_py, field_pair, demo_pair, tmp_path):
    files = {
        "INPUT_epoch1.laz": field_pair / "demo_before.las",
        "INPUT_epoch2.laz": field_pair / "demo_after.las",
        "OUTPUT_field.laz": tmp_path / "field.laz",
    }
    pipe = pdal_py.Pipeline(_pipeline_doc("icp_landslide", files, _field_args(demo_pair)))
    pipe.execute()
    _assert_cli_field(pipe.metadata["metadata"]["filters.python"]["children"], field_pair)


# --------------------------------------------------------------------------- piv

PIV_COLUMNS = ("x", "y", "dx", "dy", "dz", "snr", "valid", "near_break")


def _assert_cli_piv(kids: dict, cli_dir: Path):
    """The stage's vectors are the CLI's piv.csv (same points, same code: to 1e-9 m)."""
    import csv

    with open(cli_dir / "piv.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    cli = {k: np.array([float(r[k]) if r[k] else np.nan for r in rows]) for k in PIV_COLUMNS}
    cli["snr"][np.isinf(cli["snr"])] = np.nan  # JSON has no infinity: null in the metadata
    vec = {k: np.array([np.nan if v is None else float(v) for v in kids["vectors"][k]])
           for k in PIV_COLUMNS}  # fmt: skip
    assert len(vec["x"]) == len(cli["x"]) > 500
    for k in PIV_COLUMNS:
        np.testing.assert_allclose(vec[k], cli[k], rtol=0, atol=1e-9, err_msg=k)
    assert kids["summary"]["breaklines_given"] and kids["summary"]["n_near_break"] > 0


@pytest.fixture(scope="module")
def piv_cli(demo_pair, tmp_path_factory):
    out = tmp_path_factory.mktemp("piv_cli")
    _cli("piv", str(demo_pair / "demo_before.laz"), str(demo_pair / "demo_after.laz"),
         "--grid", "0.5", "--breaklines", str(demo_pair / "demo_fault.geojson"),
         "--out", str(out))  # fmt: skip
    return out


def test_piv_pipeline_command_equals_cli(same_python, demo_pair, piv_cli, tmp_path):
    """The two-reader PIV pipeline by the `pdal` command on the demo pair, the breakline the
    WGS 84 fault file: the CLI's vectors, and each point its vector's motion."""
    md = tmp_path / "piv.json"
    args = {"breaklines": str(demo_pair / "demo_fault.geojson"), "grid_m": 0.5}
    _run_command(
        same_python,
        PIPELINE_DIR / "piv_landslide.json",
        f"--stage.epoch1.filename={demo_pair / 'demo_before.laz'}",
        f"--stage.epoch2.filename={demo_pair / 'demo_after.laz'}",
        f"--writers.las.filename={tmp_path / 'piv.laz'}",
        f"--filters.python.pdalargs={json.dumps(_slipmap_path(args))}",
        f"--metadata={md}",
    )
    stage = json.loads(md.read_text())["stages"]["filters.python"]
    assert stage["slipmap"] == "piv"
    _assert_cli_piv(stage["children"], piv_cli)
    out = _las(tmp_path / "piv.laz")
    k = np.asarray(out.PivVector)
    has = k >= 0
    dy = np.array([np.nan if v is None else v for v in stage["children"]["vectors"]["dy"]])
    np.testing.assert_array_equal(np.asarray(out.DisplacementY)[has], dy[k[has]])


def test_piv_pipeline_bindings_equals_cli(pdal_py, demo_pair, piv_cli, tmp_path):
    files = {
        "INPUT_epoch1.laz": demo_pair / "demo_before.laz",
        "INPUT_epoch2.laz": demo_pair / "demo_after.laz",
        "OUTPUT_piv.laz": tmp_path / "piv.laz",
    }
    args = {"breaklines": str(demo_pair / "demo_fault.geojson"), "grid_m": 0.5}
    pipe = pdal_py.Pipeline(_pipeline_doc("piv_landslide", files, args))
    pipe.execute()
    _assert_cli_piv(pipe.metadata["metadata"]["filters.python"]["children"], piv_cli)
