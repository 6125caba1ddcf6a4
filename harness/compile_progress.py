"""A first run that talks: while numba compiles kernels (the reference
engine's, on a fresh machine or after an engine change), stderr says what is
compiling, for how long so far, and about how long it will take.

A listener on numba's ``numba:compile`` event (numba calls it only for a
kernel it compiles, never for one it loads from the on-disk cache: a warm
process prints nothing).  :func:`watch` installs it where numba is already
imported (the runner calls it once an engine's adapter is loaded, so an
engine that does not use numba pays nothing); ``physbench compile`` installs
it before warming the cache.

- On a terminal: one line, rewritten in place about once a second, then a
  closing line when compiling stops.
- Anywhere else (a CI log, a file, a pipe, several workers sharing one
  terminal): a line when compiling starts, one every
  :data:`LOG_EVERY_S` seconds while it lasts, and a closing line: a few
  lines, not thousands.

Worker processes write to the parent's stderr (harness/workers.py passes
it as ``PHYSBENCH_PROGRESS_FD``; :func:`take_parent_stream`), not to their
own captured stderr.

The estimate is the longest compile this engine version took before on this
machine, kept in a small timing file beside the compiled kernels
(``compile-seconds.json`` in numba's cache directory, which engine/cache.py
keys by the engine's sources); without one, the typical first compile
(:data:`TYPICAL_S`).  Test: tests/test_install.py::test_compile_progress_lines.
"""

from __future__ import annotations

import atexit
import json
import os
import shutil
import sys
import threading
import time
from pathlib import Path
from typing import Any, TextIO

#: environment variable: a file descriptor (the parent's stderr) a worker writes progress to
PROGRESS_FD_ENV = "PHYSBENCH_PROGRESS_FD"
#: environment variable: "1" when several processes share that stream (no in-place line)
PROGRESS_SHARED_ENV = "PHYSBENCH_PROGRESS_SHARED"
#: seconds between lines where the line cannot be rewritten in place
LOG_EVERY_S = 30.0
#: seconds without a compile after which compiling counts as done
IDLE_S = 1.5
#: the reference engine's first compile on a 2-core x86-64 machine, all
#: kernels (engine/README.md "Compile time"): the estimate before any timing file exists
TYPICAL_S = 180.0
TIMING_FILE = "compile-seconds.json"

#: numba event kind the engine broadcasts around a wait for a kernel group
#: another process compiles (engine/compile_share.py ``WAIT_EVENT``: the
#: same text, not imported: the harness reaches the engine through adapters)
WAIT_EVENT = "physbench:compile_wait"

_installed: "CompileProgress | None" = None
#: (fd, shared) taken from the environment by a worker at start (take_parent_stream)
_parent_stream: tuple[int, bool] | None = None


def take_parent_stream() -> None:
    """In a worker process, at start: take the parent's stream from the
    environment and remove it there, so that no process this one starts
    inherits a descriptor number it was not given."""
    global _parent_stream
    fd = os.environ.pop(PROGRESS_FD_ENV, None)
    shared = os.environ.pop(PROGRESS_SHARED_ENV, None) == "1"
    if fd:
        try:
            _parent_stream = (int(fd), shared)
        except ValueError:
            _parent_stream = None


