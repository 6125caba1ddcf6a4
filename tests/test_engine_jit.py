"""Compile time is kept apart (issue 23): the reference engine compiles or
loads its kernels at build (engine/jit.py), reports those seconds once as
the profile's ``jit_s`` and the runner's ``timing.jit_s``, and no step
compiles."""

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

_CODE = """
from physbench.harness.bench import column_scene
from physbench.harness.runner import run
from physbench.adapters.reference import engine_for
import physbench.engine.contact.gauss_seidel as sw
import physbench.engine.contact.phases as ph
import physbench.engine.contact.rows as rw
import physbench.engine.flight as fl
sc = column_scene(3)
first = run(sc, "reference", compute_metrics=False)
second = engine_for(sc)
print(first.timing["jit_s"], second.profile.jit_s, "jit_s" in first.stages)
kernels = [sw.iterate, sw.apply_rows, sw.apply_patches, ph.solve_contacts, ph.relax, rw._greedy_colours,
           fl.begin_step, fl.max_turn_sq, fl.end_displacement, fl.end_pose_pairs]
before = [len(k.overloads) for k in kernels]
second.step(60)
print(before == [len(k.overloads) for k in kernels])
"""


def test_jit_time_is_reported_once_and_no_step_compiles():
    out = subprocess.run([sys.executable, "-c", _CODE], capture_output=True, text=True, cwd=REPO,
                         env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}, timeout=600)
    assert out.returncode == 0, out.stderr
    line1, line2 = out.stdout.split("\n")[:2]
    jit_first, jit_second, in_stages = line1.split()
    assert float(jit_first) > 0.0  # the first build in a process loads (or compiles) the kernels
    assert float(jit_second) == 0.0  # later builds find them ready
    assert in_stages == "True"
    assert line2 == "True"  # the steps ran on the kernels the build prepared: no new specialisation


def test_python_m_engine_fills_the_cache_a_run_then_loads():
    """``python -m physbench.engine`` (what CI runs before the tests, .ci/run)
    compiles or loads the kernels in the cache directory it names (the
    engine's own, engine/cache.py); a later process running a contact
    scene (boxes) and a scene without contact at the default settings then
    compiles nothing, nor does one of spheres with impacts or of
    cylinders: every kernel it calls comes from that cache
    (numba's ``numba:compile`` events are raised only for a compile, a
    cache hit raises none)."""
    from physbench.engine.cache import cache_dir

    # (a user's NUMBA_CACHE_DIR is where both the engine and this process look)
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin",
           **{k: v for k, v in os.environ.items() if k == "NUMBA_CACHE_DIR"}}
    out = subprocess.run([sys.executable, "-m", "physbench.engine"], capture_output=True, text=True, cwd=REPO, env=env,
                         timeout=900)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("engine kernels compiled or loaded in "), out.stdout
    assert str(cache_dir()) in out.stdout
    code = """
from numba.core import event
with event.install_recorder("numba:compile") as rec:
    from physbench.harness.bench import column_scene
    from physbench.harness.runner import run
    from physbench.contract.scene import load_scene
    run(column_scene(3), "reference", compute_metrics=False)
    run(load_scene("forces.drag_linear_fall"), "reference", compute_metrics=False)
    # spheres with impacts, and cylinders: other families, the same fused step
    run(load_scene("billiards.head_on"), "reference", compute_metrics=False)
    run(load_scene("friction.cylinder_rolls"), "reference", compute_metrics=False)
print(sorted({ev.data["dispatcher"].py_func.__qualname__ for _, ev in rec.buffer if ev.is_start}))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env,
                         timeout=900)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_a_scene_warms_only_the_kernel_groups_its_stages_call():
    """engine.jit.parts: the free flight always; with contact the broad
    phase, the narrow phase for the scene's families only, and the
    impulse solve with time-of-impact handling or the penalty contacts;
    without contact nothing else (issue 42: a two-sphere scene does not
    compile box-cylinder).  No kernel is compiled here."""
    import dataclasses

    from physbench.engine import SETTINGS
    from physbench.engine.collision.collide import F_PS, F_SS, F_XS, N_FAMILIES
    from physbench.engine.jit import parts
    from physbench.engine.model import build_model
    from physbench.engine.fused.steady import warm_scene, warm_scene_for

    defaults = {k: v[0] for k, v in SETTINGS.items()} | {"dt": 1 / 240}
    two = build_model(warm_scene(("sphere", "sphere"), plane=False), defaults)
    got = parts(two)
    assert [p[0] for p in got] == ["flight", "force", "broad", "narrow", "solve", "ccd"]  # (the warm scene's gravity)
    assert ("force", "Gravity") in got
    fams = dict((p[0], p[1:]) for p in got)["narrow"][0]
    assert [f for f in range(N_FAMILIES) if fams[f]] == [F_SS, F_PS, F_XS]
    pen = build_model(warm_scene(("sphere", "sphere"), plane=False), defaults | {"contact_model": "penalty"})
    assert [p[0] for p in parts(pen)] == ["flight", "force", "broad", "narrow", "penalty"]
    off = build_model(warm_scene(("sphere", "sphere"), plane=False), defaults | {"ccd": "off"})
    assert [p[0] for p in parts(off)] == ["flight", "force", "broad", "narrow", "solve"]
    free = build_model(dataclasses.replace(warm_scene(), effects=frozenset({"gravity"})), defaults)
    assert parts(free) == (("flight", "rk4"), ("force", "Gravity"))  # the default integrator's flight alone
    euler = build_model(dataclasses.replace(warm_scene(), effects=frozenset({"gravity"})),
                        defaults | {"integrator": "semi_implicit_euler"})
    assert parts(euler)[0] == ("flight", "semi_implicit_euler")
    still = build_model(dataclasses.replace(warm_scene(), effects=frozenset()), defaults)
    assert parts(still) == (("flight", "rk4"),)  # no force, no gyroscopic kernel
    assert ("broad", False) in got  # two bodies: all pairs, the sweep not compiled
    many = build_model(warm_scene(("sphere",) * 20, plane=True), defaults)
    assert ("broad", True) in parts(many)
    assert ("broad", False) in parts(build_model(warm_scene(("sphere",) * 20, plane=True),
                                                 defaults | {"broadphase": "brute"}))
    assert len(parts(None)) == 19  # every group, integrator, family: python -m physbench.engine's halves
    # the fused step's warm scene has the model's families
    from physbench.engine.collision.collide import families

    from physbench.engine.broadstage import uses_sap

    for shapes, plane, sbox in ((("sphere", "sphere"), False, False), (("box", "box", "cylinder"), True, False),
                                (("capsule",), False, True), (("sphere",) + ("box",) * 19, True, False)):
        m = build_model(warm_scene(shapes, plane, sbox), defaults)
        w = build_model(warm_scene_for(m), defaults)
        assert families(w.shape) == families(m.shape)
        assert uses_sap(w) == uses_sap(m) and w.n <= max(m.n, 17)


_FLIGHTS = """
import numpy as np
from numba.core import event
from physbench.engine import flight, state
from physbench.engine.jit import _flight_arrays
from physbench.engine.pack import Pack

