"""Bad input to the slip job (``slipmap displacement``, the PDAL ``displacement`` stage):
refused before anything is written (or, when found after reading, with the output folder as
it was), inputs byte-identical, the option named as the face calls it (issue #15's audit)."""

import json
import sys
from pathlib import Path

import numpy as np
import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.io.las import PointCloud, write_las
from slipmap.core.synthetic import make_fault_pair

pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "pdal_stages"))

ORIGIN = (498000.0, 4234000.0, 20.0)
UTM10 = pyproj.CRS.from_epsg(32610)


@pytest.fixture(scope="module")
def pair(tmp_path_factory, line_file):
    d = tmp_path_factory.mktemp("slip_safety")
    fp = make_fault_pair(
        "mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.0181, 0.0), density_pts_m2=20.0
    )
    paths = {}
    for name, sc in (("before", fp.before), ("after", fp.after)):
        p = d / f"{name}.laz"
        attrs = {"Classification": sc.classification}
        write_las(p, PointCloud(xyz=sc.points, attributes=attrs, crs=UTM10))
        paths[name] = p
    fault = d / "fault.gpkg"
    line_file(fault, fp.trace_xy, UTM10)
    return fp, paths, fault


def _cli(argv, capsys):
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


def _argv(paths, fault, out):
    return ["displacement", str(paths["before"]), str(paths["after"]), "--fault", str(fault)]


def test_fault_inside_out_under_an_output_name_is_not_overwritten(pair, tmp_path, capsys,
                                                                  snapshot):  # fmt: skip
    """The audit's data loss: a fault GeoPackage named displacement.gpkg inside --out."""
    fp, paths, fault = pair
    out = tmp_path / "out"
    out.mkdir()
    trap = out / "displacement.gpkg"
    trap.write_bytes(fault.read_bytes())
    snap = snapshot(out, paths["before"], paths["after"])
    argv = _argv(paths, trap, out) + ["--out", str(out)]
    rc, err = _cli(argv, capsys)
    assert rc == 2 and "never overwrites an input" in err[-1] and "--fault" in err[-1], err
    assert snap.unchanged()


@pytest.mark.parametrize(
    "flag, value, expect",
    [
        ("--reference-slip", "nan", "--reference-slip: must be a finite number"),
        ("--reference-slip", "inf", "--reference-slip: must be a finite number"),
        ("--buffer", "-1", "--buffer: must be >= 0"),
        ("--tile-size", "0", "--tile-size: must be > 0"),
        ("--stochastic-model", "brown", "--stochastic-model: must be one of"),
    ],
)
def test_bad_values_refused_at_parse_time(pair, tmp_path, capsys, flag, value, expect):
    fp, paths, fault = pair
    out = tmp_path / "out"
    rc, err = _cli(_argv(paths, fault, out) + ["--out", str(out), flag, value], capsys)
    assert rc == 2 and expect in err[-1], err
    assert not out.exists()


def test_empty_out_and_out_a_file(pair, tmp_path, capsys, snapshot):
    fp, paths, fault = pair
    rc, err = _cli(_argv(paths, fault, None) + ["--out", ""], capsys)
    assert rc == 2 and "--out" in err[-1] and "empty" in err[-1], err
    f = tmp_path / "out.txt"
    f.write_text("a file")
    snap = snapshot(f)
    rc, err = _cli(_argv(paths, fault, None) + ["--out", str(f)], capsys)
    assert rc == 2 and "--out" in err[-1], err
    assert snap.unchanged()


def test_same_file_as_both_epochs(pair, tmp_path, capsys):
    fp, paths, fault = pair
    out = tmp_path / "out"
    argv = ["displacement", str(paths["before"]), str(paths["before"]), "--fault", str(fault)]
    rc, err = _cli(argv + ["--out", str(out)], capsys)
    assert rc == 2 and "same file" in err[-1], err
    assert not out.exists()


def test_geographic_crs_on_metre_coordinates(pair, tmp_path, capsys):
    fp, paths, fault = pair
    out = tmp_path / "out"
    rc, err = _cli(_argv(paths, fault, out) + ["--out", str(out), "--crs", "EPSG:4326"], capsys)
    assert rc == 2 and "--crs" in err[-1], err
    assert not out.exists()


