"""Tests of the Rapier adapter (adapters/rapier.py) against closed forms.

Every expected value is computed here from the scene (masses, radii, e, mu,
g, k) and from the integration scheme Rapier documents (TGS-soft: each step
is ``iterations`` substeps, each velocity first).  Rapier computes in f32:
tolerances near the f32 resolution say so, with the measured figure.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

rapier3d = pytest.importorskip("rapier3d")

from physbench.adapters.rapier import ROLLING_FRICTION_REASON, RapierAdapter  # noqa: E402
from physbench.contract.scene import load_scene  # noqa: E402
from physbench.harness.runner import run  # noqa: E402

G = 9.81
F32 = 2.0 ** -23  # f32 relative resolution (one unit in the last place at 1.0 is 2^-23)


def scene_from(tmp_path: Path, text: str, variant: str | None = None):
    p = tmp_path / "scene.toml"
    p.write_text(text, encoding="utf-8")
    return load_scene(p, variant)


def run_ok(scene, settings=None, **kw):
    r = run(scene, "rapier", settings, compute_metrics=False, **kw)
    assert r.status == "ok", r.message
    return r, r.trace.valid()


def spec(effects, bodies, statics="", duration=1.0, dt=0.001, planar=False, material="", extra=""):
    """A spec text: scenario header, [material.default] lines, bodies, statics."""
    return (f'[scenario]\nfamily = "test"\ntitle = "t"\nduration = {duration}\ndt = {dt}\n'
            f'planar = {"true" if planar else "false"}\neffects = {effects!r}\n'.replace("'", '"')
            + (f"\n[material.default]\n{material}\n" if material else "") + bodies + statics + extra)


GROUND = '\n[[static]]\nname = "ground"\nshape = "plane"\nnormal = [0.0, 0.0, 1.0]\n'


def ball(z=0.1, r=0.1, vx=0.0, vz=0.0, name="ball", extra=""):
    return (f'\n[[body]]\nname = "{name}"\nshape = "sphere"\nradius = {r}\nmass = 1.0\n'
            f'position = [0.0, 0.0, {z}]\nvelocity = [{vx}, 0.0, {vz}]\n{extra}')


# ---------------------------------------------------------------------------
# declaration and settings


def test_capabilities_and_settings():
    caps = RapierAdapter.capabilities()
    assert caps.available, caps.unavailable_reason
    assert caps.version == rapier3d.__version__ and caps.dimensions == 3
    assert caps.shapes == {"sphere", "box", "capsule", "cylinder"}
    assert caps.static_shapes == {"plane", "slope", "box"}
    assert "gyroscopic" in caps.effects and "rolling_friction" not in caps.effects
    s = caps.settings
    assert s["iterations"].default == 4 and s["pgs_iterations"].default == 1
    assert s["contact_frequency"].default == 30.0 and s["contact_damping_ratio"].default == 10.0
    assert s["ccd"].default is False and s["max_ccd_substeps"].default == 1
    assert s["friction_model"].default == "simplified" and s["springs"].default == "joint"
    # the adapter's defaults are Rapier's own
    ip = rapier3d.IntegrationParameters()
    assert ip.num_solver_iterations == s["iterations"].default
    assert ip.num_internal_pgs_iterations == s["pgs_iterations"].default
    assert ip.contact_softness.natural_frequency == s["contact_frequency"].default
    assert ip.static_contact_softness.natural_frequency == s["static_contact_frequency"].default
    assert ip.max_ccd_substeps == s["max_ccd_substeps"].default
    assert ip.contact_recycling is s["contact_recycling"].default is True
    w = rapier3d.PhysicsWorld(gravity=(0.0, 0.0, 0.0))
    rb = w.rigid_bodies[w.add_body(rapier3d.RigidBodyBuilder(rapier3d.RigidBodyType.DYNAMIC), [])]
    assert rb.allow_fast_rotation is s["fast_rotation"].default is False


def test_settings_are_validated(head_on_path):
    sc = load_scene(head_on_path)
    res = RapierAdapter.resolve_settings(sc, {"iterations": "8", "ccd": "true"})
    assert res["iterations"] == 8 and res["ccd"] is True and res["dt"] == sc.dt
    for bad in ({"iterations": 0}, {"contact_frequency": -1.0}, {"friction_model": "magic"},
                {"springs": "rope"}, {"bogus": 1}):
        with pytest.raises(ValueError):
            RapierAdapter.resolve_settings(sc, bad)


def test_settings_reach_the_engine(head_on_path):
    sc = load_scene(head_on_path)
    a = RapierAdapter()
    a.build(sc, RapierAdapter.resolve_settings(sc, {
        "iterations": 7, "pgs_iterations": 3, "contact_frequency": 45.0, "static_contact_frequency": 90.0,
        "contact_damping_ratio": 2.0, "max_ccd_substeps": 5, "friction_model": "coulomb", "dt": 0.002,
        "contact_recycling": False, "fast_rotation": True}))
    ip = a._world.integration_parameters
    assert ip.num_solver_iterations == 7 and ip.num_internal_pgs_iterations == 3
    assert ip.contact_softness.natural_frequency == 45.0 and ip.contact_softness.damping_ratio == 2.0
    assert ip.static_contact_softness.natural_frequency == 90.0
    assert ip.max_ccd_substeps == 5 and ip.friction_model == rapier3d.FrictionModel.COULOMB
    assert ip.dt == pytest.approx(0.002, rel=F32)
    assert ip.contact_recycling is False and all(rb.allow_fast_rotation for rb in a._bodies)
    a.close()


@pytest.mark.parametrize("fast", [False, True])
def test_angular_speed_cap(tmp_path, fast):
    """Rapier caps angular speed at pi/4 rad per step unless fast_rotation:
    a free body spun at 3 rad per step keeps w dt = pi/4 (to f32) when capped
    and its 3 rad per step when not (docs/ENGINE_FINDINGS.md: the 2 cm
    rolling ball)."""
    dt = 0.01
    spun = ball(z=1.0).replace("velocity = ", f"angular_velocity = [0.0, {3.0 / dt}, 0.0]\nvelocity = ")
    sc = scene_from(tmp_path, spec([], spun, duration=0.05, dt=dt))
    _, tr = run_ok(sc, {"fast_rotation": fast})
    wdt = tr.angvel[1:, 0, 1] * dt
    np.testing.assert_allclose(wdt, 3.0 if fast else math.pi / 4, rtol=4 * F32)


@pytest.mark.parametrize("recycling", [True, False])
def test_contact_recycling_tilts_the_oblique_impact(recycling):
    """billiards.oblique (two frictionless spheres, e 1) at 1-4 substeps:
    with contact recycling the impulse rides the normal of a manifold built
    up to 2 cm before impact, off Newton's law by up to 0.157 (measured at 4
    substeps; asserted > 0.05); without it, by the speculative gap's 0.024
    whatever the substep count (docs/ENGINE_FINDINGS.md)."""
    errs = []
    for s in (1, 2, 3, 4):
        r = run(load_scene("billiards.oblique"), "rapier", {"iterations": s, "contact_recycling": recycling})
        errs.append(r.metrics["post_impact_velocity_error"])
    print(f"rapier oblique, contact_recycling={recycling}: errors {np.round(errs, 4)} at 1-4 substeps")
    if recycling:
        assert max(errs) > 0.05
    else:
        assert max(errs) <= 0.026  # measured 0.0244 at every substep count
        assert max(errs) - min(errs) <= 1e-3


# Newton's law on the canonical spec, free fall under the substep scheme, a
# bounce at e and sliding at mu g: tests/test_closed_forms.py (shared with
# Box2D and pymunk)


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
orientation = [0.7071067811865476, 0.7071067811865475, 0.0, 0.0]

[[body]]
name = "cylinder"
shape = "cylinder"
radius = 0.1
half_length = 0.05
mass = 1.0
position = [3.0, 0.0, 0.05]
"""


