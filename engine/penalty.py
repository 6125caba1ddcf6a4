"""Penalty contacts (``contact_model = penalty``): an alternative to the
impulse solver, where every penetrating contact is a spring-damper.

Normal force F = max(k d - c vn, 0) for depth d = -gap > 0 and normal
relative velocity vn.  With ``penalty_stiffness = 0`` (auto) each contact's
stiffness comes from its effective mass m_eff and a contact duration of
``PERIODS`` substeps: k = m_eff (pi / T)^2, T = PERIODS h; the damping gives
the pair's restitution: c = 2 zeta sqrt(k m_eff) with zeta solved from the
closed-form motion of the clamped spring-dashpot (:func:`damping_ratio_for`;
the textbook e = exp(-zeta pi / sqrt(1 - zeta^2)) ignores that the clamped
force lets go early).  The spring is evaluated at the predicted mid-step
depth, which keeps it from creating energy.
Friction is regularised Coulomb: |Ft| = min(mu_k Fn, what stops the sliding
within the step), opposite the sliding velocity (no separate static
friction: noted by the adapter).  Rolling friction likewise: a torque
min(mu_r Fn, what stops the relative rolling) against the rolling.

Forces are held constant over the step and applied as impulses F h to the
working velocities, so the position update is the same as for the impulse
solver.  There is no CCD with penalty contacts.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numba import njit

from physbench.engine.profile import Stage
from physbench.engine.contact.rows import Rows, _pad

PERIODS = 20.0


@lru_cache(maxsize=256)
def damping_ratio_for(e: float) -> float:
    """Damping ratio zeta of a linear spring-dashpot whose contact force is
    clamped at zero (the contact lets go when k d + c d' reaches 0) that
    gives the coefficient of restitution ``e``.

    The unclamped formula e = exp(-zeta pi / sqrt(1 - zeta^2)) ignores the
    early release and gives a few per cent too much bounce; here e(zeta) is
    computed from the closed-form motion (omega = 1):
    d(t) = exp(-zeta t) sin(wd t) / wd, release at the first root of
    d + 2 zeta d' = 0, e = -d'(release); and inverted by bisection."""
    if e >= 1.0:
        return 0.0
    if e <= 0.0:
        return 1.0

    def restitution(z: float) -> float:
        wd = math.sqrt(1.0 - z * z)
        d = lambda t: math.exp(-z * t) * math.sin(wd * t) / wd  # noqa: E731
        dd = lambda t: math.exp(-z * t) * (math.cos(wd * t) - z * math.sin(wd * t) / wd)  # noqa: E731
        f = lambda t: d(t) + 2.0 * z * dd(t)  # noqa: E731
        lo, hi = 1e-9, math.pi / wd  # f > 0 just after impact, f < 0 at the half period
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            if f(mid) > 0:
                lo = mid
            else:
                hi = mid
        return -dd(0.5 * (lo + hi))

    lo, hi = 0.0, 0.999
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if restitution(mid) > e:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@njit(cache=True)
def normal_forces(X, V, W, a, b, point, normal, gap, m_eff, fixed, kfac, zeta, h, out):
    """Normal forces (N) of penetrating contacts (m,) into ``out``: F =
    max(k d_mid - c vn, 0) with the spring at the predicted mid-step depth
    d_mid = -gap - h vn / 2 (a leapfrog-like evaluation: the spring
    neither gains nor loses energy by itself) and the dashpot at the start
    normal speed vn (m/s, from the padded start velocities V, W (n+1, 3));
    k = kfac when ``fixed`` (the setting), else m_eff kfac (kfac =
    (pi / T)^2); c = 2 zeta sqrt(k m_eff).  The numpy form's arithmetic
    (the normal speed summed as einsum "ki,ki->k": (p0 + p2) + p1; the
    final states are pinned)."""
    n = X.shape[0]
    for i in range(gap.shape[0]):
        ka, kb = a[i], b[i]
        ra0, ra1, ra2 = point[i, 0] - X[ka, 0], point[i, 1] - X[ka, 1], point[i, 2] - X[ka, 2]
        xb0, xb1, xb2 = (X[kb, 0], X[kb, 1], X[kb, 2]) if kb < n else (0.0, 0.0, 0.0)
        rb0, rb1, rb2 = point[i, 0] - xb0, point[i, 1] - xb1, point[i, 2] - xb2
        r0 = V[kb, 0] + (W[kb, 1] * rb2 - W[kb, 2] * rb1) - V[ka, 0] - (W[ka, 1] * ra2 - W[ka, 2] * ra1)
        r1 = V[kb, 1] + (W[kb, 2] * rb0 - W[kb, 0] * rb2) - V[ka, 1] - (W[ka, 2] * ra0 - W[ka, 0] * ra2)
        r2 = V[kb, 2] + (W[kb, 0] * rb1 - W[kb, 1] * rb0) - V[ka, 2] - (W[ka, 0] * ra1 - W[ka, 1] * ra0)
        vn = (r0 * normal[i, 0] + r2 * normal[i, 2]) + r1 * normal[i, 1]
        k = kfac if fixed else m_eff[i] * kfac
        damp = 2.0 * zeta[i] * np.sqrt(k * m_eff[i])
        f = k * (-gap[i] - 0.5 * h * vn) - damp * vn
        out[i] = f if (f >= 0.0 or np.isnan(f)) else 0.0  # np.maximum(f, 0.0)
    return out


class PenaltyContacts(Stage):
    name = "penalty"
    family = "penalty"

    def __init__(self, model):
        self.k = float(model.settings["penalty_stiffness"])
        self.friction = model.has("friction")

    def __call__(self, model, state, ctx) -> None:
        c = ctx.contacts
        if c is None or c.m == 0:
            return
        sel = np.flatnonzero(c.gap < 0.0)
        if sel.size == 0:
            return
        h = ctx.h
        rows = Rows(model, state.x, ctx.Iinv0, c.take(sel), self.friction, colour=False)
        cs = rows.contacts
        V0, W0 = _pad(state.v), _pad(state.w)
        # k = m_eff (pi / T)^2 with T = PERIODS h (auto), or the setting
        kfac = (np.pi / (PERIODS * model.h)) ** 2 if self.k <= 0 else self.k
        e, inv = np.unique(cs.e, return_inverse=True)
        zeta = np.array([damping_ratio_for(float(x)) for x in e])[inv]
        Fn = normal_forces(state.x, V0, W0, cs.a, cs.b, cs.point, cs.normal, cs.gap, rows.mn, self.k > 0, kfac,
                           zeta, h, np.empty(cs.m))
        U = Rows.pack(ctx.v, ctx.w)
        rows.apply_normal(U, Fn * h)
        if self.friction:
            # regularised Coulomb per contact patch, at its centroid
            U0 = Rows.pack(V0, W0)
            vt = rows.patch_tangent_velocity(U0)
            speed = np.sqrt(np.einsum("km,km->k", vt, vt))
            Fn_patch = np.bincount(rows.pid, Fn, rows.np)
            stop = speed * np.min(rows.mt[:, :2], axis=1)  # impulse that would stop the sliding
            mag = np.minimum(rows.muk * Fn_patch * h, stop)
            d = np.zeros(rows.lam_t.shape)
            d[:, :2] = -vt / np.where(speed > 0, speed, 1.0)[:, None] * mag[:, None]
            if rows.rolling:
                # rolling resistance the same way: |torque| = min(mu_r Fn,
                # what stops the relative rolling), against it
                wr = rows.patch_velocity(U0, slice(3, 5))
                rs = np.sqrt(np.einsum("km,km->k", wr, wr))
                mag_r = np.minimum(rows.mur * Fn_patch * h, rs * np.min(rows.mt[:, 3:], axis=1))
                d[:, 3:] = -wr / np.where(rs > 0, rs, 1.0)[:, None] * mag_r[:, None]
            rows.apply_patch(U, d)
        Rows.unpack(U, ctx.v, ctx.w)
        ctx.profile.count("contact_rows", cs.m)


def warm_up() -> None:
    """Compile (or load) :func:`normal_forces` with the step's argument
    types (see engine/jit.py)."""
    one, i1 = np.ones((1, 3)), np.zeros(1, np.int64)
    V = np.zeros((2, 3))
    for fixed in (False, True):
        normal_forces(one, V, V, i1, i1 + 1, one, one, -np.ones(1), np.ones(1), fixed, 1.0, np.ones(1), 0.01,
                      np.empty(1))
