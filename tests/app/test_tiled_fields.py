"""Displacement fields on tiled inputs (issue #17): DEM difference, PIV and windowed ICP run
block by block (in process and on two Dask workers) give the one-file run's rasters, vectors
and cells; options that need both epochs in one place are refused naming them."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np
import pyproj
import pytest

from slipmap.app import tiled_fields as tf
from slipmap.cli import main
from slipmap.core.dem import common_grid, grid_elevation
from slipmap.core.icp import windowed_icp
from slipmap.core.io.las import PointCloud, write_las
from slipmap.core.io.tiles import open_collection
from slipmap.core.piv import piv
from slipmap.core.synthetic import LobeField

pytest.importorskip("osgeo.gdal", reason="GDAL (python3-gdal) missing")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "core"))
from test_icp import surface  # noqa: E402

UTM11 = pyproj.CRS.from_epsg(32611)
ORIGIN = np.array([500_000.0, 4_200_000.0, 0.0])
REL = 1e-9
#: a lobe 30 m across moving 0.3 m south and 0.1 m down, on 100 x 80 m of rough ground
LOBE = LobeField(centre_xy=(50.0, 40.0), radius_x_m=15.0, radius_y_m=15.0, max_d_m=(0, -0.3, -0.1))


def _terrain(rng, n, w, h):
    xy = np.c_[rng.uniform(0, w, n), rng.uniform(0, h, n)]
    x, y = xy[:, 0], xy[:, 1]
    z = (
        surface(xy)
        + 0.08 * np.sin(2 * np.pi * x / 1.3) * np.cos(2 * np.pi * y / 1.7)
        + 0.05 * np.sin(2 * np.pi * (x - y) / 2.3)
        + rng.normal(0.0, 0.005, n)
    )
    return np.c_[xy, z]


def _write_tiles(points, folder, edge):
    folder.mkdir()
    k = np.floor((points[:, :2] - points[:, :2].min(0) + 3.0) / edge).astype(int)
    for key in np.unique(k, axis=0):
        m = np.all(k == key, axis=1)
        write_las(folder / f"t_{key[0]}_{key[1]}.laz", PointCloud(points[m], {}, UTM11))


def _write_epochs(root, before, after):
    """``before`` and ``after`` (local metres, moved to ORIGIN) as one LAZ per epoch and as
    23 m / 19 m tiles (the blocks follow neither); returns ``root``."""
    for name, pts, edge in (("before", before, 23.0), ("after", after, 19.0)):
        pts = pts + ORIGIN
        write_las(root / f"{name}.laz", PointCloud(pts, {}, UTM11))
        _write_tiles(pts, root / f"{name}_tiles", edge)
    return root


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    """Independent samplings (20 pts/m²) of the ground before and after the lobe, as one LAZ
    per epoch and as 23 m / 19 m tiles (the blocks follow neither)."""
    root = tmp_path_factory.mktemp("tiled_fields")
    rng = np.random.default_rng(3)
    before = _terrain(rng, 160_000, 100.0, 80.0)
    after = _terrain(rng, 160_000, 100.0, 80.0)
    after = after + LOBE(after[:, :2])
    return _write_epochs(root, before, after)


def _whole(coll):
    from slipmap.core.io.tiles import Region

    return coll.read_region(Region(-1e12, -1e12, 1e12, 1e12)).xyz


@pytest.fixture(scope="module")
def colls(epochs):
    return open_collection(str(epochs / "before_tiles")), open_collection(
        str(epochs / "after_tiles")
    )


def _cli(argv, capsys):
    capsys.readouterr()
    try:
        rc = main(["-q", *argv])
    except SystemExit as e:
        rc = e.code
    return rc, capsys.readouterr().err.strip().splitlines()


def _rows(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def _close(a, b, key="", *, scale=None):
    """Equal NaN patterns and values within REL of ``scale`` (default: the largest |b|)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape, key
    assert np.array_equal(np.isnan(a), np.isnan(b)), key
    ok = np.isfinite(a)
    if scale is None:
        scale = max(1e-12, float(np.max(np.abs(b[ok]))) if ok.any() else 1.0)
    assert np.max(np.abs(a[ok] - b[ok]), initial=0.0) <= REL * scale, key


# --------------------------------------------------------------------------- blocks (API)


