"""A Ctrl-C that lands in a callback Python cannot raise from is neither lost nor printed."""

import gc
import signal
import subprocess
import sys
import time

import pytest

from slipmap import cli


class _Interrupts:
    """An object whose finaliser is interrupted by Ctrl-C, as Dask's GC callback was in CI."""

    def __del__(self):
        raise KeyboardInterrupt


def _drop_an_interrupted_finaliser():
    obj = _Interrupts()
    obj.cycle = obj  # only the collector frees it: the finaliser runs inside gc.collect()
    del obj
    gc.collect()


def _wait_for_interrupt():
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        time.sleep(0.01)
    pytest.fail("the swallowed Ctrl-C was not delivered again")


@pytest.fixture
def python_sigint():
    """Python's own SIGINT handler for the test (a test run started as a background job of
    a script inherits SIGINT ignored, and ``_thread.interrupt_main`` then does nothing)."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def _default_sigint():
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_swallowed_ctrl_c_during_a_run_reaches_the_main_thread(capsys, python_sigint):
    cli._keep_interrupts()
    assert sys.unraisablehook is cli._unraisable
    cli._RUNNING.set()
    try:
        with pytest.raises(KeyboardInterrupt):
            _drop_an_interrupted_finaliser()
            _wait_for_interrupt()
    finally:
        cli._RUNNING.clear()
    err = capsys.readouterr().err
    assert "Exception ignored" not in err and "Traceback" not in err


def test_swallowed_ctrl_c_after_the_run_is_dropped_quietly(capsys):
    cli._keep_interrupts()
    assert not cli._RUNNING.is_set()
    _drop_an_interrupted_finaliser()
    time.sleep(0.05)  # nothing pending: no KeyboardInterrupt here
    err = capsys.readouterr().err
    assert "Exception ignored" not in err and "Traceback" not in err


def test_other_unraisable_errors_still_reach_the_previous_hook():
    seen = []
    saved = sys.unraisablehook, cli._previous_unraisablehook
    try:
        sys.unraisablehook = seen.append
        cli._previous_unraisablehook = None
        cli._keep_interrupts()

        class Broken:
            def __del__(self):
                raise ValueError("boom")

        Broken()
        gc.collect()
        assert [type(a.exc_value) for a in seen] == [ValueError]
    finally:
        sys.unraisablehook, cli._previous_unraisablehook = saved


_SLOW_EXIT = """
import os, signal, sys, time
from slipmap import cli
cli.build_parser()  # registers the commands


def interrupted_run(args):
    os.kill(os.getpid(), signal.SIGINT)  # the first Ctrl-C, mid-run
    time.sleep(5)


help_text, add_arguments, _, spec = cli.COMMANDS["planes"]
cli.COMMANDS["planes"] = (help_text, add_arguments, interrupted_run, spec)
sys.argv = ["slipmap", "planes", "in.laz", "--out", "out"]
status = cli.main(exiting=True)
# the impatient second Ctrl-C lands after the command returned, while the process shuts
# down (Dask's cluster, then Python's finalisation, which restores SIGINT's default action)
os.kill(os.getpid(), signal.SIGINT)
time.sleep(0.2)
sys.exit(status)
"""


def test_a_second_ctrl_c_while_the_program_exits_keeps_status_130(tmp_path):
    """CI saw status -2 (killed by SIGINT) after 'slipmap: interrupted': the second Ctrl-C
    arrived while Dask and Python shut down. The program's status stays 130, one line."""
    proc = subprocess.run(
        [sys.executable, "-c", _SLOW_EXIT],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=60,
        preexec_fn=_default_sigint,  # as in a terminal, whatever this test run inherited
    )
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.count("interrupted") == 1, proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr
