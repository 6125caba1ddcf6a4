"""Narrow phase: contact points, normals and signed gaps per shape pair.

``TABLE`` maps a shape pair to a function; body-body pairs are grouped by
their (canonically ordered) shape pair when the model is built
(:func:`pair_kinds`), body-static pairs by the body's shape.  Every function
is vectorised over the pairs of its group and returns

    (k, normal, point, gap, fid)

with ``k`` the index of the pair each contact belongs to, ``normal`` (m, 3)
the unit normal from the first shape toward the second, ``point`` (m, 3) the
world point midway between the two surfaces, ``gap`` (m,) the signed
distance (m, negative = penetration) and ``fid`` a feature id.  Contacts with
``gap`` below the pair's margin are kept: beyond touching contacts, the
margin admits *speculative* contacts that the step might close (the broad
phase sizes it from the bodies' motion), which the solver and CCD use.

Pairs:
* sphere-sphere, sphere-plane, sphere-box: exact closest points.
* box-plane: the eight corners.
* box-box: separating-axis test over 15 axes (3 + 3 face normals, 9 edge
  cross products, faces preferred within a tolerance), then for a face axis
  the incident face clipped against the reference face's side planes
  (Sutherland-Hodgman), at most four points kept (deepest, farthest from it,
  and the two spanning the largest area); for an edge axis the closest
  points of the two edges plus the face manifold's points, their gaps
  clamped at the edge axis' separation (:func:`box_box`).
* capsules: their segment's closest points make sphere-like contacts:
  capsule-plane (both end caps), sphere-capsule, capsule-capsule (closest
  points, plus the end projections when nearly parallel so a lying capsule
  rests on two points), capsule-box (minimum of the box's signed distance
  along the segment by golden-section search -- the signed distance of a
  convex set is convex -- plus the end caps).
* cylinder-plane: per cap the rim points that follow the support (the
  deepest, and while the cap faces the plane the highest and the two
  between); sphere-cylinder: exact closest points.
* box-cylinder and capsule-cylinder: points of each body against the
  other's exact signed distance -- the box's corners, each edge's (or the
  capsule segment's) minimum of the cylinder's convex signed distance
  (golden section) and its crossings of the cylinder's radius, the
  capsule's end caps, the cylinder's rim points facing the other body.
* cylinder-cylinder: the same against each other's signed distance -- the
  facing cap's material square and its rim point nearest the other's axis
  (cap on cap), the rims' local minima and crossings of the other's radius
  (sampled, refined by golden section and bisection), the side line facing
  the other (side on side, side across a cap) -- with the face a point
  pressed in at a rim's edge leaves by chosen by the pair's
  separating-axis normal, and the touching set reduced to four points as
  box-box keeps them (:func:`cylinder_cylinder`).
"""

from __future__ import annotations

import math

import numpy as np

from engine.mathutil import cross, quat_to_matrix
from engine.model import BOX, CAPSULE, CYLINDER, SPHERE
from engine.profile import Stage
from engine.state import Contacts

_EPS = 1e-12


def _norm(v):
    return np.sqrt(np.einsum("...i,...i->...", v, v))


# ---------------------------------------------------------------------------
# primitives (vectorised)

def sphere_sphere(ca, ra, cb, rb):
    d = cb - ca
    L = _norm(d)
    ok = L > _EPS
    n = np.where(ok[:, None], d / np.where(ok, L, 1.0)[:, None], np.array([0.0, 0.0, 1.0]))
    gap = L - ra - rb
    point = ca + n * (ra + 0.5 * gap)[:, None]
    k = np.arange(ca.shape[0])
    return k, n, point, gap, np.zeros(k.size, np.int64)


def sphere_plane(c, r, pn, po):
    gap = np.einsum("ki,ki->k", pn, c) - po - r
    point = c - pn * (r + 0.5 * gap)[:, None]
    k = np.arange(c.shape[0])
    return k, -pn, point, gap, np.zeros(k.size, np.int64)


def sphere_box(c, r, cb, Rb, hb):
    """Sphere (first) against box (second); normal from sphere to box."""
    local = np.einsum("kji,kj->ki", Rb, c - cb)
    cl = np.clip(local, -hb, hb)
    diff = local - cl
    dist = _norm(diff)
    outside = dist > _EPS
    # inside: leave through the face of least penetration
    pen = hb - np.abs(local)
    face = np.argmin(pen, axis=1)
    k = np.arange(c.shape[0])
    n_in = np.zeros_like(local)
    n_in[k, face] = np.where(local[k, face] >= 0.0, 1.0, -1.0)
    n_loc = np.where(outside[:, None], diff / np.where(outside, dist, 1.0)[:, None], n_in)
    gap = np.where(outside, dist, -pen[k, face]) - r
    n_out = np.einsum("kij,kj->ki", Rb, n_loc)  # box outward normal, world
    point = c - n_out * (r + 0.5 * gap)[:, None]
    return k, -n_out, point, gap, np.zeros(k.size, np.int64)


#: m: how far outside both of a cylinder's faces a point may be and still
#: leave through the face the pair's normal chose (:func:`sphere_cylinder`)
FACE_TOL = 1e-9


def sphere_cylinder(c, r, cc, Rc, hl, rc, cap=None):
    """Sphere (first) against a solid cylinder (second; axis = body z, half
    length ``hl``, radius ``rc``): exact closest points, like sphere-box
    with the cylinder's clamp -- radially to the rim, axially to the caps
    (the rim's circle and the cap edges come out of the two clamps
    together).  A centre inside leaves through the nearer of the side and
    the cap, or, where ``cap`` (k,) bool is given, through the cap where it
    is true and the side where not: a point pressed in at the rim's edge is
    nearly as close to both, and only the pair's contact normal tells
    which face it was pressed through.  With ``cap`` given, a point within
    FACE_TOL outside both faces (on the rim's edge to round-off: a can's
    rim on an equal can's rim) counts as inside too, so that it does not
    flip between a radial and an axial normal from step to step.  Normal
    from sphere to cylinder; one contact (the sphere is smooth)."""
    local = np.einsum("kji,kj->ki", Rc, c - cc)
    rho = np.sqrt(local[:, 0] ** 2 + local[:, 1] ** 2)
    scale = np.minimum(1.0, rc / np.where(rho > _EPS, rho, 1.0))
    cl = np.empty_like(local)
    cl[:, :2] = local[:, :2] * scale[:, None]
    cl[:, 2] = np.clip(local[:, 2], -hl, hl)
    diff = local - cl
    dist = _norm(diff)
    outside = dist > _EPS
    # inside: through the side (radially; +x on the axis) or the nearer cap
    pen_side = rc - rho
    pen_cap = hl - np.abs(local[:, 2])
    if cap is not None:
        outside &= (pen_side < -FACE_TOL) | (pen_cap < -FACE_TOL)
    radial = np.where((rho > _EPS)[:, None], local[:, :2] / np.where(rho > _EPS, rho, 1.0)[:, None],
                      np.array([1.0, 0.0]))
    side = pen_side < pen_cap if cap is None else ~cap
    n_in = np.zeros_like(local)
    n_in[:, :2] = np.where(side[:, None], radial, 0.0)
    n_in[:, 2] = np.where(side, 0.0, np.where(local[:, 2] >= 0.0, 1.0, -1.0))
    n_loc = np.where(outside[:, None], diff / np.where(outside, dist, 1.0)[:, None], n_in)
    gap = np.where(outside, dist, -np.where(side, pen_side, pen_cap)) - r
    n_out = np.einsum("kij,kj->ki", Rc, n_loc)  # cylinder outward normal, world
    point = c - n_out * (r + 0.5 * gap)[:, None]
    k = np.arange(c.shape[0])
    return k, -n_out, point, gap, np.zeros(k.size, np.int64)


