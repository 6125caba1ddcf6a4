"""CI conformance: run every scenario's checks on every engine.

``check_main(engines, tags, junit, scenarios, jobs)`` is what ``physbench
check`` calls; it returns the process exit code (1 on any FAIL, ERROR or
XPASS, else 0).

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

import datetime as _dt
import hashlib
import json
import io
import os
import math
import re
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any, Iterable

from harness import status as st
from harness.execute import DEFAULT_TIMEOUT_S, RunRequest, WorkerLost, execute_request, lost_result
from harness.executors import make_executor
from harness.results import write_text_atomic
from contract.scene import Check, Scene

HARD_DT = 1.0 / 30.0
HARD_DT_LABEL = "1/30"
RUN_TIMEOUT_S = DEFAULT_TIMEOUT_S  # wall-clock budget per run (--timeout)
BASE = "base"  # name standing for the base scenario in a check's `variants`

# the outcome vocabulary (harness/status.py) under the names used here
PASS, FAIL, XFAIL, XPASS, UNSUPPORTED, ERROR = st.PASS, st.FAIL, st.XFAIL, st.XPASS, st.CHECK_UNSUPPORTED, st.CHECK_ERROR
BAD = st.BAD_OUTCOMES
OUTCOMES = st.OUTCOMES
ERROR_STATUSES = st.ERROR_STATUSES


# ---------------------------------------------------------------------------
# data


@dataclass
class Outcome:
    """One evaluated check: a JUnit testcase."""

    engine: str
    scenario: str
    variant: str | None
    metric: str
    outcome: str
    value: Any = None
    threshold: str = ""
    message: str = ""
    time_s: float = 0.0
    #: RunSpec.key of the run the check was evaluated on (the base run for
    #: a check combined over step phases); () when there was none
    key: tuple = ()
    #: absolute path of the case's diagnosing trace (check --traces), else ""
    trace: str = ""

    def as_dict(self) -> dict[str, Any]:
        """The outcome as stored in a row's ``checks`` column and printed by
        ``physbench run --json``; ``trace``: the absolute path of its
        ``.rrd`` or "" (docs/TRACES.md)."""
        from harness.runner import _jsonable

        return {"metric": self.metric, "outcome": self.outcome, "value": _jsonable(self.value),
                "threshold": self.threshold, "message": self.message, "trace": self.trace}

    @property
    def name(self) -> str:
        v = f"[{self.variant}]" if self.variant else ""
        return f"{self.scenario}{v}::{self.metric}"


@dataclass
class RunSpec:
    """One run to make: a scene (scenario + variant) on an engine with
    setting overrides, and the checks to evaluate on it."""

    scenario: str
    variant: str | None
    engine: str
    settings: dict[str, Any] = field(default_factory=dict)
    checks: list[Check] = field(default_factory=list)
    #: step phase of the run (contract/phase.py); phase runs of a base run
    #: carry its checks too, and its outcome combines them
    phase: float = 0.0
    #: the base run's phases (``[scenario] phases``), on the base run only
    phases: int = 1
    #: the spec file (None: ``scenario`` is an id under scenarios/)
    path: str | None = None
    #: columns added to the run's row (primary metric and its threshold)
    row_extra: dict[str, Any] = field(default_factory=dict)
    #: wall-clock budget of the run (s); not part of its identity
    timeout_s: float | None = RUN_TIMEOUT_S

    @property
    def key(self) -> tuple:
        base = (self.scenario, self.variant, self.engine, tuple(sorted(self.settings.items())))
        return base + ((self.phase,) if self.phase else ())

    @property
    def run_key(self) -> str:
        """The run's identity as text (the ``run_key`` column of check rows):
        ``scenario[variant]|engine|{settings}|phase``."""
        v = f"[{self.variant}]" if self.variant else ""
        settings = json.dumps(dict(sorted(self.settings.items())), sort_keys=True, separators=(",", ":"))
        return f"{self.scenario}{v}|{self.engine}|{settings}|{self.phase!r}"

    def request(self) -> RunRequest:
        return RunRequest(self.path or self.scenario, self.engine, self.variant, dict(self.settings),
                          phase=self.phase, timeout_s=self.timeout_s)


# ---------------------------------------------------------------------------
# check evaluation


def split_metric(metric: str) -> tuple[str, dict[str, Any]]:
    """'stable@dt=1/30' -> ('stable', {'dt': 0.0333...}); 'x' -> ('x', {})."""
    if "@" not in metric:
        return metric, {}
    name, _, rest = metric.partition("@")
    settings: dict[str, Any] = {}
    for part in rest.split(","):
        key, _, val = part.partition("=")
        if not key or not val:
            raise ValueError(f"check metric {metric!r}: expected NAME@setting=value")
        settings[key.strip()] = _parse_setting(val.strip())
    return name, settings


def _parse_setting(text: str) -> Any:
    if "/" in text:
        try:
            return float(Fraction(text))
        except (ValueError, ZeroDivisionError):
            return text
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    return text


def check_applies(check: Check, engine: str, variant: str | None) -> bool:
    if check.engines is not None and engine not in check.engines:
        return False
    if check.variants is not None:
        return (variant or BASE) in check.variants
    return True


def describe_bound(check: Check) -> str:
    tol = f" +- {check.tolerance:g}" if check.tolerance else ""
    if check.equals is not None:
        return f"== {check.equals!r}{tol}" if isinstance(check.equals, bool) else f"== {check.equals:g}{tol}"
    parts = []
    if check.min is not None:
        parts.append(f">= {check.min:g}")
    if check.max is not None:
        parts.append(f"<= {check.max:g}")
    return " and ".join(parts) + tol


def _is_missing(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, (bool,)):
        return False
    try:
        return math.isnan(float(value))
    except (TypeError, ValueError):
        return True


def meets(check: Check, value: Any) -> bool:
    """Whether a (present, non-NaN) metric value satisfies the check's bound."""
    tol = check.tolerance
    if check.equals is not None:
        if isinstance(check.equals, bool):
            # booleans (numpy's too) or exactly 0/1
            try:
                f = float(value)
            except (TypeError, ValueError):
                return False
            return f in (0.0, 1.0) and (f == 1.0) == check.equals
        return abs(float(value) - float(check.equals)) <= tol
    v = float(value)
    if check.max is not None and not v <= check.max + tol:
        return False
    if check.min is not None and not v >= check.min - tol:
        return False
    return True


