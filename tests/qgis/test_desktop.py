"""Every SlipMap algorithm run from its own dialog in the real QGIS desktop.

The QGIS application (``qgis``) starts under Xvfb with a throw-away profile into which the
plugin is installed from the zip that ``scripts/plugin_zip.sh`` builds (as a user installs
it), laspy and lazrs on QGIS's own Python path (as ``pip install --user`` puts them), and
the plugin enabled. ``desktop_driver.py`` then does, in that desktop, what an analyst does:
it loads the input layers, opens each algorithm's dialog, fills only the fields a user must
fill through the dialog's widgets (every optional field left as the dialog shows it), presses
Run, waits, and records what QGIS shows. The tests here read that record:

* the run succeeded (no message box, "Execution completed" in the dialog's log);
* every layer the run added is valid, styled (not the renderer QGIS gives the same data
  without a style), its legend classes span the data, rasters lie below vectors;
* the same run with every optional text field typed into and cleared again by key presses;
* a run cancelled from the dialog leaves no file and no layer behind;
* the windowed ICP and PIV with a scarp picked as their breaklines layer (WGS 84) on a slab
  behind a known step: the line reaches the job, the field keeps the step, PIV flags the
  vectors at it;
* with laspy, lazrs and scipy made unimportable (a second desktop), all eight algorithms are
  still listed, each says what is missing and how to install it, and Run refuses.

A screenshot of the main window per algorithm is saved (``SLIPMAP_DESKTOP_SHOTS=docs/img``
refreshes docs/img/desktop_*.png). These tests never skip where ``make test`` installed what
they need (``qgis``, ``xvfb``): on a machine without them they fail, saying so.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pyproj
import pytest
from qgis_scenes import column, features, rough_surface

pytestmark = pytest.mark.qgis

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
QGIS = shutil.which("qgis.bin") or shutil.which("qgis")  # Debian's qgis may be a wrapper
XVFB = shutil.which("xvfb-run")
UTM10 = pyproj.CRS.from_epsg(32610)
UTM12 = pyproj.CRS.from_epsg(32612)
SLIP_ORIGIN = (498000.0, 4234000.0, 20.0)
DEXTRAL_M = 0.0181
X0, Y0, SIDE = 512000.0, 4300000.0, 24.0
SHIFT = (0.40, -0.30, 0.05)
#: the step pair: the ground north of STEP_Y moves by SHIFT, the ground south of it by
#: SOUTH_SHIFT; the scarp is given as a line layer in WGS 84 (the user's fault map)
STEP_Y = Y0 + 12.0
SOUTH_SHIFT = (0.10, 0.0, 0.0)

#: the layers each algorithm's default run must add to the project (at least)
LOADED = {
    "planes": 0,
    "displacement": 1,  # Matched planes
    "pointaccuracy": 0,
    "roughness": 1,
    "piv": 4,  # vectors, dx, dy, dz
    "windowedicp": 2,  # cells, vectors
    "demdiff": 1,
    "strain": 1,
}
ALGORITHMS = tuple(LOADED)


def _require_desktop():
    missing = [n for n, p in (("qgis", QGIS), ("xvfb-run", XVFB)) if p is None]
    if missing:
        pytest.fail(
            f"the desktop tests need {' and '.join(missing)}: `make test` installs them "
            "(apt-get install qgis xvfb xauth)"
        )


# --------------------------------------------------------------------------- data


def _write_lines(path, lines, crs):
    from osgeo import ogr, osr

    drv = ogr.GetDriverByName("GPKG")
    ds = drv.CreateDataSource(str(path))
    srs = osr.SpatialReference()
    srs.ImportFromWkt(crs.to_wkt())
    layer = ds.CreateLayer(Path(path).stem, srs, ogr.wkbLineString)
    for line in lines:
        g = ogr.Geometry(ogr.wkbLineString)
        for x, y in line:
            g.AddPoint_2D(float(x), float(y))
        f = ogr.Feature(layer.GetLayerDefn())
        f.SetGeometry(g)
        layer.CreateFeature(f)
    ds = None


def _write_field(path, crs):
    """A regular grid of displacement vectors (1 % extension in x, 0.5 % shear), a point
    layer with dx, dy columns (metres), as PIV or ICP write them."""
    from osgeo import ogr, osr

    drv = ogr.GetDriverByName("GPKG")
    ds = drv.CreateDataSource(str(path))
    srs = osr.SpatialReference()
    srs.ImportFromWkt(crs.to_wkt())
    layer = ds.CreateLayer("field", srs, ogr.wkbPoint)
    for name in ("dx", "dy"):
        layer.CreateField(ogr.FieldDefn(name, ogr.OFTReal))
    for i in range(12):
        for j in range(12):
            x, y = X0 + 2.0 * i, Y0 + 2.0 * j
            f = ogr.Feature(layer.GetLayerDefn())
            f.SetField("dx", 0.01 * (x - X0) + 0.005 * (y - Y0))
            f.SetField("dy", 0.0)
            g = ogr.Geometry(ogr.wkbPoint)
            g.AddPoint_2D(x, y)
            f.SetGeometry(g)
            layer.CreateFeature(f)
    ds = None


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from slipmap.core.io.las import PointCloud, write_las
    from slipmap.core.synthetic import make_fault_pair

    d = tmp_path_factory.mktemp("desktop_data")
    fp = make_fault_pair("mls", seed=7, origin=SLIP_ORIGIN, right_offset_m=(0.0, -DEXTRAL_M, 0.0))
    for name, sc in (("before", fp.before), ("after", fp.after)):
        write_las(
            d / f"slip_{name}.las",
            PointCloud(xyz=sc.points, attributes={"Classification": sc.classification}, crs=UTM10),
        )
    _write_lines(d / "trace.gpkg", [fp.trace_xy], UTM10)
    rng = np.random.default_rng(5)
    n = int(64 * SIDE * SIDE)
    for name, (sx, sy, sz) in (("before", (0.0, 0.0, 0.0)), ("after", SHIFT)):
        xy = rng.uniform(0, SIDE, size=(n, 2)) + [X0, Y0]
        z = rough_surface(xy - [sx, sy], (X0, Y0)) + sz
        write_las(d / f"field_{name}.las", PointCloud(xyz=np.column_stack([xy, z]), crs=UTM12))
    _write_field(d / "strain_field.gpkg", UTM12)
    _write_step_pair(d)
    return d


def _write_step_pair(d):
    """A slab moving by SHIFT north of a straight scarp at STEP_Y, the ground south of it by
    SOUTH_SHIFT (64 pts/m2, independent samplings), and the scarp as a line layer in WGS 84
    reaching 5 m beyond the survey both ways."""
    from slipmap.core.io.las import PointCloud, write_las

    rng = np.random.default_rng(9)
    n = int(64 * SIDE * SIDE)
    before = rng.uniform(0, SIDE, size=(n, 2)) + [X0, Y0]
    xy = rng.uniform(0, SIDE, size=(n, 2)) + [X0, Y0]  # after: where the points lie now
    north = xy[:, 1] >= STEP_Y
    shift = np.where(north[:, None], SHIFT, SOUTH_SHIFT)
    # the points south (north) of the scarp came from the south (north): each keeps its side
    src = xy - shift[:, :2]
    keep = (src[:, 1] >= STEP_Y) == north
    z_b = rough_surface(before, (X0, Y0))
    z_a = rough_surface(src[keep], (X0, Y0)) + shift[keep, 2]
    for name, pts in (("before", np.column_stack([before, z_b])),
                      ("after", np.column_stack([xy[keep], z_a]))):  # fmt: skip
        write_las(d / f"step_{name}.las", PointCloud(xyz=pts, crs=UTM12))
    to_wgs = pyproj.Transformer.from_crs(UTM12, "EPSG:4326", always_xy=True)
    lon, lat = to_wgs.transform([X0 - 5.0, X0 + SIDE + 5.0], [STEP_Y, STEP_Y])
    _write_lines(d / "scarp.gpkg", [np.column_stack([lon, lat])], pyproj.CRS.from_epsg(4326))


# --------------------------------------------------------------------------- the desktop


@pytest.fixture(scope="module")
def profile(tmp_path_factory):
    """A throw-away QGIS profile with the plugin installed from its zip and enabled."""
    _require_desktop()
    base = tmp_path_factory.mktemp("qgis_profiles")
    plugins = base / "profiles" / "default" / "python" / "plugins"
    plugins.mkdir(parents=True)
    (base / "profiles" / "default" / "QGIS").mkdir()
    zip_path = base / "slipmap.zip"
    subprocess.run(["bash", str(ROOT / "scripts" / "plugin_zip.sh"), str(zip_path)], check=True)
    with zipfile.ZipFile(zip_path) as z:
        z.extractall(plugins)
    (base / "profiles" / "default" / "QGIS" / "QGIS3.ini").write_text(
        "[PythonPlugins]\nslipmap=true\n[qgis]\ncheckVersion=false\nshowTips=false\n"
    )
    # laspy and lazrs where `pip install --user` would put them: a folder QGIS's Python reads
    site = base / "user-site"
    site.mkdir()
    for module in ("laspy", "lazrs"):
        spec = importlib.util.find_spec(module)
        assert spec is not None and spec.origin, f"{module} is not installed in the test venv"
        origin = Path(spec.origin)
        src = origin.parent if origin.name == "__init__.py" else origin
        (site / src.name).symlink_to(src)
    return base


def _launch(profile, plan, tmp, *, block=(), timeout=600):
    """Start the desktop on ``plan``; return the driver's record and the message log."""
    plan_path, out = tmp / "plan.json", tmp / "record.json"
    messages = tmp / "messages.jsonl"
    plan = dict(plan, out=str(out))
    plan_path.write_text(json.dumps(plan))
    env = dict(os.environ)
    env.pop("QT_QPA_PLATFORM", None)  # the desktop on Xvfb, not offscreen
    env.update(
        SLIPMAP_DESKTOP_PLAN=str(plan_path),
        SLIPMAP_DESKTOP_MESSAGES=str(messages),
        SLIPMAP_DESKTOP_BLOCK=",".join(block),
        PYQGIS_STARTUP=str(HERE / "desktop_startup.py"),
        PYTHONPATH=str(profile / "user-site"),
        PYTHONDONTWRITEBYTECODE="1",
        PYTHONFAULTHANDLER="1",  # a crash of the desktop prints every thread's Python stack
    )
    for var in ("VIRTUAL_ENV", "PYTHONHOME"):
        env.pop(var, None)
    cmd = [XVFB, "-a", "-s", "-screen 0 1600x1000x24", QGIS, "--profiles-path", str(profile)]
    cmd += ["--nologo", "--noversioncheck", "--code", str(HERE / "desktop_driver.py")]
    try:
        run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
        tail = (run.returncode, run.stdout[-3000:], run.stderr[-6000:])
    except subprocess.TimeoutExpired as exc:
        tail = ("timeout", str(exc.stdout)[-3000:], str(exc.stderr)[-3000:])
    assert out.is_file(), f"the desktop wrote no record: {tail}"
    record = json.loads(out.read_text())
    record["messages"] = (
        [json.loads(line) for line in messages.read_text().splitlines()]
        if messages.is_file()
        else []
    )
    record["process"] = tail
    assert not record.get("unexpected_dialogs"), record["unexpected_dialogs"]
    return record


