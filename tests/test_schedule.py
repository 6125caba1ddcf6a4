"""A sweep's points and breaking-point searches on one executor
(harness/schedule.py), and the executor hooks it needs (harness/execute.py:
items read lazily, WAIT, one thread per run process).

The scheduling tests run on a simulated executor in virtual time (items
take given durations, values come from a function): the order and the
idle worker time are exact, whatever else the machine runs.  The last test
runs real searches with real points on the process pool and on a Dask
LocalCluster (127.0.0.1) and compares every answer with the serial path.
"""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pandas as pd
import pytest

from physbench.harness.execute import WAIT, InlineExecutor, WorkerLost, WorkerPool
from physbench.harness.selfbench.executors import sleep_task as _sleep, thread_counts
from physbench.harness.limits import EVAL_ROW, RESULT_ROW, EvalItem, LimitRequest, drive, search_items
from physbench.harness.points import Point
from physbench.harness.schedule import run_schedule
from physbench.harness.selfbench.sweep import VirtualExecutor, replay

#: a dt search on the 5-box column (scene loading only: values are answered by THRESHOLD)
THRESHOLD = {"mujoco": 0.0071, "pybullet": 0.0033, "pymunk": 0.0191}


def _req(engine: str, phases: int = 1) -> LimitRequest:
    return LimitRequest("stacking.column_5", None, engine, "dt", 0.001, 0.05, phases=phases, tol=0.05)


def _answer(req):
    """A point's row, or an evaluation's: holds below the engine's THRESHOLD."""
    if req.probe is not None:
        item = req.probe
        holds = item.value <= THRESHOLD[item.req.engine]
        return {"point_key": item.key, "limit_value": item.value, "limit_holds": holds, "limit_reason": "" if holds else "too coarse",
                "limit_cpu_s": 1.0, "phase": item.phase, "status": "ok"}
    return {"point_key": req.key, "status": "ok"}


def _answer_round(items):
    return [_answer(it) for it in items]


def SimExecutor(jobs, duration, answer=_answer):
    """physbench.harness.selfbench.sweep's virtual-time executor answering with _answer."""
    return VirtualExecutor(jobs, duration, answer)


def _points(n: int) -> list[Point]:
    return [Point("billiards.head_on", None, "mujoco", (("dt", 1e-3 * (i + 1)),)) for i in range(n)]


def _duration(item) -> float:
    if isinstance(item, Point):
        return float(item.settings_dict["dt"]) * 1e3  # point i takes i + 1 s
    if item.probe is not None:
        return 1.0
    return float(item.settings["dt"]) * 1e3


def _run(ex, points, reqs, **kw):
    rows, evals, done = {}, [], {}
    run_schedule(ex, points, reqs, lambda p, r: rows.__setitem__(p.key, r),
                 lambda req, res, summary: done.__setitem__(req.engine, (res, summary)), evals.append, **kw)
    return rows, evals, done


def test_searches_run_with_the_points_and_give_the_serial_answers():
    """Two workers, three searches (chains of 1 s evaluations) and twelve
    points (1 .. 12 s): every search and point finishes, each search's
    answer is the serial search's, and the schedule beats running the
    searches after the points (the old path) -- the workers idle only at
    the very end, less than one item's time."""
    reqs = [_req(e) for e in THRESHOLD]
    points = _points(12)
    ex = SimExecutor(2, _duration)
    rows, evals, done = _run(ex, points, reqs, point_cost=_duration, search_cost=lambda r: 1.0)
    assert sorted(rows) == sorted(p.key for p in points)
    for req in reqs:
        serial = drive(search_items(req, lambda row: None, {}), _answer_round)
        res, summary = done[req.engine]
        assert (res.limit, res.bracket, res.runs) == (serial[0].limit, serial[0].bracket, serial[0].runs)
        assert summary["row_kind"] == RESULT_ROW and summary["limit_runs"] == res.runs
        assert res.limit <= THRESHOLD[req.engine] < res.bracket[1]
    assert len(evals) == sum(done[e][0].runs for e in THRESHOLD)

    # the old path: the points, then the searches on the same two workers
    old = SimExecutor(2, _duration)
    _run(old, points, [])
    old_search = SimExecutor(2, _duration)
    _run(old_search, [], reqs)
    assert ex.busy == old.busy + old_search.busy
    assert ex.makespan < old.makespan + old_search.makespan
    assert ex.idle < max(_duration(p) for p in points)  # no worker waits on a chain while points are left
    assert ex.makespan <= math.ceil(ex.busy / 2) + 1


