import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from physbench.contract.scene import canonical_example  # noqa: E402

# one process per reference build: a cold build's helper process
# (engine/compile_share.py) is tested by tests/test_compile_share.py alone
os.environ.setdefault("PHYSBENCH_COMPILE_JOBS", "1")

# ../shared/examples/head_on.toml when shared/ stands beside the repository
# (as in CI), else the copy under tests/data
HEAD_ON = canonical_example()


@pytest.fixture
def head_on_path() -> Path:
    return HEAD_ON


SPRING_PAIR = """
[scenario]
family = "selfcheck"
title = "spring pair judged by itself"
duration = 2.0
dt = 0.02
planar = true
effects = ["spring"]
primary_metric = "self_consistency_error"

[[body]]
name = "light"
shape = "sphere"
radius = 0.05
mass = 1.0
position = [-0.4, 0.0, 1.0]

[[body]]
name = "heavy"
shape = "sphere"
radius = 0.05
mass = 2.0
position = [0.2, 0.0, 1.0]

[[spring]]
a = "light"
b = "heavy"
stiffness = 20.0
rest_length = 0.5

[reference]
model = "self_consistency"
{params}
"""


@pytest.fixture
def spring_pair() -> str:
    """A spec without a closed form in use: two spheres on a spring, free
    of gravity, judged by self-consistency (tests/test_self_consistency.py,
    tests/test_consensus.py); ``{params}`` takes the reference's params line."""
    return SPRING_PAIR


def without_effects(scene, *effects: str):
    """``scene`` with ``effects`` dropped after compilation: a spec cannot
    give a coefficient without its effect (contract/spec.py), but adapters
    must still switch off an effect a compiled scene does not list."""
    import dataclasses

    return dataclasses.replace(scene, effects=frozenset(scene.effects) - set(effects))


def _stray_outputs() -> list[str]:
    """Files in the repository that only a run writes: anything under
    results/ but its README (and committed baselines), MuJoCo's log,
    Hypothesis's storage directory."""
    results = ROOT / "results"
    out = [str(p.relative_to(ROOT)) for p in results.iterdir()
           if p.name not in ("README.md", "baselines")] if results.is_dir() else []
    out += [p.name for p in ROOT.glob("MUJOCO_LOG.TXT")]
    out += [p.name for p in ROOT.glob(".hypothesis")]
    return sorted(out)


_BEFORE: list[str] = []


def pytest_configure(config):
    """Hypothesis keeps a storage directory (its cache of the constants in
    the code under test, even with ``database=None``) in ``./.hypothesis``
    unless told otherwise: a temporary one per process instead."""
    import atexit
    import shutil
    import tempfile

    from hypothesis.configuration import set_hypothesis_home_dir

    home = tempfile.mkdtemp(prefix="physbench-hypothesis-")
    set_hypothesis_home_dir(home)
    atexit.register(shutil.rmtree, home, ignore_errors=True)


def pytest_sessionstart(session):
    _BEFORE[:] = _stray_outputs()


def pytest_sessionfinish(session, exitstatus):
    """Tests write only to temporary directories: after the suite,
    results/ holds only its README and no MuJoCo log is in the tree
    (whatever was there before the session is not the suite's doing)."""
    new = [p for p in _stray_outputs() if p not in _BEFORE]
    if new:
        print(f"\nerror: the test suite wrote into the repository: {', '.join(new)}", file=sys.stderr)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
