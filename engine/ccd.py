"""Continuous collision: impacts resolved at their time of impact (TOI).

The solver hands the CCD stage the contacts that this step's motion would
close at an approach speed above the restitution threshold
(``ctx.impacts``: row indices and a first TOI estimate gap / approach speed,
exact for straight-line motion).  Which impacts are eligible depends on the
``ccd`` setting:

* ``events`` (default): every impact.  The step is split at the earliest
  one, so bounces happen at the right time and place, with no penetration.
* ``toi``: only impacts of *fast* bodies, whose surface moves more than
  ``ccd_motion_fraction`` of their smallest half-size in a step -- the
  classic tunnelling cure; slower impacts are discrete (penetrate, then
  bounce next step).
* ``off``: no time-of-impact search; the narrow phase has no speculative
  margin either, so thin walls can be tunnelled.

Because contacts are found with a margin that covers the bodies' motion in
the step (the broad phase's sweep), a fast body meets a thin wall's surface
in the narrow phase even when its start and end poses are both clear of it:
the 5 mm ball at 400 m/s cannot pass a 4 mm wall.

:func:`refine_toi` then finds the time of impact on the *integrated*
trajectory: it reruns the (mini-)step with length tau (from the same start
state, reusing the contacts), measures the pair's signed gap at the end pose
and updates tau by Newton's method on gap(tau) (slope = the closing speed),
safeguarded by bisection on the bracket [tau with gap > 0, tau with
gap < 0], until |gap| <= TOI_TOL -- or, touching (|gap| <= TOUCH_TOL),
until it stops converging faster than linearly (``toi_stalls``).  For
motion under constant forces the gap is smooth, and two or three
iterations reach ~1e-12 m.  The step loop
(pipeline.step) then commits the state at tau, applies the impact impulse
(:class:`Impact`) and continues with the rest of the step, up to
``ccd_max_events`` events per step (after that, impacts become speculative
contacts: no penetration, but no bounce).
"""

from __future__ import annotations

import numpy as np

from physbench.engine import flight
from physbench.engine.collision import box, collide_pairs
from physbench.engine.collision.dispatch import static_row
from physbench.engine.ccd_end import (FeatureContacts, lone_impact as _lone_impact, missed_any as _missed_any,
                                      missed_candidates)
from physbench.engine.ccd_kept import (_NO_CONTACTS, _NO_FAST, _NO_I, _Groups, _cand_buffer, _collider, _drop_codes,
                                       _geometry, _geometry_kept, _member, _pair_query, _rotations, _stable_features,
                                       end_pose_pairs)
from physbench.engine.ccd_gap import NO_FID, NO_P3, collide_gap as _collide_gap, gap as _gap
from physbench.engine.geometry import Pairs
from physbench.engine.profile import Stage
from physbench.engine.contact.impact import ImpactKept, impact_solve
from physbench.engine.control import Event, EventMode, ImpactPair, TimeOfImpact
from physbench.engine.contact.rows import TOUCH_TOL, _pair_codes, _pair_codes_abs

TOI_TOL = 1e-9  # m
TOI_MAX_ITER = 30  # Newton needs 2-3; bisection (the safeguard) halves the bracket each time
STALL_RATIO = 0.25  # |gap| falling by less than this factor per Newton step (within TOUCH_TOL) is a stall
#: depth (m) beyond the correction slop at which the end pose of a pair
#: that was apart at the start (or overlaps far from where it touched) is a
#: missed impact
MISS_TOL = 2e-4


