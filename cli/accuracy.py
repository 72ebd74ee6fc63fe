"""``slipmap accuracy``: the accuracy job (:mod:`slipmap.app.accuracy`) on the command line."""

from __future__ import annotations

import argparse
import logging

from ..app import accuracy as job
from ._args import add_options, command, options_from, progress_for

log = logging.getLogger("slipmap")


@command(
    "accuracy",
    "per-point accuracy (SigmaX/Y/Z, optionally full covariance) into a LAS copy",
    job.SPEC,
)
def _run(args: argparse.Namespace) -> int:
    opts = options_from(args, job.SPEC)
    with progress_for(args, "accuracy") as bar:
        result = job.run(opts, {"output_cloud": opts["output_cloud"]}, progress=bar)
    for line in result.lines:
        log.info("%s", line)
    log.info("wrote %s", result.files["output_cloud"])
    return 0


@_run.arguments
def _arguments(p: argparse.ArgumentParser) -> None:
    add_options(p, job.SPEC)
