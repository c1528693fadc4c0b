"""Every module of the package declares its public names (``__all__``), and every name it lists
exists: the contract engine and DCC developers import against (issue 10 item 5)."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# The tree is the package: vbusd/ and every folder under it.
FOLDERS = {"vbusd": "vbusd"}


def _modules():
    for folder, package in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            relative = path.relative_to(ROOT / folder).with_suffix("")
            if relative.name.startswith("_") or "static" in relative.parts:
                continue
            yield path, ".".join([package, *relative.parts])


MODULES = list(_modules())


@pytest.mark.parametrize("path, module", MODULES, ids=[m for _, m in MODULES])
def test_module_declares_all_and_every_listed_name_exists(path, module):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    declared = [node for node in tree.body if isinstance(node, (ast.Assign, ast.AnnAssign)) and any(
        getattr(t, "id", None) == "__all__" for t in (node.targets if isinstance(node, ast.Assign) else [node.target]))]
    assert declared, f"{path.relative_to(ROOT)} has no __all__"
    assert ast.get_docstring(tree), f"{path.relative_to(ROOT)} has no module docstring"
    if module.startswith("vbusd.web.") or module == "vbusd.cli.view":
        import http.server  # noqa: F401
    loaded = importlib.import_module(module)
    missing = [name for name in loaded.__all__ if not hasattr(loaded, name)]
    assert not missing, f"{module}.__all__ names what it lacks: {missing}"
