"""The trace step after a conformance verdict: one diagnosing ``.rrd`` per
failing case.

A case is one run that decided a check: (scenario, variant, engine, the
run's setting overrides, its step phase).  :func:`write_case_trace` takes
(scene, results, outcomes) -- the run(s) with their traces and the verdicts
-- and writes ``<dir>/<case name>.rrd``; it does not care how or where the
runs were made, so it follows either execution path (in-process or worker
processes).  :func:`case_name` is the file name, stable and path-safe.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Sequence

from physbench.contract.scene import Scene
from physbench.harness.trace.writer import write_rrd

TRACED_OUTCOMES = ("FAIL", "XFAIL", "ERROR")


def case_name(scenario: str, variant: str | None, engine: str, settings: dict[str, Any] | None = None,
              phase: float = 0.0) -> str:
    """``<scenario>[<variant>]@k=v,..~phase=<f>--<engine>`` with every
    character outside [A-Za-z0-9._=,@~+-] replaced by '_'."""
    name = scenario + (f"[{variant}]" if variant else "")
    if settings:
        name += "@" + ",".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}"
                               for k, v in sorted(settings.items()))
    if phase:
        name += f"~phase={phase:.6g}"
    name += f"--{engine}"
    return re.sub(r"[^A-Za-z0-9._=,@~+\-\[\]]", "_", name).replace("[", "(").replace("]", ")")


def write_case_trace(out_dir: str | Path, scene: Scene, results: Sequence, outcomes: Sequence, *,
                     name: str | None = None, checks: dict | None = None) -> Path:
    """Write the diagnosing trace of one case: ``results`` (RunResults with
    traces; engine contacts where recorded) of ``scene`` with the case's
    ``outcomes``.  Returns the path written."""
    results = list(results)
    if name is None:
        r = results[0]
        name = case_name(scene.id, scene.variant, r.engine)
    path = Path(out_dir) / f"{name}.rrd"
    if checks is None:
        checks = {c.metric: c for c in scene.checks}
    write_rrd(path, scene, results, diagnose=True, outcomes=outcomes, checks=checks)
    return path
