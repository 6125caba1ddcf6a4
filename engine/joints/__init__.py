"""Joints in the reference engine: maximal coordinates, constraint rows
solved exactly inside the integrator, post-stabilised.

A scene with the ``joint`` effect steps on the staged path with one joint
stage in place of the free flight and the position update (decided once,
in :func:`engine.pipeline.build_pipeline`): the force stages at the start
state, then :class:`JointFlight` (engine/joints/step.py: an explicit
Runge-Kutta step whose accelerations satisfy the joints' rows exactly,
the end pose projected onto C = 0 by Newton's method and the velocities
onto J u = 0).  Rows: engine/joints/rows.py; the band solve of
K = J M^-1 J^T: engine/joints/solve.py.

Input (``SceneInput.joints``): one tuple per joint, ``(kind, body, other,
anchor_body, anchor_other, axis_body, axis_other)``: kind one of
:data:`KINDS`, body and other indices (other -1: the world), the anchor
(m) in each side's frame (from its centre of mass; the world's frame for
the world), the axis (unit, revolute: hinge; prismatic: slide) in each
side's frame or None.

Settings: ``joint_projection`` (``newton``: the post-stabilisation above;
``off``: the index-reduced ODE alone, whose drift grows with time),
``joint_tolerance`` (the largest row residual the projection leaves, m
for positions, 1 for the axis rows), ``joint_max_turn`` (a step in which
a body would turn by more than this many rad, at its start rate or at the
rate of the scene's fastest gravity swing, sqrt(|g| / shortest anchor
arm), runs as equal parts that do not; counted as ``joint_splits``).
Not modelled (:func:`unsupported_reason`): joints together with contact,
the ``velocity_verlet`` and ``semi_implicit_euler`` integrators, and the
implicit or energy-conserving gyroscopic treatments of anisotropic
bodies (the joint step integrates w x I w explicitly: setting
``gyroscopic = explicit``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from physbench.engine.profile import Stage, add_jit_seconds
from physbench.engine.joints.rows import DOT, POINT, SLIDE

#: the joint kinds the engine builds
KINDS = ("revolute", "spherical", "prismatic", "fixed")

#: explicit Runge-Kutta tableaus (A (4, 4), B (4,), stages) of the
#: integrators the joint step runs
_TABLEAUS = {
    "explicit_euler": ([], [1.0]),
    "midpoint": ([[0.5]], [0.0, 1.0]),
    "heun": ([[1.0]], [0.5, 0.5]),
    "rk4": ([[0.5], [0.0, 0.5], [0.0, 0.0, 1.0]], [1 / 6, 1 / 3, 1 / 3, 1 / 6]),
}

#: Newton iterations of the position projection at most a step
MAX_ITER = 20
#: parts a step is split into at most (setting ``joint_max_turn``)
MAX_PARTS = 4096


@dataclass(frozen=True, eq=False)
class JointModel:
    """The joints as rows (r rows; rows.py): ``rt`` (r,) row type, ``ra``
    (r,) body, ``rb`` (r,) other (-1 world), ``rk`` (r,) world axis of a
    POINT row, ``pa``/``pb`` (r, 3) anchors in a's/b's frame (m), ``s``
    (r, 3) a's vector, ``t`` (r, 3) b's vector; ``bw`` the band width of
    K (solve.py); ``joint_of_row`` (r,); ``kinds`` per joint."""

    rt: np.ndarray
    ra: np.ndarray
    rb: np.ndarray
    rk: np.ndarray
    pa: np.ndarray
    pb: np.ndarray
    s: np.ndarray
    t: np.ndarray
    bw: int
    joint_of_row: np.ndarray
    kinds: tuple

    @property
    def table(self) -> tuple:
        return (self.rt, self.ra, self.rb, self.rk, self.pa, self.pb, self.s, self.t)

    @property
    def rows(self) -> int:
        return int(self.rt.shape[0])


def _perpendiculars(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit u to an orthonormal frame."""
    u = u / np.linalg.norm(u)
    e = np.eye(3)[int(np.argmin(np.abs(u)))]
    p1 = np.cross(u, e)
    p1 /= np.linalg.norm(p1)
    return p1, np.cross(u, p1)


