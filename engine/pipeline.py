"""The step pipeline: assembled once from the scene's effects and settings,
run every step in the order of the seed notes' loop::

    forces -> integrate velocities -> collide (broad, narrow) -> solve
           -> integrate positions [-> time of impact]

Only what the scene calls for is built: no broad/narrow phase, solver or CCD
without 'contact'; no friction rows without 'friction' (the solver's
``friction`` flag); no gyroscopic stage without 'gyroscopic'; a force stage
only for an effect that is present (and non-zero somewhere).  Each stage has
the signature ``stage(model, state, ctx)`` and runs through the profile,
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
from physbench.engine import fused
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
    contact = model.has("contact") and (model.n >= 2 or model.n_statics > 0) and model.n > 0
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


#: the broad phases (whether it sweeps) whose fused steady step this
#: process compiled or loaded (:func:`_warm_steady`)
_STEADY_READY: set = set()


def _warm_steady(model: Model) -> None:
    """Compile (or load) the fused steady step (engine/steady.py) once per
    process and broad phase (the part of its argument types that follows
    the scene: engine.broadstage.uses_sap; the narrow phase's families do
    not change them, engine.collision.collide.family_table), at build like
    every kernel (engine/jit.py): a few steps of
    :func:`engine.steady.warm_scene_for` the model, with its settings; the
    seconds count as JIT time."""
    key = uses_sap(model)
    if key in _STEADY_READY:
        return
    _STEADY_READY.add(key)
    t0 = time.perf_counter()
    m = build_model(warm_scene_for(model), {**model.settings, "dt": 1 / 240})
    stages = build_pipeline(m)
    st = State.from_model(m)
    prof = Profile()
    add_jit_seconds(prof.jit_s)  # (the Profile took them: they stay pending for the caller's)
    for _ in range(4):
        step(m, st, stages, prof)
    # the loops over steps (engine/loop.py): the contact-free call's (it
    # fails on the first step's contacts), then the steady call's
    stages = build_pipeline(m)  # (a fresh solve stage: no steady solve kept)
    st = State.from_model(m)
    advance(m, st, stages, prof, 6, record_blocks(6, m.n))
    add_jit_seconds(time.perf_counter() - t0)


#: whether this process compiled or loaded the flight step (:func:`_warm_flight`)
_flight_ready = False


def _warm_flight(model: Model) -> None:
    """Compile (or load) the step of a scene without contact
    (engine/loop.py) once per process, as :func:`_warm_steady`: a few steps
    of :func:`engine.steady.warm_scene` without contact."""
    global _flight_ready
    if _flight_ready:
        return
    _flight_ready = True
    t0 = time.perf_counter()
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
    return ctx


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
    """One step dt stage by stage, as ``substeps`` substeps of
    h = dt / substeps.  A substep runs the stages in order; when the CCD
    stage reports an impact inside the substep, the substep is cut at the
    time of impact (refined on the integrated trajectory), the impact
    impulse is applied there and the rest of the substep runs the same way;
    likewise at a friction stop (a sliding or rolling contact coming to rest
    and not staying at rest, :func:`_substep`).
    A substep in which a non-round body would turn by more than
    ``max_rotation_per_step`` runs as equal parts that do not (see
    :func:`_parts`; counted as ``rotation_splits``).  ``resume``: the door
    ran the step as far as its CCD stage (:func:`engine.fused.advance`),
    which goes on from there.
    """
    ctx = context(model, state, profile)
    plan = _plan_of(model, ctx, stages)
    main, impact, max_events, turn = plan.main, plan.impact, plan.max_events, plan.turn
    for _ in range(model.substeps):
        parts = _parts(model, state, turn) if turn is not None and not resume else 1
        if parts > 1:
            profile.count("rotation_splits", parts - 1)
        for _ in range(parts):
            _substep(model, state, ctx, main, impact, max_events, model.h / parts, profile, plan.stops, resume)
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


def _parts(model: Model, state: State, turn) -> int:
    """Equal parts of the next substep such that no non-round body turns by
    more than the limit in one (from the angular velocities at its start).

    Contacts are found at the start pose and an impact is detected from
    each contact point's motion along the chord of its step; a point on a
    body turning by theta in a step strays from that chord by up to
    r (1 - cos(theta / 2)), so a spinning bar's end can dip into a thin slab
    between two steps that both see it clear (the bar of
    tunnelling.spinning_long_box at 80 rad/s and 1/30 s: 2.7 rad per step,
    17 cm deep in one phase of 16).  Rotation about the axis of a cylinder
    or capsule does not change the space it occupies and does not count."""
    limit, boxes, axisym = turn
    h = model.h
    w2 = max_turn_sq(state.w, state.q, boxes, axisym)
    theta = math.sqrt(w2) * h
    if not theta > limit:  # (NaN: a blown-up state is not split either)
        return 1
    return min(int(math.ceil(theta / limit)), MAX_PARTS)


#: friction stops (see :func:`_substep`) per (sub)step at most
MAX_STOPS = 8


def _substep(model: Model, state: State, ctx: Context, main, impact, max_events: int, h: float,
             profile: Profile, allow_stops: bool, resume: bool = False) -> None:
    """One (sub)step of length h, cut at every time of impact and at every
    friction stop.

    A friction stop (setting ``friction_stops``): the solver found a contact
    that slid (or rolled) at the start of the step at rest at its end, and
    where inside the step it came to rest (``ctx.stop``,
    :meth:`engine.solver.Rows.stop_times`).  The step is rerun to that time
    from the same start (same contacts, the warm start it began with) and
    committed there; the rest of the step then starts with the contact at
    rest, where static friction decides whether it stays or turns round.
    Without the cut the stopped contact sticks for the rest of the step
    whatever the forces, an error of first order in the step (a block thrown
    up a 35 degree slope slid back 6.6 mm behind the closed form at 1/240 s).

    ``resume``: the door (:func:`engine.fused.advance`) ran the (sub)step
    as far as its CCD stage and left the context as the stages before it
    would (``ctx.warm0`` the warm-start cache the step began with): the
    CCD stage runs, and the (sub)step goes on from there.
    """
    remaining = h
    events = 0
    stops = 0
    if not resume:
        ctx.missed_skip.clear()
    while True:
        if resume:
            resume = False
            warm0 = ctx.warm0
            profile.run(main[-1], model, state, ctx)  # the CCD stage, after what the door's call did
        else:
            warm0 = ctx.warm0 = state.warm
            ctx.event_mode = EventMode.EVENT if (impact is not None and events < max_events) else EventMode.SPECULATIVE
            ctx.begin(model, state, remaining)
            ctx.stop_allowed = allow_stops and stops < MAX_STOPS and events == 0
            for s in main:
                profile.run(s, model, state, ctx)
        if ctx.event is None and ctx.stop is not None:
            tau = ctx.stop
            state.warm = warm0
            _rerun_short(model, state, ctx, main, profile, tau)
            if ctx.impacts is None:
                _commit(model, state, ctx, tau)
                profile.count("friction_stops")
                stops += 1
                remaining -= tau
                if remaining <= 1e-12 * h:
                    break
                continue
            # an impact inside the shortened step (not seen in the whole
            # one): the step runs again whole, without the stop
            stops = MAX_STOPS
            state.warm = warm0
            continue
        if ctx.event is None:
            _commit(model, state, ctx, remaining)
            break
        clear = False
        if ctx.event.tau <= 1e-9 * h:
            tau = 0.0
        else:
            tau = refine_toi(model, state, ctx, main, profile)
            clear = ctx.toi.clear
            p = ctx.toi.pair
            if p.missed and tau <= 1e-9 * h:
                # a missed impact (ccd.missed_impacts) with no time to it:
                # the points it follows were in contact at the start already
                # -- a contact going on (a capsule rolling at 1/60 s brings
                # new material into contact, far from where it touched in
                # the body's frame), whose overlap is position correction's.
                # As an event it made no progress, 32 times over.  The
                # mini-step runs again without it.
                ctx.missed_skip.add(int(_pair_codes_abs(model, p.a, p.b, p.sidx)))
                profile.count("missed_dropped")
                state.warm = warm0
                continue
            _commit(model, state, ctx, tau)
        profile.run(impact, model, state, ctx)
        if clear:
            # the followed pair was still clear at the end of the
            # (mini-)step (the solve held it clear through other contacts):
            # the step ends here, and its solve warm-starts the next.
            # Restarting the next step cold made no pair persistent, so
            # gravity's approach made a resting box's clear corner an
            # impact again: one event a step, for as long as it lay there.
            # (The impact solve still runs: the rows the reruns left out
            # may end touching and approaching -- without it, mixed_bin at
            # 1/30 s sank 1.7 mm; 0.81 mm with it)
            break
        # the impact solve has stopped every touching approach (plastic
        # stops included): re-applying the cached resting forces over the
        # rest of the step would count them twice, and a solver with few
        # sweeps cannot take the excess back out (a Gauss-Seidel-only
        # column gained 16 x its energy); the rest of the step starts cold
        state.warm = None
        events += 1
        remaining -= tau
        if remaining <= 1e-12 * h:
            break


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
