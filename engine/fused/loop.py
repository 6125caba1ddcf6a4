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

:func:`advance` -- ``n`` steps, recording each step's state into the
caller's (n, n_bodies, 3|4) blocks: consecutive steps that the step loop
would run as one fused call each (the steady step, the contact-free step:
engine/steady.py; a scene's :class:`FlightStep`) run inside ONE compiled
call that loops over them (:func:`engine.steady.steady_loop`,
:func:`engine.steady.free_loop`, :func:`flight_loop`) and stops at the
first step that is not steady; that step then runs through :func:`engine.pipeline.step` (with the loop's try of
it, so nothing is computed twice).  The bookkeeping between the steps --
``Solve.fused_finish``, the warm-start pool's rotation, the profile's calls
and counters, ``state.t`` and ``state.steps``, ``ctx.contacts``, the
backoff -- comes out as with one :func:`engine.pipeline.step` per step
(tests/test_engine_loop.py); the profile's seconds are the loop's, shared
out as one sum.  A profile by stage (``Profile.by_stage``) and scenes with
``substeps`` > 1 (contact scenes) step one by one.
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit

from physbench.engine.control import EventMode
from physbench.engine.flight import (begin_step, free_flight, gravity, gyroscopic_torque, integrate_positions, linear_drag,
                           quadratic_drag, springs)
from physbench.engine.forces import GyroscopicTorque, Gravity, LinearDrag, QuadraticDrag, Springs
from physbench.engine.integrate import EnergyConservingRotation, ImplicitGyroscopic, IntegratePositions, IntegrateVelocities
from physbench.engine import solver as _S
from physbench.engine.fused.borrow import Borrowed, borrow
from physbench.engine.pack import Pack
from physbench.engine.state import _commit_packed, record_packed
from physbench.engine.fused.steady import _NO_TURN, _no_records, FREE_NAME, NAME, NONE, free_loop, steady_loop
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
    # here: gyro_items' is empty, engine/steady_gyro.py)
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
    pos, quat, vel, angvel = borrow((pos, quat, vel, angvel))  # (engine/borrow.py)
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
        #: step's (steady_gyro.gyro_items; no explicit torque there: the
        #: force model has it)
        self.gy = gyro_items((), gyro)
        #: the stages the call runs: each counts its calls (its seconds are
        #: the call's, ``flight_step``)
        self.names = tuple(s.name for s in forces) + tuple(s.name for s in (gyro, fly) if s is not None) + (
            "integrate_positions",)
        self._k = self._k_ctx = None
        #: the packs handed to the loop, borrowed (engine/borrow.py)
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
        rec_on, blocks = _blocks(rec, model.n)
        b = self.borrowed.of
        state.t = flight_loop(n, model.substeps, b(ctx.kept(state)), b(self._pack(ctx)), float(h), float(state.t),
                              rec_on, *blocks)
        state.steps += n
        k = n * model.substeps
        for name in self.names:
            profile.charge(name, k, 0.0)
        profile.charge(FLIGHT_NAME, k, time.perf_counter() - t0)


def _blocks(rec, nb: int) -> tuple:
    """(record?, the four blocks) for the loops: ``rec`` when its arrays
    are float64 C-contiguous (what the loops are compiled for), else
    empty blocks (and the caller records)."""
    if rec is not None and all(a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable
                               for a in rec):
        return True, tuple(rec)
    return False, _no_records(nb)


def blocks_usable(rec) -> bool:
    """Whether the loops can write the record blocks ``rec`` themselves."""
    return _blocks(rec, 0)[0]


def record_blocks(n: int, nb: int) -> tuple:
    """Record blocks for ``n`` steps of ``nb`` bodies (pos, quat, vel,
    angvel), NaN-filled."""
    return (np.full((n, nb, 3), np.nan), np.full((n, nb, 4), np.nan), np.full((n, nb, 3), np.nan),
            np.full((n, nb, 3), np.nan))


def fused_block(model, state, ctx, plan, profile, n: int, rec):
    """Up to ``n`` steps of a contact scene from ``state`` in one compiled
    loop (module doc) when the step loop would try the fused call first:
    returns (steps done, the try of the next step or None).  The try is a
    callable ``(model, state, ctx) -> status`` that settles it, for
    :func:`engine.pipeline._substep`."""
    fused = plan.fused
    if fused is None or model.substeps != 1 or fused.wait:
        return 0, None
    solve = fused.solve
    steady = solve._fast is not None
    if not steady and fused.free_wait:
        return 0, None
    t0 = time.perf_counter()
    h = float(model.h)
    # the context as pipeline._substep leaves it for its first try
    ctx.missed_skip.clear()
    ctx.warm0 = old = state.warm
    ctx.event_mode = (EventMode.EVENT if plan.impact is not None and plan.max_events > 0
                      else EventMode.SPECULATIVE)
    ctx.reset(state, h)
    ctx.stop_allowed = plan.stops
    rec_on, blocks = _blocks(rec, model.n)
    turn = fused.__dict__.get("_turn")
    if turn is None:  # (the rotation split's limit as one Pack, made once)
        turn = fused._turn = Pack(_NO_TURN if plan.turn is None else (True, float(plan.turn[0]),
                                                                       np.ascontiguousarray(plan.turn[1], np.int64),
                                                                       np.ascontiguousarray(plan.turn[2], np.int64)))
    if not steady:
        return _free_block(model, state, ctx, fused, profile, n, h, turn, rec_on, blocks, t0)
    a = fused.steady_args(model, state, ctx, h)
    if a is None:
        return 0, None
    sp, flags0, out1, store_on, c = a
    if not store_on:
        return 0, None
    # the pool's rotation: step k stores into outs[k % 2] (WarmPool.slot)
    pool = solve._warm
    size = (c.m, int(solve._fast[1].uniq_codes.size))
    out2 = pool.slot(size, out1, out1)
    if pool.slot(size, out2, out2) is not out1:
        n = min(n, 2)
    outs = (out1, out2)
    flags1 = fused.flags(ctx, True, bool(solve.warm), True)
    band_check = bool(solve.direct and c.m > _S.DIRECT_MAX_ROWS)
    kb, kf, kbr, kcol, ks = fused.packs(model, state, ctx)
    kc, kx, kt, kw, ko, kq1, kk, key, idx = sp
    kall = fused.kall.of((kb, kf, kbr, kcol, kc, kx, kt, kw, kk, key, idx, ks))
    b = fused.borrowed.of
    r = steady_loop(n, kall, ko, kq1, b(out2.kept), b(turn), h, flags0, flags1, band_check, int(solve._band),
                    float(state.t), rec_on, *blocks)
    done, t, solved, sw_sum, sw_last, res_last, free_last, pend = r[:8]
    raw = r[7:]
    if done:
        fused.backoff = 0
        state.t = t
        state.steps += done
        if solved:
            last = done - 2 if free_last else done - 1
            fused.finish_solve(model, state, ctx, outs[last % 2], True, int(sw_last), float(res_last))
            if solved > 1:
                profile.count("contact_rows", c.m * (solved - 1))
                profile.count("solver_sweeps", int(sw_sum))
            ctx.contacts = c
        ctx.warm0 = old if done == 1 else outs[(done - 2) % 2]
        if free_last:
            fused._no_contact(state, ctx)
            solve._fast = None
    calls = done + (pend != NONE)
    if calls:
        profile.charge(NAME, calls, time.perf_counter() - t0)
    if pend == NONE:
        return done, None
    out_p = outs[done % 2]

    def tried(model, state, ctx):
        return fused.settle(model, state, ctx, raw, out_p, True, c)

    return done, tried


def _free_block(model, state, ctx, fused, profile, n, h, turn, rec_on, blocks, t0):
    """:func:`fused_block` of the contact-free call (:func:`free_loop`)."""
    kb, kf, kbr, kcol, ks = fused.packs(model, state, ctx)
    done, t, pend, nbb, npl, nsb = free_loop(n, fused.kfree.of((kb, kf, kbr, kcol, ks)), h,
                                             fused.flags(ctx, False, False, False), fused.borrowed.of(turn),
                                             float(state.t), rec_on, *blocks)
    if done:
        fused.free_backoff = 0
        state.t = t
        state.steps += done
        fused._no_contact(state, ctx)
    calls = done + (pend != NONE)
    if calls:
        profile.charge(FREE_NAME, calls, time.perf_counter() - t0)
    if pend == NONE:
        return done, None
    raw = (pend, nbb, npl, nsb, 0, 0, 0.0)

    def tried(model, state, ctx):
        return fused.settle_free(model, state, ctx, raw)

    return done, tried
