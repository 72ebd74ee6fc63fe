"""Validation of PIV, windowed ICP and DEM differencing on lone-star with an injected lobe.

As Aryal et al. (section 3.2.3) do: a real cloud (tests/data/lone-star.laz, Lone Star geyser
cone, ~390 pts/m², 32 m x 41 m) is split at random into two disjoint halves; the second half is
moved by a smooth landslide-like lobe (peak -1 m north, -0.4 m vertical, ``d = d_max (1 - r²)²``
inside an ellipse of radius ~10.8 m, :func:`slipmap.core.synthetic.make_lobe_pair`). The
fields recovered for several grid, window and cell sizes are compared with the truth:

* PIV: vectors sit at window centres in the before image, so the truth is ``field(x, y)``.
  RMSE, bias and valid fraction over the lobe's interior (``r <= 0.5``) and over the whole
  lobe (``r < 1``); the RMSE is also given in grid cells.
* ICP: a cell's displacement is the motion of the material now at its centre ``c`` (after
  frame), so the truth is ``field(p0)`` with ``p0 + field(p0) = c`` (fixed-point iteration);
  a rigid cell can only see the mean motion of its points, so the RMSE against that cell mean
  is given too.
  Cells with at least 500 correspondences, inside the lobe and in the stable area.
* DEM differencing measures elevation change at fixed places, not the motion of the ground:
  its "dz" is compared with the true vertical motion to show the difference.

Usage: ``python benchmarks/validate_fields.py [--seeds 2]``. Prints a Markdown table (the one in
docs/fields.md); the last line is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from slipmap.core.dem import common_grid, dem_difference, grid_elevation
from slipmap.core.icp import windowed_icp
from slipmap.core.io.las import read_las
from slipmap.core.piv import piv
from slipmap.core.synthetic import make_lobe_pair

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "lone-star.laz"

PIV_CASES = [
    (0.1, (64, 32, 16)),
    (0.1, (64, 32, 16, 16)),
    (0.2, (32, 16, 16)),
    (0.25, (32, 16, 8)),
    (0.25, (32, 16, 16)),
    (0.25, (16, 8)),
]
ICP_CASES = [(2.0, 0), (2.0, 1), (3.0, 1), (5.0, 0)]


def _rms(a):
    a = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


def piv_case(pair, cell, windows):
    t0 = time.perf_counter()
    grid = common_grid(pair.before, pair.after, cell_m=cell)
    zb = grid_elevation(pair.before, grid=grid)
    za = grid_elevation(pair.after, grid=grid)
    d_max = float(np.max(np.abs(pair.field.max_d_m[:2])))
    res = piv(zb, za, grid=grid, windows_px=windows, expected_max_displacement_m=1.2 * d_max)
    sec = time.perf_counter() - t0
    xy = np.column_stack([res.x.ravel(), res.y.ravel()])
    truth = pair.field(xy)
    est = np.column_stack([res.dx.ravel(), res.dy.ravel(), res.dz.ravel()])
    out = {"grid_m": cell, "windows_px": list(windows), "seconds": round(sec, 2)}
    for name, frac in (("interior", 0.5), ("lobe", 0.999)):
        m = pair.field.interior_mask(xy, fraction=frac) & np.isfinite(est[:, 0])  # has data
        ok = m & res.valid.ravel()
        e = est[ok] - truth[ok]
        h = np.hypot(e[:, 0], e[:, 1])
        zok = np.isfinite(e[:, 2])
        out[name] = {
            "n": int(m.sum()),
            "valid_fraction": round(float(ok.sum() / max(m.sum(), 1)), 3),
            "rmse_h_m": round(_rms(h), 4),
            "rmse_h_cells": round(_rms(h) / cell, 3),
            "median_h_cells": round(float(np.median(h)) / cell, 3) if h.size else None,
            "p95_h_cells": round(float(np.percentile(h, 95)) / cell, 3) if h.size else None,
            "bias_dx_m": round(float(e[:, 0].mean()) if len(e) else np.nan, 4),
            "bias_dy_m": round(float(e[:, 1].mean()) if len(e) else np.nan, 4),
            "rmse_dz_m": round(_rms(e[zok, 2]), 4),
        }
    return out


def _truth_after_frame(field, c_xy, iterations=20):
    p0 = c_xy.copy()
    for _ in range(iterations):
        p0 = c_xy - field(p0)[:, :2]
    return field(p0)


def _cell_mean_truth(pair, res):
    """Mean applied motion of each fitted cell's after-points (what a rigid cell can see)."""
    x0, y0 = res.origin_xy
    col = np.floor((pair.after[:, 0] - x0) / res.cell_m).astype(np.int64)
    row = np.floor((y0 - pair.after[:, 1]) / res.cell_m).astype(np.int64)
    ok = (row >= 0) & (row < res.n_rows) & (col >= 0) & (col < res.n_cols)
    key = row[ok] * res.n_cols + col[ok]
    size = res.n_rows * res.n_cols
    n = np.bincount(key, minlength=size)
    k = res.row * res.n_cols + res.col
    sums = [np.bincount(key, pair.after_truth[ok, j], size)[k] for j in range(3)]
    return np.column_stack(sums) / np.maximum(n[k], 1)[:, None]