_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)  # (8, 3)


def box_plane(c, R, half, pn, po):
    loc = _CORNERS[None, :, :] * half[:, None, :]  # (k, 8, 3)
    corners = c[:, None, :] + np.einsum("kij,kmj->kmi", R, loc)
    gap = np.einsum("kmi,ki->km", corners, pn) - po[:, None]
    k = np.repeat(np.arange(c.shape[0]), 8)
    gap = gap.reshape(-1)
    corners = corners.reshape(-1, 3)
    pnr = np.repeat(pn, 8, axis=0)
    point = corners - pnr * (0.5 * gap)[:, None]
    fid = np.tile(np.arange(8), c.shape[0])
    return k, -pnr, point, gap, fid


def _segment_closest(p, a0, a1):
    """Closest points on segments [a0, a1] to points p (k, 3); returns
    (point, s in [0, 1])."""
    d = a1 - a0
    dd = np.einsum("ki,ki->k", d, d)
    s = np.where(dd > _EPS, np.einsum("ki,ki->k", p - a0, d) / np.where(dd > _EPS, dd, 1.0), 0.0)
    s = np.clip(s, 0.0, 1.0)
    return a0 + d * s[:, None], s


def _segment_segment(p0, p1, q0, q1):
    """Closest points between segments [p0,p1] and [q0,q1] (Ericson 5.1.9)."""
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("ki,ki->k", d1, d1)
    e = np.einsum("ki,ki->k", d2, d2)
    f = np.einsum("ki,ki->k", d2, r)
    c = np.einsum("ki,ki->k", d1, r)
    b = np.einsum("ki,ki->k", d1, d2)
    denom = a * e - b * b
    s = np.where(denom > _EPS * np.maximum(a * e, _EPS), np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0, 1), 0.0)
    t = np.where(e > _EPS, (b * s + f) / np.where(e > _EPS, e, 1.0), 0.0)
    # clamp t and recompute s
    t_lo = t < 0.0
    t_hi = t > 1.0
    t = np.clip(t, 0.0, 1.0)
    s = np.where(t_lo, np.clip(np.where(a > _EPS, -c / np.where(a > _EPS, a, 1.0), 0.0), 0, 1), s)
    s = np.where(t_hi, np.clip(np.where(a > _EPS, (b - c) / np.where(a > _EPS, a, 1.0), 0.0), 0, 1), s)
    return p0 + d1 * s[:, None], q0 + d2 * t[:, None]


def _capsule_ends(c, R, hl):
    ax = R[:, :, 2]
    return c - ax * hl[:, None], c + ax * hl[:, None]


def capsule_plane(c, R, hl, r, pn, po):
    e0, e1 = _capsule_ends(c, R, hl)
    k0, n0, p0, g0, _ = sphere_plane(e0, r, pn, po)
    k1, n1, p1, g1, _ = sphere_plane(e1, r, pn, po)
    m = c.shape[0]
    return (np.concatenate([k0, k1]), np.concatenate([n0, n1]), np.concatenate([p0, p1]),
            np.concatenate([g0, g1]), np.concatenate([np.zeros(m, np.int64), np.ones(m, np.int64)]))


def sphere_capsule(cs, rs, c, R, hl, r):
    e0, e1 = _capsule_ends(c, R, hl)
    p, _ = _segment_closest(cs, e0, e1)
    return sphere_sphere(cs, rs, p, r)


def capsule_capsule(ca, Ra, hla, ra, cb, Rb, hlb, rb):
    a0, a1 = _capsule_ends(ca, Ra, hla)
    b0, b1 = _capsule_ends(cb, Rb, hlb)
    pa, pb = _segment_segment(a0, a1, b0, b1)
    out = [sphere_sphere(pa, ra, pb, rb)]
    par = np.abs(np.einsum("ki,ki->k", Ra[:, :, 2], Rb[:, :, 2])) > 0.995
    if par.any():
        idx = np.flatnonzero(par)
        for end, fid in ((a0, 1), (a1, 2)):
            q, _ = _segment_closest(end[idx], b0[idx], b1[idx])
            k, n, p, g, _ = sphere_sphere(end[idx], ra[idx], q, rb[idx])
            out.append((idx[k], n, p, g, np.full(k.size, fid)))
        for end, fid in ((b0, 3), (b1, 4)):
            q, _ = _segment_closest(end[idx], a0[idx], a1[idx])
            k, n, p, g, _ = sphere_sphere(q, ra[idx], end[idx], rb[idx])
            out.append((idx[k], n, p, g, np.full(k.size, fid)))
    return _cat(out)


def _box_sdf(p, cb, Rb, hb):
    local = np.einsum("kji,kj->ki", Rb, p - cb)
    q = np.abs(local) - hb
    outside = _norm(np.maximum(q, 0.0))
    inside = np.minimum(np.max(q, axis=1), 0.0)
    return outside + inside


_GOLDEN = 0.5 * (math.sqrt(5.0) - 1.0)


def _golden(g, lo, hi, iters: int = 40):
    """Golden-section search for the minimum of a function ``g(s (k,)) ->
    (k,)`` unimodal on [lo, hi] (k,): one new evaluation per iteration, 40
    iterations leave a bracket of 4e-9 of the interval.  Returns the
    bracket's midpoint s and g(s)."""
    g_ = _GOLDEN
    x1 = hi - g_ * (hi - lo)
    x2 = lo + g_ * (hi - lo)
    f1 = g(x1)
    f2 = g(x2)
    for _ in range(iters):
        left = f1 < f2  # the minimum is in [lo, x2]: x1 becomes the upper probe
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        xn = np.where(left, hi - g_ * (hi - lo), lo + g_ * (hi - lo))
        fn = g(xn)
        x1, x2, f1, f2 = (np.where(left, xn, x2), np.where(left, x1, xn),
                          np.where(left, fn, f2), np.where(left, f1, fn))
    s = 0.5 * (lo + hi)
    return s, g(s)


def _segment_min(f, e0, e1, iters: int = 40):
    """Parameter s (k,) in [0, 1] of the minimum of a convex function
    ``f(points (k, 3)) -> (k,)`` along the segments e0 -> e1 (k, 3): golden
    section (:func:`_golden`), then the end points compared exactly (the
    minimum may sit at an end, and where f is flat the end wins).  Returns
    (s, f there, the smaller of f at the two ends)."""
    d = e1 - e0
    s, f_s = _golden(lambda x: f(e0 + d * x[:, None]), np.zeros(e0.shape[0]), np.ones(e0.shape[0]), iters)
    f_0 = f(e0)
    f_1 = f(e1)
    at0 = f_0 <= f_s
    at1 = f_1 < np.minimum(f_s, f_0)
    s = np.where(at1, 1.0, np.where(at0, 0.0, s))
    return s, np.where(at1, f_1, np.where(at0, f_0, f_s)), np.minimum(f_0, f_1)


