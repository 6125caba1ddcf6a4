"""No tunnelling: bodies must not pass through thin static geometry.

Definition of ``tunnelled``.  Every (body, static) pair is watched:

- a static **box** is a slab; its mid-plane is the plane through the box's
  centre normal to its thinnest axis.  The body's side is the sign of its
  centre's signed distance to that mid-plane.  The body has tunnelled if its
  centre crosses the mid-plane *within the face*: between two recorded
  frames on opposite sides, the crossing point (linear interpolation of the
  centre between them) projects inside the face's half-sizes.  A centre
  that reaches the other side around the edge of the slab -- a long body
  tipping over the edge, whose centre may cross within a bounding radius of
  the face -- does not count (an earlier window of face + bounding radius
  counted such tips: a spinning bar that skidded off its slab's edge was
  scored as tunnelling).
- a static **plane** is solid below, so the body has tunnelled if its centre
  ever goes below the surface (n . x < offset) having started above it.

A rigid body that cannot interpenetrate can never do either: its centre would
have to pass through the solid.  ``tunnelled`` is 1.0 if any pair tunnelled,
else 0.0; ``tunnelled_bodies`` counts the bodies that did.

``reflected_velocity_error`` (bullets).  Without gravity, a sphere whose
straight path meets a static box's face bounces by Newton's law of
restitution on a frictionless wall with normal n:

    v' = v - (1 + e) (v . n) n

(tangential part unchanged; e = the pair's restitution).  The metric is
max over such spheres of |v(T) - v'| / |v . n| at the last frame: 0.01 means
the outgoing velocity is off by 1 % of the normal approach speed.  A sphere
that tunnelled keeps v, an error of (1 + e).  Reported only when the scene has
no gravity and at least one sphere's path meets a box within the run.

params: ``statics`` (list of static names to watch; default all).
"""

from __future__ import annotations

import math

import numpy as np

from physbench.contract.rotation import quat_to_matrix
from physbench.harness.references import Param, ReferenceError, ReferenceModel, ReferenceSeries


