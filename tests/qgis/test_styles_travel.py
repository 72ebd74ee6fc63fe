"""Outputs open styled wherever they are opened (issue #28, finding 3): the CLI's and the
Processing algorithms' GeoPackages carry their style in ``layer_styles``, their GeoTIFFs a
``.qml`` beside them. Each file is opened as drag and drop does (a fresh ``QgsVectorLayer`` /
``QgsRasterLayer``, default style loaded) and must show SlipMap's renderer, not QGIS's
default single symbol or multiband picture; then the maps themselves (findings 5, 6): value ±
sigma labels, sides told apart, skipped tiles drawn, an arrow scale, dz as colour."""

import math
from pathlib import Path

import numpy as np
import pyproj
import pytest
from qgis_scenes import rough_surface

pytestmark = pytest.mark.qgis

UTM12 = pyproj.CRS.from_epsg(32612)
UTM10 = pyproj.CRS.from_epsg(32610)
X0, Y0, SIDE = 512000.0, 4300000.0, 24.0
SHIFT = (0.040, -0.030, 0.020)  # true motion before -> after (m): east, north, up
OFFSET = 0.0181  # dextral slip of the fault pair (m)


@pytest.fixture(scope="module")
def field_epochs(tmp_path_factory):
    """Two samplings (64 pts/m2) of one rough surface, the second moved by SHIFT."""
    from slipmap.core.io.las import PointCloud, write_las

    d = tmp_path_factory.mktemp("style_epochs")
    rng = np.random.default_rng(5)
    n = int(64 * SIDE * SIDE)
    paths = []
    for name, (sx, sy, sz) in (("before", (0.0, 0.0, 0.0)), ("after", SHIFT)):
        xy = rng.uniform(0, SIDE, size=(n, 2)) + [X0, Y0]
        z = rough_surface(xy - [sx, sy], (X0, Y0)) + sz
        p = d / f"{name}.las"
        write_las(p, PointCloud(xyz=np.column_stack([xy, z]), crs=UTM12))
        paths.append(str(p))
    return paths


@pytest.fixture(scope="module")
def fault_epochs(tmp_path_factory):
    """The synthetic fault pair (18.1 mm dextral) and its trace as a GeoPackage."""
    from slipmap.core.io.las import PointCloud, write_las
    from slipmap.core.io.vector import VectorLayer, write_gpkg_layers
    from slipmap.core.synthetic import make_fault_pair

    d = tmp_path_factory.mktemp("style_fault")
    origin = (498000.0, 4234000.0, 20.0)
    fp = make_fault_pair("mls", seed=7, origin=origin, right_offset_m=(0.0, -OFFSET, 0.0))
    for name, sc in (("before", fp.before), ("after", fp.after)):
        attrs = {"Classification": sc.classification}
        write_las(d / f"{name}.las", PointCloud(xyz=sc.points, attributes=attrs, crs=UTM10))
    trace = d / "trace.gpkg"
    write_gpkg_layers(
        trace, [VectorLayer("trace", "LineString", [np.asarray(fp.trace_xy)])], crs=UTM10
    )
    return d, trace


def _cli(*args):
    from slipmap.cli import main

    assert main([str(a) for a in args]) == 0


@pytest.fixture(scope="module")
def cli_runs(qgis_app, field_epochs, fault_epochs, tmp_path_factory):
    """The CLI's outputs of icp, piv, dem-diff and displacement (tiles, strips, windows)."""
    before, after = field_epochs
    out = tmp_path_factory.mktemp("cli_out")
    _cli("icp", before, after, "--out", out / "icp", "--cell", 4, "--no-progress")
    _cli("piv", before, after, "--out", out / "piv", "--grid", 0.25, "--no-progress")
    _cli("dem-diff", before, after, "--out", out / "dem", "--grid", 0.5, "--no-progress")
    d, trace = fault_epochs
    _cli(
        "displacement", d / "before.las", d / "after.las", "--fault", trace,
        "--out", out / "slip", "--tile-size", 30, "--strip-width", 30,
        "--window-size", 30, "--window-step", 10,
    )  # fmt: skip
    return out


def _open_vector(path, layer):
    """As drag and drop of one layer of a GeoPackage: the provider's default style loaded."""
    from qgis.core import QgsVectorLayer

    v = QgsVectorLayer(f"{path}|layername={layer}", layer, "ogr")
    assert v.isValid(), (path, layer)
    return v


