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

import numpy as np
from numba import njit
from numba.extending import register_jitable

from physbench.engine.contact import gauss_seidel, linalg, warm
from physbench.engine.contact.prepare import classify, rows as prepare_rows, sliding, targets as prepare_targets

_EPS_REL = linalg.EPS_REL  # a module global: numba compiles it in as a constant

#: the solve stage's work arrays in the order of its work Pack ``kw``
#: (engine.solver._work_items builds it in this order and checks its length)
WORK = ("J", "M", "mn", "loc", "lam_n", "target", "P", "N", "rt", "t", "Jt", "Mt", "mt", "lam_t", "slip", "mu", "U",
        "U0", "Ud", "vt0", "pin_t", "dir_t", "matched", "r_direct", "bias", "Up", "lam_p", "touch_rows", "wk", "dwf",
        "dwi")
#: where ``kw.items`` holds the patches' slip flags (np,) bool
W_SLIP = WORK.index("slip")


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


@njit(cache=True, inline="always")
def direct_layout(dwf, dwi, m, world):
    """The views of the direct start's work arrays (:func:`direct_work_size`):
    floats lam, ra (m,), w (m,), dU (world+1, 6), big (the rest: the dense
    K and K_aa, or the sparse band); ints need (1,) (the band storage the
    last sparse start needed), act, cur, rows (m,), cnt (world+1,), ptr
    (world+2,), idx (2m,), deg, order, pos, nbr, nbr_key, visited (m,)."""
    o = 3 * m + 6 * (world + 1)
    f = (dwf[:m], dwf[m:2 * m], dwf[2 * m:3 * m], dwf[3 * m:o].reshape((world + 1, 6)), dwf[o:])
    c0 = 1 + 3 * m
    c1 = c0 + world + 1
    c2 = c1 + world + 2
    c3 = c2 + 2 * m
    g = (dwi[:1], dwi[1:1 + m], dwi[1 + m:1 + 2 * m], dwi[1 + 2 * m:c0], dwi[c0:c1], dwi[c1:c2], dwi[c2:c3],
         dwi[c3:c3 + m], dwi[c3 + m:c3 + 2 * m], dwi[c3 + 2 * m:c3 + 3 * m], dwi[c3 + 3 * m:c3 + 4 * m],
         dwi[c3 + 4 * m:c3 + 5 * m], dwi[c3 + 5 * m:c3 + 6 * m])
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
def direct_start(U, U0, ab, J, M, a, b, world, lam_n, target, friction, pab, Mt, lam_t, resting, max_rows,
                 passes, r, dwf, dwi):
    """The direct start (rows.Rows.direct_normal_guess): the normal rows
    not separating (r = target - J U, with the warm friction impulses
    applied, above -``resting``) solved as equalities -- dense active set
    up to ``max_rows`` rows, sparse banded Cholesky per island above --
    and kept in ``lam_n`` when their complementarity residual beats the
    warm start's.  ``U0`` (n+1, 6) and ``r`` (m,) scratch; ``dwf``, ``dwi``
    its work arrays (:func:`direct_work_size`: nothing is allocated when
    they are long enough, tests/test_engine_steady.py::
    test_steady_direct_start_allocates_nothing; shorter ones are replaced
    by new arrays, the same bits)."""
    m = lam_n.shape[0]
    dense = m <= max_rows
    nf, ni = direct_work_size(m, world, dense, 0)  # the band: new when short
    if dwf.size < nf or dwi.size < ni:
        dwf = np.empty(nf)
        dwi = np.empty(ni, np.int64)
    (lam, ra, w, dU, big), (need, act, cur, rows, cnt, ptr, idx, deg, order, pos, nbr, nbr_key, visited) = \
        direct_layout(dwf, dwi, m, world)
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
        ok = linalg.spd_solve_sparse_into(J, M, a, b, world, r, act, _EPS_REL, lam, ra, big, cnt, ptr, idx, deg,
                                          visited, order, pos, nbr, nbr_key, need)
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
def friction_regimes(U, ab, J, M, mn, lam_n, target, friction, pab, pid, Jt, Mt, mt, lam_t, mu, mus, muk, rt,
                     mur, slip, pin_t, dir_t, pin_r, dir_r, iterations, tol, world, wk):
    """The solve phase (rows.Rows.solve_friction_regimes): sweeps with
    mu_s for sticking patches; a patch whose friction (or twist) ends on
    its mu_s limit switches to mu_k and the rows are swept again (at most
    twice); ``wk`` the sweeps' work array (engine.contact.gauss_seidel).  Returns
    (sweeps done, the last sweep's relative residual)."""
    sw, residual = gauss_seidel.iterate(U, ab, J, M, mn, lam_n, target, friction, pab, pid, Jt, Mt, mt, lam_t, mu, rt,
                                  mur, pin_t, dir_t, pin_r, dir_r, iterations, tol, world, wk)
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
        s2, residual = gauss_seidel.iterate(U, ab, J, M, mn, lam_n, target, friction, pab, pid, Jt, Mt, mt, lam_t, mu,
                                      rt, mur, pin_t, dir_t, pin_r, dir_r, iterations, tol, world, wk)
        sw += s2
    return sw, residual


