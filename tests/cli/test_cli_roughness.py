"""``slipmap roughness``: outputs checked against the core functions on the same input."""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest

from slipmap.cli import main
from slipmap.core import roughness as rg
from slipmap.core.io.las import PointCloud, read_las, write_las

DATA = Path(__file__).resolve().parents[1] / "data"


def _drop_cli_log_handlers() -> None:
    """main() points the "slipmap" logger at the stderr of its test; drop that stale handler so
    library logging outside main() (e.g. write_las in fixtures) never writes to a closed stream."""
    logging.getLogger("slipmap").handlers.clear()


@pytest.fixture(scope="module", autouse=True)
def _module_logging():
    _drop_cli_log_handlers()
    yield
    _drop_cli_log_handlers()


@pytest.fixture(autouse=True)
def _test_logging():
    _drop_cli_log_handlers()
    yield
    _drop_cli_log_handlers()


@pytest.fixture(scope="module")
def crop_las(tmp_path_factory) -> Path:
    """A 6 m x 6 m crop of lone-star.laz (a rough natural surface, ~15 000 points)."""
    cloud = read_las(DATA / "lone-star.laz")
    c = np.median(cloud.xyz, axis=0)
    keep = np.all(np.abs(cloud.xyz[:, :2] - c[:2]) < 3.0, axis=1)
    path = tmp_path_factory.mktemp("crop") / "crop.laz"
    write_las(path, cloud.subset(keep))
    return path


