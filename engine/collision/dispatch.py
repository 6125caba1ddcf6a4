"""Narrow-phase dispatch (the collision driver): the candidate pairs of a
step collided in one compiled call (:func:`engine.collision.collide.collide`:
pairs grouped by shape pair, each group through its family's compiled
loop, contacts with their pair coefficients written into buffers kept
between steps, :class:`Collider`).  The tables ``TABLE`` (body-body, keyed
by canonically ordered shape codes), ``PLANE_TABLE`` and ``SBOX_TABLE``
(body-static, keyed by the body's shape) name the supported pairs and
their families (defined with the driver, :mod:`engine.collision.collide`)."""

from __future__ import annotations

import numpy as np

from physbench.engine.mathutil import quat_to_matrix
from physbench.engine.model import BOX, CAPSULE, CYLINDER, S_PLANE, SPHERE
from physbench.engine.profile import Stage
from physbench.engine.state import Contacts
from physbench.engine.collision import box
from physbench.engine.collision.collide import (FAMILY_FW, FAMILY_IW, MAX_SLOTS, PLANE_TABLE, SBOX_TABLE, TABLE,
                                                BodyShapes, BoxRows, ContactOut, NarrowWork, PairTables,
                                                PlaneRows, Side, Slots, collide_packed, narrow_pack, families,
                                                family_table_pack, ALL_FAMILIES)
from physbench.engine.pack import KeptPack

__all__ = ["Collider", "NarrowPhase", "PLANE_TABLE", "SBOX_TABLE", "TABLE", "collide_pairs", "pair_contacts",
           "static_row", "unsupported_pairs", "warm_up"]


def unsupported_pairs(model) -> list[str]:
    """Shape pairs the scene may bring into contact that the table lacks."""
    if not model.has("contact"):
        return []
    names = {SPHERE: "sphere", BOX: "box", CAPSULE: "capsule", CYLINDER: "cylinder"}
    shapes = sorted(set(int(s) for s in model.shape))
    out = []
    if model.n >= 2:
        for a in shapes:
            for b in shapes:
                if a <= b and (a, b) not in TABLE and (a != b or int(np.sum(model.shape == a)) >= 2):
                    out.append(f"{names[a]}-{names[b]}")
    if model.plane_normal.shape[0]:
        out += [f"{names[s]}-plane" for s in shapes if s not in PLANE_TABLE]
    if model.sbox_pos.shape[0]:
        out += [f"{names[s]}-box(static)" for s in shapes if s not in SBOX_TABLE]
    return out


