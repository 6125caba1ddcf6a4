"""Cylinder-cylinder: points of each cylinder against the other's signed
distance -- the facing cap's material square and its rim point nearest the
other's axis (cap on cap), the rims' local minima and crossings of the
other's radius (sampled, refined by golden section and bisection), the side
line facing the other (side on side, side across a cap) -- with the face a
point pressed in at a rim's edge leaves by chosen by the pair's
separating-axis normal, and the touching set reduced to four points as
box-box keeps them (:func:`cylinder_cylinder`)."""

from __future__ import annotations

import math

import numpy as np

from engine.mathutil import cross
from engine.collision.common import _cat, _golden, _norm, _segment_min, _segment_segment, EDGE_POINT_TOL
from engine.collision.cylinder import _circle_crossings, _crossing_points, _cylinder_rim, _cylinder_sdf, CYLINDER_FACE_COS, cylinder_plane, sphere_cylinder


#: rim samples per cap for the search of a rim's minima and radius
#: crossings against another cylinder (a convex function has few local
#: minima on a circle, and a circle crosses a cylinder's radius at most 4 times)
RIM_SAMPLES = 16


_RIM_ANG = 2.0 * math.pi * np.arange(RIM_SAMPLES) / RIM_SAMPLES


def _rim_points(centre, ex, ey, r, ang):
    """Points (k, 3) at angles ``ang`` (k,) rad on circles of centre
    ``centre`` (k, 3), radius ``r`` (k,) in the plane of the unit vectors
    ``ex``, ``ey`` (k, 3)."""
    return centre + r[:, None] * (np.cos(ang)[:, None] * ex + np.sin(ang)[:, None] * ey)


