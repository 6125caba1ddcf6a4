"""Where the compiled kernels' on-disk cache lives, and how it is keyed.

numba keys a cached kernel by its *own* source file's timestamp and size,
under a directory named by the file's absolute path.  Two things follow that
physbench does not want:

- a kernel that calls or inlines a kernel of another file (``phases.solve_stage``
  calls ``prepare.patch_rows``, ...) keeps its cached machine code when only
  that other file changes, so an edited or upgraded engine could run stale
  code without a word;
- the same engine at another path (an installed wheel, a CI runner's new
  workspace, a second checkout) finds nothing and compiles again.

The engine therefore registers its own cache locator with numba: a kernel of
the engine is cached under ``<base>/numba-<digest>/<subpackage>``, where the
digest covers every engine source file (any change to any of them gives a
fresh, empty cache: ``tests/test_engine_cache.py``) and nothing depends on
where the engine is installed.  A cache saved by one CI run is found by the
next, wherever its checkout lies.

The base directory is ``NUMBA_CACHE_DIR`` when the user set one, else
``$XDG_CACHE_HOME/physbench`` (``~/.cache/physbench``), else a directory
under the system's temporary directory when that is not writable.  Nothing is
written inside the installed package.  Directories of older digests are left
in place (a concurrent process of another version may be using one).
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent


def source_digest(root: Path = ROOT) -> str:
    """16 hex digits of SHA-256 over every ``*.py`` under ``root`` (relative
    path and bytes, in sorted path order)."""
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(b"\0")
        h.update(p.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:16]


def _writable(d: Path) -> bool:
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(d, os.W_OK)


def base_dir() -> Path:
    """``NUMBA_CACHE_DIR``, else the user's cache directory, else a
    temporary one (never the package's own folder)."""
    user = os.environ.get("NUMBA_CACHE_DIR")
    if user:
        return Path(user)
    home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "physbench"
    if _writable(home):
        return home
    return Path(tempfile.gettempdir()) / f"physbench-cache-{os.getuid() if hasattr(os, 'getuid') else 0}"


@functools.lru_cache(maxsize=None)
def _digest_of_root() -> str:
    return source_digest(ROOT)


def cache_dir(root: Path = ROOT) -> Path:
    """The directory the engine's compiled kernels are cached in."""
    digest = _digest_of_root() if root == ROOT else source_digest(root)
    return base_dir() / f"numba-{digest}"


@functools.lru_cache(maxsize=None)
def _kernel_dir(py_file: str, user: str | None, xdg: str | None) -> str | None:
    """The cache directory of the kernels defined in ``py_file``:
    ``cache_dir()/<subpackage>`` for a file of the engine, None for any
    other.  Found once per file and base directory (``user``, ``xdg``: the
    environment :func:`base_dir` reads; an engine module defines tens of
    kernels, and importing the engine defines about 240)."""
    try:
        rel = Path(py_file).resolve().relative_to(ROOT)
    except (ValueError, OSError):
        return None
    return str(cache_dir() / ("_".join(rel.parent.parts) or "engine"))


def _engine_locator():
    """numba's locator for the engine's kernels (defined lazily: importing
    this module does not import numba)."""
    from numba.core.caching import _CacheLocator

    class EngineCacheLocator(_CacheLocator):
        """Caches a kernel of ``engine/<sub>/<file>.py`` in
        ``cache_dir()/<sub>``: keyed by the digest of every engine source,
        not by path or timestamp (so an installed copy and a checkout of the
        same sources share one cache)."""

        def __init__(self, py_func, py_file: str, path: str):
            self._lineno = py_func.__code__.co_firstlineno
            # numba's warning for a kernel it cannot cache names this file
            self._py_file = py_file
            self._cache_path = path

        def get_cache_path(self) -> str:
            return self._cache_path

        def get_source_stamp(self) -> str:
            return _digest_of_root()

        def get_disambiguator(self) -> str:
            return str(self._lineno)

        @classmethod
        def from_function(cls, py_func, py_file):
            path = _kernel_dir(py_file, os.environ.get("NUMBA_CACHE_DIR"), os.environ.get("XDG_CACHE_HOME"))
            return None if path is None else cls(py_func, py_file, path)

    return EngineCacheLocator


def configure() -> Path:
    """Register the engine's cache locator with numba and point numba's
    cache at :func:`cache_dir`.  Must run before any engine module defines
    a ``cache=True`` kernel: numba picks a kernel's cache location when the
    kernel is defined (``engine/__init__`` calls this first)."""
    from numba.core import caching, config

    d = cache_dir()
    config.CACHE_DIR = str(d)
    # numba >= 0.61 names the class CacheImpl, older ones _CacheImpl
    impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
    if not any(getattr(c, "__name__", "") == "EngineCacheLocator" for c in impl._locator_classes):
        impl._locator_classes.insert(0, _engine_locator())
    return d
