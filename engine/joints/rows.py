"""Joint constraint rows: residual C(q), Jacobian J(q) and the velocity
product (dJ/dt) u, evaluated at a state by one compiled call.

Maximal coordinates: every body keeps its 6 degrees of freedom (x, q; v, w
world frame about the centre of mass) and each joint adds scalar rows
C_r(x, q) = 0 between its ``body`` (side a) and ``other`` (side b; -1, the
world: at rest, its frame the world's).  Three row types:

* ``POINT`` (world axis e_k): C = e_k . (p_a - p_b), p_s = x_s + R_s r_s
  the anchor on side s.  J_a = [e_k, r_a x e_k], J_b = [-e_k, -(r_b x e_k)];
  bias = e_k . (w_a x (w_a x r_a) - w_b x (w_b x r_b)).
* ``DOT`` (s on a, t on b, both body-fixed): C = s . t (they start
  perpendicular).  J_a = [0, s x t] = -J_b; bias = (w_a x (w_a x s)) . t +
  2 (w_a x s) . (w_b x t) + s . (w_b x (w_b x t)).
* ``SLIDE`` (t on b, perpendicular to a slide axis): C = t . (p_a - p_b).
  J_a = [t, r_a x t], J_b = [-t, t x (p_a - x_b)]; bias = (w_b x (w_b x t))
  . d + 2 (w_b x t) . d' + t . (w_a x (w_a x r_a) - w_b x (w_b x r_b)).

The bias is d2C/dt2 at zero accelerations, so that J u' + bias = 0 is the
acceleration-level constraint (engine/joints/solve.py).

Per joint kind (engine/joints/table.py builds the rows): spherical 3
POINT; revolute 3 POINT + 2 DOT (the body's hinge axis against two
perpendiculars of the other's); fixed 3 POINT + 3 DOT (the two frames'
axes pairwise); prismatic 2 SLIDE + 3 DOT.  J's columns per row: [0:3]
linear a, [3:6] angular a, [6:9] linear b, [9:12] angular b.
Tests: tests/test_engine_joints.py.
"""

from __future__ import annotations

import math

from numba import njit

from physbench.engine.flight import _rot_row, evaluate

POINT, DOT, SLIDE = 0, 1, 2


@njit(cache=True)
def frames(q, inv_I, R, Iinv):
    """R (n, 3, 3) of the normalised quaternions q (n, 4) and the world
    inverse inertias Iinv = R diag(inv_I) R^T (n, 3, 3) (kg^-1 m^-2)."""
    for k in range(q.shape[0]):
        s = math.sqrt(q[k, 0] ** 2 + q[k, 1] ** 2 + q[k, 2] ** 2 + q[k, 3] ** 2)
        _rot_row(R, k, q[k, 0] / s, q[k, 1] / s, q[k, 2] / s, q[k, 3] / s)
        for i in range(3):
            for j in range(3):
                Iinv[k, i, j] = (R[k, i, 0] * inv_I[k, 0] * R[k, j, 0] + R[k, i, 1] * inv_I[k, 1] * R[k, j, 1]
                                 + R[k, i, 2] * inv_I[k, 2] * R[k, j, 2])


@njit(cache=True)
def free_accelerations(fm, has_forces, inv_m, inv_I, x, q, v, w, wk, a, al):
    """The frames (wk's R, Iinv), the force model's F, T (wk) at (x, q, v,
    w) and the unconstrained accelerations a = F / m, al = I^-1 T (n, 3)
    (m s^-2, rad s^-2): the set-up both joint solvers share (step.py's
    exact solve, sequential.py's impulses)."""
    R, Iinv, F, T = wk.R, wk.Iinv, wk.F, wk.T
    frames(q, inv_I, R, Iinv)
    if has_forces:
        evaluate(fm, x, q, v, w, R, F, T)
    else:
        F[:, :] = 0.0
        T[:, :] = 0.0
    for k in range(x.shape[0]):
        for c in range(3):
            a[k, c] = F[k, c] * inv_m[k]
            al[k, c] = Iinv[k, c, 0] * T[k, 0] + Iinv[k, c, 1] * T[k, 1] + Iinv[k, c, 2] * T[k, 2]


@njit(cache=True, inline="always")
def _mv(R, k, v):
    return (R[k, 0, 0] * v[0] + R[k, 0, 1] * v[1] + R[k, 0, 2] * v[2],
            R[k, 1, 0] * v[0] + R[k, 1, 1] * v[1] + R[k, 1, 2] * v[2],
            R[k, 2, 0] * v[0] + R[k, 2, 1] * v[1] + R[k, 2, 2] * v[2])


