"""joint_drift and joint_axis_drift on planted states: motions a joint
allows give 0, planted violations come back at their exact size."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from physbench.contract.rotation import quat_exp, quat_mul, quat_to_matrix
from physbench.contract.scene import load_scene
from physbench.harness.joints import joint_metrics, joint_violations
from physbench.harness.metrics import compute_metrics

SPEC = """
[scenario]
family = "joints"
title = "t"
duration = 1.0
dt = 0.01
effects = ["gravity", "joint"]

[[body]]
name = "a"
shape = "box"
half_extents = [0.1, 0.2, 0.3]
mass = 2.0
position = [0.0, 0.0, 1.0]
orientation = [0.9238795325112867, 0.0, 0.0, 0.3826834323650898]

[[body]]
name = "b"
shape = "sphere"
radius = 0.1
mass = 1.0
position = [0.5, 0.0, 1.0]

[[joint]]
kind = "{kind}"
body = "{body}"
other = "{other}"
anchor = {anchor}
{axis}
"""


def _scene(tmp_path, kind, body="a", other="world", anchor="[0.0, 0.0, 1.3]", axis="axis = [0.0, 1.0, 1.0]"):
    p = tmp_path / "j.toml"
    p.write_text(SPEC.format(kind=kind, body=body, other=other, anchor=anchor, axis=axis))
    return load_scene(p)


def _trace(scene, frames):
    """A trace from per-frame (pos (n, 3), quat (n, 4)) pairs; frame 0 is the start."""
    x0, q0, _, _ = scene.initial_state()
    pos = np.array([x0] + [f[0] for f in frames])
    quat = np.array([q0] + [f[1] for f in frames])
    F, n = pos.shape[:2]
    return SimpleNamespace(t=np.arange(F) * scene.dt, pos=pos, quat=quat, vel=np.zeros((F, n, 3)),
                           angvel=np.zeros((F, n, 3)))


def _turn(scene, i, point, rotvec, x=None, q=None):
    """Body i's state turned by the rotation vector ``rotvec`` about the world ``point``."""
    x0, q0, _, _ = scene.initial_state()
    x = x0.copy() if x is None else x.copy()
    q = q0.copy() if q is None else q.copy()
    r = quat_exp(np.array(rotvec, float))
    x[i] = point + quat_to_matrix(r) @ (x[i] - point)
    q[i] = quat_mul(r, q[i])
    return x, q


def test_revolute_allowed_motion_is_zero_and_violations_are_exact(tmp_path):
    s = _scene(tmp_path, "revolute")
    j = s.joints[0]
    u = j.axis
    ok = [_turn(s, 0, j.anchor, u * a) for a in (0.3, 1.7, -2.9)]
    m = joint_metrics(s, _trace(s, ok))
    assert m["joint_drift"] < 1e-15 and m["joint_axis_drift"] < 1e-14
    # planted: 0.37 mm off the pivot at frame 2, a 0.02 rad tilt across the axis at frame 3
    x, q = _turn(s, 0, j.anchor, u * 1.7)
    x[0] += np.array([0.0, 3.7e-4, 0.0])
    tilt = _turn(s, 0, j.anchor, 0.02 * np.array([1.0, 0.0, 0.0]))
    m = joint_metrics(s, _trace(s, [ok[0], (x, q), tilt]))
    assert m["joint_drift"] == pytest.approx(3.7e-4, rel=1e-9)
    assert m["joint_axis_drift"] == pytest.approx(0.02, rel=1e-9)
    lin, ang = joint_violations(s, _trace(s, [ok[0], (x, q), tilt]))[0]
    assert lin[1] < 1e-15 and lin[2] == pytest.approx(3.7e-4, rel=1e-9)  # per frame, not just the max


def test_prismatic_off_axis_and_rotation(tmp_path):
    s = _scene(tmp_path, "prismatic")
    j = s.joints[0]
    x0, q0, _, _ = s.initial_state()
    slide = x0.copy()
    slide[0] += 0.8 * j.axis
    assert joint_metrics(s, _trace(s, [(slide, q0)])) == {"joint_drift": pytest.approx(0.0, abs=1e-15),
                                                          "joint_axis_drift": 0.0}
    off = slide.copy()
    off[0] += 2e-4 * np.array([1.0, 0.0, 0.0])  # x is across the axis (0, 1, 1)/sqrt 2
    turned = _turn(s, 0, j.anchor, [0.0, 0.0, 0.01])
    m = joint_metrics(s, _trace(s, [(off, q0), turned]))
    assert m["joint_drift"] == pytest.approx(2e-4, rel=1e-9)
    assert m["joint_axis_drift"] == pytest.approx(0.01, rel=1e-9)


