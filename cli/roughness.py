"""``slipmap roughness``: the roughness job (:mod:`slipmap.app.roughness`) on the command line."""

from __future__ import annotations

import argparse
import logging

from ..app import roughness as job
from ._args import _parser_type, add_options, command, run_job

log = logging.getLogger("slipmap")


@command("roughness", "surface roughness by ODR on a 3D grid, with the OLS comparison", job.SPEC)
def _run(args: argparse.Namespace) -> int:
    outputs = lambda o: {"out": o["out"], "points_out": o["points_out"]}  # noqa: E731
    run_job(args, job, "roughness", outputs, lines_level=logging.DEBUG)
    return 0


@_run.arguments
def _arguments(p: argparse.ArgumentParser) -> None:
    cell = job.SPEC["cell_sizes_m"]
    p.add_argument(  # repeatable as well as a list: --cell 1 --cell 0.5 = --cell 1 0.5
        cell.name_in("cli"),
        dest=cell.key,
        action="extend",
        nargs="+",
        type=_parser_type(cell, cell.name_in("cli")),
        metavar=cell.metavar,
        help=f"{cell.help} (default: {cell.default_text()})",
    )
    add_options(p, job.SPEC, skip=(cell.key,))
