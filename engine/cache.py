"""Where the compiled kernels' on-disk cache lives.

numba keys a cached kernel by its *own* source file's timestamp and size.
A kernel that calls or inlines a kernel of another file (``phases.solve_stage``
calls ``prepare.patch_rows``, ``sweeps.*``, ...) keeps its cached machine code
when only that other file changes, so an edited or upgraded engine could run
stale code without a word.  The engine therefore points numba's cache at a
directory named by a digest of every engine source file: any change to any
of them gives a fresh, empty cache (``tests/test_engine_cache.py``).

The base directory is ``NUMBA_CACHE_DIR`` when the user set one, else the
engine's own ``__pycache__`` (numba's in-tree default) when writable, else
the user's cache directory.  Directories of older digests are left in place
(a concurrent process of another checkout may be using one).
"""

from __future__ import annotations

import hashlib
import os
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


def cache_dir(root: Path = ROOT) -> Path:
    """The directory the engine's compiled kernels are cached in."""
    user = os.environ.get("NUMBA_CACHE_DIR")
    if user:
        base = Path(user)
    elif _writable(root / "__pycache__"):
        base = root / "__pycache__"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "physbench"
    return base / f"numba-{source_digest(root)}"


def configure() -> Path:
    """Point numba's cache at :func:`cache_dir`.  Must run before any engine
    module defines a ``cache=True`` kernel: numba picks a kernel's cache
    location when the kernel is defined (``engine/__init__`` calls this
    first)."""
    from numba.core import config

    d = cache_dir()
    config.CACHE_DIR = str(d)
    return d
