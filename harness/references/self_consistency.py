"""Self-consistency: the reference of a scene without a closed form is the
same engine's own run at a finer step (Erez, Tassa and Todorov 2015).

A scene declares ``[reference] model = "self_consistency"``.  The runner
(harness.runner.run) sees :meth:`SelfConsistency.refined_dts` and, after
the run at dt, makes the same engine's runs of the same scene, with the
same settings, at dt/k and dt/k^2 (k = ``params.refine``), recording the
frames at the run's own frame times only; it hands their traces to the
model (``refined``) before the metrics are computed.  The cost columns of
the row stay those of the run at dt (the refined runs are timed apart, in
``timing.refine_s``), so a sweep over dt draws the work-precision curve of
any scene with the primary metric ``self_consistency_error``.

Distances (:func:`distances`), over the frames whose times the two runs
share and the compared bodies (``params.bodies``, default all):

- ``compare = "trajectory"``: RMS over frames and bodies of |x - x'| (m)
  and of the rotation angle between q and q' (rad);
- ``compare = "final_state"``: the largest over bodies at the last shared
  frame.

Richardson's observed order p = log(e / e') / log k, with e the distance
dt <-> dt/k and e' the distance dt/k <-> dt/k^2: for an integrator of order
p in its asymptotic range e / e' = k^p.  It is ``undefined`` when e' is at
the rounding floor (nothing left to measure) -- never a number made of
rounding noise (tests/test_self_consistency.py).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.harness.references import Param, ReferenceError, ReferenceModel, undefined

#: the compared quantities
COMPARE = ("trajectory", "final_state")
#: a frame time is shared when the two runs' times agree to this many steps
TIME_MATCH = 1e-6


def rotation_angle(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """The angle (rad, in [0, pi]) of the rotation between unit quaternions
    qa and qb (..., 4) wxyz, either sign of each: 2 acos |<qa, qb>|,
    computed as 2 atan2(|qa* qb vector part|, |scalar part|) so that small
    angles keep their precision (acos near 1 loses half the digits)."""
    qa = np.asarray(qa, float)
    qb = np.asarray(qb, float)
    dot = np.sum(qa * qb, axis=-1)
    # |vector part of conj(qa) qb|^2 = |qa|^2 |qb|^2 - dot^2 (Lagrange), computed directly:
    w1, v1 = qa[..., :1], qa[..., 1:]
    w2, v2 = qb[..., :1], qb[..., 1:]
    vec = w1 * v2 - w2 * v1 - np.cross(v1, v2)
    return 2.0 * np.arctan2(np.linalg.norm(vec, axis=-1), np.abs(dot))


def shared_frames(t: np.ndarray, t_ref: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i, j) of the frames with t[i] == t_ref[j] to within
    TIME_MATCH dt: the frame times two runs share."""
    j = np.searchsorted(t_ref, t)
    j = np.clip(j, 0, max(len(t_ref) - 1, 0))
    jm = np.clip(j - 1, 0, max(len(t_ref) - 1, 0))
    pick = np.where(np.abs(t_ref[jm] - t) < np.abs(t_ref[j] - t), jm, j) if len(t_ref) else j
    ok = np.abs(t_ref[pick] - t) <= TIME_MATCH * dt if len(t_ref) else np.zeros(len(t), bool)
    return np.nonzero(ok)[0], pick[ok]


def distances(a, b, dt: float, compare: str, bodies: np.ndarray | None = None) -> tuple[float, float, int]:
    """(position distance m, rotation distance rad, shared frames) between
    traces ``a`` and ``b`` (harness.runner.Trace, valid frames) over their
    shared frame times (:func:`shared_frames`) and the body indices
    ``bodies`` (None: all): RMS over frames and bodies for ``trajectory``,
    the largest over bodies at the last shared frame for ``final_state``.
    NaN distances with 0 frames when they share none."""
    i, j = shared_frames(np.asarray(a.t), np.asarray(b.t), dt)
    if len(i) == 0:
        return math.nan, math.nan, 0
    sel = slice(None) if bodies is None else bodies
    dx = np.linalg.norm(a.pos[i][:, sel] - b.pos[j][:, sel], axis=-1)  # (F, n)
    da = rotation_angle(a.quat[i][:, sel], b.quat[j][:, sel])
    if compare == "final_state":
        return float(np.max(dx[-1])), float(np.max(da[-1])), len(i)
    return float(np.sqrt(np.mean(dx * dx))), float(np.sqrt(np.mean(da * da))), len(i)


def observed_order(e: float, e_fine: float, k: int, floor: float) -> tuple[float, str]:
    """Richardson's observed order log(e / e_fine) / log k, or (NaN, the
    reason) when it has no value: a distance not finite, or e_fine at or
    below the rounding ``floor`` (the refined runs agree to rounding: the
    ratio would be noise)."""
    if not (math.isfinite(e) and math.isfinite(e_fine)):
        return math.nan, "a distance is not finite"
    if e_fine <= floor or e <= floor:
        return math.nan, (f"the runs agree to rounding (distances {e:.3g} and {e_fine:.3g} at or below "
                          f"the floor {floor:.3g}): no error left to measure an order from")
    return math.log(e / e_fine) / math.log(k), ""


