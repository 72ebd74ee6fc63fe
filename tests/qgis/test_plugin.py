"""The repository root loads as a QGIS plugin and registers the ``slipmap`` provider."""

import pytest

import slipmap

pytestmark = pytest.mark.qgis


def test_class_factory_registers_provider(qgis_app):
    from qgis.core import QgsApplication

    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    try:
        provider = QgsApplication.processingRegistry().providerById("slipmap")
        assert provider is not None
        assert provider.name() == "SlipMap"
        assert provider.versionInfo() == slipmap.__version__
    finally:
        plugin.unload()
    assert QgsApplication.processingRegistry().providerById("slipmap") is None


def test_an_algorithm_that_cannot_load_leaves_the_others(qgis_app, monkeypatch):
    """An import error in one algorithm module is logged; the provider still loads the rest
    (an exception escaping loadAlgorithms would abort QGIS), and a stand-in under the broken
    algorithm's id and name says it could not be loaded and refuses to run."""
    import processing
    from qgis.core import QgsApplication, QgsProcessingException

    from slipmap.qgis_plugin import provider as prov

    broken = ("nosuchmodule", "X", "broken", "Broken", "Slip", "slip")
    monkeypatch.setattr(prov, "ALGORITHMS", (broken,) + tuple(prov.ALGORITHMS[:2]))
    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    try:
        p = QgsApplication.processingRegistry().providerById("slipmap")
        ids = sorted(a.id() for a in p.algorithms())
        assert ids == ["slipmap:broken", "slipmap:displacement", "slipmap:planes"]
        stand_in = p.algorithm("broken")
        ok, message = stand_in.canExecute()
        assert not ok and message.startswith("This algorithm could not be loaded"), message
        assert "nosuchmodule" in message and "needs the Python package" not in message
        with pytest.raises(QgsProcessingException, match="could not be loaded"):
            processing.run("slipmap:broken", {})
    finally:
        plugin.unload()