class Collider:
    """The narrow phase's buffers for one model and :meth:`run`, which
    collides every candidate pair in one compiled call
    (:func:`engine.collision.collide.collide`).  Buffers (pairs, a group's
    gathered geometry and slots, the contacts) are kept between calls and
    grown geometrically when the kernel reports them short: no allocation
    per step in the steady state.  The contacts :meth:`run` returns are
    views of the output buffers, valid until its next call."""

    def __init__(self, model, pairs: int = 16, contacts: int = 64):
        self.n = model.n
        # writable copies: the kernel is compiled (and warmed) for writable
        # C-contiguous arrays, the model's are read-only
        f = lambda a, t=float: np.array(a, t)  # noqa: E731
        self.body = BodyShapes(shape=f(model.shape, np.int64), radius=f(model.radius), half=f(model.half_extents),
                               half_length=f(model.half_length), material=f(model.body_material, np.int64))
        self.planes = PlaneRows(normal=f(model.plane_normal).reshape(-1, 3), offset=f(model.plane_offset),
                                static=f(model.plane_static, np.int64))
        self.sboxes = BoxRows(centre=f(model.sbox_pos).reshape(-1, 3), R=f(model.sbox_R).reshape(-1, 3, 3),
                              half=f(model.sbox_half).reshape(-1, 3), static=f(model.sbox_static, np.int64))
        self.smat = f(model.static_material, np.int64)
        self.coef = PairTables(e=f(model.pair_e), mus=f(model.pair_mus), muk=f(model.pair_muk), mur=f(model.pair_mur))
        self.margins = (np.empty(0), np.empty(0), np.empty(0))
        #: the families compiled for the driver (collide.families: the
        #: scene's shapes; the others raise, collide.family_table)
        self.fams = families(model.shape)
        self._table = None  # (fams, family_table_pack(fams)): :meth:`packed`
        self._kept = KeptPack()  # a new Pack when a buffer grows
        self._contacts = None  # (count, out buffers, Contacts of their views) of the last run
        self._pairs(pairs)
        self._group(pairs, pairs * MAX_SLOTS)
        self._out(contacts)

    def _pairs(self, m: int) -> None:
        i, z = np.empty(m, np.int64), np.empty(m)
        self.W = NarrowWork(perm=i, start=np.zeros(33, np.int64), key=i.copy(), ga=i.copy(), gb=i.copy(), st=i.copy(),
                            gm=z, ma=i.copy(), mb=i.copy(), edge=np.zeros(m, np.bool_), se=z.copy(),
                            capm1=np.full(m, -1, np.int64), fw=np.zeros(FAMILY_FW), iw=np.zeros(FAMILY_IW, np.int64))
        self.margins = tuple(np.empty(m) for _ in range(3))

    def _group(self, k: int, slots: int) -> None:
        def side():
            return Side(c=np.zeros((k, 3)), R=np.zeros((k, 3, 3)), h=np.zeros((k, 3)), r=np.zeros(k), hl=np.zeros(k))
        self.A, self.B = side(), side()
        self.slot = Slots(n=np.zeros(3 * slots), p=np.zeros(3 * slots), g=np.zeros(slots), f=np.zeros(slots, np.int64),
                          ok=np.zeros(slots, np.bool_))

    def _out(self, m: int) -> None:
        i = np.empty(m, np.int64)
        self.out = ContactOut(a=i, b=i.copy(), sidx=i.copy(), normal=np.empty((m, 3)), point=np.empty((m, 3)),
                              gap=np.empty(m), fid=i.copy(), e=np.empty(m), mus=np.empty(m), muk=np.empty(m),
                              mur=np.empty(m))

    def packed(self):
        """The buffers as one Pack (engine/pack.py), kept while they stay."""
        kt = self._table
        if kt is None or kt[0] is not self.fams:  # (the families' table, looked up once per ``fams``)
            kt = self._table = (self.fams, family_table_pack(self.fams))
        kfams = kt[1]
        return self._kept.of((self.body, self.planes, self.sboxes, self.smat, self.coef, self.W, self.A, self.B,
                              self.slot, self.out, kfams), lambda: narrow_pack(
                                  body=self.body, planes=self.planes, sboxes=self.sboxes, smat=self.smat,
                                  coef=self.coef, W=self.W, A=self.A, B=self.B, slot=self.slot, out=self.out,
                                  kfams=kfams))

    def last_contacts(self, cnt: int) -> Contacts | None:
        """The Contacts :meth:`run` last returned when it had ``cnt``
        contacts in the present buffers (the views of a call made into the
        same buffers by a compiled caller, engine/fused/steady.py), else None."""
        last = self._contacts
        return last[2] if last is not None and last[0] == cnt and last[1] is self.out else None

    def run(self, X, R, pi, pj, plane_pairs, sbox_pairs, margins=None, margin: float = 0.0,
            sweep: np.ndarray | None = None) -> Contacts:
        """Contacts for candidate pairs at the pose (X (n, 3), R (n, 3, 3)).

        ``pi``/``pj`` body-body pairs (i < j); ``plane_pairs``/``sbox_pairs``
        (body, row).  Margins (m) per pair: ``margins`` (body-body,
        body-plane, body-static-box arrays), or, when None, ``margin`` plus
        both bodies' ``sweep`` (n,).  Returns :class:`Contacts` with b = n
        for statics, ordered deterministically (body-body pairs grouped by
        shape pair, then planes, then static boxes; see
        :mod:`engine.collision.collide`), with their pair coefficients."""
        bp, pk = plane_pairs
        bs, sk = sbox_pairs
        m = max(pi.shape[0], bp.shape[0], bs.shape[0])
        if self.W.perm.shape[0] < m:
            self._pairs(2 * m)
        from_sweep = margins is None
        if from_sweep:
            margins = self.margins
        else:
            sweep = self.W.gm
        while True:
            kept = self.packed()
            cnt, need_k, need_s = collide_packed(kept, X, R, pi, pj, margins, bp, pk, bs, sk, from_sweep, margin,
                                                 sweep, box.EDGE_FACE_POINTS)
            short = False
            if need_k > self.A.c.shape[0] or need_s > self.slot.g.shape[0]:
                self._group(2 * need_k, 2 * need_s)
                short = True
            if cnt > self.out.a.shape[0]:
                self._out(2 * cnt)
                short = True
            if not short:
                break
        o = self.out
        last = self._contacts
        if last is not None and last[0] == cnt and last[1] is o:
            # the same views of the same buffers: the same object (a steady
            # step's solve keeps what it built from them, solver.Solve)
            return last[2]
        c = Contacts(a=o.a[:cnt], b=o.b[:cnt], sidx=o.sidx[:cnt], normal=o.normal[:cnt], point=o.point[:cnt],
                     gap=o.gap[:cnt], fid=o.fid[:cnt], e=o.e[:cnt], mus=o.mus[:cnt], muk=o.muk[:cnt], mur=o.mur[:cnt])
        self._contacts = (cnt, o, c)
        return c


def collide_pairs(model, X, R, pi, pj, plane_pairs, sbox_pairs, margin_bb, margin_bp, margin_bs,
                  collider: Collider | None = None) -> Contacts:
    """Contacts for candidate pairs at the pose (X (n, 3), R (n, 3, 3)),
    with margins (m) ``margin_bb``, ``margin_bp``, ``margin_bs`` per pair
    (see :meth:`Collider.run`): views of ``collider``'s buffers (a
    :class:`Collider` of ``model`` kept by the caller, valid until its next
    call), or arrays of their own (a fresh :class:`Collider`, sized for the
    pairs: O(n) copies of the model's arrays)."""
    col = collider
    if col is None:
        m = max(pi.shape[0], plane_pairs[0].shape[0], sbox_pairs[0].shape[0], 1)
        col = Collider(model, pairs=m, contacts=8 * m)
    f = np.ascontiguousarray
    return col.run(f(X, float), f(R, float), f(pi, np.int64), f(pj, np.int64),
                   (f(plane_pairs[0], np.int64), f(plane_pairs[1], np.int64)),
                   (f(sbox_pairs[0], np.int64), f(sbox_pairs[1], np.int64)),
                   (f(margin_bb, float), f(margin_bp, float), f(margin_bs, float)))


