"""Small vectorised quaternion and rotation helpers (wxyz, unit quaternions).

The operations the integrators and the collision code need (the engine
imports nothing of the harness or the adapters).  All functions work on stacks: ``(k, 4)``
quaternions and ``(k, 3)`` vectors.
"""

from __future__ import annotations

import numpy as np


# quaternion products q_i q_j (flattened 4x4, w x y z = 0 1 2 3) combined
# into the nine entries of R as 2 (p_a + s p_b); the diagonal is 1 - 2 (p_a + p_b)
_Q2M_A = np.array([10, 6, 7, 6, 5, 11, 7, 11, 5])  # yy xy xz xy xx yz xz yz xx
_Q2M_B = np.array([15, 3, 2, 3, 15, 1, 2, 1, 10])  # zz wz wy wz zz wx wy wx yy
_Q2M_S = np.array([1.0, -1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0])
_Q2M_D = np.array([0, 4, 8])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) wxyz: the
    same arithmetic as the adapters' conventions module (bit for bit;
    tests/test_conventions.py), with the products formed in one outer product."""
    q = np.asarray(q, float)
    p = (q[..., :, None] * q[..., None, :]).reshape(q.shape[:-1] + (16,))
    R = 2 * (p[..., _Q2M_A] + _Q2M_S * p[..., _Q2M_B])
    R[..., _Q2M_D] = 1 - R[..., _Q2M_D]
    return R.reshape(q.shape[:-1] + (3, 3))


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (broadcasting); much cheaper than np.cross
    for the small stacks the engine uses."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def quat_mul(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Hamilton product a (x) b of (k, 4) wxyz quaternions."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    if out is None:
        out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    out[..., 0], out[..., 1], out[..., 2], out[..., 3] = w, x, y, z
    return out


def quat_deriv(w: np.ndarray, q: np.ndarray) -> np.ndarray:
    """dq/dt = 1/2 (0, w) (x) q for a world-frame angular velocity w (k, 3)."""
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    out = np.empty(q.shape)
    out[..., 0] = -0.5 * (wx * qx + wy * qy + wz * qz)
    out[..., 1] = 0.5 * (wx * qw + wy * qz - wz * qy)
    out[..., 2] = 0.5 * (-wx * qz + wy * qw + wz * qx)
    out[..., 3] = 0.5 * (wx * qy - wy * qx + wz * qw)
    return out


def quat_from_rotvec(phi: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation by angle |phi| about phi (k, 3)."""
    ang = np.linalg.norm(phi, axis=-1)
    half = 0.5 * ang
    # sin(half)/ang, with its limit 1/2 - ang^2/48 for tiny angles
    small = ang < 1e-8
    s = np.where(small, 0.5 - ang * ang / 48.0, np.sin(half) / np.where(small, 1.0, ang))
    out = np.empty(phi.shape[:-1] + (4,))
    out[..., 0] = np.cos(half)
    out[..., 1:] = phi * s[..., None]
    return out


def rotate_world(q: np.ndarray, phi: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Orientation q turned by the world-frame rotation vector phi:
    exp(phi) (x) q, renormalised.  (k, 4), (k, 3) -> (k, 4)."""
    r = quat_mul(quat_from_rotvec(phi), q, out=out)
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    return r


def world_inv_inertia(R: np.ndarray, inv_inertia_body: np.ndarray) -> np.ndarray:
    """I_world^-1 = R diag(1/I) R^T, (k, 3, 3) from (k, 3, 3) and (k, 3)."""
    return np.einsum("kij,kj,klj->kil", R, inv_inertia_body, R)
