"""The flight part of a fused step: what every fused step runs first, as
the stages run it one by one -- the start of the (mini-)step
(state.Context.begin), the force stages (engine.flight.apply_forces: the
one list of them, engine.forces.FORCES), the implicit gyroscopic stage,
the free flight (engine.flight.fly, the staged stage's own call), the
energy-conserving rotation.  The one description of that sequence: the
contact scene's steps (engine/fused/steady.py) and the no-contact scene's
(engine/fused/loop.py) both call :func:`flight_part`, so a force effect or
a gyroscopic stage is written once for both (the same bits as the staged
stages: tests/test_engine_force_table.py, tests/test_engine_loop.py,
tests/test_engine_steady_gyro.py).
"""

from __future__ import annotations

from numba import njit

from physbench.engine.flight import apply_forces, begin_step, fly
from physbench.engine.fused.gyro import after_flight, before_flight


@njit(cache=True, inline="always")
def flight_part(b, f, gy, h):
    """The flight part of a (mini-)step of length ``h`` s (module doc):
    ``b`` the context's begin/commit arrays (an engine.state.StepArrays),
    ``f`` the free-flight stage's (an engine.flight.Flight: its force
    model ``f.ig.fm`` evaluated at the start state), ``gy`` the gyroscopic
    stage's (an engine.gyroscopic.Gyro, empty without one).  Inlined into
    each fused entry (one compiled entry per fused step)."""
    # state.Context.begin
    begin_step(b.x, b.q, b.v, b.w, b.inv_I, b.x1, b.q1, b.V, b.W, b.F, b.T, b.vp, b.wp, b.R0, b.Iinv0)
    # the force stages at the start state (ctx.ex ... = state, ctx.eR = R0)
    apply_forces(f.ig.fm, b.x, b.R0, b.v, b.w, b.F, b.T)
    # integrate.ImplicitGyroscopic
    before_flight(gy, b.R0, b.W, h)
    # integrate.IntegrateVelocities
    fly(b, f, h)
    # integrate.EnergyConservingRotation
    after_flight(gy, b.R0, f.T_mean, b.w, b.q, h, f.ig.lever, b.q1, b.W, f.w_free, f.u_ang)
