"""Shared narrow-phase helpers: norms, segment closest points, the
golden-section search along segments, the box's corner and edge tables, and
the concatenation of per-family results ``(k, normal, point, gap, fid)``
(see :mod:`engine.collision`)."""

from __future__ import annotations

import math

import numpy as np


_EPS = 1e-12


def _norm(v):
    return np.sqrt(np.einsum("...i,...i->...", v, v))


_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)  # (8, 3)


def _segment_closest(p, a0, a1):
    """Closest points on segments [a0, a1] to points p (k, 3); returns
    (point, s in [0, 1])."""
    d = a1 - a0
    dd = np.einsum("ki,ki->k", d, d)
    s = np.where(dd > _EPS, np.einsum("ki,ki->k", p - a0, d) / np.where(dd > _EPS, dd, 1.0), 0.0)
    s = np.clip(s, 0.0, 1.0)
    return a0 + d * s[:, None], s


def _segment_segment(p0, p1, q0, q1):
    """Closest points between segments [p0,p1] and [q0,q1] (Ericson 5.1.9)."""
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("ki,ki->k", d1, d1)
    e = np.einsum("ki,ki->k", d2, d2)
    f = np.einsum("ki,ki->k", d2, r)
    c = np.einsum("ki,ki->k", d1, r)
    b = np.einsum("ki,ki->k", d1, d2)
    denom = a * e - b * b
    s = np.where(denom > _EPS * np.maximum(a * e, _EPS), np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0, 1), 0.0)
    t = np.where(e > _EPS, (b * s + f) / np.where(e > _EPS, e, 1.0), 0.0)
    # clamp t and recompute s
    t_lo = t < 0.0
    t_hi = t > 1.0
    t = np.clip(t, 0.0, 1.0)
    s = np.where(t_lo, np.clip(np.where(a > _EPS, -c / np.where(a > _EPS, a, 1.0), 0.0), 0, 1), s)
    s = np.where(t_hi, np.clip(np.where(a > _EPS, (b - c) / np.where(a > _EPS, a, 1.0), 0.0), 0, 1), s)
    return p0 + d1 * s[:, None], q0 + d2 * t[:, None]


_GOLDEN = 0.5 * (math.sqrt(5.0) - 1.0)


def _golden(g, lo, hi, iters: int = 40):
    """Golden-section search for the minimum of a function ``g(s (k,)) ->
    (k,)`` unimodal on [lo, hi] (k,): one new evaluation per iteration, 40
    iterations leave a bracket of 4e-9 of the interval.  Returns the
    bracket's midpoint s and g(s)."""
    g_ = _GOLDEN
    x1 = hi - g_ * (hi - lo)
    x2 = lo + g_ * (hi - lo)
    f1 = g(x1)
    f2 = g(x2)
    for _ in range(iters):
        left = f1 < f2  # the minimum is in [lo, x2]: x1 becomes the upper probe
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        xn = np.where(left, hi - g_ * (hi - lo), lo + g_ * (hi - lo))
        fn = g(xn)
        x1, x2, f1, f2 = (np.where(left, xn, x2), np.where(left, x1, xn),
                          np.where(left, fn, f2), np.where(left, f1, fn))
    s = 0.5 * (lo + hi)
    return s, g(s)


def _segment_min(f, e0, e1, iters: int = 40):
    """Parameter s (k,) in [0, 1] of the minimum of a convex function
    ``f(points (k, 3)) -> (k,)`` along the segments e0 -> e1 (k, 3): golden
    section (:func:`_golden`), then the end points compared exactly (the
    minimum may sit at an end, and where f is flat the end wins).  Returns
    (s, f there, the smaller of f at the two ends)."""
    d = e1 - e0
    s, f_s = _golden(lambda x: f(e0 + d * x[:, None]), np.zeros(e0.shape[0]), np.ones(e0.shape[0]), iters)
    f_0 = f(e0)
    f_1 = f(e1)
    at0 = f_0 <= f_s
    at1 = f_1 < np.minimum(f_s, f_0)
    s = np.where(at1, 1.0, np.where(at0, 0.0, s))
    return s, np.where(at1, f_1, np.where(at0, f_0, f_s)), np.minimum(f_0, f_1)


#: the twelve edges of a box in its frame: (start, end) corner multipliers,
#: edges along x, then y, then z
_BOX_EDGES = np.array([[[-1, sy, sz], [1, sy, sz]] for sy in (-1, 1) for sz in (-1, 1)]
                      + [[[sx, -1, sz], [sx, 1, sz]] for sx in (-1, 1) for sz in (-1, 1)]
                      + [[[sx, sy, -1], [sx, sy, 1]] for sx in (-1, 1) for sy in (-1, 1)], float)  # (12, 2, 3)


#: an edge point is a contact only where it is deeper (or closer) than both
#: of its corners by this much (m): on a flat stretch the corners stand for it
EDGE_POINT_TOL = 1e-9


def _empty():
    return (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))


def _cat(parts):
    parts = [p for p in parts if p[0].size]
    if not parts:
        return _empty()
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(5))
