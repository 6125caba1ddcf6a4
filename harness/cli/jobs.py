"""The batch jobs, each handing its checked arguments to its own module:
``check`` (conformance), ``sweep``, ``limits`` and ``report``."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from physbench.adapters import get_adapter
from physbench.harness.cli.common import UsageError, engine_sets, output_dir, output_file, scheduler_needs_dask, split_sets
from physbench.harness.conformance import check_main, default_engines


def cmd_check(args: argparse.Namespace) -> int:
    output_file("--junit", args.junit)
    output_dir("--traces", args.traces)
    scenarios = list(args.paths or []) + list(args.scenarios or [])
    scheduler_needs_dask(args)
    settings = None
    if args.set:
        # the engines --set is checked against; check_main says which are left out, once, as it starts
        per, rest = engine_sets(args.set, list(args.engines or default_engines(note=False)))
        if rest:
            raise UsageError(f"--set {rest[0]}: check takes engine settings only (ENGINE:KEY=VALUE or KEY=VALUE); "
                             f"vary the spec with a [[variant]]")
        settings = {e: s for e, s in per.items() if s}
    ensemble = None
    if args.ensemble is not None:
        for flag, v in (("--sigma", args.sigma), ("--threshold", args.threshold)):
            if v is not None and not (math.isfinite(v) and v > 0):
                raise UsageError(f"{flag}: expected a finite number > 0 (m), got {v!r}")
        ensemble = {"n": args.ensemble, "position": args.sigma, "threshold": args.threshold}
    elif args.sigma is not None or args.threshold is not None:
        raise UsageError("--sigma and --threshold go with --ensemble N")
    return check_main(engines=args.engines, tags=args.tags, junit=args.junit, scenarios=scenarios or None,
                      jobs=args.jobs, timeout_s=args.timeout, resume=args.resume, traces=args.traces,
                      executor=args.executor, scheduler=args.scheduler, settings=settings, ensemble=ensemble)


def cmd_sweep(args: argparse.Namespace) -> int:
    # the sweep machinery (suite, store, schedule: ~20 ms of imports): loaded by this command only, not at every start
    from physbench.harness.sweep import sweep_main

    scheduler_needs_dask(args)
    return sweep_main(args.suite, engines=args.engines, jobs=args.jobs, executor=args.executor,
                      out_dir=output_dir("--out", args.out), resume=args.resume, scenarios=args.scenarios,
                      timeout_s=args.timeout, scheduler=args.scheduler)


def cmd_limits(args: argparse.Namespace) -> int:
    # the limits machinery (~15 ms of imports): loaded by this command only, not at every start
    from physbench.harness.limits import LimitRequest, limits_main, parse_number

    settings, overrides = split_sets(args.set, set(get_adapter(args.engine).capabilities().settings))

    try:
        lo, hi = (parse_number(t, f"--range {w}") for t, w in zip(args.range, ("LO", "HI")))
    except ValueError as e:
        raise UsageError(str(e)) from None
    bounds = []
    for item in args.max or []:
        key, sep, text = item.partition("=")
        if not sep:
            raise UsageError(f"--max {item}: expected METRIC=VALUE")
        try:
            bounds.append((key.strip(), parse_number(text.strip(), f"--max {key.strip()}")))
        except ValueError as e:
            raise UsageError(str(e)) from None
    req = LimitRequest(args.scenario, args.variant, args.engine, args.param, lo, hi, phases=args.phases,
                       tol=args.tol, checks=tuple(args.check or ()), settings=tuple(sorted(settings.items())),
                       overrides=tuple(overrides.items()), bounds=tuple(sorted(bounds)))
    return limits_main(req, out_dir=Path(args.out) if args.out else None, as_json=args.json)


def cmd_report(args: argparse.Namespace) -> int:
    from physbench.harness.report import report_main  # pandas, pyarrow, matplotlib: loaded by this command only

    return report_main(results_dir=Path(args.results_dir) if args.results_dir else None,
                       out=output_file("--out", args.out), suites=args.suites, target=args.target,
                       fail_on_regression=args.fail_on_regression)

