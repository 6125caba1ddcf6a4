"""Batched runs: W copies of one scene that differ only in their start,
handed to an adapter that steps them in one call (``Adapter.batched``:
MJX vmaps its compiled scan over the worlds), else run one at a time.

:func:`run_batch` returns one :class:`runner.RunResult` per scene, as
:func:`runner.run` would (status, message, trace, settings, timing), with
no metrics (the callers judge the traces: the ensemble, harness/ensemble.py).
A batched run's ``timing``: ``jit_s`` and ``setup_s`` are the batch's
(once), ``step_cpu_s``/``step_wall_s`` the batch's stepping divided by W
(the cost per world), and ``info['batch']`` records W, the batch's own
stepping time and the cost per world-step in microseconds.  A world whose
state turns non-finite or runs away is ``diverged`` from that frame on
(the runner's rule, :func:`runner._runaway`), the others stay ``ok``.
An adapter whose model depends on the start may refuse a batch
(``adapters.base.NotOneBatch``: MJX when MuJoCo's explicit contact pairs
differ between the starts); the worlds then run one at a time, each result
noting why.

What may differ between the scenes: the bodies' position, orientation,
velocity and angular velocity.  Anything else (a mass, a material, dt, the
duration) is a different model, and :func:`same_but_start` refuses the
batch with the first difference.

Tests: tests/test_batch.py (the batched MJX worlds equal the sequential
MJX runs; the fallback equals runner.run; a batch of different models is
refused).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import time
from typing import Any

import numpy as np

from physbench.harness import status as st
from physbench.contract.scene import content_hash
from physbench.adapters import get_adapter
from physbench.adapters.base import NotOneBatch, Unsupported
from physbench.contract.scene import n_steps
from physbench.harness import runner
from physbench.harness.runner import _runaway

#: the body fields a batch's scenes may differ in
START_FIELDS = ("position", "orientation", "velocity", "angular_velocity")


def _without_start(scene: Any) -> Any:
    bodies = tuple(dataclasses.replace(b, **{k: np.zeros_like(np.asarray(getattr(b, k), float))
                                             for k in START_FIELDS}) for b in scene.bodies)
    return dataclasses.replace(scene, bodies=bodies)


def same_but_start(scenes: list[Any]) -> str | None:
    """Why ``scenes`` are not one scene with different starts, or None."""

    if not scenes:
        return "an empty batch"
    ref = content_hash(_without_start(scenes[0]))
    for k, sc in enumerate(scenes[1:], 1):
        if sc.n_bodies != scenes[0].n_bodies or content_hash(_without_start(sc)) != ref:
            return (f"scene {k} ({sc.id}[{sc.variant or 'base'}]) differs from scene 0 in more than the bodies' "
                    f"start ({', '.join(START_FIELDS)}): a batch is one model")
    return None


def run_batch(scenes: list[Any], engine: str, settings: dict[str, Any] | None = None, *,
              batch: bool = True, timeout_s: float | None = None) -> list[Any]:
    """Run ``scenes`` (one scene, different starts) on ``engine``: as one
    batch when the adapter is ``batched`` and ``batch``, else one
    :func:`runner.run` each.  One RunResult per scene, in order."""

    why = same_but_start(scenes)
    if why:
        raise ValueError(why)
    cls = get_adapter(engine)
    if not (batch and getattr(cls, "batched", False)):
        return [runner.run(sc, engine, settings, timeout_s=timeout_s, compute_metrics=False) for sc in scenes]
    caps = cls.capabilities()
    resolved = cls.resolve_settings(scenes[0], settings)
    stamp = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    results = [runner.RunResult(scenario=sc.id, variant=sc.variant, engine=engine, engine_version=caps.version,
                                status=st.OK, message="", settings=dict(resolved), machine=runner.machine_info(),
                                commit=runner.commit_id(), timestamp=stamp, scene_hash=sc.content_hash,
                                scene_path=sc.source) for sc in scenes]

    def all_(status: str, message: str) -> list[Any]:
        for r in results:
            r.status, r.message = status, message
        return results

    reason = cls.unsupported_reason(scenes[0])
    if reason is not None:
        return all_(st.UNSUPPORTED, reason)
    w, nb = len(scenes), scenes[0].n_bodies
    dt = float(resolved["dt"])
    steps = n_steps(scenes[0].duration, dt)
    runner.check_run_size(scenes[0], dt)
    traces = [runner.Trace.allocate(steps + 1, nb) for _ in scenes]
    pos, quat = np.empty((w, steps + 1, nb, 3)), np.empty((w, steps + 1, nb, 4))
    vel, angvel = np.empty((w, steps + 1, nb, 3)), np.empty((w, steps + 1, nb, 3))
    adapter = cls()
    t0 = time.perf_counter()
    try:
        adapter.build_batch(list(scenes), resolved)
        adapter.read_state_batch(pos[:, 0], quat[:, 0], vel[:, 0], angvel[:, 0])
    except Unsupported as e:
        return all_(st.UNSUPPORTED, str(e))
    except NotOneBatch as e:  # one run each, saying why
        adapter.close()
        out = [runner.run(sc, engine, settings, timeout_s=timeout_s, compute_metrics=False) for sc in scenes]
        for r in out:
            r.notes.append(f"run one at a time: {engine} cannot batch these starts: {e}")
        return out
    except Exception as e:  # the engine rejected the model
        return all_(st.FAILED, f"build failed: {type(e).__name__}: {e}")
    setup_s = time.perf_counter() - t0
    jit_s = (adapter.stages() or {}).get("jit_s")
    cpu0, wall0 = time.process_time(), time.perf_counter()
    try:
        adapter.step_record_batch(steps, pos[:, 1:], quat[:, 1:], vel[:, 1:], angvel[:, 1:])
    except Exception as e:
        return all_(st.ERROR, f"batched step failed: {type(e).__name__}: {e}")
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    adapter.close()
    per_us = cpu / max(1, w * steps) * 1e6
    for k, (r, tr) in enumerate(zip(results, traces)):
        tr.t[:] = np.arange(steps + 1) * dt
        tr.pos[:], tr.quat[:], tr.vel[:], tr.angvel[:] = pos[k], quat[k], vel[k], angvel[k]
        tr.n_frames = steps + 1
        bad = _first_bad_frame(tr)
        if bad is not None:
            frame, what = bad
            tr.n_frames = frame
            r.status, r.message = st.DIVERGED, f"{what} at t <= {frame * dt:g} s (step <= {frame})"
        r.trace = tr
        r.timing.update(setup_s=setup_s, step_cpu_s=cpu / w, step_wall_s=wall / w, steps=steps,
                        sim_time_s=steps * dt)
        if jit_s is not None:
            r.timing["jit_s"] = float(jit_s)
        r.stages = dict(adapter.stages() or {})
        r.info["batch"] = {"worlds": w, "step_cpu_s": cpu, "step_wall_s": wall, "us_per_world_step": per_us}
        r.notes = list(adapter.notes)
    return results


def _first_bad_frame(tr: Any) -> tuple[int, str] | None:
    """The first frame whose state is non-finite or runs away (the
    runner's bounds), with what, or None."""

    if not _runaway(tr, 0, tr.n_frames):
        return None
    lo, hi = 0, tr.n_frames  # the bad frame lies in [lo, hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if _runaway(tr, lo, mid):
            hi = mid
        else:
            lo = mid
    return lo, _runaway(tr, lo, lo + 1)


__all__ = ["START_FIELDS", "run_batch", "same_but_start"]
