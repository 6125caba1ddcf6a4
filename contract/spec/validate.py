"""Validating a raw spec document: the schema (contract/spec/schema.py),
then the checks that span sections (names, material references, effects a
coefficient needs, planar rules, the scene's size)."""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

from physbench.contract.spec.bounds import BOUNDS, record_size_error
from physbench.contract.spec.errors import SpecError, _format_errors
from physbench.contract.spec.schema import SpecModel, name_error

def validate_raw(raw: dict[str, Any], label: str) -> SpecModel:
    try:
        spec = SpecModel.model_validate(raw)
    except ValidationError as exc:
        raise SpecError(_format_errors(label, exc, raw)) from None
    errors = _cross_checks(spec, label)
    if errors:
        raise SpecError(errors)
    return spec


def _cross_checks(spec: SpecModel, label: str) -> list[str]:
    """Checks that span sections: names, material references, planar rules."""
    errs: list[str] = []
    materials = set(spec.material) | {"default"}
    for m in spec.material:
        why = name_error(m)
        if why:
            errs.append(f"{label}: material: the name {why}")
    names: dict[str, int] = {}
    for i, b in enumerate(spec.body):
        if b.name in names:
            errs.append(f"{label}: body[{i}].name: duplicate body name {b.name!r} (also body[{names[b.name]}])")
        names.setdefault(b.name, i)
        if b.material not in materials:
            errs.append(f"{label}: body[{i}].material: unknown material {b.material!r}; defined: {', '.join(sorted(materials))}")
    for i, s in enumerate(spec.static):
        if s.material not in materials:
            errs.append(f"{label}: static[{i}].material: unknown material {s.material!r}; defined: {', '.join(sorted(materials))}")
    effects = set(spec.scenario.effects)
    for i, sp in enumerate(spec.spring):
        for end in ("a", "b"):
            who = getattr(sp, end)
            if who != "world" and who not in names and not any(
                b.pattern is not None and who.startswith(b.name + "_") for b in spec.body
            ):
                errs.append(f"{label}: spring[{i}].{end}: unknown body {who!r}; expected a body name or 'world'")
        if sp.stiffness > 0 and "spring" not in effects:
            errs.append(f"{label}: spring[{i}].stiffness: the scene has springs but 'spring' is not in scenario.effects")
        if sp.damping > 0 and "damper" not in effects:
            errs.append(f"{label}: spring[{i}].damping: the spring is damped but 'damper' is not in scenario.effects")
    errs += _material_effects(spec, label)
    errs += _joint_checks(spec, label, names)
    if ("spring" in effects or "damper" in effects) and not spec.spring:
        errs.append(f"{label}: scenario.effects: 'spring'/'damper' listed but there is no [[spring]] table")
    for i, b in enumerate(spec.body):
        if b.drag_linear > 0 and "drag_linear" not in effects:
            errs.append(f"{label}: body[{i}].drag_linear: set but 'drag_linear' is not in scenario.effects")
        if b.drag_quadratic > 0 and "drag_quadratic" not in effects:
            errs.append(f"{label}: body[{i}].drag_quadratic: set but 'drag_quadratic' is not in scenario.effects")
    if spec.scenario.planar:
        g = spec.scenario.gravity
        if abs(g[1]) > 0:
            errs.append(f"{label}: scenario.gravity: a planar scene lies in the x-z plane, so gravity[1] must be 0, got {list(g)}")
        for i, b in enumerate(spec.body):
            p = f"{label}: body[{i}]"
            if abs(b.position[1]) > 0:
                errs.append(f"{p}.position: a planar scene lies in the x-z plane, so y must be 0, got {list(b.position)}")
            if abs(b.velocity[1]) > 0:
                errs.append(f"{p}.velocity: a planar scene lies in the x-z plane, so y must be 0, got {list(b.velocity)}")
            w = b.angular_velocity
            if abs(w[0]) > 0 or abs(w[2]) > 0:
                errs.append(f"{p}.angular_velocity: a planar scene turns about y only, so x and z must be 0, got {list(w)}")
            q = b.orientation
            if abs(q[1]) > 0 or abs(q[3]) > 0:
                errs.append(f"{p}.orientation: a planar scene turns about y only, so x and z must be 0, got {list(q)}")
            if b.pattern is not None and b.pattern.kind in ("rack", "grid") and b.pattern.kind == "rack":
                errs.append(f"{p}.pattern.kind: a 'rack' lies in the x-y plane and cannot be planar")
        for i, s in enumerate(spec.static):
            if s.normal is not None and abs(s.normal[1]) > 1e-12:
                errs.append(f"{label}: static[{i}].normal: a planar scene lies in the x-z plane, so normal[1] must be 0, got {list(s.normal)}")
            if s.orientation is not None and (abs(s.orientation[1]) > 0 or abs(s.orientation[3]) > 0):
                errs.append(f"{label}: static[{i}].orientation: a planar scene turns about y only, got {list(s.orientation)}")
    n_bodies = sum(1 if b.pattern is None else b.pattern.n_bodies() for b in spec.body)
    if n_bodies < BOUNDS["bodies"][0]:  # tests/test_fuzz.py::test_a_spec_without_bodies_is_rejected
        errs.append(f"{label}: body: the scene has no bodies; expected at least {BOUNDS['bodies'][0]:g} [[body]] table")
    elif n_bodies > BOUNDS["bodies"][1]:
        errs.append(f"{label}: body: the scene has {n_bodies} bodies after pattern expansion, beyond the bound "
                    f"of {BOUNDS['bodies'][1]:g}")
    else:
        sc = spec.scenario
        why = record_size_error(max(1, round(sc.duration / sc.dt)), n_bodies)
        if why:
            errs.append(f"{label}: scenario.duration: {why}")
    for i, c in enumerate(spec.check):
        for eng in c.xfail:
            if c.engines is not None and eng not in c.engines:
                errs.append(f"{label}: check[{i}].xfail.{eng}: engine is not in this check's engines {c.engines}")
    if spec.scenario.primary_metric is not None and spec.reference is None and spec.scenario.primary_metric in (
        "post_impact_velocity_error", "trajectory_rmse", "final_position_error"):
        errs.append(f"{label}: scenario.primary_metric: {spec.scenario.primary_metric!r} needs a [reference] model")
    return errs


