"""Compiled helpers shared by the narrow-phase kernels (numba
``@njit(cache=True)``, no fastmath, no parallel; no BLAS: every small
product is written out as a loop or a sum of three terms, left to right,
so the bits do not depend on the CPU or a BLAS kernel): one-pair contacts
(sphere against sphere, plane, box, cylinder), segment closest points, the
box and cylinder signed distances and the golden-section search along a
segment, the cylinder's rim points and radius crossings; and the Python
side's slot arrays and their gathering into contacts."""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

EPS = 1e-12

#: contact slots: normals ``n``, points ``p``, gaps ``g``, feature ids ``f``
#: (int64), written flags ``ok`` (bool) -- a family kernel's (k, S, 3) and
#: (k, S) over its pairs, one pair's (S, 3) and (S,) (:func:`pair_slots`),
#: or flat over a group's pairs x slots (the collider's buffers,
#: engine.collision.collide)
Slots = namedtuple("Slots", ("n", "p", "g", "f", "ok"))

#: cylinders (axis = body z): centres ``c`` (k, 3), rotations ``R`` (k, 3,
#: 3), half lengths ``hl`` and radii ``r`` (k,) m -- or one cylinder's (3,),
#: (3, 3) and floats (:func:`one_cylinder`)
Cylinders = namedtuple("Cylinders", ("c", "R", "hl", "r"))

#: boxes: centres ``c`` (k, 3), rotations ``R`` (k, 3, 3), half extents
#: ``h`` (k, 3) m
Boxes = namedtuple("Boxes", ("c", "R", "h"))


@njit(cache=True)
def pair_slots(S, k):
    """Pair k's slots (S, 3) and (S,): views of the family's :class:`Slots` ``S``."""
    return Slots(n=S.n[k], p=S.p[k], g=S.g[k], f=S.f[k], ok=S.ok[k])


@njit(cache=True)
def one_cylinder(cyl, k):
    """Cylinder k of the :class:`Cylinders` ``cyl``: its centre (3,) and
    rotation (3, 3) as views, half length and radius."""
    return Cylinders(c=cyl.c[k], R=cyl.R[k], hl=cyl.hl[k], r=cyl.r[k])

#: an edge point is a contact only where it is deeper (or closer) than both
#: of its corners by this much (m): on a flat stretch the corners stand for it
EDGE_POINT_TOL = 1e-9


def empty():
    """No contacts: (k, normal, point, gap, fid) of length 0."""
    return (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))


@njit(cache=True)
def cross3(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(cache=True)
def clip01(x):
    return min(max(x, 0.0), 1.0)


@njit(cache=True)
def segment_segment(p0, p1, q0, q1, pa, pb):
    """Closest points pa, pb (3,) (written in place) between segments
    [p0, p1] and [q0, q1] (Ericson 5.1.9)."""
    # (scalars, not 3-vectors: no array a call; each dot product summed x, y, z)
    d10, d11, d12 = p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]
    d20, d21, d22 = q1[0] - q0[0], q1[1] - q0[1], q1[2] - q0[2]
    r0, r1, r2 = p0[0] - q0[0], p0[1] - q0[1], p0[2] - q0[2]
    a = d10 * d10 + d11 * d11 + d12 * d12
    e = d20 * d20 + d21 * d21 + d22 * d22
    f = d20 * r0 + d21 * r1 + d22 * r2
    c = d10 * r0 + d11 * r1 + d12 * r2
    b = d10 * d20 + d11 * d21 + d12 * d22
    denom = a * e - b * b
    s = 0.0
    if denom > EPS * max(a * e, EPS):
        s = clip01((b * f - c * e) / denom)
    t = (b * s + f) / e if e > EPS else 0.0
    if t < 0.0:
        t = 0.0
        s = clip01(-c / a if a > EPS else 0.0)
    elif t > 1.0:
        t = 1.0
        s = clip01((b - c) / a if a > EPS else 0.0)
    pa[0] = p0[0] + d10 * s
    pb[0] = q0[0] + d20 * t
    pa[1] = p0[1] + d11 * s
    pb[1] = q0[1] + d21 * t
    pa[2] = p0[2] + d12 * s
    pb[2] = q0[2] + d22 * t


