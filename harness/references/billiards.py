"""Billiard-type collision references beyond the two-body law.

- ``oblique_collision``: :class:`harness.references.collision.TwoBodyCollision`
  plus ``separation_angle_error``: the angle between the two outgoing velocity
  vectors against the law's (90 degrees for equal masses and e = 1), in
  degrees.
- ``newtons_cradle``: a row of equal spheres along a line, one ball striking
  the row; the independent-collision (sequential) solution.
- ``momentum_energy``: conservation laws for many-body breaks (rack of 15 + cue).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from physbench.harness.metrics import energy_series, kinetic_energy
from physbench.harness.references import (TRAJECTORY, Param, ReferenceError, ReferenceModel, ReferenceSeries, constant,
                                divide, trajectory_metrics)
from physbench.harness.references.collision import TwoBodyCollision


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return math.nan
    c = float(np.clip(a @ b / (na * nb), -1.0, 1.0))
    return math.degrees(math.acos(c))


class ObliqueCollision(TwoBodyCollision):
    """Two-body collision with the angle between the outgoing velocities.

    ``separation_angle_error`` = |angle(v1(T), v2(T)) - angle(v1', v2')| in
    degrees, with v' from Newton's law (equal masses, e = 1: 90 degrees).  NaN
    if either reference outgoing velocity is zero (the angle is undefined).
    """

    name = "oblique_collision"
    summary = "two_body_collision plus the angle between the outgoing velocities"
    produces = {**TwoBodyCollision.produces,
                "separation_angle": "measured angle between the outgoing velocities at the last frame (deg)",
                "separation_angle_error": "|measured - reference| separation angle (deg; NaN if undefined)"}

    def metrics(self, trace) -> dict[str, float]:
        out = super().metrics(trace)
        if self.t_impact is None or trace.t[-1] <= self.t_impact:
            return out
        i, j = self.idx
        ref = _angle_deg(self.v1_post, self.v2_post)
        meas = _angle_deg(trace.vel[-1, i], trace.vel[-1, j])
        out["separation_angle"] = meas
        out["separation_angle_error"] = abs(meas - ref) if math.isfinite(ref) else math.nan
        return out


def sequential_row_collisions(m: np.ndarray, u: np.ndarray, e: float, max_sweeps: int = 100000) -> np.ndarray:
    """Final velocities of a row of touching bodies on a line under the
    independent-collision model: binary collisions by Newton's law, resolved
    pair by pair (sweeping from the struck end) until no touching pair
    approaches.  m (n,) masses, u (n,) velocities along the row (the row is
    ordered so that body i+1 is ahead of body i).  Returns (n,) velocities.

    For e = 1 and equal masses a single striking ball hands its whole velocity
    down the row: the last ball leaves with it, the others stop.
    """
    v = np.array(u, float)
    _resolve_row(v, np.asarray(m, float), e, None, max_sweeps)
    return v


def _resolve_row(v: np.ndarray, m: np.ndarray, e: float, touching: np.ndarray | None, max_sweeps: int) -> bool:
    """Sweep the row from the struck end, resolving each approaching pair
    (of the ``touching`` (n-1,) bool pairs; None: all) by Newton's law in
    place, until none approaches.  Returns whether any pair collided;
    raises after ``max_sweeps`` sweeps."""
    hit = False
    for _ in range(max_sweeps):
        moved = False
        for i in range(len(v) - 1):
            if (touching is None or touching[i]) and v[i] > v[i + 1] + 1e-15 * (abs(v[i]) + abs(v[i + 1])):
                m1, m2 = m[i], m[i + 1]
                a, b = v[i], v[i + 1]
                v[i] = ((m1 - e * m2) * a + (1 + e) * m2 * b) / (m1 + m2)
                v[i + 1] = ((m2 - e * m1) * b + (1 + e) * m1 * a) / (m1 + m2)
                moved = hit = True
        if not moved:
            return hit
    raise RuntimeError("sequential_row_collisions did not converge")


def row_collision_history(gap: np.ndarray, m: np.ndarray, u: np.ndarray, e: float, t_end: float,
                          max_events: int = 10000) -> list[tuple[float, np.ndarray]]:
    """When the independent-collision model's binary collisions happen: the
    row of :func:`sequential_row_collisions` with its gaps, run event by
    event.  gap (n-1,) m between neighbouring surfaces, m (n,), u (n,)
    velocities along the row (body i+1 ahead of body i), e the restitution.
    Returns [(t s, velocities (n,) from t on)], starting with (0, u): at
    each time the touching approaching pairs are resolved by the same sweep
    as :func:`sequential_row_collisions`; then the row flies to the next
    gap that closes.  Events after t_end are left out (a touching row hands
    the strike down at one instant)."""
    v = np.array(u, float)
    m = np.asarray(m, float)
    g = np.array(gap, float)
    tol = 1e-12 * max(float(np.max(np.abs(g), initial=0.0)), 1e-3)
    t, out = 0.0, [(0.0, v.copy())]
    for _ in range(max_events):
        if _resolve_row(v, m, e, g <= tol, 100000):
            if out[-1][0] == t:
                out[-1] = (t, v.copy())
            else:
                out.append((t, v.copy()))
        closing = v[:-1] - v[1:]
        with np.errstate(divide="ignore", invalid="ignore"):
            wait = np.where((closing > 0) & (g > tol), g / closing, np.inf)
        k = int(np.argmin(wait)) if wait.size else 0
        if not wait.size or not np.isfinite(wait[k]) or t + wait[k] > t_end:
            return out
        g = g - closing * wait[k]
        g[k] = 0.0
        t += float(wait[k])
    return out


class NewtonsCradle(ReferenceModel):
    """A row of spheres on one line (the line through the first and last
    centres), one or more of them moving along it; no gravity along the line.

    Collisions are resolved by the independent-collision model (see
    :func:`sequential_row_collisions`): the classical idealisation of a cradle
    of hard steel balls, exact when the balls are separated by small gaps and
    the accepted ideal when they touch.  Metric ``cradle_velocity_error`` =
    max over balls of |v_i(T) - v_i'| / max |v(0)| at the last frame (after
    the collisions); ``trajectory_rmse`` is not defined (the moment each ball
    leaves depends on the contact model) and not reported.
    """

    name = "newtons_cradle"
    summary = "a row of spheres on one line struck along it: the independent-collision (sequential) solution"
    takes = ("spheres with centres on one line, initial velocities along it, one restitution for every pair, "
             "no gravity along the row")
    produces = {"cradle_velocity_error": "max over balls of |v_i(T) - v_i'| / max |v(0)| at the last frame (1)"}
    primary = "cradle_velocity_error"

    def __init__(self, scene):
        super().__init__(scene)
        if scene.n_bodies < 2:
            raise ReferenceError("newtons_cradle needs at least 2 bodies")
        if any(b.shape != "sphere" for b in scene.bodies):
            raise ReferenceError("newtons_cradle needs spheres")
        x0, _, v0, _ = scene.initial_state()
        axis = x0[-1] - x0[0]
        axis /= np.linalg.norm(axis)
        s = x0 @ axis
        order = np.argsort(s)
        perp = (x0 - x0[0]) - np.outer((x0 - x0[0]) @ axis, axis)
        if np.max(np.linalg.norm(perp, axis=1)) > 1e-9:
            raise ReferenceError("newtons_cradle needs the ball centres on one line")
        if np.max(np.linalg.norm(v0 - np.outer(v0 @ axis, axis), axis=1)) > 1e-12:
            raise ReferenceError("newtons_cradle needs initial velocities along the row")
        if abs(scene.gravity @ axis) > 0:
            raise ReferenceError("newtons_cradle needs no gravity along the row")
        mats = {b.material for b in scene.bodies}
        es = {scene.pair(a, b).restitution for a in mats for b in mats}
        if len(es) != 1:
            raise ReferenceError("newtons_cradle needs one restitution for every ball pair")
        self.e = es.pop()
        self.axis = axis
        m = scene.masses[order]
        u = (v0 @ axis)[order]
        vf = sequential_row_collisions(m, u, self.e)
        self.v_final = np.empty(scene.n_bodies)
        self.v_final[order] = vf
        self.v_scale = float(np.max(np.abs(u)))
        if self.v_scale == 0:
            raise ReferenceError("newtons_cradle needs a moving ball")

        self.order = order
        self.m_row, self.u_row = m, u
        self._history = None  # history(): computed once, read per ball's line
        r = np.array([b.radius for b in scene.bodies])[order]
        self.gaps = np.diff(s[order]) - r[:-1] - r[1:]

    def history(self) -> tuple[list[tuple[float, np.ndarray]], bool]:
        """The collisions' timing within the run (:func:`row_collision_history`):
        ([(t s, velocities along the row (n,) in body order from t on)],
        timed).  ``timed`` is False when the timed row ends elsewhere than
        the model's v' (``v_final``; a restitution whose sweeps converge
        differently): then only the start, the first collision and v' from
        the last collision on are drawn."""
        if self._history is not None:
            return self._history
        hist = row_collision_history(self.gaps, self.m_row, self.u_row, self.e, self.scene.duration)
        out = []
        for t, vr in hist:
            v = np.empty_like(vr)
            v[self.order] = vr
            out.append((t, v))
        self._history = out, bool(np.max(np.abs(out[-1][1] - self.v_final)) <= 1e-9 * self.v_scale)
        return self._history

    def row_velocity(self, t: np.ndarray, i: int) -> np.ndarray:
        """Ball i's velocity along the row (m/s) at times t (F,): piecewise
        constant between the collisions of :meth:`history`; NaN between the
        first and the last collision when the timing is not the model's."""
        t = np.asarray(t, float)
        hist, timed = self.history()
        if not timed:
            hist = [hist[0], (hist[1][0], np.full_like(self.v_final, np.nan)), (hist[-1][0], self.v_final)]
        out = np.full(t.shape, np.nan)
        for k, (t0, v) in enumerate(hist):
            t1 = hist[k + 1][0] if k + 1 < len(hist) else np.inf
            out[(t >= t0) & (t < t1)] = v[i]
        return out

    def reference_series(self) -> list[ReferenceSeries]:
        """Each ball's velocity along the row (m/s): v(0) until the strike,
        v' once the collisions have handed it down."""
        ax = self.axis
        return [ReferenceSeries(f"{b.name}/row_velocity", "m/s",
                                f"{b.name} velocity along the row: {self.v_final[b.index]:.6g} m/s after the collisions",
                                lambda t, i=b.index: self.row_velocity(t, i),
                                lambda tr, i=b.index: tr.vel[:, i] @ ax)
                for b in self.scene.bodies]

    def reference_times(self) -> list[tuple[float, str]]:
        hist, _ = self.history()
        if len(hist) < 2:
            return []
        out = [(float(hist[1][0]), "first impact")]
        if hist[-1][0] > hist[1][0]:
            out.append((float(hist[-1][0]), "last collision of the row"))
        return out

    def predictions(self) -> dict[str, str]:
        return {"velocities along the row after the collisions":
                ", ".join(f"{b.name} {self.v_final[b.index]:.6g}" for b in self.scene.bodies) + " m/s"}

    def metrics(self, trace) -> dict[str, float]:
        v_end = trace.vel[-1]  # (n, 3)
        ref = np.outer(self.v_final, self.axis)
        err = np.linalg.norm(v_end - ref, axis=1)
        return {"cradle_velocity_error": float(np.max(err) / self.v_scale)}