def capsule_box(c, R, hl, r, cb, Rb, hb):
    """Capsule (first) against box (second)."""
    e0, e1 = _capsule_ends(c, R, hl)
    d = e1 - e0
    s = _segment_min(lambda p: _box_sdf(p, cb, Rb, hb), e0, e1)[0]
    out = [sphere_box(e0 + d * s[:, None], r, cb, Rb, hb)]
    for end, fid, sv in ((e0, 1, 0.0), (e1, 2, 1.0)):
        keep = np.flatnonzero(np.abs(s - sv) * 2.0 * hl > 0.02 * (2.0 * hl + r))
        if keep.size:
            k, n, p, gg, _ = sphere_box(end[keep], r[keep], cb[keep], Rb[keep], hb[keep])
            out.append((keep[k], n, p, gg, np.full(k.size, fid)))
    return _cat(out)


#: |n . axis| above which a cylinder's cap faces the plane (cos 45 deg)
CYLINDER_FACE_COS = math.sqrt(0.5)


def cylinder_plane(c, R, hl, r, pn, po):
    """Cylinder (axis = body z, half length ``hl``, radius ``r``) against a
    plane: four rim points per cap, 8 per cylinder.

    The rim points follow the support, not the material: on each cap the
    deepest rim point (direction -t, t the plane normal's component in the
    cap plane), the highest (+t) and the two halfway between (+-u, u = axis x
    t).  A cylinder lying on its side then touches along the line between
    its two deepest points, and as it rolls no material rim point comes
    down onto the plane: fixed rim points would, and their straight-line
    extrapolation within a step predicts a penetration that the true
    (cycloidal) path never makes, so the speculative rows and impact events
    they raise brake the roll (measured: 13 % slow, 0.6 m/s slip at the
    contact line on a 20 degree slope).  Standing on a cap (t = 0) the
    directions are the body's x and y axes: the cap's support square.  A
    tilted cylinder on its rim touches at the deepest point, with the +-u
    points at gap r sin(tilt) to catch it as it settles onto the cap; the
    three points other than the deepest are emitted (finite gap) only while
    the cap faces the plane within 45 degrees (``CYLINDER_FACE_COS``).

    Returns (k, normals (k, 3) from the cylinder into the plane, points,
    gaps, feature ids: 8 s + j for cap s (0: -z, 1: +z) and direction j
    (0: deepest, 1: +u, 2: highest, 3: -u))."""
    m = c.shape[0]
    P, F, drop = _cylinder_rim(c, R, hl, r, pn)
    gap = np.einsum("kmi,ki->km", P, pn) - po[:, None]
    k = np.repeat(np.arange(m), 8)
    pnr = np.repeat(pn, 8, axis=0)
    P = (P - pn[:, None, :] * (0.5 * np.where(drop, 0.0, gap))[:, :, None]).reshape(-1, 3)
    gap[drop] = np.inf
    return k, -pnr, P, gap.reshape(-1), F.reshape(-1)


#: feature ids of the rim points of :func:`_cylinder_rim`, in their order
_RIM_FIDS = np.array([0, 1, 2, 3, 8, 9, 10, 11])


def _cylinder_rim(c, R, hl, r, pn):
    """The rim points of :func:`cylinder_plane` against a surface of
    outward normal ``pn`` (k, 3) (pointing toward the cylinder): per cap the
    deepest (-t), +u, the highest (+t) and -u, t the component of pn in the
    cap plane (the body's x axis when the cap faces pn).  Returns the points
    (k, 8, 3) (cap -z first), their feature ids (k, 8) and ``drop`` (k, 8):
    the points other than the deepest while the cap does not face pn
    within 45 degrees (see cylinder_plane)."""
    ax = R[:, :, 2]
    m = c.shape[0]
    t = pn - np.einsum("ki,ki->k", pn, ax)[:, None] * ax
    tl = _norm(t)
    ok = tl > 1e-6
    tdir = np.where(ok[:, None], t / np.where(ok, tl, 1.0)[:, None], R[:, :, 0])
    udir = cross(ax, tdir)
    rim = np.stack([-tdir, udir, tdir, -udir], axis=1) * r[:, None, None]  # (m, 4, 3)
    caps = c[:, None, :] + np.array([-1.0, 1.0])[None, :, None] * (ax * hl[:, None])[:, None, :]  # (m, 2, 3)
    P = (caps[:, :, None, :] + rim[:, None, :, :]).reshape(m, 8, 3)
    F = np.broadcast_to(_RIM_FIDS, (m, 8))
    # the other rim points only while a cap faces the plane (within 45 deg):
    # then they are (nearly) material points of a cap settling flat; on a
    # cylinder lying on its side they are support points of the curved
    # side, whose material velocity (a rolling cylinder's front point comes
    # down at its speed) would raise speculative rows that brake the roll
    # once the step's sweep reaches a radius (measured: a third short at dt
    # 1/60 s over 4 s)
    side = np.abs(np.einsum("ki,ki->k", pn, ax)) < CYLINDER_FACE_COS
    drop = side[:, None] & (F % 8 != 0)
    return P, F, drop


def _cylinder_sdf(p, cc, Rc, hl, rc):
    """Signed distance (k,) m of points ``p`` (k, 3) to solid cylinders
    (centre ``cc``, rotation ``Rc`` with the axis as body z, half length
    ``hl``, radius ``rc``): the distance outside, minus the depth to the
    nearer of side and cap inside -- the signed distance of a convex set,
    hence convex in p (what :func:`_segment_min` needs)."""
    local = np.einsum("kji,kj->ki", Rc, p - cc)
    dr = np.sqrt(local[:, 0] ** 2 + local[:, 1] ** 2) - rc
    dz = np.abs(local[:, 2]) - hl
    outside = np.sqrt(np.maximum(dr, 0.0) ** 2 + np.maximum(dz, 0.0) ** 2)
    return outside + np.minimum(np.maximum(dr, dz), 0.0)


def _circle_crossings(e0, e1, cc, Rc, rc):
    """Parameters (k, 2) along the segments e0 -> e1 (k, 3) where their
    projection on a cylinder's cap plane crosses its rim circle (radius
    ``rc`` about the axis): the roots of |(x0 + s dx)_xy|^2 = rc^2 in the
    cylinder's frame; NaN where there is no crossing within [0, 1] (a
    segment along the axis, or one that misses the circle)."""
    a0 = np.einsum("kji,kj->ki", Rc, e0 - cc)[:, :2]
    dd = np.einsum("kji,kj->ki", Rc, e1 - e0)[:, :2]
    A = np.einsum("ki,ki->k", dd, dd)
    B = np.einsum("ki,ki->k", a0, dd)
    C = np.einsum("ki,ki->k", a0, a0) - rc * rc
    disc = B * B - A * C
    ok = (A > _EPS * np.maximum(rc * rc, _EPS)) & (disc > 0.0)
    sq = np.sqrt(np.where(ok, disc, 0.0))
    Aq = np.where(ok, A, 1.0)
    s = np.stack([(-B - sq) / Aq, (-B + sq) / Aq], axis=1)
    return np.where(ok[:, None] & (s >= 0.0) & (s <= 1.0), s, np.nan)