def test_shapes_rest_at_their_heights(tmp_path):
    """Each shape rests on the plane with its centre at its support height
    (sphere r, box half z, capsule lying: r, cylinder upright: half length),
    sunk by the soft contact's sag; the sag is the same for every shape
    (measured 0.069-0.108 mm at 60 Hz static contacts)."""
    sc = scene_from(tmp_path, spec(["gravity", "contact"], SHAPES, GROUND, duration=1.0, dt=1 / 240))
    _, tr = run_ok(sc)
    want = np.array([0.1, 0.05, 0.05, 0.05])
    sag = want - tr.pos[-1, :, 2]
    print(f"rapier resting sag per shape (mm): {np.round(sag * 1e3, 4)}")
    assert np.all(sag >= 0.0) and np.all(sag <= 2e-4)
    assert np.abs(tr.vel[-1]).max() <= 1e-3  # at rest


def test_cylinder_axis_is_body_z(tmp_path):
    """An upright cylinder (axis = body z) lands flat at its half length; laid
    on its side (axis turned onto world x) it lands at its radius."""
    side = SHAPES.split("[[body]]")[4].replace("position = [3.0, 0.0, 0.05]",
                                               "position = [3.0, 0.0, 0.1]\norientation = [0.7071067811865476, "
                                               "0.0, 0.7071067811865475, 0.0]")
    sc = scene_from(tmp_path, spec(["gravity", "contact"], "[[body]]" + side, GROUND, duration=0.5, dt=1 / 240))
    _, tr = run_ok(sc)
    assert abs(tr.pos[-1, 0, 2] - 0.1) <= 2e-4


