"""The reference engine's joints (engine/joints/) against closed forms and
conservation laws computed here: the pendulum's period from the complete
elliptic integral (scipy.special.ellipk) at 30 and 170 degrees, a slider's
acceleration g . u, a large-amplitude double pendulum's energy, chains
that hold; the settings act; what the engine does not model is
unsupported; a joint run missing a metric is never a passing check."""

import dataclasses
import math

import numpy as np
import pytest
from scipy.special import ellipk

from physbench.adapters.reference import ReferenceAdapter
from physbench.contract.scene import load_scene
from physbench.harness.conformance.verdicts import evaluate_check
from physbench.harness.runner import run
from physbench.harness.status import CHECK_ERROR, PASS


def _write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return load_scene(p)


def _upward_crossings(t, theta):
    """Times (s) where theta crosses 0 upward, by linear interpolation
    (theta'' = 0 at theta = 0 for a pendulum: the interpolation error is
    third order in the step)."""
    i = np.flatnonzero((theta[:-1] < 0) & (theta[1:] >= 0))
    return t[i] - theta[i] * (t[i + 1] - t[i]) / (theta[i + 1] - theta[i])


@pytest.mark.parametrize("variant, deg", [(None, 30.0), ("release_170", 170.0)])
def test_pendulum_period_is_the_elliptic_closed_form(variant, deg):
    """joints.pendulum at its defaults (dt 1 ms, rk4): the period measured
    here from the recorded angle within 1e-6 (relative) of
    4 sqrt(I / (m g d)) K(sin(theta0 / 2)), the hinge within 1e-9 m."""
    s = load_scene("joints.pendulum", variant=variant)
    r = run(s, "reference")
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    b, j = s.bodies[0], s.joints[0]
    m, rad = b.mass, b.radius
    d = float(np.linalg.norm(b.position - j.anchor))
    assert math.degrees(math.atan2(b.position[0] - j.anchor[0], j.anchor[2] - b.position[2])) == pytest.approx(deg)
    g = 9.81
    inertia = 0.4 * m * rad ** 2 + m * d ** 2
    T_ref = 4.0 * math.sqrt(inertia / (m * g * d)) * ellipk(math.sin(math.radians(deg) / 2) ** 2)
    rel = tr.pos[:, 0] - j.anchor
    theta = np.arctan2(rel[:, 0], -rel[:, 2])
    ups = _upward_crossings(tr.t, -theta)  # (the bob starts on +x, moving to -x)
    assert ups.size >= 2
    periods = np.diff(ups)
    err = np.max(np.abs(periods - T_ref)) / T_ref
    assert err < 1e-6, (err, periods, T_ref)
    assert r.metrics["joint_drift"] < 1e-9
    assert r.metrics["joint_axis_drift"] < 1e-9
    assert r.metrics["period_error"] < 1e-6


def test_pendulum_holds_without_projection_only_to_the_method_error():
    """joint_projection = off leaves the index-reduced ODE's drift (it
    grows); newton removes it to below 1e-9 m on the same run."""
    s = dataclasses.replace(load_scene("joints.pendulum", variant="release_170"), duration=2.0)
    on = run(s, "reference")
    off = run(s, "reference", {"joint_projection": "off"})
    assert on.status == off.status == "ok"
    assert on.metrics["joint_drift"] < 1e-9
    assert off.metrics["joint_drift"] > 10 * on.metrics["joint_drift"]
    assert off.metrics["joint_drift"] < 1e-4  # the rows are still solved exactly at every stage


DOUBLE = """
[scenario]
family = "joints"
title = "double pendulum, large amplitude"
duration = 3.0
dt = 0.001
effects = ["gravity", "joint"]

[[body]]
name = "upper"
shape = "sphere"
radius = 0.05
mass = 1.0
position = [{x1!r}, 0.0, {z1!r}]

[[body]]
name = "lower"
shape = "sphere"
radius = 0.05
mass = 0.5
position = [{x2!r}, 0.0, {z2!r}]

[[joint]]
kind = "revolute"
body = "upper"
anchor = [0.0, 0.0, 2.0]
axis = [0.0, 1.0, 0.0]

[[joint]]
kind = "revolute"
body = "lower"
other = "upper"
anchor = [{x1!r}, 0.0, {z1!r}]
axis = [0.0, 1.0, 0.0]
"""


