"""What a diagnosing trace computes besides the bodies: the reference
model's ghost and per-body error, event markers, the run's context text.

Pure numpy and text (no rerun calls), so each piece is tested on its own
(tests/test_trace_diagnose.py); :mod:`harness.trace.writer` logs them.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from physbench.contract.metric_defs import dissipation
from physbench.contract.scene import Scene
from physbench.harness.joints import joint_violations
from physbench.harness.metrics import momentum_drift_series, relative_energy
from physbench.harness.references import get_model
from physbench.harness.runner import RUNAWAY_POSITION, RUNAWAY_SPEED

REST_SPEED = 1e-3  # m/s: a body is at rest when |v| and |w| x bounding radius stay below this
MAX_EVENTS = 200  # per run: a trace marks where to look, it is not a log


@dataclass(frozen=True)
class Event:
    """A marker on the timeline: recorded ``frame``, TextLog ``level``
    (INFO, WARN, ERROR) and ``text``."""

    frame: int
    level: str
    text: str


def reference_model(scene: Scene):
    """The scene's reference model instance, or None (no model, or it does
    not fit: the metrics say why)."""
    if not scene.reference_model:
        return None

    try:
        return get_model(scene.reference_model)(scene)
    except Exception:
        return None


def model_trajectory(model, scene: Scene, t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The ghost at times t (F,): (pos (F, n, 3) m, quat (F, n, 4) wxyz),
    NaN for bodies the model does not place; orientations the model does not
    predict stay at the body's initial orientation.  None without a
    trajectory."""
    if model is None:
        return None
    out = model.trajectory(np.asarray(t, float))
    if out is None:
        return None
    pos, quat = out
    F, n = len(t), scene.n_bodies
    if pos.shape[1] != n:  # a one-body model of a scene with more bodies
        full = np.full((F, n, 3), np.nan)
        full[:, model.the_body().index] = pos[:, 0]
        pos = full
        if quat is not None:
            fq = np.full((F, n, 4), np.nan)
            fq[:, model.the_body().index] = quat[:, 0]
            quat = fq
    q0 = np.array([b.orientation for b in scene.bodies], float).reshape(n, 4)
    if quat is None:
        quat = np.broadcast_to(q0, (F, n, 4)).copy()
    else:
        quat = np.where(np.isfinite(quat), quat, q0[None])
    return pos, quat


#: where the model's ReferenceSeries go (the ghost's twin on the plots)
PREDICTION_PATH = "/metrics/model"


def reference_series(model) -> list:
    """The model's ReferenceSeries (harness.references), [] without a model
    or when it fails (a prediction must not lose the trace)."""
    if model is None:
        return []
    try:
        return list(model.reference_series())
    except Exception:
        return []


def evaluate_series(fn, arg) -> np.ndarray | None:
    """A ReferenceSeries' ``model(t)`` or ``measure(trace)`` as float (F,),
    or None when it fails (the line is left out, the trace is kept)."""
    try:
        return np.asarray(fn(arg), float)
    except Exception:
        return None


def reference_moments(model, t_end: float) -> list[tuple[float, str]]:
    """The model's predicted moments (t s, text) within [0, t_end], sorted;
    [] without a model or when it fails."""
    if model is None:
        return []
    try:
        moments = model.reference_times()
    except Exception:
        return []
    return sorted((float(t), str(x)) for t, x in moments if 0.0 <= t <= t_end)


def model_markdown(scene: Scene, model, t_end: float) -> str:
    """/context/model: the model's name, scalar predictions, the reference
    lines drawn (entity path, unit, what) and the predicted moments."""
    preds = {}
    try:
        preds = model.predictions()
    except Exception as e:
        preds = {"predictions failed": f"{type(e).__name__}: {e}"}
    lines = [f"# reference model: {scene.reference_model}", ""]
    lines += [f"- {k}: {v}" for k, v in preds.items()] or ["(no scalar predictions)"]
    series = reference_series(model)
    if series:
        lines += ["", "## reference lines", ""]
        lines += [f"- `{PREDICTION_PATH}/{rs.key}` ({rs.unit}): {rs.text}" for rs in series]
    moments = reference_moments(model, t_end)
    if moments:
        lines += ["", "## predicted moments (/events/model)", ""]
        lines += [f"- {x}: t = {t:.6g} s" for t, x in moments]
    return "\n".join(lines)


