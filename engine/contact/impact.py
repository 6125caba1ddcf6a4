"""The impact solver (the restitution phase at times of impact): impulsive
collision response with restitution and friction over the touching
contacts, by impulse propagation or as one simultaneous plastic impact per
island (:func:`impact_solve`)."""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from physbench.engine.contact import linalg, prepare, propagate
from physbench.engine.contact.packs import (Bodies, ContactArrays, ImpactGroups, ImpactPatches, ImpactRows, PatchSet,
                                            RowArrays)
from physbench.engine.flight import q2m
from physbench.engine.contact.rows import TOUCH_TOL, Rows, _pad, _pair_codes, _take_rows
from physbench.engine.contact.scratch import Scratch
from physbench.engine.contact.topology import Topology
from physbench.engine.state import Contacts


class ImpactKept:
    """What the impact solves of one stage keep between calls: the
    propagation's work arrays (a :class:`Scratch`, views grown
    geometrically instead of ~16 new arrays per impact) and the topologies
    of the contact sets seen (keyed by their pair codes; a Topology is a
    function of the rows' (a, b, sidx) alone, so reuse is exact -- as the
    solve stage's cache, engine/solver.py).  A ball bouncing on the floor
    builds its one topology once (tests/test_impact_propagate.py)."""

    #: topologies kept at most (the cache is emptied when full)
    MAX_TOPOLOGIES = 64

    def __init__(self) -> None:
        self.scratch = Scratch()
        self.topos: dict = {}
        self._Iinv = self._inv_I = None
        #: the compiled path's (:func:`impact_kernel`) topology arrays per
        #: topology key (an :class:`ImpactTopo`, emptied with ``topos``),
        #: its work arrays (the row views they were made of, an
        #: :class:`ImpactWork`) and its velocities U (n+1, 6)
        self._topo_args: dict = {}
        self._work = None
        self._U = None

    def inertia(self, n: int) -> np.ndarray:
        """A kept (n+1, 3, 3) buffer for the world inverse inertias."""
        if self._Iinv is None or self._Iinv.shape[0] != n + 1:
            self._Iinv = np.empty((n + 1, 3, 3))
        return self._Iinv

    def inv_inertia(self, model) -> np.ndarray:
        """The model's body inverse inertias (n, 3), a writable copy (the
        kernel is compiled for writable arrays)."""
        if self._inv_I is None:
            self._inv_I = np.array(model.inv_inertia_body, float)
        return self._inv_I

    def topology(self, model, c: Contacts, friction: bool, colour: bool) -> Topology:
        return self._topology((_codes(model, c), friction, colour), model, c, friction, colour)

    def _topology(self, key: tuple, model, c: Contacts, friction: bool, colour: bool) -> Topology:
        topo = self.topos.get(key)
        if topo is None:
            if len(self.topos) >= self.MAX_TOPOLOGIES:
                self.topos.clear()
                self._topo_args.clear()
            topo = self.topos[key] = Topology(model, c.a, c.b, c.sidx, friction, colour)
        return topo

    def impact_topology(self, model, c: Contacts, friction: bool, rolling: bool) -> tuple:
        """(the propagation's uncoloured :class:`Topology` of the contacts
        ``c``, its arrays as :func:`impact_kernel` reads them, an
        :class:`ImpactTopo`), kept per contact set.  The patches' friction
        coefficients are set as :class:`Rows` sets them (its
        ``_patches``: from each patch's first row)."""
        key = (_codes(model, c), friction, False)
        got = self._topo_args.get(key)
        if got is not None and self.topos.get(key) is got[0]:
            return got
        topo = self._topology(key, model, c, friction, False)
        if friction:
            if topo.mus is None:  # (Rows._patches' rule: the pair's coefficients, from its first row)
                first = topo.order[topo.pfirst]
                topo.mus = c.mus[first]
                topo.muk = c.muk[first]
                topo.mur = c.mur[first] if rolling else None
            args = ImpactTopo(idx=topo.order, codes=topo.codes, ab=topo.ab, pid=topo.pid, pa=topo.pa, pb=topo.pb,
                              cnt=topo.cnt, mus=topo.mus, muk=topo.muk,
                              mur=topo.mur if rolling else np.zeros(topo.np))
        else:
            args = ImpactTopo(idx=topo.order, codes=topo.codes, ab=topo.ab, pid=_NO_I, pa=_NO_I, pb=_NO_I, cnt=_NO_D,
                              mus=_NO_D, muk=_NO_D, mur=_NO_D)
        got = self._topo_args[key] = (topo, args)
        return got

    def work(self, model, topo: Topology, friction: bool, rolling: bool) -> "ImpactWork":
        """:func:`impact_kernel`'s work arrays for the rows of ``topo``: the
        row arrays are the views :class:`Rows` takes from :attr:`scratch`
        (the same group: a fallback Rows writes the same arrays), kept
        while they stay."""
        m = topo.order.size
        npch = topo.np if friction else 0
        nr = 5 if rolling else 3
        sc = self.scratch
        views = sc.group(("rows", m, npch, nr, friction), lambda: _take_rows(sc, m, npch, nr, friction))
        w = self._work
        if w is not None and w[0] is views:
            return w[1]
        J, M, mn, loc, lam_n, target, P, N, rt, t, Jt, Mt, mt, lam_t, slip, mu = views
        if not friction:  # (Rows' empty patch arrays)
            P = N = mt = lam_t = _NO_P3
            rt = mu = _NO_D
            t = _NO_T
            Jt = Mt = _NO_J
            slip = _NO_B
        n = model.n
        if self._U is None or self._U.shape[0] != n + 1:
            self._U = np.empty((n + 1, 6))
        work = ImpactWork(Iinv=self.inertia(n), inv_I=self.inv_inertia(model), inv_mass=model.inv_mass, R0=_NO_R,
                          U=self._U, rows=RowArrays(J=J, M=M, mn=mn, loc=loc, lam_n=lam_n, target=target, P=P, N=N,
                                                    rt=rt, t=t, Jt=Jt, Mt=Mt, mt=mt, lam_t=lam_t, slip=slip, mu=mu))
        self._work = (views, work)
        return work


