"""Benchmark: tiled inputs in process and on a Dask LocalCluster (issue #17).

Usage::

    python benchmarks/bench_scale.py make --copies 18 --out /tmp/slipmap-scale
    python benchmarks/bench_scale.py run --data /tmp/slipmap-scale --copies 8 --job slip \\
        --workers 2
    python benchmarks/bench_scale.py all --data /tmp/slipmap-scale --copies 2 8 18 \\
        --workers 0 1 2 --json benchmarks/results/scale.json

``make`` writes synthetic epochs to disk as LAZ tiles: ``copies`` independent 100 m x 100 m
fault-pair scenes (mobile LiDAR, 2 cm noise, trees, 18.1 mm of dextral slip on a
north-striking fault), placed one after the other along the fault's strike, one LAZ tile per
scene and epoch (~0.59 M points each), plus the fault trace. ``run`` measures one job on the
first ``copies`` tiles in a fresh process: wall time of the job (the cluster's start-up
apart), peak RSS of the driver and of each worker (``ru_maxrss``), the per-tile cost (time,
points and the bytes of the result that travel to the driver, measured in process) and
prints one JSON line. ``all`` runs ``run`` for every size, job and worker count (0 = in
process) in subprocesses and prints the table of docs/benchmarks.md, with the projection to
a larger survey from the measured per-tile costs.

Jobs: ``slip`` (50 m tiles: the study's tiles, planes per tile; joint adjustment from the
per-plane moments, full stochastic model), ``roughness`` (0.5 m cells, 100 m tiles, exact) and
``planes`` (100 m tiles with a halo, parameters from a pilot tile, planes merged across
borders).
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

X0, Y0, Z0 = 500000.0, 4200000.0, 10.0
EXTENT = 100.0
TILES = {
    "slip": 50.0,
    "roughness": 100.0,
    "planes": 100.0,
    "dem": 100.0,
    "piv": 200.0,
    "icp": 100.0,
}
#: the field jobs' settings (DEM cells and PIV windows of the study's scale, 5 m ICP cells)
FIELDS = {"grid_m": 0.5, "windows_px": (32, 16, 16), "cell_m": 5.0}


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------- data


def make(out: Path, copies: int) -> None:
    import pyproj

    from slipmap.core.errors import InvalidParameterError
    from slipmap.core.io.las import PointCloud, write_las
    from slipmap.core.synthetic import make_fault_pair

    crs = pyproj.CRS.from_epsg(32611)
    for epoch in ("before", "after"):
        (out / epoch).mkdir(parents=True, exist_ok=True)
    n = {"before": 0, "after": 0}
    for j in range(copies):
        paths = [out / e / f"tile_{j:03d}.laz" for e in ("before", "after")]
        if all(p.exists() for p in paths):
            continue
        pair = None
        for k in range(10):  # a seed whose random buildings do not fit is skipped
            try:
                seed = 100 + j + 1000 * k
                pair = make_fault_pair("mls", seed=seed, origin=(X0, Y0 + j * EXTENT, Z0))
                break
            except InvalidParameterError:
                continue
        if pair is None:
            raise SystemExit(f"copy {j}: no seed gave a scene")
        for p, scene, e in zip(paths, (pair.before, pair.after), ("before", "after")):
            write_las(p, PointCloud(scene.points, {}, crs))
            n[e] += len(scene.points)
        print(f"copy {j + 1}/{copies}: {len(pair.before.points)} + {len(pair.after.points)} points")
    (out / "trace.json").write_text(json.dumps({"x": X0 + 0.5 * EXTENT}))


def _inputs(data: Path, copies: int):
    from slipmap.core.fault import fault_trace
    from slipmap.core.io.tiles import open_collection

    files = {e: sorted((data / e).glob("tile_*.laz"))[:copies] for e in ("before", "after")}
    if len(files["before"]) < copies:
        raise SystemExit(f"{data} has fewer than {copies} tiles: run 'make' first")
    before = open_collection(files["before"], label="before")
    after = open_collection(files["after"], label="after")
    x = json.loads((data / "trace.json").read_text())["x"]
    trace = fault_trace([np.array([[x, Y0 - 20.0], [x, Y0 + copies * EXTENT + 20.0]])])
    return before, after, trace


# --------------------------------------------------------------------------- one run


def _timed_engine():
    """An in-process engine that records every task's time and result size."""
    from slipmap.app.engine import InProcess

    class Timed(InProcess):
        def __init__(self):
            self.records = []

        def map(self, fn, items, **kw):
            def timed(item):
                t0, c0 = time.perf_counter(), time.process_time()
                out = fn(item)
                dt, dc = time.perf_counter() - t0, time.process_time() - c0
                self.records.append((fn.__name__, dt, len(pickle.dumps(out)), dc))
                return out

            return super().map(timed, items, **kw)

    return Timed()


