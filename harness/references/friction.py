"""Coulomb friction on an incline: a sliding/sticking block and a rolling or
slipping sphere.

The slope is the scene's ``slope`` static (normal n = (sin a, 0, cos a),
downhill d = (cos a, 0, -sin a)), or a level ``plane`` as the flat case
(a = 0, n = +z, d the direction of the body's initial horizontal velocity,
+x if it has none); gravity g acts along -z, so along the slope
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

from contract.rotation import quat_rotate, quat_to_matrix
from harness.references import (BODY_PARAM, TRAJECTORY, Param, ReferenceError, ReferenceModel, ReferenceSeries,
                                trajectory_metrics)

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


def _check_axis_across(model: str, b, axis: np.ndarray) -> None:
    """Refuse a cylinder whose axis (body z) is not along the roll axis
    ``axis`` = n x d (lying across the slope)."""
    q = np.asarray(b.orientation, float)
    ez = quat_to_matrix(q / np.linalg.norm(q))[:, 2]  # the body's z axis (the cylinder's axis) in the world
    if abs(abs(float(ez @ axis)) - 1.0) > 1e-9:
        raise ReferenceError(f"{model} needs the cylinder's axis along the roll axis n x d = "
                             f"{axis.round(6).tolist()}; body {b.name!r} has its axis along {ez.round(6).tolist()}")


class _SlopeModel(ReferenceModel):
    params = (BODY_PARAM, Param("slope", "str", None,
                                "the slope static, or level plane, the body is on (default: the scene's only one)"))
    SURFACE = ("one `slope` static or one level `plane` (the flat case; downhill = the initial velocity's "
               "direction), gravity along -z, the 'contact' effect, the body-surface pair's friction")

    def __init__(self, scene):
        super().__init__(scene)
        self.body = self.the_body()
        sname = self.param("slope")
        level = [s for s in scene.statics if s.kind == "plane" and abs(float(s.normal[2]) - 1.0) <= 1e-12]
        slopes = [s for s in list(scene.statics) if (s.kind == "slope" or s in level)
                  and (sname is None or s.name == sname)]
        if len(slopes) != 1:
            named = [s for s in scene.statics if s.name == sname]
            what = (f"static {sname!r} is a {named[0].kind} that is not level: give an incline as a 'slope'"
                    if named else f"the scene has {len(slopes)} slopes and level planes")
            raise ReferenceError(f"{self.name} needs exactly one slope or level plane static (or params.slope naming "
                                 f"one); {what}", key="reference.params.slope" if sname else "static")
        self.slope = slopes[0]
        g = scene.gravity
        self.gmag = float(np.linalg.norm(g))
        if self.gmag == 0 or abs(g[0]) > 0 or abs(g[1]) > 0:
            raise ReferenceError(f"{self.name} needs gravity along -z", key="scenario.gravity")
        if self.slope.kind == "slope":
            a = math.radians(self.slope.angle)
            self.d = np.array([math.cos(a), 0.0, -math.sin(a)])
        else:
            a = 0.0
            vh = self.body.velocity * np.array([1.0, 1.0, 0.0])
            nv = float(np.linalg.norm(vh))
            self.d = vh / nv if nv > 0 else np.array([1.0, 0.0, 0.0])
        self.theta = a
        self.n = self.slope.normal.copy()
        self.axis = np.cross(self.n, self.d)  # spin axis of a ball rolling downhill
        self.g_d = float(g @ self.d)   # = g sin a
        self.g_n = float(-(g @ self.n))  # = g cos a
        mat = scene.pair(self.body.material, self.slope.material)
        self.mu_s, self.mu_k = mat.static_friction, mat.friction
        self.x0 = self.body.position.copy()
        self.u0 = float(self.body.velocity @ self.d)
        if not scene.has("contact"):
            raise ReferenceError(f"{self.name} needs the 'contact' effect", key="scenario.effects")

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

    A block thrown uphill on a slope steeper than atan(mu_s) decelerates
    with a = g (sin a + mu_k cos a), stops at t_stop = |u0| / a and slides
    back down with a_back = g (sin a - mu_k cos a) from rest: then
    ``return_accel_error`` = |a_measured - a_back| / a_back over the slide
    back (after its first 10 %), ``return_accel`` the measured value, and
    no ``stick_creep``.  The trajectory metrics follow the whole path: a
    turnaround late by a fraction of a step leaves a constant velocity
    error, and the position error grows linearly after it.
    """

    name = "incline_block"
    summary = "a block on an incline (or a level plane): sticks below atan(mu_s), slides with g (sin a -+ mu_k cos a)"
    takes = ("one body on " + _SlopeModel.SURFACE + "; its initial velocity along the downhill direction. "
             "Refuses a block that would slide at constant speed (no acceleration to measure: a flat frictionless "
             "surface, or tan a = mu_k with a speed)")
    produces = {
        "slide_accel": "measured acceleration along the slope while sliding (m/s^2)",
        "slide_accel_error": "|a_measured - a| / |a| while sliding (1)",
        "stick_creep": "largest displacement within the slope's plane after the (reference) stop (m)",
        "return_accel": "measured acceleration of the slide back after a stop on a steep slope (m/s^2)",
        "return_accel_error": "|a_measured - a_back| / a_back (1)",
        **TRAJECTORY,
    }
    primary = "slide_accel_error"

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
        # after a stop on a slope steeper than atan(mu_s) it slides back
        # down with a = g (sin a - mu_k cos a) (from rest, downhill)
        self.a_back = 0.0
        if math.isfinite(self.t_stop) and self.t_stop > 0 and not self.sticks_at_rest:
            self.a_back = self.g_d - self.mu_k * self.g_n
        if self.t_stop > 0 and self.a_slide == 0.0:
            raise ReferenceError(
                f"{self.name}: the block slides at a constant {u0:g} m/s (slope {math.degrees(self.theta):g} deg, "
                f"mu_k = {self.mu_k:g}): there is no acceleration to measure and no stop; give it friction, a "
                "slope, or no speed", key=f"static[{self.slope.index}]")
        # what follows the stop (stick_creep, return_accel) needs frames after it
        # (tests/test_fuzz.py::test_incline_block_refuses_a_run_that_ends_before_the_stop)
        if 0 < self.t_stop < math.inf and scene.duration <= self.t_stop:
            raise self._ends_before_stop(scene.duration)

    def _ends_before_stop(self, t_end: float) -> ReferenceError:
        after = "it slides back" if self.a_back else "it sticks"
        return ReferenceError(f"{self.name}: the run ends at {t_end:g} s, before the stop at t_stop = "
                              f"{self.t_stop:.6g} s (after which {after}): nothing to measure there",
                              key="scenario.duration")

    @property
    def regime(self) -> str:
        return "stick" if self.t_stop == 0.0 else "slide"

    def predictions(self) -> dict[str, str]:
        out = {"regime": self.regime, "acceleration along the slope": f"{self.a_slide:.6g} m/s^2"}
        if math.isfinite(self.t_stop) and self.t_stop > 0:
            out["stop time"] = f"{self.t_stop:.6g} s"
            if self.a_back:
                out["acceleration sliding back"] = f"{self.a_back:.6g} m/s^2"
        return out

    def reference_series(self) -> list[ReferenceSeries]:
        """The distance travelled downhill (m), levelling off at the stop."""
        i, x0, d = self.body.index, self.x0, self.d
        return [ReferenceSeries(f"{self.body.name}/distance", "m", "distance travelled downhill", self.distance,
                                lambda tr: (tr.pos[:, i] - x0) @ d)]

    def reference_times(self) -> list[tuple[float, str]]:
        if math.isfinite(self.t_stop) and self.t_stop > 0:
            return [(float(self.t_stop), "stop" + (" (then slides back)" if self.a_back else ""))]
        return []

    def distance(self, t: np.ndarray) -> np.ndarray:
        """Reference distance travelled downhill (m) at times t (F,)."""
        tt = np.minimum(t, self.t_stop)
        s = self.u0 * tt + 0.5 * self.a_slide * tt * tt
        if self.a_back:
            back = np.maximum(t - self.t_stop, 0.0)
            s = s + 0.5 * self.a_back * back * back
        return s

    def metrics(self, trace) -> dict[str, float]:
        out = super().metrics(trace)
        i = self.body.index
        if math.isfinite(self.t_stop) and not self.a_back:
            # displacement within the slope plane after the (reference) stop
            s_stop = float(self.distance(np.array([self.t_stop]))[0])
            rel = trace.pos[:, i] - (self.x0 + s_stop * self.d)
            tang = rel - np.outer(rel @ self.n, self.n)
            after = trace.t >= self.t_stop
            if not after.any():
                raise self._ends_before_stop(float(trace.t[-1]))
            out["stick_creep"] = float(np.nanmax(np.linalg.norm(tang[after], axis=1)))
        if self.t_stop > 0:
            w = _window(trace.t)
            if math.isfinite(self.t_stop):
                w = slice(w.start, max(int(np.searchsorted(trace.t, 0.9 * self.t_stop)), w.start + 3))
            a_meas = _fit_slope(trace.t[w], self.along(trace)[w])
            out["slide_accel"] = a_meas
            out["slide_accel_error"] = abs(a_meas - self.a_slide) / abs(self.a_slide)
        if self.a_back:
            t_end = float(trace.t[-1])
            start = self.t_stop + SKIP_FRACTION * max(t_end - self.t_stop, 0.0)
            w = slice(min(int(np.searchsorted(trace.t, start)), max(len(trace.t) - 3, 0)), len(trace.t))
            a_meas = _fit_slope(trace.t[w], self.along(trace)[w])
            out["return_accel"] = a_meas
            out["return_accel_error"] = abs(a_meas - self.a_back) / abs(self.a_back)
        return out


