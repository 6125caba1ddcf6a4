"""The harness's own geometry: overlap depth between shapes, from body states.

Metrics never trust an engine's contact report (MuJoCo's and pybullet's lag
one integration); penetration is measured here from recorded positions and
orientations, the same code for every engine.

``penetration_depths(scene, trace)`` returns (F, P) overlap depths (m, >= 0)
for the P candidate pairs; :func:`measure_penetration` gives the same data
sparsely (and the per-frame maximum without building the dense matrix).

Definition
----------
The depth of two overlapping convex shapes A and B is the length of the
minimum translation that separates them.  With h_X(n) the support function of
shape X about its centre and d = c_B - c_A,

    phi(n) = h_A(n) + h_B(n) - n . d        (n a unit vector)

is the overlap of the two shapes' projections on n (every shape here is
centrally symmetric, so h_X(-n) = h_X(n)).  phi is the support function of the
Minkowski difference A - B, hence

    s = min over unit n of phi(n)

is the penetration depth when the shapes overlap and minus their distance when
they do not; depth = max(0, s).  Every phi(n) is an upper bound of s, so a
method that evaluates phi at a candidate set containing the minimiser is exact,
and one that misses it can only over-report (never under-report) depth.

Methods and accuracy (per shape pair; "exact" = closed form, float rounding)
------------------------------------------------------------------------------
=====================  =====================================================
body vs plane          exact: offset - c.n + h(n) (support point toward -n)
sphere-sphere          exact: r1 + r2 - |d|
sphere-capsule         exact: point-segment distance
capsule-capsule        exact: segment-segment closest points (Ericson 5.1.9)
sphere-box             exact: clamp in the box frame; inside: r + distance to
                       the nearest face
sphere-cylinder        exact: clamp (rho, z) in the cylinder frame; inside:
                       r + min(R - rho, h - |z|)
box-box                exact: separating-axis test over the 15 axes (3 + 3
                       face normals, 9 edge cross products); depth = the least
                       overlap (these axes contain every face normal of A - B)
capsule-box            exact: SAT over the 6 axes of segment vs box (3 face
                       normals, 3 segment x edge) gives r + depth when the
                       capsule's core segment meets the box; otherwise
                       r - dist(segment, box) with the distance minimised by
                       golden-section search along the segment (convex in t;
                       60 steps: |dt| <= 2 h 0.618^60 ~ 6e-13 h)
capsule-cylinder       core segment outside the cylinder: r - distance by the
                       same convex golden-section search (exact to ~1e-12 h);
                       core inside: support-function search (below)
box-cylinder,          support-function search: s = min of phi over a
cylinder-cylinder,     candidate set that contains the minimiser (a normal
capsule-cylinder with  of some piece of the boundary of A - B; capsule =
the core segment       segment + ball, phi_capsule = phi_segment + r):
inside the cylinder      * fixed axes: box face normals, cylinder axes,
                           cross products of axis / edge / segment directions;
                         * ridges rim - box vertex (circles): closest point,
                           closed form (the exact separating direction when
                           the shapes are apart; when they overlap, the
                           nearest boundary point is never on a ridge);
                         * rim - rim pieces: local minima of |P - Q| over the
                           two rims, 64 samples along each rim (both ways),
                           the 3 lowest refined by 26 golden steps; candidate
                           normals P - Q and t_A x t_B;
                         * great circles of normals perpendicular to a
                           cylinder axis, a box edge or a segment: phi there
                           is a sum of |linear| and norm terms in (cos, sin);
                           72 samples, the 3 lowest local minima that can
                           still win (Lipschitz bound) refined by 26 golden
                           steps (6e-7 rad).  Every kink of phi on these
                           circles is one of the fixed axes, so any other
                           minimum is smooth and lands within ~1e-13 m.
                       Exact unless a local minimum of these 1D functions
                       sits in a basin narrower than one sample step (5
                       degrees); then it over-reports by at most phi's
                       variation over that step.  Never under-reports.
                       Measured: 480 000 random poses (incl. coins R/h = 50,
                       rods h/R = 75, plates, sticks) agree with a 240-sample,
                       50-step search within 3.5e-12 m; near-contact poses
                       (depth 1e-3, 1e-6 and -1e-6 m) agree with a dense
                       brute-force direction search within 1e-13 m, with no
                       false positive.  Cost ~40-60 us per box-cylinder and
                       ~150 us per cylinder-cylinder (frame, pair) event.
=====================  =====================================================

A pair whose depth cannot be computed (no kernel in PAIR_KERNELS, an unknown
static shape, a non-finite pose) gives NaN, never a silent 0.

Scaling
-------
Body pairs are culled per frame with bounding spheres: all pairs vectorised
for small scenes, a cKDTree per frame (bodies bucketed by bounding radius so a
few large bodies do not inflate the query radius) for large ones.  The culling
is exact (disjoint bounding spheres imply depth 0), never subsampled.  The
surviving (frame, pair) events are grouped by shape pair, the way MJX groups
collision functions, and each group is evaluated in one vectorised call per
chunk.  Only non-zero depths are stored.  Measured (2-core x86-64, numpy
2.4): 1000 touching spheres on a plane, 600 frames 0.55 s, 2400 frames 2.3 s;
16 balls x 5000 frames 0.03 s; 200 boxes on a static box, 600 frames 1.3 s;
10 stacked cylinders x 2400 frames 3.5 s (cylinder pairs dominate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from contract.rotation import quat_to_matrix, rotation_matrix
from contract.scene import Body, Scene, Static

#: body shapes in the canonical order of PAIR_KERNELS keys
SHAPES = ("sphere", "capsule", "box", "cylinder")
_ORDER = {k: i for i, k in enumerate(SHAPES)}

_INVPHI = (math.sqrt(5.0) - 1.0) / 2.0
_SEG_ITERS = 60       # golden-section steps for segment-vs-convex distances
_CIRCLE_SAMPLES = 72  # samples on a great circle of normals (5 degrees apart)
_CIRCLE_REFINE = 3    # lowest sampled local minima refined per circle
_RIM_SAMPLES = 64     # samples along a rim for the circle-circle search
_RIM_REFINE = 3
_REFINE_ITERS = 26    # golden steps on a great circle's 2-sample bracket: 6e-7 rad
_RIM_ITERS = 26       # golden steps on a rim's 2-sample bracket: 8e-7 rad
_CHUNK = 32768        # events per kernel call (bounds temporary memory)
_CHUNK_SEARCH = 4096  # events per call for the support-function search


# ---- placed shapes ------------------------------------------------------------

class Placed:
    """N placed shapes of one kind: centres ``c`` (N, 3) m, rotations ``R``
    (N, 3, 3) whose columns are the body axes in the world frame (None for
    spheres), and dimensions ``radius`` (N,), ``half_length`` (N,) (capsule and
    cylinder, along body z), ``half_extents`` (N, 3) (box).  Arrays may be
    broadcast views; kernels never write into them."""

    __slots__ = ("kind", "c", "R", "radius", "half_length", "half_extents")

    def __init__(self, kind: str, c: np.ndarray, R: np.ndarray | None = None, radius=0.0,
                 half_length=0.0, half_extents=None):
        n = c.shape[0]
        self.kind = kind
        self.c = c
        self.R = R
        self.radius = np.broadcast_to(np.asarray(radius, float), (n,))
        self.half_length = np.broadcast_to(np.asarray(half_length, float), (n,))
        he = np.zeros(3) if half_extents is None else np.asarray(half_extents, float)
        self.half_extents = np.broadcast_to(he, (n, 3))

    @property
    def n(self) -> int:
        return self.c.shape[0]

    @property
    def axis(self) -> np.ndarray:
        """(N, 3) world direction of body z (capsule/cylinder axis)."""
        return self.R[:, :, 2]

    def take(self, idx) -> "Placed":
        return Placed(self.kind, self.c[idx], None if self.R is None else self.R[idx],
                      self.radius[idx], self.half_length[idx], self.half_extents[idx])

    @classmethod
    def from_pose(cls, kind: str, pos: np.ndarray, quat: np.ndarray | None, radius=0.0,
                  half_length=0.0, half_extents=None) -> "Placed":
        """From positions (N, 3) and wxyz quaternions (N, 4) (normalised here:
        an engine's slightly non-unit quaternion means the unit one)."""
        R = None
        if kind != "sphere":
            q = np.asarray(quat, float)
            with np.errstate(invalid="ignore", divide="ignore"):
                q = q / np.linalg.norm(q, axis=-1, keepdims=True)
            R = quat_to_matrix(q)
        return cls(kind, np.asarray(pos, float), R, radius, half_length, half_extents)


def _placed_body(b: Body, pos: np.ndarray, quat: np.ndarray) -> Placed:
    return Placed.from_pose(b.shape, pos, quat, b.radius, b.half_length, b.half_extents)


def _static_rotation(s: Static) -> np.ndarray:
    return rotation_matrix(s.orientation)


def _placed_static_box(s: Static, n: int) -> Placed:
    """A static box as n copies of one placed box (broadcast views)."""
    return Placed("box", np.broadcast_to(np.asarray(s.position, float), (n, 3)),
                  np.broadcast_to(_static_rotation(s), (n, 3, 3)), half_extents=s.half_extents)


# ---- small vector helpers -----------------------------------------------------

def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _sq(v: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", v, v)


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(_dot(v, v))


def _unit_or(v: np.ndarray, fallback: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """v / |v| where |v| > eps, else ``fallback`` (a unit vector): any unit
    vector is a valid candidate direction, a zero vector is not."""
    n = _norm(v)[..., None]
    ok = n > eps
    return np.where(ok, v / np.where(ok, n, 1.0), fallback)


def _perp_basis(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (N, 3) completing unit w (N, 3) to a right-handed basis."""
    helper = np.where((np.abs(w[:, 0]) < 0.9)[:, None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    t1 = np.cross(w, helper)
    t1 /= _norm(t1)[:, None]
    return t1, np.cross(w, t1)


def _golden(fn: Callable[[np.ndarray], np.ndarray], lo: np.ndarray, hi: np.ndarray,
            iters: int) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised golden-section minimisation of fn on [lo, hi] (any shape).
    Returns (best value, its argument) over every point evaluated, so the
    result is an upper bound of the bracket's minimum even if fn is not
    unimodal there, and exact (to the final bracket width) if it is."""
    a, b = lo, hi
    x1 = b - _INVPHI * (b - a)
    x2 = a + _INVPHI * (b - a)
    f1, f2 = fn(x1), fn(x2)
    best = np.minimum(f1, f2)
    arg = np.where(f1 <= f2, x1, x2)
    for _ in range(iters):
        left = f1 <= f2  # the minimum lies in [a, x2]
        a = np.where(left, a, x1)
        b = np.where(left, x2, b)
        xn = np.where(left, b - _INVPHI * (b - a), a + _INVPHI * (b - a))
        fnew = fn(xn)
        x1, x2, f1, f2 = (np.where(left, xn, x2), np.where(left, x1, xn),
                          np.where(left, fnew, f2), np.where(left, f1, fnew))
        better = fnew < best
        arg = np.where(better, xn, arg)
        best = np.minimum(best, fnew)
    return best, arg


# ---- support functions ----------------------------------------------------------

def _support(G: Placed, n: np.ndarray) -> np.ndarray:
    """h_G(n) = max over the shape of n . (x - c), for unit n (N, M, 3) -> (N, M)."""
    k = G.kind
    if k == "sphere":
        return np.broadcast_to(G.radius[:, None], n.shape[:-1])
    if k == "box":
        return np.einsum("nmi,ni->nm", np.abs(n @ G.R), G.half_extents)
    na = np.einsum("nmj,nj->nm", n, G.axis)
    h = G.half_length[:, None] * np.abs(na)
    if k == "capsule":
        return h + G.radius[:, None]
    if k == "cylinder":
        # |n - (n.a) a| rather than sqrt(1 - (n.a)^2): the latter cancels
        # catastrophically near the axis (an error of R sqrt(eps) ~ 1e-8 R).
        return h + G.radius[:, None] * _norm(n - na[..., None] * G.axis[:, None, :])
    raise ValueError(f"unknown shape {k!r}")


def _phi(A: Placed, B: Placed, d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Overlap of the projections of A and B on unit n (N, M, 3) -> (N, M)."""
    return _support(A, n) + _support(B, n) - np.einsum("nmj,nj->nm", n, d)


# ---- body vs plane ----------------------------------------------------------------
# A plane is {x : n.x = d}, solid on the side n.x < d.  The depth of a convex
# shape is d - min over the shape of n.x = d - c.n + h(n).

def plane_gap(G: Placed, normal: np.ndarray, offset: float) -> np.ndarray:
    """Signed overlap (m, (N,)) of placed shapes with the plane: > 0 is the
    penetration depth, <= 0 minus the clearance."""
    nrm = np.broadcast_to(np.asarray(normal, float), (G.n, 1, 3))
    return offset - G.c @ np.asarray(normal, float) + _support(G, nrm)[:, 0]


def depth_body_plane(b: Body, s: Static, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Depth (m, (F,)) of body ``b`` at poses pos (F, 3), quat (F, 4) below plane ``s``."""
    return np.maximum(0.0, plane_gap(_placed_body(b, pos, quat), s.normal, s.offset))


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
    eye = np.broadcast_to(np.eye(3), (A.n, 3, 3))
    bax = np.swapaxes(C, 1, 2)  # rows: B's axes in A's frame
    cross = np.cross(eye[:, :, None, :], bax[:, None, :, :]).reshape(A.n, 9, 3)
    axes = np.concatenate([eye, bax, cross], axis=1)  # (N, 15, 3)
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


# ---- support-function search (pairs with a cylinder) -----------------------------

class _CirclePhi:
    """phi restricted to the great circle n(theta) = cos(theta) t1 + sin(theta) t2
    (unit t1 perpendicular to unit t2).  Every term of phi is linear in
    (cos, sin) inside an absolute value or a norm, so the dot products are
    precomputed per event and an evaluation is a few batched matrix products:

        phi = const + lin.cs + sum_t W_t |M_t.cs| + sum_q R_q |P_q cs|

    with cs = (cos theta, sin theta), M_t (2,), P_q (3, 2)."""

    def __init__(self, A: Placed, B: Placed, d: np.ndarray, t1: np.ndarray, t2: np.ndarray):
        N = d.shape[0]
        const = np.zeros(N)
        W, M, PW, P = [], [], [], []
        for G in (A, B):
            if G.kind == "sphere":
                const = const + G.radius
            elif G.kind == "box":
                for k in range(3):
                    u = G.R[:, :, k]
                    W.append(G.half_extents[:, k])
                    M.append(np.stack([_dot(t1, u), _dot(t2, u)], axis=1))
            else:
                a = G.axis
                W.append(G.half_length)
                M.append(np.stack([_dot(t1, a), _dot(t2, a)], axis=1))
                if G.kind == "capsule":
                    const = const + G.radius
                else:  # R |n x a| as a vector norm: no cancellation near the axis
                    PW.append(G.radius)
                    P.append(np.stack([np.cross(t1, a), np.cross(t2, a)], axis=2))  # (N, 3, 2)
        self.const = const[:, None]
        self.lin = np.stack([-_dot(t1, d), -_dot(t2, d)], axis=1)[:, None, :]  # (N, 1, 2)
        self.W = np.stack(W, axis=1) if W else None  # (N, T)
        self.M = np.stack(M, axis=1) if W else None  # (N, T, 2)
        self.PW = np.stack(PW, axis=1) if PW else None  # (N, Q)
        self.P = np.concatenate(P, axis=1) if PW else None  # (N, 3Q, 2)

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        """theta (M,) shared by all events, or (N, M) -> phi (N, M)."""
        if theta.ndim == 2 and theta.shape[1] <= 8:
            return self._few(theta)
        cs = np.stack([np.cos(theta), np.sin(theta)], axis=-2)  # (2, M) or (N, 2, M)
        out = self.const + (self.lin @ cs)[:, 0, :]
        if self.W is not None:
            out = out + np.einsum("nt,ntm->nm", self.W, np.abs(self.M @ cs))
        if self.P is not None:
            v = self.P @ cs  # (N, 3Q, M)
            v = v.reshape(v.shape[0], -1, 3, v.shape[-1])
            out = out + np.einsum("nq,nqm->nm", self.PW, np.sqrt(np.einsum("nqim,nqim->nqm", v, v)))
        return out

    def lipschitz(self) -> np.ndarray:
        """(N,) bound on |d phi / d theta|: |d/dtheta m.cs| <= |m| and
        |d/dtheta |P cs|| <= |P cs_perp| <= ||P||_F."""
        L = np.sqrt((self.lin[:, 0, :] ** 2).sum(axis=1))
        if self.W is not None:
            L = L + (self.W * np.sqrt((self.M ** 2).sum(axis=2))).sum(axis=1)
        if self.P is not None:
            fro = np.sqrt((self.P ** 2).sum(axis=2).reshape(self.P.shape[0], -1, 3).sum(axis=2))
            L = L + (self.PW * fro).sum(axis=1)
        return L

    def take(self, rows: np.ndarray) -> "_CirclePhi":
        out = object.__new__(_CirclePhi)
        for k in ("const", "lin", "W", "M", "PW", "P"):
            x = getattr(self, k)
            setattr(out, k, None if x is None else x[rows])
        return out

    def _few(self, theta: np.ndarray) -> np.ndarray:
        """Per-event angles (N, M), M small: plain broadcasting beats tiny
        batched matrix products."""
        c = np.cos(theta)[:, None, :]
        s = np.sin(theta)[:, None, :]
        out = self.const + (self.lin[:, :, 0, None] * c + self.lin[:, :, 1, None] * s)[:, 0, :]
        if self.W is not None:
            out = out + (self.W[:, :, None] * np.abs(self.M[:, :, 0, None] * c + self.M[:, :, 1, None] * s)).sum(axis=1)
        if self.P is not None:
            v = self.P[:, :, 0, None] * c + self.P[:, :, 1, None] * s  # (N, 3Q, M)
            v = (v * v).reshape(v.shape[0], -1, 3, v.shape[-1]).sum(axis=2)
            out = out + (self.PW[:, :, None] * np.sqrt(v)).sum(axis=1)
        return out


def _circle_min(A: Placed, B: Placed, d: np.ndarray, w: np.ndarray, s_best: np.ndarray) -> np.ndarray:
    """min(s_best, min of phi over the great circle of unit normals
    perpendicular to w (N, 3)): 72 samples, then the 3 lowest sampled local
    minima refined by golden section on their two-sample bracket.

    A bracket is refined only if it could beat the best value so far: within
    half a sample step of sample k, phi >= phi_k - L step / 2 with L a
    Lipschitz constant of phi(theta).  That skips nothing that matters and
    most of the work in shallow contacts (the usual case)."""
    t1, t2 = _perp_basis(w)
    fn = _CirclePhi(A, B, d, t1, t2)
    K = _CIRCLE_SAMPLES
    step = 2.0 * np.pi / K
    v = fn(np.arange(K) * step)
    best = np.minimum(s_best, v.min(axis=1))
    locmin = (v <= np.roll(v, 1, axis=1)) & (v <= np.roll(v, -1, axis=1))
    cand = locmin & (v - 0.5 * step * fn.lipschitz()[:, None] < best[:, None])
    rows = np.nonzero(cand.any(axis=1))[0]
    if rows.size == 0:
        return best
    vm = np.where(cand[rows], v[rows], np.inf)
    L = min(_CIRCLE_REFINE, K)
    sel = np.argpartition(vm, L - 1, axis=1)[:, :L]
    valid = np.isfinite(np.take_along_axis(vm, sel, axis=1))
    centre = sel * step
    val, _ = _golden(fn.take(rows), centre - step, centre + step, _REFINE_ITERS)
    best[rows] = np.minimum(best[rows], np.where(valid, val, np.inf).min(axis=1))
    return best


def _circle_closest_to_origin(m: np.ndarray, a: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The point of the circle (centre m, unit axis a, radius R) nearest the
    origin, (N, 3).  (Used on ridges rim - vertex of A - B, in the separated case.)"""
    w = -m - _dot(-m, a)[:, None] * a
    t1, _ = _perp_basis(a)
    return m + R[:, None] * _unit_or(w, t1)


def _rim_rim_points(mA, aA, RA, mB, aB, RB) -> np.ndarray:
    """Local minima of |P - Q| over P on circle A, Q on circle B: (N, K, 3)
    vectors P - Q (points of A - B whose direction is a candidate normal).
    For P fixed the nearest Q is closed form, leaving a 1D search in P's angle:
    64 samples, the 3 lowest sampled local minima refined by golden section.

    With P = mA + RA (cos e1 + sin e2), v = P - mB and its part vp
    perpendicular to aB are linear in (cos, sin), precomputed here; then
    P - Q = v - RB vp / |vp|.

    At a stationary point P - Q is perpendicular to both rim tangents, so the
    normal is also t_A x t_B: that direction hardly moves with an angle error
    dpsi, while the direction of P - Q moves by R dpsi / |P - Q| (large in a
    shallow contact).  Both are returned, so 26 golden steps suffice."""
    e1, e2 = _perp_basis(aA)
    f1, _ = _perp_basis(aB)
    V = np.stack([mA - mB, RA[:, None] * e1, RA[:, None] * e2], axis=1)  # (N, 3 coeffs, 3)
    Vp = V - _dot(V, aB[:, None, :])[..., None] * aB[:, None, :]

    def diff(psi):  # (N, M) -> (N, M, 3) P - Q
        c = np.cos(psi)[..., None]
        s = np.sin(psi)[..., None]
        v = V[:, None, 0] + c * V[:, None, 1] + s * V[:, None, 2]
        vp = Vp[:, None, 0] + c * Vp[:, None, 1] + s * Vp[:, None, 2]
        n = _norm(vp)[..., None]
        ok = n > 1e-300
        u = np.where(ok, vp / np.where(ok, n, 1.0), f1[:, None, :])  # P on B's axis: any Q
        return v - RB[:, None, None] * u

    def tangent_cross(psi):  # (N, M) -> (N, M, 3) t_A x t_B, or P - Q where parallel
        c = np.cos(psi)[..., None]
        s = np.sin(psi)[..., None]
        tA = -s * e1[:, None, :] + c * e2[:, None, :]
        vp = Vp[:, None, 0] + c * Vp[:, None, 1] + s * Vp[:, None, 2]
        tB = np.cross(aB[:, None, :], vp)
        x = np.cross(tA, tB)
        return np.where((_norm(x) > 1e-9 * _norm(vp))[..., None], x, diff(psi))

    K = _RIM_SAMPLES
    step = 2.0 * np.pi / K
    psi = np.broadcast_to(np.arange(K) * step, (mA.shape[0], K))
    g = _norm(diff(psi))
    locmin = (g <= np.roll(g, 1, axis=1)) & (g <= np.roll(g, -1, axis=1))
    gm = np.where(locmin, g, np.inf)
    L = min(_RIM_REFINE, K)
    sel = np.argpartition(gm, L - 1, axis=1)[:, :L]
    centre = sel * step
    _, arg = _golden(lambda x: _sq(diff(x)), centre - step, centre + step, _RIM_ITERS)
    return np.concatenate([diff(centre), diff(arg), tangent_cross(arg)], axis=1)


def _eval_candidates(A: Placed, B: Placed, d: np.ndarray, axes: list[np.ndarray],
                     points: list[np.ndarray]) -> np.ndarray:
    """min of phi over +-axes (unit, (N, 3) each) and +-directions of points."""
    fb = np.broadcast_to(np.array([0.0, 0.0, 1.0]), d.shape)
    dirs = [_unit_or(x, fb) for x in axes] + [_unit_or(p, fb) for p in points] + [_unit_or(d, fb)]
    n = np.stack(dirs, axis=1)
    n = np.concatenate([n, -n], axis=1)
    return _phi(A, B, d, n).min(axis=1)


def _search(A: Placed, B: Placed, cheap: Callable, expensive: Callable) -> np.ndarray:
    """s = min(cheap candidates); events not already certified separated
    (s <= 0 means a separating direction was found) get the expensive part."""
    out = np.empty(A.n)
    for lo in range(0, A.n, _CHUNK_SEARCH):
        a, b = A.take(slice(lo, lo + _CHUNK_SEARCH)), B.take(slice(lo, lo + _CHUNK_SEARCH))
        d = b.c - a.c
        s = cheap(a, b, d)
        todo = ~(s <= 0.0)  # NaN stays NaN either way
        if todo.any():
            a2, b2 = a.take(todo), b.take(todo)
            s[todo] = np.minimum(s[todo], expensive(a2, b2, b2.c - a2.c, s[todo]))
        out[lo:lo + a.n] = s
    return out


def _rims(Y: Placed) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The two rim circles of cylinders Y: (centre, axis, radius)."""
    a = Y.axis
    off = Y.half_length[:, None] * a
    return [(Y.c + off, a, Y.radius), (Y.c - off, a, Y.radius)]


def _box_vertices(Bx: Placed) -> list[np.ndarray]:
    out = []
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            for sz in (-1.0, 1.0):
                out.append(Bx.c + np.einsum("nij,nj->ni", Bx.R, np.array([sx, sy, sz]) * Bx.half_extents))
    return out


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
        s[todo] = np.minimum(s[todo], _phi(a, b, d, n).min(axis=1))
        return s

    return _search(A, B, cheap, expensive)


#: Signed-gap kernels keyed by (shape_a, shape_b) in SHAPES order.
PAIR_KERNELS: dict[tuple[str, str], Callable[[Placed, Placed], np.ndarray]] = {
    ("sphere", "sphere"): _k_sphere_sphere,
    ("sphere", "capsule"): _k_sphere_capsule,
    ("sphere", "box"): _k_sphere_box,
    ("sphere", "cylinder"): _k_sphere_cylinder,
    ("capsule", "capsule"): _k_capsule_capsule,
    ("capsule", "box"): _k_capsule_box,
    ("capsule", "cylinder"): _k_capsule_cylinder,
    ("box", "box"): _k_box_box,
    ("box", "cylinder"): _k_box_cylinder,
    ("cylinder", "cylinder"): _k_cylinder_cylinder,
}


def signed_gap(A: Placed, B: Placed) -> np.ndarray:
    """Signed overlap (m, (N,)) of two batches of placed shapes: > 0 is the
    penetration depth; <= 0 no overlap.  NaN where no kernel covers the pair."""
    if _ORDER[A.kind] > _ORDER[B.kind]:
        A, B = B, A
    fn = PAIR_KERNELS.get((A.kind, B.kind))
    if fn is None:
        return np.full(A.n, np.nan)
    out = np.empty(A.n)
    for lo in range(0, A.n, _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        out[sl] = fn(A.take(sl), B.take(sl)) if A.n > _CHUNK else fn(A, B)
    return out


def pair_depth(A: Placed, B: Placed) -> np.ndarray:
    """Penetration depth (m, (N,), >= 0; NaN where unknown)."""
    return np.maximum(0.0, signed_gap(A, B))


# ---- per-pair tables (frames of one pair; kept for callers and tests) -------------

def _body_pair_fn(ka: str, kb: str) -> Callable[..., np.ndarray]:
    def fn(a: Body, b: Body, pa, qa, pb, qb) -> np.ndarray:
        """Depth (m, (F,)) between bodies a and b at poses (F, 3)/(F, 4) each."""
        return pair_depth(_placed_body(a, np.atleast_2d(pa), np.atleast_2d(qa)),
                          _placed_body(b, np.atleast_2d(pb), np.atleast_2d(qb)))
    fn.__name__ = f"depth_{ka}_{kb}"
    return fn


def _body_static_box(b: Body, s: Static, pos, quat) -> np.ndarray:
    """Depth (m, (F,)) of body b at poses pos (F, 3), quat (F, 4) in static box s."""
    G = _placed_body(b, np.atleast_2d(pos), np.atleast_2d(quat))
    return pair_depth(G, _placed_static_box(s, G.n))


def depth_sphere_sphere(a: Body, b: Body, pa, qa, pb, qb) -> np.ndarray:
    d = np.linalg.norm(np.asarray(pb) - np.asarray(pa), axis=-1)
    return np.maximum(0.0, a.radius + b.radius - d)


BODY_PAIRS: dict[tuple[str, str], Callable[..., np.ndarray]] = {
    (ka, kb): _body_pair_fn(ka, kb) for ka in SHAPES for kb in SHAPES
}
BODY_PAIRS[("sphere", "sphere")] = depth_sphere_sphere
STATIC_PAIRS: dict[tuple[str, str], Callable[..., np.ndarray]] = {}
for _k in SHAPES:
    STATIC_PAIRS[(_k, "plane")] = depth_body_plane
    STATIC_PAIRS[(_k, "box")] = _body_static_box


# ---- the whole scene -------------------------------------------------------------

@dataclass
class Penetration:
    """Overlap depths of one trace, stored sparsely.

    ``pairs[p]`` names column p: (i, "static", s) for body i against static
    s (scene.statics index) or (i, "body", j) for bodies i < j.  Columns are
    the body-static pairs sorted by (i, s) -- every body against every plane,
    and against a static box if their bounding sphere reaches the box in some
    frame -- then the body-body pairs whose bounding spheres meet in some
    frame, sorted by (i, j).  Entries (``frames``, ``cols``, ``depths``) hold
    every non-zero depth (NaN where it is unknown); every other (frame,
    column) is 0.  ``bad`` (F, n) marks
    non-finite body poses: their columns are NaN in those frames.
    """

    n_frames: int
    pairs: list[tuple[int, str, int]]
    frames: np.ndarray
    cols: np.ndarray
    depths: np.ndarray
    bad: np.ndarray

    def _col_bodies(self) -> tuple[np.ndarray, np.ndarray]:
        a = np.array([p[0] for p in self.pairs], dtype=np.int64)
        b = np.array([p[2] if p[1] == "body" else -1 for p in self.pairs], dtype=np.int64)
        return a, b

    def dense(self) -> np.ndarray:
        """(F, P) depths (m)."""
        out = np.zeros((self.n_frames, len(self.pairs)))
        out[self.frames, self.cols] = self.depths
        if self.bad.any() and self.pairs:
            a, b = self._col_bodies()
            mask = self.bad[:, a] | (self.bad[:, np.maximum(b, 0)] & (b >= 0))
            out[mask] = np.nan
        return out

    def frame_max(self) -> np.ndarray:
        """(F,) deepest known overlap per frame (m); NaN entries are ignored
        (see :meth:`unknown`)."""
        out = np.zeros(self.n_frames)
        ok = ~np.isnan(self.depths)
        np.maximum.at(out, self.frames[ok], self.depths[ok])
        return out

    def unknown(self) -> np.ndarray:
        """(F,) frames where some depth is unknown: a NaN entry (a pair no
        kernel covers) or a non-finite body pose."""
        out = self.bad.any(axis=1) if self.bad.size else np.zeros(self.n_frames, bool)
        out[self.frames[np.isnan(self.depths)]] = True
        return out


class _BodyTable:
    """Per-body shape codes and dimensions as arrays."""

    def __init__(self, bodies: tuple[Body, ...]):
        n = len(bodies)
        self.kind = np.array([_ORDER.get(b.shape, -1) for b in bodies], dtype=np.int64)
        self.radius = np.array([b.radius for b in bodies], float)
        self.half_length = np.array([b.half_length for b in bodies], float)
        self.half_extents = np.zeros((n, 3))
        for i, b in enumerate(bodies):
            if b.half_extents is not None:
                self.half_extents[i] = b.half_extents
        self.rb = np.array([b.bounding_radius for b in bodies], float)

    def placed(self, kind: str, pos: np.ndarray, quat: np.ndarray, f: np.ndarray, i: np.ndarray) -> Placed:
        return Placed.from_pose(kind, pos[f, i], quat[f, i], self.radius[i], self.half_length[i],
                                self.half_extents[i])


class _Collector:
    def __init__(self):
        self.keys: list[np.ndarray] = []    # candidate pair keys
        self.ekeys: list[np.ndarray] = []   # entry keys
        self.frames: list[np.ndarray] = []
        self.depths: list[np.ndarray] = []

    def add(self, keys: np.ndarray, frames: np.ndarray, depth: np.ndarray) -> None:
        """Entries for events (keys, frames); all the keys become candidates."""
        if keys.size == 0:
            return
        self.keys.append(np.unique(keys))
        nz = depth != 0.0  # NaN != 0 is True: unknown depths are kept
        self.ekeys.append(keys[nz])
        self.frames.append(frames[nz])
        self.depths.append(depth[nz])

    def candidates(self) -> np.ndarray:
        return np.unique(np.concatenate(self.keys)) if self.keys else np.zeros(0, np.int64)


def _radius_classes(rb: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Bodies bucketed by bounding radius (factor-4 bands), each with its
    largest radius: a tree query per band pair then uses a radius that fits."""
    if rb.size == 0:
        return []
    rmin = max(float(rb.min()), 1e-12)
    band = np.floor(np.log(np.maximum(rb, rmin) / rmin) / np.log(4.0)).astype(np.int64)
    out = []
    for k in np.unique(band):
        idx = np.nonzero(band == k)[0]
        out.append((idx, float(rb[idx].max())))
    return out


_ALL_PAIRS_MAX = 4096  # all-pairs culling up to this many pairs, KD-trees above


def _body_events(pos: np.ndarray, bad: np.ndarray, rb: np.ndarray, f0: int, f1: int,
                 classes, allpairs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, i, j) with i < j whose bounding spheres meet, frames [f0, f1)."""
    if allpairs is not None:
        I, J = allpairs
        lim = (rb[I] + rb[J]) ** 2
        fs, ps = [], []
        step = max(1, (1 << 20) // max(1, I.size))
        for a in range(f0, f1, step):
            b = min(f1, a + step)
            dv = pos[a:b, J] - pos[a:b, I]
            ff, pp = np.nonzero(np.einsum("fpi,fpi->fp", dv, dv) <= lim)
            fs.append(ff + a)
            ps.append(pp)
        f = np.concatenate(fs)
        p = np.concatenate(ps)
        return f, I[p], J[p]
    from scipy.spatial import cKDTree

    fs, Is, Js = [], [], []
    any_bad = bad[f0:f1].any(axis=1)
    for f in range(f0, f1):
        P = pos[f]
        trees = []
        for idx, rmax in classes:
            sel = idx[~bad[f, idx]] if any_bad[f - f0] else idx
            if sel.size:
                trees.append((sel, cKDTree(P[sel], leafsize=16, balanced_tree=False, compact_nodes=False), rmax))
        for ka, (sa, ta, ra) in enumerate(trees):
            pr = ta.query_pairs(2.0 * ra, output_type="ndarray")
            if pr.size:
                Is.append(sa[pr[:, 0]])
                Js.append(sa[pr[:, 1]])
                fs.append(np.full(pr.shape[0], f))
            for sb, tb, rbb in trees[ka + 1:]:
                sm = ta.sparse_distance_matrix(tb, ra + rbb, output_type="ndarray")
                if sm.size:
                    Is.append(sa[sm["i"]])
                    Js.append(sb[sm["j"]])
                    fs.append(np.full(sm.shape[0], f))
    if not fs:
        e = np.zeros(0, np.int64)
        return e, e, e
    f = np.concatenate(fs)
    i = np.concatenate(Is)
    j = np.concatenate(Js)
    i, j = np.minimum(i, j), np.maximum(i, j)
    dv = pos[f, j] - pos[f, i]
    keep = np.einsum("ei,ei->e", dv, dv) <= (rb[i] + rb[j]) ** 2  # exact bounding-sphere test
    return f[keep], i[keep], j[keep]


def measure_penetration(scene: Scene, trace) -> Penetration:
    """Overlap depths (m) of every pair of shapes in every frame of ``trace``
    (pos (F, n, 3), quat (F, n, 4) wxyz), sparse.  See the module docstring."""
    pos = np.asarray(trace.pos, float)
    quat = np.asarray(trace.quat, float)
    F = pos.shape[0]
    bodies = scene.bodies
    n = len(bodies)
    statics = scene.statics
    ns = max(1, len(statics))
    tab = _BodyTable(bodies)
    bad = ~(np.isfinite(pos).all(axis=-1) & np.isfinite(quat).all(axis=-1)) if n else np.zeros((F, 0), bool)
    st = _Collector()  # keys i * ns + s
    bb = _Collector()  # keys i * n + j
    groups = [(k, np.nonzero(tab.kind == c)[0]) for c, k in enumerate(SHAPES)]
    groups = [(k, idx) for k, idx in groups if idx.size]
    unknown_shape = np.nonzero(tab.kind < 0)[0]

    allpairs = None
    classes = None
    if n > 1:
        npairs = n * (n - 1) // 2
        if npairs <= _ALL_PAIRS_MAX:
            allpairs = np.triu_indices(n, 1)
            allpairs = (allpairs[0].astype(np.int64), allpairs[1].astype(np.int64))
        else:
            classes = _radius_classes(tab.rb)

    block = max(1, 65536 // max(1, n))
    for f0 in range(0, F, block):
        f1 = min(F, f0 + block)
        fr = np.arange(f0, f1)
        # -- statics
        for s in statics:
            if s.shape == "plane":
                for kind, idx in groups:
                    ff = np.repeat(fr, idx.size)
                    ii = np.tile(idx, fr.size)
                    G = tab.placed(kind, pos, quat, ff, ii)
                    depth = np.maximum(0.0, plane_gap(G, s.normal, s.offset))
                    st.add(ii * ns + s.index, ff, depth)
                if unknown_shape.size:
                    ff = np.repeat(fr, unknown_shape.size)
                    ii = np.tile(unknown_shape, fr.size)
                    st.add(ii * ns + s.index, ff, np.full(ff.size, np.nan))
            elif s.shape == "box":
                # cull: a body's bounding sphere must reach the box itself
                q = (pos[f0:f1] - np.asarray(s.position, float)) @ _static_rotation(s)  # box frame
                e = np.asarray(s.half_extents, float)
                dq = q - np.clip(q, -e, e)
                ff, ii = np.nonzero(np.einsum("fni,fni->fn", dq, dq) <= tab.rb[None, :] ** 2)
                ff = ff + f0
                for kind, idx in groups:
                    m = np.isin(ii, idx)
                    if m.any():
                        G = tab.placed(kind, pos, quat, ff[m], ii[m])
                        st.add(ii[m] * ns + s.index, ff[m], pair_depth(G, _placed_static_box(s, G.n)))
                m = np.isin(ii, unknown_shape)
                if m.any():
                    st.add(ii[m] * ns + s.index, ff[m], np.full(int(m.sum()), np.nan))
            else:  # a static shape this module does not know: unknown, not zero
                ff = np.repeat(fr, n)
                ii = np.tile(np.arange(n), fr.size)
                st.add(ii * ns + s.index, ff, np.full(ff.size, np.nan))
        # -- bodies
        if n > 1:
            ef, ei, ej = _body_events(pos, bad, tab.rb, f0, f1, classes, allpairs)
            if ef.size:
                ki, kj = tab.kind[ei], tab.kind[ej]
                swap = ki > kj
                lo_i = np.where(swap, ej, ei)  # lower shape code first
                hi_i = np.where(swap, ei, ej)
                klo, khi = np.minimum(ki, kj), np.maximum(ki, kj)
                code = klo * 8 + khi
                for c in np.unique(code):
                    m = code == c
                    a_kind, b_kind = int(c) // 8, int(c) % 8
                    keys = ei[m] * n + ej[m]
                    if a_kind < 0 or b_kind < 0 or (SHAPES[a_kind], SHAPES[b_kind]) not in PAIR_KERNELS:
                        bb.add(keys, ef[m], np.full(int(m.sum()), np.nan))
                        continue
                    A = tab.placed(SHAPES[a_kind], pos, quat, ef[m], lo_i[m])
                    B = tab.placed(SHAPES[b_kind], pos, quat, ef[m], hi_i[m])
                    bb.add(keys, ef[m], pair_depth(A, B))

    skeys = st.candidates()
    bkeys = bb.candidates()
    pairs = [(int(k // ns), "static", int(k % ns)) for k in skeys] + [
        (int(k // n), "body", int(k % n)) for k in bkeys]
    frames, cols, depths = [], [], []
    for coll, keys, off in ((st, skeys, 0), (bb, bkeys, skeys.size)):
        if coll.ekeys:
            ek = np.concatenate(coll.ekeys)
            cols.append(np.searchsorted(keys, ek) + off)
            frames.append(np.concatenate(coll.frames))
            depths.append(np.concatenate(coll.depths))
    cat = (lambda xs, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(0, dt))
    return Penetration(F, pairs, cat(frames, np.int64), cat(cols, np.int64), cat(depths, float), bad)


def penetration_depths(scene: Scene, trace) -> np.ndarray:
    """Overlap depth (m) per frame and candidate pair: array (F, P).

    Columns: body-static pairs by (body, static), then body-body pairs by
    (i, j); pairs that never come within bounding-sphere reach have no column
    (see :class:`Penetration`).  A pair no kernel covers, or a non-finite
    pose, gives NaN (ignored by nan-aware reductions) rather than a silent
    zero.
    """
    return measure_penetration(scene, trace).dense()


def max_depth_per_frame(scene: Scene, trace) -> np.ndarray:
    """(F,) deepest overlap (m) in each frame without building the (F, P)
    matrix; unknown (NaN) depths are ignored (``measure_penetration(...)
    .unknown()`` says where)."""
    return measure_penetration(scene, trace).frame_max()
