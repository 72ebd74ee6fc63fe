"""Headless QGIS for the plugin tests (skipped where QGIS's Python bindings are missing)."""

import os
import sys

import pytest


@pytest.fixture(scope="session")
def qgis_app():
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    pytest.importorskip("qgis.core", reason="QGIS Python bindings (python3-qgis) missing")
    from qgis.core import QgsApplication

    app = QgsApplication([], False)
    app.initQgis()
    plugins = "/usr/share/qgis/python/plugins"
    if plugins not in sys.path:
        sys.path.append(plugins)
    from processing.core.Processing import Processing

    Processing.initialize()
    yield app


@pytest.fixture(scope="module")
def provider(qgis_app):
    """The SlipMap provider registered in Processing (the plugin as QGIS loads it), for one
    test module."""
    import slipmap

    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    yield
    plugin.unload()
