"""Job ``accuracy``: per-point accuracy (SigmaX/Y/Z, optionally the covariance) into a LAS copy.

The options are declared once in :data:`SPEC` (the point-accuracy options come from
:func:`.pointaccuracy.pa_options`, shared with the slip job); :func:`dimensions` is the
computation on a point cloud (used by PDAL on its view); :func:`run` reads the file, computes
and writes the copy through an :class:`~.outputs.OutputPlan`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import numpy as np

from .inputs import cloud_option, crs_option, read_cloud
from .job import JobResult, Progress
from .options import JobSpec, Option, OptionError
from .outputs import OutputPlan
from .pointaccuracy import check_options as check_pa
from .pointaccuracy import covariance_matrices, pa_options, settings_from_options

log = logging.getLogger("slipmap.app")

CITATION = (
    "Kusari, Glennie, Brooks and Ericksen (2019), IEEE TGRS 57(6), section II.E; Glennie "
    "(2007) for the propagated model; Schaer et al. (2007) for the beam-footprint term"
)
SIGMAS = ("SigmaX", "SigmaY", "SigmaZ")
COVS = ("CovXX", "CovYY", "CovZZ", "CovXY", "CovXZ", "CovYZ")
LAS_SUFFIXES = (".las", ".laz")


def _check(opts: Mapping[str, Any]) -> None:
    out = opts.get("output_cloud")
    is_folder = out is not None and Path(str(out)).is_dir()  # the OutputPlan says so
    if out is not None and not is_folder and Path(str(out)).suffix.lower() not in LAS_SUFFIXES:
        raise OptionError(
            "output_cloud",
            f"{str(out)!r} does not end in .las or .laz; the copy is a LAS/LAZ file: give a "
            "name ending in .las (or .laz for compressed)",
        )
    check_pa(opts)


SPEC = JobSpec(
    name="accuracy",
    title="Point accuracy",
    description=(
        "Writes a copy of a point cloud with the per-point accuracy dimensions SigmaX, SigmaY, "
        "SigmaZ (m) and, optionally, the full covariance CovXX, CovYY, CovZZ, CovXY, CovXZ, "
        "CovYZ (m²): the a-priori point accuracy that weights the slip job's planar "
        "registration."
    ),
    options=(
        cloud_option(
            "input", "LAS/LAZ point cloud in a projected CRS (metres)", "Input point cloud"
        ),
        Option(
            "output_cloud",
            "path",
            "output LAS/LAZ copy with SigmaX/SigmaY/SigmaZ (the input is not modified)",
            label="Point cloud with SigmaX/Y/Z",
            required=True,
            role="output",
            cli="--out",
            qgis=None,  # a file destination of the algorithm
            pdal=None,  # PDAL writes the view's new dimensions
            metavar="FILE.las",
            file_filter="LAS (*.las);;LAZ (*.laz)",
        ),
        crs_option(
            "CRS of the input when the file lacks one or declares a wrong one (e.g. "
            "EPSG:32611): it replaces the file's CRS (nothing is reprojected); it also places a "
            "geodetic (SBET) trajectory"
        ),
        Option(
            "full_covariance",
            "bool",
            "also write CovXX CovYY CovZZ CovXY CovXZ CovYZ (m²): the propagated model has "
            "correlated axes that SigmaX/Y/Z alone lose",
            label="Full covariance (CovXX..CovYZ, m²)",
            default=False,
        ),
        *pa_options(),
    ),
    check=_check,
    citation=CITATION,
)


def outputs_of(opts: Mapping[str, Any]) -> tuple:
    """Names of the dimensions written with these options."""
    return SIGMAS + (COVS if opts.get("full_covariance") else ())


def dimensions(cloud, opts: Mapping[str, Any]) -> Dict[str, np.ndarray]:
    """The accuracy dimensions of ``cloud`` under the job's options.

    Parameters
    ----------
    cloud
        :class:`~slipmap.core.io.las.PointCloud` (``xyz`` ``(N, 3)``; the propagated model
        reads ``GpsTime``, ``ScanAngle`` and the CRS).
    opts
        :data:`SPEC`'s options, parsed.

    Returns
    -------
    dict
        ``{"SigmaX": (N,), "SigmaY": (N,), "SigmaZ": (N,)}`` in metres, plus the six
        covariance entries ``Cov..`` (m²) with ``full_covariance``.
    """
    from ..core.accuracy import covariance_to_sigmas, covariance_to_six

    settings = settings_from_options(opts)["before"]
    cov = covariance_matrices(
        cloud, None, settings, config_key="pa_config" if opts.get("pa_config") else None
    )
    sig = covariance_to_sigmas(cov)
    out = {name: sig[:, k] for k, name in enumerate(SIGMAS)}
    if opts.get("full_covariance"):
        six = covariance_to_six(cov)
        out.update({name: six[:, k] for k, name in enumerate(COVS)})
    return out


def model_of(opts: Mapping[str, Any]) -> str:
    """The point-accuracy model the options choose."""
    return settings_from_options(opts)["before"]["model"]


def _input_files(opts: Mapping[str, Any]) -> Dict[str, Any]:
    files = {k: opts.get(k) for k in ("input", "trajectory", "trajectory_accuracy", "pa_config")}
    scanner = opts.get("scanner")
    if scanner is not None and Path(str(scanner)).suffix:  # a JSON specification file
        files["scanner"] = scanner
    return files


def run(
    opts: Mapping[str, Any], outputs: Mapping[str, Any], *, progress: Optional[Progress] = None
) -> JobResult:
    """Read, compute the per-point accuracy, write the LAS/LAZ copy.

    Parameters
    ----------
    opts
        :data:`SPEC`'s options, parsed (:meth:`JobSpec.parse`).
    outputs
        ``{"output_cloud": path}`` (the CLI passes ``opts["output_cloud"]``).
    """
    from ..core.io.las import write_las

    out = outputs.get("output_cloud")
    _check({**opts, "output_cloud": out})
    plan = OutputPlan.for_outputs(
        inputs=_input_files(opts), outputs={"output_cloud": out}, default_names={}
    )
    plan.check()
    with plan:
        cloud = read_cloud(opts["input"], key="input", crs=opts.get("crs"))
        model = model_of(opts)
        if progress is not None:
            progress(0.1, f"point accuracy ({model})")
        extra = dimensions(cloud, opts)
        if progress is not None:
            progress(0.6, "writing")
        write_las(plan.file("output_cloud"), cloud, extra_dims=extra, inputs=[opts["input"]])
        if progress is not None:
            progress(1.0, "written")
    med = np.median(np.column_stack([extra[k] for k in SIGMAS]), axis=0)
    summary = {
        "model": model,
        "n_points": int(len(cloud)),
        "median_sigma_m": {k: float(v) for k, v in zip("xyz", med)},
        "dimensions": list(extra),
        "input": str(opts["input"]),
        "output": str(plan.final("output_cloud")),
    }
    lines = [
        f"point accuracy ({model}): median sigma x {med[0]:.4f}, y {med[1]:.4f}, z {med[2]:.4f} m"
    ]
    return JobResult(summary, lines, {"output_cloud": plan.final("output_cloud")}, data=extra)
