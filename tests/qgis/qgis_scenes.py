"""Synthetic scenes, and a reader of the layers the algorithms write, shared by the QGIS tests
(imported as ``from qgis_scenes import ...``)."""

from __future__ import annotations

import numpy as np


def rough_surface(xy, origin_xy, seed=11):
    """Elevation (m) of a smooth rough surface at ``xy`` ((N, 2), metres): 100 m plus a sum of
    12 random plane waves of 1.5-6 m wavelength and 5-15 cm amplitude, phases measured from
    ``origin_xy``; the same ``seed`` gives the same surface."""
    rng = np.random.default_rng(seed)
    z = np.full(len(xy), 100.0)
    for _ in range(12):
        wl = rng.uniform(1.5, 6.0)
        th = rng.uniform(0, np.pi)
        k = 2 * np.pi / wl * np.array([np.cos(th), np.sin(th)])
        z += rng.uniform(0.05, 0.15) * np.sin((xy - origin_xy) @ k + rng.uniform(0, 2 * np.pi))
    return z


def features(path):
    """A vector file's layer (QGIS's ogr provider, as a user opens it), its field names and
    its rows as (F, 2 + fields) float64: each feature's centroid x, y, then its attributes,
    NaN where NULL."""
    from qgis.core import QgsVectorLayer

    layer = QgsVectorLayer(str(path), "out", "ogr")
    assert layer.isValid(), path
    names = [f.name() for f in layer.fields()]
    rows = []
    for f in layer.getFeatures():
        p = f.geometry().centroid().asPoint()
        rows.append(
            [p.x(), p.y()] + [np.nan if v is None or _is_null(v) else v for v in f.attributes()]
        )
    return layer, names, np.array(rows, dtype=np.float64)


def column(names, rows, name):
    """The column ``name`` of :func:`features`' rows."""
    return rows[:, 2 + names.index(name)]


def _is_null(value):
    return hasattr(value, "isNull") and value.isNull()