class _States(NamedTuple):
    """Body states of k frames: pos (k, n, 3), quat (k, n, 4) wxyz, vel
    (k, n, 3), angvel (k, n, 3): a trace's frames for the metrics' energy."""

    pos: np.ndarray
    quat: np.ndarray
    vel: np.ndarray
    angvel: np.ndarray


class MomentumEnergy(ReferenceModel):
    """Conservation laws for a many-body collision (a break).

    With only frictionless contacts (and gravity normal to a frictionless
    table), the momentum components normal to gravity are conserved exactly,
    whatever the restitution; the mechanical energy (kinetic, rotational and
    gravitational) is conserved for e = 1.  The metrics compare the last frame
    with the first, after all collisions:

    - ``momentum_error`` = |P_h(T) - P_h(0)| / |P_h(0)|, P_h = total momentum
      with its component along gravity removed (all of it without gravity);
    - ``energy_error`` = |E(T) - E(0)| / KE(0): meaningful as a conservation
      check only for e = 1 (for e < 1 it is the energy lost, reported as
      ``energy_loss`` = (E(0) - E(T)) / KE(0) too).
    """

    name = "momentum_energy"
    summary = "conservation laws for a many-body break on a frictionless table"
    takes = ("any bodies with a non-zero momentum normal to gravity; no friction, drag or springs; "
             "statics only a level table plane")
    produces = {
        "momentum_error": "|P_h(T) - P_h(0)| / |P_h(0)|, P_h the momentum normal to gravity (1)",
        "energy_error": "|E(T) - E(0)| / KE(0) (1; a conservation check for e = 1)",
        "energy_loss": "(E(0) - E(T)) / KE(0) (1)",
    }
    primary = "momentum_error"

    def __init__(self, scene):
        super().__init__(scene)
        if scene.has("friction"):
            raise ReferenceError("momentum_energy needs frictionless contacts (no 'friction' effect)")
        if scene.has("drag_linear") or scene.has("drag_quadratic") or scene.springs:
            raise ReferenceError("momentum_energy needs no drag and no springs")
        g = scene.gravity
        gn = float(np.linalg.norm(g))
        self.up = -g / gn if gn > 0 else None
        self.P0 = self._horizontal(scene.masses @ scene.initial_state()[2])
        if np.linalg.norm(self.P0) == 0:
            raise ReferenceError("momentum_energy needs a non-zero initial momentum (normal to gravity)")
        for s in scene.statics:
            if s.shape != "plane" or self.up is None or abs(abs(s.normal @ self.up) - 1) > 1e-12:
                raise ReferenceError("momentum_energy allows only a horizontal table plane as static geometry")

    def _horizontal(self, P: np.ndarray) -> np.ndarray:
        if self.up is None:
            return P
        return P - np.multiply.outer(P @ self.up, self.up)

    def _energy(self, states) -> tuple[np.ndarray, np.ndarray]:
        """(E (J, (k,)), kinetic energy (J, (k,))) of ``states`` (anything
        with pos, quat, vel, angvel of shape (k, n, 3|4)), the metrics'
        definition (harness.metrics.energy_series) with the potential from
        height 0."""
        trans, rot = kinetic_energy(self.scene, states)
        return energy_series(self.scene, states, datum=False), trans + rot

    def _initial_energy(self) -> float:
        x0, q0, v0, w0 = self.scene.initial_state()
        return float(self._energy(_States(x0[None], q0[None], v0[None], w0[None]))[0][0])

    def conserves_energy(self) -> bool:
        """Every pair of materials that can meet (:meth:`Scene.contact_materials`;
        statics never touch each other) has restitution 1: the
        mechanical energy is a conserved quantity of the model."""
        return all(p.restitution == 1.0 for p in self.scene.contact_materials())

    def reference_series(self) -> list[ReferenceSeries]:
        """|P_h| (N s), the momentum normal to gravity, constant at |P_h(0)|;
        with restitution 1 everywhere, E (J) constant at E(0)."""
        P0 = float(np.linalg.norm(self.P0))
        out = [ReferenceSeries("scene/momentum_normal_to_gravity", "N s",
                               f"|momentum normal to gravity|: conserved at {P0:.6g} N s",
                               constant(P0),
                               lambda tr: np.linalg.norm(self._horizontal(self.scene.masses @ tr.vel), axis=-1))]
        if self.conserves_energy():
            E0 = self._initial_energy()
            out.append(ReferenceSeries("scene/energy", "J", f"mechanical energy: conserved at {E0:.6g} J (e = 1)",
                                       constant(E0),
                                       lambda tr: energy_series(self.scene, tr, datum=False)))
        return out

    def predictions(self) -> dict[str, str]:
        out = {"momentum normal to gravity (conserved)": f"{np.array2string(self.P0, precision=6)} N s"}
        if self.conserves_energy():
            out["mechanical energy (conserved, e = 1)"] = f"{self._initial_energy():.6g} J"
        return out

    def metrics(self, trace) -> dict[str, float]:
        P = self._horizontal(self.scene.masses @ trace.vel[-1])
        ends = [0, -1]
        (E0, E1), (K0, _) = self._energy(_States(trace.pos[ends], trace.quat[ends], trace.vel[ends],
                                                 trace.angvel[ends]))
        E0, E1, K0 = float(E0), float(E1), float(K0)
        out = {"momentum_error": float(np.linalg.norm(P - self.P0) / np.linalg.norm(self.P0))}
        # K0 = 0 with P0 != 0: speeds so small that m v^2 underflows
        divide(out, "energy_error", abs(E1 - E0), K0, "the initial kinetic energy KE(0)")
        divide(out, "energy_loss", E0 - E1, K0, "the initial kinetic energy KE(0)")
        return out


