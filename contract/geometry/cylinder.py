"""Signed-gap kernels of the pairs with a cylinder that have no closed form:
box-cylinder, capsule-cylinder (exact while the capsule's core segment is
outside the cylinder) and cylinder-cylinder, each a candidate set for the
support-function search of contract/geometry/search.py."""

from __future__ import annotations

import numpy as np

from physbench.contract.geometry.exact import _seg_cyl_distance
from physbench.contract.geometry.placed import Placed
from physbench.contract.geometry.search import (
    _box_vertices,
    _circle_closest_to_origin,
    _circle_min,
    _eval_candidates,
    _rim_rim_points,
    _rims,
    _search,
)
from physbench.contract.geometry.support import projection_overlap
from physbench.contract.geometry.vector import _unit_or

def _k_box_cylinder(Bx: Placed, Y: Placed) -> np.ndarray:
    """Boundary pieces of Bx - Y and their normals: box faces (+-u_k), caps
    (+-a), side x box edge (a x u_k) [fixed axes]; side - vertex (normals
    perpendicular to a) and rim - edge (perpendicular to u_k) [great circles];
    rim - vertex ridges (circles, separated case) [closest points]."""
    def cheap(a, b, d):
        ax = b.axis
        axes = [ax] + [a.R[:, :, k] for k in range(3)] + [np.cross(ax, a.R[:, :, k]) for k in range(3)]
        pts = [_circle_closest_to_origin(v - m, aa, R) for v in _box_vertices(a) for (m, aa, R) in _rims(b)]
        return _eval_candidates(a, b, d, axes, pts)

    def expensive(a, b, d, s0):
        s = _circle_min(a, b, d, b.axis, s0)
        for k in range(3):
            s = _circle_min(a, b, d, a.R[:, :, k], s)
        return s

    return _search(Bx, Y, cheap, expensive)


def _k_capsule_cylinder_search(C: Placed, Y: Placed) -> np.ndarray:
    """Capsule = segment + ball r: phi = phi_segment + r, same minimiser.
    Pieces of segment - cylinder: caps (+-a), ruling x segment (a x u),
    side - endpoint (perpendicular to a), segment - rim (perpendicular to u).
    Only called with the core segment meeting the cylinder, i.e. overlapping,
    where the nearest boundary point of A - B is never on a ridge (a ball
    inside a convex set touches its boundary where the normal is unique), so
    the endpoint - rim circles are not needed."""
    def cheap(a, b, d):
        return _eval_candidates(a, b, d, [b.axis, np.cross(b.axis, a.axis)], [])

    def expensive(a, b, d, s0):
        return _circle_min(a, b, d, a.axis, _circle_min(a, b, d, b.axis, s0))

    return _search(C, Y, cheap, expensive)


def _k_capsule_cylinder(C: Placed, Y: Placed) -> np.ndarray:
    m = np.einsum("nj,nji->ni", C.c - Y.c, Y.R)
    u = np.einsum("nj,nji->ni", C.axis, Y.R)
    dist = _seg_cyl_distance(m, u, C.half_length, Y.radius, Y.half_length)
    s = C.radius - dist  # exact while the core segment is outside the cylinder
    scale = np.maximum(np.maximum(Y.radius, Y.half_length), C.half_length)
    core_in = ~(dist > 1e-12 * scale) & np.isfinite(dist)
    if core_in.any():
        s[core_in] = _k_capsule_cylinder_search(C.take(core_in), Y.take(core_in))
    return s


def _k_cylinder_cylinder(A: Placed, B: Placed) -> np.ndarray:
    """Pieces of A - B: caps (+-a_A, +-a_B), side x side (a_A x a_B) [fixed];
    side - rim (perpendicular to a_A or a_B) [great circles]; rim - rim
    (circle-circle local minima)."""
    def cheap(a, b, d):
        return _eval_candidates(a, b, d, [a.axis, b.axis, np.cross(a.axis, b.axis)], [])

    def expensive(a, b, d, s0):
        s = _circle_min(a, b, d, b.axis, _circle_min(a, b, d, a.axis, s0))
        todo = ~(s <= 0.0)  # not yet certified separated
        if not todo.any():
            return s
        a, b, d = a.take(todo), b.take(todo), d[todo]
        # search along each rim of the pair (a basin narrow along one rim is
        # wide along the other); B's search gives Q - P, whose sign +- covers
        pts = [_rim_rim_points(*ra, *rb) for ra in _rims(a) for rb in _rims(b)]
        pts += [_rim_rim_points(*rb, *ra) for ra in _rims(a) for rb in _rims(b)]
        P = np.concatenate(pts, axis=1)
        fb = np.broadcast_to(np.array([0.0, 0.0, 1.0]), P.shape)
        n = _unit_or(P, fb)
        n = np.concatenate([n, -n], axis=1)
        s[todo] = np.minimum(s[todo], projection_overlap(a, b, d, n).min(axis=1))
        return s

    return _search(A, B, cheap, expensive)

