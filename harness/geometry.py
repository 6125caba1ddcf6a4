"""The harness's own geometry: overlap depth between shapes, from body states.

Metrics never trust an engine's contact report (MuJoCo's and pybullet's lag
one integration); penetration is measured here from recorded positions and
orientations, the same code for every engine.

``penetration_depths(scene, trace)`` returns (F, P) overlap depths (m, >= 0)
for the P candidate pairs.  Depth functions live in a table keyed by shape
pair; each is vectorised over frames: inputs are (F, 3) positions and (F, 4)
wxyz quaternions of the two shapes (statics broadcast), output (F,).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from adapters.conventions import quat_rotate
from harness.scene import Body, Scene, Static

_BOX_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)


# ---- body vs plane --------------------------------------------------------
# A plane is {x : n.x = d}, solid on the side n.x < d.  The depth of a convex
# shape is d - min over the shape of n.x (its support point toward -n).

def _support_height(b: Body, pos: np.ndarray, quat: np.ndarray, n: np.ndarray) -> np.ndarray:
    """min over the shape of n . x, for frames (F,)."""
    c = pos @ n
    if b.shape == "sphere":
        return c - b.radius
    if b.shape == "box":
        corners = _BOX_CORNERS * b.half_extents  # (8, 3) body frame
        world = quat_rotate(quat[:, None, :], corners[None, :, :])  # (F, 8, 3)
        return c + (world @ n).min(axis=1)
    axis = quat_rotate(quat, np.array([0.0, 0.0, 1.0]))  # (F, 3)
    an = axis @ n
    if b.shape == "capsule":
        return c - b.half_length * np.abs(an) - b.radius
    # cylinder: lowest point of the end-cap rims
    radial = np.sqrt(np.clip(1.0 - an * an, 0.0, None))
    return c - b.half_length * np.abs(an) - b.radius * radial


def depth_body_plane(b: Body, s: Static, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    return np.maximum(0.0, s.offset - _support_height(b, pos, quat, s.normal))


# ---- body vs body -----------------------------------------------------------

def depth_sphere_sphere(a: Body, b: Body, pa, qa, pb, qb) -> np.ndarray:
    d = np.linalg.norm(pb - pa, axis=-1)
    return np.maximum(0.0, a.radius + b.radius - d)


BODY_PAIRS: dict[tuple[str, str], Callable[..., np.ndarray]] = {
    ("sphere", "sphere"): depth_sphere_sphere,
}
STATIC_PAIRS: dict[tuple[str, str], Callable[..., np.ndarray]] = {
    (shape, "plane"): depth_body_plane for shape in ("sphere", "box", "capsule", "cylinder")
}


def penetration_depths(scene: Scene, trace) -> np.ndarray:
    """Overlap depth (m) per frame and candidate pair: array (F, P).

    Pairs whose shapes the table does not cover yet contribute NaN columns
    (ignored by nan-aware reductions) rather than a silent zero.
    """
    F = trace.pos.shape[0]
    cols: list[np.ndarray] = []
    bodies = scene.bodies
    for i, a in enumerate(bodies):
        for s in scene.statics:
            fn = STATIC_PAIRS.get((a.shape, s.shape))
            cols.append(fn(a, s, trace.pos[:, i], trace.quat[:, i]) if fn else np.full(F, np.nan))
    if len(bodies) > 1:
        # cull pairs that never come within bounding-sphere reach
        r = np.array([b.bounding_radius for b in bodies])
        for i in range(len(bodies)):
            d = np.linalg.norm(trace.pos[:, i + 1:] - trace.pos[:, i:i + 1], axis=-1)  # (F, n-i-1)
            near = np.nonzero((d <= (r[i] + r[i + 1:])[None, :]).any(axis=0))[0]
            for k in near:
                j = i + 1 + int(k)
                a, b = bodies[i], bodies[j]
                fn = BODY_PAIRS.get((a.shape, b.shape))
                swap = False
                if fn is None:
                    fn = BODY_PAIRS.get((b.shape, a.shape))
                    swap = True
                if fn is None:
                    cols.append(np.full(F, np.nan))
                elif swap:
                    cols.append(fn(b, a, trace.pos[:, j], trace.quat[:, j], trace.pos[:, i], trace.quat[:, i]))
                else:
                    cols.append(fn(a, b, trace.pos[:, i], trace.quat[:, i], trace.pos[:, j], trace.quat[:, j]))
    if not cols:
        return np.zeros((F, 0))
    return np.stack(cols, axis=1)
