"""Compiled projected Gauss-Seidel sweeps of the contact solve (the solve
phase) and the impulse application of the warm start.

Velocities are one (n+1, 6) array U = [v | w] with the world's row n held
at zero: an impulse on the world is never applied.  Rows are visited in
their (colour) order, one after the other; rows of one colour share no
dynamic body, so this is the result of updating a colour at once.

Normal rows: ``J``/``M`` (m, 12), effective masses ``mn`` (m,), bodies
``ab`` (m, 2).  Friction patches: ``Jt``/``Mt`` (np, nr, 12) with nr = 3
(tangent, tangent, twist) or 5 (+ two rolling rows), ``mt`` (np, nr),
bodies ``pab`` (np, 2), the patch of each normal row ``pid`` (m,),
friction coefficients ``mu`` (np,), twist radii ``rt`` (np,), rolling
coefficients ``mur`` (np,), and the pins of :meth:`Rows.stop_times`
(``pin_t`` (np,) bool with unit directions ``dir_t`` (np, 2); ``pin_r``,
``dir_r`` for the rolling rows).

Work arrays: ``wk`` (>= :func:`work_size` (m, np, nr),) float64, kept by the
caller (no allocation per sweep or per solve): the last sweep's impulses,
the patches' normal impulses and one patch's new impulses
(:func:`work_layout`).
"""

from __future__ import annotations

import math

from numba import njit


def work_size(m: int, npch: int, nr: int) -> int:
    """Length of the sweeps' work array ``wk`` for m normal rows and npch
    patches of nr rows (see :func:`work_layout`)."""
    return m + npch * nr + 2 * npch + 40


@njit(cache=True, inline="always")
def work_layout(wk, m, npch, nr):
    """The views of ``wk``: the normal impulses before a sweep (m,), the
    patch impulses before it (np * nr,) flat, the patches' normal impulses
    of a friction sweep (np,), one patch's new impulses and block scratch
    (40,: :func:`_rolling_block`), and the
    patches' normal impulses of the static/kinetic switch (np,)."""
    o1 = m + npch * nr
    o2 = o1 + npch
    return wk[:m], wk[m:o1], wk[o1:o2], wk[o2:o2 + 40], wk[o2 + 40:o2 + 40 + npch]


@njit(cache=True, inline="always")
def add_row(U, ia, ib, M, i, d, world):
    """U[ia] += M[i, :6] d, U[ib] += M[i, 6:] d; the world's row untouched."""
    if ia != world:
        for k in range(6):
            U[ia, k] += M[i, k] * d
    if ib != world:
        for k in range(6):
            U[ib, k] += M[i, 6 + k] * d


@njit(cache=True)
def apply_rows(U, ab, M, d, world):
    """U[a] += M[:, :6] d, U[b] += M[:, 6:] d over rows in order (M (k, 12),
    d (k,)); the world row untouched."""
    for i in range(d.shape[0]):
        add_row(U, ab[i, 0], ab[i, 1], M, i, d[i], world)


@njit(cache=True)
def apply_patches(U, pab, Mt, d, world):
    """U[pa] += sum_r d[:, r] MtA[:, r], likewise b (Mt (np, nr, 12), d (np, nr))."""
    nr = d.shape[1]
    for p in range(d.shape[0]):
        ia = pab[p, 0]
        ib = pab[p, 1]
        for k in range(6):
            sa = 0.0
            sb = 0.0
            for r in range(nr):
                sa += d[p, r] * Mt[p, r, k]
                sb += d[p, r] * Mt[p, r, 6 + k]
            if ia != world:
                U[ia, k] += sa
            if ib != world:
                U[ib, k] += sb


@njit(cache=True, inline="always")
def _row_update(U, ia, ib, J, mn, lam, target, i):
    """Row i's new accumulated impulse (lam[i] set) and its change:
    J[i] . [U[ia] | U[ib]] summed in order (the a side, then the b side)."""
    vn = 0.0
    for k in range(6):
        vn += J[i, k] * U[ia, k]
    for k in range(6):
        vn += J[i, 6 + k] * U[ib, k]
    old = lam[i]
    new = max(old - mn[i] * (vn - target[i]), 0.0)
    lam[i] = new
    return new - old


