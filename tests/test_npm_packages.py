"""The web runtimes are npm packages a web user installs: @vbusd/core, @vbusd/three, @vbusd/babylon, @vbusd/gltf-transform.

* Each package.json is publishable (not private), versioned after the format (``MAJOR.MINOR`` of
  the newest format the runtime reads, docs/engines.md "npm packages"), with entry points,
  type declarations and the engine as a peer dependency; every file its ``main``, ``types`` and
  ``exports`` name exists.
* ``npm pack`` of each, then ``npm install`` of the four tarballs into a fresh npm project, offline,
  with the peer dependencies taken from the folders ``scripts/install-node-deps.sh`` installs
  (web/node_modules/three, web/babylon/node_modules/@babylonjs/*,
  web/gltf-transform/node_modules/@gltf-transform/*): every entry point imports under Node, its
  exports are the names its .d.ts declares, the installed runtimes' ``shaderModule`` return the
  text ``vbusd shader`` prints, and the glTF-Transform extension registers with ``NodeIO``.
* The tarballs hold the runtime and its types only (no tests, no node_modules, no vendored
  third-party code, no viewer pages).

The npm checks skip with one line when Node.js, npm or the installed peers are missing.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import tarfile
from pathlib import Path

import pytest

import vbusd
from vbusd.format.versioning import CURRENT

from tests.helpers.capabilities import unavailable

REPO = Path(__file__).resolve().parents[1]
WEB = REPO / "web"
INSTALL_HINT = "run scripts/install-node-deps.sh (npm ci in web, web/babylon and web/gltf-transform)"

#: package folder -> (name, {entry point specifier: its .d.ts}, peer dependencies that must be declared)
PACKAGES = {
    WEB / "core": ("@vbusd/core", {"@vbusd/core": "types/index.d.ts", "@vbusd/core/shader-modules": "types/shader-modules.d.ts"},
                   ()),
    WEB: ("@vbusd/three", {"@vbusd/three": "types/index.d.ts", "@vbusd/three/webgpu": "types/webgpu.d.ts"},
          ("three", "@vbusd/core")),
    WEB / "babylon": ("@vbusd/babylon", {"@vbusd/babylon": "types/index.d.ts"},
                      ("@babylonjs/core", "@babylonjs/loaders", "@vbusd/core", "@vbusd/three")),
    WEB / "gltf-transform": ("@vbusd/gltf-transform", {"@vbusd/gltf-transform": "types/index.d.ts"},
                             ("@gltf-transform/core", "@gltf-transform/extensions", "@gltf-transform/functions")),
}

#: The peer dependencies the fresh project installs, from the folders install-node-deps.sh fills.
LOCAL_PEERS = (WEB / "node_modules" / "three",
               WEB / "babylon" / "node_modules" / "@babylonjs" / "core",
               WEB / "babylon" / "node_modules" / "@babylonjs" / "loaders",
               WEB / "gltf-transform" / "node_modules" / "@gltf-transform" / "core",
               WEB / "gltf-transform" / "node_modules" / "@gltf-transform" / "extensions",
               WEB / "gltf-transform" / "node_modules" / "@gltf-transform" / "functions")

_DECLARED = re.compile(r"^export (?:declare )?(?:abstract )?(?:class|function|const|let) (\w+)", re.M)


def _manifest(folder: Path) -> dict:
    return json.loads((folder / "package.json").read_text(encoding="utf-8"))


def _targets(exports) -> list:
    """Every file path an ``exports`` value names (strings, or condition objects)."""
    if isinstance(exports, str):
        return [exports]
    return [path for value in exports.values() for path in _targets(value)]


@pytest.mark.parametrize("folder", list(PACKAGES), ids=[name for name, _, _ in PACKAGES.values()])
def test_package_json_is_publishable(folder):
    name, entries, peers = PACKAGES[folder]
    manifest = _manifest(folder)
    assert manifest["name"] == name
    assert "private" not in manifest, f"{name} is private: npm refuses to publish it"
    assert manifest["license"] == "Apache-2.0" and manifest["type"] == "module"
    # The version is the format's: MAJOR.MINOR of the newest format the runtime reads, then the
    # runtime's own patch number.
    major, minor, patch = manifest["version"].split(".")
    assert (int(major), int(minor)) == (CURRENT.major, CURRENT.minor) and patch.isdigit(), manifest["version"]
    assert set(peers) <= set(manifest.get("peerDependencies", {})), manifest.get("peerDependencies")
    assert "dependencies" not in manifest, "the engine, the core and the sibling runtime are peers, never bundled"
    for path in [manifest["main"], manifest["types"], *_targets(manifest["exports"])]:
        assert (folder / path).is_file(), f"{name}: {path} is missing"
    for specifier, types in entries.items():
        subpath = "." + specifier[len(name):]
        assert manifest["exports"][subpath]["types"] == f"./{types}", specifier
    assert "src" in manifest["files"] and "types" in manifest["files"]


def test_runtimes_peer_the_core_and_three_runtime_of_their_own_format():
    for folder, peer_name in ((WEB / "babylon", "@vbusd/three"), (WEB / "babylon", "@vbusd/core"), (WEB, "@vbusd/core")):
        version = _manifest(WEB if peer_name == "@vbusd/three" else WEB / "core")["version"]
        peer = _manifest(folder)["peerDependencies"][peer_name]
        assert peer == "~" + ".".join(version.split(".")[:2]) + ".0", (folder, peer_name, peer, version)


# --------------------------------------------------------------------------------------------
# npm pack, and npm install into a fresh project
# --------------------------------------------------------------------------------------------

_IMPORT_SCRIPT = """
const entries = JSON.parse(process.argv[1]);
const out = {};
for (const specifier of entries) out[specifier] = Object.keys(await import(specifier)).sort();
const three = await import('@vbusd/three');
const babylon = await import('@vbusd/babylon');
out.threeModule = three.shaderModule('dualQuat', 'float32', 4, 16, 'pulled');
out.babylonModule = babylon.shaderModule('quatTranslation', 'float16', 4, 16);
out.coreModule = (await import('@vbusd/core')).shaderModule('compactQuatTranslation', 'uint32', 4, 16, 'attributes', true);
const { NodeIO, Document } = await import('@gltf-transform/core');
const { VBUSDVirtualBones } = await import('@vbusd/gltf-transform');
const io = new NodeIO().registerExtensions([VBUSDVirtualBones]);
const document = new Document();
const animation = document.createExtension(VBUSDVirtualBones).createAnimation('walk').setPath('/Walk');
out.gltfTransform = [io.getExtensions?.().map?.((e) => e.extensionName) ?? null, animation.getPath(),
                     document.getRoot().listExtensionsUsed().map((e) => e.extensionName)];
