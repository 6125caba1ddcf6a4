"""Broad phase: which pairs may touch during this step.

Each body gets an axis-aligned box swept over the step (the union of its
boxes at the start pose and at the free-flight end pose), grown by the
contact margin.  Candidate body-body pairs come from sweep-and-prune
(``broadphase = sap``: sort the boxes' lower bounds along the axis of
largest spread, every box overlaps the boxes whose lower bound lies before
its upper bound, then test the two other axes; when that gives many
candidates per box -- dense 3D clouds -- the same sweep within the cells of
a 2D grid over the two other axes, see :func:`sap_pairs`: O(n log n)) or
from testing every pair (``brute``); both give exactly the same pairs in
the same order.  Body-plane pairs are candidates when the swept box
reaches the plane's margin; body-static-box pairs when the boxes overlap.
The stage is one compiled call per step (numba ``@njit(cache=True)``, no
BLAS; :func:`_broad_step`): the swept boxes, the pairs -- sweep and prune
along a sort order kept between steps and restored by insertion sort
(``engine.sap._sap_coherent``; dense clouds through a uniform grid,
``engine.sap._hash_grid_pairs``; non-finite or very unequal boxes fall
back to ``engine.broadphase.sap_pairs``) or the all-pairs test -- and the static pairs, into
buffers kept between steps and grown geometrically.

Also computes ``ctx.sweep`` (n,): a bound on how far any surface point of a
body moves in the step, h (max speed + max angular speed * bounding radius),
which sizes the narrow phase's speculative margin and decides which bodies
are "fast" for CCD.

Outputs (all sorted, so that the contact order -- and the result -- is
deterministic): ``ctx.pairs_i``/``pairs_j`` (i < j), ``ctx.plane_pairs``
(body, plane row), ``ctx.sbox_pairs`` (body, static-box row).
"""


from __future__ import annotations

from collections import namedtuple
from operator import is_

import numpy as np
from numba import njit

from physbench.engine.broadphase import PairBuffer, _brute_kernel, _emit, _grid_pairs, _sweep_pairs, sap_pairs
from physbench.engine.flight import q2m
from physbench.engine.geometry import Pairs, Shapes, Statics, shapes_of, statics_of  # noqa: F401
from physbench.engine.model import BOX, CAPSULE, CYLINDER, SPHERE
from physbench.engine.pack import KeptPack, Pack
from physbench.engine.profile import Stage
from physbench.engine.sap import _FALLBACK, SapBuffers, _sap_step


#: what the broad phase reads of a step's motion: the start pose ``x0`` (n,
#: 3) m, ``R0`` (n, 3, 3), the free-flight end pose ``q1`` (n, 4), ``x1``
#: (n, 3) and its rotations ``R1`` (n, 3, 3) (written), the start and end
#: velocities ``v0``, ``v1``, ``w0``, ``w1`` (>= n, 3) and the mean
#: velocity ``u`` (>= n, 3)
Motion = namedtuple("Motion", ("x0", "R0", "q1", "x1", "R1", "v0", "v1", "u", "w0", "w1"))

#: the broad phase's buffers, kept between steps: the swept boxes ``lo``,
#: ``hi`` (n, 3), ``sweep`` (n,) m, the sweep's kept sort ``order`` (n,),
#: ``state`` and ``grid`` (engine.sap.SapBuffers), and the pairs written
#: (``pi``, ``pj``, their sweep codes ``code``, ``bp``, ``pk``, ``bs``,
#: ``sk``: the fields of an engine.geometry.Pairs)
BroadBuffers = namedtuple("BroadBuffers", ("lo", "hi", "sweep", "order", "state", "grid", "pi", "pj", "code", "bp",
                                           "pk", "bs", "sk"))

#: the broad stage's kept arrays (:meth:`BroadPhase.kept`): the bodies'
#: :class:`Shapes`, the :class:`Statics`, the end rotations ``R1`` (n, 3, 3)
#: and the :class:`BroadBuffers`
BroadArrays = namedtuple("BroadArrays", ("shapes", "statics", "R1", "buf"))

