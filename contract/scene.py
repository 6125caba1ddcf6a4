"""Compiling and loading scenes: spec files and scenario ids to the
engine-neutral :class:`Scene` that adapters build from.

A validated :class:`contract.spec.SpecModel` is compiled into a frozen
:class:`Scene`: patterns expanded into bodies, masses and principal inertias
computed, slopes turned into planes, materials resolved into the *pair*
values the spec asks for (with absent effects zeroing restitution and
friction).  Adapters never read TOML; they read a Scene.

The scene's types and content hash live in :mod:`contract.scene_model`, the
shape formulas (volumes, inertias, patterns) in :mod:`contract.shapes`; this
module re-exports the types and helpers that the rest of the project imports
from here (``Scene``, ``Body``, ``Static``, ``Check``,
``n_steps``, ``principal_inertia``, ...).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from physbench.contract.data import SHIPPED_SCENARIOS, checkout_root
from physbench.contract.geometry.start import overlap_errors
from physbench.contract.models import model_refusal, scene_errors
from physbench.contract.phase import PhaseError, shift_scene
from physbench.contract.rotation import dot, norm, quat_to_matrix, transpose_apply
from physbench.contract.scene_model import (  # re-exported: the scene's types are imported from here
    Body,
    Check,
    Joint,
    Material,
    Scene,
    Spring,
    Static,
    content_hash,
    n_steps,
)
from physbench.contract.shapes import expand_pattern, principal_inertia, shape_volume
from physbench.contract.spec.bounds import bound_error
from physbench.contract.spec.errors import ModelRefusal, SpecError
from physbench.contract.spec.load import LoadedSpec, load_spec
from physbench.contract.spec.schema import SpecModel
from physbench.contract.xfail import Xfail

# the shipped scenarios (package data, contract/data.py); read at call
# time: tests point it at a folder of their own
SCENARIO_DIR = SHIPPED_SCENARIOS


# --------------------------------------------------------------------------
# compile


def _id_for(path: Path | None, family: str) -> str:
    if path is None:
        return f"{family}.inline"
    try:
        rel = path.resolve().relative_to(SCENARIO_DIR.resolve())
        return ".".join(rel.with_suffix("").parts)
    except ValueError:
        return f"{family}.{path.stem}"


def compile_scene(spec: SpecModel, path: Path | None = None, variant: str | None = None,
                  variant_names: tuple[str, ...] = (), label: str | None = None) -> Scene:
    """Validated spec -> Scene.  Raises SpecError for problems that need the
    expanded scene (ambiguous material pairs, duplicate pattern names)."""
    label = label or (str(path) if path else "<inline>")
    errs: list[str] = []
    mats: dict[str, Material] = {
        "default": Material("default", 0.0, 0.0, 0.0, 0.0),
    }
    for name, m in spec.material.items():
        mats[name] = Material(
            name,
            m.restitution,
            m.friction,
            m.static_friction if m.static_friction is not None else m.friction,
            m.rolling_friction,
        )
    bodies: list[Body] = []
    entries: list[tuple[int, bool]] = []  # per body: its [[body]] entry, made by a pattern
    seen: set[str] = set()
    for bi, b in enumerate(spec.body):
        he = np.array(b.half_extents, float) if b.half_extents is not None else None
        r = b.radius or 0.0
        h = b.half_length or 0.0
        mass = b.mass if b.mass is not None else b.density * shape_volume(b.shape, r, he, h)
        why = bound_error("mass", mass)
        if why:
            errs.append(f"{label}: body[{bi}].density: the mass it gives (density x volume) {why}")
            continue
        inertia = principal_inertia(b.shape, mass, r, he, h)
        for name, pos in expand_pattern(b):
            if name in seen:
                errs.append(f"{label}: body[{bi}].name: pattern makes a duplicate body name {name!r}")
            far = next((float(c) for c in pos if bound_error("position", float(c))), None)
            if far is not None:
                errs.append(f"{label}: body[{bi}].pattern: body {name!r} at {pos.tolist()}: position "
                            f"{bound_error('position', far)}")
                break
            seen.add(name)
            entries.append((bi, b.pattern is not None))
            bodies.append(Body(
                index=len(bodies), name=name, shape=b.shape, mass=float(mass), inertia=inertia,
                position=pos, orientation=np.array(b.orientation, float),
                velocity=np.array(b.velocity, float), angular_velocity=np.array(b.angular_velocity, float),
                material=b.material, radius=r, half_extents=he, half_length=h,
                drag_linear=b.drag_linear, drag_quadratic=b.drag_quadratic,
            ))
    statics: list[Static] = []
    for si, s in enumerate(spec.static):
        name = s.name or f"static_{si}"
        if s.shape == "plane":
            n = np.array(s.normal, float)
            n /= norm(n)
            statics.append(Static(si, name, "plane", "plane", s.material, normal=n, offset=float(s.offset or 0.0)))
        elif s.shape == "slope":
            a = math.radians(s.angle)
            n = np.array([math.sin(a), 0.0, math.cos(a)])
            pt = np.array(s.point if s.point is not None else (0.0, 0.0, 0.0), float)
            statics.append(Static(si, name, "plane", "slope", s.material, normal=n, offset=dot(n, pt), angle=float(s.angle)))
        else:
            statics.append(Static(si, name, "box", "box", s.material,
                                  position=np.array(s.position, float),
                                  orientation=np.array(s.orientation or (1.0, 0.0, 0.0, 0.0), float),
                                  half_extents=np.array(s.half_extents, float)))
    # ambiguous material pairs: two different named materials that may touch
    if "contact" in spec.scenario.effects:
        used = sorted({b.material for b in bodies})
        used_static = sorted({s.material for s in statics})
        for i, ma in enumerate(used):
            others = used[i + 1:] + [m for m in used_static if m != ma]
            for mb in others:
                if "default" in (ma, mb) or ma == mb:
                    continue
                A, B = mats[ma], mats[mb]
                if (A.restitution, A.friction, A.static_friction, A.rolling_friction) != (
                        B.restitution, B.friction, B.static_friction, B.rolling_friction):
                    errs.append(
                        f"{label}: material.{mb}: materials {ma!r} and {mb!r} can touch but "
                        f"differ; the pair value would be ambiguous (give one of them the "
                        f"name 'default', or make their coefficients equal)")
    index = {b.name: b.index for b in bodies}
    springs = []
    for si, sp in enumerate(spec.spring):
        ia = -1 if sp.a == "world" else index.get(sp.a)
        ib = -1 if sp.b == "world" else index.get(sp.b)
        if ia is None or ib is None:
            errs.append(f"{label}: spring[{si}]: unknown body {sp.a if ia is None else sp.b!r}")
            continue
        springs.append(Spring(ia, ib, np.array(sp.anchor_a, float), np.array(sp.anchor_b, float),
                              sp.stiffness if "spring" in spec.scenario.effects else 0.0,
                              sp.rest_length,
                              sp.damping if "damper" in spec.scenario.effects else 0.0))
    joints = _compile_joints(spec, bodies, index, label, errs)
    if spec.perturbation is not None and spec.perturbation.bodies is not None:
        unknown = [n for n in spec.perturbation.bodies if n not in index]
        if unknown:
            errs.append(f"{label}: perturbation.bodies: unknown bodies {unknown}; the scene has {sorted(index)}")
    if errs:
        raise SpecError(errs)
    sc = spec.scenario
    scene = Scene(
        id=_id_for(path, sc.family), variant=variant, path=path, family=sc.family, title=sc.title,
        duration=sc.duration, dt=sc.dt, effects=frozenset(sc.effects), planar=sc.planar,
        gravity_vector=np.array(sc.gravity, float), primary_metric=sc.primary_metric,
        tags=tuple(sc.tags), materials=mats, bodies=tuple(bodies), statics=tuple(statics),
        springs=tuple(springs),
        reference_model=spec.reference.model if spec.reference else None,
        reference_params=dict(spec.reference.params) if spec.reference else {},
        checks=tuple(Check(c.metric, c.max, c.min, c.equals, c.tolerance,
                           tuple(c.engines) if c.engines is not None else None,
                           tuple(c.variants) if c.variants is not None else None,
                           {e: Xfail.of(e, x if isinstance(x, str) else x.model_dump())
                            for e, x in c.xfail.items()}) for c in spec.check),
        variant_names=variant_names,
        phases=sc.phases,
        body_entries=tuple(entries),
        perturbation=spec.perturbation.model_dump() if spec.perturbation is not None else None,
        joints=joints,
    )
    # the reference model must accept the scene, and every checked metric
    # must be produced for it (tests/test_models.py)
    errs = model_refusal(scene, label)
    if errs:
        raise ModelRefusal(errs)
    errs = scene_errors(scene, label)
    if errs:
        raise SpecError(errs)
    # a start buried inside geometry is a typo, not a scene
    # (tests/test_spec.py::test_buried_start_is_a_spec_error)
    errs = overlap_errors(scene, label, spec.scenario.max_initial_overlap)
    if errs:
        raise SpecError(errs)
    scene = dataclasses.replace(scene, content_hash=content_hash(scene))
    if scene.phases > 1:
        # every phase must be runnable: the start must be free flight
        try:
            shift_scene(scene, (scene.phases - 1) / scene.phases)
        except PhaseError as e:
            raise SpecError([f"{label}: scenario.phases: {scene.phases} step phases need a start in free flight: "
                             f"{e}"]) from None
    return scene


#: an anchor further than this many bounding radii from the centre of each of
#: a joint's two bodies is "far from both bodies", a spec error
#: (tests/test_joints_spec.py::test_anchor_far_from_both_bodies)
JOINT_REACH = 2.0


def _compile_joints(spec: SpecModel, bodies: list[Body], index: dict[str, int], label: str,
                    errs: list[str]) -> tuple[Joint, ...]:
    """The ``[[joint]]`` tables as :class:`Joint` (anchor and axis also in
    each side's frame); appends to ``errs`` an unknown body (a pattern's
    name beyond its count), an anchor far from both bodies (two-body joints:
    the world is everywhere, so a pendulum bob may hang at any distance
    from its pivot) and a body named twice in one fixed chain (a loop of
    fixed joints, world included)."""
    out: list[Joint] = []
    table: list[int] = []  # per joint made: its [[joint]] table
    # fixed chains: union-find over body indices, the world as -1
    parent: dict[int, int] = {}

    def root(i: int) -> int:
        while parent.get(i, i) != i:
            i = parent[i]
        return i

    def local(i: int, v: np.ndarray, point: bool) -> np.ndarray:
        if i < 0:
            return v.copy()
        R = quat_to_matrix(bodies[i].orientation)
        return transpose_apply(R, v - bodies[i].position if point else v)

    for k, j in enumerate(spec.joint):
        p = f"{label}: joint[{k}]"
        # (body name, other name, anchor, name) per joint the table makes:
        # one, or one per link of a chain (its anchor moved with the pattern)
        if j.chain is None:
            made = [(j.body, j.other, np.array(j.anchor, float), j.name)]
        else:
            entry = next((b for b in spec.body if b.name == j.chain), None)  # a row or column (spec.validate)
            links = [n for n, _ in expand_pattern(entry)] if entry is not None and entry.pattern else []
            if not links or any(n not in index for n in links):
                continue  # spec.validate reports the chain, the pattern its own errors
            x0 = bodies[index[links[0]]].position
            made = [(n, j.other if i == 0 else links[i - 1],
                     np.array(j.anchor, float) + (bodies[index[n]].position - x0),
                     None if j.name is None else f"{j.name}_{i}") for i, n in enumerate(links)]
        for body, other, anchor, name in made:
            pl = p if j.chain is None else f"{p} ({body!r} of chain {j.chain!r})"
            ib = index.get(body)
            io = -1 if other == "world" else index.get(other)
            if ib is None or io is None:
                which, who = ("body", body) if ib is None else ("other", other)
                errs.append(f"{pl}.{which}: unknown body {who!r}; the scene has {sorted(index)}")
                continue
            if io >= 0:
                near = [float(np.linalg.norm(anchor - bodies[i].position)) / bodies[i].bounding_radius
                        for i in (ib, io)]
                if min(near) > JOINT_REACH:
                    errs.append(f"{pl}.anchor: {anchor.tolist()} is far from both bodies ({near[0]:.3g} and "
                                f"{near[1]:.3g} bounding radii from the centres of {body!r} and {other!r}; "
                                f"expected within {JOINT_REACH:g} of one of them)")
                    continue
            if j.kind == "fixed":
                ra, ro = root(ib), root(io)
                if ra == ro:
                    errs.append(f"{pl}.body: {body!r} is named twice in one fixed chain (it is already fixed to "
                                f"{other!r} through other fixed joints): a loop of fixed joints")
                    continue
                parent[ra] = ro
            axis = None if j.axis is None else np.array(j.axis, float) / norm(np.array(j.axis, float))
            # default names count the joints made so far: a chain's joints and
            # the tables after it never share one (tests/test_joint_chain.py)
            table.append(k)
            out.append(Joint(
                index=len(out), name=name or f"joint_{len(out)}", kind=j.kind, body=ib, other=io, anchor=anchor,
                axis=axis, anchor_body=local(ib, anchor, True), anchor_other=local(io, anchor, True),
                axis_body=None if axis is None else local(ib, axis, False),
                axis_other=None if axis is None else local(io, axis, False)))
    names = [jt.name for jt in out]
    for k, n in enumerate(names):
        if names.index(n) != k:
            errs.append(f"{label}: joint[{table[k]}].name: duplicate joint name {n!r}")
    return tuple(out)


def resolve_scenario(name: str | Path) -> Path:
    """A scenario id ('billiards.head_on') or a path -> the spec file's path."""
    p = Path(name)
    if p.suffix == ".toml" or p.exists():
        return p
    parts = str(name).split(".")
    cand = SCENARIO_DIR.joinpath(*parts).with_suffix(".toml")
    if cand.is_file():
        return cand
    import difflib

    ids = scenario_ids()
    near = difflib.get_close_matches(str(name), ids, n=3, cutoff=0.6)
    hint = f"did you mean {', '.join(near)}? " if near else ""
    raise SpecError([f"{name}: <scenario>: no spec file and no scenario with this id; {hint}"
                     f"{len(ids)} scenarios are known ('physbench list' names them)"])


