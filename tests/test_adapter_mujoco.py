"""MuJoCo adapter: model building, the state conversion point, effect
switching, material pairs, restitution calibration, springs, drag, settings.

Every expected value is analytic (Newton's law of restitution, free fall,
torque-free rotation, harmonic oscillators, drag ODEs) or the scene's own
request (the material's e); tolerances are stated with the figure measured on
mujoco 4.0.0 at the default settings.
"""

from __future__ import annotations

import math
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from physbench.adapters import get_adapter  # noqa: E402
from physbench.contract.rotation import body_to_world_angvel, quat_to_matrix  # noqa: E402
from physbench.adapters.mujoco import MujocoAdapter  # noqa: E402
from physbench.adapters.mujoco_calibration import ZERO_TOL, calibrate  # noqa: E402
from physbench.harness.runner import run  # noqa: E402
from physbench.contract.scene import compile_scene, load_scene  # noqa: E402
from physbench.contract.spec import validate_raw  # noqa: E402
from tests.conftest import without_effects  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
G = 9.81
PLANE = {"shape": "plane", "normal": [0.0, 0.0, 1.0], "offset": 0.0}


def scene(effects, body, static=(), material=None, spring=(), duration=1.0, dt=0.001, planar=False, **sc):
    raw = {"scenario": {"family": "mujoco", "title": "t", "duration": duration, "dt": dt,
                        "effects": list(effects), "planar": planar, **sc},
           "body": list(body), "static": list(static)}
    if material:
        raw["material"] = material
    if spring:
        raw["spring"] = list(spring)
    return compile_scene(validate_raw(raw, "<mujoco test>"))


def go(s, **settings):
    r = run(s, "mujoco", settings or None, compute_metrics=False)
    assert r.status == "ok", r.message
    return r, r.trace.valid()


def built(s, **settings):
    a = MujocoAdapter()
    a.build(s, MujocoAdapter.resolve_settings(s, settings or None))
    return a


def axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return np.r_[math.cos(angle / 2), math.sin(angle / 2) * axis]


def bounce_ratio(tr, radius, g, i=0):
    """Separation / approach normal speed at the touching height for the first
    impact of body i on the plane z = 0 (flight converted by energy:
    v^2 + 2 g h is conserved).  0 if the body never leaves the plane."""
    h = tr.pos[:, i, 2] - radius
    vz = tr.vel[:, i, 2]
    k = int(np.argmax(h < 0))
    assert h[k] < 0, "no impact"
    v_in = math.sqrt(vz[k - 1] ** 2 + 2 * g * h[k - 1])
    for j in range(k, len(h)):
        if h[j] >= 0 and vz[j] > 0:
            return math.sqrt(vz[j] ** 2 + 2 * g * h[j]) / v_in
    return 0.0


# --------------------------------------------------------------------------
# declaration


def test_import_prints_nothing():
    out = subprocess.run([sys.executable, "-c", "import physbench.adapters.mujoco, physbench.adapters.mujoco_calibration"],
                         capture_output=True, text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr
    assert out.stdout == ""


def test_unavailable_without_mujoco():
    code = ("import sys; sys.modules['mujoco'] = None\n"
            "from physbench.adapters.mujoco import MujocoAdapter\n"
            "from physbench.contract.scene import compile_scene\n"
            "from physbench.contract.spec import validate_raw\n"
            "c = MujocoAdapter.capabilities()\n"
            "assert not c.available and 'import mujoco failed' in c.unavailable_reason, c\n"
            "s = compile_scene(validate_raw({'scenario': {'family': 'f', 'title': 't', 'duration': 1.0,"
            " 'dt': 0.01, 'effects': []}, 'body': [{'name': 'b', 'shape': 'sphere', 'radius': 0.1,"
            " 'mass': 1.0}]}, 'x'))\n"
            "print(MujocoAdapter.unsupported_reason(s))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={"PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("mujoco is not available")


def test_capabilities_and_settings():
    cls = get_adapter("mujoco")
    assert cls is MujocoAdapter
    caps = cls.capabilities()
    assert caps.available and caps.engine == "mujoco" and caps.version == mujoco.__version__
    assert caps.dimensions == 3
    assert caps.shapes == {"sphere", "box", "capsule", "cylinder"}
    assert caps.static_shapes == {"plane", "slope", "box"}
    assert {"gravity", "contact", "restitution", "friction", "rolling_friction", "spring", "damper",
            "drag_linear", "drag_quadratic", "gyroscopic", "joint"} == caps.effects
    assert caps.joint_kinds == {"revolute", "spherical", "prismatic", "fixed"}
    st = caps.settings
    assert st["integrator"].default == "implicitfast" and set(st["integrator"].choices) == {
        "euler", "rk4", "implicit", "implicitfast"}
    assert st["cone"].default == "elliptic" and set(st["cone"].choices) == {"pyramidal", "elliptic"}
    assert st["impratio"].default == 1.0 and st["noslip_iterations"].default == 0
    assert st["iterations"].default == 100 and st["speculative"].default is False
    s = scene([], [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0}], dt=0.004)
    assert cls.resolve_settings(s)["dt"] == 0.004
    for bad in ({"integrator": "verlet"}, {"cone": "round"}, {"impratio": 0.5}, {"noslip_iterations": -1},
                {"iterations": 2.5}, {"solver": "cg"}):
        with pytest.raises(ValueError):
            cls.resolve_settings(s, bad)


def test_settings_reach_the_model():
    s = scene([], [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0}], dt=0.003)
    a = built(s, integrator="rk4", cone="pyramidal", impratio=10, noslip_iterations=7, iterations=33,
              speculative=True)
    o = a.m.opt
    assert o.timestep == 0.003
    assert o.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert o.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    assert (o.impratio, o.noslip_iterations, o.iterations) == (10.0, 7, 33)
    assert o.enableflags & int(mujoco.mjtEnableBit.mjENBL_SPECULATIVE)
    assert a.stages()["integrator"] == "rk4" and a.stages()["speculative"] is True
    d = built(s).m.opt
    assert d.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST and d.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert not d.enableflags & int(mujoco.mjtEnableBit.mjENBL_SPECULATIVE)


