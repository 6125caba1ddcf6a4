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
The stage is one compiled call per step (numba ``@njit(cache=True)``, no
BLAS; :func:`_broad_step`): the swept boxes, the pairs -- sweep and prune
along a sort order kept between steps and restored by insertion sort
(:func:`_sap_coherent`; dense clouds through a uniform grid, :func:`_hash_grid_pairs`;
non-finite or very unequal boxes fall back to :func:`sap_pairs`) or the all-pairs test -- and the static pairs, into
buffers kept between steps and grown geometrically.

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
from numba import njit

from engine.flight import q2m
from engine.model import BOX, CAPSULE, CYLINDER, SPHERE
from engine.profile import Stage


#: below this many bodies ``sap`` tests all pairs instead: the same pairs in
#: the same order, with fewer numpy calls (the sweep's sorting and
#: bookkeeping only pays for more bodies)
SAP_MIN_BODIES = 16


@njit(cache=True)
def _extent(shape, r, half, hl, R, e):
    """Half-sizes e (3,) of a body's world axis-aligned box at rotation R."""
    for i in range(3):
        if shape == SPHERE:
            e[i] = r
        elif shape == BOX:
            e[i] = abs(R[i, 0]) * half[0] + abs(R[i, 1]) * half[1] + abs(R[i, 2]) * half[2]
        elif shape == CAPSULE:
            e[i] = abs(R[i, 2]) * hl + r
        else:  # cylinder: the caps' discs
            e[i] = abs(R[i, 2]) * hl + r * np.sqrt(min(max(1.0 - R[i, 2] * R[i, 2], 0.0), 1.0))


@njit(cache=True)
def _swept_boxes(shape, radius, half, half_length, bound_radius, x0, R0, x1, R1, v0, v1, u, w0, w1, h, grow,
                 lo, hi, sweep):
    """Per body: the union of its boxes at the start (x0, R0) and the
    free-flight end pose (x1, R1), grown by ``grow``, into lo, hi (n, 3);
    and ``sweep`` (n,): h (max speed + max angular speed * bounding radius)
    over the start (v0, w0) and end (v1, w1) velocities and the mean
    velocity u (all (>= n, 3))."""
    e0 = np.empty(3)
    e1 = np.empty(3)
    for k in range(x0.shape[0]):
        _extent(shape[k], radius[k], half[k], half_length[k], R0[k], e0)
        _extent(shape[k], radius[k], half[k], half_length[k], R1[k], e1)
        for i in range(3):
            lo[k, i] = min(x0[k, i] - e0[i], x1[k, i] - e1[i]) - grow
            hi[k, i] = max(x0[k, i] + e0[i], x1[k, i] + e1[i]) + grow
        vmax = np.sqrt(max(v0[k, 0] * v0[k, 0] + v0[k, 1] * v0[k, 1] + v0[k, 2] * v0[k, 2],
                           v1[k, 0] * v1[k, 0] + v1[k, 1] * v1[k, 1] + v1[k, 2] * v1[k, 2]))
        umax = np.sqrt(u[k, 0] * u[k, 0] + u[k, 1] * u[k, 1] + u[k, 2] * u[k, 2])
        wmax = np.sqrt(max(w0[k, 0] * w0[k, 0] + w0[k, 1] * w0[k, 1] + w0[k, 2] * w0[k, 2],
                           w1[k, 0] * w1[k, 0] + w1[k, 1] * w1[k, 1] + w1[k, 2] * w1[k, 2]))
        sweep[k] = h * (max(vmax, umax) + wmax * bound_radius[k])


def body_extents(model, R: np.ndarray) -> np.ndarray:
    """Half-sizes (n, 3) of each body's world axis-aligned box at rotations
    R (n, 3, 3)."""
    n = model.n
    ext = np.empty((n, 3))
    e = np.empty(3)
    for k in range(n):
        _extent(model.shape[k], model.radius[k], model.half_extents[k], model.half_length[k], R[k], e)
        ext[k] = e
    return ext


@njit(cache=True)
def _emit(out_a, out_b, cnt, a, b):
    """Write the pair (a, b) at cnt when the outputs have room (the kernels
    count on, to report what they need); returns cnt + 1."""
    if cnt < out_a.shape[0]:
        out_a[cnt] = a
        out_b[cnt] = b
    return cnt + 1


