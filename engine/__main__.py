"""``python -m engine``: compile (or load) the engine's kernels into the
on-disk cache and print the seconds it took -- ahead of a first run on a
fresh machine (a CI job, an image build), so the first scene does not pay
for it.  Builds what a contact scene and a scene without contact build:
every kernel of :func:`engine.jit.warm_up`, the fused steady step and the
flight step, at the default settings (engine/README.md "Compile time").
A scene with other settings may still compile a kernel of its own."""

from __future__ import annotations

import dataclasses
import time

from engine import Engine
from engine.cache import cache_dir
from engine.steady import warm_scene


def main() -> None:
    t0 = time.perf_counter()
    Engine(warm_scene())  # the warm-up's kernels and the fused steady step
    Engine(dataclasses.replace(warm_scene(), effects=frozenset({"gravity"})))  # the flight step
    print(f"engine kernels compiled or loaded in {time.perf_counter() - t0:.1f} s (cache: {cache_dir()})")


if __name__ == "__main__":
    main()
