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
from collections import namedtuple

import numpy as np
from numba import njit

from physbench.engine.collision.kernels import (EDGE_POINT_TOL, CYLINDER_FACE_COS, GOLDEN, SDF_CYLINDER, Cylinders, Slots,
                                      circle_crossings1, cylinder_rim1, gather, norm3, one_cylinder, pair_slots,
                                      segment_min1, segment_segment, sdf1, slots, sphere_cylinder1)


#: rim samples per cap for the search of a rim's minima and radius
#: crossings against another cylinder (a convex function has few local
#: minima on a circle, and a circle crosses a cylinder's radius at most 4 times)
RIM_SAMPLES = 16

#: m: the touching set of a pair, reduced to four points, is the contacts
#: within this of its deepest; farther ones (speculative) are all kept
MANIFOLD_BAND = 1e-3

#: a manifold point is kept as a third or fourth only where it stands off
#: the line of the first two by this fraction of their distance
MANIFOLD_SPREAD = 0.01

#: m: a second manifold point closer than this to the first is not kept
MANIFOLD_MIN_SPAN = 1e-6

#: candidate points of one side of a pair at most: rim support or cap
#: square (5), rim minima and crossings (2 caps x RIM_SAMPLES each), side
#: line minimum and crossings (3)
_SIDE_MAX = 5 + 4 * RIM_SAMPLES + 3

#: the kernel's scratch as slices of the collider's kept work (nothing
#: allocated a call or a pair, tests/test_engine_steady_gyro.py::
#: test_every_gyroscopic_setting_steps_without_allocating): floats -- a
#: pair's candidates' n, p (B, 3), g (:class:`Candidates`), the
#: :class:`ManifoldWork`'s key (B,), E (B, 3), sp, area (B,), the axes and
#: normals (12), :func:`_pair_normal`'s (27), one side's
#: (:func:`_points_against`: _SIDE_FW) --; ints -- the candidates' f, the
#: work's order, near, sel (B,) and one side's fid, infg (_SIDE_MAX,)
_B = 2 * _SIDE_MAX
_RIM_FW = 12 + 2 * RIM_SAMPLES
_SIDE_FW = 3 * _SIDE_MAX + 47 + _RIM_FW
_PAIR_FW = 13 * _B + 12 + 27
YY_FW = _PAIR_FW + _SIDE_FW
YY_IW = 4 * _B + 2 * _SIDE_MAX

#: a pair's candidate contacts (B of room): normals ``n``, points ``p`` (B,
#: 3), gaps ``g`` (B,) m, feature ids ``f`` (B,) int64
Candidates = namedtuple("Candidates", ("n", "p", "g", "f"))

#: :func:`_four_points`' scratch: the candidates' ``order``, sort ``key``,
#: offsets ``E`` (B, 3) across the normal, spans ``sp`` and ``area`` (B,);
#: the touching set ``near`` and the kept flags ``sel`` (B,) int64
ManifoldWork = namedtuple("ManifoldWork", ("order", "key", "E", "sp", "area", "near", "sel"))


@njit(cache=True)
def _rim_point(cen, ex, ey, r, a, out):
    """out = cen + r (cos a ex + sin a ey): the point at angle a (rad) on a
    circle of centre cen (3,), radius r in the plane of ex, ey (3,)."""
    ca, sa = np.cos(a), np.sin(a)
    for i in range(3):
        out[i] = cen[i] + r * (ca * ex[i] + sa * ey[i])


@njit(cache=True)
def _rim_f(cen, ex, ey, r, a, oc, oR, oh, x):
    _rim_point(cen, ex, ey, r, a, x)
    return sdf1(SDF_CYLINDER, x[0], x[1], x[2], oc, oR, oh)


