"""The support-function search for pairs with a cylinder: s = min of phi over
a candidate set of normals that contains the minimiser -- fixed axes, closest
points of ridges, rim-rim local minima and great circles of normals (the
method and its measured accuracy are in contract/geometry/__init__.py).  The
kernels that use it are in contract/geometry/cylinder.py."""

from __future__ import annotations

from typing import Callable

import numpy as np

from physbench.contract.geometry.placed import Placed
from physbench.contract.geometry.support import projection_overlap
from physbench.contract.geometry.vector import _dot, _golden, _norm, _perp_basis, _sq, _unit_or

_CIRCLE_SAMPLES = 72  # samples on a great circle of normals (5 degrees apart)
_CIRCLE_REFINE = 3    # lowest sampled local minima refined per circle
_RIM_SAMPLES = 64     # samples along a rim for the circle-circle search
_RIM_REFINE = 3
_REFINE_ITERS = 26    # golden steps on a great circle's 2-sample bracket: 6e-7 rad
_RIM_ITERS = 26       # golden steps on a rim's 2-sample bracket: 8e-7 rad
_CHUNK_SEARCH = 4096  # events per call for the support-function search


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
    return projection_overlap(A, B, d, n).min(axis=1)


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