class CCD(Stage):
    """Pick the earliest impact of the step as ``ctx.event``
    (:class:`engine.control.Event`: the first estimate of its time, the
    pair to follow -- its impact points in body a's frame, feature ids to
    follow (:func:`pair_gap`), whether it is a missed impact
    (:func:`missed_impacts`), the points to leave out -- and the step's
    other impact pairs)."""

    name = "ccd"
    family = "ccd"

    def __init__(self, model):
        # ccd = "toi": only fast bodies' impacts are events (module doc), so
        # only their pairs are checked for missed impacts too -- checking
        # every pair made each discrete collision of a falling sphere cloud
        # an event (1417 in 120 steps of spheres_1000, 49 ms a step in time
        # of impact searches that rerun the whole world)
        self.fraction = float(model.settings["ccd_motion_fraction"]) if model.setting("ccd") == "toi" else None

    def prime(self, model, state, ctx, main) -> None:
        """At build (engine.pipeline.prepare): what the stage and the
        search keep in the context, made now instead of at the first
        event -- the collider of the CCD and impact collisions and its
        Pack, the model's geometry, the end-pose check's buffers' Pack, the
        rotations' buffer, the candidate flags, the gap's work rows, the
        reruns' stage list."""
        _collider(model, ctx).packed()
        _geometry_kept(model, ctx)
        ctx.end_pose_kept(0)
        _rotations(ctx, state.q)
        _cand_buffer(ctx, 16)
        _gap_work(ctx, 8)
        _rerun_stages(ctx, main)

    def __call__(self, model, state, ctx) -> None:
        ctx.event = None
        if ctx.event_mode is not EventMode.EVENT:
            return
        if ctx.impacts is None and not (ctx.pairs_i.size or ctx.plane_pairs[0].size or ctx.sbox_pairs[0].size):
            return  # no impact row and no pair to check at the end pose (a body in flight)
        pairs = []
        t = ctx.h
        if ctx.impacts is not None:
            idx, tau = ctx.impacts.rows, ctx.impacts.tau
            c = ctx.contacts
            g = _geometry(model, ctx)
            # the earliest row j, its time, the rows' pair codes and, when
            # they are one pair (a lone impact: its rows are all of them,
            # in order), its impact points in body a's frame and feature
            # ids to follow: one compiled call.  The impact points of each
            # pair, in body a's frame: the refinement follows them, not
            # the pair's deepest point (which may be another end of the
            # body, already touching or resting within the slop)
            j, t, code, lone, a, b, sidx, loc, fids, stable = _lone_impact(
                idx, tau, float(ctx.h), c.a, c.b, c.sidx, c.point, c.fid, state.x, ctx.R0, g.shapes.shape,
                g.static_shape, model.n_statics)
            j, t = int(j), float(t)
            if lone:
                a, b, sidx = int(a), int(b), int(sidx)
                pairs.append(ImpactPair(a, b, sidx, loc, _follow_fids(model, a, b, sidx, fids, bool(stable)), False,
                                        None))
                firsts = ()
            else:
                of = _Groups(code)  # the code names the pair (a, b, sidx)
                firsts = [j] + [i for i in np.unique(code, return_index=True)[1] if code[i] != code[j]]
            for i in firsts:
                k = int(idx[i])
                a, b, sidx = int(c.a[k]), int(c.b[k]), int(c.sidx[k])
                same = idx[of(code[i])]
                pairs.append(ImpactPair(a, b, sidx, np.einsum("ki,ij->kj", c.point[same] - state.x[a], ctx.R0[a]),
                                        _follow_fids(model, a, b, sidx, c.fid[same]), False, None))
            skip = code
        else:
            skip = _NO_I
        fast = None if self.fraction is None else ctx.sweep > self.fraction * model.min_extent
        missed = missed_impacts(model, state, ctx, skip, fast)
        if missed:
            ctx.profile.count("missed_impacts", len(missed))
            if not pairs:
                t = missed[0][0]
            pairs += [ImpactPair(*m[1:6], True, m[6]) for m in missed]
        if pairs:
            ctx.event = Event(t, pairs[0], tuple(pairs[1:]))








def _follow_fids(model, a: int, b: int, sidx: int, fid: np.ndarray, stable: bool | None = None) -> np.ndarray | None:
    """The feature ids a search follows besides the points (see
    :func:`pair_gap`): ``fid`` where the pair's ids name material
    features (:func:`_stable_features`), else None.  ``stable``: whether
    they do, when known (ccd_end.lone_impact's answer; ``fid`` then sorted
    and distinct already)."""
    if stable is not None:
        return fid if stable else None
    if not _stable_features(model, a, b, sidx):
        return None
    # np.unique(fid) of a pair's few ids (sorted distinct int64), without
    # its ~10 us of calls
    return np.array(sorted(set(fid.tolist())), np.int64)


