"""SlipMap: fault slip, 3D displacement and roughness from repeat LiDAR surveys.

This folder is both the Python package ``slipmap`` and a QGIS plugin folder. Importing it
imports nothing heavy; QGIS calls :func:`classFactory`.
"""

from __future__ import annotations

from ._version import __version__

__all__ = ["__version__", "classFactory"]


def classFactory(iface):  # noqa: N802 (QGIS plugin entry point name)
    """QGIS plugin entry point: return the SlipMap plugin instance."""
    from .qgis_plugin.plugin import SlipMapPlugin

    return SlipMapPlugin(iface)
