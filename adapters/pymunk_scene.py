"""What of a scene pymunk can hold, and as what: pymunk's settings and
capabilities, the planar checks the spec validator does not make, and each
body or static as a Chipmunk shape (its x-z cross-section; layout and
reasons in the module docstring of :mod:`adapters.pymunk`).  Pinned by
tests/test_adapter_pymunk.py (shapes resting at their heights, slopes,
geometry off the plane unsupported).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from physbench.adapters.base import DT_SETTING, Capabilities, Setting, Unsupported
from physbench.adapters.pymunk_joints import JOINT_KINDS
from physbench.contract.conventions import planar_from_world, world_point_to_planar
from physbench.contract.scene import Scene

# Static plane as a thick polygon: half-length along the line and depth into
# the solid side (m).
PLANE_HALF_LENGTH = 1.0e3
PLANE_DEPTH = 1.0e3


_SHAPES = frozenset({"sphere", "box", "capsule", "cylinder"})
_STATIC_SHAPES = frozenset({"plane", "slope", "box"})
_EFFECTS = frozenset({"gravity", "contact", "restitution", "friction", "spring", "damper",
                      "drag_linear", "drag_quadratic"})

SHAPES = frozenset({"sphere", "box", "capsule", "cylinder"})
STATIC_SHAPES = frozenset({"plane", "slope", "box"})
EFFECTS = frozenset({"gravity", "contact", "restitution", "friction", "spring", "damper",
                     "drag_linear", "drag_quadratic"})


def _settings() -> dict[str, Setting]:
    return {
        "dt": DT_SETTING,
        "iterations": Setting(
            "iterations", 10, int,
            "contact/joint solver iterations per engine step (pymunk default 10)", lo=1, hi=10000),
        "substeps": Setting(
            "substeps", 1, int,
            "engine steps per physbench step: each step() calls space.step(dt / substeps) "
            "this many times", lo=1, hi=10000),
        "collision_slop": Setting(
            "collision_slop", 1e-3, float,
            "overlap (m) that is tolerated and never pushed out; pymunk's default 0.1 is "
            "10 cm in SI units, far too loose", lo=0.0, hi=1.0),
        "collision_bias": Setting(
            "collision_bias", (1.0 - 0.1) ** 60, float,
            "fraction of the overlap beyond collision_slop left after one second of "
            "correction (pymunk default (1 - 0.1)^60 ~ 0.0018)", lo=0.0, hi=1.0),
    }


def declaration(engine: str, version: str, available: bool, why: str) -> Capabilities:
    """pymunk's capabilities; ``available``/``why`` from the import."""
    return Capabilities(
        engine=engine,
        version=version,
        dimensions=2,
        shapes=SHAPES,
        static_shapes=STATIC_SHAPES,
        effects=EFFECTS | {"joint"},
        joint_kinds=JOINT_KINDS,
        settings=_settings(),
        available=available,
        unavailable_reason=why,
        notes=(
            "2D engine: planar scenes (x-z plane) only",
            "pair friction and elasticity are products of per-shape values",
            "position-first integration: x' = x + v dt, then v' = v + a dt",
            "no continuous collision detection",
        ),
    )


def planar_geometry_reason(scene: Scene) -> str | None:
    """Planar checks the spec validator does not make (pattern positions,
    spring anchors, static boxes off the plane)."""
    for b in scene.bodies:
        if abs(float(b.position[1])) > 0.0:
            return f"pymunk is 2D: body {b.name} lies off the x-z plane (y = {float(b.position[1])!r})"
    for k, sp in enumerate(scene.springs):
        if abs(float(sp.anchor_a[1])) > 0.0 or abs(float(sp.anchor_b[1])) > 0.0:
            return f"pymunk is 2D: spring[{k}] has an anchor off the x-z plane (y != 0)"
    for s in scene.statics:
        if s.shape == "box" and abs(float(s.position[1])) >= float(s.half_extents[1]):
            return f"pymunk is 2D: static box {s.name} does not cross the x-z plane"
    return None


def body_shape(pm: Any, body: Any, b: Any) -> Any:
    """The body's x-z cross-section as a pymunk shape (body-local (x, z) ->
    2D local (x, y)); no mass of its own."""
    if b.shape == "sphere":
        return pm.Circle(body, float(b.radius))
    if b.shape == "box":
        hx, hz = float(b.half_extents[0]), float(b.half_extents[2])
        return pm.Poly.create_box(body, (2.0 * hx, 2.0 * hz), 0.0)
    if b.shape == "capsule":
        h = float(b.half_length)
        return pm.Segment(body, (0.0, -h), (0.0, h), float(b.radius))
    if b.shape == "cylinder":
        return pm.Poly.create_box(body, (2.0 * float(b.radius), 2.0 * float(b.half_length)), 0.0)
    raise Unsupported(f"pymunk adapter has no shape {b.shape}")  # pragma: no cover


def static_shape(pm: Any, static_body: Any, s: Any) -> Any:
    """A static plane (solid below n . x = offset) or box as a pymunk Poly in
    world 2D coordinates."""
    if s.shape == "plane":
        nx, ny = world_point_to_planar(s.normal)
        p0x, p0y = s.offset * nx, s.offset * ny
        tx, ty = -ny, nx  # along the line
        L, D = PLANE_HALF_LENGTH, PLANE_DEPTH
        verts = [
            (p0x - L * tx, p0y - L * ty),
            (p0x + L * tx, p0y + L * ty),
            (p0x + L * tx - D * nx, p0y + L * ty - D * ny),
            (p0x - L * tx - D * nx, p0y - L * ty - D * ny),
        ]
        return pm.Poly(static_body, verts, None, 0.0)
    # box: x-z cross-section, turned by its planar angle about y
    (cx, cy), _, angle, _ = planar_from_world(s.position, np.zeros(3), s.orientation, np.zeros(3))
    hx, hz = float(s.half_extents[0]), float(s.half_extents[2])
    ca, sa = math.cos(angle), math.sin(angle)
    verts = [(cx + ca * px - sa * py, cy + sa * px + ca * py)
             for px, py in ((-hx, -hz), (hx, -hz), (hx, hz), (-hx, hz))]
    return pm.Poly(static_body, verts, None, 0.0)
