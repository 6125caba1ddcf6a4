"""Tests of the Box2D v3 adapter (adapters/box2d.py, pyb2d3) against closed
forms.

Every expected value is computed here from the scene and from Box2D's soft
step (``substeps`` substeps per step, each velocity first).  Box2D computes
in f32: tolerances near the f32 resolution say so, with the measured figure.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pyb2d3 = pytest.importorskip("pyb2d3")

from physbench.adapters.base import module_version  # noqa: E402
from physbench.adapters.box2d import GYROSCOPIC_REASON, Box2dAdapter  # noqa: E402
from physbench.contract.scene import load_scene  # noqa: E402
from physbench.harness.runner import run  # noqa: E402

G = 9.81
F32 = 2.0 ** -23


def scene_from(tmp_path: Path, text: str, variant: str | None = None):
    p = tmp_path / "scene.toml"
    p.write_text(text, encoding="utf-8")
    return load_scene(p, variant)


def run_ok(scene, settings=None, **kw):
    r = run(scene, "box2d", settings, compute_metrics=False, **kw)
    assert r.status == "ok", r.message
    return r, r.trace.valid()


def spec(effects, bodies, statics="", duration=1.0, dt=0.001, material="", extra=""):
    return (f'[scenario]\nfamily = "test"\ntitle = "t"\nduration = {duration}\ndt = {dt}\nplanar = true\n'
            f'effects = {effects!r}\n'.replace("'", '"')
            + (f"\n[material.default]\n{material}\n" if material else "") + bodies + statics + extra)


GROUND = '\n[[static]]\nname = "ground"\nshape = "plane"\nnormal = [0.0, 0.0, 1.0]\n'


def ball(z=0.1, r=0.1, vx=0.0, vz=0.0, name="ball", x=0.0, extra=""):
    return (f'\n[[body]]\nname = "{name}"\nshape = "sphere"\nradius = {r}\nmass = 1.0\n'
            f'position = [{x}, 0.0, {z}]\nvelocity = [{vx}, 0.0, {vz}]\n{extra}')


# ---------------------------------------------------------------------------
# declaration, settings, unsupported


def test_capabilities_and_settings():
    caps = Box2dAdapter.capabilities()
    assert caps.available, caps.unavailable_reason
    assert caps.version == module_version("pyb2d3") and caps.dimensions == 2
    assert caps.shapes == {"sphere", "box", "capsule", "cylinder"}
    assert caps.static_shapes == {"plane", "slope", "box"}
    assert "rolling_friction" in caps.effects and "gyroscopic" not in caps.effects
    s = caps.settings
    wd = pyb2d3.WorldDef()  # Box2D's own defaults
    assert s["substeps"].default == 4
    assert s["contact_hertz"].default == wd.contact_hertz == 30.0
    assert s["contact_damping_ratio"].default == wd.contact_damping_ratio == 10.0
    assert s["max_linear_speed"].default == pytest.approx(wd.maximum_linear_speed)
    assert s["continuous"].default is True and s["bullets"].default is False
    # deliberately not Box2D's 1 m/s: the spec's e holds at every speed
    assert s["restitution_threshold"].default == 0.0 and wd.restitution_threshold == 1.0


def test_settings_are_validated(head_on_path):
    sc = load_scene(head_on_path)
    res = Box2dAdapter.resolve_settings(sc, {"substeps": "8", "bullets": "true"})
    assert res["substeps"] == 8 and res["bullets"] is True
    for bad in ({"substeps": 0}, {"contact_hertz": 0.0}, {"restitution_threshold": -1.0}, {"springs": "x"},
                {"bogus": 1}):
        with pytest.raises(ValueError):
            Box2dAdapter.resolve_settings(sc, bad)


def test_settings_reach_the_engine(head_on_path):
    sc = load_scene(head_on_path)
    a = Box2dAdapter()
    a.build(sc, Box2dAdapter.resolve_settings(sc, {"continuous": False, "bullets": True,
                                                   "restitution_threshold": 0.5}))
    assert a._world.continuous_enabled is False
    assert a._world.restitution_threshold == 0.5
    assert all(b.bullet for b in a._bodies)
    assert a.stages()["bullets"] is True and a.stages()["continuous"] is False
    a.close()


def test_non_planar_and_gyroscopic_are_unsupported(head_on_path):
    r = run(load_scene(head_on_path, None, {"scenario.planar": False}), "box2d", compute_metrics=False)
    assert r.status == "unsupported" and "2D" in r.message and "planar" in r.message
    sc = load_scene(head_on_path, None, {"scenario.effects": ["contact", "restitution", "gyroscopic"]})
    r = run(sc, "box2d", compute_metrics=False)
    assert r.status == "unsupported" and r.message == GYROSCOPIC_REASON


def test_geometry_off_the_plane_is_unsupported(tmp_path):
    grid = ball().replace("[0.0, 0.0, 0.1]", '[0.0, 0.0, 0.1]\npattern = { kind = "grid", counts = [1, 2, 1] }')
    text = spec(["gravity", "contact"], grid, GROUND)
    r = run(scene_from(tmp_path, text), "box2d", compute_metrics=False)
    assert r.status == "unsupported" and "off the x-z plane" in r.message


# ---------------------------------------------------------------------------
# the planar mapping (Newton's law on the canonical spec, free fall, a bounce
# at e and sliding at mu g: tests/test_closed_forms.py)


FREE = """
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


