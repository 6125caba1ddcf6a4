"""Compile time kept apart from stepping.

The engine's compiled kernels (numba, ``cache=True``: compiled once per
machine and numba version, then loaded from the on-disk cache) are compiled
or loaded at their first call.  :func:`warm_up` makes that first call at
build, on a tiny problem with the same argument types as the step's, so no
step pays for it; the seconds it took are *JIT time*, reported by the next
:class:`engine.profile.Profile` as ``jit_s`` (and by the runner as
``timing.jit_s``, outside ``step_cpu_s`` and ``cpu_s_per_sim_s``).  Later
builds in the same process find the kernels ready and report 0.
"""

from __future__ import annotations

import contextlib
import time

import numpy as np

from physbench.engine import compile_share
from physbench.engine.flight import METHOD
from physbench.engine.forces import FORCES
from physbench.engine.profile import add_jit_seconds

#: the force stages' classes (engine/forces.py) by name
FORCE_KINDS = tuple(S.__name__ for S in FORCES)

#: the parts compiled (or loaded) in this process (:func:`parts`)
_READY: set = set()

#: the kernels a warm-up calls that only compiled code calls in a step
#: (phases.classify_stage: inside the fused steady step; the others inside
#: the solve's, the propagation's, the gyroscopic stage's and the free
#: flight's kernels): a cold cache compiles them with their group (so a
#: helper process can take them, engine/compile_share.py), a warm one does
#: not load them (tests/test_engine_jit.py::test_a_warm_build_loads_no_compiled_only_callee);
#: names under physbench.engine
CALLEES = ("contact.phases.classify_stage", "contact.linalg.lu_solve", "contact.linalg.inverse",
           "contact.linalg.solve_batch", "contact.prepare.normal_rows", "flight.start_pose")

#: a part's cold compile, about (CPU s on a 2-core x86-64: billiards.head_on's
#: solve ~43, time of impact ~16, rk4 flight ~14, sphere narrow phase ~9,
#: broad phase ~4): the order :func:`warm_up` takes them in, and what
#: :func:`cold_seconds` adds up
_COST = {"solve": 40.0, "steady": 20.0, "ccd": 15.0, "flight": 14.0, "penalty": 10.0, "narrow": 9.0,
         "flight_step": 8.0, "broad": 4.0, "gyro": 3.0, "force": 0.5}


def cold_seconds(todo) -> float:
    """About how many CPU seconds the parts of ``todo`` not yet in the
    on-disk cache take to compile (engine/compile_share.py's marks)."""
    return sum(_COST.get(p[0], 1.0) for p in todo if not compile_share.done(p))


@contextlib.contextmanager
def helped(inp, settings: dict, model):
    """Around a build's ``build_pipeline(model)`` (``model`` built from the
    scene input ``inp`` with the full ``settings``): on a cold cache (about
    compile_share.HELPER_MIN_S CPU s or more of ``model``'s parts left to
    compile), a helper process builds the same scene at once, taking the
    kernel groups from the other end (engine/compile_share.py); waited for
    at the end."""
    todo = () if model.joints is not None else [p for p in parts(model) if p not in _READY]
    helper = (compile_share.start_helper(inp, settings)
              if todo and cold_seconds(todo) >= compile_share.HELPER_MIN_S else None)
    try:
        yield helper
    finally:
        compile_share.end_helper(helper)


def parts(model=None) -> tuple:
    """The kernel groups ``model``'s stages call (the same decision as
    :func:`engine.pipeline.build_pipeline`'s): the free flight of the
    model's integrator always (its compiled code is the method's alone:
    engine.flight.Method), each
    force stage's own kernel (engine.forces.force_stages), the gyroscopic
    stage's; with
    contact the broad phase (with the sweep's kernels only where it sweeps,
    engine.broadstage.uses_sap), the narrow phase for the scene's shape-pair
    families (:func:`engine.collision.collide.families`), and the impulse
    solve and time-of-impact handling or the penalty contacts.  ``None``:
    every group, every family."""
    from physbench.engine.broadstage import uses_sap
    from physbench.engine.collision.collide import ALL_FAMILIES, families

    if model is None:
        return (tuple(("flight", m) for m in METHOD) + tuple(("force", k) for k in FORCE_KINDS)
                + (("gyro", "implicit"), ("gyro", "energy"))
                + (("solve",), ("broad", False), ("broad", True), ("narrow", ALL_FAMILIES), ("ccd",), ("penalty",)))
    from physbench.engine.forces import force_stages

    out = [("flight", model.setting("integrator"))] + [("force", type(s).__name__) for s in force_stages(model)]
    mode = model.setting("gyroscopic")
    if model.has("gyroscopic") and np.any(~model.isotropic) and mode != "explicit":
        out.append(("gyro", "implicit" if mode == "implicit" else "energy"))
    if model.collides:
        out += [("broad", uses_sap(model)),
                ("narrow", families(model.shape))]
        if model.setting("contact_model") == "penalty":
            out.append(("penalty",))
        else:
            out.append(("solve",))
            if model.setting("ccd") != "off":
                out.append(("ccd",))
    return tuple(out)