def test_pair_values_by_product(tmp_path):
    """Ball 'a' of material 'rubber' (e 0.8) and ball 'b' of the default
    material (e 0.5) on a default floor: the pairs want rubber|default = 0.8
    and default|default = 0.5.  Under the MULTIPLY rule that takes per-material
    values sqrt(0.5) and 0.8 / sqrt(0.5) (> 1: Rapier takes it), and each
    ball bounces at its pair value."""
    text = spec(["gravity", "contact", "restitution"],
                ball(z=0.6, name="a", extra='material = "rubber"\n')
                + ball(z=0.6, name="b").replace("[0.0, 0.0, 0.6]", "[1.0, 0.0, 0.6]"),
                GROUND, duration=0.45, dt=0.001, material="restitution = 0.5",
                extra="\n[material.rubber]\nrestitution = 0.8\n")
    r, tr = run_ok(scene_from(tmp_path, text))
    v = math.sqrt(2 * G * 0.5)
    for i, e in enumerate((0.8, 0.5)):
        vz = tr.vel[:, i, 2]
        got = vz[np.argmax(vz > 0)] / v
        print(f"ball {i}: bounce {got:.5f} for pair e = {e}")
        assert abs(got - e) <= 0.01
    assert r.info["material_mode"] == "per_material"


def test_no_contact_means_no_colliders(head_on_path):
    from tests.conftest import without_effects

    sc = without_effects(load_scene(head_on_path), "contact", "restitution")
    _, tr = run_ok(sc)
    # f32 free flight: x += v h in 2000 substeps of 0.25 ms rounds at every
    # add (measured 1.9e-5 m at x = 1 m); bound: one f32 ulp of x per substep
    n_sub = 4 * (len(tr.t) - 1)
    np.testing.assert_allclose(tr.pos[-1, :, 0], [2.0 * tr.t[-1], 0.3], rtol=0, atol=n_sub * F32)
    a = RapierAdapter()
    a.build(sc, RapierAdapter.resolve_settings(sc))
    assert len(a._world.colliders) == 0
    a.close()


def test_contacts_are_read_from_the_narrow_phase(tmp_path):
    """A ball resting on the floor: Rapier's solver contact is at the ball's
    lowest point with the normal along z, overlapping by the soft sag."""
    sc = scene_from(tmp_path, spec(["gravity", "contact"], ball(z=0.1), GROUND, duration=0.2, dt=1 / 240))
    r = run(sc, "rapier", compute_metrics=False, contact_cap=4)
    assert r.status == "ok" and r.contacts
    frame, rows = r.contacts[-1]
    assert rows.shape[1] == 7
    assert np.allclose(np.abs(rows[:, 5]), 1.0) and np.allclose(rows[:, 3:5], 0.0)
    assert np.all(np.abs(rows[:, 0:2]) <= 1e-6) and np.all(np.abs(rows[:, 2]) <= 1e-3)
    assert np.all(rows[:, 6] >= 0.0) and np.all(rows[:, 6] <= 2e-4)


