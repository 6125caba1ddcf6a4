"""One schedule for a sweep: its points and its breaking-point searches on
one executor (``physbench sweep``; harness/execute.py's executors, or the
Dask one).

A sweep's points are independent of each other; a breaking-point search
(``[[limit]]``, harness/limits.py) is a chain: each value it evaluates
depends on the verdict of the last.  Run after the points, the searches
leave workers idle at the tail (two workers, one search left: one idles).
Here every search is a generator (:func:`harness.limits.search_items`)
held by the scheduler, with at most one round of evaluations in flight:
once every point has been handed out, a round holds up to
``jobs // unfinished searches`` items (at least one; one before that),
the value the chain needs next, its other step phases and the values the
chain may need after it (harness/limit_search.py "Rounds"), so a chain
spreads over the workers the other searches leave; the answers are the
one-at-a-time answers.  The executor reads its items from a source that
hands out:
1. the next evaluation of a search, the longest search first (its expected
   cost: ``search_cost``): chains are the critical path, so they must
   never wait behind a point;
2. else the next point, longest first (``point_cost``): the short ones
   fill the tail;
3. else :data:`harness.execute.WAIT`: every unfinished search has its
   round in flight and no point is left; the executor asks again
   after its next result.

With one worker the order changes nothing but the progress display: the
points run in their planned order, then the searches, one evaluation at
a time.

Everything else is the executors': the watchdog (a point or an evaluation
whose worker dies or hangs becomes an ``error``/``timeout`` row naming why),
rows streamed back to this process as they finish.  Tests:
tests/test_schedule.py.
"""

from __future__ import annotations

import heapq
import itertools
from typing import Any, Callable, Iterator

from physbench.harness import points as _points
from physbench.harness.execute import WAIT, Batch, ColdSplit, PendingCompile, RunRequest, WorkerLost, shares_compile
from physbench.harness.limits import LimitRequest, SearchResult, search_items, spec_hash
from physbench.harness.points import Point, cached_scene, lost_row
from physbench.harness.sweep_store import sweep_files


def run_item(req: RunRequest) -> dict[str, Any]:
    """The executors' function: the row of a request, a point's or one
    evaluation's of a search (harness.points.request_row)."""
    return _points.request_row(req)  # looked up per call: a test may patch harness.points.request_row


def item_budget(req: RunRequest) -> float | None:
    """Wall-clock budget of a request's worker: its timed runs."""
    return req.budget_s


def item_priority(req: RunRequest) -> int:
    """Where items queue (a Dask scheduler), evaluations go first."""
    return 1 if req.probe is not None else 0


#: at most this many points in one batch (a batch's rows come back together on Dask)
BATCH_MAX = 64
#: expected seconds of a point no earlier sweep timed, when none of the sweep's points was timed
#: before: a fixed part (process hand-over, scene, metrics) and one per model unit
#: (:func:`model_cost`: steps x (bodies + 1) x runs), fitted on a nightly subset's 538 points
DEFAULT_POINT_S = 0.02
DEFAULT_UNIT_S = 5e-6


def batched(points: list[Any], cost: Callable[[Any], float] | None, target_s: float) -> list[Any]:
    """``points`` (in their order; points' requests, in a sweep) as the executor's units: runs of
    consecutive points whose expected seconds (``cost``) add up to at least
    ``target_s`` (at most :data:`BATCH_MAX`) as one :class:`Batch`; a point
    expected to take ``target_s`` or more alone, as itself.  No ``cost``
    or ``target_s`` <= 0: every point alone.  Test:
    tests/test_schedule.py::test_points_are_batched_to_the_target_work."""
    if cost is None or target_s <= 0:
        return list(points)
    units, run, total = [], [], 0.0
    for p in points:
        c = cost(p)
        if c >= target_s and not run:
            units.append(p)
            continue
        run.append(p)
        total += c
        if total >= target_s or len(run) >= BATCH_MAX:
            units.append(run[0] if len(run) == 1 else Batch(tuple(run)))
            run, total = [], 0.0
    if run:
        units.append(run[0] if len(run) == 1 else Batch(tuple(run)))
    return units