def _crossing_points(fn, e0, e1, s2, fid0):
    """Contacts of ``fn(points, rows)`` at the circle crossings ``s2``
    (k, 2) of the segments e0 -> e1 (k, 3), feature ids fid0, fid0 + 1."""
    out = []
    for j in (0, 1):
        rows = np.flatnonzero(~np.isnan(s2[:, j]))
        if rows.size:
            pts = e0[rows] + (e1[rows] - e0[rows]) * s2[rows, j][:, None]
            k, n, p, g, _ = fn(pts, rows)
            out.append((rows[k], n, p, g, np.full(k.size, fid0 + j)))
    return out


def capsule_cylinder(c, R, hl, r, cc, Rc, hlc, rc):
    """Capsule (first) against cylinder (second): the point of the segment
    deepest in (or closest to) the cylinder -- the minimum of the
    cylinder's convex signed distance along it (:func:`_segment_min`) --
    and the end caps, as sphere-cylinder contacts; the points where the
    segment crosses the cylinder's radius (a capsule lying across a
    standing cylinder's cap rests on that chord's ends); and the cylinder's
    rim points facing the capsule (:func:`_cylinder_rim`) with their exact
    distance to the capsule (a capsule lying along a shorter cylinder rests
    on the cylinder's two end points).  Normal from capsule to cylinder;
    feature ids: 0 the minimum, 1, 2 the ends, 3, 4 the crossings, 8 + the
    rim point's id."""
    e0, e1 = _capsule_ends(c, R, hl)
    d = e1 - e0
    s = _segment_min(lambda p: _cylinder_sdf(p, cc, Rc, hlc, rc), e0, e1)[0]
    first = sphere_cylinder(e0 + d * s[:, None], r, cc, Rc, hlc, rc)
    out = [first]
    for end, fid, sv in ((e0, 1, 0.0), (e1, 2, 1.0)):
        keep = np.flatnonzero(np.abs(s - sv) * 2.0 * hl > 0.02 * (2.0 * hl + r))
        if keep.size:
            k, n, p, gg, _ = sphere_cylinder(end[keep], r[keep], cc[keep], Rc[keep], hlc[keep], rc[keep])
            out.append((keep[k], n, p, gg, np.full(k.size, fid)))
    out += _crossing_points(lambda pts, rows: sphere_cylinder(pts, r[rows], cc[rows], Rc[rows], hlc[rows], rc[rows]),
                            e0, e1, _circle_crossings(e0, e1, cc, Rc, rc), 3)
    # the rim facing the capsule: pn from the capsule toward the cylinder
    m = c.shape[0]
    P, F, drop = _cylinder_rim(cc, Rc, hlc, rc, first[1])
    Pf = P.reshape(-1, 3)
    rows = np.repeat(np.arange(m), 8)
    k, n, p, g, _ = sphere_capsule(Pf, np.zeros(Pf.shape[0]), c[rows], R[rows], hl[rows], r[rows])
    g = np.where(drop.reshape(-1), np.inf, g)
    out.append((rows[k], -n, p, g, 8 + F.reshape(-1)))
    return _cat(out)


#: the twelve edges of a box in its frame: (start, end) corner multipliers,
#: edges along x, then y, then z
_BOX_EDGES = np.array([[[-1, sy, sz], [1, sy, sz]] for sy in (-1, 1) for sz in (-1, 1)]
                      + [[[sx, -1, sz], [sx, 1, sz]] for sx in (-1, 1) for sz in (-1, 1)]
                      + [[[sx, sy, -1], [sx, sy, 1]] for sx in (-1, 1) for sy in (-1, 1)], float)  # (12, 2, 3)
#: an edge point is a contact only where it is deeper (or closer) than both
#: of its corners by this much (m): on a flat stretch the corners stand for it
EDGE_POINT_TOL = 1e-9


def box_cylinder(cb, Rb, hb, cc, Rc, hl, rc, margin=None):
    """Box (first) against cylinder (second), as points of each body
    against the other's exact signed distance:

    * the box's corners (8) and, per edge (12), its point deepest in (or
      closest to) the cylinder -- the minimum of the cylinder's convex
      signed distance along the edge (:func:`_segment_min`), kept where it
      is deeper than both corners -- and where the edge crosses the
      cylinder's radius (a box overhanging a cap rests on those points), as
      sphere-cylinder contacts of radius 0;
    * the cylinder's rim points (:func:`_cylinder_rim`) facing the box face
      of largest separation (the separating-axis test over the box's three
      face normals), with their exact distance to the box.

    Every candidate's gap is exact for its point; between them they hold
    every way a box and a cylinder meet: faces on caps or on the side (the
    corners, the rim's support square, the side line's ends), an edge on
    the side or across a rim (the edge's deepest point), a corner on either.
    Normal from box to cylinder; feature ids 0-7 corners, 8-19 edge minima,
    20-43 edge crossings (20 + 2 edge + j), 48 + the rim point's id.
    ``margin`` (k,) m, optional: edges farther than it from the cylinder's
    bounding sphere are not searched (their points would be dropped)."""
    m = cb.shape[0]
    out = []
    corners = cb[:, None, :] + np.einsum("kij,kmj->kmi", Rb, _CORNERS[None, :, :] * hb[:, None, :])
    rows8 = np.repeat(np.arange(m), 8)
    k, n, p, g, _ = sphere_cylinder(corners.reshape(-1, 3), np.zeros(8 * m), cc[rows8], Rc[rows8], hl[rows8], rc[rows8])
    out.append((rows8[k], n, p, g, np.tile(np.arange(8), m)))
    ends = cb[:, None, None, :] + np.einsum("kij,kemj->kemi", Rb, _BOX_EDGES[None] * hb[:, None, None, :])  # (m, 12, 2, 3)
    e0 = ends[:, :, 0].reshape(-1, 3)
    e1 = ends[:, :, 1].reshape(-1, 3)
    rows12 = np.repeat(np.arange(m), 12)
    edge_id = np.tile(np.arange(12), m)
    if margin is not None:
        # the golden-section search is the costly part: only edges that
        # may come within the margin of the cylinder's bounding sphere
        near = np.flatnonzero(_norm(_segment_closest(cc[rows12], e0, e1)[0] - cc[rows12])
                              - np.sqrt(hl * hl + rc * rc)[rows12] < margin[rows12])
        rows12, edge_id, e0, e1 = rows12[near], edge_id[near], e0[near], e1[near]
    ccr, Rcr, hlr, rcr = cc[rows12], Rc[rows12], hl[rows12], rc[rows12]
    if rows12.size:
        s, f_s, f_ends = _segment_min(lambda q: _cylinder_sdf(q, ccr, Rcr, hlr, rcr), e0, e1)
        pts = e0 + (e1 - e0) * s[:, None]
        sel = np.flatnonzero(f_s < f_ends - EDGE_POINT_TOL)
        if sel.size:
            k, n, p, g, _ = sphere_cylinder(pts[sel], np.zeros(sel.size), ccr[sel], Rcr[sel], hlr[sel], rcr[sel])
            out.append((rows12[sel[k]], n, p, g, 8 + edge_id[sel[k]]))
        for kk, n, p, g, f in _crossing_points(
                lambda q, rows: sphere_cylinder(q, np.zeros(rows.size), ccr[rows], Rcr[rows], hlr[rows], rcr[rows]),
                e0, e1, _circle_crossings(e0, e1, ccr, Rcr, rcr), 0):
            out.append((rows12[kk], n, p, g, 20 + 2 * edge_id[kk] + f))
    # the rim facing the box face of largest separation
    dA = np.einsum("kji,kj->ki", Rb, cc - cb)  # cylinder centre in the box frame
    axc = np.einsum("kji,kj->ki", Rb, Rc[:, :, 2])  # cylinder axis in the box frame
    sup = rc[:, None] * np.sqrt(np.maximum(1.0 - axc * axc, 0.0)) + hl[:, None] * np.abs(axc)
    sep = np.abs(dA) - hb - sup
    f = np.argmax(sep, axis=1)
    ar = np.arange(m)
    pn = Rb[ar, :, f] * np.where(dA[ar, f] >= 0.0, 1.0, -1.0)[:, None]
    P, F, drop = _cylinder_rim(cc, Rc, hl, rc, pn)
    Pf = P.reshape(-1, 3)
    k, n, p, g, _ = sphere_box(Pf, np.zeros(8 * m), cb[rows8], Rb[rows8], hb[rows8])
    g = np.where(drop.reshape(-1), np.inf, g)
    out.append((rows8[k], -n, p, g, 48 + F.reshape(-1)))
    return _cat(out)


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


