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
    (an exception escaping loadAlgorithms would abort QGIS)."""
    from qgis.core import QgsApplication

    from slipmap.qgis_plugin import provider as prov

    monkeypatch.setattr(prov, "ALGORITHMS", (("nosuchmodule", "X"),) + tuple(prov.ALGORITHMS[:2]))
    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    try:
        p = QgsApplication.processingRegistry().providerById("slipmap")
        ids = sorted(a.id() for a in p.algorithms())
        assert ids == ["slipmap:displacement", "slipmap:planes"]
    finally:
        plugin.unload()
