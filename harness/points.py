"""One sweep point: what to run (:class:`Point`: scenario, variant, engine,
swept settings, phase), running it (:func:`run_point`: repeats, timing,
the point's row) and the executor glue (:func:`lost_point_row`: a point whose
worker dies or hangs gets an ``error``/``timeout`` row; harness/execute.py).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import statistics
import time
import traceback
import warnings
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from physbench.contract.phase import PhaseError
from physbench.harness import status as st
from physbench.harness.execute import RunRequest, WorkerLost, request_scene

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

    @property
    def settings_json(self) -> str:
        """The swept settings as canonical JSON (sorted keys, shortest
        round-trip floats)."""
        return json.dumps(self.settings_dict, sort_keys=True, separators=(",", ":"))

    @property
    def label(self) -> str:
        return self.scenario + (f"[{self.variant}]" if self.variant else "")

    @property
    def key(self) -> str:
        """Stable identity across runs and nights:
        ``scenario[variant]|engine|{"dt":0.001,...}|<scene hash>``.  Repeats
        and timeouts are not part of it (they change how a point is
        measured, not what); the scene's content is."""
        return self.series_key + (f"|{self.scene_hash}" if self.scene_hash else "")

    @property
    def series_key(self) -> str:
        """The key without the scene hash: the point's place in the suite,
        whatever its content (the report's history splits a series where
        the hash changes)."""
        return f"{self.label}|{self.engine}|{self.settings_json}"


# ---------------------------------------------------------------------------
# running one point (in a worker process or in-process)


@lru_cache(maxsize=64)
def _scene(scenario: str, variant: str | None):
    """``scenario``: an id or a spec file's path."""
    from physbench.contract.scene import load_scene

    return load_scene(scenario, variant)


def run_point(point: Point) -> dict[str, Any]:
    """Run one point: the first run gives the row (metrics, status); while
    runs are ``ok``, ``point.repeats`` runs in all are timed (metrics computed
    on the first only: the engines are deterministic, and metric code is not
    what is timed).  Only ok runs count in the median and minimum CPU time
    (``repeats`` of them); a run that is not ok is not repeated (the row's
    ``cpu_s_per_sim_s`` keeps the runner's figure for the part that ran).
    Never raises for engine trouble; returns the flat row with the point
    columns (the sweep-wide ones are added by the caller)."""
    from physbench.harness import runner

    t0 = time.perf_counter()
    try:
        scene = _scene(point.path or point.scenario, point.variant)
    except Exception as e:
        return _status_row(point, st.ERROR, f"scene failed to load: {type(e).__name__}: {e}", t0)
    if point.scene_hash and scene.content_hash != point.scene_hash:
        return _status_row(point, st.ERROR, f"scene changed since the sweep was planned (content hash "
                                           f"{scene.content_hash}, planned {point.scene_hash}); sweep again", t0)
    settings = point.engine_settings
    if point.phase:
        try:
            scene = request_scene(RunRequest(point.scenario, point.engine, point.variant, settings,
                                             phase=point.phase), base=scene)
        except PhaseError as e:
            return _status_row(point, st.ERROR, f"phase {point.phase:g}: {e}", t0, scene=scene)
    first = None
    cpu: list[float] = []
    # a blow-up is recorded in the status; numpy's overflow warnings on the
    # way there would only scramble the progress display
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for i in range(point.repeats):
            try:
                res = runner.run(scene, point.engine, settings, timeout_s=point.timeout_s,
                                 compute_metrics=(i == 0))
            except Exception as e:  # a bad setting combination, an adapter import error ...
                if first is None:
                    return _status_row(point, st.FAILED, f"could not run: {type(e).__name__}: {e}", t0,
                                       scene=scene, tb=traceback.format_exc(limit=5))
                first.notes.append(f"repeat {i + 1} raised {type(e).__name__}: {e}; not timed")
                break
            res.trace = None
            if first is None:
                first = res
            if res.status != st.OK:  # a partial run's cost is no point of a work-precision curve
                if res is not first:
                    first.notes.append(f"repeat {i + 1} ended {res.status} ({res.message}); not timed")
                break
            cpu.append(float(res.metrics.get("cpu_s_per_sim_s", math.nan)))
    row = first.row()
    row.update(_point_columns(point, scene, row, cpu, t0, first))
    return row


