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

The other form, setting ``joints = links``: :class:`LinkTree`, every body a
link of one ``createMultiBody`` whose fixed base is the world (reduced
coordinates; all four kinds; trees hanging from the world only).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.base import Unsupported
from physbench.adapters.joint_rates import closes_loop, held_twice, start_rate
from physbench.contract.rotation import quat_mul, wxyz_to_xyzw
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


def form_reason(scene: Scene, settings: dict[str, Any]) -> str | None:
    """Why the chosen form (settings ``joints``, ``maximal_coordinates``)
    cannot build the scene's joints, or None."""
    if not scene.joints:
        return None
    if settings["joints"] == "links":
        return links_reason(scene)
    return prismatic_reason(scene, bool(settings["maximal_coordinates"]))


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


# ---- the reduced form: one multibody of links (setting joints = links) ----------

LINK_TYPES = {"revolute": "JOINT_REVOLUTE", "prismatic": "JOINT_PRISMATIC", "spherical": "JOINT_SPHERICAL",
              "fixed": "JOINT_FIXED"}


def links_reason(scene: Scene) -> str | None:
    """Why the links form cannot build the scene, or None: every body must
    hang from the world through a tree of joints (the multibody's fixed
    base is the world), each body the ``body`` of one joint, and the
    explicit forces act on free bodies only."""
    why = "joints: pybullet's links form (joints = links) "
    twice = held_twice(scene)
    if twice is not None:
        return why + f"builds a tree: {scene.bodies[twice[0]].name!r} is the body of two joints"
    held = {j.body for j in scene.joints}
    loose = next((b for b in scene.bodies if b.index not in held), None)
    if loose is not None:
        return why + f"needs every body held to the world by a chain of joints; {loose.name!r} is not"
    if closes_loop(scene):
        return why + "builds a tree; the joints close a loop"
    if scene.springs or scene.has("drag_linear") or scene.has("drag_quadratic"):
        return why + "applies no springs, dampers or drag"
    return None


