"""The QGIS face as GIS analysts meet it (issue #19): install hint, output folders checked
before running, loaded outputs (styles, legends, names, order), log, help; through
``processing.run`` on a small synthetic fault."""

from __future__ import annotations

import re
import shutil

import pytest

import slipmap

pytestmark = pytest.mark.qgis


# --------------------------------------------------------------------------- 1. install hint


def test_install_hint_renders_and_names_each_platform(provider, monkeypatch):
    """The canExecute message is shown as rich text (toolbox tooltip, message box): nothing
    in it may read as a tag; it names what is missing and ends with the one command for this
    platform (tests/qgis/test_dependencies.py: each platform's command)."""
    from qgis.core import QgsApplication
    from qgis.PyQt.QtGui import QTextDocument

    from slipmap.qgis_plugin import compat

    monkeypatch.setattr(compat, "missing_packages", lambda names=None: ["laspy", "lazrs"])
    command = compat.install_command(["laspy", "lazrs"])
    for alg in QgsApplication.processingRegistry().providerById("slipmap").algorithms():
        ok, message = alg.canExecute()
        assert not ok
        doc = QTextDocument()
        doc.setHtml(message)
        assert doc.toPlainText() == message  # rendered as written: no tag swallowed
        assert "<" not in message and ">" not in message
        assert message.startswith("SlipMap needs the Python packages laspy, lazrs,")
        assert message.endswith(f"then restart QGIS: {command}")
        if compat.platform_kind() == "debian" and compat._externally_managed():
            # Debian 12/13: PEP 668 refuses a plain `pip install --user`
            assert command.endswith(
                "python3 -m pip install --user --break-system-packages laspy lazrs"
            )
    for text in (compat.INSTALL_HINT,):
        doc = QTextDocument()
        doc.setHtml(text)
        assert doc.toPlainText() == text


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
                self.lines, self.texts, self.values, self.text_at = [], [], [], []

            def setProgress(self, value):  # noqa: N802 (QGIS API name)
                self.values.append(value)
                super().setProgress(value)

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
                self.text_at.append((text, self.values[-1] if self.values else 0.0))

        return Feedback()


@pytest.fixture(scope="module")
def slip_pair(provider, tmp_path_factory):
    """The synthetic pair (18.1 mm dextral) as before.las, after.las and a fault layer."""
    import numpy as np
    import pyproj
    from qgis.core import QgsFeature, QgsGeometry, QgsPointXY, QgsVectorLayer

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
    return d, fault


def _slip_parameters(d, fault, out, layers=()):
    """The Fault slip run of these tests (30 m tiles, strips, windows stepped 10 m) on the
    pair in ``d``, its files in ``out``; ``layers``: the vector outputs written too."""
    files = {"TILES": "tiles.gpkg", "STRIPS": "strips.gpkg"}
    return {
        "BEFORE": str(d / "before.las"),
        "AFTER": str(d / "after.las"),
        "FAULT": fault,
        "TILE_SIZE": 30.0,
        "COMBINE": 1,
        "STRIP_WIDTH": 30.0,
        "WINDOW_SIZE": 30.0,
        "WINDOW_STEP": 10.0,
        "SUMMARY": str(out / "slip.json"),
        "PLANES": str(out / "planes.gpkg"),
        **{name: str(out / files[name]) for name in layers},
        "WINDOWS": str(out / "windows.tif"),
    }


