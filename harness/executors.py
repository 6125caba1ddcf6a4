"""Choosing an executor by name: the one place that knows every kind.

``harness.execute`` has the run request, the local worker pool and the
in-process executor; ``harness.dask_executor`` the Dask one, built on the
worker pool.  Both are imported from here, so neither imports the other's
caller (tests/test_architecture.py::test_no_import_cycles).
"""

from __future__ import annotations

from typing import Callable

from physbench.harness.dask_executor import DaskExecutor  # imports Dask only when one is made
from physbench.harness.execute import InlineExecutor, WorkerPool

#: executor names: ``serial`` is an alias of ``inline`` (no isolation)
EXECUTOR_KINDS = ("process", "inline", "serial", "dask")


def make_executor(kind: str = "process", jobs: int = 1, scheduler: str | None = None,
                  log: Callable[[str], None] | None = None):
    """``process``: a :class:`WorkerPool` of ``jobs`` workers; ``inline``
    (alias ``serial``): :class:`InlineExecutor`; ``dask``: a
    harness.dask_executor.DaskExecutor on the cluster at ``scheduler``, or
    on a LocalCluster of ``jobs`` workers (``log`` gets its description).
    A ``scheduler`` is only for ``dask``."""
    if scheduler and kind != "dask":
        raise ValueError(f"a scheduler address is for the dask executor, not {kind!r}")
    if kind == "process":
        return WorkerPool(jobs)
    if kind in ("inline", "serial"):
        return InlineExecutor()
    if kind == "dask":
        return DaskExecutor(jobs, scheduler, log)
    raise ValueError(f"executor {kind!r}: expected one of {', '.join(EXECUTOR_KINDS)}")
