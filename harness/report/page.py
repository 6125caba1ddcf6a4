"""The report's HTML: one self-contained page (no external assets, no
JavaScript: plots are base64 ``data:`` PNGs, styles inline) from the
report's frame, its analyses and its figures.  Every cell's text is
escaped.  Order: one line naming what was left out (only when rows were),
At a glance (harness.report.glance.first_screen), the sections, Data (what
reading the rows found), footer.  Every table sits in its own box that
scrolls sideways when the table is wider than the column, so the page never
does (tests/test_report_browser.py measures it at 1280, 1400 and 1600 px)."""

from __future__ import annotations

import datetime as _dt
import html
import math
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import pandas as pd

from physbench.harness.report.analysis import (LAW_COLUMNS, breaking_points, consensus_table, contact_law_table,
                                               failing_checks, fmt_limit, limit_rows, phase_table, predictability_table,
                                               stability_matrix, sweep_points, work_precision)
from physbench.harness.report.glance import first_screen, left_out, xfail_total
from physbench.harness.report.cost import RATIO_AT_LEAST, RATIO_AT_MOST, RATIO_EXACT, cost_to_target
from physbench.harness.report.trends import (BASELINE_RUNS, DRIFT_HORIZON, ERROR_ABS_FLOOR, MACHINE_SHIFT_MIN_SERIES,
                                    MAD_TO_SIGMA, MIN_COST_HISTORY, NOISE_FLOOR, NOISE_SPREADS, history,
                                    machine_shifts, regressions, scene_change_lines, scene_changes)
from physbench.harness.report.plots import (engine_colour, plot_breaking_point, plot_contact_laws, plot_history,
                                          plot_work_precision)
from physbench.harness.report.rows import ERROR_FLOOR, fmt, is_finite, is_missing, normalised, settings_label
from physbench.contract.conventions import DRAG_EXTERNAL
from physbench.harness.runner import commit_id
from physbench.harness.status import BAD_OUTCOMES, OK, OUTCOMES, XFAIL

