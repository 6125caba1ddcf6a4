"""Cylinder against the other shapes: cylinder-plane (per cap the rim
points that follow the support), sphere-cylinder (exact closest points),
box-cylinder and capsule-cylinder (points of each body against the other's
exact signed distance: the box's corners, each edge's -- or the capsule
segment's -- minimum of the cylinder's convex signed distance by golden
section and its crossings of the cylinder's radius, the capsule's end caps,
the cylinder's rim points facing the other body)."""

from __future__ import annotations

import math

import numpy as np

from engine.mathutil import cross
from engine.collision.common import _BOX_EDGES, _cat, _CORNERS, _EPS, _norm, _segment_closest, _segment_min, EDGE_POINT_TOL
from engine.collision.sphere import sphere_box
from engine.collision.capsule import _capsule_ends, sphere_capsule


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
