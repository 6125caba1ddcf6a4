"""pybullet adapter: translation, conventions and physics against analytic values.

Every tolerance below is either a rounding bound (exact discrete formulas) or
a measured engine property documented where it is asserted (pybullet 3.2.7):

- head_on at default settings (Baumgarte contact correction, contact_erp
  0.08): each post-impact velocity is off by 0.0228 x the approach speed
  (0.0456 m/s of 2 m/s) for e = 0.9, 1 and 0: the correction adds
  contact_erp * depth / dt to the separating velocity.  With
  split_impulse = true the velocities are exact (< 1e-12).
- a sphere dropped 1 m onto a plane (e = 1, dt = 0.002): rebound / impact
  speed 0.736 at default settings (Bullet's speculative contacts stop the
  ball at the surface and remove gap/dt from the rebound); exactly e with
  split_impulse = true and contact_breaking_threshold = 1e-4.
- Bullet's implicit gyroscopic step on an intermediate-axis spin: world
  angular momentum drifts 0.6 % and kinetic energy falls 1.2 % in 2 s.
"""

from __future__ import annotations

import math
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pybullet")

from physbench.contract.rotation import quat_to_matrix  # noqa: E402
from physbench.adapters.materials import solve_product_values, solve_rolling_values  # noqa: E402
from physbench.adapters.pybullet import PybulletAdapter, _import_pybullet  # noqa: E402
from physbench.harness.runner import run  # noqa: E402
from physbench.contract.scene import compile_scene, load_scene  # noqa: E402
from physbench.contract.spec import validate_raw  # noqa: E402
from tests.conftest import without_effects  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
G = 9.81


def make_scene(effects, bodies, statics=(), materials=None, springs=(), duration=1.0, dt=0.001, gravity=None):
    """A Scene from an inline spec (validated exactly like a TOML file)."""
    scenario = {"family": "test", "title": "pybullet adapter test", "duration": duration, "dt": dt,
                "effects": list(effects)}
    if gravity is not None:
        scenario["gravity"] = list(gravity)
    raw = {"scenario": scenario, "body": list(bodies), "static": list(statics),
           "material": dict(materials or {}), "spring": list(springs)}
    return compile_scene(validate_raw(raw, "<test>"))


def sphere(name="ball", r=0.1, m=1.0, pos=(0, 0, 0), vel=(0, 0, 0), w=(0, 0, 0), q=(1, 0, 0, 0), **kw):
    return {"name": name, "shape": "sphere", "radius": r, "mass": m, "position": list(pos),
            "velocity": list(vel), "angular_velocity": list(w), "orientation": list(q), **kw}


def ok_run(scene, settings=None):
    res = run(scene, "pybullet", settings or {}, compute_metrics=False)
    assert res.status == "ok", res.message
    return res, res.trace.valid()


