"""Engine adapters.  Each module holds one Adapter subclass; the registry
imports them lazily so that a missing engine only affects its own runs.

The shipped engines are registered here, one line each (and named in
:data:`ENGINES`); plug-in engines come from the ``physbench.adapters``
entry points of installed distributions (contract/plugins.py), registered
after them under their entry-point names.  A plug-in whose name is already
taken is not registered: :data:`PLUGIN_PROBLEMS` says so (``physbench
engines`` shows it).
"""

from __future__ import annotations

import importlib

from physbench.adapters.base import (Adapter, Capabilities, Setting, Unsupported, engine_names, engine_origin,
                                     get_adapter, register, set_origin)
from physbench.contract.plugins import ADAPTERS_GROUP, plugins

ENGINES = ("reference", "mujoco", "pybullet", "pymunk", "rapier", "box2d", "drake", "mjx")


def _loader(module: str, cls: str):
    def load() -> type[Adapter]:
        return getattr(importlib.import_module(f"physbench.adapters.{module}"), cls)

    return load


register("reference", _loader("reference", "ReferenceAdapter"))
register("mujoco", _loader("mujoco", "MujocoAdapter"))
register("pybullet", _loader("pybullet", "PybulletAdapter"))
register("pymunk", _loader("pymunk", "PymunkAdapter"))
register("rapier", _loader("rapier", "RapierAdapter"))
register("box2d", _loader("box2d", "Box2dAdapter"))
register("drake", _loader("drake", "DrakeAdapter"))
register("mjx", _loader("mjx", "MjxAdapter"))

for _name in engine_names():  # the lines above: shipped with physbench
    set_origin(_name, "physbench")

#: plug-ins that were not registered, each with the reason
PLUGIN_PROBLEMS: list[str] = []
for _p in plugins(ADAPTERS_GROUP):
    if _p.name in engine_names():
        PLUGIN_PROBLEMS.append(f"{_p.name} = {_p.value!r} ({_p.dist}): not registered, the name is taken by "
                               f"{engine_origin(_p.name)}'s {_p.name}")
    else:
        register(_p.name, _p.load, _p.dist)

__all__ = ["Adapter", "Capabilities", "Setting", "Unsupported", "ENGINES", "PLUGIN_PROBLEMS", "engine_names",
           "engine_origin", "get_adapter"]
