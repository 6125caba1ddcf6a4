"""Compile time kept apart from stepping.

The engine's compiled kernels (numba, ``cache=True``: compiled once per
machine and numba version, then loaded from the on-disk cache) are compiled
or loaded at their first call.  :func:`warm_up` makes that first call at
build, on a tiny problem with the same argument types as the step's, so no
step pays for it; the seconds it took are *JIT time*, reported by the next
:class:`engine.profile.Profile` as ``jit_s`` (and by the runner as
``timing.jit_s``, outside ``step_cpu_s`` and ``cpu_s_per_sim_s``).  Later
builds in the same process find the kernels ready and report 0.
"""

from __future__ import annotations

import time

import numpy as np

_READY = False
_PENDING = 0.0


def warm_up() -> float:
    """Compile (or load from the cache) every dynamics and collision kernel
    once per process; returns the seconds spent (0.0 when already done)."""
    global _READY, _PENDING
    if _READY:
        return 0.0
    t0 = time.perf_counter()
    from engine.contact import linalg, sweeps

    m, nb = 3, 2  # three rows on two bodies and the world (index 2)
    J = np.ones((m, 12))
    M = np.full((m, 12), 0.1)
    a = np.array([0, 0, 1], np.int64)
    b = np.array([1, 2, 2], np.int64)
    r = np.ones(m)
    act = np.arange(m, dtype=np.int64)
    K = linalg.normal_matrix(J, M, a, b, nb)
    linalg.lcp_residual(linalg.k_times(J, M, a, b, nb, r) - r, r)
    linalg.dense_active_set(K, r, act, 1e-10, 2)
    linalg.spd_solve_sparse(J, M, a, b, nb, r, act, 1e-10)
    linalg.lu_solve(K + np.eye(m), r)
    linalg.inverse(K + np.eye(m))
    linalg.solve_batch(np.tile(np.eye(3), (2, 1, 1)), np.ones((2, 3)))
    linalg.islands(nb, a, b)
    U = np.zeros((nb + 1, 6))
    ab = np.stack([a, b], axis=1)
    sweeps.apply_rows(U, ab, M, r, nb)
    npch = 2
    pab = np.array([[0, 1], [0, 2]], np.int64)
    pid = np.array([0, 1, 1], np.int64)
    Jt = np.ones((npch, 5, 12))
    Mt = np.full((npch, 5, 12), 0.1)
    lam_t = np.zeros((npch, 5))
    sweeps.apply_patches(U, pab, Mt, lam_t, nb)
    zb = np.zeros(npch, np.bool_)
    z2 = np.zeros((npch, 2))
    sweeps.iterate(U, ab, J, M, np.ones(m), np.zeros(m), r, True, pab, pid, Jt, Mt, np.ones((npch, 5)), lam_t,
                   np.ones(npch), np.ones(npch), np.ones(npch), zb, z2, zb, z2, 2, 1e-7, nb)
    sweeps.iterate_normal(U, ab, J, M, np.ones(m), np.zeros(m), r, 2, 1e-7, nb)
    from engine.collision import dispatch
    dispatch.warm_up()  # the broad and narrow phases' kernels
    dt = time.perf_counter() - t0
    _READY = True
    _PENDING += dt
    return dt


def take_pending() -> float:
    """JIT seconds not yet reported by a profile (then 0 until the next
    compile)."""
    global _PENDING
    s, _PENDING = _PENDING, 0.0
    return s
