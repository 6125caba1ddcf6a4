"""Logging a run's diagnosis into a trace: ghost, error and momentum
series, thresholds, contacts, events and the context document (entity paths
in docs/TRACES.md; what each one holds in harness/trace/diagnose.py and
harness/trace/contacts.py)."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import rerun as rr

from physbench.contract.scene import Scene
from physbench.harness.metrics import momenta
from physbench.harness.trace import diagnose as dg
from physbench.harness.trace.channels import body_entity, send_scalars, time_columns
from physbench.harness.trace.contacts import DEFAULT_CAP, harness_contacts

GHOST_COLOR = (60, 200, 90, 90)  # translucent green
HARNESS_CONTACT_COLOR = (230, 30, 30, 255)
ENGINE_CONTACT_COLOR = (30, 120, 230, 255)
#: check metric -> the time-series group its threshold is drawn in; the
#: others with a running series (diagnose.check_series) go to "checks",
#: drawn against /metrics/<engine>/check/<metric>
THRESHOLD_GROUP = {"max_penetration": "penetration", "final_position_error": "error", "trajectory_rmse": "error"}
#: energy check -> the side of E0 its max bounds E(t) on: its running value
#: is |E - E0| / E_scale (both sides), (E - E0) / E_scale (upper) or
#: (E0 - E) / E_scale (lower; its min bounds the upper side)
ENERGY_BAND = {"energy_drift": "both", "energy_gain": "upper", "energy_dissipated": "lower"}


def energy_band(name: str, check, E0: float, scale: float) -> dict[str, float]:
    """The energies (J) a check on ``name`` (ENERGY_BAND) keeps E(t) within:
    {"upper": J, "lower": J}, the sides it bounds, from the check's max (+
    tolerance) and min (- tolerance), E0 (J) and the metric's E_scale (J,
    harness.metrics.relative_energy).  tests/test_trace_checks.py pins them
    to the metric's own scale."""
    side = ENERGY_BAND[name]
    tol = check.tolerance or 0.0
    out = {}
    if check.max is not None:
        if side in ("both", "upper"):
            out["upper"] = E0 + (check.max + tol) * scale
        if side in ("both", "lower"):
            out["lower"] = E0 - (check.max + tol) * scale
    if check.min is not None and side == "lower":  # (E0 - E) / E_scale >= min - tolerance
        out["upper"] = E0 - (check.min - tol) * scale
    return out


def _send_level(rec: rr.RecordingStream, path: str, steps: np.ndarray, t: np.ndarray, value: float) -> None:
    """A constant ``value`` at ``path`` as a line over the frames: its two ends."""
    ends = np.array([0, steps.size - 1])
    rec.send_columns(path, indexes=[rr.TimeColumn("step", sequence=steps[ends]),
                                    rr.TimeColumn("sim_time", duration=t[ends])],
                     columns=rr.Scalars.columns(scalars=np.full(2, value)))


