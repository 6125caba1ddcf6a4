"""Reference engine: force stages against closed forms (drag, springs),
penalty contacts, and the pipeline's effect-driven assembly."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from physbench.adapters import get_adapter
from physbench.adapters.reference import engine_for
from physbench.harness.runner import run
from physbench.contract.scene import load_scene


def scene_from(tmp_path: Path, text: str, name: str = "s.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return load_scene(p)


def test_linear_drag_exponential_decay(tmp_path):
    m, c, v0, T = 0.5, 0.3, 4.0, 2.0
    sc = scene_from(tmp_path, f"""
        [scenario]
        family = "t"
        title = "stokes"
        duration = {T}
        dt = 0.01
        effects = ["drag_linear"]
        [[body]]
        name = "b"
        shape = "sphere"
        radius = 0.05
        mass = {m}
        velocity = [{v0}, 0, 0]
        drag_linear = {c}
        """)
    eng = engine_for(sc)
    eng.step(200)
    k = c / m
    assert eng.state.v[0, 0] == pytest.approx(v0 * math.exp(-k * T), rel=1e-9)
    assert eng.state.x[0, 0] == pytest.approx(v0 / k * (1 - math.exp(-k * T)), rel=1e-9)


def test_quadratic_drag_closed_form(tmp_path):
    m, c, v0, T = 0.2, 0.05, 10.0, 1.5
    sc = scene_from(tmp_path, f"""
        [scenario]
        family = "t"
        title = "newton drag"
        duration = {T}
        dt = 0.005
        effects = ["drag_quadratic"]
        [[body]]
        name = "b"
        shape = "sphere"
        radius = 0.05
        mass = {m}
        velocity = [0, {v0}, 0]
        drag_quadratic = {c}
        """)
    eng = engine_for(sc)
    eng.step(300)
    k = c / m  # v' = -k v^2: v = v0 / (1 + k v0 t), x = ln(1 + k v0 t) / k
    assert eng.state.v[0, 1] == pytest.approx(v0 / (1 + k * v0 * T), rel=1e-8)
    assert eng.state.x[0, 1] == pytest.approx(math.log(1 + k * v0 * T) / k, rel=1e-8)


def test_terminal_velocity_gravity_and_drag(tmp_path):
    m, c = 1.0, 2.0
    sc = scene_from(tmp_path, f"""
        [scenario]
        family = "t"
        title = "terminal"
        duration = 5.0
        dt = 0.01
        effects = ["gravity", "drag_linear"]
        [[body]]
        name = "b"
        shape = "sphere"
        radius = 0.05
        mass = {m}
        drag_linear = {c}
        """)
    eng = engine_for(sc)
    eng.step(500)
    assert eng.state.v[0, 2] == pytest.approx(-9.81 * m / c * (1 - math.exp(-c / m * 5.0)), rel=1e-9)


@pytest.mark.parametrize("settings,energy_tol", [({}, 1e-4), ({"gyroscopic": "explicit"}, 1e-8)])
def test_two_body_spring_conserves_momentum_and_energy(tmp_path, settings, energy_tol):
    """Two masses on an undamped spring with off-centre anchors: total linear
    and angular momentum are conserved exactly; energy to the integrator's
    accuracy: rk4 with the gyroscopic term in the ODE gives 1e-9 over 5 s;
    the default energy-conserving rotation is exact for the free rotation
    but couples spin and spring by a second-order splitting (measured
    6.5e-5)."""
    sc = scene_from(tmp_path, """
        [scenario]
        family = "t"
        title = "dumbbell"
        duration = 5.0
        dt = 0.002
        effects = ["spring", "gyroscopic"]
        [[body]]
        name = "a"
        shape = "box"
        half_extents = [0.1, 0.05, 0.02]
        mass = 1.0
        velocity = [0, 0.3, 0]
        angular_velocity = [0.5, 0, 1.0]
        [[body]]
        name = "b"
        shape = "sphere"
        radius = 0.05
        mass = 2.0
        position = [0.6, 0, 0]
        velocity = [0, -0.15, 0.1]
        [[spring]]
        a = "a"
        b = "b"
        anchor_a = [0.1, 0.05, 0]
        anchor_b = [0, 0, 0.05]
        stiffness = 40.0
        rest_length = 0.4
        """)
    eng = engine_for(sc, settings)
    m = sc.masses
    from physbench.contract.rotation import quat_to_matrix

    def invariants():
        s = eng.state
        P = m @ s.v
        com = m @ s.x / m.sum()
        L = np.zeros(3)
        E = 0.5 * m @ np.sum(s.v ** 2, axis=1)
        for i, b in enumerate(sc.bodies):
            R = quat_to_matrix(s.q[i])
            Lb = R @ (b.inertia * (R.T @ s.w[i]))
            L += Lb + m[i] * np.cross(s.x[i] - com, s.v[i])
            E += 0.5 * s.w[i] @ Lb
        sp = sc.springs[0]
        pa = s.x[0] + quat_to_matrix(s.q[0]) @ sp.anchor_a
        pb = s.x[1] + quat_to_matrix(s.q[1]) @ sp.anchor_b
        E += 0.5 * sp.stiffness * (np.linalg.norm(pb - pa) - sp.rest_length) ** 2
        return P, L, E

    P0, L0, E0 = invariants()
    eng.step(2500)
    P, L, E = invariants()
    assert np.allclose(P, P0, atol=1e-12)
    assert np.linalg.norm(L - L0) / np.linalg.norm(L0) <= 1e-6
    assert abs(E - E0) / E0 <= energy_tol


def test_penalty_contacts_bounce(tmp_path):
    """Penalty springs: the bounce of a dropped ball has the pair's
    restitution (linear spring-dashpot law), within 2 %, and a small
    penetration."""
    sc = scene_from(tmp_path, """
        [scenario]
        family = "t"
        title = "penalty drop"
        duration = 1.2
        dt = 0.001
        effects = ["gravity", "contact", "restitution"]
        [material.default]
        restitution = 0.8
        [[body]]
        name = "ball"
        shape = "sphere"
        radius = 0.1
        mass = 1.0
        position = [0, 0, 0.6]
        [[static]]
        shape = "plane"
        normal = [0, 0, 1]
        """)
    res = run(sc, "reference", {"contact_model": "penalty"})
    assert res.status == "ok"
    assert "penalty" in res.stages and "solve" not in res.stages and "ccd" not in res.stages
    vz = res.trace.valid().vel[:, 0, 2]
    v_in = -vz.min()
    v_out = vz[np.argmin(vz):].max()
    assert v_out / v_in == pytest.approx(0.8, abs=0.02)
    z = res.trace.valid().pos[:, 0, 2]
    assert 0.1 - z.min() <= 0.02


def test_pipeline_follows_effects(tmp_path):
    base = """
        [scenario]
        family = "t"
        title = "pipeline"
        duration = 0.1
        dt = 0.01
        effects = {effects}
        [[body]]
        name = "b"
        shape = "box"
        half_extents = [0.1, 0.2, 0.3]
        mass = 1.0
        position = [0, 0, 1]
        [[static]]
        shape = "plane"
        normal = [0, 0, 1]
        """
    names = lambda e, **s: [st.name for st in engine_for(scene_from(tmp_path, base.format(effects=e)), s).stages]  # noqa: E731
    assert names("[]") == ["integrate_velocities", "integrate_positions"]
    assert names('["gravity"]') == ["gravity", "integrate_velocities", "integrate_positions"]
    assert names('["gyroscopic"]') == ["integrate_velocities", "gyroscopic", "integrate_positions"]
    assert names('["gyroscopic"]', gyroscopic="implicit") == ["gyroscopic", "integrate_velocities",
                                                              "integrate_positions"]
    assert names('["gyroscopic"]', gyroscopic="explicit") == ["gyroscopic", "integrate_velocities",
                                                              "integrate_positions"]
    assert names('["contact"]') == ["integrate_velocities", "broadphase", "narrowphase", "solve",
                                    "integrate_positions", "ccd", "impact"]
    assert names('["contact"]', ccd="off") == ["integrate_velocities", "broadphase", "narrowphase", "solve",
                                               "integrate_positions"]
    # friction rows only with 'friction'
    e1 = engine_for(scene_from(tmp_path, base.format(effects='["gravity", "contact"]')))
    e2 = engine_for(scene_from(tmp_path, base.format(effects='["gravity", "contact", "friction"]')))
    assert not next(s for s in e1.stages if s.name == "solve").friction
    assert next(s for s in e2.stages if s.name == "solve").friction


def test_adapter_contract(tmp_path):
    cls = get_adapter("reference")
    caps = cls.capabilities()
    assert caps.engine == "reference" and caps.version.startswith("physbench-") and caps.dimensions == 3
    assert {"sphere", "box", "capsule", "cylinder"} <= caps.shapes
    assert caps.static_shapes == {"plane", "slope", "box"}
    for name in ("dt", "integrator", "gyroscopic", "iterations", "position_correction", "warm_starting",
                 "broadphase", "ccd", "contact_model", "substeps", "restitution_threshold"):
        assert name in caps.settings
    assert caps.settings["integrator"].choices == ("explicit_euler", "semi_implicit_euler", "midpoint", "heun",
                                                   "rk4", "velocity_verlet")
    sc = scene_from(tmp_path, """
        [scenario]
        family = "t"
        title = "cyl"
        duration = 0.1
        dt = 0.01
        effects = ["contact"]
        [[body]]
        name = "a"
        shape = "cylinder"
        radius = 0.1
        half_length = 0.2
        mass = 1.0
        [[body]]
        name = "b"
        shape = "cylinder"
        radius = 0.1
        half_length = 0.1
        mass = 1.0
        position = [1, 0, 0]
        """)
    # every shape pair collides (cylinder-cylinder was the last one missing)
    from physbench.adapters.reference import scene_input
    from physbench.engine.model import build_model
    from physbench.engine.collision import TABLE, unsupported_pairs

    assert cls.unsupported_reason(sc) is None
    assert unsupported_pairs(build_model(scene_input(sc), cls.resolve_settings(sc, {}))) == []
    assert len(TABLE) == 10  # the 4 shapes' 10 unordered pairs
    res = run(sc, "reference")
    assert res.status == "ok", res.message
    with pytest.raises(ValueError):
        cls.resolve_settings(sc, {"integrator": "leapfrog"})


def test_substeps_match_smaller_dt(tmp_path):
    sc = scene_from(tmp_path, """
        [scenario]
        family = "t"
        title = "substeps"
        duration = 1.0
        dt = 0.01
        effects = ["spring"]
        [[body]]
        name = "b"
        shape = "sphere"
        radius = 0.05
        mass = 1.0
        position = [0.2, 0, 0]
        [[spring]]
        a = "world"
        b = "b"
        stiffness = 30.0
        """)
    a = engine_for(sc, {"dt": 0.01, "substeps": 4, "integrator": "semi_implicit_euler"})
    b = engine_for(sc, {"dt": 0.0025, "integrator": "semi_implicit_euler"})
    a.step(100)
    b.step(400)
    assert np.allclose(a.state.x, b.state.x, atol=1e-12) and np.allclose(a.state.v, b.state.v, atol=1e-12)
