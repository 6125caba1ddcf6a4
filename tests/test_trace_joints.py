"""Traces show joints: each joint's two anchor points and its axes per frame
under ``/world/<engine>/joints/<joint>`` (docs/TRACES.md).

The pendulum's trace is planted: the bob swings about the hinge line by
theta(t), tilts off it by psi(t) (a bent hinge) and sinks by delta(t) (a
stretched hinge), so the two sides' anchors and axes differ by known
amounts.  The expected points are the recorded pose applied to the local
anchor, with the rotation built here from its two matrices, not through
the harness's quaternion code.
"""

from __future__ import annotations

import numpy as np
import pytest

from physbench.contract.scene import load_scene
from physbench.harness.joints import joint_metrics
from physbench.harness.runner import RunResult, Trace
from physbench.harness.trace import write_rrd
from tests.test_trace_rrd import F32, ballistic_result, read_rrd, temporal

pytest.importorskip("rerun.chunk")

N = 201


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _motion(t: np.ndarray):
    theta = 0.5 * np.cos(3.0 * t)  # swing about the hinge (y)
    psi = 0.02 * np.sin(5.0 * t)  # tilt about x: the bob's hinge axis leaves y
    delta = 1e-3 * np.sin(2.0 * t) ** 2  # the bob sinks off its circle (m)
    return theta, psi, delta


def _planted(scene) -> RunResult:
    """The bob turned by R = Ry(theta) Rx(psi) about the pivot and lowered by delta."""
    pivot = np.array([0.0, 0.0, 2.0])
    x0 = np.array(scene.bodies[0].position, float)
    t = np.arange(N) * 0.01
    theta, psi, delta = _motion(t)
    tr = Trace.allocate(N, 1)
    tr.t[:] = t
    for f in range(N):
        R = _ry(theta[f]) @ _rx(psi[f])
        tr.pos[f, 0] = pivot + R @ (x0 - pivot) - np.array([0.0, 0.0, delta[f]])
        cy, sy, cx, sx = np.cos(theta[f] / 2), np.sin(theta[f] / 2), np.cos(psi[f] / 2), np.sin(psi[f] / 2)
        tr.quat[f, 0] = [cy * cx, cy * sx, sy * cx, -sy * sx]  # qy * qx (wxyz)
    tr.n_frames = N
    return RunResult(scene.id, None, "fake", "0", "ok", "", {"dt": 0.01}, trace=tr)


@pytest.fixture(scope="module")
def pendulum_trace(tmp_path_factory):
    scene = load_scene("joints.pendulum")
    np.testing.assert_array_equal(scene.initial_state()[1][0], [1.0, 0.0, 0.0, 0.0])  # starts unrotated
    res = _planted(scene)
    path = tmp_path_factory.mktemp("rrd") / "pendulum.rrd"
    write_rrd(path, scene, [res])
    return scene, res, read_rrd(path)


def test_anchors_are_the_recorded_pose_applied_to_the_local_anchors(pendulum_trace):
    scene, res, data = pendulum_trace
    j = scene.joints[0]
    assert j.name == "pivot"
    pivot = np.array([0.0, 0.0, 2.0])
    x0 = np.array(scene.bodies[0].position, float)
    local = pivot - x0  # the bob starts unrotated: its frame is the world's, from its centre
    df = temporal(data, "/world/fake/joints/pivot/anchors")
    assert len(df) == N and list(df["step"]) == list(range(N))
    t = np.arange(N) * 0.01
    theta, psi, delta = _motion(t)
    sep = []
    for f, pts in enumerate(df["Points3D:positions"]):
        pts = np.array([list(p) for p in pts], float)
        assert pts.shape == (2, 3)
        R = _ry(theta[f]) @ _rx(psi[f])
        body_side = res.trace.pos[f, 0] + R @ local
        np.testing.assert_allclose(pts[0], body_side, **F32)
        np.testing.assert_allclose(pts[1], pivot, **F32)  # the world side stays put
        sep.append(np.linalg.norm(pts[0] - pts[1]))
    # the bob sank by delta: its anchor is delta below the pivot's
    np.testing.assert_allclose(sep, delta, atol=2e-6)
    assert max(sep) > 5e-4
    # the same points the metric measures
    assert joint_metrics(scene, res.trace)["joint_drift"] == pytest.approx(max(sep), abs=2e-6)


