"""Contact-law residuals (harness/contact_laws.py) on planted contact
forces: rows that obey each law give 0, rows that break it by a known
amount give exactly that amount, and no rows give ``undefined`` with the
reason, never 0."""

from __future__ import annotations

import math

import numpy as np
import pytest

from physbench.harness.contact_laws import (LAWS, contact_law_metrics, cone_violation, dissipation_residual,
                                            no_forces, signorini_residual)
from physbench.contract.scene import load_scene
from physbench.harness.references import undefined_reason

RNG = np.random.default_rng(46)


def _lawful(R: int = 40):
    """R rows that satisfy every law: pressed rows at gap 0 with friction
    inside the cone; the sliding ones (every other) on the cone's edge
    opposing the slip; separated rows (gap > 0) carry no force."""
    lam_n = RNG.uniform(0.5, 5.0, R)
    gap = np.zeros(R)
    mu = RNG.uniform(0.2, 0.9, R)
    slip = np.zeros((R, 3))
    lam_t = np.zeros((R, 3))
    for i in range(R):
        d = RNG.normal(size=2)
        d = np.array([d[0], d[1], 0.0]) / np.hypot(*d)
        if i % 2:  # sliding: on the edge, opposing the slip
            slip[i] = RNG.uniform(0.05, 2.0) * d
            lam_t[i] = -mu[i] * lam_n[i] * d
        else:  # sticking: strictly inside
            lam_t[i] = RNG.uniform(0.0, 0.99) * mu[i] * lam_n[i] * d
    lam_n[-4:] = 0.0
    gap[-4:] = RNG.uniform(1e-3, 1e-2, 4)
    lam_t[-4:] = 0.0
    slip[-4:] = 0.0
    return lam_n, lam_t, gap, slip, mu


def test_lawful_rows_give_zero_residuals():
    lam_n, lam_t, gap, slip, mu = _lawful()
    m = contact_law_metrics(lam_n, lam_t, gap, slip, mu)
    for name in ("signorini_residual", "separation_force", "adhesion", "cone_violation", "dissipation_shortfall"):
        assert m[f"{name}_max"] == pytest.approx(0.0, abs=1e-12), name
    assert m["dissipation_residual_max"] < 1e-7  # an angle from atan2 of a rounding-size cross product
    assert m["signorini_residual_rows"] == 40
    assert m["cone_violation_rows"] == 36
    assert m["dissipation_residual_rows"] == 18
    assert m["separation_force_rows"] == 4


def test_signorini_finds_the_planted_force_at_a_gap():
    lam_n, lam_t, gap, slip, mu = _lawful()
    # row 3: 2.5 N pressing across a 4 mm gap; row 5: 1.5 N pulling (adhesion) at contact
    lam_n[3], gap[3] = 2.5, 4e-3
    lam_n[5] = -1.5
    m = signorini_residual(lam_n, gap)
    assert m["signorini_residual_max"] == pytest.approx(2.5 * 4e-3, rel=1e-12)
    assert m["signorini_residual_mean"] == pytest.approx(2.5 * 4e-3 / 40, rel=1e-12)
    assert m["separation_force_max"] == pytest.approx(2.5, rel=1e-12)
    assert m["separation_force_rows"] == 5
    assert m["adhesion_max"] == pytest.approx(1.5, rel=1e-12)
    # penetration under force is a residual too: 3 N at a 2 mm overlap
    lam_n, gap = np.array([3.0, 1.0]), np.array([-2e-3, 0.0])
    assert signorini_residual(lam_n, gap)["signorini_residual_max"] == pytest.approx(6e-3, rel=1e-12)


@pytest.mark.parametrize("excess", [1e-6, 0.05, 0.5, 3.0])
def test_cone_violation_finds_the_planted_excess(excess):
    """Friction pushed to (1 + excess) mu lam_n on one row: the relative
    violation is exactly excess mu."""
    lam_n, lam_t, gap, slip, mu = _lawful()
    i = 6
    d = lam_t[i] / np.linalg.norm(lam_t[i]) if np.linalg.norm(lam_t[i]) else np.array([1.0, 0, 0])
    lam_t[i] = (1 + excess) * mu[i] * lam_n[i] * d
    m = cone_violation(lam_n, lam_t, mu)
    assert m["cone_violation_max"] == pytest.approx(excess * mu[i], rel=1e-9)
    assert m["cone_violation_mean"] == pytest.approx(excess * mu[i] / 36, rel=1e-9)