def impact_solve(model, state, contacts: Contacts, iterations: int, thr: float, friction: bool,
                 plastic: str = "simultaneous", kept: ImpactKept | None = None) -> int:
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

    ``kept``: the stage's :class:`ImpactKept` (work arrays, topologies),
    or None (fresh ones).  With ``kept`` and no plastic island, the
    propagation and its set-up run as one compiled call
    (:func:`impact_kernel`; the bits of the path without ``kept``:
    tests/test_ccd_event_path.py).
    """
    k = touching_count(contacts.gap, 10 * TOUCH_TOL)
    if k == 0:
        return 0
    # (all of them, the common case: the contacts themselves, read only)
    cs = contacts if k == contacts.m else contacts.take(np.flatnonzero(contacts.gap <= 10 * TOUCH_TOL))
    # (every row bouncing, the common case of billiards: no plastic island)
    together = _plastic_islands(model, cs) if plastic == "simultaneous" and not all_positive(cs.e) else None
    if kept is not None and (together is None or not together.any()):
        m = _propagate_kept(model, state, cs, thr, friction, kept)
        if m is not None:
            return m
    n = model.n
    # the world inverse inertias of the contacts' bodies only, the others
    # zero (an O(n) pass per impact at 10,000 bodies was ~2 ms): one
    # compiled call, mathutil.world_inv_inertia(quat_to_matrix(q)) bit for
    # bit (tests/test_ccd_event_path.py)
    Iinv = np.empty((n + 1, 3, 3)) if kept is None else kept.inertia(n)
    inv_I = np.array(model.inv_inertia_body, float) if kept is None else kept.inv_inertia(model)
    contact_inertias(state.q, inv_I, cs.a, cs.b, Iinv)
    U = Rows.pack(_pad(state.v), _pad(state.w))
    m = 0
    if together is None or not together.any():
        m += _propagate(model, state.x, Iinv, cs, U, iterations, thr, friction, kept)
    else:
        m += _plastic_island_solve(model, state.x, Iinv, cs.take(np.flatnonzero(together)), U, iterations,
                                   friction)
        if not together.all():
            m += _propagate(model, state.x, Iinv, cs.take(np.flatnonzero(~together)), U, iterations, thr,
                            friction)
    state.v[:] = U[:n, :3]
    state.w[:] = U[:n, 3:]
    return m


def _codes(model, c: Contacts) -> bytes:
    """The contacts' pair codes (engine.contact.topology._pair_codes, the
    same int64 values) as bytes: a contact set's key."""
    return pair_codes(c.a, c.b, c.sidx, model.n, model.n_statics).tobytes()


