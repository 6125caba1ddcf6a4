"""The steady step: a (mini-)step with no event as ONE compiled call.

A step of a resting or steadily sliding scene runs the same stages every
time, and their Python glue (a stage call through the profile, the kept
views and packs each stage looks up) cost as much as their compiled work.
:func:`steady_kernel` runs the flight part (engine/fused/part.py: the
start of the (mini-)step, the force stages, the gyroscopic stages, the free
flight), the broad phase, the
narrow phase, the whole solve stage (:func:`engine.contact.phases.classify_stage`),
the position update, the CCD stage's end-pose check and the commit, the
same kernels with the same arguments in the same order as the stages call
them one by one (the same bits: the determinism pins and the final states
of every scenario are unchanged), and stops where the step is not steady:

* ``FAIL`` -- a buffer is short, the contact count or graph changed, a row
  is an impact, the friction-stop gate opens (a sliding patch may have
  stopped): nothing of the state was written, and the step loop runs the
  (mini-)step stage by stage from its start (the same bits: every stage
  recomputes what the call wrote into the context's work arrays);
* ``CCD`` -- a pair moved far enough between the start and end poses to
  need the CCD stage's end-pose collision (``engine.ccd.missed_impacts``):
  everything before it is done, and the step loop runs the CCD stage and
  goes on as after the staged stages;
* ``DONE`` -- committed.

Which stages a scene has is decided once (:meth:`SteadyStep.build`, the
pipeline's plan): the fused call covers every force stage of the table
(engine.forces.FORCES), every integrator, the three gyroscopic treatments
(the explicit torque, the implicit and the energy-conserving stage:
engine/fused/gyro.py), the
sequential-impulse solve without Baumgarte's bias (friction stops of
sliding and rolling contacts: the gate above, engine/fused/stops.py for
the rolling half), with or without the CCD stage, in scenes that step
whole (``substeps`` 1).  Other scenes and profiling by stage
(``Profile.by_stage``) run the stages one by one; so does a solve phase by
phase (``solver.PHASE_BY_PHASE``: it keeps no steady solve).  The steps
run through the door (engine/fused/__init__.py): :meth:`SteadyStep.advance`
runs consecutive ones in one compiled loop (:func:`steady_loop`,
:func:`free_loop`).  The profile times the fused calls as the stages
``steady_step`` and ``contact_free_step``.
"""

from __future__ import annotations

import math
import time
from collections import namedtuple
from operator import is_

import numpy as np
from numba import njit

from physbench.engine.fused.borrow import Borrowed, BorrowedOf, borrow, borrowed
from physbench.engine.broadstage import BroadPhase, FusedBroad, Motion, _broad_step
from physbench.engine.collision import NarrowPhase, box
from physbench.engine.collision.collide import collide_packed
from physbench.engine.contact import phases, prepare
from physbench.engine.control import EventMode
from physbench.engine.ccd_end import end_pose_candidates
from physbench.engine.geometry import Pairs
from physbench.engine.flight import integrate_positions, max_turn_sq
from physbench.engine.forces import FORCES
from physbench.engine.integrate import IntegratePositions, IntegrateVelocities
from physbench.engine import solver as _S
from physbench.engine.pack import Pack
from physbench.engine.solver import Solve
from physbench.engine.state import Contacts, _commit_packed, record_packed
from physbench.engine.fused.gyro import gyro_items, split_gyro
from physbench.engine.fused.part import flight_part
from physbench.engine.fused.stops import rolling_candidate

DONE, FAIL, CCD = 0, 1, 2
#: no try pending after a loop (it stopped before trying the next step)
NONE = -1
#: :func:`steady_loop`'s ``band`` where the step has no sparse direct start
#: to check (the largest int64: no band storage exceeds it)
NO_BAND_CHECK = 2 ** 63 - 1

#: the profile's name of the fused call
NAME = "steady_step"
#: ... and of the contact-free call (free_kernel)
FREE_NAME = "contact_free_step"

#: the plan's settings the steady kernels read (:meth:`SteadyStep._constants`):
#: the broad phase's sweep and speculative margin, the static count, the
#: solve's relaxation, direct start, friction, rolling friction, iterations,
#: active-set passes, direct-start row limit, the box narrow phase's
#: edge-face points
SteadyFlags = namedtuple("SteadyFlags", ("sap", "speculative", "n_statics", "relax_on", "direct", "friction",
                                         "rolling", "iterations", "passes", "max_rows", "face_points"))
#: ... and its reals: the broad margin (m), the solve's threshold, Baumgarte
#: factor, slop, resting speed, slip tolerance, the friction-stop gate's
#: largest residual, the end-pose check's limit (m), the rolling tolerance
SteadyReals = namedtuple("SteadyReals", ("margin", "thr", "beta", "slop", "resting", "slip_tol", "stop_max_res",
                                         "lim", "roll_tol"))
#: the rotation split the loops check before each step (:func:`_turns`):
#: whether the plan splits at all, its limit (rad), the boxes (k,) and the
#: axisymmetric bodies (j,) whose turn counts
Turn = namedtuple("Turn", ("split", "limit", "boxes", "axisym"))
#: the steady step's settings Pack: the flags, the reals, the gyroscopic
#: stage's arrays (engine.gyroscopic.Gyro), the rotation split
SteadyPlan = namedtuple("SteadyPlan", ("flags", "reals", "gy", "turn"))