def missed_impacts(model, state, ctx, skip: np.ndarray, fast: np.ndarray | None = None) -> list:
    """Pairs that end the step overlapping although no contact row saw them
    closing: [(tau estimate s, a, b, static index, deepest points in body
    a's frame (k, 3), their feature ids to follow or None, points where the
    pair touched at the start in body a's frame (j, 3) or None), ...],
    earliest first.

    Impacts are found by extrapolating each contact row along its normal
    from the start pose.  Where the closest features change within the step
    that misses some: the end of a capsule spinning at 32 rad/s passed a
    box's edge (its row, along the edge normal, closed by 18.6 mm of its
    31.8 mm gap) and then came down on the face, ending 18 mm inside.  So
    the end pose is checked, for the pairs whose surfaces move far enough
    between the start and end poses to overlap by more than the tolerance
    (:func:`end_pose_pairs`: no resting contact
    is ever re-collided).  A pair that
    overlaps by more than the correction slop + ``MISS_TOL`` at the end, and
    either was apart at the start or overlaps there far from where it
    touched, is an impact whose time the refinement finds (first estimate:
    the gap interpolated linearly between the start and end poses), following
    those points.  ``skip``: pair codes already impacts; ``fast`` (n,) bool
    or None: only pairs with a body where it is True are checked."""
    slop = float(model.settings["correction_slop"])
    lim = slop + MISS_TOL
    # the common answer (no contact of the end pose can be one) from one
    # compiled call (ccd_end.missed_any); else the decision below, from
    # the start
    pi, pj = ctx.pairs_i, ctx.pairs_j
    bp, pk = ctx.plane_pairs
    bs, sk = ctx.sbox_pairs
    kout = ctx.end_pose_kept(max(pi.size, bp.size, bs.size))[1]
    col = _collider(model, ctx)
    k0 = ctx.contacts if ctx.contacts is not None and ctx.contacts.m > 0 else _NO_CONTACTS
    if not _missed_any(state.x, state.q, ctx.x1, ctx.q1, _geometry_kept(model, ctx), lim, fast is not None,
                       _NO_FAST if fast is None else fast, Pairs(pi=pi, pj=pj, bp=bp, pk=pk, bs=bs, sk=sk), kout,
                       col.packed(), (col.margins, ctx.no_sweep, box.EDGE_FACE_POINTS),
                       (model.n_statics,
                        FeatureContacts(a=k0.a, b=k0.b, sidx=k0.sidx, gap=k0.gap, point=k0.point, fid=k0.fid),
                        ctx.impacts.rows if ctx.impacts is not None else _NO_I, np.asarray(skip, np.int64),
                        _drop_codes(ctx), ctx.R0, TOUCH_TOL, _cand_buffer(ctx, 0))):
        return []
    moved = end_pose_pairs(model, state, ctx, lim, fast)
    if moved is None:
        return []
    (ci, cj), planes, sboxes, R1 = moved
    # every pair's margin -lim (-lim + 0 + 0: the same bits)
    c = _collider(model, ctx).run(ctx.x1, R1, ci, cj, planes, sboxes, margin=-lim, sweep=ctx.no_sweep)
    if c.m == 0:
        return []
    c0 = ctx.contacts
    has0 = c0 is not None and c0.m > 0
    # the contacts whose pairs may be missed impacts, compiled (a superset
    # of those the rule below finds); the rule runs over their pairs only
    # -- a landing layer of spheres overlaps the floor and its neighbours
    # beyond lim at the end pose, every pair touching at the start
    cand = _cand_buffer(ctx, c.m)
    g = _geometry(model, ctx)
    k0 = c0 if has0 else _NO_CONTACTS
    if not missed_candidates(model.n_statics,
                             FeatureContacts(a=c.a, b=c.b, sidx=c.sidx, gap=c.gap, point=c.point, fid=c.fid),
                             FeatureContacts(a=k0.a, b=k0.b, sidx=k0.sidx, gap=k0.gap, point=k0.point, fid=k0.fid),
                             ctx.impacts.rows if ctx.impacts is not None else _NO_I, np.asarray(skip, np.int64),
                             _drop_codes(ctx), ctx.x1, R1, state.x, ctx.R0, g.shapes, g.static_shape, TOUCH_TOL, lim,
                             cand):
        return []
    code = _pair_codes(model, c)
    cand_codes = set(code[cand[:c.m]].tolist())
    code0 = _pair_codes(model, c0) if has0 else np.zeros(0, np.int64)
    imp_row = np.zeros(code0.size, bool)
    if ctx.impacts is not None:
        imp_row[ctx.impacts.rows] = True
    out = []
    rows_of, rows0_of, skips = _Groups(code), _Groups(code0), set(skip.tolist())
    for u, first in zip(*np.unique(code, return_index=True)):
        if int(u) not in cand_codes or int(u) in ctx.missed_skip:
            continue
        is_imp = int(u) in skips
        rows = rows_of(u)
        g1 = float(c.gap[rows].min())
        at0 = rows0_of(u)
        g0 = float(c0.gap[at0].min()) if at0.size else np.inf
        a, b, sidx = int(c.a[first]), int(c.b[first]), int(c.sidx[first])
        loc = np.einsum("ki,ij->kj", c.point[rows] - ctx.x1[a], R1[a])
        excl = None
        if is_imp or not g0 > TOUCH_TOL:
            # touching at the start: a deep point near a point that touched
            # (in body a's frame, within the warm start's matching radius)
            # is that contact going on -- what its row misses there is the
            # second-order drift of curved surfaces sliding or rolling on
            # each other (a sphere under a box spinning at 20 rad/s: 0.3-1
            # mm a step at 1/240 s), which position correction removes; as
            # events these found no approach at their time of impact, and
            # cold-restarted the solve up to the event budget.  A deep
            # point far from every touching one is a new impact: the far
            # corner of a box tumbling at 14.5 rad/s onto another it
            # already touched ended 18 mm inside it at 1/60 s.
            # (the pair's impact rows are followed by their own event: a deep
            # point far from them and from every touching point is another
            # impact of the pair, which no row saw -- a box landing at 3 m/s
            # on a box it overlapped elsewhere by 1.6 mm swung a corner in
            # that way, and ended 13.7 mm inside when the pair, an impact
            # already, was not checked)
            near = at0[(c0.gap[at0] <= lim) | imp_row[at0]]
            p0 = np.einsum("ki,ij->kj", c0.point[near] - state.x[a], ctx.R0[a])
            tol = 0.1 * float(model.bound_radius[a]) + 1e-4
            d2 = np.sum((loc[:, None, :] - p0[None, :, :]) ** 2, axis=-1).min(axis=1, initial=np.inf)
            new = d2 > tol * tol
            if _stable_features(model, a, b, sidx):
                # a round feature (a sphere, a capsule's cap or segment)
                # rolling brings new material into contact, far from where
                # it touched in the body's frame (a capsule rolling at 1.8
                # m/s, 30 mm a step at 1/60 s): the same feature touching
                # at the start is the same contact
                new &= ~_member(c.fid[rows], c0.fid[near])
            if not new.any():
                continue
            loc = loc[new]
            rows = rows[new]
            g1 = float(c.gap[rows].min())
            excl = p0
        tau = ctx.h * g0 / (g0 - g1) if np.isfinite(g0) and g0 > 0.0 else 0.5 * ctx.h
        out.append((tau, a, b, sidx, loc, _follow_fids(model, a, b, sidx, c.fid[rows]), excl))
    out.sort(key=lambda m: m[0])
    return out


