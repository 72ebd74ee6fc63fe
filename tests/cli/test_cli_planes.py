"""The ``slipmap`` command line: planes and demo, exit codes, outputs against the core."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slipmap.cli import main
from slipmap.core.io.las import PointCloud, read_las, write_las
from slipmap.core.planes import segment_planes
from slipmap.core.synthetic import make_scene

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    scene = make_scene("mls", seed=3, n_buildings=2, extent_m=55.0, origin=(500000, 4200000, 10))
    path = tmp_path_factory.mktemp("scene") / "scene.laz"
    cloud = PointCloud(xyz=scene.points, attributes={"Classification": scene.classification})
    write_las(path, cloud)
    return path, scene


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert "slipmap" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(["planes", "--help"])
    assert e.value.code == 0
    assert "--min-node-size" in capsys.readouterr().out


def test_console_script_runs():
    exe = Path(sys.executable).with_name("slipmap")
    out = subprocess.run([str(exe), "--help"], capture_output=True, text=True, check=True)
    assert "planes" in out.stdout and "demo" in out.stdout


def test_planes_outputs_match_core(scene_file, tmp_path):
    path, scene = scene_file
    out = tmp_path / "out"
    assert main(["-q", "planes", str(path), "--out", str(out)]) == 0
    payload = json.loads((out / "planes.json").read_text())
    assert set(payload) >= {"planes", "n_points", "parameters", "runtime_s"}
    assert payload["n_points"] == scene.points.shape[0]
    # ground (class 2) is excluded by default; the core on the same selection gives the same
    cloud = read_las(path)
    keep = cloud.attributes["Classification"] != 2
    core = segment_planes(cloud.xyz[keep])
    assert len(payload["planes"]) == len(core)
    for rec, k in zip(payload["planes"], range(len(core))):
        assert rec["id"] == k
        assert np.allclose(rec["normal"], core.normals[k], atol=1e-9)
        assert rec["d"] == pytest.approx(core.offsets[k], abs=1e-6)
        assert rec["n_points"] == core.n_points[k]
        assert set(rec) >= {"id", "normal", "d", "centroid", "n_points", "rms"}
    labelled = read_las(out / "scene_planes.laz")
    assert len(labelled) == len(cloud)
    assert np.array_equal(labelled.xyz, cloud.xyz)  # input order kept
    pid = labelled.attributes["PlaneId"]
    assert pid.dtype == np.int32
    assert np.all(pid[~keep] == -1)
    assert np.array_equal(pid[keep], core.labels)
    assert payload["parameters"]["planarity_ratio"] == 0.9


def test_planes_options_and_classes(scene_file, tmp_path):
    path, _ = scene_file
    out = tmp_path / "o"
    rc = main(
        [
            "-q",
            "planes",
            str(path),
            "--out",
            str(out),
            "--classes",
            "6",
            "--min-node-size",
            "1.0",
            "--planarity-threshold",
            "0.06",
            "--angle-threshold",
            "5",
            "--distance-threshold",
            "0.08",
            "--min-points",
            "100",
            "--planarity-ratio",
            "0.85",
        ]
    )
    assert rc == 0
    p = json.loads((out / "planes.json").read_text())["parameters"]
    assert p["planarity_threshold_m"] == 0.06 and p["angle_threshold_deg"] == 5
    assert p["distance_threshold_m"] == 0.08 and p["min_plane_points"] == 100
    assert p["planarity_ratio"] == 0.85 and 1.0 <= p["min_node_size_m"] < 2.0
    pid = read_las(out / "scene_planes.laz").attributes["PlaneId"]
    cls = read_las(path).attributes["Classification"]
    assert np.all(pid[cls != 6] == -1)


def test_real_file_autzen(tmp_path):
    out = tmp_path / "a"
    assert main(["-q", "planes", str(DATA / "autzen_trim.laz"), "--out", str(out)]) == 0
    assert (out / "autzen_trim_planes.laz").is_file()
    back = read_las(out / "autzen_trim_planes.laz")
    src = read_las(DATA / "autzen_trim.laz")
    assert np.array_equal(back.xyz, src.xyz)
    assert back.crs is not None and back.crs.equals(src.crs)


def _run(args, capsys):
    rc = main(args)
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


@pytest.mark.parametrize(
    "content",
    [None, b"", b"not a las file at all" * 10],
    ids=["missing", "empty-bytes", "corrupt"],
)
def test_bad_files_exit_2_and_write_nothing(tmp_path, capsys, content):
    src = tmp_path / "bad.laz"
    if content is not None:
        src.write_bytes(content)
    out = tmp_path / "out"
    rc, err = _run(["planes", str(src), "--out", str(out)], capsys)
    assert rc == 2
    assert len(err) == 1 and "error" in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def _write_points(path, xyz):
    write_las(path, PointCloud(xyz=np.asarray(xyz, dtype=float)))


@pytest.mark.parametrize("n", [0, 1, 2])
def test_too_few_points(tmp_path, capsys, n):
    src = tmp_path / "few.las"
    _write_points(src, np.arange(3 * n, dtype=float).reshape(n, 3))
    rc, err = _run(["planes", str(src), "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "point" in err[-1]
    assert not (tmp_path / "o").exists()


def test_identical_points(tmp_path, capsys):
    src = tmp_path / "same.las"
    _write_points(src, np.ones((50, 3)))
    rc, err = _run(["planes", str(src), "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "identical" in err[-1]


def test_no_planes_is_warning_with_empty_outputs(tmp_path, capsys):
    src = tmp_path / "noise.las"
    _write_points(src, np.random.default_rng(0).uniform(0, 10, (3000, 3)))
    out = tmp_path / "o"
    rc, err = _run(["planes", str(src), "--out", str(out)], capsys)
    assert rc == 0
    assert any("no planes" in line for line in err)
    assert json.loads((out / "planes.json").read_text())["planes"] == []
    assert np.all(read_las(out / "noise_planes.las").attributes["PlaneId"] == -1)


def test_unwritable_output(tmp_path, capsys, scene_file):
    path, _ = scene_file
    blocker = tmp_path / "file"
    blocker.write_text("x")
    rc, err = _run(["planes", str(path), "--out", str(blocker / "sub")], capsys)
    assert rc == 2 and "--out" in err[-1]


def test_bad_option_values(tmp_path, capsys, scene_file):
    path, _ = scene_file
    with pytest.raises(SystemExit) as e:
        main(["planes", str(path), "--out", str(tmp_path), "--min-node-size", "-1"])
    assert e.value.code == 2
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["planes", str(path), "--out", str(tmp_path), "--planarity-ratio", "2"])
    assert e.value.code == 2
    assert "--planarity-ratio: must be <= 1" in capsys.readouterr().err


def test_debug_shows_traceback(tmp_path, capsys):
    rc = main(["--debug", "planes", str(tmp_path / "missing.laz"), "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "Traceback" in capsys.readouterr().err


def test_demo_planes(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--job", "planes", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "true surfaces recovered 100.0%" in err or "true surfaces recovered 9" in err
    assert (out / "planes.json").is_file() and (out / "demo_scene_planes.laz").is_file()
