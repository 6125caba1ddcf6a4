"""The joint stage: the joint step (engine/joints/step.py) in place of the
free flight and the position update (engine/joints/__init__.py)."""

from __future__ import annotations

import time

import numpy as np

from physbench.engine.joints.step import End, Plan, Settings, Stages, System, Tableau, Work
from physbench.engine.joints.table import TABLEAUS, JointModel, unsupported_reason
from physbench.engine.pack import Pack
from physbench.engine.profile import Stage, add_jit_seconds

#: Newton iterations of the position projection at most a step
MAX_ITER = 20
#: parts a step is split into at most (setting ``joint_max_turn``)
MAX_PARTS = 4096


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
        # (sequential impulses run semi-implicit Euler of their own: no tableau)
        a, b = TABLEAUS.get(model.setting("integrator"), ([], [1.0]))
        self.S = len(b)
        self.A = np.zeros((4, 4))
        for i, row in enumerate(a):
            self.A[i + 1, :len(row)] = row
        self.B = np.zeros(4)
        self.B[:self.S] = b
        self.project = model.setting("joint_projection") == "newton"
        self.tol = float(model.setting("joint_tolerance"))
        z3 = lambda: np.zeros((n, 3))  # noqa: E731
        self.wk = Work(R=np.zeros((n, 3, 3)), Iinv=np.zeros((n, 3, 3)), F=z3(), T=z3(), C=np.zeros(r),
                       J=np.zeros((r, 12)), MJ=np.zeros((r, 12)), bias=np.zeros(r), Kb=np.zeros((r, bw + 1)),
                       L=np.zeros((r, bw + 1)), rhs=np.zeros(r), lam=np.zeros(r), y=np.zeros(r), dv=z3(), dw=z3())
        self.st = Stages(xs=z3(), qs=np.zeros((n, 4)), vs=z3(), ws=z3(), kx=np.zeros((4, n, 3)),
                         kq=np.zeros((4, n, 4)), kv=np.zeros((4, n, 3)), kw=np.zeros((4, n, 3)))
        self.max_turn = float(model.setting("joint_max_turn"))
        #: joint_solver = sequential_impulse (engine/joints/sequential.py)
        self.si = model.setting("joint_solver") == "sequential_impulse"
        self.iterations = int(model.setting("iterations"))
        self.beta = float(model.setting("joint_baumgarte"))
        #: the rows' impulses of the last step (N s; the warm start)
        self.lam = np.zeros(r)
        arms = np.linalg.norm(np.concatenate([jm.pa, jm.pb[jm.rb >= 0]]), axis=1)
        arms = arms[arms > 0]
        g = float(np.sqrt(np.sum(np.asarray(model.gravity, float) ** 2))) if model.has("gravity") else 0.0
        #: the fastest small swing of a row's anchor arm under gravity (rad/s)
        self.w_g = float(np.sqrt(g / arms.min())) if arms.size else 0.0
        self.residual = 0.0
        self.dropped = 0
        #: splits, Newton iterations, the last residual of a block (joint_block)
        self._stats = np.zeros(3)
        #: what the kernels read (engine.joints.step.Plan), as one Pack
        self.plan = Plan(
            sys=System(jm=self.jm, bw=np.int64(self.bw), fm=self.fm, has_forces=bool(self.has_forces),
                       inv_m=self.inv_m, inv_I=self.inv_I),
            tab=Tableau(A=self.A, B=self.B, S=np.int64(self.S)),
            cfg=Settings(project_on=bool(self.project), tol=float(self.tol), max_iter=np.int64(MAX_ITER),
                         w_g=float(self.w_g), max_turn=float(self.max_turn), max_parts=np.int64(MAX_PARTS),
                         si_on=bool(self.si), iterations=np.int64(self.iterations), beta=float(self.beta)),
            lam=self.lam, wk=self.wk, st=self.st, stats=self._stats)
        self._kp = Pack(self.plan)
        self._ke = self._ke_ctx = None
        self._warm(model)

    def _run(self, x0, q0, v0, w0, h, x1, q1, v1, w1):
        from physbench.engine.joints.step import joint_step_packed

        return joint_step_packed(self._kp, x0, q0, v0, w0, float(h), x1, q1, v1, w1)

    def _end(self, ctx) -> Pack:
        """The context's candidate end state (x1, q1, v, w over the first n
        rows) as one Pack of an engine.joints.step.End, kept per context."""
        if self._ke_ctx is not ctx:
            n = ctx.x1.shape[0]
            self._ke = Pack(End(x=ctx.x1, q=ctx.q1, v=ctx.v[:n], w=ctx.w[:n]))
            self._ke_ctx = ctx
        return self._ke

    def run_block(self, model, state, ctx, profile, n: int, rec=None, progress=None) -> None:
        """``n`` steps from ``state`` in one compiled call
        (engine/joints/step.py ``joint_block``: the staged steps' bits),
        recorded into ``rec`` ((pos, quat, vel, angvel) blocks of n rows)
        when given; counted and timed as ``n * substeps`` calls of this
        stage.  ``progress``: a one-element list set to the rows done."""
        from physbench.engine.joints.step import joint_block

        t0 = time.perf_counter()
        rec_on = rec is not None and all(a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable
                                         for a in rec)
        self._stats[:] = 0.0
        # blocks the loop cannot write: one step a call, recorded here
        calls = ((n, tuple(rec) if rec_on else self._no_rec),) if rec is None or rec_on else \
            tuple((1, self._no_rec) for _ in range(n))
        for k, (m, blocks) in enumerate(calls):
            state.t = joint_block(self._kp, self._end(ctx), state.x, state.q, state.v, state.w, float(model.h),
                                  np.int64(model.substeps), float(state.t), np.int64(m), *blocks)
            if rec is not None and not rec_on:
                for a, src in zip(rec, (state.x, state.q, state.v, state.w)):
                    a[k] = src
        state.steps += n
        if progress is not None:
            progress[0] = n
        self.residual = float(self._stats[2])
        if self._stats[0]:
            profile.count("joint_splits", int(self._stats[0]))
        if self._stats[1]:
            profile.count("joint_newton_iterations", int(self._stats[1]))
        profile.charge(self.name, n * model.substeps, time.perf_counter() - t0)

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
        # the loop over steps (run_block), on the same copies
        nb = model.n
        self._no_rec = (np.zeros((0, nb, 3)), np.zeros((0, nb, 4)), np.zeros((0, nb, 3)), np.zeros((0, nb, 3)))
        from physbench.engine.joints.step import joint_block

        joint_block(self._kp, self._end(ctx), st.x, st.q, st.v, st.w, float(model.h), np.int64(1), 0.0, np.int64(1),
                    *(np.zeros((1, nb, 3)), np.zeros((1, nb, 4)), np.zeros((1, nb, 3)), np.zeros((1, nb, 3))))
        self._ke = self._ke_ctx = None  # (the warm-up's context goes)
        self.lam[:] = 0.0  # (the warm-up's impulses are no warm start)
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
    """The stages of a scene with joints: the joint step alone (it
    evaluates the force stages' compiled model at every Runge-Kutta stage
    itself, the start included).  Raises ValueError for what is not
    modelled."""
    why = unsupported_reason(model)
    if why:
        raise ValueError(why)
    return (JointFlight(model, forces),)


