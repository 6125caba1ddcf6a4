"""``physbench report``: one self-contained HTML page from stored results.

Input (see results/README.md and docs/REPORT.md):

- sweep rows, ``results/sweeps/<machine-id>/<suite>/<sweep_id>.parquet``
  (consolidated) and ``results/sweeps/<machine-id>/<suite>/<sweep_id>/part-*.parquet``
  (a sweep still running or killed: read, and marked *incomplete*);
- conformance rows, ``results/check/*.parquet`` (``physbench check``), used
  for the stability matrix.

Sections: at a glance (per scenario family the cheapest engine to reach
each accuracy of the ladder 1e-2 .. 1e-9, each engine's breaking points),
header (machines, commits, suites, sweeps, engine versions), work-precision
diagrams (a frontier per engine, one colour per engine in every plot), cost
to reach each rung of the accuracy ladder and each scenario's own target,
breaking points (``physbench limits`` / ``[[limit]]`` rows), stability matrix
("ran and stayed finite" apart from "met its checks"), step phases, history
across runs (regressions flagged only beyond noise), footer.

The page has no external assets and no JavaScript: plots are matplotlib (Agg)
PNGs embedded as base64 ``data:`` URIs, styles are inline, tables are HTML.

Pure functions (tests use them on synthetic frames): :func:`load_results`,
:func:`work_precision`, :func:`cost_to_target`, :func:`stability_matrix`,
:func:`regressions`, :func:`history`, :func:`render_html`; the CLI entry is
:func:`report_main`.
"""

from __future__ import annotations

import base64
import datetime as _dt
import functools
import html
import io
import json
import math
import sys
import tomllib
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import pandas as pd

from harness.results import RESULTS_DIR, SCHEMA_VERSION
from harness.status import BROKEN_STATUSES, DIVERGED, OK, UNSUPPORTED
from harness.sweep_store import sweep_files

SUPPORTED_SCHEMAS = frozenset({SCHEMA_VERSION})
ERROR_FLOOR = 1e-16  # exact results (error 0) are drawn at this floor on log axes
NOISE_FLOOR = 0.10  # relative change below which nothing is ever flagged
NOISE_SPREADS = 3.0  # ... and the multiple of the repeats' relative spread (and of the nightly scatter)
BASELINE_RUNS = 5  # a cost is compared with the median of this many latest earlier ok runs of its series
MAD_TO_SIGMA = 1.4826  # MAD x this estimates a normal standard deviation
DRIFT_HORIZON = 30  # earlier ok runs a cost drift is looked for in
MIN_COST_HISTORY = 3  # earlier ok runs a cost series needs before a change in it is judged
MACHINE_SHIFT_MIN_SERIES = 20  # series a night needs before its machine-wide cost shift is taken out
ERROR_ABS_FLOOR = 1e-12  # an accuracy change must also exceed this absolutely
MAX_SMALL_MULTIPLES = 6

BASE_LABEL = "base"

_SWEEP_COLUMNS = ("suite", "sweep_id", "point_key", "point_settings", "primary_metric", "primary_error",
                  "cpu_s_per_sim_s_median", "cpu_s_per_sim_s_min", "repeats")


# ---------------------------------------------------------------------------
# small value helpers


def _num(v: Any) -> float:
    """A float, NaN for anything missing or not numeric."""
    if v is None or isinstance(v, str) and v.strip().lower() in ("", "none", "nan", "null"):
        return math.nan
    try:
        f = float(v)
    except (TypeError, ValueError):
        return math.nan
    return f


def _finite(v: Any) -> bool:
    return math.isfinite(_num(v))


def _missing(v: Any) -> bool:
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


def _truthy(v: Any) -> bool | None:
    """bool, 'True'/'False' text (mixed columns are stored as text), 0/1;
    None when unknown."""
    if _missing(v):
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
    f = _num(v)
    return None if math.isnan(f) else f != 0.0


def _variant(v: Any) -> str:
    """'' for the base scenario, else the variant's name."""
    if _missing(v) or str(v) == BASE_LABEL:
        return ""
    return str(v)


def _setting_value(v: Any) -> Any:
    """A setting's stored value back to a plain Python value."""
    if _missing(v):
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
    if _missing(v):
        return "-"
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    f = _num(v)
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


# ---------------------------------------------------------------------------
# loading


def _read_file(path: Path, warnings: list[str], **extra: Any) -> pd.DataFrame | None:
    try:
        df = pd.read_parquet(path)
    except Exception as e:  # a torn or foreign file must not sink the report
        warnings.append(f"{path}: unreadable, skipped ({type(e).__name__}: {e})")
        return None
    if df.empty:
        return None
    if "schema_version" in df.columns:
        sv = df["schema_version"].map(_num)
        bad = ~sv.isin(list(SUPPORTED_SCHEMAS))
        if bad.any():
            versions = sorted({fmt(x) for x in df.loc[bad, "schema_version"]})
            warnings.append(f"{path}: {int(bad.sum())} row(s) with schema_version {', '.join(versions)} skipped "
                            f"(this report reads version {', '.join(str(v) for v in sorted(SUPPORTED_SCHEMAS))})")
            df = df.loc[~bad]
            if df.empty:
                return None
    else:
        warnings.append(f"{path}: no schema_version column; read as version {SCHEMA_VERSION}")
    df = df.copy()
    df["_file"] = str(path)
    for k, v in extra.items():
        if k in ("suite", "sweep_id", "machine_id") and k in df.columns:
            # the file's own column wins; the layout fills the gaps
            df[k] = df[k].where(~df[k].map(_missing), v)
        else:
            df[k] = v
    return df


def _visible(paths: Iterable[Path]) -> list[Path]:
    return sorted(p for p in paths if not p.name.startswith("."))


def load_results(results_dir: str | Path | None = None, suites: list[str] | None = None) -> pd.DataFrame:
    """All stored rows under ``results_dir`` (default ``results/``) as one
    normalised frame.

    Added columns: ``source`` ('sweep' or 'check'), ``incomplete`` (rows of
    an unconsolidated sweep directory), ``machine_id``, ``variant`` ('' for
    the base scene), ``dt``, ``cost`` (CPU s per simulated s: the sweep's
    median of repeats, else the run's own), ``cost_min``, ``stable_flag``
    (True/False/None), ``swept`` (dict of swept settings) and, when a file
    lacks them, the sweep columns (``point_key``, ``primary_metric``,
    ``primary_error`` ...).  Warnings (unreadable files, unknown schema
    versions) are in ``df.attrs['warnings']``.
    """
    root = Path(results_dir) if results_dir is not None else RESULTS_DIR
    warnings: list[str] = []
    frames: list[pd.DataFrame] = []
    for mid, suite, sid, p, complete in sweep_files(root / "sweeps", suites):
        frames.append(_read_file(p, warnings, source="sweep", incomplete=not complete,
                                 machine_id=mid, suite=suite, sweep_id=sid))
    check = root / "check"
    if check.is_dir():
        for p in _visible(check.glob("*.parquet")):
            frames.append(_read_file(p, warnings, source="check", incomplete=False, check_file=p.stem))
    frames = [f for f in frames if f is not None]
    if not frames:
        df = _normalise(pd.DataFrame())
    else:
        df = _normalise(pd.concat(frames, ignore_index=True, sort=False))
    if suites:
        df = df[(df["source"] != "sweep") | df["suite"].isin(suites)].reset_index(drop=True)
    df.attrs["warnings"] = warnings
    return df


@functools.lru_cache(maxsize=None)
def _scene(scenario: str, variant: str, path: str = ""):
    """The compiled scene, or None when it no longer loads: from the row's
    ``scene_path`` when there is one (a spec file anywhere), else by id from
    scenarios/.  Only a fallback: rows carry their primary metric, its
    threshold and their checks' outcomes."""
    try:
        from contract.scene import load_scene, source_path

        f = source_path(path) if path and not _missing(path) else None
        if f is not None and f.is_file():
            return load_scene(f, variant or None)
        return load_scene(scenario, variant or None)
    except Exception:
        return None


def scene_primary_metric(scenario: str, variant: str = "", path: str = "") -> str | None:
    s = _scene(scenario, variant, path)
    return None if s is None else s.primary_metric


def scene_threshold(scenario: str, variant: str, metric: str | None, path: str = "") -> float | None:
    """The scenario's ``[[check]] max`` for ``metric`` (checks scoped to some
    engines only count when no unscoped one exists; the tightest wins)."""
    from harness.conformance import primary_threshold

    if not metric:
        return None
    s = _scene(scenario, variant, path)
    return None if s is None else primary_threshold(s, metric)


def hard_scenarios() -> set[str]:
    """Ids of the scenarios tagged 'hard' in scenarios/*.toml."""
    from contract.scene import SCENARIO_DIR

    out = set()
    for p in SCENARIO_DIR.rglob("*.toml"):
        try:
            data = tomllib.loads(p.read_text())
        except Exception:
            continue
        if "hard" in (data.get("scenario", {}).get("tags") or []):
            out.add(".".join(p.relative_to(SCENARIO_DIR).with_suffix("").parts))
    return out


def _setting_columns(df: pd.DataFrame) -> list[str]:
    return [c for c in df.columns if c.startswith("setting.")]


def _normalise(df: pd.DataFrame) -> pd.DataFrame:
    df = df.copy()
    n = len(df)
    for col, default in (("scenario", None), ("variant", None), ("engine", None), ("engine_version", ""),
                         ("status", "unknown"), ("message", ""), ("commit", ""), ("timestamp", ""),
                         ("source", "sweep"), ("incomplete", False), ("machine_id", None), ("_file", ""),
                         ("row_kind", None)):
        if col not in df.columns:
            df[col] = [default] * n
    for col in _SWEEP_COLUMNS + ("cpu_s_per_sim_s", "stable", "setting.dt", "scene_hash", "scene_path",
                                 "primary_threshold", "checks"):
        if col not in df.columns:
            df[col] = [None] * n
    df = df.astype({c: object for c in df.columns if str(df[c].dtype) in ("str", "string")})
    if n:
        keep = ~(df["scenario"].map(_missing) | df["engine"].map(_missing))
        df = df.loc[keep].copy()
    n = len(df)
    df["scenario"] = df["scenario"].astype(str) if n else df["scenario"]
    df["engine"] = df["engine"].astype(str) if n else df["engine"]
    df["variant"] = [_variant(v) for v in df["variant"]]
    df["status"] = [("unknown" if _missing(s) else str(s).strip().lower()) for s in df["status"]]
    df["message"] = ["" if _missing(m) else str(m) for m in df["message"]]
    df["engine_version"] = ["" if _missing(m) else str(m) for m in df["engine_version"]]
    df["commit"] = ["" if _missing(m) else str(m) for m in df["commit"]]
    df["timestamp"] = ["" if _missing(m) else str(m) for m in df["timestamp"]]
    df["incomplete"] = [bool(_truthy(v)) for v in df["incomplete"]]
    # a row's machine: the sweep's machine id, else the fingerprint's id the
    # row carries (check and run rows), else the host of rows older than it
    for col in ("machine.id", "machine.host"):
        if col in df.columns:
            df["machine_id"] = [m if not _missing(m) else h for m, h in zip(df["machine_id"], df[col])]
    df["machine_id"] = ["unknown" if _missing(m) else str(m) for m in df["machine_id"]]
    df["suite"] = ["" if _missing(s) else str(s) for s in df["suite"]]
    df["sweep_id"] = ["" if _missing(s) else str(s) for s in df["sweep_id"]]
    df["dt"] = [_num(v) for v in df["setting.dt"]]
    df["stable_flag"] = [_truthy(v) for v in df["stable"]]

    scols = _setting_columns(df)
    swept, keys = [], []
    for i, row in enumerate(df.itertuples(index=False)):
        r = dict(zip(df.columns, row))
        ps = r.get("point_settings")
        d: dict[str, Any] | None = None
        if not _missing(ps):
            try:
                d = json.loads(ps) if isinstance(ps, str) else dict(ps)
            except Exception:
                d = None
        if d is None:
            d = {c[len("setting."):]: _setting_value(r[c]) for c in scols}
            d = {k: v for k, v in d.items() if v is not None}
        swept.append(d)
        pk = r.get("point_key")
        if _missing(pk):
            pk = json.dumps([r["scenario"], r["variant"], r["engine"],
                             {c[len("setting."):]: _setting_value(r[c]) for c in scols
                              if _setting_value(r[c]) is not None}], sort_keys=True, default=str)
        keys.append(str(pk))
    df["swept"] = swept
    df["point_key"] = keys
    df["scene_hash"] = ["" if _missing(h) else str(h) for h in df["scene_hash"]]
    df["scene_path"] = ["" if _missing(h) else str(h) for h in df["scene_path"]]
    # a point's series: its key without the scene hash (history splits a
    # series where the hash changes: history(), scene_changes())
    df["series_key"] = [k[:-len(h) - 1] if h and k.endswith("|" + h) else k
                        for k, h in zip(df["point_key"], df["scene_hash"])]
    # step phase (contract/phase.py): 0 = the scene as written
    col = list(df["phase"]) if "phase" in df.columns else [None] * len(df)
    ph = []
    for d, c in zip(swept, col):
        v = _num(c)
        if not math.isfinite(v):
            v = _num(d.get("phase", 0.0)) if isinstance(d, dict) else 0.0
        ph.append(v if math.isfinite(v) else 0.0)
    df["phase"] = ph

    # primary metric and error: the sweep's columns, else the scene's metric
    pm, pe = [], []
    for i, row in enumerate(df.itertuples(index=False)):
        r = dict(zip(df.columns, row))
        m = r.get("primary_metric")
        if _missing(m):
            m = scene_primary_metric(r["scenario"], r["variant"], r.get("scene_path") or "")
        m = None if _missing(m) else str(m)
        e = _num(r.get("primary_error"))
        if math.isnan(e) and m and m in r:
            e = _num(r[m])
        if r["status"] != "ok":
            e = math.nan
        pm.append(m)
        pe.append(e)
    df["primary_metric"] = pm
    df["primary_error"] = pe
    med = [_num(v) for v in df["cpu_s_per_sim_s_median"]]
    own = [_num(v) for v in df["cpu_s_per_sim_s"]]
    df["cost"] = [m if math.isfinite(m) else o for m, o in zip(med, own)]
    df["cost_min"] = [_num(v) for v in df["cpu_s_per_sim_s_min"]]
    df["repeats"] = [_num(v) for v in df["repeats"]]
    return df.reset_index(drop=True)