# --------------------------------------------------------------------------
# the model


def test_mass_inertia_and_shapes_are_exact():
    q = axis_angle([1, 2, 3], 0.4)
    s = scene([], [
        {"name": "s", "shape": "sphere", "radius": 0.1, "mass": 1.5},
        {"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.1], "density": 700.0, "orientation": list(q)},
        {"name": "c", "shape": "capsule", "radius": 0.05, "half_length": 0.2, "mass": 2.0},
        {"name": "y", "shape": "cylinder", "radius": 0.07, "half_length": 0.15, "mass": 3.0}])
    a = built(s)
    m = a.m
    assert np.array_equal(m.body_mass[1:], s.masses)
    assert np.array_equal(m.body_inertia[1:], s.inertias)
    assert np.allclose(m.body_iquat[1:], [1, 0, 0, 0], atol=0) and np.allclose(m.body_ipos[1:], 0, atol=0)
    types = [mujoco.mjtGeom(t).name for t in m.geom_type]
    assert types == ["mjGEOM_SPHERE", "mjGEOM_BOX", "mjGEOM_CAPSULE", "mjGEOM_CYLINDER"]
    assert m.geom_size[0, 0] == 0.1
    assert np.array_equal(m.geom_size[1], [0.3, 0.2, 0.1])
    assert np.array_equal(m.geom_size[2, :2], [0.05, 0.2])   # capsule: radius, half length
    assert np.array_equal(m.geom_size[3, :2], [0.07, 0.15])
    pos, quat, vel, w = (np.zeros((4, 3)), np.zeros((4, 4)), np.zeros((4, 3)), np.zeros((4, 3)))
    a.read_state(pos, quat, vel, w)
    assert np.allclose(quat[1], q, atol=1e-15)


@pytest.mark.parametrize("shape,dims,rest_z", [
    ("box", {"half_extents": [0.1, 0.2, 0.05]}, 0.05),
    ("capsule", {"radius": 0.05, "half_length": 0.1}, 0.15),     # standing on its axis (body z)
    ("cylinder", {"radius": 0.05, "half_length": 0.1}, 0.1),
    ("sphere", {"radius": 0.1}, 0.1),
])
def test_shapes_rest_on_the_plane(shape, dims, rest_z):
    # 'gyroscopic' listed: with contact, MuJoCo's always-on term could act on
    # the non-spherical shapes, so a scene without it is unsupported
    s = scene(["gravity", "contact", "friction", "gyroscopic"],
              [{"name": "b", "shape": shape, "mass": 1.0, "position": [0, 0, rest_z + 0.05], "material": "m", **dims}],
              [PLANE], material={"m": {"friction": 0.5}}, duration=1.0)
    _, tr = go(s)
    # soft contacts sag: 1 kg resting on K = (pi / (10 dt))^2 -> ~0.1 mm
    assert tr.pos[-1, 0, 2] == pytest.approx(rest_z, abs=5e-4)
    assert np.abs(tr.vel[-1, 0]).max() < 1e-3


def test_tilted_plane_and_static_box():
    n = np.array([0.6, 0.0, 0.8])
    s = scene(["gravity", "contact"], [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0,
                                          "position": list(n * 0.8)}],
              [{"shape": "plane", "normal": list(n), "offset": 0.5}], duration=0.5)
    _, tr = go(s)
    dist = tr.pos[:, 0] @ n - 0.5           # centre height above the plane
    assert dist.min() > 0.1 - 2e-3           # never far through the plane
    assert dist[-1] == pytest.approx(0.1, abs=1e-3)
    # frictionless slide: along-plane acceleration g sin(a), sin a = 0.6
    along = np.array([0.8, 0.0, -0.6])
    k = len(tr.t) // 2
    assert np.polyfit(tr.t[k:], tr.vel[k:, 0] @ along, 1)[0] == pytest.approx(G * 0.6, rel=2e-3)
    s = scene(["gravity", "contact"], [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0,
                                          "position": [0.2, 0.1, 1.0]}],
              [{"shape": "box", "half_extents": [0.5, 0.5, 0.2], "position": [0.0, 0.0, 0.3]}], duration=1.0)
    _, tr = go(s)
    assert tr.pos[-1, 0, 2] == pytest.approx(0.6, abs=1e-3)


