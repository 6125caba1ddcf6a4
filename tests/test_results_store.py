"""The row store's Arrow path (harness/results.py: ``row_table``,
``merge_tables``, ``PartsDir.write_part``, ``consolidate_parts``) stores
what the pandas path stored: a row written as a part, and parts merged into
the consolidated file, read back with the same types and values, through
pyarrow (``to_pylist``: resume, ``part_rows``) and through pandas
(``read_parquet``: the report, ``read_sweeps``, the limit cache).  The
pandas path (``write_parquet_atomic(pandas.DataFrame(...))``, the
parts concatenated with ``pandas.concat``) is the reference."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from physbench.harness import results as R


def _rows_of_every_kind() -> list[dict]:
    """Rows as a sweep, a check and a search store them: text, None, NaN,
    floats, ints, bools, numpy scalars, columns present in some rows only,
    and columns whose type differs between rows (a setting that is a bool
    on one engine and text on another, an int on one and a float on
    another, None on one and a number on another)."""
    base = {"scenario": "billiards.head_on", "variant": None, "engine": "reference", "status": "ok",
            "message": "", "metric.max_penetration_m": 1.5e-5, "metric.energy_drift": math.nan,
            "steps": 2000, "setting.dt": 0.001, "setting.ccd": True, "setting.iterations": 10,
            "repeats": np.int64(3), "ok": np.bool_(True), "cpu": np.float64(0.25), "tags": '["smoke"]'}
    rows = [dict(base, point_key="a")]
    rows.append(dict(base, point_key="b", engine="mujoco", **{"setting.ccd": "swept", "setting.iterations": 12.5,
                                                             "metric.energy_drift": 0.01, "variant": "elastic"}))
    rows.append(dict(base, point_key="c", row_kind="limit_eval", limit_id="x", limit_value=3,
                     **{"metric.max_penetration_m": None, "steps": None}))
    rows.append({"point_key": "d", "status": "error", "message": "worker process died: SIGSEGV",
                 "setting.dt": 0.002, "row_kind": "limit", "limit_value": 2.5, "ok": False})
    rows.append(dict(base, point_key="e", **{"setting.iterations": True, "seq": [1, 2]}))
    rows.append(dict(base, point_key="a", status="failed"))  # a duplicate key: the first row wins
    return rows


@pytest.fixture(scope="module")
def sweep_rows(tmp_path_factory) -> list[dict]:
    """The rows a real sweep (the smoke suite, serial) stores."""
    from physbench.harness.sweep import sweep_main

    got: list[dict] = []
    real = R.PartsDir.write_rows

    def keep(self, rows, metadata=None):
        got.extend(dict(row) for row in rows)
        return real(self, rows, metadata)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(R.PartsDir, "write_rows", keep)
        assert sweep_main("smoke", executor="serial", out_dir=tmp_path_factory.mktemp("sweeps"), resume=False) == 0
    return got


def _same_values(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert list(x) == list(y)
        for k in x:
            u, v = x[k], y[k]
            assert type(u) is type(v), (k, u, v)
            assert u == v or (isinstance(u, float) and math.isnan(u) and math.isnan(v)), (k, u, v)


def _same_file(old, new) -> None:
    """Two Parquet files hold the same columns, types and values, read
    either way."""
    a, b = pq.read_table(old), pq.read_table(new)
    assert a.schema.names == b.schema.names
    assert [(f.name, f.type, f.nullable) for f in a.schema] == [(f.name, f.type, f.nullable) for f in b.schema], \
        [(f, g) for f, g in zip(a.schema, b.schema) if f != g]
    _same_values(a.to_pylist(), b.to_pylist())
    pd.testing.assert_frame_equal(pd.read_parquet(old), pd.read_parquet(new))


def test_a_row_reads_back_as_the_pandas_path_wrote_it(tmp_path, sweep_rows):
    rows = _rows_of_every_kind() + sweep_rows
    (tmp_path / "new").mkdir()
    store = R.PartsDir(tmp_path / "new", {}, -1, "point_key")
    for i, row in enumerate(rows):
        old = R.write_parquet_atomic(pd.DataFrame([row]), tmp_path / "old" / f"part-{i:06d}.parquet", {"x": 1})
        new = store.write_part(row, {"x": 1})
        _same_file(old, new)
        meta = json.loads(pq.read_schema(new).metadata[b"physbench"])
        assert meta == {"schema_version": R.SCHEMA_VERSION, "x": 1}
    assert len(R.list_parts(store.path)) == len(rows) and store.done == {r["point_key"] for r in rows}


def _pandas_merge(parts, key, order, columns, out):
    """The merge as it was: pandas.concat of the parts read by pandas, the
    first row of a key kept, planned order, then the pandas writer."""
    df = pd.concat([pd.read_parquet(p) for p in parts], ignore_index=True)
    df = df.drop_duplicates(key, keep="first")
    rank = {k: i for i, k in enumerate(order)}
    df = df.iloc[sorted(range(len(df)), key=lambda i: rank.get(df[key].iat[i], len(rank)))].reset_index(drop=True)
    for col in sorted({c for v in columns.values() for c in v}):
        df[col] = [columns.get(k, {}).get(col) for k in df[key]]
    return R.write_parquet_atomic(df, out)


@pytest.mark.parametrize("which", ["every kind", "sweep"])
def test_merged_parts_read_back_as_the_pandas_merge_wrote_them(tmp_path, sweep_rows, which):
    rows = _rows_of_every_kind() if which == "every kind" else sweep_rows
    d = tmp_path / "job"
    d.mkdir()
    R.write_json_atomic({"points": []}, d / "manifest.json")
    store = R.PartsDir(d, {}, -1, "point_key")
    for row in rows:
        store.write_part(row)
    keys = list(dict.fromkeys(r["point_key"] for r in rows))
    order = keys[::-1][1:] + ["never run"]  # one stored key not planned: it goes last
    columns = {k: {"checks": f'[{{"id": "{k}"}}]'} for k in keys[:2]}
    old = _pandas_merge(R.list_parts(d), "point_key", order, columns, tmp_path / "old.parquet")
    new, man = R.consolidate_parts(d, "point_key", order, "now", columns=columns)
    _same_file(old, new)
    assert not d.exists() and man["rows"] == len(keys) and man["missing"] == ["never run"]
    assert man["duplicates_dropped"] == len(rows) - len(keys)
    assert pq.read_table(new).column("point_key").to_pylist() == order[:-1] + [keys[-1]]


_KINDS = {"None": None, "text": "x", "int": 3, "float": 1.5, "NaN": math.nan, "bool": True, "absent": KeyError}


@pytest.mark.parametrize("n", [2, 3])
def test_every_mix_of_kinds_merges_as_pandas_merged_it(tmp_path, n):
    """Every sequence of ``n`` parts whose column ``c`` is None, text, an
    int, a float, NaN, a bool or absent merges to what pandas made of it --
    except where pandas' answer depends on the parts' order (a float or
    NaN part before a bool part gives floats, the reverse order text or
    bools): there harness.results.merge_tables' documented rule decides."""
    import itertools

    checked = 0
    for seq in itertools.product(_KINDS, repeat=n):
        if set(seq) == {"absent"}:
            continue
        first_bool = seq.index("bool") if "bool" in seq else n
        if any(k in ("float", "NaN") for k in seq[:first_bool]) and first_bool < n:
            continue
        d = tmp_path / "-".join(seq)
        parts = [R.write_parquet_atomic(pd.DataFrame([{"k": f"k{i}"} | ({} if k == "absent" else {"c": _KINDS[k]})]),
                                        d / f"part-{i:06d}.parquet") for i, k in enumerate(seq)]
        old = R.write_parquet_atomic(pd.concat([pd.read_parquet(p) for p in parts], ignore_index=True),
                                     d / "old.parquet")
        new = R.write_table_atomic(R.merge_tables([pq.read_table(p) for p in parts]), d / "new.parquet")
        _same_file(old, new)
        checked += 1
    assert checked > 0.8 * (len(_KINDS) ** n)


