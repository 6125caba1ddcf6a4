"""Joints in the reference engine: maximal coordinates, constraint rows
solved exactly inside the integrator, post-stabilised.

A scene with joints has one stage, ``stage.JointFlight``, in place of
the force stages, the free flight and the position update (decided once,
in :func:`engine.pipeline.build_pipeline`): engine/joints/step.py, an
explicit Runge-Kutta step whose accelerations satisfy the joints' rows
exactly (the force stages' compiled model evaluated at every stage), the
end pose projected onto C = 0 by Newton's method and the velocities onto
J u = 0.  ``pipeline.advance`` runs n steps as one compiled call
(``step.joint_block``), the same bits as the stage step by step.  Files: ``table.py`` (the joints as rows, what is not
modelled), ``rows.py`` (the rows' residuals, Jacobians and biases),
``solve.py`` (the band solve of K = J M^-1 J^T), ``step.py`` (the
integrator and the projection), ``sequential.py`` (the sequential-impulse
alternative), ``stage.py`` (the stage).

Input (``SceneInput.joints``): one tuple per joint, ``(kind, body, other,
anchor_body, anchor_other, axis_body, axis_other)``: kind one of
:data:`KINDS`, body and other indices (other -1: the world), the anchor
(m) in each side's frame (from its centre of mass; the world's frame for
the world), the axis (unit, revolute: hinge; prismatic: slide) in each
side's frame or None.

Settings: ``joint_solver`` (``direct``: the above; ``sequential_impulse``:
velocity-level rows by projected Gauss-Seidel with Baumgarte drift
correction, warm-started, semi-implicit Euler: ``sequential.py``),
``joint_baumgarte`` (its Baumgarte factor), ``joint_projection`` (``newton``: the post-stabilisation above;
``off``: the index-reduced ODE alone, whose drift grows with time),
``joint_tolerance`` (the largest row residual the projection leaves, m
for positions, 1 for the axis rows), ``joint_max_turn`` (a step in which
a body would turn by more than this many rad, at its start rate or at the
rate of the scene's fastest gravity swing, sqrt(|g| / shortest anchor
arm), runs as equal parts that do not; counted as ``joint_splits``).
Not modelled (``table.unsupported_reason``): joints together with contact,
the ``velocity_verlet`` and ``semi_implicit_euler`` integrators (the
latter but with sequential impulses, which need it), and the
implicit or energy-conserving gyroscopic treatments of anisotropic
bodies (the joint step integrates w x I w explicitly: setting
``gyroscopic = explicit``).
"""

#: the joint kinds the engine builds (defined with the settings, engine/settings.py: read without numba)
from physbench.engine.settings import JOINT_KINDS as KINDS  # noqa: E402