def test_order_chains_first_then_longest_point_first():
    """With searches running, evaluations go out before points; the points
    go out longest first."""
    reqs = [_req("mujoco"), _req("pymunk")]
    points = _points(6)
    ex = SimExecutor(2, _duration)
    _run(ex, points, reqs, point_cost=_duration, search_cost=lambda r: 1.0)
    kinds = [it.probe is not None for _t, it in ex.started]
    assert kinds[:2] == [True, True]  # one evaluation of each search first
    order = [_duration(it) for _t, it in ex.started if it.probe is None]
    assert order == sorted(order, reverse=True)


def test_one_worker_keeps_the_planned_order():
    """One worker: points in the planned order, then the searches (the
    order changes no wall time there)."""
    reqs = [_req("mujoco")]
    points = _points(4)
    ex = SimExecutor(1, _duration)
    _run(ex, points, reqs, point_cost=_duration, search_cost=lambda r: 1.0)
    items = [it for _t, it in ex.started]
    assert [it.key for it in items[:4]] == [p.key for p in points] and len(items) > 5
    assert all(isinstance(it.probe, EvalItem) for it in items[4:])
    assert not ex.waits and ex.idle == 0.0


def test_a_lost_evaluation_is_an_error_row_and_its_search_goes_on():
    """An evaluation whose worker died is stored as an ``error`` row that
    does not hold; the search treats the value as failing and finishes."""
    lost_values = []

    def answer(item):
        if item.probe is not None and item.probe.value > 0.01 and not lost_values:
            lost_values.append(item.probe.value)
            return WorkerLost("died", "worker process died while running this item: SIGKILL (killed)")
        return _answer(item)

    ex = SimExecutor(2, _duration, answer)
    rows, evals, done = _run(ex, _points(2), [_req("pymunk")])
    bad = [r for r in evals if r["limit_value"] == lost_values[0]]
    assert len(bad) == 1 and bad[0]["status"] == "error" and not bad[0]["limit_holds"]
    assert "this value" in bad[0]["limit_reason"] and bad[0]["row_kind"] == EVAL_ROW
    res, _ = done["pymunk"]
    assert res.bracket[1] <= lost_values[0]  # the value failed: the limit lies below it


def test_cached_evaluations_are_read_back_not_run():
    req = _req("mujoco", phases=1)
    ex = SimExecutor(2, _duration)
    _r, evals, _d = _run(ex, [], [req])
    cached = {r["point_key"]: r for r in evals}
    again = SimExecutor(2, _duration)
    _r, evals2, done = _run(again, [], [req], cached=cached)
    assert evals and not evals2 and not again.started
    assert done["mujoco"][0].limit <= THRESHOLD["mujoco"] < done["mujoco"][0].bracket[1]


def _phase_answer(req):
    """Holds below a threshold that falls with the step phase: a value
    between phase 0's and phase 0.75's threshold fails only in a later
    phase, so its reason names the first failing phase."""
    if req.probe is not None:
        item = req.probe
        holds = item.value <= THRESHOLD[item.req.engine] * (1.0 - 0.4 * item.phase)
        return {"point_key": item.key, "limit_value": item.value, "limit_holds": holds,
                "limit_reason": "" if holds else f"too coarse at {item.phase}", "limit_cpu_s": 1.0,
                "phase": item.phase, "status": "ok"}
    return {"point_key": req.key, "status": "ok"}


