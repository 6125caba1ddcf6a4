"""``physbench ensemble``: a scene's predictability on one engine -- N runs
from perturbed starts (harness/ensemble.py), their outcome spread and the
``predictable`` verdict.  Exit 0 predictable, 1 not (or undefined: a member
not ok), 2 bad input.

``physbench consensus``: the engines' converged runs of a scene (each at
its finest self-consistency step, harness/consensus.py) and the largest
distance between two of them.  Exit 0 when at least two engines ran ok."""

from __future__ import annotations

import argparse
import json
import sys

from physbench.adapters import get_adapter
from physbench.contract.scene import load_scene
from physbench.harness.cli.common import UsageError, split_sets
from physbench.harness.consensus import run_consensus
from physbench.harness.ensemble import Perturbation, run_ensemble


def cmd_ensemble(args: argparse.Namespace) -> int:
    cls = get_adapter(args.engine)
    settings, overrides = split_sets(args.set, set(cls.capabilities().settings))
    if overrides:
        raise UsageError(f"--set {', '.join(overrides)}: an ensemble takes engine settings only; "
                         "spec keys go in the spec file (or a variant)")
    scene = load_scene(args.scenario, args.variant)  # SpecError: exit 2
    over = {"n": args.n, "position": args.sigma, "velocity": args.sigma_velocity,
            "orientation": args.sigma_orientation, "seed": args.seed, "threshold": args.threshold}
    try:
        p = Perturbation.of_scene(scene, **over)
    except ValueError as e:
        hint = "" if scene.perturbation else f" ({scene.id} has no [perturbation] block: give --sigma)"
        raise UsageError(f"{e}{hint}") from None
    out = run_ensemble(args.scenario, args.engine, p, variant=args.variant, settings=settings, jobs=args.jobs,
                       timeout_s=args.timeout, batch=args.batch)
    if args.json:
        sys.stdout.write(json.dumps(out) + "\n")
    else:
        print(f"{scene.id} on {args.engine}: {out['members_ok']} of {out['members']} members ok")
        if out.get("batch"):
            b = out["batch"]
            print(f"  one batch of {b['worlds']} worlds: {b['us_per_world_step']:.4g} us CPU per world-step")
        for k, unit in (("final_spread", "m"), ("orientation_spread", "rad"), ("start_spread", "m"),
                        ("amplification", ""), ("event_spread", "events")):
            if out.get(k) is not None:
                print(f"  {k}: {out[k]:.4g} {unit}".rstrip())
        verdict = {True: "predictable", False: "NOT predictable", None: "undefined"}[out["predictable"]]
        print(f"  {verdict}: {out['why']}")
    return 0 if out["predictable"] is True else 1


def cmd_consensus(args: argparse.Namespace) -> int:
    load_scene(args.scenario, args.variant)  # SpecError: exit 2
    out = run_consensus(args.scenario, args.engines, variant=args.variant, jobs=args.jobs, timeout_s=args.timeout)
    if args.json:
        sys.stdout.write(json.dumps(out) + "\n")
    else:
        print(f"{out['scenario']}: each engine at dt = {out['dt_fine']:.6g} s, compared by {out['compare']}")
        for eng, (status, msg) in out["runs"].items():
            if status != "ok":
                print(f"  {eng}: {status}: {msg}")
        for p in out["pairs"]:
            print(f"  {p['a']} - {p['b']}: {p['distance']:.4g} m, {p['angle']:.4g} rad ({p['frames']} frames)")
        print(f"  consensus_spread: {out['consensus_spread']:.4g} m")
    return 0 if sum(1 for s, _ in out["runs"].values() if s == "ok") >= 2 else 1
