"""Drake joints: the scene's ``[[joint]]`` tables as MultibodyPlant joints
(reduced coordinates: the plant is a tree of bodies, each joint a
mobilizer, so a joint holds by construction).

Each joint connects a frame F on ``other`` (the world body for the world)
to a frame M on ``body``, both ``FixedOffsetFrame`` s at the anchor, turned
so that they coincide with the world frame at the start (F = R_o^T, M =
R_b^T in the bodies' frames): every joint starts at its zero position and
the joint axis is the scene's world axis in either frame.

revolute   ``RevoluteJoint`` (axis = the hinge)
prismatic  ``PrismaticJoint`` (axis = the slide)
spherical  ``BallRpyJoint`` (roll-pitch-yaw coordinates: singular at a
           pitch of +-90 deg, which a ball joint turning that far meets)
fixed      ``WeldJoint`` (X_FM = identity)

No damping, no limits.  A body with no joint of its own is a free body
(Drake adds its floating joint at Finalize).  The plant is a tree: a body
that is the ``body`` of two joints, or joints closing a loop, is
unsupported.  The starting velocities become joint rates
(:func:`adapters.joint_rates.start_rate`; a ball joint's w_FM is the
relative angular velocity expressed in F, the world frame at the start).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.joint_rates import closes_loop, held_twice, start_rate
from physbench.contract.rotation import quat_to_matrix
from physbench.contract.scene import Scene

#: the kinds this module builds
JOINT_KINDS = frozenset({"revolute", "spherical", "prismatic", "fixed"})


def tree_reason(scene: Scene) -> str | None:
    """Why Drake's tree cannot hold the scene's joints, or None."""
    if scene.joints and (scene.has("drag_linear") or scene.has("drag_quadratic")):
        return "joints: the Drake adapter applies drag to free bodies only"
    twice = held_twice(scene)
    if twice:
        b, k0, k1 = twice
        return (f"joints: Drake's MultibodyPlant is a tree, each body the 'body' of one joint; "
                f"{scene.bodies[b].name!r} is that of joint[{k0}] and joint[{k1}]")
    if closes_loop(scene):
        return "joints: Drake's MultibodyPlant is a tree; the joints close a loop"
    return None


def add_joints(plant: Any, scene: Scene, bodies: list[Any]) -> list[Any]:
    """Add every joint of ``scene`` to ``plant`` (before Finalize) between
    the rigid ``bodies`` (body order); returns the joints in scene order."""
    from pydrake.math import RigidTransform, RotationMatrix
    from pydrake.multibody.tree import (BallRpyJoint, FixedOffsetFrame, PrismaticJoint, RevoluteJoint,
                                        WeldJoint)

    def rot(i: int) -> np.ndarray:
        return np.eye(3) if i < 0 else quat_to_matrix(np.asarray(scene.bodies[i].orientation, float))

    out = []
    for j in scene.joints:
        parent = plant.world_body() if j.other < 0 else bodies[j.other]
        child = bodies[j.body]
        F = plant.AddFrame(FixedOffsetFrame(f"F{j.index}", parent.body_frame(), RigidTransform(
            RotationMatrix(rot(j.other).T), np.asarray(j.anchor_other, float))))
        M = plant.AddFrame(FixedOffsetFrame(f"M{j.index}", child.body_frame(), RigidTransform(
            RotationMatrix(rot(j.body).T), np.asarray(j.anchor_body, float))))
        name = f"j{j.index}"
        if j.kind == "revolute":
            joint = RevoluteJoint(name, F, M, np.asarray(j.axis, float))
        elif j.kind == "prismatic":
            joint = PrismaticJoint(name, F, M, np.asarray(j.axis, float))
        elif j.kind == "spherical":
            joint = BallRpyJoint(name, F, M)
        else:
            joint = WeldJoint(name, F, M, RigidTransform())
        out.append(plant.AddJoint(joint))
    return out


def start_state(plant: Any, ctx: Any, scene: Scene, bodies: list[Any], joints: list[Any]) -> None:
    """The starting state in ``ctx``: free bodies posed and moving as the
    scene says, every joint at zero position with the rate its bodies'
    starting velocities give (Unsupported when a start is not the joint's
    own motion)."""
    from pydrake.common.eigen_geometry import Quaternion
    from pydrake.math import RigidTransform
    from pydrake.multibody.math import SpatialVelocity

    held = {j.body for j in scene.joints}
    for b, body in zip(scene.bodies, bodies):
        if b.index not in held:
            plant.SetFreeBodyPose(ctx, body, RigidTransform(Quaternion(*np.asarray(b.orientation, float)),
                                                           np.asarray(b.position, float)))
            plant.SetFreeBodySpatialVelocity(body, SpatialVelocity(np.asarray(b.angular_velocity, float),
                                                                   np.asarray(b.velocity, float)), ctx)
    for j, joint in zip(scene.joints, joints):
        q = start_rate(scene, j, "Drake's MultibodyPlant")
        if j.kind == "revolute":
            joint.set_angular_rate(ctx, float(q[0]))
        elif j.kind == "prismatic":
            joint.set_translation_rate(ctx, float(q[0]))
        elif j.kind == "spherical":
            joint.set_angular_velocity(ctx, q)


def read_bodies(plant: Any, ctx: Any, bodies: list[Any], pos: np.ndarray, quat: np.ndarray, vel: np.ndarray,
                angvel: np.ndarray) -> None:
    """World pose (n, 3) m and (n, 4) wxyz, velocities (n, 3) m/s and rad/s
    of every body (its origin = centre of mass) from the plant's
    kinematics in ``ctx``."""
    for k, body in enumerate(bodies):
        X = plant.EvalBodyPoseInWorld(ctx, body)
        V = plant.EvalBodySpatialVelocityInWorld(ctx, body)
        pos[k] = X.translation()
        quat[k] = X.rotation().ToQuaternion().wxyz()
        vel[k] = V.translational()
        angvel[k] = V.rotational()
