"""physbench's benchmarks of itself, apart from the product's run path:
what a sweep's client, scheduler and workers cost and how a sweep scales
(:mod:`.sweep`, ``python -m physbench.harness.selfbench.sweep``), the
executors' overhead per item and the cost of isolating a run in a worker
process (:mod:`.executors`, ``physbench bench isolation``), and what
tracing costs (:mod:`.trace_cost`, ``python -m
physbench.harness.selfbench.trace_cost``).  Nothing of the product
imports these modules; the command line reaches them when asked.
"""
