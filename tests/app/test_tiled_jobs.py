"""The jobs on tiled inputs through their faces: a folder, a glob or comma-separated files;
``--workers`` / ``--scheduler``; errors naming the option or the tile; outputs untouched."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slipmap.cli import main
from slipmap.core.io.las import PointCloud, read_las, write_las
from slipmap.core.synthetic import make_scene


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    """A 60 m scene as one file and as 4 tiles of 30 m."""
    root = tmp_path_factory.mktemp("tiled_jobs")
    scene = make_scene("mls", seed=5, n_buildings=2, extent_m=60.0, origin=(500000, 4200000, 10))
    whole = root / "whole.laz"
    write_las(whole, PointCloud(xyz=scene.points, attributes={}))
    cloud = read_las(whole)
    folder = root / "tiles"
    folder.mkdir()
    k = np.floor((cloud.xyz[:, :2] - [500000, 4200000]) / 30.0).astype(int)
    for key in np.unique(k, axis=0):
        write_las(folder / f"t{key[0]}{key[1]}.laz", cloud.subset(np.all(k == key, axis=1)))
    return whole, folder


def _cli(argv, capsys):
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


def _planes(path):
    return json.loads((path / "planes.json").read_text())


def test_planes_folder_glob_and_list_agree(tiles, tmp_path, capsys):
    whole, folder = tiles
    files = ",".join(str(p) for p in sorted(folder.iterdir()))
    outs = []
    for i, spec in enumerate((str(folder), str(folder / "t*.laz"), files)):
        out = tmp_path / f"o{i}"
        rc, err = _cli(["planes", spec, "--out", str(out), "--tile-size", "25"], capsys)
        assert rc == 0, err
        outs.append(_planes(out))
        names = sorted(p.name for p in out.iterdir() if p.name != "planes.json")
        assert names and all(n.startswith("planes_") and n.endswith(".laz") for n in names)
        # the labelled tiles: every input point once, PlaneId counts = the summary's
        lab = np.concatenate([read_las(out / n).attributes["PlaneId"] for n in names])
        assert lab.size == outs[-1]["n_points"]
        counts = np.bincount(lab[lab >= 0], minlength=len(outs[-1]["planes"]))
        assert counts.tolist() == [p["n_points"] for p in outs[-1]["planes"]]
    for o in outs[1:]:
        assert o["planes"] == outs[0]["planes"]
    assert outs[0]["tiles"]["files"] == 4 and outs[0]["n_points"] == len(read_las(whole))
    # the same job on the one file, tiled because Dask is asked for: the same planes
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    out = tmp_path / "dask"
    rc, err = _cli(
        ["planes", str(whole), "--out", str(out), "--tile-size", "25", "--workers", "2"], capsys
    )
    assert rc == 0, err
    got = _planes(out)
    assert "dask" in got["tiles"]["engine"]
    assert len(got["planes"]) == len(outs[0]["planes"])
    for a, b in zip(got["planes"], outs[0]["planes"]):
        assert a["n_points"] == b["n_points"]
        assert np.allclose(a["centroid"], b["centroid"], rtol=0, atol=1e-9)


def test_bad_scale_options_exit_2_and_write_nothing(tiles, tmp_path, capsys, snapshot):
    whole, folder = tiles
    out = tmp_path / "out"
    out.mkdir()
    snap = snapshot(out, folder)
    rc, err = _cli(
        ["planes", str(folder), "--out", str(out), "--workers", "2", "--scheduler", "tcp://a:1"],
        capsys,
    )
    assert rc == 2 and len(err) == 1 and "--workers" in err[0] and "--scheduler" in err[0]
    rc, err = _cli(["planes", str(folder), "--out", str(out), "--workers", "0"], capsys)
    assert rc == 2 and "--workers" in err[-1]  # argparse: usage, then the line
    missing = f"{sorted(folder.iterdir())[0]},{folder / 'gone.laz'}"
    rc, err = _cli(["planes", missing, "--out", str(out)], capsys)
    assert rc == 2 and len(err) == 1 and "gone.laz" in err[0] and "INPUT" in err[0].upper()
    assert snap.unchanged()


def test_output_inside_the_tiles_folder_refused(tiles, tmp_path, capsys, snapshot):
    """Issue #31, bad case 5: ``planes TILES --out TILES`` wrote its outputs among the tiles
    (read back as tiles by the next run); an output folder that is, or is inside, the folder
    of the tiles is refused before any work, naming --out and INPUT, nothing written."""
    _, folder = tiles
    copy = tmp_path / "copy"
    copy.mkdir()
    for p in folder.iterdir():
        (copy / p.name).write_bytes(p.read_bytes())
    snap = snapshot(copy)
    for spec in (str(copy), str(copy / "*.laz"), ",".join(str(p) for p in copy.iterdir())):
        for out in (copy, copy / "out", copy / "a" / "b"):
            rc, err = _cli(["planes", spec, "--out", str(out)], capsys)
            assert rc == 2, err
            assert "--out" in err[-1] and "INPUT" in err[-1] and "folder of the tiles" in err[-1]
            assert snap.unchanged()  # no output, no staging folder, tiles byte-identical
            assert sorted(p.name for p in copy.iterdir()) == sorted(
                p.name for p in folder.iterdir()
            )


def _csv(path):
    return np.genfromtxt(path, delimiter=",", names=True)


def test_roughness_file_tiles_and_dask_agree(tiles, tmp_path, capsys):
    whole, folder = tiles
    runs = [[str(whole)], [str(folder)], [str(folder / "t*.laz"), "--tile-size", "17"]]
    try:
        import distributed  # noqa: F401
    except ImportError:  # the in-process runs still compare
        pass
    else:
        runs.append([str(whole), "--workers", "2"])
    tables = []
    for i, spec in enumerate(runs):
        out = tmp_path / f"r{i}"
        rc, err = _cli(["roughness", *spec, "--cell", "0.5", "--out", str(out)], capsys)
        assert rc == 0, err
        tables.append(_csv(out / "roughness_0.5.csv"))
    ref = tables[0]
    for got in tables[1:]:  # the tiled path: the whole cloud's cells, to rounding
        for name in ("ix", "iy", "iz", "n", "degenerate"):
            assert np.array_equal(got[name], ref[name])
        ok = ref["degenerate"] == 0
        for name in ("theta_odr", "theta_ols"):
            assert np.allclose(got[name][ok], ref[name][ok], rtol=1e-9, atol=0)


def test_roughness_points_out_refused_for_tiles(tiles, tmp_path, capsys, snapshot):
    _, folder = tiles
    out = tmp_path / "out"
    out.mkdir()
    snap = snapshot(out)
    rc, err = _cli(
        ["roughness", str(folder), "--cell", "0.5", "--out", str(out), "--points-out",
         str(out / "p.laz")],
        capsys,
    )  # fmt: skip
    assert rc == 2 and "--points-out" in err[-1]
    assert snap.unchanged()
