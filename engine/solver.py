"""Contact solver: sequential impulses (projected Gauss-Seidel) with
accumulated-impulse clamping, warm starting, Coulomb friction (static and
kinetic) and restitution; position correction by split impulse, Baumgarte
or none; and the impact solver used at times of impact.

Rows
----
Each contact point gives a normal row.  For a contact between bodies a and
b (b = n, the world, for statics) with normal n from a to b, lever arms
rA = p - xa, rB = p - xb, the normal relative velocity is

    vn = n.(vb - va) + (rB x n).wb - (rA x n).wa        (> 0: separating)

and an impulse lambda n is applied +lambda n to b and -lambda n to a.  The
effective mass is 1 / (1/ma + 1/mb + (rA x n).IA^-1 (rA x n) + (rB x n).IB^-1 (rB x n)).

The solver works on the *end-of-step* velocities v1 = v_free + dv (see
integrate.py for how dv moves positions: the "contact lever" c, 1 for
semi-implicit Euler, 1/2 for the others, so that x1 = x_free + c h dv).
A normal row's target (the least allowed vn) is the largest of

* contact: vn1 >= 0 for a touching contact (gap <= TOUCH_TOL); for a
  separated (speculative) one min(vn_free - (gap + h un) / (c h), 0), where
  un is the free flight's mean normal velocity: the end pose may just close
  the gap.  Never a push-out, so resting and slowly approaching contacts
  neither penetrate nor gain energy;
* restitution: -e vn0 when the contact is touching and approached at the
  start of the step faster than ``restitution_threshold`` (vn0 < -thr),
  with vn0 the approach velocity *before* the step's forces and the solve
  (this only happens without CCD; with it, impacts are events).

A contact that is not yet touching but that this step's motion would close
at an approach speed above the threshold is an *impact*: with ``ccd``
resolving it (mode "events", or "toi" for fast bodies) it is excluded from
the solve and handed to the CCD stage, which splits the step at the time of
impact and resolves it there (:func:`impact_solve`).  In a pair that pressed
on the other last step (a persistent contact) a closing row is an impact
only if its point did not press, was approaching faster than the threshold
already at the start of the step, and a speculative row would sink it
beyond the correction slop (see :class:`Solve`); a touching point
approaching so is an impact at once (time of impact 0).

Friction acts per contact patch (all points of a pair), see :class:`Rows`.
A patch that slides at the start of the step (relative tangential speed at
its centroid, or its twist's speed at its mean point distance, above
``SLIP_TOL``) uses mu_k; a sticking one uses mu_s, and if its friction or
twist ends on the mu_s limit it cannot stick: it switches to mu_k and the rows are
solved again (static friction cannot be exceeded; once broken, kinetic
applies).  A sliding (or rolling) patch that comes to rest inside the step
and does not stay at rest is a *friction stop*: :meth:`Rows.stop_times`
finds when, and the step loop (pipeline._substep) cuts the step there.

Position correction: push-out velocities beta (depth - slop) / h, solved on
separate pseudo velocities that move positions by h vp.  ``split_impulse``
discards them after the step (no energy); ``baumgarte`` keeps them in the
real velocity too (the classic velocity bias, which injects energy).

Gauss-Seidel, vectorised: rows are coloured greedily so that no dynamic body
appears twice in a colour; a colour's rows are independent, so updating them
together in numpy gives exactly the sequential result for that ordering.
Deterministic (fixed order).

Cost: with a few dozen rows the step costs numpy calls, not arithmetic.
Everything that depends only on the contact graph -- which bodies the rows
join, in which order: the colouring, the friction patches, the pair
grouping of the warm cache, the pair coefficients -- is a
:class:`Topology`, built once per distinct graph and reused while it is
unchanged (a resting stack: every step), so a step only redoes the
pose-dependent arithmetic.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from engine.contact import linalg, sweeps
from engine.mathutil import cross, perpendicular_basis
from engine.profile import Stage
from engine.state import Contacts

TOUCH_TOL = 1e-6  # m: a contact whose gap is below this is touching
DIRECT_MAX_ROWS = 400  # rows up to which the direct start is a dense LU solve; above, sparse (banded Cholesky per island)
#: re-solves of the dense direct start with the rows it pulls on let go
ACTIVE_SET_PASSES = 4
RESTING_SPEED = 1e-5  # m/s: rows separating slower than this count as resting in the direct start
SLIP_TOL = 1e-4  # m/s: relative tangential speed above which a contact slides (twist: at r_twist)
ROLL_TOL = 1e-4  # rad/s: relative rolling angular speed above which a contact rolls (rolling friction)
STOP_MAX_RESIDUAL = 1e-4  # friction stops only from a solve whose last sweep changed impulses by less (relative)
STOP_MIN_REST = 1e-6  # a friction stop this close to a step's end (fraction of it) does not cut the step
WARM_MIN_STEP = 1e-3  # (sub)steps shorter than this fraction of the model's step cache no forces


def dense_direct_solve(K: np.ndarray, r: np.ndarray, act: np.ndarray, passes: int):
    """The dense direct start's active-set solves (compiled,
    :func:`engine.contact.linalg.dense_active_set`, Tikhonov 1e-10 of the
    largest diagonal): (lambda (m,) >= 0, ok, whether the last pass still
    pulled on a row and was clipped)."""
    return linalg.dense_active_set(K, r, act, 1e-10, passes)


def _pad(a: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n+1, 3) with a zero world row."""
    out = np.zeros((a.shape[0] + 1, 3))
    out[:-1] = a
    return out


def _onto_disc(d: np.ndarray, lim: np.ndarray) -> None:
    """Scale the rows of the 2-vectors ``d`` (k, 2) longer than ``lim`` (k,)
    back onto that disc, in place (the Coulomb and rolling limits)."""
    mag = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)
    over = mag > lim
    if over.any():
        d *= np.where(over, lim / np.where(mag > 0, mag, 1.0), 1.0)[:, None]


def point_normal_velocity(V, W, a, b, rA, rB, n):
    """n . (vb + wb x rB - va - wa x rA) for padded (n+1, 3) V, W."""
    rel = V[b] + cross(W[b], rB) - V[a] - cross(W[a], rA)
    return np.einsum("ki,ki->k", rel, n), rel


def colour_order(a: np.ndarray, b: np.ndarray, world: int) -> tuple[np.ndarray, np.ndarray]:
    """Greedy colouring: rows of one colour share no dynamic body.  Returns
    (order, bounds): the rows sorted by colour (stable) and the colour
    boundaries, so every colour is a contiguous slice of the sorted rows."""
    m = a.size
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(1, np.int64)
    used: dict[int, int] = {}
    get = used.get
    cols = []
    append = cols.append
    for i, j in zip(a.tolist(), b.tolist()):
        ui = get(i, 0)
        if j != world:
            uj = get(j, 0)
            mask = ui | uj
        else:
            mask = ui
        c = ((~mask) & (mask + 1)).bit_length() - 1  # lowest free colour
        bit = 1 << c
        append(c)
        used[i] = ui | bit
        if j != world:
            used[j] = get(j, 0) | bit
    col = np.array(cols, np.int64)
    order = np.argsort(col, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(np.bincount(col))])
    return order, bounds


