"""[[joint]] in the spec: validation errors name the key path, the compiled
Joint stores the anchor and axis in each side's frame, and an adapter
without joints reports the scene unsupported with the reason."""

import math

import numpy as np
import pytest

from physbench.adapters.base import NO_JOINTS_REASON, get_adapter
from physbench.contract.rotation import quat_to_matrix
from physbench.contract.scene import load_scene
from physbench.contract.spec import SpecError

CHAIN = """
[scenario]
family = "joints"
title = "t"
duration = 1.0
dt = 0.01
planar = {planar}
effects = {effects}

[[body]]
name = "a"
shape = "capsule"
radius = 0.05
half_length = 0.2
mass = 1.0
position = [0.0, 0.0, 1.0]
orientation = {orient}

[[body]]
name = "link"
shape = "capsule"
radius = 0.05
half_length = 0.2
mass = 1.0
pattern = {{ kind = "column", count = 2, gap = 0.1 }}
position = [0.0, 0.0, 2.0]
"""

JOINT = """
[[joint]]
kind = "{kind}"
body = "{body}"
other = "{other}"
anchor = {anchor}
{axis}
"""


def _write(tmp_path, joints=(), planar="false", effects='["gravity", "joint"]', orient="[1.0, 0.0, 0.0, 0.0]",
           extra=""):
    text = CHAIN.format(planar=planar, effects=effects, orient=orient)
    for j in joints:
        d = {"kind": "revolute", "body": "a", "other": "world", "anchor": "[0.0, 0.0, 1.25]",
             "axis": "axis = [0.0, 1.0, 0.0]"}
        d.update(j)
        text += JOINT.format(**d)
    p = tmp_path / "s.toml"
    p.write_text(text + extra)
    return p


def _error(path) -> str:
    with pytest.raises(SpecError) as e:
        load_scene(path)
    return str(e.value)


