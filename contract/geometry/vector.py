"""Small batched vector helpers of the geometry kernels: dot products and
norms over the last axis, a safe unit vector, a perpendicular basis, and a
vectorised golden-section minimisation."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

_INVPHI = (math.sqrt(5.0) - 1.0) / 2.0


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _sq(v: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", v, v)


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(_dot(v, v))


def _unit_or(v: np.ndarray, fallback: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """v / |v| where |v| > eps, else ``fallback`` (a unit vector): any unit
    vector is a valid candidate direction, a zero vector is not."""
    n = _norm(v)[..., None]
    ok = n > eps
    return np.where(ok, v / np.where(ok, n, 1.0), fallback)


def _perp_basis(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (N, 3) completing unit w (N, 3) to a right-handed basis."""
    helper = np.where((np.abs(w[:, 0]) < 0.9)[:, None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    t1 = np.cross(w, helper)
    t1 /= _norm(t1)[:, None]
    return t1, np.cross(w, t1)


def _golden(fn: Callable[[np.ndarray], np.ndarray], lo: np.ndarray, hi: np.ndarray,
            iters: int) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised golden-section minimisation of fn on [lo, hi] (any shape).
    Returns (best value, its argument) over every point evaluated, so the
    result is an upper bound of the bracket's minimum even if fn is not
    unimodal there, and exact (to the final bracket width) if it is."""
    a, b = lo, hi
    x1 = b - _INVPHI * (b - a)
    x2 = a + _INVPHI * (b - a)
    f1, f2 = fn(x1), fn(x2)
    best = np.minimum(f1, f2)
    arg = np.where(f1 <= f2, x1, x2)
    for _ in range(iters):
        left = f1 <= f2  # the minimum lies in [a, x2]
        a = np.where(left, a, x1)
        b = np.where(left, x2, b)
        xn = np.where(left, b - _INVPHI * (b - a), a + _INVPHI * (b - a))
        fnew = fn(xn)
        x1, x2, f1, f2 = (np.where(left, xn, x2), np.where(left, x1, xn),
                          np.where(left, fnew, f2), np.where(left, f1, fnew))
        better = fnew < best
        arg = np.where(better, xn, arg)
        best = np.minimum(best, fnew)
    return best, arg
