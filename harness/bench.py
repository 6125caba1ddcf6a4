"""Benchmarks: ratios measured side by side in one run (machines are noisy).

Two benchmarks, each a table of scenes ``{name, create, steps}`` in the
style of Box2D's benchmark, timed interleaved over several repeats; medians
and ratios are printed, never asserted in tests:

- ``overhead``: per engine, the same scene stepped by the runner with full
  state recording every step vs the bare loop (``Adapter.bare_record``: the
  engine's step call and its cheapest read of every body's state, in a
  Python loop), vs the step call alone (``Adapter.bare_loop(n)``) and vs the
  adapter's fastest bare stepping (``Adapter.step(n)``), all after the same
  build.  Ratios runner / each.
- ``cost``: the reference engine vs pybullet (maximal coordinates) on the same
  scenes (a 10-box column, 100 and 1000 spheres on a plane, a planar
  10-box pyramid) at the same dt and solver iterations: per-step CPU time and
  their ratio, plus the reference engine's broad-phase cost per step against
  n (fitted exponent); MuJoCo, pymunk, Rapier and Box2D per-step CPU time on
  the same scenes at their own defaults.
- ``broadphase_scaling``: the reference engine's broad phase alone (what
  the stage runs, from its kept order and from a fresh one; the general
  ``sap_pairs``; all pairs) on random sphere clouds of constant density,
  100 to 10000 bodies, a new cloud of the same statistics at every timed
  call (not one input the branch predictor learns): cost against n.
- ``step_scaling``: the reference engine stepping 100 to 10000 spheres
  dropped on a plane: build, step and per-stage cost against n.
- ``build_cost``: the reference engine's build (scene translation, model,
  pipeline) of an n-sphere scene: CPU time and peak Python allocations.
"""

from __future__ import annotations

import gc
import math
import statistics
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from physbench.adapters import get_adapter
from physbench.harness.runner import run
from physbench.harness.workers import COMPILE_JOBS_ENV
from physbench.contract.scene import Scene, canonical_example, compile_scene, load_scene
from physbench.contract.spec import validate_raw


@dataclass(frozen=True)
class BenchScene:
    name: str
    create: Callable[[], Scene]
    steps: int


def _scene(raw: dict[str, Any]) -> Scene:
    return compile_scene(validate_raw(raw, "<bench>"))


def column_scene(n: int = 10, dt: float = 1 / 240) -> Scene:
    return _scene({
        "scenario": {"family": "bench", "title": f"{n}-box column", "duration": 1.0, "dt": dt,
                     "effects": ["gravity", "contact", "friction"]},
        "material": {"default": {"friction": 0.5, "static_friction": 0.5}},
        "body": [{"name": "box", "shape": "box", "half_extents": [0.1, 0.1, 0.1], "mass": 1.0,
                  "position": [0.0, 0.0, 0.1], "pattern": {"kind": "column", "count": n}}],
        "static": [{"shape": "plane", "normal": [0.0, 0.0, 1.0], "offset": 0.0}],
    })


def spheres_scene(n: int, dt: float = 1 / 240) -> Scene:
    """A grid of spheres dropped on a plane: side x side x nz, exactly ``n``
    when some side <= n^(1/3) squares into it (100: 5x5x4, 1000: 10^3,
    10000: 20x20x25), else the next whole layer up."""
    cube = max(1, round(n ** (1 / 3)))
    side = next((s for s in range(cube, 0, -1) if n % (s * s) == 0 and s * s <= n), cube)
    nz = max(1, math.ceil(n / (side * side)))
    r = 0.05
    return _scene({
        "scenario": {"family": "bench", "title": f"{side * side * nz} spheres", "duration": 1.0, "dt": dt,
                     "effects": ["gravity", "contact", "friction"]},
        "material": {"default": {"friction": 0.5, "static_friction": 0.5}},
        "body": [{"name": "ball", "shape": "sphere", "radius": r, "mass": 0.1,
                  "position": [0.0, 0.0, r + 0.01],
                  "pattern": {"kind": "grid", "counts": [side, side, nz], "spacing": 2.2 * r}}],
        "static": [{"shape": "plane", "normal": [0.0, 0.0, 1.0], "offset": 0.0}],
    })


