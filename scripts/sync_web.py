"""Keep web/'s generated and third-party files current: run after changing vbusd's shaders, three.js or Babylon.js.

1. Writes web/core/src/shader-modules.js from vbusd.decoders.shaders (vbusd.web.shader_modules), so the
   runtimes run the GLSL ``vbusd shader`` prints, never a retyped copy. It is the one copy (@vbusd/core): every
   runtime imports it as ``@vbusd/core/shader-modules``.
2. Copies three.js (its builds, its LICENSE and the addons the pages import) from
   web/node_modules/three (``npm ci`` in web/ installs the version web/package.json pins) to
   web/vendor/three-<version>/, with a README.md naming the version and where each file came from.
3. Copies the esbuild bundle of Babylon.js (web/babylon/dist/babylon.bundle.js, built by
   ``npm run bundle`` in web/babylon) and Babylon.js' licence to web/vendor/babylon-<version>/,
   with a README.md likewise.

A vendor folder of another version is removed: each third-party build is in the repository once.
Nothing is copied into vbusd/: the wheel's vbusd/web/static/ is made from web/ when the wheel is
built (setup.py, vbusd/web/static_files.py), and ``vbusd view`` from a checkout serves web/ itself.

Usage: ``python scripts/sync_web.py`` (writes), ``python scripts/sync_web.py --check`` (lists
what is stale and exits 1; writes nothing). tests/test_browser_package.py runs the check. What is
not installed (web/node_modules/three, web/babylon/node_modules, the bundle) is not compared; the
README.md files are checked against the pinned versions either way.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere: this checkout's vbusd
    sys.path.insert(0, str(REPO))

from vbusd.io.files import atomic_write  # noqa: E402
from vbusd.web.shader_modules import javascript_module  # noqa: E402

WEB = REPO / "web"
VENDOR = WEB / "vendor"
THREE = WEB / "node_modules" / "three"
BABYLON = WEB / "babylon"
#: Babylon.js' modules, bundled once by esbuild (``npm run bundle`` in web/babylon: @babylonjs/core's
#: ES modules are ~1,800 files).
BABYLON_BUNDLE = BABYLON / "dist" / "babylon.bundle.js"
BABYLON_LICENCE = BABYLON / "node_modules" / "@babylonjs" / "core" / "license.md"

#: three.js' file (in the npm package) -> its path in web/vendor/three-<version>/ (the URL /three/...).
THREE_FILES = {
    "build/three.module.js": "three.module.js",
    "build/three.core.js": "three.core.js",
    "build/three.webgpu.js": "three.webgpu.js",  # `vbusd view --engine three-webgpu`
    "build/three.tsl.js": "three.tsl.js",
    "LICENSE": "LICENSE",
    "examples/jsm/controls/OrbitControls.js": "addons/controls/OrbitControls.js",
    "examples/jsm/loaders/GLTFLoader.js": "addons/loaders/GLTFLoader.js",
    "examples/jsm/utils/BufferGeometryUtils.js": "addons/utils/BufferGeometryUtils.js",
    "examples/jsm/utils/SkeletonUtils.js": "addons/utils/SkeletonUtils.js",
    "examples/jsm/libs/zstddec.module.js": "addons/libs/zstddec.module.js",
    # Motion vectors under WebGPURenderer (the TRAA picture of docs/engines.md, `?post=traa`).
    "examples/jsm/tsl/display/TRAANode.js": "addons/tsl/display/TRAANode.js",
    "examples/jsm/tsl/display/MotionBlur.js": "addons/tsl/display/MotionBlur.js",
    "examples/jsm/tsl/utils/TAAUtils.js": "addons/tsl/utils/TAAUtils.js",
}


def pinned_versions() -> dict:
    """The versions web/package.json and web/babylon/package.json pin (their devDependencies)."""
    three = json.loads((WEB / "package.json").read_text(encoding="utf-8"))["devDependencies"]
    babylon = json.loads((BABYLON / "package.json").read_text(encoding="utf-8"))["devDependencies"]
    return {"three": three["three"], "babylon": babylon["@babylonjs/core"], "esbuild": babylon["esbuild"]}


def three_readme(version: str) -> str:
    rows = "\n".join(f"| `{source}` | `{target}` |" for source, target in THREE_FILES.items())
    return f"""# three.js {version} (third-party, vendored)

