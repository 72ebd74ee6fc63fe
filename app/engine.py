"""Where a job's per-tile work runs: in this process, or on a Dask (dask.distributed) cluster.

One interface, :class:`Engine`: ``map(fn, items)`` runs ``fn`` on every item (a tile, a block
of windows) and returns the results in the items' order, with progress and cancel between
items; :meth:`Engine.reduce` folds them in that order, so sums come out the same whatever the
order in which workers finished. Two engines:

* :class:`InProcess` (the default): a plain loop; Dask is not imported.
* :class:`DaskEngine`: ``workers=N`` starts a ``distributed.LocalCluster`` of N single-threaded
  worker processes; ``scheduler="tcp://host:8786"`` connects to an existing cluster (the
  workers must be able to import slipmap and read the input files at the same paths).

Why Dask and not a home-made pool: it restarts a worker that dies and re-runs its tasks
elsewhere (``distributed.scheduler.allowed-failures`` times, here :data:`ALLOWED_FAILURES`),
it runs unchanged from a laptop to a cluster (SLURM, Kubernetes, cloud) through its
deployment packages, and its dashboard shows the tiles' progress and memory.

Failures: an exception raised on a worker by a SlipMap function reaches the caller unchanged
(a :class:`~slipmap.core.errors.SlipMapError` naming the tile); a task whose workers kept dying
ends in a :class:`~slipmap.core.errors.SlipMapError` naming the item, never in a partial
result. A cancel (the progress callback raising
:class:`~slipmap.core.errors.CancelledError`) cancels every pending task before re-raising.
"""

from __future__ import annotations

import logging
import pickle
import uuid
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Sequence

from ..core.errors import DependencyError, InvalidParameterError, SlipMapError
from ..core.progress import ProgressCallback, report

log = logging.getLogger("slipmap.app")

#: times a task may lose its worker (killed, out of memory) before the run fails
ALLOWED_FAILURES = 2
#: seconds to wait for a scheduler given by address
CONNECT_TIMEOUT_S = 20

__all__ = ["ALLOWED_FAILURES", "DaskEngine", "Engine", "InProcess", "make_engine"]


