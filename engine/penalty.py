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

from engine.profile import Stage
from engine.contact.rows import Rows, _pad, point_normal_velocity

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
        vn, rel = point_normal_velocity(V0, W0, cs.a, cs.b, rows.rA, rows.rB, cs.normal)
        m_eff = rows.mn
        if self.k > 0:
            k = np.full(cs.m, self.k)
        else:
            T = PERIODS * model.h
            k = m_eff * (np.pi / T) ** 2
        zeta = np.array([damping_ratio_for(float(x)) for x in cs.e])
        damp = 2.0 * zeta * np.sqrt(k * m_eff)
        depth = -cs.gap
        # spring at the predicted mid-step depth (a leapfrog-like evaluation:
        # the spring neither gains nor loses energy by itself), dashpot at the
        # start velocity
        d_mid = depth - 0.5 * h * vn
        Fn = np.maximum(k * d_mid - damp * vn, 0.0)
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
