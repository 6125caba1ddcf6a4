"""The import rules of docs/ARCHITECTURE.md, enforced: every module outside
the tests is parsed (imports inside functions count; imports under
``if TYPE_CHECKING:`` do not, they never run), and

- no module imports a module of a higher layer;
- the contract imports nothing of ours; the engine imports only the engine;
- adapters never import the harness, and only the reference adapter
  imports the engine; only the listed harness modules import the engine;
- there is no import cycle between modules (importing ``a.b.c`` from
  outside package ``a.b`` also runs ``a/b/__init__.py``, so that counts;
  a module inside the package was itself reached through it).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("contract", "engine", "adapters", "harness")

# Layers, bottom to top: (rank, module prefixes).  A module belongs to the
# longest prefix that matches; a harness module not named here is in the
# run/metrics layer.  Imports go to the same or a lower rank only (same-rank
# imports are fine while they make no cycle).
LAYERS: list[tuple[int, tuple[str, ...]]] = [
    (0, ("contract", "engine")),
    (1, ("adapters",)),
    (2, ("harness",)),  # run, execute, metrics, geometry, references, results, status, fingerprint, trace
    (3, ("harness.conformance",)),  # check
    (4, ("harness.limits", "harness.limit_eval", "harness.limit_search", "harness.sweep", "harness.suite",
         "harness.points", "harness.sweep_store", "harness.schedule", "harness.sweep_bench", "harness.bench")),  # sweep, limits, bench
    (5, ("harness.report",)),  # report
    (6, ("harness.cli",)),  # the command line
]
# Import cycles known today, each a strongly connected set of modules.  The
# test fails when one disappears as well as when a new one forms, so this
# list only shrinks (the engine's last one, profile -> jit ->
# collision.dispatch -> profile, went when the profile took over the JIT
# seconds' bookkeeping).
KNOWN_CYCLES: list[list[str]] = []
# harness modules that use the engine directly (all others go through adapters)
ENGINE_USERS = {"harness.fingerprint", "harness.bench"}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            rel = p.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


MODULES = _modules()


def _resolve(name: str) -> str | None:
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _with_parents(mod: str, importer: str) -> list[str]:
    """``mod`` and the packages above it that importing it runs, leaving
    out the packages ``importer`` itself lives in."""
    parts = mod.split(".")
    out = [mod]
    for i in range(1, len(parts)):
        pkg = ".".join(parts[:i])
        if not importer.startswith(pkg + "."):
            out.append(pkg)
    return out


def _imports(mod: str, path: Path) -> set[str]:
    """Modules of ours that ``mod`` imports at run time (any depth in the file)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip |= {id(n) for n in ast.walk(node)}
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                here = mod.split(".") if is_pkg else mod.split(".")[:-1]
                here = here[:len(here) - (node.level - 1)]
                base = ".".join(here + ([node.module] if node.module else []))
            names = [f"{base}.{a.name}" for a in node.names] or [base]
        for n in names:
            r = _resolve(n)
            if r is None:
                continue
            out.update(m for m in _with_parents(r, mod) if m in MODULES)
    out.discard(mod)
    return out


GRAPH = {m: _imports(m, p) for m, p in MODULES.items()}


def rank(mod: str) -> int:
    best, r = -1, None
    for k, prefixes in LAYERS:
        for pre in prefixes:
            if (mod == pre or mod.startswith(pre + ".")) and len(pre) > best:
                best, r = len(pre), k
    assert r is not None, f"{mod}: in no layer of tests/test_architecture.py LAYERS"
    return r


def test_every_module_parses_and_has_a_layer():
    assert {"contract.scene", "contract.rotation", "engine", "adapters.base", "harness.cli"} <= set(MODULES)
    for m in MODULES:
        rank(m)


def test_no_upward_imports():
    bad = [f"{m} (layer {rank(m)}) imports {t} (layer {rank(t)})"
           for m, targets in GRAPH.items() for t in sorted(targets) if rank(t) > rank(m)]
    assert not bad, "\n".join(bad)


def test_leaves_and_sides():
    bad = []
    for m, targets in GRAPH.items():
        top = m.split(".")[0]
        for t in targets:
            ttop = t.split(".")[0]
            if top in ("contract", "engine") and ttop != top:
                bad.append(f"{m} is a leaf but imports {t}")
            if top == "adapters" and ttop == "engine" and m != "adapters.reference":
                bad.append(f"{m}: only the reference adapter builds the engine ({t})")
            if top == "adapters" and ttop == "harness":
                bad.append(f"{m}: adapters stand on the contract, not the harness ({t})")
            if top == "harness" and ttop == "engine" and m not in ENGINE_USERS:
                bad.append(f"{m}: the harness reaches the engine through adapters ({t})")
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(GRAPH):
        if v not in index:
            visit(v)
    new = [c for c in cycles if c not in KNOWN_CYCLES]
    gone = [c for c in KNOWN_CYCLES if c not in cycles]
    assert not new, f"import cycles: {new}"
    assert not gone, f"known cycles no longer there (remove them from KNOWN_CYCLES): {gone}"
    assert all(c[0].startswith("engine.") for c in KNOWN_CYCLES), "only the engine's own cycles may be known"


def test_the_checker_sees_function_level_and_relative_imports(tmp_path):
    """The rules cannot pass by missing imports: an import inside a function
    and a relative import are both seen."""
    p = tmp_path / "x.py"
    p.write_text("def f():\n    from harness.cli import main\n    from . import runner\n"
                 "    from harness.trace.writer import write_rrd\n", encoding="utf-8")
    assert _imports("harness.y", p) >= {"harness.cli", "harness.runner", "harness.trace", "harness.trace.writer"}