class Engine:
    """Runs a function on items (tiles) and returns the results in the items' order."""

    kind = "abstract"
    n_workers = 1

    def map(
        self,
        fn: Callable[[Any], Any],
        items: Sequence[Any],
        *,
        names: Optional[Sequence[str]] = None,
        progress: Optional[ProgressCallback] = None,
        what: str = "tile",
        each: Optional[Callable[[int, Any], Any]] = None,
    ) -> List[Any]:
        """``[fn(item) for item in items]``, with ``progress(done / n, "tile k/n")`` after each.

        ``names`` (one per item) name the item in error messages ("tile (3, 4)").
        ``each(i, result)``, when given, is called as each result arrives (in the order they
        finish) and what it returns is kept instead of the result: a job streams large
        results (raster blocks) to a file this way and keeps only their summaries.
        """
        raise NotImplementedError

    def reduce(
        self,
        fn: Callable[[Any], Any],
        items: Sequence[Any],
        combine: Callable[[Any, Any], Any],
        initial: Any,
        **kw,
    ) -> Any:
        """Fold ``combine(acc, fn(item))`` over the items in their order (deterministic)."""
        acc = initial
        for part in self.map(fn, items, **kw):
            acc = combine(acc, part)
        return acc

    def close(self) -> None:
        """Release the workers (nothing for the in-process engine)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def describe(self) -> str:
        return self.kind


class InProcess(Engine):
    """Items one after the other in this process (no Dask needed)."""

    kind = "in-process"

    def map(self, fn, items, *, names=None, progress=None, what="tile", each=None):
        n = len(items)
        out = []
        report(progress, 0.0, f"{n} {what}(s) in process")
        for i, item in enumerate(items):
            value = fn(item)
            out.append(each(i, value) if each is not None else value)
            report(progress, (i + 1) / max(n, 1), f"{what} {i + 1}/{n}")
        return out


@dataclass
class _Failure:
    """An exception raised on a worker, carried back as data (see :func:`_call`)."""

    exc: Optional[BaseException]
    text: str
    kind: str


def _call(fn, item):
    """Run ``fn(item)`` on a worker; a SlipMapError comes back as a :class:`_Failure`.

    SlipMap's exceptions (e.g. ``OptionError(key, text)``) do not all survive pickling with
    their fields; the failure carries the exception when it does, else its type and message.
    Other exceptions propagate to Dask (and reach the caller as Dask re-raises them).
    """
    try:
        return fn(item)
    except SlipMapError as exc:
        try:
            pickle.loads(pickle.dumps(exc))
            keep: Optional[BaseException] = exc
        except Exception:
            keep = None
        return _Failure(keep, str(exc), type(exc).__name__)


def _raise_failure(f: _Failure):
    if f.exc is not None:
        raise f.exc
    raise SlipMapError(f.text)


class DaskEngine(Engine):
    """Items as tasks on a Dask cluster: a LocalCluster of ``workers`` processes, or the
    scheduler at ``scheduler`` (``tcp://host:port``)."""

    kind = "dask"

    def __init__(
        self,
        *,
        workers: Optional[int] = None,
        scheduler: Optional[str] = None,
        memory_limit: Any = "auto",
        allowed_failures: int = ALLOWED_FAILURES,
    ):
        if (workers is None) == (scheduler is None):
            raise InvalidParameterError("give either workers (a local cluster) or scheduler")
        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError:
            raise DependencyError(
                "running on Dask needs dask.distributed; install it: "
                "python -m pip install 'dask[distributed]' (or slipmap[dask])"
            ) from None
        self.cluster = None
        self.scheduler = scheduler
        with dask.config.set({"distributed.scheduler.allowed-failures": int(allowed_failures)}):
            if scheduler is not None:
                try:
                    self.client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
                except (OSError, TimeoutError) as exc:
                    raise SlipMapError(
                        f"cannot reach the Dask scheduler at {scheduler} ({exc}); check the "
                        "address (tcp://host:8786) and that the scheduler is running"
                    ) from exc
            else:
                n = int(workers)
                if n < 1:
                    raise InvalidParameterError(f"workers must be >= 1, got {workers}")
                self.cluster = LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    memory_limit=memory_limit,
                    dashboard_address=":0",
                    silence_logs=logging.ERROR,
                )
                self.client = Client(self.cluster)
        self.n_workers = max(1, len(self.client.scheduler_info().get("workers", {})))
        log.info("Dask: %s", self.describe())

    def describe(self) -> str:
        where = self.scheduler or "local cluster"
        return f"dask ({where}, {self.n_workers} worker(s))"

    def map(self, fn, items, *, names=None, progress=None, what="tile", each=None):
        from distributed import as_completed

        try:
            from distributed.scheduler import KilledWorker
        except ImportError:  # pragma: no cover - older distributed
            from distributed import KilledWorker
        n = len(items)
        if n == 0:
            return []
        names = list(names) if names is not None else [f"{what} {i + 1}" for i in range(n)]
        tag = uuid.uuid4().hex[:8]
        keys = [f"slipmap-{what}-{tag}-{i}" for i in range(n)]
        futures = self.client.map(_call, [fn] * n, list(items), key=keys, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        results: List[Any] = [None] * n
        done = 0
        report(progress, 0.0, f"{n} {what}(s) on {self.describe()}")
        try:
            for fut in as_completed(futures):
                i = index[fut.key]
                try:
                    value = fut.result()
                except KilledWorker as exc:
                    raise SlipMapError(
                        f"{names[i]}: the Dask worker running it died {ALLOWED_FAILURES + 1} "
                        "times (out of memory, or killed); nothing was written. Give the "
                        "workers more memory or use smaller tiles, then run again"
                    ) from exc
                if isinstance(value, _Failure):
                    _raise_failure(value)
                fut.release()  # the worker may drop it now
                results[i] = each(i, value) if each is not None else value
                done += 1
                report(progress, done / n, f"{what} {done}/{n}")
        except BaseException:
            self.client.cancel(futures)
            raise
        finally:
            del futures
        return results

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()


def make_engine(*, workers: Optional[int] = None, scheduler: Optional[str] = None) -> Engine:
    """The engine the options ask for: Dask with ``workers`` or ``scheduler``, else in-process.

    Raises
    ------
    InvalidParameterError
        Both given.
    DependencyError
        Dask asked for but not installed.
    """
    if workers is not None and scheduler is not None:
        raise InvalidParameterError(
            "give either workers (a local Dask cluster) or a scheduler address, not both"
        )
    if workers is None and scheduler is None:
        return InProcess()
    return DaskEngine(workers=workers, scheduler=scheduler)
