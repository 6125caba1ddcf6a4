"""Compiled free flight: the force kernels (one per smooth effect) and the
integrators over all bodies in one call.

Loops over bodies (and springs) with a fixed order, no BLAS (the bits do
not depend on the BLAS kernel: tests/test_engine_blas_free.py).  Shapes:
positions ``x`` (n, 3) m, orientations ``q`` (n, 4) wxyz, velocities
``v``/``w`` (n, 3) world frame, rotations ``R`` (n, 3, 3), forces and
torques ``F``/``T`` (n, 3) N, N m (world frame, about the centre of mass).

The force model is a :data:`ForceModel` (engine.forces.force_model), the
effects absent from a scene as empty arrays: ``mg`` (n, 3) or (0, 3) gravity
forces; ``c_lin`` (n,) or (0,) linear drag N s/m; ``c_quad`` (n,) or (0,)
quadratic drag N s^2/m^2; springs ``s_a``/``s_b`` (k,) body or -1 (the
world), anchors ``s_pa``/``s_pb`` (k, 3) (body frame; world points for the
world), ``s_k`` N/m, ``s_c`` N s/m, ``s_L0`` m (k,); the explicit
gyroscopic torque on bodies ``g_idx`` (g,) with principal moments ``g_I``
(g, 3).  :func:`apply_forces` is the one list of the force kernels, in the
force stages' order (engine.forces.FORCES): the staged force stages, the
integrators' evaluations at their intermediate states (:func:`evaluate`)
and the fused steps (engine/fused/part.py) all follow it.  Integrators:
see engine/integrate.py (``METHOD`` codes); :func:`fly` is the free-flight
stage's one call, staged and fused.

Also the step loop's per-step pose kernels: the start of a (mini-)step
(:func:`begin_step`), the rotation split's turn rate (:func:`max_turn_sq`)
and the CCD stage's end-pose check (:func:`end_displacement`,
:func:`end_pose_pairs`).
"""

from __future__ import annotations

import functools
import math

from collections import namedtuple

from numba import njit, types
from numba.extending import NativeValue, box, models, overload, register_model, typeof_impl, unbox

#: the compiled force model (module doc): one field per force kernel's
#: arrays, in :func:`apply_forces`'s order
ForceModel = namedtuple("ForceModel", ("mg", "c_lin", "c_quad", "s_a", "s_b", "s_pa", "s_pb", "s_k", "s_c", "s_L0",
                                       "g_idx", "g_I"))

#: the free flight's law (:func:`free_flight`): the integrator's ``METHOD``
#: code (a :class:`Method`), whether there are forces at all, whether they
#: are state-independent (``constant``: evaluated once), whether any makes
#: torques, the force model
#: (:data:`ForceModel`), inverse masses (n,) 1/kg and principal inverse
#: inertias (n, 3) 1/(kg m^2), the contact lever (1/2, or 1 for the
#: velocity-first integrator)
Integrator = namedtuple("Integrator", ("method", "has_forces", "constant", "torque", "fm", "inv_m", "inv_I",
                                       "lever"))

#: the start of a free flight: pose x (n, 3), q (n, 4), velocities v, w
#: (n, 3) (w possibly after the implicit gyroscopic update), ``w_start`` the
#: state's angular velocities (n, 3), the forces F, T (n, 3) evaluated there
#: and their rotations R (n, 3, 3)
FlightStart = namedtuple("FlightStart", ("x", "q", "v", "w", "w_start", "F", "T", "R"))

#: what a free flight writes: the end state x (n, 3), q (n, 4), v, w (n, 3),
#: the step's mean torque ``T_mean`` and mean velocities ``u_lin``, ``u_ang``
#: (n, 3)
FlightEnd = namedtuple("FlightEnd", ("x", "q", "v", "w", "T_mean", "u_lin", "u_ang"))

#: the free-flight stage's kept arrays (:func:`fly`;
#: engine.integrate.IntegrateVelocities.pack): its :data:`Integrator`, the
#: context's working velocities ``V``, ``W`` (n, 3: the first n rows), their
#: copies after the flight ``v_free``, ``w_free``, the flight's start angular
#: velocities ``w0`` (n, 3), ``T_mean``, ``u_lin``, ``u_ang`` (n, 3), the
#: work arrays (:data:`WORK_SLABS`, n, 3) and ``work_q`` (2, n, 4), the
#: pseudo velocities ``vp``, ``wp`` (n, 3: first n rows) the position
#: update reads
Flight = namedtuple("Flight", ("ig", "V", "W", "v_free", "w_free", "w0", "T_mean", "u_lin", "u_ang", "work", "work_q",
                               "vp", "wp"))

METHOD = {"explicit_euler": 0, "semi_implicit_euler": 1, "midpoint": 2, "heun": 3, "rk4": 4, "velocity_verlet": 5}


