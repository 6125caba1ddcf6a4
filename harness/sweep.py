"""Accuracy-vs-cost sweeps: ``physbench sweep``.

A *suite* (``suites/<name>.toml``, format in ``docs/SWEEPS.md``) lists blocks
of scenarios and a grid of engine settings per block: axes common to every
engine (``grid``) and engine-specific axes (``[sweep.engine.<name>] grid``),
combined as a cartesian product.  :func:`expand` turns a suite into
:class:`Point` s, one per (scenario, variant, engine, settings); each point is
run with :func:`harness.runner.run` (the runner does the stepping, timing and
metrics; this module only plans, repeats, stores and resumes).

Rows.  One row per point: ``RunResult.row()`` of the point's first run (its
metrics: engines are deterministic) plus the sweep columns ``suite``,
``sweep_id``, ``point_key``, ``point_settings``, ``primary_metric``,
``primary_error``, ``cpu_s_per_sim_s_median``/``_min`` over ``repeats`` timed
runs, ``machine_id``, ``sweep_jobs``, ``point_wall_s`` and ``schema_version``
(``results/README.md``).  Traces are never stored.

Storage (asv style, ``results/sweeps/``)::

    <machine-id>/<suite>/<sweep_id>/manifest.json     while running
    <machine-id>/<suite>/<sweep_id>/part-000001.parquet  finished points' rows
    <machine-id>/<suite>/<sweep_id>.parquet           when complete
    <machine-id>/<suite>/<sweep_id>.manifest.json     when complete

Every file is written atomically (temp file, fsync, rename); the rows of
about five seconds go into one part (harness.sweep_store.PART_FLUSH_S), so a killed sweep loses at most those
and the points in flight.  A
sweep resumes (automatically, or with ``resume=True``) by reading the finished
point keys back from its parts.

Execution: ``jobs`` reusable worker processes under a wall-clock watchdog
(``executor="process"``, the default; harness/execute.py), or in this
process (``"serial"``: no isolation, for debugging).  A point whose worker
dies (abort, segfault, out-of-memory kill) gets an ``error`` row naming the
signal with the tail of the worker's stderr; a point stuck past its budget
(``timeout_s`` per run, times its repeats) gets a ``timeout`` row and its
worker is replaced; no other point is touched.  The suite's breaking-point
searches (``[[limit]]``) run on the same executor, concurrently with the
points (harness/schedule.py): longest search and longest point first.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

from physbench.contract.spec import SpecError, _display
from physbench.harness import status as st
from physbench.harness.dask_executor import EnvironmentRefused
from physbench.harness.executors import make_executor
from physbench.harness.limits import RESULT_ROW, describe, stored_rows
from physbench.harness.points import Point
from physbench.harness.results import SCHEMA_VERSION, list_parts
from physbench.harness.schedule import expected_costs, run_schedule
from physbench.harness.suite import scenario_label, expand, load_suite
from physbench.harness.sweep_store import SweepDir, consolidate, machine_id, open_sweep, sweeps_dir

STATUSES = st.RUN_STATUSES
EXECUTORS = ("serial", "process", "dask")


# ---------------------------------------------------------------------------
# entry point


def summarize(df, wall_s: float, console=None, title: str = "") -> None:
    """Per engine: points and counts of each status, and ``time_s``, the
    wall time spent in its points (s, summed over points, repeats and metric
    computation included)."""
    from rich.console import Console
    from rich.table import Table

    if console is None:
        console = Console()
        if not console.is_terminal:  # a log file: do not squeeze the table into 80 columns
            console = Console(width=120)
    table = Table(title=title or "sweep", caption=f"wall time {wall_s:.1f} s")
    for col in ("engine", "points", *STATUSES, "time_s"):
        table.add_column(col, justify="left" if col == "engine" else "right")
    if len(df):
        for eng in dict.fromkeys(df["engine"]):
            sub = df[df["engine"] == eng]
            counts = sub["status"].value_counts()
            t = float(sub["point_wall_s"].sum()) if "point_wall_s" in sub else math.nan
            table.add_row(eng, str(len(sub)), *(str(int(counts.get(s, 0))) for s in STATUSES), f"{t:.1f}")
    console.print(table)


@contextlib.contextmanager
def _start_up_frozen():
    """While the sweep's loop runs, the objects start-up made (modules,
    specs, scenes: about 100,000 the garbage collector tracks) are left out
    of its collections (``gc.freeze``; given back after): a full collection
    walks them all (about 45 ms of the client's CPU each, one every few
    hundred rows received), and they live as long as the sweep anyway."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _store_limits(sd: "SweepDir", ctx: dict[str, Any], err: Any):
    """(cached evaluations and summaries read back from the sweep's parts,
    store of an evaluation's row, on_search_done that stores a summary not
    stored before and prints the answer)."""
    cached = stored_rows(list_parts(sd.path))
    cached.update(stored_rows(list_parts(sd.path), RESULT_ROW))

    def store(row: dict[str, Any]) -> None:
        row.update(ctx)
        sd.write_point(row)

    def done(req: Any, res: Any, summary: dict[str, Any]) -> None:
        if summary["point_key"] not in cached:
            store(summary)
        err.print("limit: " + describe(res, req), markup=False, highlight=False, soft_wrap=True)

    return cached, store, done


