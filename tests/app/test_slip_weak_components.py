"""No vacuous σ without a word (issue #30 item 2): a side whose planes barely face a
direction is named, with the component and the reason, in the console, the JSON and the
report's lead sentence; a survey with planes facing every way gets no such line.

The weak scene: an airborne pair (no facades) of four buildings with gable roofs pitched 4°:
the horizontal rests on the roofs' 4° tilts alone, about 0.2 % of the planes' weight, and
each side's horizontal σ comes out 20-30x its vertical one.
"""

import contextlib
import io
import json
import math

import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.synthetic import Building, make_fault_pair

pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")

ORIGIN = (498000.0, 4234000.0, 20.0)
UTM10 = pyproj.CRS.from_epsg(32610)


def _run(tmp_path, fp, name, fault_pair_files):
    d = tmp_path / name
    d.mkdir()
    paths, fault = fault_pair_files(d, fp, UTM10)
    out = d / "out"
    argv = ["displacement", *paths, "--fault", fault, "--out", str(out)]
    console = io.StringIO()
    with contextlib.redirect_stderr(console):
        rc = main(argv + ["--stochastic-model", "white"])
    assert rc == 0, console.getvalue()
    return console.getvalue(), json.loads((out / "displacement.json").read_text()), out


def test_an_airborne_pair_with_low_roofs_names_the_weak_components(tmp_path, fault_pair_files):
    pitch = math.radians(4.0)
    blds = [
        Building((x, y), 16.0, 10.0, 6.0, rotation_rad=r, roof="gable", roof_pitch_rad=pitch)
        for x, y, r in [(20, 20, 0.0), (20, 60, 1.2), (60, 20, 0.4), (60, 60, 1.9)]
    ]
    fp = make_fault_pair(
        "als", seed=3, origin=ORIGIN, right_offset_m=(0.0, -0.02, 0.0), buildings=blds,
        extent_m=80.0, vegetation=False, density_pts_m2=10.0,
    )  # fmt: skip
    console, payload, out = _run(tmp_path, fp, "weak", fault_pair_files)
    weak = payload["weak_components"]
    # both sides see roofs and ground only: both horizontal components, never dz
    assert {(w["component"], w["side"]) for w in weak} == {
        (c, s) for c in ("right_lateral", "opening") for s in ("left", "right")
    }
    for w in weak:
        assert w["sigma_m"] > 10 * w["best_sigma_m"] and w["share"] < 0.02, w
        assert w["n_planes"] >= 3
    # the vertical is still the data's: dz within 4σ of the truth with a σ of centimetres
    rel = payload["relative"]
    assert rel["sigma_dz"] < 0.05 and abs(rel["dz"]) < 4 * rel["sigma_dz"] + 1e-3
    # the console says it beside the headline, naming the side by compass direction
    lines = [x for x in console.splitlines() if "weakly determined:" in x]
    assert len(lines) == 4, console
    assert any("right-lateral slip is barely determined by the left (west) side" in x
               for x in lines), lines  # fmt: skip
    assert "% of their weight" in lines[0]
    # and the report's lead sentence
    html = (out / "report.html").read_text()
    assert "Weakly determined: The right-lateral slip is barely determined" in html


def test_a_pair_with_planes_facing_every_way_has_no_weak_component(tmp_path, fault_pair_files):
    fp = make_fault_pair(
        "mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.018, 0.0),
        density_pts_m2=25.0, vegetation=False,
    )  # fmt: skip
    console, payload, out = _run(tmp_path, fp, "strong", fault_pair_files)
    assert payload["weak_components"] == []
    assert "weakly determined" not in console
    assert "Weakly determined" not in (out / "report.html").read_text()
