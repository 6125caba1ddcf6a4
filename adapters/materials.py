"""Material factors: per-object (or per-material) values whose pairwise
combination gives the scene's pair coefficients.  Bullet and Chipmunk both
combine two shapes' restitution and friction by a product, so pybullet
(:func:`per_object_factors`, one value per body and static) and pymunk
(:func:`per_material_factors`, one value per material) solve the same
problem here, with the same solver; Bullet's rolling friction rule
r_a f_b + r_b f_a has its own solver.  Pinned by
tests/test_adapter_pybullet.py (the solvers) and tests/test_adapter_pymunk.py
(per-shape values vs the pre_solve fallback).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from physbench.contract.scene import Material, Scene

#: relative residual above which a per-object product solve counts as failed
OBJECT_TOLERANCE = 1e-9
#: relative tolerance for accepting per-material values (sqrt(v)**2 may
#: differ from v by an ulp)
MATERIAL_RTOL = 1e-12


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


@dataclass
class ObjectFactors:
    """Per-object values (bodies, then statics; (n_bodies + n_statics,))
    whose engine combinations give the scene's pairs, with what could not be
    realised as notes and the residuals as info entries."""

    restitution: np.ndarray
    friction: np.ndarray
    rolling: np.ndarray
    notes: list[str] = field(default_factory=list)
    info: dict = field(default_factory=dict)


def per_object_factors(scene: Scene, engine: str, max_combined: float) -> ObjectFactors:
    """Bullet's problem: per-object restitution and friction whose products,
    and rolling friction whose r_a f_b + r_b f_a, give every contact pair of
    ``scene``; combined friction above ``max_combined`` is clamped by the
    engine (noted)."""
    nb = scene.n_bodies
    pairs = scene.contact_pairs()

    def obj(kind: str, i: int) -> int:
        return i if kind == "body" else nb + i

    def pair_values(attr: str) -> list[tuple[int, int, float]]:
        return [(obj(ka, ia), obj(kb, ib), getattr(m, attr)) for ka, ia, kb, ib, m in pairs]

    rest_pairs, fric_pairs, roll_pairs = (pair_values(a) for a in ("restitution", "friction", "rolling_friction"))
    names = [b.name for b in scene.bodies] + [s.name for s in scene.statics]
    e, e_err, e_worst = solve_product_values(len(names), rest_pairs)
    f, f_err, f_worst = solve_product_values(len(names), fric_pairs)
    r, r_err, r_worst = solve_rolling_values(f, roll_pairs)
    out = ObjectFactors(e, f, r)
    residual = {"restitution": e_err, "friction": f_err, "rolling_friction": r_err}
    out.info["material_residual"] = max(residual.values())
    out.info["material_residuals"] = residual
    for what, err, worst in (("restitution", e_err, e_worst), ("friction", f_err, f_worst),
                             ("rolling_friction", r_err, r_worst)):
        if err > OBJECT_TOLERANCE and worst is not None:
            a, b, want, got = worst
            rule = "r_a f_b + r_b f_a" if what == "rolling_friction" else "the product of the two objects' values"
            out.notes.append(
                f"{engine} cannot realise the spec's {what} pairs: it combines two objects by {rule}; "
                f"worst pair {names[a]}|{names[b]} wants {want:g}, gets {got:g} (relative error {err:.3g})")
    for what, pp in (("friction", fric_pairs), ("rolling_friction", roll_pairs)):
        combined = (lambda a, b: r[a] * f[b] + r[b] * f[a]) if what == "rolling_friction" else (lambda a, b: f[a] * f[b])
        over = [(a, b) for a, b, _ in pp if combined(a, b) > max_combined]
        if over:
            a, b = over[0]
            out.notes.append(f"Bullet clamps combined {what} to {max_combined:g}; pair {names[a]}|{names[b]} asks for more")
    if scene.has("friction"):
        diff = [(m.static_friction, m.friction) for *_, m in pairs if m.static_friction != m.friction]
        if diff:
            out.notes.append(
                f"{engine} has one Coulomb coefficient per contact: the kinetic friction is used for static "
                f"friction too (spec asks static {diff[0][0]:g}, kinetic {diff[0][1]:g})")
    out.info["per_object_restitution"] = dict(zip(names, map(float, e)))
    out.info["per_object_friction"] = dict(zip(names, map(float, f)))
    if scene.has("rolling_friction"):
        out.info["per_object_rolling_friction"] = dict(zip(names, map(float, r)))
    return out


@dataclass
class MaterialFactors:
    """Per-material elasticity and friction whose products give every pair
    (``per_shape``), or None for both when no such values exist; ``pairs``
    holds each touching material pair's values either way."""

    elasticity: dict[str, float] | None
    friction: dict[str, float] | None
    pairs: dict[tuple[str, str], Material]
    notes: list[str] = field(default_factory=list)

    @property
    def per_shape(self) -> bool:
        return self.elasticity is not None and self.friction is not None


def per_material_factors(scene: Scene, body_materials: list[str], static_materials: list[str],
                         engine: str) -> MaterialFactors | None:
    """Chipmunk's problem: per-material elasticity and friction whose
    products give every material pair that can touch (a material meets
    itself only when two bodies carry it; statics never touch statics).
    ``body_materials`` has one entry per body with a shape.  None when no
    pair can touch."""
    counts: dict[str, int] = {}
    for m in body_materials:
        counts[m] = counts.get(m, 0) + 1
    bodies, statics = sorted(counts), sorted(set(static_materials))
    keys: set[tuple[str, str]] = set()
    for i, a in enumerate(bodies):
        if counts[a] >= 2:
            keys.add((a, a))
        keys.update((a, b) for b in bodies[i + 1:])
        keys.update(tuple(sorted((a, s))) for s in statics)  # type: ignore[misc]
    if not keys:
        return None
    pairs = {p: scene.pair(*p) for p in keys}
    notes = []
    if scene.has("friction") and any(v.static_friction != v.friction for v in pairs.values()):
        notes.append(f"friction: {engine} has one Coulomb coefficient; the kinetic value is used for "
                     "sticking too (static_friction differs from friction in this scene)")
    e = solve_pair_products({p: v.restitution for p, v in pairs.items()}, MATERIAL_RTOL)
    f = solve_pair_products({p: v.friction for p, v in pairs.items()}, MATERIAL_RTOL)
    if e is None or f is None:
        e = f = None
    return MaterialFactors(e, f, pairs, notes)