def _fmt(value: Any) -> str:
    if isinstance(value, bool) or value is None:
        return repr(value)
    try:
        return f"{float(value):.6g}"
    except (TypeError, ValueError):
        return repr(value)


def evaluate_check(check: Check, result, metric_name: str | None = None) -> Outcome:
    """Evaluate one check against one RunResult.  ``metric_name`` is the
    metric to read (default: the check's metric without an @-suffix)."""
    metric = metric_name or split_metric(check.metric)[0]
    reason = check.xfail.get(result.engine)
    o = Outcome(result.engine, result.scenario, result.variant, check.metric, PASS,
                threshold=describe_bound(check), time_s=float(result.timing.get("step_wall_s", 0.0) or 0.0))
    if result.status == st.UNSUPPORTED:
        o.outcome, o.message = UNSUPPORTED, f"unsupported: {result.message}"
        return o
    if result.status in ERROR_STATUSES or result.status != st.OK:
        msg = f"{result.status}: {result.message}"
        if reason:
            o.outcome, o.message = XFAIL, f"xfail: {reason} ({msg})"
        else:
            o.outcome, o.message = ERROR, msg
        return o
    value = result.metrics.get(metric)
    o.value = value
    if _is_missing(value):
        # a check whose metric was not computed is never skipped, nor
        # covered by an xfail (tests/test_conformance.py::test_nan_or_missing_metric_is_an_error)
        o.outcome = ERROR
        o.message = (f"metric not computed: {metric} is {'missing from' if value is None else 'NaN in'} "
                     f"the run's metrics")
        extra = [n for n in result.notes if n.startswith("metrics failed")]
        if extra:
            o.message += f" ({extra[0]})"
        return o
    else:
        ok = meets(check, value)
        msg = f"{metric} = {_fmt(value)}, expected {o.threshold}"
        if metric == "stable" and not ok and result.metrics.get("stability_reason"):
            msg += f" ({result.metrics['stability_reason']})"
    if reason:
        if ok:
            o.outcome, o.message = XPASS, f"unexpected pass: {msg}; xfail reason was: {reason}"
        else:
            o.outcome, o.message = XFAIL, f"xfail: {reason} ({msg})"
    else:
        o.outcome, o.message = (PASS, msg) if ok else (FAIL, msg)
    return o