class SelfConsistency(ReferenceModel):
    name = "self_consistency"
    summary = ("No closed form: the same engine's runs at dt/k and dt/k^2 are the reference; "
               "distance to them and Richardson's observed order")
    takes = ("any scene (no closed form needed): its bodies' recorded positions and orientations. The runner "
             "makes the same engine's runs of the same scene and settings at dt/k and dt/k^2 (k = refine), "
             "timed apart from the run at dt (timing.refine_s), so the run's cost columns stay its own")
    params = (
        Param("refine", "int", 2, "refinement factor k (2..16): the reference runs are at dt/k and dt/k^2"),
        Param("compare", "str", "trajectory",
              "the compared quantity: 'trajectory' (RMS over shared frames and bodies) or "
              "'final_state' (largest over bodies at the last frame)"),
        Param("bodies", "list of str", None, "the bodies compared (default: all)"),
    )
    produces = {
        "self_consistency_error": "distance of the bodies' positions from the same engine's run at dt/k (m; "
                                  "RMS over shared frames and bodies, or the largest at the end: params.compare)",
        "self_consistency_error_fine": "the same distance between the runs at dt/k and dt/k^2 (m)",
        "observed_order": "Richardson's observed order log(e / e_fine) / log k of the position distances "
                          "(undefined when the refined runs agree to rounding)",
        "self_consistency_angle": "the same distance for orientations: rotation angle from the run at dt/k (rad)",
        "self_consistency_angle_fine": "the rotation-angle distance between the runs at dt/k and dt/k^2 (rad)",
        "observed_order_angle": "Richardson's observed order of the rotation-angle distances",
        "refined_frames": "number of frame times the run shares with its refined runs",
    }
    primary = "self_consistency_error"

    def __init__(self, scene):
        super().__init__(scene)
        k = self.param("refine", 2)
        if not 2 <= k <= 16:
            raise ReferenceError(f"refine must be an integer from 2 to 16, got {k}", key="reference.params.refine")
        self.k = int(k)
        self.compare = self.param("compare", "trajectory")
        if self.compare not in COMPARE:
            raise ReferenceError(f"compare must be one of {list(COMPARE)}, got {self.compare!r}",
                                 key="reference.params.compare")
        named = self.named("bodies", scene.bodies, "bodies")
        self.bodies = None if named is None else np.array([b.index for b in named], int)
        if scene.n_bodies == 0:
            raise ReferenceError("self_consistency needs at least one body")
        #: the refined runs' traces [dt/k, dt/k^2], set by the runner; a
        #: str: why they are missing (a refined run that was not ok)
        self.refined: list | str | None = None

    def refined_dts(self, dt: float) -> list[float]:
        """The steps of the reference runs (s): [dt/k, dt/k^2]."""
        return [dt / self.k, dt / self.k ** 2]

    def refined_record_every(self, record_every: int) -> list[int]:
        """Record every k (k^2) steps of the refined runs: their frames fall
        at the run's own frame times."""
        return [record_every * self.k, record_every * self.k ** 2]

    def metrics(self, trace) -> dict[str, Any]:
        out: dict[str, Any] = {}
        names = list(self.produces)
        if not isinstance(self.refined, list) or len(self.refined) != 2:
            why = self.refined if isinstance(self.refined, str) else (
                "needs the same engine's runs at dt/k and dt/k^2, which only the runner makes "
                "(harness.runner.run with metrics)")
            for n in names:
                undefined(out, n, why)
            return out
        fine, finer = self.refined
        dt = float(trace.t[1] - trace.t[0]) if len(trace.t) > 1 else float(self.scene.dt)
        e, a, frames = distances(trace, fine, dt, self.compare, self.bodies)
        e2, a2, frames2 = distances(fine, finer, dt, self.compare, self.bodies)
        out["refined_frames"] = min(frames, frames2)
        if frames == 0 or frames2 == 0:
            for n in names[:-1]:
                undefined(out, n, "the run and its refined runs share no frame time")
            return out
        out["self_consistency_error"] = e
        out["self_consistency_error_fine"] = e2
        out["self_consistency_angle"] = a
        out["self_consistency_angle_fine"] = a2
        # rounding floor: a few hundred ulps of the positions' scale (m) and of pi (rad)
        scale = float(np.nanmax(np.abs(trace.pos))) if trace.pos.size else 1.0
        eps = np.finfo(float).eps
        for name, (x, y, floor) in {"observed_order": (e, e2, 256 * eps * max(scale, 1.0)),
                                    "observed_order_angle": (a, a2, 256 * eps * math.pi)}.items():
            p, why = observed_order(x, y, self.k, floor)
            if why:
                undefined(out, name, why)
            else:
                out[name] = p
        return out
