"""One convention suite, run against every adapter by parametrisation:
free fall, constant spin about each axis, quaternion order, angular-velocity
frame, planar sign, material pair values.  Expected values are analytic; an
engine that cannot model a case must say `unsupported` (and the test checks
that it says so for the right reason)."""

import math

import numpy as np
import pytest

from physbench.adapters import ENGINES, get_adapter
from physbench.contract.rotation import quat_rotate
from physbench.harness.runner import run
from physbench.contract.scene import compile_scene
from physbench.contract.spec import validate_raw

G = 9.81


def scene(raw):
    return compile_scene(validate_raw(raw, "<conventions>"))


def _available(engine):
    try:
        return get_adapter(engine).capabilities().available
    except Exception:
        return False


#: engines computing in f32: one f32 unit (2^-23 at 1 m) per substep of
#: their default 4 per step bounds the rounding of x += v h over a step
F32_FLOOR = {"rapier": 4 * 2.0 ** -23, "box2d": 4 * 2.0 ** -23}

engines = pytest.mark.parametrize("engine", [
    pytest.param(e, marks=pytest.mark.skipif(not _available(e), reason=f"{e} adapter not available")) for e in ENGINES])


def axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[math.cos(angle / 2), math.sin(angle / 2) * axis]


def quat_distance(q1, q2):
    """Rotation angle (rad) between two unit quaternions (sign-insensitive)."""
    return 2 * math.acos(min(1.0, abs(float(np.dot(q1, q2)))))


def base(effects, planar=False, duration=1.0, dt=0.001, **extra):
    raw = {"scenario": {"family": "conventions", "title": "t", "duration": duration, "dt": dt,
                        "effects": effects, "planar": planar}}
    raw.update(extra)
    return raw


@engines
def test_free_fall(engine):
    s = scene(base(["gravity"], planar=True, body=[{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0,
                                                    "position": [0.0, 0.0, 10.0], "velocity": [1.0, 0.0, 0.0]}]))
    r = run(s, engine)
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    T = tr.t[-1]
    z_exact = 10 - 0.5 * G * T**2
    # any first-order integrator is within g dt T of the exact parabola
    assert abs(tr.pos[-1, 0, 2] - z_exact) <= G * s.dt * T * 1.0001
    assert tr.vel[-1, 0, 2] == pytest.approx(-G * T, abs=G * s.dt * 1.0001)
    # no hidden damping; an f32 engine rounds x += v h at every substep
    # (F32_FLOOR; measured 2.7e-5 m on Rapier, 9.3e-6 m on Box2D at x = 1 m)
    floor = F32_FLOOR.get(engine, 0.0) * round(T / s.dt)
    assert tr.pos[-1, 0, 0] == pytest.approx(1.0 * T, abs=max(1e-9, floor))
    assert tr.vel[-1, 0, 0] == pytest.approx(1.0, abs=1e-9)


@engines
@pytest.mark.parametrize("axis", [(1, 0, 0), (0, 1, 0), (0, 0, 1)], ids=["x", "y", "z"])
def test_constant_spin_about_each_axis(engine, axis):
    w = 3.0
    planar = axis == (0, 1, 0)
    s = scene(base([], planar=planar, body=[{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0,
                                              "angular_velocity": list(w * np.array(axis, float))}]))
    r = run(s, engine)
    if get_adapter(engine).capabilities().dimensions == 2 and not planar:
        assert r.status == "unsupported" and "not planar" in r.message
        return
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    T = tr.t[-1]
    assert np.allclose(tr.angvel[-1, 0], w * np.array(axis), atol=1e-6)
    assert quat_distance(tr.quat[-1, 0], axis_angle(axis, w * T)) < 1e-3


@engines
def test_quaternion_order_reads_back(engine):
    q = axis_angle([0.0, 1.0, 0.0], 0.7)   # about y, so planar engines can hold it
    s = scene(base([], planar=True, body=[{"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.1],
                                            "mass": 1.0, "orientation": list(q)}]))
    r = run(s, engine)
    assert r.status == "ok", r.message
    assert np.allclose(r.trace.quat[0, 0] * np.sign(r.trace.quat[0, 0, 0]), q, atol=1e-7)
    q3 = axis_angle([1.0, 2.0, 3.0], 1.1)
    s3 = scene(base([], body=[{"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.1],
                                "mass": 1.0, "orientation": list(q3)}]))
    r3 = run(s3, engine)
    if get_adapter(engine).capabilities().dimensions == 2:
        assert r3.status == "unsupported"
        return
    assert np.allclose(r3.trace.quat[-1, 0] * np.sign(r3.trace.quat[-1, 0, 0]), q3, atol=1e-7)