class LinkTree:
    """Every body a link of one pybullet multibody whose fixed base is the
    world (reduced coordinates: Featherstone's articulated bodies; each
    joint holds by construction).  Link i's frame has its origin at its
    joint's anchor and the body's starting orientation, its inertial frame
    at the body's centre of mass (-anchor_body in the link frame), the
    joint axis ``axis_body``.  pybullet's defaults that are not the scene's
    are switched off: the velocity motor on every joint (force 0), link
    damping (0).  The starting velocities become joint rates: revolute
    (w_b - w_o) . axis, prismatic the relative velocity along the axis,
    spherical the relative angular velocity in the link frame; a start the
    joint cannot carry is unsupported."""

    def __init__(self, p: Any, cid: int, scene: Scene, shape_of: Any, dynamics_of: Any, contact: bool,
                 notes: list[str], info: dict[str, Any]) -> None:
        from physbench.contract.rotation import quat_to_matrix

        self._p, self._cid, self._n = p, cid, scene.n_bodies
        held = {j.body: j for j in scene.joints}
        depth = {}
        for b in scene.bodies:
            d, i = 0, b.index
            while i >= 0:
                d, i = d + 1, held[i].other
            depth[b.index] = d
        order = sorted(range(scene.n_bodies), key=lambda i: depth[i])  # parents first
        link_of = {i: k for k, i in enumerate(order)}
        R = {b.index: quat_to_matrix(np.asarray(b.orientation, float)) for b in scene.bodies}
        R[-1] = np.eye(3)
        origin = {i: np.asarray(held[i].anchor, float) for i in held}  # link frame origins
        origin[-1] = np.zeros(3)
        quat = {b.index: np.asarray(b.orientation, float) for b in scene.bodies}
        quat[-1] = np.array([1.0, 0.0, 0.0, 0.0])
        cols: dict[str, list] = {k: [] for k in ("linkMasses", "linkCollisionShapeIndices", "linkVisualShapeIndices",
                                                 "linkPositions", "linkOrientations", "linkInertialFramePositions",
                                                 "linkInertialFrameOrientations", "linkParentIndices",
                                                 "linkJointTypes", "linkJointAxis")}
        for i in order:
            j, b = held[i], scene.bodies[i]
            o = j.other
            rel = quat_mul(_conj(quat[o]), quat[i])
            cols["linkMasses"].append(float(b.mass))
            cols["linkCollisionShapeIndices"].append(shape_of(b))
            cols["linkVisualShapeIndices"].append(-1)
            cols["linkPositions"].append(_v(R[o].T @ (origin[i] - origin[o])))
            cols["linkOrientations"].append(_v(wxyz_to_xyzw(rel)))
            cols["linkInertialFramePositions"].append(_v(-np.asarray(j.anchor_body, float)))
            cols["linkInertialFrameOrientations"].append([0.0, 0.0, 0.0, 1.0])
            cols["linkParentIndices"].append(0 if o < 0 else link_of[o] + 1)
            cols["linkJointTypes"].append(getattr(p, LINK_TYPES[j.kind]))
            cols["linkJointAxis"].append(_v(j.axis_body) if j.axis_body is not None else [0.0, 0.0, 1.0])
        mb = p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=-1, basePosition=[0.0, 0.0, 0.0],
                               useMaximalCoordinates=False, physicsClientId=cid, **cols)
        if mb < 0:
            raise RuntimeError("pybullet rejected the link tree")
        self.id = mb
        p.changeDynamics(mb, -1, linearDamping=0.0, angularDamping=0.0, physicsClientId=cid)
        for i in order:
            k, b, j = link_of[i], scene.bodies[i], held[i]
            p.changeDynamics(mb, k, physicsClientId=cid, **dynamics_of(b))
            p.setCollisionFilterGroupMask(mb, k, 1 if contact else 0, -1 if contact else 0, physicsClientId=cid)
            if j.kind == "spherical":
                p.setJointMotorControlMultiDof(mb, k, p.POSITION_CONTROL, targetPosition=[0.0, 0.0, 0.0, 1.0],
                                               positionGain=0.0, velocityGain=0.0, force=[0.0, 0.0, 0.0],
                                               physicsClientId=cid)
            elif j.kind != "fixed":
                p.setJointMotorControl2(mb, k, p.VELOCITY_CONTROL, force=0.0, physicsClientId=cid)
            rate = start_rate(scene, j, "pybullet's links form")
            if j.kind == "spherical":  # in the link frame (the body's)
                rate = R[i].T @ rate
            if j.kind == "spherical":
                p.resetJointStateMultiDof(mb, k, [0.0, 0.0, 0.0, 1.0], targetVelocity=_v(rate), physicsClientId=cid)
            elif j.kind != "fixed":
                p.resetJointState(mb, k, 0.0, targetVelocity=float(rate[0]), physicsClientId=cid)
        # body index -> link index, for the state read
        self._links = [link_of[i] for i in range(scene.n_bodies)]
        self._xyzw = np.zeros((scene.n_bodies, 4))
        notes.append("joints: one pybullet multibody, every body a link of the world's fixed base (reduced "
                     "coordinates); joint motors off, link damping 0")
        info["joints"] = {"form": "createMultiBody links (reduced)", "links": scene.n_bodies}

    def read(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """World centre of mass (n, 3), wxyz (n, 4), velocities (n, 3) of
        every link from one ``getLinkStates`` call (the inertial frame:
        the body's own)."""
        from physbench.contract.rotation import xyzw_to_wxyz

        states = self._p.getLinkStates(self.id, self._links, computeLinkVelocity=1, computeForwardKinematics=1,
                                       physicsClientId=self._cid)
        for k, s in enumerate(states):
            pos[k] = s[0]
            self._xyzw[k] = s[1]
            vel[k] = s[6]
            angvel[k] = s[7]
        quat[...] = xyzw_to_wxyz(self._xyzw)


def _conj(q: np.ndarray) -> np.ndarray:
    return np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])

