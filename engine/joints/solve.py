"""The joint rows' system K lambda = rhs, K = J M^-1 J^T (r x r, symmetric
positive semi-definite), in band form: rows are numbered joint by joint,
so two rows that share a body are at most ``bw`` apart (``bw`` from the
joint table at build: 9 for a chain of revolute joints listed along it)
and K is a band matrix; its Cholesky factor has the same band.  Cost
O(r bw^2) per solve, no allocation (the band arrays are kept).

Redundant rows (a closed planar loop of 3D hinges constrains the same
freedom twice) give a zero pivot: such a row is dropped (its lambda is 0)
when its pivot falls below ``DROP`` times its diagonal, which solves a
consistent system exactly.  Tests: tests/test_engine_joints.py.
"""

from __future__ import annotations

import math

from numba import njit

#: relative pivot below which a row is redundant (dropped)
DROP = 1e-11


@njit(cache=True)
def mass_times_rows(ra, rb, J, inv_m, Iinv, MJ):
    """MJ (r, 12) = the rows of M^-1 J^T: per side, inv_m J_lin and
    Iinv (world, (n, 3, 3)) J_ang; zero for the world side."""
    for r in range(J.shape[0]):
        for side in range(2):
            k = ra[r] if side == 0 else rb[r]
            o = 6 * side
            if k < 0:
                for c in range(6):
                    MJ[r, o + c] = 0.0
                continue
            for c in range(3):
                MJ[r, o + c] = inv_m[k] * J[r, o + c]
            for i in range(3):
                MJ[r, o + 3 + i] = Iinv[k, i, 0] * J[r, o + 3] + Iinv[k, i, 1] * J[r, o + 4] + Iinv[k, i, 2] * J[r, o + 5]


@njit(cache=True)
def assemble(ra, rb, J, MJ, bw, Kb):
    """Kb[i, k] = K[i, i - k] (k = 0..bw) of K = J M^-1 J^T."""
    m = J.shape[0]
    for i in range(m):
        lo = i - bw if i >= bw else 0
        for j in range(lo, i + 1):
            s = 0.0
            for si in range(2):
                bi = ra[i] if si == 0 else rb[i]
                if bi < 0:
                    continue
                for sj in range(2):
                    bj = ra[j] if sj == 0 else rb[j]
                    if bj != bi:
                        continue
                    for c in range(6):
                        s += J[i, 6 * si + c] * MJ[j, 6 * sj + c]
            Kb[i, i - j] = s


@njit(cache=True)
def factor(Kb, bw, L):
    """Band Cholesky K = L L^T (L[i, k] = L[i, i - k]); a pivot below
    DROP times its diagonal marks a redundant row (L[i, 0] = 0, its column
    zero).  Returns the number of rows dropped."""
    m = Kb.shape[0]
    dropped = 0
    for i in range(m):
        lo = i - bw if i >= bw else 0
        for j in range(lo, i):
            s = Kb[i, i - j]
            lo2 = j - bw if j >= bw else 0
            if lo2 < lo:
                lo2 = lo
            for p in range(lo2, j):
                s -= L[i, i - p] * L[j, j - p]
            L[i, i - j] = s / L[j, 0] if L[j, 0] > 0.0 else 0.0
        d = Kb[i, 0]
        for p in range(lo, i):
            d -= L[i, i - p] * L[i, i - p]
        if d > DROP * Kb[i, 0] and d > 0.0:
            L[i, 0] = math.sqrt(d)
        else:
            L[i, 0] = 0.0
            dropped += 1
    return dropped


@njit(cache=True)
def band_solve(L, bw, rhs, y, out):
    """out = K^-1 rhs from the factor L (dropped rows: 0); y (r,) work."""
    m = L.shape[0]
    for i in range(m):
        s = rhs[i]
        lo = i - bw if i >= bw else 0
        for p in range(lo, i):
            s -= L[i, i - p] * y[p]
        y[i] = s / L[i, 0] if L[i, 0] > 0.0 else 0.0
    for i in range(m - 1, -1, -1):
        s = y[i]
        hi = i + bw if i + bw < m else m - 1
        for j in range(i + 1, hi + 1):
            s -= L[j, j - i] * out[j]
        out[i] = s / L[i, 0] if L[i, 0] > 0.0 else 0.0


@njit(cache=True)
def apply_rows(ra, rb, MJ, lam, scale, dv, dw):
    """dv, dw (n, 3) += scale * M^-1 J^T lam (per side of each row)."""
    for r in range(MJ.shape[0]):
        l = scale * lam[r]
        for side in range(2):
            k = ra[r] if side == 0 else rb[r]
            if k < 0:
                continue
            o = 6 * side
            for c in range(3):
                dv[k, c] += MJ[r, o + c] * l
                dw[k, c] += MJ[r, o + 3 + c] * l


@njit(cache=True)
def rows_times(ra, rb, J, v, w, out):
    """out (r,) = J u for velocities (or accelerations) v, w (n, 3)."""
    for r in range(J.shape[0]):
        s = 0.0
        for side in range(2):
            k = ra[r] if side == 0 else rb[r]
            if k < 0:
                continue
            o = 6 * side
            for c in range(3):
                s += J[r, o + c] * v[k, c] + J[r, o + 3 + c] * w[k, c]
        out[r] = s
