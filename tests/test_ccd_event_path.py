"""The event path's kept state (engine/ccd.py, engine/contact/impact.py):
what an impact and a time-of-impact search build once instead of at every
event, with the same results (the bits script; the determinism pins)."""

from __future__ import annotations

import numpy as np
import pytest

import physbench.engine.contact.impact as impact
import physbench.engine.contact.rows as rows
from physbench.adapters.reference import engine_for
from physbench.contract.scene import load_scene


def test_a_bouncing_ball_builds_its_impact_topology_once(monkeypatch):
    """Every bounce of a ball on the floor is the same contact set: the
    impact stage keeps its topology (impact.ImpactKept) and its work arrays.
    On the code before, each impact built a Topology (and ~16 work arrays)
    again: 8 for 8 bounces."""
    built = []
    real = rows.Topology

    def counting(model, a, b, sidx, friction, colour):
        if not colour:  # the propagation's (the solve's are coloured)
            built.append(a.size)
        return real(model, a, b, sidx, friction, colour)

    monkeypatch.setattr(rows, "Topology", counting)
    monkeypatch.setattr(impact, "Topology", counting, raising=False)
    eng = engine_for(load_scene("billiards.ball_drop_bounce"), {"dt": 0.032})
    eng.step(47)
    n_impacts = eng.profile.as_dict()["counters"]["impacts"]
    assert n_impacts >= 5
    assert len(built) == 1


def test_kept_impact_state_gives_the_same_velocities():
    """The same impacts with the kept topologies and work arrays as with
    fresh ones (kept=None), bit for bit, over a mixed bin's events."""
    a = engine_for(load_scene("stacking.mixed_bin"), {"dt": 1 / 60})
    b = engine_for(load_scene("stacking.mixed_bin"), {"dt": 1 / 60})
    next(s for s in b.stages if s.family == "impact").kept = None
    a.step(40)
    b.step(40)
    assert a.profile.as_dict()["counters"]["impacts"] >= 10
    for u, v in ((a.state.x, b.state.x), (a.state.v, b.state.v), (a.state.w, b.state.w)):
        assert np.array_equal(u, v)