@njit(cache=True)
def norm3(x, y, z):
    return np.sqrt(x * x + y * y + z * z)


@njit(cache=True)
def to_local(R, x, out):
    """out = R^T x (x (3,) in the world, R (3, 3) the body's rotation)."""
    for i in range(3):
        out[i] = R[0, i] * x[0] + R[1, i] * x[1] + R[2, i] * x[2]


@njit(cache=True)
def local_offset(R, x, c, out):
    """out = R^T (x - c): the point x (3,) in the frame of a body at c (3,)
    with rotation R (or, for c = a point, the vector x - c in it)."""
    out[0], out[1], out[2] = _local3(R, x, c)


@njit(cache=True, inline="always")
def _local3(R, x, c):
    """:func:`local_offset` as a tuple: R^T (x - c)."""
    w0, w1, w2 = x[0] - c[0], x[1] - c[1], x[2] - c[2]
    return (R[0, 0] * w0 + R[1, 0] * w1 + R[2, 0] * w2, R[0, 1] * w0 + R[1, 1] * w1 + R[2, 1] * w2,
            R[0, 2] * w0 + R[1, 2] * w1 + R[2, 2] * w2)


@njit(cache=True)
def sphere_sphere1(ca, ra, cb, rb, n, p):
    """One sphere pair: the unit normal n (3,) from a toward b (+z for
    coincident centres) and the midpoint p (3,), written in place; returns
    the gap (m)."""
    d0, d1, d2 = cb[0] - ca[0], cb[1] - ca[1], cb[2] - ca[2]
    L = norm3(d0, d1, d2)
    if L > EPS:
        n[0], n[1], n[2] = d0 / L, d1 / L, d2 / L
    else:
        n[0], n[1], n[2] = 0.0, 0.0, 1.0
    gap = L - ra - rb
    s = ra + 0.5 * gap
    for i in range(3):
        p[i] = ca[i] + n[i] * s
    return gap


@njit(cache=True)
def sphere_contact(c, r, nw, gap, n, p):
    """A sphere's contact (centre c, radius r) against a surface of outward
    unit normal nw (a 3-tuple, world) at signed gap ``gap`` (m): normal n =
    -nw (from the sphere into the surface), the midpoint p between the two
    surfaces; returns the gap."""
    s = r + 0.5 * gap
    for i in range(3):
        p[i] = c[i] - nw[i] * s
        n[i] = -nw[i]
    return gap


@njit(cache=True)
def sphere_plane1(c, r, pn, po, n, p):
    """One sphere against the plane (unit normal pn, offset po): normal -pn
    into the plane, midpoint p; returns the gap."""
    return sphere_contact(c, r, (pn[0], pn[1], pn[2]), pn[0] * c[0] + pn[1] * c[1] + pn[2] * c[2] - po - r, n, p)


@njit(cache=True)
def surface_contact(c, r, R, w0, w1, w2, g, n, p):
    """The contact of a sphere (centre c, radius r) with a shape whose
    outward unit normal at the sphere's closest point is R w (w = (w0, w1,
    w2) in the shape's frame, R its rotation) and whose signed distance to
    c is g (m): normal n from the sphere to the shape, midpoint p; returns
    the gap g - r.  (Scalars and a tuple: no array a call.)"""
    o0 = R[0, 0] * w0 + R[0, 1] * w1 + R[0, 2] * w2  # the shape's outward normal, world
    o1 = R[1, 0] * w0 + R[1, 1] * w1 + R[1, 2] * w2
    o2 = R[2, 0] * w0 + R[2, 1] * w1 + R[2, 2] * w2
    return sphere_contact(c, r, (o0, o1, o2), g - r, n, p)