def fused_part(model) -> tuple | None:
    """The kernel group of the fused step a build of ``model`` compiles
    after its :func:`parts` (engine.pipeline.build_pipeline: the steady
    step's ``("steady", sweeps, integrator)``, the step without contact's
    ``("flight_step", integrator)``, engine/compile_share.py's keys), or
    None (joints, penalty contacts, substeps, Baumgarte correction, a force
    the fused steps do not cover: staged only).  The same decision as
    engine.fused.build's on the built stages
    (tests/test_engine_jit.py::test_the_fused_part_is_the_builds_fused_step)."""
    from physbench.engine.broadstage import uses_sap
    from physbench.engine.forces import force_stages

    if model.joints is not None or any(type(s) not in FORCES for s in force_stages(model)):
        return None
    if not model.collides:
        return ("flight_step", model.setting("integrator"))
    if (model.setting("contact_model") == "penalty" or model.substeps != 1
            or model.setting("position_correction") == "baumgarte"):
        return None
    return ("steady", uses_sap(model), model.setting("integrator"))


def warm_up(model=None) -> float:
    """Compile (or load from the cache) the kernels ``model`` needs
    (:func:`parts`; ``None``: all of them), each group once per process;
    returns the seconds spent (0.0 when all were done already)."""
    todo = [p for p in parts(model) if p not in _READY]
    if not todo:
        return 0.0
    t0 = time.perf_counter()

    def run(p: tuple) -> None:
        # a group in the on-disk cache already: only what Python calls is
        # loaded (the callees compiled into other kernels are not:
        # tests/test_engine_jit.py::test_a_warm_build_loads_no_compiled_only_callee)
        _warm_part(p, callees=not compile_share.done(p))
        _READY.add(p)

    # the costliest first (engine/compile_share.py: a helper process takes
    # them from the other end)
    compile_share.take(sorted(todo, key=lambda p: _COST.get(p[0], 0), reverse=True), run)
    dt = time.perf_counter() - t0
    add_jit_seconds(dt)
    return dt


def _warm_part(p: tuple, callees: bool = True) -> None:
    """Compile or load the kernel group ``p`` (:func:`parts`); ``callees``
    False: not the kernels only compiled code calls (:data:`CALLEES`), which
    a step never loads (their machine code is inside their callers')."""
    if p[0] == "flight":
        _warm_flight(p[1], callees)
    elif p[0] == "force":
        _warm_force(p[1])
    elif p[0] == "gyro":
        _warm_gyro(p[1])
    elif p[0] == "solve":
        _warm_solve(callees)
    elif p[0] == "broad":
        from physbench.engine import broadstage

        broadstage.warm_up(p[1])
    elif p[0] == "narrow":
        from physbench.engine.collision import dispatch

        dispatch.warm_up(p[1])
    elif p[0] == "ccd":
        from physbench.engine import ccd

        ccd.warm_up()  # the time-of-impact search's and impact solver's kernels
    elif p[0] == "penalty":
        from physbench.engine import penalty

        penalty.warm_up()
    else:  # pragma: no cover
        raise ValueError(f"unknown kernel group {p!r}")


def warm_collision(fams: list | None = None) -> None:
    """The broad phase's, the narrow phase's (for each families tuple of
    ``fams``, engine.collision.collide.families; None: every family), the
    time-of-impact search's, the impact solver's and the penalty contacts'
    kernels (the collision half of the warm-up: ``python -m
    physbench.engine`` compiles the two halves in two processes at once,
    engine/__main__.py)."""
    from physbench.engine.collision.collide import ALL_FAMILIES

    for p in ([("broad", False), ("broad", True)] + [("narrow", f) for f in (fams or [ALL_FAMILIES])]
              + [("ccd",), ("penalty",)]):
        _warm_part(p)


