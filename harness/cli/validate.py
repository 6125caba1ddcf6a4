"""``physbench validate``: a dry run of one spec, without stepping.

It loads and compiles the scene as every command does (a bad spec, a buried
start, a misspelt engine in a check: exit 2 with the errors) and reports
what a run would start from: the compiled scene (bodies, statics, springs,
materials), the shapes touching or overlapping at the start (measured with
the harness's geometry, contract/geometry/start.py), the reference model's
predictions (harness/references/predict.py), the engines that cannot model
the scene and why, and which checks apply to which engines, base scene and
variants (the same rules as ``physbench check``).  Exit 0 when the spec is
valid (tests/test_cli.py::test_validate_reports_without_stepping).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from physbench.adapters import engine_names, get_adapter
from physbench.contract.geometry.start import CONTACT_GAP, initial_contacts
from physbench.contract.scene import load_scene, resolve_scenario
from physbench.contract.spec import SpecError, load_spec
from physbench.harness.cli.common import UsageError, fmt_prediction, fmt_value
from physbench.harness.conformance.plan import engine_names_in_checks
from physbench.harness.conformance.verdicts import check_applies, describe_bound, hard_checks
from physbench.harness.console import console, name_column
from physbench.harness.references.predict import predictions


def _num(v: Any) -> Any:
    import numpy as np

    if isinstance(v, np.ndarray):
        return [float(x) for x in v.tolist()]
    return v


def report(scenario: str, variant: str | None = None, engines: list[str] | None = None) -> dict[str, Any]:
    """The dry run of ``scenario`` (id or spec file) as one JSON-able dict;
    raises SpecError for a spec that does not load."""
    loaded = load_spec(resolve_scenario(scenario))
    scene = load_scene(scenario, variant, loaded=loaded)
    known = engine_names()
    engines = list(engines or known)
    errors, absent = engine_names_in_checks(scene, loaded.label, known)
    if errors:
        raise SpecError(errors)
    tolerance = loaded.validated(variant).scenario.max_initial_overlap
    bodies = []
    for b in scene.bodies:
        dims = {"radius": b.radius} if b.shape == "sphere" else (
            {"half_extents": _num(b.half_extents)} if b.shape == "box" else
            {"radius": b.radius, "half_length": b.half_length})
        bodies.append({"name": b.name, "shape": b.shape, **dims, "mass": b.mass, "position": _num(b.position),
                       "orientation": _num(b.orientation), "velocity": _num(b.velocity),
                       "angular_velocity": _num(b.angular_velocity), "material": b.material})
    statics = []
    for s in scene.statics:
        d: dict[str, Any] = {"name": s.name, "shape": s.kind, "material": s.material}
        if s.shape == "plane":
            d.update(normal=_num(s.normal), offset=s.offset)
            if s.angle is not None:
                d["angle"] = s.angle
        else:
            d.update(position=_num(s.position), half_extents=_num(s.half_extents), orientation=_num(s.orientation))
        statics.append(d)
    contacts = [{"a": o.what_a, "b": o.what_b, "overlap_m": o.depth,
                 "state": "overlap" if o.depth > CONTACT_GAP else "touching"}
                for o in initial_contacts(scene)]
    values, text = predictions(scene)
    unsupported = {}
    for e in engines:
        try:
            why = get_adapter(e).unsupported_reason(scene)
        except Exception as exc:  # an engine that cannot even load is reported, not fatal
            why = f"cannot load the adapter: {type(exc).__name__}: {exc}"
        if why:
            unsupported[e] = why
    scenes = {None: scene, **{v: load_scene(scenario, v, loaded=loaded) for v in scene.variant_names
                              if variant is None}}
    checks = []
    for i, c in enumerate(scene.checks):
        where = {}
        for v, sc in scenes.items():
            where[v or "base"] = [e for e in engines if check_applies(c, e, sc.variant)]
        checks.append({"check": f"check[{i}]", "metric": c.metric, "bound": describe_bound(c), "applies_to": where,
                       "xfail": sorted(c.xfail)})
    for c in hard_checks(scene):
        checks.append({"check": "implicit (tag 'hard')", "metric": c.metric, "bound": describe_bound(c),
                       "applies_to": {"base": list(engines)}, "xfail": []})
    return {
        "scenario": scene.id, "variant": variant, "file": loaded.label, "title": scene.title,
        "duration_s": scene.duration, "dt_s": scene.dt, "steps": scene.n_steps, "effects": sorted(scene.effects),
        "planar": scene.planar, "gravity": _num(scene.gravity), "tags": list(scene.tags), "phases": scene.phases,
        "variants": list(scene.variant_names), "bodies": bodies, "statics": statics,
        "springs": len(scene.springs), "reference_model": scene.reference_model,
        "primary_metric": scene.primary_metric, "max_initial_overlap_m": tolerance,
        "initial_contacts": contacts, "predictions": values, "predictions_text": text,
        "engines": engines, "unsupported": unsupported, "not_installed": absent, "checks": checks,
    }


def cmd_validate(args: argparse.Namespace) -> int:
    engines = args.engines
    if engines:
        unknown = [e for e in engines if e not in engine_names()]
        if unknown:
            raise UsageError(f"--engines: unknown engine(s) {', '.join(unknown)}; known: {', '.join(engine_names())}")
    d = report(args.scenario, args.variant, engines)
    if args.json:
        sys.stdout.write(json.dumps(d) + "\n")
        return 0
    _print(d)
    return 0


def _where(applies: dict[str, list[str]], n_scenes: int) -> str:
    """'all 7 scenes: reference, mujoco' or 'base: mujoco; elastic: no engine':
    the scenes (base, variants) grouped by the engines a check applies to."""
    groups: dict[tuple[str, ...], list[str]] = {}
    for v, es in applies.items():
        groups.setdefault(tuple(es), []).append(v)
    parts = []
    for es, vs in groups.items():
        who = f"all {n_scenes} scenes" if len(vs) == n_scenes > 1 else ", ".join(vs)
        parts.append(f"{who}: {', '.join(es) or 'no engine'}")
    return "; ".join(parts)


def _print(d: dict[str, Any]) -> None:
    from rich.markup import escape
    from rich.table import Table

    con = console()
    v = f" [{d['variant']}]" if d["variant"] else ""
    con.print(f"[bold]{escape(d['scenario'])}{escape(v)}[/bold] ({escape(d['file'])}): {escape(d['title'])}")
    con.print(f"valid; {d['duration_s']:g} s at dt {d['dt_s']:g} s ({d['steps']} steps); effects "
              f"{', '.join(d['effects']) or 'none'}{'; planar' if d['planar'] else ''}; variants: "
              f"{', '.join(d['variants']) or 'none'}; not stepped", highlight=False)
    t = Table(title="bodies")
    name_column(t, "body", [b["name"] for b in d["bodies"]])
    for col in ("shape", "size (m)", "mass (kg)", "position (m)", "velocity (m/s)", "material"):
        t.add_column(col, overflow="fold")
    for b in d["bodies"]:
        size = {k: b[k] for k in ("radius", "half_extents", "half_length") if k in b}
        t.add_row(escape(b["name"]), b["shape"], escape(", ".join(f"{k} {fmt_prediction(x)}" for k, x in size.items())),
                  fmt_value(b["mass"]), fmt_prediction(b["position"]), fmt_prediction(b["velocity"]), escape(b["material"]))
    con.print(t)
    for s in d["statics"]:
        extra = ", ".join(f"{k} {fmt_prediction(x)}" for k, x in s.items() if k not in ("name", "shape", "material"))
        con.print(f"static {escape(s['name'])}: {s['shape']} ({escape(extra)})", highlight=False)
    con.print(f"initial contacts (touching: within {1e-9:g} m; an overlap deeper than {d['max_initial_overlap_m']:g} m "
              f"is refused at load): "
              + ("none" if not d["initial_contacts"] else ""), highlight=False)
    for c in d["initial_contacts"]:
        con.print(f"  {escape(c['a'])} and {escape(c['b'])}: {c['state']}, signed overlap {c['overlap_m']:.3g} m",
                  highlight=False)
    if d["reference_model"]:
        p = Table(title=f"the reference model {d['reference_model']} predicts")
        name_column(p, "prediction", [*d["predictions"], *d["predictions_text"]])
        p.add_column("value", overflow="fold")
        for k, x in d["predictions"].items():
            p.add_row(k, fmt_prediction(x))
        for k, x in d["predictions_text"].items():
            p.add_row(escape(k), escape(str(x)))
        con.print(p)
    c = Table(title="checks: which engines each applies to")
    name_column(c, "metric", [x["metric"] for x in d["checks"]])
    for col in ("bound", "applies to", "xfail"):
        c.add_column(col, overflow="fold")
    for x in d["checks"]:
        where = _where(x["applies_to"], len(d["variants"]) + 1)
        c.add_row(escape(x["metric"]), escape(x["bound"]), escape(where), escape(", ".join(x["xfail"])))
    con.print(c)
    for e, why in d["unsupported"].items():
        con.print(f"{escape(e)} cannot model this scene: {escape(why)}", highlight=False)
    for line in d["not_installed"]:
        con.print(f"note: {escape(line)}", highlight=False)
