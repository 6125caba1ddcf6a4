"""Steps as compiled calls: a scene without contact, and several steps in one call.

:class:`FlightStep` -- a scene with no contact stage (the gyroscopic and
force scenes: force stages, [implicit gyroscopic], the free flight,
[energy-conserving rotation], the position update) runs each (sub)step as
ONE compiled call, :func:`flight_kernel`: the flight part every fused step
shares (engine/fused/part.py), the position update and the commit, the
same kernels with the same arguments in the same order as the stages call
them one by one (the same bits: tests/test_engine_loop.py).  It covers
every force stage of the table (engine.forces.FORCES), every integrator
and both gyroscopic stages (implicit, energy-conserving); the profile
times it as the stage ``flight_step``.

Several steps in one call: :meth:`FlightStep.advance` runs ``n`` steps
in :func:`flight_loop`, recording each step's state into the caller's
(n, n_bodies, 3|4) blocks (the door: engine/fused/__init__.py).
"""

from __future__ import annotations

import time

from numba import njit

from physbench.engine.control import EventMode
from physbench.engine.flight import integrate_positions
from physbench.engine.forces import FORCES
from physbench.engine.integrate import EnergyConservingRotation, ImplicitGyroscopic, IntegratePositions, IntegrateVelocities
from physbench.engine.fused.borrow import Borrowed, borrow
from physbench.engine.fused.gyro import gyro_items
from physbench.engine.fused.part import flight_part
from physbench.engine.fused.steady import NONE, blocks
from physbench.engine.pack import Pack
from physbench.engine.state import _commit_packed, record_packed

#: the profile's name of a no-contact scene's step (FlightStep)
FLIGHT_NAME = "flight_step"


@njit(cache=True)
def flight_kernel(kb, kf, kg, h):
    """One (sub)step of length ``h`` of a scene without contact: the flight
    part (engine/fused/part.py: begin, the force stages, [implicit
    gyroscopic], the free flight, [energy-conserving rotation]), the
    position update, the commit (module doc).  ``kb`` the context's
    begin/commit pack (engine.state.Context.kept), ``kf`` the free-flight
    stage's (engine.integrate.IntegrateVelocities.pack), ``kg`` the
    gyroscopic stage's (a Pack of its engine.gyroscopic.Gyro)."""
    b, f = kb.items, kf.items
    flight_part(b, f, kg.items, h)
    integrate_positions(b.x1, b.q1, f.V, f.W, f.v_free, f.w_free, f.vp, f.wp, h, f.ig.lever)
    _commit_packed(kb)


@njit(cache=True)
def flight_loop(n, substeps, kb, kf, kg, h, t, rec_on, pos, quat, vel, angvel):
    """``n`` steps of ``substeps`` (sub)steps of :func:`flight_kernel`,
    each step's state into row k of the blocks when ``rec_on``; returns the
    time after them (``state.t`` plus h per (sub)step, added one by one as
    the step loop does)."""
    pos, quat, vel, angvel = borrow((pos, quat, vel, angvel))  # (engine/fused/borrow.py)
    for k in range(n):
        for s in range(substeps):
            flight_kernel(kb, kf, kg, h)
            t += h
        record_packed(kb, k, rec_on, pos, quat, vel, angvel)
    return t


class FlightStep:
    """The plan's step of a scene without contact (module doc) over the
    pipeline's stage objects."""

    def __init__(self, model, forces, fly, gyro):
        self.fly = fly
        self.gyro = gyro
        #: the gyroscopic stage's arrays and kept work (gyro.gyro_items)
        self.kg = Pack(gyro_items(gyro))
        #: the stages the call runs: each counts its calls (its seconds are
        #: the call's, ``flight_step``)
        self.names = tuple(s.name for s in forces) + tuple(s.name for s in (gyro, fly) if s is not None) + (
            "integrate_positions",)
        #: the packs handed to the loop, borrowed (engine/fused/borrow.py)
        self.borrowed = Borrowed()

    @staticmethod
    def build(model, stages) -> "FlightStep | None":
        """The fused step for ``stages`` when they are force stages,
        [implicit gyroscopic], the free flight, [energy-conserving
        rotation] and the position update, else None."""
        forces = [s for s in stages if s.family == "forces"]
        if any(type(s) not in FORCES for s in forces):
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

    def call(self) -> str:
        """The compiled call :meth:`advance` makes (its profile name)."""
        return FLIGHT_NAME

    def prime(self, model, state, ctx) -> None:
        """At build (pipeline.prepare): the packs the first call hands to
        the loop and their borrowed twins, which a fresh engine's first
        call would make (the same objects)."""
        b = self.borrowed.of
        b(ctx.kept(state))
        b(self.fly.pack(ctx))
        b(self.kg)

    def kept(self) -> None:
        """No steady solve (the door's Backoff): a flight step never fails."""
        return None

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
        state.t = flight_loop(n, model.substeps, b(ctx.kept(state)), b(self.fly.pack(ctx)), b(self.kg), float(h),
                              float(state.t), rec_on, *blocks_)
        state.steps += n
        k = n * model.substeps
        for name in self.names:
            profile.charge(name, k, 0.0)
        profile.charge(FLIGHT_NAME, k, time.perf_counter() - t0)
