"""Two-body collision of spheres by Newton's law of restitution.

Free flight (uniform gravity moves both bodies alike, so it does not change
their relative motion) until the centres are r1 + r2 apart, then an
instantaneous frictionless impulse along the line of centres n:

    v1n' = ((m1 - e m2) v1n + (1 + e) m2 v2n) / (m1 + m2)
    v2n' = ((m2 - e m1) v2n + (1 + e) m1 v1n) / (m1 + m2)

with tangential components unchanged.  Total linear momentum is conserved for
any e; kinetic energy for e = 1.  The same formula covers oblique impacts
(equal masses, e = 1: the outgoing velocities are 90 degrees apart).
"""

from __future__ import annotations

import math

import numpy as np

from physbench.harness.references import TRAJECTORY, Param, ReferenceError, ReferenceModel, ReferenceSeries, trajectory_metrics


class TwoBodyCollision(ReferenceModel):
    name = "two_body_collision"
    summary = "two spheres meet: Newton's law of restitution along the line of centres, free flight before and after"
    takes = ("two spheres (the scene's only two, or params.bodies), their masses, radii, initial positions and "
             "velocities, the pair's restitution, gravity (moves both alike)")
    params = (Param("bodies", "list of str", None, "the two bodies (default: the scene's only two)"),)
    produces = {
        "post_impact_velocity_error": "max over the two bodies of |v(T) - v'| / approach speed, after the impact (1)",
        "impact_time": "the reference impact time (s)",
        **TRAJECTORY,
    }
    primary = "post_impact_velocity_error"

    def __init__(self, scene):
        super().__init__(scene)
        chosen = self.named("bodies", scene.bodies, "bodies")
        if chosen is None:
            if scene.n_bodies != 2:
                raise ReferenceError(f"two_body_collision needs exactly 2 bodies (or params.bodies), the scene has {scene.n_bodies}")
            idx = (0, 1)
        else:
            idx = tuple(b.index for b in chosen)
            if len(idx) != 2:
                raise ReferenceError(f"expected two body names, got {self.param('bodies')!r}",
                                     key="reference.params.bodies")
        self.idx = idx
        b1, b2 = (scene.bodies[i] for i in idx)
        for b in (b1, b2):
            if b.shape != "sphere":
                raise ReferenceError(f"two_body_collision needs spheres, body {b.name!r} is a {b.shape}",
                                     key=scene.body_key(b.index, "shape"))
        self.m1, self.m2 = b1.mass, b2.mass
        self.R = b1.radius + b2.radius
        self.e = scene.pair(b1.material, b2.material).restitution
        self.x1, self.x2 = b1.position.copy(), b2.position.copy()
        # The law is the impact of two spheres meeting from outside: a start
        # in overlap has no contact point, and at coincident centres no line
        # of centres (a zero-length normal).  Refused at load
        # (tests/test_fuzz.py::test_two_body_collision_refuses_an_overlapping_start).
        dist = math.hypot(*(self.x2 - self.x1))
        if not dist >= self.R:
            raise ReferenceError(
                f"spheres {b1.name!r} and {b2.name!r} start overlapping: their centres are {dist:.6g} m apart, "
                f"less than r1 + r2 = {self.R:.6g} m; expected a start with the spheres apart "
                f"(centre distance >= r1 + r2)", key=scene.body_key(idx[1], "position"))
        self.v1, self.v2 = b1.velocity.copy(), b2.velocity.copy()
        self.g = scene.gravity.copy()
        self.t_impact, self.n = self._impact()
        if self.t_impact is not None:
            x1c = self.x1 + self.v1 * self.t_impact
            x2c = self.x2 + self.v2 * self.t_impact
            self.x1c, self.x2c = x1c, x2c
            self.v1_post, self.v2_post, self.approach = self._post()
        else:
            self.v1_post, self.v2_post, self.approach = self.v1, self.v2, math.nan

    def _impact(self):
        """Earliest t >= 0 with |dx + dv t| = R (relative motion is linear)."""
        dx = self.x2 - self.x1
        dv = self.v2 - self.v1
        a = dv @ dv
        b = 2 * dx @ dv
        c = dx @ dx - self.R**2
        if a == 0 or b >= 0:
            return None, None
        disc = b * b - 4 * a * c
        if disc <= 0:  # a miss, or a graze: the centres touch with no approach speed, no impulse
            return None, None
        t = (-b - math.sqrt(disc)) / (2 * a)
        t = max(t, 0.0)  # c >= 0 (no overlap at the start, __init__) makes t >= 0 but for rounding
        n = dx + dv * t  # |n| = R >= 2e-6 m (the size bound): a defined normal
        return t, n / math.hypot(*n)

    def _post(self):
        n, m1, m2, e = self.n, self.m1, self.m2, self.e
        u1, u2 = self.v1 @ n, self.v2 @ n
        w1 = ((m1 - e * m2) * u1 + (1 + e) * m2 * u2) / (m1 + m2)
        w2 = ((m2 - e * m1) * u2 + (1 + e) * m1 * u1) / (m1 + m2)
        return self.v1 + (w1 - u1) * n, self.v2 + (w2 - u2) * n, abs(u1 - u2)

    def velocities(self, t: np.ndarray) -> np.ndarray:
        """Reference velocities (F, 2, 3) of the two bodies at times t (F,)."""
        t = np.asarray(t, float)[:, None]
        after = (self.t_impact is not None) & (t >= (self.t_impact if self.t_impact is not None else np.inf))
        v1 = np.where(after, self.v1_post, self.v1) + self.g * t
        v2 = np.where(after, self.v2_post, self.v2) + self.g * t
        return np.stack([v1, v2], axis=1)

    def positions(self, t: np.ndarray) -> np.ndarray:
        """Reference positions (F, n, 3): the two bodies follow the analytic
        solution; other bodies (if any) are NaN and ignored by the metrics."""
        t = np.asarray(t, float)
        tt = t[:, None]
        grav = 0.5 * self.g * tt * tt
        if self.t_impact is None:
            p1 = self.x1 + self.v1 * tt
            p2 = self.x2 + self.v2 * tt
        else:
            tc = self.t_impact
            after = tt >= tc
            p1 = np.where(after, self.x1c + self.v1_post * (tt - tc), self.x1 + self.v1 * tt)
            p2 = np.where(after, self.x2c + self.v2_post * (tt - tc), self.x2 + self.v2 * tt)
        return np.stack([p1 + grav, p2 + grav], axis=1)

    def predictions(self) -> dict[str, str]:
        if self.t_impact is None:
            return {"impact": "none within the relative motion"}
        names = [self.scene.bodies[i].name for i in self.idx]
        return {"impact time": f"{self.t_impact:.6g} s",
                f"{names[0]} velocity after impact": f"{np.array2string(self.v1_post, precision=6)} m/s",
                f"{names[1]} velocity after impact": f"{np.array2string(self.v2_post, precision=6)} m/s"}

    def reference_series(self) -> list[ReferenceSeries]:
        """Each body's velocity along the line of centres n (m/s): v.n
        before the impact, v'.n after it (plus g.n t)."""
        if self.t_impact is None:
            return []
        out = []
        for k, (i, post) in enumerate(zip(self.idx, (self.v1_post, self.v2_post))):
            name = self.scene.bodies[i].name
            out.append(ReferenceSeries(
                f"{name}/normal_velocity", "m/s",
                f"{name} velocity along the line of centres: {float(post @ self.n):.6g} m/s after the impact",
                lambda t, k=k: self.velocities(t)[:, k] @ self.n,
                lambda tr, i=i: tr.vel[:, i] @ self.n))
        return out

    def reference_times(self) -> list[tuple[float, str]]:
        return [] if self.t_impact is None else [(float(self.t_impact), "impact")]

    def metrics(self, trace) -> dict[str, float]:
        i, j = self.idx
        pos = trace.pos[:, [i, j]]
        vel = trace.vel[:, [i, j]]
        out = trajectory_metrics(pos, self.positions(trace.t))
        if self.t_impact is None or trace.t[-1] <= self.t_impact:
            out["post_impact_velocity_error"] = math.nan
            return out
        vref = self.velocities(trace.t[-1:])[0]
        err = np.linalg.norm(vel[-1] - vref, axis=-1)
        # relative to the approach speed along the line of centres: 0.01 means
        # the outgoing velocities are off by 1 % of the speed that was reversed.
        out["post_impact_velocity_error"] = float(np.max(err) / self.approach)
        out["impact_time"] = float(self.t_impact)
        return out
