"""The joint reference models against their closed forms computed
independently here: the pendulum against scipy's solve_ivp of
I theta'' = -m g d sin theta at tight tolerance (its period from the
integration's own zero-crossing events), the slider against its
kinematics."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from physbench.contract.models import get_model
from physbench.contract.scene import SCENARIO_DIR, load_scene
from physbench.contract.spec import ModelRefusal, SpecError

PENDULUM = """
[scenario]
family = "joints"
title = "t"
duration = {duration}
dt = 0.001
effects = ["gravity", "joint"]
gravity = {gravity}

[[body]]
name = "bob"
shape = "box"
half_extents = [0.05, 0.1, 0.2]
mass = 2.0
position = {position}
orientation = {orientation}
velocity = {velocity}
angular_velocity = {angular_velocity}

[[joint]]
kind = "revolute"
body = "bob"
anchor = {anchor}
axis = {axis}

[reference]
model = "pendulum"
"""


def _vec(v):
    return "[" + ", ".join(repr(float(c)) for c in v) + "]"


def _pendulum(tmp_path, theta0_deg=30.0, w0=0.0, axis=(0.0, 1.0, 0.0), L=0.8, duration=10.0,
              gravity=(0.0, 0.0, -9.81), orientation=(1.0, 0.0, 0.0, 0.0), along=0.0):
    """A box bob at distance L from the anchor, theta0 from straight down
    about ``axis`` (normalised here), turning at w0 about it."""
    u = np.array(axis, float) / np.linalg.norm(axis)
    g = np.array(gravity, float)
    gp = g - (g @ u) * u
    e1 = gp / np.linalg.norm(gp)
    e2 = np.cross(u, e1)
    th = math.radians(theta0_deg)
    anchor = np.array([0.1, -0.2, 3.0])
    r = L * (math.cos(th) * e1 + math.sin(th) * e2) + along * u
    text = PENDULUM.format(duration=duration, gravity=_vec(g), position=_vec(anchor + r),
                           orientation=_vec(orientation), velocity=_vec(w0 * np.cross(u, r)),
                           angular_velocity=_vec(w0 * u), anchor=_vec(anchor), axis=_vec(axis))
    p = tmp_path / "p.toml"
    p.write_text(text)
    s = load_scene(p)
    return s, get_model("pendulum")(s), dict(u=u, e1=e1, e2=e2, anchor=anchor, G=float(np.linalg.norm(gp)),
                                             th0=th, w0=w0, L=L, along=along)


def _ode(s, k):
    """(I, m g d) of the bob, computed here from the scene's body: the
    rotated inertia tensor about the axis plus m d^2 (parallel axes)."""
    b = s.bodies[0]
    w, x, y, z = b.orientation
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    u = k["u"]
    I = u @ R @ np.diag(b.inertia) @ R.T @ u + b.mass * k["L"] ** 2
    return I, b.mass * k["G"] * k["L"]


def _integrate(s, k, t):
    I, mgd = _ode(s, k)

    def f(_, y):
        return [y[1], -mgd / I * math.sin(y[0])]

    def up(_, y):
        return y[0]
    up.direction = 1.0

    def turn(_, y):  # 0 each time theta has advanced a whole turn from theta0
        return math.sin((y[0] - k["th0"]) / 2.0)

    sol = solve_ivp(f, (0.0, t[-1]), [k["th0"], k["w0"]], t_eval=t, events=[up, turn], rtol=1e-12, atol=1e-14,
                    method="DOP853")
    return sol.y[0], sol.y[1], (sol.t_events[0], sol.t_events[1])


CASES = {
    "30 deg": dict(theta0_deg=30.0),
    "170 deg release": dict(theta0_deg=170.0, duration=12.0),
    "swinging back, tilted hinge, turned box": dict(theta0_deg=-50.0, w0=-2.0, axis=(0.3, 1.0, 0.2),
                                                     orientation=(0.8, 0.36, 0.48, 0.0), along=0.15),
    "thrown from the bottom": dict(theta0_deg=0.0, w0=5.0),
    "whirling over the top": dict(theta0_deg=40.0, w0=12.0, duration=4.0),
    "whirling backwards, tilted hinge": dict(theta0_deg=-100.0, w0=-20.0, axis=(0.3, 1.0, 0.2), duration=3.0),
}


@pytest.mark.parametrize("case", CASES)
def test_pendulum_angle_and_period_match_the_integrated_ode(tmp_path, case):
    s, m, k = _pendulum(tmp_path, **CASES[case])
    t = np.linspace(0.0, s.duration, 2001)
    th, w, (ups, turns) = _integrate(s, k, t)
    th_m, w_m = m.angle(t)
    assert np.max(np.abs(th_m - th)) < 1e-8 * max(1.0, np.max(np.abs(th)))
    assert np.max(np.abs(w_m - w)) < 1e-7 * max(1.0, np.max(np.abs(w)))
    if m.whirls:  # one turn: the time theta takes to advance 2 pi, from the integration's events
        turns = turns[turns > 1e-9]
        assert len(turns) >= 2
        assert m.T == pytest.approx(float(np.mean(np.diff(turns))), rel=1e-9)
        assert m.T == pytest.approx(float(turns[0]), rel=1e-9)
    else:
        assert len(ups) >= 2
        T = float(np.mean(np.diff(ups)))
        assert m.T == pytest.approx(T, rel=1e-9)


def test_period_is_the_elliptic_closed_form(tmp_path):
    """4 sqrt(I / (m g d)) K(sin(theta0 / 2)) from rest, by the arithmetic-
    geometric mean here (K(k) = pi / (2 AGM(1, sqrt(1 - k^2))))."""
    s, m, k = _pendulum(tmp_path, theta0_deg=170.0, duration=12.0)
    I, mgd = _ode(s, k)
    a, b = 1.0, math.sqrt(1.0 - math.sin(math.radians(85.0)) ** 2)
    for _ in range(30):
        a, b = (a + b) / 2, math.sqrt(a * b)
    assert m.T == pytest.approx(4 * math.sqrt(I / mgd) * math.pi / (2 * a), rel=1e-12)


def _trace(s, k, t, th, w):
    """The trace of the bob swinging at angle th (F,), rate w (F,)."""
    pos = (k["anchor"] + k["along"] * k["u"] + k["L"] * (np.cos(th)[:, None] * k["e1"]
                                                          + np.sin(th)[:, None] * k["e2"]))[:, None, :]
    F = len(t)
    return SimpleNamespace(t=t, pos=pos, quat=np.tile([1.0, 0.0, 0.0, 0.0], (F, 1, 1)),
                           vel=np.zeros((F, 1, 3)), angvel=(w[:, None] * k["u"])[:, None, :])


def test_pendulum_metrics_on_exact_and_planted_traces(tmp_path):
    s, m, k = _pendulum(tmp_path, theta0_deg=170.0, duration=12.0)
    t = np.arange(0.0, 12.0 + 1e-12, 0.01)  # frames every 10 ms: the crossings are interpolated
    th, w, _ = _integrate(s, k, t)
    out = m.metrics(_trace(s, k, t, th, w))
    assert out["period_error"] < 1e-8
    assert out["angle_error"] < 1e-8
    assert out["trajectory_rmse"] < 1e-8
    assert out["period_ref"] == m.T and out["amplitude_ref"] == pytest.approx(math.radians(170.0), rel=1e-12)
    # planted: the same swing 0.1 % slower
    slow = t / 1.001
    th2, w2, _ = _integrate(s, k, slow)
    out = m.metrics(_trace(s, k, t, th2, w2 / 1.001))
    assert out["period_error"] == pytest.approx(1e-3, rel=1e-5)
    assert out["angle_error"] > 1e-3
    # a bob that does not swing at all has no period: inf, never a pass
    still = np.full_like(t, k["th0"])
    out = m.metrics(_trace(s, k, t, still, np.zeros_like(t)))
    assert out["period_error"] == math.inf


@pytest.mark.parametrize("kw, key", [
    (dict(theta0_deg=0.0), "body[0].position"),                    # at rest at the bottom
])
def test_pendulum_refuses_with_the_key(tmp_path, kw, key):
    with pytest.raises(ModelRefusal) as e:
        _pendulum(tmp_path, **kw)
    assert key in str(e.value)


def test_pendulum_refuses_a_start_that_is_not_a_rotation_about_the_hinge(tmp_path):
    s, _, _ = _pendulum(tmp_path, theta0_deg=20.0)
    text = (tmp_path / "p.toml").read_text().replace("velocity = [0.0, 0.0, 0.0]", "velocity = [0.0, 0.5, 0.0]", 1)
    (tmp_path / "p.toml").write_text(text)
    with pytest.raises((ModelRefusal, SpecError)) as e:
        load_scene(tmp_path / "p.toml")
    assert "body[0].velocity" in str(e.value)


SLIDER = """
[scenario]
family = "joints"
title = "t"
duration = 2.0
dt = 0.01
effects = ["gravity", "joint"]

