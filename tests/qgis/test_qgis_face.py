"""The QGIS face as GIS analysts meet it (issue #19): install hint, output folders checked
before running, loaded outputs (styles, legends, names, order), log, help; through
``processing.run`` on a small synthetic fault."""

from __future__ import annotations

import re

import pytest

import slipmap

pytestmark = pytest.mark.qgis


# --------------------------------------------------------------------------- 1. install hint


def test_install_hint_renders_and_names_each_platform(provider, monkeypatch):
    """The canExecute message is shown as rich text (toolbox tooltip, message box): nothing
    in it may read as a tag, and it gives a command that works on each platform."""
    from qgis.core import QgsApplication
    from qgis.PyQt.QtGui import QTextDocument

    from slipmap.qgis_plugin import compat

    monkeypatch.setattr(compat, "missing_packages", lambda: ["laspy", "lazrs"])
    for alg in QgsApplication.processingRegistry().providerById("slipmap").algorithms():
        ok, message = alg.canExecute()
        assert not ok
        doc = QTextDocument()
        doc.setHtml(message)
        assert doc.toPlainText() == message  # rendered as written: no tag swallowed
        assert "<" not in message and ">" not in message
        assert message.startswith("Missing: laspy, lazrs.")
        # Debian 12/13: PEP 668 refuses a plain `pip install --user`
        assert "python3 -m pip install --user --break-system-packages laspy lazrs" in message
        assert "OSGeo4W Shell, python -m pip install laspy lazrs" in message
        assert "QGIS.app/Contents/MacOS/bin/python3 -m pip install laspy lazrs" in message


# --------------------------------------------------------------------------- inputs


@pytest.fixture(scope="module")
def small_cloud(tmp_path_factory):
    """A 3000-point tilted plane with 1 cm noise (roughness runs on it in a second)."""
    import numpy as np
    import pyproj

    from slipmap.core.io.las import PointCloud, write_las

    rng = np.random.default_rng(19)
    xy = rng.uniform(0.0, 20.0, size=(3000, 2)) + (500000.0, 4200000.0)
    z = 100.0 + 0.1 * (xy[:, 0] - 500000.0) + rng.normal(0.0, 0.01, 3000)
    path = tmp_path_factory.mktemp("face_cloud") / "plane.las"
    write_las(path, PointCloud(xyz=np.column_stack([xy, z]), crs=pyproj.CRS.from_epsg(32610)))
    return path


def _listing(folder):
    return sorted(p.name for p in folder.rglob("*"))


# --------------------------------------------------------------------------- 2. output folders


@pytest.mark.parametrize(
    "output, name",
    [("CSV", "cells.csv"), ("OUTPUT", "theta.tif"), ("SUMMARY", "summary.json")],
)
def test_missing_output_folder_refused_before_running(
    provider, small_cloud, tmp_path, output, name
):
    """A destination in a folder that does not exist is refused by checkParameterValues,
    naming the output by its dialog label and the folder; nothing is written."""
    import processing
    from qgis.core import QgsApplication, QgsProcessingContext, QgsProcessingException

    params = {
        "INPUT": str(small_cloud),
        "CELL": 2.0,
        "OUTPUT": str(tmp_path / "theta.tif"),
        "CSV": str(tmp_path / "cells.csv"),
    }
    missing = tmp_path / "no" / "such"
    params[output] = str(missing / name)
    label = QgsApplication.processingRegistry().algorithmById("slipmap:roughness")
    label = label.parameterDefinition(output).description()
    ok, message = (
        QgsApplication.processingRegistry()
        .createAlgorithmById("slipmap:roughness")
        .checkParameterValues(params, QgsProcessingContext())
    )
    assert not ok
    assert message.startswith(f'"{label}": the folder {missing} does not exist'), message
    with pytest.raises(QgsProcessingException, match="does not exist"):
        processing.run("slipmap:roughness", params)
    assert _listing(tmp_path) == []


