"""Metrics, computed from recorded states and scene geometry by the same code
for every engine.  Metric names are part of the interface (DESIGN.md).

Definitions (all from the trace, never from an engine's own accounting):

- ``max_penetration`` / ``mean_penetration`` (m): the deepest overlap between
  any two shapes over the run / the mean of each frame's deepest overlap over
  the frames where something overlaps (0 if nothing ever does).  Measured by
  :mod:`contract.geometry` (depth = the shortest move that separates the two
  shapes); ``penetration_unknown_frames`` counts frames where some pair could
  not be measured.  NaN without the ``contact`` effect (shapes are
  meant to pass through each other then).
- Energy (docs/METRICS.md has the full statement): E = translational +
  rotational kinetic + gravitational + spring potential energy, the
  potential measured from a datum the scene fixes (:func:`energy_datum`),
  so E0 = E(first frame) is the same number on every engine for the same
  initial state.  E_scale = max(|E0|, sum m |g| r + 1e-12), r each body's
  bounding radius.  ``energy_drift`` = max_t |E(t) - E0| / E_scale where the
  scene is conservative (:func:`contract.metric_defs.dissipation` is empty),
  NaN otherwise; ``energy_dissipated`` = (E0 - E(T)) / E_scale where it is
  not, NaN otherwise; ``energy_gain`` = max(0, max_t (E(t) - E0) / E_scale)
  always.
- ``linear_momentum_drift`` = max_t |P(t) - P0| / max(|P0|, sum m |v0|) where
  no external force acts (no gravity, no contact with statics, no world
  springs, no drag); NaN otherwise.  ``angular_momentum_drift`` likewise for L
  about the system's centre of mass; uniform gravity exerts no torque about the
  centre of mass, so gravity alone does not make it NaN.
- ``stable``: every recorded value finite, ``energy_gain`` <= 0.5 and the
  largest speed <= 100 x the scene's speed scale (max of 1 m/s, the initial
  speeds and the free-fall speed over the scene's height span).
- Reference metrics come from the scene's ``[reference]`` model
  (:mod:`harness.references`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.contract.rotation import quat_rotate
from physbench.contract.metric_defs import dissipation, external_force_free
from physbench.contract.scene import Scene
from physbench.harness.joints import held_lowest_height, joint_metrics

STABLE_MAX_ENERGY_GAIN = 0.5
STABLE_SPEED_FACTOR = 100.0


def _body_frame(q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """World angular velocities (..., 3) -> body frame, with q (..., 4) wxyz."""
    qc = q * np.array([1.0, -1.0, -1.0, -1.0])
    return quat_rotate(qc, w)


def kinetic_energy(scene: Scene, trace) -> tuple[np.ndarray, np.ndarray]:
    """(translational (F,), rotational (F,)) kinetic energy in J."""
    m = scene.masses
    inertia = scene.inertias
    trans = 0.5 * np.einsum("i,fij,fij->f", m, trace.vel, trace.vel)
    wb = _body_frame(trace.quat, trace.angvel)
    rot = 0.5 * np.einsum("ij,fij->f", inertia, wb * wb)
    return trans, rot


def energy_series(scene: Scene, trace, datum: bool = True) -> np.ndarray:
    """Total mechanical energy E (J, (F,)): translational and rotational
    kinetic (:func:`kinetic_energy`) plus gravitational and spring
    potential (:func:`potential_energy`), above the scene's datum (or,
    ``datum=False``, from height 0).  The one definition the energy
    metrics, the trace's energy plot and the models' energy lines use
    (tests/test_trace_rrd.py::test_energy_series_is_the_metrics_definition,
    tests/test_trace_predictions.py::test_break_conserved_momentum_and_energy_lines)."""
    trans, rot = kinetic_energy(scene, trace)
    return trans + rot + potential_energy(scene, trace, datum)


def potential_energy(scene: Scene, trace, datum: bool = True) -> np.ndarray:
    """Gravitational plus spring energy (J, (F,)) above the scene's datum
    :func:`energy_datum` (``datum=False``: gravitational from height 0)."""
    g = scene.gravity
    gn = float(np.linalg.norm(g))
    F = trace.pos.shape[0]
    pe = np.full(F, -energy_datum(scene) if datum else 0.0)
    if gn > 0:
        pe += gn * (trace.pos @ (-g / gn)) @ scene.masses
    for sp in scene.springs:
        pa = _anchor_world(trace, sp.a, sp.anchor_a)
        pb = _anchor_world(trace, sp.b, sp.anchor_b)
        ext = np.linalg.norm(pb - pa, axis=-1) - sp.rest_length
        pe += 0.5 * sp.stiffness * ext * ext
    return pe


def lowest_height(scene: Scene, body) -> float:
    """The lowest height (m, along -g) body ``body``'s centre can reach, from
    the scene alone: resting on a level plane beneath it (plane height +
    the body's smallest half-size); on an inclined plane beneath it, its
    start lowered by the slide a frictionless plane allows in the scene's
    duration T, sin a (|v0| T + g sin a T^2 / 2); with several planes
    beneath it the highest of these; with none, where free fall from its
    initial state takes it within T; held by a joint to the world, no lower
    than the joint lets it (harness.joints.held_lowest_height).  Never above
    the start."""
    g = scene.gravity
    gn = float(np.linalg.norm(g))
    up = -g / gn
    h0 = float(body.position @ up)
    T = scene.duration
    v_up = float(body.velocity @ up)
    low = h0 + min(0.0, v_up * T - 0.5 * gn * T * T)  # free fall
    held = held_lowest_height(scene, body, up)  # a joint to the world holds it up
    if held is not None:
        low = max(low, held)
    if scene.has("contact"):
        bounds = []
        for s in scene.statics:
            if s.shape != "plane":
                continue
            c = float(s.normal @ up)  # cos of the plane's incline
            if c <= 1e-12 or float(s.normal @ body.position) < s.offset:
                continue  # a wall or a ceiling, or the body is not above it
            if c >= 1.0 - 1e-12:
                bounds.append(s.offset / c + body.min_extent)
            else:
                sin_a = math.sqrt(max(0.0, 1.0 - c * c))
                speed = float(np.linalg.norm(body.velocity))
                bounds.append(h0 - sin_a * (speed * T + 0.5 * gn * sin_a * T * T))
        if bounds:
            low = max(bounds)
    return min(low, h0)


def energy_datum(scene: Scene) -> float:
    """The potential energy (J) the scene calls zero: sum over bodies of
    m |g| lowest_height (:func:`lowest_height`), except for bodies that
    springs connect to the world (directly or through other bodies): for
    those the minimum over their centre positions (orientations as at the
    start) of their gravitational plus spring energy, the static
    equilibrium of that cluster.  A function of the scene only, so every
    engine measures from the same datum (tests/test_metrics.py pins it)."""
    key = id(scene)
    hit = _DATUM.get(key)
    if hit is not None and hit[0] is scene:
        return hit[1]
    value = _energy_datum(scene)
    if len(_DATUM) > 64:
        _DATUM.clear()
    _DATUM[key] = (scene, value)
    return value


_DATUM: dict[int, tuple[Scene, float]] = {}


def _energy_datum(scene: Scene) -> float:
    g = scene.gravity
    gn = float(np.linalg.norm(g))
    n = scene.n_bodies
    # bodies linked by springs, and whether each cluster hangs from the world
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for sp in scene.springs:
        if sp.a >= 0 and sp.b >= 0:
            parent[find(sp.a)] = find(sp.b)
    held = {find(i) for sp in scene.springs for i in (sp.a, sp.b) if i >= 0 and (sp.a < 0 or sp.b < 0)}
    hung = [i for i in range(n) if find(i) in held]
    total = 0.0
    if gn > 0:
        total += sum(b.mass * gn * lowest_height(scene, b) for b in scene.bodies if b.index not in set(hung))
    if hung:
        total += _spring_equilibrium(scene, hung)
    return total


def _spring_equilibrium(scene: Scene, idx: list[int]) -> float:
    """Minimum over the centres of bodies ``idx`` (orientations fixed at the
    start, the other bodies where they start) of their gravitational plus
    every touching spring's energy (J)."""
    from scipy.optimize import minimize

    g = scene.gravity
    m = scene.masses[idx]
    x0, q0, _, _ = scene.initial_state()
    pos_of = {i: k for k, i in enumerate(idx)}
    springs = [sp for sp in scene.springs if sp.a in pos_of or sp.b in pos_of]
    arms = {}
    for sp in springs:
        for i, anc in ((sp.a, sp.anchor_a), (sp.b, sp.anchor_b)):
            if i >= 0:
                arms[(id(sp), i)] = quat_rotate(q0[i], anc)

    def end(sp, i, anc, X):
        if i < 0:
            return anc
        base = X[pos_of[i]] if i in pos_of else x0[i]
        return base + arms[(id(sp), i)]

    def f(flat):
        X = flat.reshape(-1, 3)
        U = -float(m @ (X @ g))
        grad = -np.outer(m, g)
        for sp in springs:
            d = end(sp, sp.b, sp.anchor_b, X) - end(sp, sp.a, sp.anchor_a, X)
            L = float(np.linalg.norm(d))
            ext = L - sp.rest_length
            U += 0.5 * sp.stiffness * ext * ext
            if L > 1e-300:
                dU = sp.stiffness * ext * d / L  # dU/d(p_b)
                if sp.b in pos_of:
                    grad[pos_of[sp.b]] += dU
                if sp.a in pos_of:
                    grad[pos_of[sp.a]] -= dU
        return U, grad.ravel()

    start = x0[idx].ravel()
    res = minimize(f, start, jac=True, method="BFGS", options={"gtol": 1e-12, "maxiter": 10000})
    return float(min(res.fun, f(start)[0]))


def _anchor_world(trace, idx: int, anchor: np.ndarray) -> np.ndarray:
    if idx < 0:
        return np.broadcast_to(anchor, (trace.pos.shape[0], 3))
    return trace.pos[:, idx] + quat_rotate(trace.quat[:, idx], anchor)


def momenta(scene: Scene, trace) -> tuple[np.ndarray, np.ndarray]:
    """Total linear momentum P (F, 3) and angular momentum L (F, 3) about the
    system's centre of mass (spin + orbital)."""
    m = scene.masses
    P = np.einsum("i,fij->fj", m, trace.vel)
    M = m.sum()
    xc = np.einsum("i,fij->fj", m, trace.pos) / M
    vc = P / M
    r = trace.pos - xc[:, None, :]
    u = trace.vel - vc[:, None, :]
    orbital = np.einsum("i,fij->fj", m, np.cross(r, u))
    wb = _body_frame(trace.quat, trace.angvel)
    Lb = wb * scene.inertias[None, :, :]
    spin = quat_rotate(trace.quat, Lb).sum(axis=1)
    return P, orbital + spin


def relative_energy(scene: Scene, trace) -> tuple[np.ndarray, np.ndarray, float]:
    """(dE (F,) = (E(t) - E0) / E_scale, E (F,) J, E_scale (J)), E0 = E[0]: the energy
    metrics' running form.  ``energy_drift`` is max |dE| (conservative
    scenes), ``energy_gain`` max(0, max dE), ``energy_dissipated`` -dE at
    the last frame (module docstring; the trace's crossing markers use it
    per frame: tests/test_trace_diagnose.py)."""
    E = energy_series(scene, trace)
    E0 = float(E[0])
    gn = float(np.linalg.norm(scene.gravity))
    floor = float(sum(b.mass * gn * b.bounding_radius for b in scene.bodies)) + 1e-12
    scale = max(abs(E0), floor)
    return (E - E0) / scale, E, scale


def momentum_drift_series(scene: Scene, trace) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Running linear and angular momentum drift, (F,) each: |P(t) - P0| /
    max(|P0|, sum m |v0|) and |L(t) - L0| / max(|L0|, sum |I w0| + sum m
    |r0 x v0|) (L about the centre of mass); None where the metric is NaN
    (an external force or torque acts: module docstring).  Their maxima
    are ``linear_momentum_drift`` and ``angular_momentum_drift``."""
    lin_ok, ang_ok = external_force_free(scene)
    if not (lin_ok or ang_ok):
        return None, None
    P, L = momenta(scene, trace)
    m = scene.masses
    lin = ang = None
    if lin_ok:
        denom = max(float(np.linalg.norm(P[0])), float(m @ np.linalg.norm(trace.vel[0], axis=1)), 1e-300)
        lin = np.linalg.norm(P - P[0], axis=1) / denom
    if ang_ok:
        spin0 = np.abs(scene.inertias * _body_frame(trace.quat[0], trace.angvel[0])).sum()
        xc = m @ trace.pos[0] / m.sum()
        orb0 = float((m * np.linalg.norm(np.cross(trace.pos[0] - xc, trace.vel[0]), axis=1)).sum())
        denom = max(float(np.linalg.norm(L[0])), float(spin0) + orb0, 1e-300)
        ang = np.linalg.norm(L - L[0], axis=1) / denom if denom > 1e-300 else np.zeros(L.shape[0])
    return lin, ang


def run_penetration(scene: Scene, trace) -> Any:
    """The penetration measurement :func:`compute_metrics` reads: a
    contract.geometry.Penetration of the trace's frames for a scene with the
    ``contact`` effect, bodies and frames; None otherwise."""
    if not scene.has("contact") or scene.n_bodies == 0 or trace.pos.shape[0] == 0:
        return None
    from physbench.contract.geometry import measure_penetration

    return measure_penetration(scene, trace)


def compute_metrics(scene: Scene, trace, dt: float | None = None, model: bool = True,
                    pen: Any = None, refined: Any = None) -> dict[str, Any]:
    """Every generic metric plus, when ``model``, the reference model's, for
    one run.  ``model=False`` is for callers whose criterion reads no model
    metric (a breaking-point evaluation: harness/limit_eval.py); the model's
    metrics are then absent, never NaN-filled or guessed.  ``pen``: the
    trace's :func:`run_penetration` when the caller has measured it (the
    runner does, and hands it to the trace writer); measured here
    otherwise.  ``refined``: the traces of the reference runs a
    self-consistency model asked for (harness.runner._refined_runs), or why
    they are missing.  The trace is only read
    (tests/test_metrics.py::test_compute_metrics_reads_its_trace_only)."""
    out: dict[str, Any] = {}
    finite = bool(np.isfinite(trace.pos).all() and np.isfinite(trace.vel).all()
                  and np.isfinite(trace.quat).all() and np.isfinite(trace.angvel).all())
    n = scene.n_bodies
    if n == 0 or trace.pos.shape[0] == 0:
        return {"stable": finite}

    # --- penetration
    if scene.has("contact"):
        if pen is None:
            pen = run_penetration(scene, trace)
        per_frame = pen.frame_max()  # (F,) deepest known overlap, 0 where none
        unknown = pen.unknown()
        out["max_penetration"] = float(per_frame.max(initial=0.0))
        touching = per_frame > 0
        out["mean_penetration"] = float(per_frame[touching].mean()) if touching.any() else 0.0
        # frames where some pair's depth could not be measured (a non-finite
        # pose, a shape pair without a kernel): said, never counted as 0
        out["penetration_unknown_frames"] = int(unknown.sum())
    else:
        out["max_penetration"] = math.nan
        out["mean_penetration"] = math.nan

    # --- energy (datum, scale and split: docs/METRICS.md)
    dE, E, scale = relative_energy(scene, trace)
    E0 = float(E[0])
    gn = float(np.linalg.norm(scene.gravity))
    conservative = not dissipation(scene)
    with np.errstate(invalid="ignore"):
        out["energy_drift"] = float(np.nanmax(np.abs(dE))) if conservative else math.nan
        out["energy_dissipated"] = math.nan if conservative else float(-dE[-1])
        out["energy_gain"] = max(0.0, float(np.nanmax(dE)))
    out["energy_final"] = float(E[-1])
    out["energy_initial"] = E0

    # --- momentum
    lin, ang = momentum_drift_series(scene, trace)
    out["linear_momentum_drift"] = math.nan if lin is None else float(np.nanmax(lin))
    out["angular_momentum_drift"] = math.nan if ang is None else float(np.nanmax(ang))

    # --- stability
    speeds = np.linalg.norm(trace.vel, axis=-1)
    v0 = float(np.max(np.linalg.norm(trace.vel[0], axis=1), initial=0.0))
    w0 = float(np.max(np.linalg.norm(trace.angvel[0], axis=1), initial=0.0))
    span = float(np.ptp(trace.pos[..., 2])) if finite else 0.0
    v_scale = max(1.0, v0, math.sqrt(2 * gn * max(span, 0.0)))
    w_scale = max(1.0, w0, v_scale / max(min(b.min_extent for b in scene.bodies), 1e-6))
    vmax = float(np.nanmax(speeds)) if speeds.size else 0.0
    wmax = float(np.nanmax(np.linalg.norm(trace.angvel, axis=-1)))
    reasons = []
    if not finite:
        reasons.append("non-finite state")
    if out["energy_gain"] > STABLE_MAX_ENERGY_GAIN or not math.isfinite(out["energy_gain"]):
        reasons.append(f"energy gain {out['energy_gain']:.3g} > {STABLE_MAX_ENERGY_GAIN}")
    if vmax > STABLE_SPEED_FACTOR * v_scale:
        reasons.append(f"speed {vmax:.3g} m/s > {STABLE_SPEED_FACTOR:g} x {v_scale:.3g}")
    if wmax > STABLE_SPEED_FACTOR * w_scale:
        reasons.append(f"angular speed {wmax:.3g} rad/s > {STABLE_SPEED_FACTOR:g} x {w_scale:.3g}")
    out["stable"] = not reasons
    out["stability_reason"] = "; ".join(reasons)
    out["max_speed"] = vmax
    out.update(joint_metrics(scene, trace))  # {} without joints (harness/joints.py)

    # --- reference model
    if model and scene.reference_model:
        from physbench.harness.references import UNDEFINED, get_model

        ref = get_model(scene.reference_model)(scene)
        if refined is not None:
            ref.refined = refined
        got = ref.metrics(trace)
        why = [w for w in (out.pop(UNDEFINED, ""), got.pop(UNDEFINED, "")) if w]
        out.update(got)
        if why:
            out[UNDEFINED] = "; ".join(why)
    return out
