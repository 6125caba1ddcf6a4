"""The status vocabulary, defined once.

Run statuses (a row's ``status``, :class:`harness.runner.RunResult`):

- ``ok``: the run went to the end and its metrics were computed;
- ``unsupported``: the engine cannot model the scene (the message says why);
- ``failed``: the engine rejected the model at build time, or the run could
  not be started (unknown engine, adapter import error);
- ``error``: an exception while stepping, or the worker process running it
  died (a signal: abort, segfault, out-of-memory kill; the message names
  the signal and carries the tail of the worker's stderr);
- ``diverged``: a non-finite or runaway state;
- ``timeout``: the run spent its wall-clock budget (stopped between step
  blocks, or its worker killed by the watchdog when stuck in one call).

Check outcomes (``physbench check``, one JUnit testcase each): ``PASS``,
``FAIL``, ``XFAIL``, ``XPASS``, ``UNSUPPORTED``, ``ERROR``; the bad ones
(exit code 1) are FAIL, XPASS and ERROR.
"""

from __future__ import annotations

OK = "ok"
UNSUPPORTED = "unsupported"
FAILED = "failed"
ERROR = "error"
DIVERGED = "diverged"
TIMEOUT = "timeout"

#: every run status, in the order tables list them
RUN_STATUSES = (OK, UNSUPPORTED, FAILED, DIVERGED, TIMEOUT, ERROR)
#: statuses of a run that did not produce a usable result (a check on it is ERROR)
ERROR_STATUSES = (ERROR, FAILED, DIVERGED, TIMEOUT)
#: statuses of a run that ended without physics to judge (could not build,
#: raised, ran out of time): the report's stability matrix counts them
#: together as "error", apart from "diverged"
BROKEN_STATUSES = (ERROR, FAILED, TIMEOUT)

PASS = "PASS"
FAIL = "FAIL"
XFAIL = "XFAIL"
XPASS = "XPASS"
CHECK_UNSUPPORTED = "UNSUPPORTED"
CHECK_ERROR = "ERROR"

#: every check outcome, in the order tables list them
OUTCOMES = (PASS, FAIL, XFAIL, XPASS, CHECK_UNSUPPORTED, CHECK_ERROR)
#: outcomes that fail a check job (exit code 1)
BAD_OUTCOMES = (FAIL, XPASS, CHECK_ERROR)