def _open_raster(path):
    from qgis.core import QgsRasterLayer

    r = QgsRasterLayer(str(path), Path(path).stem)
    assert r.isValid(), path
    return r


def _class_rules(layer):
    """The class rules (description ``class i``) of a rule-based renderer, in order."""
    from qgis.core import QgsRuleBasedRenderer

    renderer = layer.renderer()
    assert isinstance(renderer, QgsRuleBasedRenderer), (layer.name(), renderer.type())
    rules = [r for r in renderer.rootRule().descendants() if r.description().startswith("class")]
    return sorted(rules, key=lambda r: int(r.description().split()[1]))


def _limits(rule):
    """(lower, upper) of a class rule's filter ``"col" >= lo AND "col" < hi``."""
    import re

    nums = re.findall(r"[<>]=? (-?[0-9.e+-]+)", rule.filterExpression())
    return float(nums[-2]), float(nums[-1])


def _evaluate(layer, expression):
    from qgis.core import QgsExpression, QgsExpressionContext, QgsExpressionContextUtils

    expr = QgsExpression(expression)
    ctx = QgsExpressionContext(QgsExpressionContextUtils.globalProjectLayerScopes(layer))
    out = []
    for f in layer.getFeatures():
        ctx.setFeature(f)
        out.append(expr.evaluate(ctx))
    return out


def _values(layer, name):
    out = []
    for f in layer.getFeatures():
        v = f[name]
        out.append(np.nan if v is None or (hasattr(v, "isNull") and v.isNull()) else float(v))
    return np.array(out)


