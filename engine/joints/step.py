"""One (sub)step of a scene with joints: the bodies' ODE with the joint
forces solved exactly at every stage of an explicit Runge-Kutta method,
then the end pose projected back onto the joints' manifold and the
velocities onto its tangent (post-stabilisation).

At a state (x, q, v, w) the applied forces F, T (engine.flight.evaluate:
gravity, drag, springs, the explicit gyroscopic torque) give the free
accelerations u'_f = M^-1 (F, T); the joint forces J^T lambda make the
rows' second derivative vanish, J u' + bias = 0 (engine/joints/rows.py):

    K lambda = -(J u'_f + bias),   K = J M^-1 J^T,   u' = u'_f + M^-1 J^T lambda

(index reduction: exact for the ODE of the constrained motion, so the
method keeps its order; 4 with rk4).  The drift the method leaves,
O(h^5) a step with rk4, is removed after the step by Newton's method on
C(x, q) = 0 along M^-1 J^T (the smallest change in the mass metric:
x += dx, q <- exp(dtheta) q), to ``tol`` (setting ``joint_tolerance``)
in at most ``max_iter`` iterations, and the velocities by one exact
projection u -= M^-1 J^T K^-1 J u.  Everything is in kept work arrays
(kept by the stage, engine/joints/stage.py); nothing is allocated.
Tests: tests/test_engine_joints.py.
"""

from __future__ import annotations

import math
from collections import namedtuple

from numba import njit

from physbench.engine.flight import rotate
from physbench.engine.fused.borrow import borrow
from physbench.engine.joints.rows import eval_rows, frames, free_accelerations
from physbench.engine.joints.sequential import si_part
from physbench.engine.joints.solve import apply_rows, assemble, band_solve, factor, mass_times_rows, rows_times

#: the system the joint step integrates: the rows ``jm``
#: (engine.joints.table.Rows), the band width ``bw`` of K, the force model
#: ``fm`` (engine.flight.ForceModel) and whether there are forces, the
#: inverse masses (n,) 1/kg and principal inverse inertias (n, 3)
System = namedtuple("System", ("jm", "bw", "fm", "has_forces", "inv_m", "inv_I"))
#: an explicit Runge-Kutta tableau: ``A`` (4, 4) below the diagonal, ``B``
#: (4,), ``S`` stages
Tableau = namedtuple("Tableau", ("A", "B", "S"))
#: the step's settings: the Newton projection on (``project_on``), its
#: tolerance ``tol`` and most iterations ``max_iter``; the split: the
#: fastest gravity swing ``w_g`` rad/s, the turn limit ``max_turn`` rad, the
#: most parts ``max_parts``; sequential impulses on (``si_on``), their
#: ``iterations`` and Baumgarte factor ``beta``
Settings = namedtuple("Settings", ("project_on", "tol", "max_iter", "w_g", "max_turn", "max_parts", "si_on",
                                   "iterations", "beta"))
#: the kept work arrays (n bodies, r rows): rotations ``R``, world inverse
#: inertias ``Iinv`` (n, 3, 3), forces ``F``, torques ``T`` (n, 3), residuals
#: ``C`` (r,), Jacobians ``J`` and M^-1 J^T ``MJ`` (r, 12), biases ``bias``
#: (r,), the band of K ``Kb`` and its factor ``L`` (r, bw + 1), ``rhs``,
#: ``lam``, ``y`` (r,), velocity changes ``dv``, ``dw`` (n, 3)
Work = namedtuple("Work", ("R", "Iinv", "F", "T", "C", "J", "MJ", "bias", "Kb", "L", "rhs", "lam", "y", "dv", "dw"))
#: the Runge-Kutta stage arrays: the stage state ``xs``, ``qs``, ``vs``,
#: ``ws`` (n, 3|4) and the slopes ``kx``, ``kq``, ``kv``, ``kw`` (4, n, 3|4)
Stages = namedtuple("Stages", ("xs", "qs", "vs", "ws", "kx", "kq", "kv", "kw"))
#: what the joint step keeps (engine/joints/stage.py): the :data:`System`,
#: :data:`Tableau`, :data:`Settings`, the rows' impulses ``lam`` (r,) N s
#: (the sequential impulses' warm start), the :data:`Work` and
#: :data:`Stages` arrays, and ``stats`` (3,) (splits, Newton iterations,
#: the last largest residual: :func:`joint_block`)
Plan = namedtuple("Plan", ("sys", "tab", "cfg", "lam", "wk", "st", "stats"))
#: the candidate end state a step writes: x (n, 3), q (n, 4), v, w (n, 3)
End = namedtuple("End", ("x", "q", "v", "w"))


