"""Checks of the optional Python packages the algorithms need inside QGIS's Python."""

from __future__ import annotations

import importlib.util

INSTALL_HINT = (
    "pip install laspy lazrs into QGIS's Python: on Windows run `python -m pip install laspy "
    "lazrs` from the OSGeo4W Shell; on Linux/macOS run `<QGIS python> -m pip install laspy lazrs`"
)


def missing_packages() -> list:
    """Names of the required packages that cannot be imported (empty when all are there)."""
    return [name for name in ("laspy", "lazrs") if importlib.util.find_spec(name) is None]


def can_execute():
    """``(True, "")`` or ``(False, install hint)`` for ``QgsProcessingAlgorithm.canExecute``."""
    missing = missing_packages()
    if missing:
        return False, f"{INSTALL_HINT} (missing: {', '.join(missing)})"
    return True, ""
