"""Job ``synth-lobe``: inject a known landslide lobe into a real cloud (a validation pair;
Aryal et al., section 3.2.3).

The cloud is split at random into two disjoint epochs and the second is moved by a smooth
lobe (:func:`slipmap.core.synthetic.make_lobe_pair`); the epochs, the truth on a regular grid
(``truth.csv``, ``truth_interior.csv``: control points for ``piv``/``icp --control``) and
``lobe.json`` are written.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import numpy as np

from .._version import __version__
from .inputs import cloud_option, out_dir_option, read_cloud
from .job import JobResult, Progress
from .options import JobSpec, Option, OptionError
from .outputs import OutputPlan
from .resources import check_grid_memory
from .summaries import json_text

log = logging.getLogger("slipmap.app")

#: memory per truth grid node (bytes): the meshgrid (16), positions (16), the field (24),
#: the interior copies (40) and the CSV text with its Python floats (5 columns x ~60)
TRUTH_BYTES_PER_NODE = 400
_GROUP = "lobe"


def _opt(key, type_, help_, label, **kw):
    return Option(key, type_, help_, label=label, group=_GROUP, qgis=None, pdal=None, **kw)


def _check(opts: Mapping[str, Any]) -> None:
    r = opts.get("radius_m")
    if r is not None and len(r) > 2:
        raise OptionError("radius_m", f"takes one radius or two (RX RY), got {len(r)}")


SPEC = JobSpec(
    name="synth-lobe",
    title="Synthetic landslide lobe",
    description=(
        "Splits a real point cloud at random into two epochs and moves the second by a smooth "
        "landslide lobe of known displacement, with the truth as control points: a validation "
        "pair for the field jobs."
    ),
    options=(
        cloud_option("input", "real LAS/LAZ cloud to split and deform", "Input point cloud"),
        out_dir_option(),
        _opt("max_dx_m", "float", "peak east displacement, metres", "Peak dx (m)", default=0.0),
        _opt("max_dy_m", "float", "peak north displacement, metres", "Peak dy (m)", default=-1.0),
        _opt(
            "max_dz_m", "float", "peak vertical displacement, metres", "Peak dz (m)", default=-0.4
        ),
        _opt(
            "centre_xy",
            "floats",
            "lobe centre x y (map units; default the centre of the cloud's bounding box)",
            "Lobe centre",
            nargs=2,
            cli="--centre",
            metavar=("X", "Y"),
            unset_text="the cloud's centre",
        ),
        _opt(
            "radius_m",
            "floats",
            "lobe radius, metres, or two radii RX RY (default a third of the smaller extent)",
            "Lobe radius (m)",
            nargs="+",
            minimum=0,
            exclusive=True,
            metavar="R",
            unset_text="a third of the smaller extent",
        ),
        _opt(
            "azimuth_deg",
            "float",
            "azimuth of the RY axis, degrees clockwise from north",
            "Azimuth (degrees)",
            default=0.0,
        ),
        _opt("seed", "int", "seed of the random split", "Seed", default=0, minimum=0),
        _opt(
            "truth_spacing_m",
            "float",
            "spacing of the truth.csv control grid, metres",
            "Truth grid spacing (m)",
            default=1.0,
            minimum=0,
            exclusive=True,
            metavar="M",
        ),
    ),
    check=_check,
)


def default_names(opts: Mapping[str, Any]) -> Dict[str, str]:
    suffix = Path(str(opts["input"])).suffix.lower()
    ext = suffix if suffix in (".las", ".laz") else ".laz"
    return {
        "before": f"before{ext}",
        "after": f"after{ext}",
        "truth": "truth.csv",
        "truth_interior": "truth_interior.csv",
        "summary": "lobe.json",
    }


def run(
    opts: Mapping[str, Any],
    outputs: Mapping[str, Any],
    *,
    progress: Optional[Progress] = None,
) -> JobResult:
    """Read, split, deform and write the pair, the truth and ``lobe.json``."""
    from ..core.io.las import write_las
    from ..core.io.table import write_csv_columns
    from ..core.synthetic import make_lobe_pair

    names = default_names(opts)
    plan = OutputPlan.for_outputs(
        inputs={"input": opts.get("input")}, outputs=outputs, default_names=names
    )
    plan.check()
    with plan:
        cloud = read_cloud(opts["input"], key="input")
        lo, hi = cloud.xyz[:, :2].min(axis=0), cloud.xyz[:, :2].max(axis=0)
        step = opts["truth_spacing_m"]
        n_nodes = (np.floor((hi - lo) / step) + 1).prod()
        check_grid_memory(
            "truth_spacing_m", n_nodes, bytes_per_cell=TRUTH_BYTES_PER_NODE, what="truth grid"
        )
        r = opts.get("radius_m")
        pair = make_lobe_pair(
            cloud.xyz,
            max_dx_m=opts["max_dx_m"],
            max_dy_m=opts["max_dy_m"],
            max_dz_m=opts["max_dz_m"],
            centre_xy=opts.get("centre_xy"),
            radius_m=None if not r else (r[0] if len(r) == 1 else tuple(r[:2])),
            azimuth_deg=opts["azimuth_deg"],
            seed=opts["seed"],
        )
        if progress is not None:
            progress(0.5, "writing the epochs")
        src = [opts["input"]]
        if plan.wants("before"):
            write_las(plan.file("before"), cloud.subset(pair.before_index), inputs=src)
        if plan.wants("after"):
            write_las(
                plan.file("after"), cloud.subset(pair.after_index), xyz=pair.after, inputs=src
            )
        # the truth as control points on a regular grid covering the cloud
        gx = np.arange(lo[0] + step / 2, hi[0], step)
        gy = np.arange(lo[1] + step / 2, hi[1], step)
        xx, yy = np.meshgrid(gx, gy)
        xy = np.column_stack([xx.ravel(), yy.ravel()])
        d = pair.field(xy)
        interior = pair.field.interior_mask(xy)
        for key, keep in (("truth", slice(None)), ("truth_interior", interior)):
            if plan.wants(key):
                write_csv_columns(
                    plan.file(key),
                    {
                        "x": xy[keep, 0],
                        "y": xy[keep, 1],
                        "dx": d[keep, 0],
                        "dy": d[keep, 1],
                        "dz": d[keep, 2],
                    },
                )
        f = pair.field
        summary = {
            "command": "synth-lobe",
            "input": str(opts["input"]),
            "centre_xy": list(map(float, f.centre_xy)),
            "radius_x_m": float(f.radius_x_m),
            "radius_y_m": float(f.radius_y_m),
            "azimuth_deg": float(f.azimuth_deg),
            "max_d_m": list(map(float, f.max_d_m)),
            "profile": "d = max_d (1 - r^2)^2 for r < 1 (elliptical radius), 0 outside",
            "seed": opts["seed"],
            "n_before": int(len(pair.before)),
            "n_after": int(len(pair.after)),
            "files": [
                plan.final(k).name
                for k in ("before", "after", "truth", "truth_interior")
                if plan.wants(k)
            ],
            "slipmap_version": __version__,
        }
        if plan.wants("summary"):
            plan.file("summary").write_text(json_text(summary), encoding="utf-8")
        if progress is not None:
            progress(1.0, "written")
    lines = [
        f"lobe at ({f.centre_xy[0]:.2f}, {f.centre_xy[1]:.2f}), radii {f.radius_x_m:.1f} x "
        f"{f.radius_y_m:.1f} m, max d {list(map(float, f.max_d_m))} m: {len(pair.before)} "
        f"before / {len(pair.after)} after points"
    ]
    files = {k: plan.final(k) for k in names if plan.wants(k)}
    return JobResult(summary, lines, files, data=pair)