@pytest.mark.parametrize("angle", [1e-6, 0.1, 1.0, math.pi / 2, 3.0])
def test_dissipation_finds_the_planted_misalignment(angle):
    """A sliding row's friction rotated by ``angle`` in the tangent plane
    away from -slip: the residual is exactly that angle."""
    lam_n, lam_t, gap, slip, mu = _lawful()
    i = 7  # sliding
    c, s = math.cos(angle), math.sin(angle)
    x, y, z = lam_t[i]
    lam_t[i] = (c * x - s * y, s * x + c * y, z)
    m = dissipation_residual(lam_n, lam_t, slip, mu)
    assert m["dissipation_residual_max"] == pytest.approx(angle, rel=1e-9)
    assert m["dissipation_shortfall_max"] == pytest.approx(0.0, abs=1e-12)  # still on the edge


def test_dissipation_finds_the_planted_shortfall_and_works_in_2d():
    lam_n = np.array([2.0, 4.0])
    mu = np.array([0.5, 0.25])
    slip = np.array([[1.0, 0.0], [0.0, -3.0]])
    lam_t = np.array([[-0.7, 0.0], [0.0, 1.0]])  # 70 % and 100 % of mu lam_n = 1.0
    m = dissipation_residual(lam_n, lam_t, slip, mu)
    assert m["dissipation_shortfall_max"] == pytest.approx(0.3, rel=1e-12)
    assert m["dissipation_shortfall_mean"] == pytest.approx(0.15, rel=1e-12)
    assert m["dissipation_residual_max"] == pytest.approx(0.0, abs=1e-15)
    # friction along the slip (pushing it on): misaligned by pi
    m = dissipation_residual(lam_n[:1], -lam_t[:1], slip[:1], mu[:1])
    assert m["dissipation_residual_max"] == pytest.approx(math.pi, rel=1e-12)


def test_no_rows_are_undefined_with_the_reason_never_zero():
    z = np.zeros(0)
    m = contact_law_metrics(z, np.zeros((0, 3)), z, np.zeros((0, 3)), z)
    for name in ("signorini_residual", "cone_violation", "dissipation_residual"):
        assert math.isnan(m[f"{name}_max"]) and math.isnan(m[f"{name}_mean"])
        assert undefined_reason(m, f"{name}_max"), name
        assert m[f"{name}_rows"] == 0
    # resting rows only: nothing slides, so no dissipation residual
    m = dissipation_residual(np.ones(3), np.zeros((3, 3)), np.zeros((3, 3)), np.full(3, 0.5))
    assert math.isnan(m["dissipation_residual_max"])
    assert "sliding" in undefined_reason(m, "dissipation_residual_max")


def test_an_engine_without_forces_gets_undefined_with_its_reason():
    m = no_forces("pymunk: the adapter reads no contact impulses")
    for name in LAWS:
        assert math.isnan(m[f"{name}_max"])
        assert undefined_reason(m, f"{name}_max") == "pymunk: the adapter reads no contact impulses"


# ---------------------------------------------------------------------------
# the reference engine's contact forces, recorded only when asked

SCENE = """
[scenario]
family = "laws"
title = "contact laws"
duration = 0.5
dt = 0.004166666666666667
effects = ["gravity", "contact", "friction", "gyroscopic"]
{primary}

[material.default]
friction = 0.3
static_friction = 0.4

[[body]]
name = "block"
shape = "box"
half_extents = [0.1, 0.1, 0.05]
mass = 1.0
{pose}

[[static]]
name = "ground"
{ground}
{checks}
"""
FLAT = ('position = [0.0, 0.0, 0.05]', 'shape = "plane"\nnormal = [0.0, 0.0, 1.0]')
# block_slides' block on its 35 degree slope (mu 0.3 < tan 35): it slides from the start
SLOPE = ('position = [0.028678821817552304, 0.0, 0.04095760221444959]\n'
         'orientation = [0.9537169507482269, 0.0, 0.3007057995042731, 0.0]',
         'shape = "slope"\nangle = 35.0\npoint = [0.0, 0.0, 0.0]')