def test_contact_inertias_are_world_inv_inertia_bit_for_bit():
    """impact.contact_inertias: the contact bodies' world inverse inertias
    as mathutil.world_inv_inertia(quat_to_matrix(q)) gives them, zero for
    the other bodies and the world row."""
    from physbench.engine.mathutil import quat_to_matrix, world_inv_inertia

    rng = np.random.default_rng(3)
    n = 9
    for trial in range(50):
        q = rng.normal(size=(n, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        inv_I = 1.0 / rng.uniform(0.01, 3.0, size=(n, 3))
        a = rng.integers(0, n, size=5)
        b = np.where(rng.random(5) < 0.4, n, rng.integers(0, n, size=5))
        out = np.full((n + 1, 3, 3), np.nan)
        impact.contact_inertias(q, inv_I, a, b, out)
        want = np.zeros((n + 1, 3, 3))
        bodies = np.unique(np.concatenate([a, b[b < n]]))
        want[bodies] = world_inv_inertia(quat_to_matrix(q[bodies]), inv_I[bodies])
        assert np.array_equal(out, want)


def _counting(calls: dict, key: str, real):
    """``real`` that counts its calls in ``calls[key]``."""
    def f(*a):
        calls[key] += 1
        return real(*a)
    return f


def _count_impact_python_calls(monkeypatch) -> dict:
    """Count the impact kernel's calls and the Python-level calls of what
    it runs inside (Rows, the propagation's set-up and its modes)."""
    from physbench.engine.contact import propagate

    calls = {"kernel": 0, "rows": 0, "setup": 0, "propagate": 0}

    class CountingRows(rows.Rows):
        def __init__(self, *a, **k):
            calls["rows"] += 1
            super().__init__(*a, **k)

    monkeypatch.setattr(impact, "impact_kernel", _counting(calls, "kernel", impact.impact_kernel))
    monkeypatch.setattr(propagate, "setup", _counting(calls, "setup", propagate.setup))
    monkeypatch.setattr(propagate, "propagate", _counting(calls, "propagate", propagate.propagate))
    monkeypatch.setattr(impact, "Rows", CountingRows)
    return calls


def test_an_impact_is_one_compiled_call(monkeypatch):
    """A ball bouncing on the floor: each impact's contact inertias, rows,
    propagation set-up and both propagation modes run inside one compiled
    call (impact.impact_kernel): one per impact, and no Python-level Rows,
    propagate.setup or propagate.propagate call.  On the code before, each
    impact made one Rows and three such calls from Python."""
    eng = engine_for(load_scene("billiards.ball_drop_bounce"), {"dt": 0.032})
    calls = _count_impact_python_calls(monkeypatch)  # (after the build: its warm-up calls them)
    eng.step(47)
    n_impacts = eng.profile.as_dict()["counters"]["impacts"]
    assert n_impacts >= 5
    assert calls == {"kernel": n_impacts, "rows": 0, "setup": 0, "propagate": 0}


def _states(eng) -> tuple:
    return eng.state.x, eng.state.q, eng.state.v, eng.state.w


@pytest.mark.parametrize("sid, steps", [("billiards.break_16", 100), ("billiards.newtons_cradle", 50)])
def test_the_impact_kernel_gives_the_python_paths_bits(sid, steps):
    """The compiled impact (kept work arrays) and the Python path (kept=None)
    bit for bit where an impact runs down a chain of touching balls (the
    rack of a break, a cradle): many pairs propagated in one impact."""
    a = engine_for(load_scene(sid), {})
    b = engine_for(load_scene(sid), {})
    next(s for s in b.stages if s.family == "impact").kept = None
    a.step(steps)
    b.step(steps)
    assert a.profile.as_dict()["counters"]["impacts"] >= 1
    for u, v in zip(_states(a), _states(b)):
        assert np.array_equal(u, v)


def test_an_impact_the_kernel_leaves_runs_the_python_path(monkeypatch):
    """A propagation that does not settle inside the kernel (it returns
    False and leaves the state alone: a pinned configuration) is resolved
    by the Python path from the start, with the bits of kept=None: the
    kernel made to give up on every impact of a mixed bin (friction,
    rolling bodies, plastic islands)."""
    monkeypatch.setattr(impact, "impact_kernel", lambda *a: False)
    a = engine_for(load_scene("stacking.mixed_bin"), {"dt": 1 / 60})
    b = engine_for(load_scene("stacking.mixed_bin"), {"dt": 1 / 60})
    next(s for s in b.stages if s.family == "impact").kept = None
    a.step(40)
    b.step(40)
    assert a.profile.as_dict()["counters"]["impacts"] >= 10
    for u, v in zip(_states(a), _states(b)):
        assert np.array_equal(u, v)


def test_the_step_pack_follows_the_states_arrays():
    """Context.kept (the start and commit's Pack) is the same Pack while the
    state's x, q, v, w are the same arrays, and a new one holding the new
    arrays when one is replaced: a state whose arrays were swapped for
    copies steps (through events) to the bits of one that kept them."""
    a = engine_for(load_scene("billiards.head_on"), {"dt": 0.032})
    b = engine_for(load_scene("billiards.head_on"), {"dt": 0.032})
    ctx, st = a.state.ctx, a.state
    p = ctx.kept(st)
    assert ctx.kept(st) is p
    for name in ("x", "q", "v", "w"):
        setattr(st, name, getattr(st, name).copy())
        p2 = ctx.kept(st)
        assert p2 is not p and getattr(p2.items, name) is getattr(st, name)
        p = p2
    a.step(16)
    b.step(16)
    assert a.profile.as_dict()["counters"]["impacts"] == 1
    for u, v in zip(_states(a), _states(b)):
        assert np.array_equal(u, v)


def test_the_end_pose_check_answers_none_in_one_call(monkeypatch):
    """A ball bouncing on the floor: at every CCD stage with a pair to
    check, the end-pose check (the moved pairs, their collision at the end
    pose, the candidates) answers "no missed impact" in one compiled call
    (ccd_end.missed_any), and its Python path (ccd_kept.end_pose_pairs,
    the collider's run, missed_candidates) never runs.  On the code before
    it ran at each of them (three compiled calls and their set-up)."""
    from physbench.engine import ccd

    calls = {"any": 0, "python": 0}
    monkeypatch.setattr(ccd, "_missed_any", _counting(calls, "any", ccd._missed_any))
    monkeypatch.setattr(ccd, "end_pose_pairs", _counting(calls, "python", ccd.end_pose_pairs))
    eng = engine_for(load_scene("billiards.ball_drop_bounce"), {"dt": 0.032})
    eng.step(47)
    assert eng.profile.as_dict()["counters"]["impacts"] >= 5
    assert calls["any"] >= 10 and calls["python"] == 0


def _numpy_pick(rows, tau, h, ca, cb, csidx, point, fid, x, R0, shape, static_shape, n_statics):
    """The CCD stage's pick of a lone impact as numpy computed it
    (engine/ccd.py before ccd_end.lone_impact): the reference."""
    from physbench.engine.model import BOX, S_BOX

    n = x.shape[0]
    j = int(np.argmin(tau))
    t = float(min(max(tau[j], 0.0), h))
    code = (ca[rows] * (n + 1) + cb[rows]) * (n_statics + 1) + (csidx[rows] + 1)
    if not (rows.size == 1 or code.min() == code.max()):
        return j, t, code, False, None
    k = int(rows[j])
    a, b, sidx = int(ca[k]), int(cb[k]), int(csidx[k])
    loc = np.einsum("ki,ij->kj", point[rows] - x[a], R0[a])
    stable = shape[a] != BOX or (shape[b] != BOX if b < n else static_shape[sidx] != S_BOX)
    fids = np.array(sorted(set(fid[rows].tolist())), np.int64) if stable else None
    return j, t, code, True, (a, b, sidx, loc, fids)


@pytest.mark.parametrize("seed", range(30))
def test_the_lone_impact_pick_is_the_numpy_pick(seed):
    """ccd_end.lone_impact (one compiled call) gives the numpy form's
    earliest row, time (clipped to [0, h], NaN kept), pair codes, and for
    one pair its bodies, body-frame points and followed feature ids, bit
    for bit: lone and mixed pairs, boxes and round shapes, statics."""
    from physbench.engine import ccd_end

    rng = np.random.default_rng(seed)
    n, n_statics, m = 4, 2, 9
    shape = rng.integers(0, 4, n).astype(np.int64)
    static_shape = rng.integers(0, 2, n_statics).astype(np.int64)
    x = rng.standard_normal((n, 3))
    q = rng.standard_normal((n, 4))
    from physbench.engine.mathutil import quat_to_matrix

    R0 = quat_to_matrix(q / np.linalg.norm(q, axis=1)[:, None])
    a0 = int(rng.integers(0, n))
    static = bool(rng.integers(0, 2))
    ca = np.full(m, a0, np.int64)
    cb = np.full(m, n if static else (a0 + 1) % n, np.int64)
    csidx = np.full(m, int(rng.integers(0, n_statics)) if static else -1, np.int64)
    if seed % 3 == 0:  # another pair among the rows
        cb[::2] = (a0 + 2) % n
        csidx[::2] = -1
    point = x[a0] + rng.standard_normal((m, 3))
    fid = rng.integers(0, 5, m).astype(np.int64)
    rows = np.sort(rng.choice(m, int(rng.integers(1, 5)), replace=False)).astype(np.int64)
    h = 0.01
    tau = h * rng.uniform(-0.5, 1.5, rows.size)
    if seed % 5 == 1:
        tau[-1] = np.nan
    got = ccd_end.lone_impact(rows, tau, h, ca, cb, csidx, point, fid, x, R0, shape, static_shape, n_statics)
    want = _numpy_pick(rows, tau, h, ca, cb, csidx, point, fid, x, R0, shape, static_shape, n_statics)
    j, t, code, lone, a, b, sidx, loc, fids, stable = got
    assert (int(j), np.array(float(t)).tobytes(), lone) == (want[0], np.array(want[1]).tobytes(), want[3])
    assert np.array_equal(code, want[2])
    if lone:
        wa, wb, ws, wloc, wfids = want[4]
        assert (int(a), int(b), int(sidx)) == (wa, wb, ws)
        assert np.array_equal(loc, wloc)
        assert (wfids is None) == (not stable)
        if stable:
            assert np.array_equal(fids, wfids)


def test_the_impact_stages_small_kernels_are_the_numpy_forms():
    """impact.pair_codes, touching_count and all_positive (compiled) give
    what engine.contact.topology._pair_codes_abs, np.flatnonzero(gap <=
    tol).size and np.all(e > 0.0) give, NaN included."""
    from types import SimpleNamespace

    from physbench.engine.contact.topology import _pair_codes_abs

    rng = np.random.default_rng(5)
    for _ in range(20):
        m, n, ns = int(rng.integers(0, 9)), int(rng.integers(1, 50)), int(rng.integers(0, 5))
        a = rng.integers(0, n, m).astype(np.int64)
        b = rng.integers(0, n + 1, m).astype(np.int64)
        s = rng.integers(-1, ns, m).astype(np.int64)
        want = _pair_codes_abs(SimpleNamespace(n=n, n_statics=ns), a, b, s)
        assert np.array_equal(impact.pair_codes(a, b, s, n, ns), want)
        gap = rng.uniform(-1e-6, 1e-6, m)
        e = rng.choice([-0.5, 0.0, 0.3, np.nan, 1.0], m)
        if m:
            gap[0] = np.nan
        assert impact.touching_count(gap, 1e-7) == np.flatnonzero(gap <= 1e-7).size
        assert impact.all_positive(e) == bool(np.all(e > 0.0))
        assert impact.all_positive(np.abs(e) + 0.1) == bool(np.all(np.abs(e) + 0.1 > 0.0))


def _holds_a_pack(v, depth=0) -> bool:
    from numba.experimental.structref import StructRefProxy

    if isinstance(v, StructRefProxy):
        return depth > 0
    return isinstance(v, tuple) and any(_holds_a_pack(x, depth + 1) for x in v)


@pytest.mark.parametrize("scenario,settings,steps", [
    ("billiards.ball_drop_bounce", {"dt": 0.064}, 31),  # impacts, the end-pose check, the search
    ("billiards.head_on", {"dt": 0.032}, 16),
    ("tunnelling.bullet_400", {"dt": 0.004, "ccd": "events"}, 25),
])
def test_event_kernels_take_no_pack_inside_a_tuple(monkeypatch, scenario, settings, steps):
    """A Pack (engine/pack.py) passed inside a tuple makes numba type the
    whole tuple in Python at every call, the Pack's full type with it:
    ccd_end.missed_any took the narrow phase's Pack in a tuple and paid
    ~60-80 us a call, two calls an event step (half of ball_drop_bounce's
    CPU at dt 0.064).  No compiled call of a warm engine's steps takes one."""
    from numba.core import dispatcher

    scene = load_scene(scenario)
    engine_for(scene, settings).step(steps)  # (compiles or loads every kernel first)
    seen = []
    real = dispatcher._DispatcherBase.typeof_pyval

    def typeof_pyval(self, val):
        if _holds_a_pack(val):
            seen.append(self.py_func.__qualname__)
        return real(self, val)

    monkeypatch.setattr(dispatcher._DispatcherBase, "typeof_pyval", typeof_pyval)
    eng = engine_for(scene, settings)
    eng.step(steps)
    assert eng.profile.as_dict()["counters"].get("impacts", 0) + \
        eng.profile.as_dict()["counters"].get("toi_iterations", 0) > 0  # (the event path ran)
    assert sorted(set(seen)) == []
