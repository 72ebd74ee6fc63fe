"""``slipmap displacement``: the slip job (:mod:`slipmap.app.slip`) on the command line."""

from __future__ import annotations

import argparse
import logging

from ..app import slip as job
from ..app.stochasticmodel import fixed_components_or_error
from ._args import add_options, command, run_job

log = logging.getLogger("slipmap")


@command(
    "displacement", "fault slip between two epochs by planar registration on each side", job.SPEC
)
def _run(args: argparse.Namespace) -> int:
    fixed = ",".join(args.fixed_components) if args.fixed_components else None
    run_job(args, job, "displacement", overrides={"fixed_components": fixed})
    return 0


def _fixed_component(text: str) -> str:
    """argparse type of ``--fixed-component NAME=SIGMA_M`` (repeatable): checked at once."""
    try:
        fixed_components_or_error(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


@_run.arguments
def _arguments(p: argparse.ArgumentParser) -> None:
    add_options(p, job.SPEC, skip=("fixed_components",))
    opt = job.SPEC["fixed_components"]
    p.add_argument(
        opt.name_in("cli"),
        dest=opt.key,
        type=_fixed_component,
        action="append",
        metavar=opt.metavar,
        help=opt.help + " (repeatable)",
    )