@njit(cache=True)
def normal_pass(U, ab, J, M, mn, lam, target, world):
    """One sweep of the normal rows: lam >= 0, J U >= target.  Two
    consecutive rows on no common dynamic body (rows of one colour) are
    done side by side: neither reads what the other writes, each sums as
    alone, so the result is the row-by-row sweep's bit for bit, with two
    dependency chains in flight instead of one."""
    m = lam.shape[0]
    i = 0
    while i < m:
        ia = ab[i, 0]
        ib = ab[i, 1]
        if i + 1 < m:
            ja = ab[i + 1, 0]
            jb = ab[i + 1, 1]
            if ((ja == world or (ja != ia and ja != ib)) and (jb == world or (jb != ia and jb != ib))):
                v1 = 0.0
                v2 = 0.0
                for k in range(6):
                    v1 += J[i, k] * U[ia, k]
                    v2 += J[i + 1, k] * U[ja, k]
                for k in range(6):
                    v1 += J[i, 6 + k] * U[ib, k]
                    v2 += J[i + 1, 6 + k] * U[jb, k]
                o1 = lam[i]
                n1 = max(o1 - mn[i] * (v1 - target[i]), 0.0)
                lam[i] = n1
                o2 = lam[i + 1]
                n2 = max(o2 - mn[i + 1] * (v2 - target[i + 1]), 0.0)
                lam[i + 1] = n2
                add_row(U, ia, ib, M, i, n1 - o1, world)
                add_row(U, ja, jb, M, i + 1, n2 - o2, world)
                i += 2
                continue
        d = _row_update(U, ia, ib, J, mn, lam, target, i)
        add_row(U, ia, ib, M, i, d, world)
        i += 1


@njit(cache=True, inline="always")
def row_velocity(Jt, U, p, r, ia, ib):
    """Jt[p, r] . [U[ia] | U[ib]], the relative velocity of patch row r
    (the a side summed first, then the b side)."""
    v = 0.0
    for k in range(6):
        v += Jt[p, r, k] * U[ia, k]
    for k in range(6):
        v += Jt[p, r, 6 + k] * U[ib, k]
    return v


@njit(cache=True, inline="always")
def _patch_rows(U, pab, Jt, Mt, mt, lam_t, p, r0, r1, new, world):
    """new[r0:r1] = lam_t[p, r0:r1] - mt (Jt U) for patch p (unprojected),
    r1 - r0 = 3 (tangent, tangent, twist) or 2 (rolling): each row's
    velocity summed as :func:`row_velocity` sums it, the rows' sums side by
    side (independent chains, the same bits)."""
    ia = pab[p, 0]
    ib = pab[p, 1]
    three = r1 - r0 == 3
    v0 = 0.0
    v1 = 0.0
    v2 = 0.0
    for k in range(6):
        u = U[ia, k]
        v0 += Jt[p, r0, k] * u
        v1 += Jt[p, r0 + 1, k] * u
        if three:
            v2 += Jt[p, r0 + 2, k] * u
    for k in range(6):
        u = U[ib, k]
        v0 += Jt[p, r0, 6 + k] * u
        v1 += Jt[p, r0 + 1, 6 + k] * u
        if three:
            v2 += Jt[p, r0 + 2, 6 + k] * u
    new[r0] = lam_t[p, r0] - mt[p, r0] * v0
    new[r0 + 1] = lam_t[p, r0 + 1] - mt[p, r0 + 1] * v1
    if three:
        new[r0 + 2] = lam_t[p, r0 + 2] - mt[p, r0 + 2] * v2


