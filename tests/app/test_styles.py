"""The style of each output, fitted to its data (app/styles.py), without QGIS: every template
filled, classes and ramps symmetric about 0 over the data's range, legend labels that state
the sign convention, and the raster's .qml staged and moved in with it by the OutputPlan."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from slipmap.app import styles
from slipmap.app.outputs import OutputPlan

COLUMNS = {
    "side": np.array(["left", "right", "right"], dtype=object),
    "right_lateral": np.array([0.0004, 0.0178, 0.5]),
    "sigma_right_lateral": np.array([0.0024, 0.0034, 0.1]),
    "status": np.array(["ok", "ok", "skipped: no planes"], dtype=object),
    "dx": np.array([0.01, 0.02, 0.03]),
    "dy": np.array([0.0, -0.01, 0.2]),
    "dz": np.array([-0.012, 0.004, np.nan]),
    "sigma_dx": np.array([0.001, 0.002, 0.3]),
    "sigma_dy": np.array([0.001, 0.002, 0.3]),
    "magnitude": np.array([0.01, 0.0224, 0.202]),
    "azimuth_deg": np.array([90.0, 116.6, 171.5]),
    "valid": np.array([1, 1, 0]),
}


@pytest.mark.parametrize("name", sorted(styles.VECTOR_STYLES))
def test_every_vector_template_is_filled(name):
    qml = styles.vector_qml(styles.VECTOR_STYLES[name], COLUMNS)
    assert "{slipmap." not in qml
    ET.fromstring(qml.split("\n", 1)[1])  # still a QML document


def _rules(qml):
    root = ET.fromstring(qml.split("\n", 1)[1])
    rules = [r for r in root.iter("rule") if (r.get("description") or "").startswith("class")]
    return sorted(rules, key=lambda r: int(r.get("description").split()[1]))


def test_slip_classes_span_the_ok_values_symmetrically_with_the_sign_in_the_legend():
    rules = _rules(styles.vector_qml(styles.TILES, COLUMNS))
    assert len(rules) == 7
    # the skipped tile's 0.5 does not count: the classes span ±17.8 mm
    assert rules[0].get("filter").startswith('"right_lateral" >= -0.0178 AND')
    assert rules[-1].get("filter").endswith('"right_lateral" <= 0.0178')
    assert rules[0].get("label") == "\u221217.8 to \u221212.7 mm (\u2212 = left-lateral)"
    assert rules[3].get("label") == "\u22122.54 to +2.54 mm"  # the white class holds 0
    assert rules[-1].get("label") == "+12.7 to +17.8 mm (+ = right-lateral)"


def test_arrow_scale_and_sigma_flag_follow_the_data():
    tokens = styles.arrow_tokens(COLUMNS)
    # the 95th percentile of the magnitudes (0.184 m) rounded down to 1-2-5: 0.1 m
    assert float(tokens["arrow_mm_per_m"]) == pytest.approx(styles.ARROW_LEGEND_MM / 0.1)
    assert tokens["arrow_label"] == "scale: this arrow (6 mm) = 100 mm horizontal"
    flag = styles.sigma_tokens(COLUMNS)
    median = np.median(np.hypot(COLUMNS["sigma_dx"], COLUMNS["sigma_dy"]))
    assert float(flag["sigma_flag"]) == pytest.approx(3 * median)
    assert styles.nice_down(0.184) == pytest.approx(0.1)
    assert styles.nice_down(0.25) == pytest.approx(0.2)
    assert styles.nice_down(7.0) == pytest.approx(5.0)


def test_raster_ramp_is_symmetric_white_at_zero_with_the_ends_named():
    values = np.array([[np.nan, -0.02], [0.05, 0.01]])
    root = ET.fromstring(styles.raster_qml(styles.DZ, values).split("\n", 1)[1])
    renderer = root.find(".//rasterrenderer")
    assert renderer.get("band") == "1"
    assert float(renderer.get("classificationMin")) == pytest.approx(-0.05)
    assert float(renderer.get("classificationMax")) == pytest.approx(0.05)
    items = root.findall(".//colorrampshader/item")
    assert [float(i.get("value")) for i in items] == pytest.approx(np.linspace(-0.05, 0.05, 7))
    assert items[3].get("color") == "#f7f7f7"
    assert items[0].get("label") == "\u221250 mm (\u2212 = down)"
    assert items[-1].get("label") == "+50 mm (+ = up)"
    legend = root.find(".//rampLegendSettings")
    assert legend.get("maximumLabel") == "+50 mm (+ = up)"


def test_raster_style_is_staged_and_moved_in_with_the_raster(tmp_path):
    pytest.importorskip("osgeo.gdal")
    from slipmap.core.io.raster import write_geotiff

    out = tmp_path / "out"
    a = np.array([[0.01, -0.03]])
    with OutputPlan.for_outputs(
        inputs={}, outputs={"out": out}, default_names={"dz": "piv_dz.tif"}
    ) as plan:
        write_geotiff(plan.file("dz"), a, origin_xy=(0, 1), pixel_size_m=1.0)
        assert styles.write_raster_style(plan, "piv", "dz", a) == "piv_dz.qml"
        assert not (out / "piv_dz.qml").exists()  # staged until the run ends
    assert sorted(p.name for p in out.iterdir()) == ["piv_dz.qml", "piv_dz.tif"]
    assert 'classificationMax="0.03"' in (out / "piv_dz.qml").read_text()
    # a failed run leaves neither
    failed = tmp_path / "failed"
    with pytest.raises(RuntimeError):
        with OutputPlan.for_outputs(
            inputs={}, outputs={"out": failed}, default_names={"dz": "piv_dz.tif"}
        ) as plan:
            write_geotiff(plan.file("dz"), a, origin_xy=(0, 1), pixel_size_m=1.0)
            styles.write_raster_style(plan, "piv", "dz", a)
            raise RuntimeError("stopped")
    assert not failed.exists() or not any(failed.iterdir())


def test_every_declared_output_has_its_template():
    from slipmap.styles import style_path

    for job, outputs in styles.OUTPUT_STYLES.items():
        for key, style in outputs.items():
            for s in style.values() if isinstance(style, dict) else [style]:
                assert style_path(s.name) is not None, (job, key, s.name)
