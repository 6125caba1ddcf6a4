"""Reference engine: integrator orders, the gyroscopic modes, the free
rigid body against a high-accuracy solution.

Truth: the damped harmonic oscillator's closed form; Euler's equations of a
torque-free rigid body integrated by scipy's DOP853 at rtol 1e-13; the
conservation of kinetic energy and of world angular momentum for a free
body.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from physbench.contract.rotation import quat_mul, quat_to_matrix
from physbench.adapters.reference import engine_for
from physbench.contract.scene import load_scene

ORDERS = {"explicit_euler": 1, "semi_implicit_euler": 1, "midpoint": 2, "heun": 2, "rk4": 4, "velocity_verlet": 2}


def scene(tmp_path: Path, text: str, name: str):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return load_scene(p)


def box_scene(tmp_path, w=(1.0, 3.0, 2.0), duration=1.0, dt=0.01, effects='["gyroscopic"]'):
    return scene(tmp_path, f"""
        [scenario]
        family = "t"
        title = "free box"
        duration = {duration}
        dt = {dt}
        effects = {effects}
        [[body]]
        name = "b"
        shape = "box"
        half_extents = [0.3, 0.2, 0.05]
        mass = 1.0
        angular_velocity = [{w[0]}, {w[1]}, {w[2]}]
        """, "box.toml")


def free_body_reference(I, w0, t_eval):
    """Orientation (k, 4) and world angular velocity (k, 3) of a torque-free
    body from q = identity, by DOP853 on q' = 1/2 q (x) (0, w_b),
    I w_b' = (I w_b) x w_b."""
    def rhs(t, y):
        q, wb = y[:4], y[4:]
        dq = 0.5 * quat_mul(q, np.concatenate([[0.0], wb]))
        return np.concatenate([dq, np.cross(I * wb, wb) / I])

    sol = solve_ivp(rhs, (0.0, float(t_eval[-1])), np.concatenate([[1.0, 0, 0, 0], w0]), method="DOP853",
                    rtol=1e-13, atol=1e-13, t_eval=t_eval)
    q = sol.y[:4].T
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w = np.einsum("kij,kj->ki", quat_to_matrix(q), sol.y[4:].T)
    return q, w


def angle_between(qa, qb):
    return 2.0 * np.arccos(np.clip(np.abs(np.sum(qa * qb, axis=-1)), 0.0, 1.0))


def fitted_order(dts, errs):
    return float(np.polyfit(np.log(dts), np.log(errs), 1)[0])


@pytest.mark.parametrize("integrator", list(ORDERS))
def test_order_torque_free_box(tmp_path, integrator):
    sc = box_scene(tmp_path)
    T = 1.0
    qr, wr = free_body_reference(sc.bodies[0].inertia, sc.bodies[0].angular_velocity, np.array([T]))
    dts = [0.02, 0.01, 0.005, 0.0025]
    errs = []
    for dt in dts:
        eng = engine_for(sc, {"dt": dt, "integrator": integrator, "gyroscopic": "explicit"})
        eng.step(int(round(T / dt)))
        errs.append(np.linalg.norm(eng.state.w[0] - wr[0]) + angle_between(eng.state.q[0], qr[0]))
    assert abs(fitted_order(dts, errs) - ORDERS[integrator]) <= 0.3, errs


@pytest.mark.parametrize("integrator", list(ORDERS))
def test_order_damped_spring(tmp_path, integrator):
    m, k, c, x0, T = 0.5, 20.0, 0.4, 0.3, 2.0
    sc = scene(tmp_path, f"""
        [scenario]
        family = "t"
        title = "damped spring"
        duration = {T}
        dt = 0.01
        effects = ["spring", "damper"]
        [[body]]
        name = "b"
        shape = "sphere"
        radius = 0.05
        mass = {m}
        position = [{x0}, 0, 0]
        [[spring]]
        a = "world"
        b = "b"
        stiffness = {k}
        rest_length = 0.0
        damping = {c}
        """, "spring.toml")
    w0 = np.sqrt(k / m)
    z = c / (2 * np.sqrt(k * m))
    wd = w0 * np.sqrt(1 - z * z)
    exact = np.exp(-z * w0 * T) * x0 * (np.cos(wd * T) + z * w0 / wd * np.sin(wd * T))
    dts = [0.01, 0.005, 0.0025, 0.00125]
    errs = []
    for dt in dts:
        eng = engine_for(sc, {"dt": dt, "integrator": integrator})
        eng.step(int(round(T / dt)))
        errs.append(abs(eng.state.x[0, 0] - exact))
    assert abs(fitted_order(dts, errs) - ORDERS[integrator]) <= 0.3, errs


def _energy_and_momentum(sc, eng):
    I = sc.bodies[0].inertia
    R = quat_to_matrix(eng.state.q[0])
    wb = R.T @ eng.state.w[0]
    return 0.5 * wb @ (I * wb), R @ (I * wb)


