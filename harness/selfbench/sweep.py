"""How a sweep scales with workers: ``python -m physbench.harness.selfbench.sweep``.

Runs one suite (default: the nightly, points and ``[[limit]]`` searches)
fresh with each executor and worker count, one after the other into one
temporary directory (so each run but the first orders its items longest
first by the one before: harness/schedule.py), and prints for each run:

- ``wall_s``: the sweep's wall time, process start-up to consolidated file;
- ``cpu_s``: CPU time of this process and every process it started
  (workers, run processes, a LocalCluster's scheduler and workers;
  ``getrusage``), so ``cpu_s / wall_s`` is how many cores it kept busy;
- ``busy_s``: the rows' ``point_wall_s`` summed (points and search
  evaluations): time the run processes spent on items;
  ``idle = 1 - busy_s / (jobs x wall_s)``: the workers' share of the wall
  time spent not running an item (start-up, scheduling round trips, and a
  tail where some worker has nothing left to run);
- ``step_cpu_s`` / ``step_wall_s``: the engines' stepping (first run of
  each item), CPU and wall; ``wait = step_wall / step_cpu - 1``: how long a
  run process waited for a core while stepping (the machine's other load);
  ``step_cpu_s`` growing from 1 to 2 workers is each core doing less
  (shared caches, memory bandwidth, clock);
- ``speedup``: the 1-worker wall time of the same executor over this one;
- ``account``: CPU seconds by role (:class:`CpuAccount`, sampled with
  psutil, Dask's own dependency): this process's main thread (the sweep's
  loop, start-up, the merge), its part-writer thread, its other threads (a
  LocalCluster's scheduler, nannies and comms, and the sampler itself), the
  Dask worker processes and the run processes.

Then the client's CPU per stored row (:func:`store_costs`: a part written
and merged the pandas way and the Arrow way, on the 1-worker run's rows),
the scheduler overhead per item of each executor (sleeping tasks,
harness.selfbench.executors.bench_overhead) and the thread pools of its run processes
(harness.selfbench.executors.thread_counts).  Timings of a shared machine are noisy:
compare ``cpu_s`` and ``idle`` as well as the wall time, and rerun on a
quiet machine for the figures in docs/SWEEPS.md.  Example::

    python -m physbench.harness.selfbench.sweep --suite nightly --executors process dask --jobs 1 2 --json out.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import resource
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any
from physbench.harness.sweep import sweep_main
from physbench.harness.sweep_store import sweep_files
from physbench.harness import schedule, sweep
from physbench.harness.schedule import run_schedule
from physbench.harness.suite import expand, load_suite, scenario_label
from physbench.harness.execute import WorkerPool
from physbench.harness.points import cached_scene, run_point
from physbench.harness.schedule import model_cost
from physbench.harness.results import PartsDir, consolidate_parts, list_parts, write_json_atomic, write_parquet_atomic
from physbench.harness.selfbench.executors import bench_overhead, thread_counts
from physbench.harness.executors import make_executor
from physbench.harness.sweep_store import PART_WRITER
from physbench.harness.execute import END, WAIT, take


def _cpu() -> float:
    """CPU seconds (user + system) of this process and its waited-for descendants."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


