"""Closed-form signed-gap kernels: sphere vs every shape, capsule-capsule,
box-box (separating axes) and capsule-box, and the convex segment-distance
searches that capsule-box and capsule-cylinder share (accuracy in the table
of contract/geometry/__init__.py)."""

from __future__ import annotations

import numpy as np

from physbench.contract.geometry.placed import Placed
from physbench.contract.geometry.vector import _dot, _golden, _norm

_SEG_ITERS = 60       # golden-section steps for segment-vs-convex distances


# ---- exact kernels ---------------------------------------------------------------
# Each kernel returns the signed gap s (N,): s > 0 is the penetration depth;
# s <= 0 means the shapes do not overlap (its magnitude need not be the distance).

def _k_sphere_sphere(A: Placed, B: Placed) -> np.ndarray:
    return A.radius + B.radius - _norm(B.c - A.c)


def _k_sphere_capsule(S: Placed, C: Placed) -> np.ndarray:
    a = C.axis
    v = S.c - C.c
    t = np.clip(_dot(v, a), -C.half_length, C.half_length)
    return S.radius + C.radius - _norm(v - t[:, None] * a)


def _k_sphere_box(S: Placed, B: Placed) -> np.ndarray:
    q = np.einsum("nj,nji->ni", S.c - B.c, B.R)  # centre in the box frame
    e = B.half_extents
    dist = _norm(q - np.clip(q, -e, e))
    inside = np.min(e - np.abs(q), axis=1)  # distance to the nearest face (>= 0 inside)
    return np.where(dist > 0.0, S.radius - dist, S.radius + inside)


def _k_sphere_cylinder(S: Placed, C: Placed) -> np.ndarray:
    # The solid cylinder is a rectangle [0, R] x [-h, h] in the (rho, z)
    # half-plane through the point, so clamping rho and z gives the closest point.
    q = np.einsum("nj,nji->ni", S.c - C.c, C.R)
    rho = np.hypot(q[:, 0], q[:, 1])
    z = q[:, 2]
    dist = np.hypot(np.maximum(rho - C.radius, 0.0), np.maximum(np.abs(z) - C.half_length, 0.0))
    inside = np.minimum(C.radius - rho, C.half_length - np.abs(z))
    return np.where(dist > 0.0, S.radius - dist, S.radius + inside)


def _seg_seg_distance(p1, u1, h1, p2, u2, h2) -> np.ndarray:
    """Distance between segments p1 + s u1 (|s| <= h1) and p2 + t u2 (|t| <= h2),
    unit u1, u2 (Ericson, Real-Time Collision Detection 5.1.9, centred form)."""
    r = p1 - p2
    b = _dot(u1, u2)
    c = _dot(u1, r)
    f = _dot(u2, r)
    denom = 1.0 - b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(denom > 1e-12, np.clip((b * f - c) / np.where(denom > 1e-12, denom, 1.0), -h1, h1), 0.0)
    t = b * s + f
    tc = np.clip(t, -h2, h2)
    s = np.where(t != tc, np.clip(b * tc - c, -h1, h1), s)
    return _norm(r + s[:, None] * u1 - tc[:, None] * u2)


def _k_capsule_capsule(A: Placed, B: Placed) -> np.ndarray:
    d = _seg_seg_distance(A.c, A.axis, A.half_length, B.c, B.axis, B.half_length)
    return A.radius + B.radius - d


