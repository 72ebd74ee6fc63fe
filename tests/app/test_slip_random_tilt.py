"""The random tilt per plane (issue #30) as a user reaches it: on by default since the units'
drift along GpsTime, it reaches both sides' adjustments and is recorded in the summary;
``--no-random-tilt`` turns it off; the white model, which has no plane level to tilt,
ignores it."""

import contextlib
import io
import json

import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.synthetic import make_fault_pair

pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")

ORIGIN = (498000.0, 4234000.0, 20.0)
UTM10 = pyproj.CRS.from_epsg(32610)


def _files(tmp_path, fault_pair_files):
    fp = make_fault_pair("mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.0181, 0.0),
                         vegetation=False, extent_m=80.0)  # fmt: skip
    return fault_pair_files(tmp_path, fp, UTM10)


def _main(argv):
    console = io.StringIO()
    with contextlib.redirect_stderr(console):
        rc = main(argv)
    return rc, console.getvalue()


def test_random_tilt_reaches_the_adjustment_and_the_summary(tmp_path, fault_pair_files):
    paths, fault = _files(tmp_path, fault_pair_files)
    out = tmp_path / "out"
    rc, console = _main(["displacement", *paths, "--fault", fault, "--out", str(out),
                         "--stochastic-model", "plane", "--random-tilt"])  # fmt: skip
    assert rc == 0, console
    payload = json.loads((out / "displacement.json").read_text())
    assert payload["parameters"]["random_tilt"] is True
    for side in ("left", "right"):  # estimated on each side, reported with its source
        tilt = payload[side]["variance_components"]["random_tilt"]
        assert tilt["source"] == "estimated" and tilt["sigma_rad"] >= 0.0


def test_no_random_tilt_and_the_white_model(tmp_path, fault_pair_files):
    paths, fault = _files(tmp_path, fault_pair_files)
    for name, extra in (("off", ["--no-random-tilt"]), ("white", ["--stochastic-model", "white"])):
        out = tmp_path / name
        rc, console = _main(["displacement", *paths, "--fault", fault, "--out", str(out),
                             *extra])  # fmt: skip
        assert rc == 0, console
        payload = json.loads((out / "displacement.json").read_text())
        assert payload["parameters"]["random_tilt"] is False
        for side in ("left", "right"):
            assert "random_tilt" not in (payload[side].get("variance_components") or {})


def test_the_default_tilts_the_planes(tmp_path, fault_pair_files):
    paths, fault = _files(tmp_path, fault_pair_files)
    out = tmp_path / "default"
    rc, console = _main(["displacement", *paths, "--fault", fault, "--out", str(out)])
    assert rc == 0, console
    payload = json.loads((out / "displacement.json").read_text())
    assert payload["parameters"]["random_tilt"] is True
    for side in ("left", "right"):
        assert "random_tilt" in payload[side]["variance_components"]
