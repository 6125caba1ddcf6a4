"""The scalar predictions of the reference models beyond the collision,
bounce, slide, spin and flip models, drawn as reference lines at
/metrics/model/<key> with their measured twins, read back with
rerun.chunk.RrdReader.

Each test builds a fake run that moves the way the model says (so each
measured twin must equal its line) and checks the lines against the
model's own functions and, where a closed form is short, against it
computed here (Newton's cradle hands the whole velocity down the row,
rolling is g sin a / (1 + k), the terminal speed of linear drag m g / c...).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from physbench.contract.rotation import quat_rotate
from physbench.contract.scene import load_scene
from physbench.harness.trace import write_rrd
from tests.test_trace_checks import markers, scalars
from tests.test_trace_diagnose import model_of, still_result
from tests.test_trace_rrd import read_rrd, static_value


def fake_run(scene, **arrays):
    """A run of every frame of the scene (dt), at rest at the initial pose
    unless ``arrays`` (pos, quat, vel, angvel: full (F, n, k) arrays or a
    callable of the Trace filling them) say otherwise."""
    F = int(round(scene.duration / scene.dt)) + 1
    res = still_result(scene, "fake", F)
    tr = res.trace
    for name, fill in arrays.items():
        fill(tr) if callable(fill) else getattr(tr, name).__setitem__(slice(None), fill)
    return res


def traced(scene, res, tmp_path):
    path = tmp_path / "p.rrd"
    write_rrd(path, scene, [res], diagnose=True)
    return read_rrd(path)


def lines_equal_model_and_twins(scene, model, data, t_of):
    """Every reference line equals the model's function at the logged
    steps (NaN parts left out), and every measured twin equals its line.
    Returns key -> (steps, line)."""
    out = {}
    for rs in model.reference_series():
        y = rs.model(t_of(np.arange(int(round(scene.duration / scene.dt)) + 1)))
        if not np.isfinite(y).any():
            assert f"/metrics/model/{rs.key}" not in data
            continue
        steps, line = scalars(data, f"/metrics/model/{rs.key}")
        np.testing.assert_array_equal(line, y[steps])
        np.testing.assert_array_equal(steps, np.nonzero(np.isfinite(y))[0])
        if rs.measure is not None:
            s2, meas = scalars(data, f"/metrics/fake/predicted/{rs.key}")
            common = np.isin(s2, steps)
            np.testing.assert_allclose(meas[common], line[np.isin(steps, s2)], rtol=1e-9, atol=1e-9)
        out[rs.key] = (steps, line)
    return out


def model_markers(data, scene, model):
    """The /events/model markers equal the model's moments at round(t / dt)."""
    ev = [(s, tx) for s, _, tx in markers(data, "/events/model")] if "/events/model" in data else []
    want = [(round(t / scene.dt), f"model: {what} at t = {t:.6g} s") for t, what in model.reference_times()
            if t <= scene.duration]
    assert ev == want
    return ev


@pytest.mark.parametrize("variant", [None, "gapped"])
def test_newtons_cradle_hands_the_strike_down_the_row(variant, tmp_path):
    scene = load_scene("billiards.newtons_cradle", variant=variant)
    model = model_of(scene)
    ax = model.axis

    def follow(tr):
        for b in scene.bodies:
            tr.vel[:, b.index] = np.outer(model.row_velocity(tr.t, b.index), ax)

    data = traced(scene, fake_run(scene, vel=follow), tmp_path)
    lines = lines_equal_model_and_twins(scene, model, data, lambda f: f * scene.dt)
    # e = 1, equal masses: the striker's whole velocity leaves with the last ball
    u = float(scene.bodies[0].velocity @ ax)
    last = max(scene.bodies, key=lambda b: b.position @ ax).name
    for b in scene.bodies:
        steps, line = lines[f"{b.name}/row_velocity"]
        assert line[-1] == (u if b.name == last else 0.0)
        assert line[0] == (u if b.index == 0 else 0.0)
    ev = model_markers(data, scene, model)
    # the striker reaches the row after gap / speed; a gapped row hands on
    # one 1 mm gap at a time
    first_gap = scene.bodies[1].position @ ax - scene.bodies[0].position @ ax - 2 * scene.bodies[0].radius
    assert ev[0][0] == round(first_gap / u / scene.dt)
    steps, line = lines[f"{last}/row_velocity"]
    leaves = steps[np.nonzero(line == u)[0][0]]
    gaps = np.diff(sorted(b.position @ ax for b in scene.bodies))[1:] - 2 * scene.bodies[0].radius
    t_last = model.reference_times()[-1][0]
    assert t_last == pytest.approx((first_gap + gaps.sum()) / u, rel=1e-12)
    assert leaves == np.nonzero(np.arange(steps[-1] + 1) * scene.dt >= t_last)[0][0]


