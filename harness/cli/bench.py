"""``physbench bench``: runner overhead, worker isolation cost, the
reference engine's cost against pybullet, and its compile time."""

from __future__ import annotations

import argparse
import json
import sys

from physbench.harness import bench
from physbench.harness.bench_targets import targets
from physbench.harness.report.cost import cost_to_target
from physbench.harness.report.loading import load_results


def cmd_bench(args: argparse.Namespace) -> int:
    import contextlib

    out = sys.stdout
    # with --json, stdout carries the JSON only: the tables go to stderr
    with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
        if args.kind == "isolation":
            # physbench's benchmark of itself stays off the start of every other command
            from physbench.harness.selfbench.executors import bench_isolation

            rows = [bench_isolation(runs=max(3, 10 * args.repeats), engine=(args.engines or ["mujoco"])[0])]
            bench.print_rows(rows, "per-run cost of running in a worker process (wall ms per run, medians): in "
                                   "this process, in a reused worker, in a fresh worker per run")
        elif args.kind == "overhead":
            # the reference engine is left out unless asked for: its steps cost
            # milliseconds, so its overhead is lost in noise and takes minutes
            load0 = _load()
            rows = bench.overhead(args.engines or ["mujoco", "pymunk", "pybullet", "rapier", "box2d"],
                                  repeats=args.repeats)
            bench.print_rows(rows, "runner recording every step vs bare loops: bare = the engine's step call and its "
                                   "cheapest read of every body's state in a Python loop (ratio = runner / bare), "
                                   "api = the step call alone, fast = the adapter's fastest stepping (CPU time, "
                                   f"medians of {args.repeats} repeats timed in alternating order; ratio_lo/hi: the "
                                   "extreme runner / bare of one repeat; spreads: (max - min) / median)")
            print(f"load average (1, 5, 15 min) before: {load0}, after: {_load()}")
        elif args.kind == "compile":
            # fresh processes, each on a temporary compiled-kernel cache
            # (--engines and --repeats do not apply: one cold start is minutes)
            rows = bench.compile_time()
            bench.print_rows(rows, "reference engine start in fresh processes, on an empty compiled-kernel cache "
                                   "(cold) and on the cache it filled (warm): wall s, CPU s (with workers), s to "
                                   "the first step, functions numba compiled; for a build-and-step process, "
                                   "its first scenario's parts: s to import, s to build (jit_s of it: loading or "
                                   "compiling kernels), compiled libraries loaded from the cache")
        elif args.kind == "targets":
            try:
                rows = targets(cost_to_target(load_results(args.results_dir)), repeats=args.repeats,
                               scenarios=args.scenarios)
            except ValueError as e:
                print(f"physbench bench targets: {e}", file=sys.stderr)
                return 2
            bench.print_rows(rows, "the cost-to-target table's points timed again in one process: per scenario "
                                   "the reference's cheapest point reaching the target and the cheapest other "
                                   f"engine's, fresh runs, {args.repeats} repeats in alternating order after one "
                                   "untimed run each (ms CPU per simulated second, medians; ratio_lo/hi: the "
                                   "extreme ratios of one repeat; table_ratio: the sweep's)")
        elif args.kind == "scaling":
            sc = bench.step_scaling()
            rows = sc["rows"]
            bench.print_rows(rows, "reference engine: n spheres dropped on a plane, build CPU s and CPU us per step "
                                   "by stage (40 steps)")
            print("fitted exponents against n: " + ", ".join(f"{k} {v:.2f}" for k, v in sc["exponents"].items()))
        else:
            rows = bench.cost(repeats=args.repeats)
            bench.print_rows(rows, "reference engine vs pybullet (maximal coordinates), same dt and iterations; "
                                   "MuJoCo, pymunk, Rapier and Box2D at their defaults (NaN: scene not supported)")
            ok = [r for r in rows if r["scene"].startswith("spheres_") and r["reference_broadphase_us_per_step"] == r["reference_broadphase_us_per_step"]]
            if len(ok) >= 2:
                k = bench.fit_exponent([r["bodies"] for r in ok], [r["reference_broadphase_us_per_step"] for r in ok])
                print(f"reference broad phase: cost ~ n^{k:.2f} between n = {ok[0]['bodies']} and {ok[-1]['bodies']}")
            sc = bench.broadphase_scaling(repeats=args.repeats)
            bench.print_rows(sc["rows"], "broad phase alone on constant-density sphere clouds, a new cloud at every "
                                         "call (us per call, medians): the stage's path (kept order from the cloud "
                                         "before; fresh), sap_pairs, all pairs")
            ns = [r["n"] for r in sc["rows"]]
            ex = sc["exponents"]
            print(f"broad phase on constant-density clouds between {ns[0]} and {ns[-1]}: the stage ~ "
                  f"n^{ex['stage']:.2f} (fresh order n^{ex['stage_fresh']:.2f}), sap_pairs n^{ex['sap']:.2f} "
                  f"(n log n: {ex['n_log_n']:.2f}; all pairs: {ex['brute']:.2f})")
            b = bench.build_cost()
            print(f"reference build of {b['n']} spheres: {b['build_s']:.3f} s CPU, peak {b['peak_mb']:.1f} MB "
                  f"of Python allocations (median of 3)")
    if args.json:
        out.write(json.dumps(rows, default=str) + "\n")
        out.flush()
    return 0


def _load() -> str:
    """The machine's load averages, or 'n/a' where the OS has none."""
    import os

    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except (AttributeError, OSError):
        return "n/a"
