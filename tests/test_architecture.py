"""The import rules of docs/ARCHITECTURE.md, enforced: every module outside
the tests is parsed (imports inside functions count; imports under
``if TYPE_CHECKING:`` do not, they never run), and

- no module imports a module of a higher layer;
- the contract imports nothing of ours; the engine imports only the engine;
- adapters never import the harness, and only the reference adapter
  imports the engine; only the listed harness modules import the engine;
- there is no import cycle between modules (importing ``a.b.c`` from
  outside package ``a.b`` also runs ``a/b/__init__.py``, so that counts;
  a module inside the package was itself reached through it);
- the report imports no scene loading and nothing that runs a scene (it
  reads rows); the breaking-point search imports no I/O;
- in the housekept packages (cli, report, conformance, trace) our modules
  are imported at module level but where LOCAL_IMPORTS gives the reason,
  and no private name is taken from another module of ours;
- the written rules agree with the tree: docs/ARCHITECTURE.md's table with
  ``LAYERS``, README.md's layout table with the modules, pyproject.toml's
  packages with the packages.
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
    (0, ("physbench", "physbench.contract", "physbench.engine")),  # contract: spec, scene, geometry, ...; engine
    (1, ("physbench.adapters",)),
    (2, ("physbench.harness",)),  # run, execute, metrics, references, results, status, fingerprint, trace
    (3, ("physbench.harness.conformance",)),  # check
    (4, ("physbench.harness.limits", "physbench.harness.limit_eval", "physbench.harness.limit_search", "physbench.harness.sweep", "physbench.harness.suite",
         "physbench.harness.points", "physbench.harness.sweep_store", "physbench.harness.schedule", "physbench.harness.selfbench", "physbench.harness.sweep_bench",
         "physbench.harness.trace.cost", "physbench.harness.bench", "physbench.harness.bench_targets")),  # sweep, limits, bench (selfbench: physbench's own)
    (5, ("physbench.harness.report",)),  # report
    (6, ("physbench.harness.cli",)),  # the command line
]
# Import cycles known today, each a strongly connected set of modules.  The
# test fails when one disappears as well as when a new one forms, so this
# list only shrinks (the engine's last one, profile -> jit ->
# collision.dispatch -> profile, went when the profile took over the JIT
# seconds' bookkeeping).
KNOWN_CYCLES: list[list[str]] = []
# harness modules that use the engine directly (all others go through adapters)
ENGINE_USERS = {"physbench.harness.fingerprint", "physbench.harness.bench",
                "physbench.harness.cli.compile"}  # physbench compile wraps python -m physbench.engine


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            rel = p.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(["physbench", *parts])] = p
    out["physbench"] = ROOT / "__init__.py"
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


def _from_module(mod: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` in module ``mod`` (a
    package's ``__init__`` when ``is_pkg``) reads from."""
    base = node.module or ""
    if node.level:
        here = mod.split(".") if is_pkg else mod.split(".")[:-1]
        here = here[:len(here) - (node.level - 1)]
        base = ".".join(here + ([node.module] if node.module else []))
    return base


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
            base = _from_module(mod, is_pkg, node)
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
    assert {"physbench.contract.scene", "physbench.contract.rotation", "physbench.engine", "physbench.adapters.base", "physbench.harness.cli"} <= set(MODULES)
    for m in MODULES:
        rank(m)


def test_no_upward_imports():
    bad = [f"{m} (layer {rank(m)}) imports {t} (layer {rank(t)})"
           for m, targets in GRAPH.items() for t in sorted(targets) if rank(t) > rank(m)]
    assert not bad, "\n".join(bad)


def test_leaves_and_sides():
    bad = []
    for m, targets in GRAPH.items():
        top = m.split(".")[1] if "." in m else m
        for t in targets:
            ttop = t.split(".")[1] if "." in t else t
            if top in ("contract", "engine") and ttop != top:
                bad.append(f"{m} is a leaf but imports {t}")
            if top == "adapters" and ttop == "engine" and m != "physbench.adapters.reference":
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
    assert all(c[0].startswith("physbench.engine.") for c in KNOWN_CYCLES), "only the engine's own cycles may be known"


