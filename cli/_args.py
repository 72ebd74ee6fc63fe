"""The CLI's side of the application layer: argparse arguments made from a job's options.

:func:`add_options` turns a :class:`~slipmap.app.options.JobSpec` into arguments (flags named
from the keys: ``grid_m`` -> ``--grid``; positionals where the option says so), with the same
conversion every face uses, so a bad value is refused at parse time with exit 2 and one line
naming the flag. :func:`options_from` gives the converted options back as the job's keys.
:func:`command` registers a subcommand; :class:`ProgressBar` maps the progress protocol onto
tqdm.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any, Callable, Dict, Iterable, Optional

from ..app.options import JobSpec, Option, OptionError

#: subcommand name -> (help, add_arguments(parser), run(args) -> int, JobSpec or None)
COMMANDS: Dict[str, tuple] = {}
FACE = "cli"
log = logging.getLogger("slipmap")


def command(name: str, help_text: str, spec: Optional[JobSpec] = None):
    """Register ``add_arguments`` / ``run`` pairs: decorate the ``run`` function.

    With ``spec``, an :class:`OptionError` of the run is reported with the CLI's names of
    the spec's options.
    """

    def deco(run: Callable[[argparse.Namespace], int]):
        def register(add_arguments: Callable[[argparse.ArgumentParser], None]):
            COMMANDS[name] = (help_text, add_arguments, run, spec)
            return add_arguments

        run.arguments = register  # type: ignore[attr-defined]
        return run

    return deco


def _parser_type(opt: Option, flag: str):
    """argparse ``type=``: the option's own conversion, its errors as argparse errors."""
    one = opt
    if opt.is_list or opt.type == "vector3":  # one token at a time
        from dataclasses import replace

        one = replace(
            opt,
            type={"floats": "float", "ints": "int", "paths": "path", "vector3": "float"}.get(
                opt.type, "str"
            ),
            nargs=None,
        )

    def parse(text: str):
        if opt.is_list and text.strip().lower() == "none":
            return "none"
        try:
            return one.convert(text)
        except OptionError as exc:
            raise argparse.ArgumentTypeError(exc.text) from None

    parse.__name__ = opt.type  # argparse names the type in "invalid <type> value"
    return parse


def add_options(
    parser: argparse.ArgumentParser,
    spec: JobSpec,
    *,
    skip: Iterable[str] = (),
) -> None:
    """Add every option of ``spec`` the CLI shows (``cli`` not None), in groups."""
    skip = set(skip)
    groups: Dict[str, Any] = {}
    for opt in spec.for_face(FACE):
        if opt.key in skip:
            continue
        name = opt.name_in(FACE)
        target = parser
        if opt.group:
            target = groups.get(opt.group)
            if target is None:
                target = groups[opt.group] = parser.add_argument_group(opt.group)
        help_text = spec.help_in(opt, FACE)  # other options by their CLI names
        if not opt.required and opt.type != "bool" and "default" not in opt.help:
            help_text += f" (default: {opt.default_text()})"
        kw: Dict[str, Any] = {"help": help_text, "dest": opt.key}
        if opt.type == "bool":
            kw["action"] = argparse.BooleanOptionalAction if opt.default else "store_true"
            kw["default"] = None
        else:
            kw["type"] = _parser_type(opt, name)
            if opt.metavar:
                kw["metavar"] = opt.metavar
            elif opt.type == "choice":
                kw["metavar"] = "{" + ",".join(map(str, opt.choices)) + "}"
            if opt.is_list or opt.type == "vector3":
                kw["nargs"] = opt.nargs or ("+" if opt.is_list else 3)
                if opt.type == "vector3":
                    kw["nargs"] = 3
        if name.startswith("-"):
            kw["required"] = opt.required
            target.add_argument(name, **kw)
        else:
            kw.pop("dest")
            if not opt.required:
                kw["nargs"] = "?"
            target.add_argument(opt.key, **kw)


def options_from(args: argparse.Namespace, spec: JobSpec, **extra: Any) -> Dict[str, Any]:
    """The job's options from parsed ``args`` (converted, defaults in, cross-checks run).

    ``extra`` gives values the CLI supplies another way. Raises :class:`OptionError`.
    """
    raw: Dict[str, Any] = {}
    for opt in spec.for_face(FACE):
        value = getattr(args, opt.key, None)
        if opt.is_list and isinstance(value, list):
            value = () if "none" in value else value
        if opt.type == "vector3" and isinstance(value, list):
            value = [v for v in value]
        raw[opt.key] = value
    raw.update(extra)
    return spec.parse(raw, face=FACE)


def cli_error(spec: JobSpec, exc: OptionError) -> str:
    """``exc`` with the option named as the CLI calls it (``--grid: must be > 0``)."""
    return spec.render_error(exc, FACE)


class ProgressBar:
    """Maps SlipMap's progress callback onto a tqdm bar on stderr (hidden when not a TTY)."""

    def __init__(self, description: str, *, enabled: bool = True):
        self._bar = None
        if enabled:
            try:
                from tqdm import tqdm
            except ImportError:  # pragma: no cover - tqdm is a dependency
                tqdm = None
            if tqdm is not None:
                self._bar = tqdm(
                    total=1000,
                    desc=description,
                    unit="‰",
                    disable=None,
                    leave=False,
                    file=sys.stderr,
                )

    def __call__(self, fraction: float, message: str = "") -> None:
        if self._bar is None:
            return
        self._bar.n = int(round(1000 * fraction))
        if message:
            self._bar.set_postfix_str(message, refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def progress_for(args: argparse.Namespace, description: str) -> Optional[ProgressBar]:
    """A progress bar unless ``--quiet`` (or a command's ``--no-progress``)."""
    quiet = getattr(args, "quiet", False) or getattr(args, "no_progress", False)
    return ProgressBar(description, enabled=not quiet)


def run_job(
    args: argparse.Namespace,
    job,
    name: str,
    outputs=None,
    *,
    lines_level: int = logging.INFO,
    overrides: Optional[Dict[str, Any]] = None,
):
    """Run ``job`` (an :mod:`slipmap.app` job module) on the parsed arguments: its options
    (:func:`options_from`), the outputs (default: everything into ``--out``), a progress bar,
    its summary lines and the files written in the log. ``outputs``: a mapping, or
    ``f(opts) -> mapping``; ``overrides``: option values the command computed itself. Returns
    the ``JobResult``."""
    opts = options_from(args, job.SPEC, **(overrides or {}))
    if outputs is None:
        outputs = {"out": opts["out"]}
    elif callable(outputs):
        outputs = outputs(opts)
    with progress_for(args, name) as bar:
        result = job.run(opts, outputs, progress=bar)
    for line in result.lines:
        log.log(lines_level, "%s", line)
    log.info("wrote %s", ", ".join(str(p) for p in result.files.values()))
    return result
