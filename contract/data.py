"""Where the shipped data is: the scenario specs (``scenarios/``) and sweep
suites (``suites/``) travel as package data of ``physbench``
(pyproject.toml's ``package-data``) and are found through
:mod:`importlib.resources`, so a checkout, an editable install and an
installed wheel read them the same way, from any working directory.

:data:`DATA_ROOT` is the package's own folder: the repository's root in a
checkout (the root's ``__init__.py`` is the package), ``.../site-packages/physbench``
in an installed wheel.  It is read, never written: results go under the
user's working directory (harness/results.py), compiled kernels under the
user's cache (engine/cache.py).  Test:
tests/test_install.py::test_the_wheel_runs_from_anywhere_and_writes_nothing_into_the_install.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def _package_root() -> Path:
    root = files("physbench")
    # a package installed as files (a wheel, a checkout) is a pathlib.Path;
    # physbench is never imported from a zip
    return root if isinstance(root, Path) else Path(str(root))


#: the package's folder (holds ``scenarios/`` and ``suites/``)
DATA_ROOT = _package_root()
#: the shipped scenario specs, by family: ``<family>/<name>.toml``
SHIPPED_SCENARIOS = DATA_ROOT / "scenarios"
#: the shipped sweep suites: ``<name>.toml``
SHIPPED_SUITES = DATA_ROOT / "suites"


def checkout_root() -> Path | None:
    """The repository's root when physbench runs from a checkout (the
    package folder holds ``pyproject.toml`` and ``tests/``), else None (an
    installed wheel has neither)."""
    if (DATA_ROOT / "pyproject.toml").is_file() and (DATA_ROOT / "tests").is_dir():
        return DATA_ROOT
    return None


def recorded_path(path: Path) -> str:
    """A spec file's path as rows record it: relative to the package's
    folder when inside it (``scenarios/billiards/head_on.toml``, the same
    for a checkout and an installed wheel), else absolute."""
    p = Path(path).resolve()
    try:
        return p.relative_to(DATA_ROOT.resolve()).as_posix()
    except ValueError:
        return str(p)
