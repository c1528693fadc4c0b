"""The three.js runtime's files: generated from vbusd, shipped in the package, pinned three.js.

* web/src/shader-modules.js is what vbusd.web.shader_modules generates now from the shader source
  of ``vbusd shader``, and the package data under vbusd/web/static is the current copy of web/
  and of web/node_modules/three (scripts/sync_web.py --check);
* the runtime's ``shaderModule(encoding, texelFormat, K, clips)``, run under Node, returns exactly
  the text ``vbusd shader --lang glsl --no-main`` prints, for every encoding and texel format and
  several sizes (so the browser runs that module, not a retyped one);
* the shipped three.js is the version web/package-lock.json pins.

The Node checks skip with one line when Node.js or web/node_modules is missing (``npm ci`` in web/).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vbusd.web.shader_modules import javascript_module

REPO = Path(__file__).resolve().parents[1]
WEB = REPO / "web"
STATIC = REPO / "vbusd" / "web" / "static"


def test_generated_shader_modules_are_current():
    assert (WEB / "src" / "shader-modules.js").read_text(encoding="utf-8") == javascript_module()


def test_package_data_is_in_sync():
    result = subprocess.run([sys.executable, str(REPO / "scripts" / "sync_web.py"), "--check"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"run python scripts/sync_web.py:\n{result.stdout}{result.stderr}"


def test_shipped_three_is_the_pinned_version():
    lock = json.loads((WEB / "package-lock.json").read_text())
    pinned = lock["packages"]["node_modules/three"]["version"]
    assert json.loads((WEB / "package.json").read_text())["dependencies"] == {"three": pinned}
    revision = pinned.split(".")[1]
    assert f"const REVISION = '{revision}';" in (STATIC / "three" / "three.core.js").read_text(encoding="utf-8")
    assert (STATIC / "three" / "LICENSE").read_text().startswith("The MIT License")


_NODE_SCRIPT = """
import { shaderModule } from './src/material.js';
const out = {};
for (const encoding of ['crossMatrix', 'affineMatrix', 'quatTranslation', 'dualQuat'])
  for (const format of ['float16', 'float32', 'unorm16'])
    for (const [k, clips] of [[1, 1], [3, 16], [4, 16], [5, 40], [8, 256]])
      out[`${encoding}/${format}/${k}/${clips}`] = shaderModule(encoding, format, k, clips);
process.stdout.write(JSON.stringify(out));
"""


def test_runtime_shader_module_equals_vbusd_shader():
    node = shutil.which("node")
    if node is None:
        pytest.skip("node not found: install Node.js 18 or newer and run npm ci in web/")
    if not (WEB / "node_modules" / "three" / "package.json").is_file():
        pytest.skip("web/node_modules is missing: run npm ci in web/")
    result = subprocess.run([node, "--input-type=module", "-e", _NODE_SCRIPT], cwd=WEB,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-4000:]
    modules = json.loads(result.stdout)
    assert len(modules) == 4 * 3 * 5
    for key, text in modules.items():
        encoding, texel_format, k, clips = key.split("/")
        expected = subprocess.run(  # the command line, as a user would run it
            [sys.executable, "-m", "vbusd", "shader", "--lang", "glsl", "--no-main", "--encoding", encoding,
             "--texel-format", texel_format, "--max-influences", k, "--max-clips", clips],
            capture_output=True, text=True, timeout=60, check=True).stdout if key.endswith("/4/16") else None
        if expected is None:
            import vbusd

            expected = vbusd.shader("glsl", encoding, texel_format, max_influences=int(k), max_clips=int(clips),
                                    main=False)
        assert text == expected, key
