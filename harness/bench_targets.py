"""``physbench bench targets``: the cost-to-target table's ratios timed
again side by side.

The report's cost-to-target table (harness/report/cost.py) reads each
engine's cheapest point that reaches a scenario's target from a sweep
whose runs competed for the cores with each other (``--jobs``) and were
timed minutes apart.  Its ratios move by more than a 10-20 % change of an
engine.  This benchmark takes the table's points from a sweep's results
and times them again in this one process: per scenario, the reference
engine's point and the cheapest other engine's point, each built and run
afresh as the sweep runs it (harness.runner.run, no metrics), one untimed
run each first (imports, compiled-kernel loads), then ``repeats`` timed
runs each in alternating order (A B, B A, ...), so a change of the
machine's load falls on both.  The ratio is the reference's median CPU
per simulated second over the other's; its spread the least and the
greatest ratio of one repeat's pair.

The selection is the table's (:func:`harness.report.cost.cost_to_target`,
which the command line computes from the results: the report layer sits
above this one), never re-decided here; what is timed is its
``point_settings``.  Tests:
tests/test_bench_targets.py.
"""

from __future__ import annotations

import json
import math
import statistics
from typing import Any, Callable

import pandas as pd

from physbench.harness import runner
from physbench.harness import status as st
from physbench.harness.execute import request_scene
from physbench.harness.points import Point, cached_scene

#: the engine whose ratio the table is read for
REFERENCE = "reference"


def pairs(table: pd.DataFrame, reference: str = REFERENCE) -> list[dict[str, Any]]:
    """Per (scenario, variant) of the cost-to-target ``table`` where
    ``reference`` reached the target: its point and the cheapest point of
    another engine that reached it (None where none did), as dicts
    (scenario, variant, engine, point_settings, cost, ratio); in the
    table's order."""
    out = []
    ok = table[table["reached"].astype(bool)]
    for (sc, va), g in ok.groupby(["scenario", "variant"], sort=False, dropna=False):
        ref = g[g["engine"] == reference]
        if ref.empty:
            continue
        others = g[g["engine"] != reference].sort_values("cost", kind="stable")
        rec = lambda r: {k: r[k] for k in ("scenario", "variant", "engine", "point_settings", "cost", "ratio", "dt")}
        out.append({"reference": rec(ref.iloc[0]), "other": rec(others.iloc[0]) if not others.empty else None})
    return out


def _variant(point: dict[str, Any]) -> str | None:
    """A :func:`pairs` record's variant (None: the scene as written)."""
    v = point["variant"]
    return v if isinstance(v, str) and v else None


def timed_run(point: dict[str, Any]) -> float:
    """CPU seconds per simulated second of one fresh run of ``point`` (a
    :func:`pairs` record): the sweep's request for it
    (harness.points.Point.request: engine settings, phase, budget), no
    metrics; NaN when the run does not end ``ok``."""
    swept = json.loads(point["point_settings"]) if point["point_settings"] else {}
    req = Point(point["scenario"], _variant(point), point["engine"], tuple(sorted(swept.items()))).request()
    scene = request_scene(req, base=cached_scene(req.scenario, req.variant))
    res = runner.run(scene, req.engine, dict(req.settings), timeout_s=req.timeout_s, compute_metrics=False,
                     model_metrics=False)
    return float(res.metrics.get("cpu_s_per_sim_s", math.nan)) if res.status == st.OK else math.nan


#: a row's timing columns where nothing was timed
_UNTIMED = {"reference_ms_per_sim_s": math.nan, "other_ms_per_sim_s": math.nan, "ratio": math.nan,
            "ratio_lo": math.nan, "ratio_hi": math.nan}


def side_by_side(pair: dict[str, Any], repeats: int, run: Callable[[dict[str, Any]], float] = timed_run
                 ) -> dict[str, Any]:
    """One row: ``pair``'s two points timed ``repeats`` times each,
    alternating which goes first, after one untimed run of each (module
    doc).  ``run`` times one run (CPU s per simulated second)."""
    ref, oth = pair["reference"], pair["other"]
    row: dict[str, Any] = {
        "scenario": ref["scenario"] + (f"[{_variant(ref)}]" if _variant(ref) else ""),
        "reference_settings": ref["point_settings"],
        "other": oth["engine"] if oth else None,
        "other_settings": oth["point_settings"] if oth else None,
        "table_ratio": float(ref["ratio"]),
    }
    if oth is None:
        return {**row, **_UNTIMED, "note": "no other engine reached the target"}
    run(ref), run(oth)  # untimed: imports, compiled-kernel loads, first-use caches
    a: list[float] = []
    b: list[float] = []
    for i in range(repeats):
        order = ((ref, a), (oth, b)) if i % 2 == 0 else ((oth, b), (ref, a))
        for p, into in order:
            into.append(run(p))
    good = [(x, y) for x, y in zip(a, b) if math.isfinite(x) and math.isfinite(y) and y > 0]
    note = "" if len(good) == repeats else f"{repeats - len(good)} of {repeats} repeats did not end ok: left out"
    if not good:
        return {**row, **_UNTIMED, "note": note}
    ma = statistics.median(x for x, _ in good)
    mb = statistics.median(y for _, y in good)
    per = [x / y for x, y in good]
    return {**row, "reference_ms_per_sim_s": 1e3 * ma, "other_ms_per_sim_s": 1e3 * mb, "ratio": ma / mb,
            "ratio_lo": min(per), "ratio_hi": max(per), "note": note}


def targets(table: pd.DataFrame, repeats: int = 5, scenarios: list[str] | None = None,
            run: Callable[[dict[str, Any]], float] = timed_run) -> list[dict[str, Any]]:
    """The rows of ``physbench bench targets``: each scenario's pair
    (:func:`pairs`) of the cost-to-target ``table``
    (harness.report.cost.cost_to_target of a sweep's rows; the command
    line reads them) timed side by side (:func:`side_by_side`); only
    ``scenarios`` (ids) when given.  Raises ValueError when the table is
    empty or has no scenario where the reference reached its target."""
    if table.empty:
        raise ValueError("no sweep point with a target in the results directory: run `physbench sweep` first")
    todo = pairs(table)
    if scenarios:
        todo = [p for p in todo if p["reference"]["scenario"] in set(scenarios)]
    if not todo:
        raise ValueError("no scenario where the reference engine reached its target"
                         + (f" among {', '.join(scenarios)}" if scenarios else ""))
    return [side_by_side(p, repeats, run) for p in todo]