CHECKS = """
[[check]]
metric = "cone_violation_max"
max = 1e-9

[[check]]
metric = "signorini_residual_max"
max = 1e-9
"""


def _law_scene(tmp_path, where, checks=CHECKS, primary=""):
    p = tmp_path / "laws.toml"
    p.write_text(SCENE.format(pose=where[0], ground=where[1], checks=checks, primary=primary))
    return load_scene(str(p))


def test_resting_box_on_the_reference_engine(tmp_path):
    """The box's weight on the floor at a zero gap: Signorini's residual and
    the cone violation at solver tolerance; nothing slides, so maximum
    dissipation has no row and is undefined with the reason."""
    from physbench.harness.runner import run

    res = run(_law_scene(tmp_path, FLAT), "reference")
    m = res.metrics
    assert res.status == "ok", res.message
    assert m["signorini_residual_rows"] == 120  # one patch on every step
    assert m["signorini_residual_max"] < 1e-9  # N m: 9.81 N at a gap below 1e-10 m
    assert m["cone_violation_max"] == 0.0
    assert m["adhesion_max"] == 0.0
    assert math.isnan(m["dissipation_residual_max"])
    assert "no sliding contact" in undefined_reason(m, "dissipation_residual_max")


def test_sliding_block_obeys_maximum_dissipation_on_the_reference_engine(tmp_path):
    """The block sliding down the slope: friction mu_k lam_n, opposing the
    slip, at every step it slides."""
    from physbench.harness.runner import run

    res = run(_law_scene(tmp_path, SLOPE), "reference")
    m = res.metrics
    assert res.status == "ok", res.message
    assert m["dissipation_residual_rows"] >= 100
    assert m["dissipation_residual_max"] < 1e-6  # rad
    assert m["dissipation_shortfall_max"] < 1e-6
    assert m["cone_violation_max"] < 1e-9
    # the normal force is the weight's normal part, m g cos 35 = 8.036 N: the residuals read real forces
    assert m["signorini_residual_max"] < 1e-9


def test_forces_are_recorded_only_when_asked(tmp_path):
    from physbench.contract.metric_defs import wants_contact_forces
    from physbench.harness.runner import run

    res = run(_law_scene(tmp_path, FLAT, checks=""), "reference")
    assert "cone_violation_max" not in res.metrics
    scoped = _law_scene(tmp_path, FLAT, checks=CHECKS.replace("max = 1e-9", 'max = 1e-9\nengines = ["reference"]'))
    assert wants_contact_forces(scoped, "reference") and not wants_contact_forces(scoped, "mujoco")
    by_variant = _law_scene(tmp_path, FLAT, checks=CHECKS.replace("max = 1e-9", 'max = 1e-9\nvariants = ["v"]'))
    assert not wants_contact_forces(by_variant, "reference")  # the base scene: the checks name variant v only
    res = run(_law_scene(tmp_path, FLAT, checks="", primary='primary_metric = "cone_violation_mean"'), "reference")
    assert res.metrics["cone_violation_mean"] == 0.0


def test_an_adapter_without_forces_is_undefined_never_zero(tmp_path, monkeypatch):
    """An adapter with no reader (every shipped 3D engine has one now:
    MuJoCo's removed here) gives undefined with the base reason, never 0."""
    from physbench.adapters import contact_forces
    from physbench.harness.runner import run

    monkeypatch.delitem(contact_forces.READERS, "mujoco")
    res = run(_law_scene(tmp_path, FLAT), "mujoco")
    if res.status == "unsupported":
        pytest.skip(res.message)
    assert math.isnan(res.metrics["cone_violation_max"])
    assert undefined_reason(res.metrics, "cone_violation_max") == (
        "mujoco: the adapter reads no contact forces from its engine")