MAX_SMALL_MULTIPLES = 6
#: unexpected failures listed on the first screen, at most (all of them in
#: Failing checks and summary.json)
GLANCE_MAX_UNEXPECTED = 20

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1200px;
color:#222;padding:0 1em;line-height:1.4;overflow-wrap:break-word}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:2em}
h3{font-size:1.05em;margin-bottom:.3em}h4{font-size:.95em;margin:.6em 0 .2em}
.scroll{overflow-x:auto;max-width:100%}
table{border-collapse:collapse;margin:.5em 0 1em;font-size:.85em}
th,td{border:1px solid #ccc;padding:.25em .5em;text-align:left;vertical-align:top}
th{background:#f0f0f0}td.num{text-align:right;font-variant-numeric:tabular-nums}
.warn{background:#fff4d6;border:1px solid #e0b000;padding:.5em 1em;margin:1em 0}
.leftout{background:#fff4d6;border-left:4px solid #e0b000;padding:.3em .8em;margin:.8em 0}
.note{color:#555;font-size:.85em}.bad{color:#b00020;font-weight:600}.good{color:#087a2a;font-weight:600}
.incomplete{background:#ffe8c2}.wp{display:inline-block;vertical-align:top;margin:0 1em 1.5em 0;max-width:100%}
.wp img,.hist img{max-width:100%}figure.hist{margin:1em 0}figcaption{font-size:.8em;color:#444}
.cell{font-size:.8em;white-space:nowrap;min-width:13em}.cell .wrap{white-space:normal;overflow-wrap:anywhere}footer{margin-top:3em;color:#666;font-size:.8em;border-top:1px solid #ccc}
details{margin:.5em 0}summary{cursor:pointer}details details{margin-left:1em}
code{background:#f4f4f4;padding:0 .2em}
"""


def _e(v: Any) -> str:
    return html.escape("" if v is None else str(v), quote=True)


def _img(b64: str, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{b64}">'


def _table(header: list[str], rows: list[list[str]], raw: bool = False, row_class: list[str] | None = None,
           row_attr: list[str] | None = None) -> str:
    """rows' cells are escaped unless ``raw`` (then they are HTML already);
    ``row_attr``: raw attribute text per row (``data-outcome='FAIL'``).  The
    table sits in its own box that scrolls sideways when the table is wider
    than the page (the page itself never does: test_report_browser)."""
    h = "".join(f"<th>{_e(c)}</th>" for c in header)
    body = []
    for i, r in enumerate(rows):
        cls = f' class="{row_class[i]}"' if row_class and row_class[i] else ""
        attr = f" {row_attr[i]}" if row_attr and row_attr[i] else ""
        cells = "".join(f"<td>{c if raw else _e(c)}</td>" for c in r)
        body.append(f"<tr{cls}{attr}>{cells}</tr>")
    return f"<div class='scroll'><table><thead><tr>{h}</tr></thead><tbody>{''.join(body)}</tbody></table></div>"


def _date(ts: Iterable[str]) -> str:
    ts = sorted(t for t in ts if t)
    if not ts:
        return "-"
    return ts[0] if ts[0] == ts[-1] else f"{ts[0]} .. {ts[-1]}"


def _external_drag_html(df: pd.DataFrame) -> str:
    """The engines and scenarios whose drag was physbench's force law applied
    as an external force, not the engine's own drag model (rows whose notes
    carry :data:`contract.conventions.DRAG_EXTERNAL`); '' when none
    (tests/test_report.py::test_report_marks_drag_applied_by_physbench)."""
    if "notes" not in df.columns:
        return ""
    marked = df[df["notes"].map(lambda v: isinstance(v, str) and DRAG_EXTERNAL in v)]
    if marked.empty:
        return ""
    rows = [[en, ", ".join(sorted(set(g["scenario"])))] for en, g in marked.groupby("engine", sort=True)]
    return ("<h3>Drag applied by physbench</h3><p class='note'>On these rows the engine has no drag model for the "
            f"scene, so the drag is physbench's own force law ({_e(DRAG_EXTERNAL)}): they measure physbench's force "
            "code on that engine, not the engine's drag.</p>" + _table(["engine", "scenarios"], rows))


def _header_html(df: pd.DataFrame) -> str:
    out = []
    machines = []
    for mid, g in df.groupby("machine_id", sort=True):
        last = g.iloc[-1]
        info = ", ".join(f"{k}: {last[c]}" for k, c in (("cpu", "machine.cpu"),
                                                         ("family/model", "machine.cpu_family_model"),
                                                         ("flags", "machine.cpu_flags"), ("cores", "machine.cores"),
                                                         ("BLAS", "machine.blas"), ("numpy", "machine.numpy"),
                                                         ("scipy", "machine.scipy"), ("env", "machine.env_id"),
                                                         ("platform", "machine.platform"),
                                                         ("python", "machine.python"))
                         if c in g.columns and not is_missing(last[c]))
        machines.append([mid, info, str(len(g))])
    out.append("<h3>Machines</h3>" + _table(["machine", "info", "rows"], machines))
    sweeps = []
    classes = []
    s = sweep_points(df)
    if not s.empty:
        for (mid, suite, sid), g in s.groupby(["machine_id", "suite", "sweep_id"], sort=True):
            counts = g["status"].value_counts()
            inc = bool(g["incomplete"].any())
            sweeps.append([mid, suite, sid, _date(g["timestamp"]),
                           ", ".join(sorted({c for c in g["commit"] if c})) or "-", str(len(g)),
                           ", ".join(f"{k} {v}" for k, v in counts.items()),
                           "incomplete (parts only)" if inc else "complete"])
            classes.append("incomplete" if inc else "")
        out.append("<h3>Sweeps</h3>" + _table(["machine", "suite", "sweep id", "dates", "commits", "rows",
                                               "statuses", "state"], sweeps, row_class=classes))
    c = df[df["source"] == "check"]
    if not c.empty:
        checks = []
        for (mid, f), g in c.groupby(["machine_id", "_file"], sort=True):
            checks.append([mid, Path(f).name, _date(g["timestamp"]),
                           ", ".join(sorted({x for x in g["commit"] if x})) or "-", str(len(g))])
        out.append("<h3>Conformance runs (physbench check)</h3>"
                   + _table(["machine", "file", "dates", "commits", "rows"], checks))
    ev = []
    for en, g in df.groupby("engine", sort=True):
        ev.append([en, ", ".join(sorted({v for v in g["engine_version"] if v})) or "-"])
    out.append("<h3>Engines</h3>" + _table(["engine", "versions"], ev))
    out.append(_external_drag_html(df))
    commits = sorted({x for x in df["commit"] if x})
    suites = sorted({x for x in s["suite"] if x}) if not s.empty else []
    out.insert(0, f'<p>Suites: <b>{_e(", ".join(suites) or "-")}</b>. Commits covered: '
                  f'{_e(", ".join(commits) or "-")}. Rows: {len(df)} ({len(s)} from sweeps, {len(c)} from '
                  f"conformance runs). Dates: {_e(_date(df['timestamp']))}.</p>")
    return "\n".join(out)


def _wp_html(wps: dict[tuple[str, str], dict[str, Any]]) -> str:
    if not wps:
        return '<p class="note">No sweep rows: nothing to draw.</p>'
    parts = ['<p class="note">x: CPU seconds per simulated second (log); y: the scenario\'s primary error '
             "(log); one line per engine and non-dt setting combination, points along dt (labelled). Latest "
             "sweep of each point on each machine. Dashed: the target (the scenario's <code>[[check]] max</code> "
             "for its primary metric, else <code>--target</code>). Red x on the top edge: runs that were not ok "
             "(diverged, error, unstable ...), placed at their cost.</p>"]
    for (sc, va), wp in wps.items():
        b64 = plot_work_precision(wp)
        title = sc + (f" / {va}" if va else "")
        cap = [f"<b>{_e(title)}</b>: primary metric <code>{_e(wp['primary_metric'] or '?')}</code>"]
        if wp["threshold"] is not None:
            cap.append(f"target {_e(fmt(wp['threshold']))} ({_e(wp['threshold_source'])})")
        else:
            cap.append("no target (no check max; pass --target)")
        if wp["clipped"]:
            cap.append(f"errors below {ERROR_FLOOR:g} (exact results, error 0) are drawn at {ERROR_FLOOR:g}")
        if any(p["incomplete"] for l in wp["lines"] for p in l["points"]):
            cap.append("includes points of an incomplete sweep")
        body = _img(b64, f"work-precision {title}") if b64 else '<p class="note">no drawable point</p>'
        lst = ""
        if wp["not_ok"]:
            items = "".join(f"<li>{_e(p['label'])} dt={_e(fmt(p['dt']))}: <span class='bad'>{_e(p['status'])}"
                            f"</span>{(' - ' + _e(p['message'][:200])) if p['message'] else ''}"
                            f"{'' if math.isfinite(p['cost']) else ' (cost unknown)'}</li>"
                            for p in wp["not_ok"])
            lst = f"<details><summary>{len(wp['not_ok'])} point(s) not ok</summary><ul class='note'>{items}</ul></details>"
        parts.append(f'<figure class="wp">{body}<figcaption>{"; ".join(cap)}.</figcaption>{lst}</figure>')
    return "\n".join(parts)


def _cost_text(r: Mapping[str, Any]) -> str:
    """A reached cost: ``<= c`` when coarser steps were not measured."""
    return ("\u2264 " if r["cost_bound"] else "") + fmt(r["cost"])


def _ratio_text(r: Mapping[str, Any], digits: int = 3) -> str:
    """The ratio to the cheapest engine with what bounds it: ``<=`` (this
    engine's cost is an upper bound), ``>=`` (the cheapest's is), ``~ ... ?``
    (both are: the ratio is neither bound)."""
    if r["ratio"] == 1:
        return "1"
    x = fmt(r["ratio"], digits) + "x"
    mark = r.get("ratio_bound") or RATIO_EXACT
    return {RATIO_EXACT: x, RATIO_AT_MOST: "\u2264 " + x, RATIO_AT_LEAST: "\u2265 " + x}.get(mark, f"~{x} (?)")


def _best_text(r: Mapping[str, Any], prefix: str) -> str:
    """An unreached target: the best error and its settings, else the note."""
    if not is_finite(r["best_error"]):
        return r["note"] or "no ok point"
    return f"{prefix} {fmt(r['best_error'])}" + (f" at {r['best_error_settings']}" if r["best_error_settings"] else "")


def _cost_html(ct: pd.DataFrame) -> str:
    if ct.empty:
        return ('<p class="note">No scenario with a target: give the scenario a <code>[[check]] max</code> for '
                "its primary metric or pass <code>--target</code>.</p>")
    rows = []
    for r in ct.to_dict("records"):
        scen = _e(r["scenario"]) + (f" / {_e(r['variant'])}" if r["variant"] else "")
        tgt = f"{_e(r['primary_metric'] or '?')} &le; {_e(fmt(r['target']))} <span class='note'>({_e(r['target_source'])})</span>"
        if r["reached"]:
            cfg = _e(r["settings"] or f"dt={fmt(r['dt'])}")
            if r["coarse_open"]:
                cfg += f"<br><span class='note'>{_e(r['note'])}</span>"
            rows.append([scen, _e(r["engine"]), tgt, cfg, _e(fmt(r["error"])), _e(_cost_text(r)),
                         _e(fmt(r["step_us"])), _e(_ratio_text(r))])
        else:
            best = _best_text(r, "best error")
            where = ("<br><span class='note'>at the finest dt swept: finer steps not measured</span>"
                     if r["fine_open"] else "")
            rows.append([scen, _e(r["engine"]), tgt, "<span class='bad'>not reached within the grid</span>",
                         _e(best) + where, "-", "-", "-"])
    return ('<p class="note">The cheapest configuration (latest sweep) whose primary error is at most the '
            "target, its cost and its cost relative to the cheapest engine that reaches the target. "
            "&le; marks an upper bound on the engine's cost: its cheapest line reaching the target (named) "
            "does so at the coarsest dt the sweep offers, so coarser steps, not measured, may reach it for "
            "less; a dearer line open at the coarse end is named with its cost, and leaves the cost exact "
            "within the grid; a ratio with "
            "&le; is an upper bound, &ge; a lower bound (the cheapest engine's cost is the bound), "
            "~ (?) neither (both costs are bounds). Where two engines reach the target at the same dt, their "
            "ratio is that of their CPU &micro;s per step.</p>"
            + _table(["scenario", "engine", "target", "cheapest configuration", "error", "CPU s / sim s",
                      "CPU \u00b5s / step", "vs cheapest"], rows, raw=True))


def _rung(t: float) -> str:
    return f"{t:.0e}".replace("e-0", "e-")


def _ladder_html(lad: pd.DataFrame) -> str:
    if lad.empty:
        return ""
    rungs = sorted(set(lad["rung"]), reverse=True)
    rows = []
    for (sc, va, en), g in lad.groupby(["scenario", "variant", "engine"], sort=True):
        by = {r["rung"]: r for r in g.to_dict("records")}
        cells = [_e(sc) + (f" / {_e(va)}" if va else ""), f"<span style='color:{engine_colour(en)}'>"
                 f"<b>{_e(en)}</b></span>", _e(next((m for m in g["primary_metric"] if m), "?"))]
        for t in rungs:
            r = by.get(t)
            if r is None:
                cells.append("-")
            elif r["reached"]:
                ratio = "" if not is_finite(r["ratio"]) or r["ratio"] == 1 else f" ({_ratio_text(r, 2)})"
                best = " <span class='good'>cheapest</span>" if r["ratio"] == 1 else ""
                tip = f" title='{_e(r['note'])}'" if r["coarse_open"] else ""
                cells.append(f"<span{tip}>{_e(_cost_text(r))}{_e(ratio)}</span>{best}<br><span class='note'>"
                             f"{_e(r['settings'])}</span>")
            else:
                where = _best_text(r, "best")
                cells.append(f"<span class='bad'>not reached</span><br><span class='note'>{_e(where)}</span>")
        rows.append(cells)
    return ("<h3>Accuracy ladder</h3><p class='note'>Per engine, the CPU s per simulated s of its cheapest "
            "configuration (latest sweep) whose primary error is at most each rung, the factor over the cheapest "
            "engine and the configuration (&le;: an upper bound, the cheapest line reaching the rung does so at its "
            "coarsest dt swept; the tooltip names the lines open at the coarse end); where it is "
            "not reached, the best error the engine reached and with which settings.</p>"
            + _table(["scenario", "engine", "metric"] + [f"\u2264 {_rung(t)}" for t in rungs], rows, raw=True))


def _case(r: Mapping[str, Any]) -> str:
    """A check case as HTML: scenario / variant, dt."""
    case = _e(r["scenario"]) + (f" / {_e(r['variant'])}" if r["variant"] else "")
    if is_finite(r["dt"]):
        case += f" <span class='note'>dt={_e(fmt(r['dt']))}</span>"
    return case


def _engine(en: str) -> str:
    return f"<span style='color:{engine_colour(en)}'><b>{_e(en)}</b></span>"


def _runs_html(runs: pd.DataFrame) -> str:
    """Did the latest conformance run pass? One row per engine."""
    extra = [k for k in ("other", "no_verdict") if len(runs) and runs[k].sum()]
    rows, attrs = [], []
    for r in runs.to_dict("records"):
        if r["passed"] is None:
            verdict = "<span class='note'>no verdict recorded</span>"
        elif r["passed"]:
            verdict = "<span class='good'>passed</span>"
        else:
            verdict = "<span class='bad'>failed</span>"
        counts = []
        for o in OUTCOMES:
            n = int(r[o])
            cls = "bad" if n and o in BAD_OUTCOMES else ("note" if not n else "")
            counts.append(f"<span class='{cls}'>{n}</span>" if cls else str(n))
        rows.append([_engine(r["engine"]), verdict] + counts + [str(int(r[k])) for k in extra]
                    + [_e(r["commit"]), _e(r["machine_id"]), _e(r["date"]), f"<code>{_e(r['check_run'])}</code>"])
        attrs.append(f"data-engine='{_e(r['engine'])}'")
    several = runs["check_run"].nunique() > 1
    names = {"other": "other", "no_verdict": "no verdict"}
    failed = [r["engine"] for r in runs.to_dict("records") if r["passed"] is False]
    unknown = [r["engine"] for r in runs.to_dict("records") if r["passed"] is None]
    if failed:
        answer = (f"<p class='bad'>No: the latest run of {len(failed)} of {len(runs)} engine(s) "
                  f"({_e(', '.join(failed))}) has unexpected failures.</p>")
    elif unknown:
        answer = (f"<p class='note'>No verdict recorded for {_e(', '.join(unknown))}; the other engines' latest "
                  "runs passed.</p>")
    else:
        answer = f"<p class='good'>Yes: the latest run of every engine ({len(runs)}) passed.</p>"
    return (answer + "<p class='note'>Each engine's latest <code>physbench check</code> run (one check file is one run"
            + ("; the engines' latest runs differ" if several else "") + "): the verdicts it recorded, one per "
            "check and case. It passed when none is FAIL, XPASS or ERROR; an XFAIL is a known limitation "
            "(listed, folded, under <a href='#failing-checks'>Failing checks</a>).</p>"
            + _table(["engine", "verdict"] + list(OUTCOMES) + [names[k] for k in extra]
                     + ["commit", "machine", "date", "check run"], rows, raw=True, row_attr=attrs))


def _value_vs(r: Mapping[str, Any]) -> str:
    th = r["threshold"]
    return _e(fmt(r["value"], 4)) + (f" <span class='note'>vs {_e(th)}</span>" if th else "")


def _unexpected_html(first: Mapping[str, Any], page_dir: Path | None) -> str:
    """What failed unexpectedly? The FAIL, XPASS and ERROR verdicts of the
    engines' latest runs, at most GLANCE_MAX_UNEXPECTED of them."""
    un, earlier = first["unexpected"], first["earlier"]
    n_x = xfail_total(first)
    parts = []
    if un.empty:
        parts.append("<p class='good'>No unexpected failure: every verdict of the latest runs is PASS, XFAIL or "
                     "UNSUPPORTED.</p>")
    else:
        rows, attrs = [], []
        for r in un.head(GLANCE_MAX_UNEXPECTED).to_dict("records"):
            rows.append([f"<span class='bad'>{_e(r['outcome'])}</span>", _engine(r["engine"]), _case(r),
                         f"<code>{_e(r['metric'])}</code>", _value_vs(r), _e(r["reason"][:200]),
                         _trace_link(r["trace"], page_dir)])
            attrs.append(f"data-outcome='{_e(r['outcome'])}'")
        more = len(un) - len(rows)
        parts.append(f"<p class='bad'>{len(un)} unexpected failure(s) (FAIL, XPASS, ERROR) in the latest runs"
                     + (f"; the first {len(rows)} here, all under <a href='#failing-checks'>Failing checks</a>"
                        if more else "") + ".</p>"
                     + _table(["outcome", "engine", "case", "metric", "value vs threshold", "reason", "trace"],
                              rows, raw=True, row_attr=attrs))
    if len(earlier):
        per = ", ".join(f"{en} {n}" for en, n in earlier["engine"].value_counts().sort_index().items())
        parts.append(f"<p class='note'>Still standing from earlier check runs, whose cases the latest runs did not "
                     f"repeat: {len(earlier)} unexpected failure(s) ({_e(per)}), listed under "
                     "<a href='#failing-checks'>Failing checks</a>.</p>")
    if n_x:
        parts.append(f"<p class='note'>{n_x} known failure(s) (XFAIL) in the latest runs, folded under "
                     "<a href='#failing-checks'>Failing checks</a> with their measured figures.</p>")
    return "\n".join(parts)


def _glance_html(first: Mapping[str, Any], page_dir: Path | None = None) -> str:
    """The first screen: three questions, answered from whatever rows exist
    (harness.report.glance.first_screen)."""
    runs = first["runs"]
    parts = ["<h3>Did the latest conformance run pass?</h3>"]
    if runs.empty:
        parts.append("<p class='note'>No <code>physbench check</code> rows stored: run <code>physbench check</code> "
                     "to answer this and the next question.</p>")
    else:
        parts.append(_runs_html(runs))
        parts.append("<h3>What failed unexpectedly?</h3>")
        parts.append(_unexpected_html(first, page_dir))
    parts.append("<h3>What does accuracy cost?</h3>")
    parts.append(_accuracy_html(first["glance"], first["breaking_points"]))
    return "\n".join(parts)


def _accuracy_html(ag: pd.DataFrame, bp: pd.DataFrame) -> str:
    """What accuracy costs: the ladder per scenario family and the breaking
    points (harness.report.glance.first_screen's ``glance`` and
    ``breaking_points``)."""
    parts = []
    if ag.empty:
        parts.append("<p class='note'>No sweep rows with a primary error: no accuracy ladder "
                     "(<code>physbench sweep</code> fills it in).</p>")
    else:
        rungs = sorted(set(ag["rung"]), reverse=True)
        rows = []
        for fam, g in ag.groupby("family", sort=True):
            by = {r["rung"]: r for r in g.to_dict("records")}
            cells = [f"<b>{_e(fam)}</b>"]
            for t in rungs:
                r = by.get(t)
                if r is None or not r["reached"]:
                    n = r["scenarios"] if r is not None else 0
                    cells.append(f"<span class='bad'>none</span> <span class='note'>(0/{n})</span>")
                    continue
                w = ", ".join(f"<span style='color:{engine_colour(e)}'><b>{_e(e)}</b></span>"
                              + (f" {k}" if len(r["wins"]) > 1 or k > 1 else "") for e, k in r["wins"].items())
                cells.append(f"{w} <span class='note'>({r['reached']}/{r['scenarios']})</span>")
            rows.append(cells)
        parts.append("<p class='note'>Cheapest engine to reach each accuracy of the primary metric, per scenario "
                     "family (how many of the family's scenarios it is cheapest in; in brackets, in how many "
                     "scenarios any engine reached the accuracy). Details: <a href='#cost-to-target'>accuracy "
                     "ladder</a>.</p>"
                     + _table(["family"] + [f"\u2264 {_rung(t)}" for t in rungs], rows, raw=True))
    if bp.empty:
        parts.append("<p class='note'>No breaking-point searches stored (<code>physbench limits</code> or a "
                     "suite's <code>[[limit]]</code> blocks).</p>")
    else:
        engines = sorted(set(bp["engine"]))
        rows = []
        for (sc, va, par), g in bp.groupby(["scenario", "variant", "limit_param"], sort=True):
            rows.append([_e(sc) + (f" / {_e(va)}" if va else ""), f"<code>{_e(par)}</code>"]
                        + _engine_cells(g, engines, lambda r: _e(fmt_limit(r, short=True))))
        parts.append("<p class='note'>Breaking points: the last value of the parameter at which the scene still "
                     "met its checks and stayed stable (\u2264: holds below; \u2265: holds above). Brackets and "
                     "the check that failed: <a href='#breaking-points'>Breaking points</a>.</p>"
                     + _table(["scenario", "parameter"] + [f"{e}" for e in engines], rows, raw=True))
    return "\n".join(parts)


def _breaking_html(df: pd.DataFrame) -> str:
    bp = breaking_points(df)
    if bp.empty:
        return ("<p class='note'>No breaking-point searches stored. <code>physbench limits SCENARIO --engine E "
                "--param KEY --range LO HI</code> or a suite's <code>[[limit]]</code> block fills this in.</p>")
    evals = limit_rows(df, "limit_eval")
    parts = ["<p class='note'>Each search walks the parameter from the end where the scene holds (met every "
             "check, stayed stable, in every step phase) towards the other in steps of at most a factor 2, then "
             "bisects the first failing step to the search's tolerance. Limit: the last value that held; "
             "bracket: it and the nearest value that failed; the check that failed there.</p>"]
    for (sc, va, par), g in bp.groupby(["scenario", "variant", "limit_param"], sort=True):
        rows = []
        for r in g.to_dict("records"):
            rows.append([f"<span style='color:{engine_colour(r['engine'])}'><b>{_e(r['engine'])}</b></span>",
                         _e(fmt_limit(r)), _e(r["limit_failed_check"] or "-")[:300],
                         _e(fmt(r["limit_runs"])), _e(fmt(r["limit_cpu_s"])),
                         _e(f"[{fmt(r['limit_range_lo'])}, {fmt(r['limit_range_hi'])}], {fmt(r['limit_phases'])} "
                            "phase(s)")])
        ids = set(g["limit_id"])
        ev = evals[evals["limit_id"].isin(ids)] if len(evals) and "limit_id" in evals.columns else evals
        metric = next((m for m in ev["primary_metric"] if m), None) if len(ev) else None
        b64 = plot_breaking_point(ev, g, par, metric) if len(ev) else None
        title = sc + (f" / {va}" if va else "")
        over = next((o for o in g["limit_overrides"] if o and o != "{}"), None)
        parts.append(f"<h3>{_e(title)}: <code>{_e(par)}</code></h3>"
                     + (f"<p class='note'>with {_e(over)}</p>" if over else "")
                     + _table(["engine", "limit [bracket]", "failed just past it", "runs", "CPU s", "range"],
                              rows, raw=True)
                     + (f"<figure class='wp'>{_img(b64, f'breaking point {title} {par}')}<figcaption>The "
                        f"primary error along <code>{_e(par)}</code>: dots held, crosses failed; dashed, each "
                        "engine's limit; a failed run without an error is drawn at the top.</figcaption></figure>"
                        if b64 else ""))
    return "\n".join(parts)


def _colour(frac: float, n_supported: int) -> str:
    if n_supported == 0 or not math.isfinite(frac):
        return "#e6e6e6"
    hue = int(round(120 * frac))  # 0 red .. 120 green
    return f"hsl({hue},70%,80%)"


def _engine_cells(g: pd.DataFrame, engines: list[str], cell) -> list[str]:
    """One cell per engine (columns ``engines``) from the rows ``g`` (one per
    engine): ``cell(row)``, or a dash where the engine has no row."""
    by = {r["engine"]: r for r in g.to_dict("records")}
    return [cell(by[en]) if en in by else "<span class='note'>-</span>" for en in engines]


def _stability_html(sm: pd.DataFrame) -> str:
    if sm.empty:
        return '<p class="note">No sweep or conformance rows.</p>'
    engines = sorted(sm["engine"].unique())
    rows = []
    def cell(r) -> str:
        supported = r["points"] - r["unsupported"]
        txt = [f"<b>{r['ok_stable']}/{r['points']}</b> ran &amp; stayed finite",
               f"<b>{r['met_checks']}/{r['points']}</b> met its checks"
               + (f" <span class='bad wrap'>(failed: {_e(', '.join(r['checks_failed']))})</span>"
                  if r["checks_failed"] else "")]
        if r["no_verdict"]:
            txt.append(f"{r['no_verdict']} with no verdict recorded")
        for k in ("unstable", "diverged", "error", "unsupported", "other"):
            if r[k]:
                txt.append(f"{r[k]} {k}")
        if is_finite(r["max_stable_dt"]):
            txt.append(f"max stable dt {fmt(r['max_stable_dt'])}")
        if is_finite(r["min_unstable_dt"]):
            txt.append(f"fails from dt {fmt(r['min_unstable_dt'])}")
        if is_finite(r["max_met_dt"]):
            txt.append(f"checks met up to dt {fmt(r['max_met_dt'])}")
        frac = r["met_checks"] / supported if supported else math.nan
        return (f"<div class='cell' style='background:{_colour(frac, supported)};padding:.2em'>"
                + "<br>".join(txt) + "</div>")

    for (sc, va), g in sm.groupby(["scenario", "variant"], sort=True):
        rows.append([_e(sc) + (f" / {_e(va)}" if va else "")] + _engine_cells(g, engines, cell))
    sel = sm.attrs.get("selection", "")
    return (f"<p class='note'>Showing {_e(sel)}. Per cell: points that ran (status ok) and stayed finite and "
            "stable, out of all points (latest sweep points and latest <code>physbench check</code> rows); of "
            "those, the points that also met every check of the scenario (an expected failure, xfail, is still "
            "a check not met: it says the engine is known not to hold the scene), and which checks failed; counts "
            "of the other outcomes; the largest dt at which the engine stayed ok and stable, the smallest at "
            "which it did not, the largest at which it met its checks. Verdicts are the ones each row was written "
            "with; a row written before rows carried them counts as <i>no verdict recorded</i>, never re-judged. "
            "Colour: share of supported points that met their checks (red 0 .. green 1; grey: unsupported).</p>"
            + _table(["scenario"] + engines, rows, raw=True))


def _judge_html(df: pd.DataFrame) -> str:
    """Judging scenes without a model: per engine the contact-law
    residuals (a table and one plot), the predictability of the hard
    scenes (their ensembles), the engines' consensus; from the rows only."""
    parts = ["<h3>Contact-law residuals</h3>"]
    cl = contact_law_table(df)
    if cl.empty:
        parts.append("<p class='note'>No row carries contact-law residuals (a scene records contact forces only "
                     "when a check or its primary metric names one).</p>")
    else:
        rows = []
        for r in cl.to_dict("records"):
            cells = [_e(r["engine"]), f"{r['rows']} ({r['scenarios']})"]
            for n, _ in LAW_COLUMNS:
                v = r[f"{n}_max"]
                cells.append(f"{fmt(v, 3)} <span class='note'>{_e(r[f'{n}_where'])}</span>" if is_finite(v)
                             else "<span class='note'>undefined</span>")
            rows.append(cells)
        head = ["engine", "rows (scenarios)"] + [f"{n} max ({u})" for n, u in LAW_COLUMNS]
        parts.append("<p class='note'>Largest residual over each engine's latest check rows and sweep points "
                     "(the scene as written) that carry them, with the scenario it came from; <i>undefined</i>: no "
                     "row has a value (no contact forces from that engine's adapter, no sliding contact). "
                     "docs/METRICS.md defines them.</p>" + _table(head, rows, raw=True))
        png = plot_contact_laws(cl)
        if png:
            parts.append(f"<figure class='hist'>{_img(png, 'contact-law residuals per engine')}<figcaption>Largest "
                         "residual per engine, log scale; 0 drawn at 1e-16.</figcaption></figure>")
    parts.append("<h3>Predictability</h3>")
    pt = predictability_table(df)
    if pt.empty:
        parts.append("<p class='note'>No ensemble rows (<code>physbench check --ensemble N</code>, or a scene's "
                     "<code>predictable</code> check, writes them).</p>")
    else:
        rows, attrs = [], []
        for r in pt.to_dict("records"):
            p = r["predictable"]
            verdict = {True: "<span class='good'>predictable</span>", False: "<span class='bad'>not "
                       "predictable</span>", None: "<span class='bad'>undefined</span>"}[p]
            rows.append([_e(r["scenario"]) + (f" / {_e(r['variant'])}" if r["variant"] else ""), _e(r["engine"]),
                         f"{fmt(r['members_ok'])}/{fmt(r['members'])}", fmt(r["final_spread"], 3),
                         fmt(r["amplification"], 3), fmt(r["event_spread"]), fmt(r["threshold"]),
                         verdict + (f" ({_e(r['verdict'])})" if r["verdict"] else "")])
            attrs.append(f"data-predictable='{_e(p)}'")
        parts.append(f"<p class='note'>Showing {_e(pt.attrs.get('selection', ''))}: the latest ensemble of each "
                     "scene on each engine, N runs from starts perturbed by Gaussian noise (docs/METRICS.md); the "
                     "final spread (m) against the threshold (m) decides, with the check's recorded verdict.</p>"
                     + _table(["scenario", "engine", "members ok", "final spread (m)", "amplification",
                               "event spread", "threshold (m)", "verdict"], rows, raw=True, row_attr=attrs))
    ct = consensus_table(df)
    if not ct.empty:
        rows = [[_e(r["scenario"]) + (f" / {_e(r['variant'])}" if r["variant"] else ""), _e(r["engines"]),
                 _e(r["status"]), fmt(r["consensus_spread"], 3), fmt(r["consensus_spread_angle"], 3),
                 _e(r["message"]), _e(r["verdicts"])] for r in ct.to_dict("records")]
        parts.append("<h3>Consensus across engines</h3><p class='note'>The checked engines' runs at dt / k^2, "
                     "compared; the largest distance between two of them.</p>"
                     + _table(["scenario", "engines", "status", "consensus_spread (m)", "angle (rad)", "farthest",
                               "verdicts"], rows, raw=True))
    return "\n".join(parts)


def _phase_html(pt: pd.DataFrame) -> str:
    if pt.empty:
        return ('<p class="note">No point was swept over step phases (a <code>[[sweep]]</code> block with '
                '<code>phases = N</code>).</p>')
    engines = sorted(pt["engine"].unique())
    rows = []
    keys = ["machine_id", "suite", "scenario", "variant", "settings", "dt"]
    order = pt.sort_values(["scenario", "variant", "settings", "dt"], ascending=[True, True, True, False],
                           kind="stable")
    several = order[["machine_id", "suite"]].drop_duplicates().shape[0] > 1
    def cell(r) -> str:
        n = r["phases"] - r["pattern"].count("-") - r["pattern"].count("?")
        if not n:
            return f"<div class='cell' style='background:{_colour(math.nan, 0)};padding:.2em'>unsupported</div>"
        single = {".": "single run: pass", "x": "single run: FAIL", "!": "single run: not ok",
                  "?": "single run: no verdict recorded"}.get(r["phase0"], "")
        return (f"<div class='cell' style='background:{_colour(1 - r['fraction'], n)};padding:.2em'>"
                f"<b>{r['failures']}/{n}</b> failed [{fmt(r['lo'], 2)} - {fmt(r['hi'], 2)}]<br>"
                f"<code>{_e(r['pattern'])}</code><br><span class='note'>{single}</span></div>")

    for key, g in order.groupby(keys, sort=False):
        mid, suite, sc, va, st, dt = key
        label = _e(sc) + (f" / {_e(va)}" if va else "")
        if several:
            label += f"<br><span class='note'>{_e(mid)} / {_e(suite)}</span>"
        rows.append([label, _e(st), _e(fmt(dt))] + _engine_cells(g, engines, cell))
    return ("<p class='note'>One run per dt is one draw of the step phase: where a thin wall is caught depends "
            "on where the steps fall. Each configuration below ran N times with its start moved back along the "
            "exact free flight by i/N dt (i = 0 .. N-1; i = 0 is the scene as written). Failed: not ok, not "
            "stable, or the scenario's check of its primary metric not met (expected failures count). Interval: "
            "95 % Wilson (0/16 bounds the failure rate below 0.20). Pattern over the phases in order: "
            "<code>.</code> pass, <code>x</code> check failed, <code>!</code> not ok or unstable, <code>?</code> no "
            "verdict recorded (a row written before rows carried them: not counted); under it, what a "
            "single run of the scene as written saw. Colour: share of phases passed (red 0 .. green 1).</p>"
            + _table(["scenario", "settings", "dt"] + engines, rows, raw=True))


def _trace_link(trace: str, page_dir: Path | None) -> str:
    """A link to a case's ``.rrd`` trace: relative to the page when both
    are known (a results directory moved as a whole keeps its links), else
    the path as the check stored it."""
    if not trace:
        return "<span class='note'>-</span>"
    href = trace
    if page_dir is not None and os.path.isabs(trace):
        try:
            href = os.path.relpath(trace, page_dir)
        except ValueError:  # another drive
            href = Path(trace).as_uri()
    return f"<a href='{_e(href)}'><code>{_e(Path(trace).name)}</code></a>"


def _run_cell(r: Mapping[str, Any]) -> str:
    """The check run a verdict comes from (its file's stem) and the machine."""
    run = Path(r["check_file"]).stem if r["check_file"] else "-"
    return f"<code>{_e(run)}</code><br><span class='note'>{_e(r['machine_id'])}</span>"


def _xfail_html(xf: pd.DataFrame, page_dir: Path | None) -> str:
    """The expected failures, folded: one closed block, inside it one closed
    block per engine, its rows grouped by scenario, each with its measured
    figure against the threshold."""
    if xf.empty:
        return ""
    per = []
    for en, g in xf.groupby("engine", sort=True):
        rows, attrs = [], []
        for sc, h in g.groupby(["scenario", "variant"], sort=True):
            for i, r in enumerate(h.to_dict("records")):
                rows.append([_case(r) if i == 0 else "", f"<code>{_e(r['metric'])}</code>",
                             _e(fmt(r["value"], 4)), _e(r["threshold"] or "-"), _e(r["reason"][:400]),
                             _trace_link(r["trace"], page_dir)])
                attrs.append("data-outcome='XFAIL'")
        n_sc = g[["scenario", "variant"]].drop_duplicates().shape[0]
        per.append(f"<details><summary>{_engine(en)}: {len(g)} XFAIL in {n_sc} scenario(s)</summary>"
                   + _table(["case", "metric", "value", "threshold", "reason", "trace"], rows, raw=True,
                            row_attr=attrs) + "</details>")
    n_sc = xf[["scenario", "variant"]].drop_duplicates().shape[0]
    return (f"<details id='xfail'><summary>{len(xf)} expected failure(s) (XFAIL) in {n_sc} scenario(s) on "
            f"{xf['engine'].nunique()} engine(s): known limitations, each with its measured figure</summary>"
            + "".join(per) + "</details>")


def _failing_html(fc: pd.DataFrame, page_dir: Path | None = None) -> str:
    n_old = fc.attrs.get("no_verdict", 0)
    old = (f"<p class='note'>{n_old} check row(s) written before rows carried their verdicts: no verdict "
           "recorded, not re-judged.</p>" if n_old else "")
    if fc.empty:
        return old + ("<p class='note'>No failing check in the latest <code>physbench check</code> rows.</p>")
    bad = fc[fc["outcome"].isin(BAD_OUTCOMES)]
    rows, attrs = [], []
    for r in bad.to_dict("records"):
        rows.append([_case(r), _engine(r["engine"]), f"<code>{_e(r['metric'])}</code>",
                     f"<span class='bad'>{_e(r['outcome'])}</span>", _e(fmt(r["value"], 4)),
                     _e(r["threshold"] or "-"), _e(r["reason"][:400]), _trace_link(r["trace"], page_dir),
                     _run_cell(r)])
        attrs.append(f"data-outcome='{_e(r['outcome'])}'")
    n_bad = len(bad)
    table = (_table(["case", "engine", "metric", "outcome", "value", "threshold", "reason", "trace", "run"], rows,
                    raw=True, row_attr=attrs) if rows else
             "<p class='good'>No FAIL, XPASS or ERROR.</p>")
    return (old + f"<p class='note'>{n_bad} failing verdict(s) (FAIL, XPASS, ERROR) and {len(fc) - n_bad} expected "
            "failure(s) (XFAIL) in the latest <code>physbench check</code> rows (the latest verdict of each case "
            "on each machine over every check run), as each row recorded them (value against the threshold of that day); the "
            "expected failures are folded below, per engine and scenario. Trace: the case's <code>.rrd</code> "
            "from <code>physbench check --traces DIR</code> (open with <code>rerun</code>).</p>"
            + table + _xfail_html(fc[fc["outcome"] == XFAIL], page_dir))


def _history_html(df: pd.DataFrame) -> str:
    hist = history(df)
    changed = "".join(f"<p class='note'>{_e(line)}</p>" for line in scene_change_lines(scene_changes(df)))
    if not hist:
        return changed + ('<p class="note">No point is in two sweeps of the same suite on the same machine with '
                          "the same scene content yet: history starts with the second sweep.</p>")
    reg = regressions(df, hist)
    shifts = {k: f for k, f in machine_shifts(df, hist).items() if abs(f - 1.0) >= 0.02}
    parts = [f"<p class='note'>{len(hist)} point(s) with history. Cost is the median CPU s per simulated s of the "
             "repeats; a cost change is flagged when the latest median differs from the baseline (the median "
             f"cost of the last {BASELINE_RUNS} earlier ok runs, fewer if there are fewer; a series is judged from "
             f"its {MIN_COST_HISTORY + 1}th ok run on) by more than "
             f"max({NOISE_FLOOR:.0%}; {NOISE_SPREADS:g} x s; {NOISE_SPREADS:g} x {MAD_TO_SIGMA:g} x MAD), s the "
             "relative spread (median - min) / median of the repeats, the larger of the latest run's and the "
             "baseline runs' median one, MAD the baseline runs' median absolute deviation from the baseline, "
             "relative to it (night-to-night scatter); a cost drift (a creep the moving baseline absorbs) when "
             f"the latest cost exceeds the cheapest plateau (median of {BASELINE_RUNS} consecutive runs) of the last "
             f"{DRIFT_HORIZON} earlier ok runs by more than max({NOISE_FLOOR:.0%}; {NOISE_SPREADS:g} x s; "
             f"{NOISE_SPREADS:g} x the night-to-night noise from successive differences) and the rise came over "
             "several nights, not in one jump. Both are taken relative to the night's machine-wide factor (the "
             "median change over all series of that night, when it has at least "
             f"{MACHINE_SHIFT_MIN_SERIES}): a slower machine moves every series, a code change some. "
             "An accuracy change when the primary error differs from the "
             "best earlier one "
             f"by more than {NOISE_FLOOR:.0%} and {ERROR_ABS_FLOOR:g} absolute; a status change from ok to anything "
             "else is a regression. A point is compared only with sweeps of the same scene content (its "
             "scene hash): a changed scene starts a new series.</p>", changed]
    for (mid, suite, sid), f in sorted(shifts.items()):
        parts.append(f"<p class='note'>Machine-wide factor {_e(mid)} / {_e(suite)} / {_e(sid)}: every series ran "
                     f"{f - 1.0:+.1%} against its baseline (median over the series); taken out of the cost "
                     "changes below.</p>")
    if reg.empty:
        parts.append("<p class='good'>No regression or improvement beyond noise.</p>")
    else:
        n_reg = int((reg["direction"] == "regression").sum())
        parts.append(f"<p><span class='{'bad' if n_reg else 'good'}'>{n_reg} regression(s)</span>, "
                     f"{len(reg) - n_reg} improvement(s).</p>")
        rows = []
        for r in reg.to_dict("records"):
            d = r["direction"]
            cls = "bad" if d == "regression" else "good"
            if r["kind"] == "status":
                change, prev, last, thr = "-", _e(r["previous"]), _e(r["latest"]), "-"
            else:
                change = _e(f"{r['change']:+.1%}") if math.isfinite(r["change"]) else "from 0"
                prev, last, thr = _e(fmt(r["previous"])), _e(fmt(r["latest"])), _e(f"{r['threshold']:.0%}")
            rows.append([f"<span class='{cls}'>{_e(d)}</span>", _e(r["kind"]),
                         _e(r["scenario"]) + (f" / {_e(r['variant'])}" if r["variant"] else ""),
                         _e(r["engine"]), _e(r["settings"]), _e(r["machine_id"]) + " / " + _e(r["suite"]),
                         prev, last, change, thr, _e(r["previous_sweep"]) + " &rarr; " + _e(r["latest_sweep"])])
        parts.append(_table(["", "kind", "scenario", "engine", "settings", "machine / suite",
                             "before (cost: baseline; drift: plateau; error: best)", "latest", "change", "noise threshold",
                             "sweeps"], rows, raw=True))
    # small multiples: flagged regressions first, then the largest cost moves
    order: list[tuple[str, str, str]] = []
    if not reg.empty:
        for r in reg[reg["direction"] == "regression"].to_dict("records"):
            k = (r["machine_id"], r["suite"], r["point_key"])
            if k not in order:
                order.append(k)

    def move(g: pd.DataFrame) -> float:
        c = g.loc[g["status"] == OK, "cost"].to_numpy(float)
        c = c[np.isfinite(c) & (c > 0)]
        return float(np.log(c.max() / c.min())) if len(c) >= 2 else 0.0

    for k in sorted(hist, key=lambda k: -move(hist[k])):
        if k not in order:
            order.append(k)
    picks = order[:MAX_SMALL_MULTIPLES]
    series = []
    for k in picks:
        g = hist[k]
        last = g.iloc[-1]
        t = f"{last['scenario']}{' / ' + last['variant'] if last['variant'] else ''}: {last['engine']} " \
            f"{settings_label(last['swept'] or {})}"
        series.append((t, g))
    b64 = plot_history(series)
    if b64:
        parts.append(f"<figure class='hist'>{_img(b64, 'history small multiples')}<figcaption>The "
                     f"{len(picks)} worst series (flagged regressions first, then the largest cost moves): "
                     "blue, cost median per sweep with a bar down to the fastest repeat; orange, primary error "
                     "(log); red lines, sweeps where the run was not ok.</figcaption></figure>")
    return "\n".join(parts)


def _left_out_line(notes: list[Mapping[str, Any]]) -> str:
    """One line at the top naming what the data notes left out of the page
    (unreadable files, rows of a schema version this report does not
    read); '' when nothing was."""
    lo = left_out(notes)
    if not lo:
        return ""
    unreadable = [n for n in lo if n["kind"] == "unreadable"]
    rows = sum(int(n["rows"] or 0) for n in lo if n["kind"] != "unreadable")
    what = []
    if unreadable:
        what.append(f"{len(unreadable)} unreadable file(s)")
    if rows:
        files = sum(1 for n in lo if n["kind"] != "unreadable")
        what.append(f"{rows} row(s) of a schema version this report does not read, in {files} file(s)")
    return (f"<p class='leftout' id='left-out'><b>Left out of this page:</b> {_e('; '.join(what))} "
            "(<a href='#data'>Data</a>).</p>")


def _data_html(notes: list[Mapping[str, Any]], warnings: list[str], df: pd.DataFrame) -> str:
    """What reading the stored rows found: files and rows left out, files
    read as the current schema for want of a ``schema_version`` column,
    incomplete sweeps, other warnings."""
    parts = []
    lo = left_out(notes)
    if lo:
        parts.append("<h3>Left out</h3><ul>" + "".join(f"<li>{_e(n['text'])}</li>" for n in lo) + "</ul>")
    nos = [n for n in notes if n["kind"] == "no_schema_version"]
    if nos:
        version = nos[0]["text"].rsplit(" ", 1)[-1]
        parts.append(f"<p>{len(nos)} file(s), {sum(int(n['rows'] or 0) for n in nos)} row(s), without a "
                     f"<code>schema_version</code> column: read as version {_e(version)}.</p>"
                     f"<details><summary>the files</summary><ul class='note'>"
                     + "".join(f"<li>{_e(n['path'])}</li>" for n in nos) + "</ul></details>")
    known = {n["text"] for n in notes}
    other = [w for w in warnings if w not in known]
    if other:
        parts.append("<h3>Other warnings</h3><ul>" + "".join(f"<li>{_e(w)}</li>" for w in other) + "</ul>")
    inc = df[df["incomplete"]] if len(df) else df
    if len(inc):
        parts.append(f"<p>{len(inc)} row(s) come from incomplete sweeps (part files not yet consolidated): "
                     + _e(", ".join(sorted(set(inc["sweep_id"])))) + "; they are shown, marked incomplete.</p>")
    if not parts:
        return "<p class='good'>Every stored file was read as this report's schema; no row was left out.</p>"
    return "\n".join(parts)


def render_html(df: pd.DataFrame, *, target: float | None = None,
                targets: Mapping[Any, float] | float | None = None, warnings: Iterable[str] = (),
                command: str = "physbench report", generated: str | None = None,
                results_dir: str | Path | None = None, physbench_commit: str | None = None,
                page_dir: str | Path | None = None, first: Mapping[str, Any] | None = None) -> str:
    """The whole page for the frame ``df`` (from
    harness.report.loading.load_results); ``page_dir``: where the page
    will be written (trace links are made relative to it); ``first``:
    harness.report.glance.first_screen of ``df`` when the caller has it
    (report_main writes the same numbers to summary.json).  ``warnings``
    and the frame's data notes go to the Data section at the end; only
    what left rows out gets one line at the top."""
    df = normalised(df)
    notes = list(df.attrs.get("data_notes", []))
    warnings = list(warnings) + list(df.attrs.get("warnings", []))
    warnings = list(dict.fromkeys(warnings))
    generated = generated or _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    if physbench_commit is None:
        physbench_commit = commit_id()
    pdir = Path(page_dir) if page_dir is not None else None
    where = f" under <code>{_e(results_dir)}</code>" if results_dir is not None else ""
    top = [_left_out_line(notes)]
    if df.empty:
        top.append(f"<div class='warn'><b>No results found</b>{where}. Run <code>physbench sweep</code> "
                   "(or <code>physbench check</code>) first; this page fills in from the Parquet rows they "
                   "write.</div>")
        body = {k: '<p class="note">No results.</p>' for k in ("glance", "wp", "cost", "stab", "phase", "hist",
                                                               "limits", "failing", "judge")}
        header = ""
    else:
        header = _header_html(df)
        if first is None:
            first = first_screen(df)
        lad = first["ladder"]
        body = {"glance": _glance_html(first, pdir),
                "wp": _wp_html(work_precision(df, target=target, targets=targets)),
                "cost": _ladder_html(lad) + "<h3>At each scenario's own target</h3>"
                        + _cost_html(cost_to_target(df, targets=targets, target=target)),
                "limits": _breaking_html(df),
                "stab": _stability_html(stability_matrix(df)),
                "failing": _failing_html(failing_checks(df), pdir),
                "phase": _phase_html(phase_table(df)),
                "judge": _judge_html(df),
                "hist": _history_html(df)}
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>physbench report</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>{_CSS}</style></head><body>
<h1>physbench report</h1>
<p class="note">Generated {_e(generated)} from stored results{where}.</p>
{''.join(top)}
<section id="at-a-glance"><h2>At a glance</h2>{body['glance']}</section>
<section id="header"><h2>What this covers</h2>{header or '<p class="note">Nothing.</p>'}</section>
<section id="work-precision"><h2>Work-precision diagrams</h2>{body['wp']}</section>
<section id="cost-to-target"><h2>Cost to reach the target accuracy</h2>{body['cost']}</section>
<section id="breaking-points"><h2>Breaking points</h2>{body['limits']}</section>
<section id="stability"><h2>Stability matrix</h2>{body['stab']}</section>
<section id="failing-checks"><h2>Failing checks</h2>{body['failing']}</section>
<section id="phases"><h2>Hard cases over step phases</h2>{body['phase']}</section>
<section id="judging"><h2>Judging scenes without a model</h2>{body['judge']}</section>
<section id="history"><h2>History across runs</h2>{body['hist']}</section>
<section id="data"><h2>Data</h2>{_data_html(notes, warnings, df)}</section>
<footer><p>Generated by <code>{_e(command)}</code> at {_e(generated)}, physbench commit
<code>{_e(physbench_commit)}</code>. Self-contained: no external assets, no scripts.</p></footer>
</body></html>
"""
