"""The report's first screen and ``summary.json``: pure functions of the
report's frame (harness.report.rows.normalise), no I/O.

The first screen answers three questions, whatever rows exist:

- did the latest conformance run pass? each engine's latest ``physbench
  check`` run with its verdict counts, commit, machine and date
  (harness.report.analysis.latest_check_runs);
- what failed unexpectedly? the FAIL, XPASS and ERROR verdicts of those
  runs (harness.report.analysis.unexpected_failures), and how many bad
  verdicts of earlier runs still stand;
- what does accuracy cost? the accuracy ladder per scenario family
  (harness.report.cost.at_a_glance) and the breaking points.

:func:`first_screen` computes it once; the page draws it
(harness.report.page) and :func:`summary` gives the same numbers as plain
JSON data, written beside ``report.html`` as ``summary.json`` (its format:
docs/REPORT.md, "summary.json").
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

import numpy as np
import pandas as pd

from physbench.harness.report.analysis import breaking_points, latest_check_runs, sweep_points, unexpected_failures
from physbench.harness.report.cost import at_a_glance, ladder
from physbench.harness.report.rows import is_missing, normalised
from physbench.harness.status import OUTCOMES, XFAIL

#: summary.json's format version (docs/REPORT.md): bumped when a key
#: changes meaning or goes away
SUMMARY_VERSION = 1


def first_screen(df: pd.DataFrame, lad: pd.DataFrame | None = None) -> dict[str, Any]:
    """The first screen's data: ``runs`` (:func:`latest_check_runs`),
    ``unexpected`` (:func:`unexpected_failures` of those runs), ``earlier``
    (bad verdicts of earlier runs still standing), ``ladder``
    (:func:`ladder`), ``glance`` (the ladder per family,
    :func:`at_a_glance`), ``breaking_points``, ``rows`` (how
    many check and sweep rows were read).  ``lad``: :func:`ladder` of
    ``df`` when the caller has it already."""
    df = normalised(df)
    runs = latest_check_runs(df)
    unexpected = unexpected_failures(df, runs)
    if lad is None:
        lad = ladder(df)
    n_check = int((df["source"] == "check").sum()) if len(df) else 0
    return {"runs": runs, "unexpected": unexpected, "earlier": unexpected.attrs["earlier"],
            "ladder": lad, "glance": at_a_glance(df, lad=lad), "breaking_points": breaking_points(df),
            "rows": {"check": n_check, "sweep": len(sweep_points(df))}}


def _plain(v: Any) -> Any:
    """A value as JSON data: numpy scalars to Python, NaN and missing to
    None (JSON has no NaN), containers element by element."""
    if isinstance(v, Mapping):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return [_plain(x) for x in v.tolist()]
    if is_missing(v):
        return None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    return v if isinstance(v, (int, str)) else str(v)


def _verdicts(t: pd.DataFrame) -> list[dict[str, Any]]:
    return [{"engine": r["engine"], "scenario": r["scenario"], "variant": r["variant"] or None, "dt": r["dt"],
             "metric": r["metric"], "outcome": r["outcome"], "value": r["value"], "threshold": r["threshold"],
             "reason": r["reason"], "trace": r["trace"] or None, "machine": r["machine_id"],
             "check_run": _stem(r["check_file"]), "timestamp": r["timestamp"] or None}
            for r in t.to_dict("records")]


def _stem(path: str) -> str:
    name = str(path).replace("\\", "/").rsplit("/", 1)[-1]
    return name[:-len(".parquet")] if name.endswith(".parquet") else name


def left_out(notes: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The data notes (harness.report.loading) that left rows out of the page."""
    return [n for n in notes if n.get("left_out")]


def summary(first: Mapping[str, Any], *, generated: str, physbench_commit: str, report: str = "report.html",
            notes: Iterable[Mapping[str, Any]] = ()) -> dict[str, Any]:
    """The first screen's numbers (:func:`first_screen`) as JSON data, for
    a CI system to post (keys: docs/REPORT.md, "summary.json")."""
    runs = first["runs"]
    engines = []
    for r in runs.to_dict("records"):
        engines.append({"engine": r["engine"], "passed": r["passed"], "check_run": r["check_run"],
                        "commit": r["commit"], "machine": r["machine_id"], "date": r["date"], "rows": r["rows"],
                        "counts": {o: r[o] for o in OUTCOMES}, "other": r["other"], "no_verdict": r["no_verdict"]})
    totals = {o: int(runs[o].sum()) for o in OUTCOMES} if len(runs) else {o: 0 for o in OUTCOMES}
    verdict = None if runs.empty or all(e["passed"] is None for e in engines) else \
        all(e["passed"] is not False for e in engines)
    ladder_rows = [{"family": r["family"], "rung": r["rung"], "cheapest": dict(r["wins"]), "reached": r["reached"],
                    "scenarios": r["scenarios"]} for r in first["glance"].to_dict("records")]
    bp = [{"scenario": r["scenario"], "variant": r["variant"] or None, "engine": r["engine"],
           "parameter": r["limit_param"], "outcome": r["limit_outcome"], "limit": r["limit_value"],
           "bracket": [r["limit_lo"], r["limit_hi"]], "direction": r["limit_direction"],
           "failed_check": r["limit_failed_check"] or None, "machine": r["machine_id"]}
          for r in first["breaking_points"].to_dict("records")]
    notes = list(notes)
    out = {
        "summary_version": SUMMARY_VERSION,
        "generated": generated,
        "physbench_commit": physbench_commit,
        "report": report,
        "rows": dict(first["rows"]),
        "conformance": {"passed": verdict, "engines": engines, "totals": totals},
        "unexpected": _verdicts(first["unexpected"]),
        "unexpected_earlier": _verdicts(first["earlier"]),
        "ladder": ladder_rows,
        "breaking_points": bp,
        "left_out": [n["text"] for n in left_out(notes)],
        "data_notes": len(notes),
    }
    return _plain(out)


def xfail_total(first: Mapping[str, Any]) -> int:
    """XFAIL verdicts in the engines' latest runs."""
    runs = first["runs"]
    return int(runs[XFAIL].sum()) if len(runs) else 0
