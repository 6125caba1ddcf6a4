"""Spec loading and validation: good specs load, bad specs give exact
messages naming the file, the key path, what was expected and what was found."""

import math
from pathlib import Path

import numpy as np
import pytest

from physbench.contract.scene import load_scene, principal_inertia
from physbench.contract.spec import SpecError, load_spec, parse_key_path
from tests.conftest import HEAD_ON

BASE = HEAD_ON.read_text()


def test_canonical_spec_loads_with_variants():
    loaded = load_spec(HEAD_ON)
    assert set(loaded.variants) == {"elastic", "plastic"}
    s = load_scene(HEAD_ON)
    assert s.id == "billiards.head_on" and s.n_bodies == 2 and s.planar
    assert s.effects == {"contact", "restitution"}
    assert s.pair("default", "default").restitution == 0.9
    assert np.all(s.gravity == 0)  # no 'gravity' effect: none applied
    assert s.n_steps == 500
    assert load_scene(HEAD_ON, "elastic").pair("default", "default").restitution == 1.0
    assert load_scene(HEAD_ON, "plastic").pair("default", "default").restitution == 0.0
    assert s.masses.tolist() == [0.17, 0.17]


def _replace(old, new, count=1):
    assert old in BASE, old
    return BASE.replace(old, new, count)


BAD = [
    ("negative mass", _replace("mass = 0.17\nposition = [0.3", "mass = -1\nposition = [0.3"),
     "body[1].mass: must be > 0, got -1"),
    ("unknown key", _replace("title = ", 'colour = "red"\ntitle = '), "scenario.colour: unknown key"),
    ("unknown effect", _replace('["contact", "restitution"]', '["contact", "magnetism"]'),
     "scenario.effects[1]: unknown effect 'magnetism'; expected one of gravity, contact, restitution, "
     "friction, rolling_friction, drag_linear, drag_quadratic, spring, damper, gyroscopic"),
    ("unknown shape", _replace('shape = "sphere"\nradius = 0.028575\nmass = 0.17\nposition = [0.3',
                               'shape = "torus"\nradius = 0.028575\nmass = 0.17\nposition = [0.3'),
     "body[1].shape: unknown shape 'torus'; expected one of sphere, box, capsule, cylinder"),
    ("missing dimension", _replace("radius = 0.028575\nmass = 0.17\nposition = [0.0", "mass = 0.17\nposition = [0.0"),
     "body[0]: shape 'sphere' needs radius"),
    ("restitution above 1", _replace("restitution = 0.9", "restitution = 1.5"),
     "material.default.restitution: must be <= 1, got 1.5"),
    ("short vector", _replace("velocity = [2.0, 0.0, 0.0]", "velocity = [2.0, 0.0]"),
     "body[0].velocity: expected 3 numbers, got 2: [2.0, 0.0]"),
    ("long vector", _replace("velocity = [2.0, 0.0, 0.0]", "velocity = [2.0, 0.0, 0.0, 1.0]"),
     "body[0].velocity: expected 3 numbers, got 4: [2.0, 0.0, 0.0, 1.0]"),
    ("string for number", _replace("dt = 0.001", 'dt = "fast"'), "scenario.dt: expected a number, got 'fast'"),
    ("planar scene out of plane", _replace("velocity = [2.0, 0.0, 0.0]", "velocity = [2.0, 1.0, 0.0]"),
     "body[0].velocity: a planar scene lies in the x-z plane, so y must be 0, got [2.0, 1.0, 0.0]"),
    ("unknown material", _replace('name = "cue"', 'name = "cue"\nmaterial = "rubber"'),
     "body[0].material: unknown material 'rubber'; defined: default"),
    ("duplicate body", _replace('name = "object"', 'name = "cue"'),
     "body[1].name: duplicate body name 'cue' (also body[0])"),
    ("mass and density", _replace("mass = 0.17\nposition = [0.3", "mass = 0.17\ndensity = 1000.0\nposition = [0.3"),
     "body[1]: give exactly one of mass or density"),
    ("non-unit quaternion", _replace('name = "cue"', 'name = "cue"\norientation = [1.0, 1.0, 0.0, 0.0]'),
     "body[0].orientation: must be a unit quaternion (w, x, y, z), got [1.0, 1.0, 0.0, 0.0] with norm 1.41421"),
    ("variant key out of range", _replace('"material.default.restitution" = 1.0', '"body[5].mass" = 1.0'),
     "variant[elastic].body[5].mass: body[5]: no such entry (there are 2)"),
    ("unknown reference model", _replace("two_body_collision", "three_body"),
     "reference.model: unknown reference model 'three_body'; expected one of"),
    ("unknown check key", _replace("max = 0.02", "min_value = 0.02"), "check[0].min_value: unknown key"),
    ("key of another static shape", BASE + '\n[[static]]\nshape = "plane"\nnormal = [0.0, 0.0, 1.0]\nangle = 10.0\n',
     "static[0]: angle is not a key of static shape 'plane'"),
    ("effect listed twice", _replace('["contact", "restitution"]', '["contact", "contact"]'),
     "scenario.effects: effects are listed twice: ['contact', 'contact']"),
    ("not TOML", _replace("[scenario]", "[scenario"), "<toml>: not valid TOML: Expected ']'"),
    ("dt above duration", _replace("dt = 0.001", "dt = 1.0"), "scenario: dt (1.0) must not exceed duration (0.5)"),
    ("static friction below kinetic", _replace("static_friction = 0.0", "static_friction = 0.0\n").replace(
        "friction = 0.0\nstatic_friction = 0.0", "friction = 0.5\nstatic_friction = 0.2"),
     "material.default: static_friction (0.2) must be >= friction (0.5)"),
]