def test_joint_compiles_with_local_anchor_and_axis(tmp_path):
    q = [math.cos(0.3), math.sin(0.3), 0.0, 0.0]  # the body turned 0.6 rad about x
    p = _write(tmp_path, [{"body": "a", "other": "link_0", "anchor": "[0.0, 0.1, 1.2]",
                           "axis": "axis = [0.0, 0.0, 2.0]"}], orient=str(q))
    s = load_scene(p)
    (j,) = s.joints
    assert (j.name, j.kind, j.body, j.other) == ("joint_0", "revolute", 0, 1)
    np.testing.assert_allclose(j.axis, [0.0, 0.0, 1.0])  # normalised
    R = quat_to_matrix(np.array(q))
    # the body-frame anchor and axis carried back by the body's pose are the world ones
    np.testing.assert_allclose(s.bodies[0].position + R @ j.anchor_body, [0.0, 0.1, 1.2], atol=1e-15)
    np.testing.assert_allclose(R @ j.axis_body, [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(s.bodies[1].position + j.anchor_other, [0.0, 0.1, 1.2], atol=1e-15)
    assert "joint_drift" in __import__("physbench.contract.metric_defs", fromlist=["x"]).generic_metrics(s)


def test_content_hash_sees_joints_and_scenes_without_keep_theirs(tmp_path):
    a = load_scene(_write(tmp_path, [{}]))
    b = load_scene(_write(tmp_path, [{"anchor": "[0.0, 0.0, 1.2]"}]))
    assert a.content_hash != b.content_hash
    plain = load_scene(_write(tmp_path, effects='["gravity"]'))
    assert plain.joints == ()
    import dataclasses

    from physbench.contract.scene_model import content_hash
    assert content_hash(dataclasses.replace(a, joints=())) == content_hash(
        dataclasses.replace(plain, effects=a.effects))


@pytest.mark.parametrize("joints, effects, planar, want", [
    # [[joint]] without the effect, and the effect without a joint
    ([{}], '["gravity"]', "false", "joint: the scene has 1 [[joint]] table(s) but 'joint' is not in scenario.effects"),
    ([], '["gravity", "joint"]', "false", "scenario.effects: 'joint' listed but there is no [[joint]] table"),
    # zero-length axis
    ([{"axis": "axis = [0.0, 0.0, 0.0]"}], None, "false", "joint[0].axis"),
    # a joint between a body and itself
    ([{"other": "a"}], None, "false", "joint[0].other: a joint between a body and itself"),
    # an unknown body, and a pattern name beyond the pattern's count
    ([{"body": "ghost"}], None, "false", "joint[0].body: unknown body 'ghost'"),
    ([{"other": "link_7", "anchor": "[0.0, 0.0, 1.2]"}], None, "false", "joint[0].other: unknown body 'link_7'"),
    # an anchor far from both bodies (a is at z = 1, link_0 at z = 2; bounding radius 0.25)
    ([{"other": "link_0", "anchor": "[3.0, 0.0, 1.5]"}], None, "false", "joint[0].anchor: [3.0, 0.0, 1.5] is far from both"),
    # a body named twice in one fixed chain: a -- link_0 -- link_1 -- a
    ([{"kind": "fixed", "axis": "", "other": "link_0", "anchor": "[0.0, 0.0, 1.25]"},
      {"kind": "fixed", "axis": "", "body": "link_0", "other": "link_1", "anchor": "[0.0, 0.0, 2.3]"},
      {"kind": "fixed", "axis": "", "body": "link_1", "other": "a", "anchor": "[0.0, 0.0, 1.25]"}],
     None, "false", "joint[2].body: 'link_1' is named twice in one fixed chain"),
    # ... world included: a and link_0 fixed to the world, then to each other
    ([{"kind": "fixed", "axis": ""}, {"kind": "fixed", "axis": "", "body": "link_0", "anchor": "[0.0, 0.0, 2.0]"},
      {"kind": "fixed", "axis": "", "other": "link_0", "anchor": "[0.0, 0.0, 1.25]"}],
     None, "false", "joint[2].body: 'a' is named twice in one fixed chain"),
    # axis rules per kind
    ([{"axis": ""}], None, "false", "joint[0]: a revolute joint needs axis"),
    ([{"kind": "spherical"}], None, "false", "joint[0]: a spherical joint takes no axis"),
    ([{"kind": "wobbly"}], None, "false", "joint[0].kind: unknown joint kind 'wobbly'"),
    # planar: revolute about y, prismatic in x-z, anchor at y = 0, no spherical
    ([{"axis": "axis = [1.0, 0.0, 0.0]"}], None, "true", "joint[0].axis: a planar scene turns about y only"),
    ([{"kind": "prismatic", "axis": "axis = [0.0, 1.0, 0.0]"}], None, "true",
     "joint[0].axis: a planar scene lies in the x-z plane, so a slide axis must have y = 0"),
    ([{"anchor": "[0.0, 0.1, 1.25]"}], None, "true", "joint[0].anchor: a planar scene lies in the x-z plane"),
    ([{"kind": "spherical", "axis": ""}], None, "true", "joint[0].kind: a planar scene turns about y only"),
])
def test_joint_errors_name_the_key(tmp_path, joints, effects, planar, want):
    p = _write(tmp_path, joints, planar=planar, effects=effects or '["gravity", "joint"]')
    msg = _error(p)
    assert want in msg, msg
    assert "s.toml" in msg


def test_phases_and_perturbation_refuse_joints(tmp_path):
    p = _write(tmp_path, [{}], extra='\n[perturbation]\nposition = 0.001\n')
    assert "perturbation: perturbed starts would pull the joints apart" in _error(p)
    text = p.read_text().replace("\n[perturbation]\nposition = 0.001\n", "").replace("dt = 0.01", "dt = 0.01\nphases = 4")
    p.write_text(text)
    assert "scenario.phases: step phases shift a start in free flight" in _error(p)


def test_planar_accepts_hinge_about_y_and_slider_in_xz(tmp_path):
    s = load_scene(_write(tmp_path, [{"axis": "axis = [0.0, -1.0, 0.0]"},
                                     {"kind": "prismatic", "body": "link_0", "anchor": "[0.0, 0.0, 2.0]",
                                      "axis": "axis = [0.6, 0.0, 0.8]"}], planar="true"))
    assert [j.kind for j in s.joints] == ["revolute", "prismatic"]


def test_joint_to_world_may_hang_far_from_its_pivot(tmp_path):
    """A bob on a massless rod: the world is everywhere, so no reach limit."""
    s = load_scene(_write(tmp_path, [{"anchor": "[0.0, 0.0, 9.0]"}]))
    assert s.joints[0].anchor[2] == 9.0


@pytest.mark.parametrize("engine", ["reference", "mujoco", "pybullet", "pymunk", "rapier", "box2d"])
def test_engines_without_joints_say_so(tmp_path, engine):
    """Never a silently dropped joint: an adapter that builds none is
    unsupported with the reason (or unavailable altogether)."""
    try:
        cls = get_adapter(engine)
    except Exception as e:  # an adapter that is not registered here is not this test's subject
        pytest.skip(f"{engine}: {e}")
    s = load_scene(_write(tmp_path, [{}], planar="true" if engine in ("pymunk", "box2d") else "false"))
    caps = cls.capabilities()
    why = cls.unsupported_reason(s)
    if not caps.available:
        assert why is not None and "not available" in why
    elif "joint" not in caps.effects:
        assert why == NO_JOINTS_REASON
    else:
        assert why is None or "joint" in why
