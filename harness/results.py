"""Results store: run rows as Parquet under ``results/``, written atomically.

Rows are flat dicts (harness.runner.RunResult.row()).  Every file carries the
schema version in its Parquet metadata and a ``schema_version`` column, so
later readers can tell old rows from new ones.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, Iterable

import pandas as pd

from harness.scene import REPO_ROOT

SCHEMA_VERSION = 1
RESULTS_DIR = REPO_ROOT / "results"


def write_rows(rows: Iterable[dict[str, Any]], path: str | Path, append: bool = True) -> Path:
    """Write ``rows`` to the Parquet file ``path`` atomically (temp file +
    rename), appending to what is there when ``append``.  Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    df = pd.DataFrame(list(rows))
    df["schema_version"] = SCHEMA_VERSION
    if append and path.exists():
        df = pd.concat([pd.read_parquet(path), df], ignore_index=True)
    # columns mixing types (None and str, bool and float) are stored as text
    # where pyarrow cannot infer one type
    for col in df.columns:
        if df[col].dtype == object:
            kinds = {type(v) for v in df[col] if v is not None}
            if len(kinds) > 1:
                df[col] = df[col].map(lambda v: None if v is None else str(v))
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".parquet")
    os.close(fd)
    try:
        df.to_parquet(tmp, index=False)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read_rows(path: str | Path) -> pd.DataFrame:
    return pd.read_parquet(path)
