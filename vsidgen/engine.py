"""Independent tasks (diagnose refits, fleet fits) run serially or on ``dask.distributed``.

One :class:`Engine` runs a batch of independent tasks ``fn(*args)`` and gives back one
:class:`TaskOutcome` per task, in the order submitted:

* ``workers=1`` and no scheduler: the tasks run one after the other in this process (no
  pickling, no extra processes; the reference behaviour);
* otherwise a ``dask.distributed`` cluster: a :class:`~distributed.LocalCluster` of
  ``workers`` processes (default: one per two local cores) with one thread each, or the existing
  cluster at ``scheduler`` (``tcp://host:8786``). The tasks and their arguments must
  pickle (cloudpickle), and the files they read and write must be visible to every worker
  (a local cluster shares this machine's file system).

Each worker process runs one task at a time with JAX/XLA limited to one thread
(:data:`WORKER_ENV`), so ``N`` workers use ``N`` cores without oversubscription.

Failures stay per task: an exception inside a task gives :attr:`TaskStatus.FAILED` with the
message; a worker process that dies while running a task (crash, out of memory, killed)
loses only that task, which the scheduler runs once more on another worker
(``distributed.scheduler.allowed-failures = 1`` on a local cluster; an existing cluster
uses its own setting) and then reports as :attr:`TaskStatus.LOST`. Tasks that had not
finished when the ``deadline`` passed are :attr:`TaskStatus.CANCELLED` (a running task is
abandoned, not waited for). A KeyboardInterrupt cancels every pending task and propagates.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

#: environment of local worker processes: one compute thread per worker process
WORKER_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
}

#: how often a task is retried after its worker process died (local clusters)
WORKER_DEATH_RETRIES = 1
#: seconds to wait for a client / local cluster to shut down before giving up on it
CLOSE_TIMEOUT_S = 20
#: level of dask's own logging in local worker processes. Everything a task's user needs
#: comes back through its :class:`TaskOutcome` (an exception's message, a lost worker), so
#: dask's records are kept out of the user's output: at ERROR, a worker whose heartbeat
#: races the scheduler's shutdown logged ``Failed to communicate with scheduler during
#: heartbeat`` with two tracebacks at the end of a clean run (seen in CI, 1 run in many).
WORKER_LOG_LEVEL = logging.CRITICAL


class TaskStatus(enum.Enum):
    """How a task ended."""

    DONE = "done"              # returned a value
    FAILED = "failed"          # raised an exception (message in ``error``)
    LOST = "lost"              # its worker process died, also on the retry
    CANCELLED = "cancelled"    # not finished when the deadline passed


@dataclasses.dataclass(frozen=True)
class TaskOutcome:
    """One task's result: ``value`` when DONE, ``error`` (one line) otherwise."""

    key: str
    status: TaskStatus
    value: Any = None
    error: str | None = None
    wall_s: float = 0.0        # submission (or start, serially) to completion, seconds


