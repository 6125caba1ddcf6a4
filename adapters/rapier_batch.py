"""Batched state reads for the Rapier adapter.

rapier3d 0.36's Python binding has no batched getter of rigid-body state:
the per-body getters cost four calls per body per step (1.6 us per body,
measured).  It does serialise the whole rigid-body set in one call,
``RigidBodySet.to_bytes()`` (0.33 us per body, measured), whose bytes hold
every body's pose (rotation x, y, z, w then translation, f32) and, a fixed
distance further on, its linear then angular velocity (f32).

:class:`SetBytesReader` takes the layout from a probe world of distinctive
values (:func:`set_layout`: where the first body's state lies, the distance
from translation to velocity; each body follows the previous one after its
own ``to_bytes()`` length) and verifies the decoded state against the
per-body getters -- translations and velocities bit for bit, rotations to 2
f32 units, since the getter renormalises -- for every body at construction
and for up to 16 bodies, the first and the last among them, after every
recorded block (:meth:`SetBytesReader.check`, which raises, never passes a
mismatch silently).  A binding whose bytes are not as expected
raises at construction; the adapter then reads by the getters
(tests/test_adapter_rapier.py::test_set_bytes_reader_equals_getters).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

F32 = np.dtype("<f4")
ROTATION = 4 * 4  # bytes: x, y, z, w
TRANSLATION = 3 * 4  # bytes: x, y, z (right after the rotation)
VELOCITY = 6 * 4  # bytes: linear (x, y, z), angular (x, y, z)


def getter_rows(bodies: list) -> np.ndarray:
    """(n, 13) float64 rows [qx, qy, qz, qw, x, y, z, vx, vy, vz, wx, wy, wz]
    by the per-body getters (the reference the byte reader is checked
    against)."""
    return np.array([(*rb.rotation.to_tuple(), *rb.translation.to_tuple(), *rb.linvel.to_tuple(),
                      *rb.angvel.to_tuple()) for rb in bodies], float).reshape(len(bodies), 13)


def _translation_bytes(row: np.ndarray) -> bytes:
    return np.asarray(row[4:7], F32).tobytes()


def _velocity_bytes(row: np.ndarray) -> bytes:
    return np.asarray(row[7:13], F32).tobytes()


#: the rotation getter renormalises the stored quaternion: before the first
#: step (the builder's own normalisation stored) the two differ by 1 f32
#: unit, measured; after a step they agree bit for bit
#: (tests/test_adapter_rapier.py::test_set_bytes_reader_equals_getters)
QUAT_TOL = 2.0 ** -22


@functools.lru_cache(maxsize=1)
def set_layout(rp: Any) -> tuple[int, int]:
    """(offset of the first body's translation, bytes from a body's
    translation to its velocity) in ``to_bytes()`` of the rigid-body set,
    found on a probe world of two bodies with distinctive translations and
    velocities.  The rotation (x, y, z, w) precedes the translation; the
    second body follows the first after ``len(first.to_bytes())`` bytes.
    ValueError where the probe's bytes are not so."""
    world = rp.PhysicsWorld(gravity=(0.0, 0.0, 0.0))
    handles = []
    for i in range(2):
        b = (rp.RigidBodyBuilder(rp.RigidBodyType.DYNAMIC)
             .position(((1.5 + i, 2.25, 3.125), (0.5, 0.5, 0.5, 0.5)))
             .linvel((4.5, 5.25, 6.125 + i)).angvel((7.5, 8.25, 9.125 + i)).can_sleep(False))
        handles.append(world.add_body(b, [rp.Collider.ball(0.1)]))
    bodies = [world.rigid_bodies[h] for h in handles]
    rows = getter_rows(bodies)
    blob = world.rigid_bodies.to_bytes()
    t = [blob.find(_translation_bytes(r)) for r in rows]
    v = [blob.find(_velocity_bytes(r)) for r in rows]
    ok = (min(t) >= ROTATION and min(v) >= 0 and v[0] - t[0] == v[1] - t[1] >= TRANSLATION
          and t[1] - t[0] == len(bodies[0].to_bytes())
          and all(blob[x - ROTATION:x] == np.asarray(r[0:4], F32).tobytes() for x, r in zip(t, rows)))
    if not ok:
        raise ValueError("rapier3d: RigidBodySet.to_bytes() does not hold the probe bodies' state as expected")
    return t[0], v[0] - t[0]