def _optional_text_fields(alg_id):
    """The optional parameters of ``alg_id`` a user types into: files, texts, points."""
    from qgis.core import QgsApplication, QgsProcessingParameterDefinition

    alg = QgsApplication.processingRegistry().algorithmById(f"slipmap:{alg_id}")
    return [
        p.name()
        for p in alg.parameterDefinitions()
        if p.flags() & QgsProcessingParameterDefinition.FlagOptional
        and not p.isDestination()
        and p.type() in ("file", "string", "point")
    ]


def _shots(tmp):
    target = os.environ.get("SLIPMAP_DESKTOP_SHOTS")
    return Path(target).resolve() if target else tmp


def _required(data):
    slip = {
        "BEFORE": str(data / "slip_before.las"),
        "AFTER": str(data / "slip_after.las"),
        "FAULT": {"layer": "trace"},
    }
    pair = {"BEFORE": str(data / "field_before.las"), "AFTER": str(data / "field_after.las")}
    one = {"INPUT": str(data / "field_before.las")}
    return {
        "planes": one,
        "displacement": slip,
        "pointaccuracy": one,
        "roughness": one,
        "piv": pair,
        "windowedicp": pair,
        "demdiff": pair,
        "strain": {"FIELD": {"layer": "field"}},
    }


def _layers(data, alg):
    if alg == "displacement":
        return {"trace": str(data / "trace.gpkg")}
    if alg == "strain":
        return {"field": str(data / "strain_field.gpkg")}
    return {}


