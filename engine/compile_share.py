"""Compiling a cold cache on two cores, nothing compiled twice.

numba compiles on one core.  The kernels a build needs come in groups
(``engine.jit.parts``, and the fused steps: ``("steady", sweeps,
integrator)``, ``("flight_step", integrator)``).  Every process compiles
(or loads) a group under an exclusive lock on its file in the cache
directory (``<cache_dir>/groups/<digest of the key>.lock``) and marks it
done (``.done``) once it is in the cache.  :func:`take` runs a list of
groups: a group another process holds is put back and taken again at the
end (blocking), when the other process has cached it and this one loads it.
So two processes building at once -- two workers of one ``physbench check``
on a fresh machine, or a build and its helper -- share the compiling
instead of both doing all of it.

A build on a cold cache (groups of about :data:`HELPER_MIN_S` CPU seconds
or more not done: ``engine.jit.cold_seconds``) that may use two cores
starts a *helper*: ``python -m physbench.engine --help-build FILE``
builds the same scene (FILE: the pickled scene input and settings) taking
the groups in the opposite order (:data:`REVERSED`), so the build and its
helper start at opposite ends and meet (``engine.Engine``).  How many
processes a build may use: ``PHYSBENCH_COMPILE_JOBS`` (1 or 2), else 2 where
this process may use two cores or more; a worker pool of several processes
gives its workers 1 (they share through the locks already).

Tests: tests/test_compile_share.py.  Locks are ``fcntl.flock`` locks (the
kernel drops them with their process: a helper that dies leaves nothing
held); where ``fcntl`` is missing every process compiles alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None

#: processes a build may use: this environment variable (1 or 2), else 2
#: where this process may use two cores or more
JOBS_ENV = "PHYSBENCH_COMPILE_JOBS"

#: this process is a build's helper (engine/__main__.py ``--help-build``): it
#: takes the groups in reverse order
REVERSED = False


def jobs() -> int:
    """Processes a build may compile in (1 or 2)."""
    v = os.environ.get(JOBS_ENV, "").strip()
    if v:
        try:
            return 2 if int(v) >= 2 else 1
        except ValueError:
            return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 2 if cores >= 2 else 1


def _dir() -> Path:
    from physbench.engine.cache import cache_dir

    return cache_dir() / "groups"


def _path(key: tuple, suffix: str) -> Path:
    return _dir() / (hashlib.sha256(repr(key).encode()).hexdigest()[:20] + suffix)


def done(key: tuple) -> bool:
    """Whether the group ``key`` was compiled into this engine's cache."""
    return _path(key, ".done").exists()


def _mark(key: tuple) -> None:
    p = _path(key, ".done")
    if not p.exists():
        p.write_text(repr(key) + "\n")


def _open(key: tuple) -> int | None:
    if fcntl is None:
        return None
    try:
        _dir().mkdir(parents=True, exist_ok=True)
        return os.open(_path(key, ".lock"), os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:  # (a read-only cache: every process alone)
        return None


@contextlib.contextmanager
def group(key: tuple, wait: bool = True) -> Iterator[bool]:
    """Hold the lock of group ``key`` (waiting for it with ``wait``; else
    yielding False at once when another process holds it); marks it done
    when the block ends without an exception."""
    fd = _open(key)
    if fd is None:
        yield True
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        yield True
        _mark(key)
    finally:
        os.close(fd)  # (releases the lock)


def take(keys: Iterable[tuple], run: Callable[[tuple], Any]) -> None:
    """``run(key)`` for each group of ``keys`` (in reverse order in a
    helper), each under its lock: a group another process holds is taken
    again after the others, waiting for it (it then loads from the cache)."""
    keys = list(keys)
    if REVERSED:
        keys.reverse()
    later = []
    for k in keys:
        with group(k, wait=False) as mine:
            if mine:
                run(k)
                continue
        later.append(k)
    for k in later:
        with group(k):
            run(k)


#: a build starts a helper when what it has left to compile takes about
#: this many CPU seconds or more (engine.jit.cold_seconds; a helper's own
#: start costs ~1.5 s)
HELPER_MIN_S = 20.0


def start_helper(inp: Any, settings: dict) -> subprocess.Popen | None:
    """A helper process building the scene ``inp`` with ``settings`` (the
    build's own arguments) when the build may use two processes; else None.
    The caller decides that the build is cold, and waits for the helper
    (:func:`end_helper`)."""
    if REVERSED or jobs() < 2 or fcntl is None:
        return None
    try:
        _dir().mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix="build-", suffix=".pickle", dir=_dir())
        with os.fdopen(fd, "wb") as f:
            pickle.dump((inp, dict(settings)), f)
    except (OSError, pickle.PicklingError, TypeError, AttributeError):
        return None
    env = dict(os.environ)
    env[JOBS_ENV] = "1"
    return subprocess.Popen([sys.executable, "-m", "physbench.engine", "--help-build", name], env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def end_helper(p: subprocess.Popen | None) -> None:
    """Wait for a helper (it has nothing left but loading what this build
    compiled: every group it holds, this build waited for)."""
    if p is not None:
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=120)
        if p.poll() is None:  # pragma: no cover - a stuck helper
            p.kill()
            p.wait()
