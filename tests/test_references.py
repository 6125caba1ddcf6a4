"""Reference models against hand-computed values.

Each model is checked two ways: its analytic numbers against values computed
by hand (in the comments), and its metrics on synthetic traces whose error is
known by construction (an exact trace gives ~0, a trace with a planted error
gives that error back).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from physbench.contract.rotation import quat_rotate
from physbench.harness.references import MODELS, ReferenceError, get_model
from physbench.harness.runner import Trace
from physbench.contract.scene import compile_scene, load_scene
from physbench.contract.spec import validate_raw

G = 9.81


def scene_from(text: str):
    return compile_scene(validate_raw(tomllib.loads(text), "<test>"))


def make_trace(t, pos, vel=None, quat=None, angvel=None) -> Trace:
    """Trace from arrays (F,), (F, n, 3) ...; missing parts are zero/identity."""
    t = np.asarray(t, float)
    pos = np.asarray(pos, float)
    F, n = pos.shape[:2]
    if vel is None:
        vel = np.zeros((F, n, 3))
    if quat is None:
        quat = np.zeros((F, n, 4))
        quat[..., 0] = 1.0
    if angvel is None:
        angvel = np.zeros((F, n, 3))
    return Trace(t, pos, np.asarray(quat, float), np.asarray(vel, float), np.asarray(angvel, float), F)


def test_every_model_is_importable():
    for name in MODELS:
        cls = get_model(name)
        assert cls.name == name


# ---------------------------------------------------------------------------
# two-body collision (harness.references.collision)

TWO_BODY = """
[scenario]
family = "billiards"
title = "t"
duration = 1.0
dt = 0.001
planar = true
effects = ["contact", "restitution"]
[material.default]
restitution = 0.5
[[body]]
name = "a"
shape = "sphere"
radius = 0.05
mass = 1.0
position = [0.0, 0.0, 0.0]
velocity = [2.0, 0.0, 0.0]
[[body]]
name = "b"
shape = "sphere"
radius = 0.05
mass = 3.0
position = [0.5, 0.0, 0.0]
[reference]
model = "two_body_collision"
"""


def test_two_body_collision_unequal_masses():
    # m1 = 1, m2 = 3, e = 0.5, v1 = 2, v2 = 0:
    # v1' = (m1 - e m2) v1 / (m1 + m2) = (1 - 1.5) 2 / 4 = -0.25
    # v2' = (1 + e) m1 v1 / (m1 + m2) = 1.5 * 2 / 4 = 0.75
    # contact when the gap 0.5 - 0.1 = 0.4 m closes at 2 m/s: t = 0.2 s
    sc = scene_from(TWO_BODY)
    m = get_model("two_body_collision")(sc)
    assert m.t_impact == pytest.approx(0.2)
    assert m.v1_post[0] == pytest.approx(-0.25)
    assert m.v2_post[0] == pytest.approx(0.75)
    # momentum 2 kg m/s before and -0.25 + 2.25 = 2 after
    assert m.m1 * m.v1_post[0] + m.m2 * m.v2_post[0] == pytest.approx(2.0)


def test_oblique_equal_elastic_is_90_degrees():
    text = TWO_BODY.replace("mass = 3.0", "mass = 1.0").replace("restitution = 0.5", "restitution = 1.0")
    text = text.replace("position = [0.5, 0.0, 0.0]", "position = [0.5, 0.0, 0.05]")
    text = text.replace('model = "two_body_collision"', 'model = "oblique_collision"')
    sc = scene_from(text)
    m = get_model("oblique_collision")(sc)
    v1, v2 = m.v1_post, m.v2_post
    cos = v1 @ v2 / (np.linalg.norm(v1) * np.linalg.norm(v2))
    assert math.degrees(math.acos(cos)) == pytest.approx(90.0, abs=1e-9)
    # impact parameter b = R (half the contact distance): the object leaves
    # along the line of centres, 30 degrees off the cue's path, at
    # v cos 30 = 1.7320508 m/s; the cue keeps v sin 30 = 1 m/s.
    assert np.linalg.norm(v2) == pytest.approx(2 * math.cos(math.radians(30)))
    assert np.linalg.norm(v1) == pytest.approx(1.0)
    # a trace that follows the law exactly has zero angle error
    t = np.linspace(0, 1, 1001)
    vel = np.stack([m.velocities(t)[:, 0], m.velocities(t)[:, 1]], axis=1)
    out = m.metrics(make_trace(t, m.positions(t), vel))
    assert out["separation_angle_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["post_impact_velocity_error"] == pytest.approx(0.0, abs=1e-12)


# ---------------------------------------------------------------------------
# incline_block


def slope_block(angle: float, mu_k: float, mu_s: float, duration: float = 2.0) -> str:
    a = math.radians(angle)
    c = 0.05
    return f"""