@njit(cache=True)
def sphere_box1(c, r, cb, Rb, hb, n, p):
    """One sphere (centre c, radius r) against a box (centre cb, rotation
    Rb, half-extents hb): exact closest points; a centre inside leaves
    through the face of least penetration (the first of equal ones).
    Normal n from the sphere to the box, midpoint p; returns the gap.
    (Scalars, no array: nothing allocated a pair.)"""
    loc = _local3(Rb, c, cb)
    d0 = loc[0] - min(max(loc[0], -hb[0]), hb[0])
    d1 = loc[1] - min(max(loc[1], -hb[1]), hb[1])
    d2 = loc[2] - min(max(loc[2], -hb[2]), hb[2])
    dist = norm3(d0, d1, d2)
    if dist > EPS:
        w0, w1, w2 = d0 / dist, d1 / dist, d2 / dist
        g = dist
    else:
        face = 0
        best = hb[0] - abs(loc[0])
        for i in range(1, 3):
            pen = hb[i] - abs(loc[i])
            if pen < best:
                best = pen
                face = i
        sg = 1.0 if loc[face] >= 0.0 else -1.0
        w0 = sg if face == 0 else 0.0
        w1 = sg if face == 1 else 0.0
        w2 = sg if face == 2 else 0.0
        g = -best
    return surface_contact(c, r, Rb, w0, w1, w2, g, n, p)


def gather(S_n, S_p, S_g, S_f, S_ok, blocks=None):
    """The written slots (k, S, ...) of a kernel as contacts (k, normal,
    point, gap, fid), in the order the family's contacts have always had:
    ``blocks`` (slot ranges (lo, hi)) one after the other, each pair by
    pair; None: one block per slot (every pair's first contact, then
    every pair's second, ...)."""
    k, S = S_g.shape
    if blocks is None:
        blocks = [(s, s + 1) for s in range(S)]
    kk = np.broadcast_to(np.arange(k)[:, None], (k, S))
    parts = [[], [], [], [], []]
    for lo, hi in blocks:
        m = S_ok[:, lo:hi]
        for i, a in enumerate((kk, S_n, S_p, S_g, S_f)):
            parts[i].append(a[:, lo:hi][m])
    return tuple(np.concatenate(p) for p in parts)


def slots(k: int, S: int):
    """Zeroed slot arrays (k, S, ...) for a kernel: normals, points, gaps,
    feature ids, written flags."""
    return (np.zeros((k, S, 3)), np.zeros((k, S, 3)), np.zeros((k, S)), np.zeros((k, S), np.int64),
            np.zeros((k, S), np.bool_))


@njit(cache=True)
def segment_closest1(x, a0, a1, out):
    """The point out (3,) of segment [a0, a1] closest to x; returns its
    parameter s in [0, 1]."""
    d0, d1, d2 = a1[0] - a0[0], a1[1] - a0[1], a1[2] - a0[2]
    dd = d0 * d0 + d1 * d1 + d2 * d2
    s = 0.0
    if dd > EPS:
        s = clip01(((x[0] - a0[0]) * d0 + (x[1] - a0[1]) * d1 + (x[2] - a0[2]) * d2) / dd)
    out[0] = a0[0] + d0 * s
    out[1] = a0[1] + d1 * s
    out[2] = a0[2] + d2 * s
    return s


#: signed-distance kinds of :func:`sdf1`
SDF_BOX = 0
SDF_CYLINDER = 1


@njit(cache=True)
def sdf1(kind, x0, x1, x2, oc, oR, oh):
    """Signed distance (m) of the point (x0, x1, x2) to a solid box
    (``kind`` SDF_BOX: half-extents oh (3,)) or cylinder (SDF_CYLINDER:
    axis = body z, half length oh[0], radius oh[1]) of centre oc (3,) and
    rotation oR (3, 3): the distance outside, minus the depth to the
    nearest face inside -- convex in the point."""
    w0, w1, w2 = x0 - oc[0], x1 - oc[1], x2 - oc[2]
    l0 = oR[0, 0] * w0 + oR[1, 0] * w1 + oR[2, 0] * w2
    l1 = oR[0, 1] * w0 + oR[1, 1] * w1 + oR[2, 1] * w2
    l2 = oR[0, 2] * w0 + oR[1, 2] * w1 + oR[2, 2] * w2
    if kind == SDF_BOX:
        q0, q1, q2 = abs(l0) - oh[0], abs(l1) - oh[1], abs(l2) - oh[2]
        m0, m1, m2 = max(q0, 0.0), max(q1, 0.0), max(q2, 0.0)
        return np.sqrt(m0 * m0 + m1 * m1 + m2 * m2) + min(max(q0, q1, q2), 0.0)
    dr = np.sqrt(l0 * l0 + l1 * l1) - oh[1]
    dz = abs(l2) - oh[0]
    a, b = max(dr, 0.0), max(dz, 0.0)
    return np.sqrt(a * a + b * b) + min(max(dr, dz), 0.0)


