"""The contact solve's phases after preparation as ONE compiled call
(``solve_contacts``), named as Box2D's contact_solver.h names its own:
slip classification, warm start (``warm_match`` then ``warm_apply``),
direct start, solve (Gauss-Seidel sweeps with the static/kinetic switch),
store of the velocities, relax (split-impulse position correction).

Each phase is the same arithmetic, in the same order, as the Python
driver it replaces (``rows.Rows.direct_normal_guess``,
``solve_friction_regimes``, ``warm.warm_start``, ``Rows.unpack``), so the
bits are those of the per-phase calls (the determinism pins of
tests/test_determinism.py hold unchanged).  The normal rows' velocity
residual r = target - J U is summed as numpy's einsum sums a row of six
products (two interleaved partial sums, then added): see ``_row_residual``.

Velocities: U (n+1, 6) = [v | w] with the world's row n zero; arrays and
conventions as in :mod:`engine.contact.gauss_seidel` and
:mod:`engine.contact.prepare`.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit
from numba.extending import register_jitable

from physbench.engine.contact import gauss_seidel, linalg, warm
from physbench.engine.contact.packs import Bodies, NormalRows, Patches, PatchSet, Settings, Work  # noqa: F401
from physbench.engine.contact.prepare import classify, rows as prepare_rows, sliding, targets as prepare_targets

_EPS_REL = linalg.EPS_REL  # a module global: numba compiles it in as a constant

#: the direct start's int64 work (after the band need, slot 0): act, cur,
#: rows, idx (2), deg, order, pos, nbr, nbr_key, visited rows (m,) each
_DI_ROWS = 11


@register_jitable  # plain Python when called from Python (no dispatch)
def direct_work_size(m, world, dense, band):
    """(floats, ints): lengths of the direct start's work arrays ``dwf`` and
    ``dwi`` for m normal rows and ``world`` dynamic bodies
    (:func:`direct_layout`): the dense start's two (m, m) matrices, else
    ``band`` floats of band storage for the sparse one's islands."""
    return 3 * m + 6 * (world + 1) + (2 * m * m if dense else band), 1 + _DI_ROWS * m + 2 * world + 3


#: the direct start's float work (:func:`direct_layout`): lam, ra, w (m,),
#: dU (world+1, 6), big (the rest: the dense K and K_aa, or the sparse band)
DirectFloats = namedtuple("DirectFloats", ("lam", "ra", "w", "dU", "big"))
#: the direct start's int64 work (:func:`direct_layout`): need (1,) (the
#: band storage the last sparse start needed: slot 0 of ``dwi``), act, cur,
#: rows (m,), cnt (world+1,), ptr (world+2,), idx (2m,), deg, order, pos,
#: nbr, nbr_key, visited (m,)
DirectInts = namedtuple("DirectInts", ("need", "act", "cur", "rows", "cnt", "ptr", "idx", "deg", "order", "pos", "nbr",
                                       "nbr_key", "visited"))


@njit(cache=True, inline="always")
def direct_layout(dwf, dwi, m, world):
    """The views of the direct start's work arrays (:func:`direct_work_size`)
    as a :class:`DirectFloats` and a :class:`DirectInts`."""
    o = 3 * m + 6 * (world + 1)
    f = DirectFloats(lam=dwf[:m], ra=dwf[m:2 * m], w=dwf[2 * m:3 * m], dU=dwf[3 * m:o].reshape((world + 1, 6)),
                     big=dwf[o:])
    c0 = 1 + 3 * m
    c1 = c0 + world + 1
    c2 = c1 + world + 2
    c3 = c2 + 2 * m
    g = DirectInts(need=dwi[:1], act=dwi[1:1 + m], cur=dwi[1 + m:1 + 2 * m], rows=dwi[1 + 2 * m:c0], cnt=dwi[c0:c1],
                   ptr=dwi[c1:c2], idx=dwi[c2:c3], deg=dwi[c3:c3 + m], order=dwi[c3 + m:c3 + 2 * m],
                   pos=dwi[c3 + 2 * m:c3 + 3 * m], nbr=dwi[c3 + 3 * m:c3 + 4 * m], nbr_key=dwi[c3 + 4 * m:c3 + 5 * m],
                   visited=dwi[c3 + 5 * m:c3 + 6 * m])
    return f, g


