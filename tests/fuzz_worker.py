"""The unit the engine-running fuzz properties (tests/test_fuzz.py) send to
a reused harness.execute.WorkerPool: a validated scene, cut to a few steps,
run on one engine.

It lives in its own small module so that pool workers import it (and
nothing of hypothesis or pytest) by reference, ``tests.fuzz_worker``.
Unlike harness.execute.execute_request it does not turn an exception of
the runner into a ``failed`` row: whatever harness.runner.run raises
propagates, comes back to the test as WorkerLost("raised") and is counted
as a crash, like a worker that dies (abort, segfault).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Any


def cut(scene: Any, steps: int) -> Any:
    """``scene`` ending after at most ``steps`` steps of its dt (s): the
    same bodies, effects and model, a shorter run."""
    return dataclasses.replace(scene, duration=min(scene.duration, steps * scene.dt))


#: engines this process has run (their first run loads compiled code)
_RAN: set[str] = set()


def run_cut(item: tuple[Any, str, int, float]) -> tuple[Any, dict[str, float]]:
    """``item`` = (scene, engine, steps, timeout_s): the RunResult of
    ``scene`` cut to ``steps`` steps on ``engine`` (trace dropped), and the
    seconds spent in this process: ``imports`` (the engine's adapter and
    modules, once per worker) and ``run`` (build, steps, metrics); ``first``
    is 1.0 on this process's first run of ``engine`` (it also loads the
    engine's compiled code, e.g. the reference engine's numba cache)."""
    import numpy as np

    scene, engine, steps, timeout_s = item
    t0 = time.perf_counter()
    from physbench.adapters import get_adapter
    from physbench.harness import runner

    get_adapter(engine).capabilities()
    t1 = time.perf_counter()
    # a blow-up is the result's status; numpy's overflow warnings on the way
    # there would only flood the worker's stderr
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        res = runner.run(cut(scene, steps), engine, timeout_s=timeout_s)
    t2 = time.perf_counter()
    res.trace = None
    res.contacts = None
    first = engine not in _RAN
    _RAN.add(engine)
    return res, {"imports": t1 - t0, "run": t2 - t1, "first": float(first)}