@pytest.mark.parametrize("cone", ["elliptic", "pyramidal"])
def test_mjx_forces_decode_both_cones(tmp_path, cone):
    """MJX's rows come from its raw constraint forces (adapters.
    contact_forces.mjx_rows): on a block sliding down a 35 degree slope
    (mu 0.3) the friction is exactly mu lam_n and opposes the slip with
    either cone (a pyramid read as elliptic rows, or undecoded, would put
    the friction off mu lam_n and off the slip), as on MuJoCo."""
    from physbench.harness.runner import run

    checks = CHECKS.replace("cone_violation_max", "dissipation_residual_max")
    res = run(_law_scene(tmp_path, SLOPE, checks=checks), "mjx", {"cone": cone})
    if res.status == "unsupported":
        pytest.skip(res.message)
    m = res.metrics
    assert m["dissipation_residual_rows"] >= 100  # measured 110 (elliptic), 102 (pyramidal)
    assert m["dissipation_residual_max"] < 1e-9 and m["dissipation_shortfall_max"] < 1e-9  # 8.9e-15, 1.4e-14 rad; 0
    assert m["cone_violation_max"] < 1e-9


def test_reference_penalty_contacts_are_undefined_with_the_reason(tmp_path):
    from physbench.harness.runner import run

    res = run(_law_scene(tmp_path, FLAT), "reference", {"contact_model": "penalty"})
    assert math.isnan(res.metrics["cone_violation_max"])
    assert "penalty contacts keep no per-contact forces" in undefined_reason(res.metrics, "cone_violation_max")


# ---- every engine's contact forces: two cubes resting on the floor -----------

STACK = """
[scenario]
family = "laws"
title = "two cubes resting"
duration = 0.5
dt = 0.004166666666666667
effects = ["gravity", "contact", "friction"]
planar = true

[material.default]
friction = 0.3
static_friction = 0.4

[[body]]
name = "low"
shape = "box"
half_extents = [0.05, 0.05, 0.05]
mass = 1.0
position = [0.0, 0.0, 0.05]

[[body]]
name = "high"
shape = "box"
half_extents = [0.05, 0.05, 0.05]
mass = 0.5
position = [0.0, 0.0, 0.15]

[[static]]
name = "ground"
shape = "plane"
normal = [0.0, 0.0, 1.0]

[[check]]
metric = "signorini_residual_max"
max = 1e-9

[[check]]
metric = "cone_violation_max"
max = 1e-9
"""
G = 9.81
#: measured on the resting cubes (docs/ENGINE_FINDINGS.md, "Contact-law
#: residuals"): signorini_residual_max N m and cone_violation_max, each
#: bound 1.5x the figure (the reference engine: its solver tolerance)
RESTING = {
    "reference": (1e-9, 0.0),          # 6.2e-11 N m: a zero gap under 4.9 and 14.7 N
    "mujoco": (1.8e-3, 0.0),           # 1.18e-3 N m: soft contacts sink 7.2e-5 m under the load
    "pybullet": (4.8e-3, math.sqrt(2) * 0.3 - 0.4 + 1e-12),  # 3.2e-3 N m; the pyramid's corner
    "pymunk": (4.6e-3, 0.0),           # 3.1e-3 N m: overlap kept below collision_slop
    "rapier": (5.8e-4, 0.0),           # 3.87e-4 N m: soft contacts sink 1.05e-4 m under the load
    "mjx": (1.8e-3, 0.0),              # 1.18e-3 N m: MuJoCo's model, MuJoCo's figure
    "drake": (1.7e-4, 0.0),            # 1.10e-4 N m: one hydroelastic patch per pair, the harness's own gap
}
#: settings an engine needs for its friction to be read: Rapier's default
#: "simplified" friction exposes no impulse (test_rapier_default_friction_is_undefined)
FRICTION_READ = {"rapier": {"friction_model": "coulomb"}}


