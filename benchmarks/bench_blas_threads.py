"""The default windowed ICP with BLAS held to one thread, against BLAS's own thread count
(core/threads.py, issue #29 item 5).

On the lone-star lobe of docs/fields.md (``make_lobe_pair``, one pair per ``--seeds``), the
default of ``slipmap icp`` runs alternately with :func:`slipmap.core.threads.single_blas_thread`
in force (``one``) and made a no-op (``all``: BLAS's own threads, the code before stop 55),
``--repeat`` times each after one warm-up run, in one process, on the same points. Wall time,
CPU seconds of the process (all threads) and the largest difference between the two
results' displacements and σ (the same fit: only the time may differ).

Usage::

    python benchmarks/bench_blas_threads.py [--seeds 0 1] [--repeat 3] [--backend numba]

The last line is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from slipmap.core import threads
from slipmap.core.icp import windowed_icp
from slipmap.core.io.las import read_las
from slipmap.core.synthetic import make_lobe_pair

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fields import LONE_STAR, default_icp_kwargs  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--backend", default=None, help="default: the job's (auto)")
    ap.add_argument("--cell", type=float, default=5.0)
    args = ap.parse_args(argv)
    pts = read_las(str(LONE_STAR)).xyz
    limit = threads._limit
    modes = {"one": limit, "all": lambda: None}
    out = {"cell_m": args.cell, "runs": {m: [] for m in modes}, "max_diff_m": {}}
    kw = default_icp_kwargs()
    if args.backend:
        kw["backend"] = args.backend
    out["backend"] = kw["backend"]
    try:
        for seed in args.seeds:
            pair = make_lobe_pair(pts, seed=seed)
            windowed_icp(pair.before, pair.after, cell_m=args.cell, **kw)  # compile, caches
            res = {}
            for _ in range(args.repeat):
                for mode, fn in modes.items():
                    threads._limit = fn
                    t0, c0 = time.perf_counter(), time.process_time()
                    r = windowed_icp(pair.before, pair.after, cell_m=args.cell, **kw)
                    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                    out["runs"][mode].append([seed, round(wall, 3), round(cpu, 3)])
                    res[mode] = np.column_stack(
                        [r.dx, r.dy, r.dz, r.sigma_dx, r.sigma_dy, r.sigma_dz]
                    )
                    print(f"seed {seed} BLAS threads {mode}: {wall:.2f} s wall, {cpu:.2f} s CPU")
            diff = float(np.nanmax(np.abs(res["one"] - res["all"])))
            out["max_diff_m"][str(seed)] = diff
            print(f"seed {seed}: largest difference of the results {diff:.1e} m")
    finally:
        threads._limit = limit
    for mode, runs in out["runs"].items():
        walls, cpus = [r[1] for r in runs], [r[2] for r in runs]
        wall = f"{min(walls):.2f}-{max(walls):.2f} s"
        print(f"{mode}: wall {wall}, CPU {min(cpus):.2f}-{max(cpus):.2f} s")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