def _head_on() -> Scene:
    return load_scene(canonical_example())


def pyramid_scene(levels: int = 4, dt: float = 1 / 240) -> Scene:
    """A planar pyramid of boxes (levels (levels + 1) / 2 boxes), x-z plane."""
    return _scene({
        "scenario": {"family": "bench", "title": f"{levels}-level pyramid", "duration": 1.0, "dt": dt,
                     "planar": True, "effects": ["gravity", "contact", "friction"]},
        "material": {"default": {"friction": 0.5, "static_friction": 0.5}},
        "body": [{"name": "box", "shape": "box", "half_extents": [0.1, 0.1, 0.1], "mass": 1.0,
                  "position": [0.0, 0.0, 0.1], "pattern": {"kind": "pyramid", "count": levels, "gap": 0.002}}],
        "static": [{"shape": "plane", "normal": [0.0, 0.0, 1.0], "offset": 0.0}],
    })


def _time_bare(engine: str, scene: Scene, steps: int, settings: dict[str, Any] | None,
               loop: str = "bare_loop") -> float:
    """CPU seconds of ``steps`` steps by the adapter's ``loop`` method
    (``bare_loop``: the engine's public step call in a Python loop;
    ``step``: the adapter's fastest stepping, e.g. MuJoCo's C loop;
    ``bare_record``: the public step call and the engine's cheapest read of
    every body's state after each step), after the same build as the
    runner's."""
    cls = get_adapter(engine)
    a = cls()
    a.build(scene, cls.resolve_settings(scene, settings))
    f = getattr(a, loop)
    c0 = time.process_time()
    if loop == "bare_record":
        f(steps, scene.n_bodies)
    else:
        f(steps)
    c = time.process_time() - c0
    a.close()
    return c


def _time_runner(engine: str, scene: Scene, settings: dict[str, Any] | None) -> float:
    r = run(scene, engine, settings, compute_metrics=False)
    if r.status != "ok":
        raise RuntimeError(f"{engine}: {r.status}: {r.message}")
    return r.timing["step_cpu_s"]


# Scenes of the overhead benchmark, with simulated durations long enough that
# each timed run takes ~0.05-0.2 s on MuJoCo (the noise of a short run is
# larger than the effect measured).
OVERHEAD_SCENES = [
    (BenchScene("head_on (2 spheres)", _head_on, 0), 40.0),
    (BenchScene("column_10 (boxes)", lambda: column_scene(10, 1 / 240), 0), 10.0),
    (BenchScene("pyramid_10 (planar boxes)", lambda: pyramid_scene(4), 0), 10.0),
]


def overhead(engines: list[str], repeats: int = 5, duration: float | None = None) -> list[dict[str, Any]]:
    """Runner-with-recording vs bare engine loops, interleaved.  Returns rows.

    Per scene and engine, each repeat times, one after the other on fresh
    builds: the engine's public step call in a Python loop (``api``, e.g.
    ``mujoco.mj_step(m, d)`` or ``space.step(dt)``); the adapter's fastest
    bare stepping (``fast``: MuJoCo's ``mj_step(m, d, n)`` looping in C,
    pymunk's cpSpaceStep without its Python wrapper); the bare loop (``bare``:
    the public step call and, after every step, the engine's cheapest read
    of every body's position, orientation and velocities in its own form,
    ``Adapter.bare_record``: what any caller recording a trajectory pays at
    least); and the runner recording every step.  The order alternates
    from one repeat to the next (api, fast, bare, runner; then runner,
    bare, fast, api; ...), so that a machine getting busier or quieter
    during the repeats weighs on bare and runner alike.

    ``ratio`` = runner / bare (the runner's own overhead: conversion,
    storage, checks), ``ratio_vs_api`` = runner / api and ``ratio_vs_fast``
    = runner / fast (what recording costs in all over stepping alone),
    ``read_us_per_step`` = bare - api (the engine's read), all of medians
    over repeats; the spread: ``ratio_lo`` and ``ratio_hi``, the least and
    the greatest runner / bare of one repeat, and ``bare_spread`` and
    ``runner_spread``, (max - min) / median of each timing over repeats.

    The objects alive when it starts (the imported engines and libraries,
    ~10^5) are frozen out of the garbage collector's reach meanwhile
    (``gc.freeze``): a full collection, which a timed loop may set off,
    then scans only what the benchmark made since, not ~0.1 s of the
    process's imports (measured), on whichever side of a ratio it falls.
    """
    gc.collect()
    gc.freeze()
    try:
        return _overhead(engines, repeats, duration)
    finally:
        gc.unfreeze()


