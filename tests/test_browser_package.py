"""The web runtime's files: each first-party file once, third-party code once, and the wheel's copy.

* web/src/shader-modules.js is what vbusd.web.shader_modules generates now from the shader source
  of ``vbusd shader``, and web/vendor/ holds the three.js files and the Babylon.js bundle of the
  versions package.json pins (scripts/sync_web.py --check), with their licences and a README.md
  naming the version;
* no file is committed twice: ``git ls-files`` holds no two byte-identical files outside test
  fixtures and benchmark results (each a whole case or run), and nothing under vbusd/web/static;
* the build step the wheel runs (vbusd.web.static_files.copy_static) writes every file each
  engine's page imports, found by following the page's import map and every module's imports
  (an independent walk, not the list the build copies from), and the server of a checkout serves
  the same set;
* the runtime's ``shaderModule(encoding, texelFormat, K, clips, skin)``, run under Node, returns
  exactly the text ``vbusd shader --lang glsl --no-main [--skin pulled]`` prints, for every encoding
  and texel format, both skin bindings and several sizes (so the browser runs that module, not a
  retyped one);
* the runtime's ``packSkin`` writes the skin records of spec/shaders.md's worked example (K = 4,
  texels 10 and 11) and of hand-computed K = 3 and K = 8 records.

The Node checks skip with one line when Node.js or web/node_modules is missing (``npm ci`` in web/).
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from urllib.parse import urljoin

import pytest

from vbusd.web.engines import ENGINE_PAGES
from vbusd.web.shader_modules import javascript_module
from vbusd.web.static_files import copy_static, source_files, vendor_folder
from tests.helpers import node as node_tools
from tests.helpers.web_pages import folder_fetch, page_files

REPO = Path(__file__).resolve().parents[1]
WEB = REPO / "web"

#: Committed files that may be byte-identical: each fixture folder is one whole validation or
#: conversion case (an asset the validator reads on its own), and each benchmark result is one
#: run's record (two machines may measure the same deterministic study).
DUPLICATES_ALLOWED = ("tests/fixtures/", "benchmarks/results/")


def test_generated_shader_modules_are_current():
    assert (WEB / "core" / "src" / "shader-modules.js").read_text(encoding="utf-8") == javascript_module()


def test_generated_and_vendored_files_are_current():
    result = subprocess.run([sys.executable, str(REPO / "scripts" / "sync_web.py"), "--check"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"run python scripts/sync_web.py:\n{result.stdout}{result.stderr}"


def _tracked_files() -> list:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("not a git checkout (or git not found): the committed files cannot be listed")
    result = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, timeout=60)
    if result.returncode != 0:
        pytest.skip(f"git ls-files failed: {result.stderr.decode(errors='replace').strip()}")
    return [name for name in result.stdout.decode("utf-8").split("\0") if name]


def test_no_file_is_committed_twice():
    """Every first-party file once, every generated file once, third-party code once: no two
    committed files hold the same bytes (a copy of web/ under vbusd/ was the case this guards)."""
    by_digest = defaultdict(list)
    for name in _tracked_files():
        path = REPO / name
        if path.is_file() and not path.is_symlink():
            by_digest[hashlib.sha256(path.read_bytes()).hexdigest()].append(name)
    copies = [names for names in by_digest.values() if len(names) > 1
              and not all(name.startswith(DUPLICATES_ALLOWED) for name in names)]
    assert not copies, f"committed more than once: {copies}"


def test_the_wheels_static_folder_is_not_committed():
    tracked = _tracked_files()
    assert not [name for name in tracked if name.startswith("vbusd/web/static/")]
    # Third-party code lives in one clearly named place, with its licence and version.
    for name in ("three", "babylon"):
        folder = vendor_folder(REPO, name)
        assert (folder / "LICENSE").is_file() and (folder / "README.md").is_file(), folder
        assert folder.name.split("-", 1)[1] in (folder / "README.md").read_text(encoding="utf-8")
    third_party = ("three.module.js", "three.core.js", "babylon.bundle.js")
    assert sorted(name for name in tracked if name.rsplit("/", 1)[-1] in third_party) == sorted(
        f"web/vendor/{vendor_folder(REPO, 'three' if n.startswith('three') else 'babylon').name}/{n}"
        for n in third_party)


# --------------------------------------------------------------------------------------------
# The pages' modules, followed as the browser follows them
# --------------------------------------------------------------------------------------------

def test_the_build_step_writes_every_file_every_page_imports(tmp_path):
    """What setup.py's build_py runs (copy_static) into a build folder holds each engine's page
    and every module it reaches, and nothing else; the checkout's server lists the same files."""
    written = copy_static(REPO, tmp_path / "static")
    site = tmp_path / "static"
    names = {path.relative_to(site).as_posix() for path in written}
    assert names == {path.relative_to(site).as_posix() for path in site.rglob("*") if path.is_file()}
    assert names == set(source_files(REPO))
    needed = set()
    for engine, page in ENGINE_PAGES.items():
        files = page_files(folder_fetch(site), page)
        assert "/vbusd-three/index.js" in files or engine == "babylon" and "/vbusd-babylon/index.js" in files, engine
        needed |= files
    # Everything shipped is used by some page (LICENSE files ship as the licences require).
    unused = sorted(name for name in names if f"/{name}" not in needed and not name.endswith("LICENSE"))
    assert not unused, f"shipped but imported by no page: {unused}"
    # Every copy is the checkout's file, byte for byte.
    for url, source in source_files(REPO).items():
        assert (site / url).read_bytes() == source.read_bytes(), url


@pytest.mark.node
def test_shipped_three_is_the_pinned_version():
    lock = json.loads((WEB / "package-lock.json").read_text())
    pinned = lock["packages"]["node_modules/three"]["version"]
    assert json.loads((WEB / "package.json").read_text())["devDependencies"] == {"three": pinned, "@vbusd/core": "file:core"}
    folder = vendor_folder(REPO, "three")
    assert folder.name == f"three-{pinned}"
    revision = pinned.split(".")[1]
    assert f"const REVISION = '{revision}';" in (folder / "three.core.js").read_text(encoding="utf-8")
    assert (folder / "LICENSE").read_text().startswith("The MIT License")


_NODE_SCRIPT = """
import { shaderModule } from './core/src/assemble.js';
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
import { packSkin } from './core/src/skin.js';
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
    agree), and the vendored bundle is that Babylon.js (its Engine.Version), with its licence."""
    babylon = WEB / "babylon"
    lock = json.loads((babylon / "package-lock.json").read_text())
    dependencies = json.loads((babylon / "package.json").read_text())["devDependencies"]
    for name in ("@babylonjs/core", "@babylonjs/loaders"):
        assert dependencies[name] == lock["packages"][f"node_modules/{name}"]["version"]
    folder = vendor_folder(REPO, "babylon")
    assert folder.name == f"babylon-{dependencies['@babylonjs/core']}"
    bundle = (folder / "babylon.bundle.js").read_text(encoding="utf-8")
    assert f'Version(){{return"{dependencies["@babylonjs/core"]}"}}' in bundle
    assert (folder / "LICENSE").read_text().startswith("# Apache License 2.0")
