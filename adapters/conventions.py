"""Frame, quaternion and planar conversions: written once, tested once.

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


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz -> xyzw."""
    return np.asarray(q)[..., [1, 2, 3, 0]]


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """(..., 4) xyzw -> wxyz."""
    return np.asarray(q)[..., [3, 0, 1, 2]]


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) wxyz."""
    q = np.asarray(q, float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quat_rotate(q: np.ndarray, v: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4) wxyz:
    v' = v + w t + u x t with t = 2 u x v (u the vector part).

    Written out per component: the same arithmetic as with ``np.cross``
    (results are bit-identical) at half the cost on the small stacks the
    adapters convert per block.  ``out`` (..., 3) may be given to write in
    place; it must not share memory with q or v."""
    q = np.asarray(q, float)
    v = np.asarray(v, float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    vx, vy, vz = v[..., 0], v[..., 1], v[..., 2]
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    if out is None:
        out = np.empty(np.broadcast_shapes(q.shape[:-1] + (3,), v.shape))
    out[..., 0] = vx + w * tx + (y * tz - z * ty)
    out[..., 1] = vy + w * ty + (z * tx - x * tz)
    out[..., 2] = vz + w * tz + (x * ty - y * tx)
    return out


def body_to_world_angvel(q: np.ndarray, w_body: np.ndarray) -> np.ndarray:
    """Angular velocity from the body frame (MuJoCo free-joint qvel[3:6]) to
    the world frame: w_world = R(q) w_body."""
    return quat_rotate(q, w_body)


def world_to_body_angvel(q: np.ndarray, w_world: np.ndarray) -> np.ndarray:
    """Inverse of :func:`body_to_world_angvel`: w_body = R(q)^T w_world."""
    qc = np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])
    return quat_rotate(qc, w_world)


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


def planar_point_to_world(x: float, y: float) -> np.ndarray:
    """A 2D engine point (x, y) -> world (x, 0, y)."""
    return np.array([x, 0.0, y])


def world_point_to_planar(p: np.ndarray) -> tuple[float, float]:
    """World point (x, y, z) in the x-z plane -> 2D (x, z)."""
    return float(p[0]), float(p[2])
