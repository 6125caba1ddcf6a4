"""physbench harness: spec loading, runner, metrics, references, conformance,
traces, results store and CLI."""

__version__ = "0.1.0"