class Method:
    """An integrator's ``METHOD`` code as :data:`Integrator`'s ``method``:
    its numba type (:class:`MethodType`) carries the code, so a flight
    compiles for its own method alone (:func:`free_flight`; the fused steps
    once per method, tests/test_engine_jit.py)."""

    __slots__ = ("code",)

    def __init__(self, code: int):
        self.code = int(code)

    def __eq__(self, other) -> bool:
        return isinstance(other, Method) and other.code == self.code

    def __hash__(self) -> int:
        return hash(("Method", self.code))

    def __repr__(self) -> str:
        return f"Method({self.code})"


class MethodType(types.Type):
    """The numba type of a :class:`Method`: one type per code (no data)."""

    def __init__(self, code: int):
        self.code = int(code)
        super().__init__(name=f"Method({self.code})")


@typeof_impl.register(Method)
def _typeof_method(val, c):
    return MethodType(val.code)


register_model(MethodType)(models.OpaqueModel)


@unbox(MethodType)
def _unbox_method(typ, obj, c):
    return NativeValue(c.context.get_dummy_value())


@box(MethodType)
def _box_method(typ, val, c):
    return c.pyapi.unserialize(c.pyapi.serialize_object(Method(typ.code)))


#: slabs of :func:`free_flight`'s work array (WORK_SLABS, n, 3): its
#: intermediate states, accelerations, torques and sums (0-14), the
#: rotations at an intermediate state (15-17, as (n, 3, 3)); its quaternion
#: work array ``work_q`` (2, n, 4) holds the intermediate orientation and
#: the rk4 quaternion sum.  Every slab ``work[i]`` is C-contiguous, the
#: layout of the context's arrays, so the force kernels the integrators call
#: at intermediate states are the ones the force stages call (one compile
#: each).  Nothing is allocated per call
#: (tests/test_engine_steady.py::test_steady_step_allocates_nothing)
WORK_SLABS = 18


@njit(cache=True, inline="always")
def _rot_row(R, k, w, x, y, z):
    """R[k] (3, 3) the rotation matrix of the quaternion (w, x, y, z) (the
    arithmetic of mathutil.quat_to_matrix)."""
    R[k, 0, 0] = 1 - 2 * (y * y + z * z)
    R[k, 0, 1] = 2 * (x * y - w * z)
    R[k, 0, 2] = 2 * (x * z + w * y)
    R[k, 1, 0] = 2 * (x * y + w * z)
    R[k, 1, 1] = 1 - 2 * (x * x + z * z)
    R[k, 1, 2] = 2 * (y * z - w * x)
    R[k, 2, 0] = 2 * (x * z - w * y)
    R[k, 2, 1] = 2 * (y * z + w * x)
    R[k, 2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True)
def q2m(q, R):
    """Rotation matrices R (n, 3, 3) of the quaternions q (n, 4) wxyz (the
    arithmetic of mathutil.quat_to_matrix)."""
    for k in range(q.shape[0]):
        _rot_row(R, k, q[k, 0], q[k, 1], q[k, 2], q[k, 3])


@njit(cache=True)
def gravity(mg, F):
    """F += m g."""
    for k in range(mg.shape[0]):
        for c in range(3):
            F[k, c] += mg[k, c]


@njit(cache=True)
def linear_drag(c_lin, v, F):
    """F -= c v (Stokes drag)."""
    for k in range(c_lin.shape[0]):
        for c in range(3):
            F[k, c] -= c_lin[k] * v[k, c]


@njit(cache=True)
def quadratic_drag(c_quad, v, F):
    """F -= c |v| v."""
    for k in range(c_quad.shape[0]):
        s = c_quad[k] * math.sqrt(v[k, 0] * v[k, 0] + v[k, 1] * v[k, 1] + v[k, 2] * v[k, 2])
        for c in range(3):
            F[k, c] -= s * v[k, c]


@njit(cache=True)
def _end(i, anchor, x, R, v, w):
    """World point, lever arm and point velocity of a spring end on body i
    (i < 0: the world point ``anchor`` at rest)."""
    if i < 0:
        return anchor[0], anchor[1], anchor[2], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    rx = R[i, 0, 0] * anchor[0] + R[i, 0, 1] * anchor[1] + R[i, 0, 2] * anchor[2]
    ry = R[i, 1, 0] * anchor[0] + R[i, 1, 1] * anchor[1] + R[i, 1, 2] * anchor[2]
    rz = R[i, 2, 0] * anchor[0] + R[i, 2, 1] * anchor[1] + R[i, 2, 2] * anchor[2]
    vx = v[i, 0] + (w[i, 1] * rz - w[i, 2] * ry)
    vy = v[i, 1] + (w[i, 2] * rx - w[i, 0] * rz)
    vz = v[i, 2] + (w[i, 0] * ry - w[i, 1] * rx)
    return x[i, 0] + rx, x[i, 1] + ry, x[i, 2] + rz, rx, ry, rz, vx, vy, vz


