"""Step phase (contract/phase.py): the shifted start lies on the same exact
free flight, so running it forward by tau gives back the scene's start;
scenes whose start is not free flight are refused with a clear error."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from physbench.contract.phase import PhaseError, phase_values, shift_scene, wilson_interval
from physbench.contract.rotation import quat_exp as _qexp, quat_mul as _qmul, rotation_matrix as _qmat
from physbench.contract.scene import load_scene


def _forward_torque_free(q, w_world, inertia, tau):
    R = _qmat(q)

    def rhs(_t, y):
        qq, wb = y[:4], y[4:]
        return np.concatenate([0.5 * _qmul(qq, np.concatenate([[0.0], wb])), -np.cross(wb, inertia * wb) / inertia])

    sol = solve_ivp(rhs, (0.0, tau), np.concatenate([q, R.T @ w_world]), method="DOP853", rtol=1e-12, atol=1e-14)
    qq = sol.y[:4, -1] / np.linalg.norm(sol.y[:4, -1])
    return qq, _qmat(qq) @ sol.y[4:, -1]


def test_phase_zero_is_the_scene_itself_and_values_are_i_over_n():
    sc = load_scene("tunnelling.thin_box_on_thin_floor")
    assert shift_scene(sc, 0.0) is sc
    assert phase_values(4) == (0.0, 0.25, 0.5, 0.75)
    for bad in (-0.1, 1.0, 1.5):
        with pytest.raises(PhaseError, match="phase must be in"):
            shift_scene(sc, bad)
    with pytest.raises(PhaseError, match="positive integer"):
        phase_values(0)


@pytest.mark.parametrize("sid", ["tunnelling.thin_box_on_thin_floor", "tunnelling.spinning_long_box",
                                 "tunnelling.bullet_400", "gyroscopic.dzhanibekov"])
def test_forward_free_flight_over_tau_returns_to_the_start(sid):
    """x(-tau) + v(-tau) tau + g tau^2 / 2 = x0, v(-tau) + g tau = v0, and the
    rotation run forward (constant world w, or torque-free Euler equations
    when the scene lists 'gyroscopic') lands on (q0, w0)."""
    sc = load_scene(sid)
    g = sc.gravity
    for f in (0.25, 0.7):
        tau = f * sc.dt
        sh = shift_scene(sc, f)
        assert sh.id == sc.id and sh.dt == sc.dt and len(sh.bodies) == len(sc.bodies)
        for b0, b in zip(sc.bodies, sh.bodies):
            assert np.allclose(b.position + b.velocity * tau + 0.5 * g * tau * tau, b0.position, rtol=0, atol=1e-13)
            assert np.allclose(b.velocity + g * tau, b0.velocity, rtol=0, atol=1e-12)
            if sc.has("gyroscopic"):
                q, w = _forward_torque_free(b.orientation, b.angular_velocity, np.asarray(b.inertia), tau)
            else:
                q, w = _qmul(_qexp(b.angular_velocity * tau), b.orientation), b.angular_velocity
            assert min(np.abs(q - b0.orientation).max(), np.abs(q + b0.orientation).max()) < 1e-10
            assert np.allclose(w, b0.angular_velocity, rtol=0, atol=1e-9)
            assert np.isclose(np.linalg.norm(b.orientation), 1.0)


def test_dzhanibekov_shift_is_not_a_constant_rotation():
    """The asymmetric box tumbles: its world angular velocity changes over
    tau (the torque-free integration is used, not exp(-w tau))."""
    sc = load_scene("gyroscopic.dzhanibekov")
    sh = shift_scene(sc, 0.5, dt=0.05)
    assert not np.allclose(sh.bodies[0].angular_velocity, sc.bodies[0].angular_velocity, atol=1e-9)
    # energy and angular momentum are those of the start
    for s in (sc, sh):
        b = s.bodies[0]
        R = _qmat(b.orientation)
        L = R @ (np.asarray(b.inertia) * (R.T @ b.angular_velocity))
        if s is sc:
            L0 = L
    assert np.allclose(L, L0, rtol=1e-10)


def test_reference_engine_run_from_a_shifted_start_samples_the_same_motion():
    """A ball in free fall (rk4 is exact for constant gravity): the shifted
    run's frames are the original motion at t - tau."""
    from physbench.harness.runner import run

    sc = load_scene("tunnelling.thin_box_on_thin_floor")
    sc = dataclasses.replace(sc, duration=0.2)
    f = 0.4
    tau = f * sc.dt
    res = run(shift_scene(sc, f), "reference", {"integrator": "rk4"})
    assert res.status == "ok"
    b0 = sc.bodies[0]
    t = res.trace.t - tau  # original-motion time of each frame
    exact = b0.position + np.outer(t, b0.velocity) + 0.5 * np.outer(t * t, sc.gravity)
    assert np.abs(res.trace.pos[:, 0] - exact).max() < 1e-12