@njit(cache=True)
def pair_codes(a, b, sidx, n, n_statics):
    """(a (n + 1) + b) (n_statics + 1) + sidx + 1 per contact (a, b, sidx
    (m,)): engine.contact.topology._pair_codes_abs in one compiled call."""
    out = np.empty(a.shape[0], np.int64)
    for i in range(a.shape[0]):
        out[i] = (a[i] * (n + 1) + b[i]) * (n_statics + 1) + (sidx[i] + 1)
    return out


@njit(cache=True)
def touching_count(gap, tol):
    """How many of the gaps (m,) are <= tol: the size of
    np.flatnonzero(gap <= tol), in one compiled call."""
    k = 0
    for g in gap:
        if g <= tol:
            k += 1
    return k


@njit(cache=True)
def all_positive(e):
    """np.all(e > 0.0) for the coefficients of restitution e (m,) (NaN is
    not > 0), in one compiled call."""
    for v in e:
        if not v > 0.0:
            return False
    return True


@njit(cache=True)
def contact_inertias(q, inv_I, a, b, Iinv):
    """Iinv (n+1, 3, 3): R diag(inv_I) R^T (R the rotation of q (n, 4),
    :func:`engine.flight.q2m`) for the bodies of the contacts (a, b (m,);
    b = n the world), zero elsewhere -- the arithmetic of
    flight.start_pose, which is mathutil.world_inv_inertia's bit for bit."""
    n = q.shape[0]
    Iinv[:, :, :] = 0.0
    R = np.empty((1, 3, 3))
    for r in range(2 * a.shape[0]):
        k = a[r] if r < a.shape[0] else b[r - a.shape[0]]
        if k >= n or Iinv[k, 0, 0] != 0.0:
            continue  # the world, or done (a diagonal entry of R diag(1/I) R^T is > 0)
        q2m(q[k:k + 1], R)
        for i in range(3):
            for j in range(3):
                s = 0.0
                for c in range(3):
                    s += R[0, i, c] * inv_I[k, c] * R[0, j, c]
                Iinv[k, i, j] = s


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


def _propagate(model, X, Iinv, cs: Contacts, U: np.ndarray, iterations: int, thr: float, friction: bool,
               kept: ImpactKept | None = None) -> int:
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
    Returns the number of rows; ``kept`` as :func:`impact_solve`'s."""
    n = model.n
    if kept is None:
        rows = Rows(model, X, Iinv, cs, friction, colour=False)
    else:
        rows = Rows(model, X, Iinv, cs, friction, colour=False, topo=kept.topology(model, cs, friction, False),
                    scratch=kept.scratch)
    args = _propagation_args(rows, cs, U, thr, friction, n)
    if not propagate.propagate(0, *args):
        _pinned(model, X, Iinv, cs, U, iterations, thr, friction, rows, args)
    propagate.propagate(1, *args)  # slow approaches stop (plastic)
    return rows.m


