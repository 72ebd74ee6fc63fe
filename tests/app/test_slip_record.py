"""The record of a fault-slip run (issue #28, findings 7, 10, 11): the headline does not depend
on the tile size (an output option), the JSON and report name the fault's source and only the
point-accuracy settings in effect, a CRS given by the user draws no warning about the files',
an output under a file says so, and the log holds one summary line per side in words."""

from __future__ import annotations

import json
import logging
import re

import numpy as np
import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.displacement import estimate_slip
from slipmap.core.fault import fault_trace
from slipmap.core.io.las import PointCloud, read_las, write_las
from slipmap.core.synthetic import make_fault_pair

pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
pytestmark = pytest.mark.usefixtures("drop_cli_log_handlers")

ORIGIN = (498000.0, 4234000.0, 20.0)
UTM10 = pyproj.CRS.from_epsg(32610)
SLIP = 0.0181  # m, right-lateral
TILE = 50.0


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A fault pair with 18.1 mm of right-lateral slip, its trace as GeoJSON (UTM)."""
    d = tmp_path_factory.mktemp("record")
    fp = make_fault_pair("mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -SLIP, 0.0))
    paths = []
    for name, sc in (("before", fp.before), ("after", fp.after)):
        p = d / f"{name}.laz"
        cloud = PointCloud(
            xyz=sc.points, attributes={"Classification": sc.classification}, crs=UTM10
        )
        write_las(p, cloud)
        paths.append(p)
    feature = {
        "type": "Feature",
        "properties": {},
        "geometry": {"type": "LineString", "coordinates": fp.trace_xy.tolist()},
    }
    fault = d / "fault.geojson"
    fault.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "crs": {"type": "name", "properties": {"name": "EPSG:32610"}},
                "features": [feature],
            }
        )
    )
    return fp, paths, fault


def _run(files, out, capsys, *extra, quiet=False):
    fp, (before, after), fault = files
    argv = ["displacement", str(before), str(after), "--fault", str(fault), "--out", str(out)]
    capsys.readouterr()
    rc = main((["-q"] if quiet else []) + argv + ["--sigma", "0.02", *extra])
    err = capsys.readouterr().err
    assert rc == 0, err
    return json.loads((out / "displacement.json").read_text()), err


@pytest.fixture(scope="module")
def core_refs(files):
    """The core's estimates on the same points (ground is left out by the job by default)."""
    fp, (before, after), _ = files
    cb, ca = read_las(before), read_las(after)
    kb = np.asarray(cb.attributes["Classification"]) != 2
    ka = np.asarray(ca.attributes["Classification"]) != 2
    tr = fault_trace([fp.trace_xy])
    kw = dict(sigma_before=0.02, sigma_after=0.02)
    return {
        "whole": estimate_slip(cb.xyz[kb], ca.xyz[ka], tr, **kw).components(),
        "tile_planes": estimate_slip(
            cb.xyz[kb], ca.xyz[ka], tr, tile_size_m=TILE, **kw
        ).components(),
        "tiles": estimate_slip(
            cb.xyz[kb], ca.xyz[ka], tr, tile_size_m=TILE, combine="tiles", **kw
        ).components(),
    }


# --------------------------------------------------------------------------- finding 7

#: output name -> the core's component (SlipResult.components) it is made from
CORE_KEYS = {
    "right_lateral_slip": "right_lateral_slip",
    "sigma_right_lateral": "sigma_fault_parallel",
    "opening": "fault_normal",
    "dz": "dz",
}