def _run_job(job, before, after, trace, engine):
    from slipmap.app.tiled import planes_tiled, roughness_tiled, slip_tiled

    t = TILES[job]
    if job == "slip":
        res = slip_tiled(before, after, trace, tile_size_m=t, sigma_before=0.02,
                         sigma_after=0.02, stochastic_model="full", units="none",
                         engine=engine)  # fmt: skip
        return {"slip_mm": [round(1000 * v, 4) for v in res.relative]}
    if job == "roughness":
        g = roughness_tiled(before, cell_sizes_m=(0.5,), tile_size_m=t, engine=engine)[0]
        return {
            "cells": len(g),
            "median_theta_mm": round(1000 * float(np.nanmedian(g.theta_odr)), 4),
        }
    if job in ("dem", "piv", "icp"):
        return _run_field(job, before, after, t, engine)
    p = planes_tiled(before, tile_size_m=t, engine=engine)
    return {"planes": len(p), "tile_planes": p.n_tile_planes}


def _run_field(job, before, after, t, engine):
    """The field jobs on tiles: the DEM difference streamed into a COG (a temporary file),
    PIV and windowed ICP per block with their halos."""
    import tempfile

    from slipmap.app import tiled_fields as tf
    from slipmap.core.io.raster import RasterBlockWriter

    if job == "dem":
        with tempfile.TemporaryDirectory() as tmp:

            def writer(g):
                path = Path(tmp) / "dem.tif"
                return RasterBlockWriter(path, (3, *g.shape), origin_xy=g.origin_xy,
                                         pixel_size_m=g.cell_m)  # fmt: skip

            res = tf.dem_difference_tiled(before, after, cell_m=FIELDS["grid_m"],
                                          writer_factory=writer, tile_size_m=t,
                                          engine=engine)  # fmt: skip
            return {"cells": res.n_valid, "mean_dz_mm": round(1000 * res.mean_m, 4)}
    if job == "piv":
        res, _ = tf.piv_tiled(before, after, grid_m=FIELDS["grid_m"],
                              windows_px=FIELDS["windows_px"], expected_max_displacement_m=0.1,
                              tile_size_m=t, engine=engine)  # fmt: skip
        return {"vectors": int(np.isfinite(res.dx).sum()),
                "median_dy_mm": round(1000 * float(np.nanmedian(res.dy)), 3)}  # fmt: skip
    res = tf.icp_tiled(before, after, cell_m=FIELDS["cell_m"], tile_size_m=t, engine=engine)
    return {"cells": len(res.x), "median_dy_mm": round(1000 * float(np.median(res.dy)), 3)}


def _worker_peak_mb():
    import resource as r

    return r.getrusage(r.RUSAGE_SELF).ru_maxrss / 1024.0


def run(data: Path, copies: int, job: str, workers: int) -> dict:
    from slipmap.app.engine import make_engine

    before, after, trace = _inputs(data, copies)
    two = job in ("slip", "dem", "piv", "icp")  # jobs that read both epochs
    n_points = before.n_points + (after.n_points if two else 0)
    out = {"job": job, "copies": copies, "n_points": n_points, "workers": workers}
    if workers == 0:
        eng = _timed_engine()
        t0 = time.perf_counter()
        out["result"] = _run_job(job, before, after, trace, eng)
        out["seconds"] = time.perf_counter() - t0
        main = [r for r in eng.records if not r[0].startswith("_pilot")]
        out["tiles"] = len([r for r in main if r[0] in ("_slip_tile", "_roughness_tile",
                            "_planes_tile", "_dem_block", "_piv_block", "_icp_block")])  # fmt: skip
        out["task_seconds"] = sum(r[1] for r in main)
        out["task_cpu_seconds"] = sum(r[3] for r in main)
        out["result_bytes"] = sum(r[2] for r in main)
        out["driver_peak_mb"] = _rss_mb()
        out["worker_peak_mb"] = []
        return out
    from distributed import get_task_stream

    t0 = time.perf_counter()
    eng = make_engine(workers=workers)
    out["startup_seconds"] = time.perf_counter() - t0
    try:
        with get_task_stream(eng.client) as ts:
            t0 = time.perf_counter()
            out["result"] = _run_job(job, before, after, trace, eng)
            out["seconds"] = time.perf_counter() - t0
        busy = 0.0
        for rec in ts.data:
            for ss in rec.get("startstops", ()):
                if ss.get("action") == "compute":
                    busy += ss["stop"] - ss["start"]
        out["task_seconds"] = busy
        out["worker_peak_mb"] = sorted(eng.client.run(_worker_peak_mb).values())
    finally:
        eng.close()
    out["driver_peak_mb"] = _rss_mb()
    return out


