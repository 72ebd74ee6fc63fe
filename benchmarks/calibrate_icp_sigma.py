"""Calibration and out-of-sample check of the windowed ICP's sigmas (issue #29, item 3).

On lone-star (tests/data/lone-star.laz, split at random into two disjoint halves) three cases
with a known motion of the second half:

* ``shift``: a uniform shift (0.2, -0.4, 0.05) m (every cell rigid);
* ``lobe``: the default lobe of :func:`slipmap.core.synthetic.make_lobe_pair`;
* ``scarp``: a rigid slab beyond a straight scarp (a line through the cloud's centre at
  azimuth 60 degrees): the after-points on its south-east side moved 0.3 m away from it
  (and 5 cm down), the rest still (:func:`scarp_pair`, written here).

Each run of :func:`slipmap.core.icp.windowed_icp` (5 m and 2 m cells, coarse-to-fine as
:func:`_levels` says, rigid cells and the spline field) is scored per class of cell: all, dense /
sparse (upper / lower tercile of the correspondences), rough / smooth (of the point-to-plane
residual RMS), near / far from the scarp (a cell not crossed by it whose centre is within /
beyond 1.5 cells), in / out of the lobe. Scored: cells with >= 500 correspondences, not
flagged by the median test (no truth used to choose them), not crossed by the scarp. Per
class the share of the error components (dx, dy, dz against the truth at the cell centre)
within 2 sigma, for

* ``formal``: independent residuals (``sigma_model="independent"``, no factor);
* ``current``: the formal sigmas times the field's neighbour variance factor (the default
  before issue #29);
* ``blocks``: the block (cluster-robust) covariance alone (``sigma_scaling="formal"``);
* ``new``: the default: blocks and the cell-wide floor (the spline with at least
  ``SPLINE_FLOOR_SHARE`` of its cells' excess), the neighbour factor a check only.

Seeds 0-2 calibrated ``FLOOR_QUANTILE`` and ``SPLINE_FLOOR_SHARE`` (slimmer variants then
in this script), 3-5 check. Usage::

    python benchmarks/calibrate_icp_sigma.py --seeds 0 1 2 --cells 5 --cache DIR

Prints one JSON line per run and the Markdown table of docs/fields.md; ``--out FILE`` writes
the runs as JSON.
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import slipmap.core.icp as icp
from slipmap.core.icp_blocks import CellFloor
from slipmap.core.io.las import read_las
from slipmap.core.synthetic import make_lobe_pair

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "lone-star.laz"
SHIFT = np.array([0.2, -0.4, 0.05])
VARIANTS = ("formal", "current", "blocks", "new")
CLASSES = ("all", "dense", "sparse", "rough", "smooth", "near", "far", "lobe", "stable")


class ScarpPair:
    """Two halves of a cloud, the after half's points beyond a straight line moved rigidly."""

    def __init__(self, pts, seed, *, azimuth_deg=60.0, slip_m=0.3, drop_m=0.05):
        rng = np.random.default_rng(seed)
        half = rng.random(len(pts)) < 0.5
        self.before = pts[half]
        after = pts[~half].copy()
        self.point = 0.5 * (pts[:, :2].min(axis=0) + pts[:, :2].max(axis=0))
        az = np.radians(azimuth_deg)
        self.direction = np.array([np.sin(az), np.cos(az)])  # along the scarp
        self.normal = np.array([self.direction[1], -self.direction[0]])  # to the slab (SE)
        self.motion = np.r_[slip_m * self.normal, -drop_m]
        moved = self.side(after[:, :2]) > 0
        after[moved] += self.motion
        self.after = after

    def side(self, xy):
        """Signed distance from the scarp line, metres (> 0: the slab)."""
        return (np.asarray(xy) - self.point) @ self.normal

    def truth(self, c_xy):
        """Motion of the material now at ``c_xy`` (after frame)."""
        on_slab = self.side(c_xy - self.motion[:2]) > 0
        return np.where(on_slab[:, None], self.motion[None, :], 0.0)