def _point_columns(point: Point, scene: Any, row: dict[str, Any], cpu: list[float], t0: float,
                   result: Any = None) -> dict[str, Any]:
    """The sweep's columns of a point's row.  ``checks`` (JSON) holds the
    verdicts of the scene's checks on this point's run
    (harness.conformance.run_verdicts), and the scene's columns
    (harness.conformance.scene_columns: primary metric, its threshold,
    tags): the report reads them from the row, never from the scene."""
    from physbench.harness.conformance import run_verdicts, scene_columns, verdicts_column

    metric = getattr(scene, "primary_metric", None)
    value = row.get(metric) if metric else None
    try:
        err = float(value) if row.get("status") == st.OK and value is not None else math.nan
    except (TypeError, ValueError):
        err = math.nan
    finite = [c for c in cpu if math.isfinite(c)]
    cols = scene_columns(scene) if scene is not None else {"primary_metric": None, "primary_threshold": None,
                                                            "tags": None}
    return {
        **cols,
        "point_key": point.key,
        "checks": verdicts_column(run_verdicts(scene, result)) if scene is not None and result is not None else "[]",
        "point_settings": point.settings_json,
        "phase": point.phase,
        "primary_error": err,
        "cpu_s_per_sim_s_median": statistics.median(finite) if finite else math.nan,
        "cpu_s_per_sim_s_min": min(finite) if finite else math.nan,
        "repeats": len(finite),
        "point_wall_s": time.perf_counter() - t0,
    }


def _status_row(point: Point, status: str, message: str, t0: float, scene: Any = None,
                tb: str | None = None, stderr_tail: str | None = None,
                machine: dict[str, str] | None = None) -> dict[str, Any]:
    """A row for a point that produced no RunResult (scene failed to load,
    the run raised, the worker died); ``machine``: the summary of the host
    it ran on (default this one)."""
    from physbench.adapters import get_adapter
    from physbench.harness.runner import RunResult, commit_id, machine_info

    settings = point.engine_settings
    version = ""
    try:
        cls = get_adapter(point.engine)
        version = cls.capabilities().version
        if scene is None:
            scene = _scene(point.path or point.scenario, point.variant)
        settings = cls.resolve_settings(scene, settings)
    except Exception:
        pass  # keep the swept settings only
    res = RunResult(point.scenario, point.variant, point.engine, version, status, message, settings,
                    machine=machine or machine_info(), commit=commit_id(),
                    timestamp=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    scene_hash=point.scene_hash, scene_path=getattr(scene, "source", "") or (point.path or ""))
    if tb:
        res.info["traceback"] = tb
    if stderr_tail:
        res.info["stderr_tail"] = stderr_tail
    row = res.row()
    row.update(_point_columns(point, scene, row, [], t0))
    return row


# ---------------------------------------------------------------------------
# executing points


def _point_budget(p: Point) -> float:
    """Wall-clock budget of a point's worker: its timed runs, each within
    the suite's ``timeout_s``."""
    return p.timeout_s * max(1, p.repeats)


def lost_point_row(p: Point, value: WorkerLost) -> dict[str, Any]:
    """The ``error``/``timeout`` row of a point whose worker died, hung or
    raised, naming why."""
    t0 = time.perf_counter()
    if value.kind == "died":
        msg = f"{value.full_message()}".replace("this item", "this point")
    elif value.kind == "timeout":
        msg = value.full_message()
    else:
        msg = f"point failed: {value.message}"
    return _status_row(p, value.status, msg, t0, tb=value.traceback or None,
                       stderr_tail=value.stderr_tail or None, machine=value.machine)
