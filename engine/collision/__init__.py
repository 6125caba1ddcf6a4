"""Narrow phase: contact points, normals and signed gaps per shape pair.

One module per shape-pair family (``sphere``, ``capsule``, ``box``,
``cylinder``, ``cylinder_pair``; compiled helpers in ``kernels``), the
compiled driver (``collide``: every candidate pair of a step in one call,
body-body pairs grouped by their canonically ordered shape pair,
body-static pairs by the body's shape, each group through its family's
loop) and the dispatch (``dispatch``: the stage, its buffers, the tables
``TABLE``/``PLANE_TABLE``/``SBOX_TABLE`` of supported pairs).  Every family
is one compiled loop over the pairs of its group (numba
``@njit(cache=True)``, no BLAS); its Python function returns

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
  points, plus the ends of the segments' overlap, kept within the margin,
  so a capsule lying along another rests on two points), capsule-box (minimum of the box's signed distance
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

from physbench.engine.collision.box import box_box, box_plane
from physbench.engine.collision.capsule import capsule_box, capsule_capsule, capsule_plane, sphere_capsule
from physbench.engine.collision.cylinder import box_cylinder, capsule_cylinder, cylinder_plane, sphere_cylinder
from physbench.engine.collision.cylinder_pair import cylinder_cylinder
from physbench.engine.collision.dispatch import (PLANE_TABLE, SBOX_TABLE, TABLE, NarrowPhase, collide_pairs, pair_contacts,
                                       unsupported_pairs)
from physbench.engine.collision.sphere import sphere_box, sphere_plane, sphere_sphere

__all__ = ["NarrowPhase", "PLANE_TABLE", "SBOX_TABLE", "TABLE", "box_box", "box_cylinder", "box_plane",
           "capsule_box", "capsule_capsule", "capsule_cylinder", "capsule_plane", "collide_pairs",
           "cylinder_cylinder", "cylinder_plane", "pair_contacts", "sphere_box", "sphere_capsule",
           "sphere_cylinder", "sphere_plane", "sphere_sphere", "unsupported_pairs"]
