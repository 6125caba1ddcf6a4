"""Default blueprints stored in a trace: the watching layout, and the
diagnosing layout per scenario family (views listed in docs/TRACES.md)."""

from __future__ import annotations

from typing import Sequence

import rerun.blueprint as rrb

def default_blueprint(labels: Sequence[str], drawn: Sequence[bool], contact: bool, failed: Sequence[str]) -> rrb.Blueprint:
    """3D view of /world beside time-series views (energy; penetration when
    the scene has contact) and one text view per run that is not ok."""
    plots: list = []
    energy = [f"/metrics/{lab}/energy" for lab, d in zip(labels, drawn) if d]
    if energy:
        plots.append(rrb.TimeSeriesView(origin="/metrics", contents=energy, name="energy (J)"))
        if contact:
            pen = [f"/metrics/{lab}/penetration" for lab, d in zip(labels, drawn) if d]
            plots.append(rrb.TimeSeriesView(origin="/metrics", contents=pen, name="penetration (m)"))
    for lab in failed:
        plots.append(rrb.TextDocumentView(origin=f"/world/{lab}/status", name=f"{lab} status"))
    world = rrb.Spatial3DView(origin="/world", name="scene")
    if not plots:
        return rrb.Blueprint(world, collapse_panels=True)
    return rrb.Blueprint(rrb.Horizontal(world, rrb.Vertical(*plots), column_shares=[3, 2]), collapse_panels=True)



#: the time-series groups of a diagnosing trace, most telling first, per
#: scenario family (others: DEFAULT_GROUPS)
FAMILY_GROUPS: dict[str, tuple[str, ...]] = {
    "billiards": ("error", "energy", "momentum", "penetration"),
    "stacking": ("penetration", "error", "energy"),
    "tunnelling": ("penetration", "error", "energy"),
    "friction": ("error", "energy", "penetration"),
    "gyroscopic": ("error", "momentum", "energy"),
}
DEFAULT_GROUPS = ("error", "energy", "momentum", "penetration")
GROUP_TITLES = {"error": "error against the model (m)", "energy": "energy (J)",
                "momentum": "momentum |P| (N s), |L| (N m s)", "penetration": "penetration (m)",
                "checks": "checks: running metric and threshold (1)"}


def group_title(group: str) -> str:
    """A view's name: GROUP_TITLES, or "model predictions (<unit>)" for a
    ``model:<unit>`` group."""
    if group.startswith("model:"):
        return f"model predictions ({group[6:]})"
    return GROUP_TITLES[group]


def family_blueprint(family: str, labels: Sequence[str], series: dict[str, list[str]],
                     ghost: bool) -> rrb.Blueprint:
    """The diagnosing layout: on the left the engines overlaid in one 3D
    view of /world (the ghost /world/model among them) above one 3D view per
    engine side by side (that engine and the ghost); on the right the
    family's time-series groups (``series``: group -> entity paths, the
    thresholds /metrics/threshold/... included; groups the family does not
    order follow in ``series`` order: checks, model predictions), the events
    and the context documents."""
    model = ["/world/model/**"] if ghost else []
    world = rrb.Spatial3DView(origin="/world", name="overlaid" + (" (ghost: model)" if ghost else ""))
    side = [rrb.Spatial3DView(origin="/world", contents=[f"/world/{lab}/**", *model], name=lab) for lab in labels]
    left = rrb.Vertical(world, rrb.Horizontal(*side), row_shares=[3, 2]) if len(side) > 1 else world
    plots: list = []
    order = FAMILY_GROUPS.get(family, DEFAULT_GROUPS)
    for g in [*order, *(g for g in series if g not in order)]:
        if series.get(g):
            plots.append(rrb.TimeSeriesView(origin="/metrics", contents=series[g], name=group_title(g)))
    texts = [rrb.TextLogView(origin="/events", name="events")]
    texts += [rrb.TextDocumentView(origin=f"/context/{lab}", name=f"{lab} context") for lab in labels]
    right = rrb.Vertical(*plots, rrb.Tabs(*texts))
    return rrb.Blueprint(rrb.Horizontal(left, right, column_shares=[3, 2]), collapse_panels=True)
