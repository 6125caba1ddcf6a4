"""The benchmark commands run end to end on tiny sizes and report consistent
rows.  Nothing here asserts a time: only that every figure is measured
(finite, positive), that ratios are the ratios of the figures printed beside
them, and that the broad-phase variants agree on the pairs."""

import gc
import math

import numpy as np
import pytest

from physbench.adapters import get_adapter
from physbench.harness import bench


def _pos(x):
    return isinstance(x, float) and math.isfinite(x) and x > 0


def test_cost_rows_are_consistent():
    pytest.importorskip("pybullet")
    rows = bench.cost(repeats=1, sizes=(8,), steps=3, iterations=4)
    assert [r["scene"] for r in rows] == ["column_10", "spheres_8", "pyramid_10"]
    for r in rows:
        # every engine on the same scenes; the 2D ones only on the planar pyramid
        for e in bench.COST_OTHERS:
            avail = get_adapter(e).capabilities().available
            planar_only = get_adapter(e).capabilities().dimensions == 2
            want = avail and (r["scene"] == "pyramid_10" or not planar_only)
            assert _pos(r[f"{e}_us_per_step"]) == want, (e, r["scene"], r[f"{e}_us_per_step"])
        for k in ("reference_us_per_step", "reference_fast_us_per_step", "pybullet_us_per_step"):
            assert _pos(r[k]), (k, r[k])
        assert r["ratio_reference_over_pybullet"] == pytest.approx(r["reference_us_per_step"] / r["pybullet_us_per_step"])
        assert r["ratio_fast_over_pybullet"] == pytest.approx(r["reference_fast_us_per_step"] / r["pybullet_us_per_step"])


def test_overhead_rows_are_consistent():
    pytest.importorskip("mujoco")
    rows = bench.overhead(["mujoco", "pymunk"], repeats=1, duration=0.05)
    ok = [r for r in rows if r["status"] == "ok"]
    assert {(r["scene"].split()[0], r["engine"]) for r in rows if r["status"] == "unsupported"} == {("column_10", "pymunk")}
    assert len(ok) == 5
    for r in ok:
        for k in ("api", "fast", "bare", "runner"):
            assert _pos(r[f"{k}_us_per_step"]), (k, r)
        assert r["ratio"] == pytest.approx(r["runner_us_per_step"] / r["bare_us_per_step"])
        assert r["ratio_vs_api"] == pytest.approx(r["runner_us_per_step"] / r["api_us_per_step"])
        assert r["ratio_vs_fast"] == pytest.approx(r["runner_us_per_step"] / r["fast_us_per_step"])
        assert r["read_us_per_step"] == pytest.approx(r["bare_us_per_step"] - r["api_us_per_step"])
        assert r["ratio_lo"] == pytest.approx(r["ratio"]) == pytest.approx(r["ratio_hi"])  # one repeat
        assert r["bare_spread"] == 0.0 == r["runner_spread"]


def test_overhead_interleaves_and_reports_the_spread(monkeypatch):
    """Every repeat times api, fast, bare and runner, in alternating order
    (ABAB: the second repeat backwards), each on its own build, with the
    objects alive at the start frozen out of the collector's reach;
    ``ratio`` is of the medians, ``ratio_lo``/``ratio_hi`` the extreme
    runner / bare of one repeat, the spreads (max - min) / median."""
    calls = []
    fake = {"bare_loop": [4.0, 4.0, 4.0], "step": [3.0, 3.0, 3.0], "bare_record": [10.0, 12.0, 11.0]}
    runner_t = [11.0, 12.6, 11.0]

    frozen = []

    def time_bare(engine, scene, steps, settings, loop="bare_loop"):
        frozen.append(gc.get_freeze_count())
        if steps < scene.n_steps:
            return 0.0  # the warm-up
        calls.append(loop)
        return fake[loop][sum(c == loop for c in calls) - 1]

    warm = []

    def time_runner(engine, scene, settings):
        if not warm:  # the warm-up run, before the repeats
            warm.append(1)
            return 0.0
        calls.append("runner")
        return runner_t[calls.count("runner") - 1]

    pytest.importorskip("mujoco")
    monkeypatch.setattr(bench, "_time_bare", time_bare)
    monkeypatch.setattr(bench, "_time_runner", time_runner)
    monkeypatch.setattr(bench, "OVERHEAD_SCENES", bench.OVERHEAD_SCENES[:1])
    (r,) = bench.overhead(["mujoco"], repeats=3)
    assert min(frozen) > 0 and gc.get_freeze_count() == 0  # frozen while timing, every object back after
    assert calls == ["bare_loop", "step", "bare_record", "runner", "runner", "bare_record", "step", "bare_loop",
                     "bare_loop", "step", "bare_record", "runner"]
    assert r["ratio"] == pytest.approx(11.0 / 11.0)
    assert r["ratio_lo"] == pytest.approx(11.0 / 11.0) and r["ratio_hi"] == pytest.approx(11.0 / 10.0)
    assert r["bare_spread"] == pytest.approx(2.0 / 11.0) and r["runner_spread"] == pytest.approx(1.6 / 11.0)


