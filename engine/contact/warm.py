"""Compiled warm start (the warm-start phase) and its cache (the store
phase).

The cache a solve leaves (solver.WarmCache) is sorted by pair code:
``o_code`` (k,) the pair code of each cached point, ``o_loc`` (k, 3) m its
point in body a's frame, ``o_fn`` (k,) N its normal force; per distinct
pair ``u_code`` (p,) with the friction force ``u_ft`` (p, 3) N, twist
torque ``u_tw`` (p,) N m and rolling torque ``u_rr`` (p, 3) N m.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def match(codes, loc, a, bound_radius, o_code, o_loc, o_fn, u_code, u_ft, u_tw, u_rr, h, lam_n, friction,
          rolling, pid, t, lam_t, matched):
    """Warm impulses of the rows (pair ``codes`` (m,), points in body a's
    frame ``loc`` (m, 3), bodies ``a`` (m,)): each row takes lambda = fn h
    of the nearest cached point of its pair (the first on ties) within
    0.1 ``bound_radius[a]`` + 0.1 mm; with ``friction``, the patch
    ``pid[i]`` of a matched row takes its pair's friction force in its
    tangent frame ``t`` (np, 2, 3), the twist and (``rolling``) the rolling
    torque, times h.  ``lam_n`` (m,) and ``lam_t`` (np, nr) are written
    where matched (left as they are elsewhere); ``matched`` (np,) bool
    scratch."""
    m = codes.shape[0]
    k = o_code.shape[0]
    if friction:
        matched[:] = False
    for i in range(m):
        code = codes[i]
        j = np.searchsorted(o_code, code)
        best = -1
        bd = 0.0
        while j < k and o_code[j] == code:
            dx = loc[i, 0] - o_loc[j, 0]
            dy = loc[i, 1] - o_loc[j, 1]
            dz = loc[i, 2] - o_loc[j, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if best < 0 or d2 < bd:
                best = j
                bd = d2
            j += 1
        if best < 0:
            continue
        tol = 0.1 * bound_radius[a[i]] + 1e-4
        if bd > tol * tol:
            continue
        lam_n[i] = o_fn[best] * h
        if friction:
            p = pid[i]
            if matched[p]:
                continue
            matched[p] = True
            g = np.searchsorted(u_code, code)
            for r in range(2):
                lam_t[p, r] = (t[p, r, 0] * u_ft[g, 0] + t[p, r, 1] * u_ft[g, 1] + t[p, r, 2] * u_ft[g, 2]) * h
            lam_t[p, 2] = u_tw[g] * h
            if rolling:
                for r in range(2):
                    lam_t[p, 3 + r] = (t[p, r, 0] * u_rr[g, 0] + t[p, r, 1] * u_rr[g, 1]
                                       + t[p, r, 2] * u_rr[g, 2]) * h


@njit(cache=True)
def store(order, codes, loc, lam_n, touch, first, uniq_pid, friction, rolling, lam_t, t, h, o_code, o_loc,
          o_fn, o_touch, u_code, u_ft, u_tw, u_rr):
    """Fill a cache (the ``o_``/``u_`` arrays, module doc) from a solve:
    rows in the stable sort by pair code ``order`` (m,), ``first`` (p,)
    the first sorted row of each distinct pair and ``uniq_pid`` (p,) its
    patch; forces are impulses / h (N, N m)."""
    for s in range(order.shape[0]):
        i = order[s]
        o_code[s] = codes[i]
        o_fn[s] = lam_n[i] / h
        o_touch[s] = touch[i]
        for c in range(3):
            o_loc[s, c] = loc[i, c]
    for g in range(first.shape[0]):
        u_code[g] = o_code[first[g]]
        for c in range(3):
            u_ft[g, c] = 0.0
            u_rr[g, c] = 0.0
        u_tw[g] = 0.0
        if friction:
            p = uniq_pid[g]
            for c in range(3):
                u_ft[g, c] = (lam_t[p, 0] * t[p, 0, c] + lam_t[p, 1] * t[p, 1, c]) / h
                if rolling:
                    u_rr[g, c] = (lam_t[p, 3] * t[p, 0, c] + lam_t[p, 4] * t[p, 1, c]) / h
            u_tw[g] = lam_t[p, 2] / h
