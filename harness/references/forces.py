"""Closed forms for the smooth forces: a mass on a spring and dashpot, and
a body falling against linear or quadratic drag.

Oscillator (``damped_oscillator``).  One spring ([[spring]], stiffness k,
damping c, rest length L0) joins a body to the world, or two bodies to each
other, at their centres of mass.  The motion is along the spring's line e
(world: from the anchor to the body; two bodies: from a to b), so that line
must hold the initial displacement, the (relative) initial velocity and, for
a world spring, gravity.  With s the length along e (world: m_eff = m, a
gravity pull g_e = g . e; two bodies: the reduced mass m1 m2 / (m1 + m2), and
gravity moves only their centre of mass, in free fall)

    m_eff s'' = -k (s - L0) - c s' + m_eff g_e,   s_eq = L0 + m_eff g_e / k

so y = s - s_eq obeys y'' + 2 gamma y' + w0^2 y = 0, gamma = c / (2 m_eff),
w0 = sqrt(k / m_eff), damping ratio zeta = gamma / w0:

    zeta < 1:  y = e^(-gamma t) (y0 cos wd t + (v0 + gamma y0) / wd sin wd t),
               wd = w0 sqrt(1 - zeta^2), period T = 2 pi / wd
    zeta = 1:  y = e^(-gamma t) (y0 + (v0 + gamma y0) t)
    zeta > 1:  y = A e^(r1 t) + B e^(r2 t), r = -gamma +- sqrt(gamma^2 - w0^2)

Successive extremes of an underdamped y are T / 2 apart and shrink by
e^(-gamma T / 2): ln |y_peak| is a straight line of slope -gamma in t.
With L0 > 0 the spring must stay on one side of its anchor (s > 0): a scene
whose motion reaches the anchor is refused (the force's direction would
flip, not modelled).  The bound is the motion's real lowest point: y0 or
the y at the zeros of y' for t >= 0 (underdamped the first two, later
extremes shrink; critically and overdamped at most one, the overshoot).

Drag (``drag_fall``).  One body, gravity g (or none), one drag law:

    linear   m v' = m g - c v:  v = v_t + (v0 - v_t) e^(-t / tau),
             v_t = m g / c, tau = m / c, any initial velocity;
             x = x0 + v_t t + tau (v0 - v_t) (1 - e^(-t / tau))
    quadratic m v' = m g - c |v| v, along g, starting at rest or falling:
             v_t = sqrt(m |g| / c), tau = v_t / |g|,
             v0 < v_t:  v = v_t tanh(t / tau + atanh(v0 / v_t)),
                        s = v_t tau ln(cosh(t / tau + p) / cosh p)
             v0 > v_t:  v = v_t coth(t / tau + acoth(v0 / v_t)),
                        s = v_t tau ln(sinh(t / tau + p) / sinh p)
             without gravity (along v0): v = v0 / (1 + c v0 t / m),
                        s = (m / c) ln(1 + c v0 t / m)

A body thrown upward against quadratic drag (the law changes sign at the
apex) or sideways (the components couple) is refused.
"""

from __future__ import annotations

import math

import numpy as np

from physbench.harness.references import (BODY_PARAM, TRAJECTORY, ReferenceError, ReferenceModel, ReferenceSeries, constant,
                                trajectory_metrics)

_COLLINEAR = 1e-9  # relative tolerance for "along the line"


def _off_line(v: np.ndarray, e: np.ndarray) -> float:
    return float(np.linalg.norm(v - (v @ e) * e))


