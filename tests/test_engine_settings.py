"""The engine's settings table, integrator names, joint kinds and version
live in a numba-free module (engine/settings.py), so that an adapter's
capabilities and the environment fingerprint -- all a sweep's client reads
of the engine -- load no numba (about 0.2 s of the client's start-up), while
the compiled kernels' cache is still configured before the first kernel is
defined (engine/__init__.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _fresh(code: str) -> dict:
    """``code`` run in a fresh interpreter; the JSON it prints last."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_settings_and_version_import_no_numba():
    got = _fresh(
        "import json, sys\n"
        "from physbench.adapters.reference import ReferenceAdapter\n"
        "from physbench.harness.fingerprint import fingerprint\n"
        "import physbench.engine as e\n"
        "caps = ReferenceAdapter.capabilities()\n"
        "fp = fingerprint()\n"
        "print(json.dumps({'numba': 'numba' in sys.modules, 'version': caps.version,\n"
        "                  'engine_version': fp['versions']['physbench_engine'],\n"
        "                  'settings': sorted(caps.settings), 'table': sorted(e.SETTINGS),\n"
        "                  'joints': sorted(caps.joint_kinds)}))\n")
    assert got["numba"] is False
    from physbench.engine import JOINT_KINDS, SETTINGS, version

    assert got["version"] == f"physbench-{version()}" and got["engine_version"] == version()
    assert got["table"] == sorted(SETTINGS) and set(got["table"]) < set(got["settings"])  # plus dt
    assert got["joints"] == sorted(JOINT_KINDS)


def test_integrator_and_joint_names_match_the_engine_s():
    from physbench.engine import INTEGRATORS, JOINT_KINDS, SETTINGS
    from physbench.engine import integrate, joints

    # the settings table's integrator choices are the integrators the engine implements
    assert INTEGRATORS == integrate.INTEGRATORS == tuple(integrate.ORDERS)
    assert SETTINGS["integrator"][3] == INTEGRATORS and SETTINGS["integrator"][0] in INTEGRATORS
    assert joints.KINDS == JOINT_KINDS


def test_the_cache_is_configured_before_the_first_kernel():
    got = _fresh(
        "import json, sys\n"
        "import physbench.engine\n"
        "before = 'numba' in sys.modules\n"
        "from physbench.engine import flight, cache\n"
        "from numba.core import config\n"
        "print(json.dumps({'before': before, 'dir': str(cache.cache_dir()), 'config': config.CACHE_DIR,\n"
        "                  'kernel': flight.integrate_positions._cache._cache_path,\n"
        "                  'finder_left': any(type(f).__name__ == '_ConfigureCacheFirst'\n"
        "                                     or getattr(f, '__name__', '') == '_ConfigureCacheFirst'\n"
        "                                     for f in sys.meta_path)}))\n")
    assert got["before"] is False  # the package alone loads no numba
    assert got["config"] == got["dir"]
    assert Path(got["dir"]) in Path(got["kernel"]).parents
    assert got["finder_left"] is False