def _engine_adapter(scene, engine, settings=None):
    from physbench.adapters import get_adapter

    cls = get_adapter(engine)
    if cls.unsupported_reason(scene) is not None:
        pytest.skip(cls.unsupported_reason(scene))
    ad = cls()
    try:
        ad.build(scene, cls.resolve_settings(scene, settings))
    except Exception as e:  # the engine is not installed here
        if type(e).__name__ == "Unsupported":
            pytest.skip(str(e))
        raise
    return ad


@pytest.mark.parametrize("engine", list(RESTING))
def test_resting_box_forces_on_every_engine(tmp_path, engine):
    """Two cubes (1 kg below, 0.5 kg on top) at rest on the floor: the
    adapter's rows carry the weights, (m1 + m2) g on the floor's rows and
    m2 g between the cubes, positive along normals from a to b (down into
    the floor, up into the upper cube), with no friction left at rest;
    and the run's residuals are those measured for the engine.  The sums
    hold whatever an engine's rows are: points (4 per face), a patch
    (reference, pymunk) or a hydroelastic surface's resultant (Drake:
    one per pair, gap NaN -> the harness's own).  Tolerance rel 2e-3 of
    the weight on every engine."""
    from physbench.harness.runner import run

    p = tmp_path / "stack.toml"
    p.write_text(STACK)
    scene = load_scene(str(p))
    ad = _engine_adapter(scene, engine, FRICTION_READ.get(engine))
    for _ in range(120):
        ad.step(1)
    rows = ad.contact_forces()
    ad.close()
    floor = rows["b"] < 0
    assert set(rows["static"][floor]) == {0} and set(rows["a"][floor]) == {0}
    assert set(rows["a"][~floor]) == {0} and set(rows["b"][~floor]) == {1}
    assert rows["lam_n"][floor].sum() == pytest.approx(1.5 * G, rel=2e-3)
    assert rows["lam_n"][~floor].sum() == pytest.approx(0.5 * G, rel=2e-3)
    assert np.all(rows["normal"][floor][:, 2] < -0.999) and np.all(rows["normal"][~floor][:, 2] > 0.999)
    assert np.abs(rows["lam_t"].sum(axis=0)).max() < 1e-2 * G  # N: at rest
    res = run(scene, engine, FRICTION_READ.get(engine))
    assert res.status in ("ok", "failed_check"), res.message
    sig, cone = RESTING[engine]
    m = res.metrics
    assert m["signorini_residual_rows"] >= 240  # at least one row per pair per step
    assert 0.0 <= m["signorini_residual_max"] < sig
    assert 0.0 <= m["cone_violation_max"] <= cone
    assert m["adhesion_max"] == 0.0


def test_pybullet_friction_is_a_pyramid(tmp_path):
    """Bullet clamps its two lateral frictions one by one: the friction
    reaches sqrt(2) mu on the pyramid's corner (mu 0.3 -> 0.424 lam_n,
    0.024 over a cone of mu_s 0.4) and aims up to 45 degrees off the slip
    of a block sliding down a slope (MuJoCo's elliptic cone: 0)."""
    from physbench.harness.runner import run

    checks = CHECKS.replace("cone_violation_max", "dissipation_residual_max")
    scene = _law_scene(tmp_path, SLOPE, checks=checks)
    res = run(scene, "pybullet")
    if res.status == "unsupported":
        pytest.skip(res.message)
    m = res.metrics
    assert m["cone_violation_max"] == pytest.approx(math.sqrt(2) * 0.3 - 0.4, abs=1e-9)
    assert m["dissipation_residual_rows"] >= 100
    assert 0.5 < m["dissipation_residual_mean"] < m["dissipation_residual_max"] < math.pi / 4 + 0.01  # rad
    assert m["dissipation_shortfall_max"] < 1e-9  # each direction clamped at mu lam_n: |lam_t| >= mu lam_n
    res = run(scene, "mujoco")
    if res.status != "unsupported":
        assert res.metrics["dissipation_residual_max"] < 1e-9
        assert res.metrics["cone_violation_max"] == 0.0


