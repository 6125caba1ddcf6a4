"""Stored rows to the report's frame: value helpers and the one
normaliser (:func:`normalise`), pure (no I/O, no scene loading).

The report reads rows only.  Everything it judges by comes from the row as
it was written (results/README.md): ``primary_metric``,
``primary_threshold``, the verdicts in ``checks`` (JSON list of
``{"metric", "outcome", "value", "threshold", "message", "trace"}``) and
the scenario's ``tags`` (JSON list).  A row written before it carried them
has none: its checks are "no verdict recorded" (``verdicts`` None), its
tags unknown (``tags`` None), never re-judged against today's scene
(tests/test_report.py::test_old_rows_are_not_rejudged).
"""

from __future__ import annotations

import json
import math
from typing import Any, Mapping

import numpy as np
import pandas as pd

from physbench.harness.status import OK
from physbench.harness.sweep_store import SWEEP_COLUMNS

ERROR_FLOOR = 1e-16  # exact results (error 0) are drawn at this floor on log axes
BASE_LABEL = "base"



# ---------------------------------------------------------------------------
# small value helpers


def as_float(v: Any) -> float:
    """A float, NaN for anything missing or not numeric."""
    if v is None or isinstance(v, str) and v.strip().lower() in ("", "none", "nan", "null"):
        return math.nan
    try:
        f = float(v)
    except (TypeError, ValueError):
        return math.nan
    return f


def is_finite(v: Any) -> bool:
    return math.isfinite(as_float(v))


def is_missing(v: Any) -> bool:
    if v is None:
        return True
    if isinstance(v, float) and math.isnan(v):
        return True
    if isinstance(v, str) and v.strip().lower() in ("", "none", "nan", "null"):
        return True
    try:
        return bool(pd.isna(v)) if np.ndim(v) == 0 else False
    except (TypeError, ValueError):
        return False


def truthy(v: Any) -> bool | None:
    """bool, 'True'/'False' text (mixed columns are stored as text), 0/1;
    None when unknown."""
    if is_missing(v):
        return None
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, str):
        s = v.strip().lower()
        if s in ("true", "1", "yes"):
            return True
        if s in ("false", "0", "no"):
            return False
        return None
    f = as_float(v)
    return None if math.isnan(f) else f != 0.0


def _variant(v: Any) -> str:
    """'' for the base scenario, else the variant's name."""
    if is_missing(v) or str(v) == BASE_LABEL:
        return ""
    return str(v)


def _setting_value(v: Any) -> Any:
    """A setting's stored value back to a plain Python value."""
    if is_missing(v):
        return None
    if isinstance(v, (np.bool_, bool)):
        return bool(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v)
    if isinstance(v, str):
        s = v.strip()
        if s in ("True", "False"):
            return s == "True"
        try:
            return int(s)
        except ValueError:
            pass
        try:
            return float(s)
        except ValueError:
            return s
    return v


def fmt(v: Any, digits: int = 3) -> str:
    """Numbers to short text ('1.23e-05', '0.002'); '-' for missing."""
    if is_missing(v):
        return "-"
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    f = as_float(v)
    if math.isnan(f):
        return str(v)
    if math.isinf(f):
        return "inf" if f > 0 else "-inf"
    return f"{f:.{digits}g}"


def settings_label(settings: Mapping[str, Any]) -> str:
    """{'integrator': 'rk4', 'iterations': 10} -> 'rk4 iterations=10' (text
    values bare, others as key=value; keys sorted)."""
    parts = []
    for k in sorted(settings):
        v = settings[k]
        if isinstance(v, str):
            parts.append(v)
        elif isinstance(v, float):
            parts.append(f"{k}={v:g}")
        else:
            parts.append(f"{k}={v}")
    return " ".join(parts)


