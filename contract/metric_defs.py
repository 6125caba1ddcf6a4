"""The harness's own metrics: names, units, when each is reported, and which
scenes are conservative.  A leaf (no harness imports), read by
:mod:`harness.metrics` (which computes them), by the load-time check of
:func:`harness.references.scene_errors` (a check or primary metric must be
produced for its scene) and by docs/METRICS.md (tests/test_models.py checks
that every name here is documented there).

Functions take a compiled scene (``contract.scene.Scene``) by duck typing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MetricDef:
    units: str
    meaning: str
    when: str  # when the metric has a value (otherwise NaN, or absent)


ALWAYS = "reported for every run"
GENERIC_METRICS: dict[str, MetricDef] = {
    "max_penetration": MetricDef("m", "deepest overlap between any two shapes over the run",
                                 "reported only with the 'contact' effect"),
    "mean_penetration": MetricDef("m", "mean over frames with an overlap of each frame's deepest overlap",
                                  "reported only with the 'contact' effect"),
    "penetration_unknown_frames": MetricDef("frames", "frames where some pair's depth could not be measured",
                                            "reported only with the 'contact' effect"),
    "energy_initial": MetricDef("J", "mechanical energy E0 at the first frame, potential energy from the scene's datum",
                                ALWAYS),
    "energy_final": MetricDef("J", "mechanical energy at the last frame (same datum)", ALWAYS),
    "energy_drift": MetricDef("1", "max_t |E(t) - E0| / E_scale",
                              "reported only where the scene is conservative (else NaN)"),
    "energy_dissipated": MetricDef("1", "(E0 - E(T)) / E_scale: the energy the scene's dissipation removed",
                                   "reported only where the scene dissipates (else NaN)"),
    "energy_gain": MetricDef("1", "max(0, max_t (E(t) - E0) / E_scale)", ALWAYS),
    "linear_momentum_drift": MetricDef("1", "max_t |P(t) - P0| / max(|P0|, sum m |v0|)",
                                       "reported only where no external force acts (else NaN)"),
    "angular_momentum_drift": MetricDef("1", "max_t |L(t) - L0| / (|L0| or the sum of spin and orbital magnitudes)",
                                        "reported only where no external torque about the centre of mass acts "
                                        "(else NaN)"),
    "stable": MetricDef("bool", "finite state, energy_gain <= 0.5 and bounded speeds", ALWAYS),
    "stability_reason": MetricDef("text", "why a run is not stable ('' when it is)", ALWAYS),
    "undefined_metrics": MetricDef("text", "the metrics this run cannot define, each with the reason "
                                   "('name: reason; ...'; those metrics are NaN, a check on them is an error)",
                                   "reported only when some metric is undefined (a zero denominator)"),
    "max_speed": MetricDef("m/s", "largest body speed over the run", ALWAYS),
    "cpu_s_per_sim_s": MetricDef("s/s", "CPU seconds of stepping per simulated second", ALWAYS),
    "wall_s_per_sim_s": MetricDef("s/s", "wall seconds of stepping per simulated second", ALWAYS),
    "steps_per_s": MetricDef("1/s", "steps per wall second", ALWAYS),
}


#: the joint metrics (harness/joints.py), reported for scenes with [[joint]]
#: tables: measured from the recorded positions and orientations, the same
#: for every engine (never an engine's own constraint error)
JOINT_METRICS: dict[str, MetricDef] = {
    "joint_drift": MetricDef("m", "max over frames and joints of the positional violation: the separation of the "
                             "two sides' anchor points (revolute, spherical, fixed), a slider's off-axis "
                             "displacement (prismatic)", "reported only for scenes with [[joint]] tables"),
    "joint_axis_drift": MetricDef("rad", "max over frames and joints of the angular violation: the angle between "
                                  "the two sides' hinge axes (revolute), the relative rotation since the start "
                                  "(prismatic, fixed); 0 with spherical joints only",
                                  "reported only for scenes with [[joint]] tables"),
}


#: the contact-law residual families (harness/contact_laws.py): each gives
#: the metrics <name>_max, <name>_mean and <name>_rows, computed only when a
#: check or the primary metric names one of them (recording contact forces
#: costs time); docs/METRICS.md defines them
CONTACT_LAWS: dict[str, str] = {
    "signorini_residual": "|lam_n gap| over all contact rows (N m): force across a gap or penetration under force",
    "separation_force": "normal force on contact rows apart by more than 1e-6 m (N)",
    "adhesion": "max(0, -lam_n) over all contact rows: a pulling normal force (N)",
    "cone_violation": "max(0, |lam_t| - mu lam_n) / lam_n over rows with lam_n > 0: friction outside the "
                      "Coulomb cone, relative to the normal force",
    "dissipation_residual": "angle between the friction force and the opposite of the slip on sliding rows (rad)",
    "dissipation_shortfall": "max(0, mu lam_n - |lam_t|) / (mu lam_n) on sliding rows: sliding friction short "
                             "of the cone's edge, relative",
}


#: the measures of a scene's ensemble of perturbed starts
#: (harness/ensemble.py): a check on one of them is evaluated on the
#: ensemble's row (``physbench check`` runs the ensemble from the scene's
#: ``[perturbation]``, or ``check --ensemble N --sigma S``), never on a plain run
ENSEMBLE_METRICS: dict[str, MetricDef] = {
    "predictable": MetricDef("bool", "every member ok and final_spread <= the ensemble's threshold (m)",
                             "reported on ensemble rows; undefined, with the reason, when a member is not ok"),
    "final_spread": MetricDef("m", "over the bodies, the largest RMS distance of the members' final positions "
                              "from their mean", "reported on ensemble rows"),
    "orientation_spread": MetricDef("rad", "over the bodies, the largest RMS rotation of the members' final "
                                    "orientations from the first member's", "reported on ensemble rows"),
    "start_spread": MetricDef("m", "final_spread's measure of the start positions drawn",
                              "reported on ensemble rows"),
    "amplification": MetricDef("1", "final_spread / start_spread",
                               "reported on ensemble rows with position noise"),
    "event_spread": MetricDef("events", "the largest minus the smallest impact event count of a member",
                              "reported on ensemble rows"),
    "events_min": MetricDef("events", "the fewest impact events of a member", "reported on ensemble rows"),
    "events_max": MetricDef("events", "the most impact events of a member", "reported on ensemble rows"),
}

#: the engines' consensus at fine steps (harness/consensus.py): a check on
#: one of them is evaluated on the scene's consensus row (engine
#: ``consensus``), made by ``physbench check`` from the checked engines'
#: runs at dt / k^2
CONSENSUS_METRICS: dict[str, MetricDef] = {
    "consensus_spread": MetricDef("m", "the largest self-consistency distance (positions) between two engines' "
                                  "runs at dt / k^2", "reported on consensus rows with two engines ok"),
    "consensus_spread_angle": MetricDef("rad", "the same for orientations",
                                        "reported on consensus rows with two engines ok"),
}


def contact_law_metrics() -> set[str]:
    """Every column the contact-law residuals give."""
    return {f"{n}_{s}" for n in CONTACT_LAWS for s in ("max", "mean", "rows")}


def wants_contact_forces(scene, engine: str | None = None) -> bool:
    """Whether the primary metric of ``scene``, or a check that applies to
    it on ``engine`` (its ``engines`` and ``variants`` scopes; None: any
    engine), names a contact-law metric: only then does a run record
    contact forces."""
    names = contact_law_metrics()
    if getattr(scene, "primary_metric", None) in names:
        return True
    variant = getattr(scene, "variant", None) or "base"
    for c in getattr(scene, "checks", ()):
        if c.metric.partition("@")[0] not in names:
            continue
        if engine is not None and c.engines is not None and engine not in c.engines:
            continue
        if c.variants is not None and variant not in c.variants:
            continue
        return True
    return False


def _drag(scene) -> list[str]:
    out = []
    for eff in ("drag_linear", "drag_quadratic"):
        if scene.has(eff) and any(getattr(b, eff) > 0 for b in scene.bodies):
            out.append(eff.replace("_", " "))
    return out


def dissipation(scene) -> list[str]:
    """Why the scene removes mechanical energy, one phrase per cause: contact
    pairs with friction, rolling friction or restitution < 1, dampers, drag.
    Empty: the scene is conservative (energy_drift applies)."""
    out: list[str] = []
    pairs = scene.contact_materials()
    mus = sorted({m.friction for m in pairs if m.friction > 0 or m.static_friction > 0})
    if mus:
        out.append("friction (mu = " + ", ".join(f"{x:g}" for x in mus) + ")")
    if any(m.rolling_friction > 0 for m in pairs):
        out.append("rolling friction")
    es = sorted({m.restitution for m in pairs if m.restitution < 1.0})
    if es:
        out.append("impacts with e = " + ", ".join(f"{x:g}" for x in es) + " < 1")
    if any(sp.damping > 0 for sp in scene.springs):
        out.append("dampers")
    return out + _drag(scene)


def external_force_free(scene) -> tuple[bool, bool]:
    """(linear momentum conserved, angular momentum about the COM conserved)
    by the scene's physics.  Contact with statics, world springs and drag are
    external, and so are joints to the world; uniform gravity is external
    for P only."""
    touches_world = scene.has("contact") and len(scene.statics) > 0
    world_spring = any(sp.a < 0 or sp.b < 0 for sp in scene.springs)
    world_joint = any(j.other < 0 for j in getattr(scene, "joints", ()))
    free = not (touches_world or world_spring or world_joint or _drag(scene))
    gravity = bool(np.any(scene.gravity != 0))
    return free and not gravity, free


def generic_metrics(scene) -> set[str]:
    """The harness metrics a check or a primary metric of this scene may name
    (besides its model's): every harness metric, except that of the energy
    split the one that does not apply (``energy_drift`` in a dissipative
    scene, ``energy_dissipated`` in a conservative one: the scene calls for
    the other).  Metrics that are NaN for other reasons (penetration
    without contact, momentum under external forces) stay nameable, so a
    scene varied with --set keeps loading; a check on one fails at run time."""
    out = set(GENERIC_METRICS) | set(ENSEMBLE_METRICS) | set(CONSENSUS_METRICS)
    if scene.has("contact"):
        out |= contact_law_metrics()
    if getattr(scene, "joints", ()):
        out |= set(JOINT_METRICS)
    out.discard("energy_dissipated" if not dissipation(scene) else "energy_drift")
    return out