@njit(cache=True)
def _plane_pairs_kernel(lo, hi, N, off, grow, out_b, out_p):
    """(body, plane) pairs, body-major, whose box [lo, hi] reaches within
    ``grow`` of the plane (unit normal N[p], offset off[p]): the box's
    lowest point along N, c . N - e . |N| - off < grow.  Returns the
    number written, or minus the number needed when the outputs are short."""
    cnt = 0
    for k in range(lo.shape[0]):
        c0, c1, c2 = 0.5 * (lo[k, 0] + hi[k, 0]), 0.5 * (lo[k, 1] + hi[k, 1]), 0.5 * (lo[k, 2] + hi[k, 2])
        e0, e1, e2 = 0.5 * (hi[k, 0] - lo[k, 0]), 0.5 * (hi[k, 1] - lo[k, 1]), 0.5 * (hi[k, 2] - lo[k, 2])
        for p in range(N.shape[0]):
            low = (c0 * N[p, 0] + c1 * N[p, 1] + c2 * N[p, 2]
                   - (e0 * abs(N[p, 0]) + e1 * abs(N[p, 1]) + e2 * abs(N[p, 2])) - off[p])
            if low < grow:
                cnt = _emit(out_b, out_p, cnt, k, p)
    return cnt if cnt <= out_b.shape[0] else -cnt


@njit(cache=True)
def _box_pairs_kernel(lo, hi, slo, shi, out_b, out_p):
    """(body, static box) pairs, body-major, whose boxes overlap (see
    :func:`_plane_pairs_kernel` for the return value)."""
    cnt = 0
    for k in range(lo.shape[0]):
        for p in range(slo.shape[0]):
            if (lo[k, 0] <= shi[p, 0] and slo[p, 0] <= hi[k, 0] and lo[k, 1] <= shi[p, 1]
                    and slo[p, 1] <= hi[k, 1] and lo[k, 2] <= shi[p, 2] and slo[p, 2] <= hi[k, 2]):
                cnt = _emit(out_b, out_p, cnt, k, p)
    return cnt if cnt <= out_b.shape[0] else -cnt


@njit(cache=True)
def _brute_kernel(lo, hi, out_i, out_j):
    """Every pair (i < j, sorted) whose boxes overlap (see
    :func:`_plane_pairs_kernel` for the return value)."""
    n = lo.shape[0]
    cnt = 0
    for i in range(n):
        for j in range(i + 1, n):
            if (lo[i, 0] <= hi[j, 0] and lo[j, 0] <= hi[i, 0] and lo[i, 1] <= hi[j, 1]
                    and lo[j, 1] <= hi[i, 1] and lo[i, 2] <= hi[j, 2] and lo[j, 2] <= hi[i, 2]):
                cnt = _emit(out_i, out_j, cnt, i, j)
    return cnt if cnt <= out_i.shape[0] else -cnt


class PairBuffer:
    """Two int64 output arrays of a pair kernel, kept between calls and
    grown geometrically (to at least twice the need) when a kernel reports
    them short: no allocation per step in the steady state.  Returned
    pairs are copies (the caller keeps them across steps)."""

    def __init__(self, size: int = 64):
        self.a = np.empty(size, np.int64)
        self.b = np.empty(size, np.int64)

    def run(self, kernel, *args) -> tuple[np.ndarray, np.ndarray]:
        k = kernel(*args, self.a, self.b)
        if k < 0:
            self.a = np.empty(-2 * k, np.int64)
            self.b = np.empty(-2 * k, np.int64)
            k = kernel(*args, self.a, self.b)
        return self.a[:k].copy(), self.b[:k].copy()


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


