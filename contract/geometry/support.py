"""Support functions h_X(n) of the body shapes, the overlap phi(n) of two
shapes' projections on n (the support function of the Minkowski difference
A - B, see contract/geometry/__init__.py), and the body-vs-plane family,
which is exact from the support function alone."""

from __future__ import annotations

import numpy as np

from physbench.contract.scene_model import Body, Static
from physbench.contract.geometry.placed import Placed, placed_body
from physbench.contract.geometry.vector import _norm

def _support(G: Placed, n: np.ndarray) -> np.ndarray:
    """h_G(n) = max over the shape of n . (x - c), for unit n (N, M, 3) -> (N, M)."""
    k = G.kind
    if k == "sphere":
        return np.broadcast_to(G.radius[:, None], n.shape[:-1])
    if k == "box":
        return np.einsum("nmi,ni->nm", np.abs(n @ G.R), G.half_extents)
    na = np.einsum("nmj,nj->nm", n, G.axis)
    h = G.half_length[:, None] * np.abs(na)
    if k == "capsule":
        return h + G.radius[:, None]
    if k == "cylinder":
        # |n - (n.a) a| rather than sqrt(1 - (n.a)^2): the latter cancels
        # catastrophically near the axis (an error of R sqrt(eps) ~ 1e-8 R).
        return h + G.radius[:, None] * _norm(n - na[..., None] * G.axis[:, None, :])
    raise ValueError(f"unknown shape {k!r}")


def projection_overlap(A: Placed, B: Placed, d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Overlap of the projections of A and B on unit n (N, M, 3) -> (N, M)."""
    return _support(A, n) + _support(B, n) - np.einsum("nmj,nj->nm", n, d)


# ---- body vs plane ----------------------------------------------------------------
# A plane is {x : n.x = d}, solid on the side n.x < d.  The depth of a convex
# shape is d - min over the shape of n.x = d - c.n + h(n).

def plane_gap(G: Placed, normal: np.ndarray, offset: float) -> np.ndarray:
    """Signed overlap (m, (N,)) of placed shapes with the plane: > 0 is the
    penetration depth, <= 0 minus the clearance."""
    nrm = np.broadcast_to(np.asarray(normal, float), (G.n, 1, 3))
    return offset - G.c @ np.asarray(normal, float) + _support(G, nrm)[:, 0]


def depth_body_plane(b: Body, s: Static, pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Depth (m, (F,)) of body ``b`` at poses pos (F, 3), quat (F, 4) below plane ``s``."""
    return np.maximum(0.0, plane_gap(placed_body(b, pos, quat), s.normal, s.offset))