@njit(cache=True, inline="always")
def _spring(s, s_a, s_b, s_pa, s_pb, s_k, s_c, s_L0, x, R, v, w):
    """Spring s's force on body a, f u (N, 3 components: tension f along u,
    see :func:`springs`), and its lever arms r_a, r_b (m) from the bodies'
    centres to the anchor points."""
    pax, pay, paz, rax, ray, raz, vax, vay, vaz = _end(s_a[s], s_pa[s], x, R, v, w)
    pbx, pby, pbz, rbx, rby, rbz, vbx, vby, vbz = _end(s_b[s], s_pb[s], x, R, v, w)
    dx, dy, dz = pbx - pax, pby - pay, pbz - paz
    L = math.sqrt(dx * dx + dy * dy + dz * dz)
    ux = uy = uz = 0.0
    if L > 1e-12:
        ux, uy, uz = dx / L, dy / L, dz / L
    f = s_k[s] * (L - s_L0[s]) + s_c[s] * ((vbx - vax) * ux + (vby - vay) * uy + (vbz - vaz) * uz)
    return f * ux, f * uy, f * uz, rax, ray, raz, rbx, rby, rbz


@njit(cache=True)
def springs(s_a, s_b, s_pa, s_pb, s_k, s_c, s_L0, x, R, v, w, F, T):
    """Hooke springs and dashpots between anchor points (see
    forces.Springs): tension f = k (L - L0) + c (v_pb - v_pa) . u along
    u = (p_b - p_a) / L (0 when L <= 1e-12 m); body a gets +f u at p_a,
    body b -f u at p_b, with their torques r x F.  Forces on a are added
    first over all springs, then those on b: the b pass computes each
    spring's f u again from the unchanged x, R, v, w (the same bits as
    keeping it, and no array a call: tests/test_engine_steady_gyro.py::
    test_every_gyroscopic_setting_steps_without_allocating)."""
    k = s_a.shape[0]
    for s in range(k):
        fu0, fu1, fu2, rax, ray, raz, rbx, rby, rbz = _spring(s, s_a, s_b, s_pa, s_pb, s_k, s_c, s_L0, x, R, v, w)
        i = s_a[s]
        if i >= 0:
            F[i, 0] += fu0
            F[i, 1] += fu1
            F[i, 2] += fu2
            T[i, 0] += ray * fu2 - raz * fu1
            T[i, 1] += raz * fu0 - rax * fu2
            T[i, 2] += rax * fu1 - ray * fu0
    for s in range(k):
        i = s_b[s]
        if i < 0:
            continue
        fu0, fu1, fu2, rax, ray, raz, rbx, rby, rbz = _spring(s, s_a, s_b, s_pa, s_pb, s_k, s_c, s_L0, x, R, v, w)
        F[i, 0] -= fu0
        F[i, 1] -= fu1
        F[i, 2] -= fu2
        T[i, 0] += rby * -fu2 - rbz * -fu1
        T[i, 1] += rbz * -fu0 - rbx * -fu2
        T[i, 2] += rbx * -fu1 - rby * -fu0


@njit(cache=True)
def gyroscopic_torque(g_idx, g_I, R, w, T):
    """T -= w x (I_world w), I_world w = R (I (R^T w)), on the bodies
    ``g_idx``."""
    for j in range(g_idx.shape[0]):
        k = g_idx[j]
        b0 = R[k, 0, 0] * w[k, 0] + R[k, 1, 0] * w[k, 1] + R[k, 2, 0] * w[k, 2]
        b1 = R[k, 0, 1] * w[k, 0] + R[k, 1, 1] * w[k, 1] + R[k, 2, 1] * w[k, 2]
        b2 = R[k, 0, 2] * w[k, 0] + R[k, 1, 2] * w[k, 1] + R[k, 2, 2] * w[k, 2]
        b0 *= g_I[j, 0]
        b1 *= g_I[j, 1]
        b2 *= g_I[j, 2]
        lx = R[k, 0, 0] * b0 + R[k, 0, 1] * b1 + R[k, 0, 2] * b2
        ly = R[k, 1, 0] * b0 + R[k, 1, 1] * b1 + R[k, 1, 2] * b2
        lz = R[k, 2, 0] * b0 + R[k, 2, 1] * b1 + R[k, 2, 2] * b2
        T[k, 0] -= w[k, 1] * lz - w[k, 2] * ly
        T[k, 1] -= w[k, 2] * lx - w[k, 0] * lz
        T[k, 2] -= w[k, 0] * ly - w[k, 1] * lx


@njit(cache=True)
def apply_forces(fm, x, R, v, w, F, T):
    """The force kernels of the force model ``fm`` (:data:`ForceModel`) at
    (x, R, v, w), added into F, T (n, 3): the ONE list of them, in the
    force stages' order (engine.forces.FORCES: gravity, linear drag,
    quadratic drag, springs, gyroscopic torque; an absent effect's arrays
    are empty, its kernel a no-op).  A new force effect is its kernel here,
    its field of :data:`ForceModel` and its stage in engine/forces.py
    (tests/test_engine_force_table.py pins that every effect of the table
    gives the staged bits on every compiled path)."""
    gravity(fm.mg, F)
    linear_drag(fm.c_lin, v, F)
    quadratic_drag(fm.c_quad, v, F)
    springs(fm.s_a, fm.s_b, fm.s_pa, fm.s_pb, fm.s_k, fm.s_c, fm.s_L0, x, R, v, w, F, T)
    gyroscopic_torque(fm.g_idx, fm.g_I, R, w, T)


