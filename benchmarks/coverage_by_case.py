"""2σ coverage of the default field per case and class of cell, from saved harness runs
(issue #29 item 3).

``validate_landslides.py`` pools its coverage over the cases; this takes the per-cell rows of
one or more of its JSON files (``cells``, ``cell_columns``) and gives, per case and class
(``near``: centre < 3 m from a discontinuity, ``far``: the others), the cells, the share of
error components within 2 reported σ, RMS(error/σ) per component, the RMS error and the
median σ (far cells also split into ``far moving`` and ``far still`` where the rows say how
far the ground moved); and per case the RMS over the scenes of each scene's mean error
beside the mean spread of the errors within a scene (a shared error of the scene against
one per cell).

Usage::

    python benchmarks/coverage_by_case.py FILE.json [FILE.json ...] [--method default]
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict

import numpy as np

NEAR_M = 3.0
#: a far cell whose true motion is at least this (metres) is ``far moving``, else ``far
#: still`` (the harness's rows since stop 56 carry the truth's size, ``moved``): in a scene
#: of survey extent (``--extent-tiles``) most cells are still ground
MOVING_M = 0.02


def rows(paths, method: str):
    for path in paths:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
        cols = doc["cell_columns"]
        for values in doc["cells"]:
            r = dict(zip(cols, values))
            if r["method"] == method:
                r["file"] = str(path)
                yield r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="+")
    ap.add_argument("--method", default="default")
    args = ap.parse_args(argv)
    groups = defaultdict(list)
    scenes = defaultdict(list)
    for r in rows(args.files, args.method):
        cls = "near" if r["dist"] < NEAR_M else "far"
        v = [r["ex"], r["ey"], r["ez"], r["sx"], r["sy"], r["sz"]]
        keys = [(r["density"], cls, r["case"]), (r["density"], cls, "all")]
        if cls == "far" and r.get("moved") is not None:  # runs since stop 56 record it
            sub = "far moving" if r["moved"] >= MOVING_M else "far still"
            keys += [(r["density"], sub, r["case"]), (r["density"], sub, "all")]
        for key in keys:
            groups[key].append(v)
        if r["case"] not in ("slump", "slump-draped"):
            groups[(r["density"], cls, "all but the slump")].append(v)
        if cls == "far":
            scenes[(r["density"], r["case"], r["file"], r["seed"])].append(v)
    print("density class case: cells, within 2σ (x / y / z), RMS(e/σ) x / y / z, "
          "RMS error cm x / y / z, median σ cm x / y / z")  # fmt: skip
    for key in sorted(groups):
        a = np.asarray(groups[key])
        e, s = a[:, :3], a[:, 3:]
        q = np.abs(e) / s
        print(
            f"{' '.join(key)}: {len(a)}, {100 * (q <= 2).mean():.1f} % "
            f"({' / '.join(f'{100 * x:.1f}' for x in (q <= 2).mean(axis=0))}), "
            f"{' / '.join(f'{x:.2f}' for x in np.sqrt((q**2).mean(axis=0)))}, "
            f"{' / '.join(f'{100 * x:.2f}' for x in np.sqrt((e**2).mean(axis=0)))}, "
            f"{' / '.join(f'{100 * x:.2f}' for x in np.median(s, axis=0))}"
        )
    per_case = defaultdict(list)
    for (dens, case, _, _), v in scenes.items():
        e = np.asarray(v)[:, :3]
        per_case[(dens, case)].append((e.mean(axis=0), e.std(axis=0)))
    print("far cells, per case: scenes, RMS of the scene-mean error cm x / y / z, "
          "mean spread within a scene cm x / y / z")  # fmt: skip
    for (dens, case), v in sorted(per_case.items()):
        m = np.array([x[0] for x in v])
        s = np.array([x[1] for x in v])
        print(
            f"{dens} {case}: {len(v)}, "
            f"{' / '.join(f'{100 * x:.2f}' for x in np.sqrt((m**2).mean(axis=0)))}, "
            f"{' / '.join(f'{100 * x:.2f}' for x in s.mean(axis=0))}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