def test_a_nan_gap_is_the_harness_own(tmp_path):
    """An adapter's NaN gap is replaced by the pair's signed distance from
    the harness's geometry at the recorded pose; a reported gap is kept."""
    from physbench.harness.contact_laws import own_gap

    p = tmp_path / "stack.toml"
    p.write_text(STACK)
    scene = load_scene(str(p))
    pos = np.array([[0.0, 0.0, 0.049], [0.03, 0.0, 0.152]])  # low sinks 1 mm; high 3 mm above it
    quat = np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    rows = {"a": np.array([0, 0, 0]), "b": np.array([-1, 1, 1]), "static": np.array([0, -1, -1]),
            "gap": np.array([np.nan, np.nan, 7.0])}
    gap = own_gap(scene, rows, pos, quat)
    assert gap == pytest.approx([-1e-3, 3e-3, 7.0], abs=1e-12)


def test_box2d_forces_are_undefined_with_the_bindings_reason(tmp_path):
    """pyb2d3 binds no per-step contact data: on the resting cubes every
    residual is undefined with the reason that names what is missing."""
    from physbench.harness.runner import run

    p = tmp_path / "stack.toml"
    p.write_text(STACK)
    res = run(load_scene(str(p)), "box2d")
    if res.status == "unsupported":
        pytest.skip(res.message)
    m = res.metrics
    for name in LAWS:
        assert math.isnan(m[f"{name}_max"])
        why = undefined_reason(m, f"{name}_max")
        assert why.startswith("box2d: the adapter reads no contact forces: pyb2d3")
        assert "b2Shape_GetContactData" in why and "totalNormalImpulse" in why


def test_box2d_binds_no_contact_data(tmp_path):
    """What the Box2D adapter's undefined reason says is missing, measured
    on the installed pyb2d3: no call returns a contact's manifold after the
    solve (Box2D v3.1's b2Body_GetContactData / b2Shape_GetContactData, a
    pre-solve callback), the begin-touch manifold of a box landing on
    another carries zero impulses, and the debug draw's impulse segments
    are totalNormalImpulse (2 m g dt per resting pair, summed over the
    points), not the last substep's normal impulse m g dt / S.  Fails once
    a pyb2d3 binds a route: then Box2D's force reader is to be written."""
    b2 = pytest.importorskip("pyb2d3")
    from physbench.adapters import get_adapter

    for cls in (b2.Body, b2.Shape, b2.World):
        assert not [n for n in dir(cls) if "contact_data" in n or "manifold" in n], cls
    assert not [n for n in dir(b2.World) if "pre_solve" in n]
    assert not [n for n in dir(b2.DebugDrawBase) if "use_drawing" in n]
    p = tmp_path / "stack.toml"
    p.write_text(STACK.replace("position = [0.0, 0.0, 0.15]", "position = [0.0, 0.0, 0.2]"))
    sc = load_scene(str(p))
    cls = get_adapter("box2d")
    settings = cls.resolve_settings(sc, {})
    ad = cls()
    ad.build(sc, settings)
    began = []
    for _ in range(240):
        ad.step(1)
        for e in ad._world.get_contact_events().begin_events():
            began += [(q.normal_impulse, q.tangent_impulse, q.total_normal_impulse) for q in e.manifold.points()]
    assert len(began) >= 4 and not np.any(began)  # the floor's and the landing box's points

    class Segments(b2.DebugDraw):
        def __init__(self):
            super().__init__()
            self.seg = []

        def draw_segment(self, p1, p2, color):
            self.seg.append((tuple(p1), tuple(p2), color))

    d = Segments()
    d.draw_contacts = d.draw_contact_impulses = True
    d.drawing_bounds = b2.aabb(lower_bound=(-10, -10), upper_bound=(10, 10))
    ad._world.draw(d, call_begin_end=False)
    # normal segments (magenta 0xFF00FF) point up from the points: a pair's
    # lengths sum to the weight above it times 2 dt, at any substep count
    up = sorted(float(np.hypot(q[0] - p[0], q[1] - p[1])) for p, q, c in d.seg if c == 0xFF00FF)
    dt = float(settings["dt"])
    assert len(up) == 4
    assert sum(up[:2]) == pytest.approx(2 * G * 0.5 * dt, rel=1e-3)
    assert sum(up[2:]) == pytest.approx(2 * G * 1.5 * dt, rel=1e-3)


