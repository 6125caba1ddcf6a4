"""The stage protocol and the per-stage profile.

Every pipeline stage is a callable with ONE signature,
``stage(model, state, ctx) -> None``, and a ``name``.  The step loop runs a
stage through :meth:`Profile.run`, which counts the call and accumulates its
CPU time (``time.perf_counter``; the stages are single-threaded numpy, so
wall time of the call is its CPU time).  Stages that call other stages (the
integrators evaluate the force stages at intermediate states) run them
through ``ctx.profile`` too, so every evaluation is counted.
"""

from __future__ import annotations

import time
from typing import Any


#: JIT seconds (engine/jit.py's warm-up) not yet reported by a profile.
#: Kept here, not in engine/jit.py, so that this module imports nothing of
#: the engine: jit -> collision -> profile is then no cycle
#: (tests/test_architecture.py).
_jit_pending = 0.0


def add_jit_seconds(s: float) -> None:
    """Record s seconds of compiling or loading kernels, reported by the
    next :class:`Profile`."""
    global _jit_pending
    _jit_pending += s


def take_jit_seconds() -> float:
    """JIT seconds not yet reported by a profile (then 0 until the next
    compile)."""
    global _jit_pending
    s, _jit_pending = _jit_pending, 0.0
    return s


class Stage:
    """Base class of pipeline stages.  ``name`` is what the profile reports;
    ``family`` is the stage family (forces, integrate, broadphase, narrowphase,
    solver, ccd, penalty, impact)."""

    name: str = "stage"
    family: str = ""

    def __call__(self, model, state, ctx) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"<stage {self.name}>"


class Profile:
    """Call counts and accumulated seconds per stage name."""

    def __init__(self, by_stage: bool = False) -> None:
        #: time every stage on its own: the step runs stage by stage, never
        #: as the fused steady step (engine/fused/steady.py, timed as one stage,
        #: ``steady_step``)
        self.by_stage = by_stage
        #: seconds the kernels took to compile or load at the build before
        #: this profile (engine/jit.py); never part of a stage's time
        self.jit_s = take_jit_seconds()
        self.calls: dict[str, int] = {}
        self.seconds: dict[str, float] = {}
        self.counters: dict[str, int] = {}

    def register(self, name: str) -> None:
        self.calls.setdefault(name, 0)
        self.seconds.setdefault(name, 0.0)

    def run(self, stage: Stage, model, state, ctx) -> None:
        t0 = time.perf_counter()
        stage(model, state, ctx)
        self.charge(stage.name, 1, time.perf_counter() - t0)

    def charge(self, name: str, calls: int, seconds: float) -> None:
        """Count ``calls`` calls of ``name`` taking ``seconds`` (s) in all
        (a stage's, or a fused call's: engine/fused/steady.py, engine/fused/loop.py)."""
        self.calls[name] = self.calls.get(name, 0) + calls
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds

    def count(self, key: str, k: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + k

    def as_dict(self) -> dict[str, Any]:
        """{stage: {"calls": int, "cpu_s": float}} plus ``counters`` and
        ``jit_s`` (float s, see engine/jit.py)."""
        out: dict[str, Any] = {k: {"calls": self.calls[k], "cpu_s": self.seconds[k]} for k in self.calls}
        out["jit_s"] = self.jit_s
        if self.counters:
            out["counters"] = dict(self.counters)
        return out
