"""The stochastic-model options shared by the faces (``slipmap.app.stochasticmodel``): fixed
components, acquisition units from PointSourceId and GPS time; known answers, no files."""

import logging

import numpy as np
import pytest

from slipmap.app import stochasticmodel as sm
from slipmap.core.errors import InputDataError, InvalidParameterError


def test_vocabulary_equals_the_core():
    from slipmap.core import stochastic

    assert sm.MODELS == stochastic.STOCHASTIC_MODELS
    assert sm.DEFAULT_MODEL == stochastic.DEFAULT_STOCHASTIC_MODEL
    assert sm.COMPONENTS == stochastic.COMPONENT_NAMES + ("spatial_range_m",)
    assert set(sm.MODEL_HELP) == set(sm.MODELS)


@pytest.mark.parametrize(
    "value, expected",
    [
        (None, {}),
        ("", {}),
        ("plane=0.002", {"plane": 0.002}),
        (" plane = 0.002 , spatial_range_m=40 ", {"plane": 0.002, "spatial_range_m": 40.0}),
        (["unit_before=0.003", "unit_after=0"], {"unit_before": 0.003, "unit_after": 0.0}),
        ({"spatial": "0.001", "unit_after": 0.004}, {"spatial": 0.001, "unit_after": 0.004}),
    ],
)
def test_parse_fixed_components(value, expected):
    assert sm.parse_fixed_components(value, option="--fixed-component") == expected


@pytest.mark.parametrize(
    "value, words",
    [
        ("plane", ("NAME=SIGMA_M",)),
        ("=0.1", ("NAME=SIGMA_M",)),
        ("strip=0.1", ("unknown component 'strip'", "unit_before")),
        ("plane=x", ("plane must be a number",)),
        ("plane=-1e-3", (">= 0",)),
        ("plane=inf", ("finite",)),
        ("spatial_range_m=0", ("> 0",)),
        ("plane=1,plane=2", ("plane is given twice",)),
        ({"plane": None}, ("plane must be a number",)),
        ([3], ("NAME=SIGMA_M",)),
    ],
)
def test_bad_fixed_components_name_the_option(value, words):
    with pytest.raises(InvalidParameterError) as raised:
        sm.parse_fixed_components(value, option="OPT")
    text = str(raised.value)
    assert text.startswith("OPT: ")
    for w in words:
        assert w in text, text


def test_gps_time_segments_known_answer():
    t = np.array([10.0, 0.5, 3.0, 0.0, 3.2, 0.9, 10.4, 4.1])
    np.testing.assert_array_equal(sm.gps_time_segments(t, 1.0), [2, 0, 1, 0, 1, 0, 2, 1])
    # a jump of exactly the gap does not split
    np.testing.assert_array_equal(sm.gps_time_segments([0.0, 1.0, 2.5], 1.0), [0, 0, 1])
    np.testing.assert_array_equal(sm.gps_time_segments(t, 100.0), np.zeros(8))
    assert sm.gps_time_segments([], 1.0).shape == (0,)
    with pytest.raises(InvalidParameterError, match="gap"):
        sm.gps_time_segments(t, 0.0)
    with pytest.raises(InputDataError, match="NaN"):
        sm.gps_time_segments([0.0, np.nan], 1.0)


def test_epoch_units_auto():
    psid = np.array([4, 4, 7, 7, 7], dtype=np.uint16)
    u = sm.epoch_units("auto", point_source_id=psid, gps_time=None)
    assert u.source == "PointSourceId" and u.n_units == 2
    np.testing.assert_array_equal(u.units, psid)
    one = sm.epoch_units("auto", point_source_id=np.zeros(5, np.uint16))
    assert one.units is None and one.source == "none" and "single value" in one.note
    missing = sm.epoch_units("auto", gps_time=np.arange(5.0))  # auto never uses GpsTime
    assert missing.units is None and "no PointSourceId" in missing.note
    assert sm.epoch_units("none", point_source_id=psid).units is None


