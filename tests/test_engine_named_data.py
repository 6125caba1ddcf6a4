"""The engine's compiled kernels take few arguments (issue 42, "named
data"): arrays that travel together are named tuples (engine/contact/
packs.py, engine/geometry.py, engine.broadstage.Motion ...), read by name,
so no kernel needs a long positional argument list.

A scan of the engine's sources (no import, no compile) counts the
parameters of every function decorated with numba's ``njit``/``jit``.
Every kernel stays at or below ``CEILING``, except the ones listed in
``OVER`` with the count they have today: a kernel may shrink, never grow,
and one that came down to the ceiling must leave the list."""

from __future__ import annotations

import ast
from pathlib import Path

ENGINE = Path(__file__).resolve().parent.parent / "engine"

#: the most parameters a compiled kernel takes
CEILING = 15

#: the kernels still above the ceiling, with their parameter counts: the
#: time-of-impact gap
#: (called from the Python search loop, where a named tuple argument costs
#: ~0.7-0.9 us more to dispatch than its arrays one by one, ~1.1 us a call)
OVER = {
    "ccd_gap.py::gap": 16,
}


def _is_kernel(fn: ast.FunctionDef) -> bool:
    for d in fn.decorator_list:
        f = d.func if isinstance(d, ast.Call) else d
        name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
        if name in ("njit", "jit"):
            return True
    return False


def _params(fn: ast.FunctionDef) -> int:
    a = fn.args
    return len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None) + (a.kwarg is not None)


def kernel_arguments(root: Path = ENGINE) -> dict[str, int]:
    """{"<file relative to root>::<kernel>": parameter count} of every
    function under ``root`` decorated with ``njit`` or ``jit`` (called or
    not, as a name or an attribute)."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef) and _is_kernel(node):
                out[f"{path.relative_to(root).as_posix()}::{node.name}"] = _params(node)
    return out


def test_the_scan_counts_parameters_of_decorated_functions(tmp_path):
    """The scan itself: kernels decorated every way the engine writes it,
    counted; a plain function and a nested helper's parameters not."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "k.py").write_text(
        "import numba\nfrom numba import njit\n\n"
        "@njit(cache=True)\ndef a(x, y, *z, w=1, **k):\n    pass\n\n"
        "@njit\ndef b(x):\n    pass\n\n"
        "@numba.jit(nopython=True)\ndef c(x, y, z):\n    pass\n\n"
        "def plain(p, q, r, s):\n    pass\n")
    assert kernel_arguments(tmp_path) == {"sub/k.py::a": 5, "sub/k.py::b": 1, "sub/k.py::c": 3}


def test_no_kernel_takes_more_arguments_than_the_ceiling():
    counts = kernel_arguments()
    assert len(counts) > 150  # the scan sees the engine's kernels
    over = {k: n for k, n in counts.items() if n > CEILING}
    grown = {k: (n, OVER.get(k)) for k, n in over.items() if k not in OVER or n > OVER[k]}
    assert not grown, f"kernels above {CEILING} arguments (count, allowed): {grown}"
    stale = sorted(k for k in OVER if counts.get(k, 0) <= CEILING)
    assert not stale, f"at or below the ceiling now (or gone): drop them from OVER: {stale}"


def test_the_contact_solve_and_broad_phase_take_named_data():
    """The kernels that took the longest lists (solve_contacts 58,
    _broad_step 35, prepare.rows 34, propagate._resolve 33 arguments) take
    named tuples."""
    counts = kernel_arguments()
    for k in ("contact/phases.py::solve_contacts", "contact/phases.py::solve_stage",
              "contact/phases.py::classify_stage", "contact/prepare.py::rows", "contact/prepare.py::classify",
              "broadstage.py::_broad_step", "ccd_end.py::end_pose_candidates", "collision/collide.py::collide",
              "contact/gauss_seidel.py::iterate", "contact/propagate.py::_resolve", "ccd_end.py::missed_candidates"):
        assert counts[k] <= CEILING, (k, counts[k])
    assert counts["contact/phases.py::solve_contacts"] <= 8
    assert counts["broadstage.py::_broad_step"] <= 7
