"""Sweep suites (``suites/<name>.toml``, format in ``docs/SWEEPS.md``):
the schema, validation and :func:`expand`.

A suite lists blocks of scenarios and a grid of engine settings per block:
axes common to every engine (``grid``) and engine-specific axes
(``[sweep.engine.<name>] grid``), combined as a cartesian product.
:func:`expand` turns a suite into :class:`harness.points.Point` s, one per
(scenario, variant, engine, settings); ``[[limit]]`` blocks become
breaking-point searches (harness.limits.LimitRequest).
"""

from __future__ import annotations

import hashlib
import itertools
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from physbench.contract.phase import phase_values
from physbench.contract.data import SHIPPED_SUITES
from physbench.contract.spec import SpecError, _display, _format_errors, read_toml
from physbench.harness.points import PHASE_KEY, RUN_TIMEOUT_S, Point, cached_scene, cached_spec
from physbench.harness.sweep_store import PLAIN_NAME, SuiteError, plain_name
from physbench.adapters import engine_names, get_adapter
from physbench.harness.limits import LimitRequest, validate_request
from physbench.contract.scene import load_scene, n_steps, resolve_scenario, scenario_ids, spec_targets
from physbench.contract.spec import record_size_error

#: the shipped suites (package data, contract/data.py)
SUITE_DIR = SHIPPED_SUITES
_SCENARIO_ENTRY = re.compile(r"^([^\[\]]+?)(?:\[([^\[\]]+)\])?$")


# ---------------------------------------------------------------------------
# suite file model (pydantic: structure and types; engine settings and
# scenario ids are checked afterwards, against the registry and scenarios/)


class _Strict(BaseModel):
    # strict: TOML is typed, so "3" for an integer is a mistake, not a number;
    # allow_inf_nan=False: every float is finite
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


#: bounds of a suite's measuring knobs: repeats per point, seconds per run
MAX_REPEATS = 1000
MAX_TIMEOUT_S = 86400.0


class SuiteSection(_Strict):
    name: str | None = None
    description: str = ""
    engines: list[str] = Field(min_length=1)
    repeats: int = Field(default=3, ge=1, le=MAX_REPEATS)
    timeout_s: float = Field(default=RUN_TIMEOUT_S, gt=0, le=MAX_TIMEOUT_S)

    @field_validator("name")
    @classmethod
    def _plain_name(cls, v: str | None) -> str | None:
        if v is not None and not PLAIN_NAME.match(v):
            raise ValueError(f"must be a plain name (letters, digits, '_', '-', '.'): it names a directory, got {v!r}")
        if v is not None and not plain_name(v):
            raise ValueError(f"must be a plain name not starting with '.' and of at most 100 characters: it names "
                             f"a directory under the results root, got {v!r}")
        return v


class EngineSection(_Strict):
    grid: dict[str, list[Any]] = Field(default_factory=dict)


class SweepSection(_Strict):
    description: str = ""
    scenarios: list[str] = Field(min_length=1)
    engines: list[str] | None = None
    repeats: int | None = Field(default=None, ge=1, le=MAX_REPEATS)
    #: step phases per grid point (contract/phase.py): N runs with the start
    #: moved back along the free flight by i/N dt, i = 0 .. N-1
    phases: int = Field(default=1, ge=1, le=1024)
    grid: dict[str, list[Any]] = Field(default_factory=dict)
    engine: dict[str, EngineSection] = Field(default_factory=dict)


class LimitSection(_Strict):
    """A ``[[limit]]`` table: a breaking-point search (harness/limits.py) per
    scenario and engine."""

    description: str = ""
    scenarios: list[str] = Field(min_length=1)
    engines: list[str] | None = None
    #: an engine setting (dt, iterations) or a dotted spec key
    param: str
    range: tuple[float, float]
    phases: int = Field(default=1, ge=1, le=1024)
    tol: float = Field(default=0.05, gt=0, lt=1)
    #: only checks of these metrics count (stability always does)
    checks: list[str] = Field(default_factory=list)
    #: fixed engine settings and dotted spec keys for every run of the search
    set: dict[str, Any] = Field(default_factory=dict)
    #: extra criteria: metric -> largest value that holds
    max: dict[str, float] = Field(default_factory=dict)

    @field_validator("range", mode="before")
    @classmethod
    def _range(cls, v: Any) -> Any:
        # strict mode takes no int for a float: a range of [1, 1000] is meant as numbers
        if isinstance(v, list) and len(v) == 2 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                        for x in v):
            if not all(math.isfinite(float(x)) for x in v) or not float(v[0]) < float(v[1]):
                raise ValueError(f"expected [LO, HI], two finite numbers with LO < HI, got {v!r}")
            return (float(v[0]), float(v[1]))
        raise ValueError(f"expected [LO, HI], two numbers, got {v!r}")


