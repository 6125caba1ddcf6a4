"""The slope every friction model but the spin stands on (normal, downhill
direction, gravity components, the pair's coefficients) and the fits of
its measured accelerations."""

from __future__ import annotations

import math

import numpy as np

from physbench.contract.rotation import quat_to_matrix
from physbench.harness.references import (BODY_PARAM, Param, ReferenceError, ReferenceModel, ReferenceSeries, fit_slope,
                                trajectory_metrics, undefined)

SKIP_FRACTION = 0.10  # initial part of the run left out of acceleration fits
#: the two metrics of a body that comes to rest and should stay there
STOP_METRICS = {
    "stop_position_error": "largest distance within the slope's plane from the reference stop point, over the "
                           "frames from the reference stop time on (m)",
    "creep": "largest displacement within the slope's plane after the body came to rest, from its position then: "
             "the first frame whose speed along the initial motion is at most |a| dt_frame (what the reference "
             "deceleration a takes off in one frame interval) and either <= 0 or still > 0 at the next frame; "
             "the first frame for a start at rest (m)",
}


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

    def rolling_series(self, speed, spin, what: str) -> list[ReferenceSeries]:
        """The body's speed downhill (m/s) and spin about n x d (rad/s) as
        reference lines: ``speed(t)``, ``spin(t)`` the model's (``what``:
        its accelerations, for the text), each with its measured twin
        (:meth:`along`, the angular velocity about ``axis``)."""
        i, ax, name = self.body.index, self.axis, self.body.name
        return [ReferenceSeries(f"{name}/speed", "m/s", f"speed downhill ({self.regime}): {what}", speed, self.along),
                ReferenceSeries(f"{name}/spin", "rad/s", f"angular velocity about n x d ({self.regime})", spin,
                                lambda tr: tr.angvel[:, i] @ ax)]

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

    def stop_metrics(self, trace, out: dict, t_stop: float, s_stop: float, decel: float) -> None:
        """``stop_position_error`` and ``creep`` (:data:`STOP_METRICS`, m)
        into ``out`` for a body the model stops at ``t_stop`` (s) after
        ``s_stop`` (m) downhill, decelerating at ``decel`` (m/s^2), and
        holds there.  The first measures where it stopped (the stop
        distance's error, plus any creep), the second only how far it moved
        once at rest, from wherever that was
        (tests/test_references.py::test_stop_position_error_and_creep_are_apart).
        At rest: the first frame k whose speed along the initial motion is
        <= |decel| (t_k+1 - t_k) (a body still sliding or rolling with that
        speed stops within the frame interval) and that is either stopped
        (speed <= 0) or still moving on at the next frame (a soft stop's slow
        tail, or creep): an engine that stops the body dead reads creep 0
        from the frame it stopped at, not from the frame before.  ``creep``
        is undefined for a body that never came to rest in the run."""
        i, n = self.body.index, self.n

        def in_plane(rel):
            return np.linalg.norm(rel - np.outer(rel @ n, n), axis=1)

        pos, t = trace.pos[:, i], trace.t
        after = t >= t_stop
        out["stop_position_error"] = float(np.nanmax(in_plane(pos[after] - (self.x0 + s_stop * self.d))))
        if self.u0 == 0.0:
            k = 0
        else:
            speed = self.along(trace) * math.copysign(1.0, self.u0)
            dt = np.diff(t)
            slow = speed <= abs(decel) * np.append(dt, dt[-1:])  # the last frame: the last interval
            # stopped (or turned), or still moving on at the next frame (a
            # soft stop's slow tail, or creep): not a frame that a stop
            # still to come within the interval would leave behind
            held = (speed <= 0.0) | np.append(speed[1:] > 0.0, False)
            rest = np.flatnonzero(slow & held)
            if rest.size == 0:
                undefined(out, "creep", "the body never came to rest in the run (its speed along the motion never "
                                        "fell to what the reference deceleration takes off in one frame)")
                return
            k = int(rest[0])
        out["creep"] = float(np.nanmax(in_plane(pos[k:] - pos[k])))
