"""Integration stages.

``IntegrateVelocities`` advances the *free flight* (smooth forces only) over
the step h with the chosen integrator and leaves the candidate end state in
the context (``x1``, ``q1``, ``v``, ``w``); the state itself still holds the
start of the step, where collision detection runs.  The contact solver then
changes the end velocities, and ``IntegratePositions`` applies the position
effect of those changes.

The rigid-body ODE, world frame::

    x' = v                 q' = 1/2 (0, w) (x) q
    v' = F / m             w' = I_w^-1 (T - [w x I_w w])      I_w = R I R^T

where the bracketed gyroscopic term is present only with the 'gyroscopic'
effect, and only inside the ODE for ``gyroscopic = explicit``.  The other two
gyroscopic modes are separate stages:

* ``implicit`` (Catto, GDC 2015; runs before the integrator): one Newton iteration on the body-frame
  backward-Euler equation I (w2 - w1) + h w2 x I w2 = 0.  Stable, loses
  energy.
* ``energy_conserving`` (runs after the integrator, replacing its
  rotation of anisotropic bodies): the free rigid-body rotation by the implicit-midpoint
  Lie-Poisson scheme in body-frame angular momentum, L1 = L0 + h Lm x I^-1 Lm
  with Lm = (L0 + L1) / 2, and R1 = R0 cay(h [I^-1 Lm]x).  The midpoint rule
  conserves every quadratic invariant, so |L| and the kinetic energy are
  exact (to the fixed-point tolerance); the Cayley rotation makes
  R1 L1 = R0 L0, so the world angular momentum is exact too.  Three
  substeps in Yoshida's triple-jump composition make it fourth order.
  Torques enter as two half kicks of the step's mean torque on the world
  angular momentum around the free rotation (Strang splitting).

Integrators (setting ``integrator``): explicit_euler (order 1),
semi_implicit_euler (1; velocity first, then x1 = x0 + h v1 and the exact
rotation exp(h w1)), midpoint (2), heun (2), rk4 (4), velocity_verlet (2;
x1 = x0 + h v0 + h^2/2 a0, rotation exp(h (w0 + h/2 alpha0)), velocity by
the trapezoid with a predictor for velocity-dependent forces).  All are exact
for constant forces except the two Euler methods.

Quaternions are renormalised after every step.

Every stage here is one compiled call (engine/flight.py: loops over
bodies, no BLAS).
"""

from __future__ import annotations

import numpy as np

from physbench.engine.flight import METHOD, WORK_SLABS, Flight, Integrator, Method, fly_packed, integrate_positions
from physbench.engine.gyroscopic import (ENERGY, IMPLICIT, YOSHIDA, YOSHIDA_MAX, Gyro, energy_rotation_packed,
                                         energy_work, implicit_gyroscopic, implicit_work, midpoint_rotation)
from physbench.engine.forces import force_model
from physbench.engine.pack import Pack
from physbench.engine.profile import Stage
from physbench.engine.settings import INTEGRATORS  # noqa: F401  (the names; engine/settings.py holds them)

ORDERS = {"explicit_euler": 1, "semi_implicit_euler": 1, "midpoint": 2, "heun": 2, "rk4": 4, "velocity_verlet": 2}


