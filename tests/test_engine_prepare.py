"""What a fresh engine's first steps made on first use is made at build
(engine.pipeline.prepare, called by the reference adapter): the context, the
plan, the kept Packs, the colliders of the narrow phase and of the CCD
stages.  Pinned here: after the adapter's build, stepping through an impact
event (billiards.head_on) builds no Collider, no Context and no new plan,
and the results are the bits of an engine that made them on first use."""

import numpy as np

from physbench.adapters.reference import ReferenceAdapter
from physbench.contract.scene import load_scene


def _spy(monkeypatch, cls, name="__init__"):
    calls = []
    orig = getattr(cls, name)

    def wrapped(self, *a, **k):
        calls.append(1)
        return orig(self, *a, **k)

    monkeypatch.setattr(cls, name, wrapped)
    return calls


def test_build_makes_what_the_first_event_step_used(monkeypatch):
    from physbench.engine import pipeline
    from physbench.engine.collision.dispatch import Collider
    from physbench.engine.state import Context

    sc = load_scene("billiards.head_on")
    st = {"dt": 0.032, "integrator": "rk4"}
    ad = ReferenceAdapter()
    ad.build(sc, ReferenceAdapter.resolve_settings(sc, st))
    ctx = ad.state.ctx
    assert ctx.plan is not None and ctx.ccd.collider is not None and ctx.ccd.geometry is not None
    colliders = _spy(monkeypatch, Collider)
    contexts = _spy(monkeypatch, Context)
    plans = []
    orig_plan = pipeline._plan
    monkeypatch.setattr(pipeline, "_plan", lambda *a: plans.append(1) or orig_plan(*a))
    ad.step(16)
    assert ad.stages()["counters"]["impacts"] >= 1  # the run went through an impact event
    assert colliders == [] and contexts == [] and plans == []
    assert ad.state.ctx is ctx


def test_engine_prepares_at_build():
    from physbench.engine import Engine
    from physbench.adapters.reference import scene_input

    sc = load_scene("billiards.head_on")
    eng = Engine(scene_input(sc), dict(ReferenceAdapter.resolve_settings(sc, {"dt": 0.032})))
    assert eng.state.ctx.plan is not None and eng.state.ctx.ccd.collider is not None


def test_prepare_changes_no_bit():
    from physbench.engine.model import build_model
    from physbench.engine.pipeline import advance, build_pipeline
    from physbench.engine.profile import Profile
    from physbench.engine.state import State
    from physbench.adapters.reference import scene_input

    from physbench.harness.bench import REFERENCE_FAST_SETTINGS, column_scene

    cases = (("billiards.head_on", {"dt": 0.032}), ("friction.block_slides", {"dt": 0.064}),
             ("billiards.ball_drop_bounce", {"dt": 0.032}), ("column", {"iterations": 10, **REFERENCE_FAST_SETTINGS}),
             ("column", {}))
    for name, st in cases:
        sc = column_scene(10) if name == "column" else load_scene(name)
        ad = ReferenceAdapter()
        ad.build(sc, ReferenceAdapter.resolve_settings(sc, st))
        ad.step(30)
        full = dict(ReferenceAdapter.resolve_settings(sc, st))
        model = build_model(scene_input(sc), full)  # no prepare: everything made on first use
        state, stages = State.from_model(model), build_pipeline(model)
        assert state.ctx is None
        advance(model, state, stages, Profile(), 30)
        for f in ("x", "q", "v", "w"):
            assert np.array_equal(getattr(ad.state, f), getattr(state, f)), (name, f)


def _column_settings(sc):
    from physbench.harness.bench import REFERENCE_FAST_SETTINGS

    return dict(ReferenceAdapter.resolve_settings(sc, {"iterations": 10, **REFERENCE_FAST_SETTINGS}))


def _column():
    from physbench.harness.bench import column_scene

    sc = column_scene(10)
    ad = ReferenceAdapter()
    ad.build(sc, _column_settings(sc))
    return sc, ad