def json_list(v: Any) -> list | None:
    """A JSON list column (``checks``, ``tags``) back to a list; None when
    the row has none (written before rows carried it) or it is unreadable."""
    if is_missing(v):
        return None
    try:
        out = json.loads(v) if isinstance(v, str) else list(v)
    except (TypeError, ValueError):
        return None
    return out if isinstance(out, list) else None


# ---------------------------------------------------------------------------
# the report's frame


def _setting_columns(df: pd.DataFrame) -> list[str]:
    return [c for c in df.columns if c.startswith("setting.")]


def normalise(df: pd.DataFrame) -> pd.DataFrame:
    """Stored rows (check, sweep and limit rows, any schema version this
    report reads, columns missing or all-NaN tolerated) as the report's
    frame.  Added columns: ``source``, ``incomplete``, ``machine_id``,
    ``variant`` ('' for the base scene), ``dt``, ``cost`` (CPU s per
    simulated s: the sweep's median of repeats, else the run's own),
    ``cost_min``, ``stable_flag`` (True/False/None), ``swept`` (dict of
    swept settings), ``series_key``, ``phase``, ``judge`` ('ensemble',
    'consensus' or '' for a plain run), ``verdicts`` (list of
    verdict dicts, None when not recorded) and ``tags`` (tuple, None when
    not recorded)."""
    df = df.copy()
    n = len(df)
    for col, default in (("scenario", None), ("variant", None), ("engine", None), ("engine_version", ""),
                         ("status", "unknown"), ("message", ""), ("commit", ""), ("timestamp", ""),
                         ("source", "sweep"), ("incomplete", False), ("machine_id", None), ("_file", ""),
                         ("row_kind", None)):
        if col not in df.columns:
            df[col] = [default] * n
    for col in SWEEP_COLUMNS + ("cpu_s_per_sim_s", "stable", "setting.dt", "scene_hash", "scene_path"):
        if col not in df.columns:
            df[col] = [None] * n
    df = df.astype({c: object for c in df.columns if str(df[c].dtype) in ("str", "string")})
    if n:
        keep = ~(df["scenario"].map(is_missing) | df["engine"].map(is_missing))
        df = df.loc[keep].copy()
    n = len(df)
    df["scenario"] = df["scenario"].astype(str) if n else df["scenario"]
    df["engine"] = df["engine"].astype(str) if n else df["engine"]
    df["variant"] = [_variant(v) for v in df["variant"]]
    df["status"] = [("unknown" if is_missing(s) else str(s).strip().lower()) for s in df["status"]]
    df["message"] = ["" if is_missing(m) else str(m) for m in df["message"]]
    df["engine_version"] = ["" if is_missing(m) else str(m) for m in df["engine_version"]]
    df["commit"] = ["" if is_missing(m) else str(m) for m in df["commit"]]
    df["timestamp"] = ["" if is_missing(m) else str(m) for m in df["timestamp"]]
    df["incomplete"] = [bool(truthy(v)) for v in df["incomplete"]]
    # a row's machine: the sweep's machine id, else the fingerprint's id the
    # row carries (check and run rows), else the host of rows older than it
    for col in ("machine.id", "machine.host"):
        if col in df.columns:
            df["machine_id"] = [m if not is_missing(m) else h for m, h in zip(df["machine_id"], df[col])]
    df["machine_id"] = ["unknown" if is_missing(m) else str(m) for m in df["machine_id"]]
    df["suite"] = ["" if is_missing(s) else str(s) for s in df["suite"]]
    df["sweep_id"] = ["" if is_missing(s) else str(s) for s in df["sweep_id"]]
    df["dt"] = [as_float(v) for v in df["setting.dt"]]
    df["stable_flag"] = [truthy(v) for v in df["stable"]]

    scols = _setting_columns(df)
    swept, keys = [], []
    for i, row in enumerate(df.itertuples(index=False)):
        r = dict(zip(df.columns, row))
        ps = r.get("point_settings")
        d: dict[str, Any] | None = None
        if not is_missing(ps):
            try:
                d = json.loads(ps) if isinstance(ps, str) else dict(ps)
            except Exception:
                d = None
        if d is None:
            d = {c[len("setting."):]: _setting_value(r[c]) for c in scols}
            d = {k: v for k, v in d.items() if v is not None}
        swept.append(d)
        pk = r.get("point_key")
        if is_missing(pk):
            pk = json.dumps([r["scenario"], r["variant"], r["engine"],
                             {c[len("setting."):]: _setting_value(r[c]) for c in scols
                              if _setting_value(r[c]) is not None}], sort_keys=True, default=str)
        keys.append(str(pk))
    df["swept"] = swept
    df["point_key"] = keys
    # what a check row judges besides a plain run: an ensemble of perturbed
    # starts (its ``ensemble`` column) or the engines' consensus (engine
    # ``consensus``); '' for a plain run
    ens = list(df["ensemble"]) if "ensemble" in df.columns else [None] * len(df)
    df["judge"] = ["consensus" if e == "consensus" else ("ensemble" if not is_missing(x) else "")
                   for e, x in zip(df["engine"], ens)]
    df["scene_hash"] = ["" if is_missing(h) else str(h) for h in df["scene_hash"]]
    df["scene_path"] = ["" if is_missing(h) else str(h) for h in df["scene_path"]]
    # a point's series: its key without the scene hash (history splits a
    # series where the hash changes: history(), scene_changes())
    df["series_key"] = [k[:-len(h) - 1] if h and k.endswith("|" + h) else k
                        for k, h in zip(df["point_key"], df["scene_hash"])]
    # step phase (contract/phase.py): 0 = the scene as written
    col = list(df["phase"]) if "phase" in df.columns else [None] * len(df)
    ph = []
    for d, c in zip(swept, col):
        v = as_float(c)
        if not math.isfinite(v):
            v = as_float(d.get("phase", 0.0)) if isinstance(d, dict) else 0.0
        ph.append(v if math.isfinite(v) else 0.0)
    df["phase"] = ph

    # the verdicts and tags the row was written with (None: not recorded)
    df["verdicts"] = [[v for v in vs if isinstance(v, dict)] if vs is not None else None
                      for vs in map(json_list, df["checks"])]
    df["tags"] = [tuple(str(t) for t in ts) if ts is not None else None for ts in map(json_list, df["tags"])]
    # primary metric and error, as the row recorded them
    pm, pe = [], []
    for i, row in enumerate(df.itertuples(index=False)):
        r = dict(zip(df.columns, row))
        m = r.get("primary_metric")
        m = None if is_missing(m) else str(m)
        e = as_float(r.get("primary_error"))
        if math.isnan(e) and m and m in r:
            e = as_float(r[m])
        if r["status"] != OK:
            e = math.nan
        pm.append(m)
        pe.append(e)
    df["primary_metric"] = pm
    df["primary_error"] = pe
    med = [as_float(v) for v in df["cpu_s_per_sim_s_median"]]
    own = [as_float(v) for v in df["cpu_s_per_sim_s"]]
    df["cost"] = [m if math.isfinite(m) else o for m, o in zip(med, own)]
    df["cost_min"] = [as_float(v) for v in df["cpu_s_per_sim_s_min"]]
    df["repeats"] = [as_float(v) for v in df["repeats"]]
    return df.reset_index(drop=True)


def normalised(df: pd.DataFrame) -> pd.DataFrame:
    """A frame straight from Parquet (not through :func:`load_results`) is
    normalised first (its rows count as sweep rows unless they say
    otherwise)."""
    if "swept" in df.columns and "cost" in df.columns:
        return df
    warnings = list(df.attrs.get("warnings", []))
    notes = list(df.attrs.get("data_notes", []))
    out = normalise(df)
    out.attrs["warnings"] = warnings
    out.attrs["data_notes"] = notes
    return out