def test_hinge_axes_are_each_sides_axis_from_its_anchor(pendulum_trace):
    scene, res, data = pendulum_trace
    df = temporal(data, "/world/fake/joints/pivot/axis")
    assert len(df) == N
    t = np.arange(N) * 0.01
    theta, psi, _ = _motion(t)
    length = 2.0 * 0.05  # twice the bob's radius
    anchors = temporal(data, "/world/fake/joints/pivot/anchors")
    angles = []
    for f, (org, vec, pts) in enumerate(zip(df["Arrows3D:origins"], df["Arrows3D:vectors"],
                                            anchors["Points3D:positions"])):
        org = np.array([list(p) for p in org], float)
        vec = np.array([list(v) for v in vec], float)
        np.testing.assert_allclose(org, np.array([list(p) for p in pts], float), rtol=0, atol=0)
        R = _ry(theta[f]) @ _rx(psi[f])
        np.testing.assert_allclose(vec[0], length * (R @ [0.0, 1.0, 0.0]), atol=1e-6)  # carried by the bob
        np.testing.assert_allclose(vec[1], [0.0, length, 0.0], atol=1e-7)  # the world's
        angles.append(np.arctan2(np.linalg.norm(np.cross(vec[0], vec[1])), vec[0] @ vec[1]))
    # the bent hinge: the bob's axis is off the world's by |psi|
    np.testing.assert_allclose(angles, np.abs(psi), atol=1e-5)


def test_a_scene_without_joints_logs_no_joint_entities(tmp_path):
    scene = load_scene("billiards.head_on")
    assert not scene.joints
    path = tmp_path / "h.rrd"
    write_rrd(path, scene, [ballistic_result(scene, "fake", 1.0, 0.0, n_frames=11)])
    data = read_rrd(path)
    assert any(p.startswith("/world/fake/") for p in data)
    assert not [p for p in data if "/joints" in p]


def test_spherical_joint_has_anchors_but_no_axis(tmp_path):
    scene = load_scene("joints.conical_pendulum")
    assert {j.kind for j in scene.joints} == {"spherical"}
    x0, q0, _, _ = scene.initial_state()
    tr = Trace.allocate(3, scene.n_bodies)
    tr.t[:] = [0.0, 0.01, 0.02]
    tr.pos[:] = x0[None]
    tr.quat[:] = q0[None]
    tr.n_frames = 3
    path = tmp_path / "c.rrd"
    write_rrd(path, scene, [RunResult(scene.id, None, "fake", "0", "ok", "", {"dt": 0.01}, trace=tr)])
    data = read_rrd(path)
    name = scene.joints[0].name
    pts = temporal(data, f"/world/fake/joints/{name}/anchors")
    p = np.array([list(v) for v in pts["Points3D:positions"][0]], float)
    np.testing.assert_allclose(p[0], p[1], atol=1e-6)  # at rest at the start: one point
    np.testing.assert_allclose(p[1], scene.joints[0].anchor, atol=1e-6)
    assert f"/world/fake/joints/{name}/axis" not in data


def test_diagnosing_trace_draws_the_joint_drift_series(tmp_path):
    """The diagnosing trace's running joint_drift is the planted sink delta
    (its maximum the metric), drawn against the check's 0.1 mm, and the
    crossing is marked at the first step past it (computed here from delta)."""
    from physbench.harness.conformance import Outcome

    scene = load_scene("joints.pendulum")
    res = _planted(scene)
    checks = {c.metric: c for c in scene.checks if c.metric in ("joint_drift", "joint_axis_drift")
              and (c.variants is None or "base" in c.variants)}
    assert checks["joint_drift"].max == 1e-4
    o = Outcome("fake", scene.id, None, "joint_drift", "FAIL", 1e-3, "<= 0.0001")
    path = tmp_path / "d.rrd"
    write_rrd(path, scene, [res], diagnose=True, outcomes=[o], checks=checks)
    data = read_rrd(path)
    t = np.arange(N) * 0.01
    theta, psi, delta = _motion(t)
    df = temporal(data, "/metrics/fake/check/joint_drift")
    y = np.array([v[0] for v in df["Scalars:scalars"]])
    np.testing.assert_allclose(y, delta, atol=2e-9)
    ang = temporal(data, "/metrics/fake/check/joint_axis_drift")
    np.testing.assert_allclose([v[0] for v in ang["Scalars:scalars"]], np.abs(psi), atol=1e-9)
    thr = temporal(data, "/metrics/threshold/joint_drift/max")
    assert {v[0] for v in thr["Scalars:scalars"]} == {1e-4}
    first = int(np.nonzero(delta > 1e-4)[0][0])
    events = temporal(data, "/events/fake")
    hits = [s for s, tx in zip(events["step"], events["TextLog:text"]) if str(tx[0]).startswith("check joint_drift ")]
    assert hits == [first]
