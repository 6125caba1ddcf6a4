"""Planning a check: ``RunSpec`` (one run to make), the scenarios selected,
the runs each scene's checks take (base run, step phases, @-settings), and
the outcomes of the planned runs once their results are in."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from physbench.adapters import ENGINES, engine_names, get_adapter
from physbench.contract.metric_defs import CONSENSUS_METRICS
from physbench.contract.scene import Check, Scene, load_scene, resolve_scenario, scenario_ids, spec_targets
from physbench.contract.spec import SpecError, load_spec
from physbench.harness.conformance.verdicts import (ERROR, Outcome, applicable_checks, check_applies, combine_phases,
                                                    describe_bound, evaluate_check, hard_checks, scene_columns,
                                                    split_metric)
from physbench.harness.ensemble import ENSEMBLE_METRICS, Perturbation
from physbench.harness.execute import DEFAULT_TIMEOUT_S, RunRequest

RUN_TIMEOUT_S = DEFAULT_TIMEOUT_S  # wall-clock budget per run (--timeout)


@dataclass
class RunSpec:
    """One run to make: a scene (scenario + variant) on an engine with
    setting overrides, and the checks to evaluate on it."""

    scenario: str
    variant: str | None
    engine: str
    settings: dict[str, Any] = field(default_factory=dict)
    checks: list[Check] = field(default_factory=list)
    #: step phase of the run (contract/phase.py); phase runs of a base run
    #: carry its checks too, and its outcome combines them
    phase: float = 0.0
    #: the base run's phases (``[scenario] phases``), on the base run only
    phases: int = 1
    #: the spec file (None: ``scenario`` is an id under scenarios/)
    path: str | None = None
    #: columns added to the run's row (primary metric and its threshold)
    row_extra: dict[str, Any] = field(default_factory=dict)
    #: wall-clock budget of the run (s); not part of its identity
    timeout_s: float | None = RUN_TIMEOUT_S
    #: an ensemble of perturbed starts instead of one run
    #: (harness.ensemble.Perturbation; harness.ensemble.ensemble_result):
    #: the run of the scene's checks on ENSEMBLE_METRICS (``predictable``)
    ensemble: Any = None
    #: the engines of a consensus run (engine ``consensus``: their runs at
    #: dt / k^2 compared, harness.consensus.consensus_result); () otherwise
    consensus: tuple = ()

    @property
    def key(self) -> tuple:
        base = (self.scenario, self.variant, self.engine, tuple(sorted(self.settings.items())))
        return (base + ((self.phase,) if self.phase else ()) + (("ensemble", self.ensemble) if self.ensemble else ())
                + (("consensus", self.consensus) if self.consensus else ()))

    @property
    def run_key(self) -> str:
        """The run's identity as text (the ``run_key`` column of check rows):
        ``scenario[variant]|engine|{settings}|phase``, and for an ensemble
        ``|ensemble{perturbation}``."""
        v = f"[{self.variant}]" if self.variant else ""
        settings = json.dumps(dict(sorted(self.settings.items())), sort_keys=True, separators=(",", ":"))
        out = f"{self.scenario}{v}|{self.engine}|{settings}|{self.phase!r}"
        if self.ensemble:
            import dataclasses

            out += "|ensemble" + json.dumps(dataclasses.asdict(self.ensemble), sort_keys=True, separators=(",", ":"))
        if self.consensus:
            out += "|consensus" + json.dumps(list(self.consensus), separators=(",", ":"))
        return out

    def request(self) -> RunRequest:
        return RunRequest(self.path or self.scenario, self.engine, self.variant, dict(self.settings),
                          phase=self.phase, timeout_s=self.timeout_s, ensemble=self.ensemble,
                          consensus=tuple(self.consensus))


def select_scenarios(scenarios: list[str] | None, tags: list[str] | None) -> list[str]:
    """The scenarios to check, as targets for :func:`plan`: every id of
    scenarios/ by default; else each entry of ``scenarios`` -- an id stays
    an id, a spec file or a folder (all ``*.toml`` below it, sorted) becomes
    the files' paths, anywhere on disk.  An entry that is neither raises
    SpecError (exit 2).  ``tags`` keeps the scenarios that have any of them
    (a spec that does not load is kept: it is reported, never dropped)."""
    if scenarios:
        ids: list[str] = []
        for entry in scenarios:
            for t in spec_targets(entry):
                if t not in ids:
                    ids.append(t)
    else:
        ids = scenario_ids()
    if not tags:
        return ids
    keep = []
    for sid in ids:
        try:
            sc = load_scene(sid)
        except Exception:
            keep.append(sid)  # a broken spec is reported, never silently dropped
            continue
        if set(sc.tags) & set(tags):
            keep.append(sid)
    return keep


def default_engines(note: bool = True) -> list[str]:
    """The engines ``check`` runs when none are named: every registered
    engine (shipped, plug-ins) except shipped ones that are not installed
    (their extra was not: stderr says which, unless ``note`` is False;
    ``--engines`` naming one still runs it, as ``unsupported`` rows).  A
    plug-in that fails to load stays in: its rows carry its error."""
    import sys

    out, missing = [], []
    for name in engine_names():
        try:
            available = get_adapter(name).capabilities().available
        except Exception:
            available = name not in ENGINES
        (out if available else missing).append(name)
    if missing and note:
        print(f"check: left out, not installed: {', '.join(missing)} (pip install "
              f"'physbench[{','.join(missing)}]' adds them)", file=sys.stderr)
    return out


def engine_names_in_checks(scene: Scene, label: str, known: Iterable[str] | None = None) -> tuple[list[str], list[str]]:
    """The engine names a scene's checks give (``engines = [...]`` and the
    keys of ``xfail``), held against the engines registered here
    (``known``, default :func:`physbench.adapters.engine_names`: the shipped
    ones and the plug-ins installed).  Returns (errors, not installed):

    - an unregistered name that is a near miss of a registered one
      (``"mujocco"``) is a spec error naming the key path and the likely
      name: a typo would silently drop the check, or hang an xfail on no
      engine (tests/test_conformance.py::test_check_engine_names_are_validated);
    - any other unregistered name is taken as a plug-in engine not installed
      here: allowed (the scene may serve other machines), and listed, one
      line per key path, so that a check that does not run says why.

    Only the names are read: an xfail value may be a reason or a table."""
    import difflib

    if known is None:
        known = engine_names()
    known = list(known)
    errors: list[str] = []
    absent: list[str] = []
    for i, c in enumerate(scene.checks):
        places = [(f"check[{i}].engines", e) for e in (c.engines or ())]
        places += [(f"check[{i}].xfail.{e}", e) for e in c.xfail]
        for key, name in places:
            if name in known:
                continue
            # a near miss: similarity >= 0.8 ("mujocco", "pybulet"; "mujoco_mjx" is not one)
            near = difflib.get_close_matches(name, known, n=1, cutoff=0.8)
            if near:
                errors.append(f"{label}: {key}: unknown engine {name!r}; did you mean {near[0]!r}? "
                              f"(engines here: {', '.join(known)})")
            else:
                absent.append(f"{label}: {key}: engine {name!r} is not installed here (engines here: "
                              f"{', '.join(known)}); its checks run only where it is")
    return errors, absent


def idle_reason(scene: Scene, engines: Iterable[str]) -> str:
    """Why no check of ``scene`` applies to any of ``engines`` (``physbench
    check`` says it once per scene, and exits 5 when nothing at all ran)."""
    engines = list(engines)
    if not scene.checks:
        return "no [[check]] tables" + (" (the base scene is not tagged 'hard')" if scene.variant is None else "")
    whys = []
    for c in scene.checks:
        if c.variants is not None and (scene.variant or "base") not in c.variants:
            whys.append(f"{c.metric}: variants {list(c.variants)} only")
        elif c.engines is not None:
            whys.append(f"{c.metric}: engines {list(c.engines)} only")
    return (f"none of its {len(scene.checks)} checks applies to engines {', '.join(engines)}"
            + (f" ({'; '.join(whys)})" if whys else ""))


def _load_error_outcomes(sid: str, variant: str | None, engines: Iterable[str], message: str) -> list[Outcome]:
    return [Outcome(e, sid, variant, "load", ERROR, message=message) for e in engines]


def ensemble_checks(scene: Scene, engine: str, ensemble: dict[str, Any] | None) -> list[Check]:
    """The checks of ``scene`` on ``engine`` that its ensemble answers
    (metrics in harness.ensemble.ENSEMBLE_METRICS), and with ``ensemble``
    (``check --ensemble N``) on a base scene the implicit ``predictable ==
    True`` unless the scene declares a ``predictable`` check itself."""
    out = [c for c in scene.checks if check_applies(c, engine, scene.variant)
           and split_metric(c.metric)[0] in ENSEMBLE_METRICS]
    if ensemble and scene.variant is None and not any(c.metric == "predictable" for c in scene.checks):
        out.append(Check(metric="predictable", equals=True))
    return out


def ensemble_spec(scene: Scene, ensemble: dict[str, Any] | None):
    """The Perturbation of ``scene``'s ensemble: its ``[perturbation]``
    with the ``check --ensemble N --sigma S --threshold T`` values over it
    (``ensemble``: n, position, threshold; None values left out).  Raises
    ValueError (no noise: neither a block nor --sigma)."""
    return Perturbation.of_scene(scene, **(ensemble or {}))


def scene_runs(scene: Scene, engine: str, settings: dict[str, Any] | None = None, path: str | None = None,
               phases: int | None = None, timeout_s: float | None = RUN_TIMEOUT_S,
               ensemble: dict[str, Any] | None = None, ensembles: bool = False) -> list[RunSpec]:
    """The runs that evaluating ``scene``'s checks on ``engine`` takes, the
    base run first (settings ``settings``, carrying the checks); then its
    step phases (``phases``, default the scene's); then one run per
    @-suffixed check setting (``settings`` with the suffix's over them);
    with ``ensembles``, last, the ensemble run of the checks on its
    measures (:func:`ensemble_checks`; ``ensemble`` the CLI's values over
    the scene's ``[perturbation]``; its budget ``timeout_s`` per member).
    Without ``ensembles`` (``physbench run``) those checks are left out.
    Empty when no check applies.  ``physbench check`` and ``physbench run``
    both plan with it, so both give the same verdict.  Each run has the
    wall-clock budget ``timeout_s``."""
    ens = ensemble_checks(scene, engine, ensemble) if ensembles else []
    ens_run: list[RunSpec] = []
    if ens:
        p = ensemble_spec(scene, ensemble)  # ValueError: planned as a load error (plan)
        ens_run = [RunSpec(scene.id, scene.variant, engine, dict(settings or {}), ens, path=path,
                           row_extra={**scene_columns(scene), "ensemble": json.dumps(_asdict(p), sort_keys=True)},
                           timeout_s=None if timeout_s is None else timeout_s * p.n, ensemble=p)]
    checks = applicable_checks(scene, engine) + hard_checks(scene)
    if not checks:
        return ens_run
    settings = dict(settings or {})
    n = scene.phases if phases is None else phases
    extra = scene_columns(scene)
    runs = [RunSpec(scene.id, scene.variant, engine, settings, checks, phases=n, path=path, row_extra=extra,
                    timeout_s=timeout_s)]
    for i in range(1, n):
        runs.append(RunSpec(scene.id, scene.variant, engine, settings, [], phase=i / n, path=path, row_extra=extra,
                            timeout_s=timeout_s))
    suffixes = {}
    for c in checks:
        _, st = split_metric(c.metric)
        if st:
            suffixes[c.metric.partition("@")[2]] = st
    for st in suffixes.values():
        runs.append(RunSpec(scene.id, scene.variant, engine, {**settings, **st}, [], path=path, row_extra=extra,
                            timeout_s=timeout_s))
    return runs + ens_run


#: the engine name of a consensus run's row and outcomes
CONSENSUS = "consensus"


def consensus_runs(scene: Scene, engines: list[str], path: str | None = None,
                   timeout_s: float | None = RUN_TIMEOUT_S) -> list[RunSpec]:
    """The consensus run of ``scene``'s checks on CONSENSUS_METRICS
    (``consensus_spread``), one per set of engines they name (a check's
    ``engines``, else all of ``engines``): engine :data:`CONSENSUS`, the
    engines in ``consensus``, the budget ``timeout_s`` per engine."""
    groups: dict[tuple, list[Check]] = {}
    for c in scene.checks:
        if c.metric not in CONSENSUS_METRICS or (c.variants is not None and (scene.variant or "base") not in c.variants):
            continue
        who = tuple(e for e in engines if c.engines is None or e in c.engines)
        groups.setdefault(who, []).append(c)
    return [RunSpec(scene.id, scene.variant, CONSENSUS, {}, cs, path=path, row_extra=scene_columns(scene),
                    timeout_s=None if timeout_s is None else timeout_s * max(1, len(who)), consensus=who)
            for who, cs in groups.items()]


def _asdict(p: Any) -> dict[str, Any]:
    import dataclasses

    return dataclasses.asdict(p)


def plan(scenario_ids: list[str], engines: list[str],
         timeout_s: float | None = RUN_TIMEOUT_S, notes: list[str] | None = None,
         idle: list[tuple[str, str | None, str]] | None = None,
         settings: dict[str, dict[str, Any]] | None = None,
         ensemble: dict[str, Any] | None = None) -> tuple[list[RunSpec], list[Outcome]]:
    """Runs to make (each with the wall-clock budget ``timeout_s``), and
    ERROR outcomes for scenarios that fail to load (a check naming an
    unknown engine is such a failure: :func:`engine_names_in_checks`).
    ``scenario_ids``: ids or spec file paths (:func:`select_scenarios`).
    Two files with the same id (family.stem) raise SpecError: their rows
    could not be told apart.  ``notes`` (when given) receives a line per
    check engine that is not installed here; ``idle`` a (scenario,
    variant, :func:`idle_reason`) per scene to which no check applies.
    ``settings``: engine -> setting overrides of every run on it.
    ``ensemble`` (``check --ensemble N``: n, position, threshold): every
    base scene with a ``[perturbation]`` block (or any, with a position
    sigma) also gets the check ``predictable == True`` on its ensemble."""
    runs: list[RunSpec] = []
    errors: list[Outcome] = []
    seen: dict[str, str] = {}
    for sid in scenario_ids:
        try:
            loaded = load_spec(resolve_scenario(sid))
        except Exception as e:
            errors += _load_error_outcomes(sid, None, engines, f"spec failed to load: {e}")
            continue
        # an id is run by its id; a file given by path is run from it
        # (absolute: workers run in their own directory;
        # test_check_runs_a_relative_spec_path_in_worker_processes)
        path = str(loaded.path.resolve()) if (Path(sid).suffix == ".toml" or Path(sid).exists()) else None
        for variant in [None, *loaded.variants]:
            try:
                scene = load_scene(sid, variant, loaded=loaded)
                bad, absent = engine_names_in_checks(scene, loaded.label)
                if bad:
                    raise SpecError(bad)
            except Exception as e:
                errors += _load_error_outcomes(sid, variant, engines, f"scene failed to compile: {e}")
                continue
            if notes is not None and variant is None:
                notes.extend(a for a in absent if a not in notes)
            if variant is None:
                where = str(loaded.path.resolve())
                if seen.setdefault(scene.id, where) != where:
                    raise SpecError([f"{loaded.label}: <scenario>: id {scene.id!r} (family.stem) is also the id of "
                                     f"{seen[scene.id]}; rename one file or change its family"])
            n = len(runs)
            try:
                for eng in engines:
                    runs += scene_runs(scene, eng, (settings or {}).get(eng), path=path, timeout_s=timeout_s,
                                       ensemble=ensemble, ensembles=True)
            except ValueError as e:  # an ensemble check without noise to draw
                runs = runs[:n]
                if ensemble and not scene.perturbation and not any(
                        split_metric(c.metric)[0] in _ensemble_metrics() for c in scene.checks):
                    if notes is not None:
                        notes.append(f"{scene.id}: no ensemble: no [perturbation] block and no --sigma")
                    for eng in engines:
                        runs += scene_runs(scene, eng, (settings or {}).get(eng), path=path, timeout_s=timeout_s)
                else:
                    errors += _load_error_outcomes(sid, variant, engines, f"ensemble: {e}")
            runs += consensus_runs(scene, engines, path=path, timeout_s=timeout_s)
            if idle is not None and len(runs) == n:
                idle.append((scene.id, variant, idle_reason(scene, engines)))
    return runs, errors


def _ensemble_metrics() -> tuple[str, ...]:
    return ENSEMBLE_METRICS


def evaluate_runs(runs: list[RunSpec], results: dict[tuple, Any]) -> list[Outcome]:
    """Outcomes for every planned base run (runs with checks), each with the
    key of the run it was evaluated on."""
    outs: list[Outcome] = []
    for r in runs:
        if not r.checks:
            continue
        res = results[r.key]
        for c in r.checks:
            name, st = split_metric(c.metric)
            if st:
                key = RunSpec(r.scenario, r.variant, r.engine, {**r.settings, **st}).key
                other = results.get(key)
                if other is None:
                    o = Outcome(r.engine, r.scenario, r.variant, c.metric, ERROR,
                                threshold=describe_bound(c), message="run missing")
                else:
                    o = evaluate_check(c, other, name)
            elif r.phases > 1:
                per = [evaluate_check(c, res)]
                for i in range(1, r.phases):
                    other = results.get(r.key + (i / r.phases,))
                    per.append(evaluate_check(c, other) if other is not None else
                               Outcome(r.engine, r.scenario, r.variant, c.metric, ERROR,
                                       threshold=describe_bound(c), message=f"phase {i}/{r.phases} run missing"))
                o, key = combine_phases(per, c), r.key
            else:
                o, key = evaluate_check(c, res), r.key
            o.key = key
            outs.append(o)
    return outs
