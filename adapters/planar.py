"""The planar stand-ins of the 2D engines (pymunk, Box2D): what each 3D
shape of a planar scene is in the x-z plane, decided once for both.

A planar body turns about world y and touches others in the x-z plane, so
a 2D engine holds its x-z cross-section through the centre (2D x = world x,
2D y = world z, :mod:`contract.conventions`):

- sphere -> circle of its radius;
- box -> box of half sizes (x, z);
- capsule (axis = body z) -> capsule from (0, -h) to (0, h), its radius;
- cylinder -> box 2r x 2h, its axial section (a planar cylinder's axis
  lies in the plane);
- static plane or slope -> its line (a point on it and its outward normal);
  each engine makes a thick solid below it;
- static box -> its x-z cross-section, turned by its planar angle.

Pinned by tests/test_adapter_pymunk.py and tests/test_adapter_box2d.py
(shapes resting at their heights, slopes, geometry off the plane).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from physbench.contract.conventions import planar_from_world, world_point_to_planar
from physbench.contract.scene import Scene


@dataclass(frozen=True)
class PlanarShape:
    """A body's stand-in in its 2D local frame: ``kind`` 'circle', 'box' or
    'capsule'; ``radius`` (m) of a circle or capsule, 0 for a box; ``half``
    (m): a box's half sizes along 2D x and y, a capsule's (0, half segment
    length along 2D y), (0, 0) for a circle."""

    kind: str
    radius: float
    half: tuple[float, float]


def planar_shape(b: Any) -> PlanarShape:
    """The x-z cross-section of scene body ``b`` (see the module docstring)."""
    if b.shape == "sphere":
        return PlanarShape("circle", float(b.radius), (0.0, 0.0))
    if b.shape == "box":
        return PlanarShape("box", 0.0, (float(b.half_extents[0]), float(b.half_extents[2])))
    if b.shape == "capsule":
        return PlanarShape("capsule", float(b.radius), (0.0, float(b.half_length)))
    if b.shape == "cylinder":  # its axial section
        return PlanarShape("box", 0.0, (float(b.radius), float(b.half_length)))
    raise ValueError(f"no planar stand-in for shape {b.shape!r}")  # pragma: no cover - the validator's shapes


def plane_line(s: Any) -> tuple[tuple[float, float], tuple[float, float]]:
    """((x, y) point on the line, (nx, ny) outward unit normal) in 2D of a
    static plane or slope (solid below n . x = offset)."""
    nx, ny = world_point_to_planar(s.normal)
    return (s.offset * nx, s.offset * ny), (nx, ny)


def static_box_pose(s: Any) -> tuple[tuple[float, float], float, tuple[float, float]]:
    """((x, y) centre, planar angle (rad, counter-clockwise), (hx, hz) half
    sizes) of a static box's x-z cross-section."""
    (cx, cy), _, angle, _ = planar_from_world(s.position, np.zeros(3), s.orientation, np.zeros(3))
    return (cx, cy), angle, (float(s.half_extents[0]), float(s.half_extents[2]))


def planar_geometry_reason(scene: Scene, engine: str) -> str | None:
    """Why a 2D engine cannot hold the scene's geometry, beyond what the
    spec validator checks (pattern positions, spring anchors, static boxes
    off the plane), or None."""
    for b in scene.bodies:
        if abs(float(b.position[1])) > 0.0:
            return f"{engine} is 2D: body {b.name} lies off the x-z plane (y = {float(b.position[1])!r})"
    for k, sp in enumerate(scene.springs):
        if abs(float(sp.anchor_a[1])) > 0.0 or abs(float(sp.anchor_b[1])) > 0.0:
            return f"{engine} is 2D: spring[{k}] has an anchor off the x-z plane (y != 0)"
    for s in scene.statics:
        if s.shape == "box" and abs(float(s.position[1])) >= float(s.half_extents[1]):
            return f"{engine} is 2D: static box {s.name} does not cross the x-z plane"
    return None