def test_piv_blocks_smaller_than_the_dem_equal_the_whole_run(colls):
    """Blocks of 5 x 5 vectors with a 45 m halo on a 100 x 80 m DEM: most blocks see only part
    of it, and their vectors are the whole run's."""
    before, after = colls
    b, a = _whole(before), _whole(after)
    grid = common_grid(b, a, cell_m=0.5)
    kw = dict(windows_px=(16, 8), expected_max_displacement_m=0.35)
    whole = piv(grid_elevation(b, grid=grid), grid_elevation(a, grid=grid), grid=grid, **kw)
    tiled, tgrid = tf.piv_tiled(before, after, grid_m=0.5, tile_size_m=10.0, **kw)
    assert tgrid == grid
    halo_m = tf.piv_halo_px((16, 8), 0.5, 3, None) * 0.5
    assert halo_m < 50.0  # the blocks do not all read the whole DEM
    for key in ("x", "y", "dx", "dy", "dz", "snr"):
        _close(getattr(tiled, key), getattr(whole, key), key)
    assert np.array_equal(tiled.valid, whole.valid)
    # and the field is the lobe's: 0.3 m south at its centre
    centre = np.unravel_index(np.nanargmin(whole.dy), whole.dy.shape)
    assert whole.dy[centre] == pytest.approx(-0.3, abs=0.05)


def test_piv_blocks_with_a_breakline_equal_the_whole_run(colls):
    """A breakline across the lobe: each block gets it, and the blocks' vectors and
    near_break flags are the whole run's."""
    from slipmap.core.breaklines import breaklines

    before, after = colls
    b, a = _whole(before), _whole(after)
    grid = common_grid(b, a, cell_m=0.5)
    x0, y0 = ORIGIN[0] + 3.0, ORIGIN[1] + 3.0  # the data's corner: the terrain starts at 0, 0
    lines = breaklines([np.array([[x0 + 40.0, y0 - 10.0], [x0 + 55.0, y0 + 90.0]])])
    kw = dict(windows_px=(16, 8), expected_max_displacement_m=0.35, breaklines=lines)
    whole = piv(grid_elevation(b, grid=grid), grid_elevation(a, grid=grid), grid=grid, **kw)
    tiled, _ = tf.piv_tiled(before, after, grid_m=0.5, tile_size_m=10.0, **kw)
    assert whole.near_break.sum() > 10
    for key in ("x", "y", "dx", "dy", "dz", "snr"):
        _close(getattr(tiled, key), getattr(whole, key), key)
    assert np.array_equal(tiled.valid, whole.valid)
    assert np.array_equal(tiled.near_break, whole.near_break)


@pytest.mark.parametrize("passes, tile_m", [(0, 15.0), (1, 40.0)])
def test_icp_blocks_equal_the_whole_run(colls, passes, tile_m):
    """Rigid cells (3 cells of halo) and a deformation pass (the field's spline reaches
    further: 15 cells of halo)."""
    before, after = colls
    b, a = _whole(before), _whole(after)
    kw = dict(cell_m=5.0, min_points=50, deform_passes=passes)
    whole = windowed_icp(b, a, **kw)
    tiled = tf.icp_tiled(before, after, tile_size_m=tile_m, **kw)
    assert len(tiled.x) == len(whole.x) > 250
    assert tiled.skipped == whole.skipped
    for key in ("row", "col", "x", "y", "z", "sigma_dx", "sigma_dz"):
        _close(getattr(tiled, key), getattr(whole, key), key)
    for key in ("dx", "dy", "dz", "exx"):  # against the field's largest motion (0.3 m)
        _close(getattr(tiled, key), getattr(whole, key), key, scale=0.3)
    assert tiled.sigma_factor == pytest.approx(whole.sigma_factor, rel=REL)
    assert np.array_equal(tiled.flagged, whole.flagged)


def test_dem_difference_blocks_are_exact(colls):
    before, after = colls
    b, a = _whole(before), _whole(after)
    grid = common_grid(b, a, cell_m=0.5)
    zb, za = grid_elevation(b, grid=grid), grid_elevation(a, grid=grid)

    class Writer:
        def __init__(self, g):
            self.z = np.full((3, *g.shape), np.nan)

        def write(self, block, r0, c0):
            self.z[:, r0 : r0 + block.shape[1], c0 : c0 + block.shape[2]] = block

        def close(self):
            self.closed = True

        def abort(self):
            raise AssertionError("aborted")

    made = {}
    res = tf.dem_difference_tiled(
        before,
        after,
        cell_m=0.5,
        tile_size_m=7.0,
        writer_factory=lambda g: made.setdefault("w", Writer(g)),
        sample_every=1,
    )
    assert made["w"].closed
    _close(made["w"].z[1], zb)
    _close(made["w"].z[2], za)
    dz = za - zb
    ok = np.isfinite(dz)
    assert res.n_valid == ok.sum()
    assert res.mean_m == pytest.approx(dz[ok].mean(), rel=REL)
    assert res.std_m == pytest.approx(dz[ok].std(), rel=1e-7)
    assert res.stats()["median"] == pytest.approx(np.median(dz[ok]), rel=REL)


# --------------------------------------------------------------------------- the jobs (CLI)