# --------------------------------------------------------------------------
# the conversion point


def test_free_fall_is_semi_implicit_euler():
    s = scene(["gravity"], [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0,
                              "position": [0, 0, 10.0], "velocity": [1.0, 0.5, 2.0]}], duration=1.0)
    for integ in ("implicitfast", "euler"):
        _, tr = go(s, integrator=integ)
        k = np.arange(len(tr.t))
        t = tr.t
        # within the first-order bound of the exact parabola ...
        exact = 10 + 2.0 * t - 0.5 * G * t**2
        assert np.abs(tr.pos[:, 0, 2] - exact).max() <= 0.5 * G * s.dt * t[-1] * (1 + 1e-9)
        # ... and exactly MuJoCo's velocity-first Euler: z_k = z0 + v0 t - g dt^2 k (k + 1) / 2
        assert np.allclose(tr.pos[:, 0, 2], 10 + 2.0 * t - G * s.dt**2 * k * (k + 1) / 2, atol=1e-10)
        assert np.allclose(tr.vel[:, 0, 2], 2.0 - G * t, atol=1e-10)
        assert np.allclose(tr.pos[:, 0, :2], np.outer(t, [1.0, 0.5]), atol=1e-12)
    _, tr = go(s, integrator="rk4")          # RK4 is exact on a parabola
    assert np.abs(tr.pos[:, 0, 2] - (10 + 2.0 * tr.t - 0.5 * G * tr.t**2)).max() < 1e-9


def test_sphere_world_angular_velocity_is_constant():
    # equal principal inertia: torque-free rotation keeps the world w fixed; a
    # body-frame reading would swing around as the sphere turns.
    w = np.array([1.0, -2.0, 3.0])
    q0 = axis_angle([0.3, 1.0, -0.2], 1.3)
    s = scene([], [{"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0, "orientation": list(q0),
                    "angular_velocity": list(w)}], duration=1.0)
    _, tr = go(s)
    assert np.abs(tr.angvel[:, 0] - w).max() < 1e-12
    # the orientation advances about the fixed world axis: q(t) = exp(w t / 2) q0
    T = tr.t[-1]
    qw = axis_angle(w, np.linalg.norm(w) * T)
    expect = np.r_[qw[0] * q0[0] - qw[1:] @ q0[1:], qw[0] * q0[1:] + q0[0] * qw[1:] + np.cross(qw[1:], q0[1:])]
    assert abs(abs(tr.quat[-1, 0] @ expect) - 1) < 1e-9


def test_box_tumbling_conserves_world_angular_momentum():
    # unequal inertia, w off the principal axes, gyroscopic effect on.  World
    # L = R I R^T w is constant only if w is read in the right frame.
    q0 = axis_angle([1, 0, 0], math.pi / 5)
    w0 = np.array([0.5, 4.0, 1.0])
    s = scene(["gyroscopic"], [{"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.1], "mass": 1.0,
                                 "orientation": list(q0), "angular_velocity": list(w0)}], duration=2.0)
    inertia = s.inertias[0]

    def momentum(tr):
        R = quat_to_matrix(tr.quat[:, 0])
        wb = np.einsum("fji,fj->fi", R, tr.angvel[:, 0])        # R^T w
        L = np.einsum("fij,fj->fi", R, inertia * wb)
        E = 0.5 * np.einsum("fi,fi->f", wb, inertia * wb)
        return L, E

    _, tr = go(s, integrator="rk4")
    assert np.allclose(tr.angvel[0, 0], w0, atol=1e-12)
    L, E = momentum(tr)
    drift = np.abs(L - L[0]).max() / np.linalg.norm(L[0])
    print(f"rk4: |dL|/|L| = {drift:.2e}, dE/E = {np.abs(E / E[0] - 1).max():.2e}")
    assert drift < 1e-6 and np.abs(E / E[0] - 1).max() < 1e-6
    _, tr = go(s)                                                # implicitfast: dissipative
    L, E = momentum(tr)
    print(f"implicitfast: |dL|/|L| = {np.abs(L - L[0]).max() / np.linalg.norm(L[0]):.2e}, "
          f"dE/E = {(E / E[0] - 1).min():.2e}")
    assert np.abs(L - L[0]).max() / np.linalg.norm(L[0]) < 0.05