@njit(cache=True, inline="always")
def _fly_and_collide(kb, kf, kbr, kcol, h, flags, reals, gy):
    """What :func:`steady_kernel` and :func:`free_kernel` run first (inlined
    into both: engine/README.md "Compiled code and compile time"): the
    flight part (engine/fused/part.py, with the gyroscopic stage ``gy``),
    the broad phase and the narrow phase (the packs and the plan's
    :data:`SteadyFlags` and :data:`SteadyReals` as theirs).
    Returns (ok, body pairs, plane pairs, static-box pairs, contacts); ok
    False when a kept buffer is short (nothing of the state written: the
    staged step recomputes everything from its start)."""
    b, f = kb.items, kf.items
    br = kbr.items
    buf = br.buf
    flight_part(b, f, gy, h)
    # broadstage.BroadPhase
    nbb, npl, nsb = _broad_step(flags.sap, br.shapes, br.statics,
                                Motion(x0=b.x, R0=b.R0, q1=b.q1, x1=b.x1, R1=br.R1, v0=b.v, v1=b.V, u=f.u_lin, w0=b.w,
                                       w1=b.W), buf, h, reals.margin)
    if nbb < 0 or npl < 0 or nsb < 0:
        return False, 0, 0, 0, 0
    # collision.NarrowPhase (Collider.run)
    col = kcol.items
    if col.W.perm.shape[0] < max(nbb, npl, nsb):
        return False, 0, 0, 0, 0
    cnt, need_k, need_s = collide_packed(kcol, b.x, b.R0, buf.pi[:nbb], buf.pj[:nbb], br.margins, buf.bp[:npl],
                                         buf.pk[:npl], buf.bs[:nsb], buf.sk[:nsb], bool(True), reals.margin,
                                         buf.sweep if flags.speculative else br.no_sweep, flags.face_points)
    return need_k <= col.A.c.shape[0] and need_s <= col.slot.g.shape[0], nbb, npl, nsb, cnt


@njit(cache=True)
def _end_pose_moved(kbr, x, q, x1, q1, lim, has_fast, nbb, npl, nsb):
    """The CCD stage's end-pose check (engine.ccd.end_pose_pairs) inside a
    fused call: True when a pair moved far enough between the start pose
    (x, q) and the end pose (x1, q1) to need the end-pose collision, less
    the pairs whose end pose provably holds no missed impact
    (ccd_end.end_pose_clear: a rolling ball, a sliding block finish in the
    fused call, tests/test_ccd_end_clear.py).  The candidates are left in
    the pack's buffers (ci, cj, cbp, cpk, cbs, csk) for the CCD stage."""
    br = kbr.items
    buf = br.buf
    sweep, fast, fast_min = buf.sweep, br.fast, br.fast_min
    if has_fast:
        for k in range(sweep.shape[0]):
            fast[k] = sweep[k] > fast_min[k]
    nb, nplm, nsm = end_pose_candidates(x, q, x1, q1, br.shapes, br.statics, lim, has_fast, fast,
                                        Pairs(pi=buf.pi[:nbb], pj=buf.pj[:nbb], bp=buf.bp[:npl], pk=buf.pk[:npl],
                                              bs=buf.bs[:nsb], sk=buf.sk[:nsb]), br.end)
    return nb + nplm + nsm > 0


@njit(cache=True)
def _move_and_commit(kb, kf, kbr, h, lim, ccd_check, has_fast, nbb, npl, nsb):
    """What :func:`steady_kernel` and :func:`free_kernel` run last: the
    position update (integrate.IntegratePositions), the CCD stage's
    end-pose check when the step has it, and the commit
    (state.Context.commit) when nothing moved far enough to need the CCD
    stage.  Returns DONE or CCD (nothing committed)."""
    b, f = kb.items, kf.items
    integrate_positions(b.x1, b.q1, f.V, f.W, f.v_free, f.w_free, f.vp, f.wp, h, f.ig.lever)
    if ccd_check and _end_pose_moved(kbr, b.x, b.q, b.x1, b.q1, lim, has_fast, nbb, npl, nsb):
        return CCD
    _commit_packed(kb)
    return DONE


