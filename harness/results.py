"""Results store: run rows as Parquet under the results directory, written
atomically.

The results directory (:func:`results_dir`) is ``./results`` under the
working directory, unless ``--results-dir`` (the commands that write or read
results) or the ``PHYSBENCH_RESULTS`` variable names another; it is never
inside the installed package.  Run from the repository's root, it is the
repository's own ``results/``.

Rows are flat dicts (harness.runner.RunResult.row()) plus the columns of
one schema for check and sweep rows (:data:`VERDICT_COLUMNS`, then
:data:`CHECK_COLUMNS` or harness.sweep_store.SWEEP_COLUMNS).  Every file carries the
schema version in its Parquet metadata and a ``schema_version`` column, so
later readers can tell old rows from new ones.

One way to write a file: :func:`_write_bytes_atomic` (temp file in the
same directory, fsync, rename; mode 0666 minus the umask, i.e. 0644 under
the usual umask, never the 0600 of a ``mkstemp`` file), under
:func:`write_table_atomic` (a pyarrow Table), :func:`write_parquet_atomic`
(a DataFrame) and the text writers.  :class:`PartsDir` is the store of a
job that writes its finished runs' rows as parts and resumes after a kill
(``physbench sweep``: several rows to a part; ``physbench check``): parts
are built from the rows with pyarrow, one table per row schema (:func:`rows_table`,
typed as ``from_pandas`` types each row), the tables of one write stored
as one part (:func:`one_part_table`: a column two of them hold with
different types stored once per type; read back split by
:func:`read_part_tables`) and merged by :func:`merge_tables`:
pyarrow, each column typed as one ``pandas.concat`` and :func:`_normalize`
(the store's one normaliser) type it.
"""

from __future__ import annotations

import fcntl
import functools
import json
import math
import os
import shutil
import sys
from pathlib import Path
from typing import Any, Iterable

SCHEMA_VERSION = 1
#: environment variable naming the results directory
RESULTS_ENV = "PHYSBENCH_RESULTS"
#: the results directory a command line's ``--results-dir`` set (harness.cli.main), else None
_override: Path | None = None


def results_dir() -> Path:
    """The results directory, read at call time: ``--results-dir`` of the
    running command, else ``$PHYSBENCH_RESULTS``, else ``./results`` under
    the working directory (absolute).  Test:
    tests/test_install.py::test_results_dir_flag_and_variable."""
    if _override is not None:
        return _override
    env = os.environ.get(RESULTS_ENV, "").strip()
    return (Path(env) if env else Path("results")).absolute()


def set_results_dir(path: str | Path | None) -> Path | None:
    """Set (or with None clear) the results directory of this process;
    returns the previous setting.  The command line sets it from
    ``--results-dir``."""
    global _override
    old, _override = _override, (Path(path).absolute() if path is not None else None)
    return old

# The row schema (results/README.md): RunResult.row() columns, then
#: columns every check and sweep row adds, so that the report reads rows
#: only: the scene's primary metric, its threshold and tags
#: (harness.conformance.scene_columns) and the verdicts of its checks,
#: JSON (harness.conformance.verdicts_column)
VERDICT_COLUMNS = ("primary_metric", "primary_threshold", "tags", "checks")
#: columns a check row adds besides VERDICT_COLUMNS
#: (``ensemble``: the perturbation of an ensemble row, JSON; absent on a plain run's)
CHECK_COLUMNS = ("phase", "run_key", "check_id", "schema_version", "ensemble")


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