@pytest.mark.parametrize("jobs", [4, 16, 64])
def test_wide_rounds_give_the_serial_answers_sooner(jobs):
    """Workers to spare: each search's rounds hold several values and their
    step phases side by side (``jobs // unfinished searches`` items), and
    every answer -- outcome, limit, bracket, direction, failed check with
    its step phase -- is the one-at-a-time search's.  Two searches of 4
    step phases, evaluations of 1 s: the makespan falls from the serial
    chain's length (one worker: the sum of its runs) to its rounds, under
    half the serial time on 4 workers and under a fifth on 64; the rounds
    drop as the workers grow."""
    reqs = [_req("mujoco", phases=4), _req("pymunk", phases=4)]
    serial = {r.engine: drive(search_items(r, lambda row: None, {}), lambda its: [_phase_answer(i) for i in its])
              for r in reqs}
    one = SimExecutor(1, _duration, _phase_answer)
    _run(one, [], reqs)
    ex = SimExecutor(jobs, _duration, _phase_answer)
    _r, evals, done = _run(ex, [], reqs, search_cost=lambda r: 1.0)
    for r in reqs:
        s, wide = serial[r.engine][0], done[r.engine][0]
        assert (wide.outcome, wide.limit, wide.bracket, wide.direction, wide.failed_check) == \
            (s.outcome, s.limit, s.bracket, s.direction, s.failed_check)
        assert "step phase" in s.failed_check or s.failed_check.endswith("at 0.0")
        assert wide.rounds < s.rounds and wide.runs >= s.runs
        assert done[r.engine][1]["limit_rounds"] == wide.rounds
    assert one.makespan == sum(serial[e][0].runs for e in serial)
    assert ex.makespan < one.makespan / (2 if jobs == 4 else 5), (ex.makespan, one.makespan)
    assert len(evals) == sum(done[e][0].runs for e in done) and len({r["point_key"] for r in evals}) == len(evals)


# ---------------------------------------------------------------------------
# the executor hooks


def test_pool_reads_items_lazily_and_waits():
    """WorkerPool and the inline executor read one item when a worker is
    free; WAIT holds the source until a result is in; WAIT with nothing
    in flight is an error, not a hang."""
    got = []

    waits = []

    def source():
        yield 0.01
        while not got:  # nothing to run until the first result is handed over
            waits.append(len(got))
            yield WAIT
        yield 0.0

    with WorkerPool(2) as pool:
        for item, value in pool.map(_sleep, source()):
            got.append(value)
        assert got == [0.01, 0.0] and waits
        with pytest.raises(RuntimeError, match="nothing is running"):
            list(pool.map(_sleep, iter([WAIT])))
    with pytest.raises(RuntimeError, match="nothing is running"):
        list(InlineExecutor().map(_sleep, iter([0.0, WAIT])))


def test_run_processes_use_one_thread():
    """BLAS (threadpoolctl) and numba hold one thread in every run process:
    N workers use N cores, whatever the machine."""
    with WorkerPool(1) as pool:
        [(_, got)] = list(pool.map(thread_counts, [0]))
    assert got["numba"] == 1 and set(got["blas"].values()) <= {1}, got
    assert set(got["env"].values()) == {"1"}


# ---------------------------------------------------------------------------
# real runs


TIMING = ("cpu_s", "wall_s", "steps_per_s", "point_wall_s", "sweep_jobs", "limit_cpu_s")