def test_rapier_default_friction_is_undefined(tmp_path):
    """Rapier's default friction model keeps one friction impulse per
    manifold that the bindings do not expose: the adapter's rows carry NaN
    friction, Signorini's law is measured (the same figure as with
    per-point friction) and the friction laws are undefined with the
    reason, never 0."""
    from physbench.harness.runner import run

    p = tmp_path / "stack.toml"
    p.write_text(STACK)
    scene = load_scene(str(p))
    ad = _engine_adapter(scene, "rapier")
    ad.step(5)
    rows = ad.contact_forces()
    ad.close()
    assert np.isnan(rows["lam_t"]).all() and rows["lam_n"].sum() == pytest.approx(2.0 * G, rel=0.05)
    m = run(scene, "rapier").metrics
    assert 0.0 < m["signorini_residual_max"] < RESTING["rapier"][0]
    for name in ("cone_violation", "dissipation_residual", "dissipation_shortfall"):
        assert math.isnan(m[f"{name}_max"]) and m[f"{name}_rows"] == 0
        assert undefined_reason(m, f"{name}_max").startswith("rapier: friction_model 'simplified'")


# a block sliding on the floor diagonally (x and y), so that both tangents carry friction
DIAGONAL = ('position = [0.0, 0.0, 0.05]\nvelocity = [1.2, 0.9, 0.0]', FLAT[1])


@pytest.mark.parametrize("where", [SLOPE, DIAGONAL], ids=["slope", "diagonal"])
def test_rapier_friction_basis_balances_momentum(tmp_path, where):
    """The reader's world forces are Rapier's: over every step the rows'
    forces on the sliding block (normal and friction, negated: the rows
    give the force on b) equal m dv/dt - m g from the block's own velocity
    change, in all three components (the friction basis is Rapier's, not a
    guess; the lateral component would carry the whole tangent_impulse[0]
    in a wrong one)."""
    scene = _law_scene(tmp_path, where, checks="")
    ad = _engine_adapter(scene, "rapier", FRICTION_READ["rapier"])
    dt = float(ad._world.integration_parameters.dt)
    pos, quat, v0, w, v1 = np.zeros((1, 3)), np.zeros((1, 4)), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3))
    worst, friction = 0.0, 0.0
    for _ in range(30):
        ad.read_state(pos, quat, v0, w)
        ad.step(1)
        ad.read_state(pos, quat, v1, w)
        rows = ad.contact_forces()
        assert set(rows["a"]) == {0} and set(rows["b"]) == {-1}
        on_block = -(rows["lam_n"][:, None] * rows["normal"] + rows["lam_t"]).sum(axis=0)
        want = scene.bodies[0].mass * ((v1[0] - v0[0]) / dt - scene.gravity)
        worst = max(worst, float(np.abs(on_block - want).max()))
        friction = max(friction, float(np.linalg.norm(rows["lam_t"].sum(axis=0))))
    ad.close()
    assert friction > 1.5  # N: the block slides, friction acts (0.3 x 8.04 N on the slope)
    assert worst < 2e-3  # N: f32 velocities over dt = 1/240 s


def test_rapier_point_friction_is_aimed_off_the_slip(tmp_path):
    """Rapier's per-point Coulomb friction (friction_model 'coulomb') on
    the block sliding down the slope: inside the cone, on its edge, but
    each point's friction aimed 25-27 degrees off the slip (the lateral
    parts cancel in pairs; the patch's total opposes the slip at 0.9 mu
    lam_n).  Measured on rapier3d 0.36.1: 0.451 rad mean, 0.465 max."""
    from physbench.harness.runner import run

    m = run(_law_scene(tmp_path, SLOPE), "rapier", FRICTION_READ["rapier"]).metrics
    assert m["dissipation_residual_rows"] >= 400
    assert 0.43 < m["dissipation_residual_mean"] <= m["dissipation_residual_max"] < 0.48  # rad
    assert m["dissipation_shortfall_mean"] < 1e-4  # on the cone's edge
    assert m["cone_violation_max"] == 0.0


