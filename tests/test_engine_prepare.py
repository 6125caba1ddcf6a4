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

    for name, st in (("billiards.head_on", {"dt": 0.032}), ("friction.block_slides", {"dt": 0.064}),
                     ("billiards.ball_drop_bounce", {"dt": 0.032})):
        sc = load_scene(name)
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
