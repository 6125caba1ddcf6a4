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


#: below this many bodies ``sap`` tests all pairs instead: the same pairs in
#: the same order, with fewer numpy calls (the sweep's sorting and
#: bookkeeping only pays for more bodies)
SAP_MIN_BODIES = 16


def shape_groups(model) -> tuple:
    """Index arrays of the bodies by extent rule (spheres, boxes, capsules
    and cylinders), computed once per model."""
    s = model.shape
    rnd = np.flatnonzero((s == CAPSULE) | (s == CYLINDER))
    return (np.flatnonzero(s == SPHERE), np.flatnonzero(s == BOX), rnd, s[rnd] == CAPSULE)


def body_extents(model, R: np.ndarray, groups: tuple | None = None) -> np.ndarray:
    """Half-sizes (n, 3) of each body's world axis-aligned box at rotations R
    (``groups``: :func:`shape_groups`, computed here when not given)."""
    n = model.n
    sph, box, rnd, is_cap = shape_groups(model) if groups is None else groups
    ext = np.empty((n, 3))
    if sph.size:
        ext[sph] = model.radius[sph, None]
    if box.size:
        ext[box] = np.einsum("kij,kj->ki", np.abs(R[box]), model.half_extents[box])
    if rnd.size:
        ax = R[rnd][:, :, 2]
        r = model.radius[rnd, None]
        hl = model.half_length[rnd, None]
        cap = np.abs(ax) * hl + r
        cyl = np.abs(ax) * hl + r * np.sqrt(np.clip(1.0 - ax * ax, 0.0, 1.0))
        ext[rnd] = np.where(is_cap[:, None], cap, cyl)
    return ext


def sap_pairs(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sweep and prune over boxes [lo, hi] (n, 3): overlapping pairs (i < j),
    sorted lexicographically.

    Candidates are the pairs whose intervals overlap on the sweep axis (in
    sorted order, box q after box p with lo_q <= hi_p); they are then
    filtered one axis at a time on contiguous per-axis columns, each axis
    only on the survivors of the previous one (the same pairs as testing
    all three axes at once, with far fewer gathers when a sweep slab holds
    many boxes)."""
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
    # the sweep axis: lo_p <= lo_q (sorted) <= hi_q, and lo_q <= hi_p (searchsorted)
    ok_sweep = (slo[P] <= shi[Q]) & (slo[Q] <= shi[P])
    if not ok_sweep.all():  # only with degenerate (lo > hi or NaN) boxes
        P, Q = P[ok_sweep], Q[ok_sweep]
    for ax in range(3):
        if ax == axis or P.size == 0:
            continue
        la = lo[order, ax]
        ha = hi[order, ax]
        ok = (la[P] <= ha[Q]) & (la[Q] <= ha[P])
        P, Q = P[ok], Q[ok]
    i = order[P]
    j = order[Q]
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
        self.groups = shape_groups(model)

    def __call__(self, model, state, ctx) -> None:
        if ctx.reuse_contacts:
            return
        n = model.n
        h = ctx.h
        e0 = body_extents(model, ctx.R0, self.groups)
        R1 = quat_to_matrix(ctx.q1)
        e1 = body_extents(model, R1, self.groups)
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
            if self.method == "sap" and n > SAP_MIN_BODIES:
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