def _energy(s, tr):
    """Kinetic plus potential energy (J) per frame, computed here."""
    g = np.array([0.0, 0.0, -9.81])
    E = np.zeros(tr.t.shape[0])
    for b in s.bodies:
        i = b.index
        inertia = 0.4 * b.mass * b.radius ** 2  # spheres
        E += 0.5 * b.mass * np.sum(tr.vel[:, i] ** 2, axis=1) + 0.5 * inertia * np.sum(tr.angvel[:, i] ** 2, axis=1)
        E -= b.mass * tr.pos[:, i] @ g
    return E


def test_double_pendulum_conserves_energy_at_large_amplitude(tmp_path):
    """Released at 90 and 150 degrees (chaotic): the energy within 1e-7
    of its start over 3 s, both hinges within 1e-9 m."""
    a1, a2 = math.radians(90.0), math.radians(150.0)
    x1, z1 = math.sin(a1), 2.0 - math.cos(a1)
    x2, z2 = x1 + 0.8 * math.sin(a2), z1 - 0.8 * math.cos(a2)
    s = _write(tmp_path, DOUBLE.format(x1=x1, z1=z1, x2=x2, z2=z2))
    r = run(s, "reference")
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    E = _energy(s, tr)
    scale = abs(E[0]) + sum(b.mass for b in s.bodies) * 9.81 * 1.8
    assert np.max(np.abs(E - E[0])) / scale < 1e-7
    assert np.ptp(tr.pos[:, 1, 0]) > 1.0  # it did swing
    assert r.metrics["joint_drift"] < 1e-9 and r.metrics["joint_axis_drift"] < 1e-9


@pytest.mark.parametrize("name", ["joints.chain_10", "joints.chain_load_100"])
def test_chains_hold(name):
    """A 10-link chain released sideways and one holding a 1:100 end
    load: every hinge within 1e-9 m and 1e-9 rad over 1 s; the energy of
    the swinging chain within 1e-4, the loaded chain at rest."""
    s = dataclasses.replace(load_scene(name), duration=1.0)
    r = run(s, "reference")
    assert r.status == "ok", r.message
    assert r.metrics["joint_drift"] < 1e-9
    assert r.metrics["joint_axis_drift"] < 1e-9
    if name.endswith("load_100"):
        assert r.metrics["chain_rest_error"] < 1e-9 and r.metrics["chain_sag"] < 1e-9
    else:
        assert r.metrics["energy_drift"] < 1e-4
        tr = r.trace.valid()
        assert np.ptp(tr.pos[:, -1, 2]) > 0.3  # the end fell and whipped


def test_chain_at_a_game_step_is_stable_by_splitting():
    """dt = 1/30 s: the step runs as parts of at most joint_max_turn rad
    (counted as joint_splits), and the 10-link chain stays on its hinges."""
    s = dataclasses.replace(load_scene("joints.chain_10"), duration=1.0)
    r = run(s, "reference", {"dt": 1 / 30})
    assert r.status == "ok", r.message
    assert r.stages["counters"]["joint_splits"] > 0
    assert r.metrics["joint_drift"] < 1e-9


SLIDER = """
[scenario]
family = "joints"
title = "slider"
duration = 1.0
dt = 0.001
effects = ["gravity", "joint"]

[[body]]
name = "block"
shape = "box"
half_extents = [0.1, 0.2, 0.05]
mass = 2.0
position = [0.3, -0.2, 3.0]
orientation = [0.9238795325112867, 0.0, 0.3826834323650898, 0.0]
velocity = {v!r}

[[joint]]
kind = "prismatic"
body = "block"
anchor = [0.3, -0.2, 3.0]
axis = {u!r}
"""