# ---------------------------------------------------------------------------
# box-box

def _clip_batch(P: np.ndarray, cnt: np.ndarray, nrm: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sutherland-Hodgman over a batch of polygons: keep the part of each
    polygon with n.p <= off.  ``P`` (k, w, 3) vertices (the first ``cnt``
    (k,) of each row valid), ``nrm`` (k, 3), ``off`` (k,).  Same vertices in
    the same order as the one-polygon algorithm: per edge (p, q), p if it is
    inside, then the crossing point if the edge crosses the plane."""
    k, w = P.shape[0], P.shape[1]
    if w == 0:
        return P, cnt
    nx, ny, nz = nrm[:, 0:1], nrm[:, 1:2], nrm[:, 2:3]
    dp = nx * P[:, :, 0] + ny * P[:, :, 1] + nz * P[:, :, 2] - off[:, None]  # (k, w)
    slot = np.arange(w)
    valid = slot[None, :] < cnt[:, None]
    if np.all((dp <= 0.0) | ~valid):
        return P, cnt  # every vertex inside: all kept, no edge crosses
    nxt = (slot[None, :] + 1) % np.maximum(cnt, 1)[:, None]  # (k, w)
    rows = np.arange(k)[:, None]
    Q = P[rows, nxt]
    dq = dp[rows, nxt]
    keep_p = valid & (dp <= 0.0)
    cross_ = valid & (((dp < 0.0) & (0.0 < dq)) | ((dq < 0.0) & (0.0 < dp)))
    den = np.where(cross_, dp - dq, 1.0)
    t = (dp / den)[:, :, None]
    X = P + (Q - P) * t
    cand = np.empty((k, 2 * w, 3))
    cand[:, 0::2] = P
    cand[:, 1::2] = X
    mask = np.empty((k, 2 * w), bool)
    mask[:, 0::2] = keep_p
    mask[:, 1::2] = cross_
    new_cnt = mask.sum(axis=1)
    wn = int(new_cnt.max(initial=0))
    order = np.argsort(~mask, axis=1, kind="stable")[:, :wn]
    return cand[rows, order], new_cnt


def _edge_axes(C, dA, hA, hB):
    """Separations (k, 9) and unit axes (k, 9, 3) (A's frame) of the edge
    axes A_i x B_j, index 3 i + j; -inf where the axis is degenerate or
    duplicates a face normal."""
    k = C.shape[0]
    # e_i x c for c = C[:, :, j]: (0, -c2, c1), (c2, 0, -c0), (-c1, c0, 0)
    L = np.zeros((k, 3, 3, 3))  # [k, i, j, component]
    c0, c1, c2 = C[:, 0, :], C[:, 1, :], C[:, 2, :]  # (k, 3) over j
    L[:, 0, :, 1] = -c2
    L[:, 0, :, 2] = c1
    L[:, 1, :, 0] = c2
    L[:, 1, :, 2] = -c0
    L[:, 2, :, 0] = -c1
    L[:, 2, :, 1] = c0
    L = L.reshape(k, 9, 3)
    # (einsum reductions: the same sums, bit for bit, as per-axis einsums)
    ln = np.sqrt(np.einsum("kai,kai->ka", L, L))
    ok = ln > 1e-5
    Ln = L / np.where(ok, ln, 1.0)[..., None]
    aL = np.abs(Ln)
    rA = np.einsum("kai,ki->ka", aL, hA)
    aLB = np.abs(np.einsum("kai,kij->kaj", Ln, C))
    rB = np.einsum("kaj,kj->ka", aLB, hB)
    s = np.abs(np.einsum("kai,ki->ka", Ln, dA)) - rA - rB
    # an edge axis parallel to a face normal duplicates that face axis
    dup = (aL.max(axis=2) > 1 - 1e-9) | (aLB.max(axis=2) > 1 - 1e-9)
    return np.where(ok & ~dup, s, -np.inf), Ln


def _edge_contact(p, e, cA, RA, hA, cB, RB, hB, d, axesE):
    """Edge-edge contact of pair ``p`` on edge axis ``e``: (normal, point)."""
    i, j = divmod(e, 3)
    L = RA[p] @ axesE[p, e]
    if L @ d[p] < 0:
        L = -L
    sA = np.sign(RA[p].T @ L)
    sB = -np.sign(RB[p].T @ L)
    pa = cA[p] + RA[p] @ (np.where(np.arange(3) == i, 0.0, sA) * hA[p])
    pb = cB[p] + RB[p] @ (np.where(np.arange(3) == j, 0.0, sB) * hB[p])
    a0, a1 = pa - RA[p][:, i] * hA[p, i], pa + RA[p][:, i] * hA[p, i]
    b0, b1 = pb - RB[p][:, j] * hB[p, j], pb + RB[p][:, j] * hB[p, j]
    qa, qb = _segment_segment(a0[None], a1[None], b0[None], b1[None])
    return L, 0.5 * (qa[0] + qb[0])


def box_box(cA, RA, hA, cB, RB, hB, margin):
    """Separating axes + clipping; normal from A to B.  ``margin`` (k,).

    Vectorised over the pairs: the face case clips every pair's incident
    face at once (:func:`_clip_batch`); the rare edge-edge case is a loop."""
    k = cA.shape[0]
    if k == 0:
        return _empty()
    d = cB - cA
    C = np.einsum("kji,kjl->kil", RA, RB)  # C[i, j] = A_i . B_j
    absC = np.abs(C) + 1e-9
    dA = np.einsum("kji,kj->ki", RA, d)
    # faces of A
    sepA = np.abs(dA) - (hA + np.einsum("kij,kj->ki", absC, hB))
    dB = np.einsum("kij,ki->kj", C, dA)
    sepB = np.abs(dB) - (hB + np.einsum("kij,ki->kj", absC, hA))
    # edges A_i x B_j, in A's frame: L = e_i x C[:, :, j]
    sepE, axesE = _edge_axes(C, dA, hA, hB)
    ar = np.arange(k)
    fa = np.argmax(sepA, axis=1)
    fb = np.argmax(sepB, axis=1)
    sa, sb = sepA[ar, fa], sepB[ar, fb]
    e = np.argmax(sepE, axis=1)
    se = sepE[ar, e]
    # prefer face axes (stable manifolds): an edge axis or B's face must be
    # clearly better (larger separation) than the alternative
    tol_abs = 1e-5 * (hA.max(axis=1) + hB.max(axis=1))
    best_face = np.maximum(sa, sb)
    edge = se > best_face + 0.05 * np.abs(best_face) + tol_abs
    flip = sb > sa + 0.05 * np.abs(sa) + tol_abs
    # slots: the edge-edge point, then up to four face-manifold points, per
    # pair, emitted in pair order
    S_n = np.zeros((k, 5, 3))
    S_p = np.zeros((k, 5, 3))
    S_g = np.zeros((k, 5))
    S_f = np.zeros((k, 5), np.int64)
    S_ok = np.zeros((k, 5), bool)
    for p in np.flatnonzero(edge).tolist():
        if se[p] < margin[p]:
            L, pt = _edge_contact(p, int(e[p]), cA, RA, hA, cB, RB, hB, d, axesE)
            S_n[p, 0], S_p[p, 0], S_g[p, 0], S_f[p, 0], S_ok[p, 0] = L, pt, se[p], 64 + int(e[p]), True
    # The face manifold of every pair, edge pairs included.  An edge-edge
    # point alone is blind to the faces about to come down and to the
    # corners already inside: a box spinning at 20-27 rad/s about an edge
    # that crossed another box's edge brought the edge's end down onto that
    # box's face at 2 m/s; the axis of least overlap switched between the
    # face and the edge from one rerun of the step to the next, and with it
    # the contacts, so the time of impact search never converged and the
    # corner went 5.7 mm in.  An edge pair keeps the face points' gaps
    # clamped at the edge axis' separation: the edge axis is the pair's
    # least overlap, and no point of a body lies deeper in the other than
    # that, while its overlap along a face normal may be more.
    _box_box_faces(ar, cA, RA, hA, cB, RB, hB, margin, dA, dB, fa, fb, flip,
                   S_n[:, 1:], S_p[:, 1:], S_g[:, 1:], S_f[:, 1:], S_ok[:, 1:])
    _edge_pair_face_points(S_ok[:, 1:], S_g[:, 1:], edge, se, margin)
    if not S_ok.any():
        return _empty()
    kk = np.repeat(ar, 5).reshape(k, 5)
    m = S_ok
    return kk[m], S_n[m], S_p[m], S_g[m], S_f[m]


def _edge_pair_face_points(ok: np.ndarray, gap: np.ndarray, edge: np.ndarray, se: np.ndarray,
                           margin: np.ndarray) -> None:
    """The face-manifold points of the edge pairs (``edge`` (k,) bool),
    slots ``ok``, ``gap`` (k, 4), in place: kept, their gaps clamped at the
    pair's edge-axis separation ``se`` (k,) m (see :func:`box_box`) -- and
    dropped where that puts them beyond the pair's ``margin`` (k,) m."""
    gap[edge] = np.maximum(gap[edge], se[edge, None])
    ok[edge] &= gap[edge] < margin[edge, None]


def _box_box_faces(idx, cA, RA, hA, cB, RB, hB, margin, dA, dB, fa, fb, flip, S_n, S_p, S_g, S_f, S_ok):
    """Face-case contacts of the pairs ``idx``, written into the slots."""
    k = idx.size
    ar = np.arange(k)
    fl = flip[idx]
    f3 = fl[:, None]
    # reference box: A, or B when flipped (rows of the stacked [A; B] arrays)
    nA = cA.shape[0]
    ref_i = idx + nA * fl
    inc_i = idx + nA * ~fl
    cAB = np.concatenate([cA, cB])
    RAB = np.concatenate([RA, RB])
    hAB = np.concatenate([hA, hB])
    ref_c, ref_R, ref_h = cAB[ref_i], RAB[ref_i], hAB[ref_i]
    inc_c, inc_R, inc_h = cAB[inc_i], RAB[inc_i], hAB[inc_i]
    face = np.where(fl, fb[idx], fa[idx])
    # A's face: normal toward B; B's face: from B toward A
    sgnA = np.where(dA[idx, fa[idx]] >= 0, 1.0, -1.0)
    sgnB = np.where(dB[idx, fb[idx]] <= 0, 1.0, -1.0)
    nrm = ref_R[ar, :, face] * np.where(fl, sgnB, sgnA)[:, None]
    # incident face: the face of the other box most anti-parallel to nrm
    # (batched matmul: the same sums, bit for bit, as one pair's inc_R.T @ nrm)
    dots = np.matmul(inc_R.transpose(0, 2, 1), nrm[:, :, None])[:, :, 0]
    fi = np.argmax(np.abs(dots), axis=1)
    sgn = np.where(dots[ar, fi] > 0, -1.0, 1.0)
    fc = inc_c + inc_R[ar, :, fi] * (sgn * inc_h[ar, fi])[:, None]
    u_i = np.where(fi == 0, 1, 0)
    v_i = np.where(fi == 2, 1, 2)
    U = inc_R[ar, :, u_i] * inc_h[ar, u_i][:, None]
    V = inc_R[ar, :, v_i] * inc_h[ar, v_i][:, None]
    P = np.empty((k, 4, 3))
    P[:, 0] = fc + U + V
    P[:, 1] = fc - U + V
    P[:, 2] = fc - U - V
    P[:, 3] = fc + U - V
    cnt = np.full(k, 4)
    ref_face_c = ref_c + nrm * ref_h[ar, face][:, None]
    # side planes of the reference face: its other two axes, ascending
    a_lo = np.where(face == 0, 1, 0)
    a_hi = np.where(face == 2, 1, 2)
    for a in (a_lo, a_hi):
        ax = ref_R[ar, :, a]
        off = np.matmul(ax[:, None, :], ref_c[:, :, None])[:, 0, 0]  # = ax @ ref_c per pair, bit for bit
        ha = ref_h[ar, a]
        P, cnt = _clip_batch(P, cnt, ax, off + ha)
        P, cnt = _clip_batch(P, cnt, -ax, -off + ha)
    w = P.shape[1]
    if w == 0:
        return
    valid = np.arange(w)[None, :] < cnt[:, None]
    D = P - ref_face_c[:, None, :]
    gap = np.matmul(D, nrm[:, :, None])[..., 0]
    valid &= gap < margin[idx][:, None]
    nv = valid.sum(axis=1)
    # at most four points: all when there are <= 4, else the deepest, the one
    # farthest from it, and the two on either side of that line farthest from it
    sel = np.full((k, 4), -1, np.int64)
    few = nv <= 4
    if few.any():
        o = np.argsort(~valid[few], axis=1, kind="stable")[:, :4]
        fi_ = np.flatnonzero(few)
        sel[fi_[:, None], np.arange(o.shape[1])[None, :]] = np.where(np.take_along_axis(valid[few], o, axis=1), o, -1)
    many = np.flatnonzero(~few)
    if many.size:
        Pm, vm, gm, nm = P[many], valid[many], gap[many], nrm[many]
        r = np.arange(many.size)
        i0 = np.argmin(np.where(vm, gm, np.inf), axis=1)
        E = Pm - Pm[r, i0][:, None, :]
        dd = np.where(vm, np.einsum("kmi,kmi->km", E, E), -np.inf)
        i1 = np.argmax(dd, axis=1)
        cr = cross(E[r, i1][:, None, :], E)
        area = np.matmul(cr, nm[:, :, None])[..., 0]
        i2 = np.argmax(np.where(vm, area, -np.inf), axis=1)
        i3 = np.argmin(np.where(vm, area, np.inf), axis=1)
        cand = np.stack([i0, i1, i2, i3], axis=1)
        # unique, first occurrence order
        dup = np.zeros((many.size, 4), bool)
        for s in range(1, 4):
            dup[:, s] = np.any(cand[:, s:s + 1] == cand[:, :s], axis=1)
        kept = np.where(dup, -1, cand)
        o = np.argsort(kept < 0, axis=1, kind="stable")
        sel[many] = np.take_along_axis(kept, o, axis=1)
    ok = sel >= 0
    sidx = np.where(ok, sel, 0)
    Ps = P[ar[:, None], sidx] if w else np.zeros((k, 4, 3))
    gs = gap[ar[:, None], sidx]
    normal = np.where(f3, -nrm, nrm)
    rows = idx
    S_ok[rows] = ok
    S_g[rows] = np.where(ok, gs, 0.0)
    S_p[rows] = Ps - nrm[:, None, :] * (0.5 * gs)[:, :, None]
    S_n[rows] = normal[:, None, :]
    S_f[rows] = (np.where(fl, 16, 0) + 4 * face)[:, None] + np.arange(4)[None, :]


def _empty():
    return (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))


def _cat(parts):
    parts = [p for p in parts if p[0].size]
    if not parts:
        return _empty()
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(5))


