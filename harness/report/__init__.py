"""``physbench report``: one self-contained HTML page from stored results.

Input (see results/README.md and docs/REPORT.md):

- sweep rows, ``results/sweeps/<machine-id>/<suite>/<sweep_id>.parquet``
  (consolidated) and ``results/sweeps/<machine-id>/<suite>/<sweep_id>/part-*.parquet``
  (a sweep still running or killed: read, and marked *incomplete*);
- conformance rows, ``results/check/*.parquet`` (``physbench check``), used
  for at a glance, the stability matrix and the failing checks.

Sections: at a glance (three questions answered from whatever rows exist:
did each engine's latest ``physbench check`` run pass, with its verdict
counts, commit, machine and date; what failed unexpectedly, FAIL, XPASS
and ERROR with value against threshold and trace; what accuracy costs, per
scenario family the cheapest engine to reach each accuracy of the ladder
1e-2 .. 1e-9 and each engine's breaking points), header (machines,
commits, suites, sweeps, engine versions), work-precision diagrams (a
frontier per engine, one colour per engine in every plot), cost to reach
each rung of the accuracy ladder and each scenario's own target, breaking
points (``physbench limits`` / ``[[limit]]`` rows), stability matrix
("ran and stayed finite" apart from "met its checks"), failing checks (the
latest check's FAIL, XPASS, ERROR and XFAIL verdicts with value, threshold,
reason and a link to the case's ``.rrd`` trace; the XFAILs folded per engine
and scenario), step phases, history across runs (regressions flagged only
beyond noise), data (files and rows left out or read as the current schema;
what left rows out also gets one line at the top), footer.  Beside the page,
``summary.json`` holds the first screen's numbers (harness.report.glance).

The report reads rows only: thresholds, verdicts and tags are the ones each
row was written with (harness.report.rows); old rows without them show
"no verdict recorded", never re-judged against today's scenarios.

The page has no external assets and no JavaScript: plots are matplotlib
(Agg) PNGs embedded as base64 ``data:`` URIs, styles are inline, tables are
HTML.  Every table and plot fits 1280-1600 px windows (a wide table scrolls
inside its own box).

The package, by seam: ``loading`` (the only module that reads files),
``rows`` (value helpers and the one normaliser of stored rows), ``analysis``
and ``trends`` (pure functions of the frame: work-precision, cost to
target, breaking points, stability, step phases, failing checks, the latest
conformance run per engine; history and regressions beyond noise),
``glance`` (the first screen and summary.json's data), ``plots``
(matplotlib), ``page`` (HTML).
The names below are the report's interface; the CLI entry is
:func:`report_main`.
"""

from __future__ import annotations

import datetime as _dt
import os
import sys
from pathlib import Path

from physbench.harness.report.analysis import (breaking_points, consensus_table, contact_law_table, failed_checks,
                                              failing_checks, fmt_limit, frontier, hard_scenarios, latest_check_runs,
                                              latest_points, meets_checks, phase_table, predictability_table,
                                              stability_matrix, unexpected_failures, work_precision)
from physbench.harness.report.glance import SUMMARY_VERSION, first_screen, summary
from physbench.harness.report.cost import (LADDER, RATIO_AT_LEAST, RATIO_AT_MOST, RATIO_EXACT, RATIO_OPEN, at_a_glance,
                                 cost_to_target, family, grid_ends, ladder)
from physbench.harness.report.trends import (BASELINE_RUNS, NOISE_FLOOR, NOISE_SPREADS, history, machine_shifts,
                                    pooled_noise, regressions, scene_change_lines, scene_changes)
from physbench.harness.report.loading import load_results
from physbench.harness.report.page import render_html
from physbench.harness.report.plots import (ENGINE_COLOURS, engine_colour, plot_breaking_point, plot_contact_laws,
                                          plot_history, plot_work_precision)
from physbench.harness.report.rows import ERROR_FLOOR, fmt, normalise, settings_label
from physbench.harness.results import results_dir as _results_dir, write_json_atomic, write_text_atomic
from physbench.harness.runner import commit_id


