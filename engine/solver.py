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

The solve runs as named phases (engine/contact/__init__.py lists them):
classify and prepare (engine/contact/prepare.py, rows.py), warm start
(warm.py), direct start (linalg.py; its policy, the module constants
``DIRECT_MAX_ROWS``, ``ACTIVE_SET_PASSES`` and ``dense_direct_solve`` here,
read at each call), solve (gauss_seidel.py), friction stops, position
correction, store (warm.py); restitution targets are prepared with the
rows, and impacts are resolved at their time of impact (impact.py).
"""

from __future__ import annotations

import functools

import numpy as np

from physbench.engine.contact import gauss_seidel, phases, prepare
from physbench.engine.control import EventMode, Impacts
from physbench.engine.contact.impact import impact_solve  # noqa: F401
from physbench.engine.contact.rows import (  # noqa: F401  (the solver's names, as before the split)
    ACTIVE_SET_PASSES,
    DIRECT_MAX_ROWS,
    RESTING_SPEED,
    ROLL_TOL,
    SLIP_TOL,
    STOP_MAX_RESIDUAL,
    TOUCH_TOL,
    Rows,
    Topology,
    _pad,
    _pair_codes,
    _pair_codes_abs,
    colour_order,
    dense_direct_solve,
    point_normal_velocity,
)
from physbench.engine.contact.packs import Cache, Classified, ContactArrays, Pose, RowArrays, Settings, Topo, Work
from physbench.engine.contact.rows import _take_rows
from physbench.engine.contact.warm import WarmCache, WarmPool, store_forces, warm_start  # noqa: F401
from physbench.engine.pack import KeptPack, Pack
from physbench.engine.profile import Stage
from physbench.engine.state import Contacts

STOP_MIN_REST = 1e-6  # a friction stop this close to a step's end (fraction of it) does not cut the step
WARM_MIN_STEP = 1e-3  # (sub)steps shorter than this fraction of the model's step cache no forces


_NO_I = np.zeros(0, np.int64)
#: an empty warm cache (WarmCache.packed)
_NO_CACHE = Cache(code=_NO_I, loc=np.zeros((0, 3)), fn=np.zeros(0), pairs=_NO_I, ft=np.zeros((0, 3)), tw=np.zeros(0),
                  rr=np.zeros((0, 3)), touch=np.zeros(0, np.bool_))
_NO_P = np.zeros((0, 2), np.int64)
_NO_F = np.zeros((0, 3, 12))
_NO_LT = np.zeros((0, 3))
_NO_D = np.zeros(0)
_NO_B = np.zeros(0, np.bool_)
_NO_T = np.zeros((0, 2, 3))
#: run the solve's phases one by one from Python instead of the one fused
#: compiled call: the same bits
#: (tests/test_engine_contact.py::test_fused_solve_is_bit_identical_to_the_phase_by_phase_solve),
#: and the path on which a test can spy on the direct-start policies
#: (``dense_direct_solve``, ``Rows.sparse_normal_solve``)
PHASE_BY_PHASE = False
_AR = np.arange(64)
_AR.flags.writeable = False


def _arange(m: int) -> np.ndarray:
    """0..m-1 as a read-only view of a shared range grown geometrically."""
    global _AR
    if _AR.size < m:
        _AR = np.arange(max(m, 2 * _AR.size))
        _AR.flags.writeable = False
    return _AR[:m]


#: topologies a Solve stage keeps (the contact graphs of the last steps and
#: of the time-of-impact re-runs); cleared when full
TOPOLOGY_CACHE = 8


class Solve(Stage):
    """Sequential-impulse contact solve on the end-of-step velocities (see
    module doc).  Classifies contacts (touching, speculative, impact),
    leaves impacts to the CCD stage in ``ctx.impacts``
    (:class:`engine.control.Impacts`), solves the rest with warm starting, then the split-impulse
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
        self._warm = WarmPool()
        #: the fused path's kept state: (topology, work views, Rows, work Pack)
        #: of the last solve, and the (arrays, Pack) of the pose and velocities
        self._prep = None
        self._kc = KeptPack()
        #: (classification views, topology) of the last compiled solve when
        #: it had no impact row (the next steady step's one call), and the
        #: (classification views, mean velocities, Pack) that call reads
        self._fast = None
        self._kx = KeptPack()
        self._kk = KeptPack()
        #: the settings phases.solve_stage reads (:meth:`_settings`), kept
        #: while the policy constants they hold stay
        self._settings_key = self._settings_nt = None
        #: band storage (floats) of the sparse direct start's work array
        #: (grown by :meth:`_grow_band`)
        self._band = 0

    def prime(self, model, state, ctx, main) -> None:
        """At build (engine.pipeline.prepare): the empty warm cache's Pack."""
        _no_cache()

    def topology(self, model, codes: np.ndarray, c: Contacts, sel: np.ndarray) -> Topology:
        """The (cached) topology of the rows ``sel`` of ``c`` with pair codes
        ``codes`` (which identify (a, b, sidx) row by row)."""
        key = codes.tobytes()
        topo = self._topos.get(key)
        if topo is None:
            if len(self._topos) >= TOPOLOGY_CACHE:
                self._topos.clear()
            topo = self._topos[key] = Topology(model, c.a[sel], c.b[sel], c.sidx[sel], self.friction, True)
            topo.key = codes.copy()
        return topo

    def _solve_phases(self, model, state, ctx, rows, topo, old, h, sc):
        """Slip classes, warm start, direct start and sweeps of ``rows``
        phase by phase from Python (the direct start through the module's
        ``dense_direct_solve``).  Returns (U (n+1, 6) the solved end
        velocities, U0 (n+1, 6) the start velocities or None, vt0 (np, 2)
        the patches' start tangential velocities or None); ctx.v, ctx.w
        hold the end velocities."""
        n = model.n
        U0 = vt0 = None
        if self.friction:
            U0 = sc.take("U0", (n + 1, 6))
            U0[:n, :3] = state.v
            U0[:n, 3:] = state.w
            U0[n] = 0.0
            vt0 = sc.take("vt0", (rows.np, 2))
            slip = sc.take("slip0", (rows.np,), np.bool_)
            prepare.sliding(rows.Jt, U0, topo.pab, rows.r_twist, SLIP_TOL, vt0, slip)
            rows.set_slip(slip)
        U = sc.take("U", (n + 1, 6))
        U[:, :3] = ctx.v
        U[:, 3:] = ctx.w
        if self.warm and old:
            warm_start(model, old, rows, h)
        if self.direct:
            rows.direct_normal_guess(U, DIRECT_MAX_ROWS, ACTIVE_SET_PASSES, dense_direct_solve)
        if self.warm or self.direct:
            rows.warm_start(U)
        rows.sweeps = rows.solve_friction_regimes(U, self.iterations)
        Rows.unpack(U, ctx.v, ctx.w)
        return U, U0, vt0

    def _stage_phases(self, model, state, ctx, c, sel, topo, touching, vn, old, h, sc):
        """The stage after classification phase by phase from Python (the
        flag ``PHASE_BY_PHASE``): rows, targets, :meth:`_solve_phases`,
        relax, store (into ``state.warm`` when the step is long enough).
        Returns (rows, U, U0, vt0, rows pushed out)."""
        n = model.n
        rows = Rows(model, state.x, ctx.Iinv0, c, self.friction, sel=sel, topo=topo, scratch=sc, R0=ctx.R0)
        idx = rows.idx  # the rows' contacts (rows are sorted by colour)
        # touching rows: v1n >= 0 (memoryless: a target that depends on the
        # previous step's velocity feeds solver noise back into the stack);
        # separated rows: the end pose may just close the gap
        bias = sc.take("bias", (rows.m,))
        pushed = prepare.targets(idx, touching, vn, c.gap, c.e, h, self.c, self.thr, self.beta, self.slop,
                                 rows.target, bias)
        U, U0, vt0 = self._solve_phases(model, state, ctx, rows, topo, old, h, sc)
        if self.correction != "none" and pushed:
            # push-out velocities for penetration beyond the slop, solved on
            # separate (pseudo) velocities; they move positions by h vp
            # (split_impulse discards them afterwards)
            phases.relax(ctx.vp, ctx.wp, sc.take("Up", (n + 1, 6)), topo.ab, rows.J, rows.M, rows.mn,
                         sc.take("lam_p", (rows.m,)), bias, self.iterations, 1e-7, n, rows.sweep_work())
        if h >= WARM_MIN_STEP * model.h:
            state.warm = self._warm.store(rows, h, touching, old, ctx.warm0)
        return rows, U, U0, vt0, pushed

    def _solve_compiled(self, model, state, ctx, c, sel, nimp, topo, touching, vn, old, h, sc, store_on):
        """The stage after classification as one compiled call
        (:func:`engine.contact.phases.solve_stage`: rows, targets, solve,
        relax, store; the same bits as :meth:`_stage_phases`), its kept
        arrays handed over as a few :class:`engine.pack.Pack` s.  The Rows
        object and the work pack are kept while the topology and the work
        views stay (a resting stack: every step)."""
        n = model.n
        f = self.friction
        m = topo.m
        npch = topo.np if f else 0
        rolling = f and bool(model.rolling)
        nr = 5 if rolling else 3
        dsz = _direct_size(self.direct, n, m, self._band)
        views = sc.group(("stage", n, m, npch, nr, f, dsz), lambda: _take_stage(sc, n, m, npch, nr, f, dsz))
        idx = topo.order if nimp == 0 else sel[topo.order]  # = Rows.idx
        prep = self._prep
        if prep is not None and prep[0] is topo and prep[1] is views:
            rows, kw = prep[2], prep[3]
            rows.rebind(c, state.x, idx)
        else:
            rows = Rows(model, state.x, ctx.Iinv0, c, f, sel=sel, topo=topo, scratch=sc, R0=ctx.R0,
                        views=views[:16], prepared=True, idx=idx)
            kw = Pack(_work_items(views, f))
            self._prep = (topo, views, rows, kw, ("stage", n, m, npch, nr, f, dsz))
        kt = topo.__dict__.get("_kept")
        if kt is None:
            kt = topo._kept = Pack(_topology_items(topo, f, rolling))
        warm_on = bool(self.warm and old)
        ko = old.kept if warm_on else _no_cache()
        out = self._warm.slot((m, topo.uniq_codes.size), old, ctx.warm0) if store_on else None
        sw, rows.residual, pushed = phases.solve_stage(
            self._pose(model, state, ctx), kt, kw, ko, out.kept if store_on else _no_cache(), self._contacts(c), idx,
            touching, vn, h, self._settings(model), warm_on, store_on)
        rows.sweeps = int(sw)
        if store_on:
            state.warm = out
        U, U0, vt0 = views[16], views[17], views[19]
        self._grow_band(views, m)
        return rows, U, (U0 if f else None), (vt0 if f else None), pushed

    def _grow_band(self, views, m: int) -> None:
        """After a solve: when the sparse direct start needed more band
        storage than its work array holds (it took a new array, the same
        bits), the next work views hold at least twice as much and the
        kept steady solve is dropped (it holds the old views), so a steady
        state allocates nothing (tests/test_engine_steady.py::
        test_steady_direct_start_allocates_nothing)."""
        if self.direct and m > DIRECT_MAX_ROWS:
            need = int(views[-1][0])
            if need > self._band:
                self._band = max(need, 2 * self._band)
                self._prep = self._fast = None

    def _pose(self, model, state, ctx) -> Pack:
        """The pose and velocities as one Pack (see phases.solve_stage),
        kept while the arrays are the same objects (the context's, every
        step)."""
        return self._kc.of((state.x, ctx.Iinv0, ctx.R0, ctx.v, ctx.w, state.v, state.w, ctx.vp, ctx.wp, model.inv_mass,
                            model.bound_radius), lambda: Pack(Pose(
                                X=state.x, Iinv=ctx.Iinv0, R0=ctx.R0, V=ctx.v, W=ctx.w, V0=state.v, W0=state.w,
                                Vp=ctx.vp, Wp=ctx.wp, inv_mass=model.inv_mass, bound_radius=model.bound_radius)))

    def _contacts(self, c: Contacts) -> Pack:
        """The contacts' arrays read by phases.classify_stage as one Pack,
        kept while they are the same arrays (the narrow phase hands out the
        same Contacts while its count and buffers stay)."""
        return self._kk.of((c.a, c.b, c.sidx, c.point, c.normal, c.gap, c.e), lambda: Pack(ContactArrays(
            a=c.a, b=c.b, sidx=c.sidx, point=c.point, normal=c.normal, gap=c.gap, e=c.e)))

    def _classified(self, ctx, cl) -> Pack:
        """The classification's views ``cl`` and the free flight's mean
        velocities as one Pack (phases.classify_stage's ``kx``), kept while
        they are the same arrays."""
        vn, touching, impact, codes = cl
        return self._kx.of((ctx.u_lin, ctx.u_ang, vn, touching, impact, codes), lambda: Pack(Classified(
            UL=ctx.u_lin, UA=ctx.u_ang, vn=vn, touching=touching, impact=impact, codes=codes)))

    def _settings(self, model) -> Settings:
        """The solve's settings as phases.solve_stage reads them (the
        policy constants read at each call)."""
        f = self.friction
        key = (model.n_statics, bool(model.rolling), RESTING_SPEED, DIRECT_MAX_ROWS, ACTIVE_SET_PASSES, SLIP_TOL)
        if key != self._settings_key:
            self._settings_nt = Settings(
                n_statics=model.n_statics, lever=self.c, thr=self.thr, beta=self.beta, slop=self.slop, friction=f,
                rolling=f and bool(model.rolling), direct=self.direct, resting=RESTING_SPEED, max_rows=DIRECT_MAX_ROWS,
                passes=ACTIVE_SET_PASSES, slip_tol=SLIP_TOL, iterations=self.iterations,
                relax_on=self.correction != "none")
            self._settings_key = key
        return self._settings_nt

    def store_on(self, model, h: float) -> bool:
        """Whether a (sub)step of length h stores its forces for the next."""
        return h >= WARM_MIN_STEP * model.h

    def fused_args(self, model, state, ctx, h, store_on):
        """What :func:`engine.fused.steady.steady_kernel` hands to
        phases.classify_stage, assuming the step's contacts are the last
        solve's in number and graph (the kernel checks): (kc, kx, kt, kw,
        ko, kq, kk, key, idx, warm_any, warm_on, the warm cache written or
        None), or None when this stage keeps no steady solve (``_fast``
        None: the last one had an impact row or ran phase by phase)."""
        fast = self._fast
        if fast is None:
            return None
        cl, topo, c = fast
        prep = self._prep
        sc = ctx.scratch
        if (prep[0] is not topo or sc.peek(prep[4]) is not prep[1]
                or sc.peek(("classify", c.m)) is not cl):
            return None
        return self._steady_args(model, state, ctx, cl, topo, c, store_on)

    def _steady_args(self, model, state, ctx, cl, topo, c, store_on) -> tuple:
        """The kept packs phases.classify_stage reads in a steady solve
        (:meth:`fused_args`) and the flags from the
        state's warm cache: (kc, kx, kt, kw, ko, kq, kk, key, idx,
        warm_any, warm_on, the warm cache written or None)."""
        old = state.warm
        warm_any = old is not None
        out = self._warm.slot((c.m, topo.uniq_codes.size), old, ctx.warm0) if store_on else None
        return (self._pose(model, state, ctx), self._classified(ctx, cl), topo._kept, self._prep[3],
                old.kept if warm_any else _no_cache(), out.kept if store_on else _no_cache(), self._contacts(c),
                topo.key, topo.order, warm_any, bool(self.warm and warm_any), out)

    def fused_finish(self, model, state, ctx, out, store_on, sweeps, residual) -> None:
        """After a steady solve in the fused step (engine/fused/steady.py):
        what :meth:`__call__` does after the solve (:meth:`_finish`),
        without the friction-stop test: the kernel ran its gate (sliding
        and rolling, engine/fused/stops.py) and found no candidate, and the test opens
        for any rolling contact and needs the end velocities, which the
        fused call does not hand back.  No Baumgarte bias: the fused step's
        plan has none."""
        cl, topo, c = self._fast
        rows = self._steady_rows(state, c, topo.order, residual, sweeps, store_on, out)
        self._finish(model, ctx, rows, None, None, None, False, ctx.h, store_on, state, False, stop_test=False)
        self._grow_band(self._prep[1], rows.m)

    def _steady_rows(self, state, c, idx, residual, sweeps, store_on, out):
        """The kept Rows of a steady solve rebound to ``c`` (rows ``idx``)
        with its residual and sweeps; the warm cache written (``out``)
        becomes the state's when ``store_on``."""
        rows = self._prep[2]
        rows.rebind(c, state.x, idx)
        rows.residual = residual
        rows.sweeps = int(sweeps)
        if store_on:
            state.warm = out
        return rows

    def __call__(self, model, state, ctx) -> None:
        n = model.n
        h = ctx.h
        c = ctx.contacts
        ctx.rows = None
        ctx.impacts = None
        if c is None or c.m == 0:
            state.warm = None
            self._fast = None  # (no steady solve kept: the fused step tries its contact-free call)
            return
        m = c.m
        sc = ctx.scratch
        # normal velocities at the end of the free flight, at the start of
        # the step and of the mean motion (vn_free, vn0, un), and the
        # classification (see prepare.classify): in a pair that pressed last
        # step (a persistent, resting contact), closing rows are mostly
        # solver noise and gravity gained within the step, not impacts --
        # unless the point itself did not press, it was already approaching
        # faster than the threshold, and a speculative row could not stop it
        # without sinking beyond the slop (the far end of a bar rotating
        # down onto a slab: tests/test_engine_collision.py; not the idle rim
        # points of a cylinder standing on its cap, nor the rattling corners
        # of a Gauss-Seidel-only box column)
        cl = sc.group(
            ("classify", m), lambda: (sc.take("vn", (3 * m,)).reshape(3, m), sc.take("touching", (m,), np.bool_),
                                      sc.take("impact", (m,), np.bool_), sc.take("codes", (m,), np.int64)))
        vn, touching, impact, codes_all = cl
        old = state.warm
        store_on = h >= WARM_MIN_STEP * model.h
        drop = ctx.event_mode is EventMode.DROP and ctx.drop_rows is not None
        if not (drop and self.ccd == "events" and ctx.drop_rows.size == m):
            nimp = prepare.classify(self._pose(model, state, ctx), self._classified(ctx, cl), self._contacts(c),
                                    old.kept if old else _no_cache(), model.n_statics, h, self.thr, self.c, self.slop,
                                    bool(old))
        else:
            # a rerun of the time-of-impact search whose rows are all the
            # step's impact rows (a lone pair's impact: billiards, a ball
            # landing): every row is left out whatever the classification
            # (below: keep = ~impact), so there is nothing to classify or
            # solve -- what the path below ends in for sel.size == 0
            state.warm = None
            return
        vn_free, vn0, un = vn[0], vn[1], vn[2]
        gap = c.gap
        if drop:
            # a rerun of the time-of-impact search: the rows left out are
            # the step's impact rows, whatever tau.  Re-deciding them with
            # the rerun's length kept a row whose linear estimate fell after
            # tau (its point curving in earlier) as a speculative row, which
            # held the point just clear: the gap was a plateau near 0 that
            # jumped below 0 at the estimate, Newton crawled on it and
            # bisection converged on the jump (30 iterations, each a rerun
            # of the whole step)
            impact[:] = False
            impact[ctx.drop_rows] = True
            nimp = ctx.drop_rows.size
        if nimp == 0:
            sel = _arange(m)
        else:
            sel = None
            keep = ~impact
        if nimp:
            if self.ccd == "toi":
                fast = np.zeros(n + 1, bool)
                fast[:n] = ctx.sweep > self.ccd_fraction * model.min_extent
                handled = impact & (fast[c.a] | fast[c.b])
            elif self.ccd == "events":
                handled = impact
            else:
                handled = np.zeros_like(impact)
            if ctx.event_mode is EventMode.EVENT and handled.any():
                idx = np.flatnonzero(handled)
                ctx.impacts = Impacts(idx, gap[idx] / np.maximum(-un[idx], 1e-300))
            elif ctx.event_mode is EventMode.SPECULATIVE:
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
        topo = self.topology(model, codes_all[sel] if nimp else codes_all, c, sel)
        if PHASE_BY_PHASE:
            rows, U, U0, vt0, pushed = self._stage_phases(model, state, ctx, c, sel, topo, touching, vn, old, h, sc)
        else:
            rows, U, U0, vt0, pushed = self._solve_compiled(model, state, ctx, c, sel, nimp, topo, touching, vn, old, h,
                                                         sc, store_on)
            # the kept steady solve: the fused step (engine/fused/steady.py)
            # runs the next steps as one call while the contact graph and
            # these packs stay
            self._fast = (cl, topo, c) if nimp == 0 and self._prep is not None else None
        self._finish(model, ctx, rows, U, U0, vt0, pushed, h, store_on, state, bool(self.friction and rows.slip.any()))

    def _finish(self, model, ctx, rows, U, U0, vt0, pushed, h, store_on, state, sliding_any,
                stop_test: bool = True) -> None:
        """After the solve: the friction-stop test (unless ``stop_test`` is
        False), Baumgarte's bias, ``ctx.rows`` and the counters
        (``sliding_any``: a patch slides)."""
        n = model.n
        # (only from a solve that (nearly) converged: the end velocities of
        # one cut short far from convergence are solver noise, and a
        # Gauss-Seidel-only column with 5 sweeps "stopped" 422 times in 5 s
        # and gained 20 % energy)
        if (stop_test and self.friction and ctx.stop_allowed and self.stops and rows.residual <= STOP_MAX_RESIDUAL
                and (sliding_any or rows.rolling)):
            wr0 = rows.patch_velocity(U0, slice(3, 5)) if rows.rolling else None
            tau = rows.stop_times(U, vt0, wr0, h, self.iterations)
            if tau is not None:
                t = float(tau.min())
                if t < h * (1.0 - STOP_MIN_REST):
                    ctx.stop = t
        if self.correction == "baumgarte" and pushed:
            # the classic bias: the push-out velocities stay in the real
            # velocity too (it injects energy)
            ctx.v += ctx.vp
            ctx.w += ctx.wp
            ctx.v_free += ctx.vp[:n]  # not a contact impulse for the position update: h vp moves it
            ctx.w_free += ctx.wp[:n]
        ctx.rows = rows
        if not store_on:
            # a sliver of a step (the rest of a step after a late time of
            # impact): its impulses are impulsive, not forces -- cached as
            # lambda / h they came back next step as a huge impulse (a box
            # of column_5 spun up to 5e5 rad/s after a 7e-12 s remainder)
            state.warm = None
        ctx.profile.count("contact_rows", rows.m)
        ctx.profile.count("solver_sweeps", rows.sweeps)




