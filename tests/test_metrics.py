"""Metrics on hand-made traces with known answers."""

import math

import numpy as np
import pytest

from physbench.harness.metrics import compute_metrics
from physbench.harness.references import get_model
from physbench.harness.runner import Trace
from physbench.contract.scene import compile_scene, load_scene
from physbench.contract.spec import validate_raw
from tests.conftest import HEAD_ON


def make_trace(t, pos, vel, quat=None, angvel=None):
    F, n = pos.shape[:2]
    if quat is None:
        quat = np.zeros((F, n, 4))
        quat[..., 0] = 1
    if angvel is None:
        angvel = np.zeros((F, n, 3))
    return Trace(np.asarray(t, float), pos, quat, vel, angvel, F)


def scene_from(raw):
    return compile_scene(validate_raw(raw, "<test>"))


def ball_scene(effects, n=1, statics=(), r=0.1, m=2.0, z=1.0):
    raw = {
        # bodies all start at one place; the traces the tests write give the poses
        "scenario": {"family": "t", "title": "t", "duration": 1.0, "dt": 0.01, "effects": list(effects),
                     "max_initial_overlap": 1e6},
        "body": [{"name": f"b{i}", "shape": "sphere", "radius": r, "mass": m, "position": [0.0, 0.0, z]} for i in range(n)],
        "static": list(statics),
    }
    return scene_from(raw)


def test_penetration_two_spheres():
    s = ball_scene(["contact"], n=2)
    t = np.arange(4) * 0.01
    pos = np.zeros((4, 2, 3))
    pos[:, 1, 0] = [0.5, 0.2, 0.19, 0.17]  # overlaps 0, 0, 0.01, 0.03
    tr = make_trace(t, pos, np.zeros((4, 2, 3)))
    m = compute_metrics(s, tr)
    assert m["max_penetration"] == pytest.approx(0.03)
    assert m["mean_penetration"] == pytest.approx(0.02)  # mean of 0.01 and 0.03 over touching frames


def test_compute_metrics_reads_its_trace_only(monkeypatch):
    """compute_metrics leaves its trace as it was (the runner keeps the
    penetration measurement, harness.runner._finish), and reads a given
    measurement instead of measuring again."""
    import physbench.contract.geometry as G

    s = ball_scene(["contact"], n=2)
    pos = np.zeros((3, 2, 3))
    pos[:, 1, 0] = [0.5, 0.19, 0.17]  # overlaps 0, 0.01, 0.03
    tr = make_trace(np.arange(3) * 0.01, pos, np.zeros((3, 2, 3)))
    m = compute_metrics(s, tr)
    assert tr.penetration is None and m["max_penetration"] == pytest.approx(0.03)
    from physbench.harness.metrics import run_penetration

    pen = run_penetration(s, tr)
    monkeypatch.setattr(G, "measure_penetration", lambda *a: pytest.fail("measured again"))
    assert compute_metrics(s, tr, pen=pen) == m
    assert run_penetration(ball_scene([], n=2), tr) is None


def test_penetration_not_applicable_without_contact():
    s = ball_scene([], n=2)
    tr = make_trace([0.0], np.zeros((1, 2, 3)), np.zeros((1, 2, 3)))
    assert math.isnan(compute_metrics(s, tr)["max_penetration"])


def test_free_fall_energy_exact_and_gain():
    s = ball_scene(["gravity"], m=2.0, z=10.0)  # the scene the trace records
    t = np.linspace(0, 1, 101)
    g = 9.81
    pos = np.zeros((101, 1, 3))
    pos[:, 0, 2] = 10 - 0.5 * g * t**2
    vel = np.zeros((101, 1, 3))
    vel[:, 0, 2] = -g * t
    m = compute_metrics(s, make_trace(t, pos, vel))
    assert m["energy_drift"] < 1e-12
    assert math.isnan(m["linear_momentum_drift"])  # gravity is an external force
    assert m["angular_momentum_drift"] == pytest.approx(0.0, abs=1e-12)  # no torque about the COM
    # make the last frame 10 % too fast: E gain = 0.1 * KE_end / E0
    vel[-1, 0, 2] *= math.sqrt(1.1)
    m = compute_metrics(s, make_trace(t, pos, vel))
    ke_end = 0.5 * 2.0 * (g * 1.0) ** 2
    e0 = 2.0 * g * (0.5 * g)  # height above the datum: where free fall takes it in the scene's 1 s
    assert m["energy_gain"] == pytest.approx(0.1 * ke_end / e0, rel=1e-9)
    assert m["stable"] is True


def test_momentum_drift_known_value():
    s = ball_scene(["contact"], n=2, m=1.0)
    t = np.array([0.0, 0.1])
    pos = np.zeros((2, 2, 3))
    pos[:, 1, 0] = 1.0
    vel = np.zeros((2, 2, 3))
    vel[0, 0, 0] = 2.0       # P0 = 2
    vel[1, 1, 0] = 2.0       # exchanged: P = 2
    assert compute_metrics(s, make_trace(t, pos, vel))["linear_momentum_drift"] == pytest.approx(0.0, abs=1e-15)
    vel[1, 1, 0] = 2.2       # P = 2.2 -> drift 0.1
    assert compute_metrics(s, make_trace(t, pos, vel))["linear_momentum_drift"] == pytest.approx(0.1)


