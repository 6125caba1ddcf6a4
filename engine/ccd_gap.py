"""The compiled arithmetic of the time-of-impact search's gap of a followed
pair (engine/ccd.py ``pair_gap``): the contacts nearest the followed
points in body a's frame, the points left out, the feature ids followed,
and the nearest contact's normal speed, in one call."""

from __future__ import annotations

import numpy as np
from numba import njit

from physbench.engine.collision.collide import collide_packed
from physbench.engine.geometry import Pairs

#: no points to follow or leave out; no feature ids
NO_P3 = np.zeros((0, 3))
NO_FID = np.zeros(0, np.int64)


@njit(cache=True)
def gap(point, gap, fid, ca, cb, normal, x1, R, V, W, a, tol, loc, excl, fids, wk):
    """:func:`pair_gap`'s arithmetic over a pair's contacts (points,
    normals (m, 3), gap, fid, a, b (m,)) at the end pose (x1 (n, 3), body
    a's rotation R (3, 3), padded velocities V, W (n+1, 3)): the points
    to follow ``loc`` (k, 3), the points to leave out ``excl`` (j, 3), the
    feature ids to follow ``fids`` (no rows: none), matching radius
    ``tol`` (m); ``wk`` (>= m, 5) work rows.  Positional arrays, not a
    named tuple: the time-of-impact search calls this from Python, where
    a named tuple argument costs ~0.7-0.9 us more to dispatch than its
    arrays one by one (~1.1 us).  Returns (gap, normal
    speed) as the numpy form did, bit for bit: the body-frame points summed
    as einsum "ki,ij->kj" does ((p0 + p1) + p2), the normal speed as
    einsum "ki,ki->k" ((p0 + p2) + p1) (tests/test_ccd_gap.py)."""
    m = gap.shape[0]
    n = x1.shape[0]
    t2 = tol * tol
    nl, ne = loc.shape[0], excl.shape[0]
    for i in range(m):
        wk[i, 3] = gap[i]
        if nl or ne:
            d0, d1, d2 = point[i, 0] - x1[a, 0], point[i, 1] - x1[a, 1], point[i, 2] - x1[a, 2]
            for j in range(3):
                wk[i, j] = (d0 * R[0, j] + d1 * R[1, j]) + d2 * R[2, j]
    if ne:
        kept = False
        for i in range(m):
            dmin = np.inf
            for k in range(ne):
                e0, e1, e2 = wk[i, 0] - excl[k, 0], wk[i, 1] - excl[k, 1], wk[i, 2] - excl[k, 2]
                dmin = min(dmin, (e0 * e0 + e1 * e1) + e2 * e2)
            if dmin <= t2:
                wk[i, 3] = np.inf
            else:
                kept = True
        if not kept:
            return np.inf, 0.0
    if nl:
        follow = False
        for i in range(m):
            wk[i, 4] = 0.0
        for k in range(nl):
            best, bd = 0, np.inf
            for i in range(m):  # np.argmin: the first nearest, over the rows still in
                d = np.inf
                if np.isfinite(wk[i, 3]):
                    e0, e1, e2 = wk[i, 0] - loc[k, 0], wk[i, 1] - loc[k, 1], wk[i, 2] - loc[k, 2]
                    d = (e0 * e0 + e1 * e1) + e2 * e2
                if i == 0 or d < bd:
                    best, bd = i, d
            if bd <= t2:
                wk[best, 4] = 1.0
                follow = True
        if fids.shape[0]:
            for i in range(m):
                if np.isfinite(wk[i, 3]):
                    for f in fids:
                        if fid[i] == f:
                            wk[i, 4] = 1.0
                            follow = True
                            break
        if follow:
            for i in range(m):
                wk[i, 3] = gap[i] if wk[i, 4] != 0.0 else np.inf
    k = 0
    for i in range(1, m):
        if wk[i, 3] < wk[k, 3]:
            k = i
    ka, kb = ca[k], cb[k]
    xa0, xa1, xa2 = (x1[ka, 0], x1[ka, 1], x1[ka, 2]) if ka < n else (0.0, 0.0, 0.0)
    xb0, xb1, xb2 = (x1[kb, 0], x1[kb, 1], x1[kb, 2]) if kb < n else (0.0, 0.0, 0.0)
    ra0, ra1, ra2 = point[k, 0] - xa0, point[k, 1] - xa1, point[k, 2] - xa2
    rb0, rb1, rb2 = point[k, 0] - xb0, point[k, 1] - xb1, point[k, 2] - xb2
    # rel = V[b] + W[b] x rB - V[a] - W[a] x rA (rows.point_normal_velocity)
    r0 = V[kb, 0] + (W[kb, 1] * rb2 - W[kb, 2] * rb1) - V[ka, 0] - (W[ka, 1] * ra2 - W[ka, 2] * ra1)
    r1 = V[kb, 1] + (W[kb, 2] * rb0 - W[kb, 0] * rb2) - V[ka, 1] - (W[ka, 2] * ra0 - W[ka, 0] * ra2)
    r2 = V[kb, 2] + (W[kb, 0] * rb1 - W[kb, 1] * rb0) - V[ka, 2] - (W[ka, 0] * ra1 - W[ka, 1] * ra0)
    return gap[k], (r0 * normal[k, 0] + r2 * normal[k, 2]) + r1 * normal[k, 1]


