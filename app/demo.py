"""``slipmap demo``: the main job on an embedded case, compared with the truth.

The default job (:func:`run_slip_demo`) writes two synthetic MLS epochs across a fault, with
correlated survey error (trajectory drift), as LAZ files and runs the slip job
(:func:`slipmap.app.slip.run`) on them; ``--job planes`` (:func:`run_planes_demo`) runs the
planes job (:func:`slipmap.app.planes.run`) on a seeded synthetic MLS-like scene (buildings
with flat and gable roofs, ground, trees) placed at UTM coordinates, written as a LAZ file and
read back as a user's file would be. Both call the jobs directly: a failure is an exception
with its message, not an exit code.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np

from ..core.progress import ProgressCallback, scaled
from .options import JobSpec, Option

log = logging.getLogger("slipmap.demo")

DEMO_ORIGIN = (498_000.0, 4_234_000.0, 20.0)  # UTM zone 10N, near the Napa study area
DEMO_EPSG = 32610
DEMO_DRIFT_M = 0.003  # σ of the MLS trajectory drift of each epoch (correlated survey error)

SPEC = JobSpec(
    name="demo",
    title="Demo",
    description="run the main job (fault slip) on an embedded case and compare with the truth",
    options=(
        Option(
            "out",
            "path",
            "output folder (created when missing)",
            label="Output folder",
            default="demo_output",
            role="output",
            metavar="DIR",
            qgis=None,
            pdal=None,
        ),
        Option("seed", "int", "seed of the synthetic scene", default=2019, minimum=0),
        Option(
            "job",
            "choice",
            "slip: two epochs across a fault; planes: segmentation of one scene",
            default="slip",
            choices=("slip", "planes"),
        ),
    ),
)


@dataclass
class DemoSummary:
    out_dir: Path
    n_points: int
    n_planes: int
    recall: float
    precision: float
    purity: float
    n_merged: int
    n_surfaces: int
    runtime_s: float
    files: List[Path] = field(default_factory=list)

    def lines(self) -> List[str]:
        return [
            f"SlipMap demo: planar segmentation of a synthetic MLS scene ({self.n_points} points)",
            f"  planes found            {self.n_planes}",
            f"  true surfaces recovered {self.recall:.1%} of {self.n_surfaces} "
            "(>= 200 points, >= 70 % under one label)",
            f"  labelled points planar  {self.precision:.2%}   purity {self.purity:.2%}   "
            f"merged surfaces {self.n_merged}",
            f"  segmentation time       {self.runtime_s:.2f} s",
            "  outputs: " + ", ".join(str(f) for f in self.files),
        ]


def run_planes_demo(
    out_dir: Path, *, seed: int = 2019, progress: Optional[ProgressCallback] = None
) -> DemoSummary:
    """Write a synthetic scene, segment it with the planes job and score it against truth."""
    import pyproj

    from ..core.evaluation import score_segmentation
    from ..core.io.atomic import ensure_output_dir
    from ..core.io.las import PointCloud, read_las, write_las
    from ..core.synthetic import make_scene
    from . import planes

    out_dir = ensure_output_dir(out_dir)
    scene = make_scene("mls", seed=seed, origin=DEMO_ORIGIN)
    cloud = PointCloud(
        xyz=scene.points,
        attributes={"Classification": scene.classification},
        crs=pyproj.CRS.from_epsg(DEMO_EPSG),
    )
    scene_path = out_dir / "demo_scene.laz"
    write_las(scene_path, cloud, extra_dims={"TruthSurface": scene.labels.astype(np.int32)})
    log.info("wrote the synthetic scene to %s", scene_path)

    # keep ground ("none" excluded): it is a true plane of the scene
    opts = planes.SPEC.parse(
        {"input": str(scene_path), "out": str(out_dir), "exclude_classes": "none"}
    )
    read = read_las(scene_path)
    result = planes.run(opts, {"out": out_dir}, cloud=read, progress=scaled(progress, 0, 1))
    for line in result.lines:
        log.info("%s", line)
    found, labels = result.data
    payload = result.summary
    truth = read.attributes["TruthSurface"]
    scores = score_segmentation(truth, labels)
    return DemoSummary(
        out_dir=out_dir,
        n_points=len(read),
        n_planes=len(found),
        recall=scores.recall,
        precision=scores.precision,
        purity=scores.purity,
        n_merged=scores.n_merged,
        n_surfaces=scores.n_surfaces,
        runtime_s=payload["runtime_s"],
        files=[scene_path, out_dir / "planes.json", out_dir / "demo_scene_planes.laz"],
    )


@dataclass
class SlipDemoSummary:
    out_dir: Path
    truth_right_lateral_m: float
    right_lateral_m: float
    sigma_m: float
    vertical_m: float
    sigma_vertical_m: float
    n_planes: dict
    runtime_s: float
    files: List[Path] = field(default_factory=list)
    stochastic_model: str = "white"
    sigma_white_m: Optional[float] = None
    sigma_vertical_white_m: Optional[float] = None
    survey_error_m: float = 0.0
    units: dict = field(default_factory=dict)
    side_lines: List[str] = field(default_factory=list)

    def lines(self) -> List[str]:
        err = self.right_lateral_m - self.truth_right_lateral_m
        white = (
            f"   (white noise only ± {1000 * self.sigma_white_m:.2f} mm: "
            f"{abs(err) / self.sigma_white_m:.1f}σ)"
            if self.sigma_white_m
            else ""
        )
        white_v = (
            f"   (white noise only ± {1000 * self.sigma_vertical_white_m:.2f} mm)"
            if self.sigma_vertical_white_m
            else ""
        )
        drift = (
            f", {1000 * self.survey_error_m:g} mm MLS trajectory drift"
            if self.survey_error_m
            else ""
        )
        units = ", ".join(
            f"{e} {u.get('n_units', 0)} from {u.get('source', 'none')}"
            for e, u in self.units.items()
            if isinstance(u, dict)
        )
        out = [
            "SlipMap demo: fault slip between two synthetic MLS epochs (independent samplings, "
            f"2 cm noise{drift}) across a north-striking fault",
            f"  true right-lateral slip      {1000 * self.truth_right_lateral_m:8.2f} mm",
            f"  recovered right-lateral slip {1000 * self.right_lateral_m:8.2f} mm "
            f"± {1000 * self.sigma_m:.2f} mm (1σ, {self.stochastic_model} model)   "
            f"error {1000 * err:+.2f} mm = {abs(err) / self.sigma_m:.1f}σ{white}",
            f"  vertical (right − left)      {1000 * self.vertical_m:8.2f} mm "
            f"± {1000 * self.sigma_vertical_m:.2f} mm (true 0){white_v}",
            f"  matched planes               left {self.n_planes['left']}, "
            f"right {self.n_planes['right']}",
        ]
        if units:
            out.append(f"  acquisition units (passes)   {units}")
        if self.side_lines:
            out.append("  variance components (σ of one point, then of the plane-level errors):")
            out += [f"    {line}" for line in self.side_lines]
        out += [
            f"  runtime                      {self.runtime_s:.1f} s",
            "  outputs: " + ", ".join(str(f) for f in self.files),
        ]
        return out


def run_slip_demo(
    out_dir: Path, *, seed: int = 2019, progress: Optional[ProgressCallback] = None
) -> SlipDemoSummary:
    """Two epochs with 18.1 mm of dextral slip (the study's NLOD value), through the slip job:
    LAZ files and a fault trace in WGS 84 (reprojected on reading).

    Each epoch carries 3 mm of MLS trajectory drift (correlated along the drive path, an
    independent draw per epoch), so the recovered slip is off by a few millimetres: the
    full stochastic model's σ covers that, the white-noise σ beside it does not. The LAZ
    files carry PointSourceId (the pass) and GpsTime, which the units option (auto) reads."""
    import json

    import pyproj

    from ..core.io.atomic import ensure_output_dir, write_text_atomic
    from ..core.io.las import PointCloud, write_las
    from ..core.synthetic import SurveyError, make_fault_pair
    from . import slip
    from .summaries import side_component_line

    out_dir = ensure_output_dir(out_dir)
    truth = 0.0181
    drift = SurveyError(kind="mls", level_m=DEMO_DRIFT_M)
    pair = make_fault_pair(
        "mls",
        seed=seed,
        origin=DEMO_ORIGIN,
        right_offset_m=(0.0, -truth, 0.0),
        n_buildings=8,
        extent_m=120.0,
        error_before=drift,
        error_after=drift,
    )
    crs = pyproj.CRS.from_epsg(DEMO_EPSG)
    paths = []
    for name, scene, source, gps in (
        ("before", pair.before, pair.source_before, pair.gps_time_before),
        ("after", pair.after, pair.source_after, pair.gps_time_after),
    ):
        p = out_dir / f"demo_{name}.laz"
        # PointSourceId = the MLS pass: the slip job's units option (auto) reads the units
        attributes = {"Classification": scene.classification}
        if source is not None:
            attributes["PointSourceId"] = source
            attributes["GpsTime"] = gps
        write_las(p, PointCloud(xyz=scene.points, attributes=attributes, crs=crs))
        paths.append(p)
    to_ll = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = to_ll.transform(pair.trace_xy[:, 0], pair.trace_xy[:, 1])
    fault = out_dir / "demo_fault.geojson"
    geo = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"name": "synthetic fault"},
                "geometry": {
                    "type": "LineString",
                    "coordinates": [[a, b] for a, b in zip(lon, lat)],
                },
            }
        ],
    }
    write_text_atomic(fault, json.dumps(geo))
    opts = slip.SPEC.parse(
        {
            "before": str(paths[0]),
            "after": str(paths[1]),
            "fault": str(fault),
            "out": str(out_dir),
            "sigma_m": 0.02,
        }
    )
    result = slip.run(opts, {"out": out_dir}, progress=progress)
    for line in result.lines:
        log.info("%s", line)
    log.info("wrote %s", ", ".join(p.name for p in result.files.values()))
    summary = result.summary
    rel = summary["relative"]
    files = [paths[0], paths[1], fault, out_dir / "displacement.json"]
    files += [out_dir / f for f in ("displacement.gpkg", "report.html") if (out_dir / f).exists()]
    return SlipDemoSummary(
        out_dir=out_dir,
        truth_right_lateral_m=truth,
        right_lateral_m=rel["right_lateral_slip"],
        sigma_m=rel["sigma_right_lateral"],
        vertical_m=rel["dz"],
        sigma_vertical_m=rel["sigma_dz"],
        n_planes={s: summary[s]["n_planes"] for s in ("left", "right")},
        runtime_s=summary["runtime_s"],
        files=files,
        stochastic_model=summary["parameters"].get("stochastic_model", "white"),
        sigma_white_m=rel.get("sigma_right_lateral_white"),
        sigma_vertical_white_m=rel.get("sigma_dz_white"),
        survey_error_m=DEMO_DRIFT_M,
        units={
            e: u
            for e, u in summary["parameters"].get("acquisition_unit_sources", {}).items()
            if e in ("before", "after")
        },
        side_lines=[
            line
            for line in (side_component_line(s, summary[s]) for s in ("left", "right"))
            if line is not None
        ],
    )