def _rot(q: np.ndarray) -> np.ndarray:
    from physbench.engine.mathutil import quat_to_matrix

    q = np.asarray(q, float)
    return quat_to_matrix((q / np.linalg.norm(q)).reshape(1, 4))[0]


def build_joints(inp) -> JointModel | None:
    """The rows of ``inp.joints`` (module doc), or None without joints."""
    joints = tuple(getattr(inp, "joints", ()) or ())
    if not joints:
        return None
    rows: list[tuple] = []
    q0 = np.asarray(inp.q, float).reshape(-1, 4)
    for ji, (kind, b, o, pa, pb, ua, ub) in enumerate(joints):
        if kind not in KINDS:
            raise ValueError(f"joint {ji}: unknown kind {kind!r}; expected one of {KINDS}")
        pa, pb = np.asarray(pa, float), np.asarray(pb, float)
        z = np.zeros(3)
        Ra = _rot(q0[b])
        Rb = np.eye(3) if o < 0 else _rot(q0[o])
        if kind in ("revolute", "spherical", "fixed"):
            rows += [(POINT, b, o, k, pa, pb, z, z, ji) for k in range(3)]
        if kind == "revolute":
            p1, p2 = _perpendiculars(np.asarray(ub, float))
            rows += [(DOT, b, o, 0, z, z, np.asarray(ua, float), p, ji) for p in (p1, p2)]
        if kind == "prismatic":
            p1, p2 = _perpendiculars(np.asarray(ub, float))
            rows += [(SLIDE, b, o, 0, pa, pb, z, p, ji) for p in (p1, p2)]
        if kind in ("fixed", "prismatic"):
            # the world's axes e_i in each side's frame at the start;
            # rows (1, 2), (2, 3), (3, 1) start perpendicular
            for i, j in ((0, 1), (1, 2), (2, 0)):
                rows.append((DOT, b, o, 0, z, z, Ra.T[:, i].copy(), Rb.T[:, j].copy(), ji))
    r = len(rows)
    rt = np.array([x[0] for x in rows], np.int64)
    ra = np.array([x[1] for x in rows], np.int64)
    rb = np.array([x[2] for x in rows], np.int64)
    bw = 0
    for i in range(r):
        for j in range(i):
            if {ra[i], rb[i]} & {ra[j], rb[j]} - {-1}:
                bw = max(bw, i - j)
    return JointModel(rt=rt, ra=ra, rb=rb, rk=np.array([x[3] for x in rows], np.int64),
                      pa=np.array([x[4] for x in rows], float).reshape(r, 3),
                      pb=np.array([x[5] for x in rows], float).reshape(r, 3),
                      s=np.array([x[6] for x in rows], float).reshape(r, 3),
                      t=np.array([x[7] for x in rows], float).reshape(r, 3), bw=bw,
                      joint_of_row=np.array([x[8] for x in rows], np.int64), kinds=tuple(j[0] for j in joints))


def unsupported_reason(model) -> str | None:
    """Why the engine cannot step ``model``'s joints as asked, or None."""
    if model.joints is None:
        return None
    if model.has("contact"):
        return ("joints with contact: the reference engine does not yet couple its joint solve with the contact "
                "solve")
    integ = model.setting("integrator")
    if integ not in _TABLEAUS:
        return f"joints: the joint step has no {integ} integrator (it has {', '.join(_TABLEAUS)})"
    if (model.has("gyroscopic") and np.any(~model.isotropic) and model.setting("gyroscopic") != "explicit"):
        return (f"joints: gyroscopic = {model.setting('gyroscopic')} is not in the joint step (it integrates "
                "w x I w explicitly: gyroscopic = explicit)")
    return None


