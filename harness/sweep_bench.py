"""``python -m physbench.harness.sweep_bench``: the sweep scaling benchmark's
command, kept under its old name; the benchmark is
:mod:`physbench.harness.selfbench.sweep`."""

if __name__ == "__main__":  # pragma: no cover
    import sys

    from physbench.harness.selfbench.sweep import main

    sys.exit(main())