def scarp_pair(pts, seed, **kw) -> ScarpPair:
    """A rigid slab beyond a straight scarp (see :class:`ScarpPair`)."""
    return ScarpPair(pts, seed, **kw)


def _truth_after_frame(field, c_xy, iterations=20):
    p0 = c_xy.copy()
    for _ in range(iterations):
        p0 = c_xy - field(p0)[:, :2]
    return field(p0)


def _capture():
    """Wrap ``_apply_sigma_scaling`` to keep the pair covariances windowed_icp passes it,
    and the cells' pass (``_block_covariances``, ``_median_flags``) of a spline run, so that
    one run scores the rigid cells and the spline field. Returns the box and an undo."""
    box = {}
    saved = {k: getattr(icp, k) for k in ("_apply_sigma_scaling", "_block_covariances",
                                           "_median_flags")}  # fmt: skip

    def scaling(res, *a, **kw):
        args = list(a)
        box["pair_cov"] = kw.get("pair_cov", args[3] if len(args) > 3 else None)
        return saved["_apply_sigma_scaling"](res, *a, **kw)

    def blocks(fits, cov_d, flagged):
        out = saved["_block_covariances"](fits, cov_d, flagged)
        if "cells_fits" not in box:
            box.update(cells_fits=fits, cells_cov=out[1], cells_formal=cov_d,
                       cells_flagged=flagged, cells_block=out[0],
                       cells=box["last_cells"])  # fmt: skip
        return out

    def flags(cells, *a, **kw):
        box["last_cells"] = cells  # the fine pass's come last before the blocks
        return saved["_median_flags"](cells, *a, **kw)

    icp._apply_sigma_scaling = scaling
    icp._block_covariances = blocks
    icp._median_flags = flags

    def undo():
        for k, v in saved.items():
            setattr(icp, k, v)

    return box, undo


def cells_result(res, box):
    """The rigid cells' result of a spline run (their pass before the spline), as the
    fields :func:`variants` and :func:`classes` read."""
    f, cells = box["cells_fits"], box["cells"]
    ok = f.ok
    cov = box["cells_cov"][ok]
    sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    zero = np.zeros(int(ok.sum()))
    return replace(
        res,
        x=cells.centres[ok, 0],
        y=cells.centres[ok, 1],
        dx=f.d[ok, 0],
        dy=f.d[ok, 1],
        dz=f.d[ok, 2],
        sigma_dx=sd[:, 0],
        sigma_dy=sd[:, 1],
        sigma_dz=sd[:, 2],
        cov_d=cov,
        sigma_rx=zero,
        sigma_ry=zero,
        sigma_rz=zero,
        rmse=f.rmse[ok],
        n=f.n[ok],
        converged=f.converged[ok],
        flagged=box["cells_flagged"][ok],
        row=cells.row[ok],
        col=cells.col[ok],
        field_model="cells",
        sigma_formal=np.sqrt(np.diagonal(box["cells_formal"][ok], axis1=1, axis2=2)),
        sigma_block_m=box["cells_block"].block_m,
        sigma_block_ratio=box["cells_block"].kappa,
    )


def variants(res, pair_cov, cells_floor):
    """(K, 3) sigmas of dx, dy, dz per variant; ``cells_floor``: the rigid cells' floor of
    the same run (for the spline, whose neighbours share one field)."""
    sig = np.column_stack([res.sigma_dx, res.sigma_dy, res.sigma_dz])
    formal = res.sigma_formal
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(formal > 0, sig / formal, 1.0)
    pc_formal = None
    if pair_cov is not None:  # the block pair covariances scale as sqrt(r_i r_j)
        pairs, pc = pair_cov
        pc_formal = (pairs, pc / (r[pairs[:, 0]] * r[pairs[:, 1]]))
    ind = replace(
        res,
        sigma_model="independent",
        sigma_dx=formal[:, 0],
        sigma_dy=formal[:, 1],
        sigma_dz=formal[:, 2],
        cov_d=np.einsum("ki,ij->kij", formal**2, np.eye(3)),
    )
    cur = icp._apply_sigma_scaling(ind, "field", pair_cov=pc_formal)
    spline = res.field_model == "spline"
    new = icp._apply_sigma_scaling(
        res, "field", pair_cov=pair_cov, cells_floor=cells_floor if spline else None
    )

    def s(x):
        return np.column_stack([x.sigma_dx, x.sigma_dy, x.sigma_dz])

    out = {"formal": formal, "current": s(cur), "blocks": sig, "new": s(new)}
    return out, {
        "factor_current": cur.sigma_factor_estimate,
        "check_factor": new.sigma_factor_estimate,
        "n_cap": new.sigma_n_cap,
        "a": new.sigma_floor_factor**2,
        "block_m": res.sigma_block_m,
        "block_ratio": res.sigma_block_ratio,
    }


