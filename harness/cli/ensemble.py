"""``physbench ensemble``: a scene's predictability on one engine -- N runs
from perturbed starts (harness/ensemble.py), their outcome spread and the
``predictable`` verdict.  Exit 0 predictable, 1 not (or undefined: a member
not ok), 2 bad input."""

from __future__ import annotations

import argparse
import json
import sys

from physbench.harness.cli.common import UsageError, _split_sets


def cmd_ensemble(args: argparse.Namespace) -> int:
    from physbench.adapters import get_adapter
    from physbench.contract.scene import load_scene
    from physbench.harness.ensemble import Perturbation, run_ensemble

    cls = get_adapter(args.engine)
    settings, overrides = _split_sets(args.set, set(cls.capabilities().settings))
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
                       timeout_s=args.timeout)
    if args.json:
        sys.stdout.write(json.dumps(out) + "\n")
    else:
        print(f"{scene.id} on {args.engine}: {out['members_ok']} of {out['members']} members ok")
        for k, unit in (("final_spread", "m"), ("orientation_spread", "rad"), ("start_spread", "m"),
                        ("amplification", ""), ("event_spread", "events")):
            if out.get(k) is not None:
                print(f"  {k}: {out[k]:.4g} {unit}".rstrip())
        verdict = {True: "predictable", False: "NOT predictable", None: "undefined"}[out["predictable"]]
        print(f"  {verdict}: {out['why']}")
    return 0 if out["predictable"] is True else 1