def worker_env() -> dict[str, str]:
    """Environment of local worker processes: :data:`WORKER_ENV`, this process's
    ``PYTHONPATH``, and its persistent JAX compilation cache (the ``jax`` config when jax is
    imported, else ``$JAX_COMPILATION_CACHE_DIR``), so workers share compiled code."""
    import sys

    env = dict(WORKER_ENV)
    for k in ("PYTHONPATH", "JAX_COMPILATION_CACHE_DIR",
              "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "JAX_ENABLE_X64"):
        if k in os.environ:
            env[k] = os.environ[k]
    jax = sys.modules.get("jax")
    if jax is not None:
        try:
            cache = jax.config.jax_compilation_cache_dir
            if cache:
                env["JAX_COMPILATION_CACHE_DIR"] = str(cache)
                env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = str(
                    jax.config.jax_persistent_cache_min_compile_time_secs)
        except AttributeError:  # pragma: no cover - older jax
            pass
    return env


def add_engine_arguments(parser, *, what: str) -> None:
    """``--workers`` and ``--scheduler`` for a command whose independent ``what`` run on
    the engine (diagnose: candidate refits; fleet: record fits)."""
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help=f"run the {what} on a local dask cluster of N worker processes "
                             "(default: one per two local cores; 1 = serially in this "
                             "process)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help=f"run the {what} on an existing dask cluster (e.g. "
                             "tcp://host:8786; DIR must be on a file system its workers share)")


def max_local_workers() -> int:
    """Most worker processes of a local cluster: 4 per core (each runs one fit at a time;
    more only compete for the cores and memory)."""
    return 4 * (os.cpu_count() or 1)


def usable_cores() -> int:
    """Cores this process may use (``os.sched_getaffinity`` where available)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def default_workers() -> int:
    """One worker process per two usable cores (at least 1: serially in this process).

    A fit's XLA programs run on about 1.5 cores (the Hessian assembly is multi-threaded), and
    every worker process compiles the models of its own tasks. Measured with the CLI-default
    diagnose of a 1,000-sample HFB-320-like record (``benchmarks/bench_diagnose.py``): on the
    idle 2-core machine serially 283 s against 329 s with two workers; on 16 cores eight
    workers 1.69× faster than one (docs/performance.md)."""
    return max(1, usable_cores() // 2)


def _timed(fn, args):
    """Run ``fn(*args)`` on a worker; returns (value, seconds)."""
    t0 = time.perf_counter()
    return fn(*args), time.perf_counter() - t0


def error_line(err: BaseException) -> str:
    """A task's exception as one line: its type and the first line of its message."""
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")


class Engine:
    """Serial or ``dask.distributed`` execution of independent tasks (see the module docstring).

    Use as a context manager; a local cluster is started on entry and closed on exit::

        with Engine(workers=4) as eng:
            outcomes = eng.run(fn, [("a", (1,)), ("b", (2,))])

    Args:
        workers: worker processes of a local cluster (None: :func:`default_workers`);
            1 without ``scheduler`` runs serially in this process.
        scheduler: address of an existing dask scheduler (then ``workers`` is ignored).
    """

    def __init__(self, *, workers: int | None = None, scheduler: str | None = None):
        if workers is not None and workers < 1:
            from .errors import VsidgenError
            raise VsidgenError(f"--workers must be >= 1, got {workers}")
        if workers is not None and workers > max_local_workers():
            from .errors import VsidgenError
            raise VsidgenError(f"--workers {workers} is more than this machine can run "
                               f"(at most {max_local_workers()}: 4 per core)\n  hint: for more, "
                               "start a dask cluster and pass --scheduler ADDRESS")
        self.workers = default_workers() if workers is None else int(workers)
        if scheduler is not None:
            # refused before anything is written ('garbage address', 'tcp://[::1')
            from distributed.comm.addressing import parse_address, parse_host_port

            from .errors import VsidgenError
            try:
                proto, loc = parse_address(scheduler)
                if proto in ("tcp", "tls", "ws", "wss"):
                    parse_host_port(loc)
            except (ValueError, TypeError) as err:
                raise VsidgenError(f"cannot start or reach the dask cluster ({scheduler}): "
                                   f"not a scheduler address ({err})\n  hint: give it as "
                                   "tcp://HOST:PORT") from None
        self.scheduler = scheduler
        self.client = None
        self.cluster = None
        self._depth = 0

    @property
    def serial(self) -> bool:
        return self.scheduler is None and self.workers == 1

    def describe(self) -> str:
        if self.scheduler is not None:
            return f"dask cluster at {self.scheduler}"
        if self.serial:
            return "serial (this process)"
        return f"local dask cluster of {self.workers} worker processes"

    def __enter__(self) -> Engine:
        """Start or reach the cluster. Re-entrant: a command enters it before it touches its
        results directory (an unreachable ``--scheduler`` must not cost the previous results:
        red team, session 47), and the run inside enters it again; the cluster closes when
        the outermost ``with`` ends."""
        if self.serial:
            return self
        if self._depth:
            self._depth += 1
            return self
        import dask
        from distributed import Client, LocalCluster

        from .errors import VsidgenError

        try:
            if self.scheduler is not None:
                self.client = Client(self.scheduler, timeout="20s")
            else:
                env = worker_env()
                # one task at a time per worker process (saturation 1): a dying worker
                # takes only the task it was running with it
                # dask's logging is set up when a worker process imports distributed, from
                # the environment it is spawned with (silence_logs reaches only the nanny's
                # logger there, not the worker's)
                spawn_env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
                spawn_env["DASK_LOGGING__DISTRIBUTED"] = logging.getLevelName(WORKER_LOG_LEVEL)
                with dask.config.set({"distributed.scheduler.allowed-failures":
                                      WORKER_DEATH_RETRIES,
                                      "distributed.scheduler.worker-saturation": 1.0,
                                      "distributed.nanny.pre-spawn-environ": spawn_env}):
                    self.cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1,
                                                processes=True, dashboard_address=None,
                                                silence_logs=WORKER_LOG_LEVEL, env=env)
                    self.client = Client(self.cluster)
        except (OSError, TimeoutError, ValueError, TypeError) as err:
            # ValueError/TypeError: an address dask cannot parse ('garbage address', 'tcp://[::1')
            self.close()
            raise VsidgenError(f"cannot start or reach the dask cluster "
                               f"({self.scheduler or 'local'}): {err}") from None
        self._depth = 1
        return self

    def __exit__(self, *exc) -> None:
        if self._depth > 1:
            self._depth -= 1
            return
        self._depth = 0
        self.close()

    def close(self) -> None:
        """Disconnect, and stop a local cluster. Shutting down can time out while a worker is
        still busy with a task cancelled at a deadline; everything the run found is already on
        disk by then, so a slow shutdown is not an error of the run (the worker processes of a
        local cluster are terminated with it)."""
        if self.client is not None:
            try:
                self.client.close(timeout=CLOSE_TIMEOUT_S)
            except (TimeoutError, OSError, RuntimeError):
                pass
            self.client = None
        if self.cluster is not None:
            try:
                self.cluster.close(timeout=CLOSE_TIMEOUT_S)
            except (TimeoutError, OSError, RuntimeError):
                pass
            self.cluster = None

    def run(self, fn: Callable, tasks: Sequence[tuple[str, tuple]], *,
            deadline: float | None = None,
            on_done: Callable[[TaskOutcome], None] | None = None,
            stop_when: Callable[[TaskOutcome], bool] | None = None) -> list[TaskOutcome]:
        """Run ``fn(*args)`` for every ``(key, args)``; outcomes in the order of ``tasks``.

        ``deadline`` is a :func:`time.monotonic` instant: serially, no task starts after
        it; on a cluster, tasks not finished by then are cancelled. ``on_done`` is called
        in this process as each task ends (completion order). ``stop_when``: called with
        each outcome as it arrives; when it returns True the tasks not yet finished are
        not needed: serially they are not started, on a cluster they are cancelled (their
        outcome ``CANCELLED``, error :data:`NOT_NEEDED`). A task already running on a
        worker is not interrupted by dask; a task that polls :func:`stop_requested` with a
        name the caller passes to :meth:`request_stop` can end itself early.
        """
        if self.serial:
            return self._run_serial(fn, tasks, deadline, on_done, stop_when)
        return self._run_dask(fn, tasks, deadline, on_done, stop_when)

    def request_stop(self, name: str) -> None:
        """Raise the stop flag ``name`` (a ``distributed.Event``) that running tasks poll
        with :func:`stop_requested`; nothing to do serially (tasks run one at a time)."""
        if self.client is None:
            return
        from distributed import Event

        try:
            Event(name, client=self.client).set()
        except (OSError, TimeoutError, RuntimeError):
            pass   # best effort: the task then runs to its own end

    @staticmethod
    def _emit(on_done, oc):
        if on_done is not None:
            on_done(oc)
        return oc

    def _run_serial(self, fn, tasks, deadline, on_done, stop_when=None):
        out = []
        stopped = False
        for key, args in tasks:
            if stopped:
                out.append(self._emit(on_done, TaskOutcome(key, TaskStatus.CANCELLED,
                                                           error=NOT_NEEDED)))
                continue
            if deadline is not None and time.monotonic() >= deadline:
                out.append(self._emit(on_done, TaskOutcome(key, TaskStatus.CANCELLED,
                                                           error="time limit reached")))
                continue
            t0 = time.perf_counter()
            try:
                value = fn(*args)
            except Exception as err:  # noqa: BLE001 - a task's failure is its own outcome
                oc = TaskOutcome(key, TaskStatus.FAILED, error=error_line(err),
                                 wall_s=time.perf_counter() - t0)
            else:
                oc = TaskOutcome(key, TaskStatus.DONE, value=value,
                                 wall_s=time.perf_counter() - t0)
            out.append(self._emit(on_done, oc))
            stopped = stop_when is not None and bool(stop_when(oc))
        return out

    def _run_dask(self, fn, tasks, deadline, on_done, stop_when=None):
        from distributed import as_completed
        from distributed.client import FutureCancelledError
        from distributed.scheduler import KilledWorker

        t0 = time.perf_counter()
        futures = {}
        for i, (key, args) in enumerate(tasks):
            f = self.client.submit(_timed, fn, args, pure=False,
                                   key=f"vsidgen-{i}-{key}-{os.urandom(4).hex()}")
            futures[f.key] = (i, key, f)
        results: dict[int, TaskOutcome] = {}
        why = "time limit reached"
        ac = as_completed([f for _, _, f in futures.values()])
        try:
            while len(results) < len(tasks):
                timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
                try:
                    f = next(ac) if timeout is None else _next_within(ac, timeout)
                except TimeoutError:
                    break
                i, key, _ = futures[f.key]
                try:
                    value, wall = f.result()
                    oc = TaskOutcome(key, TaskStatus.DONE, value=value, wall_s=wall)
                except KilledWorker as err:
                    oc = TaskOutcome(key, TaskStatus.LOST, wall_s=time.perf_counter() - t0,
                                     error=f"worker process died twice running this task ({err})"
                                     .splitlines()[0])
                except FutureCancelledError:
                    oc = TaskOutcome(key, TaskStatus.CANCELLED, error="cancelled")
                except Exception as err:  # noqa: BLE001 - the task's own exception
                    oc = TaskOutcome(key, TaskStatus.FAILED, error=error_line(err),
                                     wall_s=time.perf_counter() - t0)
                results[i] = self._emit(on_done, oc)
                if stop_when is not None and stop_when(oc):
                    why = NOT_NEEDED
                    break
        except BaseException:
            self.client.cancel([f for _, _, f in futures.values()])
            raise
        pending = [f for i, _, f in futures.values() if i not in results]
        if pending:
            self.client.cancel(pending)
        for i, key, _ in sorted(futures.values(), key=lambda v: v[0]):
            if i not in results:
                results[i] = self._emit(on_done, TaskOutcome(key, TaskStatus.CANCELLED,
                                                             error=why))
        return [results[i] for i in range(len(tasks))]


