"""The report's analyses: pure functions of the report's frame
(harness.report.rows.normalise), no I/O, no scene loading -- what the
page shows is what the rows recorded (asv's step_detect.py style).
Tests call them on synthetic frames.

Work-precision lines and frontiers, breaking points, the stability
matrix, step phases, the failing checks and each engine's latest
conformance run; the cost to reach a target,
the accuracy ladder and at a glance are in harness.report.cost, history
and regressions in harness.report.trends.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import pandas as pd

from physbench.contract.phase import wilson_interval
from physbench.harness.report.rows import (ERROR_FLOOR, as_float, fmt, is_finite, is_missing, json_list, normalised,
                                           settings_label, truthy)
from physbench.harness.status import (BAD_OUTCOMES, BROKEN_STATUSES, CHECK_ERROR, CHECK_UNSUPPORTED, DIVERGED, FAIL, OK,
                                     OUTCOMES, UNSUPPORTED, XFAIL)

#: the row's verdicts that mean "a check not met": an expected failure is
#: still a failure here (it says the engine is known not to hold the scene)
NOT_MET = (FAIL, XFAIL, CHECK_ERROR, CHECK_UNSUPPORTED)
#: the marks of :func:`phase_table`'s pattern
PHASE_PASS, PHASE_FAIL, PHASE_NOT_OK, PHASE_UNSUPPORTED, PHASE_NO_VERDICT = ".", "x", "!", "-", "?"


# ---------------------------------------------------------------------------
# selections


def sweep_points(df: pd.DataFrame) -> pd.DataFrame:
    """Sweep grid points (breaking-point rows, ``row_kind`` set, are read by
    :func:`breaking_points` only)."""
    if not len(df):
        return df
    return df[(df["source"] == "sweep") & df["row_kind"].map(is_missing)]


def limit_rows(df: pd.DataFrame, kind: str) -> pd.DataFrame:
    if not len(df):
        return df
    return df[df["row_kind"].map(lambda v: v == kind)]


def latest_points(df: pd.DataFrame) -> pd.DataFrame:
    """Each sweep point's latest row per machine (by sweep_id, which sorts
    by time)."""
    df = normalised(df)
    s = sweep_points(df)
    if s.empty:
        return s
    s = s.sort_values(["sweep_id", "timestamp"], kind="stable")
    return s.drop_duplicates(["machine_id", "point_key"], keep="last").reset_index(drop=True)


def unshifted(df: pd.DataFrame) -> pd.DataFrame:
    """Rows of the scene as written (phase 0): the other step phases of a
    point are draws of the same configuration, summarised by
    :func:`phase_table`, not extra points of a curve."""
    if df.empty or "phase" not in df.columns:
        return df
    return df[df["phase"] == 0.0]


def _latest_checks(df: pd.DataFrame) -> pd.DataFrame:
    c = unshifted(df[df["source"] == "check"]) if len(df) else df
    if c.empty:
        return c
    # a check run is the engine's defaults at the scene's dt (or the hard
    # dt): keyed by dt, so that settings added between commits do not count
    # the same run twice
    c = c.sort_values(["_file", "timestamp"], kind="stable").copy()
    c["_dtkey"] = [fmt(d, 9) for d in c["dt"]]
    c = c.drop_duplicates(["machine_id", "scenario", "variant", "engine", "_dtkey", "judge"], keep="last")
    return c.drop(columns="_dtkey").reset_index(drop=True)


def is_good(r: Mapping[str, Any]) -> bool:
    """ok and not known to be unstable."""
    return r["status"] == OK and r.get("stable_flag") is not False


def scene_targets(df: pd.DataFrame, target: float | None,
             targets: Mapping[Any, float] | float | None = None) -> dict[tuple[str, str], tuple[float | None, str]]:
    """(scenario, variant) -> (target, where it came from)."""
    out: dict[tuple[str, str], tuple[float | None, str]] = {}
    if df.empty:
        return out
    for (sc, va), g in df.groupby(["scenario", "variant"], sort=True):
        metric = next((m for m in g["primary_metric"] if m), None)
        given = _lookup_target(targets, sc, va)
        if given is not None:
            out[(sc, va)] = (given, "given")
            continue
        th = next((as_float(t) for t in g["primary_threshold"] if is_finite(t)), None)
        if th is not None:
            out[(sc, va)] = (th, "check max")
        elif target is not None:
            out[(sc, va)] = (float(target), "--target")
        else:
            out[(sc, va)] = (None, "none")
    return out


def _lookup_target(targets: Mapping[Any, float] | float | None, sc: str, va: str) -> float | None:
    if targets is None:
        return None
    if isinstance(targets, (int, float)):
        return float(targets)
    for k in ((sc, va), (sc, va or None), f"{sc}/{va}" if va else sc, sc):
        if k in targets and targets[k] is not None:
            return float(targets[k])
    return None


# ---------------------------------------------------------------------------
# work-precision


def line_settings(r: Mapping[str, Any]) -> tuple[dict[str, Any], str]:
    """A point's work-precision line within its engine: its swept settings
    but dt, and those as a hashable key (sorted JSON)."""
    nondt = {k: v for k, v in (r["swept"] or {}).items() if k != "dt"}
    return nondt, json.dumps(nondt, sort_keys=True, default=str)


def work_precision(df: pd.DataFrame, target: float | None = None,
                   targets: Mapping[Any, float] | float | None = None) -> dict[tuple[str, str], dict[str, Any]]:
    """Per (scenario, variant): lines of (cost, primary error) points along
    dt, one line per engine x non-dt swept settings (x machine when several).

    Returns ``{(scenario, variant): {"primary_metric", "threshold",
    "threshold_source", "clipped", "lines": [{"label", "engine", "settings",
    "machine_id", "points": [{"dt", "cost", "error", "error_plot", "status",
    "message", "ok", "incomplete"}...] (ascending dt)}...],
    "not_ok": [{"label", "dt", "cost", "status", "message"}...]}}``.
    A point is ``ok`` when its status is ok, it is not known unstable, and
    its error and cost are finite; ``error_plot`` is the error clipped to
    ERROR_FLOOR (``clipped`` says whether any was).
    """
    df = normalised(df)
    pts = unshifted(latest_points(df))
    out: dict[tuple[str, str], dict[str, Any]] = {}
    if pts.empty:
        return out
    many_machines = pts["machine_id"].nunique() > 1
    tg = scene_targets(pts, target, targets)
    for (sc, va), g in pts.groupby(["scenario", "variant"], sort=True):
        metric = next((m for m in g["primary_metric"] if m), None)
        th, src = tg.get((sc, va), (None, "none"))
        lines: dict[tuple, dict[str, Any]] = {}
        not_ok = []
        clipped = False
        for r in g.to_dict("records"):
            nondt, nondt_key = line_settings(r)
            label = " ".join(x for x in (r["engine"], settings_label(nondt)) if x)
            if many_machines:
                label += f" @{r['machine_id']}"
            key = (r["engine"], nondt_key, r["machine_id"])
            line = lines.setdefault(key, {"label": label, "engine": r["engine"], "settings": nondt,
                                          "machine_id": r["machine_id"], "points": []})
            err, cost = r["primary_error"], r["cost"]
            ok = is_good(r) and math.isfinite(err) and math.isfinite(cost)
            status = r["status"] if r["status"] != OK or r.get("stable_flag") is not False else "unstable"
            if r["status"] == OK and status == OK and not math.isfinite(err):
                status = "no error"
            plot = max(err, ERROR_FLOOR) if ok else math.nan
            if ok and err < ERROR_FLOOR:
                clipped = True
            p = {"dt": r["dt"], "cost": cost, "error": err, "error_plot": plot, "status": status,
                 "message": r["message"], "ok": ok, "incomplete": r["incomplete"]}
            line["points"].append(p)
            if not ok:
                not_ok.append({"label": label, "dt": r["dt"], "cost": cost, "status": status,
                               "message": r["message"]})
        for line in lines.values():
            line["points"].sort(key=lambda p: (math.inf if math.isnan(p["dt"]) else p["dt"]))
        ordered = sorted(lines.values(), key=lambda l: l["label"])
        not_ok.sort(key=lambda p: (p["label"], math.inf if math.isnan(p["dt"]) else p["dt"]))
        out[(sc, va)] = {"scenario": sc, "variant": va, "primary_metric": metric, "threshold": th,
                         "threshold_source": src, "clipped": clipped, "lines": ordered, "not_ok": not_ok}
    return out


def breaking_points(df: pd.DataFrame) -> pd.DataFrame:
    """The latest breaking-point search per (machine, scenario, variant,
    engine, parameter, range, overrides) from the stored ``limit`` rows
    (``physbench limits`` and ``[[limit]]`` blocks), with its evaluations'
    count."""
    df = normalised(df)
    res = limit_rows(df, "limit")
    cols = ["machine_id", "scenario", "variant", "engine", "limit_param", "limit_outcome", "limit_value",
            "limit_lo", "limit_hi", "limit_direction", "limit_failed_check", "limit_runs", "limit_cpu_s",
            "limit_id", "limit_range_lo", "limit_range_hi", "limit_phases", "limit_overrides", "suite", "sweep_id"]
    if res.empty:
        return pd.DataFrame(columns=cols)
    res = res.copy()
    for c in cols:
        if c not in res.columns:
            res[c] = None
    res = res.sort_values(["sweep_id", "timestamp"], kind="stable")
    res = res.drop_duplicates(["machine_id", "limit_id"], keep="last")
    return res[cols].sort_values(["scenario", "variant", "limit_param", "engine"], kind="stable").reset_index(drop=True)


def fmt_limit(r: Mapping[str, Any], short: bool = False) -> str:
    """A breaking point as text: ``<= 0.0072 [0.0072, 0.0076]``, ``holds to
    HI``, ``fails at LO``, ``unsupported``."""
    out = r.get("limit_outcome")
    if out == "found":
        sign = "\u2264" if r.get("limit_direction") == "below" else "\u2265"
        txt = f"{sign} {fmt(r['limit_value'])}"
        return txt if short else f"{txt} [{fmt(r['limit_lo'])}, {fmt(r['limit_hi'])}]"
    if out == "holds_throughout":
        return f"holds to {fmt(r['limit_value'])}" if short else \
            f"holds over [{fmt(r['limit_range_lo'])}, {fmt(r['limit_range_hi'])}]"
    if out == "fails_throughout":
        return f"fails at {fmt(r['limit_range_lo'])}" if short else \
            f"fails at both ends [{fmt(r['limit_range_lo'])}, {fmt(r['limit_range_hi'])}]"
    return str(out or "?")


# ---------------------------------------------------------------------------
# stability


def hard_scenarios(df: pd.DataFrame) -> set[str]:
    """Ids of the scenarios whose rows say they are tagged 'hard' (the
    ``tags`` the rows were written with; rows without tags say nothing)."""
    df = normalised(df)
    return {sc for sc, tags in zip(df["scenario"], df["tags"]) if tags and "hard" in tags}


def stability_matrix(df: pd.DataFrame, scenarios: Iterable[str] | None = None) -> pd.DataFrame:
    """Per (scenario, variant, engine) over the latest sweep points and the
    latest conformance rows: points, ok-and-stable count and fraction,
    unstable (ok but not stable), diverged, error (error/failed/timeout),
    unsupported, the largest dt at which the engine was ok and stable and the
    smallest dt at which it was not; of the ok-and-stable points, how many
    met every check by their recorded verdicts (``met_checks``), which
    checks failed, and how many have no verdict recorded (``no_verdict``:
    rows written before rows carried them, never re-judged).

    ``scenarios``: which scenarios to show; default the ones whose rows are
    tagged 'hard' (:func:`hard_scenarios`), else all.
    ``df.attrs['selection']`` says which.
    """
    df = normalised(df)
    cols = ["scenario", "variant", "engine", "points", "ok_stable", "fraction", "unstable", "diverged",
            "error", "unsupported", "other", "max_stable_dt", "min_unstable_dt", "met_checks", "checks_failed",
            "max_met_dt", "no_verdict"]
    checks = _latest_checks(df)
    checks = checks[checks["judge"] == ""] if len(checks) else checks  # ensembles, consensus: not a run's stability
    parts = [p for p in (unshifted(latest_points(df)), checks) if not p.empty]
    if not parts:
        out = pd.DataFrame(columns=cols)
        out.attrs["selection"] = "no data"
        return out
    data = pd.concat(parts, ignore_index=True, sort=False)
    if scenarios is None:
        hard = hard_scenarios(data)
        if hard:
            data = data[data["scenario"].isin(hard)]
            selection = "scenarios tagged 'hard'"
        else:
            selection = "all scenarios (none tagged 'hard' has data)"
    else:
        keep = set(scenarios)
        data = data[data["scenario"].isin(keep)]
        selection = "selected scenarios"
    rows = []
    for (sc, va, en), g in data.groupby(["scenario", "variant", "engine"], sort=True):
        recs = g.to_dict("records")
        good = [r for r in recs if is_good(r)]
        bad = [r for r in recs if not is_good(r) and r["status"] != UNSUPPORTED]
        st = [r["status"] for r in recs]
        gdt = [r["dt"] for r in good if math.isfinite(r["dt"])]
        bdt = [r["dt"] for r in bad if math.isfinite(r["dt"])]
        n = len(recs)
        rows.append({
            "scenario": sc, "variant": va, "engine": en, "points": n, "ok_stable": len(good),
            "fraction": len(good) / n if n else math.nan,
            "unstable": sum(1 for r in recs if r["status"] == OK and r.get("stable_flag") is False),
            "diverged": st.count(DIVERGED),
            "error": sum(st.count(s) for s in BROKEN_STATUSES),
            "unsupported": st.count(UNSUPPORTED),
            "other": sum(1 for s in st if s not in (OK, DIVERGED, UNSUPPORTED) + BROKEN_STATUSES),
            "max_stable_dt": max(gdt) if gdt else math.nan,
            "min_unstable_dt": min(bdt) if bdt else math.nan,
            "met_checks": sum(1 for r in good if meets_checks(r) is True),
            "checks_failed": sorted({m for r in good for m in (failed_checks(r) or [])}),
            "max_met_dt": max((r["dt"] for r in good if meets_checks(r) is True and math.isfinite(r["dt"])),
                              default=math.nan),
            "no_verdict": sum(1 for r in good if failed_checks(r) is None),
        })
    out = pd.DataFrame(rows, columns=cols)
    out.attrs["selection"] = selection
    return out


def row_verdicts(r: Mapping[str, Any]) -> list[dict] | None:
    """The verdicts a row was written with (its ``checks``), None when it
    carries none."""
    v = r.get("verdicts")
    if isinstance(v, list):
        return v
    if "verdicts" in r:  # normalised: None means not recorded
        return None

    return json_list(r.get("checks"))


def failed_checks(r: Mapping[str, Any]) -> list[str] | None:
    """The metrics of the row's recorded verdicts that were not met (FAIL,
    XFAIL, ERROR, UNSUPPORTED: an ``xfail`` does not make a check met);
    None when the row has no verdict recorded (it is not re-judged)."""
    stored = row_verdicts(r)
    if stored is None:
        return None
    return sorted({str(o.get("metric")) for o in stored if o.get("outcome") in NOT_MET})


def meets_checks(r: Mapping[str, Any]) -> bool | None:
    """Whether an ok row met every one of its checks (None: no verdict
    recorded)."""
    failed = failed_checks(r)
    if failed is None:
        return None
    return r["status"] == OK and not failed


# ---------------------------------------------------------------------------
# step phases


def _phase_outcome(r: Mapping[str, Any]) -> str:
    """'.' passed, 'x' a check of the primary metric failed (by the row's
    recorded verdicts), '!' the run was not ok or not stable, '-'
    unsupported, '?' no verdict recorded."""
    if r["status"] == UNSUPPORTED:
        return PHASE_UNSUPPORTED
    if not is_good(r):
        return PHASE_NOT_OK
    stored = row_verdicts(r)
    if stored is None:
        return PHASE_NO_VERDICT
    m = r.get("primary_metric")
    bad = any(o.get("metric") == m and o.get("outcome") in (FAIL, XFAIL, CHECK_ERROR) for o in stored)
    return PHASE_FAIL if bad else PHASE_PASS


def phase_table(df: pd.DataFrame) -> pd.DataFrame:
    """Points swept over step phases (a ``[[sweep]]`` with ``phases = N``):
    per configuration (machine, suite, scenario, variant, engine, settings
    without the phase), the N phases' outcomes -- failed = not ok, not
    stable, or the scenario's check of its primary metric not met -- as a
    failure fraction k / N with its 95 % Wilson interval, and the pattern
    over the phases in order (``.`` pass, ``x`` check failed, ``!`` not ok
    or unstable, ``?`` no verdict recorded: neither counted as a failure
    nor as a pass).  ``phase0`` is the outcome of the scene as written:
    what a single run (``physbench check``, a sweep without phases) sees."""
    df = normalised(df)
    cols = ["machine_id", "suite", "scenario", "variant", "engine", "settings", "dt", "phases", "failures",
            "fraction", "lo", "hi", "pattern", "phase0"]
    pts = latest_points(df)
    if pts.empty or not (pts["phase"] > 0).any():
        return pd.DataFrame(columns=cols)
    pts = pts.copy()
    pts["_base"] = [settings_label({k: v for k, v in (d or {}).items() if k not in ("phase", "dt")})
                    for d in pts["swept"]]
    rows = []
    pts["_dtkey"] = [fmt(d, 9) for d in pts["dt"]]
    for key, g in pts.groupby(["machine_id", "suite", "scenario", "variant", "engine", "_base", "_dtkey"],
                              sort=True):
        if not (g["phase"] > 0).any():
            continue
        # the phases of the latest sweep that ran them: a phase that sweep no
        # longer runs keeps an older row in latest_points, which must not mix in
        latest = max(g.loc[g["phase"] > 0, "sweep_id"])
        g = g[g["sweep_id"] == latest]
        mid, suite, sc, va, en, base, _ = key
        recs = sorted(g.to_dict("records"), key=lambda r: r["phase"])
        pattern = "".join(_phase_outcome(r) for r in recs)
        n = sum(1 for ch in pattern if ch not in (PHASE_UNSUPPORTED, PHASE_NO_VERDICT))
        k = sum(1 for ch in pattern if ch in (PHASE_FAIL, PHASE_NOT_OK))
        lo, hi = wilson_interval(k, n) if n else (math.nan, math.nan)
        rows.append({"machine_id": mid, "suite": suite, "scenario": sc, "variant": va, "engine": en,
                     "settings": base, "dt": recs[0]["dt"], "phases": len(recs), "failures": k,
                     "fraction": k / n if n else math.nan, "lo": lo, "hi": hi, "pattern": pattern,
                     "phase0": pattern[0] if recs[0]["phase"] == 0.0 else ""})
    out = pd.DataFrame(rows, columns=cols)
    return out.sort_values(["scenario", "variant", "engine", "settings", "dt"], ascending=[True, True, True, True, False],
                           kind="stable").reset_index(drop=True)



# ---------------------------------------------------------------------------
# failing checks


#: verdicts the failing-checks table lists: the bad ones (a check job's
#: exit 1) first, then the expected failures (``check --traces`` traces both)
LISTED_OUTCOMES = BAD_OUTCOMES + (XFAIL,)


_VERDICT_COLS = ["machine_id", "scenario", "variant", "engine", "dt", "metric", "outcome", "value", "threshold",
                 "reason", "trace", "check_file", "timestamp"]


def _verdict_table(c: pd.DataFrame, outcomes: Iterable[str]) -> tuple[pd.DataFrame, int]:
    """The verdicts of the check rows ``c`` whose recorded outcome is one of
    ``outcomes``, one row per (run, check), in ``outcomes``' order then by
    scenario, variant, engine and metric; and how many rows of ``c`` at
    phase 0 carry no verdict (left out, not re-judged).  Rows of the other
    step phases carry none of their own (a phased check's combined verdict
    is on phase 0)."""
    outcomes = tuple(outcomes)
    rows, no_verdict = [], 0
    for r in c.to_dict("records"):
        verdicts = row_verdicts(r)
        if verdicts is None:
            no_verdict += r.get("phase", 0.0) == 0.0
            continue
        for v in verdicts:
            if v.get("outcome") not in outcomes:
                continue
            rows.append({"machine_id": r["machine_id"], "scenario": r["scenario"], "variant": r["variant"],
                         "engine": r["engine"], "dt": r["dt"], "metric": str(v.get("metric", "")),
                         "outcome": v["outcome"], "value": v.get("value"), "threshold": str(v.get("threshold") or ""),
                         "reason": str(v.get("message") or ""), "trace": str(v.get("trace") or ""),
                         "check_file": str(r.get("_file") or ""), "timestamp": r["timestamp"]})
    out = pd.DataFrame(rows, columns=_VERDICT_COLS)
    if len(out):
        rank = {o: i for i, o in enumerate(outcomes)}
        out["_r"] = [rank[o] for o in out["outcome"]]
        out = out.sort_values(["_r", "scenario", "variant", "engine", "metric"], kind="stable")
        out = out.drop(columns="_r").reset_index(drop=True)
    return out, int(no_verdict)


def failing_checks(df: pd.DataFrame) -> pd.DataFrame:
    """The not-passing verdicts of the latest ``physbench check`` rows (per
    machine, scenario, variant, engine and dt; phase 0, which carries a
    phased check's combined verdict): one row per (run, check) whose
    recorded outcome is FAIL, XPASS, ERROR or XFAIL, with the value, the
    threshold and the reason as written, and the case's ``.rrd`` trace when
    ``check --traces`` wrote one ('' otherwise).  Bad outcomes first.
    ``attrs['no_verdict']``: check rows with no verdict recorded (left out,
    not re-judged)."""
    df = normalised(df)
    out, no_verdict = _verdict_table(_latest_checks(df), LISTED_OUTCOMES)
    out.attrs["no_verdict"] = no_verdict
    return out


# ---------------------------------------------------------------------------
# the latest conformance run per engine


CHECK_RUN_COLS = ["engine", "check_run", "check_file", "machine_id", "commit", "date", "rows", *OUTCOMES, "other",
                  "no_verdict", "passed"]


def _latest_files(c: pd.DataFrame) -> dict[str, str]:
    """engine -> the file of its latest ``physbench check`` run: the file
    holding the engine's latest row (timestamps are UTC ISO 8601 text, which
    sorts by time; the file name, ``<UTC stamp>-<commit>``, breaks ties)."""
    out = {}
    for en, g in c.groupby("engine", sort=True):
        last = g.groupby("_file")["timestamp"].max()
        out[en] = max(last.index, key=lambda f: (last[f], Path(f).name))
    return out


def latest_check_runs(df: pd.DataFrame) -> pd.DataFrame:
    """Per engine, its latest ``physbench check`` run (one check file is one
    run; :func:`_latest_files`): the run's name (``check_run``, the file's
    stem), the machine(s), commit(s) and date (the latest row's timestamp)
    of the engine's rows in it, how many rows, and the count of each
    recorded verdict outcome (PASS, FAIL, XFAIL, XPASS, UNSUPPORTED, ERROR;
    ``other``: an outcome outside that vocabulary), rows at phase 0
    without verdicts (``no_verdict``: written before rows carried them,
    never re-judged), and ``passed``: no FAIL, XPASS, ERROR or other
    outcome (None when no row carries a verdict).  Sorted by engine.
    Engines only: the engines' consensus (rows of engine ``consensus``,
    judge ``consensus``) is no engine and belongs to the judging section
    (:func:`consensus_table`; tests/test_report_rows.py::
    test_consensus_is_no_engine_at_a_glance)."""
    df = normalised(df)
    c = df[(df["source"] == "check") & (df["judge"] != "consensus")] if len(df) else df
    if c.empty:
        return pd.DataFrame(columns=CHECK_RUN_COLS)
    rows = []
    for en, f in _latest_files(c).items():
        g = c[(c["engine"] == en) & (c["_file"] == f)]
        counts = dict.fromkeys(OUTCOMES, 0)
        other = no_verdict = 0
        for r in g.to_dict("records"):
            verdicts = row_verdicts(r)
            if verdicts is None:
                no_verdict += r["phase"] == 0.0
                continue
            for v in verdicts:
                o = v.get("outcome")
                if o in counts:
                    counts[o] += 1
                else:
                    other += 1
        judged = sum(counts.values()) + other
        bad = sum(counts[o] for o in BAD_OUTCOMES) + other
        rows.append({"engine": en, "check_run": Path(f).stem, "check_file": f,
                     "machine_id": ", ".join(sorted(set(g["machine_id"]))),
                     "commit": ", ".join(sorted({x for x in g["commit"] if x})) or "-",
                     "date": max(g["timestamp"]) or "-", "rows": len(g), **counts, "other": other,
                     "no_verdict": int(no_verdict), "passed": (bad == 0) if judged else None})
    return pd.DataFrame(rows, columns=CHECK_RUN_COLS)


def unexpected_failures(df: pd.DataFrame, runs: pd.DataFrame | None = None) -> pd.DataFrame:
    """The FAIL, XPASS and ERROR verdicts of each engine's latest
    ``physbench check`` run (:func:`latest_check_runs`; ``runs``: that
    table when the caller has it), in that order, then by scenario,
    variant, engine and metric; the columns of :func:`failing_checks`.

    ``attrs['earlier']``: the bad verdicts of :func:`failing_checks` (the
    latest verdict per case and machine over every check file) that come
    from an earlier run of their engine and whose case (scenario, variant,
    dt) the engine's latest run did not repeat on any machine: a small
    check after a full one leaves them standing."""
    df = normalised(df)
    if runs is None:
        runs = latest_check_runs(df)
    empty = pd.DataFrame(columns=_VERDICT_COLS)
    if runs.empty:
        empty.attrs["earlier"] = empty.copy()
        return empty
    latest = dict(zip(runs["engine"], runs["check_file"]))
    c = df[(df["source"] == "check").to_numpy()
           & np.array([latest.get(e) == f for e, f in zip(df["engine"], df["_file"])], dtype=bool)]
    out, _ = _verdict_table(c, BAD_OUTCOMES)
    # a case the engine's latest run repeated (same scenario, variant, dt;
    # on any machine) is judged by that run
    repeated = {(r["scenario"], r["variant"], r["engine"], fmt(r["dt"], 9)) for r in c.to_dict("records")}
    fc = failing_checks(df)
    consensus = set(df.loc[df["judge"] == "consensus", "engine"]) if len(df) else set()
    keep = [r["engine"] not in consensus and latest.get(r["engine"]) != r["check_file"]
            and (r["scenario"], r["variant"], r["engine"], fmt(r["dt"], 9)) not in repeated
            for r in fc.to_dict("records")]
    earlier = fc[fc["outcome"].isin(BAD_OUTCOMES).to_numpy() & np.array(keep, dtype=bool)].reset_index(drop=True)
    out.attrs["earlier"] = earlier
    return out


# ---------------------------------------------------------------------------
# frontiers


def frontier(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The Pareto frontier of (cost, error) points: ascending cost, each
    point strictly more accurate than every cheaper one."""
    out: list[tuple[float, float]] = []
    for c, e in sorted(points):
        if not out or e < out[-1][1]:
            out.append((c, e))
    return out