class Topology:
    """The part of a row set that depends only on which bodies (and
    statics) its rows join, in which order -- never on the pose: the
    colouring and its slices, the friction patches (grouping, colouring,
    slices, pair coefficients, inverse masses), the pair-code grouping of
    the warm-start cache and the body-sharing masks of the normal matrix.

    Built from the rows' (a, b, sidx) and reused while the contact graph is
    unchanged (:class:`Solve` keeps the last few; a resting stack rebuilds
    nothing after its first step).  Everything here is what :class:`Rows`
    computed per step before, by the same operations, so reuse is exact.
    Arrays are over the rows in colour order unless said otherwise.
    """

    def __init__(self, model, a: np.ndarray, b: np.ndarray, sidx: np.ndarray, friction: bool, colour: bool):
        n = model.n
        m = a.size
        if colour:
            order, bounds = colour_order(a, b, n)
            a, b, sidx = a[order], b[order], sidx[order]
        else:
            order, bounds = np.arange(m), np.array([0, m])
        self.colour = colour
        self.order = order
        self.m = m
        self.a, self.b, self.sidx = a, b, sidx
        #: (a, b) stacked, rows of the world included: one gather/scatter of
        #: the (n+1, 6) velocities per colour
        self.ab = np.stack([a, b], axis=1)
        #: colour slices (start, end)
        self.slices = [(int(bounds[i]), int(bounds[i + 1])) for i in range(len(bounds) - 1) if bounds[i + 1] > bounds[i]]
        self.ima = model.inv_mass[a]
        self.imb = model.inv_mass[b]
        #: pair codes of the rows (the warm cache's keys), their stable sort
        #: and the first row of each distinct pair in that sort
        self.codes = _pair_codes_abs(model, a, b, sidx)
        self.code_order = np.argsort(self.codes, kind="stable")
        sc = self.codes[self.code_order]
        self.sorted_codes = sc
        self.code_first = np.flatnonzero(np.concatenate([[True], sc[1:] != sc[:-1]]))
        self.uniq_codes = sc[self.code_first]
        #: first row (in row order) of each distinct pair, = np.unique's return_index
        self.uniq_first = self.code_order[self.code_first]
        self._masks = None
        self.friction = friction
        if friction:
            self._patches(model, colour)

    def _patches(self, model, colour: bool) -> None:
        n = model.n
        a, b = self.a, self.b
        code = a * (n + 1) + b + (n + 1) * (n + 1) * (self.sidx + 1)
        uniq, first, pid = np.unique(code, return_index=True, return_inverse=True)
        npch = uniq.size
        pa, pb = a[first], b[first]
        if colour:
            porder, pbounds = colour_order(pa, pb, n)
        else:
            porder, pbounds = np.arange(npch), np.array([0, npch])
        rank = np.empty(npch, np.int64)
        rank[porder] = np.arange(npch)
        self.pid = pid = rank[pid]
        self.pa, self.pb = pa[porder], pb[porder]
        self.pab = np.stack([self.pa, self.pb], axis=1)
        self.np = npch
        #: first row of each patch (patch order)
        self.pfirst = first[porder]
        self.cnt = np.bincount(pid, minlength=npch).astype(float)
        #: bins (patch, component) of the rows' points and normals
        self.pn_bins = (pid[:, None] * 6 + np.arange(6)).ravel()
        self.pslices = [(int(pbounds[i]), int(pbounds[i + 1])) for i in range(len(pbounds) - 1)
                        if pbounds[i + 1] > pbounds[i]]
        self.pima = model.inv_mass[self.pa]
        self.pimb = model.inv_mass[self.pb]
        #: patch of each distinct pair (uniq_codes order)
        self.uniq_pid = pid[self.uniq_first]
        self.mus = self.muk = self.mur = None  # pair coefficients, from the first contacts seen

    def masks(self):
        """Body-sharing masks of the normal matrix (a_i == a_j, a_i == b_j,
        b_i == a_j, b_i == b_j), (m, m) bool."""
        if self._masks is None:
            a, b = self.a, self.b
            self._masks = (a[:, None] == a[None, :], a[:, None] == b[None, :],
                           b[:, None] == a[None, :], b[:, None] == b[None, :])
        return self._masks


