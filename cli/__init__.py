"""The ``slipmap`` command line: one subcommand per job, a thin face over :mod:`slipmap.app`.

Each command module (``planes``, ``slip``, ``roughness``, ``accuracy``, ``fields``, ``demo``)
maps its arguments onto a job of the application layer and the job's result onto the console.

Exit codes: 0 success, 2 bad input or options (one line naming the option as the CLI spells
it; ``--debug`` for the traceback), 1 unexpected failure, 130 interrupted or cancelled.
"""

from __future__ import annotations

import _thread
import argparse
import importlib
import logging
import signal
import sys
import threading
import time
from typing import List, Optional

from .._version import __version__
from ..app.options import OptionError
from ..core.errors import CancelledError, SlipMapError
from ._args import COMMANDS, cli_error

log = logging.getLogger("slipmap")

#: modules that register commands, in the order of ``slipmap --help``
_MODULES = ("planes", "slip", "roughness", "accuracy", "fields", "demo")


def build_parser() -> argparse.ArgumentParser:
    for mod in _MODULES:
        importlib.import_module(f"{__name__}.{mod}")
    parser = argparse.ArgumentParser(
        prog="slipmap",
        description="Fault slip, displacement fields and roughness from repeat LiDAR surveys.",
    )
    parser.add_argument("--version", action="version", version=f"slipmap {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (help_text, add_arguments, run, spec) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        add_arguments(p)
        p.set_defaults(_run=run, _spec=spec)
    return parser


def _configure_logging(debug: bool, quiet: bool) -> None:
    level = logging.DEBUG if debug else (logging.WARNING if quiet else logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(message)s" if not debug else "%(name)s: %(message)s"))
    root = logging.getLogger("slipmap")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False
    logging.captureWarnings(True)
    warnings_logger = logging.getLogger("py.warnings")
    warnings_logger.handlers[:] = [handler]


#: set while a command runs: a Ctrl-C swallowed by a callback is delivered again then
_RUNNING = threading.Event()
_previous_unraisablehook = None


def _unraisable(args) -> None:
    """``sys.unraisablehook`` that keeps a Ctrl-C from being lost or printed.

    A SIGINT that arrives while Python runs a garbage-collector callback, a ``__del__`` or a
    weakref callback (Dask's ``GCDiagnosis`` installs one) raises ``KeyboardInterrupt``
    there, where Python cannot propagate it: it prints "Exception ignored in ..." with a
    traceback and forgets the interrupt. Here it is delivered again to the main thread
    while a command runs, so the run stops with one line and exit 130, and dropped silently
    once the command has returned. Anything else goes to the hook that was installed before.

    The delivery comes from a short-lived thread a moment later: ``_thread.interrupt_main``
    called in the main thread would raise inside this hook, where it would be lost again.
    """
    if args.exc_type is not None and issubclass(args.exc_type, KeyboardInterrupt):
        if _RUNNING.is_set():
            threading.Thread(target=_deliver_interrupt, name="slipmap-ctrl-c", daemon=True).start()
        return
    (_previous_unraisablehook or sys.__unraisablehook__)(args)


def _deliver_interrupt() -> None:
    time.sleep(0.02)  # the hook and the callback that swallowed the interrupt return first
    if _RUNNING.is_set():
        _thread.interrupt_main()


def _keep_interrupts() -> None:
    global _previous_unraisablehook
    if sys.unraisablehook is not _unraisable:
        _previous_unraisablehook = sys.unraisablehook
        sys.unraisablehook = _unraisable


def _interrupted(exiting: bool) -> int:
    """Say the run was interrupted; in the ``slipmap`` process, ignore any further Ctrl-C.

    An impatient second Ctrl-C would otherwise land while Dask and Python shut down, after
    this line: Python would then end the process by SIGINT (status -2 to a parent, 130 to a
    shell) or print a traceback from an ``atexit`` callback. The process is exiting anyway.
    """
    if exiting and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    log.error("slipmap: interrupted")
    return 130


def main(argv: Optional[List[str]] = None, *, exiting: bool = False) -> int:
    """Run one ``slipmap`` command; return its exit status (0, 1, 2 or 130).

    Parameters
    ----------
    argv : list of str, optional
        The arguments; ``sys.argv[1:]`` when None.
    exiting : bool
        True in the ``slipmap`` program (:func:`entry`), whose process exits once this
        returns: after a Ctrl-C, further ones are ignored so the status stays 130.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    _configure_logging(args.debug, args.quiet)
    _keep_interrupts()
    try:
        _RUNNING.set()
        try:
            return _run(args, exiting)
        finally:
            _RUNNING.clear()
    except KeyboardInterrupt:  # a second Ctrl-C while the first one was being handled
        return _interrupted(exiting)


def entry() -> None:
    """The ``slipmap`` program (console script and ``python -m slipmap.cli``)."""
    sys.exit(main(exiting=True))


def _run(args: argparse.Namespace, exiting: bool) -> int:
    try:
        return int(args._run(args) or 0)
    except CancelledError:
        log.error("slipmap %s: cancelled", args.command)
        return 130
    except SlipMapError as exc:
        if args.debug:
            log.exception("slipmap %s", args.command)
        else:
            text = str(exc)
            if isinstance(exc, OptionError) and args._spec is not None:
                text = cli_error(args._spec, exc)
            log.error("slipmap %s: error: %s", args.command, text)
        return 2
    except KeyboardInterrupt:
        return _interrupted(exiting)
    except Exception as exc:  # noqa: BLE001 - last resort: one line unless --debug
        if args.debug:
            log.exception("slipmap %s: unexpected error", args.command)
        else:
            log.error(
                "slipmap %s: unexpected error: %s: %s (run with --debug for the traceback)",
                args.command,
                type(exc).__name__,
                exc,
            )
        return 1


if __name__ == "__main__":  # pragma: no cover
    entry()