@njit(cache=True, inline="always")
def _pack(U, V, W):
    for i in range(U.shape[0]):
        for k in range(3):
            U[i, k] = V[i, k]
            U[i, 3 + k] = W[i, k]


@njit(cache=True, inline="always")
def _unpack(U, V, W):
    """V, W (n+1, 3) = U's halves, the world row n zeroed."""
    nb = U.shape[0]
    for i in range(nb):
        for k in range(3):
            V[i, k] = U[i, k]
            W[i, k] = U[i, 3 + k]
    for k in range(3):
        V[nb - 1, k] = 0.0
        W[nb - 1, k] = 0.0


@njit(cache=True, inline="always")
def _dot6(J, i, c0, U, j):
    """J[i, c0:c0+6] . U[j] summed as numpy's einsum does for six
    products: (p0 + p2 + p4) + (p1 + p3 + p5)."""
    e = J[i, c0] * U[j, 0]
    o = J[i, c0 + 1] * U[j, 1]
    e = e + J[i, c0 + 2] * U[j, 2]
    o = o + J[i, c0 + 3] * U[j, 3]
    e = e + J[i, c0 + 4] * U[j, 4]
    o = o + J[i, c0 + 5] * U[j, 5]
    return e + o


@njit(cache=True)
def _row_residual(J, U0, a, b, target, r):
    """r = target - (JA . U0[a] + JB . U0[b]) (m,)."""
    for i in range(r.shape[0]):
        r[i] = target[i] - (_dot6(J, i, 0, U0, a[i]) + _dot6(J, i, 6, U0, b[i]))


@njit(cache=True)
def _lcp_res(J, M, a, b, world, r, lam, dU, w):
    """Complementarity residual of ``lam`` for K lam >= r, lam >= 0
    (as rows.Rows._lcp_residual); ``dU`` (world+1, 6), ``w`` (m,) scratch."""
    w = linalg.k_times_into(J, M, a, b, world, lam, dU, w)
    for i in range(w.shape[0]):
        w[i] = w[i] - r[i]
    return linalg.lcp_residual(w, lam)


@njit(cache=True)
def direct_start(U, work, t, world, friction, resting, max_rows, passes):
    """The direct start (rows.Rows.direct_normal_guess) of the rows in the
    :class:`engine.contact.packs.Work` ``work`` (topology ``t``, a
    :class:`engine.contact.packs.Topo`) at the velocities ``U`` (n+1, 6):
    the normal rows not separating (r = target - J U, with the warm
    friction impulses applied, above -``resting``) solved as equalities --
    dense active set up to ``max_rows`` rows, sparse banded Cholesky per
    island above -- and kept in ``lam_n`` when their complementarity
    residual beats the warm start's.  ``work.Ud`` (n+1, 6) and
    ``work.r_direct`` (m,) scratch; ``work.dwf``, ``work.dwi`` its work arrays
    (:func:`direct_work_size`: nothing is allocated when they are long
    enough, tests/test_engine_steady.py::
    test_steady_direct_start_allocates_nothing; shorter ones are replaced
    by new arrays, the same bits)."""
    rw = work.rows
    J, M, lam_n, target, Mt, lam_t = rw.J, rw.M, rw.lam_n, rw.target, rw.Mt, rw.lam_t
    a, b, pab = t.a, t.b, t.pab
    U0, r, dwf, dwi = work.Ud, work.r_direct, work.dwf, work.dwi
    m = lam_n.shape[0]
    dense = m <= max_rows
    nf, ni = direct_work_size(m, world, dense, 0)  # the band: new when short
    if dwf.size < nf or dwi.size < ni:
        dwf = np.empty(nf)
        dwi = np.empty(ni, np.int64)
    df, di = direct_layout(dwf, dwi, m, world)
    lam, ra, w, dU, big = df.lam, df.ra, df.w, df.dU, df.big
    need, act, cur, rows, cnt, ptr, idx = di.need, di.act, di.cur, di.rows, di.cnt, di.ptr, di.idx
    need[0] = 0
    U0[:, :] = U
    if friction:
        gauss_seidel.apply_patches(U0, pab, Mt, lam_t, world)
    _row_residual(J, U0, a, b, target, r)
    k = 0
    pos_ = False
    for i in range(m):
        if r[i] > -resting:
            k += 1
            if r[i] > 0.0:
                pos_ = True
    if k == 0 or not pos_:
        return
    act = act[:k]
    k = 0
    for i in range(m):
        if r[i] > -resting:
            act[k] = i
            k += 1
    if not dense:
        ok = linalg.spd_solve_sparse_into(J, M, a, b, world, r, act, _EPS_REL, lam, ra, big, linalg.SparseWork(
            cnt=cnt, ptr=ptr, idx=idx, deg=di.deg, visited=di.visited, order=di.order, pos=di.pos, nbr=di.nbr,
            nbr_key=di.nbr_key, need=need))
        for i in range(m):
            if lam[i] < 0.0:
                lam[i] = 0.0
    else:
        if big.size < 2 * m * m:
            big = np.empty(2 * m * m)
        K = big[:m * m].reshape((m, m))
        linalg.normal_matrix_into(J, M, a, b, world, K, rows, cnt, ptr, idx)
        # ``rows`` is free once K is built: the LU's scratch
        ok, _ = linalg.dense_active_set_into(K, r, act, _EPS_REL, passes, lam, cur, big[m * m:], ra, rows)
    if not ok:
        return
    for i in range(m):
        if not np.isfinite(lam[i]):
            return
    if _lcp_res(J, M, a, b, world, r, lam, dU, w) <= _lcp_res(J, M, a, b, world, r, lam_n, dU, w):
        lam_n[:] = lam