@pytest.fixture(scope="module")
def desktop(provider, data, profile, tmp_path_factory):
    """One desktop session running every scenario; the driver's record by scenario id."""
    tmp = tmp_path_factory.mktemp("desktop_run")
    shots = _shots(tmp)
    shots.mkdir(parents=True, exist_ok=True)
    required = _required(data)
    scenarios = []
    for alg in ALGORITHMS:
        scenarios.append(
            {
                "id": f"{alg}-default",
                "alg": f"slipmap:{alg}",
                "layers": _layers(data, alg),
                "values": required[alg],
                "shot": str(shots / f"desktop_{alg}.png"),
            }
        )
    for alg in ALGORITHMS:
        scenarios.append(
            {
                "id": f"{alg}-cleared",
                "alg": f"slipmap:{alg}",
                "layers": _layers(data, alg),
                "values": required[alg],
                "clear": _optional_text_fields(alg),
            }
        )
    full = tmp / "full"
    full.mkdir()
    slip_outputs = {
        "SUMMARY": str(full / "slip.json"),
        "PLANES": str(full / "planes.gpkg"),
        "TILES": str(full / "tiles.gpkg"),
        "STRIPS": str(full / "strips.gpkg"),
        "WINDOWS": str(full / "windows.tif"),
    }
    slip_settings = {"TILE_SIZE": 30.0, "STRIP_WIDTH": 30.0, "WINDOW_SIZE": 30.0}
    scenarios.append(
        {
            "id": "displacement-full",
            "alg": "slipmap:displacement",
            "layers": _layers(data, "displacement"),
            "values": {**required["displacement"], **slip_settings},
            "outputs": slip_outputs,
            "shot": str(shots / "desktop_displacement_maps.png"),
            "shot_dialog": str(shots / "desktop_displacement_dialog.png"),
        }
    )
    tilted = tmp / "tilted"
    tilted.mkdir()
    scenarios.append(
        {
            "id": "displacement-random-tilt",
            "alg": "slipmap:displacement",
            "layers": _layers(data, "displacement"),
            "values": {**required["displacement"], "RANDOM_TILT": True},
            "outputs": {"SUMMARY": str(tilted / "slip.json")},
        }
    )
    cancelled = tmp / "cancelled"
    cancelled.mkdir()
    scenarios.append(
        {
            "id": "displacement-cancel",
            "alg": "slipmap:displacement",
            "layers": _layers(data, "displacement"),
            "values": {**required["displacement"], **slip_settings},
            "outputs": {k: str(cancelled / Path(v).name) for k, v in slip_outputs.items()},
            "cancel_at_progress": 3,
        }
    )
    stepped = tmp / "stepped"
    stepped.mkdir()
    step_pair = {
        "BEFORE": str(data / "step_before.las"),
        "AFTER": str(data / "step_after.las"),
        "BREAKLINES": {"layer": "scarp"},
    }
    for alg, outputs in (
        (
            "windowedicp",
            {"SUMMARY": str(stepped / "icp.json"), "VECTORS": str(stepped / "icp.gpkg")},
        ),
        ("piv", {"SUMMARY": str(stepped / "piv.json"), "VECTORS": str(stepped / "piv.gpkg")}),
    ):
        scenarios.append(
            {
                "id": f"{alg}-breaklines",
                "alg": f"slipmap:{alg}",
                "layers": {"scarp": str(data / "scarp.gpkg")},
                "values": step_pair,
                "outputs": outputs,
            }
        )
    only = os.environ.get("SLIPMAP_DESKTOP_ONLY")  # scenario ids, comma-separated (debugging)
    if only:
        scenarios = [s for s in scenarios if s["id"] in only.split(",")]
    record = _launch(profile, {"scenarios": scenarios}, tmp, timeout=900)
    by_id = {s["id"]: s for s in record["scenarios"]}
    dirs = {"full": full, "cancelled": cancelled, "tilted": tilted, "stepped": stepped}
    return record, by_id, dirs


