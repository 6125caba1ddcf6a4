"""The CCD stages' small helpers and what they keep in the context
(``Context.ccd``, an :class:`engine.state.CcdKept`; engine/ccd.py): the
end-pose check's Python side (its buffers and the model's geometry as
writable copies, one compiled call, :mod:`engine.ccd_end`), the collider
the CCD and impact stages' collision calls run into, the followed pair's
collision arguments, the end-pose rotations, the grouping of rows by pair
code."""

from __future__ import annotations

import numpy as np

from physbench.engine import flight
from physbench.engine.ccd_end import end_pose_call
from physbench.engine.collision.dispatch import Collider, static_row
from physbench.engine.geometry import Geometry, shapes_of, statics_of
from physbench.engine.pack import Pack
from physbench.engine.model import BOX, S_BOX


def _stable_features(model, a: int, b: int, sidx: int) -> bool:
    """Whether the pair's contact feature ids name the same material feature
    from pose to pose: all pairs but box against box (body or static), whose
    ids are slots of a clipped manifold."""
    if model.shape[a] != BOX:
        return True
    if b < model.n:
        return model.shape[b] != BOX
    return model.static_shape[sidx] != S_BOX


def end_pose_pairs(model, state, ctx, lim: float, fast: np.ndarray | None):
    """The broad-phase pairs whose gap may change by more than ``lim`` (m)
    between the start and end poses, with the end pose's rotations, from
    one compiled call (:func:`engine.ccd_end.end_pose_candidates`) into buffers
    kept in the context (``Context.end_pose_buffers``): ((body pairs i, j),
    (plane pairs body, row), (static-box pairs body, row), R1 (n, 3, 3)),
    every array a view of a buffer valid until the next call; None when no
    pair moved that far.

    A body's end displacement, |x1 - x0| + 2 sin(theta/2) r (theta the
    turn between the two orientations, cos(theta/2) = |q0 . q1|, r the
    body's bounding radius), bounds how far any surface point lies from
    where it was, so the gap of a pair changes between the two poses by at
    most the sum of its bodies' values (a rigid motion moves the point s
    from the centre by |dx + (R1 - R0) s| <= |dx| + 2 sin(theta/2) |s|).

    The broad phase's sweep bounds the same from the speeds before and
    after the solve; for resting contacts that is the speed gravity gave
    the step before the solve took it away (g h = 0.04 m/s at 1/240 s:
    0.34 mm for two boxes, beyond the end-pose check's tolerance), so a
    resting column was collided twice a step (measured 590 us of its 2.4
    ms).  The same pairs, in the same order, as the boolean masks this
    replaced (tests/test_ccd_end_pose.py) -- less those whose end pose
    provably has no contact deeper than ``lim``
    (:func:`engine.ccd_end.end_pose_clear`: the end-pose collision would
    find nothing in them; tests/test_ccd_end_clear.py)."""
    pi, pj = ctx.pairs_i, ctx.pairs_j
    bp, pk = ctx.plane_pairs
    bs, sk = ctx.sbox_pairs
    out, kout = ctx.end_pose_kept(max(pi.size, bp.size, bs.size))
    nb, npl, ns = end_pose_call(state.x, state.q, ctx.x1, ctx.q1, _geometry_kept(model, ctx), lim, fast is not None,
                                _NO_FAST if fast is None else fast, pi, pj, bp, pk, bs, sk, kout)
    if not nb + npl + ns:
        return None
    return (out.ci[:nb], out.cj[:nb]), (out.cbp[:npl], out.cpk[:npl]), (out.cbs[:ns], out.csk[:ns]), out.R1


_NO_FAST = np.zeros(0, np.bool_)


def _geometry(model, ctx) -> Geometry:
    """The model's :class:`Geometry` as writable copies (the kernels are
    compiled for writable arrays), kept in the context."""
    g = ctx.ccd.geometry
    if g is None:
        g = ctx.ccd.geometry = Geometry(shapes=shapes_of(model), statics=statics_of(model),
                                                static_shape=np.array(model.static_shape, np.int64))
    return g