@njit(cache=True, inline="always")
def steady_kernel(kall, ko, kq, h, step_flags):
    """One steady (mini-)step of length ``h`` (module doc).  ``kall`` the
    packs that stay from step to step (kb, kf, kbr, kcol, kc, kx, kt, kw,
    kk, key, idx, ks), borrowed (:func:`steady_pack`); ``ko``, ``kq`` the
    warm caches read and written, which rotate.  Inlined into
    :func:`steady_loop`, its one caller and the fused step's one compiled
    entry (engine/README.md "Compiled code and compile time").  ``kb`` the
    context's begin/commit pack (engine.state.Context.kept), ``kf`` the
    free flight's, ``kbr`` the broad phase's and the end-pose check's,
    ``kcol`` the narrow phase's (engine.collision.dispatch.Collider), ``kc``
    ... ``idx`` the solve stage's (phases.classify_stage); ``ks`` the
    plan's settings (a Pack of the flags and reals tuples), ``step_flags``
    this step's (:meth:`SteadyStep.run`).  Returns
    (status, body pairs, plane pairs, static-box pairs, contacts, sweeps,
    residual)."""
    kb, kf, kbr, kcol, kc, kx, kt, kw, kk, key, idx, ks = kall.items
    plan = ks.items
    flags, reals, gy = plan.flags, plan.reals, plan.gy
    warm_any, warm_on, store_on, stops_gate, ccd_check, has_fast = step_flags
    lever = kf.items.ig.lever
    key, idx = borrow((key, idx))  # (no reference counting: engine/fused/borrow.py)
    ok, nbb, npl, nsb, cnt = _fly_and_collide(kb, kf, kbr, kcol, h, flags, reals, gy)
    if not ok or cnt > kcol.items.out.a.shape[0] or (cnt != 0 and cnt != key.shape[0]):
        return FAIL, 0, 0, 0, 0, 0, 0.0
    sweeps = 0
    residual = 0.0
    if cnt != 0:  # (no contact: Solve.__call__ leaves the velocities; SteadyStep.settle)
        # solver.Solve (the staged solve after prepare.classify)
        settings = phases.Settings(n_statics=flags.n_statics, lever=lever, thr=reals.thr, beta=reals.beta,
                                   slop=reals.slop, friction=flags.friction, rolling=flags.rolling,
                                   direct=flags.direct, resting=reals.resting, max_rows=flags.max_rows,
                                   passes=flags.passes, slip_tol=reals.slip_tol, iterations=flags.iterations,
                                   relax_on=flags.relax_on)
        nimp, solved, sweeps, residual, pushed, sliding_any = phases.classify_stage(
            kc, kx, kt, kw, ko, kq, kk, key, idx, h, settings, warm_any, bool(True), warm_on, store_on)
        if not solved:
            return FAIL, 0, 0, 0, 0, 0, 0.0
        rolling, slip_tol, roll_tol = flags.rolling, reals.slip_tol, reals.roll_tol
        if stops_gate and residual <= reals.stop_max_res and (sliding_any or rolling):
            # Solve._finish: Rows.stop_times opens with this gate (its
            # rolling half: steady_stops)
            wi = kw.items
            ti = kt.items
            rw = wi.rows
            vt0 = wi.vt0
            if prepare.stop_candidate(ti.pid, rw.lam_n, rw.Jt, wi.U, ti.pab, vt0, slip_tol, bool(False), vt0,
                                      rw.rt[:0], roll_tol) or (rolling and rolling_candidate(
                                          ti.pid, rw.lam_n, rw.Jt, wi.U, wi.U0, ti.pab, ti.mur, roll_tol,
                                          vt0.shape[0])):
                return FAIL, 0, 0, 0, 0, 0, 0.0
    status = _move_and_commit(kb, kf, kbr, h, reals.lim, ccd_check, has_fast, nbb, npl, nsb)
    return status, nbb, npl, nsb, cnt, sweeps, residual


@njit(cache=True, inline="always")
def free_kernel(kall, h, step_flags):
    """One contact-free (mini-)step of length ``h`` as one call: what
    :func:`steady_kernel` runs when its narrow phase finds no contact (no
    solve: ``Solve.__call__`` leaves the velocities), for a stage that keeps
    no steady solve (``Solve._fast`` None: the scene's first steps, a flight
    after an impact).  The packs as :func:`steady_kernel`'s; FAIL when the
    narrow phase finds a contact (nothing of the state written).  Returns
    what :func:`steady_kernel` does (no sweeps, residual 0).  ``kall``:
    (kb, kf, kbr, kcol, ks) borrowed (:func:`free_pack`)."""
    kb, kf, kbr, kcol, ks = kall.items
    plan = ks.items
    warm_any, warm_on, store_on, stops_gate, ccd_check, has_fast = step_flags
    ok, nbb, npl, nsb, cnt = _fly_and_collide(kb, kf, kbr, kcol, h, plan.flags, plan.reals, plan.gy)
    if not ok or cnt != 0:
        return FAIL, 0, 0, 0, 0, 0, 0.0
    # (the velocities are the free flight's: v1 - v_free = 0, vp = wp = 0)
    status = _move_and_commit(kb, kf, kbr, h, plan.reals.lim, ccd_check, has_fast, nbb, npl, nsb)
    return status, nbb, npl, nsb, 0, 0, 0.0


@njit(cache=True)
def _turns(turn, kb, h):
    """Whether the next step would be split for fast rotation
    (pipeline._parts: not sqrt(w2) h > limit means one part); ``turn`` a
    :data:`Turn`, ``kb`` the context's begin/commit Pack."""
    if not turn.split:
        return False
    b = kb.items
    w2 = max_turn_sq(b.w, b.q, turn.boxes, turn.axisym)
    return math.sqrt(w2) * h > turn.limit


@njit(cache=True)
def free_loop(n, kall, h, flags, t, rec_on, pos, quat, vel, angvel):
    """Up to ``n`` steps of :func:`free_kernel` (its packs kb, kf, kbr,
    kcol, ks as one, ``kall``), each step's state into row k of the record
    blocks when ``rec_on`` (:meth:`SteadyStep.advance`); stops before a step split for
    fast rotation and at a try that is not DONE.  Returns (steps done, time
    after them, the status of the try that stopped it or NONE, the last
    try's pairs (body, plane, static box)).  The contact-free call's one
    compiled entry: one step from Python is ``n`` = 1
    (:meth:`SteadyStep.run`)."""
    pos, quat, vel, angvel = borrow((pos, quat, vel, angvel))  # (engine/fused/borrow.py)
    kb, kf, kbr, kcol, ks = kall.items
    turn = ks.items.turn
    nbb = npl = nsb = 0
    for k in range(n):
        if _turns(turn, kb, h):
            return k, t, NONE, 0, 0, 0
        status, nbb, npl, nsb, cnt, sw, res = free_kernel(kall, h, flags)
        if status != DONE:
            return k, t, status, nbb, npl, nsb
        t += h
        record_packed(kb, k, rec_on, pos, quat, vel, angvel)
    return n, t, NONE, nbb, npl, nsb


