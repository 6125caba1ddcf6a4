import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# The shared canonical spec lives beside the repository (../shared); CI clones
# the repo with shared/ beside it.  Fall back to the copy under tests/data.
_SHARED = ROOT.parent / "shared" / "examples" / "head_on.toml"
_LOCAL = ROOT / "tests" / "data" / "head_on.toml"
HEAD_ON = _SHARED if _SHARED.is_file() else _LOCAL


@pytest.fixture
def head_on_path() -> Path:
    return HEAD_ON