def test_rolling_friction_is_unsupported(head_on_path):
    sc = load_scene(head_on_path, None, {"scenario.effects": ["contact", "restitution", "rolling_friction"]})
    r = run(sc, "rapier", compute_metrics=False)
    assert r.status == "unsupported" and r.message == ROLLING_FRICTION_REASON


# ---------------------------------------------------------------------------
# gyroscopic switch, continuous collision, springs, drag

TUMBLER = """
[[body]]
name = "box"
shape = "box"
half_extents = [0.3, 0.2, 0.05]
mass = 1.0
angular_velocity = [0.5, 0.0, 3.0]
"""


def test_gyroscopic_switch(tmp_path):
    """Without 'gyroscopic' the term is off: a box spinning about a
    non-principal axis keeps its angular velocity.  With it, w changes while
    the angular momentum L = R I R^T w stays (within Rapier's implicit
    integration: measured 0.06 % over 1 s at dt 1 ms)."""
    off = scene_from(tmp_path, spec([], TUMBLER, duration=1.0))
    _, tr = run_ok(off)
    np.testing.assert_allclose(tr.angvel[-1, 0], [0.5, 0.0, 3.0], rtol=0, atol=1e-5)
    on = scene_from(tmp_path, spec(["gyroscopic"], TUMBLER, duration=1.0))
    _, tr = run_ok(on)
    from physbench.contract.rotation import quat_to_matrix

    I = np.diag(on.bodies[0].inertia)
    L = np.array([quat_to_matrix(q) @ I @ quat_to_matrix(q).T @ w for q, w in zip(tr.quat[:, 0], tr.angvel[:, 0])])
    assert np.abs(tr.angvel[-1, 0] - [0.5, 0.0, 3.0]).max() > 0.05  # the term acts (measured 0.098)
    drift = np.linalg.norm(L - L[0], axis=1).max() / np.linalg.norm(L[0])
    print(f"rapier gyroscopic on: |L| drift {drift:.3g}")
    assert drift <= 0.005


@pytest.mark.parametrize("ccd", [False, True])
def test_bullet_is_returned_in_every_phase(ccd):
    """bullet_100 (100 m/s, 0.42 m per step, against a 4 mm wall) started at
    eight step phases: Rapier's speculative contact stops it and returns it at
    -e v = -50 m/s in every phase, with or without ccd (the row records the
    flag); what the scenario's xfail records is that its centre first crosses
    the wall's mid-plane."""
    from physbench.contract.phase import shift_scene

    sc = load_scene("tunnelling.bullet_100")
    for k in range(8):
        r, tr = run_ok(shift_scene(sc, k / 8), {"ccd": ccd})
        assert tr.vel[-1, 0, 0] == pytest.approx(-50.0, rel=1e-6)
        assert r.stages["ccd"] is ccd
    a = RapierAdapter()
    a.build(sc, RapierAdapter.resolve_settings(sc, {"ccd": ccd}))
    assert a._world.rigid_bodies[a._handles[0]].ccd_enabled is ccd
    a.close()


@pytest.mark.parametrize("springs", ["joint", "force"])
def test_spring_period(tmp_path, springs):
    """A 1 kg ball on a k = 40 N/m spring to the world, no gravity: period
    2 pi sqrt(m/k).  Both the SpringJoint and the explicit force keep it
    (zero crossings of x measured within 0.02 % of the period)."""
    body = ball(z=0.0).replace("position = [0.0, 0.0, 0.0]", "position = [0.6, 0.0, 0.0]")
    extra = ('\n[[spring]]\na = "world"\nb = "ball"\nanchor_a = [0.0, 0.0, 0.0]\nstiffness = 40.0\n'
             'rest_length = 0.5\n')
    r, tr = run_ok(scene_from(tmp_path, spec(["spring"], body, duration=3.0, extra=extra)), {"springs": springs})
    x = tr.pos[:, 0, 0] - 0.5
    s = np.nonzero(np.diff(np.sign(x)) > 0)[0]
    tc = tr.t[s] - x[s] * (tr.t[s + 1] - tr.t[s]) / (x[s + 1] - x[s])
    period = np.diff(tc).mean()
    assert abs(period / (2 * math.pi * math.sqrt(1 / 40.0)) - 1) <= 2e-3
    assert r.stages["spring_joints"] == (1 if springs == "joint" else 0)