def _take_stage(sc, n: int, m: int, npch: int, nr: int, friction: bool, direct: tuple = (0, 1)) -> tuple:
    """The fused stage's work arrays (views of the scratch ``sc``): the rows'
    (:func:`engine.contact.rows._take_rows`, 16), then U, U0, Ud (n+1, 6),
    vt0 (np, 2), pin_t (np,) bool, dir_t (np, 2), matched (np,) bool,
    r_direct (m,), bias (m,), Up (n+1, 6), lam_p (m,), touch_rows (m,) bool,
    wk (the sweeps' work array, engine.contact.gauss_seidel.work_size), dwf, dwi
    the direct start's float and int64 work arrays of lengths ``direct``
    (engine.contact.phases.direct_work_size; :func:`_direct_size`).  The pins
    are zeroed here, where the views are made: the fused solve never sets
    them (only :meth:`Rows.stop_times` pins, on its own arrays)."""
    return _take_rows(sc, m, npch, nr, friction) + (
        sc.take("U", (n + 1, 6)), sc.take("U0", (n + 1, 6)), sc.take("Ud", (n + 1, 6)), sc.take("vt0", (npch, 2)),
        sc.zeros("pin_t", (npch,), np.bool_), sc.zeros("dir_t", (npch, 2)), sc.take("matched", (npch,), np.bool_),
        sc.take("r_direct", (m,)), sc.take("bias", (m,)), sc.take("Up", (n + 1, 6)), sc.take("lam_p", (m,)),
        sc.take("touch_rows", (m,), np.bool_), sc.take("sweep_work", (gauss_seidel.work_size(m, npch, nr),)),
        sc.take("direct_f", (direct[0],)), sc.take("direct_i", (direct[1],), np.int64))