class Rows:
    """Solver rows for a set of contacts at a pose (see module doc).

    Velocities are handled as one (n+1, 6) array U = [v, w] (world row n
    zero).  Normal rows, one per contact: Jacobians ``JA``/``JB`` (m, 6) with
    vn = JA.U[a] + JB.U[b], and ``MA``/``MB`` (m, 6) = M^-1 J^T, so that an
    impulse d changes U[a] += MA d, U[b] += MB d.  Rows are reordered by
    colour at construction (``contacts`` holds them in that order, ``order``
    maps back).

    Friction acts per contact *patch* (all contacts of one pair): two tangent
    rows at the patch centroid and a twist row about the patch normal,
    (np, 3, 6) Jacobians ``JtA``/``JtB``, limited by the patch's total normal
    impulse: |(l1, l2)| <= mu sum(lambda_n), |l_twist| <= mu sum(lambda_n)
    r_twist, where r_twist is the mean distance of the patch's points from
    its centroid (0 for a point contact: no torsional friction).  Coulomb's
    law is a law for the total force on a contact patch, and its limit then
    depends on the total normal impulse, which Gauss-Seidel gets right long
    before it settles how that impulse is shared among the points.

    Rolling friction (``model.rolling``: only then do the rows exist) adds
    two angular rows per patch, about the tangents t1, t2: the relative
    angular velocity perpendicular to the normal, t.(wb - wa), resisted by a
    torque whose magnitude is limited by mu_r sum(lambda_n) (a disc, like the
    tangent rows; mu_r is a length, MuJoCo's and Bullet's convention).  Rows
    (np, 5, 12) then, the rolling rows updated after the tangent and twist
    rows in each sweep (Gauss-Seidel between the two blocks: for a rolling
    ball they are strongly coupled, K_tr^2 / (K_tt K_rr) = 1 / (1 + k)).
    """

    def __init__(self, model, X, Iinv, c: Contacts, friction: bool, colour: bool = True,
                 sel: np.ndarray | None = None, topo: "Topology | None" = None):
        n = model.n
        if topo is None:
            src = c if sel is None else c.take(sel)
            topo = Topology(model, src.a, src.b, src.sidx, friction, colour)
        # rows of ``c`` (or of its rows ``sel``), sorted by colour: one gather
        if sel is None:
            if topo.colour:
                c = c.take(topo.order)
        else:
            c = c.take(sel[topo.order])
        self.topo = topo
        self.world = n
        self.order = topo.order
        self.contacts = c
        self.m = m = c.m
        self.a, self.b = topo.a, topo.b
        self.n = c.normal
        Xp = _pad(X)
        # both sides stacked (2, m, ...): the same element-wise arithmetic
        ab2 = np.stack([c.a, c.b])
        rAB = c.point - Xp[ab2]
        self.rA, self.rB = rAB[0], rAB[1]
        self.ima = topo.ima
        self.imb = topo.imb
        rnAB = cross(rAB, self.n)
        rnA, rnB = rnAB[0], rnAB[1]
        # [JA | JB] and [MA | MB] in one (m, 12) array each: the sweeps use
        # them stacked, everything else through the two views
        self.J = np.empty((m, 12))
        self.M = np.empty((m, 12))
        self.JA, self.JB = self.J[:, :6], self.J[:, 6:]
        self.MA, self.MB = self.M[:, :6], self.M[:, 6:]
        self.JA[:, :3] = -self.n
        self.JA[:, 3:] = -rnA
        self.JB[:, :3] = self.n
        self.JB[:, 3:] = rnB
        self.MA[:, :3] = -self.ima[:, None] * self.n
        IrnAB = np.einsum("skij,skj->ski", Iinv[ab2], rnAB)
        self.MA[:, 3:] = -IrnAB[0]
        self.MB[:, :3] = self.imb[:, None] * self.n
        self.MB[:, 3:] = IrnAB[1]
        kn = np.einsum("ki,ki->k", self.JA, self.MA) + np.einsum("ki,ki->k", self.JB, self.MB)
        self.mn = 1.0 / kn
        self.lam_n = np.zeros(m)
        self.target = np.zeros(m)
        self.friction = friction
        if friction:
            self._patches(model, Xp, Iinv, c)

    def _patches(self, model, Xp, Iinv, c: Contacts) -> None:
        topo = self.topo
        self.pid = pid = topo.pid
        self.pa, self.pb = topo.pa, topo.pb
        self.np = npch = topo.np
        cnt = topo.cnt
        # per-patch sums of the points and normals: one bincount over
        # (patch, component) bins, each summed in row order like a bincount
        # per component
        PN = np.bincount(topo.pn_bins, np.concatenate([c.point, c.normal], axis=1).ravel(), 6 * npch).reshape(npch, 6)
        P = PN[:, :3] / cnt[:, None]
        N = PN[:, 3:].copy()
        N /= np.linalg.norm(N, axis=1, keepdims=True)
        off = c.point - P[pid]
        Nk = N[pid]
        off -= np.einsum("ki,ki->k", off, Nk)[:, None] * Nk
        self.r_twist = np.bincount(pid, np.sqrt(np.einsum("ki,ki->k", off, off)), npch) / cnt
        self.pcentroid, self.pnormal = P, N
        t1, t2 = perpendicular_basis(N)
        self.t = np.stack([t1, t2], axis=1)  # (np, 2, 3)
        pab2 = np.stack([self.pa, self.pb])
        rAB = P - Xp[pab2]  # both sides stacked (2, np, 3)
        rtAB = cross(rAB[:, :, None, :], self.t)  # (2, np, 2, 3)
        ima, imb = topo.pima, topo.pimb
        self.rolling = rolling = bool(model.rolling)
        nr = 5 if rolling else 3  # tangent, tangent, twist (, roll, roll)
        self.Jt = np.zeros((npch, nr, 12))  # [JtA | JtB], as J above
        JtA, JtB = self.Jt[:, :, :6], self.Jt[:, :, 6:]
        JtA[:, :2, :3] = -self.t
        JtA[:, :2, 3:] = -rtAB[0]
        JtB[:, :2, :3] = self.t
        JtB[:, :2, 3:] = rtAB[1]
        JtA[:, 2, 3:] = -N
        JtB[:, 2, 3:] = N
        if rolling:
            JtA[:, 3:, 3:] = -self.t
            JtB[:, 3:, 3:] = self.t
        self.Mt = np.zeros((npch, nr, 12))
        MtA, MtB = self.Mt[:, :, :6], self.Mt[:, :, 6:]
        MtA[:, :, :3] = ima[:, None, None] * JtA[:, :, :3]
        MtB[:, :, :3] = imb[:, None, None] * JtB[:, :, :3]
        # both sides' angular responses in one einsum over the stacked sides
        Jt4 = self.Jt.reshape(npch, nr, 2, 2, 3)[:, :, :, 1].transpose(2, 0, 1, 3)  # (2, np, nr, 3) = [JtA, JtB][..., 3:]
        MtAB = np.einsum("skij,skmj->skmi", Iinv[pab2], Jt4)
        MtA[:, :, 3:] = MtAB[0]
        MtB[:, :, 3:] = MtAB[1]
        kt = np.einsum("kmi,kmi->km", JtA, MtA) + np.einsum("kmi,kmi->km", JtB, MtB)
        self.JtA, self.JtB, self.MtA, self.MtB = JtA, JtB, MtA, MtB
        self.mt = np.where(kt > 0, 1.0 / np.where(kt > 0, kt, 1.0), 0.0)
        self.lam_t = np.zeros((npch, nr))
        # pair coefficients are equal for all rows of a patch (and depend
        # only on the pair: kept in the topology)
        if topo.mus is None:
            topo.mus = c.mus[topo.pfirst]
            topo.muk = c.muk[topo.pfirst]
            topo.mur = c.mur[topo.pfirst] if rolling else None
        self.mus = topo.mus
        self.muk = topo.muk
        self.mur = topo.mur
        self.slip = np.zeros(npch, bool)
        self.mu = self.mus.copy()

    #: the last sweep's largest impulse change relative to the largest
    #: normal impulse, in the last iterate()
    residual = 0.0

    #: patches whose friction is held on its kinetic limit against a fixed
    #: direction, for :meth:`stop_times`: None, or (tangent mask (np,), unit
    #: slip directions (np, 2), rolling mask (np,) or None, unit rolling
    #: directions (np, 2) or None)
    pin = None

    def normal_matrix(self) -> np.ndarray:
        """K = J M^-1 J^T over the normal rows, (m, m) dense: rows i and j
        couple through every dynamic body they share (compiled,
        :func:`engine.contact.linalg.normal_matrix`)."""
        return linalg.normal_matrix(self.J, self.M, self.a, self.b, self.world)

    def sparse_normal_solve(self, r: np.ndarray, act: np.ndarray):
        """lambda over the rows ``act`` solving K_aa lambda = r_a
        (Tikhonov-regularised), exploiting that K couples each row only
        with the rows of its two bodies: (lambda (m,), ok)
        (:func:`engine.contact.linalg.spd_solve_sparse`)."""
        return linalg.spd_solve_sparse(self.J, self.M, self.a, self.b, self.world, r, act, 1e-10)

    def k_times(self, lam: np.ndarray) -> np.ndarray:
        """K lam (m,) without forming K."""
        return linalg.k_times(self.J, self.M, self.a, self.b, self.world, lam)

    def _lcp_residual(self, r, lam) -> float:
        """Complementarity residual of normal impulses ``lam`` for
        K lam >= r, lam >= 0: violated rows plus rows that push while
        separating."""
        return float(linalg.lcp_residual(self.k_times(lam) - r, lam))

    def direct_normal_guess(self, U) -> None:
        """Start Gauss-Seidel from a direct solution of the normal rows.

        The rows that are not separating (r = target - J U >= 0, with the
        warm friction impulses applied) are solved as equalities, K lambda = r
        (Tikhonov-regularised: for the consistent but singular systems of
        coplanar points it tends to the minimum-norm, symmetric share); in
        the dense case rows solved to pull (lambda < 0) are let go and the
        rest solved again (ACTIVE_SET_PASSES), then all are clipped at 0.  The load of a whole stack -- or of a heavy body on a
        light one -- is then in place from the first sweep, which
        Gauss-Seidel alone needs many sweeps (mass ratios: thousands) to
        transport, and indeterminate supports are not biased by the sweep
        order.  The guess is kept only if its complementarity residual
        beats the warm start's; Gauss-Seidel then settles complementarity
        and friction."""
        U0 = U.copy()
        if self.friction:
            self.apply_patch(U0, self.lam_t)
        r = self.target - (np.einsum("ki,ki->k", self.JA, U0[self.a]) + np.einsum("ki,ki->k", self.JB, U0[self.b]))
        # rows that are not separating (r >= 0, up to solver noise): resting
        # rows between bodies that fall together have r = 0 and must carry load
        act = np.flatnonzero(r > -RESTING_SPEED)
        if act.size == 0 or not np.any(r[act] > 0.0):
            return
        if self.m > DIRECT_MAX_ROWS:
            # sparse: a big scene's K couples each row only with the rows
            # of its two bodies (1000 spheres in 100 columns: ~1000 rows,
            # block diagonal), where the dense solve costs m^3; Gauss-Seidel
            # alone leaves the columns settling into one another
            # (tests/test_engine_collision.py::
            # test_sparse_direct_start_matches_the_dense_one)
            lam, ok = self.sparse_normal_solve(r, act)
            np.maximum(lam, 0.0, out=lam)
        else:
            # active set: rows the equality solve pulls on (lambda < 0) are
            # let go and the rest solved again, a few times; clipping alone
            # leaves the others short of the load those rows took, and an
            # offset can near its support's edge tips (the log-pile and
            # can-stack tests of tests/test_engine_collision.py)
            lam, ok, _ = dense_direct_solve(self.normal_matrix(), r, act, ACTIVE_SET_PASSES)
        if not ok or not np.all(np.isfinite(lam)):
            return
        if self._lcp_residual(r, lam) <= self._lcp_residual(r, self.lam_n):
            self.lam_n = lam

    def set_slip(self, slip: np.ndarray) -> None:
        self.slip = slip
        self.mu = np.where(slip, self.muk, self.mus)

    def sliding(self, U, vt: np.ndarray | None = None) -> np.ndarray:
        """(np,) bool: the patches that slide at velocities U (n+1, 6).  A
        patch slides when its centroid's relative tangential speed ``vt``
        (np, 2) m/s (computed from U unless given) exceeds ``SLIP_TOL``, or
        when it twists: |w_n| r_twist, the twist's speed at the patch's mean
        point distance, exceeds it.  A patch spinning in place slides at
        every point but its centroid, so it is kinetic friction (mu_k) that
        acts on it (classed by the centroid alone it kept mu_s: a capsule
        spinning on its side with mu_s = 2 mu_k stopped in half the time)."""
        if vt is None:
            vt = self.patch_tangent_velocity(U)
        wn = self.patch_velocity(U, slice(2, 3))[:, 0]
        return (np.sqrt(np.einsum("km,km->k", vt, vt)) > SLIP_TOL) | (np.abs(wn) * self.r_twist > SLIP_TOL)

    def patch_velocity(self, U, rows: slice) -> np.ndarray:
        """(np, k) relative velocities of the patch rows ``rows``: slice(0, 2)
        the tangential velocity at the centroids (m/s), slice(3, 5) the
        rolling angular velocity (rad/s)."""
        return (np.einsum("kmj,kj->km", self.JtA[:, rows], U[self.pa])
                + np.einsum("kmj,kj->km", self.JtB[:, rows], U[self.pb]))

    def patch_tangent_velocity(self, U) -> np.ndarray:
        """(np, 2) relative tangential velocity at the patch centroids."""
        return self.patch_velocity(U, slice(0, 2))

    # ---- velocities ---------------------------------------------------------
    @staticmethod
    def pack(V, W) -> np.ndarray:
        U = np.empty((V.shape[0], 6))
        U[:, :3] = V
        U[:, 3:] = W
        return U

    @staticmethod
    def unpack(U, V, W) -> None:
        V[:] = U[:, :3]
        W[:] = U[:, 3:]
        V[-1] = 0.0
        W[-1] = 0.0

    def apply_normal(self, U, d) -> None:
        """Add normal impulses d (m,) to U (np.add.at: bodies may repeat)."""
        sweeps.apply_rows(U, self.topo.ab, self.M, d, self.world)

    def apply_patch(self, U, d) -> None:
        """Add patch friction impulses d (np, 3) to U."""
        sweeps.apply_patches(U, self.topo.pab, self.Mt, d, self.world)

    def warm_start(self, U) -> None:
        if self.m:
            self.apply_normal(U, self.lam_n)
            if self.friction:
                self.apply_patch(U, self.lam_t)

    # ---- projected Gauss-Seidel (compiled: engine/contact/sweeps.py) --------
    _NO_F = np.zeros((0, 3, 12))
    _NO_P = np.zeros((0, 2), np.int64)

    def iterate(self, U, iterations: int, tol: float = 1e-7) -> int:
        """Sweeps of friction (patches) then normal rows, until no impulse
        changes by more than ``tol`` times the largest normal impulse in a
        sweep.  Returns the sweeps done."""
        if self.friction:
            npch = self.np
            pin = self.pin
            if pin is None:
                pin_t = pin_r = np.zeros(npch, np.bool_)
                dir_t = dir_r = np.zeros((npch, 2))
            else:
                pin_t, dir_t = pin[0], np.ascontiguousarray(pin[1])
                pin_r = pin[2] if pin[2] is not None else np.zeros(npch, np.bool_)
                dir_r = np.ascontiguousarray(pin[3]) if pin[3] is not None else np.zeros((npch, 2))
            mur = self.mur if self.mur is not None else np.zeros(npch)
            sw, self.residual = sweeps.iterate(
                U, self.topo.ab, self.J, self.M, self.mn, self.lam_n, self.target, True, self.topo.pab,
                self.pid, self.Jt, self.Mt, self.mt, self.lam_t, self.mu, self.r_twist, mur,
                pin_t, dir_t, pin_r, dir_r, iterations, tol, self.world)
        else:
            z = np.zeros(0)
            zb = np.zeros(0, np.bool_)
            sw, self.residual = sweeps.iterate(
                U, self.topo.ab, self.J, self.M, self.mn, self.lam_n, self.target, False, self._NO_P,
                np.zeros(0, np.int64), self._NO_F, self._NO_F, np.zeros((0, 3)), np.zeros((0, 3)), z, z, z,
                zb, np.zeros((0, 2)), zb, np.zeros((0, 2)), iterations, tol, self.world)
        return int(sw)

    def solve_friction_regimes(self, U, iterations: int) -> int:
        """Iterate with mu_s for sticking patches; a patch whose friction
        ends on its mu_s limit cannot stick: it switches to mu_k and the rows
        are iterated again (at most twice).  Returns the sweeps done."""
        sweeps = self.iterate(U, iterations)
        if not self.friction:
            return sweeps
        for _ in range(2):
            Fn = np.bincount(self.pid, self.lam_n, self.np)
            mag = np.sqrt(self.lam_t[:, 0] ** 2 + self.lam_t[:, 1] ** 2)
            # on the mu_s disc, or a twist on its mu_s limit (r_twist > 0:
            # a point contact has no twist row to saturate)
            lim = self.mus * Fn * (1 - 1e-6)
            sat = ~self.slip & (self.mus > self.muk) & (Fn > 0) & (
                (mag >= lim) | ((self.r_twist > 0.0) & (np.abs(self.lam_t[:, 2]) >= lim * self.r_twist)))
            if not sat.any():
                break
            self.set_slip(self.slip | sat)
            sweeps += self.iterate(U, iterations)
        return sweeps

    def stop_times(self, U, vt0, wr0, h: float, iterations: int) -> np.ndarray | None:
        """Times (s) within the step at which patches that slid (or rolled)
        at its start came to rest: (np,) with inf for the others, or None
        when no patch stopped.  ``U`` (n+1, 6) the solved end velocities,
        ``vt0`` (np, 2) m/s and ``wr0`` (np, 2) rad/s or None the patches'
        tangential and rolling velocities at the start of the step.

        A patch that slid at the start (|vt0| > SLIP_TOL) and ends the step
        at rest or turned round (its end slip along the initial direction
        below SLIP_TOL) came to rest somewhere inside the step.  The solve
        then either stuck it for the rest of the step, whatever the forces
        (a block thrown up a slope steeper than atan(mu_s) ends that step at
        rest and slides back late by the rest of it), or applied one
        friction direction to all of it (a ball rolling uphill against
        rolling resistance turns round resisted the wrong way before or
        after the turn): either way an error of first order in the step.
        Where inside the step: under constant forces
        and kinetic friction against the initial slip direction s, the slip
        velocity along s is linear in time, sigma(t) = sigma_0 + (sigma_h -
        sigma_0) t / h.  One more solve with those patches' friction held on
        the kinetic limit against s (everything else solved as before, so
        the coupling to the other rows is kept) gives sigma_h < 0, and the
        stop is at tau = h sigma_0 / (sigma_0 - sigma_h): exact for constant
        forces, second order otherwise.  Rolling rows alike, with the
        rolling angular velocity and the mu_r disc.  The impulses of the
        solve are left as they were."""
        Fn = np.bincount(self.pid, self.lam_n, self.np)
        live = Fn > 0.0
        s0 = np.sqrt(vt0[:, 0] ** 2 + vt0[:, 1] ** 2)
        tdir = vt0 / np.where(s0 > 0.0, s0, 1.0)[:, None]
        ends = {0: self.patch_velocity(U, slice(0, 2))}  # end velocities per row block
        # at rest at the end (stuck inside the disc) or already turned round
        # (on the limit, against the end motion)
        tc = live & (s0 > SLIP_TOL) & (np.einsum("km,km->k", ends[0], tdir) < SLIP_TOL)
        rc = r0 = rdir = None
        if self.rolling and wr0 is not None:
            r0 = np.sqrt(wr0[:, 0] ** 2 + wr0[:, 1] ** 2)
            rdir = wr0 / np.where(r0 > 0.0, r0, 1.0)[:, None]
            ends[3] = self.patch_velocity(U, slice(3, 5))
            rc = live & (self.mur > 0.0) & (r0 > ROLL_TOL) & (np.einsum("km,km->k", ends[3], rdir) < ROLL_TOL)
            if not rc.any():
                rc = rdir = None
        if rc is None and not tc.any():
            return None
        # (the candidates slid at the start, so their mu is already mu_k)
        saved = self.lam_n.copy(), self.lam_t.copy()
        U2 = U.copy()
        self.pin = (tc, tdir, rc, rdir)
        residual = self.residual
        try:
            self.iterate(U2, iterations)
            pinned_residual = self.residual
        finally:
            self.pin = None
            self.lam_n, self.lam_t = saved
            self.residual = residual
        if pinned_residual > STOP_MAX_RESIDUAL:
            return None
        tau = np.full(self.np, np.inf)
        for mask, rows, d, m0, lim_k, lim_s, tol in (
                (tc, slice(0, 2), tdir, s0, self.muk, self.mus, SLIP_TOL),
                (rc, slice(3, 5), rdir, r0, self.mur, self.mur, ROLL_TOL)):
            if mask is None or not mask.any():
                continue
            sig = np.einsum("km,km->k", self.patch_velocity(U2, rows), d)
            ok = mask & (sig < 0.0)
            f = m0 / np.where(ok, m0 - sig, 1.0)  # tau / h
            # A patch the solve left at rest whose rest needs no more than
            # the static limit: the impulse L it got is kinetic friction for
            # f h and a holding force F for the rest, L = -lim_k Fn f d +
            # F (1 - f) h; |F h| <= lim_s Fn means it stays at rest after the
            # stop, and the uncut step differs from the cut one only at
            # second order (where within the step the impulse acts).  The
            # cut matters where it turns round: the block on 35 degrees,
            # not a falling bar's end sticking a few per cent into a step
            # (cutting those -- 80 in one run -- set the bar's pivot
            # chattering)
            e = ends[rows.start]
            at_rest = np.sqrt(e[:, 0] ** 2 + e[:, 1] ** 2) < tol
            L = self.lam_t[:, rows] + (lim_k * Fn * np.where(ok, f, 0.0))[:, None] * d
            holds = at_rest & (np.sqrt(L[:, 0] ** 2 + L[:, 1] ** 2) <= lim_s * Fn * np.maximum(1.0 - f, 0.0))
            ok &= ~holds
            tau = np.where(ok, np.minimum(tau, h * f), tau)
        return tau

    def iterate_normal(self, U, lam, target, iterations: int, tol: float = 1e-7) -> None:
        """Normal rows only, with their own accumulator (split impulse)."""
        sweeps.iterate_normal(U, self.topo.ab, self.J, self.M, self.mn, lam, target, iterations, tol, self.world)


