"""The steady step as one compiled call (engine/steady.py): the same bits
as the step stage by stage, on every kind of step it meets (resting,
sliding, landing, impacts, friction stops), and it runs where a scene is
steady; which scenes it covers is decided once, with the plan."""

import numpy as np
import pytest

from adapters.reference import engine_for
from contract.scene import load_scene
from harness.bench import column_scene, spheres_scene


def _final(scene, settings, by_stage: bool, steps: int):
    eng = engine_for(scene, settings)
    eng.profile.by_stage = by_stage
    eng.step(steps)
    s = eng.state
    return eng, [a.copy() for a in (s.x, s.q, s.v, s.w)]


@pytest.mark.parametrize("sid,settings", [
    ("stacking.column_5", {}),
    ("stacking.pyramid", {}),
    ("stacking.mixed_bin", {}),
    ("friction.block_thrown_uphill", {}),
    ("friction.box_slides_to_rest", {}),
    ("billiards.newtons_cradle", {}),
    ("stacking.column_5", {"integrator": "semi_implicit_euler", "ccd": "toi", "direct_start": False}),
    ("stacking.column_5", {"ccd": "off"}),
])
def test_fused_step_is_bit_identical_to_the_staged_step(sid, settings):
    scene = load_scene(sid)
    steps = int(round(min(scene.duration, 0.5) / scene.dt))
    fused, a = _final(scene, settings, False, steps)
    staged, b = _final(scene, settings, True, steps)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)
    assert "steady_step" not in staged.profile.as_dict()
    # the counters the stages keep are kept by the fused step alike
    assert fused.profile.counters.get("contact_rows") == staged.profile.counters.get("contact_rows")
    assert fused.profile.counters.get("solver_sweeps") == staged.profile.counters.get("solver_sweeps")


@pytest.mark.parametrize("make,steps,share", [(lambda: column_scene(10), 240, 0.9), (lambda: spheres_scene(100), 240, 0.3)])
def test_steady_scenes_step_in_one_call(make, steps, share):
    """A resting column steps almost only through the fused call; a sphere
    cloud landing on a plane at least in part (landings are impacts and new
    contact graphs: stage by stage)."""
    eng, a = _final(make(), {}, False, steps)
    p = eng.profile.as_dict()
    assert p["steady_step"]["calls"] >= share * steps
    _, b = _final(make(), {}, True, steps)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)


@pytest.mark.parametrize("sid,settings,covered", [
    ("stacking.column_5", {}, True),
    ("stacking.column_5", {"position_correction": "baumgarte"}, False),
    ("stacking.column_5", {"contact_model": "penalty"}, False),
    ("gyroscopic.dzhanibekov", {}, False),  # no contact: nothing to fuse
    ("forces.drag_linear_fall", {}, False),
])
def test_plan_decides_once_what_the_fused_step_covers(sid, settings, covered):
    eng = engine_for(load_scene(sid), settings)
    eng.step(2)
    plan = eng.state._ctx.info["plan"]
    assert (plan.fused is not None) == covered