def error_series(pos: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """|x - x_ref| per frame and body (m, (F, n)); NaN where the model
    places no body (the same distance as harness.references.trajectory_metrics)."""
    return np.linalg.norm(pos - ref, axis=-1)


def first_above(series: np.ndarray, bound: float) -> int | None:
    """First index where ``series`` (F,) exceeds ``bound``, or None."""
    with np.errstate(invalid="ignore"):
        idx = np.nonzero(series > bound)[0]
    return int(idx[0]) if idx.size else None


def divergence_frame(trace) -> int | None:
    """First frame with a non-finite or runaway state (the runner's bounds),
    or None."""
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(trace.pos) <= RUNAWAY_POSITION).all(axis=(1, 2))
        bad |= ~(np.abs(trace.vel) <= RUNAWAY_SPEED).all(axis=(1, 2))
        bad |= ~(np.abs(trace.angvel) <= RUNAWAY_SPEED).all(axis=(1, 2))
        bad |= ~(np.abs(trace.quat) <= 2.0).all(axis=(1, 2))
    idx = np.nonzero(bad)[0]
    return int(idx[0]) if idx.size else None


def rest_frames(scene: Scene, trace) -> list[tuple[int, int]]:
    """(frame, body) where a body that moved comes to rest for the rest of
    the run: from that frame on |v| and |w| x bounding radius stay below
    REST_SPEED (m/s)."""
    r = np.array([b.bounding_radius for b in scene.bodies])
    with np.errstate(invalid="ignore"):
        speed = np.maximum(np.linalg.norm(trace.vel, axis=-1), np.linalg.norm(trace.angvel, axis=-1) * r)
        moving = ~(speed < REST_SPEED)  # NaN counts as moving
    out = []
    F = speed.shape[0]
    for i in range(scene.n_bodies):
        mv = np.nonzero(moving[:, i])[0]
        if mv.size == 0 or mv[-1] >= F - 1:
            continue  # never moved, or still moving at the end
        out.append((int(mv[-1]) + 1, i))
    return sorted(out)


#: check metric -> the per-frame running form of the metric whose first
#: frame past the check's max marks where it failed (:func:`check_series`)
CROSSING_SERIES = {"max_penetration": "penetration", "final_position_error": "error",
                   "trajectory_rmse": "error", "energy_drift": "|E - E0| / E_scale",
                   "energy_gain": "(E - E0) / E_scale", "energy_dissipated": "(E0 - E) / E_scale",
                   "linear_momentum_drift": "|P - P0| / P_scale", "angular_momentum_drift": "|L - L0| / L_scale",
                   "joint_drift": "joint separation (m)", "joint_axis_drift": "joint misalignment (rad)"}


def check_series(scene: Scene, trace, penetration: np.ndarray | None = None,
                 error: np.ndarray | None = None, energy: tuple | None = None) -> dict[str, np.ndarray]:
    """Check metric -> its running value per frame ((F,), dimensionless
    except penetration and error in m), the metrics' own definitions
    (harness.metrics.relative_energy, momentum_drift_series): the metric is
    the series' maximum (energy_dissipated: its last value).  A check with
    a ``max`` first fails at the first frame whose value exceeds it.
    ``penetration``: the per-frame deepest overlap (m, (F,)); ``error``:
    per-body error against the model (m, (F, n)), its largest body counts;
    with joints, ``joint_drift`` (m) and ``joint_axis_drift`` (rad), the
    largest violation over the joints per frame;
    ``energy``: harness.metrics.relative_energy of ``trace`` when the
    caller has it (computed here when None).
    Metrics that are NaN for the scene (energy_drift of a dissipative scene,
    momentum drift under an external force) have no series."""
    out: dict[str, np.ndarray] = {}
    if penetration is not None:
        out["max_penetration"] = penetration
    if error is not None:
        with np.errstate(invalid="ignore"):
            worst = np.nanmax(np.where(np.isfinite(error), error, -np.inf), axis=1)
        out["final_position_error"] = out["trajectory_rmse"] = worst
    if scene.n_bodies and trace.pos.shape[0]:
        dE = (relative_energy(scene, trace) if energy is None else energy)[0]
        if dissipation(scene):
            out["energy_dissipated"] = -dE
        else:
            out["energy_drift"] = np.abs(dE)
        out["energy_gain"] = dE  # max(0, .) crosses a max >= 0 where dE does
        lin, ang = momentum_drift_series(scene, trace)
        if lin is not None:
            out["linear_momentum_drift"] = lin
        if ang is not None:
            out["angular_momentum_drift"] = ang
    if scene.joints and trace.pos.shape[0]:
        # the largest violation over the joints per frame: joint_drift and
        # joint_axis_drift are these series' maxima (harness.joints;
        # tests/test_trace_joints.py::test_diagnosing_trace_draws_the_joint_drift_series)
        v = joint_violations(scene, trace)
        out["joint_drift"] = np.max(np.stack([a for a, _ in v]), axis=0)
        out["joint_axis_drift"] = np.max(np.stack([b for _, b in v]), axis=0)
    return out