class SetBytesReader:
    """Every body's state from one ``RigidBodySet.to_bytes()`` per step.

    ``blob()`` is the engine call (bound once; the set object is a live
    view); :meth:`decode` turns k blobs into (k, n, 13) float64 rows in the
    layout of :func:`getter_rows`.  Raises ValueError at construction when
    a body's state cannot be located and verified."""

    def __init__(self, rp: Any, world: Any, bodies: list) -> None:
        self._bodies = bodies
        self.blob = world.rigid_bodies.to_bytes
        first, delta = set_layout(rp)
        blob = self.blob()
        lengths = [len(rb.to_bytes()) for rb in bodies]
        self._offsets = np.concatenate([[first], first + np.cumsum(lengths[:-1], dtype=np.int64)]).astype(int)
        self._delta = delta
        #: bodies of one serialised length (one collider each, or none):
        #: the decode is then two strided views over all bodies at once
        self._stride = lengths[0] if lengths and len(set(lengths)) == 1 else None
        self._rows: memoryview | None = None
        self._spans: list = []
        self._samples: dict = {}
        self._L = 0
        #: bytes up to the end of the last body's velocity
        self.need = int(self._offsets[-1]) + delta + VELOCITY if bodies else 0
        if self.need > len(blob):
            raise ValueError("rapier3d: RigidBodySet.to_bytes() is shorter than its bodies")
        try:
            self.check(self.decode([blob])[-1])
        except RuntimeError as e:
            raise ValueError(str(e)) from None

    def _views(self, raw: Any, k: int, L: int) -> list:
        """Per group of bodies (all at once when they share one serialised
        length, else one by one): (body slice, (k, m, 7) f32 poses
        [qx, qy, qz, qw, x, y, z], (k, m, 6) f32 velocities) viewed in
        ``raw``, k rows of L bytes, by strided views: no per-row
        Python work, no copy."""
        d = self._delta

        def f32(offset: int, m: int, stride: int, width: int) -> np.ndarray:
            # a view, no copy: its strides are byte distances (L and a
            # body's serialised length need not be multiples of 4, so it
            # may be unaligned; numpy reads it as such)
            return np.ndarray((k, m, width), F32, raw, offset, (L, stride, 4))

        if self._stride is not None:
            t0, S, n = int(self._offsets[0]), self._stride, len(self._bodies)
            return [(slice(0, n), f32(t0 - ROTATION, n, S, 7), f32(t0 + d, n, S, 6))]
        return [(slice(i, i + 1), f32(t - ROTATION, 1, 0, 7), f32(t + d, 1, 0, 6))
                for i, t in enumerate(self._offsets.tolist())]

    def _joined(self, blobs: list) -> tuple[bytes, int]:
        """(the blobs joined, their row length): the set's bytes after its
        bodies change length (8 bytes per body fewer after the first step,
        measured), so unequal rows are cut to the bodies."""
        L = len(blobs[0])
        if any(len(b) != L for b in blobs):
            L = self.need
            blobs = [b[:L] for b in blobs]
        return b"".join(blobs), L

    def decode(self, blobs: list) -> np.ndarray:
        """(k, n, 13) float64 rows of k blobs, in the layout of :func:`getter_rows`."""
        out = np.empty((len(blobs), len(self._bodies), 13))
        if len(blobs) and len(self._bodies):
            raw, L = self._joined(blobs)
            for sl, pose, vel in self._views(raw, len(blobs), L):
                out[:, sl, 0:7] = pose
                out[:, sl, 7:13] = vel
        return out

    def block(self, n: int, L: int) -> tuple[memoryview, list]:
        """A reused buffer of at least n rows of L bytes and the slices of
        its first n rows (the runner's blocks copy each step's bytes into
        row i by ``buf[spans[i]] = blob``: no allocation, no arithmetic and
        no fresh pages to fault in, per step).  Buffer and slices are kept
        for the next block of the same row length."""
        if self._rows is None or len(self._rows) < n * L or self._L != L:
            cap = max(n, len(self._rows) // L if self._rows is not None and self._L == L else 0)
            self._rows = memoryview(bytearray(cap * L))
            self._spans = [slice(i * L, (i + 1) * L) for i in range(cap)]
            self._L = L
        return self._rows, self._spans

    def rows_into(self, k: int, L: int, odd: dict, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray,
                  angvel: np.ndarray) -> None:
        """The first k rows of :meth:`block`'s buffer (L bytes each;
        ``odd``: row -> bytes of another length, decoded apart) straight
        into the harness's (k, n, 3|4) arrays: positions, wxyz quaternions
        (Rapier's x, y, z, w reordered), linear and angular velocities, by
        five strided f32 -> float64 assignments over the whole block, read
        in place from the row bytes."""
        if not (k and len(self._bodies)):
            return
        parts = [(slice(0, k), self._views(self._rows, k, L))]
        parts += [(slice(i, i + 1), self._views(b, 1, len(b))) for i, b in odd.items() if i < k]
        for rows, views in parts:
            for sl, pose, v in views:
                pos[rows, sl] = pose[..., 4:7]
                quat[rows, sl, 0] = pose[..., 3]
                quat[rows, sl, 1:4] = pose[..., 0:3]
                vel[rows, sl] = v[..., 0:3]
                angvel[rows, sl] = v[..., 3:6]

    def _sample(self, sample: int | None) -> list:
        """Indices of the bodies checked: all, or ``sample`` of them evenly
        spread from the first to the last (cached per sample size)."""
        n = len(self._bodies)
        key = None if sample is None or n <= sample else int(sample)
        got = self._samples.get(key)
        if got is None:
            idx = range(n) if key is None else np.unique(np.linspace(0, n - 1, key).round().astype(int))
            got = self._samples[key] = [int(i) for i in idx]
        return got

    def check_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray,
                    sample: int | None = None) -> None:
        """:meth:`check` of one recorded state in the harness's layout:
        positions (n, 3), wxyz quaternions (n, 4), linear and angular
        velocities (n, 3).  Compared in Python floats, body by body (a few
        bodies: cheaper than array calls); anything unequal goes to
        :meth:`check`, which decides (NaN equals NaN) and raises."""
        P, Q, V, W = pos.tolist(), quat.tolist(), vel.tolist(), angvel.tolist()
        bodies, tol = self._bodies, QUAT_TOL
        for i in self._sample(sample):
            rb = bodies[i]
            x, y, z, w = rb.rotation.to_tuple()
            q = Q[i]
            if not (rb.translation.to_tuple() == tuple(P[i]) and rb.linvel.to_tuple() == tuple(V[i])
                    and rb.angvel.to_tuple() == tuple(W[i]) and abs(w - q[0]) <= tol and abs(x - q[1]) <= tol
                    and abs(y - q[2]) <= tol and abs(z - q[3]) <= tol):
                self.check(np.concatenate([quat[:, [1, 2, 3, 0]], pos, vel, angvel], axis=1), sample)
                return

    def check(self, last: np.ndarray, sample: int | None = None) -> None:
        """Raise RuntimeError unless ``last`` (n, 13) is the getters' state
        now: translations and velocities bit for bit, rotations to
        :data:`QUAT_TOL` (the getter renormalises).  ``sample``: check only
        that many bodies, evenly spread from the first to the last (the
        layout is checked for every body at construction; after a block a
        sample bounds the getters' cost on large scenes)."""
        n = len(self._bodies)
        idx = np.arange(n) if sample is None or n <= sample else np.unique(np.linspace(0, n - 1, sample).round().astype(int))
        want = getter_rows([self._bodies[i] for i in idx])
        got = last[idx]
        d = np.abs(got - want)
        d[np.isnan(got) & np.isnan(want)] = 0.0
        if not (np.all(d[:, 4:] == 0.0) and np.all(d[:, :4] <= QUAT_TOL)):
            raise RuntimeError("rapier3d: the state decoded from RigidBodySet.to_bytes() differs from the "
                               f"getters' by up to {np.nanmax(d):g}")
