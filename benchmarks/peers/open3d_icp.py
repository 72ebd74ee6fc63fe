"""Peer estimator: Open3D point-to-plane ICP on each side of a fault.

Run with the peer venv's python (``benchmarks/peers/setup_peer_venv.sh``), never with the
project's: Open3D is not a SlipMap dependency.

Usage: ``python open3d_icp.py IN.npz OUT.json``

``IN.npz`` holds ``before (N1, 3)``, ``after (N2, 3)`` (float64, map coordinates),
``side_before (N1,)``, ``side_after (N2,)`` (int8: -1 left, +1 right, 0 left out),
``centre_left (3,)``, ``centre_right (3,)`` (where each side's motion is reported) and the
optional scalars ``max_corr_m`` (0.25), ``normal_radius_m`` (1.0) and ``voxel_m`` (0: no
downsampling).

For each side the before points (source) are registered onto the after points (target) with
``registration_icp`` and ``TransformationEstimationPointToPlane`` (target normals from
``KDTreeSearchParamHybrid(normal_radius_m, 30)``, identity start, at most 100 iterations).
Both clouds are first shifted by the side's centre, so the estimated ``T`` maps a before point
``p`` (relative to the centre) to ``R p + t`` in the after epoch: the displacement of the
material at the centre (before -> after) is ``t``. The shift also keeps the rotation from
leaking into the translation through large map coordinates.

``OUT.json``::

    {"left": {"displacement": [dx, dy, dz], "fitness": ..., "inlier_rmse": ...,
              "seconds": ..., "n_source": ..., "n_target": ..., "n_correspondences": ...,
              "transformation": 4x4 (centred frame), "information": 6x6},
     "right": {...},
     "relative": [dx, dy, dz],          # right minus left, metres
     "open3d_version": "0.x.y", "options": {...}}

``seconds`` is the wall time of downsampling, normal estimation and ICP for that side (not
file I/O, not the information matrix). ``information`` is Open3D's
``get_information_matrix_from_point_clouds`` (parameter order rx, ry, rz, tx, ty, tz): a
formal figure for reference only, it ignores correlated errors.
"""

from __future__ import annotations

import json
import logging
import sys
import time

import numpy as np
import open3d as o3d

log = logging.getLogger("slipmap.peers.open3d_icp")

DEFAULTS = {"max_corr_m": 0.25, "normal_radius_m": 1.0, "voxel_m": 0.0}
MAX_NN = 30
MIN_POINTS = 10


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))


def register_side(
    before: np.ndarray,
    after: np.ndarray,
    centre: np.ndarray,
    *,
    max_corr_m: float,
    normal_radius_m: float,
    voxel_m: float,
) -> dict:
    """Point-to-plane ICP of one side's before points onto its after points.

    Parameters
    ----------
    before, after : (N, 3) float64
        The side's points in each epoch, map coordinates.
    centre : (3,) float64
        Where the displacement is reported.
    max_corr_m, normal_radius_m, voxel_m : float
        Correspondence distance, normal search radius, voxel size (0: none), metres.

    Returns
    -------
    dict
        ``displacement`` (3,) of the material at ``centre`` (before -> after) and the
        diagnostics listed in the module docstring.
    """
    if len(before) < MIN_POINTS or len(after) < MIN_POINTS:
        raise ValueError(f"too few points on a side: {len(before)} before, {len(after)} after")
    centre = np.asarray(centre, dtype=np.float64)
    t0 = time.perf_counter()
    source = _cloud(before - centre)
    target = _cloud(after - centre)
    if voxel_m > 0:
        source = source.voxel_down_sample(voxel_m)
        target = target.voxel_down_sample(voxel_m)
    target.estimate_normals(
        o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=MAX_NN)
    )
    result = o3d.pipelines.registration.registration_icp(
        source,
        target,
        max_corr_m,
        np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(
            relative_fitness=1e-9, relative_rmse=1e-9, max_iteration=100
        ),
    )
    seconds = time.perf_counter() - t0
    transform = np.asarray(result.transformation, dtype=np.float64)
    information = o3d.pipelines.registration.get_information_matrix_from_point_clouds(
        source, target, max_corr_m, transform
    )
    return {
        # the centre is the origin of the shifted frame: T maps it to t
        "displacement": transform[:3, 3].tolist(),
        "fitness": float(result.fitness),
        "inlier_rmse": float(result.inlier_rmse),
        "seconds": seconds,
        "n_source": len(source.points),
        "n_target": len(target.points),
        "n_correspondences": len(result.correspondence_set),
        "transformation": transform.tolist(),
        "information": np.asarray(information, dtype=np.float64).tolist(),
    }


def run(in_path: str, out_path: str) -> dict:
    """Read ``in_path`` (npz), register both sides, write and return the JSON report."""
    with np.load(in_path, allow_pickle=False) as data:
        arrays = {k: np.asarray(data[k]) for k in data.files}
    options = {
        k: float(arrays[k]) if k in arrays and arrays[k].size else v for k, v in DEFAULTS.items()
    }
    before = np.asarray(arrays["before"], dtype=np.float64).reshape(-1, 3)
    after = np.asarray(arrays["after"], dtype=np.float64).reshape(-1, 3)
    side_before = np.asarray(arrays["side_before"]).reshape(-1)
    side_after = np.asarray(arrays["side_after"]).reshape(-1)
    if len(side_before) != len(before) or len(side_after) != len(after):
        raise ValueError("side_before/side_after do not match before/after")
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    report: dict = {}
    for name, sign in (("left", -1), ("right", 1)):
        report[name] = register_side(
            before[side_before == sign],
            after[side_after == sign],
            np.asarray(arrays[f"centre_{name}"], dtype=np.float64).reshape(3),
            **options,
        )
        log.info("%s: %s", name, report[name]["displacement"])
    report["relative"] = (
        np.asarray(report["right"]["displacement"]) - np.asarray(report["left"]["displacement"])
    ).tolist()
    report["open3d_version"] = o3d.__version__
    report["options"] = options
    with open(out_path, "w", encoding="utf-8") as fh:
        json.dump(report, fh, indent=1)
    return report


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    if len(argv) != 2:
        log.error("usage: python open3d_icp.py IN.npz OUT.json")
        return 2
    run(argv[0], argv[1])
    return 0


if __name__ == "__main__":
    sys.exit(main())
