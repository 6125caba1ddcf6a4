"""``physbench`` command line: the user's three jobs.

    physbench run SCENARIO|FILE [--engine E] [--variant V] [--set k=v]... [--json]
    physbench check [SCENARIO|FILE|DIR ...] [--engines ...] [--tags ...] [--junit FILE] [--traces DIR]
    physbench trace SCENARIO|FILE [--engines ...] [--variant V] [--watch] -o FILE.rrd
    physbench limits SCENARIO|FILE --engine E --param KEY --range LO HI [--phases N] [--tol REL] [--json]
    physbench engines [--json]
    physbench models [NAME] [--json]
    physbench list

``--set`` takes either an engine setting (``dt=0.002``, ``integrator=rk4``) or a
dotted key path into the spec (``material.default.restitution=0.5``,
``body[0].velocity=[3,0,0]``).  Values are TOML (``true``, ``1e-3``,
``"rk4"``); a bare word is a string.

``run`` evaluates the scene's checks that apply to the run as ``check``
does (making the step-phase and ``@dt=...`` runs they need) and lists them.

Exit codes: 0 success, 1 a check failed unexpectedly (FAIL, XPASS, ERROR;
check and run) or the run's status is not ok (run), 2 bad input (spec,
settings, arguments, unknown scenario ids).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from contract.spec import SpecError, parse_value


class UsageError(Exception):
    pass


def _split_sets(pairs: list[str], engine_settings: set[str]) -> tuple[dict[str, Any], dict[str, Any]]:
    """--set k=v items -> (engine settings, spec overrides)."""
    settings: dict[str, Any] = {}
    overrides: dict[str, Any] = {}
    for item in pairs or []:
        if "=" not in item:
            raise UsageError(f"--set {item}: expected key=value")
        key, _, text = item.partition("=")
        key = key.strip()
        value = parse_value(text.strip())
        if key in engine_settings:
            settings[key] = value
        elif "." in key or "[" in key:
            overrides[key] = value
        else:
            raise UsageError(
                f"--set {key}: not a setting of this engine ({', '.join(sorted(engine_settings))}) "
                f"and not a dotted spec key (e.g. material.default.restitution)")
    return settings, overrides


def _int_in(lo: int, hi: int):
    """argparse type: an integer in [lo, hi] (argparse reports anything else
    as a usage error, exit 2)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer in [{lo}, {hi}], got {text!r}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected an integer in [{lo}, {hi}], got {v}")
        return v
    return parse


