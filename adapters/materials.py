"""Material factors: per-object (or per-material) values whose pairwise
combination gives the scene's pair coefficients.  Bullet and Chipmunk both
combine two shapes' restitution and friction by a product, so pybullet and
pymunk solve the same problem here; Bullet's rolling friction rule
r_a f_b + r_b f_a has its own solver.  Pinned by
tests/test_adapter_pybullet.py (the solvers) and tests/test_adapter_pymunk.py
(per-shape values vs the pre_solve fallback).
"""

from __future__ import annotations

import math

import numpy as np




def solve_product_values(n_objects: int, pairs: list[tuple[int, int, float]]) -> tuple[np.ndarray, float, tuple[int, int, float, float] | None]:
    """Per-object values x (n_objects,) >= 0 with x[a] * x[b] = v for every
    pair (a, b, v), as Bullet multiplies two objects' restitution or friction.

    - All pairs want the same v: x = sqrt(v) for every object in a pair (exact).
    - Otherwise: objects whose every pair wants 0 get x = 0 (that realises all
      their pairs); the other objects solve log x_a + log x_b = log v over
      their pairs wanting v > 0 by least squares (minimum norm).  A pair
      wanting 0 between two objects that also have positive pairs cannot be
      realised.
    - Objects in no pair get 0 (they never touch anything).

    Returns (x, worst relative error, worst pair as (a, b, wanted, got) or
    None).  The relative error of a pair is |x_a x_b - v| / v, and the
    absolute product when v = 0.
    """
    x = np.zeros(n_objects)
    if not pairs:
        return x, 0.0, None
    values = np.array([v for _, _, v in pairs], float)
    if np.any(values < 0):
        raise ValueError("pair values must be >= 0")
    involved = sorted({a for a, _, _ in pairs} | {b for _, b, _ in pairs})
    if np.all(values == values[0]):
        x[involved] = math.sqrt(values[0])
    else:
        positive: dict[int, bool] = {}
        for a, b, v in pairs:
            for o in (a, b):
                positive[o] = positive.get(o, False) or v > 0
        free = [o for o in involved if positive[o]]  # objects with a pair wanting > 0
        col = {o: k for k, o in enumerate(free)}
        rows = [(a, b, v) for a, b, v in pairs if v > 0]
        if rows:
            A = np.zeros((len(rows), len(free)))
            rhs = np.empty(len(rows))
            for r, (a, b, v) in enumerate(rows):
                A[r, col[a]] += 1.0
                A[r, col[b]] += 1.0
                rhs[r] = math.log(v)
            y, *_ = np.linalg.lstsq(A, rhs, rcond=None)
            x[free] = np.exp(y)
    worst, worst_pair = 0.0, None
    for a, b, v in pairs:
        got = float(x[a] * x[b])
        err = abs(got - v) / v if v > 0 else abs(got)
        if err > worst:
            worst, worst_pair = err, (a, b, float(v), got)
    return x, worst, worst_pair


def solve_rolling_values(friction: np.ndarray, pairs: list[tuple[int, int, float]]) -> tuple[np.ndarray, float, tuple[int, int, float, float] | None]:
    """Per-object rolling friction r >= 0 (m) with r_a f_b + r_b f_a = R for
    every pair (a, b, R), Bullet's rule, given the per-object (lateral)
    friction f.  Non-negative least squares; returns (r, worst relative
    error, worst pair) like :func:`solve_product_values`."""
    r = np.zeros(len(friction))
    if not pairs or all(v == 0 for _, _, v in pairs):
        return r, 0.0, None
    involved = sorted({a for a, _, _ in pairs} | {b for _, b, _ in pairs})
    col = {o: k for k, o in enumerate(involved)}
    A = np.zeros((len(pairs), len(involved)))
    rhs = np.array([v for _, _, v in pairs], float)
    for k, (a, b, _) in enumerate(pairs):
        A[k, col[a]] += friction[b]
        A[k, col[b]] += friction[a]
    from scipy.optimize import nnls

    sol, _ = nnls(A, rhs)
    r[involved] = sol
    worst, worst_pair = 0.0, None
    for a, b, v in pairs:
        got = float(r[a] * friction[b] + r[b] * friction[a])
        err = abs(got - v) / v if v > 0 else abs(got)
        if err > worst:
            worst, worst_pair = err, (a, b, float(v), got)
    return r, worst, worst_pair


def solve_pair_products(pairs: dict[tuple[str, str], float], rtol: float) -> dict[str, float] | None:
    """Per-material values f >= 0 with f[a] * f[b] == v for every pair
    (a, b) -> v (within ``rtol`` relative, absolute below 1), or None if
    :func:`solve_product_values` finds no such values.  A self pair (a, a)
    gets f[a] = sqrt(v) exactly.  When all pairs agree this gives sqrt(v)
    for every material."""
    mats = sorted({m for p in pairs for m in p})
    idx = {m: k for k, m in enumerate(mats)}
    x, _, _ = solve_product_values(len(mats), [(idx[a], idx[b], v) for (a, b), v in sorted(pairs.items())])
    f = {m: float(x[k]) for m, k in idx.items()}
    for (a, b), v in pairs.items():
        if a == b and v > 0.0:
            f[a] = math.sqrt(v)
    for (a, b), v in pairs.items():
        if abs(f[a] * f[b] - v) > rtol * max(1.0, abs(v)):
            return None
    return f
