"""The pymunk internals the pymunk adapter uses, isolated here: each is a
shortcut past pymunk's Python wrapper where the public call costs more than
the work, and each has a public twin that the adapter falls back to when an
internal is missing.

- :func:`c_stepper`: Chipmunk's ``cpSpaceStep`` called directly (public
  twin: ``Space.step``).  ``Space.step`` wraps that one C call in
  bookkeeping physbench never needs after build (a mass check of newly added
  bodies, done once here instead; deferred add/remove and post-step
  callbacks, which the adapter never registers; the ``pre_solve`` material
  callbacks run inside ``cpSpaceStep`` either way).  The wrapper costs
  ~0.5 us per step, more than reading the whole state back.
- :class:`BodyReader`: the C iterator behind ``pymunk.batch.get_space_bodies``
  called with one preallocated ``pmBatchedData`` into a fixed array viewed
  by numpy (public twin: ``get_space_bodies``, which allocates a struct and
  a buffer view per call), and the block recorder that points that array at
  a block buffer so that it appends step after step with no Python
  bookkeeping per step.

Uses ``Space._space``, ``_add_later``, ``_remove_later``,
``_post_step_callbacks``, ``_bodies_to_check``, ``Buffer._float_arr``,
``Buffer._int_arr`` and ``pymunk._chipmunk_cffi`` (pymunk 7.x).  Pinned by
tests/test_adapter_pymunk.py::test_private_paths_equal_public_paths (a
whole run through these paths equals one through the public calls, bit for
bit), ::test_direct_c_step_equals_space_step and
::test_read_state_paths_agree.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

ROW = 6  # (x, y, angle, vx, vy, w) per body


def c_stepper(space: Any, bodies: list) -> tuple[Callable[[Any, float], None], Any] | None:
    """(cpSpaceStep, the space's C handle), or None when ``Space.step`` has
    work to do (threaded space, deferred changes, post-step callbacks) or
    pymunk's internals are not as expected.  Checks each body's mass once,
    as ``Space.step`` would on its first call."""
    for b in bodies:
        if not (b.mass > 0 and math.isfinite(b.mass) and b.moment > 0):
            raise ValueError(f"pymunk body needs 0 < mass < inf and moment > 0, got {b.mass}, {b.moment}")
    try:
        from pymunk._chipmunk_cffi import lib

        if getattr(space, "threaded", False) or space._add_later or space._remove_later or space._post_step_callbacks:
            return None
        space._bodies_to_check.clear()
        return lib.cpSpaceStep, space._space
    except Exception:  # pragma: no cover - depends on pymunk internals
        return None


class BodyReader:
    """Batched C reads of every body's (x, y, angle, vx, vy, w).

    ``total`` bodies are iterated (the dynamic ones in order of addition,
    then the static body if it holds shapes); :attr:`cols` is a (6, n) view
    of the dynamic bodies' columns, valid for the reader's life (the array
    never grows: the body count is fixed).  Raises when pymunk's internals
    are not as expected (the caller then uses the public read)."""

    def __init__(self, space: Any, fields: Any, buf: Any, batch: Any, total: int, n: int) -> None:
        from pymunk._chipmunk_cffi import ffi, lib

        batch.get_space_bodies(space, fields, buf)  # sizes the array (capacity >= 6 total)
        farr = buf._float_arr
        if farr.num != ROW * total or farr.max < ROW * total:
            raise RuntimeError("unexpected batch array size")
        data = ffi.new("pmBatchedData *")
        data.fields = fields.value
        data.floatArray = farr
        data.intArray = buf._int_arr
        self._ffi = ffi
        self._buf, self._data = buf, data  # keep alive: the views below point into buf
        self._iter = ffi.addressof(lib, "pmSpaceBodyGetIteratorFuncBatched")
        self._each = lib.cpSpaceEachBody
        self._space = space._space
        self._farr = farr
        self._total, self._n = total, n
        self._raw: np.ndarray | None = None
        self.cols = np.frombuffer(ffi.buffer(farr.arr, 8 * ROW * total), dtype=np.float64).reshape(
            total, ROW)[:n].T

    def read(self) -> np.ndarray:
        """The current state as (6, n) columns (a view, overwritten by the next read)."""
        self._farr.num = 0
        self._each(self._space, self._iter, self._data)
        return self.cols

    def record(self, n: int, step_once: Callable[[], None]) -> tuple[int, np.ndarray]:
        """Call ``step_once`` n times, appending the state after each call to
        a block buffer; returns (complete rows k, (6, k, bodies) columns),
        also after ``step_once`` raised (then re-raised with the rows kept
        readable through :attr:`last_block`).

        The reader's float array is pointed at the block with a capacity
        beyond its size, so pymunk never grows it (it grows only within two
        values of its capacity, which the slack row rules out)."""
        row = ROW * self._total
        raw = self._raw
        if raw is None or raw.shape[0] < n + 1:
            raw = self._raw = np.empty((max(n, 256) + 1, self._total, ROW))  # one slack row
            self._raw_ptr = self._ffi.cast("double *", self._ffi.from_buffer(raw))
        farr, each, space_c, it, data = self._farr, self._each, self._space, self._iter, self._data
        home, home_max = farr.arr, farr.max
        farr.num, farr.max, farr.arr = 0, raw.shape[0] * row, self._raw_ptr
        try:
            for _ in range(n):
                step_once()
                each(space_c, it, data)
        finally:
            k = farr.num // row  # rows complete, also after an exception
            if farr.arr != self._raw_ptr:  # pragma: no cover - would mean pymunk reallocated
                raise RuntimeError("pymunk batch reader reallocated the block buffer")
            farr.arr, farr.max, farr.num = home, home_max, 0
            self.last_block = (k, raw[:k, :self._n].transpose(2, 0, 1))
        return self.last_block