@njit(cache=True, inline="always")
def _patch_apply(U, pab, Mt, lam_t, p, r0, r1, new, world):
    ia = pab[p, 0]
    ib = pab[p, 1]
    for k in range(6):
        sa = 0.0
        sb = 0.0
        for r in range(r0, r1):
            d = new[r] - lam_t[p, r]
            sa += d * Mt[p, r, k]
            sb += d * Mt[p, r, 6 + k]
        if ia != world:
            U[ia, k] += sa
        if ib != world:
            U[ib, k] += sb
    for r in range(r0, r1):
        lam_t[p, r] = new[r]


@njit(cache=True, inline="always")
def _scale_onto_disc(new, i, lim):
    """(new[i], new[i + 1]) scaled onto the disc of radius ``lim`` when
    outside it; whether it was."""
    mag = math.sqrt(new[i] * new[i] + new[i + 1] * new[i + 1])
    if mag > lim:
        f = lim / mag if mag > 0 else 1.0
        new[i] *= f
        new[i + 1] *= f
        return True
    return False


@njit(cache=True, inline="always")
def _onto_disc(new, i, lim, pinned, d):
    """(new[i], new[i+1]) scaled back onto the disc of radius ``lim``, or
    when ``pinned`` held on its rim against the unit direction ``d`` (2,)."""
    _scale_onto_disc(new, i, lim)
    if pinned:
        new[i] = -lim * d[0]
        new[i + 1] = -lim * d[1]


@njit(cache=True, inline="always")
def _rolling_block(U, f, p, lim_t, tl, lim_r, w, world):
    """Patch ``p`` of the patches ``f`` (engine.contact.packs.Patches) with
    five rows (tangent, tangent, twist, rolling, rolling)
    solved as a block: the per-row updates of :func:`friction_pass`
    (Coulomb disc ``lim_t``, twist limit ``tl``, rolling disc ``lim_r``)
    repeated on the patch's own velocities v = v0 + W (lam - lam0), W (5, 5)
    = Jt Mt^T its Delassus block, until no impulse moves (at most 200
    passes), then applied to ``U`` once.  The rolling rows take one common
    step on the rim (:func:`_rolling_step`).  Swept against the rest of the
    scene one row at a time, a cylinder whose axis lay between the patch
    tangents converged at about 0.75 a sweep through the coupling of its
    tangent and rolling rows (relative error 1.1e-10 at 20 sweeps); solved
    as a block it is exact at every heading
    (tests/test_engine_friction.py::test_cylinder_rolling_resistance_at_every_heading).
    ``w`` (40,) scratch: new (5,), lam (5,), v (5,), W (25,)."""
    pab, Jt, Mt, mt, lam_t = f.pab, f.Jt, f.Mt, f.mt, f.lam_t
    pin_t, dir_t, pin_r, dir_r = f.pin_t[p], f.dir_t[p], f.pin_r[p], f.dir_r[p]
    ia = pab[p, 0]
    ib = pab[p, 1]
    for r in range(5):
        w[5 + r] = lam_t[p, r]
        w[10 + r] = row_velocity(Jt, U, p, r, ia, ib)
        for c in range(5):
            x = 0.0
            for k in range(12):
                x += Jt[p, r, k] * Mt[p, c, k]
            w[15 + 5 * r + c] = x
    scale = lim_t + lim_r + abs(tl)
    for _ in range(200):
        change = 0.0
        for r0 in (0, 3):
            r1 = 3 if r0 == 0 else 5
            for r in range(r0, r1):
                w[r] = w[5 + r] - mt[p, r] * w[10 + r]
            if r0 == 0:
                _onto_disc(w, 0, lim_t, pin_t, dir_t)
                w[2] = min(max(w[2], -tl), tl)
            else:
                _rolling_step(mt, w, p, lim_r)
                _onto_disc(w, 3, lim_r, pin_r, dir_r)
            for r in range(r0, r1):
                d = w[r] - w[5 + r]
                if d != 0.0:
                    change = max(change, abs(d))
                    for q in range(5):
                        w[10 + q] += w[15 + 5 * q + r] * d
                    w[5 + r] = w[r]
        if not change > 1e-15 * scale:
            break
    for k in range(6):
        sa = 0.0
        sb = 0.0
        for r in range(5):
            d = w[5 + r] - lam_t[p, r]
            sa += d * Mt[p, r, k]
            sb += d * Mt[p, r, 6 + k]
        if ia != world:
            U[ia, k] += sa
        if ib != world:
            U[ib, k] += sb
    for r in range(5):
        lam_t[p, r] = w[5 + r]


