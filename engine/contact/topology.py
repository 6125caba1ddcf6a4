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

from engine.state import Contacts

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


def _pair_codes(model, c: Contacts) -> np.ndarray:
    return _pair_codes_abs(model, c.a, c.b, c.sidx)


def _pair_codes_abs(model, a, b, sidx) -> np.ndarray:
    """Warm-cache key of the pairs (a, b, static index): unique per pair."""
    return (a * (model.n + 1) + b) * (model.n_statics + 1) + (sidx + 1)