# ---------------------------------------------------------------------------
# judging scenes without a model: contact laws, predictability, consensus

#: the contact-law residuals the report shows, with units (docs/METRICS.md)
LAW_COLUMNS = (("signorini_residual", "N m"), ("cone_violation", "1"), ("dissipation_residual", "rad"),
               ("adhesion", "N"), ("separation_force", "N"))


def contact_law_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per engine, over its latest check rows and latest sweep points (the
    scene as written) that carry contact-law residuals: the largest
    ``<law>_max`` of each law in LAW_COLUMNS (NaN where no row has one),
    the scenario it came from (``<law>_where``), and how many rows and
    scenarios carried any.  Rows of a run without forces carry NaN (the
    reason in their ``undefined_metrics``): they count as no value, never
    as 0.  Sorted by engine."""
    df = normalised(df)
    cols = ["engine", "rows", "scenarios"] + [f"{n}_{k}" for n, _ in LAW_COLUMNS for k in ("max", "where")]
    checks = _latest_checks(df)
    checks = checks[checks["judge"] == ""] if len(checks) else checks
    parts = [p for p in (unshifted(latest_points(df)), checks) if not p.empty]
    if not parts:
        return pd.DataFrame(columns=cols)
    data = pd.concat(parts, ignore_index=True, sort=False)
    present = [f"{n}_max" for n, _ in LAW_COLUMNS if f"{n}_max" in data.columns]
    if not present:
        return pd.DataFrame(columns=cols)
    rows = []
    for en, g in data.groupby("engine", sort=True):
        recs = [r for r in g.to_dict("records") if r["status"] == OK and any(is_finite(r.get(c)) for c in present)]
        if not recs:
            continue
        out: dict[str, Any] = {"engine": en, "rows": len(recs), "scenarios": len({r["scenario"] for r in recs})}
        for n, _ in LAW_COLUMNS:
            vals = [(as_float(r.get(f"{n}_max")), r["scenario"]) for r in recs if is_finite(r.get(f"{n}_max"))]
            best = max(vals, default=(math.nan, ""))
            out[f"{n}_max"], out[f"{n}_where"] = best
        rows.append(out)
    return pd.DataFrame(rows, columns=cols)


PREDICTABILITY_COLS = ["scenario", "variant", "engine", "members", "members_ok", "final_spread", "amplification",
                       "event_spread", "threshold", "predictable", "verdict"]


def predictability_table(df: pd.DataFrame) -> pd.DataFrame:
    """The latest ensemble row (``check --ensemble``, or a scene's
    ``predictable`` check) per machine, scenario, variant and engine, of
    the scenarios tagged 'hard' (else of all, ``attrs['selection']`` says
    which): members (ok of all), final spread (m), amplification, event
    spread, the threshold (m), predictable (True/False/None: a member not
    ok) and the recorded verdict of its ``predictable`` check ('' when it
    carries none)."""
    df = normalised(df)
    c = _latest_checks(df)
    c = c[c["judge"] == "ensemble"] if len(c) else c
    if c.empty:
        out = pd.DataFrame(columns=PREDICTABILITY_COLS)
        out.attrs["selection"] = "no data"
        return out
    hard = {sc for sc, tags in zip(c["scenario"], c["tags"]) if tags and "hard" in tags}
    if hard:
        c = c[c["scenario"].isin(hard)]
    rows = []
    for r in c.sort_values(["scenario", "variant", "engine"], kind="stable").to_dict("records"):
        verdict = next((v.get("outcome", "") for v in (row_verdicts(r) or []) if v.get("metric") == "predictable"), "")
        rows.append({"scenario": r["scenario"], "variant": r["variant"], "engine": r["engine"],
                     "members": as_float(r.get("members")), "members_ok": as_float(r.get("members_ok")),
                     "final_spread": as_float(r.get("final_spread")), "amplification": as_float(r.get("amplification")),
                     "event_spread": as_float(r.get("event_spread")), "threshold": as_float(r.get("ensemble_threshold")),
                     "predictable": truthy(r.get("predictable")) if r["status"] == OK else None, "verdict": verdict})
    out = pd.DataFrame(rows, columns=PREDICTABILITY_COLS)
    out.attrs["selection"] = "scenarios tagged 'hard'" if hard else "all scenarios (none tagged 'hard' has an ensemble)"
    return out


CONSENSUS_COLS = ["scenario", "variant", "engines", "status", "consensus_spread", "consensus_spread_angle",
                  "message", "verdicts"]


def consensus_table(df: pd.DataFrame) -> pd.DataFrame:
    """The latest consensus row (engine ``consensus``) per machine,
    scenario and variant: the engines and their versions, status, the
    spreads (m, rad), the row's message (the farthest pair) and its
    recorded verdicts ('metric OUTCOME; ...')."""
    df = normalised(df)
    c = _latest_checks(df)
    c = c[c["judge"] == "consensus"] if len(c) else c
    rows = []
    for r in c.sort_values(["scenario", "variant"], kind="stable").to_dict("records"):
        vs = row_verdicts(r) or []
        rows.append({"scenario": r["scenario"], "variant": r["variant"], "engines": r["engine_version"],
                     "status": r["status"], "consensus_spread": as_float(r.get("consensus_spread")),
                     "consensus_spread_angle": as_float(r.get("consensus_spread_angle")), "message": r["message"],
                     "verdicts": "; ".join(f"{v.get('metric')} {v.get('outcome')}" for v in vs)})
    return pd.DataFrame(rows, columns=CONSENSUS_COLS)