class SuiteModel(_Strict):
    suite: SuiteSection
    sweep: list[SweepSection] = Field(default_factory=list)
    limit: list[LimitSection] = Field(default_factory=list)


# ---------------------------------------------------------------------------
# the validated suite and its points


@dataclass(frozen=True)
class SuiteEntry:
    """One scenario (and variant) of a block: its id (family.name, or
    family.stem for a file outside scenarios/), the spec file when it was
    named by path (relative to the suite file, resolved), and the scene's
    content hash (contract.scene.content_hash) when the suite was loaded."""

    scenario: str
    variant: str | None
    path: str | None
    scene_hash: str


@dataclass(frozen=True)
class SweepBlock:
    """One ``[[sweep]]`` table, validated.  ``axes[engine]`` maps each setting
    name to its coerced values: the common grid, with an engine's own axis of
    the same name replacing the common one."""

    index: int
    scenarios: tuple[SuiteEntry, ...]
    engines: tuple[str, ...]
    repeats: int
    axes: dict[str, dict[str, tuple[Any, ...]]]
    description: str = ""
    phases: int = 1


@dataclass(frozen=True)
class Suite:
    name: str
    path: Path
    file_hash: str  # sha256 of the file's bytes, 16 hex digits
    description: str
    engines: tuple[str, ...]
    repeats: int
    timeout_s: float
    sweeps: tuple[SweepBlock, ...]
    #: the ``[[limit]]`` blocks expanded: one breaking-point search
    #: (harness.limits.LimitRequest) per (block, scenario, engine)
    limits: tuple[Any, ...] = ()


def resolve_suite(suite: str | Path) -> Path:
    """A suite name (``suites/<name>.toml``) or a path -> the file's path.
    A file of that path comes first; a directory of the name is no suite
    file, so the shipped suite of the name is taken
    (tests/test_sweep.py::test_a_directory_of_a_suites_name_does_not_hide_the_suite)."""
    p = Path(suite)
    if p.suffix == ".toml" or p.is_file():
        return p
    cand = SUITE_DIR / f"{suite}.toml"
    if cand.is_file():
        return cand
    known = ", ".join(sorted(q.stem for q in SUITE_DIR.glob("*.toml"))) or "none"
    what = "is a directory, not a suite file (.toml)," if p.is_dir() else "no such file"
    raise SuiteError([f"{suite}: <suite>: {what} and no suite of this name in suites/; known suites: {known}"])


def load_suite(path: str | Path) -> Suite:
    """Read and validate a suite file (a path, or a name under suites/).
    Raises SuiteError listing every problem found."""
    p = resolve_suite(path)
    label = _display(p)
    raw, data = read_toml(p, label, SuiteError)
    try:
        model = SuiteModel.model_validate(raw)
    except ValidationError as exc:
        raise SuiteError(_format_errors(label, exc, raw)) from None
    errors: list[str] = []
    if not model.sweep and not model.limit:
        errors.append(f"{label}: <suite>: expected at least one [[sweep]] or [[limit]] table")
    blocks = _check_suite(model, label, errors, p.parent)
    limits = _check_limits(model, label, errors)
    if errors:
        raise SuiteError(errors)
    s = model.suite
    if s.name is None and not plain_name(p.stem):
        raise SuiteError([f"{label}: suite.name: the file name {p.stem!r} is not a plain name (letters, digits, "
                          f"'_', '-', '.', not starting with '.') and names a directory; give suite.name"])
    return Suite(name=s.name or p.stem, path=p, file_hash=hashlib.sha256(data).hexdigest()[:16],
                 description=s.description, engines=tuple(s.engines), repeats=s.repeats,
                 timeout_s=s.timeout_s, sweeps=tuple(blocks), limits=tuple(limits))


def _block_engines(listed: list[str] | None, suite_engines: list[str], usable: Any, where: str,
                   errors: list[str]) -> list[str]:
    """A block's engines: its own list (a subset of the suite's, each once)
    or the suite's; only those in ``usable`` (registered and loadable) are
    kept.  Appends problems to ``errors``."""
    if listed is None:
        return [e for e in suite_engines if e in usable]
    engines: list[str] = []
    for j, e in enumerate(listed):
        if e not in suite_engines:
            errors.append(f"{where}.engines[{j}]: engine {e!r} is not in suite.engines ({', '.join(suite_engines)})")
        elif e in engines:
            errors.append(f"{where}.engines[{j}]: engine {e!r} is listed twice")
        elif e in usable:
            engines.append(e)
    return engines


