"""The warm start (the warm-start phase) and its cache (the store phase):
compiled matching and filling, the cache dataclass and the phases' calls.

The cache a solve leaves (:class:`WarmCache`; the kernels read it as an
engine.contact.packs.Cache) is sorted by pair code: ``code`` (k,) the pair
code of each cached point, ``loc`` (k, 3) m its point in body a's frame,
``fn`` (k,) N its normal force; per distinct pair its code ``pairs`` (p,)
with the friction force ``ft`` (p, 3) N, twist torque ``tw`` (p,) N m and
rolling torque ``rr`` (p, 3) N m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from physbench.engine.contact.packs import Cache
from physbench.engine.contact.rows import Rows
from physbench.engine.contact.scratch import Scratch
from physbench.engine.pack import Pack

_NO_I = np.zeros(0, np.int64)
_NO_T = np.zeros((0, 2, 3))
_NO_LT = np.zeros((0, 3))


@njit(cache=True)
def match(codes, loc, a, bound_radius, ko, h, lam_n, friction, rolling, pid, t, lam_t, matched):
    """Warm impulses of the rows (pair ``codes`` (m,), points in body a's
    frame ``loc`` (m, 3), bodies ``a`` (m,)) from the cache ``ko`` (a
    :class:`engine.pack.Pack` of an engine.contact.packs.Cache): each row
    takes lambda = fn h of the nearest cached point of its pair (the first
    on ties) within 0.1 ``bound_radius[a]`` + 0.1 mm; with ``friction``,
    the patch ``pid[i]`` of a matched row takes its pair's friction force
    in its tangent frame ``t`` (np, 2, 3), the twist and (``rolling``) the
    rolling torque, times h.  ``lam_n`` (m,) and ``lam_t`` (np, nr) are
    written where matched (left as they are elsewhere); ``matched`` (np,)
    bool scratch."""
    o = ko.items
    o_code, o_loc, o_fn, u_code, u_ft, u_tw, u_rr = o.code, o.loc, o.fn, o.pairs, o.ft, o.tw, o.rr
    m = codes.shape[0]
    k = o_code.shape[0]
    if friction:
        matched[:] = False
    for i in range(m):
        code = codes[i]
        j = np.searchsorted(o_code, code)
        best = -1
        bd = 0.0
        while j < k and o_code[j] == code:
            dx = loc[i, 0] - o_loc[j, 0]
            dy = loc[i, 1] - o_loc[j, 1]
            dz = loc[i, 2] - o_loc[j, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if best < 0 or d2 < bd:
                best = j
                bd = d2
            j += 1
        if best < 0:
            continue
        tol = 0.1 * bound_radius[a[i]] + 1e-4
        if bd > tol * tol:
            continue
        lam_n[i] = o_fn[best] * h
        if friction:
            p = pid[i]
            if matched[p]:
                continue
            matched[p] = True
            g = np.searchsorted(u_code, code)
            for r in range(2):
                lam_t[p, r] = (t[p, r, 0] * u_ft[g, 0] + t[p, r, 1] * u_ft[g, 1] + t[p, r, 2] * u_ft[g, 2]) * h
            lam_t[p, 2] = u_tw[g] * h
            if rolling:
                for r in range(2):
                    lam_t[p, 3 + r] = (t[p, r, 0] * u_rr[g, 0] + t[p, r, 1] * u_rr[g, 1]
                                       + t[p, r, 2] * u_rr[g, 2]) * h


@njit(cache=True)
def store(order, codes, loc, lam_n, touch, first, uniq_pid, friction, rolling, lam_t, t, h, kq):
    """Fill a cache (``kq``, a :class:`engine.pack.Pack` of an
    engine.contact.packs.Cache) from a solve: rows in the stable sort by
    pair code ``order`` (m,), ``first`` (p,) the first sorted row of each
    distinct pair and ``uniq_pid`` (p,) its patch; forces are impulses / h
    (N, N m)."""
    q = kq.items
    o_code, o_loc, o_fn, o_touch, u_code, u_ft, u_tw, u_rr = q.code, q.loc, q.fn, q.touch, q.pairs, q.ft, q.tw, q.rr
    for s in range(order.shape[0]):
        i = order[s]
        o_code[s] = codes[i]
        o_fn[s] = lam_n[i] / h
        o_touch[s] = touch[i]
        for c in range(3):
            o_loc[s, c] = loc[i, c]
    for g in range(first.shape[0]):
        u_code[g] = o_code[first[g]]
        for c in range(3):
            u_ft[g, c] = 0.0
            u_rr[g, c] = 0.0
        u_tw[g] = 0.0
        if friction:
            p = uniq_pid[g]
            for c in range(3):
                u_ft[g, c] = (lam_t[p, 0] * t[p, 0, c] + lam_t[p, 1] * t[p, 1, c]) / h
                if rolling:
                    u_rr[g, c] = (lam_t[p, 3] * t[p, 0, c] + lam_t[p, 4] * t[p, 1, c]) / h
            u_tw[g] = lam_t[p, 2] / h


def warm_start(model, old: "WarmCache", rows: Rows, h: float) -> None:
    """Each row takes the cached force of the nearest cached point of its
    pair (in body a's frame) within 0.1 bounding radius + 0.1 mm; a patch
    with a matched point takes its pair's cached friction force and twist
    (:func:`engine.contact.warm.match`)."""
    topo = rows.topo
    f = rows.friction
    match(topo.codes, rows.loc, rows.a, model.bound_radius, old.kept, h, rows.lam_n, f, f and rows.rolling,
          topo.pid if f else _NO_I, rows.t if f else _NO_T, rows.lam_t if f else _NO_LT,
          np.zeros(rows.np if f else 0, np.bool_))


def _fill(rows: Rows, h: float, touching: np.ndarray, out: "WarmCache") -> "WarmCache":
    """Fill ``out`` (arrays sized to the rows and distinct pairs of
    ``rows``) with the solve's forces (:func:`store`)."""
    topo = rows.topo
    f = rows.friction
    store(topo.code_order, topo.codes, rows.loc, rows.lam_n, touching[rows.idx], topo.code_first,
          topo.uniq_pid if f else _NO_I, f, f and rows.rolling, rows.lam_t if f else _NO_LT, rows.t if f else _NO_T, h,
          out.kept)
    return out


def _sizes(rows: Rows) -> tuple[int, int]:
    """(cached points, distinct pairs) of the cache of ``rows``."""
    return rows.m, rows.topo.uniq_codes.size


def store_forces(rows: Rows, h: float, touching: np.ndarray) -> "WarmCache":
    """The cache of the solve's forces for the next step's warm start
    (``touching`` (k,) bool over the stage's contacts: the rows that were
    touching at the start of the step -- a point pressed *at rest* only if
    it was; a speculative row that pressed to land its point exactly on the
    surface did not rest), in arrays of its own (:class:`WarmPool` reuses
    kept ones)."""
    return _fill(rows, h, touching, empty_cache(*_sizes(rows)))


def empty_cache(m: int, p: int) -> "WarmCache":
    """A cache of ``m`` points and ``p`` distinct pairs in arrays of its
    own, contents undefined."""
    return WarmCache(np.empty(m, np.int64), np.empty((m, 3)), np.empty(m), np.empty(p, np.int64),
                     np.empty((p, 3)), np.empty(p), np.empty((p, 3)), np.empty(m, np.bool_))


class WarmPool:
    """Kept caches for a Solve stage: :meth:`store` fills one whose arrays
    are not those of a cache still in use, views of buffers grown
    geometrically (no allocation per step in the steady state).

    In use are at most two caches: the one the solve warm-started from
    (``state.warm``) and the one its (mini-)step began with, which the step
    loop restores for a rerun (pipeline._substep; the time-of-impact
    search's reruns warm-start each from the last).  Three slots always
    leave one free (tests/test_determinism.py pins the bits)."""

    SLOTS = 3

    def __init__(self) -> None:
        self._scratch = [Scratch() for _ in range(self.SLOTS)]
        self._cache: list[WarmCache | None] = [None] * self.SLOTS
        self._size: list[tuple[int, int]] = [(-1, -1)] * self.SLOTS

    def store(self, rows: Rows, h: float, touching: np.ndarray, busy0, busy1) -> "WarmCache":
        """As :func:`store_forces`, into a kept cache that is neither
        ``busy0`` nor ``busy1`` (caches, or None)."""
        return _fill(rows, h, touching, self.slot(_sizes(rows), busy0, busy1))

    def slot(self, size: tuple[int, int], busy0, busy1) -> "WarmCache":
        """A kept cache of ``size`` (points, distinct pairs) that is neither
        ``busy0`` nor ``busy1`` (caches, or None), contents undefined."""
        for k in range(self.SLOTS):
            out = self._cache[k]
            if out is None or (out is not busy0 and out is not busy1):
                break
        m, p = size
        if out is None or self._size[k] != size:
            sc = self._scratch[k]
            out = self._cache[k] = WarmCache(
                sc.take("codes", (m,), np.int64), sc.take("loc", (m, 3)), sc.take("fn", (m,)),
                sc.take("pairs", (p,), np.int64), sc.take("ft", (p, 3)), sc.take("tw", (p,)),
                sc.take("rr", (p, 3)), sc.take("touch", (m,), np.bool_))
            self._size[k] = size
        return out


@dataclass(eq=False)
class WarmCache:
    """The warm-start cache a solve leaves for the next step, as arrays
    sorted by pair code: ``codes`` (k,) the pair code of each cached point,
    ``loc`` (k, 3) m its point in body a's frame, ``fn`` (k,) N its normal
    force, ``pairs`` (p,) the distinct pair codes, ``ft`` (p, 3) N their
    friction forces, ``tw`` (p,) N m twist torques, ``rr`` (p, 3) N m
    rolling torques (zero without rolling friction), ``touch`` (k,) bool
    whether the point touched at the start of its step."""

    codes: np.ndarray
    loc: np.ndarray
    fn: np.ndarray
    pairs: np.ndarray
    ft: np.ndarray
    tw: np.ndarray
    rr: np.ndarray
    touch: np.ndarray

    @property
    def packed(self) -> Cache:
        """The arrays as the kernels read them (engine.contact.packs.Cache)."""
        return Cache(code=self.codes, loc=self.loc, fn=self.fn, pairs=self.pairs, ft=self.ft, tw=self.tw, rr=self.rr,
                     touch=self.touch)

    @property
    def kept(self) -> Pack:
        """:attr:`packed` as one :class:`engine.pack.Pack` (built on first
        use; the arrays are the cache's own, never replaced)."""
        k = self.__dict__.get("_kept")
        if k is None:
            k = self.__dict__["_kept"] = Pack(self.packed)
        return k
