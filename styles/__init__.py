"""The QML styles of SlipMap's outputs (QGIS's own style format), as package data.

They live here, outside the QGIS plugin, so that every face can ship them with its outputs:
the QGIS algorithms apply them on load, and the writers of the application layer store them
with the data (a GeoPackage's ``layer_styles`` table, a ``.qml`` beside a GeoTIFF) so the
CLI's, qgis_process's and PDAL's outputs open styled too. Reading them needs no QGIS.

They are templates (``scripts/make_styles.py``, ``scripts/make_slip_styles.py``): the numbers
that depend on the data are ``{slipmap.NAME}`` tokens and raster ramps are stored on [-1, 1];
:mod:`slipmap.app.styles` fits them to an output (its ``vector_qml`` / ``raster_qml``).
"""

from __future__ import annotations

from pathlib import Path

STYLES_DIR = Path(__file__).resolve().parent


def style_path(name):
    """Path of the bundled style ``<name>.qml`` as a string (None when there is none)."""
    p = STYLES_DIR / f"{name}.qml"
    return str(p) if p.is_file() else None