@njit(cache=True)
def evaluate(fm, x, q, v, w, R, F, T):
    """F, T (zeroed first) of the force model ``fm`` at the state (x, q, v,
    w); R (n, 3, 3) is filled from the normalised q when a force reads the
    pose (springs, gyroscopic torque)."""
    F[:, :] = 0.0
    T[:, :] = 0.0
    if fm.s_a.shape[0] or fm.g_idx.shape[0]:
        # (the normalised quaternion as scalars, no array: q2m's arithmetic)
        for k in range(q.shape[0]):
            s = math.sqrt(q[k, 0] ** 2 + q[k, 1] ** 2 + q[k, 2] ** 2 + q[k, 3] ** 2)
            _rot_row(R, k, q[k, 0] / s, q[k, 1] / s, q[k, 2] / s, q[k, 3] / s)
    apply_forces(fm, x, R, v, w, F, T)


@njit(cache=True)
def _accel(F, T, R, inv_m, inv_I, torque, a, al):
    """a = F / m; alpha = R (I^-1 (R^T T)) (0 without torques)."""
    for k in range(F.shape[0]):
        for c in range(3):
            a[k, c] = F[k, c] * inv_m[k]
        if not torque:
            al[k, 0] = al[k, 1] = al[k, 2] = 0.0
            continue
        t0 = (R[k, 0, 0] * T[k, 0] + R[k, 1, 0] * T[k, 1] + R[k, 2, 0] * T[k, 2]) * inv_I[k, 0]
        t1 = (R[k, 0, 1] * T[k, 0] + R[k, 1, 1] * T[k, 1] + R[k, 2, 1] * T[k, 2]) * inv_I[k, 1]
        t2 = (R[k, 0, 2] * T[k, 0] + R[k, 1, 2] * T[k, 1] + R[k, 2, 2] * T[k, 2]) * inv_I[k, 2]
        for c in range(3):
            al[k, c] = R[k, c, 0] * t0 + R[k, c, 1] * t1 + R[k, c, 2] * t2


@njit(cache=True)
def _stage(ig, x, q, v, w, R, Fs, Ts, T, a0, al0, a1, al1, T1):
    """Accelerations a1, al1 (n, 3) and torques T1 at an intermediate state
    (x, q, v, w): the start's (a0, al0, T) when the forces are
    ``ig.constant``, else the force model evaluated there (``ig`` an
    :data:`Integrator`)."""
    if ig.constant:
        a1[:, :] = a0
        al1[:, :] = al0
        T1[:, :] = T
    else:
        evaluate(ig.fm, x, q, v, w, R, Fs, Ts)
        _accel(Fs, Ts, R, ig.inv_m, ig.inv_I, ig.torque, a1, al1)
        T1[:, :] = Ts


@njit(cache=True)
def _q_step(q0, k, s, d0, d1, d2, d3, out):
    """out[k] = q0[k] + s d (d a quaternion derivative)."""
    out[k, 0] = q0[k, 0] + s * d0
    out[k, 1] = q0[k, 1] + s * d1
    out[k, 2] = q0[k, 2] + s * d2
    out[k, 3] = q0[k, 3] + s * d3


@njit(cache=True)
def _qd(w, q, k):
    """dq/dt = 1/2 (0, w[k]) (x) q[k]."""
    wx, wy, wz = w[k, 0], w[k, 1], w[k, 2]
    qw, qx, qy, qz = q[k, 0], q[k, 1], q[k, 2], q[k, 3]
    d0 = -0.5 * (wx * qx + wy * qy + wz * qz)
    d1 = 0.5 * (wx * qw + wy * qz - wz * qy)
    d2 = 0.5 * (-wx * qz + wy * qw + wz * qx)
    d3 = 0.5 * (wx * qy - wy * qx + wz * qw)
    return d0, d1, d2, d3


@njit(cache=True, inline="always")
def _euler_body(x0, q0, v0, w0, k, s, wd, qd, xd, vd, ad, x, q, v, w):
    """Body k's explicit step of length s (s) from (x0, q0, v0, w0) along
    slopes taken at another state: dq/dt at (wd, qd), dx/dt = xd, dv/dt =
    vd, dw/dt = ad; written into x, q, v, w (quaternions (n, 4), the rest
    (n, 3)): the midpoint method's intermediate state and its final step."""
    d0, d1, d2, d3 = _qd(wd, qd, k)
    _q_step(q0, k, s, d0, d1, d2, d3, q)
    for c in range(3):
        x[k, c] = x0[k, c] + s * xd[k, c]
        v[k, c] = v0[k, c] + s * vd[k, c]
        w[k, c] = w0[k, c] + s * ad[k, c]


