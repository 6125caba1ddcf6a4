"""Contacts for traces: the harness's own deepest points, and bounding.

:func:`harness_contacts` turns the harness's penetration measurement
(:func:`contract.geometry.measure_penetration`, the same depths the metrics
use) into contact rows per frame, in the row layout of
:meth:`adapters.base.Adapter.contacts`: [point x, y, z (m), unit normal
x, y, z, depth (m, > 0)], (k, 7) per frame, only frames where some pair
overlaps, the ``cap`` deepest pairs per frame.

Normal and point of an overlapping pair A (body i) and B (body j or a
static).  The depth is the geometry module's (exact, see its table).  The
normal n points from A toward B and is the minimiser of the projection
overlap phi(n) = h_A(n) + h_B(n) - n . (c_B - c_A) (h the support function,
the geometry module's definition) over a candidate set: the plane's normal
for a plane (exact); else the centre line, each box's face normals, each
capsule or cylinder axis and the centre line's part across it, the cross
products of one shape's axes with the other's (a box's own cross into its own
face normals), and, when a shape is curved (sphere, capsule,
cylinder, except sphere-sphere whose centre line is exact), 128 directions
spread over the sphere.  For sphere-sphere, box-box (the 15 axes of the
separating-axis test) and body-plane the set holds the minimiser, so the
normal is exact; otherwise it is the best candidate (within ~10 degrees).
The point is midway between the two surfaces along n: A's support point
along n moved back by depth / 2.  Pinned by tests/test_trace_diagnose.py.
"""

from __future__ import annotations

import numpy as np

from physbench.contract.geometry import Placed, measure_penetration, placed_body, placed_static_box, projection_overlap
from physbench.contract.scene import Scene

DEFAULT_CAP = 32  # contact rows per frame kept in a trace
_N_SPREAD = 128


def _spread(n: int) -> np.ndarray:
    """n unit vectors (n, 3) spread evenly over the sphere (Fibonacci)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    a = np.pi * (1.0 + 5.0 ** 0.5) * k
    return np.stack([r * np.cos(a), r * np.sin(a), z], axis=1)


SPREAD = _spread(_N_SPREAD)


def _axes(G: Placed) -> list[np.ndarray]:
    """World axes (each (N, 3)) whose normals matter for G: a box's three
    face normals, a capsule's or cylinder's axis, none for a sphere."""
    if G.kind == "box":
        return [G.R[:, :, k] for k in range(3)]
    if G.kind in ("capsule", "cylinder"):
        return [G.axis]
    return []


def support_point(G: Placed, n: np.ndarray) -> np.ndarray:
    """The point of each shape furthest along unit n (N, 3) -> (N, 3) m."""
    if G.kind == "sphere":
        return G.c + G.radius[:, None] * n
    if G.kind == "box":
        s = np.sign(np.einsum("nij,ni->nj", G.R, n))  # body-frame signs of n
        return G.c + np.einsum("nij,nj->ni", G.R, s * G.half_extents)
    a = G.axis
    na = np.einsum("ni,ni->n", n, a)
    p = G.c + (G.half_length * np.sign(na))[:, None] * a
    if G.kind == "capsule":
        return p + G.radius[:, None] * n
    perp = n - na[:, None] * a
    norm = np.linalg.norm(perp, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        perp = np.where(norm > 1e-12, perp / norm, 0.0)
    return p + G.radius[:, None] * perp


def pair_normals(A: Placed, B: Placed) -> np.ndarray:
    """Unit normals (N, 3) from A toward B minimising phi over the candidate
    set of the module docstring."""
    d = B.c - A.c
    cand = [d]
    axes_a, axes_b = _axes(A), _axes(B)
    axes = axes_a + axes_b
    cand += axes
    for a in axes:
        cand.append(d - np.einsum("ni,ni->n", d, a)[:, None] * a)
    # cross products of one shape's axes with the other's: a box's own
    # face normals cross into each other (already candidates), and a
    # capsule or cylinder has one axis
    cand += [np.cross(a, b) for a in axes_a for b in axes_b]
    N = A.n
    n = np.stack(cand, axis=1)  # (N, M, 3)
    curved = {A.kind, B.kind} & {"sphere", "capsule", "cylinder"}
    if curved and not (A.kind == "sphere" and B.kind == "sphere"):
        n = np.concatenate([n, np.broadcast_to(SPREAD, (N,) + SPREAD.shape)], axis=1)
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    # orient every candidate toward B (phi(-n) >= phi(n) when n . d >= 0)
    sgn = np.where(np.einsum("nmi,ni->nm", n, d) < 0, -1.0, 1.0)
    n = n * sgn[..., None]
    phi = projection_overlap(A, B, d, n)
    phi = np.where(np.isfinite(phi) & (norm[..., 0] > 1e-12), phi, np.inf)
    best = np.argmin(phi, axis=1)
    return n[np.arange(N), best]


def harness_contacts(scene: Scene, trace, cap: int = DEFAULT_CAP, pen=None) -> list[tuple[int, np.ndarray]]:
    """[(frame, rows (k, 7))] for the frames where some pair overlaps, the
    ``cap`` deepest pairs each, deepest first (layout in the module
    docstring).  ``pen``: a :class:`contract.geometry.Penetration` of this
    trace if the caller has one."""
    if pen is None:
        pen = measure_penetration(scene, trace)
    ok = np.isfinite(pen.depths) & (pen.depths > 0)
    frames, cols, depths = pen.frames[ok], pen.cols[ok], pen.depths[ok]
    if not frames.size:
        return []
    # the cap deepest per frame: sort by (frame, -depth), rank within frame
    order = np.lexsort((-depths, frames))
    frames, cols, depths = frames[order], cols[order], depths[order]
    first = np.r_[0, np.nonzero(np.diff(frames))[0] + 1]
    rank = np.arange(frames.size) - np.repeat(first, np.diff(np.r_[first, frames.size]))
    keep = rank < cap
    frames, cols, depths = frames[keep], cols[keep], depths[keep]
    rows = np.empty((frames.size, 7))
    rows[:, 6] = depths
    for col in np.unique(cols):
        sel = np.nonzero(cols == col)[0]
        i, kind, j = pen.pairs[col]
        f = frames[sel]
        A = placed_body(scene.bodies[i], trace.pos[f, i], trace.quat[f, i])
        if kind == "static" and scene.statics[j].shape != "box":
            s = scene.statics[j]
            n = np.broadcast_to(-np.asarray(s.normal, float), (sel.size, 3))  # into the solid
        else:
            B = (placed_static_box(scene.statics[j], sel.size) if kind == "static"
                 else placed_body(scene.bodies[j], trace.pos[f, j], trace.quat[f, j]))
            n = pair_normals(A, B)
        rows[sel, 3:6] = n
        rows[sel, 0:3] = support_point(A, n) - 0.5 * depths[sel, None] * n
    starts = np.r_[0, np.nonzero(np.diff(frames))[0] + 1, frames.size]
    return [(int(frames[a]), rows[a:b]) for a, b in zip(starts[:-1], starts[1:])]
