"""``physbench run``: one run of one scenario on one engine, with the
scene's checks that apply to it."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from physbench.adapters import get_adapter
from physbench.harness.cli.common import checked_request, fmt_prediction, fmt_value, output_file, split_sets
from physbench.harness.conformance import BAD, check_applies, evaluate_runs, fmt_measured, judged_apart, scene_runs
from physbench.harness.console import console, name_column
from physbench.harness.execute import WorkerPool, request_scene, run_isolated, run_requests
from physbench.harness.references.predict import predictions
from physbench.harness.results import write_rows


def cmd_run(args: argparse.Namespace) -> int:
    save = output_file("--save", args.save)
    cls = get_adapter(args.engine)
    settings, overrides = split_sets(args.set, set(cls.capabilities().settings))
    req = checked_request(args, args.engine, settings, overrides, timeout_s=args.timeout, record_every=args.record_every)
    # in a worker process: an engine that aborts or hangs is a status, not a dead command
    result = run_isolated(req)
    runs, outcomes = _run_checks(req, result, settings, args)
    values, text = _predictions(req)
    if args.save:
        row = result.row()
        row["phase"] = float(args.phase)  # 0 = the scene as written
        if runs:
            row.update(runs[0].row_extra)
        row["checks"] = json.dumps([o.as_dict() for o in outcomes], sort_keys=True)
        write_rows([row], save)
    if args.json:
        d = result.as_dict()
        d["checks"] = [o.as_dict() for o in outcomes]
        # the model's predictions beside the measured values (docs/METRICS.md, Predictions)
        d["predictions"] = values
        d["predictions_text"] = text
        sys.stdout.write(json.dumps(d, sort_keys=False) + "\n")
        sys.stdout.flush()
    else:
        _print_result(result, outcomes, values, text)
    return 0 if result.status == "ok" and not any(o.outcome in BAD for o in outcomes) else 1


def _run_checks(req, result, settings: dict[str, Any], args: argparse.Namespace):
    """The scene's checks that apply to the run of ``req``, evaluated as
    ``physbench check`` evaluates them (harness/conformance/): the runs a
    check needs beyond this one -- its step phases, an ``@dt=...`` setting --
    are made here, in one worker process, with the same settings and spec
    overrides.  A run at a given ``--phase`` is judged on itself only (it is
    one phase already).  Returns (planned runs, outcomes)."""
    import dataclasses

    scene = request_scene(dataclasses.replace(req, phase=0.0))

    apart = [c.metric for c in scene.checks if check_applies(c, args.engine, scene.variant) and judged_apart(c)]
    if apart:
        print(f"note: {', '.join(apart)}: judged on an ensemble or the engines' consensus, by physbench check "
              "(not by one run)", file=sys.stderr)
    runs = scene_runs(scene, args.engine, settings, phases=1 if args.phase else None)
    if not runs:
        return runs, []
    results = {runs[0].key: result}
    extra = {id(r): dataclasses.replace(req, settings=dict(r.settings), phase=r.phase) for r in runs[1:]}
    for r in runs[1:]:
        if not args.json:
            print(f"check run: {args.engine} {r.scenario}" + (f" phase {r.phase:g}" if r.phase else "")
                  + "".join(f" {k}={v:.6g}" if isinstance(v, float) else f" {k}={v}"
                            for k, v in r.settings.items() if settings.get(k) != v), file=sys.stderr)
    if extra:
        with WorkerPool(1) as pool:
            done = {id(q): res for q, res in run_requests(extra.values(), pool)}
        for r in runs[1:]:
            results[r.key] = done[id(extra[id(r)])]
    return runs, evaluate_runs(runs, results)


def _predictions(req) -> tuple[dict[str, Any], dict[str, str]]:
    """The scene's model predictions (harness.references.predict), for the
    scene as written (step phase 0, with the run's spec overrides)."""
    import dataclasses

    return predictions(request_scene(dataclasses.replace(req, phase=0.0)))


def _print_result(result, outcomes=(), values=None, text=None) -> None:
    from rich.table import Table

    con = console()
    title = f"{result.scenario}" + (f" [{result.variant}]" if result.variant else "") + f" on {result.engine} {result.engine_version}"
    con.print(f"[bold]{title}[/bold]: status [bold]{result.status}[/bold]" + (f" - {result.message}" if result.message else ""))
    values = values or {}
    t = Table()
    name_column(t, "metric", result.metrics)
    t.add_column("value", overflow="fold")
    # a prediction beside the metric it predicts (roll_accel_ref beside roll_accel)
    twins = {k[:-4]: k for k in values if k.endswith("_ref") and k[:-4] in result.metrics}
    if twins:
        t.add_column("model predicts", overflow="fold")
    for k, v in result.metrics.items():
        t.add_row(k, fmt_value(v), *([fmt_prediction(values[twins[k]]) if k in twins else ""] if twins else []))
    con.print(t)
    if values or text:
        p = Table(title="the reference model predicts")
        name_column(p, "prediction", [*values, *(text or {})])
        p.add_column("value", overflow="fold")
        for k, v in values.items():
            p.add_row(k, fmt_prediction(v))
        for k, v in (text or {}).items():
            p.add_row(k, str(v))
        con.print(p)
    s = Table("setting", "value")
    for k, v in result.settings.items():
        s.add_row(k, fmt_value(v))
    con.print(s)
    if result.stages:
        con.print("stages: " + json.dumps(result.stages, default=str))
    for n in result.notes:
        con.print(f"note: {n}")
    if outcomes:
        from rich.markup import escape

        c = Table(title="checks (as physbench check)")
        name_column(c, "check", [o.metric for o in outcomes])
        for col in ("threshold", "value", "outcome", "reason"):
            c.add_column(col, overflow="fold")
        for o in outcomes:
            style = "red" if o.outcome in BAD else "green" if o.outcome == "PASS" else "yellow"
            c.add_row(escape(o.metric), escape(o.threshold), fmt_measured(o.value, o.bounds), f"[{style}]{o.outcome}[/]",
                      escape(o.message))
        con.print(c)

