"""Guards before work (issue #31, bad cases 1-3): runaway tile counts, a tile smaller than a
cell, one stray point 50 km away, a spline too fine or on too few cells. Every face refuses
at once with the option (or the stray tile) named: the CLI in a subprocess killed at 60 s
(a kill counts as a failure) with exit 2, one line, no traceback, no staging folder, inputs
byte-identical; the PDAL stage with a StageError naming the key; QGIS with the dialog label.
"""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyproj
import pytest

from slipmap.core.io.las import PointCloud, read_las, write_las

pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pdal_stages"))

X0, Y0 = 500000.0, 4200000.0
CRS = pyproj.CRS.from_epsg(32611)
STRAY = (X0 + 50000.0, Y0 + 50000.0)  # one point 50 km away
TIMEOUT_S = 60


def _surface(n, seed, side=40.0, shift=(0.0, 0.0)):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, side, (n, 2))
    z = 100 + 0.5 * np.sin(xy[:, 0] / 3) * np.cos(xy[:, 1] / 2.3) + rng.normal(0, 0.005, n)
    return np.column_stack([xy[:, 0] + X0 + shift[0], xy[:, 1] + Y0 + shift[1], z])


def _write_tiles(folder, xyz, *, split=2, side=40.0, stray=False):
    """``split`` x ``split`` files of ``xyz``; with ``stray``, one point 50 km away in the
    first file (its header box then spans the gap)."""
    folder.mkdir(parents=True)
    t = side / split
    ix = np.clip(((xyz[:, :2] - [X0, Y0]) // t).astype(int), 0, split - 1)
    for i in range(split):
        for j in range(split):
            p = xyz[(ix[:, 0] == i) & (ix[:, 1] == j)]
            if stray and i == j == 0:
                p = np.vstack([p, [[*STRAY, 100.0]]])
            write_las(folder / f"tile_{i}_{j}.laz", PointCloud(xyz=p, attributes={}, crs=CRS))
    return folder


@pytest.fixture(scope="module")
def data(tmp_path_factory, line_file):
    """Small epochs: one file each (with and without a stray point), tile sets of them, a
    fault pair and its tiles, a fault trace."""
    from slipmap.core.synthetic import make_fault_pair

    d = tmp_path_factory.mktemp("guards")
    b, a = _surface(6000, 1), _surface(6000, 2, shift=(0.02, 0.0))
    out = {}
    for name, xyz in (("b", b), ("a", a)):
        write_las(d / f"{name}.laz", PointCloud(xyz=xyz, attributes={}, crs=CRS))
        stray = np.vstack([xyz, [[*STRAY, 100.0]]])
        write_las(d / f"{name}_stray.laz", PointCloud(xyz=stray, attributes={}, crs=CRS))
        out[name] = d / f"{name}.laz"
        out[name + "_stray"] = d / f"{name}_stray.laz"
        out[name + "_tiles"] = _write_tiles(d / f"{name}_tiles", xyz)
        out[name + "_stray_tiles"] = _write_tiles(d / f"{name}_stray_tiles", xyz, stray=True)
    fp = make_fault_pair(
        "mls", seed=7, origin=(X0, Y0, 20.0), right_offset_m=(0.0, -0.0181, 0.0),
        density_pts_m2=8.0,
    )  # fmt: skip
    for name, sc in (("fb", fp.before), ("fa", fp.after)):
        write_las(d / f"{name}.laz", PointCloud(xyz=sc.points, attributes={}, crs=CRS))
        out[name] = d / f"{name}.laz"
        lo = sc.points[:, :2].min(axis=0)
        side = float(np.max(sc.points[:, :2].max(axis=0) - lo)) + 1e-3
        sh = sc.points - [lo[0] - X0, lo[1] - Y0, 0.0]  # tiles cut from the data's corner
        tiles = _write_tiles(d / f"{name}_tiles", sh, side=side)
        for f in tiles.iterdir():  # back to the pair's coordinates
            c = read_las(f)
            write_las(f, PointCloud(xyz=c.xyz + [lo[0] - X0, lo[1] - Y0, 0.0], crs=CRS))
        out[name + "_tiles"] = tiles
    out["fault"] = d / "fault.gpkg"
    line_file(out["fault"], fp.trace_xy, CRS)
    out["trace_xy"] = fp.trace_xy
    out["pair"] = fp
    out["root"] = d
    return out


def _state(root):
    return sorted(
        (str(p.relative_to(root)), hashlib.sha256(p.read_bytes()).hexdigest())
        for p in root.rglob("*")
        if p.is_file()
    )


def _cli(data, tmp_path, *argv):
    """Run ``slipmap ARGV --out tmp_path/out`` in a subprocess killed at 60 s."""
    before = _state(data["root"])
    out = tmp_path / "out"
    args = [str(data.get(a, a)) if isinstance(a, str) else str(a) for a in argv]
    cmd = [sys.executable, "-m", "slipmap.cli", *args, "--out", str(out)]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    try:
        p = subprocess.run(
            cmd, capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path, env=env
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"no refusal within {TIMEOUT_S} s: {' '.join(args)}")
    text = p.stdout + p.stderr
    assert p.returncode == 2, text
    assert "Traceback" not in text, text
    errors = [ln for ln in p.stderr.splitlines() if "error:" in ln]
    assert len(errors) == 1, text
    assert not list(tmp_path.rglob(".slipmap-partial-*")), list(tmp_path.rglob("*"))
    assert not list(data["root"].rglob(".slipmap-partial-*"))
    assert _state(data["root"]) == before  # inputs byte-identical, nothing added
    return errors[0]


def _has(msg, *words):
    for w in words:
        assert w in msg, f"{w!r} not in: {msg}"


# --------------------------------------------------------------------------- bad case 1


def test_displacement_tiny_tiles_one_file(data, tmp_path):
    msg = _cli(data, tmp_path, "displacement", "fb", "fa", "--fault", "fault",
               "--tile-size", "0.001")  # fmt: skip
    _has(msg, "--tile-size", "tiles, more than the 50000", "or more (the smallest that fits)")


def test_displacement_tiny_tiles_tiled(data, tmp_path):
    msg = _cli(data, tmp_path, "displacement", "fb_tiles", "fa_tiles", "--fault", "fault",
               "--tile-size", "0.001")  # fmt: skip
    _has(msg, "--tile-size", "tiles, more than the 50000", "or more (the smallest that fits)")


def test_roughness_tile_smaller_than_a_cell(data, tmp_path):
    msg = _cli(data, tmp_path, "roughness", "b_tiles", "--cell", "0.5", "--tile-size", "0.2")
    _has(msg, "--tile-size", "smaller than the largest cell (0.5 m)", "choose 0.5 m or more")


@pytest.mark.parametrize("job", ["planes", "roughness"])
def test_tile_budget_names_the_smallest_tile(data, tmp_path, job):
    msg = _cli(data, tmp_path, job, "b_tiles", "--tile-size", "0.02",
               *(["--cell", "0.01"] if job == "roughness" else []))  # fmt: skip
    _has(msg, "--tile-size", "= 0.02 m cuts the data into", "choose 0.2 m or more")


def test_roughness_tiled_keeps_every_edge_cell(tmp_path):
    """Tiles of 8 m (not a multiple of the 1.5 m cell; a tile edge at x = 500000) and data
    from x = 500000.35: the first column of cells has its lower corner at 499999.5, in a tile
    no file meets (it was dropped). Tiled = one file: every cell, with its value."""
    from slipmap.app.tiled import roughness_tiled
    from slipmap.core.io.tiles import open_collection
    from slipmap.core.roughness import grid_roughness

    xyz = _surface(20000, 5, side=30.0) + [0.35, 0.35, 0.0]
    folder = tmp_path / "t"
    folder.mkdir()
    cut = np.clip(((xyz[:, :2] - [X0, Y0]) // 10.0).astype(int), 0, 2)
    for i in range(3):
        for j in range(3):
            p = xyz[(cut[:, 0] == i) & (cut[:, 1] == j)]
            write_las(folder / f"t{i}{j}.laz", PointCloud(xyz=p, attributes={}, crs=CRS))
    coll = open_collection(str(folder))
    (tiled,) = roughness_tiled(coll, cell_sizes_m=[1.5], tile_size_m=8.0, ols_axis="z")
    # the one-file grid on the same origin (the tiles' header bounds, as the tiled run)
    whole = grid_roughness(coll_points(coll), cell_size_m=1.5, ols_axis="z")
    assert tiled.index.shape == whole.index.shape
    assert np.any(whole.index[:, 0] == 0)  # the edge column is there
    np.testing.assert_array_equal(tiled.index, whole.index)
    np.testing.assert_allclose(tiled.theta_odr, whole.theta_odr, rtol=1e-9, atol=1e-12)


def coll_points(coll):
    return np.vstack([read_las(f.path).xyz for f in coll.files])


# --------------------------------------------------------------------------- bad case 2


@pytest.mark.parametrize(
    "job, extra",
    [
        ("dem-diff", ["a_stray_tiles", "--grid", "1"]),
        ("piv", ["a_stray_tiles", "--grid", "1"]),
        ("icp", ["a_stray_tiles", "--cell", "4"]),
        ("roughness", ["--cell", "0.5"]),
        ("planes", []),
    ],
)
def test_stray_point_in_a_tile_is_named(data, tmp_path, job, extra):
    msg = _cli(data, tmp_path, job, "b_stray_tiles", *extra)
    key = "INPUT" if job in ("roughness", "planes") else "BEFORE"
    _has(msg, key, "tile tile_0_0.laz", "x 500000.0..550000.0, y 4200000.0..4250000.0",
         "a stray point?", "remove it from the file")  # fmt: skip


def test_icp_one_file_stray_point(data, tmp_path):
    msg = _cli(data, tmp_path, "icp", "b_stray", "a_stray", "--cell", "4")
    _has(msg, "--cell", "1 point(s) of the after epoch lie far from the others",
         "x 550000.0, y 4250000.0", "remove the stray points")  # fmt: skip


def test_dem_diff_one_file_stray_point(data, tmp_path):
    msg = _cli(data, tmp_path, "dem-diff", "b_stray", "a_stray", "--grid", "1")
    _has(msg, "--grid", "cells and need")


# --------------------------------------------------------------------------- bad case 3


def test_spline_spacing_too_fine(data, tmp_path):
    msg = _cli(data, tmp_path, "icp", "b", "a", "--cell", "4", "--field-model", "spline",
               "--spline-spacing", "1e-4")  # fmt: skip
    _has(msg, "--spline-spacing", "knots", "more than the 250000", "m or more")


def test_spline_on_too_few_cells(data, tmp_path):
    msg = _cli(data, tmp_path, "icp", "b", "a", "--cell", "1000", "--field-model", "spline")
    _has(msg, "--cell", "too few cells for a spline field", "use a smaller cell")


# --------------------------------------------------------------------------- PDAL stage


def test_pdal_displacement_tiny_tiles(data):
    from pdal_harness import call, load_stage, make_ins

    from slipmap.pdal_filters._stage import StageError

    fp = data["pair"]
    (x0, y0), (x1, y1) = (map(float, v) for v in fp.trace_xy)
    pts = np.vstack([fp.before.points, fp.after.points])
    tag = np.r_[np.ones(len(fp.before.points)), np.full(len(fp.after.points), 2.0)]
    opts = {"trace": f"LINESTRING ({x0!r} {y0!r}, {x1!r} {y1!r})", "tile_size_m": 0.001}
    declared = {"PlaneId": np.dtype(np.int32), "Residual": np.dtype(np.float64)}
    with pytest.raises(StageError) as e:
        call(load_stage("displacement", opts), make_ins(pts, Epoch=tag), declared)
    _has(str(e.value), "tile_size_m", "tiles, more than the 50000", "the smallest that fits")
    assert "--" not in str(e.value)


# --------------------------------------------------------------------------- QGIS


@pytest.fixture(scope="module")
def qgis_provider():
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    pytest.importorskip("qgis.core", reason="QGIS Python bindings (python3-qgis) missing")
    from qgis.core import QgsApplication

    app = QgsApplication.instance()
    if app is None:  # alone in this session; else the one tests/qgis started
        app = QgsApplication([], False)
        app.initQgis()
    plugins = "/usr/share/qgis/python/plugins"
    if plugins not in sys.path:
        sys.path.append(plugins)
    from processing.core.Processing import Processing

    Processing.initialize()
    import slipmap

    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    yield
    plugin.unload()


def _qgis_refusal(alg, params):
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingException, QgsProcessingFeedback

    with pytest.raises(QgsProcessingException) as e:
        processing.run(
            f"slipmap:{alg}", params, context=QgsProcessingContext(),
            feedback=QgsProcessingFeedback(),
        )  # fmt: skip
    return str(e.value)


@pytest.mark.qgis
def test_qgis_demdiff_stray_tile(qgis_provider, data, tmp_path):
    before = _state(data["root"])
    msg = _qgis_refusal(
        "demdiff",
        {
            "BEFORE": str(data["b_stray_tiles"] / "*.laz"),
            "AFTER": str(data["a_stray_tiles"] / "*.laz"),
            "GRID": 1.0,
            "OUTPUT": str(tmp_path / "dd.tif"),
            "SUMMARY": str(tmp_path / "dd.json"),
        },
    )
    _has(msg, '"Before epoch"', "tile tile_0_0.laz", "a stray point?", '"Grid size (m)" = 1 m')
    assert list(tmp_path.iterdir()) == [] and _state(data["root"]) == before


@pytest.mark.qgis
def test_qgis_icp_spline_spacing(qgis_provider, data, tmp_path):
    msg = _qgis_refusal(
        "windowedicp",
        {
            "BEFORE": str(data["b"]),
            "AFTER": str(data["a"]),
            "CELL": 4.0,
            "FIELD_MODEL": 1,
            "SPLINE_SPACING": 1e-4,
            "CELLS": "TEMPORARY_OUTPUT",
            "VECTORS": "TEMPORARY_OUTPUT",
        },
    )
    _has(msg, "knots", "more than the 250000")
    assert "spacing" in msg.lower() and "--" not in msg
