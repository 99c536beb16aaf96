"""The task engine (:mod:`vsidgen.engine`): serial and on a small dask ``LocalCluster``."""

from __future__ import annotations

import os
import pathlib
import sys
import time

import pytest

from vsidgen.engine import Engine, TaskStatus


def _square(x):
    return x * x


def _fail(msg):
    raise ValueError(msg)


def _die_once(marker):
    """Kill the worker process the first time (no marker yet), succeed on the retry."""
    marker = pathlib.Path(marker)
    if not marker.exists():
        marker.write_text("died once")
        os._exit(1)
    return "second attempt"


def _die_always():
    os._exit(1)


def _sleep(s):
    time.sleep(s)
    return s


def _poll_until_stopped(name, limit):
    """A long task that ends itself once the stop flag ``name`` is raised."""
    from vsidgen.engine import stop_requested

    t0 = time.monotonic()
    while time.monotonic() - t0 < limit:
        if stop_requested(name):
            return "stopped"
        time.sleep(0.05)
    return "ran to its end"


def _quick_or_poll(key, name):
    return "quick" if key == "quick" else _poll_until_stopped(name, 150.0)


@pytest.fixture(autouse=True)
def _by_value():
    import cloudpickle
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def test_serial_outcomes_failures_and_deadline():
    seen = []
    with Engine(workers=1) as eng:
        assert eng.serial
        out = eng.run(_square, [("a", (3,)), ("b", (4,))], on_done=seen.append)
        assert [(o.key, o.status, o.value) for o in out] == [("a", TaskStatus.DONE, 9),
                                                           ("b", TaskStatus.DONE, 16)]
        bad = eng.run(_fail, [("x", ("boom",))])[0]
        assert bad.status is TaskStatus.FAILED and "boom" in bad.error
        late = eng.run(_square, [("c", (2,))], deadline=time.monotonic() - 1.0)[0]
        assert late.status is TaskStatus.CANCELLED and late.value is None
    assert [o.key for o in seen] == ["a", "b"]


def test_serial_stop_when_leaves_the_rest_unstarted():
    from vsidgen.engine import NOT_NEEDED, stop_requested

    ran = []
    with Engine(workers=1) as eng:
        out = eng.run(lambda k: ran.append(k) or k, [("a", ("a",)), ("b", ("b",)), ("c", ("c",))],
                      stop_when=lambda oc: oc.value == "b")
        eng.request_stop("nothing-to-do-serially")
    assert ran == ["a", "b"] and [o.status for o in out] == [TaskStatus.DONE, TaskStatus.DONE,
                                                             TaskStatus.CANCELLED]
    assert out[2].error == NOT_NEEDED
    assert not stop_requested("any")   # not on a worker


def test_local_cluster_results_failures_and_dead_workers(tmp_path):
    """Two worker processes: values in submission order, an exception stays with its task,
    a worker that dies once is retried (the task succeeds), one that dies every time loses
    only its own task, a decided run (``stop_when``) frees the workers at once, and a
    deadline cancels what has not finished (last: the cancelled sleep keeps its worker)."""
    with Engine(workers=2) as eng:
        assert not eng.serial and len(eng.client.scheduler_info()["workers"]) == 2
        client = eng.client
        with eng:           # re-entered (a command enters it before its results directory)
            assert eng.client is client
        assert eng.client is client      # the inner exit does not close the cluster
        out = eng.run(_square, [(f"k{i}", (i,)) for i in range(5)])
        assert [o.value for o in out] == [0, 1, 4, 9, 16]
        assert all(o.status is TaskStatus.DONE for o in out)
        bad = eng.run(_fail, [("x", ("boom",))])[0]
        assert bad.status is TaskStatus.FAILED and "boom" in bad.error
        once = eng.run(_die_once, [("once", (str(tmp_path / "marker"),))])[0]
        assert once.status is TaskStatus.DONE and once.value == "second attempt"
        eng.client.wait_for_workers(2, timeout=300)
        mixed = eng.run(lambda k: _die_always() if k == "dead" else k,
                        [("dead", ("dead",)), ("alive", ("alive",))],
                        deadline=time.monotonic() + 300.0)
        assert mixed[0].status is TaskStatus.LOST and mixed[1].value == "alive"
        # stop_when: the first outcome decides; the other task, already running on the second
        # worker, is cancelled and ends itself at its next poll of the stop flag, so both
        # workers are free again at once (the next run does not queue behind it)
        eng.client.wait_for_workers(2, timeout=300)
        from vsidgen.engine import NOT_NEEDED

        flag = f"vsidgen-test-stop-{os.getpid()}"

        def decided(oc):
            if oc.value == "quick":
                eng.request_stop(flag)
                return True
            return False

        t0 = time.monotonic()
        out = eng.run(_quick_or_poll, [("slow", ("slow", flag)), ("quick", ("quick", flag))],
                      stop_when=decided)
        assert out[1].value == "quick" and out[0].status is TaskStatus.CANCELLED
        assert out[0].error == NOT_NEEDED
        again = eng.run(_square, [("a", (2,)), ("b", (3,))])
        assert [o.value for o in again] == [4, 9] and time.monotonic() - t0 < 120.0
        eng.client.wait_for_workers(2, timeout=300)
        t0 = time.monotonic()
        slow = eng.run(_sleep, [("s2", (0.0,)), ("s1", (600.0,))], deadline=t0 + 30.0)
        assert time.monotonic() - t0 < 120.0
        assert slow[0].status is TaskStatus.DONE and slow[1].status is TaskStatus.CANCELLED
    assert eng.client is None and eng.cluster is None     # the outer exit closed it


