"""Run the Node scripts of tests/node (ktx-parse, three.js, glTF-Validator) from pytest.

A test whose tools are missing skips with one line saying what to install, or fails where the run
requires Node (:mod:`tests.helpers.capabilities`).
"""

from __future__ import annotations

import json
import shutil
import subprocess

from tests.helpers.capabilities import NODE_HINT, REPO, require, unavailable

NODE_DIR = REPO / "tests" / "node"
INSTALL_HINT = NODE_HINT


def require_packages(*packages: str, folder: str = "tests/node") -> str:
    """The node executable, after checking that ``packages`` are installed in ``folder``; else
    skip (or fail where Node is required)."""
    require("node")
    missing = [p for p in packages if not (REPO / folder / "node_modules" / p / "package.json").is_file()]
    if missing:
        unavailable("node", f"npm packages {', '.join(missing)} missing in {folder}: {NODE_HINT}")
    return shutil.which("node")


def run_json(script: str, *args, packages=("ktx-parse", "three", "gltf-validator"), timeout: float = 120):
    """Run ``node tests/node/<script> ARGS`` and parse its stdout as JSON.

    Raises:
        AssertionError: The script failed (its stderr is in the message).
    """
    node = require_packages(*packages)
    result = subprocess.run([node, str(NODE_DIR / script), *map(str, args)], cwd=NODE_DIR,
                            capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{script} failed ({result.returncode}): {result.stderr[-4000:]}"
    return json.loads(result.stdout)


GLTF_ALLOWED_INFOS = {"UNSUPPORTED_EXTENSION", "UNUSED_OBJECT"}
"""The glTF-Validator infos a vbusd package may have; any error or warning fails :func:`gltf_check`."""


def gltf_check(path) -> dict:
    """The Khronos glTF-Validator's and three.js GLTFLoader's results on the package at ``path``
    (tests/node/gltf_check.mjs); fails on any validator error or warning, or an info beyond
    :data:`GLTF_ALLOWED_INFOS`."""
    result = run_json("gltf_check.mjs", path, packages=("three", "gltf-validator"))
    issues = result["validator"]["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"]
    assert {m["code"] for m in issues["messages"]} <= GLTF_ALLOWED_INFOS, issues["messages"]
    return result
