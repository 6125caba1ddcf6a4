"""The CCD stage's end-pose check in one compiled call: the pairs that
moved far enough to overlap beyond the tolerance
(:func:`engine.flight.end_pose_pairs`), less those whose end pose
provably has no contact that deep (:func:`end_pose_clear`).

A missed impact (engine/ccd.py ``missed_impacts``) is a contact of the
end pose deeper than ``lim`` = correction slop + ``MISS_TOL``: the end-pose
collision runs with the margin -lim and keeps only contacts whose gap is
below it.  A pair whose least possible end gap is provably above -lim
gives that collision no contact, so it can never be one -- a ball rolling
on the floor, a block sliding on it, a cylinder rolling: their surfaces
move by more than lim a step (so :func:`engine.flight.end_pose_pairs`
keeps them), but they end resting within the slop.  Leaving such pairs
out leaves the collision's contacts, and so every decision made from
them, unchanged (the same bits), and lets the steady step
(engine/fused/steady.py) finish the step itself instead of returning to the
Python CCD stage to find nothing.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from physbench.engine.collision.collide import collide_packed
from physbench.engine.flight import end_pose_pairs
from physbench.engine.geometry import EndPose, Geometry, Pairs, Shapes, Statics

SPHERE, BOX, CAPSULE, CYLINDER = 0, 1, 2, 3  # engine.model's shape codes

#: how far (m) a pair's lower bound of its end gap must lie above -lim
#: before it is left out: far beyond the rounding of the collision's
#: arithmetic (~1e-16 relative) and of the bound's own (a cylinder's
#: sqrt(1 - d^2) near d = 1: ~1e-8 of its radius), far below the depths
#: that decide a missed impact (lim = 0.3 mm at the defaults).  Plus
#: CLEAR_REL of the coordinates' size, for scenes far from the origin.
CLEAR_TOL = 1e-6
CLEAR_REL = 1e-12


@njit(cache=True, inline="always")
def _plane_depth(s, r, hx, hy, hz, hl, R, k, n0, n1, n2):
    """How far body k's surface reaches below its centre along -n (unit n
    (3,)): max over its points p of n . (x - p) -- sphere r; box the sum
    of its half extents times |n . axis|; capsule r + half length |n .
    axis|; cylinder half length |n . axis| + r sqrt(1 - (n . axis)^2)
    (its rim points: the centre +- the axis' half length plus a unit
    vector of the cap plane times r)."""
    if s == SPHERE:
        return r
    d0 = n0 * R[k, 0, 0] + n1 * R[k, 1, 0] + n2 * R[k, 2, 0]
    d1 = n0 * R[k, 0, 1] + n1 * R[k, 1, 1] + n2 * R[k, 2, 1]
    d2 = n0 * R[k, 0, 2] + n1 * R[k, 1, 2] + n2 * R[k, 2, 2]
    if s == BOX:
        return hx * abs(d0) + hy * abs(d1) + hz * abs(d2)
    if s == CAPSULE:
        return r + hl * abs(d2)
    t = 1.0 - d2 * d2
    return hl * abs(d2) + r * math.sqrt(t if t > 0.0 else 0.0)


@njit(cache=True)
def end_pose_clear(x1, shapes, statics, lim, out, nb, npl, ns):
    """Leave out, in place and keeping the order, the moved pairs (the
    front ``nb`` of ``out.ci``/``cj``, ``npl`` of ``cbp``/``cpk``, ``ns`` of
    ``cbs``/``csk``, :func:`engine.flight.end_pose_pairs`; ``out`` an
    engine.geometry.EndPose) whose end pose (x1 (n, 3), ``out.R1`` (n, 3,
    3); the bodies' engine.geometry.Shapes ``shapes``, the Statics
    ``statics``) provably has no contact with a gap below
    -``lim`` (m): a lower bound of every contact's gap lies above -lim by
    more than ``CLEAR_TOL`` (+ ``CLEAR_REL`` of the coordinates).  Returns
    the counts left (body pairs, planes, static boxes).

    The bounds (each contact's gap is a signed distance the collision
    computes, engine/collision):

    * body against plane (``planes_n``/``planes_off`` rows; every contact
      a point p of the body, gap n . p - offset): n . x - offset - the
      body's reach below its centre (:func:`_plane_depth`), every shape;
    * sphere against sphere, sphere against capsule, capsule against
      capsule (gaps |pa - pb| - ra - rb between points of their centres'
      segments) and sphere against box (the box's exact signed distance
      to the centre, minus the radius): |x_i - x_j| - the two bounding
      radii;
    * sphere against a static box: the centre's distance to the box's
      AABB (``slo``/``shi`` (k, 3)) minus the radius (0 inside it);
    * any other pair is kept (box against box and the cylinder pairs: a
      clipped manifold or an approximate distance, no such bound)."""
    shape, radius, half, half_length, bound_radius = (shapes.shape, shapes.radius, shapes.half, shapes.half_length,
                                                      shapes.bound_radius)
    planes_n, planes_off, slo, shi = statics.planes_n, statics.planes_off, statics.slo, statics.shi
    ci, cj, cbp, cpk, cbs, csk, R1 = out.ci, out.cj, out.cbp, out.cpk, out.cbs, out.csk, out.R1
    thr = -lim + CLEAR_TOL
    m = 0
    for k in range(nb):
        i, j = ci[k], cj[k]
        si, sj = shape[i], shape[j]
        round_i = si == SPHERE or si == CAPSULE
        round_j = sj == SPHERE or sj == CAPSULE
        keep = True
        if (round_i and round_j) or (si == SPHERE and sj == BOX) or (si == BOX and sj == SPHERE):
            d0, d1, d2 = x1[j, 0] - x1[i, 0], x1[j, 1] - x1[i, 1], x1[j, 2] - x1[i, 2]
            size = abs(x1[i, 0]) + abs(x1[i, 1]) + abs(x1[i, 2])
            bound = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - bound_radius[i] - bound_radius[j]
            keep = not bound > thr + CLEAR_REL * size
        if keep:
            ci[m] = i
            cj[m] = j
            m += 1
    nb = m
    m = 0
    for k in range(npl):
        i, p = cbp[k], cpk[k]
        n0, n1, n2 = planes_n[p, 0], planes_n[p, 1], planes_n[p, 2]
        c = n0 * x1[i, 0] + n1 * x1[i, 1] + n2 * x1[i, 2]
        bound = c - planes_off[p] - _plane_depth(shape[i], radius[i], half[i, 0], half[i, 1], half[i, 2],
                                                 half_length[i], R1, i, n0, n1, n2)
        if not bound > thr + CLEAR_REL * (abs(c) + abs(planes_off[p])):
            cbp[m] = i
            cpk[m] = p
            m += 1
    npl = m
    m = 0
    for k in range(ns):
        i, s = cbs[k], csk[k]
        keep = True
        if shape[i] == SPHERE:
            dd = 0.0
            size = 0.0
            for c in range(3):
                v = x1[i, c]
                e = slo[s, c] - v if v < slo[s, c] else (v - shi[s, c] if v > shi[s, c] else 0.0)
                dd += e * e
                size += abs(v)
            keep = not math.sqrt(dd) - radius[i] > thr + CLEAR_REL * size
        if keep:
            cbs[m] = i
            csk[m] = s
            m += 1
    return nb, npl, m


@njit(cache=True)
def end_pose_candidates(x0, q0, x1, q1, shapes, statics, lim, has_fast, fast, pairs, out):
    """:func:`engine.flight.end_pose_pairs` (the candidate ``pairs``, an
    engine.geometry.Pairs, that moved by more than ``lim`` m between the
    start pose x0 (n, 3), q0 (n, 4) and the end pose x1, q1 -- with
    ``has_fast`` only those of a body flagged in ``fast`` (n,) --, into the
    front of ``out.ci`` ... ``csk``, ``out`` an engine.geometry.EndPose;
    ``out.R1`` (n, 3, 3) the rotations of q1 when any did), then
    :func:`end_pose_clear` over them: the counts of the pairs whose end pose
    may hold a missed impact (body pairs, planes, static boxes).  One call
    (the steady step's and the CCD stage's, engine/ccd.py
    ``end_pose_pairs``)."""
    nb, npl, ns = end_pose_pairs(x0, q0, x1, q1, shapes.bound_radius, lim, has_fast, fast, pairs, out)
    if nb + npl + ns == 0:
        return 0, 0, 0
    return end_pose_clear(x1, shapes, statics, lim, out, nb, npl, ns)


@njit(cache=True)
def end_pose_call(x0, q0, x1, q1, kgeo, lim, has_fast, fast, pi, pj, bp, pk, bs, sk, kout):
    """:func:`end_pose_candidates` from Python (the CCD stage,
    engine.ccd_kept.end_pose_pairs) with its kept arrays in Packs (one
    pointer each to unbox; named tuples handed from Python are typed off
    numba's fast path): ``kgeo`` of the model's geometry (``shapes``,
    ``statics``: engine.ccd_kept.Geometry), ``kout`` of the buffers (an
    engine.geometry.EndPose); the pairs one by one."""
    g = kgeo.items
    return end_pose_candidates(x0, q0, x1, q1, g.shapes, g.statics, lim, has_fast, fast,
                               Pairs(pi=pi, pj=pj, bp=bp, pk=pk, bs=bs, sk=sk), kout.items)


#: contacts as :func:`missed_candidates` reads them: bodies ``a``, ``b``
#: (m,) (b = n for statics), static index ``sidx`` (m,) (-1 for a body
#: pair), ``gap`` (m,) m, ``point`` (m, 3) m, feature ids ``fid`` (m,)
FeatureContacts = namedtuple("FeatureContacts", ("a", "b", "sidx", "gap", "point", "fid"))

#: relative slack of the matching radius in :func:`missed_candidates`: a
#: point within (1 - NEAR_SLACK) of it is near for sure; one at the radius
#: (up to the arithmetic's rounding, ~1e-16) is left to the Python decision
NEAR_SLACK = 1e-9


@njit(cache=True)
def missed_candidates(n_statics, end, start, imp_rows, skip, drop, x1, R1, x0, R0, shapes, static_shape, touch_tol,
                      lim, cand):
    """Which end-pose contacts (``end``, a :class:`FeatureContacts`: the
    collision at the margin -lim of the moved pairs) may make their pair a
    missed impact (engine.ccd.missed_impacts' rule): ``cand`` (>= m,) bool
    set True on them; returns how many.  The start contacts ``start`` (m0
    of them: the step's); ``imp_rows`` their impact rows; ``skip`` the
    pair codes that are impacts already, ``drop`` those left out
    (``ctx.missed_skip``); the start and end poses x0, R0, x1, R1; the
    bodies' engine.geometry.Shapes ``shapes`` (n of them), the static shape
    codes ``static_shape``.

    A contact of a pair in ``drop`` is never one.  Of a pair apart at the
    start (no impact, least start gap > ``touch_tol``) every contact is
    one.  Of a pair touching at the start (or an impact) a contact is one
    when it lies, in body a's frame, farther than the matching radius (0.1
    bounding radius + 0.1 mm) from every start contact of the pair within
    ``lim`` (or an impact row), and, for pairs whose feature ids name
    material features (all but box against box), its feature id is none of
    theirs -- the same rule; the radius test with a relative slack of
    ``NEAR_SLACK``, so that a point at the radius is left to the exact
    decision in Python.  A superset of the contacts that decide a missed
    impact, so the Python decision runs only over their pairs and finds
    the same impacts (tests/test_ccd_end_clear.py)."""
    a, b, sidx, gap, point, fid = end.a, end.b, end.sidx, end.gap, end.point, end.fid
    a0, b0, sidx0, gap0, point0, fid0 = start.a, start.b, start.sidx, start.gap, start.point, start.fid
    bound_radius, shape = shapes.bound_radius, shapes.shape
    n = shape.shape[0]
    m, m0 = gap.shape[0], gap0.shape[0]
    ns1 = n_statics + 1
    code0 = np.empty(m0, np.int64)
    for k in range(m0):
        code0[k] = (a0[k] * (n + 1) + b0[k]) * ns1 + (sidx0[k] + 1)
    order = np.argsort(code0, kind="mergesort")
    sorted0 = code0[order]
    imp = np.zeros(m0, np.bool_)
    for k in range(imp_rows.shape[0]):
        imp[imp_rows[k]] = True
    skips = np.sort(skip)
    found = 0
    for r in range(m):
        cand[r] = False
        u = (a[r] * (n + 1) + b[r]) * ns1 + (sidx[r] + 1)
        dropped = False
        for k in range(drop.shape[0]):
            if drop[k] == u:
                dropped = True
        if dropped:
            continue
        lo = np.searchsorted(sorted0, u, side="left")
        hi = np.searchsorted(sorted0, u, side="right")
        g0 = np.inf
        for k in range(lo, hi):
            g = gap0[order[k]]
            if g < g0:
                g0 = g
        t = np.searchsorted(skips, u, side="left")
        is_imp = t < skips.shape[0] and skips[t] == u
        if not (is_imp or not g0 > touch_tol):
            cand[r] = True  # apart at the start
            found += 1
            continue
        i = a[r]
        d0, d1, d2 = point[r, 0] - x1[i, 0], point[r, 1] - x1[i, 1], point[r, 2] - x1[i, 2]
        l0 = (d0 * R1[i, 0, 0] + d1 * R1[i, 1, 0]) + d2 * R1[i, 2, 0]
        l1 = (d0 * R1[i, 0, 1] + d1 * R1[i, 1, 1]) + d2 * R1[i, 2, 1]
        l2 = (d0 * R1[i, 0, 2] + d1 * R1[i, 1, 2]) + d2 * R1[i, 2, 2]
        tol = 0.1 * bound_radius[i] + 1e-4
        if shape[i] != BOX:
            stable = True
        elif b[r] < n:
            stable = shape[b[r]] != BOX
        else:
            stable = static_shape[sidx[r]] != 1  # engine.model.S_BOX
        dmin = np.inf
        member = False
        for kk in range(lo, hi):
            k = order[kk]
            if not (gap0[k] <= lim or imp[k]):
                continue
            e0, e1, e2 = point0[k, 0] - x0[i, 0], point0[k, 1] - x0[i, 1], point0[k, 2] - x0[i, 2]
            p0 = (e0 * R0[i, 0, 0] + e1 * R0[i, 1, 0]) + e2 * R0[i, 2, 0]
            p1 = (e0 * R0[i, 0, 1] + e1 * R0[i, 1, 1]) + e2 * R0[i, 2, 1]
            p2 = (e0 * R0[i, 0, 2] + e1 * R0[i, 1, 2]) + e2 * R0[i, 2, 2]
            dd = ((l0 - p0) * (l0 - p0) + (l1 - p1) * (l1 - p1)) + (l2 - p2) * (l2 - p2)
            if dd < dmin:
                dmin = dd
            if fid0[k] == fid[r]:
                member = True
        new = not dmin <= tol * tol * (1.0 - NEAR_SLACK)
        if stable and member:
            new = False
        if new:
            cand[r] = True
            found += 1
    return found


@njit(cache=True)
def missed_any(x0, q0, x1, q1, kgeo, lim, has_fast, fast, pairs, kout, kcol, narrow, cands):
    """Whether the CCD stage's end-pose check (engine/ccd.py
    ``missed_impacts``) may find a missed impact, in one call:
    :func:`end_pose_call` (its arguments; ``pairs`` an engine.geometry.Pairs
    of its pi, pj, bp, pk, bs, sk), the collision of the moved pairs at the
    end pose with the margin -``lim`` into the collider's buffers
    (``kcol``: its Pack, engine.collision.dispatch.Collider.packed;
    ``narrow``: (margins, no_sweep, face_points): its margin rows, (n,)
    zeros, engine.collision.box.EDGE_FACE_POINTS), as Collider.run makes it, then
    :func:`missed_candidates` over those contacts (``cands``: (n_statics,
    start, imp_rows, skip, drop, R0, touch_tol, cand), its other
    arguments).  Returns 0 when no contact can be
    one (nothing moved, no contact, no candidate: no missed impact), else
    the candidates' count, or -1 when a buffer (the collider's, ``cand``)
    is short: either way the caller's Python path then decides, from the
    start (the same arithmetic: tests/test_ccd_end_clear.py)."""
    # (the Pack is an argument of its own: inside a tuple it would make
    # numba type the whole tuple in Python at every call, ~60-80 us:
    # tests/test_ccd_event_path.py::test_event_kernels_take_no_pack_inside_a_tuple)
    margins, no_sweep, face_points = narrow
    n_statics, start, imp_rows, skip, drop, R0, touch_tol, cand = cands
    nb, npl, ns = end_pose_call(x0, q0, x1, q1, kgeo, lim, has_fast, fast, pairs.pi, pairs.pj, pairs.bp, pairs.pk,
                                pairs.bs, pairs.sk, kout)
    if nb + npl + ns == 0:
        return 0
    out = kout.items
    col = kcol.items
    if col.W.perm.shape[0] < max(nb, npl, ns):
        return -1
    R1 = out.R1
    cnt, need_k, need_s = collide_packed(kcol, x1, R1, out.ci[:nb], out.cj[:nb], margins, out.cbp[:npl],
                                         out.cpk[:npl], out.cbs[:ns], out.csk[:ns], bool(True), -lim, no_sweep,
                                         face_points)
    if need_k > col.A.c.shape[0] or need_s > col.slot.g.shape[0] or cnt > col.out.a.shape[0]:
        return -1
    if cnt == 0:
        return 0
    if cand.shape[0] < cnt:
        return -1
    o = col.out
    g = kgeo.items
    return missed_candidates(n_statics, FeatureContacts(a=o.a[:cnt], b=o.b[:cnt], sidx=o.sidx[:cnt], gap=o.gap[:cnt],
                                                        point=o.point[:cnt], fid=o.fid[:cnt]),
                             start, imp_rows, skip, drop, x1, R1, x0, R0, g.shapes, g.static_shape, touch_tol, lim,
                             cand)


@njit(cache=True)
def lone_impact(rows, tau, h, ca, cb, csidx, point, fid, x, R0, shape, static_shape, n_statics):
    """The CCD stage's pick of the earliest impact (engine/ccd.py
    ``CCD.__call__``) when the step's impact rows ``rows`` (k,) (into the
    contacts ``ca``, ``cb``, ``csidx``, ``point`` (m, 3), ``fid``) are of
    one pair (a lone impact), as the numpy form computes it: the earliest
    row ``j`` (np.argmin of the first time estimates ``tau`` (k,) s), its
    time clipped to [0, ``h``] as ``float(min(max(tau[j], 0.0), h))``, the
    rows' pair codes (engine.contact.topology._pair_codes_abs), then, when
    they are one pair: its bodies a, b, static index, the rows' points in
    body a's frame at the start pose (x (n, 3), R0 (n, 3, 3); einsum
    "ki,ij->kj" of point - x[a] and R0[a], summed (p0 + p1) + p2 as
    engine.ccd_gap.gap does), their feature ids sorted and distinct, and
    whether the pair's ids name material features
    (engine.ccd_kept._stable_features over the bodies' ``shape`` and the
    statics' ``static_shape`` codes).  Returns (j, t, codes, lone, a, b,
    sidx, loc, fids, stable); with ``lone`` False only j, t and the codes
    are set (tests/test_ccd_event_path.py)."""
    k = rows.shape[0]
    n = x.shape[0]
    j = -1
    for i in range(k):  # np.argmin: the first NaN, else the first least
        if math.isnan(tau[i]):
            j = i
            break
    if j < 0:
        j = 0
        for i in range(1, k):
            if tau[i] < tau[j]:
                j = i
    t = tau[j]
    if 0.0 > t:  # max(t, 0.0), then min(t, h), as Python's builtins
        t = 0.0
    if h < t:
        t = h
    codes = np.empty(k, np.int64)
    lone = True
    for i in range(k):
        r = rows[i]
        codes[i] = (ca[r] * (n + 1) + cb[r]) * (n_statics + 1) + (csidx[r] + 1)
        lone &= codes[i] == codes[0]
    loc = np.empty((k if lone else 0, 3))
    if not lone:
        return j, t, codes, False, -1, -1, -1, loc, np.empty(0, np.int64), False
    r = rows[j]
    a, b, sidx = ca[r], cb[r], csidx[r]
    for i in range(k):
        r = rows[i]
        d0, d1, d2 = point[r, 0] - x[a, 0], point[r, 1] - x[a, 1], point[r, 2] - x[a, 2]
        for c in range(3):
            loc[i, c] = (d0 * R0[a, 0, c] + d1 * R0[a, 1, c]) + d2 * R0[a, 2, c]
    f = np.empty(k, np.int64)
    for i in range(k):
        f[i] = fid[rows[i]]
    if shape[a] != BOX:
        stable = True
    elif b < n:
        stable = shape[b] != BOX
    else:
        stable = static_shape[sidx] != 1  # engine.model.S_BOX
    return j, t, codes, True, a, b, sidx, loc, np.unique(f), stable


def warm_up() -> None:
    """Compile (or load) :func:`end_pose_candidates`,
    :func:`missed_candidates`, :func:`missed_any` and :func:`lone_impact`
    with the CCD stage's argument types (engine/jit.py, through
    engine.ccd.warm_up)."""
    n = 2
    x = np.zeros((n, 3))
    x[1, 2] = 1.0
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    i = np.arange(n, dtype=np.int64)
    one = np.ones(n)
    shapes = Shapes(shape=np.array([0, 1], np.int64), radius=one, half=np.ones((n, 3)), half_length=one,
                    bound_radius=one)
    statics = Statics(planes_n=np.array([[0.0, 0.0, 1.0]]), planes_off=np.zeros(1), slo=np.zeros((1, 3)),
                      shi=np.ones((1, 3)))
    pairs = Pairs(pi=i[:1], pj=i[1:], bp=i, pk=np.zeros(n, np.int64), bs=i, sk=np.zeros(n, np.int64))
    e = np.empty(n, np.int64)
    out = EndPose(ci=e, cj=e.copy(), cbp=e.copy(), cpk=e.copy(), cbs=e.copy(), csk=e.copy(), sw=np.empty(n),
                  R1=np.empty((n, 3, 3)))
    from physbench.engine.pack import Pack

    kgeo = Pack(Geometry(shapes=shapes, statics=statics, static_shape=np.zeros(1, np.int64)))
    for has_fast in (False, True):
        end_pose_call(x, q, x + 1.0, q.copy(), kgeo, 0.1, has_fast, np.ones(n, np.bool_), *pairs, Pack(out))
    z = np.zeros(0, np.int64)
    missed_candidates(1, FeatureContacts(a=i[:1], b=i[1:], sidx=i[:1] - 1, gap=np.zeros(1), point=np.zeros((1, 3)),
                                         fid=i[:1]),
                      FeatureContacts(a=i[:1], b=i[1:], sidx=i[:1] - 1, gap=np.zeros(1), point=np.zeros((1, 3)),
                                      fid=i[:1]),
                      z, z, z, x, np.empty((n, 3, 3)), x, np.empty((n, 3, 3)),
                      Shapes(shape=np.array([0, 1], np.int64), radius=one, half=np.ones((n, 3)), half_length=one,
                             bound_radius=one),
                      np.zeros(1, np.int64), 1e-6, 3e-4, np.zeros(n, np.bool_))
    from physbench.engine.ccd_gap import warm_collider
    from physbench.engine.collision import box

    col = warm_collider()
    k0 = FeatureContacts(a=z, b=z, sidx=z, gap=np.zeros(0), point=np.zeros((0, 3)), fid=z)
    for has_fast in (False, True):  # (no pair: compiled whole, run to its first return)
        missed_any(x, q, x + 1.0, q.copy(), kgeo, 0.1, has_fast, np.ones(n, np.bool_),
                   Pairs(pi=z, pj=z, bp=z, pk=z, bs=z, sk=z), Pack(out), col.packed(),
                   (col.margins, np.zeros(n), box.EDGE_FACE_POINTS),
                   (1, k0, z, z, z, np.empty((n, 3, 3)), 1e-6, np.zeros(n, np.bool_)))
    lone_impact(i[:1], np.zeros(1), 0.01, i, i, i - 1, np.zeros((n, 3)), i, x, np.empty((n, 3, 3)), i, z, 1)