class IntegrateVelocities(Stage):
    """Free flight over ctx.h with the chosen integrator (see module doc).

    Reads the forces of the start state from ctx.F/ctx.T (the pipeline's force
    stages ran just before) and re-evaluates ``forces`` at intermediate
    states (not when they are all state-independent, ``constant``: gravity
    alone gives the same forces everywhere).  One compiled call
    (:func:`engine.flight.free_flight`, the force stages' own kernels at the
    intermediate states, which the profile therefore counts under this
    stage).  Writes ctx.x1, ctx.q1, ctx.v[:n], ctx.w[:n] (end state),
    ctx.v_free/w_free (copies of the end velocities) and ctx.u_lin/u_ang (the
    step's mean velocities, used by the contact solver's speculative rows).
    The call is engine.flight.fly, the fused steps' too (:meth:`pack`).
    """

    name = "integrate_velocities"
    family = "integrate"

    def __init__(self, model, forces: tuple[Stage, ...]):
        n = model.n
        self.forces = forces
        self.method = model.setting("integrator")
        self.code = METHOD[self.method]
        self.inv_m = np.array(model.inv_mass[:n], float)
        self.inv_I = np.array(model.inv_inertia_body[:n], float)
        self.c = float(model.contact_lever)
        # angular accelerations only when a force stage makes torques
        self.torque = any(getattr(s, "torque", True) for s in forces)
        # forces that do not depend on the state at all (gravity): every
        # evaluation at an intermediate state equals the start's, so the
        # integrator reuses it instead of evaluating the forces again (the
        # same numbers: F = 0 + m g and a = F / m either way)
        self.constant = bool(forces) and all(getattr(s, "constant", False) for s in forces)
        #: the compiled force model evaluated at the intermediate states
        self.fm = force_model(model, forces)
        #: the flight's law (engine.flight.Integrator)
        self.ig = Integrator(method=Method(self.code), has_forces=bool(forces), constant=self.constant,
                             torque=self.torque, fm=self.fm, inv_m=self.inv_m, inv_I=self.inv_I, lever=self.c)
        self._w0 = np.zeros((n, 3))
        self._work = np.zeros((WORK_SLABS, n, 3))
        self._work_q = np.zeros((2, n, 4))
        self._pack = self._pack_ctx = None

    def pack(self, ctx) -> Pack:
        """The stage's arrays and the context's views over its first n rows
        as one Pack of an engine.flight.Flight, kept per context (the
        staged call's and the fused steps')."""
        if self._pack_ctx is not ctx:
            n = ctx.x1.shape[0]
            self._pack = Pack(Flight(ig=self.ig, V=ctx.v[:n], W=ctx.w[:n], v_free=ctx.v_free, w_free=ctx.w_free,
                                     w0=self._w0, T_mean=ctx.T_mean, u_lin=ctx.u_lin, u_ang=ctx.u_ang,
                                     work=self._work, work_q=self._work_q, vp=ctx.vp[:n], wp=ctx.wp[:n]))
            self._pack_ctx = ctx
        return self._pack

    def __call__(self, model, state, ctx) -> None:
        # (w may carry the implicit gyroscopic update: the flight starts
        # from it, the mean velocity from the state's)
        fly_packed(ctx.kept(state), self.pack(ctx), ctx.h)


class ImplicitGyroscopic(Stage):
    """Catto's implicit gyroscopic update (GDC 2015), body frame:
    solve I (w2 - w1) + h w2 x I w2 = 0 by one Newton iteration from w1:
    J = I + h ([w1]x I - [I w1]x), w2 = w1 - J^-1 (h w1 x I w1).
    Updates the working angular velocity ctx.w before the integrator."""

    name = "gyroscopic"
    family = "integrate"

    def __init__(self, model):
        self.idx = np.flatnonzero(~model.isotropic).astype(np.int64)
        self.I = np.array(model.inertia_body[self.idx], float)
        #: the kernel's work arrays (Jm, fw), kept: nothing allocated a step
        self.work = implicit_work(self.idx.size)
        z3 = np.zeros((0, 3))
        #: the stage's arrays as the fused steps read them
        #: (engine.gyroscopic.Gyro)
        self.gy = Gyro(IMPLICIT, self.idx, self.I, z3, z3, YOSHIDA, float(YOSHIDA_MAX), *energy_work(0), *self.work)

    def __call__(self, model, state, ctx) -> None:
        if self.idx.size:
            implicit_gyroscopic(self.idx, self.I, ctx.R0, ctx.w, ctx.h, *self.work)


def euler_coefficients(I: np.ndarray) -> np.ndarray:
    """(k, 3) coefficients E of the torque-free Euler equations in body-frame
    angular momentum: L x (L / I) = E * (L1 L2, L2 L0, L0 L1) with
    E = (1/I2 - 1/I1, 1/I0 - 1/I2, 1/I1 - 1/I0), for principal moments
    ``I`` (k, 3) kg m^2."""
    inv = 1.0 / I
    return np.stack([inv[:, 2] - inv[:, 1], inv[:, 0] - inv[:, 2], inv[:, 1] - inv[:, 0]], axis=1)