[scenario]
family = "friction"
title = "t"
duration = {duration}
dt = 0.01
planar = true
effects = ["gravity", "contact", "friction"]
[material.default]
friction = {mu_k}
static_friction = {mu_s}
[[body]]
name = "block"
shape = "box"
half_extents = [0.1, 0.1, {c}]
mass = 1.0
position = [{c * math.sin(a)!r}, 0.0, {c * math.cos(a)!r}]
orientation = [{math.cos(a / 2)!r}, 0.0, {math.sin(a / 2)!r}, 0.0]
[[static]]
shape = "slope"
angle = {angle}
[reference]
model = "incline_block"
"""


def _along_slope_trace(model, a_true: float, duration: float):
    t = np.linspace(0.0, duration, 201)
    s = 0.5 * a_true * t * t
    pos = model.x0 + np.outer(s, model.d)
    vel = np.outer(a_true * t, model.d)
    return make_trace(t, pos[:, None], vel[:, None])


def test_incline_block_slides_30deg_mu_0_2():
    # a = g (sin 30 - 0.2 cos 30) = 9.81 (0.5 - 0.17320508) = 3.2058582 m/s^2
    sc = scene_from(slope_block(30.0, 0.2, 0.2))
    m = get_model("incline_block")(sc)
    assert m.regime == "slide"
    assert m.a_slide == pytest.approx(3.2058582, abs=1e-6)
    out = m.metrics(_along_slope_trace(m, 3.2058582, 2.0))
    assert out["slide_accel_error"] == pytest.approx(0.0, abs=1e-6)
    assert out["trajectory_rmse"] == pytest.approx(0.0, abs=1e-6)
    assert "stop_position_error" not in out and "creep" not in out
    # a block accelerating 1 % too fast
    out = m.metrics(_along_slope_trace(m, 1.01 * m.a_slide, 2.0))
    assert out["slide_accel_error"] == pytest.approx(0.01, rel=1e-9)


def test_incline_block_sticks_below_friction_angle():
    # tan 20 = 0.364 < mu_s = 0.5: sticks even though mu_k = 0.3 < tan 20
    sc = scene_from(slope_block(20.0, 0.3, 0.5, duration=5.0))
    m = get_model("incline_block")(sc)
    assert m.regime == "stick"
    t = np.linspace(0.0, 5.0, 101)
    # creeps 2 mm downhill (linearly) and sinks 0.5 mm into the slope: only the
    # in-plane 2 mm counts
    pos = m.x0 + np.outer(0.002 * t / 5.0, m.d) - np.outer(0.0005 * np.minimum(t, 1.0), m.n)
    out = m.metrics(make_trace(t, pos[:, None]))
    # at rest from the start: both measure the displacement from the start
    assert out["creep"] == pytest.approx(0.002, rel=1e-9)
    assert out["stop_position_error"] == pytest.approx(0.002, rel=1e-9)
    assert "slide_accel_error" not in out


def test_incline_block_critical_angle_boundary():
    # atan(0.5) = 26.565 deg: 1 degree below sticks, 1 degree above slides with
    # a = g (sin 27.565 - 0.5 cos 27.565) = 9.81 (0.462794 - 0.443243) = 0.19142
    below = get_model("incline_block")(scene_from(slope_block(25.565051177077994, 0.5, 0.5)))
    above = get_model("incline_block")(scene_from(slope_block(27.565051177077994, 0.5, 0.5)))
    assert below.regime == "stick"
    assert above.regime == "slide"
    assert above.a_slide == pytest.approx(0.19142, abs=1e-5)


def test_incline_block_thrown_uphill_stops_and_slides_back():
    """Thrown up 35 degrees at 2 m/s (mu_k 0.3, mu_s 0.4 < tan 35): by hand,
    a_up = 9.81 (sin 35 + 0.3 cos 35) = 9.81 (0.5735764 + 0.2457456)
    = 8.03755 m/s^2 against the motion, stop at 2 / 8.03755 = 0.248832 s after
    0.248832 m; then a_back = 9.81 (0.5735764 - 0.2457456) = 3.21602 m/s^2
    down from rest: at 1.5 s, s = -0.248832 + 3.21602 (1.5 - 0.248832)^2 / 2
    = 2.268381 m downhill of the start."""
    text = slope_block(35.0, 0.3, 0.4, duration=1.5).replace(
        'mass = 1.0', 'mass = 1.0\nvelocity = [-1.6383040885779836, 0.0, 1.1471528727020921]')
    m = get_model("incline_block")(scene_from(text))
    assert m.u0 == pytest.approx(-2.0, abs=1e-12)
    assert m.a_slide == pytest.approx(8.03755, abs=1e-5)
    assert m.t_stop == pytest.approx(0.248832, abs=1e-6)
    assert m.a_back == pytest.approx(3.21602, abs=1e-5)
    assert float(m.distance(np.array([m.t_stop]))[0]) == pytest.approx(-0.248832, abs=1e-6)
    assert float(m.distance(np.array([1.5]))[0]) == pytest.approx(2.268381, abs=1e-6)
    t = np.linspace(0.0, 1.5, 1501)

    def trace(delay):
        """The closed form, turning round ``delay`` s late (stuck meanwhile)."""
        tt = np.where(t > m.t_stop, np.maximum(t - delay, m.t_stop), t)
        s = m.distance(tt)
        v = np.where(tt < m.t_stop, m.u0 + m.a_slide * tt, m.a_back * (tt - m.t_stop))
        return make_trace(t, (m.x0 + np.outer(s, m.d))[:, None], np.outer(v, m.d)[:, None])

    out = m.metrics(trace(0.0))
    assert out["final_position_error"] == pytest.approx(0.0, abs=1e-12)
    assert out["slide_accel_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["return_accel_error"] == pytest.approx(0.0, abs=1e-9)
    assert "stop_position_error" not in out and "creep" not in out
    # a turnaround 1/480 s late (half a step at 1/240 s): the slide back keeps
    # its acceleration but ends a_back * delay * (T - t_stop - delay / 2) off
    d = 1 / 480
    out = m.metrics(trace(d))
    assert out["return_accel_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["final_position_error"] == pytest.approx(m.a_back * d * (1.5 - m.t_stop - d / 2), rel=1e-9)


def test_stop_position_error_and_creep_are_apart():
    """friction.box_slides_to_rest (2 m/s, mu_k 0.4 on the level: stops
    after d = 4 / (2 * 0.4 * 9.81) = 0.509684 m at t = 0.509684 s).  A box
    that decelerates too weakly, stops 5 mm past that point, and then creeps
    2 mm further: stop_position_error (from the reference stop point) reads
    7 mm, creep (from where it came to rest) 2 mm; a box that stops exactly
    where it should and stays reads 0 for both.  One that never comes to
    rest has no creep, with the reason."""
    from physbench.harness.references import undefined_reason

    m = get_model("slide_to_rest")(load_scene("friction.box_slides_to_rest"))
    d_ref = 4.0 / (2 * 0.4 * G)
    assert m.d_stop == pytest.approx(d_ref, rel=1e-12) and m.t_stop == pytest.approx(d_ref, rel=1e-12)
    t = np.linspace(0.0, 1.0, 1001)

    def trace(d_stop, creep):
        a = 4.0 / (2 * d_stop)  # the deceleration that stops 2 m/s after d_stop
        ts = 2.0 / a
        s = np.where(t < ts, 2.0 * t - 0.5 * a * t * t, d_stop + creep * (t - ts) / (1.0 - ts))
        v = np.where(t < ts, 2.0 - a * t, creep / (1.0 - ts))
        return make_trace(t, (m.x0 + np.outer(s, m.d))[:, None], np.outer(v, m.d)[:, None])

    out = m.metrics(trace(d_ref, 0.0))
    assert out["stop_position_error"] == pytest.approx(0.0, abs=1e-12)
    assert out["creep"] == pytest.approx(0.0, abs=1e-12)
    out = m.metrics(trace(d_ref + 0.005, 0.002))
    assert out["stop_position_error"] == pytest.approx(0.007, abs=1e-12)
    # at rest from the last decelerating frame (speed <= a dt = 3.9 mm/s,
    # still moving at the next): at most a dt^2 / 2 = 2e-6 m short of the
    # stop, then the 2 mm
    assert out["creep"] == pytest.approx(0.002, abs=2e-6)
    # a soft stop: the closed form down to 10 mm/s, then an exponential tail
    # (time constant 50 ms) that never reaches zero: at rest from the first
    # frame at <= a dt (3.9 mm/s), creep the tail's rest, <= 3.9e-3 * 0.05 m
    a, t1, tau = 2.0 / m.t_stop, m.t_stop - 0.01 / (2.0 / m.t_stop), 0.05
    v = np.where(t < t1, 2.0 - a * t, 0.01 * np.exp(-(t - t1) / tau))
    s = np.where(t < t1, 2.0 * t - 0.5 * a * t * t, 2.0 * t1 - 0.5 * a * t1 * t1 + 0.01 * tau * (1 - np.exp(-(t - t1) / tau)))
    out = m.metrics(make_trace(t, (m.x0 + np.outer(s, m.d))[:, None], np.outer(v, m.d)[:, None]))
    assert 0.0 < out["creep"] <= a * 1e-3 * tau
    never = make_trace(t, (m.x0 + np.outer(0.5 * t, m.d))[:, None], np.outer(np.full_like(t, 0.5), m.d)[:, None])
    out = m.metrics(never)
    assert math.isnan(out["creep"]) and "never came to rest" in undefined_reason(out, "creep")


# ---------------------------------------------------------------------------
# rolling_sphere


def slope_ball(angle: float, mu: float, r: float = 0.1) -> str:
    a = math.radians(angle)
    return f"""
