"""Compiled rotation kernels of the gyroscopic stages (engine/integrate.py):
Catto's implicit gyroscopic step (:func:`implicit_gyroscopic`) and the
energy-conserving free rotation (:func:`energy_rotation_into`: the
implicit-midpoint Lie-Poisson step composed by Yoshida's triple jump).

Loops over the gyroscopic bodies with a fixed order, no BLAS (the bits do
not depend on the BLAS kernel: tests/test_engine_blas_free.py).  Shapes as
in engine/flight.py: rotations ``R`` (n, 3, 3), orientations ``q`` (n, 4)
wxyz, angular velocities ``w`` (n(+1), 3) world frame, principal moments
``I`` (g, 3) over the bodies ``idx`` (g,).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
from numba import njit

from physbench.engine.contact.linalg import solve_batch
from physbench.engine.flight import q2m


@njit(cache=True)
def implicit_gyroscopic(idx, I, R0, w, h, Jm, fw):
    """Catto's implicit gyroscopic update of w (n+1, 3) in place on the
    bodies ``idx`` (principal moments ``I`` (g, 3)): one Newton iteration on
    I (w2 - w1) + h w2 x I w2 = 0 in the body frame,
    J = I + h ([w1]x I - [I w1]x), w2 = w1 - J^-1 (h w1 x I w1).  Work
    arrays (overwritten, kept by the caller: nothing is allocated,
    tests/test_engine_steady_gyro.py::test_every_gyroscopic_setting_steps_without_allocating):
    ``Jm`` (g, 3, 3) the Newton matrices, ``fw`` (2, g, 3) the right-hand
    sides (then the corrections) and the body-frame velocities."""
    g = idx.shape[0]
    f = fw[0]
    wb = fw[1]
    for j in range(g):
        k = idx[j]
        for i in range(3):
            wb[j, i] = R0[k, 0, i] * w[k, 0] + R0[k, 1, i] * w[k, 1] + R0[k, 2, i] * w[k, 2]
        b0, b1, b2 = wb[j, 0], wb[j, 1], wb[j, 2]
        l0, l1, l2 = I[j, 0] * b0, I[j, 1] * b1, I[j, 2] * b2
        f[j, 0] = h * (b1 * l2 - b2 * l1)
        f[j, 1] = h * (b2 * l0 - b0 * l2)
        f[j, 2] = h * (b0 * l1 - b1 * l0)
        # [wb]x I - [I wb]x
        S = ((0.0, -b2, b1), (b2, 0.0, -b0), (-b1, b0, 0.0))
        L = ((0.0, -l2, l1), (l2, 0.0, -l0), (-l1, l0, 0.0))
        for r in range(3):
            for c in range(3):
                Jm[j, r, c] = (I[j, r] if r == c else 0.0) + h * (S[r][c] * I[j, c] - L[r][c])
    solve_batch(Jm, f)  # f becomes the correction d = J^-1 f
    d = f
    for j in range(g):
        k = idx[j]
        b0, b1, b2 = wb[j, 0] - d[j, 0], wb[j, 1] - d[j, 1], wb[j, 2] - d[j, 2]
        for i in range(3):
            w[k, i] = R0[k, i, 0] * b0 + R0[k, i, 1] * b1 + R0[k, i, 2] * b2


def implicit_work(g: int) -> tuple:
    """Kept work arrays of :func:`implicit_gyroscopic` for g bodies: (Jm
    (g, 3, 3), fw (2, g, 3))."""
    return np.zeros((g, 3, 3)), np.zeros((2, g, 3))


def energy_work(g: int) -> tuple:
    """Kept work arrays of :func:`energy_rotation_into` for g bodies: (wk
    (4, g, 3), q (g, 4), R1 (g, 3, 3))."""
    return np.zeros((4, g, 3)), np.zeros((g, 4)), np.zeros((g, 3, 3))


#: Yoshida's fourth-order triple jump for a symmetric second-order method
_CBRT2 = 2.0 ** (1.0 / 3.0)
YOSHIDA = (1.0 / (2.0 - _CBRT2), -_CBRT2 / (2.0 - _CBRT2), 1.0 / (2.0 - _CBRT2))
YOSHIDA_MAX = max(abs(g) for g in YOSHIDA)

#: the gyroscopic stage codes: none, implicit (Catto), energy-conserving
NO_GYRO, IMPLICIT, ENERGY = 0, 1, 2

#: a gyroscopic stage's arrays (engine/integrate.py builds them, the staged
#: stage and the fused steps read them): its ``code``, bodies ``idx`` (g,)
#: int64, principal moments ``I`` (g, 3) kg m^2; for the energy-conserving
#: rotation their inverses ``inv_I``, Euler coefficients ``E`` (g, 3),
#: the composition ``yoshida`` and its largest coefficient ``ymax``, the
#: kept work arrays ``wk``, ``wq``, ``wR`` (:func:`energy_work`); for the
#: implicit update its ``J``, ``f`` (:func:`implicit_work`); what a stage
#: does not use is empty
Gyro = namedtuple("Gyro", ("code", "idx", "I", "inv_I", "E", "yoshida", "ymax", "wk", "wq", "wR", "J", "f"))


def no_gyro() -> Gyro:
    """The :data:`Gyro` of a step without a gyroscopic stage (every array
    empty)."""
    z3, zi = np.zeros((0, 3)), np.zeros(0, np.int64)
    return Gyro(NO_GYRO, zi, z3, z3, z3, YOSHIDA, float(YOSHIDA_MAX), *energy_work(0), *implicit_work(0))


@njit(cache=True)
def midpoint_rotation(Lb, q, I, E, h, tol, max_iter):
    """One implicit-midpoint Lie-Poisson step of the torque-free rigid body
    for all rows of ``Lb`` (g, 3) body angular momentum and ``q`` (g, 4), in
    place (see integrate.free_rotation_midpoint): Lm = L0 + h/2 E * (Lm1
    Lm2, Lm2 Lm0, Lm0 Lm1) by fixed-point iteration from the explicit
    predictor, until the largest change is below tol max|L0|; then
    L1 = 2 Lm - L0, q1 = q0 (x) normalize(1, h Lm / (2 I))."""
    g = Lb.shape[0]
    _midpoint(Lb, q, I, E, h, tol, max_iter, np.empty((g, 3)), np.empty((g, 3)), np.empty((g, 3)))


@njit(cache=True)
def _midpoint(Lb, q, I, E, h, tol, max_iter, Lm, Ln, hE):
    """:func:`midpoint_rotation` on the work arrays ``Lm``, ``Ln``, ``hE``
    (g, 3) each (overwritten)."""
    g = Lb.shape[0]
    scale = 0.0
    for j in range(g):
        for c in range(3):
            hE[j, c] = 0.5 * h * E[j, c]
            scale = max(scale, abs(Lb[j, c]))
        Lm[j, 0] = Lb[j, 0] + hE[j, 0] * Lb[j, 1] * Lb[j, 2]
        Lm[j, 1] = Lb[j, 1] + hE[j, 1] * Lb[j, 2] * Lb[j, 0]
        Lm[j, 2] = Lb[j, 2] + hE[j, 2] * Lb[j, 0] * Lb[j, 1]
    scale += 1e-300
    for _ in range(max_iter):
        diff = 0.0
        for j in range(g):
            Ln[j, 0] = Lb[j, 0] + hE[j, 0] * Lm[j, 1] * Lm[j, 2]
            Ln[j, 1] = Lb[j, 1] + hE[j, 1] * Lm[j, 2] * Lm[j, 0]
            Ln[j, 2] = Lb[j, 2] + hE[j, 2] * Lm[j, 0] * Lm[j, 1]
            for c in range(3):
                diff = max(diff, abs(Ln[j, c] - Lm[j, c]))
        Lm[:, :] = Ln
        if diff <= tol * scale:
            break
    for j in range(g):
        c1 = (0.5 * h) * (Lm[j, 0] / I[j, 0])
        c2 = (0.5 * h) * (Lm[j, 1] / I[j, 1])
        c3 = (0.5 * h) * (Lm[j, 2] / I[j, 2])
        s = math.sqrt(1.0 + c1 * c1 + c2 * c2 + c3 * c3)
        bw, bx, by, bz = 1.0 / s, c1 / s, c2 / s, c3 / s
        aw, ax, ay, az = q[j, 0], q[j, 1], q[j, 2], q[j, 3]
        q[j, 0] = aw * bw - ax * bx - ay * by - az * bz
        q[j, 1] = aw * bx + ax * bw + ay * bz - az * by
        q[j, 2] = aw * by - ax * bz + ay * bw + az * bx
        q[j, 3] = aw * bz + ax * by - ay * bx + az * bw
        for c in range(3):
            Lb[j, c] = 2.0 * Lm[j, c] - Lb[j, c]


@njit(cache=True)
def energy_rotation_into(gy, R0, T_mean, w0, q0, h, lever, q1, w, w_free, u_ang):
    """The energy-conserving rotation stage (integrate.EnergyConservingRotation)
    on the bodies ``gy.idx`` of the :data:`Gyro` ``gy`` (principal moments
    ``I``, ``inv_I``, Euler coefficients ``E`` (g, 3)): half a kick of the mean torque on the world
    angular momentum, the composed midpoint free rotation in m equal parts
    with |w| h max|yoshida| / m <= 0.5, the other half kick; writes q1,
    w, w_free, u_ang on those bodies.  On ``gy``'s kept work arrays
    (:func:`energy_work`) ``wk`` (4, g, 3) (the body angular momenta and the
    midpoint's three), ``wq`` (g, 4) and ``wR`` (g, 3, 3), overwritten: no
    allocation (every caller: the stage, the flight step, the fused steady
    step)."""
    idx, I, inv_I, E, yoshida, ymax = gy.idx, gy.I, gy.inv_I, gy.E, gy.yoshida, gy.ymax
    wk, q, R1 = gy.wk, gy.wq, gy.wR
    g = idx.shape[0]
    Lb = wk[0]
    wmax2 = 0.0
    for j in range(g):
        k = idx[j]
        wb0 = R0[k, 0, 0] * w0[k, 0] + R0[k, 1, 0] * w0[k, 1] + R0[k, 2, 0] * w0[k, 2]
        wb1 = R0[k, 0, 1] * w0[k, 0] + R0[k, 1, 1] * w0[k, 1] + R0[k, 2, 1] * w0[k, 2]
        wb2 = R0[k, 0, 2] * w0[k, 0] + R0[k, 1, 2] * w0[k, 1] + R0[k, 2, 2] * w0[k, 2]
        i0, i1, i2 = I[j, 0] * wb0, I[j, 1] * wb1, I[j, 2] * wb2
        Lw0 = (R0[k, 0, 0] * i0 + R0[k, 0, 1] * i1 + R0[k, 0, 2] * i2) + 0.5 * h * T_mean[k, 0]
        Lw1 = (R0[k, 1, 0] * i0 + R0[k, 1, 1] * i1 + R0[k, 1, 2] * i2) + 0.5 * h * T_mean[k, 1]
        Lw2 = (R0[k, 2, 0] * i0 + R0[k, 2, 1] * i1 + R0[k, 2, 2] * i2) + 0.5 * h * T_mean[k, 2]
        s = 0.0
        for c in range(3):
            Lb[j, c] = R0[k, 0, c] * Lw0 + R0[k, 1, c] * Lw1 + R0[k, 2, c] * Lw2
            v = Lb[j, c] * inv_I[j, c]
            s += v * v
        wmax2 = max(wmax2, s)
        for c in range(4):
            q[j, c] = q0[k, c]
    x = math.sqrt(wmax2) * h * ymax / 0.5
    m = 1
    if x > 1.0 and math.isfinite(x):
        m = int(math.ceil(x))
    hs = h / m
    for _ in range(m):
        for gy in yoshida:
            _midpoint(Lb, q, I, E, gy * hs, 1e-15, 100, wk[1], wk[2], wk[3])
    for j in range(g):
        s = math.sqrt(q[j, 0] ** 2 + q[j, 1] ** 2 + q[j, 2] ** 2 + q[j, 3] ** 2)
        for c in range(4):
            q[j, c] /= s
    q2m(q, R1)
    for j in range(g):
        k = idx[j]
        L0, L1, L2 = Lb[j, 0], Lb[j, 1], Lb[j, 2]
        Lw0 = (R1[j, 0, 0] * L0 + R1[j, 0, 1] * L1 + R1[j, 0, 2] * L2) + 0.5 * h * T_mean[k, 0]
        Lw1 = (R1[j, 1, 0] * L0 + R1[j, 1, 1] * L1 + R1[j, 1, 2] * L2) + 0.5 * h * T_mean[k, 1]
        Lw2 = (R1[j, 2, 0] * L0 + R1[j, 2, 1] * L1 + R1[j, 2, 2] * L2) + 0.5 * h * T_mean[k, 2]
        b0 = (R1[j, 0, 0] * Lw0 + R1[j, 1, 0] * Lw1 + R1[j, 2, 0] * Lw2) * inv_I[j, 0]
        b1 = (R1[j, 0, 1] * Lw0 + R1[j, 1, 1] * Lw1 + R1[j, 2, 1] * Lw2) * inv_I[j, 1]
        b2 = (R1[j, 0, 2] * Lw0 + R1[j, 1, 2] * Lw1 + R1[j, 2, 2] * Lw2) * inv_I[j, 2]
        for c in range(3):
            w1 = R1[j, c, 0] * b0 + R1[j, c, 1] * b1 + R1[j, c, 2] * b2
            w[k, c] = w1
            w_free[k, c] = w1
            u_ang[k, c] = (1.0 - lever) * w0[k, c] + lever * w1
        for c in range(4):
            q1[k, c] = q[j, c]


@njit(cache=True)
def energy_rotation_packed(kg, R0, T_mean, w0, q0, h, lever, q1, w, w_free, u_ang):
    """:func:`energy_rotation_into` from Python (the staged stage): ``kg``
    a Pack of the stage's :data:`Gyro` (one pointer to unbox)."""
    energy_rotation_into(kg.items, R0, T_mean, w0, q0, h, lever, q1, w, w_free, u_ang)
