"""Two processes share a cold compile (engine/compile_share.py): every kernel
group is compiled by one process, under its lock, and loaded by the other;
a process that dies holding a group leaves it to the next; a build starts a
helper only where it may use two processes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time

import pytest

from physbench.engine import compile_share

pytestmark = pytest.mark.skipif(compile_share.fcntl is None, reason="file locks need fcntl (POSIX)")

# a process taking eight groups: "compiling" one (not done when taken) is a
# 0.3 s sleep; each run logs whether it compiled or loaded
_TAKER = textwrap.dedent("""
    import json, os, sys, time
    from physbench.engine import compile_share
    compile_share.REVERSED = sys.argv[1] == "helper"
    log, go = sys.argv[2], sys.argv[3]
    while not os.path.exists(go):
        time.sleep(0.01)
    def run(key):
        kind = "load" if compile_share.done(key) else "compile"
        if kind == "compile":
            time.sleep(0.3)
        with open(log, "a") as f:
            f.write(json.dumps([sys.argv[1], list(key), kind]) + "\\n")
    compile_share.take([("group", i) for i in range(8)], run)
""")


def _env(cache) -> dict:
    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = str(cache)
    return env


def test_two_processes_compile_each_group_once_and_both_have_all(tmp_path):
    log, go = tmp_path / "log", tmp_path / "go"
    procs = [subprocess.Popen([sys.executable, "-c", _TAKER, who, str(log), str(go)], env=_env(tmp_path / "cache"))
             for who in ("build", "helper")]
    time.sleep(0.5)  # (both imported and waiting)
    go.touch()
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    runs = [json.loads(line) for line in log.read_text().splitlines()]
    for who in ("build", "helper"):  # each process ran every group
        assert sorted(k[1] for w, k, _ in runs if w == who) == list(range(8))
    compiled = [(w, k[1]) for w, k, kind in runs if kind == "compile"]
    assert sorted(k for _, k in compiled) == list(range(8))  # each group compiled once
    # from opposite ends: both compiled some
    assert {w for w, _ in compiled} == {"build", "helper"}
    assert min(k for w, k in compiled if w == "helper") > max(k for w, k in compiled if w == "build")


def test_a_group_held_by_a_dead_process_is_compiled_by_the_next(tmp_path):
    hold = textwrap.dedent("""
        import os, sys, time
        from physbench.engine import compile_share
        with compile_share.group(("group", 0)):
            open(sys.argv[1], "w").close()
            time.sleep(60)
    """)
    held = tmp_path / "held"
    env = _env(tmp_path / "cache")
    p = subprocess.Popen([sys.executable, "-c", hold, str(held)], env=env)
    try:
        t0 = time.monotonic()
        while not held.exists():
            assert time.monotonic() - t0 < 60 and p.poll() is None
            time.sleep(0.02)
        probe = ("import sys\nfrom physbench.engine import compile_share\n"
                 "with compile_share.group(('group', 0), wait=False) as mine:\n    sys.exit(0 if mine else 3)\n")
        assert subprocess.run([sys.executable, "-c", probe], env=env).returncode == 3  # held
        p.kill()
        p.wait()
        taker = ("import sys\nfrom physbench.engine import compile_share\nran = []\n"
                 "compile_share.take([('group', 0)], lambda k: ran.append(compile_share.done(k)))\n"
                 "sys.exit(0 if ran == [False] and compile_share.done(('group', 0)) else 4)\n")
        assert subprocess.run([sys.executable, "-c", taker], env=env).returncode == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_a_build_starts_a_helper_only_where_it_may_use_two_processes(monkeypatch):
    monkeypatch.setenv(compile_share.JOBS_ENV, "1")
    assert compile_share.jobs() == 1
    assert compile_share.start_helper(object(), {}) is None
    monkeypatch.setenv(compile_share.JOBS_ENV, "2")
    assert compile_share.jobs() == 2
    monkeypatch.setattr(compile_share, "REVERSED", True)  # a helper starts none of its own
    assert compile_share.start_helper(object(), {}) is None


def test_a_pool_of_several_workers_gives_each_one_compile_process(monkeypatch):
    from physbench.harness import workers

    assert workers.COMPILE_JOBS_ENV == compile_share.JOBS_ENV
    monkeypatch.delenv(compile_share.JOBS_ENV, raising=False)
    for jobs, want in ((2, "1"), (1, None)):
        with workers.WorkerPool(jobs) as pool:
            got = [v for _, v in pool.map(os.getenv, [compile_share.JOBS_ENV] * jobs)]
        assert got == [want] * jobs


@pytest.mark.parametrize("via", ["adapter", "engine"])
def test_a_cold_build_through_the_adapter_or_the_engine_starts_its_helper_on_its_own_scene(monkeypatch, via):
    """Both ways a reference engine is built (the adapter's ``build``, which
    every run takes, and ``engine.Engine``) start the helper on a cold
    cache, with the scene input and settings that build the same model,
    and wait for it."""
    from physbench.adapters.reference import ReferenceAdapter, scene_input
    from physbench.contract.scene import load_scene
    from physbench.engine import Engine, jit
    from physbench.engine.model import build_model

    started, ended = [], []
    monkeypatch.setattr(jit, "cold_seconds", lambda todo: 1e9)  # (the cache is warm here: say it is not)
    monkeypatch.setattr(compile_share, "start_helper", lambda inp, settings: started.append((inp, settings)) or "h")
    monkeypatch.setattr(compile_share, "end_helper", lambda h: ended.append(h))
    monkeypatch.setattr(jit, "_READY", set())  # (every part still to do in this process)
    scene = load_scene("billiards.head_on")
    if via == "adapter":
        a = ReferenceAdapter()
        a.build(scene, ReferenceAdapter.resolve_settings(scene))
        model = a.model
    else:
        model = Engine(scene_input(scene)).model
    assert len(started) == 1 and ended == ["h"]
    inp, settings = started[0]
    again = build_model(inp, settings)
    assert dict(again.settings) == dict(model.settings) and again.n == model.n


def test_the_helper_gets_every_shipped_scene_input_and_settings_exactly(tmp_path):
    """What a helper builds (compile_share.write_build / read_build: JSON,
    no pickle) is the build's scene input field for field -- values,
    dtypes, shapes, bits -- and its settings, for every shipped scenario
    (joints, springs, statics, materials)."""
    import dataclasses

    import numpy as np

    from physbench.adapters.reference import ReferenceAdapter, scene_input
    from physbench.contract.scene import load_scene, scenario_ids

    for sid in scenario_ids():
        scene = load_scene(sid)
        inp = scene_input(scene)
        settings = ReferenceAdapter.resolve_settings(scene)
        compile_share.write_build(tmp_path / "b.json", inp, settings)
        got, got_settings = compile_share.read_build(tmp_path / "b.json")
        assert got_settings == settings and all(type(got_settings[k]) is type(v) for k, v in settings.items()), sid
        for f in dataclasses.fields(inp):
            a, b = getattr(inp, f.name), getattr(got, f.name)
            if f.name == "scene":
                assert b is None
            elif isinstance(a, np.ndarray):
                assert b.dtype == a.dtype and b.shape == a.shape and a.tobytes() == b.tobytes(), (sid, f.name)
            elif f.name == "joints":
                assert len(a) == len(b), sid
                for ja, jb in zip(a, b):
                    assert len(ja) == len(jb) and all(
                        np.asarray(x).tobytes() == np.asarray(y).tobytes() and np.asarray(x).dtype == np.asarray(y).dtype
                        for x, y in zip(ja, jb)), (sid, ja, jb)
            else:
                assert a == b and type(a) is type(b), (sid, f.name, a, b)


def test_a_failed_helper_is_a_warning_with_its_log(monkeypatch, tmp_path):
    """A helper that fails costs only time (the build compiles what it left),
    and says so: a RuntimeWarning with its exit status and the file that
    keeps its stderr.  One that ends well leaves no file."""
    monkeypatch.setenv(compile_share.JOBS_ENV, "2")
    monkeypatch.setattr(compile_share, "REVERSED", False)
    monkeypatch.setattr(compile_share, "_dir", lambda: tmp_path)
    monkeypatch.setattr(compile_share, "write_build", lambda path, inp, settings: path.write_text("not JSON"))
    h = compile_share.start_helper(object(), {})
    assert h is not None
    with pytest.warns(RuntimeWarning, match="exited with status 1") as rec:
        compile_share.end_helper(h)
    assert str(h.log) in str(rec[0].message)
    assert "JSONDecodeError" in h.log.read_text()
    ok = compile_share.Helper(subprocess.Popen([sys.executable, "-c", "pass"]), tmp_path / "ok.log")
    ok.log.write_text("")
    compile_share.end_helper(ok)
    assert not ok.log.exists()
