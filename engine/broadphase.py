"""Broad phase: which pairs may touch during this step.

Each body gets an axis-aligned box swept over the step (the union of its
boxes at the start pose and at the free-flight end pose), grown by the
contact margin.  Candidate body-body pairs come from sweep-and-prune
(``broadphase = sap``: sort the boxes' lower bounds along the axis of
largest spread, every box overlaps the boxes whose lower bound lies before
its upper bound, then test the two other axes; when that gives many
candidates per box -- dense 3D clouds -- the same sweep within the cells of
a 2D grid over the two other axes, see :func:`sap_pairs`: O(n log n)) or
from testing every pair (``brute``); both give exactly the same pairs in
the same order.  Body-plane pairs are candidates when the swept box
reaches the plane's margin; body-static-box pairs when the boxes overlap.

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


_EMPTY = np.zeros(0, np.int64)

#: on each grid axis, boxes wider than this many times the median width (at
#: most about sqrt(n) of them: the threshold is raised to the sqrt(n)-th
#: largest width) are "special": tested against all boxes, not gridded
_BIG_FACTOR = 4.0
#: the single-axis sweep's candidates are used when at most this many per
#: box; beyond, the sweep runs within grid cells
_SWEEP_ONLY = 32
#: grid cells are this many times as wide as the widest (gridded) box
_CELL_SCALE = 1.0
#: cells per grid axis at most (bounds the integer cell coordinates)
_MAX_CELLS = 1 << 20
#: box comparisons per chunk of the special boxes' all-boxes test
_CHUNK = 1 << 20


def _sweep_axis(lo: np.ndarray, hi: np.ndarray) -> int:
    """Axis of largest spread of the box centres."""
    with np.errstate(invalid="ignore", over="ignore"):
        return int(np.argmax((0.5 * lo + 0.5 * hi).var(axis=0)))


def _sap_single_axis(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The former ``sap_pairs``: single-axis sweep and prune (same output as
    :func:`sap_pairs`; kept for the broad-phase benchmark).

    Candidates are the pairs whose intervals overlap on the sweep axis (in
    sorted order, box q after box p with lo_q <= hi_p); they are then
    filtered one axis at a time.  In a dense 3D cloud a slab of the sweep
    axis holds ~n^(2/3) boxes, so the candidates grow like n^(5/3)."""
    n = lo.shape[0]
    if n < 2:
        return _EMPTY, _EMPTY
    axis = _sweep_axis(lo, hi)
    order = np.argsort(lo[:, axis], kind="stable")
    slo = lo[order, axis]
    shi = hi[order, axis]
    end = np.searchsorted(slo, shi, side="right")
    cnt = np.maximum(end - np.arange(1, n + 1), 0)
    total = int(cnt.sum())
    if total == 0:
        return _EMPTY, _EMPTY
    P = np.repeat(np.arange(n), cnt)
    starts = np.cumsum(cnt) - cnt
    Q = P + 1 + (np.arange(total) - np.repeat(starts, cnt))
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