@njit(cache=True)
def steady_loop(n, kall, ko, kq1, kq2, h, flags0, flags1, band, t, rec_on, pos, quat, vel, angvel):
    """Up to ``n`` steps of :func:`steady_kernel`, the packs that stay as
    one, ``kall`` (kb, kf, kbr, kcol, kc, kx, kt, kw, kk, key, idx, ks) as
    its (a Pack argument costs ~2.5 us of dispatch): the first warm-starts
    from ``ko`` with ``flags0``, step k stores into ``kq1`` (k even) or
    ``kq2`` (k odd) and the next warm-starts from it with ``flags1`` (the
    pool's rotation, :meth:`engine.contact.warm.WarmPool.slot`).  Stops
    before a step split for fast rotation, at a try that is not DONE (not
    counted), after a step with no contact (the solve's bookkeeping
    changes: SteadyStep.settle) and after one whose sparse direct start
    needed more band storage than ``band`` (Solve._grow_band; the largest
    int64 where the step has no sparse direct start).  The rotation split
    is the settings Pack's (:data:`SteadyPlan`).  Returns (steps done, time after them, steps solved
    (with contacts), the sum of their sweeps but the last's, the last's
    sweeps and residual, whether the last step had no contact, then the
    stopping try's status or NONE and the last try's result as
    steady_kernel's (pairs, contacts, sweeps, residual)).  The steady
    call's one compiled entry: one step from Python is ``n`` = 1
    (:meth:`SteadyStep.run`), and :func:`steady_kernel` is inlined at its
    one call site here (two entries compiled the whole step twice)."""
    solved = 0
    sw_sum = 0
    sw_last = 0
    res_last = 0.0
    kb, kf, kbr, kcol, kc, kx, kt, kw, kk, key, idx, ks = kall.items
    turn = ks.items.turn
    dwi = kw.items.dwi
    pos, quat, vel, angvel = borrow((pos, quat, vel, angvel))  # (engine/fused/borrow.py; steady_kernel borrows key, idx)
    nbb = npl = nsb = cnt = sw = 0
    res = 0.0
    for k in range(n):
        if _turns(turn, kb, h):
            return k, t, solved, sw_sum, sw_last, res_last, False, NONE, 0, 0, 0, 0, 0, 0.0
        if k == 0:
            kr, ks_, fl = ko, kq1, flags0
        elif k % 2 == 1:
            kr, ks_, fl = kq1, kq2, flags1
        else:
            kr, ks_, fl = kq2, kq1, flags1
        status, nbb, npl, nsb, cnt, sw, res = steady_kernel(kall, kr, ks_, h, fl)
        if status != DONE:
            return k, t, solved, sw_sum, sw_last, res_last, False, status, nbb, npl, nsb, cnt, sw, res
        t += h
        record_packed(kb, k, rec_on, pos, quat, vel, angvel)
        if cnt == 0:
            return k + 1, t, solved, sw_sum, sw_last, res_last, True, NONE, nbb, npl, nsb, cnt, sw, res
        if solved:
            sw_sum += sw_last
        solved += 1
        sw_last = sw
        res_last = res
        if dwi[0] > band:
            return k + 1, t, solved, sw_sum, sw_last, res_last, False, NONE, nbb, npl, nsb, cnt, sw, res
    return n, t, solved, sw_sum, sw_last, res_last, False, NONE, nbb, npl, nsb, cnt, sw, res


_NO_REC: dict = {}


def _no_records(nb: int) -> tuple:
    """Empty record blocks (0, nb, 3|4) for a loop that records nothing,
    made once per body count."""
    z = _NO_REC.get(nb)
    if z is None:
        z = _NO_REC[nb] = (np.zeros((0, nb, 3)), np.zeros((0, nb, 4)), np.zeros((0, nb, 3)), np.zeros((0, nb, 3)))
    return z


def blocks(rec, nb: int) -> tuple:
    """(record?, the four blocks) for the loops: ``rec`` when given, else
    empty blocks."""
    if rec is not None:
        return True, tuple(rec)
    return False, _no_records(nb)


def blocks_usable(rec) -> bool:
    """Whether the loops can write the record blocks ``rec`` themselves
    (float64, C-contiguous, writeable: what they are compiled for)."""
    return all(a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable for a in rec)


def record_blocks(n: int, nb: int) -> tuple:
    """Record blocks for ``n`` steps of ``nb`` bodies (pos, quat, vel,
    angvel), NaN-filled."""
    return (np.full((n, nb, 3), np.nan), np.full((n, nb, 4), np.nan), np.full((n, nb, 3), np.nan),
            np.full((n, nb, 3), np.nan))


@njit(cache=True)
def steady_pack(kb, kf, kbr, kcol, kc, kx, kt, kw, kk, key, idx, ks):
    """:func:`steady_kernel`'s ``kall``: the packs borrowed (valid while they
    live: :class:`engine.borrow.BorrowedOf` holds them)."""
    return Pack((borrowed(kb), borrowed(kf), borrowed(kbr), borrowed(kcol), borrowed(kc), borrowed(kx), borrowed(kt),
                 borrowed(kw), borrowed(kk), key, idx, ks))