def applicable_checks(scene: Scene, engine: str) -> list[Check]:
    """The scene's checks that apply to ``engine`` and the scene's variant
    (all of them, including @-suffixed ones)."""
    return [c for c in scene.checks if check_applies(c, engine, scene.variant)]


def hard_checks(scene: Scene) -> list[Check]:
    """The implicit stability checks of a hard-tagged base scene, unless the
    scene declares them itself (then its own, with their xfail, are used)."""
    if "hard" not in scene.tags or scene.variant is not None:
        return []
    declared = {c.metric for c in scene.checks}
    out = []
    for metric in ("stable", f"stable@dt={HARD_DT_LABEL}"):
        if metric not in declared:
            out.append(Check(metric=metric, equals=True))
    return out


def evaluate(scene: Scene, result, extra_results: dict[str, Any] | None = None) -> list[Outcome]:
    """All outcomes for one (scene, engine) run: the applicable checks
    evaluated on ``result``; checks with an @-suffix on the matching run in
    ``extra_results`` (keyed by the suffix, e.g. 'dt=1/30'), ERROR if that run
    is missing."""
    outs = []
    for c in applicable_checks(scene, result.engine) + hard_checks(scene):
        name, settings = split_metric(c.metric)
        if not settings:
            outs.append(evaluate_check(c, result))
            continue
        suffix = c.metric.partition("@")[2]
        other = (extra_results or {}).get(suffix)
        if other is None:
            outs.append(Outcome(result.engine, result.scenario, result.variant, c.metric, ERROR,
                                threshold=describe_bound(c), message=f"no run with {suffix}"))
        else:
            outs.append(evaluate_check(c, other, name))
    return outs


# ---------------------------------------------------------------------------
# planning and running


def select_scenarios(scenarios: list[str] | None, tags: list[str] | None) -> list[str]:
    """The scenarios to check, as targets for :func:`plan`: every id of
    scenarios/ by default; else each entry of ``scenarios`` -- an id stays
    an id, a spec file or a folder (all ``*.toml`` below it, sorted) becomes
    the files' paths, anywhere on disk.  An entry that is neither raises
    SpecError (exit 2).  ``tags`` keeps the scenarios that have any of them
    (a spec that does not load is kept: it is reported, never dropped)."""
    from contract.scene import load_scene, scenario_ids, spec_targets

    if scenarios:
        ids: list[str] = []
        for entry in scenarios:
            for t in spec_targets(entry):
                if t not in ids:
                    ids.append(t)
    else:
        ids = scenario_ids()
    if not tags:
        return ids
    keep = []
    for sid in ids:
        try:
            sc = load_scene(sid)
        except Exception:
            keep.append(sid)  # a broken spec is reported, never silently dropped
            continue
        if set(sc.tags) & set(tags):
            keep.append(sid)
    return keep


def default_engines() -> list[str]:
    from adapters import ENGINES

    return list(ENGINES)


def _load_error_outcomes(sid: str, variant: str | None, engines: Iterable[str], message: str) -> list[Outcome]:
    return [Outcome(e, sid, variant, "load", ERROR, message=message) for e in engines]


