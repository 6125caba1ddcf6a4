"""physbench installs anywhere (issue 39): the built wheel, installed
non-editable into a fresh virtual environment, runs from any directory with
its shipped scenarios, writes results under the working directory and
nothing into the install; plug-in distributions add engines and reference
models through entry points; the results directory follows
``--results-dir`` and ``PHYSBENCH_RESULTS``; a compile says so on stderr.

The new environment sees the parent's site-packages through a ``.pth``
line (nothing is downloaded; the wheel and the plug-in install with
``--no-deps``).  The parent's editable install is not activated that way
(its own ``.pth`` is not processed), so the installed copy is what runs.
The numba cache is not isolated: the installed engine's sources are the
parent's, so it finds the kernels the parent compiled (engine/cache.py)."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import time
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
#: what a build needs of the tree (the rest: venvs, results, caches, git)
_IGNORE = shutil.ignore_patterns(".venv", ".git", "results", "build", "dist", "*.egg-info", "__pycache__",
                                 ".pytest_cache", ".hypothesis", "*.rrd", "tests")


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float = 900) -> subprocess.CompletedProcess:
    p = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    return p


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in root.rglob("*") if p.is_file()}


class Venv:
    def __init__(self, path: Path):
        self.path = path
        self.python = path / "bin" / "python"
        self.bin = path / "bin"
        out = subprocess.run([str(self.python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
        self.site = Path(out)

    def env(self, **extra: str) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PHYSBENCH_RESULTS", "PHYSBENCH_ADAPTERS")}
        env["PATH"] = f"{self.bin}{os.pathsep}{env.get('PATH', '')}"
        env["VIRTUAL_ENV"] = str(self.path)
        env.update(extra)
        return env

    def pip_install(self, *args: str) -> None:
        """pip of the parent environment, installing into this one."""
        p = subprocess.run([sys.executable, "-m", "pip", "--python", str(self.python), "install", "--no-deps",
                            "--no-index", "-q", *args], capture_output=True, text=True, timeout=600)
        assert p.returncode == 0, p.stderr[-3000:]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """physbench's wheel, built from a copy of the tree (nothing is written
    into the repository)."""
    tmp = tmp_path_factory.mktemp("build")
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=_IGNORE)
    p = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp / "dist"), str(src)],
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    (whl,) = (tmp / "dist").glob("physbench-*.whl")
    return whl


@pytest.fixture(scope="module")
def venv(tmp_path_factory, wheel) -> Venv:
    """A fresh virtual environment with the wheel installed, non-editable,
    seeing the parent's site-packages (for the dependencies) through a .pth."""
    path = tmp_path_factory.mktemp("venv") / "env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True, timeout=300)
    v = Venv(path)
    (v.site / "_parent_site.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    v.pip_install(str(wheel))
    return v


def test_the_wheel_holds_one_import_package_and_the_shipped_data(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    record = next(n for n in names if n.endswith(".dist-info/RECORD"))
    rows = list(csv.reader(io.StringIO(zipfile.ZipFile(wheel).read(record).decode())))
    top = {r[0].split("/")[0] for r in rows if r and not r[0].split("/")[0].endswith(".dist-info")}
    assert top == {"physbench"}
    shipped = {f"physbench/{p.relative_to(ROOT).as_posix()}" for d in ("scenarios", "suites")
               for p in (ROOT / d).rglob("*.toml")}
    assert shipped and shipped <= set(names)
    assert not [n for n in names if "/tests/" in n or n.startswith("physbench/results")]


def test_the_wheel_runs_from_anywhere_and_writes_nothing_into_the_install(venv, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    env = venv.env()
    before = _snapshot(venv.site)
    where = _run([str(venv.python), "-c", "import physbench, physbench.engine.cache as c; "
                  "print(physbench.__file__); print(c.cache_dir())"], work, env)
    assert where.returncode == 0, where.stderr
    installed_file, installed_cache = where.stdout.split()
    assert Path(installed_file).resolve().is_relative_to(venv.site.resolve())
    # the same engine sources at another path: the same numba cache directory
    from physbench.engine.cache import cache_dir

    assert Path(installed_cache) == cache_dir()
    physbench = str(venv.bin / "physbench")

    listed = _run([physbench, "list"], work, env)
    assert listed.returncode == 0, listed.stderr
    ids = [line.split()[0] for line in listed.stdout.splitlines() if line.strip()]
    assert len(ids) == len(list((ROOT / "scenarios").rglob("*.toml"))) and "billiards.head_on" in ids

    t0 = time.perf_counter()
    ran = _run([physbench, "run", "billiards.head_on", "-e", "reference"], work, env)
    run_s = time.perf_counter() - t0
    assert ran.returncode == 0, ran.stdout[-2000:] + ran.stderr[-2000:]
    warm = any(cache_dir().rglob("*.nbi"))
    if warm:  # kernels compiled by this checkout are loaded, not compiled again
        assert "compiling" not in ran.stderr, ran.stderr[-2000:]
    print(f"installed copy: `physbench run billiards.head_on -e reference` {run_s:.1f} s wall "
          f"(cache {'warm' if warm else 'cold'})")

    checked = _run([physbench, "check", "--scenarios", "billiards.head_on", "--engines", "reference", "pymunk",
                    "--junit", "j.xml"], work, env)
    assert checked.returncode == 0, checked.stdout[-2000:] + checked.stderr[-2000:]
    assert (work / "j.xml").is_file()
    parts = sorted((work / "results" / "check").glob("*.parquet"))
    assert parts, sorted(str(p) for p in work.rglob("*"))
    import pandas as pd

    rows = pd.read_parquet(parts[-1])
    assert set(rows["engine"]) == {"reference", "pymunk"}
    # the recorded spec path of a shipped scene is as in a checkout
    assert set(rows.loc[rows["scenario"] == "billiards.head_on", "scene_path"]) == {"scenarios/billiards/head_on.toml"}
    # an installed package is no checkout: rows name its version, not some git tree around it
    from importlib.metadata import version

    assert set(rows["commit"]) == {f"physbench-{version('physbench')}"}

    # a shipped suite, a trace and the report, from the same directory
    swept = _run([physbench, "sweep", "--suite", "smoke", "--engines", "pymunk"], work, env)
    assert swept.returncode == 0, swept.stdout[-2000:] + swept.stderr[-2000:]
    assert list((work / "results" / "sweeps").rglob("*.parquet"))
    traced = _run([physbench, "trace", "billiards.head_on", "--engines", "pymunk", "-o", "head_on.rrd"], work, env)
    assert traced.returncode == 0 and (work / "head_on.rrd").is_file(), traced.stderr[-2000:]
    reported = _run([physbench, "report"], work, env)
    assert reported.returncode == 0 and (work / "results" / "report.html").is_file(), reported.stderr[-2000:]
    assert _snapshot(venv.site) == before, "something was written inside the installed package's site-packages"


PLUGIN = {
    "pyproject.toml": """
        [build-system]
        requires = ["setuptools>=61"]
        build-backend = "setuptools.build_meta"

        [project]
        name = "physbench-plugdemo"
        version = "0.3.0"

        [project.entry-points."physbench.adapters"]
        plugeng = "plugdemo.adapter:PlugAdapter"
        plugbroken = "plugdemo.missing:Nope"

        [project.entry-points."physbench.models"]
        plug_collision = "plugdemo.model:PlugCollision"

        [tool.setuptools]
        packages = ["plugdemo"]
    """,
    "plugdemo/__init__.py": "",
    "plugdemo/adapter.py": """
        import dataclasses

        from physbench.adapters.pymunk import PymunkAdapter


        class PlugAdapter(PymunkAdapter):
            '''A plug-in engine: pymunk under another name and version.'''

            name = "plugeng"

            @classmethod
            def capabilities(cls):
                return dataclasses.replace(super().capabilities(), engine="plugeng", version="0.3.0")
    """,
    "plugdemo/model.py": """
        from physbench.harness.references.collision import TwoBodyCollision


        class PlugCollision(TwoBodyCollision):
            name = "plug_collision"
            summary = "a plug-in's own two-sphere model (Newton's law of restitution)"
    """,
}


def test_a_plugin_distribution_adds_an_engine_and_a_model(venv, tmp_path):
    src = tmp_path / "plugdemo"
    for rel, text in PLUGIN.items():
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(textwrap.dedent(text).lstrip(), encoding="utf-8")
    p = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"), str(src)],
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    (whl,) = (tmp_path / "dist").glob("physbench_plugdemo-*.whl")
    venv.pip_install(str(whl))
    work = tmp_path / "work"
    work.mkdir()
    spec = work / "plug_head_on.toml"
    spec.write_text((ROOT / "tests" / "data" / "head_on.toml").read_text(encoding="utf-8")
                    .replace('model = "two_body_collision"', 'model = "plug_collision"'), encoding="utf-8")
    env = venv.env()
    physbench = str(venv.bin / "physbench")

    engines = _run([physbench, "engines", "--json"], work, env)
    assert engines.returncode == 0, engines.stderr
    rows = {r["engine"]: r for r in json.loads(engines.stdout)}
    assert rows["plugeng"]["origin"] == "physbench-plugdemo 0.3.0" and rows["plugeng"]["version"] == "0.3.0"
    assert rows["plugbroken"]["origin"] == "physbench-plugdemo 0.3.0" and "plugdemo.missing" in rows["plugbroken"]["error"]
    assert rows["reference"]["origin"] == "physbench"
    models = _run([physbench, "models"], work, env)
    assert models.returncode == 0, models.stderr
    assert "plug_collision (from physbench-plugdemo 0.3.0): a plug-in's own two-sphere model" in models.stdout

    ran = _run([physbench, "run", str(spec), "-e", "plugeng", "--json"], work, env)
    assert ran.returncode == 0, ran.stdout[-2000:] + ran.stderr[-2000:]
    row = json.loads(ran.stdout)
    assert row["engine"] == "plugeng" and row["engine_version"] == "0.3.0" and row["status"] == "ok"
    # the plug-in model's metric, measured on the plug-in engine
    assert row["post_impact_velocity_error"] < 0.02

    # a broken plug-in costs its own rows only, each with its error
    checked = _run([physbench, "check", str(spec), "--engines", "plugeng", "plugbroken", "--junit", "j.xml"],
                   work, env)
    assert checked.returncode == 1, checked.stdout[-2000:] + checked.stderr[-2000:]
    assert "Traceback" not in checked.stderr
    import pandas as pd

    (part,) = sorted((work / "results" / "check").glob("*.parquet"))
    rows = pd.read_parquet(part)
    assert set(rows.loc[rows["engine"] == "plugeng", "status"]) == {"ok"}
    broken = rows[rows["engine"] == "plugbroken"]
    assert len(broken) and set(broken["status"]) == {"failed"}
    assert all("plugdemo.missing" in m for m in broken["message"])


def test_results_dir_flag_and_variable(tmp_path, monkeypatch):
    """./results under the working directory by default; PHYSBENCH_RESULTS,
    then --results-dir, override it."""
    from physbench.harness import results
    from physbench.harness.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv(results.RESULTS_ENV, raising=False)
    assert results.results_dir() == tmp_path / "results"
    monkeypatch.setenv(results.RESULTS_ENV, str(tmp_path / "from_env"))
    assert results.results_dir() == tmp_path / "from_env"
    args = ["check", "--scenarios", "billiards.head_on", "--engines", "pymunk"]
    assert main(args) == 0
    assert list((tmp_path / "from_env" / "check").glob("*.parquet"))
    assert main(args + ["--results-dir", "flagged", "--no-resume"]) == 0
    assert list((tmp_path / "flagged" / "check").glob("*.parquet"))
    assert results.results_dir() == tmp_path / "from_env"  # the flag held for its command only
    assert not (tmp_path / "results").exists()
    assert main(["report", "--results-dir", "flagged"]) == 0
    assert (tmp_path / "flagged" / "report.html").is_file()


def test_compile_progress_lines(tmp_path):
    """A compile talks on stderr: off a terminal, a line when it starts and
    a closing line with the kernel count and seconds; the longest compile
    is kept as the next estimate.  Nothing is printed for a kernel loaded
    or compiled already."""
    code = textwrap.dedent(f"""
        import numba
        from numba.core import config
        config.CACHE_DIR = {str(tmp_path / 'cache')!r}
        from physbench.harness import compile_progress as cp
        cp.IDLE_S = 0.3
        printer = cp.watch()
        @numba.njit
        def inner(x):
            return x * 2.0
        @numba.njit
        def outer(x):
            return inner(x) + 1.0
        outer(1.0)
        outer(2.0)  # compiled already: no event
        import time; time.sleep(1.5)
        print("kernels", printer.kernels)
    """)
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("physbench:")]
    assert lines[0].startswith("physbench: compiling numba kernels, now __main__.outer")
    assert "a first compile takes about" in lines[0]  # no timing file yet
    assert lines[-1].startswith("physbench: compiled 1 kernel(s) in")  # the callee compiles inside its caller
    assert len(lines) == 2 and "kernels 1" in p.stdout
    timing = json.loads((tmp_path / "cache" / "compile-seconds.json").read_text())
    assert timing["kernels"] == 1 and timing["seconds"] > 0
    assert "\r" not in p.stderr  # not a terminal: plain lines
    # the next compile (the kernels here are not cached) estimates from the timing file
    again = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    first = next(ln for ln in again.stderr.splitlines() if ln.startswith("physbench:"))
    assert "(the last compile here)" in first or "longer than the last compile here" in first, first


def test_compile_progress_says_when_a_process_waits_for_another_compile(tmp_path, monkeypatch):
    """A process that needs a kernel group another process is compiling
    (its lock held, engine/compile_share.py) says so on stderr while it
    waits, naming the group; it goes on once the lock is released."""
    from physbench.engine import compile_share

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    key = ("narrow", (True, None, True))
    code = textwrap.dedent(f"""
        import numba
        from physbench.engine import compile_share
        from physbench.harness import compile_progress as cp
        cp.watch()
        with compile_share.group({key!r}) as mine:
            print("got", mine, flush=True)
    """)
    with compile_share.group(key, wait=False) as mine:
        assert mine
        p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        import select

        ready, _, _ = select.select([p.stderr], [], [], 60.0)
        line = p.stderr.readline() if ready else ""  # said while the lock is still held here
        assert p.poll() is None
    out, err = p.communicate(timeout=120)
    assert line.startswith("physbench: waiting for another process's compile of narrow (2 shape-pair families)"), \
        line + err
    assert p.returncode == 0 and "got True" in out
    assert compile_share.done(key)  # (the lock's holder here marked it done)


TOY_JIT_ADAPTER = '''
import dataclasses

import numba

from physbench.adapters.pymunk import PymunkAdapter


@numba.njit
def _toy(x):
    return x + 1.0


class ToyJitAdapter(PymunkAdapter):
    """pymunk, after compiling a numba kernel in build (not cached: every
    worker compiles it)."""

    name = "toyjit"

    @classmethod
    def capabilities(cls):
        return dataclasses.replace(super().capabilities(), engine="toyjit")

    def build(self, scene, settings):
        _toy(1.0)
        super().build(scene, settings)
'''


def test_a_worker_compiling_talks_on_the_parents_stderr(tmp_path, monkeypatch, capfd):
    """A run in a worker process that compiles a kernel: the progress lines
    reach the command's own stderr (not the worker's captured one)."""
    import importlib

    from physbench.adapters.base import _ORIGINS, _REGISTRY, register
    from physbench.harness.execute import RunRequest, run_isolated

    (tmp_path / "toyjit_adapter.py").write_text(TOY_JIT_ADAPTER, encoding="utf-8")
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = importlib.import_module("toyjit_adapter")
    register("toyjit", lambda: mod.ToyJitAdapter)
    try:
        res = run_isolated(RunRequest(str(ROOT / "tests" / "data" / "head_on.toml"), "toyjit", timeout_s=300))
    finally:
        _REGISTRY.pop("toyjit", None)
        _ORIGINS.pop("toyjit", None)
    assert res.status == "ok", res.message
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("physbench:")]
    assert lines and lines[0].startswith("physbench: compiling numba kernels") and "toyjit_adapter._toy" in lines[0]
    assert lines[-1].startswith("physbench: compiled 1 kernel(s)")


def test_physbench_compile_warms_the_cache():
    """`physbench compile` (python -m physbench.engine's work): exit 0 and
    the seconds it took; with a warm cache it loads and prints no progress."""
    p = subprocess.run([sys.executable, "-m", "physbench.harness.cli", "compile", "--jobs", "1"],
                       capture_output=True, text=True, timeout=1800)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "engine kernels compiled or loaded in" in p.stdout


def test_check_leaves_out_shipped_engines_that_are_not_installed(monkeypatch, capsys):
    """`check` without --engines runs the installed engines; a shipped one
    whose extra is not installed is left out, and stderr says how to add it."""
    import dataclasses

    import physbench.adapters as A
    from physbench.adapters.base import _ORIGINS, _REGISTRY, register, set_origin
    from physbench.adapters.pymunk import PymunkAdapter
    from physbench.harness.conformance.plan import default_engines

    class Missing(PymunkAdapter):
        name = "missing_engine"

        @classmethod
        def capabilities(cls):
            return dataclasses.replace(super().capabilities(), engine="missing_engine", available=False,
                                       unavailable_reason="No module named 'missing_engine'")

    register("missing_engine", lambda: Missing)
    set_origin("missing_engine", "physbench")
    monkeypatch.setattr(A, "ENGINES", A.ENGINES + ("missing_engine",))
    try:
        got = default_engines()
    finally:
        _REGISTRY.pop("missing_engine", None)
        _ORIGINS.pop("missing_engine", None)
    installed = [e for e in A.ENGINES if e != "missing_engine" and A.get_adapter(e).capabilities().available]
    assert "missing_engine" not in got and set(installed) <= set(got)
    err = capsys.readouterr().err
    assert re.search(r"pip install 'physbench\[([a-z0-9_]+,)*missing_engine(,[a-z0-9_]+)*\]'", err), err