class BounceHeights(ReferenceModel):
    """A sphere dropped on a horizontal plane bounces to apex heights
    h_n = e^(2n) h_0 (Newton's law of restitution, e = the sphere-plane pair's
    restitution; heights of the sphere's bottom above the plane, no spin, no
    air).  With impact speed v1 = sqrt(v0z^2 + 2 g h_s) (h_s the starting
    height, v0z the upward starting velocity), h_0 = v1^2 / (2 g), and the
    ball is at rest after t_inf = t_1 + 2 e v1 / (g (1 - e)).

    Metrics:

    - ``bounce_ratio_error``: the measured restitution of each bounce,
      e_n = sqrt(A_n / A_{n-1}) from the measured apex heights A (A_0 = h_0;
      each A_n = h + v_n^2 / (2 g) at the frame where the normal velocity
      turns down, so frame sampling does not limit it),
      against e: max over the first ``bounces`` (params, default 3) bounces
      whose reference apex is above 1 % of h_0 and inside the run of
      |e_n - e| (absolute; a missing bounce counts as e_n = 0).  For e = 0 the
      first bounce is checked (any apex above 1 % of h_0 is an error).
    - ``trajectory_rmse`` / ``final_position_error`` against the piecewise
      parabola.
    """

    name = "bounce_heights"
    summary = "a sphere dropped on a level plane bounces to apex heights e^(2n) h_0"
    takes = "one sphere, one plane normal to gravity, the pair's restitution, the sphere's initial height and velocity"
    params = (Param("bounces", "int", 3, "how many bounces bounce_ratio_error looks at"),)
    produces = {
        "bounce_ratio_error": "max over the first `bounces` bounces of |e_n - e|, e_n = sqrt(A_n / A_n-1) "
                              "from measured apex heights A = h + v_n^2 / (2 g) at the turn of the flight (1)",
        "first_bounce_ratio": "measured sqrt(A_1 / h_0) (1)",
        **TRAJECTORY,
    }
    primary = "bounce_ratio_error"
    APEX_FRACTION = 0.01
    JITTER_FRACTION = 0.001

    def __init__(self, scene):
        super().__init__(scene)
        if scene.n_bodies != 1 or scene.bodies[0].shape != "sphere":
            raise ReferenceError("bounce_heights needs exactly one sphere")
        planes = [s for s in scene.statics if s.shape == "plane"]
        if len(planes) != 1:
            raise ReferenceError("bounce_heights needs exactly one plane")
        p = planes[0]
        g = scene.gravity
        self.g = float(np.linalg.norm(g))
        if self.g == 0 or abs(p.normal @ (-g / self.g) - 1) > 1e-12:
            raise ReferenceError("bounce_heights needs gravity normal to the plane")
        b = scene.bodies[0]
        self.n = p.normal
        self.offset = p.offset + b.radius  # centre height at touch-down
        self.e = scene.pair(b.material, p.material).restitution
        self.x0 = b.position.copy()
        hs = float(b.position @ self.n - self.offset)
        vz = float(b.velocity @ self.n)
        self.v_tan = b.velocity - vz * self.n
        if hs < 0:
            raise ReferenceError("bounce_heights: the sphere starts below the plane")
        self.v1 = math.sqrt(vz * vz + 2 * self.g * hs)
        self.h0 = self.v1**2 / (2 * self.g)
        if not self.h0 > 0:  # every apex ratio divides by it
            raise ReferenceError("bounce_heights: the sphere starts at rest on the plane (no drop height, no "
                                 "impact speed): nothing bounces", key="body")
        self.t1 = (vz + self.v1) / self.g
        self.hs, self.vz = hs, vz
        self.bounces = int(self.param("bounces", 3))

    def height(self, t: np.ndarray) -> np.ndarray:
        """Reference height of the bottom above the plane (m) at times t (F,)."""
        t = np.asarray(t, float)
        h = np.zeros_like(t)
        first = t <= self.t1
        h[first] = self.hs + self.vz * t[first] - 0.5 * self.g * t[first] ** 2
        if self.e == 0:
            return h
        tb = self.t1
        v = self.e * self.v1
        rest = ~first
        while v > 1e-9 * self.v1 and rest.any():
            T = 2 * v / self.g
            seg = rest & (t <= tb + T)
            s = t[seg] - tb
            h[seg] = v * s - 0.5 * self.g * s * s
            rest &= ~seg
            tb += T
            v *= self.e
        return h

    def positions(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        base = self.x0 - (self.x0 @ self.n - self.offset) * self.n  # touch-down point below the start
        p = base + np.outer(t, self.v_tan) + np.outer(self.height(t), self.n)
        return p[:, None, :]

    def predictions(self) -> dict[str, str]:
        apex = self.reference_apexes(self.scene.duration)[:5]
        return {"first impact": f"{self.t1:.6g} s at {self.v1:.6g} m/s",
                "apex heights (bottom above the plane)": ", ".join(f"{h:.6g}" for h in apex) + " m"}

    def flights(self, duration: float) -> list[tuple[float, float, float]]:
        """(bounce time s, next bounce time s, apex height m) of each flight
        after a bounce whose apex :meth:`reference_apexes` lists."""
        out, tb, v = [], self.t1, self.e * self.v1
        for A in self.reference_apexes(duration):
            T = 2 * v / self.g
            out.append((tb, tb + T, A))
            tb, v = tb + T, v * self.e
        return out

    def reference_series(self) -> list[ReferenceSeries]:
        """The bottom's height above the plane (m), and each apex height
        A_n as a level over its flight."""
        name, n, off = self.scene.bodies[0].name, self.n, self.offset
        flights = self.flights(self.scene.duration)

        def apex(t):
            t = np.asarray(t, float)
            out = np.full(t.shape, np.nan)
            for t0, t1, A in flights:
                out[(t >= t0) & (t < t1)] = A
            return out

        return [ReferenceSeries(f"{name}/height", "m", "height of the bottom above the plane", self.height,
                                lambda tr: tr.pos[:, 0] @ n - off),
                ReferenceSeries(f"{name}/apex_height", "m", "apex heights: "
                                + ", ".join(f"{A:.6g}" for _, _, A in flights) + " m", apex)]

    def reference_times(self) -> list[tuple[float, str]]:
        out = [(float(self.t1), f"first impact at {self.v1:.6g} m/s")]
        out += [(float(t1), f"bounce {k + 2}") for k, (_, t1, _) in enumerate(self.flights(self.scene.duration))
                if t1 <= self.scene.duration]
        return out

    def reference_apexes(self, duration: float) -> list[float]:
        """Reference apex heights A_1..A_k above 1 % of h_0 reached within duration."""
        out = []
        tb, v = self.t1, self.e * self.v1
        for _ in range(self.bounces):
            if self.e == 0:
                break
            t_apex = tb + v / self.g
            A = v * v / (2 * self.g)
            if A < self.APEX_FRACTION * self.h0 or t_apex > duration:
                break
            out.append(A)
            tb += 2 * v / self.g
            v *= self.e
        return out

    def measured_apexes(self, trace) -> list[float]:
        """Apex heights (m) after each bounce, from the state: a bounce is
        an upward crossing of the normal velocity, its apex the frame where
        that velocity turns down again; of the two frames around the turn
        the one nearer the top (smaller |v_n|) gives A = h + v_n^2 / (2 g),
        the height the ballistic flight through that state reaches.  Frame
        sampling then adds nothing: a flight that conserves h + v_n^2 / 2g
        reads its apex to round-off (the highest sampled frame would miss it
        by up to g dt^2 / 8; tests/test_references.py::
        test_bounce_apex_comes_from_the_state).  Apexes below 0.1 % of h_0
        are contact jitter, not bounces, and are ignored; a low real bounce
        (below the 1 % that decides which *reference* bounces are checked)
        still counts, so a weak bounce is measured as weak rather than as
        missing."""
        h = trace.pos[:, 0] @ self.n - self.offset
        vz = trace.vel[:, 0] @ self.n
        out = []
        k = 1
        F = len(h)
        bounced = False
        while k < F:
            if not bounced and vz[k - 1] <= 0 < vz[k] and k > 1:
                bounced = True
            elif bounced and vz[k - 1] > 0 >= vz[k]:
                j = k if -vz[k] < vz[k - 1] else k - 1
                A = float(h[j] + vz[j] * vz[j] / (2.0 * self.g))
                if A >= self.JITTER_FRACTION * self.h0:
                    out.append(A)
                bounced = False
            k += 1
        return out

    def metrics(self, trace) -> dict[str, float]:
        out = trajectory_metrics(trace.pos, self.positions(trace.t))
        ref = self.reference_apexes(float(trace.t[-1]))
        meas = self.measured_apexes(trace)
        n_check = max(len(ref), 1)
        A = [self.h0] + meas
        errs = []
        for k in range(1, n_check + 1):
            e_k = math.sqrt(max(A[k], 0.0) / A[k - 1]) if k < len(A) and A[k - 1] > 0 else 0.0
            errs.append(abs(e_k - self.e))
        out["bounce_ratio_error"] = float(max(errs))
        if meas:
            out["first_bounce_ratio"] = math.sqrt(meas[0] / self.h0)
        return out
