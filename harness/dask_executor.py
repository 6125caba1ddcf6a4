"""Sweeps and checks on a Dask cluster: ``--executor dask``.

:class:`DaskExecutor` has the interface of harness/execute.py's executors
(``map(fn, items, budget_s, on_start)`` yielding ``(item, value)`` as items
finish, ``value`` possibly a :class:`harness.execute.WorkerLost`), so
``physbench sweep`` and ``physbench check`` use it unchanged: rows stream
back to the client, which alone writes them (the same atomic parts, the same
resume).

- **Cluster.**  With ``scheduler`` (``--scheduler ADDRESS``) it joins that
  cluster; without, it starts a ``LocalCluster`` of ``jobs`` worker
  processes, one thread each, on 127.0.0.1, with BLAS held to one thread and
  a dashboard on 127.0.0.1 when bokeh is installed (else none).
- **Points are tasks, short ones batched.**  Each item -- or a
  :class:`harness.execute.Batch` of short points, about :data:`BATCH_S`
  seconds of expected work (harness/schedule.py) -- is one task keyed by
  its (first) point key (or a check run's key).  Inside the Dask worker the
  task runs in a :class:`harness.execute.WorkerPool` subprocess, so the
  watchdog is the local executor's, per item: an engine that hangs past
  the item's budget becomes ``timeout``, an abort or segfault ``error``
  naming the signal (a batch's other items keep their rows or run on), and
  the Dask worker itself survives both.  A Dask worker that dies (killed,
  out of memory, machine lost) costs its task: this client runs a batch's
  items again one by one (its finished rows were on that worker), an item
  alone once more; an item whose own task's worker dies a second time is
  an ``error`` row with the reason.  The scheduler should not retry by itself
  (``allowed-failures`` 0, as on the LocalCluster).
- **Feeding the cluster.**  Items are read as the cluster has room: one
  task per worker thread running and one more per thread waiting, the next
  submitted when a result comes back.  The waiting tasks wait *on the
  scheduler* (each is marked a data producer, which the scheduler queues
  on itself while ``worker-saturation`` is finite, as on the
  LocalCluster), so a free worker thread starts the next one without a
  round trip through this client, and a worker that dies holds only the
  task it runs: the retry-once rule charges no task it never started.
  Where the scheduler does not queue (``worker-saturation`` inf) or this
  Dask has no data-producer tasks, tasks are submitted one per thread
  (a round trip through the client per item).  Measured by
  harness/selfbench/sweep.py; results are gathered as tasks finish.
- **Environment check.**  Every worker reports its identity
  (:func:`worker_identity`: physbench commit, engine and library versions,
  BLAS, and its machine fingerprint).  A worker whose software differs from
  the client's is refused (:class:`EnvironmentRefused`): timings and bits
  would not compare.  The check runs on every worker at start and again in
  every task (a worker that joined later).  Rows are made on the worker,
  so their ``machine.*`` columns are the worker's.

Tests: tests/test_dask_executor.py.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import itertools
import os
import sys
import threading
from typing import Any, Callable, Iterable, Iterator

from physbench.harness.execute import (END, ONE_THREAD_ENV, WAIT, Batch, WorkerLost, WorkerPool, extra_adapters,
                             members, register_env_adapters, take)
from physbench.harness.fingerprint import fingerprint, package_version
from physbench.harness import runner  # runner.commit_id read at call time (tests pretend another commit)

#: Dask settings of the LocalCluster (its scheduler runs in this process, its
#: workers on the cores the run processes use): no retry by the scheduler for
#: a task whose worker died (the client retries, point by point); tasks queued on the scheduler (workers hold only the task
#: they run, so a death charges no queued task); and Dask's periodic work
#: per process -- the workers' statistical profiler (a stack sample every
#: 10 ms), the event-loop health tick (20 ms), the system monitor (0.5 s),
#: the nanny's memory poll (0.1 s) and work stealing (every 0.1 s; nothing
#: to steal with one task per thread) -- made rarer or off.  Measured in
#: docs/SWEEPS.md (Dask's own CPU on an idle cluster of 2 workers).
LOCAL_CLUSTER_CONFIG = {
    "distributed.scheduler.allowed-failures": 0,
    "distributed.scheduler.worker-saturation": 1.0,
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.scheduler.work-stealing": False,
}

#: expected seconds of work per task: points are batched up to it (harness/schedule.py), as Dask's
#: own guidance asks ("tasks of ~100 ms or more": a task costs ~1.5 ms of scheduler CPU)
BATCH_S = 0.1

#: the version pins an environment check compares (importlib.metadata names)
PACKAGES = ("numpy", "scipy", "numba", "mujoco", "pybullet", "pymunk", "threadpoolctl")


class EnvironmentRefused(RuntimeError):
    """A Dask worker runs another physbench environment than the client."""


# ---------------------------------------------------------------------------
# identity


@functools.lru_cache(maxsize=1)
def worker_identity() -> dict[str, Any]:
    """This process's environment: ``software`` (what must match between
    client and workers: physbench commit, Python, the physbench engine's
    version, library and engine package versions, BLAS libraries and
    versions) and ``machine`` (harness/fingerprint.py's flat summary: the
    hardware, which may differ and is carried in each row).  Engines are
    not imported (their package versions are read)."""

    fp = fingerprint()
    software = {"commit": runner.commit_id(), "python": fp["versions"]["python"],
                "physbench_engine": fp["versions"]["physbench_engine"],
                "blas": "; ".join(f"{b['library']} {b['version']}" for b in fp["blas"])}
    software.update({p: package_version(p) or "absent" for p in PACKAGES})
    return {"software": software, "machine": runner.machine_info(), "pid": os.getpid()}


def identity_diff(client: dict[str, Any], worker: dict[str, Any]) -> list[str]:
    """``key: client X, worker Y`` for each software field that differs."""
    a, b = client.get("software", {}), worker.get("software", {})
    return [f"{k}: client {a.get(k)!r}, worker {b.get(k)!r}" for k in sorted(set(a) | set(b))
            if a.get(k) != b.get(k)]


def refusal(address: str, diff: list[str]) -> str:
    return (f"dask worker {address} runs another physbench environment than this client ({'; '.join(diff)}): "
            "its timings and bits would not compare with the others'. Install the same physbench commit and "
            "engine versions on every worker (docs/SWEEPS.md), or stop that worker")


# ---------------------------------------------------------------------------
# the worker side

_LOCAL = threading.local()
_POOLS: list[WorkerPool] = []
_POOLS_LOCK = threading.Lock()


def _thread_pool(adapters: str, paths: tuple[str, ...]) -> WorkerPool:
    """This Dask worker thread's run process (a WorkerPool of one), created
    on first use and reused.  One per thread: a pool is not thread-safe, and
    a run process dies with the thread that started it (PR_SET_PDEATHSIG;
    Dask's executor threads live as long as the worker)."""
    key = (adapters, paths)
    pool = getattr(_LOCAL, "pool", None)
    if pool is not None and _LOCAL.key == key:
        return pool
    if pool is not None:
        _close(pool)
    for p in paths:
        if p not in sys.path:
            sys.path.append(p)
    if adapters:
        register_env_adapters(adapters)  # the pool hands them on to its process
    pool = WorkerPool(1)
    _LOCAL.pool, _LOCAL.key = pool, key
    with _POOLS_LOCK:
        _POOLS.append(pool)
    return pool


def _close(pool: WorkerPool) -> None:
    with _POOLS_LOCK:
        if pool in _POOLS:
            _POOLS.remove(pool)
    pool.close()


def close_pools() -> None:
    """Stop this Dask worker's run processes (the plugin's teardown)."""
    with _POOLS_LOCK:
        pools = list(_POOLS)
    for p in pools:
        _close(p)


def run_task(fn: Callable[[Any], Any], item: Any, budget: Any, client_identity: dict[str, Any],
             adapters: str, paths: tuple[str, ...]) -> tuple[Any, str]:
    """One item -- or a :class:`Batch` of items -- on a Dask worker: refuse
    if this worker's software differs from the client's, else run
    ``fn(item)`` in this thread's run process under the watchdog (a
    batch's items one after the other, each under its own budget:
    ``budget`` is then a tuple, one per item).  Returns (value or
    WorkerLost, worker address), for a batch (list of values, address);
    a WorkerLost carries this worker's machine summary."""
    from distributed import get_worker

    address = get_worker().address
    ident = worker_identity()
    diff = identity_diff(client_identity, ident)
    if diff:
        raise EnvironmentRefused(refusal(address, diff))
    pool = _thread_pool(adapters, paths)
    items = members(item)
    budgets = dict(zip(map(id, items), budget if isinstance(item, Batch) else (budget,)))
    # the pool yields a unit's items in their order (after a lost one, the rest run on in order)
    values = [v for _i, v in pool.map(fn, [item], budget_s=lambda i: budgets[id(i)])]
    for v in values:
        if isinstance(v, WorkerLost):
            v.machine = dict(ident["machine"])
    return (values if isinstance(item, Batch) else values[0]), address


def _identity_on_worker(dask_worker=None) -> dict[str, Any]:
    return {**worker_identity(), "address": dask_worker.address}


def _has_bokeh() -> bool:
    return importlib.util.find_spec("bokeh") is not None


def _scheduler_allowed_failures(dask_scheduler=None) -> int:
    return int(dask_scheduler.allowed_failures)


def _scheduler_queues(dask_scheduler=None) -> bool:
    """Whether the scheduler queues root-ish tasks on itself (a finite
    ``worker-saturation``) instead of sending them to workers at once."""
    import math

    return math.isfinite(float(dask_scheduler.WORKER_SATURATION))


def _queued_submit() -> Callable[..., Any] | None:
    """``submit(client, fn, *args, key=, priority=)`` making a task the
    scheduler queues on itself until a worker thread is free (a "data
    producer": root-ish whatever its group's size), or None where this
    Dask has no such task (then tasks are submitted one per thread)."""
    try:
        import uuid

        from dask._task_spec import Task
        from distributed.client import LLGExpr
        from distributed.spans import SpanMetadata

        Task("probe", len, (), _data_producer=True)
    except Exception:  # another Dask: no queued submission
        return None

    def submit(client: Any, fn: Callable[..., Any], *args: Any, key: str, priority: int = 0) -> Any:
        expr = LLGExpr({key: Task(key, fn, *args, _data_producer=True)}, _determ_token=uuid.uuid4().hex)
        return client._graph_to_futures(expr, [key], internal_priority={key: 0}, user_priority=priority,
                                        span_metadata=SpanMetadata(collections=[{"type": "Future"}]))[key]

    return submit


def _plugin():
    from distributed.diagnostics.plugin import WorkerPlugin

    class _Pools(WorkerPlugin):
        """Stops a worker's run processes when the worker closes."""

        idempotent = True
        name = "physbench-run-processes"

        def teardown(self, worker) -> None:
            close_pools()

    return _Pools()


# ---------------------------------------------------------------------------
# the client side


def _item_key(item: Any) -> str:
    """An item's readable key: a check run's ``run_key``, a point's ``key``."""
    for attr in ("run_key", "key"):
        v = getattr(item, attr, None)
        if isinstance(v, str):
            return v
    return repr(item)


class DaskExecutor:
    """Items as Dask tasks; see the module docstring.  ``log(text)`` gets
    the cluster's description (address, workers, dashboard)."""

    def __init__(self, jobs: int = 1, scheduler: str | None = None, log: Callable[[str], None] | None = None):
        import dask
        from distributed import Client, LocalCluster

        self.jobs = max(1, int(jobs))
        self.log = log or (lambda text: print(text, file=sys.stderr))
        self.cluster = None
        self.placement: dict[str, str] = {}
        self.dashboard: str | None = None
        self._seq = itertools.count()
        #: expected seconds of work per task (harness/schedule.py batches points up to it)
        self.batch_s = BATCH_S
        try:
            if scheduler:
                self.client = Client(scheduler, timeout="20s")
            else:
                with dask.config.set(LOCAL_CLUSTER_CONFIG):
                    self.cluster = LocalCluster(n_workers=self.jobs, threads_per_worker=1, processes=True,
                                                host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                                env=dict(ONE_THREAD_ENV), silence_logs=40)
                self.client = Client(self.cluster)
        except OSError as e:
            self._close_cluster()
            raise EnvironmentRefused(f"cannot reach the Dask scheduler {scheduler}: {e}") from None
        try:
            self._start(scheduler)
        except BaseException:
            self.close()
            raise

    def _start(self, scheduler: str | None) -> None:
        self.client.register_plugin(_plugin())
        self.identity = worker_identity()
        self.adapters, paths = extra_adapters()
        self.adapters_text = ",".join(f"{k}={v}" for k, v in self.adapters.items())
        self.paths = tuple(paths)
        self.workers = self.client.run(_identity_on_worker)
        if not self.workers:
            raise EnvironmentRefused(f"the Dask scheduler {scheduler} has no workers")
        refused = [refusal(a, d) for a, w in self.workers.items() if (d := identity_diff(self.identity, w))]
        if refused:
            raise EnvironmentRefused("\n".join(refused))
        ids = {w["machine"]["id"] for w in self.workers.values()}
        #: the workers' common machine id (None if they differ): a sweep's rows are filed under it
        self.machine_id = next(iter(ids)) if len(ids) == 1 else None
        info = self.client.scheduler_info()
        # the scheduler's HTTP server runs without bokeh too (health, metrics): a dashboard needs bokeh there
        if "dashboard" in info.get("services", {}) and self.client.run_on_scheduler(_has_bokeh):
            self.dashboard = self.client.dashboard_link
        #: runs at once: the workers' threads
        self.jobs = sum(int(w.get("nthreads", 1)) for w in info["workers"].values()) or len(self.workers)
        #: tasks submitted beyond the workers' threads: only tasks the scheduler queues on itself (a
        #: task sent to a worker ahead would be charged if that worker died, one it never started too:
        #: tests/test_dask_executor.py::test_a_dask_worker_killed_mid_run_is_retried_once_then_an_error_row)
        self._queued_submit = _queued_submit() if self.client.run_on_scheduler(_scheduler_queues) else None
        self.lookahead = self.jobs if self._queued_submit is not None else 0
        retries = self.client.run_on_scheduler(_scheduler_allowed_failures)
        where = f"scheduler {scheduler}" if scheduler else "LocalCluster on 127.0.0.1"
        self.log(f"dask: {where}, {len(self.workers)} workers ({self.jobs} threads) on {len(ids)} machine type(s); "
                 f"dashboard {self.dashboard or 'off (bokeh is not installed where the scheduler runs)'}")
        if retries != 0:
            self.log(f"note: the scheduler retries a task whose worker died {retries} times itself "
                     "(allowed-failures); physbench retries each point once and expects 0 (docs/SWEEPS.md)")
        if self.machine_id is None:
            self.log("note: the workers run on different machines: each row's machine.* columns name its own; "
                     "their timings do not compare with each other")

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], budget_s: Callable[[Any], float | None] = None,
            on_start: Callable[[Any], None] | None = None,
            priority: Callable[[Any], int] | None = None) -> Iterator[tuple[Any, Any]]:
        """Submit items as the cluster has room (its threads plus
        ``lookahead`` queued tasks), yield (item, value) as tasks finish;
        among queued tasks, the scheduler starts those of higher
        ``priority(item)`` first.
        ``items`` is read lazily and may yield :data:`WAIT` (nothing to
        run until a result is back).  Dask does not tell the client when a
        task starts: ``on_start(item)`` is called as its result arrives,
        just before it is yielded.  Raises EnvironmentRefused when a worker
        refuses (its item is not run); the rows yielded before stand."""
        from distributed import as_completed
        from distributed.scheduler import KilledWorker

        token = hashlib.sha256(os.urandom(8)).hexdigest()[:8]
        futures: dict[Any, Any] = {}
        done = as_completed(with_results=True, raise_errors=False)  # results gathered as tasks finish
        source, more = iter(items), True
        # items to submit again, alone, before the source's next: those of a batch whose worker died,
        # and an item whose worker died the first time (each runs once more; ids: retried already)
        again: list[Any] = []
        retried: set[int] = set()

        def submit(unit: Any) -> None:
            # unique even for items of equal keys: a repeated key would be one shared task
            k = f"physbench-{_item_key(unit)}-{token}-{next(self._seq)}"
            its = members(unit)
            budgets = tuple(budget_s(i) if budget_s else None for i in its)
            args = (fn, unit, budgets if isinstance(unit, Batch) else budgets[0], self.identity,
                    self.adapters_text, self.paths)
            prio = max(priority(i) for i in its) if priority else 0
            fut = None
            if self._queued_submit is not None:
                try:
                    fut = self._queued_submit(self.client, run_task, *args, key=k, priority=prio)
                except (TypeError, AttributeError, ImportError):
                    # the private graph API differs in this Dask: one task per thread from now on
                    self._queued_submit, self.lookahead = None, 0
            if fut is None:
                fut = self.client.submit(run_task, *args, key=k, pure=False, priority=prio)
            futures[fut] = unit
            done.add(fut)

        def fill() -> None:
            nonlocal more
            while (more or again) and len(futures) < self.jobs + self.lookahead:
                unit = again.pop(0) if again else take(source, bool(futures))
                if unit is END:
                    more = False
                elif unit is WAIT:
                    return
                else:
                    submit(unit)

        try:
            fill()
            while futures:
                fut, result = next(done)
                unit = futures.pop(fut)
                its = members(unit)
                try:
                    if fut.status == "error":  # result: (type, exception, traceback)
                        raise result[1]
                    if isinstance(result, BaseException):  # cancelled (from outside: not by this map)
                        raise RuntimeError(f"cancelled: {result!r}")
                    value, address = result
                    values = value if isinstance(unit, Batch) else [value]
                    for i in its:
                        self.placement[_item_key(i)] = address
                except EnvironmentRefused:
                    raise
                except KilledWorker as e:
                    last = getattr(e.last_worker, "address", "?")
                    if isinstance(unit, Batch) or id(unit) not in retried:
                        # the worker died: a batch's items run again one by one (its finished rows were on
                        # that worker, and which item it was running is not known here: each keeps its own
                        # retry), an item alone runs once more; its second death is the item's error row
                        if not isinstance(unit, Batch):
                            retried.add(id(unit))
                        again.extend(its)
                        fill()
                        continue
                    lost = WorkerLost("died", f"the Dask worker died while running this item, twice (retried once "
                                              f"on another worker; last {last}): killed from outside or out of "
                                              "memory, see that worker's log")
                    lost.machine = dict(self.workers.get(last, {}).get("machine") or {}) or None
                    values = [lost]
                except Exception as e:
                    values = [WorkerLost("raised", f"dask task failed: {type(e).__name__}: {e}")] * len(its)
                for i, v in zip(its, values):
                    if on_start:
                        on_start(i)
                    yield i, v
                fill()
        finally:
            if futures:  # interrupted or refused: nothing more of this map runs
                self.client.cancel(list(futures))

    def _close_cluster(self) -> None:
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None

    def close(self) -> None:
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
            self.client = None
        self._close_cluster()

    def __enter__(self) -> "DaskExecutor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


__all__ = ["DaskExecutor", "EnvironmentRefused", "worker_identity", "identity_diff", "run_task", "close_pools"]
