"""Resting stacks: every body should stay exactly where it was placed.

A stack of boxes placed in contact on the ground, released from rest under
gravity, is in static equilibrium (each contact carries the weight above it,
no tangential load), so the exact solution is "nothing moves":

    x_i(t) = x_i(0),   v_i(t) = 0   for all t.

Metrics (besides ``trajectory_rmse`` / ``final_position_error`` against the
constant reference):

- ``stack_drift`` (m): the largest displacement |x_i(t) - x_i(0)| of any body
  at any time of the run.  It collects sinking into soft contacts, sliding,
  jitter walk and toppling alike.
- ``residual_velocity`` (m/s): the largest linear speed of any body over the
  last 10 % of the run (at least the last frame): a stack that still jitters
  or slides at the end has not come to rest.
"""

from __future__ import annotations

import math

import numpy as np

from physbench.contract.rotation import quat_rotate
from physbench.harness.references import TRAJECTORY, ReferenceError, ReferenceModel, ReferenceSeries, constant, trajectory_metrics

RESIDUAL_WINDOW = 0.10  # last fraction of the run that residual_velocity looks at


#: a log pile's top log "fell" when it dropped this fraction of the way to
#: the ground (sqrt(4 r^2 - s^2) for a half spacing s): a held pile drops
#: only by contact compliance (um to mm), a collapsed one the whole way
COLLAPSE_FRACTION = 0.5


def _up(scene) -> np.ndarray:
    """Unit vector against gravity (+z without gravity)."""
    gn = float(np.linalg.norm(scene.gravity))
    return -scene.gravity / gn if gn > 0 else np.array([0.0, 0.0, 1.0])


def _height_series(scene, x0: np.ndarray, bodies) -> list[ReferenceSeries]:
    """Each of ``bodies``' height (m, along -g) held at its start: the
    reference line of a body that should not move, with the measured height
    as its twin (sinking, toppling and sliding off show as a departure)."""
    up = _up(scene)
    return [ReferenceSeries(f"{b.name}/height", "m", f"{b.name} height: stays at {float(x0[b.index] @ up):.6g} m",
                            constant(x0[b.index] @ up),
                            lambda tr, i=b.index: tr.pos[:, i] @ up)
            for b in bodies]


def _rest_metrics(trace, x0: np.ndarray) -> dict[str, float]:
    """``stack_drift`` (m): the largest |x_i(t) - x0_i| of any body at any
    time; ``residual_velocity`` (m/s): the largest speed of any body over
    the last RESIDUAL_WINDOW of the run (at least the last frame)."""
    disp = np.linalg.norm(trace.pos - x0[None], axis=-1)  # (F, n)
    F = trace.pos.shape[0]
    start = min(int(np.searchsorted(trace.t, float(trace.t[-1]) * (1.0 - RESIDUAL_WINDOW), side="left")), F - 1)
    return {"stack_drift": float(np.nanmax(disp)),
            "residual_velocity": float(np.nanmax(np.linalg.norm(trace.vel[start:], axis=-1)))}


