"""The QGIS plugin object returned by ``classFactory``."""

from __future__ import annotations


class SlipMapPlugin:
    """Registers the SlipMap Processing provider; works with ``iface=None`` (headless).

    Where a package the algorithms need is missing, loading says so where the user is: the
    SlipMap tab of the Log Messages panel (and ``qgis_process``'s stderr) always, and in the
    desktop a warning in the message bar with the one command that installs it.
    """

    def __init__(self, iface=None):
        self.iface = iface
        self.provider = None

    def initProcessing(self):  # noqa: N802 (QGIS API name)
        from qgis.core import Qgis, QgsApplication, QgsMessageLog

        from .provider import SlipMapProvider, missing_state

        self.provider = SlipMapProvider()
        QgsApplication.processingRegistry().addProvider(self.provider)
        missing, message = missing_state()
        if missing:
            # Critical: qgis_process prints it (on stderr) before its own output
            QgsMessageLog.logMessage(message, "SlipMap", Qgis.Critical)

    def initGui(self):  # noqa: N802 (QGIS API name)
        self.initProcessing()
        self.show_missing()

    def show_missing(self):
        """The missing-package warning in the desktop's message bar (no-op headless or when
        nothing is missing). Returns the message shown ('' when none)."""
        from .provider import missing_state

        missing, message = missing_state()
        if not missing or self.iface is None:
            return ""
        from qgis.core import Qgis

        try:
            self.iface.messageBar().pushMessage("SlipMap", message, Qgis.Warning, 0)
        except Exception:  # noqa: BLE001 - a message must never stop QGIS from starting
            return ""
        return message

    def unload(self):
        if self.provider is not None:
            from qgis.core import QgsApplication

            QgsApplication.processingRegistry().removeProvider(self.provider)
            self.provider = None
