"""``python -m physbench.engine``: compile (or load) the engine's kernels into the
on-disk cache and print the seconds it took -- ahead of a first run on a
fresh machine (a CI job, an image build), so the first scene does not pay
for it.  Builds what the scenes of :data:`WARM` build at the default
settings -- boxes on a plane, and spheres on a plane numerous enough for
the broad phase to sweep: their kernels (:func:`engine.jit.warm_up`) and
the fused steady step of either broad phase (the same for every shape:
engine.collision.collide.family_table), every shape-pair family's
function, the flight step of a scene without contact and the joint step
of a hinged body (engine/README.md
"Compiled code and compile time").  A scene of other settings may still
compile a kernel of its own.

numba compiles on one core, so with ``--jobs 2`` (the default where the
machine has two cores or more) the two halves of the warm-up -- the
collision side (:func:`engine.jit.warm_collision`) in a second process,
the dynamics (:func:`engine.jit.warm_dynamics`) in this one -- compile at
once; then this process loads them from the cache and compiles the fused
steps, which need both."""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import time

from physbench.engine import SETTINGS, Engine, jit
from physbench.engine.cache import cache_dir
from physbench.engine import compile_share
from physbench.engine.compile_share import JOBS_ENV
from physbench.engine.broadstage import SAP_MIN_BODIES
from physbench.engine.fused.steady import warm_scene

#: the contact scenes whose kernels are compiled ahead: (shapes, plane):
#: all pairs and the sweep
WARM = ((("box", "box"), True), (("sphere",) * (SAP_MIN_BODIES + 1), True))


def _joint_scene():
    """:func:`warm_scene` without contact, its first body hung on a hinge
    (about y, 0.5 m above its centre) to the world: the joint step's
    kernels, which every joint scene shares."""
    import numpy as np

    from physbench.engine.mathutil import quat_to_matrix

    inp = warm_scene()
    q = np.asarray(inp.q, float)[0]
    R = quat_to_matrix((q / np.linalg.norm(q)).reshape(1, 4))[0]
    arm = np.array([0.0, 0.0, 0.5])
    y = np.array([0.0, 1.0, 0.0])
    hinge = ("revolute", 0, -1, arm, np.asarray(inp.x, float)[0] + R @ arm, R.T @ y, y)
    return dataclasses.replace(inp, effects=frozenset({"gravity", "joint"}), joints=(hinge,))


def _help_build(path: str) -> int:
    """A cold build's helper (engine/compile_share.py): build the scene
    written to ``path`` (then removed) with its settings, taking the kernel
    groups in reverse order."""
    import contextlib
    from pathlib import Path

    compile_share.REVERSED = True
    try:
        inp, settings = compile_share.read_build(Path(path))
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
    Engine(inp, settings)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m physbench.engine", description=__doc__.split("\n\n")[0])
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    ap.add_argument("--jobs", type=int, default=min(2, cores), choices=(1, 2),
                    help="processes compiling at once (default: 2 where this process may use two cores or more)")
    ap.add_argument("--part", choices=("collision",), help=argparse.SUPPRESS)  # the second process's half
    ap.add_argument("--help-build", help=argparse.SUPPRESS)  # a build's helper (engine/compile_share.py)
    args = ap.parse_args(argv)
    if args.help_build:
        return _help_build(args.help_build)
    os.environ[JOBS_ENV] = "1"  # (the builds below start no helper: the halves are split here)
    t0 = time.perf_counter()
    if args.part:
        jit.warm_collision()  # every family's function
        return 0
    if args.jobs > 1:
        other = subprocess.Popen([sys.executable, "-m", "physbench.engine", "--part", "collision"])
        jit.warm_dynamics(SETTINGS["integrator"][0])  # (the default integrator's flight)
        if other.wait() != 0:  # whatever it missed, the warm-up below compiles here
            print("python -m physbench.engine: the collision half's process failed; compiling it here", file=sys.stderr)
    for shapes, plane in WARM:  # the warm-up's kernels and each one's fused steady step
        Engine(warm_scene(shapes, plane))
    Engine(dataclasses.replace(warm_scene(), effects=frozenset({"gravity"})))  # the flight step
    Engine(_joint_scene())  # the joint step and its loop (engine/joints/)
    print(f"engine kernels compiled or loaded in {time.perf_counter() - t0:.1f} s with {args.jobs} process(es) "
          f"(cache: {cache_dir()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