def test_break_conserved_momentum_and_energy_lines(tmp_path):
    scene = load_scene("billiards.break_16")
    model = model_of(scene)
    x0, q0, v0, w0 = scene.initial_state()
    data = traced(scene, fake_run(scene, vel=v0[None]), tmp_path)
    lines = lines_equal_model_and_twins(scene, model, data, lambda f: f * scene.dt)
    P0 = np.linalg.norm((scene.masses[:, None] * v0).sum(axis=0)[:2])  # gravity along -z
    np.testing.assert_allclose(lines["scene/momentum_normal_to_gravity"][1], P0, rtol=1e-12)
    g = -scene.gravity[2]
    E0 = sum(0.5 * b.mass * b.velocity @ b.velocity + b.mass * g * b.position[2] for b in scene.bodies)
    np.testing.assert_allclose(lines["scene/energy"][1], E0, rtol=1e-12)
    # restitution below 1: energy is not a conserved quantity, no line
    lossy = model_of(load_scene("billiards.break_16", overrides={"material.default.restitution": 0.9}))
    assert [rs.key for rs in lossy.reference_series()] == ["scene/momentum_normal_to_gravity"]


@pytest.mark.parametrize("sid", ["friction.ball_rolls", "friction.ball_rolls_and_slips", "friction.cylinder_rolls",
                                 "friction.rolling_resistance"])
def test_rolling_speed_and_spin_lines(sid, tmp_path):
    scene = load_scene(sid)
    model = model_of(scene)
    i = model.body.index
    speed, spin = (rs.model for rs in model.reference_series())

    def follow(tr):
        tr.vel[:, i] = np.outer(speed(tr.t), model.d)
        tr.angvel[:, i] = np.outer(spin(tr.t), model.axis)

    data = traced(scene, fake_run(scene, vel=follow, pos=lambda tr: tr.pos.__setitem__(
        slice(None), model.positions(tr.t))), tmp_path)
    name = scene.bodies[i].name
    lines = lines_equal_model_and_twins(scene, model, data, lambda f: f * scene.dt)
    steps, v = lines[f"{name}/speed"]
    t = steps * scene.dt
    b, s = scene.bodies[i], scene.statics[model.slope.index]
    g = float(np.linalg.norm(scene.gravity))
    sin_a, cos_a = math.sin(math.radians(s.angle)), math.cos(math.radians(s.angle))
    k = (b.inertia[0] if b.shape == "sphere" else b.inertia[2]) / (b.mass * b.radius**2)
    if sid == "friction.rolling_resistance":
        mu_r = scene.pair(b.material, s.material).rolling_friction
        a = (g * sin_a - mu_r / b.radius * g * cos_a) / (1 + k)
        u0 = float(b.velocity @ model.d)
        t_stop = -u0 / a
        np.testing.assert_allclose(v[t < t_stop], u0 + a * t[t < t_stop], rtol=1e-12, atol=1e-12)
        assert np.all(v[t >= t_stop] == 0.0)  # holds: tan a <= mu_r / R
        (st, _), = model_markers(data, scene, model)
        assert st == round(t_stop / scene.dt)
    elif model.regime == "roll":
        np.testing.assert_allclose(v, g * sin_a / (1 + k) * t, rtol=1e-12)
        np.testing.assert_allclose(lines[f"{name}/spin"][1], v / b.radius, rtol=1e-12)
    else:
        mu_k = scene.pair(b.material, s.material).friction
        np.testing.assert_allclose(v, g * (sin_a - mu_k * cos_a) * t, rtol=1e-12)


def test_heavy_top_precession_and_tilt_lines(tmp_path):
    scene = load_scene("gyroscopic.heavy_top")
    model = model_of(scene)

    def follow(tr):
        x, q = model.reference(tr.t)
        tr.pos[:, 0], tr.quat[:, 0] = x, q

    data = traced(scene, fake_run(scene, quat=follow), tmp_path)
    lines = lines_equal_model_and_twins(scene, model, data, lambda f: f * scene.dt)
    steps, az = lines["top/precession_angle"]
    # the line's mean slope is the precession rate the metric's reference fits
    t = steps * scene.dt
    tm = t - t.mean()
    assert float(tm @ (az - az.mean()) / (tm @ tm)) == pytest.approx(model.precession_rate_ref(), rel=1e-9)
    # the tilt starts at the body's initial tilt of the symmetry axis from the vertical
    e = np.zeros(3)
    e[model.sym] = 1.0
    a0 = quat_rotate(np.asarray(scene.bodies[0].orientation, float), e)
    assert lines["top/tilt"][1][0] == pytest.approx(math.acos(a0 @ model.up), abs=1e-9)
    text = static_value(data, "/context/model", "TextDocument:text")[0]
    assert f"{model.precession_rate_ref():.6g} rad/s" in text