@pytest.mark.parametrize("what,text,message", BAD, ids=[b[0] for b in BAD])
def test_bad_spec_message(tmp_path, what, text, message):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(SpecError) as exc:
        load_spec(p)
    first = exc.value.errors[0]
    assert first.startswith(f"{p}: "), first
    assert first[len(str(p)) + 2:].startswith(message), first


def test_missing_file(tmp_path):
    with pytest.raises(SpecError, match="no such file"):
        load_spec(tmp_path / "nope.toml")


def test_unknown_variant_names_the_known_ones():
    with pytest.raises(SpecError, match="unknown variant 'bouncy'; this spec has: elastic, plastic"):
        load_scene(HEAD_ON, "bouncy")


def test_overrides_and_key_paths():
    assert parse_key_path("body[1].mass") == ["body", 1, "mass"]
    assert parse_key_path("body.1.mass") == ["body", 1, "mass"]
    s = load_scene(HEAD_ON, overrides={"body[1].mass": 0.5, "material.default.restitution": 0.3})
    assert s.bodies[1].mass == 0.5 and s.pair("default", "default").restitution == 0.3
    with pytest.raises(SpecError, match=r"body\[1\].mass: must be > 0, got -2"):
        load_scene(HEAD_ON, overrides={"body[1].mass": -2})


def test_effects_gate_pair_values(tmp_path):
    # a spec cannot give a coefficient without its effect (next test); the
    # compiled scene's pair values are gated by its effects all the same
    import dataclasses

    s = load_scene(HEAD_ON)
    assert s.pair("default", "default").restitution == 0.9
    s = dataclasses.replace(s, effects=frozenset({"contact"}))
    assert s.pair("default", "default").restitution == 0.0


@pytest.mark.parametrize("key, value, effect", [
    ("friction", 0.5, "friction"), ("static_friction", 0.6, "friction"), ("restitution", 0.5, "restitution"),
    ("rolling_friction", 0.001, "rolling_friction")])
def test_material_coefficient_needs_its_effect(tmp_path, key, value, effect):
    """[material.default] friction = 0.5 without the friction effect used to
    run frictionless without a word: now a spec error naming file and key
    path, exit 2 from the command line."""
    import subprocess
    import sys

    text = BASE.replace("restitution = 0.9\n", "").replace('"material.default.restitution" = 1.0', "") \
        .replace('"material.default.restitution" = 0.0', "").replace("static_friction = 0.0\n", "") \
        .replace("friction = 0.0\n", "")
    text = text.replace("[material.default]\n", f"[material.default]\n{key} = {value}\n")
    text = text.replace('["contact", "restitution"]', '["contact"]')
    p = tmp_path / "s.toml"
    p.write_text(text)
    with pytest.raises(SpecError) as e:
        load_spec(p)
    assert f"s.toml: material.default.{key}: set to {value} but '{effect}' is not in scenario.effects" \
        in "\n".join(e.value.errors)
    root = Path(__file__).resolve().parent.parent
    r = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "run", str(p), "--engine", "reference"],
                       capture_output=True, text=True, cwd=root, timeout=120)
    assert r.returncode == 2 and f"material.default.{key}: set to {value}" in r.stderr
    assert "Traceback" not in r.stderr
    # with the effect listed, the same spec loads
    p.write_text(text.replace('["contact"]', f'["contact", "{effect}"]'))
    load_spec(p)