@njit(cache=True)
def _golden_rim(cen, ex, ey, r, lo, hi, oc, oR, oh, x):
    """Golden section (40 iterations) for the minimum of the other's signed
    distance over the rim's angles [lo, hi]; returns (angle, distance)."""
    x1 = hi - GOLDEN * (hi - lo)
    x2 = lo + GOLDEN * (hi - lo)
    f1 = _rim_f(cen, ex, ey, r, x1, oc, oR, oh, x)
    f2 = _rim_f(cen, ex, ey, r, x2, oc, oR, oh, x)
    for _ in range(40):
        if f1 < f2:
            hi = x2
            xn = hi - GOLDEN * (hi - lo)
            fn = _rim_f(cen, ex, ey, r, xn, oc, oR, oh, x)
            x1, x2, f1, f2 = xn, x1, fn, f1
        else:
            lo = x1
            xn = lo + GOLDEN * (hi - lo)
            fn = _rim_f(cen, ex, ey, r, xn, oc, oR, oh, x)
            x1, x2, f1, f2 = x2, xn, f2, fn
    s = 0.5 * (lo + hi)
    return s, _rim_f(cen, ex, ey, r, s, oc, oR, oh, x)


@njit(cache=True)
def _q(x, oc, oR, orr):
    """rho^2 - r^2 of the point x in the other cylinder's frame."""
    w0, w1, w2 = x[0] - oc[0], x[1] - oc[1], x[2] - oc[2]
    l0 = oR[0, 0] * w0 + oR[1, 0] * w1 + oR[2, 0] * w2
    l1 = oR[0, 1] * w0 + oR[1, 1] * w1 + oR[2, 1] * w2
    return l0 ** 2 + l1 ** 2 - orr ** 2


