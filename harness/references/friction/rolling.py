"""A sphere or a cylinder on an incline: rolling or slipping, and rolling
against rolling resistance."""

from __future__ import annotations

import math

import numpy as np

from physbench.harness.references import TRAJECTORY, ReferenceError, divide, fit_slope
from physbench.harness.references.friction.slope import SKIP_FRACTION, STOP_METRICS, _SlopeModel, _check_axis_across, _window


class RollingSphere(_SlopeModel):
    """Sphere released from rest on an incline: rolls (a = g sin a / (1 + k))
    or slips (a = g (sin a - mu_k cos a)); see the package docstring
    (harness/references/friction/__init__.py).

    Metrics: ``roll_accel_error`` = |a_meas - a| / a (linear acceleration
    downhill); ``spin_accel_error`` = |alpha_meas - alpha| / alpha (angular
    acceleration about n x d); ``rolling_slip`` (m/s): the largest speed of
    the contact point, |v + w x (-R n)|, over the fitted window (0 for rolling
    without slipping).  Plus the measured ``roll_accel`` and ``spin_accel``.
    """

    name = "rolling_sphere"
    summary = "a sphere released from rest on an incline: rolls (a = g sin a / (1 + k)) or slips"
    takes = ("one sphere at rest on " + _SlopeModel.SURFACE + "; refuses a level surface (nothing would move)")
    produces = {
        "roll_accel": "measured linear acceleration downhill (m/s^2)",
        "roll_accel_error": "|a_measured - a| / a (1)",
        "spin_accel": "measured angular acceleration about n x d (rad/s^2)",
        "spin_accel_error": "|alpha_measured - alpha| / alpha (1)",
        "rolling_slip": "largest contact-point speed over the fitted window (m/s)",
        **TRAJECTORY,
    }
    primary = "roll_accel_error"

    def _check_body(self, b) -> None:
        if b.shape != "sphere":
            raise ReferenceError(f"rolling_sphere needs a sphere, body {b.name!r} is a {b.shape}")

    def _axis_inertia(self, b) -> float:
        return float(b.inertia[0])

    def __init__(self, scene):
        super().__init__(scene)
        b = self.body
        self._check_body(b)
        if np.any(b.velocity != 0) or np.any(b.angular_velocity != 0):
            raise ReferenceError(f"{self.name} needs the body to start at rest")
        if self.g_d == 0.0:
            raise ReferenceError(f"{self.name} needs an incline: on a level surface a body at rest stays at rest "
                                 "(no acceleration to measure)", key=f"static[{self.slope.index}]")
        self.R = b.radius
        self.I = self._axis_inertia(b)
        k = self.I / (b.mass * self.R**2)
        self.k = k
        self.rolls = self.mu_s * self.g_n >= self.g_d * k / (1 + k) - 1e-15
        if self.rolls:
            self.a = self.g_d / (1 + k)
            self.alpha = self.a / self.R
        else:
            self.a = self.g_d - self.mu_k * self.g_n
            self.alpha = self.mu_k * b.mass * self.g_n * self.R / self.I

    @property
    def regime(self) -> str:
        return "roll" if self.rolls else "slip"

    def distance(self, t: np.ndarray) -> np.ndarray:
        return 0.5 * self.a * t * t

    def reference_series(self):
        """Speed a t (m/s) and spin alpha t (rad/s): rolling, alpha = a / R."""
        return self.rolling_series(lambda t: self.a * np.asarray(t, float),
                                   lambda t: self.alpha * np.asarray(t, float),
                                   f"{self.a:.6g} m/s^2, spin {self.alpha:.6g} rad/s^2")

    def predictions(self) -> dict[str, str]:
        return {"regime": self.regime, "acceleration downhill": f"{self.a:.6g} m/s^2",
                "angular acceleration about n x d": f"{self.alpha:.6g} rad/s^2"}

    def metrics(self, trace) -> dict[str, float]:
        out = super().metrics(trace)
        i = self.body.index
        w = _window(trace.t)
        a_meas = fit_slope(trace.t[w], self.along(trace)[w])
        alpha_meas = fit_slope(trace.t[w], trace.angvel[w, i] @ self.axis)
        out["roll_accel"] = a_meas
        out["spin_accel"] = alpha_meas
        # a frictionless slope: the body slides without turning (alpha = 0)
        divide(out, "roll_accel_error", abs(a_meas - self.a), abs(self.a), "the reference acceleration")
        divide(out, "spin_accel_error", abs(alpha_meas - self.alpha), abs(self.alpha),
               "the reference angular acceleration")
        vc = trace.vel[w, i] + np.cross(trace.angvel[w, i], -self.R * self.n)
        out["rolling_slip"] = float(np.nanmax(np.linalg.norm(vc, axis=1)))
        return out


