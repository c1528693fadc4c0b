"""Run the Node scripts of tests/node (ktx-parse, three.js, glTF-Validator) from pytest.

Loaded by path from the tests (they import the installed vbusd with --import-mode=importlib, so
tests/ is not a package). A test whose tools are missing skips with one line saying what to install.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

NODE_DIR = Path(__file__).resolve().parent
INSTALL_HINT = "run scripts/install-node-deps.sh (npm ci in tests/node; needs Node.js 18 or newer)"


def require(*packages: str) -> str:
    """The node executable, after checking that ``packages`` are installed in tests/node; else skip."""
    node = shutil.which("node")
    if node is None:
        pytest.skip(f"node not found: install Node.js 18 or newer, then {INSTALL_HINT}")
    missing = [p for p in packages if not (NODE_DIR / "node_modules" / p / "package.json").is_file()]
    if missing:
        pytest.skip(f"npm packages {', '.join(missing)} missing in tests/node: {INSTALL_HINT}")
    return node


def run_json(script: str, *args, packages=("ktx-parse", "three", "gltf-validator"), timeout: float = 120):
    """Run ``node tests/node/<script> ARGS`` and parse its stdout as JSON.

    Raises:
        AssertionError: The script failed (its stderr is in the message).
    """
    node = require(*packages)
    result = subprocess.run([node, str(NODE_DIR / script), *map(str, args)], cwd=NODE_DIR,
                            capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{script} failed ({result.returncode}): {result.stderr[-4000:]}"
    return json.loads(result.stdout)
