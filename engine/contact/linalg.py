"""Compiled linear algebra of the contact solve, with a fixed summation
order: no BLAS or LAPACK call, so the bits do not depend on the machine's
BLAS kernel (``OPENBLAS_CORETYPE``; pinned by
tests/test_engine_blas_free.py).

* :func:`normal_matrix`: K = J M^-1 J^T over normal rows (m, m), dense;
* :func:`lu_solve`: LU with partial pivoting (LAPACK's dgesv choices of
  pivot: the first row of largest magnitude), for the dense direct start
  and the small blocks of the impact solver;
* :func:`spd_solve_sparse`: the sparse direct start -- the rows split
  into islands (rows joined by a dynamic body), each ordered by reverse
  Cuthill-McKee and solved by a banded Cholesky factorisation;
* :func:`k_times`: K lam from the rows' Jacobians without forming K.

Rows are as in :class:`engine.contact.rows.Rows`: ``J``/``M`` (m, 12) =
[JA | JB] and [MA | MB] = M^-1 J^T, bodies ``a``/``b`` (m,), the world
index ``world`` (its rows of M are zero: it couples nothing).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Tikhonov regularisation of the direct start's normal matrix, relative to
#: its largest diagonal entry (the dense and the sparse solve alike)
EPS_REL = 1e-10


@njit(cache=True, inline="always")
def _dot6(x, i0, y, j0, i, j):
    s = 0.0
    for k in range(6):
        s += x[i, i0 + k] * y[j, j0 + k]
    return s


@njit(cache=True, inline="always")
def _k_entry(J, M, a, b, world, i, j):
    """K[i, j]: the sides of rows i and j on a shared dynamic body."""
    s = 0.0
    if a[i] == a[j]:
        s += _dot6(J, 0, M, 0, i, j)
    if a[i] == b[j] and b[j] != world:
        s += _dot6(J, 0, M, 6, i, j)
    if b[i] == a[j] and b[i] != world:
        s += _dot6(J, 6, M, 0, i, j)
    if b[i] == b[j] and b[i] != world:
        s += _dot6(J, 6, M, 6, i, j)
    return s


@njit(cache=True, inline="always")
def _k_entry_select(J, M, a, b, world, i, j):
    """:func:`_k_entry` with its four sides computed unconditionally and
    selected (0.0 for a side the rows do not share): the same bits -- the
    sum starts at +0.0 and a sum from +0.0 is never -0.0 in round to
    nearest, so adding 0.0 for a skipped side leaves it as it was -- with
    four independent products in flight instead of data-dependent branches
    (tests/test_determinism.py; the dense direct start's normal matrix)."""
    ai, bi, aj, bj = a[i], b[i], a[j], b[j]
    daa = _dot6(J, 0, M, 0, i, j)
    dab = _dot6(J, 0, M, 6, i, j)
    dba = _dot6(J, 6, M, 0, i, j)
    dbb = _dot6(J, 6, M, 6, i, j)
    s = 0.0
    s += daa if ai == aj else 0.0
    s += dab if (ai == bj and bj != world) else 0.0
    s += dba if (bi == aj and bi != world) else 0.0
    s += dbb if (bi == bj and bi != world) else 0.0
    return s


@njit(cache=True)
def normal_matrix(J, M, a, b, world):
    """K = J M^-1 J^T (m, m) of the normal rows: entry (i, j) is summed over
    the dynamic bodies rows i and j share, aa, ab, ba, bb in that order
    (:func:`_k_entry`); rows sharing no body are 0 and never visited (a row
    meets only the rows of its two bodies; a row sharing both is visited
    once, from body a)."""
    m = J.shape[0]
    K = np.zeros((m, m))
    ptr, idx = _body_rows(a, b, world, np.arange(m))
    for i in range(m):
        ai = a[i]
        for side in range(2):
            body = ai if side == 0 else b[i]
            if body == world or (side == 1 and body == ai):
                continue
            for t in range(ptr[body], ptr[body + 1]):
                j = idx[t]
                if side == 1 and ai != world and (a[j] == ai or b[j] == ai):
                    continue  # row j meets body a[i] too: its entry is set
                K[i, j] = _k_entry_select(J, M, a, b, world, i, j)
    return K


@njit(cache=True)
def k_times(J, M, a, b, world, lam):
    """K lam (m,) as J (M^-1 J^T lam): impulses summed per body in row
    order, then each row's velocity change."""
    m = J.shape[0]
    dU = np.zeros((world + 1, 6))
    for i in range(m):
        li = lam[i]
        if li != 0.0:
            for k in range(6):
                dU[a[i], k] += M[i, k] * li
            if b[i] != world:
                for k in range(6):
                    dU[b[i], k] += M[i, 6 + k] * li
    for k in range(6):
        dU[world, k] = 0.0
    out = np.empty(m)
    for i in range(m):
        s = 0.0
        for k in range(6):
            s += J[i, k] * dU[a[i], k]
        for k in range(6):
            s += J[i, 6 + k] * dU[b[i], k]
        out[i] = s
    return out


@njit(cache=True)
def lu_solve(A, r):
    """Solve A x = r (A (k, k), r (k,)) by LU with partial pivoting.
    Returns (x, det); det = 0 and x undefined when a pivot is exactly
    zero (singular)."""
    k = A.shape[0]
    L = A.copy()
    x = r.copy()
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
            return x, 0.0
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
    return x, det


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
def dense_active_set(K, r, act, eps_rel, passes):
    """The dense direct start's equality solves: rows ``act`` (indices into
    K (m, m)) solved as K_aa lam = r_a with Tikhonov eps = eps_rel max
    diag(K_aa); rows solved to pull (lam < 0) let go and the rest solved
    again, up to ``passes`` solves.  Returns (lam (m,) clipped at 0, ok,
    whether the last solve pulled on a row)."""
    m = K.shape[0]
    lam = np.zeros(m)
    cur = act.copy()
    la = np.zeros(0)
    for npass in range(1, passes + 1):
        s = cur.size
        Ka = np.empty((s, s))
        ra = np.empty(s)
        dmax = -np.inf
        for i in range(s):
            ra[i] = r[cur[i]]
            for j in range(s):
                Ka[i, j] = K[cur[i], cur[j]]
            if Ka[i, i] > dmax:
                dmax = Ka[i, i]
        eps = eps_rel * dmax
        for i in range(s):
            Ka[i, i] += eps
        la, det = lu_solve(Ka, ra)
        if det == 0.0:
            return lam, False, False
        npull = 0
        for i in range(s):
            if la[i] < 0.0:
                npull += 1
        if npull == 0 or npull == s or npass == passes:
            break
        keep = np.empty(s - npull, np.int64)
        q = 0
        for i in range(s):
            if not la[i] < 0.0:
                keep[q] = cur[i]
                q += 1
        cur = keep
    for i in range(cur.size):
        if not np.isfinite(la[i]):
            return lam, False, False
    pulled = False
    for i in range(cur.size):
        pulled |= la[i] < 0.0
        lam[cur[i]] = max(la[i], 0.0)
    return lam, True, pulled


@njit(cache=True)
def _body_rows(a, b, world, rows):
    """CSR lists of the ``rows`` touching each dynamic body: (ptr (world+1,),
    idx) with positions into ``rows``."""
    cnt = np.zeros(world + 1, np.int64)
    for q in range(rows.size):
        i = rows[q]
        cnt[a[i]] += 1
        if b[i] != world:
            cnt[b[i]] += 1
    ptr = np.zeros(world + 2, np.int64)
    for k in range(world + 1):
        ptr[k + 1] = ptr[k] + cnt[k]
    fill = ptr[:-1].copy()
    idx = np.empty(ptr[world + 1], np.int64)
    for q in range(rows.size):
        i = rows[q]
        idx[fill[a[i]]] = q
        fill[a[i]] += 1
        if b[i] != world:
            idx[fill[b[i]]] = q
            fill[b[i]] += 1
    return ptr, idx


@njit(cache=True)
def spd_solve_sparse(J, M, a, b, world, r, rows, eps_rel):
    """Solve K_aa lam = r_a over the rows ``rows`` (indices, ascending) with
    Tikhonov eps = eps_rel max diag(K_aa), K symmetric positive
    semi-definite and sparse (rows couple only through shared bodies).

    The rows split into islands by a breadth-first search over shared
    dynamic bodies that visits a row's neighbours by increasing degree
    (Cuthill-McKee), reversed; each island is then a band of the reordered
    K, factorised by banded Cholesky (cost ~ s bw^2 for an island of s rows
    and bandwidth bw: a column of spheres has bw 1-2).  Returns (lam (m,)
    with zeros outside ``rows``, ok); ok is False at a non-positive pivot."""
    m = J.shape[0]
    s = rows.size
    lam = np.zeros(m)
    if s == 0:
        return lam, True
    ptr, idx = _body_rows(a, b, world, rows)
    deg = np.zeros(s, np.int64)
    for q in range(s):
        i = rows[q]
        deg[q] = ptr[a[i] + 1] - ptr[a[i]] - 1
        if b[i] != world:
            deg[q] += ptr[b[i] + 1] - ptr[b[i]] - 1
    dmax = -np.inf
    for q in range(s):
        i = rows[q]
        d = _k_entry(J, M, a, b, world, i, i)
        if d > dmax:
            dmax = d
    eps = eps_rel * dmax
    visited = np.zeros(s, np.bool_)
    order = np.empty(s, np.int64)
    pos = np.full(s, -1, np.int64)
    nbr = np.empty(s, np.int64)
    nbr_key = np.empty(s, np.int64)
    head = 0
    for start in range(s):
        if visited[start]:
            continue
        c0 = head
        order[head] = start
        visited[start] = True
        head += 1
        tail = c0
        while tail < head:
            q = order[tail]
            tail += 1
            k = 0
            i = rows[q]
            for side in range(2):
                body = a[i] if side == 0 else b[i]
                if body == world:
                    continue
                for t in range(ptr[body], ptr[body + 1]):
                    o = idx[t]
                    if not visited[o]:
                        visited[o] = True
                        nbr[k] = o
                        nbr_key[k] = deg[o] * s + o
                        k += 1
            if k:
                srt = np.argsort(nbr_key[:k])
                for t in range(k):
                    order[head] = nbr[srt[t]]
                    head += 1
        c1 = head
        n_c = c1 - c0
        # reverse the island's order
        for t in range(n_c // 2):
            u = order[c0 + t]
            order[c0 + t] = order[c1 - 1 - t]
            order[c1 - 1 - t] = u
        for t in range(c0, c1):
            pos[order[t]] = t - c0
        bw = 0
        for t in range(c0, c1):
            q = order[t]
            i = rows[q]
            for side in range(2):
                body = a[i] if side == 0 else b[i]
                if body == world:
                    continue
                for u in range(ptr[body], ptr[body + 1]):
                    d = abs(pos[idx[u]] - pos[q])
                    if d > bw:
                        bw = d
        # band storage: L[p, bw + (j - p)] for j in [p - bw, p]
        L = np.zeros((n_c, bw + 1))
        y = np.empty(n_c)
        for t in range(c0, c1):
            q = order[t]
            p = t - c0
            i = rows[q]
            y[p] = r[i]
            for side in range(2):
                body = a[i] if side == 0 else b[i]
                if body == world:
                    continue
                for u in range(ptr[body], ptr[body + 1]):
                    o = idx[u]
                    po = pos[o]
                    if po <= p:
                        L[p, bw + po - p] = _k_entry(J, M, a, b, world, i, rows[o])
            L[p, bw] += eps
        # banded Cholesky, in place
        for p in range(n_c):
            j0 = max(0, p - bw)
            for j in range(j0, p + 1):
                acc = L[p, bw + j - p]
                k0 = max(j0, j - bw)
                for k in range(k0, j):
                    acc -= L[p, bw + k - p] * L[j, bw + k - j]
                if j == p:
                    if not acc > 0.0:
                        return lam, False
                    L[p, bw] = math.sqrt(acc)
                else:
                    L[p, bw + j - p] = acc / L[j, bw]
        for p in range(n_c):
            acc = y[p]
            for k in range(max(0, p - bw), p):
                acc -= L[p, bw + k - p] * y[k]
            y[p] = acc / L[p, bw]
        for p in range(n_c - 1, -1, -1):
            acc = y[p]
            for k in range(p + 1, min(n_c, p + bw + 1)):
                acc -= L[k, bw + p - k] * y[k]
            y[p] = acc / L[p, bw]
        for t in range(c0, c1):
            lam[rows[order[t]]] = y[t - c0]
    return lam, True


@njit(cache=True)
def lcp_residual(w, lam):
    """Complementarity residual of normal impulses ``lam`` with w = K lam - r:
    violated rows plus rows that push while separating."""
    s1 = 0.0
    s2 = 0.0
    for i in range(w.size):
        v = min(w[i], 0.0)
        s1 += v * v
    for i in range(w.size):
        if lam[i] > 0.0:
            v = max(w[i], 0.0)
            s2 += v * v
    return s1 + s2


@njit(cache=True)
def solve_batch(A, f):
    """x[k] = A[k]^-1 f[k] for (K, d, d) A and (K, d) f, each by
    :func:`lu_solve` (a singular system gives NaN, like a LAPACK solve's
    inf/NaN propagation would not: callers keep A regular)."""
    out = np.empty(f.shape)
    for k in range(A.shape[0]):
        x, det = lu_solve(A[k], f[k])
        if det == 0.0:
            x[:] = np.nan
        out[k] = x
    return out


@njit(cache=True)
def islands(n, a, b):
    """Connected components of bodies 0..n-1 joined by the edges (a, b)
    with b < n (b = n, the world, joins nothing): (n,) labels 0..k-1 in
    order of each island's lowest body, and k."""
    parent = np.arange(n)
    for e in range(a.shape[0]):
        if b[e] >= n:
            continue
        x = a[e]
        while parent[x] != x:
            x = parent[x]
        y = b[e]
        while parent[y] != y:
            y = parent[y]
        if x != y:
            if x < y:
                parent[y] = x
            else:
                parent[x] = y
    lab = np.full(n, -1, np.int64)
    k = 0
    for i in range(n):
        x = i
        while parent[x] != x:
            x = parent[x]
        if lab[x] < 0:
            lab[x] = k
            k += 1
        lab[i] = lab[x]
    return lab, k
