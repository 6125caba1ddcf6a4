"""Accuracy-vs-cost sweeps: ``physbench sweep``.

A *suite* (``suites/<name>.toml``, format in ``docs/SWEEPS.md``) lists blocks
of scenarios and a grid of engine settings per block: axes common to every
engine (``grid``) and engine-specific axes (``[sweep.engine.<name>] grid``),
combined as a cartesian product.  :func:`expand` turns a suite into
:class:`Point` s, one per (scenario, variant, engine, settings); each point is
run with :func:`harness.runner.run` (the runner does the stepping, timing and
metrics; this module only plans, repeats, stores and resumes).

Rows.  One row per point: ``RunResult.row()`` of the point's first run (its
metrics: engines are deterministic) plus the sweep columns ``suite``,
``sweep_id``, ``point_key``, ``point_settings``, ``primary_metric``,
``primary_error``, ``cpu_s_per_sim_s_median``/``_min`` over ``repeats`` timed
runs, ``machine_id``, ``sweep_jobs``, ``point_wall_s`` and ``schema_version``
(``results/README.md``).  Traces are never stored.

Storage (asv style, ``results/sweeps/``)::

    <machine-id>/<suite>/<sweep_id>/manifest.json     while running
    <machine-id>/<suite>/<sweep_id>/part-000001.parquet  one per finished point
    <machine-id>/<suite>/<sweep_id>.parquet           when complete
    <machine-id>/<suite>/<sweep_id>.manifest.json     when complete

Every file is written atomically (temp file, fsync, rename), one part per
finished point, so a killed sweep loses at most the points in flight.  A
sweep resumes (automatically, or with ``resume=True``) by reading the finished
point keys back from its parts.

Execution: ``jobs`` reusable worker processes under a wall-clock watchdog
(``executor="process"``, the default; harness/execute.py), or in this
process (``"serial"``: no isolation, for debugging).  A point whose worker
dies (abort, segfault, out-of-memory kill) gets an ``error`` row naming the
signal with the tail of the worker's stderr; a point stuck past its budget
(``timeout_s`` per run, times its repeats) gets a ``timeout`` row and its
worker is replaced; no other point is touched.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import itertools
import json
import math
import os
import re
import shutil  # noqa: F401 - consolidation removes part directories through it (tests patch it)
import statistics
import sys
import time
import traceback
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterable

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from harness import status as st
from harness.execute import RunRequest, WorkerLost, make_executor, request_scene
from contract.phase import PhaseError, phase_values
from harness.results import (RESULTS_DIR, SCHEMA_VERSION, PartsDir, consolidate_parts, list_parts, try_lock,
                             unfinished_dirs, write_json_atomic, write_parquet_atomic)
from contract.scene import REPO_ROOT
from harness.fingerprint import fingerprint, machine_id as _fingerprint_machine_id
from contract.spec import SpecError, _display, _format_errors, read_toml

SUITE_DIR = REPO_ROOT / "suites"
SWEEPS_DIR = RESULTS_DIR / "sweeps"
RUN_TIMEOUT_S = 600.0  # default wall-clock budget per run (suite.timeout_s)
STATUSES = st.RUN_STATUSES
EXECUTORS = ("serial", "process")
# Columns this module adds to RunResult.row() (the row contract, with
# results/README.md).
SWEEP_COLUMNS = ("suite", "sweep_id", "point_key", "point_settings", "phase", "primary_metric", "primary_error",
                 "primary_threshold", "checks",
                 "cpu_s_per_sim_s_median", "cpu_s_per_sim_s_min", "repeats", "machine_id", "sweep_jobs",
                 "point_wall_s", "schema_version")
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")
#: the point setting that carries a step phase (not an engine setting)
PHASE_KEY = "phase"
_SCENARIO_ENTRY = re.compile(r"^([^\[\]]+?)(?:\[([^\[\]]+)\])?$")


def plain_name(name: str) -> bool:
    """Whether ``name`` may name a directory under the results root: letters,
    digits, '_', '-', '.', at most 100 characters, and not starting with '.'
    (so never '.', '..' or a hidden directory).  Pinned by
    tests/test_fuzz.py::test_suite_name_cannot_escape_the_results_root."""
    return bool(_NAME.match(name)) and not name.startswith(".") and len(name) <= 100


class SuiteError(SpecError):
    """A suite file failed to load; ``errors`` holds one line per problem,
    ``<file>: <key path>: <what was expected, what was found>``.  A SpecError,
    so callers that report spec errors (exit code 2) report these too."""


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
        if v is not None and not _NAME.match(v):
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


@dataclass(frozen=True)
class Point:
    """One run to make: scenario (+ variant) on an engine with the swept
    settings (sorted (name, value) pairs, values coerced by the engine's
    Setting, so 1e-3 and 0.001 are the same point)."""

    scenario: str
    variant: str | None
    engine: str
    settings: tuple[tuple[str, Any], ...]
    repeats: int = 1
    timeout_s: float = RUN_TIMEOUT_S
    #: the spec file (None: ``scenario`` is an id under scenarios/)
    path: str | None = None
    #: the scene's content hash: part of the key, so a changed scene is a
    #: new point (and a new history series), never the old one resumed
    scene_hash: str = ""

    @property
    def settings_dict(self) -> dict[str, Any]:
        return dict(self.settings)

    @property
    def phase(self) -> float:
        """The step phase f (0 <= f < 1) of the point: its start moved back
        by f dt along the free flight (contract/phase.py); 0 = as written."""
        return float(self.settings_dict.get(PHASE_KEY, 0.0))

    @property
    def engine_settings(self) -> dict[str, Any]:
        """The swept settings the engine gets (the phase is the harness's)."""
        return {k: v for k, v in self.settings if k != PHASE_KEY}

    @property
    def settings_json(self) -> str:
        """The swept settings as canonical JSON (sorted keys, shortest
        round-trip floats)."""
        return json.dumps(self.settings_dict, sort_keys=True, separators=(",", ":"))

    @property
    def label(self) -> str:
        return self.scenario + (f"[{self.variant}]" if self.variant else "")

    @property
    def key(self) -> str:
        """Stable identity across runs and nights:
        ``scenario[variant]|engine|{"dt":0.001,...}|<scene hash>``.  Repeats
        and timeouts are not part of it (they change how a point is
        measured, not what); the scene's content is."""
        return self.series_key + (f"|{self.scene_hash}" if self.scene_hash else "")

    @property
    def series_key(self) -> str:
        """The key without the scene hash: the point's place in the suite,
        whatever its content (the report's history splits a series where
        the hash changes)."""
        return f"{self.label}|{self.engine}|{self.settings_json}"


def resolve_suite(suite: str | Path) -> Path:
    """A suite name (``suites/<name>.toml``) or a path -> the file's path."""
    p = Path(suite)
    if p.suffix == ".toml" or p.exists():
        return p
    cand = SUITE_DIR / f"{suite}.toml"
    if cand.is_file():
        return cand
    known = ", ".join(sorted(q.stem for q in SUITE_DIR.glob("*.toml"))) or "none"
    raise SuiteError([f"{suite}: <suite>: no such file and no suite of this name in suites/; known suites: {known}"])


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
    from adapters import engine_names, get_adapter
    from harness.limits import LimitRequest, validate_request
    from contract.scene import scenario_ids

    ids = set(scenario_ids())
    known = set(engine_names())
    out: list[Any] = []
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
                problems = validate_request(req)
                errors.extend(f"{where} ({entry} on {e}): {msg}" for msg in problems)
                if not problems:
                    out.append(req)
    return out


def _engines_text(engines: Iterable[str]) -> str:
    engines = list(engines)
    return f"engine{'s' if len(engines) > 1 else ''} {', '.join(engines)}"


def _check_suite(model: SuiteModel, label: str, errors: list[str], base: Path = REPO_ROOT) -> list[SweepBlock]:
    """Cross-checks pydantic cannot make: engines registered, scenario ids
    and variants exist, every grid key is a setting of the engines it applies
    to and every value is allowed by that setting.  Appends to ``errors``."""
    from adapters import engine_names, get_adapter
    from contract.scene import load_scene, resolve_scenario, scenario_ids, spec_targets
    from contract.spec import load_spec

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
                    loaded = load_spec(resolve_scenario(target))
                except SpecError as exc:
                    errors.append(f"{where}.scenarios[{j}]: scenario {target!r} does not load: {exc.errors[0]}")
                    continue
                if var is not None and var not in loaded.variants:
                    errors.append(f"{where}.scenarios[{j}]: scenario {target!r} has no variant {var!r}; "
                                  f"its variants: {', '.join(loaded.variants) or 'none'}")
                    continue
                try:
                    scene = load_scene(target, var, loaded=loaded)
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
    """Every point's recording fits the bounds (contract/spec.py
    record_size_error) at the smallest dt any engine sweeps: checked when
    the suite loads, before anything runs or is allocated."""
    from contract.scene import load_scene, n_steps
    from contract.spec import record_size_error

    for e, ax in axes.items():
        if "dt" not in ax:
            continue
        dt = min(float(v) for v in ax["dt"])
        for entry in scen:
            try:
                sc = load_scene(entry.path or entry.scenario, entry.variant)
            except SpecError:
                continue  # reported where the scenario is listed
            why = record_size_error(n_steps(sc.duration, dt), sc.n_bodies)
            if why:
                errors.append(f"{where}.grid.dt: {_label(entry.scenario, entry.variant)} at dt = {dt:g} on {e}: "
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
            if not any(s == sid or s == _label(sid, var) for sid, var in listed):
                raise ValueError(f"scenario {s} is not in suite {suite.name} "
                                 f"(its scenarios: {', '.join(sorted({_label(*x) for x in listed}))})")
    points: list[Point] = []
    seen: set[str] = set()
    for b in suite.sweeps:
        for entry in b.scenarios:
            sid, var = entry.scenario, entry.variant
            if scenarios is not None and sid not in scenarios and _label(sid, var) not in scenarios:
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


def _label(sid: str, var: str | None) -> str:
    return sid + (f"[{var}]" if var else "")


# ---------------------------------------------------------------------------
# machine id


# the machine id sweeps are filed under is the environment fingerprint's
# (harness/fingerprint.py): CPU model, family/model/stepping, arithmetic
# flags, cores and OS, never the host name
machine_id = _fingerprint_machine_id


# ---------------------------------------------------------------------------
# running one point (in a worker process or in-process)


@lru_cache(maxsize=64)
def _scene(scenario: str, variant: str | None):
    """``scenario``: an id or a spec file's path."""
    from contract.scene import load_scene

    return load_scene(scenario, variant)


def run_point(point: Point) -> dict[str, Any]:
    """Run one point: the first run gives the row (metrics, status); while
    runs are ``ok``, ``point.repeats`` runs in all are timed (metrics computed
    on the first only: the engines are deterministic, and metric code is not
    what is timed).  Only ok runs count in the median and minimum CPU time
    (``repeats`` of them); a run that is not ok is not repeated (the row's
    ``cpu_s_per_sim_s`` keeps the runner's figure for the part that ran).
    Never raises for engine trouble; returns the flat row with the point
    columns (the sweep-wide ones are added by the caller)."""
    from harness import runner

    t0 = time.perf_counter()
    try:
        scene = _scene(point.path or point.scenario, point.variant)
    except Exception as e:
        return _status_row(point, "error", f"scene failed to load: {type(e).__name__}: {e}", t0)
    if point.scene_hash and scene.content_hash != point.scene_hash:
        return _status_row(point, "error", f"scene changed since the sweep was planned (content hash "
                                           f"{scene.content_hash}, planned {point.scene_hash}); sweep again", t0)
    settings = point.engine_settings
    if point.phase:
        try:
            scene = request_scene(RunRequest(point.scenario, point.engine, point.variant, settings,
                                             phase=point.phase), base=scene)
        except PhaseError as e:
            return _status_row(point, "error", f"phase {point.phase:g}: {e}", t0, scene=scene)
    first = None
    cpu: list[float] = []
    # a blow-up is recorded in the status; numpy's overflow warnings on the
    # way there would only scramble the progress display
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for i in range(point.repeats):
            try:
                res = runner.run(scene, point.engine, settings, timeout_s=point.timeout_s,
                                 compute_metrics=(i == 0))
            except Exception as e:  # a bad setting combination, an adapter import error ...
                if first is None:
                    return _status_row(point, "failed", f"could not run: {type(e).__name__}: {e}", t0,
                                       scene=scene, tb=traceback.format_exc(limit=5))
                first.notes.append(f"repeat {i + 1} raised {type(e).__name__}: {e}; not timed")
                break
            res.trace = None
            if first is None:
                first = res
            if res.status != "ok":  # a partial run's cost is no point of a work-precision curve
                if res is not first:
                    first.notes.append(f"repeat {i + 1} ended {res.status} ({res.message}); not timed")
                break
            cpu.append(float(res.metrics.get("cpu_s_per_sim_s", math.nan)))
    row = first.row()
    row.update(_point_columns(point, scene, row, cpu, t0, first))
    return row


def _point_columns(point: Point, scene: Any, row: dict[str, Any], cpu: list[float], t0: float,
                   result: Any = None) -> dict[str, Any]:
    """The sweep's columns of a point's row.  ``checks`` (JSON) holds the
    scene's checks on this point's run (those that apply to the engine and
    variant, without an @-setting; evaluated as ``physbench check`` does),
    ``primary_threshold`` the check max on the primary metric: the report
    reads both from the row instead of reloading the scene."""
    from harness.conformance import applicable_checks, evaluate_check, primary_threshold, split_metric

    metric = getattr(scene, "primary_metric", None)
    value = row.get(metric) if metric else None
    try:
        err = float(value) if row.get("status") == "ok" and value is not None else math.nan
    except (TypeError, ValueError):
        err = math.nan
    finite = [c for c in cpu if math.isfinite(c)]
    checks = []
    if scene is not None and result is not None:
        checks = [evaluate_check(c, result).as_dict() for c in applicable_checks(scene, point.engine)
                  if not split_metric(c.metric)[1]]
    return {
        "point_key": point.key,
        "checks": json.dumps(checks, sort_keys=True),
        "primary_threshold": primary_threshold(scene) if scene is not None else None,
        "point_settings": point.settings_json,
        "phase": point.phase,
        "primary_metric": metric,
        "primary_error": err,
        "cpu_s_per_sim_s_median": statistics.median(finite) if finite else math.nan,
        "cpu_s_per_sim_s_min": min(finite) if finite else math.nan,
        "repeats": len(finite),
        "point_wall_s": time.perf_counter() - t0,
    }


def _status_row(point: Point, status: str, message: str, t0: float, scene: Any = None,
                tb: str | None = None, stderr_tail: str | None = None) -> dict[str, Any]:
    """A row for a point that produced no RunResult (scene failed to load,
    the run raised, the worker died)."""
    from adapters import get_adapter
    from harness.runner import RunResult, commit_id, machine_info

    settings = point.engine_settings
    version = ""
    try:
        cls = get_adapter(point.engine)
        version = cls.capabilities().version
        if scene is None:
            scene = _scene(point.path or point.scenario, point.variant)
        settings = cls.resolve_settings(scene, settings)
    except Exception:
        pass  # keep the swept settings only
    res = RunResult(point.scenario, point.variant, point.engine, version, status, message, settings,
                    machine=machine_info(), commit=commit_id(),
                    timestamp=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                    scene_hash=point.scene_hash, scene_path=getattr(scene, "source", "") or (point.path or ""))
    if tb:
        res.info["traceback"] = tb
    if stderr_tail:
        res.info["stderr_tail"] = stderr_tail
    row = res.row()
    row.update(_point_columns(point, scene, row, [], t0))
    return row


# ---------------------------------------------------------------------------
# storage


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


_write_json_atomic = write_json_atomic
_parts = list_parts
_try_lock = try_lock
_unfinished = unfinished_dirs


class _SweepDir(PartsDir):
    """An open (unfinished) sweep directory: one part per finished point,
    keyed by ``point_key`` (harness.results.PartsDir)."""

    def __init__(self, path: Path, manifest: dict[str, Any], lock_fd: int):
        super().__init__(path, manifest, lock_fd, "point_key")

    @property
    def sweep_id(self) -> str:
        return self.manifest["sweep_id"]

    def write_point(self, row: dict[str, Any]) -> Path:
        return self.write_part(row, {"sweep_id": self.sweep_id})


def confined(root: Path, *parts: str) -> Path:
    """``root / parts...``, each part a plain name (:func:`plain_name`), so
    that the path stays inside ``root`` whatever a suite or machine is
    called.  Raises SuiteError otherwise (a guard: load_suite and
    machine_id already make plain names)."""
    for part in parts:
        if not plain_name(part):
            raise SuiteError([f"{root}: <path>: {part!r} is not a plain name (letters, digits, '_', '-', '.', "
                              f"not starting with '.'); it would name a directory outside the results root"])
    return root.joinpath(*parts)


def _sweep_id(commit: str) -> str:
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    return f"{stamp}-{re.sub(r'[^A-Za-z0-9.+_-]', '_', commit)}"


def open_sweep(suite: Suite, points: list[Point], root: Path, resume: bool | None, jobs: int,
               executor: str, filters: dict[str, Any]) -> tuple[_SweepDir, bool]:
    """Find the sweep to resume or start a new one.  Returns (dir, resumed).

    Resume rule: an unfinished sweep directory of this suite on this machine
    whose manifest has the same suite-file hash and the same planned point
    keys is resumed -- automatically (``resume=None``) only if it was also
    started at the same commit, with ``resume=True`` whatever its commit (its
    rows keep their own ``commit``); ``resume=False`` always starts afresh.
    The newest match wins; a directory locked by a running sweep is skipped.
    """
    from harness.runner import commit_id, machine_info

    suite_dir = confined(root, machine_id(), suite.name)
    commit = commit_id()
    keys = [p.key for p in points]
    if resume is not False:
        for d, man in _unfinished(suite_dir):
            if (d.parent / f"{d.name}.parquet").exists():
                # consolidated, but killed before its manifest was written or
                # its directory removed: finish that (under its lock), never
                # resume it (its points are stored)
                fd = _try_lock(d)
                if fd >= 0:
                    try:
                        consolidate(d)
                    except (OSError, ValueError) as e:
                        print(f"warning: could not finish consolidating {d}: {type(e).__name__}: {e}",
                              file=sys.stderr)
                    finally:
                        os.close(fd)
                continue
            if man.get("suite_hash") != suite.file_hash or sorted(man.get("points", [])) != sorted(keys):
                continue
            if resume is None and man.get("commit") != commit:
                continue
            fd = _try_lock(d)
            if fd < 0:
                continue
            man.setdefault("resumed", []).append({"at": _now(), "commit": commit, "jobs": jobs,
                                                  "executor": executor})
            _write_json_atomic(man, d / "manifest.json")
            return _SweepDir(d, man, fd), True
        if resume:
            print(f"nothing to resume for suite {suite.name} (same suite file and points) under {suite_dir}; "
                  "starting a new sweep", file=sys.stderr)
    base = _sweep_id(commit)
    sid, n = base, 0
    while (suite_dir / sid).exists() or (suite_dir / f"{sid}.parquet").exists():
        n += 1  # two sweeps started in the same second: the later one sorts after
        sid = f"{base}-{n}"
    d = suite_dir / sid
    d.mkdir(parents=True)
    fd = _try_lock(d)
    man = {
        "schema_version": SCHEMA_VERSION,
        "suite": suite.name,
        "suite_file": _display(suite.path),
        "suite_hash": suite.file_hash,
        "sweep_id": sid,
        "commit": commit,
        "machine_id": machine_id(),
        "machine": machine_info(),
        "fingerprint": fingerprint(),
        "jobs": jobs,
        "executor": executor,
        "filters": filters,
        "started": _now(),
        "finished": None,
        "points": keys,
    }
    _write_json_atomic(man, d / "manifest.json")
    return _SweepDir(d, man, fd), False


def consolidate(d: Path) -> Path:
    """Merge the parts of sweep directory ``d`` into ``<d>.parquet`` (rows in
    planned order, one per point key), write ``<d>.manifest.json``, then --
    only once both are safely in place -- remove ``d``.  Returns the
    consolidated file's path."""
    man = json.loads((d / "manifest.json").read_text(encoding="utf-8"))
    out, _ = consolidate_parts(d, "point_key", list(man.get("points", [])), _now())
    return out


def sweep_files(root: str | Path | None = None, suites: Iterable[str] | None = None,
                machine: str | None = None, unfinished: bool = True) -> list[tuple[str, str, str, Path, bool]]:
    """Every stored sweep file under ``root`` (default results/sweeps/) as
    (machine_id, suite, sweep_id, path, complete): the consolidated
    ``<sweep_id>.parquet`` files and, with ``unfinished``, the parts of
    sweeps still running or killed -- unless their consolidated file exists
    (it wins over leftover parts).  Hidden files (temporary files about to
    be renamed into place) are skipped.  The one reader of the storage
    layout: the report and :func:`read_sweeps` both go through it."""
    root = Path(root) if root is not None else SWEEPS_DIR
    wanted = set(suites) if suites else None

    def visible(paths: Iterable[Path]) -> list[Path]:
        return sorted(p for p in paths if not p.name.startswith("."))

    out = []
    if not root.is_dir():
        return out
    for mdir in visible(p for p in root.iterdir() if p.is_dir()):
        if machine is not None and mdir.name != machine:
            continue
        for sdir in visible(p for p in mdir.iterdir() if p.is_dir()):
            if wanted is not None and sdir.name not in wanted:
                continue
            done = {p.stem: p for p in visible(sdir.glob("*.parquet"))}
            out += [(mdir.name, sdir.name, sid, p, True) for sid, p in done.items()]
            if unfinished:
                for d in visible(p for p in sdir.iterdir() if p.is_dir()):
                    if d.name not in done:
                        out += [(mdir.name, sdir.name, d.name, p, False) for p in visible(_parts(d))]
    return out


def read_sweeps(root: str | Path | None = None, suite: str | None = None, machine: str | None = None,
                unfinished: bool = False):
    """All consolidated sweep rows under ``root`` (default results/sweeps/)
    as one DataFrame, optionally one suite / one machine id; with
    ``unfinished`` also the parts of sweeps still running or killed."""
    import pandas as pd

    frames = [pd.read_parquet(f) for *_, f, _ in
              sweep_files(root, [suite] if suite else None, machine, unfinished)]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


# ---------------------------------------------------------------------------
# executing points


def _point_budget(p: Point) -> float:
    """Wall-clock budget of a point's worker: its timed runs, each within
    the suite's ``timeout_s``."""
    return p.timeout_s * max(1, p.repeats)


def run_points(todo: list[Point], executor: Any, on_row: Callable[[Point, dict[str, Any]], None],
               on_start: Callable[[Point], None]) -> None:
    """Run points through ``executor`` (harness/execute.py: a WorkerPool or
    the inline executor) and hand each row to ``on_row`` as it finishes.  A
    point whose worker dies or hangs (or whose code raises) gets an
    ``error``/``timeout`` row naming why; the other points are untouched."""
    for p, value in executor.map(run_point, todo, budget_s=_point_budget, on_start=on_start):
        if isinstance(value, WorkerLost):
            t0 = time.perf_counter()
            if value.kind == "died":
                msg = f"{value.full_message()}".replace("this item", "this point")
            elif value.kind == "timeout":
                msg = value.full_message()
            else:
                msg = f"point failed: {value.message}"
            value = _status_row(p, value.status, msg, t0, tb=value.traceback or None,
                                stderr_tail=value.stderr_tail or None)
        on_row(p, value)


# ---------------------------------------------------------------------------
# entry point


def summarize(df, wall_s: float, console=None, title: str = "") -> None:
    """Per engine: points and counts of each status, and ``time_s``, the
    wall time spent in its points (s, summed over points, repeats and metric
    computation included)."""
    from rich.console import Console
    from rich.table import Table

    if console is None:
        console = Console()
        if not console.is_terminal:  # a log file: do not squeeze the table into 80 columns
            console = Console(width=120)
    table = Table(title=title or "sweep", caption=f"wall time {wall_s:.1f} s")
    for col in ("engine", "points", *STATUSES, "time_s"):
        table.add_column(col, justify="left" if col == "engine" else "right")
    if len(df):
        for eng in dict.fromkeys(df["engine"]):
            sub = df[df["engine"] == eng]
            counts = sub["status"].value_counts()
            t = float(sub["point_wall_s"].sum()) if "point_wall_s" in sub else math.nan
            table.add_row(eng, str(len(sub)), *(str(int(counts.get(s, 0))) for s in STATUSES), f"{t:.1f}")
    console.print(table)


def _run_limits(reqs: list[Any], sd: "_SweepDir", ctx: dict[str, Any], jobs: int, err: Any) -> None:
    """The suite's breaking-point searches (``[[limit]]`` blocks), their rows
    stored in the sweep's directory like its points; evaluations stored by an
    interrupted run of this sweep are read back, not run again."""
    from harness.limits import RESULT_ROW, LockedWriter, describe, run_requests, stored_rows

    cached = stored_rows(_parts(sd.path))
    cached.update(stored_rows(_parts(sd.path), RESULT_ROW))
    err.print(f"limits: {len(reqs)} breaking-point searches ({len(cached)} stored rows read back)",
              markup=False, highlight=False)
    run_requests(reqs, LockedWriter(sd, ctx), cached, jobs,
                 on_done=lambda r, res, _s: err.print("limit: " + describe(res, r), markup=False,
                                                       highlight=False, soft_wrap=True))


def sweep_main(suite: str, engines: list[str] | None = None, jobs: int = 1, executor: str | None = None,
               out_dir: Path | None = None, resume: bool | None = None,
               scenarios: list[str] | None = None, timeout_s: float | None = None) -> int:
    """``physbench sweep``: run ``suite`` (a name under suites/ or a path)
    and store its rows under ``out_dir`` (default results/sweeps/).

    ``engines`` / ``scenarios`` restrict the suite; ``jobs`` worker processes
    with ``executor`` ``"process"`` (the default) or ``"serial"`` (in this
    process); ``timeout_s`` replaces the suite's per-run budget;
    ``resume``: None resumes an unfinished sweep of the same suite file,
    points and commit, True also across commits, False never (see
    :func:`open_sweep`).  Returns 0 when the sweep completed (failed runs are
    data, recorded as statuses), 2 for a bad suite file or arguments, 130
    when interrupted (the sweep can be resumed)."""
    from rich.console import Console
    from rich.markup import escape
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    err = Console(stderr=True)
    t_start = time.perf_counter()
    try:
        s = load_suite(suite)
    except SpecError as e:
        for line in e.errors:
            err.print(f"error: {line}", markup=False, highlight=False, soft_wrap=True)
        return 2
    try:
        points = expand(s, engines, scenarios)
    except ValueError as e:
        err.print(f"error: {e}", markup=False, highlight=False, soft_wrap=True)
        return 2
    if timeout_s is not None:
        points = [dataclasses.replace(p, timeout_s=float(timeout_s)) for p in points]
    jobs = max(1, int(jobs or 1))
    executor = executor or "process"
    if executor not in EXECUTORS:
        err.print(f"error: executor {executor!r}: expected one of {', '.join(EXECUTORS)}", markup=False, soft_wrap=True)
        return 2
    if executor == "serial" and jobs > 1:
        err.print(f"note: executor serial runs one point at a time; jobs={jobs} ignored")
        jobs = 1
    reqs = [r for r in s.limits if (engines is None or r.engine in engines)
            and (scenarios is None or r.scenario in scenarios or _label(r.scenario, r.variant) in scenarios)]
    if not points and not reqs:
        err.print(f"error: suite {s.name}: no points selected (engines {engines}, scenarios {scenarios})",
                  markup=False)
        return 2
    root = Path(out_dir) if out_dir is not None else SWEEPS_DIR
    filters = {"engines": engines, "scenarios": scenarios}
    sd, resumed = open_sweep(s, points, root, resume, jobs, executor, filters)
    ctx = {"suite": s.name, "sweep_id": sd.sweep_id, "machine_id": machine_id(), "sweep_jobs": jobs,
           "schema_version": SCHEMA_VERSION}
    todo = [p for p in points if p.key not in sd.done]
    err.print(f"sweep {s.name} ({_display(s.path)}): {len(points)} points on {', '.join(dict.fromkeys(p.engine for p in points))}"
              f"; {'resuming ' + sd.sweep_id + ': ' + str(len(points) - len(todo)) + ' done, ' if resumed else ''}"
              f"{len(todo)} to run, {executor} x{jobs}; rows under {sd.path}", markup=False, highlight=False, soft_wrap=True)
    if jobs > 1:
        err.print(f"note: {jobs} runs at a time compete for {os.cpu_count()} cores (and caches, memory "
                  "bandwidth): CPU times are not comparable with a --jobs 1 sweep; metrics are unaffected", soft_wrap=True)
    cols = (TextColumn("[bold]sweep"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            TextColumn("{task.description}"))
    try:
        with Progress(*cols, console=err, disable=not err.is_terminal) as bar:
            task = bar.add_task("", total=len(todo))

            def on_start(p: Point) -> None:
                bar.update(task, description=escape(f"{p.engine} {p.label} {p.settings_json}"))

            def on_row(p: Point, row: dict[str, Any]) -> None:
                row.update(ctx)
                sd.write_point(row)
                bar.advance(task)

            with make_executor(executor, jobs) as ex:
                run_points(todo, ex, on_row, on_start)
        if reqs:
            _run_limits(reqs, sd, ctx, jobs if executor == "process" else 1, err)
    except KeyboardInterrupt:
        err.print(f"interrupted: {len(sd.done)} of {len(points)} points stored in {sd.path}; "
                  "run the same sweep again to resume it", markup=False, soft_wrap=True)
        sd.close()
        return 130
    except BaseException:
        sd.close()
        raise
    try:  # still locked: a sweep started meanwhile must not resume this directory
        out = consolidate(sd.path)
    finally:
        sd.close()
    import pandas as pd

    df = pd.read_parquet(out)
    wall = time.perf_counter() - t_start
    if "row_kind" in df.columns:  # breaking-point rows: summarized as their searches finished
        df = df[df["row_kind"].isna()]
    if len(df) or not reqs:
            summarize(df, wall, title=f"sweep {s.name} {sd.sweep_id}: {len(df)} points"
                                  + (f" ({len(points) - len(todo)} from before the resume)" if resumed else ""))
    err.print(f"rows written to {out}", markup=False, highlight=False, soft_wrap=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(sweep_main(sys.argv[1] if len(sys.argv) > 1 else "nightly"))