def _propagation_args(rows: Rows, cs: Contacts, U: np.ndarray, thr: float, friction: bool, n: int) -> tuple:
    """:func:`engine.contact.propagate.propagate`'s arguments (all but its
    mode) for the uncoloured ``rows`` of the contacts ``cs`` and the
    velocities U (n+1, 6): the rows; the rows of each pair (ascending):
    go[gs[g]:gs[g + 1]], inv the pair of each row; of each body:
    bo[b0[k]:b0[k + 1]]; the normal speeds of all rows (kept current by the
    compiled loop: a pair's impulses change only the rows of its two
    bodies), from one compiled call; the friction patches."""
    # (uncoloured: the rows are the contacts in their order, and the
    # topology's codes theirs)
    code = rows.topo.codes
    ab = rows.topo.ab
    go, gs, inv, bo, b0, vcur = propagate.setup(code, ab, n, np.ascontiguousarray(rows.J), U)
    f = np.ascontiguousarray
    if friction:
        fr = ImpactPatches(Jt=f(rows.Jt), Mt=f(rows.Mt), mt=f(rows.mt), pa=f(rows.pa, np.int64),
                           pb=f(rows.pb, np.int64), mus=f(rows.mus, float), muk=f(rows.muk, float),
                           r_twist=f(rows.r_twist), mur=f(rows.mur, float) if rows.rolling else np.zeros(rows.np))
    else:
        nr = 3
        fr = ImpactPatches(Jt=np.zeros((0, nr, 12)), Mt=np.zeros((0, nr, 12)), mt=np.zeros((0, nr)), pa=_NO_I,
                           pb=_NO_I, mus=_NO_D, muk=_NO_D, r_twist=_NO_D, mur=_NO_D)
    return (ImpactRows(J=f(rows.J), M=f(rows.M), ab=f(ab, np.int64), e=f(cs.e, float),
                       pid=f(rows.pid, np.int64) if friction else _NO_I),
            ImpactGroups(go=go, gs=gs, inv=inv, bo=bo, b0=b0), U, vcur, float(thr), bool(friction), fr,
            bool(friction and rows.rolling))


def _pinned(model, X, Iinv, cs: Contacts, U: np.ndarray, iterations: int, thr: float, friction: bool, rows: Rows,
            args: tuple) -> None:
    """A propagation that did not settle (a pinned configuration): every
    approach resolved together by sequential impulses on U (n+1, 6) in
    place, and the rows' speeds (``args``' vcur) set to the result."""
    ab = rows.topo.ab

    def vn_all():
        # [JA | JB] . [U[a] | U[b]] per row: one gather, one reduction
        return np.einsum("kj,kj->k", rows.J, U[ab].reshape(-1, 12))

    v = vn_all()
    rows.target = np.where(v < -thr, -cs.e * v, 0.0)
    rows_c = Rows(model, X, Iinv, cs, friction)
    rows_c.target = rows.target[rows_c.order]
    rows_c.solve_friction_regimes(U, iterations)
    args[3][:] = vn_all()


def _propagate_kept(model, state, cs: Contacts, thr: float, friction: bool, kept: ImpactKept) -> int | None:
    """:func:`_propagate` of the contacts ``cs`` (no plastic island) on the
    state's velocities with the kept work arrays: the contact bodies'
    inertias, the rows, the propagation and the new velocities in one
    compiled call (:func:`impact_kernel`, the arithmetic of
    :func:`impact_solve`'s calls).  Returns the number of rows, or None
    when the propagation did not settle (a pinned configuration; the
    state untouched): the caller's path from Python then resolves it."""
    rolling = friction and bool(model.rolling)
    topo, targs = kept.impact_topology(model, cs, friction, rolling)
    work = kept.work(model, topo, friction, rolling)
    c = ContactArrays(a=cs.a, b=cs.b, sidx=cs.sidx, point=cs.point, normal=cs.normal, gap=cs.gap, e=cs.e)
    if not impact_kernel(work, targs, c, state.x, state.q, state.v, state.w, float(thr), bool(friction),
                         bool(rolling)):
        return None
    return topo.order.size