def test_read_state_matches_conventions_and_does_not_allocate():
    s = scene(["gyroscopic"], [{"name": "b", "shape": "box", "half_extents": [0.3, 0.2, 0.1], "mass": 1.0,
                                 "orientation": list(axis_angle([1, 1, 0], 0.3)),
                                 "angular_velocity": [0.5, 4.0, 1.0]},
                                {"name": "c", "shape": "capsule", "radius": 0.05, "half_length": 0.2, "mass": 1.0,
                                 "angular_velocity": [2.0, -1.0, 0.3], "velocity": [1, 2, 3]}])
    a = built(s)
    a.step(137)
    pos, quat, vel, w = (np.zeros((2, 3)), np.zeros((2, 4)), np.zeros((2, 3)), np.zeros((2, 3)))
    a.read_state(pos, quat, vel, w)
    qpos, qvel = a.d.qpos.reshape(2, 7), a.d.qvel.reshape(2, 6)
    assert np.array_equal(pos, qpos[:, :3]) and np.array_equal(quat, qpos[:, 3:])
    assert np.array_equal(vel, qvel[:, :3])
    assert np.allclose(w, body_to_world_angvel(qpos[:, 3:], qvel[:, 3:]), atol=1e-14)
    tracemalloc.start()
    for _ in range(200):
        a.read_state(pos, quat, vel, w)
        a.step(1)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 4096, f"read_state/step allocated {peak} bytes"


@pytest.mark.parametrize("body,ok", [
    ({"shape": "box", "half_extents": [0.3, 0.2, 0.1], "angular_velocity": [0.5, 4.0, 1.0]}, False),
    ({"shape": "box", "half_extents": [0.3, 0.2, 0.1], "angular_velocity": [0.0, 4.0, 0.0]}, True),  # principal
    ({"shape": "sphere", "radius": 0.1, "angular_velocity": [0.5, 4.0, 1.0]}, True),                 # equal I
    ({"shape": "box", "half_extents": [0.3, 0.2, 0.1]}, True),                                         # at rest
])
def test_gyroscopic_cannot_be_switched_off(body, ok):
    s = scene([], [{"name": "b", "mass": 1.0, **body}])
    r = run(s, "mujoco", compute_metrics=False)
    if ok:
        assert r.status == "ok", r.message
    else:
        assert r.status == "unsupported" and "gyroscopic" in r.message and "'b'" in r.message


# --------------------------------------------------------------------------
# head-on collision: Newton's law of restitution


@pytest.mark.parametrize("variant,e,tol", [
    # measured |v' - v'_Newton| at default settings (mujoco 4.0.0):
    # e 0.9: 8.4e-4 m/s; elastic: 8.3e-4 m/s; plastic: 3.5e-3 m/s (e = 0 is
    # calibrated to a bounce <= 0.005: a one-sided spring-damper never stops dead)
    (None, 0.9, 2e-3), ("elastic", 1.0, 2e-3), ("plastic", 0.0, 6e-3)])
def test_head_on(head_on_path, variant, e, tol):
    s = load_scene(head_on_path, variant=variant)
    r, tr = go(s)
    m1, m2 = s.masses
    (v1, v2) = s.bodies[0].velocity[0], s.bodies[1].velocity[0]
    v1p = ((m1 - e * m2) * v1 + (1 + e) * m2 * v2) / (m1 + m2)
    v2p = ((m2 - e * m1) * v2 + (1 + e) * m1 * v1) / (m1 + m2)
    err = np.abs(tr.vel[-1, :, 0] - [v1p, v2p]).max()
    print(f"head_on {variant or 'default'} (e = {e}): v' = {tr.vel[-1, :, 0]}, Newton {v1p:.6f} {v2p:.6f}, "
          f"error {err:.2e} m/s")
    assert err <= tol
    assert np.abs(tr.vel[-1, :, 1:]).max() < 1e-12             # stays on the line
    p = tr.vel[:, :, 0] @ s.masses
    assert np.abs(p - p[0]).max() <= 1e-12 * abs(p[0])          # momentum conserved every frame
    cal = r.info["restitution_calibration"]
    assert len(cal) == 1 and cal[0]["requested"] == e and cal[0]["phase_mode"] == "scene"
    assert any("restitution" in n for n in r.notes)
    assert r.stages["contact"] and r.stages["condim"] == 1 and r.stages["explicit_pairs"] == 0


# --------------------------------------------------------------------------
# restitution calibration


