"""The check's store: one row part per finished run, resumable by the next
same check (its identity), consolidated at the end."""

from __future__ import annotations

import datetime as _dt
import hashlib
import re
import sys
import time
from pathlib import Path
from typing import Any

from physbench.contract.scene import resolve_scenario
from physbench.harness import runner  # runner.commit_id read at call time (tests pretend another commit)
from physbench.harness.conformance.plan import RunSpec
from physbench.harness.results import (SCHEMA_VERSION, PartsDir, results_dir, try_lock, unfinished_dirs,
                                       write_json_atomic, write_rows)


def result_row(key: tuple, result: Any) -> dict[str, Any]:
    row = result.row()
    # the step phase of the run (a float 5th key element; 0 = the scene as
    # written; an ensemble's key ends in ("ensemble", perturbation) instead)
    row["phase"] = float(key[4]) if len(key) > 4 and isinstance(key[4], float) else 0.0
    return row


def save_rows(results: dict[tuple, Any], save_dir: str | Path | None) -> Path | None:
    """Every run's result row to ``<save_dir>/<UTC timestamp>.parquet``
    (default results/check/) in one file; a failure to write is reported,
    not fatal.  (``check_main`` stores rows as they finish instead.)"""
    if not results:
        return None
    d = Path(save_dir) if save_dir is not None else results_dir() / "check"
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    rows = [result_row(key, r) for key, r in results.items()]
    try:
        return write_rows(rows, d / f"{stamp}.parquet", append=False)
    except Exception as e:  # pragma: no cover - disk trouble must not hide the verdict
        print(f"warning: could not write result rows: {type(e).__name__}: {e}", file=sys.stderr)
        return None


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def check_identity(ids: list[str], engines: list[str], runs: list[RunSpec], timeout_s: float | None) -> dict[str, Any]:
    """What makes two checks "the same" (resumable one from the other): the
    commit (a dirty tree counts as its commit: code edited between the
    kill and the rerun is not noticed), the engines, the scenario ids, the
    bytes of their spec files (sha256), the per-run budget, and the planned
    run keys."""
    h = hashlib.sha256()
    for sid in ids:
        h.update(sid.encode() + b"\0")
        try:
            h.update(resolve_scenario(sid).read_bytes())
        except Exception as e:  # reported as a load error outcome
            h.update(repr(e).encode())
        h.update(b"\0")
    return {"commit": runner.commit_id(), "engines": list(engines), "scenarios": list(ids),
            "specs_hash": h.hexdigest()[:16], "timeout_s": timeout_s, "runs": [r.run_key for r in runs]}


def open_check(root: Path, ident: dict[str, Any], resume: bool = True):
    """The unfinished check under ``root`` to resume (same identity, see
    :func:`check_identity`, not locked by a running check), or a new one.
    Returns (harness.results.PartsDir keyed by ``run_key``, resumed)."""
    if resume:
        for d, man in unfinished_dirs(root):
            if (d.parent / f"{d.name}.parquet").exists():
                continue  # consolidated; only its directory was left behind
            if any(man.get(k) != v for k, v in ident.items()):
                continue
            fd = try_lock(d)
            if fd < 0:
                continue
            man.setdefault("resumed", []).append(utc_now())
            write_json_atomic(man, d / "manifest.json")
            return PartsDir(d, man, fd, "run_key"), True
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    base = f"{stamp}-{re.sub(r'[^A-Za-z0-9.+_-]', '_', ident['commit'])}"
    cid, n = base, 0
    while (root / cid).exists() or (root / f"{cid}.parquet").exists():
        n += 1
        cid = f"{base}-{n}"
    d = root / cid
    d.mkdir(parents=True)
    fd = try_lock(d)
    man = {"schema_version": SCHEMA_VERSION, "check_id": cid, "started": utc_now(), "finished": None, **ident}
    write_json_atomic(man, d / "manifest.json")
    return PartsDir(d, man, fd, "run_key"), False