#: :func:`impact_kernel`'s work arrays: the world inverse inertias
#: ``Iinv`` (n+1, 3, 3) it writes, the body inverse inertias ``inv_I`` (n,
#: 3), the model's ``inv_mass`` (n+1,), an empty ``R0`` (the rows' lever
#: frames are not wanted), the velocities ``U`` (n+1, 6), the rows'
#: arrays ``rows`` (an engine.contact.packs.RowArrays)
ImpactWork = namedtuple("ImpactWork", ("Iinv", "inv_I", "inv_mass", "R0", "U", "rows"))

#: the propagation's topology as :func:`impact_kernel` reads it: the rows'
#: contacts ``idx`` (m,), pair codes ``codes`` (m,), bodies ``ab`` (m,
#: 2), and with friction the patches' ``pid`` (m,), ``pa``, ``pb`` (np,),
#: ``cnt`` (np,), coefficients ``mus``, ``muk``, ``mur`` (np,) (empty
#: without friction; ``mur`` zeros without rolling friction)
ImpactTopo = namedtuple("ImpactTopo", ("idx", "codes", "ab", "pid", "pa", "pb", "cnt", "mus", "muk", "mur"))


@njit(cache=True)
def impact_kernel(work, topo, c, x, q, v, w, thr, friction, rolling):
    """:func:`_propagate_kept`'s one call: the contact bodies' world
    inverse inertias (:func:`contact_inertias`), U (n+1, 6) = [v | w] with
    a zero world row, the rows of the contacts ``c`` (an
    engine.contact.packs.ContactArrays) in ``topo``'s order
    (engine.contact.prepare.rows, as :class:`Rows` makes them), the
    propagation's set-up and its first mode (engine.contact.propagate); if
    that settled, its second mode and v, w (n, 3) set from U.  Returns
    whether it settled (if not, v and w are untouched and ``work.U`` holds
    the velocities so far)."""
    n = x.shape[0]
    Iinv, U, r = work.Iinv, work.U, work.rows
    contact_inertias(q, work.inv_I, c.a, c.b, Iinv)
    for i in range(n):
        for j in range(3):
            U[i, j] = v[i, j]
            U[i, 3 + j] = w[i, j]
    for j in range(6):
        U[n, j] = 0.0
    prepare.rows(Bodies(X=x, Iinv=Iinv, inv_mass=work.inv_mass, R0=work.R0), bool(False), c, topo.idx, n, r,
                 PatchSet(pid=topo.pid, pa=topo.pa, pb=topo.pb, cnt=topo.cnt, mus=topo.mus), friction, rolling)
    go, gs, inv, bo, b0, vcur = propagate.setup(topo.codes, topo.ab, n, r.J, U)
    rows = ImpactRows(J=r.J, M=r.M, ab=topo.ab, e=c.e, pid=topo.pid)
    groups = ImpactGroups(go=go, gs=gs, inv=inv, bo=bo, b0=b0)
    patches = ImpactPatches(Jt=r.Jt, Mt=r.Mt, mt=r.mt, pa=topo.pa, pb=topo.pb, mus=topo.mus, muk=topo.muk,
                            r_twist=r.rt, mur=topo.mur)
    if not propagate.propagate(np.int64(0), rows, groups, U, vcur, thr, friction, patches, rolling):
        return False
    propagate.propagate(np.int64(1), rows, groups, U, vcur, thr, friction, patches, rolling)
    for i in range(n):
        for j in range(3):
            v[i, j] = U[i, j]
            w[i, j] = U[i, 3 + j]
    return True


_NO_I = np.zeros(0, np.int64)
_NO_D = np.zeros(0)
_NO_B = np.zeros(0, np.bool_)
_NO_P3 = np.zeros((0, 3))
_NO_T = np.zeros((0, 2, 3))
_NO_J = np.zeros((0, 3, 12))
_NO_R = np.zeros((0, 3, 3))