def test_build_primes_the_first_step_and_leaves_the_state_as_it_was():
    from physbench.engine.state import State

    _, ad = _column()
    fresh = State.from_model(ad.model)
    for f in ("x", "q", "v", "w"):
        assert np.array_equal(getattr(ad.state, f), getattr(fresh, f)), f
    assert (ad.state.t, ad.state.steps, ad.state.warm) == (fresh.t, fresh.steps, None)
    ctx = ad.state.ctx
    assert ctx.contacts is None and ctx.rows is None and ctx.impacts is None and ctx.stop is None
    prof = ad.stages()
    assert all(v["calls"] == 0 for v in prof.values() if isinstance(v, dict) and "calls" in v)
    assert not prof.get("counters")
    solve = next(s for s in ad.pipeline if s.name == "solve")
    assert solve._fast is not None  # the kept steady solve of the start's contacts


def test_the_resting_column_s_first_step_is_the_steady_call_with_the_staged_bookkeeping():
    from physbench.engine.model import build_model
    from physbench.engine.pipeline import advance, build_pipeline
    from physbench.engine.profile import Profile
    from physbench.engine.state import State
    from physbench.adapters.reference import scene_input

    sc, ad = _column()
    ad.step(1)
    prof = ad.stages()
    assert prof["steady_step"]["calls"] == 1
    assert prof.get("contact_free_step", {"calls": 0})["calls"] == 0  # no try the start's contacts make fail
    assert prof["solve"]["calls"] == 0  # nothing of the step staged
    # the same step on an engine that made everything on first use (a
    # contact-free try that fails, then the staged step): same bits, counters
    model = build_model(scene_input(sc), _column_settings(sc))
    state, stages, p0 = State.from_model(model), build_pipeline(model), Profile()
    advance(model, state, stages, p0, 1)
    assert p0.calls["solve"] == 1 and p0.calls.get("contact_free_step") == 1
    for f in ("x", "q", "v", "w"):
        assert np.array_equal(getattr(ad.state, f), getattr(state, f)), f
    assert (ad.state.t, ad.state.steps) == (state.t, state.steps)
    assert prof["counters"] == p0.counters
    for f in ("codes", "loc", "fn", "pairs", "ft", "tw", "rr", "touch"):
        assert np.array_equal(getattr(ad.state.warm, f), getattr(state.warm, f)), f


def test_the_first_steady_call_makes_no_pack(monkeypatch):
    """A rolling ball's and a resting column's first steps are the steady
    loop's call: after the adapter's build it makes no Pack and borrows
    nothing new (the second warm cache's Pack and its borrowed twin were
    made at build: engine/fused/steady.py SteadyStep.prime_steady)."""
    from physbench.engine import pack
    from physbench.engine.fused import borrow

    for name, settings in (("friction.ball_rolls", {"dt": 0.064}), ("stacking.column_5", {"dt": 0.064})):
        sc = load_scene(name)
        ad = ReferenceAdapter()
        ad.build(sc, ReferenceAdapter.resolve_settings(sc, settings))
        fast = ad.state.ctx.plan.fast
        kall = fast.kall._pack
        packs = _spy(monkeypatch, pack.Pack, "__new__")
        twins = []
        real = borrow.borrowed
        monkeypatch.setattr(borrow, "borrowed", lambda p: twins.append(1) or real(p))
        nb = sc.n_bodies
        rec = (np.zeros((4, nb, 3)), np.zeros((4, nb, 4)), np.zeros((4, nb, 3)), np.zeros((4, nb, 3)))
        ad.step_record(4, *rec)
        assert ad.stages()["steady_step"]["calls"] >= 4
        assert packs == [] and twins == [] and fast.kall._pack is kall, name
        monkeypatch.undo()


def test_the_first_flight_call_makes_no_pack(monkeypatch):
    """The same for a scene without contact (engine/fused/loop.py
    FlightStep.prime): the first call borrows nothing new."""
    from physbench.engine import pack
    from physbench.engine.fused import borrow

    sc = load_scene("gyroscopic.dzhanibekov")
    ad = ReferenceAdapter()
    ad.build(sc, ReferenceAdapter.resolve_settings(sc, {"dt": 0.032}))
    packs = _spy(monkeypatch, pack.Pack, "__new__")
    twins = []
    real = borrow.borrowed
    monkeypatch.setattr(borrow, "borrowed", lambda p: twins.append(1) or real(p))
    rec = (np.zeros((4, 1, 3)), np.zeros((4, 1, 4)), np.zeros((4, 1, 3)), np.zeros((4, 1, 3)))
    ad.step_record(4, *rec)
    assert ad.stages()["flight_step"]["calls"] == 4
    assert packs == [] and twins == []