def test_planar_mapping_and_rotation_sign(tmp_path):
    """A free plate: velocities read back unchanged (f32), the orientation
    turns about +y at w_y (right-hand rule: body x goes to (cos, 0, -sin))."""
    _, tr = run_ok(scene_from(tmp_path, spec([], FREE, duration=0.5, dt=0.01)))
    t = tr.t
    np.testing.assert_allclose(tr.vel[:, 0], np.tile([0.3, 0.0, -0.2], (len(t), 1)), rtol=0, atol=4 * F32)
    np.testing.assert_allclose(tr.angvel[:, 0], np.tile([0.0, 1.7, 0.0], (len(t), 1)), rtol=0, atol=4 * F32)
    theta = math.pi / 4 + 1.7 * t
    from physbench.contract.rotation import quat_to_matrix

    R = quat_to_matrix(tr.quat[:, 0])
    np.testing.assert_allclose(R[:, :, 0], np.stack([np.cos(theta), 0 * t, -np.sin(theta)], 1), atol=1e-5)


def test_spin_sets_the_3d_moment(tmp_path):
    """A ball spinning at w_y = 20 rad/s set on a rough floor ends rolling at
    v = I w0 r / (I + m r^2) = 2/7 w0 r, the 3D sphere's I_yy = 2/5 m r^2 (a
    disc's 1/2 m r^2 would give 1/3 w0 r); the sign says the mapping is right."""
    body = ball().replace("velocity = [0.0, 0.0, 0.0]", "angular_velocity = [0.0, 20.0, 0.0]")
    _, tr = run_ok(scene_from(tmp_path, spec(["gravity", "contact", "friction"], body, GROUND, duration=1.0,
                                             material="friction = 0.3")))
    v_end = tr.vel[-1, 0, 0]
    print(f"box2d rolling speed {v_end:.6g} vs 2/7 w r {2 / 7 * 2.0:.6g}")
    assert abs(v_end / (2.0 / 7.0 * 20.0 * 0.1) - 1.0) <= 1e-3  # measured 2e-5
    # rolls: v = w_y r up to the soft friction's slip (measured 2.0e-4 m/s)
    assert abs(v_end - tr.angvel[-1, 0, 1] * 0.1) <= 5e-4


# ---------------------------------------------------------------------------
# shapes, materials, contact


SHAPES = """
[[body]]
name = "ball"
shape = "sphere"
radius = 0.1
mass = 1.0
position = [0.0, 0.0, 0.1]

[[body]]
name = "box"
shape = "box"
half_extents = [0.1, 0.15, 0.05]
mass = 2.0
position = [1.0, 0.0, 0.05]

[[body]]
name = "capsule"
shape = "capsule"
radius = 0.05
half_length = 0.2
mass = 1.0
position = [2.0, 0.0, 0.05]
orientation = [0.7071067811865476, 0.0, 0.7071067811865475, 0.0]

[[body]]
name = "cylinder"
shape = "cylinder"
radius = 0.1
half_length = 0.05
mass = 1.0
position = [3.0, 0.0, 0.05]
"""