def test_dem_diff_of_tiles_is_the_one_file_raster_as_a_cog(epochs, tmp_path, capsys):
    from osgeo import gdal

    from slipmap.core.io.raster import band_names, read_geotiff

    one, tiles = tmp_path / "one", tmp_path / "tiles"
    for out, (b, a) in (
        (one, ("before.laz", "after.laz")),
        (tiles, ("before_tiles", "after_tiles/*.laz")),
    ):
        rc, err = _cli(
            [
                "dem-diff",
                str(epochs / b),
                str(epochs / a),
                "--grid",
                "0.5",
                "--out",
                str(out),
                "--tile-size",
                "12",
            ],  # fmt: skip
            capsys,
        )
        assert rc == 0, err
    r1, gt1, wkt1 = read_geotiff(one / "dem_diff.tif")
    r2, gt2, wkt2 = read_geotiff(tiles / "dem_diff.tif")
    assert gt1 == gt2 and pyproj.CRS(wkt2).equals(pyproj.CRS(wkt1))
    for k in range(3):
        _close(r2[k], r1[k], k)
    assert band_names(tiles / "dem_diff.tif") == ["dz", "z_before", "z_after"]
    info = gdal.Info(str(tiles / "dem_diff.tif"), format="json")
    assert info["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"] == "COG"
    s1 = json.loads((one / "dem_diff.json").read_text())["dz_m"]
    s2 = json.loads((tiles / "dem_diff.json").read_text())["dz_m"]
    assert s2["n"] == s1["n"]
    for k in ("mean", "median", "min", "max"):
        assert s2[k] == pytest.approx(s1[k], rel=REL, abs=1e-15), k
    assert s2["std"] == pytest.approx(s1["std"], rel=1e-7)
    # the COG with its style (range read from the written file) and the summary
    assert sorted(p.name for p in tiles.iterdir()) == [
        "dem_diff.json",
        "dem_diff.qml",
        "dem_diff.tif",
    ]


def test_piv_and_icp_of_tiles_on_two_dask_workers_equal_one_file(epochs, tmp_path, capsys):
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    runs = {
        "piv": (["--grid", "0.5", "--window", "16", "8", "--max-displacement", "0.35"], "piv.csv"),
        "icp": (["--cell", "5", "--min-points", "50"], "icp.csv"),
    }
    for job, (extra, table) in runs.items():
        ref = tmp_path / f"{job}_one"
        args = [job, str(epochs / "before.laz"), str(epochs / "after.laz"), *extra]
        # the cells here (the tiled spline field equals the one-file one: test_tiled_spline)
        cells = ["--field-model", "cells"] if job == "icp" else []
        rc, err = _cli([*args, *cells, "--out", str(ref)], capsys)
        assert rc == 0, err
        out = tmp_path / f"{job}_dask"
        tiled = [job, str(epochs / "before_tiles"), str(epochs / "after_tiles"), *extra, *cells]
        rc, err = _cli([*tiled, "--out", str(out), "--workers", "2", "--tile-size", "20"], capsys)
        assert rc == 0, err
        got, want = _rows(out / table), _rows(ref / table)
        assert set(got) == set(want)
        # a cell that stops at the iteration limit ends where rounding (the points' order in
        # the files) leads it: within 0.1 mm; every converged cell to REL
        keep = want["converged"] > 0 if "converged" in want else np.ones(len(want["x"]), bool)
        for key in want:
            _close(got[key][keep], want[key][keep], f"{job} {key}", scale=0.3)
            _close(got[key][~keep], want[key][~keep], f"{job} {key}", scale=1e5)


@pytest.mark.parametrize(
    "job, extra, flag",
    [
        ("icp", ["--cell", "5", "--prealign"], "--prealign"),
        ("piv", ["--grid", "0.5", "--write-dems"], "--write-dems"),
    ],
)
def test_options_needing_whole_epochs_are_refused_for_tiles(
    epochs, tmp_path, capsys, snapshot, job, extra, flag
):
    out = tmp_path / "out"
    out.mkdir()
    snap = snapshot(out, epochs)
    rc, err = _cli(
        [job, str(epochs / "before_tiles"), str(epochs / "after_tiles"), *extra, "--out", str(out)],
        capsys,
    )
    assert rc == 2
    assert len(err) == 1 and flag in err[0] and "tiled inputs" in err[0], err
    assert snap.unchanged()


def test_blocks_too_large_for_memory_are_refused_naming_the_tile_size(
    epochs, tmp_path, capsys, snapshot
):
    out = tmp_path / "out"
    out.mkdir()
    snap = snapshot(out, epochs)
    rc, err = _cli(
        [
            "dem-diff",
            str(epochs / "before_tiles"),
            str(epochs / "after_tiles"),
            "--grid",
            "0.0005",
            "--tile-size",
            "1000",
            "--out",
            str(out),
        ],  # fmt: skip
        capsys,
    )
    assert rc == 2
    assert len(err) == 1 and "--tile-size" in err[0] and "DEM block" in err[0], err
    assert snap.unchanged()