def _check_limits(model: SuiteModel, label: str, errors: list[str]) -> list[Any]:
    """The ``[[limit]]`` blocks as LimitRequests, one per (block, scenario,
    engine), each validated as ``physbench limits`` validates its arguments
    (harness.limits.validate_request).  Appends to ``errors``."""

    ids = set(scenario_ids())
    known = set(engine_names())
    out: list[Any] = []
    scenes: dict[Any, Any] = {}  # loaded once for all the engines' requests (harness.limits.validate_request)
    for bi, lb in enumerate(model.limit):
        where = f"{label}: limit[{bi}]"
        engines = _block_engines(lb.engines, model.suite.engines, known, where, errors)
        seen: set[tuple[str, str | None]] = set()
        for j, entry in enumerate(lb.scenarios):
            m = _SCENARIO_ENTRY.match(entry.strip())
            if not m or m.group(1) not in ids:
                errors.append(f"{where}.scenarios[{j}]: expected a scenario id ('family.name' or "
                              f"'family.name[variant]') of scenarios/, got {entry!r}")
                continue
            sid, var = m.group(1), (None if m.group(2) in (None, "base") else m.group(2))
            if (sid, var) in seen:
                errors.append(f"{where}.scenarios[{j}]: {entry!r} is listed twice")
                continue
            seen.add((sid, var))
            for e in engines:
                names = set(get_adapter(e).capabilities().settings)
                settings = tuple(sorted((k, v) for k, v in lb.set.items() if k in names))
                overrides = tuple((k, v) for k, v in lb.set.items() if k not in names)
                bad = [k for k, _ in overrides if "." not in k and "[" not in k]
                if bad:
                    errors.append(f"{where}.set.{bad[0]}: not a setting of engine {e} and not a dotted spec key")
                    continue
                req = LimitRequest(sid, var, e, lb.param, lb.range[0], lb.range[1], lb.phases, lb.tol,
                                   tuple(lb.checks), settings, overrides, tuple(sorted(lb.max.items())),
                                   model.suite.timeout_s)
                problems = validate_request(req, scenes)
                errors.extend(f"{where} ({entry} on {e}): {msg}" for msg in problems)
                if not problems:
                    out.append(req)
    return out


def _engines_text(engines: Iterable[str]) -> str:
    engines = list(engines)
    return f"engine{'s' if len(engines) > 1 else ''} {', '.join(engines)}"


