"""CI conformance: run every scenario's checks on every engine.

``check_main(engines, tags, junit, scenarios, jobs)`` is what ``physbench
check`` calls; it returns the process exit code (1 on any FAIL, ERROR or
XPASS; 5 when no check applied to anything, each scene's reason printed;
else 0).

Modules: ``verdicts`` (the outcome vocabulary, ``Outcome``, bounds and
their evaluation, the combination over step phases, a row's verdict
columns; no I/O), ``plan`` (``RunSpec``, scenario selection, the runs a
scene's checks take, the outcomes of the planned runs), ``store`` (the
resumable parts store), ``traces`` (``check --traces``), ``junit`` and
``summary`` (exit code and console table); this module runs them
(``execute``, ``run_all``, ``check_main``) and re-exports the names other
modules and the tests take from ``harness.conformance``.

What runs.  For each selected scenario (all of ``scenarios/`` by default;
else the ids, spec files and folders of spec files given, anywhere on disk:
:func:`select_scenarios`; filtered by ``tags``: a scenario is kept if it has
any of them) the base scene
and each ``[[variant]]`` are run once per engine, at the engine's default
settings and the scene's dt, with :func:`harness.runner.run` -- but only the
ones that some check applies to:

- a check without ``variants`` applies to the base scenario and to every
  variant; a check with ``variants = [...]`` only to the variants it names,
  where the name ``"base"`` stands for the base scenario;
- a check with ``engines = [...]`` applies only to those engines.

Checks are read from the compiled scene of the run (so a variant sees the
base's checks, plus whatever its overrides change).

Hard cases.  Every scenario tagged ``hard`` is also checked for stability
(metric ``stable`` must be true) on every engine, at the default dt and at
dt = 1/30 s (settings override ``{"dt": 1/30}``), as testcases
``<scenario>::stable`` and ``<scenario>::stable@dt=1/30`` (base scene only).
A scenario may declare these checks itself, ``metric = "stable"`` or
``metric = "stable@dt=1/30"``, to attach an ``xfail``; the explicit check
then replaces the implicit one.  In general, a check metric
``NAME@dt=VALUE`` evaluates NAME on a run whose dt is overridden (VALUE may
be a fraction such as 1/30).

Step phases: a scenario with ``[scenario] phases = N`` (N > 1; its start
must be free flight) runs every engine N times, the start moved back along
the free flight by i/N dt (contract/phase.py); each check not bound to
another dt holds only if it holds in every phase.  One run is one draw of
where the steps fall, and for thin walls that decides the outcome: a plate
that a discrete engine catches in the phase as written may fall through in
13 of 16 phases.  The combined outcome: ERROR if a phase errored, else
FAIL (XFAIL with an xfail) if a phase failed, else PASS (XPASS); its
message gives the failing count and the pattern over the phases.

Outcomes, per (engine, scenario, variant, check):

- PASS / FAIL: the run is ``ok`` and the metric meets / misses the bound;
- ERROR also when the run is ``ok`` but the check's metric is missing from
  it or NaN ("metric not computed"): a check is never silently skipped, and
  an xfail does not cover it (nothing was measured);
- XFAIL / XPASS: the check lists the engine in ``xfail`` (a documented
  limitation, with the measured figure) and the run fails / passes it;
- UNSUPPORTED: the engine reported the scene as unsupported;
- ERROR: the run's status is error, failed, diverged or timeout (or the
  scene would not load): counts as a failure unless xfailed (then XFAIL).

Bounds: ``max`` (value <= max), ``min`` (value >= min), both if both given;
``equals`` with ``tolerance`` (|value - equals| <= tolerance; booleans must
match).  ``tolerance`` also widens max/min bounds.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

from physbench.harness.conformance.junit import write_junit
from physbench.harness.conformance.plan import RUN_TIMEOUT_S, RunSpec, default_engines, evaluate_runs, plan, select_scenarios
from physbench.harness.conformance.store import check_identity, open_check, result_row, utc_now
from physbench.harness.conformance.summary import exit_code, summarize
from physbench.harness.conformance.traces import trace_failures
from physbench.harness.conformance.verdicts import Outcome, verdicts_column
from physbench.harness.consensus import consensus_result
from physbench.harness.dask_executor import EnvironmentRefused
from physbench.harness.ensemble import ensemble_result
from physbench.harness.results import SCHEMA_VERSION, consolidate_parts, results_dir
from physbench.harness.runner import RunResult

# the names other modules and the tests take from harness.conformance
# (limits.py, limit_eval.py, points.py, cli/run.py, cli/trace.py; tests/test_conformance.py,
# test_scenarios.py, test_own_scenes.py, test_execute.py, test_trace_*.py)
from physbench.harness.conformance.plan import scene_runs  # noqa: F401
from physbench.harness.conformance.store import save_rows  # noqa: F401
from physbench.harness.conformance.verdicts import (BAD, BASE, ERROR, FAIL, PASS, UNSUPPORTED, XFAIL, XPASS,  # noqa: F401
                                                    applicable_checks, check_applies, combine_phases, evaluate,
                                                    evaluate_check, fmt_measured, hard_checks, judged_apart,
                                                    run_verdicts, scene_columns, split_metric)
from physbench.harness.execute import (ColdSplit, PendingCompile, RunRequest, WorkerLost, execute_request, lost_result,
                                       shares_compile)
from physbench.harness.executors import make_executor


def execute(item: RunSpec | RunRequest):
    """Run one request (or a RunSpec's) in this process
    (harness.execute.execute_request): never raises (engine import errors
    become a RunResult with status 'failed').  The trace is dropped
    (results cross process boundaries).  An ensemble request runs its
    members here, one after the other (harness.ensemble.ensemble_result),
    and a consensus request its engines' refined runs
    (harness.consensus.consensus_result), each with its share of the
    budget."""
    q = item.request() if isinstance(item, RunSpec) else item
    if q.consensus:
        per = None if q.timeout_s is None else q.timeout_s / len(q.consensus)
        return consensus_result(q.scenario, q.variant, list(q.consensus), timeout_s=per)
    if q.ensemble:
        per = None if q.timeout_s is None else q.timeout_s / q.ensemble.n
        return ensemble_result(q.scenario, q.variant, q.engine, dict(q.settings), q.ensemble, timeout_s=per)
    return execute_request(q)


def run_all(runs: list[RunSpec], jobs: int = 1, progress: bool = True, executor: str = "process",
            on_result=None, scheduler: str | None = None) -> dict[tuple, Any]:
    """Execute runs in ``jobs`` worker processes (harness/execute.py: a
    worker that dies or hangs costs only its run, which becomes an error or
    timeout result), or in this process with ``executor="inline"``, or as
    Dask tasks with ``executor="dask"`` (on the cluster at ``scheduler``,
    else a LocalCluster of ``jobs`` workers; raises
    harness.dask_executor.EnvironmentRefused); a rich progress bar on stderr.  ``on_result(spec, result)`` is called as each
    run finishes (check stores it there).  Returns {RunSpec.key: RunResult}."""
    from rich.console import Console
    from rich.markup import escape
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    results: dict[tuple, Any] = {}
    console = Console(stderr=True)
    cols = (TextColumn("[bold]conformance"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            TextColumn("eta"), TimeRemainingColumn(), TextColumn("{task.description}"))
    with make_executor(executor, jobs, scheduler, log=lambda t: console.print(t, markup=False, soft_wrap=True)) \
            if executor == "dask" else make_executor(executor, jobs) as ex, \
            Progress(*cols, console=console, disable=not progress, transient=False) as bar:
        task = bar.add_task("", total=len(runs))

        def run_one(q: RunRequest):
            return execute(q)  # looked up at call time (tests patch it for inline runs)

        # the executors' items are requests (harness.execute.RunRequest), keyed by the run's run_key
        spec_of = {}
        reqs = []
        for r in runs:
            q = dataclasses.replace(r.request(), key=r.run_key)
            spec_of[id(q)] = r
            reqs.append(q)
        fn = run_one if executor in ("inline", "serial") else execute
        # a cold compile cache on local workers: one compiles, the others run what needs none
        split = ColdSplit(reqs, PendingCompile()) if shares_compile(ex) else None
        for q, value in ex.map(fn, split if split is not None else reqs, budget_s=lambda q: q.budget_s,
                               on_start=lambda q: bar.update(task, description=escape(q.label))):
            if split is not None:
                split.done(q)
            r = spec_of.pop(id(q))
            res = lost_result(q, value) if isinstance(value, WorkerLost) else value
            results[r.key] = res
            if on_result is not None:
                on_result(r, res)
            bar.advance(task)
    return results


#: exit code of a check in which no check applied to any run (as pytest's
#: "no tests collected"): never 0, since nothing was shown to hold
NOTHING_CHECKED = 5


def _idle_lines(idle: list[tuple[str, str | None, str]]) -> list[str]:
    """One line per scenario to which no check applied, with the reason
    (its variants folded in when they share it)."""
    by: dict[str, list[tuple[str | None, str]]] = {}
    for sid, variant, why in idle:
        by.setdefault(sid, []).append((variant, why))
    out = []
    for sid, items in by.items():
        whys = {w for _, w in items}
        if len(whys) == 1:
            nv = sum(v is not None for v, _ in items)
            out.append(f"{sid}{f' (and its {nv} variants)' if nv else ''}: {items[0][1]}")
        else:
            out += [f"{sid}{f'[{v}]' if v else ''}: {w}" for v, w in items]
    return out


def check_main(engines: list[str] | None, tags: list[str] | None, junit: str | None,
               scenarios: list[str] | None, jobs: int = 1, save_dir: str | Path | None = None,
               timeout_s: float | None = RUN_TIMEOUT_S, executor: str = "process", resume: bool = True,
               traces: str | Path | None = None, scheduler: str | None = None,
               settings: dict[str, dict[str, Any]] | None = None, ensemble: dict[str, Any] | None = None) -> int:
    """Run the conformance suite; print a summary; store every run's result
    row as it finishes (``save_dir``, default results/check/: a directory
    ``<check_id>/`` of atomic parts while running, consolidated into
    ``<check_id>.parquet`` at the end) and write JUnit XML to ``junit`` if
    given; with ``traces``, one diagnosing trace per FAIL, XFAIL and ERROR
    case into that directory (:func:`trace_failures`).  A killed check is
    resumed by the next same check (``resume``, :func:`check_identity`):
    its finished runs are read back, not rerun.  Runs go to ``jobs`` worker
    processes with ``timeout_s`` seconds each (``executor="inline"``: in
    this process; ``"dask"``: tasks on the Dask cluster at ``scheduler`` or
    a LocalCluster of ``jobs`` workers; the traces of ``traces`` are rerun
    on local worker processes).  ``settings``: engine -> setting overrides
    for that engine's runs (``check --set ENGINE:KEY=VALUE``; a check's
    ``@dt=...`` setting wins over them).  ``ensemble`` (``check --ensemble
    N --sigma S --threshold T``: n, position, threshold): the ensemble
    check ``predictable`` on every base scene with noise to draw
    (harness.conformance.plan.plan).  Returns 1 on any FAIL, ERROR or XPASS, 5
    (:data:`NOTHING_CHECKED`) when no check applied to any run, else 0; raises
    SpecError for a scenario id or file that does not exist (exit 2)."""
    from rich.console import Console

    t0 = time.perf_counter()
    engines = list(engines) if engines else default_engines()
    ids = select_scenarios(scenarios, tags)  # raises SpecError for an unknown id, file or folder
    err = Console(stderr=True)
    if not ids:
        err.print(f"no scenarios selected (tags: {tags}, scenarios: {scenarios})")
        return 1
    notes: list[str] = []
    idle: list[tuple[str, str | None, str]] = []
    runs, load_errors = plan(ids, engines, timeout_s, notes=notes, idle=idle, settings=settings, ensemble=ensemble)
    for line in notes:  # check engines not installed here (harness.conformance.plan.engine_names_in_checks)
        err.print(f"note: {line}", markup=False, highlight=False, soft_wrap=True)
    for line in _idle_lines(idle):
        err.print(f"nothing to check: {line}", markup=False, highlight=False, soft_wrap=True)
    if not runs and not load_errors:
        # nothing applied anywhere: not a pass (tests/test_cli.py::test_check_with_nothing_to_check_exits_5)
        err.print(f"no check applies: {len(ids)} scenarios, engines {', '.join(engines)}; exit {NOTHING_CHECKED}",
                  markup=False, highlight=False, soft_wrap=True)
        return NOTHING_CHECKED
    root = Path(save_dir) if save_dir is not None else results_dir() / "check"
    store, resumed = open_check(root, check_identity(ids, engines, runs, timeout_s), resume)
    results: dict[tuple, Any] = {}
    by_key = {r.run_key: r for r in runs}
    for row in store.part_rows() if resumed else []:
        r = by_key.get(row.get("run_key"))
        if r is not None:
            results[r.key] = RunResult.from_row(row)
    todo = [r for r in runs if r.key not in results]
    err.print(f"{len(ids)} scenarios, {len(engines)} engines ({', '.join(engines)}): {len(runs)} runs"
              + (f"; resuming {store.path.name}: {len(runs) - len(todo)} done, {len(todo)} to run" if resumed else ""),
              markup=False, highlight=False, soft_wrap=True)

    def on_result(r: RunSpec, res: Any) -> None:
        row = result_row(r.key, res)
        row.update(r.row_extra)
        # the store's schema version in every row, as sweeps write it (the report reads it)
        row.update(run_key=r.run_key, check_id=store.path.name, schema_version=SCHEMA_VERSION)
        try:
            store.write_part(row, {"check_id": store.path.name})
        except Exception as e:  # disk trouble must not hide the verdict
            err.print(f"warning: could not store the row of {r.run_key}: {type(e).__name__}: {e}", markup=False)

    refused: tuple = ()
    if executor == "dask":
        refused = (EnvironmentRefused,)
    try:
        results.update(run_all(todo, jobs=max(1, int(jobs or 1)), progress=True, executor=executor,
                               on_result=on_result, scheduler=scheduler))
    except refused as e:  # the rows stored so far stay: the next same check resumes them
        err.print(f"error: {e}", markup=False, highlight=False, soft_wrap=True)
        store.close()
        return 2
    except BaseException:
        store.close()
        raise
    outcomes = load_errors + evaluate_runs(runs, results)
    if traces:
        written = trace_failures(traces, runs, results, outcomes, jobs=max(1, int(jobs or 1)),
                                 executor="process" if executor == "dask" else executor)
        err.print(f"{len(written)} traces written to {traces}")
    summarize(outcomes)
    try:
        # the verdicts go into the rows, so the report reads rows only
        verdicts: dict[str, list[Outcome]] = {r.run_key: [] for r in runs}
        run_keys = {r.key: r.run_key for r in runs}
        for o in outcomes:
            if o.key in run_keys:
                verdicts[run_keys[o.key]].append(o)
        columns = {k: {"checks": verdicts_column(v)} for k, v in verdicts.items()}
        saved, _ = consolidate_parts(store.path, "run_key", [r.run_key for r in runs], utc_now(), columns=columns)
        err.print(f"result rows written to {saved}", markup=False, highlight=False, soft_wrap=True)
    except Exception as e:  # the parts stay: nothing is lost
        err.print(f"warning: could not consolidate {store.path}: {type(e).__name__}: {e}", markup=False)
    finally:
        store.close()
    if junit:
        write_junit(outcomes, junit)
        err.print(f"JUnit XML written to {junit}", markup=False, highlight=False, soft_wrap=True)
    err.print(f"done in {time.perf_counter() - t0:.1f} s")
    return exit_code(outcomes)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(check_main(None, None, None, sys.argv[1:] or None))