#: the fused step's broad-phase pack (engine/fused/steady.py): the bodies'
#: :class:`Shapes`, the :class:`Statics`, the end rotations ``R1`` (n, 3,
#: 3), the :class:`BroadBuffers`, the narrow phase's ``margins`` and
#: ``no_sweep`` (n,), the CCD stage's ``fast`` flags and ``fast_min`` (n,)
#: and its end-pose buffers ``end`` (an engine.ccd_end.EndPose)
FusedBroad = namedtuple("FusedBroad", ("shapes", "statics", "R1", "buf", "margins", "no_sweep", "fast", "fast_min",
                                       "end"))


#: below this many bodies ``sap`` tests all pairs instead: the same pairs in
#: the same order, with fewer numpy calls (the sweep's sorting and
#: bookkeeping only pays for more bodies)
SAP_MIN_BODIES = 16


@njit(cache=True, inline="always")
def _extent_axis(shape, r, half, hl, R, i):
    """Half-size of a body's world axis-aligned box along world axis i at
    rotation R."""
    if shape == SPHERE:
        return r
    if shape == BOX:
        return abs(R[i, 0]) * half[0] + abs(R[i, 1]) * half[1] + abs(R[i, 2]) * half[2]
    if shape == CAPSULE:
        return abs(R[i, 2]) * hl + r
    # cylinder: the caps' discs
    return abs(R[i, 2]) * hl + r * np.sqrt(min(max(1.0 - R[i, 2] * R[i, 2], 0.0), 1.0))


@njit(cache=True)
def _swept_boxes(shapes, motion, h, grow, lo, hi, sweep):
    """Per body (``shapes`` the bodies' :class:`Shapes`, ``motion`` a
    :class:`Motion`): the union of its boxes at the start (x0, R0) and the
    free-flight end pose (x1, R1), grown by ``grow``, into lo, hi (n, 3);
    and ``sweep`` (n,): h (max speed + max angular speed * bounding radius)
    over the start (v0, w0) and end (v1, w1) velocities and the mean
    velocity u (all (>= n, 3)).  Allocates nothing
    (tests/test_engine_steady.py::test_steady_step_allocates_nothing)."""
    shape, radius, half, half_length, bound_radius = (shapes.shape, shapes.radius, shapes.half, shapes.half_length,
                                                      shapes.bound_radius)
    x0, R0, x1, R1, v0, v1, u, w0, w1 = (motion.x0, motion.R0, motion.x1, motion.R1, motion.v0, motion.v1, motion.u,
                                         motion.w0, motion.w1)
    for k in range(x0.shape[0]):
        for i in range(3):
            e0 = _extent_axis(shape[k], radius[k], half[k], half_length[k], R0[k], i)
            e1 = _extent_axis(shape[k], radius[k], half[k], half_length[k], R1[k], i)
            lo[k, i] = min(x0[k, i] - e0, x1[k, i] - e1) - grow
            hi[k, i] = max(x0[k, i] + e0, x1[k, i] + e1) + grow
        vmax = np.sqrt(max(v0[k, 0] * v0[k, 0] + v0[k, 1] * v0[k, 1] + v0[k, 2] * v0[k, 2],
                           v1[k, 0] * v1[k, 0] + v1[k, 1] * v1[k, 1] + v1[k, 2] * v1[k, 2]))
        umax = np.sqrt(u[k, 0] * u[k, 0] + u[k, 1] * u[k, 1] + u[k, 2] * u[k, 2])
        wmax = np.sqrt(max(w0[k, 0] * w0[k, 0] + w0[k, 1] * w0[k, 1] + w0[k, 2] * w0[k, 2],
                           w1[k, 0] * w1[k, 0] + w1[k, 1] * w1[k, 1] + w1[k, 2] * w1[k, 2]))
        sweep[k] = h * (max(vmax, umax) + wmax * bound_radius[k])


