"""The model's predictions as numbers, beside the measured values.

``physbench run`` (its table and ``--json``) and ``physbench validate``
show what the scene's reference model predicts, before and beside what
the run measured.  :func:`predictions` gives two things:

- ``values``: the documented prediction keys (:data:`PREDICTION_KEYS`,
  the "Predictions" table of docs/METRICS.md) with numbers in SI units,
  named ``<quantity>_ref`` after the measured metric they go beside
  (``roll_accel_ref`` beside ``roll_accel``); a value per body is a table
  {body name: value};
- ``text``: the model's own statement of what it predicts
  (:meth:`harness.references.ReferenceModel.predictions`, the trace's
  context document), label -> text with units, for every model.

Both come from the model built on the scene alone: no run is needed.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

#: prediction key -> meaning with units (docs/METRICS.md "Predictions";
#: tests/test_references.py::test_prediction_keys_are_documented)
PREDICTION_KEYS: dict[str, str] = {
    "impact_time_ref": "time of the (first) impact (s)",
    "post_impact_velocity_ref": "each colliding body's velocity just after the impact, [vx, vy, vz] (m/s)",
    "final_velocity_ref": "each ball's velocity along the row after the collisions (m/s)",
    "momentum_ref": "total momentum normal to gravity, conserved, [Px, Py, Pz] (N s)",
    "energy_ref": "mechanical energy, conserved when restitution is 1 (J)",
    "apex_heights_ref": "apex heights of the bottom above the plane after the bounces the model follows (m)",
    "impact_speed_ref": "speed at the first impact (m/s)",
    "roll_accel_ref": "acceleration downhill while rolling (or slipping) (m/s^2)",
    "spin_accel_ref": "angular acceleration about n x d (rad/s^2)",
    "slide_accel_ref": "acceleration along the slope while sliding (m/s^2)",
    "stop_time_ref": "time the motion stops (s)",
    "stop_distance_ref": "distance slid until the stop (m)",
    "spin_decel_ref": "angular deceleration of the spin about the normal (rad/s^2)",
    "period_ref": "period of the damped oscillation, 2 pi / w_d (s)",
    "decay_rate_ref": "amplitude decay rate c / (2 m_eff) (1/s)",
    "terminal_velocity_ref": "terminal speed against the drag (m/s)",
}


def _finite(x: Any) -> bool:
    return x is not None and math.isfinite(float(x))


def _collision(m) -> dict[str, Any]:
    if m.t_impact is None:
        return {}
    names = [m.scene.bodies[i].name for i in m.idx]
    return {"impact_time_ref": float(m.t_impact),
            "post_impact_velocity_ref": {names[0]: np.asarray(m.v1_post, float).tolist(),
                                         names[1]: np.asarray(m.v2_post, float).tolist()}}


def _cradle(m) -> dict[str, Any]:
    return {"final_velocity_ref": {b.name: float(m.v_final[b.index]) for b in m.scene.bodies}}


def _momentum(m) -> dict[str, Any]:
    out: dict[str, Any] = {"momentum_ref": np.asarray(m.P0, float).tolist()}
    if m.conserves_energy():
        out["energy_ref"] = float(m._initial_energy())
    return out


def _bounce(m) -> dict[str, Any]:
    return {"impact_time_ref": float(m.t1), "impact_speed_ref": float(m.v1),
            "apex_heights_ref": [float(h) for h in m.reference_apexes(m.scene.duration)]}


def _rolling(m) -> dict[str, Any]:
    return {"roll_accel_ref": float(m.a), "spin_accel_ref": float(m.alpha)}


def _rolling_resistance(m) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if m.fit_phase is not None:
        a = float(m.fit_phase[3])
        out.update(roll_accel_ref=a, spin_accel_ref=a / m.R)
    if math.isfinite(m.t_stop) and m.t_stop > 0:
        out["stop_time_ref"] = float(m.t_stop)
    return out


def _incline(m) -> dict[str, Any]:
    out: dict[str, Any] = {"slide_accel_ref": float(m.a_slide)}
    if math.isfinite(m.t_stop) and m.t_stop > 0:
        out["stop_time_ref"] = float(m.t_stop)
    return out


def _slide_to_rest(m) -> dict[str, Any]:
    return {**_incline(m), "stop_distance_ref": float(m.d_stop)}


def _spin(m) -> dict[str, Any]:
    return {"spin_decel_ref": float(m.alpha), "stop_time_ref": float(m.t_stop)}


def _oscillator(m) -> dict[str, Any]:
    out: dict[str, Any] = {"decay_rate_ref": float(m.gamma)}
    if m.zeta < 1.0 and m.wd > 0:
        out["period_ref"] = 2 * math.pi / float(m.wd)
    return out


def _drag(m) -> dict[str, Any]:
    return {"terminal_velocity_ref": float(m.v_t)}


#: model name -> its prediction values (from the model's attributes)
_VALUES: dict[str, Callable[[Any], dict[str, Any]]] = {
    "two_body_collision": _collision,
    "oblique_collision": _collision,
    "newtons_cradle": _cradle,
    "momentum_energy": _momentum,
    "bounce_heights": _bounce,
    "rolling_sphere": _rolling,
    "rolling_cylinder": _rolling,
    "rolling_resistance": _rolling_resistance,
    "incline_block": _incline,
    "slide_to_rest": _slide_to_rest,
    "spin_to_rest": _spin,
    "damped_oscillator": _oscillator,
    "drag_fall": _drag,
}


def predictions(scene) -> tuple[dict[str, Any], dict[str, str]]:
    """(values, text) the scene's reference model predicts (see the module
    docstring); ({}, {}) without a model.  Non-finite numbers are left out
    (a motion that never stops has no stop time)."""
    if not scene.reference_model:
        return {}, {}
    from physbench.contract.models import get_model

    model = get_model(scene.reference_model)(scene)
    fn = _VALUES.get(scene.reference_model)
    values = fn(model) if fn else {}
    values = {k: v for k, v in values.items() if not isinstance(v, float) or _finite(v)}
    return values, dict(model.predictions())
