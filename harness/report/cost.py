"""Cost to reach an accuracy: per scenario and engine the cheapest swept
point whose primary error meets a target, where the sweep's grid bounds
that cost, the accuracy ladder and the at-a-glance table over it.  Pure
functions of the report's frame (harness.report.rows.normalise), no I/O;
tests call them on synthetic frames (tests/test_report.py).
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

import pandas as pd

from physbench.harness.report.analysis import is_good, latest_points, line_settings, scene_targets, unshifted
from physbench.harness.report.rows import fmt, is_finite, normalised, settings_label

#: :func:`cost_to_target`'s ``ratio_bound``: what the ratio to the cheapest
#: engine is, given which of the two costs are upper bounds
RATIO_EXACT, RATIO_AT_MOST, RATIO_AT_LEAST, RATIO_OPEN = "=", "\u2264", "\u2265", "?"
#: keyed by (this engine's cost is a bound, the cheapest engine's is)
_RATIO_BOUND = {(False, False): RATIO_EXACT, (True, False): RATIO_AT_MOST, (False, True): RATIO_AT_LEAST,
                (True, True): RATIO_OPEN}


def _lines(recs: list[Mapping[str, Any]]) -> list[tuple[str, list[Mapping[str, Any]]]]:
    """One engine's points of one scenario as its lines (points sharing
    every swept setting but dt): ``[(line label, points by ascending dt)...]``
    in line-key order; points without a finite dt are left out."""
    lines: dict[str, tuple[str, list[Mapping[str, Any]]]] = {}
    for r in recs:
        if math.isfinite(r["dt"]):
            nondt, key = line_settings(r)
            lines.setdefault(key, (settings_label(nondt), []))[1].append(r)
    return [(lines[k][0], sorted(lines[k][1], key=lambda r: r["dt"])) for k in sorted(lines)]


def _reaches(r: Mapping[str, Any], target: float) -> bool:
    return is_good(r) and math.isfinite(r["primary_error"]) and r["primary_error"] <= target


def _ends(lines: list[tuple[str, list[Mapping[str, Any]]]], target: float) -> dict[str, Any]:
    """:func:`grid_ends` on lines from :func:`_lines`."""
    coarse, fine = [], []
    for label, pts in lines:
        if _reaches(pts[-1], target):
            costs = [r["cost"] for r in pts if _reaches(r, target) and math.isfinite(r["cost"])]
            coarse.append((label, pts[-1]["dt"], min(costs) if costs else math.nan))
            continue
        good = [r for r in pts if is_good(r) and math.isfinite(r["primary_error"])]
        if good and not any(r["primary_error"] <= target for r in good):
            best = min(good, key=lambda r: (r["primary_error"], r["dt"]))
            if best["dt"] == pts[0]["dt"]:
                fine.append((label, best["dt"]))
    return {"coarse": coarse, "fine": fine}


def grid_ends(recs: list[Mapping[str, Any]], target: float) -> dict[str, Any]:
    """Where one engine's swept points leave its cost to reach ``target``
    unbracketed by the grid.

    ``recs``: the engine's points of one scenario (any settings); a line is
    the points sharing every swept setting but dt.  A line is *open at the
    coarse end* when the point at its coarsest swept dt is ok and its
    primary error <= ``target``: coarser steps were not measured, and would
    reach the target at a lower cost as far as the grid says, so the line's
    cost to reach it is an upper bound.  A line is *open at the fine end*
    when its best ok error (> ``target``) is at its finest swept dt: finer
    steps were not measured.  A coarsest point that is not ok (diverged,
    unstable, refused) or misses the target closes the coarse end.

    Returns ``{"coarse": [(line label, coarsest dt, cost)...], "fine":
    [(line label, dt)...]}`` in line order; ``cost`` is the line's cheapest
    CPU s per simulated s reaching the target (NaN when no reaching point's
    cost is known).
    """
    return _ends(_lines(recs), target)


def _ends_text(ends: list[tuple[Any, ...]]) -> str:
    by: dict[str, list[str]] = {}
    for label, dt, *_ in ends:
        by.setdefault(fmt(dt), []).append(label or "defaults")
    return "; ".join(f"dt={dt} ({', '.join(ls)})" for dt, ls in by.items())


_COLS = ["scenario", "variant", "engine", "primary_metric", "target", "target_source", "reached",
         "settings", "point_settings", "dt", "cost", "step_us", "error", "ratio", "best_error",
         "best_error_settings", "points", "cost_bound", "open_cost", "coarse_open", "fine_open", "ratio_bound", "note"]


def _engine_points(df: pd.DataFrame) -> tuple[pd.DataFrame, list[tuple[tuple[str, str, str], list[dict], list]]]:
    """The selection and grouping every target shares: the latest unshifted
    points, and per (scenario, variant, engine) their records and lines
    (:func:`_lines`).  :func:`ladder` does this once for all its rungs
    (tests/test_report.py::test_ladder_selects_and_groups_the_points_once)."""
    pts = unshifted(latest_points(normalised(df)))
    if pts.empty:
        return pts, []
    groups = []
    for key, g in pts.groupby(["scenario", "variant", "engine"], sort=True):
        recs = g.to_dict("records")
        groups.append((key, recs, _lines(recs)))
    return pts, groups


def _reached_row(row: dict[str, Any], under: list[Mapping[str, Any]], ends: dict[str, Any]) -> None:
    """Fill ``row`` with the cheapest reaching point and what the grid says
    of it: the cost is an upper bound (``cost_bound``) when the cheapest
    line open at the coarse end (``open_cost``) is no dearer than it (or
    its cost is unknown): that line reaches the target at its coarsest dt
    swept, and coarser steps may reach it for less.  A dearer open line
    leaves the cost exact within the grid and is named in the note."""
    best = min(under, key=lambda r: (r["cost"], r["primary_error"]))
    row.update(reached=True, settings=settings_label(best["swept"]), point_settings=best.get("point_settings", ""),
               dt=best["dt"], cost=best["cost"],
               step_us=best["cost"] * best["dt"] * 1e6, error=best["primary_error"], best_error=math.nan,
               best_error_settings="")
    if not ends["coarse"]:
        return
    known = [c for *_, c in ends["coarse"] if math.isfinite(c)]
    row["open_cost"] = min(known) if known else math.nan
    bounding = [e for e in ends["coarse"] if not (e[2] > best["cost"])]
    if bounding:
        row["cost_bound"] = True
        row["note"] = (f"upper bound: the cheapest line reaching the target does so at its coarsest dt swept, "
                       f"{_ends_text(bounding)}; coarser steps not measured, may reach it for less")
    else:
        dearer = "; ".join(f"{label or 'defaults'} at dt={fmt(dt)} for {fmt(c)}" for label, dt, c in ends["coarse"])
        row["note"] = (f"exact within the grid; dearer lines reach the target at their coarsest dt swept "
                       f"({dearer}): coarser steps on them not measured")


def _cost_rows(groups: list[tuple[tuple[str, str, str], list[dict], list]],
               tg: Mapping[tuple[str, str], tuple[float | None, str]]) -> pd.DataFrame:
    """:func:`cost_to_target`'s table from :func:`_engine_points`' groups
    and the targets ``(scenario, variant) -> (target, source)``."""
    rows = []
    for (sc, va, en), recs, lines in groups:
        t, src = tg.get((sc, va), (None, "none"))
        if t is None:
            continue
        good = [r for r in recs if is_good(r) and math.isfinite(r["primary_error"])]
        under = [r for r in good if r["primary_error"] <= t and math.isfinite(r["cost"])]
        metric = next((r["primary_metric"] for r in recs if r["primary_metric"]), None)
        ends = _ends(lines, t)
        row = {"scenario": sc, "variant": va, "engine": en, "primary_metric": metric, "target": t,
               "target_source": src, "points": len(recs), "ratio": math.nan, "note": "",
               "cost_bound": False, "open_cost": math.nan, "coarse_open": _ends_text(ends["coarse"]),
               "fine_open": "", "ratio_bound": ""}
        if under:
            _reached_row(row, under, ends)
        else:
            row.update(reached=False, settings="", point_settings="", dt=math.nan, cost=math.nan, step_us=math.nan,
                       error=math.nan)
            row["fine_open"] = _ends_text(ends["fine"])
            if good:
                b = min(good, key=lambda r: r["primary_error"])
                row.update(best_error=b["primary_error"], best_error_settings=settings_label(b["swept"]))
                row["note"] = "not reached within the grid" + (
                    f"; best error at the finest dt swept, {row['fine_open']}: finer steps not measured"
                    if ends["fine"] else "")
            else:
                row.update(best_error=math.nan, best_error_settings="")
                row["note"] = "no ok point"
        rows.append(row)
    out = pd.DataFrame(rows, columns=_COLS)
    if out.empty:
        return out
    for (sc, va), g in out.groupby(["scenario", "variant"]):
        reached = g[g["reached"].astype(bool)]
        if len(reached):
            cheapest = reached["cost"].min()
            if cheapest > 0:
                out.loc[reached.index, "ratio"] = reached["cost"] / cheapest
                first = reached.sort_values(["cost", "engine"], kind="stable").index[0]
                cb = bool(out.at[first, "cost_bound"])
                for i in reached.index:
                    out.at[i, "ratio_bound"] = (RATIO_EXACT if i == first else
                                                _RATIO_BOUND[bool(out.at[i, "cost_bound"]), cb])
    return out.sort_values(["scenario", "variant", "reached", "cost", "engine"],
                           ascending=[True, True, False, True, True], kind="stable").reset_index(drop=True)


def cost_to_target(df: pd.DataFrame, targets: Mapping[Any, float] | float | None = None,
                   target: float | None = None) -> pd.DataFrame:
    """Per (scenario, variant, engine): the cheapest point (latest sweep)
    whose primary error <= the target, its cost and the ratio to the
    cheapest engine that reached it; ``reached`` False with the best error
    achieved otherwise.

    ``targets``: a number for every scenario, or a mapping keyed by
    (scenario, variant) / 'scenario/variant' / scenario; where it gives none,
    the scenario's ``[[check]] max`` for its primary metric, else ``target``.
    Rows without any target are left out.

    The grid bounds what the table can say (:func:`grid_ends`):
    ``coarse_open`` names the engine's lines that reach the target at their
    coarsest swept dt (coarser steps not measured) and ``open_cost`` is the
    cheapest cost among them.  ``cost_bound`` is True when that is the
    engine's cheapest cost (``open_cost`` == ``cost``): the cheapest line
    reaching the target is open at the coarse end, and the cost is an upper
    bound ("at most").  A dearer open line leaves ``cost`` exact within the
    grid; the note names it and its cost.  ``fine_open`` names, for an
    engine that never reaches the target, the lines whose best error is at
    their finest swept dt (finer steps not measured).  ``ratio_bound``:
    ``=`` both costs exact, ``\u2264`` this engine's cost is a bound and
    the cheapest's is not, ``\u2265`` the reverse, ``?`` both are bounds
    (the ratio is neither); the cheapest engine's own ratio is 1 (``=``).
    ``note`` says it in words.  ``point_settings``: the reached point's
    settings as its row stores them (JSON: what ``physbench bench
    targets`` runs again).  ``step_us``: the reached point's CPU
    microseconds per step (cost x dt x 1e6): where two engines reach the
    target at the same dt, their ratio is the ratio of these.
    """
    pts, groups = _engine_points(df)
    if pts.empty:
        return pd.DataFrame(columns=_COLS)
    return _cost_rows(groups, scene_targets(pts, target, targets))


#: accuracies of the primary metric the report asks every engine for
LADDER = (1e-2, 1e-4, 1e-6, 1e-9)


def ladder(df: pd.DataFrame, rungs: Iterable[float] = LADDER) -> pd.DataFrame:
    """:func:`cost_to_target` at every rung of the accuracy ladder: per
    (scenario, variant, engine, rung) the cheapest configuration reaching
    the rung, or (``reached`` False) the best error reached and where.
    Column ``rung`` holds the target.  The points are selected and grouped
    once for all rungs (:func:`_engine_points`)."""
    pts, groups = _engine_points(df)
    parts = []
    if not pts.empty:
        scen = sorted({(sc, va) for (sc, va, _), _, _ in groups})
        for t in rungs:
            ct = _cost_rows(groups, {k: (float(t), "given") for k in scen})
            if not ct.empty:
                parts.append(ct.assign(rung=float(t)))
    if not parts:
        return pd.DataFrame(columns=["scenario", "variant", "engine", "rung", "reached", "cost", "settings"])
    return pd.concat(parts, ignore_index=True)


def family(scenario: str) -> str:
    return scenario.split(".", 1)[0]


def at_a_glance(df: pd.DataFrame, rungs: Iterable[float] = LADDER, lad: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per scenario family and ladder rung: which engine is cheapest to
    reach the rung, counted over the family's scenarios (``wins``: engine ->
    scenarios where it is cheapest), how many scenarios some engine reached
    it in, out of how many.  ``lad``: :func:`ladder` of ``df`` at ``rungs``
    when the caller has it already (the page renders both)."""
    if lad is None:
        lad = ladder(df, rungs)
    rows = []
    if lad.empty:
        return pd.DataFrame(columns=["family", "rung", "wins", "reached", "scenarios"])
    lad = lad.assign(family=[family(x) for x in lad["scenario"]])
    for (fam, rung), g in lad.groupby(["family", "rung"], sort=True):
        wins: dict[str, int] = {}
        reached = 0
        scen = 0
        for _, h in g.groupby(["scenario", "variant"], sort=True):
            scen += 1
            r = h[h["reached"].astype(bool) & h["cost"].map(is_finite)]
            if len(r):
                reached += 1
                best = r.sort_values(["cost", "engine"], kind="stable").iloc[0]["engine"]
                wins[best] = wins.get(best, 0) + 1
        rows.append({"family": fam, "rung": rung, "wins": dict(sorted(wins.items(), key=lambda kv: -kv[1])),
                     "reached": reached, "scenarios": scen})
    return pd.DataFrame(rows).sort_values(["family", "rung"], ascending=[True, False]).reset_index(drop=True)
