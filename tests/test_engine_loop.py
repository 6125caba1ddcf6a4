"""Part of the contract between the staged and the fused step (stated in
tests/test_engine_steady.py): steps as compiled calls (engine/fused/):
several steps in one call (``pipeline.advance``) give the same bits,
frames and bookkeeping as one ``pipeline.step`` per step; the contact-free
step of a contact scene and the step of a scene without contact are one
call each, with the bits of the step stage by stage."""

import numpy as np
import pytest

from physbench.adapters.reference import ReferenceAdapter, engine_for, scene_input
from physbench.contract.scene import load_scene
from physbench.engine import default_settings, pipeline
from physbench.engine.fused import SteadyStep
from physbench.engine.fused.loop import FLIGHT_NAME
from physbench.engine.fused.steady import FREE_NAME, NAME
from physbench.harness.bench import column_scene


def _state(eng):
    s = eng.state
    return [a.copy() for a in (s.x, s.q, s.v, s.w)]


def _per_step(scene, settings, steps):
    """One pipeline.step per step, each step's state recorded."""
    eng = engine_for(scene, settings)
    frames = []
    for _ in range(steps):
        pipeline.step(eng.model, eng.state, eng.stages, eng.profile)
        frames.append(_state(eng))
    return eng, [np.array([f[i] for f in frames]) for i in range(4)]


def _advanced(scene, settings, steps, chunks=(7, 1, 50)):
    """pipeline.advance over blocks of the given lengths (in turn), recording."""
    eng = engine_for(scene, settings)
    nb = eng.model.n
    rec = (np.full((steps, nb, 3), np.nan), np.full((steps, nb, 4), np.nan), np.full((steps, nb, 3), np.nan),
           np.full((steps, nb, 3), np.nan))
    k, i = 0, 0
    while k < steps:
        m = min(chunks[i % len(chunks)], steps - k)
        done = [0]
        pipeline.advance(eng.model, eng.state, eng.stages, eng.profile, m, tuple(a[k:k + m] for a in rec), done)
        assert done[0] == m
        k += m
        i += 1
    return eng, list(rec)


def _bookkeeping(eng):
    """What must come out as with one step per step: the profile's calls
    and counters, time and steps, the warm-start cache (its pool slot and
    contents), the contacts, the backoff."""
    p = eng.profile
    s = eng.state
    ctx = s.ctx
    plan = ctx.plan
    out = {"calls": dict(p.calls), "counters": dict(p.counters), "t": s.t, "steps": s.steps}
    if s.warm is not None:
        pool = plan.fast.solve._warm if isinstance(plan.fast, SteadyStep) else None
        slot = [i for i, c in enumerate(pool._cache) if c is s.warm] if pool is not None else None
        out["warm"] = (slot, [a.tobytes() for a in s.warm.packed])
    else:
        out["warm"] = None
    c = ctx.contacts
    out["contacts"] = None if c is None else (c.m, c.gap.tobytes())
    out["backoff"] = (plan.backoff.wait, plan.backoff.span, plan.backoff.what)
    if isinstance(plan.fast, SteadyStep):
        out["steady"] = plan.fast.solve._fast is not None
    return out


SCENES = [
    ("column", lambda: column_scene(10), {}, 300),
    ("stacking.column_5", None, {}, 240),
    ("friction.block_slides", None, {}, 240),
    ("friction.box_slides_to_rest", None, {}, 240),
    ("friction.ball_rolls", None, {}, 240),
    ("billiards.ball_drop_bounce", None, {}, 480),
    ("billiards.head_on", None, {}, 120),
    ("billiards.head_on", None, {"dt": 0.008}, 60),
    ("billiards.newtons_cradle", None, {}, 240),
    ("stacking.mixed_bin", None, {}, 120),
    ("gyroscopic.dzhanibekov", None, {}, 240),
    ("gyroscopic.dzhanibekov", None, {"gyroscopic": "implicit"}, 120),
    ("gyroscopic.dzhanibekov", None, {"gyroscopic": "explicit", "integrator": "heun", "substeps": 2}, 120),
    ("column", lambda: column_scene(10), {"integrator": "semi_implicit_euler", "ccd": "toi"}, 200),
]


@pytest.mark.parametrize("sid,make,settings,steps", SCENES, ids=[f"{s[0]}-{i}" for i, s in enumerate(SCENES)])
def test_advance_gives_the_bits_frames_and_bookkeeping_of_one_step_per_step(sid, make, settings, steps):
    scene = make() if make is not None else load_scene(sid)
    a, fa = _per_step(scene, settings, steps)
    b, fb = _advanced(scene, settings, steps)
    for x, y in zip(fa, fb):
        assert np.array_equal(x, y)  # every recorded frame, bit for bit
    for x, y in zip(_state(a), _state(b)):
        assert np.array_equal(x, y)
    ka, kb = _bookkeeping(a), _bookkeeping(b)
    assert ka == kb


@pytest.mark.parametrize("sid,settings,steps", [
    ("billiards.head_on", {}, 240),
    ("billiards.ball_drop_bounce", {}, 480),
    ("friction.ball_rolls", {}, 240),
    ("gyroscopic.dzhanibekov", {}, 240),
    ("gyroscopic.dzhanibekov", {"gyroscopic": "implicit", "integrator": "midpoint"}, 240),
    ("forces.drag_linear_fall", {}, 120),
])
def test_compiled_paths_give_the_staged_bits(sid, settings, steps):
    scene = load_scene(sid)
    fused = engine_for(scene, settings)
    fused.step(steps)
    staged = engine_for(scene, settings)
    staged.profile.by_stage = True
    staged.step(steps)
    for x, y in zip(_state(fused), _state(staged)):
        assert np.array_equal(x, y)
    p = staged.profile.as_dict()
    assert NAME not in p and FREE_NAME not in p and FLIGHT_NAME not in p


