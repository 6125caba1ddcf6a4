"""Reading an engine's capabilities (every suite check does, for each of
the suite's engines) imports no slow engine: Drake and JAX are imported
by the first build (adapters/drake.py, adapters/mjx.py), their presence
read from the installed packages' metadata (adapters.base.not_installed)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from physbench.adapters.base import not_installed


def test_not_installed_reads_the_package_metadata():
    assert not_installed("numpy") == ""
    assert not_installed("numpy", "physbench-no-such-distribution") == \
        "not installed: physbench-no-such-distribution"


@pytest.mark.parametrize("engine, dists, modules", [("drake", ("drake",), ("pydrake",)),
                                                     ("mjx", ("mujoco-mjx", "jax"), ("jax", "mujoco.mjx"))])
def test_capabilities_import_no_slow_engine(tmp_path, engine, dists, modules):
    if not_installed(*dists):
        pytest.skip(f"{engine}: {not_installed(*dists)}")
    code = ("import sys\n"
            "from physbench.adapters import get_adapter\n"
            f"c = get_adapter({engine!r}).capabilities()\n"
            "print(c.available, c.unavailable_reason == '')\n"
            f"print([m for m in {list(modules)!r} if m in sys.modules])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert out.returncode == 0, out.stderr
    avail, imported = out.stdout.strip().splitlines()[-2:]
    assert avail == "True True"
    assert imported == "[]"
