"""The QGIS plugin object returned by ``classFactory``."""

from __future__ import annotations


class SlipMapPlugin:
    """Registers the SlipMap Processing provider; works with ``iface=None`` (headless)."""

    def __init__(self, iface=None):
        self.iface = iface
        self.provider = None

    def initProcessing(self):  # noqa: N802 (QGIS API name)
        from qgis.core import QgsApplication

        from .provider import SlipMapProvider

        self.provider = SlipMapProvider()
        QgsApplication.processingRegistry().addProvider(self.provider)

    def initGui(self):  # noqa: N802 (QGIS API name)
        self.initProcessing()

    def unload(self):
        if self.provider is not None:
            from qgis.core import QgsApplication

            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
