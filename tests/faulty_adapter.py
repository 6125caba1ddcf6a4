"""A test-only engine, ``faulty``: pybullet, except that in one scene it
aborts, segfaults or hangs inside an engine call.

Registered by the tests that need it (``register("faulty", ...)``, or
``PHYSBENCH_ADAPTERS=faulty=tests.faulty_adapter:FaultyAdapter`` for a
command line in a subprocess); worker processes find it through the pool
(harness/execute.py).  Which scene and how: the environment variable
``FAULTY_FAULT=<scenario id>:<abort|segfault|hang|exit>`` (the base scene
only, not its variants), read when the scene is built, so the workers a
test starts see it."""

from __future__ import annotations

import ctypes
import dataclasses
import os
import time

from physbench.adapters.pybullet import PybulletAdapter

FAULT_ENV = "FAULTY_FAULT"
KINDS = ("abort", "segfault", "hang", "exit")


class FaultyAdapter(PybulletAdapter):
    """pybullet under another name; faults on request (see module doc)."""

    @classmethod
    def capabilities(cls):
        return dataclasses.replace(super().capabilities(), engine="faulty")

    def build(self, scene, settings):
        sid, _, kind = os.environ.get(FAULT_ENV, "").partition(":")
        self._fault = kind if scene.id == sid and scene.variant is None else ""
        assert self._fault in ("",) + KINDS, self._fault
        super().build(scene, settings)

    def _maybe_fault(self) -> None:
        if not self._fault:
            return
        if os.environ.get("PHYSBENCH_WORKER") != "1":  # never take the test process itself down
            raise RuntimeError(f"fault {self._fault} requested outside a worker process")
        if self._fault == "abort":
            os.write(2, b"faulty: Mass must be positive and finite\n")
            os.abort()
        if self._fault == "segfault":
            os.write(2, b"faulty: about to read address 0\n")
            ctypes.string_at(0)
        if self._fault == "hang":
            time.sleep(3600)
        if self._fault == "exit":
            os._exit(3)

    def step(self, n: int = 1) -> None:
        self._maybe_fault()
        super().step(n)

    def step_record(self, n, pos, quat, vel, angvel) -> None:
        self._maybe_fault()
        super().step_record(n, pos, quat, vel, angvel)


def worker_pid(_item):
    """The pid of the process running it (pool tests)."""
    return os.getpid()


def die(_item):
    """Kill the process running it, as the out-of-memory killer would (pool tests)."""
    if os.environ.get("PHYSBENCH_WORKER") == "1":
        os.kill(os.getpid(), 9)


def batch_item(item):
    """(what, n): "pid" returns (n, this process's pid), "die" kills this
    process (only in a worker), "hang" sleeps for a minute."""
    what, n = item
    if what == "die":
        die(n)
    if what == "hang":
        time.sleep(60)
    return n, os.getpid()
