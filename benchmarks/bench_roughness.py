"""Benchmark of the vectorised grid roughness (Pollyea & Fairley 2011) against np.sort.

Synthetic outcrop like the study's Box Canyon scan: a 90 m x 10 m face parallel to the xz
plane, undulating in y (metre-scale relief), with rough zones (fractures) in a smooth host, UTM
offsets, N points in random order (the worst case for the gathers). Times
:func:`slipmap.core.roughness.grid_roughness` at one cell size and ``np.sort`` of N random
uint64 in the same process (after the roughness call, so the process's maxrss delta
over the call is meaningful), and measures the peak memory of the roughness call.

Memory: ``tracemalloc`` traces numpy's data allocations (numpy reports them to tracemalloc);
``peak_rss_bytes`` is the traced peak of everything the call allocates *plus* the input xyz
array, so ``memory_ratio = (xyz_bytes + traced_peak) / xyz_bytes``. ``ru_maxrss`` of the process
is printed too, as a cross-check.

Usage::

    python benchmarks/bench_roughness.py --n 20000000 [--cell 0.125] [--seed 0]

Human-readable lines first; the last line is JSON with n, cell_m, seconds, sort_seconds,
ratio_to_sort, peak_rss_bytes, xyz_bytes, memory_ratio.
"""

from __future__ import annotations

import argparse
import gc
import json
import resource
import sys
import time
import tracemalloc

import numpy as np

from slipmap.core.roughness import grid_roughness, summarize_roughness

_CHUNK = 1 << 20


def synthetic_outcrop(n: int, *, seed: int = 0) -> np.ndarray:
    """(n, 3) float64 points of a rough vertical outcrop 90 m long (x) and 10 m high (z)."""
    rng = np.random.default_rng(seed)
    xyz = np.empty((n, 3), dtype=np.float64)
    for s in range(0, n, _CHUNK):
        e = min(n, s + _CHUNK)
        m = e - s
        x = rng.uniform(0.0, 90.0, m)
        z = rng.uniform(0.0, 10.0, m)
        relief = (
            0.8 * np.sin(2 * np.pi * x / 23.0)
            + 0.3 * np.sin(2 * np.pi * z / 7.0 + 0.5)
            + 0.1 * np.sin(2 * np.pi * (x + z) / 3.1)
        )
        # rough zones: column-bounding fractures every ~6 m and a rubbly band at mid height
        fracture = np.exp(-(((x % 6.0) - 3.0) ** 2) / 0.02)
        rubble = np.exp(-(((z - 5.0) / 0.6) ** 2))
        sigma = 0.003 + 0.02 * fracture + 0.03 * rubble
        y = relief + sigma * rng.standard_normal(m)
        xyz[s:e, 0] = 512_000.0 + x
        xyz[s:e, 1] = 4_780_000.0 + y
        xyz[s:e, 2] = 1_050.0 + z
    return xyz


def _maxrss_bytes() -> int:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(r) * (1 if sys.platform == "darwin" else 1024)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2_000_000, help="number of points")
    ap.add_argument("--cell", type=float, default=0.125, help="cell size, metres")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--min-points", type=int, default=10)
    ap.add_argument("--no-trace", action="store_true", help="time without tracemalloc")
    args = ap.parse_args(argv)

    n = args.n
    print(f"numpy {np.__version__}, N = {n:,}, cell = {args.cell} m")
    t0 = time.perf_counter()
    xyz = synthetic_outcrop(n, seed=args.seed)
    print(f"synthetic outcrop generated in {time.perf_counter() - t0:.2f} s")

    rss_before = _maxrss_bytes()
    if not args.no_trace:
        tracemalloc.start()
    t0 = time.perf_counter()
    grid = grid_roughness(xyz, cell_size_m=args.cell, min_points=args.min_points, ols_axis="y")
    seconds = time.perf_counter() - t0
    traced_peak = 0
    if not args.no_trace:
        _, traced_peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    rss_after = _maxrss_bytes()

    gc.collect()
    keys = np.random.default_rng(args.seed + 1).integers(0, 2**63, n, dtype=np.int64)
    keys = keys.view(np.uint64)
    gc.collect()
    t0 = time.perf_counter()
    sorted_keys = np.sort(keys)
    sort_s = time.perf_counter() - t0
    del sorted_keys, keys
    gc.collect()
    print(f"np.sort of {n:,} uint64: {sort_s:.3f} s")

    s = summarize_roughness(grid)
    print(
        f"grid_roughness: {seconds:.3f} s, {s.n_cells:,} cells, "
        f"{s.mean_points_per_cell:.0f} points/cell, {s.n_cells_skipped} cells skipped"
    )
    print(
        f"  theta_ODR mean {s.odr.mean:.4f} m (max {s.odr.maximum:.4f}); "
        f"theta_OLS mean {s.ols.mean:.4f} m (max {s.ols.maximum:.4f})"
    )
    xyz_bytes = int(xyz.nbytes)
    peak = xyz_bytes + int(traced_peak)
    print(f"ratio to np.sort: {seconds / sort_s:.2f}")
    if not args.no_trace:
        print(
            f"traced peak of the call: {traced_peak / 1e6:.1f} MB; with the input xyz "
            f"({xyz_bytes / 1e6:.1f} MB): {peak / xyz_bytes:.2f} x xyz"
        )
    print(
        f"process ru_maxrss: {rss_after / 1e6:.1f} MB after the call, {rss_before / 1e6:.1f} MB "
        f"before it (input generated): {(xyz_bytes + rss_after - rss_before) / xyz_bytes:.2f} x "
        "xyz by maxrss delta"
    )
    result = {
        "n": n,
        "cell_m": args.cell,
        "seconds": round(seconds, 4),
        "sort_seconds": round(sort_s, 4),
        "ratio_to_sort": round(seconds / sort_s, 3),
        "peak_rss_bytes": peak if not args.no_trace else None,
        "xyz_bytes": xyz_bytes,
        "memory_ratio": round(peak / xyz_bytes, 3) if not args.no_trace else None,
        "memory_method": "tracemalloc peak of the call + xyz bytes",
        "maxrss_bytes": rss_after,
        "numpy": np.__version__,
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