def icp_case(pair, cell, levels):
    t0 = time.perf_counter()
    res = windowed_icp(pair.before, pair.after, cell_m=cell, coarse_to_fine=levels)
    sec = time.perf_counter() - t0
    c = np.column_stack([res.x, res.y])
    truth = _truth_after_frame(pair.field, c)
    mean_truth = _cell_mean_truth(pair, res)
    est = np.column_stack([res.dx, res.dy, res.dz])
    dense = res.n >= 500
    inside = np.linalg.norm(truth, axis=1) > 0
    out = {"cell_m": cell, "coarse_to_fine": levels, "cells": len(res), "seconds": round(sec, 2)}
    out["sigma_factor"] = round(res.sigma_factor, 2)
    for name, m in (("lobe", dense & inside), ("stable", dense & ~inside), ("all", dense)):
        sig = np.sqrt(res.sigma_dx[m] ** 2 + res.sigma_dy[m] ** 2 + res.sigma_dz[m] ** 2)
        e = est[m] - truth[m]
        em = est[m] - mean_truth[m]
        h = np.linalg.norm(e, axis=1)
        out[name] = {
            "cells": int(m.sum()),
            "rmse_3d_m": round(_rms(h), 4),
            "median_3d_m": round(float(np.median(h)), 4) if m.any() else None,
            "rmse_dx_dy_dz_m": [round(_rms(e[:, k]), 4) for k in range(3)],
            "rmse_3d_vs_cell_mean_m": round(_rms(np.linalg.norm(em, axis=1)), 4),
            "median_sigma_3d_m": round(float(np.median(sig)), 4) if m.any() else None,
            **_coverage(res, e, m),
        }
    return out


def _coverage(res, err, m):
    """Fraction of error components within 2 sigma, with the reported (field-scaled) and the
    formal sigmas."""
    if not m.any():
        return {"within_2sigma": None, "within_2sigma_formal": None}
    sig = np.column_stack([res.sigma_dx, res.sigma_dy, res.sigma_dz])[m]
    z = np.abs(err) / sig
    return {
        "within_2sigma": round(float(np.mean(z < 2)), 3),
        "within_2sigma_formal": round(float(np.mean(z * res.sigma_factor < 2)), 3),
    }


def shift_case(pts, seed, cell):
    """Uniform shift of one random half of the cloud against the other: every cell is rigid, so
    the errors show the noise of ICP on this surface and test the sigmas."""
    rng = np.random.default_rng(seed)
    half = rng.random(len(pts)) < 0.5
    shift = np.array([0.2, -0.4, 0.05])
    res = windowed_icp(pts[half], pts[~half] + shift, cell_m=cell)
    m = res.n >= 500
    e = np.column_stack([res.dx, res.dy, res.dz])[m] - shift
    h = np.linalg.norm(e, axis=1)
    return {
        "case": "shift",
        "seed": seed,
        "cell_m": cell,
        "cells": int(m.sum()),
        "rmse_3d_m": round(_rms(h), 4),
        "median_3d_m": round(float(np.median(h)), 4),
        "over_10cm": int(np.count_nonzero(h > 0.1)),
        "converged": round(float(np.mean(res.converged)), 3),
        "sigma_factor": round(res.sigma_factor, 2),
        **_coverage(res, e, m),
    }


