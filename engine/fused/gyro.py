"""The gyroscopic stages inside the fused steady step (engine/fused/steady.py).

A contact scene with the 'gyroscopic' effect and a non-isotropic body
(a rolling cylinder, a spinning capsule, a log pile) has one of three
gyroscopic treatments (setting ``gyroscopic``, engine/pipeline.py):

* ``explicit`` -- the force stage :class:`engine.forces.GyroscopicTorque`
  after gravity (T -= w x I_w w at the start state; the integrator
  re-evaluates it at its intermediate states through the force model);
* ``implicit`` -- the stage :class:`engine.integrate.ImplicitGyroscopic`
  between the force stages and the free flight (Catto's update of the
  working angular velocity);
* ``energy_conserving`` (the default) -- the stage
  :class:`engine.integrate.EnergyConservingRotation` right after the free
  flight (writes q1, w, w_free, u_ang of the anisotropic bodies).

The fused call runs the same compiled kernels with the same arguments at
the same places of the step (:func:`before_flight` after gravity,
:func:`after_flight` after the free flight, both before the broad phase):
the same bits as the stages one by one (tests/test_engine_steady_gyro.py).
The plan's arrays for them are one tuple (:func:`gyro_items`), the third
item of the steady step's settings Pack, so the loops over steps
(engine/fused/steady.py) pass them on unchanged; a scene without contact's
flight step (engine/fused/loop.py, ``flight_kernel``) runs the same two calls
on its own tuple (without the explicit torque: its force model has it).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from physbench.engine.flight import gyroscopic_torque
from physbench.engine.forces import GyroscopicTorque, Gravity
from physbench.engine.gyroscopic import (YOSHIDA, YOSHIDA_MAX, energy_rotation_into, energy_work, implicit_gyroscopic,
                               implicit_work)
from physbench.engine.integrate import EnergyConservingRotation, ImplicitGyroscopic

#: the gyroscopic stage codes
NO_GYRO, IMPLICIT, ENERGY = 0, 1, 2

#: the force stages the fused step covers
FORCES = (Gravity, GyroscopicTorque)


def split_gyro(rest: list) -> tuple:
    """(the gyroscopic integration stage or None, the other stages) of the
    non-force stages ``rest`` in pipeline order: ImplicitGyroscopic only
    first (before IntegrateVelocities), EnergyConservingRotation only
    second (after it); anywhere else it stays in the list (and the fused
    step's stage check fails)."""
    if rest and type(rest[0]) is ImplicitGyroscopic:
        return rest[0], rest[1:]
    if len(rest) > 1 and type(rest[1]) is EnergyConservingRotation:
        return rest[1], rest[:1] + rest[2:]
    return None, rest


def gyro_items(forces, gyro) -> tuple:
    """The plan's gyroscopic arrays as the tuple :func:`before_flight` and
    :func:`after_flight` read: (stage code, explicit torque's bodies (t,)
    int64 and principal moments (t, 3) kg m^2, the gyroscopic stage's
    bodies (g,) int64, principal moments (g, 3) kg m^2, their inverses
    (g, 3) 1/(kg m^2), Euler coefficients (g, 3) 1/(kg m^2), Yoshida's
    largest coefficient, the energy-conserving rotation's kept work arrays
    (4, g, 3), (g, 4), (g, 3, 3), the implicit update's (g, 3, 3), (2, g, 3):
    no allocation a step); absent parts as empty arrays."""
    z3, zi = np.zeros((0, 3)), np.zeros(0, np.int64)
    t = next((s for s in forces if type(s) is GyroscopicTorque), None)
    t_idx = np.ascontiguousarray(t.idx, np.int64) if t is not None else zi
    t_I = np.ascontiguousarray(t.I, float) if t is not None else z3
    code = NO_GYRO if gyro is None else (IMPLICIT if type(gyro) is ImplicitGyroscopic else ENERGY)
    energy = code == ENERGY
    gidx = np.ascontiguousarray(gyro.idx, np.int64) if gyro is not None else zi
    gI = np.ascontiguousarray(gyro.I, float) if gyro is not None else z3
    ginv = np.ascontiguousarray(gyro.inv_I, float) if energy else z3
    gE = np.ascontiguousarray(gyro.E, float) if energy else z3
    ge = gidx.shape[0] if energy else 0
    gi = gidx.shape[0] if code == IMPLICIT else 0
    return (code, t_idx, t_I, gidx, gI, ginv, gE, float(YOSHIDA_MAX)) + energy_work(ge) + implicit_work(gi)


@njit(cache=True)
def before_flight(gy, R0, w, T, W, h):
    """What runs between gravity and the free flight: the explicit
    gyroscopic torque (forces.GyroscopicTorque at the start state: ``R0``
    (n, 3, 3), ``w`` (n, 3) the state's angular velocities, into ``T``
    (n, 3) N m) and Catto's implicit update of the working angular
    velocities ``W`` (n+1, 3) rad/s (integrate.ImplicitGyroscopic) over
    ``h`` s; each a no-op without its stage."""
    code, t_idx, t_I, gidx, gI, ginv, gE, ymax, wk, wq, wR, gJ, gf = gy
    gyroscopic_torque(t_idx, t_I, R0, w, T)
    if code == IMPLICIT and gidx.shape[0]:
        implicit_gyroscopic(gidx, gI, R0, W, h, gJ, gf)


@njit(cache=True)
def after_flight(gy, R0, T_mean, w, q, h, lever, q1, W, w_free, u_ang):
    """What runs right after the free flight: the energy-conserving
    rotation (integrate.EnergyConservingRotation: from the start state's
    ``w`` (n, 3), ``q`` (n, 4), ``R0`` and the step's mean torque
    ``T_mean`` (n, 3); writes ``q1`` (n, 4), ``W`` (n+1, 3), ``w_free``,
    ``u_ang`` (n, 3) of its bodies); a no-op without the stage."""
    code, t_idx, t_I, gidx, gI, ginv, gE, ymax, wk, wq, wR, gJ, gf = gy
    if code == ENERGY and gidx.shape[0]:
        energy_rotation_into(gidx, gI, ginv, gE, YOSHIDA, ymax, R0, T_mean, w, q, h, lever, q1, W, w_free, u_ang, wk,
                             wq, wR)