def _k_box_box(A: Placed, B: Placed) -> np.ndarray:
    """SAT over the 15 axes, everything expressed in A's frame."""
    C = np.einsum("nji,njk->nik", A.R, B.R)  # C[:, i, k] = u_Ai . u_Bk
    t = np.einsum("nj,nji->ni", B.c - A.c, A.R)
    # axes (N, 15, 3): A's face normals e_i, B's b_k (columns of C) and the
    # edge pairs e_i x b_k written out: the values of np.cross but for the
    # sign of their zeros, which every use below takes |.| or squares of
    # (tests/test_geometry.py::test_box_box_matches_the_cross_product_form)
    axes = np.zeros((A.n, 15, 3))
    axes[:, 0, 0] = axes[:, 1, 1] = axes[:, 2, 2] = 1.0
    axes[:, 3:6] = np.swapaxes(C, 1, 2)
    b0, b1, b2 = C[:, 0], C[:, 1], C[:, 2]  # (N, 3) over k: the components of b_k
    axes[:, 6:9, 1], axes[:, 6:9, 2] = -b2, b1      # e_0 x b = (0, -b_2, b_1)
    axes[:, 9:12, 0], axes[:, 9:12, 2] = b2, -b0    # e_1 x b = (b_2, 0, -b_0)
    axes[:, 12:15, 0], axes[:, 12:15, 1] = -b1, b0  # e_2 x b = (-b_1, b_0, 0)
    nrm = _norm(axes)
    ok = nrm > 1e-12  # parallel edges give no axis (their faces are covered)
    L = axes / np.where(ok, nrm, 1.0)[..., None]
    ra = np.einsum("nmi,ni->nm", np.abs(L), A.half_extents)
    rb = np.einsum("nmk,nk->nm", np.abs(L @ C), B.half_extents)
    ov = ra + rb - np.abs(np.einsum("nmi,ni->nm", L, t))
    ov = np.where(ok, ov, np.inf)
    return ov.min(axis=1)


def _seg_box_distance(m, u, h, e) -> np.ndarray:
    """Distance from segment m + t u (|t| <= h, box frame) to the box [-e, e]:
    golden section on the convex function t -> dist(m + t u, box)."""
    def f(t):
        p = m[:, None, :] + t[..., None] * u[:, None, :]
        return _norm(p - np.clip(p, -e[:, None, :], e[:, None, :]))
    best, _ = _golden(f, -h[:, None], h[:, None], _SEG_ITERS)
    ends = f(np.stack([-h, h], axis=1))
    return np.minimum(best[:, 0], ends.min(axis=1))


def _k_capsule_box(C: Placed, B: Placed) -> np.ndarray:
    m = np.einsum("nj,nji->ni", C.c - B.c, B.R)  # segment centre in the box frame
    u = np.einsum("nj,nji->ni", C.axis, B.R)     # segment direction in the box frame
    e, h, r = B.half_extents, C.half_length, C.radius
    face = e + h[:, None] * np.abs(u) - np.abs(m)  # (N, 3)
    W = np.cross(np.broadcast_to(np.eye(3), (C.n, 3, 3)), u[:, None, :])  # e_k x u
    wn = _norm(W)
    ok = wn > 1e-12
    W = W / np.where(ok, wn, 1.0)[..., None]
    cross = np.einsum("nki,ni->nk", np.abs(W), e) - np.abs(np.einsum("nki,ni->nk", W, m))
    sat = np.minimum(face.min(axis=1), np.where(ok, cross, np.inf).min(axis=1))
    s = r + sat  # exact when the core segment meets the box (sat >= 0)
    need = (sat < 0.0) & (r + sat > 0.0)  # dist >= -sat, so r + sat <= 0 is already separated
    if need.any():
        s[need] = r[need] - _seg_box_distance(m[need], u[need], h[need], e[need])
    return s


def _seg_cyl_distance(m, u, h, R, hc) -> np.ndarray:
    """Distance from segment m + t u (|t| <= h, cylinder frame) to the solid
    cylinder rho <= R, |z| <= hc: golden section (convex in t)."""
    def f(t):
        p = m[:, None, :] + t[..., None] * u[:, None, :]
        rho = np.hypot(p[..., 0], p[..., 1])
        return np.hypot(np.maximum(rho - R[:, None], 0.0), np.maximum(np.abs(p[..., 2]) - hc[:, None], 0.0))
    best, _ = _golden(f, -h[:, None], h[:, None], _SEG_ITERS)
    ends = f(np.stack([-h, h], axis=1))
    return np.minimum(best[:, 0], ends.min(axis=1))