@njit(cache=True)
def _plane_pairs_kernel(lo, hi, N, off, grow, out_b, out_p):
    """(body, plane) pairs, body-major, whose box [lo, hi] reaches within
    ``grow`` of the plane (unit normal N[p], offset off[p]): the box's
    lowest point along N, c . N - e . |N| - off < grow.  Returns the
    number written, or minus the number needed when the outputs are short."""
    cnt = 0
    for k in range(lo.shape[0]):
        c0, c1, c2 = 0.5 * (lo[k, 0] + hi[k, 0]), 0.5 * (lo[k, 1] + hi[k, 1]), 0.5 * (lo[k, 2] + hi[k, 2])
        e0, e1, e2 = 0.5 * (hi[k, 0] - lo[k, 0]), 0.5 * (hi[k, 1] - lo[k, 1]), 0.5 * (hi[k, 2] - lo[k, 2])
        for p in range(N.shape[0]):
            low = (c0 * N[p, 0] + c1 * N[p, 1] + c2 * N[p, 2]
                   - (e0 * abs(N[p, 0]) + e1 * abs(N[p, 1]) + e2 * abs(N[p, 2])) - off[p])
            if low < grow:
                cnt = _emit(out_b, out_p, cnt, k, p)
    return cnt if cnt <= out_b.shape[0] else -cnt


@njit(cache=True)
def _box_pairs_kernel(lo, hi, slo, shi, out_b, out_p):
    """(body, static box) pairs, body-major, whose boxes overlap (see
    :func:`_plane_pairs_kernel` for the return value)."""
    cnt = 0
    for k in range(lo.shape[0]):
        for p in range(slo.shape[0]):
            if (lo[k, 0] <= shi[p, 0] and slo[p, 0] <= hi[k, 0] and lo[k, 1] <= shi[p, 1]
                    and slo[p, 1] <= hi[k, 1] and lo[k, 2] <= shi[p, 2] and slo[p, 2] <= hi[k, 2]):
                cnt = _emit(out_b, out_p, cnt, k, p)
    return cnt if cnt <= out_b.shape[0] else -cnt


@njit(cache=True)
def _broad_step(sap, shapes, statics, motion, buf, h, grow):
    """The whole broad phase in one call: the end rotations ``motion.R1``
    of ``motion.q1``, the swept boxes lo, hi and ``sweep``
    (:func:`_swept_boxes`, grown by ``grow`` m, over a step of ``h`` s),
    the body-body pairs (``sap``: :func:`_sap_step`, else every pair,
    :func:`_brute_kernel`), the body-plane and body-static-box pairs, into
    the buffers ``buf`` (a :class:`BroadBuffers`); ``shapes`` the bodies'
    :class:`Shapes`, ``statics`` the :class:`Statics`, ``motion`` a
    :class:`Motion`.  Returns their three counts (minus the need where a
    buffer was short; ``_FALLBACK`` for the body-body pairs to be found by
    :func:`sap_pairs`)."""
    m = motion
    lo, hi, pi, pj = buf.lo, buf.hi, buf.pi, buf.pj
    q2m(m.q1, m.R1)
    _swept_boxes(shapes, m, h, grow, lo, hi, buf.sweep)
    nbb = 0
    if lo.shape[0] >= 2:
        if sap is not None:
            nbb = _sap_step(lo, hi, buf.order, buf.state, pi, pj, buf.code, buf.grid)
            if nbb > pi.shape[0]:
                nbb = -nbb
        else:
            nbb = _brute_kernel(lo, hi, pi, pj)
    planes_n, slo = statics.planes_n, statics.slo
    npl = _plane_pairs_kernel(lo, hi, planes_n, statics.planes_off, grow, buf.bp, buf.pk) if planes_n.shape[0] else 0
    nsb = _box_pairs_kernel(lo, hi, slo, statics.shi, buf.bs, buf.sk) if slo.shape[0] else 0
    return nbb, npl, nsb