def test_limit_blocks_on_two_workers_give_the_serial_rows(tmp_path):
    """A suite of points and two searches, run serially, on two process
    workers and on a two-worker Dask LocalCluster: the same answers and
    the same rows for every evaluation the serial search made (engines are
    deterministic; two workers may evaluate more values once one search
    is done, in fewer rounds), the same point metrics."""
    pytest.importorskip("distributed")
    from physbench.harness.sweep import sweep_main
    from physbench.harness.sweep_store import read_sweeps

    p = tmp_path / "s.toml"
    p.write_text(textwrap.dedent("""
        [suite]
        name = "mix"
        engines = ["pymunk", "mujoco"]
        repeats = 1
        [[sweep]]
        scenarios = ["billiards.head_on"]
        grid = { dt = [0.002, 0.001] }
        [[limit]]
        scenarios = ["tunnelling.bullet_100"]
        param = "body[0].velocity[0]"
        range = [0.3, 10]
        phases = 2
        tol = 0.2
        checks = ["tunnelled"]
        set = { "static[0].position" = [0.05, 0.0, 0.0], "scenario.duration" = 0.5 }
    """))
    frames = {}
    for executor, jobs in (("serial", 1), ("process", 2), ("dask", 2)):
        out = tmp_path / executor
        assert sweep_main(str(p), jobs=jobs, out_dir=out, executor=executor) == 0
        frames[executor] = read_sweeps(out, suite="mix")
    a = frames["serial"]
    for name in ("process", "dask"):
        b = frames[name]
        # a wide round (a worker to spare once one search is done) may add evaluations; every serial row is there
        assert set(a["point_key"]) <= set(b["point_key"]) and b["point_key"].is_unique, name
        a_, b_ = a.set_index("point_key").sort_index(), b.set_index("point_key").loc[sorted(a["point_key"])]
        assert (a_["status"] == b_["status"]).all()
        for c in ("limit_value", "limit_lo", "limit_hi", "limit_holds", "primary_error", "max_penetration"):
            np.testing.assert_array_equal(pd.to_numeric(a_[c], errors="coerce").to_numpy(float),
                                          pd.to_numeric(b_[c], errors="coerce").to_numpy(float), err_msg=f"{name} {c}")
        ra, rb = a_[a_["row_kind"] == RESULT_ROW], b_[b_["row_kind"] == RESULT_ROW]
        assert (ra["limit_failed_check"] == rb["limit_failed_check"]).all()
        assert (rb["limit_runs"] >= ra["limit_runs"]).all() and (rb["limit_rounds"] <= ra["limit_rounds"]).all()
        assert (b["row_kind"] == EVAL_ROW).sum() == rb["limit_runs"].sum()
    res = a[a["row_kind"] == RESULT_ROW]
    assert len(res) == 2 and res["limit_outcome"].eq("found").all()
    assert (a["row_kind"] == EVAL_ROW).sum() == res["limit_runs"].sum()

    # the serial sweep replayed on two virtual workers: the searches take the stored path
    rp = replay(a, str(p), 2)
    timed = a[a["row_kind"].isna() | (a["row_kind"] == EVAL_ROW)]["point_wall_s"].sum()
    assert rp["evaluations"] == res["limit_runs"].sum() and rp["points"] == 4
    assert rp["total_s"] == pytest.approx(timed, rel=1e-9)
    assert rp["ideal_s"] <= min(rp["new_s"], rp["narrow_s"]) and rp["narrow_s"] <= rp["old_s"] <= rp["total_s"]


