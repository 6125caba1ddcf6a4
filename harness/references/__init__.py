"""Analytic and high-accuracy reference models.

A model is named by a scene's ``[reference] model = "..."``.  It takes every
parameter it can from the scene itself (masses, radii, inertias, slope angle,
materials, initial velocities) so the same model serves any scene of its kind;
``[reference] params`` holds only what the scene cannot say.

Each model is a :class:`ReferenceModel` subclass in its own module, registered
in ``MODELS`` by name -> "module:Class" and imported lazily (spec validation
only needs the names).
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from harness.scene import Scene

MODELS: dict[str, str] = {
    "two_body_collision": "harness.references.collision:TwoBodyCollision",
    "oblique_collision": "harness.references.billiards:ObliqueCollision",
    "newtons_cradle": "harness.references.billiards:NewtonsCradle",
    "momentum_energy": "harness.references.billiards:MomentumEnergy",
    "bounce_heights": "harness.references.billiards:BounceHeights",
    "static_stack": "harness.references.stacking:StaticStack",
    "log_pile": "harness.references.stacking:LogPile",
    "no_tunnelling": "harness.references.tunnelling:NoTunnelling",
    "incline_block": "harness.references.friction:InclineBlock",
    "rolling_sphere": "harness.references.friction:RollingSphere",
    "rolling_cylinder": "harness.references.friction:RollingCylinder",
    "rolling_resistance": "harness.references.friction:RollingResistance",
    "spin_to_rest": "harness.references.friction:SpinToRest",
    "torque_free_rigid_body": "harness.references.rigid_body:TorqueFreeRigidBody",
    "heavy_top": "harness.references.rigid_body:HeavyTop",
}


class ReferenceError(ValueError):
    """The scene does not fit the model (wrong body count, shape...)."""


class ReferenceModel:
    """Base class.  ``__init__(scene)`` extracts parameters (raise
    ReferenceError naming what does not fit); ``metrics(trace)`` returns the
    model's metrics for a recorded trace (harness.runner.Trace: t (F,),
    pos (F, n, 3), quat (F, n, 4), vel (F, n, 3), angvel (F, n, 3))."""

    name = ""
    params_allowed: tuple[str, ...] = ()

    def __init__(self, scene: Scene):
        self.scene = scene
        unknown = set(scene.reference_params) - set(self.params_allowed)
        if unknown:
            raise ReferenceError(
                f"reference.params: unknown key(s) {sorted(unknown)} for model {self.name!r}; "
                f"allowed: {list(self.params_allowed) or 'none'}")

    def param(self, key: str, default: Any = None) -> Any:
        return self.scene.reference_params.get(key, default)

    def the_body(self):
        """The body ``params.body`` names, else the scene's only body."""
        bname = self.param("body")
        if bname is not None:
            return self.scene.bodies[self.scene.body_index(bname)]
        if self.scene.n_bodies != 1:
            raise ReferenceError(f"{self.name} needs exactly one body (or params.body), "
                                 f"the scene has {self.scene.n_bodies}")
        return self.scene.bodies[0]

    def positions(self, t: np.ndarray) -> np.ndarray | None:
        """Reference positions (F, n, 3) at times t (F,), if the model has a
        trajectory; None otherwise."""
        return None

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The model's motion at times t (F,): (positions (F, n, 3) m,
        orientations (F, n, 4) wxyz or None when the model predicts none),
        NaN for bodies it does not model; None without a trajectory.  Drawn
        as the ghost in traces (harness.trace)."""
        pos = self.positions(t)
        return None if pos is None else (pos, None)

    def predictions(self) -> dict[str, str]:
        """The model's scalar predictions as label -> text with units
        (post-impact velocity, apex heights, flip period, stop time...), for
        the trace's context document; {} when it has none to show."""
        return {}

    def events(self, trace) -> list[tuple[int, int, str]]:
        """Moments the model recognises in a recorded trace, as (frame,
        body index, text), e.g. a body passing through a wall; [] by
        default.  Drawn as event markers in traces."""
        return []

    def metrics(self, trace) -> dict[str, float]:
        ref = self.positions(trace.t)
        if ref is None:
            return {}
        return trajectory_metrics(trace.pos, ref)


def trajectory_metrics(pos: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """trajectory_rmse: RMS over frames and bodies of |x - x_ref| (m);
    final_position_error: max over bodies of |x - x_ref| at the last frame (m)."""
    err = np.linalg.norm(pos - ref, axis=-1)
    return {
        "trajectory_rmse": float(np.sqrt(np.mean(err * err))),
        "final_position_error": float(np.max(err[-1])),
    }


def get_model(name: str) -> type[ReferenceModel]:
    if name not in MODELS:
        raise ReferenceError(f"unknown reference model {name!r}; known: {', '.join(sorted(MODELS))}")
    mod, cls = MODELS[name].split(":")
    return getattr(importlib.import_module(mod), cls)
