"""The breaking-point search as pure logic: no runs, no storage, no I/O.

A criterion ``value -> Verdict`` says whether one value holds;
:func:`search` (or :func:`search_rounds`, the same search as a generator
that a scheduler can hold) finds where it stops holding.  The runs behind
a verdict are harness/limit_eval.py's; the command is harness/limits.py.

The search.  The low end is evaluated first; the side that
holds is the start, and the range is walked from it towards the other end
in steps of at most a factor 2 (positive ranges, log space) or a quarter of
the range (linear) until a value fails: the first failing step and the
holding one before it are the bracket.  Then bisection (geometric mean in
log space, integers for integer settings) until the bracket is narrower than
``tol`` (relative: hi / lo - 1 <= tol in log space; hi - lo <= tol x the
range width in linear space; width 1 for integers).  The limit is the
bracket's holding end: the last value known to hold.  Walking from the
holding end (instead of bisecting the whole range at once) finds the first
breaking point when the criterion is not monotone (a wall that catches a
bullet again at some higher speeds).

Rounds.  The search is a chain: each value depends on the last verdict.
With workers to spare, :func:`search_rounds` evaluates several values per
round -- the value the chain needs and the ones it may need next (the next
walking steps; the next levels of the bisection tree) -- and takes the same
decisions from the same verdicts, so its answer is the one-at-a-time
answer in fewer rounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Generator, Iterable, Iterator

#: outcomes of a search
FOUND, HOLDS_THROUGHOUT, FAILS_THROUGHOUT, UNSUPPORTED = "found", "holds_throughout", "fails_throughout", "unsupported"
#: at most this many walking steps from the holding end
MAX_WALK = 8


# ---------------------------------------------------------------------------
# pure search


@dataclass(frozen=True)
class Verdict:
    """Whether one value holds.  ``reason``: the failed check (or status) when
    it does not; ``runs`` and ``cpu_s`` (s of CPU time in the engine's steps)
    spent deciding it; ``unsupported`` when the engine cannot run the scene."""

    holds: bool
    reason: str = ""
    runs: int = 1
    cpu_s: float = 0.0
    unsupported: bool = False


@dataclass
class SearchResult:
    """The answer of :func:`search`.

    ``limit``: the last value that holds (None unless ``outcome`` is
    ``found`` or ``holds_throughout``, where it is the range's far end);
    ``bracket``: (low, high) with the limit at one end and the first failing
    value at the other; ``direction``: ``"below"`` when values below the
    limit hold (dt, speed, mass ratio), ``"above"`` when values above it hold
    (solver iterations); ``failed_check``: why the failing end of the
    bracket fails; ``evaluations``: every (value, Verdict) in the order
    evaluated; ``rounds``: how many rounds of evaluations it took (one
    value each at width 1: :func:`search_rounds`)."""

    param: str
    lo: float
    hi: float
    tol: float
    outcome: str
    limit: float | None = None
    bracket: tuple[float, float] | None = None
    direction: str | None = None
    failed_check: str = ""
    evaluations: list[tuple[float, Verdict]] = field(default_factory=list)
    rounds: int = 0

    @property
    def runs(self) -> int:
        return sum(v.runs for _, v in self.evaluations)

    @property
    def cpu_s(self) -> float:
        return float(sum(v.cpu_s for _, v in self.evaluations))

    def as_dict(self) -> dict[str, Any]:
        return {"limit": self.limit, "bracket": list(self.bracket) if self.bracket else None,
                "failed_check": self.failed_check or None, "runs": self.runs, "cpu_s": self.cpu_s,
                "outcome": self.outcome, "direction": self.direction, "param": self.param,
                "range": [self.lo, self.hi], "tol": self.tol,
                "evaluations": [{"value": x, "holds": v.holds, "reason": v.reason or None} for x, v in self.evaluations]}


def _walk(lo: float, hi: float, log: bool, integer: bool) -> list[float]:
    """The walking grid from ``lo`` to ``hi`` (both included, ascending):
    steps of at most a factor 2 (log) or a quarter of the range (linear),
    at most MAX_WALK steps."""
    if log:
        n = min(MAX_WALK, max(1, math.ceil(math.log2(hi / lo) - 1e-9)))
        pts = [lo * (hi / lo) ** (i / n) for i in range(n + 1)]
    else:
        n = 4
        pts = [lo + (hi - lo) * i / n for i in range(n + 1)]
    pts[0], pts[-1] = lo, hi
    if integer:
        pts = sorted({int(round(p)) for p in pts})
    return pts


def _mid(a: float, b: float, log: bool, integer: bool) -> float:
    m = math.sqrt(a * b) if log else 0.5 * (a + b)
    if integer:
        m = int(round(m))
        if m in (a, b):
            m = int(min(a, b)) + 1
    return m


def _narrow(a: float, b: float, log: bool, integer: bool, tol: float, width: float) -> bool:
    lo, hi = min(a, b), max(a, b)
    if integer:
        return hi - lo <= 1
    if log:
        return hi / lo - 1.0 <= tol
    return hi - lo <= tol * width


def search(criterion: Callable[[float], Verdict], lo: float, hi: float, tol: float = 0.05,
           integer: bool = False, log: bool | None = None, param: str = "", width: int = 1) -> SearchResult:
    """Find where ``criterion`` stops holding between ``lo`` < ``hi``.

    ``log`` (default: both ends positive) bisects in log space; ``integer``
    keeps every value an integer.  See the module docstring for the walk and
    the tolerance.  ``width``: values evaluated per round
    (:func:`search_rounds`; 1: one at a time).  Raises ValueError for an
    empty or invalid range or tol.  The search itself is
    :func:`search_rounds`; this drives it with ``criterion``."""
    return drive(search_rounds(lo, hi, tol, integer, log, param, width),
                 lambda values: {x: criterion(x) for x in values})


def drive(steps: Generator[Any, Any, Any], answer: Callable[[Any], Any]) -> Any:
    """Run a step generator to its end, answering each value it yields with
    ``answer(value)``; returns the generator's return value."""
    try:
        question = next(steps)
        while True:
            question = steps.send(answer(question))
    except StopIteration as stop:
        return stop.value


def search_steps(lo: float, hi: float, tol: float = 0.05, integer: bool = False, log: bool | None = None,
                 param: str = "") -> Generator[float, Verdict, SearchResult]:
    """:func:`search_rounds` one value at a time (width 1): yields each
    value to evaluate, receives its Verdict, returns the SearchResult.
    Raises ValueError (at the first ``next``) for a bad range or tol."""
    rounds = search_rounds(lo, hi, tol, integer, log, param, 1)
    try:
        values = next(rounds)
        while True:
            verdict = yield values[0]
            values = rounds.send({values[0]: verdict})
    except StopIteration as stop:
        return stop.value


def _tree(good: float, bad: float, log: bool, integer: bool, tol: float, width: float) -> Iterator[float]:
    """The bisection's next midpoints from the bracket (good, bad), breadth
    first: the midpoint, then the midpoints of the half the search keeps if
    it holds and of the half it keeps if it fails, and so on, down to
    brackets narrower than ``tol``.  The first 2**d - 1 of them are every
    value the next d bisection steps may evaluate."""
    queue = [(good, bad)]
    for g, b in queue:  # the list grows as it is read: breadth first
        if _narrow(g, b, log, integer, tol, width):
            continue
        m = _mid(g, b, log, integer)
        yield m
        queue.append((m, b))
        queue.append((g, m))


def search_rounds(lo: float, hi: float, tol: float = 0.05, integer: bool = False, log: bool | None = None,
                  param: str = "", width: int | Callable[[], int] = 1
                  ) -> Generator[list[float], dict[float, Verdict], SearchResult]:
    """The search in rounds: yields a list of values to evaluate at once,
    receives {value: Verdict} for every one of them, returns the
    SearchResult.  ``width`` (a number, or a function asked before each
    round): values per round.

    A round's first value is the one the one-at-a-time search needs next;
    the others are the values it may need after it, in the order it would
    need them: the walk's next steps, or the bisection's next levels
    (:func:`_tree`: 3 values settle two bisection steps, 7 three, so rounds
    drop from log2 to log2 / d for 2**d - 1 values a round, a 2**d-ary
    search).  Every decision reads the same verdicts the one-at-a-time
    search reads, so outcome, limit, bracket, direction and failed check
    are its own for any criterion (monotone or not) and any width; a
    wider round only adds evaluations (``runs``) and cuts ``rounds``.
    Width 1 is the one-at-a-time search, value for value.  Tests:
    tests/test_limits.py::test_wider_rounds_give_the_same_answer_in_fewer_rounds.
    A scheduler runs many searches at once by holding their generators
    (harness/schedule.py).  Raises ValueError (at the first ``next``) for
    a bad range or tol."""
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"range: expected two finite numbers LO < HI, got {lo!r} {hi!r}")
    if not (0.0 < tol < 1.0):
        raise ValueError(f"tol: expected a relative tolerance 0 < tol < 1, got {tol!r}")
    if log is None:
        log = lo > 0
    if log and lo <= 0:
        raise ValueError(f"range: log-space search needs LO > 0, got {lo!r}")
    if integer:
        lo, hi = int(math.ceil(lo)), int(math.floor(hi))
        if lo >= hi:
            raise ValueError("range: expected at least two integers between LO and HI")
    res = SearchResult(param, lo, hi, tol, FAILS_THROUGHOUT)
    seen: dict[float, Verdict] = {}
    wide: Callable[[], int] = width if callable(width) else (lambda: int(width))

    def ev(x: float, ahead: Iterable[float]) -> Generator[list[float], dict[float, Verdict], Verdict]:
        """The verdict of ``x``; when not known, a round of ``x`` and the
        first unknown values of ``ahead``."""
        if x not in seen:
            n = max(1, int(wide()))
            values = [x]
            for e in ahead:
                if len(values) >= n:
                    break
                if e not in seen and e not in values:
                    values.append(e)
            got = yield values
            res.rounds += 1
            for v in values:
                seen[v] = got[v]
                res.evaluations.append((v, got[v]))
        return seen[x]

    grid = _walk(lo, hi, log, integer)
    first = yield from ev(grid[0], grid[1:])
    if first.unsupported:
        res.outcome, res.failed_check = UNSUPPORTED, first.reason
        return res
    if first.holds:
        res.direction = "below"
    else:
        last = yield from ev(grid[-1], grid[-2:0:-1])
        if not last.holds:
            res.failed_check = first.reason
            return res
        res.direction = "above"
        grid = grid[::-1]
    good, bad = grid[0], None
    for i, x in enumerate(grid[1:], 1):
        if (yield from ev(x, grid[i + 1:])).holds:
            good = x
        else:
            bad = x
            break
    if bad is None:
        res.outcome, res.limit = HOLDS_THROUGHOUT, good
        return res
    width_ = hi - lo
    while not _narrow(good, bad, log, integer, tol, width_):
        m = _mid(good, bad, log, integer)
        if (yield from ev(m, _tree(good, bad, log, integer, tol, width_))).holds:
            good = m
        else:
            bad = m
    res.outcome, res.limit = FOUND, good
    res.bracket = (min(good, bad), max(good, bad))
    res.failed_check = seen[bad].reason
    return res
