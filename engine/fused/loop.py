"""Steps as compiled calls: a scene without contact, and several steps in one call.

:class:`FlightStep` -- a scene with no contact stage (the gyroscopic and
force scenes: force stages, [implicit gyroscopic], the free flight,
[energy-conserving rotation], the position update) runs each (sub)step as
ONE compiled call, :func:`flight_kernel`: the same kernels with the same
arguments in the same order as the stages call them one by one (the same
bits: tests/test_engine_loop.py).  It covers every force stage (gravity,
linear and quadratic drag, springs and dampers, the explicit gyroscopic
torque), every integrator and both gyroscopic stages (implicit,
energy-conserving); the profile times it as the stage ``flight_step``.

Several steps in one call: :meth:`FlightStep.advance` runs ``n`` steps
in :func:`flight_loop`, recording each step's state into the caller's
(n, n_bodies, 3|4) blocks (the door: engine/fused/__init__.py).
"""

from __future__ import annotations

import time

from numba import njit

from physbench.engine.control import EventMode
from physbench.engine.flight import (begin_step, free_flight, gravity, gyroscopic_torque, integrate_positions, linear_drag,
                           quadratic_drag, springs)
from physbench.engine.forces import GyroscopicTorque, Gravity, LinearDrag, QuadraticDrag, Springs
from physbench.engine.integrate import EnergyConservingRotation, ImplicitGyroscopic, IntegratePositions, IntegrateVelocities
from physbench.engine.fused.borrow import Borrowed, borrow
from physbench.engine.pack import Pack
from physbench.engine.state import _commit_packed, record_packed
from physbench.engine.fused.steady import NONE, blocks
from physbench.engine.fused.gyro import after_flight, before_flight, gyro_items

#: the profile's name of a no-contact scene's step (FlightStep)
FLIGHT_NAME = "flight_step"


@njit(cache=True)
def flight_kernel(kb, kg, h):
    """One (sub)step of length ``h`` of a scene without contact: begin,
    the force stages at the start state (forces.py's order: gravity,
    linear drag, quadratic drag, springs, gyroscopic torque), the implicit
    gyroscopic stage, the free flight, the energy-conserving rotation, the
    position update, the commit (module doc).  ``kb`` the context's
    begin/commit pack (engine.state.Context.kept), ``kg`` the plan's
    (:meth:`FlightStep._pack`)."""
    x, q, v, w, inv_I, x1, q1, V, W, F, T, vp, wp, R0, Iinv0 = kb.items
    flags, fm, inv_m, lever, Vn, Wn, v_free, w_free, w0, T_mean, u_lin, u_ang, work, vpn, wpn, gy = kg.items
    method, has_forces, constant, torque = flags
    mg, c_lin, c_quad, s_a, s_b, s_pa, s_pb, s_k, s_c, s_L0, t_idx, t_I = fm
    begin_step(x, q, v, w, inv_I, x1, q1, V, W, F, T, vp, wp, R0, Iinv0)
    # the force stages, evaluated at the start state (ctx.ex ... = state, ctx.eR = R0)
    gravity(mg, F)
    linear_drag(c_lin, v, F)
    quadratic_drag(c_quad, v, F)
    springs(s_a, s_b, s_pa, s_pb, s_k, s_c, s_L0, x, R0, v, w, F, T)
    gyroscopic_torque(t_idx, t_I, R0, w, T)
    # integrate.ImplicitGyroscopic (the explicit torque is the force model's
    # here: gyro_items' is empty, engine/fused/gyro.py)
    before_flight(gy, R0, w, T, W, h)
    # integrate.IntegrateVelocities
    w0[:, :] = Wn
    free_flight(method, has_forces, constant, torque, fm, x, q, v, w0, w, h, F, T, R0, inv_m, inv_I, lever, x1, q1,
                Vn, Wn, T_mean, u_lin, u_ang, work)
    v_free[:, :] = Vn
    w_free[:, :] = Wn
    # integrate.EnergyConservingRotation
    after_flight(gy, R0, T_mean, w, q, h, lever, q1, W, w_free, u_ang)
    integrate_positions(x1, q1, Vn, Wn, v_free, w_free, vpn, wpn, h, lever)
    _commit_packed(kb)