def classes(res, case, extra):
    """Boolean masks of the scored cells per class (K,)."""
    base = (res.n >= 500) & ~np.asarray(res.flagged, dtype=bool)
    out = {}
    if case == "scarp":
        c = np.column_stack([res.x, res.y])
        half = 0.5 * res.cell_m
        corners = np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]]) * half
        sides = np.stack([extra.side(c + k) for k in corners], axis=1)
        crossed = np.any(sides > 0, axis=1) & np.any(sides < 0, axis=1)
        base &= ~crossed
        dist = np.abs(extra.side(c))
        out["near"] = base & (dist < 1.5 * res.cell_m)
        out["far"] = base & (dist >= 1.5 * res.cell_m)
    if case == "lobe":
        inside = np.linalg.norm(extra, axis=1) > 0
        out["lobe"] = base & inside
        out["stable"] = base & ~inside
    out["all"] = base
    for name, score in (("dense", res.n.astype(float)), ("rough", res.rmse)):
        lo, hi = np.quantile(score[base], [1 / 3, 2 / 3]) if base.any() else (0, 0)
        low = {"dense": "sparse", "rough": "smooth"}[name]
        out[name] = base & (score > hi)
        out[low] = base & (score <= lo)
    return out


def _levels(case, cell):
    """Coarse-to-fine levels: 1 (the CLI's default) in 2 m cells, 0 in 5 m cells (as the
    5 m rows of docs/fields.md; a quarter of the time)."""
    return 1 if cell < 3 else 0


def run(case, pts, seed, cell, cache=None):
    """One spline run of a case (its cells' pass scored too): two result dicts."""
    if case == "shift":
        rng = np.random.default_rng(seed)
        half = rng.random(len(pts)) < 0.5
        before, after, extra = pts[half], pts[~half] + SHIFT, None
    elif case == "lobe":
        pair = make_lobe_pair(pts, seed=seed)
        before, after, extra = pair.before, pair.after, pair
    else:
        pair = scarp_pair(pts, seed)
        before, after, extra = pair.before, pair.after, pair
    path = None if cache is None else cache / f"{case}_{seed}_{cell:g}.pkl"
    t0 = time.perf_counter()
    if path is not None and path.exists():  # the fits, to calibrate the post-processing
        res, box = pickle.loads(path.read_bytes())
    else:
        box, undo = _capture()
        try:
            res = icp.windowed_icp(
                before,
                after,
                cell_m=cell,
                coarse_to_fine=_levels(case, cell),
                field_model="spline",
                sigma_scaling="formal",
            )
        finally:
            undo()
        box.pop("last_cells", None)
        if path is not None:
            path.write_bytes(pickle.dumps((res, box)))
    sec = time.perf_counter() - t0
    cres = cells_result(res, box)
    fl = icp._apply_floor(cres)
    cfloor = CellFloor(fl.sigma_floor_factor, fl.sigma_n_cap, 0, float("nan"))
    return [score(case, seed, cell, m, r, box, extra, sec, cfloor) for m, r in (
        ("cells", cres), ("spline", res))]  # fmt: skip