@njit(cache=True)
def friction_regimes(U, w, t, friction, iterations, tol, world):
    """The solve phase (rows.Rows.solve_friction_regimes) of the rows in
    the :class:`engine.contact.packs.Work` ``w`` (topology ``t``, a
    :class:`engine.contact.packs.Topo`): sweeps with mu_s for sticking
    patches; a patch whose friction (or twist) ends on its mu_s limit
    switches to mu_k and the rows are swept again (at most twice);
    ``w.wk`` the sweeps' work array (engine.contact.gauss_seidel), the
    sweeps' pins ``w.pin_t``, ``w.dir_t`` (for the rolling rows too).
    Returns (sweeps done, the last sweep's relative residual)."""
    rw = w.rows
    lam_n, lam_t, mu, rt, slip = rw.lam_n, rw.lam_t, rw.mu, rw.rt, rw.slip
    pid, mus, muk = t.pid, t.mus, t.muk
    wk = w.wk
    normal = NormalRows(ab=t.ab, J=rw.J, M=rw.M, mn=rw.mn, lam=lam_n, target=rw.target)
    patches = Patches(pab=t.pab, pid=pid, Jt=rw.Jt, Mt=rw.Mt, mt=rw.mt, lam_t=lam_t, mu=mu, rt=rt, mur=t.mur,
                      pin_t=w.pin_t, dir_t=w.dir_t, pin_r=w.pin_t, dir_r=w.dir_t)
    sw, residual = gauss_seidel.iterate(U, normal, patches, friction, iterations, tol, world, wk)
    if not friction:
        return sw, residual
    npch = lam_t.shape[0]
    Fn = gauss_seidel.work_layout(wk, lam_n.shape[0], npch, lam_t.shape[1])[4]
    for _ in range(2):
        Fn[:] = 0.0
        for i in range(pid.shape[0]):
            Fn[pid[i]] += lam_n[i]
        any_sat = False
        for p in range(npch):
            mag = math.sqrt(lam_t[p, 0] * lam_t[p, 0] + lam_t[p, 1] * lam_t[p, 1])
            lim = mus[p] * Fn[p] * (1 - 1e-6)
            sat = (not slip[p]) and mus[p] > muk[p] and Fn[p] > 0 and (
                mag >= lim or (rt[p] > 0.0 and abs(lam_t[p, 2]) >= lim * rt[p]))
            if sat:
                slip[p] = True
                any_sat = True
        if not any_sat:
            break
        for p in range(npch):
            mu[p] = muk[p] if slip[p] else mus[p]
        s2, residual = gauss_seidel.iterate(U, normal, patches, friction, iterations, tol, world, wk)
        sw += s2
    return sw, residual


