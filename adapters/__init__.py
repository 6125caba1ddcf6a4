"""Engine adapters.  Each module holds one Adapter subclass; the registry
imports them lazily so that a missing engine only affects its own runs."""

from __future__ import annotations

import importlib

from physbench.adapters.base import Adapter, Capabilities, Setting, Unsupported, engine_names, get_adapter, register

ENGINES = ("reference", "mujoco", "pybullet", "pymunk", "drake", "mjx")


def _loader(module: str, cls: str):
    def load() -> type[Adapter]:
        return getattr(importlib.import_module(f"physbench.adapters.{module}"), cls)

    return load


register("reference", _loader("reference", "ReferenceAdapter"))
register("mujoco", _loader("mujoco", "MujocoAdapter"))
register("pybullet", _loader("pybullet", "PybulletAdapter"))
register("pymunk", _loader("pymunk", "PymunkAdapter"))
register("drake", _loader("drake", "DrakeAdapter"))
register("mjx", _loader("mjx", "MjxAdapter"))

__all__ = ["Adapter", "Capabilities", "Setting", "Unsupported", "ENGINES", "engine_names", "get_adapter"]
