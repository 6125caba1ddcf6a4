"""pybullet joints: the scene's ``[[joint]]`` tables as ``createConstraint``
constraints between the bodies' bases (maximal coordinates: each body keeps
its six degrees of freedom and the solver's constraint rows hold it; not a
``createMultiBody`` link tree).

What pybullet 3.2.7 offers, measured (tests/test_joints_engines.py):

- Between two ``btRigidBody`` (the adapter's default,
  ``maximal_coordinates = true``) ``createConstraint`` builds
  ``JOINT_POINT2POINT`` (btPoint2PointConstraint), ``JOINT_FIXED`` and
  ``JOINT_GEAR`` only; ``JOINT_PRISMATIC`` and ``JOINT_REVOLUTE`` fail, and
  so does any constraint to the world (child -1).  A joint to the world is
  therefore made to one massless, shapeless rigid body at the world origin
  (the world anchor).
- Between ``btMultiBody`` bases (``maximal_coordinates = false``)
  point2point, fixed and prismatic (btMultiBodySliderConstraint) build, the
  world included; ``JOINT_REVOLUTE`` fails there too.

Per kind:

spherical  one point2point constraint at the anchor.
revolute   pybullet has no revolute constraint: the hinge is two point2point
           constraints at ``anchor -+ h axis``, h the body's bounding radius
           (:data:`HINGE_HALF_SPAN`): together they hold the anchor and the
           axis (one of their six rows, the one along the axis, is
           redundant; the sequential-impulse solver shares it).
fixed      ``JOINT_FIXED`` with both frames set to the world frame at the
           start (frame orientations = the inverse of each side's starting
           orientation), so the relative pose of the start is held.
prismatic  ``JOINT_PRISMATIC`` with the axis in the body's frame, between
           multibody bases only: with ``maximal_coordinates = true`` a
           prismatic joint is unsupported with that reason.

The constraint error is corrected by the solver's ``erp`` (setting).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.base import Unsupported
from physbench.contract.rotation import wxyz_to_xyzw
from physbench.contract.scene import Scene

#: the kinds this module builds (prismatic needs maximal_coordinates = false)
JOINT_KINDS = frozenset({"revolute", "spherical", "prismatic", "fixed"})

#: a hinge's two points lie this many bounding radii of its body either
#: side of the anchor along the axis
HINGE_HALF_SPAN = 1.0

PRISMATIC_MAXIMAL_REASON = ("joints: pybullet createConstraint has no prismatic joint between maximal-coordinate "
                            "rigid bodies (JOINT_PRISMATIC fails on btRigidBody in pybullet 3.2.7); set "
                            "maximal_coordinates = false to build it between btMultiBody bases")


def prismatic_reason(scene: Scene, maximal: bool) -> str | None:
    """Why a scene's joints cannot be built at this setting, or None."""
    if maximal and any(j.kind == "prismatic" for j in scene.joints):
        return PRISMATIC_MAXIMAL_REASON
    return None


def _v(a: Any) -> list[float]:
    return [float(c) for c in a]


def add_joints(p: Any, cid: int, scene: Scene, ids: list[int], maximal: bool,
               notes: list[str], info: dict[str, Any]) -> list[int]:
    """Create every joint of ``scene`` between the bodies ``ids`` (pybullet
    unique ids in body order) at their starting poses; returns the
    constraint ids.  Raises :class:`Unsupported` for a prismatic joint in
    maximal coordinates."""
    why = prismatic_reason(scene, maximal)
    if why:
        raise Unsupported(why)
    world = -1
    if maximal and any(j.other < 0 for j in scene.joints):
        world = p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=-1, basePosition=[0.0, 0.0, 0.0],
                                  useMaximalCoordinates=True, physicsClientId=cid)
    out: list[int] = []

    def make(j: Any, kind: int, a_body: np.ndarray, a_other: np.ndarray, **kw: Any) -> None:
        other = world if j.other < 0 else ids[j.other]
        c = p.createConstraint(ids[j.body], -1, other, -1, kind, kw.pop("axis", [0.0, 0.0, 0.0]),
                               _v(a_body), _v(a_other), physicsClientId=cid, **kw)
        if c < 0:
            raise RuntimeError(f"pybullet rejected joint {j.name!r}")
        out.append(c)

    def frame(i: int) -> list[float]:
        # inverse of side i's starting orientation (xyzw): its joint frame is the world frame at the start
        if i < 0:
            return [0.0, 0.0, 0.0, 1.0]
        q = np.asarray(scene.bodies[i].orientation, float) * np.array([1.0, -1.0, -1.0, -1.0])
        return _v(wxyz_to_xyzw(q))

    hinges = 0
    for j in scene.joints:
        if j.kind == "spherical":
            make(j, p.JOINT_POINT2POINT, j.anchor_body, j.anchor_other)
        elif j.kind == "revolute":
            h = HINGE_HALF_SPAN * scene.bodies[j.body].bounding_radius
            for s in (-h, h):
                make(j, p.JOINT_POINT2POINT, j.anchor_body + s * j.axis_body, j.anchor_other + s * j.axis_other)
            hinges += 1
        elif j.kind == "fixed":
            make(j, p.JOINT_FIXED, j.anchor_body, j.anchor_other,
                 parentFrameOrientation=frame(j.body), childFrameOrientation=frame(j.other))
        else:  # prismatic, multibody bases
            make(j, p.JOINT_PRISMATIC, j.anchor_body, j.anchor_other, axis=_v(j.axis_body),
                 parentFrameOrientation=frame(j.body), childFrameOrientation=frame(j.other))
    if hinges:
        notes.append(f"revolute joints: pybullet has no revolute constraint; each hinge is two point2point "
                     f"constraints {HINGE_HALF_SPAN:g} bounding radius either side of the anchor along the axis")
    info["joints"] = {"form": "createConstraint (maximal)", "constraints": len(out),
                      "world_anchor": world >= 0}
    return out
