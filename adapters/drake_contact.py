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

from physbench.adapters.base import Unsupported

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


# ---- the scene's contact materials ----------------------------------------------

STATIC_STIFFNESS = 1e20  # N/m: in series with a body's k it leaves the body's
FALLBACK_SPEED = 1.0  # m/s: impact speed of a resting or unpredicted contact
MIN_IMPACT_SPEED = 0.05


def contact_materials(scene, settings: dict, ts: float, notes: list, info: dict):
    """Return material(index, is_body) -> Drake ProximityProperties realising
    every contact pair of ``scene`` (stiffness, dissipation, friction) with
    resolved ``settings`` and plant time step ``ts`` (s; 0 continuous), after
    checking that they can be realised (else raise Unsupported with the
    reason); appends the mapping to ``notes`` and ``info``."""
    from pydrake.geometry import (AddCompliantHydroelasticProperties, AddContactMaterial,
                                  AddRigidHydroelasticProperties, ProximityProperties)
    from pydrake.multibody.plant import CoulombFriction

    pairs = scene.contact_pairs()
    sap = ts > 0 and settings["approximation"] == "sap"
    omega = contact_omega(float(settings["dt"]), float(settings["contact_steps"]))
    es = {float(m.restitution) if scene.has("restitution") else 0.0 for *_, m in pairs}
    fr = {(float(max(m.static_friction, m.friction)), float(m.friction)) if scene.has("friction") else (0.0, 0.0)
          for *_, m in pairs}
    if len(fr) > 1:
        raise Unsupported(f"Drake combines two geometries' friction as 2ab/(a+b); the scene's pairs ask for "
                          f"{len(fr)} different (static, kinetic) values {sorted(fr)}, which per-geometry "
                          "values do not realise here")
    if len(es) > 1:
        raise Unsupported(f"Drake combines two geometries' dissipation; the scene's pairs ask for {len(es)} "
                          f"different restitution values {sorted(es)}, which one per-geometry dissipation "
                          "does not realise here")
    e = es.pop()
    (mus, muk), = fr
    if settings["dissipation"] >= 0.0:
        if scene.has("restitution"):
            raise Unsupported(f"dissipation is set to {settings['dissipation']:g} s/m, so the scene's "
                              f"restitution e = {e:g} cannot be realised")
        d, tau = float(settings["dissipation"]), None
        notes.append(f"Hunt-Crossley dissipation {d:g} s/m as set; not calibrated")
    elif scene.has("restitution") and (settings["point_stiffness"] > 0 or settings["contact_model"] != "point"):
        raise Unsupported(f"the restitution calibration assumes point contact with k = m omega^2 "
                          f"(point_stiffness 0); with point_stiffness {settings['point_stiffness']:g} N/m and "
                          f"contact_model {settings['contact_model']} the scene's e = {e:g} is not realised")
    else:
        from physbench.adapters.mujoco_impacts import predict_impact

        speed = max(predict_impact(scene, kb, ia, ib)["speed"] for _, ia, kb, ib, _ in pairs)
        v = speed if speed >= MIN_IMPACT_SPEED else FALLBACK_SPEED
        label = " (no restitution effect)" if not scene.has("restitution") else ""
        as_zero = f", realised as {ZERO_E}" if e < ZERO_E else ""
        if ts == 0.0:
            alpha = hc_alpha(e)
            how = f"the continuous-time Hunt-Crossley map alpha(e) = {alpha:.6g}"
        else:
            steps = math.pi / (omega * ts)  # duration of an undamped contact in plant steps
            alpha, reach = discrete_param(e, settings["approximation"], steps)
            if math.isnan(alpha):
                raise Unsupported(
                    f"Drake has no restitution coefficient and its discrete {settings['approximation']} step "
                    f"dissipates by itself: with {steps:.4g} steps per undamped contact (contact_steps) a "
                    f"contact without dissipation bounces at {reach:.4f} (Drake's own 1-D bounce, 4 impact "
                    f"phases), below the scene's e = {e:g}; more contact_steps or time_step = 0 realise it")
            how = (f"Drake's own discrete {settings['approximation']} bounce at {steps:.4g} steps per contact "
                   f"(4 impact phases; {reach:.4f} without dissipation): "
                   f"{'beta' if sap else 'alpha'}(e) = {alpha:.6g}")
        if sap:
            tau, d = alpha / omega, None
            what = f"SAP's Kelvin-Voigt relaxation time tau = beta(e) / omega = {tau:.6g} s (omega {omega:.6g} rad/s)"
        else:
            d, tau = alpha / v, None
            what = (f"Hunt-Crossley dissipation d = alpha(e) / v_impact = {d:.6g} s/m (v_impact {v:.6g} m/s: "
                    f"{'the fastest predicted first impact' if speed >= MIN_IMPACT_SPEED else 'no impact predicted'})")
        notes.append(f"Drake has no restitution coefficient: e = {e:g}{label}{as_zero} by {what}, from {how}")
    info["contact_parameters"] = {"restitution": e, "omega": omega, "hunt_crossley_dissipation": d,
                                       "relaxation_time": tau, "friction": [mus, muk]}
    hydro = settings["contact_model"] != "point"
    k_set = settings["point_stiffness"]

    def material(i: int, is_body: bool):
        p = ProximityProperties()
        k = (k_set if k_set else scene.bodies[i].mass * omega ** 2) if is_body else STATIC_STIFFNESS
        AddContactMaterial(dissipation=d if d is not None else 0.0, point_stiffness=k,
                           friction=CoulombFriction(mus, muk), properties=p)
        if tau is not None:
            p.AddProperty("material", "relaxation_time", tau)
        if hydro and is_body:
            b = scene.bodies[i]
            AddCompliantHydroelasticProperties(0.5 * b.min_extent, float(settings["hydroelastic_modulus"]), p)
        elif hydro:
            AddRigidHydroelasticProperties(p)
        return p

    return material