def _check_suite(model: SuiteModel, label: str, errors: list[str], base: Path = SHIPPED_SUITES) -> list[SweepBlock]:
    """Cross-checks pydantic cannot make: engines registered, scenario ids
    and variants exist, every grid key is a setting of the engines it applies
    to and every value is allowed by that setting.  Appends to ``errors``."""

    known = engine_names()
    caps: dict[str, Any] = {}
    for i, e in enumerate(model.suite.engines):
        if e not in known:
            errors.append(f"{label}: suite.engines[{i}]: unknown engine {e!r}; known: {', '.join(known)}")
        elif e in caps:
            errors.append(f"{label}: suite.engines[{i}]: engine {e!r} is listed twice")
        else:
            try:
                caps[e] = get_adapter(e).capabilities()
            except Exception as exc:  # a broken adapter module
                errors.append(f"{label}: suite.engines[{i}]: engine {e!r} cannot be loaded: {type(exc).__name__}: {exc}")
    ids = set(scenario_ids())
    files: dict[str, str] = {}  # scenario id -> its spec file: one file per id
    blocks: list[SweepBlock] = []
    for bi, sw in enumerate(model.sweep):
        where = f"{label}: sweep[{bi}]"
        # scenarios: 'family.name', a spec file or a folder (relative to the
        # suite file), each with an optional '[variant]'
        scen: list[SuiteEntry] = []
        for j, entry in enumerate(sw.scenarios):
            m = _SCENARIO_ENTRY.match(entry.strip())
            if not m:
                errors.append(f"{where}.scenarios[{j}]: expected 'family.name', a spec file or folder, optionally "
                              f"with '[variant]', got {entry!r}")
                continue
            sid, var = m.group(1), m.group(2)
            if var == "base":
                var = None
            pathlike = sid.endswith(".toml") or "/" in sid or (base / sid).is_dir()
            if not pathlike and sid not in ids:
                errors.append(f"{where}.scenarios[{j}]: unknown scenario {sid!r}; known ids: {', '.join(sorted(ids))}")
                continue
            try:
                targets = spec_targets(sid, base) if pathlike else [sid]
            except SpecError as exc:
                errors.append(f"{where}.scenarios[{j}]: {exc.errors[0]}")
                continue
            for target in targets:
                try:
                    loaded = cached_spec(resolve_scenario(target))
                except SpecError as exc:
                    errors.append(f"{where}.scenarios[{j}]: scenario {target!r} does not load: {exc.errors[0]}")
                    continue
                if var is not None and var not in loaded.variants:
                    errors.append(f"{where}.scenarios[{j}]: scenario {target!r} has no variant {var!r}; "
                                  f"its variants: {', '.join(loaded.variants) or 'none'}")
                    continue
                try:
                    # a shipped scenario: the per-process cache the record-size check, the schedule's cost model
                    # and the searches' summaries read too (it loads once per client); a spec file: read afresh
                    scene = load_scene(target, var, loaded=loaded) if pathlike else cached_scene(target, var)
                except SpecError as exc:
                    errors.append(f"{where}.scenarios[{j}]: scenario {target!r} does not load: {exc.errors[0]}")
                    continue
                where_from = str(loaded.path.resolve())
                if files.setdefault(scene.id, where_from) != where_from:
                    errors.append(f"{where}.scenarios[{j}]: {target!r} has the id {scene.id!r} (family.stem) of "
                                  f"another spec file, {files[scene.id]}; rename one")
                    continue
                if any((e.scenario, e.variant) == (scene.id, var) for e in scen):
                    errors.append(f"{where}.scenarios[{j}]: {entry!r} is listed twice")
                    continue
                scen.append(SuiteEntry(scene.id, var, target if pathlike else None, scene.content_hash))
        # engines of this block: a subset of the suite's
        engines = _block_engines(sw.engines, model.suite.engines, caps, where, errors)
        for e in sw.engine:
            if e not in engines:
                whose = "suite.engines" if sw.engines is None else f"sweep[{bi}].engines"
                errors.append(f"{where}.engine.{e}: engine {e!r} is not in {whose} "
                              f"({', '.join(model.suite.engines if sw.engines is None else sw.engines)})")
        # axes per engine: common grid, then the engine's own (replacing)
        axes: dict[str, dict[str, tuple[Any, ...]]] = {e: {} for e in engines}
        common_bad: dict[tuple[str, str, bool], list[str]] = {}  # (path, message, name them?) -> engines
        for key, values in sw.grid.items():
            for e in engines:
                own = sw.engine.get(e)
                if own is not None and key in own.grid:
                    continue  # replaced by the engine's own axis
                coerced = _check_axis(f"sweep[{bi}].grid.{key}", key, values, e, caps[e], common_bad, common=True)
                if coerced is not None:
                    axes[e][key] = coerced
        for (path, msg, name_engines), engs in common_bad.items():
            errors.append(f"{label}: {path}: {msg}" + (f" ({_engines_text(engs)})" if name_engines else ""))
        for e, own in sw.engine.items():
            if e not in engines:
                continue
            own_bad: dict[tuple[str, str, bool], list[str]] = {}
            for key, values in own.grid.items():
                coerced = _check_axis(f"sweep[{bi}].engine.{e}.grid.{key}", key, values, e, caps[e], own_bad,
                                      common=False)
                if coerced is not None:
                    axes[e][key] = coerced
            for (path, msg, _), _ in own_bad.items():
                errors.append(f"{label}: {path}: {msg}")
        _check_record_size(where, scen, axes, errors)
        if PHASE_KEY in sw.grid or any(PHASE_KEY in own.grid for own in sw.engine.values()):
            errors.append(f"{where}: {PHASE_KEY!r} is not a grid axis; give the number of step phases as "
                          f"'phases = N' in the [[sweep]] table")
        blocks.append(SweepBlock(bi, tuple(scen), tuple(engines), sw.repeats or model.suite.repeats,
                                 axes, sw.description, sw.phases))
    return blocks


def _check_record_size(where: str, scen: list[SuiteEntry], axes: dict[str, dict[str, tuple[Any, ...]]],
                       errors: list[str]) -> None:
    """Every point's recording fits the bounds (contract/spec/bounds.py
    record_size_error) at the smallest dt any engine sweeps: checked when
    the suite loads, before anything runs or is allocated."""

    scenes: dict[int, Any] = {}  # a scene does not depend on the engine: loaded once per entry

    def scene_of(i: int, entry: SuiteEntry) -> Any:
        if i not in scenes:
            try:
                scenes[i] = (load_scene(entry.path, entry.variant, loaded=cached_spec(resolve_scenario(entry.path)))
                             if entry.path
                             else cached_scene(entry.scenario, entry.variant))
            except SpecError:
                scenes[i] = None  # reported where the scenario is listed
        return scenes[i]

    for e, ax in axes.items():
        if "dt" not in ax:
            continue
        dt = min(float(v) for v in ax["dt"])
        for i, entry in enumerate(scen):
            sc = scene_of(i, entry)
            if sc is None:
                continue
            why = record_size_error(n_steps(sc.duration, dt), sc.n_bodies)
            if why:
                errors.append(f"{where}.grid.dt: {scenario_label(entry.scenario, entry.variant)} at dt = {dt:g} on {e}: "
                              f"{why}")
                return