def test_failure_after_reading_leaves_the_output_folder_as_it_was(pair, tmp_path, capsys,
                                                                  snapshot, line_file):  # fmt: skip
    """A fault trace away from the data is found only after both epochs are read: the run
    ends with exit 2 naming the fault, and an output folder holding a user's file keeps
    exactly that file (no partial outputs, no staging folder left)."""
    fp, paths, fault = pair
    far = tmp_path / "far.gpkg"
    line_file(far, np.asarray(fp.trace_xy) + [5000.0, 5000.0], UTM10)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    snap = snapshot(out, paths["before"], paths["after"], far)
    rc, err = _cli(_argv(paths, far, out) + ["--out", str(out)], capsys)
    assert rc == 2 and "--fault" in err[-1], err
    assert snap.unchanged()


def test_windows_output_without_window_size_is_refused_by_the_job(pair, tmp_path):
    """Scripts (and QGIS) map outputs one by one: a windows raster asked for without a window
    size is refused before reading, naming both."""
    from slipmap.app import slip as job
    from slipmap.app.options import OptionError

    fp, paths, fault = pair
    opts = job.SPEC.parse(
        {"before": str(paths["before"]), "after": str(paths["after"]), "fault": str(fault),
         "out": "-"}
    )  # fmt: skip
    with pytest.raises(OptionError) as e:
        job.run(opts, {"summary": str(tmp_path / "s.json"), "windows": str(tmp_path / "w.tif")})
    assert e.value.key == "windows" and "window_size_m" in e.value.also
    assert "--window-size" in job.SPEC.render_error(e.value, "cli")
    assert not any(tmp_path.iterdir())


# --------------------------------------------------------------------------- PDAL face


_DECLARED = {"PlaneId": np.dtype(np.int32), "Residual": np.dtype(np.float64)}


def _pdal_stage(opts):
    from pdal_harness import load_stage

    return load_stage("displacement", opts)


@pytest.mark.parametrize(
    "opts, words",
    [
        ({"buffer_m": "nan"}, ("buffer_m", "finite")),
        ({"stochastic_model": "brown"}, ("stochastic_model",)),
        ({"fixed_components": "plane=-1"}, ("fixed_components", ">= 0")),
        ({"combine": "tiles"}, ("combine", "tile_size_m")),
    ],
)
def test_pdal_bad_options_name_the_key(pair, opts, words):
    from pdal_harness import call, make_ins

    from slipmap.pdal_filters._stage import StageError

    fp, paths, fault = pair
    (x0, y0), (x1, y1) = (map(float, v) for v in fp.trace_xy)
    base = {"trace": f"LINESTRING ({x0!r} {y0!r}, {x1!r} {y1!r})"}
    pts = np.vstack([fp.before.points, fp.after.points])
    tag = np.r_[np.ones(len(fp.before.points)), np.full(len(fp.after.points), 2.0)]
    with pytest.raises(StageError) as e:
        stage = _pdal_stage({**base, **opts})
        call(stage, make_ins(pts, Epoch=tag), _DECLARED)
    msg = str(e.value)
    assert all(w in msg for w in words), msg
    assert "--" not in msg  # PDAL users see PDAL option names, not CLI flags


def test_pdal_summary_is_standard_json(pair):
    """No NaN literal in the stage's metadata JSON (one JSON policy for every face)."""
    from pdal_harness import call, make_ins, nodes

    fp, paths, fault = pair
    (x0, y0), (x1, y1) = (map(float, v) for v in fp.trace_xy)
    pts = np.vstack([fp.before.points, fp.after.points])
    tag = np.r_[np.ones(len(fp.before.points)), np.full(len(fp.after.points), 2.0)]
    stage = _pdal_stage({"trace": f"LINESTRING ({x0!r} {y0!r}, {x1!r} {y1!r})"})
    call(stage, make_ins(pts, Epoch=tag), _DECLARED)
    text = json.dumps(nodes(stage)["summary"], allow_nan=False)  # raises on NaN/inf
    assert nodes(stage)["right_lateral_slip"] == pytest.approx(0.0181, abs=0.003)
    assert "NaN" not in text