def _scenario(desktop, sid):
    record, by_id, _ = desktop
    assert sid in by_id, (
        f"scenario {sid} did not run; the desktop's last words: {record['process']}"
    )
    s = by_id[sid]
    assert "error" not in s, s["error"]
    return s


def _assert_ran(s):
    log = s.get("log", "")
    assert not s["message_boxes"], f"Run was refused: {s['message_boxes']}"
    assert not s.get("timed_out"), f"no end in sight: {log[-1500:]}"
    assert s["completed"], f"the run failed:\n{log[-2500:]}"
    assert "not correctly generated" not in log, log[-2500:]  # QGIS's "layers not generated"


def _assert_styled(layer):
    assert layer["valid"], layer
    assert layer["fingerprint"] != layer["default_fingerprint"], (
        f"{layer['name']} opened with QGIS's default style: {layer['fingerprint']}"
    )
    if "ranges" in layer and layer["data_min"] is not None:
        lo = min(r[0] for r in layer["ranges"])
        hi = max(r[1] for r in layer["ranges"])
        tol = 1e-9 + 1e-6 * max(abs(lo), abs(hi))
        assert lo - tol <= layer["data_min"] and layer["data_max"] <= hi + tol, (
            f"{layer['name']}: legend {lo}..{hi} does not span the data "
            f"{layer['data_min']}..{layer['data_max']}"
        )
    if "categories" in layer:
        cats = {c[0] for c in layer["categories"]}
        assert set(layer["data_values"]) <= cats | {""}, (layer["name"], cats)
    if layer.get("class_min") is not None and layer.get("data_min") is not None:
        tol = 1e-9 + 1e-6 * max(abs(layer["class_min"]), abs(layer["class_max"]))
        assert layer["class_min"] - tol <= layer["data_min"], layer
        assert layer["data_max"] <= layer["class_max"] + tol, layer


