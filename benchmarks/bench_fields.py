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

``--case lobe`` (issue #18): the lone-star lobe of docs/fields.md (tests/data/lone-star.laz
split into two disjoint random halves, the second moved by the default lobe, one pair per
``--seeds``), with the peers run on the same data in the same run:

3. PIV: SlipMap's :func:`~slipmap.core.piv.piv` against OpenPIV's ``windef`` (multi-pass
   window deformation, ``benchmarks/peers/openpiv_windef.py``) on the same two DEMs
   (GR 0.1 m with the default windows 64 32 16 16 px, and GR 0.25 m with 32 16 16 px, or
   ``--grid`` m and ``--windows`` px; 50 % overlap: the vectors sit at the same places).
   Horizontal error against the true motion at the vector positions, on the vectors both mark
   valid, over the lobe (``r < 1``) and its interior (``r <= 0.5``).
4. Windowed ICP: SlipMap's :func:`~slipmap.core.icp.windowed_icp` (rigid cells; with one
   coarser pass; with two deformation passes; the default of ``slipmap icp``: the spline
   field, breaklines found from the data, at most 2000 after-points per cell) against
   Open3D's point-to-plane ICP per cell
   (``benchmarks/peers/open3d_cells.py``) on the same cells (``--lobe-cell`` m; cells with
   >= 500 correspondences). 3-D error against the true motion at the cell centres, in the
   lobe and on stable ground; for SlipMap also on the lobe cells whose reported σ are all
   ≤ 1 cm (where the data constrain the motion to a centimetre). When an OpenCL device
   starts, the rigid run again with the pairs found there (``backend="opencl"``).

The peers run in the throw-away venv of ``benchmarks/peers/setup_peer_venv.sh`` (never a
SlipMap dependency), through a subprocess; a peer whose venv or module is missing is skipped
with a one-line reason. Times: SlipMap's call, the peer's own timer (its passes / normals and
ICP of every cell, not the file hand-over).

Usage::

    python benchmarks/bench_fields.py [--dem 2500] [--n 5000000] [--cell 5] [--seed 0]
    python benchmarks/bench_fields.py --case lobe [--seeds 0 1 2] [--grid 0.1]
        [--windows 64 32 16 16] [--lobe-cell 5] [--icp-points-per-cell N] [--no-piv]
        [--repeat N] [--icp-timing-only] [--backends numpy numba opencl auto]

The last line is JSON.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np
from scipy import ndimage

from slipmap.core.dem import Grid, common_grid, grid_elevation
from slipmap.core.icp import windowed_icp
from slipmap.core.piv import piv

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peers.peer import peer_missing, run_script  # noqa: E402

ORIGIN = (512_000.0, 4_780_000.0)
LONE_STAR = Path(__file__).resolve().parents[1] / "tests" / "data" / "lone-star.laz"


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


def _rms(a) -> float:
    a = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


def _stats(err: np.ndarray) -> dict:
    """RMSE and median of error vectors' lengths (m), and their count."""
    h = np.linalg.norm(err, axis=1) if err.ndim == 2 else np.abs(err)
    return {
        "n": int(h.size),
        "rmse_m": round(_rms(h), 4),
        "median_m": round(float(np.median(h)), 4) if h.size else None,
    }


