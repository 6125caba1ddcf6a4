"""The report's figures: matplotlib (Agg) PNGs as base64 text, for
``data:`` URIs.  One colour per engine in every plot."""

from __future__ import annotations

import base64
import io
import math
from typing import Any, Mapping

import numpy as np
import pandas as pd

from physbench.harness.report.analysis import frontier
from physbench.harness.report.rows import ERROR_FLOOR, is_finite, settings_label
from physbench.harness.status import OK


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
    xs = [float(v) for v in evals["limit_value"] if is_finite(v)]
    if not xs:
        return None
    if min(xs) > 0:
        ax.set_xscale("log")
    errs = [e for e in evals["primary_error"] if is_finite(e) and e > 0]
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
        ys = [max(by[v][1], ERROR_FLOOR) if is_finite(by[v][1]) and by[v][1] > 0 else ymax / 2 for v in vals]
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
        ok = (g["status"] == OK).to_numpy()
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



#: where a residual of exactly 0 is drawn on the contact-law plot's log axes
LAW_FLOOR = 1e-16


def plot_contact_laws(table: pd.DataFrame) -> str | None:
    """The contact-law residuals of harness.report.analysis.contact_law_table
    as base64 PNG (None without a finite value): one panel per law
    (Signorini N m, cone violation, dissipation rad), one bar per engine in
    its colour, log axis; a residual of exactly 0 drawn at LAW_FLOOR and
    labelled 0, a missing one left out."""
    laws = (("signorini_residual", "Signorini |lam_n gap| (N m)"), ("cone_violation", "cone violation (1)"),
            ("dissipation_residual", "dissipation angle (rad)"))
    if table is None or table.empty or not any(
            is_finite(v) for n, _ in laws if f"{n}_max" in table.columns for v in table[f"{n}_max"]):
        return None
    fig = _figure(9.0, 2.8)
    axes = fig.subplots(1, len(laws))
    engines = list(table["engine"])
    for ax, (n, title) in zip(axes, laws):
        vals = [float(v) if is_finite(v) else math.nan for v in table[f"{n}_max"]]
        for i, (en, v) in enumerate(zip(engines, vals)):
            if math.isnan(v):
                continue
            ax.bar(i, max(v, LAW_FLOOR), color=engine_colour(en), log=True)
            if v == 0.0:
                ax.annotate("0", (i, LAW_FLOOR), ha="center", va="bottom", fontsize=8)
        ax.set_xticks(range(len(engines)), [_mpl_text(e) for e in engines], rotation=30, fontsize=8)
        ax.set_title(_mpl_text(title), fontsize=9)
        ax.set_ylim(LAW_FLOOR / 10, None)
    return _png(fig)