def _pair_codes(model, c: Contacts) -> np.ndarray:
    return _pair_codes_abs(model, c.a, c.b, c.sidx)


def _pair_codes_abs(model, a, b, sidx) -> np.ndarray:
    """Warm-cache key of the pairs (a, b, static index): unique per pair."""
    return (a * (model.n + 1) + b) * (model.n_statics + 1) + (sidx + 1)


#: topologies a Solve stage keeps (the contact graphs of the last steps and
#: of the time-of-impact re-runs); cleared when full
TOPOLOGY_CACHE = 8


class Solve(Stage):
    """Sequential-impulse contact solve on the end-of-step velocities (see
    module doc).  Classifies contacts (touching, speculative, impact),
    leaves impacts to the CCD stage in ``ctx.impacts`` (row indices, time
    estimates), solves the rest with warm starting, then the split-impulse
    position correction."""

    name = "solve"
    family = "solver"

    def __init__(self, model):
        s = model.settings
        self.iterations = int(s["iterations"])
        self.correction = s["position_correction"]
        self.warm = bool(s["warm_starting"])
        self.thr = float(s["restitution_threshold"])
        self.ccd = s["ccd"]
        self.ccd_fraction = float(s["ccd_motion_fraction"])
        self.beta = float(s["correction_beta"])
        self.slop = float(s["correction_slop"])
        self.friction = model.has("friction")
        self.c = model.contact_lever
        self.direct = bool(s["direct_start"])
        self.stops = bool(s["friction_stops"])
        self._topos: dict[bytes, Topology] = {}

    def topology(self, model, codes: np.ndarray, c: Contacts, sel: np.ndarray) -> Topology:
        """The (cached) topology of the rows ``sel`` of ``c`` with pair codes
        ``codes`` (which identify (a, b, sidx) row by row)."""
        key = codes.tobytes()
        topo = self._topos.get(key)
        if topo is None:
            if len(self._topos) >= TOPOLOGY_CACHE:
                self._topos.clear()
            topo = self._topos[key] = Topology(model, c.a[sel], c.b[sel], c.sidx[sel], self.friction, True)
        return topo

    def __call__(self, model, state, ctx) -> None:
        n = model.n
        h = ctx.h
        c = ctx.contacts
        ctx.rows = None
        ctx.impacts = None
        if c is None or c.m == 0:
            state.warm = None
            return
        Xp = _pad(state.x)
        rA = c.point - Xp[c.a]
        rB = c.point - Xp[c.b]
        # normal velocities at the end of the free flight, at the start of
        # the step and of the mean motion, in one pass (the arithmetic of
        # point_normal_velocity on the three stacked velocity fields)
        VV = np.zeros((3, n + 1, 3))
        WW = np.zeros((3, n + 1, 3))
        VV[0], WW[0] = ctx.v, ctx.w
        VV[1, :n], WW[1, :n] = state.v, state.w
        VV[2, :n], WW[2, :n] = ctx.u_lin, ctx.u_ang
        rel = VV[:, c.b] + cross(WW[:, c.b], rB) - VV[:, c.a] - cross(WW[:, c.a], rA)
        m = c.m
        vn3 = np.einsum("ki,ki->k", rel.reshape(3 * m, 3), np.concatenate([c.normal, c.normal, c.normal]))
        vn_free, vn0, un = vn3[:m], vn3[m:2 * m], vn3[2 * m:]
        gap = c.gap
        touching = gap <= TOUCH_TOL
        closes = gap + h * un < 0.0
        impact = ~touching & closes & (-un > self.thr)
        codes_all = _pair_codes(model, c)
        if state.warm:
            impact |= touching & (-vn0 > self.thr) & (self.c * h * vn_free - gap - h * un > self.slop)
        if impact.any() and state.warm:
            # In a pair that pressed last step (a persistent, resting
            # contact), closing rows are mostly solver noise and gravity
            # gained within the step, not impacts: they stay speculative rows
            # -- unless the point itself did not press (no cached point of the
            # pair with a positive force within the warm start's matching
            # radius, in body a's frame), it was already approaching faster
            # than the threshold at the start of the step, and a speculative
            # row could not stop it without sinking beyond the slop.  That is
            # the far end of a bar resting on one end and rotating down onto
            # the slab (as a speculative row, stopped over the whole step, it
            # sank 4.9 mm into a 4 mm slab at 2.3 m/s and 1/240 s); not the
            # idle rim points of a cylinder standing on its cap (gravity
            # alone gives them -un = g h / 2 > the threshold every step), nor
            # the rattling corners of a box column solved by Gauss-Seidel
            # alone (as impact events, resolved pair by pair inside the
            # stack, they pumped energy into it: 275 x at dt 0.008 s).
            idx = np.flatnonzero(impact)
            o_code, _, o_fn = state.warm.packed[:3]
            persistent = np.isin(codes_all[idx], o_code[o_fn > 0.0])
            # as a speculative row stopped at vn1 = 0 (never a push-out), the
            # point would end the step overlapping by c h vn_free - gap - h un
            # (the lever c of the position update): an impact only where that
            # exceeds the position correction's slop
            sinks = self.c * h * vn_free[idx] - gap[idx] - h * un[idx] > self.slop
            cand = persistent & sinks & (-vn0[idx] > self.thr)
            if cand.any():
                loc = self._local(ctx, c.a[idx[cand]], c.point[idx[cand]], state)
                tol = 0.1 * model.bound_radius[c.a[idx[cand]]] + 1e-4
                cand[cand] = ~_pressed_points(state.warm, codes_all[idx[cand]], loc, tol)
            impact[idx[persistent & ~cand]] = False
        if ctx.event_mode == "drop" and ctx.drop_rows is not None:
            # a rerun of the time-of-impact search: the rows left out are
            # the step's impact rows, whatever tau.  Re-deciding them with
            # the rerun's length kept a row whose linear estimate fell after
            # tau (its point curving in earlier) as a speculative row, which
            # held the point just clear: the gap was a plateau near 0 that
            # jumped below 0 at the estimate, Newton crawled on it and
            # bisection converged on the jump (30 iterations, each a rerun
            # of the whole step)
            impact = np.zeros(c.m, bool)
            impact[ctx.drop_rows] = True
        keep = ~impact
        if impact.any():
            if self.ccd == "toi":
                fast = np.zeros(n + 1, bool)
                fast[:n] = ctx.sweep > self.ccd_fraction * model.min_extent
                handled = impact & (fast[c.a] | fast[c.b])
            elif self.ccd == "events":
                handled = impact
            else:
                handled = np.zeros_like(impact)
            if ctx.event_mode == "event" and handled.any():
                idx = np.flatnonzero(handled)
                ctx.impacts = (idx, gap[idx] / np.maximum(-un[idx], 1e-300))
            elif ctx.event_mode == "speculative":
                keep = keep | handled
            # impacts nobody resolves at their time of impact are left to
            # penetrate and bounce next step (discrete behaviour); touching
            # ones stay rows, with their restitution target, as before
            # touching points could be impacts (dropping them let slow
            # spheres sink into each other with ccd = "toi")
            keep = keep | (impact & touching & ~handled)
        sel = np.flatnonzero(keep)
        if sel.size == 0:
            state.warm = None
            return
        topo = self.topology(model, codes_all[sel], c, sel)
        rows = Rows(model, state.x, ctx.Iinv0, c, self.friction, sel=sel, topo=topo)
        sel = sel[rows.order]  # rows are sorted by colour
        cs = rows.contacts
        # touching rows: v1n >= 0 (memoryless: a target that depends on the
        # previous step's velocity feeds solver noise back into the stack);
        # separated rows: the end pose may just close the gap
        spec = np.where(touching[sel], 0.0,
                        np.minimum(vn_free[sel] - (np.maximum(gap[sel], 0.0) + h * un[sel]) / (self.c * h), 0.0))
        bounce = touching[sel] & (vn0[sel] < -self.thr)
        target = np.maximum(spec, np.where(bounce, -cs.e * vn0[sel], -np.inf))
        depth = -gap[sel]
        rows.target = target
        if self.friction:
            U0 = Rows.pack(VV[1], WW[1])
            vt0 = rows.patch_tangent_velocity(U0)
            rows.set_slip(rows.sliding(U0, vt0))
        U = Rows.pack(ctx.v, ctx.w)
        # contact points in body a's frame: the warm cache's matching key
        loc = self._local(ctx, cs.a, cs.point, state)
        if self.warm:
            self._warm_start(model, state, ctx, rows, cs, loc, h)
        if self.direct:
            rows.direct_normal_guess(U)
        if self.warm or self.direct:
            rows.warm_start(U)
        sweeps = rows.solve_friction_regimes(U, self.iterations)
        # (only from a solve that (nearly) converged: the end velocities of
        # one cut short far from convergence are solver noise, and a
        # Gauss-Seidel-only column with 5 sweeps "stopped" 422 times in 5 s
        # and gained 20 % energy)
        if (self.friction and ctx.stop_allowed and self.stops and rows.residual <= STOP_MAX_RESIDUAL
                and (rows.slip.any() or rows.rolling)):
            wr0 = rows.patch_velocity(U0, slice(3, 5)) if rows.rolling else None
            tau = rows.stop_times(U, vt0, wr0, h, self.iterations)
            if tau is not None:
                t = float(tau.min())
                if t < h * (1.0 - STOP_MIN_REST):
                    ctx.stop = t
        Rows.unpack(U, ctx.v, ctx.w)
        if self.correction != "none":
            # push-out velocities for penetration beyond the slop, solved on
            # separate (pseudo) velocities; they move positions by h vp.
            # split_impulse discards them afterwards; baumgarte keeps them in
            # the real velocity too (the classic bias: it injects energy)
            bias = np.where(depth > self.slop, self.beta * (depth - self.slop) / h, 0.0)
            if (bias > 0).any():
                lam = np.zeros(rows.m)
                Up = Rows.pack(ctx.vp, ctx.wp)
                rows.iterate_normal(Up, lam, bias, self.iterations)
                Rows.unpack(Up, ctx.vp, ctx.wp)
                if self.correction == "baumgarte":
                    ctx.v += ctx.vp
                    ctx.w += ctx.wp
                    ctx.v_free += ctx.vp[:n]  # not a contact impulse for the position update: h vp moves it
                    ctx.w_free += ctx.wp[:n]
        ctx.rows = rows
        if h >= WARM_MIN_STEP * model.h:
            self._store(model, state, ctx, rows, loc, h, touching[sel])
        else:
            # a sliver of a step (the rest of a step after a late time of
            # impact): its impulses are impulsive, not forces -- cached as
            # lambda / h they came back next step as a huge impulse (a box
            # of column_5 spun up to 5e5 rad/s after a 7e-12 s remainder)
            state.warm = None
        ctx.profile.count("contact_rows", rows.m)
        ctx.profile.count("solver_sweeps", sweeps)

    # ---- warm starting ----------------------------------------------------
    def _local(self, ctx, a, p, state):
        """Contact points in body a's frame (matching key for warm starts)."""
        return np.einsum("kji,kj->ki", ctx.R0[a], p - state.x[a])

    def _warm_start(self, model, state, ctx, rows, cs, loc, h):
        """Each row takes the cached force of the nearest cached point of its
        pair (in body a's frame) within 0.1 bounding radius + 0.1 mm; a
        patch with a matched point takes its pair's cached friction force
        and twist.  Vectorised over rows (the cache is packed, see
        :class:`WarmCache`); the (row, cached point) candidates depend only
        on the two steps' contact graphs and are kept in the topology while
        both are unchanged."""
        old = state.warm
        if not old:
            return
        topo = rows.topo
        o_code, o_loc, o_fn, u_code, u_ft, u_tw, u_rr = old.packed[:7]
        otopo = old.topo
        cand = topo.__dict__.get("_warm_cand")
        if cand is None or otopo is None or cand[0]() is not otopo:
            codes = topo.codes
            lo = np.searchsorted(o_code, codes, "left")
            cnt = np.searchsorted(o_code, codes, "right") - lo
            has = np.flatnonzero(cnt > 0)
            if has.size == 0:
                return
            c = cnt[has]
            tot = int(c.sum())
            starts = np.cumsum(c) - c
            R = np.repeat(has, c)  # (row, cached point) candidates, grouped by row
            J = np.repeat(lo[has], c) + (np.arange(tot) - np.repeat(starts, c))
            tol = 0.1 * model.bound_radius[cs.a] + 1e-4
            # (weak: a topology must not keep its predecessors alive)
            cand = (weakref.ref(otopo) if otopo is not None else (lambda: None), has, c, starts, R, J, tol[has] ** 2)
            topo.__dict__["_warm_cand"] = cand
        _, has, c, starts, R, J, tol2 = cand
        if has.size == 0:
            return
        d = loc[R] - o_loc[J]
        d2 = np.einsum("ki,ki->k", d, d)
        # nearest cached point per row, first on ties (like argmin)
        mn = np.minimum.reduceat(d2, starts)
        hit = np.flatnonzero(d2 == np.repeat(mn, c))
        _, fi = np.unique(R[hit], return_index=True)
        jbest = J[hit[fi]]
        ok = mn <= tol2
        r = has[ok]
        rows.lam_n[r] = o_fn[jbest[ok]] * h
        if rows.friction and r.size:
            # one patch per pair: its first row's patch, for pairs with a match
            rc = topo.codes[r]
            uc = topo.uniq_codes
            sel = np.isin(uc, rc)
            p = topo.uniq_pid[sel]
            g = np.searchsorted(u_code, uc[sel])
            rows.lam_t[p, :2] = np.einsum("kij,kj->ki", rows.t[p], u_ft[g]) * h
            rows.lam_t[p, 2] = u_tw[g] * h
            if rows.rolling and u_rr is not None:
                rows.lam_t[p, 3:] = np.einsum("kij,kj->ki", rows.t[p], u_rr[g]) * h

    def _store(self, model, state, ctx, rows, loc, h, touch):
        """Cache the step's forces for the next step's warm start (``touch``
        (m,) bool: the rows that were touching at the start of the step --
        a point pressed *at rest* only if it was; a speculative row that
        pressed to land its point exactly on the surface did not rest)."""
        topo = rows.topo
        fn = rows.lam_n / h
        order = topo.code_order
        sc = topo.sorted_codes
        first = topo.code_first
        uniq = topo.uniq_codes
        if rows.friction:
            p = topo.uniq_pid
            lt = rows.lam_t[p]
            tp = rows.t[p]
            ft = np.einsum("ki,kij->kj", lt[:, :2], tp) / h
            tw = lt[:, 2] / h
            rr = np.einsum("ki,kij->kj", lt[:, 3:], tp) / h if rows.rolling else None
        else:
            ft, tw, rr = np.zeros((uniq.size, 3)), np.zeros(uniq.size), None
        state.warm = WarmCache(sc, loc[order], fn[order], uniq, ft, tw, rr, touch[order], first, topo)


