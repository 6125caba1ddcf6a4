"""pybullet adapter: Bullet rigid bodies in a DIRECT-mode physics client.

One physics client per adapter instance (``p.connect(p.DIRECT)``); every call
passes ``physicsClientId`` so several adapters can live in one process.

Translation choices, each measured in ``tests/test_adapter_pybullet.py``:

- **Bodies** are created with ``useMaximalCoordinates=True`` by default
  (setting ``maximal_coordinates``): a plain ``btRigidBody``.  pybullet's
  default, a ``btMultiBody`` base, adds a hidden 0.04 linear and angular
  damping, caps the base speed at 100 m/s and integrates the gyroscopic term
  explicitly (energy gain); with maximal coordinates none of that happens.
  Damping is set to 0 explicitly in both modes, and sleeping is disabled.
- **Mass properties**: mass and the exact principal inertia
  (``Body.inertia``) are set with ``changeDynamics(mass=..,
  localInertiaDiagonal=..)``.  Both must be passed together: for a rigid body
  pybullet 3.2.7 applies ``localInertiaDiagonal`` with the call's ``mass``
  argument, which defaults to 0 and makes the body's mass zero (NaN state on
  the first step).  Bullet also keeps the *world* inverse inertia it computed
  at creation (from the collision shape) until the body's transform is next
  integrated, so build() takes one warm-up step with every body at rest, no
  gravity and collisions filtered out; that step leaves every pose unchanged
  and refreshes the world inertia before t = 0.
- **Conversion point**: ``read_state`` is the only place engine state is
  turned into physbench's conventions: ``getBasePositionAndOrientation``
  gives an xyzw quaternion, converted once per call with
  :func:`contract.rotation.xyzw_to_wxyz`; ``getBaseVelocity`` is already
  world-frame linear velocity of the centre of mass and world-frame angular
  velocity.  (The force loop reads the engine's own state in the engine's
  own terms and converts nothing.)
- **Shapes**: sphere, box (half extents), capsule and cylinder (Bullet's
  Z-axis variants, ``height = 2 * half_length``: the body z axis, as in the
  scene).  Statics: a plane is ``GEOM_PLANE`` with ``planeNormal = normal``
  placed at ``offset * normal``; a slope is the same plane; a static box is a
  mass-0 body.
- **Effects off where absent**: no gravity -> ``setGravity(0, 0, 0)``; no
  contact -> every body and static gets collision group = mask = 0, so the
  broadphase never pairs anything and no narrowphase or contact solve runs;
  no friction -> lateral, spinning and rolling friction 0; no restitution ->
  restitution 0.
- **Gyroscopic term**: Bullet integrates ``w x I w`` for every rigid body
  and has no switch.  A scene that omits ``gyroscopic`` is still modelled
  exactly when the term is provably zero (planar scenes; bodies with equal
  moments; bodies at rest or spinning about a principal axis with no torque
  source); otherwise it is reported unsupported.
- **Linear drag** is Bullet's own ``linearDamping`` per body, calibrated to
  the spec's c_linear (:func:`adapters.forces.bullet_linear_damping`;
  btRigidBody only: a btMultiBody base's damping is another law).
- **Springs, dampers, quadratic drag** (and linear drag on btMultiBody bases)
  are applied as world-frame external forces
  (``applyExternalForce(..., WORLD_FRAME)``) computed from the state at the
  start of each step (explicit in the force, like the engine's own gravity;
  :class:`adapters.forces.PybulletForces`), and the row says so for drag.
- **Joints** (:mod:`adapters.pybullet_joints`), setting ``joints``: by
  default ``constraint``, ``createConstraint`` constraints between the
  bodies' bases (maximal coordinates, any joint graph): a hinge is two
  point2point constraints along its axis (pybullet has no revolute
  constraint), a prismatic joint needs ``maximal_coordinates = false``;
  ``links``, every body a link of one ``createMultiBody`` hanging from the
  world (reduced coordinates, trees only).
- **Contacts** (measured, see the settings): by default penetration is
  corrected Baumgarte-style (``contact_erp * depth / dt`` added to the
  contact's target velocity), which adds 2.3 % of the approach speed to
  head-on collisions but keeps box stacks still; ``split_impulse = true``
  makes collision velocities exact but lets a 10-box stack walk ~7 cm in
  3 s.  Contacts are created up to ``contact_breaking_threshold`` (0.02 m)
  apart; such a speculative contact stops a body at the surface and the
  rebound loses gap/dt, so bounces off statics at default settings lose
  anything from nothing to all of their speed depending on where the last
  step before impact ended.  Split impulse plus a threshold of 1e-4 m gives
  rebounds of exactly e.
- **CCD** is on by default (pybullet's default is off): each body sweeps a
  sphere of half its smallest half-size when it moves more than a quarter
  of that in one step.  Measured on the conformance suite: it stops every
  tunnelling case and changes no other result.
- **Materials**: Bullet combines restitution and friction of a contact by the
  *product* of the two objects' values (rolling friction as
  ``r_a f_b + r_b f_a``); :func:`adapters.materials.per_object_factors` finds
  per-object values that give the spec's pair values and reports a residual
  when no such values exist.  Bullet has one Coulomb coefficient: the kinetic
  one is used.

Sibling modules: settings and diagnostics in :mod:`adapters.pybullet_settings`,
the force law in :mod:`adapters.forces`, the silent import in
:mod:`adapters.quiet`, the material factors in :mod:`adapters.materials`.
"""