def sweep_main(suite: str, engines: list[str] | None = None, jobs: int = 1, executor: str | None = None,
               out_dir: Path | None = None, resume: bool | None = None,
               scenarios: list[str] | None = None, timeout_s: float | None = None,
               scheduler: str | None = None) -> int:
    """``physbench sweep``: run ``suite`` (a name under suites/ or a path)
    and store its rows under ``out_dir`` (default results/sweeps/).

    ``engines`` / ``scenarios`` restrict the suite; ``jobs`` worker processes
    with ``executor`` ``"process"`` (the default) or ``"serial"`` (in this
    process), or ``"dask"``: the Dask cluster at ``scheduler``, or a
    LocalCluster of ``jobs`` workers (harness/dask_executor.py; the rows are
    filed under the workers' machine id); ``timeout_s`` replaces the suite's
    per-run budget;
    ``resume``: None resumes an unfinished sweep of the same suite file,
    points and commit, True also across commits, False never (see
    :func:`open_sweep`).  Returns 0 when the sweep completed (failed runs are
    data, recorded as statuses), 2 for a bad suite file or arguments, 130
    when interrupted (the sweep can be resumed)."""
    from rich.console import Console
    from rich.markup import escape
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    err = Console(stderr=True)
    t_start = time.perf_counter()
    try:
        s = load_suite(suite)
    except SpecError as e:
        for line in e.errors:
            err.print(f"error: {line}", markup=False, highlight=False, soft_wrap=True)
        return 2
    try:
        points = expand(s, engines, scenarios)
    except ValueError as e:
        err.print(f"error: {e}", markup=False, highlight=False, soft_wrap=True)
        return 2
    if timeout_s is not None:
        points = [dataclasses.replace(p, timeout_s=float(timeout_s)) for p in points]
    jobs = max(1, int(jobs or 1))
    executor = executor or "process"
    if executor not in EXECUTORS:
        err.print(f"error: executor {executor!r}: expected one of {', '.join(EXECUTORS)}", markup=False, soft_wrap=True)
        return 2
    if scheduler and executor != "dask":
        err.print(f"error: --scheduler is for --executor dask, not {executor}", markup=False)
        return 2
    if executor == "serial" and jobs > 1:
        err.print(f"note: executor serial runs one point at a time; jobs={jobs} ignored")
        jobs = 1
    reqs = [r for r in s.limits if (engines is None or r.engine in engines)
            and (scenarios is None or r.scenario in scenarios or scenario_label(r.scenario, r.variant) in scenarios)]
    if not points and not reqs:
        err.print(f"error: suite {s.name}: no points selected (engines {engines}, scenarios {scenarios})",
                  markup=False)
        return 2
    root = Path(out_dir) if out_dir is not None else sweeps_dir()
    filters = {"engines": engines, "scenarios": scenarios}
    ex, refused = None, ()
    if executor == "dask":  # before the sweep directory: a refused cluster writes nothing
        refused = (EnvironmentRefused,)
        try:
            ex = make_executor(executor, jobs, scheduler, log=lambda t: err.print(t, markup=False, soft_wrap=True))
        except EnvironmentRefused as e:
            err.print(f"error: {e}", markup=False, highlight=False, soft_wrap=True)
            return 2
        jobs = ex.jobs
    try:
        sd, resumed = open_sweep(s, points, root, resume, jobs, executor, filters,
                                 machine=getattr(ex, "machine_id", None))
    except BaseException:
        if ex is not None:
            ex.close()
        raise
    sd.write_behind()  # the loop feeding the workers and searches does not wait for fsyncs
    ctx = {"suite": s.name, "sweep_id": sd.sweep_id, "machine_id": sd.manifest["machine_id"], "sweep_jobs": jobs,
           "schema_version": SCHEMA_VERSION}
    todo = [p for p in points if p.key not in sd.done]
    err.print(f"sweep {s.name} ({_display(s.path)}): {len(points)} points on {', '.join(dict.fromkeys(p.engine for p in points))}"
              f"; {'resuming ' + sd.sweep_id + ': ' + str(len(points) - len(todo)) + ' done, ' if resumed else ''}"
              f"{len(todo)} to run, {executor} x{jobs}; rows under {sd.path}", markup=False, highlight=False, soft_wrap=True)
    if jobs > 1:
        err.print(f"note: {jobs} runs at a time compete for {os.cpu_count()} cores (and caches, memory "
                  "bandwidth): CPU times are not comparable with a --jobs 1 sweep; metrics are unaffected", soft_wrap=True)
    cols = (TextColumn("[bold]sweep"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            TextColumn("eta"), TimeRemainingColumn(), TextColumn("{task.description}"))
    try:
        shown = err.is_terminal  # no bar (a log file): no per-point description or advance to make
        with Progress(*cols, console=err, disable=not shown, refresh_per_second=2) as bar:
            task = bar.add_task("", total=len(todo))

            def on_start(p: Point) -> None:
                bar.update(task, description=escape(f"{p.engine} {p.label} {p.settings_json}"))

            def on_row(p: Point, row: dict[str, Any]) -> None:
                row.update(ctx)
                sd.write_point(row)
                if shown:
                    bar.advance(task)

            cached, store, done = _store_limits(sd, ctx, err)
            if reqs:
                err.print(f"limits: {len(reqs)} breaking-point searches, run with the points ({len(cached)} "
                          "stored rows read back)", markup=False, highlight=False)
            point_cost, search_cost = expected_costs(root, s.name, sd.manifest["machine_id"], todo, reqs)
            with ex if ex is not None else make_executor(executor, jobs) as ex, _start_up_frozen():
                run_schedule(ex, todo, reqs, on_row, done, store, cached, on_start if shown else None, point_cost,
                             search_cost)
    except (KeyboardInterrupt, *refused) as e:
        if isinstance(e, refused):
            err.print(f"error: {e}", markup=False, highlight=False, soft_wrap=True)
        try:
            sd.close()  # the queued rows written first (a failed write raises here)
        finally:
            if ex is not None:
                ex.close()
        err.print(f"interrupted: {len(sd.done)} of {len(points)} points stored in {sd.path}; "
                  "run the same sweep again to resume it", markup=False, soft_wrap=True)
        return 2 if isinstance(e, refused) else 130
    except BaseException:
        try:
            sd.close()  # raises a failed write the loop had not been given
        finally:
            if ex is not None:
                ex.close()
        raise
    try:  # still locked: a sweep started meanwhile must not resume this directory
        sd.drain()
        out = consolidate(sd.path, sd.written)  # the parts this process wrote: not read back
    finally:
        sd.close()
    import pandas as pd
    import pyarrow.parquet as pq

    # the summary's columns only (a nightly's file is thousands of rows of 200-odd columns)
    have = set(pq.read_schema(out).names)
    df = pd.read_parquet(out, columns=[c for c in ("engine", "status", "point_wall_s", "row_kind") if c in have])
    wall = time.perf_counter() - t_start
    if "row_kind" in df.columns:  # breaking-point rows: summarized as their searches finished
        df = df[df["row_kind"].isna()]
    if len(df) or not reqs:
            summarize(df, wall, title=f"sweep {s.name} {sd.sweep_id}: {len(df)} points"
                                  + (f" ({len(points) - len(todo)} from before the resume)" if resumed else ""))
    err.print(f"rows written to {out}", markup=False, highlight=False, soft_wrap=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(sweep_main(sys.argv[1] if len(sys.argv) > 1 else "nightly"))
