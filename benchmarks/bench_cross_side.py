"""Benchmark: the cost of the two sides' joint covariance (issue #30 item 1).

Usage: ``python benchmarks/bench_cross_side.py --planes-per-side 50 150 375 750``

The relative slip's covariance takes the survey error shared across the trace into account:
the plane-level components are estimated once more on both sides' planes together (REML,
dense, :func:`slipmap.core.stochastic.joint_covariance`, up to
``stochastic.DENSE_MAX_PLANES`` planes of both sides), else each side's components are
combined (:func:`slipmap.core.stochastic.cross_covariance`, linear in planes). This times, on
a synthetic two-sided scene (planes of every orientation, 40 points per plane and epoch, 2 mm
noise, four acquisition strips crossing the trace, a 2 mm plane component and a 3 mm spatial
field of 40 m range over both sides): the two sides' stochastic adjustments (the yardstick:
what a run costs anyway), the joint covariance, and the cross covariance of the sides'
own components on the same results, best of ``--repeat``. Prints one line per size, then the
rows as JSON on the last line.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from slipmap.core import stochastic as sto
from slipmap.core.adjustment import adjust_rigid
from slipmap.core.displacement import SideResult

SIGMA = 0.002


def make_scene(n_per_side: int, seed: int = 0, n_per: int = 40):
    """{side: (before, labels_before, after, labels_after, unit_after)} with a known shared
    survey error; the right side moves 18 mm along y."""
    rng = np.random.default_rng(seed)
    half = 30.0 * max(1.0, np.sqrt(n_per_side / 16.0))  # keep the planes' density
    geom = {}
    for side, sgn in (("left", -1.0), ("right", 1.0)):
        c = np.column_stack(
            [sgn * rng.uniform(12, 12 + 2 * half, n_per_side),
             rng.uniform(-half, half, n_per_side), rng.uniform(0, 8, n_per_side)]
        )  # fmt: skip
        nrm = rng.normal(size=(n_per_side, 3))
        nrm[0::3, :2] *= 0.3
        nrm[1::3, 2] = 0.0
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        geom[side] = (c, nrm)
    allc = np.concatenate([geom[s][0] for s in ("left", "right")])
    # the spatial field from random Fourier features (a smooth field of ~40 m correlation)
    k = rng.normal(0, 1.0 / 25.0, (64, 3))
    ph = rng.uniform(0, 2 * np.pi, 64)
    amp = rng.normal(0, 0.003 * np.sqrt(2.0 / 64), (64, 3))
    field = np.cos(allc @ k.T + ph) @ amp
    units = rng.normal(0, 0.002, (4, 3))
    out, off = {}, 0
    for side in ("left", "right"):
        c, nrm = geom[side]
        u = np.clip(((c[:, 1] + half) // (half / 2)).astype(np.int64), 0, 3)
        move = np.array([0.0, -0.018, 0.0]) if side == "right" else np.zeros(3)
        ref = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        e1 = np.cross(nrm, ref)
        e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
        e2 = np.cross(nrm, e1)
        err = np.einsum("ij,ij->i", nrm, units[u] + field[off : off + len(c)])
        err += rng.normal(0, 0.002, len(c))
        lab = np.repeat(np.arange(len(c)), n_per)
        eps = []
        for ep in (0, 1):
            ab = rng.uniform(-3, 3, (lab.size, 2))
            p = c[lab] + ab[:, :1] * e1[lab] + ab[:, 1:] * e2[lab]
            if ep:
                p = p + move + (err * nrm.T).T[lab]
            eps.append(p + rng.normal(0, SIGMA, p.shape))
        out[side] = (eps[0], lab, eps[1], lab, u[lab])
        off += len(c)
    return out


def adjust_sides(data):
    """Both sides' stochastic adjustments ("full" model, units of the after epoch)."""
    res = {}
    for side, (b, lb, a, la, ua) in data.items():
        r = adjust_rigid(
            b, lb, a, la, sigma_before=SIGMA, sigma_after=SIGMA, unit_after=ua,
            stochastic_model="full", reject_outlier_planes=False,
        )  # fmt: skip
        res[side] = SideResult(side, r, None, None, None)
    return res


def _best(repeat, fn, *args):
    best, res = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = fn(*args)
        best = min(best, time.perf_counter() - t0)
    return best, res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--planes-per-side", type=int, nargs="+", default=[50, 150, 375, 750])
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args(argv)
    rows = []
    for n in args.planes_per_side:
        t_sides, res = _best(args.repeat, adjust_sides, make_scene(n))
        ga, gb = res["left"].rigid.plane_gain, res["right"].rigid.plane_gain
        t_joint, joint = _best(args.repeat, sto.joint_covariance, ga, gb)
        t_cross, _ = _best(args.repeat, sto.cross_covariance, ga, gb)
        row = {
            "planes_per_side": n,
            "planes_joint": int(ga.e.size + gb.e.size),
            "sides_s": round(t_sides, 3),
            "joint_s": round(t_joint, 3),
            "joint_made": joint is not None,
            "cross_s": round(t_cross, 4),
            "joint_over_sides": round(t_joint / t_sides, 2),
        }
        rows.append(row)
        print(
            f"{n:5d} planes a side ({row['planes_joint']} joint): both sides' adjustments "
            f"{t_sides:.2f} s, joint covariance {t_joint:.2f} s "
            f"({'made' if row['joint_made'] else 'not made: too many planes'}), "
            f"{row['joint_over_sides']}x; cross covariance {t_cross * 1e3:.1f} ms"
        )
    print(json.dumps({"machine": platform.machine(), "numpy": np.__version__, "rows": rows}))


if __name__ == "__main__":
    main()
