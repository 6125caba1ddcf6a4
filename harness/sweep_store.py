"""The sweep store (``results/sweeps/``, asv style)::

    <machine-id>/<suite>/<sweep_id>/manifest.json     while running
    <machine-id>/<suite>/<sweep_id>/part-000001.parquet  finished points' rows
    <machine-id>/<suite>/<sweep_id>.parquet           when complete
    <machine-id>/<suite>/<sweep_id>.manifest.json     when complete

Every file is written atomically (harness/results.py: temp file, fsync,
rename); the rows of about five seconds go into one part
(harness.results.PartsDir.write_rows), so a killed sweep loses at most
those and the points in flight.  A sweep resumes by reading the finished point keys back
from its parts (:func:`open_sweep`).  The one reader of the layout is
:func:`sweep_files`.  Names that become directories are plain names
(:func:`plain_name`, :func:`confined`).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import queue
import re
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterable

from physbench.contract.spec import SpecError, _display
from physbench.harness.fingerprint import fingerprint, machine_id as _fingerprint_machine_id
from physbench.harness.results import (SCHEMA_VERSION, VERDICT_COLUMNS, PartsDir, consolidate_parts, list_parts,
                             read_frame, results_dir, try_lock, unfinished_dirs, write_json_atomic)
from physbench.harness import runner  # runner.commit_id read at call time


def sweeps_dir() -> Path:
    """The sweeps root: ``sweeps/`` under the results directory
    (harness.results.results_dir, read at call time)."""
    return results_dir() / "sweeps"

# Columns a sweep adds to RunResult.row() (the row contract, with
# results/README.md): the verdict columns every check row has too, then the
# sweep's own.
SWEEP_COLUMNS = VERDICT_COLUMNS + ("suite", "sweep_id", "point_key", "point_settings", "phase", "primary_error",
                                   "cpu_s_per_sim_s_median", "cpu_s_per_sim_s_min", "repeats", "machine_id",
                                   "sweep_jobs", "point_wall_s", "schema_version")
#: a plain name (:func:`plain_name`) before its other rules: letters, digits, '_', '-', '.'
PLAIN_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


def plain_name(name: str) -> bool:
    """Whether ``name`` may name a directory under the results root: letters,
    digits, '_', '-', '.', at most 100 characters, and not starting with '.'
    (so never '.', '..' or a hidden directory).  Pinned by
    tests/test_fuzz.py::test_suite_name_cannot_escape_the_results_root."""
    return bool(PLAIN_NAME.match(name)) and not name.startswith(".") and len(name) <= 100


class SuiteError(SpecError):
    """A suite file failed to load; ``errors`` holds one line per problem,
    ``<file>: <key path>: <what was expected, what was found>``.  A SpecError,
    so callers that report spec errors (exit code 2) report these too."""


# ---------------------------------------------------------------------------
# machine id


# the machine id sweeps are filed under is the environment fingerprint's
# (harness/fingerprint.py): CPU model, family/model/stepping, arithmetic
# flags, cores and OS, never the host name
machine_id = _fingerprint_machine_id


# ---------------------------------------------------------------------------
# storage


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


#: seconds of rows the part writer gathers into one write (a killed sweep loses at most these and the
#: points in flight; tests/test_sweep.py::test_resume_after_the_process_is_killed), and at most this many rows.
#: A part costs the client a few ms of CPU whatever its rows (a Parquet write of the flush's columns, fsync),
#: plus a few hundredths of a ms a row (harness/selfbench/sweep.py --store): 2 workers finish 7-12 of the
#: nightly's rows a second, so 5 s gives 35-60 rows a part
PART_FLUSH_S = 5.0
PART_MAX_ROWS = 1000
#: the name of the sweep's part-writer thread (:meth:`SweepDir.write_behind`;
#: harness/selfbench/sweep.py accounts its CPU by it)
PART_WRITER = "physbench-part-writer"


class SweepDir(PartsDir):
    """An open (unfinished) sweep directory: parts of finished points' rows,
    keyed by ``point_key`` (harness.results.PartsDir).  After
    :meth:`write_behind`, :meth:`write_point` hands each row to a writer
    thread, which stores the rows of each :data:`PART_FLUSH_S` seconds
    together (one part a flush, harness.results.PartsDir.write_rows): the caller (the
    sweep's loop, which feeds the executor and the searches) does not wait
    for the parts' encoding and fsync."""

    def __init__(self, path: Path, manifest: dict[str, Any], lock_fd: int):
        super().__init__(path, manifest, lock_fd, "point_key")
        self._queue: queue.SimpleQueue | None = None
        self._writer: threading.Thread | None = None
        self._write_error: BaseException | None = None
        self._write_error_raised = False
        self._wake = threading.Event()  # set: the writer writes what is queued now, not at its flush time

    @property
    def sweep_id(self) -> str:
        return self.manifest["sweep_id"]

    def write_behind(self) -> None:
        """Write parts on a writer thread from now on (until :meth:`drain`
        or :meth:`close`), :data:`PART_FLUSH_S` seconds of rows at a time.
        A row is in ``done`` once its part is on disk; a process killed
        with rows still queued loses them from disk only,
        and a resume runs those points again (never twice: a part is whole
        or absent; tests/test_sweep.py::test_resume_after_the_process_is_killed)."""
        if self._writer is None:
            self._queue = queue.SimpleQueue()
            self._writer = threading.Thread(target=self._write_loop, name=PART_WRITER, daemon=True)
            self._writer.start()

    def _write_loop(self) -> None:
        end = False
        while not end:
            batch = [self._queue.get()]
            if batch[0] is None:
                return
            # the rows of the next PART_FLUSH_S seconds (at most PART_MAX_ROWS) go into one write, one part,
            # so a part's encoding is paid per batch, not per row.  The
            # thread sleeps through those seconds instead of waking at every row (about 10 us of CPU a row);
            # drain() and a full batch (write_point) wake it early
            self._wake.wait(PART_FLUSH_S)
            self._wake.clear()
            while len(batch) < PART_MAX_ROWS:
                try:
                    row = self._queue.get_nowait()
                except queue.Empty:
                    break
                if row is None:
                    end = True
                    break
                batch.append(row)
            if self._write_error is None:  # after a failed write, nothing more is written
                try:
                    self.write_rows(batch, {"sweep_id": self.sweep_id})
                except BaseException as e:
                    self._write_error = e

    def _raise_write_error(self) -> None:
        # sticky: once a write failed, every later write_point and drain
        # raises it, so that no later row is stored as if the sweep went
        # on whole (tests/test_sweep.py::test_a_failed_write_stays_failed)
        if self._write_error is not None:
            self._write_error_raised = True
            raise self._write_error

    def write_point(self, row: dict[str, Any]) -> Path | None:
        """Store ``row`` as the next part: at once (returns its path), or
        after :meth:`write_behind` queued for the writer thread (returns
        None; raises the error of an earlier failed write, at every call
        after it: the row is then not queued)."""
        if self._writer is None:
            return self.write_part(row, {"sweep_id": self.sweep_id})
        self._raise_write_error()
        self._queue.put(dict(row))  # as it is now: the caller may change its dict
        if self._queue.qsize() >= PART_MAX_ROWS:
            self._wake.set()
        return None

    def drain(self) -> None:
        """Wait until every queued row is on disk and stop the writer
        thread; raises the error of a failed write (every time)."""
        if self._writer is not None:
            self._queue.put(None)
            self._wake.set()
            self._writer.join()
            self._queue = self._writer = None
        self._raise_write_error()

    def close(self) -> None:
        """Write the queued rows, then release the lock (also when a write
        failed).  A failed write's error is raised here only if no earlier
        call raised it: a caller cleaning up after that error (``except:
        close(); raise``) is not handed it a second time."""
        told = self._write_error_raised
        try:
            self.drain()
        except BaseException as e:
            if not (told and e is self._write_error):
                raise
        finally:
            super().close()


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


def open_sweep(suite: Any, points: list[Any], root: Path, resume: bool | None, jobs: int,
               executor: str, filters: dict[str, Any], machine: str | None = None) -> tuple[SweepDir, bool]:
    """Find the sweep to resume or start a new one.  Returns (dir, resumed).

    Resume rule: an unfinished sweep directory of this suite on this machine
    whose manifest has the same suite-file hash and the same planned point
    keys is resumed -- automatically (``resume=None``) only if it was also
    started at the same commit, with ``resume=True`` whatever its commit (its
    rows keep their own ``commit``); ``resume=False`` always starts afresh.
    The newest match wins; a directory locked by a running sweep is skipped.
    ``machine``: the machine id the rows are filed under (default this
    machine's; a Dask sweep's workers' own).
    """

    machine = machine or machine_id()
    suite_dir = confined(root, machine, suite.name)
    commit = runner.commit_id()
    keys = [p.key for p in points]
    if resume is not False:
        for d, man in unfinished_dirs(suite_dir):
            if (d.parent / f"{d.name}.parquet").exists():
                # consolidated, but killed before its manifest was written or
                # its directory removed: finish that (under its lock), never
                # resume it (its points are stored)
                fd = try_lock(d)
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
            fd = try_lock(d)
            if fd < 0:
                continue
            man.setdefault("resumed", []).append({"at": _now(), "commit": commit, "jobs": jobs,
                                                  "executor": executor})
            write_json_atomic(man, d / "manifest.json")
            return SweepDir(d, man, fd), True
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
    fd = try_lock(d)
    man = {
        "schema_version": SCHEMA_VERSION,
        "suite": suite.name,
        "suite_file": _display(suite.path),
        "suite_hash": suite.file_hash,
        "sweep_id": sid,
        "commit": commit,
        "machine_id": machine,
        "machine": runner.machine_info(),
        "fingerprint": fingerprint(),
        "jobs": jobs,
        "executor": executor,
        "filters": filters,
        "started": _now(),
        "finished": None,
        "points": keys,
    }
    write_json_atomic(man, d / "manifest.json")
    return SweepDir(d, man, fd), False


def consolidate(d: Path, written: dict[str, Any] | None = None) -> Path:
    """Merge the parts of sweep directory ``d`` into ``<d>.parquet`` (rows in
    planned order, one per point key), write ``<d>.manifest.json``, then --
    only once both are safely in place -- remove ``d``.  ``written``: the
    parts the caller wrote, held in memory (:attr:`SweepDir.written`, under
    the directory's lock: harness.results.consolidate_parts).  Returns the
    consolidated file's path."""
    man = json.loads((d / "manifest.json").read_text(encoding="utf-8"))
    out, _ = consolidate_parts(d, "point_key", list(man.get("points", [])), _now(), written=written)
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
    root = Path(root) if root is not None else sweeps_dir()
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
                        out += [(mdir.name, sdir.name, d.name, p, False) for p in visible(list_parts(d))]
    return out


def read_sweeps(root: str | Path | None = None, suite: str | None = None, machine: str | None = None,
                unfinished: bool = False):
    """All consolidated sweep rows under ``root`` (default results/sweeps/)
    as one DataFrame, optionally one suite / one machine id; with
    ``unfinished`` also the parts of sweeps still running or killed."""
    import pandas as pd

    frames = [read_frame(f) for *_, f, _ in
              sweep_files(root, [suite] if suite else None, machine, unfinished)]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