def _assert_rasters_below_vectors(layers):
    vectors = [lyr["tree_index"] for lyr in layers if lyr["kind"] == "vector"]
    for lyr in layers:
        if lyr["kind"] == "raster" and vectors:
            assert lyr["tree_index"] > max(vectors), (
                f"raster {lyr['name']} lies above a vector layer: "
                f"{[(x['name'], x['tree_index']) for x in layers]}"
            )


# --------------------------------------------------------------------------- the tests


@pytest.mark.parametrize("alg", ALGORITHMS)
def test_runs_from_its_dialog_with_only_the_required_fields(desktop, alg):
    s = _scenario(desktop, f"{alg}-default")
    _assert_ran(s)
    layers = s["layers"]
    assert len(layers) >= LOADED[alg], [x["name"] for x in layers]
    for layer in layers:
        _assert_styled(layer)
    _assert_rasters_below_vectors(layers)


@pytest.mark.parametrize("alg", ALGORITHMS)
def test_runs_with_every_optional_text_field_typed_and_cleared(desktop, alg):
    s = _scenario(desktop, f"{alg}-cleared")
    _assert_ran(s)


def test_fault_slip_maps_open_styled_with_one_sign(desktop):
    """Tiles, strips, windows and planes of a run with known dextral slip: every map styled,
    its legend spanning the data, the rasters below the vectors, and the slip read
    right-lateral (+) on every legend."""
    s = _scenario(desktop, "displacement-full")
    _assert_ran(s)
    layers = s["layers"]
    assert len(layers) >= 4, [x["name"] for x in layers]
    for layer in layers:
        _assert_styled(layer)
    _assert_rasters_below_vectors(layers)
    summary = json.loads((desktop[2]["full"] / "slip.json").read_text())
    slip = summary["relative"]["right_lateral_slip"]
    assert abs(slip - DEXTRAL_M) < 0.005, slip
    # the known dextral motion reads + on every map: the moving (east) side's tiles and strips
    # near +18 mm, the still side near 0, the windows' band + at its red end
    by_kind = {}
    for layer in layers:
        by_kind.setdefault(layer["name"].split(" ")[0], layer)
    for name in ("Tiles", "Strips"):
        lo, hi = by_kind[name]["right_lateral_range"]
        assert 0.012 < hi < 0.025 and lo > -0.006, (name, lo, hi)
    windows = by_kind["Moving"]
    assert windows["data_max"] > 0.012 and windows["data_min"] > -0.006, windows
    assert windows["labels"][-1].endswith("(+ = right-lateral)"), windows["labels"]
    assert windows["labels"][0].endswith("(\u2212 = left-lateral)"), windows["labels"]
    legend = " ".join(" ".join(map(str, x.get("rules", []))) for x in layers)
    assert "right-lateral" in legend, legend


