"""Compiled linear algebra of the contact solve, with a fixed summation
order: no BLAS or LAPACK call, so the bits do not depend on the machine's
BLAS kernel (``OPENBLAS_CORETYPE``; pinned by
tests/test_engine_blas_free.py).

* :func:`normal_matrix`: K = J M^-1 J^T over normal rows (m, m), dense;
* :func:`lu_solve`: LU with partial pivoting (LAPACK's dgesv choices of
  pivot: the first row of largest magnitude), for the dense direct start
  and the small blocks of the impact solver (:mod:`engine.contact.lu`,
  re-exported here);
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
from collections import namedtuple

import numpy as np
from numba import njit

from physbench.engine.contact.lu import inverse, lu_inplace, lu_skip_inplace, lu_solve, solve_batch  # noqa: F401 (re-exported)

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
def _dot6r(x, y, j, j0):
    """x (six floats) . y[j, j0:j0+6], summed from 0.0 in order (as _dot6)."""
    s = 0.0
    s += x[0] * y[j, j0]
    s += x[1] * y[j, j0 + 1]
    s += x[2] * y[j, j0 + 2]
    s += x[3] * y[j, j0 + 3]
    s += x[4] * y[j, j0 + 4]
    s += x[5] * y[j, j0 + 5]
    return s


@njit(cache=True, inline="always")
def _k_entry_row(Ja, Jb, M, a, b, world, i, j):
    """:func:`_k_entry` branch-free in two dot products, row i of J given
    as its halves Ja, Jb (six floats each): a row's a side meets at most
    one side of row j (aa or ab: a row's two bodies differ), so does its b
    side (ba or bb); each half is dotted with the side of M[j] it may meet
    and the products kept where the bodies are shared (0.0 else).  The
    same bits as summing the four sides in order aa, ab, ba, bb: the sum
    starts at +0.0 and a sum from +0.0 is never -0.0 in round to nearest,
    so adding 0.0 for a side the rows do not share leaves it as it was
    (tests/test_determinism.py; the dense direct start's normal matrix).
    Half the products of computing all four sides and selecting."""
    ai, bi, aj, bj = a[i], b[i], a[j], b[j]
    d1 = _dot6r(Ja, M, j, 0 if ai == aj else 6)
    d2 = _dot6r(Jb, M, j, 0 if bi == aj else 6)
    s = 0.0
    s += d1 if (ai == aj or (ai == bj and bj != world)) else 0.0
    s += d2 if (bi != world and (bi == aj or bi == bj)) else 0.0
    return s


@njit(cache=True, inline="always")
def _zero2(A):
    """A[:, :] = 0 as a plain loop (a memset; numba's slice assignment
    iterates generically)."""
    for i in range(A.shape[0]):
        for j in range(A.shape[1]):
            A[i, j] = 0.0


@njit(cache=True)
def normal_matrix_into(J, M, a, b, world, K, rows, cnt, ptr, idx):
    """K = J M^-1 J^T (m, m) of the normal rows, written into ``K`` (zeroed
    here): entry (i, j) is summed over the dynamic bodies rows i and j
    share, aa, ab, ba, bb in that order (:func:`_k_entry_row`); rows sharing
    no body are 0 and never visited (a row meets only the rows of its two
    bodies; a row sharing both is visited once, from body a).  ``rows``
    (>= m,), ``cnt`` (world+1,), ``ptr`` (world+2,), ``idx`` (>= 2m,) int64
    scratch (:func:`body_rows_into`)."""
    m = J.shape[0]
    _zero2(K)
    for i in range(m):
        rows[i] = i
    ptr, idx = body_rows_into(a, b, world, rows[:m], cnt, ptr, idx)
    for i in range(m):
        ai = a[i]
        # row i of J held in registers (K, an argument, may alias J for the
        # compiler: re-read after every store otherwise)
        Ja = (J[i, 0], J[i, 1], J[i, 2], J[i, 3], J[i, 4], J[i, 5])
        Jb = (J[i, 6], J[i, 7], J[i, 8], J[i, 9], J[i, 10], J[i, 11])
        for side in range(2):
            lo, hi = _side_range(a, b, world, ptr, i, side)
            if side == 1 and b[i] == ai:
                continue
            for t in range(lo, hi):
                j = idx[t]
                if side == 1 and ai != world and (a[j] == ai or b[j] == ai):
                    continue  # row j meets body a[i] too: its entry is set
                K[i, j] = _k_entry_row(Ja, Jb, M, a, b, world, i, j)


@njit(cache=True)
def normal_matrix(J, M, a, b, world):
    """:func:`normal_matrix_into` into a new (m, m) array."""
    m = J.shape[0]
    K = np.empty((m, m))
    normal_matrix_into(J, M, a, b, world, K, np.empty(m, np.int64), np.empty(world + 1, np.int64),
                       np.empty(world + 2, np.int64), np.empty(2 * m, np.int64))
    return K


@njit(cache=True)
def k_times_into(J, M, a, b, world, lam, dU, out):
    """K lam (m,) as J (M^-1 J^T lam): impulses summed per body in row
    order, then each row's velocity change, written into ``out`` (>= m,)
    (its first m returned); ``dU`` (world+1, 6) scratch (zeroed here)."""
    m = J.shape[0]
    _zero2(dU)
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
    out = out[:m]
    for i in range(m):
        s = 0.0
        for k in range(6):
            s += J[i, k] * dU[a[i], k]
        for k in range(6):
            s += J[i, 6 + k] * dU[b[i], k]
        out[i] = s
    return out


@njit(cache=True)
def k_times(J, M, a, b, world, lam):
    """:func:`k_times_into` into new arrays: K lam (m,)."""
    return k_times_into(J, M, a, b, world, lam, np.empty((world + 1, 6)), np.empty(J.shape[0]))


@njit(cache=True, inline="always")
def _active_system(K, r, cur, s, eps_rel, Ka, la):
    """Ka = K[cur, cur] + eps I (eps = eps_rel max diag), la = r[cur]
    (s rows; a plain copy of K's leading block when ``cur`` is 0..s-1)."""
    ident = True
    for i in range(s):
        ident &= cur[i] == i
    for i in range(s):
        ci = cur[i]
        la[i] = r[ci]
        if ident:
            for j in range(s):
                Ka[i, j] = K[i, j]
        else:
            for j in range(s):
                Ka[i, j] = K[ci, cur[j]]
    dmax = -np.inf
    for i in range(s):
        if Ka[i, i] > dmax:
            dmax = Ka[i, i]
    eps = eps_rel * dmax
    for i in range(s):
        Ka[i, i] += eps


@njit(cache=True)
def dense_active_set_into(K, r, act, eps_rel, passes, lam, cur, big, ra, nz):
    """The dense direct start's equality solves: rows ``act`` (indices into
    K (m, m)) solved as K_aa lam = r_a with Tikhonov eps = eps_rel max
    diag(K_aa); rows solved to pull (lam < 0) let go and the rest solved
    again, up to ``passes`` solves.  Writes ``lam`` (m,) (zeroed here,
    clipped at 0); ``cur``, ``nz`` (>= s,) int64, ``big`` (>= s*s,) and
    ``ra`` (>= s,) scratch for s = act.size rows.  Each solve is
    :func:`lu_skip_inplace` (the bits of :func:`lu_inplace`, without its
    no-ops on the zeros of K: a pile of islands costs ~ its islands'
    work, not s^3), :func:`lu_inplace` where that cannot vouch for its bits.
    Returns (ok, whether the last solve pulled on a row)."""
    m = K.shape[0]
    lam[:] = 0.0
    s = act.size
    for i in range(s):
        cur[i] = act[i]
    la = ra[:0]
    for npass in range(1, passes + 1):
        Ka = big[:s * s].reshape((s, s))
        la = ra[:s]
        _active_system(K, r, cur, s, eps_rel, Ka, la)
        det = lu_skip_inplace(Ka, la, nz)
        if det != det:  # not vouched for: the plain LU on the system again
            _active_system(K, r, cur, s, eps_rel, Ka, la)
            det = lu_inplace(Ka, la)
        if det == 0.0:
            return False, False
        npull = 0
        for i in range(s):
            if la[i] < 0.0:
                npull += 1
        if npull == 0 or npull == s or npass == passes:
            break
        q = 0  # the rows kept, compacted in place (q <= i)
        for i in range(s):
            if not la[i] < 0.0:
                cur[q] = cur[i]
                q += 1
        s = q
    for i in range(la.size):
        if not np.isfinite(la[i]):
            lam[:] = 0.0
            return False, False
    pulled = False
    for i in range(la.size):
        pulled |= la[i] < 0.0
        lam[cur[i]] = max(la[i], 0.0)
    return True, pulled


@njit(cache=True)
def dense_active_set(K, r, act, eps_rel, passes):
    """:func:`dense_active_set_into` into new arrays: (lam (m,), ok, pulled)."""
    m = K.shape[0]
    s = act.size
    lam = np.empty(m)
    ok, pulled = dense_active_set_into(K, r, act, eps_rel, passes, lam, np.empty(s, np.int64), np.empty(s * s),
                                       np.empty(s), np.empty(s, np.int64))
    return lam, ok, pulled


@njit(cache=True)
def body_rows_into(a, b, world, rows, cnt, ptr, idx):
    """CSR lists of the ``rows`` touching each dynamic body: (ptr (world+2,),
    idx) with positions into ``rows``, written into ``ptr`` and ``idx``
    (>= 2 rows.size,); ``cnt`` (world+1,) int64 scratch."""
    cnt[:] = 0
    for q in range(rows.size):
        i = rows[q]
        cnt[a[i]] += 1
        if b[i] != world:
            cnt[b[i]] += 1
    ptr[0] = 0
    for k in range(world + 1):
        ptr[k + 1] = ptr[k] + cnt[k]
    fill = cnt  # each body's next free slot
    for k in range(world + 1):
        fill[k] = ptr[k]
    for q in range(rows.size):
        i = rows[q]
        idx[fill[a[i]]] = q
        fill[a[i]] += 1
        if b[i] != world:
            idx[fill[b[i]]] = q
            fill[b[i]] += 1
    return ptr, idx[:ptr[world + 1]]


@njit(cache=True, inline="always")
def _side_range(a, b, world, ptr, i, side):
    """The slots [lo, hi) of body a[i] (side 0) or b[i] (side 1) in the
    CSR lists ``ptr`` of :func:`body_rows_into`; empty for the world."""
    body = a[i] if side == 0 else b[i]
    if body == world:
        return 0, 0
    return ptr[body], ptr[body + 1]


@njit(cache=True)
def _sort_by_key(key, val, k):
    """Sort key[:k] ascending in place (heapsort), val[:k] along; the keys
    are distinct, so the order is the one any sort (np.argsort) gives."""
    for end in range(k, 1, -1):
        start = end // 2 - 1 if end == k else 0
        for root0 in range(start, -1, -1):
            root = root0
            while True:
                c = 2 * root + 1
                if c >= end:
                    break
                if c + 1 < end and key[c + 1] > key[c]:
                    c += 1
                if key[c] <= key[root]:
                    break
                key[root], key[c] = key[c], key[root]
                val[root], val[c] = val[c], val[root]
                root = c
        key[0], key[end - 1] = key[end - 1], key[0]
        val[0], val[end - 1] = val[end - 1], val[0]


#: :func:`spd_solve_sparse_into`'s int64 work arrays (its doc)
SparseWork = namedtuple("SparseWork", ("cnt", "ptr", "idx", "deg", "visited", "order", "pos", "nbr", "nbr_key", "need"))


@njit(cache=True)
def spd_solve_sparse_into(J, M, a, b, world, r, rows, eps_rel, lam, y, band, work):
    """Solve K_aa lam = r_a over the rows ``rows`` (indices, ascending) with
    Tikhonov eps = eps_rel max diag(K_aa), K symmetric positive
    semi-definite and sparse (rows couple only through shared bodies).

    The rows split into islands by a breadth-first search over shared
    dynamic bodies that visits a row's neighbours by increasing degree
    (Cuthill-McKee), reversed; each island is then a band of the reordered
    K, factorised by banded Cholesky (cost ~ s bw^2 for an island of s rows
    and bandwidth bw: a column of spheres has bw 1-2).  Writes ``lam`` (m,)
    (zeros outside ``rows``); returns ok, False at a non-positive pivot.
    Scratch: ``y`` (>= s,), ``band`` (an island's band storage: a new array
    when it is shorter; ``need[0]`` is set to the most this call needed),
    and ``work`` (a :class:`SparseWork`): int64 ``cnt``, ``ptr``, ``idx`` as
    :func:`body_rows_into`, ``deg``, ``visited``, ``order``, ``pos``,
    ``nbr``, ``nbr_key`` (>= s,), ``need`` (1,)."""
    cnt, ptr, idx, deg, visited = work.cnt, work.ptr, work.idx, work.deg, work.visited
    order, pos, nbr, nbr_key, need = work.order, work.pos, work.nbr, work.nbr_key, work.need
    s = rows.size
    lam[:] = 0.0
    need[0] = 0
    if s == 0:
        return True
    ptr, idx = body_rows_into(a, b, world, rows, cnt, ptr, idx)
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
    visited[:s] = 0
    pos[:s] = -1
    head = 0
    for start in range(s):
        if visited[start]:
            continue
        c0 = head
        order[head] = start
        visited[start] = 1
        head += 1
        tail = c0
        while tail < head:
            q = order[tail]
            tail += 1
            k = 0
            i = rows[q]
            for side in range(2):
                lo, hi = _side_range(a, b, world, ptr, i, side)
                for t in range(lo, hi):
                    o = idx[t]
                    if not visited[o]:
                        visited[o] = 1
                        nbr[k] = o
                        nbr_key[k] = deg[o] * s + o
                        k += 1
            if k:
                _sort_by_key(nbr_key, nbr, k)
                for t in range(k):
                    order[head] = nbr[t]
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
                lo, hi = _side_range(a, b, world, ptr, i, side)
                for u in range(lo, hi):
                    d = abs(pos[idx[u]] - pos[q])
                    if d > bw:
                        bw = d
        # band storage: L[p, bw + (j - p)] for j in [p - bw, p]
        nl = n_c * (bw + 1)
        need[0] = max(need[0], nl)
        if nl <= band.size:
            L = band[:nl].reshape((n_c, bw + 1))
            _zero2(L)
        else:
            L = np.zeros((n_c, bw + 1))
        for t in range(c0, c1):
            q = order[t]
            p = t - c0
            i = rows[q]
            y[p] = r[i]
            for side in range(2):
                lo, hi = _side_range(a, b, world, ptr, i, side)
                for u in range(lo, hi):
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
                        return False
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
    return True


@njit(cache=True)
def spd_solve_sparse(J, M, a, b, world, r, rows, eps_rel):
    """:func:`spd_solve_sparse_into` into new arrays: (lam (m,), ok)."""
    m = J.shape[0]
    s = rows.size
    lam = np.empty(m)
    e = np.empty(s, np.int64)
    work = SparseWork(cnt=np.empty(world + 1, np.int64), ptr=np.empty(world + 2, np.int64),
                      idx=np.empty(2 * s, np.int64), deg=e, visited=np.empty(s, np.int64), order=np.empty(s, np.int64),
                      pos=np.empty(s, np.int64), nbr=np.empty(s, np.int64), nbr_key=np.empty(s, np.int64),
                      need=np.empty(1, np.int64))
    ok = spd_solve_sparse_into(J, M, a, b, world, r, rows, eps_rel, lam, np.empty(s), np.empty(0), work)
    return lam, ok


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
