"""PIV at discontinuities (issue #29, item 2): lone-star with a scarp, with OpenPIV beside it.

Two cases made from tests/data/lone-star.laz (the cloud split at random into two disjoint
halves, one seeded split per ``--seeds``; the second half moved by a known field), as the
issue's new-user table:

* ``lobe``: the smooth round lobe (radius a third of the cloud's smaller side, 10.8 m; peak
  0.6 m south and 0.24 m down, :func:`slipmap.core.synthetic.make_lobe_pair`);
* ``scarp``: a straight scarp across the cloud (through ``centre + (6, 0)`` m, azimuth 15°);
  east of it a rigid slab translating by ``(0.25, -0.45, -0.15)`` m; west of it an elongated,
  rotated lobe (semi-axes 5 m x 13 m, azimuth 25°, centre ``centre - (5, 0)`` m, peak 0.6 m
  south and 0.24 m down). The field jumps across the scarp.

PIV (GR ``--grid``, default 0.15 m, the default passes ``64 32 16 16 16`` px, 50 % overlap) runs
without breaklines and, on the scarp case, with the true scarp as ``breaklines``; OpenPIV's
``windef`` (``benchmarks/peers/openpiv_windef.py``, the peer venv) on the same DEMs, vectors at
the same places. Truth at the vector positions (before image). Scored on the valid vectors with
data: in the moving ground (the lobe, ``r < 1``, and the slab) at least 3 m from the scarp;
on all vectors >= 3 m from it; and on the vectors within 3 m (near the scarp). RMSE of the
horizontal error in metres and in grid cells (target: <= 0.25 cell).

Usage: ``python benchmarks/validate_piv.py [--seeds 0 1 2] [--grid 0.15] [--case lobe scarp]
[--windows 64 32 16 16 16] [--no-peer]``. The last line is JSON.
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from slipmap.core.breaklines import breaklines as make_breaklines
from slipmap.core.breaklines import distance_m
from slipmap.core.dem import common_grid, grid_elevation
from slipmap.core.fields import field_from_columns, sample_field
from slipmap.core.io.las import read_las
from slipmap.core.piv import piv
from slipmap.core.synthetic import LobeField

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peers.peer import peer_missing, run_script  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "lone-star.laz"
SCORE_FROM_SCARP_M = 3.0


class ScarpField:
    """Lobe west of a straight scarp, rigid slab east of it (see the module docstring)."""

    def __init__(self, centre, *, slab=(0.25, -0.45, -0.15), azimuth_deg=15.0, offset_m=6.0):
        self.centre = np.asarray(centre, dtype=np.float64)
        a = math.radians(azimuth_deg)
        self.direction = np.array([math.sin(a), math.cos(a)])
        self.normal = np.array([math.cos(a), -math.sin(a)])  # pointing east-ish
        self.point = self.centre + np.array([offset_m, 0.0])
        self.slab = np.asarray(slab, dtype=np.float64)
        self.lobe = LobeField(
            centre_xy=tuple(self.centre - np.array([5.0, 0.0])),
            radius_x_m=5.0,
            radius_y_m=13.0,
            azimuth_deg=25.0,
            max_d_m=(0.0, -0.6, -0.24),
        )

    def east(self, xy):
        return (np.asarray(xy)[:, :2] - self.point) @ self.normal > 0

    def line(self, half_length_m=60.0):
        return np.vstack(
            [
                self.point - half_length_m * self.direction,
                self.point + half_length_m * self.direction,
            ]
        )

    def moving(self, xy):
        return self.east(xy) | self.lobe.interior_mask(xy, fraction=0.999)

    def __call__(self, xy):
        xy = np.asarray(xy, dtype=np.float64)
        return np.where(self.east(xy)[:, None], self.slab[None, :], self.lobe(xy))


class RoundLobe:
    def __init__(self, centre, radius):
        self.lobe = LobeField(
            centre_xy=tuple(centre), radius_x_m=radius, radius_y_m=radius, max_d_m=(0, -0.6, -0.24)
        )

    def moving(self, xy):
        return self.lobe.interior_mask(xy, fraction=0.999)

    def __call__(self, xy):
        return self.lobe(xy)


def make_pair(pts, field, seed):
    rng = np.random.default_rng([seed, 29])
    half = rng.random(len(pts)) < 0.5
    before = pts[half]
    after = pts[~half] + field(pts[~half])
    return before, after


def _rms(a):
    a = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(a**2))) if a.size else float("nan")


def _score(err_h, cell, mask):
    e = err_h[mask]
    return {
        "n": int(mask.sum()),
        "rmse_m": round(_rms(e), 4),
        "rmse_cells": round(_rms(e) / cell, 3),
        "median_m": round(float(np.median(e)), 4) if e.size else None,
    }


def cell_centres(after, cell_m=5.0, min_points=500):
    """Centres of the ``cell_m`` cells (windowed ICP's lattice, origin 0, 0) holding at least
    ``min_points`` after-points: the places the issue's table scores every method at."""
    x0 = math.floor(after[:, 0].min() / cell_m) * cell_m
    y0 = math.ceil(after[:, 1].max() / cell_m) * cell_m
    col = np.floor((after[:, 0] - x0) / cell_m).astype(np.int64)
    row = np.floor((y0 - after[:, 1]) / cell_m).astype(np.int64)
    key, n = np.unique(np.column_stack([row, col]), axis=0, return_counts=True)
    key = key[n >= min_points]
    return np.column_stack([x0 + (key[:, 1] + 0.5) * cell_m, y0 - (key[:, 0] + 0.5) * cell_m])


def _at_cells(res, field, bl, centres, cell):
    """Horizontal RMSE of the PIV field sampled bilinearly (valid vectors) at the cell
    centres >= 3 m from the scarp (as the issue's table)."""
    gf = field_from_columns(
        res.x.ravel(), res.y.ravel(), res.dx.ravel(), res.dy.ravel(), spacing_m=res.spacing_m,
        valid=res.valid.ravel(),
    )  # fmt: skip
    d = distance_m(centres, bl) if bl is not None else np.full(len(centres), np.inf)
    c = centres[d >= SCORE_FROM_SCARP_M]
    est = sample_field(gf, c)[:, :2]
    ok = np.isfinite(est).all(axis=1)
    eh = np.hypot(*(est[ok] - field(c[ok])[:, :2]).T)
    return {"n": int(ok.sum()), "of": len(c), "rmse_m": round(_rms(eh), 4),
            "rmse_cells": round(_rms(eh) / cell, 3)}  # fmt: skip


def _regions(field, xy, bl):
    d = distance_m(xy, bl) if bl is not None else np.full(len(xy), np.inf)
    far = d >= SCORE_FROM_SCARP_M
    return {"moving_far": field.moving(xy) & far, "all_far": far, "near": ~far}


def run_case(name, pts, seed, grid_m, windows, peer):
    lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    centre = 0.5 * (lo + hi)
    if name == "scarp":
        field = ScarpField(centre)
        bl = make_breaklines([field.line()])
    else:
        field = RoundLobe(centre, float(np.min(hi - lo)) / 3.0)
        bl = None
    before, after = make_pair(pts, field, seed)
    grid = common_grid(before, after, cell_m=grid_m)
    zb = grid_elevation(before, grid=grid)
    za = grid_elevation(after, grid=grid)
    out = {"case": name, "seed": seed, "grid_m": grid_m, "windows_px": list(windows)}
    takes_lines = "breaklines" in inspect.signature(piv).parameters
    runs = [("slipmap", None)] + ([("slipmap_breaklines", bl)] if bl and takes_lines else [])
    xy = None
    for label, lines in runs:
        t0 = time.perf_counter()
        kw = {} if lines is None else {"breaklines": lines}
        res = piv(zb, za, grid=grid, windows_px=windows, expected_max_displacement_m=0.9, **kw)
        sec = time.perf_counter() - t0
        xy = np.column_stack([res.x.ravel(), res.y.ravel()])
        truth = field(xy)[:, :2]
        est = np.column_stack([res.dx.ravel(), res.dy.ravel()])
        ok = res.valid.ravel() & np.isfinite(est).all(axis=1)
        eh = np.hypot(*(est - truth).T)
        r = {"seconds": round(sec, 2)}
        for reg, m in _regions(field, xy, bl).items():
            r[reg] = _score(eh, grid_m, m & ok)
        r["cells5"] = _at_cells(res, field, bl, cell_centres(after), grid_m)
        nb = getattr(res, "near_break", None)
        if nb is not None and lines is not None:
            nb = nb.ravel() & np.isfinite(est).all(axis=1)
            r["near_break"] = _score(eh, grid_m, nb)
            r["near_break_valid"] = _score(eh, grid_m, nb & ok)
        out[label] = r
    if peer:
        out["openpiv"] = _openpiv(zb, za, grid, grid_m, windows, field, bl, xy)
    return out


def _openpiv(zb, za, grid, grid_m, windows, field, bl, xy_slipmap):
    why = peer_missing("openpiv")
    if why is not None:
        return {"skipped": why}
    overlap = 0.5
    w, step = windows[-1], max(1, int(round(windows[-1] * (1.0 - overlap))))
    r0, c0 = (((n - w) - ((n - w) // step) * step) // 2 for n in zb.shape)
    o = run_script(
        "openpiv_windef.py",
        {
            "z_before": zb[r0:, c0:],
            "z_after": za[r0:, c0:],
            "windows_px": np.asarray(windows, dtype=np.int64),
            "overlap": np.float64(overlap),
            "max_displacement_px": np.float64(0.9 / grid_m + 2),
        },
    )
    ox = grid.x_min + (c0 + np.asarray(o["x"]).ravel()) * grid_m
    oy = grid.y_max - (r0 + np.asarray(o["y"]).ravel()) * grid_m
    od = np.column_stack([np.asarray(o["u"]).ravel(), -np.asarray(o["v"]).ravel()]) * grid_m
    ok = np.asarray(o["valid"]).ravel() & np.isfinite(od).all(axis=1)
    oxy = np.column_stack([ox, oy])
    eh = np.hypot(*(od - field(oxy)[:, :2]).T)
    r = {"seconds": round(float(o["seconds"]), 2), "version": o["openpiv_version"]}
    for reg, m in _regions(field, oxy, bl).items():
        r[reg] = _score(eh, grid_m, m & ok)
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--grid", type=float, default=0.15)
    ap.add_argument("--windows", type=int, nargs="+", default=[64, 32, 16, 16, 16])
    ap.add_argument("--case", nargs="+", default=["lobe", "scarp"], choices=["lobe", "scarp"])
    ap.add_argument("--no-peer", action="store_true")
    args = ap.parse_args(argv)
    pts = read_las(DATA).xyz
    results = []
    for seed in args.seeds:
        for case in args.case:
            r = run_case(case, pts, seed, args.grid, tuple(args.windows), not args.no_peer)
            results.append(r)
            print(json.dumps(r), flush=True)
    print()
    print(
        "| case | seed | method | at 5 m cells >= 3 m: RMSE (cm) | (cells) | "
        "moving ground >= 3 m from the scarp: RMSE (cm) | (cells) | "
        "all vectors >= 3 m: RMSE (cm) | within 3 m: RMSE (cm) | flagged near_break: RMSE (cm) "
        "| s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        for label in ("slipmap", "slipmap_breaklines", "openpiv"):
            m = r.get(label)
            if m is None or "skipped" in m:
                continue
            nb = m.get("near_break", {})
            print(
                f"| {r['case']} | {r['seed']} | {label} | "
                + (
                    f"{100 * m['cells5']['rmse_m']:.2f} | {m['cells5']['rmse_cells']} | "
                    if "cells5" in m
                    else "| | "
                )
                + f"{100 * m['moving_far']['rmse_m']:.2f} | "
                f"{m['moving_far']['rmse_cells']} | {100 * m['all_far']['rmse_m']:.2f} | "
                f"{100 * m['near']['rmse_m']:.2f} | "
                f"{'' if not nb else round(100 * nb['rmse_m'], 2)} | {m['seconds']} |"
            )
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