class JointFlight(Stage):
    """The joint step (engine/joints/step.py) from the state into the
    context's candidate end state (x1, q1, v, w); forces from the force
    stages' compiled model.  Counts ``joint_newton_iterations`` and
    ``joint_splits``; the
    largest residual left is ``self.residual``."""

    name = "joint_step"
    family = "integrate"

    def __init__(self, model, forces):
        from physbench.engine.forces import force_model

        jm: JointModel = model.joints
        n, r, bw = model.n, jm.rows, jm.bw
        self.jm = jm.table
        self.bw = int(bw)
        self.fm = force_model(model, forces)
        self.has_forces = bool(forces)
        self.inv_m = np.array(model.inv_mass[:n], float)
        self.inv_I = np.array(model.inv_inertia_body[:n], float)
        a, b = _TABLEAUS[model.setting("integrator")]
        self.S = len(b)
        self.A = np.zeros((4, 4))
        for i, row in enumerate(a):
            self.A[i + 1, :len(row)] = row
        self.B = np.zeros(4)
        self.B[:self.S] = b
        self.project = model.setting("joint_projection") == "newton"
        self.tol = float(model.setting("joint_tolerance"))
        z3 = lambda: np.zeros((n, 3))  # noqa: E731
        self.wk = (np.zeros((n, 3, 3)), np.zeros((n, 3, 3)), z3(), z3(), np.zeros(r), np.zeros((r, 12)),
                   np.zeros((r, 12)), np.zeros(r), np.zeros((r, bw + 1)), np.zeros((r, bw + 1)), np.zeros(r),
                   np.zeros(r), np.zeros(r), z3(), z3())
        self.st = (z3(), np.zeros((n, 4)), z3(), z3(), np.zeros((4, n, 3)), np.zeros((4, n, 4)),
                   np.zeros((4, n, 3)), np.zeros((4, n, 3)))
        self.max_turn = float(model.setting("joint_max_turn"))
        arms = np.linalg.norm(np.concatenate([jm.pa, jm.pb[jm.rb >= 0]]), axis=1)
        arms = arms[arms > 0]
        g = float(np.linalg.norm(model.gravity)) if model.has("gravity") else 0.0
        #: the fastest small swing of a row's anchor arm under gravity (rad/s)
        self.w_g = float(np.sqrt(g / arms.min())) if arms.size else 0.0
        self.residual = 0.0
        self.dropped = 0
        self._warm(model)

    def _run(self, x0, q0, v0, w0, h, x1, q1, v1, w1):
        from physbench.engine.joints.step import joint_step

        return joint_step(self.jm, np.int64(self.bw), self.fm, bool(self.has_forces), self.inv_m, self.inv_I, self.A,
                          self.B, np.int64(self.S), x0, q0, v0, w0, float(h), x1, q1, v1, w1, self.wk, self.st,
                          bool(self.project), float(self.tol), np.int64(MAX_ITER), float(self.w_g),
                          float(self.max_turn), np.int64(MAX_PARTS))

    def _warm(self, model) -> None:
        """Compile (or load) the joint step at build, on copies of the
        initial state: no step compiles; the seconds are JIT time."""
        from physbench.engine.state import Context, State

        t0 = time.perf_counter()
        st = State.from_model(model)
        ctx = Context(model)
        ctx.begin(model, st, model.h)  # (the staged step's begin and commit kernels)
        n = model.n
        self._run(st.x, st.q, st.v, st.w, model.h, ctx.x1, ctx.q1, ctx.v[:n], ctx.w[:n])
        ctx.commit(st)
        add_jit_seconds(time.perf_counter() - t0)

    def __call__(self, model, state, ctx) -> None:
        n = model.n
        parts, it, worst, dropped = self._run(state.x, state.q, state.v, state.w, ctx.h, ctx.x1, ctx.q1, ctx.v[:n],
                                       ctx.w[:n])
        self.residual = worst
        self.dropped = dropped
        if it:
            ctx.profile.count("joint_newton_iterations", it)
        if parts > 1:
            ctx.profile.count("joint_splits", parts - 1)


def joint_stages(model, forces) -> tuple[Stage, ...]:
    """The stages of a scene with joints: the force stages, then the joint
    step (module doc).  Raises ValueError for what is not modelled."""
    why = unsupported_reason(model)
    if why:
        raise ValueError(why)
    return tuple(forces) + (JointFlight(model, forces),)


__all__ = ["KINDS", "JointFlight", "JointModel", "build_joints", "joint_stages", "unsupported_reason"]