class Diagnosis:
    """What a diagnosing trace adds, for one scene: the model (or None),
    the check outcomes of every run (harness.conformance.Outcome; filtered
    per engine), ``checks`` metric -> contract.scene.Check, the per-frame
    contact cap."""

    def __init__(self, scene: Scene, outcomes: Sequence = (), checks: dict | None = None,
                 contact_cap: int = DEFAULT_CAP):
        self.scene = scene
        self.model = dg.reference_model(scene)
        self.outcomes = list(outcomes)
        self.checks = dict(checks or {})
        self.contact_cap = int(contact_cap)
        self.ghost = False
        self.predicted = dg.reference_series(self.model)

    # ---- layout ------------------------------------------------------------
    def thresholds(self) -> dict[str, float]:
        """Entity path -> bound drawn as a line: ``/metrics/threshold/
        <metric>/max`` (max + tolerance) and ``.../min`` (min - tolerance)
        of each check whose metric has a running series
        (diagnose.CROSSING_SERIES; "@" checks are left out: their run is
        another setting)."""
        out = {}
        for name, c in self.checks.items():
            if name not in dg.CROSSING_SERIES:
                continue
            if c.max is not None:
                out[f"/metrics/threshold/{name}/max"] = float(c.max + (c.tolerance or 0.0))
            if c.min is not None:
                out[f"/metrics/threshold/{name}/min"] = float(c.min - (c.tolerance or 0.0))
        return out

    def series(self, labels: Sequence[str]) -> dict[str, list[str]]:
        """Blueprint group -> entity path queries: energy, momentum,
        penetration, error, checks (the running check metrics against their
        thresholds), ``model:<unit>`` (the model's predictions against
        their measured twins)."""
        g: dict[str, list[str]] = {
            "energy": [p for lab in labels for p in (f"/metrics/{lab}/energy", f"/metrics/{lab}/energy_band/**")],
            "momentum": [f"/metrics/{lab}/momentum/**" for lab in labels],
            "penetration": [f"/metrics/{lab}/penetration" for lab in labels] if self.scene.has("contact") else [],
            "error": [f"/metrics/{lab}/error/**" for lab in labels] if self.model is not None else [],
            "checks": [],
        }
        for path in self.thresholds():
            name = path.split("/")[3]
            group = THRESHOLD_GROUP.get(name, "checks")
            if group == "checks":
                g["checks"] += [f"/metrics/{lab}/check/{name}" for lab in labels]
            if g[group] or group == "checks":
                g[group].append(path)
        g["checks"] = list(dict.fromkeys(g["checks"]))
        for rs in self.predicted:
            paths = g.setdefault(f"model:{rs.unit}", [])
            paths.append(f"{dg.PREDICTION_PATH}/{rs.key}")
            if rs.measure is not None:
                paths += [f"/metrics/{lab}/predicted/{rs.key}" for lab in labels]
        return g

    # ---- the ghost -----------------------------------------------------------
    def log_ghost(self, rec: rr.RecordingStream, steps: np.ndarray, t: np.ndarray, log_bodies) -> None:
        """/world/model/<body>: the model's trajectory at the given frames."""
        traj = dg.model_trajectory(self.model, self.scene, t)
        if traj is None:
            return
        self.ghost = True
        log_bodies(rec, "/world/model", self.scene, steps, t, traj[0], traj[1], GHOST_COLOR)

    def log_predictions(self, rec: rr.RecordingStream, steps: np.ndarray, t: np.ndarray, dt: float) -> None:
        """The model's scalar predictions: each ReferenceSeries at
        /metrics/model/<key> over the given frames, each predicted moment
        as a TextLog at /events/model at step round(t / dt), and both as
        text in the Markdown document /context/model."""
        for rs in self.predicted:
            y = dg.evaluate_series(rs.model, t)
            if y is not None:
                send_scalars(rec, f"{dg.PREDICTION_PATH}/{rs.key}", steps, t, y)
        if self.model is None:
            return
        t_end = float(t[-1]) if t.size else 0.0
        rec.log("/context/model", rr.TextDocument(dg.model_markdown(self.scene, self.model, t_end),
                                                  media_type=rr.MediaType.MARKDOWN), static=True)
        moments = dg.reference_moments(self.model, t_end)
        if moments:
            tm = np.array([m[0] for m in moments])
            st = np.rint(tm / dt).astype(np.int64) if dt and dt > 0 else np.searchsorted(t, tm)
            rec.send_columns("/events/model", indexes=time_columns(st, tm),
                             columns=rr.TextLog.columns(text=[f"model: {m[1]} at t = {m[0]:.6g} s" for m in moments],
                                                        level=["INFO"] * len(moments)))

    def log_thresholds(self, rec: rr.RecordingStream, steps: np.ndarray, t: np.ndarray) -> None:
        """/metrics/threshold/<metric>/{max,min}: the check's bound as a line over the run."""
        if not steps.size:
            return
        for path, bound in self.thresholds().items():
            _send_level(rec, path, steps, t, bound)

    def log_energy_band(self, rec: rr.RecordingStream, metrics_path: str, scene: Scene, tr, steps: np.ndarray,
                        t: np.ndarray, running: dict, energy: tuple) -> None:
        """``<metrics_path>/energy_band/<metric>/{upper,lower}`` (J): the
        energy checks' bounds on this run's energy plot, E0 +- bound x
        E_scale with this run's E0 and the metric's E_scale
        (``energy``: harness.metrics.relative_energy of ``tr``); only checks
        with a running series (not NaN for the scene)."""
        names = [n for n in self.checks if n in ENERGY_BAND and n in running]
        if not names or not steps.size:
            return
        _, E, scale = energy
        for name in names:
            for side, value in energy_band(name, self.checks[name], float(E[0]), scale).items():
                _send_level(rec, f"{metrics_path}/energy_band/{name}/{side}", steps, t, value)

    # ---- one run -------------------------------------------------------------
    def log_context_only(self, rec: rr.RecordingStream, lab: str, result) -> None:
        """/context/<lab> for a run with nothing to draw (unsupported, failed)."""
        mine = [o for o in self.outcomes if o.engine == result.engine]
        doc = dg.context_markdown(self.scene, result, mine, self.model)
        rec.log(f"/context/{lab}", rr.TextDocument(doc, media_type=rr.MediaType.MARKDOWN), static=True)

    def log_run(self, rec: rr.RecordingStream, engine_path: str, metrics_path: str, scene: Scene, result,
                tr, steps: np.ndarray, t: np.ndarray, pen, energy: tuple) -> None:
        """The diagnosis of one drawn run: momentum, error, contacts, check
        series, energy bands, predictions, events, context.  ``pen``: the
        run's contract.geometry.Penetration (None without contact);
        ``energy``: harness.metrics.relative_energy of ``tr``, computed once
        by the writer."""
        lab = engine_path.rsplit("/", 1)[1]
        P, L = momenta(scene, tr)
        send_scalars(rec, f"{metrics_path}/momentum/linear", steps, t, np.linalg.norm(P, axis=1))
        send_scalars(rec, f"{metrics_path}/momentum/angular", steps, t, np.linalg.norm(L, axis=1))
        err = None
        traj = dg.model_trajectory(self.model, scene, t)
        if traj is not None:
            err = dg.error_series(tr.pos, traj[0])  # (F, n)
            for i, b in enumerate(scene.bodies):
                if np.isfinite(traj[0][:, i]).all():
                    send_scalars(rec, body_entity(f"{metrics_path}/error", b), steps, t, err[:, i])
        mine = [o for o in self.outcomes if o.engine == result.engine]
        frame_max = pen.frame_max() if pen is not None else None
        # contacts: the harness's, then the engine's own
        if pen is not None:
            self._log_contacts(rec, f"{engine_path}/contacts", steps, t,
                               harness_contacts(scene, tr, self.contact_cap, pen=pen), HARNESS_CONTACT_COLOR,
                               time_columns)
        engine_note = ""
        if result.contacts is None:
            engine_note = "not recorded (the run was not traced with contacts, or the adapter cannot read them)"
        elif scene.has("contact"):
            F = tr.t.shape[0]
            eng = [(f, c) for f, c in result.contacts if f < F]
            self._log_contacts(rec, f"{engine_path}/engine_contacts", steps, t, eng, ENGINE_CONTACT_COLOR,
                               time_columns)
            engine_note = f"{len(eng)} frames with contacts at /world/{lab}/engine_contacts"
        running = dg.check_series(scene, tr, frame_max, err, energy=energy)
        self.log_energy_band(rec, metrics_path, scene, tr, steps, t, running, energy)
        for name in self.checks:
            if name in running and name not in THRESHOLD_GROUP:
                send_scalars(rec, f"{metrics_path}/check/{name}", steps, t, running[name])
        for rs in self.predicted:
            y = None if rs.measure is None else dg.evaluate_series(rs.measure, tr)
            if y is not None:
                send_scalars(rec, f"{metrics_path}/predicted/{rs.key}", steps, t, y)
        events = dg.find_events(scene, result, tr, penetration=frame_max, error=err, model=self.model,
                                outcomes=mine, checks=self.checks, series=running)
        if events:
            f = np.array([e.frame for e in events])
            rec.send_columns(f"/events/{lab}", indexes=time_columns(steps[f], t[f]),
                             columns=rr.TextLog.columns(text=[e.text for e in events],
                                                        level=[e.level for e in events]))
        doc = dg.context_markdown(scene, result, mine, self.model, engine_note)
        rec.log(f"/context/{lab}", rr.TextDocument(doc, media_type=rr.MediaType.MARKDOWN), static=True)

    @staticmethod
    def _log_contacts(rec, path: str, steps, t, per_frame: list, color, time_columns) -> None:
        """Points (Points3D) at ``path`` and normals scaled by depth
        (Arrows3D, vector = depth x normal) at ``path``/normals, one
        partition per frame with contacts."""
        per_frame = [(f, c) for f, c in per_frame if len(c)]
        if not per_frame:
            return
        f = np.array([x[0] for x in per_frame])
        lengths = np.array([len(x[1]) for x in per_frame])
        rows = np.concatenate([x[1] for x in per_frame])
        idx = time_columns(steps[f], t[f])
        rec.send_columns(path, indexes=idx, columns=rr.Points3D.columns(
            positions=rows[:, 0:3].astype(np.float32), colors=np.tile(color, (len(rows), 1))).partition(lengths))
        rec.send_columns(f"{path}/normals", indexes=idx, columns=rr.Arrows3D.columns(
            origins=rows[:, 0:3].astype(np.float32),
            vectors=(rows[:, 3:6] * rows[:, 6:7]).astype(np.float32)).partition(lengths))
