"""Self-consistency (harness/references/self_consistency.py): the distance
functions on planted traces, Richardson's observed order on synthetic
errors, and the reference engine's integrators' orders measured on scenes
with no closed form (no analytic model is used anywhere here)."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

from physbench.contract.scene import load_scene
from physbench.contract.spec import SpecError
from physbench.harness.references.self_consistency import (distances, observed_order, rotation_angle,
                                                           shared_frames)
from physbench.harness.runner import Trace

TUMBLE = """
[scenario]
family = "selfcheck"
title = "torque-free box tumbling about its intermediate axis, judged by itself"
duration = 3.0
dt = 0.01
effects = ["gyroscopic"]
primary_metric = "self_consistency_angle"

[[body]]
name = "box"
shape = "box"
half_extents = [0.3, 0.2, 0.05]
mass = 1.0
angular_velocity = [0.05, 10.0, 0.05]

[reference]
model = "self_consistency"
"""


def _scene(tmp_path, text: str, name: str = "s.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return load_scene(str(p))


def _quat(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def _trace(t, pos, quat):
    F, n = pos.shape[:2]
    return Trace(np.asarray(t, float), pos, quat, np.zeros((F, n, 3)), np.zeros((F, n, 3)), F)


# ---------------------------------------------------------------------------
# the pure functions


@pytest.mark.parametrize("angle", [1e-9, 1e-4, 0.3, 2.0, math.pi - 1e-3])
def test_rotation_angle_finds_the_planted_angle(angle):
    qa = _quat([0.3, -0.5, 0.8], 0.7)
    dq = _quat([1.0, 2.0, -0.5], angle)
    # qb = qa * dq (Hamilton product), so the rotation between them is `angle`
    w1, v1 = qa[0], qa[1:]
    w2, v2 = dq[0], dq[1:]
    qb = np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])
    assert rotation_angle(qa, qb) == pytest.approx(angle, rel=1e-9, abs=1e-15)
    assert rotation_angle(qa, -qb) == pytest.approx(angle, rel=1e-9, abs=1e-15)  # q and -q: one rotation


def test_distances_on_planted_offsets():
    """Two bodies, 5 frames; the second trace has every other frame (the
    fine run records at the coarse run's times only when its steps divide),
    body 1 displaced by 0.1 m per shared frame index and rotated 0.02 rad."""
    F = 5
    t = np.arange(F) * 0.1
    pos = np.zeros((F, 2, 3))
    quat = np.tile([1.0, 0, 0, 0], (F, 2, 1))
    t2 = np.arange(2 * F - 1) * 0.05  # twice as many frames, same times every other
    pos2 = np.zeros((2 * F - 1, 2, 3))
    quat2 = np.tile([1.0, 0, 0, 0], (2 * F - 1, 2, 1))
    pos2[::2, 1, 0] = 0.1 * np.arange(F)
    pos2[1::2, 1, 0] = 99.0  # not a shared time: never compared
    quat2[::2, 1] = _quat([0, 0, 1], 0.02)
    a, b = _trace(t, pos, quat), _trace(t2, pos2, quat2)
    i, j = shared_frames(a.t, b.t, 0.1)
    assert list(j) == [0, 2, 4, 6, 8] and list(i) == [0, 1, 2, 3, 4]
    dx, da, n = distances(a, b, 0.1, "trajectory")
    # RMS over 5 frames x 2 bodies of body 1's offsets 0, .1, .2, .3, .4
    assert dx == pytest.approx(math.sqrt(sum((0.1 * k) ** 2 for k in range(F)) / (2 * F)), rel=1e-12)
    assert da == pytest.approx(math.sqrt(F * 0.02 ** 2 / (2 * F)), rel=1e-9)
    assert n == F
    dx, da, _ = distances(a, b, 0.1, "final_state")
    assert dx == pytest.approx(0.4, rel=1e-12) and da == pytest.approx(0.02, rel=1e-9)
    dx, da, _ = distances(a, b, 0.1, "final_state", bodies=np.array([0]))
    assert dx == 0.0 and da == 0.0


def test_no_shared_frame_is_nan_not_zero():
    a = _trace([0.0, 0.1], np.zeros((2, 1, 3)), np.tile([1.0, 0, 0, 0], (2, 1, 1)))
    b = _trace([0.05, 0.15], np.zeros((2, 1, 3)), np.tile([1.0, 0, 0, 0], (2, 1, 1)))
    dx, da, n = distances(a, b, 0.1, "trajectory")
    assert n == 0 and math.isnan(dx) and math.isnan(da)


@pytest.mark.parametrize("p,k", [(1.0, 2), (2.0, 3), (4.0, 2), (4.0, 4)])
def test_observed_order_of_planted_errors(p, k):
    h = 0.01
    e, e_fine = 3.7 * h ** p, 3.7 * (h / k) ** p  # e = C h^p
    got, why = observed_order(e, e_fine, k, 1e-14)
    assert why == "" and got == pytest.approx(p, rel=1e-12)


def test_observed_order_at_the_rounding_floor_is_undefined():
    got, why = observed_order(1e-6, 1e-17, 2, 1e-14)
    assert math.isnan(got) and "rounding" in why
    got, why = observed_order(float("nan"), 1e-3, 2, 1e-14)
    assert math.isnan(got) and "not finite" in why


# ---------------------------------------------------------------------------
# the model at load time


@pytest.mark.parametrize("params,key", [("params = { refine = 1 }", "reference.params.refine"),
                                        ("params = { compare = \"energy\" }", "reference.params.compare"),
                                        ("params = { bodies = [\"nobody\"] }", "reference.params.bodies"),
                                        ("params = { refine = 2.5 }", "reference.params.refine")])
def test_bad_params_are_spec_errors(tmp_path, params, key, spring_pair):
    with pytest.raises(SpecError) as e:
        _scene(tmp_path, spring_pair.format(params=params))
    assert key in str(e.value)


def test_without_the_runner_the_metrics_are_undefined_with_the_reason(tmp_path, spring_pair):
    """compute_metrics alone (no refined runs) never makes up a number."""
    from physbench.harness import runner
    from physbench.harness.metrics import compute_metrics
    from physbench.harness.references import undefined_reason

    sc = _scene(tmp_path, spring_pair.format(params=""))
    res = runner.run(sc, "reference", compute_metrics=False)
    m = compute_metrics(sc, res.trace.valid(), dt=sc.dt)
    assert math.isnan(m["self_consistency_error"])
    assert "dt/k" in undefined_reason(m, "self_consistency_error")


# ---------------------------------------------------------------------------
# the reference engine judged by itself


@pytest.mark.parametrize("integrator,order", [("rk4", 4.0), ("heun", 2.0), ("semi_implicit_euler", 1.0)])
def test_observed_order_of_the_reference_integrators_on_a_spring_pair(tmp_path, integrator, order, spring_pair):
    """The spring pair has a closed form, but it is not used: the order
    comes from the engine's own runs at dt, dt/2, dt/4 only.  Measured
    (dt = 0.02 s): rk4 3.991, heun 1.994, semi-implicit Euler 1.056."""
    from physbench.harness import runner

    sc = _scene(tmp_path, spring_pair.format(params=""))
    res = runner.run(sc, "reference", {"integrator": integrator})
    assert res.status == "ok", res.message
    m = res.metrics
    assert m["observed_order"] == pytest.approx(order, abs=0.2)
    assert m["self_consistency_error"] > m["self_consistency_error_fine"] > 0
    assert m["refined_frames"] == 101  # every frame of the run at dt is shared
    # the refined runs are timed apart: the cost columns are the run's own
    assert res.timing["refine_s"] > 0
    assert res.metrics["cpu_s_per_sim_s"] == pytest.approx(res.timing["step_cpu_s"] / 2.0)
    # spheres that never turn: no orientation error to take an order from
    assert math.isnan(m["observed_order_angle"])


@pytest.mark.parametrize("engine", ["mujoco", "pybullet", "pymunk"])
def test_observed_order_of_the_other_engines_on_a_spring_pair(tmp_path, engine, spring_pair):
    """Each engine's own default step, judged by itself: first order
    (semi-implicit Euler and its kin).  Measured: mujoco 4.0.0 1.056,
    pybullet 3.2.7 1.056, pymunk 7.3.1 0.946."""
    from physbench.harness import runner

    sc = _scene(tmp_path, spring_pair.format(params=""))
    res = runner.run(sc, engine)
    if res.status == "unsupported":
        pytest.skip(res.message)
    assert res.status == "ok", res.message
    assert res.metrics["observed_order"] == pytest.approx(1.0, abs=0.2)


def test_observed_order_of_rk4_on_a_tumbling_body(tmp_path):
    """A torque-free box spinning about its intermediate axis: the rotation
    angle between the runs at dt, dt/2 and dt/4 gives the order of the
    engine's rotation integration.  Measured (dt = 0.01 s): 3.988."""
    from physbench.harness import runner

    sc = _scene(tmp_path, TUMBLE)
    res = runner.run(sc, "reference", {"integrator": "rk4"})
    assert res.status == "ok", res.message
    assert res.metrics["observed_order_angle"] == pytest.approx(4.0, abs=0.2)
    # it does not move: the position distances are at rounding, the order undefined
    assert math.isnan(res.metrics["observed_order"])


def test_final_state_and_k3(tmp_path, spring_pair):
    from physbench.harness import runner

    sc = _scene(tmp_path, spring_pair.format(params='params = { refine = 3, compare = "final_state" }'))
    res = runner.run(sc, "reference", {"integrator": "rk4"})
    assert res.metrics["observed_order"] == pytest.approx(4.0, abs=0.2)


def test_a_refined_run_that_fails_makes_the_metrics_undefined(tmp_path, spring_pair):
    """dt/k^2 below the engine's smallest step: no refined run, and the
    metrics say so (never 0)."""
    from physbench.adapters import get_adapter
    from physbench.harness import runner
    from physbench.harness.references import undefined_reason

    lo = get_adapter("reference").capabilities().settings["dt"].lo
    if lo is None or lo <= 0:
        pytest.skip("the reference engine's dt has no lower bound")
    text = spring_pair.format(params="params = { refine = 16 }").replace("duration = 2.0", "duration = 0.001").replace("dt = 0.02", "dt = 0.0001")
    sc = _scene(tmp_path, text)
    dt = 100 * lo  # dt/256 is below the bound
    res = runner.run(sc, "reference", {"dt": dt})
    assert math.isnan(res.metrics["self_consistency_error"])
    assert "refined run" in undefined_reason(res.metrics, "self_consistency_error")


def test_a_sweep_point_gets_a_work_precision_point(tmp_path, spring_pair):
    """The sweep's point rows (harness.points.run_point) carry the primary
    error from self-consistency beside the run's own cost, and the error
    falls as dt^4 for rk4: a work-precision curve for a scene without a
    model of its own."""
    from physbench.harness.points import Point, run_point

    p = tmp_path / "s.toml"
    p.write_text(textwrap.dedent(spring_pair.format(params="")))
    rows = {}
    for dt in (0.04, 0.02, 0.01):
        pt = Point("selfcheck.s", None, "reference", (("dt", dt), ("integrator", "rk4")), path=str(p))
        row = run_point(pt)
        assert row["status"] == "ok", row["message"]
        rows[dt] = row
    errs = [rows[dt]["primary_error"] for dt in (0.04, 0.02, 0.01)]
    assert errs[0] > errs[1] > errs[2] > 0
    assert math.log2(errs[0] / errs[1]) == pytest.approx(4.0, abs=0.2)
    assert all(math.isfinite(rows[dt]["cpu_s_per_sim_s_median"]) for dt in rows)