def test_tile_size_does_not_change_the_headline(files, core_refs, tmp_path, capsys):
    """The tile size asks for a map: the headline stays the whole side's adjustment (equal to
    the core's untiled estimate), the tiles' own plane set is recorded beside it."""
    plain, _ = _run(files, tmp_path / "plain", capsys)
    tiled, err = _run(files, tmp_path / "tiled", capsys, "--tile-size", f"{TILE:g}")
    whole, tp = core_refs["whole"], core_refs["tile_planes"]
    # the outputs' names (docs/methods.md, sign convention) against the core's components
    for key, core in CORE_KEYS.items():
        assert tiled["relative"][key] == pytest.approx(plain["relative"][key], rel=1e-12, abs=0)
        assert plain["relative"][key] == pytest.approx(whole[core], rel=1e-9, abs=1e-12)
        assert tiled["tile_planes_estimate"][key] == pytest.approx(tp[core], rel=1e-9, abs=1e-12)
    assert tiled["relative"]["right_lateral_slip"] == pytest.approx(SLIP, abs=0.003)
    assert tiled["tiles"] and tiled["parameters"]["tile_size_m"] == TILE
    assert "tile_planes_estimate" not in plain
    assert "map beside it" in tiled["headline"] and "do not change it" in tiled["headline"]
    assert "tiles" not in plain["headline"]
    assert tiled["headline"] in err  # the log says it in the same words
    html = (tmp_path / "tiled" / "report.html").read_text(encoding="utf-8")
    assert "map beside it" in html


def test_combine_tiles_is_a_different_estimate_and_says_so(files, core_refs, tmp_path, capsys):
    js, err = _run(files, tmp_path / "comb", capsys, "--tile-size", f"{TILE:g}", "--combine",
                   "tiles")  # fmt: skip
    ref = core_refs["tiles"]
    for key in ("right_lateral_slip", "sigma_right_lateral"):
        assert js["relative"][key] == pytest.approx(ref[CORE_KEYS[key]], rel=1e-9, abs=1e-12)
    assert "information-weighted mean" in js["headline"]
    assert "different estimate" in js["headline"] and js["headline"] in err
    assert "tile_planes_estimate" not in js  # the headline is the tiles' own estimate


def test_unused_settings_are_worded_as_each_face_names_them():
    from slipmap.app import slip

    opts = {"strip_width_m": 50.0, "window_size_m": 40.0}
    notes = slip.unused_settings(opts, ["tiles"])
    qgis = [slip.SPEC.render_error(n, "qgis") for n in notes]
    assert qgis == [
        '"Strip width (m)": is set but no "Strips" output is asked for: the strips go only '
        'into the summary JSON and the report; ask for "Strips" to get the layer',
        '"Moving-window size (m)": is set but no "Moving windows" output is asked for: no '
        'windows are computed; ask for "Moving windows" to get them',
    ]
    assert slip.unused_settings(opts, ["strips", "windows"]) == []
    assert slip.unused_settings({}, []) == []


# --------------------------------------------------------------------------- finding 10


def test_record_names_the_fault_file_and_only_the_settings_in_effect(files, tmp_path, capsys):
    _, _, fault = files
    js, _ = _run(files, tmp_path / "rec", capsys)
    prm = js["parameters"]
    assert prm["fault"] == str(fault)
    assert prm["point_accuracy"] == {
        "before": {"model": "constant", "sigma": 0.02},
        "after": {"model": "constant", "sigma": 0.02},
    }
    html = (tmp_path / "rec" / "report.html").read_text(encoding="utf-8")
    assert "fault.geojson" in html and "(layer)" not in html
    for word in ("scanner", "footprint", "sigma_xyz"):
        assert word not in html
    axis, _ = _run(files, tmp_path / "axis", capsys, "--sigma-xyz", "0.01", "0.01", "0.03")
    assert axis["parameters"]["point_accuracy"]["before"] == {
        "model": "axis",
        "sigma_xyz": [0.01, 0.01, 0.03],
    }


def test_settings_in_effect_per_model():
    from slipmap.app.pointaccuracy import settings_in_effect

    dialog = {"scanner": "leica-als60", "footprint": True, "sigma_xyz": None}
    assert settings_in_effect({"model": "constant", **dialog}) == {
        "model": "constant",
        "sigma": 0.05,
    }
    static = {"model": "propagated", "scanner": "riegl-vz400", "scanner_position": [1, 2, 3],
              "trajectory": "t.sbet", "sigma": 0.02}  # fmt: skip
    assert settings_in_effect(static) == {
        "model": "propagated",
        "scanner": "riegl-vz400",
        "scanner_position": [1, 2, 3],
        "footprint": True,
    }
    assert settings_in_effect({"model": "columns", "scanner": "x"}) == {
        "model": "columns",
        "columns": ["SigmaX", "SigmaY", "SigmaZ"],
    }