@njit(cache=True)
def solve_contacts(pose, t, w, ko, s, warm_on, h, tol):
    """The solve of prepared rows, phase by phase (module doc), on the
    named tuples of engine.contact.packs: ``pose`` the :class:`Pose`,
    ``t`` the :class:`Topo`, ``w`` the :class:`Work`, ``s`` the
    :class:`Settings`; ``ko`` the warm cache read (a Pack of a
    :class:`Cache`).  Slip classification at the start velocities V0, W0
    (n, 3) (``w.vt0`` (np, 2), ``slip`` (np,), ``mu``), the warm start
    matched from the cache (``warm_on``), the direct start
    (``s.direct``), the warm impulses applied, the sweeps with the
    static/kinetic switch (relative tolerance ``tol``), and the end
    velocities written to V, W (n+1, 3) from ``w.U`` (packed here from V,
    W).  ``w.U0`` (n+1, 6) is left holding the start velocities (with
    friction); ``Ud``, ``r_direct``, ``matched``, ``wk`` (the sweeps' work
    array) scratch; ``pin_t``/``dir_t`` the (unset: all False) pins of
    the sweeps.  Returns (sweeps, residual)."""
    V, W, V0, W0 = pose.V, pose.W, pose.V0, pose.W0
    U, U0 = w.U, w.U0
    rw = w.rows
    lam_n, lam_t, mu, slip = rw.lam_n, rw.lam_t, rw.mu, rw.slip
    friction = s.friction
    nb = world = pose.X.shape[0]
    if friction:
        # slip classification at the start of the step (prepare.sliding)
        for i in range(nb):
            for k in range(3):
                U0[i, k] = V0[i, k]
                U0[i, 3 + k] = W0[i, k]
        for k in range(6):
            U0[nb, k] = 0.0
        sliding(rw.Jt, U0, t.pab, rw.rt, s.slip_tol, w.vt0, slip)
        mus, muk = t.mus, t.muk
        for p in range(mu.shape[0]):
            mu[p] = muk[p] if slip[p] else mus[p]
    _pack(U, V, W)
    if warm_on:
        warm.match(t.codes, rw.loc, t.a, pose.bound_radius, ko, h, lam_n, friction, friction and s.rolling, t.pid,
                   rw.t, lam_t, w.matched)
    if s.direct:
        direct_start(U, w, t, world, friction, s.resting, s.max_rows, s.passes)
    if warm_on or s.direct:
        if lam_n.shape[0]:
            gauss_seidel.apply_rows(U, t.ab, rw.M, lam_n, world)
            if friction:
                gauss_seidel.apply_patches(U, t.pab, rw.Mt, lam_t, world)
    sw, residual = friction_regimes(U, w, t, friction, s.iterations, tol, world)
    _unpack(U, V, W)
    return sw, residual


@njit(cache=True)
def relax(Vp, Wp, Up, ab, J, M, mn, lam_p, bias, iterations, tol, world, wk):
    """Split-impulse position correction: normal rows swept on the pseudo
    velocities Vp, Wp (n+1, 3) towards the push-out ``bias`` with their
    own accumulator ``lam_p`` (zeroed here); ``Up``, ``wk`` (>= m,) scratch."""
    lam_p[:] = 0.0
    _pack(Up, Vp, Wp)
    gauss_seidel.iterate_normal(Up, ab, J, M, mn, lam_p, bias, iterations, tol, world, wk)
    _unpack(Up, Vp, Wp)