def _rim_search(c, R, hl, r, oc, oR, orr, sdf, margin):
    """Points on both rims of cylinders (c, R, hl, r) found against other
    cylinders (centre ``oc``, rotation ``oR``, radius ``orr``) by sampling
    each rim at RIM_SAMPLES angles:

    * the rim's local minima of the other body's signed distance
      (``sdf(rows (j,))`` returns it for those pair rows, gathered once, as
      a function of points (j, 3) -> (j,)): each sample no higher than
      its neighbours (one of them strictly) is refined by golden section
      between them, and kept where it is deeper than both by
      EDGE_POINT_TOL (on a flat stretch -- a cap lying on a cap -- the
      rim's support points and the crossings stand for it);
    * the points where the rim crosses the other cylinder's radius (the
      sign changes of rho^2 - r^2 in its frame, bisected): where a cap
      lies offset on another cap these end the overlap of the two discs,
      and the support spans it.

    Samples farther than the margin (m, (k,) or None) are not refined.
    Returns (rows, points (j, 3), fid (j,)) with fid 16 + 16 cap + i for a
    minimum near sample i, 64 + 16 cap + i for a crossing after it."""
    m = c.shape[0]
    N = RIM_SAMPLES
    ax, ex, ey = R[:, :, 2], R[:, :, 0], R[:, :, 1]
    centres = c[:, None, :] + np.array([-1.0, 1.0])[None, :, None] * (hl[:, None] * ax)[:, None, :]  # (m, 2, 3)
    ring = r[:, None, None] * (np.cos(_RIM_ANG)[None, :, None] * ex[:, None, :]
                               + np.sin(_RIM_ANG)[None, :, None] * ey[:, None, :])  # (m, N, 3)
    P = (centres[:, :, None, :] + ring[:, None, :, :]).reshape(-1, 3)  # (m 2 N, 3)
    rows = np.repeat(np.arange(m), 2 * N)
    fv = sdf(rows)(P).reshape(m, 2, N)
    prev, nxt = np.roll(fv, 1, axis=2), np.roll(fv, -1, axis=2)
    lo_n = np.minimum(prev, nxt)
    cand = (fv <= lo_n) & (fv < np.maximum(prev, nxt))
    if margin is not None:
        # the signed distance is 1-Lipschitz: within an arc of 2 pi r / N
        # of a sample it drops at most that much
        cand &= fv - (2.0 * math.pi / N) * r[:, None, None] < margin[:, None, None]
    out_r, out_p, out_f = [], [], []
    kk, cap, i = np.nonzero(cand)
    if kk.size:
        cen, exk, eyk, rk = centres[kk, cap], ex[kk], ey[kk], r[kk]
        f_k = sdf(kk)
        th, f_th = _golden(lambda a: f_k(_rim_points(cen, exk, eyk, rk, a)),
                           _RIM_ANG[i] - 2.0 * math.pi / N, _RIM_ANG[i] + 2.0 * math.pi / N)
        keep = np.flatnonzero(f_th < lo_n[kk, cap, i] - EDGE_POINT_TOL)
        out_r.append(kk[keep])
        out_p.append(_rim_points(cen[keep], exk[keep], eyk[keep], rk[keep], th[keep]))
        out_f.append(16 + 16 * cap[keep] + i[keep])
    # radius crossings: q = rho^2 - r^2 of the samples in the other's frame
    loc = np.einsum("kji,kj->ki", oR[rows], P - oc[rows])
    q = (loc[:, 0] ** 2 + loc[:, 1] ** 2 - orr[rows] ** 2).reshape(m, 2, N)
    qn = np.roll(q, -1, axis=2)
    # a rim on the other's radius (equal cans stacked) has q at round-off
    # all along: no crossings there, only sign changes that at least one
    # end makes clearly (1e-12 of r^2)
    cross = ((q < 0.0) != (qn < 0.0)) & (np.maximum(np.abs(q), np.abs(qn)) > 1e-12 * (orr * orr)[:, None, None])
    if margin is not None:
        cross &= np.minimum(fv, np.roll(fv, -1, axis=2)) - (2.0 * math.pi / N) * r[:, None, None] < margin[:, None, None]
    kk, cap, i = np.nonzero(cross)
    if kk.size:
        cen, exk, eyk, rk = centres[kk, cap], ex[kk], ey[kk], r[kk]
        oRk, ock, ork = oR[kk], oc[kk], orr[kk]
        lo = _RIM_ANG[i]
        hi = lo + 2.0 * math.pi / N
        neg_lo = q[kk, cap, i] < 0.0
        for _ in range(32):  # the bracket ends 2 pi / N 2^-32 = 9e-11 rad apart
            mid = 0.5 * (lo + hi)
            lm = np.einsum("kji,kj->ki", oRk, _rim_points(cen, exk, eyk, rk, mid) - ock)
            same = (lm[:, 0] ** 2 + lm[:, 1] ** 2 - ork ** 2 < 0.0) == neg_lo
            lo = np.where(same, mid, lo)
            hi = np.where(same, hi, mid)
        out_r.append(kk)
        # the bracket's end within the radius: the point is on the rim and
        # on or inside the other's side to 1e-11 m
        out_p.append(_rim_points(cen, exk, eyk, rk, np.where(neg_lo, lo, hi)))
        out_f.append(64 + 16 * cap + i)
    if not out_r:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(out_r), np.concatenate(out_p), np.concatenate(out_f)


def _cylinder_support(n, ax, hl, r):
    """Support half-width (k,) m of cylinders (axis ``ax`` (k, 3), half
    length ``hl``, radius ``r``) along unit directions ``n`` (k, 3)."""
    ca = np.abs(np.einsum("ki,ki->k", n, ax))
    return r * np.sqrt(np.maximum(1.0 - ca * ca, 0.0)) + hl * ca


def _cylinder_pair_normal(ca, axa, hla, ra, cb, axb, hlb, rb):
    """The pair's contact normal (k, 3) from the first cylinder toward the
    second, by the separating-axis test over three candidates: the two
    axes (a cap on the other body) and the direction between the axes'
    closest points (side on side), each oriented from first to second; the
    candidate of largest separation wins, caps preferred within 1e-9 m."""
    pa, pb = _segment_segment(ca - axa * hla[:, None], ca + axa * hla[:, None],
                              cb - axb * hlb[:, None], cb + axb * hlb[:, None])
    d = pb - pa
    dl = _norm(d)
    okd = dl > 1e-9
    dn = np.where(okd[:, None], d / np.where(okd, dl, 1.0)[:, None], axa)
    cand = np.stack([axa, axb, dn], axis=1)  # (k, 3, 3)
    dc = cb - ca
    proj = np.einsum("kci,ki->kc", cand, dc)
    cand = cand * np.where(proj >= 0.0, 1.0, -1.0)[:, :, None]
    sep = np.abs(proj) - np.stack([_cylinder_support(cand[:, j], axa, hla, ra)
                                   + _cylinder_support(cand[:, j], axb, hlb, rb) for j in range(3)], axis=1)
    sep[:, 2] = np.where(okd, sep[:, 2] - 1e-9, -np.inf)
    j = np.argmax(sep, axis=1)
    return cand[np.arange(ca.shape[0]), j]


