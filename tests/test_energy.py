"""Energy from a datum the scene fixes: E0 is the same on every engine, and
the drift / dissipated / gain split follows the scene's physics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from physbench.adapters import ENGINES
from physbench.contract.metric_defs import dissipation
from physbench.harness.metrics import compute_metrics, energy_datum, kinetic_energy, lowest_height, potential_energy
from physbench.harness.runner import Trace, run
from physbench.contract.scene import compile_scene, load_scene, scenario_ids
from physbench.contract.spec import validate_raw


def _scene(text_raw):
    return compile_scene(validate_raw(text_raw, "<test>"))


def _frame0(sc) -> Trace:
    x, q, v, w = sc.initial_state()
    return Trace(np.zeros(1), x[None], q[None], v[None], w[None], 1)


def _e0(sc, trace) -> float:
    """E at the first frame, as compute_metrics' energy_initial (the same
    functions, without the reference model's metrics)."""
    trans, rot = kinetic_energy(sc, trace)
    return float((trans + rot + potential_energy(sc, trace))[0])


# planar ones (all four engines), ones with springs, a 3D stack and a spinning box
E0_SCENES = ["billiards.head_on", "billiards.ball_drop_bounce", "friction.box_slides_to_rest",
             "friction.block_slides", "forces.damped_spring", "forces.spring_pair", "forces.drag_linear_fall",
             "stacking.column_5", "gyroscopic.heavy_top"]


@pytest.mark.parametrize("sid", E0_SCENES)
def test_initial_energy_is_the_same_on_every_engine(sid):
    """The first frame of every engine that runs the scene has the same E0,
    to 1e-12 relative (1e-6 for the f32 engines, whose state is read back
    rounded to f32: measured <= 2.1e-7), and it is the scene's own initial
    energy."""
    sc = load_scene(sid)
    short = load_scene(sid, overrides={"scenario.duration": sc.duration})  # same scene, own object
    expect = _e0(sc, _frame0(sc))
    seen = {}
    for eng in ENGINES:
        r = run(short, eng, {}, compute_metrics=False)
        if r.status == "unsupported":
            continue
        assert r.trace is not None and r.trace.n_frames >= 1, (eng, r.status, r.message)
        seen[eng] = _e0(short, r.trace.valid())
    assert len(seen) >= 2, seen
    for eng, e0 in seen.items():
        rtol = 1e-6 if eng in ("rapier", "box2d") else 1e-12
        assert abs(e0 - expect) <= rtol * max(abs(expect), 1.0), (sid, eng, e0, expect)
    print(sid, {k: f"{v:.15g}" for k, v in seen.items()})


@pytest.mark.parametrize("sid", scenario_ids())
def test_shipped_scenes_start_at_or_above_their_datum(sid):
    sc = load_scene(sid)
    assert _e0(sc, _frame0(sc)) >= -1e-12


def _box_on_floor(effects, velocity=(2.0, 0.0, 0.0), friction=0.4, duration=1.0):
    return _scene({
        "scenario": {"family": "t", "title": "t", "duration": duration, "dt": 0.001, "effects": effects},
        "material": {"default": {"friction": friction}} if "friction" in effects else {},
        "body": [{"name": "box", "shape": "box", "half_extents": [0.1, 0.2, 0.05], "mass": 1.0,
                  "position": [0.0, 0.0, 0.55], "velocity": list(velocity)}],
        "static": [{"shape": "plane", "normal": [0.0, 0.0, 1.0], "offset": 0.5}],
    })


def test_datum_on_a_level_floor_is_resting_on_the_smallest_half_size():
    sc = _box_on_floor(["gravity", "contact", "friction"])
    assert lowest_height(sc, sc.bodies[0]) == pytest.approx(0.55)
    assert energy_datum(sc) == pytest.approx(9.81 * 0.55)
    assert _e0(sc, _frame0(sc)) == pytest.approx(0.5 * 4.0, abs=1e-12)


def test_datum_in_free_flight_is_where_free_fall_takes_the_body():
    sc = _scene({"scenario": {"family": "t", "title": "t", "duration": 2.0, "dt": 0.01, "effects": ["gravity"]},
                 "body": [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0, "position": [0, 0, 3.0],
                           "velocity": [0.0, 0.0, 4.0]}]})
    assert lowest_height(sc, sc.bodies[0]) == pytest.approx(3.0 + 4.0 * 2.0 - 0.5 * 9.81 * 4.0)


def test_datum_of_a_hanging_spring_is_its_equilibrium():
    sc = load_scene("forces.damped_spring")  # released 0.1 m below equilibrium, k = 40
    assert _e0(sc, _frame0(sc)) == pytest.approx(0.5 * 40.0 * 0.1**2, rel=1e-9)


def test_box_sliding_to_rest_is_dissipation_not_drift():
    sc = _box_on_floor(["gravity", "contact", "friction"])
    assert dissipation(sc) == ["friction (mu = 0.4)", "impacts with e = 0 < 1"]
    F = 3
    x, q, v, w = sc.initial_state()
    pos = np.repeat(x[None], F, 0)
    pos[:, 0, 0] = [0.0, 0.3, 0.51]
    vel = np.zeros((F, 1, 3))
    vel[0, 0, 0], vel[1, 0, 0] = 3.0, 1.0  # E0 = 4.5 J, above the scale's floor m g r = 2.25 J
    tr = Trace(np.array([0.0, 0.25, 0.6]), pos, np.repeat(q[None], F, 0), vel, np.zeros((F, 1, 3)), F)
    m = compute_metrics(sc, tr)
    assert math.isnan(m["energy_drift"])
    assert m["energy_dissipated"] == pytest.approx(1.0, abs=1e-12)
    assert m["energy_gain"] == 0.0


def test_reference_engine_box_dissipates_all_its_energy():
    r = run(load_scene("friction.box_slides_to_rest"), "reference")
    assert r.status == "ok"
    assert math.isnan(r.metrics["energy_drift"])
    assert r.metrics["energy_dissipated"] == pytest.approx(1.0, abs=1e-6)


def test_conservative_scene_reports_drift_not_dissipation():
    sc = _box_on_floor(["gravity", "contact"])  # frictionless, but e = 0 impacts: dissipative
    assert dissipation(sc) == ["impacts with e = 0 < 1"]
    free = _scene({"scenario": {"family": "t", "title": "t", "duration": 1.0, "dt": 0.01,
                                "effects": ["gravity", "contact"]},
                   "body": [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0}]})
    assert dissipation(free) == []  # contact, but nothing to touch
    m = compute_metrics(free, _frame0(free))
    assert m["energy_drift"] == 0.0 and math.isnan(m["energy_dissipated"])
    r = run(load_scene("forces.spring_pair"), "reference")
    assert r.metrics["energy_drift"] <= 1e-9 and math.isnan(r.metrics["energy_dissipated"])