@njit(cache=True)
def rotate(q, k, px, py, pz, out):
    """out[k] = exp(phi) (x) q[k], renormalised."""
    ang = math.sqrt(px * px + py * py + pz * pz)
    half = 0.5 * ang
    if ang < 1e-8:
        s = 0.5 - ang * ang / 48.0
    else:
        s = math.sin(half) / ang
    aw, ax, ay, az = math.cos(half), px * s, py * s, pz * s
    bw, bx, by, bz = q[k, 0], q[k, 1], q[k, 2], q[k, 3]
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    nrm = math.sqrt(w * w + x * x + y * y + z * z)
    out[k, 0], out[k, 1], out[k, 2], out[k, 3] = w / nrm, x / nrm, y / nrm, z / nrm


def free_flight(ig, start, end, h, work, work_q):
    """The free flight over h (see engine/integrate.py) by the law ``ig``
    (:data:`Integrator`): from ``start`` (:data:`FlightStart`: x0, q0, v0,
    w0 with the forces F, T (n, 3) already evaluated there, R0 their
    rotations), writes into ``end`` (:data:`FlightEnd`) the end state (x1,
    q1, v1, w1), the step's mean torque ``T_mean`` (the method's weights),
    the mean velocities u_lin = (x1 - x0) / h and u_ang = (1 - lever)
    w_start + lever w1.  Forces are re-evaluated at the method's
    intermediate states unless ``ig.constant`` (then they equal the
    start's).  ``work`` (:data:`WORK_SLABS`, n, 3), ``work_q`` (2, n, 4)
    scratch (nothing is allocated).  Called from compiled code only: it
    compiles for the one
    method ``ig.method`` (a :class:`Method`, its code in its numba type),
    the others' branches pruned before typing (:func:`_free_flight_for`)."""
    raise TypeError("engine.flight.free_flight is called from compiled code only (engine.flight.fly)")


@overload(free_flight)
def _free_flight_typed(ig, start, end, h, work, work_q):
    return _free_flight_for(ig.types[ig.fields.index("method")].code)


