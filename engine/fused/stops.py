"""The rolling part of the friction-stop gate inside the fused steady step
(engine/fused/steady.py).

A steady step of a scene with rolling friction and friction stops
(friction.rolling_resistance, friction.cylinder_rolling_resistance) must
fall back to the staged step wherever the staged solve's stop test could
find a rolling contact that came to rest inside the step.  That test
(``Solve._finish`` -> ``Rows.stop_times``) opens with
:func:`engine.contact.prepare.stop_candidate` over the patches' start
rolling velocities ``wr0 = Rows.patch_velocity(U0, slice(3, 5))``;
:func:`rolling_candidate` is its rolling half with ``wr0`` computed in the
same loop from the same rows and start velocities (the same sums,
``gauss_seidel.row_velocity``), so no (np, 2) buffer is needed, and it decides
exactly as the staged gate does (the same bits:
tests/test_engine_steady_gyro.py::test_rolling_friction_with_stops_takes_the_fused_step).
"""

from __future__ import annotations

import math

from numba import njit

from physbench.engine.contact.prepare import _pressed
from physbench.engine.contact.gauss_seidel import row_velocity


@njit(cache=True)
def rolling_candidate(pid, lam_n, Jt, U, U0, pab, mur, roll_tol, npch):
    """Whether a pressed patch (of ``npch``) with rolling friction
    (``mur`` (np,) > 0) rolled at the start of the step (|wr0| > roll_tol
    rad/s, wr0 the rolling rows 3, 4 of ``Jt`` (np, 5, 12) at the start
    velocities ``U0`` (nb+1, 6)) and ends with its rolling velocity along
    the start direction below roll_tol (end velocities ``U``): the rolling
    branch of prepare.stop_candidate, term for term.  ``pid`` (m,) the
    rows' patches, ``lam_n`` (m,) their impulses, ``pab`` (np, 2) the
    patches' bodies."""
    for p in range(npch):
        if mur[p] > 0.0:
            ia = pab[p, 0]
            ib = pab[p, 1]
            w0 = row_velocity(Jt, U0, p, 3, ia, ib)
            w1 = row_velocity(Jt, U0, p, 4, ia, ib)
            r0 = math.sqrt(w0 * w0 + w1 * w1)
            if r0 > roll_tol * (1.0 - 1e-9):
                e0 = row_velocity(Jt, U, p, 3, ia, ib) * (w0 / r0)
                e1 = row_velocity(Jt, U, p, 4, ia, ib) * (w1 / r0)
                if e0 + e1 < roll_tol + 1e-9 * (abs(e0) + abs(e1)) and _pressed(pid, lam_n, p):
                    return True
    return False
