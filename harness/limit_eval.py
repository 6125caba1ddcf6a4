"""One evaluation of a breaking-point search, and a search over them.

:func:`evaluate_point` runs the scene at one value in one step phase and
turns the run into a stored row with its verdict (the only function that
runs an engine; small so that it can move onto another execution path);
:func:`search_items` drives the pure search (harness/limit_search.py) with
such rows, reading finished ones back; :func:`run_search` runs it in this
process.  The command and its store are harness/limits.py.

The criterion.  A value *holds* when, in every one of the N step phases
(``contract/phase.py``; phase 0 is the scene as written), the run is ``ok``,
its ``stable`` metric is true (every recorded value finite, no energy
blow-up) and it meets every applicable check of the scene (the checks
``physbench check`` evaluates, with the same bounds; an ``xfail`` marks a
known limitation but does not make a failed check hold; checks bound to other
settings, ``metric@dt=...``, are left out: the searched value replaces
them).  ``checks`` restricts the criterion to checks of the named metrics
(stability always counts).  Phases stop at the first failing one.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
import traceback
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Generator

from physbench.adapters import get_adapter
from physbench.contract.metric_defs import GENERIC_METRICS
from physbench.contract.phase import phase_values
from physbench.contract.scene import load_scene, resolve_scenario
from physbench.contract.spec import SpecError, parse_key_path
from physbench.contract.spec.schema import integer_key
from physbench.harness.conformance import FAIL, PASS, applicable_checks, evaluate_check, split_metric
from physbench.harness.execute import RunRequest
from physbench.harness.limit_search import UNSUPPORTED, SearchResult, Verdict, drive, search_rounds
from physbench.harness.points import cached_scene, cached_spec, lost_row, request_row
from physbench.harness.references import get_model

#: row kinds (column ``row_kind``): one row per run of a search, one per search
EVAL_ROW, RESULT_ROW = "limit_eval", "limit"


# ---------------------------------------------------------------------------
# one evaluation: run the scene at one value in one phase


@dataclass(frozen=True)
class LimitRequest:
    """One search: ``scenario`` (an id or a spec file path) and ``variant``
    on ``engine``; ``param`` moved over [``lo``, ``hi``]; a value holds only
    in all ``phases`` step phases; ``tol`` relative; ``checks``: only checks
    of these metrics count (empty: all); ``settings``: fixed engine settings
    (not the searched one); ``overrides``: fixed dotted spec keys applied
    before the searched one (``scenario.duration``, a wall's position);
    ``bounds``: extra (metric, max) criteria (``energy_gain`` <= 0.01: where
    energy starts to grow); ``timeout_s`` per run."""

    scenario: str
    variant: str | None
    engine: str
    param: str
    lo: float
    hi: float
    phases: int = 1
    tol: float = 0.05
    checks: tuple[str, ...] = ()
    settings: tuple[tuple[str, Any], ...] = ()
    overrides: tuple[tuple[str, Any], ...] = ()
    bounds: tuple[tuple[str, float], ...] = ()
    timeout_s: float = 600.0

    @property
    def label(self) -> str:
        return self.scenario + (f"[{self.variant}]" if self.variant else "")

    def identity(self, spec_hash: str) -> str:
        """16 hex digits naming the search: scene file content, variant,
        engine, parameter, range, phases, tol, checks, fixed settings and
        overrides."""
        text = json.dumps([spec_hash, self.label, self.engine, self.param, self.lo, self.hi, self.phases,
                           self.tol, list(self.checks), [list(s) for s in self.settings],
                           [list(o) for o in self.overrides], [list(b) for b in self.bounds]], default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def eval_key(self, limit_id: str, value: float, phase: float) -> str:
        """Stable key of one evaluation (the row's ``point_key``)."""
        return f"limit:{limit_id}|{self.label}|{self.engine}|{self.param}={value!r}|phase={phase!r}"


def is_engine_setting(engine: str, param: str) -> bool:
    return param in _setting_names(get_adapter(engine))


@lru_cache(maxsize=64)
def _setting_names(cls: type) -> frozenset[str]:
    """An adapter class's setting names (its capabilities cost up to a ms
    each; a sweep's client asks for every evaluation it hands out)."""
    return frozenset(cls.capabilities().settings)


@lru_cache(maxsize=1024)
def _integer_key(param: str) -> bool:
    return integer_key(param)  # the schema walk costs ~0.2 ms; asked once per evaluation


def _fill_vector(loaded: Any, variant: str | None, path: str) -> dict[str, Any]:
    """Overrides that make ``path`` settable: when ``path`` names an element
    of a vector the spec leaves at its default (``body[0].velocity[0]`` of a
    body written without ``velocity``), the whole vector at its validated
    default."""

    parts = parse_key_path(path)
    if not isinstance(parts[-1], int) or len(parts) < 2:
        return {}
    model = loaded.validated(variant).model_dump()
    node: Any = model
    for p in parts[:-1]:
        try:
            node = node[p]
        except (KeyError, IndexError, TypeError):
            return {}
    raw: Any = loaded.raw
    for p in parts[:-1]:
        try:
            raw = raw[p]
        except (KeyError, IndexError, TypeError):
            prefix = path[: path.rfind("[")]
            return {prefix: list(node)} if isinstance(node, (list, tuple)) else {}
    return {}


def _spec_value(param: str, value: float) -> float | int:
    """``value`` as the spec key ``param`` takes it: a whole number as an
    int for an integer key (a count), else unchanged (a fraction stays a
    float, which the spec then refuses with the key's path)."""
    if _integer_key(param) and float(value).is_integer():
        return int(value)
    return value


def load_at(req: LimitRequest, value: float):
    """The request's scene with the searched spec key set to ``value`` (for
    an engine setting, the scene as written).  Raises SpecError (a value the
    spec does not accept: a negative mass, a restitution over 1)."""

    loaded = cached_spec(resolve_scenario(req.scenario))
    overrides = dict(req.overrides)
    if is_engine_setting(req.engine, req.param):
        return load_scene(req.scenario, req.variant, overrides or None, loaded=loaded)
    overrides.update(_fill_vector(loaded, req.variant, req.param))
    overrides[req.param] = _spec_value(req.param, value)
    return load_scene(req.scenario, req.variant, overrides, loaded=loaded)


def _criterion_checks(scene: Any, engine: str, checks: tuple[str, ...]) -> list[Any]:
    """The scene's checks the criterion evaluates: applicable to ``engine``,
    not bound to other settings, of a metric in ``checks`` (empty: all)."""

    out = []
    for c in applicable_checks(scene, engine):
        name, bound = split_metric(c.metric)
        if not bound and not (checks and name not in checks):
            out.append(c)
    return out


def skipped_model_metrics(scene: Any, engine: str, checks: tuple[str, ...] = (),
                          bounds: tuple[tuple[str, float], ...] = ()) -> tuple[str, ...]:
    """The reference model's metrics an evaluation need not compute: all
    those the scene's model declares (``produces``) when the criterion
    (:func:`judge` with these ``checks`` and ``bounds``) reads only harness
    metrics (contract.metric_defs.GENERIC_METRICS); () when it reads any
    other metric (the model's, or one no declaration names) or the scene
    has no model.  Decided from the scene before the run.  No model
    produces a harness metric's name, so the criterion never reads a
    metric skipped here (tests/test_limits_model_metrics.py::
    test_the_criterion_never_reads_a_skipped_metric)."""

    if not scene.reference_model:
        return ()
    read = {split_metric(c.metric)[0] for c in _criterion_checks(scene, engine, checks)} | {m for m, _ in bounds}
    if read - set(GENERIC_METRICS):
        return ()

    return tuple(sorted(get_model(scene.reference_model).produces))


def judge(scene: Any, result: Any, checks: tuple[str, ...] = (),
          bounds: tuple[tuple[str, float], ...] = ()) -> tuple[bool, str]:
    """Whether one run holds (module docstring), and if not, why: the first
    failure as ``metric: message``.  ``checks``: only the scene's checks of
    these metrics (``("stable",)``: stability alone); ``bounds``: extra
    (metric, max) criteria, a missing or NaN value failing."""

    if result.status != "ok":
        return False, f"status {result.status}: {result.message}"
    stable = result.metrics.get("stable")
    if stable is not None and not bool(stable):
        why = result.metrics.get("stability_reason") or "a recorded value is not finite or energy blew up"
        return False, f"stable: {why}"
    for c in _criterion_checks(scene, result.engine, checks):
        o = evaluate_check(dataclasses.replace(c, xfail={}), result)
        if o.outcome != PASS:
            return False, f"{c.metric}: {o.message}" if o.outcome == FAIL else f"{c.metric}: {o.outcome} {o.message}"
    for metric, hi in bounds:
        try:
            x = float(result.metrics.get(metric))
        except (TypeError, ValueError):
            x = math.nan
        if not x <= hi:
            return False, f"{metric}: {metric} = {x:.6g}, expected <= {hi:g}" if math.isfinite(x) else \
                f"{metric}: metric not computed"
    return True, ""


def evaluate_point(req: LimitRequest, limit_id: str, value: float, phase: float) -> dict[str, Any]:
    """Run the request's scene with the parameter at ``value`` in step phase
    ``phase`` and return its row (harness.points.request_row of the
    evaluation's request: ``RunResult.row()``, the sweep's point columns
    and the ``limit_*`` columns, ``limit_holds`` and ``limit_reason``).
    Never raises: a scene the value makes invalid, a run that raises, are
    rows whose verdict fails with the reason."""
    return request_row(EvalItem(req, limit_id, value, phase).request())


def _eval_columns(item: "EvalItem", holds: bool, reason: str, unsupported: bool, cpu: float,
                  skipped: tuple[str, ...]) -> dict[str, Any]:
    """The columns every evaluation row carries, whatever became of the run
    (:func:`evaluate_point`, :func:`lost_eval_row`): its key, the search and
    value, the verdict, the step CPU (s) and ``limit_skipped_metrics``, the
    one record of the model metrics it did not compute, comma-separated
    ("" when it computed all or none ran).  Test:
    tests/test_limits_model_metrics.py::test_every_eval_row_records_the_skipped_metrics_once."""
    return {"row_kind": EVAL_ROW, "point_key": item.key, "limit_id": item.limit_id, "limit_param": item.req.param,
            "limit_value": float(item.value), "phase": float(item.phase), "limit_holds": bool(holds),
            "limit_reason": reason, "limit_unsupported": bool(unsupported), "limit_cpu_s": float(cpu),
            "limit_skipped_metrics": ",".join(skipped)}


def verdict_of_rows(rows: list[dict[str, Any]]) -> Verdict:
    """A value's verdict from its phase rows (phase order): holds only if
    every row holds; the reason is the first failing phase's."""
    n = len(rows)
    cpu = float(sum(float(r.get("limit_cpu_s") or 0.0) for r in rows))
    for i, r in enumerate(rows):
        if r.get("limit_unsupported"):
            return Verdict(False, f"unsupported: {r.get('message', '')}", n, cpu, unsupported=True)
        if not r.get("limit_holds"):
            where = f" (step phase {float(r.get('phase') or 0.0):g})" if r.get("phase") else ""
            return Verdict(False, f"{r.get('limit_reason', '')}{where}", n, cpu)
    return Verdict(True, "", n, cpu)


# ---------------------------------------------------------------------------
# running a search with stored, resumable rows


Runner = Callable[[LimitRequest, str, float, float], dict[str, Any]]


def spec_hash(req: LimitRequest) -> str:
    return hashlib.sha256(Path(resolve_scenario(req.scenario)).read_bytes()).hexdigest()[:16]


def _filled(req: LimitRequest) -> tuple[tuple[str, Any], ...]:
    """:func:`_fill_vector` of the searched key (it does not depend on the
    value); () for an engine setting or a scene that does not load."""
    return _filled_at(req.scenario, req.variant, req.engine, req.param)


@lru_cache(maxsize=256)
def _filled_at(scenario: str, variant: str | None, engine: str, param: str) -> tuple[tuple[str, Any], ...]:
    if is_engine_setting(engine, param):
        return ()
    try:
        return tuple(_fill_vector(cached_spec(resolve_scenario(scenario)), variant, param).items())
    except Exception:
        return ()  # the run's own load reports it


@dataclass(frozen=True)
class EvalItem:
    """One evaluation of a search: ``req``'s scene with the parameter at
    ``value`` in step phase ``phase``.  ``key`` is the row's point key.
    The executors run its :meth:`request`, whose ``probe`` it is: it adds
    the evaluation's columns (its verdict, :func:`judge`) to the one row
    builder's row (harness.points.request_row, failure_row)."""

    req: LimitRequest
    limit_id: str
    value: float
    phase: float

    @property
    def key(self) -> str:
        return self.req.eval_key(self.limit_id, self.value, self.phase)

    def request(self) -> RunRequest:
        """The run of this evaluation: the engine setting, or the spec key
        (the fixed overrides, the vector it is an element of, then the
        value), at the step phase, one run within the search's timeout."""
        req = self.req
        settings = dict(req.settings)
        overrides = dict(req.overrides)
        if is_engine_setting(req.engine, req.param):
            settings[req.param] = self.value
        else:
            overrides.update(copy.deepcopy(dict(_filled(req))))  # a vector default: a list of its own
            overrides[req.param] = _spec_value(req.param, self.value)
        return RunRequest(req.scenario, req.engine, req.variant, settings, overrides, phase=self.phase,
                          timeout_s=req.timeout_s, key=self.key, probe=self)

    def skipped_metrics(self, scene: Any) -> tuple[str, ...]:
        return skipped_model_metrics(scene, self.req.engine, self.req.checks, self.req.bounds)

    def load_error(self, e: BaseException) -> tuple[str, str | None]:
        """(message, traceback) of a scene the value does not load into."""

        msg = "; ".join(e.errors) if isinstance(e, SpecError) else f"{type(e).__name__}: {e}"
        return f"{self.req.param}={self.value!r}: {msg}", \
            None if isinstance(e, SpecError) else traceback.format_exc(limit=5)

    def columns(self, scene: Any, result: Any, skipped: tuple[str, ...]) -> dict[str, Any]:
        """The evaluation's columns of a run: its verdict and step CPU."""
        holds, reason = judge(scene, result, self.req.checks, self.req.bounds)
        cpu = float(result.timing.get("step_cpu_s", 0.0) or 0.0)
        return _eval_columns(self, holds, reason, result.status == "unsupported", cpu, skipped)

    def failed_columns(self, message: str) -> dict[str, Any]:
        """The evaluation's columns when it produced no run: fails, for ``message``."""
        return _eval_columns(self, False, message, False, 0.0, ())


def evaluate_item(item: EvalItem) -> dict[str, Any]:
    """The row of one EvalItem (harness.points.request_row of its request)."""
    return request_row(item.request())


def lost_eval_row(item: EvalItem, lost: Any) -> dict[str, Any]:
    """The row of an evaluation whose worker died, hung or raised
    (``lost``: a harness.execute.WorkerLost): its status and message, and
    a verdict that does not hold for that reason (harness.points.lost_row)."""
    return lost_row(item.request(), lost)


def _decided(rows: list[dict[str, Any] | None]) -> bool:
    """Whether a value's verdict is known from its phase rows (phase order,
    None where not run): every phase up to and including the first failing
    one, or all phases, have a row."""
    for r in rows:
        if r is None:
            return False
        if not r.get("limit_holds"):
            return True
    return True


#: the scenes of searches' summaries that set spec keys, by (scenario, variant, repr of the keys set)
_SUMMARY_SCENES: dict[tuple[str, str | None, str], Any] = {}


def _summary_scene(req: LimitRequest) -> Any:
    """The scene a search's summary row names (its id, primary metric):
    loaded once per process for every search of the same scenario, variant
    and spec keys set (a suite's ``[[limit]]`` block is one search per
    engine), a scene without keys set from the per-process cache the
    suite's check filled (harness.points.cached_scene)."""
    if not req.overrides:
        return cached_scene(req.scenario, req.variant)
    key = (req.scenario, req.variant, repr(req.overrides))
    if key not in _SUMMARY_SCENES:
        _SUMMARY_SCENES[key] = load_scene(req.scenario, req.variant, dict(req.overrides))
    return _SUMMARY_SCENES[key]


def search_items(req: LimitRequest, store: Callable[[dict[str, Any]], None], cached: dict[str, dict[str, Any]],
                 width: int | Callable[[], int] = 1
                 ) -> Generator[list[EvalItem], list[dict[str, Any]], tuple[SearchResult, dict[str, Any]]]:
    """Search ``req`` as a generator: yields each round of evaluations to
    run at once (a list of RunRequests, each with its :class:`EvalItem` as
    ``probe``), receives their rows (a list, in the same order), returns
    (result, summary row).

    ``width`` (a number, or a function asked before each round): at most
    this many items a round (at least one).  The pure search
    (:func:`harness.limit_search.search_rounds`) gets ``width // phases``
    values a round (at least one); a value's step phases run side by side,
    up to ``width`` at a time, in phase order, and a value is decided once
    its phases up to the first failing one have rows (its verdict is
    :func:`verdict_of_rows` of those: the reason is the first failing
    phase's, as one phase after the other).  Width 1 is the one-at-a-time
    search: one item a round, phases in order, stopping at the first
    failing one.  Evaluations whose key is in ``cached`` are read back (not
    yielded); every new row is handed to ``store``.  The summary row
    (``row_kind`` = ``limit``) is the caller's to store.  Tests:
    tests/test_schedule.py::test_wide_rounds_give_the_serial_answers_sooner."""

    limit_id = req.identity(spec_hash(req))
    phases = phase_values(req.phases)
    if is_engine_setting(req.engine, req.param):
        integer = get_adapter(req.engine).capabilities().settings[req.param].kind is int
    else:
        integer = integer_key(req.param)  # a count (body[k].pattern.count): whole numbers
    wide: Callable[[], int] = width if callable(width) else (lambda: int(width))
    budget = [1]

    def values_per_round() -> int:
        budget[0] = max(1, int(wide()))
        return max(1, budget[0] // len(phases))

    new_runs = rounds = 0
    steps = search_rounds(req.lo, req.hi, req.tol, integer=integer, param=req.param, width=values_per_round)
    try:
        values = next(steps)
        while True:
            rows = {v: [cached.get(EvalItem(req, limit_id, v, f).key) for f in phases] for v in values}
            first_round = True
            while not all(_decided(rows[v]) for v in values):
                n = budget[0] if first_round else max(1, int(wide()))
                first_round = False
                todo: list[tuple[float, int]] = []
                for v in values:  # the phases a value still needs: those before its first known failure
                    for i, r in enumerate(rows[v]):
                        if r is not None and not r.get("limit_holds"):
                            break
                        if r is None:
                            todo.append((v, i))
                items = [EvalItem(req, limit_id, v, phases[i]).request() for v, i in todo[:n]]
                got = yield items
                rounds += 1
                for (v, i), row in zip(todo[:n], got):
                    store(row)
                    new_runs += 1
                    rows[v][i] = row
            verdicts = {}
            for v in values:
                done = []
                for r in rows[v]:
                    if r is None:
                        break
                    done.append(r)
                    if not r.get("limit_holds"):
                        break
                ran = [r for r in rows[v] if r is not None]  # a wide round may have run phases past the failing one
                verdicts[v] = dataclasses.replace(verdict_of_rows(done), runs=len(ran), cpu_s=float(
                    sum(float(r.get("limit_cpu_s") or 0.0) for r in ran)))
            values = steps.send(verdicts)
    except StopIteration as stop:
        res: SearchResult = stop.value
    res.rounds = rounds  # rounds of runs (a value's phases may take several; rows read back take none)
    scene = _summary_scene(req)
    summary = {
        "row_kind": RESULT_ROW, "point_key": f"limit:{limit_id}", "limit_id": limit_id,
        "scenario": scene.id, "variant": req.variant, "engine": req.engine,
        "status": "unsupported" if res.outcome == UNSUPPORTED else "ok", "message": res.failed_check,
        "primary_metric": scene.primary_metric, "limit_param": req.param, "limit_outcome": res.outcome,
        "limit_value": math.nan if res.limit is None else float(res.limit),
        "limit_lo": res.bracket[0] if res.bracket else math.nan,
        "limit_hi": res.bracket[1] if res.bracket else math.nan,
        "limit_direction": res.direction, "limit_failed_check": res.failed_check,
        "limit_runs": res.runs, "limit_new_runs": new_runs, "limit_rounds": res.rounds, "limit_cpu_s": res.cpu_s,
        "limit_range_lo": float(req.lo), "limit_range_hi": float(req.hi), "limit_tol": req.tol,
        "limit_phases": req.phases, "limit_checks": ",".join(req.checks),
        "limit_settings": json.dumps(dict(req.settings), sort_keys=True, default=str),
        "limit_overrides": json.dumps(dict(req.overrides), sort_keys=True, default=str),
    }
    return res, summary


def run_search(req: LimitRequest, store: Callable[[dict[str, Any]], None], cached: dict[str, dict[str, Any]],
               evaluate: Runner = evaluate_point) -> tuple[SearchResult, dict[str, Any]]:
    """Search ``req`` in this process, one evaluation after the other
    (:func:`search_items` driven by ``evaluate``).  Returns the result and
    its summary row (the caller stores it).  A sweep runs its searches
    concurrently with its points instead: harness/schedule.py."""
    return drive(search_items(req, store, cached),
                 lambda reqs: [evaluate(r.probe.req, r.probe.limit_id, r.probe.value, r.probe.phase) for r in reqs])
