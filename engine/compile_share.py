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
builds the same scene (FILE: the scene input and settings as JSON) taking
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
import json
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, NamedTuple

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


#: numba event kind broadcast around a wait for a group another process holds (data: {"group": key})
WAIT_EVENT = "physbench:compile_wait"


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
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if not wait:
                yield False
                return
            # another process compiles it: said on numba's event bus (harness/compile_progress.py shows it)
            from numba.core import event

            with event.trigger_event(WAIT_EVENT, data={"group": key}):
                fcntl.flock(fd, fcntl.LOCK_EX)
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


def _encode(v: Any) -> Any:
    """A scene input's field as JSON (floats round-trip exactly: repr)."""
    import numpy as np

    if isinstance(v, np.ndarray):
        return {"nd": v.tolist(), "dtype": v.dtype.str, "shape": list(v.shape)}
    if isinstance(v, (tuple, list)):
        return {"tuple": [_encode(x) for x in v]}
    if isinstance(v, frozenset):
        return {"set": sorted(v)}
    if isinstance(v, np.generic):
        return v.item()
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    raise TypeError(f"cannot hand a {type(v).__name__} to a helper")


def _decode(v: Any) -> Any:
    import numpy as np

    if isinstance(v, dict):
        if "nd" in v:
            return np.array(v["nd"], dtype=np.dtype(v["dtype"])).reshape(v["shape"])
        if "tuple" in v:
            return tuple(_decode(x) for x in v["tuple"])
        if "set" in v:
            return frozenset(v["set"])
    return v


def write_build(path: Path, inp: Any, settings: dict) -> None:
    """The scene input ``inp`` (an engine.model.SceneInput; its ``scene``,
    the caller's own object the engine never reads, left out) and the
    build's ``settings``, as JSON at ``path`` (:func:`read_build`)."""
    import dataclasses

    fields = {f.name: _encode(getattr(inp, f.name)) for f in dataclasses.fields(inp) if f.name != "scene"}
    path.write_text(json.dumps({"input": fields, "settings": {k: _encode(v) for k, v in settings.items()}}))


def read_build(path: Path) -> tuple:
    """(scene input, settings) as :func:`write_build` wrote them."""
    from physbench.engine.model import SceneInput

    d = json.loads(path.read_text())
    return (SceneInput(**{k: _decode(v) for k, v in d["input"].items()}),
            {k: _decode(v) for k, v in d["settings"].items()})


class Helper(NamedTuple):
    """A started helper: its process and the file its stderr goes to."""

    proc: subprocess.Popen
    log: Path


def start_helper(inp: Any, settings: dict) -> Helper | None:
    """A helper process building the scene ``inp`` with ``settings`` (the
    build's own arguments) when the build may use two processes; else None.
    The caller decides that the build is cold, and waits for it
    (:func:`end_helper`)."""
    if REVERSED or jobs() < 2 or fcntl is None:
        return None
    try:
        _dir().mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix="build-", suffix=".json", dir=_dir())
        os.close(fd)
        write_build(Path(name), inp, settings)
        log = Path(name).with_suffix(".log")
        err = open(log, "wb")
    except (OSError, TypeError, ValueError):
        return None
    env = dict(os.environ)
    env[JOBS_ENV] = "1"
    with err:
        proc = subprocess.Popen([sys.executable, "-m", "physbench.engine", "--help-build", name], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    return Helper(proc, log)


def end_helper(h: Helper | None) -> None:
    """Wait for a helper (it has nothing left but loading what this build
    compiled: every group it holds, this build waited for).  A helper that
    failed costs only time (this build compiled what it left): a warning
    names its exit status and the file that keeps its stderr
    (tests/test_compile_share.py::test_a_failed_helper_is_a_warning_with_its_log)."""
    if h is None:
        return
    p = h.proc
    with contextlib.suppress(subprocess.TimeoutExpired):
        p.wait(timeout=120)
    if p.poll() is None:  # pragma: no cover - a stuck helper
        p.kill()
        p.wait()
    if p.returncode == 0:
        with contextlib.suppress(OSError):
            h.log.unlink()
        return
    try:
        tail = h.log.read_text(errors="replace")[-600:].strip()
    except OSError:
        tail = ""
    warnings.warn(f"the compile helper process exited with status {p.returncode} (this build compiled its "
                  f"kernel groups itself); its stderr is in {h.log}" + (f": ...{tail}" if tail else ""),
                  RuntimeWarning, stacklevel=2)
