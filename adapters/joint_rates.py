"""What the adapters that build joints in reduced coordinates (pybullet
links, Rapier multibody, Drake) share: whether the joints form a tree
(:func:`held_twice`, :func:`closes_loop`), and a joint's starting rate
from the scene's starting velocities.  In reduced coordinates a body's velocity is its parent's plus the
joint's own motion, so the scene's velocities must be such a motion and
become the joint's rate.  A start the joint cannot carry is
:class:`Unsupported` (it would be dropped silently otherwise).
tests/test_joints_engines.py::test_reduced_forms_start_with_the_scene_velocities
pins it (a rotated, spinning ball-jointed body reads back its velocities).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.base import Unsupported
from physbench.contract.scene import Scene

#: relative tolerance of a start's consistency with its joint (of 1 + |v| + |w|)
START_TOLERANCE = 1e-9


def start_rate(scene: Scene, j: Any, engine: str) -> np.ndarray:
    """Joint ``j``'s starting rate: revolute (1,) (w_b - w_o) . axis;
    prismatic (1,) the body's velocity relative to the other's material
    point, along the axis; spherical (3,) the relative angular velocity
    w_b - w_o in world coordinates (each adapter expresses it in its joint
    frame); fixed (0,).  Units rad/s or m/s.  Raises Unsupported naming
    ``engine`` when the body's starting velocity is not the other's plus
    that motion."""

    def state(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if i < 0:
            return np.zeros(3), np.zeros(3), np.zeros(3)
        b = scene.bodies[i]
        return (np.asarray(b.position, float), np.asarray(b.velocity, float),
                np.asarray(b.angular_velocity, float))

    xo, vo, wo = state(j.other)
    xb, vb, wb = state(j.body)
    a = np.asarray(j.anchor, float)
    va = vo + np.cross(wo, a - xo)  # the other's material point at the anchor
    if j.kind == "revolute":
        q = np.array([float(np.dot(wb - wo, j.axis))])
        w_exp = wo + q[0] * j.axis
        v_exp = va + np.cross(w_exp, xb - a)
    elif j.kind == "prismatic":
        carried = vo + np.cross(wo, xb - xo)
        q = np.array([float(np.dot(vb - carried, j.axis))])
        w_exp, v_exp = wo, carried + q[0] * j.axis
    elif j.kind == "spherical":
        q = wb - wo
        w_exp, v_exp = wb, va + np.cross(wb, xb - a)
    else:  # fixed
        q = np.zeros(0)
        w_exp, v_exp = wo, vo + np.cross(wo, xb - xo)
    scale = 1.0 + float(np.linalg.norm(vb)) + float(np.linalg.norm(wb))
    if (np.linalg.norm(w_exp - wb) > START_TOLERANCE * scale
            or np.linalg.norm(v_exp - vb) > START_TOLERANCE * scale):
        raise Unsupported(f"joints: body {scene.bodies[j.body].name!r} starts with a motion its {j.kind} joint "
                          f"does not allow ({engine} carries the joint's own motion only)")
    return q


def held_twice(scene: Scene) -> tuple[int, int, int] | None:
    """(body, first joint, second joint) of the first body that is the
    ``body`` of two joints, or None: a tree holds each body by one joint."""
    held: dict[int, int] = {}
    for k, j in enumerate(scene.joints):
        if j.body in held:
            return j.body, held[j.body], k
        held[j.body] = k
    return None


def closes_loop(scene: Scene) -> bool:
    """Whether following each joint's ``body`` to its ``other`` comes back
    to a body already passed (the joints close a loop)."""
    parent = {j.body: j.other for j in scene.joints}
    for start in parent:
        seen, i = set(), start
        while i >= 0 and i in parent:
            if i in seen:
                return True
            seen.add(i)
            i = parent[i]
    return False
