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

Dask as a user meets it (issue #31), for every face since they all come through here:

* a scheduler address is checked before anything connects (:func:`check_scheduler_address`:
  one of Dask's schemes, a host, a port in 1..65535), an :class:`~.options.OptionError` naming
  the ``scheduler`` option and what to type;
* the whole handshake (TCP connect *and* the scheduler's first answer) is bounded by
  :func:`handshake_timeout_s` (:func:`probe_scheduler`): a port where something listens but
  does not speak Dask (an HTTP server, a silent listener) is refused in that time, not waited
  on for ever;
* ``workers`` is bounded by the machine (:func:`local_worker_bound`: cores, and
  :data:`MIN_WORKER_MEMORY_BYTES` per worker), clamped with a warning;
* local workers ignore SIGINT (a terminal's Ctrl-C reaches the whole process group): only
  this process sees it, cancels the tasks and closes the cluster with Dask's loggers silenced,
  so the user reads one line, not a traceback per worker;
* the cluster's own failures (``CommClosedError``, ``TimeoutError``, ``OSError`` of the comm
  layer, a lost scheduler) become a :class:`ClusterError`, a SlipMapError every face shows as
  one line.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import pickle
import signal
import threading
import uuid
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Sequence
from urllib.parse import urlsplit

from ..core.errors import DependencyError, InvalidParameterError, SlipMapError
from ..core.progress import ProgressCallback, report

log = logging.getLogger("slipmap.app")

#: times a task may lose its worker (killed, out of memory) before the run fails
ALLOWED_FAILURES = 2
#: seconds to wait for a scheduler given by address, connecting and its first answer together,
#: unless Dask's own ``distributed.comm.timeouts.connect`` is set (see :func:`handshake_timeout_s`)
CONNECT_TIMEOUT_S = 20.0
HANDSHAKE_TIMEOUT_S = CONNECT_TIMEOUT_S  # the same setting, by what it bounds
_DASK_DEFAULT_CONNECT = "30s"
#: Dask's address schemes (``distributed.comm.registry.backends``)
SCHEMES = ("tcp", "tls", "inproc", "ucx", "ws", "wss")
#: memory each local worker is given at least (one processing tile of the default size, its
#: halo and the results of a block fit well inside it), bytes
MIN_WORKER_MEMORY_BYTES = 1 << 30

__all__ = [
    "ALLOWED_FAILURES",
    "ClusterError",
    "DaskEngine",
    "Engine",
    "HANDSHAKE_TIMEOUT_S",
    "InProcess",
    "MIN_WORKER_MEMORY_BYTES",
    "SCHEMES",
    "check_scheduler_address",
    "local_worker_bound",
    "make_engine",
    "probe_scheduler",
]


class ClusterError(SlipMapError):
    """The Dask cluster failed (not the data): the scheduler cannot be reached or is not a
    Dask scheduler, the connection was lost, a worker stopped answering."""


_SCHEDULER_HINT = "give e.g. tcp://host:8786 (the address the scheduler prints when it starts)"


def check_scheduler_address(address: str) -> str:
    """``address`` (stripped) when it can name a Dask scheduler; nothing is contacted.

    Checks the scheme (one of :data:`SCHEMES`), the host and, for the network schemes, the
    port (present, a whole number in 1..65535). ``inproc://`` addresses are in-process only.

    Raises
    ------
    OptionError
        Key ``scheduler``, the text saying what is wrong and what to type.
    """
    from .options import OptionError

    text = str(address).strip()
    if not text:
        raise OptionError("scheduler", f"is empty; {_SCHEDULER_HINT}")
    if "://" not in text:
        raise OptionError("scheduler", f"{text!r} is not an address; {_SCHEDULER_HINT}")
    scheme, _, rest = text.partition("://")
    if scheme.lower() not in SCHEMES:
        raise OptionError(
            "scheduler",
            f"{text!r}: unknown scheme {scheme + '://'!r}; Dask's are "
            f"{', '.join(s + '://' for s in SCHEMES)}; {_SCHEDULER_HINT}",
        )
    if scheme.lower() == "inproc":
        if not rest.strip("/"):
            raise OptionError("scheduler", f"{text!r} names no scheduler; {_SCHEDULER_HINT}")
        return text
    try:
        parts = urlsplit(f"//{rest}")
        host, port = parts.hostname, parts.port
    except ValueError:
        raise OptionError(
            "scheduler", f"{text!r}: the port must be a whole number in 1..65535; {_SCHEDULER_HINT}"
        ) from None
    if parts.path.strip("/") or parts.query or parts.fragment:
        raise OptionError(
            "scheduler", f"{text!r} has more than host:port after the scheme; {_SCHEDULER_HINT}"
        )
    if not host:
        raise OptionError("scheduler", f"{text!r} has no host; {_SCHEDULER_HINT}")
    if port is None:
        raise OptionError("scheduler", f"{text!r} has no port; add it, e.g. {scheme}://{host}:8786")
    if not 1 <= port <= 65535:  # pragma: no cover - urlsplit refuses these already
        raise OptionError("scheduler", f"{text!r}: the port must be in 1..65535")
    return text


async def _identity(address: str, timeout: float, box: dict) -> dict:
    from distributed.comm import connect

    comm = await connect(address, timeout=timeout)
    box["connected"] = True
    try:
        await comm.write({"op": "identity"})
        return await comm.read()
    finally:
        comm.abort()


def probe_scheduler(address: str, *, timeout_s: Optional[float] = None) -> dict:
    """Ask the scheduler at ``address`` who it is, the whole exchange bounded by ``timeout_s``.

    Runs on its own event loop in a helper thread (so it works whether or not the caller has
    a loop), and the thread is waited on for ``timeout_s`` plus a second at most.

    Returns
    -------
    dict
        The scheduler's identity (``type`` is ``"Scheduler"``).

    Raises
    ------
    ClusterError
        Nothing answers (refused, unreachable), the answer is not Dask's (an HTTP server), or
        no answer came within ``timeout_s`` (a silent listener).
    """
    if timeout_s is None:
        timeout_s = handshake_timeout_s()
    box: dict = {}

    def run():
        try:
            box["reply"] = asyncio.run(
                asyncio.wait_for(_identity(address, timeout_s, box), timeout_s)
            )
        except BaseException as exc:  # noqa: BLE001 - carried to the caller's thread
            box["error"] = exc

    t = threading.Thread(target=run, name="slipmap-scheduler-probe", daemon=True)
    t.start()
    t.join(timeout_s + 1.0)
    exc = box.get("error")
    reply = box.get("reply")
    what = f"the Dask scheduler at {address}"
    if (
        not box.get("connected")
        and (t.is_alive() or isinstance(exc, OSError))
        and not _listens(address, timeout_s)
    ):
        raise ClusterError(
            f"cannot reach {what}: nothing accepted a connection within {timeout_s:g} s "
            f"({exc or 'no answer'}); check the address and that the scheduler is running"
        )
    if t.is_alive() or isinstance(exc, (asyncio.TimeoutError, TimeoutError)):
        raise ClusterError(
            f"{what} did not answer within {timeout_s:g} s: something listens there but does "
            "not speak Dask, or the network drops the traffic; check the address and the port "
            "(the scheduler's, usually 8786, not its dashboard's)"
        )
    if isinstance(exc, OSError):
        raise ClusterError(
            f"cannot reach {what} ({exc}); check the address and that the scheduler is running"
        )
    if exc is not None or not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        raise ClusterError(
            f"{address} answered, but not as a Dask scheduler does (a web server or another "
            "service on that port?); give the scheduler's address, usually port 8786"
        )
    return reply


def handshake_timeout_s() -> float:
    """Seconds allowed for the whole handshake with a scheduler: :data:`CONNECT_TIMEOUT_S`,
    or Dask's ``distributed.comm.timeouts.connect`` when the user set it to something else
    than Dask's default (``DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT=5s`` in the environment,
    or Dask's configuration file)."""
    try:
        import dask
        from dask.utils import parse_timedelta

        value = dask.config.get("distributed.comm.timeouts.connect", _DASK_DEFAULT_CONNECT)
        if str(value).strip() != _DASK_DEFAULT_CONNECT:
            return float(parse_timedelta(value, default="seconds"))
    except (ImportError, ValueError, TypeError):
        pass
    return float(CONNECT_TIMEOUT_S)


def _listens(address: str, timeout_s: float) -> bool:
    """Whether something accepts a TCP connection at ``address`` (``tcp``, ``tls``, ``ws``,
    ``wss``): tells "nothing there" from "something there that does not speak Dask" (Dask's
    ``connect`` includes its own handshake, so it cannot tell them apart)."""
    import socket

    scheme, _, rest = address.partition("://")
    if scheme.lower() not in ("tcp", "tls", "ws", "wss"):
        return False
    try:
        parts = urlsplit(f"//{rest}")
        with socket.create_connection((parts.hostname, parts.port), timeout=min(timeout_s, 5)):
            return True
    except (OSError, ValueError):
        return False


def local_worker_bound(*, memory_bytes: Optional[int] = None, cores: Optional[int] = None) -> int:
    """The most local workers this machine can run: its cores (those this process may use),
    and :data:`MIN_WORKER_MEMORY_BYTES` of memory each; at least 1."""
    if cores is None:
        try:
            cores = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            cores = os.cpu_count() or 1
    if memory_bytes is None:
        try:
            from distributed.system import MEMORY_LIMIT

            memory_bytes = int(MEMORY_LIMIT)
        except ImportError:  # pragma: no cover - psutil comes with distributed
            memory_bytes = MIN_WORKER_MEMORY_BYTES * cores
    return max(1, min(int(cores), int(memory_bytes // MIN_WORKER_MEMORY_BYTES)))


def clamp_workers(workers: int) -> int:
    """``workers`` limited to :func:`local_worker_bound`, with a warning when it is lowered.

    Why a clamp and not a refusal: the result does not depend on the number of workers (the
    items are folded in their order), only the speed does, and more single-threaded workers
    than cores only share the same cores while each takes its own memory; a script written
    on a large machine (``--workers 32``) then still runs on a laptop, and the warning says
    what was used. Values below 1 are refused by the option itself.
    """
    n = int(workers)
    bound = local_worker_bound()
    if n > bound:
        log.warning(
            "workers: %d asked for, but this machine has room for %d (%d core(s), %s GiB of "
            "memory at %g GiB per worker); running %d",
            n,
            bound,
            local_worker_bound(memory_bytes=1 << 62),
            _memory_gib(),
            MIN_WORKER_MEMORY_BYTES / (1 << 30),
            bound,
        )
        return bound
    return n


def _memory_gib() -> str:
    try:
        from distributed.system import MEMORY_LIMIT

        return f"{MEMORY_LIMIT / (1 << 30):.1f}"
    except ImportError:  # pragma: no cover
        return "?"


def _no_gc_diagnosis() -> None:
    """Dask's garbage-collection diagnosis off in this process (the local cluster's scheduler
    runs here and turns it on). It times every collection from a ``gc`` callback; a Ctrl-C
    that lands inside that callback cannot propagate and leaves its timer half-started, so
    later collections print "Exception ignored … AssertionError" tracebacks (CI, stop 30/32).
    It only logs long GC pauses, which SlipMap does not use."""
    try:
        from distributed.gc import disable_gc_diagnosis

        disable_gc_diagnosis(force=True)
    except Exception:  # noqa: BLE001 - an older or newer distributed without it: harmless
        log.debug("Dask GC diagnosis left as it is", exc_info=True)


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored while local worker processes start: they inherit the disposition (a
    spawned Python keeps an ignored SIGINT ignored), so a terminal's Ctrl-C, which reaches
    the whole process group, interrupts only this process, which then closes them."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def _dask_quiet():
    """Dask's and Tornado's loggers silenced (shutdown after a failure or a Ctrl-C: closed
    connections are expected then and would print tracebacks)."""
    names = ("distributed", "tornado", "asyncio")
    saved = [(logging.getLogger(n), logging.getLogger(n).level) for n in names]
    for lg, _ in saved:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for lg, level in saved:
            lg.setLevel(level)


def _worker_log_level() -> int:
    """Local workers log errors only under ``--debug`` (the slipmap logger at DEBUG): their
    errors reach this process as the tasks' results anyway."""
    return (
        logging.WARNING
        if logging.getLogger("slipmap").isEnabledFor(logging.DEBUG)
        else (logging.CRITICAL)
    )


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
        self.client = None
        self.scheduler = scheduler
        with dask.config.set({"distributed.scheduler.allowed-failures": int(allowed_failures)}):
            try:
                if scheduler is not None:
                    scheduler = self.scheduler = check_scheduler_address(scheduler)
                    timeout = handshake_timeout_s()
                    if not scheduler.lower().startswith("inproc://"):
                        probe_scheduler(scheduler, timeout_s=timeout)
                    self.client = Client(scheduler, timeout=timeout)
                else:
                    n = int(workers)
                    if n < 1:
                        raise InvalidParameterError(f"workers must be >= 1, got {workers}")
                    n = clamp_workers(n)
                    with _sigint_ignored():
                        self.cluster = LocalCluster(
                            n_workers=n,
                            threads_per_worker=1,
                            processes=True,
                            memory_limit=memory_limit,
                            dashboard_address=":0",
                            silence_logs=_worker_log_level(),
                        )
                    _no_gc_diagnosis()
                    self.client = Client(self.cluster)
                self.n_workers = max(1, len(self.client.scheduler_info().get("workers", {})))
            except SlipMapError:
                self._close_quietly()
                raise
            except (OSError, TimeoutError) as exc:
                self._close_quietly()
                where = f"the Dask scheduler at {scheduler}" if scheduler else "a local cluster"
                raise ClusterError(
                    f"cannot start on {where} ({type(exc).__name__}: {exc}); check the "
                    "address and that the scheduler is running"
                    if scheduler
                    else f"cannot start {where} ({type(exc).__name__}: {exc}); run without "
                    "workers, or with fewer"
                ) from exc
            except BaseException:
                self._close_quietly()
                raise
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
        futures = []
        results: List[Any] = [None] * n
        done = 0
        own: Optional[BaseException] = None  # a task's own OSError, passed on unchanged
        try:
            futures = self.client.map(_call, [fn] * n, list(items), key=keys, pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            report(progress, 0.0, f"{n} {what}(s) on {self.describe()}")
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
                except (OSError, TimeoutError) as exc:
                    if fut.status == "error":  # the task's own exception: unchanged
                        own = exc
                        raise
                    raise self._cluster_error(exc, f"while {names[i]} ran") from exc
                if isinstance(value, _Failure):
                    _raise_failure(value)
                fut.release()  # the worker may drop it now
                results[i] = each(i, value) if each is not None else value
                done += 1
                report(progress, done / n, f"{what} {done}/{n}")
        except (OSError, TimeoutError) as exc:
            self._failed = True
            self._cancel(futures)
            if isinstance(exc, SlipMapError) or exc is own:
                raise
            raise self._cluster_error(exc, f"after {done} of {n} {what}(s)") from exc
        except BaseException:
            self._failed = True
            self._cancel(futures)
            raise
        finally:
            del futures
        return results

    _failed = False

    def _cancel(self, futures) -> None:
        with _dask_quiet(), contextlib.suppress(Exception):
            self.client.cancel(futures)

    def _cluster_error(self, exc: BaseException, when: str) -> ClusterError:
        where = f"the Dask scheduler at {self.scheduler}" if self.scheduler else "the local cluster"
        return ClusterError(
            f"the connection to {where} failed {when} ({type(exc).__name__}: {exc}); nothing "
            "was written. Check that the scheduler and its workers are running, then run again"
        )

    #: seconds the client and the local cluster get to close after a failure or a Ctrl-C
    #: (workers still starting may not answer; the user is waiting for the prompt)
    CLOSE_TIMEOUT_S = 10

    def _close_quietly(self) -> None:
        with _dask_quiet():
            for part in (self.client, self.cluster):
                if part is not None:
                    with contextlib.suppress(Exception):
                        part.close(timeout=self.CLOSE_TIMEOUT_S)

    def close(self) -> None:
        """Close the client and the local cluster; after a failure or a Ctrl-C, with Dask's
        loggers silenced (the closed connections are expected then)."""
        if self._failed:
            self._close_quietly()
            return
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self._failed = True
        self.close()


def make_engine(*, workers: Optional[int] = None, scheduler: Optional[str] = None) -> Engine:
    """The engine the options ask for: Dask with ``workers`` or ``scheduler``, else in-process.

    Raises
    ------
    InvalidParameterError
        Both given.
    OptionError
        ``scheduler`` cannot be an address (:func:`check_scheduler_address`).
    DependencyError
        Dask asked for but not installed.
    ClusterError
        The scheduler does not answer as a Dask scheduler within :func:`handshake_timeout_s`,
        or the local cluster cannot start.
    """
    if workers is not None and scheduler is not None:
        raise InvalidParameterError(
            "give either workers (a local Dask cluster) or a scheduler address, not both"
        )
    if workers is None and scheduler is None:
        return InProcess()
    if scheduler is not None:
        scheduler = check_scheduler_address(scheduler)
    return DaskEngine(workers=workers, scheduler=scheduler)