def test_linear_drag(tmp_path):
    """Linear drag c v, no gravity: v(t) = v0 exp(-c t / m)."""
    body = ball(z=0.0, vx=3.0, extra="drag_linear = 0.5\n")
    _, tr = run_ok(scene_from(tmp_path, spec(["drag_linear"], body, duration=2.0)))
    np.testing.assert_allclose(tr.vel[:, 0, 0], 3.0 * np.exp(-0.5 * tr.t), rtol=2e-3)


# ---------------------------------------------------------------------------
# state reads


from physbench.adapters.rapier_batch import QUAT_TOL  # noqa: E402


def _getter_loop(scene, steps):
    """(steps, n, 13) rows by the per-body getters after every step(1): the
    reference for the byte reader."""
    from physbench.adapters.rapier_batch import getter_rows

    a = RapierAdapter()
    a.build(scene, RapierAdapter.resolve_settings(scene))
    rows = []
    for _ in range(steps):
        a.step(1)
        rows.append(getter_rows(a._bodies))
    a.close()
    return np.array(rows)


def test_set_bytes_reader_equals_getters(tmp_path):
    """The runner's block recording (one RigidBodySet.to_bytes() per step,
    decoded at located offsets) gives bit for bit the state the four
    per-body getters give after every step (quaternions to 2 f32 units), on tumbling, colliding bodies of
    every shape (poses, velocities and quaternions all moving); the reader
    is in use (info state_reader)."""
    tumbling = re.sub(r"(mass = [0-9.]+\n)", r"\1angular_velocity = [3.0, -2.0, 5.0]\nvelocity = [0.5, 0.0, 1.0]\n",
                      SHAPES)
    sc = scene_from(tmp_path, spec(["gravity", "contact", "friction", "gyroscopic"], tumbling, GROUND,
                                   duration=0.6, dt=1 / 240, material="friction = 0.5\nstatic_friction = 0.5"))
    r, tr = run_ok(sc)
    assert r.info["state_reader"] == "set_bytes"
    want = _getter_loop(sc, sc.n_steps)
    assert np.abs(want[:, :, 10:13]).max() > 1.0  # the bodies do turn
    np.testing.assert_array_equal(tr.pos[1:], want[:, :, 4:7])
    # the rotation getter renormalises the stored quaternion: components 1
    # f32 unit apart (measured: 23 % of them, 1.2e-7), never more than 2
    np.testing.assert_allclose(tr.quat[1:, :, 0], want[:, :, 3], rtol=0, atol=QUAT_TOL)
    np.testing.assert_allclose(tr.quat[1:, :, 1:], want[:, :, 0:3], rtol=0, atol=QUAT_TOL)
    np.testing.assert_array_equal(tr.vel[1:], want[:, :, 7:10])
    np.testing.assert_array_equal(tr.angvel[1:], want[:, :, 10:13])


def test_set_bytes_reader_check_raises_on_a_mismatch(head_on_path):
    """A decoded state that differs from the getters' is an error, never
    recorded silently (the check after every block)."""
    sc = load_scene(head_on_path)
    a = RapierAdapter()
    a.build(sc, RapierAdapter.resolve_settings(sc))
    a.step(3)
    row = a._reader.decode([a._reader.blob()])[-1]
    a._reader.check(row)  # equal: no error
    row[0, 3] += 2 * QUAT_TOL  # a rotation beyond the tolerance
    with pytest.raises(RuntimeError, match="differs from the getters"):
        a._reader.check(row)
    row[0, 3] -= 2 * QUAT_TOL
    row[1, 5] += 1e-6  # a translation off by anything
    with pytest.raises(RuntimeError, match="differs from the getters"):
        a._reader.check(row)
    with pytest.raises(RuntimeError, match="differs from the getters"):
        a._reader.check(row, sample=2)  # a sample keeps the first and the last body
    a.close()