def test_epoch_units_explicit(caplog):
    t = np.array([0.0, 0.1, 5.0, 5.2])
    u = sm.epoch_units("GpsTime", gps_time=t, gap_s=1.0)
    assert u.source == "GpsTime" and u.n_units == 2
    np.testing.assert_array_equal(u.units, [0, 0, 1, 1])
    assert u.to_dict() == {"source": "GpsTime", "n_units": 2, "gps_time": False}
    with caplog.at_level(logging.WARNING, logger="slipmap"):
        single = sm.epoch_units("PointSourceId", point_source_id=np.ones(4, np.uint16))
    assert single.n_units == 1 and "not estimable" in single.note
    assert "not estimable" in caplog.text
    spelling = {"GpsTime": "gps-time", "PointSourceId": "point-source-id"}
    with pytest.raises(InvalidParameterError) as raised:
        sm.epoch_units(
            "GpsTime", point_source_id=np.ones(3), epoch="after epoch (b.las)",
            option="--units", spelling=spelling,
        )  # fmt: skip
    text = str(raised.value)
    assert text.startswith("--units gps-time: the after epoch (b.las) has no GpsTime dimension")
    assert "--units auto, point-source-id, none" in text
    with pytest.raises(InvalidParameterError, match="--units must be one of"):
        sm.epoch_units("strips", option="--units")
    with pytest.raises(InvalidParameterError, match="non-integer"):
        sm.epoch_units("PointSourceId", point_source_id=np.array([1.5, 2.0]))


def _payload(model="full"):
    comp = {
        "white": {"sigma_m": 0.0199, "sd_m": None, "source": "estimated", "variance_factor": 0.99},
        "plane": {"sigma_m": 0.0012, "sd_m": 0.0003, "source": "estimated"},
        "spatial": {"sigma_m": 0.0025, "sd_m": 0.0006, "source": "estimated"},
        "unit_before": {"sigma_m": 0.004, "sd_m": None, "source": "prior", "note": "few <units>"},
        "unit_after": {"sigma_m": 0.0, "sd_m": None, "source": "off", "note": "no units"},
    }
    side = {
        "n_planes": 20,
        "stochastic_model": model,
        "rejected_planes": [{"plane": 3, "reason": "w-test |w| = 6.1 > 4.2"}],
        "downweighted_planes": [{"plane": 5, "weight": 0.4, "reason": "IGG-III"}],
    }
    if model != "white":
        side["variance_components"] = {
            "components": comp,
            "n_planes": 20,
            "n_eff": 12.345,
            "spatial_range_m": 31.6,
            "notes": [],
        }
    rel = {  # the sign convention (app/signs.py)
        "right_lateral": 0.01586,
        "sigma_right_lateral": 0.00285,
        "opening": 0.00006,
        "sigma_opening": 0.0029,
        "dz": 0.00368,
        "sigma_dz": 0.00306,
        "right_lateral_slip": 0.01586,
    }
    if model != "white":
        rel.update(sigma_right_lateral_white=0.000142, sigma_dz_white=0.000338)
    return {
        "relative": rel,
        "left": side,
        "right": dict(side),
        "fault": {"strike_deg": 0.0, "left_side": "west", "right_side": "east"},
        "parameters": {
            "stochastic_model": model,
            "acquisition_unit_sources": {
                "units_option": "auto",
                "before": {"source": "PointSourceId", "n_units": 5},
                "after": {"source": "none", "n_units": 0, "note": "auto: single value"},
            },
        },
    }


def test_slip_summary_lines_known_answer():
    from slipmap.app.summaries import slip_summary_lines

    lines = slip_summary_lines(_payload())
    assert lines[0] == (
        "relative motion of the right (east) side against the left (west) side, "
        "stochastic model full:"
    )
    assert lines[1] == (
        "  right-lateral    +15.86 ± 2.85 mm   (white noise only ± 0.14 mm)   (+ = dextral)"
    )
    assert lines[2] == "  opening           +0.06 ± 2.90 mm   (+ = apart)"
    assert lines[3] == (
        "  dz                +3.68 ± 3.06 mm   (white noise only ± 0.34 mm)   (+ = east side up)"
    )
    assert lines[4] == "  right-lateral slip +15.86 ± 2.85 mm"
    assert lines[5] == (
        "  left side: 20 planes, n_eff 12.3; white 19.90 mm (estimated, σ0² 0.99); "
        "plane 1.20 mm (sd 0.30, estimated); spatial 2.50 mm (sd 0.60, estimated, range 32 m); "
        "unit_before 4.00 mm (prior); unit_after off"
    )
    white = slip_summary_lines(_payload("white"))
    assert len(white) == 5 and "white noise only" not in " ".join(white)