def _cylinder_points_against(c, R, hl, r, oc, oR, ohl, orr, pn, margin):
    """One side of :func:`cylinder_cylinder`: points of cylinders (c, R,
    hl, r) against the other cylinders' exact signed distance, ``pn``
    (k, 3) the pair normal from these toward the others.  Points inside
    the other leave through its cap where pn is within 45 degrees of its
    axis, else through its side.  Returns contacts with normals from these
    toward the others."""
    m = c.shape[0]
    cap_face = np.abs(np.einsum("ki,ki->k", pn, oR[:, :, 2])) >= CYLINDER_FACE_COS

    def contact(p, rows):
        return sphere_cylinder(p, np.zeros(rows.size), oc[rows], oR[rows], ohl[rows], orr[rows], cap_face[rows])

    def sdf(rows):
        # gathered once per search, not at each of its 40 evaluations
        g = (oc[rows], oR[rows], ohl[rows], orr[rows])
        return lambda p: _cylinder_sdf(p, *g)

    out = []
    ax = R[:, :, 2]
    cosf = np.einsum("ki,ki->k", pn, ax)
    facing = np.abs(cosf) >= CYLINDER_FACE_COS
    # side on: each rim's support point toward the other body (the ends of
    # a side lying along the other)
    side = np.flatnonzero(~facing)
    if side.size:
        P, F, _ = _cylinder_rim(c[side], R[side], hl[side], r[side], -pn[side])
        P, F = P[:, [0, 4]].reshape(-1, 3), F[:, [0, 4]].reshape(-1)
        rows = np.repeat(side, 2)
        k, n, p, g, _ = contact(P, rows)
        out.append((rows[k], n, p, g, F))
    # cap on: the facing cap's material square (body x, y; a cap within
    # the other's cap rests on it) and its rim point nearest the other's
    # axis (the lens of two offset caps reaches farthest there).  Material
    # points, not the support-following ones of cylinder_plane: a lens's
    # support must not turn with the tilt's direction, which at a tilt of
    # 1e-6 rad swings the square and tipped an offset can over its edge
    fc = np.flatnonzero(facing)
    if fc.size:
        sgn = np.where(cosf[fc] >= 0.0, 1.0, -1.0)
        capc = c[fc] + ax[fc] * (sgn * hl[fc])[:, None]
        ex, ey = R[fc, :, 0], R[fc, :, 1]
        to = oc[fc] - capc
        to -= np.einsum("ki,ki->k", to, ax[fc])[:, None] * ax[fc]
        tl = _norm(to)
        okt = tl > 1e-9 * r[fc]
        tdir = np.where(okt[:, None], to / np.where(okt, tl, 1.0)[:, None], ex)
        dirs = np.stack([ex, ey, -ex, -ey, tdir], axis=1)  # (j, 5, 3)
        P = (capc[:, None, :] + dirs * r[fc, None, None]).reshape(-1, 3)
        rows = np.repeat(fc, 5)
        F = (np.where(sgn > 0, 9, 1)[:, None] + np.arange(5)[None, :]).reshape(-1)
        k, n, p, g, _ = contact(P, rows)
        out.append((rows[k], n, p, np.where(np.repeat(okt, 5) | (np.arange(rows.size) % 5 != 4), g, np.inf), F))
    # the rims' minima and radius crossings
    rows, pts, fid = _rim_search(c, R, hl, r, oc, oR, orr, sdf, margin)
    if rows.size:
        k, n, p, g, _ = contact(pts, rows)
        out.append((rows[k], n, p, g, fid[k]))
    # the side line facing the other body: its deepest point (side across
    # side) and its crossings of the other's radius (a side lying across a cap)
    t = pn - np.einsum("ki,ki->k", pn, ax)[:, None] * ax
    tl = _norm(t)
    rows = np.flatnonzero(tl > 1e-6)
    if rows.size:
        line = c[rows] + t[rows] * (r[rows] / tl[rows])[:, None]
        e0 = line - ax[rows] * hl[rows, None]
        e1 = line + ax[rows] * hl[rows, None]
        s, f_s, f_ends = _segment_min(sdf(rows), e0, e1)
        sel = np.flatnonzero(f_s < f_ends - EDGE_POINT_TOL)
        if sel.size:
            k, n, p, g, _ = contact(e0[sel] + (e1[sel] - e0[sel]) * s[sel, None], rows[sel])
            out.append((rows[sel[k]], n, p, g, np.full(k.size, 48)))
        for kk, n, p, g, f in _crossing_points(lambda x, rr: contact(x, rows[rr]), e0, e1,
                                               _circle_crossings(e0, e1, oc[rows], oR[rows], orr[rows]), 49):
            out.append((rows[kk], n, p, g, f))
    return _cat(out)