def _ensure(df: pd.DataFrame) -> pd.DataFrame:
    """A frame straight from Parquet (not through :func:`load_results`) is
    normalised first (its rows count as sweep rows unless they say
    otherwise)."""
    if "swept" in df.columns and "cost" in df.columns:
        return df
    warnings = list(df.attrs.get("warnings", []))
    out = _normalise(df)
    out.attrs["warnings"] = warnings
    return out


# ---------------------------------------------------------------------------
# selections


def _sweeps(df: pd.DataFrame) -> pd.DataFrame:
    """Sweep grid points (breaking-point rows, ``row_kind`` set, are read by
    :func:`breaking_points` only)."""
    if not len(df):
        return df
    return df[(df["source"] == "sweep") & df["row_kind"].map(_missing)]


def _limit_rows(df: pd.DataFrame, kind: str) -> pd.DataFrame:
    if not len(df):
        return df
    return df[df["row_kind"].map(lambda v: v == kind)]


def latest_points(df: pd.DataFrame) -> pd.DataFrame:
    """Each sweep point's latest row per machine (by sweep_id, which sorts
    by time)."""
    df = _ensure(df)
    s = _sweeps(df)
    if s.empty:
        return s
    s = s.sort_values(["sweep_id", "timestamp"], kind="stable")
    return s.drop_duplicates(["machine_id", "point_key"], keep="last").reset_index(drop=True)


def _unshifted(df: pd.DataFrame) -> pd.DataFrame:
    """Rows of the scene as written (phase 0): the other step phases of a
    point are draws of the same configuration, summarised by
    :func:`phase_table`, not extra points of a curve."""
    if df.empty or "phase" not in df.columns:
        return df
    return df[df["phase"] == 0.0]


def _latest_checks(df: pd.DataFrame) -> pd.DataFrame:
    c = _unshifted(df[df["source"] == "check"]) if len(df) else df
    if c.empty:
        return c
    # a check run is the engine's defaults at the scene's dt (or the hard
    # dt): keyed by dt, so that settings added between commits do not count
    # the same run twice
    c = c.sort_values(["_file", "timestamp"], kind="stable").copy()
    c["_dtkey"] = [fmt(d, 9) for d in c["dt"]]
    c = c.drop_duplicates(["machine_id", "scenario", "variant", "engine", "_dtkey"], keep="last")
    return c.drop(columns="_dtkey").reset_index(drop=True)


def _good(r: Mapping[str, Any]) -> bool:
    """ok and not known to be unstable."""
    return r["status"] == "ok" and r.get("stable_flag") is not False


def _targets(df: pd.DataFrame, target: float | None,
             targets: Mapping[Any, float] | float | None = None) -> dict[tuple[str, str], tuple[float | None, str]]:
    """(scenario, variant) -> (target, where it came from)."""
    out: dict[tuple[str, str], tuple[float | None, str]] = {}
    if df.empty:
        return out
    for (sc, va), g in df.groupby(["scenario", "variant"], sort=True):
        metric = next((m for m in g["primary_metric"] if m), None)
        given = _lookup_target(targets, sc, va)
        if given is not None:
            out[(sc, va)] = (given, "given")
            continue
        th = next((_num(t) for t in g["primary_threshold"] if _finite(t)), None)
        if th is None:
            path = next((p for p in g["scene_path"] if p), "")
            th = scene_threshold(sc, va, metric, path)
        if th is not None:
            out[(sc, va)] = (th, "check max")
        elif target is not None:
            out[(sc, va)] = (float(target), "--target")
        else:
            out[(sc, va)] = (None, "none")
    return out


def _lookup_target(targets: Mapping[Any, float] | float | None, sc: str, va: str) -> float | None:
    if targets is None:
        return None
    if isinstance(targets, (int, float)):
        return float(targets)
    for k in ((sc, va), (sc, va or None), f"{sc}/{va}" if va else sc, sc):
        if k in targets and targets[k] is not None:
            return float(targets[k])
    return None


# ---------------------------------------------------------------------------
# work-precision


def work_precision(df: pd.DataFrame, target: float | None = None,
                   targets: Mapping[Any, float] | float | None = None) -> dict[tuple[str, str], dict[str, Any]]:
    """Per (scenario, variant): lines of (cost, primary error) points along
    dt, one line per engine x non-dt swept settings (x machine when several).

    Returns ``{(scenario, variant): {"primary_metric", "threshold",
    "threshold_source", "clipped", "lines": [{"label", "engine", "settings",
    "machine_id", "points": [{"dt", "cost", "error", "error_plot", "status",
    "message", "ok", "incomplete"}...] (ascending dt)}...],
    "not_ok": [{"label", "dt", "cost", "status", "message"}...]}}``.
    A point is ``ok`` when its status is ok, it is not known unstable, and
    its error and cost are finite; ``error_plot`` is the error clipped to
    ERROR_FLOOR (``clipped`` says whether any was).
    """
    df = _ensure(df)
    pts = _unshifted(latest_points(df))
    out: dict[tuple[str, str], dict[str, Any]] = {}
    if pts.empty:
        return out
    many_machines = pts["machine_id"].nunique() > 1
    tg = _targets(pts, target, targets)
    for (sc, va), g in pts.groupby(["scenario", "variant"], sort=True):
        metric = next((m for m in g["primary_metric"] if m), None)
        th, src = tg.get((sc, va), (None, "none"))
        lines: dict[tuple, dict[str, Any]] = {}
        not_ok = []
        clipped = False
        for r in g.to_dict("records"):
            nondt = {k: v for k, v in (r["swept"] or {}).items() if k != "dt"}
            label = " ".join(x for x in (r["engine"], settings_label(nondt)) if x)
            if many_machines:
                label += f" @{r['machine_id']}"
            key = (r["engine"], json.dumps(nondt, sort_keys=True, default=str), r["machine_id"])
            line = lines.setdefault(key, {"label": label, "engine": r["engine"], "settings": nondt,
                                          "machine_id": r["machine_id"], "points": []})
            err, cost = r["primary_error"], r["cost"]
            ok = _good(r) and math.isfinite(err) and math.isfinite(cost)
            status = r["status"] if r["status"] != "ok" or r.get("stable_flag") is not False else "unstable"
            if r["status"] == "ok" and status == "ok" and not math.isfinite(err):
                status = "no error"
            plot = max(err, ERROR_FLOOR) if ok else math.nan
            if ok and err < ERROR_FLOOR:
                clipped = True
            p = {"dt": r["dt"], "cost": cost, "error": err, "error_plot": plot, "status": status,
                 "message": r["message"], "ok": ok, "incomplete": r["incomplete"]}
            line["points"].append(p)
            if not ok:
                not_ok.append({"label": label, "dt": r["dt"], "cost": cost, "status": status,
                               "message": r["message"]})
        for line in lines.values():
            line["points"].sort(key=lambda p: (math.inf if math.isnan(p["dt"]) else p["dt"]))
        ordered = sorted(lines.values(), key=lambda l: l["label"])
        not_ok.sort(key=lambda p: (p["label"], math.inf if math.isnan(p["dt"]) else p["dt"]))
        out[(sc, va)] = {"scenario": sc, "variant": va, "primary_metric": metric, "threshold": th,
                         "threshold_source": src, "clipped": clipped, "lines": ordered, "not_ok": not_ok}
    return out


# ---------------------------------------------------------------------------
# cost to reach a target accuracy


def cost_to_target(df: pd.DataFrame, targets: Mapping[Any, float] | float | None = None,
                   target: float | None = None) -> pd.DataFrame:
    """Per (scenario, variant, engine): the cheapest point (latest sweep)
    whose primary error <= the target, its cost and the ratio to the
    cheapest engine that reached it; ``reached`` False with the best error
    achieved otherwise.

    ``targets``: a number for every scenario, or a mapping keyed by
    (scenario, variant) / 'scenario/variant' / scenario; where it gives none,
    the scenario's ``[[check]] max`` for its primary metric, else ``target``.
    Rows without any target are left out.
    """
    df = _ensure(df)
    cols = ["scenario", "variant", "engine", "primary_metric", "target", "target_source", "reached",
            "settings", "dt", "cost", "error", "ratio", "best_error", "best_error_settings", "points", "note"]
    pts = _unshifted(latest_points(df))
    if pts.empty:
        return pd.DataFrame(columns=cols)
    tg = _targets(pts, target, targets)
    rows = []
    for (sc, va, en), g in pts.groupby(["scenario", "variant", "engine"], sort=True):
        t, src = tg.get((sc, va), (None, "none"))
        if t is None:
            continue
        recs = g.to_dict("records")
        good = [r for r in recs if _good(r) and math.isfinite(r["primary_error"])]
        under = [r for r in good if r["primary_error"] <= t and math.isfinite(r["cost"])]
        metric = next((r["primary_metric"] for r in recs if r["primary_metric"]), None)
        row = {"scenario": sc, "variant": va, "engine": en, "primary_metric": metric, "target": t,
               "target_source": src, "points": len(recs), "ratio": math.nan, "note": ""}
        if under:
            best = min(under, key=lambda r: (r["cost"], r["primary_error"]))
            row.update(reached=True, settings=settings_label(best["swept"]), dt=best["dt"], cost=best["cost"],
                       error=best["primary_error"], best_error=math.nan, best_error_settings="")
        else:
            row.update(reached=False, settings="", dt=math.nan, cost=math.nan, error=math.nan)
            if good:
                b = min(good, key=lambda r: r["primary_error"])
                row.update(best_error=b["primary_error"], best_error_settings=settings_label(b["swept"]))
            else:
                row.update(best_error=math.nan, best_error_settings="")
                row["note"] = "no ok point"
        rows.append(row)
    out = pd.DataFrame(rows, columns=cols)
    if out.empty:
        return out
    for (sc, va), g in out.groupby(["scenario", "variant"]):
        reached = g[g["reached"].astype(bool)]
        if len(reached):
            cheapest = reached["cost"].min()
            if cheapest > 0:
                out.loc[reached.index, "ratio"] = reached["cost"] / cheapest
    return out.sort_values(["scenario", "variant", "reached", "cost", "engine"],
                           ascending=[True, True, False, True, True], kind="stable").reset_index(drop=True)


