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

from physbench.adapters.base import DT_SETTING, Capabilities, Setting
from physbench.adapters.planar import plane_line, planar_shape, static_box_pose
from physbench.adapters.pymunk_joints import JOINT_KINDS

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


def body_shape(pm: Any, body: Any, b: Any) -> Any:
    """The body's planar stand-in (:func:`adapters.planar.planar_shape`) as a
    pymunk shape (2D local (x, y)); no mass of its own."""
    p = planar_shape(b)
    if p.kind == "circle":
        return pm.Circle(body, p.radius)
    if p.kind == "box":
        return pm.Poly.create_box(body, (2.0 * p.half[0], 2.0 * p.half[1]), 0.0)
    return pm.Segment(body, (0.0, -p.half[1]), (0.0, p.half[1]), p.radius)  # capsule


def static_shape(pm: Any, static_body: Any, s: Any) -> Any:
    """A static plane (solid below n . x = offset) or box as a pymunk Poly in
    world 2D coordinates."""
    if s.shape == "plane":
        (p0x, p0y), (nx, ny) = plane_line(s)
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
    (cx, cy), angle, (hx, hz) = static_box_pose(s)
    ca, sa = math.cos(angle), math.sin(angle)
    verts = [(cx + ca * px - sa * py, cy + sa * px + ca * py)
             for px, py in ((-hx, -hz), (hx, -hz), (hx, hz), (-hx, hz))]
    return pm.Poly(static_body, verts, None, 0.0)