[[body]]
name = "block"
shape = "box"
half_extents = [0.1, 0.1, 0.1]
mass = 1.0
position = [0.0, 0.0, 1.0]
velocity = {velocity}

[[joint]]
kind = "prismatic"
body = "block"
anchor = [0.0, 0.0, 1.0]
axis = {axis}

[reference]
model = "slider"
"""


def test_slider_accelerates_at_g_sin_alpha(tmp_path):
    alpha = math.radians(25.0)
    u = np.array([math.cos(alpha), 0.0, -math.sin(alpha)])
    v0 = 0.4
    p = tmp_path / "s.toml"
    p.write_text(SLIDER.format(velocity=_vec(v0 * u), axis=_vec(u)))
    s = load_scene(p)
    m = get_model("slider")(s)
    assert m.a == pytest.approx(9.81 * math.sin(alpha), rel=1e-14)
    t = np.linspace(0.0, 2.0, 201)
    for a, err in ((9.81 * math.sin(alpha), 0.0), (9.81 * math.sin(alpha) * 0.98, 0.02)):
        sdist = v0 * t + 0.5 * a * t * t
        tr = SimpleNamespace(t=t, pos=(s.bodies[0].position + sdist[:, None] * u)[:, None, :],
                             vel=((v0 + a * t)[:, None] * u)[:, None, :],
                             quat=np.tile([1.0, 0.0, 0.0, 0.0], (201, 1, 1)), angvel=np.zeros((201, 1, 3)))
        out = m.metrics(tr)
        assert out["slider_acceleration_error"] == pytest.approx(err, abs=1e-12)
        assert out["slider_position_error"] == pytest.approx(0.5 * (9.81 * math.sin(alpha) - a) * 4.0, abs=1e-12)
    p.write_text(SLIDER.format(velocity="[0.0, 0.3, 0.0]", axis=_vec(u)))
    with pytest.raises(ModelRefusal) as e:
        load_scene(p)
    assert "body[0].velocity" in str(e.value)


def test_shipped_pendulum_scenes_load_with_their_periods():
    base = get_model("pendulum")(load_scene("joints.pendulum"))
    wide = get_model("pendulum")(load_scene("joints.pendulum", variant="release_170"))
    assert base.T == pytest.approx(2.04201013, rel=1e-8)
    assert wide.T == pytest.approx(4.89597042, rel=1e-8)


CONICAL = """
[scenario]
family = "joints"
title = "t"
duration = 3.0
dt = 0.001
effects = ["gravity", "joint"]