class SlideToRest(InclineBlock):
    """A box given a speed u0 along a level plane or a slope slides to rest
    under kinetic friction and stays there.

    Deceleration along the motion: level, mu_k g; down a slope of angle a,
    g (mu_k cos a - sin a); up it, g (sin a + mu_k cos a).  Then

        stop distance  d = u0^2 / (2 |a|)   (v^2 / (2 mu_k g) on the level)
        stop time      t_stop = |u0| / |a|

    What it refuses (load time, naming the surface): a box sliding down a
    slope at or steeper than the kinetic friction angle atan(mu_k) never
    stops (g sin a >= mu_k g cos a); a box sent up a slope steeper than the
    static friction angle atan(mu_s) stops and slides back down
    (``incline_block`` models both); a run that ends before t_stop.

    Metrics: ``stop_distance`` (m) the distance the centre moved along the
    motion by the last frame, ``stop_distance_error`` = |d_meas - d| / d;
    ``stop_time`` (s) where the least-squares line of the speed along the
    motion (10 % to 90 % of t_stop) reaches zero, ``stop_time_error`` =
    |t_meas - t_stop| / t_stop; incline_block's ``slide_accel(_error)``,
    ``stick_creep`` and the trajectory metrics.
    """

    name = "slide_to_rest"
    summary = "a box given a speed on a level or inclined frictional plane slides to rest: d = v^2 / (2 mu_k g) on the level"
    takes = ("one body with an initial velocity along the downhill direction (up or down; on a level plane any "
             "horizontal direction) on " + _SlopeModel.SURFACE + ", mu_k > 0. Refuses a slope at or steeper than "
             "atan(mu_k) going down (never stops), steeper than atan(mu_s) going up (slides back: use "
             "incline_block), and a duration shorter than the stop time")
    produces = {
        "stop_distance": "distance the centre moved along the motion by the last frame (m)",
        "stop_distance_ref": "u0^2 / (2 |a|) (m)",
        "stop_distance_error": "|d_measured - d| / d (1)",
        "stop_time": "zero of the fitted speed line (s)",
        "stop_time_ref": "|u0| / |a| (s)",
        "stop_time_error": "|t_measured - t_stop| / t_stop (1)",
        "slide_accel": InclineBlock.produces["slide_accel"],
        "slide_accel_error": InclineBlock.produces["slide_accel_error"],
        "stick_creep": InclineBlock.produces["stick_creep"],
        **TRAJECTORY,
    }
    primary = "stop_distance_error"

    def __init__(self, scene):
        super().__init__(scene)
        b, where = self.body, f"static[{self.slope.index}]"
        deg = math.degrees(self.theta)
        if self.u0 == 0.0 or not np.allclose(b.velocity, self.u0 * self.d, atol=1e-12 * abs(self.u0)):
            raise ReferenceError(f"slide_to_rest needs an initial velocity along {self.d.round(6).tolist()} "
                                 "(down or up the slope; on a level plane, horizontal)", key="body")
        if self.u0 > 0 and self.a_slide >= 0:
            raise ReferenceError(
                f"slide_to_rest: a {deg:g} deg slope is at or steeper than the kinetic friction angle "
                f"atan(mu_k) = {math.degrees(math.atan(self.mu_k)):.6g} deg: sliding down, the box never stops "
                "(use incline_block)", key=where)
        if self.a_back:
            raise ReferenceError(
                f"slide_to_rest: a {deg:g} deg slope is steeper than the static friction angle atan(mu_s) = "
                f"{math.degrees(math.atan(self.mu_s)):.6g} deg: the box stops and slides back down "
                "(use incline_block, which models the return)", key=where)
        self.d_stop = self.u0 * self.u0 / (2.0 * abs(self.a_slide))

    def metrics(self, trace) -> dict[str, float]:
        out = super().metrics(trace)
        i, sgn = self.body.index, math.copysign(1.0, self.u0)
        d = float((trace.pos[-1, i] - self.x0) @ self.d) * sgn
        out["stop_distance"] = d
        out["stop_distance_ref"] = self.d_stop
        out["stop_distance_error"] = abs(d - self.d_stop) / self.d_stop
        t = trace.t
        lo = int(np.searchsorted(t, SKIP_FRACTION * self.t_stop, side="left"))
        hi = max(int(np.searchsorted(t, 0.9 * self.t_stop, side="right")), lo + 3)
        speed = self.along(trace)[lo:hi] * sgn
        slope = _fit_slope(t[lo:hi], speed)
        t_meas = float(t[lo:hi].mean() - speed.mean() / slope) if slope < 0 else math.inf
        out["stop_time"] = t_meas
        out["stop_time_ref"] = self.t_stop
        out["stop_time_error"] = abs(t_meas - self.t_stop) / self.t_stop
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
    window; ``stick_creep`` (m) for a ball that holds: its largest
    displacement within the slope's plane from the reference stopping point
    after it (stopping distance errors show up here and in
    ``final_position_error``); plus ``trajectory_rmse`` and
    ``final_position_error``.
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
        "stick_creep": "largest displacement within the slope's plane from the reference stop after it (m)",
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
            a_meas = _fit_slope(t[w], self.along(trace)[w])
            alpha_meas = _fit_slope(t[w], trace.angvel[w, i] @ self.axis)
            out["roll_accel"] = a_meas
            out["spin_accel"] = alpha_meas
            out["roll_accel_error"] = abs(a_meas - a) / abs(a)
            out["spin_accel_error"] = abs(alpha_meas - a / self.R) / abs(a / self.R)
            vc = trace.vel[w, i] + np.cross(trace.angvel[w, i], -self.R * self.n)
            out["rolling_slip"] = float(np.nanmax(np.linalg.norm(vc, axis=1)))
        if math.isfinite(self.t_stop) and self.holds:
            s_stop = float(self.distance(np.array([self.t_stop]))[0])
            rel = trace.pos[:, i] - (self.x0 + s_stop * self.d)
            tang = rel - np.outer(rel @ self.n, self.n)
            after = t >= self.t_stop
            if after.any():
                out["stick_creep"] = float(np.nanmax(np.linalg.norm(tang[after], axis=1)))
        return out


