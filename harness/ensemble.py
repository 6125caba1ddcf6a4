"""Predictability (Chung and Pollard 2016): how much the outcome of a scene
on an engine moves when its start moves a little.

An ensemble is N runs of one scene on one engine, each from the scene's
start perturbed by independent Gaussian noise (:class:`Perturbation`: a
standard deviation for positions, velocities, orientations and angular
velocities, a seed; ``[perturbation]`` in the spec or
``physbench ensemble --n N --sigma S``).  The runs are items on the same
executors as every other run (harness.executors: worker processes under
the watchdog, or this process), each made by the runner
(:func:`run_member`), so a member that dies or hangs costs only itself and
becomes its status.

The outcome and its spread (:func:`summarize`):

- ``final_spread`` (m): over the bodies, the largest RMS distance of the
  members' final positions from their mean (``final_spread_by_body``);
- ``orientation_spread`` (rad): over the bodies, the largest RMS rotation
  angle of the members' final orientations from the first member's;
- ``events`` per member: impact events counted from the recorded
  velocities (:func:`impact_events`), and ``event_spread`` = max - min;
- ``amplification``: ``final_spread`` / the spread of the start positions
  actually drawn (undefined without position noise);
- ``predictable``: every member ``ok`` and ``final_spread`` <=
  ``threshold`` (m); None, with the reason, when a member is not ok.

tests/test_ensemble.py: a sphere dropped onto the apex of another sphere is
unpredictable, a resting stack predictable, on the reference engine.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from physbench.contract.metric_defs import ENSEMBLE_METRICS as _ENSEMBLE_DEFS
from physbench.harness import status as st

#: m: the default bound on final_spread for a ``predictable`` verdict
DEFAULT_THRESHOLD = 0.01
#: m/s: a velocity change (beyond what gravity makes in a frame) above this is an impact event
JUMP_SPEED = 0.05


@dataclass(frozen=True)
class Perturbation:
    """The ensemble: ``n`` members; Gaussian standard deviations
    ``position`` (m, per component), ``velocity`` (m/s), ``orientation``
    (rad, per component of a rotation vector applied to the body's
    orientation), ``angular_velocity`` (rad/s); ``seed``; the perturbed
    ``bodies`` (names, None: all); ``threshold`` (m) on ``final_spread``
    for a ``predictable`` verdict.  Planar scenes are perturbed in their
    x-z plane only (rotations about y)."""

    n: int = 16
    position: float = 0.0
    velocity: float = 0.0
    orientation: float = 0.0
    angular_velocity: float = 0.0
    seed: int = 0
    bodies: tuple[str, ...] | None = None
    threshold: float = DEFAULT_THRESHOLD

    def __post_init__(self) -> None:
        if not isinstance(self.n, int) or self.n < 2:
            raise ValueError(f"perturbation.n: expected an integer >= 2, got {self.n!r}")
        for k in ("position", "velocity", "orientation", "angular_velocity"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"perturbation.{k}: expected a finite number >= 0, got {v!r}")
        if not (self.position or self.velocity or self.orientation or self.angular_velocity):
            raise ValueError("perturbation: every standard deviation is 0: the members would all be the same run")
        if not (isinstance(self.threshold, (int, float)) and self.threshold > 0):
            raise ValueError(f"perturbation.threshold: expected a number > 0 (m), got {self.threshold!r}")

    @classmethod
    def of_scene(cls, scene: Any, **over: Any) -> "Perturbation":
        """The scene's ``[perturbation]`` block (its keys over the
        defaults), then the keyword overrides that are not None."""
        d = dict(getattr(scene, "perturbation", None) or {})
        d.update({k: v for k, v in over.items() if v is not None})
        if d.get("bodies") is not None:
            d["bodies"] = tuple(d["bodies"])
        return cls(**d)


def _rotvec_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (wxyz) of rotation vector r (3,) rad."""
    a = float(np.linalg.norm(r))
    if a == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[math.cos(a / 2)], math.sin(a / 2) * r / a])


