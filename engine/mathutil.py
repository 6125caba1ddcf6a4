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


def _blas_thread_setter():
    """numpy's bundled OpenBLAS ``openblas_set_num_threads_local`` (thread-
    local, returns the previous count), or None when it cannot be found."""
    import ctypes
    import glob
    import os

    libdir = os.path.join(os.path.dirname(os.path.dirname(np.__file__)), "numpy.libs")
    for path in sorted(glob.glob(os.path.join(libdir, "*openblas*.so*"))):
        try:
            lib = ctypes.CDLL(path)
            fn = lib.openblas_set_num_threads_local
            fn.argtypes = [ctypes.c_int]
            fn.restype = ctypes.c_int
            return fn
        except (OSError, AttributeError):
            continue
    return None


_SET_BLAS_THREADS = _blas_thread_setter()


def solve_small(K: np.ndarray, r: np.ndarray) -> np.ndarray:
    """np.linalg.solve with numpy's OpenBLAS held to one thread for the call
    (thread-local, restored after).  For the engine's small systems
    (10-400 rows) threading never pays, and on a loaded machine a threaded
    LAPACK call waiting for busy cores was measured 500 times slower
    (90 ms instead of 0.15 ms for 100 rows)."""
    if _SET_BLAS_THREADS is None:
        return np.linalg.solve(K, r)
    prev = _SET_BLAS_THREADS(1)
    try:
        return np.linalg.solve(K, r)
    finally:
        _SET_BLAS_THREADS(prev)


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


def normalize_quat(q: np.ndarray) -> np.ndarray:
    """Renormalise (k, 4) quaternions in place and return them."""
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q


def world_inv_inertia(R: np.ndarray, inv_inertia_body: np.ndarray) -> np.ndarray:
    """I_world^-1 = R diag(1/I) R^T, (k, 3, 3) from (k, 3, 3) and (k, 3)."""
    return np.einsum("kij,kj,klj->kil", R, inv_inertia_body, R)


def apply_world_inertia(R: np.ndarray, inertia_body: np.ndarray, w: np.ndarray) -> np.ndarray:
    """I_world w = R (I_body (R^T w)) for (k, 3, 3), (k, 3), (k, 3)."""
    wb = np.einsum("kji,kj->ki", R, w)
    return np.einsum("kij,kj->ki", R, inertia_body * wb)


def perpendicular_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (k, 3) completing unit normals n (k, 3) to a
    right-handed orthonormal basis (n, t1, t2).  Deterministic: t1 is n x e
    for the world axis e least aligned with n."""
    k = n.shape[0]
    idx = np.argmin(np.abs(n), axis=1)
    e = np.zeros((k, 3))
    e[np.arange(k), idx] = 1.0
    t1 = cross(n, e)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = cross(n, t1)
    return t1, t2