def _float_where(test: Any, expected: str):
    """argparse type: a number for which ``test(v)`` holds (nan never does)."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if not (math.isfinite(v) and test(v)):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text}")
        return v
    return parse


_phase_value = _float_where(lambda v: 0.0 <= v < 1.0, "a number 0 <= F < 1")
_positive_float = _float_where(lambda v: v > 0.0, "a finite number > 0")


#: bounds of the CLI's counts: runs at once, benchmark repeats, record stride
MAX_JOBS = 256
MAX_REPEATS = 1000
MAX_RECORD_EVERY = 10**8


def output_file(flag: str, value: str | None) -> Path | None:
    """The file an output flag (``--junit``, ``-o``, ``--save``, ``--out``)
    names, checked before any run: not empty, not an existing directory,
    and no existing file where a parent directory must be (missing parent
    directories are created when the file is written).  UsageError (exit 2)
    otherwise."""
    if value is None:
        return None
    if not value.strip():
        raise UsageError(f"{flag}: expected a file path, got {value!r}")
    p = Path(value)
    if p.is_dir() or value.endswith(("/", "\\")):
        raise UsageError(f"{flag} {value}: is a directory; expected a file path")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise UsageError(f"{flag} {value}: {parent} is a file, not a directory")
            break
    return p


def output_dir(flag: str, value: str | None) -> Path | None:
    """The directory an output flag names: not empty, not an existing file."""
    if value is None:
        return None
    if not value.strip():
        raise UsageError(f"{flag}: expected a directory path, got {value!r}")
    p = Path(value)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{flag} {value}: is a file; expected a directory")
    return p


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "n/a"
        return f"{v:.6g}"
    if v is None:
        return "n/a"
    return str(v)


def _request(args: argparse.Namespace, engine: str, settings: dict[str, Any], overrides: dict[str, Any], **kw):
    """The RunRequest of a command line, checked in this process before it
    goes to a worker: a bad spec, setting or phase is exit 2 here."""
    from adapters import get_adapter
    from harness.execute import RunRequest, request_scene
    from contract.phase import PhaseError

    req = RunRequest(str(args.scenario), engine, args.variant, settings, overrides or {}, phase=args.phase, **kw)
    try:
        scene = request_scene(req)
    except PhaseError as e:
        raise UsageError(str(e) if str(e).startswith("--set dt") else f"--phase {args.phase:g}: {e}") from None
    from harness.runner import check_run_size

    try:
        resolved = get_adapter(engine).resolve_settings(scene, settings)
        check_run_size(scene, float(resolved["dt"]), req.record_every)
    except ValueError as e:  # bad setting value, or a recording too large to allocate
        raise UsageError(str(e)) from None
    return req


def cmd_run(args: argparse.Namespace) -> int:
    from adapters import get_adapter
    from harness.conformance import BAD
    from harness.execute import run_isolated

    save = output_file("--save", args.save)
    cls = get_adapter(args.engine)
    settings, overrides = _split_sets(args.set, set(cls.capabilities().settings))
    req = _request(args, args.engine, settings, overrides, timeout_s=args.timeout, record_every=args.record_every)
    # in a worker process: an engine that aborts or hangs is a status, not a dead command
    result = run_isolated(req)
    runs, outcomes = _run_checks(req, result, settings, args)
    if args.save:
        from harness.results import write_rows

        row = result.row()
        row["phase"] = float(args.phase)  # 0 = the scene as written
        if runs:
            row.update(runs[0].row_extra)
        row["checks"] = json.dumps([o.as_dict() for o in outcomes], sort_keys=True)
        write_rows([row], save)
    if args.json:
        d = result.as_dict()
        d["checks"] = [o.as_dict() for o in outcomes]
        sys.stdout.write(json.dumps(d, sort_keys=False) + "\n")
        sys.stdout.flush()
    else:
        _print_result(result, outcomes)
    return 0 if result.status == "ok" and not any(o.outcome in BAD for o in outcomes) else 1


def _run_checks(req, result, settings: dict[str, Any], args: argparse.Namespace):
    """The scene's checks that apply to the run of ``req``, evaluated as
    ``physbench check`` evaluates them (harness/conformance.py): the runs a
    check needs beyond this one -- its step phases, an ``@dt=...`` setting --
    are made here, in one worker process, with the same settings and spec
    overrides.  A run at a given ``--phase`` is judged on itself only (it is
    one phase already).  Returns (planned runs, outcomes)."""
    import dataclasses

    from harness.conformance import evaluate_runs, scene_runs
    from harness.execute import WorkerPool, request_scene, run_requests

    scene = request_scene(dataclasses.replace(req, phase=0.0))
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


def _print_result(result, outcomes=()) -> None:
    from rich.console import Console
    from rich.table import Table

    con = Console()
    title = f"{result.scenario}" + (f" [{result.variant}]" if result.variant else "") + f" on {result.engine} {result.engine_version}"
    con.print(f"[bold]{title}[/bold]: status [bold]{result.status}[/bold]" + (f" - {result.message}" if result.message else ""))
    t = Table("metric", "value")
    for k, v in result.metrics.items():
        t.add_row(k, _fmt(v))
    con.print(t)
    s = Table("setting", "value")
    for k, v in result.settings.items():
        s.add_row(k, _fmt(v))
    con.print(s)
    if result.stages:
        con.print("stages: " + json.dumps(result.stages, default=str))
    for n in result.notes:
        con.print(f"note: {n}")
    if outcomes:
        from rich.markup import escape

        from harness.conformance import BAD, _fmt as fmt_value

        c = Table("check", "threshold", "value", "outcome", "reason", title="checks (as physbench check)")
        for o in outcomes:
            style = "red" if o.outcome in BAD else "green" if o.outcome == "PASS" else "yellow"
            c.add_row(escape(o.metric), escape(o.threshold), fmt_value(o.value), f"[{style}]{o.outcome}[/]",
                      escape(o.message))
        con.print(c)


def cmd_engines(args: argparse.Namespace) -> int:
    from adapters import ENGINES, get_adapter

    caps = []
    for name in ENGINES:
        try:
            caps.append(get_adapter(name).capabilities().as_dict())
        except Exception as e:  # a broken adapter module is reported, not fatal
            caps.append({"engine": name, "available": False, "error": f"{type(e).__name__}: {e}"})
    if args.json:
        print(json.dumps(caps, indent=2, default=str))
        return 0
    from rich.console import Console
    from rich.table import Table

    t = Table("engine", "version", "available", "dims", "shapes", "effects", "settings (default)")
    for c in caps:
        if "error" in c:
            t.add_row(c["engine"], "", "no", "", "", "", c["error"])
            continue
        t.add_row(c["engine"], c["version"], "yes" if c["available"] else "no", str(c["dimensions"]),
                  ", ".join(c["shapes"]), ", ".join(c["effects"]),
                  ", ".join(f"{k}={_fmt(v['default']) if v['default'] is not None else 'scene'}"
                            for k, v in c["settings"].items()))
    Console(width=200).print(t)
    return 0


def cmd_trace(args: argparse.Namespace) -> int:
    from adapters import ENGINES, get_adapter
    from harness.execute import WorkerPool, request_scene, run_requests
    from harness.trace.contacts import DEFAULT_CAP

    engines = args.engines or list(ENGINES)
    if Path(args.scenario).is_dir():
        raise UsageError(f"{args.scenario}: trace records one scene side by side on engines: give a scenario id "
                         f"or a spec file, not a folder")
    output_file("-o", args.output)
    overrides = _split_sets(args.set, set())[1] if args.set else {}
    reqs = []
    for e in engines:
        get_adapter(e)
        reqs.append(_request(args, e, {}, overrides, timeout_s=args.timeout, keep_trace=True,
                             contact_cap=0 if args.watch else DEFAULT_CAP))
    scene = request_scene(reqs[0])
    with WorkerPool(args.jobs) as pool:
        done = {id(req): res for req, res in run_requests(reqs, pool)}
    results = [done[id(r)] for r in reqs]
    from harness.conformance import evaluate
    from harness.trace import write_rrd

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


def cmd_check(args: argparse.Namespace) -> int:
    from harness.conformance import check_main

    output_file("--junit", args.junit)
    output_dir("--traces", args.traces)
    scenarios = list(args.paths or []) + list(args.scenarios or [])
    _scheduler_needs_dask(args)
    return check_main(engines=args.engines, tags=args.tags, junit=args.junit, scenarios=scenarios or None,
                      jobs=args.jobs, timeout_s=args.timeout, resume=args.resume, traces=args.traces,
                      executor=args.executor, scheduler=args.scheduler)


def cmd_bench(args: argparse.Namespace) -> int:
    import contextlib

    from harness import bench

    out = sys.stdout
    # with --json, stdout carries the JSON only: the tables go to stderr
    with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
        if args.kind == "isolation":
            from harness.execute import bench_isolation

            rows = [bench_isolation(runs=max(3, 10 * args.repeats), engine=(args.engines or ["mujoco"])[0])]
            bench.print_rows(rows, "per-run cost of running in a worker process (wall ms per run, medians): in "
                                   "this process, in a reused worker, in a fresh worker per run")
        elif args.kind == "overhead":
            # the reference engine is left out unless asked for: its steps cost
            # milliseconds, so its overhead is lost in noise and takes minutes
            rows = bench.overhead(args.engines or ["mujoco", "pymunk", "pybullet"], repeats=args.repeats)
            bench.print_rows(rows, "runner recording every step vs bare loops: api = the engine's step call in a "
                                   "Python loop, fast = the adapter's fastest stepping (CPU time, medians)")
        else:
            rows = bench.cost(repeats=args.repeats)
            bench.print_rows(rows, "reference engine vs pybullet (maximal coordinates), same dt and iterations")
            ok = [r for r in rows if r["scene"].startswith("spheres_") and r["reference_broadphase_us_per_step"] == r["reference_broadphase_us_per_step"]]
            if len(ok) >= 2:
                k = bench.fit_exponent([r["bodies"] for r in ok], [r["reference_broadphase_us_per_step"] for r in ok])
                print(f"reference broad phase: cost ~ n^{k:.2f} between n = {ok[0]['bodies']} and {ok[-1]['bodies']}")
            sc = bench.broadphase_scaling(repeats=args.repeats)
            bench.print_rows(sc["rows"], "broad phase alone on static constant-density sphere clouds (us per call, "
                                         "medians): sap, all pairs")
            ns = [r["n"] for r in sc["rows"]]
            ex = sc["exponents"]
            print(f"broad phase (sap) on constant-density clouds: cost ~ n^{ex['sap']:.2f} between {ns[0]} and "
                  f"{ns[-1]} (n log n: {ex['n_log_n']:.2f}; all pairs: {ex['brute']:.2f})")
            b = bench.build_cost()
            print(f"reference build of {b['n']} spheres: {b['build_s']:.3f} s CPU, peak {b['peak_mb']:.1f} MB "
                  f"of Python allocations (median of 3)")
    if args.json:
        out.write(json.dumps(rows, default=str) + "\n")
        out.flush()
    return 0


def _scheduler_needs_dask(args: argparse.Namespace) -> None:
    if args.scheduler and args.executor != "dask":
        raise UsageError(f"--scheduler {args.scheduler}: a scheduler address needs --executor dask")


def cmd_sweep(args: argparse.Namespace) -> int:
    from harness.sweep import sweep_main

    _scheduler_needs_dask(args)
    return sweep_main(args.suite, engines=args.engines, jobs=args.jobs, executor=args.executor,
                      out_dir=output_dir("--out", args.out), resume=args.resume, scenarios=args.scenarios,
                      timeout_s=args.timeout, scheduler=args.scheduler)


def cmd_limits(args: argparse.Namespace) -> int:
    from adapters import get_adapter
    from harness.limits import LimitRequest, limits_main, parse_number

    settings, overrides = _split_sets(args.set, set(get_adapter(args.engine).capabilities().settings))

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
    from harness.report import report_main

    return report_main(results_dir=Path(args.results_dir) if args.results_dir else None,
                       out=output_file("--out", args.out), suites=args.suites, target=args.target,
                       fail_on_regression=args.fail_on_regression)


def cmd_models(args: argparse.Namespace) -> int:
    """The reference models' declarations (the same text as docs/MODELS.md)."""
    from harness.references import MODELS, describe

    if args.name is not None and args.name not in MODELS:
        raise UsageError(f"models: unknown model {args.name!r}; known: {', '.join(sorted(MODELS))}")
    descs = describe(args.name)
    if args.json:
        print(json.dumps(descs if args.name is None else descs[0]))
        return 0
    for d in descs:
        print(f"{d['name']}: {d['summary']}")
        print(f"  takes: {d['takes']}")
        for p in d["params"]:
            default = "-" if p["default"] is None else repr(p["default"])
            print(f"  param {p['name']} ({p['type']}, default {default}): {p['meaning']}")
        print(f"  metrics (primary {d['primary']}):")
        for m, meaning in d["produces"].items():
            print(f"    {m}: {meaning}")
        print()
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    from contract.scene import load_scene, scenario_ids

    for sid in scenario_ids():
        try:
            s = load_scene(sid)
            print(f"{sid:40s} {','.join(s.tags):20s} variants: {', '.join(s.variant_names) or '-'}")
        except SpecError as e:
            print(f"{sid:40s} INVALID: {e.errors[0]}")
    return 0