def primary_threshold(scene: Scene, metric: str | None = None) -> float | None:
    """The scene's ``[[check]] max`` (plus tolerance) on ``metric`` (default
    its primary metric) for its variant: the accuracy target of the report.
    Checks scoped to some engines count only when no unscoped one exists;
    the tightest wins."""
    metric = metric or scene.primary_metric
    if not metric:
        return None
    cands = [c for c in scene.checks if c.metric == metric and c.max is not None
             and (c.variants is None or (scene.variant or BASE) in c.variants)]
    use = [c for c in cands if c.engines is None] or cands
    return min(float(c.max) + float(c.tolerance or 0.0) for c in use) if use else None


def scene_columns(scene: Scene) -> dict[str, Any]:
    """The columns every check and sweep row carries from its scene, so that
    the report reads rows only (never the scene again): the primary metric,
    its threshold (:func:`primary_threshold`) and the scenario's tags (JSON
    list).  The verdicts go in ``checks`` (:func:`verdicts_column`)."""
    return {"primary_metric": scene.primary_metric, "primary_threshold": primary_threshold(scene),
            "tags": json.dumps(list(scene.tags))}


def run_verdicts(scene: Scene, result) -> list[Outcome]:
    """The scene's checks that apply to the result's engine and the scene's
    variant, without an @-setting, evaluated on ``result`` as ``physbench
    check`` does: a sweep point's verdicts."""
    return [evaluate_check(c, result) for c in applicable_checks(scene, result.engine)
            if not split_metric(c.metric)[1]]


def verdicts_column(outcomes: Iterable[Outcome]) -> str:
    """A row's ``checks`` column: its verdicts (Outcome.as_dict: metric,
    outcome, value, threshold, message as the reason, trace) as JSON."""
    return json.dumps([o.as_dict() for o in outcomes], sort_keys=True)


def scene_runs(scene: Scene, engine: str, settings: dict[str, Any] | None = None, path: str | None = None,
               phases: int | None = None, timeout_s: float | None = RUN_TIMEOUT_S) -> list[RunSpec]:
    """The runs that evaluating ``scene``'s checks on ``engine`` takes, the
    base run first (settings ``settings``, carrying the checks); then its
    step phases (``phases``, default the scene's); then one run per
    @-suffixed check setting (``settings`` with the suffix's over them).
    Empty when no check applies.  ``physbench check`` and ``physbench run``
    both plan with it, so both give the same verdict.  Each run has the
    wall-clock budget ``timeout_s``."""
    checks = applicable_checks(scene, engine) + hard_checks(scene)
    if not checks:
        return []
    settings = dict(settings or {})
    n = scene.phases if phases is None else phases
    extra = scene_columns(scene)
    runs = [RunSpec(scene.id, scene.variant, engine, settings, checks, phases=n, path=path, row_extra=extra,
                    timeout_s=timeout_s)]
    for i in range(1, n):
        runs.append(RunSpec(scene.id, scene.variant, engine, settings, [], phase=i / n, path=path, row_extra=extra,
                            timeout_s=timeout_s))
    suffixes = {}
    for c in checks:
        _, st = split_metric(c.metric)
        if st:
            suffixes[c.metric.partition("@")[2]] = st
    for st in suffixes.values():
        runs.append(RunSpec(scene.id, scene.variant, engine, {**settings, **st}, [], path=path, row_extra=extra,
                            timeout_s=timeout_s))
    return runs


