"""``--crs`` of the single-input commands (planes, roughness, accuracy): it replaces the file's
CRS (nothing reprojected) and every georeferenced output carries it."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.io.crs import same_crs
from slipmap.core.io.las import PointCloud, read_las, write_las

DATA = Path(__file__).resolve().parents[1] / "data"
UTM12 = "EPSG:32612"  # what lone-star.laz's coordinates are (it declares WGS 84)


pytestmark = pytest.mark.usefixtures("drop_cli_log_handlers")


@pytest.fixture(scope="module")
def mislabelled(tmp_path_factory) -> Path:
    """A 4 m x 4 m crop of lone-star.laz (LAS 1.1, GeoTIFF keys declaring WGS 84 for UTM)."""
    logging.getLogger("slipmap").handlers.clear()
    las = laspy.read(DATA / "lone-star.laz")  # laspy itself: SlipMap's writer would not copy
    xyz = np.column_stack([las.x, las.y, las.z])  # a CRS its reader found implausible
    c = np.median(xyz, axis=0)
    keep = np.all(np.abs(xyz[:, :2] - c[:2]) < 2.0, axis=1)
    path = tmp_path_factory.mktemp("crs") / "crop.laz"
    crop = laspy.LasData(las.header)
    crop.points = las.points[keep]
    crop.write(path)
    return path


def _las_crs(path: Path) -> pyproj.CRS:
    """The CRS the LAS header declares (laspy, without SlipMap's plausibility check)."""
    with laspy.open(path) as reader:
        return reader.header.parse_crs()


def test_planes_outputs_carry_the_given_crs(mislabelled, tmp_path):
    assert same_crs(_las_crs(mislabelled), "EPSG:4326") and read_las(mislabelled).crs is None
    out = tmp_path / "p"
    assert main(["-q", "planes", str(mislabelled), "--out", str(out), "--crs", UTM12]) == 0
    assert same_crs(json.loads((out / "planes.json").read_text())["crs"], UTM12)
    labelled = out / "crop_planes.laz"
    assert same_crs(_las_crs(labelled), UTM12) and same_crs(read_las(labelled).crs, UTM12)
    assert np.array_equal(read_las(labelled).xyz, read_las(mislabelled).xyz)  # not reprojected


def test_roughness_outputs_carry_the_given_crs(mislabelled, tmp_path):
    pytest.importorskip("osgeo.gdal")
    from slipmap.core.io.raster import read_geotiff

    out, pts = tmp_path / "r", tmp_path / "rough.las"
    argv = ["-q", "roughness", str(mislabelled), "--cell", "1", "--out", str(out)]
    argv += ["--map-plane", "xy", "--points-out", str(pts), "--no-figures", "--crs", UTM12]
    assert main(argv) == 0
    _, gt, wkt = read_geotiff(out / "roughness_1.tif")
    assert same_crs(wkt, UTM12)
    assert 515_360 < gt[0] < 515_410  # UTM metres, as in the file
    assert same_crs(json.loads((out / "summary.json").read_text())["crs"], UTM12)
    assert same_crs(_las_crs(pts), UTM12)


def test_accuracy_output_carries_the_given_crs(mislabelled, tmp_path):
    out = tmp_path / "a.laz"
    argv = ["-q", "accuracy", str(mislabelled), "--out", str(out), "--sigma", "0.02"]
    assert main([*argv, "--crs", UTM12]) == 0
    back = read_las(out)
    assert same_crs(_las_crs(out), UTM12) and same_crs(back.crs, UTM12)
    assert np.allclose(back.attributes["SigmaZ"], 0.02)


def test_accuracy_sbet_uses_the_given_crs(tmp_path, capsys):
    """An SBET (geodetic) trajectory is put in the points' frame with --crs, not with the
    wrong CRS the file declares: the sigmas equal those of the correctly labelled file."""
    from slipmap.core.io.trajectory import read_smrmsg

    acc = read_smrmsg(DATA / "smrmsg.smrmsg")
    t0 = float(acc.time_s[0]) + 100.0
    utm = pyproj.CRS.from_epsg(32610)
    tt = t0 + np.arange(0, 20.0, 0.5)  # flying north along x = 500000 at 500 m, 50 m/s
    lon, lat, h = pyproj.Transformer.from_crs(utm, "EPSG:4979", always_xy=True).transform(
        np.full(tt.size, 500000.0), 4200000.0 + 50.0 * (tt - t0), np.full(tt.size, 500.0)
    )
    rec = np.zeros((tt.size, 17))
    rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3] = tt, np.radians(lat), np.radians(lon), h
    sbet = tmp_path / "line.sbet"
    rec.astype("<f8").tofile(sbet)
    rng = np.random.default_rng(1)
    gx, gy = 500000.0 + rng.uniform(-200, 200, 500), 4200000.0 + rng.uniform(100, 900, 500)
    pts = PointCloud(
        xyz=np.column_stack([gx, gy, np.zeros(500)]),
        attributes={
            "GpsTime": t0 + (gy - 4200000.0) / 50.0,
            "ScanAngle": np.degrees(np.arctan2(gx - 500000.0, 500.0)),
        },
    )
    args = ["--pa", "propagated", "--trajectory", str(sbet)]
    args += ["--trajectory-accuracy", str(DATA / "smrmsg.smrmsg"), "--scanner-spec", "leica-als60"]
    sigmas = {}
    for name, crs, extra in (
        ("right", utm, []),
        ("wrong", pyproj.CRS.from_epsg(32611), ["--crs", "EPSG:32610"]),
        ("none", None, ["--crs", "EPSG:32610"]),
    ):
        pts.crs = crs
        write_las(tmp_path / f"{name}.las", pts)
        out = tmp_path / f"{name}_pa.las"
        assert (
            main(
                ["-q", "accuracy", str(tmp_path / f"{name}.las"), "--out", str(out), *args, *extra]
            )
            == 0
        )
        back = read_las(out)
        assert same_crs(back.crs, utm)
        sigmas[name] = np.column_stack([back.attributes[k] for k in ("SigmaX", "SigmaY", "SigmaZ")])
    np.testing.assert_array_equal(sigmas["wrong"], sigmas["right"])
    np.testing.assert_array_equal(sigmas["none"], sigmas["right"])
    # without --crs the file without a CRS cannot place the trajectory
    rc = main(["accuracy", str(tmp_path / "none.las"), "--out", str(tmp_path / "x.las"), *args])
    assert rc == 2 and "no CRS" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["planes", "roughness", "accuracy", "piv"])
def test_bad_crs_is_a_clear_error(command, mislabelled, tmp_path, capsys):
    argv = {
        "planes": ["planes", str(mislabelled), "--out", str(tmp_path / "o")],
        "roughness": ["roughness", str(mislabelled), "--cell", "1", "--out", str(tmp_path / "o")],
        "accuracy": ["accuracy", str(mislabelled), "--out", str(tmp_path / "o.las")],
        "piv": [
            "piv",
            str(mislabelled),
            str(mislabelled),
            "--grid",
            "1",
            "--out",
            str(tmp_path / "o"),
        ],
    }[command]
    try:  # refused at parse time (argparse exits 2) or by the command (returns 2)
        rc = main([*argv, "--crs", "EPSG:99999999"])
    except SystemExit as exc:
        rc = exc.code
    assert rc == 2
    err = capsys.readouterr().err
    assert f"slipmap {command}: error:" in err and "--crs: " in err and "'EPSG:99999999'" in err
    assert "Traceback" not in err and not (tmp_path / "o").exists()