@njit(cache=True)
def accelerations(js, x, q, v, w, wk, a, al):
    """The constrained accelerations a, al (n, 3) at (x, q, v, w) of the
    :data:`System` ``js`` (module doc).  Returns the rows dropped as
    redundant."""
    jm, bw, inv_m = js.jm, js.bw, js.inv_m
    R, Iinv, C, J, MJ, bias = wk.R, wk.Iinv, wk.C, wk.J, wk.MJ, wk.bias
    Kb, L, rhs, lam, y = wk.Kb, wk.L, wk.rhs, wk.lam, wk.y
    ra, rb = jm.ra, jm.rb
    free_accelerations(js.fm, js.has_forces, js.inv_m, js.inv_I, x, q, v, w, wk, a, al)
    eval_rows(jm, x, R, v, w, True, C, J, bias)
    mass_times_rows(ra, rb, J, inv_m, Iinv, MJ)
    assemble(ra, rb, J, MJ, bw, Kb)
    dropped = factor(Kb, bw, L)
    rows_times(ra, rb, J, a, al, rhs)
    for r in range(rhs.shape[0]):
        rhs[r] = -(rhs[r] + bias[r])
    band_solve(L, bw, rhs, y, lam)
    apply_rows(ra, rb, MJ, lam, 1.0, a, al)
    return dropped


@njit(cache=True)
def project(js, x, q, v, w, wk, tol, max_iter, velocities):
    """Newton's method on C(x, q) = 0 along M^-1 J^T, then, when
    ``velocities``, u onto J u = 0 (module doc; ``js`` the
    :data:`System`).  Returns (iterations, largest |C| left (m or 1))."""
    jm, bw, inv_m, inv_I = js.jm, js.bw, js.inv_m, js.inv_I
    R, Iinv, C, J, MJ, bias, Kb, L, rhs, lam, y, dv, dw = (wk.R, wk.Iinv, wk.C, wk.J, wk.MJ, wk.bias, wk.Kb, wk.L,
                                                            wk.rhs, wk.lam, wk.y, wk.dv, wk.dw)
    ra, rb = jm.ra, jm.rb
    n = x.shape[0]
    it = 0
    worst = 0.0
    while True:
        frames(q, inv_I, R, Iinv)
        eval_rows(jm, x, R, v, w, False, C, J, bias)
        worst = 0.0
        for r in range(C.shape[0]):
            if abs(C[r]) > worst:
                worst = abs(C[r])
        if worst <= tol or it >= max_iter:
            break
        it += 1
        mass_times_rows(ra, rb, J, inv_m, Iinv, MJ)
        assemble(ra, rb, J, MJ, bw, Kb)
        factor(Kb, bw, L)
        band_solve(L, bw, C, y, lam)
        dv[:, :] = 0.0
        dw[:, :] = 0.0
        apply_rows(ra, rb, MJ, lam, -1.0, dv, dw)
        for k in range(n):
            for c in range(3):
                x[k, c] += dv[k, c]
            rotate(q, k, dw[k, 0], dw[k, 1], dw[k, 2], q)
    if not velocities:
        return it, worst
    # velocities onto the tangent at the final pose (J, R, Iinv are its)
    mass_times_rows(ra, rb, J, inv_m, Iinv, MJ)
    assemble(ra, rb, J, MJ, bw, Kb)
    factor(Kb, bw, L)
    rows_times(ra, rb, J, v, w, rhs)
    band_solve(L, bw, rhs, y, lam)
    apply_rows(ra, rb, MJ, lam, -1.0, v, w)
    return it, worst