def test_points_are_batched_to_the_target_work():
    """harness.schedule.batched: consecutive points whose expected seconds
    add up to the target go into one Batch (at most BATCH_MAX points); a
    point expected to reach the target alone stays alone; no target or
    no cost: every point alone.  Run through run_schedule, every point
    gives its row once, as unbatched."""
    from physbench.harness.execute import Batch
    from physbench.harness.schedule import BATCH_MAX, batched

    pts = _points(200)
    cost = dict(zip((p.key for p in pts), [0.5, 0.03, 0.03, 0.03, 0.03, 0.2, 0.06, 0.06, 0.01] + [0.001] * 191))
    units = batched(pts, lambda p: cost[p.key], 0.1)
    assert units[0] is pts[0] and units[2] is pts[5]
    assert isinstance(units[1], Batch) and units[1].items == tuple(pts[1:5])  # 0.12 s
    assert isinstance(units[3], Batch) and units[3].items == tuple(pts[6:8])
    assert units[4].items == tuple(pts[8:8 + BATCH_MAX])  # 0.073 s, but BATCH_MAX points
    assert [p for u in units for p in (u.items if isinstance(u, Batch) else (u,))] == pts
    assert batched(pts, None, 0.1) == pts and batched(pts, lambda p: cost[p.key], 0.0) == pts

    import physbench.harness.points as P

    ex = InlineExecutor()
    ex.batch_s = 0.1
    got, rows = [], []
    real = P.request_row
    P.request_row = lambda r: {"point_key": r.key, "status": "ok"}
    try:
        run_schedule(ex, pts, [], lambda p, r: rows.append((p, r["point_key"])), lambda *a: None, lambda r: None,
                     on_start=got.append, point_cost=lambda p: cost[p.key])
    finally:
        P.request_row = real
    assert [p for p, _ in rows] == pts == got and all(p.key == k for p, k in rows)


# ---------------------------------------------------------------------------
# a cold compile cache on two workers (harness.execute.ColdSplit)


class _Build:
    """A fake run: ``groups`` of compiled code its engine needs (none: an
    engine that compiles nothing), then ``run_s`` seconds of stepping."""

    def __init__(self, name: str, groups: tuple[str, ...] = (), run_s: float = 1.0):
        self.name, self.groups, self.run_s = name, groups, run_s

    def __repr__(self) -> str:
        return self.name


class _LockSim:
    """Two (``jobs``) workers in virtual time sharing a compile cache as
    engine/compile_share.py does: a build compiles, in order, the groups
    nobody has compiled or is compiling (COST s each), then waits for the
    groups another worker is compiling, then runs.  ``pending(item)``: the
    seconds of its groups not yet compiled at the current time (the
    engine's done marks).  ``waited``: worker seconds spent waiting on
    another's compile; ``makespan``."""

    shares_compile_cache = True
    COST = {"solve": 100.0}

    def __init__(self, jobs: int = 2):
        self.jobs, self.now, self.ready_at, self.waited, self.makespan = jobs, 0.0, {}, 0.0, 0.0
        self.started: list = []

    def pending(self, item) -> frozenset:
        return frozenset(g for g in item.groups if self.ready_at.get(g, math.inf) > self.now)

    def _start(self, item) -> float:
        t, wait_for = self.now, self.now
        for g in item.groups:
            if g in self.ready_at:  # compiled, or another worker compiles it: loaded at the end
                wait_for = max(wait_for, self.ready_at[g])
            else:
                t += self.COST.get(g, 10.0)
                self.ready_at[g] = t
        end = max(t, wait_for)
        self.waited += end - t
        return end + item.run_s

    def map(self, fn, items, budget_s=None, on_start=None, priority=None):
        import heapq
        import itertools

        from physbench.harness.execute import END, take

        source, more, seq, running = iter(items), True, itertools.count(), []
        while more or running:
            while more and len(running) < self.jobs:
                unit = take(source, bool(running))
                if unit is END:
                    more = False
                if unit is END or unit is WAIT:
                    break
                self.started.append(unit)
                heapq.heappush(running, (self._start(unit), next(seq), unit))
            if running:
                self.now, _, unit = heapq.heappop(running)
                yield unit, unit.name
        self.makespan = self.now


def _check_plan(n_scenes: int = 6, others: int = 3) -> list[_Build]:
    """A check's planned order: per scene, the reference run (the shared
    solve group and the scene's own shape-pair group) then ``others``
    runs of engines that compile nothing (5 s each)."""
    out = []
    for k in range(n_scenes):
        out.append(_Build(f"ref{k}", ("solve", f"narrow{k % 3}"), 1.0))
        out += [_Build(f"o{k}.{j}", (), 5.0) for j in range(others)]
    return out