def test_missing_folder_of_a_slip_sink_and_raster_refused(provider, small_cloud, tmp_path):
    """The same for the Fault slip algorithm's vector sinks and its raster."""
    from qgis.core import QgsApplication, QgsProcessingContext

    from slipmap.app import slip

    alg = QgsApplication.processingRegistry().createAlgorithmById("slipmap:displacement")
    base = {
        "BEFORE": str(small_cloud),
        "AFTER": str(small_cloud),
        "FAULT": str(small_cloud),
        "TILE_SIZE": 30.0,
        "WINDOW_SIZE": 30.0,
        "SUMMARY": str(tmp_path / "s.json"),
    }
    for output in ("TILES", "WINDOWS", "PLANES"):
        dest = tmp_path / "gone" / ("x.tif" if output == "WINDOWS" else "x.gpkg")
        label = alg.parameterDefinition(output).description()
        ok, message = alg.checkParameterValues({**base, output: str(dest)}, QgsProcessingContext())
        assert not ok
        # an input error may come first (the same file twice); the folder is named otherwise
        if "does not exist" in message:
            assert message.startswith(f'"{label}": the folder {dest.parent}'), message
        else:
            assert slip.SPEC["after"].dialog_label in message or "same" in message, message
    assert _listing(tmp_path) == []


def test_raster_named_as_another_format_refused(provider, small_cloud, tmp_path):
    from qgis.core import QgsApplication, QgsProcessingContext

    alg = QgsApplication.processingRegistry().createAlgorithmById("slipmap:roughness")
    params = {
        "INPUT": str(small_cloud),
        "CELL": 2.0,
        "OUTPUT": str(tmp_path / "theta.gpkg"),
        "CSV": str(tmp_path / "cells.csv"),
    }
    ok, message = alg.checkParameterValues(params, QgsProcessingContext())
    assert not ok and "GeoTIFF" in message and ".gpkg" in message, message


def test_raster_without_suffix_written_and_loaded_as_tif(provider, small_cloud, tmp_path):
    """A raster destination typed without a suffix is written as NAME.tif and that file is
    the one QGIS loads when the run ends."""
    import processing
    from qgis.core import QgsProcessingContext, QgsProcessingFeedback, QgsProject

    project = QgsProject.instance()
    project.removeAllMapLayers()
    context = QgsProcessingContext()
    context.setProject(project)
    params = {
        "INPUT": str(small_cloud),
        "CELL": 2.0,
        "OUTPUT": str(tmp_path / "theta"),
        "CSV": str(tmp_path / "cells.csv"),
    }
    res = processing.runAndLoadResults(
        "slipmap:roughness", params, context=context, feedback=QgsProcessingFeedback()
    )
    assert res["OUTPUT"] == str(tmp_path / "theta.tif")
    assert (tmp_path / "theta.tif").is_file() and not (tmp_path / "theta").exists()
    sources = [layer.source() for layer in project.mapLayers().values()]
    assert sources == [str(tmp_path / "theta.tif")]
    assert all(layer.isValid() for layer in project.mapLayers().values())
    project.removeAllMapLayers()


# --------------------------------------------------------------------------- 3. loaded outputs

OFFSET = 0.0181  # the synthetic right side moves 18.1 mm opposite strike: dextral


class _Feedback:
    """A QgsProcessingFeedback that keeps every log line and progress text."""

    @staticmethod
    def make():
        from qgis.core import QgsProcessingFeedback

        class Feedback(QgsProcessingFeedback):
            def __init__(self):
                super().__init__()
                self.lines, self.texts = [], []

            def pushInfo(self, text):  # noqa: N802 (QGIS API name)
                self.lines.append(text)

            def pushWarning(self, text):  # noqa: N802 (QGIS API name)
                self.lines.append(text)

            def pushDebugInfo(self, text):  # noqa: N802 (QGIS API name)
                pass

            def reportError(self, text, fatal_error=False):  # noqa: N802 (QGIS API name)
                self.lines.append(text)

            def setProgressText(self, text):  # noqa: N802 (QGIS API name)
                self.texts.append(text)

        return Feedback()