# ---------------------------------------------------------------------------
# dispatch

class _BodyGeom(dict):
    """Geometry of the bodies ``idx``: ``c`` centres, ``R`` rotations, ``r``
    radii, ``h`` half-extents, ``hl`` half-lengths, each gathered on first
    use (a pair function reads only what its shapes need).  ``const``: the
    pose-independent entries already gathered (kept by the pair groups)."""

    def __init__(self, model, X, R, idx, const=None):
        super().__init__()
        self._src = {"c": X, "R": R, "r": model.radius, "h": model.half_extents, "hl": model.half_length}
        self._idx = idx
        self._const = const

    def __missing__(self, key):
        const = self._const
        if const is not None and key in const:
            v = self[key] = const[key]
            return v
        v = self[key] = self._src[key][self._idx]
        if const is not None and key in ("r", "h", "hl"):
            const[key] = v
        return v


def _body_geom(model, X, R, idx, const=None):
    return _BodyGeom(model, X, R, idx, const)


def _bb_sphere_sphere(A, B, margin):
    return sphere_sphere(A["c"], A["r"], B["c"], B["r"])


def _bb_sphere_box(A, B, margin):
    return sphere_box(A["c"], A["r"], B["c"], B["R"], B["h"])


def _bb_box_box(A, B, margin):
    return box_box(A["c"], A["R"], A["h"], B["c"], B["R"], B["h"], margin)


