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
"""

from __future__ import annotations

import math

import numpy as np

from engine.mathutil import (
    cross,
    apply_world_inertia,
    normalize_quat,
    quat_deriv,
    quat_from_rotvec,
    quat_mul,
    quat_to_matrix,
    rotate_world,
)
from engine.contact.linalg import solve_batch
from engine.profile import Stage

INTEGRATORS = ("explicit_euler", "semi_implicit_euler", "midpoint", "heun", "rk4", "velocity_verlet")
ORDERS = {"explicit_euler": 1, "semi_implicit_euler": 1, "midpoint": 2, "heun": 2, "rk4": 4, "velocity_verlet": 2}


class IntegrateVelocities(Stage):
    """Free flight over ctx.h with the chosen integrator (see module doc).

    Reads the forces of the start state from ctx.F/ctx.T (the pipeline's force
    stages ran just before) and re-evaluates ``forces`` at intermediate
    states (not when they are all state-independent, ``constant``: gravity
    alone gives the same forces everywhere).  Writes ctx.x1, ctx.q1, ctx.v[:n], ctx.w[:n] (end state),
    ctx.v_free/w_free (copies of the end velocities) and ctx.u_lin/u_ang (the
    step's mean velocities, used by the contact solver's speculative rows).
    """

    name = "integrate_velocities"
    family = "integrate"

    def __init__(self, model, forces: tuple[Stage, ...]):
        self.forces = forces
        self.method = model.setting("integrator")
        self.inv_m = model.inv_mass[: model.n, None].copy()
        self.inv_I = model.inv_inertia_body[: model.n].copy()
        self.c = model.contact_lever
        # skip rotation matrices / angular accelerations when no force stage needs them
        self.torque = any(getattr(s, "torque", True) for s in forces)
        self.pose = any(getattr(s, "pose", True) for s in forces) or self.torque
        # forces that do not depend on the state at all (gravity): every
        # evaluation at an intermediate state equals the start's, so the
        # integrator reuses it instead of re-running the force stages (the
        # same numbers: F = 0 + m g and a = F / m either way)
        self.constant = bool(forces) and all(getattr(s, "constant", False) for s in forces)
        self._zero = np.zeros((model.n, 3))

    # ---- right-hand side -------------------------------------------------
    def _accel(self, model, state, ctx, x, q, v, w):
        """Accelerations (a, alpha), (n, 3) each, at the state (x, q, v, w)."""
        if self.constant:
            self._T.append(self._T[0])
            return self._acc0
        R = quat_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True)) if self.pose else None
        ctx.ex, ctx.eq, ctx.ev, ctx.ew, ctx.eR = x, q, v, w, R
        ctx.F[:] = 0.0
        ctx.T[:] = 0.0
        for s in self.forces:
            ctx.profile.run(s, model, state, ctx)
        self._T.append(ctx.T.copy())
        return self._from_forces(ctx, R)

    def _from_forces(self, ctx, R):
        a = ctx.F * self.inv_m
        if not self.torque:
            return a, self._zero
        tb = np.einsum("kji,kj->ki", R, ctx.T)
        alpha = np.einsum("kij,kj->ki", R, tb * self.inv_I)
        return a, alpha

    def __call__(self, model, state, ctx) -> None:
        n = model.n
        h = ctx.h
        x0, q0, v0, w0 = state.x, state.q, state.v, ctx.w[:n].copy()  # w may carry the implicit gyroscopic update
        m = self.method
        if not self.forces:
            # no forces at all: every integrator's exact answer is uniform
            # motion and rotation at constant w (no gyroscopic term in the ODE)
            np.multiply(v0, h, out=ctx.x1)
            ctx.x1 += x0
            ctx.q1[:] = rotate_world(q0, h * w0)
            ctx.v[:n] = v0
            ctx.w[:n] = w0
            ctx.T_mean[:] = 0.0
            self._finish(model, state, ctx, x0)
            return
        a0, al0 = self._from_forces(ctx, ctx.R0)
        self._T = [ctx.T.copy()]
        self._acc0 = (a0, al0)
        f = lambda x, q, v, w: self._accel(model, state, ctx, x, q, v, w)  # noqa: E731
        if m == "explicit_euler":
            x1 = x0 + h * v0
            q1 = q0 + h * quat_deriv(w0, q0)
            v1 = v0 + h * a0
            w1 = w0 + h * al0
        elif m == "semi_implicit_euler":
            v1 = v0 + h * a0
            w1 = w0 + h * al0
            x1 = x0 + h * v1
            q1 = rotate_world(q0, h * w1)
        elif m == "midpoint":
            xm, qm = x0 + 0.5 * h * v0, q0 + 0.5 * h * quat_deriv(w0, q0)
            vm, wm = v0 + 0.5 * h * a0, w0 + 0.5 * h * al0
            am, alm = f(xm, qm, vm, wm)
            x1 = x0 + h * vm
            q1 = q0 + h * quat_deriv(wm, qm)
            v1 = v0 + h * am
            w1 = w0 + h * alm
        elif m == "heun":
            xp, qp = x0 + h * v0, q0 + h * quat_deriv(w0, q0)
            vp, wp = v0 + h * a0, w0 + h * al0
            ap, alp = f(xp, qp, vp, wp)
            x1 = x0 + 0.5 * h * (v0 + vp)
            q1 = q0 + 0.5 * h * (quat_deriv(w0, q0) + quat_deriv(wp, qp))
            v1 = v0 + 0.5 * h * (a0 + ap)
            w1 = w0 + 0.5 * h * (al0 + alp)
        elif m == "rk4":
            # the state and slopes stacked as (n, 13) rows [x | q | v | w]:
            # the same element-wise arithmetic as per array, in one call each
            Y0 = np.empty((n, 13))
            Y0[:, 0:3], Y0[:, 3:7], Y0[:, 7:10], Y0[:, 10:13] = x0, q0, v0, w0

            def slope(Y, a, al):
                K = np.empty((n, 13))
                K[:, 0:3] = Y[:, 7:10]
                K[:, 3:7] = quat_deriv(Y[:, 10:13], Y[:, 3:7])
                K[:, 7:10] = a
                K[:, 10:13] = al
                return K

            def parts(Y):
                return Y[:, 0:3], Y[:, 3:7], Y[:, 7:10], Y[:, 10:13]

            K1 = slope(Y0, a0, al0)
            Y2 = Y0 + 0.5 * h * K1
            K2 = slope(Y2, *f(*parts(Y2)))
            Y3 = Y0 + 0.5 * h * K2
            K3 = slope(Y3, *f(*parts(Y3)))
            Y4 = Y0 + h * K3
            K4 = slope(Y4, *f(*parts(Y4)))
            x1, q1, v1, w1 = parts(Y0 + h / 6.0 * (K1 + 2 * K2 + 2 * K3 + K4))
        elif m == "velocity_verlet":
            x1 = x0 + h * v0 + 0.5 * h * h * a0
            q1 = rotate_world(q0, h * (w0 + 0.5 * h * al0))
            a1, al1 = f(x1, q1, v0 + h * a0, w0 + h * al0)
            v1 = v0 + 0.5 * h * (a0 + a1)
            w1 = w0 + 0.5 * h * (al0 + al1)
        else:  # pragma: no cover - settings are validated
            raise ValueError(m)
        ctx.x1[:] = x1
        ctx.q1[:] = q1
        normalize_quat(ctx.q1)
        ctx.v[:n] = v1
        ctx.w[:n] = w1
        # the step's mean torque, with the method's own weights (used by the
        # energy-conserving rotation, so that spin and orbital angular
        # momentum change consistently)
        T = self._T
        ctx.T_mean[:] = {"explicit_euler": lambda: T[0], "semi_implicit_euler": lambda: T[0],
                         "midpoint": lambda: T[1], "heun": lambda: 0.5 * (T[0] + T[1]),
                         "rk4": lambda: (T[0] + 2 * T[1] + 2 * T[2] + T[3]) / 6.0,
                         "velocity_verlet": lambda: 0.5 * (T[0] + T[1])}[m]()
        self._finish(model, state, ctx, x0)

    def _finish(self, model, state, ctx, x0):
        n = model.n
        h = ctx.h
        ctx.v_free[:] = ctx.v[:n]
        ctx.w_free[:] = ctx.w[:n]
        np.subtract(ctx.x1, x0, out=ctx.u_lin)
        ctx.u_lin /= h
        # mean angular velocity over the step, consistent with the contact lever
        ctx.u_ang[:] = (1.0 - self.c) * state.w + self.c * ctx.w[:n]
        # restore the force evaluation point to the start state for later readers
        ctx.ex, ctx.eq, ctx.ev, ctx.ew, ctx.eR = state.x, state.q, state.v, state.w, ctx.R0


class ImplicitGyroscopic(Stage):
    """Catto's implicit gyroscopic update (GDC 2015), body frame:
    solve I (w2 - w1) + h w2 x I w2 = 0 by one Newton iteration from w1:
    J = I + h ([w1]x I - [I w1]x), w2 = w1 - J^-1 (h w1 x I w1).
    Updates the working angular velocity ctx.w before the integrator."""

    name = "gyroscopic"
    family = "integrate"

    def __init__(self, model):
        self.idx = np.flatnonzero(~model.isotropic)
        self.I = model.inertia_body[self.idx]
        self.Imat = np.zeros((self.idx.size, 3, 3))
        self.Imat[:, [0, 1, 2], [0, 1, 2]] = self.I

    @staticmethod
    def _skew(v):
        S = np.zeros(v.shape[:-1] + (3, 3))
        S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
        S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
        S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
        return S

    def __call__(self, model, state, ctx) -> None:
        k = self.idx
        if k.size == 0:
            return
        h = ctx.h
        R = ctx.R0[k]
        wb = np.einsum("kji,kj->ki", R, ctx.w[k])
        Iw = self.I * wb
        f = h * cross(wb, Iw)
        J = self.Imat + h * (np.einsum("kij,kjl->kil", self._skew(wb), self.Imat) - self._skew(Iw))
        wb2 = wb - solve_batch(J, f)
        ctx.w[k] = np.einsum("kij,kj->ki", R, wb2)


# Yoshida's fourth-order triple jump for a symmetric second-order method
_CBRT2 = 2.0 ** (1.0 / 3.0)
YOSHIDA = (1.0 / (2.0 - _CBRT2), -_CBRT2 / (2.0 - _CBRT2), 1.0 / (2.0 - _CBRT2))
YOSHIDA_MAX = max(abs(g) for g in YOSHIDA)


def euler_coefficients(I: np.ndarray) -> np.ndarray:
    """(k, 3) coefficients E of the torque-free Euler equations in body-frame
    angular momentum: L x (L / I) = E * (L1 L2, L2 L0, L0 L1) with
    E = (1/I2 - 1/I1, 1/I0 - 1/I2, 1/I1 - 1/I0), for principal moments
    ``I`` (k, 3) kg m^2."""
    inv = 1.0 / I
    return np.stack([inv[:, 2] - inv[:, 1], inv[:, 0] - inv[:, 2], inv[:, 1] - inv[:, 0]], axis=1)


_NEXT = np.array([1, 2, 0])
_PREV = np.array([2, 0, 1])


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
    hE = 0.5 * h * E
    Lm = Lb + hE * Lb[:, _NEXT] * Lb[:, _PREV]
    scale = np.abs(Lb).max() + 1e-300
    for _ in range(max_iter):
        L_new = Lb + hE * Lm[:, _NEXT] * Lm[:, _PREV]
        diff = np.abs(L_new - Lm).max()
        Lm = L_new
        if diff <= tol * scale:
            break
    qc = np.empty(q.shape)
    qc[:, 0] = 1.0
    qc[:, 1:] = (0.5 * h) * (Lm / I)
    qc /= np.sqrt(np.einsum("ki,ki->k", qc, qc))[:, None]
    return 2.0 * Lm - Lb, quat_mul(q, qc)


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
        self.idx = np.flatnonzero(~model.isotropic)
        self.I = model.inertia_body[self.idx]
        self.inv_I = 1.0 / self.I
        self.E = euler_coefficients(self.I)
        self.c = model.contact_lever

    def __call__(self, model, state, ctx) -> None:
        k = self.idx
        if k.size == 0:
            return
        h = ctx.h
        R0 = ctx.R0[k]
        T = ctx.T_mean[k]
        Lw = apply_world_inertia(R0, self.I, state.w[k]) + 0.5 * h * T
        Lb = np.einsum("kji,kj->ki", R0, Lw)
        q = state.q[k]
        # The midpoint fixed point contracts like |w| h: at game steps and
        # fast spins (150 rad/s at dt 1/30: |w| h = 5) it would diverge.  The
        # free rotation is therefore split into m equal parts with
        # |w| h |g|max / m <= 0.5; each part conserves E and L exactly, so
        # splitting only adds accuracy (m = 1 for ordinary spins).
        wmax = float(np.sqrt(np.max(np.einsum("ki,ki->k", Lb * self.inv_I, Lb * self.inv_I))))
        m = max(1, math.ceil(wmax * h * YOSHIDA_MAX / 0.5))
        hs = h / m
        for _ in range(m):
            for g in YOSHIDA:
                Lb, q = free_rotation_midpoint(Lb, q, self.I, g * hs, E=self.E)
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        R1 = quat_to_matrix(q)
        Lw1 = np.einsum("kij,kj->ki", R1, Lb) + 0.5 * h * T
        wb1 = np.einsum("kji,kj->ki", R1, Lw1) * self.inv_I
        w1 = np.einsum("kij,kj->ki", R1, wb1)
        ctx.q1[k] = q
        ctx.w[k] = w1
        ctx.w_free[k] = w1
        ctx.u_ang[k] = (1.0 - self.c) * state.w[k] + self.c * w1


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
        h = ctx.h
        ch = self.c * h
        dv = ctx.v[:n] - ctx.v_free
        dw = ctx.w[:n] - ctx.w_free
        ctx.x1 += ch * dv + h * ctx.vp[:n]
        phi = ch * dw + h * ctx.wp[:n]
        moved = np.flatnonzero(np.einsum("ki,ki->k", phi, phi) > 0.0)
        if moved.size:
            ctx.q1[moved] = rotate_world(ctx.q1[moved], phi[moved])
