"""Force stages: one stage per smooth effect.

A force stage adds forces (N) and torques (N m, world frame, about the centre
of mass) into ``ctx.F``/``ctx.T`` (n, 3), evaluated at the context's
evaluation point ``ctx.ex`` (n, 3) positions, ``ctx.eq`` (n, 4) orientations,
``ctx.eR`` (n, 3, 3) their rotation matrices, ``ctx.ev``/``ctx.ew`` (n, 3)
velocities.  The pipeline runs them once at the start of a step; the
integrators run them again at their intermediate states (RK stages).

Stages exist only for the effects a scene lists (see pipeline.build_pipeline).
Each stage runs its compiled kernel of engine/flight.py; the compiled
integrators evaluate the same kernels at their intermediate states
(:func:`force_model`).
"""

from __future__ import annotations

import numpy as np

from physbench.engine import flight
from physbench.engine.profile import Stage


class Gravity(Stage):
    """F += m g (g is zero without the 'gravity' effect, and then the stage
    is not built at all)."""

    name = "gravity"
    family = "forces"
    torque = False  # makes no torque
    pose = False  # does not read orientations
    constant = True  # does not depend on the state at all

    def __init__(self, model):
        self.mg = model.mass[:, None] * model.gravity[None, :]  # (n, 3), computed once

    def __call__(self, model, state, ctx) -> None:
        flight.gravity(self.mg, ctx.F)


class _Drag(Stage):
    """A velocity-only drag law: its kernel adds F(c, v) into ctx.F, with
    c the per-body coefficient array named like the stage
    (``model.<name>``, (n,))."""

    family = "forces"
    torque = False
    pose = False

    def __init__(self, model):
        self.c = getattr(model, self.name).copy()

    def __call__(self, model, state, ctx) -> None:
        self.kernel(self.c, ctx.ev, ctx.F)


class LinearDrag(_Drag):
    """Stokes drag F = -c v (c = Body.drag_linear, N s/m)."""

    name = "drag_linear"
    kernel = staticmethod(flight.linear_drag)


class QuadraticDrag(_Drag):
    """Quadratic drag F = -c |v| v (c = Body.drag_quadratic, N s^2/m^2)."""

    name = "drag_quadratic"
    kernel = staticmethod(flight.quadratic_drag)


class Springs(Stage):
    """Hooke springs and dashpots between anchor points.

    Anchors are body-frame offsets from the centre of mass (world-frame points
    for the world, index -1).  With d = p_b - p_a, L = |d|, u = d / L the
    tension is f = k (L - L0) + c (v_pb - v_pa) . u; body a receives +f u at
    p_a and body b -f u at p_b (with the torques r x F).  The same stage
    serves 'spring' and 'damper' (k or c are zeroed by the scene when the
    effect is absent).
    """

    name = "springs"
    family = "forces"
    torque = True
    pose = True

    def __init__(self, model):
        self.args = (np.array(model.spring_a, np.int64), np.array(model.spring_b, np.int64),
                     np.array(model.spring_anchor_a, float),
                     np.array(model.spring_anchor_b, float), np.array(model.spring_k, float),
                     np.array(model.spring_c, float), np.array(model.spring_rest, float))

    def __call__(self, model, state, ctx) -> None:
        flight.springs(*self.args, ctx.ex, ctx.eR, ctx.ev, ctx.ew, ctx.F, ctx.T)


class GyroscopicTorque(Stage):
    """Explicit gyroscopic term as a torque: T -= w x (I_world w), evaluated
    at the evaluation point, so the chosen integrator integrates it with its
    own order (forward Euler gains energy; see integrate.py for the implicit
    and energy-conserving alternatives)."""

    name = "gyroscopic"
    family = "forces"
    torque = True
    pose = True

    def __init__(self, model):
        self.idx = np.flatnonzero(~model.isotropic)
        self.I = np.array(model.inertia_body[self.idx], float)

    def __call__(self, model, state, ctx) -> None:
        flight.gyroscopic_torque(self.idx, self.I, ctx.eR, ctx.ew, ctx.T)


def force_model(model, stages) -> tuple:
    """The force stages ``stages`` as the compiled force model of
    :mod:`engine.flight` (its module doc): absent effects as empty arrays."""
    n = model.n
    z1, z3, zi = np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64)
    mg, c_lin, c_quad, sp, g_idx, g_I = z3, z1, z1, (zi, zi, z3, z3, z1, z1, z1), zi, z3
    for s in stages:
        if isinstance(s, Gravity):
            mg = np.array(s.mg, float)
        elif isinstance(s, LinearDrag):
            c_lin = s.c
        elif isinstance(s, QuadraticDrag):
            c_quad = s.c
        elif isinstance(s, Springs):
            sp = s.args
        elif isinstance(s, GyroscopicTorque):
            g_idx, g_I = np.array(s.idx, np.int64), s.I
        else:  # pragma: no cover - every force stage is listed here
            raise TypeError(f"no compiled form of the force stage {s.name}")
    assert mg.shape[0] in (0, n)
    return (mg, c_lin, c_quad) + tuple(sp) + (g_idx, g_I)


def force_stages(model) -> tuple[Stage, ...]:
    """The force stages for the scene's smooth effects."""
    out: list[Stage] = []
    if model.has("gravity") and np.any(model.gravity != 0.0):
        out.append(Gravity(model))
    if model.has("drag_linear") and np.any(model.drag_linear > 0):
        out.append(LinearDrag(model))
    if model.has("drag_quadratic") and np.any(model.drag_quadratic > 0):
        out.append(QuadraticDrag(model))
    if (model.has("spring") or model.has("damper")) and model.spring_a.size and (
            np.any(model.spring_k > 0) or np.any(model.spring_c > 0)):
        out.append(Springs(model))
    if model.has("gyroscopic") and model.setting("gyroscopic") == "explicit" and np.any(~model.isotropic):
        out.append(GyroscopicTorque(model))
    return tuple(out)
