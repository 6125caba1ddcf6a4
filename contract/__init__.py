"""The scene contract: the bottom layer, imported by everyone and importing
nothing of ours (docs/ARCHITECTURE.md; tests/test_architecture.py).

- :mod:`contract.spec`: the TOML schema, bounds and load-time validation;
- :mod:`contract.scene`: compiling and loading scenes (and the names of the
  scene's types, re-exported);
- :mod:`contract.scene_model`: the engine-neutral compiled scene and its content hash;
- :mod:`contract.shapes`: volumes, principal inertias and pattern expansion;
- :mod:`contract.models`: the reference-model registry (names only) and the
  load-time model check;
- :mod:`contract.metric_defs`: the harness's metric names and when each has a value;
- :mod:`contract.phase`: step phases (the start moved back along free flight);
- :mod:`contract.rotation`: quaternions, rotation matrices, angular-velocity frames;
- :mod:`contract.conventions`: the planar (x-z) mapping of 2D engines.
"""
