"""``physbench`` command line: the user's three jobs.

    physbench run SCENARIO|FILE [--engine E] [--variant V] [--set k=v]... [--json]
    physbench check [SCENARIO|FILE|DIR ...] [--engines ...] [--tags ...] [--set [E:]k=v]... [--junit FILE] [--traces DIR]
                    [--ensemble N [--sigma M] [--threshold M]]
    physbench trace SCENARIO|FILE [--engines ...] [--variant V] [--set [E:]k=v]... [--watch] -o FILE.rrd
    physbench validate FILE|SCENARIO [--variant V] [--engines ...] [--json]
    physbench limits SCENARIO|FILE --engine E --param KEY --range LO HI [--phases N] [--tol REL] [--json]
    physbench engines [--json]
    physbench models [NAME] [--json]
    physbench ensemble SCENARIO|FILE [--engine E] [--n N] [--sigma M] [--seed S] [--threshold M] [--json]
    physbench consensus SCENARIO|FILE [--engines ...] [--json]
    physbench list
    physbench compile [--jobs N]

``--results-dir DIR`` (check, sweep, limits, report) and the
``PHYSBENCH_RESULTS`` variable name the results directory; by default it is
``./results`` under the working directory (harness/results.py).

``--set`` takes either an engine setting (``dt=0.002``, ``integrator=rk4``) or a
dotted key path into the spec (``material.default.restitution=0.5``,
``body[0].velocity=[3,0,0]``).  Values are TOML (``true``, ``1e-3``,
``"rk4"``) or a fraction (``dt=1/240``); a bare word is a string.  ``check``
and ``trace`` also take ``ENGINE:KEY=VALUE``, one engine's setting
(``mujoco:impratio=10``).

``run`` evaluates the scene's checks that apply to the run as ``check``
does (making the step-phase and ``@dt=...`` runs they need) and lists them.

Exit codes: 0 success, 1 a check failed unexpectedly (FAIL, XPASS, ERROR;
check and run) or the run's status is not ok (run), 2 bad input (spec,
settings, arguments, unknown scenario ids), 5 nothing to check (check: no
check applied to any scene, each scene's reason printed).
"""

from __future__ import annotations

import argparse
import os
import sys

from physbench.adapters import engine_names
from physbench.contract.spec import SpecError
from physbench.harness import results
from physbench.harness.cli.bench import cmd_bench
from physbench.harness.cli.common import (
    MAX_JOBS,
    MAX_RECORD_EVERY,
    MAX_REPEATS,
    UsageError,
    int_in,
    output_dir,
    phase_value,
    positive_float,
    timeout_seconds,
)
from physbench.harness.cli.compile import cmd_compile
from physbench.harness.cli.info import cmd_engines, cmd_list, cmd_models
from physbench.harness.cli.ensemble import cmd_consensus, cmd_ensemble
from physbench.harness.cli.jobs import cmd_check, cmd_limits, cmd_report, cmd_sweep
from physbench.harness.cli.run import cmd_run
from physbench.harness.cli.trace import cmd_trace
from physbench.harness.cli.validate import cmd_validate
from physbench.harness.execute import DEFAULT_TIMEOUT_S, register_env_adapters

# build_parser binds each subcommand to the cmd_* name in this module at
# call time, so a patched harness.cli.cmd_* is what runs
# (tests/test_fuzz.py::test_cli_argument_lists).