def warm_dynamics(integrator: str) -> None:
    """The contact solve's, the free flight's, the force stages' and the
    gyroscopic stages' kernels (the other half of :func:`warm_up` with no
    model), the flight of ``integrator`` only (an engine.flight.METHOD
    name: ``python -m physbench.engine`` passes the default, the one every
    shipped scenario and every fused step it compiles uses; another
    integrator's flight compiles at its scene's build,
    engine.flight.Method)."""
    _warm_solve()
    for p in parts(None):
        if p[0] in ("force", "gyro") or p == ("flight", integrator):
            _warm_part(p)


def _warm_solve(callees: bool = True) -> None:
    """The contact solve's kernels (and the contact topology's); with
    ``callees``, also those only compiled code calls (:data:`CALLEES`)."""
    from physbench.engine.contact import gauss_seidel, linalg, prepare, warm
    from physbench.engine.contact.packs import Bodies, Cache, ContactArrays, NormalRows, Patches, PatchSet, RowArrays
    from physbench.engine.pack import Pack

    m, nb = 3, 2  # three rows on two bodies and the world (index 2)
    J = np.ones((m, 12))
    M = np.full((m, 12), 0.1)
    a = np.array([0, 0, 1], np.int64)
    b = np.array([1, 2, 2], np.int64)
    r = np.ones(m)
    act = np.arange(m, dtype=np.int64)
    K = linalg.normal_matrix(J, M, a, b, nb)
    linalg.lcp_residual(linalg.k_times(J, M, a, b, nb, r) - r, r)
    linalg.dense_active_set(K, r, act, 1e-10, 2)
    linalg.spd_solve_sparse(J, M, a, b, nb, r, act, 1e-10)
    if callees:
        linalg.lu_solve(K + np.eye(m), r)
        linalg.inverse(K + np.eye(m))
        linalg.solve_batch(np.tile(np.eye(3), (2, 1, 1)), np.ones((2, 3)))  # (in place)
    linalg.islands(nb, a, b)
    from physbench.engine.contact.rows import _greedy_colours

    _greedy_colours(a, b, nb, np.empty(m, np.int64))
    U = np.zeros((nb + 1, 6))
    ab = np.stack([a, b], axis=1)
    gauss_seidel.apply_rows(U, ab, M, r, nb)
    npch = 2
    pab = np.array([[0, 1], [0, 2]], np.int64)
    pid = np.array([0, 1, 1], np.int64)
    Jt = np.ones((npch, 5, 12))
    Mt = np.full((npch, 5, 12), 0.1)
    lam_t = np.zeros((npch, 5))
    gauss_seidel.apply_patches(U, pab, Mt, lam_t, nb)
    zb = np.zeros(npch, np.bool_)
    z2 = np.zeros((npch, 2))
    gauss_seidel.iterate(U, NormalRows(ab=ab, J=J, M=M, mn=np.ones(m), lam=np.zeros(m), target=r),
                         Patches(pab=pab, pid=pid, Jt=Jt, Mt=Mt, mt=np.ones((npch, 5)), lam_t=lam_t, mu=np.ones(npch),
                                 rt=np.ones(npch), mur=np.ones(npch), pin_t=zb, dir_t=z2, pin_r=zb, dir_r=z2),
                         True, 2, 1e-7, nb, np.empty(gauss_seidel.work_size(m, npch, 5)))
    gauss_seidel.iterate_normal(U, ab, J, M, np.ones(m), np.zeros(m), r, 2, 1e-7, nb, np.empty(m))
    # preparation and warm start: two bodies and the world, three contacts
    # (the model's arrays are read-only: ``ro``, the types the step passes)
    X = np.zeros((nb, 3))
    R0 = np.tile(np.eye(3), (nb, 1, 1))
    Iinv = np.tile(np.eye(3), (nb + 1, 1, 1))
    im = _ro(np.ones(nb + 1))
    br = _ro(np.ones(nb))
    P3 = np.ones((m, 3))
    z3 = np.zeros(m)
    vn = np.zeros((3, m))
    tb = np.zeros(m, np.bool_)
    codes = np.zeros(m, np.int64)
    # (prepare.classify: compiled by phases.classify_stage's warm-up, the
    # same argument types)
    lm = np.empty((m, 3))
    if callees:
        prepare.normal_rows(X, Iinv, im, R0, True, a, b, P3, P3, act, nb, J, M, r.copy(), lm)
    P = np.zeros((npch, 3))
    t = np.zeros((npch, 2, 3))
    bodies = Bodies(X=X, Iinv=Iinv, inv_mass=im, R0=R0)
    cs = ContactArrays(a=a, b=b, sidx=-np.ones(m, np.int64), point=P3, normal=P3, gap=z3, e=z3.copy())
    ps = PatchSet(pid=pid, pa=pab[:, 0].copy(), pb=pab[:, 1].copy(), cnt=np.ones(npch), mus=np.ones(npch))
    for nr in (3, 5):
        Jt5 = np.zeros((npch, nr, 12))
        out = RowArrays(J=J, M=M, mn=r.copy(), loc=lm, lam_n=r.copy(), target=r.copy(), P=P, N=P.copy(),
                        rt=np.zeros(npch), t=t, Jt=Jt5, Mt=Jt5.copy(), mt=np.zeros((npch, nr)),
                        lam_t=np.zeros((npch, nr)), slip=zb.copy(), mu=np.ones(npch))
        prepare.rows(bodies, True, cs, act, nb, out, ps, True, nr == 5)
        prepare.patch_velocity(Jt5, U, pab, 0, 2, z2.copy())
        prepare.sliding(Jt5, U, pab, np.ones(npch), 1e-4, z2.copy(), zb.copy())
        prepare.stop_candidate(pid, r, Jt5, U, pab, z2, 1e-4, nr == 5, z2, np.ones(npch), 1e-4)
    e0 = np.zeros(0)
    e3 = np.zeros((0, 3))
    ei = np.zeros(0, np.int64)
    prepare.rows(bodies, True, cs, act, nb,
                 RowArrays(J=J, M=M, mn=r.copy(), loc=lm, lam_n=r.copy(), target=r.copy(), P=e3, N=e3, rt=e0,
                           t=np.zeros((0, 2, 3)), Jt=np.zeros((0, 3, 12)), Mt=np.zeros((0, 3, 12)), mt=e3, lam_t=e3,
                           slip=np.zeros(0, np.bool_), mu=e0),
                 PatchSet(pid=ei, pa=ei, pb=ei, cnt=e0, mus=e0), False, False)
    prepare.targets(act, tb, vn, z3, z3, 0.01, 0.5, 0.01, 0.2, 1e-4, r.copy(), r.copy())
    lt = np.zeros((npch, 3))
    cache = Pack(Cache(code=codes, loc=lm, fn=z3, pairs=codes.copy(), ft=P3, tw=z3.copy(), rr=P3.copy(), touch=tb))
    warm.match(codes, lm, a, br, cache, 0.01, r.copy(), True, False, pid, t, lt, zb.copy())
    warm.store(act, codes, lm, r, tb, act[:npch].copy(), act[:npch].copy(), True, False, lt, t, 0.01, cache)
    _warm_phases(nb, ab, a, b, J, M, r, codes, lm, br, pab, pid, t, tb, callees)
    from physbench.engine.contact import topology

    topology.warm_up()


