"""Drake adapter (pydrake 1.51, 3D; planar scenes run as 3D scenes).

One ``MultibodyPlant`` (with its ``SceneGraph``) in a diagram run by a
``Simulator``.  A ``VectorLogSink`` on the plant's state port samples the
state every dt inside Drake, so a block of steps is one ``AdvanceTo`` call.

Bodies
    One rigid body per scene body (a free body: Drake adds the quaternion
    floating joint at Finalize), ``SpatialInertia`` of the scene's mass and
    principal moments about the body origin = centre of mass, and one
    collision geometry: ``Sphere(r)``, ``Box(2 half extents)``,
    ``Capsule(r, 2 half_length)``, ``Cylinder(r, 2 half_length)`` (axis z,
    as in the Scene).  Statics: a plane is a ``HalfSpace`` posed by its
    normal, a static box a ``Box`` welded to the world.
State
    Positions of a free body are [qw qx qy qz x y z], velocities [w; v], both
    world frame (read straight from the plant's state vector).  A discrete
    plant does not renormalise its quaternions (a rolling ball's norm grows
    to 2.2 in 2 s at dt 1/240); Drake's kinematics use q / |q|, and so does
    the read-back.
Contact (point contact where the scene has restitution, else hydroelastic
with point fallback; ``contact_model`` overrides)
    Stiffness per body k = m omega^2, omega = pi / (contact_steps dt); statics
    are 1e20 N/m, so Drake's series rule gives every pair k = m_eff omega^2
    (an undamped contact lasts contact_steps steps), or ``point_stiffness``
    when set.  Dissipation realises the pair's restitution
    (:mod:`adapters.drake_contact`): Hunt–Crossley d = alpha(e) / v_impact
    (tamsi, similar, lagged, continuous time) or the relaxation time
    tau = beta(e) / omega (SAP); absent restitution -> e = 0, realised as
    e = 0.005.  Friction: ``CoulombFriction(static, kinetic)``, both
    coefficients (Drake combines two geometries' by 2ab / (a + b); every
    scene pair equal -> exact, otherwise unsupported).
Effects
    gravity (the plant's gravity field; absent -> zero), contact (absent ->
    no collision geometry), friction (absent -> 0), restitution (above),
    spring/damper (``LinearSpringDamper``; a zero rest length is
    unsupported: Drake requires a positive free length), drag (a held force
    on the applied-spatial-force port before every step; those scenes step
    one dt per ``AdvanceTo``), gyroscopic (always on), joint (the plant's
    own joints in a tree, :mod:`adapters.drake_joints`; the bodies then read
    through the plant's kinematics).  No rolling friction.
Contact forces
    Read from the plant's ``ContactResults`` only when a check asks for a
    contact-law metric (:func:`adapters.contact_forces.drake_rows`: a row
    per point pair, or per hydroelastic surface at its centroid with the
    resultant force).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.base import Adapter, Capabilities, Unsupported, module_version, not_installed
from physbench.adapters.drake_contact import contact_materials, quiet_drake
from physbench.adapters.drake_settings import settings as drake_settings
from physbench.adapters.drake_joints import JOINT_KINDS, add_joints, read_bodies, start_state, tree_reason
from physbench.adapters.forces import drag_coefficients
from physbench.contract.scene import Scene

#: '' when Drake is installed, else what is missing: Drake itself is imported
#: by the first build (a suite's check reads the capabilities without it)
_MISSING = not_installed("drake")

ENGINE = "drake"
_SHAPES = frozenset({"sphere", "box", "capsule", "cylinder"})
_EFFECTS = frozenset({"gravity", "contact", "restitution", "friction", "drag_linear", "drag_quadratic",
                      "spring", "damper", "gyroscopic"})
class DrakeAdapter(Adapter):
    """Adapter for Drake's MultibodyPlant (free rigid bodies)."""

    name = ENGINE
    gyroscopic_always_on = "Drake"

    @classmethod
    def capabilities(cls) -> Capabilities:
        return Capabilities(
            engine=ENGINE, version=module_version("drake"), dimensions=3, shapes=_SHAPES,
            static_shapes=frozenset({"plane", "slope", "box"}), effects=_EFFECTS | {"joint"},
            joint_kinds=JOINT_KINDS, settings=drake_settings(),
            available=not _MISSING, unavailable_reason=_MISSING,
            notes=("no restitution coefficient: dissipation calibrated to e (Hunt-Crossley or SAP "
                   "relaxation time), e = 0 realised as 0.005",
                   "compliant point contact: bodies overlap by design", "the gyroscopic term is always on",
                   "no rolling friction"))

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        reason = super().unsupported_reason(scene) or tree_reason(scene)
        if reason is None:
            for sp in scene.springs:
                if sp.rest_length <= 0.0 and (sp.stiffness or sp.damping):
                    return ("Drake's LinearSpringDamper needs a positive free length; spring "
                            f"{sp.a}->{sp.b} has rest length {sp.rest_length:g} m")
        return reason

    @classmethod
    def resolve_settings(cls, scene: Scene, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
        """As the base, and a negative time_step or dissipation must be -1 (the
        default's marker)."""
        out = super().resolve_settings(scene, overrides)
        for key in ("time_step", "dissipation"):
            if out[key] < 0.0 and out[key] != -1.0:
                raise ValueError(f"setting {key}: expected -1 (default) or a value >= 0, got {out[key]!r}")
        return out

    # ---- build -------------------------------------------------------------
    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        with quiet_drake():
            self._build(scene, settings)

    def _build(self, scene: Scene, settings: dict[str, Any]) -> None:
        # Drake is imported by the first build, not with this module (0.2 s of a sweep client's start-up)
        from pydrake.common.eigen_geometry import Quaternion
        from pydrake.geometry import Box, Capsule, Cylinder, HalfSpace, Sphere
        from pydrake.math import RigidTransform
        from pydrake.multibody.math import SpatialForce
        from pydrake.multibody.plant import AddMultibodyPlant, ExternallyAppliedSpatialForce, MultibodyPlantConfig
        from pydrake.multibody.tree import LinearSpringDamper, SpatialInertia, UnitInertia
        from pydrake.systems.analysis import ResetIntegratorFromFlags, Simulator
        from pydrake.systems.framework import DiagramBuilder
        from pydrake.systems.primitives import LogVectorOutput

        reason = self.unsupported_reason(scene)
        if reason is not None:
            raise Unsupported(reason)
        self.scene, self.settings, self.n = scene, dict(settings), scene.n_bodies
        dt = self.dt = float(settings["dt"])
        ts = float(settings["time_step"])
        ts = dt if ts < 0.0 else ts
        if 0.0 < ts and abs(ts - dt) > 1e-12 * dt:
            self.notes.append(f"the plant steps at time_step {ts:g} s, states are sampled every dt {dt:g} s")
        contact = scene.has("contact") and bool(scene.contact_pairs())
        model = settings["contact_model"]
        if model == "auto":
            model = "point" if scene.has("restitution") else "hydroelastic_with_fallback"
        settings = self.settings = dict(settings, contact_model=model)
        material = contact_materials(scene, settings, ts, self.notes, self.info) if contact else None
        builder = DiagramBuilder()
        cfg = MultibodyPlantConfig(time_step=ts, contact_model=model,
                                   discrete_contact_approximation=settings["approximation"] if ts > 0 else "")
        plant, _ = AddMultibodyPlant(cfg, builder)
        self.plant = plant
        bodies = []
        for b in scene.bodies:
            I = np.asarray(b.inertia, float) / b.mass
            body = plant.AddRigidBody(f"b{b.index}", SpatialInertia(b.mass, np.zeros(3), UnitInertia(*I)))
            bodies.append(body)
            if contact:
                shape = {"sphere": lambda: Sphere(b.radius), "box": lambda: Box(*(2.0 * np.asarray(b.half_extents))),
                         "capsule": lambda: Capsule(b.radius, 2.0 * b.half_length),
                         "cylinder": lambda: Cylinder(b.radius, 2.0 * b.half_length)}[b.shape]()
                plant.RegisterCollisionGeometry(body, RigidTransform(), shape, f"g{b.index}",
                                                material(b.index, True))
        for s in scene.statics if contact else ():
            if s.shape == "plane":
                n = np.asarray(s.normal, float)
                X, shape = HalfSpace.MakePose(n, n * s.offset), HalfSpace()
            else:
                X = RigidTransform(Quaternion(*s.orientation), np.asarray(s.position, float))
                shape = Box(*(2.0 * np.asarray(s.half_extents)))
            plant.RegisterCollisionGeometry(plant.world_body(), X, shape, f"s{s.index}", material(s.index, False))
        for sp in scene.springs:
            if sp.stiffness or sp.damping:
                ba = plant.world_body() if sp.a < 0 else bodies[sp.a]
                bb = plant.world_body() if sp.b < 0 else bodies[sp.b]
                plant.AddForceElement(LinearSpringDamper(ba, np.asarray(sp.anchor_a, float), bb,
                                                         np.asarray(sp.anchor_b, float), sp.rest_length,
                                                         sp.stiffness, sp.damping))
        joints = add_joints(plant, scene, bodies) if scene.joints else []  # adapters/drake_joints.py
        self._bodies = bodies if joints else None
        plant.mutable_gravity_field().set_gravity_vector(
            np.asarray(scene.gravity, float) if scene.has("gravity") else np.zeros(3))
        plant.Finalize()
        self.log = LogVectorOutput(plant.get_state_output_port(), builder, dt)
        self.diagram = builder.Build()
        self.sim = Simulator(self.diagram)
        ctx = self.sim.get_mutable_context()
        self.pctx = plant.GetMyMutableContextFromRoot(ctx)
        self.lctx = self.log.GetMyContextFromRoot(ctx)
        if joints:  # joint coordinates: bodies are read through the plant's kinematics
            start_state(plant, self.pctx, scene, bodies, joints)
        else:
            x0, q0, v0, w0 = scene.initial_state()
            qi = np.array([bd.floating_positions_start() for bd in bodies], int).reshape(-1, 1)
            vi = np.array([plant.num_positions() + bd.floating_velocities_start_in_v() for bd in bodies],
                          int).reshape(-1, 1)
            self._iq, self._ip = qi + np.arange(4), qi + 4 + np.arange(3)  # (n, 4) and (n, 3) state indices
            self._iw, self._iv = vi + np.arange(3), vi + 3 + np.arange(3)
            state = np.zeros(plant.num_positions() + plant.num_velocities())
            state[self._iq], state[self._ip], state[self._iw], state[self._iv] = q0, x0, w0, v0
            plant.SetPositionsAndVelocities(self.pctx, state)
        if ts == 0.0:
            integ = ResetIntegratorFromFlags(self.sim, settings["integrator"], dt)
            integ.set_target_accuracy(float(settings["accuracy"]))
        c1, c2 = drag_coefficients(scene)
        self._drag = [(bodies[i].index(), float(c1[i]), float(c2[i])) for i in range(self.n) if c1[i] or c2[i]]
        self._drag_types = (ExternallyAppliedSpatialForce, SpatialForce)  # (for each step's _apply_drag)
        if self._drag:
            self._drag_port = plant.get_applied_spatial_force_input_port()
            self.notes.append("drag: a force at the centre of mass from the velocity at the start of each "
                              "step, held over the step (explicit); no drag torque")
        self.sim.Initialize()
        self._state = plant.GetPositionsAndVelocities(self.pctx)
        self.steps = 0
        if joints:
            self.notes.append("joints: MultibodyPlant joints (reduced coordinates), states read through the "
                              "plant's kinematics after every step")
            self.info["joints"] = {"form": "MultibodyPlant tree (reduced)", "joints": len(joints)}
        self._stages = {"engine": ENGINE, "time_step": ts, "continuous": ts == 0.0,
                        "approximation": settings["approximation"] if ts > 0 else None,
                        "integrator": settings["integrator"] if ts == 0 else None,
                        "contact_model": model, "contact": contact, "drag": bool(self._drag),
                        "springs": len(scene.springs), "gyroscopic": True}

    # ---- stepping ----------------------------------------------------------
    def _advance(self, n: int) -> None:
        if not self._drag:
            self.sim.AdvanceTo((self.steps + n) * self.dt)
            self.steps += n
            return
        for _ in range(n):
            self._apply_drag()
            self.steps += 1
            self.sim.AdvanceTo(self.steps * self.dt)

    def _apply_drag(self) -> None:
        ExternallyAppliedSpatialForce, SpatialForce = self._drag_types
        x = self.plant.GetPositionsAndVelocities(self.pctx)  # free bodies only (drag refuses joints)
        forces = []
        for (idx, c1, c2), iv in zip(self._drag, self._iv):
            v = x[iv]
            f = ExternallyAppliedSpatialForce()
            f.body_index = idx
            f.F_Bq_W = SpatialForce(np.zeros(3), -(c1 + c2 * float(np.linalg.norm(v))) * v)
            forces.append(f)
        self._drag_port.FixValue(self.pctx, forces)

    def step(self, n: int = 1) -> None:
        self._advance(n)
        self._state = self.plant.GetPositionsAndVelocities(self.pctx)

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """n steps in one AdvanceTo; the log sink's samples at the n step
        times are the recorded states (a test asserts they equal a step(1)
        loop's).  Jointed scenes step one dt at a time and read the bodies
        through the plant's kinematics."""
        if self._bodies is not None:
            return super().step_record(n, pos, quat, vel, angvel)
        self.block_done = 0
        log = self.log.GetMutableLog(self.lctx)
        log.Clear()
        t0 = self.steps
        blew_up = None
        try:
            self._advance(n)
        except RuntimeError as e:
            # a state that overflowed: SceneGraph refuses its non-finite pose.
            # The steps logged before it are kept and the rest recorded as
            # NaN, so that the runner reports the run as diverged.
            if "non-finite" not in str(e):
                raise
            blew_up = str(e)
            self.notes.append(f"Drake stopped at a non-finite state: {e}")
        times, data = log.sample_times(), log.data()
        k = np.rint(times / self.dt).astype(np.int64) - t0
        keep = (k >= 1) & (k <= n)
        rows = np.full(n, -1)
        rows[k[keep] - 1] = np.nonzero(keep)[0]  # the last sample at each step time wins
        if np.any(rows < 0) and blew_up is None:
            raise RuntimeError(f"Drake's log sink missed {int(np.sum(rows < 0))} of {n} step samples")
        st = np.where(rows[:, None] >= 0, data[:, np.maximum(rows, 0)].T if data.size else np.nan, np.nan)
        pos[...], quat[...], vel[...], angvel[...] = st[:, self._ip], st[:, self._iq], st[:, self._iv], st[:, self._iw]
        quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
        self._state = st[-1]
        self.block_done = n

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        if self._bodies is not None:
            return read_bodies(self.plant, self.pctx, self._bodies, pos, quat, vel, angvel)
        st = self._state
        pos[...], quat[...], vel[...], angvel[...] = st[self._ip], st[self._iq], st[self._iv], st[self._iw]
        quat /= np.linalg.norm(quat, axis=-1, keepdims=True)

    def contacts(self) -> np.ndarray:
        """The plant's point-pair contact results: for a discrete plant those
        the last step solved, found at its start (the sampled output port);
        point, normal nhat_BA_W (from B into A), depth (> 0 overlap)."""
        cr = self.plant.get_contact_results_output_port().Eval(self.pctx)
        k = cr.num_point_pair_contacts()
        out = np.empty((k, 7))
        for i in range(k):
            info = cr.point_pair_contact_info(i)
            pp = info.point_pair()
            out[i, 0:3] = info.contact_point()
            out[i, 3:6] = pp.nhat_BA_W
            out[i, 6] = pp.depth
        return out

    def stages(self) -> dict[str, Any]:
        out = dict(getattr(self, "_stages", {}))
        out["steps"] = getattr(self, "steps", 0)
        return out

    def close(self) -> None:
        self.sim = self.diagram = self.plant = self.pctx = self.lctx = self.log = None
