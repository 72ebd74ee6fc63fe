"""Tile sets as delivered (issue #31, build item 2): a tile delivered twice is read once, with
a warning naming it; tiles whose boxes overlap count each point once; ``keep duplicate
points`` reads everything as given. Through the CLI (a subprocess, killed at 120 s: a hang
fails) and the QGIS provider; PDAL stages get a view, not tiles (no case there).

Known answers: the copy and the overlap give the un-overlapped set's point counts and planes
exactly, and the slip/σ of the same points in one file (the tiled path on one file) to 1e-9.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyproj
import pytest

from slipmap.core.io.las import PointCloud, read_las, write_las

#: GDAL's Python bindings (a fault trace, GeoTIFFs): not in the plain numpy-2 venv
NEEDS_GDAL = pytest.mark.skipif(
    importlib.util.find_spec("osgeo") is None, reason="GDAL's Python bindings (osgeo) missing"
)

DATA = Path(__file__).resolve().parents[1] / "data"
CRS = pyproj.CRS.from_epsg(32613)
UTM11 = pyproj.CRS.from_epsg(32611)
TIMEOUT_S = 120


def _cli(*args, cwd=None):
    exe = Path(sys.executable).with_name("slipmap")
    try:
        return subprocess.run(
            [str(exe), "--quiet", *map(str, args)],
            capture_output=True, text=True, timeout=TIMEOUT_S, cwd=cwd,
        )  # fmt: skip
    except subprocess.TimeoutExpired:  # the harness's time bound: a hang is a failure
        pytest.fail(f"slipmap {' '.join(map(str, args))} ran past {TIMEOUT_S} s")


def _digests(*folders):
    out = {}
    for folder in folders:
        for p in sorted(Path(folder).rglob("*")):
            if p.is_file():
                out[p] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _clean_exit(res, root):
    assert "Traceback" not in res.stderr, res.stderr
    assert not list(Path(root).rglob(".slipmap-partial-*"))


def _cut(cloud, folder, edges, grow=0.0):
    """Tiles of ``cloud`` on a grid of ``edges`` (x, y metres) from the data's lower corner,
    each grown by ``grow`` metres on every side (an overlapping delivery)."""
    folder.mkdir(parents=True)
    lo = np.floor(cloud.xyz[:, :2].min(0))
    hi = cloud.xyz[:, :2].max(0)
    nx, ny = (int(np.ceil((hi[k] - lo[k] + 1e-9) / edges[k])) for k in (0, 1))
    for i in range(nx):
        for j in range(ny):
            x0, y0 = lo[0] + i * edges[0], lo[1] + j * edges[1]
            x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
            m = (x >= x0 - grow) & (x < x0 + edges[0] + grow)
            m &= (y >= y0 - grow) & (y < y0 + edges[1] + grow)
            if m.any():
                write_las(folder / f"t_{i}_{j}.laz", cloud.subset(m))
    return folder


# --------------------------------------------------------------------------- planes (GpsTime)


@pytest.fixture(scope="module")
def lonestar(tmp_path_factory):
    """A 16 x 20 m part of lone-star.laz (GpsTime present) as one file, 2 x 2 tiles, the
    same tiles grown by 2 m (overlap), and the tiles with one delivered twice."""
    root = tmp_path_factory.mktemp("lonestar")
    full = read_las(DATA / "lone-star.laz", crs=CRS)
    lo = full.xyz[:, :2].min(0)
    part = full.subset((full.xyz[:, 0] < lo[0] + 16) & (full.xyz[:, 1] < lo[1] + 20))
    (root / "one").mkdir()
    write_las(root / "one" / "all.laz", part)
    _cut(part, root / "clean", (8.0, 10.0))
    _cut(part, root / "overlap", (8.0, 10.0), grow=2.0)
    shutil.copytree(root / "clean", root / "copied")
    shutil.copy(root / "clean" / "t_0_0.laz", root / "copied" / "t_0_0 (1).laz")
    return {"root": root, "n": len(part)}


def _planes(root, src, name, *extra):
    out = root / f"out_{name}"
    res = _cli("planes", src, "--tile-size", 10, "--out", out, *extra)
    _clean_exit(res, root)
    assert res.returncode == 0, res.stderr
    return json.loads((out / "planes.json").read_text()), res


def test_overlapping_tiles_count_each_point_once(lonestar):
    """2 m overlap: the header counts say more points than there are; every point is read
    once (the selected count is the one file's), the planes are the clean tiles' planes."""
    root = lonestar["root"]
    before = _digests(root / "overlap")
    ref, _ = _planes(root, root / "clean", "clean")
    got, res = _planes(root, root / "overlap", "overlap")
    assert got["n_points"] > lonestar["n"]  # the headers overlap ...
    assert ref["n_selected"] == got["n_selected"] == lonestar["n"]  # ... the points do not
    assert len(got["planes"]) == len(ref["planes"])
    assert [p["n_points"] for p in got["planes"]] == [p["n_points"] for p in ref["planes"]]
    np.testing.assert_allclose(
        [p["normal"] for p in got["planes"]], [p["normal"] for p in ref["planes"]], atol=1e-12
    )
    assert _digests(root / "overlap") == before  # inputs byte-identical


def test_keep_duplicate_points_reads_overlaps_as_given(lonestar):
    root = lonestar["root"]
    got, _ = _planes(root, root / "overlap", "overlap_kept", "--keep-duplicate-points")
    assert got["n_selected"] == got["n_points"] > lonestar["n"]


def test_tile_delivered_twice_is_read_once_with_a_warning(lonestar):
    root = lonestar["root"]
    before = _digests(root / "copied")
    ref, _ = _planes(root, root / "clean", "clean2")
    got, res = _planes(root, root / "copied", "copied")
    assert " are the same tile " in res.stderr and "read once" in res.stderr
    assert "t_0_0 (1).laz" in res.stderr and "t_0_0.laz" in res.stderr
    assert "--keep-duplicate-points" in res.stderr  # what to do, in the CLI's words
    assert got["n_selected"] == ref["n_selected"] == lonestar["n"]
    assert len(got["planes"]) == len(ref["planes"])
    assert _digests(root / "copied") == before


@NEEDS_GDAL
def test_roughness_and_dem_diff_on_overlapping_tiles(lonestar):
    """Roughness of overlapping tiles equals the clean tiles' cell by cell (points per cell
    are the test: a point read twice adds one); dem-diff of the overlap against the clean
    set is zero everywhere (each cell's mean is the same points' mean)."""
    from osgeo import gdal

    root = lonestar["root"]
    outs = {}
    for name in ("clean", "overlap"):
        out = root / f"rough_{name}"
        res = _cli("roughness", root / name, "--cell", 2, "--tile-size", 10, "--out", out)
        _clean_exit(res, root)
        assert res.returncode == 0, res.stderr
        tifs = sorted(out.glob("*.tif"))
        assert tifs
        outs[name] = [gdal.Open(str(t)).ReadAsArray() for t in tifs]
    for a, b in zip(outs["clean"], outs["overlap"]):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12, equal_nan=True)
    out = root / "dem_overlap"
    res = _cli("dem-diff", root / "clean", root / "overlap", "--grid", 2, "--out", out)
    _clean_exit(res, root)
    assert res.returncode == 0, res.stderr
    ds = gdal.Open(str(sorted(out.glob("*.tif"))[0]))
    band = ds.GetRasterBand(1)
    dz = band.ReadAsArray().astype(float)
    nodata = band.GetNoDataValue()
    del band, ds
    ok = np.isfinite(dz) & (dz != nodata if nodata is not None else True)
    assert ok.sum() > 10 and np.max(np.abs(dz[ok])) < 1e-9


# --------------------------------------------------------------------------- slip


@pytest.fixture(scope="module")
def fault_pair(tmp_path_factory):
    """A synthetic fault pair (no GpsTime: identity by coordinates) as one file per epoch
    (in a folder, read by a glob: the tiled path on one file), as 30 m tiles, as the same
    tiles grown by 2 m, and as the tiles with one before-tile delivered twice."""
    from slipmap.core.synthetic import make_fault_pair

    root = tmp_path_factory.mktemp("pair")
    pair = make_fault_pair(
        "mls", seed=7, origin=(500000.0, 4200000.0, 10.0), right_offset_m=(0.0, -0.0181, 0.0),
        vegetation=False,
    )  # fmt: skip
    lon, lat = pyproj.Transformer.from_crs(UTM11, "EPSG:4326", always_xy=True).transform(
        pair.trace_xy[:, 0], pair.trace_xy[:, 1]
    )
    line = {"type": "LineString", "coordinates": [[a, b] for a, b in zip(lon, lat)]}
    feature = {"type": "Feature", "properties": {}, "geometry": line}
    (root / "trace.geojson").write_text(
        json.dumps({"type": "FeatureCollection", "features": [feature]})
    )
    for name, scene in (("before", pair.before), ("after", pair.after)):
        (root / "one" / name).mkdir(parents=True)
        write_las(root / "one" / name / f"{name}.laz", PointCloud(scene.points, {}, UTM11))
        cloud = read_las(root / "one" / name / f"{name}.laz")
        _cut(cloud, root / "clean" / name, (30.0, 30.0))
        _cut(cloud, root / "overlap" / name, (30.0, 30.0), grow=2.0)
    shutil.copytree(root / "clean", root / "copied")
    first = sorted((root / "copied" / "before").glob("*.laz"))[0]
    shutil.copy(first, first.with_name("copy_of_" + first.name))
    return root


def _slip(root, layout, name, *extra):
    out = root / f"out_{name}"
    if layout == "one":
        b, a = root / "one/before/*.laz", root / "one/after/*.laz"
    else:
        b, a = root / layout / "before", root / layout / "after"
    res = _cli(
        "displacement", b, a, "--fault", root / "trace.geojson", "--tile-size", 35,
        "--units", "none", "--out", out, *extra,
    )  # fmt: skip
    _clean_exit(res, root)
    assert res.returncode == 0, res.stderr
    return json.loads((out / "displacement.json").read_text()), res


def _same(a, b, rel=1e-9):
    fa, fb = _flat(a), _flat(b)
    assert fa.keys() == fb.keys()
    for k in fa:
        x, y = fa[k], fb[k]
        assert abs(x - y) <= rel * max(abs(y), 1e-6), (k, x, y)


def _flat(node, prefix=""):
    """The numbers of the summary's headline (slip and its σ), by path."""
    out = {}
    if isinstance(node, dict):
        for k, v in node.items():
            if k in ("runtime_s", "input", "before", "after", "engine", "files", "parameters"):
                continue
            out.update(_flat(v, f"{prefix}/{k}"))
    elif isinstance(node, (int, float)) and not isinstance(node, bool):
        out[prefix] = float(node)
    return out


