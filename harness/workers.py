"""Running a function over items in reusable worker processes under a
wall-clock watchdog: the local executors of harness/execute.py (and the
run processes inside each Dask worker, harness/dask_executor.py).

- :class:`WorkerPool` runs any module-level function over items in ``jobs``
  worker processes.  Workers are fresh interpreters (``subprocess``, not
  ``fork``: nothing of a multi-threaded parent's locks is inherited), reused
  from one item to the next.  A worker that dies (abort, segfault, killed
  for memory) costs only the item it was running, which comes back as
  :class:`WorkerLost` with the signal and the tail of the worker's stderr;
  an item that outlives its budget is ``timeout``: its worker is killed and
  a fresh one takes the next item.  Nothing else of the job is touched;
- :class:`InlineExecutor` is the same interface in this process (no
  isolation: for debugging, profiling and tests that patch the runner).

Workers register the shipped engines and the entry-point plug-ins
themselves (importing ``physbench.adapters``).  Adapters registered at run
time (``adapters.base.register``: a test's faulty engine, a notebook's own
adapter) reach them by ``module:Class`` reference: the pool passes them in
``PHYSBENCH_ADAPTERS`` (``name=module:Class,...``), which the command line
also reads at start, so an adapter not packaged as a plug-in can be named
there too.  Worker stdout and stderr go to a file in the pool's
temporary directory, which is also the workers' working directory (so
nothing an engine writes lands in the user's tree); the pool removes it.
"""

from __future__ import annotations

import importlib
import math
import os
import pickle
import select
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from physbench.harness import status as st
from physbench.harness.compile_progress import PROGRESS_FD_ENV, PROGRESS_SHARED_ENV, take_parent_stream
from physbench.adapters.base import _REGISTRY, engine_origin
from physbench.adapters.base import register

#: environment variable naming extra adapters, ``name=module:Class,...``
ADAPTERS_ENV = "PHYSBENCH_ADAPTERS"
#: set (to "1") in worker processes
WORKER_ENV = "PHYSBENCH_WORKER"
#: characters of a dead worker's stderr kept in its row
STDERR_TAIL = 2000
_HEADER = struct.Struct("<Q")
#: processes one reference build may compile in (the engine's
#: ``compile_share.JOBS_ENV``: a pool of several workers gives each 1)
COMPILE_JOBS_ENV = "PHYSBENCH_COMPILE_JOBS"

#: environment of every run process: BLAS, OpenMP and numba held to one
#: thread, so N workers use N cores (tests/test_execute.py::test_run_processes_use_one_thread)
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                  "NUMBA_NUM_THREADS": "1"}


class _Wait:
    """The type of :data:`WAIT`."""

    def __repr__(self) -> str:
        return "WAIT"


#: what an executor's item iterator yields when it has nothing to run yet:
#: the executor runs what it has in flight and asks again once a result is
#: in (a search's next value depends on the last one: harness/schedule.py)
WAIT = _Wait()
#: what :func:`take` returns when the source has no more items, ever
END = object()


def take(source: Iterator[Any], in_flight: bool) -> Any:
    """The next item of an executor's item source: an item, :data:`WAIT`
    (nothing to run until a result is in) or :data:`END`.  Raises
    RuntimeError for WAIT with nothing ``in_flight``: no result would ever
    come (a bug of the source)."""
    item = next(source, END)
    if item is WAIT and not in_flight:
        raise RuntimeError("the item source waits for a result, but nothing is running")
    return item


@dataclass(frozen=True)
class Batch:
    """Items one worker runs one after the other in one hand-over (a Dask
    task, a run process's request): the executors' map takes a Batch from
    its source like an item and yields ``(item, value)`` for each of its
    ``items``, each under its own budget.  Where a worker dies or hangs in
    the middle, the items it finished keep their values, the one it was
    running is lost (:class:`WorkerLost`) and the rest run again
    (harness/schedule.py makes batches; tests/test_execute.py)."""

    items: tuple[Any, ...]

    @property
    def key(self) -> str:
        first = getattr(self.items[0], "key", None) if self.items else None
        return f"batch{len(self.items)}-{first if isinstance(first, str) else repr(self.items[:1])}"


def members(unit: Any) -> tuple[Any, ...]:
    """The items of an executor's unit of work: a :class:`Batch`'s items,
    or the one item."""
    return unit.items if isinstance(unit, Batch) else (unit,)


def grace_s(budget_s: float) -> float:
    """Seconds the watchdog waits past an item's budget before killing its
    worker: the runner stops stepping at the budget itself (between step
    blocks) and still computes metrics on the partial trace, which the
    grace leaves time for; only a worker stuck inside one call is killed."""
    return min(60.0, 2.0 + 0.1 * budget_s)