@pytest.fixture(scope="module")
def loaded_slip(slip_pair):
    """One Fault slip run with every output, loaded into the project as the dialog does."""
    import processing
    from qgis.core import QgsProcessingContext, QgsProject

    d, fault = slip_pair
    project = QgsProject.instance()
    project.removeAllMapLayers()
    context = QgsProcessingContext()
    context.setProject(project)
    feedback = _Feedback.make()
    res = processing.runAndLoadResults(
        "slipmap:displacement",
        _slip_parameters(d, fault, d, ("TILES", "STRIPS")),
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
    from qgis.core import QgsRuleBasedRenderer, QgsSingleBandPseudoColorRenderer

    _, layers, _, _ = loaded_slip
    assert set(layers) == {"planes.gpkg", "tiles.gpkg", "strips.gpkg", "windows.tif"}
    assert all(layer.isValid() for layer in layers.values())
    # matched planes: by weight (full, down-weighted, rejected, unused), not QGIS's default
    assert isinstance(layers["planes.gpkg"].renderer(), QgsRuleBasedRenderer)
    labels = [r.label() for r in layers["planes.gpkg"].renderer().rootRule().children()]
    assert any("rejected" in t for t in labels) and any("down-weighted" in t for t in labels)
    for name in ("tiles.gpkg", "strips.gpkg"):  # right-lateral classes and the skipped ones
        renderer = layers[name].renderer()
        assert isinstance(renderer, QgsRuleBasedRenderer)
        labels = [r.label() for r in renderer.rootRule().descendants()]
        assert any(t.endswith("(+ = right-lateral)") for t in labels), labels
        assert any(t.startswith("skipped") for t in labels), labels
    assert isinstance(layers["windows.tif"].renderer(), QgsSingleBandPseudoColorRenderer)


def test_tiles_and_strips_show_the_summary_sign(loaded_slip):
    """The slip is +18.1 mm dextral: the right side's tiles and strips are labelled about
    ``R +18 ± σ mm``, the left side's about 0; the classes span ±max|right_lateral| of the ok
    features, + (right-lateral) red."""
    import re

    import numpy as np

    res, layers, _, _ = loaded_slip
    slip_mm = 1000.0 * res["RIGHT_LATERAL_SLIP"]
    assert slip_mm == pytest.approx(1000 * OFFSET, abs=1.5)
    for name in ("tiles.gpkg", "strips.gpkg"):
        layer = layers[name]
        if "right_lateral" not in layer.fields().names():
            pytest.skip("the data's fields are renamed by issue #28's sign convention (item 4)")
        labeling = layer.labeling()
        label = labeling.settings().fieldName
        from qgis.core import QgsExpression, QgsExpressionContext, QgsExpressionContextUtils

        expr = QgsExpression(label)
        ctx = QgsExpressionContext(QgsExpressionContextUtils.globalProjectLayerScopes(layer))
        values = {"left": [], "right": []}
        everything = []
        for f in layer.getFeatures():
            ctx.setFeature(f)
            text = expr.evaluate(ctx)
            if f["status"] != "ok":
                assert "skipped" in text
                continue
            everything.append(abs(f["right_lateral"]) * 1000)
            m = re.match(r"([LR]) ([+-][0-9.]+) ± ([0-9.]+) mm$", text)
            assert m and m.group(1) == f["side"][0].upper(), text
            values[f["side"]].append(float(m.group(2)))
        assert np.median(values["right"]) == pytest.approx(slip_mm, abs=3.0), (name, values)
        assert abs(np.median(values["left"])) < 3.0, (name, values)
        rules = sorted(
            (r for r in layer.renderer().rootRule().descendants() if r.description()),
            key=lambda r: int(r.description().split()[1]),
        )
        top = float(re.findall(r"<= (\S+)$", rules[-1].filterExpression())[0])
        assert top * 1000 == pytest.approx(max(everything))
        assert rules[-1].symbol().color().red() > rules[-1].symbol().color().blue()  # +: red


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
    assert items[0].label.endswith(" mm (\u2212 = left-lateral)"), items[0].label
    assert items[-1].label == f"{1000 * m:+.3g} mm (+ = right-lateral)"
    assert items[-1].color.red() > items[-1].color.blue()  # right_lateral_m > 0: red
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


# --------------------------------------------------------------------------- progress, cancel


@pytest.fixture(scope="module")
def unthrottled_slip(slip_pair):
    """The Fault slip run of :func:`loaded_slip` (not loaded) with every progress text kept
    (the dialog's 2 s throttle off), so which text the bar stood at does not depend on the
    machine's speed."""
    import processing
    from qgis.core import QgsProcessingContext, QgsProject

    from slipmap.qgis_plugin.algorithms import _base

    d, fault = slip_pair
    context = QgsProcessingContext()
    context.setProject(QgsProject.instance())
    feedback = _Feedback.make()
    out = d / "unthrottled"
    out.mkdir(exist_ok=True)
    every, _base.PROGRESS_TEXT_EVERY_S = _base.PROGRESS_TEXT_EVERY_S, 0.0
    try:
        processing.run(
            "slipmap:displacement",
            _slip_parameters(d, fault, out),
            context=context,
            feedback=feedback,
        )
    finally:
        _base.PROGRESS_TEXT_EVERY_S = every
    return feedback


def test_progress_bar_follows_the_log(unthrottled_slip):
    """The bar never goes back and ends full, and the moving windows (the job's last phase,
    one adjustment per window) hold their share of it: while the log says "window k/N", the
    bar still has at least 20 % of the run for every remaining whole loop (issue #28: 85 % at
    "window 287/2115" left 10 % for 86 % of the loop). The job ends its computing at 95 %
    (the writing of the outputs is the last 5 %)."""
    feedback = unthrottled_slip
    values = feedback.values
    run = values[: values.index(100.0) + 1]  # then QGIS loads the layers, from 0 again
    back = [(i, a, b) for i, (a, b) in enumerate(zip(run, run[1:])) if b < a]
    assert not back, back[:5]
    windows = [
        (int(m.group(1)) / int(m.group(2)), at)
        for text, at in feedback.text_at
        if (m := re.fullmatch(r"window (\d+)/(\d+)", text))
    ]
    assert windows, feedback.text_at
    for k, at in windows:
        assert 95.0 - at >= 20.0 * (1.0 - k), (k, at, feedback.text_at)
        assert at > 50.0, (k, at)  # after the slip and the strips


def test_cancel_mid_run_leaves_nothing_and_no_finished(slip_pair, tmp_path):
    """Cancel after a few progress steps of a Fault slip run (an algorithm with an HTML
    output): the run raises "Run cancelled.", writes nothing, logs no "finished", and what the
    algorithm dialog runs next (``handleAlgorithmResults``, QGIS's Postprocessing) returns
    False, so the dialog resets instead of printing "Algorithm … finished" and "HTML output
    has been generated"; no layer is loaded."""
    import processing
    from processing.gui.Postprocessing import handleAlgorithmResults
    from qgis.core import (
        QgsApplication,
        QgsProcessingContext,
        QgsProcessingException,
        QgsProject,
    )

    d, fault = slip_pair
    out = tmp_path / "out"
    out.mkdir()
    project = QgsProject.instance()
    project.removeAllMapLayers()
    context = QgsProcessingContext()
    context.setProject(project)
    feedback = _Feedback.make()
    calls = []

    def progress(value):
        calls.append(value)
        if len(calls) == 5:
            feedback.cancel()

    feedback.setProgress = progress
    with pytest.raises(QgsProcessingException, match="Run cancelled"):
        processing.run(
            "slipmap:displacement",
            {
                "BEFORE": str(d / "before.las"),
                "AFTER": str(d / "after.las"),
                "FAULT": fault,
                "SUMMARY": str(out / "slip.json"),
                "PLANES": str(out / "planes.gpkg"),
                "STRIP_WIDTH": 30.0,
            },
            context=context,
            feedback=feedback,
        )
    assert len(calls) == 5
    assert _listing(out) == []
    said = feedback.lines + feedback.texts
    assert not [t for t in said if "finished" in t.lower() or "html output" in t.lower()], said
    alg = QgsApplication.processingRegistry().createAlgorithmById("slipmap:displacement")
    assert alg.hasHtmlOutputs()  # the dialog would print "HTML output has been generated"
    assert handleAlgorithmResults(alg, context, feedback) is False  # 3.22 and 3.40 alike
    assert project.mapLayers() == {}


def test_a_finished_run_leaves_no_cancel_mark(provider, small_cloud, tmp_path):
    from qgis.core import QgsApplication, QgsProcessingContext, QgsProcessingFeedback

    from slipmap.qgis_plugin.algorithms._base import CANCELLED_MARK

    alg = QgsApplication.processingRegistry().createAlgorithmById("slipmap:roughness")
    context, feedback = QgsProcessingContext(), QgsProcessingFeedback()
    params = {
        "INPUT": str(small_cloud),
        "CELL": 2.0,
        "OUTPUT": str(tmp_path / "t.tif"),
        "CSV": str(tmp_path / "c.csv"),
    }
    results, ok = alg.run(params, context, feedback)
    assert ok and CANCELLED_MARK not in context.layersToLoadOnCompletion()


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


def _write_gpkg(layer, path):
    from qgis.core import QgsCoordinateTransformContext, QgsVectorFileWriter

    options = QgsVectorFileWriter.SaveVectorOptions()
    options.driverName = "GPKG"
    error = QgsVectorFileWriter.writeAsVectorFormatV3(
        layer, str(path), QgsCoordinateTransformContext(), options
    )
    assert error[0] == QgsVectorFileWriter.NoError, error


def _doc_blocks():
    """The two sh blocks of docs/qgis.md's "qgis_process examples": the Debian 12 shell
    function, and the commands."""
    from pathlib import Path

    text = (Path(slipmap.__file__).resolve().parent / "docs" / "qgis.md").read_text()
    section = text.split("## qgis_process examples", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```sh\n(.*?)```", section, re.S)
    assert len(blocks) == 2, blocks
    return blocks


@pytest.mark.skipif(_qgis_process() is None, reason="no qgis_process binary (QGIS desktop)")
def test_documented_qgis_process_examples(slip_pair, tmp_path):
    """docs/qgis.md's qgis_process commands, run as printed with bash (on Debian 12 after the
    documented shell function, since the qgis_process wrapper fails there), in a folder with
    the synthetic epochs as before.laz / after.laz and the trace as fault.gpkg, the plugin
    enabled in a throw-away profile and QGIS's Python given laspy and lazrs (as the user's
    ~/.local would): every command succeeds and writes what it names; the help gives
    defaults and no CLI flag."""
    import os
    import subprocess
    from pathlib import Path

    import laspy
    import lazrs

    from slipmap.core.io.las import read_las, write_las

    d, fault = slip_pair
    work = tmp_path / "work"
    work.mkdir()
    for name in ("before", "after"):
        write_las(work / f"{name}.laz", read_las(d / f"{name}.las"))
    _write_gpkg(fault, work / "fault.gpkg")
    site = tmp_path / "site"  # only laspy and lazrs, not the test venv's other packages
    site.mkdir()
    for module in (laspy, lazrs):
        (site / module.__name__).symlink_to(Path(module.__file__).parent)
    plugins = tmp_path / "profile" / "profiles" / "default" / "python" / "plugins"
    plugins.mkdir(parents=True)
    (plugins / "slipmap").symlink_to(Path(slipmap.__file__).resolve().parent)
    env = dict(
        os.environ,
        QGIS_CUSTOM_CONFIG_PATH=str(tmp_path / "profile"),
        PYTHONPATH=str(site),
    )
    env.pop("QT_QPA_PLATFORM", None)  # the documented function sets it
    function, commands = _doc_blocks()
    script = ("set -e\n" + function if shutil.which("qgis_process.bin") else "set -e\n") + (
        commands
    )
    run = subprocess.run(
        ["bash", "-c", script], cwd=work, env=env, capture_output=True, text=True, timeout=900
    )
    assert run.returncode == 0, (run.stdout[-3000:], run.stderr[-3000:])
    written = {p.name for p in work.iterdir()}
    for name in (
        "before_planes.laz",
        "planes.json",
        "slip.json",
        "matched_planes.gpkg",
        "slip_windows.json",
        "tiles.gpkg",
        "strips.gpkg",
        "windows.tif",
        "roughness_2.tif",
        "roughness_2.csv",
        "before_sigma.laz",
    ):
        assert name in written, (name, sorted(written))
    import json

    summary = json.loads((work / "slip_windows.json").read_text())
    assert summary["relative"]["right_lateral_slip"] == pytest.approx(OFFSET, abs=0.0015)
    help_text = run.stdout.split("Fault slip (displacement) (slipmap:displacement)", 1)[1]
    help_text = help_text.split("Planar segmentation", 1)[0]
    assert "Default: full" in help_text or "Default: " in help_text
    assert "--workers" not in help_text and "--scheduler" not in help_text


@pytest.mark.skipif(_qgis_process() is None, reason="no qgis_process binary (QGIS desktop)")
def test_qgis_process_needs_no_output_and_takes_enum_names(slip_pair, tmp_path):
    """qgis_process 3.22 without SUMMARY/PLANES, with STOCHASTIC_MODEL by name and PIV
    without GRID: the outputs go to temporary files, the name is taken, the dialog's default
    grid is used (finding 9); a wrong name is refused naming the choices."""
    import os
    import subprocess
    from pathlib import Path

    import laspy
    import lazrs

    d, _ = slip_pair
    site = tmp_path / "site"
    site.mkdir()
    for module in (laspy, lazrs):
        (site / module.__name__).symlink_to(Path(module.__file__).parent)
    profile = tmp_path / "profile"
    plugins = profile / "profiles" / "default" / "python" / "plugins"
    plugins.mkdir(parents=True)
    (plugins / "slipmap").symlink_to(Path(slipmap.__file__).resolve().parent)
    env = dict(
        os.environ,
        QGIS_CUSTOM_CONFIG_PATH=str(profile),
        PYTHONPATH=str(site),
        QT_QPA_PLATFORM="offscreen",
    )
    exe = [_qgis_process()]
    subprocess.run(exe + ["plugins", "enable", "slipmap"], env=env, capture_output=True)

    def run(*args):
        r = subprocess.run(
            exe + ["run", *args], env=env, capture_output=True, text=True, timeout=600
        )
        return r.returncode, r.stdout + r.stderr

    fault = tmp_path / "fault.gpkg"
    _write_gpkg(slip_pair[1], fault)
    before, after = str(d / "before.las"), str(d / "after.las")
    code, out = run(
        "slipmap:displacement",
        "--",
        f"BEFORE={before}",
        f"AFTER={after}",
        f"FAULT={fault}",
        "STOCHASTIC_MODEL=white",
    )
    assert code == 0, out[-3000:]
    results = out.split("Results", 1)[1]  # temporary files: gone when qgis_process ends
    assert re.search(r"SUMMARY:\s+\S+\.json", results), results
    assert re.search(r"STOCHASTIC_MODEL:\s+white\n", results), results
    code, out = run(
        "slipmap:displacement",
        "--",
        f"BEFORE={before}",
        f"AFTER={after}",
        f"FAULT={fault}",
        "STOCHASTIC_MODEL=fulll",
    )
    assert code != 0 and '"Stochastic model": must be one of white, plane, full' in out, out
    code, out = run("slipmap:piv", "--", f"BEFORE={before}")
    assert code != 0 and "AFTER" in out and "GRID" not in out, out[-2000:]


def test_parameter_help_gives_defaults_in_the_dialogs_words(provider):
    """Each option parameter's help (tooltip; qgis_process help's Arguments) says its default
    or what leaving it empty does, and names no CLI flag; a destination is optional (a
    temporary file when left out) and an enum reads an option's name."""
    from qgis.core import QgsApplication, QgsProcessingParameterDefinition

    registry = QgsApplication.processingRegistry()
    piv = registry.algorithmById("slipmap:piv")
    assert piv.parameterDefinition("GRID").help().endswith("Default: 0.25")
    assert piv.parameterDefinition("GRID").defaultValue() == 0.25
    assert piv.parameterDefinition("PASSES").help().endswith("Left empty: one per window")
    slip = registry.algorithmById("slipmap:displacement")
    assert slip.parameterDefinition("STOCHASTIC_MODEL").help().endswith("by REML (default)")
    assert slip.parameterDefinition("BUFFER").help().count("efault") == 1  # said once
    for alg in registry.providerById("slipmap").algorithms():
        for p in alg.parameterDefinitions():
            assert "--" not in p.help(), (alg.id(), p.name(), p.help())
            if p.isDestination():
                assert p.flags() & QgsProcessingParameterDefinition.FlagOptional, p.name()
    alg = registry.createAlgorithmById("slipmap:displacement")
    run = alg.run_parameters({"STOCHASTIC_MODEL": "Plane", "COMBINE": "1", "UNITS": "gps-time"})
    assert (run["STOCHASTIC_MODEL"], run["COMBINE"], run["UNITS"]) == (1, 1, 2)
    assert run["SUMMARY"] == run["PLANES"] == "TEMPORARY_OUTPUT"
    assert alg.run_parameters({"STOCHASTIC_MODEL": "nope"})["STOCHASTIC_MODEL"] == "nope"
