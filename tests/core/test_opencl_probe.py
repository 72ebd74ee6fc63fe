"""The OpenCL probe: a driver that aborts takes down only the probe's child (issue #20)."""

from __future__ import annotations

import pytest

pytest.importorskip("pyopencl", reason="PyOpenCL is not installed")

from slipmap.core.opencl import backend  # noqa: E402


@pytest.fixture
def fresh(monkeypatch):
    monkeypatch.setattr(backend, "_probe_result", {})
    return monkeypatch


def test_probe_reports_an_abort_instead_of_dying(fresh):
    child = "import sys, os; print('Not enough memory to run on this device', file=sys.stderr)"
    fresh.setattr(backend, "_PROBE_CHILD", child + "; sys.stderr.flush(); os.abort()")
    reason = backend.probe_runtime(timeout_s=60)
    assert reason is not None
    assert "SIGABRT" in reason and "Not enough memory to run on this device" in reason


def test_probe_reports_a_failure_and_caches(fresh):
    fresh.setattr(backend, "_PROBE_CHILD", "raise SystemExit('no OpenCL device at all')")
    reason = backend.probe_runtime(timeout_s=60)
    assert reason == "the OpenCL runtime did not start (exit 1): no OpenCL device at all"
    fresh.setattr(backend, "_PROBE_CHILD", "print('ok')")
    assert backend.probe_runtime(timeout_s=60) == reason  # cached for the process


def test_probe_times_out(fresh):
    fresh.setattr(backend, "_PROBE_CHILD", "import time; time.sleep(30)")
    assert "more than 0.5 s" in backend.probe_runtime(timeout_s=0.5)


def test_probe_passes_where_the_runtime_starts(fresh):
    reason = backend.probe_runtime()
    if reason is not None:
        pytest.skip(f"the OpenCL runtime cannot start here: {reason}")
    assert backend.OpenCLKernels().device_name