@njit(cache=True, inline="always")
def _rolling_step(mt, w, p, lim):
    """The rolling rows' update ``w[3:5]`` of a patch on the rim of its
    disc (radius ``lim``), given the per-row update lam - mt w_r in ``w``
    and lam in ``w[8:10]``: when the two rows' effective masses differ (a
    cylinder's axis between the patch tangents) and the per-row update
    leaves the disc, one common step lam - m w_r, m = 2 / (1/mt3 + 1/mt4),
    for both rows.  A common step keeps the update along the rolling
    velocity w_r, so the rim's fixed point is lam = -lim w_r / |w_r|: mu_r
    Fn against the rolling (maximum dissipation).  Per-row steps turned it
    off w_r by the anisotropy of the rows' effective masses, whatever the
    iterations
    (tests/test_engine_friction.py::test_cylinder_rolling_resistance_at_every_heading).
    At that fixed point the per-row update also lands outside the disc, so
    the switch is consistent; m <= 2 / lambda_max of the 2x2 block, so the
    passes still converge.  Inside the disc nothing changes."""
    m3 = mt[p, 3]
    m4 = mt[p, 4]
    if m3 == m4 or not (m3 > 0.0 and m4 > 0.0) or w[3] * w[3] + w[4] * w[4] <= lim * lim:
        return
    l3 = w[8]
    l4 = w[9]
    m = 2.0 * m3 * m4 / (m3 + m4)
    w[3] = l3 + (m / m3) * (w[3] - l3)  # lam - m w_r, with new - lam = -mt w_r
    w[4] = l4 + (m / m4) * (w[4] - l4)


@njit(cache=True)
def friction_pass(U, f, lam_n, world, Fn, new):
    """One sweep of the friction patches ``f`` (engine.contact.packs.Patches):
    tangent and twist rows (Coulomb disc mu Fn, twist limit mu Fn
    r_twist), then the rolling rows (disc mu_r Fn), Fn the patch's normal
    impulse at the start of the sweep.  ``Fn`` (np,) and ``new`` (>= nr,)
    work arrays."""
    pab, Jt, Mt, mt, lam_t, mu, rt = f.pab, f.Jt, f.Mt, f.mt, f.lam_t, f.mu, f.rt
    pid, pin_t, dir_t = f.pid, f.pin_t, f.dir_t
    npch = lam_t.shape[0]
    nr = lam_t.shape[1]
    Fn[:] = 0.0
    for i in range(pid.shape[0]):
        Fn[pid[i]] += lam_n[i]
    if nr == 5:  # patches with rolling rows: each solved as a block
        mur = f.mur
        for p in range(npch):
            lim = mu[p] * Fn[p]
            _rolling_block(U, f, p, lim, lim * rt[p], mur[p] * Fn[p], new, world)
        return
    for p in range(npch):
        _patch_rows(U, pab, Jt, Mt, mt, lam_t, p, 0, 3, new, world)
        lim = mu[p] * Fn[p]
        _onto_disc(new, 0, lim, pin_t[p], dir_t[p])
        tl = lim * rt[p]
        new[2] = min(max(new[2], -tl), tl)
        _patch_apply(U, pab, Mt, lam_t, p, 0, 3, new, world)


