"""Cylinder against the other shapes: cylinder-plane (per cap the rim
points that follow the support), sphere-cylinder (exact closest points),
box-cylinder and capsule-cylinder (points of each body against the other's
exact signed distance: the box's corners, each edge's -- or the capsule
segment's -- minimum of the cylinder's convex signed distance by golden
section and its crossings of the cylinder's radius, the capsule's end caps,
the cylinder's rim points facing the other body)."""

from __future__ import annotations

import numpy as np
from numba import njit

from physbench.engine.collision.capsule import capsule_ends1
from physbench.engine.collision.kernels import (EDGE_POINT_TOL, CYLINDER_FACE_COS, FACE_TOL, RIM_FIDS, SDF_BOX, SDF_CYLINDER,
                                      Boxes, Cylinders, Slots, crossing_contacts1, cylinder_rim1, gather, local_offset,
                                      norm3, one_cylinder, pair_slots, rim_contacts1, segment_and_caps1,
                                      segment_closest1, segment_min1, slots, sphere_cylinder1, to_local)

__all__ = ["CYLINDER_FACE_COS", "FACE_TOL", "box_cylinder", "capsule_cylinder", "cylinder_plane", "sphere_cylinder"]


#: length of the cylinder kernels' float scratch ``fw`` (their small vectors
#: and matrices as slices of the collider's kept work: nothing allocated a
#: call, tests/test_engine_steady_gyro.py::test_every_gyroscopic_setting_steps_without_allocating)
CYLINDER_FW = 47


def _f(a):
    return np.ascontiguousarray(a, dtype=float)


@njit(cache=True)
def _sphere_cylinder_kernel(c, r, cc, Rc, hl, rc, cap, n, p, g):
    for k in range(c.shape[0]):
        g[k] = sphere_cylinder1(c[k], r[k], cc[k], Rc[k], hl[k], rc[k], cap[k], n[k], p[k])


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
    m = c.shape[0]
    n, p, g = np.empty((m, 3)), np.empty((m, 3)), np.empty(m)
    if m:
        capi = np.full(m, -1, np.int64) if cap is None else np.asarray(cap, np.int64)
        _sphere_cylinder_kernel(_f(c), _f(r), _f(cc), _f(Rc), _f(hl), _f(rc), capi, n, p, g)
    return np.arange(m), n, p, g, np.zeros(m, np.int64)


@njit(cache=True)
def _cylinder_plane_kernel(c, R, hl, r, pn, po, S_n, S_p, S_g, S_f):
    for k in range(c.shape[0]):
        side = cylinder_rim1(c[k], R[k], hl[k], r[k], pn[k], S_p[k])
        for m in range(8):
            drop = side and m % 4 != 0
            g = S_p[k, m, 0] * pn[k, 0] + S_p[k, m, 1] * pn[k, 1] + S_p[k, m, 2] * pn[k, 2] - po[k]
            h = 0.0 if drop else 0.5 * g
            for i in range(3):
                S_p[k, m, i] -= pn[k, i] * h
                S_n[k, m, i] = -pn[k, i]
            S_g[k, m] = np.inf if drop else g
            S_f[k, m] = RIM_FIDS[m]


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
    S_n, S_p, S_g, S_f = np.empty((m, 8, 3)), np.empty((m, 8, 3)), np.empty((m, 8)), np.empty((m, 8), np.int64)
    if m:
        _cylinder_plane_kernel(_f(c), _f(R), _f(hl), _f(r), _f(pn), _f(po), S_n, S_p, S_g, S_f)
    return np.repeat(np.arange(m), 8), S_n.reshape(-1, 3), S_p.reshape(-1, 3), S_g.reshape(-1), S_f.reshape(-1)


@njit(cache=True)
def _capsule_cylinder_kernel(c, R, hl, r, cyl, S, fw):
    """:func:`capsule_cylinder` over the pairs: capsules (c (k, 3), R (k,
    3, 3), half lengths hl, radii r (k,)) against the :class:`Cylinders`
    ``cyl`` into the :class:`Slots` ``S`` (k, 13); ``fw`` (>= CYLINDER_FW,)
    scratch."""
    V = fw[:12].reshape((4, 3))
    e0, e1, x, q = V[0], V[1], V[2], V[3]
    s2 = fw[12:14]
    oh = fw[14:17]
    P = fw[17:41].reshape((8, 3))
    for k in range(c.shape[0]):
        cy = one_cylinder(cyl, k)
        Sk = pair_slots(S, k)
        oh[0], oh[1], oh[2] = cy.hl, cy.r, 0.0
        capsule_ends1(c[k], R[k], hl[k], e0, e1)
        segment_and_caps1(SDF_CYLINDER, e0, e1, hl[k], r[k], cy.c, cy.R, oh, x, Sk.n, Sk.p, Sk.g, Sk.f, Sk.ok)
        crossing_contacts1(e0, e1, r[k], cy, s2, x, 3, 1, 3, 1, Sk)
        # the rim facing the capsule: pn from the capsule toward the cylinder
        rim_contacts1(cy, Sk.n[0], SDF_CYLINDER, e0, e1, cy.R, r[k], 5, 8, P, q, Sk)


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
    out = slots(c.shape[0], 13)
    if c.shape[0]:
        _capsule_cylinder_kernel(_f(c), _f(R), _f(hl), _f(r), Cylinders(c=_f(cc), R=_f(Rc), hl=_f(hlc), r=_f(rc)),
                                 Slots(*out), np.empty(CYLINDER_FW))
    return gather(*out, blocks=[(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 13)])


