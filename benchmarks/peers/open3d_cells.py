"""Peer estimator: Open3D point-to-plane ICP per windowed-ICP cell (issue #18).

Run with the peer venv's python (``benchmarks/peers/setup_peer_venv.sh``): Open3D is not a
SlipMap dependency.

Usage: ``python open3d_cells.py IN.npz OUT.json``

``IN.npz``: ``before (M, 3)``, ``after (N, 3)``, ``cell (N,)`` (int, -1: not used),
``centres (K, 3)``, ``boxes (K, 4)`` (xmin, xmax, ymin, ymax of the before points a cell may
use), scalars ``max_corr_m`` and ``normal_radius_m``. Each cell's after points (source) are
registered onto its before points (target) from the identity, both shifted by the cell
centre; the ground motion at the centre is then ``-t`` of the fitted ``T``. ``OUT.json``:
``{"d": (K, 3), "fitness": (K,), "seconds": total, "cpu_seconds": ..., "open3d_version": ...}``;
``seconds`` (wall) and ``cpu_seconds`` (all threads) cover normals and ICP of every cell, not
file I/O.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import open3d as o3d


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    with np.load(argv[0]) as f:
        before, after, cell = f["before"], f["after"], f["cell"]
        centres, boxes = f["centres"], f["boxes"]
        max_corr, radius = float(f["max_corr_m"]), float(f["normal_radius_m"])
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    order = np.argsort(cell, kind="stable")
    bounds = np.searchsorted(cell[order], np.arange(len(centres) + 1))
    out_d, fit = np.full((len(centres), 3), np.nan), np.zeros(len(centres))
    t0, c0 = time.perf_counter(), time.process_time()
    for k, c in enumerate(centres):
        src = after[order[bounds[k] : bounds[k + 1]]] - c
        x0, x1, y0, y1 = boxes[k]
        inb = (before[:, 0] >= x0) & (before[:, 0] <= x1) & (before[:, 1] >= y0)
        tgt = before[inb & (before[:, 1] <= y1)] - c
        if len(src) < 10 or len(tgt) < 10:
            continue
        s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
        t = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
        t.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        r = o3d.pipelines.registration.registration_icp(
            s, t, max_corr, np.eye(4),
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50),
        )  # fmt: skip
        out_d[k] = -np.asarray(r.transformation)[:3, 3]
        fit[k] = r.fitness
    seconds = time.perf_counter() - t0
    cpu_seconds = time.process_time() - c0  # all threads of the process
    with open(argv[1], "w", encoding="utf-8") as fh:
        json.dump(
            {"d": out_d.tolist(), "fitness": fit.tolist(), "seconds": seconds,
             "cpu_seconds": cpu_seconds, "open3d_version": o3d.__version__},
            fh,
        )  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