def _headline(d):
    """The slip and its σ in the fault frame (the JSON's ``relative``)."""
    return d["relative"]


@NEEDS_GDAL
def test_slip_with_a_tile_delivered_twice_equals_without(fault_pair):
    root = fault_pair
    ref, _ = _slip(root, "clean", "clean")
    got, res = _slip(root, "copied", "copied")
    assert "before epoch: " in res.stderr and " are the same tile " in res.stderr
    assert "/t_0_0.laz" in res.stderr and "/copy_of_t_0_0.laz" in res.stderr
    _same(_headline(got), _headline(ref))
    kept, _ = _slip(root, "copied", "copied_kept", "--keep-duplicate-points")
    assert _flat(_headline(kept)) != _flat(_headline(ref))  # the copy read twice differs


@NEEDS_GDAL
def test_slip_on_overlapping_tiles_equals_one_file(fault_pair):
    root = fault_pair
    one, _ = _slip(root, "one", "one")
    got, _ = _slip(root, "overlap", "overlap")
    _same(_headline(got), _headline(one))


# --------------------------------------------------------------------------- QGIS


@pytest.mark.qgis
def test_qgis_planes_checkbox_and_copy_warning(provider, lonestar, tmp_path):
    """The option is a checkbox of the planes dialog (advanced); a copied tile is read once
    and the warning reaches the Processing log naming the files."""
    import processing
    from qgis.core import (
        QgsApplication,
        QgsProcessingContext,
        QgsProcessingFeedback,
        QgsProcessingParameterBoolean,
        QgsProcessingParameterDefinition,
    )

    alg = QgsApplication.processingRegistry().algorithmById("slipmap:planes")
    p = alg.parameterDefinition("KEEP_DUPLICATE_POINTS")
    assert isinstance(p, QgsProcessingParameterBoolean)
    assert p.flags() & QgsProcessingParameterDefinition.FlagAdvanced

    class Log(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.lines = []

        def reportError(self, error, fatalError=False):  # noqa: N802
            self.lines.append(error)

        def pushWarning(self, text):  # noqa: N802
            self.lines.append(text)

        def pushInfo(self, text):  # noqa: N802
            self.lines.append(text)

    root = lonestar["root"]
    before = _digests(root / "copied")
    feedback = Log()
    summary = tmp_path / "planes.json"
    processing.run(
        "slipmap:planes",
        {"INPUT": str(root / "copied" / "*.laz"), "SUMMARY": str(summary), "TILE_SIZE": 10.0},
        context=QgsProcessingContext(),
        feedback=feedback,
    )
    got = json.loads(summary.read_text())
    assert got["n_selected"] == lonestar["n"]
    text = "\n".join(feedback.lines)
    assert " are the same tile " in text and "t_0_0 (1).laz" in text and "t_0_0.laz" in text
    assert '"Keep duplicate points of overlapping tiles"' in text  # the dialog's words
    assert _digests(root / "copied") == before
    assert not list(tmp_path.rglob(".slipmap-partial-*"))
