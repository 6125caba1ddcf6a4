"""physbench's in-house reference engine: 3D rigid bodies, accurate by
default.  See engine/README.md for the pipeline, stages, settings and why the
defaults are what they are.

Use::

    from physbench.engine import Engine
    eng = Engine(inp, {"dt": 1e-3})   # inp: engine.model.SceneInput; settings: defaults from SETTINGS
    eng.step(100)
    eng.state.x, eng.state.q, eng.state.v, eng.state.w
    eng.profile.as_dict()
"""

from __future__ import annotations

import sys
import threading
from typing import Any, Mapping

from physbench.engine import cache as _cache
from physbench.engine.settings import INTEGRATORS, JOINT_KINDS, SETTINGS, default_settings, version

#: the engine's modules that import no numba: this package, its settings
#: table and version (engine/settings.py) and the cache's bookkeeping load
#: without it, so an adapter's capabilities and the environment fingerprint
#: cost no numba import (tests/test_engine_settings.py::test_settings_and_version_import_no_numba)
NUMBA_FREE = frozenset({f"{__name__}.cache", f"{__name__}.settings"})

_configuring = threading.Lock()


class _ConfigureCacheFirst:
    """A finder on ``sys.meta_path`` that finds nothing: before the first
    engine module outside :data:`NUMBA_FREE` is imported, it registers the
    engine's kernel cache with numba (:func:`engine.cache.configure`:
    numba fixes a kernel's cache location when the kernel is defined, and
    every kernel is defined in such a module), then leaves ``sys.meta_path``.
    tests/test_engine_cache.py::test_kernels_are_cached_under_the_digest_directory
    and tests/test_engine_settings.py::test_the_cache_is_configured_before_the_first_kernel."""

    @staticmethod
    def find_spec(name: str, path: Any = None, target: Any = None) -> None:
        if name.startswith(f"{__name__}.") and name not in NUMBA_FREE:
            configure_cache()
        return None


def configure_cache() -> None:
    """Register the engine's kernel cache with numba (once a process);
    runs by itself before the first kernel module is imported."""
    with _configuring:
        if _ConfigureCacheFirst in sys.meta_path:
            _cache.configure()
            sys.meta_path.remove(_ConfigureCacheFirst)


if not any(m.startswith(f"{__name__}.") and m not in NUMBA_FREE for m in sys.modules):
    sys.meta_path.insert(0, _ConfigureCacheFirst)
else:  # pragma: no cover - kernel modules loaded without this package (a reload): configure now
    _cache.configure()


class Engine:
    """Convenience wrapper: model, state, pipeline and profile for a scene
    given as a :class:`engine.model.SceneInput` (the reference adapter's
    ``scene_input`` translates a harness scene; ``engine_for`` does both)."""

    def __init__(self, inp, settings: Mapping[str, Any] | None = None):
        from physbench.engine.model import build_model
        from physbench.engine.pipeline import build_pipeline, prepare
        from physbench.engine.profile import Profile
        from physbench.engine.state import State

        from physbench.engine.jit import helped

        full = default_settings(inp)
        full.update(settings or {})
        self.model = build_model(inp, full)
        self.state = State.from_model(self.model)
        with helped(inp, full, self.model):  # (a cold cache: a helper process compiles at once)
            self.stages = build_pipeline(self.model)
        self.profile = Profile()
        for s in self.stages:
            self.profile.register(s.name)
        prepare(self.model, self.state, self.stages, self.profile)  # (what the first steps would make)

    def step(self, n: int = 1) -> None:
        from physbench.engine.pipeline import advance

        advance(self.model, self.state, self.stages, self.profile, n)


__all__ = ["Engine", "INTEGRATORS", "JOINT_KINDS", "SETTINGS", "configure_cache", "default_settings", "version"]