def plan(scenario_ids: list[str], engines: list[str],
         timeout_s: float | None = RUN_TIMEOUT_S) -> tuple[list[RunSpec], list[Outcome]]:
    """Runs to make (each with the wall-clock budget ``timeout_s``), and
    ERROR outcomes for scenarios that fail to load.
    ``scenario_ids``: ids or spec file paths (:func:`select_scenarios`).
    Two files with the same id (family.stem) raise SpecError: their rows
    could not be told apart."""
    from contract.scene import load_scene, resolve_scenario
    from contract.spec import SpecError, load_spec

    runs: list[RunSpec] = []
    errors: list[Outcome] = []
    seen: dict[str, str] = {}
    for sid in scenario_ids:
        try:
            loaded = load_spec(resolve_scenario(sid))
        except Exception as e:
            errors += _load_error_outcomes(sid, None, engines, f"spec failed to load: {e}")
            continue
        # an id is run by its id; a file given by path is run from it
        path = str(loaded.path) if (Path(sid).suffix == ".toml" or Path(sid).exists()) else None
        for variant in [None, *loaded.variants]:
            try:
                scene = load_scene(sid, variant, loaded=loaded)
            except Exception as e:
                errors += _load_error_outcomes(sid, variant, engines, f"scene failed to compile: {e}")
                continue
            if variant is None:
                where = str(loaded.path.resolve())
                if seen.setdefault(scene.id, where) != where:
                    raise SpecError([f"{loaded.label}: <scenario>: id {scene.id!r} (family.stem) is also the id of "
                                     f"{seen[scene.id]}; rename one file or change its family"])
            for eng in engines:
                runs += scene_runs(scene, eng, path=path, timeout_s=timeout_s)
    return runs, errors


def execute(spec: RunSpec):
    """Run one RunSpec in this process (harness.execute.execute_request):
    never raises (engine import errors become a RunResult with status
    'failed').  The trace is dropped (results cross process boundaries)."""
    return execute_request(spec.request())


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

        def run_one(r: RunSpec):
            return execute(r)  # looked up at call time (tests patch it for inline runs)

        fn = run_one if executor in ("inline", "serial") else execute
        for r, value in ex.map(fn, runs, budget_s=lambda r: r.timeout_s,
                               on_start=lambda r: bar.update(task, description=escape(r.request().label))):
            res = lost_result(r.request(), value) if isinstance(value, WorkerLost) else value
            results[r.key] = res
            if on_result is not None:
                on_result(r, res)
            bar.advance(task)
    return results


def evaluate_runs(runs: list[RunSpec], results: dict[tuple, Any]) -> list[Outcome]:
    """Outcomes for every planned base run (runs with checks), each with the
    key of the run it was evaluated on."""
    outs: list[Outcome] = []
    for r in runs:
        if not r.checks:
            continue
        res = results[r.key]
        for c in r.checks:
            name, st = split_metric(c.metric)
            if st:
                key = RunSpec(r.scenario, r.variant, r.engine, {**r.settings, **st}).key
                other = results.get(key)
                if other is None:
                    o = Outcome(r.engine, r.scenario, r.variant, c.metric, ERROR,
                                threshold=describe_bound(c), message="run missing")
                else:
                    o = evaluate_check(c, other, name)
            elif r.phases > 1:
                per = [evaluate_check(c, res)]
                for i in range(1, r.phases):
                    other = results.get(r.key + (i / r.phases,))
                    per.append(evaluate_check(c, other) if other is not None else
                               Outcome(r.engine, r.scenario, r.variant, c.metric, ERROR,
                                       threshold=describe_bound(c), message=f"phase {i}/{r.phases} run missing"))
                o, key = _combine_phases(per, c), r.key
            else:
                o, key = evaluate_check(c, res), r.key
            o.key = key
            outs.append(o)
    return outs


_PHASE_MARK = {PASS: ".", XPASS: ".", FAIL: "x", XFAIL: "x", ERROR: "!", UNSUPPORTED: "-"}