def _direct_size(direct: bool, n: int, m: int, band: int) -> tuple:
    """The direct start's work lengths (floats, ints) for m rows on n bodies
    (engine.contact.phases.direct_work_size; ``band`` floats of band
    storage for the sparse start above DIRECT_MAX_ROWS rows), (0, 1) without
    a direct start."""
    if not direct:
        return 0, 1
    nf, ni = phases.direct_work_size(m, n, m <= DIRECT_MAX_ROWS, band)
    return int(nf), int(ni)


def _work_items(views: tuple, friction: bool) -> tuple:
    """:func:`_take_stage`'s views as :func:`engine.contact.phases.solve_stage`
    reads them (empty arrays for the patches without friction)."""
    J, M, mn, loc, lam_n, target, P, N, rt, t, Jt, Mt, mt, lam_t, slip, mu = views[:16]
    if not friction:
        P = N = mt = lam_t = _NO_LT
        rt = mu = _NO_D
        t = _NO_T
        Jt = Mt = _NO_F
        slip = _NO_B
    rows = RowArrays(J=J, M=M, mn=mn, loc=loc, lam_n=lam_n, target=target, P=P, N=N, rt=rt, t=t, Jt=Jt, Mt=Mt, mt=mt,
                     lam_t=lam_t, slip=slip, mu=mu)
    U, U0, Ud, vt0, pin_t, dir_t, matched, r_direct, bias, Up, lam_p, touch_rows, wk, dwf, dwi = views[16:]
    return Work(rows=rows, U=U, U0=U0, Ud=Ud, vt0=vt0, pin_t=pin_t, dir_t=dir_t, matched=matched, r_direct=r_direct,
                bias=bias, Up=Up, lam_p=lam_p, touch_rows=touch_rows, wk=wk, dwf=dwf, dwi=dwi)


