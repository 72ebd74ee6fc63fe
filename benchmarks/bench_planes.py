"""Benchmark: planar segmentation of an N-point synthetic MLS scene, against np.sort of N keys.

Usage: ``python benchmarks/bench_planes.py --n 5000000 [--backends numpy,opencl] [--open3d]``

Times ``segment_planes`` (no file I/O) for each backend and, in the same run, ``np.sort`` of N
random uint64 (best of ``--repeat`` runs each). Prints human-readable lines, then, as the last
line, JSON for the fastest backend: ``{"n", "backend", "seconds", "sort_seconds",
"ratio_to_sort", ...}``. With ``--open3d`` (if Open3D is installed) it also times Open3D's
``detect_planar_patches`` on the same cloud and reports its recall beside ours.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import numpy as np

from slipmap.core.evaluation import score_segmentation
from slipmap.core.planes import segment_planes
from slipmap.core.synthetic import make_scene_n_points


def best_of(repeat, fn):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def sort_seconds(n, repeat, seed=0):
    keys = np.random.default_rng(seed).integers(0, 2**63, n, dtype=np.uint64)
    return best_of(repeat, lambda: np.sort(keys))[0]


def open3d_labels(points, seed=0):
    """Labels from Open3D's detect_planar_patches: a point belongs to the first patch whose
    oriented box contains it (patches are boxes around planar regions)."""
    import open3d as o3d

    o3d.utility.random.seed(seed)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - points.mean(axis=0)))
    t0 = time.perf_counter()
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    patches = pcd.detect_planar_patches(
        normal_variance_threshold_deg=60,
        coplanarity_deg=75,
        outlier_ratio=0.75,
        min_plane_edge_length=0,
        min_num_points=0,
        search_param=o3d.geometry.KDTreeSearchParamKNN(knn=30),
    )
    seconds = time.perf_counter() - t0
    labels = np.full(points.shape[0], -1, dtype=np.int64)
    for k, box in enumerate(patches):
        idx = np.asarray(box.get_point_indices_within_bounding_box(pcd.points))
        if idx.size:
            free = idx[labels[idx] < 0]
            labels[free] = k
    return seconds, labels


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="points in the scene")
    ap.add_argument("--backends", default="numpy,opencl", help="comma-separated backends")
    ap.add_argument("--repeat", type=int, default=2, help="runs per timing (best is kept)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--open3d", action="store_true", help="also time Open3D if installed")
    args = ap.parse_args(argv)

    scene = make_scene_n_points(args.n, "mls", seed=args.seed)
    n = scene.points.shape[0]
    print(
        f"scene: {n} points, {len(scene.surfaces)} surfaces, numpy {np.__version__}, "
        f"python {platform.python_version()}, {platform.machine()}"
    )
    t_sort = sort_seconds(n, max(3, args.repeat), args.seed)
    print(f"np.sort of {n} uint64: {t_sort:.3f} s")
    results = []
    for backend in [b.strip() for b in args.backends.split(",") if b.strip()]:
        try:
            seconds, res = best_of(
                args.repeat, lambda b=backend: segment_planes(scene.points, backend=b)
            )
        except Exception as exc:  # noqa: BLE001 - a missing backend is reported, not fatal
            print(f"{backend}: unavailable ({exc})")
            continue
        s = score_segmentation(scene.labels, res.labels)
        stages = ", ".join(f"{k} {v:.2f}" for k, v in res.timings_s.items())
        print(
            f"{backend}: {seconds:.3f} s = {seconds / t_sort:.2f} x sort; {len(res)} planes, "
            f"recall {s.recall:.3f}, precision {s.precision:.4f}, merged {s.n_merged} [{stages}]"
        )
        results.append(
            {
                "n": n,
                "backend": backend,
                "seconds": round(seconds, 4),
                "sort_seconds": round(t_sort, 4),
                "ratio_to_sort": round(seconds / t_sort, 3),
                "recall": round(s.recall, 4),
                "precision": round(s.precision, 5),
                "n_merged": s.n_merged,
                "n_planes": len(res),
            }
        )
    if not results:
        print("no backend ran", file=sys.stderr)
        return 1
    best = min(results, key=lambda r: r["seconds"])
    if args.open3d:
        try:
            o3d_seconds, o3d_labels = open3d_labels(scene.points, args.seed)
        except ImportError:
            print("open3d: not installed (pip install open3d)")
        else:
            s = score_segmentation(scene.labels, o3d_labels)
            print(
                f"open3d detect_planar_patches: {o3d_seconds:.3f} s, recall {s.recall:.3f}, "
                f"precision {s.precision:.4f}, merged {s.n_merged}"
            )
            best.update(
                {
                    "open3d_seconds": round(o3d_seconds, 4),
                    "open3d_recall": round(s.recall, 4),
                    "speedup_vs_open3d": round(o3d_seconds / best["seconds"], 2),
                }
            )
    print(json.dumps(best))
    return 0


if __name__ == "__main__":
    sys.exit(main())
