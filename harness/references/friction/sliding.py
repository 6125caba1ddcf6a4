"""A block on an incline: sticking, sliding, thrown uphill and sliding back;
and a block sliding to rest on a level plane."""

from __future__ import annotations

import math

import numpy as np

from physbench.harness.references import TRAJECTORY, ReferenceError, ReferenceSeries, divide, fit_slope
from physbench.harness.references.friction.slope import SKIP_FRACTION, STOP_METRICS, _SlopeModel, _window


class InclineBlock(_SlopeModel):
    """Block on an incline: sticks below atan(mu_s), slides above.

    Metrics, for a block that stops (or starts at rest) and holds
    (distances within the slope's plane: the normal component, sinking into
    a soft contact, left out): ``stop_position_error`` (m) the largest
    distance from the reference stop point from the reference stop time on
    (where it stopped: the stop distance's error plus any creep);
    ``creep`` (m) the largest displacement after the body came to rest,
    from where it came to rest (for a start at rest both are the largest
    displacement from the start); ``slide_accel_error`` (sliding
    regime): |a_measured - a| / |a| with a = g (sin a - mu_k cos a);
    ``slide_accel`` the measured value (m/s^2).  Each is reported only in its
    regime (a block with an initial velocity that stops reports both).

    A block thrown uphill on a slope steeper than atan(mu_s) decelerates
    with a = g (sin a + mu_k cos a), stops at t_stop = |u0| / a and slides
    back down with a_back = g (sin a - mu_k cos a) from rest: then
    ``return_accel_error`` = |a_measured - a_back| / a_back over the slide
    back (after its first 10 %), ``return_accel`` the measured value, and
    no ``stop_position_error`` or ``creep``.  The trajectory metrics follow the whole path: a
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
        **STOP_METRICS,
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
        # what follows the stop (stop_position_error, creep, return_accel) needs frames after it
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
            if not (trace.t >= self.t_stop).any():
                raise self._ends_before_stop(float(trace.t[-1]))
            self.stop_metrics(trace, out, self.t_stop, float(self.distance(np.array([self.t_stop]))[0]), self.a_slide)
        if self.t_stop > 0:
            w = _window(trace.t)
            if math.isfinite(self.t_stop):
                w = slice(w.start, max(int(np.searchsorted(trace.t, 0.9 * self.t_stop)), w.start + 3))
            a_meas = fit_slope(trace.t[w], self.along(trace)[w])
            out["slide_accel"] = a_meas
            out["slide_accel_error"] = abs(a_meas - self.a_slide) / abs(self.a_slide)
        if self.a_back:
            t_end = float(trace.t[-1])
            start = self.t_stop + SKIP_FRACTION * max(t_end - self.t_stop, 0.0)
            w = slice(min(int(np.searchsorted(trace.t, start)), max(len(trace.t) - 3, 0)), len(trace.t))
            a_meas = fit_slope(trace.t[w], self.along(trace)[w])
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
    ``stop_position_error``, ``creep`` and the trajectory metrics.
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
        **STOP_METRICS,
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
        # d_stop = u0^2 / (2 |a|) is 0 for a speed whose square underflows
        divide(out, "stop_distance_error", abs(d - self.d_stop), self.d_stop, "the reference stop distance")
        t = trace.t
        lo = int(np.searchsorted(t, SKIP_FRACTION * self.t_stop, side="left"))
        hi = max(int(np.searchsorted(t, 0.9 * self.t_stop, side="right")), lo + 3)
        speed = self.along(trace)[lo:hi] * sgn
        slope = fit_slope(t[lo:hi], speed)
        t_meas = float(t[lo:hi].mean() - speed.mean() / slope) if slope < 0 else math.inf
        out["stop_time"] = t_meas
        out["stop_time_ref"] = self.t_stop
        divide(out, "stop_time_error", abs(t_meas - self.t_stop), self.t_stop, "the reference stop time")
        return out
