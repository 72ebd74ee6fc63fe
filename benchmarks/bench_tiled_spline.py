"""Time and memory of the spline field on tiles against the one-file run (issue #29, item 4).

The lone-star lobe of docs/fields.md (tests/data/lone-star.laz split into two disjoint random
halves, the second moved by the default lobe; ``--seed``) is written as one LAZ per epoch and
as 2 x 2 LAZ tiles per epoch (cut at the middle of the after epoch's extent). Then
``slipmap icp BEFORE AFTER --field-model spline`` runs in a fresh process on the one file,
on the tiles in process and on the tiles on a local Dask cluster of ``--workers`` workers
(blocks of ``--tile-size`` m), each timed (wall clock of the command) with its peak resident
memory (the largest of the process and its children: Dask's workers). Every column of the
tiled runs' icp.csv is compared with the one-file run's (largest absolute difference) and the
lobe's RMSE at the cells with >= 500 points is printed for each run.

``--case slab`` (or another case of benchmarks/validate_landslides.py: ``fault``, ``slump``,
...) moves the after epoch by that landslide field instead, so that the default's breaklines
are detected (on the tiles since stop 40); the record then gives the lines found, and the
RMSE is over the moving cells with >= 500 points.

Usage::

    python benchmarks/bench_tiled_spline.py [--seed 0] [--tile-size 20] [--workers 2]
        [--case lobe]

One JSON line per run; appended to benchmarks/results/tiled_spline.jsonl with ``--record``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
LONE_STAR = ROOT / "tests" / "data" / "lone-star.laz"
RESULTS = ROOT / "benchmarks" / "results" / "tiled_spline.jsonl"

_RUNNER = """
import resource, sys, time
from slipmap.cli import main
t = time.perf_counter()
try:
    rc = main(sys.argv[1:])
except SystemExit as e:
    rc = e.code
dt = time.perf_counter() - t
own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
print("BENCH", rc, dt, own, kids, file=sys.stderr)
"""


def _write(folder: Path, pair) -> None:
    from slipmap.core.io.las import PointCloud, write_las

    mid = 0.5 * (pair.after[:, :2].min(axis=0) + pair.after[:, :2].max(axis=0))
    for name, pts in (("before", pair.before), ("after", pair.after)):
        write_las(folder / f"{name}.laz", PointCloud(pts, {}, None))
        tiles = folder / f"{name}_tiles"
        tiles.mkdir()
        k = (pts[:, :2] >= mid).astype(int)
        for i in (0, 1):
            for j in (0, 1):
                m = (k[:, 0] == i) & (k[:, 1] == j)
                write_las(tiles / f"t_{i}_{j}.laz", PointCloud(pts[m], {}, None))


def _run(args, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT.parent))
    cmd = [sys.executable, "-c", _RUNNER, "-q", "icp", *args, "--out", str(out)]
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    line = [x for x in p.stderr.splitlines() if x.startswith("BENCH")]
    if p.returncode or not line:
        raise RuntimeError(p.stderr[-2000:])
    _, rc, dt, own, kids = line[-1].split()
    if int(rc):
        raise RuntimeError(p.stderr[-2000:])
    return {"seconds": round(float(dt), 1), "peak_rss_mb": round(max(int(own), int(kids)) / 1024)}


def _rows(path: Path) -> dict:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tile-size", type=float, default=20.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--record", action="store_true")
    ap.add_argument("--case", default="lobe", help="lobe, or a validate_landslides.py case")
    a = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT.parent))
    from bench_fields import _icp_truth

    from slipmap.core.io.las import read_las
    from slipmap.core.synthetic import make_lobe_pair

    pts = read_las(str(LONE_STAR)).xyz
    if a.case == "lobe":
        pair = make_lobe_pair(pts, seed=a.seed)
    else:
        from validate_landslides import fields

        from slipmap.core.synthetic import make_landslide_pair

        fld = fields(pts[:, :2].min(axis=0), pts[:, :2].max(axis=0))[a.case]
        pair = make_landslide_pair(pts, fld, seed=a.seed)
    base = {"date": time.strftime("%Y-%m-%d"), "case": a.case, "seed": a.seed,
            "points": len(pair.after), "tile_size_m": a.tile_size,
            "load": round(os.getloadavg()[0], 1)}  # fmt: skip
    lines = []
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        _write(d, pair)
        spline = ["--field-model", "spline"]
        runs = {
            "one file": [str(d / "before.laz"), str(d / "after.laz"), *spline],
            "tiles, in process": [str(d / "before_tiles"), str(d / "after_tiles"), *spline,
                                  "--tile-size", f"{a.tile_size:g}"],
            f"tiles, Dask {a.workers} workers": [
                str(d / "before_tiles"), str(d / "after_tiles"), *spline,
                "--tile-size", f"{a.tile_size:g}", "--workers", str(a.workers)],
        }  # fmt: skip
        ref = None
        for name, args in runs.items():
            out = d / name.replace(" ", "_").replace(",", "")
            rec = dict(base, run=name, **_run(args, out))
            rows = _rows(out / "icp.csv")
            truth = _icp_truth(pair.field, np.column_stack([rows["x"], rows["y"]]))
            err = np.column_stack([rows["dx"], rows["dy"], rows["dz"]]) - truth
            lobe = (rows["n"] >= 500) & (np.linalg.norm(truth, axis=1) > 0)
            rec["cells"] = len(rows["x"])
            rec["lobe_rmse_cm"] = round(100 * float(np.sqrt(np.mean(np.sum(err[lobe] ** 2, 1)))), 2)
            doc = json.loads((out / "icp.json").read_text())["breaklines"]
            rec["breaklines"] = {k: doc.get(k) for k in ("source", "count", "length_m")}
            if ref is None:
                ref = rows
            else:
                rec["max_abs_diff_vs_one_file"] = float(
                    max(np.max(np.abs(rows[k] - ref[k])) for k in ref)
                )
            print(json.dumps(rec), flush=True)
            lines.append(rec)
    if a.record:
        with open(RESULTS, "a", encoding="utf-8") as f:
            for rec in lines:
                f.write(json.dumps(rec) + "\n")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