@njit(cache=True)
def solve_contacts(V, W, V0, W0, U, U0, Ud, ab, J, M, mn, lam_n, target, world, friction, rolling, pab, pid, Jt, Mt,
                   mt, lam_t, mu, mus, muk, mur, rt, slip, vt0, t, slip_tol, warm_on, codes, loc, a, b,
                   bound_radius, o_code, o_loc, o_fn, u_code, u_ft, u_tw, u_rr, h, matched, direct, resting,
                   max_rows, passes, r, pin_t, dir_t, iterations, tol, wk, dwf, dwi):
    """The solve of prepared rows, phase by phase (module doc): slip
    classification at the start velocities V0, W0 (n, 3) (``vt0`` (np, 2),
    ``slip`` (np,), ``mu``), the warm start matched from the cache
    (``warm_on``; the ``o_``/``u_`` arrays of engine.contact.warm), the
    direct start (``direct``), the warm impulses applied, the sweeps with
    the static/kinetic switch, and the end velocities written to V, W
    (n+1, 3) from ``U`` (packed here from V, W).  ``U0`` (n+1, 6) is left
    holding the start velocities (with friction); ``Ud``, ``r``,
    ``matched``, ``wk`` (the sweeps' work array) scratch; ``pin_t``/``dir_t``
    the (unset: all False) pins of the sweeps.  Returns (sweeps, residual)."""
    nb = world
    if friction:
        # slip classification at the start of the step (prepare.sliding)
        for i in range(nb):
            for k in range(3):
                U0[i, k] = V0[i, k]
                U0[i, 3 + k] = W0[i, k]
        for k in range(6):
            U0[nb, k] = 0.0
        sliding(Jt, U0, pab, rt, slip_tol, vt0, slip)
        for p in range(mu.shape[0]):
            mu[p] = muk[p] if slip[p] else mus[p]
    _pack(U, V, W)
    if warm_on:
        warm.match(codes, loc, a, bound_radius, o_code, o_loc, o_fn, u_code, u_ft, u_tw, u_rr, h, lam_n, friction,
                   friction and rolling, pid, t, lam_t, matched)
    if direct:
        direct_start(U, Ud, ab, J, M, a, b, world, lam_n, target, friction, pab, Mt, lam_t, resting, max_rows,
                     passes, r, dwf, dwi)
    if warm_on or direct:
        if lam_n.shape[0]:
            gauss_seidel.apply_rows(U, ab, M, lam_n, world)
            if friction:
                gauss_seidel.apply_patches(U, pab, Mt, lam_t, world)
    sw, residual = friction_regimes(U, ab, J, M, mn, lam_n, target, friction, pab, pid, Jt, Mt, mt, lam_t, mu,
                                    mus, muk, rt, mur, slip, pin_t, dir_t, pin_t, dir_t, iterations, tol, world, wk)
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
def solve_stage(kc, kt, kw, ko, kq, ca, cb, point, normal, gap, e, idx, touching, vn, h, lever, thr, beta, slop,
                friction, rolling, warm_on, direct, resting, max_rows, passes, slip_tol, iterations, relax_on,
                store_on):
    """The solve stage after classification as ONE compiled call: the
    rows (:func:`engine.contact.prepare.rows`), their targets
    (:func:`engine.contact.prepare.targets`), :func:`solve_contacts`,
    :func:`relax` (``relax_on`` and a row to push out) and the warm
    cache's store (``store_on``, :func:`engine.contact.warm.store`), in
    that order, the same calls as the stage made one by one (the same
    bits).  The kept arrays come as :class:`engine.pack.Pack` s (one
    pointer each to unbox): ``kc`` the pose and velocities (X (n, 3),
    Iinv (n+1, 3, 3), R0 (n, 3, 3), V, W (n+1, 3) the end velocities,
    V0, W0 (n, 3) the start ones, Vp, Wp (n+1, 3) the pseudo velocities,
    inverse masses (n+1,), bounding radii (n,)); ``kt`` the topology's
    arrays; ``kw`` the rows' and the solve's work arrays; ``ko``/``kq``
    the warm cache read and the one written (engine.contact.warm's
    ``o_``/``u_`` arrays, then the touch flags).  The stage's contacts
    (``ca``, ``cb``, ``point``, ``normal``, ``gap``, ``e``), ``idx`` (m,)
    the rows' contacts in row order, ``touching`` and ``vn`` from the
    classification.  Returns (sweeps, residual, whether a row pushes out)."""
    X, Iinv, R0, V, W, V0, W0, Vp, Wp, inv_mass, bound_radius = kc.items
    ab, a, b, pid, pa, pb, cnt, pab, codes, code_order, code_first, uniq_pid, mus, muk, mur = kt.items
    (J, M, mn, loc, lam_n, target, P, N, rt, t, Jt, Mt, mt, lam_t, slip, mu, U, U0, Ud, vt0, pin_t, dir_t, matched,
     r_direct, bias, Up, lam_p, touch_rows, wk, dwf, dwi) = kw.items
    o_code, o_loc, o_fn, u_code, u_ft, u_tw, u_rr, _ = ko.items
    nb = X.shape[0]
    prepare_rows(X, Iinv, inv_mass, R0, bool(True), ca, cb, point, normal, idx, nb, J, M, mn, loc, lam_n, target,
                 friction, pid, pa, pb, cnt, rolling, P, N, rt, t, Jt, Mt, mt, lam_t, slip, mu, mus)
    pushed = prepare_targets(idx, touching, vn, gap, e, h, lever, thr, beta, slop, target, bias)
    sw, residual = solve_contacts(V, W, V0, W0, U, U0, Ud, ab, J, M, mn, lam_n, target, nb, friction, rolling, pab,
                                  pid, Jt, Mt, mt, lam_t, mu, mus, muk, mur, rt, slip, vt0, t, slip_tol, warm_on,
                                  codes, loc, a, b, bound_radius, o_code, o_loc, o_fn, u_code, u_ft, u_tw, u_rr, h,
                                  matched, direct, resting, max_rows, passes, r_direct, pin_t, dir_t, iterations,
                                  1e-7, wk, dwf, dwi)
    if relax_on and pushed > 0:
        relax(Vp, Wp, Up, ab, J, M, mn, lam_p, bias, iterations, 1e-7, nb, wk)
    if store_on:
        q_code, q_loc, q_fn, q_pairs, q_ft, q_tw, q_rr, q_touch = kq.items
        for i in range(idx.shape[0]):
            touch_rows[i] = touching[idx[i]]
        warm.store(code_order, codes, loc, lam_n, touch_rows, code_first, uniq_pid, friction, rolling, lam_t, t, h,
                   q_code, q_loc, q_fn, q_touch, q_pairs, q_ft, q_tw, q_rr)
    return sw, residual, pushed


