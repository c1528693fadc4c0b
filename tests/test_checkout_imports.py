"""The tree is the package (issue 32): Python started in the repository's root imports vbusd and
every part of it (converters, validators, schema) from the checkout's own ``vbusd/`` folder, with no
remapped folder, no import hook and no module whose class is swapped.

The interpreter is this one (an installed vbusd may be on its path); the current directory, which
Python puts first on ``sys.path``, makes the checkout's ``vbusd/`` the one imported, as for a reader
following docs/api.md.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

PROGRAM = r"""
import json, sys
import vbusd, vbusd.converters, vbusd.validators
vbusd.convert
import vbusd.converters.gltf, vbusd.converters.usdskel
import vbusd.validators.api, vbusd.schema, vbusd.schema.usd
from vbusd.converters.registry import entries, find_converter
from vbusd.io.usd_plugin import plugin_dir

report = vbusd.validate("tests/fixtures/validate/valid/dualQuat_float16/asset.usda")
print(json.dumps({
    "files": {name: sys.modules[name].__file__ for name in
              ("vbusd", "vbusd.converters", "vbusd.converters.gltf", "vbusd.validators.api", "vbusd.schema.usd")},
    "plugin": str(plugin_dir()), "valid": report.valid, "converters": sorted(e.name for e in entries()),
    "gltf": find_converter("tests/fixtures/gltf/bar.gltf").__file__,
    "convert": [type(vbusd.convert).__name__, vbusd.convert.__module__],
    "finders": [type(f).__module__ for f in sys.meta_path],
}))
"""


def _run(code: str):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONSAFEPATH", "PYTHONPATH")}
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.cli
def test_the_checkout_is_the_package():
    result = _run(PROGRAM)
    assert result.returncode == 0, result.stderr[-3000:]
    found = json.loads(result.stdout.strip().splitlines()[-1])
    for name, file in found["files"].items():
        assert Path(file).resolve().is_relative_to(REPO / "vbusd"), (name, file)  # never half from another copy
    assert Path(found["files"]["vbusd.converters"]).resolve() == REPO / "vbusd" / "converters" / "__init__.py"
    assert Path(found["plugin"]).resolve() == REPO / "vbusd" / "schema" / "usd"
    assert found["valid"] is True
    assert {"gltf", "usdskel"} <= set(found["converters"])
    assert Path(found["gltf"]).resolve() == REPO / "vbusd" / "converters" / "gltf.py"
    assert found["convert"] == ["function", "vbusd.jobs.conversion"]  # a function, not a module made callable
    assert not [f for f in found["finders"] if f.startswith("vbusd")], found["finders"]


@pytest.mark.slow
def test_no_import_magic_in_the_package():
    """No remapped folder in pyproject.toml, no import finder and no module class swap in the package."""
    import tomllib

    setuptools = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "package-dir" not in setuptools
    offenders = []
    for path in sorted((REPO / "vbusd").rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr in ("meta_path", "path_hooks") and \
                    isinstance(node.value, ast.Name) and node.value.id == "sys" and path.name != "threads.py":
                offenders.append(f"{path.relative_to(REPO)}:{node.lineno}: sys.{node.attr}")
            if isinstance(node, ast.Assign) and any(isinstance(t, ast.Attribute) and t.attr == "__class__"
                                                    for t in node.targets):
                offenders.append(f"{path.relative_to(REPO)}:{node.lineno}: assigns __class__")
    assert offenders == []
    assert "PYTHONSAFEPATH" not in (REPO / ".ci" / "run").read_text()


def test_no_module_shares_a_name_with_a_public_function():
    """``vbusd.X`` for a public function X is that function: no module or package named X beside it."""
    import vbusd

    functions = [name for name in vbusd.__all__ if isinstance(getattr(vbusd, name), types.FunctionType)]
    assert {"convert", "bake", "decode", "skin"} <= set(functions)
    clashes = [name for name in functions
               if (REPO / "vbusd" / f"{name}.py").exists() or (REPO / "vbusd" / name / "__init__.py").exists()]
    assert clashes == []


@pytest.mark.cli
def test_only_the_package_is_a_package():
    """The repository's other folders do not become vbusd packages."""
    result = _run("import importlib.util, vbusd; "
                  "print([n for n in ('tests', 'samples', 'spec', 'docs', 'benchmarks', 'scripts', 'dcc') "
                  "if importlib.util.find_spec('vbusd.' + n) is not None])")
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip() == "[]"