def test_parts_of_mixed_kinds_merge_to_one_typed_column(tmp_path):
    """Parts whose columns disagree -- a metric NaN in one part, a float in
    another, None in a third; a setting int in one part and float in
    another; text beside None; a column only one part has; a column an int
    in one part and text in another -- consolidate to one type per column:
    numbers as float (NaN and None as null), text as text, a mix as the
    text of each value, a column a part lacks null there."""
    import pyarrow as pa

    d = tmp_path / "job"
    d.mkdir()
    R.write_json_atomic({"points": []}, d / "manifest.json")
    store = R.PartsDir(d, {}, -1, "k")
    rows = [{"k": "a", "metric.e": math.nan, "setting.n": 3, "label": "x", "only_a": 7, "flag": True},
            {"k": "b", "metric.e": 0.5, "setting.n": 2.5, "label": None, "flag": False},
            {"k": "c", "metric.e": None, "setting.n": None, "label": "y", "flag": None, "mixed": 1},
            {"k": "d", "metric.e": 0.25, "setting.n": 4, "label": "z", "flag": True, "mixed": "swept"}]
    for row in rows:
        store.write_part(row)
    out, _ = R.consolidate_parts(d, "k", ["a", "b", "c", "d"], "now")
    t = pq.read_table(out)
    types = {f.name: f.type for f in t.schema}
    assert types["metric.e"] == types["setting.n"] == types["only_a"] == pa.float64()
    assert pa.types.is_string(types["label"]) or pa.types.is_large_string(types["label"])
    assert pa.types.is_large_string(types["mixed"]) and types["flag"] == pa.bool_()
    cols = t.to_pydict()
    assert cols["k"] == ["a", "b", "c", "d"]
    assert cols["metric.e"] == [None, 0.5, None, 0.25]
    assert cols["setting.n"] == [3.0, 2.5, None, 4.0] and all(type(v) is float for v in cols["setting.n"] if v)
    assert cols["only_a"] == [7.0, None, None, None]
    assert cols["label"] == ["x", None, "y", "z"] and cols["flag"] == [True, False, None, True]
    assert cols["mixed"] == [None, None, "1", "swept"]
    df = pd.read_parquet(out)
    assert str(df["metric.e"].dtype) == str(df["setting.n"].dtype) == "float64"
    assert math.isnan(df["metric.e"].iat[0]) and df["setting.n"].iat[0] == 3.0