class NoTunnelling(ReferenceModel):
    name = "no_tunnelling"
    summary = "bodies must not pass through thin static geometry; spheres bounce off walls by Newton's law"
    takes = "the watched statics (boxes as slabs, planes as half-spaces), every body's path, restitution"
    params = (Param("statics", "list of str", None, "names of the statics to watch (default: all)"),)
    produces = {
        "tunnelled": "1.0 if any body's centre crossed a watched slab within its face or went below a plane, else 0.0",
        "tunnelled_bodies": "how many bodies did",
        "reflected_velocity_error": "without gravity, max over spheres meeting a box of |v(T) - v'| / |v . n| (1)",
    }
    primary = "tunnelled"

    def __init__(self, scene):
        super().__init__(scene)
        statics = self.named("statics", scene.statics, "statics")
        if statics is None:
            statics = list(scene.statics)
        if not statics:
            raise ReferenceError("no_tunnelling needs at least one static to watch")
        if scene.n_bodies == 0:
            raise ReferenceError("no_tunnelling needs at least one body")
        self.statics = statics
        # per static: (centre c (3,), mid-plane normal n (3,), in-plane axes (2, 3), half-sizes (2,)) for
        # boxes; planes use (point on plane, normal, None, None).
        self.slabs = []
        for s in statics:
            if s.shape == "box":
                R = quat_to_matrix(s.orientation)
                k = int(np.argmin(s.half_extents))
                others = [i for i in range(3) if i != k]
                self.slabs.append(("box", s.position.copy(), R[:, k].copy(), R[:, others].T.copy(),
                                   s.half_extents[others].copy(), float(s.half_extents[k])))
            else:
                self.slabs.append(("plane", s.normal * s.offset, s.normal.copy(), None, None, 0.0))
        self.e_by_body = [
            {s.index: scene.pair(b.material, s.material).restitution for s in statics} for b in scene.bodies
        ]
        self._bullets = self._predict_bullets()

    # ---- bullets -----------------------------------------------------------
    def _predict_bullets(self):
        """For each sphere, if (without gravity) its straight path hits a box's
        face within the run: (body index, reference final velocity, |v.n|)."""
        sc = self.scene
        if np.any(sc.gravity != 0) or not sc.has("contact"):
            return []
        out = []
        for b in sc.bodies:
            if b.shape != "sphere":
                continue
            v = b.velocity
            if not np.any(v):
                continue
            best = None
            for s, (kind, c, n, axes, half, thick) in zip(self.statics, self.slabs):
                if kind != "box":
                    continue
                d0 = float((b.position - c) @ n)
                vn = float(v @ n)
                if d0 == 0 or vn == 0 or np.sign(vn) == np.sign(d0):
                    continue  # moving away or parallel
                # time when the sphere's surface reaches the face (|d| = thick + r)
                gap = abs(d0) - thick - b.radius
                t_hit = max(gap, 0.0) / abs(vn)
                if t_hit > sc.duration:
                    continue
                p = b.position + v * t_hit - c
                if np.any(np.abs(axes @ p) > half):
                    continue  # misses the face
                if best is None or t_hit < best[0]:
                    best = (t_hit, n, vn, self.e_by_body[b.index][s.index], s.name)
            if best is not None:
                t_hit, n, vn, e, wall = best
                out.append((b.index, v - (1.0 + e) * vn * n, abs(vn), t_hit, n, wall))
        return out

    # ---- predictions as lines ------------------------------------------------
    def tunnelled_count(self, trace) -> np.ndarray:
        """How many bodies have tunnelled by each frame (F,): the running
        form of ``tunnelled_bodies`` (its last value), a body counted from
        the frame :meth:`events` marks."""
        first = {}
        for f, i, _ in self.events(trace):
            first[i] = min(f, first.get(i, f))
        out = np.zeros(trace.pos.shape[0])
        for f in first.values():
            out[f:] += 1
        return out

    def reference_series(self) -> list[ReferenceSeries]:
        """The count of bodies that tunnelled (0 throughout), and for each
        bullet (a sphere whose straight path meets a box's face, no
        gravity) its velocity along the face normal: v.n before the hit,
        -e v.n after it (Newton's law on a frictionless wall)."""
        out = [ReferenceSeries("scene/tunnelled_bodies", "1", "bodies that passed through a watched static: 0",
                               lambda t: np.zeros(np.shape(t)), self.tunnelled_count)]
        for i, v_ref, _vn, t_hit, n, wall in self._bullets:
            name, before, after = self.scene.bodies[i].name, float(self.scene.bodies[i].velocity @ n), float(v_ref @ n)
            out.append(ReferenceSeries(
                f"{name}/normal_velocity", "m/s",
                f"{name} velocity along {wall}'s normal: {before:.6g} m/s, {after:.6g} m/s after the bounce",
                lambda t, t_hit=t_hit, before=before, after=after: np.where(np.asarray(t, float) < t_hit, before, after),
                lambda tr, i=i, n=n: tr.vel[:, i] @ n))
        return out

    def reference_times(self) -> list[tuple[float, str]]:
        return [(float(t_hit), f"{self.scene.bodies[i].name} hits {wall}") for i, _v, _vn, t_hit, _n, wall in self._bullets]

    def predictions(self) -> dict[str, str]:
        out = {"tunnelled": "0 bodies (none passes through " + ", ".join(s.name for s in self.statics) + ")"}
        for i, v_ref, _vn, t_hit, _n, wall in self._bullets:
            out[f"{self.scene.bodies[i].name} bounces off {wall}"] = (
                f"at t = {t_hit:.6g} s, leaving at {np.array2string(v_ref, precision=6)} m/s")
        return out

    # ---- metrics -------------------------------------------------------------
    def side_flips(self, trace) -> np.ndarray:
        """(n_bodies,) bool: which bodies tunnelled through a watched static."""
        flipped = np.zeros(trace.pos.shape[1], dtype=bool)
        for _s, bad in self._crossings(trace):
            with np.errstate(invalid="ignore"):
                flipped |= np.any(bad, axis=0)
        return flipped

    def events(self, trace) -> list[tuple[int, int, str]]:
        """(frame, body, text) of each body's first pass through each
        watched static: the first frame on the far side (a box) or below
        the surface (a plane)."""
        out = []
        for s, bad in self._crossings(trace):
            shift = 1 if s.shape == "box" else 0  # box rows are frame pairs (i, i+1)
            for i in np.nonzero(bad.any(axis=0))[0]:
                f = int(np.argmax(bad[:, i])) + shift
                where = "passed through" if s.shape == "box" else "went below"
                out.append((f, int(i), f"tunnelling: {self.scene.bodies[i].name} {where} {s.name} "
                                       f"(t = {float(trace.t[f]):.6g} s)"))
        return out

    def _crossings(self, trace):
        """Per watched static: (static, bad) with bad (F-1, n) bool for a box
        (frames i -> i+1 crossing the mid-plane within the face) or (F, n)
        for a plane (centre below the surface having started above)."""
        pos = trace.pos  # (F, n, 3)
        for s, (kind, c, n, axes, half, _thick) in zip(self.statics, self.slabs):
            rel = pos - c  # (F, n, 3)
            d = rel @ n  # (F, n)
            s0 = np.sign(d[0])
            if kind == "plane":
                with np.errstate(invalid="ignore"):
                    yield s, (s0[None, :] > 0) & (d < 0)
            else:
                # frames i -> i+1 on opposite sides, either way; a frame exactly
                # on the mid-plane (d = 0) takes the side it came from, so
                # + 0 - crosses at the 0 frame and + 0 + does not
                sgn = np.sign(d)
                idx = np.where(sgn != 0, np.arange(len(d))[:, None], 0)
                np.maximum.accumulate(idx, axis=0, out=idx)
                side = np.take_along_axis(sgn, idx, axis=0)  # last nonzero side up to each frame
                with np.errstate(invalid="ignore"):
                    cross = side[:-1] * d[1:] < 0  # (F-1, n)
                if not cross.any():
                    continue
                with np.errstate(invalid="ignore", divide="ignore"):
                    f = d[:-1] / (d[:-1] - d[1:])  # fraction of the way to the mid-plane
                    p = rel[:-1] + (rel[1:] - rel[:-1]) * f[..., None]  # (F-1, n, 3) crossing points
                    inside = np.all(np.abs(p @ axes.T) <= half[None, None, :], axis=-1)
                yield s, cross & inside

    def metrics(self, trace) -> dict[str, float]:
        flipped = self.side_flips(trace)
        out = {"tunnelled": 1.0 if flipped.any() else 0.0, "tunnelled_bodies": float(flipped.sum())}
        if self._bullets:
            errs = []
            for i, v_ref, vn, *_ in self._bullets:
                errs.append(float(np.linalg.norm(trace.vel[-1, i] - v_ref)) / vn)
            out["reflected_velocity_error"] = max(errs) if all(map(math.isfinite, errs)) else math.nan
        return out
