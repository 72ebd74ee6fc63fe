"""The OpenCL probe: a driver that aborts takes down only the probe's child (issue #20)."""

from __future__ import annotations

import pytest

pytest.importorskip("pyopencl", reason="PyOpenCL is not installed")

from slipmap.core.opencl import backend  # noqa: E402


@pytest.fixture
def fresh(monkeypatch):
    monkeypatch.setattr(backend, "_probe_result", {})
    monkeypatch.setattr(backend, "_no_driver_registered", lambda: None)  # the child runs
    return monkeypatch


def test_no_registered_driver_is_answered_without_a_child(monkeypatch, tmp_path):
    """Linux: no ``*.icd`` where the ICD loader looks (``OCL_ICD_VENDORS`` replaces the
    default folder) -> the probe answers at once, no child process (issue #29)."""
    import subprocess
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("the ICD folders are Linux's")
    monkeypatch.setattr(backend, "_probe_result", {})
    monkeypatch.delenv("OCL_ICD_FILENAMES", raising=False)
    monkeypatch.setenv("OCL_ICD_VENDORS", str(tmp_path))
    monkeypatch.setattr(sys, "prefix", str(tmp_path / "env"))

    def no_child(*a, **kw):
        raise AssertionError("the probe started a child")

    monkeypatch.setattr(subprocess, "run", no_child)
    reason = backend.probe_runtime(timeout_s=60)
    assert reason is not None and "no OpenCL driver is registered" in reason
    (tmp_path / "vendor.icd").write_text("libvendor.so\n")
    assert backend._no_driver_registered() is None  # a driver: the child decides


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