def _qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    w1, v1 = p[0], p[1:]
    w2, v2 = q[0], q[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def perturb_scene(scene: Any, p: Perturbation, member: int):
    """``scene`` with the start of member ``member`` (0-based): each
    perturbed body's position, velocity, angular velocity moved by
    N(0, sigma^2) per component and its orientation turned by a rotation
    vector drawn so; the draws are the seed's and the member's only
    (numpy default_rng([seed, member])), so a member is the same start on
    every engine and every run."""
    rng = np.random.default_rng([int(p.seed), int(member)])
    names = set(p.bodies) if p.bodies is not None else None
    if names is not None:
        missing = sorted(names - {b.name for b in scene.bodies})
        if missing:
            raise ValueError(f"perturbation.bodies: unknown bodies {missing}; the scene has "
                             f"{[b.name for b in scene.bodies]}")
    plane = np.array([1.0, 0.0, 1.0]) if scene.planar else np.ones(3)
    axis = np.array([0.0, 1.0, 0.0]) if scene.planar else np.ones(3)
    bodies = []
    for b in scene.bodies:
        # draw for every body, perturbed or not: a body's draws do not depend on which others are listed
        dx, dv, dr, dw = (rng.normal(size=3) for _ in range(4))
        if names is not None and b.name not in names:
            bodies.append(b)
            continue
        q = _qmul(_rotvec_quat(p.orientation * dr * axis), np.asarray(b.orientation, float))
        bodies.append(dataclasses.replace(
            b, position=np.asarray(b.position, float) + p.position * dx * plane,
            velocity=np.asarray(b.velocity, float) + p.velocity * dv * plane,
            angular_velocity=np.asarray(b.angular_velocity, float) + p.angular_velocity * dw * axis,
            orientation=q / np.linalg.norm(q)))
    return dataclasses.replace(scene, bodies=tuple(bodies))


def impact_events(scene: Any, vel: np.ndarray, dt_frame: float) -> int:
    """Impact events in recorded velocities vel (F, n, 3) m/s, frames
    ``dt_frame`` s apart: a frame where some body's velocity change, less
    what gravity makes (g dt_frame), exceeds JUMP_SPEED + |g| dt_frame m/s
    starts an event (the |g| dt_frame: a body at rest on a support changes
    by 0, which is |g| dt_frame from free fall); consecutive such frames
    are one event."""
    if vel.shape[0] < 2:
        return 0
    g = np.asarray(scene.gravity, float)
    dv = np.diff(vel, axis=0) - g * dt_frame
    tol = JUMP_SPEED + float(np.linalg.norm(g)) * dt_frame
    jump = (np.linalg.norm(dv, axis=-1) > tol).any(axis=1)  # (F-1,)
    starts = jump & ~np.concatenate([[False], jump[:-1]])
    return int(starts.sum())


@dataclass(frozen=True)
class Member:
    """One member run: the scene (an id or a spec file's path) and variant
    on ``engine`` with ``settings`` (sorted pairs), started as member
    ``index`` of ``perturbation``; ``timeout_s`` of wall-clock budget."""

    scenario: str
    variant: str | None
    engine: str
    settings: tuple[tuple[str, Any], ...]
    perturbation: Perturbation
    index: int
    timeout_s: float | None = 600.0

    @property
    def label(self) -> str:
        return f"{self.engine} {self.scenario} member {self.index}"


def run_member(m: Member) -> dict[str, Any]:
    """Run one member (in a worker or this process): its status, message,
    final positions (n, 3) and orientations (n, 4) as lists, start
    positions (n, 3), impact event count, CPU seconds of stepping.  Never
    raises for engine trouble (a status)."""
    from physbench.contract.scene import load_scene
    from physbench.harness import runner

    out: dict[str, Any] = {"index": m.index, "status": st.ERROR, "message": ""}
    try:
        scene = perturb_scene(load_scene(m.scenario, m.variant), m.perturbation, m.index)
    except Exception as e:
        out["message"] = f"scene failed to load or perturb: {type(e).__name__}: {e}"
        return out
    res = runner.run(scene, m.engine, dict(m.settings) or None, timeout_s=m.timeout_s, compute_metrics=False)
    return _member_out(out, scene, res)


def _member_out(out: dict[str, Any], scene: Any, res: Any) -> dict[str, Any]:
    """A member's dict (:func:`run_member`) from its run result."""
    out["status"], out["message"] = res.status, res.message
    tr = res.trace.valid() if res.trace is not None else None
    if tr is None or tr.n_frames == 0:
        return out
    out["start"] = np.array([b.position for b in scene.bodies], float).tolist()
    out["final_pos"] = tr.pos[-1].tolist()
    out["final_quat"] = tr.quat[-1].tolist()
    dt = float(res.settings.get("dt", scene.dt))
    out["events"] = impact_events(scene, tr.vel, dt)
    out["step_cpu_s"] = float(res.timing.get("step_cpu_s", math.nan))
    if "batch" in res.info:
        out["batch"] = dict(res.info["batch"])
    return out


@dataclass(frozen=True)
class BatchJob:
    """All members of an ensemble as one item: one batch of an adapter that
    steps many worlds in one call (``Adapter.batched``, harness/batch.py)."""

    members: tuple[Member, ...]

    @property
    def timeout_s(self) -> float | None:
        return self.members[0].timeout_s

    @property
    def label(self) -> str:
        m = self.members[0]
        return f"{m.engine} {m.scenario} batch of {len(self.members)} members"


def run_members_batched(job: BatchJob) -> list[dict[str, Any]]:
    """Run every member of ``job`` as one batch (in a worker or this
    process): the same member dicts as :func:`run_member`, each with
    ``batch`` (worlds, the batch's stepping time, us per world-step)."""
    from physbench.contract.scene import load_scene
    from physbench.harness.batch import run_batch

    m0 = job.members[0]
    outs = [{"index": m.index, "status": st.ERROR, "message": ""} for m in job.members]
    try:
        base = load_scene(m0.scenario, m0.variant)
        scenes = [perturb_scene(base, m.perturbation, m.index) for m in job.members]
    except Exception as e:
        for o in outs:
            o["message"] = f"scene failed to load or perturb: {type(e).__name__}: {e}"
        return outs
    results = run_batch(scenes, m0.engine, dict(m0.settings) or None, timeout_s=m0.timeout_s)
    return [_member_out(o, sc, r) for o, sc, r in zip(outs, scenes, results)]


def summarize(members: list[dict[str, Any]], threshold: float) -> dict[str, Any]:
    """The ensemble's outcome spread and verdict (module docstring) from
    :func:`run_member` results."""
    from physbench.harness.references.self_consistency import rotation_angle

    out: dict[str, Any] = {"members": len(members), "threshold": float(threshold)}
    bad = [m for m in members if m.get("status") != st.OK]
    out["members_ok"] = len(members) - len(bad)
    have = [m for m in members if "final_pos" in m]
    if len(have) >= 2:
        x = np.array([m["final_pos"] for m in have])  # (N, n, 3)
        per_body = np.sqrt(np.mean(np.sum((x - x.mean(axis=0)) ** 2, axis=-1), axis=0))  # (n,)
        out["final_spread_by_body"] = per_body.tolist()
        out["final_spread"] = float(per_body.max())
        q = np.array([m["final_quat"] for m in have])
        ang = rotation_angle(q, q[:1])  # (N, n)
        out["orientation_spread"] = float(np.sqrt(np.mean(ang * ang, axis=0)).max())
        x0 = np.array([m["start"] for m in have])
        start = float(np.sqrt(np.mean(np.sum((x0 - x0.mean(axis=0)) ** 2, axis=-1), axis=0)).max())
        out["start_spread"] = start
        out["amplification"] = out["final_spread"] / start if start > 0 else None
        ev = [int(m["events"]) for m in have]
        out["events_min"], out["events_max"] = min(ev), max(ev)
        out["event_spread"] = max(ev) - min(ev)
    if bad:
        out["predictable"] = None
        out["why"] = (f"{len(bad)} of {len(members)} members not ok (first: member {bad[0]['index']} "
                      f"{bad[0]['status']}: {bad[0].get('message', '')})")
    elif "final_spread" not in out:
        out["predictable"] = None
        out["why"] = "fewer than two members recorded a final state"
    else:
        out["predictable"] = bool(out["final_spread"] <= threshold)
        out["why"] = (f"final spread {out['final_spread']:.3g} m {'<=' if out['predictable'] else '>'} "
                      f"threshold {threshold:g} m")
    return out


def run_ensemble(scenario: str, engine: str, perturbation: Perturbation | None = None, *,
                 variant: str | None = None, settings: dict[str, Any] | None = None, jobs: int = 1,
                 executor: str = "process", timeout_s: float | None = 600.0, batch: bool = True,
                 **over: Any) -> dict[str, Any]:
    """Run the ensemble of ``scenario`` (an id or a spec file) on
    ``engine``: ``perturbation``, else the scene's ``[perturbation]`` with
    the keyword overrides (n, position, ...); the members go to ``jobs``
    worker processes (``executor="inline"``: this process).  Returns the
    :func:`summarize` dict plus ``scenario``, ``engine``, ``perturbation``
    and ``per_member`` (index, status, events, final positions).  An
    engine whose adapter steps many worlds in one call (``batched``: MJX)
    gets every member as one batch, one item on the executor (``batch``
    False: one run each); ``batch`` in the result then records the worlds
    and the cost per world-step (harness/batch.py), else it is None."""
    from physbench.contract.scene import load_scene
    from physbench.harness.executors import make_executor
    from physbench.harness.execute import WorkerLost

    if perturbation is None:
        perturbation = Perturbation.of_scene(load_scene(scenario, variant), **over)
    members = [Member(scenario, variant, engine, tuple(sorted((settings or {}).items())), perturbation, i,
                      timeout_s) for i in range(perturbation.n)]
    from physbench.adapters import get_adapter

    results: list[dict[str, Any]] = []
    batched = batch and bool(getattr(get_adapter(engine), "batched", False))
    with make_executor(executor, max(1, int(jobs))) as ex:
        if batched:
            for job, value in ex.map(run_members_batched, [BatchJob(tuple(members))], budget_s=lambda j: j.timeout_s):
                if isinstance(value, WorkerLost):
                    value = [{"index": m.index, "status": value.status, "message": value.full_message()}
                             for m in job.members]
                results.extend(value)
        else:
            for m, value in ex.map(run_member, members, budget_s=lambda m: m.timeout_s):
                if isinstance(value, WorkerLost):
                    value = {"index": m.index, "status": value.status, "message": value.full_message()}
                results.append(value)
    results.sort(key=lambda r: r["index"])
    out = summarize(results, perturbation.threshold)
    out["batch"] = next((r["batch"] for r in results if "batch" in r), None)
    out.update(scenario=scenario, engine=engine, perturbation=dataclasses.asdict(perturbation),
               per_member=[{k: r.get(k) for k in ("index", "status", "message", "events", "final_pos")}
                           for r in results])
    return out


#: the outcome measures a check may bound (``[[check]] metric =
#: "predictable"``, ``equals = true``; or ``final_spread``, ...): a check on
#: one of them is evaluated on the scene's ensemble, not on its plain run
#: (harness.conformance: ``check --ensemble N``)
ENSEMBLE_METRICS = tuple(_ENSEMBLE_DEFS)
#: the ensemble row's measures besides ENSEMBLE_METRICS
_ROW_EXTRA = ("members", "members_ok", "threshold")


def ensemble_result(scenario: str, variant: str | None, engine: str, settings: dict[str, Any],
                    p: Perturbation, timeout_s: float | None = 600.0):
    """The ensemble of ``scenario`` on ``engine`` as one
    harness.runner.RunResult (a check row): status ``unsupported`` when
    every member is, else ``ok`` with the measures of :func:`summarize` as
    metrics (``predictable`` True/False, or undefined with the reason when
    a member is not ok: a check on it is then an ERROR, never a pass),
    ``ensemble_threshold`` the bound (m), the perturbation and each
    member's status in ``info``.  The members run one after the other in
    this process (a check runs this in a worker; each member has
    ``timeout_s``)."""
    import time

    from physbench.adapters import get_adapter
    from physbench.harness.references import undefined
    from physbench.harness.runner import RunResult, commit_id

    from physbench.contract.scene import load_scene

    t0 = time.perf_counter()
    scene = load_scene(scenario, variant)
    resolved = dict(settings)
    try:
        cls = get_adapter(engine)
        version = cls.capabilities().version
        resolved = cls.resolve_settings(scene, dict(settings) or None)  # the members' settings, as a run's row has them
    except Exception:  # an engine that is not installed: its members say so
        version = ""
    res = RunResult(scenario=scene.id, variant=variant, engine=engine, engine_version=version, status=st.OK,
                    message="", settings=resolved, commit=commit_id(), scene_hash=scene.content_hash,
                    scene_path=scene.source)
    out = run_ensemble(scenario, engine, p, variant=variant, settings=settings or None, executor="inline",
                       timeout_s=timeout_s)
    res.info["perturbation"] = out["perturbation"]
    res.info["members"] = [{"index": m["index"], "status": m["status"], "events": m.get("events")}
                           for m in out["per_member"]]
    unsupported = [m for m in out["per_member"] if m["status"] == st.UNSUPPORTED]
    if len(unsupported) == len(out["per_member"]):
        res.status, res.message = st.UNSUPPORTED, unsupported[0]["message"]
        return res
    for k in ENSEMBLE_METRICS + _ROW_EXTRA:
        v = out.get(k)
        name = "ensemble_threshold" if k == "threshold" else k
        if v is None:
            undefined(res.metrics, name, "no position noise: the start spread is 0"
                      if k == "amplification" and "final_spread" in out else out["why"])
        else:
            res.metrics[name] = v
    res.message = out["why"]
    res.timing["step_wall_s"] = time.perf_counter() - t0
    return res
