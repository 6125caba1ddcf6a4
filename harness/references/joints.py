"""Closed forms for jointed bodies: a physical pendulum on a hinge, a block
on a slider.

Pendulum (``pendulum``).  One body on one revolute joint to the world, hinge
axis u, anchor a, gravity g.  Only the part of g across the axis turns the
body: G = |g - (g . u) u|, e1 = (g - (g . u) u) / G (down), e2 = u x e1.  The
centre of mass sits at r = x - a; its part across the axis has length d (the
pendulum's length) and angle theta from e1 towards e2:
theta = atan2(r . e2, r . e1).  With I the moment of inertia about the hinge
line (the body's own about u plus m d^2),

    I theta'' = -m G d sin theta,   wn = sqrt(m G d / I).

Energy fixes the amplitude: cos theta_max = cos theta0 - theta0'^2 / (2 wn^2),
k = sin(theta_max / 2), m_e = k^2.  The motion, through Jacobi's elliptic
functions (scipy.special.ellipj), is

    sin(theta / 2) = k sn(wn t + u0 | m_e),   theta' = 2 k wn cn(wn t + u0 | m_e),

with u0 = F(phi0 | m_e), sin phi0 = sin(theta0 / 2) / k (incomplete integral
F, scipy.special.ellipkinc), or 2K - F(phi0 | m_e) when the body starts
swinging back (theta0' < 0).  The period at any amplitude is
T = 4 K(m_e) / wn = 4 sqrt(I / (m G d)) K(sin(theta_max / 2)).  A start with
k > 1 whirls over the top: theta / 2 = s am(k wn t + u0 | 1 / k^2), u0 =
F(s theta0 / 2 | 1 / k^2), s the sense of turning, theta' = 2 s k wn dn(...),
one turn in T = 2 K(1 / k^2) / (k wn).  A start on the separatrix (k = 1)
or one that never swings (k = 0) is refused.

Slider (``slider``).  One body on one prismatic joint to the world, slide
axis u, no friction: s'' = g . u along the axis (a = g sin alpha on an
incline of angle alpha), x(t) = x0 + (v0 t + (g . u) t^2 / 2) u.

Conical pendulum (``conical_pendulum``).  One body with equal principal
moments on one spherical joint to the world, its centre a distance L from
the anchor at the cone angle alpha from straight down, turning as one piece
at rate w about the vertical.  The rate of change of the angular momentum
about the anchor, w up x L_anchor = m w^2 L^2 sin alpha cos alpha (the
body's own inertia, isotropic, adds nothing), equals gravity's torque
m g L sin alpha: w^2 = g / (L cos alpha).

Hanging chain (``hanging_chain``).  Bodies at rest hanging straight down
from one world joint, each through joints whose anchors lie on the vertical
below it: every joint force is vertical and balances the weight below it,
so the exact motion is none at all, whatever the mass ratio of an end load.

Double pendulum (``double_pendulum``).  Two bodies on parallel hinges, the
first to the world, the second to the first; theta1 the angle of the first
link (world anchor to second anchor, length l1, the first centre on it at
d1), theta2 that of the second body's centre (d2 from its hinge).  At small
amplitude M theta'' + K theta = 0 with M = [[I1 + m2 l1^2, m2 l1 d2],
[m2 l1 d2, I2 + m2 d2^2]] (I1 about the world hinge, I2 about the second
body's centre) and K = diag(g (m1 d1 + m2 l1), g m2 d2): the normal modes are
the roots of det(K - w^2 M) = 0, and the modal coordinates q = Phi^T M theta
(Phi the M-orthonormal modes) each swing at one frequency.

Four-bar linkage (``four_bar``).  A crank (pivot O2, length a), a coupler
(b) and a rocker (pivot O4, length c) on four parallel hinges, the ground
O2 O4 of length d.  At crank angle theta the crank pin is A = O2 + a (cos
theta e1 + sin theta e2) and the coupler-rocker pin B the intersection of
the circles |B - A| = b and |B - O4| = c on the start's side of A O4
(closed-form position kinematics); the coupler's and rocker's rates per
unit crank rate solve A' + w3 u x (B - A) = w4 u x (B - O4).  One degree
of freedom: the kinetic energy is I_eff(theta) theta'^2 / 2, so energy
gives theta'(theta)^2 = 2 (E - V(theta)) / I_eff(theta) and one crank turn
takes T = integral of d theta / |theta'| (a smooth periodic integrand: the
trapezoid rule on a uniform grid is spectrally exact).

Tests: tests/test_joint_models.py (each against scipy's solve_ivp of the
equation of motion, or the kinematics, computed in the test);
tests/test_engine_joints.py (the four-bar against a loop closure solved by
root finding and scipy's quad, computed in the test).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from physbench.contract.rotation import quat_to_matrix
from physbench.harness.references import (TRAJECTORY, ReferenceError, ReferenceModel, divide, fit_slope,
                                          trajectory_metrics)

#: relative tolerance on "the start is a rotation about the joint"
_RIGID = 1e-9


def _one_world_joint(model: ReferenceModel, kind: str):
    """The scene's only joint, of ``kind``, to the world; its body."""
    sc = model.scene
    if len(sc.joints) != 1:
        raise ReferenceError(f"{model.name} needs exactly one [[joint]], the scene has {len(sc.joints)}",
                             key="joint")
    j = sc.joints[0]
    if j.kind != kind:
        raise ReferenceError(f"{model.name} needs a {kind} joint, got {j.kind!r}", key="joint[0].kind")
    if j.other != -1:
        raise ReferenceError(f"{model.name} needs a joint to the world, got one to "
                             f"{sc.bodies[j.other].name!r}", key="joint[0].other")
    if sc.n_bodies != 1:
        raise ReferenceError(f"{model.name} needs exactly one body, the scene has {sc.n_bodies}")
    for eff in ("contact", "spring", "damper", "drag_linear", "drag_quadratic"):
        if sc.has(eff):
            raise ReferenceError(f"{model.name} models the joint and gravity only; the scene lists {eff!r}",
                                 key="scenario.effects")
    return j, sc.bodies[j.body]