def test_unread_friction_leaves_the_friction_laws_undefined(tmp_path):
    """Rows with NaN lam_t (friction the engine does not expose) count in
    Signorini's law only; with no row of read friction the friction laws
    are undefined with the adapter's reason; mixed rows: the read ones
    are judged, exactly."""
    from types import SimpleNamespace

    from physbench.harness.contact_laws import run_contact_laws

    p = tmp_path / "stack.toml"
    p.write_text(STACK)
    scene = load_scene(str(p))
    trace = SimpleNamespace(pos=np.array([[[0.0, 0, 0.05], [0.0, 0, 0.15]]]), quat=np.tile([1.0, 0, 0, 0], (1, 2, 1)),
                            vel=np.zeros((1, 2, 3)), angvel=np.zeros((1, 2, 3)))
    rows = {"a": np.array([0, 0]), "b": np.array([-1, 1]), "static": np.array([0, -1]),
            "point": np.array([[0.0, 0, 0], [0.0, 0, 0.1]]), "normal": np.array([[0.0, 0, -1], [0.0, 0, 1]]),
            "gap": np.array([-1e-3, 0.0]), "lam_n": np.array([14.715, 4.905]), "lam_t": np.full((2, 3), np.nan)}
    m = run_contact_laws(scene, [(0, rows)], trace, "eng: friction hidden")
    assert m["signorini_residual_max"] == pytest.approx(14.715e-3) and m["signorini_residual_rows"] == 2
    for name in ("cone_violation", "dissipation_residual", "dissipation_shortfall"):
        assert math.isnan(m[f"{name}_max"]) and m[f"{name}_rows"] == 0
        assert undefined_reason(m, f"{name}_max") == "eng: friction hidden"
    rows["lam_t"][1] = [4.905 * 0.5, 0.0, 0.0]  # mu_s 0.4: 0.1 lam_n over the cone
    m = run_contact_laws(scene, [(0, rows)], trace, "eng: friction hidden")
    assert m["cone_violation_rows"] == 1 and m["cone_violation_max"] == pytest.approx(0.1)


@pytest.mark.parametrize("name, settings, steps", [
    ("friction.block_slides", {"dt": 0.064, "integrator": "rk4", "friction_stops": False}, 31),
    ("friction.block_slides", {}, 120),
    ("stacking.column_5", {"dt": 0.064, "direct_start": True, "iterations": 5}, 60),
    ("stacking.mixed_bin", {}, 120),
])
def test_reference_patch_forces_are_the_cached_forces(name, settings, steps):
    """After every step of a sliding block, a column and a bin of mixed
    shapes, each patch row the reference adapter reads has the normal
    force of its pair's cached contact forces, summed independently."""
    import physbench.adapters.reference as R

    scene = load_scene(name)
    ad = R.ReferenceAdapter()
    ad.build(scene, R.ReferenceAdapter.resolve_settings(scene, settings))
    seen = 0
    for _ in range(steps):
        ad.step(1)
        st = ad.state
        c, w = st.ctx.contacts, st.warm
        if w is None or c is None or c.m == 0 or len(w.pairs) == 0:
            continue
        rows = ad.contact_forces()
        # independently: each row's normal force is the sum of its pair's cached normal forces
        n1, ns1 = ad.model.n + 1, ad.model.n_statics + 1
        for i in range(rows["a"].size):
            b = rows["b"][i] if rows["b"][i] >= 0 else ad.model.n
            code = (rows["a"][i] * n1 + b) * ns1 + rows["static"][i] + 1
            assert rows["lam_n"][i] == pytest.approx(float(np.sum(w.fn[w.codes == code])), rel=1e-12, abs=1e-300)
        seen += 1
    assert seen >= 20  # (the bin: its bodies fall for the first ~90 steps)