def quat_mul(a, b):
    """Hamilton product of wxyz quaternions."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def same_rotation(q1, q2, tol):
    """q and -q are the same rotation."""
    return min(np.abs(np.asarray(q1) - q2).max(), np.abs(np.asarray(q1) + q2).max()) < tol


# --------------------------------------------------------------------------
# declaration and output hygiene


def test_capabilities():
    caps = PybulletAdapter.capabilities()
    assert caps.engine == "pybullet" and caps.available
    assert caps.version == version("pybullet")
    assert caps.dimensions == 3
    assert caps.shapes == {"sphere", "box", "capsule", "cylinder"}
    assert caps.static_shapes == {"plane", "slope", "box"}
    assert {"gravity", "contact", "restitution", "friction", "gyroscopic", "spring", "damper"} <= caps.effects
    s = caps.settings
    assert s["dt"].default is None
    assert s["iterations"].default == 50 and s["substeps"].default == 0
    assert s["maximal_coordinates"].default is True and s["ccd"].default is True
    assert s["restitution_velocity_threshold"].default == 0.0
    assert s["split_impulse"].default is False


def test_import_and_run_print_nothing_subprocess(head_on_path):
    """A fresh interpreter: importing the adapter, importing pybullet (its C
    code prints 'pybullet build time: ...') and a whole run write nothing to
    stdout or stderr, so `--json` output stays clean even through a pipe."""
    code = (
        "import sys; sys.path.insert(0, sys.argv[1])\n"
        "import physbench.adapters.pybullet as m\n"
        "from physbench.contract.scene import load_scene\n"
        "from physbench.harness.runner import run\n"
        "assert m.PybulletAdapter.capabilities().available\n"
        "r = run(load_scene(sys.argv[2]), 'pybullet', compute_metrics=False)\n"
        "assert r.status == 'ok', r.message\n"
    )
    out = subprocess.run([sys.executable, "-c", code, str(ROOT), str(head_on_path)],
                         capture_output=True, timeout=120)
    assert out.returncode == 0, out.stderr.decode()
    assert out.stdout == b""
    assert out.stderr == b""


def test_build_step_close_print_nothing(capfd, head_on_path):
    _import_pybullet()
    scene = load_scene(head_on_path)
    a = PybulletAdapter()
    a.build(scene, PybulletAdapter.resolve_settings(scene))
    a.step(10)
    a.close()
    out, err = capfd.readouterr()
    assert out == "" and err == ""


# --------------------------------------------------------------------------
# the canonical collision


@pytest.mark.parametrize("variant", [None, "elastic", "plastic"])
def test_head_on_newton_restitution(head_on_path, variant):
    scene = load_scene(head_on_path, variant=variant)
    m1, m2 = scene.masses
    e = scene.pair(scene.bodies[0].material, scene.bodies[1].material).restitution
    v1, v2 = scene.bodies[0].velocity[0], scene.bodies[1].velocity[0]
    v1p = ((m1 - e * m2) * v1 + (1 + e) * m2 * v2) / (m1 + m2)
    v2p = ((m2 - e * m1) * v2 + (1 + e) * m1 * v1) / (m1 + m2)
    approach = abs(v1 - v2)
    for settings, tol in (({}, 0.03), ({"split_impulse": True}, 1e-12)):
        res, tr = ok_run(scene, settings)
        got = tr.vel[-1, :, 0]
        err = float(np.abs(got - [v1p, v2p]).max() / approach)
        print(f"head_on[{variant}] {settings or 'defaults'}: post-impact velocities {got}, "
              f"Newton {v1p:.6g} {v2p:.6g}, error {err:.4g} of the approach speed")
        # defaults: measured 0.0228 (Baumgarte: contact_erp * depth / dt of
        # separating velocity added); split impulse: exact.
        assert err <= tol
        # momentum is exact either way: contact impulses are equal and opposite
        P = tr.vel[:, :, :] * scene.masses[None, :, None]
        P = P.sum(axis=1)
        assert np.abs(P - P[0]).max() <= 1e-12 * abs(P[0, 0])
        # the motion stays on the line of centres
        assert np.abs(tr.pos[:, :, 1:] - tr.pos[0, :, 1:]).max() < 1e-12


# --------------------------------------------------------------------------
# integration and hidden effects


def test_free_fall_semi_implicit_euler():
    """Velocity first, then position: z_n = z0 - g dt^2 n (n + 1) / 2 exactly;
    with k substeps the same formula with dt/k and n k substeps."""
    dt, z0 = 0.01, 2.0
    scene = make_scene(["gravity"], [sphere(pos=(0, 0, z0))], duration=0.5, dt=dt)
    for sub in (0, 4):
        _, tr = ok_run(scene, {"substeps": sub})
        k = max(sub, 1)
        h = dt / k
        n = np.arange(len(tr.t)) * k
        z_exact = z0 - G * h * h * n * (n + 1) / 2
        assert np.abs(tr.pos[:, 0, 2] - z_exact).max() < 1e-12
        assert np.abs(tr.vel[:, 0, 2] + G * h * n).max() < 1e-12
        # and against the continuous motion: the first-order offset g dt t / 2
        t = tr.t
        assert np.abs(tr.pos[:, 0, 2] - (z0 - G * t * t / 2) + G * h * t / 2).max() < 1e-12


def test_no_hidden_damping_speed_cap_or_sleeping():
    """Maximal coordinates: 150 m/s in zero gravity stays 150 m/s (no 100 m/s
    cap, no 0.04 damping); a slow body never falls asleep."""
    scene = make_scene([], [sphere("fast", vel=(150, 0, 0), w=(0, 0, 30)),
                            sphere("slow", pos=(0, 5, 0), vel=(0.05, 0, 0), w=(0.1, 0, 0))],
                       duration=3.0, dt=0.01)
    _, tr = ok_run(scene)
    assert np.abs(tr.vel[:, 0] - [150, 0, 0]).max() < 1e-9
    assert np.abs(tr.angvel[:, 0] - [0, 0, 30]).max() < 1e-9
    assert np.abs(tr.vel[:, 1] - [0.05, 0, 0]).max() < 1e-12
    assert abs(tr.pos[-1, 1, 0] - 0.05 * 3.0) < 1e-9
    # The btMultiBody alternative caps the speed at 100 m/s at the first step
    # (the adapter sets its damping to 0) ...
    res, tr = ok_run(scene, {"maximal_coordinates": False})
    assert abs(tr.vel[1, 0, 0] - 100.0) < 1e-9
    assert any("100 m/s" in n for n in res.notes)
    # ... and left to pybullet's defaults it also damps (0.04): raw engine check.
    p = _import_pybullet()
    cid = p.connect(p.DIRECT)
    try:
        p.setPhysicsEngineParameter(fixedTimeStep=0.01, physicsClientId=cid)
        s = p.createCollisionShape(p.GEOM_SPHERE, radius=0.1, physicsClientId=cid)
        b = p.createMultiBody(1.0, s, -1, [0, 0, 0], physicsClientId=cid)
        p.resetBaseVelocity(b, [50, 0, 0], [0, 0, 0], physicsClientId=cid)
        for _ in range(100):
            p.stepSimulation(physicsClientId=cid)
        v = p.getBaseVelocity(b, physicsClientId=cid)[0][0]
    finally:
        p.disconnect(physicsClientId=cid)
    assert v < 0.97 * 50  # exp(-0.04 * 1 s) ~ 0.961


# --------------------------------------------------------------------------
# conventions: quaternion order and frames


def test_quaternion_order_round_trip():
    q0 = np.array([0.8, 0.2, -0.4, 0.4])
    q0 /= np.linalg.norm(q0)
    box = {"name": "box", "shape": "box", "half_extents": [0.3, 0.2, 0.1], "mass": 2.0,
           "position": [1, 2, 3], "orientation": q0.tolist()}
    scene = make_scene(["gyroscopic"], [box], duration=0.1, dt=0.01)
    _, tr = ok_run(scene)
    # at t = 0 and while it does not turn, the read quaternion is the spec's wxyz
    for f in range(len(tr.t)):
        assert same_rotation(tr.quat[f, 0], q0, 1e-12)
        assert np.allclose(tr.pos[f, 0], [1, 2, 3], atol=1e-12)


def test_world_frame_angular_velocity_and_orientation_update():
    """A sphere turned 90 degrees about x spins about world z: the angular
    velocity reads (0, 0, 5) in every frame (a body-frame reading would be
    (0, 5, 0)) and the orientation is q(t) = rot_z(5 t) * q0."""
    q0 = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    scene = make_scene([], [sphere(q=q0, w=(0, 0, 5))], duration=0.2, dt=0.001)
    _, tr = ok_run(scene)
    assert np.abs(tr.angvel[:, 0] - [0, 0, 5]).max() < 1e-12
    for f in range(0, len(tr.t), 20):
        a = 5.0 * tr.t[f]
        qz = np.array([math.cos(a / 2), 0, 0, math.sin(a / 2)])
        assert same_rotation(tr.quat[f, 0], quat_mul(qz, q0), 1e-9)
    # the body's own z axis (world -y at t = 0) turns about world z
    R = quat_to_matrix(tr.quat[-1, 0])
    a = 5.0 * tr.t[-1]
    assert np.allclose(R[:, 2], [math.sin(a), -math.cos(a), 0.0], atol=1e-9)


# --------------------------------------------------------------------------
# effects switched off where absent


def test_no_contact_means_no_collision(head_on_path):
    scene = without_effects(load_scene(head_on_path), "contact", "restitution")
    res, tr = ok_run(scene)
    assert res.stages["collision_detection"] is False
    assert res.stages["gravity"] is False
    # the balls pass through each other at their initial velocities
    assert np.abs(tr.vel[:, :, :] - tr.vel[0]).max() == 0.0
    assert tr.pos[-1, 0, 0] > tr.pos[0, 1, 0] + 0.5
    assert res.stages["steps"] == scene.n_steps


def test_absent_friction_and_restitution_are_zero():
    scene = without_effects(
        make_scene(["gravity", "contact", "restitution", "friction"], [sphere(pos=(0, 0, 0.1), vel=(1, 0, 0))],
                   statics=[{"shape": "plane", "normal": [0, 0, 1], "material": "rough"}],
                   materials={"rough": {"restitution": 0.8, "friction": 0.7}}, duration=0.5),
        "restitution", "friction")
    res, tr = ok_run(scene)
    assert set(res.info["per_object_friction"].values()) == {0.0}
    assert set(res.info["per_object_restitution"].values()) == {0.0}
    # a frictionless ball slides without spinning up
    assert np.abs(tr.vel[:, 0, 0] - 1.0).max() < 1e-9
    assert np.abs(tr.angvel[:, 0]).max() < 1e-9


def test_gyroscopic_unsupported_only_where_the_term_acts():
    """Bullet's gyroscopic term cannot be switched off.  Without the effect,
    a body with unequal moments is fine while w x I w is provably zero, and
    unsupported as soon as it can turn about a non-principal axis."""
    box = {"name": "box", "shape": "box", "half_extents": [0.3, 0.2, 0.05], "mass": 1.0,
           "angular_velocity": [0.1, 10.0, 0.1]}
    plane = [{"shape": "plane", "normal": [0, 0, 1], "offset": -1.0}]

    def status(effects, body, statics=(), springs=()):
        sc = make_scene(effects, [body], statics, springs=springs, duration=0.01)
        res = run(sc, "pybullet", compute_metrics=False)
        return res.status, res.message

    st, msg = status([], box)  # spins about a non-principal axis
    assert st == "unsupported" and "gyroscopic" in msg and "non-principal" in msg
    assert status([], dict(box, angular_velocity=[0, 10.0, 0]))[0] == "ok"  # principal axis, torque-free
    assert status([], dict(box, angular_velocity=[0, 0, 0]))[0] == "ok"
    st, msg = status(["contact"], dict(box, angular_velocity=[0, 0, 0]), plane)
    assert st == "unsupported" and "contacts" in msg
    st, msg = status(["spring"], dict(box, angular_velocity=[0, 0, 0]),
                     springs=[{"a": "world", "b": "box", "anchor_b": [0.3, 0, 0], "stiffness": 1.0}])
    assert st == "unsupported" and "spring" in msg
    # a cube (equal moments) needs no gyroscopic term
    cube = dict(box, half_extents=[0.1, 0.1, 0.1])
    assert status(["contact"], cube, plane)[0] == "ok"
    # planar scenes: every body turns about its principal y axis
    planar = {"scenario": {"family": "test", "title": "t", "duration": 0.01, "dt": 0.001, "planar": True,
                           "effects": ["gravity", "contact", "friction"]},
              "body": [dict(box, position=[0, 0, 0.05], angular_velocity=[0, 1.0, 0])],
              "static": [{"shape": "plane", "normal": [0, 0, 1]}]}
    assert run(compile_scene(validate_raw(planar, "<test>")), "pybullet", compute_metrics=False).status == "ok"


def test_gyroscopic_term_acts_when_listed():
    """With the effect listed, Bullet's implicit gyroscopic term turns an
    intermediate-axis spin (w changes) while keeping the world angular
    momentum and not creating energy."""
    box = {"name": "box", "shape": "box", "half_extents": [0.3, 0.2, 0.05], "mass": 1.0,
           "angular_velocity": [0.1, 10.0, 0.1]}
    scene = make_scene(["gyroscopic"], [box], duration=2.0, dt=0.001)
    _, tr = ok_run(scene)
    I = scene.bodies[0].inertia
    R = quat_to_matrix(tr.quat)[:, 0]
    w = tr.angvel[:, 0]
    L = np.einsum("fij,j,fkj,fk->fi", R, I, R, w)
    E = 0.5 * np.einsum("fi,fi->f", w, L)
    dL = np.linalg.norm(L - L[0], axis=1).max() / np.linalg.norm(L[0])
    print(f"intermediate-axis spin, 2 s: |w - w0| max {np.abs(w - w[0]).max():.3g} rad/s, "
          f"L drift {dL:.3g}, energy change {E[-1] / E[0] - 1:.3g}")
    assert np.abs(w - w[0]).max() > 0.05
    assert dL < 0.02  # measured 0.006
    assert E.max() <= E[0] * (1 + 1e-9)


# --------------------------------------------------------------------------
# materials


def test_product_solver_uniform_general_and_zero():
    x, err, _ = solve_product_values(3, [(0, 1, 0.81), (0, 2, 0.81), (1, 2, 0.81)])
    assert np.allclose(x, 0.9, rtol=0, atol=1e-15) and err == 0.0
    # general: x0 x1 = .5, x0 x2 = .2, x1 x2 = .4  ->  (.5, 1, .4)
    x, err, _ = solve_product_values(3, [(0, 1, 0.5), (0, 2, 0.2), (1, 2, 0.4)])
    assert np.allclose(x, [0.5, 1.0, 0.4], rtol=1e-12) and err < 1e-12
    # zero pairs: object 0 wants 0 with everyone -> 0; the others sqrt(.36)
    x, err, _ = solve_product_values(4, [(0, 1, 0.0), (0, 2, 0.0), (1, 2, 0.36)])
    assert x[0] == 0.0 and np.allclose(x[1:3], 0.6, rtol=1e-12) and x[3] == 0.0 and err < 1e-12
    # infeasible: a zero pair between two objects that need positive values
    x, err, worst = solve_product_values(3, [(0, 1, 0.0), (0, 2, 0.5), (1, 2, 0.5)])
    assert err > 1e-3 and worst[:3] == (0, 1, 0.0)
    # infeasible cycle: x0 x1 = x2 x3 = 1 and x1 x2 = x3 x0 = 0.25 contradict
    _, err, _ = solve_product_values(4, [(0, 1, 1.0), (1, 2, 0.25), (2, 3, 1.0), (3, 0, 0.25), (0, 2, 1.0)])
    assert err > 1e-3
    # rolling: r_a f_b + r_b f_a = R
    f = np.array([0.5, 1.0, 0.4])
    r, err, _ = solve_rolling_values(f, [(0, 1, 0.01), (0, 2, 0.004), (1, 2, 0.006)])
    assert err < 1e-9
    assert np.all(r >= 0)


def test_mixed_materials_realised_or_reported():
    plane = {"shape": "plane", "normal": [0, 0, 1]}
    # 'rubber' against default: feasible, each pair gets exactly its value
    bodies = [sphere("a", pos=(0, 0, 0.1), material="rubber"), sphere("b", pos=(1, 0, 0.1))]
    mats = {"default": {"restitution": 0.5, "friction": 0.3},
            "rubber": {"restitution": 0.8, "friction": 0.9, "static_friction": 1.1}}
    scene = make_scene(["gravity", "contact", "restitution", "friction"], bodies, [plane], mats, duration=0.01)
    res, _ = ok_run(scene)
    e, f = res.info["per_object_restitution"], res.info["per_object_friction"]
    assert math.isclose(e["a"] * e["static_0"], 0.8) and math.isclose(e["a"] * e["b"], 0.8)
    assert math.isclose(e["b"] * e["static_0"], 0.5)
    assert math.isclose(f["a"] * f["static_0"], 0.9) and math.isclose(f["b"] * f["static_0"], 0.3)
    assert res.info["material_residual"] < 1e-9
    assert any("static friction" in n for n in res.notes)
    # two rubber balls and a default ball on a default plane: rubber|rubber
    # and rubber|default want 0.8, default|default 0.5 -> no per-object values
    bodies.append(sphere("c", pos=(2, 0, 0.1), material="rubber"))
    scene = without_effects(make_scene(["gravity", "contact", "restitution", "friction"], bodies, [plane], mats,
                                       duration=0.01), "friction")
    res, _ = ok_run(scene)
    print("infeasible restitution residual:", res.info["material_residual"])
    assert res.info["material_residual"] > 1e-3
    assert any("cannot realise" in n and "restitution" in n for n in res.notes)


def test_bounce_on_plane():
    """A 1 m drop (r 0.1 m, m 1 kg, e = 1).  Defaults: Bullet's speculative
    contacts never create energy but lose rebound speed (measured 0.736 at
    dt 0.002).  split_impulse + contact_breaking_threshold 1e-4: the rebound
    speed is exactly e times the impact speed."""
    for e, dt in ((1.0, 0.002), (0.5, 0.001)):
        scene = make_scene(["gravity", "contact", "restitution"], [sphere(pos=(0, 0, 1.1))],
                           statics=[{"shape": "plane", "normal": [0, 0, 1]}],
                           materials={"default": {"restitution": e}}, duration=0.6, dt=dt)
        for settings, exact in (({}, False), ({"split_impulse": True, "contact_breaking_threshold": 1e-4}, True)):
            _, tr = ok_run(scene, settings)
            vz = tr.vel[:, 0, 2]
            k = int(np.argmax(vz > 0))
            assert k > 0
            ratio = -vz[k] / vz[k - 1]
            print(f"bounce e={e} dt={dt} {settings or 'defaults'}: rebound/impact speed {ratio:.4f}")
            if exact:
                assert abs(ratio - e) < 1e-9
            else:
                assert 0.0 <= ratio <= e + 1e-9


# --------------------------------------------------------------------------
# shapes and statics


def test_slope_orientation_frictionless_slide():
    """A frictionless sphere on a 30 degree slope accelerates at g sin(a)
    downhill (+x) and stays on the surface."""
    a = math.radians(30.0)
    n = np.array([math.sin(a), 0.0, math.cos(a)])
    down = np.array([math.cos(a), 0.0, -math.sin(a)])
    scene = make_scene(["gravity", "contact"], [sphere(pos=n * 0.1)],
                       statics=[{"shape": "slope", "angle": 30.0}], duration=0.5, dt=0.002)
    _, tr = ok_run(scene)
    speed = tr.vel[:, 0] @ down
    acc = np.polyfit(tr.t, speed, 1)[0]
    assert abs(acc - G * math.sin(a)) < 1e-9
    assert np.abs(tr.pos[:, 0] @ n - 0.1).max() < 1e-4  # measured 1e-5 (linear slop)
    assert np.abs(tr.angvel).max() < 1e-9


@pytest.mark.parametrize("shape", ["box", "capsule", "cylinder"])
def test_shapes_rest_on_plane_at_their_size(shape):
    """Each shape settles on a plane at its geometric half-height (capsule and
    cylinder stand on their local z axis): checks dimensions and axis."""
    dims = {"box": {"half_extents": [0.2, 0.1, 0.05]},
            "capsule": {"radius": 0.05, "half_length": 0.1},
            "cylinder": {"radius": 0.1, "half_length": 0.05}}[shape]
    half_height = {"box": 0.05, "capsule": 0.15, "cylinder": 0.05}[shape]
    body = {"name": "b", "shape": shape, "mass": 1.0, "position": [0, 0, half_height + 0.01], **dims}
    scene = make_scene(["gravity", "contact", "gyroscopic"], [body],
                       statics=[{"shape": "plane", "normal": [0, 0, 1]}], duration=0.5, dt=0.002)
    res, tr = ok_run(scene)
    assert abs(tr.pos[-1, 0, 2] - half_height) < 1e-3
    # mass and exact principal inertia reached the engine (both must be
    # passed together to changeDynamics, see the adapter)
    a = PybulletAdapter()
    a.build(scene, PybulletAdapter.resolve_settings(scene))
    try:
        info = a._p.getDynamicsInfo(a._ids[0], -1, physicsClientId=a._cid)
    finally:
        a.close()
    assert info[0] == 1.0
    assert np.allclose(info[2], scene.bodies[0].inertia, rtol=1e-12)


def test_ccd_stops_tunnelling():
    """A 5 cm sphere at 200 m/s against a 1 cm wall, dt 0.002 (0.4 m a step)."""
    scene = make_scene(["contact"], [sphere(r=0.05, pos=(-0.5, 0, 0), vel=(200, 0, 0))],
                       statics=[{"shape": "box", "half_extents": [0.005, 1, 1], "position": [0, 0, 0]}],
                       duration=0.05, dt=0.002)
    _, tr = ok_run(scene, {"ccd": False})
    assert tr.pos[-1, 0, 0] > 1.0  # tunnelled
    res, tr = ok_run(scene)  # CCD is on by default
    assert tr.pos[:, 0, 0].max() < 0.0 and res.stages["ccd"] is True


@pytest.mark.parametrize("f", [1.0, 0.5, 0.1])
def test_ccd_radius_sets_the_overlap_at_the_catch(f):
    """The sweep stops the body where its swept sphere (f x the smallest
    half-size) touches the wall, so the body itself overlaps the wall by
    (1 - f) r: none with the default f = 1 (measured exactly so)."""
    r = 0.05
    scene = make_scene(["contact"], [sphere(r=r, pos=(-0.5, 0, 0), vel=(200, 0, 0))],
                       statics=[{"shape": "box", "half_extents": [0.005, 1, 1], "position": [0, 0, 0]}],
                       duration=0.05, dt=0.002)
    settings = None if f == 1.0 else {"ccd_radius": f}
    _, tr = ok_run(scene, settings)
    overlap = tr.pos[:, 0, 0].max() + r - (-0.005)
    print(f"f = {f}: overlap {overlap:.6f} m")
    assert overlap == pytest.approx((1.0 - f) * r, abs=1e-3 * r)


@pytest.mark.parametrize("allowed, dt, tunnels", [
    (None, 1 / 240, True),    # 2.6 cm per step < 4 cm: the sweep is ignored, the plate falls through
    (None, 1 / 120, False),   # 5.2 cm per step > 4 cm: caught
    (0.001, 1 / 240, False),  # caught at any dt
    (0.001, 1 / 30, False),
])
def test_ccd_allowed_penetration_decides_whether_the_sweep_acts(allowed, dt, tunnels):
    """Bullet's CCD ignores a swept-sphere hit unless the step would carry
    the body more than allowedCcdPenetration (pybullet default 0.04 m) into
    the surface: the 2 mm plate of tunnelling.thin_box_on_thin_floor,
    arriving at 6.3 m/s, is caught at 1/120 s and not at 1/240 s (the
    adapter's default), and at every dt with 1 mm (measured; the phase of
    the steps decides the uncaught case, 0.88 of phases tunnel at 1/240 s,
    and this phase is one of them)."""
    from physbench.harness.references import get_model
    scene = load_scene("tunnelling.thin_box_on_thin_floor", None, {"scenario.dt": dt})
    settings = {} if allowed is None else {"ccd_allowed_penetration": allowed}
    res, tr = ok_run(scene, settings)
    tunnelled = get_model("no_tunnelling")(scene).metrics(tr)["tunnelled"]
    assert tunnelled == (1.0 if tunnels else 0.0)
    params = res.info["engine_parameters"]
    assert params["allowedCcdPenetration"] == (0.04 if allowed is None else allowed)


# --------------------------------------------------------------------------
# external forces: springs, dampers, drag, rolling friction


def test_spring_damper_match_the_symplectic_euler_recurrence():
    """Forces are computed from the state at the start of each step:
    v+ = v + dt (-k x - c v) / m,  x+ = x + dt v+  (the engine's own order)."""
    k, c, m, dt = 40.0, 0.8, 0.5, 0.001
    for effects, damping in ((["spring"], 0.0), (["spring", "damper"], c)):
        scene = make_scene(effects, [sphere(m=m, pos=(0.3, 0, 0))], duration=1.0, dt=dt,
                           springs=[{"a": "world", "b": "ball", "stiffness": k, "damping": damping,
                                     "rest_length": 0.0}])
        res, tr = ok_run(scene)
        x, v = 0.3, 0.0
        xs = [x]
        for _ in range(len(tr.t) - 1):
            v += dt * (-k * x - damping * v) / m
            x += dt * v
            xs.append(x)
        # rounding only (~1e-12 a step inside the engine, 2e-9 after 1000 steps)
        assert np.abs(tr.pos[:, 0, 0] - xs).max() < 1e-8
        assert res.stages["external_forces"] == ["spring"] and res.stages["force_steps"] == scene.n_steps
        # and against the continuous oscillator (first-order method): amplitude within 1 %
        w0 = math.sqrt(k / m)
        zeta = damping / (2 * math.sqrt(k * m))
        wd = w0 * math.sqrt(1 - zeta * zeta)
        t = tr.t
        exact = 0.3 * np.exp(-zeta * w0 * t) * (np.cos(wd * t) + zeta * w0 / wd * np.sin(wd * t))
        assert np.abs(tr.pos[:, 0, 0] - exact).max() < 0.01 * 0.3


def test_first_step_uses_the_exact_inertia():
    """An off-centre spring on a turned capsule: after one step from rest
    dv = F dt / m and dw = I_world^-1 (r x F) dt with I_world = R I R^T from
    the scene's inertia (Bullet keeps a stale world inertia until its first
    integration; the adapter's warm-up step refreshes it)."""
    q0 = np.array([0.9, 0.3, -0.2, 0.25])
    q0 /= np.linalg.norm(q0)
    # a capsule: Bullet's own capsule inertia (a box approximation) differs
    # from the exact one, so a stale world inertia would show
    box = {"name": "box", "shape": "capsule", "radius": 0.1, "half_length": 0.3, "mass": 2.0,
           "orientation": q0.tolist()}
    anchor_b = np.array([0.05, 0.05, 0.3])
    anchor_w = np.array([1.0, 1.0, 1.0])
    k, dt = 10.0, 0.001
    scene = make_scene(["spring", "gyroscopic"], [box], duration=dt, dt=dt,
                       springs=[{"a": "box", "b": "world", "anchor_a": anchor_b.tolist(),
                                 "anchor_b": anchor_w.tolist(), "stiffness": k}])
    _, tr = ok_run(scene)
    R = quat_to_matrix(q0)
    r = R @ anchor_b
    F = k * (anchor_w - r)
    I_world = R @ np.diag(scene.bodies[0].inertia) @ R.T
    dv = F * dt / 2.0
    dw = np.linalg.solve(I_world, np.cross(r, F)) * dt
    assert np.abs(tr.vel[1, 0] - dv).max() < 1e-12 * np.abs(dv).max()
    assert np.abs(tr.angvel[1, 0] - dw).max() < 1e-9 * np.abs(dw).max()


def test_linear_and_quadratic_drag():
    """Linear drag is Bullet's own linearDamping d = 1 - e^(-c / m): the
    velocity decays exactly as e^(-c t / m); quadratic drag (Bullet has
    none) is the external force law, one explicit step each, and the row
    says so."""
    from physbench.adapters.forces import DRAG_EXTERNAL

    m, dt = 2.0, 0.01
    for effect, key, c in (("drag_linear", "drag_linear", 0.5), ("drag_quadratic", "drag_quadratic", 0.3)):
        scene = make_scene([effect], [sphere(m=m, vel=(3, 0, 4), **{key: c})], duration=1.0, dt=dt)
        res, tr = ok_run(scene)
        v = np.array([3.0, 0.0, 4.0])
        if effect == "drag_linear":
            assert res.info["drag"].startswith("Bullet's linearDamping")
            assert not any(DRAG_EXTERNAL in n for n in res.notes)
            np.testing.assert_allclose(tr.vel[:, 0], np.outer(np.exp(-c * tr.t / m), v), rtol=1e-12, atol=1e-14)
            continue
        assert res.info["drag"].startswith(DRAG_EXTERNAL) and any(DRAG_EXTERNAL in n for n in res.notes)
        for f in range(1, len(tr.t)):
            v = v - dt * c * np.linalg.norm(v) * v / m
            assert np.allclose(tr.vel[f, 0], v, rtol=1e-12, atol=1e-14)
    # btMultiBody bases damp by another law: their linear drag is the force law
    scene = make_scene(["drag_linear"], [sphere(m=m, vel=(3, 0, 4), drag_linear=0.5)], duration=0.1, dt=dt)
    res, _ = ok_run(scene, {"maximal_coordinates": False})
    assert res.info["drag"].startswith(DRAG_EXTERNAL)


def test_rolling_friction_deceleration():
    """Rolling resistance as a lever arm mu_r (m): torque mu_r N on a rolling
    sphere gives a = (5/7) mu_r g / r (Bullet: r_a f_b + r_b f_a per pair)."""
    r, mur = 0.1, 0.01
    scene = make_scene(["gravity", "contact", "friction", "rolling_friction"],
                       [sphere(r=r, pos=(0, 0, r), vel=(2, 0, 0), w=(0, 2 / r, 0))],
                       statics=[{"shape": "plane", "normal": [0, 0, 1]}],
                       materials={"default": {"friction": 0.5, "rolling_friction": mur}}, duration=1.0, dt=0.002)
    res, tr = ok_run(scene)
    acc = np.polyfit(tr.t[10:], tr.vel[10:, 0, 0], 1)[0]
    assert abs(acc + 5 / 7 * mur * G / r) < 1e-9
    assert np.allclose(tr.angvel[:, 0, 1] * r, tr.vel[:, 0, 0], atol=1e-9)  # rolls without slipping
    assert res.info["material_residual"] < 1e-9
