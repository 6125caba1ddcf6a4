"""The joint rows in a sequential-impulse solver (Box2D's and Bullet's way,
setting ``joint_solver = sequential_impulse``): velocity-level rows solved
by projected Gauss-Seidel, warm-started, drift corrected by Baumgarte.

One step of length h, semi-implicit Euler (the integrator these solvers
run, setting ``integrator = semi_implicit_euler``):

1. v* = v + h M^-1 f (the force model at the start state);
2. the rows at the start pose (rows.py): J, C and each row's effective
   mass 1 / (J_r M^-1 J_r^T);
3. warm start: the last step's impulses applied again, v* += M^-1 J^T lambda;
4. ``iterations`` Gauss-Seidel passes over the rows in order:
   d lambda_r = -(J_r v + beta C_r / h) / (J_r M^-1 J_r^T), lambda_r += d lambda_r,
   v += M^-1 J_r^T d lambda_r (beta: setting ``joint_baumgarte``);
5. x += h v, q <- exp(h w) q.

The rows hold only as far as the passes converge and Baumgarte pulls the
drift back (the field's behaviour: joint error grows with the length of
a chain and the mass ratio).  With ``joint_projection = newton`` the
positions are then projected onto the joints (as nonlinear Gauss-Seidel
corrects positions apart from velocities); the velocities are left to the
next step's solve (projecting the step's velocities onto the new tangent
loses energy at O(h)).  Tests: tests/test_engine_joints.py.
"""

from __future__ import annotations

from numba import njit

from physbench.engine.flight import rotate
from physbench.engine.joints.rows import eval_rows, free_accelerations
from physbench.engine.joints.solve import mass_times_rows


@njit(cache=True)
def si_part(js, x, q, v, w, h, iterations, beta, lam, wk):
    """One semi-implicit step of length h (s) in place on (x, q, v, w)
    of the system ``js`` (engine.joints.step.System) with the joint rows
    solved by sequential impulses (module doc); ``lam`` (r,) the rows'
    impulses (N s), kept between steps (warm start); ``wk`` the work
    arrays (engine.joints.step.Work)."""
    jm, fm, has_forces, inv_m, inv_I = js.jm, js.fm, js.has_forces, js.inv_m, js.inv_I
    R, Iinv, C, J, MJ, bias, y, dv, dw = wk.R, wk.Iinv, wk.C, wk.J, wk.MJ, wk.bias, wk.y, wk.dv, wk.dw
    ra, rb = jm.ra, jm.rb
    n = x.shape[0]
    free_accelerations(fm, has_forces, inv_m, inv_I, x, q, v, w, wk, dv, dw)
    for k in range(n):
        for c in range(3):
            v[k, c] += h * dv[k, c]
            w[k, c] += h * dw[k, c]
    eval_rows(jm, x, R, v, w, False, C, J, bias)
    mass_times_rows(ra, rb, J, inv_m, Iinv, MJ)
    m = C.shape[0]
    for r in range(m):  # effective masses (into y)
        s = 0.0
        for c in range(12):
            s += J[r, c] * MJ[r, c]
        y[r] = 1.0 / s if s > 0.0 else 0.0
    for it in range(iterations + 1):
        for r in range(m):
            if it == 0:
                d = lam[r]  # warm start: last step's impulse
            else:
                jv = 0.0
                for side in range(2):
                    k = ra[r] if side == 0 else rb[r]
                    if k < 0:
                        continue
                    o = 6 * side
                    for c in range(3):
                        jv += J[r, o + c] * v[k, c] + J[r, o + 3 + c] * w[k, c]
                d = -(jv + beta * C[r] / h) * y[r]
                lam[r] += d
            for side in range(2):
                k = ra[r] if side == 0 else rb[r]
                if k < 0:
                    continue
                o = 6 * side
                for c in range(3):
                    v[k, c] += MJ[r, o + c] * d
                    w[k, c] += MJ[r, o + 3 + c] * d
    for k in range(n):
        for c in range(3):
            x[k, c] += h * v[k, c]
        rotate(q, k, h * w[k, 0], h * w[k, 1], h * w[k, 2], q)
