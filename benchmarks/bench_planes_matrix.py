"""Benchmark: known-answer matrix of the automatic plane segmentation.

Usage::

    python benchmarks/bench_planes_matrix.py [--quick] [--seeds 0,1] [--only density=4,50]
        [--only size=10] [--max-points 4000000] [--out benchmarks/results/planes_matrix.json]

Crosses density {1, 4, 10, 50, 300, 3000} pts/m2, noise {0.002, 0.01, 0.05} m, scene size
{10, 100, 1000} m and clutter {0, 0.3, 0.6} (162 cases per seed; ``--quick``: sizes 10 and
100 only). Each case is :func:`slipmap.core.planetruth.make_plane_case` (at most
``--max-points`` points: larger cases are a window of the scene at the same density), segmented
by :func:`slipmap.core.planes.segment_planes` with automatic parameters (timed alone) and
scored by :func:`slipmap.core.planetruth.score_case`. Prints a Markdown table, a summary per
density x noise, and writes every row as JSON to ``--out``.
"""

from __future__ import annotations

import argparse
import gc
import hashlib
import itertools
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from slipmap.core import planes
from slipmap.core.planes import segment_planes
from slipmap.core.planetruth import make_plane_case, score_case

DENSITIES = (1.0, 4.0, 10.0, 50.0, 300.0, 3000.0)
NOISES = (0.002, 0.01, 0.05)
SIZES = (10.0, 100.0, 1000.0)
CLUTTERS = (0.0, 0.3, 0.6)
AXES = {"density": DENSITIES, "noise": NOISES, "size": SIZES, "clutter": CLUTTERS}
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "planes_matrix.json"


def parse_only(items):
    """``["density=4,50", "size=10"]`` -> ``{"density": {4.0, 50.0}, "size": {10.0}}``."""
    out = {}
    for item in items or ():
        key, _, values = item.partition("=")
        key = key.strip()
        if key not in AXES or not values:
            raise SystemExit(f"--only expects one of {sorted(AXES)}=v1,v2,..., got {item!r}")
        out.setdefault(key, set()).update(float(v) for v in values.split(","))
    return out


def cases(quick, only, seeds):
    sizes = tuple(s for s in SIZES if s <= 100.0) if quick else SIZES
    axes = dict(AXES, size=sizes)
    for seed, d, n, s, c in itertools.product(
        seeds, axes["density"], axes["noise"], axes["size"], axes["clutter"]
    ):
        point = {"density": d, "noise": n, "size": s, "clutter": c}
        if all(point[k] in v for k, v in only.items()):
            yield seed, d, n, s, c


def run_case(seed, density, noise, size, clutter, max_points):
    t0 = time.perf_counter()
    case = make_plane_case(
        density_pts_m2=density,
        noise_m=noise,
        size_m=size,
        clutter_fraction=clutter,
        seed=seed,
        max_points=max_points,
    )
    t_gen = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = segment_planes(case.points)
    seconds = time.perf_counter() - t0
    score = score_case(case, res.labels)
    p = res.parameters
    row = {
        "density": density,
        "noise": noise,
        "size": size,
        "clutter": clutter,
        "seed": seed,
        "n_points": int(case.points.shape[0]),
        "seconds": round(seconds, 3),
        "generate_seconds": round(t_gen, 3),
        **score,
        "spacing_true_m": round(case.point_spacing_m, 5),
        "spacing_est_m": float(f"{p.point_spacing_m:.4g}"),
        "noise_est_m": float(f"{p.noise_m:.4g}"),
        "parameters": p.to_dict(),
        "subsampled_area": case.subsampled_area,
        "footprint_m": [round(float(v), 2) for v in case.footprint_m],
        "notes": case.notes,
        "missed_kinds": [case.kinds[i] for i in score["missed"]],
    }
    return row


def markdown(rows):
    head = (
        "| density | noise | size | clutter | seed | N | s | recall | precision | merged | "
        "planes | resolvable | spacing est (true) | noise est (true) | sub |"
    )
    lines = [head, "|" + "---|" * 15]
    for r in rows:
        lines.append(
            f"| {r['density']:g} | {r['noise']:g} | {r['size']:g} | {r['clutter']:g} | "
            f"{r['seed']} | {r['n_points']} | {r['seconds']:.2f} | {r['recall']:.3f} | "
            f"{r['precision']:.3f} | {r['n_merged']} | {r['n_planes']} | {r['n_resolvable']} | "
            f"{r['spacing_est_m']:.3g} ({r['spacing_true_m']:.3g}) | "
            f"{r['noise_est_m']:.3g} ({r['noise']:g}) | {'yes' if r['subsampled_area'] else ''} |"
        )
    return "\n".join(lines)


def summary(rows):
    groups = {}
    for r in rows:
        groups.setdefault((r["density"], r["noise"]), []).append(r)
    lines = [
        "| density | noise | cases | min recall | min precision | total merged | "
        "max noise est / true |",
        "|" + "---|" * 7,
    ]
    out = []
    for (d, n), rs in sorted(groups.items()):
        item = {
            "density": d,
            "noise": n,
            "cases": len(rs),
            "min_recall": min(r["recall"] for r in rs),
            "min_precision": min(r["precision"] for r in rs),
            "total_merged": sum(r["n_merged"] for r in rs),
            "max_noise_ratio": round(max(r["noise_est_m"] / n for r in rs), 3),
        }
        out.append(item)
        lines.append(
            f"| {d:g} | {n:g} | {item['cases']} | {item['min_recall']:.3f} | "
            f"{item['min_precision']:.3f} | {item['total_merged']} | "
            f"{item['max_noise_ratio']:.2f} |"
        )
    return "\n".join(lines), out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="sizes 10 and 100 m only")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds (default 0)")
    ap.add_argument(
        "--only",
        action="append",
        metavar="AXIS=V1,V2",
        help="keep only these values of density, noise, size or clutter (repeatable)",
    )
    ap.add_argument("--max-points", type=int, default=4_000_000, help="most points per case")
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="JSON file of all rows")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    only = parse_only(args.only)
    todo = list(cases(args.quick, only, seeds))
    print(f"{len(todo)} cases", file=sys.stderr)
    rows = []
    t_all = time.perf_counter()
    for k, (seed, d, n, s, c) in enumerate(todo):
        row = run_case(seed, d, n, s, c, args.max_points)
        rows.append(row)
        print(
            f"[{k + 1}/{len(todo)}] density={d:g} noise={n:g} size={s:g} clutter={c:g} "
            f"seed={seed}: N={row['n_points']} {row['seconds']:.2f}s recall={row['recall']:.3f} "
            f"precision={row['precision']:.3f} merged={row['n_merged']}",
            file=sys.stderr,
        )
        gc.collect()
    table = markdown(rows)
    summ_text, summ = summary(rows)
    print(table)
    print()
    print(summ_text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {
        "machine": {"python": platform.python_version(), "numpy": np.__version__},
        # the segmentation is under active change: record which planes.py was measured
        "planes_py_sha1": hashlib.sha1(Path(planes.__file__).read_bytes()).hexdigest(),
        "args": {"quick": args.quick, "seeds": seeds, "only": args.only or []},
        "total_seconds": round(time.perf_counter() - t_all, 1),
        "rows": rows,
        "summary": summ,
    }
    out.write_text(json.dumps(doc, indent=1))
    print(f"\nwrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