def _assert_symmetric_pseudocolor(raster, band=1):
    from osgeo import gdal
    from qgis.core import QgsSingleBandPseudoColorRenderer

    from slipmap.qgis_plugin.compat import renderer_band

    r = raster.renderer()
    assert isinstance(r, QgsSingleBandPseudoColorRenderer), r.type()  # not multiband/grey
    assert renderer_band(r) == band
    ds = gdal.Open(raster.source())
    a = ds.GetRasterBand(band).ReadAsArray().astype(float)
    ds = None
    m = np.nanmax(np.abs(a))
    assert (r.classificationMin(), r.classificationMax()) == pytest.approx((-m, m), rel=1e-9)
    items = r.shader().rasterShaderFunction().colorRampItemList()
    assert items[0].value == pytest.approx(-m) and items[-1].value == pytest.approx(m)
    assert items[len(items) // 2].value == pytest.approx(0, abs=1e-12)
    assert items[len(items) // 2].color.name() == "#f7f7f7"  # white at 0
    return items


# --------------------------------------------------------------------------- the CLI's files


def test_cli_icp_layers_open_styled(cli_runs):
    from slipmap.core.io.vector import read_gpkg_layer

    gpkg = next((cli_runs / "icp").glob("*.gpkg"))
    cells = _open_vector(gpkg, "cells")
    rules = _class_rules(cells)  # dz classes, symmetric about 0
    _, cols = read_gpkg_layer(gpkg, "cells")
    m = np.nanmax(np.abs(cols["dz"]))
    assert _limits(rules[0])[0] == pytest.approx(-m) and _limits(rules[-1])[1] == pytest.approx(m)
    assert "+ = up" in rules[-1].label() and "\u2212 = down" in rules[0].label()
    # value ± sigma in mm, e.g. "50 ± 3 mm" for the 50 mm horizontal shift
    assert cells.labelsEnabled()
    labels = [t for t in _evaluate(cells, cells.labeling().settings().fieldName) if t]
    value, sigma = (float(v) for v in labels[0].replace(" mm", "").split(" ± "))
    assert value == pytest.approx(1000 * math.hypot(*SHIFT[:2]), abs=10)
    assert 0 < sigma < 20
    vectors = _open_vector(gpkg, "vectors")
    labels = [r.label() for r in vectors.renderer().rootRule().children()]
    assert any(t.startswith("scale: this arrow (6 mm) = ") for t in labels), labels
    assert any(t.startswith("uncertain: horizontal \u03c3 > ") for t in labels), labels


def test_cli_rasters_open_styled(cli_runs):
    for path, band, ends in (
        (cli_runs / "piv" / "piv_dz.tif", 1, ("down", "up")),
        (cli_runs / "piv" / "piv_dx.tif", 1, ("west", "east")),
        (cli_runs / "dem" / "dem_diff.tif", 1, ("down", "up")),
        (next((cli_runs / "icp").glob("*.tif")), 3, ("down", "up")),
        (cli_runs / "slip" / "windows.tif", 1, ("left-lateral", "right-lateral")),
    ):
        assert path.with_suffix(".qml").is_file(), path
        items = _assert_symmetric_pseudocolor(_open_raster(path), band)
        assert items[0].label.endswith(f"(\u2212 = {ends[0]})"), (path, items[0].label)
        assert items[-1].label.endswith(f"(+ = {ends[1]})"), (path, items[-1].label)
        assert items[-1].color.red() > items[-1].color.blue() or ends[1] == "up"


def test_cli_slip_layers_open_styled(cli_runs):
    from qgis.core import QgsRuleBasedRenderer, QgsSingleSymbolRenderer

    gpkg = cli_runs / "slip" / "displacement.gpkg"
    for name in ("tiles", "strips"):
        layer = _open_vector(gpkg, name)
        rules = _class_rules(layer)
        assert all('"right_lateral"' in r.filterExpression() for r in rules)
        assert "+ = right-lateral" in rules[-1].label()
        assert rules[-1].symbol().color().red() > rules[-1].symbol().color().blue()  # + red
        names = [f.name() for f in layer.fields()]
        if "right_lateral" in names:  # the one sign convention's columns (issue #28, 4)
            ok = [f["status"] == "ok" for f in layer.getFeatures()]
            m = np.nanmax(np.abs(_values(layer, "right_lateral")[ok]))
            assert _limits(rules[-1])[1] == pytest.approx(m)
    planes = _open_vector(gpkg, "planes_left")
    assert isinstance(planes.renderer(), QgsRuleBasedRenderer)
    assert isinstance(_open_vector(gpkg, "fault_trace").renderer(), QgsSingleSymbolRenderer)
    # the table QGIS reads: one default row per layer, QGIS's own columns
    import sqlite3

    with sqlite3.connect(gpkg) as db:
        rows = db.execute(
            "SELECT f_table_name, f_geometry_column, useAsDefault FROM layer_styles"
        ).fetchall()
    assert sorted(r[0] for r in rows) == sorted(
        {"planes_left", "planes_right", "tiles", "strips", "fault_trace"}
    )
    assert all(r[1] == "geom" and r[2] == 1 for r in rows)


# --------------------------------------------------------------------------- Processing's files


def test_processing_sinks_store_their_style(provider, field_epochs, tmp_path):
    """windowedicp and piv through ``processing.run`` (nothing loaded, as qgis_process):
    the GeoPackages QGIS writes for the sinks carry the style, the rasters their .qml."""
    import processing

    before, after = field_epochs
    processing.run(
        "slipmap:windowedicp",
        {
            "BEFORE": before,
            "AFTER": after,
            "CELL": 4.0,
            "CELLS": str(tmp_path / "cells.gpkg"),
            "VECTORS": str(tmp_path / "vectors.gpkg"),
            "SUMMARY": str(tmp_path / "icp.json"),
        },
    )
    cells = _open_vector(tmp_path / "cells.gpkg", "cells")
    assert _class_rules(cells) and cells.labelsEnabled()
    vectors = _open_vector(tmp_path / "vectors.gpkg", "vectors")
    top = [r.label() for r in vectors.renderer().rootRule().children()]
    assert any(t.startswith("scale: this arrow") for t in top)
    processing.run(
        "slipmap:piv",
        {
            "BEFORE": before,
            "AFTER": after,
            "GRID": 0.25,
            "VECTORS": str(tmp_path / "piv.gpkg"),
            "DX": str(tmp_path / "dx.tif"),
            "DY": str(tmp_path / "dy.tif"),
            "DZ": str(tmp_path / "dz.tif"),
            "SUMMARY": str(tmp_path / "piv.json"),
        },
    )
    piv = _open_vector(tmp_path / "piv.gpkg", "piv")
    assert "+ = up" in _class_rules(piv)[-1].label()
    _assert_symmetric_pseudocolor(_open_raster(tmp_path / "dz.tif"))


def _qgis_process():
    import shutil

    return shutil.which("qgis_process.bin") or shutil.which("qgis_process")


@pytest.mark.skipif(_qgis_process() is None, reason="no qgis_process binary (QGIS desktop)")
def test_qgis_process_outputs_open_styled(qgis_app, field_epochs, tmp_path):
    """``qgis_process run slipmap:windowedicp``: its cells GeoPackage opens styled."""
    import os
    import subprocess

    import slipmap

    plugins = tmp_path / "profiles" / "default" / "python" / "plugins"
    plugins.mkdir(parents=True)
    (plugins / "slipmap").symlink_to(Path(slipmap.__file__).resolve().parent)
    env = dict(os.environ, QGIS_CUSTOM_CONFIG_PATH=str(tmp_path), QT_QPA_PLATFORM="offscreen")
    laspy = pytest.importorskip("laspy")  # QGIS's Python finds this environment's laspy
    site = str(Path(laspy.__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (site, env.get("PYTHONPATH")) if p)
    run = [_qgis_process()]
    subprocess.run(
        run + ["plugins", "enable", "slipmap"], env=env, capture_output=True, timeout=120
    )
    before, after = field_epochs
    out = subprocess.run(
        run
        + ["run", "slipmap:windowedicp", "--", f"BEFORE={before}", f"AFTER={after}", "CELL=4",
           f"CELLS={tmp_path / 'cells.gpkg'}", f"VECTORS={tmp_path / 'vectors.gpkg'}",
           f"SUMMARY={tmp_path / 'icp.json'}"],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    if "Algorithm" in out.stderr + out.stdout and "not found" in out.stderr + out.stdout:
        pytest.skip("qgis_process did not load the plugin: " + out.stderr[-300:])
    assert (tmp_path / "cells.gpkg").is_file(), out.stdout[-2000:] + out.stderr[-2000:]
    from qgis.core import QgsVectorLayer

    cells = QgsVectorLayer(str(tmp_path / "cells.gpkg"), "cells", "ogr")
    assert cells.isValid()
    assert _class_rules(cells) and cells.labelsEnabled()


# --------------------------------------------------------------------------- the maps


def _write(tmp_path, name, geometry, geoms, cols):
    from slipmap.app.styles import gpkg_styles
    from slipmap.core.io.vector import VectorLayer, write_gpkg_layers

    layers = [VectorLayer(name, geometry, geoms, cols)]
    styles = gpkg_styles("slip", layers)
    write_gpkg_layers(tmp_path / f"{name}.gpkg", layers, crs=32610, styles=styles)
    return _open_vector(tmp_path / f"{name}.gpkg", name)


ROWS = (
    ("left", 0.0004, 0.0024, "ok"),
    ("right", 0.0178, 0.0034, "ok"),
    ("right", np.nan, np.nan, "skipped: 2 matched planes (need 3)"),
)


def test_tiles_label_side_value_sigma_and_skipped_reason(qgis_app, tmp_path):
    from qgis.core import QgsRenderContext

    cols = {
        "side": np.array([r[0] for r in ROWS], dtype=object),
        "right_lateral": np.array([r[1] for r in ROWS]),
        "sigma_right_lateral": np.array([r[2] for r in ROWS]),
        "status": np.array([r[3] for r in ROWS], dtype=object),
    }
    rings = [np.array([[0, 0], [10, 0], [10, 10], [0, 10]]) + [12 * i, 0] for i in range(3)]
    tiles = _write(tmp_path, "tiles", "Polygon", rings, cols)
    labels = _evaluate(tiles, tiles.labeling().settings().fieldName)
    assert labels == ["L +0.4 ± 2.4 mm", "R +17.8 ± 3.4 mm", "R skipped: 2 matched planes (need 3)"]
    rules = tiles.renderer().rootRule().children()
    skipped = next(r for r in rules if r.label().startswith("skipped"))
    ctx = QgsRenderContext()
    feats = list(tiles.getFeatures())
    skipped.startRender(ctx, tiles.fields(), "")
    assert skipped.isFilterOK(feats[2], ctx) and not skipped.isFilterOK(feats[0], ctx)
    skipped.stopRender(ctx)
    assert skipped.symbol() is not None  # skipped tiles are drawn (hatched)
    for r in _class_rules(tiles):  # semi-transparent: planes and the raster show through
        assert r.symbol().color().alpha() < 200
    # the largest ok value sets the classes; the skipped tile's NaN does not
    assert _limits(_class_rules(tiles)[-1])[1] == pytest.approx(0.0178)


def test_strips_draw_each_side_apart_with_its_label(qgis_app, tmp_path):
    from qgis.core import QgsPalLayerSettings, QgsSymbolLayer

    cols = {
        "side": np.array(["left", "right"], dtype=object),
        "right_lateral": np.array([0.0004, 0.0178]),
        "sigma_right_lateral": np.array([0.0024, 0.0034]),
        "status": np.array(["ok", "ok"], dtype=object),
    }
    strips = _write(tmp_path, "strips", "Point", [np.array([5.0, 5.0])] * 2, cols)
    assert _evaluate(strips, strips.labeling().settings().fieldName) == [
        "L +0.4 ± 2.4 mm",
        "R +17.8 ± 3.4 mm",
    ]
    # both sit on the trace: drawn apart (left circle offset left, right square right) and
    # labelled on their own side
    sl = _class_rules(strips)[0].symbol().symbolLayer(0)
    offset = sl.dataDefinedProperties().property(QgsSymbolLayer.PropertyOffset)
    assert _evaluate(strips, offset.expressionString()) == ["-2.2,0", "2.2,0"]
    shape = sl.dataDefinedProperties().property(QgsSymbolLayer.PropertyName)
    assert _evaluate(strips, shape.expressionString()) == ["circle", "square"]
    labeling = strips.labeling()
    settings = labeling.settings()  # kept: the properties live in it
    props = settings.dataDefinedProperties()
    quad = props.property(QgsPalLayerSettings.OffsetQuad).expressionString()
    assert _evaluate(strips, quad) == [3, 5]  # left of the point, right of the point


def test_on_load_post_processor_uses_the_fitted_style(qgis_app, tmp_path):
    """The QGIS algorithms' on-load style is the same fitted QML the files carry."""
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback, QgsVectorLayer

    from slipmap.qgis_plugin.algorithms._base import apply_style_on_load

    cols = {
        "side": np.array(["left", "right"], dtype=object),
        "right_lateral": np.array([-0.002, 0.021]),
        "sigma_right_lateral": np.array([0.001, 0.002]),
        "status": np.array(["ok", "ok"], dtype=object),
    }
    mem = QgsVectorLayer(
        "Polygon?crs=EPSG:32610&field=side:string&field=right_lateral:double"
        "&field=sigma_right_lateral:double&field=status:string",
        "tiles",
        "memory",
    )
    context = QgsProcessingContext()
    context.addLayerToLoadOnCompletion(
        "x", QgsProcessingContext.LayerDetails("tiles", None, "TILES")
    )
    apply_style_on_load(context, "x", "slip_tiles", columns=cols)
    context.layerToLoadOnCompletionDetails("x").postProcessor().postProcessLayer(
        mem, context, QgsProcessingFeedback()
    )
    rules = _class_rules(mem)
    assert _limits(rules[0])[0] == pytest.approx(-0.021)
    assert _limits(rules[-1])[1] == pytest.approx(0.021)


def _assert_sequential(raster, values_path):
    """A viridis ramp from 0 to the roughest cell on band 1 (theta_ODR, legend in mm)."""
    from qgis.core import QgsSingleBandPseudoColorRenderer

    from slipmap.core.io.raster import read_geotiff

    renderer = raster.renderer()
    assert isinstance(renderer, QgsSingleBandPseudoColorRenderer), type(renderer)
    band = np.asarray(read_geotiff(values_path)[0], dtype=np.float64)[0]
    m = float(np.nanmax(band[np.isfinite(band)]))
    assert renderer.classificationMin() == 0.0
    assert renderer.classificationMax() == pytest.approx(m, rel=1e-6)
    items = renderer.shader().rasterShaderFunction().colorRampItemList()
    assert items[0].label.endswith("(smooth)") and items[-1].label.endswith("(rough)")
    assert items[-1].label.startswith(f"{1000 * m:.3g} mm"), items[-1].label


def test_roughness_geotiff_opens_as_a_map(qgis_app, provider, field_epochs, tmp_path):
    """The roughness GeoTIFF (7 bands) opens on band 1 with its ramp, from the CLI and from
    the Processing algorithm, not as an RGB picture of bands 1-3."""
    before, _ = field_epochs
    _cli("roughness", before, "--out", tmp_path / "cli", "--cell", 0.5)
    tif = next((tmp_path / "cli").glob("roughness_*.tif"))
    assert tif.with_suffix(".qml").is_file()
    _assert_sequential(_open_raster(tif), tif)

    import processing

    out = tmp_path / "qgis_roughness.tif"
    processing.run(
        "slipmap:roughness",
        {"INPUT": before, "CELL": 0.5, "OUTPUT": str(out), "CSV": str(tmp_path / "r.csv")},
    )
    assert out.with_suffix(".qml").is_file()
    _assert_sequential(_open_raster(out), out)