def test_patterns_expand(tmp_path):
    spec = """
[scenario]
family = "stacking"
title = "t"
duration = 1.0
dt = 0.01
effects = ["gravity", "contact"]
max_initial_overlap = 1.0  # the pyramid starts inside the slope: opted in
[[body]]
name = "box"
shape = "box"
half_extents = [0.1, 0.2, 0.05]
density = 1000.0
position = [0.0, 0.0, 0.05]
[body.pattern]
kind = "pyramid"
count = 3
gap = 0.01
[[static]]
shape = "slope"
angle = 30.0
"""
    p = tmp_path / "p.toml"
    p.write_text(spec)
    s = load_scene(p)
    assert [b.name for b in s.bodies] == [f"box_{i}" for i in range(6)]
    assert s.bodies[0].mass == pytest.approx(1000 * 0.2 * 0.4 * 0.1)
    z = sorted({round(b.position[2], 9) for b in s.bodies})
    assert z == pytest.approx([0.05, 0.16, 0.27])
    st = s.statics[0]
    assert st.kind == "slope" and np.allclose(st.normal, [0.5, 0, math.sqrt(3) / 2])


def test_inertia_formulas():
    # hand values: box 1 kg, half extents (1, 2, 3): Ixx = (4 + 9)/3
    assert np.allclose(principal_inertia("box", 1.0, 0, np.array([1.0, 2.0, 3.0]), 0), [13 / 3, 10 / 3, 5 / 3])
    assert np.allclose(principal_inertia("sphere", 2.0, 0.5, None, 0), [0.2] * 3)
    # cylinder r = 1, h = 1 (length 2), m = 12: Iz = 6, Ix = 12 (3 + 4)/12 = 7
    assert np.allclose(principal_inertia("cylinder", 12.0, 1.0, None, 1.0), [7, 7, 6])
    # capsule with h -> 0 is a sphere
    assert np.allclose(principal_inertia("capsule", 1.0, 1.0, None, 1e-12), [0.4] * 3)


# --- issue 40: buried starts and type slips


@pytest.mark.parametrize("text,message", [
    (_replace("max = 0.02", 'max = "0.02"'),
     "check[0].max: expected a number, got '0.02' (text, in quotes: write the value without them)"),
    (_replace("max = 0.02", "max = true"), "check[0].max: expected a number, got true"),
    (_replace("max = 0.02", "max = 0.02\nmin = 0.0"),
     "check[0]: give one of max or min, not both (max = 0.02, min = 0.0); write two [[check]] tables for a range"),
    (_replace('name = "cue"', 'name = "cue"\nvelocity = ["2.0", 0.0, 0.0]', 1).replace(
        "velocity = [2.0, 0.0, 0.0]\n", "", 1), "body[0].velocity: expected a number, got '2.0'"),
    (_replace("planar = true", 'planar = "true"'), "scenario.planar: expected true or false, got 'true'"),
], ids=["max as text", "max as boolean", "max and min", "vector component as text", "boolean as text"])
def test_type_slips_are_refused(tmp_path, text, message):
    """A number in quotes, a boolean where a number goes, and a check with
    both max and min are refused, never read as something else."""
    p = tmp_path / "slip.toml"
    p.write_text(text)
    with pytest.raises(SpecError) as exc:
        load_spec(p)
    assert any(e == f"{p}: {message}" or e.startswith(f"{p}: {message}") for e in exc.value.errors), exc.value.errors


ROLLS = (Path(__file__).resolve().parent.parent / "scenarios" / "friction" / "ball_rolls.toml").read_text()


def _ball_on_slope(tmp_path, radius="radius = 0.1", angle="angle = 20.0", extra=""):
    text = ROLLS.replace("radius = 0.1", radius, 1).replace("angle = 20.0", angle, 1)
    text = text.replace('tags = ["conformance"]', 'tags = ["conformance"]' + extra, 1)
    p = tmp_path / "ball.toml"
    p.write_text(text)
    return p


def test_buried_start_is_a_spec_error(tmp_path):
    """A start inside geometry deeper than scenario.max_initial_overlap is a
    spec error naming both shapes, the depth and the key paths (issue 40:
    a radius typed as 150 for 150 mm; a slope angle in radians)."""
    c = np.array([0.03420201433256687, 0.0, 0.09396926207859085])  # the ball's centre in the file
    # the angle in radians: the plane through 0 with normal (sin a, 0, cos a)
    a = 0.3490658503988659
    depth = 0.1 - (math.sin(math.radians(a)) * c[0] + math.cos(math.radians(a)) * c[2])
    p = _ball_on_slope(tmp_path, angle=f"angle = {a!r}")
    with pytest.raises(SpecError) as exc:
        load_scene(p)
    assert exc.value.errors == [
        f"{p}: body[0].position: the start is buried: body 'ball' (body[0].position) overlaps slope 'slope' "
        f"(static[0].angle) by {depth:.6g} m, deeper than scenario.max_initial_overlap = 1e-06 m (check units: "
        f"lengths in m, angles in degrees); move the shapes apart, or set [scenario] max_initial_overlap where the "
        f"overlap is the point"]
    assert 0.0057 < depth < 0.0059  # 5.8 mm inside
    # the radius in millimetres: buried by 150 - 0.1 m
    p = _ball_on_slope(tmp_path, radius="radius = 150.0")
    with pytest.raises(SpecError, match=r"overlaps slope 'slope' \(static\[0\]\.angle\) by 149\.9 m"):
        load_scene(p)
    # opted in: the same start loads
    assert load_scene(_ball_on_slope(tmp_path, radius="radius = 150.0", extra="\nmax_initial_overlap = 150.0"))