def _special_pairs(lo: np.ndarray, hi: np.ndarray, spec: np.ndarray,
                   is_spec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping pairs (i < j, unsorted) with at least one special box:
    each special box tested against every box (a special-special pair once)."""
    n = lo.shape[0]
    out_a, out_b = [_EMPTY], [_EMPTY]
    step = max(1, _CHUNK // n)
    js = np.arange(n)
    for k in range(0, spec.size, step):
        s = spec[k:k + step]
        ok = np.all((lo[s, None, :] <= hi[None, :, :]) & (lo[None, :, :] <= hi[s, None, :]), axis=2)
        ok &= ~is_spec[None, :] | (js[None, :] > s[:, None])
        r, j = np.nonzero(ok)
        i = s[r]
        out_a.append(np.minimum(i, j))
        out_b.append(np.maximum(i, j))
    return np.concatenate(out_a), np.concatenate(out_b)


def _cells(lo: np.ndarray, hi: np.ndarray, max_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """First and last cell coordinate (int64) of intervals [lo, hi] on a
    grid of cells ``_CELL_SCALE`` times as wide as the widest interval (at
    most ``max_cells`` cells).  floor((x - min) / c) is monotone in x in
    floating point too, so overlapping intervals always share a cell."""
    mn = lo.min()
    span = hi.max() - mn
    c = max(_CELL_SCALE * float((hi - lo).max()), span / max_cells)
    if not (np.isfinite(c) and np.isfinite(span)) or c <= 0.0:
        z = np.zeros(lo.shape[0], np.int64)
        return z, z
    return (np.floor((lo - mn) / c).astype(np.int64),
            np.floor((hi - mn) / c).astype(np.int64))


def sap_pairs(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sweep and prune over boxes [lo, hi] (n, 3): overlapping pairs (i < j;
    lo_i <= hi_j and lo_j <= hi_i on all three axes), sorted
    lexicographically -- exactly :func:`brute_pairs`' pairs, for any input
    (a row with a NaN overlaps nothing, as there).

    The boxes' lower bounds are sorted along the axis of largest spread
    (the sweep axis); the pairs overlapping on it are those of box p with
    the later boxes q whose lower bound is <= p's upper bound.  When these
    are few (at most ``_SWEEP_ONLY`` per box: sparse or planar layouts,
    small n) they are the candidates, tested on the two other axes.  In a
    dense 3D cloud they grow like n^(5/3) (a slab of the sweep axis holds
    ~n^(2/3) boxes), so instead the sweep runs within the cells of a 2D grid
    over the two other axes (:func:`_grid_pairs`), whose candidates grow
    like n:

    * cells are as wide as the widest box on each grid axis; boxes much
      wider than the median (see ``_BIG_FACTOR``; at most ~sqrt(n) per
      axis), and boxes with lo > hi or an infinite bound (any n), are
      instead tested against all boxes (:func:`_special_pairs`);
    * every other box is entered in each cell it covers (at most 2 x 2:
      four runs, each already in order, merged by one stable sort); the
      entries are sorted by the integer key cell * (m + 1) + rank of the
      lower bound on the sweep axis (times 4, plus two bits: is the cell
      the box's first on each grid axis), and each entry's candidates --
      the later entries of its cell whose lower bound is <= its upper
      bound -- are found by one searchsorted of cell * (m + 1) + number of
      lower bounds <= its upper bound (exact: integer keys, no
      floating-point combination);
    * a candidate is kept only in the cell holding the lower corner of the
      two boxes' intersection (so once, though they may share up to four
      cells), then tested on the two grid axes.

    Cost O(n log n) for boxes of similar sizes, whatever the layout."""
    n = lo.shape[0]
    if n < 2:
        return _EMPTY, _EMPTY
    with np.errstate(invalid="ignore", over="ignore"):
        w = hi - lo
        # finite bounds and lo <= hi (False for any NaN or infinite bound)
        good = ((w >= 0.0) & (w < np.inf)).all(axis=1)
    all_good = bool(good.all())
    if all_good:
        i, j, big = _finite_pairs(lo, hi, w)
        if big is None:
            return _sorted_pairs([i], [j], n)
        gi = np.arange(n)
    else:
        gi = np.flatnonzero(good)
        i, j, big = _finite_pairs(lo[gi], hi[gi], w[gi])
        i, j = gi[i], gi[j]
    pa, pb = [i], [j]
    if big is not None:
        good[gi[big]] = False
    nan = np.isnan(lo).any(axis=1) | np.isnan(hi).any(axis=1)
    spec = np.flatnonzero(~nan & ~good)
    if spec.size:
        i, j = _special_pairs(lo, hi, spec, ~good)  # NaN rows overlap nothing anyway
        pa.append(i)
        pb.append(j)
    return _sorted_pairs(pa, pb, n)


def _sorted_pairs(pa: list, pb: list, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated pairs (i < j, each once) in lexicographic order."""
    code = pa[0] * n + pb[0] if len(pa) == 1 else np.concatenate(pa) * n + np.concatenate(pb)
    code.sort()
    return code // n, code % n


def _finite_pairs(lo: np.ndarray, hi: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Overlapping pairs (i < j, unsorted) of finite boxes with lo <= hi
    (widths w): by a single-axis sweep when it has few candidates, else by
    :func:`_grid_pairs`.  The third result is None, or the mask of the
    boxes left out of the grid (too wide: the caller tests them against
    all boxes)."""
    m = lo.shape[0]
    if m < 2:
        return _EMPTY, _EMPTY, None
    axis = _sweep_axis(lo, hi)
    order = np.argsort(lo[:, axis], kind="stable")
    slo = lo[order, axis]
    end = np.searchsorted(slo, hi[order, axis], side="right")
    cnt = end - np.arange(1, m + 1)  # >= 0: lo <= hi
    total = int(cnt.sum())
    if total <= _SWEEP_ONLY * m:
        if total == 0:
            return _EMPTY, _EMPTY, None
        P = np.repeat(np.arange(m), cnt)
        Q = np.arange(total) + np.repeat(np.arange(1, m + 1) - (np.cumsum(cnt) - cnt), cnt)
        # the sweep axis holds (lo_p <= lo_q <= hi_q, lo_q <= hi_p); the
        # others one at a time, each on the survivors of the previous one
        for a in range(3):
            if a == axis:
                continue
            la = lo[order, a]
            ha = hi[order, a]
            ok = (la[P] <= ha[Q]) & (la[Q] <= ha[P])
            P, Q = P[ok], Q[ok]
        i, j = order[P], order[Q]
        return np.minimum(i, j), np.maximum(i, j), None
    u, v = [a for a in range(3) if a != axis]
    wuv = w[:, (u, v)]
    mid = m // 2
    top = max(m - 1 - int(np.ceil(np.sqrt(m))), mid)
    part = np.partition(wuv, (mid, top), axis=0)
    thr = np.maximum(_BIG_FACTOR * part[mid], part[top])
    big = (wuv > thr).any(axis=1)
    if not big.any():
        i, j = _grid_pairs(lo, hi, axis, u, v, order, end)
        return i, j, None
    keep = np.flatnonzero(~big)
    i, j = _grid_pairs(lo[keep], hi[keep], axis, u, v)
    return keep[i], keep[j], big


def _grid_pairs(lo: np.ndarray, hi: np.ndarray, axis: int, u: int, v: int,
                order: np.ndarray | None = None,
                end: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping pairs (i < j, unsorted) of finite boxes with lo <= hi,
    by sweep and prune along ``axis`` within the cells of a grid on axes
    u, v (see :func:`sap_pairs`); ``order`` (stable argsort of the lower
    bounds on ``axis``) and ``end`` (for each box in that order, the number
    of lower bounds <= its upper bound) when already known."""
    m = lo.shape[0]
    if m < 2:
        return _EMPTY, _EMPTY
    if order is None:
        order = np.argsort(lo[:, axis], kind="stable")
        end = np.searchsorted(lo[order, axis], hi[order, axis], side="right")
    # keys below: (cell * (m + 1) + rank) * 4 + 2 bits, < 2^63
    max_cells = min(_MAX_CELLS, int(np.sqrt(2.0 ** 60 / (m + 1))))
    u0, u1 = _cells(lo[order, u], hi[order, u], max_cells)  # in sweep order: index = rank
    v0, v1 = _cells(lo[order, v], hi[order, v], max_cells)
    nv = int(v1.max()) + 1
    du = u1 - u0
    dv = v1 - v0
    M = m + 1
    # an entry per box and cell it covers, as the key
    # ((cell * M + rank of the box's lower bound on the sweep axis) << 2) | loc,
    # loc's bit 0 set when the cell is not the box's first on v, bit 1 on u;
    # lo_q <= hi_p  <=>  rank_q < end_p  (end_p: lower bounds <= hi_p)
    k0 = (u0 * nv + v0) * M + np.arange(m)
    if int(du.max()) <= 1 and int(dv.max()) <= 1:  # 2 x 2 cells at most (always, but for rounding)
        # four runs, each sorted by (cell, rank) when the first one is:
        # sorting their concatenation (timsort) merges them
        k0.sort(kind="stable")
        r = k0 % M
        has_v, has_u = dv[r] == 1, du[r] == 1
        key = np.concatenate((k0 << 2,
                              ((k0[has_v] + M) << 2) | 1,
                              ((k0[has_u] + nv * M) << 2) | 2,
                              ((k0[has_u & has_v] + (nv + 1) * M) << 2) | 3))
        key.sort(kind="stable")
    else:
        cnt = (du + 1) * (dv + 1)
        rep = np.repeat(np.arange(m), cnt)
        t = np.arange(rep.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        dve = dv[rep] + 1
        tu, tv = t // dve, t % dve
        loc = (tu > 0).astype(np.int64) << 1 | (tv > 0)
        key = np.sort(((k0[rep] + (tu * nv + tv) * M) << 2) | loc)
    kr = key >> 2
    rank = kr % M
    E = key.size
    # candidates of entry p: the later entries of its cell with rank < end
    last = np.searchsorted(key, (kr - rank + end[rank]) << 2, side="left")
    c = last - np.arange(1, E + 1)  # >= 0: a box's own rank < its end
    total = int(c.sum())
    if total == 0:
        return _EMPTY, _EMPTY
    P = np.repeat(np.arange(E), c)
    Q = np.arange(total) + np.repeat(np.arange(1, E + 1) - (np.cumsum(c) - c), c)
    # once per pair: in the cell of the lower corner of the boxes'
    # intersection, i.e. on each grid axis the cell is the first of one of
    # the two boxes (both cover the cells from their first one on)
    loc = (key & 3).astype(np.int8)
    ok = (loc[P] & loc[Q]) == 0
    i, j = rank[P[ok]], rank[Q[ok]]
    # the sweep axis holds by construction (lo_p <= lo_q <= hi_q, lo_q <= hi_p);
    # the grid axes one at a time, each on the survivors of the previous one
    for a in (u, v):
        la, ha = lo[order, a], hi[order, a]
        ok = (la[i] <= ha[j]) & (la[j] <= ha[i])
        i, j = i[ok], j[ok]
    i, j = order[i], order[j]
    return np.minimum(i, j), np.maximum(i, j)


def brute_pairs(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i < j, sorted) whose boxes [lo, hi] (n, 3) overlap, by
    testing all n (n - 1) / 2 of them."""
    i, j = np.triu_indices(lo.shape[0], 1)
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
                ctx.pairs_i, ctx.pairs_j = brute_pairs(lo, hi)
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
