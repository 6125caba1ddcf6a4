"""Choosing an executor by name: the one place that knows every kind.

``harness.execute`` has the run request, the local worker pool and the
in-process executor; ``harness.dask_executor`` the Dask one, built on the
worker pool.  Both are imported from here, so neither imports the other's
caller (tests/test_architecture.py::test_no_import_cycles).
"""

from __future__ import annotations

import os
from typing import Callable

from physbench.harness.execute import InlineExecutor, WorkerPool

#: executor names: ``serial`` is an alias of ``inline`` (no isolation)
EXECUTOR_KINDS = ("process", "inline", "serial", "dask")


def make_executor(kind: str = "process", jobs: int = 1, scheduler: str | None = None,
                  log: Callable[[str], None] | None = None):
    """``process``: a :class:`WorkerPool` of ``jobs`` workers; ``inline``
    (alias ``serial``): :class:`InlineExecutor`; ``dask``: a
    harness.dask_executor.DaskExecutor on the cluster at ``scheduler``, or
    on a LocalCluster of ``jobs`` workers (``log`` gets its description).
    A ``scheduler`` is only for ``dask``."""
    if scheduler and kind != "dask":
        raise ValueError(f"a scheduler address is for the dask executor, not {kind!r}")
    if kind == "process":
        return WorkerPool(jobs)
    if kind in ("inline", "serial"):
        return InlineExecutor()
    if kind == "dask":
        from physbench.harness.dask_executor import DaskExecutor

        return DaskExecutor(jobs, scheduler, log)
    raise ValueError(f"executor {kind!r}: expected one of {', '.join(EXECUTOR_KINDS)}")


def _sleep(seconds: float) -> float:
    """A task of a known wall time (s): the executor overhead benchmark's item."""
    import time

    time.sleep(seconds)
    return seconds


def thread_counts(_item: object = None) -> dict:
    """This process's thread pools: ``numba`` (numba.get_num_threads()),
    ``blas`` (threadpoolctl: {library: threads}) and the thread environment
    variables.  Mapped over an executor, what its run processes use."""
    import numba
    import threadpoolctl

    from physbench.harness.execute import ONE_THREAD_ENV

    return {"numba": numba.get_num_threads(),
            "blas": {f"{i['internal_api']} {i.get('version') or ''}".strip(): i["num_threads"]
                     for i in threadpoolctl.threadpool_info()},
            "env": {k: os.environ.get(k) for k in ONE_THREAD_ENV}}


def bench_overhead(kind: str = "process", jobs: int = 1, items: int = 200, task_s: float = 0.0,
                   log: Callable[[str], None] | None = None) -> dict:
    """Scheduler overhead per item of executor ``kind`` with ``jobs``
    workers: ``items`` tasks that each sleep ``task_s`` seconds, after one
    warm-up round; ``overhead_ms`` = (wall x jobs - items x task_s) / items,
    the worker time per item not spent in the task (ms; sleeping tasks, so
    the figure does not depend on how busy the cores are with other work).
    ``physbench bench executors``."""
    import time

    with make_executor(kind, jobs, log=log or (lambda _t: None)) as ex:
        list(ex.map(_sleep, [0.3] * (2 * ex.jobs)))  # start every worker and its run process
        t = time.perf_counter()
        list(ex.map(_sleep, [task_s] * items))
        wall = time.perf_counter() - t
    return {"executor": kind, "jobs": jobs, "items": items, "task_s": task_s, "wall_s": wall,
            "overhead_ms": 1e3 * (wall * jobs - items * task_s) / items}