def _overhead(engines: list[str], repeats: int, duration: float | None) -> list[dict[str, Any]]:
    rows = []
    for bs, dur in OVERHEAD_SCENES:
        scene0 = bs.create()
        scene = Scene(**{**scene0.__dict__, "duration": duration or dur})
        for engine in engines:
            cls = get_adapter(engine)
            if cls.unsupported_reason(scene) is not None:
                rows.append({"scene": bs.name, "engine": engine, "status": "unsupported"})
                continue
            steps = scene.n_steps
            times: dict[str, list[float]] = {"api": [], "fast": [], "bare": [], "runner": []}
            timers = {
                "api": lambda: _time_bare(engine, scene, steps, None, "bare_loop"),
                "fast": lambda: _time_bare(engine, scene, steps, None, "step"),
                "bare": lambda: _time_bare(engine, scene, steps, None, "bare_record"),
                "runner": lambda: _time_runner(engine, scene, None),
            }
            _time_bare(engine, scene, min(steps, 200), None)  # warm-up (imports, caches)
            _time_runner(engine, scene, None)
            order = list(timers)
            for i in range(repeats):
                for k in (order if i % 2 == 0 else order[::-1]):
                    times[k].append(timers[k]())
            ma, mf, mb, mr = (statistics.median(times[k]) for k in order)
            paired = [r / b for r, b in zip(times["runner"], times["bare"])]
            rows.append({
                "scene": bs.name, "engine": engine, "status": "ok", "steps": steps,
                "api_us_per_step": 1e6 * ma / steps,
                "fast_us_per_step": 1e6 * mf / steps,
                "bare_us_per_step": 1e6 * mb / steps,
                "runner_us_per_step": 1e6 * mr / steps,
                "ratio": mr / mb,
                "ratio_lo": min(paired),
                "ratio_hi": max(paired),
                "bare_spread": (max(times["bare"]) - min(times["bare"])) / mb,
                "runner_spread": (max(times["runner"]) - min(times["runner"])) / mr,
                "ratio_vs_api": mr / ma,
                "ratio_vs_fast": mr / mf,
                "read_us_per_step": 1e6 * (mb - ma) / steps,
            })
    return rows


#: the reference engine's cheapest sound configuration: semi-implicit Euler
#: (one force evaluation, as pybullet) and CCD only for fast bodies (``toi``)
#: instead of resolving every impact at its time of impact (``events``).
#: The direct start of resting contacts stays on: without it the column's
#: Gauss-Seidel sweeps never meet their tolerance and the step costs twice as
#: much (measured 3.3 ms against 1.6 ms), besides drifting.
REFERENCE_FAST_SETTINGS = {"integrator": "semi_implicit_euler", "ccd": "toi"}


#: engines timed beside the reference and pybullet in ``cost``, each at its
#: own default settings (their solver settings mean different things:
#: Rapier's iterations and Box2D's substeps are substeps of a soft step)
COST_OTHERS = ("mujoco", "pymunk", "rapier", "box2d")