def test_the_checker_sees_function_level_and_relative_imports(tmp_path):
    """The rules cannot pass by missing imports: an import inside a function
    and a relative import are both seen."""
    p = tmp_path / "x.py"
    p.write_text("def f():\n    from physbench.harness.cli import main\n    from . import runner\n"
                 "    from physbench.harness.trace.writer import write_rrd\n", encoding="utf-8")
    assert _imports("physbench.harness.y", p) >= {"physbench.harness.cli", "physbench.harness.runner", "physbench.harness.trace", "physbench.harness.trace.writer"}


# What the report may not import, directly: scene loading and compiling (the
# spec, the scene, the model check), check evaluation, the references and
# metrics, adapters and the engine, anything that runs a scene.  It reads
# rows; tests/test_report_rows.py pins the same at run time (loading a scene
# during the report fails it).
REPORT_MAY_NOT_IMPORT = ("physbench.contract.scene", "physbench.contract.scene_model", "physbench.contract.shapes", "physbench.contract.models",
                         "physbench.contract.spec", "physbench.adapters", "physbench.engine", "physbench.harness.conformance", "physbench.harness.references",
                         "physbench.harness.metrics", "physbench.contract.geometry", "physbench.harness.points", "physbench.harness.suite",
                         "physbench.harness.limits", "physbench.harness.limit_eval", "physbench.harness.execute", "physbench.harness.workers",
                         "physbench.harness.trace")
# names the report may take from the runner (the commit the page was made at)
REPORT_FROM_RUNNER = {"commit_id"}


