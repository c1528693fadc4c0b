"""Python started in the repository's root imports the checkout the way it imports the installed
package (issue 24): ``vbusd.converters``, ``vbusd.validators`` and ``vbusd.schema`` come from the
checkout's sibling folders, whatever else is installed, without PYTHONSAFEPATH or PYTHONPATH.

The interpreter is this one (the installed vbusd is on its path); the current directory, which
Python puts first on ``sys.path``, makes the checkout's ``vbusd/`` shadow it, as for a reader
following docs/api.md.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

PROGRAM = r"""
import json, sys
import vbusd
import vbusd.converters, vbusd.converters.gltf, vbusd.converters.usdskel
import vbusd.validators, vbusd.validators.api, vbusd.schema, vbusd.schema.usd
from vbusd.converters.registry import entries, find_converter
from vbusd.io.usd_plugin import plugin_dir

report = vbusd.validate("tests/fixtures/validate/valid/dualQuat_float16/asset.usda")
print(json.dumps({
    "files": {name: sys.modules[name].__file__ for name in
              ("vbusd", "vbusd.converters", "vbusd.converters.gltf", "vbusd.validators.api", "vbusd.schema.usd")},
    "plugin": str(plugin_dir()), "valid": report.valid, "converters": sorted(e.name for e in entries()),
    "gltf": find_converter("tests/fixtures/gltf/bar.gltf").__file__,
}))
"""


def _run(code: str):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONSAFEPATH", "PYTHONPATH")}
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)


def test_the_checkout_imports_its_own_mapped_folders():
    result = _run(PROGRAM)
    assert result.returncode == 0, result.stderr[-3000:]
    found = json.loads(result.stdout.strip().splitlines()[-1])
    for name, file in found["files"].items():
        assert Path(file).resolve().is_relative_to(REPO), (name, file)  # never half from another copy
    assert Path(found["files"]["vbusd.converters"]).resolve() == REPO / "converters" / "__init__.py"
    assert Path(found["plugin"]).resolve() == REPO / "schema" / "usd"
    assert found["valid"] is True
    assert {"gltf", "usdskel"} <= set(found["converters"])
    assert Path(found["gltf"]).resolve() == REPO / "converters" / "gltf.py"


def test_the_mapping_adds_nothing_else():
    """Only the three mapped folders: the repository's other folders do not become vbusd packages."""
    result = _run("import importlib.util, vbusd; "
                  "print([n for n in ('tests', 'samples', 'spec', 'docs', 'benchmarks', 'scripts', 'dcc') "
                  "if importlib.util.find_spec('vbusd.' + n) is not None])")
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip() == "[]"
