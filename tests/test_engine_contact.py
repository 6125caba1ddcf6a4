"""Reference engine: impacts with restitution, ball drops, resting contact.

Every expectation is analytic: Newton's law of restitution for head-on
impacts, the ballistic bounce sequence for a dropped ball (exact within the
step thanks to time-of-impact splitting), rest at z = r afterwards.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pytest

from physbench.adapters.reference import engine_for
from physbench.harness.runner import run
from physbench.contract.scene import load_scene


def scene_from(tmp_path: Path, text: str, name: str = "s.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return load_scene(p)


def newton(m1, m2, v1, v2, e):
    """Outgoing velocities of a head-on impact (law of restitution)."""
    u1 = ((m1 - e * m2) * v1 + (1 + e) * m2 * v2) / (m1 + m2)
    u2 = ((m2 - e * m1) * v2 + (1 + e) * m1 * v1) / (m1 + m2)
    return u1, u2


@pytest.mark.parametrize("variant", [None, "elastic", "plastic"])
def test_head_on_example_through_runner(head_on_path, variant):
    scene = load_scene(head_on_path, variant)
    res = run(scene, "reference")
    assert res.status == "ok", res.message
    tr = res.trace.valid()
    m = scene.masses
    e = scene.pair(scene.bodies[0].material, scene.bodies[1].material).restitution
    v1, v2 = scene.bodies[0].velocity[0], scene.bodies[1].velocity[0]
    u1, u2 = newton(m[0], m[1], v1, v2, e)
    approach = abs(v1 - v2)
    err = max(abs(tr.vel[-1, 0, 0] - u1), abs(tr.vel[-1, 1, 0] - u2)) / approach
    assert err <= 1e-9
    P = np.einsum("k,fki->fi", m, tr.vel)
    assert np.max(np.abs(P - P[0])) / np.linalg.norm(P[0]) <= 1e-12
    gap = np.linalg.norm(tr.pos[:, 1] - tr.pos[:, 0], axis=1) - scene.bodies[0].radius - scene.bodies[1].radius
    assert -gap.min() <= 1e-9  # impact resolved at its time of impact: no penetration
    # stages observable: collision ran, no force stage exists (no gravity)
    st = res.stages
    assert st["narrowphase"]["calls"] > 0 and st["impact"]["calls"] == 1
    assert "gravity" not in st


@pytest.mark.parametrize("m1,m2,v1,v2,e", [
    (0.1, 0.5, 3.0, -1.0, 0.0),
    (2.0, 0.3, 1.5, 0.2, 0.5),
    (0.7, 0.7, 0.9, -0.4, 1.0),
    (5.0, 0.05, 0.3, -7.0, 0.8),
])
def test_head_on_any_masses(tmp_path, m1, m2, v1, v2, e):
    scene = scene_from(tmp_path, f"""
        [scenario]
        family = "t"
        title = "head on"
        duration = 0.4
        dt = 0.0013
        effects = ["contact", "restitution"]
        [material.default]
        restitution = {e}
        [[body]]
        name = "a"
        shape = "sphere"
        radius = 0.05
        mass = {m1}
        velocity = [{v1}, 0, 0]
        [[body]]
        name = "b"
        shape = "sphere"
        radius = 0.03
        mass = {m2}
        position = [0.31, 0, 0]
        velocity = [{v2}, 0, 0]
        """)
    eng = engine_for(scene)
    eng.step(int(round(0.4 / 0.0013)))
    u1, u2 = newton(m1, m2, v1, v2, e)
    err = max(abs(eng.state.v[0, 0] - u1), abs(eng.state.v[1, 0] - u2)) / abs(v1 - v2)
    assert err <= 1e-9
    assert np.allclose(eng.state.v[:, 1:], 0.0, atol=1e-12)
    assert np.allclose(eng.state.w, 0.0, atol=1e-12)


DROP = """
    [scenario]
    family = "t"
    title = "ball drop"
    duration = 3.0
    dt = {dt}
    effects = ["gravity", "contact", "restitution"]
    [material.default]
    restitution = {e}
    [[body]]
    name = "ball"
    shape = "sphere"
    radius = 0.1
    mass = 1.0
    position = [0, 0, 1.1]
    {ground}
    """

GROUNDS = {
    "plane": '[[static]]\n    shape = "plane"\n    normal = [0, 0, 1]',
    "box": '[[static]]\n    shape = "box"\n    half_extents = [2, 2, 0.5]\n    position = [0, 0, -0.5]',
}


def bounce_height(t: np.ndarray, z0: float, e: float, g: float = 9.81) -> np.ndarray:
    """Height of the lowest point of a ball dropped from rest at z0 above a
    floor, bouncing with coefficient e (analytic, piecewise parabolas)."""
    out = np.empty_like(t)
    for i, tt in enumerate(t):
        z, v, t0 = z0, 0.0, 0.0
        while True:
            s = (v + np.sqrt(v * v + 2 * g * z)) / g
            if t0 + s >= tt:
                s = tt - t0
                out[i] = z + v * s - 0.5 * g * s * s
                break
            v, z, t0 = -(v - g * s) * e, 0.0, t0 + s
    return out


@pytest.mark.parametrize("ground", ["plane", "box"])
@pytest.mark.parametrize("dt", [1 / 240, 0.01])
def test_ball_drop_bounce_trajectory(tmp_path, ground, dt):
    scene = scene_from(tmp_path, DROP.format(dt=dt, e=0.9, ground=GROUNDS[ground]))
    eng = engine_for(scene)
    n = int(round(3.0 / dt))
    z = np.empty(n)
    for k in range(n):
        eng.step()
        z[k] = eng.state.x[0, 2]
    t = dt * np.arange(1, n + 1)
    ref = bounce_height(t, 1.0, 0.9) + 0.1
    assert np.max(np.abs(z - ref)) <= 1e-6  # requirement: 1e-3 m
    assert (z >= 0.1 - 1e-9).all()  # no penetration
    assert eng.profile.counters["impacts"] >= 4


def test_ball_comes_to_rest(tmp_path):
    scene = scene_from(tmp_path, DROP.format(dt=1 / 240, e=0.5, ground=GROUNDS["plane"]))
    eng = engine_for(scene)
    eng.step(240 * 3)  # bounces end after ~1.35 s (Zeno sum)
    assert abs(eng.state.x[0, 2] - 0.1) <= 1e-4  # within the correction slop
    assert np.abs(eng.state.v).max() <= 1e-9
    z = eng.state.x[0, 2]
    eng.step(240)
    assert abs(eng.state.x[0, 2] - z) <= 1e-9  # at rest means at rest


def test_no_contact_effect_runs_no_collision(tmp_path):
    scene = scene_from(tmp_path, """
        [scenario]
        family = "t"
        title = "fall"
        duration = 0.5
        dt = 0.01
        effects = ["gravity"]
        [[body]]
        name = "ball"
        shape = "sphere"
        radius = 0.1
        mass = 1.0
        [[static]]
        shape = "plane"
        normal = [0, 0, 1]
        offset = -0.5
        """)
    res = run(scene, "reference")
    assert res.status == "ok"
    st = res.stages
    for stage in ("broadphase", "narrowphase", "solve", "ccd", "impact", "gyroscopic", "springs"):
        assert stage not in st
    assert st["gravity"]["calls"] >= 50 and st["integrate_velocities"]["calls"] == 50
    # exact free fall (rk4 is exact for constant forces), straight through the plane
    tr = res.trace.valid()
    assert abs(tr.pos[-1, 0, 2] - (-0.5 * 9.81 * 0.25)) <= 1e-12


@pytest.mark.parametrize("sid,settings,sparse", [
    ("stacking.column_5", {}, False),
    ("stacking.column_5", {}, True),
    ("stacking.column_5", {"direct_start": False, "iterations": 7}, False),
    ("friction.block_thrown_uphill", {}, False),
    ("friction.rolling_resistance", {"position_correction": "baumgarte"}, False),
    ("stacking.mixed_bin", {"warm_starting": False}, False),
])
def test_fused_solve_is_bit_identical_to_the_phase_by_phase_solve(monkeypatch, sid, settings, sparse):
    """The solve's phases after preparation run as one compiled call
    (engine/contact/phases.py) with the arithmetic, in the order, of the
    per-phase Python driver it replaced (which stays for a replaced
    direct-start policy): the final states are the same bits either way,
    with the dense direct start and with the sparse one (``sparse``:
    forced at every size)."""
    from physbench.engine import solver

    if sparse:
        monkeypatch.setattr(solver, "DIRECT_MAX_ROWS", 0)

    def final(fused: bool):
        monkeypatch.setattr(solver, "PHASE_BY_PHASE", not fused)
        calls = {"fused": 0}
        orig = solver.Solve._solve_compiled

        def spy(self, *a):
            calls["fused"] += 1
            return orig(self, *a)

        # (spied from the build on: a resting start's first solve runs there
        # once, to prime the first step, engine.pipeline._prime_start, and
        # every step of a column may then be the fused steady step, whose
        # solve is the same compiled call inlined)
        monkeypatch.setattr(solver.Solve, "_solve_compiled", spy)
        eng = engine_for(load_scene(sid, overrides={"scenario.duration": 0.3}), settings)
        eng.step(72)
        s = eng.state
        return calls["fused"], [a.copy() for a in (s.x, s.q, s.v, s.w)]

    n_fused, fused = final(True)
    n_phases, phases = final(False)
    assert n_fused > 0 and n_phases == 0
    for f, p in zip(fused, phases):
        assert np.array_equal(f, p)


@pytest.mark.parametrize("sid", ["stacking.mixed_bin", "friction.block_thrown_uphill", "stacking.column_5"])
def test_kept_warm_caches_give_the_bits_of_fresh_ones(monkeypatch, sid):
    """A solve stores its warm-start cache into one of three kept caches
    (engine.contact.warm.WarmPool), never the one it warm-started from nor
    the one its (mini-)step began with (which the step loop restores for
    the reruns of events and friction stops): the final state is the same
    bits as with a fresh cache per solve, and no more than three caches
    are ever handed out."""
    from physbench.engine.contact import warm

    def final(kept: bool):
        seen = {}  # id -> cache (kept alive: ids of freed caches are reused)
        orig = warm.WarmPool.slot

        # (every solve takes the cache it stores into from WarmPool.slot)
        def slot(self, size, busy0, busy1):
            out = orig(self, size, busy0, busy1) if kept else warm.empty_cache(*size)
            assert out is not busy0 and out is not busy1
            seen[id(out)] = out
            return out

        monkeypatch.setattr(warm.WarmPool, "slot", slot)
        eng = engine_for(load_scene(sid, overrides={"scenario.duration": 0.3}), {})
        eng.step(72)
        s = eng.state
        return len(seen), [a.copy() for a in (s.x, s.q, s.v, s.w)]

    n_kept, kept = final(True)
    n_fresh, fresh = final(False)
    assert 0 < n_kept <= warm.WarmPool.SLOTS < n_fresh
    for k, f in zip(kept, fresh):
        assert np.array_equal(k, f)


def test_compiled_colouring_is_the_greedy_colouring():
    """Topology's colouring (compiled, 63-bit masks; Python beyond 63
    colours at a body) is the greedy colouring row by row: no two rows of a
    colour share a dynamic body, each row takes the lowest colour free at
    both its bodies, rows sorted by colour stably."""
    from physbench.engine.contact.rows import colour_order

    rng = np.random.default_rng(3)
    cases = []
    for _ in range(50):
        n, m = int(rng.integers(2, 40)), int(rng.integers(1, 300))
        a, b = rng.integers(0, n, m), rng.integers(0, n + 1, m)
        b[b == a] = n
        cases.append((a, b, n))
    cases.append((np.zeros(100, np.int64), np.arange(1, 101, dtype=np.int64), 101))  # 100 colours at body 0
    for a, b, world in cases:
        order, bounds = colour_order(a, b, world)
        used: dict[int, set] = {}
        col = np.empty(a.size, np.int64)
        for k, (i, j) in enumerate(zip(a.tolist(), b.tolist())):
            taken = used.get(i, set()) | (used.get(j, set()) if j != world else set())
            c = next(c for c in range(a.size + 1) if c not in taken)
            col[k] = c
            used.setdefault(i, set()).add(c)
            if j != world:
                used.setdefault(j, set()).add(c)
        assert np.array_equal(order, np.argsort(col, kind="stable"))
        assert np.array_equal(bounds, np.concatenate([[0], np.cumsum(np.bincount(col))]))


@pytest.mark.parametrize("sid,settings,steady", [
    ("stacking.column_5", {}, 0.5),
    ("friction.rolling_resistance", {}, 0.5),
    ("stacking.column_5", {"direct_start": False, "iterations": 7, "warm_starting": False}, 0.5),
])
def test_steady_steps_solve_in_one_compiled_call(monkeypatch, sid, settings, steady):
    """A steady step (no impact row, the contact graph of the last solve)
    runs, its whole solve stage included, as one compiled call: the fused
    step (engine/fused/steady.py, whose kernel runs
    engine.contact.phases.classify_stage; ``steady`` the least fraction of
    the steps that do), and the final state is the bits of the solve
    phase by phase, stage by stage (the Solve stage itself has no fast
    path: one compiled call after classification, or the phases)."""
    from physbench.engine import solver
    from physbench.engine.fused.steady import NAME

    def final(one_call: bool):
        monkeypatch.setattr(solver, "PHASE_BY_PHASE", not one_call)
        eng = engine_for(load_scene(sid, overrides={"scenario.duration": 0.3}), settings)
        eng.profile.by_stage = not one_call
        eng.step(72)
        s = eng.state
        return eng.profile.as_dict().get(NAME, {}).get("calls", 0), [a.copy() for a in (s.x, s.q, s.v, s.w)]

    calls, one = final(True)
    assert calls >= steady * 72
    none, phased = final(False)
    assert none == 0
    for f, p in zip(one, phased):
        assert np.array_equal(f, p)


def test_friction_stop_gate_lets_through_every_candidate():
    """physbench.engine.contact.prepare.stop_candidate (the compiled test that opens
    Rows.stop_times) is conservative: on random patches, many of them on
    the thresholds, it says True whenever the numpy test of stop_times
    finds a candidate patch (sliding or rolling), and it finds them."""
    from physbench.engine.contact.prepare import patch_velocity, stop_candidate

    rng = np.random.default_rng(5)
    tol = 1e-4
    found = 0
    for trial in range(400):
        npch, nb = int(rng.integers(1, 5)), 3
        m = 2 * npch
        pid = np.repeat(np.arange(npch), 2)
        lam_n = rng.normal(size=m) * (trial % 3 != 0) + 1e-3 * (trial % 3 == 1)
        Jt = rng.normal(size=(npch, 5, 12)) * 10.0 ** rng.integers(-6, 1)
        U = rng.normal(size=(nb + 1, 6))
        U[nb] = 0.0
        pab = np.stack([rng.integers(0, nb, npch), np.full(npch, nb)], axis=1)
        vt0 = rng.normal(size=(npch, 2)) * 10.0 ** rng.integers(-5, 0)
        wr0 = rng.normal(size=(npch, 2)) * 10.0 ** rng.integers(-5, 0)
        mur = np.abs(rng.normal(size=npch)) * (trial % 2)
        ends = np.empty((npch, 2))
        patch_velocity(Jt, U, pab, 0, 2, ends)
        s0 = np.sqrt(vt0[:, 0] ** 2 + vt0[:, 1] ** 2)
        if trial % 4 == 0:  # put the end projection on the threshold
            vt0 *= (tol * (1 + 1e-15)) / s0[:, None]
            s0 = np.sqrt(vt0[:, 0] ** 2 + vt0[:, 1] ** 2)
        tdir = vt0 / np.where(s0 > 0.0, s0, 1.0)[:, None]
        live = np.bincount(pid, lam_n, npch) > 0.0
        tc = live & (s0 > tol) & (np.einsum("km,km->k", ends, tdir) < tol)
        rolling = trial % 2 == 1
        rends = np.empty((npch, 2))
        patch_velocity(Jt, U, pab, 3, 5, rends)
        r0 = np.sqrt(wr0[:, 0] ** 2 + wr0[:, 1] ** 2)
        rdir = wr0 / np.where(r0 > 0.0, r0, 1.0)[:, None]
        rc = live & (mur > 0.0) & (r0 > tol) & (np.einsum("km,km->k", rends, rdir) < tol)
        numpy_says = bool(tc.any() or (rolling and rc.any()))
        gate = stop_candidate(pid, lam_n, Jt, U, pab, vt0, tol, rolling, wr0, mur, tol)
        if numpy_says:
            assert gate, trial
            found += 1
    assert found >= 50
