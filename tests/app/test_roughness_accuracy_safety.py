"""Bad input to the roughness and accuracy jobs in the CLI and PDAL faces: refused before
anything is written, inputs untouched, the option named as the face calls it."""

import json
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from slipmap.cli import main
from slipmap.core.io.las import PointCloud, write_las

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pdal_stages"))

ORIGIN = np.array([500000.0, 4200000.0, 100.0])


@pytest.fixture(scope="module")
def cloud_file(tmp_path_factory):
    """A rough tilted plane, 8 m x 8 m, UTM 10N."""
    rng = np.random.default_rng(4)
    xy = rng.uniform(0.0, 8.0, (6000, 2))
    z = 0.3 * xy[:, 0] + rng.normal(0.0, 0.02, xy.shape[0])
    import pyproj

    path = tmp_path_factory.mktemp("rough_safety") / "plane.las"
    write_las(
        path, PointCloud(xyz=np.column_stack([xy, z]) + ORIGIN, crs=pyproj.CRS.from_epsg(32610))
    )
    return path


@pytest.fixture
def work(tmp_path, cloud_file):
    """A copy of the input in a folder of its own, and an output folder holding one file."""
    src = tmp_path / "in" / "plane.las"
    src.parent.mkdir()
    src.write_bytes(cloud_file.read_bytes())
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    return src, out


def _cli(argv, capsys):
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


def _one_line(err):
    assert len(err) == 1, err
    return err[0]


# --------------------------------------------------------------------------- roughness, CLI


def test_points_out_over_the_input_refused_before_anything(work, capsys, snapshot):
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(["roughness", str(src), "--out", str(out), "--points-out", str(src)], capsys)
    line = _one_line(err)
    assert rc == 2 and "--points-out" in line and "never overwrites an input" in line
    assert snap.unchanged()


def test_points_out_not_las_refused_before_anything(work, capsys, snapshot):
    src, out = work
    snap = snapshot(src.parent, out)
    bad = out / "points.txt"
    rc, err = _cli(["roughness", str(src), "--out", str(out), "--points-out", str(bad)], capsys)
    line = _one_line(err)
    assert rc == 2 and line.split("error: ")[1].startswith("--points-out:") and ".las" in line
    assert snap.unchanged()


def test_out_is_a_file(work, capsys, snapshot):
    src, out = work
    target = out / "keep.txt"
    snap = snapshot(src.parent, out)
    rc, err = _cli(["roughness", str(src), "--out", str(target)], capsys)
    line = _one_line(err)
    assert rc == 2 and "--out:" in line and "not a folder" in line
    assert snap.unchanged()


@pytest.mark.parametrize(
    "extra, flag",
    [
        (["--cell", "50"], "--cell"),  # larger than the cloud
        (["--cell", "0.1", "--min-points", "5000"], "--min-points"),  # no cell evaluated
    ],
)
def test_failures_after_reading_leave_the_folder_untouched(work, capsys, snapshot, extra, flag):
    src, out = work
    pts = out / "points.las"
    snap = snapshot(src.parent, out)
    rc, err = _cli(
        ["roughness", str(src), "--out", str(out), "--points-out", str(pts), *extra], capsys
    )
    line = _one_line(err)
    assert rc == 2 and line.split("error: ")[1].startswith(flag + ":"), line
    assert snap.unchanged() and not list(out.glob(".slipmap-partial-*"))


def test_raster_too_large_for_memory_refused_naming_the_cell(work, capsys, snapshot, monkeypatch):
    from slipmap.app import resources

    monkeypatch.setattr(resources, "available_bytes", lambda: 1_000_000)  # 1 MB free
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(["roughness", str(src), "--out", str(out), "--cell", "0.05"], capsys)
    line = _one_line(err)
    assert rc == 2 and "--cell:" in line and "GiB" in line, line
    assert snap.unchanged()


def test_raster_memory_check_uses_the_shared_resource_check(monkeypatch):
    """The roughness job's memory check is app/resources.check_grid_memory, keyed on the cell
    option (piv and dem-diff share it)."""
    from slipmap.app import resources
    from slipmap.app import roughness as job

    calls = []
    monkeypatch.setattr(job, "check_grid_memory", lambda *a, **k: calls.append((a, k)))
    uv = np.array([[0.0, 0.0], [10.0, 4.0]])
    job.check_raster_memory((0.5,), uv)
    ((args, kw),) = calls
    assert args[0] == "cell_sizes_m" and args[1] == (20 + 2) * (8 + 2)
    assert job.check_grid_memory is not resources.check_grid_memory  # patched: it was used


