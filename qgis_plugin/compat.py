"""Checks of the optional Python packages the algorithms need inside QGIS's Python."""

from __future__ import annotations

import importlib.util

#: what to run where laspy/lazrs are missing; plain text (no "<...>": QGIS shows the message in
#: rich-text tooltips and message boxes, which would swallow it as a tag)
INSTALL_HINT = (
    "SlipMap needs the Python packages laspy and lazrs in the Python that QGIS runs; install "
    "them and restart QGIS. "
    "Debian or Ubuntu (QGIS from the distribution; its Python is externally managed and there "
    "is no Debian package of laspy): python3 -m pip install --user --break-system-packages "
    "laspy lazrs. "
    "Windows: in the OSGeo4W Shell, python -m pip install laspy lazrs. "
    "macOS: /Applications/QGIS.app/Contents/MacOS/bin/python3 -m pip install laspy lazrs "
    "(QGIS-LTR.app for the LTR)."
)


def missing_packages() -> list:
    """Names of the required packages that cannot be imported (empty when all are there)."""
    return [name for name in ("laspy", "lazrs") if importlib.util.find_spec(name) is None]


def can_execute():
    """``(True, "")`` or ``(False, install hint)`` for ``QgsProcessingAlgorithm.canExecute``."""
    missing = missing_packages()
    if missing:
        return False, f"Missing: {', '.join(missing)}. {INSTALL_HINT}"
    return True, ""


# --------------------------------------------------------------------------- QGIS API versions
# QGIS 3.38/3.40 deprecated API that SlipMap used since 3.22; these helpers call the new API where
# it exists and the old one elsewhere, so no DeprecationWarning shows on 3.40 and 3.22 still runs
# (QGIS 4 / Qt 6 removes the deprecated API: docs/qgis.md, "QGIS 4 / Qt 6").

#: field type names for :func:`make_field`, as QMetaType/QVariant type numbers (equal in Qt 5)
FIELD_TYPES = {"bool": 1, "int": 2, "longlong": 4, "double": 6, "string": 10}


def _qgis_version_int() -> int:
    from qgis.core import Qgis

    return int(Qgis.QGIS_VERSION_INT)


def make_field(name: str, kind):
    """A ``QgsField`` of type ``kind`` without the constructor deprecated in QGIS 3.38.

    ``kind`` is a name of :data:`FIELD_TYPES` ('double', 'int', 'longlong', 'string', 'bool')
    or a Qt type value (``QVariant.Double`` or ``QMetaType.Type.Double``). QGIS >= 3.38 is
    given a ``QMetaType.Type`` (the QVariant.Type constructor is deprecated there and gone in
    QGIS 4); older QGIS a ``QVariant.Type``.
    """
    from qgis.core import QgsField

    code = FIELD_TYPES[kind.lower()] if isinstance(kind, str) else int(getattr(kind, "value", kind))
    if _qgis_version_int() >= 33800:
        from qgis.PyQt.QtCore import QMetaType

        return QgsField(name, QMetaType.Type(code))
    from qgis.PyQt.QtCore import QVariant

    return QgsField(name, QVariant.Type(code))


def renderer_band(renderer) -> int:
    """The input band of a raster renderer (``inputBand()`` since QGIS 3.38, else ``band()``)."""
    if hasattr(renderer, "inputBand"):
        return int(renderer.inputBand())
    return int(renderer.band())


def set_renderer_band(renderer, band: int) -> None:
    """Set a raster renderer's input band (``setInputBand`` since QGIS 3.38, else ``setBand``)."""
    if hasattr(renderer, "setInputBand"):
        renderer.setInputBand(int(band))
    else:
        renderer.setBand(int(band))


def band_statistics(provider, band: int, stats=("Min", "Max")):
    """``provider.bandStatistics(band, …)`` holding at least the statistics named in ``stats``.

    ``stats`` holds ``QgsRasterBandStats`` names: 'Min', 'Max', 'Range', 'Sum', 'Mean',
    'StdDev', 'SumOfSquares', 'All'. QGIS 3.40 deprecates the call with int flags, and its
    Python binding takes that overload whenever ``stats`` is passed at all (also for
    ``Qgis.RasterBandStatistic`` flags), so from 3.40 on every statistic is computed (the
    default, one pass over the band) and the requested ones are among them.
    """
    if _qgis_version_int() >= 34000:
        return provider.bandStatistics(int(band))
    from qgis.core import QgsRasterBandStats

    flags = 0
    for name in stats:
        flags |= int(getattr(QgsRasterBandStats, name))
    return provider.bandStatistics(int(band), flags)