def spec_targets(entry: str | Path, base: Path | None = None) -> list[str]:
    """One selection entry -> the specs it names: a scenario id stays the
    id; a spec file (``*.toml``, anywhere) is its path; a folder is every
    ``*.toml`` below it (sorted, hidden files skipped).  Relative paths are
    taken from ``base`` when given (a suite file's folder), else from the
    working directory.  Anything else raises SpecError naming the entry."""
    text = str(entry)
    p = Path(text)
    if base is not None and not p.is_absolute():
        p = base / p
    pathlike = p.suffix == ".toml" or "/" in text or p.exists()
    if p.is_dir():
        files = sorted(q for q in p.rglob("*.toml")
                       if not any(part.startswith(".") for part in q.relative_to(p).parts))
        if not files:
            raise SpecError([f"{text}: <scenario>: a folder without spec files (*.toml)"])
        return [str(q) for q in files]
    if pathlike:
        if not p.is_file():
            raise SpecError([f"{text}: <scenario>: no such spec file" + (f" (looked for {p})" if p != Path(text) else "")])
        return [str(p)]
    resolve_scenario(text)  # an id: raises SpecError naming the known ones
    return [text]


def canonical_example() -> Path:
    """The canonical spec: in a checkout, ../shared/examples/head_on.toml
    beside the repository, else the copy kept under tests/data; in an
    installed package, the shipped billiards.head_on (the canonical spec
    with its xfails and variants: the same scene)."""
    root = checkout_root()
    if root is not None:
        shared = root.parent / "shared" / "examples" / "head_on.toml"
        return shared if shared.is_file() else root / "tests" / "data" / "head_on.toml"
    return SHIPPED_SCENARIOS / "billiards" / "head_on.toml"


def scenario_ids() -> list[str]:
    return sorted(".".join(p.relative_to(SCENARIO_DIR).with_suffix("").parts)
                  for p in SCENARIO_DIR.rglob("*.toml"))


def load_scene(name: str | Path, variant: str | None = None, overrides: dict[str, Any] | None = None,
               loaded: LoadedSpec | None = None) -> Scene:
    """Load, validate and compile one scene (optionally a variant, optionally
    with dotted-key ``overrides``).  Raises SpecError."""
    if loaded is None:
        loaded = load_spec(resolve_scenario(name))
    spec = loaded.validated(variant, overrides)
    return compile_scene(spec, loaded.path, variant, tuple(loaded.variants), loaded.label)
