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
