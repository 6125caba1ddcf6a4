"""``[[joint]] chain``: one table joins a row or column pattern of bodies
link to link, so the chain's length is the pattern's count, a spec key
(``body[k].pattern.count``) that variants, --set and breaking-point
searches vary; its errors name the key path (exit 2)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from physbench.contract.scene import load_scene
from physbench.contract.spec import SpecError
from physbench.contract.spec.schema import integer_key
from physbench.harness.limit_eval import load_at
from physbench.harness.limits import LimitRequest, validate_request

SPEC = """
[scenario]
family = "joints"
title = "t"
duration = 1.0
dt = 0.01
planar = {planar}
effects = ["gravity", "joint"]

[[body]]
name = "link"
shape = "sphere"
radius = 0.04
mass = 0.1
position = [0.05, 0.0, 2.0]
pattern = {{ kind = "{kind}", count = {count}, spacing = 0.1 }}

[[body]]
name = "lone"
shape = "sphere"
radius = 0.04
mass = 0.1
position = [-0.5, 0.0, 2.0]

[[joint]]
{joint}
kind = "revolute"
other = "{other}"
anchor = [0.0, 0.0, 2.0]
axis = [0.0, 1.0, 0.0]
"""

EXTRA = """
[[joint]]
kind = "revolute"
body = "lone"
other = "world"
anchor = [-0.5, 0.0, 2.05]
axis = [0.0, 1.0, 0.0]
"""


def _write(tmp_path, joint='chain = "link"', kind="row", count=5, other="world", planar="true", extra=""):
    p = tmp_path / "chain.toml"
    p.write_text(SPEC.format(joint=joint, kind=kind, count=count, other=other, planar=planar) + extra)
    return p


def test_chain_makes_one_joint_per_link(tmp_path):
    s = load_scene(_write(tmp_path, extra=EXTRA))
    links = [b for b in s.bodies if b.name.startswith("link_")]
    assert len(links) == 5 and len(s.joints) == 6
    for i, j in enumerate(s.joints[:5]):
        # link i hangs from link i-1 (link 0 from the world) at the midpoint 0.1 i m along x
        assert (j.kind, j.body, j.other) == ("revolute", links[i].index, -1 if i == 0 else links[i - 1].index)
        np.testing.assert_allclose(j.anchor, [0.1 * i, 0.0, 2.0], rtol=0, atol=1e-15)
        np.testing.assert_allclose(j.anchor_body, [-0.05, 0.0, 0.0], rtol=0, atol=1e-15)  # 5 cm behind its centre
        other_side = [0.0, 0.0, 2.0] if i == 0 else [0.05, 0.0, 0.0]  # the world's point, or 5 cm ahead
        np.testing.assert_allclose(j.anchor_other, other_side, rtol=0, atol=1e-15)
        np.testing.assert_allclose(j.axis_body, [0.0, 1.0, 0.0])
    # default names count the joints made: the table after the chain gets its own
    assert [j.name for j in s.joints] == [f"joint_{i}" for i in range(6)]
    assert s.joints[5].body == s.bodies[[b.name for b in s.bodies].index("lone")].index
    named = load_scene(_write(tmp_path, joint='name = "hinge"\nchain = "link"'))
    assert [j.name for j in named.joints] == [f"hinge_{i}" for i in range(5)]


def test_column_chain_hangs_from_a_body(tmp_path):
    p = _write(tmp_path, kind="column", count=3, other="lone", planar="false")
    text = p.read_text().replace('position = [-0.5, 0.0, 2.0]', 'position = [0.05, 0.0, 1.95]')
    p.write_text(text.replace("anchor = [0.0, 0.0, 2.0]", "anchor = [0.05, 0.0, 1.975]"))
    s = load_scene(p)
    lone = [b.name for b in s.bodies].index("lone")
    assert [(j.body, j.other) for j in s.joints] == [(0, lone), (1, 0), (2, 1)]
    np.testing.assert_allclose([j.anchor for j in s.joints],
                               [[0.05, 0.0, 1.975 + 0.1 * i] for i in range(3)], rtol=0, atol=1e-15)


@pytest.mark.parametrize("n", [10, 30])
def test_chain_scenarios_are_the_chains_they_were(n):
    """joints.chain_10 and chain_30 are written as one chain table: the
    joints are those of the per-link tables they replaced (link i to link
    i-1 at (0.1 i, 0, 2), link 0 to the world), to rounding."""
    s = load_scene(f"joints.chain_{n}")
    assert len(s.joints) == n == s.n_bodies
    for i, j in enumerate(s.joints):
        assert (j.name, j.kind, j.body, j.other) == (f"joint_{i}", "revolute", i, i - 1 if i else -1)
        np.testing.assert_allclose(j.anchor, [0.1 * i, 0.0, 2.0], rtol=0, atol=1e-15)
        np.testing.assert_allclose(j.anchor_body, [-0.05, 0.0, 0.0], rtol=0, atol=1e-15)


def test_chain_length_is_the_pattern_count():
    s = load_scene("joints.chain_10", overrides={"body[0].pattern.count": 4})
    assert s.n_bodies == 4 and len(s.joints) == 4
    # a breaking-point search over the count sets whole numbers (the range's floats too)
    req = LimitRequest("joints.chain_10", None, "reference", "body[0].pattern.count", 2.0, 60.0)
    assert validate_request(req) == []
    assert len(load_at(req, 7.0).joints) == 7
    bad = LimitRequest("joints.chain_10", None, "reference", "body[0].pattern.count", 2.5, 60.0)
    errs = validate_request(bad)
    assert len(errs) == 1 and errs[0].startswith("--param body[0].pattern.count = 2.5: ") and "count" in errs[0]


def test_integer_spec_keys():
    assert integer_key("body[0].pattern.count") and integer_key("body.3.pattern.count")
    assert integer_key("scenario.phases")
    for k in ("body[1].mass", "dt", "scenario.duration", "body[0].velocity[0]", "material.default.friction",
              "body[0].pattern", "nope.x", "body[0].pattern.count.x", "]["):
        assert not integer_key(k), k


def test_limit_search_over_the_chain_length_steps_in_whole_numbers():
    from physbench.harness.limit_eval import EVAL_ROW, run_search

    seen = []

    def evaluate(req, limit_id, value, phase):
        seen.append(value)
        ok = value <= 17
        return {"row_kind": EVAL_ROW, "point_key": req.eval_key(limit_id, value, phase), "limit_id": limit_id,
                "limit_value": value, "phase": phase, "limit_holds": ok, "limit_reason": "" if ok else "past",
                "limit_cpu_s": 0.0, "status": "ok"}

    req = LimitRequest("joints.chain_10", None, "reference", "body[0].pattern.count", 2.0, 60.0)
    res, summary = run_search(req, lambda row: None, {}, evaluate)
    assert all(float(v).is_integer() for v in seen)
    assert res.limit == 17 and res.bracket == (17, 18)


@pytest.mark.parametrize("joint, kind, other, want", [
    ('chain = "ghost"', "row", "world",
     "joint[0].chain: expected the name of a [[body]] with a pattern (its bodies are the links), got 'ghost' "
     "(no [[body]]); patterned bodies: ['link']"),
    ('chain = "lone"', "row", "world",
     "joint[0].chain: expected the name of a [[body]] with a pattern (its bodies are the links), got 'lone' "
     "(a [[body]] without a pattern); patterned bodies: ['link']"),
    ('chain = "link"', "pyramid", "world",
     "joint[0].chain: body 'link' has a 'pyramid' pattern; a chain runs along a 'row' or a 'column' "
     "(link i next to link i-1)"),
    ('chain = "link"', "row", "link_2",
     "joint[0].other: 'link_2' is a link of the chain 'link' itself; expected 'world' or another body's name"),
    ('chain = "link"\nbody = "lone"', "row", "world",
     "joint[0]: give body or chain, not both (body = 'lone', chain = 'link')"),
    ("", "row", "world", "joint[0]: a joint needs body = <a body's name> (or chain = <a patterned body's name>)"),
    # hung from a body, its first link's anchor is checked as any two-body joint's
    ('chain = "link"', "row", "lone",
     "joint[0] ('link_0' of chain 'link').anchor: [-0.25, 0.0, 2.0] is far from both bodies (7.5 and 6.25 "
     "bounding radii from the centres of 'link_0' and 'lone'"),
])
def test_chain_errors_name_the_key(tmp_path, joint, kind, other, want):
    p = _write(tmp_path, joint=joint, kind=kind, other=other)
    if other == "lone":
        p.write_text(p.read_text().replace("anchor = [0.0, 0.0, 2.0]", "anchor = [-0.25, 0.0, 2.0]"))
    with pytest.raises(SpecError) as e:
        load_scene(p)
    assert any(line.startswith(f"{p}: {want}") for line in e.value.errors), e.value.errors


def test_bad_chain_exits_2_without_a_traceback(tmp_path):
    p = _write(tmp_path, joint='chain = "ghost"')
    r = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "validate", str(p)], capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "error: chain.toml: joint[0].chain: expected the name of a [[body]] with a pattern" in r.stderr
    assert "Traceback" not in r.stderr
