"""Adapter for physbench's in-house reference engine (``engine/``).

Thin: the engine builds from the engine-neutral Scene directly and uses the
same conventions (SI, Z up, wxyz, world-frame velocities), so there is no
conversion; read_state copies the state arrays.  ``stages()`` exposes the
engine's per-stage profile: {stage: {"calls": int, "cpu_s": float}} plus
counters (contact rows, impacts, time-of-impact iterations).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from adapters.base import DT_SETTING, Adapter, Capabilities, Setting, Unsupported
from harness.scene import Scene


def _settings() -> dict[str, Setting]:
    from engine import SETTINGS

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


class ReferenceAdapter(Adapter):
    name = "reference"

    @classmethod
    def capabilities(cls) -> Capabilities:
        from engine import version

        return Capabilities(
            engine="reference",
            version=f"physbench-{version()}",
            dimensions=3,
            shapes=frozenset({"sphere", "box", "capsule", "cylinder"}),
            static_shapes=frozenset({"plane", "slope", "box"}),
            effects=frozenset({"gravity", "contact", "restitution", "friction", "rolling_friction", "drag_linear",
                               "drag_quadratic", "spring", "damper", "gyroscopic"}),
            settings=_settings(),
            notes=("every shape pair collides, and each shape with every static (plane, slope, box)",),
        )

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        reason = super().unsupported_reason(scene)
        if reason is not None:
            return reason
        return None

    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        from engine.model import build_model
        from engine.narrowphase import unsupported_pairs
        from engine.pipeline import build_pipeline
        from engine.profile import Profile
        from engine.state import State

        self.model = build_model(scene, settings)
        missing = unsupported_pairs(self.model)
        if missing:
            raise Unsupported(f"reference engine has no narrow phase for {', '.join(missing)}")
        self.state = State.from_model(self.model)
        self.pipeline = build_pipeline(self.model)
        self.profile = Profile()
        for s in self.pipeline:
            self.profile.register(s.name)
        self.info["pipeline"] = [s.name for s in self.pipeline]
        if settings.get("contact_model") == "penalty":
            self.notes.append("penalty contacts: regularised Coulomb friction, no separate static friction; no CCD")

    def step(self, n: int = 1) -> None:
        from engine.pipeline import step

        m, s, st, p = self.model, self.state, self.pipeline, self.profile
        for _ in range(n):
            step(m, s, st, p)

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
        ctx = getattr(getattr(self, "state", None), "_ctx", None)
        if ctx is None:
            return None
        c = getattr(ctx, "contacts", None)
        if c is None:
            return np.empty((0, 7))
        try:
            return np.column_stack([c.point, c.normal, -np.asarray(c.gap)]).reshape(-1, 7)
        except AttributeError:
            return None

    def close(self) -> None:
        pass