def test_touching_start_is_accepted(tmp_path):
    """Shapes placed exactly in contact overlap by rounding only (~1e-17 m):
    every shipped stack and resting body loads; an overlap within the
    tolerance loads; past it, not."""
    from physbench.contract.geometry.start import MAX_INITIAL_OVERLAP, initial_overlaps

    s = load_scene("stacking.column_5")
    ov = initial_overlaps(s)
    assert ov and max(o.depth for o in ov) < 1e-15  # touching, counted, far below the tolerance
    n = np.array([math.sin(math.radians(20.0)), 0.0, math.cos(math.radians(20.0))])
    for sink, ok in ((0.5 * MAX_INITIAL_OVERLAP, True), (2 * MAX_INITIAL_OVERLAP, False)):
        c = (0.1 - sink) * n
        text = ROLLS.replace("position = [0.03420201433256687, 0.0, 0.09396926207859085]",
                             f"position = [{float(c[0])!r}, 0.0, {float(c[2])!r}]")
        p = tmp_path / f"sink_{ok}.toml"
        p.write_text(text)
        if ok:
            assert initial_overlaps(load_scene(p))[0].depth == pytest.approx(sink, rel=1e-6)
        else:
            with pytest.raises(SpecError, match="the start is buried"):
                load_scene(p)


def test_model_metric_without_reference_says_add_reference(tmp_path):
    """Checks on a model's metrics in a scene without [reference]: one
    error that says which model to add, not one per check listing the
    harness's metrics."""
    text = ROLLS.replace('[reference]\nmodel = "rolling_sphere"\n', "")
    text += '\n[[check]]\nmetric = "max_penetration"\nmax = 0.01\n'
    p = tmp_path / "noref.toml"
    p.write_text(text)
    with pytest.raises(SpecError) as exc:
        load_scene(p)
    errs = exc.value.errors
    assert len(errs) == 1, errs
    assert errs[0].startswith(f"{p}: reference: 'roll_accel_error', 'spin_accel_error', 'rolling_slip' "
                              f"(scenario.primary_metric, check[0].metric, check[1].metric, check[2].metric) are "
                              f"metrics of a reference model, and the scene has none: add [reference] model = "), errs
    # every model producing all three, named
    assert errs[0].endswith("add [reference] model = 'rolling_cylinder' (or one of rolling_resistance, "
                            "rolling_sphere) (physbench models lists them)"), errs
    assert "max_penetration" not in errs[0]  # the harness's metrics are not listed
    # a metric no model and no harness code produces keeps its own error, with the list
    p.write_text(ROLLS.replace('metric = "roll_accel_error"', 'metric = "roll_acel_error"'))
    with pytest.raises(SpecError, match=r"check\[0\]\.metric: 'roll_acel_error' is not produced"):
        load_scene(p)


def test_buried_body_pair_names_both_bodies(tmp_path):
    """Two boxes of a column placed 3 mm into each other: the error names
    both bodies, their key paths and the depth (0.003 m, the overlap of
    two aligned boxes along z)."""
    p = tmp_path / "stack.toml"
    p.write_text("""
[scenario]
family = "t"
title = "two boxes"
duration = 0.1
dt = 0.01
effects = ["gravity", "contact"]
[[body]]
name = "low"
shape = "box"
half_extents = [0.1, 0.1, 0.05]
mass = 1.0
position = [0.0, 0.0, 0.05]
[[body]]
name = "high"
shape = "box"
half_extents = [0.1, 0.1, 0.05]
mass = 1.0
position = [0.0, 0.0, 0.147]
[[static]]
shape = "plane"
normal = [0.0, 0.0, 1.0]
""")
    with pytest.raises(SpecError) as exc:
        load_scene(p)
    (err,) = exc.value.errors
    assert err.startswith(f"{p}: body[0].position: the start is buried: body 'low' (body[0].position) overlaps "
                          f"body 'high' (body[1].position) by 0.003 m, deeper than"), err
