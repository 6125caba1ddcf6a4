"""Step phase: run a scene with its steps falling at other instants of the
same motion.

A discrete engine samples a motion at t = 0, dt, 2 dt, ...  Whether a fast
body is caught by a thin wall, or which step lands a falling box, depends on
where those instants fall relative to the event -- the *phase* of the steps.
One run per dt is one draw of that phase (docs/ENGINE_FINDINGS.md: a plate
tunnels in 1 - 3 mm / (v dt) of phases on an engine without a working guard,
so a pass at one dt and a fail at the next can both be luck).

:func:`shift_scene` moves the start of a scene back along its exact free
flight by tau = f dt (0 <= f < 1): every body starts where and how it was
tau seconds earlier, so the continuous motion is unchanged and the steps fall
f dt earlier along it.  f = 0 is the scene as written.  Sweeping f over
i / N gives N draws, and the fraction that fails estimates the probability
of failure over phases (``physbench sweep``: a ``[[sweep]]`` block's
``phases = N``; the report's phase table).

Exact, and therefore allowed, only when the start is free flight:

- the effects are among gravity, contact, restitution, friction,
  rolling_friction and gyroscopic (no drag, springs or dampers: they act in
  free flight and their backward motion is not closed-form here), and
- no body can touch anything between -tau and 0: along its backward path
  its bounding sphere (which rotation about the centre never leaves) stays
  clear of every static and every other body.

Backward free flight: x(-tau) = x0 - v0 tau + g tau^2 / 2, v(-tau) = v0 - g tau;
rotation: the world-frame angular velocity is constant without the
gyroscopic effect (that is the scene's physics then), q(-tau) =
exp(-w tau) q0; with it, the torque-free Euler equations are integrated back
over tau (fixed-step Runge-Kutta: the same bits on every CPU), which for a spin about a principal axis or an
isotropic body is the same constant rotation.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from physbench.contract.rotation import (body_to_world_angvel, dot, norm, quat_exp, quat_mul, rotation_matrix,
                                         world_to_body_angvel)

#: effects under which the motion before t = 0 is free flight with a
#: closed form (contacts are ruled out by the clearance test)
FREE_FLIGHT_EFFECTS = frozenset({"gravity", "contact", "restitution", "friction", "rolling_friction", "gyroscopic"})


class PhaseError(ValueError):
    """The scene's start is not free flight, so it cannot be phase-shifted."""


#: the torque-free integration's steps: at most this much rotation (rad) of
#: the attitude or of the body-frame angular velocity per step of the
#: classical Runge-Kutta scheme (local error ~ (rate h)^5 / 120): the
#: backward start agrees with scipy's DOP853 at rtol 1e-13 within 1e-11
#: (tests/test_phase.py::test_the_torque_free_backward_flight_matches_an_adaptive_solver)
_RK_TURN = 1e-3


def _euler_rhs(y: tuple[float, ...], I: tuple[float, float, float]) -> tuple[float, ...]:
    """d/dt of (q wxyz, w body) of a torque-free body with principal
    moments ``I``: q' = q (0, w) / 2, I w' = -w x I w; Python floats."""
    qw, qx, qy, qz, a, b, c = y
    Ia, Ib, Ic = I
    return (0.5 * (-qx * a - qy * b - qz * c), 0.5 * (qw * a + qy * c - qz * b),
            0.5 * (qw * b - qx * c + qz * a), 0.5 * (qw * c + qx * b - qy * a),
            (Ib - Ic) * b * c / Ia, (Ic - Ia) * c * a / Ib, (Ia - Ib) * a * b / Ic)


def _torque_free_back(q0: np.ndarray, w0: np.ndarray, inertia: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """(q, w world) of a torque-free body tau seconds before (q0, w0 world),
    principal moments ``inertia`` (3,).  Classical Runge-Kutta over equal
    steps of at most :data:`_RK_TURN` rad, in Python floats summed in a
    fixed order: no BLAS call and no adaptive step, so the start is the same
    to the bit on every CPU (tests/test_engine_blas_free.py)."""
    q0 = np.asarray(q0, float) / norm(q0)
    wb0 = world_to_body_angvel(q0, np.asarray(w0, float))
    Lb = np.asarray(inertia, float) * wb0
    if norm(np.cross(wb0, Lb)) <= 1e-12 * (norm(wb0) * norm(Lb) + 1e-300):
        # steady rotation (isotropic, or about a principal axis): w constant in the world
        return quat_mul(quat_exp(-np.asarray(w0, float) * tau), q0), np.asarray(w0, float).copy()
    I = tuple(float(v) for v in inertia)
    # the body-frame rates: |w| for the attitude, up to |w| |I_j - I_k| / I_i
    # for w itself (Euler's equations)
    rate = norm(wb0) * max(1.0, abs(I[1] - I[2]) / I[0], abs(I[2] - I[0]) / I[1], abs(I[0] - I[1]) / I[2])
    n = max(16, math.ceil(rate * tau / _RK_TURN))
    h = -tau / n
    y = tuple(float(v) for v in q0) + tuple(float(v) for v in wb0)
    for _ in range(n):
        k1 = _euler_rhs(y, I)
        k2 = _euler_rhs(tuple(a + 0.5 * h * b for a, b in zip(y, k1)), I)
        k3 = _euler_rhs(tuple(a + 0.5 * h * b for a, b in zip(y, k2)), I)
        k4 = _euler_rhs(tuple(a + h * b for a, b in zip(y, k3)), I)
        y = tuple(a + h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4) for a, b1, b2, b3, b4 in zip(y, k1, k2, k3, k4))
    q = np.array(y[:4])
    q = q / norm(q)
    return q, body_to_world_angvel(q, np.array(y[4:]))


