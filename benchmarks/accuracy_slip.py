"""Honest σ of the slip under correlated survey error: calibration against an ICP peer.

Usage::

    bash benchmarks/peers/setup_peer_venv.sh          # once: Open3D in a throw-away venv
    python benchmarks/accuracy_slip.py --seeds 25 --jobs 2 [--cases mls-3mm,als-1cm] \
        [--out results.jsonl] [--no-peer]

Each case draws ``--seeds`` synthetic fault pairs (18.1 mm of dextral slip, a town of 12
buildings on 150 m, independent samplings of both epochs) with a correlated survey error of
a kind and level (``core.synthetic.SurveyError``: MLS trajectory drift along the drive path,
ALS strip offsets with PointSourceId, MLS before and ALS after, gross building moves), and
runs on the same points:

* SlipMap with ``stochastic_model="white"`` (the study's model), ``"plane"`` and ``"full"``
  (units from the pair's PointSourceId); for ALS cases also ``"full"`` with the strip
  accuracy given as a fixed unit component (``full+prior``: what a user who knows the strip
  adjustment's accuracy enters with ``--fixed-component``);
* the peer: a per-side point-to-plane ICP of Open3D (``benchmarks/peers``), same side masks.

Per case and method it prints the RMS error of the fault-parallel slip, the mean σ, std of
error/σ (ideal 1; target [0.8, 1.25]) and the share of |error| ≤ 2.5 σ (target ≥ 98 %), and
the same pooled over the three components. Per-seed rows go to ``--out`` (JSON lines); the
last line printed is the summary as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from slipmap.core.displacement import estimate_slip
from slipmap.core.fault import fault_geometry, fault_trace, side_masks
from slipmap.core.synthetic import SurveyError, make_fault_pair

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peers.peer import icp_relative, peer_python  # noqa: E402

NLOD = 0.0181
ORIGIN = (500000.0, 4200000.0, 10.0)
SCENE = dict(n_buildings=12, extent_m=150.0, vegetation=False)


def _case(profile, before=None, after=None, after_profile=None, blunder=False, prior=None):
    # airborne scans see no facades: gable roofs of several azimuths carry the horizontal
    scene = {"roof_kinds": ("gable",)} if "als" in (profile, after_profile) else {}
    if profile == "als":
        scene["density_pts_m2"] = 20.0  # a dense ALS survey (Table X's ALS is ~ 10-20 pts/m²)
    return dict(profile=profile, before=before, after=after, after_profile=after_profile,
                blunder=blunder, prior=prior, scene=scene)  # fmt: skip


def _mls(level, **kw):
    return SurveyError(kind="mls", level_m=level, **kw)


def _als(level):
    return SurveyError(kind="als", level_m=level)


CASES = {
    "mls-white": _case("mls"),
    "mls-1mm": _case("mls", _mls(0.001), _mls(0.001)),
    "mls-3mm": _case("mls", _mls(0.003), _mls(0.003)),
    "mls-5mm": _case("mls", _mls(0.005), _mls(0.005)),
    "mls-3mm-nonflat": _case("mls", _mls(0.003, nonflat_m=0.002), _mls(0.003, nonflat_m=0.002)),
    "mls-3mm-renovated": _case("mls", _mls(0.003), _mls(0.003), blunder=True),
    "als-1cm": _case("als", _als(0.01), _als(0.01), prior=(0.01, 0.01)),
    "als-3cm": _case("als", _als(0.03), _als(0.03), prior=(0.03, 0.03)),
    "mls-als": _case("mls", _mls(0.003), _als(0.01), after_profile="als", prior=(None, 0.01)),
}


def one(case_name: str, seed: int, peer: bool) -> dict:
    """One pair of one case: errors of every method (metres) and their σ."""
    c = CASES[case_name]
    rng = np.random.default_rng(seed + 77)
    extra = {}
    if c["blunder"]:
        az = rng.uniform(0, 2 * math.pi)
        mag = rng.uniform(0.35, 0.5)
        extra = dict(blunder_fraction=0.1, blunder_offset_m=(mag * math.sin(az),
                     mag * math.cos(az), 0.0))  # fmt: skip
    t0 = time.perf_counter()
    fp = make_fault_pair(
        c["profile"], seed=seed, origin=ORIGIN, right_offset_m=(0.0, -NLOD, 0.0),
        error_before=c["before"], error_after=c["after"], after_profile=c["after_profile"],
        **SCENE, **c["scene"], **extra,
    )  # fmt: skip
    trace = fault_trace([fp.trace_xy])
    truth = fp.relative_offset_m
    row = {"case": case_name, "seed": seed, "n_before": int(fp.before.n_points),
           "n_after": int(fp.after.n_points),
           "pair_s": round(time.perf_counter() - t0, 2)}  # fmt: skip
    units = {}
    if fp.source_before is not None:
        units = dict(
            unit_before=fp.source_before.astype(np.int64),
            unit_after=fp.source_after.astype(np.int64),
        )
    models = [("white", "white", {}), ("plane", "plane", {}), ("full", "full", units)]
    if c["prior"] is not None:
        fixed = {k: v for k, v in zip(("unit_before", "unit_after"), c["prior"]) if v}
        models.append(("full+prior", "full", dict(units, components=fixed)))
    strike = None
    for label, model, kw in models:
        t0 = time.perf_counter()
        try:
            res = estimate_slip(
                fp.before.points, fp.after.points, trace, sigma_before=fp.before.noise_m,
                sigma_after=fp.after.noise_m, stochastic_model=model, **kw,
            )  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - a failed run is recorded and counted
            row[label] = {"failed": f"{type(exc).__name__}: {exc}"}
            continue
        comp = res.components()
        strike = res.strike_rad
        err = _errors(res.relative, truth, strike)
        sig = [comp["sigma_fault_parallel"], comp["sigma_fault_normal"], comp["sigma_dz"]]
        row[label] = {"err": err, "sigma": sig, "s": round(time.perf_counter() - t0, 2),
                      "planes": [res.left.rigid.n_planes, res.right.rigid.n_planes],
                      "rejected": [len(res.left.rigid.rejected_planes),
                                   len(res.right.rigid.rejected_planes)]}  # fmt: skip
        if model != "white":
            row[label]["components"] = {
                s: {k.name: k.sigma_m for k in getattr(res, s).rigid.variance_components.components}
                for s in ("left", "right")
            }
    if peer and strike is not None:
        gb = fault_geometry(fp.before.points[:, :2], trace)
        ga = fault_geometry(fp.after.points[:, :2], trace)
        sides = []
        for g in (gb, ga):
            lm, rm = side_masks(g, buffer_m=10.0)
            sides.append(np.where(lm, -1, np.where(rm, 1, 0)).astype(np.int8))
        pts = fp.before.points
        t0 = time.perf_counter()
        try:
            out = icp_relative(
                fp.before.points, fp.after.points, sides[0], sides[1],
                pts[sides[0] < 0].mean(axis=0), pts[sides[0] > 0].mean(axis=0), voxel_m=VOXEL_M,
            )  # fmt: skip
            row["icp"] = {"err": _errors(np.asarray(out["relative"]), truth, strike),
                          "s": round(time.perf_counter() - t0, 2)}  # fmt: skip
        except RuntimeError as exc:
            row["icp"] = {"failed": str(exc)[:300]}
    return row


def _errors(rel, truth, strike):
    """Errors of the fault-parallel, fault-normal and vertical relative motion (metres)."""
    d = np.asarray(rel) - np.asarray(truth)
    jp = np.array([math.sin(strike), math.cos(strike), 0.0])
    jn = np.array([math.cos(strike), -math.sin(strike), 0.0])
    return [float(jp @ d), float(jn @ d), float(d[2])]


#: the peer works on a 0.25 m voxel grid: 4-6x faster, and on these scenes as accurate (its
#: error is the survey error, not the point noise; checked on white-noise scenes: 0.1-0.8 mm)
VOXEL_M = 0.25
WEAK_SIGMA_M = 0.005  # pairs whose full-model σ∥ exceeds this: geometry too weak to compare


def summarise(rows):
    """Per case and method: n, RMS error (mm), median |error| (mm), RMS error over the pairs
    whose full-model σ∥ is below :data:`WEAK_SIGMA_M` (the same pairs for every method), mean σ
    (mm), RMS(error/σ), share within 2.5σ (fault-parallel, and pooled over the three
    components)."""
    out = {}
    for case in dict.fromkeys(r["case"] for r in rows):
        rs = [r for r in rows if r["case"] == case]
        strong = {
            r["seed"]
            for r in rs
            if "sigma" in r.get("full", {}) and r["full"]["sigma"][0] < WEAK_SIGMA_M
        }
        methods = [m for m in ("white", "plane", "full", "full+prior", "icp") if m in rs[0]]
        out[case] = {}
        for m in methods:
            ok = [r[m] for r in rs if m in r and "err" in r[m]]
            if not ok:
                out[case][m] = {"n": 0, "failed": len(rs)}
                continue
            e = np.array([o["err"] for o in ok])
            es = np.array([r[m]["err"][0] for r in rs
                           if r["seed"] in strong and "err" in r.get(m, {})])  # fmt: skip
            s = {"n": len(ok), "failed": len(rs) - len(ok),
                 "rms_mm": round(1000 * float(np.sqrt((e[:, 0] ** 2).mean())), 3),
                 "median_abs_mm": round(1000 * float(np.median(np.abs(e[:, 0]))), 3),
                 "n_strong": int(es.size),
                 "rms_strong_mm": round(1000 * float(np.sqrt((es**2).mean())), 3)
                 if es.size else None,
                 "rms3_mm": [round(1000 * float(v), 3)
                             for v in np.sqrt((e**2).mean(axis=0))]}  # fmt: skip
            if "sigma" in ok[0]:
                sg = np.array([o["sigma"] for o in ok])
                z = e / sg
                s.update(
                    mean_sigma_mm=round(1000 * float(sg[:, 0].mean()), 3),
                    std_z=round(float(np.sqrt((z[:, 0] ** 2).mean())), 3),
                    within_2_5=round(float((np.abs(z[:, 0]) <= 2.5).mean()), 3),
                    std_z_all=round(float(np.sqrt((z**2).mean())), 3),
                    within_2_5_all=round(float((np.abs(z) <= 2.5).mean()), 3),
                )
            out[case][m] = s
    return out


def table(summary) -> str:
    """Markdown table of :func:`summarise`."""
    lines = [
        "| case | method | n | RMS error ∥ (mm) | median abs. error ∥ (mm) | RMS error ∥, "
        "σ∥ < 5 mm (n) | mean σ ∥ (mm) | RMS(err/σ) ∥ | ≤2.5σ ∥ | RMS(err/σ) 3 comp. | "
        "≤2.5σ 3 comp. |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case, ms in summary.items():
        for m, s in ms.items():
            if not s.get("n"):
                lines.append(f"| {case} | {m} | 0 | failed {s.get('failed')} | | | | | | | |")
                continue
            lines.append(
                f"| {case} | {m} | {s['n']} | {s['rms_mm']:.2f} | {s['median_abs_mm']:.2f} | "
                f"{s['rms_strong_mm'] if s['rms_strong_mm'] is not None else ''} "
                f"({s['n_strong']}) | "
                f"{s.get('mean_sigma_mm', float('nan')):.2f} | {s.get('std_z', '')} | "
                f"{s.get('within_2_5', '')} | {s.get('std_z_all', '')} | "
                f"{s.get('within_2_5_all', '')} |"
            )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=25, help="pairs per case")
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="per-seed rows (JSON lines)")
    ap.add_argument("--no-peer", action="store_true", help="skip the Open3D ICP peer")
    args = ap.parse_args(argv)
    cases = [c for c in args.cases.split(",") if c]
    for c in cases:
        if c not in CASES:
            ap.error(f"--cases: unknown case {c!r}; known: {', '.join(CASES)}")
    peer = not args.no_peer
    if peer and peer_python() is None:
        ap.error("no peer venv: run bash benchmarks/peers/setup_peer_venv.sh, or --no-peer")
    jobs = [
        (c, s, peer) for c in cases for s in range(args.first_seed, args.first_seed + args.seeds)
    ]
    t0 = time.perf_counter()
    rows = []
    fh = args.out.open("w") if args.out else None
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as ex:
        for row in ex.map(one, *zip(*jobs)):
            rows.append(row)
            if fh:
                fh.write(json.dumps(row) + "\n")
                fh.flush()
            brief = {m: round(1000 * row[m]["err"][0], 2) for m in row
                     if isinstance(row[m], dict) and "err" in row[m]}  # fmt: skip
            print(
                f"{row['case']} seed {row['seed']}: fault-parallel error (mm) {brief}", flush=True
            )
    if fh:
        fh.close()
    summary = summarise(rows)
    print(table(summary))
    print(json.dumps({"seconds": round(time.perf_counter() - t0, 1), "summary": summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