def cost(repeats: int = 3, sizes: tuple[int, ...] = (100, 1000), steps: int = 120,
         iterations: int = 10, others: tuple[str, ...] = COST_OTHERS) -> list[dict[str, Any]]:
    """Reference engine vs pybullet per-step cost on the same scenes,
    interleaved.  Same dt (1/240) and solver iterations for both.  The
    reference runs twice: at its defaults (accurate) and with
    REFERENCE_FAST_SETTINGS (its cheapest sound configuration), so the
    table shows what its accuracy costs as well as how far its floor is from
    pybullet's.  Every engine of ``others`` is timed on the same scenes at
    its default settings (``<engine>_us_per_step``; NaN where it cannot run
    the scene: the 2D engines run only the planar pyramid)."""
    table = [BenchScene("column_10", lambda: column_scene(10), steps)]
    table += [BenchScene(f"spheres_{n}", (lambda n=n: spheres_scene(n)), steps) for n in sizes]
    table += [BenchScene("pyramid_10", lambda: pyramid_scene(4), steps)]
    configs = {
        "reference": ("reference", {"iterations": iterations}),
        "reference_fast": ("reference", {"iterations": iterations, **REFERENCE_FAST_SETTINGS}),
        "pybullet": ("pybullet", {"iterations": iterations}),
    }
    configs.update({e: (e, {}) for e in others})
    rows = []
    for bs in table:
        scene0 = bs.create()
        scene = Scene(**{**scene0.__dict__, "duration": bs.steps * scene0.dt})
        times: dict[str, list[float]] = {k: [] for k in configs}
        broad: list[float] = []
        for _ in range(repeats):
            for name, (engine, settings) in configs.items():
                cls = get_adapter(engine)
                if cls.unsupported_reason(scene) is not None:
                    continue
                a = cls()
                st = cls.resolve_settings(scene, settings)
                a.build(scene, st)
                c0 = time.process_time()
                a.step(bs.steps)
                times[name].append((time.process_time() - c0) / bs.steps)
                if name == "reference":
                    prof = a.stages()
                    b = _stage_time(prof, "broadphase")
                    if b is not None:
                        broad.append(b / bs.steps)
                a.close()
        ref, fast, pb = (statistics.median(times[k]) for k in ("reference", "reference_fast", "pybullet"))
        row = {"scene": bs.name, "bodies": scene.n_bodies, "reference_us_per_step": 1e6 * ref,
               "pybullet_us_per_step": 1e6 * pb, "ratio_reference_over_pybullet": ref / pb,
               "reference_fast_us_per_step": 1e6 * fast, "ratio_fast_over_pybullet": fast / pb,
               "reference_broadphase_us_per_step": 1e6 * statistics.median(broad) if broad else float("nan")}
        for e in others:
            row[f"{e}_us_per_step"] = 1e6 * statistics.median(times[e]) if times[e] else float("nan")
        rows.append(row)
    return rows


