"""Broad-phase pair finders over boxes [lo, hi] (n, 3): the general
sweep and prune :func:`sap_pairs` (any boxes, NaN and infinite bounds
included; numpy around compiled loops), the all-pairs test
:func:`brute_pairs`, and :func:`stage_pairs`, the stage's own compiled path
(engine/sap.py) from a fresh order.  All give exactly the same pairs
(i < j) in lexicographic order (tests/test_broadphase.py).  The stage that
runs them every step is engine/broadstage.py.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from physbench.engine.sap import _FALLBACK, SWEEP_ONLY, SapBuffers, _overlap_off_axis


@njit(cache=True)
def _emit(out_a, out_b, cnt, a, b):
    """Write the pair (a, b) at cnt when the outputs have room (the kernels
    count on, to report what they need); returns cnt + 1."""
    if cnt < out_a.shape[0]:
        out_a[cnt] = a
        out_b[cnt] = b
    return cnt + 1


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
#: box; beyond, the sweep runs within grid cells (the stage's sweep switches
#: to its grid at the same count: engine/sap.py)
_SWEEP_ONLY = SWEEP_ONLY
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