def test_shapes_rest_at_their_heights(tmp_path):
    """Each stand-in rests at its support height (ball r, box half z, capsule
    lying along x: r, upright cylinder's axial section: half length), sunk by
    the soft step's sag (measured 0.069-0.139 mm at Box2D's 30 Hz)."""
    sc = scene_from(tmp_path, spec(["gravity", "contact"], SHAPES, GROUND, duration=1.0, dt=1 / 240))
    _, tr = run_ok(sc)
    sag = np.array([0.1, 0.05, 0.05, 0.05]) - tr.pos[-1, :, 2]
    print(f"box2d resting sag per shape (mm): {np.round(sag * 1e3, 4)}")
    assert np.all(sag >= 0.0) and np.all(sag <= 3e-4)
    assert np.abs(tr.vel[-1]).max() <= 1e-3


@pytest.mark.parametrize("threshold,bounces", [(0.0, True), (1.0, False)])
def test_restitution_threshold(tmp_path, threshold, bounces):
    """A 0.44 m/s impact (1 cm drop) bounces at e with the adapter's default
    threshold 0 and not at all with Box2D's own 1 m/s."""
    h = 0.01
    sc = scene_from(tmp_path, spec(["gravity", "contact", "restitution"], ball(z=0.1 + h), GROUND,
                                   duration=0.08, material="restitution = 0.5"))
    _, tr = run_ok(sc, {"restitution_threshold": threshold})
    vmax = tr.vel[:, 0, 2].max()
    if bounces:
        assert abs(vmax / math.sqrt(2 * G * h) - 0.5) <= 0.05
    else:
        assert vmax <= 0.05 * math.sqrt(2 * G * h)


def test_pair_values_through_mixing_rules(tmp_path):
    """Ball 'a' (material 'rubber': e 0.8, mu 0.6) and ball 'b' (default:
    e 0.5, mu 0.2) on a default floor.  Box2D mixes restitution by max and
    friction by sqrt(f_a f_b): the floor gets e 0.5, mu 0.2 and the rubber
    ball e 0.8, mu 1.8 (sqrt(0.2 x 1.8) = 0.6); each ball bounces at its pair e."""
    text = spec(["gravity", "contact", "restitution", "friction"],
                ball(z=0.6, name="a", extra='material = "rubber"\n') + ball(z=0.6, x=1.0, name="b"),
                GROUND, duration=0.45, material="restitution = 0.5\nfriction = 0.2\nstatic_friction = 0.2",
                extra="\n[material.rubber]\nrestitution = 0.8\nfriction = 0.6\nstatic_friction = 0.6\n")
    r, tr = run_ok(scene_from(tmp_path, text))
    v = math.sqrt(2 * G * 0.5)
    for i, e in enumerate((0.8, 0.5)):
        vz = tr.vel[:, i, 2]
        assert abs(vz[np.argmax(vz > 0)] / v - e) <= 0.01
    assert max(r.info["material_residuals"].values()) <= 1e-6


def test_rolling_resistance(tmp_path):
    """A rolling ball against rolling resistance mu_r (m) on the level:
    torque mu_r m g about the contact decelerates it at
    a = mu_r g / (r (1 + I / (m r^2))) = 5/7 mu_r g / r; Box2D's coefficient
    is dimensionless (x the shape radius), so the adapter sets mu_r / r."""
    mu_r, r = 0.005, 0.1
    body = ball(vx=1.0).replace("velocity = [1.0, 0.0, 0.0]",
                                "velocity = [1.0, 0.0, 0.0]\nangular_velocity = [0.0, 10.0, 0.0]")
    sc = scene_from(tmp_path, spec(["gravity", "contact", "friction", "rolling_friction"], body, GROUND,
                                   duration=1.5, dt=1 / 240,
                                   material=f"friction = 0.5\nstatic_friction = 0.5\nrolling_friction = {mu_r}"))
    r_, tr = run_ok(sc)
    a = np.polyfit(tr.t, tr.vel[:, 0, 0], 1)[0]
    want = 5.0 / 7.0 * mu_r * G / r
    print(f"box2d rolling deceleration {-a:.6f} vs {want:.6f}")
    assert abs(-a / want - 1.0) <= 0.01  # measured 0.02 %


