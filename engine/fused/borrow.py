"""Borrowed packs: the fused calls' kept arrays without reference counting.

numba counts references to every array it handles: an array taken out of
a Pack's tuple, handed to a compiled callee or sliced is an atomic
increment of its NRT record, and one decrement when the handle dies --
~2000 of them in one steady step of a single rolling sphere (counted by
replacing ``NRT_incref``/``NRT_decref``: 901 and 1053), each a locked
instruction: ~13 of the step's ~20 us in the compiled loop, whatever the
number of contacts (the step's own arithmetic: ~6.5 us).  A *borrowed*
array is the same array (data, shape, strides: the same memory, the same
type, the same bits) with no NRT record (``meminfo`` and ``parent`` NULL):
numba's increments and decrements of it return at their NULL check.

:func:`borrowed` is a Pack whose arrays (in its tuple and nested tuples)
are borrowed views of a kept Pack's; it does not keep them alive, so
:class:`Borrowed` keeps the Pack it was made from next to it (as long as
the borrowed one is handed out).  Only the fused calls' packs and the
joint step's arrays are borrowed (engine/fused/steady.py,
engine/fused/loop.py, engine/joints/step.py); a borrowed array is never
handed back to Python (numba would box it as an array that owns nothing).
"""

from __future__ import annotations

from operator import is_

from numba import njit
from numba.core import cgutils, types
from numba.extending import intrinsic

from physbench.engine.pack import Pack


def _no_records(context, builder, ty, val):
    """``val`` of type ``ty`` with every array in it (through nested
    tuples) a view without NRT record; other members passed on with a
    reference of their own."""
    if isinstance(ty, types.Array):
        src = context.make_array(ty)(context, builder, value=val)
        dst = context.make_array(ty)(context, builder)
        dst.meminfo = cgutils.get_null_value(dst.meminfo.type)
        dst.parent = cgutils.get_null_value(dst.parent.type)
        dst.nitems = src.nitems
        dst.itemsize = src.itemsize
        dst.data = src.data
        dst.shape = src.shape
        dst.strides = src.strides
        return dst._getvalue()
    if isinstance(ty, types.BaseTuple):
        out = val
        for i, t in enumerate(ty.types):
            out = builder.insert_value(out, _no_records(context, builder, t, builder.extract_value(val, i)), i)
        return out
    context.nrt.incref(builder, ty, val)
    return val


@intrinsic
def borrow(typingctx, items):
    """``items`` (an array, or a tuple of arrays, scalars and tuples of
    them) with its arrays borrowed (module doc): the same type and
    memory, no NRT record.  Valid while the arrays it was made from live."""

    def codegen(context, builder, sig, args):
        return _no_records(context, builder, sig.args[0], args[0])

    return items(items), codegen


@njit(cache=True)
def borrowed(p):
    """A Pack of ``p``'s items with their arrays borrowed (same type as
    ``p``); valid while ``p`` lives."""
    return Pack(borrow(p.items))


class Borrowed:
    """The borrowed twins of kept Packs (:func:`borrowed`), made once per
    Pack and held with it (so the arrays they view stay alive): ``of(p)``.
    Holds at most ``cap`` pairs (a pack replaced when its buffers grew
    drops out when the table is full)."""

    __slots__ = ("_twins", "cap")

    def __init__(self, cap: int = 32) -> None:
        self._twins: dict = {}
        self.cap = cap

    def of(self, p: Pack) -> Pack:
        e = self._twins.get(id(p))
        if e is None or e[0] is not p:
            if len(self._twins) >= self.cap:
                self._twins.clear()
            e = self._twins[id(p)] = (p, borrowed(p))
        return e[1]


class BorrowedOf:
    """One Pack of borrowed twins of kept Packs, made by the compiled
    ``make`` (one dispatch: ~30 us for twelve packs where a tuple of them
    handed to ``Pack`` cost ~170 us to type) and kept while the items it
    was made from are the same objects (it holds them: the arrays the
    twins view stay alive)."""

    __slots__ = ("_items", "_pack", "_make")

    def __init__(self, make) -> None:
        self._items: tuple | None = None
        self._pack = None
        self._make = make

    def of(self, items: tuple) -> Pack:
        last = self._items
        if last is None or not all(map(is_, last, items)):
            self._pack = self._make(*items)
            self._items = items
        return self._pack