@njit(cache=True)
def _cells(lo, hi, order, a, max_cells, cell_scale, c0, c1):
    """First and last cell coordinate c0, c1 (m,) int64, in sweep order, of
    the boxes' intervals on axis ``a`` on a grid of cells ``cell_scale``
    times as wide as the widest interval (at most ``max_cells`` cells).
    floor((x - min) / c) is monotone in x in floating point too, so
    overlapping intervals always share a cell."""
    m = order.shape[0]
    mn = np.inf
    mx = -np.inf
    wmax = -np.inf
    for r in range(m):
        k = order[r]
        mn = min(mn, lo[k, a])
        mx = max(mx, hi[k, a])
        wmax = max(wmax, hi[k, a] - lo[k, a])
    span = mx - mn
    c = max(cell_scale * wmax, span / max_cells)
    if not (np.isfinite(c) and np.isfinite(span)) or c <= 0.0:
        c0[:] = 0
        c1[:] = 0
        return
    for r in range(m):
        k = order[r]
        c0[r] = np.int64(np.floor((lo[k, a] - mn) / c))
        c1[r] = np.int64(np.floor((hi[k, a] - mn) / c))


def sap_pairs(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sweep and prune over boxes [lo, hi] (n, 3): overlapping pairs (i < j;
    lo_i <= hi_j and lo_j <= hi_i on all three axes), sorted
    lexicographically -- exactly :func:`brute_pairs`' pairs, for any input
    (a row with a NaN overlaps nothing, as there).  The general path,
    numpy around compiled loops (the stage runs :func:`stage_pairs`' path
    and falls back to this one):

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
    * every other box is entered in each cell it covers (at most 2 x 2);
      the entries are sorted by the integer key cell * (m + 1) + rank of
      the lower bound on the sweep axis (times 4, plus two bits: is the
      cell the box's first on each grid axis), and each entry's
      candidates -- the later entries of its cell whose lower bound is <=
      its upper bound -- end at the first key >= cell * (m + 1) + number
      of lower bounds <= its upper bound (exact: integer keys, no
      floating-point combination);
    * a candidate is kept only in the cell holding the lower corner of the
      two boxes' intersection (so once, though they may share up to four
      cells), then tested on the two grid axes.

    Cost O(n log n) for boxes of similar sizes, whatever the layout.  The
    sweeps' loops (candidates, keys, their sort and the tests) are
    compiled (:func:`_sweep_kernel`, :func:`_grid_kernel`); the choice of
    axis and path, the sort along the sweep axis and the special boxes stay
    numpy calls (a fixed handful per call, O(n log n) work)."""
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
        return _sweep_pairs(lo, hi, axis, order, end, total)
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
    # keys: (cell * (m + 1) + rank) * 4 + 2 bits, < 2^63
    max_cells = min(_MAX_CELLS, int(np.sqrt(2.0 ** 60 / (m + 1))))
    return _grid_kernel(lo, hi, u, v, order, end, max_cells, float(_CELL_SCALE))


@njit(cache=True)
def _first_at_least(key, x, lo):
    """The first index >= lo of the sorted key whose value is >= x."""
    hi = key.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if key[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def _grid_kernel(lo, hi, u, v, order, end, max_cells, cell_scale):
    """:func:`_grid_pairs` compiled: an entry per box and grid cell it
    covers, as the key ((cell * M + rank) << 2) | loc (M = m + 1; rank:
    the box's place in the sweep order; loc's bit 0 set when the cell is
    not the box's first on v, bit 1 on u); the keys sorted; each entry's
    candidates are the later entries of its cell with rank < end (lo_q <=
    hi_p on the sweep axis), kept only in the cell of the lower corner of
    the two boxes' intersection (no loc bit set in both: on each grid axis
    the cell is the first of one of the two boxes), then tested on the two
    grid axes.  Returns (i, j) (min, max original indices, unsorted)."""
    m = order.shape[0]
    u0 = np.empty(m, np.int64)
    u1 = np.empty(m, np.int64)
    v0 = np.empty(m, np.int64)
    v1 = np.empty(m, np.int64)
    _cells(lo, hi, order, u, max_cells, cell_scale, u0, u1)
    _cells(lo, hi, order, v, max_cells, cell_scale, v0, v1)
    nv = v1.max() + 1
    M = m + 1
    E = 0
    for r in range(m):
        E += (u1[r] - u0[r] + 1) * (v1[r] - v0[r] + 1)
    key = np.empty(E, np.int64)
    e = 0
    for r in range(m):
        k0 = (u0[r] * nv + v0[r]) * M + r
        for tu in range(u1[r] - u0[r] + 1):
            for tv in range(v1[r] - v0[r] + 1):
                loc = (2 if tu > 0 else 0) | (1 if tv > 0 else 0)
                key[e] = ((k0 + (tu * nv + tv) * M) << 2) | loc
                e += 1
    key.sort()
    last = np.empty(E, np.int64)
    total = 0
    for p in range(E):
        kr = key[p] >> 2
        rank = kr % M
        last[p] = _first_at_least(key, (kr - rank + end[rank]) << 2, p + 1)
        total += last[p] - p - 1
    out_i = np.empty(total, np.int64)
    out_j = np.empty(total, np.int64)
    cnt = 0
    for p in range(E):
        lp = key[p] & 3
        i = order[(key[p] >> 2) % M]
        for q in range(p + 1, last[p]):
            if lp & (key[q] & 3):
                continue
            j = order[(key[q] >> 2) % M]
            if (lo[i, u] <= hi[j, u] and lo[j, u] <= hi[i, u]
                    and lo[i, v] <= hi[j, v] and lo[j, v] <= hi[i, v]):
                out_i[cnt] = min(i, j)
                out_j[cnt] = max(i, j)
                cnt += 1
    return out_i[:cnt], out_j[:cnt]


@njit(cache=True)
def _overlap_off_axis(lo, hi, i, j, axis):
    """Whether boxes i and j overlap (lo <= hi both ways) on the two axes
    other than ``axis``."""
    for a in range(3):
        if a != axis and not (lo[i, a] <= hi[j, a] and lo[j, a] <= hi[i, a]):
            return False
    return True


@njit(cache=True)
def _sweep_kernel(lo, hi, axis, order, end, out_i, out_j):
    """The single-axis sweep's pairs: box order[p] with the later boxes
    order[q] (p < q < end[p]: lo_q <= hi_p on the sweep axis), tested on
    the two other axes (lo <= hi on each), written as (min, max) original
    indices; returns their number."""
    m = order.shape[0]
    cnt = 0
    for p in range(m):
        i = order[p]
        for q in range(p + 1, end[p]):
            j = order[q]
            if _overlap_off_axis(lo, hi, i, j, axis):
                out_i[cnt] = min(i, j)
                out_j[cnt] = max(i, j)
                cnt += 1
    return cnt


def _sweep_pairs(lo, hi, axis, order, end, total):
    out_i = np.empty(total, np.int64)
    out_j = np.empty(total, np.int64)
    k = _sweep_kernel(lo, hi, axis, order, end, out_i, out_j)
    return out_i[:k], out_j[:k], None


def stage_pairs(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sap_pairs`' pairs by the broad-phase stage's compiled path
    (:func:`_sap_step`: the sweep, or the uniform grid for dense clouds)
    from a fresh sort order, or, for what that leaves (non-finite or
    inverted boxes, boxes too unequal for the grid), by :func:`sap_pairs`."""
    n = lo.shape[0]
    if n < 2:
        return _EMPTY, _EMPTY
    lo = np.ascontiguousarray(lo, float)
    hi = np.ascontiguousarray(hi, float)
    buf = SapBuffers(n)
    k = buf.run(lo, hi)
    if k == _FALLBACK:
        return sap_pairs(lo, hi)
    return buf.pi[:k].copy(), buf.pj[:k].copy()


def brute_pairs(lo: np.ndarray, hi: np.ndarray, buf: PairBuffer | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i < j, sorted) whose boxes [lo, hi] (n, 3) overlap, by
    testing all n (n - 1) / 2 of them (one compiled loop)."""
    return (buf or PairBuffer()).run(_brute_kernel, np.ascontiguousarray(lo, float), np.ascontiguousarray(hi, float))


#: a count the step kernel returns when the stage must fall back to
#: :func:`sap_pairs` (a box with a NaN or infinite bound or lo > hi, or a
#: dense cloud: the grid path)
_FALLBACK = -1
#: :func:`_sap_coherent`'s count for a dense cloud (the hash grid's case)
_DENSE = -2
#: the sweep axis is changed only for an axis whose box centres spread
#: this many times more (variance): a step near a tie does not re-sort
_AXIS_HYSTERESIS = 2.0


@njit(cache=True)
def _sap_coherent(lo, hi, order, state, out_i, out_j, code):
    """Sweep and prune along a persistent sweep axis (``state[0]``, -1 at
    first) and sort order ``order`` (n,) of the lower bounds, kept between
    steps and restored by insertion sort (boxes move little per step:
    O(n + swaps)); the axis changes (and ``order`` is sorted anew) only
    when another axis' spread of box centres exceeds the current one's
    ``_AXIS_HYSTERESIS`` times.  The pairs (i < j) overlapping on all
    three axes are written to out_i, out_j sorted lexicographically
    (``code`` (capacity,) scratch) -- exactly :func:`brute_pairs`' pairs:
    the axis and the order decide only the work.  Returns their number
    (written while they fit), or ``_DENSE`` beyond ``_SWEEP_ONLY``
    candidates per box.  The boxes are finite with lo <= hi."""
    n = lo.shape[0]
    var = np.zeros(3)
    for a in range(3):
        mean = 0.0
        for k in range(n):
            mean += 0.5 * lo[k, a] + 0.5 * hi[k, a]
        mean /= n
        for k in range(n):
            d = 0.5 * lo[k, a] + 0.5 * hi[k, a] - mean
            var[a] += d * d
    axis = state[0]
    best = 0 if var[0] >= var[1] and var[0] >= var[2] else (1 if var[1] >= var[2] else 2)
    if axis < 0 or not var[best] <= _AXIS_HYSTERESIS * var[axis]:
        axis = best
        state[0] = axis
        srt = np.argsort(lo[:, axis], kind="mergesort")
        for k in range(n):
            order[k] = srt[k]
    else:
        for p in range(1, n):  # insertion sort by (lower bound, index)
            t = order[p]
            x = lo[t, axis]
            q = p - 1
            while q >= 0 and (lo[order[q], axis] > x or (lo[order[q], axis] == x and order[q] > t)):
                order[q + 1] = order[q]
                q -= 1
            order[q + 1] = t
    cap = out_i.shape[0]
    cnt = 0
    total = 0
    for p in range(n):
        i = order[p]
        hp = hi[i, axis]
        q = p + 1
        while q < n and lo[order[q], axis] <= hp:
            j = order[q]
            if _overlap_off_axis(lo, hi, i, j, axis):
                if cnt < cap:
                    code[cnt] = min(i, j) * n + max(i, j)
                cnt += 1
            q += 1
        total += q - p - 1
        if total > _SWEEP_ONLY * n:
            return _DENSE
    if cnt <= cap:
        code[:cnt].sort()
        for t in range(cnt):
            out_i[t] = code[t] // n
            out_j[t] = code[t] % n
    return cnt


#: the hash grid is used only while no box is wider than this many times
#: the boxes' mean width (its cells are as wide as the widest box)
_GRID_WIDE = 8.0
#: the grid's cells are this much wider than the widest box, so that
#: round-off in the cell coordinates cannot put two overlapping boxes two
#: cells apart
_GRID_PAD = 1e-6
#: cells per axis at most (beyond, round-off in the coordinates could
#: exceed the pad): sap_pairs then
_GRID_MAX_CELLS = 1e6


@njit(cache=True)
def _cell_hash(cx, cy, cz, mask):
    return ((cx * 73856093) ^ (cy * 19349663) ^ (cz * 83492791)) & mask


@njit(cache=True)
def _hash_grid_pairs(lo, hi, start, perm, cell, key, js, out_i, out_j):
    """Overlapping pairs (i < j, sorted lexicographically) of finite boxes
    (lo <= hi), by a uniform grid: cells as wide as the widest box (plus
    ``_GRID_PAD``), each box in the cell of its lower corner -- boxes that
    overlap lie in neighbouring cells on every axis -- so each box is
    tested against the boxes of its 27 neighbouring cells.  The cells are
    numbered densely (x, y, z major to minor: a cell's three z neighbours
    are one run) while there are at most ``start.size - 1`` of them (2n
    and more), else hashed into that many buckets (a power of two; a box
    is tested only against the boxes of a bucket whose cell is the one
    looked for, so a hash collision adds tests, never a pair twice).
    O(n + tests); the pairs come in order (each box's few partners are
    sorted).  Work arrays: start (T + 1,), perm, key, js (n,), cell (n, 3).
    Returns the number of pairs (written while they fit), or ``_FALLBACK``
    when a box is wider than ``_GRID_WIDE`` times the mean or the grid
    would have more than ``_GRID_MAX_CELLS`` cells per axis."""
    n = lo.shape[0]
    wmax = 0.0
    wsum = 0.0
    mn = np.empty(3)
    mx = np.empty(3)
    for a in range(3):
        mn[a] = np.inf
        mx[a] = -np.inf
    for k in range(n):
        for a in range(3):
            w = hi[k, a] - lo[k, a]
            wmax = max(wmax, w)
            wsum += w
            mn[a] = min(mn[a], lo[k, a])
            mx[a] = max(mx[a], lo[k, a])
    if wmax > _GRID_WIDE * wsum / (3 * n):
        return _FALLBACK
    c = wmax * (1.0 + _GRID_PAD) if wmax > 0.0 else 1.0
    for a in range(3):
        if (mx[a] - mn[a]) / c > _GRID_MAX_CELLS:
            return _FALLBACK
    T = start.shape[0] - 1
    ny = np.int64(np.floor((mx[1] - mn[1]) / c)) + 1
    nz = np.int64(np.floor((mx[2] - mn[2]) / c)) + 1
    nx = np.int64(np.floor((mx[0] - mn[0]) / c)) + 1
    dense = nx * ny * nz <= T
    mask = T - 1
    for t in range(T + 1):
        start[t] = 0
    for k in range(n):
        for a in range(3):
            cell[k, a] = np.int64(np.floor((lo[k, a] - mn[a]) / c))
        if dense:
            key[k] = (cell[k, 0] * ny + cell[k, 1]) * nz + cell[k, 2]
        else:
            key[k] = _cell_hash(cell[k, 0], cell[k, 1], cell[k, 2], mask)
        start[key[k] + 1] += 1
    for t in range(T):
        start[t + 1] += start[t]
    for k in range(n):  # counting sort by key (start[b] runs ahead, then is restored)
        perm[start[key[k]]] = k
        start[key[k]] += 1
    for t in range(T, 0, -1):
        start[t] = start[t - 1]
    start[0] = 0
    cap = out_i.shape[0]
    cnt = 0
    for i in range(n):
        m = 0
        for dx in range(-1, 2):
            cx = cell[i, 0] + dx
            if dense and not 0 <= cx < nx:
                continue
            for dy in range(-1, 2):
                cy = cell[i, 1] + dy
                if dense:
                    if not 0 <= cy < ny:
                        continue
                    row = (cx * ny + cy) * nz
                    u0 = start[row + max(cell[i, 2] - 1, 0)]
                    u1 = start[row + min(cell[i, 2] + 1, nz - 1) + 1]
                    for u in range(u0, u1):
                        j = perm[u]
                        if (j > i and lo[i, 0] <= hi[j, 0] and lo[j, 0] <= hi[i, 0]
                                and _overlap_off_axis(lo, hi, i, j, 0)):
                            js[m] = j
                            m += 1
                    continue
                for dz in range(-1, 2):
                    cz = cell[i, 2] + dz
                    b = _cell_hash(cx, cy, cz, mask)
                    for u in range(start[b], start[b + 1]):
                        j = perm[u]
                        if (j > i and cell[j, 0] == cx and cell[j, 1] == cy and cell[j, 2] == cz
                                and lo[i, 0] <= hi[j, 0] and lo[j, 0] <= hi[i, 0]
                                and _overlap_off_axis(lo, hi, i, j, 0)):
                            js[m] = j
                            m += 1
        for a in range(1, m):  # insertion sort: few per box
            j = js[a]
            b = a - 1
            while b >= 0 and js[b] > j:
                js[b + 1] = js[b]
                b -= 1
            js[b + 1] = j
        for a in range(m):
            if cnt < cap:
                out_i[cnt] = i
                out_j[cnt] = js[a]
            cnt += 1
    return cnt


@njit(cache=True)
def _sap_step(lo, hi, order, state, out_i, out_j, code, grid):
    """The body-body pairs of ``broadphase = sap`` (i < j, sorted
    lexicographically; exactly :func:`brute_pairs`' pairs): by the sweep
    along a persistent axis and order (:func:`_sap_coherent`) or, for a
    dense cloud (``state[1]`` = 1 from the step the sweep found it dense
    on), the hash grid (:func:`_hash_grid_pairs`; ``grid`` its work
    arrays).  Returns their number, or ``_FALLBACK`` (boxes not all finite
    with lo <= hi, or too unequal for the grid: :func:`sap_pairs` then)."""
    n = lo.shape[0]
    for k in range(n):
        for a in range(3):
            w = hi[k, a] - lo[k, a]
            if not (w >= 0.0 and w < np.inf):
                return _FALLBACK
    if state[1] == 0:
        cnt = _sap_coherent(lo, hi, order, state, out_i, out_j, code)
        if cnt != _DENSE:
            return cnt
        state[1] = 1
    cnt = _hash_grid_pairs(lo, hi, *grid, out_i, out_j)
    if cnt == _FALLBACK:
        state[1] = 0
    return cnt


@njit(cache=True)
def _broad_step(sap, shape, radius, half, half_length, bound_radius, x0, R0, q1, x1, R1, v0, v1, u, w0, w1, h, grow,
                planes_n, planes_off, slo, shi, lo, hi, sweep, order, state, grid, pi, pj, code, bp, pk, bs, sk):
    """The whole broad phase in one call: the end rotations R1 of q1, the
    swept boxes lo, hi and ``sweep`` (:func:`_swept_boxes`), the body-body
    pairs (``sap``: :func:`_sap_step`, else every pair,
    :func:`_brute_kernel`), the body-plane and body-static-box pairs, into
    the caller's buffers.  Returns their three counts (minus the need where
    a buffer was short; ``_FALLBACK`` for the body-body pairs to be found
    by :func:`sap_pairs`)."""
    q2m(q1, R1)
    _swept_boxes(shape, radius, half, half_length, bound_radius, x0, R0, x1, R1, v0, v1, u, w0, w1, h, grow,
                 lo, hi, sweep)
    nbb = 0
    if lo.shape[0] >= 2:
        if sap:
            nbb = _sap_step(lo, hi, order, state, pi, pj, code, grid)
            if nbb > pi.shape[0]:
                nbb = -nbb
        else:
            nbb = _brute_kernel(lo, hi, pi, pj)
    npl = _plane_pairs_kernel(lo, hi, planes_n, planes_off, grow, bp, pk) if planes_n.shape[0] else 0
    nsb = _box_pairs_kernel(lo, hi, slo, shi, bs, sk) if slo.shape[0] else 0
    return nbb, npl, nsb


class SapBuffers:
    """The body-body pairs' state and buffers of :func:`_sap_step` for n
    boxes, kept between calls: the sweep's sort order and axis, the dense
    flag, the hash grid's work arrays, the pair outputs (grown
    geometrically: no allocation per step in the steady state)."""

    def __init__(self, n: int):
        self.order = np.arange(n, dtype=np.int64)
        #: the sweep axis (-1: none yet), the dense flag (_sap_step)
        self.state = np.array([-1, 0], np.int64)
        T = 1 << int(max(8 * n, 2) - 1).bit_length()  # grid cells or hash buckets: a power of two >= 8n
        self.grid = (np.zeros(T + 1, np.int64), np.empty(n, np.int64), np.empty((n, 3), np.int64),
                     np.empty(n, np.int64), np.empty(n, np.int64))
        self.grow(4 * n + 16)

    def grow(self, m: int) -> None:
        self.pi, self.pj, self.code = (np.empty(m, np.int64) for _ in range(3))

    def run(self, lo: np.ndarray, hi: np.ndarray) -> int:
        """:func:`_sap_step` on boxes lo, hi (n, 3) (C-contiguous float64),
        growing the outputs when short: the pairs' number (in pi, pj) or
        ``_FALLBACK``."""
        while True:
            k = _sap_step(lo, hi, self.order, self.state, self.pi, self.pj, self.code, self.grid)
            if k <= self.pi.size:
                return k
            self.grow(2 * k)


class BroadPhase(Stage):
    """Swept-box broad phase (see module doc): one compiled call per step
    (:func:`_broad_step`) into buffers kept between steps and grown
    geometrically; ``ctx.pairs_i`` ... are views of them, valid until the
    stage's next call."""

    name = "broadphase"
    family = "broadphase"

    def __init__(self, model):
        self.sap = model.setting("broadphase") == "sap" and model.n > SAP_MIN_BODIES
        self.margin = float(model.setting("contact_margin"))
        n = model.n
        # scratch, allocated once
        self.lo = np.empty((n, 3))
        self.hi = np.empty((n, 3))
        self.R1 = np.empty((n, 3, 3))
        self.pairs = SapBuffers(n)
        self._grow(2 * n + 16, 2 * n + 16)
        # writable copies: the kernels are compiled (and warmed, warm_up)
        # for writable arrays, and the model's are read-only
        self.shape = np.array(model.shape, np.int64)
        self.geom = tuple(np.array(a, float) for a in (model.radius, model.half_extents, model.half_length,
                                                       model.bound_radius))
        self.planes = (np.array(model.plane_normal, float).reshape(-1, 3), np.array(model.plane_offset, float))
        self.sbox = (np.array(model.sbox_aabb_lo, float).reshape(-1, 3), np.array(model.sbox_aabb_hi, float).reshape(-1, 3))

    def _grow(self, npl: int, nsb: int) -> None:
        self.bp, self.pk = np.empty(npl, np.int64), np.empty(npl, np.int64)
        self.bs, self.sk = np.empty(nsb, np.int64), np.empty(nsb, np.int64)

    def __call__(self, model, state, ctx) -> None:
        if ctx.reuse_contacts:
            return
        P = self.pairs
        while True:
            nbb, npl, nsb = _broad_step(self.sap, self.shape, *self.geom, state.x, ctx.R0, ctx.q1, ctx.x1, self.R1,
                                        state.v, ctx.v, ctx.u_lin, state.w, ctx.w, float(ctx.h), self.margin,
                                        *self.planes, *self.sbox, self.lo, self.hi, ctx.sweep, P.order, P.state,
                                        P.grid, P.pi, P.pj, P.code, self.bp, self.pk, self.bs, self.sk)
            short = [max(-c, 0) for c in (nbb, npl, nsb)]
            if nbb == _FALLBACK:
                short[0] = 0
            if not any(short):
                break
            if short[0]:
                P.grow(2 * short[0])
            self._grow(max(2 * short[1], self.bp.size), max(2 * short[2], self.bs.size))
        if nbb == _FALLBACK:
            ctx.pairs_i, ctx.pairs_j = sap_pairs(self.lo, self.hi)
        else:
            ctx.pairs_i, ctx.pairs_j = P.pi[:nbb], P.pj[:nbb]
        ctx.plane_pairs = (self.bp[:npl], self.pk[:npl])
        ctx.sbox_pairs = (self.bs[:nsb], self.sk[:nsb])


