"""Cost of the units' drift along GpsTime (``core.unit_drift``), of tying the units on the
planes they share (``core.unit_contrasts``), of letting them turn (``core.stochastic``
``UNIT_TURN``) or of offering REML the horizontal wave family (``DEFAULT_FAMILIES``) in a
slip run (issue #30).

For one pair of each of four survey kinds of ``accuracy_slip.py`` (MLS drift with renovated
buildings, MLS lever arm on crossing streets, TLS setups, ALS strips with a boresight roll;
with ``--compare contrasts`` also MLS before and ALS after), times
:func:`slipmap.core.displacement.estimate_slip` with the job's defaults and the pair's
acquisition units, alternated, ``--repeat`` times each:

- ``--compare drift`` (default): with and without the units' GpsTime (the drift profiled by
  REML, or one rigid error per unit), with the contrasts off as before stop 43; reports the
  knot spacing each side and the joint estimate chose;
- ``--compare contrasts``: with the GpsTime, with and without the within-epoch unit
  contrasts; reports the contrast rows each side used (before, after);
- ``--compare turn``: with the GpsTime and the contrasts (the job's defaults), with and
  without the units' turn (``UNIT_TURN``, the lever profiled by REML); reports the lever each
  side and the joint estimate chose;
- ``--compare families``: the job's defaults with the spatial families REML chooses from
  the spherical one alone (as before stop 45) or with the horizontal wave ("wave_h"); adds
  a pair of the short-wavelength field kind; reports the family each side and the joint
  estimate chose.

CPU seconds of the process (run with ``OMP_NUM_THREADS=1`` for one core), the fastest of the
repeats.

Usage::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/bench_unit_drift.py \\
        [--compare drift|contrasts|turn|families] [--repeat 3]

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

from slipmap.core import stochastic  # noqa: E402
from slipmap.core.displacement import estimate_slip  # noqa: E402
from slipmap.core.fault import fault_trace  # noqa: E402

PAIRS = (
    ("mls-3mm-renovated", 2004),
    ("mls-3mm-lever-crossing", 2001),
    ("tls-6-setups", 2002),
    ("als-1cm-roll", 2003),
)
#: ``--compare contrasts`` adds a mixed pair (an ALS epoch's strips tied to an MLS epoch's passes)
MIXED = (("mls-als", 2001),)
#: ``--compare families`` adds a pair of the short-wavelength field (a field of the map position)
FIELD = (("field-3mm-37-53m", 2002),)


#: per ``--compare``: the two runs' names, the JSON key and the console label of what the
#: second run chose, and the attribute of the side's and the joint components that holds it
#: (None: the contrast rows each side used)
COMPARE = {
    "drift": (("rigid", "drift"), "spacing_s_left_right_joint", "spacing left/right/joint",
              "unit_interval_s"),
    "contrasts": (("untied", "tied"), "contrasts_left_right",
                  "contrast rows (before, after) left / right", None),
    "turn": (("translating", "turning"), "lever_m_left_right_joint",
             "lever (m) left/right/joint", "unit_lever_m"),
    "families": (("spherical", "with_wave_h"), "family_left_right_joint",
                 "family left/right/joint", "family"),
}  # fmt: skip
#: the families REML chooses from in each run of ``--compare families`` (every other run:
#: the library's default)
FAMILIES = {"spherical": ("spherical",), "with_wave_h": ("spherical", "wave_h")}
LIBRARY_FAMILIES = stochastic.DEFAULT_FAMILIES


def _spacing(v):
    return None if not math.isfinite(v) else float(v)


def _what(res, attr):
    """What the run chose: the components' ``attr`` (a knot spacing or a lever) left, right
    and joint, or (``attr`` None) the contrast rows each side used."""
    vcs = [getattr(res, s).rigid.variance_components for s in ("left", "right")]
    if attr is None:
        return [list(vc.n_contrasts) for vc in vcs]
    jc = res.joint_components
    if attr == "family":
        return [vc.spatial_family for vc in vcs] + [jc.family if jc is not None else None]
    return [_spacing(getattr(vc, attr)) for vc in vcs] + [
        _spacing(getattr(jc, attr)) if jc is not None else None
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--compare", choices=tuple(COMPARE), default="drift")
    args = ap.parse_args(argv)
    names, key, what, attr = COMPARE[args.compare]
    rows = []
    extra = {"drift": (), "families": MIXED + FIELD}.get(args.compare, MIXED)
    for case, seed in PAIRS + extra:
        fp = A.draw_pair(case, seed)
        trace = fault_trace([fp.trace_xy])
        base = dict(
            sigma_before=fp.before.noise_m, sigma_after=fp.after.noise_m,
            unit_before=fp.source_before.astype(np.int64),
            unit_after=fp.source_after.astype(np.int64),
        )  # fmt: skip
        times = dict(unit_time_before=fp.gps_time_before, unit_time_after=fp.gps_time_after)
        if args.compare == "drift":
            runs = {"rigid": {"unit_contrasts": False},
                    "drift": dict(times, unit_contrasts=False)}  # fmt: skip
        elif args.compare == "contrasts":
            runs = {"untied": dict(times, unit_contrasts=False),
                    "tied": dict(times, unit_contrasts=True)}  # fmt: skip
        else:  # the turn and the families: the same options, a module switch between them
            runs = {n: dict(times) for n in names}
        cpu = {n: [] for n in names}
        chosen = None
        for _ in range(args.repeat):
            for name in names:
                stochastic.UNIT_TURN = name != "translating"  # benchmark devices
                stochastic.DEFAULT_FAMILIES = FAMILIES.get(name, LIBRARY_FAMILIES)
                t0 = time.process_time()
                res = estimate_slip(fp.before.points, fp.after.points, trace, **base, **runs[name])
                cpu[name].append(time.process_time() - t0)
                if name == names[1]:
                    chosen = _what(res, attr)
        stochastic.UNIT_TURN = True
        stochastic.DEFAULT_FAMILIES = LIBRARY_FAMILIES
        a, b = (min(cpu[n]) for n in names)
        row = {
            "case": case,
            "seed": seed,
            "points": [int(fp.before.n_points), int(fp.after.n_points)],
            f"cpu_s_{names[0]}": round(a, 2),
            f"cpu_s_{names[1]}": round(b, 2),
            "ratio": round(b / a, 2),
            key: chosen,
        }
        rows.append(row)
        print(
            f"{case} seed {seed}: {a:.2f} s {names[0]}, {b:.2f} s {names[1]} ({row['ratio']}x); "
            f"{what} {chosen}",
            flush=True,
        )
    print(json.dumps({"compare": args.compare, "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