@pytest.mark.parametrize(
    "flag, value, words",
    [
        ("--cell", "nan", "must be a finite number"),
        ("--cell", "-1", "must be > 0"),
        ("--cutoff", "inf", "must be a finite number"),
        ("--cutoff", "1.5", "must be <= 1"),
        ("--min-points", "2", "must be >= 3"),
        ("--ols-axis", "w", "must be one of"),
        ("--crs", "EPSG:999999", "not a CRS"),
        ("--out", "", "is empty"),
    ],
)
def test_roughness_values_refused_at_parse_time(work, capsys, snapshot, flag, value, words):
    src, out = work
    snap = snapshot(src.parent, out)
    argv = ["roughness", str(src), "--out", str(out), flag, value]
    rc, err = _cli(argv, capsys)
    assert rc == 2 and flag in err[-1] and words in err[-1], err
    assert snap.unchanged()


def test_geographic_crs_on_metre_coordinates(work, capsys, snapshot):
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(["roughness", str(src), "--out", str(out), "--crs", "EPSG:4326"], capsys)
    line = _one_line(err)
    assert rc == 2 and "--crs:" in line and "geographic" in line and "not degrees" in line
    assert snap.unchanged()


def test_las_header_with_scale_zero(work, capsys, snapshot):
    src, out = work
    raw = bytearray(src.read_bytes())
    raw[131:139] = struct.pack("<d", 0.0)  # X scale factor
    src.write_bytes(bytes(raw))
    snap = snapshot(src.parent, out)
    rc, err = _cli(["roughness", str(src), "--out", str(out)], capsys)
    line = _one_line(err)
    assert rc == 2 and "INPUT:" in line and str(src) in line and "scale" in line
    assert snap.unchanged()


# --------------------------------------------------------------------------- accuracy, CLI


def test_accuracy_out_an_existing_folder_refused_before_running(work, capsys, snapshot):
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(["accuracy", str(src), "--out", str(out)], capsys)
    line = _one_line(err)
    assert rc == 2 and "--out:" in line and "is a folder; give a file name" in line
    assert snap.unchanged()


@pytest.mark.parametrize("name", ["sigmas.txt", "sigmas", "sigmas.csv"])
def test_accuracy_out_not_las_refused(work, capsys, snapshot, name):
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(["accuracy", str(src), "--out", str(out / name)], capsys)
    line = _one_line(err)
    assert rc == 2 and "--out:" in line and ".las" in line
    assert snap.unchanged()


def test_accuracy_out_over_the_input(work, capsys, snapshot):
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(["accuracy", str(src), "--out", str(src)], capsys)
    line = _one_line(err)
    assert rc == 2 and "--out:" in line and "never overwrites an input" in line
    assert snap.unchanged()


@pytest.mark.parametrize(
    "extra, flag, words",
    [
        (["--pa", "axis"], "--sigma-xyz", "axis model"),
        (["--pa", "propagated"], "--scanner-spec", "propagated model"),
        (
            ["--pa", "propagated", "--scanner-spec", "riegl-vz400"],
            "--trajectory",
            "--scanner-position",
        ),
        (["--pa", "columns"], "--sigma-columns", "SigmaX"),
        (["--pa", "columns", "--sigma-columns", "A", "B", "C"], "--sigma-columns", "A, B, C"),
    ],
)
def test_accuracy_model_errors_name_the_flag(work, capsys, snapshot, extra, flag, words):
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(["accuracy", str(src), "--out", str(out / "a.las"), *extra], capsys)
    line = _one_line(err)
    assert rc == 2 and line.split("error: ")[1].startswith(flag + ":") and words in line, line
    assert snap.unchanged()


def test_accuracy_pa_config_errors_name_the_option(work, capsys, snapshot, tmp_path):
    src, out = work
    cfg = tmp_path / "pa.json"
    cfg.write_text(json.dumps({"before": {"model": "axis"}, "after": {"sigma": "nan"}}))
    snap = snapshot(src.parent, out, cfg)
    rc, err = _cli(
        ["accuracy", str(src), "--out", str(out / "a.las"), "--pa-config", str(cfg)], capsys
    )
    line = _one_line(err)
    assert rc == 2 and "--pa-config:" in line and "sigma_xyz" in line
    assert snap.unchanged()


@pytest.mark.parametrize(
    "flag, values, words",
    [
        ("--sigma", ["nan"], "must be a finite number"),
        ("--sigma", ["0"], "must be > 0"),
        ("--sigma-xyz", ["0.1", "inf", "0.1"], "must be a finite number"),
        ("--sigma-xyz", ["0.1", "-1", "0.1"], "must be > 0"),
        ("--scanner-position", ["1", "nan", "2"], "must be a finite number"),
        ("--pa", ["kalman"], "must be one of"),
    ],
)
def test_accuracy_values_refused_at_parse_time(work, capsys, snapshot, flag, values, words):
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(["accuracy", str(src), "--out", str(out / "a.las"), flag, *values], capsys)
    assert rc == 2 and flag in err[-1] and words in err[-1], err
    assert snap.unchanged()