def find_events(scene: Scene, result, trace, *, penetration: np.ndarray | None, error: np.ndarray | None,
                model, outcomes: Sequence = (), checks: dict | None = None,
                series: dict[str, np.ndarray] | None = None) -> list[Event]:
    """Events of one run, sorted by frame (at most MAX_EVENTS):

    - each check (``outcomes`` of this run) whose metric has a running
      series (:func:`check_series`, CROSSING_SERIES) and a ``max``
      (``checks``: metric -> its contract.scene.Check): the first frame
      past max (+ tolerance);
    - the deepest penetration (its first frame);
    - the model's own events (a body passing through a wall);
    - the first diverged frame (non-finite or runaway state);
    - each body that moved coming to rest (REST_SPEED).
    """
    ev: list[Event] = []
    if series is None:
        series = check_series(scene, trace, penetration, error)
    for o in outcomes:
        name = o.metric.partition("@")[0]
        check = (checks or {}).get(o.metric)
        y = series.get(name)
        if y is None or check is None or check.max is None:
            continue
        bound = check.max + (check.tolerance or 0.0)
        f = first_above(y, bound)
        if f is not None:
            ev.append(Event(f, "ERROR" if o.outcome in ("FAIL", "ERROR") else "WARN",
                            f"check {o.metric} {o.threshold} first crossed: {CROSSING_SERIES[name]} = "
                            f"{y[f]:.6g} at t = {trace.t[f]:.6g} s ({o.outcome})"))
    if penetration is not None and penetration.size and np.nanmax(penetration) > 0:
        f = int(np.nanargmax(penetration))
        ev.append(Event(f, "INFO", f"maximum penetration {penetration[f]:.6g} m at t = {trace.t[f]:.6g} s"))
    if model is not None:
        try:
            ev += [Event(f, "ERROR", text) for f, _i, text in model.events(trace)]
        except Exception as e:  # a model's event finder must not lose the trace
            ev.append(Event(0, "WARN", f"model events failed: {type(e).__name__}: {e}"))
    f = divergence_frame(trace)
    if f is not None:
        ev.append(Event(f, "ERROR", f"diverged: non-finite or runaway state at t = {trace.t[f]:.6g} s"
                                    + (f" ({result.message})" if result.message else "")))
    for f, i in rest_frames(scene, trace):
        ev.append(Event(f, "INFO", f"{scene.bodies[i].name} at rest from t = {trace.t[f]:.6g} s"))
    ev.sort(key=lambda e: e.frame)
    return ev[:MAX_EVENTS]


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return "n/a" if math.isnan(v) else f"{v:.6g}"
    return str(v)


def context_markdown(scene: Scene, result, outcomes: Sequence = (), model=None,
                     engine_contacts: str = "") -> str:
    """The run's context as one Markdown document: scene, status, settings,
    notes, stages that ran, check thresholds and verdicts, the model's
    predictions."""
    title = scene.id + (f" [{scene.variant}]" if scene.variant else "")
    lines = [f"# {title} on {result.engine} {result.engine_version}", "",
             f"**status**: {result.status}" + (f" - {result.message}" if result.message else ""), ""]
    lines += ["## settings", ""] + [f"- {k} = {_fmt(v)}" for k, v in (result.settings or {}).items()] + [""]
    if outcomes:
        lines += ["## checks", "", "| check | threshold | value | verdict | message |", "|---|---|---|---|---|"]
        for o in outcomes:
            msg = str(o.message).replace("|", "/").replace("\n", " ")
            lines.append(f"| {o.metric} | {o.threshold} | {_fmt(o.value)} | {o.outcome} | {msg} |")
        lines.append("")
    if model is not None:
        preds = {}
        try:
            preds = model.predictions()
        except Exception as e:
            preds = {"predictions failed": f"{type(e).__name__}: {e}"}
        lines += [f"## reference model: {scene.reference_model}", ""]
        lines += [f"- {k}: {v}" for k, v in preds.items()] or ["- (no scalar predictions)"]
        lines.append("")
    if result.notes:
        lines += ["## notes", ""] + [f"- {n}" for n in result.notes] + [""]
    if result.stages:
        lines += ["## stages", "", "```", json.dumps(result.stages, indent=1, default=str, sort_keys=True), "```", ""]
    if result.metrics:
        lines += ["## metrics", ""] + [f"- {k} = {_fmt(v)}" for k, v in result.metrics.items()] + [""]
    if engine_contacts:
        lines += ["## engine contacts", "", engine_contacts, ""]
    timing = {k: v for k, v in (result.timing or {}).items()}
    if timing:
        lines += ["## timing", ""] + [f"- {k} = {_fmt(v)}" for k, v in timing.items()]
    return "\n".join(lines)
