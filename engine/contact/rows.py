"""Contact rows (the prepare phase's Python side): the rows of a set of
contacts at a pose, their friction patches, and their solve.

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

Gauss-Seidel: rows are coloured greedily so that no dynamic body appears
twice in a colour and visited colour by colour (engine/contact/gauss_seidel.py);
deterministic (fixed order).

Everything that depends only on the contact graph -- which bodies the rows
join, in which order: the colouring, the friction patches, the pair
grouping of the warm cache, the pair coefficients -- is a
:class:`Topology`, built once per distinct graph and reused while it is
unchanged (a resting stack: every step), so a step only redoes the
pose-dependent arithmetic (compiled: engine/contact/prepare.py).
"""

from __future__ import annotations

import numpy as np

from physbench.engine.contact import gauss_seidel, linalg, prepare
from physbench.engine.contact.packs import Bodies, ContactArrays, NormalRows, Patches, PatchSet, RowArrays
from physbench.engine.contact.scratch import Scratch
from physbench.engine.contact.topology import (  # noqa: F401  (the names rows.py had before the split)
    Topology,
    _greedy_colours,
    _pair_codes,
    _pair_codes_abs,
    colour_order,
)
from physbench.engine.mathutil import cross
from physbench.engine.state import Contacts

TOUCH_TOL = 1e-6  # m: a contact whose gap is below this is touching
DIRECT_MAX_ROWS = 400  # rows up to which the direct start is a dense LU solve; above, sparse (banded Cholesky per island)
#: re-solves of the dense direct start with the rows it pulls on let go
ACTIVE_SET_PASSES = 4
RESTING_SPEED = 1e-5  # m/s: rows separating slower than this count as resting in the direct start
SLIP_TOL = 1e-4  # m/s: relative tangential speed above which a contact slides (twist: at r_twist)
ROLL_TOL = 1e-4  # rad/s: relative rolling angular speed above which a contact rolls (rolling friction)
STOP_MAX_RESIDUAL = 1e-4  # friction stops only from a solve whose last sweep changed impulses by less (relative)


def dense_direct_solve(K: np.ndarray, r: np.ndarray, act: np.ndarray, passes: int):
    """The dense direct start's active-set solves (compiled,
    :func:`engine.contact.linalg.dense_active_set`, Tikhonov ``linalg.EPS_REL`` of the
    largest diagonal): (lambda (m,) >= 0, ok, whether the last pass still
    pulled on a row and was clipped)."""
    return linalg.dense_active_set(K, r, act, linalg.EPS_REL, passes)


def _pad(a: np.ndarray) -> np.ndarray:
    """(n, 3) -> (n+1, 3) with a zero world row."""
    out = np.zeros((a.shape[0] + 1, 3))
    out[:-1] = a
    return out


_NO_R = np.zeros((0, 3, 3))
_NO_I = np.zeros(0, np.int64)
_NO_D = np.zeros(0)
_NO_B = np.zeros(0, np.bool_)
_NO_P3 = np.zeros((0, 3))
_NO_T = np.zeros((0, 2, 3))
_NO_J = np.zeros((0, 3, 12))
def point_normal_velocity(V, W, a, b, rA, rB, n):
    """n . (vb + wb x rB - va - wa x rA) for padded (n+1, 3) V, W."""
    rel = V[b] + cross(W[b], rB) - V[a] - cross(W[a], rA)
    return np.einsum("ki,ki->k", rel, n), rel