@pytest.mark.parametrize("axis", [(math.cos(math.radians(30)), 0.0, -0.5), (0.6, 0.48, -0.64)])
def test_slider_accelerates_at_g_along_its_axis(tmp_path, axis):
    """A turned box on a frictionless prismatic joint, thrown along it at
    0.5 m/s: s(t) = v0 t + (g . u) t^2 / 2 (g sin 30 deg = 4.905 m/s^2 on
    the first axis) to 1e-9 m, never off the axis nor turned."""
    u = np.array(axis) / np.linalg.norm(axis)
    s = _write(tmp_path, SLIDER.format(u=[float(c) for c in axis], v=[float(c) for c in 0.5 * u]))
    r = run(s, "reference")
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    d = tr.pos[:, 0] - np.array([0.3, -0.2, 3.0])
    along = d @ u
    a = float(np.array([0.0, 0.0, -9.81]) @ u)
    np.testing.assert_allclose(along, 0.5 * tr.t + 0.5 * a * tr.t ** 2, rtol=0, atol=1e-9)
    assert np.max(np.linalg.norm(d - along[:, None] * u, axis=1)) < 1e-9
    np.testing.assert_allclose(tr.quat[:, 0], np.broadcast_to(s.bodies[0].orientation, tr.quat[:, 0].shape),
                               atol=1e-9)
    assert r.metrics["joint_drift"] < 1e-9 and r.metrics["joint_axis_drift"] < 1e-9


BALL_WELD = """
[scenario]
family = "joints"
title = "a ball joint and a weld"
duration = 2.0
dt = 0.001
effects = ["gravity", "joint"]

[[body]]
name = "a"
shape = "sphere"
radius = 0.1
mass = 1.0
position = [0.5, 0.0, 1.0]
velocity = [0.0, 1.0, 0.0]
angular_velocity = [0.0, 0.0, 2.0]

[[body]]
name = "b"
shape = "sphere"
radius = 0.1
mass = 2.0
position = [0.5, 0.0, 0.8]
velocity = [0.0, 1.0, 0.0]
angular_velocity = [0.0, 0.0, 2.0]

[[joint]]
kind = "spherical"
body = "a"
anchor = [0.0, 0.0, 1.5]

[[joint]]
kind = "fixed"
body = "b"
other = "a"
anchor = [0.5, 0.0, 0.9]
"""


def test_ball_joint_and_weld_hold_and_conserve_energy(tmp_path):
    """Two spheres welded together swing and spin on a ball joint: both
    joints within 1e-9 (m, rad), the energy within 1e-8, the weld keeps
    the pair's distance to round-off."""
    s = _write(tmp_path, BALL_WELD)
    r = run(s, "reference")
    assert r.status == "ok", r.message
    tr = r.trace.valid()
    assert r.metrics["joint_drift"] < 1e-9 and r.metrics["joint_axis_drift"] < 1e-9
    E = _energy(s, tr)
    assert np.max(np.abs(E - E[0])) / (3.0 * 9.81 * 1.0) < 1e-8
    sep = np.linalg.norm(tr.pos[:, 0] - tr.pos[:, 1], axis=1)
    assert np.max(np.abs(sep - 0.2)) < 1e-9
    assert np.ptp(tr.pos[:, 0, 1]) > 0.1  # it moved out of the x-z plane


def test_capabilities_name_every_joint_kind():
    caps = ReferenceAdapter.capabilities()
    assert "joint" in caps.effects
    assert caps.joint_kinds == frozenset({"revolute", "spherical", "prismatic", "fixed"})
    assert {"joint_projection", "joint_tolerance", "joint_max_turn"} <= set(caps.settings)


def test_joints_with_contact_are_unsupported_with_the_reason(tmp_path):
    text = BALL_WELD.replace('effects = ["gravity", "joint"]', 'effects = ["gravity", "joint", "contact"]')
    text += '\n[[static]]\nname = "ground"\nshape = "plane"\nnormal = [0.0, 0.0, 1.0]\noffset = 0.0\n'
    r = run(_write(tmp_path, text), "reference")
    assert r.status == "unsupported"
    assert "joints with contact" in r.message


