"""``slipmap planes``: the planes job (:mod:`slipmap.app.planes`) on the command line."""

from __future__ import annotations

import argparse
import logging

from ..app import planes as job
from ._args import add_options, command, run_job

log = logging.getLogger("slipmap")


@command("planes", "planar segmentation (octree + region growing) of one point cloud", job.SPEC)
def _run(args: argparse.Namespace) -> int:
    run_job(args, job, "planes")
    return 0


@_run.arguments
def _arguments(p: argparse.ArgumentParser) -> None:
    add_options(p, job.SPEC)