@pytest.mark.parametrize("dt", [0.001, 0.002])
@pytest.mark.parametrize("e", [0.0, 0.25, 0.5, 0.75, 0.9, 0.95])
def test_restitution_bounce_ratio(e, dt):
    r_ball = 0.05
    s = scene(["gravity", "contact", "restitution"],
              [{"name": "b", "shape": "sphere", "radius": r_ball, "mass": 0.2, "material": "ball",
                "position": [0.0, 0.0, 1.0 + r_ball]}], [PLANE],
              material={"ball": {"restitution": e}}, duration=0.75, dt=dt)
    r, tr = go(s)
    ratio = bounce_ratio(tr, r_ball, G)
    cal = r.info["restitution_calibration"][0]
    print(f"e {e} dt {dt}: bounce {ratio:.4f} (calibration {cal['achieved']:.4f}, solref {cal['solref']}, "
          f"phase spread {cal['phase_spread']}, penetration {cal['penetration'] * 1e3:.1f} mm)")
    if e == 0.0:
        assert ratio <= 0.02
    else:
        assert ratio == pytest.approx(e, rel=0.02)
    assert abs(cal["residual"]) <= max(0.002 * e, ZERO_TOL)


@pytest.mark.parametrize("e", [0.5, 0.9])
def test_restitution_phase_averaged(e):
    # calibrated to the mean over step phases: the scene's own impact lands
    # somewhere inside the reported scatter
    s = scene(["gravity", "contact", "restitution"],
              [{"name": "b", "shape": "sphere", "radius": 0.05, "mass": 0.2, "material": "ball",
                "position": [0.0, 0.0, 1.05]}], [PLANE], material={"ball": {"restitution": e}}, duration=0.75)
    r, tr = go(s, restitution_phase="averaged")
    cal = r.info["restitution_calibration"][0]
    assert cal["phase_mode"] == "averaged" and cal["achieved"] == pytest.approx(e, rel=2e-3)
    ratio = bounce_ratio(tr, 0.05, G)
    print(f"e {e}, averaged calibration: this impact {ratio:.4f}, spread {cal['phase_spread']}")
    assert cal["phase_spread"][0] - 0.005 <= ratio <= cal["phase_spread"][1] + 0.005


@pytest.mark.parametrize("gravity", [0.0, G])
@pytest.mark.parametrize("e", [0.0, 0.3, 0.8])
def test_calibration_without_scene_phase(e, gravity):
    # averaged over four impact phases at a given impact speed
    c = calibrate(e, 0.001, 3.0, gravity)
    assert c.phase_mode == "averaged"
    assert c.achieved == pytest.approx(e, abs=max(0.002 * e, ZERO_TOL))
    assert c.phase_spread[0] <= c.achieved + 1e-12 and c.achieved <= c.phase_spread[1] + 1e-12
    assert c.solref[0] < 0 and c.solref[1] <= 0            # direct form
    assert calibrate(e, 0.001, 3.0, gravity) is c           # cached


def test_no_restitution_effect_means_no_bounce():
    s = without_effects(scene(["gravity", "contact", "restitution"],
                              [{"name": "b", "shape": "sphere", "radius": 0.05, "mass": 0.2,
                                "material": "ball", "position": [0, 0, 0.55]}], [PLANE],
                              material={"ball": {"restitution": 0.9}}, duration=0.6), "restitution")
    r, tr = go(s)
    assert bounce_ratio(tr, 0.05, G) <= 0.02
    assert r.info["restitution_calibration"][0]["requested"] == 0.0
    assert any("inelastic" in n for n in r.notes)


def test_mixed_materials_use_explicit_pairs():
    # each ball bounces with its own material's e off the plane; the two balls
    # also collide (an approaching pair, e of the named material)
    s = scene(["gravity", "contact", "restitution"], [
        {"name": "a", "shape": "sphere", "radius": 0.05, "mass": 0.2, "position": [0, 0, 1.05], "material": "bouncy"},
        {"name": "b", "shape": "sphere", "radius": 0.05, "mass": 0.2, "position": [1.0, 0, 1.05]},
    ], [PLANE], material={"bouncy": {"restitution": 0.8}, "default": {"restitution": 0.3}}, duration=0.7)
    r, tr = go(s)
    assert r.stages["explicit_pairs"] >= 1 and r.stages["dynamic_contacts"]
    assert bounce_ratio(tr, 0.05, G, 0) == pytest.approx(0.8, rel=0.02)
    assert bounce_ratio(tr, 0.05, G, 1) == pytest.approx(0.3, rel=0.02)
    # two balls meeting in flight (no plane): the pair value is the named material's
    s = scene(["contact", "restitution"], [
        {"name": "a", "shape": "sphere", "radius": 0.05, "mass": 0.2, "velocity": [1.0, 0, 0], "material": "bouncy"},
        {"name": "b", "shape": "sphere", "radius": 0.05, "mass": 0.6, "position": [0.3, 0, 0]},
        {"name": "c", "shape": "sphere", "radius": 0.05, "mass": 0.2, "position": [0, 1.0, 0]},
    ], material={"bouncy": {"restitution": 0.6}, "default": {"restitution": 0.2}}, duration=0.5)
    r, tr = go(s)
    m1, m2, e = 0.2, 0.6, 0.6
    v1p, v2p = (m1 - e * m2) / (m1 + m2), (1 + e) * m1 / (m1 + m2)
    assert np.abs(tr.vel[-1, :2, 0] - [v1p, v2p]).max() < 2e-3
    a = built(s)
    assert a.m.npair == r.stages["explicit_pairs"] >= 1


