"""The contact graph's side of a row set (the part that never depends on
the pose): the rows' greedy colouring (:func:`colour_order`), the warm
cache's pair codes (:func:`_pair_codes_abs`) and :class:`Topology`, built
once per distinct contact graph and reused while it stays (a resting
stack: every step; :class:`engine.solver.Solve` keeps the last few).
Split from engine/contact/rows.py, which re-exports these names.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from physbench.engine.state import Contacts

@njit(cache=True)
def _greedy_colours(a, b, world, col):
    """The greedy colouring of :func:`colour_order` compiled, with 63-bit
    colour masks per body: ``col`` (m,) written; False (col undefined) when
    a row would need a 64th colour."""
    used = np.zeros(world + 1, np.int64)
    for k in range(a.shape[0]):
        i = a[k]
        j = b[k]
        mask = used[i]
        if j != world:
            mask |= used[j]
        c = 0
        while (mask >> c) & 1:
            c += 1
        if c >= 63:
            return False
        bit = np.int64(1) << c
        col[k] = c
        used[i] |= bit
        if j != world:
            used[j] |= bit
    return True


def colour_order(a: np.ndarray, b: np.ndarray, world: int) -> tuple[np.ndarray, np.ndarray]:
    """Greedy colouring: rows of one colour share no dynamic body.  Returns
    (order, bounds): the rows sorted by colour (stable) and the colour
    boundaries, so every colour is a contiguous slice of the sorted rows."""
    m = a.size
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(1, np.int64)
    col = np.empty(m, np.int64)
    if _greedy_colours(a, b, world, col):
        order = np.argsort(col, kind="stable")
        bounds = np.concatenate([[0], np.cumsum(np.bincount(col))])
        return order, bounds
    # more than 63 colours at some body: unbounded Python masks
    used: dict[int, int] = {}
    get = used.get
    cols = []
    append = cols.append
    for i, j in zip(a.tolist(), b.tolist()):
        ui = get(i, 0)
        if j != world:
            uj = get(j, 0)
            mask = ui | uj
        else:
            mask = ui
        c = ((~mask) & (mask + 1)).bit_length() - 1  # lowest free colour
        bit = 1 << c
        append(c)
        used[i] = ui | bit
        if j != world:
            used[j] = get(j, 0) | bit
    col = np.array(cols, np.int64)
    order = np.argsort(col, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(np.bincount(col))])
    return order, bounds


class Topology:
    """The part of a row set that depends only on which bodies (and
    statics) its rows join, in which order -- never on the pose: the
    colouring and its slices, the friction patches (grouping, colouring,
    slices, pair coefficients, inverse masses), the pair-code grouping of
    the warm-start cache and the body-sharing masks of the normal matrix.

    Built from the rows' (a, b, sidx) and reused while the contact graph is
    unchanged (:class:`Solve` keeps the last few; a resting stack rebuilds
    nothing after its first step).  Everything here is what :class:`Rows`
    computed per step before, by the same operations, so reuse is exact.
    Arrays are over the rows in colour order unless said otherwise.
    """

    def __init__(self, model, a: np.ndarray, b: np.ndarray, sidx: np.ndarray, friction: bool, colour: bool):
        if a.size == 0 or not self._compiled(model, a, b, sidx, friction, colour):
            self._numpy(model, a, b, sidx, friction, colour)

    def _compiled(self, model, a, b, sidx, friction: bool, colour: bool) -> bool:
        """The arrays of :meth:`_numpy` from one compiled call
        (:func:`_topology_kernel`, the same integers: ~10 us instead of
        ~40-150 us of numpy calls for a few rows -- a fresh engine's first
        staged steps and every new contact graph build one); False (nothing
        set) when a colouring needs a 64th colour (then :meth:`_numpy`).
        tests/test_engine_topology.py pins the equality."""
        n = model.n
        f = np.ascontiguousarray
        r = _topology_kernel(f(a, np.int64), f(b, np.int64), f(sidx, np.int64), n, model.n_statics, colour,
                             friction)
        if not r[0]:
            return False
        (_, order, bounds, a, b, sidx, ab, codes, code_order, code_first, uniq_codes, uniq_first, pid, pa, pb, pab,
         pfirst, cnt, uniq_pid) = r
        self.colour = colour
        self.order = order
        self.m = a.size
        self.a, self.b, self.sidx = a, b, sidx
        self.ab = ab
        bl = bounds.tolist()
        self.slices = [(bl[i], bl[i + 1]) for i in range(len(bl) - 1) if bl[i + 1] > bl[i]]
        self.ima = model.inv_mass[a]
        self.imb = model.inv_mass[b]
        self.codes = codes
        self.code_order = code_order
        self.code_first = code_first
        self.uniq_codes = uniq_codes
        self.uniq_first = uniq_first
        self._masks = None
        self.key = None
        self.friction = friction
        if friction:
            self.pid = pid
            self.pa, self.pb = pa, pb
            self.pab = pab
            self.np = pa.size
            self.pfirst = pfirst
            self.cnt = cnt
            self.uniq_pid = uniq_pid
            self.mus = self.muk = self.mur = None
        return True

    def _numpy(self, model, a: np.ndarray, b: np.ndarray, sidx: np.ndarray, friction: bool, colour: bool) -> None:
        """The topology by numpy calls (the reference of :meth:`_compiled`,
        and its path beyond 63 colours)."""
        n = model.n
        m = a.size
        if colour:
            order, bounds = colour_order(a, b, n)
            a, b, sidx = a[order], b[order], sidx[order]
        else:
            order, bounds = np.arange(m), np.array([0, m])
        self.colour = colour
        self.order = order
        self.m = m
        self.a, self.b, self.sidx = a, b, sidx
        #: (a, b) stacked, rows of the world included: one gather/scatter of
        #: the (n+1, 6) velocities per colour
        self.ab = np.stack([a, b], axis=1)
        #: colour slices (start, end)
        self.slices = [(int(bounds[i]), int(bounds[i + 1])) for i in range(len(bounds) - 1) if bounds[i + 1] > bounds[i]]
        self.ima = model.inv_mass[a]
        self.imb = model.inv_mass[b]
        #: pair codes of the rows (the warm cache's keys), their stable sort
        #: and the first row of each distinct pair in that sort
        self.codes = _pair_codes_abs(model, a, b, sidx)
        self.code_order = np.argsort(self.codes, kind="stable")
        sc = self.codes[self.code_order]
        self.code_first = np.flatnonzero(np.concatenate([[True], sc[1:] != sc[:-1]]))
        self.uniq_codes = sc[self.code_first]
        #: first row (in row order) of each distinct pair, = np.unique's return_index
        self.uniq_first = self.code_order[self.code_first]
        self._masks = None
        #: the pair codes (contact order) it was built for, set by
        #: solver.Solve.topology (the one-call path compares a step's codes)
        self.key = None
        self.friction = friction
        if friction:
            self._patches(model, colour)

    def _patches(self, model, colour: bool) -> None:
        n = model.n
        a, b = self.a, self.b
        code = a * (n + 1) + b + (n + 1) * (n + 1) * (self.sidx + 1)
        uniq, first, pid = np.unique(code, return_index=True, return_inverse=True)
        npch = uniq.size
        pa, pb = a[first], b[first]
        if colour:
            porder, pbounds = colour_order(pa, pb, n)
        else:
            porder, pbounds = np.arange(npch), np.array([0, npch])
        rank = np.empty(npch, np.int64)
        rank[porder] = np.arange(npch)
        self.pid = pid = rank[pid]
        self.pa, self.pb = pa[porder], pb[porder]
        self.pab = np.stack([self.pa, self.pb], axis=1)
        self.np = npch
        #: first row of each patch (patch order)
        self.pfirst = first[porder]
        self.cnt = np.bincount(pid, minlength=npch).astype(float)
        #: patch of each distinct pair (uniq_codes order)
        self.uniq_pid = pid[self.uniq_first]
        self.mus = self.muk = self.mur = None  # pair coefficients, from the first contacts seen

    def masks(self):
        """Body-sharing masks of the normal matrix (a_i == a_j, a_i == b_j,
        b_i == a_j, b_i == b_j), (m, m) bool."""
        if self._masks is None:
            a, b = self.a, self.b
            self._masks = (a[:, None] == a[None, :], a[:, None] == b[None, :],
                           b[:, None] == a[None, :], b[:, None] == b[None, :])
        return self._masks


@njit(cache=True)
def _counting_order(key, k):
    """The stable order of ``key`` (values 0..k-1) and the bounds of each
    value's run ((k + 1,)): np.argsort(key, kind="stable") and
    concatenate([[0], cumsum(bincount(key, minlength=k))])."""
    m = key.shape[0]
    bounds = np.zeros(k + 1, np.int64)
    for i in range(m):
        bounds[key[i] + 1] += 1
    for c in range(k):
        bounds[c + 1] += bounds[c]
    pos = bounds[:k].copy()
    order = np.empty(m, np.int64)
    for i in range(m):
        c = key[i]
        order[pos[c]] = i
        pos[c] += 1
    return order, bounds


@njit(cache=True)
def _colour_order1(a, b, world):
    """:func:`colour_order`'s compiled path: (ok, order, bounds); ok False
    when a row would need a 64th colour."""
    m = a.shape[0]
    col = np.empty(m, np.int64)
    if not _greedy_colours(a, b, world, col):
        return False, np.empty(0, np.int64), np.empty(0, np.int64)
    k = 0
    for i in range(m):
        if col[i] + 1 > k:
            k = col[i] + 1
    order, bounds = _counting_order(col, k)
    return True, order, bounds


@njit(cache=True)
def _runs(sorted_keys):
    """Positions (k,) where a run of equal values starts in a sorted array."""
    m = sorted_keys.shape[0]
    first = np.empty(m, np.int64)
    k = 0
    for i in range(m):
        if i == 0 or sorted_keys[i] != sorted_keys[i - 1]:
            first[k] = i
            k += 1
    return first[:k].copy()


@njit(cache=True)
def _topology_kernel(a0, b0, s0, n, n_statics, colour, friction):
    """:class:`Topology`'s arrays for the rows (a0, b0, s0) (m >= 1,) in one
    call, the integers :meth:`Topology._numpy` computes: (ok, order,
    colour bounds, a, b, sidx, ab, codes, code_order, code_first,
    uniq_codes, uniq_first, then the patches' pid, pa, pb, pab, pfirst,
    cnt, uniq_pid (empty without friction)); ok False when a colouring
    needs a 64th colour."""
    m = a0.shape[0]
    e = np.empty(0, np.int64)
    e2 = np.empty((0, 2), np.int64)
    ef = np.empty(0)
    if colour:
        ok, order, bounds = _colour_order1(a0, b0, n)
        if not ok:
            return False, e, e, e, e, e, e2, e, e, e, e, e, e, e, e, e2, e, ef, e
    else:
        order = np.arange(m)
        bounds = np.array([0, m], np.int64)
    a = a0[order]
    b = b0[order]
    sidx = s0[order]
    ab = np.empty((m, 2), np.int64)
    ab[:, 0] = a
    ab[:, 1] = b
    codes = (a * (n + 1) + b) * (n_statics + 1) + (sidx + 1)
    code_order = np.argsort(codes, kind="mergesort")
    sc = codes[code_order]
    code_first = _runs(sc)
    uniq_codes = sc[code_first]
    uniq_first = code_order[code_first]
    if not friction:
        return True, order, bounds, a, b, sidx, ab, codes, code_order, code_first, uniq_codes, uniq_first, e, e, e, \
            e2, e, ef, e
    # patches: np.unique(code, return_index=True, return_inverse=True)
    pcode = a * (n + 1) + b + (n + 1) * (n + 1) * (sidx + 1)
    perm = np.argsort(pcode, kind="mergesort")
    ps = pcode[perm]
    starts = _runs(ps)
    npch = starts.shape[0]
    first = perm[starts]
    pid0 = np.empty(m, np.int64)
    u = -1
    for i in range(m):
        if i == 0 or ps[i] != ps[i - 1]:
            u += 1
        pid0[perm[i]] = u
    pa0 = a[first]
    pb0 = b[first]
    if colour:
        ok, porder, _ = _colour_order1(pa0, pb0, n)
        if not ok:
            return False, e, e, e, e, e, e2, e, e, e, e, e, e, e, e, e2, e, ef, e
    else:
        porder = np.arange(npch)
    rank = np.empty(npch, np.int64)
    for i in range(npch):
        rank[porder[i]] = i
    pid = rank[pid0]
    pa = pa0[porder]
    pb = pb0[porder]
    pab = np.empty((npch, 2), np.int64)
    pab[:, 0] = pa
    pab[:, 1] = pb
    pfirst = first[porder]
    cnt = np.zeros(npch)
    for i in range(m):
        cnt[pid[i]] += 1.0
    uniq_pid = pid[uniq_first]
    return True, order, bounds, a, b, sidx, ab, codes, code_order, code_first, uniq_codes, uniq_first, pid, pa, pb, \
        pab, pfirst, cnt, uniq_pid


def warm_up() -> None:
    """Compile (or load) :func:`_topology_kernel` with the step's argument
    types (engine/jit.py): three rows, with and without colouring and
    friction."""
    a = np.array([0, 0, 1], np.int64)
    b = np.array([1, 2, 2], np.int64)
    s = np.array([-1, 0, 0], np.int64)
    for colour in (False, True):
        for friction in (False, True):
            _topology_kernel(a, b, s, 2, 1, colour, friction)


def _pair_codes(model, c: Contacts) -> np.ndarray:
    return _pair_codes_abs(model, c.a, c.b, c.sidx)


def _pair_codes_abs(model, a, b, sidx) -> np.ndarray:
    """Warm-cache key of the pairs (a, b, static index): unique per pair."""
    return (a * (model.n + 1) + b) * (model.n_statics + 1) + (sidx + 1)
