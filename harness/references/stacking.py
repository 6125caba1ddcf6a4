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

import numpy as np

from harness.references import ReferenceError, ReferenceModel, trajectory_metrics

RESIDUAL_WINDOW = 0.10  # last fraction of the run that residual_velocity looks at


class StaticStack(ReferenceModel):
    name = "static_stack"
    params_allowed = ()

    def __init__(self, scene):
        super().__init__(scene)
        if scene.n_bodies == 0:
            raise ReferenceError("static_stack needs at least one body")
        x0, _, v0, w0 = scene.initial_state()
        if np.any(v0 != 0) or np.any(w0 != 0):
            raise ReferenceError("static_stack needs every body at rest at t = 0 (velocity and angular_velocity zero)")
        self.x0 = x0

    def positions(self, t: np.ndarray) -> np.ndarray:
        """Constant reference positions (F, n, 3)."""
        return np.broadcast_to(self.x0, (len(t),) + self.x0.shape).copy()

    def metrics(self, trace) -> dict[str, float]:
        out = trajectory_metrics(trace.pos, self.positions(trace.t))
        disp = np.linalg.norm(trace.pos - self.x0[None], axis=-1)  # (F, n)
        out["stack_drift"] = float(np.nanmax(disp))
        F = trace.pos.shape[0]
        t_end = float(trace.t[-1])
        start = np.searchsorted(trace.t, t_end * (1.0 - RESIDUAL_WINDOW), side="left")
        start = min(int(start), F - 1)
        speeds = np.linalg.norm(trace.vel[start:], axis=-1)
        out["residual_velocity"] = float(np.nanmax(speeds))
        return out