def test_a_joint_run_missing_its_drift_is_not_a_pass():
    """Planted: the same ok run with joint_drift removed, or NaN, gives an
    ERROR outcome for the scene's joint_drift check, never PASS."""
    s = dataclasses.replace(load_scene("joints.pendulum"), duration=0.5)
    r = run(s, "reference")
    assert r.status == "ok", r.message
    check = next(c for c in s.checks if c.metric == "joint_drift")
    assert evaluate_check(check, r).outcome == PASS
    for planted in (None, float("nan")):
        bad = dataclasses.replace(r, metrics={**r.metrics})
        if planted is None:
            del bad.metrics["joint_drift"]
        else:
            bad.metrics["joint_drift"] = planted
        o = evaluate_check(check, bad)
        assert o.outcome == CHECK_ERROR and "metric not computed" in o.message


def _four_bar_period_independently(s):
    """One crank turn of joints.four_bar's linkage (s), computed here
    without the model: the rocker angle by root finding on the loop
    closure |A(theta) - B(phi)| = b, the centres from the rigid links, the
    kinetic energy's I_eff by central differences, scipy's quad of
    d theta / theta'.  Planar in x-z: angles from +x towards +z."""
    from scipy.integrate import quad
    from scipy.optimize import brentq

    by = {b.name: b for b in s.bodies}
    js = {j.name: j for j in s.joints}
    xz = lambda p: np.array([p[0], p[2]])  # noqa: E731
    O2, O4 = xz(js["crank_pivot"].anchor), xz(js["rocker_pivot"].anchor)
    A0, B0 = xz(js["crank_pin"].anchor), xz(js["rocker_pin"].anchor)
    a, b, c = np.linalg.norm(A0 - O2), np.linalg.norm(B0 - A0), np.linalg.norm(B0 - O4)
    phi0 = math.atan2(*(B0 - O4)[::-1])

    def pins(th):
        A = O2 + a * np.array([math.cos(th), math.sin(th)])
        f = lambda p: np.linalg.norm(A - O4 - c * np.array([math.cos(p), math.sin(p)])) - b  # noqa: E731
        # the branch of the start: the root nearest phi0 in (0, pi) (the rocker above the ground)
        phi = brentq(f, 1e-6, math.pi / 2) if f(1e-6) * f(math.pi / 2) < 0 else brentq(f, math.pi / 2, math.pi - 1e-6)
        return A, O4 + c * np.array([math.cos(phi), math.sin(phi)]), phi

    def frame(P, Q, x0, P0, Q0):
        """x0's place on the link P0 -> Q0 carried to P -> Q."""
        e0 = (Q0 - P0) / np.linalg.norm(Q0 - P0)
        n0 = np.array([-e0[1], e0[0]])
        r = x0 - P0
        e = (Q - P) / np.linalg.norm(Q - P)
        n = np.array([-e[1], e[0]])
        return P + (r @ e0) * e + (r @ n0) * n

    def config(th):
        A, B, phi = pins(th)
        x = [frame(O2, A, xz(by["crank"].position), O2, A0), frame(A, B, xz(by["coupler"].position), A0, B0),
             frame(O4, B, xz(by["rocker"].position), O4, B0)]
        ang = [th, math.atan2(*(B - A)[::-1]), phi]
        return np.array(x), np.array(ang)

    def iy(b_):  # the moment about y of a box turned about y (thin along y: I_yy of the body)
        return b_.inertia[1]

    m = np.array([by[n].mass for n in ("crank", "coupler", "rocker")])
    I = np.array([iy(by[n]) for n in ("crank", "coupler", "rocker")])

    def ieff(th, h=1e-6):
        xp, ap = config(th + h)
        xm, am = config(th - h)
        v = (xp - xm) / (2 * h)
        w = (ap - am) / (2 * h)
        return float(np.sum(m * np.sum(v * v, axis=1)) + np.sum(I * w * w))

    def pot(th):
        x, _ = config(th)
        return float(np.sum(m * 9.81 * x[:, 1]))

    th0 = math.atan2(*(A0 - O2)[::-1])
    w0 = -by["crank"].angular_velocity[1]  # about -y: x towards z
    E = 0.5 * ieff(th0) * w0 ** 2 + pot(th0)
    T, _ = quad(lambda th: 1.0 / math.sqrt(2 * (E - pot(th)) / ieff(th)), th0, th0 + 2 * math.pi, limit=400,
                epsabs=1e-13, epsrel=1e-11)
    return T