process.stdout.write(JSON.stringify(out));
"""


@pytest.fixture(scope="module")
def fresh_project(tmp_path_factory):
    """The three packages packed and installed into a fresh npm project (offline); yields
    (project folder, {package name: list of files in its tarball})."""
    # Capability node: these tests skip with one line here, and fail naming it in CI.
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        unavailable("node", "node or npm not found: install Node.js 18 or newer")
    missing = [str(path.relative_to(REPO)) for path in LOCAL_PEERS if not (path / "package.json").is_file()]
    if missing:
        unavailable("node", f"{', '.join(missing)} missing: {INSTALL_HINT}")
    base = tmp_path_factory.mktemp("npm")
    packs, cache = base / "packs", base / "cache"
    packs.mkdir()
    contents = {}
    for folder, (name, _, _) in PACKAGES.items():
        result = subprocess.run([npm, "pack", "--json", "--pack-destination", str(packs), "--cache", str(cache)],
                                cwd=folder, capture_output=True, text=True, timeout=300)
        assert result.returncode == 0, result.stderr[-4000:]
        (packed,) = json.loads(result.stdout)
        with tarfile.open(packs / packed["filename"]) as archive:
            contents[name] = sorted(member.name.removeprefix("package/") for member in archive.getmembers()
                                    if member.isfile())
    project = base / "project"
    project.mkdir()
    (project / "package.json").write_text(json.dumps({"name": "fresh", "private": True, "type": "module"}))
    result = subprocess.run([npm, "install", "--offline", "--no-audit", "--no-fund", "--cache", str(cache),
                             *sorted(str(path) for path in packs.glob("*.tgz")), *map(str, LOCAL_PEERS)],
                            cwd=project, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-4000:]
    return project, contents


@pytest.mark.node
def test_tarballs_hold_the_runtime_and_its_types_only(fresh_project):
    _, contents = fresh_project
    for name, files in contents.items():
        assert "package.json" in files and any(f.startswith("types/") for f in files), name
        for file in files:
            assert file.split("/")[0] in ("src", "types", "package.json", "README.md", "gltf-transform.config.mjs"), \
                f"{name} packs {file}"
    assert "src/shader-modules.js" in contents["@vbusd/core"]
    assert "src/webgpu/index.js" in contents["@vbusd/three"]
    # One copy of the generated shader modules: every runtime imports @vbusd/core's.
    assert not [f for name in ("@vbusd/three", "@vbusd/babylon") for f in contents[name] if f.endswith("shader-modules.js")]


@pytest.mark.node
def test_installed_packages_import_and_declare_every_export(fresh_project):
    project, _ = fresh_project
    entries = {specifier: folder / types for folder, (_, specs, _) in PACKAGES.items()
               for specifier, types in specs.items()}
    result = subprocess.run([shutil.which("node"), "--input-type=module", "-e", _IMPORT_SCRIPT, json.dumps(list(entries))],
                            cwd=project, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-4000:]
    out = json.loads(result.stdout)
    for specifier, types in entries.items():
        declared = sorted(set(_DECLARED.findall(types.read_text(encoding="utf-8"))))
        assert out[specifier] == declared, f"{specifier}: exports {out[specifier]}, {types.name} declares {declared}"
    # The installed runtimes run the GLSL `vbusd shader` prints (the three.js one with the pulled
    # skin, the Babylon.js one the attribute binding it adapts).
    assert out["threeModule"] == vbusd.shader("glsl", "dualQuat", "float32", max_influences=4, max_clips=16,
                                              main=False, skin="pulled")
    assert out["babylonModule"] == vbusd.shader("glsl", "quatTranslation", "float16", max_influences=4, max_clips=16,
                                                main=False)
    assert out["coreModule"] == vbusd.shader("glsl", "compactQuatTranslation", "uint32", max_influences=4, max_clips=16,
                                             main=False, layers=True)
    assert out["gltfTransform"][1:] == ["/Walk", ["VBUSD_virtual_bones"]]
