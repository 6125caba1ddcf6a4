"""physbench's own benchmarks of its execution path, apart from the run
path a user's command takes: the cost of isolating a run in a worker
process (``physbench bench isolation``), the executors' overhead per item
on sleeping tasks (``python -m physbench.harness.selfbench.sweep``)
and the thread pools a run process uses.  The sweep's scaling benchmark is
harness/selfbench/sweep.py.
"""

from __future__ import annotations

import os
import statistics
import time
from typing import Any, Callable

from physbench.harness.execute import ONE_THREAD_ENV, RunRequest, WorkerPool, execute_request, run_isolated, run_requests
from physbench.harness.executors import make_executor


def _noop(x: Any) -> Any:
    return x


def bench_isolation(runs: int = 50, scenario: str = "billiards.head_on", engine: str = "mujoco") -> dict[str, Any]:
    """Per-run cost of isolation (ms of wall time per run, medians): one
    ``engine`` run of ``scenario`` in this process, in a reused worker,
    and in a fresh worker per run; and the bare round trip of an empty item
    through a reused worker.  ``physbench bench isolation``."""
    req = RunRequest(scenario, engine, compute_metrics=True)
    execute_request(req)  # warm: imports, caches

    def timed(f: Callable[[], Any], n: int) -> float:
        ts = []
        for _ in range(n):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        return 1e3 * statistics.median(ts)

    inline = timed(lambda: execute_request(req), runs)
    with WorkerPool(1) as pool:
        list(pool.map(_noop, [0]))  # start the worker
        list(run_requests([req], pool))
        rt = timed(lambda: list(pool.map(_noop, [0])), runs)
        reused = timed(lambda: list(run_requests([req], pool)), runs)
    fresh = timed(lambda: run_isolated(req), max(3, runs // 5))
    return {"scenario": scenario, "engine": engine, "runs": runs, "in_process_ms": inline,
            "reused_worker_ms": reused, "fresh_worker_ms": fresh, "round_trip_ms": rt,
            "reused_overhead_ms": reused - inline, "fresh_overhead_ms": fresh - inline}


def sleep_task(seconds: float) -> float:
    """A task of a known wall time (s): the executor overhead benchmark's item."""
    time.sleep(seconds)
    return seconds


def thread_counts(_item: object = None) -> dict:
    """This process's thread pools: ``numba`` (numba.get_num_threads()),
    ``blas`` (threadpoolctl: {library: threads}) and the thread environment
    variables.  Mapped over an executor, what its run processes use."""
    import numba
    import threadpoolctl

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
    with make_executor(kind, jobs, log=log or (lambda _t: None)) as ex:
        list(ex.map(sleep_task, [0.3] * (2 * ex.jobs)))  # start every worker and its run process
        t = time.perf_counter()
        list(ex.map(sleep_task, [task_s] * items))
        wall = time.perf_counter() - t
    return {"executor": kind, "jobs": jobs, "items": items, "task_s": task_s, "wall_s": wall,
            "overhead_ms": 1e3 * (wall * jobs - items * task_s) / items}
