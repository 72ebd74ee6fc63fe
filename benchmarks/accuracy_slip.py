"""Honest uncertainty of the slip: error / sigma over many seeds, and the variance factor.

Usage: ``python benchmarks/accuracy_slip.py --seeds 50 [--profile mls] [--noise 0.02]``

Each seed draws a new synthetic fault pair (independent samplings of both epochs, Gaussian
noise of ``--noise`` m, 18.1 mm of dextral slip) and runs the joint slip workflow with
``sigma`` equal to the true noise. Prints, per seed, the error of the fault-parallel, fault-normal
and vertical components against their 1σ, then the summary: std of error/σ (ideal 1; target
[0.8, 1.25]) and the mean a-posteriori variance factor σ0² (ideal 1; target 1 ± 0.1). The last
line is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from slipmap.core.displacement import estimate_slip
from slipmap.core.fault import fault_trace
from slipmap.core.synthetic import make_fault_pair

NLOD = 0.0181


def one_seed(seed: int, profile: str, noise: float, sigma: float, **scene):
    fp = make_fault_pair(
        profile,
        seed=seed,
        origin=(500000.0, 4200000.0, 10.0),
        right_offset_m=(0.0, -NLOD, 0.0),
        noise_m=noise,
        vegetation=False,
        **scene,
    )
    res = estimate_slip(
        fp.before.points,
        fp.after.points,
        fault_trace([fp.trace_xy]),
        sigma_before=sigma,
        sigma_after=sigma,
    )
    c = res.components()
    z = np.array(
        [
            (c["right_lateral_slip"] - NLOD) / c["sigma_fault_parallel"],
            c["fault_normal"] / c["sigma_fault_normal"],
            c["dz"] / c["sigma_dz"],
        ]
    )
    err = np.array([c["right_lateral_slip"] - NLOD, c["fault_normal"], c["dz"]])
    vf = [res.left.rigid.variance_factor, res.right.rigid.variance_factor]
    return z, err, vf, c["sigma_fault_parallel"]


def run(
    seeds: int,
    profile: str = "mls",
    noise: float = 0.02,
    sigma: float | None = None,
    first_seed: int = 1000,
    **scene,
):
    sigma = noise if sigma is None else sigma
    zs, errs, vfs, sig = [], [], [], []
    for s in range(first_seed, first_seed + seeds):
        try:
            z, e, vf, sp = one_seed(s, profile, noise, sigma, **scene)
        except Exception as exc:  # noqa: BLE001 - a failed layout is skipped, and counted
            print(f"seed {s}: skipped ({type(exc).__name__}: {exc})")
            continue
        zs.append(z), errs.append(e), vfs.extend(vf), sig.append(sp)
        print(
            f"seed {s}: error (mm) par {1000 * e[0]:+.3f} nor {1000 * e[1]:+.3f} "
            f"z {1000 * e[2]:+.3f}; error/sigma {z.round(2).tolist()}; s0^2 {np.round(vf, 3)}"
        )
    zs, errs = np.array(zs), np.array(errs)
    return {
        "profile": profile,
        "noise_m": noise,
        "sigma_m": sigma,
        "seeds": int(len(zs)),
        "std_error_over_sigma": [round(float(v), 3) for v in zs.std(axis=0, ddof=1)],
        "std_error_over_sigma_all": round(float(zs.std(ddof=1)), 3),
        "mean_variance_factor": round(float(np.mean(vfs)), 4),
        "rms_error_mm": [round(float(v), 4) for v in 1000 * np.sqrt((errs**2).mean(axis=0))],
        "max_abs_error_parallel_mm": round(float(1000 * np.abs(errs[:, 0]).max()), 4),
        "mean_sigma_parallel_mm": round(float(1000 * np.mean(sig)), 4),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--profile", default="mls")
    ap.add_argument("--noise", type=float, default=0.02)
    ap.add_argument("--sigma", type=float, default=None, help="assumed sigma (default: --noise)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = run(args.seeds, args.profile, args.noise, args.sigma)
    out["seconds"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
