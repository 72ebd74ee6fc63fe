"""The ``slipmap`` Processing provider. Algorithms are added as their core lands."""

from __future__ import annotations

from qgis.core import QgsProcessingProvider

from .._version import __version__


class SlipMapProvider(QgsProcessingProvider):
    def id(self):
        return "slipmap"

    def name(self):
        return "SlipMap"

    def longName(self):  # noqa: N802 (QGIS API name)
        return f"SlipMap {__version__}"

    def versionInfo(self):  # noqa: N802 (QGIS API name)
        return __version__

    def loadAlgorithms(self):  # noqa: N802 (QGIS API name)
        # Filled by the QGIS Processing issue (#8).
        return
