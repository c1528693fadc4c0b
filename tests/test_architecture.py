"""The package's layers, as docs/architecture.md states them, held against the imports in the code.

docs/architecture.md ("Layers") has a table of the package's layers, bottom first, each naming the
folders (or root modules) it holds. This test reads that table and every ``import`` of every module
of ``vbusd/`` as written (module level and inside functions alike, as a reader or a structure tool
sees them), and fails when:

* a module imports from a higher layer (the table's ``allowed upward imports`` list names the only
  exceptions, each with its reason there);
* files import each other in a circle;
* a module imports a vbusd module or a standard-library module inside a function rather than at its
  top (the rule that keeps helper threads from importing: vbusd/process/threads.py), except the
  heavy optional third-party packages the table lists;
* a module loads modules by name (``importlib.import_module``) outside the two dispatch points the
  table names.
"""

from __future__ import annotations

import ast
import re
import sys
from collections import defaultdict
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "vbusd"
ARCHITECTURE = REPO / "docs" / "architecture.md"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py")) if "static" not in p.parts}


MODULES = _modules()


def _section(title: str) -> str:
    text = ARCHITECTURE.read_text(encoding="utf-8")
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", text, flags=re.M | re.S)
    assert match, f"docs/architecture.md has no '## {title}' section"
    return match.group(1)


def _layers() -> list:
    """``[(layer number, [parts])]`` from the table: a part is ``vbusd.X`` (a folder or root module)."""
    rows = []
    for line in _section("Layers").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].isdigit():
            parts = re.findall(r"`vbusd/([\w]+)(?:/|\.py)?`", cells[1])
            assert parts, line
            rows.append((int(cells[0]), ["vbusd." + p for p in parts]))
    return rows


def _bullets(name: str) -> list:
    """The bullets of the list that follows ``name`` (a paragraph ending in ``:``) in the Layers section,
    continuation lines joined."""
    section = _section("Layers")
    match = re.search(rf"^{re.escape(name)}[^\n]*(?:\n[^\n*-][^\n]*)*:\n((?:[*-] .*\n?|  .*\n?)+)", section, flags=re.M)
    assert match, f"docs/architecture.md, Layers: no list '{name}'"
    bullets = []
    for line in match.group(1).splitlines():
        if re.match(r"[*-] ", line):
            bullets.append(line[2:])
        elif bullets:
            bullets[-1] += " " + line.strip()
    return bullets


def _listed(name: str) -> list:
    """The first backquoted entry of each bullet of the list ``name``."""
    return [m.group(1) for m in (re.match(r"`([^`]+)`", b) for b in _bullets(name)) if m]


def _imported_where_used() -> dict:
    r"""``{module: importers}`` of the list "Imported where used": an entry ``\`m\` in \`a\`, \`b\`: why``
    may be imported inside functions of ``a`` and ``b`` only; ``\`m\`: why`` anywhere (None)."""
    allowed = {}
    for bullet in _bullets("Imported where used"):
        match = re.match(r"`([^`]+)`(?: in ((?:`[^`]+`(?:, | and )?)+))?:", bullet)
        assert match, bullet
        allowed[match.group(1)] = None if match.group(2) is None else set(re.findall(r"`([^`]+)`", match.group(2)))
    return allowed


def _layer_of(module: str, layers: list):
    for number, parts in layers:
        if any(module == p or module.startswith(p + ".") for p in parts):
            return number
    return None


