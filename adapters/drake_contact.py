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

import functools
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