@njit(cache=True)
def _broad_call(sap, kbroad, kb, u, h, grow):
    """:func:`_broad_step` from Python with its arrays in two Packs (one
    pointer each to unbox; named tuples handed from Python are typed off
    numba's fast path): ``kbroad`` the stage's :class:`BroadArrays`, ``kb``
    the (mini-)step's engine.state.StepArrays (the start pose and
    velocities x, R0, v, w, the free flight's end x1, q1, V, W), ``u`` the
    mean velocity (>= n, 3)."""
    b = kbroad.items
    s = kb.items
    return _broad_step(sap, b.shapes, b.statics,
                       Motion(x0=s.x, R0=s.R0, q1=s.q1, x1=s.x1, R1=b.R1, v0=s.v, v1=s.V, u=u, w0=s.w, w1=s.W),
                       b.buf, h, grow)


class BroadPhase(Stage):
    """Swept-box broad phase (see module doc): one compiled call per step
    (:func:`_broad_step`) into buffers kept between steps and grown
    geometrically; ``ctx.pairs_i`` ... are views of them, valid until the
    stage's next call."""

    name = "broadphase"
    family = "broadphase"

    def __init__(self, model):
        #: True, or None where the scene never sweeps: the type selects
        #: :func:`_broad_step`'s compiled variant (a scene of a few bodies
        #: does not compile the sweep; tests/test_engine_jit.py::
        #: test_a_scene_warms_only_the_kernel_groups_its_stages_call)
        self.sap = True if uses_sap(model) else None
        self.margin = float(model.setting("contact_margin"))
        n = model.n
        # scratch, allocated once
        self.lo = np.empty((n, 3))
        self.hi = np.empty((n, 3))
        self.R1 = np.empty((n, 3, 3))
        self.pairs = SapBuffers(n)
        self._grow(2 * n + 16, 2 * n + 16)
        # writable copies: the kernels are compiled (and warmed, warm_up)
        # for writable arrays, and the model's are read-only
        self.shapes = shapes_of(model)
        self.statics = statics_of(model)
        self._buf = self._buf_key = None
        self._kept = KeptPack()

    def _grow(self, npl: int, nsb: int) -> None:
        self.bp, self.pk = np.empty(npl, np.int64), np.empty(npl, np.int64)
        self.bs, self.sk = np.empty(nsb, np.int64), np.empty(nsb, np.int64)

    def buffers(self, ctx) -> BroadBuffers:
        """The buffers :func:`_broad_step` writes (the sweep's into
        ``ctx.sweep``), the same object while they are the same arrays (a
        grown buffer is a new array)."""
        P = self.pairs
        key = (ctx.sweep, P.order, P.state, P.grid, P.pi, P.pj, P.code, self.bp, self.pk, self.bs, self.sk)
        if self._buf_key is None or not all(map(is_, key, self._buf_key)):
            self._buf = BroadBuffers(lo=self.lo, hi=self.hi, sweep=ctx.sweep, order=P.order, state=P.state,
                                     grid=P.grid, pi=P.pi, pj=P.pj, code=P.code, bp=self.bp, pk=self.pk, bs=self.bs,
                                     sk=self.sk)
            self._buf_key = key
        return self._buf

    def kept(self, ctx) -> Pack:
        """:func:`_broad_call`'s ``kbroad``: the stage's arrays as one Pack,
        kept while they stay."""
        buf = self.buffers(ctx)
        return self._kept.of((self.shapes, self.statics, self.R1, buf), lambda: Pack(BroadArrays(
            shapes=self.shapes, statics=self.statics, R1=self.R1, buf=buf)))

    def __call__(self, model, state, ctx) -> None:
        if ctx.reuse_contacts:
            return
        P = self.pairs
        while True:
            nbb, npl, nsb = _broad_call(self.sap, self.kept(ctx), ctx.kept(state), ctx.u_lin, float(ctx.h),
                                        self.margin)
            short = [max(-c, 0) for c in (nbb, npl, nsb)]
            if nbb == _FALLBACK:
                short[0] = 0
            if not any(short):
                break
            if short[0]:
                P.grow(2 * short[0])
            self._grow(max(2 * short[1], self.bp.size), max(2 * short[2], self.bs.size))
        if nbb == _FALLBACK:
            ctx.pairs_i, ctx.pairs_j = sap_pairs(self.lo, self.hi)
        else:
            ctx.pairs_i, ctx.pairs_j = P.pi[:nbb], P.pj[:nbb]
        ctx.plane_pairs = (self.bp[:npl], self.pk[:npl])
        ctx.sbox_pairs = (self.bs[:nsb], self.sk[:nsb])


