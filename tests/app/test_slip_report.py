"""The slip report leads with the result in mm with its σ and model, lists the inputs and
settings, and gives every value with its unit (issue #19: the report as geodesists read it)."""

import pyproj
import pytest

from slipmap.app.slip import report_tables


def _payload(model="full"):
    rel = {  # the sign convention (app/signs.py): right_lateral + = dextral
        "right_lateral_slip": 0.0181,
        "right_lateral": 0.0181,
        "sigma_right_lateral": 0.0004,
        "dx": 0.001,
        "sigma_dx": 0.0005,
        "dz": -0.002,
        "sigma_dz": 0.0006,
    }
    if model != "white":
        rel["sigma_right_lateral_white"] = 0.0001
    side = {"dx": 0.002, "rx": 1.5e-5, "n_planes": 22, "n_points": 1000, "variance_factor": 0.97}
    return {
        "relative": rel,
        "left": side,
        "right": dict(side, n_points=900),
        "fault": {"strike_deg": 0.0, "left_side": "west", "right_side": "east"},
        "parameters": {
            "before": "/data/epochs/before.laz",
            "after": "/data/epochs/after.laz",
            "fault": "/data/fault.gpkg",
            "buffer_m": 10.0,
            "combine": "joint",
            "stochastic_model": model,
            "acquisition_unit_sources": {"units_option": "auto"},
            "point_accuracy": {"before": {"model": "constant", "sigma": 0.02}},
        },
    }


def test_lead_is_the_slip_in_mm_with_sigma_and_model():
    lead, _ = report_tables(_payload())
    assert lead.startswith(
        "Right-lateral slip +18.10 ± 0.40 mm (1σ, full model); white noise alone would claim "
        "± 0.10 mm. Signs: + right-lateral = dextral; + opening = the sides move apart; "
        "relative dz + = east side up (the right (east) side of the trace as digitised)"
    )
    lead, _ = report_tables(_payload("white"))
    assert lead.startswith("Right-lateral slip +18.10 ± 0.40 mm (1σ, white model). Signs: ")


def test_tables_carry_units_inputs_and_settings():
    _, tables = report_tables(_payload(), pyproj.CRS.from_epsg(32610))
    res = tables["Result: relative motion of the right (east) side against the left (west) side"]
    assert res["right-lateral (mm, + = dextral)"] == pytest.approx(18.1)
    assert res["σ right-lateral (mm)"] == pytest.approx(0.4)
    assert res["dz (mm, + = east side up)"] == pytest.approx(-2.0)
    assert all("(" in k for k in res)  # every motion row names its unit
    assert not [k for k in res if "fault" in k]
    left = tables["Left (west) side: after against before"]
    assert left["rx (mrad)"] == pytest.approx(0.015) and left["points"] == 1000
    inputs = tables["Inputs"]
    assert inputs["before epoch"] == "before.laz" and inputs["fault trace"] == "fault.gpkg"
    assert inputs["CRS"] == "WGS 84 / UTM zone 10N"
    assert inputs["points used, right (east) side (both epochs)"] == 900
    settings = tables["Settings"]
    assert settings["buffer around the trace (m)"] == 10.0
    assert settings["point accuracy, before"] == "model constant, sigma 0.02"


def test_html_report_shows_the_lead_first(tmp_path):
    pytest.importorskip("numpy")
    from slipmap.app.report import write_html_report

    lead, tables = report_tables(_payload())
    path = write_html_report(tmp_path / "r.html", "SlipMap fault slip", tables, [], lead=lead)
    text = path.read_text(encoding="utf-8")
    assert text.index("Right-lateral slip +18.10 ± 0.40 mm") < text.index("<table>")
    assert "e-0" not in text  # numbers for reading, no exponent
