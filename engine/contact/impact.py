"""The impact solver (the restitution phase at times of impact): impulsive
collision response with restitution and friction over the touching
contacts, by impulse propagation or as one simultaneous plastic impact per
island (:func:`impact_solve`)."""

from __future__ import annotations

import math

import numpy as np

from engine.contact import linalg
from engine.contact.rows import SLIP_TOL, TOUCH_TOL, Rows, _pad, _pair_codes
from engine.state import Contacts


def _pair_block(rows: Rows, idx: np.ndarray) -> tuple:
    """(a, b, JA, JB, MA, MB, K) of the normal rows ``idx`` of one pair,
    gathered once per Rows (the impact solver resolves a pair many times)."""
    cache = rows.__dict__.setdefault("_pair_blocks", {})
    key = idx.tobytes()
    out = cache.get(key)
    if out is None:
        JA, JB, MA, MB = rows.JA[idx], rows.JB[idx], rows.MA[idx], rows.MB[idx]
        out = (rows.a[idx[0]], rows.b[idx[0]], JA, JB, MA, MB,
               np.einsum("ik,jk->ij", JA, MA) + np.einsum("ik,jk->ij", JB, MB))
        cache[key] = out
    return out


def _patch_block(rows: Rows, p: int) -> tuple:
    """(a, b, JA, JB, MA, MB, K^-1 or None when K is singular, (mu_s, mu_k,
    r_twist, mu_r)) of friction patch ``p`` (cached per Rows: the impact
    solver resolves a pair many times, and the 3x3 (with rolling friction
    5x5) block is inverted once)."""
    cache = rows.__dict__.setdefault("_patch_blocks", {})
    out = cache.get(p)
    if out is None:
        JA, JB, MA, MB = rows.JtA[p], rows.JtB[p], rows.MtA[p], rows.MtB[p]
        K = np.einsum("ik,jk->ij", JA, MA) + np.einsum("ik,jk->ij", JB, MB)
        Kinv, ok = linalg.inverse(K)
        if not ok:
            Kinv = None
        out = (int(rows.pa[p]), int(rows.pb[p]), JA, JB, MA.T.copy(), MB.T.copy(), Kinv,
               (float(rows.mus[p]), float(rows.muk[p]), float(rows.r_twist[p]),
                float(rows.mur[p]) if rows.rolling else 0.0))
        cache[p] = out
    return out