def warm_up() -> None:
    """Compile (or load) the propagation kernel, the contact bodies'
    inertias, :func:`impact_kernel` and the stage's small kernels with the
    step's argument types (see engine/jit.py): one pair of two rows, with
    and without friction; and the topology's kernel
    (engine/contact/topology.py)."""
    from physbench.engine.contact import topology

    topology.warm_up()
    _warm_impact_kernel()
    i1 = np.zeros(1, np.int64)
    touching_count(np.zeros(1), 1e-8)
    pair_codes(i1, i1 + 1, i1 - 1, 1, 1)
    all_positive(np.ones(1))
    propagate.setup(np.array([5, 5], np.int64), np.array([[0, 1], [0, 1]], np.int64), 1, np.ones((2, 12)),
                    np.zeros((2, 6)))
    contact_inertias(np.array([[1.0, 0.0, 0.0, 0.0]]), np.ones((1, 3)), i1, i1 + 1, np.empty((2, 3, 3)))
    J = np.ones((2, 12))
    ab = np.array([[0, 1], [0, 1]], np.int64)
    i2 = np.zeros(2, np.int64)
    U = np.zeros((2, 6))
    for friction in (False, True):
        k = 1 if friction else 0
        propagate.propagate(0, ImpactRows(J=J, M=J.copy(), ab=ab, e=np.ones(2), pid=i2[:2 if friction else 0]),
                            ImpactGroups(go=np.arange(2, dtype=np.int64), gs=np.array([0, 2], np.int64), inv=i2,
                                         bo=np.arange(2, dtype=np.int64), b0=np.array([0, 2, 2], np.int64)),
                            U, -np.ones(2), 0.1, friction,
                            ImpactPatches(Jt=np.ones((k, 3, 12)), Mt=np.ones((k, 3, 12)), mt=np.ones((k, 3)),
                                          pa=i2[:k], pb=i2[:k] + 1, mus=np.ones(k), muk=np.ones(k), r_twist=np.ones(k),
                                          mur=np.ones(k)),
                            False)


def _warm_impact_kernel() -> None:
    """:func:`impact_kernel` on a sphere resting on a plane (one row, one
    patch; the model's inverse masses read-only, as the model holds them),
    with the arrays typed as :meth:`ImpactKept.work` and
    :meth:`ImpactKept.impact_topology` hand them over: one signature with
    and without friction."""
    i1 = np.zeros(1, np.int64)
    im = np.array([1.0, 0.0])
    im.flags.writeable = False
    sc = Scratch()
    for friction in (False, True):
        J, M, mn, loc, lam_n, target, P, N, rt, t, Jt, Mt, mt, lam_t, slip, mu = _take_rows(sc, 1, 1, 3, True)
        if not friction:
            P = N = mt = lam_t = _NO_P3
            rt = mu = _NO_D
            t = _NO_T
            Jt = Mt = _NO_J
            slip = _NO_B
        work = ImpactWork(Iinv=np.zeros((2, 3, 3)), inv_I=np.ones((1, 3)), inv_mass=im, R0=_NO_R, U=np.zeros((2, 6)),
                          rows=RowArrays(J=J, M=M, mn=mn, loc=loc, lam_n=lam_n, target=target, P=P, N=N, rt=rt, t=t,
                                         Jt=Jt, Mt=Mt, mt=mt, lam_t=lam_t, slip=slip, mu=mu))
        one = np.ones(1)
        topo = (ImpactTopo(idx=i1, codes=i1 + 7, ab=np.array([[0, 1]], np.int64), pid=i1, pa=i1, pb=i1 + 1, cnt=one,
                           mus=one * 0.5, muk=one * 0.5, mur=np.zeros(1)) if friction else
                ImpactTopo(idx=i1, codes=i1 + 7, ab=np.array([[0, 1]], np.int64), pid=_NO_I, pa=_NO_I, pb=_NO_I,
                           cnt=_NO_D, mus=_NO_D, muk=_NO_D, mur=_NO_D))
        c = ContactArrays(a=i1.copy(), b=i1 + 1, sidx=i1.copy(), point=np.zeros((1, 3)),
                          normal=np.array([[0.0, 0.0, -1.0]]), gap=np.zeros(1), e=np.ones(1) * 0.5)
        impact_kernel(work, topo, c, np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, -1.0]]),
                      np.zeros((1, 3)), 0.1, friction, False)