@pytest.fixture(scope="module")
def loaded_slip(provider, tmp_path_factory):
    """One Fault slip run with every output, loaded into the project as the dialog does."""
    import numpy as np
    import processing
    import pyproj
    from qgis.core import (
        QgsFeature,
        QgsGeometry,
        QgsPointXY,
        QgsProcessingContext,
        QgsProject,
        QgsVectorLayer,
    )

    from slipmap.core.io.las import PointCloud, write_las
    from slipmap.core.synthetic import make_fault_pair

    d = tmp_path_factory.mktemp("face_slip")
    utm = pyproj.CRS.from_epsg(32610)
    fp = make_fault_pair(
        "mls", seed=7, origin=(498000.0, 4234000.0, 20.0), right_offset_m=(0.0, -OFFSET, 0.0)
    )
    for name, sc in (("before", fp.before), ("after", fp.after)):
        attrs = {"Classification": sc.classification}
        write_las(d / f"{name}.las", PointCloud(xyz=sc.points, attributes=attrs, crs=utm))
    fault = QgsVectorLayer("LineString?crs=EPSG:32610", "fault", "memory")
    f = QgsFeature()
    f.setGeometry(QgsGeometry.fromPolylineXY([QgsPointXY(*p) for p in np.asarray(fp.trace_xy)]))
    fault.dataProvider().addFeatures([f])
    project = QgsProject.instance()
    project.removeAllMapLayers()
    context = QgsProcessingContext()
    context.setProject(project)
    feedback = _Feedback.make()
    res = processing.runAndLoadResults(
        "slipmap:displacement",
        {
            "BEFORE": str(d / "before.las"),
            "AFTER": str(d / "after.las"),
            "FAULT": fault,
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
        context=context,
        feedback=feedback,
    )
    layers = {
        layer.source().split("|")[0].rsplit("/", 1)[-1]: layer
        for layer in project.mapLayers().values()
    }
    yield res, layers, feedback, project
    project.removeAllMapLayers()


def _expression_values(layer, expression_text, where=None):
    from qgis.core import (
        QgsExpression,
        QgsExpressionContext,
        QgsExpressionContextUtils,
    )

    expr = QgsExpression(expression_text)
    ctx = QgsExpressionContext(QgsExpressionContextUtils.globalProjectLayerScopes(layer))
    out = []
    for feature in layer.getFeatures():
        if where is not None and not where(feature):
            continue
        ctx.setFeature(feature)
        v = expr.evaluate(ctx)
        out.append(None if v is None else float(v))
    return out


def test_every_slip_output_loads_styled(loaded_slip):
    from qgis.core import (
        QgsGraduatedSymbolRenderer,
        QgsRuleBasedRenderer,
        QgsSingleBandPseudoColorRenderer,
    )

    _, layers, _, _ = loaded_slip
    assert set(layers) == {"planes.gpkg", "tiles.gpkg", "strips.gpkg", "windows.tif"}
    assert all(layer.isValid() for layer in layers.values())
    # matched planes: by weight (full, down-weighted, rejected, unused), not QGIS's default
    assert isinstance(layers["planes.gpkg"].renderer(), QgsRuleBasedRenderer)
    labels = [r.label() for r in layers["planes.gpkg"].renderer().rootRule().children()]
    assert any("rejected" in t for t in labels) and any("down-weighted" in t for t in labels)
    for name in ("tiles.gpkg", "strips.gpkg"):
        assert isinstance(layers[name].renderer(), QgsGraduatedSymbolRenderer)
    assert isinstance(layers["windows.tif"].renderer(), QgsSingleBandPseudoColorRenderer)


def test_tiles_and_strips_show_the_summary_sign(loaded_slip):
    """The slip is +18.1 mm dextral: the right side's tiles and strips show about +18 mm in
    their class values and labels, the left side's about 0; the classes span ±max|value|."""
    import numpy as np

    res, layers, _, _ = loaded_slip
    slip_mm = 1000.0 * res["RIGHT_LATERAL_SLIP"]
    assert slip_mm == pytest.approx(1000 * OFFSET, abs=1.5)
    for name in ("tiles.gpkg", "strips.gpkg"):
        layer = layers[name]
        renderer = layer.renderer()
        expression = renderer.classAttribute()

        def ok_side(side):
            return lambda f: f["side"] == side and f["status"] == "ok"

        right = _expression_values(layer, expression, ok_side("right"))
        left = _expression_values(layer, expression, ok_side("left"))
        assert right and left
        assert np.median(right) == pytest.approx(slip_mm, abs=3.0), (name, right)
        assert abs(np.median(left)) < 3.0, (name, left)
        labeling = layer.labeling()
        label = labeling.settings().fieldName
        texts = _expression_values(layer, f"to_real(regexp_substr({label}, '^-?[0-9.]+'))")
        assert np.nanmax([t for t in texts if t is not None]) > 0.8 * slip_mm
        everything = [abs(v) for v in _expression_values(layer, expression) if v is not None]
        ranges = renderer.ranges()
        assert ranges[0].lowerValue() == pytest.approx(-max(everything))
        assert ranges[-1].upperValue() == pytest.approx(max(everything))
        assert ranges[-1].symbol().color().red() > ranges[-1].symbol().color().blue()  # +: red


def test_window_legend_equals_the_data_and_red_is_right_lateral(loaded_slip):
    import numpy as np
    from osgeo import gdal

    _, layers, _, _ = loaded_slip
    layer = layers["windows.tif"]
    ds = gdal.Open(layer.source())
    band = ds.GetRasterBand(1).ReadAsArray().astype(float)
    band[band == ds.GetRasterBand(1).GetNoDataValue()] = np.nan
    ds = None
    m = np.nanmax(np.abs(band))
    renderer = layer.renderer()
    assert renderer.classificationMin() == pytest.approx(-m, rel=1e-6)
    assert renderer.classificationMax() == pytest.approx(m, rel=1e-6)
    ramp = renderer.shader().rasterShaderFunction()
    assert (ramp.minimumValue(), ramp.maximumValue()) == pytest.approx((-m, m), rel=1e-6)
    items = ramp.colorRampItemList()
    assert items[0].value == pytest.approx(-m, rel=1e-6)
    # the sign convention: band right_lateral_m, + = right-lateral (red), - = left-lateral
    assert items[0].label == f"{-1000 * m:+.3g} mm (left-lateral)"
    assert items[-1].label == f"{1000 * m:+.3g} mm (right-lateral)"
    assert items[-1].color.red() > items[-1].color.blue()  # + = right-lateral: red
    assert items[0].color.blue() > items[0].color.red()  # - = left-lateral: blue
    assert renderer.opacity() < 1.0


def test_raster_below_the_vectors(loaded_slip):
    from qgis.core import QgsMapLayerType

    _, layers, _, project = loaded_slip
    order = [n.layer() for n in project.layerTreeRoot().findLayers()]  # top first
    kinds = [layer.type() for layer in order]
    assert kinds.index(QgsMapLayerType.RasterLayer) > max(
        i for i, k in enumerate(kinds) if k == QgsMapLayerType.VectorLayer
    )


def test_layer_names_unique_per_run(provider, small_cloud, tmp_path):
    import processing
    from qgis.core import QgsProcessingContext, QgsProject

    project = QgsProject.instance()
    before = set(project.mapLayers())
    names = []
    for k in range(2):
        context = QgsProcessingContext()
        context.setProject(project)
        processing.runAndLoadResults(
            "slipmap:roughness",
            {
                "INPUT": str(small_cloud),
                "CELL": 2.0,
                "OUTPUT": "TEMPORARY_OUTPUT",
                "CSV": str(tmp_path / f"cells{k}.csv"),
            },
            context=context,
            feedback=_Feedback.make(),
        )
        names += [project.mapLayer(i).name() for i in set(project.mapLayers()) - before]
        before = set(project.mapLayers())
    assert len(names) == 2 and len(set(names)) == 2, names
    assert all(n.startswith("Roughness (GeoTIFF) ") for n in names), names


# --------------------------------------------------------------------------- 4. log


def test_a_few_log_lines_per_job(loaded_slip):
    """Per tile, per window or per cell there is no log line: the core's per-item info goes
    to the debug log, a repeated warning is written once and counted at the end, and the
    progress text is throttled."""
    _, _, feedback, _ = loaded_slip
    lines = [t for t in feedback.lines if not t.startswith("Results:")]  # QGIS's own
    assert len(lines) <= 16, "\n".join(lines)
    per_item = re.compile(r"(window|tile|cell|strip)\s+\d+\s*(/|of)\s*\d+", re.I)
    assert not [t for t in lines if per_item.search(t)]
    assert not [t for t in lines if t.startswith("point spacing")]
    assert len(lines) == len(set(lines))
    assert "  right-lateral slip" in "\n".join(lines)
    assert len(feedback.texts) <= 12, feedback.texts


def test_cancel_says_run_cancelled_once(provider, small_cloud, tmp_path):
    import processing
    from qgis.core import QgsProcessingException

    feedback = _Feedback.make()
    feedback.setProgress = lambda value: feedback.cancel()  # cancel at the first step
    with pytest.raises(QgsProcessingException) as raised:
        processing.run(
            "slipmap:roughness",
            {
                "INPUT": str(small_cloud),
                "CELL": 2.0,
                "OUTPUT": str(tmp_path / "theta.tif"),
                "CSV": str(tmp_path / "cells.csv"),
            },
            feedback=feedback,
        )
    said = [str(raised.value)] + feedback.lines
    assert str(raised.value).strip().endswith("Run cancelled."), said
    assert sum(t.lower().count("cancel") for t in said) <= 2, said  # the exception, its log line
    assert not any("cancelled by the user" in t for t in said), said
    assert _listing(tmp_path) == []


# --------------------------------------------------------------------------- 5. help

_TAG = re.compile(r"</?[A-Za-z][^>]*>")


def _dialog_html(alg):
    """The help panel's HTML as QGIS builds it (QgsProcessingAlgorithmDialogBase::formatHelp:
    one <p> per line of shortHelpString)."""
    help_text = alg.shortHelpString()
    return f"<h2>{alg.displayName()}</h2>" + "".join(
        f"<p>{line}</p>" for line in help_text.split("\n")
    )


def test_help_is_sectioned_plain_text(provider):
    from qgis.core import QgsApplication
    from qgis.PyQt.QtGui import QTextDocument

    algs = QgsApplication.processingRegistry().providerById("slipmap").algorithms()
    assert len(algs) == 8
    for alg in algs:
        text = alg.shortHelpString()
        assert not _TAG.search(text), (alg.id(), _TAG.search(text).group())
        assert "docs/qgis.md" not in text, alg.id()  # helpUrl() points there
        paragraphs = [p for p in text.split("\n\n")]
        assert paragraphs[-1].startswith("Method: "), alg.id()
        assert any(p.startswith("Outputs: ") for p in paragraphs), alg.id()
        doc = QTextDocument()
        doc.setHtml(_dialog_html(alg))
        plain = doc.toPlainText()
        for p in paragraphs:  # every paragraph reads in the dialog as written
            assert p in plain, (alg.id(), p[:60])
    slip = QgsApplication.processingRegistry().algorithmById("slipmap:displacement")
    text = slip.shortHelpString()
    assert text.count("Kusari") == 1  # the study cited once
    models = next(p for p in text.split("\n\n") if p.startswith("Point accuracy models"))
    assert all(m in models for m in ("constant =", "axis =", "columns =", "propagated ="))
    assert len(models) < 800
    assert "Stochastic model: " in text and len(text) < 3000


def _qgis_process():
    import shutil

    return shutil.which("qgis_process.bin") or shutil.which("qgis_process")


@pytest.mark.skipif(_qgis_process() is None, reason="no qgis_process binary (QGIS desktop)")
def test_qgis_process_help_reads_as_plain_text(tmp_path):
    """``qgis_process help slipmap:displacement`` prints the help with no raw tags (the
    plugin from a throw-away profile folder; Debian's qgis_process wrapper passes an option
    3.22's binary refuses, so the .bin is called where there is one)."""
    import os
    import subprocess
    from pathlib import Path

    plugins = tmp_path / "profiles" / "default" / "python" / "plugins"
    plugins.mkdir(parents=True)
    (plugins / "slipmap").symlink_to(Path(slipmap.__file__).resolve().parent)
    env = dict(os.environ, QGIS_CUSTOM_CONFIG_PATH=str(tmp_path), QT_QPA_PLATFORM="offscreen")
    run = [_qgis_process()]
    subprocess.run(
        run + ["plugins", "enable", "slipmap"], env=env, capture_output=True, timeout=120
    )
    out = subprocess.run(
        run + ["help", "slipmap:displacement"], env=env, capture_output=True, text=True, timeout=120
    ).stdout
    if "Fault slip" not in out:
        pytest.skip("qgis_process did not load the plugin: " + out[-200:])
    description = out.split("Arguments\n")[0]  # qgis_process marks types as <outputFile>
    assert not _TAG.search(description), _TAG.search(description).group()
    assert "\nPoint accuracy models (one per epoch): constant =" in description
    assert description.count("Kusari") == 1