def _crossings(t: np.ndarray, y: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Times (s) where y (F,) crosses 0 upwards, located by the cubic
    Hermite interpolant of (y, dy) on each frame interval (Newton from the
    linear guess); intervals with |jump| > pi (an angle wrapping over the top)
    are skipped."""
    i = np.nonzero((y[:-1] <= 0.0) & (y[1:] > 0.0) & (np.abs(y[1:] - y[:-1]) < math.pi))[0]
    out = []
    for k in i:
        h = t[k + 1] - t[k]
        y0, y1, m0, m1 = y[k], y[k + 1], dy[k] * h, dy[k + 1] * h
        s = -y0 / (y1 - y0)
        for _ in range(8):
            s2, s3 = s * s, s * s * s
            f = (2 * s3 - 3 * s2 + 1) * y0 + (s3 - 2 * s2 + s) * m0 + (-2 * s3 + 3 * s2) * y1 + (s3 - s2) * m1
            df = (6 * s2 - 6 * s) * y0 + (3 * s2 - 4 * s + 1) * m0 + (-6 * s2 + 6 * s) * y1 + (3 * s2 - 2 * s) * m1
            if df == 0.0:
                break
            s = min(1.0, max(0.0, s - f / df))
        out.append(t[k] + s * h)
    return np.array(out)


class Pendulum(ReferenceModel):
    name = "pendulum"
    summary = ("a rigid body on a revolute joint to the world under gravity: the physical pendulum at any "
               "amplitude, swinging or whirling over the top, through Jacobi's elliptic functions")
    takes = ("exactly one body and one revolute [[joint]] to the world (its anchor and hinge axis), gravity "
             "across the axis, the body's mass and inertia; a start that is a rotation about the hinge "
             "(angular velocity along the axis, velocity = w x (x - anchor)). Refuses contact, springs and "
             "drag, a start on the separatrix (reaching the top at rest), and one at rest hanging straight "
             "down. Energy: the "
             "harness's energy_drift; the joint: joint_drift")
    produces = {
        "period": "measured mean time between upward crossings of theta = 0 (s; Hermite-interpolated from the "
                  "angle and the angular velocity about the axis; whirling, crossings in the sense of turning: "
                  "the time of one turn)",
        "period_ref": "4 sqrt(I / (m g d)) K(k), k = sin(theta_max / 2); whirling (k > 1): "
                      "2 sqrt(I / (m g d)) K(1 / k^2) / k, one turn (s)",
        "period_error": "|T - T_ref| / T_ref (1; inf with fewer than two upward crossings in the run)",
        "angle_error": "max_t |theta - theta_ref| (rad), theta the angle of the centre of mass about the hinge "
                       "from straight down",
        "amplitude_ref": "theta_max (rad; pi for a pendulum whirling over the top, which passes it)",
        **TRAJECTORY,
    }
    primary = "period_error"

    def __init__(self, scene):
        super().__init__(scene)
        j, b = _one_world_joint(self, "revolute")
        self.joint, self.body = j, b
        u = j.axis
        g = scene.gravity
        gp = g - (g @ u) * u
        G = float(np.linalg.norm(gp))
        if not G > 0.0:
            raise ReferenceError("gravity has no part across the hinge axis: the pendulum has no restoring "
                                 "torque", key="scenario.gravity")
        e1 = gp / G
        e2 = np.cross(u, e1)
        r0 = b.position - j.anchor
        self.along = float(r0 @ u)
        rp = r0 - self.along * u
        d = float(np.linalg.norm(rp))
        k_idx = scene.body_key(b.index, "position")
        if not d > 0.0:
            raise ReferenceError("the centre of mass lies on the hinge line: no restoring torque", key=k_idx)
        R = quat_to_matrix(b.orientation)
        I = float(u @ (R @ np.diag(b.inertia) @ R.T) @ u) + b.mass * d * d
        w0 = float(b.angular_velocity @ u)
        scale = abs(w0) * d + math.sqrt(G * d)
        if np.linalg.norm(b.angular_velocity - w0 * u) * d > _RIGID * scale:
            raise ReferenceError(f"the start turns about more than the hinge axis {u.tolist()}: angular_velocity "
                                 f"{b.angular_velocity.tolist()}", key=scene.body_key(b.index, "angular_velocity"))
        if np.linalg.norm(b.velocity - w0 * np.cross(u, r0)) > _RIGID * scale:
            raise ReferenceError(f"the start is not a rotation about the hinge: velocity {b.velocity.tolist()} "
                                 f"!= w x (x - anchor) = {(w0 * np.cross(u, r0)).tolist()}",
                                 key=scene.body_key(b.index, "velocity"))
        self.u, self.e1, self.e2, self.G, self.d, self.I = u, e1, e2, G, d, I
        self.wn = math.sqrt(b.mass * G * d / I)
        th0 = math.atan2(float(rp @ e2), float(rp @ e1))
        cmax = math.cos(th0) - w0 * w0 / (2 * self.wn ** 2)
        k2 = (1.0 - cmax) / 2.0
        if abs(k2 - 1.0) < 1e-9:
            raise ReferenceError(f"the start is on the separatrix (k^2 = {k2:.12g}): it would take forever to reach "
                                 f"the top", key=scene.body_key(b.index, "angular_velocity"))
        if not k2 > 0.0:
            raise ReferenceError("the pendulum starts at rest hanging straight down: it never swings", key=k_idx)
        self.k = math.sqrt(k2)
        self.theta0, self.w0 = th0, w0
        #: swinging (k < 1) or whirling over the top (k > 1)
        self.whirls = k2 > 1.0
        if not self.whirls:
            self.m = k2
            self.theta_max = 2.0 * math.asin(self.k)
        else:
            # theta / 2 = s am(k wn t + u0 | 1 / k^2), s the sense of turning;
            # one turn takes 2 K(1 / k^2) / (k wn)
            self.m = 1.0 / k2
            self.theta_max = math.pi
            self.sense = 1.0 if w0 > 0.0 else -1.0

    @functools.cached_property
    def _elliptic(self) -> tuple[float, float, float]:
        """(K(m), u0, T s): the complete integral, the start's argument of
        the elliptic functions and the period (one turn when it whirls).
        Computed on first use, not in __init__: every refusal is made before
        them, and a sweep's client, which builds the model only to check the
        scene, then never imports scipy.special (0.16 s of CPU;
        tests/test_sweep.py::test_checking_the_nightly_does_not_import_scipy_special)."""
        from scipy.special import ellipk, ellipkinc

        K = float(ellipk(self.m))
        if not self.whirls:
            phi0 = math.asin(max(-1.0, min(1.0, math.sin(self.theta0 / 2) / self.k)))
            F0 = float(ellipkinc(phi0, self.m))
            return K, (F0 if self.w0 >= 0.0 else 2.0 * K - F0), 4.0 * K / self.wn
        return K, float(ellipkinc(self.sense * self.theta0 / 2.0, self.m)), 2.0 * K / (self.k * self.wn)

    @property
    def K(self) -> float:
        return self._elliptic[0]

    @property
    def u0(self) -> float:
        return self._elliptic[1]

    @property
    def T(self) -> float:
        return self._elliptic[2]

    # ---- the closed form ---------------------------------------------------
    def angle(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(theta (F,) rad, theta' (F,) rad/s) at times t (F,) s."""
        from scipy.special import ellipj  # see _elliptic

        if self.whirls:
            _, _, dn, ph = ellipj(self.k * self.wn * np.asarray(t, float) + self.u0, self.m)
            return self.sense * 2.0 * ph, self.sense * 2.0 * self.k * self.wn * dn
        sn, cn, _, _ = ellipj(self.wn * np.asarray(t, float) + self.u0, self.m)
        return 2.0 * np.arcsin(np.clip(self.k * sn, -1.0, 1.0)), 2.0 * self.k * self.wn * cn

    def positions(self, t: np.ndarray) -> np.ndarray:
        th, _ = self.angle(t)
        out = np.full((len(t), self.scene.n_bodies, 3), np.nan)
        j = self.joint
        out[:, self.body.index] = (j.anchor + self.along * self.u
                                   + self.d * (np.cos(th)[:, None] * self.e1 + np.sin(th)[:, None] * self.e2))
        return out

    def measured_angle(self, trace) -> tuple[np.ndarray, np.ndarray]:
        """(theta (F,) rad, theta' (F,) rad/s) of the recorded body."""
        i = self.body.index
        r = trace.pos[:, i] - self.joint.anchor
        return np.arctan2(r @ self.e2, r @ self.e1), trace.angvel[:, i] @ self.u

    def predictions(self) -> dict[str, str]:
        if self.whirls:
            return {"one turn": f"{self.T:.9g} s", "motion": "whirls over the top",
                    "small-angle period": f"{2 * math.pi / self.wn:.9g} s"}
        return {"period": f"{self.T:.9g} s", "amplitude": f"{math.degrees(self.theta_max):.6g} deg",
                "small-angle period": f"{2 * math.pi / self.wn:.9g} s"}

    def metrics(self, trace) -> dict[str, float]:
        t = np.asarray(trace.t, float)
        out: dict[str, float] = {}
        i = self.body.index
        ref = self.positions(t)[:, [i]]
        out.update(trajectory_metrics(trace.pos[:, [i]], ref))
        th, dth = self.measured_angle(trace)
        th_ref, _ = self.angle(t)
        diff = np.angle(np.exp(1j * (th - th_ref)))
        out["angle_error"] = float(np.max(np.abs(diff))) if np.isfinite(diff).all() else float("nan")
        out["amplitude_ref"] = self.theta_max  # pi when it whirls: it passes the top
        if self.whirls and self.sense < 0:  # turning backwards: time the upward crossings of -theta
            th, dth = -th, -dth
        out["period_ref"] = self.T
        c = _crossings(t, th, dth) if np.isfinite(th).all() and np.isfinite(dth).all() else np.array([])
        if len(c) >= 2:
            T = float((c[-1] - c[0]) / (len(c) - 1))
            out["period"] = T
            out["period_error"] = abs(T - self.T) / self.T
        else:
            out["period"] = float("nan")
            out["period_error"] = float("inf")
        return out


class Slider(ReferenceModel):
    name = "slider"
    summary = "a body on a frictionless prismatic joint to the world: uniform acceleration g . u along the slide"
    takes = ("exactly one body and one prismatic [[joint]] to the world (its slide axis u), gravity; a start "
             "moving along the axis without turning. Refuses contact, springs and drag. The joint: joint_drift")
    produces = {
        "slider_position_error": "max_t |x - x_ref| (m), x_ref = x0 + (v0 t + (g . u) t^2 / 2) u",
        "slider_acceleration": "measured acceleration along the axis: the least-squares slope of the velocity "
                               "along u (m/s^2)",
        "slider_acceleration_ref": "g . u (m/s^2; g sin alpha on an incline of angle alpha)",
        "slider_acceleration_error": "|a - a_ref| / |a_ref| (1; undefined when the axis is level)",
        **TRAJECTORY,
    }
    primary = "slider_acceleration_error"

    def __init__(self, scene):
        super().__init__(scene)
        j, b = _one_world_joint(self, "prismatic")
        self.joint, self.body = j, b
        u = j.axis
        v0 = float(b.velocity @ u)
        scale = abs(v0) + 1.0
        if np.linalg.norm(b.velocity - v0 * u) > _RIGID * scale:
            raise ReferenceError(f"the start moves off the slide axis {u.tolist()}: velocity {b.velocity.tolist()}",
                                 key=scene.body_key(b.index, "velocity"))
        if np.linalg.norm(b.angular_velocity) > 0.0:
            raise ReferenceError("a slider does not turn: the start's angular_velocity must be 0",
                                 key=scene.body_key(b.index, "angular_velocity"))
        self.u, self.v0, self.a = u, v0, float(scene.gravity @ u)

    def positions(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        out = np.full((len(t), self.scene.n_bodies, 3), np.nan)
        s = self.v0 * t + 0.5 * self.a * t * t
        out[:, self.body.index] = self.body.position + s[:, None] * self.u
        return out

    def predictions(self) -> dict[str, str]:
        return {"acceleration along the slide": f"{self.a:.9g} m/s^2"}

    def metrics(self, trace) -> dict[str, float]:
        t = np.asarray(trace.t, float)
        i = self.body.index
        ref = self.positions(t)[:, [i]]
        out = trajectory_metrics(trace.pos[:, [i]], ref)
        out["slider_position_error"] = float(np.max(np.linalg.norm(trace.pos[:, i] - ref[:, 0], axis=-1)))
        a = fit_slope(t, trace.vel[:, i] @ self.u)
        out["slider_acceleration"] = a
        out["slider_acceleration_ref"] = self.a
        divide(out, "slider_acceleration_error", abs(a - self.a), abs(self.a), "the acceleration along the axis")
        return out


class ConicalPendulum(ReferenceModel):
    name = "conical_pendulum"
    summary = ("a body with equal principal moments on a spherical joint to the world, in steady circular motion "
               "about the vertical: w^2 = g / (L cos alpha)")
    takes = ("exactly one body with equal principal moments (a sphere: its own spin then exerts no gyroscopic "
             "torque) and one spherical [[joint]] to the world below which it hangs, gravity; the start must be "
             "the steady motion: turning as one rigid piece with the rod at w = sqrt(g / (L cos alpha)) about "
             "the vertical through the anchor (angular velocity w up, velocity w x (x - anchor)), L the "
             "anchor-centre distance, alpha the cone angle. Refuses contact, springs and drag, and any other start")
    produces = {
        "cone_angle_error": "max_t |alpha(t) - alpha| (rad), alpha(t) the angle between the anchor-centre line and "
                            "straight down",
        "cone_rate": "measured rate about the vertical: the least-squares slope of the unwrapped azimuth of the "
                     "centre (rad/s)",
        "cone_rate_ref": "sqrt(g / (L cos alpha)) (rad/s)",
        "cone_rate_error": "|w_measured - w| / w (1)",
        **TRAJECTORY,
    }
    primary = "cone_rate_error"

    def __init__(self, scene):
        super().__init__(scene)
        j, b = _one_world_joint(self, "spherical")
        self.joint, self.body = j, b
        if np.ptp(b.inertia) > 1e-12 * float(np.max(b.inertia)):
            raise ReferenceError(f"{self.name} needs equal principal moments (a sphere), got {b.inertia.tolist()}",
                                 key=scene.body_key(b.index, "shape"))
        g = scene.gravity
        G = float(np.linalg.norm(g))
        if not G > 0.0:
            raise ReferenceError("the conical pendulum needs gravity", key="scenario.effects")
        up = -g / G
        r = b.position - j.anchor
        L = float(np.linalg.norm(r))
        cos_a = float(-(r @ up)) / L if L > 0 else 0.0
        if not 1e-9 < cos_a < 1.0 - 1e-12:
            raise ReferenceError(f"the body must hang below the anchor and off the vertical (cos alpha = {cos_a:.6g})",
                                 key=scene.body_key(b.index, "position"))
        w = math.sqrt(G / (L * cos_a))
        scale = w * L
        pos_key = scene.body_key(b.index, "angular_velocity")
        if np.linalg.norm(b.angular_velocity - w * up) * L > 1e-9 * scale:
            raise ReferenceError(f"the steady motion turns at w = sqrt(g / (L cos alpha)) = {w:.9g} rad/s about "
                                 f"{up.tolist()}; angular_velocity is {b.angular_velocity.tolist()}", key=pos_key)
        if np.linalg.norm(b.velocity - w * np.cross(up, r)) > 1e-9 * scale:
            raise ReferenceError(f"the steady motion has velocity w x (x - anchor) = "
                                 f"{(w * np.cross(up, r)).tolist()}, got {b.velocity.tolist()}",
                                 key=scene.body_key(b.index, "velocity"))
        self.up, self.L, self.w = up, L, w
        self.alpha = math.acos(cos_a)
        self.e1 = (r - (r @ up) * up) / np.linalg.norm(r - (r @ up) * up)
        self.e2 = np.cross(up, self.e1)
        self.h = float(r @ up)  # the centre's height below the anchor (< 0)
        self.rho = float(np.linalg.norm(r - (r @ up) * up))

    def positions(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)
        out = np.full((len(t), self.scene.n_bodies, 3), np.nan)
        phi = self.w * t
        out[:, self.body.index] = (self.joint.anchor + self.h * self.up
                                   + self.rho * (np.cos(phi)[:, None] * self.e1 + np.sin(phi)[:, None] * self.e2))
        return out

    def predictions(self) -> dict[str, str]:
        return {"rate": f"{self.w:.9g} rad/s", "cone angle": f"{math.degrees(self.alpha):.6g} deg",
                "period": f"{2 * math.pi / self.w:.9g} s"}

    def metrics(self, trace) -> dict[str, float]:
        t = np.asarray(trace.t, float)
        i = self.body.index
        out = trajectory_metrics(trace.pos[:, [i]], self.positions(t)[:, [i]])
        r = trace.pos[:, i] - self.joint.anchor
        down = -(r @ self.up) / np.linalg.norm(r, axis=-1)
        side = np.linalg.norm(r - (r @ self.up)[:, None] * self.up, axis=-1) / np.linalg.norm(r, axis=-1)
        alpha = np.arctan2(side, down)
        out["cone_angle_error"] = float(np.max(np.abs(alpha - self.alpha)))
        phi = np.unwrap(np.arctan2(r @ self.e2, r @ self.e1))
        out["cone_rate"] = fit_slope(t, phi)
        out["cone_rate_ref"] = self.w
        out["cone_rate_error"] = abs(out["cone_rate"] - self.w) / self.w
        return out


class HangingChain(ReferenceModel):
    name = "hanging_chain"
    summary = "bodies hanging at rest from the world through joints: a static equilibrium that must stay put"
    takes = ("bodies at rest (no velocity, no angular velocity), every one held to the world through [[joint]] "
             "tables (revolute, spherical or fixed; no slider), every joint's anchor and every body's centre on "
             "the vertical line through a world joint's anchor, below it: each link hangs straight down from "
             "the one above, whatever the masses (an end load of any ratio). Refuses contact, springs and drag")
    produces = {
        "chain_rest_error": "max over frames and bodies of |x - x0| (m): how far the chain leaves its rest",
        "chain_sag": "max over frames of the lowest body's drop below its start (m; 0 when it never drops)",
    }
    primary = "chain_rest_error"

    def __init__(self, scene):
        super().__init__(scene)
        sc = scene
        for eff in ("contact", "spring", "damper", "drag_linear", "drag_quadratic"):
            if sc.has(eff):
                raise ReferenceError(f"{self.name} models joints and gravity only; the scene lists {eff!r}",
                                     key="scenario.effects")
        g = sc.gravity
        G = float(np.linalg.norm(g))
        if not G > 0.0:
            raise ReferenceError("a hanging chain needs gravity", key="scenario.effects")
        down = g / G
        roots = [j for j in sc.joints if j.other < 0]
        if len(roots) != 1:
            raise ReferenceError(f"{self.name} needs exactly one joint to the world, the scene has {len(roots)}",
                                 key="joint")
        top = roots[0].anchor
        for k, j in enumerate(sc.joints):
            if j.kind == "prismatic":
                raise ReferenceError("a slider has no rest on a vertical line", key=f"joint[{k}].kind")
            if self._off(j.anchor - top, down) > 1e-9 * (1.0 + np.linalg.norm(j.anchor - top)):
                raise ReferenceError(f"the anchor {j.anchor.tolist()} is off the vertical through the top anchor "
                                     f"{top.tolist()}", key=f"joint[{k}].anchor")
        held = {j.body for j in sc.joints} | {j.other for j in sc.joints if j.other >= 0}
        for b in sc.bodies:
            r = b.position - top
            if b.index not in held:
                raise ReferenceError(f"body {b.name!r} is not held by any joint", key="joint")
            if self._off(r, down) > 1e-9 * (1.0 + np.linalg.norm(r)) or float(r @ down) <= 0.0:
                raise ReferenceError(f"body {b.name!r} at {b.position.tolist()} does not hang on the vertical "
                                     f"below {top.tolist()}", key=sc.body_key(b.index, "position"))
            if np.any(b.velocity != 0.0) or np.any(b.angular_velocity != 0.0):
                raise ReferenceError(f"body {b.name!r} must start at rest", key=sc.body_key(b.index, "velocity"))
        self.down = down
        self.lowest = max(sc.bodies, key=lambda b: float(b.position @ down)).index

    @staticmethod
    def _off(r: np.ndarray, down: np.ndarray) -> float:
        return float(np.linalg.norm(r - (r @ down) * down))

    def positions(self, t: np.ndarray) -> np.ndarray:
        x0 = np.array([b.position for b in self.scene.bodies], float)
        return np.broadcast_to(x0, (len(t),) + x0.shape).copy()

    def metrics(self, trace) -> dict[str, float]:
        x0 = self.positions(np.asarray(trace.t, float))
        out = {"chain_rest_error": float(np.max(np.linalg.norm(trace.pos - x0, axis=-1)))}
        drop = (trace.pos[:, self.lowest] - x0[:, self.lowest]) @ self.down
        out["chain_sag"] = max(0.0, float(np.max(drop)))
        return out


class DoublePendulum(ReferenceModel):
    name = "double_pendulum"
    summary = ("two bodies on parallel hinges (the first to the world, the second to the first) at small "
               "amplitude: the two normal-mode frequencies in closed form")
    takes = ("exactly two bodies and two revolute [[joint]] tables with parallel axes: the first body to the "
             "world, the second to the first; the first body's centre on the line from the world anchor to the "
             "second anchor; gravity across the axes; a start at rest (any small angles: both modes are "
             "measured when both are excited). Refuses contact, springs and drag. Large amplitudes: check the "
             "harness's energy_drift and joint_drift instead")
    produces = {
        "mode_frequency_ref_1": "the lower normal-mode angular frequency (rad/s): M^-1 K's smaller eigenvalue's root",
        "mode_frequency_ref_2": "the higher normal-mode angular frequency (rad/s)",
        "mode_frequency_error_1": "|w1 - w1_ref| / w1_ref, w1 measured from the upward zero crossings of the "
                                  "first modal coordinate q = Phi^T M theta (1; inf with fewer than two crossings)",
        "mode_frequency_error_2": "the same for the second mode (1)",
        "mode_frequency_error": "the larger of the two (1)",
        "linear_amplitude": "the largest hinge angle at the start (rad): the model is exact as it goes to 0",
    }
    primary = "mode_frequency_error"

    def __init__(self, scene):
        super().__init__(scene)
        sc = scene
        for eff in ("contact", "spring", "damper", "drag_linear", "drag_quadratic"):
            if sc.has(eff):
                raise ReferenceError(f"{self.name} models the hinges and gravity only; the scene lists {eff!r}",
                                     key="scenario.effects")
        if sc.n_bodies != 2 or len(sc.joints) != 2:
            raise ReferenceError(f"{self.name} needs two bodies and two joints, the scene has {sc.n_bodies} and "
                                 f"{len(sc.joints)}", key="joint")
        j0 = next((j for j in sc.joints if j.other < 0), None)
        if j0 is None:
            raise ReferenceError("one joint must hold a body to the world", key="joint")
        j1 = next(j for j in sc.joints if j is not j0)
        if not (j1.kind == j0.kind == "revolute") or j1.other != j0.body or j1.body == j0.body:
            raise ReferenceError("two revolute joints: body 1 to the world, body 2 to body 1", key="joint")
        u = j0.axis
        if np.linalg.norm(np.cross(u, j1.axis)) > 1e-9:
            raise ReferenceError(f"the hinge axes must be parallel, got {u.tolist()} and {j1.axis.tolist()}",
                                 key=f"joint[{j1.index}].axis")
        b1, b2 = sc.bodies[j0.body], sc.bodies[j1.body]
        for b in (b1, b2):
            if np.any(b.velocity != 0.0) or np.any(b.angular_velocity != 0.0):
                raise ReferenceError("the model starts at rest", key=sc.body_key(b.index, "velocity"))
        g = sc.gravity
        gp = g - (g @ u) * u
        G = float(np.linalg.norm(gp))
        if not G > 0.0:
            raise ReferenceError("gravity has no part across the hinges", key="scenario.gravity")
        e1 = gp / G
        e2 = np.cross(u, e1)

        def across(v):
            return v - (v @ u) * u

        l1v = across(j1.anchor - j0.anchor)
        l1 = float(np.linalg.norm(l1v))
        c1 = across(b1.position - j0.anchor)
        if not l1 > 0.0 or np.linalg.norm(np.cross(l1v, c1)) > 1e-9 * l1 * (1.0 + np.linalg.norm(c1)):
            raise ReferenceError("body 1's centre must lie on the line from the world anchor to the second anchor",
                                 key=sc.body_key(b1.index, "position"))
        d1 = float(c1 @ l1v) / l1  # signed, along the link
        c2 = across(b2.position - j1.anchor)
        d2 = float(np.linalg.norm(c2))
        if not d2 > 0.0:
            raise ReferenceError("body 2's centre lies on its hinge line", key=sc.body_key(b2.index, "position"))

        def own(b):
            R = quat_to_matrix(b.orientation)
            return float(u @ (R @ np.diag(b.inertia) @ R.T) @ u)

        m1, m2 = b1.mass, b2.mass
        I1 = own(b1) + m1 * d1 * d1
        M = np.array([[I1 + m2 * l1 * l1, m2 * l1 * d2], [m2 * l1 * d2, own(b2) + m2 * d2 * d2]])
        K = np.diag([G * (m1 * d1 + m2 * l1), G * m2 * d2])
        if K[0, 0] <= 0.0:
            raise ReferenceError("the first link is not held down by gravity (its centre of mass is above the "
                                 "pivot)", key=sc.body_key(b1.index, "position"))
        # generalised symmetric eigenproblem K phi = w^2 M phi, by the Cholesky factor of M
        Lc = np.linalg.cholesky(M)
        A = np.linalg.solve(Lc, np.linalg.solve(Lc, K).T).T
        lam, V = np.linalg.eigh(A)
        self.Phi = np.linalg.solve(Lc.T, V)  # M-orthonormal modes (columns)
        self.w = np.sqrt(lam)
        self.M, self.u, self.e1, self.e2 = M, u, e1, e2
        self.j0, self.j1, self.b1, self.b2 = j0, j1, b1, b2
        th = self._angles(np.array([b1.position]), np.array([j1.anchor]), np.array([b2.position]))
        self.amplitude = float(np.max(np.abs(th)))

    def _angles(self, x1, a1, x2) -> np.ndarray:
        """(F, 2) angles (rad) from straight down of link 1 (the world anchor
        to the second anchor) and link 2 (the second anchor to body 2's centre)."""
        r1 = a1 - self.j0.anchor
        r2 = x2 - a1
        return np.stack([np.arctan2(r1 @ self.e2, r1 @ self.e1), np.arctan2(r2 @ self.e2, r2 @ self.e1)], axis=-1)

    def predictions(self) -> dict[str, str]:
        return {"mode 1": f"{self.w[0]:.9g} rad/s (period {2 * math.pi / self.w[0]:.9g} s)",
                "mode 2": f"{self.w[1]:.9g} rad/s (period {2 * math.pi / self.w[1]:.9g} s)"}

    def metrics(self, trace) -> dict[str, float]:
        from physbench.contract.rotation import quat_rotate

        t = np.asarray(trace.t, float)
        i1, i2 = self.b1.index, self.b2.index
        a1 = trace.pos[:, i1] + quat_rotate(trace.quat[:, i1], np.broadcast_to(self.j1.anchor_other, (len(t), 3)))
        th = self._angles(trace.pos[:, i1], a1, trace.pos[:, i2])
        dth = np.stack([trace.angvel[:, i1] @ self.u, trace.angvel[:, i2] @ self.u], axis=-1)
        q = th @ (self.M @ self.Phi)  # modal coordinates Phi^T M theta
        dq = dth @ (self.M @ self.Phi)
        out = {"mode_frequency_ref_1": float(self.w[0]), "mode_frequency_ref_2": float(self.w[1]),
               "linear_amplitude": self.amplitude}
        worst = 0.0
        for k in (0, 1):
            ok = np.isfinite(q[:, k]).all() and np.isfinite(dq[:, k]).all()
            c = _crossings(t, q[:, k], dq[:, k]) if ok else np.array([])
            if len(c) >= 2:
                w = 2 * math.pi * (len(c) - 1) / float(c[-1] - c[0])
                err = abs(w - self.w[k]) / self.w[k]
            else:
                err = float("inf")
            out[f"mode_frequency_error_{k + 1}"] = err
            worst = max(worst, err)
        out["mode_frequency_error"] = worst
        return out


class FourBar(ReferenceModel):
    name = "four_bar"
    summary = ("a closed four-bar linkage (crank, coupler and rocker on four parallel hinges, two of them to the "
               "world) whose crank turns all the way round: the coupler and rocker where the closed-form "
               "kinematics put them, the crank's rate and period from its energy")
    takes = ("exactly three bodies and four revolute [[joint]] tables with parallel axes: the crank (the body of "
             "the first joint to the world) and the rocker (of the second) each hinged to the world, the coupler "
             "hinged to both; gravity (any, or none); a start that moves the linkage as one degree of freedom "
             "(velocities and angular velocities those of the crank's rate, to 1e-9 relative), with the energy "
             "to turn the crank all the way round and no toggle position (the coupler and rocker never "
             "in line). Refuses contact, springs and drag. Loop closure: the harness's joint_drift")
    produces = {
        "crank_period": "measured time of one crank turn (s): the time of the last whole turn in the run over the "
                        "number of turns (Hermite-interpolated from the crank angle and rate)",
        "crank_period_ref": "the integral over a turn of d theta / theta'(theta), theta'(theta)^2 = "
                            "2 (E - V(theta)) / I_eff(theta) (s; periodic trapezoid rule, spectrally exact)",
        "crank_period_error": "|T - T_ref| / T_ref (1; inf before one whole turn)",
        "crank_rate_error": "max_t |theta' - theta'_ref(theta)| / max |theta'_ref| over the measured crank angle "
                            "theta (1)",
        "crank_angle_error": "max_t |theta - theta_ref(t)| (rad), theta_ref(t) the inverse of t(theta) = "
                             "integral of d theta / theta'",
        "four_bar_position_error": "max_t over the three bodies of |x - x_ref(theta)| (m), x_ref where the "
                                   "closed-form kinematics (the coupler-rocker pin on the intersection of two "
                                   "circles) put the centre for the measured crank angle",
    }
    primary = "crank_period_error"

    def __init__(self, scene):
        super().__init__(scene)
        sc = scene
        for eff in ("contact", "spring", "damper", "drag_linear", "drag_quadratic"):
            if sc.has(eff):
                raise ReferenceError(f"{self.name} models the hinges and gravity only; the scene lists {eff!r}",
                                     key="scenario.effects")
        if sc.n_bodies != 3 or len(sc.joints) != 4 or any(j.kind != "revolute" for j in sc.joints):
            raise ReferenceError(f"{self.name} needs three bodies and four revolute joints, the scene has "
                                 f"{sc.n_bodies} bodies and joints {[j.kind for j in sc.joints]}", key="joint")
        world = [j for j in sc.joints if j.other < 0]
        pins = [j for j in sc.joints if j.other >= 0]
        if len(world) != 2 or world[0].body == world[1].body:
            raise ReferenceError("two joints must hold two different bodies (crank, rocker) to the world", key="joint")
        jc, jr = world
        crank, rocker = jc.body, jr.body
        coupler = ({0, 1, 2} - {crank, rocker}).pop()
        pa = next((j for j in pins if {j.body, j.other} == {crank, coupler}), None)
        pb = next((j for j in pins if {j.body, j.other} == {rocker, coupler}), None)
        if pa is None or pb is None:
            raise ReferenceError("the coupler must be hinged to the crank and to the rocker", key="joint")
        u = jc.axis
        for j in sc.joints:
            if np.linalg.norm(np.cross(u, j.axis)) > 1e-9:
                raise ReferenceError(f"the hinge axes must be parallel, got {u.tolist()} and {j.axis.tolist()}",
                                     key=f"joint[{j.index}].axis")
        self.u = u

        def across(v):
            return v - (v @ u) * u

        ground = across(jr.anchor - jc.anchor)
        d = float(np.linalg.norm(ground))
        if not d > 0.0:
            raise ReferenceError("the two world hinges coincide across the axis", key=f"joint[{jr.index}].anchor")
        e1 = ground / d
        e2 = np.cross(u, e1)
        self.e1, self.e2 = e1, e2
        O2, O4, A, B = jc.anchor, jr.anchor, pa.anchor, pb.anchor
        self.O2, self.O4 = O2, O4
        self.a = float(np.linalg.norm(across(A - O2)))
        self.b = float(np.linalg.norm(across(B - A)))
        self.c = float(np.linalg.norm(across(B - O4)))
        if min(self.a, self.b, self.c) <= 0.0:
            raise ReferenceError("a link has zero length across the axes", key="joint")
        # the pins' offsets along the axis, kept as they move
        self.A_along, self.B_along = float((A - O2) @ u), float((B - O4) @ u)
        # the branch of the pin B: on which side of the line A -> O4
        self.sigma = 1.0 if float(np.cross(across(O4 - A), across(B - A)) @ u) < 0.0 else -1.0
        self.bodies = (sc.bodies[crank], sc.bodies[coupler], sc.bodies[rocker])
        # each centre in the frame of its link (from, to): (along, across, axis) components
        self.local = []
        for b, (P, Q) in zip(self.bodies, ((O2, A), (A, B), (O4, B))):
            ev = across(Q - P)
            ev = ev / np.linalg.norm(ev)
            nv = np.cross(u, ev)
            r = b.position - P
            self.local.append((float(r @ ev), float(r @ nv), float(r @ u)))

        def own(b):
            R = quat_to_matrix(b.orientation)
            return float(u @ (R @ np.diag(b.inertia) @ R.T) @ u)

        self.m = np.array([b.mass for b in self.bodies])
        self.Iu = np.array([own(b) for b in self.bodies])
        self.g = np.array(sc.gravity, float)
        th0 = float(self._angle(A))
        # the start: one degree of freedom at the crank's rate
        w0 = float(sc.bodies[crank].angular_velocity @ u)
        x, v, w = self._kinematics(np.array([th0]))
        scale = abs(w0) * (self.a + self.b + self.c) + 1e-12
        for k, b in enumerate(self.bodies):
            if (np.linalg.norm(b.velocity - w0 * v[0, k]) > 1e-9 * scale
                    or np.linalg.norm(b.angular_velocity - w0 * w[0, k] * u) > 1e-9 * scale / self.a):
                raise ReferenceError(f"body {b.name!r} does not start with the motion the crank's rate {w0:g} "
                                     f"rad/s gives it (velocity {(w0 * v[0, k]).tolist()}, angular velocity "
                                     f"{(w0 * w[0, k] * u).tolist()})", key=sc.body_key(b.index, "velocity"))
        if w0 == 0.0:
            raise ReferenceError("the crank starts at rest", key=sc.body_key(crank, "angular_velocity"))
        self.theta0, self.w0 = th0, w0
        self.sense = 1.0 if w0 > 0 else -1.0
        self.E = 0.5 * float(self._inertia(np.array([th0]))[0]) * w0 * w0 + float(self._potential(np.array([th0]))[0])
        # one turn on a uniform grid (periodic: the trapezoid rule converges spectrally)
        N = 1 << 14
        grid = th0 + self.sense * 2 * math.pi * np.arange(N) / N
        rate = self.rate(grid)
        if not np.all(np.isfinite(rate)) or np.min(np.abs(rate)) <= 0.0:
            raise ReferenceError("the crank does not turn all the way round (too little energy, or a toggle "
                                 "position)", key=sc.body_key(crank, "angular_velocity"))
        self.T = float(np.sum(1.0 / np.abs(rate)) * 2 * math.pi / N)
        # t(theta) over one turn by Simpson's rule on pairs of a fine grid,
        # for theta_ref(t) (a cubic Hermite spline through (t, theta, theta'))
        M = 1 << 14
        th = th0 + self.sense * 2 * math.pi * np.arange(2 * M + 1) / (2 * M)
        f = 1.0 / np.abs(self.rate(th))
        hstep = 2 * math.pi / (2 * M)
        seg = hstep / 3.0 * (f[0:-1:2] + 4 * f[1::2] + f[2::2])
        self._t = np.concatenate([[0.0], np.cumsum(seg)])
        self._th = th[::2]
        self._rate = self.rate(self._th)

    # ---- the closed form ---------------------------------------------------
    def _angle(self, A) -> np.ndarray:
        r = A - self.O2
        return np.arctan2(r @ self.e2, r @ self.e1)

    def _kinematics(self, theta: np.ndarray):
        """Centres x (F, 3, 3) m, their velocities per unit crank rate
        v (F, 3, 3) m/rad and the bodies' rates per unit crank rate w (F, 3)
        (crank, coupler, rocker) at crank angles theta (F,)."""
        u, e1, e2 = self.u, self.e1, self.e2
        th = np.asarray(theta, float)[:, None]
        dirA = np.cos(th) * e1 + np.sin(th) * e2
        A = self.O2 + self.a * dirA + self.A_along * u
        D = self.O4 - A
        D = D - (D @ u)[:, None] * u
        L = np.linalg.norm(D, axis=1)[:, None]
        s = (self.b ** 2 - self.c ** 2 + L ** 2) / (2 * L)
        h = np.sqrt(np.maximum(self.b ** 2 - s * s, 0.0)) * np.where(self.b ** 2 - s * s >= 0, 1.0, np.nan)
        dn = np.cross(u, D / L)
        B = A + s * D / L - self.sigma * h * dn
        B = B - ((B - self.O4) @ u)[:, None] * u + self.B_along * u
        # velocities: A' = a u x dirA; A' + w3 u x (B - A) = w4 u x (B - O4)
        Ad = self.a * np.cross(u, dirA)
        p3 = np.cross(u, B - A)
        p4 = np.cross(u, B - self.O4)
        # 2x2 in the plane (e1, e2): [p3, -p4] (w3, w4) = -A'
        m11, m12 = p3 @ e1, -(p4 @ e1)
        m21, m22 = p3 @ e2, -(p4 @ e2)
        r1, r2 = -(Ad @ e1), -(Ad @ e2)
        det = m11 * m22 - m12 * m21
        w3 = (r1 * m22 - m12 * r2) / det
        w4 = (m11 * r2 - m21 * r1) / det
        F = th.shape[0]
        x = np.empty((F, 3, 3))
        v = np.empty((F, 3, 3))
        w = np.stack([np.ones(F), w3, w4], axis=1)
        for k, (P, Q) in enumerate(((self.O2 + 0 * A, A), (A, B), (self.O4 + 0 * A, B))):
            ev = Q - P
            ev = ev - (ev @ u)[:, None] * u
            ev = ev / np.linalg.norm(ev, axis=1)[:, None]
            nv = np.cross(u, ev)
            al, ac, ax = self.local[k]
            x[:, k] = P + al * ev + ac * nv + ax * u
        v[:, 0] = np.cross(u, x[:, 0] - self.O2)
        v[:, 1] = Ad + w3[:, None] * np.cross(u, x[:, 1] - A)
        v[:, 2] = w4[:, None] * np.cross(u, x[:, 2] - self.O4)
        return x, v, w

    def _inertia(self, theta) -> np.ndarray:
        """I_eff (F,) kg m^2: the kinetic energy over theta'^2 / 2."""
        _, v, w = self._kinematics(theta)
        return np.sum(self.m * np.sum(v * v, axis=-1) + self.Iu * w * w, axis=1)

    def _potential(self, theta) -> np.ndarray:
        x, _, _ = self._kinematics(theta)
        return -np.sum(self.m * (x @ self.g), axis=1)

    def rate(self, theta) -> np.ndarray:
        """The crank's rate theta' (F,) rad/s at crank angles theta (F,),
        from the energy (NaN where the crank cannot reach)."""
        k = 2.0 * (self.E - self._potential(theta)) / self._inertia(theta)
        return self.sense * np.sqrt(np.where(k > 0, k, np.nan))

    def angle(self, t: np.ndarray) -> np.ndarray:
        """theta_ref (F,) rad at times t (F,) s (unwrapped, from theta0)."""
        from scipy.interpolate import CubicHermiteSpline

        t = np.asarray(t, float)
        turns = np.floor(t / self.T)
        tt = t - turns * self.T
        sp = CubicHermiteSpline(self._t, self._th, self._rate)
        return sp(np.clip(tt, 0.0, self._t[-1])) + self.sense * 2 * math.pi * turns

    def positions(self, t: np.ndarray) -> np.ndarray:
        x, _, _ = self._kinematics(self.angle(t))
        out = np.full((len(t), self.scene.n_bodies, 3), np.nan)
        for k, b in enumerate(self.bodies):
            out[:, b.index] = x[:, k]
        return out

    def predictions(self) -> dict[str, str]:
        return {"one crank turn": f"{self.T:.9g} s",
                "links": f"crank {self.a:.6g} m, coupler {self.b:.6g} m, rocker {self.c:.6g} m, ground "
                         f"{float(np.linalg.norm((self.O4 - self.O2) - ((self.O4 - self.O2) @ self.u) * self.u)):.6g} m"}

    def metrics(self, trace) -> dict[str, float]:
        from physbench.contract.rotation import quat_rotate

        t = np.asarray(trace.t, float)
        ic = self.bodies[0].index
        pa = next(j for j in self.scene.joints if j.other >= 0 and ic in (j.body, j.other))
        local = pa.anchor_body if pa.body == ic else pa.anchor_other
        # the crank pin where the crank carries it: the crank angle
        A = trace.pos[:, ic] + quat_rotate(trace.quat[:, ic], np.broadcast_to(local, (len(t), 3)))
        th = np.unwrap(self._angle(A))
        dth = trace.angvel[:, ic] @ self.u
        out: dict[str, float] = {"crank_period_ref": self.T}
        if not (np.isfinite(th).all() and np.isfinite(dth).all()):
            nan = float("nan")
            out.update(crank_period=nan, crank_period_error=float("inf"), crank_rate_error=nan,
                       crank_angle_error=nan, four_bar_position_error=nan)
            return out
        y = self.sense * (th - self.theta0)
        turns = int(np.floor(np.max(y) / (2 * math.pi)))
        if turns >= 1:
            c = _crossings(t, y - 2 * math.pi * turns, self.sense * dth)
            T = float(c[-1]) / turns if len(c) else float("nan")
            out["crank_period"] = T
            out["crank_period_error"] = abs(T - self.T) / self.T if np.isfinite(T) else float("inf")
        else:
            out["crank_period"] = float("nan")
            out["crank_period_error"] = float("inf")
        ref_rate = self.rate(th)
        out["crank_rate_error"] = float(np.max(np.abs(dth - ref_rate)) / np.max(np.abs(self._rate)))
        out["crank_angle_error"] = float(np.max(np.abs(th - self.angle(t))))
        x, _, _ = self._kinematics(th)
        err = 0.0
        for k, b in enumerate(self.bodies):
            err = max(err, float(np.max(np.linalg.norm(trace.pos[:, b.index] - x[:, k], axis=1))))
        out["four_bar_position_error"] = err
        return out