def _pairs_contacts(model, ctx, pairs) -> list:
    """Each pair's contacts at the context's end pose with no margin, as
    :func:`engine.collision.pair_contacts` gives them, from ONE collision
    call (the rotations computed once): a layer of spheres landing together
    is ~100 impact pairs checked at every time found, and one call per
    pair cost 1.7 ms a step of spheres_1000's 4.4."""
    n = model.n
    R1 = _rotations(ctx, ctx.q1)
    bi, bj, pa, prow, sa, srow = [], [], [], [], [], []
    for q in pairs:
        if q.sidx < 0:
            bi.append(min(q.a, q.b))
            bj.append(max(q.a, q.b))
            continue
        plane, row = static_row(model, q.sidx)
        (pa if plane else sa).append(q.a)
        (prow if plane else srow).append(row)
    arr = lambda v: np.array(v, np.int64)
    c = collide_pairs(model, ctx.x1, R1, arr(bi), arr(bj), (arr(pa), arr(prow)), (arr(sa), arr(srow)),
                      np.full(len(bi), np.inf), np.full(len(pa), np.inf), np.full(len(sa), np.inf),
                      _collider(model, ctx))
    rows_of = _Groups(_pair_codes(model, c))
    out = []
    for q in pairs:
        if q.sidx < 0:
            u = _pair_codes_abs(model, min(q.a, q.b), max(q.a, q.b), -1)
        else:
            u = _pair_codes_abs(model, q.a, n, q.sidx)
        out.append(c.take(rows_of(u)))
    return out


