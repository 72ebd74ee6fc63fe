"""``slipmap synth-lobe``, ``dem-diff``, ``strain``, ``piv``, ``icp``: outputs against the core."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from slipmap.cli import main
from slipmap.core.io.las import read_las
from slipmap.core.io.table import read_csv_columns, write_csv_columns

DATA = Path(__file__).resolve().parents[1] / "data"
LONE = DATA / "lone-star.laz"


def _need_gdal():
    """These commands write GeoTIFF / GeoPackage outputs (GDAL; absent in the numpy-2 venv)."""
    pytest.importorskip("osgeo.gdal", reason="GDAL's Python bindings (python3-gdal) missing")


@pytest.fixture(scope="module", autouse=True)
def _module_logging():
    logging.getLogger("slipmap").handlers.clear()
    yield
    logging.getLogger("slipmap").handlers.clear()


@pytest.fixture(scope="module")
def lobe(tmp_path_factory):
    """lone-star with the study's lobe (-1 m north, -0.4 m up) injected, via the CLI."""
    out = tmp_path_factory.mktemp("lobe")
    assert main(["-q", "synth-lobe", str(LONE), "--out", str(out), "--seed", "3"]) == 0
    return out


def test_synth_lobe_outputs_match_the_field(lobe):
    from slipmap.core.synthetic import LobeField

    src = read_las(LONE)
    b, a = read_las(lobe / "before.laz"), read_las(lobe / "after.laz")
    assert len(b) + len(a) == len(src) and abs(len(b) - len(a)) <= 1
    info = json.loads((lobe / "lobe.json").read_text())
    field = LobeField(
        centre_xy=tuple(info["centre_xy"]),
        radius_x_m=info["radius_x_m"],
        radius_y_m=info["radius_y_m"],
        azimuth_deg=info["azimuth_deg"],
        max_d_m=tuple(info["max_d_m"]),
    )
    # before points are original points; each after point is an original point + field(xy)
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(src.xyz).query(b.xyz)
    assert dist.max() < 1e-6
    moved_back = a.xyz - field(a.xyz[:, :2])  # field at the displaced xy ~ at the original
    dist, idx = cKDTree(src.xyz).query(moved_back)
    assert np.median(dist) < 1e-3  # LAS quantisation (0.25 mm) + field gradient x |d|
    truth = read_csv_columns(lobe / "truth.csv", required=("x", "y", "dx", "dy", "dz"))
    d = field(np.column_stack([truth["x"], truth["y"]]))
    np.testing.assert_allclose(np.column_stack([truth["dx"], truth["dy"], truth["dz"]]), d)
    assert truth["dy"].min() == pytest.approx(-1.0, abs=0.02)


def test_dem_diff_equals_core(lobe, tmp_path):
    _need_gdal()
    from slipmap.core.dem import dem_difference
    from slipmap.core.io.raster import read_geotiff

    rc = main(
        [
            "-q",
            "dem-diff",
            str(lobe / "before.laz"),
            str(lobe / "after.laz"),
            "--grid",
            "0.5",
            "--out",
            str(tmp_path),
            "--crs",
            "EPSG:32612",
        ]
    )
    assert rc == 0
    arr, gt, wkt = read_geotiff(tmp_path / "dem_diff.tif")
    assert "32612" in wkt or "UTM zone 12N" in wkt  # --crs replaces the file's wrong CRS
    core = dem_difference(
        read_las(lobe / "before.laz").xyz, read_las(lobe / "after.laz").xyz, cell_m=0.5
    )
    np.testing.assert_array_equal(arr[0], core.dz)
    assert gt == (core.grid.x_min, 0.5, 0.0, core.grid.y_max, 0.0, -0.5)
    summary = json.loads((tmp_path / "dem_diff.json").read_text())
    assert summary["dz_m"]["n"] == core.n_valid
    assert (tmp_path / "dem_diff.png").stat().st_size > 1000


