"""The reference-model registry of the contract: names only.

``MODELS`` maps a model name to ``"module:Class"``; the class is imported
only when a scene that names it is loaded (:func:`get_model`).  So loading
a spec never imports a model module, and this module imports nothing above
the contract (tests/test_architecture.py).  ``MODELS`` holds the shipped
models (:data:`SHIPPED_MODELS`) and then the ``physbench.models`` entry
points of installed distributions (contract/plugins.py; a name already
taken is left out and named in :data:`PLUGIN_PROBLEMS`); a plug-in model
that fails to import refuses the scenes that name it, as a spec error.

:func:`model_refusal` and :func:`scene_errors` are the load-time check
(called by :func:`contract.scene.compile_scene`): the model must accept the
scene, and the primary metric and every check's metric must be produced by
the model or the harness for this scene.  The models themselves
(:class:`harness.references.ReferenceModel` subclasses) live in
``harness/references/``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from physbench.contract.metric_defs import dissipation, generic_metrics
from physbench.contract.plugins import MODELS_GROUP, plugins

if TYPE_CHECKING:
    from physbench.contract.scene import Scene

SHIPPED_MODELS: dict[str, str] = {
    "two_body_collision": "physbench.harness.references.collision:TwoBodyCollision",
    "oblique_collision": "physbench.harness.references.billiards:ObliqueCollision",
    "newtons_cradle": "physbench.harness.references.billiards:NewtonsCradle",
    "momentum_energy": "physbench.harness.references.billiards:MomentumEnergy",
    "bounce_heights": "physbench.harness.references.billiards:BounceHeights",
    "static_stack": "physbench.harness.references.stacking:StaticStack",
    "log_pile": "physbench.harness.references.stacking:LogPile",
    "no_tunnelling": "physbench.harness.references.tunnelling:NoTunnelling",
    "incline_block": "physbench.harness.references.friction:InclineBlock",
    "slide_to_rest": "physbench.harness.references.friction:SlideToRest",
    "rolling_sphere": "physbench.harness.references.friction:RollingSphere",
    "rolling_cylinder": "physbench.harness.references.friction:RollingCylinder",
    "rolling_resistance": "physbench.harness.references.friction:RollingResistance",
    "spin_to_rest": "physbench.harness.references.friction:SpinToRest",
    "torque_free_rigid_body": "physbench.harness.references.rigid_body:TorqueFreeRigidBody",
    "heavy_top": "physbench.harness.references.rigid_body:HeavyTop",
    "damped_oscillator": "physbench.harness.references.forces:DampedOscillator",
    "drag_fall": "physbench.harness.references.forces:DragFall",
    "pendulum": "physbench.harness.references.joints:Pendulum",
    "slider": "physbench.harness.references.joints:Slider",
    "conical_pendulum": "physbench.harness.references.joints:ConicalPendulum",
    "hanging_chain": "physbench.harness.references.joints:HangingChain",
    "double_pendulum": "physbench.harness.references.joints:DoublePendulum",
    "four_bar": "physbench.harness.references.joints:FourBar",
    "self_consistency": "physbench.harness.references.self_consistency:SelfConsistency",
}
#: every model: the shipped ones, then the plug-ins
MODELS: dict[str, str] = dict(SHIPPED_MODELS)
#: model name -> "physbench" or the plug-in's distribution ("name version")
MODEL_ORIGINS: dict[str, str] = {name: "physbench" for name in SHIPPED_MODELS}
#: plug-in models that were not registered, each with the reason
PLUGIN_PROBLEMS: list[str] = []
for _p in plugins(MODELS_GROUP):
    if _p.name in MODELS:
        PLUGIN_PROBLEMS.append(f"{_p.name} = {_p.value!r} ({_p.dist}): not registered, the name is taken by "
                               f"{MODEL_ORIGINS[_p.name]}'s {_p.name}")
    elif ":" not in _p.value:
        PLUGIN_PROBLEMS.append(f"{_p.name} = {_p.value!r} ({_p.dist}): not registered, expected module:Class")
    else:
        MODELS[_p.name] = _p.value
        MODEL_ORIGINS[_p.name] = _p.dist


class ReferenceError(ValueError):
    """The scene does not fit the model (wrong body count, shape...).
    ``key`` is the spec key path the problem is about (default
    ``reference.model``)."""

    def __init__(self, message: str, key: str = "reference.model"):
        super().__init__(message)
        self.key = key


def get_model(name: str) -> Any:
    """The model class registered under ``name`` (imported on first use)."""
    if name not in MODELS:
        raise ReferenceError(f"unknown reference model {name!r}; known: {', '.join(sorted(MODELS))}")
    mod, _, qual = MODELS[name].partition(":")
    obj: Any = importlib.import_module(mod.strip())
    for part in qual.strip().split("."):
        obj = getattr(obj, part)
    return obj


# --------------------------------------------------------------------------
# load-time check


def model_refusal(scene: "Scene", label: str) -> list[str]:
    """Spec-error lines (``<file>: <key path>: <problem>``) when the scene's
    reference model does not accept the compiled scene: its refusal, or any
    failure while it reads the scene; [] when it accepts (or there is none)."""
    if not scene.reference_model:
        return []
    try:
        get_model(scene.reference_model)(scene)
    except ReferenceError as e:
        return [f"{label}: {e.key}: model {scene.reference_model!r} cannot model this scene: {e}"]
    except Exception as e:  # a model that fails while reading the scene cannot model it either
        return [f"{label}: reference.model: model {scene.reference_model!r} cannot model this scene: "
                f"{type(e).__name__}: {e}"]
    return []


def scene_errors(scene: "Scene", label: str) -> list[str]:
    """Spec-error lines for the primary metric and every check's metric
    that neither the scene's model nor the harness produces for this scene
    (:func:`contract.metric_defs.generic_metrics`)."""
    errs: list[str] = []
    produced = generic_metrics(scene)
    origin = "the harness"
    if scene.reference_model:
        produced = produced | set(get_model(scene.reference_model).produces)
        origin = f"the harness or model {scene.reference_model!r}"
    hint = f"; {origin} produce(s): {', '.join(sorted(produced))}"
    wanted = [("scenario.primary_metric", scene.primary_metric)] if scene.primary_metric is not None else []
    wanted += [(f"check[{i}].metric", c.metric.partition("@")[0]) for i, c in enumerate(scene.checks)]
    missing = [(key, name) for key, name in wanted if name not in produced]
    if not scene.reference_model:
        # metrics only a model produces, in a scene without one: one error that
        # says what to add, not one per check listing the harness's metrics
        # (tests/test_spec.py::test_model_metric_without_reference_says_add_reference)
        by_model = {name: _models_producing(name) for _, name in missing}
        need = [(key, name) for key, name in missing if by_model[name]]
        if need:
            names = list(dict.fromkeys(name for _, name in need))
            common = set.intersection(*(set(by_model[n]) for n in names))
            cands = sorted(common) if common else sorted({m for n in names for m in by_model[n]})
            errs.append(f"{label}: reference: {', '.join(repr(n) for n in names)} ({', '.join(k for k, _ in need)}) "
                        f"{'is a metric' if len(names) == 1 else 'are metrics'} of a reference model, and the scene "
                        f"has none: add [reference] model = {cands[0]!r}"
                        + (f" (or one of {', '.join(cands[1:])})" if len(cands) > 1 else "")
                        + " (physbench models lists them)")
            missing = [(key, name) for key, name in missing if not by_model[name]]
    for key, name in missing:
        errs.append(f"{label}: {key}: {name!r} is not produced for this scene" + _why(scene, name) + hint)
    return errs


def _models_producing(metric: str) -> list[str]:
    """The registered models that produce ``metric`` (imports each model's
    class: called only on a spec error)."""
    out = []
    for name in MODELS:
        try:
            if metric in get_model(name).produces:
                out.append(name)
        except Exception:  # a model that cannot be imported produces nothing here
            continue
    return out


def _why(scene: "Scene", metric: str) -> str:
    if metric == "energy_drift":
        return (f" (the scene is not conservative: {'; '.join(dissipation(scene))}; check energy_dissipated "
                "or energy_gain instead)")
    if metric == "energy_dissipated":
        return " (the scene is conservative: check energy_drift instead)"
    return ""