def _fmt_s(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min"


def group_name(key: Any) -> str:
    """A kernel group's key (engine/jit.py ``parts``) as a short name:
    ``('narrow', (True, None, ...))`` -> ``narrow (3 shape-pair families)``,
    ``('steady', False, 'rk4')`` -> ``steady False rk4``."""
    if not isinstance(key, tuple) or not key:
        return str(key)
    words = []
    for v in key:
        if isinstance(v, tuple):
            words.append(f"({sum(1 for f in v if f)} shape-pair families)")
        else:
            words.append(str(v))
    return " ".join(words)


def _cache_dir() -> Path | None:
    try:
        from numba.core import config

        d = getattr(config, "CACHE_DIR", "")
    except Exception:
        return None
    return Path(d) if d else None


def read_estimate(cache_dir: Path | None) -> float | None:
    """The longest compile recorded for this cache directory (s), or None."""
    if cache_dir is None:
        return None
    try:
        return float(json.loads((cache_dir / TIMING_FILE).read_text())["seconds"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def record_seconds(cache_dir: Path | None, seconds: float, kernels: int) -> None:
    """Keep the longest compile seen (seconds of compiling in one process)."""
    if cache_dir is None or seconds <= 0:
        return
    old = read_estimate(cache_dir) or 0.0
    if seconds <= old:
        return
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = cache_dir / f".{TIMING_FILE}.{os.getpid()}"
        tmp.write_text(json.dumps({"seconds": round(seconds, 1), "kernels": kernels}))
        os.replace(tmp, cache_dir / TIMING_FILE)
    except OSError:
        pass  # a read-only cache: no estimate next time, nothing else lost


def _numba_listener_base() -> type:
    from numba.core.event import Listener

    return Listener


class CompileProgress:
    """The progress printer: ``start(name)`` / ``end()`` around each
    outermost kernel compile (nested compiles of callees count as part of
    their caller), a ticker thread that rewrites or logs the line and
    closes it once compiling has stopped for :data:`IDLE_S`."""

    def __init__(self, stream: TextIO, interactive: bool, estimate_s: float | None,
                 log_every_s: float = LOG_EVERY_S, idle_s: float = IDLE_S, clock=time.monotonic):
        self.stream, self.interactive = stream, interactive
        self.estimate_s = estimate_s
        self.log_every_s, self.idle_s, self.clock = log_every_s, idle_s, clock
        self.lock = threading.Lock()
        self.depth = 0
        self.kernels = 0
        self.current = ""
        self.t0: float | None = None  # start of the current burst of compiling
        self.last_event = 0.0
        self.last_line = 0.0
        self.total_s = 0.0  # seconds spent compiling in this process (all bursts)
        self.bursts_done_s = 0.0
        self._ticker: threading.Thread | None = None

    # ---- events (numba's compiling thread) ---------------------------------
    def start(self, name: str) -> None:
        with self.lock:
            now = self.clock()
            self.depth += 1
            if self.depth > 1:
                return
            self.current = name
            self.last_event = now
            if self.t0 is None:
                self.t0 = now
                self._write(self._line(now, first=True), now)
                if self._ticker is None:
                    self._ticker = threading.Thread(target=self._tick, name="physbench-compile-progress", daemon=True)
                    self._ticker.start()

    def end(self) -> None:
        with self.lock:
            self.depth = max(0, self.depth - 1)
            if self.depth == 0:
                self.kernels += 1
                self.last_event = self.clock()

    def waiting(self, group: str) -> None:
        """This process waits for another one's compile of ``group`` (a
        kernel group held under its lock, engine/compile_share.py): said
        at once, since no compile event comes while it waits."""
        with self.lock:
            now = self.clock()
            self._write(f"physbench: waiting for another process's compile of {group} (then loaded from the cache)",
                        now, final=self.interactive and self.t0 is None)

    # ---- the line ----------------------------------------------------------
    def elapsed(self, now: float) -> float:
        return self.bursts_done_s + (now - self.t0 if self.t0 is not None else 0.0)

    def _line(self, now: float, first: bool = False) -> str:
        el = self.elapsed(now)
        if self.estimate_s is not None and el <= self.estimate_s:
            est = f"~{_fmt_s(self.estimate_s - el)} left of ~{_fmt_s(self.estimate_s)} (the last compile here)"
        elif self.estimate_s is not None:
            est = f"longer than the last compile here ({_fmt_s(self.estimate_s)})"
        else:
            est = f"a first compile takes about {_fmt_s(TYPICAL_S)} on 2 cores"
        if first:
            return (f"physbench: compiling numba kernels, now {self.current}; {est} (once per engine version: "
                    f"later runs load them from the cache)")
        return f"physbench: compiling kernels: {_fmt_s(el)} elapsed, {self.kernels} done; {est}; now {self.current}"

    def _write(self, text: str, now: float, final: bool = False) -> None:
        try:
            if self.interactive:  # one line, cut to the terminal's width (a wrapped line cannot be rewritten)
                width = shutil.get_terminal_size((100, 20)).columns - 1
                self.stream.write("\r\x1b[K" + text[:max(20, width)] + ("\n" if final else ""))
            else:
                self.stream.write(text + "\n")
            self.stream.flush()
        except (OSError, ValueError):
            pass  # the stream went away: progress is never worth an error
        self.last_line = now

    def _tick(self) -> None:
        while True:
            time.sleep(0.2 if self.interactive else 1.0)
            with self.lock:
                if self.t0 is None:
                    continue
                now = self.clock()
                if self.depth == 0 and now - self.last_event >= self.idle_s:
                    self.finish(now)
                    continue
                if self.depth > 0 and now - self.last_line >= (1.0 if self.interactive else self.log_every_s):
                    self._write(self._line(now), now)

    def finish(self, now: float | None = None) -> None:
        """Close the current burst: the closing line, the seconds added to
        :attr:`total_s` (call with the lock held or from one thread)."""
        if self.t0 is None:
            return
        now = self.clock() if now is None else now
        burst = max(0.0, min(now, self.last_event) - self.t0)
        self.bursts_done_s += burst
        self.total_s = self.bursts_done_s
        self.t0 = None
        self._write(f"physbench: compiled {self.kernels} kernel(s) in {_fmt_s(self.total_s)} (cached for later "
                    f"runs)", now, final=True)


def _stream() -> tuple[TextIO, bool]:
    """Where progress goes, and whether the line may be rewritten in place."""
    stream: TextIO = sys.stderr
    shared = False
    if _parent_stream is not None:
        fd, shared = _parent_stream
        try:
            stream = os.fdopen(fd, "w", buffering=1, closefd=False)
        except (OSError, ValueError):
            stream, shared = sys.stderr, False
    try:
        tty = stream.isatty()
    except (OSError, ValueError, AttributeError):
        tty = False
    return stream, tty and not shared


def watch(force: bool = False) -> "CompileProgress | None":
    """Install the progress listener once per process, if numba is imported
    (or ``force``: import it).  Returns the printer (None without numba)."""
    global _installed
    if _installed is not None:
        return _installed
    if not force and "numba" not in sys.modules:
        return None
    try:
        from numba.core import event
    except Exception:
        return None
    stream, interactive = _stream()
    cache = _cache_dir()
    printer = CompileProgress(stream, interactive, read_estimate(cache))

    class _Listener(_numba_listener_base()):
        def on_start(self, ev: Any) -> None:
            disp = (ev.data or {}).get("dispatcher")
            fn = getattr(disp, "py_func", None)
            name = f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', '?')}".removeprefix("physbench.")
            printer.start(name)

        def on_end(self, ev: Any) -> None:
            printer.end()

    event.register("numba:compile", _Listener())

    class _Waits(_numba_listener_base()):
        def on_start(self, ev: Any) -> None:
            printer.waiting(group_name((ev.data or {}).get("group")))

        def on_end(self, ev: Any) -> None:
            pass

    event.register(WAIT_EVENT, _Waits())

    def at_exit() -> None:
        with printer.lock:
            printer.finish()
        # the cache directory is read again: the engine may set it after watch()
        record_seconds(_cache_dir() or cache, printer.total_s, printer.kernels)

    atexit.register(at_exit)
    _installed = printer
    return printer