def test_random_tilt_ticked_in_the_dialog_reaches_both_sides(desktop):
    """The advanced checkbox "Random tilt per plane" ticked in the real dialog: the run
    records it and each side's adjustment estimated a random tilt."""
    s = _scenario(desktop, "displacement-random-tilt")
    _assert_ran(s)
    assert s["parameters"]["RANDOM_TILT"] == "True", s["parameters"]
    summary = json.loads((desktop[2]["tilted"] / "slip.json").read_text())
    assert summary["parameters"]["random_tilt"] is True
    for side in ("left", "right"):
        tilt = summary[side]["variance_components"]["random_tilt"]
        assert tilt["source"] == "estimated" and tilt["sigma_rad"] >= 0.0, tilt


def _step_truth(xy):
    """The step pair's motion (N, 3) at map positions ``xy`` (N, 2)."""
    return np.where((xy[:, 1] >= STEP_Y)[:, None], SHIFT, SOUTH_SHIFT)


def _vectors(path):
    """x, y (N, 2) and each column (N,) of a vectors GeoPackage, by name."""
    _, names, rows = features(path)
    return {"xy": rows[:, :2], **{n: column(names, rows, n) for n in names}}


def test_icp_breaklines_picked_in_the_dialog_keep_the_step(desktop):
    """The scarp picked as a line layer (WGS 84) in the windowed ICP's own dialog: the run
    reports the given line, reprojected to the clouds' CRS, and the default spline field
    jumps across it: every cell 3 m or more from the scarp has its own side's motion (0.43
    m apart across it) to 5 mm, on noise-free ground sampled at 64 pts/m2."""
    s = _scenario(desktop, "windowedicp-breaklines")
    _assert_ran(s)
    assert "scarp" in s["parameters"]["BREAKLINES"], s["parameters"]
    summary = json.loads((desktop[2]["stepped"] / "icp.json").read_text())
    assert summary["model"]["field"] == "spline", summary["model"]
    lines = summary["breaklines"]
    assert lines["source"] == "given" and lines["count"] == 1, lines
    got = np.array(lines["lines"][0])
    np.testing.assert_allclose(got[:, 1], STEP_Y, atol=0.01)  # through WGS 84 and back
    v = _vectors(desktop[2]["stepped"] / "icp.gpkg")
    far = np.abs(v["xy"][:, 1] - STEP_Y) >= 3.0
    assert far.sum() >= 8 and (v["xy"][far, 1] > STEP_Y).any(), v["xy"]
    err = np.column_stack([v["dx"], v["dy"], v["dz"]])[far] - _step_truth(v["xy"][far])
    assert np.all(np.abs(err) < 0.005), np.round(err, 4)