@functools.cache
def _free_flight_for(method: int):
    """:func:`free_flight` for the METHOD code ``method``: a constant of the
    closure, so numba prunes the other methods' branches before typing
    (one implementation per code, the same arithmetic as every other)."""

    def free_flight_method(ig, start, end, h, work, work_q):
        has_forces, torque, inv_m, inv_I, lever = ig.has_forces, ig.torque, ig.inv_m, ig.inv_I, ig.lever
        x0, q0, v0, w0, w_start, F, T, R0 = start.x, start.q, start.v, start.w, start.w_start, start.F, start.T, start.R
        x1, q1, v1, w1, T_mean, u_lin, u_ang = end.x, end.q, end.v, end.w, end.T_mean, end.u_lin, end.u_ang
        n = x0.shape[0]
        a0, al0, a1, al1 = work[0], work[1], work[2], work[3]
        xs, vs, ws = work[4], work[5], work[6]
        Fs, Ts = work[7], work[8]
        T1, T2, T3 = work[9], work[10], work[11]
        Sw, Sx, Sv = work[12], work[13], work[14]
        Rs = work[15:18].reshape((n, 3, 3))
        qs, Sq = work_q[0], work_q[1]
        if not has_forces:
            for k in range(n):
                for c in range(3):
                    x1[k, c] = v0[k, c] * h + x0[k, c]
                    v1[k, c] = v0[k, c]
                    w1[k, c] = w0[k, c]
                    T_mean[k, c] = 0.0
                rotate(q0, k, h * w0[k, 0], h * w0[k, 1], h * w0[k, 2], q1)
        else:
            _accel(F, T, R0, inv_m, inv_I, torque, a0, al0)
            hh = 0.5 * h
            if method == 0 or method == 1:  # explicit / semi-implicit Euler
                for k in range(n):
                    d0, d1, d2, d3 = _qd(w0, q0, k)
                    for c in range(3):
                        v1[k, c] = v0[k, c] + h * a0[k, c]
                        w1[k, c] = w0[k, c] + h * al0[k, c]
                        T_mean[k, c] = T[k, c]
                    if method == 0:
                        for c in range(3):
                            x1[k, c] = x0[k, c] + h * v0[k, c]
                        _q_step(q0, k, h, d0, d1, d2, d3, q1)
                    else:
                        for c in range(3):
                            x1[k, c] = x0[k, c] + h * v1[k, c]
                        rotate(q0, k, h * w1[k, 0], h * w1[k, 1], h * w1[k, 2], q1)
            elif method == 2 or method == 3:  # midpoint / Heun: one intermediate state
                s = hh if method == 2 else h
                for k in range(n):
                    _euler_body(x0, q0, v0, w0, k, s, w0, q0, v0, a0, al0, xs, qs, vs, ws)
                _stage(ig, xs, qs, vs, ws, Rs, Fs, Ts, T, a0, al0, a1, al1, T1)
                for k in range(n):
                    if method == 2:
                        _euler_body(x0, q0, v0, w0, k, h, ws, qs, vs, a1, al1, x1, q1, v1, w1)
                        for c in range(3):
                            T_mean[k, c] = T1[k, c]
                    else:
                        e0, e1, e2, e3 = _qd(w0, q0, k)
                        d0, d1, d2, d3 = _qd(ws, qs, k)
                        q1[k, 0] = q0[k, 0] + hh * (e0 + d0)
                        q1[k, 1] = q0[k, 1] + hh * (e1 + d1)
                        q1[k, 2] = q0[k, 2] + hh * (e2 + d2)
                        q1[k, 3] = q0[k, 3] + hh * (e3 + d3)
                        for c in range(3):
                            x1[k, c] = x0[k, c] + hh * (v0[k, c] + vs[k, c])
                            v1[k, c] = v0[k, c] + hh * (a0[k, c] + a1[k, c])
                            w1[k, c] = w0[k, c] + hh * (al0[k, c] + al1[k, c])
                            T_mean[k, c] = 0.5 * (T[k, c] + T1[k, c])
            elif method == 4:  # rk4
                # slopes K_j = [v, dq/dt, a, alpha] of the stages, summed as
                # K1 + 2 K2 + 2 K3 + K4 in that order
                ka, kal = a0, al0
                for k in range(n):  # K1
                    d0, d1, d2, d3 = _qd(w0, q0, k)
                    Sq[k, 0], Sq[k, 1], Sq[k, 2], Sq[k, 3] = d0, d1, d2, d3
                    for c in range(3):
                        Sx[k, c] = v0[k, c]
                        Sv[k, c] = a0[k, c]
                        Sw[k, c] = al0[k, c]
                for stage in range(3):
                    s = hh if stage < 2 else h
                    Tx = T1 if stage == 0 else (T2 if stage == 1 else T3)
                    # Y = Y0 + s K (K the last slope)
                    for k in range(n):
                        if stage == 0:
                            d0, d1, d2, d3 = _qd(w0, q0, k)
                            kv = v0
                        else:
                            d0, d1, d2, d3 = _qd(ws, qs, k)
                            kv = vs
                        kx0, kx1, kx2 = kv[k, 0], kv[k, 1], kv[k, 2]
                        _q_step(q0, k, s, d0, d1, d2, d3, qs)
                        xs[k, 0] = x0[k, 0] + s * kx0
                        xs[k, 1] = x0[k, 1] + s * kx1
                        xs[k, 2] = x0[k, 2] + s * kx2
                        for c in range(3):
                            vs[k, c] = v0[k, c] + s * ka[k, c]
                            ws[k, c] = w0[k, c] + s * kal[k, c]
                    _stage(ig, xs, qs, vs, ws, Rs, Fs, Ts, T, a0, al0, a1, al1, Tx)
                    wgt = 2.0 if stage < 2 else 1.0
                    for k in range(n):
                        d0, d1, d2, d3 = _qd(ws, qs, k)
                        Sq[k, 0] += wgt * d0
                        Sq[k, 1] += wgt * d1
                        Sq[k, 2] += wgt * d2
                        Sq[k, 3] += wgt * d3
                        for c in range(3):
                            Sx[k, c] += wgt * vs[k, c]
                            Sv[k, c] += wgt * a1[k, c]
                            Sw[k, c] += wgt * al1[k, c]
                    # the next stage reads this stage's slopes before its own
                    # _stage overwrites a1, al1: no copy needed
                    ka, kal = a1, al1
                h6 = h / 6.0
                for k in range(n):
                    for c in range(3):
                        x1[k, c] = x0[k, c] + h6 * Sx[k, c]
                        v1[k, c] = v0[k, c] + h6 * Sv[k, c]
                        w1[k, c] = w0[k, c] + h6 * Sw[k, c]
                        T_mean[k, c] = (T[k, c] + 2 * T1[k, c] + 2 * T2[k, c] + T3[k, c]) / 6.0
                    for c in range(4):
                        q1[k, c] = q0[k, c] + h6 * Sq[k, c]
            else:  # velocity Verlet
                hh2 = hh * h
                for k in range(n):
                    for c in range(3):
                        x1[k, c] = x0[k, c] + h * v0[k, c] + hh2 * a0[k, c]
                        vs[k, c] = v0[k, c] + h * a0[k, c]
                        ws[k, c] = w0[k, c] + h * al0[k, c]
                    rotate(q0, k, h * (w0[k, 0] + hh * al0[k, 0]), h * (w0[k, 1] + hh * al0[k, 1]),
                           h * (w0[k, 2] + hh * al0[k, 2]), q1)
                _stage(ig, x1, q1, vs, ws, Rs, Fs, Ts, T, a0, al0, a1, al1, T1)
                for k in range(n):
                    for c in range(3):
                        v1[k, c] = v0[k, c] + hh * (a0[k, c] + a1[k, c])
                        w1[k, c] = w0[k, c] + hh * (al0[k, c] + al1[k, c])
                        T_mean[k, c] = 0.5 * (T[k, c] + T1[k, c])
            for k in range(n):  # renormalise
                s = math.sqrt(q1[k, 0] ** 2 + q1[k, 1] ** 2 + q1[k, 2] ** 2 + q1[k, 3] ** 2)
                for c in range(4):
                    q1[k, c] /= s
        for k in range(n):
            for c in range(3):
                u_lin[k, c] = (x1[k, c] - x0[k, c]) / h
                u_ang[k, c] = (1.0 - lever) * w_start[k, c] + lever * w1[k, c]

    return free_flight_method