[scenario]
family = "friction"
title = "t"
duration = 2.0
dt = 0.01
planar = true
effects = ["gravity", "contact", "friction"]
[material.default]
friction = {mu}
[[body]]
name = "ball"
shape = "sphere"
radius = {r}
mass = 1.0
position = [{r * math.sin(a)!r}, 0.0, {r * math.cos(a)!r}]
[[static]]
shape = "slope"
angle = {angle}
[reference]
model = "rolling_sphere"
"""


def test_rolling_sphere_rolls():
    # rolling needs mu >= 2/7 tan 20 = 0.104; a = 5/7 g sin 20 = 2.396584 m/s^2,
    # alpha = a / R = 23.96584 rad/s^2 about +y (downhill is +x)
    m = get_model("rolling_sphere")(scene_from(slope_ball(20.0, 0.5)))
    assert m.regime == "roll"
    assert m.a == pytest.approx(2.396584, abs=1e-6)
    assert m.alpha == pytest.approx(23.96584, abs=1e-5)
    np.testing.assert_allclose(m.axis, [0.0, 1.0, 0.0], atol=1e-15)
    t = np.linspace(0, 2, 201)
    pos = m.x0 + np.outer(0.5 * m.a * t * t, m.d)
    vel = np.outer(m.a * t, m.d)
    w = np.outer(m.alpha * t, m.axis)
    out = m.metrics(make_trace(t, pos[:, None], vel[:, None], angvel=w[:, None]))
    assert out["roll_accel_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["spin_accel_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["rolling_slip"] == pytest.approx(0.0, abs=1e-9)


def test_rolling_sphere_slips():
    # mu = 0.1 < 2/7 tan 30 = 0.165: slips.
    # a = g (sin 30 - 0.1 cos 30) = 9.81 (0.5 - 0.0866025) = 4.055429 m/s^2
    # alpha = mu m g cos 30 R / (2/5 m R^2) = 5 * 0.1 * 9.81 * 0.8660254 / (2 * 0.1)
    #       = 21.239273 rad/s^2
    m = get_model("rolling_sphere")(scene_from(slope_ball(30.0, 0.1)))
    assert m.regime == "slip"
    assert m.a == pytest.approx(4.055429, abs=1e-6)
    assert m.alpha == pytest.approx(21.239273, abs=1e-6)


def slope_cylinder(angle: float, mu: float, q: str = "[0.7071067811865476, -0.7071067811865476, 0.0, 0.0]") -> str:
    text = slope_ball(angle, mu).replace('shape = "sphere"', 'shape = "cylinder"\nhalf_length = 0.05\norientation = ' + q)
    return text.replace('model = "rolling_sphere"', 'model = "rolling_cylinder"').replace(
        '"friction"]', '"friction", "gyroscopic"]').replace("planar = true\n", "")


def test_rolling_cylinder_rolls_and_slips():
    # k = I_axis / (m r^2) = 1/2: rolls when mu >= 1/3 tan a;
    # a = 2/3 g sin 20 = 2.236817 m/s^2, alpha = a / r
    m = get_model("rolling_cylinder")(scene_from(slope_cylinder(20.0, 0.5)))
    assert m.regime == "roll" and m.k == pytest.approx(0.5, abs=1e-12)
    assert m.a == pytest.approx(2.0 / 3.0 * 9.81 * math.sin(math.radians(20.0)), rel=1e-12)
    assert m.alpha == pytest.approx(m.a / 0.1, rel=1e-12)
    # mu = 0.1 < 1/3 tan 30 = 0.192: slips; alpha = mu g cos 30 r / (r^2 / 2)
    m = get_model("rolling_cylinder")(scene_from(slope_cylinder(30.0, 0.1)))
    assert m.regime == "slip"
    assert m.alpha == pytest.approx(2 * 0.1 * 9.81 * math.cos(math.radians(30.0)) / 0.1, rel=1e-12)


def test_rolling_cylinder_needs_its_axis_across_the_slope():
    # axis (body z) left along world z: it would not roll down the slope
    with pytest.raises(ReferenceError, match="axis along the roll axis"):
        get_model("rolling_cylinder")(scene_from(slope_cylinder(20.0, 0.5, q="[1.0, 0.0, 0.0, 0.0]")))
    with pytest.raises(ReferenceError, match="needs a cylinder"):
        get_model("rolling_cylinder")(scene_from(slope_ball(20.0, 0.5).replace("rolling_sphere", "rolling_cylinder")))


# ---------------------------------------------------------------------------
# rolling_resistance


def rolling_ball(angle: float, u0: float, mur: float = 0.005, mu: float = 0.5, r: float = 0.1) -> str:
    """A ball on a slope of ``angle`` degrees rolling downhill at u0 (m/s;
    negative: uphill) with w0 = u0 / r, rolling friction ``mur`` (m)."""
    a = math.radians(angle)
    d = (math.cos(a), 0.0, -math.sin(a))
    text = slope_ball(angle, mu, r).replace('"friction"]', '"friction", "rolling_friction"]')
    text = text.replace(f"friction = {mu}\n", f"friction = {mu}\nrolling_friction = {mur}\n")
    text = text.replace("mass = 1.0\n", f"mass = 1.0\nvelocity = [{u0 * d[0]!r}, 0.0, {u0 * d[2]!r}]\n"
                                           f"angular_velocity = [0.0, {u0 / r!r}, 0.0]\n")
    return text.replace('model = "rolling_sphere"', 'model = "rolling_resistance"').replace("duration = 2.0", "duration = 4.0")


def test_rolling_resistance_regimes():
    # flat, 1 m/s: a = -5/7 (0.005 / 0.1) 9.81 = -0.3503571 m/s^2, stops at
    # 1 / 0.3503571 = 2.854230 s after 1 / (2 * 0.3503571) = 1.427115 m
    m = get_model("rolling_resistance")(scene_from(rolling_ball(0.0, 1.0)))
    assert m.regime == "stop"
    assert m.phases[0][3] == pytest.approx(-0.3503571, abs=1e-7)
    assert m.t_stop == pytest.approx(2.854230, abs=1e-6)
    assert m.distance(np.array([3.0, 4.0])) == pytest.approx([1.427115, 1.427115], abs=1e-6)
    # 2 degrees at rest: tan 2 = 0.0349 <= 0.05: holds
    assert get_model("rolling_resistance")(scene_from(rolling_ball(2.0, 0.0))).regime == "hold"
    # 5 degrees at rest: a = 5/7 9.81 (sin 5 - 0.05 cos 5) = 0.2616889 m/s^2
    m = get_model("rolling_resistance")(scene_from(rolling_ball(5.0, 0.0)))
    assert m.regime == "roll" and m.phases[0][3] == pytest.approx(0.2616889, abs=1e-7)
    # 5 degrees, 1 m/s uphill: a = 5/7 9.81 (sin 5 + 0.05 cos 5) = 0.9597367 m/s^2
    # until t = 1.041952 s, then back down with 0.2616889
    m = get_model("rolling_resistance")(scene_from(rolling_ball(5.0, -1.0)))
    assert m.regime == "stop_and_return"
    assert m.phases[0][3] == pytest.approx(0.9597367, abs=1e-7)
    assert m.t_stop == pytest.approx(1.041952, abs=1e-6)
    assert m.phases[1][3] == pytest.approx(0.2616889, abs=1e-7)
    # s(t) continuous at the turnaround: -1 * t + a t^2 / 2 = -0.5209760 m
    assert m.distance(np.array([m.t_stop])) == pytest.approx([-0.5209760], abs=1e-6)


def test_rolling_resistance_metrics_on_exact_and_planted_traces():
    m = get_model("rolling_resistance")(scene_from(rolling_ball(0.0, 1.0)))
    t = np.linspace(0.0, 4.0, 961)
    s = m.distance(t)
    u = np.where(t < m.t_stop, 1.0 + m.phases[0][3] * t, 0.0)
    pos = m.x0 + np.outer(s, m.d)
    vel = np.outer(u, m.d)
    w = np.outer(u / m.R, m.axis)
    out = m.metrics(make_trace(t, pos[:, None], vel[:, None], angvel=w[:, None]))
    assert out["roll_accel_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["spin_accel_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["rolling_slip"] == pytest.approx(0.0, abs=1e-12)
    assert out["stop_position_error"] == pytest.approx(0.0, abs=1e-12)
    assert out["creep"] == pytest.approx(0.0, abs=1e-12)
    assert out["final_position_error"] == pytest.approx(0.0, abs=1e-12)
    # planted: 2 % weaker deceleration, and a slip of 0.03 m/s
    a2 = 0.98 * m.phases[0][3]
    u2 = 1.0 + a2 * t
    out = m.metrics(make_trace(t, pos[:, None], np.outer(u2, m.d)[:, None],
                               angvel=np.outer((u2 - 0.03) / m.R, m.axis)[:, None]))
    assert out["roll_accel_error"] == pytest.approx(0.02, abs=1e-9)
    assert out["rolling_slip"] == pytest.approx(0.03, abs=1e-9)
    # a ball that stops 5 mm too far and stays there: off the stop point,
    # no creep
    out = m.metrics(make_trace(t, (pos + np.outer(np.where(t >= m.t_stop, 0.005, 0.0), m.d))[:, None],
                               vel[:, None]))
    assert out["stop_position_error"] == pytest.approx(0.005, abs=1e-12)
    assert out["creep"] == pytest.approx(0.0, abs=1e-12)
    assert out["final_position_error"] == pytest.approx(0.005, abs=1e-12)


def test_rolling_resistance_refuses_what_it_does_not_model():
    with pytest.raises(ReferenceError, match="rolling start"):
        get_model("rolling_resistance")(scene_from(rolling_ball(0.0, 1.0).replace("angular_velocity = [0.0, 10.0, 0.0]",
                                                                                  "angular_velocity = [0.0, 0.0, 0.0]")))
    # rolling against mu_r = 0.05 m on a 5 cm ball needs more friction than 0.1
    with pytest.raises(ReferenceError, match="would slip"):
        get_model("rolling_resistance")(scene_from(rolling_ball(0.0, 1.0, mur=0.05, mu=0.1, r=0.05)))
    with pytest.raises(ReferenceError, match="rolling_friction"):
        get_model("rolling_resistance")(scene_from(rolling_ball(0.0, 1.0, mur=0.0)))


# ---------------------------------------------------------------------------
# spin_to_rest


def spinning_capsule(w: float = 10.0, mu_k: float = 0.3, mu_s: float = 0.6, z: float = 0.02,
                     orientation: str = "[0.7071067811865476, 0.0, 0.7071067811865476, 0.0]") -> str:
    return f"""
