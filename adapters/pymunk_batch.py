"""pymunk's batched reads through its public API (``pymunk.batch``): every
body's (x, y, angle, vx, vy, w) in one call, and every touching arbiter's
contact points in one call, as numpy arrays in pymunk's own 2D terms (the
adapter converts them).  Pinned by
tests/test_adapter_pymunk.py::test_read_state_paths_agree and
::test_batched_contacts_equal_each_arbiter.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.pymunk_internals import ROW


class PublicBodyBatch:
    """``get_space_bodies`` into one reused buffer.  The iterator visits the
    dynamic bodies in order of addition (sleeping disabled, nothing
    removed), then the static body if it holds shapes: ``total`` rows, the
    first n the scene's bodies.  Order and layout are verified at
    construction against the bodies' ids and properties."""

    def __init__(self, batch: Any, space: Any, bodies: list) -> None:
        bf = batch.BodyFields
        self.fields = bf.POSITION | bf.ANGLE | bf.VELOCITY | bf.ANGULAR_VELOCITY
        self.buf = batch.Buffer()
        self._batch, self._space, self._n = batch, space, len(bodies)
        check = batch.Buffer()
        batch.get_space_bodies(space, self.fields | bf.BODY_ID, check)
        ids = np.frombuffer(check.int_buf(), dtype=np.uintp)
        self.total = len(ids)
        if list(ids[:self._n]) != [b.id for b in bodies]:
            raise RuntimeError("pymunk batch body order differs from the order bodies were added")
        got = np.frombuffer(check.float_buf()).reshape(self.total, ROW)[:self._n]
        want = np.array([(b.position.x, b.position.y, b.angle, b.velocity.x, b.velocity.y, b.angular_velocity)
                         for b in bodies], float).reshape(self._n, ROW)
        if not np.array_equal(got, want):
            raise RuntimeError("pymunk batch layout is not (x, y, angle, vx, vy, w)")

    def read(self) -> np.ndarray:
        """The current state as (6, n) columns (a view into the buffer)."""
        self.buf.clear()
        self._batch.get_space_bodies(self._space, self.fields, self.buf)
        return np.frombuffer(self.buf.float_buf()).reshape(self.total, ROW)[:self._n].T


#: per arbiter the batch holds [normal (2), then per point k = 1, 2:
#: point_a (2), point_b (2), distance]; GATHER picks (normal, a, b, distance)
#: per point, MIDPOINT turns that into [point (2), normal (2), depth]
GATHER = np.array([[0, 1, 2, 3, 4, 5, 6], [0, 1, 7, 8, 9, 10, 11]])
MIDPOINT = np.zeros((7, 5))
MIDPOINT[[2, 4], 0] = MIDPOINT[[3, 5], 1] = 0.5
MIDPOINT[0, 2] = MIDPOINT[1, 3] = 1.0
MIDPOINT[6, 4] = -1.0


class ArbiterBatch:
    """``get_space_arbiters`` into one reused buffer, as contact rows.

    ``bodies`` are every body an arbiter can hold, in scene order (the
    static body last); a normal is oriented from the lower-indexed body of
    its pair toward the other, as ``Body.each_arbiter`` visited from the
    bodies in order orients it.  Which arbiters the batch holds (and their
    order, and how many points each has) changes only when contacts come or
    go: the normals' signs and the rows kept are worked out once per such
    set and reused."""

    def __init__(self, batch: Any, space: Any, bodies: list) -> None:
        af = batch.ArbiterFields
        self.fields = (af.BODY_A_ID | af.BODY_B_ID | af.NORMAL | af.CONTACT_COUNT | af.POINT_A_1 | af.POINT_B_1
                       | af.DISTANCE_1 | af.POINT_A_2 | af.POINT_B_2 | af.DISTANCE_2)
        self.buf = batch.Buffer()
        self._batch, self._space = batch, space
        self._index = {b.id: k for k, b in enumerate(bodies)}
        self._plans: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def _plan(self, ints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(sign of each arbiter's normal (A, 1, 1), rows kept (A, 2) bool)
        for the batch's (body a id, body b id, count) rows (A, 3)."""
        key = ints.tobytes()
        plan = self._plans.get(key)
        if plan is None:
            if len(self._plans) > 4096:  # contact sets come and go: keep the memory bounded
                self._plans.clear()
            ia = np.array([self._index[int(i)] for i in ints[:, 0]], int)
            ib = np.array([self._index[int(i)] for i in ints[:, 1]], int)
            sign = np.where(ia > ib, -1.0, 1.0).reshape(-1, 1, 1)
            plan = self._plans[key] = (sign, np.arange(2)[None, :] < ints[:, 2:3].astype(int))
        return plan

    def contact_rows(self) -> np.ndarray:
        """(k, 5) rows [point x, y (m), unit normal x, y, depth (m, > 0 =
        overlap)] in pymunk's 2D frame: point midway between point_a and
        point_b, depth = -distance.

        The batch visits every cached arbiter, also those kept for a few
        steps after their shapes separated; those report a contact count of
        0 and are left out."""
        buf = self.buf
        buf.clear()
        self._batch.get_space_arbiters(self._space, self.fields, buf)
        ints = np.frombuffer(buf.int_buf(), dtype=np.uintp).reshape(-1, 3)  # body a id, body b id, count
        sign, keep = self._plan(ints)
        x = np.frombuffer(buf.float_buf()).reshape(len(ints), 12)[:, GATHER]  # (A, 2 points, 7)
        x[:, :, 0:2] *= sign
        return (x @ MIDPOINT)[keep]
