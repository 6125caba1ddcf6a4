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