def pair_gap(model, ctx, a: int, b: int, sidx: int, loc: np.ndarray | None = None,
             exclude: np.ndarray | None = None, fids: np.ndarray | None = None,
             contacts=None) -> tuple[float, float]:
    """Signed gap (m) of a pair at the context's end pose and its rate of
    change (m/s, the normal relative velocity at the closest feature).

    ``loc`` (k, 3): body-a-frame points to follow -- the gap is then the
    least over the contacts nearest to each of them (one per point, within
    0.1 bounding radius + 0.1 mm, the warm start's matching radius; all
    contacts if none is that near).  A bar landing on one end while its other end still sits on the
    slab (gap slightly negative, within the correction slop) has its time
    of impact where the landing end arrives; the pair's least gap is
    negative at every tau and drove the search to tau ~ 0, so the step
    advanced by microseconds per event until the event budget ran out and
    the landing end was stopped as a speculative row, sinking h v / 2
    (18.7 mm at 1/60 s).

    ``exclude`` (j, 3): body-a-frame points where the pair touched at the
    start of the step (a missed impact in a touching pair,
    :func:`missed_impacts`): contacts within the matching radius of them
    are that contact going on, not the impact, and do not count (their
    overlap at the start drove the search to tau = 0: a box corner landing
    on a box it overlapped elsewhere by 1.6 mm sank 12.9 mm at 1/60 s).
    With no contact left the gap is +inf.

    ``fids``: feature ids (of a pair whose ids name material features,
    :func:`_stable_features`) whose contacts are followed too, wherever
    they lie.  The closest point of a capsule's segment slides along it as
    the capsule turns: a capsule whose end was the impact turned its middle
    down onto a box, the segment's contact left the matching radius of the
    point it started from, and the search followed only the end, which
    never closed -- it ran to the end of the step (30 iterations) with the
    segment 3.5 mm inside the box (a random pile at 1/240 s).

    ``contacts``: the pair's contacts at the end pose when already found
    (:func:`_pairs_contacts`)."""
    R1 = _rotations(ctx, ctx.q1)
    c = contacts
    tol = 0.1 * float(model.bound_radius[a]) + 1e-4
    loc = NO_P3 if loc is None else loc
    exclude = NO_P3 if exclude is None else exclude
    fids = NO_FID if fids is None else fids
    if c is None:
        # pair_contacts' collision of the pair (no margin), its arguments
        # kept per pair in the context (a search calls this at every
        # iterate): with the gap, one compiled call while the collider's
        # and the gap's buffers hold it (ccd_gap.collide_gap), else the
        # collider's run (which grows them) and the gap's call
        pi, pj, planes, sboxes, margins = _pair_query(model, ctx, a, b, sidx)
        col = _collider(model, ctx)
        wk = ctx.ccd.gap_work
        if wk is not None:
            done, g, vn = _collide_gap(col.packed(), ctx.x1, R1,
                                       Pairs(pi=pi, pj=pj, bp=planes[0], pk=planes[1], bs=sboxes[0], sk=sboxes[1]),
                                       margins, col.W.gm, box.EDGE_FACE_POINTS, ctx.v, ctx.w, a, tol, loc, exclude,
                                       fids, wk)
            if done:
                return g, vn
        c = col.run(ctx.x1, R1, pi, pj, planes, sboxes, margins)
    if c.m == 0:
        return np.inf, 0.0
    return _gap(c.point, c.gap, c.fid, c.a, c.b, c.normal, ctx.x1, R1[a], ctx.v, ctx.w, a, tol, loc, exclude, fids,
                _gap_work(ctx, c.m))


def _gap_work(ctx, m: int) -> np.ndarray:
    """The gap kernel's (>= m, 5) work rows, kept in the context."""
    wk = ctx.ccd.gap_work
    if wk is None or wk.shape[0] < m:
        wk = ctx.ccd.gap_work = np.empty((2 * m, 5))
    return wk


def warm_up() -> None:
    """Compile (or load) the end-pose check's kernel, the followed pair's
    gap kernel and the impact solver's propagation with the step's argument types (see
    engine/jit.py)."""
    from physbench.engine import ccd_end, ccd_gap
    from physbench.engine.contact import impact

    ccd_end.warm_up()
    ccd_gap.warm_up()
    flight.q2m(np.zeros((1, 4)), np.empty((1, 3, 3)))  # _rotations (else loaded at the first event, ~8 ms)
    impact.warm_up()