# --------------------------------------------------------------------------
# effect switching


def test_absent_gravity_and_contact_are_switched_off():
    s = scene([], [
        {"name": "a", "shape": "sphere", "radius": 0.1, "mass": 1.0, "position": [0, 0, 1.0], "velocity": [2, 0, 0]},
        {"name": "b", "shape": "sphere", "radius": 0.1, "mass": 1.0, "position": [1, 0, 1.0], "velocity": [-2, 0, 0]},
    ], [PLANE], duration=0.5)
    r, tr = go(s)
    a = built(s)
    assert a.m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_GRAVITY)
    assert a.m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    assert not r.stages["gravity"] and not r.stages["contact"] and r.stages["explicit_pairs"] == 0
    assert np.all(tr.pos[:, :, 2] == 1.0)                           # no fall
    assert np.array_equal(tr.vel[-1, :, 0], [2.0, -2.0])           # passed through each other
    assert tr.pos[-1, 0, 0] > tr.pos[-1, 1, 0]
    a.step(300)
    assert a.d.ncon == 0


def test_friction_switches_condim():
    body = [{"name": "b", "shape": "box", "half_extents": [0.1, 0.1, 0.1], "mass": 1.0, "position": [0, 0, 0.1],
             "material": "m"}]
    mat = {"m": {"friction": 0.5, "static_friction": 0.7, "rolling_friction": 0.01}}
    full = scene(["gravity", "contact", "friction", "rolling_friction"], body, [PLANE], material=mat)
    a = built(without_effects(full, "friction", "rolling_friction"))
    assert set(a.m.geom_condim) == {1}
    a = built(without_effects(full, "rolling_friction"))
    assert set(a.m.geom_condim) == {3} and np.allclose(a.m.geom_friction[:, 0], 0.5)
    assert any("static_friction" in n for n in a.notes)
    a = built(scene(["gravity", "contact", "friction", "rolling_friction"], body, [PLANE], material=mat))
    assert set(a.m.geom_condim) == {6} and np.allclose(a.m.geom_friction[:, 2], 0.01)


def test_rolling_friction_slows_a_rolling_ball():
    # rolling resistance torque mu_r N on a ball rolling without slip:
    # (I/r + m r) dw/dt = -mu_r m g  ->  dv/dt = -mu_r g / (r (1 + 2/5))
    r_b, mu_r, v0 = 0.1, 0.005, 1.0
    s = scene(["gravity", "contact", "friction", "rolling_friction"],
              [{"name": "b", "shape": "sphere", "radius": r_b, "mass": 1.0, "position": [0, 0, r_b],
                "velocity": [v0, 0, 0], "angular_velocity": [0, v0 / r_b, 0], "material": "m"}],
              [PLANE], material={"m": {"friction": 0.5, "rolling_friction": mu_r}}, duration=1.0)
    _, tr = go(s)
    k = len(tr.t) // 4
    a = np.polyfit(tr.t[k:], tr.vel[k:, 0, 0], 1)[0]
    print(f"rolling deceleration {a:.5f}, analytic {-mu_r * G / (r_b * 1.4):.5f}")
    assert a == pytest.approx(-mu_r * G / (r_b * 1.4), rel=0.05)


def test_speculative_contacts_stop_tunnelling():
    # ENGINE_NOTES: a 0.05 m sphere at 200 m/s tunnels through a 0.01 m wall at dt 0.002
    s = scene(["contact"], [{"name": "b", "shape": "sphere", "radius": 0.05, "mass": 0.1,
                             "position": [-0.5, 0, 0], "velocity": [200.0, 0, 0]}],
              [{"shape": "box", "half_extents": [0.005, 1.0, 1.0], "position": [0, 0, 0]}],
              duration=0.02, dt=0.002)
    _, tr = go(s)
    assert tr.pos[-1, 0, 0] > 0.5                    # went through
    _, tr = go(s, speculative=True)
    assert tr.pos[:, 0, 0].max() < 0.0               # stopped on the near side


# --------------------------------------------------------------------------
# springs, dampers, drag


