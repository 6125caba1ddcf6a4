"""Force stages: one stage per smooth effect.

A force stage adds forces (N) and torques (N m, world frame, about the centre
of mass) into ``ctx.F``/``ctx.T`` (n, 3), evaluated at the context's
evaluation point ``ctx.ex`` (n, 3) positions, ``ctx.eq`` (n, 4) orientations,
``ctx.eR`` (n, 3, 3) their rotation matrices, ``ctx.ev``/``ctx.ew`` (n, 3)
velocities.  The pipeline runs them once at the start of a step; the
integrators run them again at their intermediate states (RK stages).

Stages exist only for the effects a scene lists (see pipeline.build_pipeline).
"""

from __future__ import annotations

import numpy as np

from engine.mathutil import cross
from engine.profile import Stage


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
        ctx.F += self.mg


class LinearDrag(Stage):
    """Stokes drag F = -c v (c = Body.drag_linear, N s/m)."""

    name = "drag_linear"
    family = "forces"
    torque = False
    pose = False

    def __init__(self, model):
        self.c = model.drag_linear[:, None].copy()

    def __call__(self, model, state, ctx) -> None:
        ctx.F -= self.c * ctx.ev


class QuadraticDrag(Stage):
    """Quadratic drag F = -c |v| v (c = Body.drag_quadratic, N s^2/m^2)."""

    name = "drag_quadratic"
    family = "forces"
    torque = False
    pose = False

    def __init__(self, model):
        self.c = model.drag_quadratic.copy()

    def __call__(self, model, state, ctx) -> None:
        v = ctx.ev
        speed = np.sqrt(np.einsum("ki,ki->k", v, v))
        ctx.F -= (self.c * speed)[:, None] * v


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
        self.a = model.spring_a
        self.b = model.spring_b
        self.k = model.spring_k
        self.c = model.spring_c
        self.L0 = model.spring_rest
        self.wa = self.a >= 0
        self.wb = self.b >= 0
        # indices with the world mapped to 0 (masked out below)
        self.ia = np.where(self.wa, self.a, 0)
        self.ib = np.where(self.wb, self.b, 0)
        self.anc_a = model.spring_anchor_a
        self.anc_b = model.spring_anchor_b

    def _end(self, ctx, idx, mask, anchor):
        """World anchor point, lever arm and point velocity of one end."""
        R = ctx.eR[idx]
        r = np.einsum("kij,kj->ki", R, anchor)
        p = np.where(mask[:, None], ctx.ex[idx] + r, anchor)
        vel = np.where(mask[:, None], ctx.ev[idx] + cross(ctx.ew[idx], r), 0.0)
        return p, np.where(mask[:, None], r, 0.0), vel

    def __call__(self, model, state, ctx) -> None:
        pa, ra, va = self._end(ctx, self.ia, self.wa, self.anc_a)
        pb, rb, vb = self._end(ctx, self.ib, self.wb, self.anc_b)
        d = pb - pa
        L = np.sqrt(np.einsum("ki,ki->k", d, d))
        safe = L > 1e-12
        u = np.where(safe[:, None], d / np.where(safe, L, 1.0)[:, None], 0.0)
        f = self.k * (L - self.L0) + self.c * np.einsum("ki,ki->k", vb - va, u)
        Fa = f[:, None] * u  # on a, toward b when stretched
        ma = self.wa[:, None]
        mb = self.wb[:, None]
        np.add.at(ctx.F, self.ia, np.where(ma, Fa, 0.0))
        np.add.at(ctx.T, self.ia, np.where(ma, cross(ra, Fa), 0.0))
        np.add.at(ctx.F, self.ib, np.where(mb, -Fa, 0.0))
        np.add.at(ctx.T, self.ib, np.where(mb, cross(rb, -Fa), 0.0))


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
        self.I = model.inertia_body[self.idx]

    def __call__(self, model, state, ctx) -> None:
        k = self.idx
        if k.size == 0:
            return
        R = ctx.eR[k]
        w = ctx.ew[k]
        wb = np.einsum("kji,kj->ki", R, w)
        Lw = np.einsum("kij,kj->ki", R, self.I * wb)
        ctx.T[k] -= cross(w, Lw)