def test_shift_uses_the_runs_dt():
    sc = load_scene("tunnelling.thin_box_on_thin_floor")
    a = shift_scene(sc, 0.5, dt=0.01)
    b = shift_scene(dataclasses.replace(sc, dt=0.01), 0.5)
    assert np.array_equal(a.bodies[0].position, b.bodies[0].position)
    assert a.bodies[0].velocity[2] == pytest.approx(-sc.gravity[2] * 0.005)


def test_scenes_not_in_free_flight_are_refused():
    # resting on the floor: the box touches the plane
    with pytest.raises(PhaseError, match=r"stacking.column_5: .*within .* of static"):
        shift_scene(load_scene("stacking.column_5"), 0.5)
    # springs act in free flight
    with pytest.raises(PhaseError, match="gyroscopic.heavy_top: .*(spring|damper)"):
        shift_scene(load_scene("gyroscopic.heavy_top"), 0.5)
    # balls touching in a row
    with pytest.raises(PhaseError, match="billiards.newtons_cradle: .*(bodies|static)"):
        shift_scene(load_scene("billiards.newtons_cradle"), 0.5)


def test_wilson_interval():
    lo, hi = wilson_interval(0, 32)
    assert lo == 0.0 and hi == pytest.approx(0.1072, abs=1e-4)  # "0/32 bounds the rate below 0.11"
    lo, hi = wilson_interval(16, 32)
    assert lo == pytest.approx(0.3364, abs=1e-4) and hi == pytest.approx(0.6636, abs=1e-4)
    assert all(math.isnan(x) for x in wilson_interval(0, 0))


def test_clearance_is_checked_between_samples_of_a_fast_path():
    """A 0.1 m ball at 400 m/s (no gravity) whose backward path over
    15/16 of a 1/60 s step grazes a box edge 0.05 m deep at tau/64: the
    check must see it (samples 33 along the 6 m path would miss it)."""
    sc = load_scene("tunnelling.bullet_400")
    st = dataclasses.replace(sc.statics[0], position=np.zeros(3), half_extents=np.array([0.5, 0.5, 0.5]))
    v = 400.0 * np.array([1.0, -1.0, 0.0]) / math.sqrt(2.0)
    tau = 15 / 16 / 60
    closest = np.array([0.5, 0.5, 0.0]) + 0.05 * np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0)
    x0 = closest + v * tau / 64
    b = dataclasses.replace(sc.bodies[0], radius=0.1, position=x0, velocity=v)
    bad = dataclasses.replace(sc, bodies=(b,), statics=(st,), effects=frozenset({"contact"}))
    with pytest.raises(PhaseError, match="comes within -0.05 m of static"):
        shift_scene(bad, 15 / 16, dt=1 / 60)
    # the same path 0.2 m from the edge is clear
    b = dataclasses.replace(b, position=x0 + 0.15 * np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0))
    shift_scene(dataclasses.replace(bad, bodies=(b,)), 15 / 16, dt=1 / 60)


def test_a_static_box_without_orientation_is_the_identity():
    sc = load_scene("tunnelling.thin_box_on_thin_floor")
    st = dataclasses.replace(sc.statics[0], orientation=None)
    sh = shift_scene(dataclasses.replace(sc, statics=(st,)), 0.5)
    assert np.array_equal(sh.bodies[0].position, shift_scene(sc, 0.5).bodies[0].position)


def test_the_torque_free_backward_flight_matches_an_adaptive_solver():
    """The fixed-step Runge-Kutta of contract/phase.py against scipy's DOP853
    at rtol 1e-13 (computed here), for random tumbling bodies: quaternion
    within 1e-11, world angular velocity within 1e-11 |w|."""
    from physbench.contract.phase import _torque_free_back

    rng = np.random.default_rng(7)
    for _ in range(12):
        inertia = rng.uniform(0.1, 2.0, 3)
        q0 = rng.normal(size=4)
        q0 /= np.linalg.norm(q0)
        w0 = rng.normal(size=3) * rng.uniform(1.0, 80.0)
        tau = rng.uniform(1e-3, 0.05)
        q, w = _torque_free_back(q0, w0, inertia, tau)
        R = _qmat(q0)

        def rhs(_t, y):
            qq, wb = y[:4], y[4:]
            return np.concatenate([0.5 * _qmul(qq, np.concatenate([[0.0], wb])), -np.cross(wb, inertia * wb) / inertia])

        sol = solve_ivp(rhs, (0.0, -tau), np.concatenate([q0, R.T @ w0]), method="DOP853", rtol=1e-13, atol=1e-15)
        qr = sol.y[:4, -1] / np.linalg.norm(sol.y[:4, -1])
        wr = _qmat(qr) @ sol.y[4:, -1]
        assert min(np.abs(q - qr).max(), np.abs(q + qr).max()) < 1e-11
        assert np.abs(w - wr).max() < 1e-11 * np.linalg.norm(w0)
