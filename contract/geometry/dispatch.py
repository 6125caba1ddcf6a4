"""The dispatch table: which kernel measures which shape pair (the way MJX's
collision_driver holds only its table), the signed gap and depth of two
batches of placed shapes, and the per-pair depth functions of bodies and
statics over the frames of one pair."""

from __future__ import annotations

from typing import Callable

import numpy as np

from physbench.contract.scene_model import Body, Static
from physbench.contract.geometry.cylinder import _k_box_cylinder, _k_capsule_cylinder, _k_cylinder_cylinder
from physbench.contract.geometry.exact import (
    _k_box_box,
    _k_capsule_box,
    _k_capsule_capsule,
    _k_sphere_box,
    _k_sphere_capsule,
    _k_sphere_cylinder,
    _k_sphere_sphere,
)
from physbench.contract.geometry.placed import SHAPES, Placed, _ORDER, placed_body, placed_static_box
from physbench.contract.geometry.support import depth_body_plane

_CHUNK = 32768        # events per kernel call (bounds temporary memory)


#: Signed-gap kernels keyed by (shape_a, shape_b) in SHAPES order.
PAIR_KERNELS: dict[tuple[str, str], Callable[[Placed, Placed], np.ndarray]] = {
    ("sphere", "sphere"): _k_sphere_sphere,
    ("sphere", "capsule"): _k_sphere_capsule,
    ("sphere", "box"): _k_sphere_box,
    ("sphere", "cylinder"): _k_sphere_cylinder,
    ("capsule", "capsule"): _k_capsule_capsule,
    ("capsule", "box"): _k_capsule_box,
    ("capsule", "cylinder"): _k_capsule_cylinder,
    ("box", "box"): _k_box_box,
    ("box", "cylinder"): _k_box_cylinder,
    ("cylinder", "cylinder"): _k_cylinder_cylinder,
}


def signed_gap(A: Placed, B: Placed) -> np.ndarray:
    """Signed overlap (m, (N,)) of two batches of placed shapes: > 0 is the
    penetration depth; <= 0 no overlap.  NaN where no kernel covers the pair."""
    if _ORDER[A.kind] > _ORDER[B.kind]:
        A, B = B, A
    fn = PAIR_KERNELS.get((A.kind, B.kind))
    if fn is None:
        return np.full(A.n, np.nan)
    out = np.empty(A.n)
    for lo in range(0, A.n, _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        out[sl] = fn(A.take(sl), B.take(sl)) if A.n > _CHUNK else fn(A, B)
    return out


def pair_depth(A: Placed, B: Placed) -> np.ndarray:
    """Penetration depth (m, (N,), >= 0; NaN where unknown)."""
    return np.maximum(0.0, signed_gap(A, B))


# ---- per-pair tables (frames of one pair; kept for callers and tests) -------------

def _body_pair_fn(ka: str, kb: str) -> Callable[..., np.ndarray]:
    def fn(a: Body, b: Body, pa, qa, pb, qb) -> np.ndarray:
        """Depth (m, (F,)) between bodies a and b at poses (F, 3)/(F, 4) each."""
        return pair_depth(placed_body(a, np.atleast_2d(pa), np.atleast_2d(qa)),
                          placed_body(b, np.atleast_2d(pb), np.atleast_2d(qb)))
    fn.__name__ = f"depth_{ka}_{kb}"
    return fn


def _body_static_box(b: Body, s: Static, pos, quat) -> np.ndarray:
    """Depth (m, (F,)) of body b at poses pos (F, 3), quat (F, 4) in static box s."""
    G = placed_body(b, np.atleast_2d(pos), np.atleast_2d(quat))
    return pair_depth(G, placed_static_box(s, G.n))


def depth_sphere_sphere(a: Body, b: Body, pa, qa, pb, qb) -> np.ndarray:
    d = np.linalg.norm(np.asarray(pb) - np.asarray(pa), axis=-1)
    return np.maximum(0.0, a.radius + b.radius - d)


BODY_PAIRS: dict[tuple[str, str], Callable[..., np.ndarray]] = {
    (ka, kb): _body_pair_fn(ka, kb) for ka in SHAPES for kb in SHAPES
}
BODY_PAIRS[("sphere", "sphere")] = depth_sphere_sphere
STATIC_PAIRS: dict[tuple[str, str], Callable[..., np.ndarray]] = {}
for _k in SHAPES:
    STATIC_PAIRS[(_k, "plane")] = depth_body_plane
    STATIC_PAIRS[(_k, "box")] = _body_static_box
