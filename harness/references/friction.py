"""Coulomb friction on an incline: a sliding/sticking block and a rolling or
slipping sphere.

The slope is the scene's ``slope`` static (normal n = (sin a, 0, cos a),
downhill d = (cos a, 0, -sin a)); gravity g acts along -z, so along the slope
the driving acceleration is g_d = g . d = |g| sin a and the normal load per
unit mass is g_n = -g . n = |g| cos a.  Coefficients are the body-slope pair's
(static mu_s, kinetic mu_k).

Block (``incline_block``), starting at rest:

    tan a <= mu_s :  sticks, a = 0
    tan a >  mu_s :  slides, a = g (sin a - mu_k cos a)

(with an initial velocity along the slope the block slides with
a = g sin a -+ mu_k g cos a until it stops, then the static test applies).

Sphere (``rolling_sphere``), radius R, moment of inertia I about a diameter,
k = I / (m R^2) (2/5 for a solid sphere), starting at rest: rolling without
slipping needs the friction force f = m g sin a k / (1 + k) to stay within
mu_s m g cos a:

    mu_s >= tan a k / (1 + k)  (2/7 tan a) :  rolls,
        a = g sin a / (1 + k)  (5/7 g sin a),  alpha = a / R
    otherwise :  slips with kinetic friction,
        a = g (sin a - mu_k cos a),  alpha = mu_k m g cos a R / I

(alpha is the angular acceleration about e = n x d, the axis a ball rolling
downhill spins about).

Measured accelerations are least-squares slopes of the velocity along d
(and of the angular velocity about e) over the run after its first 10 %
(contacts settle in the first steps).
"""

from __future__ import annotations

import math

import numpy as np

from adapters.conventions import quat_to_matrix
from harness.references import ReferenceError, ReferenceModel, trajectory_metrics

SKIP_FRACTION = 0.10  # initial part of the run left out of acceleration fits