def test_static_stack_heights_are_the_start_heights(tmp_path):
    scene = load_scene("stacking.column_5")
    model = model_of(scene)
    sink = 1e-4 * np.arange(int(round(scene.duration / scene.dt)) + 1)  # m, a planted sinking of the top box

    def plant(tr):
        tr.pos[:, -1, 2] -= sink[:tr.pos.shape[0]]

    data = traced(scene, fake_run(scene, pos=plant), tmp_path)
    for b in scene.bodies:
        steps, line = scalars(data, f"/metrics/model/{b.name}/height")
        np.testing.assert_array_equal(line, b.position[2])
        _, meas = scalars(data, f"/metrics/fake/predicted/{b.name}/height")
        np.testing.assert_allclose(meas, b.position[2] - (sink[steps] if b.index == scene.n_bodies - 1 else 0.0),
                                   atol=1e-12)


@pytest.mark.parametrize("sid", ["stacking.log_pile", "stacking.log_pile_slides"])
def test_log_pile_drop_line_and_fall_level(sid, tmp_path):
    scene = load_scene(sid)
    model = model_of(scene)
    data = traced(scene, fake_run(scene), tmp_path)
    top = scene.bodies[model.top].name
    r = scene.bodies[0].radius
    lower = [b for b in scene.bodies if b.index != model.top]
    s = 0.5 * abs(lower[0].position[0] - lower[1].position[0])
    steps, level = scalars(data, f"/metrics/model/{top}/fall_level")
    np.testing.assert_allclose(level, 0.5 * math.sqrt(4 * r * r - s * s), rtol=1e-12)
    _, meas = scalars(data, f"/metrics/fake/predicted/{top}/drop")
    np.testing.assert_array_equal(meas, 0.0)
    if model.holds:
        np.testing.assert_array_equal(scalars(data, f"/metrics/model/{top}/drop")[1], 0.0)
    else:  # a collapse has no timed line, only the level it must pass
        assert f"/metrics/model/{top}/drop" not in data
    text = static_value(data, "/context/model", "TextDocument:text")[0]
    assert ("outcome: holds" if model.holds else "outcome: collapses") in text


@pytest.mark.parametrize("sid", ["forces.damped_spring", "forces.spring_pair"])
def test_oscillator_displacement_envelope_and_crossings(sid, tmp_path):
    scene = load_scene(sid)
    model = model_of(scene)
    pos = model.positions(np.arange(int(round(scene.duration / scene.dt)) + 1) * scene.dt)
    idx = list(model.idx)

    def follow(tr):
        tr.pos[:, idx] = pos[:, idx]

    data = traced(scene, fake_run(scene, pos=follow), tmp_path)
    lines = lines_equal_model_and_twins(scene, model, data, lambda f: f * scene.dt)
    key = "_".join(scene.bodies[i].name for i in idx)
    steps, y = lines[f"{key}/displacement"]
    sp = scene.springs[0]
    m_eff = scene.bodies[idx[0]].mass if len(idx) == 1 else 1 / sum(1 / scene.bodies[i].mass for i in idx)
    gamma, w0 = sp.damping / (2 * m_eff), math.sqrt(sp.stiffness / m_eff)
    wd = math.sqrt(w0 * w0 - gamma * gamma)
    # the markers are the upward crossings of the equilibrium, one period 2 pi / wd apart
    tc = np.array([t for t, _ in model.reference_times()])
    assert len(tc) >= 3
    np.testing.assert_allclose(np.diff(tc), 2 * math.pi / wd, rtol=1e-12)
    np.testing.assert_allclose(model.y(tc), 0.0, atol=1e-12 * model.amp)
    assert np.all(model.y(tc + 1e-6) > 0)
    model_markers(data, scene, model)
    if gamma > 0:
        _, env = lines[f"{key}/envelope"]
        assert np.all(np.abs(y) <= env * (1 + 1e-12))
        np.testing.assert_allclose(env, model.amp * np.exp(-gamma * steps * scene.dt), rtol=1e-12)
    else:
        assert f"/metrics/model/{key}/envelope" not in data