GOLDEN = 0.5 * (np.sqrt(5.0) - 1.0)


@njit(cache=True)
def _seg_f(kind, e0, d, x, oc, oR, oh):
    return sdf1(kind, e0[0] + d[0] * x, e0[1] + d[1] * x, e0[2] + d[2] * x, oc, oR, oh)


@njit(cache=True)
def segment_min1(kind, e0, e1, oc, oR, oh, iters):
    """The minimum of the other body's signed distance (:func:`sdf1`)
    along the segment e0 -> e1: golden section over [0, 1] (``iters``
    iterations, one evaluation each: 40 leave a bracket of 4e-9), then the
    ends compared exactly (where the distance is flat the end wins).
    Returns (s, the distance there, the smaller of the ends' distances)."""
    d = (e1[0] - e0[0], e1[1] - e0[1], e1[2] - e0[2])  # (a tuple: no array a call)
    lo, hi = 0.0, 1.0
    x1 = hi - GOLDEN * (hi - lo)
    x2 = lo + GOLDEN * (hi - lo)
    f1 = _seg_f(kind, e0, d, x1, oc, oR, oh)
    f2 = _seg_f(kind, e0, d, x2, oc, oR, oh)
    for _ in range(iters):
        if f1 < f2:  # the minimum is in [lo, x2]: x1 becomes the upper probe
            hi = x2
            xn = hi - GOLDEN * (hi - lo)
            fn = _seg_f(kind, e0, d, xn, oc, oR, oh)
            x1, x2, f1, f2 = xn, x1, fn, f1
        else:
            lo = x1
            xn = lo + GOLDEN * (hi - lo)
            fn = _seg_f(kind, e0, d, xn, oc, oR, oh)
            x1, x2, f1, f2 = x2, xn, f2, fn
    s = 0.5 * (lo + hi)
    f_s = _seg_f(kind, e0, d, s, oc, oR, oh)
    f_0 = sdf1(kind, e0[0], e0[1], e0[2], oc, oR, oh)
    f_1 = sdf1(kind, e1[0], e1[1], e1[2], oc, oR, oh)
    if f_1 < min(f_s, f_0):
        return 1.0, f_1, min(f_0, f_1)
    if f_0 <= f_s:
        return 0.0, f_0, min(f_0, f_1)
    return s, f_s, min(f_0, f_1)


#: m: how far outside both of a cylinder's faces a point may be and still
#: leave through the face the pair's normal chose (:func:`sphere_cylinder1`)
FACE_TOL = 1e-9

#: |n . axis| above which a cylinder's cap faces the surface (cos 45 deg)
CYLINDER_FACE_COS = np.sqrt(0.5)


@njit(cache=True)
def sphere_cylinder1(c, r, cc, Rc, hl, rc, cap, n, p):
    """One sphere (centre c, radius r) against a solid cylinder (centre cc,
    rotation Rc with the axis as body z, half length hl, radius rc): exact
    closest points (see :func:`engine.collision.sphere_cylinder`; ``cap``
    -1: inside leaves through the nearer face, 1: through the cap, 0:
    through the side).  Normal n from the sphere to the cylinder, midpoint
    p; returns the gap.  (Scalars, no array: nothing allocated a pair.)"""
    loc = _local3(Rc, c, cc)
    rho = np.sqrt(loc[0] ** 2 + loc[1] ** 2)
    scale = min(1.0, rc / (rho if rho > EPS else 1.0))
    d0 = loc[0] - loc[0] * scale
    d1 = loc[1] - loc[1] * scale
    d2 = loc[2] - min(max(loc[2], -hl), hl)
    dist = norm3(d0, d1, d2)
    outside = dist > EPS
    pen_side = rc - rho
    pen_cap = hl - abs(loc[2])
    if cap >= 0:
        outside = outside and (pen_side < -FACE_TOL or pen_cap < -FACE_TOL)
        side = cap == 0
    else:
        side = pen_side < pen_cap
    if outside:
        w0, w1, w2 = d0 / dist, d1 / dist, d2 / dist
        g = dist
    elif side:
        if rho > EPS:
            w0, w1 = loc[0] / rho, loc[1] / rho
        else:
            w0, w1 = 1.0, 0.0
        w2 = 0.0
        g = -pen_side
    else:
        w0 = w1 = 0.0
        w2 = 1.0 if loc[2] >= 0.0 else -1.0
        g = -pen_cap
    return surface_contact(c, r, Rc, w0, w1, w2, g, n, p)