def _fit_slope(t: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope dy/dt of y (F,) over t (F,)."""
    tm = t - t.mean()
    den = float(tm @ tm)
    return float(tm @ (y - y.mean()) / den) if den > 0 else math.nan


def _window(t: np.ndarray) -> slice:
    start = int(np.searchsorted(t, SKIP_FRACTION * t[-1], side="left"))
    start = min(start, max(len(t) - 3, 0))
    return slice(start, len(t))


class _SlopeModel(ReferenceModel):
    params_allowed = ("body", "slope")

    def __init__(self, scene):
        super().__init__(scene)
        bname = self.param("body")
        if bname is None:
            if scene.n_bodies != 1:
                raise ReferenceError(f"{self.name} needs exactly one body (or params.body), the scene has {scene.n_bodies}")
            self.body = scene.bodies[0]
        else:
            self.body = scene.bodies[scene.body_index(bname)]
        sname = self.param("slope")
        slopes = [s for s in scene.statics if s.kind == "slope" and (sname is None or s.name == sname)]
        if len(slopes) != 1:
            raise ReferenceError(f"{self.name} needs exactly one slope static (or params.slope naming one)")
        self.slope = slopes[0]
        g = scene.gravity
        self.gmag = float(np.linalg.norm(g))
        if self.gmag == 0 or abs(g[0]) > 0 or abs(g[1]) > 0:
            raise ReferenceError(f"{self.name} needs gravity along -z")
        a = math.radians(self.slope.angle)
        self.theta = a
        self.n = self.slope.normal.copy()
        self.d = np.array([math.cos(a), 0.0, -math.sin(a)])
        self.axis = np.cross(self.n, self.d)  # spin axis of a ball rolling downhill
        self.g_d = float(g @ self.d)   # = g sin a
        self.g_n = float(-(g @ self.n))  # = g cos a
        mat = scene.pair(self.body.material, self.slope.material)
        self.mu_s, self.mu_k = mat.static_friction, mat.friction
        self.x0 = self.body.position.copy()
        self.u0 = float(self.body.velocity @ self.d)
        if not scene.has("contact"):
            raise ReferenceError(f"{self.name} needs the 'contact' effect")

    def along(self, trace) -> np.ndarray:
        """Velocity along the downhill direction (F,)."""
        return trace.vel[:, self.body.index] @ self.d

    def positions(self, t: np.ndarray) -> np.ndarray:
        s = self.distance(np.asarray(t, float))
        p = self.x0 + np.outer(s, self.d)
        out = np.full((len(t), self.scene.n_bodies, 3), np.nan)
        out[:, self.body.index] = p
        return out

    def metrics(self, trace) -> dict[str, float]:
        i = self.body.index
        ref = self.positions(trace.t)
        return trajectory_metrics(trace.pos[:, [i]], ref[:, [i]])


class InclineBlock(_SlopeModel):
    """Block on an incline: sticks below atan(mu_s), slides above.

    Metrics: ``stick_creep`` (m, sticking regime): the largest displacement
    of the block within the slope's plane (the normal component, sinking into
    a soft contact, left out) at any time; ``slide_accel_error`` (sliding
    regime): |a_measured - a| / |a| with a = g (sin a - mu_k cos a);
    ``slide_accel`` the measured value (m/s^2).  Each is reported only in its
    regime (a block with an initial velocity that stops reports both).
    """

    name = "incline_block"

    def __init__(self, scene):
        super().__init__(scene)
        self.sticks_at_rest = math.tan(self.theta) <= self.mu_s + 1e-15
        u0 = self.u0
        if u0 > 0:
            self.a_slide = self.g_d - self.mu_k * self.g_n
        elif u0 < 0:
            self.a_slide = self.g_d + self.mu_k * self.g_n
        else:
            self.a_slide = 0.0 if self.sticks_at_rest else self.g_d - self.mu_k * self.g_n
        # time the block stops (if it decelerates to rest)
        if u0 != 0 and self.a_slide * u0 < 0:
            self.t_stop = -u0 / self.a_slide
        elif u0 == 0 and self.sticks_at_rest:
            self.t_stop = 0.0
        else:
            self.t_stop = math.inf
        if math.isfinite(self.t_stop) and not self.sticks_at_rest:
            raise ReferenceError("incline_block: a block that stops and then slides again is not modelled")

    @property
    def regime(self) -> str:
        return "stick" if self.t_stop == 0.0 else "slide"

    def distance(self, t: np.ndarray) -> np.ndarray:
        """Reference distance travelled downhill (m) at times t (F,)."""
        tt = np.minimum(t, self.t_stop)
        return self.u0 * tt + 0.5 * self.a_slide * tt * tt

    def metrics(self, trace) -> dict[str, float]:
        out = super().metrics(trace)
        i = self.body.index
        if math.isfinite(self.t_stop):
            # displacement within the slope plane after the (reference) stop
            s_stop = float(self.distance(np.array([self.t_stop]))[0])
            rel = trace.pos[:, i] - (self.x0 + s_stop * self.d)
            tang = rel - np.outer(rel @ self.n, self.n)
            after = trace.t >= self.t_stop
            out["stick_creep"] = float(np.nanmax(np.linalg.norm(tang[after], axis=1)))
        if self.t_stop > 0:
            w = _window(trace.t)
            if math.isfinite(self.t_stop):
                w = slice(w.start, max(int(np.searchsorted(trace.t, 0.9 * self.t_stop)), w.start + 3))
            a_meas = _fit_slope(trace.t[w], self.along(trace)[w])
            out["slide_accel"] = a_meas
            out["slide_accel_error"] = abs(a_meas - self.a_slide) / abs(self.a_slide)
        return out


class RollingSphere(_SlopeModel):
    """Sphere released from rest on an incline: rolls (a = g sin a / (1 + k))
    or slips (a = g (sin a - mu_k cos a)); see the module docstring.

    Metrics: ``roll_accel_error`` = |a_meas - a| / a (linear acceleration
    downhill); ``spin_accel_error`` = |alpha_meas - alpha| / alpha (angular
    acceleration about n x d); ``rolling_slip`` (m/s): the largest speed of
    the contact point, |v + w x (-R n)|, over the fitted window (0 for rolling
    without slipping).  Plus the measured ``roll_accel`` and ``spin_accel``.
    """

    name = "rolling_sphere"

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

    def metrics(self, trace) -> dict[str, float]:
        out = super().metrics(trace)
        i = self.body.index
        w = _window(trace.t)
        a_meas = _fit_slope(trace.t[w], self.along(trace)[w])
        alpha_meas = _fit_slope(trace.t[w], trace.angvel[w, i] @ self.axis)
        out["roll_accel"] = a_meas
        out["spin_accel"] = alpha_meas
        out["roll_accel_error"] = abs(a_meas - self.a) / abs(self.a)
        out["spin_accel_error"] = abs(alpha_meas - self.alpha) / abs(self.alpha)
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

    def _check_body(self, b) -> None:
        if b.shape != "cylinder":
            raise ReferenceError(f"rolling_cylinder needs a cylinder, body {b.name!r} is a {b.shape}")
        q = np.asarray(b.orientation, float)
        ez = quat_to_matrix(q / np.linalg.norm(q))[:, 2]  # the body's z axis (the cylinder's axis) in the world
        if abs(abs(float(ez @ self.axis)) - 1.0) > 1e-9:
            raise ReferenceError(f"rolling_cylinder needs the cylinder's axis along the roll axis n x d = "
                                 f"{self.axis.round(6).tolist()}; body {b.name!r} has its axis along {ez.round(6).tolist()}")

    def _axis_inertia(self, b) -> float:
        return float(b.inertia[2])  # principal moment about the body z axis