@njit(cache=True)
def iterate(U, rows, f, friction, iterations, tol, world, wk):
    """Sweeps of friction (the patches ``f``, engine.contact.packs.Patches,
    with ``friction``) then normal rows (``rows``, engine.contact.packs.
    NormalRows) until no impulse changes by more than ``tol`` times the
    largest normal impulse in a sweep; ``wk`` the work array (module doc).
    Returns (sweeps done, the last sweep's largest change relative to the
    largest normal impulse)."""
    ab, J, M, mn, lam_n, target = rows.ab, rows.J, rows.M, rows.mn, rows.lam, rows.target
    pab, pid, Mt, lam_t, mu, rt, mur = f.pab, f.pid, f.Mt, f.lam_t, f.mu, f.rt, f.mur
    m = lam_n.shape[0]
    npch = lam_t.shape[0]
    nr = lam_t.shape[1]
    prev_n, prev_t, Fn, new, _ = work_layout(wk, m, npch, nr)
    residual = 0.0
    for it in range(iterations):
        prev_n[:] = lam_n
        if friction:
            for p in range(npch):
                for r in range(nr):
                    prev_t[p * nr + r] = lam_t[p, r]
            friction_pass(U, f, lam_n, world, Fn, new)
        normal_pass(U, ab, J, M, mn, lam_n, target, world)
        change = 0.0
        for i in range(m):
            change = max(change, abs(lam_n[i] - prev_n[i]))
        if friction:
            for p in range(npch):
                for r in range(nr):
                    change = max(change, abs(lam_t[p, r] - prev_t[p * nr + r]))
        scale = 0.0
        for i in range(m):
            scale = max(scale, lam_n[i])
        residual = change / scale if scale > 0.0 else 0.0
        if change <= tol * scale or change == 0.0:
            return it + 1, residual
    if friction:
        onto_cone(U, pab, pid, Mt, lam_t, lam_n, mu, rt, mur, world, Fn, new)
    return iterations, residual


@njit(cache=True)
def onto_cone(U, pab, pid, Mt, lam_t, lam_n, mu, rt, mur, world, Fn, new):
    """Each patch's friction impulses scaled back onto its limits at the
    normal impulses ``lam_n`` as they are now (tangent disc mu Fn, twist
    mu Fn r_twist, rolling disc mu_r Fn), the change applied to ``U``; a
    patch inside its limits is not touched (not one bit).  Called when
    the sweeps stop at their limit unconverged: a sweep clamps the
    friction against the normal impulses at its start and the normal rows
    swept after it may lower them, so the impulses the step applies would
    leave the cone (a speculative row of stacking.poured_bin went from at
    least 3.0e-3 N to 1.0e-4 N under a friction of 2.1e-3 N: 20 times its
    cone); a converged solve moved no normal impulse by more than its
    tolerance.  Pinned by
    tests/test_engine_friction.py::test_a_solve_cut_short_ends_inside_the_cone.
    ``Fn`` (np,), ``new`` (>= nr,) work arrays."""
    npch = lam_t.shape[0]
    nr = lam_t.shape[1]
    Fn[:] = 0.0
    for i in range(pid.shape[0]):
        Fn[pid[i]] += lam_n[i]
    for p in range(npch):
        lim = mu[p] * Fn[p]
        if lim < 0.0:
            lim = 0.0
        for r in range(nr):
            new[r] = lam_t[p, r]
        out = _scale_onto_disc(new, 0, lim)
        tl = lim * rt[p]
        if abs(new[2]) > tl:
            new[2] = min(max(new[2], -tl), tl)
            out = True
        if nr == 5:
            lr = mur[p] * Fn[p]
            if _scale_onto_disc(new, 3, lr if lr > 0.0 else 0.0):
                out = True
        if out:
            _patch_apply(U, pab, Mt, lam_t, p, 0, nr, new, world)


@njit(cache=True)
def iterate_normal(U, ab, J, M, mn, lam, target, iterations, tol, world, wk):
    """Normal rows only, with their own accumulator (split impulse);
    ``wk`` (>= m,) work array."""
    m = lam.shape[0]
    prev = wk[:m]
    for _ in range(iterations):
        prev[:] = lam
        normal_pass(U, ab, J, M, mn, lam, target, world)
        change = 0.0
        scale = 0.0
        for i in range(m):
            change = max(change, abs(lam[i] - prev[i]))
            scale = max(scale, lam[i])
        if change <= tol * scale or change == 0.0:
            return
