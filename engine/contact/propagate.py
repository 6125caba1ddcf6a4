"""Compiled impulse propagation (the impact solver's binary collisions one
after another, engine/contact/impact.py ``_propagate``): the pair loop,
each pair's exact block solve of its normal rows (active sets enumerated
largest first) and its one-shot Coulomb friction impulse, in one call.

Bit for bit the numpy form it replaced (the engine's final states are
pinned): every sum is formed in the order numpy formed it --
:func:`_edot` is einsum's contiguous dot (two interleaved partial sums,
blocks of eight first), :func:`_colsum` einsum's strided one (in order),
:func:`_pwsum` ``ndarray.sum`` (pairwise, eight accumulators), and
:func:`hypot` CPython's ``math.hypot`` (its vector_norm: scaled, exact
squares, compensated sums and a corrected square root) -- pinned by
tests/test_impact_propagate.py against numpy and ``math.hypot``."""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from physbench.engine.contact import linalg
from physbench.engine.contact.rows import SLIP_TOL

#: :func:`propagate`'s scratch for :func:`_resolve`: each pair's normal
#: block ``K`` (G, k, k) and whether it is built (``have`` (G,)), each
#: patch's inverted friction block ``Kinv`` (np, nr, nr) and ``ok`` (np,),
#: a pair's targets ``tgt``, impulses ``lam`` and residual ``r`` (k,)
_Work = namedtuple("_Work", ("K", "have", "Kinv", "ok", "tgt", "lam", "r"))


@njit(cache=True)
def _edot(x, y, n):
    """sum x[i] y[i] (i < n) as numpy's einsum sums a contiguous dot:
    two lanes (even and odd i), blocks of eight first (each lane's four
    products added from the last), then pairs in order, the lanes added
    last."""
    l0 = 0.0
    l1 = 0.0
    i = 0
    while n - i >= 8:
        l0 = (((l0 + x[i + 6] * y[i + 6]) + x[i + 4] * y[i + 4]) + x[i + 2] * y[i + 2]) + x[i] * y[i]
        l1 = (((l1 + x[i + 7] * y[i + 7]) + x[i + 5] * y[i + 5]) + x[i + 3] * y[i + 3]) + x[i + 1] * y[i + 1]
        i += 8
    while i < n:
        l0 = l0 + x[i] * y[i]
        if i + 1 < n:
            l1 = l1 + x[i + 1] * y[i + 1]
        i += 2
    return l0 + l1


@njit(cache=True)
def _vn(J, r, U, a, b):
    """Normal speed of row r: J[r] (12,) . [U[a] | U[b]] (einsum
    "kj,kj->k" over the gathered pair velocities, :func:`_edot`'s order)."""
    l0 = 0.0
    l1 = 0.0
    for i in (6, 4, 2, 0):  # the block of eight: U[a] (6) and U[b]'s first two
        l0 = l0 + J[r, i] * (U[a, i] if i < 6 else U[b, i - 6])
        l1 = l1 + J[r, i + 1] * (U[a, i + 1] if i + 1 < 6 else U[b, i - 5])
    for i in (8, 10):
        l0 = l0 + J[r, i] * U[b, i - 6]
        l1 = l1 + J[r, i + 1] * U[b, i - 5]
    return l0 + l1


@njit(cache=True)
def _pwsum(x, n):
    """x[:n].sum() as numpy sums (pairwise: below eight in order, else
    eight accumulators; n <= 128)."""
    if n < 8:
        s = 0.0
        for i in range(n):
            s = s + x[i]
        return s
    r = np.empty(8)
    for j in range(8):
        r[j] = x[j]
    i = 8
    while i + 8 <= n:
        for j in range(8):
            r[j] = r[j] + x[i + j]
        i += 8
    s = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        s = s + x[i]
        i += 1
    return s


@njit(cache=True)
def _two_prod(x, y):
    """(x y, its rounding error) exactly (Dekker's product, what fma gives)."""
    z = x * y
    t = 134217729.0 * x
    xh = t - (t - x)
    xl = x - xh
    t = 134217729.0 * y
    yh = t - (t - y)
    yl = y - yh
    return z, ((xh * yh - z) + xh * yl + xl * yh) + xl * yl


