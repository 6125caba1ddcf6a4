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
import os
import sys

from physbench.contract.spec import SpecError
from physbench.harness.cli.bench import cmd_bench
from physbench.harness.cli.common import (
    MAX_JOBS,
    MAX_RECORD_EVERY,
    MAX_REPEATS,
    UsageError,
    _int_in,
    _phase_value,
    _positive_float,
    _seconds,
)
from physbench.harness.cli.info import cmd_engines, cmd_list, cmd_models
from physbench.harness.cli.jobs import cmd_check, cmd_limits, cmd_report, cmd_sweep
from physbench.harness.cli.run import cmd_run
from physbench.harness.cli.trace import cmd_trace

# build_parser binds each subcommand to the cmd_* name in this module at
# call time, so a patched harness.cli.cmd_* is what runs
# (tests/test_fuzz.py::test_cli_argument_lists).


def build_parser() -> argparse.ArgumentParser:
    from physbench.adapters import engine_names
    from physbench.harness.execute import DEFAULT_TIMEOUT_S

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

    b = sub.add_parser("bench", help="benchmarks: runner overhead, reference vs pybullet cost, reference scaling, "
                                     "reference compile time (cold and warm start)")
    b.add_argument("kind", choices=["overhead", "cost", "isolation", "scaling", "compile"])
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
    from physbench.harness.execute import register_env_adapters

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
    except BrokenPipeError:
        # the reader went away (`physbench list | head`): stop quietly, as
        # other Unix tools do; stdout is pointed at devnull so that the
        # interpreter's final flush does not raise again
        # (tests/test_cli.py::test_a_closed_pipe_is_not_a_traceback)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a killed writer