@njit(cache=True, inline="always")
def _qdot(w, q, k):
    wx, wy, wz = w[k, 0], w[k, 1], w[k, 2]
    qw, qx, qy, qz = q[k, 0], q[k, 1], q[k, 2], q[k, 3]
    return (-0.5 * (wx * qx + wy * qy + wz * qz), 0.5 * (wx * qw + wy * qz - wz * qy),
            0.5 * (-wx * qz + wy * qw + wz * qx), 0.5 * (wx * qy - wy * qx + wz * qw))


@njit(cache=True)
def _rk_part(js, tab, x, q, v, w, h, wk, st):
    """One explicit Runge-Kutta step of length h (s) of the constrained
    ODE of the :data:`System` ``js`` (``tab`` the :data:`Tableau`), in
    place on (x, q, v, w); quaternions renormalised.  Returns the rows
    dropped as redundant at its first stage."""
    A, B, S = tab.A, tab.B, tab.S
    xs, qs, vs, ws, kx, kq, kv, kw = st.xs, st.qs, st.vs, st.ws, st.kx, st.kq, st.kv, st.kw
    n = x.shape[0]
    dropped = 0
    for i in range(S):
        for k in range(n):
            for c in range(3):
                sx, sv, sw = x[k, c], v[k, c], w[k, c]
                for j in range(i):
                    sx += h * A[i, j] * kx[j, k, c]
                    sv += h * A[i, j] * kv[j, k, c]
                    sw += h * A[i, j] * kw[j, k, c]
                xs[k, c], vs[k, c], ws[k, c] = sx, sv, sw
            for c in range(4):
                sq = q[k, c]
                for j in range(i):
                    sq += h * A[i, j] * kq[j, k, c]
                qs[k, c] = sq
        d = accelerations(js, xs, qs, vs, ws, wk, kv[i], kw[i])
        if i == 0:
            dropped = d
        for k in range(n):
            for c in range(3):
                kx[i, k, c] = vs[k, c]
            d0, d1, d2, d3 = _qdot(ws, qs, k)
            kq[i, k, 0], kq[i, k, 1], kq[i, k, 2], kq[i, k, 3] = d0, d1, d2, d3
    for k in range(n):
        for c in range(3):
            sx, sv, sw = x[k, c], v[k, c], w[k, c]
            for i in range(S):
                sx += h * B[i] * kx[i, k, c]
                sv += h * B[i] * kv[i, k, c]
                sw += h * B[i] * kw[i, k, c]
            x[k, c], v[k, c], w[k, c] = sx, sv, sw
        s2 = 0.0
        for c in range(4):
            sq = q[k, c]
            for i in range(S):
                sq += h * B[i] * kq[i, k, c]
            q[k, c] = sq
            s2 += sq * sq
        nq = math.sqrt(s2)
        for c in range(4):
            q[k, c] /= nq
    return dropped


@njit(cache=True)
def parts_for(w, h, w_g, max_turn, max_parts):
    """Equal parts of a step of length h such that no body turns by more
    than ``max_turn`` (rad) in one at its start rate, nor does the
    fastest gravity pendulum of the rows (rate ``w_g`` = sqrt(|g| / the
    shortest anchor arm), rad/s); 1 when ``max_turn`` is 0, at most
    ``max_parts``."""
    if max_turn <= 0.0:
        return 1
    top = w_g * w_g
    for k in range(w.shape[0]):
        s = w[k, 0] ** 2 + w[k, 1] ** 2 + w[k, 2] ** 2
        if s > top:
            top = s
    turn = math.sqrt(top) * h
    if not turn > max_turn:  # (NaN: a blown-up state is not split)
        return 1
    p = int(math.ceil(turn / max_turn))
    return p if p < max_parts else max_parts