#: error of a task cancelled because ``stop_when`` decided without it
NOT_NEEDED = "not needed: an earlier outcome decided"


def stop_requested(name: str) -> bool:
    """In a task on a dask worker: has :meth:`Engine.request_stop` raised the flag
    ``name``? False outside a worker (serial runs) and when the scheduler cannot be asked."""
    try:
        from distributed import Event, get_worker

        get_worker()
    except (ImportError, ValueError):
        return False
    try:
        return bool(Event(name).is_set())
    except (OSError, TimeoutError, RuntimeError, ValueError):
        return False


def _next_within(ac, timeout: float):
    """Next completed future of an ``as_completed`` iterator, waiting at most ``timeout`` s."""
    end = time.monotonic() + timeout
    while True:
        if ac.has_ready():
            return next(ac)
        if ac.is_empty():
            raise StopIteration
        if time.monotonic() >= end:
            raise TimeoutError
        time.sleep(min(0.05, max(0.0, end - time.monotonic())))


def terminate_as_interrupt():
    """Context manager: SIGTERM raises KeyboardInterrupt (so a terminated run writes what it
    has, as on Ctrl-C); the previous handler is restored on exit. No-op off the main thread."""
    import contextlib
    import signal
    import threading

    @contextlib.contextmanager
    def cm():
        if threading.current_thread() is not threading.main_thread():
            yield
            return

        def handler(signum, frame):
            raise KeyboardInterrupt(f"signal {signum}")

        old = signal.signal(signal.SIGTERM, handler)
        try:
            yield
        finally:
            signal.signal(signal.SIGTERM, old)
    return cm()
