"""Rapier joints: the scene's ``[[joint]]`` tables as Rapier generic joints,
in one of the two forms Rapier offers (setting ``joints``):

- ``impulse`` (default): ``ImpulseJointSet``, maximal coordinates: every
  body keeps six degrees of freedom and the TGS-soft solver's joint rows
  hold it (any graph: trees and loops).
- ``multibody``: ``MultibodyJointSet``, reduced coordinates (Featherstone):
  each joint nests its ``body`` under ``other`` in an articulation rooted
  at a fixed body, so the joint holds by construction.  Trees only: a body
  held by two joints, or joints closing a loop, is unsupported.

Every joint is a ``GenericJoint`` with both local frames given explicitly:
one world frame per joint, its origin at the anchor and its x axis along
the joint axis (revolute: the hinge, prismatic: the slide; the identity for
spherical and fixed), written in each side's frame at the start
(``other`` is Rapier's body 1, ``body`` its body 2; a fixed body at the
origin stands for the world).  So the starting pose satisfies the joint
exactly, whatever the bodies' orientations (Rapier's typed builders derive
the frames from the axes alone, which leaves the twist about the axis to
chance).  Locked axes: Rapier's LOCKED_REVOLUTE_AXES (free: angular x),
LOCKED_PRISMATIC_AXES (free: linear x), LOCKED_SPHERICAL_AXES,
LOCKED_FIXED_AXES.  Contacts between jointed bodies are off (Rapier's
default), no limits or motors.

Multibody starts: Rapier gives every multibody degree of freedom a joint
damping of 0.1 and a generalized velocity of 0, whatever the bodies'
velocities; the adapter sets the damping to 0 and each joint's rate from
the scene's starting velocities (revolute: the relative angular velocity
along the axis; prismatic: the relative anchor velocity along the axis;
spherical: the relative angular velocity in the joint frame, world-aligned at the start), and
refuses a start the joint cannot carry (a motion the joint does not allow
would be dropped silently).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.joint_rates import closes_loop, held_twice, start_rate
from physbench.contract.rotation import quat_to_matrix
from physbench.contract.scene import Scene

#: the kinds this module builds
JOINT_KINDS = frozenset({"revolute", "spherical", "prismatic", "fixed"})

_LOCKED = {"revolute": "LOCKED_REVOLUTE_AXES", "prismatic": "LOCKED_PRISMATIC_AXES",
           "spherical": "LOCKED_SPHERICAL_AXES", "fixed": "LOCKED_FIXED_AXES"}


def tree_reason(scene: Scene) -> str | None:
    """Why the multibody form cannot hold the scene's joints, or None."""
    twice = held_twice(scene)
    if twice:
        b, k0, k1 = twice
        return (f"joints: Rapier multibody joints build a tree, each body the 'body' of one joint; "
                f"{scene.bodies[b].name!r} is that of joint[{k0}] and joint[{k1}] "
                f"(setting joints = impulse builds it)")
    if closes_loop(scene):
        return "joints: Rapier multibody joints build a tree; the joints close a loop (setting joints = impulse)"
    return None


def _frame(axis: np.ndarray | None) -> np.ndarray:
    """A world rotation matrix (3, 3) whose first column is ``axis`` (the
    identity without one)."""
    if axis is None:
        return np.eye(3)
    x = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.eye(3)[int(np.argmin(np.abs(x)))]
    y = np.cross(x, t)
    y /= np.linalg.norm(y)
    return np.column_stack([x, y, np.cross(x, y)])


def _quat(m: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (m[j, i] + m[i, j]) / s
        v[k] = (m[k, i] + m[i, k]) / s
        q = ((m[k, j] - m[j, k]) / s, v[0], v[1], v[2])
    q = np.asarray(q, float)
    q /= np.linalg.norm(q)
    return tuple(float(c) for c in q)  # type: ignore[return-value]


def add_joints(rp: Any, world: Any, scene: Scene, handles: list[Any], form: str, notes: list[str],
               info: dict[str, Any]) -> int:
    """Insert every joint of ``scene`` between the rigid bodies ``handles``
    (body order, at their starting poses) into the world's impulse or
    multibody joint set (``form``); returns the number inserted.  Raises
    ValueError when Rapier refuses a multibody joint."""
    ground = None
    if any(j.other < 0 for j in scene.joints):
        ground = world.add_body(rp.RigidBodyBuilder(rp.RigidBodyType.FIXED), [])

    def rot(i: int) -> np.ndarray:
        return np.eye(3) if i < 0 else quat_to_matrix(np.asarray(scene.bodies[i].orientation, float))

    # multibody: parents before children (Rapier attaches a link to an existing articulation)
    order = list(scene.joints)
    if form == "multibody":
        depth = {}
        parent = {j.body: j.other for j in scene.joints}
        for j in order:
            d, i = 0, j.other
            while i >= 0:
                d, i = d + 1, parent.get(i, -1)
            depth[j.index] = d
        order.sort(key=lambda j: depth[j.index])
    n = 0
    for j in order:
        rw = _frame(j.axis)
        frames = []
        for i, a in ((j.other, j.anchor_other), (j.body, j.anchor_body)):
            frames.append(rp.Isometry3(tuple(float(c) for c in a), rp.Rotation3(*_quat(rot(i).T @ rw))))
        joint = rp.GenericJoint.builder(getattr(rp.JointAxesMask, _LOCKED[j.kind]), local_frame1=frames[0],
                                        local_frame2=frames[1], contacts_enabled=False).build()
        h1 = ground if j.other < 0 else handles[j.other]
        h2 = handles[j.body]
        if form == "multibody":
            if world.multibody_joints.insert(h1, h2, joint, True) is None:
                raise ValueError(f"joints: Rapier refused joint {j.name!r} as a multibody link")
        else:
            world.impulse_joints.insert(h1, h2, joint, True)
        n += 1
    if form == "multibody":
        _start_multibody(world, scene, handles)
    notes.append(f"joints: Rapier generic joints with explicit frames, {form} form "
                 f"({'maximal coordinates, solver rows' if form == 'impulse' else 'reduced coordinates'})")
    info["joints"] = {"form": form, "joints": n}
    return n


def _start_multibody(world: Any, scene: Scene, handles: list[Any]) -> None:
    """Zero Rapier's default multibody joint damping and set each joint's
    rate from the starting velocities; :class:`Unsupported` when a body
    starts with a motion its joint does not allow."""
    mj = world.multibody_joints
    rates: dict[Any, dict[int, list[float]]] = {}
    for j in scene.joints:
        q = [float(c) for c in start_rate(scene, j, "Rapier's multibody form")]  # spherical: world = joint frame
        link = mj.rigid_body_link(handles[j.body])
        mb = mj.get_multibody(link.multibody)
        rates.setdefault(link.multibody, {})[mb.get_link(link.id).assembly_id] = q
    for index, by_link in rates.items():
        mb = mj.get_multibody(index)
        mb.set_damping([0.0] * mb.ndofs)
        v = [0.0] * mb.ndofs
        for start, q in by_link.items():
            v[start:start + len(q)] = q
        mb.set_generalized_velocity(v)