@njit(cache=True)
def free_pack(kb, kf, kbr, kcol, ks):
    """:func:`free_kernel`'s ``kall`` (as :func:`steady_pack`)."""
    return Pack((borrowed(kb), borrowed(kf), borrowed(kbr), borrowed(kcol), ks))


class SteadyStep:
    """The plan's fused steady step (module doc) over the pipeline's stage
    objects, whose kept buffers it reads and writes."""

    def __init__(self, model, forces, fly, broad, narrow, solve, pos, ccd, gyro=None, turn=None):
        #: the gyroscopic stage's arrays (engine/fused/gyro.py), the
        #: settings Pack's ``gy``
        self.gyro = gyro_items(gyro)
        self.fly, self.broad, self.narrow, self.solve, self.pos, self.ccd = fly, broad, narrow, solve, pos, ccd
        n = model.n
        s = model.settings
        self.lim = float(s["correction_slop"]) + _miss_tol()
        frac = ccd.fraction if ccd is not None else None
        self.has_fast = frac is not None
        # (n,): a body is fast when its sweep exceeds this (ccd.CCD: fraction x min extent)
        self.fast_min = np.array(frac * model.min_extent if frac is not None else np.zeros(n), float)
        self.fast = np.zeros(n, np.bool_)
        self.no_sweep = np.zeros(n)
        self._kbr = self._kbr_key = None
        self._ks = self._ks_key = None
        self._empty = Contacts.empty()
        #: the warm caches' packs handed to the fused calls, borrowed
        #: (engine/fused/borrow.py)
        self.borrowed = Borrowed()
        #: the packs that stay as one, borrowed (steady_kernel, free_kernel and
        #: the loops over steps)
        self.kall = BorrowedOf(steady_pack)
        self.kfree = BorrowedOf(free_pack)
        #: the rotation split's limit as the loops read it (:func:`_turns`;
        #: ``turn`` the plan's, pipeline._turn_limit: None never splits)
        self.turn = (Turn(False, 0.0, np.zeros(0, np.int64), np.zeros(0, np.int64)) if turn is None else Turn(
            True, float(turn[0]), np.ascontiguousarray(turn[1], np.int64), np.ascontiguousarray(turn[2], np.int64)))

    @staticmethod
    def build(model, stages, turn=None) -> "SteadyStep | None":
        """The fused step for ``stages`` when the scene has only stages it
        covers (module doc) and steps whole (``substeps`` 1), else None:
        decided once, with the plan (``turn`` its rotation split's limit)."""
        from physbench.engine.ccd import CCD as CCDStage, Impact

        if model.substeps != 1:
            return None
        forces = [s for s in stages if s.family == "forces"]
        if any(type(s) not in FORCES for s in forces):
            return None
        gyro, rest = split_gyro([s for s in stages if s.family != "forces"])
        want = [IntegrateVelocities, BroadPhase, NarrowPhase, Solve, IntegratePositions]
        tail = [type(s) for s in rest[len(want):]]
        if [type(s) for s in rest[:len(want)]] != want or tail not in ([], [CCDStage, Impact]):
            return None
        fly, broad, narrow, solve, pos = rest[:5]
        if solve.correction == "baumgarte":
            return None
        return SteadyStep(model, forces, fly, broad, narrow, solve, pos, rest[5] if tail else None, gyro, turn)

    def _broad_pack(self, ctx):
        """The broad phase's, the narrow phase's margins and the end-pose
        check's arrays as one Pack, kept while none of its buffers grew."""
        b, col = self.broad, self.narrow.collider
        P = b.pairs
        ep = ctx.end_pose_buffers(max(P.pi.size, b.bp.size, b.bs.size))
        key = (ctx, P.pi, P.order, P.state, P.grid, b.bp, b.bs, col.margins, ep)
        if self._kbr_key is None or not all(map(is_, key, self._kbr_key)):
            self._kbr = Pack(FusedBroad(shapes=b.shapes, statics=b.statics, R1=b.R1, buf=b.buffers(ctx),
                                        margins=col.margins, no_sweep=self.no_sweep, fast=self.fast,
                                        fast_min=self.fast_min, end=ep))
            self._kbr_key = key
        return self._kbr

    def _settings(self, model):
        """The kernel's flags and reals that do not change from step to step
        as one Pack, kept while the solver's policy constants (read at each
        call, as the stage reads them) stay."""
        key = (_S.ACTIVE_SET_PASSES, _S.DIRECT_MAX_ROWS, _S.RESTING_SPEED, _S.SLIP_TOL, _S.STOP_MAX_RESIDUAL,
               _S.ROLL_TOL, box.EDGE_FACE_POINTS)
        if key != self._ks_key:
            flags, reals = self._constants(model)
            self._ks = Pack(SteadyPlan(flags=flags, reals=reals, gy=self.gyro, turn=self.turn))
            self._ks_key = key
        return self._ks

    def _constants(self, model):
        b, solve = self.broad, self.solve
        flags = SteadyFlags(sap=b.sap, speculative=self.narrow.speculative, n_statics=model.n_statics,
                            relax_on=solve.correction != "none", direct=solve.direct, friction=solve.friction,
                            rolling=bool(solve.friction and model.rolling), iterations=solve.iterations,
                            passes=_S.ACTIVE_SET_PASSES, max_rows=_S.DIRECT_MAX_ROWS,
                            face_points=box.EDGE_FACE_POINTS)
        reals = SteadyReals(margin=b.margin, thr=solve.thr, beta=solve.beta, slop=solve.slop,
                            resting=_S.RESTING_SPEED, slip_tol=_S.SLIP_TOL, stop_max_res=_S.STOP_MAX_RESIDUAL,
                            lim=self.lim, roll_tol=_S.ROLL_TOL)
        return flags, reals

    def flags(self, ctx, warm_any: bool, warm_on: bool, store_on: bool) -> tuple:
        """The kernels' ``step_flags`` for a (mini-)step of ``ctx``."""
        solve = self.solve
        return (warm_any, warm_on, store_on, bool(solve.friction and ctx.stop_allowed and solve.stops),
                self.ccd is not None and ctx.event_mode is EventMode.EVENT, self.has_fast)

    def steady_args(self, model, state, ctx, h: float):
        """What :func:`steady_kernel` takes for a (mini-)step of length
        ``h`` from ``state`` (as a tuple, after its pose packs) and what
        :meth:`settle` needs: (kc .. idx, step flags, the warm cache
        written, its store flag, the contacts), or None where the solve
        keeps no steady solve or its contacts are not the narrow phase's
        last."""
        solve = self.solve
        store_on = solve.store_on(model, h)
        args = solve.fused_args(model, state, ctx, h, store_on)
        if args is None:
            return None
        kc, kx, kt, kw, ko, kq, kk, key, idx, warm_any, warm_on, out = args
        c = solve._fast[2]
        if self.narrow.collider.last_contacts(c.m) is not c:
            return None
        b = self.borrowed.of
        return ((kc, kx, kt, kw, b(ko), b(kq), kk, key, idx), self.flags(ctx, warm_any, warm_on, store_on), out,
                store_on, c)

    def packs(self, model, state, ctx) -> tuple:
        """The kernels' first four packs (begin/commit, free flight, broad
        phase, narrow phase) and the settings' (module doc)."""
        return (ctx.kept(state), self.fly.pack(ctx), self._broad_pack(ctx), self.narrow.collider.packed(),
                self._settings(model))

    def prime(self, model, state, ctx) -> None:
        """At build (pipeline.prepare): the packs and the contact-free
        call's borrowed pack, which a fresh engine's first try would make
        (~50-100 us once); the steady call's waits for a steady solve."""
        kb, kf, kbr, kcol, ks = self.packs(model, state, ctx)
        self.kfree.of((kb, kf, kbr, kcol, ks))

    def call(self) -> str:
        """The compiled call :meth:`advance` makes next (its profile name):
        the steady call while the solve keeps a steady solve, else the
        contact-free call."""
        return FREE_NAME if self.solve._fast is None else NAME

    def kept(self):
        """The kept steady solve's contact graph (its engine.solver.Topology,
        one object per graph while the solve's cache holds it) or None: what
        the door's Backoff compares a failed try's with."""
        fast = self.solve._fast
        return None if fast is None else fast[1]

    def advance(self, model, state, ctx, plan, n: int, rec) -> tuple[int, int]:
        """Up to ``n`` steps from ``state`` in one compiled loop
        (:func:`steady_loop` while the solve keeps a steady solve, else
        :func:`free_loop`), each step's state into row k of the blocks
        ``rec`` when given: the door's step (engine/fused/__init__.py).
        Returns (steps done, the status of the try that stopped the loop,
        settled, or NONE).  With CCD the context holds what the CCD stage
        reads, and the staged step goes on from it; with FAIL nothing of
        that step was kept.  The bookkeeping between the steps --
        ``Solve.fused_finish``, the warm-start pool's rotation, the
        profile's calls and counters, ``state.t`` and ``state.steps``,
        ``ctx.contacts`` -- comes out as with one staged step per step
        (tests/test_engine_loop.py); the profile's seconds are the loop's."""
        t0 = time.perf_counter()
        h = float(model.h)
        # the context as the staged step begins a step
        ctx.missed_skip.clear()
        ctx.warm0 = old = state.warm
        ctx.event_mode = (EventMode.EVENT if plan.impact is not None and plan.max_events > 0
                          else EventMode.SPECULATIVE)
        ctx.reset(state, h)
        ctx.stop_allowed = plan.stops
        rec_on, blocks_ = blocks(rec, model.n)
        solve = self.solve
        if solve._fast is None:
            return self._free_advance(model, state, ctx, plan, n, h, rec_on, blocks_, t0)
        a = self.steady_args(model, state, ctx, h)
        if a is None:
            return 0, NONE
        sp, flags0, out1, store_on, c = a
        if not store_on:
            return 0, NONE
        out2, kall = self._loop_packs(model, state, ctx, sp, out1, c)
        if solve._warm.slot((c.m, int(solve._fast[1].uniq_codes.size)), out2, out2) is not out1:
            n = min(n, 2)
        outs = (out1, out2)
        flags1 = self.flags(ctx, True, bool(solve.warm), True)
        band = int(solve._band) if solve.direct and c.m > _S.DIRECT_MAX_ROWS else NO_BAND_CHECK
        ko, kq1 = sp[4], sp[5]
        b = self.borrowed.of
        r = steady_loop(n, kall, ko, kq1, b(out2.kept), h, flags0, flags1, band, float(state.t), rec_on, *blocks_)
        done, t, solved, sw_sum, sw_last, res_last, free_last, pend = r[:8]
        if done:
            state.t = t
            state.steps += done
            if solved:
                last = done - 2 if free_last else done - 1
                self.finish_solve(model, state, ctx, outs[last % 2], True, int(sw_last), float(res_last))
                if solved > 1:
                    ctx.profile.count("contact_rows", c.m * (solved - 1))
                    ctx.profile.count("solver_sweeps", int(sw_sum))
                ctx.contacts = c
            ctx.warm0 = old if done == 1 else outs[(done - 2) % 2]
            if free_last:
                self._no_contact(state, ctx)
                solve._fast = None
        if pend != NONE:
            self._restart(state, ctx, plan, h)
            pend = self.settle(model, state, ctx, r[7:], outs[done % 2], True, c)
        calls = done + (pend != NONE)
        if calls:
            ctx.profile.charge(NAME, calls, time.perf_counter() - t0)
        return done, pend

    def _loop_packs(self, model, state, ctx, sp, out1, c) -> tuple:
        """The steady loop's second warm cache and its one borrowed pack
        (``sp``, ``out1``, ``c`` from :meth:`steady_args`): (out2, kall).
        The pool's rotation: step k stores into (out1, out2)[k % 2]
        (WarmPool.slot)."""
        solve = self.solve
        out2 = solve._warm.slot((c.m, int(solve._fast[1].uniq_codes.size)), out1, out1)
        kb, kf, kbr, kcol, ks = self.packs(model, state, ctx)
        kc, kx, kt, kw, ko, kq1, kk, key, idx = sp
        return out2, self.kall.of((kb, kf, kbr, kcol, kc, kx, kt, kw, kk, key, idx, ks))

    def prime_steady(self, model, state, ctx) -> None:
        """At build, after the solve kept a steady solve of the start's
        contacts (pipeline._prime_start), with the state and context as a
        fresh engine's: the steady loop's warm caches and borrowed packs,
        which the door's first try would make (the same objects): the
        second warm cache's Pack and its borrowed twin among them (10-20 us
        of a fresh engine's first call, measured on friction.ball_rolls:
        tests/test_engine_prepare.py::test_the_first_steady_call_makes_no_pack)."""
        if self.solve._fast is None:
            return
        a = self.steady_args(model, state, ctx, float(model.h))
        if a is not None and a[3]:
            out2, _ = self._loop_packs(model, state, ctx, a[0], a[2], a[4])
            self.borrowed.of(out2.kept)

    def _free_advance(self, model, state, ctx, plan, n, h, rec_on, blocks_, t0) -> tuple[int, int]:
        """:meth:`advance` by the contact-free call (:func:`free_loop`)."""
        kb, kf, kbr, kcol, ks = self.packs(model, state, ctx)
        done, t, pend, nbb, npl, nsb = free_loop(n, self.kfree.of((kb, kf, kbr, kcol, ks)), h,
                                                 self.flags(ctx, False, False, False), float(state.t), rec_on,
                                                 *blocks_)
        if done:
            state.t = t
            state.steps += done
            self._no_contact(state, ctx)
        if pend != NONE:
            self._restart(state, ctx, plan, h)
            pend = self.settle_free(model, state, ctx, (pend, nbb, npl, nsb))
        calls = done + (pend != NONE)
        if calls:
            ctx.profile.charge(FREE_NAME, calls, time.perf_counter() - t0)
        return done, pend

    def _restart(self, state, ctx, plan, h: float) -> None:
        """The context as the staged step begins the step a loop stopped
        at (its try is settled into it: a CCD status goes on from there)."""
        ctx.missed_skip.clear()
        ctx.warm0 = state.warm
        ctx.event_mode = (EventMode.EVENT if plan.impact is not None and plan.max_events > 0
                          else EventMode.SPECULATIVE)
        ctx.reset(state, h)
        ctx.stop_allowed = plan.stops

    def settle(self, model, state, ctx, res, out, store_on: bool, c) -> int:
        """After :func:`steady_kernel` returned ``res``: the solve's
        bookkeeping (``Solve.fused_finish``, or a step with no contact:
        :meth:`_no_contact`), the pairs the CCD stage reads.  Returns the
        status (FAIL: nothing to do, the staged step runs the step)."""
        status, nbb, npl, nsb, cnt, sw, r = res
        if status == FAIL:
            return status
        if cnt:
            self.finish_solve(model, state, ctx, out, store_on, int(sw), float(r))
            ctx.contacts = c
        else:
            # no contact: what Solve.__call__ does then; the next steps try
            # the contact-free call until a solve is steady again
            self._no_contact(state, ctx)
            self.solve._fast = None
        if status == CCD:
            self._pairs(ctx, nbb, npl, nsb)
        return status

    def finish_solve(self, model, state, ctx, out, store_on: bool, sweeps: int, residual: float) -> None:
        """``Solve.fused_finish`` after a fused solve."""
        self.solve.fused_finish(model, state, ctx, out, store_on, sweeps, residual)

    def settle_free(self, model, state, ctx, res) -> int:
        """After :func:`free_kernel` returned ``res`` (status and pairs, as
        :meth:`settle`)."""
        status, nbb, npl, nsb = res
        if status == FAIL:
            return status
        self._no_contact(state, ctx)
        if status == CCD:
            self._pairs(ctx, nbb, npl, nsb)
        return status

    def _no_contact(self, state, ctx) -> None:
        """The context and state after a (mini-)step with no contact, as
        the narrow phase and Solve.__call__ leave them: no contacts, no
        rows, no warm-start cache."""
        c = self.narrow.collider.last_contacts(0)
        ctx.contacts = c if c is not None else self._empty
        ctx.rows = None
        state.warm = None

    def _pairs(self, ctx, nbb: int, npl: int, nsb: int) -> None:
        """The broad phase's pairs of the call, for the CCD stage."""
        b = self.broad
        P = b.pairs
        ctx.pairs_i, ctx.pairs_j = P.pi[:nbb], P.pj[:nbb]
        ctx.plane_pairs = (b.bp[:npl], b.pk[:npl])
        ctx.sbox_pairs = (b.bs[:nsb], b.sk[:nsb])