[[body]]
name = "bob"
shape = "sphere"
radius = 0.1
mass = 1.5
position = {position}
velocity = {velocity}
angular_velocity = {angular_velocity}

[[joint]]
kind = "spherical"
body = "bob"
anchor = [0.0, 0.0, 2.0]

[reference]
model = "conical_pendulum"
"""


def _conical(tmp_path, L=0.9, alpha_deg=35.0, rate_factor=1.0):
    a = math.radians(alpha_deg)
    r = np.array([L * math.sin(a), 0.0, -L * math.cos(a)])
    w = rate_factor * math.sqrt(9.81 / (L * math.cos(a)))  # the closed form, written here
    wv = np.array([0.0, 0.0, w])
    p = tmp_path / "c.toml"
    p.write_text(CONICAL.format(position=_vec(np.array([0.0, 0.0, 2.0]) + r), velocity=_vec(np.cross(wv, r)),
                                angular_velocity=_vec(wv)))
    return p, r, w


def _rigid_pivot_ode(s, r0, t):
    """The bob as a rigid body about the anchor, integrated here: world
    inertia about the pivot I_p = R (I_c + m (|r|^2 1 - r r^T)) R^T,
    d(I_p w)/dt = r x m g; centre offsets r(t) (F, 3)."""
    b = s.bodies[0]
    Ib = np.diag(b.inertia) + b.mass * (r0 @ r0 * np.eye(3) - np.outer(r0, r0))
    g = np.array([0.0, 0.0, -9.81])

    def rot(q):
        w, x, y, z = q / np.linalg.norm(q)
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])

    def f(_, y):
        q, w = y[:4], y[4:]
        R = rot(q)
        Ip = R @ Ib @ R.T
        r = R @ r0
        wdot = np.linalg.solve(Ip, np.cross(r, b.mass * g) - np.cross(w, Ip @ w))
        qw, qx, qy, qz = q
        wx, wy, wz = w
        qdot = 0.5 * np.array([-wx * qx - wy * qy - wz * qz, wx * qw + wy * qz - wz * qy,
                               wy * qw + wz * qx - wx * qz, wz * qw + wx * qy - wy * qx])
        return np.concatenate([qdot, wdot])

    sol = solve_ivp(f, (0.0, t[-1]), np.concatenate([[1.0, 0.0, 0.0, 0.0], b.angular_velocity]), t_eval=t,
                    rtol=1e-12, atol=1e-13, method="DOP853")
    return np.array([rot(q) @ r0 for q in sol.y[:4].T])


def test_conical_pendulum_rate_against_the_rigid_body_integrated(tmp_path):
    p, r0, w = _conical(tmp_path)
    s = load_scene(p)
    m = get_model("conical_pendulum")(s)
    assert m.w == pytest.approx(w, rel=1e-14) and m.alpha == pytest.approx(math.radians(35.0), rel=1e-14)
    t = np.linspace(0.0, 3.0, 601)
    r = _rigid_pivot_ode(s, r0, t)
    # the integrated motion stays on the cone and turns at the closed form's rate
    F = len(t)
    tr = SimpleNamespace(t=t, pos=(np.array([0.0, 0.0, 2.0]) + r)[:, None, :],
                         quat=np.tile([1.0, 0.0, 0.0, 0.0], (F, 1, 1)), vel=np.zeros((F, 1, 3)),
                         angvel=np.zeros((F, 1, 3)))
    out = m.metrics(tr)
    assert out["cone_angle_error"] < 1e-8
    assert out["cone_rate_error"] < 1e-9
    assert out["trajectory_rmse"] < 1e-8
    # planted: the same circle turning 0.2 % fast
    fast = m.positions(t * 1.002)
    tr.pos = fast
    out = m.metrics(tr)
    assert out["cone_rate_error"] == pytest.approx(2e-3, rel=1e-9)
    assert out["cone_angle_error"] < 1e-12


def test_conical_pendulum_refuses_an_unsteady_start(tmp_path):
    p, _, _ = _conical(tmp_path, rate_factor=1.01)
    with pytest.raises(ModelRefusal) as e:
        load_scene(p)
    assert "body[0].angular_velocity" in str(e.value)


def test_hanging_chain_rest_and_sag_on_planted_traces(tmp_path):
    s = load_scene("joints.chain_load_100")
    m = get_model("hanging_chain")(s)
    x0 = np.array([b.position for b in s.bodies])
    t = np.linspace(0.0, 2.0, 11)
    pos = np.broadcast_to(x0, (11,) + x0.shape).copy()
    F, n = pos.shape[:2]
    tr = SimpleNamespace(t=t, pos=pos, quat=np.tile([1.0, 0.0, 0.0, 0.0], (F, n, 1)), vel=np.zeros((F, n, 3)),
                         angvel=np.zeros((F, n, 3)))
    assert m.metrics(tr) == {"chain_rest_error": 0.0, "chain_sag": 0.0}
    # planted: the load (the lowest body) sinks 2 mm by the end, a link swings 3 mm sideways at frame 4
    load = s.body_index("load")
    tr.pos[:, load, 2] -= np.linspace(0.0, 2e-3, 11)
    tr.pos[4, s.body_index("link_5"), 0] += 3e-3
    out = m.metrics(tr)
    assert out["chain_sag"] == pytest.approx(2e-3, rel=1e-9)
    assert out["chain_rest_error"] == pytest.approx(3e-3, rel=1e-9)


def test_hanging_chain_refuses_a_chain_off_the_vertical(tmp_path):
    text = (SCENARIO_DIR / "joints" / "chain_load_100.toml").read_text()
    p = tmp_path / "c.toml"
    p.write_text(text.replace("position = [0.0, 0.0, 0.85]", "position = [0.01, 0.0, 0.85]"))
    with pytest.raises(ModelRefusal) as e:
        load_scene(p)
    assert "body[1].position" in str(e.value) and "does not hang on the vertical" in str(e.value)
    p.write_text(text.replace("position = [0.0, 0.0, 0.85]", "position = [0.0, 0.0, 0.85]\nvelocity = [0.1, 0.0, 0.0]"))
    with pytest.raises(ModelRefusal) as e:
        load_scene(p)
    assert "body[1].velocity" in str(e.value)


def test_whirling_pendulum_metrics_on_the_integrated_trace(tmp_path):
    s, m, k = _pendulum(tmp_path, theta0_deg=-100.0, w0=-20.0, duration=3.0)
    assert m.whirls
    t = np.arange(0.0, 3.0 + 1e-12, 0.002)
    th, w, _ = _integrate(s, k, t)
    out = m.metrics(_trace(s, k, t, th, w))
    assert out["period_error"] < 1e-8 and out["angle_error"] < 1e-8
    assert out["amplitude_ref"] == math.pi


def test_double_pendulum_modes_against_the_integrated_nonlinear_motion():
    """joints.double_pendulum: the frequencies against the roots of
    det(K - w^2 M) = 0 solved here by the quadratic formula, and the
    measured ones from a trace of the full nonlinear equations of motion
    (integrated here) within the small-amplitude shift (~theta^2 / 16)."""
    s = load_scene("joints.double_pendulum")
    m = get_model("double_pendulum")(s)
    g, L, r = 9.81, 1.0, 0.05
    Ic = 0.4 * 1.0 * r * r  # each sphere's own moment, 1 kg
    M11, M12, M22 = Ic + 1.0 * L * L + 1.0 * L * L, 1.0 * L * L, Ic + 1.0 * L * L
    K1, K2 = g * 2.0 * L, g * 1.0 * L
    a = M11 * M22 - M12 * M12
    b = -(K1 * M22 + K2 * M11)
    c = K1 * K2
    w2 = sorted(((-b - math.sqrt(b * b - 4 * a * c)) / (2 * a), (-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)))
    np.testing.assert_allclose(m.w, np.sqrt(w2), rtol=1e-12)

    def f(_, y):
        t1, t2, w1, w2_ = y
        d = t1 - t2
        A = np.array([[M11, M12 * math.cos(d)], [M12 * math.cos(d), M22]])
        rhs = np.array([-M12 * w2_ * w2_ * math.sin(d) - K1 * math.sin(t1),
                        M12 * w1 * w1 * math.sin(d) - K2 * math.sin(t2)])
        return [w1, w2_, *np.linalg.solve(A, rhs)]

    t = np.arange(0.0, 12.0 + 1e-12, 0.005)
    sol = solve_ivp(f, (0.0, 12.0), [0.01, 0.02, 0.0, 0.0], t_eval=t, rtol=1e-12, atol=1e-14, method="DOP853")
    t1, t2, w1, w2_ = sol.y
    # the trace: the two sphere centres, each turning with its link (e1 = -z, e2 = -x)
    x1 = np.stack([-L * np.sin(t1), np.zeros_like(t), 2.0 - L * np.cos(t1)], axis=-1)
    x2 = x1 + np.stack([-L * np.sin(t2), np.zeros_like(t), -L * np.cos(t2)], axis=-1)
    F = len(t)
    # the bodies start turned by (0.01, 0.02): their frames at theta are the start's turned on by theta - theta0
    q0 = np.array([b.orientation for b in s.bodies])
    assert np.allclose(q0, [1.0, 0.0, 0.0, 0.0])
    dq1 = np.stack([np.cos((t1 - 0.01) / 2), 0 * t, np.sin((t1 - 0.01) / 2), 0 * t], axis=-1)
    dq2 = np.stack([np.cos((t2 - 0.02) / 2), 0 * t, np.sin((t2 - 0.02) / 2), 0 * t], axis=-1)
    angvel = np.zeros((F, 2, 3))
    angvel[:, 0, 1], angvel[:, 1, 1] = w1, w2_
    tr = SimpleNamespace(t=t, pos=np.stack([x1, x2], axis=1), quat=np.stack([dq1, dq2], axis=1),
                         vel=np.zeros((F, 2, 3)), angvel=angvel)
    out = m.metrics(tr)
    assert out["mode_frequency_error_1"] < 5e-5 and out["mode_frequency_error_2"] < 5e-5
    assert out["linear_amplitude"] == pytest.approx(0.02, rel=1e-12)
    # planted: the same motion 0.5 % slow
    slow = SimpleNamespace(**{**tr.__dict__, "t": t * 1.005, "angvel": angvel / 1.005})
    out = m.metrics(slow)
    assert out["mode_frequency_error_1"] == pytest.approx(1 - 1 / 1.005, abs=5e-5)
    assert out["mode_frequency_error_2"] == pytest.approx(1 - 1 / 1.005, abs=5e-5)
