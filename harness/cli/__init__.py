"""``physbench`` command line: the user's three jobs.

    physbench run SCENARIO|FILE [--engine E] [--variant V] [--set k=v]... [--json]
    physbench check [SCENARIO|FILE|DIR ...] [--engines ...] [--tags ...] [--junit FILE] [--traces DIR]
    physbench trace SCENARIO|FILE [--engines ...] [--variant V] [--watch] -o FILE.rrd
    physbench limits SCENARIO|FILE --engine E --param KEY --range LO HI [--phases N] [--tol REL] [--json]
    physbench engines [--json]
    physbench models [NAME] [--json]
    physbench list

``--set`` takes either an engine setting (``dt=0.002``, ``integrator=rk4``) or a
dotted key path into the spec (``material.default.restitution=0.5``,
``body[0].velocity=[3,0,0]``).  Values are TOML (``true``, ``1e-3``,
``"rk4"``); a bare word is a string.

``run`` evaluates the scene's checks that apply to the run as ``check``
does (making the step-phase and ``@dt=...`` runs they need) and lists them.

Exit codes: 0 success, 1 a check failed unexpectedly (FAIL, XPASS, ERROR;
check and run) or the run's status is not ok (run), 2 bad input (spec,
settings, arguments, unknown scenario ids).
"""

from __future__ import annotations

import sys

from contract.spec import SpecError
from harness.cli.common import UsageError
from harness.cli.parser import build_parser


def main(argv: list[str] | None = None) -> int:
    from harness.execute import register_env_adapters

    register_env_adapters()
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except SpecError as e:
        for line in e.errors:
            print(f"error: {line}", file=sys.stderr)
        return 2
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2

