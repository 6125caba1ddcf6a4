"""The contact solve, by phase (as Box2D's contact_solver.h names its own).

A solve (``engine.solver.Solve``, once per (mini-)step) runs:

1. **classify** -- the contacts' normal velocities at the start, the free
   flight's end and its mean motion; touching, speculative and impact
   rows (``prepare.classify``);
2. **prepare** -- normal rows (Jacobians, effective masses, points in body
   a's frame), friction patches (centroid frame, tangent, twist and
   rolling rows), targets with restitution, position-correction bias
   (``prepare``, driven by ``rows.Rows`` over a cached ``topology.Topology``);
3. **warm start** -- the last step's forces matched to this step's rows
   (``warm.match``) and applied (``gauss_seidel.apply_rows``/``apply_patches``);
4. **direct start** -- the normal rows that do not separate solved as
   equalities, dense LU with an active set or sparse banded Cholesky per
   island (``linalg``);
5. **solve** -- projected Gauss-Seidel sweeps with friction patches, twist,
   rolling and the static/kinetic switch (``gauss_seidel.iterate``); the
   friction-stop search reruns it with pins (``rows.Rows.stop_times``);
6. **relax** -- split-impulse (or Baumgarte) position correction on pseudo
   velocities (``gauss_seidel.iterate_normal``);
7. **store** -- the forces cached for the next step (``warm.store``).

Restitution: bounce targets are prepared with the rows (2); impacts found
by the CCD stage are resolved at their time of impact by ``impact``
(propagation, or one simultaneous plastic impact per island).

Compiled (numba, ``cache=True``, no fastmath, no parallel, no BLAS):
``prepare``, ``warm`` (matching, store), ``linalg``, ``gauss_seidel``.  Work
arrays come from ``scratch.Scratch`` (kept in the step's Context).
"""