def _bb_sphere_capsule(A, B, margin):
    return sphere_capsule(A["c"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_sphere_cylinder(A, B, margin):
    return sphere_cylinder(A["c"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_box_capsule(A, B, margin):
    # capsule_box has the capsule first: swap and flip the normal
    k, n, p, g, f = capsule_box(B["c"], B["R"], B["hl"], B["r"], A["c"], A["R"], A["h"])
    return k, -n, p, g, f


def _bb_capsule_capsule(A, B, margin):
    return capsule_capsule(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_box_cylinder(A, B, margin):
    return box_cylinder(A["c"], A["R"], A["h"], B["c"], B["R"], B["hl"], B["r"], margin)


def _bb_capsule_cylinder(A, B, margin):
    return capsule_cylinder(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_cylinder_cylinder(A, B, margin):
    return cylinder_cylinder(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["hl"], B["r"], margin)


def _cylinder_sbox(A, B, m):
    # box_cylinder has the box first: swap and flip the normal
    k, n, p, g, f = box_cylinder(B["c"], B["R"], B["h"], A["c"], A["R"], A["hl"], A["r"], m)
    return k, -n, p, g, f


def _plane(model, pk):
    return dict(n=model.plane_normal[pk], o=model.plane_offset[pk])


def _sbox(model, sk):
    return dict(c=model.sbox_pos[sk], R=model.sbox_R[sk], h=model.sbox_half[sk])


#: body-body functions keyed by canonically ordered shape codes
TABLE = {
    (SPHERE, SPHERE): _bb_sphere_sphere,
    (SPHERE, BOX): _bb_sphere_box,
    (BOX, BOX): _bb_box_box,
    (SPHERE, CAPSULE): _bb_sphere_capsule,
    (BOX, CAPSULE): _bb_box_capsule,
    (CAPSULE, CAPSULE): _bb_capsule_capsule,
    (SPHERE, CYLINDER): _bb_sphere_cylinder,
    (BOX, CYLINDER): _bb_box_cylinder,
    (CAPSULE, CYLINDER): _bb_capsule_cylinder,
    (CYLINDER, CYLINDER): _bb_cylinder_cylinder,
}

#: body-plane functions keyed by the body's shape code
PLANE_TABLE = {
    SPHERE: lambda A, P, m: sphere_plane(A["c"], A["r"], P["n"], P["o"]),
    BOX: lambda A, P, m: box_plane(A["c"], A["R"], A["h"], P["n"], P["o"]),
    CAPSULE: lambda A, P, m: capsule_plane(A["c"], A["R"], A["hl"], A["r"], P["n"], P["o"]),
    CYLINDER: lambda A, P, m: cylinder_plane(A["c"], A["R"], A["hl"], A["r"], P["n"], P["o"]),
}

#: body-static-box functions keyed by the body's shape code
SBOX_TABLE = {
    SPHERE: lambda A, B, m: sphere_box(A["c"], A["r"], B["c"], B["R"], B["h"]),
    BOX: lambda A, B, m: box_box(A["c"], A["R"], A["h"], B["c"], B["R"], B["h"], m),
    CAPSULE: lambda A, B, m: capsule_box(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["h"]),
    CYLINDER: _cylinder_sbox,
}


def unsupported_pairs(model) -> list[str]:
    """Shape pairs the scene may bring into contact that the table lacks."""
    if not model.has("contact"):
        return []
    names = {SPHERE: "sphere", BOX: "box", CAPSULE: "capsule", CYLINDER: "cylinder"}
    shapes = sorted(set(int(s) for s in model.shape))
    out = []
    if model.n >= 2:
        for a in shapes:
            for b in shapes:
                if a <= b and (a, b) not in TABLE and (a != b or int(np.sum(model.shape == a)) >= 2):
                    out.append(f"{names[a]}-{names[b]}")
    if model.plane_normal.shape[0]:
        out += [f"{names[s]}-plane" for s in shapes if s not in PLANE_TABLE]
    if model.sbox_pos.shape[0]:
        out += [f"{names[s]}-box(static)" for s in shapes if s not in SBOX_TABLE]
    return out


def _ro(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _bb_groups(model, pi, pj) -> list:
    """Body-body candidate pairs grouped by canonically ordered shape pair:
    [(fn, sel, a, b, const_a, const_b, (e, mus, muk, mur))] with ``sel`` the
    pairs of the group, a/b its bodies (first/second shape) and the pair
    coefficients per pair.  Depends only on the candidate pairs."""
    si, sj = model.shape[pi], model.shape[pj]
    swap = si > sj
    a = np.where(swap, pj, pi)
    b = np.where(swap, pi, pj)
    sa = np.minimum(si, sj)
    sb = np.maximum(si, sj)
    key = sa * 8 + sb
    out = []
    for kv in np.unique(key):
        sel = np.flatnonzero(key == kv)
        fn = TABLE.get((int(kv) // 8, int(kv) % 8))
        if fn is None:
            continue
        ga, gb = _ro(a[sel]), _ro(b[sel])
        mat = tuple(_ro(t[ga, gb]) for t in (model.e_bb, model.mus_bb, model.muk_bb, model.mur_bb))
        out.append((fn, sel, ga, gb, {}, {}, mat))
    return out


def _static_groups(model, pairs, table, statics, e_mu) -> list:
    """Body-static candidate pairs grouped by the body's shape:
    [(fn, sel, bodies, rows, static indices, const, (e, mus, muk, mur))]."""
    bi, sk = pairs
    shapes = model.shape[bi]
    out = []
    for s in np.unique(shapes):
        sel = np.flatnonzero(shapes == s)
        fn = table.get(int(s))
        if fn is None:
            continue
        b_, k_ = _ro(bi[sel]), _ro(sk[sel])
        st = _ro(statics[k_])
        mat = tuple(_ro(t[b_, st]) for t in e_mu)
        out.append((fn, sel, b_, k_, st, {}, mat))
    return out


#: pair groupings a narrow phase keeps (keyed by the candidate pairs);
#: cleared when full
GROUP_CACHE = 16


def _cached(cache, key, make):
    if cache is None:
        return make()
    v = cache.get(key)
    if v is None:
        if len(cache) >= GROUP_CACHE:
            cache.clear()
        v = cache[key] = make()
    return v


def collide_pairs(model, X, R, pi, pj, plane_pairs, sbox_pairs, margin_bb, margin_bp, margin_bs,
                  cache: dict | None = None) -> Contacts:
    """Contacts for candidate pairs at the pose (X (n, 3), R (n, 3, 3)).

    ``pi``/``pj`` body-body pairs (i < j) with margins ``margin_bb``;
    ``plane_pairs``/``sbox_pairs`` (body, row) with margins.  Returns
    :class:`Contacts` with b = n for statics, ordered deterministically
    (body-body by pair, then planes, then static boxes), with their pair
    coefficients.  ``cache``: a dict in which the grouping of the candidate
    pairs by shape (and their coefficients) is kept, keyed by the pairs --
    it depends on nothing else, and a resting scene has the same candidates
    every step."""
    n = model.n
    parts: list[Contacts] = []
    if pi.size:
        groups = _cached(cache, ("bb", pi.tobytes(), pj.tobytes()), lambda: _bb_groups(model, pi, pj))
        for fn, sel, ga, gb, ca, cb, mat in groups:
            mg = margin_bb[sel]
            k, nn, p, g, f = fn(_body_geom(model, X, R, ga, ca), _body_geom(model, X, R, gb, cb), mg)
            keep = g < mg[k]
            if keep.all():
                parts.append(Contacts(ga[k], gb[k], np.full(k.size, -1, np.int64), nn, p, g, f,
                                      mat[0][k], mat[1][k], mat[2][k], mat[3][k]))
                continue
            k = k[keep]
            parts.append(Contacts(ga[k], gb[k], np.full(k.size, -1, np.int64), nn[keep], p[keep], g[keep], f[keep],
                                  mat[0][k], mat[1][k], mat[2][k], mat[3][k]))
    for tag, pairs, table, geom, margins, statics, e_mu in (
            ("plane", plane_pairs, PLANE_TABLE, _plane, margin_bp, model.plane_static,
             (model.e_bs, model.mus_bs, model.muk_bs, model.mur_bs)),
            ("sbox", sbox_pairs, SBOX_TABLE, _sbox, margin_bs, model.sbox_static,
             (model.e_bs, model.mus_bs, model.muk_bs, model.mur_bs))):
        bi, sk = pairs
        if bi.size == 0:
            continue
        groups = _cached(cache, (tag, bi.tobytes(), sk.tobytes()),
                         lambda: _static_groups(model, pairs, table, statics, e_mu))
        for fn, sel, b_, k_, st, const, mat in groups:
            mg = margins[sel]
            G = const.get("geom")
            if G is None:
                G = const["geom"] = {key: _ro(v) for key, v in geom(model, k_).items()}
            k, nn, p, g, f = fn(_body_geom(model, X, R, b_, const), G, mg)
            keep = g < mg[k]
            if not keep.all():
                k = k[keep]
                nn, p, g, f = nn[keep], p[keep], g[keep], f[keep]
            parts.append(Contacts(b_[k], np.full(k.size, n, np.int64), st[k], nn, p, g, f,
                                  mat[0][k], mat[1][k], mat[2][k], mat[3][k]))
    return Contacts.concat(parts)


class NarrowPhase(Stage):
    """Contacts at the start pose for the broad phase's pairs, with a margin
    per pair of ``contact_margin`` plus both bodies' sweep (how far they can
    close in this step)."""

    name = "narrowphase"
    family = "narrowphase"

    def __init__(self, model):
        self.margin = float(model.setting("contact_margin"))
        self.speculative = model.setting("ccd") != "off"
        self.groups: dict = {}  # pair groupings by candidate pairs (see collide_pairs)

    def __call__(self, model, state, ctx) -> None:
        if ctx.reuse_contacts:
            return
        sw = ctx.sweep if self.speculative else np.zeros(model.n)
        pi, pj = ctx.pairs_i, ctx.pairs_j
        mbb = self.margin + sw[pi] + sw[pj]
        mbp = self.margin + sw[ctx.plane_pairs[0]]
        mbs = self.margin + sw[ctx.sbox_pairs[0]]
        ctx.contacts = collide_pairs(model, state.x, ctx.R0, pi, pj, ctx.plane_pairs, ctx.sbox_pairs, mbb, mbp, mbs,
                                     self.groups)


def pair_contacts(model, X, q_or_R, a: int, b: int, sidx: int) -> Contacts:
    """All features of one pair at a pose, with no margin (for time-of-impact
    refinement).  ``b`` is a body index, or n with ``sidx`` the static."""
    R = q_or_R if q_or_R.ndim == 3 else quat_to_matrix(q_or_R)
    inf = np.array([np.inf])
    z = np.zeros(0, np.int64)
    if sidx < 0:
        i, j = min(a, b), max(a, b)
        return collide_pairs(model, X, R, np.array([i]), np.array([j]), (z, z), (z, z), inf, inf, inf)
    st = model.scene.statics[sidx]
    if st.shape == "plane":
        row = int(np.flatnonzero(model.plane_static == sidx)[0])
        return collide_pairs(model, X, R, z, z, (np.array([a]), np.array([row])), (z, z), inf, inf, inf)
    row = int(np.flatnonzero(model.sbox_static == sidx)[0])
    return collide_pairs(model, X, R, z, z, (z, z), (np.array([a]), np.array([row])), inf, inf, inf)
