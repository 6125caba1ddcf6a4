"""Planar conversions of the contract: written once, tested once (the
rotation math is in :mod:`contract.rotation`).

physbench's conventions: quaternions (w, x, y, z); linear and angular
velocities in the world frame; planar scenes in the x-z plane, where a 2D
engine's (x, y) is world (x, z) and its counter-clockwise angular velocity w
(turning +x toward +z... seen from -y) is the world angular velocity (0, -w, 0).

Why the minus sign: a 2D engine's counter-clockwise rotation turns its +x
axis toward its +y axis.  Its +y is world +z.  A rotation turning world +x
toward world +z is a rotation about world -y (right-hand rule: y x z = x, so
+y turns z toward x).  Hence omega_world = (0, -w, 0), and a 2D angle theta is
the world orientation quat(cos(theta/2), 0, -sin(theta/2), 0).
"""

from __future__ import annotations

import numpy as np

#: the words an adapter puts in a row's ``notes`` and ``info["drag"]`` when the
#: row's drag is physbench's own force law applied as an external force, not
#: the engine's drag model (adapters.forces; the report marks such rows)
DRAG_EXTERNAL = "drag applied as an external force each step"


# ---- planar (x-z) mapping -------------------------------------------------

def planar_from_world(position: np.ndarray, velocity: np.ndarray, orientation: np.ndarray,
                      angular_velocity: np.ndarray) -> tuple[tuple[float, float], tuple[float, float], float, float]:
    """World state of a planar body -> 2D engine state.

    Returns ((x, y), (vx, vy), angle, w) with 2D y = world z, angle the
    counter-clockwise 2D angle and w = -omega_world_y.
    """
    q = np.asarray(orientation, float)
    # q = (cos(theta/2), 0, -sin(theta/2), 0)  =>  theta = -2 atan2(q_y, q_w)
    angle = -2.0 * float(np.arctan2(q[2], q[0]))
    return ((float(position[0]), float(position[2])), (float(velocity[0]), float(velocity[2])),
            angle, -float(angular_velocity[1]))


def world_from_planar(x: float, y: float, vx: float, vy: float, angle: float, w: float,
                      pos_out: np.ndarray, quat_out: np.ndarray, vel_out: np.ndarray,
                      angvel_out: np.ndarray) -> None:
    """2D engine state -> world arrays, written in place (pos_out (3,),
    quat_out (4,) wxyz, vel_out (3,), angvel_out (3,))."""
    pos_out[0] = x
    pos_out[1] = 0.0
    pos_out[2] = y
    h = 0.5 * angle
    quat_out[0] = np.cos(h)
    quat_out[1] = 0.0
    quat_out[2] = -np.sin(h)
    quat_out[3] = 0.0
    vel_out[0] = vx
    vel_out[1] = 0.0
    vel_out[2] = vy
    angvel_out[0] = 0.0
    angvel_out[1] = -w
    angvel_out[2] = 0.0


def world_point_to_planar(p: np.ndarray) -> tuple[float, float]:
    """World point (x, y, z) in the x-z plane -> 2D (x, z)."""
    return float(p[0]), float(p[2])
