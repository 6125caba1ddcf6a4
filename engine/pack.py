"""Kept arrays handed to a compiled call as ONE argument.

A compiled (numba) call unboxes each array argument on every call, ~0.1-0.15
us apiece: a kernel of 60 array arguments paid ~8 us a call in dispatch
alone, a tuple of them more.  A :class:`Pack` is a numba structref holding
one tuple (of arrays, scalars and tuples of them), built once while the
arrays it holds stay the same (buffers kept between steps) and unboxed as
one pointer (~1 us a call whatever it holds).  Kernels read ``pack.items``
and unpack the tuple inside the compiled code.

The pack keeps its arrays alive (it holds references); writes through the
arrays are seen by both sides (they share memory).

A Pack is passed as an argument of its own, never inside a tuple: numba
types a tuple holding one in Python, the Pack's whole type with it, at
every call (~60-80 us for the narrow phase's;
tests/test_ccd_event_path.py::test_event_kernels_take_no_pack_inside_a_tuple).
"""

from __future__ import annotations

from operator import is_

from numba import njit
from numba.core import types
from numba.experimental import structref


@structref.register
class PackType(types.StructRef):
    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


class Pack(structref.StructRefProxy):
    """``Pack(items)``: ``items`` a tuple of arrays (C-contiguous, as the
    kernels are compiled for them), scalars or tuples of them."""

    def __new__(cls, items: tuple):
        return _new(items)

    @property
    def items(self) -> tuple:
        return _items(self)


structref.define_proxy(Pack, PackType, ["items"])


@njit(cache=True)
def _new(items):
    return Pack(items)


@njit(cache=True)
def _items(p):
    return p.items


class KeptPack:
    """One :class:`Pack` kept while the objects it holds stay the same:
    ``kept.of(items)`` is the Pack built the last time when every item is
    the same object (``is``) as then, else a new Pack of ``items``.  The
    one cache of the kept packs (the step's pose, the contacts, the narrow
    phase's buffers): a buffer grown or replaced gives a new Pack."""

    __slots__ = ("_items", "_pack")

    def __init__(self) -> None:
        self._items: tuple | None = None
        self._pack = None

    def of(self, items: tuple, make=None) -> Pack:
        """The Pack made last time when ``items`` (what it holds) are the
        same objects as then, else a new one: ``make()`` (a Pack of a
        named tuple of ``items``, built only then: a named tuple costs more
        to build in Python than the identity test), default
        ``Pack(items)``."""
        last = self._items
        if last is None or len(last) != len(items) or not all(map(is_, last, items)):
            self._pack = Pack(items) if make is None else make()
            self._items = items
        return self._pack
