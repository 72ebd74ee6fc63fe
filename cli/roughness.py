"""``slipmap roughness``: the roughness job (:mod:`slipmap.app.roughness`) on the command line."""

from __future__ import annotations

import argparse
import logging

from ..app import roughness as job
from ._args import _parser_type, add_options, command, options_from, progress_for

log = logging.getLogger("slipmap")


@command("roughness", "surface roughness by ODR on a 3D grid, with the OLS comparison", job.SPEC)
def _run(args: argparse.Namespace) -> int:
    opts = options_from(args, job.SPEC)
    outputs = {"out": opts["out"], "points_out": opts["points_out"]}
    with progress_for(args, "roughness") as bar:
        result = job.run(opts, outputs, progress=bar)
    for line in result.lines:
        log.debug("%s", line)
    log.info("wrote %s", ", ".join(str(p) for p in result.files.values()))
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