def _known_body(spec: SpecModel, names: dict[str, int], who: str) -> bool:
    """Whether ``who`` names a body of the spec: a [[body]] name, or a
    pattern's ``<name>_<i>`` (the pattern's count is checked on compile)."""
    return who in names or any(b.pattern is not None and who.startswith(b.name + "_") for b in spec.body)


#: the body patterns a ``[[joint]] chain`` runs along (link i next to link i-1)
CHAIN_PATTERNS = ("row", "column")


def _chain_checks(spec: SpecModel, p: str, j) -> list[str]:
    """A ``[[joint]]``'s ``chain``: the name of a [[body]] whose pattern is
    a row or a column, and ``other`` not one of its links.  Tests:
    tests/test_joint_chain.py::test_chain_errors_name_the_key."""
    b = next((b for b in spec.body if b.name == j.chain), None)
    if b is None or b.pattern is None:
        pats = [x.name for x in spec.body if x.pattern is not None]
        what = "a [[body]] without a pattern" if b is not None else "no [[body]]"
        return [f"{p}.chain: expected the name of a [[body]] with a pattern (its bodies are the links), got "
                f"{j.chain!r} ({what}); patterned bodies: {pats}"]
    if b.pattern.kind not in CHAIN_PATTERNS:
        return [f"{p}.chain: body {j.chain!r} has a {b.pattern.kind!r} pattern; a chain runs along a "
                f"{' or a '.join(repr(k) for k in CHAIN_PATTERNS)} (link i next to link i-1)"]
    if j.other != "world" and j.other.startswith(j.chain + "_") and j.other[len(j.chain) + 1:].isdigit():
        return [f"{p}.other: {j.other!r} is a link of the chain {j.chain!r} itself; expected 'world' or "
                f"another body's name"]
    return []


