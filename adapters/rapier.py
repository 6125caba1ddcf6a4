"""Rapier adapter (``rapier3d`` 0.36 Python bindings: 3D, single precision;
planar scenes run as 3D scenes).

Precision
    Rapier computes in f32: positions, velocities and quaternions come back
    rounded to 24-bit mantissas (a relative 6e-8; 6e-8 m at 1 m from the
    origin), which puts a floor under every error metric the harness forms
    from them (docs/ENGINE_FINDINGS.md gives the measured floor).

Stepping
    ``PhysicsWorld.step()`` advances ``integration_parameters.dt``.  Rapier's
    TGS-soft solver splits every step into ``num_solver_iterations``
    substeps of dt/S, each with ``num_internal_pgs_iterations`` PGS sweeps,
    and integrates each substep velocity first (v += a h, then x += v h):
    free fall from rest gives z_k = -g dt^2 k (k + 1/S) / 2
    (tests/test_closed_forms.py::test_free_fall).

Bodies
    A dynamic body per scene body, posed at its centre of mass (Rapier takes
    quaternions as (x, y, z, w)), its velocities world-frame (Rapier's
    ``angvel`` is world-frame), sleeping off, damping 0.  Mass and principal
    inertia are the Scene's, given as the body's additional mass properties
    (colliders have density 0), so no shape formula of Rapier's enters.

Shapes
    sphere -> ball; box -> cuboid (half extents); capsule -> ``capsule_z``
    (axis = body z); cylinder -> ``cylinder`` (Rapier's axis is its local y),
    turned +90 degrees about x so that its axis is body z.  Statics: a plane
    (or slope) is a ``halfspace`` with outward normal n through offset * n;
    a static box is a cuboid.  Without ``contact`` no collider exists at all.

Materials
    Rapier combines a pair per collider rule (the higher-priority rule of the
    two wins).  Every collider gets ``MULTIPLY`` for friction and
    restitution, and per-material values whose products give every pair
    (:func:`adapters.materials.per_material_factors`; per-object values by
    least squares with the residual in the notes where no per-material ones
    exist).  Rapier has one Coulomb coefficient: the kinetic friction is used
    (noted where static_friction differs).  Rapier has no rolling resistance:
    ``rolling_friction`` is unsupported.

Effects
    joint -> Rapier generic joints with explicit frames, impulse (maximal)
    or multibody (reduced) by the setting ``joints``
    (:mod:`adapters.rapier_joints`).  gravity -> world gravity; springs, dampers and drag are explicit forces
    from the state at the start of each step (:class:`adapters.forces.StateForces`,
    held over its substeps; noted in the row).  gyroscopic: Rapier's
    per-body switch ``gyroscopic_forces`` is on exactly when the scene lists
    the effect.  Rapier's source describes what it integrates: the explicit
    term, L_body += -(w x I w) h, then L_body rescaled to its magnitude before
    the update (no implicit solve; "similar to Jolt").  Measured, torque-free
    rotation then gains energy (1 % in 2 s at 14.7 rad/s on the fast spinner's
    box; docs/ENGINE_FINDINGS.md).  Without the effect the angular velocity is
    held exactly (tests/test_adapter_rapier.py::test_gyroscopic_switch).

Contacts
    :meth:`RapierAdapter.contacts` reads the narrow phase's solver contacts
    (world points; manifold normal from collider 1 toward collider 2; depth =
    -dist, so speculative contacts within the prediction distance come out
    negative).

State reads
    One ``RigidBodySet.to_bytes()`` per step holds every body's state
    (:mod:`adapters.rapier_batch`, checked against the per-body getters after
    every recorded block); the four getters per body are the fallback.

Sibling modules: settings and colliders in :mod:`adapters.rapier_scene`, the
state reader in :mod:`adapters.rapier_batch`, the force laws in
:mod:`adapters.forces`, material factors in :mod:`adapters.materials`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.adapters import bare_loops
from physbench.adapters.base import Adapter, Capabilities, Unsupported, module_version, optional_import
from physbench.adapters.forces import DRAG_NOTE, StateForces
from physbench.adapters.materials import per_material_factors, per_object_factors
from physbench.adapters.rapier_batch import SetBytesReader, getter_rows
from physbench.adapters.rapier_joints import JOINT_KINDS, add_joints, tree_reason
from physbench.adapters.rapier_scene import EFFECTS, SHAPES, STATIC_SHAPES, body_collider, static_collider
from physbench.adapters.rapier_scene import settings as rapier_settings
from physbench.contract.rotation import wxyz_to_xyzw, xyzw_to_wxyz
from physbench.contract.scene import Scene

rp, _IMPORT_ERROR = optional_import("rapier3d")  # the engine; a missing rapier3d only makes its runs unavailable

ENGINE = "rapier"

ROLLING_FRICTION_REASON = "Rapier 0.36 has no rolling resistance (rolling_friction)"

#: bytes of set bytes decoded at once while recording (CHUNK_BYTES over a
#: step's length, 32 to 1024 steps): the row buffer (~0.5 kB per body and
#: step) then stays in the CPU's cache between its writing and its reading
#: (measured on the bench's 10-box column: the runner's own work 1.2 us per
#: step less than decoding every 1024 steps)
CHUNK_BYTES = 256 << 10

class RapierAdapter(Adapter):
    """Adapter for rapier3d 0.36 (see the module docstring)."""

    name = ENGINE

    @classmethod
    def capabilities(cls) -> Capabilities:
        return Capabilities(
            engine=ENGINE,
            version=rp.__version__ if rp is not None else module_version("rapier3d"),
            dimensions=3,
            shapes=SHAPES,
            static_shapes=STATIC_SHAPES,
            effects=EFFECTS | {"joint"},
            joint_kinds=JOINT_KINDS,
            settings=rapier_settings(),
            available=rp is not None,
            unavailable_reason=_IMPORT_ERROR,
            notes=(
                "single precision (f32) throughout",
                "TGS-soft solver: each step is `iterations` substeps",
                "friction and restitution combine by product (MULTIPLY rule on every collider)",
                "one Coulomb coefficient: static friction = kinetic friction",
                "no rolling resistance",
                "springs, dampers and drag are explicit forces from the state at the start of each step",
                "gyroscopic term switchable per body (on when the scene lists it)",
            ),
        )

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        reason = super().unsupported_reason(scene)
        if reason is not None and cls.capabilities().available and "rolling_friction" in scene.effects:
            return ROLLING_FRICTION_REASON
        return reason

    # ---- build -------------------------------------------------------------
    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        reason = self.unsupported_reason(scene)
        if reason is not None:
            raise Unsupported(reason)
        if scene.joints and settings["joints"] == "multibody":
            why = tree_reason(scene)
            if why:
                raise Unsupported(why)
        world = rp.PhysicsWorld(gravity=tuple(float(g) for g in scene.gravity))
        ip = world.integration_parameters  # a live view: edited in place
        ip.dt = float(settings["dt"])
        ip.num_solver_iterations = int(settings["iterations"])
        ip.num_internal_pgs_iterations = int(settings["pgs_iterations"])
        zeta = float(settings["contact_damping_ratio"])
        ip.contact_softness = rp.SpringCoefficients(float(settings["contact_frequency"]), zeta)
        ip.static_contact_softness = rp.SpringCoefficients(float(settings["static_contact_frequency"]), zeta)
        ip.max_ccd_substeps = int(settings["max_ccd_substeps"])
        ip.friction_model = rp.FrictionModel.COULOMB if settings["friction_model"] == "coulomb" \
            else rp.FrictionModel.SIMPLIFIED
        ip.contact_recycling = bool(settings["contact_recycling"])
        self._world = world
        contact = scene.has("contact")
        ccd = bool(settings["ccd"]) and contact
        gyro = scene.has("gyroscopic")

        e_of, f_of = self._materials(scene) if contact else ({}, {})
        mul = rp.CoefficientCombineRule.MULTIPLY

        def material(c: Any, key: Any) -> Any:
            return (c.friction(f_of.get(key, 0.0)).restitution(e_of.get(key, 0.0))
                    .friction_combine_rule(mul).restitution_combine_rule(mul))

        self._handles = []
        for b in scene.bodies:
            builder = (rp.RigidBodyBuilder(rp.RigidBodyType.DYNAMIC)
                       .position((tuple(map(float, b.position)), tuple(map(float, wxyz_to_xyzw(b.orientation)))))
                       .linvel(tuple(map(float, b.velocity))).angvel(tuple(map(float, b.angular_velocity)))
                       .can_sleep(False).ccd_enabled(ccd).gyroscopic_forces(gyro)
                       .allow_fast_rotation(bool(settings["fast_rotation"]))
                       .additional_mass_properties(rp.MassProperties(
                           mass=float(b.mass), principal_inertia=tuple(map(float, b.inertia)))))
            colliders = [material(body_collider(rp, b).density(0.0), ("body", b.index))] if contact else []
            self._handles.append(world.add_body(builder, colliders))
        # collider handle index -> scene static index (adapters.contact_forces.rapier_rows)
        self._static_of = {world.add_collider(material(static_collider(rp, s), ("static", s.index))).index: s.index
                           for s in scene.statics} if contact else {}

        if scene.joints:  # adapters/rapier_joints.py
            add_joints(rp, world, scene, self._handles, settings["joints"], self.notes, self.info)
        joints = settings["springs"] == "joint"
        self._n_springs = self._add_springs(scene) if joints else 0
        self._forces = StateForces(scene, springs=not joints) or None
        if self._forces:
            self.notes.append(DRAG_NOTE + "; held over Rapier's substeps" if joints else
                              "springs, dampers and drag: explicit forces from the state at the start of each "
                              "step, held over Rapier's substeps")
        # live proxies (they follow the engine's state): the getters' fallback
        # and the byte reader's check
        self._bodies = [world.rigid_bodies[h] for h in self._handles]
        self._n = scene.n_bodies
        self._reader: SetBytesReader | None = None
        if scene.joints and settings["joints"] == "multibody":
            # a multibody link's pose is the multibody's: the set's bytes lag the
            # getters (by up to 2.4e-5 m on the conical pendulum), so the getters
            # are read (tests/test_joints_engines.py::test_conical_pendulum_rate)
            self.info["state_reader_fallback"] = "multibody joints: the getters are read"
        else:
            try:  # one call per step for every body's state (adapters.rapier_batch)
                self._reader = SetBytesReader(rp, world, self._bodies)
            except ValueError as e:
                self.info["state_reader_fallback"] = str(e)
        self.info["state_reader"] = "set_bytes" if self._reader is not None else "getters"
        self.steps = 0
        self._stages = {
            "gravity": bool(np.any(scene.gravity != 0)), "contact": contact, "ccd": ccd,
            "gyroscopic": gyro, "spring_joints": self._n_springs,
            "external_forces": self._forces.kinds if self._forces else [],
            "substeps": int(settings["iterations"]), "pgs_iterations": int(settings["pgs_iterations"]),
        }

    def _add_springs(self, scene: Scene) -> int:
        """Every spring/damper as a Rapier ``SpringJoint`` with the force-based
        model: stiffness (N/m) and damping (N s/m) as the spec gives them,
        between the anchors (a fixed body at the origin holds world anchors),
        solved implicitly in each substep; contacts between the two bodies stay on."""
        springs = [sp for sp in scene.springs if sp.stiffness != 0.0 or sp.damping != 0.0]
        if not springs:
            return 0
        world = self._world
        ground = world.add_body(rp.RigidBodyBuilder(rp.RigidBodyType.FIXED), [])
        for sp in springs:
            joint = (rp.SpringJoint.builder(float(sp.rest_length), float(sp.stiffness), float(sp.damping))
                     .local_anchor1(tuple(map(float, sp.anchor_a))).local_anchor2(tuple(map(float, sp.anchor_b)))
                     .spring_model(rp.MotorModel.FORCE_BASED).contacts_enabled(True).build())
            world.impulse_joints.insert(ground if sp.a < 0 else self._handles[sp.a],
                                        ground if sp.b < 0 else self._handles[sp.b], joint, True)
        self.notes.append("springs and dampers: Rapier SpringJoint (force-based model: the spec's stiffness and "
                          "damping between the anchors), solved implicitly in every substep")
        return len(springs)

    def _materials(self, scene: Scene) -> tuple[dict, dict]:
        """(restitution, friction) per collider key ('body', i) / ('static',
        j): per-material values whose products give every pair, else
        per-object least-squares values (residual noted)."""
        f = per_material_factors(scene, [b.material for b in scene.bodies], [s.material for s in scene.statics],
                                 ENGINE)
        keys = [("body", b.index) for b in scene.bodies] + [("static", s.index) for s in scene.statics]
        mats = [b.material for b in scene.bodies] + [s.material for s in scene.statics]
        if f is None:
            return {}, {}
        self.notes.extend(f.notes)
        if f.per_shape:
            self.info["material_mode"] = "per_material"
            return ({k: f.elasticity.get(m, 0.0) for k, m in zip(keys, mats)},
                    {k: f.friction.get(m, 0.0) for k, m in zip(keys, mats)})
        o = per_object_factors(scene, ENGINE, math.inf)
        self.notes.extend(n for n in o.notes if "rolling" not in n and "one Coulomb" not in n)
        self.info["material_mode"] = "per_object"
        self.info["material_residual"] = o.info["material_residual"]
        return dict(zip(keys, map(float, o.restitution))), dict(zip(keys, map(float, o.friction)))

    # ---- stepping ----------------------------------------------------------
    def step(self, n: int = 1) -> None:
        world = self._world
        if self._forces is None:
            for _ in range(n):
                world.step()
        else:
            pos, quat, vel, angvel = (np.empty((self._n, k)) for k in (3, 4, 3, 3))
            idx = self._forces.bodies
            for _ in range(n):
                self.read_state(pos, quat, vel, angvel)
                F, T = self._forces.evaluate(pos, quat, vel, angvel)
                for i in idx:
                    rb = self._bodies[i]
                    rb.reset_forces(False)
                    rb.reset_torques(False)
                    rb.add_force(tuple(F[i]), False)
                    rb.add_torque(tuple(T[i]), False)
                world.step()
        self.steps += n

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Step n times recording every step: one ``to_bytes()`` of the
        rigid-body set per step, copied into a reused row buffer and, every
        :data:`CHUNK_BYTES` of them, decoded and converted into the (n, bodies,
        3|4) blocks at once (:class:`adapters.rapier_batch.SetBytesReader`;
        the block's last row checked against the getters on up to 16
        bodies), also the complete steps before an exception.  Per step:
        the step call, the set's bytes and one slice assignment into the
        buffer, nothing else."""
        if self._forces is not None or self._reader is None:
            return super().step_record(n, pos, quat, vel, angvel)
        self.block_done = 0
        chunk = max(32, min(1024, CHUNK_BYTES // max(1, self._reader.need)))
        for c in range(0, n, chunk):
            m = min(chunk, n - c)
            self._record(m, pos[c:c + m], quat[c:c + m], vel[c:c + m], angvel[c:c + m])
        if n > 0 and self._n:  # what landed in the last recorded row, against the getters
            self._reader.check_state(pos[n - 1], quat[n - 1], vel[n - 1], angvel[n - 1], sample=16)

    def _record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """:meth:`step_record`'s chunk of n >= 1 steps: the set's bytes of
        each step into a row of the reader's buffer, then all rows decoded
        into the (n, bodies, 3|4) arrays (also the complete rows before an
        exception; ``block_done`` and ``steps`` count them)."""
        reader = self._reader
        step, blob = self._world.step, reader.blob
        odd: dict = {}  # rows whose bytes have another length than the chunk's first
        L, k = 0, 0  # k: complete steps
        try:
            step()
            b = blob()
            L = len(b)  # the first step's length is the chunk's row length
            rows, spans = reader.block(n, L)
            rows[spans[0]] = b
            k = 1
            for k, sl in enumerate(spans[1:n], 1):
                step()
                b = blob()
                try:
                    rows[sl] = b
                except ValueError:
                    odd[k] = b
            k = n
        finally:
            self.steps += k
            self.block_done += k
            reader.rows_into(k, L, odd, pos[:k], quat[:k], vel[:k], angvel[:k])

    @staticmethod
    def _write(a: np.ndarray, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Rows [qx, qy, qz, qw, x, y, z, v, w] (..., 13) into the harness's
        arrays (Rapier's (x, y, z, w) quaternion to wxyz)."""
        pos[...] = a[..., 4:7]
        quat[...] = xyzw_to_wxyz(a[..., 0:4])
        vel[...] = a[..., 7:10]
        angvel[...] = a[..., 10:13]

    bare_record = bare_loops.rapier

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """World positions (n, 3) m, wxyz quaternions (n, 4), linear (n, 3)
        m/s and angular (n, 3) rad/s velocities, world frame, about the
        centre of mass: one ``to_bytes()`` of the set decoded (the four
        getters per body without the byte reader)."""
        a = self._reader.decode([self._reader.blob()])[0] if self._reader is not None else getter_rows(self._bodies)
        self._write(a, pos, quat, vel, angvel)

    def contacts(self) -> np.ndarray:
        """The narrow phase's solver contacts after the last step: rows
        [world point (midway between the two bodies' points), manifold normal
        (from collider 1 toward collider 2), depth = -dist]."""
        rows = []
        bodies = self._world.rigid_bodies
        for pair in self._world.narrow_phase.contact_pairs():
            for m in pair.manifolds:
                d = m.data
                n = d.normal.to_tuple()
                for c in d.solver_contacts:
                    p1, p2 = d.solver_contact_world_points(c, bodies)
                    p = 0.5 * (np.asarray(p1.to_tuple()) + np.asarray(p2.to_tuple()))
                    rows.append((*p, *n, -float(c.dist)))
        return np.array(rows, float).reshape(-1, 7)

    def stages(self) -> dict[str, Any]:
        return {**getattr(self, "_stages", {}), "steps": getattr(self, "steps", 0)}

    def close(self) -> None:
        self._world = None
        self._handles = []
        self._bodies = []
        self._reader = None