def test_max_linear_speed_clamps(tmp_path):
    """Box2D clamps speeds to max_linear_speed (default 400 m/s), noted."""
    r, tr = run_ok(scene_from(tmp_path, spec([], ball(vx=500.0), duration=0.01)))
    assert tr.vel[-1, 0, 0] == pytest.approx(400.0, rel=F32 * 4)
    assert any("max_linear_speed" in n for n in r.notes)
    _, tr = run_ok(scene_from(tmp_path, spec([], ball(vx=500.0), duration=0.01)), {"max_linear_speed": 1000.0})
    assert tr.vel[-1, 0, 0] == pytest.approx(500.0, rel=F32 * 4)


def test_contact_hertz_sets_the_sag(tmp_path):
    """A softer contact sags deeper: a resting box at 60 Hz sinks less than at
    30 Hz (measured 0.086 and 0.022 mm: about 1/f^2, a spring's static sag)."""
    box = ('\n[[body]]\nname = "box"\nshape = "box"\nhalf_extents = [0.1, 0.1, 0.1]\nmass = 1.0\n'
           'position = [0.0, 0.0, 0.1]\n')
    sc = scene_from(tmp_path, spec(["gravity", "contact"], box, GROUND, duration=1.0, dt=1 / 240))
    sags = [0.1 - run_ok(sc, {"contact_hertz": hz})[1].pos[-1, 0, 2] for hz in (30.0, 60.0)]
    print(f"box2d resting sag at 30 / 60 Hz: {sags[0] * 1e3:.3f} / {sags[1] * 1e3:.3f} mm")
    assert 0.0 < sags[1] < 0.5 * sags[0] and sags[0] <= 3e-4


def test_contacts_are_the_begin_touch_manifolds(tmp_path):
    """A ball dropped 1 cm: Box2D's begin-touch event in the landing step gives
    a manifold point at the ball's lowest point, normal along z; no begin
    events follow while it rests."""
    sc = scene_from(tmp_path, spec(["gravity", "contact"], ball(z=0.11), GROUND, duration=0.2, dt=1 / 240))
    r = run(sc, "box2d", compute_metrics=False, contact_cap=4)
    assert r.status == "ok" and r.contacts
    frames = [f for f, _ in r.contacts]
    frame, rows = r.contacts[0]
    assert rows.shape[1] == 7 and len(set(frames)) == len(frames)
    assert np.allclose(np.abs(rows[:, 5]), 1.0) and np.allclose(rows[:, [3, 4]], 0.0)
    assert np.all(np.abs(rows[:, 0]) <= 1e-4) and np.all(np.abs(rows[:, 2]) <= 0.01)
    assert frames[-1] < r.trace.n_frames - 10  # no new begin events while resting


@pytest.mark.parametrize("springs", ["joint", "force"])
def test_spring_period(tmp_path, springs):
    """A 1 kg ball on a k = 40 N/m spring to the world: period 2 pi sqrt(m/k),
    through Box2D's distance-joint spring (f = sqrt(k/m) / 2 pi) or the
    explicit force."""
    body = ball(z=0.0).replace("position = [0.0, 0.0, 0.0]", "position = [0.6, 0.0, 0.0]")
    extra = ('\n[[spring]]\na = "world"\nb = "ball"\nanchor_a = [0.0, 0.0, 0.0]\nstiffness = 40.0\n'
             'rest_length = 0.5\n')
    r, tr = run_ok(scene_from(tmp_path, spec(["spring"], body, duration=3.0, extra=extra)), {"springs": springs})
    x = tr.pos[:, 0, 0] - 0.5
    s = np.nonzero(np.diff(np.sign(x)) > 0)[0]
    tc = tr.t[s] - x[s] * (tr.t[s + 1] - tr.t[s]) / (x[s + 1] - x[s])
    assert abs(np.diff(tc).mean() / (2 * math.pi * math.sqrt(1 / 40.0)) - 1) <= 2e-3
    assert r.stages["spring_joints"] == (1 if springs == "joint" else 0)


def test_linear_drag(tmp_path):
    body = ball(z=0.0, vx=3.0, extra="drag_linear = 0.5\n")
    _, tr = run_ok(scene_from(tmp_path, spec(["drag_linear"], body, duration=2.0)))
    np.testing.assert_allclose(tr.vel[:, 0, 0], 3.0 * np.exp(-0.5 * tr.t), rtol=2e-3)