def cylinder_cylinder(ca, Ra, hla, ra, cb, Rb, hlb, rb, margin=None):
    """Cylinder against cylinder, as points of each against the other's
    exact signed distance (the box-cylinder method, with a circle where the
    box had corners and edges):

    * while a cap faces the other body (within 45 degrees of the pair
      normal): that cap's material square (body x, y) and its rim point
      nearest the other's axis -- a cap standing on a cap, offset or not;
      else each rim's support point toward the other (:func:`_cylinder_rim`
      along the pair normal) -- a side lying along a side;
    * each rim's local minima of the other's signed distance (sampled and
      refined, :func:`_rim_search`): a rim on a side, rim across rim, a
      tilted cap on its edge;
    * each rim's crossings of the other's radius: a cap offset on a cap
      rests on the ends of the two discs' overlap;
    * each side line facing the other body (along the pair normal): its
      minimum (side across side) and its crossings of the other's radius (a
      side lying across a cap).

    The pair normal is a separating-axis choice among the two axes and the
    direction between the axes' closest points
    (:func:`_cylinder_pair_normal`); it picks the features and the face a
    point pressed in at a rim's edge leaves by, while each contact's own
    normal and gap are those of the other's signed distance at its point.
    The touching set is then cut to four points (:func:`_four_points`).
    Separated, the smallest gap is the distance between the solids.
    Normal from the first cylinder to the second; feature ids: the first
    cylinder's points 0-127 (rim support 0 and 8, facing cap's square and
    nearest point 1-5 or 9-13, rim minima 16-47, side line 48-50, rim
    crossings 64-95), the second's the same plus 128."""
    axa, axb = Ra[:, :, 2], Rb[:, :, 2]
    pn = _cylinder_pair_normal(ca, axa, hla, ra, cb, axb, hlb, rb)
    k0, n0, p0, g0, f0 = _cylinder_points_against(ca, Ra, hla, ra, cb, Rb, hlb, rb, pn, margin)
    k1, n1, p1, g1, f1 = _cylinder_points_against(cb, Rb, hlb, rb, ca, Ra, hla, ra, -pn, margin)
    return _four_points(_cat([(k0, n0, p0, g0, f0), (k1, -n1, p1, g1, 128 + f1)]), pn, margin)


#: m: the touching set of a pair, reduced to four points, is the contacts
#: within this of its deepest; farther ones (speculative) are all kept
MANIFOLD_BAND = 1e-3


#: a manifold point is kept as a third or fourth only where it stands off
#: the line of the first two by this fraction of their distance
MANIFOLD_SPREAD = 0.01


#: m: a second manifold point closer than this to the first is not kept
MANIFOLD_MIN_SPAN = 1e-6