def test_a_part_of_several_rows_reads_back_as_its_rows_one_by_one(tmp_path, sweep_rows):
    """``PartsDir.write_rows`` stores the rows of one call as one part: one
    table per row signature, in the order the signatures first appear, all
    in the part even where two of them hold a column with different
    non-null types (stored as two columns, the second under a made-up name):
    each row reads back with the names, types and values its own one-row
    part held, the report's and the limit cache's reader (``read_frame``)
    sees one row per row without the part's bookkeeping columns, and the
    merged file is the one the one-row parts merge to."""
    import pyarrow as pa

    rows = _rows_of_every_kind() + sweep_rows + _rows_of_every_kind()[:3]
    one, many = tmp_path / "one", tmp_path / "many"
    for d in (one, many):
        d.mkdir()
        R.write_json_atomic({"points": []}, d / "manifest.json")
    a, b = R.PartsDir(one, {}, -1, "point_key"), R.PartsDir(many, {}, -1, "point_key")
    for row in rows:
        a.write_part(row)
    paths = b.write_rows(rows[:5]) + b.write_rows(rows[5:])
    groups: dict = {}
    for i, row in enumerate(rows[:5]):
        groups.setdefault(R.row_signature(row) or i, []).append(i)
    for i, row in enumerate(rows[5:], 5):
        groups.setdefault(("second", R.row_signature(row) or i), []).append(i)
    # rows a and b disagree in type (setting.ccd bool / text, setting.iterations int / float), and so do
    # the smoke sweep's rows of several signatures: still one part a call
    assert len(paths) == 2 and len(groups) < len(rows) and b.done == a.done
    assert sum(pq.read_metadata(p).num_rows for p in paths) == len(rows)
    assert all(R.PART_SCHEMA_COLUMN in pq.read_schema(p).names for p in paths)
    second = [isinstance(g, tuple) and g[0] == "second" for g in groups]
    assert [len(R.read_part_tables(p)) for p in paths] == [second.count(False), second.count(True)]
    renamed = json.loads(pq.read_schema(paths[0]).metadata[b"physbench"])[R.PART_COLUMNS_KEY]
    stored = pq.read_schema(paths[0]).names
    # one stored column per type the rows give a column (bool and text; int, float and bool), the first
    # type's under the column's own name
    assert renamed.count("setting.ccd") == 2 and renamed.count("setting.iterations") == 3
    for name in ("setting.ccd", "setting.iterations"):
        assert stored[renamed.index(name)] == name and stored.count(name) == 1
    types: dict = {}  # across the part's tables, a column may have several types
    for t in R.read_part_tables(paths[0]):
        for f in t.schema:
            if f.type != pa.null():
                types.setdefault(f.name, set()).add(f.type)
    assert len(types["setting.ccd"]) == 2 and len(types["setting.iterations"]) == 3  # int, float, bool
    one_rows = a.part_rows()
    _same_values([one_rows[i] for same in groups.values() for i in same], b.part_rows())
    framed = pd.concat([R.read_frame(p) for p in paths], ignore_index=True)
    assert R.PART_SCHEMA_COLUMN not in framed.columns and len(framed) == len(rows)
    assert framed["point_key"].tolist() == [rows[i]["point_key"] for same in groups.values() for i in same]
    order = list(dict.fromkeys(r["point_key"] for r in rows))[::-1]
    _same_file(R.consolidate_parts(one, "point_key", order, "now")[0],
               R.consolidate_parts(many, "point_key", order, "now")[0])