def lobe_piv(pair, grid_m: float, windows, overlap: float = 0.5) -> dict:
    """SlipMap PIV and OpenPIV windef on the same two DEMs of a lobe pair (see the docstring)."""
    grid = common_grid(pair.before, pair.after, cell_m=grid_m)
    zb = grid_elevation(pair.before, grid=grid)
    za = grid_elevation(pair.after, grid=grid)
    d_max = float(np.max(np.abs(pair.field.max_d_m[:2])))
    t0 = time.perf_counter()
    res = piv(
        zb, za, grid=grid, windows_px=windows, overlap=overlap,
        expected_max_displacement_m=1.2 * d_max,
    )  # fmt: skip
    sec = time.perf_counter() - t0
    xy = np.column_stack([res.x.ravel(), res.y.ravel()])
    truth = pair.field(xy)[:, :2]
    est = np.column_stack([res.dx.ravel(), res.dy.ravel()])
    valid = res.valid.ravel() & np.all(np.isfinite(est), axis=1)
    regions = {
        "lobe": pair.field.interior_mask(xy, fraction=0.999),
        "interior": pair.field.interior_mask(xy, fraction=0.5),
    }
    out = {"grid_m": grid_m, "windows_px": list(windows), "vectors": int(valid.size)}
    out["slipmap"] = {"seconds": round(sec, 2), "valid": int(valid.sum())}
    why = peer_missing("openpiv")
    if why is not None:
        out["openpiv"] = {"skipped": why}
        for name, m in regions.items():
            out["slipmap"][name] = _stats(est[m & valid] - truth[m & valid])
        return out
    # SlipMap centres its windows in the DEM, OpenPIV starts them at pixel 0: crop OpenPIV's
    # images so that the final windows of both sit at the same places
    w, step = windows[-1], max(1, int(round(windows[-1] * (1.0 - overlap))))
    r0, c0 = (((n - w) - ((n - w) // step) * step) // 2 for n in zb.shape)
    o = run_script(
        "openpiv_windef.py",
        {
            "z_before": zb[r0:, c0:],
            "z_after": za[r0:, c0:],
            "windows_px": np.asarray(windows, dtype=np.int64),
            "overlap": np.float64(overlap),
            "max_displacement_px": np.float64(1.2 * d_max / grid_m + 2),
        },
    )
    # OpenPIV's centres are pixel-edge coordinates (column, row from the upper-left corner);
    # its v is positive southward
    ox = grid.x_min + (c0 + np.asarray(o["x"]).ravel()) * grid_m
    oy = grid.y_max - (r0 + np.asarray(o["y"]).ravel()) * grid_m
    od = np.column_stack([np.asarray(o["u"]).ravel(), -np.asarray(o["v"]).ravel()]) * grid_m
    ovalid = np.asarray(o["valid"]).ravel()
    # the same vector places: match by position (1 mm)
    key = {(round(a, 3), round(b, 3)): i for i, (a, b) in enumerate(zip(ox, oy))}
    j = np.array([key.get((round(a, 3), round(b, 3)), -1) for a, b in xy[:, :2]])
    same = j >= 0
    both = valid & same & ovalid[np.maximum(j, 0)]
    od_at = np.where(same[:, None], od[np.maximum(j, 0)], np.nan)
    out["openpiv"] = {
        "seconds": round(float(o["seconds"]), 2),
        "valid": int(ovalid.sum()),
        "version": o["openpiv_version"],
        "settings": o["settings"],
    }
    out["matched_vectors"] = int(same.sum())
    if not same.any():
        raise RuntimeError("no OpenPIV vector at a SlipMap vector's place: check the layouts")
    for name, m in regions.items():
        mb = m & both
        out["slipmap"][name] = _stats(est[mb] - truth[mb])
        out["openpiv"][name] = _stats(od_at[mb] - truth[mb])
        out["slipmap"][name + "_own_valid"] = _stats(est[m & valid] - truth[m & valid])
        ov = np.isfinite(od[:, 0]) & ovalid
        oxy = np.column_stack([ox, oy])
        mo = pair.field.interior_mask(oxy, fraction=0.999 if name == "lobe" else 0.5) & ov
        out["openpiv"][name + "_own_valid"] = _stats(od[mo] - pair.field(oxy[mo])[:, :2])
    return out


def _icp_truth(field, c_xy, iterations=20):
    """Motion of the material now at ``c_xy`` (after frame): ``field(p0)``, ``p0 + field(p0) = c``
    (fixed point, as benchmarks/validate_fields.py)."""
    p0 = c_xy.copy()
    for _ in range(iterations):
        p0 = c_xy - field(p0)[:, :2]
    return field(p0)


def default_icp_kwargs() -> dict:
    """The keywords ``slipmap icp`` gives :func:`~slipmap.core.icp.windowed_icp` with every
    option at its default (the job's ``SPEC`` parsed as the CLI parses it, less the cell)."""
    from slipmap.app.icp import SPEC, core_kwargs

    opts = SPEC.parse({"before": "before.laz", "after": "after.laz", "out": "out"},
                      run_check=False)  # fmt: skip
    kw = core_kwargs(opts)
    kw.pop("cell_m", None)
    return kw


#: the default run of ``slipmap icp`` (the spline field, its breaklines found from the data,
#: at most DEFAULT_MAX_POINTS_PER_CELL after-points per cell), timed beside the rigid cells
DEFAULT_RUN = "slipmap icp defaults"

ICP_RUNS = (
    ("slipmap rigid", {"coarse_to_fine": 0}),
    ("slipmap rigid, coarse-to-fine 1", {"coarse_to_fine": 1}),
    ("slipmap rigid, coarse-to-fine 1, 2 deformation passes",
     {"coarse_to_fine": 1, "deform_passes": 2}),
    ("slipmap rigid, coarse-to-fine 1, spline field",
     {"coarse_to_fine": 1, "field_model": "spline"}),
    (DEFAULT_RUN, default_icp_kwargs()),
)  # fmt: skip


def opencl_runs() -> tuple:
    """The rigid run with the pairs on an OpenCL device, when one starts (else none)."""
    from slipmap.core.opencl.backend import probe_runtime

    if probe_runtime() is not None:
        return ()
    return (("slipmap rigid, OpenCL pairs", {"coarse_to_fine": 0, "backend": "opencl"}),)


def backend_runs(backends) -> tuple:
    """The rigid run once per named backend (``--backends``); None: the OpenCL run when a
    device starts (:func:`opencl_runs`)."""
    if backends is None:
        return opencl_runs()
    return tuple(
        (f"slipmap rigid, backend {b}", {"coarse_to_fine": 0, "backend": b}) for b in backends
    )


def cap_per_cell(points: np.ndarray, cell: float, cap: int) -> np.ndarray:
    """At most ``cap`` points per ``cell``-metre square (on multiples of ``cell``, the
    windowed ICP's lattice): the sample ``max_points_per_cell`` draws
    (:func:`slipmap.core.icp.sample_priority`, seed 0), so both estimators get the same
    points."""
    from slipmap.core.icp import sample_priority

    key = np.floor(points[:, :2] / cell).astype(np.int64)
    _, cid = np.unique(key, axis=0, return_inverse=True)
    cid = cid.reshape(-1)
    pri = sample_priority(points)
    order = np.lexsort((pri, cid))
    rank = np.empty(len(points), dtype=np.int64)
    first = np.searchsorted(cid[order], cid[order])
    rank[order] = np.arange(len(points)) - first
    return points[rank < cap]


def lobe_icp(
    pair,
    cell: float,
    cap: Optional[int] = None,
    repeat: int = 1,
    timing_only: bool = False,
    backends=None,
) -> dict:
    """SlipMap windowed ICP variants and Open3D's per-cell ICP on the same cells (with
    ``cap``: both on the same sample of at most ``cap`` after-points per cell). With
    ``repeat`` > 1 SlipMap's rigid run and Open3D's run ``repeat`` times more, alternately,
    and each reports every time (``runs_s``) and the fastest (``min_s``): on a shared VM the
    spread between runs of the same work is larger than the difference asked about.
    ``timing_only``: the rigid runs (the default backend and ``backends``) and the default
    of ``slipmap icp`` alone; ``repeat`` times these."""
    if cap is not None:
        pair = replace(pair, after=cap_per_cell(pair.after, cell, cap))
    runs = {}
    timed_runs = (ICP_RUNS[0], ICP_RUNS[-1])  # the rigid cells and the default
    todo = (timed_runs if timing_only else ICP_RUNS) + backend_runs(backends)
    for name, kw in todo:
        t0 = time.perf_counter()
        runs[name] = (windowed_icp(pair.before, pair.after, cell_m=cell, **kw), t0)
        runs[name] = (runs[name][0], time.perf_counter() - t0)
    ref = runs[ICP_RUNS[0][0]][0]
    centres = np.column_stack([ref.x, ref.y, ref.z])
    truth = _icp_truth(pair.field, centres[:, :2])
    dense = ref.n >= 500
    masks = {"lobe": dense & (np.linalg.norm(truth, axis=1) > 0)}
    masks["stable"] = dense & ~masks["lobe"]
    out = {"cell_m": cell, "cells": len(ref), "points_per_cell_cap": cap, "methods": {}}
    for name, (r, sec) in runs.items():
        if not (np.array_equal(r.row, ref.row) and np.array_equal(r.col, ref.col)):
            raise RuntimeError(f"{name}: other cells than the first run")
        d = np.column_stack([r.dx, r.dy, r.dz])
        sig = np.column_stack([r.sigma_dx, r.sigma_dy, r.sigma_dz])
        out["methods"][name] = {"seconds": round(sec, 2)}
        for k, m in masks.items():
            out["methods"][name][k] = _stats(d[m] - truth[m])
            # share of the components within 2 reported sigma (calibration of the sigmas)
            inside = np.abs(d[m] - truth[m]) <= 2.0 * sig[m]
            out["methods"][name][k]["within_2sigma"] = round(float(inside.mean()), 3)
        # the lobe cells whose reported sigma are all <= 1 cm (the data constrain them)
        well = masks["lobe"] & np.all(sig <= 0.01, axis=1)
        out["methods"][name]["lobe_sigma_le_1cm"] = _stats(d[well] - truth[well])
    why = peer_missing("open3d")
    if why is not None:
        out["methods"]["open3d"] = {"skipped": why}
        return out
    # the same cells: after-points by cell, before-points in the cell grown by the buffer
    x0, y0 = ref.origin_xy
    col = np.floor((pair.after[:, 0] - x0) / cell).astype(np.int64)
    row = np.floor((y0 - pair.after[:, 1]) / cell).astype(np.int64)
    key = {int(k): i for i, k in enumerate(ref.row * ref.n_cols + ref.col)}
    inside = (row >= 0) & (row < ref.n_rows) & (col >= 0) & (col < ref.n_cols)
    flat = np.where(inside, row * ref.n_cols + col, -1)
    cid = np.array([key.get(int(k), -1) for k in flat], dtype=np.int64)
    buf = 0.5 * cell
    boxes = np.column_stack(
        [x0 + ref.col * cell - buf, x0 + (ref.col + 1) * cell + buf,
         y0 - (ref.row + 1) * cell - buf, y0 - ref.row * cell + buf]
    )  # fmt: skip
    peer_in = {
        "before": pair.before,
        "after": pair.after,
        "cell": cid,
        "centres": centres,
        "boxes": boxes,
        "max_corr_m": np.float64(buf),
        "normal_radius_m": np.float64(1.0),
    }
    o = run_script("open3d_cells.py", peer_in)
    d = np.asarray(o["d"], dtype=np.float64)
    name = f"open3d {o['open3d_version']} per cell"
    out["methods"][name] = {"seconds": round(float(o["seconds"]), 2)}
    for k, m in masks.items():
        ok = m & np.all(np.isfinite(d), axis=1)
        out["methods"][name][k] = _stats(d[ok] - truth[ok])
    if repeat > 1:
        timed = timed_runs + backend_runs(backends)
        times = {n: [runs[n][1]] for n, _ in timed}
        cpus = {n: [] for n, _ in timed}
        times[name] = [float(o["seconds"])]
        cpus[name] = [float(o["cpu_seconds"])] if "cpu_seconds" in o else []
        for _ in range(repeat - 1):
            for rigid_name, rigid_kw in timed:
                t0, c0 = time.perf_counter(), time.process_time()
                windowed_icp(pair.before, pair.after, cell_m=cell, **rigid_kw)
                times[rigid_name].append(time.perf_counter() - t0)
                cpus[rigid_name].append(time.process_time() - c0)  # all threads
            o = run_script("open3d_cells.py", peer_in)
            times[name].append(float(o["seconds"]))
            if "cpu_seconds" in o:
                cpus[name].append(float(o["cpu_seconds"]))
        for n, ts in times.items():
            out["methods"][n]["runs_s"] = [round(t, 2) for t in ts]
            out["methods"][n]["min_s"] = round(min(ts), 2)
            if cpus[n]:  # CPU seconds of the repeats (a loaded machine stretches wall time)
                out["methods"][n]["cpu_runs_s"] = [round(t, 2) for t in cpus[n]]
                out["methods"][n]["min_cpu_s"] = round(min(cpus[n]), 2)
    return out


def shift_icp(pts, seed: int, cell: float, cap: Optional[int] = None) -> dict:
    """The uniform shift of docs/fields.md (one random half of lone-star against the other
    moved by (0.2, -0.4, 0.05) m): rigid cells against the spline field, cells with >= 500
    correspondences."""
    rng = np.random.default_rng(seed)
    half = rng.random(len(pts)) < 0.5
    shift = np.array([0.2, -0.4, 0.05])
    before, after = pts[half], pts[~half] + shift
    if cap is not None:
        after = cap_per_cell(after, cell, cap)
    out = {}
    for name, kw in (("slipmap rigid", {}), ("slipmap spline field", {"field_model": "spline"})):
        t0 = time.perf_counter()
        r = windowed_icp(before, after, cell_m=cell, **kw)
        m = r.n >= 500
        e = np.column_stack([r.dx, r.dy, r.dz])[m] - shift
        sig = np.column_stack([r.sigma_dx, r.sigma_dy, r.sigma_dz])[m]
        out[name] = {"seconds": round(time.perf_counter() - t0, 2), **_stats(e)}
        out[name]["within_2sigma"] = round(float(np.mean(np.abs(e) <= 2.0 * sig)), 3)
    return out


def bench_lobe(
    seeds, piv_cases, cell, cap=None, repeat=1, timing_only=False, backends=None
) -> list:
    """The lone-star lobe cases, one per seed (PIV and ICP with their peers)."""
    from slipmap.core.io.las import read_las
    from slipmap.core.synthetic import make_lobe_pair

    pts = read_las(str(LONE_STAR)).xyz
    out = []
    for seed in seeds:
        pair = make_lobe_pair(pts, seed=seed)
        pivs = [lobe_piv(pair, g, w) for g, w in piv_cases]
        for p in pivs:
            sp, op = p["slipmap"], p["openpiv"]
            case = f"seed {seed} PIV GR {p['grid_m']} m, windows {p['windows_px']}"
            for name in ("lobe", "interior"):
                line = f"{case}, {name}: SlipMap {sp['seconds']} s {sp[name]}"
                if "skipped" in op:
                    line += f"; OpenPIV skipped: {op['skipped']}"
                else:
                    line += f"; OpenPIV windef {op['seconds']} s {op[name]}"
                print(line)
        i = lobe_icp(pair, cell, cap, repeat, timing_only, backends)
        for name, r in i["methods"].items():
            if "skipped" in r:
                print(f"seed {seed} ICP {name}: skipped: {r['skipped']}")
            else:
                lobe, stable = r["lobe"], r["stable"]
                line = f"seed {seed} ICP {name}: {r['seconds']} s lobe {lobe} stable {stable}"
                if "lobe_sigma_le_1cm" in r:
                    line += f" lobe cells with sigma <= 1 cm {r['lobe_sigma_le_1cm']}"
                if "min_s" in r:
                    line += f" runs {r['runs_s']} s, fastest {r['min_s']} s"
                if "min_cpu_s" in r:
                    line += f"; CPU {r['cpu_runs_s']} s, least {r['min_cpu_s']} s"
                print(line)
        sh = {} if timing_only else shift_icp(pts, seed, cell, cap)
        for name, r in sh.items():
            print(f"seed {seed} ICP uniform shift, {name}: {r}")
        out.append({"seed": seed, "piv": pivs, "icp": i, "shift": sh})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dem", type=int, default=2500)
    ap.add_argument("--n", type=int, default=5_000_000)
    ap.add_argument("--cell", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--case", choices=("synthetic", "lobe"), default="synthetic")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="lobe case seeds")
    ap.add_argument(
        "--grid", type=float, default=None,
        help="lobe case: one PIV grid (m) instead of 0.1 m (64 32 16 16) and 0.25 m (32 16 16)",
    )  # fmt: skip
    ap.add_argument("--windows", type=int, nargs="+", default=None, help="with --grid")
    ap.add_argument("--lobe-cell", type=float, default=5.0, help="lobe case ICP cell (m)")
    ap.add_argument(
        "--icp-points-per-cell", type=int, default=None,
        help="lobe case: both ICPs on the same sample of at most N after-points per cell",
    )  # fmt: skip
    ap.add_argument("--no-piv", action="store_true", help="lobe case: the ICP part only")
    ap.add_argument(
        "--repeat", type=int, default=1,
        help="lobe case: run SlipMap's rigid ICP, the default of `slipmap icp` and Open3D's "
        "N times, alternately (times)",
    )  # fmt: skip
    ap.add_argument(
        "--icp-timing-only", action="store_true",
        help="lobe case: SlipMap's rigid ICP (numpy and OpenCL pairs), the default of "
        "`slipmap icp` and Open3D's only",
    )  # fmt: skip
    ap.add_argument(
        "--backends", nargs="+", default=None, choices=("numpy", "numba", "opencl", "auto"),
        help="lobe case: the rigid run again with each of these backends, timed alternately "
        "with the default one and Open3D (default: OpenCL when a device starts)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    if args.case == "lobe":
        logging.basicConfig(level=logging.WARNING)
        cases = [(0.1, (64, 32, 16, 16)), (0.25, (32, 16, 16))]
        if args.grid is not None:
            cases = [(args.grid, tuple(args.windows or (64, 32, 16, 16)))]
        if args.no_piv:
            cases = []
        out = bench_lobe(
            args.seeds, cases, args.lobe_cell, args.icp_points_per_cell, args.repeat,
            args.icp_timing_only, args.backends,
        )  # fmt: skip
        print(json.dumps({"lobe": out}))
        return 0
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