def _block_normal(rows: Rows, U: np.ndarray, idx: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Exact normal impulses for the rows ``idx`` of ONE pair (k <= ~8):
    the linear complementarity problem  lambda >= 0,  K lambda >= r,
    lambda . (K lambda - r) = 0  with K = J M^-1 J^T and r = target - vn,
    solved by enumerating active sets (largest first; K may be singular, e.g.
    four coplanar points).  Applies the impulses to U and returns them."""
    from itertools import combinations

    a, b, JA, JB, MA, MB, K = _pair_block(rows, idx)
    r = target - (np.einsum("kj,j->k", JA, U[a]) + np.einsum("kj,j->k", JB, U[b]))
    k = idx.size
    lam = np.zeros(k)
    if k == 1:
        # one row (the common case: sphere contacts): the only active set is
        # {0}, lambda = r / K -- the same tests as the enumeration below
        K00, r0 = float(K[0, 0]), float(r[0])
        if r0 <= 0.0:
            return lam
        if abs(K00) >= 1e-12 * max(1.0, abs(K00)):
            l0 = r0 / K00
            if l0 >= 0.0 and K00 * l0 - r0 >= -1e-9 * abs(r0):
                lam[0] = l0
                U[a] += MA[0] * l0
                U[b] += MB[0] * l0
                U[-1] = 0.0
                return lam
    if np.all(r <= 0.0):
        return lam
    scale = float(np.max(np.abs(r)))
    found = False
    for size in range(k, 0, -1):
        for S in combinations(range(k), size):
            S = list(S)
            KS = K[np.ix_(S, S)]
            lS, det = linalg.lu_solve(KS, r[S])
            if abs(det) < 1e-12 * max(1.0, float(np.max(np.abs(KS)))) ** size:
                continue
            if np.any(lS < 0.0):
                continue
            trial = np.zeros(k)
            trial[S] = lS
            if np.all(np.einsum("ij,j->i", K, trial) - r >= -1e-9 * scale):
                lam = trial
                found = True
                break
        if found:
            break
    if not found:  # degenerate: fall back to projected Gauss-Seidel on the block
        for _ in range(200):
            for i in range(k):
                lam[i] = max(0.0, lam[i] + (r[i] - np.einsum("j,j->", K[i], lam)) / K[i, i])
    U[a] += np.einsum("kj,k->j", MA, lam)
    U[b] += np.einsum("kj,k->j", MB, lam)
    U[-1] = 0.0
    return lam


def _patch_impulse(rows: Rows, U: np.ndarray, p: int, Fn: float) -> None:
    """One-shot Coulomb friction impulse on patch ``p`` after a normal
    impulse of total ``Fn``: the impulse that stops the tangential and twist
    (and rolling) motion (exact block, by its inverse computed once per
    patch), kept if within the static limits -- mu_s for a patch at rest,
    mu_k for one that slides or twists (``Rows.sliding``: it slides until it
    stops, so kinetic friction is what has to stop it) -- else its force
    scaled onto the mu_k disc and its twist clipped to mu_k Fn r_twist; the
    rolling torque impulse is limited to the mu_r Fn disc."""
    if Fn <= 0.0:
        return
    a, b, JA, JB, MAT, MBT, Kinv, (mus, muk, rt, mur) = _patch_block(rows, p)
    vt = np.einsum("kj,j->k", JA, U[a]) + np.einsum("kj,j->k", JB, U[b])
    if Kinv is not None:
        d = -np.einsum("ij,j->i", Kinv, vt)
    else:
        d = -vt * rows.mt[p]
    # the patch sticks if both the force and the twist that stop it lie
    # within the limits; else it slides at every point: both are held to
    # the kinetic ones
    mu = muk if (math.hypot(vt[0], vt[1]) > SLIP_TOL or abs(vt[2]) * rt > SLIP_TOL) else mus
    mag = math.hypot(d[0], d[1])
    if mag > mu * Fn or (rt > 0.0 and abs(d[2]) > mu * Fn * rt):
        if mag > muk * Fn:
            d[:2] *= muk * Fn / mag
        tl = muk * Fn * rt
        d[2] = min(max(d[2], -tl), tl)
    if d.size > 3:
        rmag = math.hypot(d[3], d[4])
        if rmag > mur * Fn:
            d[3:] *= mur * Fn / rmag
    U[a] += np.einsum("jk,k->j", MAT, d)
    U[b] += np.einsum("jk,k->j", MBT, d)
    U[-1] = 0.0


def impact_solve(model, state, contacts: Contacts, iterations: int, thr: float, friction: bool,
                 plastic: str = "simultaneous") -> int:
    """Impulsive collision response at a time of impact, on the state's
    velocities, over the touching contacts (gap <= 10 TOUCH_TOL).  Returns
    the number of rows.

    The touching pairs split into islands (bodies joined by touching
    contacts; the world joins nothing).  Islands are independent, and each
    is resolved by one of two laws:

    * an island with restitution anywhere in it, or with one pair only:
      impulse propagation, binary collisions one after another
      (:func:`_propagate`) -- a striker hitting a row of touching balls
      hands its momentum down the row (Newton's cradle);
    * with ``plastic = "simultaneous"`` (the default), an island of two or
      more pairs, all with e = 0: one simultaneous plastic impact, Moreau's
      law (:func:`_plastic_island_solve`): the post-impact velocity is the
      one nearest the pre-impact velocity in the kinetic-energy metric that
      approaches at no contact (the LCP lambda >= 0, J u+ >= 0,
      lambda . J u+ = 0), with Coulomb friction; it does not depend on an
      order of the pairs.  Propagation gives the same for a column landing
      on the floor (everything stops), but only in the limit: with no
      rebound to hand on, the pairs push one another back and forth and
      the approach decays geometrically -- about 20 pair solves per contact
      in a column of 10 spheres; a layer landing on 100 such columns cost
      0.2-1 s of CPU per impact (spheres_1000), and some did not settle
      within the propagation's budget.  ``"sequential"`` propagates these
      islands too.
    """
    from engine.mathutil import quat_to_matrix, world_inv_inertia

    sel = np.flatnonzero(contacts.gap <= 10 * TOUCH_TOL)
    if sel.size == 0:
        return 0
    cs = contacts.take(sel)
    n = model.n
    # the world inverse inertias of the contacts' bodies only (the same
    # bits per body: an O(n) pass per impact at 10,000 bodies was ~2 ms)
    bodies = np.unique(np.concatenate([cs.a, cs.b[cs.b < n]]))
    Iinv = np.zeros((n + 1, 3, 3))
    Iinv[bodies] = world_inv_inertia(quat_to_matrix(state.q[bodies]), model.inv_inertia_body[bodies])
    U = Rows.pack(_pad(state.v), _pad(state.w))
    # (every row bouncing, the common case of billiards: no plastic island)
    together = _plastic_islands(model, cs) if plastic == "simultaneous" and not np.all(cs.e > 0.0) else None
    m = 0
    if together is None or not together.any():
        m += _propagate(model, state.x, Iinv, cs, U, iterations, thr, friction)
    else:
        m += _plastic_island_solve(model, state.x, Iinv, cs.take(np.flatnonzero(together)), U, iterations,
                                   friction)
        if not together.all():
            m += _propagate(model, state.x, Iinv, cs.take(np.flatnonzero(~together)), U, iterations, thr,
                            friction)
    state.v[:] = U[:n, :3]
    state.w[:] = U[:n, 3:]
    return m


def _plastic_islands(model, cs: Contacts) -> np.ndarray:
    """(m,) bool: the rows of ``cs`` in islands of two or more pairs whose
    rows all have e = 0 (see :func:`impact_solve`)."""
    code = _pair_codes(model, cs)
    if np.all(code == code[0]):  # one pair (a single landing): nothing to join
        return np.zeros(cs.m, bool)
    n = model.n
    dyn = cs.b < n  # a is always a body; b may be the world
    lab, k = linalg.islands(n, cs.a[dyn], cs.b[dyn])
    isl = lab[cs.a]
    bouncy = np.bincount(isl, cs.e > 0.0, k) > 0
    _, first = np.unique(code, return_index=True)
    pairs = np.bincount(isl[first], minlength=k)
    ok = ~bouncy & (pairs >= 2)
    return ok[isl]


def _plastic_island_solve(model, X, Iinv, cs: Contacts, U: np.ndarray, iterations: int, friction: bool) -> int:
    """Simultaneous plastic impact of the contacts ``cs`` (Moreau's law, see
    :func:`impact_solve`) on U (n+1, 6) in place: target vn+ >= 0 on every
    row, started from the direct solution of the rows that do not separate
    (exact when all of them end pressed, as in a column that lands, where a
    Gauss-Seidel sweep moves an impulse only one contact down), then
    projected Gauss-Seidel with Coulomb friction (mu_k for patches sliding
    at the impact, mu_s for the others, switching where the static limit is
    reached).  Returns the number of rows."""
    rows = Rows(model, X, Iinv, cs, friction)
    if friction:
        rows.set_slip(rows.sliding(U))
    rows.direct_normal_guess(U)
    rows.warm_start(U)
    rows.solve_friction_regimes(U, iterations)
    return rows.m


def _propagate(model, X, Iinv, cs: Contacts, U: np.ndarray, iterations: int, thr: float, friction: bool) -> int:
    """Impulse propagation over the contacts ``cs`` on U (n+1, 6) in place:
    repeatedly take the touching pair that approaches fastest (normal speed
    above ``thr``), give it the exact pair impulse (block solve of its
    points) with the restitution target vn+ = -e vn- and a Coulomb friction
    impulse, until no touching pair approaches faster than ``thr``; then
    stop the slow approaches (vn+ >= 0).  Binary collisions one after
    another: a striker hitting a row of touching balls hands its momentum
    down the row (Newton's cradle) and symmetric contacts get symmetric
    impulses.  If the propagation does not settle (pinned ping-pong), the
    remaining approaches are resolved together by sequential impulses.
    Returns the number of rows."""
    n = model.n
    rows = Rows(model, X, Iinv, cs, friction, colour=False)
    cs = rows.contacts
    code = _pair_codes(model, cs)
    uniq, inv = np.unique(code, return_inverse=True)
    # rows of each pair (ascending), and of each body
    go = np.argsort(inv, kind="stable")
    groups = np.split(go, np.cumsum(np.bincount(inv, minlength=uniq.size))[:-1])
    e = cs.e
    ra, rb = rows.a, rows.b
    ab_rows = np.concatenate([ra, rb])
    bo = np.argsort(ab_rows, kind="stable") % rows.m
    # body k's rows: bo[b0[k]:b0[k + 1]] (sliced when a pair needs them: a
    # split into n + 1 arrays cost O(n) per impact, ~5 ms at 10,000 bodies)
    b0 = np.zeros(n + 2, np.int64)
    np.cumsum(np.bincount(ab_rows, minlength=n + 1), out=b0[1:])
    affected: dict[int, tuple] = {}
    group_sub: dict[int, tuple] = {}

    ab = rows.topo.ab

    def vn_all():
        # [JA | JB] . [U[a] | U[b]] per row: one gather, one reduction
        return np.einsum("kj,kj->k", rows.J, U[ab].reshape(-1, 12))

    def vn_sub(sub):
        # the same per-row arithmetic as vn_all, on a subset of the rows
        # gathered once: sub = (J, ab) of those rows
        Js, ABs = sub
        return np.einsum("kj,kj->k", Js, U[ABs].reshape(-1, 12))

    # normal velocities of all rows, kept current: a pair's impulses change
    # only the rows of its two bodies
    vcur = vn_all()

    def resolve(g, restitution: bool):
        idx = groups[g]
        v = vcur[idx]
        tgt = np.where(v < -thr, -e[idx] * v, 0.0) if restitution else np.zeros(idx.size)
        lam = _block_normal(rows, U, idx, tgt)
        if friction and lam.sum() > 0:
            _patch_impulse(rows, U, int(rows.pid[idx[0]]), float(lam.sum()))
            # friction may have changed the normal velocities: keep them >= 0
            gs = group_sub.get(g)
            if gs is None:
                gs = group_sub[g] = (rows.J[idx], ab[idx])
            v2 = vn_sub(gs)
            if np.any(v2 < np.minimum(tgt, 0.0) - 1e-12):
                _block_normal(rows, U, idx, np.maximum(np.minimum(tgt, 0.0), v2 * 0.0))
        entry = affected.get(g)
        if entry is None:
            i, j = int(ra[idx[0]]), int(rb[idx[0]])
            aff = np.unique(np.concatenate([bo[b0[i]:b0[i + 1]]] + ([bo[b0[j]:b0[j + 1]]] if j != n else [])))
            entry = (aff, (rows.J[aff], ab[aff]))
            affected[g] = entry
        vcur[entry[0]] = vn_sub(entry[1])

    settled = False
    for _ in range(20 * len(groups) + 10):
        j = int(np.argmin(vcur))
        if vcur[j] >= -thr:
            settled = True
            break
        resolve(int(inv[j]), True)
    if not settled:
        # pinned configuration: resolve all approaches together
        v = vn_all()
        rows.target = np.where(v < -thr, -e * v, 0.0)
        rows_c = Rows(model, X, Iinv, cs, friction)
        rows_c.target = rows.target[rows_c.order]
        rows_c.solve_friction_regimes(U, iterations)
        vcur[:] = vn_all()
    for _ in range(3):  # slow approaches stop (plastic)
        slow = np.unique(inv[vcur < -1e-12])
        if slow.size == 0:
            break
        for g in slow.tolist():
            resolve(g, False)
    return rows.m
