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


def world_inv_inertia(R: np.ndarray, inv_inertia_body: np.ndarray) -> np.ndarray:
    """I_world^-1 = R diag(1/I) R^T, (k, 3, 3) from (k, 3, 3) and (k, 3)."""
    return np.einsum("kij,kj,klj->kil", R, inv_inertia_body, R)