def test_stochastic_tables_and_html(tmp_path):
    from slipmap.app.report import write_html_report
    from slipmap.app.summaries import stochastic_tables

    tables = stochastic_tables(_payload())
    head = tables["Stochastic model"]
    assert head["model"] == "full"
    assert head["σ right-lateral (mm)"] == pytest.approx(2.85)
    assert head["σ right-lateral, white noise only (mm)"] == pytest.approx(0.142)
    assert head["left: n_eff"] == pytest.approx(12.345)
    assert head["acquisition units, before"] == "5 from PointSourceId"
    assert head["acquisition units, after"] == "auto: single value"
    rows = tables["Stochastic model: components per side"]
    assert len(rows) == 10 and rows[3]["component"] == "unit_before"
    assert rows[3]["σ (mm)"] == pytest.approx(4.0) and rows[3]["sd (mm)"] is None
    planes = tables["Rejected and down-weighted planes"]
    assert [(p["side"], p["plane"], p["status"], p["weight"]) for p in planes] == [
        ("left", 3, "rejected", 0.0),
        ("left", 5, "down-weighted", 0.4),
        ("right", 3, "rejected", 0.0),
        ("right", 5, "down-weighted", 0.4),
    ]
    html = write_html_report(tmp_path / "r.html", "t", tables, []).read_text()
    assert "<th>side</th><th>component</th><th>σ (mm)</th><th>sd (mm)</th>" in html
    assert "few &lt;units&gt;" in html  # escaped
    assert "<td>4</td><td></td>" in html  # None is an empty cell
    white = stochastic_tables(_payload("white"))
    assert "Stochastic model: components per side" not in white
    assert "σ right-lateral, white noise only (mm)" not in white["Stochastic model"]


def test_a_turning_unit_is_named_with_its_turn_and_lever():
    """A unit component with a lever (core.stochastic UNIT_LEVERS_M) says how much the unit
    turns: 4 mm over a 40 m lever is 0.1 mrad per axis; the table names the lever."""
    from slipmap.app.summaries import component_text, side_component_line, stochastic_tables

    comp = {"sigma_m": 0.004, "source": "estimated"}
    assert component_text("unit_before", comp, lever_m=40.0) == (
        "unit_before 4.00 mm (estimated, turning 0.100 mrad about its origin (lever 40 m))"
    )
    assert "turning" not in component_text("unit_before", comp)
    assert "turning" not in component_text("plane", comp, lever_m=40.0)
    payload = _payload()
    payload["left"]["variance_components"]["unit_turn_lever_m"] = 60.0
    line = side_component_line("left", payload["left"])
    assert "unit_before 4.00 mm (prior, turning 0.067 mrad about its origin (lever 60 m))" in line
    head = stochastic_tables(payload)["Stochastic model"]
    assert head["left: unit turn lever (m; empty: units translate only)"] == 60.0
    head = stochastic_tables(_payload())["Stochastic model"]
    assert "left: unit turn lever (m; empty: units translate only)" not in head


def test_a_wave_field_is_named_with_its_family_and_wavelength():
    """The spatial term of the horizontal wave (core.stochastic "wave_h") reads as waves of
    the map position and their wavelength, in the console line and the table; the spherical
    one keeps its range and no family row."""
    from slipmap.app.summaries import component_text, side_component_line, stochastic_tables

    comp = {"sigma_m": 0.0042, "source": "estimated"}
    assert component_text("spatial", comp, 45.0, family="wave_h") == (
        "spatial 4.20 mm (estimated, waves of the map position, wavelength 45 m)"
    )
    assert component_text("spatial", comp, 45.0, family="spherical") == (
        "spatial 4.20 mm (estimated, range 45 m)"
    )
    payload = _payload()
    vc = payload["left"]["variance_components"]
    vc.update(spatial_range_m=45.0, spatial_family="wave_h")
    vc["components"]["spatial"] = dict(comp)
    line = side_component_line("left", payload["left"])
    assert "waves of the map position, wavelength 45 m" in line
    head = stochastic_tables(payload)["Stochastic model"]
    assert head["left: spatial family (range: its wavelength)"] == "wave_h"
    head = stochastic_tables(_payload())["Stochastic model"]
    assert "left: spatial family (range: its wavelength)" not in head


def test_every_wavelength_family_has_a_name_and_the_others_keep_a_range():
    """Every family whose range is a wavelength in core (WAVELENGTH_FAMILIES) has a console
    name; an exponential field reads as its family and range, and its table row does not
    call the range a wavelength."""
    from slipmap.app.summaries import WAVE_FAMILIES, component_text, stochastic_tables
    from slipmap.core.stochastic import SPATIAL_FAMILIES, WAVELENGTH_FAMILIES

    assert set(WAVE_FAMILIES) == set(WAVELENGTH_FAMILIES) <= set(SPATIAL_FAMILIES)
    comp = {"sigma_m": 0.0042, "source": "estimated"}
    assert component_text("spatial", comp, 27.0, family="exponential") == (
        "spatial 4.20 mm (estimated, exponential, range 27 m)"
    )
    payload = _payload()
    payload["left"]["variance_components"].update(
        spatial_range_m=27.0, spatial_family="exponential"
    )
    head = stochastic_tables(payload)["Stochastic model"]
    assert head["left: spatial family"] == "exponential"
    assert "left: spatial family (range: its wavelength)" not in head