def _check_axis(path: str, key: str, values: list[Any], engine: str, caps: Any,
                bad: dict[tuple[str, str, bool], list[str]], common: bool) -> tuple[Any, ...] | None:
    """Coerce one axis's values with ``engine``'s Setting.  Problems go into
    ``bad`` keyed by (key path, message, whether to name the engines), so
    that the same problem on several engines is reported once, naming them
    all."""
    setting = caps.settings.get(key)

    def problem(where: str, msg: str, name_engines: bool = True) -> None:
        bad.setdefault((where, msg, name_engines), []).append(engine)

    if setting is None:
        known = ", ".join(caps.settings)
        if common:
            problem(path, f"not a setting of engine {engine} (its settings: {known}); a common axis must be a "
                          f"setting of every engine of the sweep, engine-specific axes go under "
                          f"[sweep.engine.<engine>]", False)
        else:
            problem(path, f"not a setting of engine {engine}; its settings: {known}", False)
        return None
    if not values:
        problem(path, "expected at least one value", False)
        return None
    out: list[Any] = []
    ok = True
    for i, v in enumerate(values):
        if not isinstance(v, (bool, int, float, str)):
            problem(f"{path}[{i}]", f"expected a number, string or boolean, got {v!r}", False)
            ok = False
            continue
        try:
            c = setting.coerce(v)
        except ValueError as exc:
            problem(f"{path}[{i}]", re.sub(rf"^setting {re.escape(key)}: ", "", str(exc)), common)
            ok = False
            continue
        if isinstance(c, float) and not math.isfinite(c):
            problem(f"{path}[{i}]", f"expected a finite number, got {v!r}", False)
            ok = False
            continue
        if c in out:
            problem(f"{path}[{i}]", f"value {v!r} is listed twice", False)
            ok = False
            continue
        out.append(c)
    return tuple(out) if ok else None


def expand(suite: Suite, engines: list[str] | None = None, scenarios: list[str] | None = None) -> list[Point]:
    """All points of ``suite``, in suite order (block, scenario, engine, grid
    in axis order), optionally only ``engines`` and ``scenarios`` (ids, or
    ``id[variant]`` for one variant).  A point listed by two blocks is kept
    once (the first).  Raises ValueError for an engine or scenario that is
    not in the suite."""
    if engines is not None:
        unknown = [e for e in engines if e not in suite.engines]
        if unknown:
            raise ValueError(f"engine {', '.join(unknown)} is not in suite {suite.name} "
                             f"(its engines: {', '.join(suite.engines)})")
    listed = {(e.scenario, e.variant) for b in suite.sweeps for e in b.scenarios}
    listed |= {(r.scenario, r.variant) for r in suite.limits}
    if scenarios is not None:
        for s in scenarios:
            if not any(s == sid or s == scenario_label(sid, var) for sid, var in listed):
                raise ValueError(f"scenario {s} is not in suite {suite.name} "
                                 f"(its scenarios: {', '.join(sorted({scenario_label(*x) for x in listed}))})")
    points: list[Point] = []
    seen: set[str] = set()
    for b in suite.sweeps:
        for entry in b.scenarios:
            sid, var = entry.scenario, entry.variant
            if scenarios is not None and sid not in scenarios and scenario_label(sid, var) not in scenarios:
                continue
            for e in b.engines:
                if engines is not None and e not in engines:
                    continue
                axes = b.axes.get(e, {})
                names = sorted(axes)
                for combo in itertools.product(*(axes[n] for n in names)):
                    for f in phase_values(b.phases):
                        # phase 0 is the scene as written: no phase key, so it is
                        # the same point (and history) as in a block without phases
                        settings = tuple(zip(names, combo))
                        if f:
                            settings = tuple(sorted(settings + ((PHASE_KEY, f),)))
                        p = Point(sid, var, e, settings, b.repeats, suite.timeout_s, entry.path, entry.scene_hash)
                        if p.key not in seen:
                            seen.add(p.key)
                            points.append(p)
    return points


def scenario_label(sid: str, var: str | None) -> str:
    return sid + (f"[{var}]" if var else "")