#: accuracies of the primary metric the report asks every engine for
LADDER = (1e-2, 1e-4, 1e-6, 1e-9)


def ladder(df: pd.DataFrame, rungs: Iterable[float] = LADDER) -> pd.DataFrame:
    """:func:`cost_to_target` at every rung of the accuracy ladder: per
    (scenario, variant, engine, rung) the cheapest configuration reaching
    the rung, or (``reached`` False) the best error reached and where.
    Column ``rung`` holds the target."""
    parts = []
    for t in rungs:
        ct = cost_to_target(df, targets=float(t))
        if not ct.empty:
            parts.append(ct.assign(rung=float(t)))
    if not parts:
        return pd.DataFrame(columns=["scenario", "variant", "engine", "rung", "reached", "cost", "settings"])
    return pd.concat(parts, ignore_index=True)


def family(scenario: str) -> str:
    return scenario.split(".", 1)[0]


def breaking_points(df: pd.DataFrame) -> pd.DataFrame:
    """The latest breaking-point search per (machine, scenario, variant,
    engine, parameter, range, overrides) from the stored ``limit`` rows
    (``physbench limits`` and ``[[limit]]`` blocks), with its evaluations'
    count."""
    df = _ensure(df)
    res = _limit_rows(df, "limit")
    cols = ["machine_id", "scenario", "variant", "engine", "limit_param", "limit_outcome", "limit_value",
            "limit_lo", "limit_hi", "limit_direction", "limit_failed_check", "limit_runs", "limit_cpu_s",
            "limit_id", "limit_range_lo", "limit_range_hi", "limit_phases", "limit_overrides", "suite", "sweep_id"]
    if res.empty:
        return pd.DataFrame(columns=cols)
    res = res.copy()
    for c in cols:
        if c not in res.columns:
            res[c] = None
    res = res.sort_values(["sweep_id", "timestamp"], kind="stable")
    res = res.drop_duplicates(["machine_id", "limit_id"], keep="last")
    return res[cols].sort_values(["scenario", "variant", "limit_param", "engine"], kind="stable").reset_index(drop=True)


def fmt_limit(r: Mapping[str, Any], short: bool = False) -> str:
    """A breaking point as text: ``<= 0.0072 [0.0072, 0.0076]``, ``holds to
    HI``, ``fails at LO``, ``unsupported``."""
    out = r.get("limit_outcome")
    if out == "found":
        sign = "\u2264" if r.get("limit_direction") == "below" else "\u2265"
        txt = f"{sign} {fmt(r['limit_value'])}"
        return txt if short else f"{txt} [{fmt(r['limit_lo'])}, {fmt(r['limit_hi'])}]"
    if out == "holds_throughout":
        return f"holds to {fmt(r['limit_value'])}" if short else \
            f"holds over [{fmt(r['limit_range_lo'])}, {fmt(r['limit_range_hi'])}]"
    if out == "fails_throughout":
        return f"fails at {fmt(r['limit_range_lo'])}" if short else \
            f"fails at both ends [{fmt(r['limit_range_lo'])}, {fmt(r['limit_range_hi'])}]"
    return str(out or "?")


def at_a_glance(df: pd.DataFrame, rungs: Iterable[float] = LADDER) -> pd.DataFrame:
    """Per scenario family and ladder rung: which engine is cheapest to
    reach the rung, counted over the family's scenarios (``wins``: engine ->
    scenarios where it is cheapest), how many scenarios some engine reached
    it in, out of how many."""
    lad = ladder(df, rungs)
    rows = []
    if lad.empty:
        return pd.DataFrame(columns=["family", "rung", "wins", "reached", "scenarios"])
    lad = lad.assign(family=[family(x) for x in lad["scenario"]])
    for (fam, rung), g in lad.groupby(["family", "rung"], sort=True):
        wins: dict[str, int] = {}
        reached = 0
        scen = 0
        for _, h in g.groupby(["scenario", "variant"], sort=True):
            scen += 1
            r = h[h["reached"].astype(bool) & h["cost"].map(_finite)]
            if len(r):
                reached += 1
                best = r.sort_values(["cost", "engine"], kind="stable").iloc[0]["engine"]
                wins[best] = wins.get(best, 0) + 1
        rows.append({"family": fam, "rung": rung, "wins": dict(sorted(wins.items(), key=lambda kv: -kv[1])),
                     "reached": reached, "scenarios": scen})
    return pd.DataFrame(rows).sort_values(["family", "rung"], ascending=[True, False]).reset_index(drop=True)


# ---------------------------------------------------------------------------
# stability


def stability_matrix(df: pd.DataFrame, scenarios: Iterable[str] | None = None) -> pd.DataFrame:
    """Per (scenario, variant, engine) over the latest sweep points and the
    latest conformance rows: points, ok-and-stable count and fraction,
    unstable (ok but not stable), diverged, error (error/failed/timeout),
    unsupported, the largest dt at which the engine was ok and stable and the
    smallest dt at which it was not.

    ``scenarios``: which scenarios to show; default the ones tagged 'hard'
    in scenarios/*.toml that have data, else all.  ``df.attrs['selection']``
    says which.
    """
    df = _ensure(df)
    cols = ["scenario", "variant", "engine", "points", "ok_stable", "fraction", "unstable", "diverged",
            "error", "unsupported", "other", "max_stable_dt", "min_unstable_dt", "met_checks", "checks_failed",
            "max_met_dt"]
    parts = [p for p in (_unshifted(latest_points(df)), _latest_checks(df)) if not p.empty]
    if not parts:
        out = pd.DataFrame(columns=cols)
        out.attrs["selection"] = "no data"
        return out
    data = pd.concat(parts, ignore_index=True, sort=False)
    if scenarios is None:
        hard = hard_scenarios() & set(data["scenario"])
        if hard:
            data = data[data["scenario"].isin(hard)]
            selection = "scenarios tagged 'hard'"
        else:
            selection = "all scenarios (none tagged 'hard' has data)"
    else:
        keep = set(scenarios)
        data = data[data["scenario"].isin(keep)]
        selection = "selected scenarios"
    rows = []
    for (sc, va, en), g in data.groupby(["scenario", "variant", "engine"], sort=True):
        recs = g.to_dict("records")
        good = [r for r in recs if _good(r)]
        bad = [r for r in recs if not _good(r) and r["status"] != "unsupported"]
        st = [r["status"] for r in recs]
        gdt = [r["dt"] for r in good if math.isfinite(r["dt"])]
        bdt = [r["dt"] for r in bad if math.isfinite(r["dt"])]
        n = len(recs)
        rows.append({
            "scenario": sc, "variant": va, "engine": en, "points": n, "ok_stable": len(good),
            "fraction": len(good) / n if n else math.nan,
            "unstable": sum(1 for r in recs if r["status"] == "ok" and r.get("stable_flag") is False),
            "diverged": st.count("diverged"),
            "error": sum(st.count(s) for s in BROKEN_STATUSES),
            "unsupported": st.count("unsupported"),
            "other": sum(1 for s in st if s not in (OK, DIVERGED, UNSUPPORTED) + BROKEN_STATUSES),
            "max_stable_dt": max(gdt) if gdt else math.nan,
            "min_unstable_dt": min(bdt) if bdt else math.nan,
            "met_checks": sum(1 for r in good if meets_checks(r) is True),
            "checks_failed": sorted({m for r in good for m in (failed_checks(r) or [])}),
            "max_met_dt": max((r["dt"] for r in good if meets_checks(r) is True and math.isfinite(r["dt"])),
                              default=math.nan),
        })
    out = pd.DataFrame(rows, columns=cols)
    out.attrs["selection"] = selection
    return out


def failed_checks(r: Mapping[str, Any]) -> list[str] | None:
    """The metrics of the row's checks (those that apply to its engine,
    without an @-setting) that it did not meet -- an ``xfail`` does not make
    a check met.  The outcomes the row carries (its ``checks`` column) when
    it has them, else the scene's checks evaluated on the row's values (a
    missing value fails); None when neither is known (the scene no longer
    loads)."""
    from harness.conformance import ERROR, FAIL, UNSUPPORTED, XFAIL, applicable_checks, meets, split_metric

    stored = _row_checks(r)
    if stored is not None:
        return sorted({str(o.get("metric")) for o in stored if o.get("outcome") in (FAIL, XFAIL, ERROR, UNSUPPORTED)})
    sc = _scene(r["scenario"], r["variant"], r.get("scene_path", ""))
    if sc is None:
        return None
    out = []
    for c in applicable_checks(sc, r["engine"]):
        name, bound = split_metric(c.metric)
        if bound:
            continue
        v = r.get(name)
        if _missing(v) or not meets(c, v):
            out.append(name)
    return out


def meets_checks(r: Mapping[str, Any]) -> bool | None:
    """Whether an ok row met every one of its checks (None: not known)."""
    failed = failed_checks(r)
    if failed is None:
        return None
    return r["status"] == "ok" and not failed


# ---------------------------------------------------------------------------
# step phases


def _primary_checks(scenario: str, variant: str, engine: str, metric: str | None, path: str = "") -> list:
    """The scene's checks of its primary metric that apply to ``engine``
    (xfail or not: an expected failure is still a failure here), for rows
    that do not carry their checks' outcomes."""
    from harness.conformance import check_applies

    sc = _scene(scenario, variant, path)
    if sc is None or not metric:
        return []
    return [c for c in sc.checks if c.metric == metric and check_applies(c, engine, variant or None)]


def _row_checks(r: Mapping[str, Any]) -> list[dict] | None:
    """The outcomes stored in a row's ``checks`` column, None without one."""
    v = r.get("checks")
    if _missing(v):
        return None
    try:
        out = json.loads(v) if isinstance(v, str) else list(v)
    except (TypeError, ValueError):
        return None
    return out if isinstance(out, list) else None


def _phase_outcome(r: Mapping[str, Any], checks: list) -> str:
    """'.' passed, 'x' a primary check failed, '!' the run was not ok or not
    stable, '-' unsupported.  The row's own outcomes of its primary metric's
    checks when it carries them, else ``checks`` evaluated here."""
    from harness.conformance import ERROR, FAIL, XFAIL, meets

    if r["status"] == "unsupported":
        return "-"
    if not _good(r):
        return "!"
    m = r.get("primary_metric")
    stored = _row_checks(r)
    if stored is not None:
        return "x" if any(o.get("metric") == m and o.get("outcome") in (FAIL, XFAIL, ERROR) for o in stored) else "."
    v = r.get(m) if m else None
    for c in checks:
        if v is None or (isinstance(v, float) and math.isnan(v)) or not meets(c, v):
            return "x"
    return "."


def phase_table(df: pd.DataFrame) -> pd.DataFrame:
    """Points swept over step phases (a ``[[sweep]]`` with ``phases = N``):
    per configuration (machine, suite, scenario, variant, engine, settings
    without the phase), the N phases' outcomes -- failed = not ok, not
    stable, or the scenario's check of its primary metric not met -- as a
    failure fraction k / N with its 95 % Wilson interval, and the pattern
    over the phases in order (``.`` pass, ``x`` check failed, ``!`` not ok
    or unstable).  ``phase0`` is the outcome of the scene as written: what a
    single run (``physbench check``, a sweep without phases) sees."""
    from contract.phase import wilson_interval

    df = _ensure(df)
    cols = ["machine_id", "suite", "scenario", "variant", "engine", "settings", "dt", "phases", "failures",
            "fraction", "lo", "hi", "pattern", "phase0"]
    pts = latest_points(df)
    if pts.empty or not (pts["phase"] > 0).any():
        return pd.DataFrame(columns=cols)
    pts = pts.copy()
    pts["_base"] = [settings_label({k: v for k, v in (d or {}).items() if k not in ("phase", "dt")})
                    for d in pts["swept"]]
    rows = []
    pts["_dtkey"] = [fmt(d, 9) for d in pts["dt"]]
    for key, g in pts.groupby(["machine_id", "suite", "scenario", "variant", "engine", "_base", "_dtkey"],
                              sort=True):
        if not (g["phase"] > 0).any():
            continue
        # the phases of the latest sweep that ran them: a phase that sweep no
        # longer runs keeps an older row in latest_points, which must not mix in
        latest = max(g.loc[g["phase"] > 0, "sweep_id"])
        g = g[g["sweep_id"] == latest]
        mid, suite, sc, va, en, base, _ = key
        recs = sorted(g.to_dict("records"), key=lambda r: r["phase"])
        checks = ([] if all(_row_checks(r) is not None for r in recs) else
                  _primary_checks(sc, va, en, recs[0].get("primary_metric"), recs[0].get("scene_path") or ""))
        pattern = "".join(_phase_outcome(r, checks) for r in recs)
        n = sum(1 for ch in pattern if ch != "-")
        k = sum(1 for ch in pattern if ch in "x!")
        lo, hi = wilson_interval(k, n) if n else (math.nan, math.nan)
        rows.append({"machine_id": mid, "suite": suite, "scenario": sc, "variant": va, "engine": en,
                     "settings": base, "dt": recs[0]["dt"], "phases": len(recs), "failures": k,
                     "fraction": k / n if n else math.nan, "lo": lo, "hi": hi, "pattern": pattern,
                     "phase0": pattern[0] if recs[0]["phase"] == 0.0 else ""})
    out = pd.DataFrame(rows, columns=cols)
    return out.sort_values(["scenario", "variant", "engine", "settings", "dt"], ascending=[True, True, True, True, False],
                           kind="stable").reset_index(drop=True)


