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
    quat_out (4,) wxyz, vel_out (3,), angvel_out (3,)); the state may be
    arrays of one shape, each output then having its component axis first
    (quat_out (4, ...)).  An engine that holds a rotation as (cos, sin)
    rather than an angle gets the same quaternion from
    :func:`world_quat_from_planar_rotation`."""
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


def world_quat_from_planar_rotation(c: np.ndarray, s: np.ndarray, w_out: np.ndarray, y_out: np.ndarray,
                                    scratch: np.ndarray) -> None:
    """A 2D rotation given by its (cos, sin) pair -> the w and y components
    of its world quaternion, the mapping of :func:`world_from_planar` with
    angle = atan2(s, c) in (-pi, pi]: w = cos(angle/2) >= 0, y =
    -sin(angle/2), x = z = 0 (left to the caller), with no transcendental
    function (square roots and divisions only).

    c, s: arrays of one shape (any float dtype; (c, s) need not be exactly
    unit, as a single-precision engine's are not: normalised by r =
    sqrt(c^2 + s^2) in float64); w_out, y_out: float64 arrays of that shape,
    written in place; scratch: float64 array (4, *shape), overwritten.

    Half-angle formula, accurate everywhere (no cancellation): with
    p = r + |c| (>= r), the half-angle pair has a large component
    big = sqrt(p / 2r) (>= 1/sqrt 2) and a small one small = |s| / (2 r big),
    both to a few ulps; the large one is the cosine when c >= 0 (|angle| <=
    pi/2), the sine when c < 0.  The choice is exact, branch-free
    arithmetic: with u = copysign(big, c), cos = max(u, small) and |sin| =
    max(-u, small) (at c = +-0 both are 1/sqrt 2 to an ulp, so either is
    right); sin takes the sign of s, so s = +-0 gives the angle +-0 for
    c > 0 and +-pi for c < 0, as atan2 does.  A NaN in gives NaN out, and so
    does c = s = 0 (not a rotation).  19 array operations, no temporary.
    Agrees with world_from_planar(atan2(s, c)) to 2^-50 absolute
    (tests/test_frames.py::test_planar_rotation_quaternion_matches_the_angle_path)."""
    a, b, r, p = scratch[0], scratch[1], scratch[2], scratch[3]
    a[...] = c
    np.negative(s, out=b)  # -s, the sign of the quaternion's y
    np.multiply(a, a, out=r)  # exact for float32 input
    np.multiply(b, b, out=p)
    np.add(r, p, out=r)
    np.sqrt(r, out=r)  # r
    np.abs(a, out=p)
    np.add(p, r, out=p)  # p = r + |c|
    np.add(r, r, out=r)  # 2r
    np.divide(p, r, out=p)
    np.sqrt(p, out=p)  # big
    np.multiply(r, p, out=r)  # 2 r big
    np.divide(b, r, out=r)
    np.abs(r, out=r)  # small
    np.copysign(p, a, out=a)  # u
    np.maximum(a, r, out=w_out)  # cos(angle/2)
    np.negative(a, out=a)
    np.maximum(a, r, out=p)  # |sin(angle/2)|
    np.copysign(p, b, out=y_out)  # -sin(angle/2)


def world_point_to_planar(p: np.ndarray) -> tuple[float, float]:
    """World point (x, y, z) in the x-z plane -> 2D (x, z)."""
    return float(p[0]), float(p[2])
