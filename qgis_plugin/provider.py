"""The ``slipmap`` Processing provider: every algorithm listed, also where a package is missing.

Where laspy, lazrs or scipy cannot be imported in QGIS's Python, nothing vanishes: the
provider's name in the toolbox and in ``qgis_process list`` says what is missing, its tooltip
gives the one command that installs it on this platform (``compat.missing_message``), every
algorithm's tooltip (``shortDescription``) and ``canExecute()`` say the same, and a run
refuses at once with that command. An algorithm whose module cannot be imported at all (scipy
missing: six of them import it when loaded) is listed as a stand-in with the same id, name
and group, which says the same and runs nothing.
"""

from __future__ import annotations

from qgis.core import QgsProcessingProvider

from .._version import __version__
from . import compat

#: (module, class, id, name, group, group id) of every algorithm, in toolbox order; the id,
#: name and group let a stand-in take the place of an algorithm whose module cannot be
#: imported (tests/qgis/test_dependencies.py checks them against the classes)
ALGORITHMS = (
    ("planes", "PlanesAlgorithm", "planes", "Planar segmentation", "Segmentation", "segmentation"),
    (
        "displacement",
        "DisplacementAlgorithm",
        "displacement",
        "Fault slip (displacement)",
        "Slip",
        "slip",
    ),
    ("roughness", "RoughnessAlgorithm", "roughness", "Surface roughness", "Roughness", "roughness"),
    (
        "accuracy",
        "PointAccuracyAlgorithm",
        "pointaccuracy",
        "Point accuracy",
        "Accuracy",
        "accuracy",
    ),
    ("piv", "PIVAlgorithm", "piv", "Displacement field (PIV)", "Displacement fields", "fields"),
    (
        "windowedicp",
        "WindowedICPAlgorithm",
        "windowedicp",
        "Displacement field (windowed ICP)",
        "Displacement fields",
        "fields",
    ),
    (
        "demdiff",
        "DemDifferenceAlgorithm",
        "demdiff",
        "DEM difference",
        "Displacement fields",
        "fields",
    ),
    (
        "strain",
        "StrainAlgorithm",
        "strain",
        "Strain from a displacement field",
        "Displacement fields",
        "fields",
    ),
)


def missing_state():
    """``(missing packages, message)`` for the whole plugin (``([], "")`` when all are there)."""
    missing = compat.missing_packages()
    return missing, compat.missing_message(missing) if missing else ""


class SlipMapProvider(QgsProcessingProvider):
    def id(self):
        return "slipmap"

    def name(self):
        # the toolbox's node and `qgis_process list`'s heading: where a user looks first
        missing, _ = missing_state()
        if missing:
            return f"SlipMap (cannot run: {', '.join(missing)} missing)"
        return "SlipMap"

    def longName(self):  # noqa: N802 (QGIS API name)
        # the toolbox tooltip of the provider's node
        _, message = missing_state()
        return f"SlipMap {__version__}. {message}" if message else f"SlipMap {__version__}"

    def warningMessage(self):  # noqa: N802 (QGIS API name)
        # the algorithm dialog writes it in red at the start of a run
        return missing_state()[1]

    def versionInfo(self):  # noqa: N802 (QGIS API name)
        return __version__

    def icon(self):
        from qgis.PyQt.QtGui import QIcon

        return QIcon(self.svgIconPath())

    def svgIconPath(self):  # noqa: N802 (QGIS API name)
        from pathlib import Path

        return str(Path(__file__).resolve().parent / "icons" / "slipmap.svg")

    def loadAlgorithms(self):  # noqa: N802 (QGIS API name)
        # The algorithm modules import only qgis (and what SlipMap itself needs at load time)
        # when loaded: without laspy/lazrs the real algorithms load and their canExecute()
        # says how to install them. A module that cannot be imported (scipy missing, or a
        # bug) is replaced by a stand-in that says why and refuses to run; the reason is
        # logged too. An exception escaping loadAlgorithms would abort QGIS.
        import importlib

        from qgis.core import Qgis, QgsMessageLog

        for module, name, alg_id, display, group, group_id in ALGORITHMS:
            try:
                cls = getattr(importlib.import_module(f".algorithms.{module}", __package__), name)
                alg = cls()
            except Exception as exc:  # noqa: BLE001 - report and go on with the others
                known = getattr(exc, "name", None) in compat.PACKAGES  # said once by the plugin
                QgsMessageLog.logMessage(
                    f"SlipMap: algorithm {alg_id} not loaded: {type(exc).__name__}: {exc}",
                    "SlipMap",
                    Qgis.Info if known else Qgis.Critical,
                )
                alg = _stand_in(alg_id, display, group, group_id, exc)
                if alg is None:
                    continue
            self.addAlgorithm(alg)


def _stand_in(alg_id, display, group, group_id, exc):
    """An algorithm that takes the place of one whose module failed to import with ``exc``:
    listed under the same id, name and group, it says why and refuses to run (None where even
    that cannot be built)."""
    try:
        from .algorithms._stand_in import StandInAlgorithm
    except Exception:  # noqa: BLE001 - nothing better to show; the log has the reason
        return None
    return StandInAlgorithm.make(alg_id, display, group, group_id, exc)
