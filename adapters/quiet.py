"""Silencing engines' C-level output and log files.

Some engines print from C when imported (pybullet 3.2.7: ``pybullet build
time: ...`` on stderr).  C-level output escapes
``contextlib.redirect_stdout`` and, on a pipe, sits in libc's buffer until
exit, where it would corrupt ``--json`` output.  :func:`quiet_import`
imports a module with file descriptors 1 and 2 pointed at /dev/null and
flushes C's buffers into /dev/null before restoring them.  Pinned by
tests/test_adapter_pybullet.py::test_import_and_run_print_nothing_subprocess.

MuJoCo appends its warnings ("Nan, Inf or huge value in QACC", "contact
buffer full" ...) to MUJOCO_LOG.TXT in the working directory unless a
handler takes them: :func:`collect_mujoco_warnings` installs one that keeps
them in a list instead (tests/test_execute.py::
test_mujoco_warnings_write_no_log_file).
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import io
import os
import sys
from types import ModuleType
from typing import Any

#: warnings kept per run at most: a blow-up repeats the same warning every step
MAX_WARNINGS = 20


def flush_c_stdio() -> None:
    """fflush(NULL): push anything C code buffered for stdout/stderr out *now*."""
    try:
        ctypes.CDLL(None).fflush(None)
    except Exception:  # pragma: no cover - no libc symbol table
        pass


def quiet_import(name: str) -> ModuleType:
    """Import module ``name`` with fds 1 and 2 pointed at /dev/null: flush
    Python's and C's streams, redirect, import, flush C's buffers into
    /dev/null, restore the fds.  An import failure propagates as the
    module's own exception (silencing loses nothing)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # pragma: no cover - closed stream
            pass
    flush_c_stdio()
    saved = {fd: os.dup(fd) for fd in (1, 2)}
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in saved:
            os.dup2(devnull, fd)
        # Python-level prints too, when sys.stdout is not fd 1 (pytest's
        # capsys; mujoco.mjx prints "Failed to import warp" with print())
        try:
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                return importlib.import_module(name)
        finally:
            flush_c_stdio()
            for fd, dup in saved.items():
                os.dup2(dup, fd)
    finally:
        os.close(devnull)
        for dup in saved.values():
            os.close(dup)


def collect_mujoco_warnings(mujoco: Any) -> list[str]:
    """Install a MuJoCo warning handler (process-wide) and return the list it
    appends to (at most MAX_WARNINGS entries; the caller clears it per run)."""
    warnings: list[str] = []

    def on_warning(msg: str) -> None:
        if len(warnings) < MAX_WARNINGS:
            warnings.append(str(msg))

    mujoco.set_mju_user_warning(on_warning)
    return warnings