@njit(cache=True)
def collide_gap(kept, X, R1, pairs, margins, sweep, face_points, V, W, a, tol, loc, excl, fids, wk):
    """The followed pair's contacts and :func:`gap` over them in one call
    (engine/ccd.py ``pair_gap``): the collision of the pair (``pairs`` an
    engine.geometry.Pairs of pi, pj, bp, pk, bs, sk: one pair; its
    ``margins``) at the end pose (X (n, 3), R1
    (n, 3, 3)) into the collider's buffers ``kept`` (its Pack,
    engine.collision.dispatch.Collider.packed), as Collider.run makes it
    (``sweep`` the collider's margin work row, ``face_points``
    engine.collision.box.EDGE_FACE_POINTS), then the gap of body ``a``'s
    contacts as :func:`gap` (the rest its arguments).  Returns (done, gap,
    normal speed); done False when a buffer was short (the collider grows
    it in Collider.run, which the caller then runs: the same contacts)."""
    cnt, need_k, need_s = collide_packed(kept, X, R1, pairs.pi, pairs.pj, margins, pairs.bp, pairs.pk, pairs.bs,
                                         pairs.sk, bool(False), float(0.0), sweep, face_points)
    b = kept.items
    if need_k > b.A.c.shape[0] or need_s > b.slot.g.shape[0] or cnt > b.out.a.shape[0] or cnt > wk.shape[0]:
        return False, np.inf, 0.0
    if cnt == 0:
        return True, np.inf, 0.0
    o = b.out
    g, vn = gap(o.point[:cnt], o.gap[:cnt], o.fid[:cnt], o.a[:cnt], o.b[:cnt], o.normal[:cnt], X, R1[a], V, W, a, tol,
                loc, excl, fids, wk)
    return True, g, vn


def warm_up() -> None:
    """Compile (or load) :func:`gap` and :func:`collide_gap` with the
    step's argument types (see engine/jit.py): the latter into a collider
    of a sphere and a plane, its families' table all missing (the driver's
    type is the same for every scene; no family is compiled here)."""
    from physbench.engine.collision import box

    z3, i1 = np.ones((1, 3)), np.zeros(1, np.int64)
    V = np.zeros((2, 3))
    gap(z3, np.ones(1), i1, i1, i1 + 1, z3, z3, np.eye(3), V, V, 0, 0.1, z3, z3, i1, np.empty((1, 5)))
    col = warm_collider()
    z = np.zeros(0, np.int64)
    inf = np.array([np.inf])
    collide_gap(col.packed(), np.zeros((1, 3)), np.eye(3)[None].copy(), Pairs(pi=z, pj=z, bp=z, pk=z, bs=z, sk=z),
                (inf, inf.copy(), inf.copy()), col.W.gm, box.EDGE_FACE_POINTS, V, V, 0, 0.1, NO_P3, NO_P3, NO_FID,
                np.empty((1, 5)))


def warm_collider():
    """A collider (engine.collision.dispatch.Collider) of one sphere and a
    plane with every family missing from its table: what the warm-ups of
    the compiled callers of the narrow phase's driver collide into (the
    driver's type is the same for every scene; no family compiles)."""
    from types import SimpleNamespace

    from physbench.engine.collision.collide import N_FAMILIES
    from physbench.engine.collision.dispatch import Collider

    model = SimpleNamespace(
        n=1, shape=np.zeros(1, np.int64), radius=np.full(1, 0.1), half_extents=np.full((1, 3), 0.1),
        half_length=np.full(1, 0.1), body_material=np.zeros(1, np.int64), plane_normal=np.array([[0.0, 0.0, 1.0]]),
        plane_offset=np.zeros(1), plane_static=np.zeros(1, np.int64), sbox_pos=np.zeros((0, 3)),
        sbox_R=np.zeros((0, 3, 3)), sbox_half=np.zeros((0, 3)), sbox_static=np.zeros(0, np.int64),
        static_material=np.zeros(1, np.int64), pair_e=np.zeros((1, 1)), pair_mus=np.zeros((1, 1)),
        pair_muk=np.zeros((1, 1)), pair_mur=np.zeros((1, 1)))
    col = Collider(model, pairs=1, contacts=1)
    col.fams = (False,) * N_FAMILIES
    return col
