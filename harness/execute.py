"""One execution path: a run request, executed in this process or in
reusable worker processes under a wall-clock watchdog.

``physbench run``, ``check``, ``trace``, ``sweep`` and ``limits`` all go
through here, with one kind of work item:

- :class:`RunRequest` says what to run (scenario id or spec file, variant,
  engine, engine settings, spec overrides, step phase, budget, recording;
  for a stored row also its key, timed repeats and, for one evaluation of
  a breaking-point search, its ``probe``: harness/limit_eval.py);
  :func:`request_scene` turns it into the scene to run (the one place the
  step phase is applied, contract/phase.py);
- :func:`execute_request` runs one request in this process and returns its
  :class:`harness.runner.RunResult` (``run``, ``check``, ``trace``);
  :func:`harness.points.request_row` the stored row of one (``sweep``,
  ``limits``: a point's or an evaluation's).  Neither raises: a scene that
  does not load, an engine that cannot be imported, a bad setting, a
  worker that died are statuses, all built by :func:`failure_result` (the
  one failure builder; :func:`harness.points.failure_row` is its row);
- the executors that run requests (:class:`WorkerPool`, worker processes
  under a watchdog, and :class:`InlineExecutor`, this process) are
  harness/workers.py's, re-exported here; :func:`run_requests` turns a
  lost worker into the request's ``error``/``timeout`` result.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import os
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from physbench.harness import status as st
from physbench.harness.workers import (ADAPTERS_ENV, END, ONE_THREAD_ENV, WAIT, WORKER_ENV, Batch,  # noqa: F401
                             InlineExecutor, WorkerLost, WorkerPool, extra_adapters, grace_s, members,
                             register_env_adapters, take, worker_main)
from physbench.adapters.base import Adapter, get_adapter
from physbench.contract.phase import PhaseError, shift_scene
from physbench.contract.scene import load_scene
from physbench.harness import runner  # its names read at call time (tests patch them)

#: default wall-clock budget per run (s)
DEFAULT_TIMEOUT_S = 600.0


# ---------------------------------------------------------------------------
# the request


@dataclass(frozen=True)
class RunRequest:
    """One run: ``scenario`` (an id ``family.name`` or a spec file path;
    a relative path is made absolute, workers run elsewhere) with
    ``variant`` on ``engine`` with engine ``settings`` and spec key
    ``overrides`` (dotted key paths, contract.scene.load_scene), its start
    moved back along the free flight by ``phase`` dt (0 <= phase < 1, 0 =
    as written), ``timeout_s`` seconds of wall-clock budget per run (None:
    no limit), one frame recorded every ``record_every`` steps, metrics
    computed when ``compute_metrics`` (the reference model's too when
    ``model_metrics``), the trace (and contacts, with ``contact_cap``)
    returned when ``keep_trace`` (``physbench trace``, ``check --traces``;
    they cross process boundaries).

    A stored row's request (``sweep``, ``limits``;
    harness.points.request_row) also has: ``key``, the row's
    ``point_key``; ``repeats``, the timed runs (metrics from the first);
    ``scene_hash``, the content hash the scene must still have;
    ``row_settings``, the ``point_settings`` column (default: the settings
    and the phase as JSON); ``probe``, for one evaluation of a
    breaking-point search, its criterion and columns
    (harness.limit_eval.EvalItem).  A check's request may instead stand for
    an ensemble of perturbed starts (``ensemble``) or a consensus of
    engines (``consensus``)."""

    scenario: str
    engine: str
    variant: str | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    overrides: dict[str, Any] = field(default_factory=dict)
    phase: float = 0.0
    timeout_s: float | None = DEFAULT_TIMEOUT_S
    record_every: int = 1
    compute_metrics: bool = True
    keep_trace: bool = False
    #: > 0: also record the engine's contacts, at most this many per frame
    #: (tracing only; harness.runner.run)
    contact_cap: int = 0
    model_metrics: bool = True
    key: str = ""
    repeats: int = 1
    scene_hash: str = ""
    row_settings: str | None = None
    probe: Any = None
    #: check's ensemble of perturbed starts (harness.ensemble.Perturbation)
    #: or consensus engines (harness.conformance.execute runs these)
    ensemble: Any = None
    consensus: tuple = ()

    def __post_init__(self) -> None:
        s = self.scenario
        # an id: no path to build (a sweep makes one request an item)
        if (s.endswith(".toml") or os.sep in s) and not os.path.isabs(s) and os.path.exists(s):
            object.__setattr__(self, "scenario", str(Path(s).resolve()))

    @property
    def label(self) -> str:
        s = ",".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in self.settings.items())
        return (f"{self.engine} {self.scenario}" + (f"[{self.variant}]" if self.variant else "")
                + (f" @{s}" if s else "") + (f" phase {self.phase:g}" if self.phase else ""))

    @property
    def budget_s(self) -> float | None:
        """The wall-clock budget of the request's worker: each timed run
        within ``timeout_s`` (None: no limit)."""
        return None if self.timeout_s is None else float(self.timeout_s) * max(1, self.repeats)


def request_scene(req: RunRequest, base: Any = None):
    """The scene ``req`` runs: loaded (with its overrides; or ``base``, the
    already loaded scene of ``req.scenario``/``req.variant``) and shifted
    to its step phase at the run's dt.  Raises SpecError for a bad spec,
    contract.phase.PhaseError for a phase the scene does not allow (or a dt
    setting that is not a number)."""

    scene = base if base is not None else load_scene(req.scenario, req.variant, dict(req.overrides) or None)
    if not req.phase:
        return scene
    dt = req.settings.get("dt", scene.dt)
    try:
        h = float(dt)
    except (TypeError, ValueError):
        raise PhaseError(f"--set dt={dt!r}: expected a number of seconds") from None
    return shift_scene(scene, req.phase, dt=h)


def failure_result(req: RunRequest, status: str, message: str, scene: Any = None, lost: WorkerLost | None = None,
                   tb: str | None = None):
    """The RunResult of a request that produced none of its own (the scene
    did not load, the run could not start, the worker raised, died or hung:
    ``lost``): ``status`` and ``message``, the engine's version and the
    settings resolved for the scene where they can be had (the scene loaded
    here when not given), the machine it ran on (``lost.machine``, else
    this one), the traceback and the worker's stderr tail in ``info``.
    The one failure builder of every command; its row is
    harness.points.failure_row."""

    settings, version = dict(req.settings), ""
    try:
        from physbench.adapters import get_adapter

        cls = get_adapter(req.engine)
        version = cls.capabilities().version
        if scene is None:
            scene = request_scene(dataclasses.replace(req, phase=0.0))
        settings = cls.resolve_settings(scene, req.settings)
    except Exception:
        pass  # keep the requested settings
    res = runner.RunResult(getattr(scene, "id", None) or req.scenario, req.variant, req.engine, version, status, message,
                    settings, machine=dict(lost.machine) if lost is not None and lost.machine else runner.machine_info(),
                    commit=runner.commit_id(), timestamp=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    scene_hash=req.scene_hash,
                    scene_path=getattr(scene, "source", "") or (req.scenario if req.scenario.endswith(".toml") else ""))
    tb = tb or (lost.traceback if lost is not None else None)
    if tb:
        res.info["traceback"] = tb
    if lost is not None and lost.stderr_tail:
        res.info["stderr_tail"] = lost.stderr_tail
    if lost is not None and lost.signal:
        res.info["signal"] = lost.signal
    return res


def execute_request(req: RunRequest):
    """Run ``req`` in this process; never raises for a bad scene or engine
    trouble (statuses, harness/status.py).  The trace is dropped unless
    ``req.keep_trace``."""
    import numpy as np

    try:
        scene = request_scene(req)
    except Exception as e:
        return failure_result(req, st.ERROR, f"scene failed to load: {e}")
    try:
        # a blow-up is recorded in the result's status; numpy's overflow
        # warnings on the way there would only flood stderr
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore", RuntimeWarning)
            res = runner.run(scene, req.engine, dict(req.settings) or None, record_every=req.record_every,
                             timeout_s=req.timeout_s, compute_metrics=req.compute_metrics,
                             contact_cap=req.contact_cap, model_metrics=req.model_metrics)
    except Exception as e:  # adapter import error, bad setting ...
        res = failure_result(req, st.FAILED, f"could not run: {type(e).__name__}: {e}", scene,
                             tb=traceback.format_exc(limit=5))
    if req.phase:
        res.notes.append(f"step phase {req.phase:g}: start moved back along the free flight by {req.phase:g} dt")
    if not req.keep_trace:
        res.trace = None
        res.contacts = None
    return res



# ---------------------------------------------------------------------------
# lost items


def lost_result(req: RunRequest, lost: WorkerLost):
    """The RunResult of a request whose worker raised, died or hung
    (:func:`failure_result`)."""
    return failure_result(req, lost.status, lost.full_message(), lost=lost)


EXECUTORS = ("process", "inline", "dask")


# ---------------------------------------------------------------------------
# a cold compile cache on several workers


class PendingCompile:
    """``pending(req)``: the compiled-code groups the engine(s) of a
    request would compile before stepping, by their own on-disk caches
    (adapters' ``pending_compile``: the reference engine's kernel groups
    not yet marked done), as a frozenset of ``engine:group`` names.  An
    engine is asked once per (scene, settings); the groups compiled since,
    by the cold units handed out and finished (:meth:`compiled`), are taken
    off here (a compiled group stays compiled).  Never raises (an item
    that cannot say has none: it runs as it would)."""

    def __init__(self) -> None:
        self._scenes: dict[tuple, Any] = {}
        self._asked: dict[tuple, frozenset[str]] = {}
        self._compiled: set[str] = set()

    def compiled(self, groups: Iterable[str]) -> None:
        """``groups`` are in the cache now (a cold unit that needed them finished)."""
        self._compiled.update(groups)

    def __call__(self, req: Any) -> frozenset[str]:
        if not isinstance(req, RunRequest):
            return frozenset()
        out: set[str] = set()
        for eng in tuple(req.consensus) or (req.engine,):
            key = (req.scenario, req.variant, repr(sorted(req.overrides.items())), eng,
                   repr(sorted(req.settings.items())))
            if key not in self._asked:
                self._asked[key] = self._ask(key, req, eng)
            out |= self._asked[key]
        return frozenset(out - self._compiled)

    def _ask(self, key: tuple, req: RunRequest, eng: str) -> frozenset[str]:
        try:
            cls = get_adapter(eng)
            if cls.pending_compile.__func__ is _BASE_PENDING:  # an engine without a cache of its own
                return frozenset()
            skey = key[:3]
            if skey not in self._scenes:
                self._scenes[skey] = load_scene(req.scenario, req.variant, dict(req.overrides) or None)
            scene = self._scenes[skey]
            groups = cls.pending_compile(scene, cls.resolve_settings(scene, dict(req.settings)))
            return frozenset(f"{eng}:{g}" for g, s in groups.items() if s > 0)
        except Exception:
            return frozenset()


_BASE_PENDING = Adapter.pending_compile.__func__


class ColdSplit:
    """An executor's item source that keeps builds that would compile the
    same code apart.  A unit's *pending* groups (``pending(item)`` over its
    items: :class:`PendingCompile`) are the compiled-code groups its builds
    would compile; a unit *conflicts* while a unit handed out and not done
    is compiling one of them.  Each time a worker is free it gets the
    oldest held-back unit that does not conflict, else the source's next
    one that does not (the units that do are held back, in order); when
    every unit left conflicts, the oldest (its build then shares the
    compiling through the engine's locks, engine/compile_share.py, and
    waits for the rest).

    Why: pool workers share a cold compile through locks on its kernel
    groups, and a build that needs a group another worker is compiling
    waits for it, running nothing.  So on a cold cache one worker compiles
    a group while the others run what does not need it: other engines'
    runs, scenes whose code is compiled, scenes that compile other groups.
    Every unit is handed out exactly once, whatever the executor; with a
    warm cache (nothing pending) the order is the source's.  The consumer
    calls :meth:`done` with each finished item; the groups of a finished
    unit go to ``pending.compiled`` where it has one.  Tests:
    tests/test_schedule.py::test_cold_split_*."""

    def __init__(self, source: Iterable[Any], pending: Callable[[Any], frozenset]):
        self.source = iter(source)
        self.pending = pending
        self.compiling: dict[int, frozenset] = {}  # id(item) -> the groups its unit compiles (handed out, not done)
        self.waiting: list[Any] = []  # units held back, in the source's order
        self.deferred = 0  # units held back (counted once each time one is)

    def _groups(self, unit: Any) -> frozenset:
        out: frozenset = frozenset()
        for i in members(unit):
            out |= self.pending(i)
        return out

    def _busy(self) -> set:
        return set().union(*self.compiling.values())

    def _hand(self, unit: Any, groups: frozenset) -> Any:
        if groups:
            for i in members(unit):
                self.compiling[id(i)] = groups
        return unit

    def done(self, item: Any) -> None:
        """``item`` (a unit's member) finished (a value or a lost worker)."""
        groups = self.compiling.pop(id(item), None)
        if groups and not any(g is groups for g in self.compiling.values()):  # the unit's last item
            compiled = getattr(self.pending, "compiled", None)
            if compiled is not None:
                compiled(groups)

    def __iter__(self) -> Iterator[Any]:
        while True:
            busy = self._busy()
            for k, unit in enumerate(self.waiting):
                groups = self._groups(unit)
                if not groups & busy:
                    del self.waiting[k]
                    break
            else:
                unit = next(self.source, END)
                if unit is END or unit is WAIT:
                    if self.waiting:  # every unit left conflicts: the oldest, sharing the compile
                        unit = self.waiting.pop(0)
                        yield self._hand(unit, self._groups(unit))
                        continue
                    if unit is END:
                        return
                    yield unit
                    continue
                groups = self._groups(unit)
                if groups & busy:
                    self.waiting.append(unit)
                    self.deferred += 1
                    continue
            yield self._hand(unit, groups)


def shares_compile(executor: Any) -> bool:
    """Whether ``executor``'s workers share this machine's compile cache
    and run at once (``shares_compile_cache``: a local :class:`WorkerPool`)
    with two workers or more: where :class:`ColdSplit` pays."""
    return bool(getattr(executor, "shares_compile_cache", False)) and getattr(executor, "jobs", 1) > 1



def run_requests(reqs: Iterable[RunRequest], executor: Any) -> Iterator[tuple[RunRequest, Any]]:
    """(request, RunResult) for each request as it finishes, through
    ``executor``; a lost worker becomes the request's error/timeout result."""
    for req, value in executor.map(execute_request, reqs, budget_s=lambda r: r.budget_s):
        yield req, (lost_result(req, value) if isinstance(value, WorkerLost) else value)


def run_isolated(req: RunRequest):
    """One request in one fresh worker process (``physbench run``)."""
    with WorkerPool(1) as pool:
        return next(run_requests([req], pool))[1]


__all__ = ["RunRequest", "request_scene", "execute_request", "WorkerLost", "failure_result", "lost_result", "WorkerPool",
           "InlineExecutor", "run_requests", "run_isolated", "register_env_adapters",
           "DEFAULT_TIMEOUT_S", "grace_s", "WAIT", "END", "take", "ONE_THREAD_ENV", "Batch",
           "members", "ColdSplit", "PendingCompile", "shares_compile"]
