"""The trace step after the verdicts (``check --traces``): the deciding run
of each failing case run again with its trace."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

from physbench.harness.conformance.plan import RunSpec
from physbench.harness.conformance.verdicts import ERROR, FAIL, XFAIL, Outcome, evaluate_check, split_metric
from physbench.harness.execute import RunRequest, request_scene, run_requests
from physbench.harness.executors import make_executor
from physbench.contract.scene import Check


def deciding_run(spec: "RunSpec", check: Check, results: dict[tuple, Any]) -> tuple[dict[str, Any], float]:
    """(settings, step phase) of the run that decided ``check`` on the base
    run ``spec``: the @-suffix's settings; for a phased scene the first
    phase that failed; else the base run."""
    name, sett = split_metric(check.metric)
    if sett:
        return sett, 0.0
    if spec.phases > 1:
        for i in range(spec.phases):
            res = results.get(spec.key + ((i / spec.phases,) if i else ()))
            if res is not None and evaluate_check(check, res).outcome in (FAIL, XFAIL, ERROR):
                return {}, i / spec.phases
    return {}, 0.0


def trace_failures(traces_dir: str | Path, runs: list["RunSpec"], results: dict[tuple, Any],
                   outcomes: list[Outcome], jobs: int = 1, executor: str = "process") -> list[Path]:
    """The trace step after the verdicts (``check --traces DIR``): every
    FAIL, XFAIL and ERROR outcome's deciding run is run again with its trace
    and the engine's contacts, and one diagnosing ``.rrd`` per case
    (harness.trace.cases.case_name) goes to ``traces_dir``; each outcome
    gets its file in ``Outcome.trace``.  Load errors have no run and no
    trace.  A trace that cannot be written is reported, never fatal."""
    # the trace package imports rerun (~0.5 s): loaded for --traces only, not by every check and run
    from physbench.harness.trace.cases import TRACED_OUTCOMES, case_name, write_case_trace
    from physbench.harness.trace.contacts import DEFAULT_CAP

    # plain runs only: an ensemble's or the consensus's verdicts have no one run to trace
    base = {(r.scenario, r.variant, r.engine): r for r in runs if r.checks and not r.ensemble and not r.consensus}
    cases: dict[str, tuple] = {}
    for o in outcomes:
        spec = base.get((o.scenario, o.variant, o.engine))
        if o.outcome not in TRACED_OUTCOMES or spec is None:
            continue
        check = next((c for c in spec.checks if c.metric == o.metric), None)
        if check is None:
            continue
        settings, phase = deciding_run(spec, check, results)
        name = case_name(o.scenario, o.variant, o.engine, settings, phase)
        cases.setdefault(name, (spec, settings, phase, []))[3].append(o)
    written = []
    reqs = {name: RunRequest(spec.path or spec.scenario, spec.engine, spec.variant, dict(settings), phase=phase,
                             timeout_s=spec.timeout_s, keep_trace=True, contact_cap=DEFAULT_CAP)
            for name, (spec, settings, phase, _) in cases.items()}
    with make_executor(executor, jobs) as ex:  # a traced rerun that crashes is a status too
        traced = {id(req): res for req, res in run_requests(reqs.values(), ex)}
    for name, (spec, settings, phase, failing) in cases.items():
        try:
            scene = request_scene(reqs[name])
            res = traced[id(reqs[name])]
            res.notes.append("run again after the verdict to record this trace")
            mine = [o for o in outcomes if (o.scenario, o.variant, o.engine) == (spec.scenario, spec.variant,
                                                                                   spec.engine)]
            path = write_case_trace(traces_dir, scene, [res], mine, name=name,
                                    checks={c.metric: c for c in spec.checks})
        except Exception as e:  # pragma: no cover - a trace must not lose the verdict
            print(f"warning: no trace for {name}: {type(e).__name__}: {e}", file=sys.stderr)
            continue
        for o in failing:
            o.trace = os.path.abspath(path)
        written.append(path)
    return written