@pytest.mark.parametrize("sid,name,share", [
    ("billiards.head_on", FREE_NAME, 0.8),  # free flight before and after the impact
    ("billiards.ball_drop_bounce", FREE_NAME, 0.4),  # the flights between bounces (then it rests: steady)
    ("gyroscopic.dzhanibekov", FLIGHT_NAME, 1.0),  # no contact at all
    ("forces.drag_linear_fall", FLIGHT_NAME, 1.0),
])
def test_contact_free_and_no_contact_steps_are_one_call(sid, name, share):
    scene = load_scene(sid)
    eng = engine_for(scene, {})
    steps = int(round(scene.duration / scene.dt))
    eng.step(steps)
    p = eng.profile.as_dict()
    assert p[name]["calls"] >= share * steps
    if name == FLIGHT_NAME:
        # the stages the call runs count their runs
        assert p["integrate_velocities"]["calls"] == steps * eng.model.substeps


def test_steady_steps_run_many_to_a_compiled_call(monkeypatch):
    """A resting column steps stage by stage (pipeline.staged) only where
    a step is not steady: 300 steps, a handful of staged steps."""
    eng = engine_for(column_scene(10), {})
    calls = [0]
    real = pipeline.staged

    def counting(*a, **k):
        calls[0] += 1
        return real(*a, **k)

    monkeypatch.setattr(pipeline, "staged", counting)
    eng.step(300)
    assert eng.profile.as_dict()[NAME]["calls"] >= 290
    assert calls[0] <= 10


def test_a_failure_in_a_block_loses_no_recorded_frame(monkeypatch):
    """step_record's block_done counts the rows written by the compiled
    loop before a step that raised (the head-on impact's step runs stage
    by stage: pipeline.staged), and those rows are the per-step loop's."""
    scene = load_scene("billiards.head_on")
    steps = int(round(scene.duration / scene.dt))
    ref, frames = _per_step(scene, {}, steps)
    a = ReferenceAdapter()
    a.build(scene, default_settings(scene_input(scene)))
    real = pipeline.staged

    def boom(*args, **kw):
        raise RuntimeError("boom")

    monkeypatch.setattr(pipeline, "staged", boom)
    nb = scene.n_bodies
    blocks = (np.full((steps, nb, 3), np.nan), np.full((steps, nb, 4), np.nan), np.full((steps, nb, 3), np.nan),
              np.full((steps, nb, 3), np.nan))
    with pytest.raises(RuntimeError):
        a.step_record(steps, *blocks)
    k = a.block_done
    assert 0 < k < steps
    for x, y in zip(blocks, frames):
        assert np.array_equal(x[:k], y[:k])
        assert np.isnan(x[k:]).all()
    monkeypatch.setattr(pipeline, "staged", real)


def test_backoff_waits_unless_the_staged_step_kept_another_contact_graph():
    """engine.fused.Backoff: a failed try waits 1, 2, 4 ... steps while the
    tries of the same call keep failing; only the first wait of a run of
    failures is skipped, and only when the kept steady solve (its contact
    graph) is another than the one the failed try was made with."""
    from physbench.engine.fused import Backoff

    g1, g2, g3 = object(), object(), object()
    b = Backoff()
    b.failed("steady", g1)
    assert not b.ready("steady", g1)  # the same graph: wait 1
    assert b.ready("steady", g1)
    b = Backoff()
    b.failed("steady", g1)
    assert b.ready("steady", g2)  # a new graph: at once
    b.failed("steady", g2)  # it failed again: wait 2, whatever the graph
    assert (b.span, b.wait) == (2, 2)
    assert not b.ready("steady", g3) and not b.ready("steady", g1)
    assert b.ready("steady", g3)
    b = Backoff()
    b.failed("steady", g1)
    assert not b.ready("steady", None)  # no steady solve kept: wait
    b = Backoff()
    b.failed("free", None)
    assert b.ready("steady", g1)  # another call: at once, as before
    b.passed()
    assert (b.span, b.kept) == (0, None)


def test_backoff_retries_at_once_after_a_new_contact_graph(monkeypatch):
    """The sliding block (dt 0.064, rk4, no friction stops) gains its
    speculative contacts (4 -> 8) at step 7: the steady call fails there
    and the staged step keeps the new graph's solve; the next step is the
    steady call again, not a second staged step (measured before: two
    staged steps, ~145 us more for the second)."""
    eng = engine_for(load_scene("friction.block_slides"),
                     {"dt": 0.064, "integrator": "rk4", "friction_stops": False})
    staged = []
    real = pipeline.staged

    def counting(model, state, *a, **k):
        staged.append(state.steps)
        return real(model, state, *a, **k)

    monkeypatch.setattr(pipeline, "staged", counting)
    eng.step(31)
    assert staged == [6]  # (steps done before it: the 7th step, where the graph changed)
    assert eng.state.ctx.contacts.m == 8
    assert eng.profile.as_dict()[NAME]["calls"] >= 30