@njit(cache=True)
def solve_stage(kc, kt, kw, ko, kq, kk, idx, touching, vn, h, s, warm_on, store_on):
    """The solve stage after classification as ONE compiled call: the
    rows (:func:`engine.contact.prepare.rows`), their targets
    (:func:`engine.contact.prepare.targets`), :func:`solve_contacts`,
    :func:`relax` (``s.relax_on`` and a row to push out) and the warm
    cache's store (``store_on``, :func:`engine.contact.warm.store`), in
    that order, the same calls as the stage made one by one (the same
    bits).  The kept arrays come as :class:`engine.pack.Pack` s (one
    pointer each to unbox) of the named tuples of engine.contact.packs:
    ``kc`` the :class:`Pose` (V, W the end velocities, V0, W0 the start
    ones, Vp, Wp the pseudo velocities), ``kt`` the :class:`Topo`, ``kw``
    the :class:`Work`, ``ko``/``kq`` the warm :class:`Cache` read and the
    one written, ``kk`` the stage's :class:`ContactArrays`; ``idx`` (m,)
    the rows' contacts in row order, ``touching`` (k,) and ``vn`` (3, k)
    from the classification; ``s`` the :class:`Settings`.  Returns
    (sweeps, residual, whether a row pushes out)."""
    pose, t, w, c = kc.items, kt.items, kw.items, kk.items
    rw = w.rows
    nb = pose.X.shape[0]
    bodies = Bodies(X=pose.X, Iinv=pose.Iinv, inv_mass=pose.inv_mass, R0=pose.R0)
    prepare_rows(bodies, bool(True), c, idx, nb, rw, PatchSet(pid=t.pid, pa=t.pa, pb=t.pb, cnt=t.cnt, mus=t.mus),
                 s.friction, s.rolling)
    pushed = prepare_targets(idx, touching, vn, c.gap, c.e, h, s.lever, s.thr, s.beta, s.slop, rw.target, w.bias)
    sw, residual = solve_contacts(pose, t, w, ko, s, warm_on, h, 1e-7)
    if s.relax_on and pushed > 0:
        relax(pose.Vp, pose.Wp, w.Up, t.ab, rw.J, rw.M, rw.mn, w.lam_p, w.bias, s.iterations, 1e-7, nb, w.wk)
    if store_on:
        touch_rows = w.touch_rows
        for i in range(idx.shape[0]):
            touch_rows[i] = touching[idx[i]]
        warm.store(t.code_order, t.codes, rw.loc, rw.lam_n, touch_rows, t.code_first, t.uniq_pid, s.friction,
                   s.rolling, rw.lam_t, rw.t, h, kq)
    return sw, residual, pushed


@njit(cache=True)
def classify_stage(kc, kx, kt, kw, ko, kq, kk, key, idx, h, s, warm_any, fast, warm_on, store_on):
    """The whole solve stage of a steady step as ONE compiled call: the
    classification (:func:`engine.contact.prepare.classify`) and, when it
    finds no impact row (``fast``: the caller may go on) and its pair codes
    equal ``key`` (m,) (the pair codes, in contact order, of the topology
    the packs were built for: the contact graph is unchanged),
    :func:`solve_stage` over the rows ``idx`` (m,) (the topology's colour
    order).  The same calls in the same order as the stage makes them one
    by one (the same bits).  ``kc``, ``kt``, ``kw``, ``kq``, ``s`` as in
    :func:`solve_stage`; ``kx`` the :class:`engine.contact.packs.Classified`
    (the free flight's mean velocities and the classification's outputs),
    ``kk`` the contacts; ``ko`` the last solve's warm cache (empty without
    one; ``warm_any`` whether there is one, ``warm_on`` whether the solve
    warm-starts from it).  Returns (impact rows, solved, sweeps, residual,
    whether a row pushes out, whether a patch slides); when not ``solved``
    the caller goes on from the classification."""
    nimp = classify(kc, kx, kk, ko, s.n_statics, h, s.thr, s.lever, s.slop, warm_any)
    cl = kx.items
    codes = cl.codes
    m = codes.shape[0]
    if nimp > 0 or not fast or key.shape[0] != m:
        return nimp, False, 0, 0.0, 0, False
    for i in range(m):
        if codes[i] != key[i]:
            return nimp, False, 0, 0.0, 0, False
    sw, residual, pushed = solve_stage(kc, kt, kw, ko, kq, kk, idx, cl.touching, cl.vn, h, s, warm_on, store_on)
    slip = kw.items.rows.slip
    sliding_any = False
    for p in range(slip.shape[0]):
        if slip[p]:
            sliding_any = True
            break
    return nimp, True, sw, residual, pushed, sliding_any
