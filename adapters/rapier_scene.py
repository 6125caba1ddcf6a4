"""What of a scene Rapier can hold, and as what: the Rapier adapter's
settings (defaults are Rapier's own, tests/test_adapter_rapier.py::
test_capabilities_and_settings) and each body or static as a Rapier collider
builder (layout and reasons in the module docstring of
:mod:`adapters.rapier`; the engine module is passed in, so that this module
imports without rapier3d).
"""

from __future__ import annotations

import math
from typing import Any

from physbench.adapters.base import DT_SETTING, Setting
from physbench.contract.rotation import wxyz_to_xyzw

SHAPES = frozenset({"sphere", "box", "capsule", "cylinder"})
STATIC_SHAPES = frozenset({"plane", "slope", "box"})
EFFECTS = frozenset({"gravity", "contact", "restitution", "friction", "drag_linear", "drag_quadratic",
                     "spring", "damper", "gyroscopic"})


def settings() -> dict[str, Setting]:
    return {
        "dt": DT_SETTING,
        "iterations": Setting(
            "iterations", 4, int,
            "num_solver_iterations: TGS-soft substeps per step, each dt/iterations long "
            "(Rapier default 4)", lo=1, hi=1000),
        "pgs_iterations": Setting(
            "pgs_iterations", 1, int,
            "num_internal_pgs_iterations: PGS sweeps of the contacts per substep (Rapier default 1)",
            lo=1, hi=1000),
        "contact_frequency": Setting(
            "contact_frequency", 30.0, float,
            "contact_softness.natural_frequency (Hz) of the soft contact constraint between "
            "dynamic bodies; Rapier default 30 (its static contacts use "
            "static_contact_frequency)", lo=0.1, hi=1e5),
        "static_contact_frequency": Setting(
            "static_contact_frequency", 60.0, float,
            "static_contact_softness.natural_frequency (Hz): contacts with fixed colliders "
            "(Rapier default 60)", lo=0.1, hi=1e5),
        "contact_damping_ratio": Setting(
            "contact_damping_ratio", 10.0, float,
            "damping ratio of both contact softnesses (Rapier default 10)", lo=0.0, hi=1e4),
        "ccd": Setting(
            "ccd", False, bool,
            "ccd_enabled on every body: Rapier's nonlinear time-of-impact sweep for bodies "
            "moving more than their thickness per step (Rapier default off)"),
        "max_ccd_substeps": Setting(
            "max_ccd_substeps", 1, int,
            "max_ccd_substeps: time-of-impact substeps per step with ccd on (Rapier default 1)",
            lo=1, hi=100),
        "joints": Setting(
            "joints", "impulse", str,
            "'impulse': [[joint]] tables are impulse joints (maximal coordinates, solver rows; any graph); "
            "'multibody': multibody joints (reduced coordinates; trees only)", choices=("impulse", "multibody")),
        "springs": Setting(
            "springs", "joint", str,
            "'joint': springs and dampers are Rapier SpringJoints (force-based, implicit in each substep); "
            "'force': explicit forces from the state at the start of each step",
            choices=("joint", "force")),
        "friction_model": Setting(
            "friction_model", "simplified", str,
            "friction_model: 'simplified' (one friction constraint per manifold plus a twist "
            "constraint; Rapier default) or 'coulomb' (one per contact point)",
            choices=("simplified", "coulomb")),
        "contact_recycling": Setting(
            "contact_recycling", True, bool,
            "contact_recycling: keep a manifold's normal and points while they stay within the recycle "
            "distance (Rapier default on; docs/ENGINE_FINDINGS.md: it tilts oblique impacts found "
            "within the 2 cm prediction distance)"),
        "fast_rotation": Setting(
            "fast_rotation", False, bool,
            "allow_fast_rotation on every body: lift Rapier's cap of angular speed at pi/4 rad per step "
            "(Rapier default off: capped)"),
    }


# ---- shapes -------------------------------------------------------------------

def body_collider(rp: Any, b: Any) -> Any:
    """The body's collider builder in the body frame (centre of mass at the origin)."""
    if b.shape == "sphere":
        return rp.Collider.ball(float(b.radius))
    if b.shape == "box":
        return rp.Collider.cuboid(*map(float, b.half_extents))
    if b.shape == "capsule":
        return rp.Collider.capsule_z(float(b.half_length), float(b.radius))
    # cylinder: Rapier's axis is local y; +90 degrees about x turns y onto z
    return rp.Collider.cylinder(float(b.half_length), float(b.radius)).rotation((0.5 * math.pi, 0.0, 0.0))


def static_collider(rp: Any, s: Any) -> Any:
    """A parentless collider for a static plane (halfspace) or box."""
    if s.shape == "plane":
        n = tuple(map(float, s.normal))
        return rp.Collider.halfspace(n).translation(tuple(float(s.offset) * c for c in n))
    return rp.Collider.cuboid(*map(float, s.half_extents)).position(
        (tuple(map(float, s.position)), tuple(map(float, wxyz_to_xyzw(s.orientation)))))