def test_worker_env_single_thread_and_shared_compilation_cache(monkeypatch, tmp_path):
    import jax

    from vsidgen.engine import worker_env

    old = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    try:
        env = worker_env()
    finally:
        jax.config.update("jax_compilation_cache_dir", old)
    assert env["OMP_NUM_THREADS"] == "1" and "intra_op_parallelism_threads=1" in env["XLA_FLAGS"]
    assert env["JAX_COMPILATION_CACHE_DIR"] == str(tmp_path)


def test_existing_cluster_by_scheduler_address():
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as lc:
        with Engine(scheduler=lc.scheduler_address) as eng:
            assert not eng.serial and lc.scheduler_address in eng.describe()
            out = eng.run(_square, [("a", (5,)), ("b", (6,))])
            assert [o.value for o in out] == [25, 36]


def test_close_survives_a_shutdown_that_times_out():
    """A local cluster whose worker is still busy with a task cancelled at the deadline can
    time out while shutting down; the run's results are on disk by then, so closing the engine
    must not turn that into an error (it did: 'internal error: TimeoutError' after
    --time-limit)."""
    calls = []

    class Slow:
        def __init__(self, name):
            self.name = name

        def close(self, timeout=None):
            calls.append((self.name, timeout))
            raise TimeoutError("workers did not stop in time")

    eng = Engine(workers=2)
    eng.client, eng.cluster = Slow("client"), Slow("cluster")
    eng.close()
    assert [c for c, _ in calls] == ["client", "cluster"]
    assert all(t is not None and t > 0 for _, t in calls)
    assert eng.client is None and eng.cluster is None


def test_workers_bounded_by_the_machine():
    """--workers 100000 would start 100000 processes: refused with a hint to use a cluster."""
    from vsidgen.engine import max_local_workers
    from vsidgen.errors import VsidgenError

    with pytest.raises(VsidgenError, match="--scheduler"):
        Engine(workers=max_local_workers() + 1)
    assert Engine(workers=max_local_workers()).workers == max_local_workers()


@pytest.mark.parametrize("cores, workers", [(1, 1), (2, 1), (3, 1), (4, 2), (16, 8)])
def test_default_workers_one_per_two_usable_cores(monkeypatch, cores, workers):
    """Measured (docs/performance.md): on 2 cores the serial diagnose beat two workers
    (283 s against 329 s), on 16 cores eight workers were 1.69× faster than one."""
    from vsidgen import engine

    monkeypatch.setattr(engine.os, "sched_getaffinity", lambda pid: set(range(cores)),
                        raising=False)
    assert engine.usable_cores() == cores
    assert engine.default_workers() == workers
    assert Engine().workers == workers and Engine().serial == (workers == 1)


def _run_script(tmp_path, text: str):
    """Run ``text`` as a script in a fresh interpreter that imports this checkout's vsidgen
    (local dask workers need a ``__main__`` guard, so not in the test process)."""
    import subprocess

    script = tmp_path / "script.py"
    script.write_text(text)
    root = pathlib.Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=300, env=env, cwd=tmp_path)


CLOSE_SCRIPT = """
from vsidgen.engine import Engine

def task(x):
    import vsidgen.precision  # noqa: F401  (wraps the worker's gc callbacks, dask's too)
    return x * 2

if __name__ == "__main__":
    with Engine(workers=2) as e:
        print([o.value for o in e.run(task, [("a", (1,)), ("b", (2,))])])
"""


def test_workers_close_without_tracebacks(tmp_path):
    """Local workers that imported vsidgen close cleanly: dask removes its gc callback when a
    worker closes, and vsidgen's interrupt guard (:mod:`vsidgen.interrupts`) had wrapped it,
    so every closing worker printed ``ValueError: list.remove(x): x not in list`` with a
    traceback into the user's diagnose output."""
    p = _run_script(tmp_path, CLOSE_SCRIPT)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "[2, 4]" in p.stdout
    assert "Traceback" not in p.stderr and "not in list" not in p.stderr, p.stderr[-2000:]


LOG_SCRIPT = """
import logging
from vsidgen.engine import Engine

def task(x):
    logging.getLogger("distributed.worker").error("a dask record the user never sees")
    return logging.getLogger("distributed.worker").getEffectiveLevel()

if __name__ == "__main__":
    with Engine(workers=2) as e:
        print([o.value for o in e.run(task, [("a", (1,)), ("b", (2,))])])
"""


def test_local_workers_keep_dask_records_out_of_the_output(tmp_path):
    """dask's own ERROR records in a local worker never reach the user's output: a worker
    whose heartbeat raced the scheduler's shutdown printed two tracebacks at the end of a
    clean run (CI, once). ``silence_logs`` reaches only the nanny's logger in the worker
    process, so the level travels in the environment the worker is spawned with."""
    import logging

    p = _run_script(tmp_path, LOG_SCRIPT)
    assert p.returncode == 0, p.stderr[-2000:]
    assert f"[{logging.CRITICAL}, {logging.CRITICAL}]" in p.stdout, p.stdout
    assert "never sees" not in p.stderr, p.stderr[-2000:]
