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
        # The algorithm modules import only qgis at load time: the provider loads without
        # laspy/lazrs, and each algorithm's canExecute() then says how to install them.
        from .algorithms.accuracy import PointAccuracyAlgorithm
        from .algorithms.demdiff import DemDifferenceAlgorithm
        from .algorithms.displacement import DisplacementAlgorithm
        from .algorithms.piv import PIVAlgorithm
        from .algorithms.planes import PlanesAlgorithm
        from .algorithms.roughness import RoughnessAlgorithm
        from .algorithms.strain import StrainAlgorithm
        from .algorithms.windowedicp import WindowedICPAlgorithm

        for cls in (
            PlanesAlgorithm,
            DisplacementAlgorithm,
            RoughnessAlgorithm,
            PointAccuracyAlgorithm,
            PIVAlgorithm,
            WindowedICPAlgorithm,
            DemDifferenceAlgorithm,
            StrainAlgorithm,
        ):
            self.addAlgorithm(cls())
