"""Check evaluation: the outcome vocabulary, ``Outcome``, bounds and their
evaluation on a run, the implicit stability checks of hard scenes, the
combination over step phases, and the columns a row carries from its scene
(primary metric, threshold, tags, verdicts).  No I/O."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Iterable

from physbench.contract.metric_defs import CONSENSUS_METRICS, ENSEMBLE_METRICS
from physbench.harness import status as st
from physbench.harness.references import undefined_reason
from physbench.contract.scene import Check, Scene
from physbench.contract.xfail import xfail_for
from physbench.harness.runner import jsonable

HARD_DT_LABEL = "1/30"
BASE = "base"  # name standing for the base scenario in a check's `variants`

# the outcome vocabulary (harness/status.py) under the names used here
PASS, FAIL, XFAIL, XPASS, UNSUPPORTED, ERROR = st.PASS, st.FAIL, st.XFAIL, st.XPASS, st.CHECK_UNSUPPORTED, st.CHECK_ERROR
BAD = st.BAD_OUTCOMES
OUTCOMES = st.OUTCOMES
ERROR_STATUSES = st.ERROR_STATUSES


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
    #: the check's numeric bounds (max, min, equals +- tolerance), for
    #: printing the value with the digits that tell it from them (:func:`fmt_measured`)
    bounds: tuple = ()

    def as_dict(self) -> dict[str, Any]:
        """The outcome as stored in a row's ``checks`` column and printed by
        ``physbench run --json``; ``trace``: the absolute path of its
        ``.rrd`` or "" (docs/TRACES.md)."""
        return {"metric": self.metric, "outcome": self.outcome, "value": jsonable(self.value),
                "threshold": self.threshold, "message": self.message, "trace": self.trace}

    @property
    def name(self) -> str:
        v = f"[{self.variant}]" if self.variant else ""
        return f"{self.scenario}{v}::{self.metric}"


def case_names(outcomes: list[Outcome]) -> list[str]:
    """Each outcome's test-case name, unique per engine: ``Outcome.name``
    (``scenario[variant]::metric``, the @-setting part of the metric), and
    where two checks of one engine share it (the same metric bounded twice)
    the bound as well, ``...::max_penetration[<= 0.001]``; a check written
    twice with the same bound gets ``#2``, ``#3`` after the first
    (tests/test_conformance.py::test_junit_case_names_are_unique)."""
    from collections import Counter

    base = [(o.engine, o.name) for o in outcomes]
    dup = Counter(base)
    named = [(e, f"{n}[{o.threshold}]" if dup[(e, n)] > 1 else n) for (e, n), o in zip(base, outcomes)]
    dup2, seen = Counter(named), Counter()
    out = []
    for e, n in named:
        if dup2[(e, n)] > 1:
            seen[(e, n)] += 1
            if seen[(e, n)] > 1:
                n = f"{n}#{seen[(e, n)]}"
        out.append(n)
    return out


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


def _num(x: float) -> str:
    """A bound as written: the shortest text that reads back as the same
    float ('0.001', '1e-06', '0.0123456789'), never rounded to 6 digits."""
    x = float(x)
    for p in range(6, 18):
        text = f"{x:.{p}g}"
        if float(text) == x:
            return text
    return repr(x)


def describe_bound(check: Check) -> str:
    tol = f" +- {_num(check.tolerance)}" if check.tolerance else ""
    if check.equals is not None:
        return f"== {check.equals!r}{tol}" if isinstance(check.equals, bool) else f"== {_num(check.equals)}{tol}"
    parts = []
    if check.min is not None:
        parts.append(f">= {_num(check.min)}")
    if check.max is not None:
        parts.append(f"<= {_num(check.max)}")
    return " and ".join(parts) + tol


def check_bounds(check: Check) -> tuple[float, ...]:
    """The numbers a value is compared with: max + tol, min - tol,
    equals -+ tol (booleans: none)."""
    tol = float(check.tolerance or 0.0)
    if check.equals is not None:
        return () if isinstance(check.equals, bool) else (float(check.equals) - tol, float(check.equals) + tol)
    return tuple(float(b) for b in ((None if check.max is None else check.max + tol),
                                    (None if check.min is None else check.min - tol)) if b is not None)


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


def fmt_measured(value: Any, bounds: Iterable[float] = ()) -> str:
    """A metric value in a verdict: 6 significant digits, or as many more
    as it takes to tell it from each of ``bounds`` -- the digits that show
    why 0.0010000000000002507 fails ``<= 0.001`` (the text then reads back
    on the same side of every bound as the value;
    tests/test_conformance.py::test_verdict_prints_the_digits_that_decide_it)."""
    if isinstance(value, bool) or value is None:
        return repr(value)
    try:
        v = float(value)
    except (TypeError, ValueError):
        return repr(value)
    if not math.isfinite(v):
        return repr(v)
    bounds = [float(b) for b in bounds]
    for p in range(6, 18):
        text = f"{v:.{p}g}"
        r = float(text)
        if all((r < b) == (v < b) and (r > b) == (v > b) for b in bounds):
            return text
    return repr(v)


def evaluate_check(check: Check, result, metric_name: str | None = None) -> Outcome:
    """Evaluate one check against one RunResult.  ``metric_name`` is the
    metric to read (default: the check's metric without an @-suffix)."""
    metric = metric_name or split_metric(check.metric)[0]
    # a known limitation applies within the engine versions it was measured
    # for; outside them the check is a plain one and says so (contract/xfail.py)
    reason, version_note = xfail_for(check.xfail, result.engine, getattr(result, "engine_version", "") or "",
                                     getattr(result, "variant", None))
    o = Outcome(result.engine, result.scenario, result.variant, check.metric, PASS,
                threshold=describe_bound(check), time_s=float(result.timing.get("step_wall_s", 0.0) or 0.0),
                bounds=check_bounds(check))
    if result.status == st.UNSUPPORTED:
        o.outcome, o.message = UNSUPPORTED, f"unsupported: {result.message}"
        return o
    if result.status in ERROR_STATUSES or result.status != st.OK:
        msg = f"{result.status}: {result.message}"
        if reason:
            o.outcome, o.message = XFAIL, f"xfail: {reason} ({msg})"
        else:
            o.outcome, o.message = ERROR, msg + (f" [{version_note}]" if version_note else "")
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
        why = undefined_reason(result.metrics, metric)
        if why:
            o.message += f" (undefined on this run: {why})"
        return o
    else:
        ok = meets(check, value)
        msg = f"{metric} = {fmt_measured(value, o.bounds)}, expected {o.threshold}"
        if metric == "stable" and not ok and result.metrics.get("stability_reason"):
            msg += f" ({result.metrics['stability_reason']})"
    if reason:
        if ok:
            o.outcome, o.message = XPASS, f"unexpected pass: {msg}; xfail reason was: {reason}"
        else:
            o.outcome, o.message = XFAIL, f"xfail: {reason} ({msg})"
    else:
        o.outcome, o.message = (PASS, msg) if ok else (FAIL, msg)
    if version_note:
        o.message += f" [{version_note}]"
    return o


def applicable_checks(scene: Scene, engine: str) -> list[Check]:
    """The scene's checks that apply to a run of ``engine`` and the scene's
    variant (including @-suffixed ones); not those a run cannot answer,
    on an ensemble's or the engines' consensus's measures
    (:func:`judged_apart`: ``physbench check`` plans their own runs)."""
    return [c for c in scene.checks if check_applies(c, engine, scene.variant) and not judged_apart(c)]


def judged_apart(check: Check) -> bool:
    """Whether ``check`` bounds a measure of the scene's ensemble
    (contract.metric_defs.ENSEMBLE_METRICS) or of the engines' consensus
    (CONSENSUS_METRICS): evaluated on a run of its own, never a plain run's."""
    name = split_metric(check.metric)[0]
    return name in ENSEMBLE_METRICS or name in CONSENSUS_METRICS


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


_PHASE_MARK = {PASS: ".", XPASS: ".", FAIL: "x", XFAIL: "x", ERROR: "!", UNSUPPORTED: "-"}


def combine_phases(per: list[Outcome], check: Check) -> Outcome:
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
                  o0.message, sum(o.time_s for o in per), bounds=check_bounds(check))
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
        # the xfail applied in the phases (it depends on the engine's version)
        out.outcome = XFAIL if any(o.outcome in (XFAIL, XPASS) for o in per) else FAIL
    out.value = first.value
    out.message = f"failed in {len(bad)} of {n} step phases [{pattern}]; phase {i}/{n}: {first.message}"
    return out