class CpuAccount:
    """CPU seconds (user + system) by role while it is entered: this
    process's main thread, its part-writer thread, its other threads, and
    its descendants by kind (Dask worker processes, run processes, other)
    and, apart, the sampler thread's own CPU (``sampler``: no part of the
    sweep; it counted as ``other threads`` before),
    sampled every ``dt`` seconds (a process's CPU up to its last sample;
    processes that exist at entry count from there).  ``report()`` is a
    dict of role -> CPU s, ``wall_s`` and ``cores`` (the CPU cores this
    machine has)."""

    def __init__(self, dt: float = 0.2):
        import psutil

        self.dt, self._stop = dt, threading.Event()
        self.me = psutil.Process()
        self.main = threading.main_thread().native_id
        self.first: dict[Any, float] = {}
        self.last: dict[Any, float] = {}
        self.kind: dict[Any, str] = {}
        self.threads0 = self._threads()
        self.threads: dict[int, float] = dict(self.threads0)
        self.writers: set[int] = set()
        self._thread = threading.Thread(target=self._loop, name="physbench-cpu-account", daemon=True)

    def _threads(self) -> dict[int, float]:
        return {t.id: t.user_time + t.system_time for t in self.me.threads()}

    @staticmethod
    def _kind(cmdline: str) -> str:
        if "worker_main" in cmdline:
            return "run processes"
        if "multiprocessing" in cmdline:
            return "dask worker processes"
        return "other processes"

    def sample(self, start: bool = False) -> None:
        import psutil

        for p in self.me.children(recursive=True):
            try:
                k = (p.pid, p.create_time())
                c = p.cpu_times()
                if k not in self.kind:
                    self.first[k] = c.user + c.system if start else 0.0
                if self.kind.get(k, "other processes") == "other processes":
                    # asked again until it is known: a process sampled between its fork and its exec still
                    # shows this process's command line
                    self.kind[k] = self._kind(" ".join(p.cmdline()))
                self.last[k] = c.user + c.system
            except psutil.Error:
                pass
        self.threads.update(self._threads())
        self.writers |= {t.native_id for t in threading.enumerate() if t.name == PART_WRITER}

    def _loop(self) -> None:
        while not self._stop.wait(self.dt):
            self.sample()

    def __enter__(self) -> "CpuAccount":
        self.t0 = time.perf_counter()
        self.sample(start=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.sample()
        self._stop.set()
        self._thread.join()
        self.wall = time.perf_counter() - self.t0

    def report(self) -> dict[str, float]:
        def used(tid: int) -> float:
            return self.threads[tid] - self.threads0.get(tid, 0.0)

        me = self._thread.native_id  # the sampler: the measurement's own CPU, no part of the sweep's
        out = {"main thread": used(self.main) if self.main in self.threads else 0.0,
               "part writer": sum(used(t) for t in self.threads if t in self.writers),
               "other threads": sum(used(t) for t in self.threads
                                    if t != self.main and t not in self.writers and t != me),
               "sampler": used(me) if me in self.threads else 0.0}
        for kind in ("dask worker processes", "run processes", "other processes"):
            out[kind] = sum(self.last[k] - self.first[k] for k in self.kind if self.kind[k] == kind)
        out["wall_s"] = self.wall
        out["cores"] = float(os.cpu_count() or 0)
        return out


def measure(root: Path, suite: str, executor: str, jobs: int, engines: list[str] | None = None,
            scenarios: list[str] | None = None, scheduler: str | None = None) -> dict[str, Any]:
    """One fresh sweep of ``suite`` with ``executor`` x ``jobs`` under
    ``root`` (its earlier sweeps there give the longest-first order); the
    figures of the module docstring.  ``scheduler``: a Dask cluster's
    address (``dask`` only; its scheduler's and workers' CPU is then not
    this machine's, and not counted)."""
    import pandas as pd

    units: list[int] = []
    loop: list[float] = []
    real_batched, real_schedule = schedule.batched, sweep.run_schedule

    def counted(*a: Any, **kw: Any) -> list[Any]:  # the executor's units of points (tasks, with Dask)
        out = real_batched(*a, **kw)
        units.append(len(out))
        return out

    def timed(*a: Any, **kw: Any) -> None:  # the main thread's CPU in the sweep's loop, apart from start and end
        c = time.thread_time()
        try:
            real_schedule(*a, **kw)
        finally:
            loop.append(time.thread_time() - c)

    load = os.getloadavg()[0]
    c0, t0 = _cpu(), time.perf_counter()
    schedule.batched, sweep.run_schedule = counted, timed
    try:
        with CpuAccount() as account:
            rc = sweep_main(suite, engines=engines, jobs=jobs, executor=executor, out_dir=root, resume=False,
                            scenarios=scenarios, scheduler=scheduler)
    finally:
        schedule.batched, sweep.run_schedule = real_batched, real_schedule
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    newest = max((f for *_m, f, done in sweep_files(root, unfinished=False) if done), key=lambda f: f.stem)
    df = pd.read_parquet(newest)
    if rc != 0:
        raise RuntimeError(f"sweep {suite} on {executor} x{jobs} exited {rc}")

    def total(col: str) -> float:
        return float(pd.to_numeric(df[col], errors="coerce").fillna(0.0).sum()) if col in df else math.nan

    busy = total("point_wall_s")
    step_cpu, step_wall = total("timing.step_cpu_s"), total("timing.step_wall_s")
    kind = df["row_kind"] if "row_kind" in df else pd.Series([None] * len(df))
    evaluations = int((kind == "limit_eval").sum())
    return {"executor": executor, "jobs": jobs, "points": int(kind.isna().sum()),
            "evaluations": evaluations, "searches": int((kind == "limit").sum()),
            "tasks": sum(units) + evaluations if units else None, "loop_cpu_s": sum(loop),
            "errors": int(df["status"].isin(["error", "timeout"]).sum()),
            "wall_s": wall, "cpu_s": cpu, "cores_busy": cpu / wall, "busy_s": busy,
            "idle": 1.0 - busy / (jobs * wall), "step_cpu_s": step_cpu, "step_wall_s": step_wall,
            "wait": step_wall / step_cpu - 1.0 if step_cpu > 0 else math.nan, "sweep_file": str(newest),
            "load_before": load, "load_after": os.getloadavg()[0], "account": account.report()}


class VirtualExecutor:
    """``jobs`` workers in virtual time, for replaying a schedule: an item
    takes ``duration(item)`` seconds and its value is ``answer(item)``
    (``fn`` is not called).  Records when each item started (``started``),
    when the source said WAIT (``waits``), the worker seconds spent on
    items (``busy``) and the ``makespan``.  Tests: tests/test_schedule.py."""

    def __init__(self, jobs: int, duration: Any, answer: Any):
        self.jobs, self.duration, self.answer = jobs, duration, answer
        self.started: list[tuple[float, Any]] = []
        self.waits: list[float] = []
        self.busy = 0.0
        self.makespan = 0.0

    def map(self, fn: Any, items: Any, budget_s: Any = None, on_start: Any = None, priority: Any = None):
        import heapq
        import itertools

        source, more, now, seq = iter(items), True, 0.0, itertools.count()
        running: list = []
        while more or running:
            while more and len(running) < self.jobs:
                item = take(source, bool(running))
                if item is END:
                    more = False
                if item is WAIT:
                    self.waits.append(now)
                if item is END or item is WAIT:
                    break
                self.started.append((now, item))
                if on_start:
                    on_start(item)
                heapq.heappush(running, (now + self.duration(item), next(seq), item))
            if running:
                now, _, item = heapq.heappop(running)
                self.busy += self.duration(item)
                yield item, self.answer(item)
        self.makespan = now

    @property
    def idle(self) -> float:
        """Worker seconds not spent on an item, over the makespan."""
        return self.jobs * self.makespan - self.busy


def _list_schedule(durations: list[float], jobs: int) -> float:
    """Makespan of jobs taken in order by the first free of ``jobs`` workers."""
    import heapq

    free = [0.0] * jobs
    for d in durations:
        heapq.heapreplace(free, free[0] + d)
    return max(free)


def replay(sweep: Any, suite: str, jobs: int = 2, engines: list[str] | None = None,
           scenarios: list[str] | None = None) -> dict[str, float]:
    """The makespan on ``jobs`` uncontended workers of a sweep's items,
    each taking the wall time it took in ``sweep`` (a DataFrame of a
    finished sweep of ``suite``, best a 1-worker one; the searches take the
    same path, their verdicts read from its rows, in rounds as wide as the
    virtual workers allow: a value the stored search did not evaluate holds
    on its limit's side and takes the mean time of its evaluations):
    ``total_s`` (all items,
    one worker), ``ideal_s`` (total / jobs), ``new_s``
    (harness/schedule.py's order and rounds), ``narrow_s`` (the same, every
    search one value at a time: the schedule before wide rounds), ``work_s`` (the worker
    seconds it spent: total and a wide round's extra evaluations),
    ``old_s`` (the points in planned order, then the searches, ``jobs`` at
    a time, each one value at a time: the path before), and the speed-ups
    total / new, total / old: what the schedule allows before any
    contention or overhead.  The
    new order knows the items' times (as a sweep does from the one before
    it)."""
    import math

    s = load_suite(suite)
    points = expand(s, engines, scenarios)
    reqs = [r for r in s.limits if (engines is None or r.engine in engines)
            and (scenarios is None or r.scenario in scenarios or scenario_label(r.scenario, r.variant) in scenarios)]
    records = sweep.to_dict("records")
    rows = {r["point_key"]: r for r in records}
    # a wide round's values the stored (serial) search did not evaluate: they hold on the limit's side of
    # its bracket and take the mean time of its stored evaluations; the search's decisions never read them
    summaries = {r["limit_id"]: r for r in records if r.get("row_kind") == "limit"}
    mean_s: dict[str, list[float]] = {}
    for r in records:
        if r.get("row_kind") == "limit_eval" and math.isfinite(w := float(r.get("point_wall_s", math.nan))):
            mean_s.setdefault(r["limit_id"], []).append(w)

    def modelled(req: Any) -> dict[str, Any]:
        item = req.probe
        s = summaries.get(item.limit_id, {})
        limit, outcome = s.get("limit_value", math.nan), s.get("limit_outcome")
        holds = outcome == "holds_throughout" or (outcome == "found" and (
            item.value <= limit if s.get("limit_direction") == "below" else item.value >= limit))
        ws = mean_s.get(item.limit_id, [0.0])
        return {"point_key": req.key, "limit_value": item.value, "phase": item.phase, "limit_holds": bool(holds),
                "limit_reason": "" if holds else "modelled", "limit_cpu_s": 0.0, "status": "ok",
                "point_wall_s": sum(ws) / len(ws)}

    def duration(item: Any) -> float:
        w = float((rows.get(item.key) or modelled(item))["point_wall_s"])
        return w if math.isfinite(w) else 0.0

    def answer(item: Any) -> dict[str, Any]:
        return dict(rows.get(item.key) or modelled(item))

    total = sum(duration(p) for p in points)
    search_s: dict[int, float] = {}

    def done(req: Any, res: Any, _summary: dict[str, Any]) -> None:
        pass

    ex = VirtualExecutor(1, duration, answer)
    run_schedule(ex, [], reqs, lambda p, r: None, done, lambda r: None)
    for _t, item in ex.started:  # each search's chain, one worker: its total
        search_s[id(item.probe.req)] = search_s.get(id(item.probe.req), 0.0) + duration(item)
    chains = [search_s.get(id(r), 0.0) for r in reqs]
    total += sum(chains)
    by_req = {id(r): c for r, c in zip(reqs, chains)}

    new = VirtualExecutor(jobs, duration, answer)
    run_schedule(new, points, reqs, lambda p, r: None, done, lambda r: None,
                 point_cost=duration, search_cost=lambda r: by_req.get(id(r), 0.0))
    narrow = VirtualExecutor(jobs, duration, answer)
    run_schedule(narrow, points, reqs, lambda p, r: None, done, lambda r: None,
                 point_cost=duration, search_cost=lambda r: by_req.get(id(r), 0.0), wide_rounds=False)
    old_points = VirtualExecutor(jobs, duration, answer)
    run_schedule(old_points, points, [], lambda p, r: None, done, lambda r: None)
    old = old_points.makespan + _list_schedule(chains, jobs)
    ideal = total / jobs
    return {"jobs": jobs, "points": len(points), "searches": len(reqs), "evaluations": len(ex.started),
            "total_s": total, "ideal_s": ideal, "new_s": new.makespan, "narrow_s": narrow.makespan,
            "old_s": old, "work_s": new.busy,
            "longest_search_s": max(chains, default=0.0), "longest_point_s": max(map(duration, points), default=0.0),
            "speedup_new": total / new.makespan if new.makespan else math.nan,
            "speedup_narrow": total / narrow.makespan if narrow.makespan else math.nan,
            "speedup_old": total / old if old else math.nan}


def core_scaling(copies: int = 2, rounds: int = 3, scenario: str = "stacking.column_5",
                 engine: str = "reference") -> dict[str, Any]:
    """CPU per simulated second of one sweep point (the suite nightly's
    most expensive ``engine`` point of ``scenario``) run alone, then as
    ``copies`` copies at once, each in its own run process, ``rounds``
    times (medians of the points' ``cpu_s_per_sim_s_median``).  ``ratio`` =
    together / alone: above 1, each core does less when all run (shared
    caches and memory bandwidth, clock, or vCPUs that share a physical
    core); ``copies / ratio`` bounds the speed-up any schedule reaches."""
    import statistics

    pts = expand(load_suite("nightly"), [engine], [scenario])
    point = max(pts, key=lambda p: model_cost(cached_scene(p.scenario, p.variant), p.engine_settings.get("dt"), p.repeats))

    def cpu(pool: WorkerPool, n: int) -> list[float]:
        return [float(r["cpu_s_per_sim_s_median"]) for _p, r in pool.map(run_point, [point] * n)]

    with WorkerPool(1) as pool:
        cpu(pool, 1)  # warm: imports, compiled kernels from the cache
        alone = statistics.median(cpu(pool, rounds))
    with WorkerPool(copies) as pool:
        cpu(pool, copies)
        together = statistics.median(cpu(pool, copies * rounds))
    return {"point": point.key, "copies": copies, "alone_cpu_s_per_sim_s": alone,
            "together_cpu_s_per_sim_s": together, "ratio": together / alone, "bound": copies * alone / together}


def store_costs(rows: list[dict[str, Any]], limit: int = 2000, batch: int = 32) -> dict[str, Any]:
    """The client's CPU per row for storing ``rows`` (a finished sweep's
    rows, at most ``limit``), three ways side by side, in one temporary
    directory: a part per row the pandas way (``DataFrame`` ->
    ``Table.from_pandas`` -> Parquet, fsync, rename), a part per row the
    Arrow way (``PartsDir.write_part``), and ``batch`` rows at a time
    (``PartsDir.write_rows``: one part a write, as the sweep's part writer
    stores each flush of rows); and the merge of each store's parts into
    one file (pandas: ``read_parquet`` + ``concat``; Arrow:
    ``consolidate_parts``, the batched parts from the writer's own copy of
    them, as the sweep merges them).  ms of CPU (``time.process_time``) per
    row; ``client_ms`` = write + merge of the batched parts."""
    import pandas as pd

    rows = rows[:limit]
    n = max(1, len(rows))
    tmp = Path(tempfile.mkdtemp(prefix="physbench-store-bench-"))
    out: dict[str, Any] = {"rows": len(rows), "columns": max((len(r) for r in rows), default=0), "batch": batch}
    try:
        dirs = {k: tmp / k for k in ("pandas", "row", "batch")}
        for d in dirs.values():
            d.mkdir()
            write_json_atomic({"points": []}, d / "manifest.json")
        c = time.process_time()
        for i, r in enumerate(rows):
            write_parquet_atomic(pd.DataFrame([r]), dirs["pandas"] / f"part-{i:06d}.parquet", {"sweep_id": "bench"})
        out["part_write_pandas_ms"] = 1e3 * (time.process_time() - c) / n
        store = PartsDir(dirs["row"], {}, -1, "point_key")
        c = time.process_time()
        for r in rows:
            store.write_part(r, {"sweep_id": "bench"})
        out["part_write_row_ms"] = 1e3 * (time.process_time() - c) / n
        batched = store = PartsDir(dirs["batch"], {}, -1, "point_key")
        c = time.process_time()
        for i in range(0, len(rows), batch):
            store.write_rows(rows[i:i + batch], {"sweep_id": "bench"})
        out["part_write_batch_ms"] = 1e3 * (time.process_time() - c) / n
        out["parts_batch"] = len(list_parts(dirs["batch"]))
        c = time.process_time()
        df = pd.concat([pd.read_parquet(p) for p in list_parts(dirs["pandas"])], ignore_index=True)
        write_parquet_atomic(df, tmp / "pandas.parquet")
        out["merge_pandas_ms"] = 1e3 * (time.process_time() - c) / n
        for k in ("row", "batch"):
            c = time.process_time()
            consolidate_parts(dirs[k], "point_key", [r["point_key"] for r in rows], "now",
                              written=batched.written if k == "batch" else None)
            out[f"merge_{k}_ms"] = 1e3 * (time.process_time() - c) / n
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out["client_row_ms"] = out["part_write_row_ms"] + out["merge_row_ms"]
    out["client_ms"] = out["part_write_batch_ms"] + out["merge_batch_ms"]
    return out


def _print_store(sc: dict[str, Any]) -> None:
    print(f"client CPU per stored row ({sc['rows']} rows, up to {sc['columns']} columns): part write "
          f"{sc['part_write_pandas_ms']:.2f} ms (pandas, a part per row) / {sc['part_write_row_ms']:.2f} ms "
          f"(Arrow, a part per row) / {sc['part_write_batch_ms']:.2f} ms (Arrow, {sc['batch']} rows at a time: "
          f"{sc['parts_batch']} parts); merge {sc['merge_pandas_ms']:.2f} / {sc['merge_row_ms']:.2f} / "
          f"{sc['merge_batch_ms']:.2f} ms; write + merge {sc['client_row_ms']:.2f} -> {sc['client_ms']:.2f} ms")


#: worker counts the scaling projection is made for
PROJECT_WORKERS = (8, 32, 128)


def scaling(run: dict[str, Any], workers: tuple[int, ...] = PROJECT_WORKERS) -> dict[str, Any]:
    """Amdahl's projection from one measured sweep (:func:`measure`): per
    item (point or search evaluation), the serial CPU -- the client's
    (main thread: start-up, the loop feeding the executor and receiving
    results (``client_loop_ms``), the merge; the part writer) and the scheduler's (a LocalCluster's scheduler, comms and
    nannies run in the client's other threads; with the process executor
    there are none: its transport to the run processes is the main
    thread's; the sampler's own CPU is left out) -- against the parallel CPU (run
    processes: the points' own CPU; Dask worker processes: their task
    handling and transport).  ``speedup[N]`` = 1 / (s + (1 - s) / N), s =
    serial / (serial + parallel): what N workers on cores of their own
    reach if nothing else limits them (ms per item)."""
    a = run["account"]
    items = max(1, run["points"] + run["evaluations"])
    loop = run.get("loop_cpu_s", math.nan)
    client = 1e3 * (a["main thread"] + a["part writer"]) / items
    sched = 1e3 * a["other threads"] / items
    point = 1e3 * a["run processes"] / items
    worker = 1e3 * a["dask worker processes"] / items
    serial, parallel = client + sched, point + worker
    s = serial / (serial + parallel) if serial + parallel > 0 else math.nan
    return {"executor": run["executor"], "jobs": run["jobs"], "items": items, "tasks": run.get("tasks"),
            "client_ms": client, "client_loop_ms": 1e3 * loop / items, "writer_ms": 1e3 * a["part writer"] / items,
            "start_end_s": a["main thread"] - loop, "scheduler_ms": sched, "serial_ms": serial,
            "point_cpu_ms": point, "worker_ms": worker, "serial_fraction": s,
            "speedup": {n: 1.0 / (s + (1.0 - s) / n) for n in workers}}


def _print_scaling(sc: dict[str, Any]) -> None:
    print(f"  {sc['executor']} x{sc['jobs']}: {sc['items']} items" + (f" in {sc['tasks']} tasks" if sc["tasks"] else "")
          + f"; serial CPU per item {sc['serial_ms']:.2f} ms (client {sc['client_ms']:.2f}: its loop "
          f"{sc['client_loop_ms']:.2f}, part writer {sc['writer_ms']:.2f}, start-up and merge {sc['start_end_s']:.1f} s "
          f"in all; scheduler and comms {sc['scheduler_ms']:.2f}); point CPU {sc['point_cpu_ms']:.1f} ms + Dask worker {sc['worker_ms']:.2f} ms; "
          f"serial fraction {sc['serial_fraction']:.4f}; Amdahl on "
          + ", ".join(f"{n} workers {v:.1f}x" for n, v in sc["speedup"].items()))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m physbench.harness.selfbench.sweep", description=__doc__.split("\n\n")[0])
    p.add_argument("--suite", default="nightly")
    p.add_argument("--engines", nargs="+", default=None)
    p.add_argument("--scenarios", nargs="+", default=None, help="a subset of the suite's scenarios")
    p.add_argument("--executors", nargs="+", default=["process", "dask"], choices=["process", "dask"])
    p.add_argument("--jobs", nargs="+", type=int, default=[1, 2])
    p.add_argument("--repeat", type=int, default=1, help="rounds of every executor and worker count, interleaved")
    p.add_argument("--overhead-items", type=int, default=200, help="sleeping tasks per overhead figure (0: skip)")
    p.add_argument("--store-rows", type=int, default=2000,
                   help="rows of the first run the client's storing cost is measured on (0: skip; minutes for 2000)")
    p.add_argument("--store-batch", type=int, default=32,
                   help="rows to a write in the client's storing cost (the sweep's part writer gathers "
                        "harness.sweep_store.PART_FLUSH_S seconds of rows)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures to this file")
    p.add_argument("--core-scaling", action="store_true",
                   help="only measure one point's CPU alone and as --jobs copies at once")
    p.add_argument("--replay", type=Path, default=None,
                   help="only replay this finished sweep file (best a 1-worker one) on --jobs virtual workers")
    p.add_argument("--store", type=Path, default=None,
                   help="only measure the client's CPU per stored row (part write, merge; pandas and Arrow) "
                        "on the rows of this finished sweep file")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="the dask executor joins this cluster (tcp://host:8786) instead of a LocalCluster: the "
                        "client's serial CPU per item on a real cluster (its scheduler's CPU is not counted)")
    p.add_argument("--dask-batch-s", type=float, default=None,
                   help="expected seconds of work per Dask task (default harness.dask_executor.BATCH_S; "
                        "0: one point per task)")
    p.add_argument("--keep", type=Path, default=None, help="store the sweeps here (default: a temporary "
                                                           "directory, removed)")
    args = p.parse_args(argv)

    if args.dask_batch_s is not None:
        from physbench.harness import dask_executor

        dask_executor.BATCH_S = args.dask_batch_s

    if args.core_scaling:
        for jobs in args.jobs:
            if jobs > 1:
                print(json.dumps(core_scaling(jobs)))
        return 0
    if args.store is not None:
        import pyarrow.parquet as pq

        _print_store(store_costs(pq.read_table(args.store).to_pylist(), limit=args.store_rows or 2000,
                                 batch=args.store_batch))
        return 0
    if args.replay is not None:
        import pandas as pd

        df = pd.read_parquet(args.replay)
        for jobs in args.jobs:
            print(json.dumps(replay(df, args.suite, jobs, args.engines, args.scenarios)))
        return 0
    rows: list[dict[str, Any]] = []
    replays: list[dict[str, Any]] = []
    store: dict[str, Any] = {}
    root = args.keep or Path(tempfile.mkdtemp(prefix="physbench-sweep-bench-"))
    try:
        # executors interleaved, each round in full: the machine's load drifts between runs
        for rnd, jobs, ex in itertools.product(range(args.repeat), args.jobs, args.executors):
            r = measure(root, args.suite, ex, jobs, args.engines, args.scenarios,
                        args.scheduler if ex == "dask" else None)
            r["round"] = rnd
            one = next((x for x in reversed(rows) if x["executor"] == ex and x["jobs"] == 1), None)
            r["speedup"] = one["wall_s"] / r["wall_s"] if one else math.nan
            rows.append(r)
            print(json.dumps(r), file=sys.stderr, flush=True)
            if not replays:  # the item times of the first run (best a 1-worker one): what the schedule allows
                import pandas as pd

                df = pd.read_parquet(r["sweep_file"])
                replays = [replay(df, args.suite, j, args.engines, args.scenarios)
                           for j in sorted({j for j in args.jobs if j > 1} | set(PROJECT_WORKERS))]
                import pyarrow.parquet as pq

                if args.store_rows > 0:
                    store = store_costs(pq.read_table(r["sweep_file"]).to_pylist(), limit=args.store_rows,
                                        batch=args.store_batch)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    overhead = []
    if args.overhead_items > 0:
        for ex in args.executors:
            for jobs in args.jobs:
                for task_s in (0.0, 0.02):
                    overhead.append(bench_overhead(ex, jobs, args.overhead_items, task_s))
    threads = {}
    for ex in args.executors:
        with make_executor(ex, 1, log=lambda _t: None) as e:
            threads[ex] = list(e.map(thread_counts, [0]))[0][1]

    print(f"sweep {args.suite}" + (f", scenarios {' '.join(args.scenarios)}" if args.scenarios else ""))
    cols = ("round", "executor", "jobs", "points", "evaluations", "errors", "wall_s", "speedup", "cpu_s", "cores_busy",
            "busy_s", "idle", "step_cpu_s", "step_wall_s", "wait")
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(f"{r[c]:.3g}" if isinstance(r[c], float) else str(r[c]) for c in cols))
    print("CPU s by role (main thread: the sweep's loop, start-up and merge; other threads: a LocalCluster's "
          "scheduler, nannies and comms, and the sampler; load average before -> after)")
    for r in rows:
        a = r["account"]
        print(f"  {r['executor']} x{r['jobs']}: wall {a['wall_s']:.1f} s on {a['cores']:g} cores; "
              + ", ".join(f"{k} {v:.1f}" for k, v in a.items() if k not in ("wall_s", "cores"))
              + f"; load {r['load_before']:.1f} -> {r['load_after']:.1f}")
    print("serial CPU per item and Amdahl's projection (workers on cores of their own; harness.selfbench.sweep.scaling)")
    scalings = [scaling(r) for r in rows]
    for sc in scalings:
        _print_scaling(sc)
    for rp in replays:
        print(f"replay of the first run's item times on {rp['jobs']} uncontended workers: total {rp['total_s']:.1f} s, "
              f"ideal {rp['ideal_s']:.1f} s; this schedule {rp['new_s']:.1f} s ({rp['speedup_new']:.2f}x; "
              f"{rp['work_s']:.1f} s of work with the wide rounds' extra evaluations; one value at a time "
              f"{rp['narrow_s']:.1f} s, {rp['speedup_narrow']:.2f}x), "
              f"points then searches one value at a time {rp['old_s']:.1f} s ({rp['speedup_old']:.2f}x); longest search "
              f"{rp['longest_search_s']:.1f} s, longest point {rp['longest_point_s']:.1f} s")
    if store:
        _print_store(store)
    if overhead:
        print("scheduler overhead per item (ms of worker time not in the task; sleeping tasks)")
        for o in overhead:
            print(f"  {o['executor']} x{o['jobs']}, {o['items']} tasks of {o['task_s'] * 1e3:g} ms: "
                  f"{o['overhead_ms']:.2f} ms")
    for ex, t in threads.items():
        print(f"run process threads ({ex}): numba {t['numba']}, BLAS {t['blas']}, env {t['env']}")
    if args.json:
        args.json.write_text(json.dumps({"suite": args.suite, "scenarios": args.scenarios, "runs": rows,
                                         "scaling": scalings, "replays": replays,
                                         "overhead": overhead, "threads": threads,
                                         "store": store}, indent=1, default=float))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
