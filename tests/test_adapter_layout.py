"""The adapters stay thin (issue: a house that is easy to live in): each
engine's module is translation only, at most about 250 lines without
docstrings, and pymunk's private internals are used in one module only
(tests/test_adapter_pymunk.py::test_private_paths_equal_public_paths pins
that module against the public API)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ADAPTERS = Path(__file__).resolve().parent.parent / "adapters"
ENGINE_MODULES = ("reference", "mujoco", "pybullet", "pymunk", "rapier", "box2d", "drake", "mjx")
MAX_LINES = 260  # "about 250"
PYMUNK_PRIVATE = ("_chipmunk_cffi", "_add_later", "_remove_later", "_post_step_callbacks", "_bodies_to_check",
                  "_float_arr", "_int_arr")


def code_lines(path: Path) -> int:
    """Lines that are neither blank nor part of a module, class or function docstring."""
    src = path.read_text(encoding="utf-8")
    doc: set[int] = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            first = node.body[0] if node.body else None
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                doc.update(range(first.lineno, first.end_lineno + 1))
    return sum(1 for k, line in enumerate(src.splitlines(), 1) if k not in doc and line.strip())


@pytest.mark.parametrize("engine", ENGINE_MODULES)
def test_engine_adapter_is_thin(engine):
    n = code_lines(ADAPTERS / f"{engine}.py")
    print(f"adapters/{engine}.py: {n} lines without docstrings and blank lines")
    assert n <= MAX_LINES


def test_pymunk_internals_in_one_module():
    users = sorted(p.name for p in ADAPTERS.glob("*.py")
                   if any(name in p.read_text(encoding="utf-8") for name in PYMUNK_PRIVATE))
    assert users == ["pymunk_internals.py"]


def test_optional_import_names_why_an_engine_is_missing():
    """adapters.base.optional_import: a present package comes back with no
    reason (its submodules imported too); a missing one is (None, the
    import's error), never an exception -- the engine is then unavailable,
    the others unaffected."""
    from physbench.adapters.base import optional_import

    mod, why = optional_import("json", "json.decoder")
    assert why == "" and mod.__name__ == "json" and hasattr(mod, "decoder")
    mod, why = optional_import("no_such_engine_package_xyz")
    assert mod is None
    assert why.startswith("import no_such_engine_package_xyz failed: ModuleNotFoundError:")
    mod, why = optional_import("json", "json.no_such_submodule_xyz")
    assert mod is None and "json.no_such_submodule_xyz" in why