@engines
def test_angular_velocity_is_world_frame(engine):
    # a box tilted 45 deg about x spins steadily about its own z axis (a principal
    # axis: torque-free steady rotation).  In the world frame that axis is
    # R(q) e_z = (0, -sin 45, cos 45).  A body-frame reading would be (0, 0, 5).
    q = axis_angle([1, 0, 0], math.pi / 4)
    w_world = 5.0 * quat_rotate(q, np.array([0, 0, 1.0]))
    s = scene(base(["gyroscopic"], duration=0.5, body=[{"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.1],
                                                        "mass": 1.0, "orientation": list(q), "angular_velocity": list(w_world)}]))
    r = run(s, engine)
    if get_adapter(engine).capabilities().dimensions == 2:
        assert r.status == "unsupported"
        return
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    assert np.allclose(tr.angvel[0, 0], w_world, atol=1e-9)
    assert np.allclose(tr.angvel[-1, 0], w_world, atol=1e-3)
    # the body z axis stays put, the body x axis turns about it
    ez = quat_rotate(tr.quat[-1, 0], np.array([0, 0, 1.0]))
    assert np.allclose(ez, w_world / 5.0, atol=1e-3)


@engines
def test_planar_sign(engine):
    # positive world rotation about +y turns +x toward -z
    wy = 2.0
    s = scene(base([], planar=True, duration=0.25, body=[{"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.1],
                                                           "mass": 1.0, "angular_velocity": [0.0, wy, 0.0]}]))
    r = run(s, engine)
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    T = tr.t[-1]
    ex = quat_rotate(tr.quat[-1, 0], np.array([1.0, 0, 0]))
    assert np.allclose(ex, [math.cos(wy * T), 0, -math.sin(wy * T)], atol=1e-3)
    assert tr.angvel[-1, 0, 1] == pytest.approx(wy, abs=1e-6)


# The material tests check that each adapter realises the spec's *pair* values
# through its engine's combination rule.  pybullet's default contact handling
# (position correction folded into the velocity solve, speculative contacts
# 2 cm early) distorts every impact by itself — measured 0.474 for e = 0.5 and
# a slide 4.4 % slow at its defaults; the conformance scenarios report that.
# Here it runs with split impulse and a tight contact margin, which remove
# those artefacts, so the test isolates the material convention.
# Drake's discrete step dissipates by itself (an e above 0.65 is unsupported
# at 10 steps per contact, docs/ENGINE_FINDINGS.md): continuous time isolates
# its restitution map.
ISOLATE_CONTACT = {"pybullet": {"split_impulse": True, "contact_breaking_threshold": 1e-4},
                   "drake": {"time_step": 0.0}}


def _bounce_ratio(tr):
    vz = tr.vel[:, 0, 2]
    k = int(np.argmin(vz))           # fastest descent: the frame before impact
    after = vz[k:]
    return float(after.max() / -vz[k])


@engines
@pytest.mark.parametrize("e", [0.5, 0.8])
def test_material_pair_restitution(engine, e):
    # a ball dropped from 1 m on a plane: the material pair's e is the bounce ratio
    s = scene(base(["gravity", "contact", "restitution"], planar=True, duration=0.6, dt=0.001,
                   material={"default": {"restitution": 0.0}, "ball": {"restitution": e}},
                   body=[{"name": "b", "shape": "sphere", "radius": 0.05, "mass": 0.2, "material": "ball",
                          "position": [0.0, 0.0, 1.05]}],
                   static=[{"shape": "plane", "normal": [0.0, 0.0, 1.0], "offset": 0.0}]))
    r = run(s, engine, ISOLATE_CONTACT.get(engine))
    assert r.status == "ok", r.message
    ratio = _bounce_ratio(r.trace.valid())
    # g dt over the impact speed (4.4 m/s) bounds the discretisation error: 0.3 %
    assert ratio == pytest.approx(e, rel=0.02), f"{engine}: bounce ratio {ratio:.4f} for e = {e}"


@engines
def test_material_pair_friction(engine):
    # a block sliding down a 30 degree slope with mu_k = 0.3: a = g (sin - mu cos)
    th = math.radians(30)
    mu = 0.3
    n = np.array([math.sin(th), 0, math.cos(th)])
    h = 0.05
    start = n * (h + 1e-4)
    down = np.array([math.cos(th), 0, -math.sin(th)])
    s = scene(base(["gravity", "contact", "friction"], planar=True, duration=0.5, dt=0.001,
                   material={"default": {"friction": 0.0}, "block": {"friction": mu, "static_friction": mu}},
                   body=[{"name": "b", "shape": "box", "half_extents": [h, h, h], "mass": 1.0, "material": "block",
                          "position": list(start), "orientation": list(axis_angle([0, 1, 0], th))}],
                   static=[{"shape": "slope", "angle": 30.0}]))
    r = run(s, engine, ISOLATE_CONTACT.get(engine))
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    a_exact = G * (math.sin(th) - mu * math.cos(th))
    # fit the along-slope velocity over the second half (after any settling)
    k = len(tr.t) // 2
    v_along = tr.vel[k:, 0] @ down
    a_fit = np.polyfit(tr.t[k:], v_along, 1)[0]
    assert a_fit == pytest.approx(a_exact, rel=0.02), f"{engine}: a = {a_fit:.4f}, exact {a_exact:.4f}"