@pytest.mark.parametrize("sid", ["forces.drag_linear_fall", "forces.drag_quadratic_fall"])
def test_drag_speed_and_terminal_speed(sid, tmp_path):
    scene = load_scene(sid)
    model = model_of(scene)
    b = scene.bodies[0]

    def follow(tr):
        tr.pos[:, 0], tr.vel[:, 0] = model.state(tr.t)

    data = traced(scene, fake_run(scene, vel=follow), tmp_path)
    lines = lines_equal_model_and_twins(scene, model, data, lambda f: f * scene.dt)
    g = float(np.linalg.norm(scene.gravity))
    vt = b.mass * g / b.drag_linear if model.quadratic is False else math.sqrt(b.mass * g / b.drag_quadratic)
    np.testing.assert_allclose(lines["ball/terminal_speed"][1], vt, rtol=1e-12)
    steps, v = lines["ball/speed"]
    assert abs(v[-1] - vt) < 0.01 * abs(v[0] - vt)  # has all but reached v_t
    if not model.quadratic:
        t = steps * scene.dt
        v0 = b.velocity
        vv = model.vt_vec + np.outer(np.exp(-t * b.drag_linear / b.mass), v0 - model.vt_vec)
        np.testing.assert_allclose(v, np.linalg.norm(vv, axis=1), rtol=1e-12)


def test_bullet_bounce_line_and_a_planted_tunnelling_count(tmp_path):
    scene = load_scene("tunnelling.bullet_400")
    model = model_of(scene)
    (i, v_ref, _vn, t_hit, n, wall), = model._bullets
    wall_s = next(s for s in scene.statics if s.name == wall)
    u = scene.bodies[i].velocity
    e = scene.pair(scene.bodies[i].material, wall_s.material).restitution
    F = int(round(scene.duration / scene.dt)) + 1
    pass_frame = F // 2
    x0 = scene.bodies[i].position
    # planted: the bullet flies straight through the wall at its speed, and is
    # measured with the model's velocity (the twin follows the line)
    tt = np.arange(F) * scene.dt

    def plant(tr):
        tr.pos[:, i] = x0 + np.outer(tt, u)
        tr.vel[:, i] = np.where((tt < t_hit)[:, None], u, v_ref)

    data = traced(scene, fake_run(scene, pos=plant), tmp_path)
    steps, vn = scalars(data, f"/metrics/model/{scene.bodies[i].name}/normal_velocity")
    t = steps * scene.dt
    np.testing.assert_allclose(vn[t < t_hit], u @ n, rtol=1e-12)
    np.testing.assert_allclose(vn[t >= t_hit], -e * (u @ n), rtol=1e-12)
    _, meas = scalars(data, f"/metrics/fake/predicted/{scene.bodies[i].name}/normal_velocity")
    np.testing.assert_allclose(meas, vn, rtol=1e-12)
    model_markers(data, scene, model)
    # the count of tunnelled bodies: 0 on the model's line; on the run it
    # steps to 1 at the frame the engine's marker says the bullet passed the wall
    _, zero = scalars(data, "/metrics/model/scene/tunnelled_bodies")
    assert np.all(zero == 0.0)
    s2, count = scalars(data, "/metrics/fake/predicted/scene/tunnelled_bodies")
    ev = [s for s, _, tx in markers(data, "/events/fake") if tx.startswith("tunnelling:")]
    d = (x0 + np.outer(tt, u) - wall_s.position) @ n
    crossed = int(np.nonzero(d > 0)[0][0])
    assert ev == [crossed] and crossed < pass_frame * 2
    np.testing.assert_array_equal(count, (s2 >= crossed).astype(float))


def test_trace_cost_tool_measures_a_traced_run_and_its_file(tmp_path):
    """physbench.harness.selfbench.trace_cost (docs/TRACES.md, "Cost") on a short column: one
    row per engine with the traced run's engine contacts and the file it
    wrote (sizes and counts only: a benchmark, no time is asserted)."""
    from physbench.harness.selfbench.trace_cost import markdown, measure

    (row,) = measure("stacking.column_5", duration=0.05, repeats=1, engines=("pymunk",), out_dir=tmp_path)
    assert row["status"] == "ok" and row["frames"] == int(round(0.05 / load_scene("stacking.column_5").dt)) + 1
    assert row["contact_rows"] > 0  # five boxes resting on each other touch from the first step
    assert row["size"] == (tmp_path / "pymunk.rrd").stat().st_size > row["plain_size"] > 0
    assert markdown([row]).splitlines()[2].startswith("| pymunk |")