nb = 2
with event.install_recorder("numba:compile") as rec:
    ends, staged = [], []
    for name in ("semi_implicit_euler", "rk4"):
        x, q, v, R, idx, I, plain, springs = _flight_arrays(nb)
        x[0] = (0.1, 0.2, 0.3)
        w = np.array([[0.5, -1.0, 2.0], [3.0, 0.25, -0.5]])
        vw = np.zeros((nb + 1, 3))
        R0, Iinv0 = np.zeros((nb, 3, 3)), np.zeros((nb + 1, 3, 3))
        inv_I = 1.0 / I
        flight.start_pose(q, inv_I, R0, Iinv0)
        b = state.StepArrays(x=x, q=q, v=v, w=w, inv_I=inv_I, x1=x.copy(), q1=q.copy(), V=vw.copy(), W=vw.copy(),
                             F=np.zeros((nb, 3)), T=np.zeros((nb, 3)), vp=vw.copy(), wp=vw.copy(), R0=R0, Iinv0=Iinv0)
        kept = Pack(b)
        state._begin_packed(kept)
        flight.apply_forces(springs, b.x, b.R0, b.v, b.w, b.F, b.T)  # (the force stages at the start state)
        ig = flight.Integrator(method=flight.Method(flight.METHOD[name]), has_forces=True, constant=False,
                               torque=True, fm=springs, inv_m=np.ones(nb), inv_I=inv_I, lever=0.5)
        F = np.zeros((nb, 3))
        f = flight.Flight(ig=ig, V=b.V[:nb], W=b.W[:nb], v_free=F.copy(), w_free=F.copy(), w0=F.copy(),
                          T_mean=F.copy(), u_lin=F.copy(), u_ang=F.copy(), work=np.zeros((flight.WORK_SLABS, nb, 3)),
                          work_q=np.zeros((2, nb, 4)), vp=b.vp[:nb], wp=b.wp[:nb])
        flight.fly_packed(kept, Pack(f), 1e-2)
        ends.append(np.concatenate([b.x1.ravel(), b.q1.ravel(), f.V.ravel(), f.W.ravel(), f.T_mean.ravel()]))
        staged.append(len(flight._stage.overloads))