def build_parser() -> argparse.ArgumentParser:
    ENGINES = engine_names()  # the shipped engines, entry-point plug-ins and any named in PHYSBENCH_ADAPTERS
    results_help = "results directory (default ./results, or $PHYSBENCH_RESULTS)"
    timeout_help = f"wall-clock budget per run in seconds (default {DEFAULT_TIMEOUT_S:g}); a run past it is 'timeout'"
    p = argparse.ArgumentParser(prog="physbench", description="Validation and benchmark harness for rigid-body physics engines.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="one run of one scenario on one engine")
    r.add_argument("scenario", help="scenario id (family.name) or path to a spec file")
    r.add_argument("--engine", "-e", default="reference", choices=ENGINES)
    r.add_argument("--variant", "-v", default=None)
    r.add_argument("--set", "-s", action="append", default=[], metavar="KEY=VALUE")
    r.add_argument("--json", action="store_true", help="print the result row as one JSON object")
    r.add_argument("--record-every", type=int_in(1, MAX_RECORD_EVERY), default=1,
                   help="record every N >= 1 steps (default 1)")
    r.add_argument("--save", metavar="FILE.parquet", help="append the result row to a Parquet file")
    r.add_argument("--phase", type=phase_value, default=0.0, metavar="F",
                   help="step phase 0 <= F < 1: start moved back along the free flight by F dt, to reproduce a "
                        "point of a phase sweep (scenes that start in free flight only)")
    r.add_argument("--timeout", type=timeout_seconds, default=DEFAULT_TIMEOUT_S, metavar="SECONDS", help=timeout_help)
    r.set_defaults(func=cmd_run)

    c = sub.add_parser("check", help="CI conformance: every scenario's checks on every engine")
    c.add_argument("paths", nargs="*", metavar="SCENARIO|FILE|DIR",
                   help="scenario ids, spec files or folders of spec files (anywhere); default all of scenarios/")
    c.add_argument("--engines", nargs="+", choices=ENGINES, default=None)
    c.add_argument("--tags", nargs="+", default=None)
    c.add_argument("--scenarios", nargs="+", default=None, metavar="SCENARIO|FILE|DIR",
                   help="only these: scenario ids, spec files or folders of spec files")
    c.add_argument("--junit", default=None, metavar="FILE.xml")
    c.add_argument("--jobs", type=int_in(1, MAX_JOBS), default=1, help="worker processes (default 1)")
    c.add_argument("--executor", choices=["process", "dask"], default="process",
                   help="process (default): worker processes under a watchdog; dask: runs as Dask tasks "
                        "(docs/SWEEPS.md)")
    c.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="with --executor dask: join the cluster of this Dask scheduler (e.g. tcp://host:8786); "
                        "default: a local cluster of --jobs workers")
    c.add_argument("--timeout", type=timeout_seconds, default=DEFAULT_TIMEOUT_S, metavar="SECONDS", help=timeout_help)
    c.add_argument("--resume", action=argparse.BooleanOptionalAction, default=True,
                   help="resume an unfinished check with the same commit, engines, scenarios, spec files and "
                        "budget (default); --no-resume always starts afresh")
    c.add_argument("--set", "-s", action="append", default=[], metavar="[ENGINE:]KEY=VALUE",
                   help="engine settings for every run: ENGINE:KEY=VALUE for one engine (mujoco:impratio=10), "
                        "KEY=VALUE for a setting every checked engine has (dt=1/240); a check's @dt=... wins")
    c.add_argument("--traces", default=None, metavar="DIR",
                   help="write one diagnosing .rrd per FAIL, XFAIL and ERROR case into DIR (docs/TRACES.md)")
    c.add_argument("--ensemble", type=int_in(2, 100000), default=None, metavar="N",
                   help="also judge predictability: N runs from perturbed starts per scene and engine (the scene's "
                        "[perturbation], or --sigma), the check predictable == true (docs/METRICS.md)")
    c.add_argument("--sigma", type=float, default=None, metavar="M",
                   help="with --ensemble: position noise (m, standard deviation) over the scene's [perturbation]")
    c.add_argument("--threshold", type=float, default=None, metavar="M",
                   help="with --ensemble: the largest final spread (m) of a predictable scene (default the "
                        "scene's, else 0.01)")
    c.add_argument("--results-dir", default=None, metavar="DIR", help=results_help)
    c.set_defaults(func=cmd_check)

    t = sub.add_parser("trace", help="run engines and write one rerun recording side by side")
    t.add_argument("scenario")
    t.add_argument("--engines", nargs="+", choices=ENGINES, default=None)
    t.add_argument("--variant", "-v", default=None)
    t.add_argument("--set", "-s", action="append", default=[], metavar="[ENGINE:]KEY=VALUE",
                   help="ENGINE:KEY=VALUE sets one engine's setting (mujoco:impratio=10); KEY=VALUE a setting every "
                        "traced engine has (dt=1/240) or a dotted spec key (material.default.restitution=0.5)")
    t.add_argument("-o", "--output", required=True, metavar="FILE.rrd")
    t.add_argument("--watch", action="store_true",
                   help="the plain side-by-side trace (bodies, energy, penetration) without the diagnosis")
    t.add_argument("--phase", type=phase_value, default=0.0, metavar="F",
                   help="step phase 0 <= F < 1 (start moved back along the free flight by F dt; dt from the spec, "
                        "e.g. --set scenario.dt=...)")
    t.add_argument("--timeout", type=timeout_seconds, default=DEFAULT_TIMEOUT_S, metavar="SECONDS", help=timeout_help)
    t.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    t.set_defaults(func=cmd_trace)

    va = sub.add_parser("validate", help="dry run of one spec: the compiled scene, initial contacts, the model's "
                                         "predictions and which checks apply to which engines, without stepping")
    va.add_argument("scenario", help="scenario id (family.name) or path to a spec file")
    va.add_argument("--variant", "-v", default=None)
    va.add_argument("--engines", nargs="+", default=None, help="the engines to plan the checks for (default all)")
    va.add_argument("--json", action="store_true", help="print the report as one JSON object")
    va.set_defaults(func=cmd_validate)

    e = sub.add_parser("engines", help="engines, versions, capabilities and settings")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_engines)

    b = sub.add_parser("bench", help="benchmarks: runner overhead, reference vs pybullet cost, reference scaling, "
                                     "reference compile time (cold and warm start), the cost-to-target table's "
                                     "points timed again side by side (targets)")
    b.add_argument("kind", choices=["overhead", "cost", "isolation", "scaling", "compile", "targets"])
    b.add_argument("--results-dir", default=None, metavar="DIR",
                   help="targets: the sweep results to read (default ./results, or $PHYSBENCH_RESULTS)")
    b.add_argument("--scenarios", nargs="+", default=None, help="targets: only these scenario ids")
    b.add_argument("--engines", nargs="+", choices=ENGINES, default=None)
    b.add_argument("--repeats", type=int_in(1, MAX_REPEATS), default=5)
    b.add_argument("--json", action="store_true")
    b.set_defaults(func=cmd_bench)

    sw = sub.add_parser("sweep", help="accuracy-vs-cost sweep of a suite (suites/*.toml) into results/sweeps/")
    sw.add_argument("--suite", default="nightly", help="suite name under suites/ or path to a suite file (default nightly)")
    sw.add_argument("--engines", nargs="+", choices=ENGINES, default=None, help="only these of the suite's engines")
    sw.add_argument("--scenarios", nargs="+", default=None, help="only these of the suite's scenario ids")
    sw.add_argument("--jobs", type=int_in(1, MAX_JOBS), default=1, help="runs at once (timings then compete for cores)")
    sw.add_argument("--executor", choices=["serial", "process", "dask"], default=None,
                    help="default: process (worker processes under a watchdog); serial runs in this process, "
                         "without isolation; dask: points as Dask tasks (docs/SWEEPS.md)")
    sw.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="with --executor dask: join the cluster of this Dask scheduler (e.g. tcp://host:8786); "
                         "default: a local cluster of --jobs workers")
    sw.add_argument("--timeout", type=timeout_seconds, default=None, metavar="SECONDS",
                    help="wall-clock budget per run in seconds (default: the suite's timeout_s)")
    sw.add_argument("--resume", action=argparse.BooleanOptionalAction, default=None,
                    help="default: resume an unfinished sweep of the same suite file, points and commit; "
                         "--resume also across commits; --no-resume always starts afresh")
    sw.add_argument("--out", default=None, metavar="DIR", help="sweeps root (default <results-dir>/sweeps)")
    sw.add_argument("--results-dir", default=None, metavar="DIR", help=results_help)
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
    lm.add_argument("--out", default=None, metavar="DIR", help="sweeps root (default <results-dir>/sweeps)")
    lm.add_argument("--results-dir", default=None, metavar="DIR", help=results_help)
    lm.add_argument("--json", action="store_true",
                    help="print one JSON object (limit, bracket, failed_check, runs, cpu_s, ...) on stdout")
    lm.set_defaults(func=cmd_limits)

    rp = sub.add_parser("report", help="one self-contained HTML page from stored sweep and check results")
    rp.add_argument("--results-dir", default=None, metavar="DIR", help=results_help)
    rp.add_argument("--out", default=None, metavar="FILE.html", help="default <results-dir>/report.html")
    rp.add_argument("--suites", nargs="+", default=None, help="only these suites' sweep rows")
    rp.add_argument("--target", type=positive_float, default=None,
                    help="accuracy target for scenarios whose primary metric has no [[check]] max")
    rp.add_argument("--fail-on-regression", action="store_true",
                    help="exit 3 when a regression beyond noise is flagged (for a nightly pipeline)")
    rp.set_defaults(func=cmd_report)

    en = sub.add_parser("ensemble", help="predictability: N runs from perturbed starts, their outcome spread")
    en.add_argument("scenario", help="scenario id (family.name) or path to a spec file")
    en.add_argument("--engine", "-e", default="reference", choices=ENGINES)
    en.add_argument("--variant", "-v", default=None)
    en.add_argument("--set", "-s", action="append", default=[], metavar="KEY=VALUE", help="an engine setting")
    en.add_argument("--n", type=int_in(2, 1000), default=None, help="members (default: the scene's [perturbation])")
    en.add_argument("--sigma", type=float, default=None, metavar="M", help="position noise per component (m)")
    en.add_argument("--sigma-velocity", type=float, default=None, metavar="M/S")
    en.add_argument("--sigma-orientation", type=float, default=None, metavar="RAD")
    en.add_argument("--seed", type=int_in(0, 2**32 - 1), default=None)
    en.add_argument("--threshold", type=float, default=None, metavar="M",
                    help="largest final spread of a predictable scene (m; default 0.01)")
    en.add_argument("--jobs", "-j", type=int_in(1, MAX_JOBS), default=1)
    en.add_argument("--no-batch", dest="batch", action="store_false",
                    help="one run per member even where the engine steps many worlds in one call (MJX)")
    en.add_argument("--json", action="store_true")
    en.add_argument("--timeout", type=timeout_seconds, default=DEFAULT_TIMEOUT_S, metavar="SECONDS", help=timeout_help)
    en.set_defaults(func=cmd_ensemble)

    cs = sub.add_parser("consensus", help="how far apart the engines' converged runs of a scene are")
    cs.add_argument("scenario", help="scenario id (family.name) or path to a spec file")
    cs.add_argument("--engines", nargs="+", default=list(ENGINES), choices=ENGINES)
    cs.add_argument("--variant", "-v", default=None)
    cs.add_argument("--jobs", "-j", type=int_in(1, MAX_JOBS), default=1)
    cs.add_argument("--json", action="store_true")
    cs.add_argument("--timeout", type=timeout_seconds, default=DEFAULT_TIMEOUT_S, metavar="SECONDS", help=timeout_help)
    cs.set_defaults(func=cmd_consensus)

    mo = sub.add_parser("models", help="the reference models: what each takes, its params and metrics")
    mo.add_argument("name", nargs="?", default=None, help="one model (default: all)")
    mo.add_argument("--json", action="store_true", help="print the declarations as JSON")
    mo.set_defaults(func=cmd_models)

    ls = sub.add_parser("list", help="the shipped scenarios with tags and variants")
    ls.set_defaults(func=cmd_list)

    co = sub.add_parser("compile", help="compile the reference engine's kernels into the on-disk cache ahead of a "
                                        "first run (python -m physbench.engine)")
    co.add_argument("--jobs", type=int, default=None, choices=(1, 2),
                    help="processes compiling at once (default: 2 where two cores or more may be used)")
    co.set_defaults(func=cmd_compile)
    return p


def main(argv: list[str] | None = None) -> int:
    register_env_adapters()
    args = build_parser().parse_args(argv)
    # --results-dir, for this command (results.results_dir reads it)
    previous = results.set_results_dir(None)
    try:
        if getattr(args, "results_dir", None) is not None:
            results.set_results_dir(output_dir("--results-dir", args.results_dir))
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
    finally:
        results.set_results_dir(previous)

