"""Cost of tying the acquisition units on the planes they share (issue #30,
``core.unit_contrasts``) in a slip run.

For one pair of each of five survey kinds of ``accuracy_slip.py`` (MLS drift with renovated
buildings, MLS lever arm on crossing streets, TLS setups, ALS strips with a boresight roll,
MLS before and ALS after), times :func:`slipmap.core.displacement.estimate_slip` with the
job's defaults (units and their GpsTime given), with and without the within-epoch unit
contrasts, alternated, ``--repeat`` times each; CPU seconds of the process (run with
``OMP_NUM_THREADS=1`` for one core), the fastest of the repeats, and the contrast rows each
side used (before / after).

Usage::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_unit_contrasts.py [--repeat 3]

The last line is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_slip as A  # noqa: E402

from slipmap.core.displacement import estimate_slip  # noqa: E402
from slipmap.core.fault import fault_trace  # noqa: E402

PAIRS = (
    ("mls-3mm-renovated", 2004),
    ("mls-3mm-lever-crossing", 2001),
    ("tls-6-setups", 2002),
    ("als-1cm-roll", 2003),
    ("mls-als", 2001),
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    rows = []
    for case, seed in PAIRS:
        fp = A.draw_pair(case, seed)
        trace = fault_trace([fp.trace_xy])
        base = dict(
            sigma_before=fp.before.noise_m, sigma_after=fp.after.noise_m,
            unit_before=fp.source_before.astype(np.int64),
            unit_after=fp.source_after.astype(np.int64),
            unit_time_before=fp.gps_time_before, unit_time_after=fp.gps_time_after,
        )  # fmt: skip
        cpu = {False: [], True: []}
        used = None
        for _ in range(args.repeat):
            for tied in (False, True):
                t0 = time.process_time()
                res = estimate_slip(
                    fp.before.points, fp.after.points, trace, unit_contrasts=tied, **base
                )
                cpu[tied].append(time.process_time() - t0)
                if tied:
                    used = [
                        list(getattr(res, s).rigid.variance_components.n_contrasts)
                        for s in ("left", "right")
                    ]
        row = {
            "case": case,
            "seed": seed,
            "points": [int(fp.before.n_points), int(fp.after.n_points)],
            "cpu_s_untied": round(min(cpu[False]), 2),
            "cpu_s_tied": round(min(cpu[True]), 2),
            "ratio": round(min(cpu[True]) / min(cpu[False]), 2),
            "contrasts_left_right": used,
        }
        rows.append(row)
        print(
            f"{case} seed {seed}: {row['cpu_s_untied']} s untied, {row['cpu_s_tied']} s tied "
            f"({row['ratio']}x); contrast rows (before, after) left / right {used}",
            flush=True,
        )
    print(json.dumps({"rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