print(staged, sum(1 for _, e in rec.buffer if e.is_start))
print(ends[0].tobytes().hex())
print(ends[1].tobytes().hex())
"""


def test_each_integrator_compiles_its_own_flight_and_the_cache_keeps_both(tmp_path):
    """The free flight compiles for the model's integrator alone
    (engine.flight.Method: the method's code is in the argument types, the
    other methods' branches are pruned before typing): the semi-implicit
    Euler flight never types the intermediate-state kernel
    (``flight._stage``) that rk4 needs.  The two methods' compiled flights
    are separate cache entries: a second process with the same cache
    directory loads both (no compile at all) and gets the same bits."""
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "NUMBA_CACHE_DIR": str(tmp_path)}
    runs = []
    for _ in range(2):
        out = subprocess.run([sys.executable, "-c", _FLIGHTS], capture_output=True, text=True, cwd=REPO, env=env,
                             timeout=600)
        assert out.returncode == 0, out.stderr
        runs.append(out.stdout.split("\n")[:3])
    (staged, compiles), (staged2, compiles2) = (r[0].rsplit(" ", 1) for r in runs)
    assert staged == "[0, 1]"  # Euler: no intermediate state; rk4: one
    assert int(compiles) > 0
    assert (staged2, compiles2) == ("[0, 0]", "0")  # everything loaded from the cache
    assert runs[0][1:] == runs[1][1:]  # the same end states, method by method
    assert runs[0][1] != runs[0][2]  # (two methods, two different end states)


_WARM_BUILD = """
import gc, importlib, json
from numba.core.dispatcher import Dispatcher
from physbench.adapters.reference import engine_for
from physbench.contract.scene import load_scene
from physbench.engine import compile_share
from physbench.engine.jit import CALLEES, parts


def stats():
    # every dispatcher in the process: (its cache loads, compiles, specialisations)
    return {id(d): (d, sum(d.stats.cache_hits.values()), sum(d.stats.cache_misses.values()), len(d.overloads))
            for d in gc.get_objects() if isinstance(d, Dispatcher)}


out = {"changed": []}
for variant in (None, "plastic"):
    eng = engine_for(load_scene("billiards.head_on", variant))
    if variant is None:
        out["warm"] = all(compile_share.done(p) for p in parts(eng.model))
        out["loaded"] = sum(s[1] for s in stats().values())
        out["callees"] = {n: len(getattr(importlib.import_module("physbench.engine." + n.rsplit(".", 1)[0]),
                                         n.rsplit(".", 1)[1]).overloads) for n in CALLEES}
    before = stats()
    eng.step(500)  # the whole scenario: the flight, the impact, the flights after it
    out["changed"] += sorted(s[0].py_func.__qualname__ for k, s in stats().items()
                             if before.get(k, (None, 0, 0, 0))[1:] != s[1:])
print(json.dumps(out))
"""


def test_a_warm_build_loads_no_compiled_only_callee():
    """On a warm cache a build loads the kernels Python calls, not those
    only compiled code calls (engine.jit.CALLEES: phases.classify_stage is
    inside the fused steady step, ...): a second process building
    billiards.head_on loads none of them, and no step of either process
    loads or compiles anything (the whole scenario, base and plastic
    variant: the impact included), so the build still loads all a step
    needs.  The libraries the warm build loads: at most 68 (74 while the
    callees were loaded too; each costs 2 to 75 ms of the warm start,
    ``physbench bench compile``)."""
    import json

    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin",
           **{k: v for k, v in os.environ.items() if k == "NUMBA_CACHE_DIR"}}
    runs = []
    for _ in range(2):  # (the first fills a cold cache)
        out = subprocess.run([sys.executable, "-c", _WARM_BUILD], capture_output=True, text=True, cwd=REPO, env=env,
                             timeout=900)
        assert out.returncode == 0, out.stderr
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    first, warm = runs
    assert warm["warm"]
    assert warm["callees"] == {n: 0 for n in warm["callees"]} and len(warm["callees"]) == 6
    assert first["changed"] == [] and warm["changed"] == []  # no step loads or compiles
    # (68 libraries with the six callees left out; 69 since the narrow
    # phase's family table is a Pack of its own, collide.family_table_pack:
    # one load a process for ~1 ms less a build)
    assert 0 < warm["loaded"] <= 69


def test_the_fused_part_is_the_builds_fused_step():
    """engine.jit.fused_part (what the harness's cold-cache scheduling reads,
    harness.execute.PendingCompile) is the group of the fused step
    build_pipeline warms: engine.fused.build on the built stages, for every
    shipped scenario the reference runs and settings that change it
    (penalty contacts, substeps, Baumgarte correction, the integrator, all
    pairs)."""
    from physbench.adapters.reference import ReferenceAdapter, scene_input
    from physbench.contract.scene import load_scene, scenario_ids
    from physbench.engine import fused
    from physbench.engine.broadstage import uses_sap
    from physbench.engine.jit import fused_part
    from physbench.engine.model import build_model
    from physbench.engine.pipeline import build_pipeline

    variants = ({}, {"contact_model": "penalty"}, {"substeps": 2}, {"position_correction": "baumgarte"},
                {"integrator": "semi_implicit_euler", "broadphase": "brute"})
    seen = set()
    for sid in scenario_ids():
        scene = load_scene(sid)
        if ReferenceAdapter.unsupported_reason(scene) is not None:
            continue
        for v in variants:
            model = build_model(scene_input(scene), ReferenceAdapter.resolve_settings(scene, v))
            want = None
            if model.joints is None:
                fast = fused.build(model, build_pipeline(model))
                integ = model.setting("integrator")
                want = (("steady", uses_sap(model), integ) if isinstance(fast, fused.SteadyStep)
                        else ("flight_step", integ) if fast is not None else None)
            assert fused_part(model) == want, (sid, v)
            seen.add(None if want is None else want[0])
    assert seen == {None, "steady", "flight_step"}  # (every answer met)
