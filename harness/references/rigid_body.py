"""High-accuracy references for spinning rigid bodies (scipy ``solve_ivp``,
DOP853, rtol 1e-10).

``torque_free_rigid_body``: one body, no forces (or uniform gravity, which
moves the centre of mass but exerts no torque about it).  Euler's equations
in the body's principal frame,

    I1 w1' = (I2 - I3) w2 w3,  I2 w2' = (I3 - I1) w3 w1,  I3 w3' = (I1 - I2) w1 w2,

with the orientation from q' = q (x) (0, w_body) / 2 (q wxyz, body -> world).
Kinetic energy E = w.Iw/2 and the world angular momentum L = R I w are
invariant; spin about the largest or smallest principal axis is stable, spin
about the intermediate axis flips over periodically (Dzhanibekov effect).

Metrics:

- ``orientation_error`` (rad): max over the run of the rotation angle between
  the body's orientation and the reference's;
- ``angular_velocity_error``: max |w(t) - w_ref(t)| / |w(0)| (world frame);
- ``flip_period_error``: for an intermediate-axis spin, the mean time between
  sign changes of the intermediate-axis component of the body-frame angular
  velocity (half the period of w_body) against the reference's, relative; no
  sign change in the run where the reference flips gives inf.  Reported only
  when the body spins mainly about its intermediate axis (largest component
  of I w) and the reference flips at least twice in the run;
- ``spin_axis_deviation`` (rad): max over the run of the angle between the
  world direction of the principal axis nearest the initial spin and its
  initial direction (``spin_axis_deviation_ref`` for the reference: a stable
  spin wobbles within a cone set by the perturbation);
- ``spin_axis_excess`` (rad): how far the axis strays beyond the reference's
  cone, max(0, spin_axis_deviation - spin_axis_deviation_ref).

``heavy_top``: one body held by world springs/dampers (the scene's
``[[spring]]`` tables with a = "world"), under gravity: a symmetric top whose
tip is tied to a fixed pivot by a stiff zero-length spring.  There is no
joint vocabulary, so the pivot *is* a spring in every engine, and the
reference integrates exactly the same equations (rigid body + spring force
-k (|d| - L0) d/|d| - c (d'.u) u at the anchor + gravity + gyroscopic terms)
to rtol 1e-10.  Metrics: ``precession_rate_error`` = |Omega - Omega_ref| /
|Omega_ref| where Omega is the least-squares slope of the unwrapped azimuth of
the symmetry axis; ``tilt_error`` (rad) = max |theta(t) - theta_ref(t)| of the
axis's angle from the vertical; ``trajectory_rmse`` of the centre of mass.
``precession_rate_ideal`` gives the rigid-pivot gyroscopic estimate
m g l / (I3 w3) for comparison (not checked).
"""

from __future__ import annotations

import math

import numpy as np

from physbench.contract.rotation import quat_rotate, quat_to_matrix, world_to_body_angvel
from physbench.harness.references import (BODY_PARAM, TRAJECTORY, ReferenceError, ReferenceModel, ReferenceSeries,
                                fit_slope, trajectory_metrics)

RTOL = 1e-10
ATOL = 1e-12

# Reference solutions depend only on the scene's parameters; one conformance
# job builds the same model once per engine, so keep the last few.
_CACHE: dict[tuple, object] = {}
_CACHE_SIZE = 16


def _cached(key: tuple, compute):
    if key not in _CACHE:
        if len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = compute()
    return _CACHE[key]


def euler_rhs(inertia: np.ndarray):
    """Right-hand side for y = (q (4), w_body (3)) of a torque-free body:
    q' = q (x) (0, w_body) / 2 and Euler's equations, written with Python
    floats (the solver calls it ~10^4 times per solve and numpy's per-call
    overhead on 4-vectors would dominate).  The same operations in the
    same order as :func:`contract.rotation.quat_mul` (the zero terms
    included), so the solution is bit for bit the one of the array form
    (tests/test_references.py::test_torque_free_rhs_matches_the_array_form)."""
    I1, I2, I3 = (float(x) for x in inertia)
    a1, a2, a3 = I2 - I3, I3 - I1, I1 - I2

    def f(_t, y):
        qw, qx, qy, qz, w1, w2, w3 = y.tolist()
        return [0.5 * (qw * 0.0 - qx * w1 - qy * w2 - qz * w3),
                0.5 * (qw * w1 + qx * 0.0 + qy * w3 - qz * w2),
                0.5 * (qw * w2 - qx * w3 + qy * 0.0 + qz * w1),
                0.5 * (qw * w3 + qx * w2 - qy * w1 + qz * 0.0),
                a1 * w2 * w3 / I1,
                a2 * w3 * w1 / I2,
                a3 * w1 * w2 / I3]

    return f


