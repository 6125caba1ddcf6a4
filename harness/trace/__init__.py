"""Rerun traces (rerun-sdk 0.41): every engine's run of one scene in one
``.rrd``, to watch (:func:`write_rrd`) or to diagnose (``diagnose=True``:
the model's ghost, per-body error, contacts, events, context, the family's
blueprint) and, after a conformance verdict, one file per failing case
(:func:`harness.trace.cases.write_case_trace`).  Entity paths:
docs/TRACES.md.

Modules: ``writer`` (layout, bodies, statics, series, :func:`write_rrd`),
``channels`` (entity paths, scalar series),
``blueprint`` (default views), ``diagnose`` (ghost, error, events, context:
numpy and text), ``contacts`` (the harness's deepest points), ``annotate``
(logging the diagnosis), ``cases`` (the check step)."""

from physbench.harness.trace.blueprint import default_blueprint, family_blueprint
from physbench.harness.trace.writer import frame_steps, plane_patch, quat_z_to, run_labels, scene_extent, write_rrd

__all__ = ["write_rrd", "scene_extent", "quat_z_to", "plane_patch",
           "default_blueprint", "family_blueprint", "run_labels", "frame_steps"]
