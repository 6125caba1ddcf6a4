"""Rerun traces: every engine's run of one scene, side by side, in one ``.rrd``.

:func:`write_rrd` writes ONE recording (rerun-sdk 0.41) holding, per run:

``/world``
    ``ViewCoordinates.RIGHT_HAND_Z_UP`` (static): the scene is Z up, SI units
    (metres, seconds, joules).
``/world/<engine>``
    A static ``Transform3D(translation=(0, k * spacing, 0))``: the k-th drawn
    run's whole scene (k = 0, 1, ... over the runs that have bodies, in the
    order given) is shifted sideways along +y so the runs stand side by side.
    ``spacing`` (m) is the y-size of the scene's padded bounding box times
    1.2 (see :func:`scene_extent`).  Because the offset sits on this parent
    entity, the translations logged below it are the trace positions
    unchanged.
``/world/<engine>/<body name>``
    The body's shape, logged once (static), centred on the body origin in the
    body frame: sphere -> ``Ellipsoids3D(half_sizes=(r, r, r))``; box ->
    ``Boxes3D(half_sizes)``; capsule -> ``Capsules3D(lengths=2 h, radii=r)``
    translated by (0, 0, -h) because rerun's capsule runs from (0, 0, 0) to
    (0, 0, length) along +z; cylinder -> ``Cylinders3D(lengths=2 h, radii=r)``
    (rerun 0.41 has it, centred on the origin along +z, so no approximation).
    The pose per recorded frame is a ``Transform3D(translation, quaternion)``
    sent columnar (one ``send_columns`` per body for all frames), quaternion
    converted from physbench's wxyz to rerun's xyzw.  Frames where the body's
    pose is not finite (a diverged run's last frames) are left out.
    A body named ``static``, ``status``, ``contacts``, ``engine_contacts``
    or ``joints`` is logged as ``<name>_body`` so it cannot parent the
    statics, the status document, the contacts or the joints.
``/world/<engine>/joints/<joint name>/anchors``
    Scenes with ``[[joint]]`` tables: per recorded frame, two points (m,
    world frame): the joint's anchor carried by its ``body`` (the run's
    colour) and the one carried by ``other`` (dark grey; the world side
    stays put), each side's recorded pose applied to its local anchor, the
    points ``joint_drift`` measures (:func:`harness.joints.joint_world`).
    A joint that holds shows them as one point.
``/world/<engine>/joints/<joint name>/axis``
    Revolute and prismatic joints: two ``Arrows3D`` from those points along
    each side's world axis, 2 x the body's bounding radius long; a hinge
    that holds shows them as one arrow.
``/world/<engine>/static/<name>``
    Fixed geometry, static: a box as ``Boxes3D``; a plane (infinite) as a thin
    box patch whose top face lies on the plane, oriented by the normal and
    large enough to cover the scene's padded bounding box projected on it.
``/world/<engine>/status``
    For any run that is not ``ok``: a ``TextDocument`` "status: message".
    Runs whose status is neither ``ok`` nor ``diverged``, or that have no
    trace, get only this document, no bodies.
``/metrics/<engine>/energy``
    E(t) = translational + rotational kinetic + gravitational + spring
    potential energy (J), :func:`harness.metrics.energy_series`, computed
    once per run (the diagnosing trace's bands and crossings reuse it).  As in the metrics, the
    potential is measured from the datum the scene fixes
    (:func:`harness.metrics.energy_datum`, docs/METRICS.md), the same for
    every engine, so the curves start at the same level.
``/metrics/<engine>/penetration``
    Per-frame deepest overlap (m) over all candidate pairs,
    :func:`contract.geometry.max_depth_per_frame` (0 when there are no pairs);
    only for scenes with the ``contact`` effect.  The run's own measurement
    when the runner kept it (``Trace.penetration``), else measured.

Timelines: ``step`` (sequence, the simulation step number round(t / dt) with
the run's resolved ``dt``, equal to the frame index when every step is
recorded) and ``sim_time`` (duration, seconds).  All time-varying data go
through ``RecordingStream.send_columns`` (columnar; it adds no other
timelines), never one call per body per frame.

The default blueprint (a 3D view of ``/world`` beside time-series views of
the energies and penetrations, plus a text view per failed run) is stored in
the file through ``rec.save(path, default_blueprint=...)`` before anything is
logged, as ENGINE_NOTES prescribes for rerun 0.41.
"""