@njit(cache=True)
def start_pose(q, inv_I, R0, Iinv0):
    """Rotations R0 (n, 3, 3) of q (n, 4) and world inverse inertias
    Iinv0[:n] = R diag(1/I) R^T (``inv_I`` (n, 3)); the world's row n zero."""
    n = q.shape[0]
    q2m(q, R0)
    for k in range(n):
        for i in range(3):
            for j in range(3):
                s = 0.0
                for c in range(3):
                    s += R0[k, i, c] * inv_I[k, c] * R0[k, j, c]
                Iinv0[k, i, j] = s
    Iinv0[n, :, :] = 0.0


@njit(cache=True)
def integrate_positions(x1, q1, v1, w1, v_free, w_free, vp, wp, h, lever):
    """The contact solve's position effect (see integrate.IntegratePositions):
    x1 += lever h dv + h vp; q1 <- exp(lever h dw + h wp) (x) q1 where that
    rotation is not zero; dv = v1 - v_free, dw = w1 - w_free (n, 3)."""
    ch = lever * h
    for k in range(x1.shape[0]):
        for c in range(3):
            x1[k, c] += ch * (v1[k, c] - v_free[k, c]) + h * vp[k, c]
        px = ch * (w1[k, 0] - w_free[k, 0]) + h * wp[k, 0]
        py = ch * (w1[k, 1] - w_free[k, 1]) + h * wp[k, 1]
        pz = ch * (w1[k, 2] - w_free[k, 2]) + h * wp[k, 2]
        if px * px + py * py + pz * pz > 0.0:
            rotate(q1, k, px, py, pz, q1)


@njit(cache=True)
def fly(b, f, h):
    """The free-flight stage (engine.integrate.IntegrateVelocities) over h
    s: :func:`free_flight` from the (mini-)step's start ``b`` (an
    engine.state.StepArrays: the state's x, q, w, the forces F, T, the
    rotations R0) with the working angular velocities as they are (after
    the implicit gyroscopic update) into the candidate end state (x1, q1,
    the working V, W), then the free velocities v_free, w_free set to the
    end velocities.  ``f`` the stage's :data:`Flight`.  The one call of the
    staged stage (:func:`fly_packed`) and of the fused steps
    (engine/fused/part.py): the same bits by construction."""
    f.w0[:, :] = f.W
    free_flight(f.ig, FlightStart(x=b.x, q=b.q, v=b.v, w=f.w0, w_start=b.w, F=b.F, T=b.T, R=b.R0),
                FlightEnd(x=b.x1, q=b.q1, v=f.V, w=f.W, T_mean=f.T_mean, u_lin=f.u_lin, u_ang=f.u_ang), h, f.work,
                f.work_q)
    f.v_free[:, :] = f.V
    f.w_free[:, :] = f.W


@njit(cache=True)
def fly_packed(kb, kf, h):
    """:func:`fly` from Python (the staged stage): ``kb`` the context's
    begin/commit Pack (engine.state.Context.kept), ``kf`` the stage's Pack
    of its :data:`Flight` (one pointer each to unbox)."""
    fly(kb.items, kf.items, h)


@njit(cache=True)
def max_turn_sq(w, q, boxes, axisym):
    """The largest squared angular speed (rad/s)^2 that turns a body's
    occupied space: |w|^2 over ``boxes`` (k,), and over the axisymmetric
    bodies ``axisym`` (j,) the part of w perpendicular to the body z axis
    (R(q) e_z, q (n, 4) wxyz).  Summed as the numpy expressions it replaces
    (pipeline._parts): einsum's (p0 + p2) + p1 for three products,
    mathutil.quat_to_matrix's entries.  0.0 for no bodies."""
    w2 = 0.0
    for s in range(boxes.shape[0]):
        k = boxes[s]
        d = (w[k, 0] * w[k, 0] + w[k, 2] * w[k, 2]) + w[k, 1] * w[k, 1]
        if s == 0 or d > w2 or d != d:
            w2 = d
    wa = 0.0
    for s in range(axisym.shape[0]):
        k = axisym[s]
        qw, qx, qy, qz = q[k, 0], q[k, 1], q[k, 2], q[k, 3]
        a0 = 2 * (qx * qz + qw * qy)
        a1 = 2 * (qy * qz + -1.0 * (qw * qx))
        a2 = 1 - 2 * (qx * qx + 1.0 * (qy * qy))
        wn = (w[k, 0] * a0 + w[k, 2] * a2) + w[k, 1] * a1
        p0 = w[k, 0] - wn * a0
        p1 = w[k, 1] - wn * a1
        p2 = w[k, 2] - wn * a2
        d = (p0 * p0 + p2 * p2) + p1 * p1
        if s == 0 or d > wa or d != d:
            wa = d
    if axisym.shape[0] and wa > w2:  # max(w2, wa) as Python's: the first unless the second is larger
        w2 = wa
    return w2