# ---------------------------------------------------------------------------
# lost items


@dataclass
class WorkerLost:
    """An item that produced no value: ``kind`` is ``raised`` (the function
    raised), ``died`` (the worker process died: ``signal`` names the signal,
    or the exit code) or ``timeout`` (the watchdog killed it).  ``status``
    is the run status it stands for (error or timeout)."""

    kind: str
    message: str
    stderr_tail: str = ""
    traceback: str = ""
    signal: str = ""
    #: the machine.* summary of the host it ran on, when not this one (a Dask worker)
    machine: dict[str, str] | None = None

    @property
    def status(self) -> str:
        return st.TIMEOUT if self.kind == "timeout" else st.ERROR

    def full_message(self) -> str:
        tail = self.stderr_tail.strip()
        if not tail:
            return self.message
        last = " | ".join(line.strip() for line in tail.splitlines()[-3:] if line.strip())
        return f"{self.message}; stderr: {last}"



_SIGNAL_WHY = {
    "SIGABRT": "abort inside the engine (a failed assertion or check)",
    "SIGSEGV": "segmentation fault inside the engine",
    "SIGBUS": "bus error inside the engine",
    "SIGFPE": "arithmetic fault inside the engine",
    "SIGILL": "illegal instruction inside the engine",
    "SIGKILL": "killed from outside the worker, e.g. by the out-of-memory killer",
}


def _death(rc: int) -> tuple[str, str]:
    """(signal or exit text, description) of a worker's return code."""
    if rc < 0:
        try:
            name = signal.Signals(-rc).name
        except ValueError:
            name = f"signal {-rc}"
        return name, f"{name} ({_SIGNAL_WHY.get(name, 'killed by a signal')})"
    return f"exit {rc}", f"exit code {rc}"


# ---------------------------------------------------------------------------
# executors


class InlineExecutor:
    """Items run one by one in this process: no isolation, no watchdog (a
    crash takes the process down; the runner's own timeout still stops a
    run between step blocks)."""

    jobs = 1

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], budget_s: Callable[[Any], float | None] = None,
            on_start: Callable[[Any], None] | None = None,
            priority: Callable[[Any], int] | None = None) -> Iterator[tuple[Any, Any]]:
        source = iter(items)
        while (unit := take(source, False)) is not END:  # one at a time: never anything in flight
            for item in members(unit):
                if on_start:
                    on_start(item)
                try:
                    value = fn(item)
                except Exception as e:
                    value = WorkerLost("raised", f"{type(e).__name__}: {e}", traceback=traceback.format_exc(limit=5))
                yield item, value

    def close(self) -> None:
        pass

    def __enter__(self) -> "InlineExecutor":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def extra_adapters() -> tuple[dict[str, str], list[str]]:
    """Registered adapters that are not shipped, as {name: 'module:Class'}
    (those a worker can import: not defined in ``__main__`` or in a
    function), merged with the ones named in the environment; and the
    directories their modules are imported from (a test module imported by
    file name needs its own directory on the path)."""

    out = _parse_adapters(os.environ.get(ADAPTERS_ENV, ""))
    paths: list[str] = []
    for name, loader in _REGISTRY.items():
        # shipped engines and entry-point plug-ins register themselves in the
        # worker; adapters registered at run time or from PHYSBENCH_ADAPTERS are passed on
        if engine_origin(name) not in ("run time", ADAPTERS_ENV) or name in out:
            continue
        try:
            cls = loader()
        except Exception:
            continue  # a broken adapter: the worker reports it when asked to run it
        if cls.__module__ == "__main__" or "<locals>" in cls.__qualname__:
            continue
        out[name] = f"{cls.__module__}:{cls.__qualname__}"
        f = getattr(sys.modules.get(cls.__module__), "__file__", None)
        if f:
            root = Path(f).resolve().parent
            for _ in range(cls.__module__.count(".")):
                root = root.parent
            if str(root) not in paths:
                paths.append(str(root))
    return out, paths


def _parse_adapters(text: str) -> dict[str, str]:
    out = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, _, ref = part.partition("=")
        if not name or ":" not in ref:
            raise ValueError(f"{ADAPTERS_ENV}: expected name=module:Class entries, got {part!r}")
        out[name.strip()] = ref.strip()
    return out


