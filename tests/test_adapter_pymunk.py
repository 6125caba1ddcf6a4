"""Tests of the pymunk adapter (adapters/pymunk.py) against analytic physics.

Every expected value is derived from the scene (masses, radii, e, mu, g) and
from the integration scheme pymunk documents (positions first with the old
velocity, then velocities); nothing is compared with a recorded snapshot.
Tolerances are stated next to the value they bound, with the measured figure.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pymunk = pytest.importorskip("pymunk")

from physbench.contract.rotation import quat_to_matrix  # noqa: E402
from physbench.adapters.pymunk import GYROSCOPIC_REASON, PymunkAdapter  # noqa: E402
from physbench.harness.runner import run  # noqa: E402
from physbench.contract.scene import load_scene  # noqa: E402

G = 9.81

# head_on_path (tests/conftest.py): the canonical examples/head_on.toml.


def scene_from(tmp_path: Path, text: str, overrides: dict | None = None):
    p = tmp_path / "scene.toml"
    p.write_text(text, encoding="utf-8")
    return load_scene(p, None, overrides)


def run_ok(scene, settings=None):
    r = run(scene, "pymunk", settings, compute_metrics=False)
    assert r.status == "ok", r.message
    return r, r.trace.valid()


# ---------------------------------------------------------------------------
# declaration


def test_capabilities():
    caps = PymunkAdapter.capabilities()
    assert caps.available, caps.unavailable_reason
    assert caps.engine == "pymunk"
    assert caps.version == pymunk.version
    assert caps.dimensions == 2
    assert caps.shapes == {"sphere", "box", "capsule", "cylinder"}
    assert caps.static_shapes == {"plane", "slope", "box"}
    assert {"gravity", "contact", "restitution", "friction", "spring", "damper",
            "drag_linear", "drag_quadratic"} <= caps.effects
    assert "gyroscopic" not in caps.effects and "rolling_friction" not in caps.effects
    s = caps.settings
    assert s["collision_slop"].default == 1e-3  # metres, not pymunk's 0.1
    assert s["substeps"].default == 1 and s["iterations"].default == 10
    assert s["collision_bias"].default == pytest.approx(0.9**60)


def test_settings_are_validated(head_on_path):
    sc = load_scene(head_on_path)
    res = PymunkAdapter.resolve_settings(sc, {"substeps": "3", "collision_slop": 1e-4})
    assert res["substeps"] == 3 and res["collision_slop"] == 1e-4 and res["dt"] == sc.dt
    for bad in ({"substeps": 0}, {"collision_slop": -1.0}, {"iterations": 1.5}, {"bogus": 1}):
        with pytest.raises(ValueError):
            PymunkAdapter.resolve_settings(sc, bad)


# ---------------------------------------------------------------------------
# head-on collision (Newton's law and momentum: tests/test_closed_forms.py)


@pytest.mark.parametrize("variant", [None, "elastic", "plastic"])
def test_head_on_overlap_within_one_step(head_on_path, variant):
    """No speculative contacts: the overlap when the contact is first found
    is at most one step of closing, |u1 - u2| dt (measured 1.15 mm of 2 mm).
    (Newton's law and momentum: tests/test_closed_forms.py::test_head_on_newton.)"""
    sc = load_scene(head_on_path, variant)
    _, tr = run_ok(sc)
    u1, u2 = sc.bodies[0].velocity[0], sc.bodies[1].velocity[0]
    r_sum = sc.bodies[0].radius + sc.bodies[1].radius
    overlap = r_sum - (tr.pos[:, 1, 0] - tr.pos[:, 0, 0])
    print(f"head_on[{variant}]: max overlap {overlap.max() * 1e3:.3f} mm")
    assert 0.0 < overlap.max() <= abs(u1 - u2) * sc.dt + 1e-12


def test_head_on_without_contact_passes_through(head_on_path):
    from tests.conftest import without_effects

    sc = without_effects(load_scene(head_on_path), "contact", "restitution")
    r, tr = run_ok(sc)
    assert r.stages["contact"] is False and r.stages["material_mode"] == "none"
    t = tr.t[-1]
    np.testing.assert_allclose(tr.pos[-1, :, 0], [2.0 * t, 0.3], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(tr.vel[-1, :, 0], [2.0, 0.0])
    a = PymunkAdapter()
    a.build(sc, PymunkAdapter.resolve_settings(sc))
    assert len(a._space.shapes) == 0  # no collision stage at all
    a.close()


# ---------------------------------------------------------------------------
# unsupported scenes


def test_non_planar_is_unsupported(head_on_path):
    sc = load_scene(head_on_path, None, {"scenario.planar": False})
    r = run(sc, "pymunk", compute_metrics=False)
    assert r.status == "unsupported"
    assert "2D" in r.message and "planar" in r.message


@pytest.mark.parametrize("effect,reason", [("gyroscopic", GYROSCOPIC_REASON),
                                           ("rolling_friction", "rolling")])
def test_effects_without_a_2d_counterpart_are_unsupported(head_on_path, effect, reason):
    sc = load_scene(head_on_path, None, {"scenario.effects": ["contact", "restitution", effect]})
    r = run(sc, "pymunk", compute_metrics=False)
    assert r.status == "unsupported"
    assert reason in r.message


BALL_ON_GROUND = """
[scenario]
family = "test"
title = "ball"
duration = 0.1
dt = 0.001
planar = true
effects = ["gravity", "contact"]

[[body]]
name = "ball"
shape = "sphere"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 0.1]

[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]
"""


def test_geometry_off_the_plane_is_unsupported(tmp_path):
    grid = BALL_ON_GROUND.replace('position = [0.0, 0.0, 0.1]',
                                  'position = [0.0, 0.0, 0.1]\npattern = { kind = "grid", counts = [1, 2, 1] }')
    r = run(scene_from(tmp_path, grid), "pymunk", compute_metrics=False)
    assert r.status == "unsupported" and "off the x-z plane" in r.message
    box = BALL_ON_GROUND + """
[[static]]
shape = "box"
half_extents = [1.0, 0.1, 1.0]
position = [0.0, 0.5, 0.0]
"""
    r = run(scene_from(tmp_path, box), "pymunk", compute_metrics=False)
    assert r.status == "unsupported" and "does not cross" in r.message


# ---------------------------------------------------------------------------
# the planar mapping, end to end

FREE = """
[scenario]
family = "test"
title = "free body"
duration = 0.5
dt = 0.01
planar = true
effects = []

[[body]]
name = "plate"
shape = "box"
half_extents = [0.3, 0.1, 0.05]
mass = 2.0
position = [0.1, 0.0, 0.2]
orientation = [0.9238795325112867, 0.0, 0.3826834323650898, 0.0]
velocity = [0.3, 0.0, -0.2]
angular_velocity = [0.0, 1.7, 0.0]
"""


def test_planar_mapping_round_trip_and_rotation_sign(tmp_path):
    sc = scene_from(tmp_path, FREE)
    _, tr = run_ok(sc)
    t = tr.t
    # velocities read back unchanged (world frame, y component zero)
    np.testing.assert_array_equal(tr.vel[:, 0], np.tile([0.3, 0.0, -0.2], (len(t), 1)))
    np.testing.assert_array_equal(tr.angvel[:, 0], np.tile([0.0, 1.7, 0.0], (len(t), 1)))
    np.testing.assert_allclose(tr.pos[:, 0], np.array([0.1, 0.0, 0.2]) + np.outer(t, [0.3, 0.0, -0.2]),
                               rtol=0, atol=1e-12)
    # orientation: the initial 45 degrees about +y plus wy * t about +y
    theta = math.pi / 4 + 1.7 * t
    q_exp = np.stack([np.cos(theta / 2), 0 * t, np.sin(theta / 2), 0 * t], axis=1)
    err = np.minimum(np.abs(tr.quat[:, 0] - q_exp).max(1), np.abs(tr.quat[:, 0] + q_exp).max(1))
    assert err.max() <= 1e-12
    # right-hand rule: turning about +y by theta takes body x to (cos, 0, -sin)
    R = quat_to_matrix(tr.quat[:, 0])
    np.testing.assert_allclose(R[:, :, 0], np.stack([np.cos(theta), 0 * t, -np.sin(theta)], 1), atol=1e-12)


SPIN = """
[scenario]
family = "test"
title = "spinning ball set down"
duration = 1.0
dt = 0.001
planar = true
effects = ["gravity", "contact", "friction"]

[material.default]
friction = 0.3

[[body]]
name = "ball"
shape = "sphere"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 0.1]
angular_velocity = [0.0, 20.0, 0.0]

[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]
"""


def test_spin_sign_and_moment_through_friction(tmp_path):
    """A ball spinning with w_y > 0 set on a rough floor: its lowest point
    moves at w x r = (0, w, 0) x (0, 0, -r) = (-w r, 0, 0), so friction drives
    it toward +x.  Angular momentum about the contact point is conserved,
    so it ends rolling at v = I w0 r / (I + m r^2) = 2/7 w0 r for a solid
    sphere: this checks the sign of the mapping and that the pymunk moment is
    the sphere's I_yy = 2/5 m r^2 (a disc's 1/2 m r^2 would give 1/3 w0 r)."""
    sc = scene_from(tmp_path, SPIN)
    _, tr = run_ok(sc)
    r, w0 = 0.1, 20.0
    v_end = tr.vel[-1, 0, 0]
    err = abs(v_end / (2.0 / 7.0 * w0 * r) - 1.0)
    print(f"rolling speed {v_end:.12g} m/s, relative error vs 2/7 w r: {err:.3g}")
    assert err <= 1e-9  # measured 5e-15
    assert abs(v_end - tr.angvel[-1, 0, 1] * r) <= 1e-9  # rolls without slipping: v = w_y r


# ---------------------------------------------------------------------------
# integration order





# ---------------------------------------------------------------------------
# contacts: collision_slop in metres, shapes, statics, materials

DROP = """
[scenario]
family = "test"
title = "drop"
duration = 1.5
dt = 0.002
planar = true
effects = ["gravity", "contact"]

[[body]]
name = "ball"
shape = "sphere"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 0.1]
velocity = [0.0, 0.0, -2.0]

[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]
"""


@pytest.mark.parametrize("slop", [1e-3, 1e-4])
def test_collision_slop_is_in_metres(tmp_path, slop):
    """The ball lands 4 mm deep (2 m/s x 2 ms, no speculative contacts); the
    bias then removes the overlap beyond collision_slop, leaving ~slop."""
    sc = scene_from(tmp_path, DROP)
    _, tr = run_ok(sc, {"collision_slop": slop})
    pen = 0.1 - tr.pos[:, 0, 2]
    print(f"slop {slop}: landing overlap {pen.max() * 1e3:.3f} mm, resting overlap {pen[-1] * 1e3:.5f} mm")
    assert pen.max() <= 2.0 * sc.dt + 1e-12
    # measured resting overlap: 1.0002 mm (slop 1 mm), 0.1003 mm (slop 0.1 mm)
    assert slop <= pen[-1] <= 1.01 * slop


SHAPES = """
[scenario]
family = "test"
title = "shapes at rest"
duration = 0.5
dt = 0.001
planar = true
effects = ["gravity", "contact"]

[[body]]
name = "sphere"
shape = "sphere"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 0.101]

[[body]]
name = "box"
shape = "box"
half_extents = [0.2, 0.3, 0.1]
mass = 1.5
position = [1.0, 0.0, 0.101]

[[body]]
name = "box_on_end"
shape = "box"
half_extents = [0.2, 0.3, 0.1]
mass = 1.5
position = [2.0, 0.0, 0.201]
orientation = [0.7071067811865476, 0.0, 0.7071067811865476, 0.0]

[[body]]
name = "capsule_up"
shape = "capsule"
radius = 0.05
half_length = 0.2
density = 1000.0
position = [3.0, 0.0, 0.251]

[[body]]
name = "cylinder_up"
shape = "cylinder"
radius = 0.05
half_length = 0.2
density = 1000.0
position = [4.0, 0.0, 0.201]

[[body]]
name = "cylinder_lying"
shape = "cylinder"
radius = 0.05
half_length = 0.2
density = 1000.0
position = [5.0, 0.0, 0.051]
orientation = [0.7071067811865476, 0.0, 0.7071067811865476, 0.0]

[[body]]
name = "on_block"
shape = "sphere"
radius = 0.1
mass = 1.0
position = [7.0, 0.0, 0.601]

[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]

[[static]]
shape = "box"
half_extents = [0.5, 0.5, 0.25]
position = [7.0, 0.0, 0.25]
"""

# resting heights of the centres: the extent along world z after the rotation
REST_Z = [0.1, 0.1, 0.2, 0.25, 0.2, 0.05, 0.6]


def test_shapes_rest_at_their_heights_with_3d_mass_properties(tmp_path):
    """Capsule and cylinder axes are body z: upright they stand on their
    ends, turned 90 degrees about y they lie on their sides; a box turned 90
    degrees rests on its x half-extent.  Each body's pymunk mass and moment
    are the 3D mass and I_yy."""
    sc = scene_from(tmp_path, SHAPES)
    a = PymunkAdapter()
    a.build(sc, PymunkAdapter.resolve_settings(sc))
    for b, pb in zip(sc.bodies, a._bodies):
        assert pb.mass == b.mass and pb.moment == b.inertia[1], b.name
    a.close()
    _, tr = run_ok(sc)
    z = tr.pos[-1, :, 2]
    slop = PymunkAdapter.capabilities().settings["collision_slop"].default
    for name, zi, zr in zip((b.name for b in sc.bodies), z, REST_Z):
        print(f"{name}: rests at {zi:.6f} m, expected {zr} m (overlap {(zr - zi) * 1e3:.4f} mm)")
    # A 1 mm drop lands < 0.15 mm deep (below slop, never pushed out), and
    # nothing rests above its height.
    assert np.all(z <= np.array(REST_Z) + 1e-9)
    assert np.all(z >= np.array(REST_Z) - slop)
    np.testing.assert_allclose(tr.vel[-1], 0.0, atol=1e-9)
    np.testing.assert_allclose(tr.angvel[-1], 0.0, atol=1e-9)


SLOPE = """
[scenario]
family = "test"
title = "block on a slope"
duration = 0.5
dt = 0.001
planar = true
effects = ["gravity", "contact", "friction"]
max_initial_overlap = 2e-4  # 0.1 mm deep on purpose (test_slope_slide_kinetic_friction)

[material.default]
friction = 0.2
static_friction = 0.3

[[body]]
name = "block"
shape = "box"
half_extents = [0.1, 0.1, 0.1]
mass = 1.0
position = [0.04995, 0.0, 0.08651593783806542]
orientation = [0.9659258262890683, 0.0, 0.25881904510252074, 0.0]

[[static]]
shape = "slope"
angle = 30.0
"""


def test_slope_slide_kinetic_friction(tmp_path):
    """A block on a 30 degree slope (normal (sin a, 0, cos a), downhill +x)
    slides with a = g (sin a - mu cos a).  pymunk has one coefficient: the
    kinetic one is used and a note says so.

    The block starts 0.1 mm deep (its centre at 0.0999 m along the normal;
    less than collision_slop, so never pushed out) so that both corners are
    in contact from the first step.  Set exactly touching, pymunk finds no
    contact in step 1 (no speculative contacts), the block falls freely for
    one step, the friction of that step is lost, and the speed stays 0.8 mm/s
    behind a t with a transient spin (measured)."""
    sc = scene_from(tmp_path, SLOPE)
    r, tr = run_ok(sc)
    assert any("one Coulomb coefficient" in n for n in r.notes)
    a = math.radians(30.0)
    down = np.array([math.cos(a), 0.0, -math.sin(a)])
    acc = G * (math.sin(a) - 0.2 * math.cos(a))
    v_along = tr.vel[:, 0] @ down
    err = np.abs(v_along - acc * tr.t).max()
    print(f"slope: speed error vs a t: {err:.3g} m/s (a = {acc:.6f} m/s^2)")
    assert err <= 1e-9  # measured 3.4e-12
    normal = np.array([math.sin(a), 0.0, math.cos(a)])
    assert np.abs(tr.vel[:, 0] @ normal).max() <= 1e-9
    assert np.abs(tr.angvel[:, 0]).max() <= 1e-9  # slides flat, no tipping


MATERIALS = """
[scenario]
family = "test"
title = "bounces per material"
duration = 0.6
dt = 0.001
planar = true
effects = ["gravity", "contact", "restitution"]

[material.default]
restitution = 0.2

[material.rubber]
restitution = 0.8

[[body]]
name = "rubber"
shape = "sphere"
radius = 0.05
mass = 0.1
position = [0.0, 0.0, 0.3]
material = "rubber"
pattern = { kind = "row", count = 2, spacing = 1.0 }

[[body]]
name = "plain"
shape = "sphere"
radius = 0.05
mass = 0.1
position = [3.0, 0.0, 0.3]

[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]
"""


def _first_bounce_ratio(vz: np.ndarray) -> float:
    """-v_after / v_before at the first frame where v_z turns positive."""
    k = int(np.argmax(vz > 0))
    assert k > 0
    return -vz[k] / vz[k - 1]


@pytest.mark.parametrize("with_plain_ball", [False, True])
def test_pair_restitution_per_shape_or_callback(tmp_path, with_plain_ball):
    """rubber meets the default ground at e = 0.8 (named beats default); the
    default ball meets it at e = 0.2.  Without the plain ball, per-shape values
    (sqrt 0.8 each) reproduce the pairs as products; with it, rubber-rubber
    0.8, rubber-default 0.8 and default-default 0.2 admit no per-shape
    values, so the adapter sets the pair values in a pre_solve callback.
    Either way the bounce ratio equals the pair's e (position-first: the
    bounce acts on the velocity from before the step's gravity)."""
    text = MATERIALS if with_plain_ball else MATERIALS.split("[[body]]\nname = \"plain\"")[0] + \
        '[[static]]\nshape = "plane"\nnormal = [0.0, 0.0, 1.0]\n'
    sc = scene_from(tmp_path, text)
    r, tr = run_ok(sc)
    assert r.stages["material_mode"] == ("pre_solve_callback" if with_plain_ball else "per_shape")
    for i, b in enumerate(sc.bodies):
        e = sc.pair(b.material, sc.statics[0].material).restitution
        ratio = _first_bounce_ratio(tr.vel[:, i, 2])
        print(f"{b.name}: bounce ratio {ratio:.15f}, pair e {e}")
        assert ratio == pytest.approx(e, abs=1e-12)


# ---------------------------------------------------------------------------
# springs, dampers, drag

SPRING = """
[scenario]
family = "test"
title = "mass on a spring"
duration = 1.0
dt = 0.001
planar = true
effects = ["spring"]

[[body]]
name = "m"
shape = "sphere"
radius = 0.05
mass = 1.0
position = [0.6, 0.0, 0.0]

[[spring]]
a = "world"
b = "m"
stiffness = 100.0
rest_length = 0.5
"""


def test_spring_oscillation(tmp_path):
    sc = scene_from(tmp_path, SPRING)
    r, tr = run_ok(sc)
    assert r.stages["springs"] == 1
    x = tr.pos[:, 0, 0]
    v = tr.vel[:, 0, 0]
    dt, k, m, L = sc.dt, 100.0, 1.0, 0.5
    # the scheme, exactly: x' = x + v dt, then v' = v - k (x' - L) / m dt
    xs, vs = [0.6], [0.0]
    for _ in range(len(x) - 1):
        xn = xs[-1] + vs[-1] * dt
        vs.append(vs[-1] - k * (xn - L) / m * dt)
        xs.append(xn)
    np.testing.assert_allclose(x, xs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(v, vs, rtol=0, atol=1e-10)
    # and the analytic oscillator, within the scheme's first-order phase error
    w = math.sqrt(k / m)
    err = np.abs(x - (L + 0.1 * np.cos(w * tr.t))).max()
    print(f"spring: max error vs analytic {err:.3g} m (dt {dt})")
    assert err <= 0.1 * w * dt  # measured about half of this bound


DAMPER = SPRING.replace('effects = ["spring"]', 'effects = ["damper"]').replace(
    "stiffness = 100.0", "stiffness = 0.0").replace("rest_length = 0.5", "rest_length = 0.5\ndamping = 3.0").replace(
    'position = [0.6, 0.0, 0.0]', 'position = [0.6, 0.0, 0.0]\nvelocity = [1.0, 0.0, 0.0]')


def test_damper_exponential_decay(tmp_path):
    """Damper alone (no stiffness: the 'spring' effect is absent): pymunk
    decays the velocity along the line by exp(-c dt / m) each step, so
    v(t) = v0 exp(-c t / m) at every sample."""
    sc = scene_from(tmp_path, DAMPER)
    r, tr = run_ok(sc)
    assert any("damper" in n for n in r.notes)
    np.testing.assert_allclose(tr.vel[:, 0, 0], np.exp(-3.0 * tr.t), rtol=1e-12, atol=0)


DRAG = """
[scenario]
family = "test"
title = "drag"
duration = 1.0
dt = 0.001
planar = true
effects = ["drag_linear", "drag_quadratic"]

[[body]]
name = "lin"
shape = "sphere"
radius = 0.05
mass = 2.0
velocity = [3.0, 0.0, 4.0]
drag_linear = 0.5

[[body]]
name = "quad"
shape = "sphere"
radius = 0.05
mass = 2.0
position = [1.0, 0.0, 0.0]
velocity = [3.0, 0.0, 4.0]
drag_quadratic = 0.5
"""


def test_drag(tmp_path):
    sc = scene_from(tmp_path, DRAG)
    r, tr = run_ok(sc)
    assert r.stages["drag_bodies"] == 2
    dt, m, c = sc.dt, 2.0, 0.5
    k = np.round(tr.t / dt)
    # linear: explicit step v' = v (1 - c dt / m)
    speed = np.linalg.norm(tr.vel[:, 0], axis=1)
    np.testing.assert_allclose(speed, 5.0 * (1 - c * dt / m) ** k, rtol=1e-12)
    err_lin = np.abs(speed / (5.0 * np.exp(-c * tr.t / m)) - 1).max()
    # quadratic: analytic v(t) = v0 / (1 + c v0 t / m); explicit Euler error O(dt)
    speed_q = np.linalg.norm(tr.vel[:, 1], axis=1)
    err_q = np.abs(speed_q / (5.0 / (1 + c * 5.0 * tr.t / m)) - 1).max()
    print(f"drag: relative error vs analytic, linear {err_lin:.3g}, quadratic {err_q:.3g}")
    assert err_lin <= c * dt / m and err_q <= 2 * c * 5.0 * dt / m
    # the direction of motion never changes
    np.testing.assert_allclose(tr.vel[:, :, 0] / tr.vel[:, :, 2], 0.75, rtol=1e-12)


def test_linear_drag_is_pymunk_damping(tmp_path):
    """Linear drag alone, one c / m for every body: pymunk's own
    space.damping = e^(-c / m), so the speed decays exactly as e^(-c t / m)
    (the explicit force law read (1 - c dt / m)^k); with quadratic drag in
    the scene (test_drag) pymunk has no model and the row says so."""
    from physbench.adapters.forces import DRAG_EXTERNAL

    text = DRAG.replace('effects = ["drag_linear", "drag_quadratic"]', 'effects = ["drag_linear"]').replace(
        "drag_quadratic = 0.5", "drag_linear = 0.5")
    r, tr = run_ok(scene_from(tmp_path, text))
    assert r.info["drag"].startswith("pymunk's space.damping") and r.stages["drag_bodies"] == 0
    assert not any(DRAG_EXTERNAL in n for n in r.notes)
    speed = np.linalg.norm(tr.vel, axis=2)
    np.testing.assert_allclose(speed, np.repeat(5.0 * np.exp(-0.5 * tr.t / 2.0)[:, None], 2, axis=1), rtol=1e-12)
    r, _ = run_ok(scene_from(tmp_path, DRAG))
    assert r.info["drag"] == f"{DRAG_EXTERNAL} (pymunk has no quadratic drag)"


# ---------------------------------------------------------------------------
# state reads


def test_read_state_paths_agree(tmp_path):
    """The fast batched read and the public pymunk.batch fallback give the
    same arrays, and they equal the per-body pymunk properties."""
    sc = scene_from(tmp_path, SHAPES)
    a = PymunkAdapter()
    a.build(sc, PymunkAdapter.resolve_settings(sc))
    a.step(50)
    n = sc.n_bodies
    out1 = [np.full((n, 3), np.nan), np.full((n, 4), np.nan), np.full((n, 3), np.nan), np.full((n, 3), np.nan)]
    out2 = [np.full_like(x, np.nan) for x in out1]
    a.read_state(*out1)
    assert a.info["state_reader"] == "c_batch"
    a._c_each = None
    a.read_state(*out2)
    for x, y in zip(out1, out2):
        np.testing.assert_array_equal(x, y)
    for i, b in enumerate(a._bodies):
        assert tuple(out1[0][i]) == (b.position.x, 0.0, b.position.y)
        assert tuple(out1[2][i]) == (b.velocity.x, 0.0, b.velocity.y)
        assert out1[3][i][1] == -b.angular_velocity
    a.close()


def _states(a, n):
    out = [np.full((n, 3), np.nan), np.full((n, 4), np.nan), np.full((n, 3), np.nan), np.full((n, 3), np.nan)]
    a.read_state(*out)
    return out


@pytest.mark.parametrize("text", ["SHAPES", "MATERIALS"])
def test_direct_c_step_equals_space_step(tmp_path, text):
    """step() calls cpSpaceStep without pymunk's Python wrapper; bare_loop()
    calls the public space.step(dt).  The states are bit-identical, also with
    the exact-pair pre_solve callbacks (MATERIALS has a plain ball, so the
    pair values come from the callback, which must still run)."""
    sc = scene_from(tmp_path, globals()[text])
    runs = []
    for loop in ("step", "bare_loop"):
        a = PymunkAdapter()
        a.build(sc, PymunkAdapter.resolve_settings(sc))
        if loop == "step":
            assert a._c_step is not None
        getattr(a, loop)(400)
        runs.append(_states(a, sc.n_bodies))
        if text == "MATERIALS":
            assert a.stages()["material_mode"] == "pre_solve_callback"
        a.close()
    for x, y in zip(*runs):
        assert np.isfinite(x).all()
        np.testing.assert_array_equal(x, y)


def test_block_recording_keeps_frames_before_an_engine_error(tmp_path):
    """An exception in the k-th step of a block leaves the k - 1 steps before
    it recorded and converted (block_done says how many), equal to a plain
    step-and-read loop."""
    sc = scene_from(tmp_path, SHAPES)
    n = sc.n_bodies
    ref = PymunkAdapter()
    ref.build(sc, PymunkAdapter.resolve_settings(sc))
    want = []
    for _ in range(6):
        ref.step(1)
        want.append(_states(ref, n))
    ref.close()

    a = PymunkAdapter()
    a.build(sc, PymunkAdapter.resolve_settings(sc))
    real, calls = a._c_step, [0]

    def failing(space, h):
        calls[0] += 1
        if calls[0] == 7:
            raise RuntimeError("engine trouble")
        real(space, h)

    a._c_step = failing
    block = [np.full((10, n, 3), np.nan), np.full((10, n, 4), np.nan), np.full((10, n, 3), np.nan),
             np.full((10, n, 3), np.nan)]
    with pytest.raises(RuntimeError, match="engine trouble"):
        a.step_record(10, *block)
    assert a.block_done == 6
    for k in range(6):
        for got, exp in zip(block, want[k]):
            np.testing.assert_array_equal(got[k], exp)
    assert np.isnan(block[0][6:]).all()
    # the reader's buffer is home again: a plain read still works
    assert np.isfinite(_states(a, n)[0]).all()
    a.close()


# ---------------------------------------------------------------------------
# private internals (adapters/pymunk_internals.py) against the public API


def _each_arbiter_rows(a) -> np.ndarray:
    """The contact rows through pymunk's per-arbiter public API
    (Body.each_arbiter, Arbiter.contact_point_set): each arbiter once,
    point midway between point_a and point_b, normal, depth = -distance."""
    rows, seen = [], set()

    def visit(arb):
        key = tuple(sorted(id(s) for s in arb.shapes))
        if key in seen:
            return
        seen.add(key)
        cps = arb.contact_point_set
        for pt in cps.points:
            rows.append([0.5 * (pt.point_a.x + pt.point_b.x), 0.0, 0.5 * (pt.point_a.y + pt.point_b.y),
                         cps.normal.x, 0.0, cps.normal.y, -pt.distance])

    for body in a._bodies:
        body.each_arbiter(visit)
    return np.array(rows, float).reshape(-1, 7)


def _sorted_rows(c: np.ndarray) -> np.ndarray:
    return c[np.lexsort(c.T[::-1])]


@pytest.mark.parametrize("text", ["SHAPES", "MATERIALS"])
def test_batched_contacts_equal_each_arbiter(tmp_path, text):
    """contacts() reads every arbiter in one batched call; its rows equal
    the per-arbiter public API's at every step, also on the steps after a
    bounce, when the batch still holds the separated pairs' cached arbiters
    (counted here: they occur) and with the pre_solve material callbacks
    (MATERIALS, whose typed handlers may swap an arbiter's shapes).  The
    depth is the same dot product summed in another order: equal to 1e-12 m."""
    sc = scene_from(tmp_path, globals()[text])
    a = PymunkAdapter()
    a.build(sc, PymunkAdapter.resolve_settings(sc))
    af = pymunk.batch.ArbiterFields
    buf = pymunk.batch.Buffer()
    cached, touching_steps = 0, 0
    for _ in range(sc.n_steps):
        a.step(1)
        got, want = a.contacts(), _each_arbiter_rows(a)
        assert got.shape == want.shape
        np.testing.assert_allclose(_sorted_rows(got), _sorted_rows(want), rtol=0, atol=1e-12)
        touching_steps += len(want) > 0
        buf.clear()
        pymunk.batch.get_space_arbiters(a._space, af.CONTACT_COUNT, buf)
        cached += int(np.sum(np.frombuffer(buf.int_buf(), dtype=np.uintp) == 0))
    print(f"{text}: {touching_steps} steps with contacts, {cached} cached separated arbiters seen")
    assert touching_steps > 0
    if text == "MATERIALS":
        assert cached > 0  # the filter was exercised
    a.close()


@pytest.mark.parametrize("text", ["SHAPES", "MATERIALS", "DRAG"])
def test_private_paths_equal_public_paths(tmp_path, monkeypatch, text):
    """A whole run through the private paths (cpSpaceStep called directly,
    the allocation-free batch reader and its block recorder) equals a run
    through the public calls only (Space.step, pymunk.batch.get_space_bodies
    per step), bit for bit."""
    import physbench.adapters.pymunk as am

    sc = scene_from(tmp_path, globals()[text])
    fast, _ = run_ok(sc)
    assert fast.info["state_reader"] == "c_batch"

    def no_reader(*args, **kw):
        raise RuntimeError("private reader disabled")

    monkeypatch.setattr(am, "c_stepper", lambda space, bodies: None)
    monkeypatch.setattr(am, "BodyReader", no_reader)
    public, _ = run_ok(sc)
    assert public.info["state_reader"] == "public_batch"
    for name in ("pos", "quat", "vel", "angvel"):
        x, y = getattr(fast.trace.valid(), name), getattr(public.trace.valid(), name)
        assert np.isfinite(x).all()
        np.testing.assert_array_equal(x, y)