def test_broadphase_scaling_runs_and_fits():
    out = bench.broadphase_scaling(sizes=(40, 120), repeats=1)
    assert [r["n"] for r in out["rows"]] == [40, 120]
    assert all(r["pairs"] > 0 and _pos(r["sap_us"]) for r in out["rows"])
    assert math.isfinite(out["exponents"]["sap"])


def test_broadphase_scaling_times_every_call_on_a_new_cloud(monkeypatch):
    """No timed call sees the input of the call before it on the same
    arrays (a branch predictor would learn one static cloud and flatter the
    small sizes' cost), and the methods still agree on every cloud."""
    import physbench.engine.broadphase as B

    seen = []
    real = B.sap_pairs

    def recording(lo, hi):
        seen.append((id(lo), lo.tobytes()))
        return real(lo, hi)

    monkeypatch.setattr(B, "sap_pairs", recording)
    out = bench.broadphase_scaling(sizes=(200,), repeats=2, brute_max=0)
    assert _pos(out["rows"][0]["sap_us"])
    timed = [b for i, b in seen if sum(j == i for j, _ in seen) > 2]  # the shared arrays' calls
    assert len(timed) >= 2
    assert all(a != b for a, b in zip(timed, timed[1:]))


def test_sphere_cloud_variants_keep_the_statistics():
    """A variant is a new cloud of the same statistics: the same n and cube,
    every tenth sphere touching the previous one, about as many pairs;
    variant 0 is the base cloud, and a variant is reproducible."""
    from physbench.engine.broadphase import sap_pairs

    n, r, spacing = 3000, 0.05, 2.5
    base = bench.sphere_cloud(n)
    side = spacing * r * n ** (1 / 3)
    e = r + 1e-4
    pairs0 = sap_pairs(*base)[0].size
    for j in (1, 2):
        lo, hi = bench.sphere_cloud(n, variant=j)
        c = lo + e
        assert lo.shape == (n, 3) and not np.array_equal(lo, base[0])
        np.testing.assert_array_equal(lo, bench.sphere_cloud(n, variant=j)[0])
        free = np.ones(n, bool)
        free[1::10] = False
        assert c[free].min() >= 0.0 and c[free].max() < side
        np.testing.assert_allclose(c[1::10] - c[0:-1:10][: c[1::10].shape[0]], [[2 * r, 0.0, 0.0]] * (n // 10),
                                   atol=1e-12)
        assert abs(sap_pairs(lo, hi)[0].size - pairs0) < 0.1 * pairs0


def test_build_cost_reports_time_and_peak_memory():
    out = bench.build_cost(n=300, repeats=1)
    assert out["n"] == 300
    assert _pos(out["build_s"]) and _pos(out["peak_mb"])


def test_broadphase_scaling_times_the_stage_path():
    out = bench.broadphase_scaling(sizes=(40, 120), repeats=1)
    assert all(_pos(r["stage_us"]) and _pos(r["stage_fresh_us"]) for r in out["rows"])
    assert math.isfinite(out["exponents"]["stage"]) and math.isfinite(out["exponents"]["stage_fresh"])


def test_step_scaling_reports_every_stage_and_fits():
    out = bench.step_scaling(sizes=(8, 27), steps=3)
    assert [r["n"] for r in out["rows"]] == [8, 27]
    for r in out["rows"]:
        assert _pos(r["build_s"]) and _pos(r["step_us"])
        for k in ("integrate_velocities", "broadphase", "narrowphase", "solve", "integrate_positions"):
            assert _pos(r[f"{k}_us"]), (k, r)
    ex = out["exponents"]
    assert math.isfinite(ex["step"]) and math.isfinite(ex["broadphase"]) and math.isfinite(ex["n_log_n"])


def test_compile_bench_runs_cold_on_an_empty_cache_and_warm_on_the_one_it_filled(monkeypatch):
    """``physbench bench compile``: each cold measurement starts on a new,
    empty NUMBA_CACHE_DIR; the warm one of the same command reuses the
    cache the cold one filled; rows carry the figures each child reported
    (no real compile here: the children are stood in for)."""
    import json
    import os

    calls = []

    def child(cmd, cache, timeout, jobs=None):
        calls.append((cmd, cache, sorted(os.listdir(cache)), jobs))
        with open(os.path.join(cache, f"marker{len(calls)}"), "w"):
            pass
        out = json.dumps({"first_step_s": 0.5, "wall_s": 1.0, "cpu_s": 0.75, "compiled": ["a", "b"]})
        return {"wall_s": 2.0 + len(calls), "cpu_s": 1.5, "stdout": out + "\n"}

    monkeypatch.setattr(bench, "_child", child)
    rows = bench.compile_time("billiards.head_on", everything=True)
    assert [r["measure"].split(", ", 1)[1] for r in rows] == ["cold", "warm", "cold, one process", "cold", "warm",
                                                              "cold"]
    (c1, d1, l1, j1), (c2, d2, l2, j2), (c3, d3, l3, j3), (c4, d4, l4, j4), (c5, d5, l5, j5), (c6, d6, l6, j6) = calls
    assert l1 == [] and l3 == [] and l4 == [] and l6 == []  # cold: an empty cache
    assert d2 == d1 and l2 == ["marker1"] and d5 == d4 and l5 == ["marker4"]  # warm: the cold run's cache
    assert len({d1, d3, d4, d6}) == 4
    assert j3 == 1 and {j1, j2, j4, j5, j6} == {None}  # one process beside the user's way (a helper)
    assert c1[-7:] == ["run", "billiards.head_on", "-e", "reference", "--json", "--timeout", "3600.0"]
    assert c3 == c4 and c4[-1] == "billiards.head_on" and len(c6) > 10  # every shipped scenario in one process
    assert [r["wall_s"] for r in rows] == [3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    assert rows[0]["first_step_s"] is None and rows[3]["first_step_s"] == 0.5 and rows[5]["compiled"] == 2
    assert not any(os.path.exists(d) for d in (d1, d3, d4, d6))  # temporary


def test_compile_bench_start_reports_the_warm_start_in_parts(monkeypatch):
    """The compile benchmark's build-and-step process (bench._START_CODE)
    reports the first scenario's start in parts: import, build (of it the
    engine's JIT time: loading kernels) and the libraries numba loaded from
    its cache; the parts lie within the seconds to the first step, and the
    rows carry them."""
    import json
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k in ("PATH", "HOME", "NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    runs = []
    for _ in range(2):  # (the second on the cache the first filled, if it was cold)
        out = subprocess.run([sys.executable, "-c", bench._START_CODE, "billiards.head_on"], capture_output=True,
                             text=True, env=env, timeout=900)
        assert out.returncode == 0, out.stderr
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    info = runs[1]
    assert info["compiled"] == []  # warm: everything loaded
    assert info["loaded"] > 10  # (head_on's flight, broad and narrow phase, solve, impact, fused steps)
    assert 0 < info["imports_s"] and 0 < info["jit_s"] <= info["build_s"]
    assert info["imports_s"] + info["build_s"] < info["first_step_s"] <= info["wall_s"]
    rows = []

    def child(cmd, cache, timeout, jobs=None):
        rows.append(cmd)
        return {"wall_s": 1.0, "cpu_s": 1.0, "stdout": json.dumps(info) + "\n"}

    monkeypatch.setattr(bench, "_child", child)
    got = bench.compile_time("billiards.head_on", everything=False)
    warm = got[-1]
    assert warm["measure"] == "build and step billiards.head_on, warm"
    assert warm["loaded"] == info["loaded"] and warm["imports_s"] == round(info["imports_s"], 2)
    assert warm["build_s"] == round(info["build_s"], 2) and warm["jit_s"] == round(info["jit_s"], 2)
    assert got[0]["loaded"] is None and got[0]["imports_s"] is None  # (physbench run: no parts)


@pytest.mark.parametrize("engine", ["mujoco", "pymunk", "pybullet", "rapier", "box2d"])
def test_bare_record_steps_the_same_simulation(engine):
    """The overhead benchmark's bare loop (Adapter.bare_record: step call and
    raw state read, kept) advances the scene exactly as the adapter's
    step(n): the same state bit for bit, on the bench's planar pyramid
    (contacts and friction), so `ratio` compares like with like."""
    cls = get_adapter(engine)
    if not cls.capabilities().available:
        pytest.skip(f"{engine} not installed")
    scene = bench.pyramid_scene(4)
    states = []
    for loop in ("step", "bare_record"):
        a = cls()
        a.build(scene, cls.resolve_settings(scene))
        if loop == "step":
            a.step(300)
        else:
            a.bare_record(300, scene.n_bodies)
        out = [np.empty((scene.n_bodies, k)) for k in (3, 4, 3, 3)]
        a.read_state(*out)
        a.close()
        states.append(out)
    assert np.abs(states[0][0][:, 2] - 0.1).max() < 1.0  # the pyramid is there, finite
    for x, y in zip(*states):
        np.testing.assert_array_equal(x, y)