def test_block_conversion_is_world_from_planar():
    """The block conversion (Box2dAdapter._convert: reused scratch, outputs
    written in place), for a block and for one state, at angles all round
    the circle (both signs of zero, +-pi): positions and velocities bit for
    bit what contract.conventions.world_from_planar gives on the same
    float32 states converted to float64; the quaternion bit for bit
    contract.conventions.world_quat_from_planar_rotation's (its x and z
    exactly 0), which is world_from_planar's at angle = atan2(sin, cos) to
    2^-50 (the bound derived in
    tests/test_frames.py::test_planar_rotation_quaternion_matches_the_angle_path)."""
    from physbench.contract.conventions import world_from_planar, world_quat_from_planar_rotation

    rng = np.random.default_rng(7)
    k, nb = 300, 7
    ang = rng.uniform(-np.pi, np.pi, (k, nb))
    ang[0, :4] = [0.0, np.pi, -np.pi, 1e-9]
    t = np.stack([rng.normal(0, 3, (k, nb)), rng.normal(0, 3, (k, nb)), np.cos(ang), np.sin(ang)], -1).astype(np.float32)
    t[0, 4, 2:] = [1.0, -0.0]
    t[0, 5, 2:] = [-1.0, -0.0]
    v = rng.normal(0, 5, (k, nb, 2)).astype(np.float32)
    w = rng.normal(0, 20, (k, nb)).astype(np.float32)
    a = Box2dAdapter()
    for sl in (np.s_[:], np.s_[5]):
        tt, vv, ww = t[sl], v[sl], w[sl]
        shape = ww.shape
        want = [np.full((*shape, m), np.nan) for m in (3, 4, 3, 3)]
        t64 = tt.astype(float)
        world_from_planar(t64[..., 0], t64[..., 1], vv[..., 0].astype(float), vv[..., 1].astype(float),
                          np.arctan2(t64[..., 3], t64[..., 2]), ww.astype(float), *(np.moveaxis(x, -1, 0) for x in want))
        got = [np.full((*shape, m), np.nan) for m in (3, 4, 3, 3)]
        a._convert(tt, vv, ww, *got)
        for i in (0, 2, 3):
            assert np.array_equal(got[i].view(np.uint64), want[i].view(np.uint64))
        q = np.full((2, *shape), np.nan)
        world_quat_from_planar_rotation(tt[..., 2], tt[..., 3], q[0], q[1], np.empty((4, *shape)))
        assert np.array_equal(got[1][..., 0::2].view(np.uint64), np.moveaxis(q, 0, -1).view(np.uint64))
        assert np.array_equal(got[1][..., 1::2].view(np.uint64), np.zeros((*shape, 2), np.uint64))
        assert np.abs(got[1] - want[1]).max() <= 2.0 ** -50


def test_block_recording_keeps_frames_before_an_engine_error(head_on_path):
    """An exception in the k-th step of a block (past the first staging
    chunk) leaves the k - 1 steps before it recorded and converted
    (block_done says how many), equal to a plain step-and-read loop."""
    from physbench.adapters import box2d

    sc = load_scene(head_on_path)
    k = max(box2d.CHUNK_ROWS, box2d.CHUNK_ELEMENTS // sc.n_bodies) + 9
    n = k + 50
    ref = Box2dAdapter()
    ref.build(sc, Box2dAdapter.resolve_settings(sc))
    want = [np.zeros((k - 1, 2, j)) for j in (3, 4, 3, 3)]
    for i in range(k - 1):
        ref.step(1)
        ref.read_state(*(x[i] for x in want))
    a = Box2dAdapter()
    a.build(sc, Box2dAdapter.resolve_settings(sc))

    class Failing:
        def __init__(self, world):
            self.world, self.calls = world, 0

        def step(self, dt, sub):
            self.calls += 1
            if self.calls == k:
                raise RuntimeError("engine failure")
            self.world.step(dt, sub)

    assert a._chunk == k - 9
    a._world = Failing(a._world)
    got = [np.full((n, 2, j), np.nan) for j in (3, 4, 3, 3)]
    with pytest.raises(RuntimeError, match="engine failure"):
        a.step_record(n, *got)
    assert a.block_done == k - 1 and a.steps == k - 1
    for g, x in zip(got, want):
        np.testing.assert_array_equal(g[:k - 1], x)
        assert np.isnan(g[k - 1:]).all()
