"""Breaking points: ``physbench limits``.

Where does an engine stop holding a scene?  One parameter -- an engine
setting (``dt``, ``iterations``) or any dotted spec key, an element of a
vector included (``body[0].velocity[0]``, ``body[1].mass``,
``material.default.restitution``) -- is moved over a range, and the search
finds the value at which the scene stops meeting its checks or stops being
stable.

Three layers, kept apart so that the search can be tested on a fake
criterion:
- harness/limit_search.py -- pure logic: bracket, then bisect, on a
  criterion ``value -> Verdict``; no runs, no storage (the walk and the
  tolerance are described there).
- harness/limit_eval.py -- one run of one value in one step phase, turned
  into a stored row with its verdict (the criterion is described there),
  and a search driven by such rows.
- this module -- rows stored like sweep rows (``harness/sweep_store.py``:
  atomic parts, resumable: a rerun reads finished evaluations back instead
  of running them again), request validation and the command.

The names of the two modules below are re-exported here, where the
command line, suites, sweeps, the scheduler and the tests import them.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from physbench.adapters import engine_names, get_adapter
from physbench.contract.phase import PhaseError, shift_scene
from physbench.contract.scene import resolve_scenario
from physbench.contract.spec import SpecError
from physbench.harness.conformance import applicable_checks, split_metric
from physbench.harness.results import SCHEMA_VERSION, read_frame
from physbench.harness.runner import commit_id
from physbench.harness.sweep_store import consolidate, machine_id, open_sweep, sweep_files, sweeps_dir
from physbench.harness.limit_eval import load_at as _load_at
from physbench.harness.limit_eval import (EVAL_ROW, RESULT_ROW, EvalItem, LimitRequest, Runner, evaluate_item,
                                evaluate_point, is_engine_setting, judge, load_at, lost_eval_row, run_search,
                                search_items, spec_hash, verdict_of_rows)
from physbench.harness.limit_search import (FAILS_THROUGHOUT, FOUND, HOLDS_THROUGHOUT, MAX_WALK, UNSUPPORTED,
                                            SearchResult, Verdict, drive, search, search_rounds, search_steps)

__all__ = ["EVAL_ROW", "FAILS_THROUGHOUT", "FOUND", "HOLDS_THROUGHOUT", "LIMITS_SUITE", "MAX_WALK", "RESULT_ROW",
           "UNSUPPORTED", "EvalItem", "LimitRequest", "Runner", "SearchResult", "Verdict", "describe", "drive",
           "evaluate_item", "evaluate_point", "is_engine_setting", "judge", "limits_main", "load_at",
           "lost_eval_row", "parse_number", "run_search", "search", "search_items", "search_rounds", "search_steps", "spec_hash",
           "stored_rows", "validate_request", "verdict_of_rows"]

#: the suite name under which ``physbench limits`` stores its rows
LIMITS_SUITE = "limits"


# ---------------------------------------------------------------------------
# running a search with stored, resumable rows

def stored_rows(paths: list[Path], kind: str = EVAL_ROW) -> dict[str, dict[str, Any]]:
    """Rows of ``kind`` in the Parquet files ``paths``, by point key (the
    first stored wins)."""
    out: dict[str, dict[str, Any]] = {}
    for p in paths:
        try:
            df = read_frame(p)
        except Exception:
            continue
        if "row_kind" not in df.columns:
            continue
        for r in df[df["row_kind"] == kind].to_dict("records"):
            out.setdefault(r["point_key"], r)
    return out


# ---------------------------------------------------------------------------
# physbench limits


@dataclass(frozen=True)
class _SearchSuite:
    """What :func:`harness.sweep_store.open_sweep` needs of a suite: a name, a hash
    naming what is planned, and a path for the manifest."""

    name: str
    file_hash: str
    path: Path


def parse_number(text: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"{what}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{what}: expected a finite number, got {text!r}")
    return v


def validate_request(req: LimitRequest, scenes: dict[Any, Any] | None = None) -> list[str]:
    """Problems with a request, one line each (empty: fine): the scenario
    loads, the engine exists, the parameter is a setting of the engine or a
    spec key the scene accepts at both ends of the range, the phases are
    possible.  ``scenes``: the scenes loaded so far, shared between the
    requests of a suite (harness.suite's check: one search block is a
    request per engine, all loading the same scenes at the same ends)."""

    errs: list[str] = []
    scenes = {} if scenes is None else scenes

    def load_at(req: LimitRequest, value: float) -> Any:  # each end's scene loaded once (SpecError: each time)
        # what harness.limit_eval.load_at loads: for an engine setting the scene as written, whatever the value
        key = (req.scenario, req.variant, repr(req.overrides)) + (
            (None,) if is_engine_setting(req.engine, req.param) else (req.param, value))
        if key not in scenes:
            scenes[key] = _load_at(req, value)
        return scenes[key]

    if req.engine not in engine_names():
        return [f"--engine: unknown engine {req.engine!r}; known: {', '.join(engine_names())}"]
    if not (req.lo < req.hi):
        errs.append(f"--range: expected LO < HI, got {req.lo!r} {req.hi!r}")
    if not (0.0 < req.tol < 1.0):
        errs.append(f"--tol: expected a relative tolerance 0 < tol < 1, got {req.tol!r}")
    if not (1 <= req.phases <= 1024):
        errs.append(f"--phases: expected 1 .. 1024, got {req.phases!r}")
    caps = get_adapter(req.engine).capabilities()
    if req.param in caps.settings:
        st = caps.settings[req.param]
        if st.kind not in (int, float):
            errs.append(f"--param {req.param}: setting of engine {req.engine} is not a number ({st.kind.__name__})")
        for end in (req.lo, req.hi):
            try:
                st.coerce(int(end) if st.kind is int and float(end).is_integer() else end)
            except (ValueError, TypeError) as e:
                errs.append(f"--range: {end!r} for setting {req.param}: {e}")
        if req.param == "dt" and req.lo <= 0:
            errs.append(f"--range: dt must be positive, got LO = {req.lo!r}")
        try:
            load_at(req, req.lo)
        except SpecError as e:
            errs.extend(f"--set: {m}" for m in e.errors)
    elif "." in req.param or "[" in req.param:
        for end in (req.lo, req.hi):
            try:
                load_at(req, end)
            except SpecError as e:
                errs.append(f"--param {req.param} = {end!r}: {e.errors[0]}")
            except ValueError as e:
                errs.append(f"--param {req.param}: {e}")
    else:
        errs.append(f"--param {req.param}: not a setting of engine {req.engine} ({', '.join(caps.settings)}) "
                    f"and not a dotted spec key (e.g. body[0].velocity[0], material.default.restitution)")
    if req.checks:
        try:
            sc = load_at(req, req.lo)

            have = {split_metric(c.metric)[0] for c in applicable_checks(sc, req.engine)} | {"stable"}
            for m in req.checks:
                if m not in have:
                    errs.append(f"--check {m}: no check of this metric applies to {req.label} on {req.engine} "
                                f"(its checks: {', '.join(sorted(have)) or 'none'})")
        except (SpecError, ValueError):
            pass  # reported above
    for m, b in req.bounds:
        if not (isinstance(b, (int, float)) and math.isfinite(b)):
            errs.append(f"--max {m}: expected a finite number, got {b!r}")
    for k, v in req.settings:
        if k == req.param:
            errs.append(f"--set {k}: is the searched parameter")
        elif k not in caps.settings:
            errs.append(f"--set {k}: not a setting of engine {req.engine} ({', '.join(caps.settings)})")
        else:
            try:
                caps.settings[k].coerce(v)
            except ValueError as e:
                errs.append(f"--set {k}={v!r}: {e}")
    if errs:
        return errs
    if req.phases > 1:
        try:
            sc = load_at(req, req.lo)
            dt = req.lo if req.param == "dt" else dict(req.settings).get("dt", sc.dt)
            shift_scene(sc, (req.phases - 1) / req.phases, dt=float(dt))
        except PhaseError as e:
            errs.append(f"--phases {req.phases}: step phases need a start in free flight: {e}")
    return errs


def describe(res: SearchResult, req: LimitRequest) -> str:
    """The answer in one paragraph of text."""
    where = f"{req.label} on {req.engine}, {req.param} in [{req.lo:g}, {req.hi:g}]"
    cost = f"{res.runs} runs, {res.cpu_s:.2f} s CPU"
    if res.outcome == FOUND:
        side = "below" if res.direction == "below" else "above"
        return (f"{where}: limit {req.param} = {res.limit:.6g} (holds {side}; bracket "
                f"[{res.bracket[0]:.6g}, {res.bracket[1]:.6g}]); just past it: {res.failed_check}; {cost}")
    if res.outcome == HOLDS_THROUGHOUT:
        return f"{where}: holds over the whole range ({cost})"
    if res.outcome == UNSUPPORTED:
        return f"{where}: {res.failed_check}"
    return f"{where}: fails at both ends of the range: {res.failed_check} ({cost})"


def limits_main(req: LimitRequest, out_dir: Path | None = None, as_json: bool = False) -> int:
    """``physbench limits``: search ``req``, store its rows under
    ``<out_dir>/<machine>/limits/`` (default results/sweeps/), print the
    answer (``as_json``: one JSON object on stdout, nothing else there).
    A search interrupted or rerun at the same commit reads its finished
    evaluations back.  Returns 0 (the search ran; its outcome is data), 2
    for bad input, 130 when interrupted."""

    errs = validate_request(req)
    if errs:
        for e in errs:
            print(f"error: {req.label}: {e}", file=sys.stderr)
        return 2
    root = Path(out_dir) if out_dir is not None else sweeps_dir()
    limit_id = req.identity(spec_hash(req))

    commit = commit_id()
    # finished evaluations of this search at this commit: every stored file of
    # the limits suite (consolidated or parts) whose rows carry this limit_id
    files = [p for m, _s, _sid, p, _c in sweep_files(root, [LIMITS_SUITE], machine_id(), unfinished=True)]
    cached = {k: r for k, r in stored_rows(files).items()
              if r.get("limit_id") == limit_id and r.get("commit") == commit}

    suite = _SearchSuite(LIMITS_SUITE, limit_id, Path(resolve_scenario(req.scenario)))
    sd = None
    lock = threading.Lock()

    def store(row: dict[str, Any]) -> None:
        nonlocal sd
        with lock:
            if sd is None:
                sd, _ = open_sweep(suite, [], root, None, 1, "serial", {"limit": dataclasses.asdict(req)})
            row.update({"suite": LIMITS_SUITE, "sweep_id": sd.sweep_id, "machine_id": machine_id(),
                        "sweep_jobs": 1, "schema_version": SCHEMA_VERSION})
            sd.write_point(row)

    try:
        res, summary = run_search(req, store, cached)
    except KeyboardInterrupt:
        print(f"interrupted: finished evaluations stored under {root}; run the same command again to resume",
              file=sys.stderr)
        if sd is not None:
            sd.close()
        return 130
    if sd is not None:
        store(summary)
        try:
            out = consolidate(sd.path)
        finally:
            sd.close()
        print(f"rows written to {out}", file=sys.stderr)
    else:
        print(f"all {res.runs} runs read back from stored rows (same search, same commit)", file=sys.stderr)
    if as_json:
        sys.stdout.write(json.dumps(res.as_dict(), default=float) + "\n")
        sys.stdout.flush()
    else:
        print(describe(res, req))
    return 0