def dem_case(pair, cell):
    res = dem_difference(pair.before, pair.after, cell_m=cell)
    g = res.grid
    xs, ys = g.centres()
    xx, yy = np.meshgrid(xs, ys)
    xy = np.column_stack([xx.ravel(), yy.ravel()])
    tz = pair.field(xy)[:, 2]
    dz = res.dz.ravel()
    m = pair.field.interior_mask(xy, fraction=0.5) & np.isfinite(dz)
    stable = (tz == 0) & np.isfinite(dz)
    return {
        "grid_m": cell,
        "interior_rmse_dz_vs_true_vertical_m": round(_rms(dz[m] - tz[m]), 4),
        "interior_median_abs_m": round(float(np.median(np.abs(dz[m] - tz[m]))), 4),
        "stable_rmse_dz_m": round(_rms(dz[stable]), 4),
        "stable_median_abs_m": round(float(np.median(np.abs(dz[stable]))), 4),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1)
    ap.add_argument(
        "--radius",
        type=float,
        nargs="+",
        default=None,
        help="lobe radius (m) or RX RY; default a third of the cloud's smaller side (10.8 m)",
    )
    args = ap.parse_args(argv)
    pts = read_las(DATA).xyz
    results = {"piv": [], "icp": [], "dem": []}
    radius = (
        None
        if not args.radius
        else (args.radius[0] if len(args.radius) == 1 else tuple(args.radius[:2]))
    )
    for seed in range(args.seeds):
        pair = make_lobe_pair(pts, seed=seed, radius_m=radius)
        for cell, win in PIV_CASES:
            r = piv_case(pair, cell, win)
            r["seed"] = seed
            results["piv"].append(r)
            print(json.dumps(r))
        for cell, levels in ICP_CASES:
            r = icp_case(pair, cell, levels)
            r["seed"] = seed
            results["icp"].append(r)
            print(json.dumps(r))
        for cell in (0.1, 0.25):
            r = dem_case(pair, cell)
            r["seed"] = seed
            results["dem"].append(r)
            print(json.dumps(r))
        for cell in (2.0, 5.0):
            r = shift_case(pts, seed, cell)
            results.setdefault("shift", []).append(r)
            print(json.dumps(r))
    print()
    print(
        "| PIV grid | windows (px) | interior RMSE (m) | (cells) | median, p95 (cells) | "
        "bias dx, dy (m) | valid | whole-lobe RMSE (m) | dz RMSE (m) | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results["piv"]:
        i, lobe = r["interior"], r["lobe"]
        print(
            f"| {r['grid_m']} | {r['windows_px']} | {i['rmse_h_m']} | {i['rmse_h_cells']} | "
            f"{i['median_h_cells']}, {i['p95_h_cells']} | {i['bias_dx_m']}, {i['bias_dy_m']} | "
            f"{i['valid_fraction']} | {lobe['rmse_h_m']} | {i['rmse_dz_m']} | {r['seconds']} |"
        )
    print()
    print(
        "| ICP cell (m) | coarse-to-fine | lobe cells | 3-D RMSE (m) | median (m) | "
        "dx, dy, dz RMSE (m) | RMSE vs cell-mean motion (m) | median σ (m) | within ±2σ | "
        "stable cells | 3-D RMSE (m) | median (m) | within ±2σ (formal) | sigma factor | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results["icp"]:
        lo, st = r["lobe"], r["stable"]
        print(
            f"| {r['cell_m']} | {r['coarse_to_fine']} | {lo['cells']} | {lo['rmse_3d_m']} | "
            f"{lo['median_3d_m']} | {lo['rmse_dx_dy_dz_m']} | {lo['rmse_3d_vs_cell_mean_m']} | "
            f"{lo['median_sigma_3d_m']} | {lo['within_2sigma']} | {st['cells']} | "
            f"{st['rmse_3d_m']} | {st['median_3d_m']} | {st['within_2sigma']} "
            f"({st['within_2sigma_formal']}) | {r['sigma_factor']} | {r['seconds']} |"
        )
    print()
    print(
        "| uniform shift: cell (m) | seed | cells | 3-D RMSE (m) | median (m) | cells > 10 cm | "
        "converged | sigma factor | within ±2σ | within ±2 formal σ |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results.get("shift", []):
        print(
            f"| {r['cell_m']} | {r['seed']} | {r['cells']} | {r['rmse_3d_m']} | "
            f"{r['median_3d_m']} | {r['over_10cm']} | {r['converged']} | {r['sigma_factor']} | "
            f"{r['within_2sigma']} | {r['within_2sigma_formal']} |"
        )
    print()
    for r in results["dem"]:
        print(
            f"DEM difference {r['grid_m']} m: interior RMSE of dz against the true vertical "
            f"motion {r['interior_rmse_dz_vs_true_vertical_m']} m (median |error| "
            f"{r['interior_median_abs_m']} m); stable-area RMSE {r['stable_rmse_dz_m']} m "
            f"(median |dz| {r['stable_median_abs_m']} m)"
        )
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
