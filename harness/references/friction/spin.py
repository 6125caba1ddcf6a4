"""A capsule lying on a level plane spun to rest by twist friction."""

from __future__ import annotations

import math

import numpy as np

from physbench.contract.rotation import quat_rotate, quat_to_matrix
from physbench.harness.references import (BODY_PARAM, TRAJECTORY, ReferenceError, ReferenceModel, ReferenceSeries,
                                divide, fit_slope, trajectory_metrics)
from physbench.harness.references.friction.slope import SKIP_FRACTION


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
        decel = -fit_slope(t[lo:hi], spin[lo:hi])
        out["spin_decel"] = decel
        divide(out, "spin_decel_error", abs(decel - self.alpha), self.alpha, "the reference spin deceleration")
        if t[-1] > self.t_stop:
            th = float(self.turned(trace)[-1])
            out["spin_stop_angle"] = th
            # theta_stop = w0^2 / (2 alpha) is 0 for a spin whose square underflows
            divide(out, "spin_stop_angle_error", abs(th - self.theta_stop), abs(self.theta_stop),
                   "the reference angle turned")
        return out
