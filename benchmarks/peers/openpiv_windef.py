"""Peer estimator: OpenPIV's multi-pass window-deformation PIV (``openpiv.windef``) on two DEMs.

Run with the peer venv's python (``benchmarks/peers/setup_peer_venv.sh``), never with the
project's: OpenPIV is not a SlipMap dependency (and is GPLv3).

Usage: ``python openpiv_windef.py IN.npz OUT.json``

``IN.npz``: ``z_before``, ``z_after`` (``(R, C)`` float64 elevations on one grid, row 0 north,
NaN = no data), ``windows_px`` (int, one window side per pass), scalars ``overlap`` (fraction,
as SlipMap's ``piv``) and ``max_displacement_px`` (the first-pass validation range).

OpenPIV correlates images without a data mask, so each DEM is made an image by subtracting
its mean and setting the gaps to 0 (the mean). The passes are OpenPIV's own: ``first_pass``,
``typical_validation`` + ``replace_outliers``, then ``multipass_img_deform`` per later pass
(symmetric deformation, cubic image interpolation), with normalised, zero-padded ("linear")
correlation (better than the default circular, unnormalised one on DEMs with gaps: the
circular correlation wraps the heights' trend around the window).

``OUT.json``: ``x``, ``y`` (window centres in pixel-edge coordinates of the image: column /
row from the upper-left corner, as OpenPIV returns them), ``u`` (pixels, +column), ``v``
(pixels, +row, i.e. southward), ``valid`` (not flagged by the last pass's validation),
``seconds`` (all passes, not file I/O), ``openpiv_version`` and ``settings``.
"""

from __future__ import annotations

import json
import logging
import sys
import time

import numpy as np
import openpiv
from openpiv import filters, validation, windef
from openpiv.settings import PIVSettings

logging.getLogger("openpiv").setLevel(logging.ERROR)


def _image(z: np.ndarray) -> np.ndarray:
    z = np.asarray(z, dtype=np.float64)
    img = z - np.nanmean(z)
    return np.where(np.isfinite(img), img, 0.0)


def run(z_before, z_after, windows_px, overlap: float, max_displacement_px: float) -> dict:
    """OpenPIV windef passes on two DEMs; see the module docstring."""
    windows = tuple(int(w) for w in windows_px)
    s = PIVSettings()
    s.windowsizes = windows
    s.overlap = tuple(int(round(w * overlap)) for w in windows)
    s.num_iterations = len(windows)
    s.correlation_method = "linear"
    s.normalized_correlation = True
    m = float(max_displacement_px)
    s.min_max_u_disp = (-m, m)
    s.min_max_v_disp = (-m, m)
    frame_a, frame_b = _image(z_before), _image(z_after)
    t0 = time.perf_counter()
    x, y, u, v, s2n = windef.first_pass(frame_a, frame_b, s)
    u = np.ma.masked_array(u, mask=np.zeros_like(u, dtype=bool))
    v = np.ma.masked_array(v, mask=np.zeros_like(v, dtype=bool))
    flags = validation.typical_validation(u, v, s2n, s)
    u, v = filters.replace_outliers(
        u, v, flags, method=s.filter_method, max_iter=s.max_filter_iteration,
        kernel_size=s.filter_kernel_size,
    )  # fmt: skip
    for i in range(1, s.num_iterations):
        x, y, u, v, _, flags = windef.multipass_img_deform(frame_a, frame_b, i, x, y, u, v, s)
    seconds = time.perf_counter() - t0
    u = np.ma.filled(np.ma.masked_invalid(u), np.nan)
    v = np.ma.filled(np.ma.masked_invalid(v), np.nan)
    valid = ~np.asarray(flags, dtype=bool) & np.isfinite(u) & np.isfinite(v)
    return {
        "x": np.asarray(x, dtype=float).tolist(),
        "y": np.asarray(y, dtype=float).tolist(),
        "u": np.asarray(u, dtype=float).tolist(),
        "v": np.asarray(v, dtype=float).tolist(),
        "valid": valid.tolist(),
        "seconds": seconds,
        "openpiv_version": getattr(openpiv, "__version__", "unknown"),
        "settings": {
            "windowsizes": list(s.windowsizes),
            "overlap": list(s.overlap),
            "correlation_method": s.correlation_method,
            "normalized_correlation": s.normalized_correlation,
            "deformation_method": s.deformation_method,
            "interpolation_order": s.interpolation_order,
            "min_max_disp_px": m,
        },
    }


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    with np.load(argv[0]) as f:
        out = run(
            f["z_before"],
            f["z_after"],
            f["windows_px"],
            float(f["overlap"]),
            float(f["max_displacement_px"]),
        )
    with open(argv[1], "w", encoding="utf-8") as fh:
        json.dump(out, fh)
    return 0


if __name__ == "__main__":
    sys.exit(main())