def _drive(ex, units, split: bool):
    from physbench.harness.execute import ColdSplit

    src = ColdSplit(units, ex.pending) if split else units
    got = []
    for item, value in ex.map(None, src):
        if split:
            src.done(item)
        got.append(value)
    return got


def test_cold_split_keeps_a_second_worker_off_the_compile_it_would_wait_for():
    """On a cold cache, planned order: the second worker starts the next
    scene's reference build and waits ~80 s for the first worker's solve
    group.  ColdSplit hands it the other engines' runs instead: no worker
    waits, every run runs once, and the makespan drops to within a run of
    the work over two workers."""
    plain, split = _LockSim(), _LockSim()
    got_plain = _drive(plain, _check_plan(), False)
    got_split = _drive(split, _check_plan(), True)
    assert sorted(got_plain) == sorted(got_split) == sorted(b.name for b in _check_plan())
    assert len(got_split) == len(set(got_split))
    assert plain.waited > 50.0  # the waste being removed
    assert split.waited == 0.0
    work = 100 + 3 * 10 + 6 * 1 + 18 * 5  # compile once, run everything
    assert split.makespan <= work / 2 + 5.0 < plain.makespan - 30.0


def test_cold_split_keeps_the_order_on_a_warm_cache():
    """Nothing to compile (pending 0 everywhere): the source's order,
    unchanged, and nothing held back."""
    from physbench.harness.execute import ColdSplit

    units = _check_plan()
    split = ColdSplit(units, lambda item: frozenset())
    assert list(split) == units and split.deferred == 0
    ex = _LockSim()
    for b in units:
        ex.ready_at.update({g: 0.0 for g in b.groups})
    _drive(ex, units, True)
    assert ex.started == units


def test_cold_split_holds_conflicting_units_back_in_order_and_never_starves():
    """A unit that would compile a group another unit in flight compiles
    is held back (units that need none, or other groups, pass it); the
    oldest held-back unit that no longer conflicts goes first; with only
    conflicting units left they are handed out anyway (no worker left
    idle); a WAIT of the source hands a held-back unit instead of waiting;
    a finished unit's groups go to ``pending.compiled``."""
    from physbench.harness.execute import ColdSplit

    c1, c2, c3, w1, w2 = (_Build(n, g) for n, g in (("c1", ("a",)), ("c2", ("a",)), ("c3", ("b",)),
                                                       ("w1", ()), ("w2", ())))

    class Pending:
        def __init__(self):
            self.done = set()

        def __call__(self, item):
            return frozenset(item.groups) - self.done

        def compiled(self, groups):
            self.done |= groups

    split = ColdSplit([c1, c2, w1, c3, w2], Pending())
    it = iter(split)
    assert next(it) is c1
    assert next(it) is w1  # c2 held back: c1 compiles group a
    assert next(it) is c3  # group b: compiled beside a
    assert next(it) is w2
    assert next(it) is c2  # only conflicting ones left: handed out while c1 is in flight
    split.done(c1)
    assert split.pending.done == {"a"}
    assert next(it, None) is None and split.deferred == 1
    # the oldest held-back unit first once nothing in flight compiles its group
    split = ColdSplit([c1, c2, c2, w1, w2, w1], Pending())
    it = iter(split)
    assert [next(it), next(it)] == [c1, w1]
    split.done(c1)
    assert next(it) is c2 and split.waiting == [c2]  # (warm now: c1 compiled a)
    assert next(it) is c2
    # a source that says WAIT: a held-back unit runs meanwhile
    def source():
        yield c1
        yield c2
        yield WAIT
        yield w1

    split = ColdSplit(source(), Pending())
    assert list(split) == [c1, c2, w1]