def _miss_tol() -> float:
    from physbench.engine.ccd import MISS_TOL

    return float(MISS_TOL)


def warm_scene(shapes: tuple = ("box", "box"), plane: bool = True, static_box: bool = False):
    """A small contact scene (an engine.model.SceneInput) whose first steps
    compile (or load) the fused steps with the step's argument types
    (engine.pipeline.build_pipeline, once per process and broad phase)
    and the kernels of its shape-pair families: bodies of ``shapes`` (0.1 m sizes, body z up) stacked in
    touching contact along z under gravity -- on a plane at z = 0 when
    ``plane``, else falling together --, and a static box far off when
    ``static_box``.
    Its families (:func:`engine.collision.collide.families`) are those of
    any scene with the same shapes (each twice when the other scene has two
    of it), statics and planes.  The default: two boxes resting on a plane."""
    from physbench.engine.model import SceneInput

    n = len(shapes)
    f = np.zeros
    r = np.array([0.1 if s in ("sphere", "capsule", "cylinder") else 0.0 for s in shapes])
    hl = np.array([0.1 if s in ("capsule", "cylinder") else 0.0 for s in shapes])
    he = np.array([[0.1, 0.1, 0.1] if s == "box" else [0.0, 0.0, 0.0] for s in shapes])
    # half-height along body z: a sphere's radius, a box's half-extent, a
    # capsule's half-length plus radius, a cylinder's half-length
    up = np.array([{"sphere": 0.1, "box": 0.1, "capsule": 0.2, "cylinder": 0.1}[s] for s in shapes])
    x = f((n, 3))
    x[:, 2] = 2 * np.cumsum(up) - up
    q = f((n, 4))
    q[:, 0] = 1.0
    one = np.ones((1, 1))
    statics = (("plane",) if plane else ()) + (("box",) if static_box else ())
    ns = len(statics)
    normal = np.array([[0.0, 0.0, 1.0]] * ns).reshape(ns, 3)
    pos = f((ns, 3))
    pos[[i for i, s in enumerate(statics) if s == "box"], 0] = 100.0
    hs = np.array([[0.0, 0.0, 0.0] if s == "plane" else [0.1, 0.1, 0.1] for s in statics]).reshape(ns, 3)
    rot = np.tile([1.0, 0.0, 0.0, 0.0], (ns, 1))
    return SceneInput(
        dt=1 / 240, effects=frozenset({"gravity", "contact", "friction"}),
        gravity=np.array([0.0, 0.0, -9.81]), shape=tuple(shapes), mass=np.ones(n),
        inertia=np.full((n, 3), 1 / 150), radius=r, half_extents=he, half_length=hl,
        bound_radius=np.array([np.sqrt((he[i] ** 2).sum()) + r[i] + hl[i] if shapes[i] != "cylinder" else np.hypot(r[i], hl[i])
                                for i in range(n)]), min_extent=np.full(n, 0.1), drag_linear=f(n),
        drag_quadratic=f(n), material=np.zeros(n, np.int64), x=x, q=q, v=f((n, 3)), w=f((n, 3)),
        static_shape=statics, static_material=np.zeros(ns, np.int64), static_normal=normal, static_offset=f(ns),
        static_position=pos, static_orientation=rot, static_half_extents=hs, spring_a=np.zeros(0, np.int64),
        spring_b=np.zeros(0, np.int64), spring_anchor_a=f((0, 3)), spring_anchor_b=f((0, 3)), spring_k=f(0),
        spring_rest=f(0), spring_c=f(0), pair_e=0.0 * one, pair_mus=0.5 * one, pair_muk=0.5 * one,
        pair_mur=0.0 * one)


def warm_scene_for(model):
    """:func:`warm_scene` with ``model``'s shape-pair families and broad
    phase: each of its shapes (twice where it has two bodies of it), a
    plane and a static box where it has them; where the model's broad
    phase sweeps (more than ``SAP_MIN_BODIES`` bodies), as many more bodies
    of its most frequent shape."""
    from physbench.engine.broadstage import SAP_MIN_BODIES, uses_sap
    from physbench.engine.model import BOX, CAPSULE, CYLINDER, SPHERE

    names = {SPHERE: "sphere", BOX: "box", CAPSULE: "capsule", CYLINDER: "cylinder"}
    shape = np.asarray(model.shape)
    shapes = []
    for code in sorted(set(int(c) for c in shape)):
        shapes += [names[code]] * min(2, int(np.sum(shape == code)))
    if uses_sap(model):
        most = names[int(np.argmax(np.bincount(shape.astype(np.int64), minlength=4)))]
        shapes += [most] * (SAP_MIN_BODIES + 1 - len(shapes))
    return warm_scene(tuple(shapes), plane=model.plane_normal.shape[0] > 0, static_box=model.sbox_pos.shape[0] > 0)