def _write_bytes_atomic(data: bytes, path: Path) -> Path:
    """``data`` to ``path`` atomically: a temp file in the same directory
    (the directory is made if missing), written, fsynced, given the mode
    ``open()`` would create, renamed into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
            os.fchmod(fd, _file_mode())
        finally:
            os.close(fd)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def write_table_atomic(table, path: str | Path, metadata: dict[str, Any] | None = None,
                       **write_options: Any) -> Path:
    """Write the pyarrow Table ``table`` to ``path`` atomically
    (:func:`_write_bytes_atomic`); ``metadata`` is stored as JSON in the
    Parquet schema metadata under ``physbench``, with the schema version.
    Readers never see half a file; the file is readable by others as far
    as the umask allows (test:
    tests/test_execute.py::test_result_files_are_readable).
    ``write_options`` go to ``pyarrow.parquet.write_table``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    meta = dict(table.schema.metadata or {})
    meta[b"physbench"] = json.dumps({"schema_version": SCHEMA_VERSION, **(metadata or {})}, default=str).encode()
    buf = pa.BufferOutputStream()
    pq.write_table(table.replace_schema_metadata(meta), buf, **write_options)
    return _write_bytes_atomic(buf.getvalue(), Path(path))


def write_parquet_atomic(df, path: str | Path, metadata: dict[str, Any] | None = None) -> Path:
    """Write a DataFrame to ``path`` atomically (:func:`write_table_atomic`;
    columns mixing types normalized first, :func:`_normalize`)."""
    import pyarrow as pa

    return write_table_atomic(pa.Table.from_pandas(_normalize(df), preserve_index=False), path, metadata)