def solve_torque_free(inertia: np.ndarray, q0: np.ndarray, w0_body: np.ndarray, t_end: float,
                      t_eval: np.ndarray | None = None):
    """Integrate Euler's equations + quaternion kinematics; returns the
    solve_ivp solution (dense output on)."""
    from scipy.integrate import solve_ivp  # heavy (0.3 s); a sweep's client loads this module only to check scenes

    y0 = np.concatenate([q0, w0_body])
    return solve_ivp(euler_rhs(np.asarray(inertia, float)), (0.0, t_end), y0, method="DOP853",
                     rtol=RTOL, atol=ATOL, dense_output=True, t_eval=t_eval)


def sign_change_times(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Times where y (F,) changes sign, linearly interpolated."""
    s = np.sign(y)
    k = np.nonzero(s[:-1] * s[1:] < 0)[0]
    return t[k] - y[k] * (t[k + 1] - t[k]) / (y[k + 1] - y[k])


def intermediate_flip_interval(inertia: np.ndarray, w0_body: np.ndarray) -> float:
    """Analytic time between sign changes of the intermediate-axis body
    angular velocity: 2 K(m) / lambda (Jacobi elliptic solution of Euler's
    equations, Landau & Lifshitz, Mechanics, section 37).  Used to test the
    numerical reference.  Requires distinct moments."""
    from scipy.special import ellipk

    order = np.argsort(inertia)
    I1, I2, I3 = (float(inertia[i]) for i in order)
    w = np.asarray(w0_body, float)[order]
    E2 = float(np.sum(np.array([I1, I2, I3]) * w * w))  # 2E
    L2 = float(np.sum((np.array([I1, I2, I3]) * w) ** 2))  # |L|^2
    if L2 > E2 * I2:
        lam = math.sqrt((I3 - I2) * (L2 - E2 * I1) / (I1 * I2 * I3))
        m = (I2 - I1) * (E2 * I3 - L2) / ((I3 - I2) * (L2 - E2 * I1))
    else:
        lam = math.sqrt((I2 - I1) * (E2 * I3 - L2) / (I1 * I2 * I3))
        m = (I3 - I2) * (L2 - E2 * I1) / ((I2 - I1) * (E2 * I3 - L2))
    return 2.0 * float(ellipk(m)) / lam


def _rotation_angle(q: np.ndarray, qr: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation taking qr to q, (F,)."""
    dot = np.abs(np.einsum("fi,fi->f", q, qr) / (np.linalg.norm(q, axis=1) * np.linalg.norm(qr, axis=1)))
    return 2.0 * np.arccos(np.clip(dot, -1.0, 1.0))


class TorqueFreeRigidBody(ReferenceModel):
    name = "torque_free_rigid_body"
    summary = "a free spinning body: Euler's equations integrated to 1e-10 (Dzhanibekov flips, stable spins)"
    takes = ("one spinning body without static geometry, springs or drag; unequal principal moments need the "
             "'gyroscopic' effect; gravity only moves the centre")
    params = (BODY_PARAM,)
    produces = {
        "orientation_error": "largest rotation angle between the body's and the reference orientation (rad)",
        "angular_velocity_error": "max_t |w - w_ref| / |w0| (1)",
        "spin_axis_deviation": "largest angle of the spin axis from its start (rad)",
        "spin_axis_deviation_ref": "the same for the reference (rad)",
        "spin_axis_excess": "max(0, spin_axis_deviation - spin_axis_deviation_ref) (rad)",
        "flip_interval": "measured mean time between intermediate-axis flips (s)",
        "flip_interval_ref": "reference flip interval (s)",
        "flip_period_error": "|T - T_ref| / T_ref (1; spin about the intermediate axis only)",
        **TRAJECTORY,
    }
    primary = "orientation_error"

    def __init__(self, scene):
        super().__init__(scene)
        b = self.the_body()
        if scene.has("contact") and scene.statics:
            raise ReferenceError("torque_free_rigid_body needs a free body (no static geometry)")
        if scene.springs or scene.has("drag_linear") or scene.has("drag_quadratic"):
            raise ReferenceError("torque_free_rigid_body needs no springs and no drag")
        if len(set(np.round(b.inertia, 15))) > 1 and not scene.has("gyroscopic"):
            raise ReferenceError("torque_free_rigid_body: the body has unequal principal moments, "
                                 "so the scene needs the 'gyroscopic' effect")
        self.body = b
        self.inertia = np.asarray(b.inertia, float)
        self.q0 = b.orientation / np.linalg.norm(b.orientation)
        self.w0_world = b.angular_velocity.copy()
        self.w0 = world_to_body_angvel(self.q0, self.w0_world)
        if not np.any(self.w0):
            raise ReferenceError("torque_free_rigid_body needs a spinning body")
        self.x0, self.v0 = b.position.copy(), b.velocity.copy()
        self.g = scene.gravity.copy()
        t_end = scene.duration * (1 + 1e-9) + 1e-9
        key = ("torque_free", tuple(map(float, self.inertia)), tuple(map(float, self.q0)),
               tuple(map(float, self.w0)), t_end)
        self._sol_key, self._t_end = key, t_end
        order = np.argsort(self.inertia)
        self.mid_axis = int(order[1])
        self.spin_axis = int(np.argmax(np.abs(self.inertia * self.w0)))

    @property
    def _sol(self):
        """The reference solution, solved on first use (loading a scene
        only checks that the model fits it)."""
        return _cached(self._sol_key, lambda: solve_torque_free(self.inertia, self.q0, self.w0, self._t_end))

    def reference(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q (F, 4) wxyz, w_body (F, 3)) at times t (clipped to the run)."""
        y = self._sol.sol(np.clip(t, 0.0, self._sol.t[-1]))
        q = y[:4].T
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        return q, y[4:].T

    def positions(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)[:, None]
        p = self.x0 + self.v0 * t + 0.5 * self.g * t * t
        out = np.full((t.shape[0], self.scene.n_bodies, 3), np.nan)
        out[:, self.body.index] = p
        return out

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t, float)
        quat = np.full((t.shape[0], self.scene.n_bodies, 4), np.nan)
        quat[:, self.body.index] = self.reference(t)[0]
        return self.positions(t), quat

    def predictions(self) -> dict[str, str]:
        if self._flips():
            return {"flip period (half of the intermediate-axis cycle)":
                    f"{intermediate_flip_interval(self.inertia, self.w0):.6g} s"}
        return {}

    def _flips(self) -> bool:
        """Spun about (near) the intermediate axis of distinct moments."""
        return len(set(np.round(self.inertia, 12))) == 3 and self.spin_axis == self.mid_axis

    def reference_series(self) -> list[ReferenceSeries]:
        """The body-frame angular velocity about the intermediate axis
        (rad/s): its sign changes are the flips."""
        if not self._flips():
            return []
        i, k = self.body.index, self.mid_axis
        return [ReferenceSeries(
            f"{self.body.name}/w_intermediate", "rad/s",
            f"angular velocity about the intermediate axis (body frame); flips every "
            f"{intermediate_flip_interval(self.inertia, self.w0):.6g} s",
            lambda t: self.reference(np.asarray(t, float))[1][:, k],
            lambda tr: world_to_body_angvel(tr.quat[:, i], tr.angvel[:, i])[:, k])]

    def reference_times(self) -> list[tuple[float, str]]:
        """The flips: sign changes of the reference intermediate-axis rate,
        sampled at the scene's dt."""
        if not self._flips():
            return []
        t = np.arange(0.0, self.scene.duration + 0.5 * self.scene.dt, self.scene.dt)
        return [(float(tf), f"flip {k + 1}")
                for k, tf in enumerate(sign_change_times(t, self.reference(t)[1][:, self.mid_axis]))]

    def flip_interval(self, t: np.ndarray, w_body: np.ndarray) -> float:
        """Mean time between sign changes of the intermediate-axis component
        (nan with fewer than two sign changes)."""
        z = sign_change_times(t, w_body[:, self.mid_axis])
        return float(np.mean(np.diff(z))) if len(z) >= 2 else math.nan

    def metrics(self, trace) -> dict[str, float]:
        i = self.body.index
        ref = self.positions(trace.t)
        out = trajectory_metrics(trace.pos[:, [i]], ref[:, [i]])
        q, w = trace.quat[:, i], trace.angvel[:, i]
        q_ref, wb_ref = self.reference(trace.t)
        w_ref = quat_rotate(q_ref, wb_ref)
        out["orientation_error"] = float(np.nanmax(_rotation_angle(q, q_ref)))
        out["angular_velocity_error"] = float(np.nanmax(np.linalg.norm(w - w_ref, axis=1)) / np.linalg.norm(self.w0))
        # spin axis deviation
        e = np.zeros(3)
        e[self.spin_axis] = 1.0
        a0 = quat_rotate(self.q0, e)
        for name, qq in (("spin_axis_deviation", q), ("spin_axis_deviation_ref", q_ref)):
            a = quat_rotate(qq, e)
            out[name] = float(np.nanmax(np.arccos(np.clip(a @ a0, -1.0, 1.0))))
        out["spin_axis_excess"] = max(0.0, out["spin_axis_deviation"] - out["spin_axis_deviation_ref"])
        # flips: reference on a fine grid, measured on the trace (only for a
        # spin about the intermediate axis: the grid costs a dense-output
        # evaluation of every solver step)
        T_ref = math.nan
        if self.spin_axis == self.mid_axis:
            t_end = float(trace.t[-1])
            tf = np.linspace(0.0, t_end, max(2000, int(t_end * 2000)))
            _, wf = self.reference(tf)
            T_ref = self.flip_interval(tf, wf)
        if math.isfinite(T_ref):
            wb = world_to_body_angvel(q, w)
            T = self.flip_interval(trace.t, wb)
            out["flip_interval"] = T
            out["flip_interval_ref"] = T_ref
            out["flip_period_error"] = abs(T - T_ref) / T_ref if math.isfinite(T) else math.inf
        return out


class HeavyTop(ReferenceModel):
    name = "heavy_top"
    summary = "a symmetric top held at a pivot by stiff springs to the world: precession and nutation (ODE, 1e-10)"
    takes = ("one symmetric body (two equal principal moments), springs between it and the world, gravity, the "
             "'gyroscopic' effect, no static geometry")
    produces = {
        "precession_rate": "measured mean precession rate of the symmetry axis (rad/s)",
        "precession_rate_ref": "the reference's (rad/s)",
        "precession_rate_ideal": "the gyroscopic approximation m g l / (I3 w3) (rad/s)",
        "precession_rate_error": "|measured - reference| / |reference| (1)",
        "tilt_error": "largest |tilt - tilt_ref| of the symmetry axis (rad)",
        **TRAJECTORY,
    }
    primary = "precession_rate_error"

    def __init__(self, scene):
        super().__init__(scene)
        if scene.n_bodies != 1:
            raise ReferenceError("heavy_top needs exactly one body")
        b = scene.bodies[0]
        self.body = b
        if scene.has("contact") and scene.statics:
            raise ReferenceError("heavy_top needs no static geometry (the pivot is a spring to the world)")
        if not scene.springs or any(sp.a >= 0 and sp.b >= 0 for sp in scene.springs):
            raise ReferenceError("heavy_top needs springs between the body and the world")
        if not scene.has("gyroscopic"):
            raise ReferenceError("heavy_top needs the 'gyroscopic' effect")
        I = np.asarray(b.inertia, float)
        # symmetry axis: the moment that differs from the other two
        if abs(I[0] - I[1]) <= 1e-12 * I.max():
            self.sym = 2
        elif abs(I[1] - I[2]) <= 1e-12 * I.max():
            self.sym = 0
        elif abs(I[0] - I[2]) <= 1e-12 * I.max():
            self.sym = 1
        else:
            raise ReferenceError("heavy_top needs a symmetric body (two equal principal moments)")
        self.inertia = I
        self.m = b.mass
        self.g = scene.gravity.copy()
        if not np.any(self.g):
            raise ReferenceError("heavy_top needs gravity")
        self.up = -self.g / np.linalg.norm(self.g)
        # springs as (world point, body anchor, k, L0, c)
        self.springs = []
        for sp in scene.springs:
            if sp.a < 0:
                self.springs.append((sp.anchor_a.copy(), sp.anchor_b.copy(), sp.stiffness, sp.rest_length, sp.damping))
            else:
                self.springs.append((sp.anchor_b.copy(), sp.anchor_a.copy(), sp.stiffness, sp.rest_length, sp.damping))
        self.pivot = self.springs[0][0]
        self._g = tuple(float(c) for c in self.g)
        self._I = tuple(float(c) for c in I)
        self._springs_t = [(tuple(map(float, p)), tuple(map(float, a)), float(k), float(L0), float(c))
                           for p, a, k, L0, c in self.springs]
        q0 = b.orientation / np.linalg.norm(b.orientation)
        y0 = np.concatenate([b.position, b.velocity, q0, world_to_body_angvel(q0, b.angular_velocity)])
        t_end = scene.duration * (1 + 1e-9) + 1e-9
        key = ("heavy_top", self._I, self.m, self._g, tuple(self._springs_t), tuple(map(float, y0)), t_end)
        self._sol_args = (key, y0, t_end)
        e = np.zeros(3)
        e[self.sym] = 1.0
        self.e_sym = e
        a0 = quat_rotate(q0, e)
        w3 = float(world_to_body_angvel(q0, b.angular_velocity)[self.sym])
        lever = float(np.linalg.norm(b.position - self.pivot))
        self.precession_ideal = self.m * float(np.linalg.norm(self.g)) * lever / (I[self.sym] * w3) if w3 else math.nan
        self._a0 = a0

    def _rhs(self, _t, y):
        """d/dt of (x, v, q wxyz, w_body), written with scalars: the solver
        calls it ~10^5 times, and numpy's per-call overhead on 3-vectors
        would dominate."""
        x0, x1, x2, v0, v1, v2, qw, qx, qy, qz, p, q_, r = y
        n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw / n, qx / n, qy / n, qz / n
        # rotation matrix (body -> world)
        R00 = 1 - 2 * (qy * qy + qz * qz); R01 = 2 * (qx * qy - qw * qz); R02 = 2 * (qx * qz + qw * qy)
        R10 = 2 * (qx * qy + qw * qz); R11 = 1 - 2 * (qx * qx + qz * qz); R12 = 2 * (qy * qz - qw * qx)
        R20 = 2 * (qx * qz - qw * qy); R21 = 2 * (qy * qz + qw * qx); R22 = 1 - 2 * (qx * qx + qy * qy)
        # world angular velocity
        w0 = R00 * p + R01 * q_ + R02 * r
        w1 = R10 * p + R11 * q_ + R12 * r
        w2 = R20 * p + R21 * q_ + R22 * r
        m = self.m
        F0, F1, F2 = m * self._g[0], m * self._g[1], m * self._g[2]
        T0 = T1 = T2 = 0.0
        for (P0, P1, P2), (a0, a1, a2), k, L0, c in self._springs_t:
            r0 = R00 * a0 + R01 * a1 + R02 * a2
            r1 = R10 * a0 + R11 * a1 + R12 * a2
            r2 = R20 * a0 + R21 * a1 + R22 * a2
            d0, d1, d2 = x0 + r0 - P0, x1 + r1 - P1, x2 + r2 - P2
            dd0 = v0 + w1 * r2 - w2 * r1
            dd1 = v1 + w2 * r0 - w0 * r2
            dd2 = v2 + w0 * r1 - w1 * r0
            L = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if L0 == 0.0:
                f0, f1, f2 = -k * d0, -k * d1, -k * d2
                if c and L > 0:
                    u0, u1, u2 = d0 / L, d1 / L, d2 / L
                    s = c * (dd0 * u0 + dd1 * u1 + dd2 * u2)
                    f0, f1, f2 = f0 - s * u0, f1 - s * u1, f2 - s * u2
            else:
                u0, u1, u2 = d0 / L, d1 / L, d2 / L
                s = k * (L - L0) + c * (dd0 * u0 + dd1 * u1 + dd2 * u2)
                f0, f1, f2 = -s * u0, -s * u1, -s * u2
            F0 += f0; F1 += f1; F2 += f2
            T0 += r1 * f2 - r2 * f1
            T1 += r2 * f0 - r0 * f2
            T2 += r0 * f1 - r1 * f0
        # torque to the body frame (R^T T); Euler's equations
        tb0 = R00 * T0 + R10 * T1 + R20 * T2
        tb1 = R01 * T0 + R11 * T1 + R21 * T2
        tb2 = R02 * T0 + R12 * T1 + R22 * T2
        I0, I1, I2 = self._I
        pd = (tb0 - (I2 - I1) * q_ * r) / I0
        qd = (tb1 - (I0 - I2) * r * p) / I1
        rd = (tb2 - (I1 - I0) * p * q_) / I2
        # q' = q (x) (0, w_body) / 2
        return [v0, v1, v2, F0 / m, F1 / m, F2 / m,
                0.5 * (-qx * p - qy * q_ - qz * r),
                0.5 * (qw * p + qy * r - qz * q_),
                0.5 * (qw * q_ - qx * r + qz * p),
                0.5 * (qw * r + qx * q_ - qy * p),
                pd, qd, rd]

    @property
    def _sol(self):
        """The reference solution, solved on first use."""
        from scipy.integrate import solve_ivp  # heavy: see solve_torque_free

        key, y0, t_end = self._sol_args
        return _cached(key, lambda: solve_ivp(self._rhs, (0.0, t_end), y0, method="DOP853",
                                              rtol=RTOL, atol=ATOL, dense_output=True))

    def reference(self, t: np.ndarray):
        y = self._sol.sol(np.clip(t, 0.0, self._sol.t[-1]))
        q = y[6:10].T
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        return y[:3].T, q

    def positions(self, t: np.ndarray) -> np.ndarray:
        x, _ = self.reference(np.asarray(t, float))
        return x[:, None, :]

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, q = self.reference(np.asarray(t, float))
        return x[:, None, :], q[:, None, :]

    def _azimuth_tilt(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = quat_rotate(q, self.e_sym)  # (F, 3)
        up = self.up
        # horizontal basis: any vector normal to up, and up x it
        h1 = np.cross(up, [0.0, 1.0, 0.0]) if abs(up[1]) < 0.9 else np.cross(up, [1.0, 0.0, 0.0])
        h1 /= np.linalg.norm(h1)
        h2 = np.cross(up, h1)
        az = np.unwrap(np.arctan2(a @ h2, a @ h1))
        tilt = np.arccos(np.clip(a @ up, -1.0, 1.0))
        return az, tilt

    def precession_rate_ref(self) -> float:
        """The reference's mean precession rate (rad/s) over the run sampled
        at the scene's dt (what the ``precession_rate_ref`` metric fits on a
        run of that dt)."""
        t = np.arange(0.0, self.scene.duration + 0.5 * self.scene.dt, self.scene.dt)
        return fit_slope(t, self._azimuth_tilt(self.reference(t)[1])[0])

    def reference_series(self) -> list[ReferenceSeries]:
        """The symmetry axis' azimuth about the vertical (rad, unwrapped: its
        slope is the precession rate) and its tilt from the vertical (rad:
        the nutation), from the reference solution."""
        name = self.body.name
        return [ReferenceSeries(f"{name}/precession_angle", "rad",
                                f"azimuth of the symmetry axis: precesses at {self.precession_rate_ref():.6g} rad/s "
                                f"(gyroscopic approximation {self.precession_ideal:.6g})",
                                lambda t: self._azimuth_tilt(self.reference(np.asarray(t, float))[1])[0],
                                lambda tr: self._azimuth_tilt(tr.quat[:, self.body.index])[0]),
                ReferenceSeries(f"{name}/tilt", "rad", "tilt of the symmetry axis from the vertical (nutation)",
                                lambda t: self._azimuth_tilt(self.reference(np.asarray(t, float))[1])[1],
                                lambda tr: self._azimuth_tilt(tr.quat[:, self.body.index])[1])]

    def predictions(self) -> dict[str, str]:
        return {"precession rate (reference solution)": f"{self.precession_rate_ref():.6g} rad/s",
                "precession rate (gyroscopic approximation m g l / (I3 w3))": f"{self.precession_ideal:.6g} rad/s"}

    def metrics(self, trace) -> dict[str, float]:
        out = trajectory_metrics(trace.pos, self.positions(trace.t))
        _, q_ref = self.reference(trace.t)
        az, tilt = self._azimuth_tilt(trace.quat[:, 0])
        az_r, tilt_r = self._azimuth_tilt(q_ref)
        om = fit_slope(trace.t, az)
        om_r = fit_slope(trace.t, az_r)
        out["precession_rate"] = om
        out["precession_rate_ref"] = om_r
        out["precession_rate_ideal"] = self.precession_ideal
        out["precession_rate_error"] = abs(om - om_r) / abs(om_r)
        out["tilt_error"] = float(np.nanmax(np.abs(tilt - tilt_r)))
        return out
