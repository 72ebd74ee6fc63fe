"""One BLAS thread while a kernel of many small dense operations runs (issue #29 item 5).

The windowed ICP and its spline field call BLAS and LAPACK on small matrices, thousands of
times per run: batched 6 × 6 eigen-decompositions of the cells, products over blocks of 1024
points, SuperLU's supernodes. OpenBLAS (numpy's BLAS on Debian and in the PyPI wheels) starts
its threads for such calls and leaves them spinning after each one: under cProfile the
cells' batched ``eigh`` took 0.56 s of a run with two BLAS threads and 0.04 s with one. On
the 2-core test machine (lone-star lobe, the default ``slipmap icp``, paired runs) one BLAS
thread takes 40-43 % off the CPU time with the same results (5e-8 m); the wall time stays
level there (-4 % with the Numba matcher, -2 % with PoCL, within the runs' spread): the
freed core is what a machine running other work, or with more cores, gains
(docs/benchmarks.md, stop 55).

:func:`single_blas_thread` limits BLAS to one thread through threadpoolctl, the library
scikit-learn uses for the same purpose, and restores the caller's limit on exit; nested
uses (the coarse pass inside the windowed ICP, the field inside it) are threadpoolctl's own
nesting. OpenBLAS's limit is process-wide: threadpoolctl (>= 3.6) lets one thread at a time
own it, so a second thread that runs the windowed ICP at the same time neither sets nor
lifts it (it runs under whatever limit holds). SlipMap's engines do not run two in one
process (tiles run one after the other, or in Dask worker processes of one thread each).
Without threadpoolctl installed it does nothing: the results are the same either way (to
rounding), only the time differs.
"""

from __future__ import annotations

import contextlib
import logging

log = logging.getLogger(__name__)


def _limit():
    """threadpoolctl's limiter at one BLAS thread (already in force), or None."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: without it BLAS keeps its own thread count
        log.debug("threadpoolctl not installed: BLAS threads left as they are")
        return None
    try:
        return threadpool_limits(limits=1, user_api="blas")
    except Exception as exc:  # a speed-up only: never let it stop a run
        log.debug("BLAS threads not limited: %s", exc)
        return None


@contextlib.contextmanager
def single_blas_thread():
    """Context manager (and decorator) that holds BLAS to one thread inside it and restores
    the previous limits on exit."""
    limiter = _limit()
    if limiter is None:
        yield
        return
    with limiter:
        yield