def _combine_phases(per: list[Outcome], check: Check) -> Outcome:
    """One check's outcome over the N step phases of its scene (``per``,
    phase 0 first): it holds only if it holds in every phase.  ERROR if
    any phase errored (without an xfail); else FAIL (XFAIL with an xfail)
    if any phase failed; else PASS (XPASS with an xfail).  The message
    names the failing phases and the pattern (``.`` pass, ``x`` fail,
    ``!`` error) and carries the first failing phase's message; the value
    is phase 0's."""
    n = len(per)
    pattern = "".join(_PHASE_MARK.get(o.outcome, "?") for o in per)
    o0 = per[0]
    out = Outcome(o0.engine, o0.scenario, o0.variant, o0.metric, o0.outcome, o0.value, o0.threshold,
                  o0.message, sum(o.time_s for o in per))
    if all(o.outcome == UNSUPPORTED for o in per):
        return out
    if any(o.outcome == UNSUPPORTED for o in per):
        out.outcome = ERROR
        out.message = f"unsupported in some step phases only [{pattern}]: " + next(
            o.message for o in per if o.outcome == UNSUPPORTED)
        return out
    bad = [(i, o) for i, o in enumerate(per) if o.outcome in (FAIL, XFAIL, ERROR)]
    if not bad:
        out.message = f"all {n} step phases: {o0.message}"
        return out
    i, first = bad[0]
    errored = any(o.outcome == ERROR for _, o in bad)
    if errored:
        out.outcome = ERROR
    else:
        out.outcome = XFAIL if check.xfail.get(o0.engine) else FAIL
    out.value = first.value
    out.message = f"failed in {len(bad)} of {n} step phases [{pattern}]; phase {i}/{n}: {first.message}"
    return out


# ---------------------------------------------------------------------------
# reporting


def junit_xml(outcomes: list[Outcome]) -> ET.ElementTree:
    """JUnit XML: one <testsuite> per engine; testcase name
    '<scenario>[<variant>]::<metric>', classname 'physbench.<engine>.<family>'.
    FAIL -> <failure>; ERROR -> <error>; XPASS -> <failure> 'unexpected pass';
    XFAIL -> <skipped> 'xfail: reason'; UNSUPPORTED -> <skipped>.  A
    testcase with a trace (check --traces) carries it as
    ``<property name="trace" value="PATH"/>`` and a ``trace: PATH`` line in
    ``<system-out>``."""
    root = ET.Element("testsuites", name="physbench conformance")
    by_engine: dict[str, list[Outcome]] = {}
    for o in outcomes:
        by_engine.setdefault(o.engine, []).append(o)
    totals = dict(tests=0, failures=0, errors=0, skipped=0)
    for eng, outs in by_engine.items():
        counts = dict(tests=len(outs),
                      failures=sum(o.outcome in (FAIL, XPASS) for o in outs),
                      errors=sum(o.outcome == ERROR for o in outs),
                      skipped=sum(o.outcome in (XFAIL, UNSUPPORTED) for o in outs))
        t = sum(o.time_s for o in outs)
        suite = ET.SubElement(root, "testsuite", name=eng, time=f"{t:.3f}",
                              **{k: str(v) for k, v in counts.items()})
        for k in totals:
            totals[k] += counts[k]
        for o in outs:
            family = o.scenario.split(".")[0]
            tc = ET.SubElement(suite, "testcase", name=o.name, classname=f"physbench.{eng}.{family}",
                               time=f"{o.time_s:.3f}")
            if o.trace:
                props = ET.SubElement(tc, "properties")
                ET.SubElement(props, "property", name="trace", value=o.trace)
            if o.outcome == FAIL:
                ET.SubElement(tc, "failure", message=o.message, type="FAIL").text = _detail(o)
            elif o.outcome == XPASS:
                ET.SubElement(tc, "failure", message=o.message, type="XPASS").text = _detail(o)
            elif o.outcome == ERROR:
                ET.SubElement(tc, "error", message=o.message, type="ERROR").text = _detail(o)
            elif o.outcome in (XFAIL, UNSUPPORTED):
                ET.SubElement(tc, "skipped", message=o.message, type=o.outcome)
            if o.trace:
                ET.SubElement(tc, "system-out").text = f"trace: {o.trace}"
    for k, v in totals.items():
        root.set(k, str(v))
    return ET.ElementTree(root)


def _detail(o: Outcome) -> str:
    return f"metric {o.metric}: value {_fmt(o.value)}, threshold {o.threshold}\n{o.message}"


