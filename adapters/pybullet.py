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
- **Springs, dampers and drag** are applied as world-frame external forces
  (``applyExternalForce(..., WORLD_FRAME)``) computed from the state at the
  start of each step (explicit in the force, like the engine's own gravity).
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
  ``r_a f_b + r_b f_a``); :func:`solve_product_values` finds per-object values
  that give the spec's pair values and reports a residual when no such values
  exist.  Bullet has one Coulomb coefficient: the kinetic one is used.
"""

from __future__ import annotations

import ctypes
import functools
import math
import os
import sys
from typing import Any

import numpy as np

from adapters.base import gyroscopic_reason, DT_SETTING, Adapter, Capabilities, Setting, Unsupported, module_version
from adapters.materials import solve_product_values, solve_rolling_values
from contract.rotation import wxyz_to_xyzw, xyzw_to_wxyz
from contract.scene import Scene

ENGINE = "pybullet"

# Bullet clamps every combined friction and rolling friction to this value
# (btManifoldResult::calculateCombined*Friction).
MAX_COMBINED_FRICTION = 10.0

# Relative residual above which a material product solve counts as failed.
MATERIAL_TOLERANCE = 1e-9

# CCD: Bullet sweeps a sphere of this fraction of the body's smallest
# half-size; pybullet sets the motion threshold that switches the sweep on to
# half the sphere radius.  0.5 keeps the swept sphere well inside every
# shape (so a sweep never reports a hit the real shape would not make) while
# a body moving more than a quarter of its thinnest half-size in one step is
# swept.
CCD_RADIUS_FRACTION = 1.0


# --------------------------------------------------------------------------
# lazy, silent import


_pb: Any = None
_import_error: str | None = None


def _flush_c_stdio() -> None:
    """fflush(NULL): push anything C code buffered for stdout/stderr out *now*."""
    try:
        ctypes.CDLL(None).fflush(None)
    except Exception:  # pragma: no cover - no libc symbol table
        pass


def _import_pybullet() -> Any:
    """Import pybullet with file descriptors 1 and 2 pointed at /dev/null.

    The module's C initialiser prints ``pybullet build time: ...`` (measured
    with 3.2.7: on stderr; ENGINE_NOTES had it on stdout, so both are
    silenced).  C-level output escapes ``contextlib.redirect_stdout`` and, on
    a pipe, sits in libc's buffer until exit, so: flush Python's and C's
    streams, point fds 1 and 2 at /dev/null, import, flush C's buffers into
    /dev/null, restore the fds.  The import error, if any, is kept as a
    Python exception (ImportError, cached), so silencing loses nothing.
    """
    global _pb, _import_error
    if _pb is not None:
        return _pb
    if _import_error is not None:
        raise ImportError(_import_error)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # pragma: no cover - closed stream
            pass
    _flush_c_stdio()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in saved:
            os.dup2(devnull, fd)
        try:
            import pybullet
        except Exception as e:  # ImportError, or a broken binary
            _import_error = f"{type(e).__name__}: {e}"
            raise ImportError(_import_error) from None
        finally:
            _flush_c_stdio()
            for fd, dup in saved.items():
                os.dup2(dup, fd)
    finally:
        os.close(devnull)
        for dup in saved.values():
            os.close(dup)
    _pb = pybullet
    return pybullet


# --------------------------------------------------------------------------
# capabilities


SETTINGS: dict[str, Setting] = {
    "dt": DT_SETTING,
    "iterations": Setting("iterations", 50, int, "numSolverIterations: sequential-impulse sweeps per step (pybullet default 50)", lo=1, hi=100000),
    "substeps": Setting("substeps", 0, int, "numSubSteps: 0 = one internal step of dt; k > 0 = k internal steps of dt/k per step (external forces held over the step)", lo=0, hi=1000),
    "split_impulse": Setting("split_impulse", False, bool,
                             "useSplitImpulse: true = correct every penetration with a separate position-only impulse that adds no "
                             "velocity (splitImpulsePenetrationThreshold 0): exact collision velocities, but box stacks walk; "
                             "false = Baumgarte: contact_erp * depth / dt is added to the contact's target velocity (energy gain in "
                             "impacts, stable stacks).  pybullet's own default uses the split impulse only for penetrations deeper "
                             "than 4 cm, i.e. behaves like false in small scenes"),
    "erp": Setting("erp", 0.2, float, "erp: error reduction of non-contact constraints (joints; physbench scenes have none, measured: no effect on contacts; pybullet default 0.2)", lo=0.0, hi=1.0),
    "contact_erp": Setting("contact_erp", 0.08, float, "contactERP: fraction of a contact's penetration corrected per step, by Baumgarte velocity or by the split impulse (pybullet default 0.08)", lo=0.0, hi=1.0),
    "friction_erp": Setting("friction_erp", 0.2, float, "frictionERP: positional correction of friction anchors, which physbench does not enable (pybullet default 0.2)", lo=0.0, hi=1.0),
    "contact_breaking_threshold": Setting("contact_breaking_threshold", 0.02, float,
                                          "contactBreakingThreshold (m): contacts are created up to this separation (speculative "
                                          "contacts: a body is stopped at the surface and its rebound loses gap/dt) and kept until it; "
                                          "pybullet default 0.02.  Process-global in Bullet: set at every build",
                                          lo=0.0, hi=1.0),
    "ccd": Setting("ccd", True, bool,
                   f"continuous collision detection: sweep a sphere of {CCD_RADIUS_FRACTION} x the body's smallest half-size "
                   "(ccdSweptSphereRadius; pybullet switches the sweep on above half that radius of motion per step).  "
                   "On by default (pybullet's is off): measured on the conformance suite it stops the bullets and "
                   "changes no other result, since slower bodies never reach the motion threshold.  A sweep shallower "
                   "than ccd_allowed_penetration is ignored"),
    "ccd_radius": Setting("ccd_radius", CCD_RADIUS_FRACTION, float,
                          "ccdSweptSphereRadius as a fraction f of each body's smallest half-size (with ccd on); "
                          "the sweep starts above half that radius of motion per step.  A body caught by the sweep "
                          "stops with its swept sphere touching, so it overlaps by (1 - f) x its half-size (measured): "
                          "1 (the default, the inscribed sphere) leaves no overlap, 0.5 leaves half the radius",
                          lo=1e-6, hi=1.0),
    "ccd_allowed_penetration": Setting("ccd_allowed_penetration", 0.04, float,
                                       "allowedCcdPenetration (m): Bullet's CCD ignores a swept-sphere hit unless the "
                                       "step would carry the body deeper than this into the surface (pybullet default "
                                       "0.04).  Measured: a plate falling at 6.3 m/s (2.6 cm per step at 1/240 s) onto a "
                                       "4 mm slab is then not caught and falls through in 0.88 of step phases; with "
                                       "0.001 it is caught at every dt",
                                       lo=0.0, hi=10.0),
    "maximal_coordinates": Setting("maximal_coordinates", True, bool,
                                   "useMaximalCoordinates: btRigidBody (true) or btMultiBody base (false: 100 m/s speed cap, explicit gyroscopic term)"),
    "restitution_velocity_threshold": Setting("restitution_velocity_threshold", 0.0, float,
                                              "restitutionVelocityThreshold (m/s): impacts slower than this do not bounce (pybullet default 0.2)",
                                              lo=0.0, hi=1000.0),
}

BODY_SHAPES = frozenset({"sphere", "box", "capsule", "cylinder"})
STATIC_SHAPES = frozenset({"plane", "slope", "box"})
EFFECTS = frozenset({"gravity", "contact", "restitution", "friction", "rolling_friction",
                     "drag_linear", "drag_quadratic", "spring", "damper", "gyroscopic"})


@functools.lru_cache(maxsize=1)
def _capabilities() -> Capabilities:
    try:
        _import_pybullet()
        available, why = True, ""
    except ImportError as e:
        available, why = False, str(e)
    return Capabilities(
        engine=ENGINE,
        version=module_version("pybullet"),
        dimensions=3,
        shapes=BODY_SHAPES,
        static_shapes=STATIC_SHAPES,
        effects=EFFECTS,
        settings=dict(SETTINGS),
        available=available,
        unavailable_reason=why,
        notes=(
            "restitution and friction combine by product; per-body values are solved so that pairs match the spec",
            "one Coulomb coefficient: static friction = kinetic friction",
            "gyroscopic term always on (no switch)",
            "springs, dampers and drag are applied as external forces from the state at the start of each step",
        ),
    )


# --------------------------------------------------------------------------
# the adapter


class PybulletAdapter(Adapter):
    """Drives one pybullet DIRECT client.  See the module docstring."""

    name = ENGINE

    def __init__(self) -> None:
        super().__init__()
        self._p: Any = None
        self._cid: int | None = None
        self._ids: list[int] = []
        self._static_ids: list[int] = []
        self._xyzw: np.ndarray = np.zeros((0, 4))
        self._forces: list[tuple] = []
        self._force_bodies: list[int] = []
        self._fstate: dict[int, tuple] = {}
        self._stage: dict[str, Any] = {}
        self._steps = 0

    # ---- declaration -------------------------------------------------------
    @classmethod
    def capabilities(cls) -> Capabilities:
        return _capabilities()

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        reason = super().unsupported_reason(scene)
        if reason is not None:
            return reason
        return gyroscopic_reason(scene, "pybullet")

    # ---- build ---------------------------------------------------------------
    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        reason = self.unsupported_reason(scene)
        if reason is not None:
            raise Unsupported(reason)
        p = _import_pybullet()
        self._p = p
        cid = p.connect(p.DIRECT)
        if cid < 0:
            raise RuntimeError("pybullet could not start a DIRECT physics client")
        self._cid = cid
        dt = float(settings["dt"])
        split = bool(settings["split_impulse"])
        maximal = bool(settings["maximal_coordinates"])
        contact = scene.has("contact")
        ccd = bool(settings["ccd"]) and contact  # nothing to sweep against without contacts

        params = dict(
            fixedTimeStep=dt,
            numSolverIterations=int(settings["iterations"]),
            numSubSteps=int(settings["substeps"]),
            useSplitImpulse=int(split),
            erp=float(settings["erp"]),
            contactERP=float(settings["contact_erp"]),
            frictionERP=float(settings["friction_erp"]),
            restitutionVelocityThreshold=float(settings["restitution_velocity_threshold"]),
            # a process-global in Bullet (gContactBreakingThreshold): always set
            contactBreakingThreshold=float(settings["contact_breaking_threshold"]),
        )
        if ccd:
            params["allowedCcdPenetration"] = float(settings["ccd_allowed_penetration"])
        if split:
            # Bullet uses the split impulse only for penetrations deeper than
            # splitImpulsePenetrationThreshold (default -0.04 m: 4 cm!) and
            # Baumgarte (velocity-adding) correction for shallower ones.  0
            # makes every penetration use the split impulse.
            params["splitImpulsePenetrationThreshold"] = 0.0
        p.setPhysicsEngineParameter(physicsClientId=cid, **params)
        self.info["engine_parameters"] = dict(params)
        # Warm-up happens with gravity off (see below).
        p.setGravity(0.0, 0.0, 0.0, physicsClientId=cid)

        # ---- materials -----------------------------------------------------
        nb, ns = scene.n_bodies, len(scene.statics)
        restitution, friction, rolling = self._solve_materials(scene, nb, ns)

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

        # ---- dynamic bodies ------------------------------------------------
        min_ccd_threshold = math.inf
        for b in scene.bodies:
            if b.shape == "sphere":
                sid = shape_id("sphere", radius=float(b.radius))
            elif b.shape == "box":
                sid = shape_id("box", halfExtents=[float(h) for h in b.half_extents])
            else:  # capsule / cylinder: Bullet's Z variants, total height 2 * half_length
                sid = shape_id(b.shape, radius=float(b.radius), height=2.0 * float(b.half_length))
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
                linearDamping=0.0, angularDamping=0.0,
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
        g = scene.gravity
        p.setGravity(float(g[0]), float(g[1]), float(g[2]), physicsClientId=cid)

        # ---- external forces -------------------------------------------------
        self._setup_forces(scene)

        self._xyzw = np.zeros((nb, 4))
        self._stage = self._describe_stages(scene, settings, min_ccd_threshold)
        self._notes_for(scene, settings, dt)

    # ---- materials -----------------------------------------------------------
    def _solve_materials(self, scene: Scene, nb: int, ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-object (bodies, then statics) restitution, lateral friction and
        rolling friction whose Bullet combinations give the spec's pairs."""
        n = nb + ns
        pairs = scene.contact_pairs()

        def obj(kind: str, i: int) -> int:
            return i if kind == "body" else nb + i

        rest_pairs = [(obj(ka, ia), obj(kb, ib), m.restitution) for ka, ia, kb, ib, m in pairs]
        fric_pairs = [(obj(ka, ia), obj(kb, ib), m.friction) for ka, ia, kb, ib, m in pairs]
        roll_pairs = [(obj(ka, ia), obj(kb, ib), m.rolling_friction) for ka, ia, kb, ib, m in pairs]
        names = [b.name for b in scene.bodies] + [s.name for s in scene.statics]

        e, e_err, e_worst = solve_product_values(n, rest_pairs)
        f, f_err, f_worst = solve_product_values(n, fric_pairs)
        r, r_err, r_worst = solve_rolling_values(f, roll_pairs)
        residual = {"restitution": e_err, "friction": f_err, "rolling_friction": r_err}
        self.info["material_residual"] = max(residual.values())
        self.info["material_residuals"] = residual
        for what, err, worst in (("restitution", e_err, e_worst), ("friction", f_err, f_worst),
                                 ("rolling_friction", r_err, r_worst)):
            if err > MATERIAL_TOLERANCE and worst is not None:
                a, b, want, got = worst
                rule = "r_a f_b + r_b f_a" if what == "rolling_friction" else "the product of the two objects' values"
                self.notes.append(
                    f"pybullet cannot realise the spec's {what} pairs: it combines two objects by {rule}; "
                    f"worst pair {names[a]}|{names[b]} wants {want:g}, gets {got:g} (relative error {err:.3g})")
        for what, vals, pp in (("friction", f, fric_pairs), ("rolling_friction", r, roll_pairs)):
            over = [(a, b) for a, b, _ in pp if (vals[a] * f[b] + vals[b] * f[a] if what == "rolling_friction" else vals[a] * vals[b]) > MAX_COMBINED_FRICTION]
            if over:
                a, b = over[0]
                self.notes.append(f"Bullet clamps combined {what} to {MAX_COMBINED_FRICTION:g}; pair {names[a]}|{names[b]} asks for more")
        if scene.has("friction"):
            diff = [(m.static_friction, m.friction) for *_, m in pairs if m.static_friction != m.friction]
            if diff:
                self.notes.append(
                    f"pybullet has one Coulomb coefficient per contact: the kinetic friction is used for static "
                    f"friction too (spec asks static {diff[0][0]:g}, kinetic {diff[0][1]:g})")
        self.info["per_object_restitution"] = dict(zip(names, map(float, e)))
        self.info["per_object_friction"] = dict(zip(names, map(float, f)))
        if scene.has("rolling_friction"):
            self.info["per_object_rolling_friction"] = dict(zip(names, map(float, r)))
        return e, f, r

    # ---- external forces -------------------------------------------------------
    def _setup_forces(self, scene: Scene) -> None:
        """Preallocate the force terms applied before every step:
        ('spring', ia, ib, anchor_a, anchor_b, k, L0, c) and
        ('drag', i, c_linear, c_quadratic)."""
        forces: list[tuple] = []
        for sp in scene.springs:
            if sp.stiffness == 0.0 and sp.damping == 0.0:
                continue
            forces.append(("spring", sp.a, sp.b, tuple(map(float, sp.anchor_a)), tuple(map(float, sp.anchor_b)),
                           float(sp.stiffness), float(sp.rest_length), float(sp.damping)))
        for b in scene.bodies:
            cl = b.drag_linear if scene.has("drag_linear") else 0.0
            cq = b.drag_quadratic if scene.has("drag_quadratic") else 0.0
            if cl > 0.0 or cq > 0.0:
                forces.append(("drag", b.index, float(cl), float(cq)))
        self._forces = forces
        involved = set()
        for f in forces:
            if f[0] == "spring":
                involved.update(i for i in (f[1], f[2]) if i >= 0)
            else:
                involved.add(f[1])
        self._force_bodies = sorted(involved)
        # per-step state cache: index -> (pos, xyzw, v, w) tuples from the engine
        self._fstate: dict[int, tuple] = {}

    def _apply_forces(self) -> None:
        """Apply spring, damper and drag forces from the current state as
        world-frame forces at world points (cleared by Bullet after the step).

        Spring/damper between anchors pa, pb (world), d = pb - pa, L = |d|,
        u = d / L: the force on a is (k (L - L0) + c (v_pb - v_pa) . u) u,
        on b its opposite.  Drag on body i: -(c_lin + c_quad |v|) v at the
        centre of mass (no drag torque).
        """
        p, cid = self._p, self._cid
        st = self._fstate
        for i in self._force_bodies:
            bid = self._ids[i]
            pos, orn = p.getBasePositionAndOrientation(bid, physicsClientId=cid)
            v, w = p.getBaseVelocity(bid, physicsClientId=cid)
            st[i] = (pos, orn, v, w)
        wf = p.WORLD_FRAME
        for f in self._forces:
            if f[0] == "drag":
                _, i, cl, cq = f
                pos, _, v, _ = st[i]
                speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
                c = cl + cq * speed
                if c * speed == 0.0:
                    continue
                p.applyExternalForce(self._ids[i], -1, (-c * v[0], -c * v[1], -c * v[2]), pos, wf, physicsClientId=cid)
                continue
            _, ia, ib, anc_a, anc_b, k, L0, c = f
            pa, va = self._anchor(ia, anc_a)
            pb, vb = self._anchor(ib, anc_b)
            d0, d1, d2 = pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2]
            L = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            if L < 1e-12:
                continue  # direction undefined; a zero-rest-length spring has zero force here anyway
            u0, u1, u2 = d0 / L, d1 / L, d2 / L
            rate = (vb[0] - va[0]) * u0 + (vb[1] - va[1]) * u1 + (vb[2] - va[2]) * u2
            mag = k * (L - L0) + c * rate
            F = (mag * u0, mag * u1, mag * u2)
            if ia >= 0:
                p.applyExternalForce(self._ids[ia], -1, F, pa, wf, physicsClientId=cid)
            if ib >= 0:
                p.applyExternalForce(self._ids[ib], -1, (-F[0], -F[1], -F[2]), pb, wf, physicsClientId=cid)

    def _anchor(self, i: int, anchor: tuple[float, float, float]) -> tuple[tuple, tuple]:
        """World position and velocity of a body-frame anchor (world anchor if i < 0)."""
        if i < 0:
            return anchor, (0.0, 0.0, 0.0)
        pos, orn, v, w = self._fstate[i]
        # The engine's rotation matrix (double precision; p.multiplyTransforms
        # is single precision, measured 3e-8 m errors) rotates the anchor.
        m = self._p.getMatrixFromQuaternion(orn)
        a0, a1, a2 = anchor
        r0 = m[0] * a0 + m[1] * a1 + m[2] * a2
        r1 = m[3] * a0 + m[4] * a1 + m[5] * a2
        r2 = m[6] * a0 + m[7] * a1 + m[8] * a2
        world = (pos[0] + r0, pos[1] + r1, pos[2] + r2)
        vel = (v[0] + w[1] * r2 - w[2] * r1, v[1] + w[2] * r0 - w[0] * r2, v[2] + w[0] * r1 - w[1] * r0)
        return world, vel

    # ---- reporting -------------------------------------------------------------
    def _describe_stages(self, scene: Scene, settings: dict[str, Any], min_ccd_threshold: float) -> dict[str, Any]:
        contact = scene.has("contact")
        forces = sorted({f[0] for f in self._forces})
        return {
            "body_model": "btRigidBody (maximal coordinates)" if settings["maximal_coordinates"] else "btMultiBody base",
            "gravity": bool(scene.has("gravity") and np.any(scene.gravity != 0)),
            "collision_detection": contact,
            "restitution": contact and scene.has("restitution"),
            "friction": contact and scene.has("friction"),
            "rolling_friction": contact and scene.has("rolling_friction"),
            "gyroscopic": "always on (implicit)" if settings["maximal_coordinates"] else "always on (explicit)",
            "external_forces": forces,
            "ccd": bool(settings["ccd"]) and contact,
            "ccd_motion_threshold_m": float(min_ccd_threshold) if math.isfinite(min_ccd_threshold) else None,
            "split_impulse": bool(settings["split_impulse"]),
            "contact_breaking_threshold": float(settings["contact_breaking_threshold"]),
            "solver_iterations": int(settings["iterations"]),
            "substeps": int(settings["substeps"]),
            "dt": float(settings["dt"]),
        }

    def _notes_for(self, scene: Scene, settings: dict[str, Any], dt: float) -> None:
        if not settings["maximal_coordinates"]:
            self.notes.append("maximal_coordinates = false: bodies are btMultiBody bases, whose speed Bullet caps at "
                              "100 m/s and whose gyroscopic term is integrated explicitly (damping set to 0)")
        # Bullet limits rotation per step to pi/2 (btRigidBody::integrateVelocities).
        wmax = 0.5 * math.pi / dt * max(1, int(settings["substeps"]))
        self.info["max_angular_speed"] = wmax
        w0 = max((float(np.linalg.norm(b.angular_velocity)) for b in scene.bodies), default=0.0)
        if w0 > 0.5 * wmax:
            self.notes.append(f"Bullet clamps angular speed to (pi/2)/dt = {wmax:.4g} rad/s; a body starts at {w0:.4g} rad/s")
        if self._forces and int(settings["substeps"]) > 0:
            self.notes.append("spring/damper/drag forces are computed once per step and held constant over its substeps")
        if scene.has("rolling_friction"):
            self.notes.append("Bullet applies rolling friction at one contact point per contact manifold")
        if scene.has("contact") and scene.has("restitution"):
            if not settings["split_impulse"]:
                self.notes.append("split_impulse = false: Baumgarte contact correction adds contact_erp * depth / dt "
                                  "to separating velocities (measured +2.3 % of the approach speed head-on)")
            if settings["contact_breaking_threshold"] > 1e-3 and scene.statics:
                self.notes.append(f"speculative contacts (contact_breaking_threshold {settings['contact_breaking_threshold']:g} m) "
                                  "stop a body at a surface and take gap/dt off its rebound; split_impulse = true with "
                                  "contact_breaking_threshold = 1e-4 gives rebounds of exactly e")
        if settings["contact_breaking_threshold"] != SETTINGS["contact_breaking_threshold"].default:
            self.notes.append("contact_breaking_threshold is process-global in Bullet: other pybullet clients in this "
                              "process use it too until they are rebuilt")

    def stages(self) -> dict[str, Any]:
        out = dict(self._stage)
        out["steps"] = self._steps
        out["force_steps"] = self._steps if self._forces else 0
        return out

    # ---- life cycle --------------------------------------------------------------
    def step(self, n: int = 1) -> None:
        p, cid = self._p, self._cid
        if self._forces:
            for _ in range(n):
                self._apply_forces()
                p.stepSimulation(physicsClientId=cid)
        else:
            for _ in range(n):
                p.stepSimulation(physicsClientId=cid)
        self._steps += n

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
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
                    self._apply_forces()
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
                po, ve = po[:m], ve[:m]
                pos[:k] = np.array([t[0] for t in po]).reshape(k, nb, 3)
                quat[:k] = xyzw_to_wxyz(np.array([t[1] for t in po]).reshape(k, nb, 4))
                vel[:k] = np.array([t[0] for t in ve]).reshape(k, nb, 3)
                angvel[:k] = np.array([t[1] for t in ve]).reshape(k, nb, 3)

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Write positions (n, 3) m, quaternions (n, 4) wxyz, linear (n, 3) m/s
        and angular (n, 3) rad/s velocities, world frame, about the centre of
        mass.  pybullet forces one call per body per quantity (tuples); the
        quaternions go through one preallocated xyzw buffer and are converted
        to wxyz in a single place."""
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