@njit(cache=True, inline="always")
def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True, inline="always")
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always")
def _row3(A, r):
    return (A[r, 0], A[r, 1], A[r, 2])


@njit(cache=True, inline="always")
def _put(J, r, c, v):
    J[r, c] = v[0]
    J[r, c + 1] = v[1]
    J[r, c + 2] = v[2]


@njit(cache=True)
def eval_rows(jm, x, R, v, w, want_bias, C, J, bias):
    """Rows of the joint model ``jm`` (engine/joints/table.py
    ``JointModel.table``) at the pose (x (n, 3), R (n, 3, 3)) and velocities
    (v, w (n, 3)): C (r,) residuals (m for POINT and SLIDE, 1 for DOT),
    J (r, 12), and, when ``want_bias``, bias (r,) = (dJ/dt) u."""
    rt, ra, rb, rk, pa0, pb0, s0, t0 = jm.rt, jm.ra, jm.rb, jm.rk, jm.pa, jm.pb, jm.s, jm.t
    z = (0.0, 0.0, 0.0)
    for r in range(rt.shape[0]):
        a, b, typ = ra[r], rb[r], rt[r]
        xa = _row3(x, a)
        va = _row3(v, a)
        wa = _row3(w, a)
        if b >= 0:
            xb = _row3(x, b)
            vb = _row3(v, b)
            wb = _row3(w, b)
        else:
            xb, vb, wb = z, z, z
        for c in range(12):
            J[r, c] = 0.0
        if typ == DOT:
            s = _mv(R, a, _row3(s0, r))
            t = _mv(R, b, _row3(t0, r)) if b >= 0 else _row3(t0, r)
            C[r] = _dot(s, t)
            st = _cross(s, t)
            _put(J, r, 3, st)
            _put(J, r, 9, (-st[0], -st[1], -st[2]))
            if want_bias:
                was = _cross(wa, s)
                wbt = _cross(wb, t)
                bias[r] = _dot(_cross(wa, was), t) + 2.0 * _dot(was, wbt) + _dot(s, _cross(wb, wbt))
            continue
        r_a = _mv(R, a, _row3(pa0, r))
        r_b = _mv(R, b, _row3(pb0, r)) if b >= 0 else _row3(pb0, r)
        d = (xa[0] + r_a[0] - xb[0] - r_b[0], xa[1] + r_a[1] - xb[1] - r_b[1], xa[2] + r_a[2] - xb[2] - r_b[2])
        if typ == POINT:
            k = rk[r]
            e = (1.0 if k == 0 else 0.0, 1.0 if k == 1 else 0.0, 1.0 if k == 2 else 0.0)
            C[r] = d[k]
            _put(J, r, 0, e)
            _put(J, r, 3, _cross(r_a, e))
            _put(J, r, 6, (-e[0], -e[1], -e[2]))
            rbe = _cross(r_b, e)
            _put(J, r, 9, (-rbe[0], -rbe[1], -rbe[2]))
            if want_bias:
                ca = _cross(wa, _cross(wa, r_a))
                cb = _cross(wb, _cross(wb, r_b))
                bias[r] = ca[k] - cb[k]
            continue
        # SLIDE
        t = _mv(R, b, _row3(t0, r)) if b >= 0 else _row3(t0, r)
        C[r] = _dot(t, d)
        _put(J, r, 0, t)
        _put(J, r, 3, _cross(r_a, t))
        _put(J, r, 6, (-t[0], -t[1], -t[2]))
        _put(J, r, 9, _cross(t, (xa[0] + r_a[0] - xb[0], xa[1] + r_a[1] - xb[1], xa[2] + r_a[2] - xb[2])))
        if want_bias:
            war = _cross(wa, r_a)
            wbr = _cross(wb, r_b)
            dd = (va[0] + war[0] - vb[0] - wbr[0], va[1] + war[1] - vb[1] - wbr[1], va[2] + war[2] - vb[2] - wbr[2])
            wbt = _cross(wb, t)
            ca = _cross(wa, war)
            cb = _cross(wb, wbr)
            bias[r] = (_dot(_cross(wb, wbt), d) + 2.0 * _dot(wbt, dd)
                       + _dot(t, (ca[0] - cb[0], ca[1] - cb[1], ca[2] - cb[2])))
