"""Plug-ins through entry points, the Python packaging convention pytest's
plug-ins use: a distribution declares, in its ``pyproject.toml``::

    [project.entry-points."physbench.adapters"]
    myengine = "mypackage.adapter:MyEngineAdapter"

    [project.entry-points."physbench.models"]
    my_model = "mypackage.model:MyModel"

and, once installed, ``myengine`` is an engine (``physbench engines``) and
``my_model`` a reference model (``physbench models``).  This module only
reads the declarations (names, ``module:Class`` references and the
distribution they come from); nothing is imported until a run or a scene
asks for it, so a broken plug-in costs its own rows only (adapters/__init__.py,
contract/models.py).  Test: tests/test_install.py::test_a_plugin_distribution_adds_an_engine_and_a_model.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any, Callable

#: entry-point group of engine adapters (name -> module:Class, an adapters.base.Adapter subclass)
ADAPTERS_GROUP = "physbench.adapters"
#: entry-point group of reference models (name -> module:Class, a harness.references.ReferenceModel subclass)
MODELS_GROUP = "physbench.models"


@dataclass(frozen=True)
class Plugin:
    """One declared plug-in: its ``name``, ``module:Class`` reference,
    the distribution ``dist`` it comes from ("name version") and its loader."""

    name: str
    value: str
    dist: str
    load: Callable[[], Any]


def plugins(group: str) -> list[Plugin]:
    """The plug-ins installed for ``group``, in the order the environment
    lists them (a distribution whose metadata cannot be read is skipped)."""
    out = []
    try:
        eps = entry_points(group=group)
    except Exception:  # unreadable metadata in the environment: no plug-ins rather than no CLI
        return []
    for ep in eps:
        dist = getattr(ep, "dist", None)
        label = f"{dist.name} {dist.version}" if dist is not None else "unknown distribution"
        out.append(Plugin(ep.name, ep.value, label, ep.load))
    return out
