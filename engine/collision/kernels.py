"""Compiled scalar helpers shared by the narrow-phase kernels (numba
``@njit(cache=True)``, no fastmath, no parallel; no BLAS: every small
product is written out as a loop or a sum of three terms, in the order the
former numpy code summed it)."""

from __future__ import annotations

import numpy as np
from numba import njit

EPS = 1e-12


@njit(cache=True)
def dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True)
def cross3(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(cache=True)
def clip01(x):
    return min(max(x, 0.0), 1.0)


@njit(cache=True)
def segment_segment(p0, p1, q0, q1, pa, pb):
    """Closest points pa, pb (3,) (written in place) between segments
    [p0, p1] and [q0, q1] (Ericson 5.1.9)."""
    d1 = np.empty(3)
    d2 = np.empty(3)
    r = np.empty(3)
    for i in range(3):
        d1[i] = p1[i] - p0[i]
        d2[i] = q1[i] - q0[i]
        r[i] = p0[i] - q0[i]
    a = dot3(d1, d1)
    e = dot3(d2, d2)
    f = dot3(d2, r)
    c = dot3(d1, r)
    b = dot3(d1, d2)
    denom = a * e - b * b
    s = 0.0
    if denom > EPS * max(a * e, EPS):
        s = clip01((b * f - c * e) / denom)
    t = (b * s + f) / e if e > EPS else 0.0
    if t < 0.0:
        t = 0.0
        s = clip01(-c / a if a > EPS else 0.0)
    elif t > 1.0:
        t = 1.0
        s = clip01((b - c) / a if a > EPS else 0.0)
    for i in range(3):
        pa[i] = p0[i] + d1[i] * s
        pb[i] = q0[i] + d2[i] * t