#: the twelve edges of a box in its frame: (start, end) corner multipliers,
#: edges along x, then y, then z
_BOX_EDGES = np.array([[[-1, sy, sz], [1, sy, sz]] for sy in (-1, 1) for sz in (-1, 1)]
                      + [[[sx, -1, sz], [sx, 1, sz]] for sx in (-1, 1) for sz in (-1, 1)]
                      + [[[sx, sy, -1], [sx, sy, 1]] for sx in (-1, 1) for sy in (-1, 1)], float)  # (12, 2, 3)
_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)  # (8, 3)


@njit(cache=True)
def _box_point(cb, Rb, hb, mult, out):
    """out = cb + Rb (mult * hb): a box point from its frame multipliers."""
    for i in range(3):
        out[i] = cb[i] + (Rb[i, 0] * (mult[0] * hb[0]) + Rb[i, 1] * (mult[1] * hb[1]) + Rb[i, 2] * (mult[2] * hb[2]))


@njit(cache=True)
def _box_cylinder_kernel(box, cyl, margin, use_margin, corners, edges, S, fw):
    """:func:`box_cylinder` over the pairs: the :class:`Boxes` ``box``
    against the :class:`Cylinders` ``cyl`` into the :class:`Slots` ``S``
    (k, 52); ``corners`` (8, 3) and ``edges`` (12, 2, 3) the box's
    multipliers (``_CORNERS``, ``_BOX_EDGES``), ``margin`` (k,) m where
    ``use_margin``; ``fw`` (>= CYLINDER_FW,) scratch."""
    cb, Rb, hb = box.c, box.R, box.h
    cc, Rc, hl, rc = cyl.c, cyl.R, cyl.hl, cyl.r
    S_n, S_p, S_g, S_f, S_ok = S.n, S.p, S.g, S.f, S.ok
    V = fw[:21].reshape((7, 3))
    x, e0, e1, oh, dA, axc, pn = V[0], V[1], V[2], V[3], V[4], V[5], V[6]
    s2 = fw[21:23]
    P = fw[23:47].reshape((8, 3))
    for k in range(cb.shape[0]):
        cy = one_cylinder(cyl, k)
        Sk = pair_slots(S, k)
        oh[0], oh[1], oh[2] = hl[k], rc[k], 0.0
        for m in range(8):
            _box_point(cb[k], Rb[k], hb[k], corners[m], x)
            S_g[k, m] = sphere_cylinder1(x, 0.0, cc[k], Rc[k], hl[k], rc[k], np.int64(-1), S_n[k, m], S_p[k, m])
            S_f[k, m] = m
            S_ok[k, m] = True
        bound = np.sqrt(hl[k] * hl[k] + rc[k] * rc[k])
        for e in range(12):
            _box_point(cb[k], Rb[k], hb[k], edges[e, 0], e0)
            _box_point(cb[k], Rb[k], hb[k], edges[e, 1], e1)
            if use_margin:
                # the golden-section search is the costly part: only edges
                # that may come within the margin of the bounding sphere
                segment_closest1(cc[k], e0, e1, x)
                if not norm3(x[0] - cc[k, 0], x[1] - cc[k, 1], x[2] - cc[k, 2]) - bound < margin[k]:
                    continue
            s, f_s, f_ends = segment_min1(SDF_CYLINDER, e0, e1, cc[k], Rc[k], oh, 40)
            if f_s < f_ends - EDGE_POINT_TOL:
                for i in range(3):
                    x[i] = e0[i] + (e1[i] - e0[i]) * s
                sl = 8 + e
                S_g[k, sl] = sphere_cylinder1(x, 0.0, cc[k], Rc[k], hl[k], rc[k], np.int64(-1), S_n[k, sl], S_p[k, sl])
                S_f[k, sl] = 8 + e
                S_ok[k, sl] = True
            crossing_contacts1(e0, e1, 0.0, cy, s2, x, 20 + e, 12, 20 + 2 * e, 1, Sk)
        # the rim facing the box face of largest separation
        local_offset(Rb[k], cc[k], cb[k], dA)
        for i in range(3):
            x[i] = Rc[k, i, 2]
        to_local(Rb[k], x, axc)
        f = 0
        best = 0.0
        for i in range(3):
            sup = rc[k] * np.sqrt(max(1.0 - axc[i] * axc[i], 0.0)) + hl[k] * abs(axc[i])
            sep = abs(dA[i]) - hb[k, i] - sup
            if i == 0 or sep > best:
                best = sep
                f = i
        sg = 1.0 if dA[f] >= 0.0 else -1.0
        for i in range(3):
            pn[i] = Rb[k, i, f] * sg
        rim_contacts1(cy, pn, SDF_BOX, cb[k], hb[k], Rb[k], 0.0, 44, 48, P, x, Sk)


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
    out = slots(m, 52)
    if m:
        mg = np.zeros(m) if margin is None else _f(margin)
        _box_cylinder_kernel(Boxes(c=_f(cb), R=_f(Rb), h=_f(hb)), Cylinders(c=_f(cc), R=_f(Rc), hl=_f(hl), r=_f(rc)),
                             mg, margin is not None, _CORNERS, _BOX_EDGES, Slots(*out), np.empty(CYLINDER_FW))
    return gather(*out, blocks=[(0, 8), (8, 20), (20, 32), (32, 44), (44, 52)])