def write_junit(outcomes: list[Outcome], path: str | Path) -> None:
    tree = junit_xml(outcomes)
    ET.indent(tree)
    buf = io.BytesIO()
    tree.write(buf, encoding="utf-8", xml_declaration=True)
    write_text_atomic(buf.getvalue().decode("utf-8"), path)


def summarize(outcomes: list[Outcome], console=None) -> None:
    """Print a per engine x scenario count table and every FAIL/XPASS/ERROR."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    console = console or Console()
    engines = sorted({o.engine for o in outcomes})
    scenarios = sorted({o.scenario for o in outcomes})
    table = Table(title="conformance: checks per engine (pass/fail/xfail/xpass/unsupported/error)")
    table.add_column("scenario")
    for e in engines:
        table.add_column(e, justify="center")
    cells: dict[tuple[str, str], dict[str, int]] = {}
    for o in outcomes:
        cells.setdefault((o.scenario, o.engine), {k: 0 for k in OUTCOMES})[o.outcome] += 1
    for s in scenarios:
        row = [escape(s)]
        for e in engines:
            c = cells.get((s, e))
            row.append(_cell(c) if c else "-")
        table.add_row(*row)
    tot = {k: sum(o.outcome == k for o in outcomes) for k in OUTCOMES}
    console.print(table)
    console.print("totals: " + ", ".join(f"{k} {v}" for k, v in tot.items()))
    bad = [o for o in outcomes if o.outcome in BAD]
    if bad:
        t2 = Table(title="failures")
        for col in ("engine", "testcase", "outcome", "value", "threshold", "message"):
            t2.add_column(col, overflow="fold")
        for o in bad:
            t2.add_row(*(escape(x) for x in (o.engine, o.name, o.outcome, _fmt(o.value), o.threshold, o.message)))
        console.print(t2)


def _cell(c: dict[str, int]) -> str:
    parts = []
    style = {PASS: "green", FAIL: "red", XFAIL: "yellow", XPASS: "magenta", UNSUPPORTED: "dim", ERROR: "red"}
    for k in OUTCOMES:
        if c[k]:
            parts.append(f"[{style[k]}]{c[k]} {k.lower()}[/]")
    return " ".join(parts)


def exit_code(outcomes: list[Outcome]) -> int:
    return 1 if any(o.outcome in BAD for o in outcomes) else 0


# ---------------------------------------------------------------------------
# entry point


def _row(key: tuple, result: Any) -> dict[str, Any]:
    row = result.row()
    # the step phase of the run (a 5th key element; 0 = the scene as written)
    row["phase"] = float(key[4]) if len(key) > 4 else 0.0
    return row


def save_rows(results: dict[tuple, Any], save_dir: str | Path | None) -> Path | None:
    """Every run's result row to ``<save_dir>/<UTC timestamp>.parquet``
    (default results/check/) in one file; a failure to write is reported,
    not fatal.  (``check_main`` stores rows as they finish instead.)"""
    from harness.results import RESULTS_DIR, write_rows

    if not results:
        return None
    d = Path(save_dir) if save_dir is not None else RESULTS_DIR / "check"
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    rows = [_row(key, r) for key, r in results.items()]
    try:
        return write_rows(rows, d / f"{stamp}.parquet", append=False)
    except Exception as e:  # pragma: no cover - disk trouble must not hide the verdict
        print(f"warning: could not write result rows: {type(e).__name__}: {e}", file=sys.stderr)
        return None


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
    from harness.execute import request_scene, run_requests
    from harness.trace.cases import TRACED_OUTCOMES, case_name, write_case_trace
    from harness.trace.contacts import DEFAULT_CAP

    base = {(r.scenario, r.variant, r.engine): r for r in runs if r.checks}
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


# ---------------------------------------------------------------------------
# the check's store: one part per finished run, resumable


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def check_identity(ids: list[str], engines: list[str], runs: list[RunSpec], timeout_s: float | None) -> dict[str, Any]:
    """What makes two checks "the same" (resumable one from the other): the
    commit (a dirty tree counts as its commit: code edited between the
    kill and the rerun is not noticed), the engines, the scenario ids, the
    bytes of their spec files (sha256), the per-run budget, and the planned
    run keys."""
    from harness.runner import commit_id
    from contract.scene import resolve_scenario

    h = hashlib.sha256()
    for sid in ids:
        h.update(sid.encode() + b"\0")
        try:
            h.update(resolve_scenario(sid).read_bytes())
        except Exception as e:  # reported as a load error outcome
            h.update(repr(e).encode())
        h.update(b"\0")
    return {"commit": commit_id(), "engines": list(engines), "scenarios": list(ids),
            "specs_hash": h.hexdigest()[:16], "timeout_s": timeout_s, "runs": [r.run_key for r in runs]}


def open_check(root: Path, ident: dict[str, Any], resume: bool = True):
    """The unfinished check under ``root`` to resume (same identity, see
    :func:`check_identity`, not locked by a running check), or a new one.
    Returns (harness.results.PartsDir keyed by ``run_key``, resumed)."""
    from harness.results import PartsDir, SCHEMA_VERSION, try_lock, unfinished_dirs, write_json_atomic

    if resume:
        for d, man in unfinished_dirs(root):
            if (d.parent / f"{d.name}.parquet").exists():
                continue  # consolidated; only its directory was left behind
            if any(man.get(k) != v for k, v in ident.items()):
                continue
            fd = try_lock(d)
            if fd < 0:
                continue
            man.setdefault("resumed", []).append(_now())
            write_json_atomic(man, d / "manifest.json")
            return PartsDir(d, man, fd, "run_key"), True
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    base = f"{stamp}-{re.sub(r'[^A-Za-z0-9.+_-]', '_', ident['commit'])}"
    cid, n = base, 0
    while (root / cid).exists() or (root / f"{cid}.parquet").exists():
        n += 1
        cid = f"{base}-{n}"
    d = root / cid
    d.mkdir(parents=True)
    fd = try_lock(d)
    man = {"schema_version": SCHEMA_VERSION, "check_id": cid, "started": _now(), "finished": None, **ident}
    write_json_atomic(man, d / "manifest.json")
    return PartsDir(d, man, fd, "run_key"), False


def check_main(engines: list[str] | None, tags: list[str] | None, junit: str | None,
               scenarios: list[str] | None, jobs: int = 1, save_dir: str | Path | None = None,
               timeout_s: float | None = RUN_TIMEOUT_S, executor: str = "process", resume: bool = True,
               traces: str | Path | None = None, scheduler: str | None = None) -> int:
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
    on local worker processes).  Returns 1 on any FAIL, ERROR or XPASS, else 0; raises
    SpecError for a scenario id or file that does not exist (exit 2)."""
    from rich.console import Console

    from harness.results import RESULTS_DIR, consolidate_parts
    from harness.runner import RunResult
    from contract.scene import resolve_scenario
    from contract.spec import SpecError

    t0 = time.perf_counter()
    engines = list(engines) if engines else default_engines()
    ids = select_scenarios(scenarios, tags)  # raises SpecError for an unknown id, file or folder
    err = Console(stderr=True)
    if not ids:
        err.print(f"no scenarios selected (tags: {tags}, scenarios: {scenarios})")
        return 1
    runs, load_errors = plan(ids, engines, timeout_s)
    root = Path(save_dir) if save_dir is not None else RESULTS_DIR / "check"
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
        row = _row(r.key, res)
        row.update(r.row_extra)
        row.update(run_key=r.run_key, check_id=store.path.name)
        try:
            store.write_part(row, {"check_id": store.path.name})
        except Exception as e:  # disk trouble must not hide the verdict
            err.print(f"warning: could not store the row of {r.run_key}: {type(e).__name__}: {e}", markup=False)

    refused: tuple = ()
    if executor == "dask":
        from harness.dask_executor import EnvironmentRefused

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
        saved, _ = consolidate_parts(store.path, "run_key", [r.run_key for r in runs], _now(), columns=columns)
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