@njit(cache=True)
def classify_stage(kc, kx, kt, kw, ko, kq, kk, key, idx, n_statics, h, lever, thr,
                   beta, slop, warm_any, fast, friction, rolling, warm_on, direct, resting, max_rows, passes, slip_tol,
                   iterations, relax_on, store_on):
    """The whole solve stage of a steady step as ONE compiled call: the
    classification (:func:`engine.contact.prepare.classify`) and, when it
    finds no impact row (``fast``: the caller may go on) and its pair codes
    equal ``key`` (m,) (the pair codes, in contact order, of the topology
    the packs were built for: the contact graph is unchanged),
    :func:`solve_stage` over the rows ``idx`` (m,) (the topology's colour
    order).  The same calls in the same order as the stage makes them one
    by one (the same bits).  ``kc``, ``kt``, ``kw``, ``kq`` as in
    :func:`solve_stage`; ``kx`` the free flight's mean velocities UL, UA
    (n, 3) and the classification's outputs vn (3, m), touching, impact
    (m,) bool, codes (m,) int64; ``kk`` the contacts (a, b, sidx (m,),
    point, normal (m, 3), gap, e (m,)); ``ko`` the last solve's warm cache (empty
    without one; ``warm_any`` whether there is one, ``warm_on`` whether
    the solve warm-starts from it).  Returns (impact rows, solved,
    sweeps, residual, whether a row pushes out, whether a patch slides);
    when not ``solved`` the caller goes on from the classification."""
    X, Iinv, R0, V, W, V0, W0, Vp, Wp, inv_mass, bound_radius = kc.items
    UL, UA, vn, touching, impact, codes = kx.items
    ca, cb, sidx, point, normal, gap, e = kk.items
    o_code, o_loc, o_fn, _, _, _, _, o_touch = ko.items
    nb = X.shape[0]
    nimp = classify(X, V, W, V0, W0, UL, UA, ca, cb, sidx, point, normal, gap, nb, n_statics, h, thr, lever, slop,
                    warm_any, o_code, o_loc, o_fn, o_touch, R0, bound_radius, vn, touching, impact, codes)
    m = codes.shape[0]
    if nimp > 0 or not fast or key.shape[0] != m:
        return nimp, False, 0, 0.0, 0, False
    for i in range(m):
        if codes[i] != key[i]:
            return nimp, False, 0, 0.0, 0, False
    sw, residual, pushed = solve_stage(kc, kt, kw, ko, kq, ca, cb, point, normal, gap, e, idx, touching, vn, h, lever,
                                       thr, beta, slop, friction, rolling, warm_on, direct, resting, max_rows, passes,
                                       slip_tol, iterations, relax_on, store_on)
    slip = kw.items[W_SLIP]
    sliding_any = False
    for p in range(slip.shape[0]):
        if slip[p]:
            sliding_any = True
            break
    return nimp, True, sw, residual, pushed, sliding_any