class SpinToRest(ReferenceModel):
    """A capsule lying on a level plane, spun about the plane's normal, comes
    to rest under kinetic friction (twist friction of two point contacts).

    A capsule lying flat (its axis perpendicular to the normal n) touches
    the plane at two points, the bottoms of its end spheres, at +-h (its
    half_length) along the axis from the centre of mass; by symmetry each
    carries m g / 2.  Spinning at w about n, both points slide (speed
    |w| h) in opposite directions, so kinetic friction mu_k m g / 2 at each
    is a pure couple about n (the two forces' lever arm below the centre,
    -r n, cancels between them) of magnitude mu_k m g h:

        alpha = mu_k m g h / I_n,   t_stop = |w0| / alpha,
        angle turned = w0^2 / (2 alpha)   (then it stays: nothing drives it)

    with I_n the moment of inertia about n through the centre (a transverse
    principal moment of the capsule, so the rotation stays about n).  The
    static coefficient plays no part: every point slides until the stop.
    This is the case where a point-contact model is exact -- a flat face or
    a line contact would need a pressure distribution, which rigid bodies
    leave undetermined.

    Metrics: ``spin_decel_error`` = |alpha_meas - alpha| / alpha, alpha_meas
    the least-squares slope of -sign(w0) w.n between 10 % and 90 % of
    t_stop, or of the measured stop (the spin below 1 % of |w0|) if that
    comes first; ``spin_stop_angle_error`` (relative) = |theta_end - theta_stop|
    / |theta_stop|, theta_end the angle the axis has turned about n at the
    last frame (reported when the run lasts past t_stop); ``spin_decel``
    (rad/s^2) and ``spin_stop_angle`` (rad) the measured values; plus
    ``trajectory_rmse`` and ``final_position_error`` of the centre, which
    stays where it started.
    """

    name = "spin_to_rest"
    summary = "a capsule lying on a level plane, spun about the normal, stops under twist friction"
    takes = ("one capsule lying flat on exactly one level plane, centre at rest, angular velocity along the normal, "
             "the 'contact' and 'friction' effects, kinetic friction > 0")
    params = (BODY_PARAM,)
    produces = {
        "spin_decel": "measured angular deceleration (rad/s^2)",
        "spin_decel_error": "|alpha_measured - alpha| / alpha (1)",
        "spin_stop_angle": "angle turned about the normal at the last frame (rad)",
        "spin_stop_angle_error": "|theta_end - theta_stop| / |theta_stop| (1)",
        **TRAJECTORY,
    }
    primary = "spin_decel_error"

    def __init__(self, scene):
        super().__init__(scene)
        self.body = b = self.the_body()
        if b.shape != "capsule":
            raise ReferenceError(f"spin_to_rest needs a capsule, body {b.name!r} is a {b.shape}")
        planes = [s for s in scene.statics if s.shape == "plane"]
        if len(planes) != 1:
            raise ReferenceError(f"spin_to_rest needs exactly one plane static, the scene has {len(planes)}")
        plane = planes[0]
        n = np.asarray(plane.normal, float) / np.linalg.norm(plane.normal)
        g = np.asarray(scene.gravity, float)
        gmag = float(np.linalg.norm(g))
        if gmag == 0 or abs(float(g @ n) + gmag) > 1e-9 * gmag:
            raise ReferenceError("spin_to_rest needs a level plane: gravity along -normal")
        for eff in ("contact", "friction"):
            if not scene.has(eff):
                raise ReferenceError(f"spin_to_rest needs the {eff!r} effect")
        q = np.asarray(b.orientation, float)
        axis = quat_to_matrix(q / np.linalg.norm(q))[:, 2]
        if abs(float(axis @ n)) > 1e-9:
            raise ReferenceError(f"spin_to_rest needs the capsule lying flat: its axis {axis.round(6).tolist()} "
                                 f"perpendicular to the plane's normal {n.round(6).tolist()}")
        height = float(b.position @ n) - plane.offset
        if abs(height - b.radius) > 1e-9:
            raise ReferenceError(f"spin_to_rest needs the capsule resting on the plane: centre {height:.9g} m above it, "
                                 f"radius {b.radius:.9g} m")
        if np.any(b.velocity != 0):
            raise ReferenceError("spin_to_rest needs the capsule's centre at rest (velocity = 0)")
        w0 = float(b.angular_velocity @ n)
        if w0 == 0 or not np.allclose(b.angular_velocity, w0 * n, atol=1e-12):
            raise ReferenceError(f"spin_to_rest needs an angular velocity along the normal {n.round(6).tolist()}")
        mat = scene.pair(b.material, plane.material)
        self.mu_k = mat.friction
        if self.mu_k <= 0:
            raise ReferenceError("spin_to_rest needs kinetic friction > 0")
        # a transverse principal moment: the capsule's axis is body z
        self.I_n = float(b.inertia[0])
        self.n, self.axis0, self.w0, self.x0 = n, axis, w0, b.position.copy()
        self.alpha = self.mu_k * b.mass * gmag * b.half_length / self.I_n
        self.t_stop = abs(w0) / self.alpha
        self.theta_stop = math.copysign(w0 * w0 / (2.0 * self.alpha), w0)

    def angle(self, t: np.ndarray) -> np.ndarray:
        """Reference angle (rad, signed like w0) turned about n at times t."""
        tt = np.minimum(np.asarray(t, float), self.t_stop)
        return self.w0 * tt - math.copysign(0.5 * self.alpha, self.w0) * tt * tt

    def positions(self, t: np.ndarray) -> np.ndarray:
        out = np.full((len(t), self.scene.n_bodies, 3), np.nan)
        out[:, self.body.index] = self.x0
        return out

    def reference_series(self) -> list[ReferenceSeries]:
        """The angle turned about the normal (rad), levelling off at the stop."""
        return [ReferenceSeries(f"{self.body.name}/angle_turned", "rad",
                                f"angle turned: {self.theta_stop:.6g} rad at the stop", self.angle, self.turned)]

    def reference_times(self) -> list[tuple[float, str]]:
        return [(float(self.t_stop), "spin stops")]

    def turned(self, trace) -> np.ndarray:
        """Angle (rad, unwrapped) the capsule's axis has turned about n, (F,)."""
        i = self.body.index
        e = quat_rotate(trace.quat[:, i], np.broadcast_to([0.0, 0.0, 1.0], (len(trace.t), 3)))
        s = np.cross(self.axis0, e) @ self.n
        return np.unwrap(np.arctan2(s, e @ self.axis0))

    def predictions(self) -> dict[str, str]:
        return {"spin deceleration": f"{self.alpha:.6g} rad/s^2", "stop time": f"{self.t_stop:.6g} s",
                "angle turned": f"{self.theta_stop:.6g} rad"}

    def metrics(self, trace) -> dict[str, float]:
        i = self.body.index
        out = trajectory_metrics(trace.pos[:, [i]], self.positions(trace.t)[:, [i]])
        t = trace.t
        # the spin-down as measured: up to 90 % of the earlier of the two
        # stops (a fit running past an early stop averages the fast
        # spin-down with the rest that follows it)
        spin = math.copysign(1.0, self.w0) * (trace.angvel[:, i] @ self.n)
        low = np.flatnonzero(spin <= 0.01 * abs(self.w0))
        t_end = min(self.t_stop, float(t[low[0]]) if low.size else math.inf)
        lo = int(np.searchsorted(t, SKIP_FRACTION * t_end, side="left"))
        hi = max(int(np.searchsorted(t, 0.9 * t_end, side="right")), lo + 3)
        decel = -_fit_slope(t[lo:hi], spin[lo:hi])
        out["spin_decel"] = decel
        out["spin_decel_error"] = abs(decel - self.alpha) / self.alpha
        if t[-1] > self.t_stop:
            th = float(self.turned(trace)[-1])
            out["spin_stop_angle"] = th
            out["spin_stop_angle_error"] = abs(th - self.theta_stop) / abs(self.theta_stop)
        return out