@njit(cache=True)
def _vnorm(ax, ay, mx):
    scale = math.ldexp(1.0, -math.frexp(mx)[1])
    csum, frac1, frac2 = 1.0, 0.0, 0.0
    for v in (ax, ay):
        x = v * scale
        hi, lo = _two_prod(x, x)
        s = csum + hi
        frac2 += (csum - s) + hi
        csum = s
        frac1 += lo
    h = math.sqrt(csum - 1.0 + (frac1 + frac2))
    hi, lo = _two_prod(-h, h)
    s = csum + hi
    frac2 += (csum - s) + hi
    csum = s
    frac1 += lo
    x = csum - 1.0 + (frac1 + frac2)
    h += x / (2.0 * h)
    return h / scale


@njit(cache=True)
def hypot(x, y):
    """math.hypot(x, y) as CPython computes it (libm's hypot differs in
    the last bit in ~1 of 1000 cases)."""
    ax, ay = abs(x), abs(y)
    mx = 0.0
    if ax > mx:
        mx = ax
    if ay > mx:
        mx = ay
    if math.isinf(mx):
        return mx
    if math.isnan(x) or math.isnan(y):
        return math.nan
    if mx == 0.0:
        return mx
    if math.frexp(mx)[1] < -1023:
        tiny = 2.2250738585072014e-308
        return tiny * _vnorm(ax / tiny, ay / tiny, mx / tiny)
    return _vnorm(ax, ay, mx)


@njit(cache=True)
def _pair_matrix(J, M, idx, k, K):
    """K = J M^T over the rows idx[:k] of one pair (einsum "ik,jk->ij" of
    each body's half, added)."""
    for i in range(k):
        for j in range(k):
            ri, rj = idx[i], idx[j]
            K[i, j] = _edot(J[ri, 0:6], M[rj, 0:6], 6) + _edot(J[ri, 6:12], M[rj, 6:12], 6)


@njit(cache=True)
def _apply(U, a, b, M, idx, k, lam, world):
    """U[a] += MA^T lam, U[b] += MB^T lam (einsum "kj,k->j": in order)."""
    for j in range(6):
        s = 0.0
        for i in range(k):
            s = s + M[idx[i], j] * lam[i]
        U[a, j] = U[a, j] + s
    for j in range(6):
        s = 0.0
        for i in range(k):
            s = s + M[idx[i], 6 + j] * lam[i]
        U[b, j] = U[b, j] + s
    U[world, :] = 0.0


