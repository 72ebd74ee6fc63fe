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