from __future__ import annotations

import functools
import itertools
import math
from typing import Any

import numpy as np

from physbench.adapters import bare_loops
from physbench.adapters.base import Adapter, Capabilities, Unsupported
from physbench.adapters.forces import PybulletForces, bullet_drag_notes, bullet_linear_damping
from physbench.adapters.materials import per_object_factors
from physbench.adapters.pybullet_joints import LinkTree, add_joints, form_reason
from physbench.adapters.pybullet_settings import (MAX_COMBINED_FRICTION, declaration, describe_stages, engine_parameters,
                                                 import_pybullet as _import_pybullet, run_notes)
from physbench.contract.rotation import wxyz_to_xyzw, xyzw_to_wxyz
from physbench.contract.scene import Scene

ENGINE = "pybullet"

@functools.lru_cache(maxsize=1)
def _capabilities() -> Capabilities:
    try:
        _import_pybullet()
        return declaration(ENGINE, True, "")
    except ImportError as e:
        return declaration(ENGINE, False, str(e))


class PybulletAdapter(Adapter):
    """Drives one pybullet DIRECT client.  See the module docstring."""

    name = ENGINE
    gyroscopic_always_on = "pybullet"

    def __init__(self) -> None:
        super().__init__()
        self._p: Any = None
        self._cid: int | None = None
        self._ids: list[int] = []
        self._static_ids: list[int] = []
        self._xyzw: np.ndarray = np.zeros((0, 4))
        self._forces: PybulletForces | None = None
        self._links: LinkTree | None = None
        self._stage: dict[str, Any] = {}
        self._steps = 0

    # ---- declaration -------------------------------------------------------
    @classmethod
    def capabilities(cls) -> Capabilities:
        return _capabilities()

    # ---- build ---------------------------------------------------------------
    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        reason = self.unsupported_reason(scene)
        if reason is not None:
            raise Unsupported(reason)
        p = _import_pybullet()
        self._p = p
        maximal = bool(settings["maximal_coordinates"])
        why = form_reason(scene, settings)  # before connecting: nothing to close
        if why:
            raise Unsupported(why)
        cid = p.connect(p.DIRECT)
        if cid < 0:
            raise RuntimeError("pybullet could not start a DIRECT physics client")
        self._cid = cid
        dt = float(settings["dt"])
        contact = scene.has("contact")
        ccd = bool(settings["ccd"]) and contact  # nothing to sweep against without contacts

        params = engine_parameters(settings, ccd)
        p.setPhysicsEngineParameter(physicsClientId=cid, **params)
        self.info["engine_parameters"] = dict(params)
        # Warm-up happens with gravity off (see below).
        p.setGravity(0.0, 0.0, 0.0, physicsClientId=cid)

        # ---- materials -----------------------------------------------------
        nb = scene.n_bodies
        mats = per_object_factors(scene, ENGINE, MAX_COMBINED_FRICTION)
        self.notes.extend(mats.notes)
        self.info.update(mats.info)
        restitution, friction, rolling = mats.restitution, mats.friction, mats.rolling

        # ---- collision shapes (shared between identical bodies) -------------
        shape_cache: dict[tuple, int] = {}

        def shape_id(kind: str, **kw: Any) -> int:
            key = (kind,) + tuple(sorted((k, tuple(v) if isinstance(v, (list, tuple)) else v) for k, v in kw.items()))
            if key not in shape_cache:
                geom = {"sphere": p.GEOM_SPHERE, "box": p.GEOM_BOX, "capsule": p.GEOM_CAPSULE,
                        "cylinder": p.GEOM_CYLINDER, "plane": p.GEOM_PLANE}[kind]
                sid = p.createCollisionShape(geom, physicsClientId=cid, **kw)
                if sid < 0:
                    raise RuntimeError(f"pybullet rejected collision shape {kind} {kw}")
                shape_cache[key] = sid
            return shape_cache[key]

        def body_shape(b: Any) -> int:
            if b.shape == "sphere":
                return shape_id("sphere", radius=float(b.radius))
            if b.shape == "box":
                return shape_id("box", halfExtents=[float(h) for h in b.half_extents])
            # capsule / cylinder: Bullet's Z variants, total height 2 * half_length
            return shape_id(b.shape, radius=float(b.radius), height=2.0 * float(b.half_length))

        # ---- dynamic bodies ------------------------------------------------
        damping = bullet_linear_damping(scene) if maximal else {}  # linear drag, btRigidBody's own
        min_ccd_threshold = math.inf
        links = bool(scene.joints) and settings["joints"] == "links"
        for b in (() if links else scene.bodies):  # the links form builds its bodies below
            sid = body_shape(b)
            xyzw = [float(c) for c in wxyz_to_xyzw(b.orientation)]
            bid = p.createMultiBody(baseMass=float(b.mass), baseCollisionShapeIndex=sid,
                                    basePosition=[float(c) for c in b.position], baseOrientation=xyzw,
                                    useMaximalCoordinates=maximal, physicsClientId=cid)
            if bid < 0:
                raise RuntimeError(f"pybullet rejected body {b.name!r}")
            k = b.index
            dyn = dict(
                mass=float(b.mass),  # must accompany localInertiaDiagonal, see module docstring
                localInertiaDiagonal=[float(c) for c in b.inertia],
                linearDamping=damping.get(k, 0.0), angularDamping=0.0,
                lateralFriction=float(friction[k]), spinningFriction=0.0,
                rollingFriction=float(rolling[k]), restitution=float(restitution[k]),
                activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING,
            )
            if ccd:
                r = float(settings["ccd_radius"]) * b.min_extent
                dyn["ccdSweptSphereRadius"] = r
                min_ccd_threshold = min(min_ccd_threshold, r / 2.0)
            p.changeDynamics(bid, -1, physicsClientId=cid, **dyn)
            self._ids.append(bid)

        # ---- statics ---------------------------------------------------------
        for s in scene.statics:
            k = nb + s.index
            if s.shape == "plane":
                n = [float(c) for c in s.normal]
                sid = shape_id("plane", planeNormal=n)
                pos = [float(c) * s.offset for c in s.normal]
                orn = [0.0, 0.0, 0.0, 1.0]
            else:
                sid = shape_id("box", halfExtents=[float(h) for h in s.half_extents])
                pos = [float(c) for c in s.position]
                orn = [float(c) for c in wxyz_to_xyzw(s.orientation)]
            sbid = p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=sid, basePosition=pos,
                                     baseOrientation=orn, useMaximalCoordinates=maximal, physicsClientId=cid)
            if sbid < 0:
                raise RuntimeError(f"pybullet rejected static {s.name!r}")
            p.changeDynamics(sbid, -1, lateralFriction=float(friction[k]), spinningFriction=0.0,
                             rollingFriction=float(rolling[k]), restitution=float(restitution[k]),
                             physicsClientId=cid)
            self._static_ids.append(sbid)

        # ---- warm-up: refresh Bullet's world inverse inertia -----------------
        # All bodies at rest, no gravity, nothing collides: one step leaves
        # every pose unchanged and recomputes R I^-1 R^T from the inertia set
        # above (Bullet only does that when it integrates a transform).
        everything = self._ids + self._static_ids
        for x in everything:
            p.setCollisionFilterGroupMask(x, -1, 0, 0, physicsClientId=cid)
        p.stepSimulation(physicsClientId=cid)
        if contact:
            for x in everything:
                p.setCollisionFilterGroupMask(x, -1, 1, -1, physicsClientId=cid)
        # else: group = mask = 0 stays: the broadphase never pairs anything.

        # ---- initial state ---------------------------------------------------
        for b, bid in zip(scene.bodies, self._ids):
            p.resetBasePositionAndOrientation(bid, [float(c) for c in b.position],
                                              [float(c) for c in wxyz_to_xyzw(b.orientation)], physicsClientId=cid)
            p.resetBaseVelocity(bid, [float(c) for c in b.velocity], [float(c) for c in b.angular_velocity],
                                physicsClientId=cid)
        if links:  # one multibody of links (adapters/pybullet_joints.py)
            self._links = LinkTree(p, cid, scene, body_shape, lambda b: dict(
                mass=float(b.mass), localInertiaDiagonal=[float(c) for c in b.inertia], linearDamping=0.0,
                angularDamping=0.0, lateralFriction=float(friction[b.index]), spinningFriction=0.0,
                rollingFriction=float(rolling[b.index]), restitution=float(restitution[b.index])),
                contact, self.notes, self.info)
        elif scene.joints:  # constraints between the bases, at the starting poses (adapters/pybullet_joints.py)
            add_joints(p, cid, scene, self._ids, maximal, self.notes, self.info)
        g = scene.gravity
        p.setGravity(float(g[0]), float(g[1]), float(g[2]), physicsClientId=cid)

        # ---- external forces -------------------------------------------------
        self._forces = PybulletForces(scene, frozenset(damping)) or None
        bullet_drag_notes(scene, damping, maximal, self.notes, self.info)

        self._xyzw = np.zeros((nb, 4))
        self._stage = describe_stages(scene, settings, min_ccd_threshold, self._forces.kinds if self._forces else [])
        run_notes(scene, settings, dt, bool(self._forces), self.notes, self.info)

    def stages(self) -> dict[str, Any]:
        out = dict(self._stage)
        out["steps"] = self._steps
        out["force_steps"] = self._steps if self._forces else 0
        return out

    # ---- life cycle --------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        p, cid = self._p, self._cid
        if self._forces:
            apply, ids = self._forces.apply, self._ids
            for _ in range(n):
                apply(p, cid, ids)
                p.stepSimulation(physicsClientId=cid)
        else:
            for _ in range(n):
                p.stepSimulation(physicsClientId=cid)
        self._steps += n

    bare_record = bare_loops.pybullet

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        if self._links is not None:  # one getLinkStates call per step
            return super().step_record(n, pos, quat, vel, angvel)
        self._record(n, pos, quat, vel, angvel)

    def _record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Step n times and record every step.  pybullet has no batched state
        read: each body costs two calls per step (~1 us each, the bound of
        this adapter's overhead).  Their tuples are only appended to lists
        while stepping; the block is converted to arrays once at its end (or
        at an exception, keeping every complete step)."""
        p, cid, ids = self._p, self._cid, self._ids
        nb = len(ids)
        st, gpo, gv = p.stepSimulation, p.getBasePositionAndOrientation, p.getBaseVelocity
        po: list = []
        ve: list = []
        apo, ave = po.append, ve.append
        forces = self._forces
        stepped = 0
        try:
            for _ in range(n):
                if forces:
                    forces.apply(p, cid, ids)
                st(cid)
                stepped += 1
                for bid in ids:
                    apo(gpo(bid, cid))
                    ave(gv(bid, cid))
        finally:
            self._steps += stepped
            k = min(len(po), len(ve)) // nb  # complete steps
            self.block_done = k
            if k:
                m = k * nb
                # the tuples flattened in C (no Python loop over rows):
                # (x, y, z, qx, qy, qz, qw) and (vx, vy, vz, wx, wy, wz)
                flat = itertools.chain.from_iterable
                a = np.fromiter(flat(flat(po[:m])), float, count=7 * m).reshape(k, nb, 7)
                b = np.fromiter(flat(flat(ve[:m])), float, count=6 * m).reshape(k, nb, 6)
                pos[:k] = a[..., 0:3]
                quat[:k] = xyzw_to_wxyz(a[..., 3:7])
                vel[:k] = b[..., 0:3]
                angvel[:k] = b[..., 3:6]

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Write positions (n, 3) m, quaternions (n, 4) wxyz, linear (n, 3) m/s
        and angular (n, 3) rad/s velocities, world frame, about the centre of
        mass.  pybullet forces one call per body per quantity (tuples); the
        quaternions go through one preallocated xyzw buffer and are converted
        to wxyz in a single place."""
        if self._links is not None:
            return self._links.read(pos, quat, vel, angvel)
        p, cid = self._p, self._cid
        xyzw = self._xyzw
        for k, bid in enumerate(self._ids):
            x, q = p.getBasePositionAndOrientation(bid, physicsClientId=cid)
            v, w = p.getBaseVelocity(bid, physicsClientId=cid)
            pos[k] = x
            xyzw[k] = q
            vel[k] = v
            angvel[k] = w
        quat[...] = xyzw_to_wxyz(xyzw)

    def contacts(self) -> np.ndarray:
        """``getContactPoints`` after the last step: point midway between
        positionOnA and positionOnB, normal contactNormalOnB (from B toward
        A), depth = -contactDistance."""
        pts = self._p.getContactPoints(physicsClientId=self._cid)
        out = np.empty((len(pts), 7))
        for i, c in enumerate(pts):
            out[i, 0:3] = 0.5 * (np.asarray(c[5]) + np.asarray(c[6]))
            out[i, 3:6] = c[7]
            out[i, 6] = -c[8]
        return out

    def close(self) -> None:
        if self._cid is not None and self._p is not None:
            try:
                self._p.disconnect(physicsClientId=self._cid)
            finally:
                self._cid = None
