"""The console summary of a check's outcomes and its exit code."""

from __future__ import annotations

from physbench.harness.conformance.verdicts import (BAD, ERROR, FAIL, OUTCOMES, PASS, UNSUPPORTED, XFAIL, XPASS, Outcome,
                                                    case_names, fmt_measured)
from physbench.harness.console import console as make_console, name_column


def summarize(outcomes: list[Outcome], console=None) -> None:
    """Print a per engine x scenario count table and every FAIL/XPASS/ERROR."""
    from rich.markup import escape
    from rich.table import Table

    console = console or make_console()
    engines = sorted({o.engine for o in outcomes})
    scenarios = sorted({o.scenario for o in outcomes})
    table = Table(title="conformance: checks per engine (pass/fail/xfail/xpass/unsupported/error)")
    name_column(table, "scenario", scenarios)
    for e in engines:
        table.add_column(e, justify="center", overflow="fold")
    cells: dict[tuple[str, str], dict[str, int]] = {}
    for o in outcomes:
        cells.setdefault((o.scenario, o.engine), {k: 0 for k in OUTCOMES})[o.outcome] += 1
    for s in scenarios:
        row = [escape(s)]
        for e in engines:
            c = cells.get((s, e))
            row.append(_cell(c) if c else "-")
        table.add_row(*row)
    tot = {k: sum(o.outcome == k for o in outcomes) for k in OUTCOMES}
    console.print(table)
    console.print("totals: " + ", ".join(f"{k} {v}" for k, v in tot.items()))
    bad = [o for o in outcomes if o.outcome in BAD]
    if bad:
        names = {id(o): n for o, n in zip(outcomes, case_names(outcomes))}
        t2 = Table(title="failures")
        t2.add_column("engine", no_wrap=True)
        name_column(t2, "testcase", [names[id(o)] for o in bad])
        for col in ("outcome", "value", "threshold", "message"):
            t2.add_column(col, overflow="fold")
        for o in bad:
            t2.add_row(*(escape(x) for x in (o.engine, names[id(o)], o.outcome, fmt_measured(o.value, o.bounds), o.threshold, o.message)))
        console.print(t2)


def _cell(c: dict[str, int]) -> str:
    parts = []
    style = {PASS: "green", FAIL: "red", XFAIL: "yellow", XPASS: "magenta", UNSUPPORTED: "dim", ERROR: "red"}
    for k in OUTCOMES:
        if c[k]:
            parts.append(f"[{style[k]}]{c[k]} {k.lower()}[/]")
    return " ".join(parts)


def exit_code(outcomes: list[Outcome]) -> int:
    return 1 if any(o.outcome in BAD for o in outcomes) else 0
