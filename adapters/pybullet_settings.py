"""pybullet's settings and the run's diagnostics: the engine features a
scene switches on (``stages``) and the notes on what Bullet does
differently from the spec at the chosen settings.  Each setting's doc gives
the measured effect (tests/test_adapter_pybullet.py)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.adapters.base import DT_SETTING, Capabilities, Setting, module_version
from physbench.adapters.pybullet_joints import JOINT_KINDS
from physbench.adapters.quiet import quiet_import
from physbench.contract.scene import Scene

# Bullet clamps every combined friction and rolling friction to this value
# (btManifoldResult::calculateCombined*Friction).
MAX_COMBINED_FRICTION = 10.0

# CCD: Bullet sweeps a sphere of this fraction of the body's smallest
# half-size; pybullet sets the motion threshold that switches the sweep on to
# half the sphere radius.  1 (the inscribed sphere) keeps the swept sphere
# inside every shape (so a sweep never reports a hit the real shape would
# not make) while a body moving more than half its thinnest half-size in
# one step is swept.
CCD_RADIUS_FRACTION = 1.0


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
    "erp": Setting("erp", 0.2, float, "erp: error reduction of non-contact constraints (the joints' constraint error corrected per step; measured: no effect on contacts; pybullet default 0.2)", lo=0.0, hi=1.0),
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
                                   "useMaximalCoordinates: btRigidBody (true) or btMultiBody base (false: 100 m/s speed cap, explicit gyroscopic term; "
                                   "the form prismatic joints need: adapters/pybullet_joints.py)"),
    "joints": Setting("joints", "constraint", str,
                      "the form of [[joint]] tables: 'constraint' = createConstraint between the bodies (maximal "
                      "coordinates; a hinge is two point2point constraints); 'links' = one createMultiBody whose "
                      "links are the bodies, hanging from the world (reduced coordinates; trees only)",
                      choices=("constraint", "links")),
    "restitution_velocity_threshold": Setting("restitution_velocity_threshold", 0.0, float,
                                              "restitutionVelocityThreshold (m/s): impacts slower than this do not bounce (pybullet default 0.2)",
                                              lo=0.0, hi=1000.0),
}


def declaration(engine: str, available: bool, why: str) -> Capabilities:
    """pybullet's capabilities; ``available``/``why`` from the import."""
    return Capabilities(
        engine=engine,
        version=module_version("pybullet"),
        dimensions=3,
        shapes=frozenset({"sphere", "box", "capsule", "cylinder"}),
        static_shapes=frozenset({"plane", "slope", "box"}),
        effects=frozenset({"gravity", "contact", "restitution", "friction", "rolling_friction",
                           "drag_linear", "drag_quadratic", "spring", "damper", "gyroscopic", "joint"}),
        joint_kinds=JOINT_KINDS,
        settings=dict(SETTINGS),
        available=available,
        unavailable_reason=why,
        notes=(
            "restitution and friction combine by product; per-body values are solved so that pairs match the spec",
            "one Coulomb coefficient: static friction = kinetic friction",
            "gyroscopic term always on (no switch)",
            "linear drag is Bullet's linearDamping (btRigidBody); springs, dampers and quadratic drag are applied as "
            "external forces from the state at the start of each step",
        ),
    )


def engine_parameters(settings: dict[str, Any], ccd: bool) -> dict[str, Any]:
    """``setPhysicsEngineParameter`` keywords for resolved ``settings``
    (``ccd``: CCD on and the scene has contacts)."""
    split = bool(settings["split_impulse"])
    params: dict[str, Any] = dict(
        fixedTimeStep=float(settings["dt"]),
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
    return params


def describe_stages(scene: Scene, settings: dict[str, Any], min_ccd_threshold: float, forces: list[str]) -> dict[str, Any]:
    """The engine features switched on for ``scene`` (the run's ``stages``)."""
    contact = scene.has("contact")
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

def run_notes(scene: Scene, settings: dict[str, Any], dt: float, forces: bool, notes: list[str],
              info: dict[str, Any]) -> None:
    """Append to ``notes`` what Bullet does differently from the spec in this
    run; ``info`` gets the angular speed limit."""
    if not settings["maximal_coordinates"]:
        notes.append("maximal_coordinates = false: bodies are btMultiBody bases, whose speed Bullet caps at "
                          "100 m/s and whose gyroscopic term is integrated explicitly (damping set to 0)")
    # Bullet limits rotation per step to pi/2 (btRigidBody::integrateVelocities).
    wmax = 0.5 * math.pi / dt * max(1, int(settings["substeps"]))
    info["max_angular_speed"] = wmax
    w0 = max((float(np.linalg.norm(b.angular_velocity)) for b in scene.bodies), default=0.0)
    if w0 > 0.5 * wmax:
        notes.append(f"Bullet clamps angular speed to (pi/2)/dt = {wmax:.4g} rad/s; a body starts at {w0:.4g} rad/s")
    if forces and int(settings["substeps"]) > 0:
        notes.append("spring/damper/drag forces are computed once per step and held constant over its substeps")
    if scene.has("rolling_friction"):
        notes.append("Bullet applies rolling friction at one contact point per contact manifold")
    if scene.has("contact") and scene.has("restitution"):
        if not settings["split_impulse"]:
            notes.append("split_impulse = false: Baumgarte contact correction adds contact_erp * depth / dt "
                              "to separating velocities (measured +2.3 % of the approach speed head-on)")
        if settings["contact_breaking_threshold"] > 1e-3 and scene.statics:
            notes.append(f"speculative contacts (contact_breaking_threshold {settings['contact_breaking_threshold']:g} m) "
                              "stop a body at a surface and take gap/dt off its rebound; split_impulse = true with "
                              "contact_breaking_threshold = 1e-4 gives rebounds of exactly e")
    if settings["contact_breaking_threshold"] != SETTINGS["contact_breaking_threshold"].default:
        notes.append("contact_breaking_threshold is process-global in Bullet: other pybullet clients in this "
                          "process use it too until they are rebuilt")


_pb: Any = None
_import_error: str | None = None


def import_pybullet() -> Any:
    """pybullet, imported once without a byte of output
    (:func:`adapters.quiet.quiet_import`); an import failure is kept and
    raised again as ImportError on every later call."""
    global _pb, _import_error
    if _pb is None:
        if _import_error is not None:
            raise ImportError(_import_error)
        try:
            _pb = quiet_import("pybullet")
        except Exception as e:  # ImportError, or a broken binary
            _import_error = f"{type(e).__name__}: {e}"
            raise ImportError(_import_error) from None
    return _pb
