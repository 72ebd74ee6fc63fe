"""Bad input to the planes job in the CLI and PDAL faces: refused before anything is written,
inputs untouched, the option named as the face calls it."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from slipmap.cli import main
from slipmap.core.io.las import PointCloud, write_las
from slipmap.core.synthetic import make_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pdal_stages"))


@pytest.fixture(scope="module")
def cloud_file(tmp_path_factory):
    scene = make_scene("mls", seed=3, n_buildings=1, extent_m=30.0, origin=(500000, 4200000, 10))
    path = tmp_path_factory.mktemp("planes_safety") / "scene.laz"
    write_las(path, PointCloud(xyz=scene.points, attributes={}))
    return path


def _cli(argv, capsys):
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


def test_output_over_the_input_refused_before_reading(tmp_path, cloud_file, snapshot):
    """The labelled copy written over the input itself (a QGIS destination or a script's
    outputs mapping): refused before the file is even read."""
    from slipmap.app import planes as job
    from slipmap.app.options import OptionError

    src = tmp_path / "scene.laz"
    src.write_bytes(cloud_file.read_bytes())
    snap = snapshot(tmp_path)
    opts = job.SPEC.parse({"input": str(src), "out": "-"})
    with pytest.raises(OptionError) as e:
        job.run(opts, {"labelled_cloud": str(src), "summary": str(tmp_path / "p.json")})
    assert e.value.key == "labelled_cloud" and "never overwrites an input" in e.value.text
    assert job.SPEC.render_error(e.value, "qgis").startswith('"Labelled point cloud (PlaneId)"')
    assert snap.unchanged()


@pytest.mark.parametrize(
    "flag, value, expect",
    [
        ("--min-node-size", "nan", "--min-node-size: must be a finite number"),
        ("--planarity-threshold", "inf", "--planarity-threshold: must be a finite number"),
        ("--planarity-ratio", "0", "--planarity-ratio: must be > 0"),
        ("--min-points", "2.5", "--min-points: must be a whole number"),
        ("--backend", "cuda", "--backend: must be one of numpy, opencl, auto"),
        ("--crs", "EPSG:99999999", "--crs:"),
    ],
)
def test_bad_values_refused_at_parse_time(tmp_path, capsys, cloud_file, flag, value, expect):
    out = tmp_path / "out"
    rc, err = _cli(["planes", str(cloud_file), "--out", str(out), flag, value], capsys)
    assert rc == 2 and expect in err[-1], err
    assert not out.exists()


def test_empty_out_refused(capsys, cloud_file):
    rc, err = _cli(["planes", str(cloud_file), "--out", ""], capsys)
    assert rc == 2 and "--out" in err[-1] and "empty" in err[-1]


def test_out_is_a_file(tmp_path, capsys, cloud_file, snapshot):
    out = tmp_path / "out.txt"
    out.write_text("a file")
    snap = snapshot(out, cloud_file)
    rc, err = _cli(["planes", str(cloud_file), "--out", str(out)], capsys)
    assert rc == 2 and "--out" in err[-1] and "not a folder" in err[-1]
    assert snap.unchanged()


def test_missing_and_empty_input(tmp_path, capsys):
    out = tmp_path / "out"
    rc, err = _cli(["planes", str(tmp_path / "missing.laz"), "--out", str(out)], capsys)
    assert rc == 2 and err[-1].startswith("slipmap planes: error: INPUT:"), err
    empty = tmp_path / "empty.laz"
    write_las(empty, PointCloud(xyz=np.zeros((0, 3)), attributes={}))
    rc, err = _cli(["planes", str(empty), "--out", str(out)], capsys)
    assert rc == 2 and "INPUT:" in err[-1] and "no points" in err[-1]
    assert not out.exists()


def test_classes_on_an_unclassified_cloud(tmp_path, capsys, cloud_file):
    out = tmp_path / "out"
    rc, err = _cli(["planes", str(cloud_file), "--out", str(out), "--classes", "6"], capsys)
    assert rc == 2 and err[-1].startswith("slipmap planes: error: --classes:"), err
    assert "is left by the class selection (its classes: 0)" in err[-1]
    assert not out.exists()


def test_failure_after_reading_leaves_nothing(tmp_path, capsys, cloud_file, monkeypatch, snapshot):
    """A failure in the computation (here: injected) leaves the output folder as it was."""
    from slipmap.app import planes as job

    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("the user's")
    snap = snapshot(out, cloud_file)

    def boom(*a, **k):
        raise MemoryError("injected")

    monkeypatch.setattr(job, "segment", boom)
    rc, err = _cli(["planes", str(cloud_file), "--out", str(out)], capsys)
    assert rc == 1
    assert snap.unchanged()


# --------------------------------------------------------------------------- PDAL


def test_pdal_names_its_own_option():
    from pdal_harness import call, load_stage, make_ins, parse_add_dimension

    from slipmap.pdal_filters._stage import StageError

    dims = parse_add_dimension(["PlaneId=int32", "Planarity"])
    pts = np.random.default_rng(0).random((100, 3))
    for args, expect in (
        ({"min_node_size_m": "nan"}, "'min_node_size_m' must be a finite number"),
        ({"planarity_ratio": 1.5}, "'planarity_ratio' must be <= 1"),
        ({"backend": "cuda"}, "'backend' must be one of"),
    ):
        mod = load_stage("planes", json.dumps(args))
        with pytest.raises(StageError, match=expect):
            call(mod, make_ins(pts), dims)
