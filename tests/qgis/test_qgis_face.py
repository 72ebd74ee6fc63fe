"""The QGIS face as GIS analysts meet it (issue #19): install hint, output folders checked
before running, loaded outputs (styles, legends, names, order), log, help; through
``processing.run`` on a small synthetic fault."""

from __future__ import annotations

import pytest

import slipmap

pytestmark = pytest.mark.qgis


@pytest.fixture(scope="module")
def provider(qgis_app):
    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    yield
    plugin.unload()


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