def _resolve(name: str) -> str:
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def _imports(path: Path) -> list:
    """``(line, target module, inside a function, statement)`` for every vbusd import of ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    found = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                for alias in child.names:
                    found.append((child.lineno, alias.name, in_function, ast.unparse(child)))
            elif isinstance(child, ast.ImportFrom) and child.module and not child.level:
                for alias in child.names:
                    full = f"{child.module}.{alias.name}"
                    vbusd = child.module.split(".")[0] == "vbusd"
                    found.append((child.lineno, full if full in MODULES or not vbusd else child.module, in_function,
                                  ast.unparse(child)))
            elif isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue  # for type checkers only: never runs
            visit(child, inside)

    visit(tree, False)
    return found


def _edges() -> dict:
    edges = defaultdict(set)
    for module, path in MODULES.items():
        for _, target, _, _ in _imports(path):
            if target.split(".")[0] == "vbusd":
                target = _resolve(target)
                if target and target != module:
                    edges[module].add(target)
    return edges


def test_every_module_belongs_to_a_layer():
    layers = _layers()
    assert [n for n, _ in layers] == sorted(n for n, _ in layers)
    loose = [m for m in MODULES if m != "vbusd" and _layer_of(m, layers) is None]
    assert loose == [], "modules in no layer of docs/architecture.md: " + ", ".join(loose)


def test_no_module_imports_from_a_higher_layer():
    layers = _layers()
    allowed = set(_listed("Allowed upward imports"))
    assert len(allowed) <= 1, "at most one import may run upward (issue 32)"
    upward = []
    for module, targets in sorted(_edges().items()):
        if module == "vbusd":  # the package's face: its lazy table names the public functions' homes
            continue
        here = _layer_of(module, layers)
        for target in sorted(targets):
            there = 10 ** 6 if target == "vbusd" else _layer_of(target, layers)
            if there is not None and here is not None and there > here and f"{module} -> {target}" not in allowed:
                upward.append(f"{module} (layer {here}) -> {target} (layer {there})")
    assert upward == [], "imports that run upward:\n" + "\n".join(upward)


@pytest.mark.slow
def test_no_circle_of_imports_between_files():
    edges = _edges()
    index, low, stack, on_stack, circles = {}, {}, [], set(), []
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))

    def connect(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in sorted(MODULES):
        if v not in index:
            connect(v)
    # The package's face (vbusd/__init__.py) is imported by every submodule's import machinery, not by
    # their code: only a circle through an import written in a module counts.
    assert circles == [], "circles of imports: " + "; ".join(" <-> ".join(c) for c in circles)


def test_imports_sit_at_the_top_of_modules():
    """No vbusd or standard-library import inside a function: what a job's helper threads run is
    imported when the job's module is (vbusd/process/threads.py). Heavy optional packages that only
    some commands use may be imported where they are used; the table lists them."""
    allowed = _imported_where_used()

    def excused(target: str, module: str) -> bool:
        for name, importers in allowed.items():
            if (target == name or target.startswith(name + ".")) and (importers is None or module in importers):
                return True
        return False

    deferred = []
    for module, path in MODULES.items():
        for line, target, in_function, statement in _imports(path):
            if in_function and not excused(target, module):
                deferred.append(f"{path.relative_to(REPO)}:{line}: {statement}")
    deferred = list(dict.fromkeys(deferred))  # one line per statement, not per name it imports
    assert deferred == [], "imports inside functions:\n" + "\n".join(deferred)


def test_modules_are_loaded_by_name_only_at_the_dispatch_points():
    dispatch = set(_listed("Modules loaded by name"))
    found = []
    for module, path in MODULES.items():
        text = path.read_text(encoding="utf-8")
        if re.search(r"\bimport_module\(|__import__\(", text) and module not in dispatch:
            found.append(module)
    assert found == [], "modules that load others by name: " + ", ".join(found)


@pytest.mark.slow
@pytest.mark.parametrize("lower", ["vbusd.format", "vbusd.io", "vbusd.process"])
def test_the_lowest_layers_import_nothing_above_them(lower):
    """Named on their own because issue 32 asks it: format/, process/ and io/ never reach upward."""
    layers = _layers()
    level = _layer_of(lower, layers)
    reached = sorted({t for m, ts in _edges().items() if m.startswith(lower + ".") or m == lower
                      for t in ts if _layer_of(t, layers) is None or _layer_of(t, layers) > level})
    assert reached == []