__all__ = ["BASELINE_RUNS", "ENGINE_COLOURS", "ERROR_FLOOR", "LADDER", "NOISE_FLOOR", "NOISE_SPREADS",
           "RATIO_AT_LEAST", "RATIO_AT_MOST", "RATIO_EXACT", "RATIO_OPEN", "SUMMARY_VERSION",
           "at_a_glance", "breaking_points", "consensus_table", "contact_law_table", "cost_to_target",
           "engine_colour", "failed_checks", "failing_checks",
           "family", "first_screen", "fmt", "fmt_limit", "frontier", "grid_ends", "hard_scenarios", "history",
           "ladder", "latest_check_runs", "latest_points",
           "load_results", "machine_shifts", "meets_checks", "normalise", "phase_table", "plot_breaking_point",
           "plot_contact_laws", "predictability_table",
           "plot_history", "plot_work_precision", "pooled_noise", "regressions", "render_html", "report_main",
           "scene_change_lines", "scene_changes", "settings_label", "stability_matrix", "summary",
           "unexpected_failures", "work_precision"]


def report_main(results_dir: Path | None = None, out: Path | None = None, suites: list[str] | None = None,
                target: float | None = None, fail_on_regression: bool = False) -> int:
    """Write the report (default ``<results_dir>/report.html``) and, beside
    it, ``summary.json`` (the first screen's numbers:
    harness.report.glance.summary), and print the page's path and one line
    per regression flagged beyond noise.  Returns 0; 1
    when there were no usable result rows (the page is still written and
    says so); 3 when ``fail_on_regression`` and a regression is flagged (for
    a nightly pipeline that should go red)."""
    root = Path(results_dir) if results_dir is not None else _results_dir()
    out = Path(out) if out is not None else root / "report.html"
    cmd = ["physbench", "report"]
    if results_dir is not None:
        cmd += ["--results-dir", str(results_dir)]
    if out != root / "report.html":
        cmd += ["--out", str(out)]
    if suites:
        cmd += ["--suites", *suites]
    if target is not None:
        cmd += ["--target", f"{target:g}"]
    if fail_on_regression:
        cmd += ["--fail-on-regression"]
    df = load_results(root, suites=suites)
    warnings = df.attrs.get("warnings", [])
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)

    generated = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    physbench_commit = commit_id()
    first = first_screen(df)
    page = render_html(df, target=target, warnings=warnings, command=" ".join(cmd), results_dir=root,
                       page_dir=os.path.abspath(out.parent), generated=generated,
                       physbench_commit=physbench_commit, first=first)
    write_text_atomic(page, out)
    write_json_atomic(summary(first, generated=generated, physbench_commit=physbench_commit, report=out.name,
                              notes=df.attrs.get("data_notes", [])), out.parent / "summary.json")
    if df.empty:
        print(f"no results under {root}{' for suites ' + ', '.join(suites) if suites else ''}; "
              f"wrote an empty report to {out}", file=sys.stderr)
        print(out)
        return 1
    print(out)
    reg = regressions(df)
    for line in scene_change_lines(scene_changes(df)):
        print(f"note: {line}")
    for (mid, suite, sid), f in sorted(machine_shifts(df).items()):
        if abs(f - 1.0) >= 0.02:
            print(f"note: {mid} / {suite} / {sid}: every series ran {f - 1.0:+.0%} against its baseline "
                  "(median over the series): taken out of each cost change as the machine's, not the code's")
    bad = reg[reg["direction"] == "regression"] if not reg.empty else reg
    for r in bad.itertuples():
        change = "" if r.kind == "status" else f" ({r.change:+.0%}, threshold {r.threshold:.0%})"
        print(f"regression: {r.kind}: {r.scenario} on {r.engine} [{r.settings}]: {r.previous} -> {r.latest}{change}")
    if len(bad):
        print(f"{len(bad)} regression(s) beyond noise")
    return 3 if fail_on_regression and len(bad) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(report_main())