def _seconds(text: str) -> float:
    """A --timeout value: a positive, finite number of seconds."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive, finite number of seconds, got {text!r}")
    return v


def build_parser() -> argparse.ArgumentParser:
    from adapters import engine_names
    from harness.execute import DEFAULT_TIMEOUT_S

    ENGINES = engine_names()  # the shipped four and any named in PHYSBENCH_ADAPTERS
    timeout_help = f"wall-clock budget per run in seconds (default {DEFAULT_TIMEOUT_S:g}); a run past it is 'timeout'"
    p = argparse.ArgumentParser(prog="physbench", description="Validation and benchmark harness for rigid-body physics engines.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="one run of one scenario on one engine")
    r.add_argument("scenario", help="scenario id (family.name) or path to a spec file")
    r.add_argument("--engine", "-e", default="reference", choices=ENGINES)
    r.add_argument("--variant", "-v", default=None)
    r.add_argument("--set", "-s", action="append", default=[], metavar="KEY=VALUE")
    r.add_argument("--json", action="store_true", help="print the result row as one JSON object")
    r.add_argument("--record-every", type=_int_in(1, MAX_RECORD_EVERY), default=1,
                   help="record every N >= 1 steps (default 1)")
    r.add_argument("--save", metavar="FILE.parquet", help="append the result row to a Parquet file")
    r.add_argument("--phase", type=_phase_value, default=0.0, metavar="F",
                   help="step phase 0 <= F < 1: start moved back along the free flight by F dt, to reproduce a "
                        "point of a phase sweep (scenes that start in free flight only)")
    r.add_argument("--timeout", type=_seconds, default=DEFAULT_TIMEOUT_S, metavar="SECONDS", help=timeout_help)
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("check", help="CI conformance: every scenario's checks on every engine")
    c.add_argument("paths", nargs="*", metavar="SCENARIO|FILE|DIR",
                   help="scenario ids, spec files or folders of spec files (anywhere); default all of scenarios/")
    c.add_argument("--engines", nargs="+", choices=ENGINES, default=None)
    c.add_argument("--tags", nargs="+", default=None)
    c.add_argument("--scenarios", nargs="+", default=None, metavar="SCENARIO|FILE|DIR",
                   help="only these: scenario ids, spec files or folders of spec files")
    c.add_argument("--junit", default=None, metavar="FILE.xml")
    c.add_argument("--jobs", type=_int_in(1, MAX_JOBS), default=1, help="worker processes (default 1)")
    c.add_argument("--executor", choices=["process", "dask"], default="process",
                   help="process (default): worker processes under a watchdog; dask: runs as Dask tasks "
                        "(docs/SWEEPS.md)")
    c.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="with --executor dask: join the cluster of this Dask scheduler (e.g. tcp://host:8786); "
                        "default: a local cluster of --jobs workers")
    c.add_argument("--timeout", type=_seconds, default=DEFAULT_TIMEOUT_S, metavar="SECONDS", help=timeout_help)
    c.add_argument("--resume", action=argparse.BooleanOptionalAction, default=True,
                   help="resume an unfinished check with the same commit, engines, scenarios, spec files and "
                        "budget (default); --no-resume always starts afresh")
    c.add_argument("--traces", default=None, metavar="DIR",
                   help="write one diagnosing .rrd per FAIL, XFAIL and ERROR case into DIR (docs/TRACES.md)")
    c.set_defaults(func=cmd_check)

    t = sub.add_parser("trace", help="run engines and write one rerun recording side by side")
    t.add_argument("scenario")
    t.add_argument("--engines", nargs="+", choices=ENGINES, default=None)
    t.add_argument("--variant", "-v", default=None)
    t.add_argument("--set", "-s", action="append", default=[], metavar="KEY=VALUE",
                   help="dotted spec keys only (engine settings differ per engine)")
    t.add_argument("-o", "--output", required=True, metavar="FILE.rrd")
    t.add_argument("--watch", action="store_true",
                   help="the plain side-by-side trace (bodies, energy, penetration) without the diagnosis")
    t.add_argument("--phase", type=_phase_value, default=0.0, metavar="F",
                   help="step phase 0 <= F < 1 (start moved back along the free flight by F dt; dt from the spec, "
                        "e.g. --set scenario.dt=...)")
    t.add_argument("--timeout", type=_seconds, default=DEFAULT_TIMEOUT_S, metavar="SECONDS", help=timeout_help)
    t.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    t.set_defaults(func=cmd_trace)

    e = sub.add_parser("engines", help="engines, versions, capabilities and settings")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_engines)

    b = sub.add_parser("bench", help="benchmarks: runner overhead, or reference vs pybullet cost")
    b.add_argument("kind", choices=["overhead", "cost", "isolation"])
    b.add_argument("--engines", nargs="+", choices=ENGINES, default=None)
    b.add_argument("--repeats", type=_int_in(1, MAX_REPEATS), default=5)
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)

    sw = sub.add_parser("sweep", help="accuracy-vs-cost sweep of a suite (suites/*.toml) into results/sweeps/")
    sw.add_argument("--suite", default="nightly", help="suite name under suites/ or path to a suite file (default nightly)")
    sw.add_argument("--engines", nargs="+", choices=ENGINES, default=None, help="only these of the suite's engines")
    sw.add_argument("--scenarios", nargs="+", default=None, help="only these of the suite's scenario ids")
    sw.add_argument("--jobs", type=_int_in(1, MAX_JOBS), default=1, help="runs at once (timings then compete for cores)")
    sw.add_argument("--executor", choices=["serial", "process", "dask"], default=None,
                    help="default: process (worker processes under a watchdog); serial runs in this process, "
                         "without isolation; dask: points as Dask tasks (docs/SWEEPS.md)")
    sw.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="with --executor dask: join the cluster of this Dask scheduler (e.g. tcp://host:8786); "
                         "default: a local cluster of --jobs workers")
    sw.add_argument("--timeout", type=_seconds, default=None, metavar="SECONDS",
                    help="wall-clock budget per run in seconds (default: the suite's timeout_s)")
    sw.add_argument("--resume", action=argparse.BooleanOptionalAction, default=None,
                    help="default: resume an unfinished sweep of the same suite file, points and commit; "
                         "--resume also across commits; --no-resume always starts afresh")
    sw.add_argument("--out", default=None, metavar="DIR", help="sweeps root (default results/sweeps)")
    sw.set_defaults(func=cmd_sweep)

    lm = sub.add_parser("limits", help="breaking point: where a scene stops holding as one parameter moves")
    lm.add_argument("scenario", help="scenario id (family.name) or path to a spec file")
    lm.add_argument("--engine", "-e", required=True, choices=ENGINES)
    lm.add_argument("--variant", "-v", default=None)
    lm.add_argument("--param", required=True, metavar="KEY",
                    help="engine setting (dt, iterations) or dotted spec key (body[0].velocity[0], body[1].mass)")
    lm.add_argument("--range", nargs=2, required=True, metavar=("LO", "HI"))
    lm.add_argument("--phases", type=int, default=1, metavar="N",
                    help="a value holds only if it holds in all N step phases (default 1)")
    lm.add_argument("--tol", type=float, default=0.05, metavar="REL",
                    help="relative width of the final bracket (default 0.05)")
    lm.add_argument("--check", action="append", default=None, metavar="METRIC",
                    help="only checks of this metric count (repeatable; stability always counts)")
    lm.add_argument("--max", action="append", default=None, metavar="METRIC=VALUE",
                    help="extra criterion: the metric must stay <= VALUE (e.g. energy_gain=0.01); repeatable")
    lm.add_argument("--set", "-s", action="append", default=[], metavar="KEY=VALUE",
                    help="fixed engine setting or dotted spec key for every run of the search")
    lm.add_argument("--out", default=None, metavar="DIR", help="sweeps root (default results/sweeps)")
    lm.add_argument("--json", action="store_true",
                    help="print one JSON object (limit, bracket, failed_check, runs, cpu_s, ...) on stdout")
    lm.set_defaults(func=cmd_limits)

    rp = sub.add_parser("report", help="one self-contained HTML page from stored sweep and check results")
    rp.add_argument("--results-dir", default=None, metavar="DIR", help="default results/")
    rp.add_argument("--out", default=None, metavar="FILE.html", help="default <results-dir>/report.html")
    rp.add_argument("--suites", nargs="+", default=None, help="only these suites' sweep rows")
    rp.add_argument("--target", type=_positive_float, default=None,
                    help="accuracy target for scenarios whose primary metric has no [[check]] max")
    rp.add_argument("--fail-on-regression", action="store_true",
                    help="exit 3 when a regression beyond noise is flagged (for a nightly pipeline)")
    rp.set_defaults(func=cmd_report)

    mo = sub.add_parser("models", help="the reference models: what each takes, its params and metrics")
    mo.add_argument("name", nargs="?", default=None, help="one model (default: all)")
    mo.add_argument("--json", action="store_true", help="print the declarations as JSON")
    mo.set_defaults(func=cmd_models)

    ls = sub.add_parser("list", help="the scenarios in scenarios/")
    ls.set_defaults(func=cmd_list)
    return p


def main(argv: list[str] | None = None) -> int:
    from harness.execute import register_env_adapters

    register_env_adapters()
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except SpecError as e:
        for line in e.errors:
            print(f"error: {line}", file=sys.stderr)
        return 2
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