def refine_toi(model, state, ctx, main_stages, profile) -> float:
    """Rerun the step to the time of impact (see module doc).  Leaves the
    context holding the rerun to the returned tau (s).

    The search follows the earliest-estimated impact pair.  Every impact
    row of the step is left out of the reruns (they must not be constrained
    on the way), so at the time found the step's other impact pairs are
    checked too: one already through the surface there (its impact came
    first after all, or the followed pair never closed: a pair the solve
    holds off through other contacts hovers just clear, and the search ran
    to the end of the step while a box corner elsewhere went 18.5 mm into
    the floor) becomes the followed pair, searched for before that time.
    ``ctx.toi``: the pair followed in the end and whether it was still
    clear at the end of the (mini-)step (:class:`engine.control.TimeOfImpact`)."""
    h_full = ctx.h
    ev = ctx.event
    tau, pair, others = ev.tau, ev.pair, ev.others
    lo, hi = 0.0, h_full
    ctx.reuse_contacts = True
    ctx.drop_rows = ctx.impacts.rows if ctx.impacts is not None else np.zeros(0, np.int64)
    clear = False
    try:
        for _ in range(len(others) + 1):
            tau, clear = _search(model, state, ctx, main_stages, profile, pair, tau, lo, hi, h_full)
            if not others:
                break
            worst, g_worst = None, -TOI_TOL
            for q, c in zip(others, _pairs_contacts(model, ctx, others)):
                if c.m == 0 or not c.gap.min() < g_worst:
                    continue  # pair_gap's gap is one of c.gap (or inf): not below g_worst
                g, _ = pair_gap(model, ctx, q.a, q.b, q.sidx, q.loc, q.excl, q.fids, contacts=c)
                if g < g_worst:
                    worst, g_worst = q, g
            if worst is None:
                break
            profile.count("toi_switches")
            others = tuple(q for q in others if q is not worst)
            pair = worst
            lo, hi = 0.0, tau
            tau = 0.5 * tau
    finally:
        ctx.reuse_contacts = False
        ctx.drop_rows = None
    ctx.toi = TimeOfImpact(pair, clear)
    return tau


def _search(model, state, ctx, main_stages, profile, pair, tau: float, lo: float, hi: float,
            h_full: float) -> tuple[float, bool]:
    """Newton's method on the followed pair's gap, safeguarded by bisection
    in [lo, hi] within the (mini-)step of length h_full (see module doc);
    leaves the context at the returned tau.  Returns (tau, whether the
    pair was still clear at the end of the (mini-)step)."""
    a, b, sidx, loc, fids, excl = pair.a, pair.b, pair.sidx, pair.loc, pair.fids, pair.excl
    thr = float(model.settings["restitution_threshold"])
    tau = min(max(tau, lo), hi)
    g = np.inf
    converged = False
    clear = False
    end_tried = tau >= h_full
    for it in range(TOI_MAX_ITER):
        g_prev = g
        _rerun(model, state, ctx, main_stages, profile, tau)
        g, vn = pair_gap(model, ctx, a, b, sidx, loc, excl, fids)
        profile.count("toi_iterations")
        if abs(g) <= TOI_TOL:
            converged = True
            break
        if abs(g) <= TOUCH_TOL and g * g_prev > 0.0 and abs(g) > STALL_RATIO * abs(g_prev):
            # touching, and the search closing in only linearly (Newton
            # overestimates the slope: the gap flattens at its root because
            # the rerun's other contacts move with tau -- a layer of
            # spheres landing on columns still settling into one another,
            # where each Newton step took off 30-40 % of the gap: up to 30
            # iterations from 1e-5 m to 1e-9 m, each a rerun of the whole
            # step).  Touching is what the impact solve needs (it takes
            # gaps up to 10 TOUCH_TOL); quadratic convergence -- free
            # flight, billiards, bullets -- still runs to TOI_TOL.
            profile.count("toi_stalls")
            converged = True
            break
        if abs(g) <= TOUCH_TOL and -vn <= thr:
            # touching and no longer approaching fast: the gap is flat
            # here (an end settling on the surface, sliding), where
            # Newton crawls; the solver takes it as a resting contact.
            # (On either side of the surface: a box corner held 2e-9 to
            # 1e-6 m above the floor by the solve kept bisection going for
            # all 30 iterations.)
            converged = True
            break
        if g > 0:
            if tau >= h_full:
                # still clear at the end of the (mini-)step: no impact in it
                converged = True
                clear = True
                break
            lo = tau
        else:
            hi = tau
        nxt = tau - g / vn if vn < 0 else None
        if nxt is None or not (lo < nxt < hi):
            # Newton's step leaves the bracket: bisect -- but try the end
            # of the step first when it is the bracket's untried upper end.
            # A point the solve holds just clear through other contacts
            # (a box rocking on an edge, its corner 1e-5 m above the floor)
            # never closes; bisection crept towards the end for all 30
            # iterations, each a rerun of the whole step
            # (tests/data/impact_search_corner_held_clear.toml: 32
            # iterations for 2 impacts, now 4)
            nxt = h_full if (g > 0 and hi >= h_full and not end_tried) else 0.5 * (lo + hi)
            end_tried |= nxt >= h_full
        if abs(nxt - tau) <= 1e-15 * h_full:
            break
        tau = nxt
    if not converged and g < -TOI_TOL and 1e-9 * h_full < lo < tau:
        # not converged (a kink where another followed point becomes the
        # deepest slows Newton down): commit at the last time that was
        # still clear, not inside the surface.  (Not after the settling
        # stop above: a box sliding 4 um above the floor, its corners
        # impacts by the step's mean motion, went back to the last clear
        # time, 0.05 ms in, 32 times over -- the whole event budget, after
        # which a box landing beside it was a speculative row and sank
        # 14 mm.)
        tau = lo
        _rerun(model, state, ctx, main_stages, profile, tau)
    return tau, clear


