"""``slipmap demo``: the main job on an embedded case (:mod:`slipmap.app.demo`)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from ..app import demo as job
from ..app.outputs import OutputPlan
from ._args import add_options, command, options_from, progress_for

log = logging.getLogger("slipmap")


@command("demo", job.SPEC.description, job.SPEC)
def _run(args: argparse.Namespace) -> int:
    opts = options_from(args, job.SPEC)
    out = Path(opts["out"])
    OutputPlan(out_dir=("out", out)).check()  # a folder we can write, before any work
    run = job.run_slip_demo if opts["job"] == "slip" else job.run_planes_demo
    with progress_for(args, "demo") as bar:
        summary = run(out, seed=opts["seed"], progress=bar if not args.quiet else None)
    for line in summary.lines():
        log.warning("%s", line) if args.quiet else log.info("%s", line)
    return 0


@_run.arguments
def _arguments(p: argparse.ArgumentParser) -> None:
    add_options(p, job.SPEC)