def test_piv_breaklines_picked_in_the_dialog_flag_the_vectors_at_the_scarp(desktop):
    """The scarp picked in PIV's own dialog: the vectors whose final window (the default
    window and grid: 16 px of 0.25 m) the scarp crosses are flagged (near_break), those
    whose window it does not reach are not, and the summary counts them; the vectors 3 m or
    more from it have their own side's motion within the issue's mark, 0.25 cell RMS."""
    from slipmap.app import piv as piv_job

    s = _scenario(desktop, "piv-breaklines")
    _assert_ran(s)
    summary = json.loads((desktop[2]["stepped"] / "piv.json").read_text())
    v = _vectors(desktop[2]["stepped"] / "piv.gpkg")
    flagged = v["near_break"] == 1
    grid_m = piv_job.SPEC["grid_m"].default
    half = 0.5 * piv_job.SPEC["windows_px"].default[-1] * grid_m  # the final window, metres
    off = np.abs(v["xy"][:, 1] - STEP_Y)
    assert 0 < flagged.sum() < len(flagged), flagged.sum()
    assert np.all(off[flagged] <= half + 0.01), off[flagged]
    assert not flagged[off > half + 0.26].any(), off[flagged]
    assert summary["n_near_break"] == int(flagged.sum())
    far = (off >= 3.0) & (v["valid"] == 1)
    assert far.sum() >= 40, far.sum()
    err = np.column_stack([v["dx"], v["dy"]])[far] - _step_truth(v["xy"][far])[:, :2]
    rms = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    assert rms <= 0.25 * grid_m, rms


def test_cancel_leaves_nothing_behind(desktop):
    s = _scenario(desktop, "displacement-cancel")
    assert any("Cancel pressed" in e[1] for e in s["events"]), s["events"]
    assert not s["completed"], "the run completed before Cancel was pressed"
    assert not s["layers"], [x["name"] for x in s["layers"]]
    assert not any(desktop[2]["cancelled"].iterdir()), list(desktop[2]["cancelled"].iterdir())
    log = s["log"].lower()
    assert "cancel" in log, s["log"][-1500:]
    assert "has been generated" not in log and "' finished" not in log, s["log"][-1500:]


def test_progress_never_runs_backwards(desktop):
    _, by_id, _ = desktop
    for sid, s in by_id.items():
        values = [p for _, p, _ in s.get("progress", []) if p is not None and p > 0]
        drops = [(a, b) for a, b in zip(values, values[1:]) if b < a - 1]
        assert not drops, (sid, s["progress"])


@pytest.fixture(scope="module")
def desktop_without_dependencies(provider, data, profile, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("desktop_missing")
    plan = {
        "scenarios": [
            {
                "id": "displacement-missing",
                "alg": "slipmap:displacement",
                "layers": _layers(data, "displacement"),
                "values": _required(data)["displacement"],
            }
        ]
    }
    return _launch(profile, plan, tmp, block=("laspy", "lazrs", "scipy"), timeout=240)


def test_missing_dependencies_are_said_where_the_user_looks(desktop_without_dependencies):
    record = desktop_without_dependencies
    state = record["state"]
    assert state["provider"], record["process"]
    ids = sorted(a["id"].split(":")[1] for a in state["algorithms"])
    assert ids == sorted(ALGORITHMS), ids  # nothing vanishes
    for alg in state["algorithms"]:
        assert not alg["can_execute"], alg
        # each names what it needs (strain reads a table or GeoTIFF: scipy only) and the
        # command that installs it on this machine (Debian: apt for scipy, pip for the rest)
        needs = ("scipy",) if alg["id"] == "slipmap:strain" else ("laspy", "lazrs", "scipy")
        for module in needs:
            assert module in alg["why"], alg
        assert "python3-scipy" in alg["why"], alg
        if "laspy" in needs:
            assert "--break-system-packages laspy lazrs" in alg["why"], alg
        assert alg["why"] in alg["short_description"], alg  # the toolbox's tooltip says it
    s = record["scenarios"][0]
    assert not s.get("completed"), s.get("log", "")[-1500:]
    said = " ".join(t for _, t in s["message_boxes"]) + s.get("log", "")
    assert "laspy" in said, said[-1500:]