def test_strain_of_a_uniform_shear_csv_is_analytic(tmp_path):
    _need_gdal()
    gamma = 2e-3
    x, y = np.meshgrid(500000.0 + np.arange(12) * 2.0, 4200000.0 + np.arange(9) * 2.0)
    dx = gamma * (y - 4200000.0)
    keep = np.ones(x.shape, bool)
    keep[4, 5] = keep[0, 0] = False  # gaps
    write_csv_columns(
        tmp_path / "field.csv",
        {"x": x[keep], "y": y[keep], "dx": dx[keep], "dy": np.zeros(keep.sum())},
    )
    out = tmp_path / "s"
    assert (
        main(
            ["-q", "strain", str(tmp_path / "field.csv"), "--out", str(out), "--crs", "EPSG:32612"]
        )
        == 0
    )
    from slipmap.core.io.raster import band_names, read_geotiff

    arr, gt, wkt = read_geotiff(out / "strain.tif")
    names = band_names(out / "strain.tif")
    bands = dict(zip(names, arr))
    ok = np.isfinite(bands["exy"])
    assert ok.sum() == keep.sum()
    np.testing.assert_allclose(bands["exy"][ok], gamma / 2, rtol=1e-9)
    np.testing.assert_allclose(bands["rotation_rad"][ok], -gamma / 2, rtol=1e-9)
    np.testing.assert_allclose(bands["max_shear"][ok], gamma / 2, rtol=1e-9)
    np.testing.assert_allclose(bands["dilatation"][ok], 0, atol=1e-12)
    assert gt[1] == 2.0 and gt[5] == -2.0 and "32612" in wkt


def test_strain_from_two_band_geotiff_and_bad_inputs(tmp_path, capsys):
    _need_gdal()
    from slipmap.core.io.raster import write_geotiff

    yy, xx = np.mgrid[0:6, 0:7].astype(float)
    # north-up: row 0 is north, so y = -row * 1 m; u = 1e-3 x -> exx = 1e-3
    write_geotiff(
        tmp_path / "d.tif", np.stack([1e-3 * xx, 0 * xx]), origin_xy=(0.0, 6.0), pixel_size_m=1.0
    )
    assert main(["-q", "strain", str(tmp_path / "d.tif"), "--out", str(tmp_path / "o")]) == 0
    from slipmap.core.io.raster import band_names, read_geotiff

    arr, _, _ = read_geotiff(tmp_path / "o" / "strain.tif")
    bands = dict(zip(band_names(tmp_path / "o" / "strain.tif"), arr))
    np.testing.assert_allclose(bands["exx"], 1e-3, rtol=1e-9)
    write_geotiff(tmp_path / "one.tif", xx, origin_xy=(0.0, 6.0), pixel_size_m=1.0)
    assert main(["strain", str(tmp_path / "one.tif"), "--out", str(tmp_path / "p")]) == 2
    assert "--dy" in capsys.readouterr().err
    (tmp_path / "f.csv").write_text("x,y,dx\n1,2,3\n")
    assert main(["strain", str(tmp_path / "f.csv"), "--out", str(tmp_path / "q")]) == 2
    assert "dy" in capsys.readouterr().err
    bad = ["strain", str(tmp_path / "d.tif"), "--out", str(tmp_path / "r"), "--crs", "EPSG:1"]
    with pytest.raises(SystemExit) as exited:  # refused at parse time
        main(bad)
    assert exited.value.code == 2
    assert "--crs" in capsys.readouterr().err and not (tmp_path / "r").exists()


def _rough(n, seed, side=20.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, side, (n, 2))
    x, y = xy[:, 0], xy[:, 1]
    z = (
        0.5 * np.sin(x / 2.7) * np.cos(y / 3.1)
        + 0.2 * np.sin((x + y) / 1.3)
        + 0.06 * np.sin(x / 0.21 + 1.3 * np.sin(y / 0.37))  # metre-scale texture, as rough
        + 0.05 * np.cos(y / 0.17 + 0.8 * np.sin(x / 0.29))  # ground has (PIV needs it)
    )
    return np.column_stack([xy + [512000.0, 4780000.0], z + 1500.0])


@pytest.fixture(scope="module")
def shifted_pair(tmp_path_factory):
    """A rough 20 m patch sampled twice (no shared points), the second shifted."""
    import pyproj

    from slipmap.core.io.las import PointCloud, write_las

    d = tmp_path_factory.mktemp("pair")
    crs = pyproj.CRS.from_epsg(32612)
    shift = np.array([0.12, -0.2, 0.05])
    b, a = _rough(40000, 1), _rough(40000, 2) + shift
    write_las(d / "b.las", PointCloud(xyz=b, crs=crs))
    write_las(d / "a.las", PointCloud(xyz=a, crs=crs))
    return d, shift


