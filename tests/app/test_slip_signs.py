"""One sign convention across every output of a fault-slip run (issue #28, finding 4).

A synthetic fault pair with known dextral slip split over both sides (the west side moves
8 mm north and 2 mm west, the east side 10 mm south, 3 mm east and 4 mm up: 18 mm of
right-lateral slip, 5 mm of opening, the east side 4 mm up) runs once through the command
line with tiles, strips and moving windows; every output is read back from disk
(displacement.json, the GeoPackage layers through OGR, windows.tif through GDAL, the report's
tables, the strip-profile PNG's text chunk, the console lines) and must read + right-lateral,
with a left and a right value adding up to the relative one within their σ. The same run with
the trace digitised the other way must give the same right-lateral and opening everywhere,
and only the values the convention ties to the digitised direction change: the relative dx,
dy, dz (right minus left) change sign, and the report names the other side as "up".
"""

import contextlib
import io
import json
import math
import re
from html.parser import HTMLParser

import numpy as np
import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.io.las import PointCloud, write_las
from slipmap.core.synthetic import make_fault_pair

ogr = pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")
gdal = pytest.importorskip("osgeo.gdal", reason="GDAL (python3-gdal) missing")
pytest.importorskip("matplotlib", reason="the report's figures need matplotlib")

ORIGIN = (498000.0, 4234000.0, 20.0)
UTM10 = pyproj.CRS.from_epsg(32610)
#: the truth: each side's own motion (east, north, up), metres; the trace strikes north
WEST = np.array([-0.002, 0.008, 0.0])
EAST = np.array([0.003, -0.010, 0.004])
#: in the convention: right_lateral, opening, dz of each side and of the slip (east - west)
TRUTH = {
    "west": {"right_lateral": 0.008, "opening": 0.002, "dz": 0.0},
    "east": {"right_lateral": 0.010, "opening": 0.003, "dz": 0.004},
    "relative": {"right_lateral": 0.018, "opening": 0.005, "dz": 0.004},
}
SIGNED = ("right_lateral", "opening")
SIGMA_SCALE = 4.0  # |estimate - truth| within 4 σ (plus 1 mm for the scene's own bias)
SLACK = 0.001


def _run(paths, fault, out):
    """The CLI run; its console (stderr: the summary lines) as lines."""
    argv = ["displacement", str(paths["before"]), str(paths["after"]), "--fault", str(fault)]
    argv += ["--out", str(out), "--sigma", "0.02", "--stochastic-model", "white"]
    argv += ["--tile-size", "50", "--strip-width", "50", "--window-size", "50"]
    argv += ["--window-step", "25"]
    console = io.StringIO()
    with contextlib.redirect_stderr(console):  # the CLI's log handler writes to sys.stderr
        rc = main(argv)
    assert rc == 0, console.getvalue()
    return console.getvalue().splitlines()


@pytest.fixture(scope="module")
def runs(tmp_path_factory, line_file):
    """Both epochs, the trace digitised north and south, and the two runs' folders and
    console lines."""
    d = tmp_path_factory.mktemp("signs")
    fp = make_fault_pair(
        "mls",
        seed=7,
        origin=ORIGIN,
        left_offset_m=WEST,
        right_offset_m=EAST,
        density_pts_m2=25.0,
        vegetation=False,
    )
    assert fp.trace_xy[1, 1] > fp.trace_xy[0, 1]  # digitised northwards: the east is right
    paths = {}
    for name, sc in (("before", fp.before), ("after", fp.after)):
        p = d / f"{name}.laz"
        write_las(p, PointCloud(sc.points, {"Classification": sc.classification}, crs=UTM10))
        paths[name] = p
    north, south = d / "north.gpkg", d / "south.gpkg"
    line_file(north, fp.trace_xy, UTM10)
    line_file(south, fp.trace_xy[::-1], UTM10)
    out = {}
    for name, fault in (("north", north), ("south", south)):
        out[name] = {"folder": d / name, "lines": _run(paths, fault, d / name)}
    out["trace_x"] = float(fp.trace_xy[0, 0])
    return out


