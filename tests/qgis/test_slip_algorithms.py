"""``slipmap:displacement`` tiles, strips, windows and point-accuracy models, and
``slipmap:pointaccuracy`` for every model, through ``processing.run`` against the core."""

import json
import math

import numpy as np
import pyproj
import pytest

pytestmark = pytest.mark.qgis

UTM10 = pyproj.CRS.from_epsg(32610)
ORIGIN = (498000.0, 4234000.0, 20.0)
OFFSET = 0.0181


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    from slipmap.core.io.las import PointCloud, read_las, write_las
    from slipmap.core.synthetic import make_fault_pair

    d = tmp_path_factory.mktemp("slip_epochs")
    fp = make_fault_pair("mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -OFFSET, 0.0))
    paths, xyz = [], []
    for name, sc in (("before", fp.before), ("after", fp.after)):
        p = d / f"{name}.las"
        write_las(
            p,
            PointCloud(xyz=sc.points, attributes={"Classification": sc.classification}, crs=UTM10),
        )
        cloud = read_las(p)  # the core sees the stored (quantised) coordinates, as the plugin
        paths.append(p)
        xyz.append(cloud.xyz[np.asarray(cloud.attributes["Classification"]) != 2])
    return fp, paths, xyz


@pytest.fixture(scope="module")
def tiled_run(provider, epochs, tmp_path_factory):
    """One run with tiles, strips and windows (the core runs once for the module)."""
    import processing

    fp, (before, after), _ = epochs
    d = tmp_path_factory.mktemp("slip_out")
    res = processing.run(
        "slipmap:displacement",
        {
            "BEFORE": str(before),
            "AFTER": str(after),
            "FAULT": _fault_layer(fp.trace_xy),
            "TILE_SIZE": 30.0,
            "COMBINE": 1,
            "STRIP_WIDTH": 30.0,
            "WINDOW_SIZE": 30.0,
            "WINDOW_STEP": 10.0,
            "SUMMARY": str(d / "slip.json"),
            "PLANES": str(d / "planes.gpkg"),
            "TILES": str(d / "tiles.gpkg"),
            "STRIPS": str(d / "strips.gpkg"),
            "WINDOWS": str(d / "windows.tif"),
        },
    )
    return res, d


@pytest.fixture(scope="module")
def core_tiled(epochs):
    from slipmap.core.displacement import estimate_slip, strip_profile, window_field
    from slipmap.core.fault import fault_trace

    fp, _, (b, a) = epochs
    trace = fault_trace([fp.trace_xy])
    result = estimate_slip(b, a, trace, tile_size_m=30.0, combine="tiles")
    strips = strip_profile(b, a, trace, result, strip_width_m=30.0)
    windows = window_field(b, a, trace, result, window_size_m=30.0, window_step_m=10.0)
    return result, strips, windows


def _fault_layer(xy_utm, crs="EPSG:32610"):
    """The trace as a memory line layer in ``crs`` (the equality tests keep the cloud's CRS:
    a round trip through another CRS moves vertices by ~1e-9 m, and points on the buffer's
    edge with them; test_algorithms.py covers the reprojection)."""
    from qgis.core import QgsFeature, QgsGeometry, QgsPointXY, QgsVectorLayer

    tr = pyproj.Transformer.from_crs(UTM10, crs, always_xy=True)
    lon, lat = tr.transform(xy_utm[:, 0], xy_utm[:, 1])
    layer = QgsVectorLayer(f"LineString?crs={crs}", "fault", "memory")
    f = QgsFeature()
    f.setGeometry(QgsGeometry.fromPolylineXY([QgsPointXY(a, b) for a, b in zip(lon, lat)]))
    layer.dataProvider().addFeatures([f])
    return layer


def _features(path):
    from qgis.core import QgsVectorLayer

    layer = QgsVectorLayer(str(path), "out", "ogr")
    assert layer.isValid(), path
    return layer, list(layer.getFeatures())


def _value(v):
    return float("nan") if v is None or (hasattr(v, "isNull") and v.isNull()) else float(v)


# --------------------------------------------------------------------------- displacement


def test_tiles_equal_core(tiled_run, core_tiled):
    res, _ = tiled_run
    result, _, _ = core_tiled
    comp = result.components()
    assert res["RIGHT_LATERAL_SLIP"] == pytest.approx(comp["right_lateral_slip"], abs=1e-6)
    assert abs(res["RIGHT_LATERAL_SLIP"] - OFFSET) < 2e-3
    layer, feats = _features(res["TILES"])
    assert layer.crs().authid() == "EPSG:32610"
    assert len(feats) == len(result.tiles)
    by_key = {(f["side"], f["ix"], f["iy"]): f for f in feats}
    j = np.array([math.sin(result.strike_rad), math.cos(result.strike_rad), 0.0])
    n_ok = 0
    for t in result.tiles:
        f = by_key[(t.side, t.ix, t.iy)]
        assert f["status"] == t.status
        assert f["n_planes"] == t.n_planes
        box = f.geometry().boundingBox()
        np.testing.assert_allclose(
            [box.xMinimum(), box.yMinimum(), box.xMaximum(), box.yMaximum()], t.bounds, atol=1e-6
        )
        if t.status != "ok":
            assert math.isnan(_value(f["dx"]))
            continue
        n_ok += 1
        np.testing.assert_allclose([f["dx"], f["dy"], f["dz"]], t.displacement, atol=1e-9)
        np.testing.assert_allclose(
            [f["sigma_dx"], f["sigma_dy"], f["sigma_dz"]],
            np.sqrt(np.diag(t.covariance)),
            rtol=1e-9,
        )
        # the sign convention: + = right-lateral (a left tile's along-strike motion, a right
        # tile's against it), opening + = away from the trace
        sign = 1.0 if t.side == "left" else -1.0
        jn = np.array([math.cos(result.strike_rad), -math.sin(result.strike_rad), 0.0])
        assert f["right_lateral"] == pytest.approx(sign * (j @ t.displacement), abs=1e-9)
        assert f["sigma_right_lateral"] == pytest.approx(math.sqrt(j @ t.covariance @ j), rel=1e-9)
        assert f["opening"] == pytest.approx(-sign * (jn @ t.displacement), abs=1e-9)
        assert f["sigma_opening"] == pytest.approx(math.sqrt(jn @ t.covariance @ jn), rel=1e-9)
    assert n_ok >= 4
    assert "fault_parallel" not in layer.fields().names()
    right = [_value(f["right_lateral"]) for f in feats if f["side"] == "right"]
    assert np.nanmedian(right) == pytest.approx(OFFSET, abs=2e-3)  # the east side moved


def test_strips_equal_core(tiled_run, core_tiled, epochs):
    from slipmap.core.fault import fault_trace, point_at_chainage

    res, _ = tiled_run
    result, strips, _ = core_tiled
    fp = epochs[0]
    layer, feats = _features(res["STRIPS"])
    assert len(feats) == len(strips)
    got = {(f["side"], round(f["along_start_m"], 6)): f for f in feats}
    c, s = math.cos(result.strike_rad), math.sin(result.strike_rad)
    j, jn = np.array([s, c, 0.0]), np.array([c, -s, 0.0])
    trace = fault_trace([fp.trace_xy])
    for st in strips:
        f = got[(st.side, round(st.along_start_m, 6))]
        assert f["status"] == st.status
        pt = f.geometry().asPoint()
        np.testing.assert_allclose(
            [pt.x(), pt.y()], point_at_chainage(trace, st.along_centre_m), atol=1e-6
        )
        if st.status != "ok":
            assert math.isnan(_value(f["right_lateral"]))
            continue
        # each strip's own motion in the sign convention (as tiles)
        sign = 1.0 if st.side == "left" else -1.0
        d, cov = st.displacement, st.covariance
        assert f["right_lateral"] == pytest.approx(sign * (j @ d), abs=1e-9)
        assert f["sigma_right_lateral"] == pytest.approx(np.sqrt(j @ cov @ j), rel=1e-9)
        assert f["opening"] == pytest.approx(-sign * (jn @ d), abs=1e-9)
        assert f["sigma_opening"] == pytest.approx(np.sqrt(jn @ cov @ jn), rel=1e-9)
        assert f["dz"] == pytest.approx(d[2], abs=1e-9)
        assert f["sigma_dz"] == pytest.approx(np.sqrt(cov[2, 2]), rel=1e-9)
    right = [_value(f["right_lateral"]) for f in feats if f["side"] == "right"]
    left = [_value(f["right_lateral"]) for f in feats if f["side"] == "left"]
    assert np.nanmedian(right) == pytest.approx(OFFSET, abs=2e-3)  # + = dextral
    assert np.nanmedian(left) == pytest.approx(0.0, abs=2e-3)  # the west side did not move
    summary = json.loads((tiled_run[1] / "slip.json").read_text())
    assert len(summary["strips"]) == len(strips)
    assert len(summary["tiles"]) == len(result.tiles)


def test_windows_raster_grid_and_values(tiled_run, core_tiled):
    from osgeo import gdal
    from qgis.core import QgsRasterLayer

    res, _ = tiled_run
    _, _, w = core_tiled
    layer = QgsRasterLayer(res["WINDOWS"], "windows")
    assert layer.isValid()
    assert layer.crs().authid() == "EPSG:32610"
    assert layer.bandCount() == 8
    ny, nx = w.shape
    assert (layer.width(), layer.height()) == (nx, ny)
    ext = layer.extent()
    half = w.step_m / 2
    np.testing.assert_allclose(
        [ext.xMinimum(), ext.yMaximum(), ext.xMaximum(), ext.yMinimum()],
        [w.x0 - half, w.y0 + half, w.x0 - half + nx * w.step_m, w.y0 + half - ny * w.step_m],
        atol=1e-6,
    )
    ds = gdal.Open(res["WINDOWS"])
    result = core_tiled[0]
    # each window's own motion (the left side's global motion added back)
    own = [w.dx + w.reference_m[0], w.dy + w.reference_m[1], w.dz + w.reference_m[2]]
    fp = math.sin(result.strike_rad) * own[0] + math.cos(result.strike_rad) * own[1]
    rl = np.where(w.side < 0, fp, np.where(w.side > 0, -fp, np.nan))  # + = dextral
    sig = [np.sqrt(w.covariance[..., k, k]) for k in range(2)]
    for band, ref in enumerate((rl, *own, *sig, w.n_planes)):
        np.testing.assert_allclose(ds.GetRasterBand(band + 1).ReadAsArray(), ref, equal_nan=True)
    names = [ds.GetRasterBand(k + 1).GetDescription() for k in range(ds.RasterCount)]
    assert names[0] == "right_lateral_m" and names[-1] == "sigma_right_lateral_m"
    # right-side (east) windows carry the offset, + = right-lateral; the west side is still
    right = rl[(w.side == 1) & np.isfinite(rl)]
    left = rl[(w.side == -1) & np.isfinite(rl)]
    assert right.size > 0 and np.median(right) == pytest.approx(OFFSET, abs=2e-3)
    assert left.size > 0 and np.median(left) == pytest.approx(0.0, abs=2e-3)


def test_report_has_plots(tiled_run):
    res, d = tiled_run
    html = open(res["REPORT"], encoding="utf-8").read()
    assert "Right-lateral slip +" in html and "right-lateral (mm, + = dextral)" in html
    assert "fault-parallel" not in html
    pytest.importorskip("matplotlib")
    for name in ("slip_residuals.png", "slip_normals.png", "slip_strips.png"):
        assert name in html
        assert (d / name).is_file()


def test_pa_config_per_epoch_equals_core(provider, epochs, tmp_path):
    import processing

    from slipmap.core.displacement import estimate_slip
    from slipmap.core.fault import fault_trace

    fp, (before, after), (b, a) = epochs
    cfg = tmp_path / "pa.json"
    cfg.write_text(
        json.dumps(
            {
                "before": {"model": "constant", "sigma": 0.02},
                "after": {"model": "axis", "sigma_xyz": [0.01, 0.02, 0.04]},
            }
        )
    )
    res = processing.run(
        "slipmap:displacement",
        {
            "BEFORE": str(before),
            "AFTER": str(after),
            "FAULT": _fault_layer(fp.trace_xy),
            "PA_CONFIG": str(cfg),
            "SUMMARY": str(tmp_path / "s.json"),
            "PLANES": "TEMPORARY_OUTPUT",
        },
    )
    ref = estimate_slip(
        b,
        a,
        fault_trace([fp.trace_xy]),
        sigma_before=0.02,
        sigma_after=np.array([0.01, 0.02, 0.04]),
    ).components()
    assert res["RIGHT_LATERAL_SLIP"] == pytest.approx(ref["right_lateral_slip"], abs=1e-7)
    assert res["SIGMA_RIGHT_LATERAL"] == pytest.approx(ref["sigma_fault_parallel"], rel=1e-6)
    pa = json.loads((tmp_path / "s.json").read_text())["parameters"]["point_accuracy"]
    assert pa["after"]["model"] == "axis"


@pytest.mark.parametrize(
    "extra, words",
    [
        ({"TILES": "TEMPORARY_OUTPUT"}, ("Tiles", "Tile size (m)")),
        ({"WINDOWS": "TEMPORARY_OUTPUT"}, ("Moving windows", "Moving-window size (m)")),
        ({"PA_BEFORE": 3}, ("Trajectory, propagated", "Scanner position")),
        ({"PA_AFTER": 2, "SIGMA_COLUMNS": "SigmaX,SigmaY"}, ("Sigma columns", "3 values")),
        ({"PA_AFTER": 2}, ("SigmaX", "columns", "Sigma columns")),
        ({"PA_CONFIG": "/no/such/pa.json"}, ("Point-accuracy configuration", "JSON")),
        ({"FIXED_COMPONENTS": "plane"}, ("Fixed components", "name=value")),
        ({"FIXED_COMPONENTS": "bogus=0.001"}, ("Fixed components", "bogus", "spatial")),
        ({"FIXED_COMPONENTS": "plane=-0.001"}, ("Fixed components", "plane", ">= 0")),
        ({"FIXED_COMPONENTS": "plane=1,plane=2"}, ("Fixed components", "twice")),
        (
            {"STOCHASTIC_MODEL": 0, "FIXED_COMPONENTS": "plane=0.001"},
            ("Fixed components", "white"),
        ),
    ],
)
def test_bad_parameters_name_the_parameter(provider, epochs, tmp_path, extra, words):
    import processing
    from qgis.core import QgsProcessingException, QgsProcessingFeedback

    class Errors(QgsProcessingFeedback):
        def __init__(self):
            super().__init__()
            self.errors = []

        def reportError(self, error, fatalError=False):  # noqa: N802, N803
            self.errors.append(error)
            super().reportError(error, fatalError)

    fp, (before, after), _ = epochs
    params = {
        "BEFORE": str(before),
        "AFTER": str(after),
        "FAULT": _fault_layer(fp.trace_xy),
        "SUMMARY": str(tmp_path / "s.json"),
        "PLANES": "TEMPORARY_OUTPUT",
    }
    feedback = Errors()
    with pytest.raises(QgsProcessingException) as raised:
        processing.run("slipmap:displacement", {**params, **extra}, feedback=feedback)
    text = str(raised.value) + " ".join(feedback.errors)
    for word in words:
        assert word in text, text


def test_styles_applied_on_load(provider, epochs, tmp_path):
    """TILES and WINDOWS outputs loaded on completion get the bundled styles: tile labels in
    mm, the windows' diverging ramp rescaled to the layer's own symmetric range."""
    import processing
    from osgeo import gdal
    from qgis.core import (
        QgsProcessingContext,
        QgsProcessingFeedback,
        QgsProject,
        QgsRasterLayer,
        QgsRuleBasedRenderer,
        QgsSingleBandPseudoColorRenderer,
        QgsVectorLayer,
    )

    fp, (before, after), _ = epochs
    tiles, windows = str(tmp_path / "tiles.gpkg"), str(tmp_path / "windows.tif")
    context = QgsProcessingContext()
    context.setProject(QgsProject.instance())
    for path, name in ((tiles, "TILES"), (windows, "WINDOWS")):
        context.addLayerToLoadOnCompletion(
            path, QgsProcessingContext.LayerDetails(name, QgsProject.instance(), name)
        )
    feedback = QgsProcessingFeedback()
    processing.run(
        "slipmap:displacement",
        {
            "BEFORE": str(before),
            "AFTER": str(after),
            "FAULT": _fault_layer(fp.trace_xy),
            "TILE_SIZE": 40.0,
            "WINDOW_SIZE": 40.0,
            "WINDOW_STEP": 20.0,
            "SUMMARY": str(tmp_path / "s.json"),
            "PLANES": "TEMPORARY_OUTPUT",
            "TILES": tiles,
            "WINDOWS": windows,
        },
        context=context,
        feedback=feedback,
    )
    layer = QgsVectorLayer(tiles, "tiles", "ogr")
    context.layerToLoadOnCompletionDetails(tiles).postProcessor().postProcessLayer(
        layer, context, feedback
    )
    assert isinstance(layer.renderer(), QgsRuleBasedRenderer)  # right-lateral classes, skipped
    assert layer.labelsEnabled()
    assert "1000" in layer.labeling().settings().fieldName
    raster = QgsRasterLayer(windows, "windows")
    context.layerToLoadOnCompletionDetails(windows).postProcessor().postProcessLayer(
        raster, context, feedback
    )
    renderer = raster.renderer()
    assert isinstance(renderer, QgsSingleBandPseudoColorRenderer)
    ds = gdal.Open(windows)  # kept: a band outliving its dataset crashes GDAL
    band1 = ds.GetRasterBand(1).ReadAsArray()
    m = np.nanmax(np.abs(band1))
    assert 0.01 < m < 0.1
    assert renderer.classificationMax() == pytest.approx(m, rel=1e-6)
    assert renderer.classificationMin() == pytest.approx(-m, rel=1e-6)


@pytest.mark.parametrize(
    "style, uri",
    [
        ("slip_tiles", "Polygon?crs=EPSG:32610"),
        ("slip_strips", "Point?crs=EPSG:32610"),
    ],
)
def test_vector_styles_load(qgis_app, style, uri):
    from qgis.core import (
        QgsExpression,
        QgsExpressionContext,
        QgsExpressionContextUtils,
        QgsFeature,
        QgsGeometry,
        QgsPointXY,
        QgsRectangle,
        QgsRenderContext,
        QgsVectorLayer,
    )

    from slipmap.app.styles import VECTOR_STYLES, vector_qml
    from slipmap.qgis_plugin.algorithms._base import import_qml

    fields = "&".join(
        f"field={n}:{t}"
        for n, t in (
            ("side", "string"),
            ("right_lateral", "double"),
            ("sigma_right_lateral", "double"),
            ("status", "string"),
        )
    )
    layer = QgsVectorLayer(f"{uri}&{fields}", style, "memory")
    f = QgsFeature(layer.fields())
    geom = (
        QgsGeometry.fromRect(QgsRectangle(0, 0, 10, 10))
        if uri.startswith("Polygon")
        else QgsGeometry.fromPointXY(QgsPointXY(5, 5))
    )
    f.setGeometry(geom)
    f.setAttributes(["right", 0.0181, 0.0004, "ok"])
    layer.dataProvider().addFeatures([f])
    columns = {"right_lateral": np.array([0.0181]), "status": np.array(["ok"], dtype=object)}
    import_qml(layer, vector_qml(VECTOR_STYLES[style], columns))
    assert layer.labelsEnabled()
    ctx = QgsExpressionContext(QgsExpressionContextUtils.globalProjectLayerScopes(layer))
    ctx.setFeature(next(layer.getFeatures()))
    label = QgsExpression(layer.labeling().settings().fieldName).evaluate(ctx)
    assert label == "R +18.1 ± 0.4 mm"  # a right-side tile moving 18.1 mm dextrally
    assert len(layer.renderer().symbols(QgsRenderContext())) >= 2


def test_window_style_loads(tiled_run):
    from qgis.core import QgsRasterLayer, QgsSingleBandPseudoColorRenderer

    from slipmap.qgis_plugin.algorithms._base import style_path
    from slipmap.qgis_plugin.compat import renderer_band

    layer = QgsRasterLayer(tiled_run[0]["WINDOWS"], "windows")
    message, ok = layer.loadNamedStyle(style_path("diverging"))
    assert ok, message
    renderer = layer.renderer()
    assert isinstance(renderer, QgsSingleBandPseudoColorRenderer)
    assert renderer_band(renderer) == 1
    assert renderer.classificationMin() == -renderer.classificationMax()


# --------------------------------------------------------------------------- point accuracy


@pytest.fixture(scope="module")
def small_cloud(tmp_path_factory):
    """2000 points with per-point sigmas in SigmaA/SigmaB/SigmaC (UTM 10N)."""
    from slipmap.core.io.las import PointCloud, write_las

    rng = np.random.default_rng(3)
    xyz = np.array(ORIGIN) + rng.uniform([0, 0, 0], [40, 40, 5], size=(2000, 3))
    sig = rng.uniform(0.005, 0.05, size=(2000, 3))
    path = tmp_path_factory.mktemp("pa") / "small.las"
    attrs = {"SigmaA": sig[:, 0], "SigmaB": sig[:, 1], "SigmaC": sig[:, 2]}
    write_las(path, PointCloud(xyz=xyz, attributes=attrs, crs=UTM10))
    return path


def _accuracy(path, out, **params):
    import processing

    processing.run("slipmap:pointaccuracy", {"INPUT": str(path), "OUTPUT": str(out), **params})
    from slipmap.core.io.las import read_las

    return read_las(out)


def test_pointaccuracy_columns_equals_core(provider, small_cloud, tmp_path):
    from slipmap.app.pointaccuracy import covariance_matrices
    from slipmap.core.io.las import read_las

    out = _accuracy(small_cloud, tmp_path / "c.las", MODEL=2, SIGMA_COLUMNS="SigmaA, SigmaB,SigmaC")
    cov = covariance_matrices(
        read_las(small_cloud), None, {"model": "columns", "columns": ["SigmaA", "SigmaB", "SigmaC"]}
    )
    for k, name in enumerate(("SigmaX", "SigmaY", "SigmaZ")):
        np.testing.assert_allclose(out.attributes[name], np.sqrt(cov[:, k, k]), rtol=1e-12)
    assert "CovXY" not in out.attributes


def test_pointaccuracy_tls_reprojected_position_full_covariance(provider, small_cloud, tmp_path):
    from slipmap.app.pointaccuracy import covariance_matrices
    from slipmap.core.io.las import read_las

    pos = np.array([ORIGIN[0] - 15.0, ORIGIN[1] + 10.0, ORIGIN[2] + 1.8])
    lon, lat = pyproj.Transformer.from_crs(UTM10, "EPSG:4326", always_xy=True).transform(
        pos[0], pos[1]
    )
    out = _accuracy(
        small_cloud,
        tmp_path / "tls.laz",
        MODEL=3,
        SCANNER=2,  # riegl-vz400 (sorted names)
        SCANNER_POSITION=f"{lon:.10f},{lat:.10f} [EPSG:4326]",
        SCANNER_HEIGHT=float(pos[2]),
        FULL_COVARIANCE=True,
    )
    settings = {"model": "propagated", "scanner": "riegl-vz400", "scanner_position": list(pos)}
    cov = covariance_matrices(read_las(small_cloud), None, settings)
    for k, name in enumerate(("SigmaX", "SigmaY", "SigmaZ")):
        np.testing.assert_allclose(out.attributes[name], np.sqrt(cov[:, k, k]), rtol=1e-5)
    for name, (r, c) in (
        ("CovXX", (0, 0)),
        ("CovYY", (1, 1)),
        ("CovZZ", (2, 2)),
        ("CovXY", (0, 1)),
        ("CovXZ", (0, 2)),
        ("CovYZ", (1, 2)),
    ):
        np.testing.assert_allclose(out.attributes[name], cov[:, r, c], rtol=1e-4, atol=1e-10)
    assert np.any(np.abs(out.attributes["CovXY"]) > 1e-8)  # correlated: a real TLS model


def test_pointaccuracy_pa_config_and_scanner_names(provider, small_cloud, tmp_path):
    from slipmap.core.accuracy import SCANNERS
    from slipmap.qgis_plugin.algorithms import accuracy

    assert accuracy.SCANNER_NAMES == tuple(sorted(SCANNERS))
    cfg = tmp_path / "pa.json"
    cfg.write_text(json.dumps({"model": "axis", "sigma_xyz": [0.01, 0.02, 0.03]}))
    out = _accuracy(small_cloud, tmp_path / "cfg.las", PA_CONFIG=str(cfg))
    for name, value in (("SigmaX", 0.01), ("SigmaY", 0.02), ("SigmaZ", 0.03)):
        np.testing.assert_allclose(out.attributes[name], value, rtol=1e-12)


def test_pointaccuracy_scanner_file_missing_is_clear(provider, small_cloud, tmp_path):
    import processing
    from qgis.core import QgsProcessingException

    with pytest.raises(QgsProcessingException) as raised:
        processing.run(
            "slipmap:pointaccuracy",
            {
                "INPUT": str(small_cloud),
                "OUTPUT": str(tmp_path / "x.las"),
                "MODEL": 3,
                "SCANNER": 3,  # the "JSON file" choice
                "SCANNER_POSITION": f"{ORIGIN[0]},{ORIGIN[1]} [EPSG:32610]",
            },
        )
    assert "Scanner specification file (JSON)" in str(raised.value)


def test_point_cloud_layer_id_resolves_to_its_file(provider, monkeypatch, tmp_path):
    """A BEFORE/AFTER value naming a project point-cloud layer reads the layer's file (the
    Debian QGIS has no PDAL provider, so the layer lookup is stubbed)."""
    from qgis.core import QgsMapLayerType, QgsProcessingContext

    from slipmap.qgis_plugin.algorithms import displacement

    las = tmp_path / "cloud.laz"
    las.write_bytes(b"")

    class Layer:
        def type(self):
            return QgsMapLayerType.PointCloudLayer

        def source(self):
            return str(las)

    class Utils:
        @staticmethod
        def mapLayerFromString(value, context):  # noqa: N802
            return Layer() if value == "cloud_layer_id" else None

    import qgis.core

    monkeypatch.setattr(qgis.core, "QgsProcessingUtils", Utils)
    alg = displacement.DisplacementAlgorithm()
    alg.initAlgorithm()
    context = QgsProcessingContext()
    assert displacement.cloud_path(alg, {"BEFORE": "cloud_layer_id"}, "BEFORE", context) == str(las)
    assert displacement.cloud_path(alg, {"BEFORE": str(las)}, "BEFORE", context) == str(las)
    assert displacement.cloud_path(alg, {"BEFORE": "/no/such.las"}, "BEFORE", context) == (
        "/no/such.las"
    )
    # every algorithm's cloud inputs resolve the same way (the base's path reading)
    from slipmap.qgis_plugin.algorithms.planes import PlanesAlgorithm

    planes = PlanesAlgorithm()
    planes.initAlgorithm()
    opts = planes.job_options({"INPUT": "cloud_layer_id"}, context)
    assert opts["input"] == str(las)


# --------------------------------------------------------------------------- stochastic model


def test_stochastic_parameters(provider):
    from qgis.core import QgsApplication, QgsProcessingParameterDefinition

    alg = QgsApplication.processingRegistry().algorithmById("slipmap:displacement")
    model = alg.parameterDefinition("STOCHASTIC_MODEL")
    assert model.options() == ["white", "plane", "full"] and model.defaultValue() == 2
    assert "REML" in model.help() and "white" in model.help()
    units = alg.parameterDefinition("UNITS")
    assert units.options() == ["auto", "PointSourceId", "GpsTime", "none"]
    assert units.defaultValue() == 0
    advanced = QgsProcessingParameterDefinition.FlagAdvanced
    for name in ("FIXED_COMPONENTS", "GPS_GAP"):
        p = alg.parameterDefinition(name)
        assert p.flags() & advanced, name
    assert alg.parameterDefinition("FIXED_COMPONENTS").flags() & (
        QgsProcessingParameterDefinition.FlagOptional
    )
    assert alg.parameterDefinition("GPS_GAP").defaultValue() == 1.0
    outputs = {o.name() for o in alg.outputDefinitions()}
    assert {
        "SIGMA_RIGHT_LATERAL_WHITE",
        "STOCHASTIC_MODEL",
        "N_EFF_LEFT",
        "N_EFF_RIGHT",
        "VARIANCE_COMPONENTS",
    } <= outputs
    assert "Stochastic model" in alg.shortHelpString()
    # one vocabulary with the core
    from slipmap.app import stochasticmodel
    from slipmap.core import stochastic

    assert stochasticmodel.MODELS == stochastic.STOCHASTIC_MODELS
    assert stochasticmodel.DEFAULT_MODEL == stochastic.DEFAULT_STOCHASTIC_MODEL
    assert stochasticmodel.COMPONENTS == stochastic.COMPONENT_NAMES + ("spatial_range_m",)


@pytest.fixture(scope="module")
def drift_epochs(tmp_path_factory):
    """A small pair with 3 mm of MLS drift, PointSourceId and GpsTime written in the LAS."""
    from slipmap.core.io.las import PointCloud, read_las, write_las
    from slipmap.core.synthetic import SurveyError, make_fault_pair

    d = tmp_path_factory.mktemp("drift_epochs")
    err = SurveyError(kind="mls", level_m=0.003)
    fp = make_fault_pair(
        "mls",
        seed=11,
        origin=ORIGIN,
        n_buildings=4,
        extent_m=70.0,
        right_offset_m=(0.0, -OFFSET, 0.0),
        error_before=err,
        error_after=err,
    )
    paths, clouds = [], []
    for name, sc, src, gps in (
        ("before", fp.before, fp.source_before, fp.gps_time_before),
        ("after", fp.after, fp.source_after, fp.gps_time_after),
    ):
        p = d / f"{name}.las"
        attrs = {"Classification": sc.classification, "PointSourceId": src, "GpsTime": gps}
        write_las(p, PointCloud(xyz=sc.points, attributes=attrs, crs=UTM10))
        paths.append(p)
        clouds.append(read_las(p))
    return fp, paths, clouds


def test_units_auto_and_components_equal_core(provider, drift_epochs, tmp_path):
    """UNITS auto reads PointSourceId: the slip, its σ and the white σ equal the core's with
    the same units; the outputs, JSON, report and planes carry the components."""
    import processing

    from slipmap.core.displacement import estimate_slip
    from slipmap.core.fault import fault_trace

    fp, (before, after), (cb, ca) = drift_epochs
    res = processing.run(
        "slipmap:displacement",
        {
            "BEFORE": str(before),
            "AFTER": str(after),
            "FAULT": _fault_layer(fp.trace_xy),
            "SUMMARY": str(tmp_path / "s.json"),
            "PLANES": str(tmp_path / "planes.gpkg"),
        },
    )
    kb = np.asarray(cb.attributes["Classification"]) != 2
    ka = np.asarray(ca.attributes["Classification"]) != 2
    ub, ua = cb.attributes["PointSourceId"][kb], ca.attributes["PointSourceId"][ka]
    # the units' GpsTime reaches the core too (the unit_drift option, on by default)
    ref = estimate_slip(
        cb.xyz[kb], ca.xyz[ka], fault_trace([fp.trace_xy]), unit_before=ub, unit_after=ua,
        unit_time_before=cb.attributes["GpsTime"][kb], unit_time_after=ca.attributes["GpsTime"][ka],
    )  # fmt: skip
    comp = ref.components()
    assert res["RIGHT_LATERAL_SLIP"] == pytest.approx(comp["right_lateral_slip"], abs=1e-7)
    assert res["SIGMA_RIGHT_LATERAL"] == pytest.approx(comp["sigma_fault_parallel"], rel=1e-6)
    assert res["SIGMA_RIGHT_LATERAL_WHITE"] == pytest.approx(
        comp["sigma_fault_parallel_white"], rel=1e-6
    )
    assert res["SIGMA_RIGHT_LATERAL_WHITE"] < res["SIGMA_RIGHT_LATERAL"]
    assert res["STOCHASTIC_MODEL"] == "full"
    assert res["N_EFF_LEFT"] == pytest.approx(ref.left.rigid.variance_components.n_eff)
    assert 1.0 <= res["N_EFF_RIGHT"] <= ref.right.rigid.n_planes
    vc = json.loads(res["VARIANCE_COMPONENTS"])
    assert vc["left"]["unit_before_source"] != "off"  # the units reached the core
    assert vc["right"]["plane_m"] == pytest.approx(
        ref.right.rigid.variance_components.component("plane").sigma_m
    )
    summary = json.loads((tmp_path / "s.json").read_text())  # standard JSON (no NaN)
    acq = summary["parameters"]["acquisition_unit_sources"]
    assert acq["before"]["source"] == "PointSourceId"
    assert acq["before"]["n_units"] == int(np.unique(ub).size) > 1
    for side in ("left", "right"):
        comps = summary[side]["variance_components"]["components"]
        assert set(comps) == {"white", "plane", "spatial", "unit_before", "unit_after"}
        assert all(math.isfinite(c["sigma_m"]) for c in comps.values())
    html = open(res["REPORT"], encoding="utf-8").read()
    assert "Stochastic model" in html and "unit_before" in html
    assert "Rejected and down-weighted planes" in html
    layer, feats = _features(res["PLANES"])
    names = [f.name() for f in layer.fields()]
    assert {"weight", "w_test", "offset_mm", "misclosure_mm"} <= set(names)
    weights = [_value(f["weight"]) for f in feats]
    assert all(0.0 <= w <= 1.0 for w in weights if not math.isnan(w))
    assert any(not math.isnan(_value(f["offset_mm"])) for f in feats)


def test_white_model_and_fixed_components(provider, drift_epochs, tmp_path):
    import processing

    fp, (before, after), _ = drift_epochs
    base = {
        "BEFORE": str(before),
        "AFTER": str(after),
        "FAULT": _fault_layer(fp.trace_xy),
        "PLANES": "TEMPORARY_OUTPUT",
    }
    white = processing.run(
        "slipmap:displacement",
        {**base, "STOCHASTIC_MODEL": 0, "UNITS": 1, "SUMMARY": str(tmp_path / "w.json")},
    )
    assert white["STOCHASTIC_MODEL"] == "white"
    assert white["SIGMA_RIGHT_LATERAL_WHITE"] == white["SIGMA_RIGHT_LATERAL"]
    assert white["N_EFF_LEFT"] is None
    js = json.loads((tmp_path / "w.json").read_text())
    assert "variance_components" not in js["left"]
    units = js["parameters"]["acquisition_unit_sources"]
    unread = {"source": "none", "n_units": 0, "note": "not used by the white model"}
    assert units["before"] == unread and units["after"] == unread
    fixed = processing.run(
        "slipmap:displacement",
        {
            **base,
            "STOCHASTIC_MODEL": 1,
            "FIXED_COMPONENTS": "plane=0.002",
            "SUMMARY": str(tmp_path / "f.json"),
        },
    )
    vc = json.loads(fixed["VARIANCE_COMPONENTS"])
    assert vc["model"] == "plane"
    for side in ("left", "right"):
        assert vc[side]["plane_source"] == "fixed"
        assert vc[side]["plane_m"] == pytest.approx(0.002, abs=1e-12)


class _Feedback:
    """A QgsProcessingFeedback that keeps what the algorithm pushes (the dialog's log)."""

    def __new__(cls):
        from qgis.core import QgsProcessingFeedback

        class Kept(QgsProcessingFeedback):
            def __init__(self):
                super().__init__()
                self.warnings, self.infos = [], []

            def pushWarning(self, text):  # noqa: N802 (QGIS API name)
                self.warnings.append(text)

            def pushInfo(self, text):  # noqa: N802 (QGIS API name)
                self.infos.append(text)

        return Kept()


def test_record_and_unused_settings_in_the_dialogs_words(provider, epochs, tmp_path):
    """A fault from a file layer is recorded by its file; the point accuracy lists only the
    constant model's sigma (not the dialog's scanner and footprint defaults); a strip width
    and a window size without their outputs are named by the dialog's labels (strips into the
    JSON, no windows computed); VARIANCE_COMPONENTS prints on one line in the dialog's
    results (QGIS prints them with pprint)."""
    from pprint import pformat

    import processing
    from qgis.core import QgsVectorFileWriter, QgsVectorLayer

    fp, (before, after), _ = epochs
    path = str(tmp_path / "trace.gpkg")
    mem = _fault_layer(fp.trace_xy)
    opts = QgsVectorFileWriter.SaveVectorOptions()
    opts.driverName, opts.layerName = "GPKG", "trace"
    QgsVectorFileWriter.writeAsVectorFormatV3(
        mem, path, mem.transformContext(), opts
    )  # fmt: skip
    layer = QgsVectorLayer(f"{path}|layername=trace", "trace", "ogr")
    assert layer.isValid()
    feedback = _Feedback()
    res = processing.run(
        "slipmap:displacement",
        {
            "BEFORE": str(before),
            "AFTER": str(after),
            "FAULT": layer,
            "STRIP_WIDTH": 50.0,
            "WINDOW_SIZE": 40.0,
            "SUMMARY": str(tmp_path / "s.json"),
            "PLANES": "TEMPORARY_OUTPUT",
        },
        feedback=feedback,
    )
    assert feedback.warnings == [
        '"Strip width (m)": is set but no "Strips" output is asked for: the strips go only '
        'into the summary JSON and the report; ask for "Strips" to get the layer',
        '"Moving-window size (m)": is set but no "Moving windows" output is asked for: no '
        'windows are computed; ask for "Moving windows" to get them',
    ]
    assert not any("WINDOW_SIZE" in t for t in feedback.infos + feedback.warnings)
    js = json.loads((tmp_path / "s.json").read_text())
    assert js["strips"] and "windows" not in {p.stem for p in tmp_path.iterdir()}
    prm = js["parameters"]
    assert prm["fault"] == layer.source() and prm["fault"].startswith(path)
    assert prm["point_accuracy"]["before"] == {"model": "constant", "sigma": 0.05}
    html = open(res["REPORT"], encoding="utf-8").read()
    assert "trace.gpkg (layername=trace)" in html and "(layer)" not in html
    assert "scanner" not in html and "footprint" not in html
    text = pformat({k: v for k, v in res.items() if k == "VARIANCE_COMPONENTS"})
    assert len(text.splitlines()) == 1, text
    assert json.loads(res["VARIANCE_COMPONENTS"])["model"] == "full"


def test_memory_fault_layer_is_recorded_as_such(tiled_run):
    res, d = tiled_run
    js = json.loads((d / "slip.json").read_text())
    assert js["parameters"]["fault"] == "memory layer 'fault' (not saved to a file)"


def test_output_under_a_file_says_it_is_a_file(provider, epochs, tmp_path):
    import processing
    from qgis.core import QgsProcessingException

    fp, (before, after), _ = epochs
    (tmp_path / "slip.json").write_text("{}")
    with pytest.raises(QgsProcessingException) as e:
        processing.run(
            "slipmap:displacement",
            {
                "BEFORE": str(before),
                "AFTER": str(after),
                "FAULT": _fault_layer(fp.trace_xy),
                "SUMMARY": str(tmp_path / "slip.json" / "out.json"),
                "PLANES": "TEMPORARY_OUTPUT",
            },
        )
    text = str(e.value)
    assert '"Summary": ' in text and "slip.json is a file, not a folder" in text, text
    assert "does not exist" not in text