def sphere_cloud(n: int, seed: int = 0, radius: float = 0.05, spacing: float = 2.5,
                 margin: float = 1e-4, variant: int = 0, jitter: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (lo, hi), each (n, 3) m, of n spheres of one radius at random
    in a cube of side ``L = spacing * radius * n^(1/3)`` (constant
    density: ~13 % of the volume filled at 2.5), grown by the contact
    margin; every tenth sphere is moved to touch the previous one (centres
    2 radii apart along x).

    ``variant`` j > 0: the same cloud with every centre moved by a uniform
    offset of at most ``jitter * spacing * radius`` per axis (seeded by
    (seed, j)), wrapped into the cube (so the centres stay uniform in it),
    the touching pairs made again: a new input of the same statistics for
    a benchmark that must not time the branch predictor learning one input
    (tests/test_bench.py::test_sphere_cloud_variants_keep_the_statistics)."""
    rng = np.random.default_rng(seed)
    side = spacing * radius * n ** (1 / 3)
    c = rng.uniform(0.0, side, (n, 3))
    if variant:
        step = jitter * spacing * radius
        c = np.mod(c + np.random.default_rng([seed, variant]).uniform(-step, step, (n, 3)), side)
    c[1::10] = c[0:-1:10][: c[1::10].shape[0]] + [2 * radius, 0.0, 0.0]
    e = radius + margin
    return c - e, c + e


def _time_call(f: Callable[[], Any], min_s: float = 0.02) -> float:
    """Seconds per call of f: enough calls to last ``min_s``."""
    k = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(k):
            f()
        t = time.perf_counter() - t0
        if t >= min_s:
            return t / k
        k *= 2 if t <= 0 else max(2, min(16, int(1.5 * min_s / t) + 1))


def _time_varied(f: Callable[[], Any], inputs: list[tuple[np.ndarray, ...]], into: tuple[np.ndarray, ...],
                 start: int = 1, min_s: float = 0.02) -> tuple[float, int]:
    """Seconds per call of f, each call on the next of ``inputs`` in turn
    (from index ``start``), copied into the arrays ``into`` that f reads
    (the same memory, other values) untimed: calls until they last
    ``min_s`` in all, the copies not counted.  Returns (seconds per call,
    the index the next call would take)."""
    total, k, i = 0.0, 0, start
    while total < min_s or k == 0:
        for dst, src in zip(into, inputs[i % len(inputs)]):
            np.copyto(dst, src)
        t0 = time.perf_counter()
        f()
        total += time.perf_counter() - t0
        k += 1
        i += 1
    return total / k, i


def broadphase_scaling(sizes: tuple[int, ...] = (100, 300, 1000, 3000, 10000), repeats: int = 5,
                       brute_max: int = 3000, variants: int = 8, jitter: float = 0.2) -> dict[str, Any]:
    """The broad phase's body-body pairs alone on constant-density sphere
    clouds, timed interleaved, medians of ``repeats``.  Every timed call
    gets a new input: ``variants`` clouds of the same statistics
    (:func:`sphere_cloud` ``variant`` 0..variants-1 at ``jitter``) in turn,
    copied into the same arrays (untimed), so that no method is timed on an
    input the CPU's branch predictor has learnt.  ``stage`` is what the
    stage runs every step (``engine.sap.SapBuffers.run``: its sort order,
    axis and dense flag kept from the call before, on the cloud before, as
    in a steady run; its first call, which builds them, is not timed),
    ``stage_fresh`` the same from a fresh order
    (``engine.broadphase.stage_pairs``), ``sap`` the general path the stage
    falls back to (``sap_pairs``) and ``brute`` the all-pairs test (up to
    ``brute_max``).  Every method's pairs are checked equal on each cloud.
    Returns ``{"rows": [{n, pairs, stage_us, stage_fresh_us, sap_us,
    brute_us}], "exponents": {method: k}}``, ``pairs`` the base cloud's,
    k the least-squares slope of log time against log n, with ``n_log_n``:
    the slope of n log n over the same sizes for reference."""
    from physbench.engine.broadphase import brute_pairs, sap_pairs, stage_pairs
    from physbench.engine.sap import _FALLBACK, SapBuffers

    methods = ("stage", "stage_fresh", "sap", "brute")
    rows = []
    for n in sizes:
        clouds = [sphere_cloud(n, variant=j, jitter=jitter) for j in range(max(1, variants))]
        lo, hi = (x.copy() for x in clouds[0])
        kept = SapBuffers(n)
        pairs = 0
        for j, (cl, ch) in enumerate(clouds):
            a, b = sap_pairs(cl, ch)
            pairs = pairs or int(a.size)
            np.copyto(lo, cl), np.copyto(hi, ch)
            k = kept.run(lo, hi)
            checks = [stage_pairs(cl, ch), (kept.pi[:k], kept.pj[:k]) if k != _FALLBACK else (a, b)]
            if n <= brute_max and j == 0:
                checks.append(brute_pairs(cl, ch))
            for other in checks:
                if not (np.array_equal(a, other[0]) and np.array_equal(b, other[1])):
                    raise AssertionError(f"broad phase methods disagree at n = {n}, cloud {j}")
        np.copyto(lo, clouds[0][0]), np.copyto(hi, clouds[0][1])
        kept.run(lo, hi)  # the kept order of cloud 0: the timed calls start at cloud 1
        funcs = {"stage": lambda: kept.run(lo, hi), "stage_fresh": lambda: stage_pairs(lo, hi),
                 "sap": lambda: sap_pairs(lo, hi)}
        if n <= brute_max:
            funcs["brute"] = lambda: brute_pairs(lo, hi)
        times: dict[str, list[float]] = {k: [] for k in funcs}
        # per method the next cloud: the stage's kept order is always the
        # one of the cloud before its call's
        nxt = dict.fromkeys(funcs, 1)
        for _ in range(repeats):
            for k, f in funcs.items():
                t, nxt[k] = _time_varied(f, clouds, (lo, hi), start=nxt[k])
                times[k].append(t)
        row: dict[str, Any] = {"n": n, "pairs": pairs}
        for k in methods:
            row[f"{k}_us"] = 1e6 * statistics.median(times[k]) if k in times else float("nan")
        rows.append(row)
    return {"rows": rows, "exponents": _exponents(rows, methods)}


def _exponents(rows: list[dict[str, Any]], keys, n_key: str = "n", suffix: str = "_us") -> dict[str, float]:
    """Per key, the fitted exponent of ``row[key + suffix]`` against
    ``row[n_key]`` over the rows where it is a positive number (NaN with
    fewer than two), and ``n_log_n``: n log n's over the same sizes."""
    out: dict[str, float] = {}
    for k in keys:
        ok = [r for r in rows if r.get(f"{k}{suffix}", float("nan")) > 0]
        out[k] = fit_exponent([r[n_key] for r in ok], [r[f"{k}{suffix}"] for r in ok]) if len(ok) >= 2 else float("nan")
    ns = [r[n_key] for r in rows]
    out["n_log_n"] = fit_exponent(ns, [n * math.log(n) for n in ns]) if len(ns) >= 2 else float("nan")
    return out


def step_scaling(sizes: tuple[int, ...] = (100, 1000, 3000, 10000), steps: int = 40,
                 settings: dict[str, Any] | None = None) -> dict[str, Any]:
    """The reference engine stepping a grid of n spheres dropped on a plane
    (:func:`spheres_scene`), ``steps`` steps after its build: build CPU
    seconds, CPU per step and each pipeline stage's time per step (the
    engine's profile by stage: the staged step), and the fitted exponent of each against n.  Returns
    ``{"rows": [{n, build_s, step_us, <stage>_us, ...}], "exponents":
    {"step": k, <stage>: k, "n_log_n": k}}``."""
    cls = get_adapter("reference")
    rows = []
    stages: list[str] = []
    for n in sizes:
        scene0 = spheres_scene(n)
        scene = Scene(**{**scene0.__dict__, "duration": steps * scene0.dt})
        a = cls()
        t0 = time.process_time()
        a.build(scene, cls.resolve_settings(scene, settings))
        build = time.process_time() - t0
        # every stage timed on its own: the fused calls (the steady and the
        # contact-free step, engine/fused/steady.py) time several stages as one
        a.profile.by_stage = True
        t0 = time.process_time()
        a.step(steps)
        row: dict[str, Any] = {"n": n, "build_s": build, "step_us": 1e6 * (time.process_time() - t0) / steps}
        for k, v in a.stages().items():
            if isinstance(v, dict) and "cpu_s" in v:
                row[f"{k}_us"] = 1e6 * v["cpu_s"] / steps
                stages += [k] if k not in stages else []
        a.close()
        rows.append(row)
    return {"rows": rows, "exponents": _exponents(rows, ["step", *stages])}


def build_cost(n: int = 10000, repeats: int = 3) -> dict[str, Any]:
    """The reference engine's build of ``n`` spheres on a plane
    (:func:`spheres_scene`): the scene's translation, the model and the
    pipeline (``adapters.reference.engine_for``), no step.  Returns ``{n,
    build_s, peak_mb}``: the median CPU time (s) of ``repeats`` builds and
    the peak of Python allocations (MB, tracemalloc: numpy arrays included)
    during one more."""
    import tracemalloc

    from physbench.adapters.reference import engine_for

    scene = spheres_scene(n)
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        engine_for(scene, {})
        times.append(time.process_time() - t0)
    tracemalloc.start()
    try:
        engine_for(scene, {})
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return {"n": n, "build_s": statistics.median(times), "peak_mb": peak / 1e6}


def _stage_time(profile: dict[str, Any], name: str) -> float | None:
    """Total CPU seconds of stage ``name`` from a reference-engine profile
    (``{stage: {"calls": n, "cpu_s": t}}`` or ``{stage: {"time_s": t}}``)."""
    for key, val in profile.items():
        if name in key and isinstance(val, dict):
            for tkey in ("cpu_s", "time_s", "seconds", "wall_s"):
                if tkey in val:
                    return float(val[tkey])
    return None


def fit_exponent(ns: list[int], ts: list[float]) -> float:
    """Least-squares slope of log t against log n."""
    return float(np.polyfit(np.log(ns), np.log(ts), 1)[0])


def print_rows(rows: list[dict[str, Any]], title: str) -> None:
    from rich.console import Console
    from rich.table import Table

    if not rows:
        return
    cols = list(dict.fromkeys(k for r in rows for k in r))
    t = Table(*cols, title=title)
    for r in rows:
        t.add_row(*[f"{r[c]:.4g}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols])
    # wide enough for every header in full: the names are the figures' units
    Console(width=max(120, sum(max(len(c), 10) + 3 for c in cols) + 4)).print(t)


# ---------------------------------------------------------------------------
# compile time (the reference engine's cold and warm start)

#: a fresh process: build the reference engine for each scenario id given
#: (default variant, default settings), step it 3 steps; prints one JSON
#: object: seconds from the process' start to the first step done, CPU s,
#: the functions numba compiled (numba's ``numba:compile`` events; a cache
#: hit raises none) and the first scenario's start in parts: seconds to
#: import the adapter and the scene loader (``imports_s``), to build its
#: engine (``build_s``), of which loading or compiling kernels
#: (``jit_s``: the engine's own account, engine/jit.py), and the compiled
#: libraries numba loaded from its on-disk cache (``loaded``: the cache
#: hits of every dispatcher in the process)
_START_CODE = """
import json, sys, time
t0 = time.perf_counter()
from numba.core import event
names = set()
with event.install_recorder("numba:compile") as rec:
    from physbench.adapters.reference import engine_for
    from physbench.contract.scene import load_scene
    parts = {"imports_s": time.perf_counter() - t0}
    first = None
    for sid in sys.argv[1:]:
        scene = load_scene(sid)
        t1 = time.perf_counter()
        eng = engine_for(scene)
        if first is None:
            parts.update(build_s=time.perf_counter() - t1, jit_s=eng.profile.jit_s)
        eng.step(3)
        if first is None:
            first = time.perf_counter() - t0
            import gc
            from numba.core.dispatcher import Dispatcher
            parts["loaded"] = sum(sum(d.stats.cache_hits.values()) for d in gc.get_objects()
                                  if isinstance(d, Dispatcher))
names = sorted({e.data["dispatcher"].py_func.__qualname__ for _, e in rec.buffer if e.is_start})
print(json.dumps({"first_step_s": first, "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time(),
                  "compiled": names, **parts}))
"""


def _child(cmd: list[str], cache: str, timeout: float, jobs: int | None = None) -> dict[str, Any]:
    """Run ``cmd`` with NUMBA_CACHE_DIR ``cache`` (and a reference build's
    compile processes ``jobs``: PHYSBENCH_COMPILE_JOBS; None: as this
    process has it): its wall s, its (and its children's) CPU s, its
    stdout."""
    import os
    import resource
    import subprocess

    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    if jobs is not None:
        env[COMPILE_JOBS_ENV] = str(jobs)
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:4])} ... exited {out.returncode}: {out.stderr[-2000:]}")
    return {"wall_s": wall, "cpu_s": (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), "stdout": out.stdout}