# --------------------------------------------------------------------------- all


def _sub(data, copies, job, workers) -> dict:
    cmd = [sys.executable, __file__, "run", "--data", str(data), "--copies", str(copies),
           "--job", job, "--workers", str(workers)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    lines = [x for x in proc.stdout.splitlines() if x.startswith("{")]
    if proc.returncode != 0 or not lines:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return json.loads(lines[-1])


def _table(rows) -> str:
    out = [
        "| job | points | workers | time (s) | points/s | driver peak RSS (MB) | "
        "worker peak RSS (MB) | speed-up vs 1 worker |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    one = {(r["job"], r["copies"]): r["seconds"] for r in rows if r["workers"] == 1}
    for r in rows:
        w = "in process" if r["workers"] == 0 else str(r["workers"])
        wk = ", ".join(f"{v:.0f}" for v in r["worker_peak_mb"]) or "-"
        sp = one.get((r["job"], r["copies"]))
        spd = f"{sp / r['seconds']:.2f}" if sp and r["workers"] > 0 else "-"
        out.append(
            f"| {r['job']} | {r['n_points'] / 1e6:.1f} M | {w} | {r['seconds']:.1f} | "
            f"{r['n_points'] / r['seconds'] / 1e3:.0f} k | {r['driver_peak_mb']:.0f} | {wk} | "
            f"{spd} |"
        )
    return "\n".join(out)


def _projection(rows, total_points=4e9, workers=32) -> str:
    """Time and driver memory for 2 x 2 billion points on 32 workers, from per-tile costs."""
    out = [
        f"| job | measured s per M points (one core) | tiles for {total_points / 1e9:.0f} G "
        f"points | projected time on {workers} workers | driver memory for the results |",
        "|---|---:|---:|---:|---:|",
    ]
    rows_out = []
    for job in TILES:
        rs = [r for r in rows if r["job"] == job and r["workers"] == 0]
        if not rs:
            continue
        r = max(rs, key=lambda x: x["n_points"])
        s_per_m = r["task_cpu_seconds"] / (r["n_points"] / 1e6)  # CPU: the machine is shared
        pts_per_tile = r["n_points"] / r["tiles"]
        tiles = total_points / pts_per_tile
        # the in-process run's driver part (reduce, adjustment) grows with the tiles' results
        driver_s = max(0.0, r["seconds"] - r["task_seconds"]) * total_points / r["n_points"]
        rows_out.append((job, s_per_m, tiles, driver_s))
        t = total_points / 1e6 * s_per_m / workers + driver_s
        mem = r["result_bytes"] / r["tiles"] * tiles / 1e9
        out.append(f"| {job} | {s_per_m:.2f} | {tiles:,.0f} | {t / 3600:.1f} h | {mem:.1f} GB |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make")
    m.add_argument("--copies", type=int, default=18)
    m.add_argument("--out", type=Path, required=True)
    r = sub.add_parser("run")
    r.add_argument("--data", type=Path, required=True)
    r.add_argument("--copies", type=int, required=True)
    r.add_argument("--job", choices=sorted(TILES), required=True)
    r.add_argument("--workers", type=int, default=0)
    a = sub.add_parser("all")
    a.add_argument("--data", type=Path, required=True)
    a.add_argument("--copies", type=int, nargs="+", default=[2, 8, 18])
    a.add_argument("--workers", type=int, nargs="+", default=[0, 1, 2])
    a.add_argument("--jobs", nargs="+", default=list(TILES))
    a.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "make":
        make(args.out, args.copies)
        return 0
    if args.cmd == "run":
        print(json.dumps(run(args.data, args.copies, args.job, args.workers)))
        return 0
    make(args.data, max(args.copies))
    rows = []
    for job in args.jobs:
        for c in args.copies:
            for w in args.workers:
                row = _sub(args.data, c, job, w)
                print(json.dumps(row), flush=True)
                rows.append(row)
    meta = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "python": platform.python_version(),
    }
    meta["load_average"] = os.getloadavg()
    print(_table(rows))
    print()
    print(_projection(rows))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
