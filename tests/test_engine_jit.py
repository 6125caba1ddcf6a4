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
    assert parts(free) == (("flight",), ("force", "Gravity"))
    still = build_model(dataclasses.replace(warm_scene(), effects=frozenset()), defaults)
    assert parts(still) == (("flight",),)  # no force, no gyroscopic kernel
    assert ("broad", False) in got  # two bodies: all pairs, the sweep not compiled
    many = build_model(warm_scene(("sphere",) * 20, plane=True), defaults)
    assert ("broad", True) in parts(many)
    assert ("broad", False) in parts(build_model(warm_scene(("sphere",) * 20, plane=True),
                                                 defaults | {"broadphase": "brute"}))
    assert len(parts(None)) == 14  # every group, every family: python -m physbench.engine's halves
    # the fused step's warm scene has the model's families
    from physbench.engine.collision.collide import families

    from physbench.engine.broadstage import uses_sap

    for shapes, plane, sbox in ((("sphere", "sphere"), False, False), (("box", "box", "cylinder"), True, False),
                                (("capsule",), False, True), (("sphere",) + ("box",) * 19, True, False)):
        m = build_model(warm_scene(shapes, plane, sbox), defaults)
        w = build_model(warm_scene_for(m), defaults)
        assert families(w.shape) == families(m.shape)
        assert uses_sap(w) == uses_sap(m) and w.n <= max(m.n, 17)
