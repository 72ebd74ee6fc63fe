"""Benchmark: one Gauss-Helmert iteration of ``adjust_rigid`` against np.sort of N keys.

Usage: ``python benchmarks/bench_adjustment.py --n-points 10000000 --n-planes 10000``

Builds a synthetic two-epoch problem (``n_points`` in all, half per epoch, on ``n_planes``
random planar patches of several orientations at UTM-like coordinates, 2 cm noise, a known
motion), times ``adjust_rigid(..., max_iterations=1)`` (all of it: validation, centring,
moments, one iteration, outlier test, residuals) and, in the same run, ``np.sort`` of
``n_points`` random uint64 (best of ``--repeat`` each). Peak memory of the adjustment is
measured in a separate run under ``tracemalloc`` (numpy reports its buffers to it). Prints
human-readable lines, then, as the last line, JSON:
``{"n_points", "n_planes", "seconds", "sort_seconds", "ratio_to_sort", "peak_mb", ...}``.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import time
import tracemalloc

import numpy as np

from slipmap.core.adjustment import adjust_rigid


def make_problem(n_points, n_planes, sigma=0.02, seed=0):
    """Two epochs of points on ``n_planes`` patches; after = R before + t about the origin
    of the scene."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n_planes, 3))
    normals[0::3, :2] *= 0.2  # roofs / ground
    normals[1::3, 2] = 0.0  # walls
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    ref = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(normals, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normals, e1)
    origin = np.array([500000.0, 4200000.0, 100.0])
    centres = origin + rng.uniform(-1000, 1000, (n_planes, 3)) * [1, 1, 0.02]
    w = np.array([3e-5, -2e-5, 1e-4])
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    r = np.eye(3) + k + 0.5 * k @ k
    t = np.array([0.3, -0.2, 0.1])
    out = []
    half = n_points // 2
    for ep in range(2):
        lab = np.sort(rng.integers(0, n_planes, half))
        ab = rng.uniform(-5, 5, (half, 2))
        p = ab[:, :1] * e1[lab]
        p += ab[:, 1:] * e2[lab]
        p += centres[lab] - origin
        if ep == 1:
            p = p @ r.T + t
        p += origin
        p += rng.normal(0, sigma, p.shape)
        out += [p, lab]
    return out, (r, t, origin)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-points", type=int, default=1_000_000)
    ap.add_argument("--n-planes", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--no-memory", action="store_true", help="skip the tracemalloc run")
    ap.add_argument(
        "--stochastic",
        action="store_true",
        help="instead: converged adjustments with the white and the full stochastic model "
        "(components, spatial covariance, plane tests) on the same problem, and their ratio",
    )
    args = ap.parse_args(argv)
    if args.stochastic:
        return stochastic_cost(args)

    (before, bl, after, al), (r, t, origin) = make_problem(args.n_points, args.n_planes)
    best, res = float("inf"), None
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        res = adjust_rigid(before, bl, after, al, sigma_before=0.02, sigma_after=0.02,
                           max_iterations=1)  # fmt: skip
        best = min(best, time.perf_counter() - t0)
    keys = np.random.default_rng(1).integers(0, 2**63, args.n_points, dtype=np.uint64)
    sort_best = float("inf")
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        np.sort(keys)
        sort_best = min(sort_best, time.perf_counter() - t0)
    del keys
    peak_mb = None
    if not args.no_memory:
        tracemalloc.start()
        adjust_rigid(before, bl, after, al, sigma_before=0.02, sigma_after=0.02,
                     max_iterations=1)  # fmt: skip
        peak_mb = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    input_mb = sum(x.nbytes for x in (before, bl, after, al)) / 2**20
    maxrss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    c = res.centre
    err = res.displacement - ((c - origin) @ r.T + origin + t - c)  # truth at the centre
    print(f"adjust_rigid, 1 iteration: {best:.3f} s  ({args.n_points} points, "
          f"{args.n_planes} planes)")  # fmt: skip
    print(f"np.sort of {args.n_points} uint64: {sort_best:.3f} s  ratio {best / sort_best:.2f}")
    print(f"peak memory of the adjustment {peak_mb} MiB (inputs {input_mb:.0f} MiB), "
          f"process max RSS {maxrss_mb:.0f} MiB")  # fmt: skip
    print(f"translation error after one iteration (m): {err}, "
          f"rejected planes {len(res.rejected_planes)}")  # fmt: skip
    print(
        json.dumps(
            {
                "n_points": args.n_points,
                "n_planes": args.n_planes,
                "seconds": round(best, 4),
                "sort_seconds": round(sort_best, 4),
                "ratio_to_sort": round(best / sort_best, 3),
                "peak_mb": None if peak_mb is None else round(peak_mb, 1),
                "input_mb": round(input_mb, 1),
                "maxrss_mb": round(maxrss_mb, 1),
                "python": platform.python_version(),
                "numpy": np.__version__,
            }
        )
    )


def stochastic_cost(args):
    """Converged ``adjust_rigid`` with ``stochastic_model="white"`` and ``"full"``, each with
    and without plane tests (best of ``--repeat``, interleaved), on a problem with 3 mm of
    smooth 3-D drift on the after epoch. The yardstick is one white adjustment without plane
    tests; the white model's data snooping re-adjusts once per rejected plane."""
    (before, bl, after, al), (r, t, origin) = make_problem(args.n_points, args.n_planes)
    # a smooth drift field (random Fourier features, 3 mm per axis, ~50 m correlation)
    rng = np.random.default_rng(7)
    om = rng.normal(0, 1 / 50.0, (64, 2))
    ph = rng.uniform(0, 2 * np.pi, 64)
    amp = rng.normal(0, 0.003 * np.sqrt(2 / 64), (64, 3))
    after = after + np.cos((after[:, :2] - origin[:2]) @ om.T + ph) @ amp
    runs = {
        "white": ("white", True),  # the study's data snooping: one re-adjustment per rejection
        "white, no plane tests": ("white", False),  # one adjustment: the yardstick
        "full": ("full", True),
        "full, no plane tests": ("full", False),
    }
    times = {k: float("inf") for k in runs}
    res = {}
    for _ in range(args.repeat):
        for name, (model, reject) in runs.items():
            t0 = time.perf_counter()
            res[name] = adjust_rigid(
                before, bl, after, al, sigma_before=0.02, sigma_after=0.02,
                stochastic_model=model, reject_outlier_planes=reject,
            )  # fmt: skip
            times[name] = min(times[name], time.perf_counter() - t0)
    vc = res["full"].variance_components
    for model, sec in times.items():
        rr = res[model]
        c = rr.centre
        err = rr.displacement - ((c - origin) @ r.T + origin + t - c)
        print(f"{model}: {sec:.2f} s, {rr.iterations} iterations, translation error (mm) "
              f"{np.round(1000 * err, 3)}, sigma (mm) {np.round(1000 * rr.sigma[3:], 3)}, "
              f"rejected {len(rr.rejected_planes)}")  # fmt: skip
    print("components:", {k.name: round(1000 * k.sigma_m, 3) for k in vc.components},
          "range", vc.spatial_range_m, "n_eff", round(vc.n_eff, 1))  # fmt: skip
    one = times["white, no plane tests"]
    print(json.dumps({"n_points": args.n_points, "n_planes": args.n_planes,
                      **{k.replace(", ", "_").replace(" ", "_") + "_s": round(v, 3)
                         for k, v in times.items()},
                      "full_over_one_adjustment": round(times["full"] / one, 3),
                      "full_no_tests_over_one_adjustment": round(
                          times["full, no plane tests"] / one, 3),
                      "numpy": np.__version__}))  # fmt: skip
    return 0


if __name__ == "__main__":
    main()