# --------------------------------------------------------------------------- readers


def _json(run):
    return json.loads((run["folder"] / "displacement.json").read_text())


def _keys(obj):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield k
            yield from _keys(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _keys(v)


def _layer(run, name):
    """(x, y, attributes) of every feature of a GeoPackage layer, through OGR."""
    ds = ogr.Open(str(run["folder"] / "displacement.gpkg"))
    layer = ds.GetLayerByName(name)
    defn = layer.GetLayerDefn()
    fields = [defn.GetFieldDefn(i).GetName() for i in range(defn.GetFieldCount())]
    rows = []
    for f in layer:
        c = f.GetGeometryRef().Centroid()
        attrs = {k: f.GetField(k) for k in fields}
        rows.append((round(c.GetX(), 3), round(c.GetY(), 3), attrs))
    return fields, rows


def _windows(run):
    ds = gdal.Open(str(run["folder"] / "windows.tif"))
    names = [ds.GetRasterBand(i + 1).GetDescription() for i in range(ds.RasterCount)]
    bands = {n: ds.GetRasterBand(i + 1).ReadAsArray() for i, n in enumerate(names)}
    gt = ds.GetGeoTransform()
    ny, nx = bands[names[0]].shape
    x = gt[0] + gt[1] * (np.arange(nx) + 0.5)
    return names, bands, np.broadcast_to(x, (ny, nx)), ds.GetMetadata()


class _Tables(HTMLParser):
    """{caption or heading: {first cell: second cell}} of an HTML report."""

    def __init__(self):
        super().__init__()
        self.tables, self.title, self.row, self.cell, self.text = {}, None, None, None, ""

    def handle_starttag(self, tag, attrs):
        if tag in ("h2", "h3", "caption", "td", "th"):
            self.text = ""
        if tag == "tr":
            self.row = []

    def handle_endtag(self, tag):
        if tag in ("h2", "h3", "caption"):
            self.title = self.text.strip()
        elif tag in ("td", "th") and self.row is not None:
            self.row.append(self.text.strip())
        elif tag == "tr" and self.row:
            if len(self.row) >= 2:
                self.tables.setdefault(self.title, {})[self.row[0]] = self.row[1]
            self.row = None

    def handle_data(self, data):
        self.text += data


def _report(run):
    html = (run["folder"] / "report.html").read_text(encoding="utf-8")
    p = _Tables()
    p.feed(html)
    return html, p.tables


def _number(text):
    return float(text.replace("−", "-").replace("+", ""))


def _close(value, truth, sigma):
    return abs(value - truth) <= SIGMA_SCALE * sigma + SLACK


# --------------------------------------------------------------------------- one run


def test_json_reads_right_lateral_positive_and_the_sides_add_up(runs):
    js = _json(runs["north"])
    assert not [k for k in _keys(js) if "fault_parallel" in k or "fault_normal" in k]
    rel = js["relative"]
    assert rel["right_lateral_slip"] == rel["right_lateral"] > 0
    for key in ("right_lateral", "opening", "dz"):
        assert _close(rel[key], TRUTH["relative"][key], rel[f"sigma_{key}"]), key
    assert js["fault"]["right_side"] == "east" and js["fault"]["left_side"] == "west"
    assert "right-lateral" in js["fault"]["sign_convention"]
    for side, where in (("left", "west"), ("right", "east")):
        s = js[side]
        for key in ("right_lateral", "opening"):
            assert _close(s[key], TRUTH[where][key], s[f"sigma_{key}"]), (side, key)
        assert s["right_lateral"] > 0
    for key in SIGNED:  # the two sides' own motions add up to the slip (the same adjustment)
        assert js["left"][key] + js["right"][key] == pytest.approx(rel[key], abs=1e-12)
        assert math.hypot(js["left"][f"sigma_{key}"], js["right"][f"sigma_{key}"]) == pytest.approx(
            rel[f"sigma_{key}"], rel=1e-9
        )
    assert js["right"]["dz"] - js["left"]["dz"] == pytest.approx(rel["dz"], abs=1e-12)
    tiles = [t for t in js["tiles"] if t["status"] == "ok"]
    strips = [s for s in js["strips"] if s["status"] == "ok"]
    assert len({t["side"] for t in tiles}) == 2 and len({s["side"] for s in strips}) == 2
    for row in tiles + strips:
        where = "west" if row["side"] == "left" else "east"
        for key in ("right_lateral", "opening", "dz"):
            assert _close(row[key], TRUTH[where][key], row[f"sigma_{key}"]), (row, key)


def _weighted(rows, side, key):
    v = np.array([r[key] for r in rows if r["side"] == side and r[key] is not None])
    s = np.array([r[f"sigma_{key}"] for r in rows if r["side"] == side and r[key] is not None])
    w = 1.0 / s**2
    return float(np.sum(w * v) / np.sum(w)), float(1.0 / math.sqrt(np.sum(w)))


def test_geopackage_tiles_and_strips_read_right_lateral_and_add_up(runs):
    rel = _json(runs["north"])["relative"]
    for name in ("tiles", "strips"):
        fields, rows = _layer(runs["north"], name)
        assert {"right_lateral", "sigma_right_lateral", "opening", "sigma_opening"} <= set(fields)
        assert {"dz", "sigma_dz", "dx", "dy"} <= set(fields)
        assert not [f for f in fields if "fault" in f or f in ("sigma_fp", "sigma_fn")]
        attrs = [a for _, _, a in rows if a["status"] == "ok"]
        for key in SIGNED:
            (lv, ls), (rv, rs) = (_weighted(attrs, s, key) for s in ("left", "right"))
            assert lv > 0 if key == "right_lateral" else True
            assert rv > 0 if key == "right_lateral" else True
            # each side's mean against its truth, and the two means add up to the slip
            assert _close(lv, TRUTH["west"][key], ls), (name, key, lv)
            assert _close(rv, TRUTH["east"][key], rs), (name, key, rv)
            total = math.hypot(ls, rs) + rel[f"sigma_{key}"]
            assert _close(lv + rv, rel[key], total), (name, key)


def test_windows_band_right_lateral_is_positive_on_both_sides(runs):
    names, bands, x, meta = _windows(runs["north"])
    assert names[0] == "right_lateral_m" and "sigma_right_lateral_m" in names
    assert not [n for n in names if "fault" in n]
    assert "right-lateral" in meta["SLIPMAP_SIGN_CONVENTION"]
    rl, sig = bands["right_lateral_m"], bands["sigma_right_lateral_m"]
    ok = np.isfinite(rl)
    west, east = ok & (x < runs["trace_x"]), ok & (x > runs["trace_x"])
    assert west.sum() >= 3 and east.sum() >= 3
    for mask, where in ((west, "west"), (east, "east")):
        assert np.all(
            np.abs(rl[mask] - TRUTH[where]["right_lateral"]) <= SIGMA_SCALE * sig[mask] + SLACK
        )
    assert np.median(rl[west]) + np.median(rl[east]) == pytest.approx(0.018, abs=0.003)
    dz = bands["dz_m"]
    assert np.nanmedian(dz[east]) == pytest.approx(0.004, abs=0.002)


def test_report_and_console_say_right_lateral_with_plus(runs):
    html, tables = _report(runs["north"])
    assert "fault-parallel" not in html and "fault-normal" not in html
    [title] = [t for t in tables if t and t.startswith("Result: relative motion")]
    assert "right (east) side against the left (west) side" in title
    result = tables[title]
    js = _json(runs["north"])["relative"]
    assert _number(result["right-lateral (mm, + = dextral)"]) == pytest.approx(
        1e3 * js["right_lateral"], abs=0.01
    )
    assert _number(result["right-lateral (mm, + = dextral)"]) > 0
    assert _number(result["dz (mm, + = east side up)"]) > 0
    assert _number(result["opening (mm, + = apart)"]) > 0
    for side, where in (("Left (west) side", "west"), ("Right (east) side", "east")):
        [t] = [t for t in tables if t and t.startswith(side)]
        value = _number(tables[t]["right-lateral (mm, + = dextral)"]) / 1e3
        sigma = _number(tables[t]["σ right-lateral (mm)"]) / 1e3
        assert value > 0 and _close(value, TRUTH[where]["right_lateral"], sigma)
    assert re.search(r"Right-lateral slip \+1[6-9]\.\d\d ± ", html)
    lines = runs["north"]["lines"]
    [rl] = [line for line in lines if line.strip().startswith("right-lateral  ")]
    assert "(+ = dextral)" in rl and _number(rl.split()[1]) > 0
    assert any("right-lateral slip +1" in line for line in lines)
    assert any("(+ = east side up)" in line for line in lines)
    for where in ("west", "east"):
        [line] = [line for line in lines if f"({where}) side moved: right-lateral +" in line]
    assert not any("fault-parallel" in line for line in lines)


def test_strip_profile_png_plots_right_lateral_up(runs):
    from PIL import Image

    text = Image.open(runs["north"]["folder"] / "strips.png").text
    desc = json.loads(text["Description"])
    assert desc["ylabel"] == "right-lateral motion (mm, + = dextral)"
    series = desc["series_mm"]
    for label, where in (("left (west) side", "west"), ("right (east) side", "east")):
        values = [v for _, v in series[label]]
        assert np.median(values) == pytest.approx(1e3 * TRUTH[where]["right_lateral"], abs=2.5)
    sums = [v for _, v in series["sum: local right-lateral slip"]]
    assert np.median(sums) == pytest.approx(18.0, abs=3.0)


# --------------------------------------------------------------------------- reversed trace


def test_reversing_the_trace_changes_no_right_lateral_or_opening(runs):
    a, b = _json(runs["north"]), _json(runs["south"])
    assert b["fault"]["right_side"] == "west" and b["fault"]["left_side"] == "east"
    for key in ("right_lateral", "right_lateral_slip", "opening"):
        assert b["relative"][key] == pytest.approx(a["relative"][key], abs=1e-9), key
    for key in ("dx", "dy", "dz"):  # right minus left: the other way round
        assert b["relative"][key] == pytest.approx(-a["relative"][key], abs=1e-9), key
    for key in SIGNED + ("dz",):  # each side's own motion: the west side stays the west side
        assert b["right"][key] == pytest.approx(a["left"][key], abs=1e-9)
        assert b["left"][key] == pytest.approx(a["right"][key], abs=1e-9)
    for name in ("tiles", "strips"):
        fa, ra = _layer(runs["north"], name)
        fb, rb = _layer(runs["south"], name)
        by_place = {(x, y, at["side"]): at for x, y, at in ra}
        flip = {"left": "right", "right": "left"}
        matched = 0
        for x, y, at in rb:
            other = by_place.get((x, y, flip[at["side"]]))
            if other is None or at["status"] != "ok":
                continue
            matched += 1
            assert other["status"] == "ok"
            for key in SIGNED + ("dz", "dx", "dy"):
                # tiles: the same points; strips are cut by chainage, which runs the other way:
                # the few points exactly on a strip boundary (LAS's 1 mm grid) change strip
                tol = 1e-7 if name == "tiles" else 0.05 * other[f"sigma_{key}"]
                assert at[key] == pytest.approx(other[key], abs=tol), (name, key)
        assert matched >= 4, name
    na, ba, _, _ = _windows(runs["north"])
    nb, bb, _, _ = _windows(runs["south"])
    assert na == nb
    for band in ("right_lateral_m", "dx_m", "dy_m", "dz_m", "sigma_right_lateral_m"):
        np.testing.assert_allclose(bb[band], ba[band], atol=1e-7, equal_nan=True)


def test_reversed_report_names_the_side_that_is_up(runs):
    _, ta = _report(runs["north"])
    _, tb = _report(runs["south"])
    [ka] = [t for t in ta if t and t.startswith("Result: relative motion")]
    [kb] = [t for t in tb if t and t.startswith("Result: relative motion")]
    assert "right (west) side against the left (east) side" in kb
    assert _number(tb[kb]["right-lateral (mm, + = dextral)"]) == pytest.approx(
        _number(ta[ka]["right-lateral (mm, + = dextral)"]), abs=0.01
    )
    east_up = _number(ta[ka]["dz (mm, + = east side up)"])
    west_up = _number(tb[kb]["dz (mm, + = west side up)"])
    assert east_up > 0 and west_up == pytest.approx(-east_up, abs=0.01)
    assert any("(+ = west side up)" in line for line in runs["south"]["lines"])


# --------------------------------------------------------------------------- the rule itself


def test_convention_known_answers():
    from slipmap.app import signs

    cov = np.diag([1e-6, 4e-6, 9e-6])
    # a north-striking trace: the east side (right) moving south is right-lateral
    m = signs.motion([0.003, -0.010, 0.004], cov, 0.0, "right")
    assert m["right_lateral"] == pytest.approx(0.010) and m["opening"] == pytest.approx(0.003)
    assert m["sigma_right_lateral"] == pytest.approx(0.002)
    assert m["sigma_opening"] == pytest.approx(0.001) and m["sigma_dz"] == pytest.approx(0.003)
    m = signs.motion([-0.002, 0.008, 0.0], cov, 0.0, "left")  # the west side moving north
    assert m["right_lateral"] == pytest.approx(0.008) and m["opening"] == pytest.approx(0.002)
    m = signs.motion([0.005, -0.018, 0.004], cov, 0.0, None)  # east minus west
    assert m["right_lateral"] == pytest.approx(0.018) and m["opening"] == pytest.approx(0.005)
    assert signs.side_names(0.0) == {"left": "west", "right": "east"}
    assert signs.side_names(180.0) == {"left": "east", "right": "west"}
    assert signs.side_names(45.0) == {"left": "north-west", "right": "south-east"}
    assert signs.side_names(None) == {}
    assert signs.dz_meaning({"right": "east"}) == "+ = east side up"


@pytest.mark.parametrize("seed", range(5))
def test_convention_is_blind_to_the_digitised_direction(seed):
    """Random strike and motions: the two sides' own values add up to the relative ones, and
    digitising the other way (strike + 180°, the sides swapped) changes no right_lateral or
    opening, while the relative dz changes sign and the right side's name."""
    from slipmap.app import signs

    rng = np.random.default_rng(seed)
    strike = rng.uniform(0, 2 * math.pi)
    d = {"a": rng.normal(0, 0.01, 3), "b": rng.normal(0, 0.01, 3)}  # a: left, b: right
    cov = np.eye(3) * 1e-6
    left = signs.motion(d["a"], cov, strike, "left")
    right = signs.motion(d["b"], cov, strike, "right")
    rel = signs.motion(d["b"] - d["a"], 2 * cov, strike, None)
    for key in SIGNED:
        assert left[key] + right[key] == pytest.approx(rel[key], abs=1e-15)
    back = strike + math.pi
    left2 = signs.motion(d["b"], cov, back, "left")
    right2 = signs.motion(d["a"], cov, back, "right")
    rel2 = signs.motion(d["a"] - d["b"], 2 * cov, back, None)
    for key in SIGNED:
        assert left2[key] == pytest.approx(right[key], abs=1e-15)
        assert right2[key] == pytest.approx(left[key], abs=1e-15)
        assert rel2[key] == pytest.approx(rel[key], abs=1e-15)
    assert rel2["dz"] == pytest.approx(-rel["dz"], abs=1e-15)
    names, names2 = (signs.side_names(math.degrees(s)) for s in (strike, back))
    assert names2 == {"left": names["right"], "right": names["left"]}