def test_icp_cli_equals_core_and_writes_layers(shifted_pair, tmp_path):
    _need_gdal()
    from slipmap.core.icp import windowed_icp
    from slipmap.core.io.raster import read_geotiff
    from slipmap.core.io.vector import read_gpkg_layer

    d, shift = shifted_pair
    ctrl = tmp_path / "ctrl.csv"
    write_csv_columns(
        ctrl,
        {"x": [512005.0], "y": [4780005.0], "dx": [shift[0]], "dy": [shift[1]], "dz": [shift[2]]},
    )
    out = tmp_path / "icp"
    rc = main(
        [
            "-q",
            "icp",
            str(d / "b.las"),
            str(d / "a.las"),
            "--cell",
            "5",
            "--out",
            str(out),
            "--no-progress",
            "--control",
            str(ctrl),
        ]
    )
    assert rc == 0
    from slipmap.app.icp import DEFAULT_MAX_POINTS_PER_CELL

    # the job's defaults: the spline field, breaklines detected, 2000 points per cell
    core = windowed_icp(
        read_las(d / "b.las").xyz, read_las(d / "a.las").xyz, cell_m=5.0, coarse_to_fine=1,
        field_model="spline", detect_breaklines=True, cell_choice=True,
        max_points_per_cell=DEFAULT_MAX_POINTS_PER_CELL,
    )  # fmt: skip
    cols = read_csv_columns(
        out / "icp.csv",
        required=("x", "y", "z", "dx", "dy", "dz", "sigma_dx", "sigma_dy", "sigma_dz", "rmse", "n"),
    )
    np.testing.assert_array_equal(cols["dx"], core.dx)
    np.testing.assert_array_equal(cols["sigma_dz"], core.sigma_dz)
    inner = cols["n"] >= 500
    assert np.abs(cols["dx"][inner] - shift[0]).max() < 0.01
    geoms, fields = read_gpkg_layer(out / "icp.gpkg", "cells")
    assert len(geoms) == len(core) and {"dx", "sigma_dy", "magnitude", "azimuth_deg"} <= set(fields)
    arr, gt, wkt = read_geotiff(out / "icp.tif")
    assert arr.shape[0] == 8 and gt[1] == 5.0 and "32612" in wkt or "UTM zone 12N" in wkt
    summary = json.loads((out / "icp.json").read_text())
    assert summary["control"]["n_compared"] == 1
    assert summary["control"]["rmse_horizontal_m"] < 0.01
    assert summary["sigma_factor"]["applied"] == core.sigma_factor >= 1.0
    formal = tmp_path / "formal"
    args = ["-q", "icp", str(d / "b.las"), str(d / "a.las"), "--cell", "5", "--no-progress"]
    assert main([*args, "--out", str(formal), "--formal-sigma"]) == 0
    cols_formal = read_csv_columns(formal / "icp.csv", required=("sigma_dz", "dx"))
    # the formal sigmas: the independent-residuals model, under which every point weighs as
    # one observation (the spline's data weights come from the blocks model), as the core
    # reports it with that model; smaller than the default's honest sigmas
    core_formal = windowed_icp(
        read_las(d / "b.las").xyz, read_las(d / "a.las").xyz, cell_m=5.0, coarse_to_fine=1,
        field_model="spline", detect_breaklines=True, cell_choice=True, sigma_model="independent",
        sigma_scaling="formal", max_points_per_cell=DEFAULT_MAX_POINTS_PER_CELL,
    )  # fmt: skip
    np.testing.assert_array_equal(cols_formal["dx"], core_formal.dx)
    np.testing.assert_allclose(cols_formal["sigma_dz"], core_formal.sigma_dz)
    assert np.median(cols_formal["sigma_dz"] / cols["sigma_dz"]) < 1.0
    assert json.loads((formal / "icp.json").read_text())["sigma_factor"]["applied"] == 1.0


def test_piv_cli_equals_core(shifted_pair, tmp_path):
    _need_gdal()
    from slipmap.core.dem import common_grid, grid_elevation
    from slipmap.core.io.raster import read_geotiff
    from slipmap.core.piv import piv

    d, shift = shifted_pair
    out = tmp_path / "piv"
    rc = main(
        [
            "-q",
            "piv",
            str(d / "b.las"),
            str(d / "a.las"),
            "--grid",
            "0.2",
            "--window",
            "32",
            "16",
            "--out",
            str(out),
            "--no-progress",
            "--max-displacement",
            "0.5",
        ]
    )
    assert rc == 0
    b, a = read_las(d / "b.las").xyz, read_las(d / "a.las").xyz
    grid = common_grid(b, a, cell_m=0.2)
    core = piv(
        grid_elevation(b, grid=grid),
        grid_elevation(a, grid=grid),
        grid=grid,
        windows_px=(32, 16),
        expected_max_displacement_m=0.5,
    )
    cols = read_csv_columns(out / "piv.csv", required=("x", "y", "dx", "dy", "dz", "snr", "valid"))
    np.testing.assert_array_equal(cols["dx"], core.dx.ravel())
    np.testing.assert_array_equal(cols["valid"], core.valid.ravel().astype(float))
    ok = cols["valid"] > 0
    assert ok.mean() > 0.5
    assert np.median(np.abs(cols["dx"][ok] - shift[0])) < 0.02
    assert np.median(np.abs(cols["dy"][ok] - shift[1])) < 0.02
    dz, gt, _ = read_geotiff(out / "piv_dz.tif")
    np.testing.assert_array_equal(dz, core.dz)
    assert gt[0] == core.origin_xy[0] and gt[1] == core.spacing_m
    assert (out / "piv.png").stat().st_size > 1000


