"""The runner: build an adapter for a scene, step it for the scene's
duration, record states into preallocated arrays, time the stepping apart
from set-up and metrics, and turn every failure into a recorded status.

Statuses (defined in harness/status.py): ``ok``; ``unsupported`` (the
engine cannot model the scene, with the reason); ``failed`` (the engine
rejected the model at build time); ``error`` (an exception while stepping);
``diverged`` (non-finite or runaway state); ``timeout`` (the run exceeded
its wall-clock budget, checked between step blocks -- a run stuck inside
one engine call is stopped by the worker's watchdog, harness/execute.py).
Metrics are computed on whatever prefix of the trace was recorded.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import math
import numbers
import subprocess
import time
import traceback
from dataclasses import dataclass, field
from importlib.metadata import version as _dist_version
from typing import Any

import numpy as np

from physbench.adapters import get_adapter
from physbench.adapters.base import Unsupported
from physbench.contract.data import checkout_root
from physbench.contract.metric_defs import wants_contact_forces
from physbench.contract.scene import Scene, n_steps
from physbench.contract.spec import record_size_error
from physbench.harness import status as st
from physbench.harness.compile_progress import watch
from physbench.harness.contact_laws import merge_into, run_contact_laws
from physbench.harness.fingerprint import summary
from physbench.harness.metrics import compute_metrics as _metrics
from physbench.harness.metrics import run_penetration
from physbench.harness.references import UNDEFINED, get_model
from physbench.harness.results import CHECK_COLUMNS, VERDICT_COLUMNS

# A state this far from the origin or this fast is a blow-up, not physics.
RUNAWAY_POSITION = 1e6  # m
RUNAWAY_SPEED = 1e6  # m/s or rad/s
CHECK_EVERY = 256  # steps in the first recorded block / between finiteness checks
# Blocks grow (doubling) while one takes less than BLOCK_TARGET_S of CPU time,
# up to MAX_BLOCK steps and BLOCK_BYTES of recorded state: the per-block cost
# (the adapter's call into compiled code, one vectorised conversion, one
# finiteness check) is then spread over enough steps to vanish beside the
# engine's own, while a blow-up is still seen within ~0.05 s of CPU.  CPU
# time: on a loaded machine wall time would keep blocks small, and their
# per-block cost large, exactly when the run is timed against others
# (``physbench bench overhead``); a block also stops growing once it takes
# BLOCK_WALL_S of wall time, so that a timeout is seen within ~2
# BLOCK_WALL_S of wall time even for an engine whose steps wait rather than
# compute (tests/test_runner.py::test_blocks_grow_and_lose_nothing).
MAX_BLOCK = 8192
BLOCK_TARGET_S = 0.02
BLOCK_WALL_S = 0.25
BLOCK_BYTES = 8 << 20


@dataclass
class Trace:
    """Recorded states, one frame per record.  Shapes: t (F,), pos (F, n, 3),
    quat (F, n, 4) wxyz, vel (F, n, 3), angvel (F, n, 3), world frame.
    ``n_frames`` frames are valid (fewer than F if the run stopped early)."""

    t: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    vel: np.ndarray
    angvel: np.ndarray
    n_frames: int = 0
    #: the harness's penetration measurement of the valid frames
    #: (contract.geometry.Penetration, harness.metrics.run_penetration),
    #: measured once by the runner for the metrics and kept so that the
    #: trace writer does not measure again; None when not measured
    penetration: Any = None

    @classmethod
    def allocate(cls, n_frames: int, n_bodies: int) -> "Trace":
        return cls(
            t=np.full(n_frames, np.nan),
            pos=np.full((n_frames, n_bodies, 3), np.nan),
            quat=np.full((n_frames, n_bodies, 4), np.nan),
            vel=np.full((n_frames, n_bodies, 3), np.nan),
            angvel=np.full((n_frames, n_bodies, 3), np.nan),
        )

    def valid(self) -> "Trace":
        """The filled prefix (views, no copy)."""
        k = self.n_frames
        return Trace(self.t[:k], self.pos[:k], self.quat[:k], self.vel[:k], self.angvel[:k], k, self.penetration)


@dataclass
class RunResult:
    scenario: str
    variant: str | None
    engine: str
    engine_version: str
    status: str
    message: str
    settings: dict[str, Any]
    metrics: dict[str, Any] = field(default_factory=dict)
    timing: dict[str, float] = field(default_factory=dict)
    stages: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    #: the environment fingerprint's summary: every row names its machine,
    #: also rows made without a run (load errors, dead workers)
    machine: dict[str, str] = field(default_factory=lambda: machine_info())
    commit: str = ""
    timestamp: str = ""
    trace: Trace | None = None
    #: the scene's content hash (contract.scene.content_hash) and the spec
    #: file it was loaded from ('' when unknown)
    scene_hash: str = ""
    scene_path: str = ""
    #: the engine's own contacts per recorded frame, only when the run was
    #: traced with ``contact_cap``: [(frame, (k, 7) rows of
    #: Adapter.contacts(), k <= cap, deepest first)]; None when not asked
    #: for or when the adapter cannot read them.  Never part of a row.
    contacts: list | None = None

    def as_dict(self) -> dict[str, Any]:
        """The result row as one JSON-able object: identity, status, every
        metric as a top-level key, then settings, timing, stages, notes."""
        out: dict[str, Any] = {
            "scenario": self.scenario,
            "variant": self.variant,
            "scene_hash": self.scene_hash,
            "scene_path": self.scene_path,
            "engine": self.engine,
            "engine_version": self.engine_version,
            "status": self.status,
            "message": self.message,
        }
        out.update({k: jsonable(v) for k, v in self.metrics.items()})
        out["settings"] = {k: jsonable(v) for k, v in self.settings.items()}
        out["timing"] = {k: jsonable(v) for k, v in self.timing.items()}
        out["stages"] = jsonable(self.stages)
        out["notes"] = list(self.notes)
        out["info"] = jsonable(self.info)
        out["machine"] = dict(self.machine)
        out["commit"] = self.commit
        out["timestamp"] = self.timestamp
        return out

    @classmethod
    def from_row(cls, row: dict[str, Any]) -> "RunResult":
        """The result a stored row was made from (:meth:`row`), as far as a
        row holds it: every column that is not identity, status, a setting,
        timing, machine, JSON, verdict or bookkeeping column
        (harness.results.VERDICT_COLUMNS, CHECK_COLUMNS) is a metric.  A resumed
        check evaluates its finished runs from these."""
        fixed = {"scenario", "variant", "engine", "engine_version", "status", "message", "commit", "timestamp",
                 "notes", "stages", "info", *CHECK_COLUMNS, *VERDICT_COLUMNS}
        settings, timing, machine, metrics = {}, {}, {}, {}
        for k, v in row.items():
            if k in fixed:
                continue
            head, dot, tail = k.partition(".")
            if dot and head == "setting":
                settings[tail] = v
            elif dot and head == "timing":
                timing[tail] = v
            elif dot and head == "machine":
                machine[tail] = v
            else:
                metrics[k] = v

        def load(key: str, default: Any) -> Any:
            try:
                return json.loads(row[key]) if isinstance(row.get(key), str) else default
            except ValueError:
                return default

        return cls(row.get("scenario"), row.get("variant"), row.get("engine"), row.get("engine_version") or "",
                   row.get("status"), row.get("message") or "", settings, metrics, timing, load("stages", {}),
                   load("notes", []), load("info", {}), machine, row.get("commit") or "", row.get("timestamp") or "")

    def row(self) -> dict[str, Any]:
        """Flat row for tables and Parquet: nested dicts become dotted
        columns ('setting.dt', 'timing.setup_s'); lists and the stage profile
        are JSON strings."""
        d = self.as_dict()
        row: dict[str, Any] = {}
        for k, v in d.items():
            if k == "settings":
                row.update({f"setting.{sk}": sv for sk, sv in v.items()})
            elif k in ("timing", "machine"):
                row.update({f"{k}.{sk}": sv for sk, sv in v.items()})
            elif isinstance(v, (dict, list)):
                row[k] = json.dumps(v, sort_keys=True)
            else:
                row[k] = v
        return row


def jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist())
    return v


def machine_info() -> dict[str, str]:
    """A row's ``machine.*`` columns: the environment fingerprint's flat
    summary (harness/fingerprint.py: ``id`` is the machine id sweeps file
    under, ``env_id`` adds the library stack; CPU model, family/model,
    arithmetic flags, cores, BLAS, numpy/scipy/numba/Python versions, host).
    One mechanism for check, run and sweep rows
    (tests/test_fuzz.py::test_rows_and_manifests_carry_the_fingerprint)."""
    return dict(summary())


@functools.lru_cache(maxsize=1)
def commit_id() -> str:
    """The checkout's commit (``+dirty`` with uncommitted changes); for an
    installed package, which is no checkout (its folder may still lie in
    some other project's git tree), ``physbench-<version>``."""
    if checkout_root() is None:
        try:
            return f"physbench-{_dist_version('physbench')}"
        except Exception:
            return "unknown"
    root = str(checkout_root())
    try:
        out = subprocess.run(["git", "-C", root, "rev-parse", "--short=12", "HEAD"],
                             capture_output=True, text=True, timeout=5)
        sha = out.stdout.strip()
        if not sha:
            return "unknown"
        dirty = subprocess.run(["git", "-C", root, "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except Exception:
        return "unknown"


def check_run_size(scene: Scene, dt: float, record_every: Any = 1) -> int:
    """``record_every`` as an int, after checking that a run of ``scene`` at
    step ``dt`` fits the recording bounds (contract/spec/bounds.py
    record_size_error): raises ValueError naming dt and the bound.  Checked
    before anything is allocated, by the runner and, before a run goes to a
    worker, by the CLI (tests/test_fuzz.py::test_record_bound_before_allocation)."""
    if not isinstance(record_every, numbers.Integral) or record_every < 1:
        raise ValueError(f"record_every: expected an integer >= 1, got {record_every!r}")
    too_big = record_size_error(n_steps(scene.duration, dt), scene.n_bodies, int(record_every))
    if too_big:
        raise ValueError(f"{scene.id}: dt = {dt:g} s, recording every {record_every} step(s): {too_big}")
    return int(record_every)


def run(scene: Scene, engine: str, settings: dict[str, Any] | None = None, *,
        record_every: int = 1, timeout_s: float | None = None, compute_metrics: bool = True,
        contact_cap: int = 0, model_metrics: bool = True) -> RunResult:
    """Run ``scene`` on ``engine`` with setting ``settings`` overrides.

    ``model_metrics`` False leaves the reference model's metrics out of the
    computed metrics (``harness.metrics.compute_metrics(model=False)``).

    ``contact_cap`` > 0 (tracing only) also records the engine's own contact
    points after every recorded step, at most that many per frame (the
    deepest), into ``result.contacts``; it steps one step at a time through
    the adapter's public calls, so a plain run (0) pays nothing.

    Never raises for engine trouble: every failure becomes the result's
    status with a message.  Raises ValueError only for bad settings (a user
    error the caller should report as such).
    """
    cls = get_adapter(engine)
    caps = cls.capabilities()
    # an engine whose kernels numba compiles says so on stderr while it does
    # (harness/compile_progress.py; nothing when they load from the cache)
    watch()
    resolved = cls.resolve_settings(scene, settings)
    result = RunResult(
        scenario=scene.id, variant=scene.variant, engine=engine, engine_version=caps.version,
        status=st.OK, message="", settings=resolved, machine=machine_info(), commit=commit_id(),
        timestamp=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        scene_hash=scene.content_hash, scene_path=scene.source,
    )
    reason = cls.unsupported_reason(scene)
    if reason is not None:
        result.status, result.message = st.UNSUPPORTED, reason
        return result

    dt = float(resolved["dt"])
    steps = n_steps(scene.duration, dt)
    record_every = check_run_size(scene, dt, record_every)
    n_frames = steps // record_every + 1 + (1 if steps % record_every else 0)
    trace = Trace.allocate(n_frames, scene.n_bodies)
    result.trace = trace

    adapter = cls()
    if contact_cap:
        result.contacts = []
    # contact forces after every recorded step, only when a check or the
    # primary metric names a contact-law metric (stepping one step at a
    # time costs: docs/METRICS.md); a str: why the adapter has none
    forces: list | str | None = [] if compute_metrics and wants_contact_forces(scene, engine) else None
    t0 = time.perf_counter()
    try:
        adapter.build(scene, resolved)
        adapter.read_state(trace.pos[0], trace.quat[0], trace.vel[0], trace.angvel[0])
        trace.t[0] = 0.0
        trace.n_frames = 1
    except Unsupported as e:
        result.status, result.message = st.UNSUPPORTED, str(e)
        _finish(result, adapter, scene, trace, compute_metrics, dt, model_metrics)
        return result
    except Exception as e:  # the engine rejected the model
        result.status, result.message = st.FAILED, f"build failed: {type(e).__name__}: {e}"
        result.info["traceback"] = traceback.format_exc(limit=5)
        _finish(result, adapter, scene, trace, compute_metrics, dt, model_metrics)
        return result
    result.timing["setup_s"] = time.perf_counter() - t0
    # compile time of a JIT-compiled engine (within setup_s, never in step_cpu_s)
    jit_s = (adapter.stages() or {}).get("jit_s")
    if jit_s is not None:
        result.timing["jit_s"] = float(jit_s)

    cpu0 = time.process_time()
    wall0 = time.perf_counter()
    done = 0
    frame = 1
    pos, quat, vel, angvel, tt = trace.pos, trace.quat, trace.vel, trace.angvel, trace.t
    block = CHECK_EVERY
    max_block = max(CHECK_EVERY, min(MAX_BLOCK, BLOCK_BYTES // (8 * 13 * max(1, scene.n_bodies))))
    try:
        while done < steps:
            b0, w0 = time.process_time(), time.perf_counter()
            if record_every == 1:
                # a block of steps recorded every step; blocks bound the
                # work lost to a blow-up and let adapters record in bulk
                n = min(block, steps - done)
                adapter.block_done = 0
                if isinstance(forces, list):  # a str: the adapter has none, step in blocks again
                    forces = _step_record_forces(adapter, n, frame, trace, result, contact_cap, forces)
                elif contact_cap:
                    _step_record_contacts(adapter, n, frame, trace, result, contact_cap)
                else:
                    adapter.step_record(n, pos[frame:frame + n], quat[frame:frame + n],
                                        vel[frame:frame + n], angvel[frame:frame + n])
                done += n
                frame += n
                a = frame - n
            else:
                a = frame
                for _ in range(CHECK_EVERY // record_every or 1):
                    n = min(record_every, steps - done)
                    adapter.step(n)
                    done += n
                    adapter.read_state(pos[frame], quat[frame], vel[frame], angvel[frame])
                    if contact_cap:
                        _keep_contacts(adapter, frame, result, contact_cap)
                    if forces is not None:
                        forces = _keep_forces(adapter, frame, forces)
                    tt[frame] = done * dt
                    frame += 1
                    if done >= steps:
                        break
            trace.n_frames = frame
            bad = _runaway(trace, max(0, a - 1), frame)
            if bad:
                result.status, result.message = st.DIVERGED, f"{bad} at t <= {done * dt:.6g} s (step <= {done})"
                break
            now = time.perf_counter()
            if timeout_s is not None and now - wall0 > timeout_s:
                result.status = st.TIMEOUT
                result.message = f"stopped after {now - wall0:.1f} s wall at step {done} of {steps}"
                break
            if (record_every == 1 and block < max_block and time.process_time() - b0 < BLOCK_TARGET_S
                    and now - w0 < BLOCK_WALL_S):
                block = min(2 * block, max_block)
    except Exception as e:
        if record_every == 1:
            k = int(getattr(adapter, "block_done", 0))
            done += k
            frame += k
        result.status, result.message = st.ERROR, f"step {done + 1}: {type(e).__name__}: {e}"
        result.info["traceback"] = traceback.format_exc(limit=5)
    cpu = time.process_time() - cpu0
    wall = time.perf_counter() - wall0
    trace.n_frames = frame
    if record_every == 1:
        tt[1:frame] = np.arange(1, frame) * dt
    sim_time = done * dt
    result.timing.update({
        "step_cpu_s": cpu,
        "step_wall_s": wall,
        "steps": done,
        "sim_time_s": sim_time,
    })
    if isinstance(forces, list):
        # stepped one step a call, the contact forces read after each: this
        # run's step time is not the engine's (harness.points.request_row
        # times another run; tests/test_points_timing.py pins it)
        result.info["contact_forces_per_step"] = True
    result.metrics["cpu_s_per_sim_s"] = cpu / sim_time if sim_time > 0 else float("nan")
    result.metrics["wall_s_per_sim_s"] = wall / sim_time if sim_time > 0 else float("nan")
    result.metrics["steps_per_s"] = done / wall if wall > 0 else float("nan")
    refined = None
    if compute_metrics and model_metrics and result.status == st.OK:
        refined = _refined_runs(scene, engine, settings, dt, record_every, timeout_s, wall0, result)
    _finish(result, adapter, scene, trace, compute_metrics, dt, model_metrics, refined, forces)
    return result


def _keep_forces(adapter: Any, frame: int, forces: list | str) -> list | str:
    """``forces`` with the adapter's contact forces after ``frame``
    appended; the adapter's reason (a str) once it has none."""
    if isinstance(forces, str):
        return forces
    rows = adapter.contact_forces()
    if rows is None:
        return f"{adapter.name}: {adapter.contact_forces_reason}"
    forces.append((frame, {k: np.array(v) for k, v in rows.items()}))
    return forces


def _step_record_forces(adapter: Any, n: int, frame: int, trace: Trace, result: RunResult, cap: int,
                        forces: list | str) -> list | str:
    """The block of ``n`` steps from ``frame`` one step at a time, the
    contact forces (and, with ``cap``, the contacts) read after each."""
    for i in range(n):
        adapter.step(1)
        f = frame + i
        adapter.read_state(trace.pos[f], trace.quat[f], trace.vel[f], trace.angvel[f])
        forces = _keep_forces(adapter, f, forces)
        if cap:
            _keep_contacts(adapter, f, result, cap)
        adapter.block_done = i + 1
    return forces


def _refined_runs(scene: Scene, engine: str, settings: dict[str, Any] | None, dt: float, record_every: int,
                  timeout_s: float | None, wall0: float, result: RunResult) -> list | str | None:
    """The reference runs a self-consistency model asks for (its
    ``refined_dts``: the same engine and scene with the same setting
    overrides ``settings`` at finer steps -- a setting whose default
    depends on dt takes its default at the finer dt, as a run made there
    would --, recording at this run's frame times), as their valid traces; a str
    saying why when one of them is not ok (its metrics are then undefined
    with that reason); None for a model that asks for none.  They share
    this run's wall-clock budget and are timed apart from its stepping
    (``timing.refine_s``): the run's cost columns stay its own
    (tests/test_self_consistency.py)."""
    if not scene.reference_model:
        return None
    try:
        model = get_model(scene.reference_model)(scene)
    except Exception:
        return None  # the load-time check refuses such a scene; the metrics say why
    dts = getattr(model, "refined_dts", None)
    if dts is None:
        return None
    t0 = time.perf_counter()
    traces: list | str = []
    for h, every in zip(dts(dt), model.refined_record_every(record_every)):
        left = None if timeout_s is None else max(0.0, timeout_s - (time.perf_counter() - wall0))
        try:
            sub = run(scene, engine, {**(settings or {}), "dt": h}, record_every=every, timeout_s=left,
                      compute_metrics=False)
        except ValueError as e:  # a step below the engine's bound, a recording beyond the bounds
            traces = f"no refined run at dt = {h:.6g} s: {e}"
            break
        if sub.status != st.OK or sub.trace is None:
            traces = f"the refined run at dt = {h:.6g} s ended {sub.status}: {sub.message}"
            break
        traces.append(sub.trace.valid())
    result.timing["refine_s"] = time.perf_counter() - t0
    return traces


def _keep_contacts(adapter: Any, frame: int, result: RunResult, cap: int) -> None:
    """Append the adapter's contacts at ``frame`` (the ``cap`` deepest) to
    ``result.contacts``; an adapter that cannot read them sets it to None
    for good."""
    if result.contacts is None:
        return  # the adapter said no on an earlier frame
    c = adapter.contacts()
    if c is None:
        result.contacts = None
        return
    if len(c):
        if len(c) > cap:
            c = c[np.argsort(-c[:, 6], kind="stable")[:cap]]
        result.contacts.append((frame, np.array(c, float)))


def _step_record_contacts(adapter: Any, n: int, frame: int, trace: Trace, result: RunResult, cap: int) -> None:
    """The block of ``n`` steps from ``frame`` one step at a time (the
    contacts must be read after each), recording states and contacts."""
    for i in range(n):
        adapter.step(1)
        f = frame + i
        adapter.read_state(trace.pos[f], trace.quat[f], trace.vel[f], trace.angvel[f])
        _keep_contacts(adapter, f, result, cap)
        adapter.block_done = i + 1


def _runaway(trace: Trace, a: int, b: int) -> str:
    """Describe a non-finite or runaway state in frames [a, b), or ''.

    Two reductions per array and no temporary: |x| <= bound for every
    element exactly when max <= bound and -min <= bound, and a NaN makes
    the maximum and the minimum NaN, which fails the ``<=`` test; the
    message is worked out only when something is wrong
    (tests/test_runner.py::test_runaway_finds_every_bad_value)."""
    for name, bound in _RUNAWAY_BOUNDS:
        chunk = getattr(trace, name)[a:b]
        if chunk.size and not (chunk.max() <= bound and -chunk.min() <= bound):
            if not np.isfinite(chunk).all():
                return f"non-finite {name}"
            if name == "pos":
                return f"position beyond {RUNAWAY_POSITION:g} m"
            if name == "quat":
                return "quaternion norm beyond 2 (not a rotation)"
            return f"speed beyond {RUNAWAY_SPEED:g}"
    return ""


#: (trace array, bound on every component's magnitude) for :func:`_runaway`
_RUNAWAY_BOUNDS = (("pos", RUNAWAY_POSITION), ("quat", 2.0), ("vel", RUNAWAY_SPEED), ("angvel", RUNAWAY_SPEED))


def _finish(result: RunResult, adapter: Any, scene: Scene, trace: Trace, compute_metrics: bool, dt: float,
            model_metrics: bool = True, refined: list | str | None = None,
            forces: list | str | None = None) -> None:
    try:
        result.stages = adapter.stages()
    except Exception as e:  # pragma: no cover - defensive
        result.stages = {"error": str(e)}
    result.notes.extend(getattr(adapter, "notes", []))
    result.info.update(getattr(adapter, "info", {}))
    try:
        adapter.close()
    except Exception as e:
        result.notes.append(f"close() raised {type(e).__name__}: {e}")
    if compute_metrics and trace.n_frames > 0 and result.status != st.UNSUPPORTED:
        t0 = time.perf_counter()
        try:
            valid = trace.valid()
            # measured once: the metrics read it, the trace carries it to
            # the trace writer (tests/test_trace_rrd.py::test_the_runs_penetration_is_handed_to_the_trace)
            pen = run_penetration(scene, valid)
            extra = {"refined": refined} if refined is not None else {}  # only self-consistency scenes have them
            result.metrics.update(_metrics(scene, valid, dt=dt, model=model_metrics, pen=pen, **extra))
            trace.penetration = pen
            if forces is not None:
                why = getattr(adapter, "friction_forces_reason", "")
                merge_into(result.metrics, run_contact_laws(scene, forces, valid, why and f"{adapter.name}: {why}"))
        except Exception as e:
            # no ok without its metrics: a run whose metrics cannot be
            # computed is an error (tests/test_runner.py::test_metric_failure_is_an_error)
            why = f"metrics failed: {type(e).__name__}: {e}"
            if result.status == st.OK:
                result.status, result.message = st.ERROR, why
            else:
                result.notes.append(why)
            result.info["metrics_traceback"] = traceback.format_exc(limit=5)
        result.timing["metrics_s"] = time.perf_counter() - t0
        if result.status == st.OK and result.metrics.get("stable") is False:
            result.notes.append("unstable: " + str(result.metrics.get("stability_reason", "")))
        if result.metrics.get(UNDEFINED):
            result.notes.append("undefined metrics: " + str(result.metrics[UNDEFINED]))