def test_angular_momentum_and_rotational_energy_of_spinning_box():
    raw = {"scenario": {"family": "t", "title": "t", "duration": 1.0, "dt": 0.01, "effects": ["gyroscopic"]},
           "body": [{"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.05], "mass": 3.0}]}
    s = scene_from(raw)
    I = s.inertias[0]
    # spin about body z while the body is turned 90 degrees about x: world w must be along -y
    q = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0])
    quat = np.tile(q, (2, 1, 1))
    w = np.zeros((2, 1, 3))
    w[:, 0] = [0, -5.0, 0]
    tr = make_trace([0, 0.1], np.zeros((2, 1, 3)), np.zeros((2, 1, 3)), quat, w)
    m = compute_metrics(s, tr)
    assert m["energy_initial"] == pytest.approx(0.5 * I[2] * 25)
    assert m["angular_momentum_drift"] == pytest.approx(0.0, abs=1e-12)
    w[1, 0] = [0, -5.5, 0]
    m = compute_metrics(s, make_trace([0, 0.1], np.zeros((2, 1, 3)), np.zeros((2, 1, 3)), quat, w))
    assert m["angular_momentum_drift"] == pytest.approx(0.1)
    assert m["energy_gain"] == pytest.approx(0.21)


def test_non_finite_is_unstable():
    s = ball_scene([])
    pos = np.zeros((3, 1, 3))
    pos[2, 0, 0] = np.nan
    m = compute_metrics(s, make_trace([0, 1, 2], pos, np.zeros((3, 1, 3))))
    assert m["stable"] is False and "non-finite" in m["stability_reason"]


def test_two_body_collision_reference_hand_values():
    # m1 = 1, m2 = 3, e = 0.5, v1 = 4, v2 = 0:
    # v1' = (1 - 1.5) * 4 / 4 = -0.5 ; v2' = 1.5 * 4 / 4 = 1.5
    raw = {"scenario": {"family": "t", "title": "t", "duration": 1.0, "dt": 0.01, "effects": ["contact", "restitution"]},
           "material": {"default": {"restitution": 0.5}},
           "body": [{"name": "a", "shape": "sphere", "radius": 0.1, "mass": 1.0, "velocity": [4.0, 0, 0]},
                    {"name": "b", "shape": "sphere", "radius": 0.1, "mass": 3.0, "position": [1.0, 0, 0]}],
           "reference": {"model": "two_body_collision"}}
    s = scene_from(raw)
    ref = get_model("two_body_collision")(s)
    assert ref.t_impact == pytest.approx(0.8 / 4)
    assert ref.v1_post[0] == pytest.approx(-0.5) and ref.v2_post[0] == pytest.approx(1.5)
    t = np.linspace(0, 1, 101)
    exact = make_trace(t, ref.positions(t), ref.velocities(t))
    m = ref.metrics(exact)
    assert m["post_impact_velocity_error"] == pytest.approx(0.0, abs=1e-15)
    assert m["trajectory_rmse"] == pytest.approx(0.0, abs=1e-15)
    wrong = ref.velocities(t)
    wrong[-1, 1, 0] += 0.04  # 1 % of the 4 m/s approach speed
    m = ref.metrics(make_trace(t, ref.positions(t), wrong))
    assert m["post_impact_velocity_error"] == pytest.approx(0.01)


def test_head_on_reference_equal_masses():
    s = load_scene(HEAD_ON, "elastic")
    ref = get_model("two_body_collision")(s)
    assert ref.v1_post[0] == pytest.approx(0.0) and ref.v2_post[0] == pytest.approx(2.0)
    assert ref.t_impact == pytest.approx((0.3 - 2 * 0.028575) / 2.0)


# ---------------------------------------------------------------------------
# metrics a run cannot define: missing with the reason, never a crash


def _shipped_raw(rel):
    import tomllib

    from physbench.contract.scene import SCENARIO_DIR

    return tomllib.loads((SCENARIO_DIR / rel).read_text(encoding="utf-8"))


def _held_trace(scene, frames=33):
    """The scene's initial state at frame 0, then the bodies where they
    start, at rest (what an engine records for a body too slow to move)."""
    x0, q0, v0, w0 = scene.initial_state()
    F, n = frames, scene.n_bodies
    pos = np.broadcast_to(x0, (F, n, 3)).copy()
    vel, angvel = np.zeros((F, n, 3)), np.zeros((F, n, 3))
    vel[0], angvel[0] = v0, w0
    return make_trace(np.arange(F) * scene.dt, pos, vel, quat=np.broadcast_to(q0, (F, n, 4)).copy(), angvel=angvel)


def _set(raw, path, value):
    node = raw
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return raw


# Each raised ZeroDivisionError inside the model before (the nightly fuzz's
# "metrics failed: ZeroDivisionError"): a denominator the scene makes 0.
UNDEFINED_CASES = [
    # a frictionless slope: the ball slides without turning, alpha = 0
    ("friction/ball_rolls.toml", [(("material", "default", "friction"), 0.0),
                                  (("material", "default", "static_friction"), 0.0)],
     "spin_accel_error", "the reference angular acceleration is 0"),
    # a heavy cue ball so slow that v.v underflows: |P0| = m |v| > 0 but KE(0) = 0
    ("billiards/break_16.toml", [(("body", 0, "velocity"), [1e-163, 0.0, 0.0]), (("body", 0, "mass"), 100.0)],
     "energy_error", "the initial kinetic energy KE(0) is 0"),
    # u0^2 / (2 |a|) underflows: the stop distance is 0
    ("friction/box_slides_to_rest.toml", [(("body", 0, "velocity"), [2e-170, 0.0, 0.0])],
     "stop_distance_error", "the reference stop distance is 0"),
    # w0^2 / (2 alpha) underflows: the angle turned is 0
    ("friction/capsule_spins_to_rest.toml", [(("body", 0, "angular_velocity"), [0.0, 0.0, 1e-170])],
     "spin_stop_angle_error", "the reference angle turned is 0"),
]


@pytest.mark.parametrize("rel, edits, metric, why", UNDEFINED_CASES, ids=[c[2] for c in UNDEFINED_CASES])
def test_undefined_metric_is_missing_with_its_reason(rel, edits, metric, why):
    from physbench.harness.conformance.verdicts import ERROR, evaluate
    from physbench.harness.references import UNDEFINED, undefined_reason
    from physbench.harness.runner import RunResult

    raw = _shipped_raw(rel)
    raw.pop("variant", None)
    for path, value in edits:
        _set(raw, path, value)
    scene = scene_from(raw)
    m = compute_metrics(scene, _held_trace(scene))
    assert math.isnan(m[metric])
    assert why in undefined_reason(m, metric), m.get(UNDEFINED)
    # the model's other metrics are still there
    defined = [k for k, v in m.items() if isinstance(v, float) and math.isfinite(v)]
    assert scene.primary_metric in defined or scene.primary_metric == metric
    # a check on it is an error that gives the reason, not a pass, a skip or an xfail
    res = RunResult(scene.id, None, "reference", "", "ok", "", {}, m, {}, {}, [], {}, {}, "", "")
    outs = [o for o in evaluate(scene, res) if o.metric == metric]
    if outs:
        assert all(o.outcome == ERROR and why in o.message for o in outs), [(o.outcome, o.message) for o in outs]


def test_undefined_metric_helpers():
    from physbench.harness.references import UNDEFINED, divide, undefined, undefined_reason

    out = {}
    divide(out, "a", 3.0, 2.0, "the scale")
    divide(out, "b", 1.0, 0.0, "the scale")
    divide(out, "c", 1.0, -0.0, "the other scale")
    undefined(out, "d", "no apex: nothing bounced")
    assert out["a"] == 1.5 and all(math.isnan(out[k]) for k in "bcd")
    assert out[UNDEFINED] == "b: the scale is 0; c: the other scale is -0; d: no apex: nothing bounced"
    assert undefined_reason(out, "d") == "no apex: nothing bounced"
    assert undefined_reason(out, "a") == "" and undefined_reason({}, "a") == ""


def test_run_with_an_undefined_metric_says_so():
    """End to end on an engine: the frictionless ball runs ``ok`` with its
    other metrics; the undefined one is named in the row and the notes, and
    the scene's check on it is an error."""
    from physbench.harness.conformance.verdicts import ERROR, evaluate
    from physbench.harness.runner import run

    raw = _set(_set(_shipped_raw("friction/ball_rolls.toml"), ("material", "default", "friction"), 0.0),
               ("material", "default", "static_friction"), 0.0)
    raw["scenario"]["duration"] = 0.25
    raw.pop("variant", None)
    scene = scene_from(raw)
    res = run(scene, "pymunk")
    assert res.status == "ok", res.message
    assert math.isnan(res.metrics["spin_accel_error"]) and math.isfinite(res.metrics["roll_accel_error"])
    assert "spin_accel_error" in res.row()["undefined_metrics"]
    assert any(n.startswith("undefined metrics: spin_accel_error") for n in res.notes)
    spin = [o for o in evaluate(scene, res) if o.metric == "spin_accel_error"]
    assert spin and spin[0].outcome == ERROR and "angular acceleration is 0" in spin[0].message


def test_bounce_heights_refuses_a_ball_at_rest_on_the_plane():
    """No drop height and no impact speed: every apex ratio would divide by
    h_0 = 0 (a resting ball's contact jitter made the metrics raise
    ZeroDivisionError); the spec is refused at load, naming the model."""
    from physbench.contract.spec import SpecError

    raw = _set(_shipped_raw("billiards/ball_drop_bounce.toml"), ("body", 0, "position"), [0.0, 0.0, 0.05])
    raw.pop("variant", None)
    with pytest.raises(SpecError, match="nothing bounces"):
        scene_from(raw)
    raw["body"][0]["velocity"] = [0.0, 0.0, 1e-3]  # a throw from the plane is a bounce
    assert scene_from(raw).reference_model == "bounce_heights"