def uses_sap(model) -> bool:
    """Whether the broad phase of ``model`` sweeps (``broadphase = sap``
    and more than ``SAP_MIN_BODIES`` bodies), else it tests all pairs."""
    return model.setting("broadphase") == "sap" and model.n > SAP_MIN_BODIES


def warm_up(sap: bool = True) -> None:
    """Compile (or load from the cache) the broad phase's kernels, with the
    argument types of the step (writable C-contiguous float64 and int64
    arrays), on a tiny problem (see :mod:`engine.jit`): all pairs, and with
    ``sap`` the sweep's kernels and the general ``sap_pairs``' too."""
    from physbench.engine.state import StepArrays

    n = 3
    z3, z = np.zeros((n, 3)), np.zeros(n)
    R = np.tile(np.eye(3), (n, 1, 1))
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    lo, hi, sw = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    shape = np.array([SPHERE, BOX, CYLINDER], np.int64)
    grid = (np.zeros(9, np.int64), np.empty(n, np.int64), np.empty((n, 3), np.int64), np.empty(n, np.int64),
            np.empty(n, np.int64))
    for flag in ((True,) if sap else (None,)):
        i1 = np.empty(1, np.int64)
        kbroad = Pack(BroadArrays(
            shapes=Shapes(shape=shape, radius=z + 0.1, half=z3 + 0.1, half_length=z, bound_radius=z + 0.2),
            statics=Statics(planes_n=np.array([[0.0, 0.0, 1.0]]), planes_off=np.zeros(1), slo=z3[:1].copy(),
                            shi=z3[:1].copy()),
            R1=R.copy(),
            buf=BroadBuffers(lo=lo, hi=hi, sweep=sw, order=np.arange(n, dtype=np.int64),
                             state=np.array([-1, 1], np.int64), grid=grid, pi=i1, pj=i1.copy(), code=i1.copy(),
                             bp=i1.copy(), pk=i1.copy(), bs=i1.copy(), sk=i1.copy())))
        v1 = np.zeros((n + 1, 3))
        kb = Pack(StepArrays(x=z3, q=q, v=z3.copy(), w=z3.copy(), inv_I=z3 + 1.0, x1=z3.copy(), q1=q.copy(), V=v1,
                             W=v1.copy(), F=z3.copy(), T=z3.copy(), vp=v1.copy(), wp=v1.copy(), R0=R,
                             Iinv0=np.zeros((n + 1, 3, 3))))
        _broad_call(flag, kbroad, kb, z3.copy(), 0.01, 1e-4)
    if not sap:
        return
    SapBuffers(n).run(lo, hi)
    buf = PairBuffer(1)
    buf.run(_brute_kernel, lo, hi)
    order = np.argsort(lo[:, 0], kind="stable")
    end = np.searchsorted(lo[order, 0], hi[order, 0], side="right")
    _sweep_pairs(lo, hi, 0, order, end, 3)
    _grid_pairs(lo, hi, 0, 1, 2, order, end)