def _rerun(model, state, ctx, stages, profile, tau: float) -> None:
    mode = ctx.event_mode
    ctx.begin(model, state, tau)
    ctx.event_mode = EventMode.DROP  # the impact itself must not be constrained on the way
    for s in _rerun_stages(ctx, stages):
        profile.run(s, model, state, ctx)
    ctx.event_mode = mode


def _rerun_stages(ctx, stages) -> tuple:
    """The stages a rerun runs (all but the broad and narrow phases and the
    CCD stage: the contacts are the step's), kept in the context per stage
    list."""
    kept = ctx.ccd.rerun
    if kept is None or kept[0] is not stages:
        rerun = tuple(s for s in stages if s.family not in ("broadphase", "narrowphase", "ccd"))
        kept = ctx.ccd.rerun = (stages, rerun)
    return kept[1]


class Impact(Stage):
    """At a time of impact (state committed there): find the touching
    contacts among this step's broad-phase pairs and apply the impulsive
    response with restitution and friction (solver.impact_solve)."""

    name = "impact"
    family = "impact"

    def __init__(self, model):
        self.iterations = int(model.settings["iterations"])
        self.thr = float(model.settings["restitution_threshold"])
        self.friction = model.has("friction")
        self.plastic = str(model.settings["plastic_impacts"])
        self.kept = ImpactKept()
        self._margin = np.full(16, 10 * TOUCH_TOL)  # (>= pairs,) the collision's margins, never written

    def prime(self, model, state, ctx, main) -> None:
        """At build (engine.pipeline.prepare): the impact solve's kept
        inertia buffers."""
        self.kept.inertia(model.n)
        self.kept.inv_inertia(model)

    def __call__(self, model, state, ctx) -> None:
        R = _rotations(ctx, state.q)
        pi, pj = ctx.pairs_i, ctx.pairs_j
        # every margin 10 TOUCH_TOL: views of a kept buffer
        k = max(pi.size, ctx.plane_pairs[0].size, ctx.sbox_pairs[0].size)
        if self._margin.size < k:
            self._margin = np.full(max(k, 2 * self._margin.size), 10 * TOUCH_TOL)
        mg = self._margin
        c = collide_pairs(model, state.x, R, pi, pj, ctx.plane_pairs, ctx.sbox_pairs, mg[:pi.size],
                          mg[:ctx.plane_pairs[0].size], mg[:ctx.sbox_pairs[0].size], _collider(model, ctx))
        impact_solve(model, state, c, self.iterations, self.thr, self.friction, self.plastic, self.kept)
        profile = ctx.profile
        profile.count("impacts")