@njit(cache=True)
def end_displacement(x0, q0, x1, q1, bound_radius, out):
    """``out`` (n,) m: how far any surface point of each body lies from
    where it was, end pose (x1, q1) against start pose (x0, q0):
    |x1 - x0| + 2 sin(theta/2) r (see engine.ccd.end_displacement); summed
    as its numpy form (einsum's (p0 + p2) + (p1 + p3) for four products,
    (p0 + p2) + p1 for three)."""
    for k in range(out.shape[0]):
        c = abs((q0[k, 0] * q1[k, 0] + q0[k, 2] * q1[k, 2]) + (q0[k, 1] * q1[k, 1] + q0[k, 3] * q1[k, 3]))
        if c > 1.0:  # np.minimum / np.maximum: NaN stays NaN
            c = 1.0
        t = 1.0 - c * c
        if t < 0.0:
            t = 0.0
        s = math.sqrt(t)
        d0 = x1[k, 0] - x0[k, 0]
        d1 = x1[k, 1] - x0[k, 1]
        d2 = x1[k, 2] - x0[k, 2]
        out[k] = math.sqrt((d0 * d0 + d2 * d2) + d1 * d1) + 2.0 * s * bound_radius[k]


@njit(cache=True)
def begin_step(x, q, v, w, inv_I, x1, q1, V, W, F, T, vp, wp, R0, Iinv0):
    """The start of a (mini-)step (state.Context.begin): the candidate end
    state x1, q1 (n, 3|4) and the working velocities V, W (n+1, 3) set to
    the state's, their world row n, the force accumulators F, T (n, 3)
    and the pseudo velocities vp, wp (n+1, 3) zeroed, and the start pose
    (:func:`start_pose`)."""
    n = x.shape[0]
    for k in range(n):
        for c in range(3):
            x1[k, c] = x[k, c]
            V[k, c] = v[k, c]
            W[k, c] = w[k, c]
            F[k, c] = 0.0
            T[k, c] = 0.0
        for c in range(4):
            q1[k, c] = q[k, c]
    for c in range(3):
        V[n, c] = 0.0
        W[n, c] = 0.0
    vp[:, :] = 0.0
    wp[:, :] = 0.0
    start_pose(q, inv_I, R0, Iinv0)


@njit(cache=True, inline="always")
def _moved_static_pairs(sw, lim, has_fast, fast, body, other, cbody, cother):
    """Copy the (body, static) pairs whose body moved by more than ``lim``
    (and, with ``has_fast``, is fast) in order to the front of ``cbody``/
    ``cother``; returns their count."""
    m = 0
    for k in range(body.shape[0]):
        if sw[body[k]] > lim and (not has_fast or fast[body[k]]):
            cbody[m] = body[k]
            cother[m] = other[k]
            m += 1
    return m


@njit(cache=True)
def end_pose_pairs(x0, q0, x1, q1, bound_radius, lim, has_fast, fast, pairs, out):
    """The CCD stage's end-pose check in one call: ``out.sw`` (n,) m the
    bodies' :func:`end_displacement` (start pose x0, q0 against end pose
    x1, q1); the pairs of ``pairs`` (an engine.geometry.Pairs) whose
    surfaces moved apart or together by more than ``lim`` (m) -- body pairs
    ``pi``/``pj`` (the sum of both bodies' values), body-plane ``bp``/``pk``
    and body-static-box ``bs``/``sk`` (the body's value), with ``has_fast``
    only pairs with a body where ``fast`` (n,) holds -- copied in order
    into the front of ``out.ci``/``cj``, ``cbp``/``cpk``, ``cbs``/``csk``
    (an engine.geometry.EndPose; int64, at least as long as their inputs);
    and, when any pair moved, ``out.R1`` (n, 3, 3) the rotations of q1
    (:func:`q2m`).  Returns the counts (body pairs, planes, static boxes)."""
    sw = out.sw
    end_displacement(x0, q0, x1, q1, bound_radius, sw)
    pi, pj, ci, cj = pairs.pi, pairs.pj, out.ci, out.cj
    nb = 0
    for k in range(pi.shape[0]):
        i, j = pi[k], pj[k]
        if sw[i] + sw[j] > lim and (not has_fast or fast[i] or fast[j]):
            ci[nb] = i
            cj[nb] = j
            nb += 1
    npl = _moved_static_pairs(sw, lim, has_fast, fast, pairs.bp, pairs.pk, out.cbp, out.cpk)
    ns = _moved_static_pairs(sw, lim, has_fast, fast, pairs.bs, pairs.sk, out.cbs, out.csk)
    if nb + npl + ns:
        q2m(q1, out.R1)
    return nb, npl, ns