class LogPile(ReferenceModel):
    """Three equal logs (cylinders lying parallel and level): two on a level
    ground, the third resting symmetrically in the groove between them,
    released at rest.

    Statics.  The top log (weight W_t) presses on each lower log along
    their line of centres, at th = asin(s / 2r) from vertical (s the half
    spacing of the lower logs).  A lower log is held by that contact and the
    ground's alone (the lower logs must not touch: s > r); its moment about
    its own axis makes the two friction forces on it equal, F = f.  Then
    (derivation in the scenario file)

        N = W_t / 2,   F / N = tan(th / 2)                  (log on log)
        R = W_b + W_t / 2,   f / R = tan(th / 2) W_t / (2 W_b + W_t)   (log on ground)

    so the pile holds when static friction covers both demands and
    collapses otherwise: the lower logs roll apart and the top log falls to
    the ground (the demand only grows as th opens).

    Metrics: ``friction_demand`` (tan(th / 2)), ``ground_friction_demand``,
    ``pile_holds`` (the prediction, bool), ``top_drop`` (m, the largest fall
    of the top log below its start), ``top_fell`` (bool: top_drop beyond
    COLLAPSE_FRACTION of the way to the ground), ``outcome_ok`` (bool:
    top_fell is the opposite of pile_holds), and static_stack's
    ``stack_drift`` and ``residual_velocity``.
    """

    name = "log_pile"
    summary = "three logs (two on level ground, one in the groove): statics predict whether friction holds the pile"
    takes = ("three equal-radius cylinders lying level and parallel, at rest, one level ground plane, gravity "
             "along -z, the pairs' static friction")
    produces = {
        "friction_demand": "tan(th / 2), the log-on-log friction ratio the pile needs (1)",
        "ground_friction_demand": "the log-on-ground friction ratio the pile needs (1)",
        "pile_holds": "the prediction (bool)",
        "top_drop": "largest fall of the top log below its start (m)",
        "top_fell": "top_drop beyond half the way to the ground (bool)",
        "outcome_ok": "top_fell is the opposite of pile_holds (bool)",
        "stack_drift": "largest displacement of any body from its start at any time (m)",
        "residual_velocity": "largest speed of any body over the last 10 % of the run (m/s)",
        **TRAJECTORY,
    }
    primary = "stack_drift"

    def __init__(self, scene):
        super().__init__(scene)
        bodies = scene.bodies
        if len(bodies) != 3 or any(b.shape != "cylinder" for b in bodies):
            raise ReferenceError("log_pile needs exactly three cylinder bodies")
        r = bodies[0].radius
        if any(abs(b.radius - r) > 1e-12 * r for b in bodies):
            raise ReferenceError("log_pile needs logs of one radius")
        planes = [s for s in scene.statics if s.shape == "plane"]
        if len(planes) != 1 or not np.allclose(planes[0].normal, [0.0, 0.0, 1.0], atol=1e-12):
            raise ReferenceError("log_pile needs one level ground plane (normal +z)")
        g = scene.gravity
        if abs(g[0]) > 0 or abs(g[1]) > 0 or g[2] >= 0:
            raise ReferenceError("log_pile needs gravity along -z")
        x0, q0, v0, w0 = scene.initial_state()
        if np.any(v0 != 0) or np.any(w0 != 0):
            raise ReferenceError("log_pile needs every log at rest at t = 0")
        ax = quat_rotate(q0, np.broadcast_to([0.0, 0.0, 1.0], (3, 3)))  # the logs' axes
        if np.any(np.abs(ax[:, 2]) > 1e-9) or np.any(np.linalg.norm(np.cross(ax, ax[0]), axis=1) > 1e-9):
            raise ReferenceError("log_pile needs the three logs lying level and parallel")
        ground = float(planes[0].offset)
        order = np.argsort(x0[:, 2])
        lo, top = order[:2], int(order[2])
        if np.any(np.abs(x0[lo, 2] - (ground + r)) > 1e-9):
            raise ReferenceError("log_pile needs two logs lying on the ground (centres at height r)")
        across = np.cross(ax[0], [0.0, 0.0, 1.0])  # level, across the logs
        u = (x0 - x0[top]) @ across
        s = 0.5 * (u[lo].max() - u[lo].min())
        if abs(u[lo].sum()) > 1e-9 or not (r < s < 2.0 * r):
            raise ReferenceError("log_pile needs the lower logs apart (r < half spacing < 2 r) "
                                 "and the top log centred above them")
        h = math.sqrt(4.0 * r * r - s * s)
        if abs(x0[top, 2] - (ground + r + h)) > 1e-9:
            raise ReferenceError("log_pile needs the top log resting on both lower logs "
                                 f"(centre at height {ground + r + h:.9g})")
        mb = bodies[int(lo[0])].mass
        if abs(bodies[int(lo[1])].mass - mb) > 1e-12 * mb:
            raise ReferenceError("log_pile needs the two lower logs of one mass")
        mt = bodies[top].mass
        half = math.tan(0.5 * math.asin(s / (2.0 * r)))
        self.friction_demand = half
        self.ground_friction_demand = half * mt / (2.0 * mb + mt)
        mu_ll = min(scene.pair(bodies[top].material, bodies[int(i)].material).static_friction for i in lo)
        mu_lg = min(scene.pair(bodies[int(i)].material, planes[0].material).static_friction for i in lo)
        self.holds = bool(mu_ll >= half and mu_lg >= self.ground_friction_demand)
        self.top, self.x0 = top, x0
        self.full_drop = h

    def positions(self, t: np.ndarray) -> np.ndarray | None:
        """Held: the start, constant (F, n, 3).  Collapsing: no closed form."""
        if not self.holds:
            return None
        return np.broadcast_to(self.x0, (len(t),) + self.x0.shape).copy()

    def reference_series(self) -> list[ReferenceSeries]:
        """The top log's drop (m): 0 while the pile holds (no line for a
        collapse: its timing has no closed form), and the drop past which
        the pile counts as fallen (a level, no measured twin)."""
        top, z0, level = self.top, float(self.x0[self.top, 2]), COLLAPSE_FRACTION * self.full_drop
        name = self.scene.bodies[top].name
        held = np.nan if not self.holds else 0.0
        return [ReferenceSeries(f"{name}/drop", "m", f"drop of the top log: predicted {'0 (holds)' if self.holds else 'a collapse'}",
                                constant(held), lambda tr: z0 - tr.pos[:, top, 2]),
                ReferenceSeries(f"{name}/fall_level", "m", f"top_fell past a drop of {level:.6g} m "
                                f"({COLLAPSE_FRACTION:g} of the way to the ground)", constant(level))]

    def predictions(self) -> dict[str, str]:
        return {"outcome": "holds" if self.holds else "collapses",
                "friction demand (log on log, ground)": f"{self.friction_demand:.6g}, {self.ground_friction_demand:.6g}",
                "top log's drop to the ground": f"{self.full_drop:.6g} m"}

    def metrics(self, trace) -> dict[str, float]:
        out = trajectory_metrics(trace.pos, self.positions(trace.t)) if self.holds else {}
        drop = float(np.nanmax(self.x0[self.top, 2] - trace.pos[:, self.top, 2]))
        fell = drop > COLLAPSE_FRACTION * self.full_drop
        out.update(friction_demand=self.friction_demand, ground_friction_demand=self.ground_friction_demand,
                   pile_holds=self.holds, top_drop=drop, top_fell=bool(fell), outcome_ok=bool(fell != self.holds),
                   **_rest_metrics(trace, self.x0))
        return out