def _dzhanibekov(tmp_path, settings, T=20.0, dt=1 / 240):
    """Relative energy change (max gain, max loss) and world angular momentum
    drift of the box 0.6 x 0.4 x 0.1 spun at 10 rad/s about its
    intermediate axis (flips ~7 times in 20 s)."""
    sc = box_scene(tmp_path, w=(0.0, 10.0, 0.01), duration=T, dt=dt)
    eng = engine_for(sc, settings)
    E0, L0 = _energy_and_momentum(sc, eng)
    gain = loss = dl = 0.0
    for _ in range(int(round(T / dt))):
        eng.step()
        E, L = _energy_and_momentum(sc, eng)
        gain = max(gain, (E - E0) / E0)
        loss = min(loss, (E - E0) / E0)
        dl = max(dl, np.linalg.norm(L - L0) / np.linalg.norm(L0))
    return gain, loss, dl, eng


@pytest.mark.slow
def test_dzhanibekov_energy_by_gyroscopic_mode(tmp_path):
    gain, loss, dl, _ = _dzhanibekov(tmp_path, {"gyroscopic": "energy_conserving"})  # the default
    assert gain <= 1e-6 and -loss <= 1e-6 and dl <= 1e-6
    gain, loss, _, _ = _dzhanibekov(tmp_path, {"gyroscopic": "explicit", "integrator": "semi_implicit_euler"})
    assert gain > 0.1 and loss == 0.0  # the forward-Euler gyroscopic term creates energy
    gain, loss, _, _ = _dzhanibekov(tmp_path, {"gyroscopic": "implicit"})
    assert gain == 0.0 and loss < -0.1  # Catto's implicit step dissipates


def test_explicit_gyroscopic_gains_energy_short(tmp_path):
    """The same ordering over 2 s (fast run)."""
    g_exp, l_exp, _, _ = _dzhanibekov(tmp_path, {"gyroscopic": "explicit", "integrator": "semi_implicit_euler"}, T=2.0)
    g_imp, l_imp, _, _ = _dzhanibekov(tmp_path, {"gyroscopic": "implicit"}, T=2.0)
    g_ec, l_ec, dl, _ = _dzhanibekov(tmp_path, {}, T=2.0)
    assert g_exp > 1e-3 and l_exp == 0.0
    assert g_imp == 0.0 and l_imp < -1e-3
    assert max(g_ec, -l_ec, dl) <= 1e-9


@pytest.mark.slow
def test_free_body_orientation_through_flips(tmp_path):
    """Default settings against DOP853 over 20 s (seven flips)."""
    T, dt = 20.0, 1 / 240
    sc = box_scene(tmp_path, w=(0.0, 10.0, 0.01), duration=T, dt=dt)
    n = int(round(T / dt))
    t = dt * np.arange(1, n + 1)
    qr, wr = free_body_reference(sc.bodies[0].inertia, sc.bodies[0].angular_velocity, t)
    flips = int(np.sum(np.diff(np.sign(np.einsum("kji,kj->ki", quat_to_matrix(qr), wr)[:, 1])) != 0))
    assert flips >= 2
    eng = engine_for(sc)
    err = 0.0
    for k in range(n):
        eng.step()
        err = max(err, float(angle_between(eng.state.q[0], qr[k])))
    assert err <= 1e-3  # rad; measured 5e-5
    assert np.allclose(eng.state.w[0], wr[-1], atol=1e-2)


def test_free_body_short_against_reference(tmp_path):
    T, dt = 2.0, 1 / 240
    sc = box_scene(tmp_path, w=(1.0, 3.0, 2.0), duration=T, dt=dt)
    qr, wr = free_body_reference(sc.bodies[0].inertia, sc.bodies[0].angular_velocity, np.array([T]))
    eng = engine_for(sc)
    eng.step(int(round(T / dt)))
    assert angle_between(eng.state.q[0], qr[0]) <= 1e-6
    assert np.linalg.norm(eng.state.w[0] - wr[0]) <= 1e-6
    assert abs(np.linalg.norm(eng.state.q[0]) - 1.0) <= 1e-14


def test_without_gyroscopic_effect_w_is_constant(tmp_path):
    """Without the 'gyroscopic' effect the w x I w term is absent: w stays
    constant (and no gyroscopic stage exists)."""
    sc = box_scene(tmp_path, effects="[]")
    eng = engine_for(sc)
    eng.step(100)
    assert np.array_equal(eng.state.w[0], sc.bodies[0].angular_velocity)
    assert "gyroscopic" not in eng.profile.calls
    # rotation at constant w is exact: q = exp(t w / 2)
    w = sc.bodies[0].angular_velocity
    ang = np.linalg.norm(w) * 1.0
    q_exact = np.concatenate([[np.cos(ang / 2)], np.sin(ang / 2) * w / np.linalg.norm(w)])
    assert angle_between(eng.state.q[0], q_exact) <= 1e-12