@njit(cache=True)
def _rim_search(c, R, hl, r, oc, oR, oh, margin, use_margin, pts, fid, cnt, rw):
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
    minimum near sample i, 64 + 16 cap + i for a crossing after it.
    ``rw`` (_RIM_FW,) scratch."""
    N = RIM_SAMPLES
    step = 2.0 * math.pi / N
    cen = rw[0:3]
    ex = rw[3:6]
    ey = rw[6:9]
    x = rw[9:12]
    fv = rw[12:12 + N]
    q = rw[12 + N:12 + 2 * N]
    for i in range(3):
        ex[i] = R[i, 0]
        ey[i] = R[i, 1]
    for cap in range(2):
        sg = -1.0 if cap == 0 else 1.0
        for i in range(3):
            cen[i] = c[i] + sg * (hl * R[i, 2])
        for i in range(N):
            a = 2.0 * math.pi * i / N
            fv[i] = _rim_f(cen, ex, ey, r, a, oc, oR, oh, x)
            q[i] = _q(x, oc, oR, oh[1])
        for i in range(N):
            prev, nxt = fv[(i - 1) % N], fv[(i + 1) % N]
            lo_n = min(prev, nxt)
            if not (fv[i] <= lo_n and fv[i] < max(prev, nxt)):
                continue
            # the signed distance is 1-Lipschitz: within an arc of 2 pi r / N
            # of a sample it drops at most that much
            if use_margin and not fv[i] - step * r < margin:
                continue
            a = 2.0 * math.pi * i / N
            th, f_th = _golden_rim(cen, ex, ey, r, a - step, a + step, oc, oR, oh, x)
            if f_th < lo_n - EDGE_POINT_TOL:
                _rim_point(cen, ex, ey, r, th, pts[cnt])
                fid[cnt] = 16 + 16 * cap + i
                cnt += 1
        # radius crossings: sign changes of q = rho^2 - r^2; a rim on the
        # other's radius (equal cans stacked) has q at round-off all along:
        # only sign changes that at least one end makes clearly (1e-12 r^2)
        for i in range(N):
            qn = q[(i + 1) % N]
            if (q[i] < 0.0) == (qn < 0.0) or not max(abs(q[i]), abs(qn)) > 1e-12 * (oh[1] * oh[1]):
                continue
            if use_margin and not min(fv[i], fv[(i + 1) % N]) - step * r < margin:
                continue
            lo = 2.0 * math.pi * i / N
            hi = lo + step
            neg_lo = q[i] < 0.0
            for _ in range(32):  # the bracket ends 2 pi / N 2^-32 = 9e-11 rad apart
                mid = 0.5 * (lo + hi)
                _rim_point(cen, ex, ey, r, mid, x)
                if (_q(x, oc, oR, oh[1]) < 0.0) == neg_lo:
                    lo = mid
                else:
                    hi = mid
            # the bracket's end within the radius: on the rim and on or
            # inside the other's side to 1e-11 m
            _rim_point(cen, ex, ey, r, lo if neg_lo else hi, pts[cnt])
            fid[cnt] = 64 + 16 * cap + i
            cnt += 1
    return cnt


@njit(cache=True)
def _support(n, ax, hl, r):
    """Support half-width (m) of a cylinder (axis ax, half length hl,
    radius r) along the unit direction n."""
    ca = abs(n[0] * ax[0] + n[1] * ax[1] + n[2] * ax[2])
    return r * np.sqrt(max(1.0 - ca * ca, 0.0)) + hl * ca


@njit(cache=True)
def _pair_normal(ca, axa, hla, ra, cb, axb, hlb, rb, out, pw):
    """The pair's contact normal (k, 3) from the first cylinder toward the
    second, by the separating-axis test over three candidates: the two
    axes (a cap on the other body) and the direction between the axes'
    closest points (side on side), each oriented from first to second; the
    candidate of largest separation wins, caps preferred within 1e-9 m.
    ``pw`` (27,) scratch."""
    V = pw[0:18].reshape((6, 3))
    p0, p1, q0, q1, pa, pb = V[0], V[1], V[2], V[3], V[4], V[5]
    cand = pw[18:27].reshape((3, 3))
    for i in range(3):
        p0[i] = ca[i] - axa[i] * hla
        p1[i] = ca[i] + axa[i] * hla
        q0[i] = cb[i] - axb[i] * hlb
        q1[i] = cb[i] + axb[i] * hlb
    segment_segment(p0, p1, q0, q1, pa, pb)
    d0, d1, d2 = pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2]
    dl = norm3(d0, d1, d2)
    okd = dl > 1e-9
    for i in range(3):
        cand[0, i] = axa[i]
        cand[1, i] = axb[i]
    if okd:
        cand[2, 0], cand[2, 1], cand[2, 2] = d0 / dl, d1 / dl, d2 / dl
    else:
        for i in range(3):
            cand[2, i] = axa[i]
    best = 0
    bsep = 0.0
    for j in range(3):
        proj = (cand[j, 0] * (cb[0] - ca[0]) + cand[j, 1] * (cb[1] - ca[1]) + cand[j, 2] * (cb[2] - ca[2]))
        if proj < 0.0:
            for i in range(3):
                cand[j, i] = -cand[j, i]
        sep = abs(proj) - (_support(cand[j], axa, hla, ra) + _support(cand[j], axb, hlb, rb))
        if j == 2:
            sep = sep - 1e-9 if okd else -np.inf
        if j == 0 or sep > bsep:
            bsep = sep
            best = j
    for i in range(3):
        out[i] = cand[best, i]


@njit(cache=True)
def _points_against(me, other, pn, margin, use_margin, sgn_n, fid0, cand, cnt, sw, siw):
    """One side of :func:`cylinder_cylinder`: points of the cylinder ``me``
    against the cylinder ``other``'s exact signed distance (each
    :func:`engine.collision.kernels.one_cylinder`), ``pn`` (3,) the pair
    normal from ``me`` toward ``other``.  Points inside the other leave
    through its cap where pn is within 45 degrees of its axis, else
    through its side.  Writes the contacts, normals times ``sgn_n`` (from
    ``me`` toward ``other`` for 1), fids ``fid0`` + the feature's, into the
    :class:`Candidates` ``cand`` from ``cnt`` on; returns the count after
    them.  ``margin`` m, where ``use_margin``: rim samples farther are not
    refined.  ``sw`` (_SIDE_FW,), ``siw`` (2 _SIDE_MAX,) int64 scratch."""
    c, R, hl, r = me.c, me.R, me.hl, me.r
    oc, oR, ohl, orr = other.c, other.R, other.hl, other.r
    oh = sw[0:3]
    oh[0], oh[1], oh[2] = ohl, orr, 0.0
    cap_face = 1 if abs(pn[0] * oR[0, 2] + pn[1] * oR[1, 2] + pn[2] * oR[2, 2]) >= CYLINDER_FACE_COS else 0
    ax = sw[3:6]
    for i in range(3):
        ax[i] = R[i, 2]
    o = 6 + 3 * _SIDE_MAX
    pts = sw[6:o].reshape((_SIDE_MAX, 3))
    fid = siw[0:_SIDE_MAX]
    infg = siw[_SIDE_MAX:2 * _SIDE_MAX]  # (0/1 flags)
    for t in range(_SIDE_MAX):
        infg[t] = 0
    m = np.int64(0)
    cosf = pn[0] * ax[0] + pn[1] * ax[1] + pn[2] * ax[2]
    if not abs(cosf) >= CYLINDER_FACE_COS:
        # side on: each rim's support point toward the other body (the ends
        # of a side lying along the other)
        mp = sw[o:o + 3]
        for i in range(3):
            mp[i] = -pn[i]
        P = sw[o + 3:o + 27].reshape((8, 3))
        cylinder_rim1(c, R, hl, r, mp, P)
        for j in (0, 4):
            for i in range(3):
                pts[m, i] = P[j, i]
            fid[m] = 0 if j == 0 else 8
            m += 1
    else:
        # cap on: the facing cap's material square (body x, y) and its rim
        # point nearest the other's axis (see cylinder_cylinder)
        sgn = 1.0 if cosf >= 0.0 else -1.0
        capc = sw[o + 27:o + 30]
        to = sw[o + 30:o + 33]
        for i in range(3):
            capc[i] = c[i] + ax[i] * (sgn * hl)
            to[i] = oc[i] - capc[i]
        ta = to[0] * ax[0] + to[1] * ax[1] + to[2] * ax[2]
        for i in range(3):
            to[i] -= ta * ax[i]
        tl = norm3(to[0], to[1], to[2])
        okt = tl > 1e-9 * r
        base = 9 if sgn > 0 else 1
        for j in range(5):
            for i in range(3):
                if j == 0:
                    d = R[i, 0]
                elif j == 1:
                    d = R[i, 1]
                elif j == 2:
                    d = -R[i, 0]
                elif j == 3:
                    d = -R[i, 1]
                else:
                    d = to[i] / tl if okt else R[i, 0]
                pts[m, i] = capc[i] + d * r
            fid[m] = base + j
            infg[m] = j == 4 and not okt
            m += 1
    # the rims' minima and radius crossings
    m = _rim_search(c, R, hl, r, oc, oR, oh, margin, use_margin, pts, fid, m, sw[o + 41:o + 41 + _RIM_FW])
    # the side line facing the other body: its deepest point (side across
    # side) and its crossings of the other's radius (a side lying across a cap)
    t0, t1, t2 = pn[0] - cosf * ax[0], pn[1] - cosf * ax[1], pn[2] - cosf * ax[2]
    tl = norm3(t0, t1, t2)
    if tl > 1e-6:
        e0 = sw[o + 33:o + 36]
        e1 = sw[o + 36:o + 39]
        s2 = sw[o + 39:o + 41]
        sc = r / tl
        e0[0], e0[1], e0[2] = c[0] + t0 * sc - ax[0] * hl, c[1] + t1 * sc - ax[1] * hl, c[2] + t2 * sc - ax[2] * hl
        e1[0], e1[1], e1[2] = c[0] + t0 * sc + ax[0] * hl, c[1] + t1 * sc + ax[1] * hl, c[2] + t2 * sc + ax[2] * hl
        s, f_s, f_ends = segment_min1(SDF_CYLINDER, e0, e1, oc, oR, oh, 40)
        if f_s < f_ends - EDGE_POINT_TOL:
            for i in range(3):
                pts[m, i] = e0[i] + (e1[i] - e0[i]) * s
            fid[m] = 48
            m += 1
        circle_crossings1(e0, e1, oc, oR, orr, s2)
        for j in range(2):
            if not np.isnan(s2[j]):
                for i in range(3):
                    pts[m, i] = e0[i] + (e1[i] - e0[i]) * s2[j]
                fid[m] = 49 + j
                m += 1
    for t in range(m):
        g = sphere_cylinder1(pts[t], 0.0, oc, oR, ohl, orr, cap_face, cand.n[cnt], cand.p[cnt])
        cand.g[cnt] = np.inf if infg[t] else g
        for i in range(3):
            cand.n[cnt, i] *= sgn_n
        cand.f[cnt] = fid0 + fid[t]
        cnt += 1
    return cnt


@njit(cache=True)
def _cylinder_cylinder_kernel(A, B, margin, use_margin, S, fw, iw):
    """:func:`cylinder_cylinder` over the pairs (the :class:`Cylinders`
    ``A`` against ``B``, ``margin`` (k,) m where ``use_margin``) into the
    :class:`Slots` ``S`` (k, 4 + 2 _SIDE_MAX); ``fw`` (>= YY_FW,) float64
    and ``iw`` (>= YY_IW,) int64 scratch."""
    Ra, Rb = A.R, B.R
    nB = _B
    cand = Candidates(n=fw[0:3 * nB].reshape((nB, 3)), p=fw[3 * nB:6 * nB].reshape((nB, 3)), g=fw[6 * nB:7 * nB],
                      f=iw[0:nB])
    axa = fw[13 * nB:13 * nB + 3]
    axb = fw[13 * nB + 3:13 * nB + 6]
    pn = fw[13 * nB + 6:13 * nB + 9]
    mpn = fw[13 * nB + 9:13 * nB + 12]
    pw = fw[13 * nB + 12:_PAIR_FW]
    sw = fw[_PAIR_FW:_PAIR_FW + _SIDE_FW]
    work = ManifoldWork(order=iw[nB:2 * nB], key=fw[7 * nB:8 * nB], E=fw[8 * nB:11 * nB].reshape((nB, 3)),
                        sp=fw[11 * nB:12 * nB], area=fw[12 * nB:13 * nB], near=iw[2 * nB:3 * nB],
                        sel=iw[3 * nB:4 * nB])
    siw = iw[4 * nB:4 * nB + 2 * _SIDE_MAX]
    for k in range(A.c.shape[0]):
        a, b = one_cylinder(A, k), one_cylinder(B, k)
        for i in range(3):
            axa[i] = Ra[k, i, 2]
            axb[i] = Rb[k, i, 2]
        _pair_normal(a.c, axa, a.hl, a.r, b.c, axb, b.hl, b.r, pn, pw)
        for i in range(3):
            mpn[i] = -pn[i]
        cnt = _points_against(a, b, pn, margin[k], use_margin, 1.0, np.int64(0), cand, np.int64(0), sw,
                              siw)  # (typed ints: one compile)
        cnt = _points_against(b, a, mpn, margin[k], use_margin, -1.0, np.int64(128), cand, cnt, sw, siw)
        _four_points(cand, cnt, pn, margin[k], use_margin, work, pair_slots(S, k))


@njit(cache=True)
def _four_points(cand, cnt, pn, margin, use_margin, work, S):
    """The touching set of a pair -- its first ``cnt`` :class:`Candidates`
    ``cand`` within MANIFOLD_BAND of its deepest -- reduced to at most four
    points as box-box keeps them (the deepest, the one farthest from it,
    and on either side of their line the one farthest from it, all
    measured across the pair normal ``pn`` (3,)), without near repeats,
    into slots 0-3 of the pair's :class:`Slots` ``S``; the pair's farther
    (speculative) contacts are all kept, from slot 4 on.  The features of
    the two bodies often name the same point twice (a rim crossing seen
    from each side) or nearly (a rim support point a few mm from a
    crossing): with them in, a can offset on an equal can turned at 2e-3
    rad/s within a step instead of resting.
    Contacts beyond the ``margin`` (m, where ``use_margin``) are dropped
    first.  Separated, the deepest is the smallest gap: the distance stays
    exact.  ``work`` a :class:`ManifoldWork`."""
    bn, bp, bg, bf = cand.n, cand.p, cand.g, cand.f
    order, key, E, sp, area = work.order, work.key, work.E, work.sp, work.area
    m = np.int64(0)
    first = np.inf
    for t in range(cnt):
        if use_margin and not bg[t] < margin:
            continue
        order[m] = t
        m += 1
        first = min(first, bg[t])
    # deepest first, gaps within 1e-9 m of the deepest counted as ties and
    # ordered by feature id: on a flat support the round-off must not pick
    # another first point (and with it another four) every step
    for a in range(m):
        t = order[a]
        key[t] = -np.inf if bg[t] <= first + 1e-9 else bg[t]
    for a in range(1, m):  # insertion sort by (key, fid): stable, few points
        t = order[a]
        b = a - 1
        while b >= 0 and (key[order[b]] > key[t] or (key[order[b]] == key[t] and bf[order[b]] > bf[t])):
            order[b + 1] = order[b]
            b -= 1
        order[b + 1] = t
    # a point clear of the other body (not the pair's deepest) whose normal
    # turns more than 45 degrees from the pair normal reaches round the
    # other's edge (pinned by the log pile's tests): dropped
    w = 0
    for a in range(m):
        t = order[a]
        if bg[t] > first + 1e-9 and bn[t, 0] * pn[0] + bn[t, 1] * pn[1] + bn[t, 2] * pn[2] < CYLINDER_FACE_COS:
            continue
        order[w] = t
        w += 1
    m = w
    # the touching set (within MANIFOLD_BAND of the deepest), in order
    nn = 0
    for a in range(m):
        if bg[order[a]] <= first + MANIFOLD_BAND:
            nn += 1
    ns = np.int64(0)
    if nn:
        near = work.near[:nn]
        j = 0
        for a in range(m):
            if bg[order[a]] <= first + MANIFOLD_BAND:
                near[j] = order[a]
                j += 1
        d0 = near[0]
        smax = 0.0
        for a in range(nn):
            t = near[a]
            for i in range(3):
                E[a, i] = bp[t, i] - bp[d0, i]
            en = E[a, 0] * pn[0] + E[a, 1] * pn[1] + E[a, 2] * pn[2]
            for i in range(3):
                E[a, i] -= en * pn[i]
            sp[a] = np.sqrt(max(E[a, 0] * E[a, 0] + E[a, 1] * E[a, 1] + E[a, 2] * E[a, 2], 0.0))
            smax = max(smax, sp[a])
        # the farthest point, of those within MANIFOLD_MIN_SPAN of the
        # farthest the deepest (rows are in depth order)
        i1 = 0
        for a in range(nn):
            if sp[a] >= smax - MANIFOLD_MIN_SPAN:
                i1 = a
                break
        span = sp[i1]
        i2 = 0
        i3 = 0
        for a in range(nn):
            area[a] = ((E[i1, 1] * E[a, 2] - E[i1, 2] * E[a, 1]) * pn[0]
                       + (E[i1, 2] * E[a, 0] - E[i1, 0] * E[a, 2]) * pn[1]
                       + (E[i1, 0] * E[a, 1] - E[i1, 1] * E[a, 0]) * pn[2])
            if area[a] > area[i2]:
                i2 = a
            if area[a] < area[i3]:
                i3 = a
        ok1 = span > MANIFOLD_MIN_SPAN
        sel = work.sel[:nn]  # (0/1 flags)
        for a in range(nn):
            sel[a] = 0
        sel[0] = True
        if ok1:
            sel[i1] = True
            if area[i2] > MANIFOLD_SPREAD * span * span:
                sel[i2] = True
            if -area[i3] > MANIFOLD_SPREAD * span * span:
                sel[i3] = True
        for a in range(nn):  # in depth order
            if sel[a]:
                _put(near[a], ns, cand, S)
                ns += 1
    # the farther (speculative) contacts, all kept, in order after slot 4
    sl = np.int64(4)
    for a in range(m):
        t = order[a]
        if bg[t] > first + MANIFOLD_BAND:
            _put(t, sl, cand, S)
            sl += 1


@njit(cache=True)
def _put(t, sl, cand, S):
    """Candidate t into slot sl of one pair's :class:`Slots` ``S``."""
    for i in range(3):
        S.n[sl, i] = cand.n[t, i]
        S.p[sl, i] = cand.p[t, i]
    S.g[sl] = cand.g[t]
    S.f[sl] = cand.f[t]
    S.ok[sl] = True


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
    m = ca.shape[0]
    out = slots(m, 4 + 2 * _SIDE_MAX)
    if m:
        f = lambda a: np.ascontiguousarray(a, dtype=float)  # noqa: E731
        mg = np.zeros(m) if margin is None else f(margin)
        _cylinder_cylinder_kernel(Cylinders(c=f(ca), R=f(Ra), hl=f(hla), r=f(ra)),
                                  Cylinders(c=f(cb), R=f(Rb), hl=f(hlb), r=f(rb)), mg, margin is not None,
                                  Slots(*out), np.empty(YY_FW), np.empty(YY_IW, np.int64))
    return gather(*out, blocks=[(0, 4), (4, 4 + 2 * _SIDE_MAX)])
