"""``slipmap planes``: the planes job (:mod:`slipmap.app.planes`) on the command line."""

from __future__ import annotations

import argparse
import logging

from ..app import planes as job
from ._args import add_options, command, options_from, progress_for

log = logging.getLogger("slipmap")


@command("planes", "planar segmentation (octree + region growing) of one point cloud", job.SPEC)
def _run(args: argparse.Namespace) -> int:
    opts = options_from(args, job.SPEC)
    with progress_for(args, "planes") as bar:
        result = job.run(opts, {"out": opts["out"]}, progress=bar)
    for line in result.lines:
        log.info("%s", line)
    log.info("wrote %s", ", ".join(str(p) for p in result.files.values()))
    return 0


@_run.arguments
def _arguments(p: argparse.ArgumentParser) -> None:
    add_options(p, job.SPEC)
