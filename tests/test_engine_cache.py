"""The compiled kernels' on-disk cache follows every engine source file.

numba invalidates a cached kernel only when the kernel's own file changes;
a kernel inlining a kernel of another file would keep stale machine code
(``prepare.patch_rows`` changed while ``phases.solve_stage``, which calls it,
was cached).  engine/cache.py names the cache directory by a digest of all
engine sources; these tests pin that.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import physbench.engine  # noqa: F401  (configures the cache)

from physbench import engine
from physbench.engine import cache


def _copy(tmp_path: Path) -> Path:
    dst = tmp_path / "engine"
    shutil.copytree(cache.ROOT, dst, ignore=shutil.ignore_patterns("__pycache__"))
    return dst


def test_digest_changes_with_any_engine_source(tmp_path):
    root = _copy(tmp_path)
    d0 = cache.source_digest(root)
    assert cache.source_digest(root) == d0  # stable
    for rel in ("contact/prepare.py", "collision/box.py", "pipeline.py"):
        p = root / rel
        text = p.read_bytes()
        p.write_bytes(text + b"\n# edited\n")
        assert cache.source_digest(root) != d0, rel
        p.write_bytes(text)
        assert cache.source_digest(root) == d0
    (root / "contact" / "new_stage.py").write_text("X = 1\n")
    assert cache.source_digest(root) != d0


def test_digest_ignores_compiled_files(tmp_path):
    root = _copy(tmp_path)
    d0 = cache.source_digest(root)
    (root / "__pycache__").mkdir()
    (root / "__pycache__" / "x.nbi").write_bytes(b"index")
    assert cache.source_digest(root) == d0


def test_kernels_are_cached_under_the_digest_directory():
    from numba.core import config

    from physbench.engine.contact import phases, prepare

    d = cache.cache_dir()
    assert d.name == f"numba-{cache.source_digest()}"
    assert Path(config.CACHE_DIR) == d
    for kernel in (phases.solve_stage, prepare.patch_rows):
        path = Path(kernel._cache._cache_path)
        assert d in path.parents, (kernel, path)


def test_user_cache_dir_is_the_base(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert cache.cache_dir() == tmp_path / f"numba-{cache.source_digest()}"


def test_the_cache_does_not_depend_on_where_the_engine_lies():
    """A kernel's cache path and stamp name no absolute path and no file
    time: an installed wheel, a CI runner's fresh workspace and a checkout
    with the same engine sources share one cache (issue 39)."""
    from physbench.engine.contact import phases

    impl = phases.solve_stage._cache._impl
    loc = impl.locator
    assert type(loc).__name__ == "EngineCacheLocator"
    assert Path(loc.get_cache_path()) == cache.cache_dir() / "contact"
    assert str(cache.ROOT) not in loc.get_cache_path()
    assert loc.get_source_stamp() == cache.source_digest()
    # the same kernel file under another root maps to the same place
    other = type(loc).from_function(phases.solve_stage.py_func, str(cache.ROOT / "contact" / "phases.py"))
    assert other.get_cache_path() == loc.get_cache_path()
    assert type(loc).from_function(phases.solve_stage.py_func, "/elsewhere/x.py") is None


def test_nothing_is_cached_inside_the_package(monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert cache.ROOT not in cache.cache_dir().parents


def test_a_kernel_numba_cannot_cache_warns_and_does_not_crash():
    """numba names the kernel's file in the warning it gives for a kernel it
    cannot cache (lifted loops, dynamic globals: it happens at NUMBA_OPT=0);
    the engine's locator must carry that file, or the build dies with an
    AttributeError instead of running uncached."""
    import types
    import warnings

    from physbench.engine.contact import phases

    impl = phases.solve_stage._cache._impl
    assert impl.locator._py_file.endswith("phases.py")
    cres = types.SimpleNamespace(lifted=[types.SimpleNamespace(can_cache=False)],
                                 library=types.SimpleNamespace(has_dynamic_globals=False),
                                 fndesc=types.SimpleNamespace(qualname="solve_stage"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert impl.check_cachable(cres) is False
    assert any("Cannot cache" in str(w.message) and w.filename.endswith("phases.py") for w in caught)