[scenario]
family = "friction"
title = "t"
duration = 0.5
dt = 0.004
effects = ["gravity", "contact", "friction", "gyroscopic"]
[material.default]
friction = {mu_k}
static_friction = {mu_s}
[[body]]
name = "capsule"
shape = "capsule"
radius = 0.02
half_length = 0.1
mass = 1.0
position = [0.0, 0.0, {z}]
orientation = {orientation}
angular_velocity = [0.0, 0.0, {w}]
[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]
[reference]
model = "spin_to_rest"
"""


def _spin_trace(m, alpha: float, t_end: float = 0.5, frames: int = 501):
    """A capsule turning about z with w0 - alpha t until it stops."""
    t = np.linspace(0.0, t_end, frames)
    ts = np.minimum(t, abs(m.w0) / alpha)
    th = m.w0 * ts - math.copysign(0.5 * alpha, m.w0) * ts * ts
    w = np.where(t < abs(m.w0) / alpha, m.w0 - math.copysign(alpha, m.w0) * t, 0.0)
    # lying along x (body z -> world x), turned by th about z
    q0 = np.array([math.sqrt(0.5), 0.0, math.sqrt(0.5), 0.0])
    qz = np.stack([np.cos(th / 2), 0 * th, 0 * th, np.sin(th / 2)], axis=1)
    w1, v1 = qz[:, :1], qz[:, 1:]
    quat = np.concatenate([w1 * q0[0] - v1 @ q0[1:, None],
                           w1 * q0[1:] + q0[0] * v1 + np.cross(v1, q0[1:])], axis=1)
    return make_trace(t, np.tile(m.x0, (frames, 1))[:, None], quat=quat[:, None],
                      angvel=np.outer(w, [0.0, 0.0, 1.0])[:, None])


def test_spin_to_rest_by_hand():
    # transverse moment of the capsule (r 0.02, h 0.1, 1 kg, uniform): the
    # cylinder's 0.88235 kg (0.2^2 / 12 + 0.02^2 / 4) = 3.02941e-3 plus the
    # caps' 0.11765 kg (2 0.02^2 / 5 + 0.2^2 / 4 + 3 0.2 0.02 / 8) =
    # 1.37176e-3: 4.40118e-3 kg m^2; alpha = 0.3 9.81 0.1 / 4.40118e-3 =
    # 66.8685 rad/s^2, t_stop = 10 / 66.8685 = 0.149548 s, angle =
    # 100 / (2 66.8685) = 0.747738 rad
    m = get_model("spin_to_rest")(scene_from(spinning_capsule()))
    assert m.I_n == pytest.approx(4.40118e-3, rel=1e-5)
    assert m.alpha == pytest.approx(66.8685, rel=1e-5)
    assert m.t_stop == pytest.approx(0.149548, rel=1e-5)
    assert m.theta_stop == pytest.approx(0.747738, rel=1e-5)
    # the static coefficient plays no part; a negative spin turns the other way
    m2 = get_model("spin_to_rest")(scene_from(spinning_capsule(w=-10.0, mu_s=0.3)))
    assert m2.alpha == m.alpha and m2.theta_stop == -m.theta_stop


@pytest.mark.parametrize("w", [10.0, -40.0])
def test_spin_to_rest_metrics_on_exact_and_planted_traces(w):
    m = get_model("spin_to_rest")(scene_from(spinning_capsule(w=w)))
    t_end = 1.0 if abs(w) > 10 else 0.5
    out = m.metrics(_spin_trace(m, m.alpha, t_end, 2001))
    assert out["spin_decel_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["spin_decel"] == pytest.approx(m.alpha, rel=1e-9)
    assert out["spin_stop_angle_error"] == pytest.approx(0.0, abs=1e-9)
    assert out["final_position_error"] == 0.0
    # 2 % too much friction: the deceleration 2 % high, the angle 1/1.02 of the truth
    out = m.metrics(_spin_trace(m, 1.02 * m.alpha, t_end, 2001))
    assert out["spin_decel_error"] == pytest.approx(0.02, rel=1e-6)
    assert out["spin_stop_angle_error"] == pytest.approx(1 - 1 / 1.02, rel=1e-6)
    # twice the friction (mu_s acting): the fit stops where the spin stopped
    out = m.metrics(_spin_trace(m, 2.0 * m.alpha, t_end, 2001))
    assert out["spin_decel_error"] == pytest.approx(1.0, rel=1e-6)
    assert out["spin_stop_angle_error"] == pytest.approx(0.5, rel=1e-6)
    # a run that ends before the stop has no stop angle
    out = m.metrics(_spin_trace(m, m.alpha, 0.9 * m.t_stop, 501))
    assert "spin_stop_angle_error" not in out
    assert out["spin_decel_error"] == pytest.approx(0.0, abs=1e-9)


def test_spin_to_rest_refuses_what_it_does_not_model():
    with pytest.raises(ReferenceError, match="lying flat"):
        get_model("spin_to_rest")(scene_from(spinning_capsule(orientation="[1.0, 0.0, 0.0, 0.0]", z=0.12)))
    with pytest.raises(ReferenceError, match="resting on the plane"):
        get_model("spin_to_rest")(scene_from(spinning_capsule(z=0.05)))
    with pytest.raises(ReferenceError, match="along the normal"):
        get_model("spin_to_rest")(scene_from(spinning_capsule(w=0.0)))
    with pytest.raises(ReferenceError, match="kinetic friction"):
        get_model("spin_to_rest")(scene_from(spinning_capsule(mu_k=0.0, mu_s=0.0)))
    with pytest.raises(ReferenceError, match="needs a capsule"):
        get_model("spin_to_rest")(scene_from(spinning_capsule().replace('shape = "capsule"', 'shape = "sphere"')
                                             .replace("half_length = 0.1\n", "")))


# ---------------------------------------------------------------------------
# bounce_heights

BOUNCE = """
[scenario]
family = "billiards"
title = "t"
duration = 3.0
dt = 0.001
planar = true
effects = ["gravity", "contact", "restitution"]
[material.default]
restitution = 0.5
[[body]]
name = "ball"
shape = "sphere"
radius = 0.05
mass = 1.0
position = [0.0, 0.0, 1.05]
[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]
[reference]
model = "bounce_heights"
"""


def _bounce_trace(h0: float, e: float, r: float, duration: float, dt: float = 1e-3):
    """Sampled exact bouncing motion with restitution e (independent of the
    model's own code: event-driven, step by step)."""
    t = np.arange(0.0, duration + dt / 2, dt)
    z = np.empty_like(t)
    vz = np.empty_like(t)
    tb, v, h = 0.0, 0.0, h0  # current flight: start time, upward speed, start height
    for i, ti in enumerate(t):
        while True:
            s = ti - tb
            hz = h + v * s - 0.5 * G * s * s
            if hz >= 0 or v == 0 and h == 0:
                break
            # landing time of this flight
            land = (v + math.sqrt(v * v + 2 * G * h)) / G
            vin = v - G * land
            tb, v, h = tb + land, -e * vin, 0.0
            if v < 1e-6:
                v = 0.0
        z[i] = max(hz, 0.0) + r
        vz[i] = v - G * s if z[i] > r else 0.0
    pos = np.zeros((len(t), 1, 3))
    pos[:, 0, 2] = z
    vel = np.zeros((len(t), 1, 3))
    vel[:, 0, 2] = vz
    return make_trace(t, pos, vel)


def test_bounce_heights_e_0_5():
    # h_n = e^(2n) h0 = 0.25, 0.0625, 0.015625 m from h0 = 1 m
    m = get_model("bounce_heights")(scene_from(BOUNCE))
    assert m.h0 == pytest.approx(1.0)
    np.testing.assert_allclose(m.reference_apexes(3.0), [0.25, 0.0625, 0.015625], rtol=1e-12)
    # first impact at sqrt(2 h0 / g) = 0.4515236 s; at rest after
    # t1 (1 + 2 e / (1 - e)) = 3 t1 = 1.3545709 s
    assert m.t1 == pytest.approx(0.4515236, abs=1e-7)
    assert m.height(np.array([1.36, 2.0])) == pytest.approx([0.0, 0.0], abs=1e-12)
    assert m.height(np.array([m.t1 + 0.5 * m.v1 / G]))[0] == pytest.approx(0.25)
    out = m.metrics(_bounce_trace(1.0, 0.5, 0.05, 3.0))
    assert out["bounce_ratio_error"] < 1e-9  # apexes from the state: no sampling floor
    assert out["trajectory_rmse"] < 1e-3
    # a ball that bounces with e = 0.6 instead: error 0.1
    out = m.metrics(_bounce_trace(1.0, 0.6, 0.05, 3.0))
    assert out["bounce_ratio_error"] == pytest.approx(0.1, abs=1e-9)
    # a ball that does not bounce at all: error e
    out = m.metrics(_bounce_trace(1.0, 0.0, 0.05, 3.0))
    assert out["bounce_ratio_error"] == pytest.approx(0.5)


@pytest.mark.parametrize("dt", [1e-3, 1 / 60])
def test_bounce_apex_comes_from_the_state(dt):
    """Each apex is h + v^2 / (2 g) at the frame where the flight turns
    down, not the highest sampled frame (which misses it by up to
    g dt^2 / 8, 0.35 mm at 1/60 s: e_3 = sqrt(A_3 / A_2) off by ~1e-2).
    Planted: bounces with e = 0.5 but the second rebound 1 % faster
    (apex A_2 = 0.0625 * 1.01^2): e_2 = 0.505, e_3 = 0.5 / 1.01, so the
    error is max(0.005, 0.5 - 0.5 / 1.01) = 0.005 exactly, at either frame
    rate."""
    m = get_model("bounce_heights")(scene_from(BOUNCE))
    t = np.arange(0.0, 3.0 + dt / 2, dt)
    # event-driven by hand: drop from 1 m, rebound speeds v1 e, v1 e^2 1.01, v1 e^3 1.01
    v1 = math.sqrt(2 * G)
    ups = [0.5 * v1, 0.25 * v1 * 1.01, 0.125 * v1 * 1.01, 0.0625 * v1 * 1.01]
    t_b = [math.sqrt(2 / G)]
    for u in ups[:-1]:
        t_b.append(t_b[-1] + 2 * u / G)
    h = 1.0 - 0.5 * G * t * t
    vz = -G * t
    for tb, u in zip(t_b, ups):
        s = t - tb
        fl = s >= 0
        h[fl] = u * s[fl] - 0.5 * G * s[fl] ** 2
        vz[fl] = u - G * s[fl]
    h = np.maximum(h, 0.0)
    pos = np.zeros((len(t), 1, 3))
    pos[:, 0, 2] = h + 0.05
    vel = np.zeros((len(t), 1, 3))
    vel[:, 0, 2] = vz
    tr = make_trace(t, pos, vel)
    apexes = m.measured_apexes(tr)
    np.testing.assert_allclose(apexes[:3], [u * u / (2 * G) for u in ups[:3]], rtol=1e-12)
    out = m.metrics(tr)
    assert out["bounce_ratio_error"] == pytest.approx(0.005, abs=1e-12)


def test_bounce_ratio_is_exact_on_the_reference_engine():
    """The reference engine's flights are exact (h + v^2 / 2g conserved to
    round-off): the metric reads round-off, not frame sampling (it read
    2.4e-5 at e^2 = 0.98 from the highest sampled frame)."""
    from physbench.harness.runner import run

    for over in ({}, {"material.default.restitution": math.sqrt(0.98)}):
        res = run(load_scene("billiards.ball_drop_bounce", overrides=over), "reference")
        assert res.status == "ok", res.message
        assert res.metrics["bounce_ratio_error"] <= 1e-9, (over, res.metrics["bounce_ratio_error"])


# ---------------------------------------------------------------------------
# static_stack


def test_static_stack_drift_and_residual():
    sc = load_scene("stacking.column_5")
    m = get_model("static_stack")(sc)
    x0 = sc.initial_state()[0]
    t = np.linspace(0, 5, 501)
    pos = np.repeat(x0[None], len(t), axis=0)
    pos[:, 4, 0] += 0.003 * t / 5  # top box slides 3 mm
    vel = np.zeros_like(pos)
    vel[:, 4, 0] = 0.0006
    vel[:400, 2, 2] = 0.5  # a transient early on: outside the last 10 %
    out = m.metrics(make_trace(t, pos, vel))
    assert out["stack_drift"] == pytest.approx(0.003)
    assert out["residual_velocity"] == pytest.approx(0.0006)


# ---------------------------------------------------------------------------
# log_pile


def _log_pile_text(mu: float, x_top: float = 0.0, z_top: float | None = None, x_right: float = 0.051,
                   x_left: float = -0.051) -> str:
    text = (Path(__file__).resolve().parents[1] / "scenarios" / "stacking" / "log_pile.toml").read_text()
    text = text.replace("friction = 0.32\nstatic_friction = 0.32", f"friction = {mu}\nstatic_friction = {mu}")
    text = text.replace("position = [0.051, 0.0, 0.05]", f"position = [{x_right}, 0.0, 0.05]")
    text = text.replace("position = [-0.051, 0.0, 0.05]", f"position = [{x_left}, 0.0, 0.05]")
    if z_top is not None or x_top:
        text = text.replace("position = [0.0, 0.0, 0.13601744009211156]",
                            f"position = [{x_top}, 0.0, {z_top if z_top is not None else 0.13601744009211156}]")
    return text


def test_log_pile_statics():
    """By hand: half spacing s = 0.051, r = 0.05: sin th = 0.51, th =
    30.6638 deg, tan(th / 2) = 0.274168; the ground's share with equal
    masses is a third of it, 0.091389.  The pile holds from that friction
    up, and the top log rests at r + sqrt(4 r^2 - s^2) = 0.1360174."""
    m = get_model("log_pile")(load_scene("stacking.log_pile"))
    assert m.friction_demand == pytest.approx(0.2741678, rel=1e-6)
    assert m.ground_friction_demand == pytest.approx(0.2741678 / 3.0, rel=1e-6)
    assert m.full_drop == pytest.approx(0.0860174, rel=1e-6)
    assert m.holds
    assert not get_model("log_pile")(scene_from(_log_pile_text(0.274))).holds
    assert get_model("log_pile")(scene_from(_log_pile_text(0.2742))).holds
    assert not get_model("log_pile")(load_scene("stacking.log_pile_slides")).holds


def test_log_pile_metrics_on_planted_traces():
    sc = load_scene("stacking.log_pile")
    m = get_model("log_pile")(sc)
    x0 = sc.initial_state()[0]
    t = np.linspace(0, 3, 301)
    top = int(np.argmax(x0[:, 2]))
    pos = np.repeat(x0[None], len(t), axis=0)
    pos[:, top, 2] -= 0.0005 * t / 3  # sinks 0.5 mm: held
    out = m.metrics(make_trace(t, pos))
    assert out["top_drop"] == pytest.approx(0.0005)
    assert out["stack_drift"] == pytest.approx(0.0005)
    assert out["pile_holds"] and not out["top_fell"] and out["outcome_ok"]
    assert out["final_position_error"] == pytest.approx(0.0005)
    # the whole pile rolls away 7 cm (the lower logs rolling, the top one
    # turning the other way): the top does not drop, the drift tells
    pos = np.repeat(x0[None], len(t), axis=0)
    pos[:, :, 0] += 0.07 * (t / 3)[:, None]
    out = m.metrics(make_trace(t, pos))
    assert out["top_drop"] == pytest.approx(0.0, abs=1e-15) and out["outcome_ok"]
    assert out["stack_drift"] == pytest.approx(0.07)
    # collapsed: the top falls 8.6 cm to the ground; wrong for this pile,
    # right for the one below the demand
    pos = np.repeat(x0[None], len(t), axis=0)
    pos[:, top, 2] -= np.minimum(t, 0.0860174)
    out = m.metrics(make_trace(t, pos))
    assert out["top_fell"] and not out["outcome_ok"]
    slides = get_model("log_pile")(load_scene("stacking.log_pile_slides"))
    out = slides.metrics(make_trace(t, pos))
    assert out["top_fell"] and out["outcome_ok"] and "final_position_error" not in out


@pytest.mark.parametrize("kw,what", [
    (dict(x_right=0.045, x_left=-0.045), "apart"),  # lower logs overlap
    (dict(x_right=0.06), "centred"),
    (dict(z_top=0.14), "resting"),
])
def test_log_pile_refuses_other_piles(kw, what):
    with pytest.raises(ReferenceError, match=what):
        get_model("log_pile")(scene_from(_log_pile_text(0.32, **kw)))


# ---------------------------------------------------------------------------
# no_tunnelling


def test_no_tunnelling_bullet():
    sc = load_scene("tunnelling.bullet_100")
    m = get_model("no_tunnelling")(sc)
    t = np.linspace(0, 0.1, 25)
    # exact: reaches the wall face (x = 0.5 - 0.002 - 0.005) at t = 4.93 ms,
    # then leaves at -e v = -50 m/s
    th = 0.493 / 100.0
    x = np.where(t < th, 100 * t, 0.493 - 50 * (t - th))
    v = np.where(t < th, 100.0, -50.0)
    pos = np.zeros((25, 1, 3))
    pos[:, 0, 0] = x
    vel = np.zeros((25, 1, 3))
    vel[:, 0, 0] = v
    out = m.metrics(make_trace(t, pos, vel))
    assert out["tunnelled"] == 0.0
    assert out["reflected_velocity_error"] == pytest.approx(0.0)
    # straight through: ends at x = 10 m with v unchanged: error (1 + e) = 1.5
    pos[:, 0, 0] = 100 * t
    vel[:, 0, 0] = 100.0
    out = m.metrics(make_trace(t, pos, vel))
    assert out["tunnelled"] == 1.0
    assert out["reflected_velocity_error"] == pytest.approx(1.5)


def test_no_tunnelling_around_the_edge_is_not_tunnelling():
    sc = load_scene("tunnelling.bullet_100")
    m = get_model("no_tunnelling")(sc)
    t = np.array([0.0, 1.0, 2.0])
    # passes beside the wall (|y| = 2 m > 0.5 m half-size + radius)
    pos = np.array([[[0.0, 0.0, 0.0]], [[0.5, 2.0, 0.0]], [[1.0, 2.0, 0.0]]])
    assert m.metrics(make_trace(t, pos))["tunnelled"] == 0.0
    # crosses within the face
    pos = np.array([[[0.0, 0.0, 0.0]], [[0.4, 0.3, 0.0]], [[1.0, 0.3, 0.0]]])
    assert m.metrics(make_trace(t, pos))["tunnelled"] == 1.0


def test_no_tunnelling_counts_crossings_within_the_face_only():
    """The crossing point between two frames on opposite sides decides: a
    long body tipping over the slab's edge (centre crossing within a
    bounding radius of the face, as a spinning bar skidding off its slab
    did) is not tunnelling; a fast body whose frames both lie beside the
    face but whose straight path between them crosses inside it is."""
    sc = load_scene("tunnelling.bullet_100")  # wall: mid-plane x = 0.5, face |y|, |z| <= 0.5
    m = get_model("no_tunnelling")(sc)
    t = np.array([0.0, 1.0, 2.0])
    # goes round the edge (crosses x = 0.5 at y = 0.8, beside the face), then sits behind the
    # wall in the face's shadow
    pos = np.array([[[0.0, 0.8, 0.0]], [[1.0, 0.8, 0.0]], [[1.0, 0.2, 0.0]]])
    assert m.metrics(make_trace(t, pos))["tunnelled"] == 0.0
    # a long body (bounding radius 0.5 m) tipping over the edge: crossing at y = 0.6, inside the
    # old face + radius window, outside the face
    sc_long = load_scene("tunnelling.spinning_long_box")
    m_long = get_model("no_tunnelling")(sc_long)
    half = sc_long.statics[0].half_extents[0]
    z0 = sc_long.bodies[0].position[2]
    pos = np.array([[[0.0, 0.0, z0]], [[half + 0.3, 0.0, 0.01]], [[half + 0.4, 0.0, -0.2]]])
    assert m_long.metrics(make_trace(t, pos))["tunnelled"] == 0.0
    pos[2, 0, 0] = half - 0.3  # the same drop with the crossing inside the face
    pos[1, 0, 0] = half - 0.3
    assert m_long.metrics(make_trace(t, pos))["tunnelled"] == 1.0
    # frames beside the face on both sides (y = -0.7 and y = 0.7), the straight path crosses at y = 0
    pos = np.array([[[0.0, 0.0, 0.0]], [[0.4, -0.7, 0.0]], [[0.6, 0.7, 0.0]]])
    assert m.metrics(make_trace(t, pos))["tunnelled"] == 1.0
    # a frame exactly on the mid-plane: + 0 - crosses there, + 0 + does not
    t4 = np.array([0.0, 1.0, 2.0, 3.0])
    pos = np.array([[[0.0, 0.0, 0.0]], [[0.5, 0.1, 0.0]], [[1.0, 0.1, 0.0]], [[1.0, 0.1, 0.0]]])
    assert m.metrics(make_trace(t4, pos))["tunnelled"] == 1.0
    pos = np.array([[[0.0, 0.0, 0.0]], [[0.5, 0.1, 0.0]], [[0.2, 0.1, 0.0]], [[0.2, 0.1, 0.0]]])
    assert m.metrics(make_trace(t4, pos))["tunnelled"] == 0.0
    # and back again through the face counts too (a body that went round and came back through)
    pos = np.array([[[0.0, 0.8, 0.0]], [[1.0, 0.8, 0.0]], [[0.0, 0.0, 0.0]]])
    assert m.metrics(make_trace(t, pos))["tunnelled"] == 1.0


def test_no_tunnelling_floor_slab():
    sc = load_scene("tunnelling.thin_box_on_thin_floor")
    m = get_model("no_tunnelling")(sc)
    t = np.array([0.0, 0.5, 1.0])
    rest = np.array([[[0.0, 0.0, 2.0]], [[0.0, 0.0, 0.5]], [[0.0, 0.0, 0.003]]])
    assert m.metrics(make_trace(t, rest))["tunnelled"] == 0.0
    through = np.array([[[0.0, 0.0, 2.0]], [[0.0, 0.0, 0.5]], [[0.0, 0.0, -0.5]]])
    assert m.metrics(make_trace(t, through))["tunnelled"] == 1.0


# ---------------------------------------------------------------------------
# newtons_cradle, momentum_energy


def test_sequential_row_collisions():
    from physbench.harness.references.billiards import sequential_row_collisions

    # equal masses, e = 1: the striker's velocity ends in the last ball
    v = sequential_row_collisions(np.ones(5), np.array([1.0, 0, 0, 0, 0]), 1.0)
    np.testing.assert_allclose(v, [0, 0, 0, 0, 1.0], atol=1e-15)
    # two balls m1 = 1, m2 = 3, e = 0.5: the two-body law (-0.25, 0.75)
    v = sequential_row_collisions(np.array([1.0, 3.0]), np.array([2.0, 0.0]), 0.5)
    np.testing.assert_allclose(v, [-0.25, 0.75])
    # two strikers, e = 1: the last two balls leave
    v = sequential_row_collisions(np.ones(5), np.array([1.0, 1.0, 0, 0, 0]), 1.0)
    np.testing.assert_allclose(v, [0, 0, 0, 1.0, 1.0], atol=1e-15)


def test_newtons_cradle_model():
    sc = load_scene("billiards.newtons_cradle")
    m = get_model("newtons_cradle")(sc)
    np.testing.assert_allclose(m.v_final, [0, 0, 0, 0, 1.0], atol=1e-15)
    t = np.array([0.0, 0.5])
    x0 = sc.initial_state()[0]
    vel = np.zeros((2, 5, 3))
    vel[0, 0, 0] = 1.0
    vel[1, 4, 0] = 0.9   # last ball 10 % slow, the 4th keeps 0.1
    vel[1, 3, 0] = 0.1
    out = m.metrics(make_trace(t, np.stack([x0, x0]), vel))
    assert out["cradle_velocity_error"] == pytest.approx(0.1)


def test_momentum_energy():
    sc = load_scene("billiards.break_16")
    m = get_model("momentum_energy")(sc)
    x0, _, v0, _ = sc.initial_state()
    # cue 0.17 kg at 5 m/s: P = 0.85 kg m/s, KE = 2.125 J.  After: cue stops,
    # the momentum is shared by two balls at 60 degrees either side of x:
    # 2 * 0.17 * u cos 30 = 0.85 -> u = 2.5 / cos 30 = 2.886751 m/s,
    # KE = 0.17 u^2 = 1.416667 J: one third of the energy lost.
    u = 2.5 / math.cos(math.radians(30))
    v1 = np.zeros_like(v0)
    v1[1] = [u * math.cos(math.radians(30)), u * math.sin(math.radians(30)), 0]
    v1[2] = [u * math.cos(math.radians(30)), -u * math.sin(math.radians(30)), 0]
    tr = make_trace([0.0, 1.0], np.stack([x0, x0]), np.stack([v0, v1]))
    out = m.metrics(tr)
    assert out["momentum_error"] == pytest.approx(0.0, abs=1e-15)
    assert out["energy_loss"] == pytest.approx(1.0 / 3.0)
    assert out["energy_error"] == pytest.approx(1.0 / 3.0)


# ---------------------------------------------------------------------------
# torque_free_rigid_body


def test_dzhanibekov_reference_invariants_and_period():
    from physbench.harness.references.rigid_body import intermediate_flip_interval

    sc = load_scene("gyroscopic.dzhanibekov")
    m = get_model("torque_free_rigid_body")(sc)
    I = m.inertia
    # box 0.6 x 0.4 x 0.1 m, 1 kg: I = m/3 (b^2 + c^2, a^2 + c^2, a^2 + b^2)
    np.testing.assert_allclose(I, [0.0425 / 3, 0.0925 / 3, 0.13 / 3], rtol=1e-12)
    t = np.linspace(0.0, sc.duration, 4001)
    q, wb = m.reference(t)
    E = 0.5 * np.sum(I * wb * wb, axis=1)
    L = quat_rotate(q, I * wb)  # world angular momentum
    assert np.max(np.abs(E - E[0])) / E[0] < 1e-8
    assert np.max(np.linalg.norm(L - L[0], axis=1)) / np.linalg.norm(L[0]) < 1e-8
    # independent estimate: Jacobi elliptic period 2 K(m) / lambda
    T_exact = intermediate_flip_interval(I, m.w0)
    tf = np.linspace(0.0, sc.duration, 40001)
    _, wf = m.reference(tf)
    T_num = m.flip_interval(tf, wf)
    assert T_num == pytest.approx(T_exact, rel=1e-3)
    assert T_exact == pytest.approx(2.2387, abs=1e-4)  # the figure quoted in the spec
    # the model's own metrics on the reference itself are ~0
    tr = make_trace(t, np.zeros((len(t), 1, 3)), quat=q[:, None], angvel=quat_rotate(q, wb)[:, None])
    out = m.metrics(tr)
    assert out["flip_period_error"] < 1e-3
    assert out["orientation_error"] < 1e-6
    assert out["angular_velocity_error"] < 1e-6


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_torque_free_rhs_matches_the_array_form():
    """The scalar right-hand side of Euler's equations (written out for
    speed) is bit for bit the array form q (x) (0, w) / 2 with quat_mul, so
    the reference solution (and every metric against it) is unchanged; a
    non-finite state propagates the same way (0 * inf is NaN in both).
    Finite states raise no floating-point warning; the one NaN numpy flags
    is the non-finite state's inf * 0 in quat_mul, made on purpose."""
    from scipy.integrate import solve_ivp

    from physbench.contract.rotation import quat_mul
    from physbench.harness.references.rigid_body import RTOL, ATOL, euler_rhs

    def array_form(inertia):
        I1, I2, I3 = inertia

        def f(_t, y):
            w1, w2, w3 = y[4:]
            qd = 0.5 * quat_mul(y[:4], np.array([0.0, w1, w2, w3]))
            return np.array([*qd, (I2 - I3) * w2 * w3 / I1, (I3 - I1) * w3 * w1 / I2, (I1 - I2) * w1 * w2 / I3])

        return f

    rng = np.random.default_rng(7)
    for _ in range(50):
        inertia = rng.uniform(1e-3, 2.0, 3)
        y = rng.normal(size=7) * rng.choice([1e-3, 1.0, 1e3], 7)
        assert np.array_equal(np.asarray(euler_rhs(inertia)(0.0, y)), array_form(inertia)(0.0, y))
    y = np.array([np.inf, 0.5, -0.5, 0.5, 1.0, np.nan, 3.0])
    with np.errstate(invalid="ignore"):  # q_w = inf times (0, w)'s 0: NaN intended
        np.testing.assert_array_equal(np.asarray(euler_rhs(inertia)(0.0, y)), array_form(inertia)(0.0, y))
    inertia = np.array([0.0135, 0.0308, 0.0433])
    y0 = np.array([1.0, 0.0, 0.0, 0.0, 20.0, 5.0, 150.0])
    runs = [solve_ivp(f(inertia), (0.0, 0.5), y0, method="DOP853", rtol=RTOL, atol=ATOL, dense_output=True)
            for f in (euler_rhs, array_form)]
    assert np.array_equal(runs[0].t, runs[1].t) and np.array_equal(runs[0].y, runs[1].y)


def test_stable_axes_stay_put_in_the_reference():
    for sid in ("gyroscopic.stable_major", "gyroscopic.stable_minor"):
        sc = load_scene(sid)
        m = get_model("torque_free_rigid_body")(sc)
        t = np.linspace(0.0, sc.duration, 2001)
        q, wb = m.reference(t)
        tr = make_trace(t, np.zeros((len(t), 1, 3)), quat=q[:, None], angvel=quat_rotate(q, wb)[:, None])
        out = m.metrics(tr)
        # a 1 % perturbation: the axis wobbles in a cone of 0.017 rad (major)
        # and 0.077 rad (minor) but never leaves it
        assert out["spin_axis_deviation_ref"] < 0.1
        assert out["spin_axis_excess"] < 1e-6
        assert "flip_period_error" not in out  # no flips


# ---------------------------------------------------------------------------
# heavy_top


def test_heavy_top_reference_precesses_at_the_analytic_rate():
    # The scene starts in the rigid-pivot steady precession:
    # I1' cos(30) W^2 - I3 w3 W + m g l = 0 with I3 = m r^2 / 2 = 0.005,
    # I1' = m (3 r^2 + (2h)^2) / 12 + m l^2 = 0.0026333 + 0.01, w3 = 100, l = 0.1:
    # W = (0.5 - sqrt(0.25 - 4 * 0.0109058 * 0.981)) / (2 * 0.0109058) = 2.054348 rad/s.
    # The 0.5 mm spring sag changes it by ~1e-4 relative.
    sc = load_scene("gyroscopic.heavy_top")
    m = get_model("heavy_top")(sc)
    t = np.linspace(0.0, sc.duration, 3001)
    x, q = m.reference(t)
    az, tilt = m._azimuth_tilt(q)
    from physbench.harness.references import fit_slope

    assert fit_slope(t, az) == pytest.approx(2.054348, rel=1e-3)
    assert np.max(np.abs(tilt - math.radians(30))) < 0.01  # steady: no nutation to speak of
    # the model scores the reference itself as exact
    vel = np.gradient(x, t, axis=0)
    out = m.metrics(make_trace(t, x[:, None], vel[:, None], quat=q[:, None]))
    assert out["precession_rate_error"] < 1e-9
    assert out["tilt_error"] < 1e-9


def test_fit_slope_is_the_least_squares_slope():
    """The one slope fit the references use (friction accelerations, the
    heavy top's precession rate): exact on a line, NaN where t does not vary."""
    from physbench.harness.references import fit_slope

    t = np.linspace(0.0, 2.0, 41)
    assert fit_slope(t, 3.0 * t - 1.0) == pytest.approx(3.0, rel=1e-14)
    wiggle = np.where(np.arange(41) % 2, 0.01, -0.01)  # zero mean, no trend over pairs
    assert fit_slope(t, -0.5 * t + wiggle) == pytest.approx(np.polyfit(t, -0.5 * t + wiggle, 1)[0], rel=1e-12)
    assert math.isnan(fit_slope(np.ones(5), np.arange(5.0)))


def test_constant_series_predicts_its_value_at_every_time():
    from physbench.harness.references import constant

    f = constant(np.float64(2.5))
    t = np.linspace(0.0, 1.0, 7)
    y = f(t)
    assert y.shape == (7,) and y.dtype == np.float64 and (y == 2.5).all()
    assert f(0.3).shape == () and float(f(0.3)) == 2.5


@pytest.mark.parametrize("spacing, b_x, b_shape, bodies, key", [
    (1.0, 0.05, "sphere", '["a_0", "b"]', r"body\[1\]\.position"),  # b: entry 1, body 2
    (0.05, 0.5, "sphere", '["a_0", "a_1"]', r"body\[0\]\.pattern"),  # the pattern made the overlap
    (1.0, 0.5, "capsule", '["a_0", "b"]', r"body\[1\]\.shape"),
])
def test_two_body_refusal_names_the_spec_entry(tmp_path, capsys, spacing, b_x, b_shape, bodies, key):
    """two_body_collision's refusals name the spec's key path -- the
    ``[[body]]`` entry (not the body's index among the bodies a pattern
    expands to), the pattern where it placed the body -- with the file, the
    expectation and the value, and the command exits 2 without a traceback."""
    import re

    from physbench.contract.spec import SpecError
    from physbench.harness import cli

    text = TWO_BODY.replace('velocity = [2.0, 0.0, 0.0]',
                            f'velocity = [2.0, 0.0, 0.0]\npattern = {{ kind = "row", count = 2, spacing = {spacing} }}')
    text = text.replace("position = [0.5, 0.0, 0.0]", f"position = [{b_x}, 0.0, 0.0]")
    text = text.replace('model = "two_body_collision"', f'model = "two_body_collision"\nparams = {{ bodies = {bodies} }}')
    if b_shape == "capsule":
        text = text.replace('shape = "sphere"\nradius = 0.05\nmass = 3.0', 'shape = "capsule"\nradius = 0.05\n'
                            'half_length = 0.1\nmass = 3.0')
    p = tmp_path / "pair.toml"
    p.write_text(text)
    with pytest.raises(SpecError) as e:
        load_scene(p)
    (line,) = e.value.errors
    assert line.startswith(f"{p}: ") and re.match(key + ": ", line[len(str(p)) + 2:]), line
    assert ("start overlapping" in line and "expected a start with the spheres apart" in line
            and "m apart, less than r1 + r2 = 0.1 m" in line) or "needs spheres, body 'b' is a capsule" in line
    rc = cli.main(["run", str(p), "-e", "reference", "--json"])
    err = capsys.readouterr().err
    assert rc == 2 and re.search(key, err) and "Traceback" not in err, err


@pytest.mark.parametrize("model, key, names", [("two_body_collision", "bodies", '["a", "nosuch"]'),
                                               ("no_tunnelling", "statics", '["nosuch"]')])
def test_a_name_list_param_refuses_an_unknown_name(model, key, names):
    """``params.bodies`` / ``params.statics`` naming what the scene does not
    have: refused at ``reference.params.<key>``, with the unknown name and
    the names the scene has."""
    text = TWO_BODY.replace('model = "two_body_collision"', f'model = "{model}"\nparams = {{ {key} = {names} }}')
    text += '[[static]]\nname = "floor"\nshape = "plane"\nnormal = [0.0, 0.0, 1.0]\noffset = -1.0\n'
    from physbench.contract.spec import SpecError

    with pytest.raises(SpecError) as e:
        scene_from(text)
    (line,) = e.value.errors
    assert f": reference.params.{key}: " in line and f"unknown {key} ['nosuch']" in line, line
    assert f"the scene has {['a', 'b'] if key == 'bodies' else ['floor']}" in line, line
