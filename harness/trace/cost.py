"""``python -m physbench.harness.trace.cost``: the tracing cost benchmark's
command, kept under its old name; the benchmark is
:mod:`physbench.harness.selfbench.trace_cost`."""

if __name__ == "__main__":  # pragma: no cover
    import sys

    from physbench.harness.selfbench.trace_cost import main

    sys.exit(main())