def write_text_atomic(text: str, path: str | Path) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically (temp file in the same
    directory, fsync, rename; the directory is made if missing)."""
    return _write_bytes_atomic(text.encode("utf-8"), Path(path))


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
# rows as Arrow tables: the parts (pyarrow) and their merge


@functools.lru_cache(maxsize=1)
def _scalar_types() -> dict[type, Any]:
    """The Arrow type of a value of each Python type a row holds, as
    ``pandas.DataFrame([row])`` then ``pyarrow.Table.from_pandas`` types it
    (pandas 3 stores text as ``large_string``; None alone is ``null``)."""
    import numpy as np
    import pyarrow as pa

    return {type(None): pa.null(), bool: pa.bool_(), np.bool_: pa.bool_(), int: pa.int64(), np.int64: pa.int64(),
            float: pa.float64(), np.float64: pa.float64(), str: pa.large_string()}


@functools.lru_cache(maxsize=64)
def _row_schema(signature: tuple[tuple[str, Any], ...]):
    import pyarrow as pa

    return pa.schema(list(signature))


def row_signature(row: dict[str, Any]) -> tuple[tuple[str, Any], ...] | None:
    """The Arrow schema of ``row`` as (column, type) pairs, from its values'
    Python types (:func:`_scalar_types`), or None for a row holding a value
    of another type (a list, another numpy scalar: the pandas path types
    it).  Rows of one signature make one table (:func:`rows_table`)."""
    types = _scalar_types()
    try:
        return tuple((k, types[type(v)]) for k, v in row.items())
    except KeyError:
        return None


def rows_table(rows: list[dict[str, Any]], signature: tuple[tuple[str, Any], ...] | None = None):
    """Rows of one :func:`row_signature` as one pyarrow Table, built column
    by column with that one schema (no DataFrame, no per-row table), typed
    as ``Table.from_pandas(pandas.DataFrame([row]))`` types each row (a float
    NaN stored as null, as pandas stores it): the same table as the rows'
    one-row tables concatenated.  A value the schema cannot hold (an int
    beyond 64 bits) sends the rows through the pandas path one by one.
    Test: tests/test_results_store.py::test_a_part_of_several_rows_reads_back_as_its_rows_one_by_one."""
    import pyarrow as pa

    sig = signature if signature is not None else row_signature(rows[0])
    if sig is None:
        return pa.concat_tables([_pandas_row_table(r) for r in rows])
    try:
        arrays = [pa.array([r[k] for r in rows], t, from_pandas=True) if t == pa.float64()  # NaN -> null
                  else pa.array([r[k] for r in rows], t) for k, t in sig]
        return pa.Table.from_arrays(arrays, schema=_row_schema(sig))
    except (OverflowError, pa.ArrowException):
        return pa.concat_tables([_pandas_row_table(r) for r in rows])


def row_table(row: dict[str, Any]):
    """One row as a one-row pyarrow Table typed as
    ``Table.from_pandas(pandas.DataFrame([row]))`` types it (a float NaN is
    stored as null, as pandas stores it), without building a DataFrame: the
    schema comes from the values' Python types and is reused for every row
    of the same columns and types (:func:`rows_table`).  A value of another
    type (a list, a numpy scalar other than bool/int64/float64, an int
    beyond 64 bits) takes the pandas path for its row.  Test:
    tests/test_results_store.py::test_a_row_reads_back_as_the_pandas_path_wrote_it."""
    return rows_table([row])


def _pandas_row_table(row: dict[str, Any]):
    import pandas as pd
    import pyarrow as pa

    return pa.Table.from_pandas(_normalize(pd.DataFrame([row])), preserve_index=False)


def _exact_cast(src: Any, dst: Any) -> bool:
    """Whether :func:`merge_tables` may cast a column of type ``src`` to
    ``dst`` in Arrow with the values pandas gives: the same type, nulls as
    any type, an int64 as a float64 (the C conversion numpy makes too),
    text widened or narrowed."""
    import pyarrow as pa

    return (src == dst or pa.types.is_null(src) or (src == pa.int64() and dst == pa.float64())
            or ((pa.types.is_string(src) or pa.types.is_large_string(src))
                and (pa.types.is_string(dst) or pa.types.is_large_string(dst))))


@functools.lru_cache(maxsize=1)
def _simple_types() -> frozenset:
    """The column types :func:`merge_tables` types in Arrow (others take the pandas merge)."""
    import pyarrow as pa

    return frozenset((pa.null(), pa.bool_(), pa.int64(), pa.float64(), pa.string(), pa.large_string()))


def _sample(typ: Any, nulls: int) -> Any:
    """A stand-in column of type ``typ`` for :func:`_pandas_typing`: one
    value, one value and a null (``nulls`` 1), or one null (``nulls`` 2)."""
    import pyarrow as pa

    value = {pa.bool_(): True, pa.int64(): 1, pa.float64(): 1.5}.get(typ, "x")
    if pa.types.is_null(typ) or nulls == 2:
        return pa.nulls(1, typ)
    return pa.array([value, None] if nulls else [value], typ)


@functools.lru_cache(maxsize=4096)
def _pandas_typing(situation: tuple[tuple[Any, int] | None, ...]) -> Any:
    """The Arrow type the pandas merge (``Table.to_pandas`` of each schema's
    rows, ``pandas.concat``, :func:`_normalize`, ``Table.from_pandas``)
    gives a column whose schemas hold it as ``situation`` says, per schema
    in order: None (absent), or (its type, 0 no null / 1 some / 2 all
    null); found by running that merge on one stand-in row per schema
    (:func:`_sample`; each state once, in the order they first come).  Only
    asked where the schemas hold at most one non-null type: there pandas'
    typing depends on no value but these (:func:`_normalize` leaves a column
    of one kind of value as it is)."""
    import pandas as pd
    import pyarrow as pa

    frames = []
    for have in situation:
        cols = {"__k": pa.array(["k"] * (2 if have and have[1] == 1 else 1))}
        if have is not None:
            cols["c"] = _sample(*have)
        frames.append(pa.table(cols).to_pandas())
    df = _normalize(pd.concat(frames, ignore_index=True))
    return pa.Table.from_pandas(df[["c"]], preserve_index=False).schema.field("c").type


def merge_tables(tables: list[Any], rows: list[int] | None = None):
    """The rows of ``tables`` (parts, each typed on its own) as one Table,
    in the parts' order, typed as ``pandas.concat`` of the parts then
    :func:`_normalize` types them (the store's one normaliser): parts of
    one schema are concatenated by pyarrow; where the parts' schemas
    differ (a column missing from some parts, or int in one and float,
    None or text in another), the columns are the union of the schemas'
    in pandas' order, and each column is typed as the pandas merge (each
    schema's rows one DataFrame, the job's frames one ``pandas.concat``,
    then :func:`_normalize`) types it: in Arrow where its schemas hold at
    most one non-null type (:func:`_pandas_typing` gives the type; the
    parts' values cast exactly, :func:`_exact_cast`), the other columns
    (text beside a bool, an int beside text ...) through that pandas merge.
    (pandas' typing of a few mixes depends on the order of the frames: a
    float before a bool gives floats, the reverse text or bools; the
    frames are in the order their schemas first appear.)
    ``rows``: only these rows (indices into the parts' rows, in their
    order), in this order -- the same table as the whole merge's ``take``.
    Tests: tests/test_results_store.py::test_merged_parts_read_back_as_the_pandas_merge_wrote_them,
    ::test_every_mix_of_kinds_merges_as_pandas_merged_it,
    ::test_parts_of_mixed_kinds_merge_to_one_typed_column,
    ::test_the_arrow_merge_types_every_column_as_the_pandas_merge."""
    import pandas as pd
    import pyarrow as pa
    import pyarrow.compute as pc

    if not tables:
        return pa.table({})
    groups: dict[Any, list[tuple[Any, int]]] = {}  # parts of one schema, each with its first row's index
    start = 0
    for t in tables:
        t = t.replace_schema_metadata(None)
        groups.setdefault(t.schema, []).append((t, start))
        start += t.num_rows
    if len(groups) == 1:
        whole = pa.concat_tables([t for t, _ in next(iter(groups.values()))])
        return whole if rows is None else whole.take(pa.array(rows, pa.int64()))
    merged = [pa.concat_tables([t for t, _ in same]).combine_chunks() for same in groups.values()]
    rank = [i for same in groups.values() for t, at in same for i in range(at, at + t.num_rows)]
    order = sorted(range(len(rank)), key=rank.__getitem__)  # parts' order -> group order
    final = pa.array(order if rows is None else [order[i] for i in rows], pa.int64())
    names = list(dict.fromkeys(n for g in merged for n in g.schema.names))  # pandas.concat's: as they first come
    columns: dict[str, Any] = {}
    hard: list[str] = []
    simple, null = _simple_types(), pa.null()
    # per column and schema: None (absent) or (its type, 0 no null / 1 some / 2 all null)
    states: dict[str, list[tuple[Any, int] | None]] = {n: [None] * len(merged) for n in names}
    for gi, g in enumerate(merged):
        n = g.num_rows
        for f, col in zip(g.schema, g.columns):
            states[f.name][gi] = (f.type, 0 if col.null_count == 0 else 2 if col.null_count == n else 1)
    for name in names:
        situation = states[name]
        kinds = {h[0] for h in situation if h is not None and h[1] != 2 and h[0] != null}
        if len(kinds) > 1 or not all(h is None or h[0] in simple for h in situation):
            hard.append(name)
            continue
        # pandas types a column by the kinds of its frames, not by how often each comes
        typ = _pandas_typing(tuple(dict.fromkeys(situation)))
        pieces, gap = [], 0  # gap: rows of nulls to add before the next piece (absent or all null)
        for g, have in zip(merged, situation):
            if have is None or pa.types.is_null(have[0]) or have[1] == 2:
                gap += g.num_rows
                continue
            if gap:
                pieces.append(pa.nulls(gap, typ))
                gap = 0
            if have[0] == typ:
                pieces.extend(g.column(name).chunks)
            elif _exact_cast(have[0], typ):
                pieces.extend(c.cast(typ, safe=False) for c in g.column(name).chunks)
            else:
                break
        else:
            if gap:
                pieces.append(pa.nulls(gap, typ))
            col = pa.chunked_array(pieces, typ)
            if pa.types.is_floating(typ) and pc.any(pc.is_nan(col)).as_py():
                col = pc.if_else(pc.is_nan(col), pa.scalar(None, typ), col)  # NaN stored as null, as pandas
            columns[name] = col.take(final)
            continue
        hard.append(name)
    if hard:  # the pandas merge, on these columns only (pandas types each column on its own)
        df = pd.concat([g.select([c for c in hard if c in g.schema.names]).to_pandas() for g in merged],
                       ignore_index=True)
        df = _normalize(df.iloc[order].reset_index(drop=True))  # typed on every row, as the whole merge
        table = pa.Table.from_pandas(df[hard], preserve_index=False)
        if rows is not None:
            table = table.take(pa.array(rows, pa.int64()))
        columns.update((c, table.column(c)) for c in hard)
    return pa.table({n: columns[n] for n in names})


# ---------------------------------------------------------------------------
# a job's parts: one Parquet file per finished run, resumable


def list_parts(d: Path) -> list[Path]:
    return sorted(d.glob("part-*.parquet"))


#: a part holding rows of several row schemas (:func:`one_part_table`): the column naming each row's own,
#: an index into the list stored under this key in the part's ``physbench`` metadata
PART_SCHEMA_COLUMN = "__row_schema"
PART_SCHEMAS_KEY = "row_schemas"
#: ... and, where two of its row schemas hold a column with different types (an int and a float, a bool and
#: text), the column's name of each stored column (the stored names of the second type on are made up)
PART_COLUMNS_KEY = "row_columns"


def _stored_columns(schemas: list[Any]) -> tuple[list[tuple[str, Any]], dict[tuple[str, Any], int]]:
    """The columns a part of rows of ``schemas`` (each a pyarrow Schema or
    (name, type) pairs) stores: one per column name and non-null type, in
    the order they first appear (a name held null-typed only: one of type
    null), as (name, type); and the index of each (name, type) a schema
    holds -- a null-typed one's is its name's first stored column."""
    import pyarrow as pa

    null = pa.null()
    kinds: dict[str, list[Any]] = {}
    for sch in schemas:
        for f in sch:
            n, t = (f.name, f.type) if isinstance(f, pa.Field) else f
            have = kinds.setdefault(n, [])
            if t != null and t not in have:
                have.append(t)
    stored = [(n, t) for n, ts in kinds.items() for t in (ts or [null])]
    index = {c: i for i, c in enumerate(stored)}
    for n, ts in kinds.items():
        index[(n, null)] = index[(n, ts[0] if ts else null)]
    return stored, index


def _stored_names(stored: list[tuple[str, Any]]) -> tuple[list[str], list[str] | None]:
    """The names the ``stored`` columns are written under -- their own, but
    a made-up one (``__row_schema<k>:<name>``) for a name's second type on --
    and, where one is made up, every stored column's own name (None else)."""
    seen: set[str] = set()
    own = {m for m, _ in stored}
    out = []
    for n, _ in stored:
        name, k = n, 0
        while name in seen or (name != n and name in own):
            k += 1
            name = f"{PART_SCHEMA_COLUMN}{k}:{n}"
        seen.add(name)
        out.append(name)
    return out, (None if out == [n for n, _ in stored] else [n for n, _ in stored])


def _signature_part(groups: list[tuple[tuple[tuple[str, Any], ...], list[dict[str, Any]]]]):
    """Rows of several signatures as :func:`one_part_table` makes them from
    their :func:`rows_table` s, built straight from the rows: one array per
    stored column (:func:`_stored_columns`), not one per column of each
    signature.  Raises what pyarrow raises for a value its type cannot hold
    (the caller then takes the tables' path)."""
    import pyarrow as pa

    null, f64 = pa.null(), pa.float64()
    stored, index = _stored_columns([sig for sig, _ in groups])
    values: list[list[Any]] = [[] for _ in stored]
    for sig, same in groups:
        # a signature's rows hold its columns in its order: transposed in C, not value by value
        columns = list(zip(*[r.values() for r in same]))
        held = {index[c]: j for j, c in enumerate(sig) if c[1] != null}
        gap = [None] * len(same)
        for i, col in enumerate(values):
            j = held.get(i)
            col.extend(gap if j is None else columns[j])
    arrays = [pa.array(v, t, from_pandas=True) if t == f64 else pa.array(v, t)  # NaN -> null, as rows_table
              for v, (_, t) in zip(values, stored)]
    arrays.append(pa.array([k for k, (_, same) in enumerate(groups) for _ in same], pa.int32()))
    names, own = _stored_names(stored)
    schema = pa.schema([(m, t) for m, (_, t) in zip(names, stored)] + [(PART_SCHEMA_COLUMN, pa.int32())])
    schemas = [[[index[c] for c in sig], [index[c] for c in sig if c[1] == null]] for sig, _ in groups]
    return pa.Table.from_arrays(arrays, schema=schema), schemas, own


def one_part_table(tables: list[Any]) -> tuple[Any, list[list[list[int]]] | None, list[str] | None]:
    """Tables (each of its own row schema) as one table to store as one
    part, and what :func:`read_part_tables` needs to give the tables back:
    (table, None, None) for one table; for several, their stored columns
    (:func:`_stored_columns`: one per column name and type; a table lacking
    a column, or holding it null-typed, has nulls there) plus
    :data:`PART_SCHEMA_COLUMN`, each row's table, per table [its columns,
    those of them null-typed] as indices into the stored columns, and the
    stored columns' own names where a name is stored under two types
    (:func:`_stored_names`; else None).  A flush of a sweep's rows so costs
    one Parquet write, whatever their row signatures and however their
    types disagree
    (tests/test_results_store.py::test_a_part_of_several_rows_reads_back_as_its_rows_one_by_one)."""
    import pyarrow as pa

    if len(tables) == 1:
        return tables[0], None, None
    null = pa.null()
    stored, index = _stored_columns([t.schema for t in tables])
    names, own = _stored_names(stored)
    schema = pa.schema([(m, t) for m, (_, t) in zip(names, stored)] + [(PART_SCHEMA_COLUMN, pa.int32())])
    parts, schemas = [], []
    for k, t in enumerate(tables):
        n = t.num_rows
        have = {index[(f.name, f.type)]: i for i, f in enumerate(t.schema) if f.type != null}
        cols = [t.column(have[j]) if j in have else pa.nulls(n, ty) for j, (_, ty) in enumerate(stored)]
        parts.append(pa.Table.from_arrays(cols + [pa.array([k] * n, pa.int32())], schema=schema))
        schemas.append([[index[(f.name, f.type)] for f in t.schema],
                        [index[(f.name, f.type)] for f in t.schema if f.type == null]])
    return pa.concat_tables(parts).combine_chunks(), schemas, own


def read_part_tables(p: Path) -> list[Any]:
    """The tables a part holds (:func:`read_part`), each with its own row
    schema: one, or those :func:`one_part_table` stored together, given
    back as they were (columns, names, order, types, values)."""
    t = read_part(p)
    return split_part(t, json.loads((t.schema.metadata or {}).get(b"physbench", b"{}")))


def split_part(t: Any, meta: dict[str, Any]) -> list[Any]:
    """The tables of a part's table ``t`` whose ``physbench`` metadata is
    ``meta`` (:func:`read_part_tables`; the part writer's own copy of what
    it wrote, :attr:`PartsDir.written`, is split the same way)."""
    import pyarrow as pa

    schemas = meta.get(PART_SCHEMAS_KEY)
    if not schemas:
        return [t]
    names = meta.get(PART_COLUMNS_KEY) or t.column_names
    fields = [f.remove_metadata().with_name(n) for f, n in zip(t.schema, names)]
    which = t.column(PART_SCHEMA_COLUMN).to_pylist()
    out, start = [], 0
    while start < len(which):
        k, end = which[start], start
        while end < len(which) and which[end] == k:
            end += 1
        cols, nulls = schemas[k][0], set(schemas[k][1])
        rows = t.slice(start, end - start)
        out.append(pa.Table.from_arrays(
            [pa.nulls(end - start) if i in nulls else rows.column(i) for i in cols],
            schema=pa.schema([pa.field(names[i], pa.null()) if i in nulls else fields[i] for i in cols])))
        start = end
    return out


def read_frame(p: Path):
    """A stored Parquet file (a consolidated sweep, a part) as a DataFrame,
    one row per stored row: the rows of a part of several row schemas
    with the union of their columns (pandas.concat of its tables)."""
    import pandas as pd

    tables = read_part_tables(p) if p.name.startswith("part-") else None
    if not tables or len(tables) == 1:
        return pd.read_parquet(p)
    return pd.concat([t.to_pandas() for t in tables], ignore_index=True)


def read_part(p: Path, columns: list[str] | None = None):
    """One Parquet file (a part) as a pyarrow Table, read in this thread:
    a fraction of ``pyarrow.parquet.read_table``'s cost for a one-row
    file (no dataset discovery, no thread pool)."""
    import pyarrow.parquet as pq

    with pq.ParquetFile(p) as f:
        return f.read(columns=columns, use_threads=False)


def part_keys(d: Path, key_column: str) -> tuple[set[str], int]:
    """Finished keys (column ``key_column``) stored in the parts of job
    directory ``d``, and the next part number.  An unreadable part (it
    cannot be half-written: parts are renamed into place) is set aside as
    ``*.bad``."""

    keys: set[str] = set()
    n = 0
    for p in list_parts(d):
        try:
            n = max(n, int(p.stem.split("-")[1]))
        except (IndexError, ValueError):
            pass
        try:
            keys.update(read_part(p, [key_column]).column(key_column).to_pylist())
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


#: rows of the parts a :class:`PartsDir` keeps in memory for the merge (about 3 kB a row in Arrow: a
#: nightly's 3,200 rows are 10 MB); parts beyond are read back from disk
KEEP_ROWS = 20_000

#: pyarrow.parquet.write_table options of a part: no compression,
#: no column statistics (a part is read whole, once); the merged file is
#: written with the defaults
PART_WRITE_OPTIONS = {"compression": "none", "write_statistics": False, "use_dictionary": False}


class PartsDir:
    """An open (unfinished) job directory: ``manifest.json`` and
    ``part-NNNNNN.parquet`` files holding the finished runs' rows (one or
    more per part), each identified by its ``key_column`` value; locked against a second process resuming it at
    the same time."""

    def __init__(self, path: Path, manifest: dict[str, Any], lock_fd: int, key_column: str):
        self.path = path
        self.manifest = manifest
        self.lock_fd = lock_fd
        self.key_column = key_column
        self.done, self.next_part = part_keys(path, key_column)
        #: the parts this object wrote, by file name: (table, its ``physbench`` metadata), as written, up to
        #: :data:`KEEP_ROWS` rows in all -- the merge takes them from here instead of reading them back
        #: (:func:`consolidate_parts`; the same tables: tests/test_results_store.py::test_the_merge_of_the_kept_parts_is_the_merge_of_the_files)
        self.written: dict[str, tuple[Any, dict[str, Any]]] = {}
        self._kept_rows = 0
        for tmp in path.glob(".tmp-*"):  # a write in flight when killed
            tmp.unlink()

    def write_part(self, row: dict[str, Any], metadata: dict[str, Any] | None = None) -> Path:
        """Store ``row`` as the next part (:meth:`write_rows` of one row)."""
        return self.write_rows([row], metadata)[0]

    def write_rows(self, rows: list[dict[str, Any]], metadata: dict[str, Any] | None = None) -> list[Path]:
        """Store ``rows`` as the next part: one table per :func:`row_signature`
        among them (its rows in their order, :func:`rows_table`; the tables
        in the order their signatures first appear, so a merge types the
        columns as it typed one part per row), all in one part
        (:func:`one_part_table`: a sweep's rows of different engines and
        statuses, one write, whatever their columns' types), written
        atomically and fsynced before this returns: once the caller counts
        a row done, it is on disk.  A part is whole or absent, so a kill
        loses whole parts, never half a row.  Returns the part's path (a
        list: empty for no rows)."""
        if not rows:
            return []
        groups: dict[Any, tuple[Any, list[dict[str, Any]]]] = {}  # a row the pandas path types: a table alone
        for i, row in enumerate(rows):
            sig = row_signature(row)
            groups.setdefault(sig if sig is not None else i, (sig, []))[1].append(row)
        import pyarrow as pa

        listed = list(groups.values())
        p = self.path / f"part-{self.next_part:06d}.parquet"
        table = schemas = names = None
        if len(listed) > 1 and all(sig is not None for sig, _ in listed):
            try:
                table, schemas, names = _signature_part(listed)
            except (OverflowError, pa.ArrowException):
                table = None
        if table is None:
            table, schemas, names = one_part_table([rows_table(same, sig) for sig, same in listed])
        meta = dict(metadata or {})
        if schemas is not None:
            meta[PART_SCHEMAS_KEY] = schemas
        if names is not None:
            meta[PART_COLUMNS_KEY] = names
        write_table_atomic(table, p, meta, **PART_WRITE_OPTIONS)
        if self._kept_rows + len(rows) <= KEEP_ROWS:
            self.written[p.name] = (table, meta)
            self._kept_rows += len(rows)
        self.next_part += 1
        self.done.update(r[self.key_column] for r in rows)
        return [p]

    def part_rows(self) -> list[dict[str, Any]]:
        """The stored rows, one dict per row, each part read on its own (so
        a column's type is the one its row was written with)."""

        out = []
        for p in list_parts(self.path):
            for t in read_part_tables(p):
                out.extend(t.to_pylist())
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
                      columns: dict[str, dict[str, Any]] | None = None,
                      written: dict[str, tuple[Any, dict[str, Any]]] | None = None) -> tuple[Path, dict[str, Any]]:
    """Merge the parts of job directory ``d`` into ``<d>.parquet`` (rows in
    ``order`` of their keys, one per key; :func:`merge_tables`), write
    ``<d>.manifest.json``, then -- only once both are safely in place --
    remove ``d``.  ``columns`` maps a key to values set on its row (a
    check's verdicts, known only once every run is in).  ``written``: the
    tables of parts the caller wrote itself and holds the directory's lock
    for (:attr:`PartsDir.written`), taken from memory instead of read back
    (a part the size of a nightly's flush costs a few ms to read); every
    other part is read.  Returns (consolidated file, manifest)."""
    import pyarrow as pa

    man = json.loads((d / "manifest.json").read_text(encoding="utf-8"))
    parts = []
    for p in list_parts(d):
        kept = (written or {}).get(p.name)
        parts.extend(split_part(*kept) if kept is not None else read_part_tables(p))
    keyed = bool(parts) and all(t.schema.get_field_index(key_column) >= 0 for t in parts)
    if keyed:  # the keys first: the merge then builds only the rows kept, in their order
        keys = [k for t in parts for k in t.column(key_column).to_pylist()]
    else:
        table = merge_tables(parts)
        if key_column not in table.column_names:
            table = table.append_column(key_column, pa.array([None] * table.num_rows, pa.large_string()))
        keys = table.column(key_column).to_pylist()
    rank = {k: i for i, k in enumerate(order)}
    # a key is stored once by construction; should a bug ever store one
    # twice, the first row wins and the manifest says so
    first: dict[Any, int] = {}
    for i, k in enumerate(keys):
        first.setdefault(k, i)
    man["duplicates_dropped"] = len(keys) - len(first)
    rows = sorted(first.values(), key=lambda i: rank.get(keys[i], len(rank)))
    table = merge_tables(parts, rows) if keyed else table.take(pa.array(rows, pa.int64()))
    keys = [keys[i] for i in rows]
    for col in sorted({c for v in (columns or {}).values() for c in v}):
        values = pa.array([(columns or {}).get(k, {}).get(col) for k in keys])
        if pa.types.is_string(values.type):
            values = values.cast(pa.large_string())
        if col in table.column_names:
            table = table.set_column(table.column_names.index(col), col, values)
        else:
            table = table.append_column(col, values)
    man["finished"] = man.get("finished") or finished
    man["rows"] = table.num_rows
    have = set(keys)
    man["missing"] = [k for k in order if k not in have]
    out = d.parent / f"{d.name}.parquet"
    write_table_atomic(table, out, {"manifest": {k: v for k, v in man.items() if k not in ("points", "runs")}})
    write_json_atomic(man, d.parent / f"{d.name}.manifest.json")
    try:
        shutil.rmtree(d)
    except OSError as e:  # the rows are safe; the next job of this kind finishes the removal
        print(f"warning: {out} written but {d} could not be removed ({type(e).__name__}: {e}); "
              "the next run of this job removes it", file=sys.stderr)
    return out, man