class DampedOscillator(ReferenceModel):
    summary = "a body on a spring and dashpot to the world, or two bodies joined by one: closed-form damped motion"
    takes = ("exactly one [[spring]] (stiffness > 0, damping optional) at the centres of mass (anchors on bodies "
             "zero), joining one body to the world or two bodies; the motion along the spring's line (initial "
             "displacement, relative velocity and, for a world spring, gravity along it); no contact with "
             "statics, no drag. Refuses a spring with rest length > 0 whose motion would reach its anchor")
    name = "damped_oscillator"
    produces = {
        "oscillator_position_error": "max_t |x - x_ref| / A0, A0 the initial amplitude (1)",
        "period": "measured mean time between same-direction crossings of the equilibrium (s; zeta < 1)",
        "period_ref": "2 pi / wd (s)",
        "period_error": "|T - T_ref| / T_ref (1; zeta < 1; inf with fewer than two crossings in the run)",
        "decay_rate": "measured gamma: -slope of ln|y| over the extremes (1/s; zeta < 1; NaN with fewer than "
                      "three extremes above 0.1 % of A0)",
        "decay_rate_ref": "c / (2 m_eff) (1/s)",
        "decay_rate_error": "|gamma_measured - gamma| / gamma (1; zeta < 1 with damping; inf if not measured)",
        **TRAJECTORY,
    }
    primary = "oscillator_position_error"

    def __init__(self, scene):
        super().__init__(scene)
        if len(scene.springs) != 1:
            raise ReferenceError(f"damped_oscillator needs exactly one [[spring]], the scene has {len(scene.springs)}",
                                 key="spring")
        sp = scene.springs[0]
        if sp.stiffness <= 0:
            raise ReferenceError("damped_oscillator needs stiffness > 0 (and the 'spring' effect)",
                                 key="spring[0].stiffness")
        for end, i, anc in (("a", sp.a, sp.anchor_a), ("b", sp.b, sp.anchor_b)):
            if i >= 0 and np.any(anc != 0):
                raise ReferenceError("damped_oscillator needs the spring at the body's centre of mass "
                                     f"(anchor_{end} = [0, 0, 0]); an offset anchor couples rotation",
                                     key=f"spring[0].anchor_{end}")
        if scene.has("contact") and scene.statics:
            raise ReferenceError("damped_oscillator needs nothing to touch: no statics with the 'contact' effect",
                                 key="scenario.effects")
        for b in scene.bodies:
            if (scene.has("drag_linear") and b.drag_linear > 0) or (scene.has("drag_quadratic") and b.drag_quadratic > 0):
                raise ReferenceError("damped_oscillator needs no drag (use drag_fall)", key="scenario.effects")
        g = scene.gravity
        if sp.a < 0 or sp.b < 0:
            i, anchor = (sp.b, sp.anchor_a) if sp.a < 0 else (sp.a, sp.anchor_b)
            b = scene.bodies[i]
            self.idx = (i,)
            self.m_eff = b.mass
            y0 = b.position - anchor
            v0 = b.velocity.copy()
            self.anchor = anchor.copy()
        else:
            ba, bb = scene.bodies[sp.a], scene.bodies[sp.b]
            self.idx = (sp.a, sp.b)
            self.m_eff = ba.mass * bb.mass / (ba.mass + bb.mass)
            y0 = bb.position - ba.position
            v0 = bb.velocity - ba.velocity
            M = ba.mass + bb.mass
            self.X0 = (ba.mass * ba.position + bb.mass * bb.position) / M
            self.V0 = (ba.mass * ba.velocity + bb.mass * bb.velocity) / M
            self.frac = (bb.mass / M, ba.mass / M)  # x_a = X - frac_a y, x_b = X + frac_b y
        L = float(np.linalg.norm(y0))
        if L > 0:
            e = y0 / L
        elif sp.rest_length > 0:
            raise ReferenceError("damped_oscillator: the body starts on the anchor of a spring with rest length > 0 "
                                 "(no direction to stretch in)", key="spring[0].rest_length")
        else:
            cands = [v0, g if len(self.idx) == 1 else np.zeros(3), np.array([0.0, 0.0, 1.0])]
            e = next(c / np.linalg.norm(c) for c in cands if np.linalg.norm(c) > 0)
        scale_v = max(float(np.linalg.norm(v0)), 1e-300)
        if _off_line(v0, e) > _COLLINEAR * scale_v:
            raise ReferenceError("damped_oscillator needs the (relative) initial velocity along the spring's line "
                                 f"{e.round(6).tolist()}: a sideways start swings (not modelled)", key="body")
        g_e = 0.0
        if len(self.idx) == 1:
            gn = float(np.linalg.norm(g))
            if gn > 0 and _off_line(g, e) > _COLLINEAR * gn:
                raise ReferenceError("damped_oscillator needs gravity along the spring's line "
                                     f"{e.round(6).tolist()} (a hanging spring), or no gravity", key="scenario.gravity")
            g_e = float(g @ e)
        self.g = g.copy()
        self.e = e
        k, c, m = sp.stiffness, sp.damping, self.m_eff
        self.k, self.c, self.L0 = k, c, sp.rest_length
        self.s_eq = sp.rest_length + m * g_e / k
        self.y0 = L - self.s_eq
        self.v0 = float(v0 @ e)
        self.w0 = math.sqrt(k / m)
        self.gamma = c / (2.0 * m)
        self.zeta = self.gamma / self.w0
        if self.zeta < 1.0:
            self.wd = self.w0 * math.sqrt(1.0 - self.zeta**2)
            self.amp = math.hypot(self.y0, (self.v0 + self.gamma * self.y0) / self.wd)
        else:
            self.wd = 0.0
            self.amp = abs(self.y0) + abs(self.v0) / self.w0
        if self.amp == 0:
            raise ReferenceError("damped_oscillator needs a start away from equilibrium (displacement or speed)",
                                 key="body")
        # the anchor bound is the motion's real lowest point, damping included
        # (tests/test_references.py::test_damped_oscillator_bounds_the_real_motion)
        self.y_min = self.lowest()
        if self.L0 > 0 and self.s_eq + self.y_min <= 0:
            raise ReferenceError(f"damped_oscillator: the motion (lowest point {self.y_min:.6g} m from the "
                                 f"equilibrium at {self.s_eq:.6g} m from the anchor) would reach the spring's anchor, "
                                 "where its force turns round (not modelled)", key="spring[0].rest_length")

    def stationary_times(self) -> list[float]:
        """Times t >= 0 (s) at which y' = 0: the extremes of the motion.
        Underdamped, the first two (one of each sign; later ones shrink by
        e^(-gamma T / 2)); critically and overdamped, the one overshoot if
        there is one (y' = 0 has at most one root)."""
        y0, v0, gm, w0 = self.y0, self.v0, self.gamma, self.w0
        if self.zeta < 1.0:
            wd = self.wd
            # y' = e^(-gm t) (v0 cos wd t - (y0 wd + gm b) sin wd t), b = (v0 + gm y0) / wd
            q = y0 * wd + gm * (v0 + gm * y0) / wd
            phi = math.atan2(v0, q) % math.pi  # first root of tan(wd t) = v0 / q in [0, pi)
            return [phi / wd, (phi + math.pi) / wd]
        if self.zeta == 1.0:
            # y' = e^(-gm t) (v0 - gm (v0 + gm y0) t)
            den = gm * (v0 + gm * y0)
            return [v0 / den] if den != 0 and v0 / den > 0 else []
        root = math.sqrt(gm * gm - w0 * w0)
        r1, r2 = -gm + root, -gm - root
        A = (v0 - r2 * y0) / (r1 - r2)
        B = y0 - A
        # y' = A r1 e^(r1 t) + B r2 e^(r2 t) = 0  <=>  e^((r1 - r2) t) = -B r2 / (A r1)
        if A == 0 or B == 0:
            return []
        arg = -B * r2 / (A * r1)
        return [math.log(arg) / (r1 - r2)] if arg > 1.0 else []

    def lowest(self) -> float:
        """The least displacement y (m) over t >= 0: the start, an extreme
        (:meth:`stationary_times`), or the equilibrium it tends to."""
        ts = self.stationary_times()
        return float(min([self.y0, 0.0] + list(self.y(np.array(ts, float))))) if ts else min(self.y0, 0.0)

    def y(self, t: np.ndarray) -> np.ndarray:
        """Displacement from equilibrium along e (m) at times t (F,)."""
        t = np.asarray(t, float)
        y0, v0, gm, w0 = self.y0, self.v0, self.gamma, self.w0
        if self.zeta < 1.0:
            wd = self.wd
            return np.exp(-gm * t) * (y0 * np.cos(wd * t) + (v0 + gm * y0) / wd * np.sin(wd * t))
        if self.zeta == 1.0:
            return np.exp(-gm * t) * (y0 + (v0 + gm * y0) * t)
        root = math.sqrt(gm * gm - w0 * w0)
        r1, r2 = -gm + root, -gm - root
        A = (v0 - r2 * y0) / (r1 - r2)
        return A * np.exp(r1 * t) + (y0 - A) * np.exp(r2 * t)

    def positions(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        rel = np.outer(self.s_eq + self.y(t), self.e)  # (F, 3)
        out = np.full((len(t), self.scene.n_bodies, 3), np.nan)
        if len(self.idx) == 1:
            out[:, self.idx[0]] = self.anchor + rel
        else:
            X = self.X0 + np.outer(t, self.V0) + 0.5 * np.outer(t * t, self.g)
            out[:, self.idx[0]] = X - self.frac[0] * rel
            out[:, self.idx[1]] = X + self.frac[1] * rel
        return out

    def measured_y(self, trace) -> np.ndarray:
        if len(self.idx) == 1:
            rel = trace.pos[:, self.idx[0]] - self.anchor
        else:
            rel = trace.pos[:, self.idx[1]] - trace.pos[:, self.idx[0]]
        return rel @ self.e - self.s_eq

    def _key(self) -> str:
        names = [self.scene.bodies[i].name for i in self.idx]
        return names[0] if len(names) == 1 else "_".join(names)

    def upward_crossings(self) -> list[float]:
        """Times (s) within the run when an underdamped y crosses the
        equilibrium upward: y = A e^(-gamma t) cos(wd t - phi) with
        wd t - phi = -pi/2 + 2 pi k; [] for zeta >= 1."""
        if self.zeta >= 1.0:
            return []
        phi = math.atan2((self.v0 + self.gamma * self.y0) / self.wd, self.y0)
        k0 = math.ceil((-phi + math.pi / 2) / (2 * math.pi) - 1e-12)
        out = []
        while True:
            t = (phi - math.pi / 2 + 2 * math.pi * k0) / self.wd
            if t > self.scene.duration:
                return out
            if t > 0:
                out.append(t)
            k0 += 1

    def reference_series(self) -> list[ReferenceSeries]:
        """The displacement from equilibrium along the spring's line y(t)
        (m), and for zeta < 1 with damping its envelope A e^(-gamma t) (a
        line with no measured twin)."""
        key = self._key()
        per = f"period {2 * math.pi / self.wd:.6g} s, " if self.zeta < 1.0 else ""
        out = [ReferenceSeries(f"{key}/displacement", "m", f"displacement from equilibrium along the spring ({per}"
                               f"zeta {self.zeta:.6g})", self.y, self.measured_y)]
        if self.zeta < 1.0 and self.gamma > 0:
            out.append(ReferenceSeries(f"{key}/envelope", "m", f"envelope {self.amp:.6g} e^(-{self.gamma:.6g} t) m",
                                       lambda t: self.amp * np.exp(-self.gamma * np.asarray(t, float))))
        return out

    def reference_times(self) -> list[tuple[float, str]]:
        return [(t, "upward through equilibrium") for t in self.upward_crossings()]

    def predictions(self) -> dict[str, str]:
        out = {"equilibrium length": f"{self.s_eq:.6g} m", "damping ratio": f"{self.zeta:.6g}"}
        if self.zeta < 1.0:
            out["period"] = f"{2 * math.pi / self.wd:.6g} s"
            out["decay rate"] = f"{self.gamma:.6g} 1/s"
        return out

    def metrics(self, trace) -> dict[str, float]:
        idx = list(self.idx)
        ref = self.positions(trace.t)
        out = trajectory_metrics(trace.pos[:, idx], ref[:, idx])
        err = np.linalg.norm(trace.pos[:, idx] - ref[:, idx], axis=-1)
        out["oscillator_position_error"] = float(np.nanmax(err)) / self.amp
        if self.zeta >= 1.0:
            return out
        t, y = trace.t, self.measured_y(trace)
        T_ref = 2.0 * math.pi / self.wd
        out["period_ref"] = T_ref
        out["decay_rate_ref"] = self.gamma
        # upward crossings of the equilibrium, linearly interpolated
        k = np.nonzero((y[:-1] < 0) & (y[1:] >= 0))[0]
        ups = t[k] - y[k] * (t[k + 1] - t[k]) / (y[k + 1] - y[k])
        # fewer than two crossings: no oscillation measured, an infinite error
        T = float(np.mean(np.diff(ups))) if len(ups) >= 2 else math.nan
        out["period"] = T
        out["period_error"] = abs(T - T_ref) / T_ref if math.isfinite(T) else math.inf
        # extremes, each refined by the parabola through its three samples
        a = np.abs(y)
        j = np.nonzero((a[1:-1] > a[:-2]) & (a[1:-1] >= a[2:]) & (a[1:-1] > 1e-3 * self.amp))[0] + 1
        if len(j) >= 3:
            y0_, y1_, y2_ = a[j - 1], a[j], a[j + 1]
            den = y0_ - 2 * y1_ + y2_
            off = np.where(den != 0, 0.5 * (y0_ - y2_) / np.where(den != 0, den, 1.0), 0.0)
            h = t[j + 1] - t[j]
            tp = t[j] + off * h
            yp = y1_ - 0.25 * (y0_ - y2_) * off
            tm = tp - tp.mean()
            slope = float(tm @ (np.log(yp) - np.log(yp).mean()) / (tm @ tm))
            out["decay_rate"] = -slope
        else:  # fewer than three extremes: no decay measured
            out["decay_rate"] = math.nan
        if self.gamma > 0:
            rate = out["decay_rate"]
            out["decay_rate_error"] = abs(rate - self.gamma) / self.gamma if math.isfinite(rate) else math.inf
        return out


class DragFall(ReferenceModel):
    summary = "a body falling (or coasting) against linear or quadratic drag: exponential or tanh approach to v_t"
    takes = ("one body, one of the 'drag_linear' / 'drag_quadratic' effects with its coefficient > 0 (not both), "
             "gravity or none, no springs, no contact with statics; quadratic drag: the initial velocity along "
             "gravity and downward or zero (without gravity: any)")
    name = "drag_fall"
    params = (BODY_PARAM,)
    produces = {
        "drag_velocity_error": "max_t |v - v_ref| / v_scale, v_scale = max(v_t, |v0|) (1)",
        "terminal_velocity_ref": "v_t = m g / c (linear) or sqrt(m g / c) (quadratic) (m/s)",
        "final_speed": "measured speed at the last frame (m/s)",
        "final_speed_error": "|speed(T) - speed_ref(T)| / v_scale (1)",
        **TRAJECTORY,
    }
    primary = "drag_velocity_error"

    def __init__(self, scene):
        super().__init__(scene)
        b = self.the_body()
        self.body = b
        lin = scene.has("drag_linear") and b.drag_linear > 0
        quad = scene.has("drag_quadratic") and b.drag_quadratic > 0
        if lin == quad:
            raise ReferenceError("drag_fall needs exactly one drag law on the body: 'drag_linear' with "
                                 "body.drag_linear > 0 or 'drag_quadratic' with body.drag_quadratic > 0"
                                 + (" (both are set)" if lin else ""), key="scenario.effects")
        if scene.springs:
            raise ReferenceError("drag_fall needs no springs (use damped_oscillator)", key="spring")
        if scene.has("contact") and scene.statics:
            raise ReferenceError("drag_fall needs free flight: no statics with the 'contact' effect",
                                 key="scenario.effects")
        self.quadratic = quad
        m = b.mass
        g = scene.gravity
        gn = float(np.linalg.norm(g))
        self.x0, self.v0 = b.position.copy(), b.velocity.copy()
        self.g, self.gn = g.copy(), gn
        if not quad:
            c = b.drag_linear
            self.tau = m / c
            self.vt_vec = m * g / c
            self.v_t = float(np.linalg.norm(self.vt_vec))
        else:
            c = b.drag_quadratic
            self.c = c
            v0 = self.v0
            if gn > 0:
                e = g / gn
                if _off_line(v0, e) > _COLLINEAR * max(float(np.linalg.norm(v0)), 1e-300) or float(v0 @ e) < 0:
                    raise ReferenceError("drag_fall with quadratic drag needs the initial velocity downward along "
                                         "gravity or zero (an upward or sideways start is not modelled)",
                                         key="body")
                self.v_t = math.sqrt(m * gn / c)
                self.tau = self.v_t / gn
            else:
                sp = float(np.linalg.norm(v0))
                if sp == 0:
                    raise ReferenceError("drag_fall without gravity needs an initial velocity", key="body")
                e = v0 / sp
                self.v_t = 0.0
                self.tau = m / (c * sp)
            self.e = e
            self.u0 = float(v0 @ e)
        self.v_scale = max(self.v_t, float(np.linalg.norm(self.v0)))
        if self.v_scale == 0:
            raise ReferenceError("drag_fall needs gravity or an initial velocity (nothing moves)", key="body")

    def state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reference (x (F, 3), v (F, 3)) of the body at times t (F,)."""
        t = np.asarray(t, float)
        if not self.quadratic:
            ex = np.exp(-t / self.tau)
            dv = self.v0 - self.vt_vec
            v = self.vt_vec + np.outer(ex, dv)
            x = self.x0 + np.outer(t, self.vt_vec) + self.tau * np.outer(1.0 - ex, dv)
            return x, v
        u0, vt, tau = self.u0, self.v_t, self.tau
        if vt == 0.0:  # coasting, no gravity: tau = m / (c u0)
            u = u0 / (1.0 + t / tau)
            s = u0 * tau * np.log1p(t / tau)
        elif u0 == vt:
            u, s = np.full_like(t, vt), vt * t
        elif u0 < vt:
            p = math.atanh(u0 / vt)
            u = vt * np.tanh(t / tau + p)
            s = vt * tau * (np.log(np.cosh(t / tau + p)) - math.log(math.cosh(p)))
        else:
            p = math.atanh(vt / u0)
            u = vt / np.tanh(t / tau + p)
            s = vt * tau * (np.log(np.sinh(t / tau + p)) - math.log(math.sinh(p)))
        return self.x0 + np.outer(s, self.e), np.outer(u, self.e)

    def positions(self, t: np.ndarray) -> np.ndarray:
        out = np.full((len(t), self.scene.n_bodies, 3), np.nan)
        out[:, self.body.index] = self.state(t)[0]
        return out

    def reference_series(self) -> list[ReferenceSeries]:
        """The speed |v(t)| (m/s), and the terminal speed v_t as a level
        (no measured twin) where there is one."""
        i, name = self.body.index, self.body.name
        law = "quadratic" if self.quadratic else "linear"
        out = [ReferenceSeries(f"{name}/speed", "m/s", f"speed against {law} drag (time scale {self.tau:.6g} s)",
                               lambda t: np.linalg.norm(self.state(np.asarray(t, float))[1], axis=1),
                               lambda tr: np.linalg.norm(tr.vel[:, i], axis=1))]
        if self.v_t > 0:
            out.append(ReferenceSeries(f"{name}/terminal_speed", "m/s", f"terminal speed {self.v_t:.6g} m/s",
                                       constant(self.v_t)))
        return out

    def predictions(self) -> dict[str, str]:
        return {"terminal speed": f"{self.v_t:.6g} m/s", "time scale": f"{self.tau:.6g} s",
                "speed at the end": f"{float(np.linalg.norm(self.state(np.array([self.scene.duration]))[1])):.6g} m/s"}

    def metrics(self, trace) -> dict[str, float]:
        i = self.body.index
        x, v = self.state(trace.t)
        out = trajectory_metrics(trace.pos[:, [i]], x[:, None, :])
        out["drag_velocity_error"] = float(np.nanmax(np.linalg.norm(trace.vel[:, i] - v, axis=1))) / self.v_scale
        out["terminal_velocity_ref"] = self.v_t
        sp = float(np.linalg.norm(trace.vel[-1, i]))
        out["final_speed"] = sp
        out["final_speed_error"] = abs(sp - float(np.linalg.norm(v[-1]))) / self.v_scale
        return out