@dataclass(eq=False)
class WarmCache:
    """The warm-start cache a solve leaves for the next step, as arrays
    sorted by pair code: ``codes`` (k,) the pair code of each cached point,
    ``loc`` (k, 3) m its point in body a's frame, ``fn`` (k,) N its normal
    force, ``pairs`` (p,) the distinct pair codes, ``ft`` (p, 3) N their
    friction forces, ``tw`` (p,) N m twist torques, ``rr`` (p, 3) N m
    rolling torques or None, ``touch`` (k,) bool whether the point touched
    at the start of its step; ``first`` (p,) each pair's first point and
    ``topo`` the topology that wrote it."""

    codes: np.ndarray
    loc: np.ndarray
    fn: np.ndarray
    pairs: np.ndarray
    ft: np.ndarray
    tw: np.ndarray
    rr: np.ndarray | None
    touch: np.ndarray
    first: np.ndarray
    topo: Topology

    @property
    def packed(self) -> tuple:
        return (self.codes, self.loc, self.fn, self.pairs, self.ft, self.tw, self.rr, self.touch)


def _pressed_points(warm: "WarmCache", codes: np.ndarray, loc: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """(k,) bool: contact points (pair ``codes`` (k,), points in body a's
    frame ``loc`` (k, 3) m) that pressed at rest in the step that wrote
    ``warm``: a cached point of the same pair that was touching at the start
    of that step and carried a positive normal force lies within ``tol``
    (k,) m of them (the warm start's matching radius).  A speculative row
    that pressed only to land its point exactly on the surface does not
    count: that point arrives still approaching, an impact."""
    pk = warm.packed
    o_code, o_loc, o_fn = pk[0], pk[1], np.where(pk[7], pk[2], 0.0)
    out = np.zeros(codes.size, bool)
    lo = np.searchsorted(o_code, codes, "left")
    hi = np.searchsorted(o_code, codes, "right")
    for i in np.flatnonzero(hi > lo).tolist():  # impact candidates: a few rows
        sl = slice(lo[i], hi[i])
        d = o_loc[sl] - loc[i]
        out[i] = bool(np.any((o_fn[sl] > 0.0) & (np.einsum("ki,ki->k", d, d) <= tol[i] ** 2)))
    return out


def _pair_block(rows: Rows, idx: np.ndarray) -> tuple:
    """(a, b, JA, JB, MA, MB, K) of the normal rows ``idx`` of one pair,
    gathered once per Rows (the impact solver resolves a pair many times)."""
    cache = rows.__dict__.setdefault("_pair_blocks", {})
    key = idx.tobytes()
    out = cache.get(key)
    if out is None:
        JA, JB, MA, MB = rows.JA[idx], rows.JB[idx], rows.MA[idx], rows.MB[idx]
        out = (rows.a[idx[0]], rows.b[idx[0]], JA, JB, MA, MB,
               np.einsum("ik,jk->ij", JA, MA) + np.einsum("ik,jk->ij", JB, MB))
        cache[key] = out
    return out


def _patch_block(rows: Rows, p: int) -> tuple:
    """(a, b, JA, JB, MA, MB, K^-1 or None when K is singular, (mu_s, mu_k,
    r_twist, mu_r)) of friction patch ``p`` (cached per Rows: the impact
    solver resolves a pair many times, and the 3x3 (with rolling friction
    5x5) block is inverted once)."""
    cache = rows.__dict__.setdefault("_patch_blocks", {})
    out = cache.get(p)
    if out is None:
        JA, JB, MA, MB = rows.JtA[p], rows.JtB[p], rows.MtA[p], rows.MtB[p]
        K = np.einsum("ik,jk->ij", JA, MA) + np.einsum("ik,jk->ij", JB, MB)
        Kinv, ok = linalg.inverse(K)
        if not ok:
            Kinv = None
        out = (int(rows.pa[p]), int(rows.pb[p]), JA, JB, MA.T.copy(), MB.T.copy(), Kinv,
               (float(rows.mus[p]), float(rows.muk[p]), float(rows.r_twist[p]),
                float(rows.mur[p]) if rows.rolling else 0.0))
        cache[p] = out
    return out


def _block_normal(rows: Rows, U: np.ndarray, idx: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Exact normal impulses for the rows ``idx`` of ONE pair (k <= ~8):
    the linear complementarity problem  lambda >= 0,  K lambda >= r,
    lambda . (K lambda - r) = 0  with K = J M^-1 J^T and r = target - vn,
    solved by enumerating active sets (largest first; K may be singular, e.g.
    four coplanar points).  Applies the impulses to U and returns them."""
    from itertools import combinations

    a, b, JA, JB, MA, MB, K = _pair_block(rows, idx)
    r = target - (np.einsum("kj,j->k", JA, U[a]) + np.einsum("kj,j->k", JB, U[b]))
    k = idx.size
    lam = np.zeros(k)
    if k == 1:
        # one row (the common case: sphere contacts): the only active set is
        # {0}, lambda = r / K -- the same tests as the enumeration below
        K00, r0 = float(K[0, 0]), float(r[0])
        if r0 <= 0.0:
            return lam
        if abs(K00) >= 1e-12 * max(1.0, abs(K00)):
            l0 = r0 / K00
            if l0 >= 0.0 and K00 * l0 - r0 >= -1e-9 * abs(r0):
                lam[0] = l0
                U[a] += MA[0] * l0
                U[b] += MB[0] * l0
                U[-1] = 0.0
                return lam
    if np.all(r <= 0.0):
        return lam
    scale = float(np.max(np.abs(r)))
    found = False
    for size in range(k, 0, -1):
        for S in combinations(range(k), size):
            S = list(S)
            KS = K[np.ix_(S, S)]
            lS, det = linalg.lu_solve(KS, r[S])
            if abs(det) < 1e-12 * max(1.0, float(np.max(np.abs(KS)))) ** size:
                continue
            if np.any(lS < 0.0):
                continue
            trial = np.zeros(k)
            trial[S] = lS
            if np.all(np.einsum("ij,j->i", K, trial) - r >= -1e-9 * scale):
                lam = trial
                found = True
                break
        if found:
            break
    if not found:  # degenerate: fall back to projected Gauss-Seidel on the block
        for _ in range(200):
            for i in range(k):
                lam[i] = max(0.0, lam[i] + (r[i] - np.einsum("j,j->", K[i], lam)) / K[i, i])
    U[a] += np.einsum("kj,k->j", MA, lam)
    U[b] += np.einsum("kj,k->j", MB, lam)
    U[-1] = 0.0
    return lam


def _patch_impulse(rows: Rows, U: np.ndarray, p: int, Fn: float) -> None:
    """One-shot Coulomb friction impulse on patch ``p`` after a normal
    impulse of total ``Fn``: the impulse that stops the tangential and twist
    (and rolling) motion (exact block, by its inverse computed once per
    patch), kept if within the static limits -- mu_s for a patch at rest,
    mu_k for one that slides or twists (``Rows.sliding``: it slides until it
    stops, so kinetic friction is what has to stop it) -- else its force
    scaled onto the mu_k disc and its twist clipped to mu_k Fn r_twist; the
    rolling torque impulse is limited to the mu_r Fn disc."""
    if Fn <= 0.0:
        return
    a, b, JA, JB, MAT, MBT, Kinv, (mus, muk, rt, mur) = _patch_block(rows, p)
    vt = np.einsum("kj,j->k", JA, U[a]) + np.einsum("kj,j->k", JB, U[b])
    if Kinv is not None:
        d = -np.einsum("ij,j->i", Kinv, vt)
    else:
        d = -vt * rows.mt[p]
    # the patch sticks if both the force and the twist that stop it lie
    # within the limits; else it slides at every point: both are held to
    # the kinetic ones
    mu = muk if (math.hypot(vt[0], vt[1]) > SLIP_TOL or abs(vt[2]) * rt > SLIP_TOL) else mus
    mag = math.hypot(d[0], d[1])
    if mag > mu * Fn or (rt > 0.0 and abs(d[2]) > mu * Fn * rt):
        if mag > muk * Fn:
            d[:2] *= muk * Fn / mag
        tl = muk * Fn * rt
        d[2] = min(max(d[2], -tl), tl)
    if d.size > 3:
        rmag = math.hypot(d[3], d[4])
        if rmag > mur * Fn:
            d[3:] *= mur * Fn / rmag
    U[a] += np.einsum("jk,k->j", MAT, d)
    U[b] += np.einsum("jk,k->j", MBT, d)
    U[-1] = 0.0


def impact_solve(model, state, contacts: Contacts, iterations: int, thr: float, friction: bool,
                 plastic: str = "simultaneous") -> int:
    """Impulsive collision response at a time of impact, on the state's
    velocities, over the touching contacts (gap <= 10 TOUCH_TOL).  Returns
    the number of rows.

    The touching pairs split into islands (bodies joined by touching
    contacts; the world joins nothing).  Islands are independent, and each
    is resolved by one of two laws:

    * an island with restitution anywhere in it, or with one pair only:
      impulse propagation, binary collisions one after another
      (:func:`_propagate`) -- a striker hitting a row of touching balls
      hands its momentum down the row (Newton's cradle);
    * with ``plastic = "simultaneous"`` (the default), an island of two or
      more pairs, all with e = 0: one simultaneous plastic impact, Moreau's
      law (:func:`_plastic_island_solve`): the post-impact velocity is the
      one nearest the pre-impact velocity in the kinetic-energy metric that
      approaches at no contact (the LCP lambda >= 0, J u+ >= 0,
      lambda . J u+ = 0), with Coulomb friction; it does not depend on an
      order of the pairs.  Propagation gives the same for a column landing
      on the floor (everything stops), but only in the limit: with no
      rebound to hand on, the pairs push one another back and forth and
      the approach decays geometrically -- about 20 pair solves per contact
      in a column of 10 spheres; a layer landing on 100 such columns cost
      0.2-1 s of CPU per impact (spheres_1000), and some did not settle
      within the propagation's budget.  ``"sequential"`` propagates these
      islands too.
    """
    from engine.mathutil import quat_to_matrix, world_inv_inertia

    sel = np.flatnonzero(contacts.gap <= 10 * TOUCH_TOL)
    if sel.size == 0:
        return 0
    cs = contacts.take(sel)
    n = model.n
    R = quat_to_matrix(state.q)
    Iinv = np.zeros((n + 1, 3, 3))
    Iinv[:n] = world_inv_inertia(R, model.inv_inertia_body[:n])
    U = Rows.pack(_pad(state.v), _pad(state.w))
    # (every row bouncing, the common case of billiards: no plastic island)
    together = _plastic_islands(model, cs) if plastic == "simultaneous" and not np.all(cs.e > 0.0) else None
    m = 0
    if together is None or not together.any():
        m += _propagate(model, state.x, Iinv, cs, U, iterations, thr, friction)
    else:
        m += _plastic_island_solve(model, state.x, Iinv, cs.take(np.flatnonzero(together)), U, iterations,
                                   friction)
        if not together.all():
            m += _propagate(model, state.x, Iinv, cs.take(np.flatnonzero(~together)), U, iterations, thr,
                            friction)
    state.v[:] = U[:n, :3]
    state.w[:] = U[:n, 3:]
    return m


def _plastic_islands(model, cs: Contacts) -> np.ndarray:
    """(m,) bool: the rows of ``cs`` in islands of two or more pairs whose
    rows all have e = 0 (see :func:`impact_solve`)."""
    code = _pair_codes(model, cs)
    if np.all(code == code[0]):  # one pair (a single landing): nothing to join
        return np.zeros(cs.m, bool)
    n = model.n
    dyn = cs.b < n  # a is always a body; b may be the world
    lab, k = linalg.islands(n, cs.a[dyn], cs.b[dyn])
    isl = lab[cs.a]
    bouncy = np.bincount(isl, cs.e > 0.0, k) > 0
    _, first = np.unique(code, return_index=True)
    pairs = np.bincount(isl[first], minlength=k)
    ok = ~bouncy & (pairs >= 2)
    return ok[isl]


def _plastic_island_solve(model, X, Iinv, cs: Contacts, U: np.ndarray, iterations: int, friction: bool) -> int:
    """Simultaneous plastic impact of the contacts ``cs`` (Moreau's law, see
    :func:`impact_solve`) on U (n+1, 6) in place: target vn+ >= 0 on every
    row, started from the direct solution of the rows that do not separate
    (exact when all of them end pressed, as in a column that lands, where a
    Gauss-Seidel sweep moves an impulse only one contact down), then
    projected Gauss-Seidel with Coulomb friction (mu_k for patches sliding
    at the impact, mu_s for the others, switching where the static limit is
    reached).  Returns the number of rows."""
    rows = Rows(model, X, Iinv, cs, friction)
    if friction:
        rows.set_slip(rows.sliding(U))
    rows.direct_normal_guess(U)
    rows.warm_start(U)
    rows.solve_friction_regimes(U, iterations)
    return rows.m


def _propagate(model, X, Iinv, cs: Contacts, U: np.ndarray, iterations: int, thr: float, friction: bool) -> int:
    """Impulse propagation over the contacts ``cs`` on U (n+1, 6) in place:
    repeatedly take the touching pair that approaches fastest (normal speed
    above ``thr``), give it the exact pair impulse (block solve of its
    points) with the restitution target vn+ = -e vn- and a Coulomb friction
    impulse, until no touching pair approaches faster than ``thr``; then
    stop the slow approaches (vn+ >= 0).  Binary collisions one after
    another: a striker hitting a row of touching balls hands its momentum
    down the row (Newton's cradle) and symmetric contacts get symmetric
    impulses.  If the propagation does not settle (pinned ping-pong), the
    remaining approaches are resolved together by sequential impulses.
    Returns the number of rows."""
    n = model.n
    rows = Rows(model, X, Iinv, cs, friction, colour=False)
    cs = rows.contacts
    code = _pair_codes(model, cs)
    uniq, inv = np.unique(code, return_inverse=True)
    # rows of each pair (ascending), and of each body
    go = np.argsort(inv, kind="stable")
    groups = np.split(go, np.cumsum(np.bincount(inv, minlength=uniq.size))[:-1])
    e = cs.e
    ra, rb = rows.a, rows.b
    ab_rows = np.concatenate([ra, rb])
    bo = np.argsort(ab_rows, kind="stable")
    body_rows = np.split(bo % rows.m, np.cumsum(np.bincount(ab_rows, minlength=n + 1))[:-1])
    affected: dict[int, tuple] = {}
    group_sub: dict[int, tuple] = {}

    ab = rows.topo.ab

    def vn_all():
        # [JA | JB] . [U[a] | U[b]] per row: one gather, one reduction
        return np.einsum("kj,kj->k", rows.J, U[ab].reshape(-1, 12))

    def vn_sub(sub):
        # the same per-row arithmetic as vn_all, on a subset of the rows
        # gathered once: sub = (J, ab) of those rows
        Js, ABs = sub
        return np.einsum("kj,kj->k", Js, U[ABs].reshape(-1, 12))

    # normal velocities of all rows, kept current: a pair's impulses change
    # only the rows of its two bodies
    vcur = vn_all()

    def resolve(g, restitution: bool):
        idx = groups[g]
        v = vcur[idx]
        tgt = np.where(v < -thr, -e[idx] * v, 0.0) if restitution else np.zeros(idx.size)
        lam = _block_normal(rows, U, idx, tgt)
        if friction and lam.sum() > 0:
            _patch_impulse(rows, U, int(rows.pid[idx[0]]), float(lam.sum()))
            # friction may have changed the normal velocities: keep them >= 0
            gs = group_sub.get(g)
            if gs is None:
                gs = group_sub[g] = (rows.J[idx], ab[idx])
            v2 = vn_sub(gs)
            if np.any(v2 < np.minimum(tgt, 0.0) - 1e-12):
                _block_normal(rows, U, idx, np.maximum(np.minimum(tgt, 0.0), v2 * 0.0))
        entry = affected.get(g)
        if entry is None:
            i, j = int(ra[idx[0]]), int(rb[idx[0]])
            aff = np.unique(np.concatenate([body_rows[i]] + ([body_rows[j]] if j != n else [])))
            entry = (aff, (rows.J[aff], ab[aff]))
            affected[g] = entry
        vcur[entry[0]] = vn_sub(entry[1])

    settled = False
    for _ in range(20 * len(groups) + 10):
        j = int(np.argmin(vcur))
        if vcur[j] >= -thr:
            settled = True
            break
        resolve(int(inv[j]), True)
    if not settled:
        # pinned configuration: resolve all approaches together
        v = vn_all()
        rows.target = np.where(v < -thr, -e * v, 0.0)
        rows_c = Rows(model, X, Iinv, cs, friction)
        rows_c.target = rows.target[rows_c.order]
        rows_c.solve_friction_regimes(U, iterations)
        vcur[:] = vn_all()
    for _ in range(3):  # slow approaches stop (plastic)
        slow = np.unique(inv[vcur < -1e-12])
        if slow.size == 0:
            break
        for g in slow.tolist():
            resolve(g, False)
    return rows.m
