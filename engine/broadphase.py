"""Broad phase: which pairs may touch during this step.

Each body gets an axis-aligned box swept over the step (the union of its
boxes at the start pose and at the free-flight end pose), grown by the
contact margin.  Candidate body-body pairs come from sweep-and-prune
(``broadphase = sap``: sort the boxes' lower bounds along the axis of
largest spread, every box overlaps the boxes whose lower bound lies before
its upper bound, then test the two other axes) or from testing every pair
(``brute``).  Body-plane pairs are candidates when the swept box reaches the
plane's margin; body-static-box pairs when the boxes overlap.

Also computes ``ctx.sweep`` (n,): a bound on how far any surface point of a
body moves in the step, h (max speed + max angular speed * bounding radius),
which sizes the narrow phase's speculative margin and decides which bodies
are "fast" for CCD.

Outputs (all sorted, so that the contact order -- and the result -- is
deterministic): ``ctx.pairs_i``/``pairs_j`` (i < j), ``ctx.plane_pairs``
(body, plane row), ``ctx.sbox_pairs`` (body, static-box row).
"""

from __future__ import annotations

import numpy as np

from engine.mathutil import quat_to_matrix
from engine.model import BOX, CAPSULE, CYLINDER, SPHERE
from engine.profile import Stage


def body_extents(model, R: np.ndarray) -> np.ndarray:
    """Half-sizes (n, 3) of each body's world axis-aligned box at rotations R."""
    n = model.n
    ext = np.empty((n, 3))
    s = model.shape
    m = s == SPHERE
    if m.any():
        ext[m] = model.radius[m, None]
    m = s == BOX
    if m.any():
        ext[m] = np.einsum("kij,kj->ki", np.abs(R[m]), model.half_extents[m])
    m = (s == CAPSULE) | (s == CYLINDER)
    if m.any():
        ax = R[m][:, :, 2]
        r = model.radius[m, None]
        hl = model.half_length[m, None]
        cap = np.abs(ax) * hl + r
        cyl = np.abs(ax) * hl + r * np.sqrt(np.clip(1.0 - ax * ax, 0.0, 1.0))
        ext[m] = np.where((s[m] == CAPSULE)[:, None], cap, cyl)
    return ext


def sap_pairs(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sweep and prune over boxes [lo, hi] (n, 3): overlapping pairs (i < j),
    sorted lexicographically."""
    n = lo.shape[0]
    if n < 2:
        z = np.zeros(0, np.int64)
        return z, z
    centre = 0.5 * (lo + hi)
    axis = int(np.argmax(centre.var(axis=0)))
    order = np.argsort(lo[:, axis], kind="stable")
    slo = lo[order, axis]
    shi = hi[order, axis]
    end = np.searchsorted(slo, shi, side="right")
    cnt = np.maximum(end - np.arange(1, n + 1), 0)
    total = int(cnt.sum())
    if total == 0:
        z = np.zeros(0, np.int64)
        return z, z
    P = np.repeat(np.arange(n), cnt)
    starts = np.cumsum(cnt) - cnt
    Q = P + 1 + (np.arange(total) - np.repeat(starts, cnt))
    i = order[P]
    j = order[Q]
    ok = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    i, j = i[ok], j[ok]
    a, b = np.minimum(i, j), np.maximum(i, j)
    srt = np.lexsort((b, a))
    return a[srt], b[srt]


def brute_pairs(model, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (precomputed, i < j, sorted) whose boxes overlap."""
    i, j = model.pair_i, model.pair_j
    ok = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    return i[ok], j[ok]


class BroadPhase(Stage):
    """Swept-box broad phase (see module doc)."""

    name = "broadphase"
    family = "broadphase"

    def __init__(self, model):
        self.method = model.setting("broadphase")
        self.margin = float(model.setting("contact_margin"))
        self.n_planes = model.plane_normal.shape[0]
        self.n_sbox = model.sbox_pos.shape[0]

    def __call__(self, model, state, ctx) -> None:
        if ctx.reuse_contacts:
            return
        n = model.n
        h = ctx.h
        e0 = body_extents(model, ctx.R0)
        R1 = quat_to_matrix(ctx.q1)
        e1 = body_extents(model, R1)
        vmax = np.sqrt(np.maximum(np.einsum("ki,ki->k", state.v, state.v),
                                  np.einsum("ki,ki->k", ctx.v[:n], ctx.v[:n])))
        umax = np.sqrt(np.einsum("ki,ki->k", ctx.u_lin, ctx.u_lin))
        wmax = np.sqrt(np.maximum(np.einsum("ki,ki->k", state.w, state.w),
                                  np.einsum("ki,ki->k", ctx.w[:n], ctx.w[:n])))
        ctx.sweep[:] = h * (np.maximum(vmax, umax) + wmax * model.bound_radius)
        grow = self.margin
        lo = np.minimum(state.x - e0, ctx.x1 - e1) - grow
        hi = np.maximum(state.x + e0, ctx.x1 + e1) + grow
        if n >= 2:
            if self.method == "sap":
                ctx.pairs_i, ctx.pairs_j = sap_pairs(lo, hi)
            else:
                ctx.pairs_i, ctx.pairs_j = brute_pairs(model, lo, hi)
        if self.n_planes:
            # lowest point of each swept box along each plane normal
            c = 0.5 * (lo + hi)
            ex = 0.5 * (hi - lo)
            N = model.plane_normal
            low = c @ N.T - ex @ np.abs(N).T - model.plane_offset[None, :]  # (n, planes)
            bi, pk = np.nonzero(low < grow)
            ctx.plane_pairs = (bi, pk)
        else:
            ctx.plane_pairs = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        if self.n_sbox:
            ok = np.all((lo[:, None, :] <= model.sbox_aabb_hi[None]) & (model.sbox_aabb_lo[None] <= hi[:, None, :]), axis=2)
            bi, sk = np.nonzero(ok)
            ctx.sbox_pairs = (bi, sk)
        else:
            ctx.sbox_pairs = (np.zeros(0, np.int64), np.zeros(0, np.int64))
