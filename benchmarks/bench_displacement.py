"""Benchmark: the end-to-end slip workflow for 2 x N points, against np.sort of N keys.

Usage: ``python benchmarks/bench_displacement.py --n 10000000``

Two synthetic MLS epochs of about N points each (independent samplings, 18.1 mm dextral slip
across a north-striking fault) through :func:`slipmap.core.displacement.estimate_slip`
(fault geometry, planes of both epochs on both sides, matching, two adjustments), no file I/O.
Target (issue #3): ratio to np.sort of N uint64 <= 25 at N = 10 M. Last line JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from slipmap.core.displacement import estimate_slip
from slipmap.core.fault import fault_trace
from slipmap.core.synthetic import make_fault_pair, make_scene_n_points


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2_000_000, help="points per epoch (about)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backend", default="numpy")
    args = ap.parse_args(argv)
    # scene size that gives about N points per epoch, with the buildings of make_scene_n_points
    probe = make_scene_n_points(args.n, "mls", seed=args.seed, vegetation=False)
    fp = make_fault_pair(
        "mls",
        seed=args.seed,
        n_buildings=len(probe.buildings),
        extent_m=probe.extent_m,
        origin=(500000.0, 4200000.0, 10.0),
        right_offset_m=(0.0, -0.0181, 0.0),
        vegetation=False,
    )
    del probe
    n = fp.before.points.shape[0]
    keys = np.random.default_rng(args.seed).integers(0, 2**63, n, dtype=np.uint64)
    t_sort = min(_time(lambda: np.sort(keys)) for _ in range(3))
    t0 = time.perf_counter()
    res = estimate_slip(
        fp.before.points,
        fp.after.points,
        fault_trace([fp.trace_xy]),
        sigma_before=0.02,
        sigma_after=0.02,
        plane_options={"backend": args.backend},
    )
    seconds = time.perf_counter() - t0
    c = res.components()
    print(f"epochs: {n} + {fp.after.points.shape[0]} points, numpy {np.__version__}")
    print(
        f"estimate_slip: {seconds:.2f} s; np.sort of {n} uint64: {t_sort:.3f} s; "
        f"ratio {seconds / t_sort:.2f}"
    )
    print(
        f"right-lateral slip {1000 * c['right_lateral_slip']:.3f} mm "
        f"± {1000 * c['sigma_fault_parallel']:.3f} (truth 18.100); planes left "
        f"{res.left.rigid.n_planes}, right {res.right.rigid.n_planes}"
    )
    print(
        json.dumps(
            {
                "n": n,
                "backend": args.backend,
                "seconds": round(seconds, 3),
                "sort_seconds": round(t_sort, 4),
                "ratio_to_sort": round(seconds / t_sort, 2),
                "error_mm": round(1000 * (c["right_lateral_slip"] - 0.0181), 4),
            }
        )
    )
    return 0


def _time(fn):
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


if __name__ == "__main__":
    sys.exit(main())