def _two_masses(k, c, effects):
    return scene(effects, [{"name": "a", "shape": "sphere", "radius": 0.05, "mass": 1.0},
                           {"name": "b", "shape": "sphere", "radius": 0.05, "mass": 2.0, "position": [1.1, 0, 0]}],
                 spring=[{"a": "a", "b": "b", "stiffness": k, "rest_length": 1.0, "damping": c}], duration=3.0)


def test_spring_period_and_damper_decay():
    mu = 2.0 / 3.0
    r, tr = go(_two_masses(50.0, 0.0, ["spring"]))
    assert r.stages["tendon_springs"] == 1
    x = tr.pos[:, 1, 0] - tr.pos[:, 0, 0] - 1.0
    down = np.where((x[:-1] > 0) & (x[1:] <= 0))[0]
    period = np.diff(tr.t[down]).mean()
    print(f"spring period {period:.5f}, analytic {2 * math.pi * math.sqrt(mu / 50):.5f}")
    assert period == pytest.approx(2 * math.pi * math.sqrt(mu / 50.0), rel=2e-3)
    assert np.abs(tr.vel[:, :, 0] @ [1.0, 2.0]).max() < 1e-12      # internal force: momentum 0
    _, tr = go(_two_masses(50.0, 2.0, ["spring", "damper"]))
    x = tr.pos[:, 1, 0] - tr.pos[:, 0, 0] - 1.0
    peaks = [i for i in range(1, len(x) - 1) if x[i] > 0 and x[i] > x[i - 1] and x[i] >= x[i + 1]]
    rate = -np.polyfit(tr.t[peaks], np.log(x[peaks]), 1)[0]
    assert rate == pytest.approx(2.0 / (2 * mu), rel=5e-3)


def test_spring_to_world_equilibrium():
    s = scene(["gravity", "spring", "damper"], [{"name": "a", "shape": "sphere", "radius": 0.05, "mass": 1.0,
                                                  "position": [0, 0, -1.0]}],
              spring=[{"a": "world", "b": "a", "anchor_a": [0, 0, 0], "stiffness": 100.0, "rest_length": 1.0,
                       "damping": 5.0}], duration=5.0)
    _, tr = go(s)
    assert tr.pos[-1, 0, 2] == pytest.approx(-1.0 - G / 100.0, abs=1e-5)


def test_drag():
    m, c, v0 = 2.0, 0.5, 3.0
    s = scene(["drag_linear"], [{"name": "a", "shape": "sphere", "radius": 0.05, "mass": m,
                                  "velocity": [v0, 0, 0], "drag_linear": c}], duration=2.0)
    r, tr = go(s)
    assert r.stages["drag"]
    # MuJoCo's fluid model under implicitfast: first order in dt, c dt / (2 m) * c t / m ~ 1.3e-4 at t = 2 s
    assert np.allclose(tr.vel[:, 0, 0], v0 * np.exp(-c * tr.t / m), rtol=2e-4)
    s = scene(["drag_quadratic"], [{"name": "a", "shape": "sphere", "radius": 0.05, "mass": m,
                                     "velocity": [v0, 0, 0], "drag_quadratic": c}], duration=2.0)
    _, tr = go(s)
    # first order in dt: relative error below 5e-4 at t = 2 s
    assert np.allclose(tr.vel[:, 0, 0], v0 / (1 + c * v0 * tr.t / m), rtol=5e-4)
    # terminal velocity under gravity: sqrt(m g / c)
    s = scene(["gravity", "drag_quadratic"], [{"name": "a", "shape": "sphere", "radius": 0.05, "mass": m,
                                                "drag_quadratic": c}], duration=3.0)
    _, tr = go(s)
    assert tr.vel[-1, 0, 2] == pytest.approx(-math.sqrt(m * G / c), rel=1e-3)
    assert not go(scene([], [{"name": "a", "shape": "sphere", "radius": 0.05, "mass": m}]))[0].stages["drag"]


