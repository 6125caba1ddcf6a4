"""Work arrays kept from step to step (no allocation per step in the
steady state).

:class:`Scratch` hands out named arrays of a requested shape as views of
buffers that grow geometrically (at least doubling) along their first axis
when a step needs more rows than any before: a scene with a steady contact
count allocates nothing after its first steps.  A view is valid until the
next ``take`` of the same name (each solve phase takes its own names).
"""

from __future__ import annotations

import numpy as np


class Scratch:
    def __init__(self) -> None:
        self._buf: dict[str, np.ndarray] = {}
        #: the last view handed out per name, with its shape and dtype (a
        #: steady step asks for the same shapes every time: no new view)
        self._last: dict[str, tuple] = {}
        #: the last views of a group (:meth:`group`) per group name
        self._group: dict[str, tuple] = {}

    def take(self, name: str, shape: tuple, dtype=np.float64) -> np.ndarray:
        """A view of shape ``shape`` (contents undefined) of the buffer
        ``name``."""
        last = self._last.get(name)
        if last is not None and last[0] == shape and last[1] is dtype:
            return last[2]
        k = shape[0]
        buf = self._buf.get(name)
        if buf is None or buf.shape[0] < k or buf.shape[1:] != tuple(shape[1:]) or buf.dtype != dtype:
            cap = max(k, 2 * buf.shape[0] if buf is not None else 0, 16)
            buf = self._buf[name] = np.empty((cap,) + tuple(shape[1:]), dtype)
        view = buf[:k]
        self._last[name] = (shape, dtype, view)
        return view

    def zeros(self, name: str, shape: tuple, dtype=np.float64) -> np.ndarray:
        """As :meth:`take`, zeroed."""
        out = self.take(name, shape, dtype)
        out[...] = 0
        return out

    def group(self, key: tuple, make):
        """The views ``make()`` returned for ``key`` (a tuple: the group's
        name, then its sizes) the last time it was asked for, or ``make()``'s
        views now (a steady step asks for the same sizes: one lookup instead
        of one :meth:`take` per array)."""
        last = self._group.get(key[0])
        if last is not None and last[0] == key:
            return last[1]
        views = make()
        self._group[key[0]] = (key, views)
        return views


    def peek(self, key: tuple):
        """The views of the group ``key`` when it was the last asked for
        under its name with these sizes, else None (nothing is made)."""
        last = self._group.get(key[0])
        return last[1] if last is not None and last[0] == key else None