def score(case, seed, cell, model, res, box, extra, sec, cfloor):
    """Shares within 2 sigma of one result per class and variant."""
    c = np.column_stack([res.x, res.y])
    if case == "shift":
        truth = np.broadcast_to(SHIFT, (len(res), 3))
    elif case == "lobe":
        truth = _truth_after_frame(extra.field, c)
        extra = truth
    else:
        truth = extra.truth(c)
    err = np.column_stack([res.dx, res.dy, res.dz]) - truth
    sig, info = variants(res, box.get("pair_cov") if model == "spline" else None, cfloor)
    masks = classes(res, case, extra)
    counts = {}
    for cl, m in masks.items():
        counts[cl] = {"cells": int(m.sum())}
        for v, s in sig.items():
            counts[cl][v] = int(np.sum(np.abs(err[m]) < 2 * s[m]))
    return {
        "case": case,
        "seed": seed,
        "cell_m": cell,
        "model": model,
        "seconds": round(sec, 1),
        "rmse_3d_m": round(float(np.sqrt(np.mean(np.sum(err[masks["all"]] ** 2, 1)))), 4),
        **{k: (round(v, 3) if np.isfinite(v) else str(v)) for k, v in info.items()},
        "counts": counts,
    }


def table(runs, title):
    """Markdown table: per case, cell, model and class the pooled share within 2 sigma."""
    lines = [
        f"{title}",
        "",
        "| case | cell (m) | model | class | cells | " + " | ".join(VARIANTS) + " |",
        "|---|---|---|---|---|" + "---|" * len(VARIANTS),
    ]
    keys = sorted({(r["case"], r["cell_m"], r["model"]) for r in runs})
    for case, cell, model in keys:
        rs = [r for r in runs if (r["case"], r["cell_m"], r["model"]) == (case, cell, model)]
        for cl in CLASSES:
            have = [r["counts"][cl] for r in rs if cl in r["counts"]]
            n = sum(h["cells"] for h in have)
            if n == 0:
                continue
            share = [sum(h[v] for h in have) / (3 * n) for v in VARIANTS]
            cells_txt = f"{n}"
            lines.append(
                f"| {case} | {cell:g} | {model} | {cl} | {cells_txt} | "
                + " | ".join(f"{s:.2f}" for s in share)
                + " |"
            )
    return "\n".join(lines)


def estimates(runs):
    """Markdown table: per case, cell and model the ranges over the seeds of the chosen block
    size, the block ratio, the floor's a and n_cap and the check factor."""
    lines = [
        "| case | cell (m) | model | block (m) | block ratio | a | n_cap | check factor | "
        "old factor |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def rng(vals):
        v = [float(x) for x in vals]
        lo, hi = min(v), max(v)
        fmt = (lambda t: f"{t:.0f}") if hi > 100 else (lambda t: f"{t:.2f}")
        return fmt(lo) if lo == hi else f"{fmt(lo)}–{fmt(hi)}"

    keys = sorted({(r["case"], r["cell_m"], r["model"]) for r in runs})
    for case, cell, model in keys:
        rs = [r for r in runs if (r["case"], r["cell_m"], r["model"]) == (case, cell, model)]
        keys_ = ("block_m", "block_ratio", "a", "n_cap", "check_factor", "factor_current")
        cols = [rng(r[k] for r in rs) for k in keys_]
        lines.append(f"| {case} | {cell:g} | {model} | " + " | ".join(cols) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--cells", type=float, nargs="+", default=[5.0])
    ap.add_argument("--cases", nargs="+", default=["shift", "lobe", "scarp"])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--cache", type=Path, default=None, help="folder keeping the fits")
    args = ap.parse_args(argv)
    if args.cache:
        args.cache.mkdir(parents=True, exist_ok=True)
    pts = read_las(DATA).xyz
    runs = []
    for seed in args.seeds:
        for case in args.cases:
            for cell in args.cells:
                for r in run(case, pts, seed, cell, args.cache):
                    runs.append(r)
                    print(json.dumps(r), flush=True)
    print(table(runs, f"seeds {args.seeds}"))
    print()
    print(estimates(runs))
    if args.out:
        args.out.write_text(json.dumps(runs, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