def warm_up() -> None:
    """Compile (or load from the cache) the broad phase's kernels, with the
    argument types of the step (writable C-contiguous float64 and int64
    arrays), on a tiny problem (see :mod:`engine.jit`)."""
    n = 3
    z3, z = np.zeros((n, 3)), np.zeros(n)
    R = np.tile(np.eye(3), (n, 1, 1))
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    lo, hi, sw = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    shape = np.array([SPHERE, BOX, CYLINDER], np.int64)
    grid = (np.zeros(9, np.int64), np.empty(n, np.int64), np.empty((n, 3), np.int64), np.empty(n, np.int64),
            np.empty(n, np.int64))
    for sap in (False, True):
        i1 = np.empty(1, np.int64)
        _broad_step(sap, shape, z + 0.1, z3 + 0.1, z, z + 0.2, z3, R, q, z3, R.copy(), z3, np.zeros((n + 1, 3)), z3,
                    z3, np.zeros((n + 1, 3)), 0.01, 1e-4, np.array([[0.0, 0.0, 1.0]]), np.zeros(1), z3[:1].copy(),
                    z3[:1].copy(), lo, hi, sw, np.arange(n, dtype=np.int64), np.array([-1, 1], np.int64), grid, i1,
                    i1.copy(), i1.copy(), i1.copy(), i1.copy(), i1.copy(), i1.copy())
    SapBuffers(n).run(lo, hi)
    buf = PairBuffer(1)
    buf.run(_brute_kernel, lo, hi)
    order = np.argsort(lo[:, 0], kind="stable")
    end = np.searchsorted(lo[order, 0], hi[order, 0], side="right")
    _sweep_pairs(lo, hi, 0, order, end, 3)
    _grid_pairs(lo, hi, 0, 1, 2, order, end)
