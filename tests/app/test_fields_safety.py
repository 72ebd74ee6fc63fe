"""Bad input to the field jobs (piv, icp, dem-diff, strain, synth-lobe) on the command line:
exit 2 and one line naming the flag, inputs byte-identical, the output folder untouched."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from slipmap.cli import main
from slipmap.core.io.table import write_csv_columns

DATA = Path(__file__).resolve().parents[1] / "data"
X0, Y0 = 512000.0, 4780000.0


def _need_gdal():
    pytest.importorskip("osgeo.gdal", reason="GDAL's Python bindings (python3-gdal) missing")


pytestmark = pytest.mark.usefixtures("drop_cli_log_handlers")


def _rough(n, seed, side=20.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, side, (n, 2))
    x, y = xy[:, 0], xy[:, 1]
    z = 0.5 * np.sin(x / 2.7) * np.cos(y / 3.1) + 0.06 * np.sin(x / 0.21 + np.sin(y / 0.37))
    return np.column_stack([xy + [X0, Y0], z + 100.0])


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    import pyproj

    from slipmap.core.io.las import PointCloud, write_las

    d = tmp_path_factory.mktemp("fields_safety")
    crs = pyproj.CRS.from_epsg(32612)
    write_las(d / "b.las", PointCloud(xyz=_rough(8000, 1), crs=crs))
    write_las(d / "a.las", PointCloud(xyz=_rough(8000, 2) + [0.1, -0.1, 0.02], crs=crs))
    return d / "b.las", d / "a.las"


def _cli(argv, capsys):
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    err = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.strip()]
    return rc, err


def _copy(src: Path, dst: Path) -> Path:
    dst.write_bytes(src.read_bytes())
    return dst


@pytest.fixture
def never_computed(monkeypatch):
    """Fail the test if a field computation starts (checks must come first)."""

    def boom(*a, **k):
        raise AssertionError("the computation ran before the refusal")

    import slipmap.core.dem as dem
    import slipmap.core.icp as icp
    import slipmap.core.piv as piv

    monkeypatch.setattr(piv, "piv", boom)
    monkeypatch.setattr(icp, "windowed_icp", boom)
    monkeypatch.setattr(dem, "dem_difference", boom)


# --------------------------------------------------------------------------- data loss


def test_piv_control_named_like_an_output_is_refused(
    pair, tmp_path, capsys, snapshot, never_computed
):
    """A control CSV inside --out named piv.csv was overwritten before it was read."""
    b, a = pair
    out = tmp_path / "out"
    out.mkdir()
    control = out / "piv.csv"
    write_csv_columns(control, {"x": [X0 + 10], "y": [Y0 + 10], "dx": [0.1], "dy": [-0.1]})
    snap = snapshot(out, b, a)
    rc, err = _cli(
        ["piv", str(b), str(a), "--grid", "0.5", "--out", str(out), "--control", str(control)],
        capsys,
    )
    assert rc == 2 and len(err) == 1, err
    assert "--out:" in err[0] and "--control" in err[0] and "never overwrites" in err[0]
    assert snap.unchanged()


def test_icp_stable_mask_named_like_an_output_is_refused(
    pair, tmp_path, capsys, snapshot, never_computed
):
    b, a = pair
    out = tmp_path / "out"
    out.mkdir()
    mask = out / "icp.gpkg"
    mask.write_bytes(b"not read: refused before")
    snap = snapshot(out, b, a)
    rc, err = _cli(["icp", str(b), str(a), "--out", str(out), "--stable-mask", str(mask)], capsys)
    assert rc == 2 and len(err) == 1, err
    assert "--out:" in err[0] and "--stable-mask" in err[0]
    assert snap.unchanged()


@pytest.mark.parametrize("command", ["piv", "dem-diff", "icp"])
def test_same_file_as_both_epochs(pair, tmp_path, capsys, command, never_computed):
    b, _ = pair
    opt = ["--cell", "5"] if command == "icp" else ["--grid", "0.5"]
    rc, err = _cli([command, str(b), str(b), *opt, "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and len(err) == 1 and "AFTER:" in err[0] and "BEFORE" in err[0], err
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- exit 1 -> 2


@pytest.mark.parametrize("command", ["piv", "dem-diff"])
def test_grid_too_fine_is_refused_before_allocating(
    pair, tmp_path, capsys, command, never_computed
):
    b, a = pair
    out = tmp_path / "o"
    rc, err = _cli([command, str(b), str(a), "--grid", "1e-5", "--out", str(out)], capsys)
    assert rc == 2 and len(err) == 1, err
    assert "--grid:" in err[0] and "GiB" in err[0] and "coarser" in err[0]
    assert not out.exists()


def test_strain_given_a_las_file(pair, tmp_path, capsys, snapshot):
    b, _ = pair
    snap = snapshot(b)
    rc, err = _cli(["strain", str(b), "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and len(err) == 1, err
    assert "FIELD:" in err[0] and "LAS/LAZ" in err[0] and "piv.csv" in err[0]
    assert "GeoTIFF" in err[0] and "--dy" in err[0]
    las_as_csv = _copy(b, tmp_path / "cloud.csv")  # a LAS under a table's name
    rc, err = _cli(["strain", str(las_as_csv), "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and len(err) == 1 and "FIELD:" in err[0] and "LAS/LAZ" in err[0], err
    assert snap.unchanged() and not (tmp_path / "o").exists()


def test_strain_off_lattice_table_names_the_input_not_the_function(tmp_path, capsys):
    write_csv_columns(
        tmp_path / "f.csv",
        {"x": [0.0, 1.0, 2.0, 3.37], "y": [0.0, 0.0, 0.0, 0.0], "dx": [0] * 4, "dy": [0] * 4},
    )
    rc, err = _cli(["strain", str(tmp_path / "f.csv"), "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and len(err) == 1, err
    assert "FIELD:" in err[0] and "field_from_columns" not in err[0] and "--spacing" in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("where", ["under_a_file", "read_only"])
def test_piv_out_unwritable_fails_before_computing(pair, tmp_path, capsys, where, never_computed):
    b, a = pair
    if where == "under_a_file":
        (tmp_path / "file.txt").write_text("x")
        out = tmp_path / "file.txt" / "out"
    else:
        if os.geteuid() == 0:
            pytest.skip("root writes in read-only folders")
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        out = ro / "out"
    rc, err = _cli(["piv", str(b), str(a), "--grid", "0.5", "--out", str(out)], capsys)
    assert rc == 2 and len(err) == 1 and "--out:" in err[0], err
    assert not out.exists()


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["--grid", "nan"], "--grid"),
        (["--grid", "0.5", "--overlap", "inf"], "--overlap"),
        (["--grid", "0.5", "--window", "32", "2"], "--window"),
        (["--grid", "0.5", "--out", ""], "--out"),
    ],
)
def test_bad_values_refused_at_parse_time(pair, tmp_path, capsys, argv, flag):
    b, a = pair
    out = tmp_path / "o"
    argv = ["piv", str(b), str(a), *argv]
    if "--out" not in argv:
        argv += ["--out", str(out)]
    rc, err = _cli(argv, capsys)
    assert rc == 2 and f"{flag}:" in err[-1], err
    assert not out.exists()


def test_class_selection_names_the_epoch(pair, tmp_path, capsys):
    b, a = pair
    rc, err = _cli(
        ["piv", str(b), str(a), "--grid", "0.5", "--classes", "2", "--out", str(tmp_path / "o")],
        capsys,
    )
    assert rc == 2 and len(err) == 1, err
    assert "--classes:" in err[0] and "before epoch" in err[0]


# --------------------------------------------------------------------------- control points


@pytest.mark.parametrize("command", ["piv", "icp"])
def test_control_points_none_comparable_refused_and_nothing_written(
    pair, tmp_path, capsys, snapshot, command
):
    _need_gdal()
    b, a = pair
    control = tmp_path / "far.csv"
    write_csv_columns(  # two rows far outside the field, one without dx
        control,
        {
            "x": [X0 - 500, X0 + 900, X0 + 5],
            "y": [Y0, Y0, Y0 + 5],
            "dx": [0, 0, np.nan],
            "dy": [0] * 3,
        },
    )
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    snap = snapshot(out, control, b, a)
    opt = ["--cell", "5", "--min-points", "50"] if command == "icp" else ["--grid", "0.5"]
    if command == "piv":
        opt += ["--window", "16", "8"]
    rc, err = _cli(
        [command, str(b), str(a), *opt, "--out", str(out), "--control", str(control)], capsys
    )
    assert rc == 2 and "--control:" in err[-1], err
    assert "3 row(s) read" in err[-1] and "1 without a finite dx/dy" in err[-1]
    assert "2 outside the field" in err[-1]
    assert snap.unchanged()


def test_control_without_finite_displacements_refused_before_computing(
    pair, tmp_path, capsys, never_computed
):
    b, a = pair
    control = tmp_path / "c.csv"
    control.write_text("x,y,dx,dy\n512005,4780005,,\n")
    rc, err = _cli(
        [
            "piv",
            str(b),
            str(a),
            "--grid",
            "0.5",
            "--out",
            str(tmp_path / "o"),
            "--control",
            str(control),
        ],
        capsys,
    )
    assert rc == 2 and len(err) == 1 and "--control:" in err[0] and "finite dx and dy" in err[0]
    assert not (tmp_path / "o").exists()


def test_control_points_are_counted(pair, tmp_path, capsys):
    """Rows read / outside / without a reference are reported with the comparison."""
    _need_gdal()
    import json

    b, a = pair
    control = tmp_path / "c.csv"
    write_csv_columns(
        control,
        {
            "x": [X0 + 8, X0 + 12, X0 - 300, X0 + 9],
            "y": [Y0 + 8, Y0 + 11, Y0, Y0 + 9],
            "dx": [0.1, 0.1, 0.1, np.nan],
            "dy": [-0.1, -0.1, -0.1, -0.1],
        },
    )
    out = tmp_path / "o"
    rc, _ = _cli(
        [
            "-q",
            "piv",
            str(b),
            str(a),
            "--grid",
            "0.5",
            "--window",
            "16",
            "8",
            "--out",
            str(out),
            "--control",
            str(control),
            "--no-progress",
        ],
        capsys,
    )
    assert rc == 0
    c = json.loads((out / "piv.json").read_text())["control"]
    assert c["n_rows"] == 4 and c["n_without_reference"] == 1 and c["n_outside"] == 1
    assert c["n_compared"] + c["n_without_vector"] == 2


# --------------------------------------------------------------------------- synth-lobe


def test_synth_lobe_failure_leaves_nothing(tmp_path, capsys, snapshot, monkeypatch):
    import slipmap.core.io.table as table

    src = _copy(DATA / "lone-star.laz", tmp_path / "lone.laz")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    snap = snapshot(out, src)

    def boom(*a, **k):
        raise table.InputDataError("disk full (simulated)")

    monkeypatch.setattr(table, "write_csv_columns", boom)
    rc, err = _cli(["synth-lobe", str(src), "--out", str(out)], capsys)
    assert rc == 2 and "disk full" in err[-1], err
    assert snap.unchanged()  # the epochs written before the failure are gone too
    monkeypatch.undo()
    rc, err = _cli(["synth-lobe", str(src), "--out", str(out), "--truth-spacing", "1e-6"], capsys)
    assert rc == 2 and "--truth-spacing:" in err[-1], err  # (a warning about its CRS above)
    assert snap.unchanged()
    rc, err = _cli(["synth-lobe", str(src), "--out", str(out), "--radius", "1", "2", "3"], capsys)
    assert rc == 2 and "--radius:" in err[-1], err
    assert snap.unchanged()