def test_drag_uses_the_fluid_model_where_it_can():
    """Drag on a sphere that does not spin is MuJoCo's own ellipsoid fluid
    model, calibrated (viscosity c1 / (6 pi r), density 1, blunt drag
    c2 / (pi r^2), other coefficients 0): integrated with RK4 the fall
    against c1 + c2 |v| matches the closed forms to round-off (an external
    force held over each step could not: first order in dt).  A box has no
    isotropic fluid drag in MuJoCo: its drag is the external force law, and
    the row says so."""
    from physbench.adapters.forces import DRAG_EXTERNAL

    m, r = 0.1, 0.05
    s = scene(["gravity", "drag_quadratic"], [{"name": "a", "shape": "sphere", "radius": r, "mass": m,
                                                "drag_quadratic": 0.01}], duration=2.0)
    a = built(s, integrator="rk4")
    assert 'fluidshape="ellipsoid"' in a.xml and a.info["drag"].startswith("MuJoCo's ellipsoid fluid model")
    assert not any(DRAG_EXTERNAL in n for n in a.notes)
    res, tr = go(s, integrator="rk4")
    assert res.stages["drag"] == "fluid"
    vt = math.sqrt(m * G / 0.01)
    np.testing.assert_allclose(tr.vel[:, 0, 2], -vt * np.tanh(G * tr.t / vt), rtol=0, atol=1e-10 * vt)
    # linear, thrown sideways: v = vt + (v0 - vt) e^(-c t / m) per component
    s = scene(["gravity", "drag_linear"], [{"name": "a", "shape": "sphere", "radius": r, "mass": m,
                                             "velocity": [3.0, 0, 0], "drag_linear": 0.2}], duration=2.0)
    _, tr = go(s, integrator="rk4")
    e = np.exp(-0.2 * tr.t / m)
    np.testing.assert_allclose(tr.vel[:, 0, 0], 3.0 * e, rtol=0, atol=1e-10)
    np.testing.assert_allclose(tr.vel[:, 0, 2], -m * G / 0.2 * (1 - e), rtol=0, atol=1e-10)
    box = scene(["gravity", "drag_quadratic"], [{"name": "a", "shape": "box", "half_extents": [0.05, 0.05, 0.05],
                                                  "mass": m, "drag_quadratic": 0.01}], duration=0.1)
    a = built(box)
    assert "fluidshape" not in a.xml
    assert a.info["drag"].startswith(DRAG_EXTERNAL) and any(n.startswith(DRAG_EXTERNAL) for n in a.notes)


def test_planar_scene_stays_planar():
    # planar scenes run in 3D; symmetric contacts keep them in the x-z plane
    s = scene(["gravity", "contact", "friction", "restitution"], [
        {"name": "b", "shape": "box", "half_extents": [0.1, 0.05, 0.08], "mass": 1.0, "position": [0, 0, 0.5],
         "velocity": [1.0, 0, 0], "angular_velocity": [0, 3.0, 0], "material": "m"}],
        [{"shape": "slope", "angle": 10.0}], material={"m": {"friction": 0.4, "restitution": 0.5}},
        planar=True, duration=1.0)
    _, tr = go(s)
    assert np.abs(tr.pos[:, 0, 1]).max() < 1e-9
    assert np.abs(tr.angvel[:, 0, [0, 2]]).max() < 1e-9


def test_python_step_loop_equals_c_loop():
    """bare_loop() (the overhead benchmark's baseline: mj_step(m, d) in a
    Python loop) and step(n) (mj_step(m, d, n), looping in C) reach the same
    state bit for bit on a contact-rich scene."""
    s = scene(["gravity", "contact", "friction"],
              [{"name": "box", "shape": "box", "half_extents": [0.1, 0.1, 0.1], "mass": 1.0,
                "position": [0.0, 0.0, 0.1], "pattern": {"kind": "column", "count": 4}}],
              static=[PLANE], material={"default": {"friction": 0.5, "static_friction": 0.5}})
    a, b = built(s), built(s)
    a.step(300)
    b.bare_loop(300)
    assert a.steps == b.steps == 300
    np.testing.assert_array_equal(a.d.qpos, b.d.qpos)
    np.testing.assert_array_equal(a.d.qvel, b.d.qvel)
    a.close()
    b.close()


def test_parallel_cylinders_touch_on_one_point_at_an_end():
    """Measured for stacking.log_pile's xfails: MuJoCo 4.0.0 gives a pair
    of parallel cylinders lying side by side one contact (its convex
    collider's; multi-contact is on by default but not for cylinders), at
    one end of their 30 cm line, and the end it picks changes from step to
    step -- the top log of the pile pitches and the pile collapses.  A
    MuJoCo whose cylinder pairs hold a line contact would fail this test
    and show the pile's checks as unexpected passes."""
    sc = load_scene("stacking.log_pile")
    a = MujocoAdapter()
    a.build(sc, MujocoAdapter.resolve_settings(sc, {}))
    m, d = a.m, a.d
    ends, seen = set(), 0
    for _ in range(8):
        mujoco.mj_step(m, d)
        mujoco.mj_forward(m, d)
        by_pair: dict = {}
        for c in d.contact[:d.ncon]:
            b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
            if b1 and b2:  # log on log (body 0 is the world)
                by_pair.setdefault((min(b1, b2), max(b1, b2)), []).append(c.pos.copy())
        if not by_pair:  # the first step: the logs rest at 0 gap
            continue
        seen += 1
        assert len(by_pair) == 2
        for pts in by_pair.values():
            assert len(pts) == 1
            assert abs(abs(pts[0][1]) - 0.15) < 2e-3
            ends.add(float(np.sign(pts[0][1])))
    assert seen >= 6
    assert ends == {-1.0, 1.0}