from __future__ import annotations

import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import rerun as rr

from physbench.contract.geometry import measure_penetration
from physbench.harness.metrics import relative_energy
from physbench.harness.trace.annotate import DEFAULT_CAP, Diagnosis
from physbench.harness.trace.blueprint import default_blueprint, family_blueprint
from physbench.harness.joints import joint_world
from physbench.harness.trace.channels import body_entity, entity_part, joint_entity, send_scalars, time_columns

from physbench.contract.rotation import quat_rotate, wxyz_to_xyzw
from physbench.contract.scene import Body, Scene, Static

DRAWN_STATUSES = ("ok", "diverged")
MODEL_PATH = "/world/model"

# One colour per run (RGBA); statics are a translucent grey.
PALETTE = (
    (31, 119, 180, 255),
    (255, 127, 14, 255),
    (44, 160, 44, 255),
    (214, 39, 40, 255),
    (148, 103, 189, 255),
    (140, 86, 75, 255),
    (227, 119, 194, 255),
    (127, 127, 127, 255),
)
STATIC_COLOR = (150, 150, 150, 110)

# Padding of the scene box (fraction of its largest size) and the gap between
# side-by-side copies (fraction of the padded y-size).
PAD_FRACTION = 0.1
SPACING_FACTOR = 1.2


@dataclass(frozen=True)
class Extent:
    """Axis-aligned box (m): ``lo`` and ``hi`` of shape (3,)."""

    lo: np.ndarray
    hi: np.ndarray

    @property
    def size(self) -> np.ndarray:
        return self.hi - self.lo

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.lo + self.hi)

    def union(self, other: "Extent") -> "Extent":
        return Extent(np.minimum(self.lo, other.lo), np.maximum(self.hi, other.hi))


# ---------------------------------------------------------------------------
# geometry helpers


def quat_z_to(n: np.ndarray) -> np.ndarray:
    """Unit quaternion (wxyz, (4,)) of the shortest rotation taking +z to the
    unit vector ``n`` (3,).  For n = -z (no unique axis) a half turn about x."""
    n = np.asarray(n, float)
    n = n / np.linalg.norm(n)
    # q = (1 + z.n, z x n) normalised is the half-angle form of the rotation
    # by acos(z.n) about z x n.
    w = 1.0 + n[2]
    if w < 1e-12:
        return np.array([0.0, 1.0, 0.0, 0.0])
    q = np.array([w, -n[1], n[0], 0.0])
    return q / np.linalg.norm(q)


def _abs_rot(q: np.ndarray) -> np.ndarray:
    """|R| elementwise for the rotation of wxyz ``q``: |R| @ h is the world
    half-size of a box with body half-extents h."""
    return np.abs(quat_rotate(np.asarray(q, float)[None, :], np.eye(3)).T)


def _static_box_extent(s: Static) -> Extent:
    h = _abs_rot(s.orientation) @ np.asarray(s.half_extents, float)
    p = np.asarray(s.position, float)
    return Extent(p - h, p + h)