def _from_imports(path: Path, module: str) -> set[str]:
    """Names imported as ``from <module> import ...`` anywhere in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    return {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module == module
            for a in n.names}


def _report_violations(graph: dict[str, set[str]], paths: dict[str, Path]) -> list[str]:
    bad = []
    for m, targets in graph.items():
        if not (m == "physbench.harness.report" or m.startswith("physbench.harness.report.")):
            continue
        for t in sorted(targets):
            if any(t == p or t.startswith(p + ".") for p in REPORT_MAY_NOT_IMPORT):
                bad.append(f"{m} imports {t}: the report reads rows only")
        extra = _from_imports(paths[m], "physbench.harness.runner") - REPORT_FROM_RUNNER
        if extra or "physbench.harness.runner" in targets and not _from_imports(paths[m], "physbench.harness.runner"):
            bad.append(f"{m} takes {sorted(extra) or 'the module'} from harness.runner; only "
                       f"{sorted(REPORT_FROM_RUNNER)} may come from there")
    return bad


def test_the_report_reads_rows_only():
    assert {"physbench.harness.report", "physbench.harness.report.page", "physbench.harness.report.loading"} <= set(MODULES)
    bad = _report_violations(GRAPH, MODULES)
    assert not bad, "\n".join(bad)


def test_the_report_rule_can_fail(tmp_path):
    """A report module that loads a scene, or takes more than the commit
    from the runner, is caught."""
    p = tmp_path / "x.py"
    p.write_text("def f():\n    from physbench.contract.scene import load_scene\n"
                 "    from physbench.harness.runner import run, commit_id\n", encoding="utf-8")
    bad = _report_violations({"physbench.harness.report.x": _imports("physbench.harness.report.x", p)}, {"physbench.harness.report.x": p})
    assert any("physbench.contract.scene" in b for b in bad) and any("['run']" in b for b in bad), bad


# The breaking-point search is pure logic (asv's step_detect.py is the
# model): it imports nothing of ours and nothing that does I/O, so it is
# tested on a fake criterion (tests/test_limits.py).
PURE_MODULES = {"physbench.harness.limit_search": {"__future__", "math", "dataclasses", "typing"}}


def test_pure_modules_import_no_io():
    for m, allowed in PURE_MODULES.items():
        tree = ast.parse(MODULES[m].read_text(encoding="utf-8"))
        names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {(n.module or "").split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert names <= allowed, f"{m} imports {sorted(names - allowed)}: it is pure logic, no I/O"
        assert not GRAPH[m], f"{m} imports {sorted(GRAPH[m])}"


def _table_rows(path: Path, heading: str) -> list[list[str]]:
    """The rows (cells) of the first Markdown table after ``heading``."""
    lines = path.read_text(encoding="utf-8").splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.strip() == heading)
    rows, seen = [], False
    for ln in lines[start + 1:]:
        if ln.startswith("|"):
            seen = True
            cells = [c.strip() for c in ln.strip().strip("|").split("|")]
            if not set(cells[0]) <= set("- "):
                rows.append(cells)
        elif seen:
            break
    return rows[1:]  # without the header


def _files_named(text: str) -> set[str]:
    """Backticked file and folder names in ``text`` (``x.py``, ``geometry/``)."""
    import re

    return set(re.findall(r"`([\w/]+(?:\.py|/))`", text))


def test_architecture_doc_names_the_layers_of_the_test():
    """docs/ARCHITECTURE.md's table and LAYERS say the same: every harness
    module or package LAYERS places above layer 2 is named in that layer's
    row, and every harness file a row of layers 2-6 names exists and is in
    that layer."""
    rows = _table_rows(ROOT / "docs" / "ARCHITECTURE.md", "# Architecture: layers and import rules")
    by_layer: dict[int, set[str]] = {}
    for cells in rows:
        by_layer.setdefault(int(cells[0]), set()).update(_files_named(cells[1]))
    bad = []
    for k, prefixes in LAYERS:
        if k <= 2:
            continue
        for pre in prefixes:
            rel = pre.removeprefix("physbench.").replace(".", "/")
            name = Path(rel).name + ("/" if (ROOT / rel).is_dir() else ".py")
            if not ({name, rel + "/", rel + ".py"} & by_layer.get(k, set())):
                bad.append(f"{pre}: layer {k} in LAYERS, not named in the row of layer {k}")
    for k, names in by_layer.items():
        if k < 2:
            continue
        for name in names:
            rel = name.removesuffix(".py").rstrip("/")
            mod = "physbench." + (rel if rel.startswith("harness") else "harness/" + rel).replace("/", ".")
            if mod in MODULES and rank(mod) != k:
                bad.append(f"{name}: in the row of layer {k}, but LAYERS puts {mod} in layer {rank(mod)}")
            if mod not in MODULES:
                bad.append(f"{name}: named in the row of layer {k} but there is no module {mod}")
    assert not bad, "\n".join(bad)


def test_readme_layout_names_every_module():
    """README.md's layout table matches the tree: every file or folder it
    names exists, and every module directly under contract/, adapters/ and
    harness/ (a file or a subpackage) is named in its package's row."""
    rows = {cells[0].strip("`"): cells[1] for cells in _table_rows(ROOT / "README.md", "## Layout")}
    bad = []
    for where, text in rows.items():
        for name in _files_named(text):
            if not ((ROOT / where / name).exists() or (ROOT / name).is_dir()):  # or a top-level package
                bad.append(f"README layout, {where}: names {name}, which does not exist")
    for pkg in ("contract", "adapters", "harness"):
        named = _files_named(rows[pkg + "/"])
        for p in sorted((ROOT / pkg).iterdir()):
            if p.name.startswith(("_", ".")):
                continue
            name = p.name + "/" if p.is_dir() and (p / "__init__.py").exists() else p.name
            if name.endswith((".py", "/")) and name not in named:
                bad.append(f"README layout, {pkg}/: does not name {name}")
    assert not bad, "\n".join(bad)