def _warm_phases(nb, ab, a, b, J, M, r, codes, loc, br, pab, pid, t, tb, callees: bool = True) -> None:
    """The solve's compiled calls from Python (engine/contact/phases.py):
    ``relax`` (the phase-by-phase path's) and the stage's fused calls
    (``solve_contacts`` and the kernels it calls are compiled into those,
    never called from Python: no warm-up of their own)."""
    from physbench.engine.contact import phases

    m = r.size
    V = np.zeros((nb + 1, 3))
    U = np.zeros((nb + 1, 6))
    phases.relax(V, V.copy(), U, ab, J, M, np.ones(m), np.zeros(m), r, 2, 1e-7, nb, np.empty(m))
    _warm_stage(nb, ab, a, b, J, M, r, codes, loc, br, pab, pid, t, tb, callees)


def _warm_stage(nb, ab, a, b, J, M, r, codes, loc, br, pab, pid, t, tb, callees: bool = True) -> None:
    """The solve stage's one compiled call (phases.solve_stage) with its
    packs built by the stage's own helpers (engine/solver.py), with and
    without friction and rolling; with ``callees`` the fused steady step's
    whole solve stage (phases.classify_stage) too."""
    from types import SimpleNamespace

    from physbench.engine import solver
    from physbench.engine.contact import phases
    from physbench.engine.contact.packs import Cache, Classified, ContactArrays, Pose, Settings
    from physbench.engine.contact.scratch import Scratch
    from physbench.engine.pack import Pack

    m, npch = r.size, pab.shape[0]
    V = np.zeros((nb + 1, 3))
    X = np.zeros((nb, 3))
    R0 = np.tile(np.eye(3), (nb, 1, 1))
    Iinv = np.tile(np.eye(3), (nb + 1, 1, 1))
    kc = Pack(Pose(X=X, Iinv=Iinv, R0=R0, V=V, W=V.copy(), V0=X.copy(), W0=X.copy(), Vp=V.copy(), Wp=V.copy(),
                   inv_mass=_ro(np.ones(nb + 1)), bound_radius=br))
    f1 = np.ones(npch)
    topo = SimpleNamespace(ab=ab, a=a, b=b, pid=pid, pa=pab[:, 0].copy(), pb=pab[:, 1].copy(), cnt=f1.copy(),
                           pab=pab, codes=codes, code_order=np.arange(m, dtype=np.int64),
                           code_first=np.arange(npch, dtype=np.int64), uniq_pid=np.arange(npch, dtype=np.int64),
                           mus=f1.copy(), muk=f1.copy(), mur=None, np=npch)
    cache = Pack(Cache(code=codes, loc=loc, fn=r, pairs=codes[:npch].copy(), ft=loc[:npch].copy(), tw=f1.copy(),
                       rr=loc[:npch].copy(), touch=tb))
    out = Pack(Cache(code=codes.copy(), loc=loc.copy(), fn=r.copy(), pairs=codes[:npch].copy(), ft=loc[:npch].copy(),
                     tw=f1.copy(), rr=loc[:npch].copy(), touch=tb.copy()))
    vn = np.zeros((3, m))
    for friction, rolling in ((True, False), (True, True), (False, False)):
        k = npch if friction else 0
        views = solver._take_stage(Scratch(), nb, m, k, 5 if rolling else 3, friction,
                                   solver._direct_size(True, nb, m, 0))
        kt, kw = Pack(solver._topology_items(topo, friction, rolling)), Pack(solver._work_items(views, friction))
        s = Settings(n_statics=0, lever=0.5, thr=0.01, beta=0.2, slop=1e-4, friction=friction, rolling=rolling,
                     direct=True, resting=1e-5, max_rows=400, passes=4, slip_tol=1e-4, iterations=2, relax_on=True)
        kk = Pack(ContactArrays(a=a, b=b, sidx=-np.ones(m, np.int64), point=loc.copy(), normal=loc.copy(), gap=r.copy(),
                                e=r.copy()))
        phases.solve_stage(kc, kt, kw, cache, out, kk, a, tb, vn, 0.01, s, True, True)
        if not callees:
            continue
        # the whole stage of a steady step (classification first)
        kx = Pack(Classified(UL=X.copy(), UA=X.copy(), vn=vn, touching=tb.copy(), impact=tb.copy(), codes=codes.copy()))
        phases.classify_stage(kc, kx, kt, kw, cache, out, kk, codes.copy(), a, 0.01, s, True, True, True, True)