# ---------------------------------------------------------------------------
# history and regressions


def _spread(median: float, mn: float) -> float:
    """Relative spread of a run's repeats: (median - min) / median; 0 when
    unknown (one repeat, or no min recorded)."""
    if not (math.isfinite(median) and math.isfinite(mn)) or median <= 0:
        return 0.0
    return max(0.0, (median - mn) / median)


def _cost_baseline(window: list[dict]) -> tuple[float, float, float]:
    """(baseline, scatter, spread) of a series' baseline runs (ok, cost > 0):
    the median cost; the median absolute deviation of the costs from it,
    relative to it (0 for one run); the median of the runs' relative
    spreads of repeats (``_spread``)."""
    costs = [r["cost"] for r in window]
    baseline = float(np.median(costs))
    scatter = float(np.median([abs(c - baseline) for c in costs])) / baseline
    spread = float(np.median([_spread(r["cost"], r["cost_min"]) for r in window]))
    return baseline, scatter, spread


def _cost_drift(runs: list[dict], last: dict) -> dict | None:
    """A slow creep of cost that the recent-baseline rule absorbs: the
    latest run against the cheapest plateau of the horizon ``runs`` (the
    lowest median of ``BASELINE_RUNS`` consecutive ok runs), flagged when

    - it exceeds max(10 %, 3 x the repeats' spread (latest, plateau),
      3 x sigma), sigma the night-to-night noise estimated from successive
      differences of log cost over the horizon (1.4826 MAD / sqrt 2, which
      a trend hardly moves, unlike the spread around a window's median), and
    - the rise did not come in one jump: no single night-to-night step from
      the plateau's end to the latest run makes up half of it (a step is the
      recent rule's business: flagged while it is new, then accepted).

    Returns the row fields (kind ``cost_drift``) or None."""
    if len(runs) < BASELINE_RUNS + 1:
        return None
    logc = np.log([r["cost"] for r in runs] + [last["cost"]])
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(np.diff(logc)))) / math.sqrt(2.0)
    k = BASELINE_RUNS
    meds = [float(np.median([r["cost"] for r in runs[i:i + k]])) for i in range(len(runs) - k + 1)]
    i = int(np.argmin(meds))
    plateau = runs[i:i + k]
    base_cost = meds[i]
    spread = float(np.median([_spread(r["cost"], r["cost_min"]) for r in plateau]))
    thr = max(NOISE_FLOOR, NOISE_SPREADS * max(_spread(last["cost"], last["cost_min"]), spread),
              NOISE_SPREADS * sigma)
    change = last["cost"] / base_cost - 1.0
    if change <= thr:
        return None
    rise = math.log(last["cost"] / base_cost)
    steps = np.diff(logc[i + k - 1:])
    if steps.size and float(steps.max()) >= 0.5 * rise:
        return None
    return {"kind": "cost_drift", "direction": "regression", "previous": base_cost, "latest": last["cost"],
            "change": change, "threshold": thr,
            "previous_sweep": f"{plateau[0]['sweep_id']}..{plateau[-1]['sweep_id']}", "severity": change / thr}


def _series(df: pd.DataFrame):
    """(machine_id, suite, series_key) -> that point's sweep rows over time
    (one per sweep, the last if repeated; ascending sweep_id), whatever the
    scene's content."""
    s = _sweeps(_ensure(df))
    if s.empty:
        return
    s = s.sort_values(["sweep_id", "timestamp"], kind="stable")
    s = s.drop_duplicates(["machine_id", "suite", "point_key", "sweep_id"], keep="last")
    yield from s.groupby(["machine_id", "suite", "series_key"], sort=True)


def _same_scene(g: pd.DataFrame) -> pd.DataFrame:
    """The trailing rows of a series with the latest row's scene hash: the
    only ones its latest run may be compared with.  Rows without a hash
    (written before rows carried one) count as a different, unknown scene
    -- unless no row of the series has one."""
    h = list(g["scene_hash"])
    i = len(h) - 1
    while i > 0 and h[i - 1] == h[-1]:
        i -= 1
    return g.iloc[i:]


def history(df: pd.DataFrame) -> dict[tuple[str, str, str], pd.DataFrame]:
    """(machine_id, suite, series key) -> that point's rows over its sweeps
    (one per sweep, the last if repeated; ascending sweep_id), for points
    present in at least two sweeps of the same suite on the same machine
    *with the same scene content* (``scene_hash``): a changed scene starts
    a new series (:func:`scene_changes` lists where), it is never compared
    with the old one.  The series key is the point key without the scene
    hash."""
    out: dict[tuple[str, str, str], pd.DataFrame] = {}
    for key, g in _series(df):
        g = _same_scene(g)
        if g["sweep_id"].nunique() >= 2:
            out[key] = g.reset_index(drop=True)
    return out


def scene_changes(df: pd.DataFrame) -> pd.DataFrame:
    """Where a series was cut because its scene changed: per machine,
    suite, scenario, variant and the sweep that first ran the new content,
    the date (of that sweep's rows), the number of points and engines, and
    the previous and new hashes ('' for rows written before rows carried
    one).  Only the latest cut of each series (the earlier rows are not
    compared with anything any more)."""
    cols = ["machine_id", "suite", "scenario", "variant", "sweep_id", "date", "points", "engines",
            "previous_hash", "scene_hash"]
    rows = []
    for (mid, suite, _sk), g in _series(df):
        new = _same_scene(g)
        if len(new) == len(g):
            continue
        first, before = new.iloc[0], g.iloc[len(g) - len(new) - 1]
        rows.append({"machine_id": mid, "suite": suite, "scenario": first["scenario"], "variant": first["variant"],
                     "sweep_id": first["sweep_id"], "date": str(first["timestamp"])[:10] or first["sweep_id"][:8],
                     "engine": first["engine"], "previous_hash": before["scene_hash"],
                     "scene_hash": first["scene_hash"]})
    if not rows:
        return pd.DataFrame(columns=cols)
    d = pd.DataFrame(rows)
    out = []
    for key, g in d.groupby(["machine_id", "suite", "scenario", "variant", "sweep_id", "date",
                             "previous_hash", "scene_hash"], sort=True):
        out.append(dict(zip(["machine_id", "suite", "scenario", "variant", "sweep_id", "date", "previous_hash",
                             "scene_hash"], key), points=len(g), engines=", ".join(sorted(set(g["engine"])))))
    return pd.DataFrame(out, columns=cols)


def scene_change_lines(changes: pd.DataFrame) -> list[str]:
    """One sentence per :func:`scene_changes` row."""
    out = []
    for r in changes.to_dict("records"):
        what = r["scenario"] + (f" [{r['variant']}]" if r["variant"] else "")
        was = (f"content {r['previous_hash']} -> {r['scene_hash']}" if r["previous_hash"]
               else f"content {r['scene_hash']}; earlier rows carry no scene hash")
        out.append(f"{what}: scene changed on {r['date']} (sweep {r['sweep_id']}, {r['machine_id']} / {r['suite']}): "
                   f"new series for {r['points']} point(s) on {r['engines']}, not compared with earlier sweeps "
                   f"({was})")
    return out


def machine_shifts(df: pd.DataFrame, hist: dict | None = None) -> dict[tuple[str, str, str], float]:
    """(machine_id, suite, sweep_id) -> the night's machine-wide cost
    factor: the median, over the series judged that night (ok, with
    ``MIN_COST_HISTORY`` earlier ok runs), of latest cost / their baseline
    (the median of their last ``BASELINE_RUNS`` earlier ok runs).  Only
    nights with at least ``MACHINE_SHIFT_MIN_SERIES`` such series get one.
    Measured: on a night when this VM ran 5-8 % slower for every engine
    alike (MuJoCo, pybullet and pymunk unchanged), 277 of 894 points
    exceeded the 10 % floor; a code change moves some series, a slower
    machine moves all of them."""
    df = _ensure(df)
    hist = history(df) if hist is None else hist
    logs: dict[tuple[str, str, str], list[float]] = {}
    for (mid, suite, _pk), g in hist.items():
        recs = g.to_dict("records")
        last = recs[-1]
        if last["status"] != "ok" or not (math.isfinite(last["cost"]) and last["cost"] > 0):
            continue
        costs = [r for r in recs[:-1] if r["status"] == "ok" and math.isfinite(r["cost"]) and r["cost"] > 0]
        if len(costs) < MIN_COST_HISTORY:
            continue
        base = float(np.median([r["cost"] for r in costs[-BASELINE_RUNS:]]))
        logs.setdefault((mid, suite, last["sweep_id"]), []).append(math.log(last["cost"] / base))
    return {k: math.exp(float(np.median(v))) for k, v in logs.items() if len(v) >= MACHINE_SHIFT_MIN_SERIES}


def pooled_noise(df: pd.DataFrame, hist: dict | None = None) -> dict[tuple[str, str, str], float]:
    """(machine_id, suite, engine) -> the relative night-to-night noise of
    that engine's costs on that machine, pooled over all its series:
    1.4826 x the median |log(c_k / c_k-1)| over consecutive earlier ok runs
    (the latest excluded) / sqrt 2.  One series' few nights say little
    about its scatter; the engine's hundreds of series say much (measured on
    this VM over three nights: 3.7 % MuJoCo, 5.0 % pybullet, 5.7 % pymunk,
    2.8 % reference).  Needs ``MACHINE_SHIFT_MIN_SERIES`` differences."""
    df = _ensure(df)
    hist = history(df) if hist is None else hist
    diffs: dict[tuple[str, str, str], list[float]] = {}
    for (mid, suite, _pk), g in hist.items():
        recs = g.to_dict("records")
        c = [r["cost"] for r in recs[:-1] if r["status"] == "ok" and math.isfinite(r["cost"]) and r["cost"] > 0]
        if len(c) >= 2:
            diffs.setdefault((mid, suite, recs[-1]["engine"]), []).extend(np.abs(np.diff(np.log(c))).tolist())
    return {k: MAD_TO_SIGMA * float(np.median(v)) / math.sqrt(2.0) for k, v in diffs.items()
            if len(v) >= MACHINE_SHIFT_MIN_SERIES}


