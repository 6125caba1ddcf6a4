"""Compiled LU with partial pivoting (LAPACK's dgesv choices of pivot: the
first row of largest magnitude), a fixed summation order and no BLAS or
LAPACK call (tests/test_engine_blas_free.py): :func:`lu_solve`,
:func:`lu_inplace`, :func:`lu_skip_inplace` (the same bits without the
no-ops on a sparse matrix's zeros: the dense direct start's), the small
inverses and batched solves of the impact solver and the gyroscopic
stages.  Re-exported by :mod:`engine.contact.linalg`.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def lu_solve(A, r):
    """Solve A x = r (A (k, k), r (k,)) by LU with partial pivoting.
    Returns (x, det); det = 0 and x undefined when a pivot is exactly
    zero (singular)."""
    x = r.copy()
    return x, lu_inplace(A.copy(), x)


@njit(cache=True)
def lu_inplace(L, x):
    """:func:`lu_solve` in place: ``L`` (k, k) overwritten by its factors,
    ``x`` (k,) from r to the solution; returns det (0 when singular)."""
    k = L.shape[0]
    det = 1.0
    for c in range(k):
        p = c
        big = abs(L[c, c])
        for i in range(c + 1, k):
            v = abs(L[i, c])
            if v > big:
                big = v
                p = i
        if big == 0.0:
            return 0.0
        if p != c:
            for j in range(k):
                t = L[c, j]
                L[c, j] = L[p, j]
                L[p, j] = t
            t = x[c]
            x[c] = x[p]
            x[p] = t
            det = -det
        piv = L[c, c]
        det *= piv
        for i in range(c + 1, k):
            f = L[i, c] / piv
            L[i, c] = f
            if f != 0.0:
                for j in range(c + 1, k):
                    L[i, j] -= f * L[c, j]
                x[i] -= f * x[c]
    for c in range(k - 1, -1, -1):
        s = x[c]
        for j in range(c + 1, k):
            s -= L[c, j] * x[j]
        x[c] = s / L[c, c]
    return det


@njit(cache=True)
def lu_skip_inplace(L, x, nz):
    """:func:`lu_inplace` without its exact no-ops, for a matrix mostly
    zero (a contact graph's normal matrix: islands, and within an island
    rows coupled only through a shared body) whose entries are never -0.0
    (K's: sums from +0.0, or zero): returns det
    with ``x`` the solution, the same bits, or NaN when that could not be
    assured or the matrix is singular (then ``L`` and ``x`` are spoilt: the
    caller redoes :func:`lu_inplace` on the matrix).  ``nz`` (>= k,) int64 scratch.

    The same pivots (the same scan), the same multipliers and updates of
    every entry that changes; skipped: a row whose multiplier is zero
    (also skipped there), the updates L[i, j] -= f L[c, j] where L[c, j]
    is zero, the back substitution's terms L[c, j] x[j] with L[c, j] zero,
    the multipliers' stores and the swaps of the columns left of the pivot
    (never read again: only x and det are returned).  Why the same bits:
    with every value finite, f L[c, j] is a signed zero and x - (+-0) = x
    for every x but -0.0; the active entries start as K's (sums from +0.0,
    never -0.0) or zero and x - y is -0.0 only for x = -0.0, so no entry is
    ever -0.0; a back substitution whose sum starts at a zero runs every
    term.  Finiteness: a non-finite value given or made on the way
    reaches det or x (every active entry becomes a pivot, a term of the
    back substitution or a multiplier of x), and then NaN is returned.  Pinned by the bits of
    every scenario (tests/test_determinism.py) and
    tests/test_engine_steady.py::test_lu_skip_is_lu_bit_for_bit."""
    k = L.shape[0]
    det = 1.0
    for c in range(k):
        p = c
        big = abs(L[c, c])
        for i in range(c + 1, k):
            v = abs(L[i, c])
            if v > big:
                big = v
                p = i
        if big == 0.0:  # singular (or a non-finite column): lu_inplace decides
            return np.nan
        if p != c:
            for j in range(c, k):
                t = L[c, j]
                L[c, j] = L[p, j]
                L[p, j] = t
            t = x[c]
            x[c] = x[p]
            x[p] = t
            det = -det
        piv = L[c, c]
        det *= piv
        q = 0
        for j in range(c + 1, k):  # row c's non-zeros right of the pivot
            nz[q] = j
            q += L[c, j] != 0.0
        xc = x[c]
        for i in range(c + 1, k):
            e = L[i, c]
            if e != 0.0:
                f = e / piv
                if f != 0.0:
                    for t in range(q):
                        j = nz[t]
                        L[i, j] -= f * L[c, j]
                    x[i] -= f * xc
    if not np.isfinite(det):
        return np.nan
    for c in range(k - 1, -1, -1):
        s = x[c]
        if s == 0.0:  # +0.0 or -0.0: every term, as lu_inplace
            for j in range(c + 1, k):
                s -= L[c, j] * x[j]
        else:
            for j in range(c + 1, k):
                u = L[c, j]
                if u != 0.0:
                    s -= u * x[j]
        x[c] = s / L[c, c]
        if not np.isfinite(x[c]):
            return np.nan
    return det


@njit(cache=True)
def inverse(A):
    """A^-1 (k, k) column by column (:func:`lu_solve`); (inverse, ok)."""
    k = A.shape[0]
    out = np.empty((k, k))
    e = np.zeros(k)
    for j in range(k):
        e[:] = 0.0
        e[j] = 1.0
        x, det = lu_solve(A, e)
        if det == 0.0:
            return out, False
        for i in range(k):
            out[i, j] = x[i]
    for i in range(k):
        for j in range(k):
            if not np.isfinite(out[i, j]):
                return out, False
    return out, True


@njit(cache=True)
def solve_batch(A, f):
    """f[k] <- A[k]^-1 f[k] in place for (K, d, d) A and (K, d) f, each by
    :func:`lu_inplace` on A[k] (overwritten by its factors; the arithmetic of
    :func:`lu_solve`, nothing allocated); a singular system gives NaN (like a
    LAPACK solve's inf/NaN propagation would not: callers keep A
    regular)."""
    for k in range(A.shape[0]):
        x = f[k]
        if lu_inplace(A[k], x) == 0.0:
            x[:] = np.nan
