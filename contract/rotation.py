"""Rotation math of the contract, written once: quaternions (w, x, y, z),
rotation matrices, world <-> body angular velocity.

Everything outside the engine takes its rotations from here (adapters,
metrics, geometry, reference models, phase shifting, traces).  ``engine/``
keeps its own compiled copies (``engine/mathutil.py``): the engine is a leaf
and imports nothing of ours (docs/ARCHITECTURE.md);
tests/test_frames.py pins both against each other.
"""

from __future__ import annotations

import math

import numpy as np


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """(..., 4) wxyz -> xyzw."""
    return np.asarray(q)[..., [1, 2, 3, 0]]


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """(..., 4) xyzw -> wxyz."""
    return np.asarray(q)[..., [3, 0, 1, 2]]


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b of two 1-D vectors, summed left to right in Python floats.  A
    1-D ``a @ b`` or ``np.linalg.norm(a)`` calls BLAS ``ddot``, whose
    rounding depends on the kernel OpenBLAS picks (``OPENBLAS_CORETYPE``):
    a scene built with it would differ in its last bits from one machine to
    the next (tests/test_engine_blas_free.py)."""
    return sum((float(x) * float(y) for x, y in zip(a, b)), 0.0)


def norm(a: np.ndarray) -> float:
    """|a| of a 1-D vector without BLAS (:func:`dot`)."""
    return math.sqrt(dot(a, a))


def transpose_apply(R: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R^T v for a (3, 3) matrix and a (3,) vector without BLAS (:func:`dot`)."""
    return np.array([dot(R[:, i], v) for i in range(3)])


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


def rotation_matrix(q: np.ndarray | None) -> np.ndarray:
    """Rotation matrix (3, 3) of a wxyz quaternion (4,) that need not be of
    unit length (it is normalised first); None is the identity."""
    q = np.asarray(q if q is not None else (1.0, 0.0, 0.0, 0.0), float)
    return quat_to_matrix(q / norm(q))


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a b of wxyz quaternions (4,)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw])


def quat_exp(phi: np.ndarray) -> np.ndarray:
    """Unit quaternion (wxyz, (4,)) of the rotation vector phi (3,) rad."""
    phi = np.asarray(phi, float)
    a = norm(phi)
    if a < 1e-300:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[math.cos(a / 2)], math.sin(a / 2) * phi / a])


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