def _flight_arrays(nb: int = 2):
    from physbench.engine import flight

    x = np.zeros((nb, 3))
    q = np.zeros((nb, 4))
    q[:, 0] = 1.0
    idx = np.arange(nb, dtype=np.int64)
    I = np.array([[1.0, 2.0, 3.0]] * nb)
    z1, z3, zi = np.zeros(0), np.zeros((0, 3)), np.zeros(0, np.int64)
    springs = flight.ForceModel(z3, np.ones(nb), np.ones(nb), np.array([0], np.int64), np.array([-1], np.int64),
                                np.zeros((1, 3)), np.ones((1, 3)), np.ones(1), np.ones(1), np.ones(1), idx, I)
    plain = flight.ForceModel(np.ones((nb, 3)), z1, z1, zi, zi, z3, z3, z1, z1, z1, zi, z3)
    return x, q, np.ones((nb, 3)), np.zeros((nb, 3, 3)), idx, I, plain, springs


def _warm_flight(method: str, callees: bool = True) -> None:
    """The free-flight kernels (engine/flight.py) on two bodies: the
    integrator ``method`` (an engine.flight.METHOD name; the force kernels
    are compiled into it), the position update, the start and commit of a
    (mini-)step, the turn limit and the end-pose check."""
    from physbench.engine import flight, state
    from physbench.engine.geometry import EndPose, Pairs
    from physbench.engine.pack import Pack

    nb = 2
    x, q, v, R, idx, I, plain, springs = _flight_arrays(nb)
    Iinv = np.zeros((nb + 1, 3, 3))
    inv_I = np.ones((nb, 3))
    if callees:  # (compiled into begin_step: state._begin_packed)
        flight.start_pose(q, np.ones((nb, 3)), R, Iinv)
    vw1 = np.zeros((nb + 1, 3))
    kept = Pack(state.StepArrays(x=x.copy(), q=q.copy(), v=v.copy(), w=v.copy(), inv_I=inv_I, x1=x.copy(), q1=q.copy(),
                                 V=vw1.copy(), W=vw1.copy(), F=v.copy(), T=v.copy(), vp=vw1.copy(), wp=vw1.copy(),
                                 R0=R.copy(), Iinv0=Iinv.copy()))
    state._begin_packed(kept)  # Context.begin and .commit
    state._commit_packed(kept)
    F = np.zeros((nb, 3))
    vw = np.zeros((nb + 1, 3))
    for fm in (plain, springs):  # (one signature: the same types)
        # (the free-flight stage's one call, engine.integrate.IntegrateVelocities)
        ig = flight.Integrator(method=flight.Method(METHOD[method]), has_forces=True, constant=False, torque=True,
                               fm=fm, inv_m=np.ones(nb), inv_I=inv_I, lever=0.5)
        flight.fly_packed(kept, Pack(flight.Flight(ig=ig, V=vw[:nb], W=vw[:nb], v_free=F.copy(), w_free=F.copy(),
                                                   w0=F.copy(), T_mean=F.copy(), u_lin=F.copy(), u_ang=F.copy(),
                                                   work=np.zeros((flight.WORK_SLABS, nb, 3)),
                                                   work_q=np.zeros((2, nb, 4)), vp=vw[:nb], wp=vw[:nb])), 0.01)
    flight.integrate_positions(x.copy(), q.copy(), vw[:nb], vw[:nb], v, v, vw[:nb], vw[:nb], 0.01, 0.5)
    flight.max_turn_sq(v, q, idx, idx)
    zb = np.zeros(nb, np.bool_)
    for fast in (False, True):
        flight.end_pose_pairs(x, q, x.copy(), q.copy(), _ro(np.ones(nb)), 0.1, fast, zb,
                              Pairs(pi=idx, pj=idx, bp=idx, pk=idx, bs=idx, sk=idx),
                              EndPose(ci=idx.copy(), cj=idx.copy(), cbp=idx.copy(), cpk=idx.copy(), cbs=idx.copy(),
                                      csk=idx.copy(), sw=np.zeros(nb), R1=R.copy()))


