"""Results store: run rows as Parquet under ``results/``, written atomically.

Rows are flat dicts (harness.runner.RunResult.row()) plus the columns of
one schema for check and sweep rows (:data:`VERDICT_COLUMNS`, then
:data:`CHECK_COLUMNS` or harness.sweep_store.SWEEP_COLUMNS).  Every file carries the
schema version in its Parquet metadata and a ``schema_version`` column, so
later readers can tell old rows from new ones.

One writer: :func:`write_parquet_atomic` (temp file in the same directory,
fsync, rename; mode 0666 minus the umask, i.e. 0644 under the usual umask,
never the 0600 of a ``mkstemp`` file).  :class:`PartsDir` is the store of a
job that writes one part per finished run and resumes after a kill
(``physbench sweep`` and ``physbench check``).
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import shutil
import sys
from pathlib import Path
from typing import Any, Iterable

from contract.scene import REPO_ROOT

SCHEMA_VERSION = 1
RESULTS_DIR = REPO_ROOT / "results"

# The row schema (results/README.md): RunResult.row() columns, then
#: columns every check and sweep row adds, so that the report reads rows
#: only: the scene's primary metric, its threshold and tags
#: (harness.conformance.scene_columns) and the verdicts of its checks,
#: JSON (harness.conformance.verdicts_column)
VERDICT_COLUMNS = ("primary_metric", "primary_threshold", "tags", "checks")
#: columns a check row adds besides VERDICT_COLUMNS
CHECK_COLUMNS = ("phase", "run_key", "check_id", "schema_version")


# ---------------------------------------------------------------------------
# atomic writers


def _normalize(df):
    """Columns mixing types (a setting that is a bool on one engine and a
    string on another) are stored as text.  Ints and floats together (a part
    where the column was None, one where it was an int, one where it was a
    float) are numbers, stored as float."""
    import numbers

    import numpy as np

    for col in df.columns:
        if df[col].dtype == object:
            vals = [v for v in df[col] if v is not None and not (isinstance(v, float) and math.isnan(v))]
            kinds = {type(v) for v in vals}
            if len(kinds) > 1 and all(isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))
                                      for v in vals):
                df[col] = df[col].map(lambda v: math.nan if v is None else float(v)).astype(float)
            elif len(kinds) > 1:
                df[col] = df[col].map(lambda v: None if v is None or (isinstance(v, float) and math.isnan(v))
                                      else str(v))
    return df


def _file_mode() -> int:
    """0666 minus the process umask: what ``open()`` would create."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def _fsync_replace(tmp: Path, path: Path) -> None:
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.chmod(tmp, _file_mode())
    os.replace(tmp, path)


