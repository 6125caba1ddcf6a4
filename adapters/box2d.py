"""Box2D v3 adapter (``pyb2d3`` 0.11 bindings of Box2D >= 3.1): planar
scenes only, single precision.

Planar mapping (as for pymunk): a planar scene lives in the world x-z
plane; :func:`contract.conventions.planar_from_world` at build and
:func:`contract.conventions.world_from_planar`'s mapping in :meth:`Box2dAdapter._convert`
(vectorised over a block, the quaternion from Box2D's (cos, sin) by
:func:`contract.conventions.world_quat_from_planar_rotation`) are the only
conversions (2D x = world x, 2D y = world z, counter-clockwise w = world
angular velocity (0, -w, 0)).  Mass = ``Body.mass`` and rotational
inertia = ``Body.inertia[1]`` (I_yy of the 3D body, exact for rotations about
y), set as the body's mass data after its shape (density 0).

Shapes (the x-z cross-section through the centre): sphere -> circle; box ->
box of half sizes (x, z); capsule -> capsule from (0, -h) to (0, h);
cylinder -> box 2r x 2h, its axial section (a planar cylinder's axis lies in
the plane).  Statics: a plane or slope is a static box 400 m long and 10 m
deep on its solid side, its top face on the plane's line; a static box is
its x-z cross-section.

Stepping: ``World.step(dt, substeps)``.  Box2D's soft step splits a step
into ``substeps`` substeps of dt/S; each integrates velocities then
positions (free fall from rest: z_k = -g dt^2 k (k + 1/S) / 2) and solves
contacts as soft springs of ``contact_hertz`` (capped by Box2D at a quarter
of the substep rate) with ``contact_damping_ratio``, pushing overlap out at
no more than ``contact_push_speed``; restitution is applied after the
substeps to contacts that approached faster than ``restitution_threshold``.
Speeds are clamped to ``max_linear_speed``.  Sleeping is off.

Materials: Box2D mixes a pair by friction sqrt(f_a f_b), restitution
max(e_a, e_b), rolling resistance max(c_a, c_b) x the larger shape radius
(its rolling coefficient is dimensionless; the spec's is a lever arm in m,
so c = mu_r / r).  pyb2d3 exposes no mixing callbacks: per-shape values are
solved (:func:`adapters.box2d_scene.shape_materials`), residuals noted.  One
Coulomb coefficient: the kinetic one.

Effects: gravity; contact absent -> bodies get no shape at all; springs,
dampers and drag are explicit forces from the state at the start of each
step (:class:`adapters.forces.StateForces`), held over its substeps and
noted; ``joint`` -> Box2D revolute, prismatic and weld joints
(:mod:`adapters.box2d_joints`); ``gyroscopic`` is unsupported (identically zero in 2D).

Contacts: pyb2d3 gives contact data only as begin/end/hit events, not as a
per-step list.  :meth:`Box2dAdapter.contacts` returns the manifold points of
the contacts that began touching in the last step.  No contact forces can be
read (:attr:`Box2dAdapter.contact_forces_reason`): the contact-law metrics
are undefined with that reason.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.adapters import bare_loops
from physbench.adapters.base import (Adapter, Capabilities, Unsupported, module_version, optional_import,
                                     planar_gyroscopic_reason)
from physbench.adapters.box2d_joints import add_joints
from physbench.adapters.box2d_scene import body_shape, declaration, rot, shape_materials, static_pose
from physbench.adapters.forces import DRAG_NOTE, StateForces
from physbench.adapters.planar import planar_geometry_reason
from physbench.contract.conventions import planar_from_world, world_point_to_planar, world_quat_from_planar_rotation
from physbench.contract.scene import Scene

ENGINE = "box2d"

GYROSCOPIC_REASON = planar_gyroscopic_reason("Box2D")

#: body-steps (rows x bodies) of the staging block between two conversions,
#: for scenes of fewer than 10 bodies; more bodies take :data:`CHUNK_ROWS`
#: rows.  Its row views are made once per adapter (made for every block of
#: the runner's they cost ~0.8 us per recorded step on the 10-box pyramid,
#: measured) and it stays in cache until converted.  A conversion costs ~14 us whatever its length (30 array
#: operations and their views) besides ~14 ns per body and step, and works
#: in cache best at ~1280 body-steps: recording the 10-box pyramid in runs
#: (runner / bare loop, interleaved, 41 repeats, load 5.5) costs 1.053 at 128
#: rows and 1.061-1.065 at 256; head_on (2 bodies) 0.957 at 640 rows and
#: 0.991 at 128 (21 repeats)
CHUNK_ELEMENTS = 1280
#: the fewest steps of a staging block (10 bodies and more)
CHUNK_ROWS = 128


class Box2dAdapter(Adapter):
    """Adapter for Box2D v3 through pyb2d3 (2D, planar scenes in the x-z plane)."""

    name = ENGINE
    #: measured on pyb2d3 0.11.1 (docs/ENGINE_FINDINGS.md, "Contact-law residuals")
    contact_forces_reason = (
        "the adapter reads no contact forces: pyb2d3 0.11 (Box2D v3.1) binds none of the calls that give a contact's "
        "manifold after the solve (b2Body_GetContactData, b2Shape_GetContactData: its ContactData type is returned "
        "by nothing, nor b2World_SetPreSolveCallback), its begin-touch events carry the manifold from before the "
        "solve (impulses 0), and its debug draw cannot set useDrawingBounds (the path that draws normalImpulse): "
        "the path it takes draws totalNormalImpulse, the impulse summed over every solve and relax pass of the "
        "substeps (2 m g dt on a resting box), not a force, with no shape ids")

    @classmethod
    def capabilities(cls) -> Capabilities:
        b2, why = optional_import("pyb2d3")
        return declaration(ENGINE, module_version("pyb2d3"), b2 is not None, why)

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        reason = super().unsupported_reason(scene)
        if reason is not None:
            if cls.capabilities().available and scene.planar and "gyroscopic" in scene.effects:
                return GYROSCOPIC_REASON
            return reason
        return planar_geometry_reason(scene, "Box2D")

    # ---- build -------------------------------------------------------------
    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        reason = self.unsupported_reason(scene)
        if reason is not None:
            raise Unsupported(reason)
        b2, _ = optional_import("pyb2d3")
        self._b2 = b2
        self._dt = float(settings["dt"])
        self._substeps = int(settings["substeps"])
        world = b2.World(gravity=world_point_to_planar(scene.gravity),
                         contact_hertz=float(settings["contact_hertz"]),
                         contact_damping_ratio=float(settings["contact_damping_ratio"]),
                         restitution_threshold=float(settings["restitution_threshold"]),
                         maximum_linear_speed=float(settings["max_linear_speed"]))
        world.set_contact_tuning(float(settings["contact_hertz"]), float(settings["contact_damping_ratio"]),
                                 float(settings["contact_push_speed"]))
        world.sleeping_enabled = False
        contact = scene.has("contact")
        world.continuous_enabled = bool(settings["continuous"]) and contact
        bullet = bool(settings["bullets"]) and contact
        self._world = world

        geoms = [body_shape(b2, b) for b in scene.bodies] if contact else []
        mats = shape_materials(scene, [r for _, r in geoms], self.notes, self.info) if contact else None

        def shape_def(k: int) -> Any:
            f, e, c = (float(x) for x in mats[k])
            return b2.shape_def(density=0.0, enable_contact_events=True,
                                material=b2.surface_material(friction=f, restitution=e, rolling_resistance=c))

        self._bodies = []
        for b in scene.bodies:
            (x, y), (vx, vy), angle, w = planar_from_world(b.position, b.velocity, b.orientation,
                                                           b.angular_velocity)
            body = world.create_body(b2.body_def(
                type=b2.BodyType.DYNAMIC, position=(x, y), rotation=rot(b2, angle), linear_velocity=(vx, vy),
                angular_velocity=w, enable_sleep=False, is_bullet=bullet, linear_damping=0.0,
                angular_damping=0.0))
            if contact:
                body.create_shape(shape_def(b.index), geoms[b.index][0])
            md = b2.MassData()
            md.mass, md.rotational_inertia, md.center = float(b.mass), float(b.inertia[1]), (0.0, 0.0)
            body.mass_data = md
            self._bodies.append(body)
        if contact:
            for s in scene.statics:
                (x, y), angle, (hx, hy), centre = static_pose(s)
                ground = world.create_body(b2.body_def(type=b2.BodyType.STATIC, position=(x, y),
                                                       rotation=rot(b2, angle)))
                ground.create_shape(shape_def(scene.n_bodies + s.index), b2.box(hx, hy, center=centre))
        self._batch = b2.Bodies()
        for body in self._bodies:
            self._batch.append(body)
        n = scene.n_bodies
        self._t, self._v, self._w = np.zeros((n, 4), np.float32), np.zeros((n, 2), np.float32), np.zeros(n, np.float32)
        self._chunk = max(CHUNK_ROWS, CHUNK_ELEMENTS // max(n, 1))  # staging rows
        self._block = None

        if scene.joints:  # adapters/box2d_joints.py
            add_joints(b2, world, scene, self._bodies, self.notes, self.info)
        self._spring_mode = settings["springs"]
        explicit = self._add_springs(scene)
        self._forces = StateForces(scene, springs=explicit) or None
        if self._forces:
            self.notes.append(DRAG_NOTE if self._forces.kinds == ["drag"] else
                              "springs, dampers and drag: explicit forces (Hooke spring, dashpot along the spring "
                              "line, F = -(c1 + c2 |v|) v) from the state at the start of each step, held over "
                              "Box2D's substeps (a spring with an anchor off a centre of mass, or a damper "
                              "without a spring, has no exact distance-joint counterpart)")
        vmax = max((float(np.linalg.norm(b.velocity)) for b in scene.bodies), default=0.0)
        if vmax > float(settings["max_linear_speed"]):
            self.notes.append(f"Box2D clamps every speed to max_linear_speed = {settings['max_linear_speed']:g} m/s; "
                              f"a body starts at {vmax:g} m/s")
        self.steps = 0
        self._stages = {"gravity": bool(np.any(scene.gravity != 0)), "contact": contact,
                        "continuous": world.continuous_enabled, "bullets": bullet, "substeps": self._substeps,
                        "spring_joints": self._n_joints,
                        "external_forces": self._forces.kinds if self._forces else []}

    def _add_springs(self, scene: Scene) -> list:
        """Springs anchored at centres of mass (or the world) become Box2D
        distance joints with a spring; returns the others (explicit forces).

        Box2D sets a joint spring by frequency f and damping ratio z of the
        joint's effective mass along its axis, m_eff = 1 / (1/m_a + 1/m_b)
        (1/m = 0 for the world) when both anchors are centres of mass; then
        f = sqrt(k / m_eff) / (2 pi) and z = c / (2 sqrt(k m_eff)) give
        exactly the spec's k (N/m) and c (N s/m).  Off-centre anchors add
        rotational terms that change with the pose: no constant f, z fits."""
        b2, explicit, joints = self._b2, [], 0
        ground = None
        for sp in scene.springs:
            if sp.stiffness == 0.0 and sp.damping == 0.0:
                continue
            centred = all(i < 0 or not np.any(np.asarray(anc) != 0.0)
                          for i, anc in ((sp.a, sp.anchor_a), (sp.b, sp.anchor_b)))
            if sp.stiffness <= 0.0 or not centred or self._spring_mode == "force":
                explicit.append(sp)
                continue
            if ground is None:
                ground = self._world.create_body(b2.body_def(type=b2.BodyType.STATIC, position=(0.0, 0.0)))
            inv = sum(1.0 / scene.bodies[i].mass for i in (sp.a, sp.b) if i >= 0)
            m_eff = 1.0 / inv
            ends = [(ground, world_point_to_planar(anc)) if i < 0 else (self._bodies[i], (0.0, 0.0))
                    for i, anc in ((sp.a, sp.anchor_a), (sp.b, sp.anchor_b))]
            self._world.create_distance_joint(
                body_a=ends[0][0], body_b=ends[1][0], local_anchor_a=ends[0][1], local_anchor_b=ends[1][1],
                length=float(sp.rest_length), enable_spring=True, enable_limit=False, collide_connected=True,
                hertz=float(np.sqrt(sp.stiffness / m_eff) / (2.0 * np.pi)),
                damping_ratio=float(sp.damping / (2.0 * np.sqrt(sp.stiffness * m_eff))))
            joints += 1
        if joints:
            self.notes.append("springs anchored at centres of mass: Box2D distance joints with a spring, frequency "
                              "and damping ratio set from the spec's k and c and the joint's effective mass")
        self._n_joints = joints
        return explicit

    # ---- stepping ----------------------------------------------------------
    def step(self, n: int = 1) -> None:
        world, dt, sub = self._world, self._dt, self._substeps
        if self._forces is None:
            for _ in range(n):
                world.step(dt, sub)
        else:
            k = len(self._bodies)
            pos, quat, vel, angvel = np.empty((k, 3)), np.empty((k, 4)), np.empty((k, 3)), np.empty((k, 3))
            for _ in range(n):
                self.read_state(pos, quat, vel, angvel)
                F, T = self._forces.evaluate(pos, quat, vel, angvel)
                for i in self._forces.bodies:
                    body = self._bodies[i]
                    body.apply_force_to_center((float(F[i, 0]), float(F[i, 2])), False)
                    body.apply_torque(-float(T[i, 1]), False)  # 2D counter-clockwise = world -y
                world.step(dt, sub)
        self.steps += n

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Step n times, each step's three batched f32 reads (transforms,
        linear and angular velocities) written straight into a row of a
        reused staging block (:data:`CHUNK_ELEMENTS`) through views made
        once (no allocation per step), converted (:meth:`_convert`) into
        the (n, bodies, 3|4) blocks every block of steps, while the staging
        rows are still in cache; also the complete steps before an
        exception."""
        if self._forces is not None:
            return super().step_record(n, pos, quat, vel, angvel)
        self.block_done = 0
        chunk = self._chunk
        for c in range(0, n, chunk):
            m = min(chunk, n - c)
            self._record(m, pos[c:c + m], quat[c:c + m], vel[c:c + m], angvel[c:c + m])

    def _record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """:meth:`step_record`'s chunk of n <= ``_chunk`` steps
        (``block_done`` and ``steps`` count the complete ones)."""
        nb = len(self._bodies)
        blk = self._block
        if blk is None:
            # pyb2d3 silently copies a non-contiguous output array (and then
            # writes nothing back): every row view below is C-contiguous,
            # made once for the adapter's life, as far as the steps need
            c = self._chunk
            t, v, w = np.zeros((c, nb, 4), np.float32), np.zeros((c, nb, 2), np.float32), np.zeros((c, nb), np.float32)
            blk = self._block = (t, v, w, [], _inputs(t, v, w, np.empty((4, c, nb))))
        t, v, w, rows, full = blk
        rows.extend(zip(t[len(rows):n], v[len(rows):n], w[len(rows):n]))  # missing row views (none: empty slices)
        world, dt, sub, bt = self._world, self._dt, self._substeps, self._batch
        step, gt, gv, gw = world.step, bt.get_transforms, bt.get_linear_velocities, bt.get_angular_velocities
        done = 0
        try:
            for ti, vi, wi in rows[:n]:
                step(dt, sub)
                done += 1
                gt(ti)
                gv(vi)
                gw(wi)
        finally:
            self.steps += done
            self.block_done += done
            if done == len(t) and done == len(pos) and nb:  # a whole block: its views made once
                _write(full, pos, quat, vel, angvel)
            elif done and nb:
                self._convert(t[:done], v[:done], w[:done], pos[:done], quat[:done], vel[:done], angvel[:done])

    def _convert(self, t: np.ndarray, v: np.ndarray, w: np.ndarray, pos: np.ndarray, quat: np.ndarray,
                 vel: np.ndarray, angvel: np.ndarray) -> None:
        """Box2D's f32 transforms (..., nb, 4) [x, y, cos, sin], velocities
        (..., nb, 2) and angular velocities (..., nb) into the harness's
        world arrays (..., nb, 3|4): the mapping of
        :func:`contract.conventions.world_from_planar` (x, y -> world x, z;
        w -> (0, -w, 0)), the quaternion from (cos, sin) by
        :func:`contract.conventions.world_quat_from_planar_rotation` (the
        angle path's (cos a/2, 0, -sin a/2, 0), a = atan2(sin, cos), without
        its three transcendental passes), vectorised over the block into the
        output arrays and a reused float64 scratch block: no temporary
        (tests/test_adapter_box2d.py::test_block_conversion_is_world_from_planar)."""
        shape = t.shape[:-1]
        m = math.prod(shape)
        if m == 0:
            return
        s = getattr(self, "_scratch", None)
        if s is None or s.shape[1] < m:
            s = self._scratch = np.empty((4, max(m, 1024)))
        _write(_inputs(t, v, w, s[:, :m].reshape((4, *shape))), pos, quat, vel, angvel)

    bare_record = bare_loops.box2d

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """World positions (n, 3) m, wxyz quaternions (n, 4), linear (n, 3)
        m/s and angular (n, 3) rad/s velocities: three batched f32 reads
        into preallocated arrays, then :meth:`_convert`."""
        bt = self._batch
        bt.get_transforms(self._t)
        bt.get_linear_velocities(self._v)
        bt.get_angular_velocities(self._w)
        self._convert(self._t, self._v, self._w, pos, quat, vel, angvel)

    def contacts(self) -> np.ndarray:
        """Manifold points of the contacts that began touching in the last
        step (Box2D's begin-touch events; pyb2d3 has no per-step contact
        list): rows [world point (x, 0, z), manifold normal (from shape A
        toward shape B), depth = -separation]."""
        ev = self._world.get_contact_events()
        rows = []
        for e in ev.begin_events():
            m = e.manifold
            nx, ny = m.normal.x, m.normal.y
            for mp in m.points():
                rows.append((mp.point.x, 0.0, mp.point.y, nx, 0.0, ny, -float(mp.separation)))
        return np.array(rows, float).reshape(-1, 7)

    def stages(self) -> dict[str, Any]:
        return {**getattr(self, "_stages", {}), "steps": getattr(self, "steps", 0)}

    def close(self) -> None:
        self._batch = None
        self._block = None
        self._scratch = None
        self._bodies = []
        self._world = None