def register_env_adapters(text: str | None = None) -> list[str]:
    """Register the adapters named in ``PHYSBENCH_ADAPTERS`` (or ``text``),
    ``name=module:Class,...``; each is imported when first asked for.
    Returns their names."""

    refs = _parse_adapters(os.environ.get(ADAPTERS_ENV, "") if text is None else text)

    def loader(ref: str):
        def load():
            mod, _, qual = ref.partition(":")
            obj: Any = importlib.import_module(mod)
            for part in qual.split("."):
                obj = getattr(obj, part)
            return obj
        return load

    for name, ref in refs.items():
        register(name, loader(ref), ADAPTERS_ENV)
    return list(refs)


def _progress_fd() -> int | None:
    """A duplicate of this process's stderr for the workers' compile
    progress, or None when stderr has no file descriptor."""
    try:
        fd = os.dup(sys.stderr.fileno())
    except (AttributeError, OSError, ValueError):
        return None
    os.set_inheritable(fd, True)
    return fd


#: bytes read from a worker's pipe at a time
READ_CHUNK = 1 << 16


class _Worker:
    """One worker process: its pipes, stderr file, and the item it runs."""

    def __init__(self, workdir: Path, env: dict[str, str], n: int):
        self.err_path = workdir / f"worker-{n}.stderr"
        self.err = open(self.err_path, "ab")
        fd = env.get(PROGRESS_FD_ENV)
        self.proc = subprocess.Popen([sys.executable, "-c", "from physbench.harness.workers import worker_main; worker_main()"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.err, cwd=workdir,
                                     env=env, close_fds=True, pass_fds=(int(fd),) if fd else ())
        self.fd = self.proc.stdout.fileno()
        os.set_blocking(self.fd, False)
        self.buf = bytearray()
        self.items: tuple[Any, ...] = ()  # the unit's items; self.index: the one running
        self.index = 0
        self.budgets: list[float | None] = []
        self.busy = False
        self.deadline = math.inf
        self.t0 = 0.0
        self.err_offset = 0

    @property
    def item(self) -> Any:
        """The item running (or the last one run)."""
        return self.items[min(self.index, len(self.items) - 1)]

    @property
    def budget(self) -> float | None:
        return self.budgets[min(self.index, len(self.budgets) - 1)]

    def send(self, fn: Callable, unit: Any, budgets: list[float | None]) -> None:
        """Hand ``unit`` (an item or a :class:`Batch`) over; ``budgets``: one per item."""
        payload = pickle.dumps((fn, unit), protocol=pickle.HIGHEST_PROTOCOL)
        self.err.flush()
        self.err_offset = os.fstat(self.err.fileno()).st_size  # the file the worker's stderr goes to
        self.proc.stdin.write(_HEADER.pack(len(payload)) + payload)
        self.proc.stdin.flush()
        self.items, self.index, self.budgets, self.busy = members(unit), 0, budgets, True
        self._start_item()

    def _start_item(self) -> None:
        # each item of a batch is watched under its own budget, from when the one before replied
        self.t0 = time.monotonic()
        b = self.budget
        self.deadline = self.t0 + b + grace_s(b) if b is not None else math.inf

    def read(self) -> tuple[bool, list[Any]]:
        """Read what is there: (eof, the whole replies in), one reply per
        item; eof: the worker died (end of file)."""
        eof, got = False, False
        while True:
            # 64 KiB at a time: a reply is a few KiB, and a 1 MiB read buffer is allocated (mmap) and freed
            # at every read (about 10 us of CPU each)
            try:
                chunk = os.read(self.fd, READ_CHUNK)
            except BlockingIOError:
                break
            if not chunk:
                eof = True
                break
            self.buf += chunk
            got = True
            if len(chunk) < READ_CHUNK:
                break  # the pipe is empty
        if not got:
            return eof, []
        msgs = []
        while len(self.buf) >= _HEADER.size:
            (n,) = _HEADER.unpack_from(self.buf)
            if len(self.buf) < _HEADER.size + n:
                break
            msgs.append(pickle.loads(bytes(self.buf[_HEADER.size:_HEADER.size + n])))
            del self.buf[:_HEADER.size + n]
        return eof, msgs

    def replied(self) -> Any:
        """Count the running item's reply in: returns the item; the next
        item of the unit starts its clock, or the worker is free."""
        item = self.items[self.index]
        self.index += 1
        if self.index < len(self.items):
            self._start_item()
        else:
            self.busy = False
        return item

    def rest(self) -> Any:
        """The unit's items after the running one (not started): None, an
        item, or a Batch."""
        rest = self.items[self.index + 1:]
        return None if not rest else rest[0] if len(rest) == 1 else Batch(rest)

    def stderr_tail(self) -> str:
        try:
            with open(self.err_path, "rb") as f:
                f.seek(self.err_offset)
                data = f.read()
        except OSError:
            return ""
        return data[-STDERR_TAIL:].decode("utf-8", errors="replace")

    def kill(self) -> int:
        if self.proc.poll() is None:
            self.proc.kill()
        rc = self.proc.wait()
        self.close_files()
        return rc

    def stop(self) -> None:
        """Ask an idle worker to leave (end of its input), kill it if it does not."""
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.close_files()

    def close_files(self) -> None:
        for f in (self.proc.stdin, self.proc.stdout, self.err):
            try:
                f.close()
            except (OSError, ValueError):
                pass


class WorkerPool:
    """``jobs`` reusable worker processes under a wall-clock watchdog.

    ``map(fn, items, budget_s, on_start)`` runs the module-level function
    ``fn`` on each item (both pickled to the worker) and yields ``(item,
    value)`` as items finish, in finishing order; ``value`` is what ``fn``
    returned or a :class:`WorkerLost`.  ``budget_s(item)`` is the item's
    wall-clock budget (None: unlimited): past budget + :func:`grace_s` its
    worker is killed.  ``items`` is read lazily, one item when a worker is
    free (a free worker gets its next item before the consumer handles the
    result it just gave: writing a row does not idle it); it may yield
    :data:`WAIT` (nothing to run until a result is in).  ``priority`` is
    for executors where items queue (Dask); here an item is read only when
    a worker is free to run it.  Tests: tests/test_execute.py,
    tests/test_schedule.py."""

    #: the workers share this machine's compile caches (harness.execute.shares_compile)
    shares_compile_cache = True

    def __init__(self, jobs: int = 1):
        self.jobs = max(1, int(jobs))
        self.workdir = Path(tempfile.mkdtemp(prefix="physbench-workers-"))
        env = dict(os.environ)
        env[WORKER_ENV] = "1"
        env[WORKER_ENV + "_PARENT"] = str(os.getpid())
        env.update(ONE_THREAD_ENV)
        if self.jobs > 1:  # (several workers share a cold compile already: engine/compile_share.py)
            env.setdefault(COMPILE_JOBS_ENV, "1")
        adapters, paths = extra_adapters()
        # physbench itself is imported as this process imported it (installed, or
        # an editable install's finder); added: a checkout's root (its tests'
        # modules hold functions and adapters workers run) and the folders of
        # run-time registered adapters' modules
        from physbench.contract.data import checkout_root

        root = checkout_root()
        paths = ([str(root)] if root is not None else []) + [p for p in paths if p != str(root)]
        if paths:
            env["PYTHONPATH"] = os.pathsep.join(paths + [p for p in [env.get("PYTHONPATH")] if p])
        if adapters:
            env[ADAPTERS_ENV] = ",".join(f"{k}={v}" for k, v in adapters.items())
        # compile progress goes to this process's stderr, not the worker's
        # captured one (harness/compile_progress.py)
        self.progress_fd = _progress_fd()
        if self.progress_fd is not None:
            env[PROGRESS_FD_ENV] = str(self.progress_fd)
            env[PROGRESS_SHARED_ENV] = "1" if self.jobs > 1 else "0"
        self.env = env
        self.idle: list[_Worker] = []
        self.started = 0

    def _spawn(self) -> _Worker:
        self.started += 1
        return _Worker(self.workdir, self.env, self.started)

    def map(self, fn: Callable[[Any], Any], items: Iterable[Any], budget_s: Callable[[Any], float | None] = None,
            on_start: Callable[[Any], None] | None = None,
            priority: Callable[[Any], int] | None = None) -> Iterator[tuple[Any, Any]]:
        source = iter(items)
        more = True  # the source may still give items
        busy: list[_Worker] = []
        # the items of a batch after one whose worker died or hung: run before the source's next
        again: list[Any] = []
        # finished items not yet handed to the consumer: free workers get their next item
        # before the consumer handles these (writes rows ...), not after
        out: list[tuple[Any, Any]] = []

        def lost(w: _Worker, value: WorkerLost) -> None:
            out.append((w.item, value))
            rest = w.rest()
            if rest is not None:
                again.append(rest)

        try:
            while more or busy or out or again:
                while (more or again) and len(busy) < self.jobs:
                    if out and not self.idle:
                        # only a fresh worker is free: hand the results over first (a consumer
                        # that stops at a lost worker would kill it unused;
                        # tests/test_fuzz.py::test_engine_runs_are_isolated_and_counted)
                        break
                    unit = again.pop(0) if again else take(source, bool(busy or out))
                    if unit is END:
                        more = False
                    if unit is END or unit is WAIT:
                        break
                    budgets = [budget_s(i) if budget_s else None for i in members(unit)]
                    w = self.idle.pop() if self.idle else self._spawn()
                    try:
                        w.send(fn, unit, budgets)
                    except (BrokenPipeError, OSError):  # an idle worker that died: a fresh one
                        w.kill()
                        w = self._spawn()
                        try:
                            w.send(fn, unit, budgets)
                        except (BrokenPipeError, OSError) as e:
                            w.kill()
                            out.extend((i, WorkerLost("died", f"worker process could not be started: {e}"))
                                       for i in members(unit))
                            continue
                    except Exception as e:  # the item or function cannot be pickled
                        self.idle.append(w)
                        out.extend((i, WorkerLost("raised", f"{type(e).__name__}: {e}")) for i in members(unit))
                        continue
                    if on_start:
                        on_start(w.item)
                    busy.append(w)
                if out:  # then back to the source: what it gives may depend on these results
                    while out:
                        yield out.pop(0)
                    continue
                if not busy:
                    continue
                now = time.monotonic()
                wait = max(0.0, min(w.deadline for w in busy) - now)
                poller = select.poll()
                for w in busy:
                    poller.register(w.fd, select.POLLIN | select.POLLHUP | select.POLLERR)
                ready = {fd for fd, _ in poller.poll(1e3 * min(wait, 3600.0))}
                for w in [w for w in busy if w.fd in ready]:
                    eof, msgs = w.read()
                    for kind, payload, tb in msgs:
                        item = w.replied()
                        out.append((item, payload if kind == "ok" else WorkerLost("raised", payload, traceback=tb)))
                        if w.busy and on_start:
                            on_start(w.item)
                    if not w.busy:
                        busy.remove(w)
                        self.idle.append(w)
                    elif eof:  # end of file: the worker died
                        busy.remove(w)
                        tail = w.stderr_tail()
                        rc = w.kill()
                        sig, why = _death(rc)
                        lost(w, WorkerLost("died", f"worker process died while running this item: {why}", tail,
                                           signal=sig))
                now = time.monotonic()
                for w in [w for w in busy if w.deadline <= now]:
                    busy.remove(w)
                    tail = w.stderr_tail()
                    w.kill()
                    lost(w, WorkerLost("timeout", f"no result after {now - w.t0:.1f} s wall (budget {w.budget:g} s): "
                                                  "worker killed, stuck inside one call", tail))
        finally:
            for w in busy:  # abandoned (interrupted, or the consumer stopped): nothing of theirs is kept
                w.kill()

    def close(self) -> None:
        for w in self.idle:
            w.stop()
        self.idle = []
        shutil.rmtree(self.workdir, ignore_errors=True)
        if self.progress_fd is not None:
            os.close(self.progress_fd)
            self.progress_fd = None

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# ---------------------------------------------------------------------------
# the worker


def _die_with_parent() -> None:
    """Linux: SIGKILL this worker when the process that started it dies (a
    ``kill -9`` of a check must not leave a worker hanging in an engine
    call).  Elsewhere a worker leaves when its input closes."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
        if str(os.getppid()) != os.environ.get(WORKER_ENV + "_PARENT", str(os.getppid())):
            os._exit(1)  # the parent died before the call
    except Exception:
        pass


def worker_main() -> None:
    """Worker loop: read (function, item or :class:`Batch`) frames from
    stdin, write one ("ok", value, "") or ("raised", message, traceback)
    frame per item, as each finishes.  The
    replies go to a private copy of the original stdout; fd 1 is pointed
    at stderr, so nothing an engine prints can corrupt them."""
    _die_with_parent()
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    inp = sys.stdin.buffer
    take_parent_stream()  # compile progress to the parent's stderr
    register_env_adapters()
    while True:
        head = inp.read(_HEADER.size)
        if len(head) < _HEADER.size:
            return
        (n,) = _HEADER.unpack(head)
        fn, unit = pickle.loads(inp.read(n))
        for item in members(unit):  # one reply per item, sent as it finishes
            try:
                reply = ("ok", fn(item), "")
                data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
            except Exception as e:
                data = pickle.dumps(("raised", f"{type(e).__name__}: {e}", traceback.format_exc(limit=8)),
                                    protocol=pickle.HIGHEST_PROTOCOL)
            sys.stderr.flush()
            try:
                out.write(_HEADER.pack(len(data)) + data)
                out.flush()
            except BrokenPipeError:  # the parent is gone
                return


__all__ = ["WorkerLost", "WorkerPool", "InlineExecutor", "Batch", "members", "register_env_adapters", "worker_main", "grace_s",
           "WAIT", "END", "take", "ONE_THREAD_ENV", "ADAPTERS_ENV", "WORKER_ENV"]