def write_parquet_atomic(df, path: str | Path, metadata: dict[str, Any] | None = None) -> Path:
    """Write a DataFrame to ``path`` atomically (temp file in the same
    directory, fsync, rename); ``metadata`` is stored as JSON in the Parquet
    schema metadata under ``physbench``.  Readers never see half a file;
    the file is readable by others as far as the umask allows (test:
    tests/test_execute.py::test_result_files_are_readable)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    table = pa.Table.from_pandas(_normalize(df), preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[b"physbench"] = json.dumps({"schema_version": SCHEMA_VERSION, **(metadata or {})}, default=str).encode()
    table = table.replace_schema_metadata(meta)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        pq.write_table(table, tmp)
        _fsync_replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def write_text_atomic(text: str, path: str | Path) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically (temp file in the same
    directory, fsync, rename; the directory is made if missing)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        tmp.write_text(text, encoding="utf-8")
        _fsync_replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def write_json_atomic(obj: Any, path: Path) -> None:
    write_text_atomic(json.dumps(obj, indent=1, default=str) + "\n", path)


def write_rows(rows: Iterable[dict[str, Any]], path: str | Path, append: bool = True) -> Path:
    """Write ``rows`` to the Parquet file ``path`` atomically, appending to
    what is there when ``append``.  Returns the path."""
    import pandas as pd

    path = Path(path)
    df = pd.DataFrame(list(rows))
    df["schema_version"] = SCHEMA_VERSION
    if append and path.exists():
        df = pd.concat([pd.read_parquet(path), df], ignore_index=True)
    return write_parquet_atomic(df, path)


# ---------------------------------------------------------------------------
# a job's parts: one Parquet file per finished run, resumable


def list_parts(d: Path) -> list[Path]:
    return sorted(d.glob("part-*.parquet"))


def part_keys(d: Path, key_column: str) -> tuple[set[str], int]:
    """Finished keys (column ``key_column``) stored in the parts of job
    directory ``d``, and the next part number.  An unreadable part (it
    cannot be half-written: parts are renamed into place) is set aside as
    ``*.bad``."""
    import pyarrow.parquet as pq

    keys: set[str] = set()
    n = 0
    for p in list_parts(d):
        try:
            n = max(n, int(p.stem.split("-")[1]))
        except (IndexError, ValueError):
            pass
        try:
            keys.update(pq.read_table(p, columns=[key_column]).column(key_column).to_pylist())
        except Exception as e:
            print(f"warning: unreadable part {p} set aside ({type(e).__name__}: {e}); its runs rerun",
                  file=sys.stderr)
            p.rename(p.with_suffix(".bad"))
    return keys, n + 1


def try_lock(d: Path) -> int:
    """An exclusive lock on ``d/.lock`` (fd), or -1 if another process holds
    it (flock: released when the process dies, however it dies)."""
    fd = os.open(d / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return -1
    return fd


class PartsDir:
    """An open (unfinished) job directory: ``manifest.json`` and one
    ``part-NNNNNN.parquet`` per finished run, each identified by its
    ``key_column`` value; locked against a second process resuming it at
    the same time."""

    def __init__(self, path: Path, manifest: dict[str, Any], lock_fd: int, key_column: str):
        self.path = path
        self.manifest = manifest
        self.lock_fd = lock_fd
        self.key_column = key_column
        self.done, self.next_part = part_keys(path, key_column)
        for tmp in path.glob(".tmp-*"):  # a write in flight when killed
            tmp.unlink()

    def write_part(self, row: dict[str, Any], metadata: dict[str, Any] | None = None) -> Path:
        import pandas as pd

        p = self.path / f"part-{self.next_part:06d}.parquet"
        write_parquet_atomic(pd.DataFrame([row]), p, metadata)
        self.next_part += 1
        self.done.add(row[self.key_column])
        return p

    def part_rows(self) -> list[dict[str, Any]]:
        """The stored rows, one dict per part, each read on its own (so a
        column's type is the one its row was written with)."""
        import pyarrow.parquet as pq

        out = []
        for p in list_parts(self.path):
            out.extend(pq.read_table(p).to_pylist())
        return out

    def close(self) -> None:
        if self.lock_fd >= 0:
            os.close(self.lock_fd)
            self.lock_fd = -1


def unfinished_dirs(parent: Path) -> list[tuple[Path, dict[str, Any]]]:
    """Unfinished job directories (with a readable manifest) under
    ``parent``, newest first."""
    out = []
    if not parent.is_dir():
        return out
    for d in sorted(parent.iterdir(), reverse=True):
        m = d / "manifest.json"
        if d.is_dir() and m.is_file():
            try:
                out.append((d, json.loads(m.read_text(encoding="utf-8"))))
            except (OSError, ValueError):
                continue
    return out


def consolidate_parts(d: Path, key_column: str, order: list[str], finished: str,
                      columns: dict[str, dict[str, Any]] | None = None) -> tuple[Path, dict[str, Any]]:
    """Merge the parts of job directory ``d`` into ``<d>.parquet`` (rows in
    ``order`` of their keys, one per key), write ``<d>.manifest.json``,
    then -- only once both are safely in place -- remove ``d``.  ``columns``
    maps a key to values set on its row (a check's verdicts, known only once
    every run is in).  Returns (consolidated file, manifest)."""
    import pandas as pd

    man = json.loads((d / "manifest.json").read_text(encoding="utf-8"))
    frames = [pd.read_parquet(p) for p in list_parts(d)]
    df = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=[key_column])
    rank = {k: i for i, k in enumerate(order)}
    # a key is stored once by construction; should a bug ever store one
    # twice, the first row wins and the manifest says so
    n = len(df)
    df = df.drop_duplicates(key_column, keep="first")
    man["duplicates_dropped"] = n - len(df)
    df = df.iloc[sorted(range(len(df)), key=lambda i: rank.get(df[key_column].iat[i], len(rank)))]
    df = df.reset_index(drop=True)
    for col in sorted({c for v in (columns or {}).values() for c in v}):
        df[col] = [(columns or {}).get(k, {}).get(col) for k in df[key_column]]
    man["finished"] = man.get("finished") or finished
    man["rows"] = int(len(df))
    have = set(df[key_column])
    man["missing"] = [k for k in order if k not in have]
    out = d.parent / f"{d.name}.parquet"
    write_parquet_atomic(df, out, {"manifest": {k: v for k, v in man.items() if k not in ("points", "runs")}})
    write_json_atomic(man, d.parent / f"{d.name}.manifest.json")
    try:
        shutil.rmtree(d)
    except OSError as e:  # the rows are safe; the next job of this kind finishes the removal
        print(f"warning: {out} written but {d} could not be removed ({type(e).__name__}: {e}); "
              "the next run of this job removes it", file=sys.stderr)
    return out, man
