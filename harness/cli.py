"""``physbench`` command line: the user's three jobs.

    physbench run SCENARIO|FILE [--engine E] [--variant V] [--set k=v]... [--json]
    physbench check [--engines ...] [--tags ...] [--junit FILE] [--traces DIR]
    physbench trace SCENARIO|FILE [--engines ...] [--variant V] [--watch] -o FILE.rrd
    physbench engines [--json]
    physbench list

``--set`` takes either an engine setting (``dt=0.002``, ``integrator=rk4``) or a
dotted key path into the spec (``material.default.restitution=0.5``,
``body[0].velocity=[3,0,0]``).  Values are TOML (``true``, ``1e-3``,
``"rk4"``); a bare word is a string.

Exit codes: 0 success, 1 a check failed (check) or the run's status is not
ok (run), 2 bad input (spec, settings, arguments).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from harness.spec import SpecError, parse_value


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


def cmd_run(args: argparse.Namespace) -> int:
    from adapters import get_adapter
    from harness.runner import run
    from harness.scene import load_scene

    cls = get_adapter(args.engine)
    settings, overrides = _split_sets(args.set, set(cls.capabilities().settings))
    scene = _phase(load_scene(args.scenario, args.variant, overrides), args.phase, settings.get("dt"))
    try:
        result = run(scene, args.engine, settings, record_every=args.record_every)
    except ValueError as e:  # bad setting value
        raise UsageError(str(e)) from None
    if args.phase:
        result.notes.append(f"step phase {args.phase:g}: start moved back along the free flight by "
                            f"{args.phase:g} dt")
    if args.save:
        from harness.results import write_rows

        row = result.row()
        row["phase"] = float(args.phase)  # 0 = the scene as written
        write_rows([row], args.save)
    if args.json:
        sys.stdout.write(json.dumps(result.as_dict(), sort_keys=False) + "\n")
        sys.stdout.flush()
    else:
        _print_result(result)
    return 0 if result.status == "ok" else 1


def _phase(scene, f: float, dt: Any = None):
    """``scene`` shifted to step phase ``f`` (harness/phase.py); a scene
    that does not start in free flight is a usage error naming why."""
    if not f:
        return scene
    from harness.phase import PhaseError, shift_scene

    try:
        h = None if dt is None else float(dt)
    except (TypeError, ValueError):
        raise UsageError(f"--set dt={dt!r}: expected a number of seconds") from None
    try:
        return shift_scene(scene, f, dt=h)
    except PhaseError as e:
        raise UsageError(f"--phase {f:g}: {e}") from None


def _print_result(result) -> None:
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
    from harness.runner import run
    from harness.scene import load_scene
    from harness.trace.contacts import DEFAULT_CAP

    engines = args.engines or list(ENGINES)
    scene = load_scene(args.scenario, args.variant, _split_sets(args.set, set())[1] if args.set else None)
    scene = _phase(scene, args.phase)
    results = []
    for e in engines:
        get_adapter(e)
        results.append(run(scene, e, contact_cap=0 if args.watch else DEFAULT_CAP))
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

    return check_main(engines=args.engines, tags=args.tags, junit=args.junit, scenarios=args.scenarios, jobs=args.jobs,
                      traces=args.traces)


def cmd_bench(args: argparse.Namespace) -> int:
    from harness import bench

    if args.kind == "overhead":
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
        print(json.dumps(rows, default=str))
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from harness.sweep import sweep_main

    return sweep_main(args.suite, engines=args.engines, jobs=args.jobs, executor=args.executor,
                      out_dir=Path(args.out) if args.out else None, resume=args.resume, scenarios=args.scenarios)


def cmd_report(args: argparse.Namespace) -> int:
    from harness.report import report_main

    return report_main(results_dir=Path(args.results_dir) if args.results_dir else None,
                       out=Path(args.out) if args.out else None, suites=args.suites, target=args.target,
                       fail_on_regression=args.fail_on_regression)


def cmd_list(args: argparse.Namespace) -> int:
    from harness.scene import load_scene, scenario_ids

    for sid in scenario_ids():
        try:
            s = load_scene(sid)
            print(f"{sid:40s} {','.join(s.tags):20s} variants: {', '.join(s.variant_names) or '-'}")
        except SpecError as e:
            print(f"{sid:40s} INVALID: {e.errors[0]}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from adapters import ENGINES

    p = argparse.ArgumentParser(prog="physbench", description="Validation and benchmark harness for rigid-body physics engines.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="one run of one scenario on one engine")
    r.add_argument("scenario", help="scenario id (family.name) or path to a spec file")
    r.add_argument("--engine", "-e", default="reference", choices=ENGINES)
    r.add_argument("--variant", "-v", default=None)
    r.add_argument("--set", "-s", action="append", default=[], metavar="KEY=VALUE")
    r.add_argument("--json", action="store_true", help="print the result row as one JSON object")
    r.add_argument("--record-every", type=int, default=1, help="record every N steps (default 1)")
    r.add_argument("--save", metavar="FILE.parquet", help="append the result row to a Parquet file")
    r.add_argument("--phase", type=float, default=0.0, metavar="F",
                   help="step phase 0 <= F < 1: start moved back along the free flight by F dt, to reproduce a "
                        "point of a phase sweep (scenes that start in free flight only)")
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("check", help="CI conformance: every scenario's checks on every engine")
    c.add_argument("--engines", nargs="+", choices=ENGINES, default=None)
    c.add_argument("--tags", nargs="+", default=None)
    c.add_argument("--scenarios", nargs="+", default=None, help="only these scenario ids")
    c.add_argument("--junit", default=None, metavar="FILE.xml")
    c.add_argument("--jobs", type=int, default=1)
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
    t.add_argument("--phase", type=float, default=0.0, metavar="F",
                   help="step phase 0 <= F < 1 (start moved back along the free flight by F dt; dt from the spec, "
                        "e.g. --set scenario.dt=...)")
    t.set_defaults(func=cmd_trace)

    e = sub.add_parser("engines", help="engines, versions, capabilities and settings")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_engines)

    b = sub.add_parser("bench", help="benchmarks: runner overhead, or reference vs pybullet cost")
    b.add_argument("kind", choices=["overhead", "cost"])
    b.add_argument("--engines", nargs="+", choices=ENGINES, default=None)
    b.add_argument("--repeats", type=int, default=5)
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)

    sw = sub.add_parser("sweep", help="accuracy-vs-cost sweep of a suite (suites/*.toml) into results/sweeps/")
    sw.add_argument("--suite", default="nightly", help="suite name under suites/ or path to a suite file (default nightly)")
    sw.add_argument("--engines", nargs="+", choices=ENGINES, default=None, help="only these of the suite's engines")
    sw.add_argument("--scenarios", nargs="+", default=None, help="only these of the suite's scenario ids")
    sw.add_argument("--jobs", type=int, default=1, help="runs at once (timings then compete for cores)")
    sw.add_argument("--executor", choices=["serial", "process"], default=None,
                    help="default: serial for --jobs 1, a process pool otherwise")
    sw.add_argument("--resume", action=argparse.BooleanOptionalAction, default=None,
                    help="default: resume an unfinished sweep of the same suite file, points and commit; "
                         "--resume also across commits; --no-resume always starts afresh")
    sw.add_argument("--out", default=None, metavar="DIR", help="sweeps root (default results/sweeps)")
    sw.set_defaults(func=cmd_sweep)

    rp = sub.add_parser("report", help="one self-contained HTML page from stored sweep and check results")
    rp.add_argument("--results-dir", default=None, metavar="DIR", help="default results/")
    rp.add_argument("--out", default=None, metavar="FILE.html", help="default <results-dir>/report.html")
    rp.add_argument("--suites", nargs="+", default=None, help="only these suites' sweep rows")
    rp.add_argument("--target", type=float, default=None,
                    help="accuracy target for scenarios whose primary metric has no [[check]] max")
    rp.add_argument("--fail-on-regression", action="store_true",
                    help="exit 3 when a regression beyond noise is flagged (for a nightly pipeline)")
    rp.set_defaults(func=cmd_report)

    ls = sub.add_parser("list", help="the scenarios in scenarios/")
    ls.set_defaults(func=cmd_list)
    return p


def main(argv: list[str] | None = None) -> int:
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