def test_accuracy_failure_mid_run_writes_nothing(work, capsys, snapshot, tmp_path):
    """The propagated model on a cloud without GpsTime fails after reading: nothing written,
    the trajectory files untouched."""
    data = Path(__file__).resolve().parents[1] / "data"
    src, out = work
    traj = tmp_path / "traj.smrmsg"
    traj.write_bytes((data / "smrmsg.smrmsg").read_bytes())
    snap = snapshot(src.parent, out, traj)
    argv = ["accuracy", str(src), "--out", str(out / "a.las"), "--pa", "propagated"]
    argv += ["--scanner-spec", "leica-als60", "--trajectory", str(data / "smrmsg.txt")]
    argv += ["--trajectory-accuracy", str(traj)]
    rc, err = _cli(argv, capsys)
    assert rc == 2 and "GpsTime" in _one_line(err)
    assert snap.unchanged() and not list(out.glob(".slipmap-partial-*"))


def test_accuracy_geographic_crs_on_metre_coordinates(work, capsys, snapshot):
    src, out = work
    snap = snapshot(src.parent, out)
    rc, err = _cli(
        ["accuracy", str(src), "--out", str(out / "a.las"), "--crs", "EPSG:4326"], capsys
    )
    line = _one_line(err)
    assert rc == 2 and "--crs:" in line and "geographic" in line
    assert snap.unchanged()


# --------------------------------------------------------------------------- PDAL


def _pts():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 10, (3000, 2))
    return np.column_stack([xy, 0.2 * xy[:, 0] + rng.normal(0, 0.01, 3000)]) + ORIGIN


@pytest.mark.parametrize(
    "args, key, words",
    [
        ({"cell": "nan"}, "cell", "finite"),
        ({"cell": [0.5, "inf"]}, "cell", "finite"),
        ({"cell": 0}, "cell", "> 0"),
        ({"cell": 50}, "cell", "larger than the extent"),
        ({"min_points": 2}, "min_points", ">= 3"),
        ({"ols_axis": "w"}, "ols_axis", "must be one of"),
        ({"method": "lsq"}, "method", "must be one of"),
        ({"map_plane": "xy"}, "map_plane", "unknown option"),  # not a PDAL option
    ],
)
def test_pdal_roughness_bad_options(args, key, words):
    from pdal_harness import call, load_stage, make_ins, parse_add_dimension

    from slipmap.pdal_filters._stage import StageError

    with pytest.raises(StageError) as e:
        call(load_stage("roughness", args), make_ins(_pts()), parse_add_dimension("Roughness"))
    text = str(e.value)
    assert f"'{key}'" in text or f"{key}:" in text, text
    assert words in text and "--" not in text, text


@pytest.mark.parametrize(
    "args, key, words",
    [
        ({"sigma": "nan"}, "sigma", "finite"),
        ({"model": "axis"}, "sigma_xyz", "axis model"),
        ({"model": "axis", "sigma_xyz": [0.1, "inf", 0.1]}, "sigma_xyz", "finite"),
        ({"model": "columns"}, "columns", "SigmaX"),
        ({"model": "propagated"}, "scanner", "propagated model"),
        ({"model": "propagated", "scanner": "riegl-vz400"}, "trajectory", "scanner_position"),
        ({"scanner_position": [1, "nan", 2]}, "scanner_position", "finite"),
        ({"pa_config": "x.json"}, "pa_config", "unknown option"),  # not a PDAL option
    ],
)
def test_pdal_accuracy_bad_options(args, key, words):
    from pdal_harness import call, load_stage, make_ins, parse_add_dimension

    from slipmap.pdal_filters._stage import StageError

    sig = parse_add_dimension(["SigmaX", "SigmaY", "SigmaZ"])
    with pytest.raises(StageError) as e:
        call(load_stage("accuracy", args), make_ins(_pts()), sig)
    text = str(e.value)
    assert f"'{key}'" in text or f"{key}:" in text, text
    assert words in text and "--" not in text, text


def test_pdal_accuracy_unreadable_trajectory_names_it_and_leaves_it(tmp_path, snapshot):
    from pdal_harness import call, load_stage, make_ins, parse_add_dimension

    from slipmap.pdal_filters._stage import StageError

    traj = tmp_path / "broken.sbet"
    traj.write_bytes(b"\x00" * 13)  # not a whole SBET record
    acc = tmp_path / "acc.smrmsg"
    acc.write_bytes((Path(__file__).resolve().parents[1] / "data" / "smrmsg.smrmsg").read_bytes())
    snap = snapshot(tmp_path)
    pts = _pts()
    args = {
        "model": "propagated",
        "scanner": "leica-als60",
        "trajectory": str(traj),
        "trajectory_accuracy": str(acc),
    }
    ins = make_ins(pts, GpsTime=np.linspace(0, 10, len(pts)), ScanAngleRank=np.zeros(len(pts)))
    with pytest.raises(StageError) as e:
        call(load_stage("accuracy", args), ins, parse_add_dimension(["SigmaX", "SigmaY", "SigmaZ"]))
    assert "trajectory" in str(e.value) and "broken.sbet" in str(e.value), e.value
    assert snap.unchanged()
