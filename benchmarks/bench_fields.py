"""Benchmark of the displacement-field kernels (issue #6) against np.sort.

1. PIV: two textured synthetic DEMs of ``--dem`` x ``--dem`` cells (Gaussian-filtered noise at
   several scales, 2 % of the cells NaN), the second shifted by a known sub-pixel offset;
   :func:`slipmap.core.piv.piv` with the default passes. Ratio to ``np.sort`` of as many
   float64 values as the DEM has cells.
2. Windowed ICP: two independent samplings of ``--n`` points each of a rough synthetic surface
   (UTM offsets, ~400 pts/m², as lone-star), the second moved by a known small rotation and
   translation; :func:`slipmap.core.icp.windowed_icp` with ``--cell`` m cells. Ratio to
   ``np.sort`` of ``2 * n`` float64 (all the points the run touches).

Accuracy of both is printed too (they must recover the injected motion).

Usage::

    python benchmarks/bench_fields.py [--dem 2500] [--n 5000000] [--cell 5] [--seed 0]

The last line is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
from scipy import ndimage

from slipmap.core.dem import Grid
from slipmap.core.icp import windowed_icp
from slipmap.core.piv import piv

ORIGIN = (512_000.0, 4_780_000.0)


def _sort_seconds(n: int, seed: int) -> float:
    a = np.random.default_rng(seed).random(n)
    t0 = time.perf_counter()
    np.sort(a)
    return time.perf_counter() - t0


def textured_dem(n: int, seed: int) -> np.ndarray:
    """(n, n) float64 elevations (m): multi-scale smoothed noise, like rough ground."""
    rng = np.random.default_rng(seed)
    z = np.zeros((n, n))
    for sigma, amp in ((2.0, 0.05), (6.0, 0.2), (20.0, 0.6)):
        f = ndimage.gaussian_filter(rng.standard_normal((n, n)), sigma, mode="wrap")
        z += amp * f / f.std()
    return z


def bench_piv(n: int, seed: int, shift_px=(2.3, -1.6)) -> dict:
    cell = 0.04  # the study's GR
    z = textured_dem(n + 16, seed)
    # after = before moved by (dx, dy) px: sample before at (col - dx, row + dy)
    rows, cols = np.mgrid[0:n, 0:n].astype(np.float64)
    dx_px, dy_px = shift_px
    zb = z[8 : 8 + n, 8 : 8 + n].copy()
    za = ndimage.map_coordinates(z, [rows + 8 + dy_px, cols + 8 - dx_px], order=3)
    holes = np.random.default_rng(seed + 1).random((n, n)) < 0.02
    zb[holes] = np.nan
    za[np.roll(holes, 7, axis=1)] = np.nan
    grid = Grid(x_min=ORIGIN[0], y_max=ORIGIN[1], cell_m=cell, n_rows=n, n_cols=n)
    t0 = time.perf_counter()
    res = piv(zb, za, grid=grid)
    seconds = time.perf_counter() - t0
    t_sort = _sort_seconds(n * n, seed)
    ok = res.valid & np.isfinite(res.dx)
    err = np.hypot(res.dx[ok] / cell - dx_px, res.dy[ok] / cell - dy_px)
    return {
        "dem_cells": n * n,
        "vectors": int(res.dx.size),
        "valid_fraction": round(float(ok.mean()), 4),
        "rms_error_px": round(float(np.sqrt(np.mean(err**2))), 4),
        "seconds": round(seconds, 3),
        "sort_seconds": round(t_sort, 4),
        "ratio_to_sort": round(seconds / t_sort, 2),
    }


def rough_surface(n: int, seed: int, side_m: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, side_m, (n, 2))
    x, y = xy[:, 0], xy[:, 1]
    z = (
        0.8 * np.sin(2 * np.pi * x / 17.0) * np.cos(2 * np.pi * y / 23.0)
        + 0.25 * np.sin(2 * np.pi * (x + 0.6 * y) / 3.7)
        + 0.08 * np.sin(2 * np.pi * (0.8 * x - y) / 1.3)
        + 0.003 * rng.standard_normal(n)
    )
    return np.column_stack([x + ORIGIN[0], y + ORIGIN[1], z + 1500.0])


def bench_icp(n: int, cell: float, seed: int) -> dict:
    side = float(np.sqrt(n / 400.0))
    before = rough_surface(n, seed, side)
    after = rough_surface(n, seed + 1, side)
    t = np.array([0.12, -0.07, 0.03])
    a = 2e-4  # rad about z, around the scene centre
    c = np.array([ORIGIN[0] + side / 2, ORIGIN[1] + side / 2, 1500.0])
    r = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    after = (after - c) @ r.T + c + t
    t0 = time.perf_counter()
    res = windowed_icp(before, after, cell_m=cell)
    seconds = time.perf_counter() - t0
    t_sort = _sort_seconds(2 * n, seed)
    # truth: the ground motion at each cell centre p (after frame): p - T(p), T = inverse motion
    p = np.column_stack([res.x, res.y, res.z])
    p_before = (p - t - c) @ r + c
    truth = p - p_before
    err = np.column_stack([res.dx, res.dy, res.dz]) - truth
    return {
        "points_per_epoch": n,
        "cell_m": cell,
        "cells": len(res),
        "skipped": dict(res.skipped),
        "rms_error_mm": [round(float(v), 3) for v in 1000 * np.sqrt(np.mean(err**2, axis=0))],
        "seconds": round(seconds, 3),
        "sort_seconds": round(t_sort, 4),
        "ratio_to_sort": round(seconds / t_sort, 2),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dem", type=int, default=2500)
    ap.add_argument("--n", type=int, default=5_000_000)
    ap.add_argument("--cell", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    p = bench_piv(args.dem, args.seed)
    print(
        f"PIV {args.dem}x{args.dem}: {p['vectors']} vectors in {p['seconds']} s "
        f"({p['ratio_to_sort']}x np.sort of {p['dem_cells']}), valid {p['valid_fraction']}, "
        f"RMS error {p['rms_error_px']} px"
    )
    i = bench_icp(args.n, args.cell, args.seed)
    print(
        f"ICP 2x{args.n}: {i['cells']} cells of {args.cell} m in {i['seconds']} s "
        f"({i['ratio_to_sort']}x np.sort of {2 * args.n}), RMS error {i['rms_error_mm']} mm"
    )
    print(json.dumps({"piv": p, "icp": i}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
