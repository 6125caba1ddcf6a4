"""The fast path of the step: whole steps as compiled calls, behind one door.

:func:`advance` is the only way in.  The step loop (engine/pipeline.py)
calls it before it steps stage by stage; it runs up to ``n`` steps as
compiled calls and returns how many it ran.  Which compiled step a scene
has is decided once, with the plan (:func:`build`):

* :class:`engine.fused.loop.FlightStep` -- a scene without contact: every
  step is one call (loop.py);
* :class:`engine.fused.steady.SteadyStep` -- a contact scene whose stages
  the fused step covers (steady.py): a steady step (the solve keeps the
  last contact graph) or a contact-free one is one call, and consecutive
  ones run inside one compiled loop; the loop stops at the first step that
  is not steady;
* None -- every step is staged.

Both compiled steps begin with the same flight part (part.py: the start,
the force stages of engine.forces.FORCES, the gyroscopic stages, the free
flight as the staged stage's own call).

The contract between the two paths: a step run here gives the bits of the
same step run stage by stage, and leaves the same bookkeeping (profile
counts, ``state.t``, ``state.steps``, the warm-start cache, the contacts).
tests/test_engine_steady.py, tests/test_engine_steady_gyro.py,
tests/test_engine_loop.py and tests/test_engine_force_table.py pin it.
"""

from __future__ import annotations

from physbench.engine.fused.loop import FlightStep
from physbench.engine.fused.steady import CCD, FAIL, NONE, SteadyStep

#: most steps a failed try makes the next tries wait
MAX_BACKOFF = 64


class Backoff:
    """When the door tries a call again after a try of it that FAILed (a
    step that was not steady: nothing of it was kept, the staged step ran
    it from its start): it waits 1, 2, 4 ... ``MAX_BACKOFF`` steps while
    the tries keep failing; a try that ran a step starts over.  The wait
    is for the call that failed (``what``, the compiled step's
    ``call()``): a scene whose contact-free call failed at a landing tries
    the steady call as soon as its solve is steady.  The first wait of a
    run of failures is skipped when the staged step kept a steady solve
    of another contact graph than the one the failed try was made with
    (``kept``, the compiled step's ``kept()``): a contact that came or
    went fails the try that meets it, and the graph the staged step kept
    is what the next try checks against (a block whose speculative
    contacts appear as it speeds up).  A graph that keeps changing fails
    again and waits 2, 4 ... as before
    (tests/test_engine_loop.py::test_backoff_retries_at_once_after_a_new_contact_graph)."""

    __slots__ = ("wait", "span", "what", "kept")

    def __init__(self) -> None:
        #: steps left to wait before the next try
        self.wait = 0
        #: the last wait (0: the last try ran a step)
        self.span = 0
        #: the call that failed last
        self.what = None
        #: the steady solve (its contact graph) the failed try was made with
        self.kept = None

    def ready(self, what, kept=None) -> bool:
        """Whether this step tries the call ``what`` with the kept steady
        solve ``kept`` (a waiting step counts down)."""
        if self.wait and what == self.what:
            if self.span == 1 and kept is not None and kept is not self.kept:
                self.wait = 0  # (a new contact graph since the first failure: try it)
                return True
            self.wait -= 1
            return False
        return True

    def failed(self, what, kept=None) -> None:
        self.span = min(2 * self.span, MAX_BACKOFF) if self.span and what == self.what else 1
        self.wait = self.span
        self.what = what
        self.kept = kept

    def passed(self) -> None:
        self.span = 0
        self.kept = None


def build(model, stages, turn=None):
    """The plan's compiled step for ``stages`` (module doc), or None;
    ``turn`` the plan's rotation split's limit (pipeline._turn_limit)."""
    return FlightStep.build(model, stages) or SteadyStep.build(model, stages, turn)


def advance(model, state, ctx, plan, n: int, rec=None) -> tuple[int, int]:
    """Up to ``n`` steps from ``state`` as compiled calls (module doc).

    ``plan`` the step loop's plan (``plan.fast`` the compiled step,
    ``plan.backoff`` the door's :class:`Backoff`); ``rec`` (pos, quat, vel,
    angvel) blocks (n, n_bodies, 3|4) of float64 that get the state after
    step i in row i, or None.  Returns (steps done, stop), ``stop`` what
    stopped it at the next step:

    * ``NONE`` -- it did not try it (the caller may call again when steps
      were done; else the step is staged);
    * ``FAIL`` -- it was not steady: nothing of it kept, the staged step
      runs it from its start;
    * ``CCD`` -- it ran as far as its CCD stage (a pair moved far enough
      to need the end-pose collision), and the staged step goes on from
      there.

    Nothing is tried while the profile times each stage
    (``Profile.by_stage``) or while the backoff waits."""
    fast = plan.fast
    if fast is None or ctx.profile.by_stage:
        return 0, NONE
    what = fast.call()
    kept = fast.kept()
    if not plan.backoff.ready(what, kept):
        return 0, NONE
    done, status = fast.advance(model, state, ctx, plan, n, rec)
    if done:
        plan.backoff.passed()
    if status == FAIL:  # (the try that stopped the steps: the same rule whatever ran before it)
        # (the solve the failing try checked: after done steps, the kept one now)
        plan.backoff.failed(what, fast.kept())
    return done, status


__all__ = ["Backoff", "FlightStep", "SteadyStep", "advance", "build", "CCD", "FAIL", "MAX_BACKOFF", "NONE"]
