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

The explicit torque is a force stage (engine.flight.apply_forces); the
fused flight part (engine/fused/part.py) runs the other two with the same
compiled kernels on the stage's own arrays (its engine.gyroscopic.Gyro) at
the same places of the step (:func:`before_flight` after the forces,
:func:`after_flight` after the free flight): the same bits as the stages
one by one (tests/test_engine_steady_gyro.py).
"""

from __future__ import annotations

from numba import njit

from physbench.engine.gyroscopic import (ENERGY, IMPLICIT, NO_GYRO, energy_rotation_into, implicit_gyroscopic,
                                         no_gyro)
from physbench.engine.integrate import EnergyConservingRotation, ImplicitGyroscopic

__all__ = ("ENERGY", "IMPLICIT", "NO_GYRO", "after_flight", "before_flight", "gyro_items", "split_gyro")


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


def gyro_items(gyro):
    """The gyroscopic stage ``gyro``'s arrays (its engine.gyroscopic.Gyro,
    the staged stage's own: kept work arrays, no allocation a step), or an
    empty Gyro without one."""
    return gyro.gy if gyro is not None else no_gyro()


@njit(cache=True)
def before_flight(gy, R0, W, h):
    """What runs between the force stages and the free flight: Catto's
    implicit update of the working angular velocities ``W`` (n+1, 3) rad/s
    (integrate.ImplicitGyroscopic) over ``h`` s at the start rotations
    ``R0`` (n, 3, 3); a no-op without the stage."""
    if gy.code == IMPLICIT and gy.idx.shape[0]:
        implicit_gyroscopic(gy.idx, gy.I, R0, W, h, gy.J, gy.f)


@njit(cache=True)
def after_flight(gy, R0, T_mean, w, q, h, lever, q1, W, w_free, u_ang):
    """What runs right after the free flight: the energy-conserving
    rotation (integrate.EnergyConservingRotation: from the start state's
    ``w`` (n, 3), ``q`` (n, 4), ``R0`` and the step's mean torque
    ``T_mean`` (n, 3); writes ``q1`` (n, 4), ``W`` (n+1, 3), ``w_free``,
    ``u_ang`` (n, 3) of its bodies); a no-op without the stage."""
    if gy.code == ENERGY and gy.idx.shape[0]:
        energy_rotation_into(gy, R0, T_mean, w, q, h, lever, q1, W, w_free, u_ang)
