"""Metrics on hand-made traces with known answers."""

import math

import numpy as np
import pytest

from harness.metrics import compute_metrics
from harness.references import get_model
from harness.runner import Trace
from contract.scene import compile_scene, load_scene
from contract.spec import validate_raw
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
        "scenario": {"family": "t", "title": "t", "duration": 1.0, "dt": 0.01, "effects": list(effects)},
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