def regressions(df: pd.DataFrame, hist: dict | None = None) -> pd.DataFrame:
    """Flagged changes of each point's latest sweep against its earlier ones
    (same machine, same suite, same scene content: :func:`history`).  Only
    beyond noise:

    - cost (``cpu_s_per_sim_s_median``), asv style: the latest ok run
      against a baseline, the median cost of the last ``BASELINE_RUNS`` (5)
      earlier ok runs of the series (fewer if there are fewer), judged only
      once the series has ``MIN_COST_HISTORY`` (3) earlier ok runs, so that
      the night-to-night noise is estimated.  Flagged when the relative change latest / baseline - 1
      exceeds max(10 %, 3 x s, 3 x 1.4826 x MAD / baseline): ``s`` the
      larger of the latest run's relative spread of repeats, (median - min)
      / median, and the median of that spread over the baseline runs; MAD
      the median absolute deviation of the baseline runs' costs from the
      baseline, so night-to-night scatter counts as noise.  Faster by as
      much is an improvement.  Not the best earlier run: the minimum of
      many noisy nights is optimistic, so that rule's false alarms grew
      with the length of the history.  A step change becomes the new
      baseline once it is the majority of the window (3 nights of 5).
      A steady creep moves that baseline with it, so it is left to:
    - cost drift (kind ``cost_drift``), when the cost rule flags nothing:
      the latest run against the cheapest plateau of the last
      ``DRIFT_HORIZON`` (30) earlier ok runs (lowest median of 5
      consecutive runs), beyond max(10 %, 3 x spreads, 3 x the nightly
      noise from successive differences), and only if the rise came over
      several nights, not in one jump (see :func:`_cost_drift`).  Flagged
      every night until the cost comes back or the plateau leaves the
      horizon.
    - accuracy (primary error): the latest ok run against the best earlier
      ok run; flagged when it grows by more than 10 % and by more than 1e-12
      absolutely (shrinks by as much: an improvement).  Errors are
      deterministic for an engine version and its settings, so the best
      earlier night is not a noisy minimum, and comparing with it keeps a
      real accuracy regression flagged every night until it is fixed
      instead of letting it become the new normal.
    - status: ok in the previous sweep and anything else in the latest is a
      regression (the reverse an improvement).

    Columns: kind (cost / cost_drift / accuracy / status), direction (regression /
    improvement), machine_id, suite, scenario, variant, engine, settings,
    point_key (the series key: the point key without the scene hash), previous (cost: the baseline median; cost_drift: the
    plateau's median; accuracy: the best
    earlier error; status: the previous status), latest, change (relative;
    for status NaN), threshold, previous_sweep (cost: the baseline window
    as ``first..last`` sweep id, or the one id when the window is one run;
    otherwise the sweep compared with), latest_sweep, severity (for
    ordering).
    """
    df = _ensure(df)
    cols = ["kind", "direction", "machine_id", "suite", "scenario", "variant", "engine", "settings",
            "point_key", "previous", "latest", "change", "threshold", "previous_sweep", "latest_sweep",
            "severity"]
    hist = history(df) if hist is None else hist
    shifts = machine_shifts(df, hist)
    pooled = pooled_noise(df, hist)
    rows = []
    for (mid, suite, pk), g in hist.items():
        recs = g.to_dict("records")
        last, prev = recs[-1], recs[-2]
        # the night's machine-wide cost factor (1 when unknown): taken out of
        # every series' change, so that a slower machine is not a regression
        factor = shifts.get((mid, suite, last["sweep_id"]), 1.0)
        earlier = recs[:-1]
        base = {"machine_id": mid, "suite": suite, "scenario": last["scenario"], "variant": last["variant"],
                "engine": last["engine"], "settings": settings_label(last["swept"] or {}), "point_key": pk,
                "latest_sweep": last["sweep_id"]}
        if prev["status"] == "ok" and last["status"] != "ok":
            rows.append({**base, "kind": "status", "direction": "regression", "previous": "ok",
                         "latest": last["status"], "change": math.nan, "threshold": math.nan,
                         "previous_sweep": prev["sweep_id"], "severity": math.inf})
            continue
        if prev["status"] != "ok" and last["status"] == "ok":
            rows.append({**base, "kind": "status", "direction": "improvement", "previous": prev["status"],
                         "latest": "ok", "change": math.nan, "threshold": math.nan,
                         "previous_sweep": prev["sweep_id"], "severity": math.inf})
        if last["status"] != "ok":
            continue
        ok_before = [r for r in earlier if r["status"] == "ok"]
        # cost
        costs = [r for r in ok_before if math.isfinite(r["cost"]) and r["cost"] > 0]
        # the night-to-night noise must be estimated before a change can be
        # called beyond it: with fewer earlier runs a cost is not judged (on
        # the second night of the nightly suite, 86 points moved by 10-60 %
        # against a single earlier night, sub-millisecond runs of one repeat
        # and interleaved runs of three alike)
        if len(costs) >= MIN_COST_HISTORY and math.isfinite(last["cost"]) and last["cost"] > 0:
            window = costs[-BASELINE_RUNS:]  # recs ascend by sweep_id: the latest earlier ok runs
            baseline, scatter, spread = _cost_baseline(window)
            # the engine's pooled night-to-night noise on this machine, for the
            # difference of one night from a median of up to 5
            sig = pooled.get((mid, suite, last["engine"]), 0.0) * math.sqrt(1.0 + 1.0 / len(window))
            thr = max(NOISE_FLOOR, NOISE_SPREADS * max(_spread(last["cost"], last["cost_min"]), spread),
                      NOISE_SPREADS * MAD_TO_SIGMA * scatter, math.expm1(NOISE_SPREADS * sig))
            change = last["cost"] / (baseline * factor) - 1.0
            direction = ("regression" if change > thr else
                         "improvement" if -change > thr else None)
            if direction:
                first, final = window[0]["sweep_id"], window[-1]["sweep_id"]
                rows.append({**base, "kind": "cost", "direction": direction, "previous": baseline,
                             "latest": last["cost"], "change": change, "threshold": thr,
                             "previous_sweep": final if len(window) == 1 else f"{first}..{final}",
                             "severity": abs(change) / thr})
            else:
                drift = _cost_drift(costs[-DRIFT_HORIZON:], {**last, "cost": last["cost"] / factor,
                                                              "cost_min": last["cost_min"] / factor})
                if drift is not None:
                    rows.append({**base, **drift})
        # accuracy
        errs = [r for r in ok_before if math.isfinite(r["primary_error"])]
        le = last["primary_error"]
        if errs and math.isfinite(le):
            best = min(errs, key=lambda r: r["primary_error"])
            be = best["primary_error"]
            direction = None
            if le > be * (1 + NOISE_FLOOR) and le - be > ERROR_ABS_FLOOR:
                direction = "regression"
            elif be > le * (1 + NOISE_FLOOR) and be - le > ERROR_ABS_FLOOR:
                direction = "improvement"
            if direction:
                change = (le / be - 1.0) if be > 0 else math.inf
                sev = abs(math.log10(max(le, ERROR_FLOOR) / max(be, ERROR_FLOOR))) / math.log10(1 + NOISE_FLOOR)
                rows.append({**base, "kind": "accuracy", "direction": direction, "previous": be, "latest": le,
                             "change": change, "threshold": NOISE_FLOOR, "previous_sweep": best["sweep_id"],
                             "severity": sev})
    out = pd.DataFrame(rows, columns=cols)
    if out.empty:
        return out
    out["_r"] = (out["direction"] != "regression").astype(int)
    return out.sort_values(["_r", "severity"], ascending=[True, False], kind="stable").drop(columns="_r") \
              .reset_index(drop=True)


# ---------------------------------------------------------------------------
# plotting


def _figure(w: float, h: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(w, h), dpi=90, layout="constrained")


def _png(fig) -> str:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _mpl_text(s: str) -> str:
    return s.replace("$", r"\$")


#: one colour per engine in every plot (colour-blind-safe Okabe-Ito hues)
ENGINE_COLOURS = {"reference": "#0072B2", "mujoco": "#D55E00", "pybullet": "#009E73", "pymunk": "#CC79A7"}
_SPARE_COLOURS = ("#E69F00", "#56B4E9", "#F0E442", "#000000")
MARKERS = "osD^v<>P"
MAX_LEGEND = 8  # legend entries per plot, at most


def engine_colour(engine: str) -> str:
    """The engine's colour, the same in every plot."""
    if engine in ENGINE_COLOURS:
        return ENGINE_COLOURS[engine]
    return _SPARE_COLOURS[sum(engine.encode()) % len(_SPARE_COLOURS)]