def _topology_items(topo: Topology, friction: bool, rolling: bool) -> tuple:
    """The topology's arrays as :func:`engine.contact.phases.solve_stage`
    reads them (after the first rows of ``topo`` set its pair coefficients)."""
    if friction:
        mur = topo.mur if topo.mur is not None else np.zeros(topo.np)
        fr = (topo.pid, topo.pa, topo.pb, topo.cnt, topo.pab)
        coef = (topo.mus, topo.muk, mur)
        uniq_pid = topo.uniq_pid
    else:
        fr = (_NO_I, _NO_I, _NO_I, _NO_D, _NO_P)
        coef = (_NO_D, _NO_D, _NO_D)
        uniq_pid = _NO_I
    pid, pa, pb, cnt, pab = fr
    mus, muk, mur = coef
    return Topo(ab=topo.ab, a=topo.a, b=topo.b, pid=pid, pa=pa, pb=pb, cnt=cnt, pab=pab, codes=topo.codes,
                code_order=topo.code_order, code_first=topo.code_first, uniq_pid=uniq_pid, mus=mus, muk=muk, mur=mur)


@functools.cache
def _no_cache() -> Pack:
    """The empty warm cache as a Pack (built on first use, then the same
    object: its arrays never change)."""
    return Pack(_NO_CACHE)
