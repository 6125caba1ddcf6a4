"""Typed step control: what the stages tell the step loop
(engine/pipeline.py) and the time-of-impact search (engine/ccd.py).

A (mini-)step runs in one :class:`EventMode`; the solve reports the step's
impact rows (:class:`Impacts`), the CCD stage the earliest impact as an
:class:`Event` over :class:`ImpactPair` s, the search its result as a
:class:`TimeOfImpact`; a friction stop is the time (s) at which a sliding
contact came to rest (``Context.stop``).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np


class EventMode(Enum):
    """How the solve treats the impacts of a (mini-)step."""

    #: impacts are events: left out of the solve for the CCD stage
    EVENT = "event"
    #: no events left in this substep (``ccd_max_events``): impacts become
    #: speculative rows (no penetration, no bounce)
    SPECULATIVE = "speculative"
    #: a rerun of the time-of-impact search: the step's impact rows
    #: (``Context.drop_rows``) are left out, whatever the rerun's length
    DROP = "drop"


@dataclass(frozen=True, eq=False)
class Impacts:
    """The solve's impact rows: ``rows`` (k,) indices into the step's
    contacts, ``tau`` (k,) s first time-of-impact estimates
    (gap / approach speed)."""

    rows: np.ndarray
    tau: np.ndarray


@dataclass(frozen=True, eq=False)
class ImpactPair:
    """A pair the time-of-impact search may follow: bodies ``a``, ``b``
    (b = n for a static), static index ``sidx`` (-1 for a body pair), the
    impact points in body a's frame ``loc`` (k, 3) m, their feature ids to
    follow or None (ccd.pair_gap), whether it is a missed impact
    (ccd.missed_impacts), and the points to leave out or None."""

    a: int
    b: int
    sidx: int
    loc: np.ndarray
    fids: object
    missed: bool
    excl: object


@dataclass(frozen=True, eq=False)
class Event:
    """The step's earliest impact: ``tau`` s its first estimate, ``pair``
    the pair to follow, ``others`` the step's other impact pairs."""

    tau: float
    pair: ImpactPair
    others: tuple


@dataclass(frozen=True, eq=False)
class TimeOfImpact:
    """The search's result: the pair followed in the end, and whether it
    was still clear at the end of the (mini-)step (no impact in it)."""

    pair: ImpactPair
    clear: bool