@njit(cache=True)
def flight_loop(n, substeps, kb, kg, h, t, rec_on, pos, quat, vel, angvel):
    """``n`` steps of ``substeps`` (sub)steps of :func:`flight_kernel`,
    each step's state into row k of the blocks when ``rec_on``; returns the
    time after them (``state.t`` plus h per (sub)step, added one by one as
    the step loop does)."""
    pos, quat, vel, angvel = borrow((pos, quat, vel, angvel))  # (engine/fused/borrow.py)
    for k in range(n):
        for s in range(substeps):
            flight_kernel(kb, kg, h)
            t += h
        record_packed(kb, k, rec_on, pos, quat, vel, angvel)
    return t


class FlightStep:
    """The plan's step of a scene without contact (module doc) over the
    pipeline's stage objects."""

    def __init__(self, model, forces, fly, gyro):
        self.fly = fly
        self.gyro = gyro
        #: the gyroscopic stage's arrays and kept work, as the fused steady
        #: step's (gyro.gyro_items; no explicit torque there: the
        #: force model has it)
        self.gy = gyro_items((), gyro)
        #: the stages the call runs: each counts its calls (its seconds are
        #: the call's, ``flight_step``)
        self.names = tuple(s.name for s in forces) + tuple(s.name for s in (gyro, fly) if s is not None) + (
            "integrate_positions",)
        self._k = self._k_ctx = None
        #: the packs handed to the loop, borrowed (engine/fused/borrow.py)
        self.borrowed = Borrowed()

    @staticmethod
    def build(model, stages) -> "FlightStep | None":
        """The fused step for ``stages`` when they are force stages,
        [implicit gyroscopic], the free flight, [energy-conserving
        rotation] and the position update, else None."""
        forces = [s for s in stages if s.family == "forces"]
        if any(type(s) not in (Gravity, LinearDrag, QuadraticDrag, Springs, GyroscopicTorque) for s in forces):
            return None
        rest = [type(s) for s in stages if s.family != "forces"]
        for gyro in ([], [ImplicitGyroscopic], [EnergyConservingRotation]):
            want = [IntegrateVelocities, IntegratePositions]
            if gyro == [ImplicitGyroscopic]:
                want = gyro + want
            elif gyro:
                want = [IntegrateVelocities] + gyro + [IntegratePositions]
            if rest == want:
                break
        else:
            return None
        fly = next(s for s in stages if type(s) is IntegrateVelocities)
        g = next((s for s in stages if type(s) in (ImplicitGyroscopic, EnergyConservingRotation)), None)
        return FlightStep(model, forces, fly, g)

    def _pack(self, ctx) -> Pack:
        """The plan's arrays and the context's views as one Pack, kept per
        context."""
        if self._k_ctx is not ctx:
            n = ctx.x1.shape[0]
            fly = self.fly
            flags = (fly.code, bool(fly.forces), fly.constant, fly.torque)
            self._k = Pack((flags, fly.fm, fly.inv_m, float(fly.c), ctx.v[:n], ctx.w[:n], ctx.v_free, ctx.w_free,
                            fly._w0, ctx.T_mean, ctx.u_lin, ctx.u_ang, fly._work, ctx.vp[:n], ctx.wp[:n], self.gy))
            self._k_ctx = ctx
        return self._k

    def call(self) -> str:
        """The compiled call :meth:`advance` makes (its profile name)."""
        return FLIGHT_NAME

    def advance(self, model, state, ctx, plan, n: int, rec) -> tuple[int, int]:
        """The door's step (engine/fused/__init__.py): :meth:`run`, which
        never stops early.  Returns (n, NONE)."""
        self.run(model, state, ctx, ctx.profile, n, rec)
        return n, NONE

    def run(self, model, state, ctx, profile, n: int = 1, rec=None) -> None:
        """``n`` steps (``model.substeps`` (sub)steps each) from ``state``,
        recorded into ``rec`` ((pos, quat, vel, angvel) blocks of n rows)
        when given; counted and timed as ``n * substeps`` calls."""
        t0 = time.perf_counter()
        h = model.h
        ctx.missed_skip.clear()
        ctx.warm0 = state.warm
        ctx.event_mode = EventMode.SPECULATIVE
        ctx.reset(state, h)
        ctx.stop_allowed = False
        rec_on, blocks_ = blocks(rec, model.n)
        b = self.borrowed.of
        state.t = flight_loop(n, model.substeps, b(ctx.kept(state)), b(self._pack(ctx)), float(h), float(state.t),
                              rec_on, *blocks_)
        state.steps += n
        k = n * model.substeps
        for name in self.names:
            profile.charge(name, k, 0.0)
        profile.charge(FLIGHT_NAME, k, time.perf_counter() - t0)
