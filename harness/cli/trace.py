"""``physbench trace``: run engines and write one rerun recording side by side."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from physbench.adapters import ENGINES, get_adapter
from physbench.harness.cli.common import UsageError, checked_request, engine_sets, output_file, split_sets
from physbench.harness.conformance import evaluate
from physbench.harness.execute import WorkerPool, request_scene, run_requests


def cmd_trace(args: argparse.Namespace) -> int:
    # the trace package imports rerun (~0.5 s): loaded by this command only, not at every start
    from physbench.harness.trace import write_rrd
    from physbench.harness.trace.contacts import DEFAULT_CAP

    engines = args.engines or list(ENGINES)
    if Path(args.scenario).is_dir():
        raise UsageError(f"{args.scenario}: trace records one scene side by side on engines: give a scenario id "
                         f"or a spec file, not a folder")
    output_file("-o", args.output)
    # ENGINE:KEY=VALUE for one engine, KEY=VALUE for a setting every engine has; dotted spec keys
    per_engine, rest = engine_sets(args.set, engines)
    overrides = split_sets(rest, set())[1] if rest else {}
    reqs = []
    for e in engines:
        get_adapter(e)
        reqs.append(checked_request(args, e, per_engine[e], overrides, timeout_s=args.timeout, keep_trace=True,
                             contact_cap=0 if args.watch else DEFAULT_CAP))
    scene = request_scene(reqs[0])
    with WorkerPool(args.jobs) as pool:
        done = {id(req): res for req, res in run_requests(reqs, pool)}
    results = [done[id(r)] for r in reqs]
    if args.watch:
        write_rrd(args.output, scene, results)
    else:
        outcomes = [o for r in results for o in evaluate(scene, r) if "@" not in o.metric]
        write_rrd(args.output, scene, results, diagnose=True, outcomes=outcomes,
                  checks={c.metric: c for c in scene.checks}, contact_cap=DEFAULT_CAP)
    for r in results:
        print(f"{r.engine}: {r.status}" + (f" ({r.message})" if r.message else ""), file=sys.stderr)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0

