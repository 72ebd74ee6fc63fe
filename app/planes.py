"""Job ``planes``: planar segmentation of one point cloud (Kusari et al. 2019, section II).

The options are declared once in :data:`SPEC`; :func:`segment` is the computation on arrays
(used by PDAL, the slip job and the demo), :func:`run` reads the file, segments it and
writes the labelled cloud and ``planes.json`` through an :class:`~.outputs.OutputPlan`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import numpy as np

from .._version import __version__
from .inputs import cloud_option, crs_option, out_dir_option, read_cloud, select_points
from .inputs import selection_options as _selection
from .job import JobResult, Progress, Timer, scaled
from .options import JobSpec, Option
from .outputs import OutputPlan
from .summaries import json_text
from .tiled import check_scale, is_tiled, run_planes_job, scale_options

log = logging.getLogger("slipmap.app")

CITATION = (
    "Kusari, Glennie, Brooks and Ericksen (2019), Precise registration of laser mapping data "
    "by planar feature extraction for deformation monitoring, IEEE TGRS 57(6), section II"
)
_SEG = "segmentation (estimated from the data when not given; the values used are logged)"


def plane_options(*, group: str = _SEG, advanced: bool = True) -> tuple:
    """The segmentation options, shared by the planes and slip jobs."""

    def num(key, type_, help_, label, **kw):
        return Option(key, type_, help_, label=label, group=group, advanced=advanced, **kw)

    return (
        num(
            "min_node_size_m",
            "float",
            "smallest octree leaf edge, metres",
            "Smallest octree node size (m)",
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
        num(
            "max_node_size_m",
            "float",
            "largest leaf edge tested, metres (default 4x the leaf)",
            "Largest octree node size (m)",
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
        num(
            "planarity_threshold_m",
            "float",
            "point-to-plane distance for the planarity test, metres (default 3x the noise)",
            "Planarity threshold (m)",
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
        num(
            "planarity_ratio",
            "float",
            "fraction of a leaf's points within the threshold for it to be planar (0-1; "
            "default from the clutter share, 0.9 on clean surfaces)",
            "Planarity ratio (0-1)",
            minimum=0,
            maximum=1,
            exclusive=True,
            metavar="R",
        ),
        num(
            "angle_threshold_deg",
            "float",
            "largest angle between normals of joined leaves, degrees",
            "Angle threshold (degrees)",
            minimum=0,
            maximum=90,
            exclusive=True,
            metavar="DEG",
        ),
        num(
            "distance_threshold_m",
            "float",
            "largest centroid-to-plane distance of joined leaves, metres (default the "
            "planarity threshold)",
            "Distance threshold (m)",
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
        num(
            "min_plane_points",
            "int",
            "smallest number of points of a reported plane (default 3 leaves, at least 30)",
            "Smallest plane (points)",
            minimum=1,
            cli="--min-points",
            qgis="MIN_POINTS",
            metavar="N",
        ),
        num(
            "min_leaf_points",
            "int",
            "smallest number of points in a leaf for a plane fit",
            "Smallest leaf for a plane fit (points)",
            minimum=3,
            metavar="N",
            unset_text="10",
        ),
        Option(
            "backend",
            "choice",
            "numpy (the reference) or OpenCL through PyOpenCL; auto uses OpenCL when a "
            "device is available (the labels are the same)",
            label="Backend",
            default="numpy",
            choices=("numpy", "opencl", "auto"),
            group=group,
            advanced=True,
        ),
    )


PLANE_KEYS = (
    "min_node_size_m",
    "max_node_size_m",
    "planarity_threshold_m",
    "planarity_ratio",
    "angle_threshold_deg",
    "distance_threshold_m",
    "min_plane_points",
    "min_leaf_points",
    "backend",
)

SPEC = JobSpec(
    name="planes",
    title="Planar segmentation",
    description=(
        "Finds the planar surfaces of a point cloud (octree leaves that pass a planarity "
        "test, grown into regions) and labels every point with the id of its plane "
        "(PlaneId, -1 = none)."
    ),
    options=(
        cloud_option(
            "input",
            "LAS/LAZ point cloud in a projected CRS (metres); or tiles: a folder, a glob "
            "(quoted) or files separated by commas (processed tile by tile; labelled per tile)",
            "Input point cloud",
        ),
        out_dir_option(),
        crs_option(),
        *_selection(ground_default=True),
        *plane_options(),
        *scale_options(),
        Option(
            "labelled_cloud",
            "path",
            "labelled copy of the input with PlaneId",
            label="Labelled point cloud (PlaneId)",
            role="output",
            cli=None,
            qgis="OUTPUT",
            pdal=None,
            file_filter="LAS (*.las);;LAZ (*.laz)",
        ),
        Option(
            "summary",
            "path",
            "planes summary (JSON): one record per plane",
            label="Planes summary",
            role="output",
            cli=None,
            pdal=None,
            file_filter="JSON (*.json)",
        ),
    ),
    check=check_scale,
    citation=CITATION,
)


def core_kwargs(opts: Mapping[str, Any]) -> Dict[str, Any]:
    """``segment_planes`` keywords of the options that are set."""
    return {k: opts[k] for k in PLANE_KEYS if opts.get(k) is not None}


def segment(points: np.ndarray, opts: Mapping[str, Any], *, progress: Optional[Progress] = None):
    """Segment ``points`` ``(N, 3)`` float64 (map units) with the job's options.

    Returns the :class:`~slipmap.core.planes.PlaneSet`.
    """
    from ..core.planes import segment_planes

    return segment_planes(points, progress=progress, **core_kwargs(opts))


def default_names(opts: Mapping[str, Any]) -> Dict[str, str]:
    """File names of the outputs in an output folder (the CLI's ``--out``)."""
    src = Path(str(opts["input"]))
    suffix = ".laz" if src.suffix.lower() == ".laz" else ".las"
    return {"summary": "planes.json", "labelled_cloud": f"{src.stem}_planes{suffix}"}


def run(
    opts: Mapping[str, Any],
    outputs: Mapping[str, Any],
    *,
    cloud=None,
    progress: Optional[Progress] = None,
) -> JobResult:
    """Read, select, segment and write.

    Parameters
    ----------
    opts
        :data:`SPEC`'s options, parsed (:meth:`JobSpec.parse`).
    outputs
        ``{"labelled_cloud": path or None, "summary": path or None}``; or ``{"out": folder}``
        for both under :func:`default_names`.
    cloud
        An already-read :class:`~slipmap.core.io.las.PointCloud` (the demo); ``opts["input"]``
        then only names it.
    """
    if cloud is None and is_tiled(opts, "input"):  # tiles, or Dask: app/tiled.py
        return run_planes_job(opts, outputs, plane_options=core_kwargs(opts), progress=progress)
    plan = OutputPlan.for_outputs(
        inputs={"input": opts.get("input")}, outputs=outputs, default_names=default_names(opts)
    )
    plan.check()
    with plan:
        if cloud is None:
            cloud = read_cloud(opts["input"], key="input", crs=opts.get("crs"))
        sel = select_points(
            cloud,
            classes=opts.get("classes"),
            exclude_classes=opts.get("exclude_classes"),
            ground_default=True,
        )
        log.info("%d of %d points selected", sel.size, len(cloud))
        with Timer() as t:
            planes = segment(cloud.xyz[sel], opts, progress=scaled(progress, 0.0, 0.9))
        labels = np.full(len(cloud), -1, dtype=np.int32)
        labels[sel] = planes.labels
        params = planes.parameters.to_dict()
        for key, value in params.items():
            log.info("  %-24s %s", key, value)
        n_lab = int(np.count_nonzero(labels >= 0))
        summary = {
            "planes": planes.to_records(),
            "n_points": int(len(cloud)),
            "n_selected": int(sel.size),
            "n_labelled": n_lab,
            "parameters": params,
            "runtime_s": round(t.seconds, 4),
            "input": str(cloud.source) if cloud.source else None,
            "crs": cloud.crs.to_wkt() if cloud.crs is not None else None,
            "slipmap_version": __version__,
        }
        if plan.wants("summary"):
            plan.file("summary").write_text(json_text(summary), encoding="utf-8")
        if plan.wants("labelled_cloud"):
            from ..core.io.las import write_las

            write_las(plan.file("labelled_cloud"), cloud, extra_dims={"PlaneId": labels})
        if progress is not None:
            progress(1.0, "written")
    lines = [
        f"{len(planes)} planes, {n_lab} of {len(cloud)} points labelled "
        f"({100.0 * n_lab / max(1, len(cloud)):.1f} %), {t.seconds:.2f} s"
    ]
    written = {k: plan.final(k) for k in ("summary", "labelled_cloud") if plan.wants(k)}
    return JobResult(summary, lines, written, data=(planes, labels))
