"""The listing commands: ``engines``, ``models`` and ``list``."""

from __future__ import annotations

import argparse
import json

from physbench.adapters import PLUGIN_PROBLEMS, engine_names, engine_origin, get_adapter
from physbench.contract.models import PLUGIN_PROBLEMS as MODEL_PLUGIN_PROBLEMS
from physbench.contract.scene import load_scene, scenario_ids
from physbench.contract.spec import SpecError
from physbench.contract.xfail import Xfail, shipped_xfails
from physbench.harness.cli.common import UsageError, fmt_value
from physbench.harness.references import MODELS, describe, judge_lines


def _xfail_ranges(engine: str, version: str, shipped: dict) -> str:
    """Whether ``version`` lies inside the ranges the shipped xfails of
    ``engine`` were measured for (contract/xfail.py)."""
    parts = []
    for (measured, rng), n in sorted(shipped.get(engine, {}).items()):
        inside = Xfail("", measured, rng).covers(version)
        verdict = {True: "inside", False: "OUTSIDE: run as plain checks", None: "not comparable"}[inside]
        parts.append(f"{n} measured on {measured or '?'} ({rng or 'any version'}): {verdict}")
    return "; ".join(parts) or "no shipped xfails"


def cmd_engines(args: argparse.Namespace) -> int:
    """Every registered engine (shipped, plug-ins, run time) with its
    version, where it comes from, whether that version is inside the ranges
    the shipped known limitations were measured for, capabilities and
    settings; plug-ins that failed to load are listed with their error."""
    shipped = shipped_xfails()
    caps = []
    for name in engine_names():
        try:
            c = get_adapter(name).capabilities().as_dict()
        except Exception as e:  # a broken adapter module is reported, not fatal
            c = {"engine": name, "available": False, "error": f"{type(e).__name__}: {e}"}
        c["origin"] = engine_origin(name)
        if "error" not in c:
            c["xfail_ranges"] = _xfail_ranges(name, str(c.get("version", "")), shipped)
        caps.append(c)
    if args.json:
        print(json.dumps(caps, indent=2, default=str))
        return 0
    from rich.console import Console
    from rich.table import Table

    t = Table("engine", "version", "from", "available", "shipped xfails' versions", "dims", "shapes", "effects",
              "settings (default)")
    for c in caps:
        if "error" in c:
            t.add_row(c["engine"], "", c["origin"], "no", "", "", "", "", c["error"])
            continue
        t.add_row(c["engine"], c["version"], c["origin"], "yes" if c["available"] else "no", c["xfail_ranges"],
                  str(c["dimensions"]), ", ".join(c["shapes"]), ", ".join(c["effects"]),
                  ", ".join(f"{k}={fmt_value(v['default']) if v['default'] is not None else 'scene'}"
                            for k, v in c["settings"].items()))
    Console(width=240).print(t)
    for line in PLUGIN_PROBLEMS:
        print(f"plug-in: {line}")
    return 0


def cmd_models(args: argparse.Namespace) -> int:
    """The reference models' declarations (the same text as docs/MODELS.md)."""
    if args.name is not None and args.name not in MODELS:
        raise UsageError(f"models: unknown model {args.name!r}; known: {', '.join(sorted(MODELS))}")
    descs = describe(args.name)
    if args.json:
        print(json.dumps(descs if args.name is None else descs[0]))
        return 0
    for d in descs:
        if "error" in d:
            print(f"{d['name']} (from {d['origin']}): cannot be loaded: {d['error']}")
            print()
            continue
        print(f"{d['name']} (from {d['origin']}): {d['summary']}")
        print(f"  takes: {d['takes']}")
        for p in d["params"]:
            default = "-" if p["default"] is None else repr(p["default"])
            print(f"  param {p['name']} ({p['type']}, default {default}): {p['meaning']}")
        print(f"  metrics (primary {d['primary']}):")
        for m, meaning in d["produces"].items():
            print(f"    {m}: {meaning}")
        print()
    if args.name is None:
        print("Judging a scene without a model:")
        for line in judge_lines():
            print(f"  {line}".rstrip())
        print()
    for line in MODEL_PLUGIN_PROBLEMS:
        print(f"plug-in: {line}")
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    for sid in scenario_ids():
        try:
            s = load_scene(sid)
            print(f"{sid:40s} {','.join(s.tags):20s} variants: {', '.join(s.variant_names) or '-'}")
        except SpecError as e:
            print(f"{sid:40s} INVALID: {e.errors[0]}")
    return 0