class NarrowPhase(Stage):
    """Contacts at the start pose for the broad phase's pairs, with a margin
    per pair of ``contact_margin`` plus both bodies' sweep (how far they can
    close in this step).  ``ctx.contacts`` are views of the stage's
    buffers (:class:`Collider`), valid until its next call."""

    name = "narrowphase"
    family = "narrowphase"

    def __init__(self, model):
        self.margin = float(model.setting("contact_margin"))
        self.speculative = model.setting("ccd") != "off"
        self.collider = Collider(model)
        self.zeros = np.zeros(model.n)

    def prime(self, model, state, ctx, main) -> None:
        """At build (engine.pipeline.prepare): the collider's Pack."""
        self.collider.packed()

    def __call__(self, model, state, ctx) -> None:
        if ctx.reuse_contacts:
            return
        ctx.contacts = self.collider.run(state.x, ctx.R0, ctx.pairs_i, ctx.pairs_j, ctx.plane_pairs, ctx.sbox_pairs,
                                         margin=self.margin, sweep=ctx.sweep if self.speculative else self.zeros)


def pair_contacts(model, X, q_or_R, a: int, b: int, sidx: int, collider: Collider | None = None) -> Contacts:
    """All features of one pair at a pose, with no margin (for time-of-impact
    refinement).  ``b`` is a body index, or n with ``sidx`` the static;
    ``collider`` as for :func:`collide_pairs`."""
    R = q_or_R if q_or_R.ndim == 3 else quat_to_matrix(q_or_R)
    inf = np.array([np.inf])
    z = np.zeros(0, np.int64)
    if sidx < 0:
        i, j = min(a, b), max(a, b)
        return collide_pairs(model, X, R, np.array([i]), np.array([j]), (z, z), (z, z), inf, inf, inf, collider)
    plane, row = static_row(model, sidx)
    if plane:
        return collide_pairs(model, X, R, z, z, (np.array([a]), np.array([row])), (z, z), inf, inf, inf, collider)
    return collide_pairs(model, X, R, z, z, (z, z), (np.array([a]), np.array([row])), inf, inf, inf, collider)


def static_row(model, sidx: int) -> tuple[bool, int]:
    """(whether static ``sidx`` is a plane, its row in the model's plane
    table (``plane_*``) or static-box table (``sbox_*``))."""
    if model.static_shape[sidx] == S_PLANE:
        return True, int(np.flatnonzero(model.plane_static == sidx)[0])
    return False, int(np.flatnonzero(model.sbox_static == sidx)[0])


def warm_up(fams: tuple = ALL_FAMILIES) -> None:
    """Compile (or load from the cache) the narrow phase's driver for the
    families ``fams`` (:func:`engine.collision.collide.families`; only
    their kernels), with the argument types of the step (writable
    C-contiguous float64 and int64 arrays), on a tiny scene (see
    :mod:`engine.jit`): one body of each shape, a plane and a static box,
    no candidate pair (what is compiled does not depend on the pairs)."""
    from types import SimpleNamespace

    n = 4
    I = np.eye(3)
    z1 = np.zeros(1)
    model = SimpleNamespace(
        n=n, shape=np.array([SPHERE, BOX, CAPSULE, CYLINDER], np.int64), radius=np.full(n, 0.1),
        half_extents=np.full((n, 3), 0.1), half_length=np.full(n, 0.1), body_material=np.zeros(n, np.int64),
        plane_normal=np.array([[0.0, 0.0, 1.0]]), plane_offset=z1, plane_static=np.zeros(1, np.int64),
        sbox_pos=np.zeros((1, 3)), sbox_R=I[None], sbox_half=np.full((1, 3), 0.1), sbox_static=np.ones(1, np.int64),
        static_material=np.zeros(2, np.int64), pair_e=np.zeros((1, 1)), pair_mus=np.zeros((1, 1)),
        pair_muk=np.zeros((1, 1)), pair_mur=np.zeros((1, 1)))
    X = np.array([[0.0, 0.0, 0.05], [0.1, 0.0, 0.05], [0.0, 0.1, 0.05], [0.1, 0.1, 0.05]])
    R = np.tile(I, (n, 1, 1))
    col = Collider(model, pairs=1, contacts=1)
    col.fams = fams
    z = np.zeros(0, np.int64)
    col.run(X, R, z, z, (z, z), (z, z), margin=1.0, sweep=np.zeros(n))
    col.run(X, R, z, z, (z, z), (z, z), (np.ones(0), np.ones(0), np.ones(0)))