def _pandas_group_merge(tables):
    """The merge of parts of several schemas as harness.results.merge_tables
    made it before it typed columns in Arrow: each schema's rows one
    DataFrame (schemas in the order they first appear), one
    ``pandas.concat``, the parts' row order, ``_normalize``, ``from_pandas``."""
    import pyarrow as pa

    groups: dict = {}
    start = 0
    for t in tables:
        t = t.replace_schema_metadata(None)
        groups.setdefault(t.schema, []).append((t, start))
        start += t.num_rows
    frames, rank = [], []
    for same in groups.values():
        frames.append(pa.concat_tables([t for t, _ in same]).to_pandas())
        rank.extend(i for t, at in same for i in range(at, at + t.num_rows))
    df = pd.concat(frames, ignore_index=True)
    df = df.iloc[sorted(range(len(rank)), key=rank.__getitem__)].reset_index(drop=True)
    return pa.Table.from_pandas(R._normalize(df), preserve_index=False)


@pytest.mark.parametrize("seed", range(10))
def test_the_arrow_merge_types_every_column_as_the_pandas_merge(tmp_path, seed):
    """Parts of random rows -- each column, row by row, None, text, an int,
    a float, NaN, a bool or absent, mostly one kind per column as a sweep's
    rows are (a metric float or NaN, a setting absent on other engines,
    text beside gaps, a column all None) -- stored several rows to a part
    (``PartsDir.write_rows``) merge to the columns, types and values the
    whole-frame pandas merge gives (:func:`_pandas_group_merge`), read
    either way; and so does a part per row."""
    import random

    rng = random.Random(seed)
    kinds = list(_KINDS)
    cols = [f"c{j}" for j in range(14)]
    main = {c: rng.choice(kinds) for c in cols}  # a column's usual kind
    rows = []
    for i in range(rng.randint(20, 60)):
        row = {"point_key": f"k{i}"}
        for c in cols:
            k = main[c] if rng.random() < 0.8 else rng.choice(kinds)
            if k != "absent":
                row[c] = _KINDS[k] if k != "int" else rng.randint(-5, 5)
        if rng.random() < 0.1:  # a row whose columns come in another order
            items = list(row.items())
            rng.shuffle(items)
            row = dict(items)
        rows.append(row)
    for per_part in (1, 7):
        d = tmp_path / f"job{per_part}"
        d.mkdir()
        store = R.PartsDir(d, {}, -1, "point_key")
        for i in range(0, len(rows), per_part):
            store.write_rows(rows[i:i + per_part])
        tables = [t for p in R.list_parts(d) for t in R.read_part_tables(p)]
        if len({t.schema for t in tables}) < 2:
            continue
        old = R.write_table_atomic(_pandas_group_merge(tables), tmp_path / f"old{per_part}.parquet")
        new = R.write_table_atomic(R.merge_tables(tables), tmp_path / f"new{per_part}.parquet")
        _same_file(old, new)


def test_the_merge_of_the_kept_parts_is_the_merge_of_the_files(tmp_path, sweep_rows):
    """A sweep merges the parts it wrote itself from its own copy of them
    (``PartsDir.written``) instead of reading them back: the merged file is
    the one reading every part gives, also when only some parts are kept (a
    resumed sweep's parts from before are read) and when a part holds a
    row the pandas path types (a list)."""
    rows = _rows_of_every_kind() + sweep_rows + _rows_of_every_kind()[:3]
    dirs = [tmp_path / n for n in ("read", "kept", "some")]
    stores = []
    for d in dirs:
        d.mkdir()
        R.write_json_atomic({"points": []}, d / "manifest.json")
        store = R.PartsDir(d, {}, -1, "point_key")
        for i in range(0, len(rows), 7):
            store.write_rows(rows[i:i + 7], {"sweep_id": "s"})
        stores.append(store)
    names = [p.name for p in R.list_parts(dirs[0])]
    assert len(names) > 2 and list(stores[1].written) == names
    some = dict(list(stores[2].written.items())[1:])
    order = list(dict.fromkeys(r["point_key"] for r in rows))[::-1]
    read = R.consolidate_parts(dirs[0], "point_key", order, "now")[0]
    for d, written in ((dirs[1], stores[1].written), (dirs[2], some)):
        _same_file(read, R.consolidate_parts(d, "point_key", order, "now", written=written)[0])
