"""MuJoCo adapter (mujoco 4.x, 3D; planar scenes run as 3D scenes).

The model is an MJCF string written from the :class:`contract.scene.Scene`
(never from TOML) by :func:`adapters.mjcf.build_mjcf`, with each contact
pair's restitution calibrated by :func:`adapters.mujoco_impacts.calibrate_pairs`.

Bodies
    One ``<body>`` per scene body with a ``<freejoint/>``, an explicit
    ``<inertial mass=... diaginertia=...>`` at the body origin (so MuJoCo's
    mass and principal inertia are exactly the Scene's, whatever the geom
    says; ``inertiafromgeom="false"``; all scaled by one power of two when
    the smallest is below MuJoCo's compiler floor, :func:`adapters.mjcf.mass_scale`) and one geom: sphere (size r), box
    (half extents), capsule (size r, half_length: MuJoCo's capsule size is
    the radius and the half length of the cylindrical part), cylinder (r,
    half_length).  Capsule and cylinder axes are the geom's local z = body z,
    as in the Scene.

Statics
    A plane {x : n.x = offset} (slopes arrive as planes) is a ``plane`` geom at
    ``pos = offset * n`` with ``zaxis = n`` (MuJoCo planes are infinite for
    collision and solid below their z).  A static box is a ``box`` geom.

The one conversion point (:meth:`MujocoAdapter.read_state`, and the initial
state in :meth:`MujocoAdapter.build`): for free joints ``qpos[0:3]`` is the
world position of the body origin (= centre of mass here), ``qpos[3:7]`` the
orientation quaternion (w, x, y, z), ``qvel[0:3]`` the world linear velocity
and ``qvel[3:6]`` the angular velocity in the **body frame**.  The initial
one is converted with :func:`contract.rotation.world_to_body_angvel`; the
read-back applies the same rule as
:func:`~contract.rotation.body_to_world_angvel`, w_world = R(q) w_body,
as one batched product with R from ``mj_kinematics`` on the current qpos
(the conventions function costs ~30 us per call on numpy 2, ten times a
small model's ``mj_step``; the tests assert both agree).  ``d.xpos``,
``d.xmat`` and ``d.contact`` are never read straight after ``mj_step``: they
describe the state before the step's integration.

Effects (everything absent is switched off)
    gravity     ``opt.gravity`` = scene gravity; absent -> mjDSBL_GRAVITY.
    contact     absent -> mjDSBL_CONTACT and geoms with contype = conaffinity
                = 0: no collision detection runs at all.
    friction    condim 3 with the pair's kinetic coefficient (elliptic or
                pyramidal cone, a setting); absent (or 0) -> condim 1.
                MuJoCo has one coefficient: a static coefficient above the
                kinetic one is not modelled (noted).
    rolling_friction  condim 6 with the rolling coefficient (m); MuJoCo's
                torsional coefficient is set to 0 (it clamps to 1e-5).
    restitution MuJoCo has no coefficient: each pair's ``solref`` (direct
                form, -stiffness, -damping) is calibrated numerically to the
                pair's e (:mod:`adapters.mujoco_calibration`), at the scene's
                predicted impact; absent -> calibrated to e = 0 (no bounce).
    spring, damper  a spatial tendon between two sites with ``stiffness``,
                ``damping`` and ``springlength`` = rest length: exactly a
                Hooke spring / dashpot between the anchor points.
    drag_linear, drag_quadratic  MuJoCo's ellipsoid fluid model calibrated
                to F = -(c1 + c2 |v|) v where it reproduces it (spheres that
                do not spin: :func:`adapters.forces.mujoco_fluid`), then
                integrated by MuJoCo's integrator; else that force written
                into ``xfrc_applied`` before every engine step from the
                current velocity (explicit in time; no drag torque), and the
                row says so (notes, info["drag"]).
    gyroscopic  MuJoCo always integrates w x I w and cannot switch it off: a
                scene without the effect where it matters at t = 0 (unequal
                inertia and w not along a principal axis) is unsupported.

Materials
    MuJoCo combines two geoms' friction by element-wise max and their solref
    by a solmix-weighted mean.  The adapter gives every geom the contact
    parameters of the most common pair signature (condim, friction, solref)
    so that the engine's combination yields it, and writes an explicit
    ``<contact><pair>`` with the exact values for every other pair.  An
    explicit pair overrides MuJoCo's automatic (dynamic) contact for the same
    two geoms (measured on 4.0.1: no duplicate contacts, the pair's solref
    wins), so broad phase stays automatic and only mixed-material scenes pay
    for explicit pairs.

Sibling modules: the MJCF writer in :mod:`adapters.mjcf`, the predicted
impacts and per-group calibration in :mod:`adapters.mujoco_impacts` (the
1-D calibration itself in :mod:`adapters.mujoco_calibration`), the warning
sink in :mod:`adapters.quiet`, drag coefficients in :mod:`adapters.forces`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters import bare_loops
from physbench.adapters.base import Adapter, Capabilities, Unsupported, module_version
from physbench.adapters.forces import DRAG_EXTERNAL, DRAG_NOTE, drag_coefficients
from physbench.adapters.mjcf import JOINT_TYPES, build_mjcf, joint_start, joint_tree_reason
from physbench.adapters.mujoco_impacts import calibrate_pairs
from physbench.adapters.mujoco_settings import mujoco_settings
from physbench.adapters.quiet import collect_mujoco_warnings
from physbench.contract.rotation import quat_rotate, world_to_body_angvel
from physbench.contract.scene import Scene

try:  # the engine; a missing mujoco only makes its runs unavailable
    import mujoco

    _IMPORT_ERROR = ""
except ImportError as _e:  # pragma: no cover - depends on the environment
    mujoco = None
    _IMPORT_ERROR = f"import mujoco failed: {_e}"

ENGINE = "mujoco"

#: MuJoCo's warnings of the run in progress, kept instead of written to
#: MUJOCO_LOG.TXT (:func:`adapters.quiet.collect_mujoco_warnings`); they
#: become notes of the run.
_WARNINGS: list[str] = collect_mujoco_warnings(mujoco) if mujoco is not None else []

_SHAPES = frozenset({"sphere", "box", "capsule", "cylinder"})
_STATIC_SHAPES = frozenset({"plane", "slope", "box"})
_EFFECTS = frozenset({"gravity", "contact", "restitution", "friction", "rolling_friction",
                      "drag_linear", "drag_quadratic", "spring", "damper", "gyroscopic", "joint"})

class MujocoAdapter(Adapter):
    """Adapter for MuJoCo 4.x (free rigid bodies, MJCF built from the Scene)."""

    name = ENGINE
    gyroscopic_always_on = "MuJoCo"

    # ---- declaration -------------------------------------------------------
    @classmethod
    def capabilities(cls) -> Capabilities:
        return Capabilities(
            engine=ENGINE,
            version=mujoco.__version__ if mujoco is not None else module_version("mujoco"),
            dimensions=3,
            shapes=_SHAPES,
            static_shapes=_STATIC_SHAPES,
            effects=_EFFECTS,
            settings=mujoco_settings(),
            available=mujoco is not None,
            unavailable_reason=_IMPORT_ERROR,
            joint_kinds=frozenset(JOINT_TYPES),
            notes=(
                "restitution is calibrated per pair (solref), not native",
                "one friction coefficient: no static/kinetic split",
                "the gyroscopic term is always on",
                "soft contacts: bodies overlap by design",
            ),
        )

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        return super().unsupported_reason(scene) or joint_tree_reason(scene)

    # ---- build -------------------------------------------------------------
    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        reason = self.unsupported_reason(scene)
        if reason is not None:
            raise Unsupported(reason)
        _WARNINGS.clear()  # a warning belongs to the run that raised it
        self.scene = scene
        self.settings = dict(settings)
        pair_solref = calibrate_pairs(scene, settings, self.notes, self.info)
        xml, meta = build_mjcf(scene, settings, pair_solref, self.notes)
        self.xml = xml
        self.meta = meta
        m = mujoco.MjModel.from_xml_string(xml)
        d = mujoco.MjData(m)
        self.m, self.d = m, d
        self.n_bodies = scene.n_bodies
        self._roll_state = None
        n = scene.n_bodies
        self._jointed = bool(scene.joints)
        if self._jointed:
            self._build_jointed(scene, settings, meta)
            return

        # the free joints come in body order: qpos 7 and qvel 6 per body
        if n:
            assert m.njnt == n and m.nq == 7 * n and m.nv == 6 * n
            assert list(m.jnt_qposadr) == list(range(0, 7 * n, 7))
            assert list(m.jnt_dofadr) == list(range(0, 6 * n, 6))
        # preallocated views into MuJoCo's own buffers (no copies, no per-call
        # indexing): d.qpos/d.qvel are fixed arrays for the life of d.
        qpos = d.qpos.reshape(n, 7)
        qvel = d.qvel.reshape(n, 6)
        assert n == 0 or (np.shares_memory(qpos, d.qpos) and np.shares_memory(qvel, d.qvel))
        self._pos, self._quat = qpos[:, 0:3], qpos[:, 3:7]
        self._lin, self._ang = qvel[:, 0:3], qvel[:, 3:6]
        self._ang_col = self._ang[..., None]  # (n, 3, 1) for the batched R @ w
        ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"b{i}") for i in range(n)]
        assert ids == list(range(1, n + 1))  # body 0 is the world
        self._xmat = d.xmat[1:n + 1].reshape(n, 3, 3)  # row-major R (body -> world)
        assert n == 0 or np.shares_memory(self._xmat, d.xmat)

        x0, q0, v0, w0 = scene.initial_state()
        self._pos[...] = x0
        self._quat[...] = q0
        self._lin[...] = v0
        self._ang[...] = world_to_body_angvel(q0, w0)  # world -> body frame
        mujoco.mj_forward(m, d)

        # drag: MuJoCo's fluid model where it carries the spec's law, else
        # F = -(c1 + c2 |v|) v into xfrc_applied before every step
        # (tests/test_adapter_mujoco.py::test_drag_uses_the_fluid_model_where_it_can)
        c1, c2 = drag_coefficients(scene)
        c1, c2 = c1 * meta["mass_scale"], c2 * meta["mass_scale"]  # forces on the scaled masses (mjcf.mass_scale)
        fluid = meta["fluid"]
        if fluid:
            self.info["drag"] = (f"MuJoCo's ellipsoid fluid model: viscosity {fluid['viscosity']:.6g}, density "
                                 f"{fluid['density']:g}, blunt drag coefficient per sphere c_quadratic / (pi r^2)")
            self.notes.append("drag: MuJoCo's ellipsoid fluid model (fluidshape=ellipsoid), calibrated to "
                              "F = -(c_linear + c_quadratic |v|) v: viscosity c_linear / (6 pi r), density 1, blunt "
                              "drag coefficient c_quadratic / (pi r^2), its other coefficients 0")
        self._drag = not fluid and bool(np.any(c1 > 0) or np.any(c2 > 0))
        if self._drag:
            self.info["drag"] = f"{DRAG_EXTERNAL} ({meta['fluid_refused']})"
            self._c1, self._c2 = c1, c2
            self._force = d.xfrc_applied[1:n + 1, 0:3]
            assert np.shares_memory(self._force, d.xfrc_applied)
            self._sq = np.empty((n, 3))
            self._speed = np.empty(n)
            self._coef_col = self._speed[:, None]
            self.notes.append(f"{DRAG_NOTE} ({meta['fluid_refused']})")
        self._stages = {
            "engine": ENGINE,
            "gravity": scene.has("gravity"),
            "contact": scene.has("contact"),
            "dynamic_contacts": meta["dynamic_contacts"],
            "explicit_pairs": meta["explicit_pairs"],
            "condim": meta["condim"],
            "restitution_calibrated": len(self.info.get("restitution_calibration", [])),
            "tendon_springs": meta["tendons"],
            "mass_scale": meta["mass_scale"],
            "drag": "fluid" if fluid else ("external" if self._drag else False),
            "gyroscopic": True,
            "integrator": settings["integrator"],
            "cone": settings["cone"],
            "speculative": bool(settings["speculative"]),
        }
        self.steps = 0

    def _build_jointed(self, scene: Scene, settings: dict[str, Any], meta: dict[str, Any]) -> None:
        """A scene with joints (to the world: mjcf.joint_tree_reason): the
        state is read from the bodies' world poses and velocities
        (:meth:`read_state`), not from free-joint coordinates."""
        m, d = self.m, self.d
        try:
            joint_start(scene, m, d)
        except ValueError as e:
            raise Unsupported(str(e)) from None
        mujoco.mj_forward(m, d)
        self._drag = False
        self._res = np.empty(6)
        # scene body i is MuJoCo's body "b<i>", numbered depth-first through the tree
        self._ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"b{i}") for i in range(scene.n_bodies)],
                             dtype=int)
        self._stages = {"engine": ENGINE, "gravity": scene.has("gravity"), "contact": scene.has("contact"),
                        "joints": len(scene.joints), "dofs": int(m.nv), "mass_scale": meta["mass_scale"],
                        "gyroscopic": True, "integrator": settings["integrator"]}
        self.steps = 0

    # ---- stepping ----------------------------------------------------------
    def step(self, n: int = 1) -> None:
        m, d = self.m, self.d
        if not self._drag:
            mujoco.mj_step(m, d, n)
        else:
            lin, sq, sp, c1, c2, col, force = (self._lin, self._sq, self._speed, self._c1, self._c2,
                                               self._coef_col, self._force)
            for _ in range(n):
                np.multiply(lin, lin, out=sq)
                np.sum(sq, axis=1, out=sp)
                np.sqrt(sp, out=sp)
                np.multiply(sp, c2, out=sp)
                np.add(sp, c1, out=sp)
                np.multiply(lin, col, out=force)
                np.negative(force, out=force)
                mujoco.mj_step(m, d)
        self.steps += n

    bare_loop = bare_loops.mujoco_bare_loop
    bare_record = bare_loops.mujoco

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Step and record a block of n steps in compiled code.

        ``mujoco.rollout`` runs the n mj_step calls in C and returns every
        step's full physics state; the block is then converted once,
        vectorised (body-frame angular velocity -> world with the recorded
        quaternions).  The solver warm start is carried across blocks, so the
        states are those of a plain mj_step loop (a test asserts equality).
        Scenes with drag need a Python force update before each step and use
        the per-step loop."""
        if self._drag or self._jointed or self.m.nq != 7 * self.n_bodies:
            return super().step_record(n, pos, quat, vel, angvel)
        from mujoco import rollout

        m, d = self.m, self.d
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        if self._roll_state is None or self._roll_state.shape[1] < n:
            self._state0 = np.empty((1, mujoco.mj_stateSize(m, spec)))
            self._roll_state = np.empty((1, max(n, 256), self._state0.shape[1]))
            self._warm = np.empty((1, m.nv))
        mujoco.mj_getState(m, d, self._state0[0], spec)
        self._warm[0] = d.qacc_warmstart
        out = self._roll_state[:, :n]
        rollout.rollout([m], [d], self._state0, nstep=n, initial_warmstart=self._warm, state=out,
                        skip_checks=True)
        st = out[0]
        nq, nb = m.nq, self.n_bodies
        # FULLPHYSICS layout: time (1), qpos (nq), qvel (nv), then the rest
        qpos = st[:, 1:1 + nq].reshape(n, nb, 7)
        qvel = st[:, 1 + nq:1 + nq + m.nv].reshape(n, nb, 6)
        pos[...] = qpos[..., 0:3]
        quat[...] = qpos[..., 3:7]
        vel[...] = qvel[..., 0:3]
        quat_rotate(quat, qvel[..., 3:6], out=angvel)
        mujoco.mj_setState(m, d, st[-1], spec)
        d.qacc_warmstart[:] = self._rollout_data_warmstart(d)
        self.steps += n
        self.block_done = n

    @staticmethod
    def _rollout_data_warmstart(d) -> np.ndarray:
        # rollout steps ``d`` itself (single thread), so its warm start is the
        # one after the block's last step
        return d.qacc_warmstart

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        if self._jointed:
            # poses and velocities of the current qpos/qvel (after mj_step the
            # derived quantities are a step old); no solver call, so the warm
            # start is untouched
            m, d, res = self.m, self.d, self._res
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            mujoco.mj_comVel(m, d)
            ids = self._ids
            np.copyto(pos, d.xpos[ids])
            np.copyto(quat, d.xquat[ids])
            for i, bid in enumerate(ids):
                mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, int(bid), res, 0)
                angvel[i] = res[0:3]
                vel[i] = res[3:6]
            return
        np.copyto(pos, self._pos)
        np.copyto(quat, self._quat)
        np.copyto(vel, self._lin)
        # body frame -> world: w_world = R(q) w_body, the rule of
        # conventions.body_to_world_angvel (tests assert equality).  R comes
        # from mj_kinematics on the *current* qpos (after mj_step d.xmat is
        # one step old); this costs ~0.2 us for small models against ~30 us
        # for conventions.body_to_world_angvel (np.cross is slow on numpy 2),
        # and is overwritten by the next mj_step, so it changes nothing.
        mujoco.mj_kinematics(self.m, self.d)
        np.matmul(self._xmat, self._ang_col, out=angvel[..., None])

    def contacts(self) -> np.ndarray:
        """``d.contact`` of the last ``mj_step``: the contacts that step
        solved, found at its start (before its integration).  Normal from
        geom1 toward geom2; depth = -dist."""
        d = self.d
        k = int(d.ncon)
        out = np.empty((k, 7))
        if k:
            c = d.contact
            out[:, 0:3] = c.pos[:k]
            out[:, 3:6] = c.frame[:k, 0:3]
            out[:, 6] = -c.dist[:k]
        return out

    def close(self) -> None:
        # the views keep MjData's buffers alive: drop them with the model
        self.m = self.d = None
        self._pos = self._quat = self._lin = self._ang = self._ang_col = self._xmat = None
        self._force = None

    def stages(self) -> dict[str, Any]:
        self.notes.extend(f"mujoco warning: {w}" for w in _WARNINGS)
        _WARNINGS.clear()
        out = dict(getattr(self, "_stages", {}))
        out["steps"] = getattr(self, "steps", 0)
        return out
