"""Shape formulas of the compile step: volumes and principal inertias of the
body shapes, and the expansion of a body's ``pattern`` into named positions."""

from __future__ import annotations

import math

import numpy as np

from physbench.contract.spec.schema import BodySection

def shape_volume(shape: str, radius: float, half_extents: np.ndarray | None, half_length: float) -> float:
    if shape == "sphere":
        return 4.0 / 3.0 * math.pi * radius**3
    if shape == "box":
        return 8.0 * float(np.prod(half_extents))
    if shape == "capsule":
        return math.pi * radius**2 * 2.0 * half_length + 4.0 / 3.0 * math.pi * radius**3
    return math.pi * radius**2 * 2.0 * half_length


def principal_inertia(shape: str, mass: float, radius: float, half_extents: np.ndarray | None, half_length: float) -> np.ndarray:
    """Principal moments (kg m^2) of a uniform solid about its centre, axes of
    the shape (capsule/cylinder along z)."""
    if shape == "sphere":
        i = 0.4 * mass * radius**2
        return np.array([i, i, i])
    if shape == "box":
        a, b, c = (float(x) for x in half_extents)
        return mass / 3.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    r, h = radius, half_length
    if shape == "cylinder":
        iz = 0.5 * mass * r * r
        ix = mass * (3 * r * r + (2 * h) ** 2) / 12.0
        return np.array([ix, ix, iz])
    # capsule: cylinder of length 2h plus two hemispheres sharing the mass by volume.
    vc = math.pi * r * r * 2 * h
    vs = 4.0 / 3.0 * math.pi * r**3
    mc = mass * vc / (vc + vs)
    ms = mass - mc
    iz = mc * r * r / 2 + ms * 2 * r * r / 5
    # each hemisphere: 83/320 m r^2 about its own centroid (3r/8 from the flat
    # face); moved to the capsule centre, the two together give
    # ms (2r^2/5 + h^2 + 3 h r / 4).
    ix = mc * (r * r / 4 + (2 * h) ** 2 / 12) + ms * (2 * r * r / 5 + h * h + 0.75 * h * r)
    return np.array([ix, ix, iz])


# --------------------------------------------------------------------------
# patterns


def _extent(b: BodySection) -> np.ndarray:
    """Half-size of the shape along world axes at its given orientation, taken
    as the axis-aligned half-size (patterns assume the identity orientation)."""
    if b.shape == "sphere":
        return np.full(3, b.radius)
    if b.shape == "box":
        return np.array(b.half_extents, float)
    return np.array([b.radius, b.radius, b.half_length + (b.radius if b.shape == "capsule" else 0.0)])


def expand_pattern(b: BodySection) -> list[tuple[str, np.ndarray]]:
    """Names and positions for a body entry's pattern (or the entry itself).

    column: ``count`` bodies up +z from ``position``; row: along +x;
    grid: ``counts`` [nx, ny, nz] along x, y, z; pyramid: ``count`` levels in
    the x-z plane, the base centred on ``position``; rack: a billiard triangle
    of ``count`` rows in the x-y plane, apex at ``position``, opening toward
    +x.  ``spacing`` is the centre distance (scalar or per axis); by default
    the shape's size plus ``gap``.
    """
    p0 = np.array(b.position, float)
    if b.pattern is None:
        return [(b.name, p0)]
    pat = b.pattern
    size = 2.0 * _extent(b) + pat.gap
    if pat.spacing is None:
        sp = size
    elif isinstance(pat.spacing, (int, float)):
        sp = np.full(3, float(pat.spacing))
    else:
        sp = np.array(pat.spacing, float)
    pts: list[np.ndarray] = []
    if pat.kind == "column":
        pts = [p0 + np.array([0, 0, k * sp[2]]) for k in range(pat.count)]
    elif pat.kind == "row":
        pts = [p0 + np.array([k * sp[0], 0, 0]) for k in range(pat.count)]
    elif pat.kind == "grid":
        nx, ny, nz = pat.counts
        pts = [p0 + np.array([i * sp[0], j * sp[1], k * sp[2]]) for k in range(nz) for j in range(ny) for i in range(nx)]
    elif pat.kind == "pyramid":
        n = pat.count
        for level in range(n):
            width = n - level
            for k in range(width):
                x = (k - (width - 1) / 2.0) * sp[0]
                pts.append(p0 + np.array([x, 0.0, level * sp[2]]))
    elif pat.kind == "rack":
        # rows of a triangle: row r has r+1 balls; rows spaced d*sqrt(3)/2 in x
        d = sp[0]
        for r in range(pat.count):
            for k in range(r + 1):
                pts.append(p0 + np.array([r * d * math.sqrt(3) / 2.0, (k - r / 2.0) * d, 0.0]))
    return [(f"{b.name}_{i}", p) for i, p in enumerate(pts)]