def test_a_crs_given_by_the_user_draws_no_warning_about_the_files(tmp_path, caplog):
    """Files declaring EPSG:4326 for UTM coordinates: one warning per file when read as they
    are; none when the user gives the CRS (the answer to that warning)."""
    from slipmap.app.inputs import read_epoch_pair

    rng = np.random.default_rng(3)
    paths = []
    for name in ("b", "a"):
        xyz = np.array(ORIGIN) + rng.uniform(0, 10, (100, 3))
        p = tmp_path / f"{name}.las"
        write_las(p, PointCloud(xyz=xyz, attributes={}, crs=pyproj.CRS.from_epsg(4326)))
        paths.append(p)

    def warnings():
        return [r for r in caplog.records if "give the correct CRS explicitly" in r.getMessage()]

    with caplog.at_level(logging.INFO, logger="slipmap"):
        read_epoch_pair(*paths)
    assert len(warnings()) == 2
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="slipmap"):
        pair = read_epoch_pair(*paths, crs="EPSG:32610")
    assert warnings() == [] and pair.crs.to_epsg() == 32610


def test_an_output_under_a_file_says_it_is_a_file(tmp_path):
    from slipmap.app.options import OptionError
    from slipmap.app.outputs import OutputPlan

    (tmp_path / "slip.json").write_text("{}")
    plan = OutputPlan.for_outputs(
        inputs={}, outputs={"summary": tmp_path / "slip.json" / "out.json"}, default_names={}
    )
    with pytest.raises(OptionError) as e:
        plan.check()
    assert e.value.key == "summary"
    assert "slip.json' is a file, not a folder" in e.value.text
    assert "does not exist" not in e.value.text


# --------------------------------------------------------------------------- finding 11


def test_the_log_holds_one_summary_line_per_side(files, tmp_path, capsys):
    _, err = _run(files, tmp_path / "log", capsys, "--tile-size", "25")
    lines = err.splitlines()
    assert not [x for x in lines if "surface-like nodes" in x]  # per-piece details: DEBUG
    assert not [x for x in lines if " / " in x and "planes matched" in x]
    assert "{'" not in err and '{"' not in err  # no Python dict or JSON in the log
    for side in ("left", "right"):
        whole = [x for x in lines if x.startswith(f"{side} side: ") and "planes before" in x]
        assert len(whole) == 1, whole
        assert "point spacing" in whole[0] and "matched" in whole[0]
        tiles = [x for x in lines if x.startswith(f"{side} side: ") and "tiles of 25 m" in x]
        assert len(tiles) == 1, tiles
        m = re.search(
            r"(\d+) tiles of 25 m, (\d+) matched planes; (\d+) adjusted(, (\d+) skipped: .+)?$",
            tiles[0],
        )
        assert m, tiles[0]
        n, adjusted, skipped = int(m[1]), int(m[3]), int(m[5] or 0)
        assert n == adjusted + skipped and adjusted >= 1


def test_skipped_tiles_and_cells_in_words():
    from slipmap.core.displacement import skipped_text
    from slipmap.core.icp import skipped_cells_text

    statuses = [
        "ok",
        "skipped: no planes (2 / 40 points in the two epochs)",
        "skipped: 2 matched planes (need 3)",
        "skipped: 1 matched planes (need 3)",
        "skipped: singular displacement covariance",
    ]
    assert skipped_text(statuses) == (
        "4 skipped: 1 with no planes, 2 with fewer than 3 matched planes, 1 with no regular "
        "adjustment"
    )
    assert skipped_text(["ok"]) == ""
    cells = {"few_after_points": 1, "few_before_points": 0, "icp_failed": 2}
    assert skipped_cells_text(cells) == (
        ", 3 skipped (1 too few points in the second epoch; 2 no usable ICP fit)"
    )
    assert skipped_cells_text({"few_after_points": 0}) == ""