def run_schedule(executor: Any, points: list[Point], searches: list[LimitRequest],
                 on_point_row: Callable[[Point, dict[str, Any]], None],
                 on_search_done: Callable[[LimitRequest, SearchResult, dict[str, Any]], None],
                 store_eval: Callable[[dict[str, Any]], None], cached: dict[str, dict[str, Any]] | None = None,
                 on_start: Callable[[Point], None] | None = None,
                 point_cost: Callable[[Point], float] | None = None,
                 search_cost: Callable[[LimitRequest], float] | None = None, wide_rounds: bool = True) -> None:
    """Run ``points`` and ``searches`` through ``executor`` (module
    docstring).  Each point's row goes to ``on_point_row`` as it finishes,
    each new evaluation's row to ``store_eval``, each search's result and
    summary row to ``on_search_done`` (the caller stores the summary);
    evaluations whose key is in ``cached`` are read back, not run.
    ``point_cost`` / ``search_cost``: expected seconds (larger runs
    first; default: the order given); points are batched by ``point_cost``
    into units of the executor's ``batch_s`` seconds (:func:`batched`).  ``on_start(point)`` when a point
    starts (harness/execute.py: Dask calls it as the result arrives).  ``wide_rounds`` False: every
    search one evaluation at a time, whatever the workers (the benchmark's comparison)."""
    cached = cached or {}
    # one worker: the order does not change the wall time; keep the planned one (points, then searches)
    parallel = getattr(executor, "jobs", 1) > 1
    order = sorted(range(len(points)), key=lambda i: -point_cost(points[i])) if point_cost and parallel \
        else range(len(points))
    if not parallel:
        search_cost = None
    # points batched into units of the executor's batch_s expected seconds (Dask: a task's own cost is
    # worth it only for ~0.1 s of work); a search's evaluations are never batched (a round's go out side by side)
    # the executors' items are requests (harness.execute.RunRequest), a point's made from it; plan: id -> point
    plan: dict[int, Point] = {}
    requests = []
    for i in order:
        req = points[i].request()
        plan[id(req)] = points[i]
        requests.append(req)
    req_cost = (lambda r: point_cost(plan[id(r)])) if point_cost else None
    units = batched(requests, req_cost, float(getattr(executor, "batch_s", 0.0) or 0.0))
    # a cold compile cache on local workers: one compiles, the others run points that need none
    # (harness.execute.ColdSplit; the searches' evaluations are never held back)
    split = ColdSplit(units, PendingCompile()) if shares_compile(executor) else None
    todo = iter(split if split is not None else units)
    seq = itertools.count()
    ready: list[tuple[float, int, RunRequest]] = []  # heap: (-search cost, tie, item)
    owner: dict[int, tuple[Any, LimitRequest, float]] = {}  # id(item) -> (its search's generator, req, cost)
    rounds: dict[int, tuple[list[RunRequest], dict[int, dict[str, Any]]]] = {}  # id(gen) -> (round, rows so far)
    active = 0
    points_left = [bool(points)]

    def width() -> int:
        """Items a search's next round may hold: once no point is left to
        hand out, the workers shared out over the unfinished searches; 1
        before that, and with one worker (the one-at-a-time search)."""
        if not (parallel and wide_rounds) or points_left[0]:
            return 1  # while points wait, a worker has a point to run: a wide round's extra values would cost
        return max(1, getattr(executor, "jobs", 1) // max(1, active))

    def advance(gen: Any, req: LimitRequest, cost: float, got: list[dict[str, Any]] | None) -> None:
        """Feed a search its last round's rows (None: start it); queue its
        next round, or finish it."""
        nonlocal active
        try:
            items = next(gen) if got is None else gen.send(got)
        except StopIteration as stop:
            active -= 1
            res, summary = stop.value
            on_search_done(req, res, summary)
            return
        rounds[id(gen)] = (items, {})
        for item in items:
            owner[id(item)] = (gen, req, cost)
            heapq.heappush(ready, (-cost, next(seq), item))

    def answered(item: RunRequest, row: dict[str, Any]) -> None:
        gen, req, cost = owner.pop(id(item))
        items, got = rounds[id(gen)]
        got[id(item)] = row
        if len(got) == len(items):
            del rounds[id(gen)]
            advance(gen, req, cost, [got[id(it)] for it in items])

    active = len(searches)
    for req in sorted(searches, key=lambda r: -search_cost(r)) if search_cost else searches:
        advance(search_items(req, store_eval, cached, width), req, search_cost(req) if search_cost else 0.0, None)

    def source() -> Iterator[Any]:
        while True:
            if ready and (parallel or not points_left[0]):
                yield heapq.heappop(ready)[2]
                continue
            p = next(todo, None)
            if p is not None:
                yield p
                continue
            if points_left[0]:
                points_left[0] = False
                continue
            if not active:
                return
            yield WAIT

    def started(item: RunRequest) -> None:
        if on_start is not None and item.probe is None and id(item) in plan:
            on_start(plan[id(item)])

    for item, value in executor.map(run_item, source(), budget_s=item_budget, on_start=started,
                                    priority=item_priority):
        row = lost_row(item, value) if isinstance(value, WorkerLost) else value
        if split is not None:
            split.done(item)
        if item.probe is not None:
            answered(item, row)
        else:
            on_point_row(plan.pop(id(item)), row)
    if active:  # the source ends only when every search has finished
        raise RuntimeError(f"scheduler: {active} searches left unfinished")


def model_cost(scene: Any, dt: Any, runs: int) -> float:
    """Steps x (bodies + 1) x runs: a stand-in for seconds where no earlier
    sweep timed the item."""
    try:
        steps = float(scene.duration) / float(dt if dt is not None else scene.dt)
    except (TypeError, ValueError, ZeroDivisionError):
        steps = 1.0
    return max(1, runs) * steps * (len(scene.bodies) + 1)


def expected_costs(root: Any, suite: str, machine: str | None, points: list[Point], searches: list[LimitRequest]
                   ) -> tuple[Callable[[Point], float], Callable[[LimitRequest], float]]:
    """(point cost, search cost) of ``points`` and ``searches`` for
    :func:`run_schedule`'s longest-first order: the wall time of the same
    point, or the summed wall time of the same search's evaluations, in the
    newest finished sweep of ``suite`` on ``machine`` under ``root`` (s);
    for an item it did not time, a model (steps x bodies x runs) scaled to
    seconds by the points both know, or, when none, the default estimate
    (:data:`DEFAULT_POINT_S` + :data:`DEFAULT_UNIT_S` per unit).  They
    order the items and size the batches (:func:`batched`)."""
    import math


    wall: dict[str, float] = {}
    search_wall: dict[str, float] = {}
    files = sorted(f for m, _s, sid, f, _c in sweep_files(root, [suite], machine, unfinished=False))
    if files:
        import pandas as pd

        try:
            import pyarrow.parquet as pq

            have = set(pq.read_schema(files[-1]).names)  # the columns read below only
            df = pd.read_parquet(files[-1], columns=[c for c in ("point_key", "point_wall_s", "row_kind", "limit_id")
                                                     if c in have])
        except Exception:
            df = pd.DataFrame()
        if "point_wall_s" in df.columns and "point_key" in df.columns:
            kind = df["row_kind"] if "row_kind" in df.columns else pd.Series([None] * len(df), index=df.index)
            pts = df[kind.isna()]
            wall = dict(zip(pts["point_key"], pts["point_wall_s"].astype(float)))
            if "limit_id" in df.columns:
                ev = df[kind == "limit_eval"]
                search_wall = ev.groupby("limit_id")["point_wall_s"].sum().astype(float).to_dict()

    def point_model(p: Point) -> float:
        try:
            scene = cached_scene(p.path or p.scenario, p.variant)
        except Exception:
            return 0.0
        return model_cost(scene, p.engine_settings.get("dt"), p.repeats)

    def search_model(r: LimitRequest) -> float:
        try:
            scene = cached_scene(r.scenario, r.variant)
        except Exception:
            return 0.0
        return model_cost(scene, dict(r.settings).get("dt"), 8 * r.phases)  # ~8 values per search

    # seconds per model unit: the median over the points timed before; none: the default estimate
    ratios = sorted(w / m for p in points if math.isfinite(w := wall.get(p.key, math.nan))
                    and (m := point_model(p)) > 0)
    scale, fixed = (ratios[len(ratios) // 2], 0.0) if ratios else (DEFAULT_UNIT_S, DEFAULT_POINT_S)
    pc = {p.key: w if math.isfinite(w := wall.get(p.key, math.nan)) else fixed + scale * point_model(p)
          for p in points}
    sc = {}
    for r in searches:
        try:
            w = search_wall.get(r.identity(spec_hash(r)), math.nan)
        except OSError:
            w = math.nan
        sc[id(r)] = w if math.isfinite(w) else fixed * 8 * r.phases + scale * search_model(r)

    def point_cost(p: Point) -> float:
        return pc.get(p.key, 0.0)

    def search_cost(r: LimitRequest) -> float:
        return sc.get(id(r), 0.0)

    return point_cost, search_cost


__all__ = ["run_schedule", "run_item", "item_budget", "item_priority", "expected_costs", "batched", "model_cost",
           "BATCH_MAX"]