def test_cold_split_compiles_other_groups_beside_each_other():
    """With nothing but reference runs left (no other engine's run to hand
    out), a scene's base and its variant (the same groups) are kept apart
    and another scene's run (other groups) goes beside: no worker waits,
    where the planned order makes one wait for each pair."""
    plan = []
    for k in range(4):
        plan += [_Build(f"s{k}", (f"narrow{k}",), 1.0), _Build(f"s{k}v", (f"narrow{k}",), 1.0)]
    plain, split = _LockSim(), _LockSim()
    assert sorted(_drive(plain, plan, False)) == sorted(_drive(split, plan, True))
    assert plain.waited >= 4 * 9.0
    assert split.waited == 0.0 and split.makespan < plain.makespan - 10.0


def test_cold_split_serves_a_sweeps_points(monkeypatch):
    """run_schedule puts a sweep's points through ColdSplit on an executor
    whose workers share the compile cache: same rows, no worker waits on
    another's compile, a shorter makespan than the same points on an
    executor that does not share it (the planned order)."""
    from physbench.harness import schedule

    plan = _check_plan()
    pts = [Point("billiards.head_on", None, "mujoco", (("dt", 1e-3 * (i + 1)),)) for i in range(len(plan))]
    build = {}

    class Sim(_LockSim):
        def map(self, fn, items, **kw):
            for item, _ in super().map(fn, (build[id(u)] if id(u) in build else u for u in items), **kw):
                yield item.req, {"point_key": item.req.key, "status": "ok"}

    def request(p, _orig=Point.request):
        r = _orig(p)
        b = plan[pts.index(p)]
        build[id(r)] = b
        b.req = r
        return r

    monkeypatch.setattr(Point, "request", request)
    runs = {}
    for share in (True, False):
        ex = Sim()
        ex.shares_compile_cache = share
        monkeypatch.setattr(schedule, "PendingCompile", lambda ex=ex: (lambda req: ex.pending(build[id(req)])))
        rows, _, _ = _run(ex, pts, [])
        runs[share] = ex
        assert set(rows) == {p.key for p in pts}
    assert runs[True].waited == 0.0 < runs[False].waited
    assert runs[True].makespan < runs[False].makespan - 30.0


def test_pending_compile_reads_the_engines_own_cache(tmp_path, monkeypatch):
    """PendingCompile asks the engine's adapter (pending_compile): the
    reference engine on an empty cache has its kernel groups to compile
    (the contact solve among them), none once every group of the scene is
    marked done (engine/compile_share.py) or reported compiled by a
    finished unit; an engine that compiles nothing of its own has none; a
    consensus run counts its engines'."""
    from physbench.adapters import get_adapter
    from physbench.adapters.reference import scene_input
    from physbench.contract.scene import load_scene
    from physbench.engine import compile_share
    from physbench.engine.jit import fused_part, parts
    from physbench.engine.model import build_model
    from physbench.harness.execute import PendingCompile, RunRequest

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    ref = RunRequest("billiards.head_on", "reference")
    both = RunRequest("billiards.head_on", "consensus", consensus=("mujoco", "reference"))
    pending = PendingCompile()
    groups = pending(ref)
    assert "reference:('solve',)" in groups and len(groups) >= 4
    assert any(g.startswith("reference:('steady',") for g in groups)  # the fused step's group too
    assert pending(RunRequest("billiards.head_on", "mujoco")) == frozenset()
    assert pending(both) == groups
    assert pending(RunRequest("billiards.head_on", "reference", phase=0.5)) == groups  # the phase changes no kernel
    pending.compiled(groups)  # (a unit that needed them finished)
    assert pending(ref) == frozenset() and pending(both) == frozenset()
    scene = load_scene("billiards.head_on")
    model = build_model(scene_input(scene), get_adapter("reference").resolve_settings(scene, {}))
    for key in parts(model) + (fused_part(model),):
        with compile_share.group(key):  # (compiled: marked done)
            pass
    assert PendingCompile()(ref) == frozenset()
