"""Cost of the units' drift along GpsTime (issue #30, ``core.unit_drift``) in a slip run.

For one pair of each of four survey kinds of ``accuracy_slip.py`` (MLS drift with renovated
buildings, MLS lever arm on crossing streets, TLS setups, ALS strips with a boresight roll),
times :func:`slipmap.core.displacement.estimate_slip` with the job's defaults and the pair's
acquisition units, with and without their GpsTime (the drift profiled by REML, or one rigid
error per unit), alternated, ``--repeat`` times each; CPU seconds of the process (run with
``OMP_NUM_THREADS=1`` for one core), the fastest of the repeats, and the knot spacing each
side and the joint estimate chose.

Usage::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_unit_drift.py [--repeat 3]

The last line is JSON.
"""

from __future__ import annotations

import argparse
import json
import math
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
)


def _spacing(v):
    return None if not math.isfinite(v) else float(v)


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
        )  # fmt: skip
        times = dict(unit_time_before=fp.gps_time_before, unit_time_after=fp.gps_time_after)
        cpu = {"rigid": [], "drift": []}
        chosen = None
        for _ in range(args.repeat):
            for name, kw in (("rigid", {}), ("drift", times)):
                t0 = time.process_time()
                res = estimate_slip(fp.before.points, fp.after.points, trace, **base, **kw)
                cpu[name].append(time.process_time() - t0)
                if name == "drift":
                    jc = res.joint_components
                    chosen = [
                        _spacing(getattr(res, s).rigid.variance_components.unit_interval_s)
                        for s in ("left", "right")
                    ] + [_spacing(jc.unit_interval_s) if jc is not None else None]
        row = {
            "case": case,
            "seed": seed,
            "points": [int(fp.before.n_points), int(fp.after.n_points)],
            "cpu_s_rigid": round(min(cpu["rigid"]), 2),
            "cpu_s_drift": round(min(cpu["drift"]), 2),
            "ratio": round(min(cpu["drift"]) / min(cpu["rigid"]), 2),
            "spacing_s_left_right_joint": chosen,
        }
        rows.append(row)
        print(
            f"{case} seed {seed}: {row['cpu_s_rigid']} s rigid units, {row['cpu_s_drift']} s "
            f"drifting ({row['ratio']}x); spacing left/right/joint {chosen}",
            flush=True,
        )
    print(json.dumps({"rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
