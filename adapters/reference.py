"""Adapter for physbench's in-house reference engine (``engine/``).

The engine uses the same conventions (SI, Z up, wxyz, world-frame
velocities) but imports nothing of the harness: :func:`scene_input`
translates the Scene into the engine's own input (``engine.model.SceneInput``:
arrays over bodies and statics, and pair tables over the scene's materials);
read_state copies the state arrays.  ``stages()`` exposes the
engine's per-stage profile: {stage: {"calls": int, "cpu_s": float}} plus
counters (contact rows, impacts, time-of-impact iterations).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.base import DT_SETTING, Adapter, Capabilities, Setting, Unsupported
from physbench.contract.scene import Scene


def scene_input(scene: Scene):
    """The engine's input (:class:`engine.model.SceneInput`) for ``scene``:
    per-body and per-static arrays, and the pair coefficients
    (``Scene.pair``, with the static friction at least the kinetic one) over
    every pair of the materials the bodies and statics use."""
    from physbench.engine.model import SceneInput

    bodies, statics = scene.bodies, sorted(scene.statics, key=lambda s: s.index)
    if [s.index for s in statics] != list(range(len(statics))):
        raise ValueError("scene statics must be indexed 0..n_statics-1")
    names = sorted({b.material for b in bodies} | {s.material for s in statics})
    mid = {m: i for i, m in enumerate(names)}
    M = len(names)
    tabs = np.zeros((4, M, M))
    for i, ma in enumerate(names):
        for j, mb in enumerate(names):
            m = scene.pair(ma, mb)
            tabs[:, i, j] = (m.restitution, max(m.static_friction, m.friction), m.friction, m.rolling_friction)
    n, ns = len(bodies), len(statics)
    half = np.zeros((n, 3))
    for b in bodies:
        if b.half_extents is not None:
            half[b.index] = b.half_extents
    x, q, v, w = scene.initial_state()

    def col(get, k: int, rows, width: int | None = None, default=0.0):
        shape = (k,) if width is None else (k, width)
        out = np.full(shape, default, float)
        for i, r in enumerate(rows):
            val = get(r)
            if val is not None:
                out[i] = val
        return out

    sp = scene.springs
    return SceneInput(
        dt=float(scene.dt), effects=frozenset(scene.effects), gravity=np.array(scene.gravity, float),
        shape=tuple(b.shape for b in bodies), mass=scene.masses, inertia=scene.inertias,
        radius=col(lambda b: b.radius, n, bodies), half_extents=half,
        half_length=col(lambda b: b.half_length, n, bodies),
        bound_radius=col(lambda b: b.bounding_radius, n, bodies),
        min_extent=col(lambda b: b.min_extent, n, bodies),
        drag_linear=col(lambda b: b.drag_linear, n, bodies), drag_quadratic=col(lambda b: b.drag_quadratic, n, bodies),
        material=np.array([mid[b.material] for b in bodies], np.int64), x=x, q=q, v=v, w=w,
        static_shape=tuple(s.shape for s in statics),
        static_material=np.array([mid[s.material] for s in statics], np.int64),
        static_normal=col(lambda s: s.normal, ns, statics, 3), static_offset=col(lambda s: s.offset, ns, statics),
        static_position=col(lambda s: s.position, ns, statics, 3),
        static_orientation=np.array([(1.0, 0.0, 0.0, 0.0) if s.orientation is None else s.orientation
                                     for s in statics], float).reshape(ns, 4),
        static_half_extents=col(lambda s: s.half_extents, ns, statics, 3),
        spring_a=np.array([s.a for s in sp], np.int64), spring_b=np.array([s.b for s in sp], np.int64),
        spring_anchor_a=np.array([s.anchor_a for s in sp], float).reshape(-1, 3),
        spring_anchor_b=np.array([s.anchor_b for s in sp], float).reshape(-1, 3),
        spring_k=np.array([s.stiffness for s in sp], float), spring_rest=np.array([s.rest_length for s in sp], float),
        spring_c=np.array([s.damping for s in sp], float),
        pair_e=tabs[0], pair_mus=tabs[1], pair_muk=tabs[2], pair_mur=tabs[3], scene=scene,
        joints=tuple((j.kind, j.body, j.other, j.anchor_body, j.anchor_other, j.axis_body, j.axis_other)
                     for j in getattr(scene, "joints", ())),
    )


def engine_for(scene: Scene, settings: dict[str, Any] | None = None):
    """An :class:`engine.Engine` for the harness ``scene`` (settings over
    the engine's defaults)."""
    from physbench.engine import Engine

    return Engine(scene_input(scene), settings)


def _settings() -> dict[str, Setting]:
    from physbench.engine import SETTINGS

    out = {"dt": DT_SETTING}
    for name, (default, kind, doc, allowed) in SETTINGS.items():
        if kind is str:
            out[name] = Setting(name, default, str, doc, choices=tuple(allowed))
        elif kind is bool:
            out[name] = Setting(name, default, bool, doc)
        else:
            lo, hi = allowed
            out[name] = Setting(name, default, kind, doc, lo=lo, hi=hi)
    return out


def _joint_kinds() -> frozenset[str]:
    from physbench.engine import JOINT_KINDS  # engine/settings.py: no numba

    return frozenset(JOINT_KINDS)


class ReferenceAdapter(Adapter):
    name = "reference"

    @classmethod
    def capabilities(cls) -> Capabilities:
        from physbench.engine import version

        return Capabilities(
            engine="reference",
            version=f"physbench-{version()}",
            dimensions=3,
            shapes=frozenset({"sphere", "box", "capsule", "cylinder"}),
            static_shapes=frozenset({"plane", "slope", "box"}),
            effects=frozenset({"gravity", "contact", "restitution", "friction", "rolling_friction", "drag_linear",
                               "drag_quadratic", "spring", "damper", "gyroscopic", "joint"}),
            joint_kinds=_joint_kinds(),
            settings=_settings(),
            notes=("every shape pair collides, and each shape with every static (plane, slope, box)",),
        )

    @classmethod
    def pending_compile(cls, scene: Scene, settings: dict[str, Any]) -> dict[str, float]:
        """The kernel groups a build of ``scene`` takes (engine.jit.parts,
        then its fused step's, engine.jit.fused_part) that are not in the
        on-disk cache yet, by name, with their CPU seconds
        (engine.jit.cold_seconds, the engine's own marks); empty for a scene
        with joints (its kernels are not taken under the groups' locks) or
        one that does not build."""
        try:
            from physbench.engine.jit import cold_seconds, fused_part, parts
            from physbench.engine.model import build_model

            model = build_model(scene_input(scene), settings)
            if model.joints is not None:
                return {}
            fused = fused_part(model)
            groups = parts(model) + ((fused,) if fused is not None else ())
            return {repr(p): s for p in groups if (s := float(cold_seconds([p]))) > 0}
        except Exception:
            return {}

    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        from physbench.engine.collision import unsupported_pairs
        from physbench.engine.jit import helped
        from physbench.engine.model import build_model
        from physbench.engine.pipeline import build_pipeline, prepare
        from physbench.engine.profile import Profile
        from physbench.engine.state import State

        from physbench.engine.joints.table import unsupported_reason as joint_reason

        inp = scene_input(scene)
        self.model = build_model(inp, settings)
        why = joint_reason(self.model)
        if why:
            raise Unsupported(why)
        missing = unsupported_pairs(self.model)
        if missing:
            raise Unsupported(f"reference engine has no narrow phase for {', '.join(missing)}")
        self.state = State.from_model(self.model)
        with helped(inp, settings, self.model):  # (a cold cache: a helper process compiles at once)
            self.pipeline = build_pipeline(self.model)
        self.profile = Profile()
        for s in self.pipeline:
            self.profile.register(s.name)
        # what the first steps would make on first use (the context, the
        # plan, kept packs and colliders), made here: a short run's steps
        # do not pay for it
        prepare(self.model, self.state, self.pipeline, self.profile)
        self.info["pipeline"] = [s.name for s in self.pipeline]
        if settings.get("contact_model") == "penalty":
            self.notes.append("penalty contacts: regularised Coulomb friction, no separate static friction; no CCD")
            self.contact_forces_reason = "penalty contacts keep no per-contact forces the adapter can read"

    def step(self, n: int = 1) -> None:
        from physbench.engine.pipeline import advance

        # the steady steps n at a time in one compiled call (engine/fused/loop.py)
        advance(self.model, self.state, self.pipeline, self.profile, n)

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """As the base class's loop of step(1) and read_state, the steady
        steps recorded inside the engine's compiled loop (engine/fused/loop.py);
        ``block_done`` counts the rows written."""
        from physbench.engine.pipeline import advance

        self.block_done = 0
        done = [0]
        try:
            advance(self.model, self.state, self.pipeline, self.profile, n, (pos, quat, vel, angvel), done)
        finally:
            self.block_done = done[0]

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        s = self.state
        pos[...] = s.x
        quat[...] = s.q
        vel[...] = s.v
        angvel[...] = s.w

    def stages(self) -> dict[str, Any]:
        return self.profile.as_dict() if hasattr(self, "profile") else {}

    def contacts(self) -> np.ndarray | None:
        """The contact rows (engine.state.Contacts) of the last step, read
        from the step context the pipeline keeps on the state: point midway
        between the surfaces, normal from body a toward b, depth = -gap;
        None if the engine keeps them in another form."""
        ctx = getattr(getattr(self, "state", None), "ctx", None)
        if ctx is None:
            return None
        c = getattr(ctx, "contacts", None)
        if c is None:
            return np.empty((0, 7))
        try:
            return np.column_stack([c.point, c.normal, -np.asarray(c.gap)]).reshape(-1, 7)
        except AttributeError:
            return None

    def contact_forces(self) -> dict[str, np.ndarray] | None:
        """Per contact patch (a pair's points: the engine's friction acts
        on the patch, its cone on the sum of the points' normal forces),
        from the warm-start cache the step's solve left (engine/contact/
        warm.py: the points' normal forces ``fn`` N and the pair's friction
        force ``ft`` N, applied +to b, -to a) and the step's contact rows
        (normal a -> b, gap): lam_n the sum of the points' normal forces,
        lam_t the friction force on b, the point the mean of the pair's
        contact points, the gap their smallest.  No cache after a step
        (a sliver step before an impact stores none): no rows."""
        if self.contact_forces_reason.startswith("penalty"):
            return None
        st = getattr(self, "state", None)
        ctx = getattr(st, "ctx", None)
        c = getattr(ctx, "contacts", None)
        w = getattr(st, "warm", None)
        if w is None or c is None or len(w.pairs) == 0 or c.m == 0:
            return _NO_FORCES
        from physbench.engine.contact.topology import _pair_codes

        m = self.model
        n, ns = m.n, m.n_statics
        codes = _pair_codes(m, c)
        keep = np.isin(codes, w.pairs)
        uniq, inv = np.unique(codes[keep], return_inverse=True)  # sorted, as w.pairs
        at = np.searchsorted(w.pairs, uniq)
        k = uniq.size
        cnt = np.bincount(inv, minlength=k).astype(float)
        point = np.stack([np.bincount(inv, c.point[keep][:, j], k) for j in range(3)], axis=1) / cnt[:, None]
        nrm = np.stack([np.bincount(inv, c.normal[keep][:, j], k) for j in range(3)], axis=1)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        gap = np.full(k, np.inf)
        np.minimum.at(gap, inv, np.asarray(c.gap)[keep])
        wl = np.searchsorted(w.pairs, w.codes)  # each cached point's pair
        lam_n = np.bincount(wl, w.fn, w.pairs.size)[at]
        ft = np.asarray(w.ft, float)[at]
        lam_t = ft - np.sum(ft * nrm, axis=1, keepdims=True) * nrm
        sidx = uniq % (ns + 1) - 1
        q = uniq // (ns + 1)
        b = q % (n + 1)
        a = q // (n + 1)
        return {"a": a.astype(np.int64), "b": np.where(b >= n, -1, b).astype(np.int64),
                "static": sidx.astype(np.int64), "point": point, "normal": nrm, "gap": gap, "lam_n": lam_n,
                "lam_t": lam_t}

    def close(self) -> None:
        pass


_NO_FORCES = {"a": np.zeros(0, np.int64), "b": np.zeros(0, np.int64), "static": np.zeros(0, np.int64),
              "point": np.zeros((0, 3)), "normal": np.zeros((0, 3)), "gap": np.zeros(0), "lam_n": np.zeros(0),
              "lam_t": np.zeros((0, 3))}
