"""``physbench compile``: the reference engine's kernels into the on-disk
cache ahead of a first run (a CI job before its check, an image build),
talking while it compiles (harness/compile_progress.py).  The work is
``python -m physbench.engine``'s (engine/__main__.py), which stays as an
alias; this wraps it with the progress line."""

from __future__ import annotations

import argparse

from physbench.harness.compile_progress import watch


def cmd_compile(args: argparse.Namespace) -> int:
    # numba (and its cache directory set): loaded by this command only, not at every start
    from physbench.engine import __main__ as engine_main

    watch()
    return int(engine_main.main([] if args.jobs is None else ["--jobs", str(args.jobs)]) or 0)