def test_check_state_reads_the_harness_layout(head_on_path):
    """The check after every recorded block (SetBytesReader.check_state,
    Python floats on the harness's arrays) passes the state read_state
    recorded, also a quaternion within QUAT_TOL, and raises on a
    translation or velocity off by anything or a quaternion beyond
    QUAT_TOL, also on the last body of a sample."""
    sc = load_scene(head_on_path)
    a = RapierAdapter()
    a.build(sc, RapierAdapter.resolve_settings(sc))
    a.step(3)
    st = [np.zeros((2, j)) for j in (3, 4, 3, 3)]
    a.read_state(*st)
    r = a._reader
    r.check_state(*st)
    r.check_state(*st, sample=2)
    for arr, idx, dv in [(0, (1, 2), 1e-9), (2, (0, 0), 1e-9), (3, (1, 1), 1e-9), (1, (1, 0), 2 * QUAT_TOL),
                         (1, (0, 3), -2 * QUAT_TOL)]:
        bad = [x.copy() for x in st]
        bad[arr][idx] += dv
        with pytest.raises(RuntimeError, match="differs from the getters"):
            r.check_state(*bad, sample=2)
    near = [x.copy() for x in st]
    near[1][1, 2] += 0.5 * QUAT_TOL
    r.check_state(*near)
    a.close()


def test_block_recording_keeps_frames_before_an_engine_error(head_on_path, monkeypatch):
    """An exception in the k-th step of a block (in its fifth decoded chunk
    of 32 steps) leaves the k - 1 steps before it recorded and converted
    (block_done says how many), equal to a plain step-and-read loop."""
    from physbench.adapters import rapier

    monkeypatch.setattr(rapier, "CHUNK_BYTES", 1)  # chunks of 32 steps, the least
    sc = load_scene(head_on_path)
    n, k = 300, 137
    ref = RapierAdapter()
    ref.build(sc, RapierAdapter.resolve_settings(sc))
    want = [np.zeros((k - 1, 2, j)) for j in (3, 4, 3, 3)]
    for i in range(k - 1):
        ref.step(1)
        ref.read_state(*(w[i] for w in want))
    a = RapierAdapter()
    a.build(sc, RapierAdapter.resolve_settings(sc))

    class Failing:
        def __init__(self, world):
            self.world, self.calls = world, 0
            self.rigid_bodies = world.rigid_bodies

        def step(self):
            self.calls += 1
            if self.calls == k:
                raise RuntimeError("engine failure")
            self.world.step()

    a._world = Failing(a._world)
    got = [np.full((n, 2, j), np.nan) for j in (3, 4, 3, 3)]
    with pytest.raises(RuntimeError, match="engine failure"):
        a.step_record(n, *got)
    assert a.block_done == k - 1 and a.steps == k - 1
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g[:k - 1], w)
        assert np.isnan(g[k - 1:]).all()


def test_rows_of_another_length_are_decoded_apart(head_on_path):
    """A step whose set bytes have another length than the block's first
    (the set shrinks by 8 bytes per body after the first step) is decoded
    on its own, to the same state as the getters'."""
    from physbench.adapters.rapier_batch import getter_rows

    sc = load_scene(head_on_path)
    a = RapierAdapter()
    a.build(sc, RapierAdapter.resolve_settings(sc))
    r = a._reader
    first = r.blob()  # before any step: longer
    a.step(1)
    after = r.blob()
    assert len(first) != len(after)
    L = len(after)
    rows, spans = r.block(2, L)
    rows[spans[0]] = after
    out = [np.zeros((2, 2, j)) for j in (3, 4, 3, 3)]
    r.rows_into(2, L, {1: after + b"\0" * 8}, *out)
    want = getter_rows(a._bodies)
    for row in (0, 1):
        np.testing.assert_array_equal(out[0][row], want[:, 4:7])
        np.testing.assert_array_equal(out[2][row], want[:, 7:10])
        np.testing.assert_allclose(out[1][row][:, [1, 2, 3, 0]], want[:, 0:4], rtol=0, atol=QUAT_TOL)
    a.close()