def _static_clearance(p: np.ndarray, r: float, s: Any) -> np.ndarray:
    """Distances (m) from spheres (centres p (k, 3), radius r) to static
    ``s`` (negative: overlapping), (k,).  Component by component (no
    BLAS-dispatched product: the same decision on every CPU)."""
    p = np.atleast_2d(np.asarray(p, float))
    if s.shape == "plane":
        n = np.asarray(s.normal, float)
        return p[:, 0] * n[0] + p[:, 1] * n[1] + p[:, 2] * n[2] - s.offset - r
    d = p - np.asarray(s.position, float)
    R = rotation_matrix(s.orientation)
    local = np.stack([d[:, 0] * R[0, i] + d[:, 1] * R[1, i] + d[:, 2] * R[2, i] for i in range(3)], axis=1)  # R^T d
    h = np.asarray(s.half_extents, float)
    e = np.maximum(np.abs(local) - h, 0.0)
    outside = np.sqrt(e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1] + e[:, 2] * e[:, 2])
    inside = -np.min(h - np.abs(local), axis=1)
    return np.where(outside > 0.0, outside, inside) - r


def shift_scene(scene: Any, f: float, dt: float | None = None) -> Any:
    """``scene`` with its start moved back along the exact free flight by
    tau = f dt (``dt``: the run's step, default the scene's).  f = 0 returns
    the scene itself.  Raises PhaseError when the start is not free flight
    (naming the scene and what stands in the way) or f is outside [0, 1)."""
    f = float(f)
    if not (0.0 <= f < 1.0):
        raise PhaseError(f"{scene.id}: phase must be in [0, 1), got {f!r}")
    if f == 0.0:
        return scene
    h = float(scene.dt if dt is None else dt)
    tau = f * h
    extra = sorted(set(scene.effects) - FREE_FLIGHT_EFFECTS)
    if extra:
        raise PhaseError(f"{scene.id}: phase shift needs free flight before t = 0; effect(s) {', '.join(extra)} "
                         f"act in free flight (allowed: {', '.join(sorted(FREE_FLIGHT_EFFECTS))})")
    if scene.springs:
        raise PhaseError(f"{scene.id}: phase shift needs free flight before t = 0; the scene has springs")
    g = np.asarray(scene.gravity, float)
    gyro = scene.has("gyroscopic")
    if scene.has("contact"):
        # the bodies' centres over [-tau, 0], sampled at most 1 mm apart (up
        # to 20001 samples): the distance to a static changes by at most the
        # path length, so between samples it can dip by at most half their
        # spacing below the sampled minimum, and the parabola's chords are off
        # by at most |g| tau^2 / 8 -- both go into the allowance
        slack0 = norm(g) * tau * tau
        for i, b in enumerate(scene.bodies):
            x0, v0 = np.asarray(b.position, float), np.asarray(b.velocity, float)
            length = norm(v0) * tau + slack0
            k = int(min(max(33, math.ceil(length / 1e-3) + 1), 20001))
            s_ = np.linspace(0.0, 1.0, k)[:, None] * tau
            path = x0 - v0 * s_ + 0.5 * g * s_ * s_
            slack = slack0 + 0.5 * length / (k - 1)
            for st in scene.statics:
                gap = float(np.min(_static_clearance(path, b.bounding_radius, st)))
                if gap <= slack:
                    raise PhaseError(f"{scene.id}: phase shift needs free flight before t = 0; body {b.name!r} "
                                     f"comes within {gap:.3g} m of static {st.name!r} over the {tau:.3g} s "
                                     f"before the start")
            for j in range(i + 1, scene.n_bodies):
                c = scene.bodies[j]
                # relative motion is uniform (same gravity): closest approach over the segment
                d0 = x0 - np.asarray(c.position, float)
                dv = v0 - np.asarray(c.velocity, float)
                den = dot(dv, dv) * tau * tau
                u = 0.0 if den == 0 else min(max(dot(d0, dv) * tau / den, 0.0), 1.0)
                gap = norm(d0 - dv * tau * u) - b.bounding_radius - c.bounding_radius
                if gap <= 0.0:
                    raise PhaseError(f"{scene.id}: phase shift needs free flight before t = 0; bodies {b.name!r} "
                                     f"and {c.name!r} come within {gap:.3g} m of each other over the {tau:.3g} s "
                                     f"before the start")
    bodies = []
    for b in scene.bodies:
        x0, v0 = np.asarray(b.position, float), np.asarray(b.velocity, float)
        q0, w0 = np.asarray(b.orientation, float), np.asarray(b.angular_velocity, float)
        if gyro:
            q, w = _torque_free_back(q0, w0, np.asarray(b.inertia, float), tau)
        else:
            q, w = quat_mul(quat_exp(-w0 * tau), q0), w0.copy()
        bodies.append(dataclasses.replace(b, position=x0 - v0 * tau + 0.5 * g * tau * tau, velocity=v0 - g * tau,
                                          orientation=q / norm(q), angular_velocity=w))
    return dataclasses.replace(scene, bodies=tuple(bodies))


def phase_values(n: int) -> tuple[float, ...]:
    """The N phases i / N, i = 0 .. N-1 (0: the scene as written)."""
    if int(n) != n or n < 1:
        raise PhaseError(f"phases must be a positive integer, got {n!r}")
    return tuple(i / int(n) for i in range(int(n)))


def wilson_interval(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """95 % Wilson score interval (lo, hi) of a proportion k / n."""
    if n <= 0:
        return (math.nan, math.nan)
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, mid - half), min(1.0, mid + half))