#: feature ids of the rim points of :func:`cylinder_rim1`, in their order
RIM_FIDS = np.array([0, 1, 2, 3, 8, 9, 10, 11])


@njit(cache=True)
def cylinder_rim1(c, R, hl, r, pn, P):
    """The rim points of a cylinder against a surface of outward normal pn
    (3,) (toward the cylinder), written to P (8, 3): per cap (-z first) the
    deepest (-t), +u, the highest (+t) and -u, t the component of pn in the
    cap plane (the body's x axis when the cap faces pn), u = axis x t.
    Returns whether the cap does not face pn within 45 degrees: then the
    points other than each cap's deepest (m % 4 != 0) are to be dropped
    (see :func:`engine.collision.cylinder_plane`; a bool, not a (8,) array:
    nothing allocated a call)."""
    dn = pn[0] * R[0, 2] + pn[1] * R[1, 2] + pn[2] * R[2, 2]
    t0, t1, t2 = pn[0] - dn * R[0, 2], pn[1] - dn * R[1, 2], pn[2] - dn * R[2, 2]
    tl = norm3(t0, t1, t2)
    if tl > 1e-6:
        t0, t1, t2 = t0 / tl, t1 / tl, t2 / tl
    else:
        t0, t1, t2 = R[0, 0], R[1, 0], R[2, 0]
    a0, a1, a2 = R[0, 2], R[1, 2], R[2, 2]
    u0, u1, u2 = a1 * t2 - a2 * t1, a2 * t0 - a0 * t2, a0 * t1 - a1 * t0
    side = abs(dn) < CYLINDER_FACE_COS
    for cap in range(2):
        sg = -1.0 if cap == 0 else 1.0
        for j in range(4):
            if j == 0:
                d0, d1, d2 = -t0, -t1, -t2
            elif j == 1:
                d0, d1, d2 = u0, u1, u2
            elif j == 2:
                d0, d1, d2 = t0, t1, t2
            else:
                d0, d1, d2 = -u0, -u1, -u2
            m = 4 * cap + j
            P[m, 0] = (c[0] + sg * (a0 * hl)) + d0 * r
            P[m, 1] = (c[1] + sg * (a1 * hl)) + d1 * r
            P[m, 2] = (c[2] + sg * (a2 * hl)) + d2 * r
    return side


@njit(cache=True)
def circle_crossings1(e0, e1, cc, Rc, rc, out):
    """Parameters out (2,) along the segment e0 -> e1 where its projection
    on a cylinder's cap plane crosses the rim circle (radius rc about the
    axis): the roots of |(x0 + s dx)_xy|^2 = rc^2 in the cylinder's frame;
    NaN where there is no crossing within [0, 1]."""
    a = _local3(Rc, e0, cc)  # (tuples: no array a call)
    dd = _local3(Rc, e1, e0)
    A = dd[0] * dd[0] + dd[1] * dd[1]
    B = a[0] * dd[0] + a[1] * dd[1]
    C = a[0] * a[0] + a[1] * a[1] - rc * rc
    disc = B * B - A * C
    out[0] = out[1] = np.nan
    if A > EPS * max(rc * rc, EPS) and disc > 0.0:
        sq = np.sqrt(disc)
        s0 = (-B - sq) / A
        s1 = (-B + sq) / A
        if 0.0 <= s0 <= 1.0:
            out[0] = s0
        if 0.0 <= s1 <= 1.0:
            out[1] = s1


@njit(cache=True)
def sphere_solid1(kind, c, r, oc, oR, oh, n, p):
    """One sphere against a solid of :func:`sdf1`'s ``kind``: a box
    (:func:`sphere_box1`, half-extents oh) or a cylinder
    (:func:`sphere_cylinder1` leaving through the nearer face, half length
    oh[0], radius oh[1]).  Normal n from the sphere, midpoint p; returns
    the gap."""
    if kind == SDF_BOX:
        return sphere_box1(c, r, oc, oR, oh, n, p)
    return sphere_cylinder1(c, r, oc, oR, oh[0], oh[1], np.int64(-1), n, p)


