"""``slipmap displacement`` on tiled inputs (issue #17): one file per epoch, a folder of tiles,
a glob and a local Dask cluster give the same slip and σ; what needs the points in one place
(strips, moving windows, per-point accuracy models, GPS-time units) is refused naming the flag
with nothing written; a missing tile is named."""

from __future__ import annotations

import json

import numpy as np
import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.io.las import PointCloud, read_las, write_las
from slipmap.core.synthetic import make_fault_pair

pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")

ORIGIN = (500000.0, 4200000.0, 10.0)
UTM11 = pyproj.CRS.from_epsg(32611)
TILE = "35"  # the study's tile of every run (the whole-file run too), metres
REL = 1e-9


def _write_tiles(cloud, folder, edge):
    """Tiles of ``edge`` metres cut off the 35 m grid (the job's tiles do not follow them)."""
    folder.mkdir()
    k = np.floor((cloud.xyz[:, :2] - cloud.xyz[:, :2].min(0) + 3.0) / edge).astype(int)
    for key in np.unique(k, axis=0):
        write_las(folder / f"t_{key[0]}_{key[1]}.laz", cloud.subset(np.all(k == key, axis=1)))


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    """A fault pair (18.1 mm right-lateral) as one LAZ per epoch and as 37 / 41 m tiles, and
    its trace as GeoJSON (longitude, latitude)."""
    root = tmp_path_factory.mktemp("tiled_slip")
    pair = make_fault_pair(
        "mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.0181, 0.0), vegetation=False
    )
    for name, scene, edge in (("before", pair.before, 37.0), ("after", pair.after, 41.0)):
        cls = np.asarray(scene.classification, dtype=np.uint8)
        write_las(root / f"{name}.laz", PointCloud(scene.points, {"Classification": cls}, UTM11))
        _write_tiles(read_las(root / f"{name}.laz"), root / f"{name}_tiles", edge)
    tr = pyproj.Transformer.from_crs(UTM11, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(pair.trace_xy[:, 0], pair.trace_xy[:, 1])
    feature = {
        "type": "Feature",
        "properties": {},
        "geometry": {"type": "LineString", "coordinates": [[a, b] for a, b in zip(lon, lat)]},
    }
    (root / "fault.geojson").write_text(
        json.dumps({"type": "FeatureCollection", "features": [feature]})
    )
    return root


def _cli(argv, capsys):
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


def _slip(root, before, after, out, capsys, *extra):
    argv = ["-q", "displacement", str(before), str(after), "--fault", str(root / "fault.geojson")]
    rc, err = _cli([*argv, "--out", str(out), "--tile-size", TILE, *extra], capsys)
    assert rc == 0, err
    return json.loads((out / "displacement.json").read_text())


@pytest.fixture(scope="module")
def whole(epochs, tmp_path_factory):
    """The slip of one file per epoch (read whole, in process)."""
    out = tmp_path_factory.mktemp("whole") / "out"
    cap = _NoCapture()
    return _slip(epochs, epochs / "before.laz", epochs / "after.laz", out, cap)


class _NoCapture:
    """capsys for a module fixture (pytest's is function-scoped)."""

    def readouterr(self):
        class R:
            err = ""

        return R()


def _same(got, ref):
    """Tiled inputs' headline equals the one-file run's estimate on planes extracted tile by
    tile (recorded beside its headline, which is the whole side's: tiles there are a map)."""
    tiles = ref["tile_planes_estimate"]
    for key in ("right_lateral_slip", "right_lateral", "sigma_right_lateral"):
        g, r = got["relative"][key], tiles[key]
        assert abs(g - r) <= REL * abs(r), (key, g, r)
    for side in ("left", "right"):
        assert got[side]["n_planes"] == tiles["n_planes"][side]
    assert got["headline"].startswith("headline: one adjustment per side of the planes "
                                      "extracted tile by tile")  # fmt: skip


def test_folder_and_glob_equal_one_file(epochs, whole, tmp_path, capsys):
    assert whole["relative"]["right_lateral_slip"] == pytest.approx(0.0181, abs=0.003)
    runs = {
        "folder": (epochs / "before_tiles", epochs / "after_tiles"),
        "glob": (epochs / "before_tiles" / "t_*.laz", epochs / "after_tiles" / "*.laz"),
    }
    for name, (before, after) in runs.items():
        out = tmp_path / name
        got = _slip(epochs, before, after, out, capsys)
        _same(got, whole)
        assert got["parameters"]["engine"] == "in-process"
        assert got["parameters"]["acquisition_unit_sources"]["tiled"] is True
        names = {p.name for p in out.iterdir()}
        assert {"displacement.json", "displacement.gpkg", "report.html"} <= names
        assert "residuals.png" not in names  # no per-point residuals from tiles
        # the tiles in the sign convention: each tile's own motion, + = dextral; the right
        # (east) side moved 18.1 mm south, the left side not at all
        tiles = [t for t in got["tiles"] if t["status"] == "ok"]
        assert not [k for t in tiles for k in t if "fault" in k]
        for t in tiles:
            truth = 0.0181 if t["side"] == "right" else 0.0
            assert abs(t["right_lateral"] - truth) < 4 * t["sigma_right_lateral"] + 0.002, t
        assert got["fault"]["right_side"] == "east"


def test_two_dask_workers_equal_one_file(epochs, whole, tmp_path, capsys):
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    before, after = epochs / "before.laz", epochs / "after.laz"
    got = _slip(epochs, before, after, tmp_path / "dask", capsys, "--workers", "2")
    _same(got, whole)
    assert "dask" in got["parameters"]["engine"]


@pytest.mark.parametrize(
    "extra, flag",
    [
        (["--strip-width", "50"], "--strip-width"),
        (["--window-size", "100"], "--window-size"),
        (["--pa", "columns", "--sigma-columns", "X", "Y", "Z"], "--pa"),
        (["--units", "gps-time"], "--units"),
    ],
)
def test_needs_the_points_in_one_place_refused(epochs, tmp_path, capsys, snapshot, extra, flag):
    out = tmp_path / "out"
    out.mkdir()
    snap = snapshot(out, epochs)
    rc, err = _cli(
        ["displacement", str(epochs / "before_tiles"), str(epochs / "after_tiles"), "--fault",
         str(epochs / "fault.geojson"), "--out", str(out), *extra],
        capsys,
    )  # fmt: skip
    assert rc == 2 and len(err) == 1, err
    assert f"error: {flag}: " in err[0], err
    assert "one place" in err[0]
    assert snap.unchanged()


def test_missing_tile_named(epochs, tmp_path, capsys, snapshot):
    out = tmp_path / "out"
    snap = snapshot(epochs)
    tiles = sorted((epochs / "after_tiles").iterdir())
    listed = ",".join([str(tiles[0]), str(epochs / "after_tiles" / "gone.laz")])
    rc, err = _cli(
        ["displacement", str(epochs / "before_tiles"), listed, "--fault",
         str(epochs / "fault.geojson"), "--out", str(out)],
        capsys,
    )  # fmt: skip
    assert rc == 2 and len(err) == 1, err
    assert "error: AFTER: " in err[0] and "gone.laz" in err[0], err
    assert not out.exists() and snap.unchanged()


def test_trace_away_from_the_tiles_named(epochs, tmp_path, capsys, snapshot):
    text = (epochs / "fault.geojson").read_text()
    feature = json.loads(text)
    for c in feature["features"][0]["geometry"]["coordinates"]:
        c[0] += 0.5  # about 40 km east: the trace does not cross the tiles
    far = tmp_path / "far.geojson"
    far.write_text(json.dumps(feature))
    out = tmp_path / "out"
    snap = snapshot(epochs)
    rc, err = _cli(
        ["-q", "displacement", str(epochs / "before_tiles"), str(epochs / "after_tiles"),
         "--fault", str(far), "--out", str(out)],
        capsys,
    )  # fmt: skip
    assert rc == 2 and len(err) == 1 and "error: --fault: " in err[0], err
    assert not out.exists() and snap.unchanged()


def test_progress_and_cancel_pass_through(epochs, tmp_path, snapshot):
    """The job's progress reaches the tiles; a cancel between tiles leaves nothing."""
    from slipmap.app import slip
    from slipmap.core.errors import CancelledError

    opts = slip.SPEC.parse(
        {
            "before": str(epochs / "before_tiles"),
            "after": str(epochs / "after_tiles"),
            "fault": str(epochs / "fault.geojson"),
            "out": str(tmp_path / "out"),
            "tile_size_m": float(TILE),
        }
    )
    seen = []

    def progress(fraction, message):
        seen.append((fraction, message))
        if len(seen) == 3:
            raise CancelledError("cancelled")

    snap = snapshot(epochs)
    with pytest.raises(CancelledError):
        slip.run(opts, {"out": opts["out"]}, progress=progress)
    assert len(seen) == 3 and 0 < seen[-1][0] < 0.95
    assert not (tmp_path / "out").exists() and snap.unchanged()
