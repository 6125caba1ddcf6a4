"""Box2D v3 joints: a planar scene's ``[[joint]]`` tables as Box2D joints
(maximal coordinates: soft-step constraint rows in Box2D's solver, each
body keeping its three planar degrees of freedom).

The planar mapping is the adapter's (:mod:`adapters.box2d`): a body-frame
point (x, y, z) is the 2D body-local (x, z) (each body's origin is its
centre of mass: mass data centre (0, 0)), a world point the same on one
static body at the origin.  The spec allows a planar scene revolute joints
about y and prismatic joints in x-z only (contract/scene.py).

revolute   ``RevoluteJoint`` at the anchor, ``reference_angle`` = the
           starting relative angle, no limit, motor or spring.
prismatic  ``PrismaticJoint``: ``local_axis_a`` = the slide axis in
           ``other``'s frame, no limit, motor or spring (Box2D's prismatic
           joint holds the relative angle).
fixed      ``WeldJoint`` with ``linear_hertz`` = ``angular_hertz`` = 0 (rigid,
           not a spring).
spherical  not planar (the spec refuses it in a planar scene).

Box2D softens joints with the world's joint stiffness (b2WorldDef
jointHertz / jointDampingRatio), which pyb2d3 0.11 does not expose: the
engine's default holds.  Jointed bodies do not collide with each other
(``collide_connected`` false, Box2D's default).
"""

from __future__ import annotations

from typing import Any

from physbench.contract.conventions import world_point_to_planar
from physbench.contract.scene import Scene

#: the kinds this module builds
JOINT_KINDS = frozenset({"revolute", "prismatic", "fixed"})


def add_joints(b2: Any, world: Any, scene: Scene, bodies: list[Any], notes: list[str],
               info: dict[str, Any]) -> int:
    """Create every joint of ``scene`` between ``bodies`` (Box2D bodies in
    body order, at their starting poses); returns the number created."""
    ground = None
    if any(j.other < 0 for j in scene.joints):
        ground = world.create_body(b2.body_def(type=b2.BodyType.STATIC, position=(0.0, 0.0)))
    n = 0
    for j in scene.joints:
        a = ground if j.other < 0 else bodies[j.other]  # Box2D's body_a: the side the axis is fixed in
        b = bodies[j.body]
        kw = dict(body_a=a, body_b=b, local_anchor_a=world_point_to_planar(j.anchor_other),
                  local_anchor_b=world_point_to_planar(j.anchor_body), collide_connected=False)
        rel = float(b.angle) - float(a.angle)
        if j.kind == "revolute":
            world.create_revolute_joint(reference_angle=rel, enable_limit=False, enable_motor=False,
                                        enable_spring=False, **kw)
        elif j.kind == "prismatic":
            world.create_prismatic_joint(local_axis_a=world_point_to_planar(j.axis_other), reference_angle=rel,
                                         enable_limit=False, enable_motor=False, enable_spring=False, **kw)
        elif j.kind == "fixed":
            world.create_weld_joint(reference_angle=rel, linear_hertz=0.0, angular_hertz=0.0, **kw)
        else:  # pragma: no cover - the spec refuses it in planar scenes
            raise ValueError(f"box2d: a {j.kind} joint is not planar")
        n += 1
    notes.append("joints: Box2D revolute, prismatic and weld (rigid) joints, softened by Box2D's default world "
                 "joint stiffness (not exposed by pyb2d3)")
    info["joints"] = {"form": "Box2D joints (maximal, soft step)", "joints": n}
    return n