def _joint_checks(spec: SpecModel, label: str, names: dict[str, int]) -> list[str]:
    """[[joint]] against the rest of the spec: the 'joint' effect, the body
    names, a joint of a body to itself, step phases, the planar rules
    (revolute about y, prismatic in x-z, anchors at y = 0, no spherical
    joint).  The anchor's distance and fixed chains need the compiled scene
    (:func:`contract.scene.compile_scene`).  Tests: tests/test_joints_spec.py."""
    errs: list[str] = []
    effects = set(spec.scenario.effects)
    if spec.joint and "joint" not in effects:
        errs.append(f"{label}: joint: the scene has {len(spec.joint)} [[joint]] table(s) but 'joint' is not in "
                    f"scenario.effects (add it: joints are an effect an engine must model)")
    if "joint" in effects and not spec.joint:
        errs.append(f"{label}: scenario.effects: 'joint' listed but there is no [[joint]] table")
    if spec.joint and spec.perturbation is not None:
        errs.append(f"{label}: perturbation: perturbed starts would pull the joints apart at t = 0 (a perturbation "
                    f"that keeps the joints is not built yet); leave [perturbation] out of a scene with joints")
    if spec.joint and spec.scenario.phases > 1:
        errs.append(f"{label}: scenario.phases: step phases shift a start in free flight; a scene with joints "
                    f"has none (leave phases at 1)")
    for i, j in enumerate(spec.joint):
        p = f"{label}: joint[{i}]"
        if j.chain is not None:
            errs.extend(_chain_checks(spec, p, j))
        elif not _known_body(spec, names, j.body):
            errs.append(f"{p}.body: unknown body {j.body!r}; expected a body's name")
        if j.other != "world" and not _known_body(spec, names, j.other):
            errs.append(f"{p}.other: unknown body {j.other!r}; expected a body's name or 'world'")
        if j.body is not None and j.body == j.other:
            errs.append(f"{p}.other: a joint between a body and itself (body = other = {j.body!r})")
        if spec.scenario.planar:
            if abs(j.anchor[1]) > 0:
                errs.append(f"{p}.anchor: a planar scene lies in the x-z plane, so y must be 0, got {list(j.anchor)}")
            if j.kind == "spherical":
                errs.append(f"{p}.kind: a planar scene turns about y only: use a revolute joint with "
                            f"axis = [0, 1, 0], not a spherical one")
            elif j.kind == "revolute" and j.axis is not None and (abs(j.axis[0]) > 0 or abs(j.axis[2]) > 0):
                errs.append(f"{p}.axis: a planar scene turns about y only, so a hinge axis must be [0, +-1, 0], "
                            f"got {list(j.axis)}")
            elif j.kind == "prismatic" and j.axis is not None and abs(j.axis[1]) > 0:
                errs.append(f"{p}.axis: a planar scene lies in the x-z plane, so a slide axis must have y = 0, "
                            f"got {list(j.axis)}")
    return errs


#: material coefficient -> the effect without which it would be ignored
MATERIAL_EFFECTS = {"restitution": "restitution", "friction": "friction", "static_friction": "friction",
                    "rolling_friction": "rolling_friction"}


def _material_effects(spec: SpecModel, label: str) -> list[str]:
    """A non-zero material coefficient whose effect the scene does not list
    would be dropped by Scene.pair without a word: an error, as for body and
    spring coefficients (tests/test_spec.py::test_material_coefficient_needs_its_effect)."""
    effects = set(spec.scenario.effects)
    errs = []
    for name, m in spec.material.items():
        for key, effect in MATERIAL_EFFECTS.items():
            value = getattr(m, key)
            if value and effect not in effects:
                errs.append(f"{label}: material.{name}.{key}: set to {value!r} but {effect!r} is not in "
                            f"scenario.effects (add the effect, or leave the coefficient out)")
    return errs