@njit(cache=True)
def block_normal(J, M, ab, idx, k, target, U, K, world, lam, r):
    """Exact normal impulses of the rows idx[:k] of ONE pair (the LCP
    lambda >= 0, K lambda >= r, lambda . (K lambda - r) = 0 with
    r = target - vn, by active sets largest first, projected Gauss-Seidel
    when none fits); applies them to U, leaves them in lam[:k]."""
    a, b = ab[idx[0], 0], ab[idx[0], 1]
    for i in range(k):
        ri = idx[i]
        r[i] = target[i] - (_edot(J[ri, 0:6], U[a], 6) + _edot(J[ri, 6:12], U[b], 6))
        lam[i] = 0.0
    if k == 1:
        K00, r0 = K[0, 0], r[0]
        if r0 <= 0.0:
            return
        if abs(K00) >= 1e-12 * max(1.0, abs(K00)):
            l0 = r0 / K00
            if l0 >= 0.0 and K00 * l0 - r0 >= -1e-9 * abs(r0):
                lam[0] = l0
                for j in range(6):
                    U[a, j] = U[a, j] + M[idx[0], j] * l0
                for j in range(6):
                    U[b, j] = U[b, j] + M[idx[0], 6 + j] * l0
                U[world, :] = 0.0
                return
    done = True
    scale = 0.0
    for i in range(k):
        done &= r[i] <= 0.0
        scale = max(scale, abs(r[i]))
    if done:
        return
    found = False
    S = np.empty(k, np.int64)
    trial = np.empty(k)
    for size in range(k, 0, -1):
        for i in range(size):  # the combinations of size rows, in itertools' order
            S[i] = i
        while True:
            KS = np.empty((size, size))
            rS = np.empty(size)
            big = 0.0
            for i in range(size):
                rS[i] = r[S[i]]
                for j in range(size):
                    KS[i, j] = K[S[i], S[j]]
                    big = max(big, abs(KS[i, j]))
            lS, det = linalg.lu_solve(KS, rS)
            if not abs(det) < 1e-12 * math.pow(max(1.0, big), float(size)):
                neg = False
                for i in range(size):
                    neg |= lS[i] < 0.0
                if not neg:
                    trial[:k] = 0.0
                    for i in range(size):
                        trial[S[i]] = lS[i]
                    fits = True
                    for i in range(k):
                        if not _edot(K[i], trial, k) - r[i] >= -1e-9 * scale:
                            fits = False
                            break
                    if fits:
                        for i in range(k):
                            lam[i] = trial[i]
                        found = True
                        break
            t = size - 1  # the next combination
            while t >= 0 and S[t] == k - size + t:
                t -= 1
            if t < 0:
                break
            S[t] += 1
            for i in range(t + 1, size):
                S[i] = S[i - 1] + 1
        if found:
            break
    if not found:  # degenerate: projected Gauss-Seidel on the block
        for _ in range(200):
            for i in range(k):
                v = lam[i] + (r[i] - _edot(K[i], lam, k)) / K[i, i]
                lam[i] = v if v > 0.0 else 0.0
    _apply(U, a, b, M, idx, k, lam, world)


@njit(cache=True)
def patch_impulse(f, rolling, p, Fn, U, world, Kinv, ok):
    """One-shot Coulomb friction impulse on patch p of the patches ``f``
    (an engine.contact.packs.ImpactPatches) after a normal impulse
    Fn (impact._propagate's doc): the impulse that stops its tangential
    and twist (and rolling) motion by the inverse of its block (Kinv[p],
    computed at the patch's first impulse: ok[p] 1 invertible, -1 not, 0
    not yet), kept within the static limits, else held to the kinetic
    ones; the rolling impulse to the mu_r Fn disc."""
    if Fn <= 0.0:
        return
    Jt, Mt, mt, pa, pb, mus, muk, r_twist, mur = f.Jt, f.Mt, f.mt, f.pa, f.pb, f.mus, f.muk, f.r_twist, f.mur
    nr = Jt.shape[1]
    a, b = pa[p], pb[p]
    if ok[p] == 0:
        K = np.empty((nr, nr))
        for i in range(nr):
            for j in range(nr):
                K[i, j] = _edot(Jt[p, i, 0:6], Mt[p, j, 0:6], 6) + _edot(Jt[p, i, 6:12], Mt[p, j, 6:12], 6)
        inv, good = linalg.inverse(K)
        ok[p] = 1 if good else -1
        if good:
            Kinv[p, :nr, :nr] = inv
    vt = np.empty(nr)
    d = np.empty(nr)
    for i in range(nr):
        vt[i] = _edot(Jt[p, i, 0:6], U[a], 6) + _edot(Jt[p, i, 6:12], U[b], 6)
    for i in range(nr):
        d[i] = -_edot(Kinv[p, i], vt, nr) if ok[p] == 1 else -vt[i] * mt[p, i]
    rt = r_twist[p]
    mu = muk[p] if (hypot(vt[0], vt[1]) > SLIP_TOL or abs(vt[2]) * rt > SLIP_TOL) else mus[p]
    mag = hypot(d[0], d[1])
    kin = muk[p] * Fn
    if mag > mu * Fn or (rt > 0.0 and abs(d[2]) > mu * Fn * rt):
        if mag > kin:
            f = kin / mag
            d[0] = d[0] * f
            d[1] = d[1] * f
        tl = kin * rt
        x = d[2]
        if -tl > x:
            x = -tl
        if tl < x:
            x = tl
        d[2] = x
    if nr > 3:
        lim = (mur[p] if rolling else 0.0) * Fn
        rmag = hypot(d[3], d[4])
        if rmag > lim:
            f = lim / rmag
            d[3] = d[3] * f
            d[4] = d[4] * f
    for j in range(6):
        l0 = 0.0
        l1 = 0.0
        for i in range(0, nr, 2):  # einsum "jk,k->j" over M^T's contiguous rows (nr < 8)
            l0 = l0 + Mt[p, i, j] * d[i]
            if i + 1 < nr:
                l1 = l1 + Mt[p, i + 1, j] * d[i + 1]
        U[a, j] = U[a, j] + (l0 + l1)
    for j in range(6):
        l0 = 0.0
        l1 = 0.0
        for i in range(0, nr, 2):
            l0 = l0 + Mt[p, i, 6 + j] * d[i]
            if i + 1 < nr:
                l1 = l1 + Mt[p, i + 1, 6 + j] * d[i + 1]
        U[b, j] = U[b, j] + (l0 + l1)
    U[world, :] = 0.0


