"""Breaking points: ``physbench limits``.

Where does an engine stop holding a scene?  One parameter -- an engine
setting (``dt``, ``iterations``) or any dotted spec key, an element of a
vector included (``body[0].velocity[0]``, ``body[1].mass``,
``material.default.restitution``) -- is moved over a range, and the search
finds the value at which the scene stops meeting its checks or stops being
stable.

Three layers, kept apart so that the search can be tested on a fake
criterion:

- :func:`search` -- pure logic: bracket, then bisect, on a criterion
  ``value -> Verdict``; no runs, no storage.
- :func:`evaluate_point` -- one run of one value in one step phase, turned
  into a stored row with its verdict (the only function that runs an
  engine; small so that it can move onto another execution path).
- :class:`LimitStore` and :func:`limits_main` -- rows stored like sweep rows
  (``harness/sweep_store.py``: atomic parts, resumable: a rerun reads finished
  evaluations back instead of running them again).

The criterion.  A value *holds* when, in every one of the N step phases
(``contract/phase.py``; phase 0 is the scene as written), the run is ``ok``,
its ``stable`` metric is true (every recorded value finite, no energy
blow-up) and it meets every applicable check of the scene (the checks
``physbench check`` evaluates, with the same bounds; an ``xfail`` marks a
known limitation but does not make a failed check hold; checks bound to other
settings, ``metric@dt=...``, are left out: the searched value replaces
them).  ``checks`` restricts the criterion to checks of the named metrics
(stability always counts).  Phases stop at the first failing one.

The search (:func:`search`).  The low end is evaluated first; the side that
holds is the start, and the range is walked from it towards the other end
in steps of at most a factor 2 (positive ranges, log space) or a quarter of
the range (linear) until a value fails: the first failing step and the
holding one before it are the bracket.  Then bisection (geometric mean in
log space, integers for integer settings) until the bracket is narrower than
``tol`` (relative: hi / lo - 1 <= tol in log space; hi - lo <= tol x the
range width in linear space; width 1 for integers).  The limit is the
bracket's holding end: the last value known to hold.  Walking from the
holding end (instead of bisecting the whole range at once) finds the first
breaking point when the criterion is not monotone (a wall that catches a
bullet again at some higher speeds).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import sys
import threading
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Generator

#: outcomes of a search
FOUND, HOLDS_THROUGHOUT, FAILS_THROUGHOUT, UNSUPPORTED = "found", "holds_throughout", "fails_throughout", "unsupported"
#: the suite name under which ``physbench limits`` stores its rows
LIMITS_SUITE = "limits"
#: row kinds (column ``row_kind``): one row per run of a search, one per search
EVAL_ROW, RESULT_ROW = "limit_eval", "limit"
#: at most this many walking steps from the holding end
MAX_WALK = 8


# ---------------------------------------------------------------------------
# pure search


@dataclass(frozen=True)
class Verdict:
    """Whether one value holds.  ``reason``: the failed check (or status) when
    it does not; ``runs`` and ``cpu_s`` (s of CPU time in the engine's steps)
    spent deciding it; ``unsupported`` when the engine cannot run the scene."""

    holds: bool
    reason: str = ""
    runs: int = 1
    cpu_s: float = 0.0
    unsupported: bool = False


@dataclass
class SearchResult:
    """The answer of :func:`search`.

    ``limit``: the last value that holds (None unless ``outcome`` is
    ``found`` or ``holds_throughout``, where it is the range's far end);
    ``bracket``: (low, high) with the limit at one end and the first failing
    value at the other; ``direction``: ``"below"`` when values below the
    limit hold (dt, speed, mass ratio), ``"above"`` when values above it hold
    (solver iterations); ``failed_check``: why the failing end of the
    bracket fails; ``evaluations``: every (value, Verdict) in the order
    evaluated."""

    param: str
    lo: float
    hi: float
    tol: float
    outcome: str
    limit: float | None = None
    bracket: tuple[float, float] | None = None
    direction: str | None = None
    failed_check: str = ""
    evaluations: list[tuple[float, Verdict]] = field(default_factory=list)

    @property
    def runs(self) -> int:
        return sum(v.runs for _, v in self.evaluations)

    @property
    def cpu_s(self) -> float:
        return float(sum(v.cpu_s for _, v in self.evaluations))

    def as_dict(self) -> dict[str, Any]:
        return {"limit": self.limit, "bracket": list(self.bracket) if self.bracket else None,
                "failed_check": self.failed_check or None, "runs": self.runs, "cpu_s": self.cpu_s,
                "outcome": self.outcome, "direction": self.direction, "param": self.param,
                "range": [self.lo, self.hi], "tol": self.tol,
                "evaluations": [{"value": x, "holds": v.holds, "reason": v.reason or None} for x, v in self.evaluations]}


def _walk(lo: float, hi: float, log: bool, integer: bool) -> list[float]:
    """The walking grid from ``lo`` to ``hi`` (both included, ascending):
    steps of at most a factor 2 (log) or a quarter of the range (linear),
    at most MAX_WALK steps."""
    if log:
        n = min(MAX_WALK, max(1, math.ceil(math.log2(hi / lo) - 1e-9)))
        pts = [lo * (hi / lo) ** (i / n) for i in range(n + 1)]
    else:
        n = 4
        pts = [lo + (hi - lo) * i / n for i in range(n + 1)]
    pts[0], pts[-1] = lo, hi
    if integer:
        pts = sorted({int(round(p)) for p in pts})
    return pts


def _mid(a: float, b: float, log: bool, integer: bool) -> float:
    m = math.sqrt(a * b) if log else 0.5 * (a + b)
    if integer:
        m = int(round(m))
        if m in (a, b):
            m = int(min(a, b)) + 1
    return m


def _narrow(a: float, b: float, log: bool, integer: bool, tol: float, width: float) -> bool:
    lo, hi = min(a, b), max(a, b)
    if integer:
        return hi - lo <= 1
    if log:
        return hi / lo - 1.0 <= tol
    return hi - lo <= tol * width


def search(criterion: Callable[[float], Verdict], lo: float, hi: float, tol: float = 0.05,
           integer: bool = False, log: bool | None = None, param: str = "") -> SearchResult:
    """Find where ``criterion`` stops holding between ``lo`` < ``hi``.

    ``log`` (default: both ends positive) bisects in log space; ``integer``
    keeps every value an integer.  See the module docstring for the walk and
    the tolerance.  Raises ValueError for an empty or invalid range or tol.
    The search itself is :func:`search_steps`; this drives it with
    ``criterion``."""
    return drive(search_steps(lo, hi, tol, integer, log, param), criterion)


def drive(steps: Generator[Any, Any, Any], answer: Callable[[Any], Any]) -> Any:
    """Run a step generator to its end, answering each value it yields with
    ``answer(value)``; returns the generator's return value."""
    try:
        question = next(steps)
        while True:
            question = steps.send(answer(question))
    except StopIteration as stop:
        return stop.value


def search_steps(lo: float, hi: float, tol: float = 0.05, integer: bool = False, log: bool | None = None,
                 param: str = "") -> Generator[float, Verdict, SearchResult]:
    """:func:`search` as a generator: yields each value to evaluate,
    receives its Verdict, returns the SearchResult.  A search is sequential
    (each value depends on the last verdict); a scheduler runs many of
    them at once by holding their generators (harness/schedule.py).
    Raises ValueError (at the first ``next``) for a bad range or tol."""
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"range: expected two finite numbers LO < HI, got {lo!r} {hi!r}")
    if not (0.0 < tol < 1.0):
        raise ValueError(f"tol: expected a relative tolerance 0 < tol < 1, got {tol!r}")
    if log is None:
        log = lo > 0
    if log and lo <= 0:
        raise ValueError(f"range: log-space search needs LO > 0, got {lo!r}")
    if integer:
        lo, hi = int(math.ceil(lo)), int(math.floor(hi))
        if lo >= hi:
            raise ValueError("range: expected at least two integers between LO and HI")
    res = SearchResult(param, lo, hi, tol, FAILS_THROUGHOUT)
    seen: dict[float, Verdict] = {}

    def ev(x: float) -> Generator[float, Verdict, Verdict]:
        if x not in seen:
            seen[x] = yield x
            res.evaluations.append((x, seen[x]))
        return seen[x]

    grid = _walk(lo, hi, log, integer)
    first = yield from ev(grid[0])
    if first.unsupported:
        res.outcome, res.failed_check = UNSUPPORTED, first.reason
        return res
    if first.holds:
        res.direction = "below"
    else:
        last = yield from ev(grid[-1])
        if not last.holds:
            res.failed_check = first.reason
            return res
        res.direction = "above"
        grid = grid[::-1]
    good, bad = grid[0], None
    for x in grid[1:]:
        if (yield from ev(x)).holds:
            good = x
        else:
            bad = x
            break
    if bad is None:
        res.outcome, res.limit = HOLDS_THROUGHOUT, good
        return res
    width = hi - lo
    while not _narrow(good, bad, log, integer, tol, width):
        m = _mid(good, bad, log, integer)
        if (yield from ev(m)).holds:
            good = m
        else:
            bad = m
    res.outcome, res.limit = FOUND, good
    res.bracket = (min(good, bad), max(good, bad))
    res.failed_check = seen[bad].reason
    return res


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
    from adapters import get_adapter

    return param in get_adapter(engine).capabilities().settings


def _fill_vector(loaded: Any, variant: str | None, path: str) -> dict[str, Any]:
    """Overrides that make ``path`` settable: when ``path`` names an element
    of a vector the spec leaves at its default (``body[0].velocity[0]`` of a
    body written without ``velocity``), the whole vector at its validated
    default."""
    from contract.spec import parse_key_path

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


def load_at(req: LimitRequest, value: float):
    """The request's scene with the searched spec key set to ``value`` (for
    an engine setting, the scene as written).  Raises SpecError (a value the
    spec does not accept: a negative mass, a restitution over 1)."""
    from contract.scene import load_scene, resolve_scenario
    from contract.spec import load_spec

    loaded = load_spec(resolve_scenario(req.scenario))
    overrides = dict(req.overrides)
    if is_engine_setting(req.engine, req.param):
        return load_scene(req.scenario, req.variant, overrides or None, loaded=loaded)
    overrides.update(_fill_vector(loaded, req.variant, req.param))
    overrides[req.param] = value
    return load_scene(req.scenario, req.variant, overrides, loaded=loaded)


def judge(scene: Any, result: Any, checks: tuple[str, ...] = (),
          bounds: tuple[tuple[str, float], ...] = ()) -> tuple[bool, str]:
    """Whether one run holds (module docstring), and if not, why: the first
    failure as ``metric: message``.  ``checks``: only the scene's checks of
    these metrics (``("stable",)``: stability alone); ``bounds``: extra
    (metric, max) criteria, a missing or NaN value failing."""
    from harness.conformance import FAIL, PASS, applicable_checks, evaluate_check, split_metric

    if result.status != "ok":
        return False, f"status {result.status}: {result.message}"
    stable = result.metrics.get("stable")
    if stable is not None and not bool(stable):
        why = result.metrics.get("stability_reason") or "a recorded value is not finite or energy blew up"
        return False, f"stable: {why}"
    for c in applicable_checks(scene, result.engine):
        name, bound = split_metric(c.metric)
        if bound or (checks and name not in checks):
            continue
        o = evaluate_check(dataclasses.replace(c, xfail={}), result)
        if o.outcome != PASS:
            return False, f"{c.metric}: {o.message}" if o.outcome == FAIL else f"{c.metric}: {o.outcome} {o.message}"
    for metric, hi in bounds:
        v = result.metrics.get(metric)
        try:
            x = float(v)
        except (TypeError, ValueError):
            x = math.nan
        if not x <= hi:
            return False, f"{metric}: {metric} = {x:.6g}, expected <= {hi:g}" if math.isfinite(x) else \
                f"{metric}: metric not computed"
    return True, ""


def evaluate_point(req: LimitRequest, limit_id: str, value: float, phase: float) -> dict[str, Any]:
    """Run the request's scene with the parameter at ``value`` in step phase
    ``phase`` and return its row: ``RunResult.row()`` plus the sweep point
    columns and ``limit_*`` columns (``limit_holds``, ``limit_reason``).
    Never raises: a scene the value makes invalid, a run that raises, are
    rows whose verdict fails with the reason."""
    from harness import runner
    from contract.phase import shift_scene
    from harness.points import PHASE_KEY, Point, _point_columns, _status_row

    t0 = time.perf_counter()
    settings = dict(req.settings)
    engine_param = is_engine_setting(req.engine, req.param)
    if engine_param:
        settings[req.param] = value
    pt = Point(req.scenario, req.variant, req.engine,
               tuple(sorted({**settings, **({PHASE_KEY: phase} if phase else {})}.items())), 1, req.timeout_s)
    scene = None
    try:
        scene = load_at(req, value)
        if phase:
            scene = shift_scene(scene, phase, dt=settings.get("dt", scene.dt))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            res = runner.run(scene, req.engine, settings, timeout_s=req.timeout_s)
        res.trace = None
        row = res.row()
        row.update(_point_columns(pt, scene, row, [float(res.metrics.get("cpu_s_per_sim_s", math.nan))], t0, res))
        holds, reason = judge(scene, res, req.checks, req.bounds)
        cpu = float(res.timing.get("step_cpu_s", 0.0) or 0.0)
        unsupported = res.status == "unsupported"
    except Exception as e:  # the value makes the spec invalid, a bad setting, an engine import error
        from contract.spec import SpecError

        msg = "; ".join(e.errors) if isinstance(e, SpecError) else f"{type(e).__name__}: {e}"
        row = _status_row(pt, "error", f"{req.param}={value!r}: {msg}", t0, scene=scene,
                          tb=None if isinstance(e, SpecError) else traceback.format_exc(limit=5))
        holds, reason, cpu, unsupported = False, f"{req.param}={value!r}: {msg}", 0.0, False
    row.update({"row_kind": EVAL_ROW, "point_key": req.eval_key(limit_id, value, phase), "limit_id": limit_id,
                "limit_param": req.param, "limit_value": float(value), "limit_holds": bool(holds),
                "limit_reason": reason, "limit_unsupported": bool(unsupported), "limit_cpu_s": cpu})
    return row


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
    from contract.scene import resolve_scenario

    return hashlib.sha256(Path(resolve_scenario(req.scenario)).read_bytes()).hexdigest()[:16]


@dataclass(frozen=True)
class EvalItem:
    """One evaluation of a search, as an executor item: ``req``'s scene with
    the parameter at ``value`` in step phase ``phase``.  ``key`` is the
    row's point key (a Dask task is keyed by it)."""

    req: LimitRequest
    limit_id: str
    value: float
    phase: float

    @property
    def key(self) -> str:
        return self.req.eval_key(self.limit_id, self.value, self.phase)


def evaluate_item(item: EvalItem) -> dict[str, Any]:
    """:func:`evaluate_point` of one EvalItem (an executor's function)."""
    return evaluate_point(item.req, item.limit_id, item.value, item.phase)


def lost_eval_row(item: EvalItem, lost: Any) -> dict[str, Any]:
    """The row of an evaluation whose worker died, hung or raised
    (``lost``: a harness.execute.WorkerLost): its status and message, and
    a verdict that does not hold for that reason."""
    from harness.points import Point, _status_row

    req = item.req
    why = lost.full_message().replace("this item", "this value")
    row = _status_row(Point(req.scenario, req.variant, req.engine, (), 1, req.timeout_s), lost.status, why,
                      time.perf_counter(), tb=lost.traceback or None, stderr_tail=lost.stderr_tail or None,
                      machine=lost.machine)
    row.update({"row_kind": EVAL_ROW, "point_key": item.key, "limit_id": item.limit_id, "limit_param": req.param,
                "limit_value": float(item.value), "phase": float(item.phase), "limit_holds": False,
                "limit_reason": why, "limit_unsupported": False, "limit_cpu_s": 0.0})
    return row


def search_items(req: LimitRequest, store: Callable[[dict[str, Any]], None], cached: dict[str, dict[str, Any]]
                 ) -> Generator[EvalItem, dict[str, Any], tuple[SearchResult, dict[str, Any]]]:
    """Search ``req`` as a generator: yields each evaluation to run (an
    :class:`EvalItem`), receives its row, returns (result, summary row).
    Evaluations whose key is in ``cached`` are read back (not yielded);
    every new row is handed to ``store``.  The summary row (``row_kind`` =
    ``limit``) is the caller's to store."""
    from contract.phase import phase_values
    from contract.scene import load_scene

    limit_id = req.identity(spec_hash(req))
    phases = phase_values(req.phases)
    integer = False
    if is_engine_setting(req.engine, req.param):
        from adapters import get_adapter

        integer = get_adapter(req.engine).capabilities().settings[req.param].kind is int
    new_runs = 0
    steps = search_steps(req.lo, req.hi, req.tol, integer=integer, param=req.param)
    try:
        value = next(steps)
        while True:
            rows = []
            for f in phases:  # one failing phase decides
                item = EvalItem(req, limit_id, value, f)
                row = cached.get(item.key)
                if row is None:
                    row = yield item
                    store(row)
                    new_runs += 1
                rows.append(row)
                if not row.get("limit_holds"):
                    break
            value = steps.send(verdict_of_rows(rows))
    except StopIteration as stop:
        res: SearchResult = stop.value
    scene = load_scene(req.scenario, req.variant, dict(req.overrides) or None)
    summary = {
        "row_kind": RESULT_ROW, "point_key": f"limit:{limit_id}", "limit_id": limit_id,
        "scenario": scene.id, "variant": req.variant, "engine": req.engine,
        "status": "unsupported" if res.outcome == UNSUPPORTED else "ok", "message": res.failed_check,
        "primary_metric": scene.primary_metric, "limit_param": req.param, "limit_outcome": res.outcome,
        "limit_value": math.nan if res.limit is None else float(res.limit),
        "limit_lo": res.bracket[0] if res.bracket else math.nan,
        "limit_hi": res.bracket[1] if res.bracket else math.nan,
        "limit_direction": res.direction, "limit_failed_check": res.failed_check,
        "limit_runs": res.runs, "limit_new_runs": new_runs, "limit_cpu_s": res.cpu_s,
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
    return drive(search_items(req, store, cached), lambda it: evaluate(it.req, it.limit_id, it.value, it.phase))


def stored_rows(paths: list[Path], kind: str = EVAL_ROW) -> dict[str, dict[str, Any]]:
    """Rows of ``kind`` in the Parquet files ``paths``, by point key (the
    first stored wins)."""
    import pandas as pd

    out: dict[str, dict[str, Any]] = {}
    for p in paths:
        try:
            df = pd.read_parquet(p)
        except Exception:
            continue
        if "row_kind" not in df.columns:
            continue
        for r in df[df["row_kind"] == kind].to_dict("records"):
            out.setdefault(r["point_key"], r)
    return out


# ---------------------------------------------------------------------------
# physbench limits


@dataclass(frozen=True)
class _SearchSuite:
    """What :func:`harness.sweep_store.open_sweep` needs of a suite: a name, a hash
    naming what is planned, and a path for the manifest."""

    name: str
    file_hash: str
    path: Path


def parse_number(text: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{what}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{what}: expected a finite number, got {text!r}")
    return v


def validate_request(req: LimitRequest) -> list[str]:
    """Problems with a request, one line each (empty: fine): the scenario
    loads, the engine exists, the parameter is a setting of the engine or a
    spec key the scene accepts at both ends of the range, the phases are
    possible."""
    from adapters import engine_names, get_adapter
    from contract.phase import PhaseError, shift_scene
    from contract.spec import SpecError

    errs: list[str] = []
    if req.engine not in engine_names():
        return [f"--engine: unknown engine {req.engine!r}; known: {', '.join(engine_names())}"]
    if not (req.lo < req.hi):
        errs.append(f"--range: expected LO < HI, got {req.lo!r} {req.hi!r}")
    if not (0.0 < req.tol < 1.0):
        errs.append(f"--tol: expected a relative tolerance 0 < tol < 1, got {req.tol!r}")
    if not (1 <= req.phases <= 1024):
        errs.append(f"--phases: expected 1 .. 1024, got {req.phases!r}")
    caps = get_adapter(req.engine).capabilities()
    if req.param in caps.settings:
        st = caps.settings[req.param]
        if st.kind not in (int, float):
            errs.append(f"--param {req.param}: setting of engine {req.engine} is not a number ({st.kind.__name__})")
        for end in (req.lo, req.hi):
            try:
                st.coerce(int(end) if st.kind is int and float(end).is_integer() else end)
            except (ValueError, TypeError) as e:
                errs.append(f"--range: {end!r} for setting {req.param}: {e}")
        if req.param == "dt" and req.lo <= 0:
            errs.append(f"--range: dt must be positive, got LO = {req.lo!r}")
        try:
            load_at(req, req.lo)
        except SpecError as e:
            errs.extend(f"--set: {m}" for m in e.errors)
    elif "." in req.param or "[" in req.param:
        for end in (req.lo, req.hi):
            try:
                load_at(req, end)
            except SpecError as e:
                errs.append(f"--param {req.param} = {end!r}: {e.errors[0]}")
            except ValueError as e:
                errs.append(f"--param {req.param}: {e}")
    else:
        errs.append(f"--param {req.param}: not a setting of engine {req.engine} ({', '.join(caps.settings)}) "
                    f"and not a dotted spec key (e.g. body[0].velocity[0], material.default.restitution)")
    if req.checks:
        try:
            sc = load_at(req, req.lo)
            from harness.conformance import applicable_checks, split_metric

            have = {split_metric(c.metric)[0] for c in applicable_checks(sc, req.engine)} | {"stable"}
            for m in req.checks:
                if m not in have:
                    errs.append(f"--check {m}: no check of this metric applies to {req.label} on {req.engine} "
                                f"(its checks: {', '.join(sorted(have)) or 'none'})")
        except (SpecError, ValueError):
            pass  # reported above
    for m, b in req.bounds:
        if not (isinstance(b, (int, float)) and math.isfinite(b)):
            errs.append(f"--max {m}: expected a finite number, got {b!r}")
    for k, v in req.settings:
        if k == req.param:
            errs.append(f"--set {k}: is the searched parameter")
        elif k not in caps.settings:
            errs.append(f"--set {k}: not a setting of engine {req.engine} ({', '.join(caps.settings)})")
        else:
            try:
                caps.settings[k].coerce(v)
            except ValueError as e:
                errs.append(f"--set {k}={v!r}: {e}")
    if errs:
        return errs
    if req.phases > 1:
        try:
            sc = load_at(req, req.lo)
            dt = req.lo if req.param == "dt" else dict(req.settings).get("dt", sc.dt)
            shift_scene(sc, (req.phases - 1) / req.phases, dt=float(dt))
        except PhaseError as e:
            errs.append(f"--phases {req.phases}: step phases need a start in free flight: {e}")
    return errs


def describe(res: SearchResult, req: LimitRequest) -> str:
    """The answer in one paragraph of text."""
    where = f"{req.label} on {req.engine}, {req.param} in [{req.lo:g}, {req.hi:g}]"
    cost = f"{res.runs} runs, {res.cpu_s:.2f} s CPU"
    if res.outcome == FOUND:
        side = "below" if res.direction == "below" else "above"
        return (f"{where}: limit {req.param} = {res.limit:.6g} (holds {side}; bracket "
                f"[{res.bracket[0]:.6g}, {res.bracket[1]:.6g}]); just past it: {res.failed_check}; {cost}")
    if res.outcome == HOLDS_THROUGHOUT:
        return f"{where}: holds over the whole range ({cost})"
    if res.outcome == UNSUPPORTED:
        return f"{where}: {res.failed_check}"
    return f"{where}: fails at both ends of the range: {res.failed_check} ({cost})"


def limits_main(req: LimitRequest, out_dir: Path | None = None, as_json: bool = False) -> int:
    """``physbench limits``: search ``req``, store its rows under
    ``<out_dir>/<machine>/limits/`` (default results/sweeps/), print the
    answer (``as_json``: one JSON object on stdout, nothing else there).
    A search interrupted or rerun at the same commit reads its finished
    evaluations back.  Returns 0 (the search ran; its outcome is data), 2
    for bad input, 130 when interrupted."""
    from harness.results import SCHEMA_VERSION
    from harness.sweep_store import SWEEPS_DIR, consolidate, machine_id, open_sweep, sweep_files

    errs = validate_request(req)
    if errs:
        for e in errs:
            print(f"error: {req.label}: {e}", file=sys.stderr)
        return 2
    root = Path(out_dir) if out_dir is not None else SWEEPS_DIR
    limit_id = req.identity(spec_hash(req))
    from harness.runner import commit_id

    commit = commit_id()
    # finished evaluations of this search at this commit: every stored file of
    # the limits suite (consolidated or parts) whose rows carry this limit_id
    files = [p for m, _s, _sid, p, _c in sweep_files(root, [LIMITS_SUITE], machine_id(), unfinished=True)]
    cached = {k: r for k, r in stored_rows(files).items()
              if r.get("limit_id") == limit_id and r.get("commit") == commit}
    from contract.scene import resolve_scenario

    suite = _SearchSuite(LIMITS_SUITE, limit_id, Path(resolve_scenario(req.scenario)))
    sd = None
    lock = threading.Lock()

    def store(row: dict[str, Any]) -> None:
        nonlocal sd
        with lock:
            if sd is None:
                sd, _ = open_sweep(suite, [], root, None, 1, "serial", {"limit": dataclasses.asdict(req)})
            row.update({"suite": LIMITS_SUITE, "sweep_id": sd.sweep_id, "machine_id": machine_id(),
                        "sweep_jobs": 1, "schema_version": SCHEMA_VERSION})
            sd.write_point(row)

    try:
        res, summary = run_search(req, store, cached)
    except KeyboardInterrupt:
        print(f"interrupted: finished evaluations stored under {root}; run the same command again to resume",
              file=sys.stderr)
        if sd is not None:
            sd.close()
        return 130
    if sd is not None:
        store(summary)
        try:
            out = consolidate(sd.path)
        finally:
            sd.close()
        print(f"rows written to {out}", file=sys.stderr)
    else:
        print(f"all {res.runs} runs read back from stored rows (same search, same commit)", file=sys.stderr)
    if as_json:
        sys.stdout.write(json.dumps(res.as_dict(), default=float) + "\n")
        sys.stdout.flush()
    else:
        print(describe(res, req))
    return 0
