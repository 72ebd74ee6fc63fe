"""``slipmap piv``, ``icp``, ``dem-diff``, ``strain``, ``synth-lobe``: the displacement-field
jobs (:mod:`slipmap.app.piv`, :mod:`~slipmap.app.icp`, :mod:`~slipmap.app.dem_diff`,
:mod:`~slipmap.app.strain`, :mod:`~slipmap.app.synthetic`) on the command line."""

from __future__ import annotations

import argparse
import logging

from ..app import dem_diff, icp, piv, strain, synthetic
from ._args import add_options, command, run_job

log = logging.getLogger("slipmap")


def _arguments(job):
    def add(p: argparse.ArgumentParser) -> None:
        add_options(p, job.SPEC)
        p.add_argument("--no-progress", action="store_true", help="no progress bar")

    return add


def _register(name: str, help_text: str, job) -> None:
    def run(args: argparse.Namespace) -> int:
        run_job(args, job, name)
        return 0

    run = command(name, help_text, job.SPEC)(run)
    run.arguments(_arguments(job))


_register("piv", "3D displacement field by PIV on gridded elevation (Aryal et al., 3.2.1)", piv)
_register("icp", "3D displacement field by windowed point-to-plane ICP (Aryal et al., 3.2.2)", icp)
_register("dem-diff", "vertical change by DEM differencing (the simple baseline)", dem_diff)
_register("strain", "horizontal strain from a displacement field (PIV/ICP CSV or GeoTIFFs)", strain)
_register(
    "synth-lobe", "inject a known landslide lobe into a real cloud (validation pair)", synthetic
)