def test_piv_cli_breaklines_equal_core(shifted_pair, tmp_path):
    """``--breaklines FILE`` (a GeoJSON line in the clouds' CRS) reaches the core: the same
    vectors and near_break flags as :func:`piv` given the line."""
    _need_gdal()
    from slipmap.core.breaklines import breaklines
    from slipmap.core.dem import common_grid, grid_elevation
    from slipmap.core.piv import piv

    d, _ = shifted_pair
    b, a = read_las(d / "b.las").xyz, read_las(d / "a.las").xyz
    mid = 0.5 * (b[:, :2].min(axis=0) + b[:, :2].max(axis=0))
    line = [[mid[0] - 1.0, mid[1] - 15.0], [mid[0] + 2.0, mid[1] + 15.0]]
    path = tmp_path / "scarp.geojson"
    path.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "crs": {"type": "name", "properties": {"name": "EPSG:32612"}},
                "features": [
                    {
                        "type": "Feature",
                        "properties": {},
                        "geometry": {"type": "LineString", "coordinates": line},
                    }
                ],
            }
        )
    )
    out = tmp_path / "piv"
    argv = ["-q", "piv", str(d / "b.las"), str(d / "a.las"), "--grid", "0.2", "--window", "32"]
    argv += ["16", "--max-displacement", "0.5", "--breaklines", str(path), "--out", str(out)]
    assert main(argv + ["--no-progress"]) == 0
    grid = common_grid(b, a, cell_m=0.2)
    core = piv(
        grid_elevation(b, grid=grid),
        grid_elevation(a, grid=grid),
        grid=grid,
        windows_px=(32, 16),
        expected_max_displacement_m=0.5,
        breaklines=breaklines([np.array(line)]),
    )
    cols = read_csv_columns(out / "piv.csv", required=("dx", "near_break"))
    np.testing.assert_array_equal(cols["dx"], core.dx.ravel())
    np.testing.assert_array_equal(cols["near_break"], core.near_break.ravel().astype(float))
    assert 0 < core.near_break.sum() < core.near_break.size
    summary = json.loads((out / "piv.json").read_text())
    assert summary["n_near_break"] == int(core.near_break.sum())


def test_field_commands_refuse_bad_input(shifted_pair, tmp_path, capsys):
    _need_gdal()
    d, _ = shifted_pair
    with pytest.raises(SystemExit):  # argparse refuses --grid 0
        main(["piv", str(d / "b.las"), str(d / "a.las"), "--grid", "0", "--out", str(tmp_path)])
    assert "--grid: must be > 0" in capsys.readouterr().err
    rc = main(
        [
            "piv",
            str(d / "b.las"),
            str(d / "a.las"),
            "--grid",
            "0.5",
            "--window",
            "128",
            "--out",
            str(tmp_path / "p"),
        ]
    )
    assert rc == 2 and "window" in capsys.readouterr().err
    far = tmp_path / "far.las"
    from slipmap.core.io.las import PointCloud, write_las

    write_las(far, PointCloud(xyz=_rough(1000, 3) + [1000.0, 0.0, 0.0]))
    for cmd in ("piv", "icp", "dem-diff"):
        opt = ["--cell", "5"] if cmd == "icp" else ["--grid", "0.5"]
        rc = main([cmd, str(d / "b.las"), str(far), *opt, "--out", str(tmp_path / cmd)])
        assert rc == 2 and "overlap" in capsys.readouterr().err, cmd


def test_icp_prealign_reports_the_epoch_offset_at_the_centre(shifted_pair, tmp_path):
    _need_gdal()
    d, shift = shifted_pair
    out = tmp_path / "pre"
    rc = main(
        [
            "-q",
            "icp",
            str(d / "b.las"),
            str(d / "a.las"),
            "--cell",
            "5",
            "--out",
            str(out),
            "--no-progress",
            "--prealign",
            "--coarse-to-fine",
            "0",
        ]
    )
    assert rc == 0
    pre = json.loads((out / "icp.json").read_text())["prealignment"]
    np.testing.assert_allclose(pre["offset_at_centre_m"], shift, atol=0.01)
    cols = read_csv_columns(out / "icp.csv", required=("dx", "dy", "dz", "n"))
    inner = cols["n"] >= 500
    assert np.abs(cols["dx"][inner]).max() < 0.01  # relative to the stable frame