class StaticStack(ReferenceModel):
    name = "static_stack"
    summary = "bodies placed at rest in static equilibrium stay where they are"
    takes = "any bodies, every one at rest at t = 0"
    produces = {
        "stack_drift": "largest displacement of any body from its start at any time (m)",
        "residual_velocity": "largest speed of any body over the last 10 % of the run (m/s)",
        **TRAJECTORY,
    }
    primary = "stack_drift"

    def __init__(self, scene):
        super().__init__(scene)
        if scene.n_bodies == 0:
            raise ReferenceError("static_stack needs at least one body")
        x0, _, v0, w0 = scene.initial_state()
        if np.any(v0 != 0) or np.any(w0 != 0):
            raise ReferenceError("static_stack needs every body at rest at t = 0 (velocity and angular_velocity zero)")
        self.x0 = x0

    def reference_series(self) -> list[ReferenceSeries]:
        """Each body's height held at its start (m)."""
        return _height_series(self.scene, self.x0, self.scene.bodies)

    def predictions(self) -> dict[str, str]:
        return {"every body": "stays at its start, at rest",
                "heights": ", ".join(f"{b.name} {float(self.x0[b.index] @ _up(self.scene)):.6g}"
                                     for b in self.scene.bodies) + " m"}

    def positions(self, t: np.ndarray) -> np.ndarray:
        """Constant reference positions (F, n, 3)."""
        return np.broadcast_to(self.x0, (len(t),) + self.x0.shape).copy()

    def metrics(self, trace) -> dict[str, float]:
        out = trajectory_metrics(trace.pos, self.positions(trace.t))
        out.update(_rest_metrics(trace, self.x0))
        return out
