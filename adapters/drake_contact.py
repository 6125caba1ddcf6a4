"""Contact parameters for Drake's compliant point contact: stiffness from a
contact duration, dissipation calibrated to a coefficient of restitution.

Drake has no coefficient of restitution.  Its point contact is a compliant
force on the penetration x (m) and its rate xdot (m/s, > 0 approaching):

- Hunt–Crossley (continuous time, and the discrete approximations tamsi,
  similar, lagged): f = k x (1 + d xdot), d in s/m;
- linear Kelvin–Voigt (the SAP approximation): f = k (x + tau xdot), tau in s;

both one-sided (f >= 0).  With x scaled by v_in / omega and time by 1/omega
(omega = sqrt(k / m_eff), v_in the approach speed) each becomes one
dimensionless equation, X'' = -X (1 + alpha X') with alpha = d v_in, or
X'' = -(X + beta X') with beta = tau omega, so the bounce ratio is a function
e(alpha) or e(beta) alone (no gravity acting during the contact, continuous
time).  :func:`hc_alpha` and :func:`kv_beta` invert those functions by
integrating the dimensionless equation (scipy RK45,
rtol 1e-10).  The mapping the adapter states:

- d = alpha(e) / v_impact, v_impact the pair group's predicted first impact
  speed (:func:`adapters.mujoco_impacts.predict_impact`; a resting or
  unpredicted contact takes 1 m/s);
- tau = beta(e) / omega, omega = pi / (contact_steps dt): independent of the
  impact speed.

e = 0 is out of reach of both laws (alpha, beta -> infinity): it is realised
as e = ZERO_E.  Pinned by tests/test_adapter_drake.py (the inverse against a
direct integration, bounce ratios of runs against e).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math

#: the bounce ratio that stands for e = 0 (neither law reaches 0)
ZERO_E = 0.005


def _bounce(accel, max_t: float = 1e4) -> float:
    """Exit speed over entry speed of the scaled contact X'' = accel(X, X'),
    X(0) = 0, X'(0) = 1, until X returns to 0 (scipy's RK45 at rtol 1e-10,
    the return found as an event; once the force vanishes the body coasts)."""
    from scipy.integrate import solve_ivp

    def out(t, y):
        return y[0]

    out.terminal, out.direction = True, -1.0
    sol = solve_ivp(lambda t, y: (y[1], accel(y[0], y[1])), (0.0, max_t), (0.0, 1.0), events=out,
                    rtol=1e-10, atol=1e-12, first_step=1e-3)
    if not sol.t_events[0].size:
        return 0.0  # never leaves
    return max(-float(sol.y_events[0][0][1]), 0.0)


def hc_bounce(alpha: float) -> float:
    """Bounce ratio of the Hunt–Crossley contact at alpha = d v_in."""
    return _bounce(lambda x, v: -x * max(1.0 + alpha * v, 0.0) if x > 0.0 else 0.0)


def kv_bounce(beta: float) -> float:
    """Bounce ratio of the clipped Kelvin–Voigt contact at beta = tau omega."""
    return _bounce(lambda x, v: -max(x + beta * v, 0.0) if x > 0.0 else 0.0)


def _invert(fn, e: float) -> float:
    """The parameter p >= 0 with fn(p) = e (fn decreasing from fn(0) = 1),
    by bisection on log p to a relative 1e-6 of p."""
    if e >= 1.0:
        return 0.0
    lo, hi = 1e-9, 1.0
    while fn(hi) > e:
        lo, hi = hi, hi * 4.0
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        if fn(mid) > e:
            lo = mid
        else:
            hi = mid
        if hi / lo - 1.0 < 1e-6:
            break
    return math.sqrt(lo * hi)


@functools.lru_cache(maxsize=256)
def hc_alpha(e: float) -> float:
    """alpha = d v_in of the Hunt–Crossley contact that bounces at e (e = 0
    is taken as ZERO_E)."""
    return _invert(hc_bounce, max(float(e), ZERO_E))


@functools.lru_cache(maxsize=256)
def kv_beta(e: float) -> float:
    """beta = tau omega of the clipped Kelvin–Voigt contact that bounces at e
    (e = 0 is taken as ZERO_E)."""
    return _invert(kv_bounce, max(float(e), ZERO_E))


def contact_omega(dt: float, contact_steps: float) -> float:
    """omega = pi / (contact_steps dt) (rad/s): an undamped contact lasts
    ``contact_steps`` steps of ``dt`` (s), whatever the masses (each body's
    stiffness is m omega^2, and Drake's series combination of two bodies'
    stiffness gives m_eff omega^2)."""
    return math.pi / (contact_steps * dt)


# ---- discrete time: Drake's own 1-D bounce ------------------------------------

@contextlib.contextmanager
def quiet_drake():
    """Drake's log at ERROR while building: a rigid half space draws a warning
    about deformable contact, and there are no deformable bodies here."""
    log = logging.getLogger("drake")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)


_R = 100.0  # m: the calibration sphere's radius, far above its overlap (~3 m)
#: impact phases (fraction of a step) the discrete calibration averages over
PHASES = (0.125, 0.375, 0.625, 0.875)


def discrete_bounce(param: float, approximation: str, contact_steps: float, phases=PHASES) -> float:
    """Mean bounce ratio of Drake's discrete plant (``approximation``, time
    step 1 s, omega = pi / contact_steps) for a unit-mass sphere hitting a
    half space at 1 m/s without gravity, over the impact ``phases``.
    ``param`` is alpha = d v (Hunt–Crossley) or beta = tau omega (SAP): the
    scaled problem depends on nothing else, so the result holds for every
    dt, mass and speed (pinned by tests/test_adapter_drake.py: the runs'
    bounce ratios)."""

    with quiet_drake():
        return _discrete_bounce(param, approximation, contact_steps, phases)


def _discrete_bounce(param: float, approximation: str, contact_steps: float, phases) -> float:
    import numpy as np
    from pydrake.geometry import AddContactMaterial, HalfSpace, ProximityProperties, Sphere
    from pydrake.math import RigidTransform
    from pydrake.multibody.plant import AddMultibodyPlant, CoulombFriction, MultibodyPlantConfig
    from pydrake.multibody.tree import SpatialInertia, UnitInertia
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.framework import DiagramBuilder

    omega = math.pi / contact_steps
    sap = approximation == "sap"
    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(MultibodyPlantConfig(time_step=1.0, contact_model="point",
                                                      discrete_contact_approximation=approximation), builder)
    ball = plant.AddRigidBody("ball", SpatialInertia(1.0, np.zeros(3), UnitInertia(0.1, 0.1, 0.1)))
    for body, shape, X, k in ((ball, Sphere(_R), RigidTransform(), omega ** 2),
                              (plant.world_body(), HalfSpace(), RigidTransform(), 1e20)):
        p = ProximityProperties()
        AddContactMaterial(dissipation=0.0 if sap else param, point_stiffness=k,
                           friction=CoulombFriction(0.0, 0.0), properties=p)
        if sap:
            p.AddProperty("material", "relaxation_time", param / omega)
        plant.RegisterCollisionGeometry(body, X, shape, "g" if body is ball else "s", p)
    plant.mutable_gravity_field().set_gravity_vector(np.zeros(3))
    plant.Finalize()
    sim = Simulator(builder.Build())
    ctx = sim.get_mutable_context()
    pctx = plant.GetMyMutableContextFromRoot(ctx)
    out = []
    for ph in phases:
        x = np.zeros(13)
        x[0], x[6], x[12] = 1.0, _R + 2.0 - ph, -1.0  # qw, z = r + gap (m), vz (m/s)
        ctx.SetTime(0.0)
        plant.SetPositionsAndVelocities(pctx, x)
        sim.Initialize()
        e = 0.0
        for k in range(1, int(20 * contact_steps) + 10):
            sim.AdvanceTo(float(k))
            z, vz = plant.GetPositions(pctx)[6], plant.GetVelocities(pctx)[5]
            if z > _R and vz > 0.0:
                e = vz
                break
        out.append(e)
    return float(sum(out) / len(out))


@functools.lru_cache(maxsize=256)
def discrete_param(e: float, approximation: str, contact_steps: float) -> tuple[float, float]:
    """(parameter, reach): alpha (or beta for SAP) whose discrete bounce
    (:func:`discrete_bounce`) is ``e`` (e = 0 as ZERO_E), and the bounce at
    zero dissipation, the most this step can realise (then the parameter is
    nan when e exceeds it)."""
    reach = discrete_bounce(0.0, approximation, contact_steps)
    target = max(float(e), ZERO_E)
    if target > reach:
        return math.nan, reach
    fn = functools.partial(_bounded, approximation=approximation, contact_steps=contact_steps)
    return _invert(fn, target), reach


def _bounded(p: float, approximation: str, contact_steps: float) -> float:
    return discrete_bounce(p, approximation, contact_steps)
