"""History across sweeps and regressions beyond noise: pure functions of
the report's frame (harness.report.rows.normalise), no I/O -- asv's
step_detect.py style.  The rules and their measured figures are in
:func:`regressions`' docstring and tests/test_report.py."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from physbench.harness.report.analysis import sweep_points
from physbench.harness.report.rows import ERROR_FLOOR, normalised, settings_label
from physbench.harness.status import OK

NOISE_FLOOR = 0.10  # relative change below which nothing is ever flagged
NOISE_SPREADS = 3.0  # ... and the multiple of the repeats' relative spread (and of the nightly scatter)
BASELINE_RUNS = 5  # a cost is compared with the median of this many latest earlier ok runs of its series
MAD_TO_SIGMA = 1.4826  # MAD x this estimates a normal standard deviation
DRIFT_HORIZON = 30  # earlier ok runs a cost drift is looked for in
MIN_COST_HISTORY = 3  # earlier ok runs a cost series needs before a change in it is judged
MACHINE_SHIFT_MIN_SERIES = 20  # series a night needs before its machine-wide cost shift is taken out
ERROR_ABS_FLOOR = 1e-12  # an accuracy change must also exceed this absolutely


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
    s = sweep_points(normalised(df))
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
    df = normalised(df)
    hist = history(df) if hist is None else hist
    logs: dict[tuple[str, str, str], list[float]] = {}
    for (mid, suite, _pk), g in hist.items():
        recs = g.to_dict("records")
        last = recs[-1]
        if last["status"] != OK or not (math.isfinite(last["cost"]) and last["cost"] > 0):
            continue
        costs = [r for r in recs[:-1] if r["status"] == OK and math.isfinite(r["cost"]) and r["cost"] > 0]
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
    df = normalised(df)
    hist = history(df) if hist is None else hist
    diffs: dict[tuple[str, str, str], list[float]] = {}
    for (mid, suite, _pk), g in hist.items():
        recs = g.to_dict("records")
        c = [r["cost"] for r in recs[:-1] if r["status"] == OK and math.isfinite(r["cost"]) and r["cost"] > 0]
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
    df = normalised(df)
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
        if prev["status"] == OK and last["status"] != OK:
            rows.append({**base, "kind": "status", "direction": "regression", "previous": OK,
                         "latest": last["status"], "change": math.nan, "threshold": math.nan,
                         "previous_sweep": prev["sweep_id"], "severity": math.inf})
            continue
        if prev["status"] != OK and last["status"] == OK:
            rows.append({**base, "kind": "status", "direction": "improvement", "previous": prev["status"],
                         "latest": OK, "change": math.nan, "threshold": math.nan,
                         "previous_sweep": prev["sweep_id"], "severity": math.inf})
        if last["status"] != OK:
            continue
        ok_before = [r for r in earlier if r["status"] == OK]
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

