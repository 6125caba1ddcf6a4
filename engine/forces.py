"""Force stages: one stage per smooth effect.

A force stage adds forces (N) and torques (N m, world frame, about the centre
of mass) into ``ctx.F``/``ctx.T`` (n, 3), evaluated at the context's
evaluation point ``ctx.ex`` (n, 3) positions, ``ctx.eq`` (n, 4) orientations,
``ctx.eR`` (n, 3, 3) their rotation matrices, ``ctx.ev``/``ctx.ew`` (n, 3)
velocities.  The pipeline runs them once at the start of a step; the
integrators run them again at their intermediate states (RK stages).

:data:`FORCES` is the one table of the force stages, in their order: a
stage exists for the effects a scene lists (``wanted``, see
:func:`force_stages`), runs its compiled kernel of engine/flight.py and
gives its arrays to the compiled force model (``fields``,
:func:`force_model`) and compiles its kernel ahead on small arrays of the
context's types (``warm``, engine.jit), which the integrators evaluate at their intermediate
states and the fused steps at the start (engine.flight.apply_forces lists
the kernels in the same order; tests/test_engine_force_table.py pins the
staged bits of every entry on every compiled path).
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
    kernel = staticmethod(flight.gravity)
    torque = False  # makes no torque
    pose = False  # does not read orientations
    constant = True  # does not depend on the state at all

    def __init__(self, model):
        self.mg = model.mass[:, None] * model.gravity[None, :]  # (n, 3), computed once

    @staticmethod
    def wanted(model) -> bool:
        return model.has("gravity") and bool(np.any(model.gravity != 0.0))

    def fields(self) -> dict:
        return {"mg": np.array(self.mg, float)}

    @staticmethod
    def warm(x, R, v, F, T) -> None:
        flight.gravity(np.ones(F.shape), F)

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

    @classmethod
    def wanted(cls, model) -> bool:
        return model.has(cls.name) and bool(np.any(getattr(model, cls.name) > 0))

    def fields(self) -> dict:
        return {self.field: self.c}

    @classmethod
    def warm(cls, x, R, v, F, T) -> None:
        cls.kernel(np.ones(x.shape[0]), v, F)

    def __call__(self, model, state, ctx) -> None:
        self.kernel(self.c, ctx.ev, ctx.F)


class LinearDrag(_Drag):
    """Stokes drag F = -c v (c = Body.drag_linear, N s/m)."""

    name = "drag_linear"
    field = "c_lin"
    kernel = staticmethod(flight.linear_drag)


class QuadraticDrag(_Drag):
    """Quadratic drag F = -c |v| v (c = Body.drag_quadratic, N s^2/m^2)."""

    name = "drag_quadratic"
    field = "c_quad"
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
    kernel = staticmethod(flight.springs)
    torque = True
    pose = True

    def __init__(self, model):
        self.args = (np.array(model.spring_a, np.int64), np.array(model.spring_b, np.int64),
                     np.array(model.spring_anchor_a, float),
                     np.array(model.spring_anchor_b, float), np.array(model.spring_k, float),
                     np.array(model.spring_c, float), np.array(model.spring_rest, float))

    @staticmethod
    def wanted(model) -> bool:
        return (model.has("spring") or model.has("damper")) and bool(model.spring_a.size) and bool(
            np.any(model.spring_k > 0) or np.any(model.spring_c > 0))

    def fields(self) -> dict:
        return dict(zip(("s_a", "s_b", "s_pa", "s_pb", "s_k", "s_c", "s_L0"), self.args))

    @staticmethod
    def warm(x, R, v, F, T) -> None:
        one = np.ones(1)
        flight.springs(np.array([0], np.int64), np.array([-1], np.int64), np.zeros((1, 3)), np.ones((1, 3)), one,
                       one, one, x, R, v, v, F, T)

    def __call__(self, model, state, ctx) -> None:
        flight.springs(*self.args, ctx.ex, ctx.eR, ctx.ev, ctx.ew, ctx.F, ctx.T)


class GyroscopicTorque(Stage):
    """Explicit gyroscopic term as a torque: T -= w x (I_world w), evaluated
    at the evaluation point, so the chosen integrator integrates it with its
    own order (forward Euler gains energy; see integrate.py for the implicit
    and energy-conserving alternatives)."""

    name = "gyroscopic"
    family = "forces"
    kernel = staticmethod(flight.gyroscopic_torque)
    torque = True
    pose = True

    def __init__(self, model):
        self.idx = np.flatnonzero(~model.isotropic)
        self.I = np.array(model.inertia_body[self.idx], float)

    @staticmethod
    def wanted(model) -> bool:
        return model.has("gyroscopic") and model.setting("gyroscopic") == "explicit" and bool(np.any(~model.isotropic))

    def fields(self) -> dict:
        return {"g_idx": np.array(self.idx, np.int64), "g_I": self.I}

    @staticmethod
    def warm(x, R, v, F, T) -> None:
        flight.gyroscopic_torque(np.arange(x.shape[0], dtype=np.int64), np.ones((x.shape[0], 3)), R, v, T)

    def __call__(self, model, state, ctx) -> None:
        flight.gyroscopic_torque(self.idx, self.I, ctx.eR, ctx.ew, ctx.T)


#: the force stages, in the order they run (the order of
#: engine.flight.apply_forces): the one table a new force effect is added to
FORCES = (Gravity, LinearDrag, QuadraticDrag, Springs, GyroscopicTorque)


def force_model(model, stages) -> flight.ForceModel:
    """The force stages ``stages`` as the compiled force model of
    :mod:`engine.flight` (its module doc): absent effects as empty arrays."""
    n = model.n
    z1, z3, zi = np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64)
    fm = dict(mg=z3, c_lin=z1, c_quad=z1, s_a=zi, s_b=zi, s_pa=z3, s_pb=z3, s_k=z1, s_c=z1, s_L0=z1, g_idx=zi, g_I=z3)
    for s in stages:
        if type(s) not in FORCES:  # pragma: no cover - every force stage is in the table
            raise TypeError(f"no compiled form of the force stage {s.name}")
        fm.update(s.fields())
    assert fm["mg"].shape[0] in (0, n)
    return flight.ForceModel(**fm)


def force_stages(model) -> tuple[Stage, ...]:
    """The force stages for the scene's smooth effects (:data:`FORCES`'
    order)."""
    return tuple(S(model) for S in FORCES if S.wanted(model))