@pytest.fixture(scope="module")
def plane_las(tmp_path_factory) -> Path:
    """A rough tilted plane (no CRS) at survey offsets."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(0.0, 4.0, (20_000, 2))
    z = 0.4 * xy[:, 0] + 0.1 * xy[:, 1] + rng.normal(0.0, 0.01, xy.shape[0]) + 0.25
    xyz = np.column_stack([xy, z]) + [500_000.0, 4_000_000.0, 100.0]
    path = tmp_path_factory.mktemp("plane") / "plane.las"
    write_las(path, PointCloud(xyz=xyz))
    return path


def _read_csv(path: Path) -> dict:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]} if rows else {}


def _core(path: Path, cell: float, **kw):
    xyz = read_las(path).xyz
    frame = rg.principal_frame(xyz)
    axis = rg.resolve_ols_axis(frame, "auto")
    return xyz, frame, rg.grid_roughness(xyz, cell_size_m=cell, ols_axis=axis, **kw)


def test_outputs_match_the_core_functions(crop_las, tmp_path):
    out = tmp_path / "out"
    pts_out = tmp_path / "points.laz"
    argv = ["-q", "roughness", str(crop_las), "--cell", "1", "--cell", "0.5", "--out", str(out)]
    assert main([*argv, "--points-out", str(pts_out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["options"]["cell_sizes_m"] == [1.0, 0.5]
    for rec, cell in zip(summary["cell_sizes"], (1.0, 0.5)):
        xyz, frame, grid = _core(crop_las, cell)
        assert summary["options"]["ols_axis"] == grid.ols_axis
        # CSV: one row per evaluated cell, values of the core function
        table = _read_csv(out / rec["files"]["csv"])
        assert list(table) == [
            "ix", "iy", "iz", "x", "y", "z", "n", "theta_odr", "theta_ols", "e_ols", "degenerate"
        ]  # fmt: skip
        np.testing.assert_array_equal(table["ix"], grid.index[:, 0])
        np.testing.assert_array_equal(table["iz"], grid.index[:, 2])
        np.testing.assert_allclose(table["x"], grid.centre_m[:, 0], atol=1e-6)
        np.testing.assert_allclose(table["z"], grid.centre_m[:, 2], atol=1e-6)
        np.testing.assert_array_equal(table["n"], grid.n_points)
        for name in ("theta_odr", "theta_ols", "e_ols"):
            np.testing.assert_allclose(table[name], getattr(grid, name), rtol=1e-8)
        # summary.json: Table 1 of the core summary
        expected = rg.summarize_roughness(grid).to_dict()
        for key in ("n_cells", "n_cells_skipped", "n_points_skipped", "n_degenerate"):
            assert rec[key] == expected[key]
        assert rec["mean_points_per_cell"] == pytest.approx(expected["mean_points_per_cell"])
        for method in ("odr", "ols", "e_ols"):
            for stat, value in expected[method].items():
                assert rec[method][stat] == pytest.approx(value, rel=1e-12), (method, stat)
        _, frac = rg.roughness_histogram(rg.normalise_range(grid.theta_odr))
        assert rec["fraction_first_histogram_bin"]["odr"] == pytest.approx(frac[0])
    # per-point Roughness of the first --cell
    _, _, grid1 = _core(crop_las, 1.0)
    cloud = read_las(pts_out)
    expected = rg.roughness_per_point(cloud.xyz, grid1)
    np.testing.assert_allclose(cloud.attributes["Roughness"], expected, rtol=1e-12)
    assert np.isfinite(expected).mean() > 0.9
    assert summary["points_out_cell_m"] == 1.0


def test_geotiff_semivariogram_and_figures(plane_las, tmp_path):
    gdal = pytest.importorskip("osgeo.gdal")
    from slipmap.core.io.raster import band_names, read_geotiff

    out = tmp_path / "out"
    args = ["-q", "roughness", str(plane_las), "--cell", "0.5", "--out", str(out)]
    assert main([*args, "--map-plane", "xy", "--cutoff", "0.1"]) == 0
    xyz, frame, grid = _core(plane_las, 0.5)
    plane = rg.choose_map_plane(frame, "xy")
    raster = rg.rasterize_cells(grid.centre_m, grid.theta_odr, plane, pixel_size_m=0.5)
    arr, gt, wkt = read_geotiff(out / "roughness_0.5.tif")
    assert arr.shape[0] == 7 and band_names(out / "roughness_0.5.tif")[0] == "theta_odr_m"
    np.testing.assert_allclose(arr[0], raster.values[0].astype(np.float32), rtol=1e-6)
    assert gt == (raster.origin_uv_m[0], 0.5, 0.0, raster.origin_uv_m[1], 0.0, -0.5)
    assert set(np.unique(arr[5][np.isfinite(arr[5])])) <= {0.0, 1.0}
    assert wkt == ""  # the input has no CRS
    del gdal
    sv = rg.semivariogram_raster(raster.values[0], pixel_size_m=0.5)
    table = _read_csv(out / "semivariogram_0.5.csv")
    ok = np.isfinite(sv.gamma)
    np.testing.assert_allclose(table["gamma_odr"][ok], sv.gamma[ok], rtol=1e-6)
    np.testing.assert_array_equal(table["n_pairs_odr"], sv.n_pairs)
    if pytest.importorskip("matplotlib"):
        for name in ("roughness_0.5_binary.png", "roughness_0.5_hist.png", "semivariograms.png"):
            assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_signed_and_ols_axis_options(plane_las, tmp_path):
    out = tmp_path / "out"
    argv = ["-q", "roughness", str(plane_las), "--cell", "1", "--out", str(out), "--no-figures"]
    assert main([*argv, "--signed", "--ols-axis", "x"]) == 0
    xyz = read_las(plane_las).xyz
    grid = rg.grid_roughness(xyz, cell_size_m=1.0, ols_axis="x", signed=True)
    table = _read_csv(out / "roughness_1.csv")
    np.testing.assert_allclose(table["theta_odr"], grid.theta_odr, rtol=1e-8)
    np.testing.assert_allclose(table["theta_ols"], grid.theta_ols, rtol=1e-8)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["options"]["signed"] is True and summary["options"]["ols_axis"] == "x"
    assert not list(out.glob("*.png"))
    # signed roughness = sigma of the noise orthogonal to the plane: 0.01 m vertical * cos(tilt)
    sigma_orth = 0.01 / math.sqrt(1 + 0.4**2 + 0.1**2)
    assert summary["cell_sizes"][0]["odr"]["mean"] == pytest.approx(sigma_orth, rel=0.05)


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_bad_input_exits_2_with_one_line(plane_las, tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main(["roughness", str(plane_las), "--cell", "100", "--out", out]) == 2
    assert "larger than the extent" in _one_error_line(capsys)
    assert main(["roughness", str(tmp_path / "missing.las"), "--cell", "1", "--out", out]) == 2
    assert "missing.las" in _one_error_line(capsys)
    # refused at parse time (argparse: exit 2, the flag named)
    for bad, words in (
        (["--cell", "1", "--cutoff", "2"], ("--cutoff", "must be <= 1")),
        (["--cell", "0"], ("--cell", "must be > 0")),
    ):
        with pytest.raises(SystemExit) as exc:
            main(["roughness", str(plane_las), "--out", out, *bad])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert all(w in err for w in words), err
    assert not (tmp_path / "out" / "summary.json").exists()


def test_empty_input_exits_2(tmp_path, capsys):
    empty = tmp_path / "empty.las"
    write_las(empty, PointCloud(xyz=np.zeros((0, 3))))
    assert main(["roughness", str(empty), "--cell", "1", "--out", str(tmp_path / "o")]) == 2
    assert "no points" in _one_error_line(capsys)


def test_too_few_points_are_counted_in_the_summary(plane_las, tmp_path):
    out = tmp_path / "out"
    argv = ["-q", "roughness", str(plane_las), "--cell", "0.125", "--out", str(out)]
    assert main([*argv, "--min-points", "20", "--no-figures"]) == 0
    rec = json.loads((out / "summary.json").read_text())["cell_sizes"][0]
    assert rec["n_cells_skipped"] > 0 and rec["n_points_skipped"] > 0
    assert rec["n_cells"] * rec["mean_points_per_cell"] + rec["n_points_skipped"] == (
        pytest.approx(20_000)
    )
    assert math.isfinite(rec["odr"]["mean"])