def test_fixed_pair_moving_together_and_apart(tmp_path):
    s = _scene(tmp_path, "fixed", body="b", other="a", anchor="[0.35, 0.0, 1.0]", axis="")
    j = s.joints[0]
    P = np.array([0.2, -0.4, 0.7])
    x, q = _turn(s, 0, P, [0.4, -0.2, 1.1])
    x, q = _turn(s, 1, P, [0.4, -0.2, 1.1], x, q)  # both bodies, one rigid motion
    m = joint_metrics(s, _trace(s, [(x, q)]))
    assert m["joint_drift"] < 1e-14 and m["joint_axis_drift"] < 1e-14
    bent = _turn(s, 0, j.anchor, [0.0, 0.03, 0.0])  # a alone turns 0.03 rad about the shared anchor
    m = joint_metrics(s, _trace(s, [(x, q), bent]))
    assert m["joint_drift"] < 1e-14
    assert m["joint_axis_drift"] == pytest.approx(0.03, rel=1e-9)


def test_spherical_turns_freely_but_not_apart(tmp_path):
    s = _scene(tmp_path, "spherical", body="b", other="a", anchor="[0.35, 0.0, 1.0]", axis="")
    j = s.joints[0]
    free = _turn(s, 1, j.anchor, [1.0, 2.0, -0.5])
    x, q = _turn(s, 1, j.anchor, [0.0, 0.5, 0.0])
    x[1] += np.array([0.0, 0.0, -5e-3])
    m = joint_metrics(s, _trace(s, [free, (x, q)]))
    assert m["joint_drift"] == pytest.approx(5e-3, rel=1e-9)
    assert m["joint_axis_drift"] == 0.0


def test_compute_metrics_reports_joint_drift_and_not_momentum_for_a_world_joint(tmp_path):
    s = _scene(tmp_path, "revolute")
    x, q = _turn(s, 0, s.joints[0].anchor, s.joints[0].axis * 0.5)
    x[0, 2] -= 1e-3
    m = compute_metrics(s, _trace(s, [(x, q)]), model=False)
    assert m["joint_drift"] == pytest.approx(1e-3, rel=1e-9)
    # the joint to the world is an external force: no momentum conservation claimed
    assert math.isnan(m["linear_momentum_drift"]) and math.isnan(m["angular_momentum_drift"])


def test_energy_datum_of_a_held_body(tmp_path):
    """A hinge body's datum is the bottom of its circle, not where free fall
    would take it: the box's centre at (0, 0, 1), the hinge line through
    (0, 0, 1.3) along (0, 1, 1)/sqrt 2; the circle's centre, radius and tilt
    are computed here."""
    from physbench.harness.metrics import lowest_height
    s = _scene(tmp_path, "revolute")
    u = np.array([0.0, 1.0, 1.0]) / math.sqrt(2.0)
    r = np.array([0.0, 0.0, -0.3])
    centre_z = 1.3 + (r @ u) * u[2]
    radius = np.linalg.norm(r - (r @ u) * u)
    up = np.array([0.0, 0.0, 1.0])
    across = np.linalg.norm(up - (up @ u) * u)
    assert lowest_height(s, s.bodies[0]) == pytest.approx(centre_z - radius * across, rel=1e-14)
    sph = _scene(tmp_path, "spherical", axis="")
    assert lowest_height(sph, sph.bodies[0]) == pytest.approx(1.3 - 0.3, rel=1e-14)
    fixed = _scene(tmp_path, "fixed", axis="")
    assert lowest_height(fixed, fixed.bodies[0]) == pytest.approx(1.0, rel=1e-14)
    # the free body b still falls freely for the scene's 1 s
    assert lowest_height(s, s.bodies[1]) == pytest.approx(1.0 - 0.5 * 9.81, rel=1e-14)


def test_energy_datum_of_a_chain_is_the_chain_hanging_straight_down():
    """joints.chain_10: link k (centre 0.1 k + 0.05 m out along x, hinged at
    0.1 k) can hang no lower than 2 - (0.1 k + 0.05) m."""
    from physbench.harness.metrics import lowest_height
    s = load_scene("joints.chain_10")
    for k, b in enumerate(s.bodies):
        assert lowest_height(s, b) == pytest.approx(2.0 - (0.1 * k + 0.05), rel=1e-12)
