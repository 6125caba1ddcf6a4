"""Reading stored rows: the only part of the report that touches the disk
(results/README.md's layout: ``sweeps/`` through
harness.sweep_store.sweep_files, ``check/*.parquet``).  Rows go through
the one normaliser (harness.report.rows.normalise) and nothing else: no
scene is loaded, no spec parsed.

What reading found is kept twice: as text (``df.attrs['warnings']``, one
line per file, printed on stderr) and as notes
(``df.attrs['data_notes']``, :func:`_note`), whose ``left_out`` says
whether rows were left out of the page (an unreadable file, rows of a
schema version this report does not read) or only how they were read (a
file without a ``schema_version`` column).  The page's "Data" section lists
every note; the ones that left rows out also get one line at the top."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

import pandas as pd

from physbench.harness.report.rows import as_float, fmt, is_missing, normalise
from physbench.harness.results import SCHEMA_VERSION, read_frame, results_dir as _results_dir
from physbench.harness.sweep_store import sweep_files

SUPPORTED_SCHEMAS = frozenset({SCHEMA_VERSION})


#: :func:`_note` kinds: whether rows were left out (True) or read otherwise
UNREADABLE, SCHEMA_SKIPPED, NO_SCHEMA = "unreadable", "schema_skipped", "no_schema_version"
LEFT_OUT = {UNREADABLE: True, SCHEMA_SKIPPED: True, NO_SCHEMA: False}


def _note(notes: list[dict[str, Any]], path: Path, kind: str, text: str, rows: int | None = None) -> None:
    """A data note: ``{"path", "kind", "rows", "left_out", "text"}``;
    ``rows``: how many rows it concerns (None: the file could not be read);
    ``text``: the warning line (path first)."""
    notes.append({"path": str(path), "kind": kind, "rows": rows, "left_out": LEFT_OUT[kind], "text": text})


def _read_file(path: Path, notes: list[dict[str, Any]], **extra: Any) -> pd.DataFrame | None:
    try:
        df = read_frame(path)
    except Exception as e:  # a torn or foreign file must not sink the report
        _note(notes, path, UNREADABLE, f"{path}: unreadable, skipped ({type(e).__name__}: {e})")
        return None
    if df.empty:
        return None
    if "schema_version" in df.columns:
        sv = df["schema_version"].map(as_float)
        bad = ~sv.isin(list(SUPPORTED_SCHEMAS))
        if bad.any():
            versions = sorted({fmt(x) for x in df.loc[bad, "schema_version"]})
            _note(notes, path, SCHEMA_SKIPPED,
                  f"{path}: {int(bad.sum())} row(s) with schema_version {', '.join(versions)} skipped "
                  f"(this report reads version {', '.join(str(v) for v in sorted(SUPPORTED_SCHEMAS))})",
                  int(bad.sum()))
            df = df.loc[~bad]
            if df.empty:
                return None
    else:
        _note(notes, path, NO_SCHEMA, f"{path}: no schema_version column; read as version {SCHEMA_VERSION}",
              len(df))
    df = df.copy()
    df["_file"] = str(path)
    for k, v in extra.items():
        if k in ("suite", "sweep_id", "machine_id") and k in df.columns:
            # the file's own column wins; the layout fills the gaps
            df[k] = df[k].where(~df[k].map(is_missing), v)
        else:
            df[k] = v
    return df


def _visible(paths: Iterable[Path]) -> list[Path]:
    return sorted(p for p in paths if not p.name.startswith("."))


def load_results(results_dir: str | Path | None = None, suites: list[str] | None = None) -> pd.DataFrame:
    """All stored rows under ``results_dir`` (default ``results/``) as one
    frame (harness.report.rows.normalise: its docstring lists the added
    columns), with ``source`` ('sweep' or 'check') and ``incomplete`` (rows
    of an unconsolidated sweep directory) set from where the file lies.
    Warnings (unreadable files, unknown schema versions, files without a
    schema version) are in ``df.attrs['warnings']`` as text and in
    ``df.attrs['data_notes']`` as notes (:func:`_note`).
    """
    root = Path(results_dir) if results_dir is not None else _results_dir()
    notes: list[dict[str, Any]] = []
    frames: list[pd.DataFrame] = []
    for mid, suite, sid, p, complete in sweep_files(root / "sweeps", suites):
        frames.append(_read_file(p, notes, source="sweep", incomplete=not complete,
                                 machine_id=mid, suite=suite, sweep_id=sid))
    check = root / "check"
    if check.is_dir():
        for p in _visible(check.glob("*.parquet")):
            frames.append(_read_file(p, notes, source="check", incomplete=False, check_file=p.stem))
    frames = [f for f in frames if f is not None]
    if not frames:
        df = normalise(pd.DataFrame())
    else:
        df = normalise(pd.concat(frames, ignore_index=True, sort=False))
    if suites:
        df = df[(df["source"] != "sweep") | df["suite"].isin(suites)].reset_index(drop=True)
    df.attrs["warnings"] = [n["text"] for n in notes]
    df.attrs["data_notes"] = notes
    return df