def free_rotation_midpoint(Lb: np.ndarray, q: np.ndarray, I: np.ndarray, h: float,
                           tol: float = 1e-15, max_iter: int = 100,
                           E: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One implicit-midpoint Lie-Poisson step of the torque-free rigid body.

    ``Lb`` (k, 3) body-frame angular momentum, ``q`` (k, 4) orientation,
    ``I`` (k, 3) principal moments, step ``h`` (s); ``E`` (k, 3) the
    bodies' :func:`euler_coefficients` (computed from I if not given).
    Solves L1 = L0 + h Lm x (Lm / I), Lm = (L0 + L1)/2, for the midpoint:
    Lm = L0 + h/2 f(Lm), f(L) = E * (L1 L2, L2 L0, L0 L1) (Euler's
    equations in principal axes: four array operations per evaluation
    instead of a cross product's twelve), by fixed-point iteration
    (contraction ~ h |w| / 2) from the explicit predictor
    Lm = L0 + h/2 f(L0).  Then L1 = 2 Lm - L0 and
    q1 = q0 (x) normalize(1, h wm / 2), the quaternion of the Cayley
    rotation cay(h [wm]x), wm = Lm / I.  Returns (L1, q1)."""
    if E is None:
        E = euler_coefficients(I)
    L1 = np.array(Lb, float)
    q1 = np.array(q, float)
    midpoint_rotation(L1, q1, np.array(I, float), np.array(E, float), h, tol, max_iter)
    return L1, q1


class EnergyConservingRotation(Stage):
    """Energy- and momentum-conserving rotation (see module doc), run after
    the integrator: it replaces the integrator's rotation of the anisotropic
    bodies by half a kick of the step's mean torque (ctx.T_mean, weighted
    like the integrator's own stages), the fourth-order composed midpoint
    Lie-Poisson free rotation, and the other half kick.  Isotropic bodies
    (spheres, cubes) have no gyroscopic term and keep the integrator's
    (exact, for constant torque-free w) rotation."""

    name = "gyroscopic"
    family = "integrate"

    def __init__(self, model):
        self.idx = np.flatnonzero(~model.isotropic).astype(np.int64)
        self.I = np.array(model.inertia_body[self.idx], float)
        self.inv_I = 1.0 / self.I
        self.E = euler_coefficients(self.I)
        self.c = float(model.contact_lever)
        #: the kernel's arrays and kept work arrays (engine.gyroscopic.Gyro:
        #: nothing allocated a step), the staged call's and the fused steps'
        self.gy = Gyro(ENERGY, self.idx, self.I, self.inv_I, self.E, YOSHIDA, float(YOSHIDA_MAX),
                       *energy_work(self.idx.size), *implicit_work(0))
        self._kg = Pack(self.gy)

    def __call__(self, model, state, ctx) -> None:
        # The midpoint fixed point contracts like |w| h: at game steps and
        # fast spins (150 rad/s at dt 1/30: |w| h = 5) it would diverge.  The
        # free rotation is therefore split into m equal parts with
        # |w| h |g|max / m <= 0.5; each part conserves E and L exactly, so
        # splitting only adds accuracy (m = 1 for ordinary spins).
        if self.idx.size:
            energy_rotation_packed(self._kg, ctx.R0, ctx.T_mean, state.w, state.q, ctx.h, self.c, ctx.q1, ctx.w,
                                   ctx.w_free, ctx.u_ang)


class IntegratePositions(Stage):
    """Apply the contact solver's velocity changes to the candidate end pose.

    dv = v1 - v_free (and dw) are the contact impulses per unit mass.  For the
    velocity-first integrator (semi-implicit Euler) they act from the start
    of the step, x1 += h dv; for the others a contact impulse is a constant
    force over the step, whose displacement is h/2 dv (exact for constant
    forces, which keeps resting and sliding contacts free of drift).  The
    split-impulse pseudo velocities (vp, wp) move positions only:
    x1 += h vp.  Orientation: q1 <- exp(c h dw + h wp) (x) q1.
    """

    name = "integrate_positions"
    family = "integrate"

    def __init__(self, model):
        self.c = model.contact_lever

    def __call__(self, model, state, ctx) -> None:
        n = model.n
        integrate_positions(ctx.x1, ctx.q1, ctx.v[:n], ctx.w[:n], ctx.v_free, ctx.w_free, ctx.vp[:n], ctx.wp[:n],
                            ctx.h, self.c)
