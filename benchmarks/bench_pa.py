"""Point accuracy: its cost in the adjustment, and its effect on a heteroscedastic scene.

Usage: ``python benchmarks/bench_pa.py [--n 2000000] [--seeds 30]``

1. Cost: the slip workflow on an N-point-per-epoch MLS pair with a constant sigma, then with a
   per-point (N, 3, 3) covariance (same values): ratio of the run times (issue #4 target: <= 1.5).
   Each variant is timed ``--repeats`` times, interleaved; the ratios are of medians.
2. Effect: seeds of a fault pair whose after-epoch noise varies 5x across the scene (5 mm
   south, 25 mm north of the centre; before epoch 4 mm). Constant sigma (the RMS of the true
   noise) against the matching per-point model: RMS error, std(error/sigma) and sigma0^2.
The last line is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from slipmap.core.accuracy import columns_covariance
from slipmap.core.displacement import estimate_slip
from slipmap.core.fault import fault_trace
from slipmap.core.synthetic import make_fault_pair, make_scene_n_points

NLOD = 0.0181
ORIGIN = (500000.0, 4200000.0, 10.0)


def cost(n: int, repeats: int = 3) -> dict:
    """Median run times of the slip workflow, constant sigma against per-point inputs.

    Runs are interleaved (constant, matrices, packed, per-axis, constant, ...) so machine
    load affects all alike; ratios are of medians. "matrices" passes (N, 3, 3) covariance
    arrays (validated and packed inside), "packed" the (N, 6) form (``xx yy zz xy xz yz``,
    as ``slipmap accuracy --full-covariance`` writes), "per_axis" (N, 3) sigmas.
    """
    probe = make_scene_n_points(n, "mls", seed=0, vegetation=False)
    fp = make_fault_pair(
        "mls",
        seed=0,
        n_buildings=len(probe.buildings),
        extent_m=probe.extent_m,
        origin=ORIGIN,
        vegetation=False,
        right_offset_m=(0, -NLOD, 0),
    )
    tr = fault_trace([fp.trace_xy])
    nb, na = fp.before.points.shape[0], fp.after.points.shape[0]
    six = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]) * 0.02**2
    variants = {
        "constant": (0.02, 0.02),
        "matrices": (
            np.tile(np.eye(3) * 0.02**2, (nb, 1, 1)),
            np.tile(np.eye(3) * 0.02**2, (na, 1, 1)),
        ),
        "packed": (np.tile(six, (nb, 1)), np.tile(six, (na, 1))),
        "per_axis": (np.full((nb, 3), 0.02), np.full((na, 3), 0.02)),
    }
    times = {k: [] for k in variants}
    for _ in range(repeats):
        for name, (sb, sa) in variants.items():
            t0 = time.perf_counter()
            estimate_slip(fp.before.points, fp.after.points, tr, sigma_before=sb, sigma_after=sa)
            times[name].append(time.perf_counter() - t0)
    med = {k: float(np.median(v)) for k, v in times.items()}
    out = {"n": int(nb), "repeats": repeats, "constant_s": round(med["constant"], 3)}
    for name in ("matrices", "packed", "per_axis"):
        out[f"{name}_s"] = round(med[name], 3)
        out[f"{name}_ratio"] = round(med[name] / med["constant"], 3)
    out["pa_ratio"] = out["matrices_ratio"]
    return out


def effect(seeds: int) -> dict:
    out = {"constant": [], "pa": []}
    vf = {"constant": [], "pa": []}
    for seed in range(2000, 2000 + seeds):
        try:
            fp = make_fault_pair(
                "mls",
                seed=seed,
                origin=ORIGIN,
                vegetation=False,
                noise_m=0.004,
                right_offset_m=(0, -NLOD, 0),
            )
        except Exception:  # noqa: BLE001 - a layout that does not fit is skipped
            continue
        rng = np.random.default_rng(seed)
        after = fp.after.points.copy()
        north = after[:, 1] > ORIGIN[1] + 0.5 * fp.after.extent_m
        extra = np.where(north, 0.025, 0.005)
        after += rng.normal(size=after.shape) * extra[:, None] / np.sqrt(3)
        # the condition variance B C B^T is the variance along the normal: 4 mm (synthetic
        # noise along the normal) plus one axis-share of the isotropic extra noise
        true_sigma = np.sqrt(0.004**2 + extra**2 / 3)
        tr = fault_trace([fp.trace_xy])
        runs = {
            "constant": float(np.sqrt(np.mean(true_sigma**2))),
            "pa": columns_covariance(true_sigma, true_sigma, true_sigma),
        }
        for name, sig in runs.items():
            try:
                r = estimate_slip(
                    fp.before.points, after, tr, sigma_before=0.004 / np.sqrt(3), sigma_after=sig
                )
            except Exception as exc:  # noqa: BLE001
                print(f"seed {seed} {name}: skipped ({exc})")
                continue
            c = r.components()
            e = c["right_lateral_slip"] - NLOD
            out[name].append((e, c["sigma_fault_parallel"]))
            vf[name] += [r.left.rigid.variance_factor, r.right.rigid.variance_factor]
        print(
            f"seed {seed}: "
            + ", ".join(
                f"{k} err {1000 * v[-1][0]:+.3f} mm / sigma {1000 * v[-1][1]:.3f}"
                for k, v in out.items()
                if v
            )
        )
    res = {}
    for name, v in out.items():
        a = np.array(v)
        res[name] = {
            "seeds": len(a),
            "rms_error_mm": round(float(1000 * np.sqrt((a[:, 0] ** 2).mean())), 4),
            "std_error_over_sigma": round(float((a[:, 0] / a[:, 1]).std(ddof=1)), 3),
            "mean_sigma_mm": round(float(1000 * a[:, 1].mean()), 4),
            "mean_variance_factor": round(float(np.mean(vf[name])), 3),
        }
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2_000_000)
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    c = cost(args.n, args.repeats)
    print(
        f"cost (median of {c['repeats']}): constant {c['constant_s']} s; (N, 3, 3) "
        f"covariances {c['matrices_s']} s = {c['matrices_ratio']}x; (N, 6) packed "
        f"{c['packed_s']} s = {c['packed_ratio']}x; (N, 3) sigmas {c['per_axis_s']} s = "
        f"{c['per_axis_ratio']}x"
    )
    e = effect(args.seeds) if args.seeds > 0 else {}
    print(json.dumps({"cost": c, "effect": e}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