def _warm_force(kind: str) -> None:
    """The force stage ``kind``'s own kernel (engine.forces.FORCES: the
    stage's ``warm``), as the stage calls it (C-contiguous arrays of the
    context)."""
    nb = 2
    x, q, v, R, idx, I, plain, springs = _flight_arrays(nb)
    next(S for S in FORCES if S.__name__ == kind).warm(x, R, v, np.zeros((nb, 3)), np.zeros((nb, 3)))


def _warm_gyro(mode: str) -> None:
    """The gyroscopic stage's kernel (engine/gyroscopic.py): the implicit
    update or the energy-conserving rotation."""
    from physbench.engine import gyroscopic as G
    from physbench.engine.pack import Pack

    nb = 2
    x, q, v, R, idx, I, plain, springs = _flight_arrays(nb)
    vw = np.zeros((nb + 1, 3))
    if mode == "implicit":
        G.implicit_gyroscopic(idx, I, R, vw, 0.01, *G.implicit_work(nb))
    else:
        F = np.zeros((nb, 3))
        gy = G.Gyro(G.ENERGY, idx, I, 1.0 / I, I.copy(), G.YOSHIDA, float(G.YOSHIDA_MAX), *G.energy_work(nb),
                    *G.implicit_work(0))
        G.energy_rotation_packed(Pack(gy), R, F, v, q, 0.01, 0.5, q.copy(), vw, v.copy(), v.copy())


def _ro(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a
