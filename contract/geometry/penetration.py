"""Overlap depths of every pair of shapes in every frame of a trace, stored
sparsely (:class:`Penetration`): bodies against statics, and body pairs that
survive the culling (contract/geometry/cull.py) grouped by shape pair and
measured by the kernels of the dispatch table (contract/geometry/dispatch.py)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from physbench.contract.scene_model import Body, Scene
from physbench.contract.geometry.cull import _ALL_PAIRS_MAX, _body_events, _radius_classes
from physbench.contract.geometry.dispatch import PAIR_KERNELS, pair_depth
from physbench.contract.geometry.placed import SHAPES, Placed, _ORDER, placed_static_box, _static_rotation
from physbench.contract.geometry.support import plane_gap

@dataclass
class Penetration:
    """Overlap depths of one trace, stored sparsely.

    ``pairs[p]`` names column p: (i, "static", s) for body i against static
    s (scene.statics index) or (i, "body", j) for bodies i < j.  Columns are
    the body-static pairs sorted by (i, s) -- every body against every plane,
    and against a static box if their bounding sphere reaches the box in some
    frame -- then the body-body pairs whose bounding spheres meet in some
    frame, sorted by (i, j).  Entries (``frames``, ``cols``, ``depths``) hold
    every non-zero depth (NaN where it is unknown); every other (frame,
    column) is 0.  ``bad`` (F, n) marks
    non-finite body poses: their columns are NaN in those frames.
    """

    n_frames: int
    pairs: list[tuple[int, str, int]]
    frames: np.ndarray
    cols: np.ndarray
    depths: np.ndarray
    bad: np.ndarray

    def _col_bodies(self) -> tuple[np.ndarray, np.ndarray]:
        a = np.array([p[0] for p in self.pairs], dtype=np.int64)
        b = np.array([p[2] if p[1] == "body" else -1 for p in self.pairs], dtype=np.int64)
        return a, b

    def dense(self) -> np.ndarray:
        """(F, P) depths (m)."""
        out = np.zeros((self.n_frames, len(self.pairs)))
        out[self.frames, self.cols] = self.depths
        if self.bad.any() and self.pairs:
            a, b = self._col_bodies()
            mask = self.bad[:, a] | (self.bad[:, np.maximum(b, 0)] & (b >= 0))
            out[mask] = np.nan
        return out

    def frame_max(self) -> np.ndarray:
        """(F,) deepest known overlap per frame (m); NaN entries are ignored
        (see :meth:`unknown`)."""
        out = np.zeros(self.n_frames)
        ok = ~np.isnan(self.depths)
        np.maximum.at(out, self.frames[ok], self.depths[ok])
        return out

    def unknown(self) -> np.ndarray:
        """(F,) frames where some depth is unknown: a NaN entry (a pair no
        kernel covers) or a non-finite body pose."""
        out = self.bad.any(axis=1) if self.bad.size else np.zeros(self.n_frames, bool)
        out[self.frames[np.isnan(self.depths)]] = True
        return out


class _BodyTable:
    """Per-body shape codes and dimensions as arrays."""

    def __init__(self, bodies: tuple[Body, ...]):
        n = len(bodies)
        self.kind = np.array([_ORDER.get(b.shape, -1) for b in bodies], dtype=np.int64)
        self.radius = np.array([b.radius for b in bodies], float)
        self.half_length = np.array([b.half_length for b in bodies], float)
        self.half_extents = np.zeros((n, 3))
        for i, b in enumerate(bodies):
            if b.half_extents is not None:
                self.half_extents[i] = b.half_extents
        self.rb = np.array([b.bounding_radius for b in bodies], float)

    def placed(self, kind: str, pos: np.ndarray, quat: np.ndarray, f: np.ndarray, i: np.ndarray) -> Placed:
        return Placed.from_pose(kind, pos[f, i], quat[f, i], self.radius[i], self.half_length[i],
                                self.half_extents[i])


class _Collector:
    def __init__(self):
        self.keys: list[np.ndarray] = []    # candidate pair keys
        self.ekeys: list[np.ndarray] = []   # entry keys
        self.frames: list[np.ndarray] = []
        self.depths: list[np.ndarray] = []

    def add(self, keys: np.ndarray, frames: np.ndarray, depth: np.ndarray) -> None:
        """Entries for events (keys, frames); all the keys become candidates."""
        if keys.size == 0:
            return
        self.keys.append(np.unique(keys))
        nz = depth != 0.0  # NaN != 0 is True: unknown depths are kept
        self.ekeys.append(keys[nz])
        self.frames.append(frames[nz])
        self.depths.append(depth[nz])

    def candidates(self) -> np.ndarray:
        return np.unique(np.concatenate(self.keys)) if self.keys else np.zeros(0, np.int64)



def measure_penetration(scene: Scene, trace) -> Penetration:
    """Overlap depths (m) of every pair of shapes in every frame of ``trace``
    (pos (F, n, 3), quat (F, n, 4) wxyz), sparse.  See the module docstring."""
    pos = np.asarray(trace.pos, float)
    quat = np.asarray(trace.quat, float)
    F = pos.shape[0]
    bodies = scene.bodies
    n = len(bodies)
    statics = scene.statics
    ns = max(1, len(statics))
    tab = _BodyTable(bodies)
    bad = ~(np.isfinite(pos).all(axis=-1) & np.isfinite(quat).all(axis=-1)) if n else np.zeros((F, 0), bool)
    st = _Collector()  # keys i * ns + s
    bb = _Collector()  # keys i * n + j
    groups = [(k, np.nonzero(tab.kind == c)[0]) for c, k in enumerate(SHAPES)]
    groups = [(k, idx) for k, idx in groups if idx.size]
    unknown_shape = np.nonzero(tab.kind < 0)[0]

    allpairs = None
    classes = None
    if n > 1:
        npairs = n * (n - 1) // 2
        if npairs <= _ALL_PAIRS_MAX:
            allpairs = np.triu_indices(n, 1)
            allpairs = (allpairs[0].astype(np.int64), allpairs[1].astype(np.int64))
        else:
            classes = _radius_classes(tab.rb)

    block = max(1, 65536 // max(1, n))
    for f0 in range(0, F, block):
        f1 = min(F, f0 + block)
        fr = np.arange(f0, f1)
        # -- statics
        for s in statics:
            if s.shape == "plane":
                for kind, idx in groups:
                    ff = np.repeat(fr, idx.size)
                    ii = np.tile(idx, fr.size)
                    G = tab.placed(kind, pos, quat, ff, ii)
                    depth = np.maximum(0.0, plane_gap(G, s.normal, s.offset))
                    st.add(ii * ns + s.index, ff, depth)
                if unknown_shape.size:
                    ff = np.repeat(fr, unknown_shape.size)
                    ii = np.tile(unknown_shape, fr.size)
                    st.add(ii * ns + s.index, ff, np.full(ff.size, np.nan))
            elif s.shape == "box":
                # cull: a body's bounding sphere must reach the box itself
                q = (pos[f0:f1] - np.asarray(s.position, float)) @ _static_rotation(s)  # box frame
                e = np.asarray(s.half_extents, float)
                dq = q - np.clip(q, -e, e)
                ff, ii = np.nonzero(np.einsum("fni,fni->fn", dq, dq) <= tab.rb[None, :] ** 2)
                ff = ff + f0
                for kind, idx in groups:
                    m = np.isin(ii, idx)
                    if m.any():
                        G = tab.placed(kind, pos, quat, ff[m], ii[m])
                        st.add(ii[m] * ns + s.index, ff[m], pair_depth(G, placed_static_box(s, G.n)))
                m = np.isin(ii, unknown_shape)
                if m.any():
                    st.add(ii[m] * ns + s.index, ff[m], np.full(int(m.sum()), np.nan))
            else:  # a static shape this module does not know: unknown, not zero
                ff = np.repeat(fr, n)
                ii = np.tile(np.arange(n), fr.size)
                st.add(ii * ns + s.index, ff, np.full(ff.size, np.nan))
        # -- bodies
        if n > 1:
            ef, ei, ej = _body_events(pos, bad, tab.rb, f0, f1, classes, allpairs)
            if ef.size:
                ki, kj = tab.kind[ei], tab.kind[ej]
                swap = ki > kj
                lo_i = np.where(swap, ej, ei)  # lower shape code first
                hi_i = np.where(swap, ei, ej)
                klo, khi = np.minimum(ki, kj), np.maximum(ki, kj)
                code = klo * 8 + khi
                for c in np.unique(code):
                    m = code == c
                    a_kind, b_kind = int(c) // 8, int(c) % 8
                    keys = ei[m] * n + ej[m]
                    if a_kind < 0 or b_kind < 0 or (SHAPES[a_kind], SHAPES[b_kind]) not in PAIR_KERNELS:
                        bb.add(keys, ef[m], np.full(int(m.sum()), np.nan))
                        continue
                    A = tab.placed(SHAPES[a_kind], pos, quat, ef[m], lo_i[m])
                    B = tab.placed(SHAPES[b_kind], pos, quat, ef[m], hi_i[m])
                    bb.add(keys, ef[m], pair_depth(A, B))

    skeys = st.candidates()
    bkeys = bb.candidates()
    pairs = [(int(k // ns), "static", int(k % ns)) for k in skeys] + [
        (int(k // n), "body", int(k % n)) for k in bkeys]
    frames, cols, depths = [], [], []
    for coll, keys, off in ((st, skeys, 0), (bb, bkeys, skeys.size)):
        if coll.ekeys:
            ek = np.concatenate(coll.ekeys)
            cols.append(np.searchsorted(keys, ek) + off)
            frames.append(np.concatenate(coll.frames))
            depths.append(np.concatenate(coll.depths))
    cat = (lambda xs, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(0, dt))
    return Penetration(F, pairs, cat(frames, np.int64), cat(cols, np.int64), cat(depths, float), bad)


def penetration_depths(scene: Scene, trace) -> np.ndarray:
    """Overlap depth (m) per frame and candidate pair: array (F, P).

    Columns: body-static pairs by (body, static), then body-body pairs by
    (i, j); pairs that never come within bounding-sphere reach have no column
    (see :class:`Penetration`).  A pair no kernel covers, or a non-finite
    pose, gives NaN (ignored by nan-aware reductions) rather than a silent
    zero.
    """
    return measure_penetration(scene, trace).dense()


def max_depth_per_frame(scene: Scene, trace) -> np.ndarray:
    """(F,) deepest overlap (m) in each frame without building the (F, P)
    matrix; unknown (NaN) depths are ignored (``measure_penetration(...)
    .unknown()`` says where)."""
    return measure_penetration(scene, trace).frame_max()
