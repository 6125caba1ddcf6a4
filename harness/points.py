"""A stored row of one request: a sweep point's or a search evaluation's.

:class:`Point` is one point of a suite's plan (scenario, variant, engine,
swept settings, phase); :meth:`Point.request` is the
:class:`harness.execute.RunRequest` the executors run.  The one row
builder: :func:`request_row` runs a request (repeats, timing) and returns
its row; :func:`failure_row` is the row of a request that produced no run
(the scene did not load, the run raised, the worker died or hung:
harness.execute.failure_result) -- for a point and for an evaluation of a
breaking-point search alike (the request's ``probe`` adds the
evaluation's columns, harness/limit_eval.py).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import statistics
import time
import traceback
import warnings
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any

from physbench.contract.phase import PhaseError
from physbench.contract.scene import load_scene, resolve_scenario
from physbench.contract.spec import LoadedSpec, load_spec
from physbench.harness import runner
from physbench.harness import status as st
from physbench.harness.conformance import run_verdicts, scene_columns, verdicts_column
from physbench.harness.execute import RunRequest, WorkerLost, failure_result, request_scene

RUN_TIMEOUT_S = 600.0  # default wall-clock budget per run (suite.timeout_s)
#: the point setting that carries a step phase (not an engine setting)
PHASE_KEY = "phase"


@dataclass(frozen=True)
class Point:
    """One run to make: scenario (+ variant) on an engine with the swept
    settings (sorted (name, value) pairs, values coerced by the engine's
    Setting, so 1e-3 and 0.001 are the same point)."""

    scenario: str
    variant: str | None
    engine: str
    settings: tuple[tuple[str, Any], ...]
    repeats: int = 1
    timeout_s: float = RUN_TIMEOUT_S
    #: the spec file (None: ``scenario`` is an id under scenarios/)
    path: str | None = None
    #: the scene's content hash: part of the key, so a changed scene is a
    #: new point (and a new history series), never the old one resumed
    scene_hash: str = ""

    @property
    def settings_dict(self) -> dict[str, Any]:
        return dict(self.settings)

    @property
    def phase(self) -> float:
        """The step phase f (0 <= f < 1) of the point: its start moved back
        by f dt along the free flight (contract/phase.py); 0 = as written."""
        return float(self.settings_dict.get(PHASE_KEY, 0.0))

    @property
    def engine_settings(self) -> dict[str, Any]:
        """The swept settings the engine gets (the phase is the harness's)."""
        return {k: v for k, v in self.settings if k != PHASE_KEY}

    @cached_property
    def settings_json(self) -> str:
        """The swept settings as canonical JSON (sorted keys, shortest
        round-trip floats)."""
        return json.dumps(self.settings_dict, sort_keys=True, separators=(",", ":"))

    @property
    def label(self) -> str:
        return self.scenario + (f"[{self.variant}]" if self.variant else "")

    @cached_property
    def key(self) -> str:
        """Stable identity across runs and nights:
        ``scenario[variant]|engine|{"dt":0.001,...}|<scene hash>``.  Repeats
        and timeouts are not part of it (they change how a point is
        measured, not what); the scene's content is."""
        return self.series_key + (f"|{self.scene_hash}" if self.scene_hash else "")

    def request(self) -> RunRequest:
        """The request that runs this point (the executors' work item):
        its engine settings, phase, timed repeats, budget per run, key and
        scene hash."""
        return RunRequest(self.path or self.scenario, self.engine, self.variant, self.engine_settings,
                          phase=self.phase, timeout_s=self.timeout_s, key=self.key, repeats=self.repeats,
                          scene_hash=self.scene_hash, row_settings=self.settings_json)

    @property
    def series_key(self) -> str:
        """The key without the scene hash: the point's place in the suite,
        whatever its content (the report's history splits a series where
        the hash changes)."""
        return f"{self.label}|{self.engine}|{self.settings_json}"


# ---------------------------------------------------------------------------
# running one point (in a worker process or in-process)


#: (path as given, resolved path, SHA-256 of the file's bytes) -> its LoadedSpec
_SPECS: dict[tuple[str, str, bytes], LoadedSpec] = {}
_SPECS_MAX = 256


def cached_spec(path: str | Path) -> LoadedSpec:
    """``load_spec(path)``, parsed and validated once per process for the
    same bytes: the file is read on every call and a changed file is loaded
    afresh (a file that does not load raises its SpecError every time).  A
    suite's check loads each spec file once, for its sweep blocks, scenes
    and searches (tests/test_sweep.py::test_a_suite_check_parses_each_spec_file_once);
    a worker loads a search's spec once, not once per evaluation.  Callers
    do not modify what it returns (LoadedSpec.validated copies)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError:
        return load_spec(p)  # its SpecError, naming the file
    key = (str(p), str(p.resolve()), hashlib.sha256(data).digest())
    hit = _SPECS.get(key)
    if hit is None:
        hit = load_spec(p)
        try:
            same = p.read_bytes() == data  # not written to in between: the spec read is the one keyed
        except OSError:
            same = False
        if same:
            if len(_SPECS) >= _SPECS_MAX:
                _SPECS.clear()
            _SPECS[key] = hit
    return hit


@lru_cache(maxsize=64)
def cached_scene(scenario: str, variant: str | None):
    """``scenario``: an id or a spec file's path."""

    return load_scene(scenario, variant, loaded=cached_spec(resolve_scenario(scenario)))


def run_point(point: Point) -> dict[str, Any]:
    """The row of one point (:func:`request_row` of its request)."""
    return request_row(point.request())


def _request_scene(req: RunRequest) -> Any:
    """The scene of a row's request, phase applied: a scene without
    overrides comes from a per-process cache."""
    base = None if req.overrides else cached_scene(req.scenario, req.variant)
    return request_scene(req, base=base)


def request_row(req: RunRequest) -> dict[str, Any]:
    """Run ``req`` and return its stored row (``sweep``, ``limits``): the
    first run gives the row (metrics, status); while runs are ``ok``,
    ``req.repeats`` runs in all are timed (metrics computed on the first
    only: the engines are deterministic, and metric code is not what is
    timed).  A first run that read the contact forces after every step
    (a contact-law metric: harness/runner.py) is not timed: one more run
    is, so the row's cost is the engine's stepping alone.  Only ok runs
    count in the median and minimum CPU time; a run that is not ok is
    not repeated (the row's ``cpu_s_per_sim_s`` keeps the runner's figure
    for the part that ran).  A request with a
    ``probe`` (one evaluation of a breaking-point search) also gets the
    probe's columns (its verdict).  Never raises for engine trouble: a
    scene that does not load, a run that raises are :func:`failure_row`
    rows.  The sweep-wide columns are added by the caller."""

    t0 = time.perf_counter()
    probe = req.probe
    scene = None
    try:
        scene = _request_scene(req)
    except Exception as e:
        if probe is not None:
            msg, tb = probe.load_error(e)
            return failure_row(req, st.ERROR, msg, t0, scene=scene, tb=tb)
        what = f"phase {req.phase:g}: {e}" if isinstance(e, PhaseError) else \
            f"scene failed to load: {type(e).__name__}: {e}"
        return failure_row(req, st.ERROR, what, t0)
    if req.scene_hash and scene.content_hash != req.scene_hash:
        return failure_row(req, st.ERROR, f"scene changed since the sweep was planned (content hash "
                                          f"{scene.content_hash}, planned {req.scene_hash}); sweep again", t0)
    skipped = probe.skipped_metrics(scene) if probe is not None else ()
    first = None
    cpu: list[float] = []
    # a blow-up is recorded in the status; numpy's overflow warnings on the
    # way there would only scramble the progress display
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        runs = max(1, req.repeats)
        i = 0
        while i < runs:
            try:
                res = runner.run(scene, req.engine, dict(req.settings), timeout_s=req.timeout_s,
                                 compute_metrics=req.compute_metrics and i == 0,
                                 model_metrics=req.model_metrics and not skipped)
            except Exception as e:  # a bad setting combination, an adapter import error ...
                if first is None:
                    return failure_row(req, st.FAILED, f"could not run: {type(e).__name__}: {e}", t0,
                                       scene=scene, tb=traceback.format_exc(limit=5))
                first.notes.append(f"repeat {i + 1} raised {type(e).__name__}: {e}; not timed")
                break
            res.trace = None
            res.contacts = None
            if first is None:
                first = res
            if res.status != st.OK:  # a partial run's cost is no point of a work-precision curve
                if res is not first:
                    first.notes.append(f"repeat {i + 1} ended {res.status} ({res.message}); not timed")
                break
            if res.info.get("contact_forces_per_step") and probe is None:
                # the metrics run read contact forces after every step (harness/runner.py): not the
                # engine's step time; one more run is timed in its place (a search's evaluation
                # is judged, not timed: its one run stands, below)
                runs += 1
            else:
                cpu.append(float(res.metrics.get("cpu_s_per_sim_s", math.nan)))
            i += 1
    if probe is not None and not cpu:  # an evaluation's row times its one run, whatever its status
        cpu = [float(first.metrics.get("cpu_s_per_sim_s", math.nan))]
    row = first.row()
    row.update(_request_columns(req, scene, row, cpu, t0, first))
    if probe is not None:
        row.update(probe.columns(scene, first, skipped))
    return row


def _request_columns(req: RunRequest, scene: Any, row: dict[str, Any], cpu: list[float], t0: float,
                     result: Any = None) -> dict[str, Any]:
    """The sweep's columns of a request's row.  ``checks`` (JSON) holds the
    verdicts of the scene's checks on this run
    (harness.conformance.run_verdicts), and the scene's columns
    (harness.conformance.scene_columns: primary metric, its threshold,
    tags): the report reads them from the row, never from the scene."""

    metric = getattr(scene, "primary_metric", None)
    value = row.get(metric) if metric else None
    try:
        err = float(value) if row.get("status") == st.OK and value is not None else math.nan
    except (TypeError, ValueError):
        err = math.nan
    finite = [c for c in cpu if math.isfinite(c)]
    cols = scene_columns(scene) if scene is not None else {"primary_metric": None, "primary_threshold": None,
                                                            "tags": None}
    settings = req.row_settings if req.row_settings is not None else json.dumps(
        {**req.settings, **({PHASE_KEY: req.phase} if req.phase else {})}, sort_keys=True, separators=(",", ":"))
    return {
        **cols,
        "point_key": req.key,
        "checks": verdicts_column(run_verdicts(scene, result)) if scene is not None and result is not None else "[]",
        "point_settings": settings,
        "phase": float(req.phase),
        "primary_error": err,
        "cpu_s_per_sim_s_median": statistics.median(finite) if finite else math.nan,
        "cpu_s_per_sim_s_min": min(finite) if finite else math.nan,
        "repeats": len(finite),
        "point_wall_s": time.perf_counter() - t0,
    }


def failure_row(req: RunRequest, status: str, message: str, t0: float | None = None, scene: Any = None,
                tb: str | None = None, lost: WorkerLost | None = None) -> dict[str, Any]:
    """The row of a request that produced no run (its scene did not load,
    the run raised, the worker died or hung: ``lost``): the RunResult of
    harness.execute.failure_result (status, message, engine version,
    resolved settings, machine, traceback, stderr tail) with the request's
    row columns, and for an evaluation its probe's failing verdict.  The
    one failure-row builder of ``sweep`` and ``limits``."""
    t0 = time.perf_counter() if t0 is None else t0
    if scene is None:  # for the resolved settings and the scene's columns, where it loads
        try:
            scene = _request_scene(dataclasses.replace(req, phase=0.0))
        except Exception:
            scene = None
    res = failure_result(req, status, message, scene, lost=lost, tb=tb)
    row = res.row()
    row.update(_request_columns(req, scene, row, [], t0))
    if req.probe is not None:
        row.update(req.probe.failed_columns(message))
    return row


def lost_row(req: RunRequest, lost: WorkerLost) -> dict[str, Any]:
    """The ``error``/``timeout`` row of a request whose worker died, hung
    or raised, naming why (this point, this value)."""
    noun = "value" if req.probe is not None else "point"
    if lost.kind == "raised" and req.probe is None:
        msg = f"point failed: {lost.message}"
    else:
        msg = lost.full_message().replace("this item", f"this {noun}")
    return failure_row(req, lost.status, msg, lost=lost)


# ---------------------------------------------------------------------------
# executing points


def lost_point_row(p: Point, value: WorkerLost) -> dict[str, Any]:
    """The ``error``/``timeout`` row of a point whose worker died, hung or
    raised (:func:`lost_row` of its request)."""
    return lost_row(p.request(), value)
