"""The listing commands: ``engines``, ``models`` and ``list``."""

from __future__ import annotations

import argparse
import json

from physbench.contract.spec import SpecError
from physbench.harness.cli.common import UsageError, _fmt


def cmd_engines(args: argparse.Namespace) -> int:
    from physbench.adapters import ENGINES, get_adapter

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


def cmd_models(args: argparse.Namespace) -> int:
    """The reference models' declarations (the same text as docs/MODELS.md)."""
    from physbench.harness.references import MODELS, describe

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
    from physbench.contract.scene import load_scene, scenario_ids

    for sid in scenario_ids():
        try:
            s = load_scene(sid)
            print(f"{sid:40s} {','.join(s.tags):20s} variants: {', '.join(s.variant_names) or '-'}")
        except SpecError as e:
            print(f"{sid:40s} INVALID: {e.errors[0]}")
    return 0