def _take_rows(sc: Scratch, m: int, npch: int, nr: int, friction: bool) -> tuple:
    """The work arrays of ``m`` normal rows (J, M (m, 12), mn (m,), loc
    (m, 3), lam_n, target (m,)) and, with ``friction``, of ``npch``
    patches of ``nr`` rows (P, N (np, 3), r_twist (np,), t (np, 2, 3),
    Jt, Mt (np, nr, 12), mt, lam_t (np, nr), slip (np,) bool, mu (np,)),
    views of the scratch ``sc``'s buffers (None without friction)."""
    rows = (sc.take("J", (m, 12)), sc.take("M", (m, 12)), sc.take("mn", (m,)), sc.take("loc", (m, 3)),
            sc.take("lam_n", (m,)), sc.take("target", (m,)))
    if not friction:
        return rows + (None,) * 10
    return rows + (sc.take("P", (npch, 3)), sc.take("N", (npch, 3)), sc.take("r_twist", (npch,)),
                   sc.take("t", (npch, 2, 3)), sc.take("Jt", (npch, nr, 12)), sc.take("Mt", (npch, nr, 12)),
                   sc.take("mt", (npch, nr)), sc.take("lam_t", (npch, nr)), sc.take("slip", (npch,), np.bool_),
                   sc.take("mu", (npch,)))


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
                 sel: np.ndarray | None = None, topo: "Topology | None" = None, scratch: Scratch | None = None,
                 R0: np.ndarray | None = None, views: tuple | None = None, prepared: bool = False,
                 idx: np.ndarray | None = None):
        n = model.n
        if topo is None:
            src = c if sel is None else c.take(sel)
            topo = Topology(model, src.a, src.b, src.sidx, friction, colour)
        # the contacts of the rows, in row (colour) order
        if idx is None:
            idx = topo.order if sel is None else sel[topo.order]
        self.idx = idx
        self._c = c
        self._X = X
        self.topo = topo
        self.world = n
        self.order = topo.order
        self.m = m = idx.size
        self.a, self.b = topo.a, topo.b
        self.ima = topo.ima
        self.imb = topo.imb
        sc = self._sc = scratch if scratch is not None else Scratch()
        self.friction = friction
        want_loc = R0 is not None
        if friction:
            self.np = npch = topo.np
            self.rolling = rolling = bool(model.rolling)
        else:
            npch, rolling = 0, False
        nr = 5 if rolling else 3  # friction rows per patch: tangent, tangent, twist (, roll, roll)
        # the work arrays: views of the scratch's buffers, the same views
        # while the sizes stay (a resting stack: every step)
        if views is None:
            views = sc.group(("rows", m, npch, nr, friction), lambda: _take_rows(sc, m, npch, nr, friction))
        (self.J, self.M, self.mn, self.loc, self.lam_n, self.target, P, N, rt, t, Jt, Mt, mt, lam_t, slip,
         mu) = views
        if friction:
            self._patches(c, P, N, rt, t, Jt, Mt, mt, lam_t, slip, mu)
            pid, pa, pb, cnt, mus = topo.pid, topo.pa, topo.pb, topo.cnt, self.mus
        else:
            pid = pa = pb = _NO_I
            cnt = rt = mu = mus = _NO_D
            P = N = _NO_P3
            t, Jt, Mt, mt, lam_t, slip = _NO_T, _NO_J, _NO_J, _NO_P3, _NO_P3, _NO_B
        if prepared:
            return  # the caller's compiled call fills the views (engine/contact/phases.py solve_stage)
        # normal rows, patches, cleared impulses: one compiled call
        prepare.rows(Bodies(X=X, Iinv=Iinv, inv_mass=model.inv_mass, R0=R0 if want_loc else _NO_R), want_loc,
                     ContactArrays(a=c.a, b=c.b, sidx=c.sidx, point=c.point, normal=c.normal, gap=c.gap,
                                   e=_NO_D if c.e is None else c.e),
                     idx, n, RowArrays(J=self.J, M=self.M, mn=self.mn, loc=self.loc, lam_n=self.lam_n,
                                       target=self.target, P=P, N=N, rt=rt, t=t, Jt=Jt, Mt=Mt, mt=mt, lam_t=lam_t,
                                       slip=slip, mu=mu),
                     PatchSet(pid=pid, pa=pa, pb=pb, cnt=cnt, mus=mus), friction, rolling)

    # the body-a and body-b halves of the rows (views; the sweeps use the
    # stacked (m, 12) and (np, nr, 12) arrays)
    JA = property(lambda self: self.J[:, :6], doc="(m, 6) body a's Jacobian rows")
    JB = property(lambda self: self.J[:, 6:], doc="(m, 6) body b's Jacobian rows")
    MA = property(lambda self: self.M[:, :6], doc="(m, 6) body a's M^-1 J^T rows")
    MB = property(lambda self: self.M[:, 6:], doc="(m, 6) body b's M^-1 J^T rows")
    JtA = property(lambda self: self.Jt[:, :, :6], doc="(np, nr, 6) body a's friction rows")
    JtB = property(lambda self: self.Jt[:, :, 6:], doc="(np, nr, 6) body b's friction rows")
    MtA = property(lambda self: self.Mt[:, :, :6], doc="(np, nr, 6) body a's M^-1 Jt^T rows")
    MtB = property(lambda self: self.Mt[:, :, 6:], doc="(np, nr, 6) body b's M^-1 Jt^T rows")

    def rebind(self, c: Contacts, X: np.ndarray, idx: np.ndarray) -> None:
        """Reuse these rows for another step's contacts ``c`` (same topology
        and work arrays): its positions X (n, 3) and row order ``idx`` (m,);
        the row-ordered contacts are taken again when asked for."""
        self.idx = idx
        self._c = c
        self._X = X
        self.__dict__.pop("_cs", None)

    @property
    def contacts(self) -> Contacts:
        """The rows' contacts, in row order (gathered on first use)."""
        cs = self.__dict__.get("_cs")
        if cs is None:
            cs = self.__dict__["_cs"] = self._c.take(self.idx)
        return cs

    @property
    def rA(self) -> np.ndarray:
        """(m, 3) lever arms p - x_a."""
        cs = self.contacts
        return cs.point - _pad(self._X)[cs.a]

    @property
    def rB(self) -> np.ndarray:
        """(m, 3) lever arms p - x_b (the world's origin for statics)."""
        cs = self.contacts
        return cs.point - _pad(self._X)[cs.b]

    def _patches(self, c: Contacts, P, N, rt, t, Jt, Mt, mt, lam_t, slip, mu) -> None:
        """The friction patches' work arrays (filled by prepare.rows)."""
        topo = self.topo
        self.pid = topo.pid
        self.pa, self.pb = topo.pa, topo.pb
        self.pcentroid = P  # (np, 3)
        self.pnormal = N  # (np, 3)
        self.r_twist = rt  # (np,)
        self.t = t  # (np, 2, 3)
        self.Jt = Jt  # (np, nr, 12): [JtA | JtB], as J above
        self.Mt = Mt
        self.mt = mt  # (np, nr)
        self.lam_t = lam_t  # (np, nr)
        # pair coefficients are equal for all rows of a patch (and depend
        # only on the pair: kept in the topology)
        if topo.mus is None:
            first = self.idx[topo.pfirst]
            topo.mus = c.mus[first]
            topo.muk = c.muk[first]
            topo.mur = c.mur[first] if self.rolling else None
        self.mus = topo.mus
        self.muk = topo.muk
        self.mur = topo.mur
        self.slip = slip  # (np,) bool
        self.mu = mu  # (np,)

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
        return linalg.spd_solve_sparse(self.J, self.M, self.a, self.b, self.world, r, act, linalg.EPS_REL)

    def k_times(self, lam: np.ndarray) -> np.ndarray:
        """K lam (m,) without forming K."""
        return linalg.k_times(self.J, self.M, self.a, self.b, self.world, lam)

    def _lcp_residual(self, r, lam) -> float:
        """Complementarity residual of normal impulses ``lam`` for
        K lam >= r, lam >= 0: violated rows plus rows that push while
        separating."""
        return float(linalg.lcp_residual(self.k_times(lam) - r, lam))

    def direct_normal_guess(self, U, max_rows: int = DIRECT_MAX_ROWS, passes: int = ACTIVE_SET_PASSES,
                            dense=dense_direct_solve) -> None:
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
        if self.m > max_rows:
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
            lam, ok, _ = dense(self.normal_matrix(), r, act, passes)
        if not ok or not np.all(np.isfinite(lam)):
            return
        if self._lcp_residual(r, lam) <= self._lcp_residual(r, self.lam_n):
            self.lam_n = lam

    def set_slip(self, slip: np.ndarray) -> None:
        """Patches ``slip`` (np,) bool use mu_k, the others mu_s."""
        if slip is not self.slip:
            self.slip[:] = slip
        self.mu[:] = self.mus
        np.copyto(self.mu, self.muk, where=self.slip)

    def sliding(self, U, vt: np.ndarray | None = None) -> np.ndarray:
        """(np,) bool: the patches that slide at velocities U (n+1, 6).  A
        patch slides when its centroid's relative tangential speed (written
        to ``vt`` (np, 2) m/s when given) exceeds ``SLIP_TOL``, or
        when it twists: |w_n| r_twist, the twist's speed at the patch's mean
        point distance, exceeds it.  A patch spinning in place slides at
        every point but its centroid, so it is kinetic friction (mu_k) that
        acts on it (classed by the centroid alone it kept mu_s: a capsule
        spinning on its side with mu_s = 2 mu_k stopped in half the time)."""
        if vt is None:
            vt = np.empty((self.np, 2))
        slip = np.empty(self.np, np.bool_)
        prepare.sliding(self.Jt, U, self.topo.pab, self.r_twist, SLIP_TOL, vt, slip)
        return slip

    def patch_velocity(self, U, rows: slice) -> np.ndarray:
        """(np, k) relative velocities of the patch rows ``rows``: slice(0, 2)
        the tangential velocity at the centroids (m/s), slice(3, 5) the
        rolling angular velocity (rad/s)."""
        out = np.empty((self.np, rows.stop - rows.start))
        prepare.patch_velocity(self.Jt, U, self.topo.pab, rows.start, rows.stop, out)
        return out

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
        gauss_seidel.apply_rows(U, self.topo.ab, self.M, d, self.world)

    def apply_patch(self, U, d) -> None:
        """Add patch friction impulses d (np, 3) to U."""
        gauss_seidel.apply_patches(U, self.topo.pab, self.Mt, d, self.world)

    def warm_start(self, U) -> None:
        if self.m:
            self.apply_normal(U, self.lam_n)
            if self.friction:
                self.apply_patch(U, self.lam_t)

    # ---- projected Gauss-Seidel (compiled: engine/contact/gauss_seidel.py) --------
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
            patches = Patches(pab=self.topo.pab, pid=self.pid, Jt=self.Jt, Mt=self.Mt, mt=self.mt, lam_t=self.lam_t,
                              mu=self.mu, rt=self.r_twist, mur=mur, pin_t=pin_t, dir_t=dir_t, pin_r=pin_r,
                              dir_r=dir_r)
        else:
            z = np.zeros(0)
            zb = np.zeros(0, np.bool_)
            patches = Patches(pab=self._NO_P, pid=np.zeros(0, np.int64), Jt=self._NO_F, Mt=self._NO_F,
                              mt=np.zeros((0, 3)), lam_t=np.zeros((0, 3)), mu=z, rt=z, mur=z, pin_t=zb,
                              dir_t=np.zeros((0, 2)), pin_r=zb, dir_r=np.zeros((0, 2)))
        normal = NormalRows(ab=self.topo.ab, J=self.J, M=self.M, mn=self.mn, lam=self.lam_n, target=self.target)
        sw, self.residual = gauss_seidel.iterate(U, normal, patches, self.friction, iterations, tol, self.world,
                                                 self.sweep_work())
        return int(sw)

    def sweep_work(self) -> np.ndarray:
        """The sweeps' work array for these rows (engine.contact.gauss_seidel), a
        view of the scratch's buffer."""
        npch, nr = (self.np, self.lam_t.shape[1]) if self.friction else (0, 0)
        return self._sc.take("rows_work", (gauss_seidel.work_size(self.m, npch, nr),))

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
        roll = bool(self.rolling and wr0 is not None)
        if not prepare.stop_candidate(self.pid, self.lam_n, self.Jt, U, self.topo.pab, vt0, SLIP_TOL, roll,
                                      wr0 if roll else vt0, self.mur if roll else _NO_D, ROLL_TOL):
            return None  # (the common case, one compiled call; the numpy below decides the rest)
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
            self.lam_n[:] = saved[0]  # in place: the arrays are kept views (solver.Solve reuses the rows)
            self.lam_t[:] = saved[1]
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
        gauss_seidel.iterate_normal(U, self.topo.ab, self.J, self.M, self.mn, lam, target, iterations, tol, self.world,
                              self.sweep_work())