def test_packaging_ships_every_package():
    """pyproject.toml's package list covers every package of the tree (a
    subpackage left out is missing from an installed wheel: the CLI's own
    ``harness.cli`` once was)."""
    import fnmatch
    import tomllib

    conf = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    listed = conf.get("packages")
    pkgs = sorted(m for m, p in MODULES.items() if p.name == "__init__.py")
    assert len(pkgs) >= 10
    if isinstance(listed, list):
        missing = [m for m in pkgs if m not in listed]
    else:
        include = listed["find"].get("include", ["*"])
        missing = [m for m in pkgs if not any(fnmatch.fnmatchcase(m, pat) for pat in include)]
    assert not missing, f"pyproject.toml does not ship {missing}"


# Imports of our own modules sit at module level.  A function-level one
# stays only with its reason in a comment on its line or the line above:
# an optional engine, a heavy import on a cold path (rerun, pandas/pyarrow,
# numba: a command that does not always need it), or an import cycle the
# layers forbid breaking otherwise.  In the packages below, the table lists
# every one left (importer -> imported module -> reason), and no module
# takes a private name (``_x``) from another module of ours, by import or
# as ``module._x``.  The test fails on one more and on one fewer, so the
# table only shrinks; the rest of harness/ has ceilings that only go down.
HOUSEKEPT = ("physbench.harness.cli", "physbench.harness.report", "physbench.harness.conformance",
             "physbench.harness.trace")
LOCAL_IMPORTS: dict[str, dict[str, str]] = {
    "physbench.harness.cli.bench": {"physbench.harness.selfbench.executors": "physbench's benchmark of itself, "
                                    "off the start of every other command"},
    "physbench.harness.cli.compile": {"physbench.engine.__main__": "numba, for this command only"},
    "physbench.harness.cli.jobs": {"physbench.harness.report": "pandas, pyarrow, matplotlib, for this command only",
                                   "physbench.harness.sweep": "the sweep machinery, for this command only",
                                   "physbench.harness.limits": "the limits machinery, for this command only"},
    "physbench.harness.cli.trace": {"physbench.harness.trace": "rerun, for this command only",
                                    "physbench.harness.trace.contacts": "rerun (the trace package), for this command only"},
    "physbench.harness.conformance.traces": {"physbench.harness.trace.cases": "rerun, for check --traces only",
                                             "physbench.harness.trace.contacts": "rerun, for check --traces only"},
}
# the rest of harness/ (another pass owes it): at most this many
HARNESS_LOCAL_IMPORTS_MAX = 41
HARNESS_PRIVATE_IMPORTS_MAX = 12


def _import_hygiene(mod: str, path: Path) -> tuple[list[tuple[int, str, bool]], list[tuple[int, str]]]:
    """(function-level imports of our modules as (line, module, whether a
    comment gives its reason), private names taken from other modules
    of ours as (line, 'module._name'))."""
    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    tree = ast.parse(text, str(path))
    is_pkg = path.name == "__init__.py"
    in_func: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            in_func |= {id(n) for n in ast.walk(node) if n is not node}
    local: list[tuple[int, str, bool]] = []
    private: list[tuple[int, str]] = []
    module_names: dict[str, str] = {}  # a local name bound to a module of ours

    def commented(node: ast.stmt) -> bool:
        """A comment on the import's lines, or above it (and the imports
        right above it: one comment for a block of them)."""
        if any("#" in ln for ln in lines[node.lineno - 1:node.end_lineno]):
            return True
        i = node.lineno - 2
        while i >= 0 and lines[i].strip().startswith(("from ", "import ")):
            i -= 1
        return i >= 0 and lines[i].strip().startswith("#")

    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.ImportFrom):
            base = _from_module(mod, is_pkg, node)
            if _resolve(base) is None:
                continue
            for a in node.names:
                full = f"{base}.{a.name}"
                targets.append(full if full in MODULES else _resolve(base))
                if full in MODULES:
                    module_names[a.asname or a.name] = full
                if a.name.startswith("_") and not a.name.startswith("__"):
                    private.append((node.lineno, full))
        elif isinstance(node, ast.Import):
            for a in node.names:
                if _resolve(a.name) is None:
                    continue
                targets.append(_resolve(a.name))
                if a.asname:
                    module_names[a.asname] = a.name
        if targets and id(node) in in_func:
            local += [(node.lineno, t, commented(node)) for t in dict.fromkeys(targets)]
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in module_names
                and node.attr.startswith("_") and not node.attr.startswith("__")
                and module_names[node.value.id] != mod):
            private.append((node.lineno, f"{module_names[node.value.id]}.{node.attr}"))
    return local, private


