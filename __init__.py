"""physbench: an engine-agnostic validation and benchmark harness for
rigid-body physics.

The one import package.  Its subpackages live in the repository's top-level
folders (pyproject.toml maps them): ``physbench.contract`` (the scene
contract), ``physbench.engine`` (the reference engine), ``physbench.adapters``
(one module per engine) and ``physbench.harness`` (runs, metrics, checks,
sweeps, reports and the command line).  This module imports nothing.
"""