@njit(cache=True)
def joint_step(p, x0, q0, v0, w0, h, x1, q1, v1, w1):
    """One step of length h (s) from (x0, q0, v0, w0) into (x1, q1, v1,
    w1) by the :data:`Plan` ``p``: :func:`parts_for` equal parts, each an
    explicit Runge-Kutta step of the constrained ODE (:func:`_rk_part`)
    followed, when ``project_on``, by :func:`project`.  ``si_on``: each
    part is instead the sequential-impulse step
    (engine/joints/sequential.py: ``iterations`` passes, Baumgarte
    ``beta``, the warm-start impulses ``p.lam`` (r,)).  Returns (parts,
    Newton iterations, largest |C| after the step, redundant rows
    dropped)."""
    js, cfg, wk = p.sys, p.cfg, p.wk
    n = x0.shape[0]
    for k in range(n):
        for c in range(3):
            x1[k, c], v1[k, c], w1[k, c] = x0[k, c], v0[k, c], w0[k, c]
        for c in range(4):
            q1[k, c] = q0[k, c]
    parts = parts_for(w0, h, cfg.w_g, cfg.max_turn, cfg.max_parts)
    hp = h / parts
    its, worst, dropped = 0, 0.0, 0
    for _ in range(parts):
        if cfg.si_on:
            si_part(js, x1, q1, v1, w1, hp, cfg.iterations, cfg.beta, p.lam, wk)
        else:
            dropped = _rk_part(js, p.tab, x1, q1, v1, w1, hp, wk, p.st)
        if cfg.project_on:
            # (after sequential impulses the positions only: their next
            # solve takes the velocities, and a projection of the
            # symplectic Euler step's velocities loses energy at O(h))
            it, worst = project(js, x1, q1, v1, w1, wk, cfg.tol, cfg.max_iter, not cfg.si_on)
            its += it
    return parts, its, worst, dropped


@njit(cache=True)
def joint_step_packed(kp, x0, q0, v0, w0, h, x1, q1, v1, w1):
    """:func:`joint_step` from Python (the stage): ``kp`` a Pack of the
    :data:`Plan` (one pointer to unbox).  The plan's and the state's
    arrays are borrowed for the call (engine/fused/borrow.py: no reference
    counting, the same memory and arithmetic; they live in the caller's
    hands throughout)."""
    x0, q0, v0, w0, x1, q1, v1, w1 = borrow((x0, q0, v0, w0, x1, q1, v1, w1))
    return joint_step(borrow(kp.items), x0, q0, v0, w0, h, x1, q1, v1, w1)


@njit(cache=True)
def joint_block(kp, ke, x, q, v, w, h, substeps, t, n, pos, quat, vel, angvel):
    """``n`` steps of ``substeps`` (sub)steps of length h (s) from the
    state (x, q, v, w), each :func:`joint_step` (``kp`` a Pack of the
    :data:`Plan`) into the end state (``ke`` a Pack of an :data:`End`)
    and committed (copied back): the
    same arithmetic as the staged step's stage and commit, so the same
    bits.  The state after step k goes to row k of pos, quat, vel, angvel
    when they have rows (none: nothing recorded).  The plan's stats (3,)
    += (splits, Newton iterations), stats[2] = the last largest residual.
    Returns the time t (s) advanced as the staged steps advance it.
    Every array is borrowed for the call (engine/fused/borrow.py: no
    reference counting, which cost more than the step's arithmetic; the
    same memory, the same bits: tests/test_engine_joints.py::
    test_the_loop_over_steps_gives_the_staged_steps_bits)."""
    p = borrow(kp.items)
    e = borrow(ke.items)
    x, q, v, w, pos, quat, vel, angvel = borrow((x, q, v, w, pos, quat, vel, angvel))
    x1, q1, v1, w1 = e.x, e.q, e.v, e.w
    stats = p.stats
    rec_on = pos.shape[0] != 0
    nb = x.shape[0]
    for k in range(n):
        for _ in range(substeps):
            parts, its, worst, dropped = joint_step(p, x, q, v, w, h, x1, q1, v1, w1)
            for i in range(nb):
                for c in range(3):
                    x[i, c] = x1[i, c]
                    v[i, c] = v1[i, c]
                    w[i, c] = w1[i, c]
                for c in range(4):
                    q[i, c] = q1[i, c]
            t += h
            stats[0] += parts - 1
            stats[1] += its
            stats[2] = worst
        if rec_on:
            for i in range(nb):
                for c in range(3):
                    pos[k, i, c] = x[i, c]
                    vel[k, i, c] = v[i, c]
                    angvel[k, i, c] = w[i, c]
                for c in range(4):
                    quat[k, i, c] = q[i, c]
    return t
