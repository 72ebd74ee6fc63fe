"""The ``slipmap`` Processing provider. Algorithms are added as their core lands."""

from __future__ import annotations

from qgis.core import QgsProcessingProvider

from .._version import __version__

#: (module, class) of every algorithm, in toolbox order
ALGORITHMS = (
    ("planes", "PlanesAlgorithm"),
    ("displacement", "DisplacementAlgorithm"),
    ("roughness", "RoughnessAlgorithm"),
    ("accuracy", "PointAccuracyAlgorithm"),
    ("piv", "PIVAlgorithm"),
    ("windowedicp", "WindowedICPAlgorithm"),
    ("demdiff", "DemDifferenceAlgorithm"),
    ("strain", "StrainAlgorithm"),
)


class SlipMapProvider(QgsProcessingProvider):
    def id(self):
        return "slipmap"

    def name(self):
        return "SlipMap"

    def longName(self):  # noqa: N802 (QGIS API name)
        return f"SlipMap {__version__}"

    def versionInfo(self):  # noqa: N802 (QGIS API name)
        return __version__

    def icon(self):
        from qgis.PyQt.QtGui import QIcon

        return QIcon(self.svgIconPath())

    def svgIconPath(self):  # noqa: N802 (QGIS API name)
        from pathlib import Path

        return str(Path(__file__).resolve().parent / "icons" / "slipmap.svg")

    def loadAlgorithms(self):  # noqa: N802 (QGIS API name)
        # The algorithm modules import only qgis at load time: the provider loads without
        # laspy/lazrs, and each algorithm's canExecute() then says how to install them. An
        # algorithm whose module cannot be imported is left out and logged; the others load
        # (an exception escaping loadAlgorithms would abort QGIS).
        import importlib

        from qgis.core import Qgis, QgsMessageLog

        for module, name in ALGORITHMS:
            try:
                cls = getattr(importlib.import_module(f".algorithms.{module}", __package__), name)
            except Exception as exc:  # noqa: BLE001 - report and go on with the others
                QgsMessageLog.logMessage(
                    f"SlipMap: algorithm {module} not loaded: {type(exc).__name__}: {exc}",
                    "SlipMap",
                    Qgis.Critical,
                )
                continue
            self.addAlgorithm(cls())