class RollingCylinder(RollingSphere):
    """Solid cylinder released from rest on an incline with its axis along
    the roll axis n x d (lying across the slope): the same closed forms as
    :class:`RollingSphere` with k = I_axis / (m r^2) about the cylinder's
    own axis (1/2 for a solid cylinder: a = 2/3 g sin a when it rolls).

    The contact is a line (two rim points, or a patch, in most engines)
    rather than a point, and the axis must stay across the slope: a tilt of
    the axis (yaw) shows up as a drift of the body across the slope, which
    the trajectory metrics measure.  Same metrics as ``rolling_sphere``.
    """

    name = "rolling_cylinder"
    summary = "a solid cylinder released from rest across an incline: rolls (a = 2/3 g sin a) or slips"
    takes = ("one cylinder at rest, its axis along n x d (across the slope), on " + _SlopeModel.SURFACE
             + "; refuses a level surface")

    def _check_body(self, b) -> None:
        if b.shape != "cylinder":
            raise ReferenceError(f"rolling_cylinder needs a cylinder, body {b.name!r} is a {b.shape}")
        _check_axis_across(self.name, b, self.axis)

    def _axis_inertia(self, b) -> float:
        return float(b.inertia[2])  # principal moment about the body z axis


class RollingResistance(_SlopeModel):
    """A sphere (or a cylinder lying across the slope) rolling without
    slipping against rolling resistance, on an incline of any angle
    (0: flat).

    The resistance is a torque against the rolling of magnitude mu_r N,
    with mu_r the pair's ``rolling_friction`` (a length, m: MuJoCo's and
    Bullet's convention) and N = m g cos a the normal load.  Along the
    downhill direction d, with friction force F (along d) at the contact
    and spin w about e = n x d (rolling: u = w R):

        m du/dt = m g sin a + F,    I dw/dt = -F R - s mu_r m g cos a

    where s = sign(u) while rolling.  Eliminating F with du/dt = R dw/dt:

        rolling:  a = (g sin a - s (mu_r / R) g cos a) / (1 + k),  k = I / (m R^2)
        at rest:  holds while tan a <= mu_r / R (the torque m g sin a R
                  the friction force must pass on stays within mu_r N),
                  else rolls downhill with s = +1.

    (5/7 for a solid sphere, 2/3 for a solid cylinder.)  Starting with
    u0 != 0 (and w0 = u0 / R: rolling), the ball decelerates while
    the resistance exceeds the slope's pull, stops at t_stop = |u0 / a| and
    then holds or rolls back down (both modelled).  Rolling without
    slipping needs |F| = m |g sin a - a| <= mu_s m g cos a in every phase;
    a scene that would slip is refused (not modelled).

    Metrics: ``roll_accel_error`` / ``spin_accel_error`` (the first rolling
    phase, fitted after its first 10 % and before 90 % of t_stop, relative
    to |a|), ``roll_accel`` and ``spin_accel`` the fitted values,
    ``rolling_slip`` (m/s) the largest contact-point speed over that
    window; for a body that stops (or starts at rest) and holds,
    ``stop_position_error`` (m) its largest distance within the slope's
    plane from the reference stop point from the reference stop time on
    (the stop distance's error plus any creep) and ``creep`` (m) its largest
    displacement within the slope's plane after it came to rest, from where
    it came to rest; plus ``trajectory_rmse`` and ``final_position_error``.
    """

    name = "rolling_resistance"
    summary = "a sphere or cylinder rolling on an incline or level plane against rolling friction mu_r"
    takes = ("one sphere or cylinder (axis across the slope) with a rolling start (w0 = u0 / R) on "
             + _SlopeModel.SURFACE + "; the 'rolling_friction' effect and a pair rolling_friction > 0; refuses "
             "a scene where the body would slip")
    produces = {
        "roll_accel": "fitted acceleration of the first rolling phase (m/s^2)",
        "roll_accel_error": "|a_measured - a| / |a| (1)",
        "spin_accel": "fitted angular acceleration (rad/s^2)",
        "spin_accel_error": "|alpha_measured - a / R| / |a / R| (1)",
        "rolling_slip": "largest contact-point speed over the fitted window (m/s)",
        **STOP_METRICS,
        **TRAJECTORY,
    }
    primary = "roll_accel_error"

    def __init__(self, scene):
        super().__init__(scene)
        b = self.body
        if b.shape == "sphere":
            I = float(b.inertia[0])
        elif b.shape == "cylinder":
            _check_axis_across(self.name, b, self.axis)
            I = float(b.inertia[2])
        else:
            raise ReferenceError(f"rolling_resistance needs a sphere or a cylinder, body {b.name!r} is a {b.shape}")
        R = self.R = b.radius
        k = self.k = I / (b.mass * R * R)
        mat = scene.pair(b.material, self.slope.material)
        self.mu_r = mur = mat.rolling_friction
        if not scene.has("rolling_friction") or mur <= 0:
            raise ReferenceError("rolling_resistance needs the 'rolling_friction' effect and a pair rolling_friction > 0")
        u0 = self.u0
        if not np.allclose(b.velocity, u0 * self.d, atol=1e-12):
            raise ReferenceError("rolling_resistance needs the initial velocity along the downhill direction "
                                 f"{self.d.round(6).tolist()} (or zero)")
        if not np.allclose(b.angular_velocity, (u0 / R) * self.axis, atol=1e-12):
            raise ReferenceError("rolling_resistance needs a rolling start: angular velocity = (u0 / R) n x d = "
                                 f"{((u0 / R) * self.axis).round(9).tolist()} rad/s")
        c = mur / R * self.g_n  # the resistance's deceleration scale, m/s^2
        holds = self.g_d <= c + 1e-15
        # phases: (start time, start distance, start speed, acceleration)
        if u0 != 0.0:
            a1 = (self.g_d - math.copysign(c, u0)) / (1 + k)
            t_stop = -u0 / a1 if a1 * u0 < 0 else math.inf
        else:
            a1, t_stop = 0.0, 0.0
        a2 = 0.0 if holds else (self.g_d - c) / (1 + k)
        self.phases = [(0.0, 0.0, u0, a1)] if u0 != 0.0 else []
        if math.isfinite(t_stop):
            s_stop = u0 * t_stop + 0.5 * a1 * t_stop**2
            self.phases.append((t_stop, s_stop, 0.0, a2))
        self.t_stop, self.holds = t_stop, holds
        for _, _, _, acc in self.phases:
            if abs(self.g_d - acc) > self.mu_s * self.g_n * (1 + 1e-12):
                raise ReferenceError(f"rolling_resistance: rolling needs a friction force {abs(self.g_d - acc):.4g} m/s^2 "
                                     f"per unit mass, more than mu_s g cos a = {self.mu_s * self.g_n:.4g}: "
                                     "the body would slip (not modelled)")
        # the first phase that moves is the one whose acceleration is fitted
        moving = [p for p in self.phases if p[2] != 0.0 or p[3] != 0.0]
        self.fit_phase = moving[0] if moving else None

    @property
    def regime(self) -> str:
        if self.t_stop == 0.0:
            return "hold" if self.holds else "roll"
        return ("stop" if self.holds else "stop_and_return") if math.isfinite(self.t_stop) else "roll"

    def distance(self, t: np.ndarray) -> np.ndarray:
        """Reference distance travelled downhill (m) at times t (F,)."""
        out = np.zeros_like(t, dtype=float)
        for t0, s0, u, a in self.phases:
            m = t >= t0
            tt = t[m] - t0
            out[m] = s0 + u * tt + 0.5 * a * tt * tt
        return out

    def speed(self, t: np.ndarray) -> np.ndarray:
        """Reference speed downhill (m/s) at times t (F,): d/dt of :meth:`distance`."""
        t = np.asarray(t, float)
        out = np.zeros_like(t)
        for t0, _s0, u, a in self.phases:
            m = t >= t0
            out[m] = u + a * (t[m] - t0)
        return out

    def reference_series(self):
        """Speed downhill (m/s), phase by phase, and the rolling spin u / R (rad/s)."""
        return self.rolling_series(self.speed, lambda t: self.speed(t) / self.R,
                                   ", then ".join(f"{a:.6g} m/s^2" for *_, a in self.phases) or "holds")

    def reference_times(self) -> list[tuple[float, str]]:
        if math.isfinite(self.t_stop) and self.t_stop > 0:
            return [(float(self.t_stop), "stop" + (" (then holds)" if self.holds else " (then rolls back)"))]
        return []

    def predictions(self) -> dict[str, str]:
        out = {"regime": self.regime}
        out.update({f"phase {k + 1} from t = {t0:.6g} s": f"acceleration {a:.6g} m/s^2 from {u:.6g} m/s"
                    for k, (t0, _s, u, a) in enumerate(self.phases)})
        if math.isfinite(self.t_stop) and self.t_stop > 0:
            out["stop time"] = f"{self.t_stop:.6g} s"
        return out

    def metrics(self, trace) -> dict[str, float]:
        out = super().metrics(trace)
        i = self.body.index
        t = trace.t
        if self.fit_phase is not None and self.fit_phase[3] != 0.0:
            t0, _, _, a = self.fit_phase
            ends = [p[0] for p in self.phases if p[0] > t0]
            t1 = min(ends[0] if ends else t[-1], t[-1])
            lo = int(np.searchsorted(t, t0 + SKIP_FRACTION * (t1 - t0), side="left"))
            hi = int(np.searchsorted(t, t0 + 0.9 * (t1 - t0), side="right"))
            w = slice(lo, max(hi, lo + 3))
            a_meas = fit_slope(t[w], self.along(trace)[w])
            alpha_meas = fit_slope(t[w], trace.angvel[w, i] @ self.axis)
            out["roll_accel"] = a_meas
            out["spin_accel"] = alpha_meas
            out["roll_accel_error"] = abs(a_meas - a) / abs(a)
            divide(out, "spin_accel_error", abs(alpha_meas - a / self.R), abs(a / self.R),
                   "the reference angular acceleration")
            vc = trace.vel[w, i] + np.cross(trace.angvel[w, i], -self.R * self.n)
            out["rolling_slip"] = float(np.nanmax(np.linalg.norm(vc, axis=1)))
        if math.isfinite(self.t_stop) and self.holds and (t >= self.t_stop).any():
            self.stop_metrics(trace, out, self.t_stop, float(self.distance(np.array([self.t_stop]))[0]),
                              self.phases[0][3] if self.phases else 0.0)
        return out