def frontier(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The Pareto frontier of (cost, error) points: ascending cost, each
    point strictly more accurate than every cheaper one."""
    out: list[tuple[float, float]] = []
    for c, e in sorted(points):
        if not out or e < out[-1][1]:
            out.append((c, e))
    return out


def plot_work_precision(wp: Mapping[str, Any]) -> str | None:
    """One work-precision figure as base64 PNG (None if no point is
    drawable): left, every engine's points in its colour with its frontier
    (the cheapest way to each accuracy) as a line -- a legend of engines only;
    right, one small panel per engine with its settings as markers (at most
    MAX_LEGEND entries; further ones grey, counted in the panel's title).  No
    per-point labels: dt is along each line (smallest dt most expensive)."""
    ok = [p for l in wp["lines"] for p in l["points"] if p["ok"] and p["cost"] > 0]
    fails = [p for l in wp["lines"] for p in l["points"] if not p["ok"] and math.isfinite(p["cost"]) and p["cost"] > 0]
    if not ok and not fails:
        return None
    engines = sorted({l["engine"] for l in wp["lines"]})
    ncol = 2
    nrow = max(1, math.ceil(len(engines) / ncol))
    fig = _figure(11.5, max(4.2, 2.3 * nrow))
    grid = fig.add_gridspec(nrow, 1 + ncol, width_ratios=[1.5] + [1] * ncol)
    ax = fig.add_subplot(grid[:, 0])
    ys = [p["error_plot"] for p in ok]
    if wp["threshold"] is not None and wp["threshold"] > 0:
        ys.append(wp["threshold"])
    lo, hi = (min(ys), max(ys)) if ys else (1e-6, 1.0)
    top = hi * 10.0  # headroom for the not-ok markers along the top edge
    xs_all = [p["cost"] for p in ok + fails]
    xlim = (min(xs_all) / 1.6, max(xs_all) * 1.6)
    for en in engines:
        pts = [(p["cost"], p["error_plot"]) for l in wp["lines"] if l["engine"] == en
               for p in l["points"] if p["ok"] and p["cost"] > 0]
        if not pts:
            continue
        col = engine_colour(en)
        ax.scatter([c for c, _ in pts], [e for _, e in pts], s=14, color=col, alpha=0.45, lw=0)
        fr = frontier(pts)
        ax.plot([c for c, _ in fr], [e for _, e in fr], "-o", color=col, lw=2, ms=4, label=_mpl_text(en))
    if wp["threshold"] is not None and wp["threshold"] > 0:
        ax.axhline(wp["threshold"], color="k", ls="--", lw=1,
                   label=f"target {wp['threshold']:g} ({wp['threshold_source']})")
    if fails:
        ax.scatter([p["cost"] for p in fails], [top / 2.0] * len(fails), marker="x", color="red", s=30,
                   label=f"not ok ({len(fails)}, listed below)", zorder=5)
    for a in (ax,):
        a.set_xscale("log")
        a.set_yscale("log")
        a.set_ylim(lo / 3.0, top)
        a.set_xlim(*xlim)
        a.grid(True, which="major", alpha=0.3)
    ax.set_xlabel("CPU s per simulated s")
    ax.set_ylabel(_mpl_text(wp["primary_metric"] or "primary error"))
    title = wp["scenario"] + (f" / {wp['variant']}" if wp["variant"] else "")
    ax.set_title(_mpl_text(title) + ": frontier per engine", fontsize=10)
    ax.legend(fontsize=8, loc="lower left", framealpha=0.85)
    for i, en in enumerate(engines):
        sub = fig.add_subplot(grid[i // ncol, 1 + i % ncol], sharex=ax, sharey=ax)
        lines = [l for l in wp["lines"] if l["engine"] == en]
        col = engine_colour(en)
        extra = 0
        for j, line in enumerate(lines):
            pts = [p for p in line["points"] if p["ok"] and p["cost"] > 0]
            if not pts:
                continue
            lab = settings_label(line["settings"]) or "defaults"
            if j < MAX_LEGEND:
                sub.plot([p["cost"] for p in pts], [p["error_plot"] for p in pts], "-", marker=MARKERS[j],
                         color=col, ms=4, lw=1, mfc="none" if j % 2 else col, label=_mpl_text(lab))
            else:
                extra += 1
                sub.plot([p["cost"] for p in pts], [p["error_plot"] for p in pts], "-", color="0.7", lw=0.8)
        sub.set_title(_mpl_text(en) + (f" (+{extra} grey)" if extra else ""), fontsize=9, color=col)
        sub.tick_params(labelsize=7)
        sub.grid(True, which="major", alpha=0.3)
        if sub.get_legend_handles_labels()[0]:
            sub.legend(fontsize=6.5, loc="lower left", framealpha=0.85, handlelength=1.5)
    return _png(fig)


def plot_breaking_point(evals: pd.DataFrame, limits: pd.DataFrame, param: str, metric: str | None) -> str | None:
    """The criterion along the parameter: per engine (its colour) each
    evaluated value's primary error (phase 0; filled: the value held in every
    phase, x: it did not), the limit as a vertical dashed line.  None when
    nothing is drawable."""
    if evals.empty:
        return None
    fig = _figure(7.5, 3.6)
    ax = fig.add_subplot()
    xs = [float(v) for v in evals["limit_value"] if _finite(v)]
    if not xs:
        return None
    if min(xs) > 0:
        ax.set_xscale("log")
    errs = [e for e in evals["primary_error"] if _finite(e) and e > 0]
    ymax = max(errs) * 10 if errs else 1.0
    ymin = max(min(errs) / 3 if errs else 1e-3, ERROR_FLOOR)
    ax.set_yscale("log")
    for en in sorted(set(evals["engine"])):
        g = evals[evals["engine"] == en].sort_values("limit_value")
        col = engine_colour(en)
        # one mark per value: held (all phases) or not; its phase-0 error
        by = {}
        for r in g.to_dict("records"):
            v = float(r["limit_value"])
            held = bool(r.get("limit_holds")) and by.get(v, (True, None))[0]
            e = r["primary_error"] if r.get("phase", 0.0) == 0.0 else by.get(v, (True, None))[1]
            by[v] = (held, e if e is not None else by.get(v, (True, None))[1])
        vals = sorted(by)
        ys = [max(by[v][1], ERROR_FLOOR) if _finite(by[v][1]) and by[v][1] > 0 else ymax / 2 for v in vals]
        ax.plot(vals, ys, "-", color=col, lw=0.8, alpha=0.6)
        held = [i for i, v in enumerate(vals) if by[v][0]]
        bad = [i for i, v in enumerate(vals) if not by[v][0]]
        ax.scatter([vals[i] for i in held], [ys[i] for i in held], color=col, s=22, marker="o", label=_mpl_text(en))
        ax.scatter([vals[i] for i in bad], [ys[i] for i in bad], color=col, s=30, marker="x")
        lim = limits[limits["engine"] == en]
        if len(lim) and lim.iloc[0]["limit_outcome"] == "found":
            ax.axvline(float(lim.iloc[0]["limit_value"]), color=col, ls="--", lw=1.2)
    ax.set_ylim(ymin, ymax)
    ax.set_xlabel(_mpl_text(param))
    ax.set_ylabel(_mpl_text(metric or "primary error") + " (phase 0)")
    ax.grid(True, which="major", alpha=0.3)
    ax.scatter([], [], color="0.3", marker="x", s=30, label="fails")
    ax.legend(fontsize=8, loc="best", framealpha=0.85)
    return _png(fig)


def plot_history(series: list[tuple[str, pd.DataFrame]]) -> str | None:
    """Small multiples: cost (median, bar down to min) and primary error per
    sweep for a few points."""
    if not series:
        return None
    n = len(series)
    ncol = min(3, n)
    nrow = math.ceil(n / ncol)
    fig = _figure(4.0 * ncol, 2.9 * nrow)
    axes = fig.subplots(nrow, ncol, squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    for ax, (title, g) in zip(axes.flat, series):
        x = np.arange(len(g))
        cost = g["cost"].to_numpy(float)
        cmin = g["cost_min"].to_numpy(float)
        ok = (g["status"] == "ok").to_numpy()
        lo = np.where(np.isfinite(cmin), np.clip(cost - cmin, 0, None), 0)
        c_ok = ok & np.isfinite(cost)
        ax.errorbar(x[c_ok], cost[c_ok], yerr=[lo[c_ok], np.zeros(c_ok.sum())], fmt="o-", color="C0",
                    ms=3, lw=1, capsize=2)
        ax.set_ylabel("CPU s / sim s", color="C0", fontsize=7)
        ax.tick_params(labelsize=6)
        if c_ok.any():
            ax.set_ylim(0, np.nanmax(cost[c_ok]) * 1.25)
        err = g["primary_error"].to_numpy(float)
        e_ok = ok & np.isfinite(err)
        if e_ok.any():
            ax2 = ax.twinx()
            ax2.set_yscale("log")
            ax2.plot(x[e_ok], np.maximum(err[e_ok], ERROR_FLOOR), "s--", color="C1", ms=3, lw=1)
            ax2.set_ylabel("primary error", color="C1", fontsize=7)
            ax2.tick_params(labelsize=6)
        for xi in x[~ok]:
            ax.axvline(xi, color="red", lw=0.8, alpha=0.6)
            ax.text(xi, 0.95, g["status"].iloc[xi], color="red", fontsize=6, transform=ax.get_xaxis_transform(),
                    ha="center")
        ax.set_xticks(x)
        ax.set_xticklabels([str(s)[:16] for s in g["sweep_id"]], rotation=30, ha="right", fontsize=5.5)
        ax.set_title(_mpl_text(title), fontsize=7)
    return _png(fig)


# ---------------------------------------------------------------------------
# HTML

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1200px;
color:#222;padding:0 1em;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:2em}
h3{font-size:1.05em;margin-bottom:.3em}
table{border-collapse:collapse;margin:.5em 0 1em;font-size:.85em}
th,td{border:1px solid #ccc;padding:.25em .5em;text-align:left;vertical-align:top}
th{background:#f0f0f0}td.num{text-align:right;font-variant-numeric:tabular-nums}
.warn{background:#fff4d6;border:1px solid #e0b000;padding:.5em 1em;margin:1em 0}
.note{color:#555;font-size:.85em}.bad{color:#b00020;font-weight:600}.good{color:#087a2a;font-weight:600}
.incomplete{background:#ffe8c2}.wp{display:inline-block;vertical-align:top;margin:0 1em 1.5em 0;max-width:1180px}
.wp img,.hist img{max-width:100%}figcaption{font-size:.8em;color:#444}
.cell{font-size:.8em;white-space:nowrap}footer{margin-top:3em;color:#666;font-size:.8em;border-top:1px solid #ccc}
code{background:#f4f4f4;padding:0 .2em}
"""


def _e(v: Any) -> str:
    return html.escape("" if v is None else str(v), quote=True)


def _img(b64: str, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{b64}">'


def _table(header: list[str], rows: list[list[str]], raw: bool = False, row_class: list[str] | None = None) -> str:
    """rows' cells are escaped unless ``raw`` (then they are HTML already)."""
    h = "".join(f"<th>{_e(c)}</th>" for c in header)
    body = []
    for i, r in enumerate(rows):
        cls = f' class="{row_class[i]}"' if row_class and row_class[i] else ""
        cells = "".join(f"<td>{c if raw else _e(c)}</td>" for c in r)
        body.append(f"<tr{cls}>{cells}</tr>")
    return f"<table><thead><tr>{h}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _date(ts: Iterable[str]) -> str:
    ts = sorted(t for t in ts if t)
    if not ts:
        return "-"
    return ts[0] if ts[0] == ts[-1] else f"{ts[0]} .. {ts[-1]}"


def _header_html(df: pd.DataFrame) -> str:
    out = []
    machines = []
    for mid, g in df.groupby("machine_id", sort=True):
        last = g.iloc[-1]
        info = ", ".join(f"{k}: {last[c]}" for k, c in (("cpu", "machine.cpu"),
                                                         ("family/model", "machine.cpu_family_model"),
                                                         ("flags", "machine.cpu_flags"), ("cores", "machine.cores"),
                                                         ("BLAS", "machine.blas"), ("numpy", "machine.numpy"),
                                                         ("scipy", "machine.scipy"), ("env", "machine.env_id"),
                                                         ("platform", "machine.platform"),
                                                         ("python", "machine.python"))
                         if c in g.columns and not _missing(last[c]))
        machines.append([mid, info, str(len(g))])
    out.append("<h3>Machines</h3>" + _table(["machine", "info", "rows"], machines))
    sweeps = []
    classes = []
    s = _sweeps(df)
    if not s.empty:
        for (mid, suite, sid), g in s.groupby(["machine_id", "suite", "sweep_id"], sort=True):
            counts = g["status"].value_counts()
            inc = bool(g["incomplete"].any())
            sweeps.append([mid, suite, sid, _date(g["timestamp"]),
                           ", ".join(sorted({c for c in g["commit"] if c})) or "-", str(len(g)),
                           ", ".join(f"{k} {v}" for k, v in counts.items()),
                           "incomplete (parts only)" if inc else "complete"])
            classes.append("incomplete" if inc else "")
        out.append("<h3>Sweeps</h3>" + _table(["machine", "suite", "sweep id", "dates", "commits", "rows",
                                               "statuses", "state"], sweeps, row_class=classes))
    c = df[df["source"] == "check"]
    if not c.empty:
        checks = []
        for (mid, f), g in c.groupby(["machine_id", "_file"], sort=True):
            checks.append([mid, Path(f).name, _date(g["timestamp"]),
                           ", ".join(sorted({x for x in g["commit"] if x})) or "-", str(len(g))])
        out.append("<h3>Conformance runs (physbench check)</h3>"
                   + _table(["machine", "file", "dates", "commits", "rows"], checks))
    ev = []
    for en, g in df.groupby("engine", sort=True):
        ev.append([en, ", ".join(sorted({v for v in g["engine_version"] if v})) or "-"])
    out.append("<h3>Engines</h3>" + _table(["engine", "versions"], ev))
    commits = sorted({x for x in df["commit"] if x})
    suites = sorted({x for x in s["suite"] if x}) if not s.empty else []
    out.insert(0, f'<p>Suites: <b>{_e(", ".join(suites) or "-")}</b>. Commits covered: '
                  f'{_e(", ".join(commits) or "-")}. Rows: {len(df)} ({len(s)} from sweeps, {len(c)} from '
                  f"conformance runs). Dates: {_e(_date(df['timestamp']))}.</p>")
    return "\n".join(out)


def _wp_html(wps: dict[tuple[str, str], dict[str, Any]]) -> str:
    if not wps:
        return '<p class="note">No sweep rows: nothing to draw.</p>'
    parts = ['<p class="note">x: CPU seconds per simulated second (log); y: the scenario\'s primary error '
             "(log); one line per engine and non-dt setting combination, points along dt (labelled). Latest "
             "sweep of each point on each machine. Dashed: the target (the scenario's <code>[[check]] max</code> "
             "for its primary metric, else <code>--target</code>). Red x on the top edge: runs that were not ok "
             "(diverged, error, unstable ...), placed at their cost.</p>"]
    for (sc, va), wp in wps.items():
        b64 = plot_work_precision(wp)
        title = sc + (f" / {va}" if va else "")
        cap = [f"<b>{_e(title)}</b>: primary metric <code>{_e(wp['primary_metric'] or '?')}</code>"]
        if wp["threshold"] is not None:
            cap.append(f"target {_e(fmt(wp['threshold']))} ({_e(wp['threshold_source'])})")
        else:
            cap.append("no target (no check max; pass --target)")
        if wp["clipped"]:
            cap.append(f"errors below {ERROR_FLOOR:g} (exact results, error 0) are drawn at {ERROR_FLOOR:g}")
        if any(p["incomplete"] for l in wp["lines"] for p in l["points"]):
            cap.append("includes points of an incomplete sweep")
        body = _img(b64, f"work-precision {title}") if b64 else '<p class="note">no drawable point</p>'
        lst = ""
        if wp["not_ok"]:
            items = "".join(f"<li>{_e(p['label'])} dt={_e(fmt(p['dt']))}: <span class='bad'>{_e(p['status'])}"
                            f"</span>{(' - ' + _e(p['message'][:200])) if p['message'] else ''}"
                            f"{'' if math.isfinite(p['cost']) else ' (cost unknown)'}</li>"
                            for p in wp["not_ok"])
            lst = f"<details><summary>{len(wp['not_ok'])} point(s) not ok</summary><ul class='note'>{items}</ul></details>"
        parts.append(f'<figure class="wp">{body}<figcaption>{"; ".join(cap)}.</figcaption>{lst}</figure>')
    return "\n".join(parts)


def _cost_html(ct: pd.DataFrame) -> str:
    if ct.empty:
        return ('<p class="note">No scenario with a target: give the scenario a <code>[[check]] max</code> for '
                "its primary metric or pass <code>--target</code>.</p>")
    rows = []
    for r in ct.to_dict("records"):
        scen = _e(r["scenario"]) + (f" / {_e(r['variant'])}" if r["variant"] else "")
        tgt = f"{_e(r['primary_metric'] or '?')} &le; {_e(fmt(r['target']))} <span class='note'>({_e(r['target_source'])})</span>"
        if r["reached"]:
            cfg = _e(r["settings"] or f"dt={fmt(r['dt'])}")
            rows.append([scen, _e(r["engine"]), tgt, cfg, _e(fmt(r["error"])), _e(fmt(r["cost"])),
                         _e("1" if r["ratio"] == 1 else fmt(r["ratio"]) + "x")])
        else:
            best = (f"best error {fmt(r['best_error'])}" + (f" at {r['best_error_settings']}"
                                                             if r["best_error_settings"] else "")
                    if _finite(r["best_error"]) else (r["note"] or "no ok point"))
            rows.append([scen, _e(r["engine"]), tgt, "<span class='bad'>not reached</span>",
                         _e(best), "-", "-"])
    return ('<p class="note">The cheapest configuration (latest sweep) whose primary error is at most the '
            "target, its cost and its cost relative to the cheapest engine that reaches the target.</p>"
            + _table(["scenario", "engine", "target", "cheapest configuration", "error", "CPU s / sim s",
                      "vs cheapest"], rows, raw=True))


def _rung(t: float) -> str:
    return f"{t:.0e}".replace("e-0", "e-")


def _ladder_html(lad: pd.DataFrame) -> str:
    if lad.empty:
        return ""
    rungs = sorted(set(lad["rung"]), reverse=True)
    rows = []
    for (sc, va, en), g in lad.groupby(["scenario", "variant", "engine"], sort=True):
        by = {r["rung"]: r for r in g.to_dict("records")}
        cells = [_e(sc) + (f" / {_e(va)}" if va else ""), f"<span style='color:{engine_colour(en)}'>"
                 f"<b>{_e(en)}</b></span>", _e(next((m for m in g["primary_metric"] if m), "?"))]
        for t in rungs:
            r = by.get(t)
            if r is None:
                cells.append("-")
            elif r["reached"]:
                ratio = "" if not _finite(r["ratio"]) or r["ratio"] == 1 else f" ({fmt(r['ratio'], 2)}x)"
                best = " <span class='good'>cheapest</span>" if r["ratio"] == 1 else ""
                cells.append(f"{_e(fmt(r['cost']))}{_e(ratio)}{best}<br><span class='note'>"
                             f"{_e(r['settings'])}</span>")
            else:
                where = (f"best {fmt(r['best_error'])}" + (f" at {r['best_error_settings']}"
                                                           if r["best_error_settings"] else "")
                         if _finite(r["best_error"]) else (r["note"] or "no ok point"))
                cells.append(f"<span class='bad'>not reached</span><br><span class='note'>{_e(where)}</span>")
        rows.append(cells)
    return ("<h3>Accuracy ladder</h3><p class='note'>Per engine, the CPU s per simulated s of its cheapest "
            "configuration (latest sweep) whose primary error is at most each rung, the factor over the cheapest "
            "engine and the configuration; where it is not reached, the best error the engine reached and with "
            "which settings.</p>"
            + _table(["scenario", "engine", "metric"] + [f"\u2264 {_rung(t)}" for t in rungs], rows, raw=True))


def _glance_html(df: pd.DataFrame) -> str:
    ag = at_a_glance(df)
    bp = breaking_points(df)
    parts = []
    if ag.empty:
        parts.append("<p class='note'>No sweep rows with a primary error: no accuracy ladder.</p>")
    else:
        rungs = sorted(set(ag["rung"]), reverse=True)
        rows = []
        for fam, g in ag.groupby("family", sort=True):
            by = {r["rung"]: r for r in g.to_dict("records")}
            cells = [f"<b>{_e(fam)}</b>"]
            for t in rungs:
                r = by.get(t)
                if r is None or not r["reached"]:
                    n = r["scenarios"] if r is not None else 0
                    cells.append(f"<span class='bad'>none</span> <span class='note'>(0/{n})</span>")
                    continue
                w = ", ".join(f"<span style='color:{engine_colour(e)}'><b>{_e(e)}</b></span>"
                              + (f" {k}" if len(r["wins"]) > 1 or k > 1 else "") for e, k in r["wins"].items())
                cells.append(f"{w} <span class='note'>({r['reached']}/{r['scenarios']})</span>")
            rows.append(cells)
        parts.append("<p class='note'>Cheapest engine to reach each accuracy of the primary metric, per scenario "
                     "family (how many of the family's scenarios it is cheapest in; in brackets, in how many "
                     "scenarios any engine reached the accuracy). Details: <a href='#cost-to-target'>accuracy "
                     "ladder</a>.</p>"
                     + _table(["family"] + [f"\u2264 {_rung(t)}" for t in rungs], rows, raw=True))
    if bp.empty:
        parts.append("<p class='note'>No breaking-point searches stored (<code>physbench limits</code> or a "
                     "suite's <code>[[limit]]</code> blocks).</p>")
    else:
        engines = sorted(set(bp["engine"]))
        rows = []
        for (sc, va, par), g in bp.groupby(["scenario", "variant", "limit_param"], sort=True):
            rows.append([_e(sc) + (f" / {_e(va)}" if va else ""), f"<code>{_e(par)}</code>"]
                        + _engine_cells(g, engines, lambda r: _e(fmt_limit(r, short=True))))
        parts.append("<p class='note'>Breaking points: the last value of the parameter at which the scene still "
                     "met its checks and stayed stable (\u2264: holds below; \u2265: holds above). Brackets and "
                     "the check that failed: <a href='#breaking-points'>Breaking points</a>.</p>"
                     + _table(["scenario", "parameter"] + [f"{e}" for e in engines], rows, raw=True))
    return "\n".join(parts)


def _breaking_html(df: pd.DataFrame) -> str:
    bp = breaking_points(df)
    if bp.empty:
        return ("<p class='note'>No breaking-point searches stored. <code>physbench limits SCENARIO --engine E "
                "--param KEY --range LO HI</code> or a suite's <code>[[limit]]</code> block fills this in.</p>")
    evals = _limit_rows(df, "limit_eval")
    parts = ["<p class='note'>Each search walks the parameter from the end where the scene holds (met every "
             "check, stayed stable, in every step phase) towards the other in steps of at most a factor 2, then "
             "bisects the first failing step to the search's tolerance. Limit: the last value that held; "
             "bracket: it and the nearest value that failed; the check that failed there.</p>"]
    for (sc, va, par), g in bp.groupby(["scenario", "variant", "limit_param"], sort=True):
        rows = []
        for r in g.to_dict("records"):
            rows.append([f"<span style='color:{engine_colour(r['engine'])}'><b>{_e(r['engine'])}</b></span>",
                         _e(fmt_limit(r)), _e(r["limit_failed_check"] or "-")[:300],
                         _e(fmt(r["limit_runs"])), _e(fmt(r["limit_cpu_s"])),
                         _e(f"[{fmt(r['limit_range_lo'])}, {fmt(r['limit_range_hi'])}], {fmt(r['limit_phases'])} "
                            "phase(s)")])
        ids = set(g["limit_id"])
        ev = evals[evals["limit_id"].isin(ids)] if len(evals) and "limit_id" in evals.columns else evals
        metric = next((m for m in ev["primary_metric"] if m), None) if len(ev) else None
        b64 = plot_breaking_point(ev, g, par, metric) if len(ev) else None
        title = sc + (f" / {va}" if va else "")
        over = next((o for o in g["limit_overrides"] if o and o != "{}"), None)
        parts.append(f"<h3>{_e(title)}: <code>{_e(par)}</code></h3>"
                     + (f"<p class='note'>with {_e(over)}</p>" if over else "")
                     + _table(["engine", "limit [bracket]", "failed just past it", "runs", "CPU s", "range"],
                              rows, raw=True)
                     + (f"<figure class='wp'>{_img(b64, f'breaking point {title} {par}')}<figcaption>The "
                        f"primary error along <code>{_e(par)}</code>: dots held, crosses failed; dashed, each "
                        "engine's limit; a failed run without an error is drawn at the top.</figcaption></figure>"
                        if b64 else ""))
    return "\n".join(parts)


def _colour(frac: float, n_supported: int) -> str:
    if n_supported == 0 or not math.isfinite(frac):
        return "#e6e6e6"
    hue = int(round(120 * frac))  # 0 red .. 120 green
    return f"hsl({hue},70%,80%)"


def _engine_cells(g: pd.DataFrame, engines: list[str], cell) -> list[str]:
    """One cell per engine (columns ``engines``) from the rows ``g`` (one per
    engine): ``cell(row)``, or a dash where the engine has no row."""
    by = {r["engine"]: r for r in g.to_dict("records")}
    return [cell(by[en]) if en in by else "<span class='note'>-</span>" for en in engines]


def _stability_html(sm: pd.DataFrame) -> str:
    if sm.empty:
        return '<p class="note">No sweep or conformance rows.</p>'
    engines = sorted(sm["engine"].unique())
    rows = []
    def cell(r) -> str:
        supported = r["points"] - r["unsupported"]
        txt = [f"<b>{r['ok_stable']}/{r['points']}</b> ran &amp; stayed finite",
               f"<b>{r['met_checks']}/{r['points']}</b> met its checks"
               + (f" <span class='bad'>(failed: {_e(', '.join(r['checks_failed']))})</span>"
                  if r["checks_failed"] else "")]
        for k in ("unstable", "diverged", "error", "unsupported", "other"):
            if r[k]:
                txt.append(f"{r[k]} {k}")
        if _finite(r["max_stable_dt"]):
            txt.append(f"max stable dt {fmt(r['max_stable_dt'])}")
        if _finite(r["min_unstable_dt"]):
            txt.append(f"fails from dt {fmt(r['min_unstable_dt'])}")
        if _finite(r["max_met_dt"]):
            txt.append(f"checks met up to dt {fmt(r['max_met_dt'])}")
        frac = r["met_checks"] / supported if supported else math.nan
        return (f"<div class='cell' style='background:{_colour(frac, supported)};padding:.2em'>"
                + "<br>".join(txt) + "</div>")

    for (sc, va), g in sm.groupby(["scenario", "variant"], sort=True):
        rows.append([_e(sc) + (f" / {_e(va)}" if va else "")] + _engine_cells(g, engines, cell))
    sel = sm.attrs.get("selection", "")
    return (f"<p class='note'>Showing {_e(sel)}. Per cell: points that ran (status ok) and stayed finite and "
            "stable, out of all points (latest sweep points and latest <code>physbench check</code> rows); of "
            "those, the points that also met every check of the scenario (an expected failure, xfail, is still "
            "a check not met: it says the engine is known not to hold the scene), and which checks failed; counts "
            "of the other outcomes; the largest dt at which the engine stayed ok and stable, the smallest at "
            "which it did not, the largest at which it met its checks. "
            "Colour: share of supported points that met their checks (red 0 .. green 1; grey: unsupported).</p>"
            + _table(["scenario"] + engines, rows, raw=True))


def _phase_html(pt: pd.DataFrame) -> str:
    if pt.empty:
        return ('<p class="note">No point was swept over step phases (a <code>[[sweep]]</code> block with '
                '<code>phases = N</code>).</p>')
    engines = sorted(pt["engine"].unique())
    rows = []
    keys = ["machine_id", "suite", "scenario", "variant", "settings", "dt"]
    order = pt.sort_values(["scenario", "variant", "settings", "dt"], ascending=[True, True, True, False],
                           kind="stable")
    several = order[["machine_id", "suite"]].drop_duplicates().shape[0] > 1
    def cell(r) -> str:
        n = r["phases"] - r["pattern"].count("-")
        if not n:
            return f"<div class='cell' style='background:{_colour(math.nan, 0)};padding:.2em'>unsupported</div>"
        single = {".": "single run: pass", "x": "single run: FAIL", "!": "single run: not ok"}.get(r["phase0"], "")
        return (f"<div class='cell' style='background:{_colour(1 - r['fraction'], n)};padding:.2em'>"
                f"<b>{r['failures']}/{n}</b> failed [{fmt(r['lo'], 2)} - {fmt(r['hi'], 2)}]<br>"
                f"<code>{_e(r['pattern'])}</code><br><span class='note'>{single}</span></div>")

    for key, g in order.groupby(keys, sort=False):
        mid, suite, sc, va, st, dt = key
        label = _e(sc) + (f" / {_e(va)}" if va else "")
        if several:
            label += f"<br><span class='note'>{_e(mid)} / {_e(suite)}</span>"
        rows.append([label, _e(st), _e(fmt(dt))] + _engine_cells(g, engines, cell))
    return ("<p class='note'>One run per dt is one draw of the step phase: where a thin wall is caught depends "
            "on where the steps fall. Each configuration below ran N times with its start moved back along the "
            "exact free flight by i/N dt (i = 0 .. N-1; i = 0 is the scene as written). Failed: not ok, not "
            "stable, or the scenario's check of its primary metric not met (expected failures count). Interval: "
            "95 % Wilson (0/16 bounds the failure rate below 0.20). Pattern over the phases in order: "
            "<code>.</code> pass, <code>x</code> check failed, <code>!</code> not ok or unstable; under it, what a "
            "single run of the scene as written saw. Colour: share of phases passed (red 0 .. green 1).</p>"
            + _table(["scenario", "settings", "dt"] + engines, rows, raw=True))


def _history_html(df: pd.DataFrame) -> str:
    hist = history(df)
    changed = "".join(f"<p class='note'>{_e(line)}</p>" for line in scene_change_lines(scene_changes(df)))
    if not hist:
        return changed + ('<p class="note">No point is in two sweeps of the same suite on the same machine with '
                          "the same scene content yet: history starts with the second sweep.</p>")
    reg = regressions(df, hist)
    shifts = {k: f for k, f in machine_shifts(df, hist).items() if abs(f - 1.0) >= 0.02}
    parts = [f"<p class='note'>{len(hist)} point(s) with history. Cost is the median CPU s per simulated s of the "
             "repeats; a cost change is flagged when the latest median differs from the baseline (the median "
             f"cost of the last {BASELINE_RUNS} earlier ok runs, fewer if there are fewer; a series is judged from "
             f"its {MIN_COST_HISTORY + 1}th ok run on) by more than "
             f"max({NOISE_FLOOR:.0%}; {NOISE_SPREADS:g} x s; {NOISE_SPREADS:g} x {MAD_TO_SIGMA:g} x MAD), s the "
             "relative spread (median - min) / median of the repeats, the larger of the latest run's and the "
             "baseline runs' median one, MAD the baseline runs' median absolute deviation from the baseline, "
             "relative to it (night-to-night scatter); a cost drift (a creep the moving baseline absorbs) when "
             f"the latest cost exceeds the cheapest plateau (median of {BASELINE_RUNS} consecutive runs) of the last "
             f"{DRIFT_HORIZON} earlier ok runs by more than max({NOISE_FLOOR:.0%}; {NOISE_SPREADS:g} x s; "
             f"{NOISE_SPREADS:g} x the night-to-night noise from successive differences) and the rise came over "
             "several nights, not in one jump. Both are taken relative to the night's machine-wide factor (the "
             "median change over all series of that night, when it has at least "
             f"{MACHINE_SHIFT_MIN_SERIES}): a slower machine moves every series, a code change some. "
             "An accuracy change when the primary error differs from the "
             "best earlier one "
             f"by more than {NOISE_FLOOR:.0%} and {ERROR_ABS_FLOOR:g} absolute; a status change from ok to anything "
             "else is a regression. A point is compared only with sweeps of the same scene content (its "
             "scene hash): a changed scene starts a new series.</p>", changed]
    for (mid, suite, sid), f in sorted(shifts.items()):
        parts.append(f"<p class='note'>Machine-wide factor {_e(mid)} / {_e(suite)} / {_e(sid)}: every series ran "
                     f"{f - 1.0:+.1%} against its baseline (median over the series); taken out of the cost "
                     "changes below.</p>")
    if reg.empty:
        parts.append("<p class='good'>No regression or improvement beyond noise.</p>")
    else:
        n_reg = int((reg["direction"] == "regression").sum())
        parts.append(f"<p><span class='{'bad' if n_reg else 'good'}'>{n_reg} regression(s)</span>, "
                     f"{len(reg) - n_reg} improvement(s).</p>")
        rows = []
        for r in reg.to_dict("records"):
            d = r["direction"]
            cls = "bad" if d == "regression" else "good"
            if r["kind"] == "status":
                change, prev, last, thr = "-", _e(r["previous"]), _e(r["latest"]), "-"
            else:
                change = _e(f"{r['change']:+.1%}") if math.isfinite(r["change"]) else "from 0"
                prev, last, thr = _e(fmt(r["previous"])), _e(fmt(r["latest"])), _e(f"{r['threshold']:.0%}")
            rows.append([f"<span class='{cls}'>{_e(d)}</span>", _e(r["kind"]),
                         _e(r["scenario"]) + (f" / {_e(r['variant'])}" if r["variant"] else ""),
                         _e(r["engine"]), _e(r["settings"]), _e(r["machine_id"]) + " / " + _e(r["suite"]),
                         prev, last, change, thr, _e(r["previous_sweep"]) + " &rarr; " + _e(r["latest_sweep"])])
        parts.append(_table(["", "kind", "scenario", "engine", "settings", "machine / suite",
                             "before (cost: baseline; drift: plateau; error: best)", "latest", "change", "noise threshold",
                             "sweeps"], rows, raw=True))
    # small multiples: flagged regressions first, then the largest cost moves
    order: list[tuple[str, str, str]] = []
    if not reg.empty:
        for r in reg[reg["direction"] == "regression"].to_dict("records"):
            k = (r["machine_id"], r["suite"], r["point_key"])
            if k not in order:
                order.append(k)

    def move(g: pd.DataFrame) -> float:
        c = g.loc[g["status"] == "ok", "cost"].to_numpy(float)
        c = c[np.isfinite(c) & (c > 0)]
        return float(np.log(c.max() / c.min())) if len(c) >= 2 else 0.0

    for k in sorted(hist, key=lambda k: -move(hist[k])):
        if k not in order:
            order.append(k)
    picks = order[:MAX_SMALL_MULTIPLES]
    series = []
    for k in picks:
        g = hist[k]
        last = g.iloc[-1]
        t = f"{last['scenario']}{' / ' + last['variant'] if last['variant'] else ''}: {last['engine']} " \
            f"{settings_label(last['swept'] or {})}"
        series.append((t, g))
    b64 = plot_history(series)
    if b64:
        parts.append(f"<figure class='hist'>{_img(b64, 'history small multiples')}<figcaption>The "
                     f"{len(picks)} worst series (flagged regressions first, then the largest cost moves): "
                     "blue, cost median per sweep with a bar down to the fastest repeat; orange, primary error "
                     "(log); red lines, sweeps where the run was not ok.</figcaption></figure>")
    return "\n".join(parts)


def render_html(df: pd.DataFrame, *, target: float | None = None,
                targets: Mapping[Any, float] | float | None = None, warnings: Iterable[str] = (),
                command: str = "physbench report", generated: str | None = None,
                results_dir: str | Path | None = None, physbench_commit: str | None = None) -> str:
    """The whole page for the normalised frame ``df`` (from
    :func:`load_results`)."""
    df = _ensure(df)
    warnings = list(warnings) + list(df.attrs.get("warnings", []) if hasattr(df, "attrs") else [])
    warnings = list(dict.fromkeys(warnings))
    generated = generated or _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    if physbench_commit is None:
        from harness.runner import commit_id

        physbench_commit = commit_id()
    where = f" under <code>{_e(results_dir)}</code>" if results_dir is not None else ""
    sections = []
    if warnings:
        items = "".join(f"<li>{_e(w)}</li>" for w in warnings)
        sections.append(f"<div class='warn'><b>Warnings</b><ul>{items}</ul></div>")
    if df.empty:
        sections.append(f"<div class='warn'><b>No results found</b>{where}. Run <code>physbench sweep</code> "
                        "(or <code>physbench check</code>) first; this page fills in from the Parquet rows they "
                        "write.</div>")
        body = {k: '<p class="note">No results.</p>' for k in ("glance", "wp", "cost", "stab", "phase", "hist",
                                                               "limits")}
        header = ""
    else:
        header = _header_html(df)
        body = {"glance": _glance_html(df),
                "wp": _wp_html(work_precision(df, target=target, targets=targets)),
                "cost": _ladder_html(ladder(df)) + "<h3>At each scenario's own target</h3>"
                        + _cost_html(cost_to_target(df, targets=targets, target=target)),
                "limits": _breaking_html(df),
                "stab": _stability_html(stability_matrix(df)),
                "phase": _phase_html(phase_table(df)),
                "hist": _history_html(df)}
        inc = df[df["incomplete"]]
        if len(inc):
            sections.append(f"<div class='warn'>{len(inc)} row(s) come from incomplete sweeps (part files not yet "
                            "consolidated): " + _e(", ".join(sorted(set(inc["sweep_id"])))) + ".</div>")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>physbench report</title>
<style>{_CSS}</style></head><body>
<h1>physbench report</h1>
<p class="note">Generated {_e(generated)} from stored results{where}.</p>
{''.join(sections)}
<section id="at-a-glance"><h2>At a glance</h2>{body['glance']}</section>
<section id="header"><h2>What this covers</h2>{header or '<p class="note">Nothing.</p>'}</section>
<section id="work-precision"><h2>Work-precision diagrams</h2>{body['wp']}</section>
<section id="cost-to-target"><h2>Cost to reach the target accuracy</h2>{body['cost']}</section>
<section id="breaking-points"><h2>Breaking points</h2>{body['limits']}</section>
<section id="stability"><h2>Stability matrix</h2>{body['stab']}</section>
<section id="phases"><h2>Hard cases over step phases</h2>{body['phase']}</section>
<section id="history"><h2>History across runs</h2>{body['hist']}</section>
<footer><p>Generated by <code>{_e(command)}</code> at {_e(generated)}, physbench commit
<code>{_e(physbench_commit)}</code>. Self-contained: no external assets, no scripts.</p></footer>
</body></html>
"""


# ---------------------------------------------------------------------------
# entry point


def report_main(results_dir: Path | None = None, out: Path | None = None, suites: list[str] | None = None,
                target: float | None = None, fail_on_regression: bool = False) -> int:
    """Write the report (default ``<results_dir>/report.html``) and print its
    path and one line per regression flagged beyond noise.  Returns 0; 1
    when there were no usable result rows (the page is still written and
    says so); 3 when ``fail_on_regression`` and a regression is flagged (for
    a nightly pipeline that should go red)."""
    root = Path(results_dir) if results_dir is not None else RESULTS_DIR
    out = Path(out) if out is not None else root / "report.html"
    cmd = ["physbench", "report"]
    if results_dir is not None:
        cmd += ["--results-dir", str(results_dir)]
    if out != root / "report.html":
        cmd += ["--out", str(out)]
    if suites:
        cmd += ["--suites", *suites]
    if target is not None:
        cmd += ["--target", f"{target:g}"]
    if fail_on_regression:
        cmd += ["--fail-on-regression"]
    df = load_results(root, suites=suites)
    warnings = df.attrs.get("warnings", [])
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    page = render_html(df, target=target, warnings=warnings, command=" ".join(cmd), results_dir=root)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".tmp-{out.name}")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(out)
    if df.empty:
        print(f"no results under {root}{' for suites ' + ', '.join(suites) if suites else ''}; "
              f"wrote an empty report to {out}", file=sys.stderr)
        print(out)
        return 1
    print(out)
    reg = regressions(df)
    for line in scene_change_lines(scene_changes(df)):
        print(f"note: {line}")
    for (mid, suite, sid), f in sorted(machine_shifts(df).items()):
        if abs(f - 1.0) >= 0.02:
            print(f"note: {mid} / {suite} / {sid}: every series ran {f - 1.0:+.0%} against its baseline "
                  "(median over the series): taken out of each cost change as the machine's, not the code's")
    bad = reg[reg["direction"] == "regression"] if not reg.empty else reg
    for r in bad.itertuples():
        change = "" if r.kind == "status" else f" ({r.change:+.0%}, threshold {r.threshold:.0%})"
        print(f"regression: {r.kind}: {r.scenario} on {r.engine} [{r.settings}]: {r.previous} -> {r.latest}{change}")
    if len(bad):
        print(f"{len(bad)} regression(s) beyond noise")
    return 3 if fail_on_regression and len(bad) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(report_main())