def compile_time(scenario: str = "billiards.head_on", everything: bool = True,
                 timeout: float = 3600.0) -> list[dict[str, Any]]:
    """The reference engine's start, each in fresh processes: ``physbench
    run <scenario> -e reference`` with an empty compiled-kernel cache
    (cold: a temporary NUMBA_CACHE_DIR) and again on the cache it filled
    (warm); a process building the scenario's engine and stepping it, cold
    and warm (seconds to its first step, the functions numba compiled); and
    with ``everything``, one process building and stepping every shipped
    scenario the reference engine runs on an empty cache (what they all
    compile).  The cold builds run as a user's would: with a helper process
    where two cores may be used (engine/compile_share.py); the cold build
    of the scenario also in one process (``PHYSBENCH_COMPILE_JOBS=1``),
    beside it.  Rows: wall s, CPU s (the process, its workers and a
    build's helper), seconds to the first step, the number of functions
    compiled in the building process (not its helper's); for a process
    building and stepping, the first scenario's start in parts: seconds
    to import (``imports_s``), to build (``build_s``; ``jit_s`` of it
    loading or compiling kernels) and the compiled libraries loaded from
    the cache (``loaded``)."""
    import json
    import sys
    import tempfile

    from physbench.contract.scene import scenario_ids

    rows: list[dict[str, Any]] = []

    def row(what: str, r: dict[str, Any], first=None, compiled=None, info=None) -> None:
        info = info or {}
        rows.append({"measure": what, "wall_s": round(r["wall_s"], 2), "cpu_s": round(r["cpu_s"], 2),
                     "first_step_s": None if first is None else round(first, 2),
                     "compiled": None if compiled is None else len(compiled),
                     # the first scenario's start in parts (_START_CODE)
                     **{k: None if info.get(k) is None else round(info[k], 2) for k in ("imports_s", "build_s", "jit_s")},
                     "loaded": info.get("loaded")})
        print(f"bench compile: {json.dumps(rows[-1])}", file=sys.stderr, flush=True)  # (minutes apart)

    # (the run's own wall-clock budget is the bench's: a cold compile on a
    # loaded machine can pass the run's default)
    cli = [sys.executable, "-m", "physbench.harness.cli", "run", scenario, "-e", "reference", "--json",
           "--timeout", str(timeout)]
    start = [sys.executable, "-c", _START_CODE]
    with tempfile.TemporaryDirectory(prefix="physbench-compile-") as cache:
        row(f"physbench run {scenario}, cold", _child(cli, cache, timeout))
        row(f"physbench run {scenario}, warm", _child(cli, cache, timeout))
    with tempfile.TemporaryDirectory(prefix="physbench-compile-") as cache:
        r = _child(start + [scenario], cache, timeout, jobs=1)
        info = json.loads(r["stdout"].strip().splitlines()[-1])
        row(f"build and step {scenario}, cold, one process", r, info["first_step_s"], info["compiled"], info)
    with tempfile.TemporaryDirectory(prefix="physbench-compile-") as cache:
        for kind in ("cold", "warm"):
            r = _child(start + [scenario], cache, timeout)
            info = json.loads(r["stdout"].strip().splitlines()[-1])
            row(f"build and step {scenario}, {kind}", r, info["first_step_s"], info["compiled"], info)
    if everything:
        from physbench.adapters.reference import ReferenceAdapter
        from physbench.contract.scene import load_scene

        # the scenarios the reference engine runs (not those it reports
        # unsupported, which it never builds)
        ids = [i for i in scenario_ids() if ReferenceAdapter.unsupported_reason(load_scene(i)) is None]
        with tempfile.TemporaryDirectory(prefix="physbench-compile-") as cache:
            r = _child(start + ids, cache, timeout)
            info = json.loads(r["stdout"].strip().splitlines()[-1])
            row(f"build and step all {len(ids)} shipped scenarios it runs, cold", r, info["first_step_s"], info["compiled"],
                info)
    return rows
