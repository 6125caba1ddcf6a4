"""Consensus across engines: how far apart the engines' own converged
answers are (Erez, Tassa and Todorov 2015).

Each engine runs the scene at its finest self-consistency step, dt/k^2
(k: the scene's ``self_consistency`` ``refine`` param, default 2), as items
on the executors like any other run (harness.execute.RunRequest with the
trace kept, recorded at the scene's own frame times).  ``consensus_spread``
is the largest distance between two engines' runs (the self-consistency
distance, harness/references/self_consistency.py: RMS over shared frames
and bodies for ``trajectory``, the largest at the end for
``final_state``), beside the distance of every pair.  When the engines
each converge (their self-consistency errors are small) and the spread is
large, they converge to different answers.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

from physbench.harness import status as st


def spread(traces: dict[str, Any], dt: float, compare: str = "trajectory",
           bodies: Any = None) -> dict[str, Any]:
    """``consensus_spread`` (m): the largest position distance between two
    of ``traces`` ({engine: Trace}), ``consensus_spread_angle`` (rad) the
    largest rotation distance, and ``pairs`` [{a, b, distance, angle,
    frames}] for every pair (frames shared to within dt).  NaN spreads
    with fewer than two traces."""
    from physbench.harness.references.self_consistency import distances

    pairs = []
    for a, b in itertools.combinations(sorted(traces), 2):
        dx, da, n = distances(traces[a], traces[b], dt, compare, bodies)
        pairs.append({"a": a, "b": b, "distance": dx, "angle": da, "frames": n})
    ok = [p for p in pairs if p["frames"] > 0]
    return {
        "consensus_spread": max((p["distance"] for p in ok), default=math.nan),
        "consensus_spread_angle": max((p["angle"] for p in ok), default=math.nan),
        "pairs": pairs,
    }


def run_consensus(scenario: str, engines: list[str], *, variant: str | None = None, jobs: int = 1,
                  executor: str = "process", timeout_s: float | None = 600.0) -> dict[str, Any]:
    """Run ``scenario`` (an id or spec file) on each engine at dt/k^2,
    recording every k^2 steps (the scene's frame times), and return
    :func:`spread` of the ``ok`` runs plus ``dt_fine``, ``compare`` and
    ``runs`` {engine: (status, message)}.  k and the compared quantity
    come from the scene's ``self_consistency`` params (k = 2 and
    ``trajectory`` for a scene with another model)."""
    from physbench.contract.scene import load_scene
    from physbench.harness.execute import RunRequest, run_requests
    from physbench.harness.executors import make_executor

    scene = load_scene(scenario, variant)
    params = scene.reference_params if scene.reference_model == "self_consistency" else {}
    k = int(params.get("refine", 2))
    compare = params.get("compare", "trajectory")
    h = scene.dt / k ** 2
    reqs = [RunRequest(scenario, e, variant, {"dt": h}, timeout_s=timeout_s, record_every=k * k,
                       compute_metrics=False, keep_trace=True) for e in engines]
    traces: dict[str, Any] = {}
    runs: dict[str, tuple[str, str]] = {}
    with make_executor(executor, max(1, int(jobs))) as ex:
        for req, res in run_requests(reqs, ex):
            runs[req.engine] = (res.status, res.message)
            if res.status == st.OK and res.trace is not None:
                traces[req.engine] = res.trace.valid()
    bodies = None
    names = params.get("bodies")
    if names is not None:
        import numpy as np

        bodies = np.array([scene.body_index(n) for n in names], int)
    out = spread(traces, scene.dt, compare, bodies)
    out.update(scenario=scene.id, dt_fine=h, compare=compare, runs=runs)
    return out


def consensus_result(scenario: str, variant: str | None, engines: list[str], timeout_s: float | None = 600.0):
    """The consensus of ``engines`` on ``scenario`` as one
    harness.runner.RunResult (a check row of engine ``consensus``):
    ``unsupported`` when no engine could run the scene, else ``ok`` with
    ``consensus_spread`` and ``consensus_spread_angle`` as metrics
    (undefined, with the reason, when fewer than two engines ran ok: a
    check on them is then an ERROR), each engine's version in
    ``engine_version`` and its run's status, every pair's distance,
    ``dt_fine`` and ``compare`` in ``info``.  The engines' runs are made
    one after the other in this process (a check runs this in a worker;
    each run has ``timeout_s``)."""
    import time

    from physbench.adapters import get_adapter
    from physbench.contract.scene import load_scene
    from physbench.harness.references import undefined
    from physbench.harness.runner import RunResult, commit_id

    t0 = time.perf_counter()
    scene = load_scene(scenario, variant)
    versions = []
    for e in engines:
        try:
            versions.append(f"{e} {get_adapter(e).capabilities().version}")
        except Exception:
            versions.append(e)
    res = RunResult(scenario=scene.id, variant=variant, engine="consensus", engine_version=", ".join(versions),
                    status=st.OK, message="", settings={}, commit=commit_id(), scene_hash=scene.content_hash,
                    scene_path=scene.source)
    out = run_consensus(scenario, engines, variant=variant, executor="inline", timeout_s=timeout_s)
    res.info.update(runs={e: list(v) for e, v in out["runs"].items()}, pairs=out["pairs"], dt_fine=out["dt_fine"],
                    compare=out["compare"])
    ok = [e for e, (s, _) in out["runs"].items() if s == st.OK]
    if all(s == st.UNSUPPORTED for s, _ in out["runs"].values()):
        res.status = st.UNSUPPORTED
        res.message = "; ".join(f"{e}: {m}" for e, (_, m) in out["runs"].items())
        return res
    if len(ok) < 2:
        why = (f"fewer than two engines ran ok at dt = {out['dt_fine']:.6g} s ("
               + ", ".join(f"{e} {s}" for e, (s, _) in out["runs"].items()) + ")")
        undefined(res.metrics, "consensus_spread", why)
        undefined(res.metrics, "consensus_spread_angle", why)
        res.message = why
    else:
        res.metrics["consensus_spread"] = out["consensus_spread"]
        res.metrics["consensus_spread_angle"] = out["consensus_spread_angle"]
        worst = max((p for p in out["pairs"] if p["frames"] > 0), key=lambda p: p["distance"])
        res.message = (f"{len(ok)} engines at dt = {out['dt_fine']:.6g} s; farthest apart: {worst['a']} - "
                       f"{worst['b']} {worst['distance']:.4g} m")
    res.timing["step_wall_s"] = time.perf_counter() - t0
    return res
