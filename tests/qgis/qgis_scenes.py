"""Synthetic scenes shared by the QGIS tests (imported as ``from qgis_scenes import ...``)."""

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
