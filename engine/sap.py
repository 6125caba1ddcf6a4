"""The broad-phase stage's compiled body-body pair finders
(engine/broadstage.py): sweep and prune along a sort order kept between
steps (:func:`_sap_coherent`) and, for dense clouds, a uniform grid
(:func:`_hash_grid_pairs`), driven by :func:`_sap_step` with its state and
buffers in :class:`SapBuffers`.  Exactly the all-pairs test's pairs (i < j)
in lexicographic order; what they cannot take (non-finite or very unequal
boxes) they hand back as ``_FALLBACK`` for engine/broadphase.py's
:func:`sap_pairs`.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _overlap_off_axis(lo, hi, i, j, axis):
    """Whether boxes i and j overlap (lo <= hi both ways) on the two axes
    other than ``axis``."""
    for a in range(3):
        if a != axis and not (lo[i, a] <= hi[j, a] and lo[j, a] <= hi[i, a]):
            return False
    return True


#: the sweep's candidates per box beyond which a cloud is dense (the grid's
#: case)
SWEEP_ONLY = 32
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
def _sap_coherent(lo, hi, order, state, out_i, out_j, code, cs):
    """Sweep and prune along a persistent sweep axis (``state[0]``, -1 at
    first) and sort order ``order`` (n,) of the lower bounds, kept between
    steps and restored by insertion sort (boxes move little per step:
    O(n + swaps)); the axis changes (and ``order`` is sorted anew) only
    when another axis' spread of box centres exceeds the current one's
    ``_AXIS_HYSTERESIS`` times.  The pairs (i < j) overlapping on all
    three axes are written to out_i, out_j sorted lexicographically
    (``code`` (capacity,), ``cs`` (>= n + 1,) scratch) -- exactly
    :func:`brute_pairs`' pairs:
    the axis and the order decide only the work.  Returns their number
    (written while they fit), or ``_DENSE`` beyond ``SWEEP_ONLY``
    candidates per box.  The boxes are finite with lo <= hi."""
    n = lo.shape[0]
    v0 = _spread(lo, hi, 0)
    v1 = _spread(lo, hi, 1)
    v2 = _spread(lo, hi, 2)
    axis = state[0]
    best = 0 if v0 >= v1 and v0 >= v2 else (1 if v1 >= v2 else 2)
    if axis < 0 or not _pick3(v0, v1, v2, best) <= _AXIS_HYSTERESIS * _pick3(v0, v1, v2, axis):
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
        if total > SWEEP_ONLY * n:
            return _DENSE
    if cnt <= cap:
        _sort_codes(code, cnt, n, cs, out_i, out_j)
    return cnt


@njit(cache=True, inline="always")
def _spread(lo, hi, a):
    """The variance (times n) of the box centres along axis a, summed in
    box order."""
    n = lo.shape[0]
    mean = 0.0
    for k in range(n):
        mean += 0.5 * lo[k, a] + 0.5 * hi[k, a]
    mean /= n
    v = 0.0
    for k in range(n):
        d = 0.5 * lo[k, a] + 0.5 * hi[k, a] - mean
        v += d * d
    return v


@njit(cache=True, inline="always")
def _pick3(v0, v1, v2, a):
    return v0 if a == 0 else (v1 if a == 1 else v2)


@njit(cache=True)
def _sort_codes(code, cnt, n, cs, out_i, out_j):
    """The pairs of the unique codes ``code[:cnt]`` (min * n + max) in
    ascending code order into ``out_i``, ``out_j``: a counting sort by
    the first body (``cs`` (>= n + 1,) scratch), then each body's few
    partners by insertion sort -- the order of sorting the codes, without
    the allocations of numba's ``ndarray.sort``
    (tests/test_engine_steady.py::test_steady_step_allocates_nothing)."""
    for t in range(n + 1):
        cs[t] = 0
    for t in range(cnt):
        cs[code[t] // n + 1] += 1
    for t in range(n):
        cs[t + 1] += cs[t]
    for t in range(cnt):
        i = code[t] // n
        u = cs[i]
        out_i[u] = i
        out_j[u] = code[t] % n
        cs[i] = u + 1
    b0 = 0
    for i in range(n):  # cs[i] is now the end of body i's run
        b1 = cs[i]
        for a in range(b0 + 1, b1):
            j = out_j[a]
            b = a - 1
            while b >= b0 and out_j[b] > j:
                out_j[b + 1] = out_j[b]
                b -= 1
            out_j[b + 1] = j
        b0 = b1


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
    mn0 = mn1 = mn2 = np.inf  # the lower corners' bounds, per axis (scalars: nothing allocated)
    mx0 = mx1 = mx2 = -np.inf
    for k in range(n):
        for a in range(3):
            w = hi[k, a] - lo[k, a]
            wmax = max(wmax, w)
            wsum += w
        mn0 = min(mn0, lo[k, 0])
        mx0 = max(mx0, lo[k, 0])
        mn1 = min(mn1, lo[k, 1])
        mx1 = max(mx1, lo[k, 1])
        mn2 = min(mn2, lo[k, 2])
        mx2 = max(mx2, lo[k, 2])
    if wmax > _GRID_WIDE * wsum / (3 * n):
        return _FALLBACK
    c = wmax * (1.0 + _GRID_PAD) if wmax > 0.0 else 1.0
    if ((mx0 - mn0) / c > _GRID_MAX_CELLS or (mx1 - mn1) / c > _GRID_MAX_CELLS
            or (mx2 - mn2) / c > _GRID_MAX_CELLS):
        return _FALLBACK
    T = start.shape[0] - 1
    ny = np.int64(np.floor((mx1 - mn1) / c)) + 1
    nz = np.int64(np.floor((mx2 - mn2) / c)) + 1
    nx = np.int64(np.floor((mx0 - mn0) / c)) + 1
    dense = nx * ny * nz <= T
    mask = T - 1
    used = nx * ny * nz if dense else T  # the cells (buckets) numbered: start[:used + 1]
    for t in range(used + 1):
        start[t] = 0
    for k in range(n):
        cell[k, 0] = np.int64(np.floor((lo[k, 0] - mn0) / c))
        cell[k, 1] = np.int64(np.floor((lo[k, 1] - mn1) / c))
        cell[k, 2] = np.int64(np.floor((lo[k, 2] - mn2) / c))
        if dense:
            key[k] = (cell[k, 0] * ny + cell[k, 1]) * nz + cell[k, 2]
        else:
            key[k] = _cell_hash(cell[k, 0], cell[k, 1], cell[k, 2], mask)
        start[key[k] + 1] += 1
    for t in range(used):
        start[t + 1] += start[t]
    for k in range(n):  # counting sort by key (start[b] runs ahead, then is restored)
        perm[start[key[k]]] = k
        start[key[k]] += 1
    for t in range(used, 0, -1):
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
        cnt = _sap_coherent(lo, hi, order, state, out_i, out_j, code, grid[0])
        if cnt != _DENSE:
            return cnt
        state[1] = 1
    cnt = _hash_grid_pairs(lo, hi, *grid, out_i, out_j)
    if cnt == _FALLBACK:
        state[1] = 0
    return cnt


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