def _four_points(cs, pn, margin):
    """The touching set of each pair -- its contacts within MANIFOLD_BAND
    of its deepest -- reduced to at most four points as box-box keeps them
    (the deepest, the one farthest from it, and on either side of their
    line the one farthest from it, all measured across the pair normal
    ``pn`` (k, 3)), without near repeats; the pair's farther (speculative)
    contacts are all kept.  The features of the two bodies often name the
    same point twice (a rim crossing seen from each side) or nearly (a rim
    support point a few mm from a crossing): with them in, a can offset on
    an equal can turned at 2e-3 rad/s within a step instead of resting.
    Contacts beyond the margin (k,) are dropped first.  Separated, the
    deepest is the smallest gap: the distance stays exact."""
    k, n, p, g, f = cs
    if margin is not None:
        keep = g < margin[k]
        k, n, p, g, f = k[keep], n[keep], p[keep], g[keep], f[keep]
    if k.size == 0:
        return k, n, p, g, f
    m = pn.shape[0]
    first = np.full(m, np.inf)
    np.minimum.at(first, k, g)
    # deepest first, gaps within 1e-9 m of the deepest counted as ties and
    # ordered by feature id: on a flat support the round-off must not pick
    # another first point (and with it another four) every step
    o = np.lexsort((f, np.where(g <= first[k] + 1e-9, -np.inf, g), k))
    k, n, p, g, f = k[o], n[o], p[o], g[o], f[o]
    # a point clear of the other body (not the pair's deepest) whose normal
    # turns more than 45 degrees from the pair normal reaches round the
    # other's edge, and is dropped.  Two logs of equal length side by side,
    # one slid 0.8 um along its axis, put the longer one's rim end just past
    # the shorter one's cap, at the round-off distance from its rim's edge
    # with a normal along the axes: as a manifold point it stood in for the
    # shorter one's rim end on the other's side, and the top log of a pile
    # sank 0.1 mm at that end; as a speculative row it turned the pair's
    # friction patch (whose normal is the mean of the rows') 63 degrees
    # toward the axes, and the pile held at 0.22 of friction where
    # statics needs 0.274.  Sliding along the axes, such a point moves
    # along the other's side, not into it.
    around = (g > first[k] + 1e-9) & (np.einsum("ki,ki->k", n, pn[k]) < CYLINDER_FACE_COS)
    k, n, p, g, f = k[~around], n[~around], p[~around], g[~around], f[~around]
    far = np.flatnonzero(g > first[k] + MANIFOLD_BAND)
    near = np.flatnonzero(g <= first[k] + MANIFOLD_BAND)
    k, n, p, g, f, rest = k[near], n[near], p[near], g[near], f[near], (k[far], n[far], p[far], g[far], f[far])
    cnt = np.bincount(k, minlength=m)
    W = int(cnt.max())
    slot = np.arange(k.size) - (np.cumsum(cnt) - cnt)[k]
    idx = np.full((m, W), -1, np.int64)
    idx[k, slot] = np.arange(k.size)
    valid = idx >= 0
    E = p[np.where(valid, idx, 0)] - p[np.where(valid[:, :1], idx[:, :1], 0)]  # from each pair's deepest
    E -= np.einsum("kwi,ki->kw", E, pn)[:, :, None] * pn[:, None, :]
    dd = np.where(valid, np.einsum("kwi,kwi->kw", E, E), -np.inf)
    r = np.arange(m)
    # the farthest point, of those within MANIFOLD_MIN_SPAN of the farthest
    # the deepest (rows are in depth order): two logs of equal length side
    # by side, one slid along its axis, have at the shorter one's end its
    # rim point on the other's side (normal exact) and, 7e-6 m round the
    # rim, the longer one's rim crossing the other's radius (at 1e-9 m of
    # overlap its normal is 1.4e-4 rad off, and it turns further as the
    # overlap grows), 1e-10 m farther from the deepest
    sp = np.sqrt(np.maximum(dd, 0.0))
    i1 = np.argmax(valid & (sp >= sp.max(axis=1, keepdims=True) - MANIFOLD_MIN_SPAN), axis=1)
    span = sp[r, i1]
    area = np.einsum("kwi,ki->kw", cross(np.broadcast_to(E[r, i1][:, None, :], E.shape), E), pn)
    i2 = np.argmax(np.where(valid, area, -np.inf), axis=1)
    i3 = np.argmin(np.where(valid, area, np.inf), axis=1)
    has = cnt > 0
    ok1 = has & (span > MANIFOLD_MIN_SPAN)
    ok2 = ok1 & (area[r, i2] > MANIFOLD_SPREAD * span * span)
    ok3 = ok1 & (-area[r, i3] > MANIFOLD_SPREAD * span * span)
    sel = np.concatenate([idx[has, 0], idx[ok1, i1[ok1]], idx[ok2, i2[ok2]], idx[ok3, i3[ok3]]])
    sel.sort()
    if rest[0].size == 0:
        return k[sel], n[sel], p[sel], g[sel], f[sel]
    return _cat([(k[sel], n[sel], p[sel], g[sel], f[sel]), rest])