@njit(cache=True)
def setup(code, ab, n, J, U):
    """The propagation's index arrays and speeds for rows of pair codes
    ``code`` (m,) between bodies ``ab`` (m, 2) (n the world), Jacobians J
    (m, 12), velocities U (n+1, 6), as impact._propagate formed them in
    numpy: inv (m,) the pair of each row (np.unique's inverse), go, gs
    (np.argsort(inv, stable), the cumulated counts: the rows of pair g are
    go[gs[g]:gs[g + 1]]), bo, b0 (the stable argsort of [a, b] modulo m and
    the cumulated counts over n + 1 bodies: the rows of body i are
    bo[b0[i]:b0[i + 1]]), vcur (m,) the rows' normal speeds (einsum
    "kj,kj->k" over the gathered pair, :func:`_vn`).  Returns (go, gs, inv,
    bo, b0, vcur) (tests/test_impact_propagate.py)."""
    m = code.shape[0]
    srt = np.argsort(code, kind="mergesort")
    inv = np.empty(m, np.int64)
    G = 0
    for t in range(m):
        if t == 0 or code[srt[t]] != code[srt[t - 1]]:
            G += 1
        inv[srt[t]] = G - 1
    gs = np.zeros(G + 1, np.int64)
    for r in range(m):
        gs[inv[r] + 1] += 1
    for g in range(G):
        gs[g + 1] += gs[g]
    go = np.empty(m, np.int64)
    pos = gs[:G].copy()
    for r in range(m):
        go[pos[inv[r]]] = r
        pos[inv[r]] += 1
    b0 = np.zeros(n + 2, np.int64)
    for r in range(2 * m):
        b0[ab[r % m, r // m] + 1] += 1
    for i in range(n + 1):
        b0[i + 1] += b0[i]
    bo = np.empty(2 * m, np.int64)
    posb = b0[:n + 1].copy()
    for r in range(2 * m):
        i = ab[r % m, r // m]
        bo[posb[i]] = r % m
        posb[i] += 1
    vcur = np.empty(m)
    for r in range(m):
        vcur[r] = _vn(J, r, U, ab[r, 0], ab[r, 1])
    return go, gs, inv, bo, b0, vcur


@njit(cache=True)
def propagate(mode, rows, groups, U, vcur, thr, friction, patches, rolling):
    """Impulse propagation over ``rows`` (an engine.contact.packs.ImpactRows;
    ``groups`` its ImpactGroups: the rows of each pair and of each body,
    the pair of each row) on U (n+1, 6) in place, with vcur (m,) the rows'
    normal speeds kept current; with ``friction`` the ImpactPatches
    ``patches`` (``rolling``: their rolling rows).  ``mode`` 0: the fastest
    approach above ``thr`` first,
    with restitution, until none is left (returns whether it settled
    within 20 solves per pair + 10); 1: the slow approaches stopped, three
    passes over the approaching pairs in order (returns True)."""
    m = vcur.shape[0]
    gs, inv = groups.gs, groups.inv
    Jt = patches.Jt
    G = gs.shape[0] - 1
    world = U.shape[0] - 1
    kmax = 1
    for g in range(G):
        kmax = max(kmax, gs[g + 1] - gs[g])
    K = np.zeros((G, kmax, kmax))
    have = np.zeros(G, np.bool_)
    npch = Jt.shape[0]
    nr = Jt.shape[1]
    Kinv = np.zeros((npch, nr, nr))
    ok = np.zeros(npch, np.int64)
    tgt = np.empty(kmax)
    lam = np.empty(kmax)
    r = np.empty(kmax)
    mark = np.zeros(G, np.bool_)
    work = _Work(K=K, have=have, Kinv=Kinv, ok=ok, tgt=tgt, lam=lam, r=r)
    if mode == 0:
        for _ in range(20 * G + 10):
            j = 0
            for i in range(1, m):
                if vcur[i] < vcur[j]:
                    j = i
            if vcur[j] >= -thr:
                return True
            _resolve(inv[j], bool(True), rows, groups, U, vcur, thr, friction, patches, rolling, work, world)
        return False
    for _ in range(3):
        any_slow = False
        mark[:] = False
        for i in range(m):
            if vcur[i] < -1e-12:
                mark[inv[i]] = True
                any_slow = True
        if not any_slow:
            break
        for g in range(G):
            if mark[g]:
                _resolve(g, bool(False), rows, groups, U, vcur, thr, friction, patches, rolling, work, world)
    return True


@njit(cache=True)
def _resolve(g, restitution, rows, groups, U, vcur, thr, friction, patches, rolling, work, world):
    """One pair's collision (pair ``g``; the arguments as
    :func:`propagate`'s, ``work`` its scratch): its normal block with
    restitution targets (or none), its friction impulse, the normal block
    again if friction left a row approaching, then its bodies' rows'
    speeds."""
    J, M, ab, e, pid = rows.J, rows.M, rows.ab, rows.e, rows.pid
    go, gs, bo, b0 = groups.go, groups.gs, groups.bo, groups.b0
    K, have, Kinv, ok, tgt, lam, r = work.K, work.have, work.Kinv, work.ok, work.tgt, work.lam, work.r
    idx = go[gs[g]:gs[g + 1]]
    k = idx.shape[0]
    if not have[g]:
        _pair_matrix(J, M, idx, k, K[g])
        have[g] = True
    for i in range(k):
        v = vcur[idx[i]]
        tgt[i] = -e[idx[i]] * v if (restitution and v < -thr) else 0.0
    block_normal(J, M, ab, idx, k, tgt, U, K[g], world, lam, r)
    if friction:
        Fn = _pwsum(lam, k)
        if Fn > 0:
            patch_impulse(patches, rolling, pid[idx[0]], Fn, U, world, Kinv, ok)
            again = False
            for i in range(k):
                v2 = _vn(J, idx[i], U, ab[idx[i], 0], ab[idx[i], 1])
                t0 = tgt[i] if (tgt[i] <= 0.0 or math.isnan(tgt[i])) else 0.0  # np.minimum(tgt, 0.0)
                again |= v2 < t0 - 1e-12
                z = v2 * 0.0
                tgt[i] = t0 if (t0 >= z or math.isnan(t0)) else z  # np.maximum(that, v2 * 0.0)
            if again:
                block_normal(J, M, ab, idx, k, tgt, U, K[g], world, lam, r)
    i, j = ab[idx[0], 0], ab[idx[0], 1]
    for u in range(b0[i], b0[i + 1]):
        q = bo[u]
        vcur[q] = _vn(J, q, U, ab[q, 0], ab[q, 1])
    if j != world:
        for u in range(b0[j], b0[j + 1]):
            q = bo[u]
            vcur[q] = _vn(J, q, U, ab[q, 0], ab[q, 1])
