"""pymunk joints: a planar scene's ``[[joint]]`` tables as Chipmunk
constraints (maximal coordinates: each body keeps its three planar degrees
of freedom and the solver's impulses hold the joint).

The planar mapping is the adapter's (:mod:`adapters.pymunk`): a
body-frame point (x, y, z) is the 2D body-local (x, z), a world point the
same on the space's static body (at the origin, angle 0).  The spec allows
a planar scene revolute joints about y and prismatic joints in x-z only
(contract/scene.py), so every joint below is a planar one.

revolute   ``PivotJoint`` at the anchor (a hinge about y is a pivot in 2D).
prismatic  ``GrooveJoint``: a groove on ``other`` through the anchor along
           the axis, :data:`GROOVE_HALF_LENGTH` either side, the body's
           anchor held in it, plus a ``RotaryLimitJoint`` with min = max =
           the starting relative angle (a slider does not turn).
fixed      ``PivotJoint`` plus the same ``RotaryLimitJoint`` (no GearJoint:
           Chipmunk's gear holds a velocity ratio and corrects the angle
           with the same bias, the limit joint states the invariant).
spherical  not planar (the spec refuses it in a planar scene).

Every constraint keeps Chipmunk's defaults: infinite ``max_force``,
``error_bias`` = (1 - 0.1)^60 (the fraction of a joint error left after one
second) and ``max_bias`` infinite.
"""

from __future__ import annotations

from typing import Any

from physbench.contract.conventions import world_point_to_planar
from physbench.contract.scene import Scene

#: the kinds this module builds
JOINT_KINDS = frozenset({"revolute", "prismatic", "fixed"})

#: half length (m) of a prismatic joint's groove either side of its anchor:
#: far beyond any physbench scene, so the groove's ends never act
GROOVE_HALF_LENGTH = 1.0e3


def add_joints(pm: Any, space: Any, scene: Scene, bodies: list[Any], notes: list[str],
               info: dict[str, Any]) -> int:
    """Add every joint of ``scene`` between ``bodies`` (pymunk bodies in body
    order, at their starting poses) to ``space``; returns the number of
    Chipmunk constraints added."""
    n = 0

    def side(i: int) -> Any:
        return space.static_body if i < 0 else bodies[i]

    def lock(a: Any, b: Any) -> None:
        nonlocal n
        rel = b.angle - a.angle
        space.add(pm.RotaryLimitJoint(a, b, rel, rel))
        n += 1

    for j in scene.joints:
        b, o = side(j.body), side(j.other)
        ab, ao = world_point_to_planar(j.anchor_body), world_point_to_planar(j.anchor_other)
        if j.kind in ("revolute", "fixed"):
            space.add(pm.PivotJoint(o, b, ao, ab))
            n += 1
            if j.kind == "fixed":
                lock(o, b)
        elif j.kind == "prismatic":
            ux, uy = world_point_to_planar(j.axis_other)
            L = GROOVE_HALF_LENGTH
            space.add(pm.GrooveJoint(o, b, (ao[0] - L * ux, ao[1] - L * uy), (ao[0] + L * ux, ao[1] + L * uy), ab))
            n += 1
            lock(o, b)
        else:  # pragma: no cover - the spec refuses it in planar scenes
            raise ValueError(f"pymunk: a {j.kind} joint is not planar")
    notes.append("joints: Chipmunk constraints (PivotJoint; GrooveJoint + RotaryLimitJoint for prismatic; "
                 "PivotJoint + RotaryLimitJoint for fixed), Chipmunk's default error_bias")
    info["joints"] = {"form": "Chipmunk constraints (maximal)", "constraints": n}
    return n
