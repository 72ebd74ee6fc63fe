"""``slipmap accuracy``: the accuracy job (:mod:`slipmap.app.accuracy`) on the command line."""

from __future__ import annotations

import argparse
import logging

from ..app import accuracy as job
from ._args import add_options, command, run_job

log = logging.getLogger("slipmap")


@command(
    "accuracy",
    "per-point accuracy (SigmaX/Y/Z, optionally full covariance) into a LAS copy",
    job.SPEC,
)
def _run(args: argparse.Namespace) -> int:
    run_job(args, job, "accuracy", lambda o: {"output_cloud": o["output_cloud"]})
    return 0


@_run.arguments
def _arguments(p: argparse.ArgumentParser) -> None:
    add_options(p, job.SPEC)