def plane_patch(s: Static, box: Extent) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A finite thin box standing for plane ``s`` under the region ``box``.

    Returns (centre (3,) on the plane, wxyz orientation (4,) whose z is the
    normal, in-plane half-sizes (2,), thickness (m)).  The half-sizes are the
    support of ``box`` along the patch's in-plane axes u, v
    (sum_i |u_i| h_i), so the patch covers the box's projection.
    """
    n = np.asarray(s.normal, float)
    n = n / np.linalg.norm(n)
    q = quat_z_to(n)
    c = box.center
    centre = c - (c @ n - s.offset) * n  # closest point of the plane to c
    axes = quat_rotate(q[None, :], np.eye(3))  # rows: patch x (u), y (v), z (= n)
    h = 0.5 * box.size
    half = np.abs(axes[:2]) @ h
    thickness = max(1e-3, 0.01 * float(np.max(box.size)))
    return centre, q, half, thickness


def scene_extent(scene: Scene, traces: Sequence) -> tuple[Extent, float]:
    """(padded scene box, side-by-side spacing along y), metres.

    The box holds every body (centre +- bounding radius) at t = 0 and in every
    given trace's finite frames, and every static box; it is padded by
    ``PAD_FRACTION`` of its largest size.  Plane patches cover it, and the
    spacing is ``SPACING_FACTOR`` x the y-size of box and patches together.
    Callers pass only trustworthy traces (status ok): a diverged run's
    runaway positions would blow the box up.
    """
    boxes: list[Extent] = []
    if scene.n_bodies:
        r = np.array([b.bounding_radius for b in scene.bodies])[:, None]
        x0 = scene.initial_state()[0]
        boxes.append(Extent((x0 - r).min(axis=0), (x0 + r).max(axis=0)))
        for tr in traces:
            p = tr.pos  # (F, n, 3)
            if p.shape[0] == 0:
                continue
            if not np.isfinite(p).all():  # drop the frames a body is not finite in
                p = np.where(np.isfinite(p).all(axis=2, keepdims=True), p, np.nan)
                if np.isnan(p).all():
                    continue
            # per body over frames first, then the bounding radius
            with np.errstate(invalid="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN bodies
                lo = np.nanmin(np.nanmin(p, axis=0) - r, axis=0)
                hi = np.nanmax(np.nanmax(p, axis=0) + r, axis=0)
            boxes.append(Extent(lo, hi))
    for s in scene.statics:
        if s.shape == "box":
            boxes.append(_static_box_extent(s))
    if not boxes:
        box = Extent(np.full(3, -0.5), np.full(3, 0.5))
    else:
        box = boxes[0]
        for b in boxes[1:]:
            box = box.union(b)
    pad = PAD_FRACTION * float(np.max(box.size)) + 1e-3
    box = Extent(box.lo - pad, box.hi + pad)
    full = box
    for s in scene.statics:
        if s.shape == "plane":
            centre, q, half, th = plane_patch(s, box)
            hw = _abs_rot(q) @ np.array([half[0], half[1], 0.5 * th])
            full = full.union(Extent(centre - hw, centre + hw))
    spacing = SPACING_FACTOR * float(full.size[1])
    return box, spacing


# ---------------------------------------------------------------------------
# logging pieces


def body_shape(body: Body, color) -> rr.AsComponents:
    """The body's shape in its own frame (centred on the body origin, long
    axis of capsules and cylinders along +z, as in contract.scene)."""
    if body.shape == "sphere":
        r = body.radius
        # wireframe (the default) so that spin is visible
        return rr.Ellipsoids3D(half_sizes=[[r, r, r]], colors=[color])
    if body.shape == "box":
        return rr.Boxes3D(half_sizes=[body.half_extents], colors=[color], fill_mode="solid")
    if body.shape == "capsule":
        h = body.half_length
        # rerun's capsule runs from (0,0,0) to (0,0,length): shift it by -h
        return rr.Capsules3D(lengths=[2.0 * h], radii=[body.radius], translations=[[0.0, 0.0, -h]],
                             colors=[color], fill_mode="solid")
    if body.shape == "cylinder":
        # rerun 0.41 cylinders are centred on the origin along +z
        return rr.Cylinders3D(lengths=[2.0 * body.half_length], radii=[body.radius], colors=[color],
                              fill_mode="solid")
    raise ValueError(f"body {body.name!r}: no rerun shape for {body.shape!r}")


def _log_statics(rec: rr.RecordingStream, engine_path: str, scene: Scene, box: Extent) -> None:
    for s in scene.statics:
        path = f"{engine_path}/static/{entity_part(s.name)}"
        if s.shape == "box":
            rec.log(path, rr.Transform3D(translation=s.position,
                                         quaternion=rr.Quaternion(xyzw=wxyz_to_xyzw(s.orientation))),
                    static=True)
            rec.log(path, rr.Boxes3D(half_sizes=[s.half_extents], colors=[STATIC_COLOR], fill_mode="solid"),
                    static=True)
        elif s.shape == "plane":
            centre, q, half, th = plane_patch(s, box)
            rec.log(path, rr.Transform3D(translation=centre, quaternion=rr.Quaternion(xyzw=wxyz_to_xyzw(q))),
                    static=True)
            # patch frame: z is the normal; the top face lies on the plane
            rec.log(path, rr.Boxes3D(half_sizes=[[half[0], half[1], 0.5 * th]], centers=[[0.0, 0.0, -0.5 * th]],
                                     colors=[STATIC_COLOR], fill_mode="solid"), static=True)
        else:
            raise ValueError(f"static {s.name!r}: no rerun shape for {s.shape!r}")


def frame_steps(t: np.ndarray, dt: float | None) -> np.ndarray:
    """Step numbers (int64, (F,)) of frames at times ``t``: round(t / dt), or
    the frame index if dt is unknown."""
    if dt and dt > 0 and np.isfinite(t).all():
        return np.rint(t / dt).astype(np.int64)
    return np.arange(t.shape[0], dtype=np.int64)


def _log_bodies(rec: rr.RecordingStream, engine_path: str, scene: Scene, steps: np.ndarray, t: np.ndarray,
                pos: np.ndarray, quat: np.ndarray, color) -> None:
    """Each body's shape (static) and its poses pos (F, n, 3), quat (F, n, 4)
    wxyz at the given steps, one send_columns per body, non-finite frames
    left out."""
    times = time_columns(steps, t)
    # one copy each into per-body contiguous float32 blocks (what rerun
    # stores), instead of a strided copy per body
    pos = np.ascontiguousarray(np.swapaxes(pos, 0, 1), dtype=np.float32)  # (n, F, 3)
    quat = np.ascontiguousarray(np.swapaxes(wxyz_to_xyzw(quat), 0, 1), dtype=np.float32)  # (n, F, 4) xyzw
    finite = np.isfinite(pos).all(axis=2) & np.isfinite(quat).all(axis=2)  # (n, F)
    shapes: dict[tuple, rr.AsComponents] = {}  # bodies of one size share one archetype
    for i, body in enumerate(scene.bodies):
        ok = finite[i]
        if not ok.any() and engine_path == MODEL_PATH:
            continue  # a body the model does not place
        path = body_entity(engine_path, body)
        key = (body.shape, body.radius, body.half_length,
               None if body.half_extents is None else tuple(np.asarray(body.half_extents, float)))
        shape = shapes.get(key)
        if shape is None:
            shape = shapes[key] = body_shape(body, color)
        rec.log(path, shape, static=True)
        if ok.all():
            idx, p, q = times, pos[i], quat[i]
        elif ok.any():
            idx, p, q = time_columns(steps[ok], t[ok]), pos[i][ok], quat[i][ok]
        else:
            continue
        rec.send_columns(path, indexes=idx, columns=rr.Transform3D.columns(translation=p, quaternion=q))


#: a joint's axis arrows are this many times its body's bounding radius long
AXIS_ARROW_FACTOR = 2.0


def _log_joints(rec: rr.RecordingStream, engine_path: str, scene: Scene, steps: np.ndarray, t: np.ndarray,
                tr, color) -> None:
    """Each joint of ``scene`` as its two sides hold it, per recorded frame
    (harness.joints.joint_world, the points joint_drift measures):
    ``<joint>/anchors`` two points (m, world frame), the anchor carried by
    ``body`` then the one carried by ``other``; revolute and prismatic
    joints also ``<joint>/axis``, two arrows from those points along each
    side's axis, AXIS_ARROW_FACTOR x the body's bounding radius long.
    Frames where a side is not finite are left out."""
    if not scene.joints or not steps.size:
        return
    other_color = (20, 20, 20, 255)
    for j, (pb, po, ub, uo) in zip(scene.joints, joint_world(scene, tr)):
        path = joint_entity(engine_path, j)
        pts = np.stack([pb, po], axis=1)  # (F, 2, 3)
        ok = np.isfinite(pts).all(axis=(1, 2))
        if ub is not None:
            axes = np.stack([ub, uo], axis=1)
            ok &= np.isfinite(axes).all(axis=(1, 2))
        if not ok.any():
            continue
        n = int(ok.sum())
        idx = time_columns(steps[ok], t[ok])
        lengths = np.full(n, 2)
        colors = np.tile(np.array([color, other_color], np.uint8), (n, 1))
        rec.send_columns(f"{path}/anchors", indexes=idx, columns=rr.Points3D.columns(
            positions=pts[ok].reshape(-1, 3).astype(np.float32), colors=colors).partition(lengths))
        if ub is not None:
            length = AXIS_ARROW_FACTOR * scene.bodies[j.body].bounding_radius
            rec.send_columns(f"{path}/axis", indexes=idx, columns=rr.Arrows3D.columns(
                origins=pts[ok].reshape(-1, 3).astype(np.float32),
                vectors=(length * axes[ok]).reshape(-1, 3).astype(np.float32), colors=colors).partition(lengths))


def _log_run(rec: rr.RecordingStream, engine_path: str, metrics_path: str, scene: Scene, result,
             color, box: Extent, diag: "Diagnosis | None" = None) -> None:
    """Bodies, statics and metric series of one drawn run (and, with
    ``diag``, its diagnosis: harness/trace/diagnose.py)."""
    tr = result.trace.valid()
    F = tr.t.shape[0]
    dt = (result.settings or {}).get("dt") or scene.dt
    steps = frame_steps(tr.t, dt)
    t = np.asarray(tr.t, float)
    _log_statics(rec, engine_path, scene, box)
    _log_bodies(rec, engine_path, scene, steps, t, tr.pos, tr.quat, color)
    _log_joints(rec, engine_path, scene, steps, t, tr, color)
    if not (F and scene.n_bodies):
        return
    energy = relative_energy(scene, tr)  # (dE, E, E_scale): the plot, the bands, the crossings
    send_scalars(rec, f"{metrics_path}/energy", steps, t, energy[1])
    pen = None
    if scene.has("contact"):
        pen = tr.penetration
        if pen is None or pen.n_frames != F:
            pen = measure_penetration(scene, tr)
        send_scalars(rec, f"{metrics_path}/penetration", steps, t, pen.frame_max())
    if diag is not None:
        diag.log_run(rec, engine_path, metrics_path, scene, result, tr, steps, t, pen, energy)


def run_labels(results: Sequence) -> list[str]:
    """One entity-path-safe label per result: the engine name, with ``_2``,
    ``_3`` ... appended to repeats (e.g. two settings of one engine)."""
    seen: dict[str, int] = {}
    out = []
    for r in results:
        k = seen.get(r.engine, 0) + 1
        seen[r.engine] = k
        out.append(entity_part(r.engine if k == 1 else f"{r.engine}_{k}"))
    return out


def is_drawn(result) -> bool:
    return result.status in DRAWN_STATUSES and result.trace is not None and result.trace.n_frames > 0


def write_rrd(path, scene: Scene, results: Sequence, *, app_id: str = "physbench",
              recording_id: str | None = None, diagnose: bool = False, outcomes: Sequence = (),
              checks: dict | None = None, contact_cap: int | None = None) -> None:
    """Write the runs ``results`` (harness.runner.RunResult) of ``scene`` into
    ONE rerun recording at ``path`` (``.rrd``), side by side (layout in the
    module docstring).  ``recording_id`` defaults to a fresh
    ``<scene id>[:<variant>]:<uuid4>``; the viewer merges recordings that
    share an id.  The file is complete (flushed, footer written) on return,
    also when logging raised.

    ``diagnose`` writes the diagnosing trace instead (docs/TRACES.md): the
    runs overlaid (no sideways offset) with the model's ghost, error and
    momentum series, thresholds, contacts, events and context documents, and
    the scenario family's blueprint.  ``outcomes`` (harness.conformance
    .Outcome) and ``checks`` (metric -> contract.scene.Check) feed the
    verdicts, thresholds and crossing events; ``contact_cap`` bounds the
    contact rows per frame.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    results = list(results)
    labels = run_labels(results)
    drawn = [is_drawn(r) for r in results]
    failed = [lab for lab, r in zip(labels, results) if r.status != "ok"]
    # the extent only trusts ok runs (a diverged run may be at 1e6 m)
    box, spacing = scene_extent(scene, [r.trace.valid() for r, d in zip(results, drawn) if d and r.status == "ok"])
    diag = None
    if diagnose:
        diag = Diagnosis(scene, outcomes, checks, DEFAULT_CAP if contact_cap is None else contact_cap)
        drawn_labels = [lab for lab, d in zip(labels, drawn) if d]
        blueprint = family_blueprint(scene.family, drawn_labels, diag.series(drawn_labels),
                                     diag.model is not None)
    else:
        blueprint = default_blueprint(labels, drawn, scene.has("contact"), failed)

    if recording_id is None:
        tag = scene.id + (f":{scene.variant}" if scene.variant else "")
        recording_id = f"{tag}:{uuid.uuid4()}"
    rec = rr.RecordingStream(app_id, recording_id=recording_id)
    # the blueprint must go in with save(): see ENGINE_NOTES (rerun 0.41)
    rec.save(str(path), default_blueprint=blueprint)
    try:
        rec.send_recording_name(scene.id + (f" [{scene.variant}]" if scene.variant else ""))
        rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if diag is not None:
            # the ghost and the thresholds over the longest drawn run's frames
            longest = max((r for r, d in zip(results, drawn) if d), key=lambda r: r.trace.n_frames, default=None)
            if longest is not None:
                tr = longest.trace.valid()
                dt = (longest.settings or {}).get("dt") or scene.dt
                st, tt = frame_steps(tr.t, dt), np.asarray(tr.t, float)
                diag.log_ghost(rec, st, tt, _log_bodies)
                diag.log_predictions(rec, st, tt, dt)
                diag.log_thresholds(rec, st, tt)
        slot = 0  # drawn runs take consecutive slots along +y
        for k, (r, lab, d) in enumerate(zip(results, labels, drawn)):
            engine_path = f"/world/{lab}"
            if r.status != "ok":
                text = f"{r.status}: {r.message}" if r.message else r.status
                rec.log(f"{engine_path}/status", rr.TextDocument(text), static=True)
            if diag is not None and not d:
                diag.log_context_only(rec, lab, r)
            if d:
                if diag is None:
                    # the sideways offset of this run's copy of the scene
                    rec.log(engine_path, rr.Transform3D(translation=[0.0, slot * spacing, 0.0]), static=True)
                _log_run(rec, engine_path, f"/metrics/{lab}", scene, r, PALETTE[k % len(PALETTE)], box, diag)
                slot += 1
    finally:
        # flush() alone leaves the file without its footer/manifest (the
        # reader then warns and falls back to a whole-file scan);
        # disconnect() closes the file sink and writes the footer.
        rec.flush()
        rec.disconnect()


__all__ = ["write_rrd", "scene_extent", "quat_z_to", "plane_patch",
           "default_blueprint", "run_labels", "frame_steps"]
