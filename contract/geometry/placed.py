"""Placed shapes: N shapes of one kind at their poses, the input of every
geometry kernel (contract/geometry/), and the scene's bodies and static boxes
turned into them."""

from __future__ import annotations

import numpy as np

from physbench.contract.rotation import quat_to_matrix, rotation_matrix
from physbench.contract.scene_model import Body, Static

#: body shapes in the canonical order of PAIR_KERNELS keys
SHAPES = ("sphere", "capsule", "box", "cylinder")
_ORDER = {k: i for i, k in enumerate(SHAPES)}


class Placed:
    """N placed shapes of one kind: centres ``c`` (N, 3) m, rotations ``R``
    (N, 3, 3) whose columns are the body axes in the world frame (None for
    spheres), and dimensions ``radius`` (N,), ``half_length`` (N,) (capsule and
    cylinder, along body z), ``half_extents`` (N, 3) (box).  Arrays may be
    broadcast views; kernels never write into them."""

    __slots__ = ("kind", "c", "R", "radius", "half_length", "half_extents")

    def __init__(self, kind: str, c: np.ndarray, R: np.ndarray | None = None, radius=0.0,
                 half_length=0.0, half_extents=None):
        n = c.shape[0]
        self.kind = kind
        self.c = c
        self.R = R
        self.radius = np.broadcast_to(np.asarray(radius, float), (n,))
        self.half_length = np.broadcast_to(np.asarray(half_length, float), (n,))
        he = np.zeros(3) if half_extents is None else np.asarray(half_extents, float)
        self.half_extents = np.broadcast_to(he, (n, 3))

    @property
    def n(self) -> int:
        return self.c.shape[0]

    @property
    def axis(self) -> np.ndarray:
        """(N, 3) world direction of body z (capsule/cylinder axis)."""
        return self.R[:, :, 2]

    def take(self, idx) -> "Placed":
        return Placed(self.kind, self.c[idx], None if self.R is None else self.R[idx],
                      self.radius[idx], self.half_length[idx], self.half_extents[idx])

    @classmethod
    def from_pose(cls, kind: str, pos: np.ndarray, quat: np.ndarray | None, radius=0.0,
                  half_length=0.0, half_extents=None) -> "Placed":
        """From positions (N, 3) and wxyz quaternions (N, 4) (normalised here:
        an engine's slightly non-unit quaternion means the unit one)."""
        R = None
        if kind != "sphere":
            q = np.asarray(quat, float)
            with np.errstate(invalid="ignore", divide="ignore"):
                q = q / np.linalg.norm(q, axis=-1, keepdims=True)
            R = quat_to_matrix(q)
        return cls(kind, np.asarray(pos, float), R, radius, half_length, half_extents)


def placed_body(b: Body, pos: np.ndarray, quat: np.ndarray) -> Placed:
    return Placed.from_pose(b.shape, pos, quat, b.radius, b.half_length, b.half_extents)


def _static_rotation(s: Static) -> np.ndarray:
    return rotation_matrix(s.orientation)


def placed_static_box(s: Static, n: int) -> Placed:
    """A static box as n copies of one placed box (broadcast views)."""
    return Placed("box", np.broadcast_to(np.asarray(s.position, float), (n, 3)),
                  np.broadcast_to(_static_rotation(s), (n, 3, 3)), half_extents=s.half_extents)