def test_four_bar_model_period_against_an_independent_loop_closure():
    """The model's one crank turn equals the one computed here within 1e-7
    (central differences bound the agreement), and its metrics on its own
    closed-form trace are zero while a planted 1 mm shift of the coupler
    is measured."""
    from types import SimpleNamespace

    from physbench.contract.models import get_model

    s = load_scene("joints.four_bar")
    model = get_model("four_bar")(s)
    T = _four_bar_period_independently(s)
    assert abs(model.T - T) / T < 1e-7, (model.T, T)
    t = np.linspace(0.0, 0.5, 501)
    pos = model.positions(t)
    quat = np.zeros(pos.shape[:2] + (4,))
    for b in s.bodies:  # each body turned with its link (its angle from the closed form)
        quat[:, b.index] = b.orientation
    # the crank's orientation carries its pin: the model's angle runs from x towards u x x = -z, a turn
    # about +y: turn the crank by theta - theta0 about y
    th = model.angle(t)
    half = (th - model.theta0) / 2
    qrot = np.stack([np.cos(half), np.zeros_like(half), np.sin(half), np.zeros_like(half)], axis=1)
    ic = model.bodies[0].index
    q0 = s.bodies[ic].orientation  # a turn about y composed with one about y: the angles add
    quat[:, ic] = np.stack([qrot[:, 0] * q0[0] - qrot[:, 2] * q0[2], np.zeros_like(half),
                            qrot[:, 0] * q0[2] + qrot[:, 2] * q0[0], np.zeros_like(half)], axis=1)
    angvel = np.zeros_like(pos)
    angvel[:, ic, 1] = model.rate(th)
    trace = SimpleNamespace(t=t, pos=pos, quat=quat, vel=np.zeros_like(pos), angvel=angvel)
    got = model.metrics(trace)
    assert got["four_bar_position_error"] < 1e-12
    assert got["crank_angle_error"] < 1e-9
    assert got["crank_rate_error"] < 1e-12
    assert got["crank_period_error"] < 1e-9
    planted = pos.copy()
    planted[:, model.bodies[1].index, 0] += 1e-3
    got = model.metrics(SimpleNamespace(t=t, pos=planted, quat=quat, vel=trace.vel, angvel=angvel))
    assert got["four_bar_position_error"] == pytest.approx(1e-3, rel=1e-6)


def test_four_bar_loop_closes_on_the_reference():
    """joints.four_bar at its defaults: the loop's redundant rows (a planar
    loop of 3D hinges) are dropped, the fourth hinge holds to 1e-9 m, the
    crank turns in the independently computed time within 1e-6."""
    s = load_scene("joints.four_bar")
    r = run(s, "reference")
    assert r.status == "ok", r.message
    T = _four_bar_period_independently(s)
    assert abs(r.metrics["crank_period"] - T) / T < 1e-6
    assert r.metrics["joint_drift"] < 1e-9 and r.metrics["joint_axis_drift"] < 1e-9
    assert r.metrics["four_bar_position_error"] < 1e-9
    assert r.metrics["energy_drift"] < 1e-6


@pytest.mark.parametrize("name, dt", [("joints.chain_10", 1 / 30), ("joints.four_bar", 1e-3)])
def test_the_loop_over_steps_gives_the_staged_steps_bits(name, dt):
    """pipeline.advance runs a joint scene's steps as one compiled call
    (engine/joints/step.py joint_block); step by step through the stage
    (a profile by stage) gives the same bits, splits and time."""
    from physbench.adapters.reference import engine_for

    s = load_scene(name)
    a, b = engine_for(s, {"dt": dt}), engine_for(s, {"dt": dt})
    b.profile.by_stage = True
    a.step(40)
    b.step(40)
    for u, v in ((a.state.x, b.state.x), (a.state.q, b.state.q), (a.state.v, b.state.v), (a.state.w, b.state.w)):
        assert np.array_equal(u, v)
    assert a.state.t == b.state.t and a.state.steps == b.state.steps == 40
    ca, cb = a.profile.as_dict()["counters"], b.profile.as_dict()["counters"]
    assert ca == cb and ca.get("joint_newton_iterations", 0) > 0
    assert a.profile.as_dict()["joint_step"]["calls"] == b.profile.as_dict()["joint_step"]["calls"] == 40


