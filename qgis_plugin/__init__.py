"""SlipMap's QGIS face: a Processing provider (filled by the QGIS issue)."""