def _hygiene_violations(paths: dict[str, Path]) -> tuple[list[str], int, int]:
    """(violations in the housekept packages, function-level imports and
    private-name imports in the rest of harness/)."""
    bad: list[str] = []
    rest_local = rest_private = 0
    for m, p in sorted(paths.items()):
        if not m.startswith("physbench.harness"):
            continue
        local, private = _import_hygiene(m, p)
        if not any(m == pkg or m.startswith(pkg + ".") for pkg in HOUSEKEPT):
            rest_local += len(local)
            rest_private += len(private)
            continue
        allowed = LOCAL_IMPORTS.get(m, {})
        seen = set()
        for line, target, has_comment in local:
            seen.add(target)
            if target not in allowed:
                bad.append(f"{m}:{line}: imports {target} inside a function; move it to module level "
                           f"(or list it in LOCAL_IMPORTS with its reason)")
            elif not has_comment:
                bad.append(f"{m}:{line}: the function-level import of {target} says no reason in a comment")
        bad += [f"{m}: LOCAL_IMPORTS lists {t}, which it no longer imports in a function: remove it"
                for t in sorted(set(allowed) - seen)]
        bad += [f"{m}:{line}: takes the private name {name} from another module: make it public or move it"
                for line, name in private]
    bad += [f"LOCAL_IMPORTS names {m}, which is not a module" for m in sorted(set(LOCAL_IMPORTS) - set(paths))]
    return bad, rest_local, rest_private


def test_imports_at_module_level_and_no_private_names_across_modules():
    bad, rest_local, rest_private = _hygiene_violations(MODULES)
    assert not bad, "\n".join(bad)
    assert rest_local <= HARNESS_LOCAL_IMPORTS_MAX, (
        f"harness/ outside {HOUSEKEPT}: {rest_local} function-level imports of our modules, at most "
        f"{HARNESS_LOCAL_IMPORTS_MAX}")
    assert rest_private <= HARNESS_PRIVATE_IMPORTS_MAX, (
        f"harness/ outside {HOUSEKEPT}: {rest_private} private names taken across modules, at most "
        f"{HARNESS_PRIVATE_IMPORTS_MAX}")


def test_the_import_hygiene_rule_can_fail(tmp_path):
    """A function-level import, one listed without a comment, a listed one
    gone, and a private name by import or attribute are each caught."""
    pkg = tmp_path / "x.py"
    pkg.write_text("from physbench.harness import runner\n"
                   "from physbench.contract.geometry import _support\n"
                   "def f():\n"
                   "    from physbench.harness.execute import RunRequest\n"
                   "    from physbench.harness.trace import write_rrd\n"
                   "    return runner._metrics\n", encoding="utf-8")
    local, private = _import_hygiene("physbench.harness.cli.x", pkg)
    assert [(t, c) for _, t, c in local] == [("physbench.harness.execute", False), ("physbench.harness.trace", False)]
    assert sorted(n for _, n in private) == ["physbench.contract.geometry._support", "physbench.harness.runner._metrics"]
    paths = {"physbench.harness.cli.trace": pkg}
    bad, _, _ = _hygiene_violations(paths)
    assert any("imports physbench.harness.execute inside a function" in b for b in bad), bad
    assert any("import of physbench.harness.trace says no reason" in b for b in bad), bad
    assert any("lists physbench.harness.trace.contacts, which it no longer" in b for b in bad), bad
    assert any("private name physbench.harness.runner._metrics" in b for b in bad), bad
    assert any("private name physbench.contract.geometry._support" in b for b in bad), bad