def _geometry_kept(model, ctx) -> Pack:
    """:func:`_geometry` as one Pack (engine.ccd_end.end_pose_call), kept in
    the context."""
    k = ctx.ccd.geometry_pack
    if k is None:
        k = ctx.ccd.geometry_pack = Pack(_geometry(model, ctx))
    return k


class _Groups:
    """The positions of each value of an integer key array (m,), ascending
    within a value -- what ``np.flatnonzero(key == u)`` gives -- from one
    stable sort: a mask over all m rows per value was O(values x m), and
    400 spheres landing together on the floor are 400 values."""

    def __init__(self, key: np.ndarray):
        self.order = np.argsort(key, kind="stable")
        self.keys = key[self.order]

    def __call__(self, u) -> np.ndarray:
        return self.order[np.searchsorted(self.keys, u, "left"):np.searchsorted(self.keys, u, "right")]


def _collider(model, ctx) -> Collider:
    """The collider the CCD and impact stages' collision calls run into,
    kept in the context (their contacts are views of its buffers, valid
    until its next call): a fresh one per call copied the model's arrays,
    O(n) each time, ~0.3 ms a call at 30 bodies."""
    col = ctx.ccd.collider
    if col is None:
        col = ctx.ccd.collider = Collider(model)
    return col


def _member(x: np.ndarray, s: np.ndarray) -> np.ndarray:
    """np.isin(x, s) for the few feature ids of a pair: (k,) bool."""
    if x.size == 0 or s.size == 0:
        return np.zeros(x.shape, bool)
    return (x.reshape(-1, 1) == s.reshape(1, -1)).any(axis=1)


def _cand_buffer(ctx, m: int) -> np.ndarray:
    """A kept (>= m,) bool buffer of the context (missed_candidates' flags)."""
    buf = ctx.ccd.cand
    if buf is None or buf.shape[0] < m:
        buf = ctx.ccd.cand = np.zeros(max(m, 2 * (0 if buf is None else buf.shape[0]), 16), np.bool_)
    return buf


def _drop_codes(ctx) -> np.ndarray:
    """``ctx.missed_skip`` (pair codes left out) as an int64 array."""
    return np.array(sorted(ctx.missed_skip), np.int64) if ctx.missed_skip else _NO_I


class _NoContacts:
    a = b = sidx = fid = np.zeros(0, np.int64)
    gap = np.zeros(0)
    point = np.zeros((0, 3))


_NO_CONTACTS = _NoContacts()
_NO_I = np.zeros(0, np.int64)


def _pair_query(model, ctx, a: int, b: int, sidx: int) -> tuple:
    """The arguments of :meth:`Collider.run` that collide one pair with no
    margin, as :func:`engine.collision.pair_contacts` builds them: (body
    pairs i, j, plane pairs, static-box pairs, margins), kept in the
    context per pair."""
    qs = ctx.ccd.pair_query
    key = (a, b, sidx)
    q = qs.get(key)
    if q is None:
        if len(qs) >= 256:
            qs.clear()
        one = lambda v: np.array([v], np.int64)  # noqa: E731
        z = np.zeros(0, np.int64)
        inf = np.array([np.inf])
        none = (z, z)
        if sidx < 0:
            q = (one(min(a, b)), one(max(a, b)), none, none, (inf, inf.copy(), inf.copy()))
        else:
            plane, row = static_row(model, sidx)
            pair = (one(a), one(row))
            q = (z, z, pair if plane else none, none if plane else pair, (inf, inf.copy(), inf.copy()))
        qs[key] = q
    return q


def _rotations(ctx, q: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of the quaternions q (n, 4) from one
    compiled call (:func:`engine.flight.q2m`, mathutil.quat_to_matrix's
    arithmetic) into a buffer kept in the context, valid until the next
    call."""
    R = ctx.ccd.R
    if R is None or R.shape[0] != q.shape[0]:
        R = ctx.ccd.R = np.empty((q.shape[0], 3, 3))
    flight.q2m(q, R)
    return R