The files of [three.js](https://threejs.org) {version} that the pages of `vbusd view` and the
examples of docs/engines.md import, unchanged, from the npm package `three@{version}`
(web/package.json pins it; `npm ci` in web/ installs it). Written by `python scripts/sync_web.py`,
which tests/test_browser_package.py checks; do not edit. Licence: MIT, three.js' own `LICENSE`
beside this file. The pages see this folder as `/three/`; the wheel's copy is made from it when
the wheel is built (setup.py).

| file of the npm package | here |
|---|---|
{rows}
"""


def babylon_readme(version: str, esbuild: str) -> str:
    return f"""# Babylon.js {version} (third-party, vendored bundle)

`babylon.bundle.js` is `@babylonjs/core` and `@babylonjs/loaders` {version} (web/babylon/package.json
pins them) bundled by esbuild {esbuild} from web/babylon/bundle-entry.js, which names the exports the
Babylon.js page of `vbusd view` and docs/engines.md's example use: `npm run bundle` in web/babylon
(minified, ES module, the licence comments kept at its end; @babylonjs/core alone is ~1,800 ES
module files). `LICENSE` is `@babylonjs/core`'s `license.md` (Apache-2.0). Copied here by
`python scripts/sync_web.py`, which tests/test_browser_package.py checks; do not edit. The pages
see this folder as `/babylon/`; the wheel's copy is made from it when the wheel is built (setup.py).
"""


def planned_files() -> tuple:
    """Every generated or copied file with the bytes it must hold, and the vendor folders to remove.

    Returns:
        (target path -> content, [stale vendor folders]). Copies whose source is not installed are
        left out (not compared).
    """
    versions = pinned_versions()
    three_folder = VENDOR / f"three-{versions['three']}"
    babylon_folder = VENDOR / f"babylon-{versions['babylon']}"
    files: dict[Path, bytes] = {
        WEB / "core" / "src" / "shader-modules.js": javascript_module().encode("utf-8"),
        three_folder / "README.md": three_readme(versions["three"]).encode("utf-8"),
        babylon_folder / "README.md": babylon_readme(versions["babylon"], versions["esbuild"]).encode("utf-8"),
    }
    if (THREE / "package.json").is_file():
        installed = json.loads((THREE / "package.json").read_text(encoding="utf-8"))["version"]
        if installed != versions["three"]:
            raise SystemExit(f"sync_web: web/node_modules/three is {installed}, web/package.json pins "
                             f"{versions['three']}: run npm ci in web/")
        for source, target in THREE_FILES.items():
            files[three_folder / target] = (THREE / source).read_bytes()
    if BABYLON_BUNDLE.is_file():
        files[babylon_folder / "babylon.bundle.js"] = BABYLON_BUNDLE.read_bytes()
    if BABYLON_LICENCE.is_file():
        files[babylon_folder / "LICENSE"] = BABYLON_LICENCE.read_bytes()
    keep = {three_folder, babylon_folder}
    stale_folders = sorted(path for name in ("three", "babylon") for path in VENDOR.glob(f"{name}-*")
                           if path.is_dir() and path not in keep)
    return files, stale_folders


def stale(files: dict) -> list:
    """The planned files whose content on disk differs (or that are missing)."""
    return [path for path, data in files.items() if not path.is_file() or path.read_bytes() != data]


def main(argv=None) -> int:
    """Write the stale files (or, with ``--check``, list them and return 1 if any).

    Args:
        argv: Command-line arguments (default: ``sys.argv[1:]``).

    Returns:
        The exit status.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="list stale files, exit 1 if any; write nothing")
    args = parser.parse_args(argv)
    if not THREE.is_dir():
        print("sync_web: web/node_modules/three is missing (run `npm ci` in web/); three.js files not compared",
              file=sys.stderr)
    files, old_folders = planned_files()
    outdated = stale(files)
    if args.check:
        for path in outdated + old_folders:
            print(f"stale: {path.relative_to(REPO)}")
        return 1 if outdated or old_folders else 0
    for path in outdated:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as handle:
            handle.write(files[path])
        print(f"wrote {path.relative_to(REPO)}")
    for folder in old_folders:
        shutil.rmtree(folder)
        print(f"removed {folder.relative_to(REPO)} (another version)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