def _inputs(t: np.ndarray, v: np.ndarray, w: np.ndarray, scratch: np.ndarray) -> tuple:
    """The component views :func:`_write` reads: x, y, cos, sin of the
    transforms (..., nb, 4), vx, vy of the velocities (..., nb, 2), the
    angular velocities (..., nb) and a float64 scratch (4, ..., nb)."""
    return t[..., 0], t[..., 1], t[..., 2], t[..., 3], v[..., 0], v[..., 1], w, scratch


def _write(inputs: tuple, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
    """:meth:`Box2dAdapter._convert`'s array operations, from
    :func:`_inputs`' views into the world arrays (..., nb, 3|4)."""
    x, y, c, s, vx, vy, w, scratch = inputs
    world_quat_from_planar_rotation(c, s, quat[..., 0], quat[..., 2], scratch)
    quat[..., 1::2] = 0.0
    # one component per assignment: each is then one long strided loop
    # (a (..., 2) pair of components would be loops of two: 2.6x slower,
    # measured); a float32 -> float64 assignment, not a ufunc casting on
    # the way (3x slower, measured)
    pos[..., 0] = x
    pos[..., 1] = 0.0
    pos[..., 2] = y
    vel[..., 0] = vx
    vel[..., 1] = 0.0
    vel[..., 2] = vy
    angvel[..., 0::2] = 0.0
    angvel[..., 1] = w
    np.negative(angvel[..., 1], out=angvel[..., 1])