@njit(cache=True)
def segment_and_caps1(kind, e0, e1, hl, r, oc, oR, oh, x, S_n, S_p, S_g, S_f, S_ok):
    """A capsule (segment e0 -> e1 of half length hl, radius r) against a
    solid (:func:`sphere_solid1`) into slots 0-2 of one pair's rows: the
    segment's point of least signed distance (:func:`segment_min1`, fid 0)
    and the end caps where the minimum is not at them (fids 1, 2).  ``x``
    (3,) scratch.  Returns the minimum's parameter along the segment."""
    s = segment_min1(kind, e0, e1, oc, oR, oh, 40)[0]
    for i in range(3):
        x[i] = e0[i] + (e1[i] - e0[i]) * s
    S_g[0] = sphere_solid1(kind, x, r, oc, oR, oh, S_n[0], S_p[0])
    S_ok[0] = True
    tol = 0.02 * (2.0 * hl + r)
    if abs(s - 0.0) * 2.0 * hl > tol:
        S_g[1] = sphere_solid1(kind, e0, r, oc, oR, oh, S_n[1], S_p[1])
        S_f[1] = 1
        S_ok[1] = True
    if abs(s - 1.0) * 2.0 * hl > tol:
        S_g[2] = sphere_solid1(kind, e1, r, oc, oR, oh, S_n[2], S_p[2])
        S_f[2] = 2
        S_ok[2] = True
    return s


@njit(cache=True)
def crossing_contacts1(e0, e1, r, cyl, s2, x, sl0, sl_step, fid0, fid_step, S):
    """Spheres of radius r at the segment e0 -> e1's crossings of a
    cylinder's radius (:func:`circle_crossings1`; ``cyl`` one cylinder,
    :func:`one_cylinder`) against the cylinder, into slots sl0 + j sl_step
    of one pair's slots ``S`` (:func:`pair_slots`) with fids fid0 + j
    fid_step (j = 0, 1; none where there is no crossing).  ``s2`` (2,),
    ``x`` (3,) scratch."""
    circle_crossings1(e0, e1, cyl.c, cyl.R, cyl.r, s2)
    for j in range(2):
        if not np.isnan(s2[j]):
            for i in range(3):
                x[i] = e0[i] + (e1[i] - e0[i]) * s2[j]
            sl = sl0 + sl_step * j
            S.g[sl] = sphere_cylinder1(x, r, cyl.c, cyl.R, cyl.hl, cyl.r, np.int64(-1), S.n[sl], S.p[sl])
            S.f[sl] = fid0 + fid_step * j
            S.ok[sl] = True


@njit(cache=True)
def rim_contacts1(cyl, pn, kind, oa, ob, oR, orr, sl0, fid0, P, q, S):
    """The rim points of one cylinder ``cyl`` (:func:`one_cylinder`) facing
    a surface of normal pn (toward the cylinder; :func:`cylinder_rim1`)
    against the other body, into slots sl0.. sl0 + 7 of one pair's slots
    ``S`` (:func:`pair_slots`) with fids fid0 + RIM_FIDS: against a
    capsule (``kind`` SDF_CYLINDER: segment oa -> ob, radius orr; the
    closest point on it) or a box (SDF_BOX: centre oa, rotation oR,
    half-extents ob).  Normals from the other body toward the cylinder;
    the points :func:`cylinder_rim1` drops get gap inf.  P (8, 3), q (3,)
    scratch."""
    side = cylinder_rim1(cyl.c, cyl.R, cyl.hl, cyl.r, pn, P)
    for m in range(8):
        sl = sl0 + m
        if kind == SDF_BOX:
            g = sphere_box1(P[m], 0.0, oa, oR, ob, S.n[sl], S.p[sl])
        else:
            segment_closest1(P[m], oa, ob, q)
            g = sphere_sphere1(P[m], 0.0, q, orr, S.n[sl], S.p[sl])
        for i in range(3):
            S.n[sl, i] = -S.n[sl, i]
        S.g[sl] = np.inf if side and m % 4 != 0 else g
        S.f[sl] = fid0 + RIM_FIDS[m]
        S.ok[sl] = True