def test_no_joint_step_compiles():
    """The build compiles (or loads) the joint step, its loop over steps
    and the staged step's begin and commit: stepping compiles nothing."""
    from numba.core import event

    from physbench.adapters.reference import engine_for

    eng = engine_for(load_scene("joints.double_pendulum"))
    with event.install_recorder("numba:compile") as rec:
        eng.step(3)
        eng.profile.by_stage = True
        eng.step(2)
    assert not [ev for _, ev in rec.buffer if ev.is_start]


def test_sequential_impulses_are_the_fields_rows_and_drift():
    """joint_solver = sequential_impulse (velocity-level rows by projected
    Gauss-Seidel, warm-started, Baumgarte 0.2, 20 passes; semi-implicit
    Euler) without the projection: the 170-degree pendulum's hinge drifts
    (measured 1.1e-4 m over 10 s at dt 1 ms; period_error 1.1e-3) but stays
    within 1 mm, and a 10-link chain's hinges drift further than the
    pendulum's (1.1e-3 m measured over 2 s); with rk4 the choice is unsupported, never
    silently changed."""
    si = {"joint_solver": "sequential_impulse", "integrator": "semi_implicit_euler", "joint_projection": "off",
          "joint_max_turn": 0.0}
    s = load_scene("joints.pendulum", variant="release_170")
    pend = run(s, "reference", si)
    assert pend.status == "ok", pend.message
    assert 1e-7 < pend.metrics["joint_drift"] < 1e-3
    assert pend.metrics["period_error"] < 5e-3
    chain = run(dataclasses.replace(load_scene("joints.chain_10"), duration=1.0), "reference", si)
    assert chain.status == "ok", chain.message
    assert chain.metrics["joint_drift"] > pend.metrics["joint_drift"]
    r = run(s, "reference", {"joint_solver": "sequential_impulse"})
    assert r.status == "unsupported" and "semi_implicit_euler" in r.message


HEAVY = """
[scenario]
family = "joints"
title = "a box on a ball joint"
duration = 2.0
dt = 0.001
effects = ["gravity", "joint", "gyroscopic"]

[[body]]
name = "box"
shape = "box"
half_extents = [0.3, 0.1, 0.05]
mass = 1.5
position = [0.2, 0.1, 1.0]
orientation = [0.9233805168766387, 0.10259783520851541, 0.3077935056255462, 0.20519567041703082]
velocity = {v!r}
angular_velocity = [3.0, -2.0, 5.0]

[[joint]]
kind = "spherical"
body = "box"
anchor = [0.0, 0.0, 1.3]
"""


def test_an_anisotropic_body_on_a_ball_joint_conserves_energy(tmp_path):
    """A spinning box hung by a corner-side point (gyroscopic = explicit:
    w x I w inside the constrained ODE): energy with the full inertia
    tensor, computed here, within 1e-8 over 2 s, the joint within 1e-9 m;
    the other gyroscopic treatments are unsupported with the reason."""
    from physbench.contract.rotation import quat_to_matrix

    w = np.array([3.0, -2.0, 5.0])
    r = np.array([0.2, 0.1, 1.0]) - np.array([0.0, 0.0, 1.3])
    s = _write(tmp_path, HEAVY.format(v=[float(c) for c in np.cross(w, r)]))
    res = run(s, "reference", {"gyroscopic": "explicit"})
    assert res.status == "ok", res.message
    tr = res.trace.valid()
    b = s.bodies[0]
    E = np.empty(tr.t.shape[0])
    for f in range(E.size):
        R = quat_to_matrix(tr.quat[f, 0])
        Iw = R @ np.diag(b.inertia) @ R.T
        E[f] = (0.5 * b.mass * tr.vel[f, 0] @ tr.vel[f, 0] + 0.5 * tr.angvel[f, 0] @ Iw @ tr.angvel[f, 0]
                + b.mass * 9.81 * tr.pos[f, 0, 2])
    assert np.max(np.abs(E - E[0])) / abs(E[0]) < 1e-8
    assert res.metrics["joint_drift"] < 1e-9
    other = run(s, "reference")  # gyroscopic = energy_conserving, the default
    assert other.status == "unsupported" and "gyroscopic = explicit" in other.message
