import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from harness.scene import canonical_example  # noqa: E402

# ../shared/examples/head_on.toml when shared/ stands beside the repository
# (as in CI), else the copy under tests/data
HEAD_ON = canonical_example()


@pytest.fixture
def head_on_path() -> Path:
    return HEAD_ON


def without_effects(scene, *effects: str):
    """``scene`` with ``effects`` dropped after compilation: a spec cannot
    give a coefficient without its effect (harness/spec.py), but adapters
    must still switch off an effect a compiled scene does not list."""
    import dataclasses

    return dataclasses.replace(scene, effects=frozenset(scene.effects) - set(effects))
