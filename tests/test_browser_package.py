"""The three.js runtime's files: generated from vbusd, shipped in the package, pinned three.js.

* web/src/shader-modules.js is what vbusd.web.shader_modules generates now from the shader source
  of ``vbusd shader``, and the package data under vbusd/web/static is the current copy of web/
  and of web/node_modules/three (scripts/sync_web.py --check);
* the runtime's ``shaderModule(encoding, texelFormat, K, clips, skin)``, run under Node, returns
  exactly the text ``vbusd shader --lang glsl --no-main [--skin pulled]`` prints, for every encoding
  and texel format, both skin bindings and several sizes (so the browser runs that module, not a
  retyped one);
* the runtime's ``packSkin`` writes the skin records of spec/shaders.md's worked example (K = 4,
  texels 10 and 11) and of hand-computed K = 3 and K = 8 records;
* the shipped three.js is the version web/package-lock.json pins.

The Node checks skip with one line when Node.js or web/node_modules is missing (``npm ci`` in web/).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from vbusd.web.shader_modules import javascript_module
from tests.helpers import node as node_tools

REPO = Path(__file__).resolve().parents[1]
WEB = REPO / "web"
STATIC = REPO / "vbusd" / "web" / "static"


def test_generated_shader_modules_are_current():
    assert (WEB / "src" / "shader-modules.js").read_text(encoding="utf-8") == javascript_module()


@pytest.mark.cli
def test_package_data_is_in_sync():
    result = subprocess.run([sys.executable, str(REPO / "scripts" / "sync_web.py"), "--check"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"run python scripts/sync_web.py:\n{result.stdout}{result.stderr}"


@pytest.mark.node
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
      for (const skin of ['attributes', 'pulled'])
        out[`${encoding}/${format}/${k}/${clips}/${skin}`] = shaderModule(encoding, format, k, clips, skin);
process.stdout.write(JSON.stringify(out));
"""


@pytest.mark.cli
@pytest.mark.node
def test_runtime_shader_module_equals_vbusd_shader():
    node = node_tools.require_packages("three", folder="web")
    result = subprocess.run([node, "--input-type=module", "-e", _NODE_SCRIPT], cwd=WEB,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-4000:]
    modules = json.loads(result.stdout)
    assert len(modules) == 4 * 3 * 5 * 2
    for key, text in modules.items():
        encoding, texel_format, k, clips, skin = key.split("/")
        expected = subprocess.run(  # the command line, as a user would run it
            [sys.executable, "-m", "vbusd", "shader", "--lang", "glsl", "--no-main", "--encoding", encoding,
             "--texel-format", texel_format, "--max-influences", k, "--max-clips", clips, "--skin", skin],
            capture_output=True, text=True, timeout=60, check=True).stdout if "/4/16/" in key else None
        if expected is None:
            import vbusd

            expected = vbusd.shader("glsl", encoding, texel_format, max_influences=int(k), max_clips=int(clips),
                                    main=False, skin=skin)
        assert text == expected, key


_PACK_SCRIPT = """
import { packSkin } from './src/skin.js';
const hex = (records) => Array.from(records, (x) => x.toString(16).padStart(8, '0'));
// spec/shaders.md, Skin records: vertex 5 of a K = 4 mesh, indices (3, 17, 0, 0), weights (0.75, 0.25, 0, 0).
const idx = new Int16Array(6 * 4); const w = new Float32Array(6 * 4);
idx.set([3, 17, 0, 0], 20); w.set([0.75, 0.25, 0, 0], 20);
// K = 3 (one vertex; slot 3 is padding the record leaves out) and K = 8 (two sets of four).
const k3 = packSkin([new Int16Array([7, 1, 2, 9])], [new Float32Array([0.5, 0.25, 0.25, 0.75])], 3);
const k8 = packSkin([new Int16Array([1, 2, 3, 4]), new Int16Array([5, 6, 7, 8191])],
                    [new Float32Array([1, 0, 0, 0]), new Float32Array([0, 0, -2, 0.5])], 8);
process.stdout.write(JSON.stringify({ k4: hex(packSkin([idx], [w], 4)).slice(40, 48), length: packSkin([idx], [w], 4).length,
                                      k3: hex(k3), k8: hex(k8) }));
"""


@pytest.mark.cli
@pytest.mark.node
def test_runtime_packs_skin_records_as_the_spec_states():
    node = node_tools.require_packages("three", folder="web")
    result = subprocess.run([node, "--input-type=module", "-e", _PACK_SCRIPT], cwd=WEB,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-4000:]
    records = json.loads(result.stdout)
    # The spec's worked example, word for word (texels 10 and 11 of 6 vertices x 2 texels).
    assert records["length"] == 6 * 2 * 4
    assert records["k4"] == ["00110003", "00000000", "3f400000", "3e800000"] + ["00000000"] * 4
    # K = 3: 2 index words + 3 weights = 5 words, 2 texels: (7 | 1 << 16), (2 | 0 << 16), 0.5, 0.25, 0.25.
    assert records["k3"] == ["00010007", "00000002", "3f000000", "3e800000", "3e800000", "00000000", "00000000",
                             "00000000"]
    # K = 8: 4 index words + 8 weights = 12 words, 3 texels; 8191 = 0x1fff; -2.0 = 0xc0000000.
    assert records["k8"] == ["00020001", "00040003", "00060005", "1fff0007", "3f800000", "00000000", "00000000",
                             "00000000", "00000000", "00000000", "c0000000", "3f000000"]


@pytest.mark.node
def test_shipped_babylon_is_the_pinned_version():
    """web/babylon pins @babylonjs/core and @babylonjs/loaders exactly (package.json and its lock
    agree), and the committed bundle is that Babylon.js (its Engine.Version), with its licence."""
    babylon = WEB / "babylon"
    lock = json.loads((babylon / "package-lock.json").read_text())
    dependencies = json.loads((babylon / "package.json").read_text())["dependencies"]
    for name in ("@babylonjs/core", "@babylonjs/loaders"):
        assert dependencies[name] == lock["packages"][f"node_modules/{name}"]["version"]
    bundle = (STATIC / "babylon" / "babylon.bundle.js").read_text(encoding="utf-8")
    assert f'Version(){{return"{dependencies["@babylonjs/core"]}"}}' in bundle
    assert (STATIC / "babylon" / "LICENSE").read_text().startswith("# Apache License 2.0")
