"""The step: stages assembled once from the scene's effects and settings
(:func:`build_pipeline`), and the step loop that runs them, as named
stages::

    step = advance(1)
    advance(n):   fast path (engine.fused.advance: whole steps as compiled
                  calls while the scene is steady)  ->  staged step where it stops
    staged:       substeps x rotation parts (_parts) x _substep
    _substep:     stages  ->  friction stop | commit | impact event
    stages:       forces -> [implicit gyroscopic] -> integrate velocities
                  -> [energy-conserving rotation] -> broad phase -> narrow phase
                  -> solve -> integrate positions [-> CCD]

Only what the scene calls for is built: no broad/narrow phase, solver or CCD
without 'contact'; no friction rows without 'friction' (the solver's
``friction`` flag); no gyroscopic stage without 'gyroscopic'; a force stage
only for an effect that is present (and non-zero somewhere).  What the step
loop switches on is decided once per pipeline (:class:`Plan`).  Each stage
has the signature ``stage(model, state, ctx)`` and runs through the profile,
which counts calls and time per stage (see profile.py).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from physbench.engine.ccd import CCD, Impact, refine_toi
from physbench.engine.forces import force_stages
from physbench.engine.flight import max_turn_sq
from physbench.engine.jit import warm_up
from physbench.engine.integrate import EnergyConservingRotation, ImplicitGyroscopic, IntegratePositions, IntegrateVelocities
from physbench.engine.model import BOX, CAPSULE, CYLINDER, Model, build_model
from physbench.engine.collision import NarrowPhase
from physbench.engine.control import EventMode
from physbench.engine.broadstage import BroadPhase, uses_sap
from physbench.engine.penalty import PenaltyContacts
from physbench.engine.profile import Profile, Stage, add_jit_seconds
from physbench.engine.solver import Solve, _pair_codes_abs
from physbench.engine.state import Context, State
from physbench.engine import compile_share, fused
from physbench.engine.fused.steady import blocks_usable, record_blocks, warm_scene, warm_scene_for


def build_pipeline(model: Model) -> tuple[Stage, ...]:
    """The ordered stages for ``model`` (see module doc).  Compiles (or
    loads) the kernels its stages call first, so that no step does
    (:func:`engine.jit.warm_up`).  A scene with joints steps on the staged
    path: its force stages, then the joint step (engine/joints/)."""
    if model.joints is not None:
        from physbench.engine.joints.stage import joint_stages

        return joint_stages(model, force_stages(model))
    warm_up(model)
    forces = force_stages(model)
    stages: list[Stage] = list(forces)
    mode = model.setting("gyroscopic")
    gyro = model.has("gyroscopic") and np.any(~model.isotropic)
    if gyro and mode == "implicit":
        stages.append(ImplicitGyroscopic(model))
    stages.append(IntegrateVelocities(model, forces))
    if gyro and mode == "energy_conserving":
        stages.append(EnergyConservingRotation(model))
    contact = model.collides
    penalty = model.setting("contact_model") == "penalty"
    if contact:
        stages += [BroadPhase(model), NarrowPhase(model)]
        stages.append(PenaltyContacts(model) if penalty else Solve(model))
    stages.append(IntegratePositions(model))
    if contact and not penalty and model.setting("ccd") != "off":
        stages += [CCD(model), Impact(model)]
    fast = fused.build(model, stages)
    if isinstance(fast, fused.SteadyStep):
        _warm_steady(model)
    elif fast is not None:
        _warm_flight(model)
    return tuple(stages)


#: the (broad phase: whether it sweeps, integrator) pairs whose fused steady
#: step this process compiled or loaded (:func:`_warm_steady`)
_STEADY_READY: set = set()


def _warm_steady(model: Model) -> None:
    """Compile (or load) the fused steady step (engine/fused/steady.py) once per
    process, broad phase and integrator (the parts of its argument types
    that follow the scene: engine.broadstage.uses_sap, engine.flight.Method;
    the narrow phase's families do not change them,
    engine.collision.collide.family_table), at build like
    every kernel (engine/jit.py): a few steps of
    :func:`engine.fused.steady.warm_scene_for` the model, with its settings; the
    seconds count as JIT time."""
    key = (uses_sap(model), model.setting("integrator"))
    if key in _STEADY_READY:
        return
    _STEADY_READY.add(key)
    t0 = time.perf_counter()
    with compile_share.group(("steady",) + key):  # (another process compiling it: wait, then load)
        _steady_steps(model)
    add_jit_seconds(time.perf_counter() - t0)


def _steady_steps(model: Model) -> None:
    m = build_model(warm_scene_for(model), {**model.settings, "dt": 1 / 240})
    stages = build_pipeline(m)
    st = State.from_model(m)
    prof = Profile()
    add_jit_seconds(prof.jit_s)  # (the Profile took them: they stay pending for the caller's)
    for _ in range(4):
        step(m, st, stages, prof)
    # the loops over steps (engine/fused/steady.py): the contact-free call's (it
    # fails on the first step's contacts), then the steady call's
    stages = build_pipeline(m)  # (a fresh solve stage: no steady solve kept)
    st = State.from_model(m)
    advance(m, st, stages, prof, 6, record_blocks(6, m.n))


#: the integrators whose flight step this process compiled or loaded
#: (:func:`_warm_flight`)
_FLIGHT_READY: set = set()


def _warm_flight(model: Model) -> None:
    """Compile (or load) the step of a scene without contact
    (engine/fused/loop.py) once per process and integrator, as
    :func:`_warm_steady`: a few steps of
    :func:`engine.fused.steady.warm_scene` without contact."""
    key = model.setting("integrator")
    if key in _FLIGHT_READY:
        return
    _FLIGHT_READY.add(key)
    t0 = time.perf_counter()
    with compile_share.group(("flight_step", key)):
        inp = dataclasses.replace(warm_scene(), effects=frozenset({"gravity"}))
        m = build_model(inp, {**model.settings, "dt": 1 / 240})
        stages = build_pipeline(m)
        st = State.from_model(m)
        prof = Profile()
        add_jit_seconds(prof.jit_s)
        step(m, st, stages, prof)
        advance(m, st, stages, prof, 2, record_blocks(2, m.n))
    add_jit_seconds(time.perf_counter() - t0)


def prepare(model: Model, state: State, stages: tuple[Stage, ...], profile: Profile) -> Context:
    """Make at build what a fresh engine's first steps would make on first
    use, so that they pay nothing extra (~0.3-0.6 ms of Python on a short
    run otherwise): the state's context and the step's plan, the kept
    Packs of the start/commit and of the fused steady step, the narrow
    phase's and the CCD stages' colliders and kept arrays.  Each is the
    object the step would make (the same buffers, sizes and contents), so
    the bits do not change (tests/test_engine_prepare.py).  Returns the
    context."""
    ctx = context(model, state, profile)
    plan = _plan_of(model, ctx, stages)
    ctx.kept(state)
    prime = getattr(plan.fast, "prime", None)
    if prime is not None:
        prime(model, state, ctx)
    for s in stages:
        prime = getattr(s, "prime", None)
        if prime is not None:
            prime(model, state, ctx, plan.main)
    if isinstance(plan.fast, fused.SteadyStep):
        _prime_start(model, state, ctx, plan)
    return ctx


#: the context's attributes a (mini-)step's stages assign (each step sets
#: them anew before reading them); :func:`_prime_start` gives them back
_STEP_FIELDS = ("h", "event_mode", "stop_allowed", "event", "impacts", "stop", "ex", "eq", "ev", "ew", "eR", "warm0",
                "contacts", "rows", "pairs_i", "pairs_j", "plane_pairs", "sbox_pairs", "reuse_contacts")


def _prime_start(model: Model, state: State, ctx: Context, plan: "Plan") -> None:
    """At build, for a scene with a fused steady step: the first step's
    stages up to the solve run once on the start state and their results
    are dropped (the state's pose, velocities, ``t``, ``steps`` and warm
    cache, the context's per-step fields and the profile are as before).
    What stays is set-up: the narrow phase's contact buffers sized for the
    start's contacts, the solve's work views, topology, Rows and Packs, and
    the solve's kept steady solve (``Solve._fast``), so the door's first try
    is the steady call instead of a contact-free call that the start's
    contacts make fail, and that call's warm caches and packs
    (``SteadyStep.prime_steady``).  The first step still computes all of its physics
    (flight, broad and narrow phase, classification, direct start, sweeps):
    the steady call checks that its contacts are the kept solve's in number
    and graph, and any step it cannot run whole runs staged from its start,
    with the same bits (tests/test_engine_prepare.py::
    test_prepare_changes_no_bit, the fused/staged contract).  A stage that
    raises here primes nothing: the first step meets the error itself."""
    solve = plan.fast.solve
    saved = {k: getattr(ctx, k) for k in _STEP_FIELDS}
    warm, profile = state.warm, ctx.profile
    probe = ctx.profile = Profile()
    add_jit_seconds(probe.jit_s)  # (the Profile took them: they stay pending for the caller's)
    try:
        ctx.missed_skip.clear()
        ctx.warm0 = state.warm
        ctx.event_mode = EventMode.EVENT if plan.impact is not None and plan.max_events > 0 else EventMode.SPECULATIVE
        ctx.begin(model, state, model.h)
        ctx.stop_allowed = plan.stops
        for s in plan.main:
            s(model, state, ctx)
            if s is solve:
                break
    except Exception:  # noqa: BLE001 (the first step raises it again, where a failure is recorded)
        solve._fast = None
    finally:
        state.warm = warm
        ctx.profile = profile
        for k, v in saved.items():
            setattr(ctx, k, v)
        ctx.missed_skip.clear()
    plan.fast.prime_steady(model, state, ctx)


def context(model: Model, state: State, profile: Profile) -> Context:
    """The state's scratch context (``state.ctx``, created on first use)."""
    ctx = state.ctx
    if ctx is None:
        ctx = state.ctx = Context(model)
    ctx.profile = profile
    return ctx


def _commit(model: Model, state: State, ctx: Context, h: float) -> None:
    ctx.commit(state)
    state.t += h


def step(model: Model, state: State, stages: tuple[Stage, ...], profile: Profile) -> None:
    """Advance ``state`` by one step dt: :func:`advance` of one step."""
    advance(model, state, stages, profile, 1)


def advance(model: Model, state: State, stages: tuple[Stage, ...], profile: Profile, n: int, rec=None,
            progress: list | None = None) -> None:
    """``n`` steps: each through the fast path's door (engine/fused/,
    :func:`engine.fused.advance`: whole steps as compiled calls, the bits
    of the staged step), and where it stops, one :func:`staged` step.
    ``rec``: (pos, quat, vel, angvel) blocks (n, n_bodies, 3|4) that get the
    state after step i in row i, or None; ``progress``: a one-element list
    that holds the rows recorded so far (a failure in the middle loses no
    recorded frame)."""
    ctx = context(model, state, profile)
    if model.joints is not None and not profile.by_stage:
        # a scene with joints: n steps as one compiled call (engine/joints/stage.py)
        stages[-1].run_block(model, state, ctx, profile, n, rec, progress)
        return
    plan = _plan_of(model, ctx, stages)
    # (the door records into the blocks when its loops can write them;
    # else it steps one at a time, and each row is written here)
    direct = rec is None or blocks_usable(rec)
    k = 0
    while k < n:
        got, stop = fused.advance(model, state, ctx, plan, n - k if direct else 1,
                                  None if rec is None or not direct else tuple(a[k:] for a in rec))
        if got and not direct:
            _record(rec, k, state)
        k += got
        if progress is not None:
            progress[0] = k
        if k >= n:
            break
        if got and stop == fused.NONE:
            continue  # (it stopped before trying the next step: it may run it)
        staged(model, state, stages, profile, stop == fused.CCD)
        if rec is not None:
            _record(rec, k, state)
        k += 1
        if progress is not None:
            progress[0] = k


def _record(rec, k: int, state: State) -> None:
    rec[0][k] = state.x
    rec[1][k] = state.q
    rec[2][k] = state.v
    rec[3][k] = state.w


def staged(model: Model, state: State, stages: tuple[Stage, ...], profile: Profile, resume: bool = False) -> None:
    """One step dt stage by stage: ``substeps`` substeps of h = dt /
    substeps, each in equal parts where a non-round body would turn by more
    than ``max_rotation_per_step`` (:func:`_parts`, counted as
    ``rotation_splits``), each part one :func:`_substep`.  ``resume``: the
    door ran the step as far as its CCD stage (:func:`engine.fused.advance`),
    and the step goes on from there."""
    ctx = context(model, state, profile)
    plan = _plan_of(model, ctx, stages)
    for _ in range(model.substeps):
        parts = 1 if resume else _parts(model, state, plan.turn, profile)
        for _ in range(parts):
            _substep(model, state, ctx, plan, model.h / parts, profile, resume)
            resume = False
    state.steps += 1


def _plan_of(model: Model, ctx: Context, stages) -> "Plan":
    """The context's plan for ``stages`` (made once)."""
    plan = ctx.plan
    if plan is None or plan.stages is not stages:
        plan = ctx.plan = _plan(model, stages)
    return plan


@dataclass(frozen=True)
class Plan:
    """What the step loop decides once per pipeline (not per step):
    ``main`` the stages a (mini-)step runs, ``impact`` the impact stage or
    None, ``max_events`` the setting ``ccd_max_events``, ``turn`` the
    rotation split's limit (:func:`_turn_limit`, None: never split),
    ``stops`` whether friction stops are looked for."""

    stages: tuple
    main: tuple
    impact: Stage | None
    max_events: int
    turn: tuple | None
    stops: bool
    #: the scene's compiled step behind the door (:func:`engine.fused.build`:
    #: engine.fused.FlightStep or engine.fused.SteadyStep), or None
    fast: object = None
    #: when the door tries again after a failed try
    backoff: fused.Backoff = field(default_factory=fused.Backoff)


def _plan(model: Model, stages: tuple[Stage, ...]) -> Plan:
    turn = _turn_limit(model)
    return Plan(stages, tuple(s for s in stages if s.family != "impact"),
                next((s for s in stages if s.family == "impact"), None), int(model.settings["ccd_max_events"]),
                turn, bool(model.settings["friction_stops"]) and model.has("friction"),
                fused.build(model, stages, turn))


#: most parts a step is split into for fast rotation (a diverging run would
#: otherwise be split without end); 64 parts of 1 rad cover 10 turns a step
MAX_PARTS = 64


def _turn_limit(model: Model):
    """(limit rad, boxes (k,), axisymmetric bodies (k,)) when steps may be
    split for fast rotation (contact scenes with a limit > 0 and a body
    whose turning changes the space it occupies), else None."""
    limit = float(model.settings["max_rotation_per_step"])
    if limit <= 0 or not model.has("contact"):
        return None
    boxes = np.flatnonzero(model.shape == BOX)
    axisym = np.flatnonzero((model.shape == CAPSULE) | (model.shape == CYLINDER))
    if boxes.size == 0 and axisym.size == 0:
        return None  # spheres look the same at any orientation
    return limit, boxes, axisym


def _parts(model: Model, state: State, turn, profile: Profile) -> int:
    """Equal parts of the next substep such that no non-round body turns by
    more than the limit in one (from the angular velocities at its start);
    1 when ``turn`` (the plan's limit) is None.

    Contacts are found at the start pose and an impact is detected from
    each contact point's motion along the chord of its step; a point on a
    body turning by theta in a step strays from that chord by up to
    r (1 - cos(theta / 2)), so a spinning bar's end can dip into a thin slab
    between two steps that both see it clear (the bar of
    tunnelling.spinning_long_box at 80 rad/s and 1/30 s: 2.7 rad per step,
    17 cm deep in one phase of 16).  Rotation about the axis of a cylinder
    or capsule does not change the space it occupies and does not count."""
    if turn is None:
        return 1
    limit, boxes, axisym = turn
    h = model.h
    w2 = max_turn_sq(state.w, state.q, boxes, axisym)
    theta = math.sqrt(w2) * h
    if not theta > limit:  # (NaN: a blown-up state is not split either)
        return 1
    parts = min(int(math.ceil(theta / limit)), MAX_PARTS)
    profile.count("rotation_splits", parts - 1)
    return parts


#: friction stops (see :func:`_substep`) per (sub)step at most
MAX_STOPS = 8


@dataclass
class _Cut:
    """Where a (sub)step of length ``h`` stands: ``remaining`` s of it to
    run, the ``events`` (times of impact) and friction ``stops`` it was cut
    at so far."""

    h: float
    remaining: float
    events: int = 0
    stops: int = 0


def _substep(model: Model, state: State, ctx: Context, plan: "Plan", h: float, profile: Profile,
             resume: bool = False) -> None:
    """One (sub)step of length h, cut at every friction stop and at every
    time of impact: its named stages, in a loop until the (sub)step is
    committed whole::

        stages (forces ... CCD) -> friction stop | commit | impact event

    ``resume``: the door (:func:`engine.fused.advance`) ran the (sub)step
    as far as its CCD stage and left the context as the stages before it
    would (``ctx.warm0`` the warm-start cache the step began with): the
    CCD stage runs, and the (sub)step goes on from there.
    """
    cut = _Cut(h, h)
    if not resume:
        ctx.missed_skip.clear()
    while True:
        warm0 = _stages(model, state, ctx, plan, cut, profile, resume)
        resume = False
        if ctx.event is None and ctx.stop is not None:
            done = _friction_stop(model, state, ctx, plan, cut, warm0, profile)
        elif ctx.event is None:
            _commit(model, state, ctx, cut.remaining)
            done = True
        else:
            done = _impact_event(model, state, ctx, plan, cut, warm0, profile)
        if done:
            return


def _stages(model: Model, state: State, ctx: Context, plan: "Plan", cut: _Cut, profile: Profile, resume: bool):
    """The stages over the rest of the (sub)step from ``state`` (after the
    door's call: the CCD stage only).  Returns the warm-start cache the
    run began with."""
    main = plan.main
    if resume:
        profile.run(main[-1], model, state, ctx)  # the CCD stage, after what the door's call did
        return ctx.warm0
    warm0 = ctx.warm0 = state.warm
    ctx.event_mode = (EventMode.EVENT if (plan.impact is not None and cut.events < plan.max_events)
                      else EventMode.SPECULATIVE)
    ctx.begin(model, state, cut.remaining)
    ctx.stop_allowed = plan.stops and cut.stops < MAX_STOPS and cut.events == 0
    for s in main:
        profile.run(s, model, state, ctx)
    return warm0


def _friction_stop(model: Model, state: State, ctx: Context, plan: "Plan", cut: _Cut, warm0,
                   profile: Profile) -> bool:
    """Cut the (sub)step at a friction stop (setting ``friction_stops``):
    the solver found a contact that slid (or rolled) at the start of the
    step at rest at its end, and where inside the step it came to rest
    (``ctx.stop``, :meth:`engine.solver.Rows.stop_times`).  The step is
    rerun to that time from the same start (same contacts, the warm start
    it began with) and committed there; the rest of the step then starts
    with the contact at rest, where static friction decides whether it
    stays or turns round (a turnaround exact instead of first order in the
    step: tests/test_engine_friction.py).  Returns whether the (sub)step
    is done."""
    tau = ctx.stop
    state.warm = warm0
    _rerun_short(model, state, ctx, plan.main, profile, tau)
    if ctx.impacts is None:
        _commit(model, state, ctx, tau)
        profile.count("friction_stops")
        cut.stops += 1
        cut.remaining -= tau
        return cut.remaining <= 1e-12 * cut.h
    # an impact inside the shortened step (not seen in the whole
    # one): the step runs again whole, without the stop
    cut.stops = MAX_STOPS
    state.warm = warm0
    return False


def _impact_event(model: Model, state: State, ctx: Context, plan: "Plan", cut: _Cut, warm0,
                  profile: Profile) -> bool:
    """Cut the (sub)step at the time of impact the CCD stage reported
    (refined on the integrated trajectory, :func:`engine.ccd.refine_toi`),
    commit there and resolve the impact (the impact stage).  Returns
    whether the (sub)step is done."""
    h = cut.h
    clear = False
    if ctx.event.tau <= 1e-9 * h:
        tau = 0.0
    else:
        tau = refine_toi(model, state, ctx, plan.main, profile)
        clear = ctx.toi.clear
        p = ctx.toi.pair
        if p.missed and tau <= 1e-9 * h:
            # a missed impact (ccd.missed_impacts) with no time to it: the
            # points it follows were in contact at the start already -- a
            # contact going on, whose overlap is position correction's.  The
            # mini-step runs again without it.
            ctx.missed_skip.add(int(_pair_codes_abs(model, p.a, p.b, p.sidx)))
            profile.count("missed_dropped")
            state.warm = warm0
            return False
        _commit(model, state, ctx, tau)
    profile.run(plan.impact, model, state, ctx)
    if clear:
        # the followed pair was still clear at the end of the (mini-)step
        # (the solve held it clear through other contacts): the step ends
        # here, and its solve warm-starts the next (a cold start would
        # make a resting box's clear corner an impact again every step).
        # The impact solve still runs: the rows the reruns left out may
        # end touching and approaching.
        return True
    # the impact solve has stopped every touching approach (plastic stops
    # included): the rest of the step starts cold (re-applying the cached
    # resting forces would count them twice)
    state.warm = None
    cut.events += 1
    cut.remaining -= tau
    return cut.remaining <= 1e-12 * h


def _rerun_short(model: Model, state: State, ctx: Context, main, profile: Profile, tau: float) -> None:
    """Rerun the (mini-)step from ``state`` with length ``tau`` (shorter
    than the one just run), reusing its contacts (found with a margin that
    covers the longer motion): no broad or narrow phase, no CCD stage."""
    mode = ctx.event_mode
    ctx.begin(model, state, tau)
    ctx.event_mode = mode
    ctx.stop_allowed = False
    ctx.reuse_contacts = True
    try:
        for s in main:
            if s.family in ("broadphase", "narrowphase", "ccd"):
                continue
            profile.run(s, model, state, ctx)
    finally:
        ctx.reuse_contacts = False
