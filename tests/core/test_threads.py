"""One BLAS thread while the windowed ICP runs (core/threads.py, issue #29 item 5)."""

import threading

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

from slipmap.core import threads
from slipmap.core.icp import windowed_icp


def _blas_threads():
    return sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})


def test_the_limit_holds_inside_and_is_restored_after():
    with threadpool_limits(limits=2, user_api="blas"):  # a caller's own limit
        before = _blas_threads()
        with threads.single_blas_thread():
            assert _blas_threads() == [1]
        assert _blas_threads() == before


def test_nested_uses_restore_only_at_the_outer_exit():
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        with threads.single_blas_thread():
            with threads.single_blas_thread():
                assert _blas_threads() == [1]
            assert _blas_threads() == [1]  # the outer use is still inside
        assert _blas_threads() == before


def test_a_worker_thread_sets_and_restores_the_limit():
    """QGIS runs an algorithm in a task thread, not the main one."""
    before = _blas_threads()
    seen = {}

    def task():
        with threads.single_blas_thread():
            seen["inside"] = _blas_threads()
        seen["after"] = _blas_threads()

    t = threading.Thread(target=task)
    t.start()
    t.join(20)
    assert seen == {"inside": [1], "after": before}
    assert _blas_threads() == before


def test_without_threadpoolctl_nothing_changes(monkeypatch):
    monkeypatch.setattr(threads, "_limit", lambda: None)
    with threadpool_limits(limits=2, user_api="blas"):
        before = _blas_threads()
        with threads.single_blas_thread():
            assert _blas_threads() == before
        assert _blas_threads() == before


def test_windowed_icp_runs_on_one_blas_thread_and_restores_the_callers():
    """Seen from the run's own progress callback; the caller's limit is back afterwards."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 20, size=(20_000, 2))
    z = 0.3 * np.sin(xy[:, 0] / 2.0) + 0.2 * np.cos(xy[:, 1] / 3.0)
    before = np.column_stack([xy, z + rng.normal(0, 0.002, len(xy))])
    after = before + np.array([0.05, -0.03, 0.01])
    seen = []

    def progress(fraction, message):
        seen.append(_blas_threads())

    with threadpool_limits(limits=2, user_api="blas"):
        outside = _blas_threads()
        r = windowed_icp(before, after, cell_m=10.0, backend="numpy", progress=progress)
        assert _blas_threads() == outside
    assert seen and all(s == [1] for s in seen)
    assert np.allclose(np.median(r.dx), 0.05, atol=5e-3)
