"""Build the viewer's package data from web/: run after changing web/, vbusd's shaders or three.js.

1. Writes web/src/shader-modules.js from vbusd.decoders.shaders (vbusd.web.shader_modules), so the
   three.js runtime runs the GLSL ``vbusd shader`` prints, never a retyped copy.
2. Copies the runtime (web/src/*.js, web/src/webgpu/*.js) to vbusd/web/static/vbusd-three/ and the viewer pages
   (web/viewer/*) to vbusd/web/static/.
3. Copies the Babylon.js runtime (web/babylon/src/*.js) to vbusd/web/static/vbusd-babylon/ with its own
   copy of the shader modules, and the esbuild bundle of Babylon.js (web/babylon/dist, built by
   ``npm run bundle`` in web/babylon; the copy under static/babylon/ is committed) with its licence.
4. Copies three.js (three.module.js, three.core.js, its LICENSE and the addons the page imports)
   from web/node_modules/three (``npm ci`` in web/ installs the version package-lock.json pins) to
   vbusd/web/static/three/, so ``vbusd view`` works offline from the wheel, without a CDN.

Usage: ``python scripts/sync_web.py`` (writes), ``python scripts/sync_web.py --check`` (lists
what is stale and exits 1; writes nothing). tests/test_browser_package.py runs the check.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
WEB = REPO / "web"
STATIC = REPO / "vbusd" / "web" / "static"
THREE = WEB / "node_modules" / "three"
BABYLON = WEB / "babylon"
#: Babylon.js' modules, bundled once by esbuild (``npm run bundle`` in web/babylon: @babylonjs/core's
#: ES modules are ~1,800 files); the bundle is committed, so the wheel builds without node.
BABYLON_BUNDLE = BABYLON / "dist" / "babylon.bundle.js"

THREE_FILES = {
    "build/three.module.js": "three/three.module.js",
    "build/three.core.js": "three/three.core.js",
    "build/three.webgpu.js": "three/three.webgpu.js",  # `vbusd view --engine three-webgpu`
    "build/three.tsl.js": "three/three.tsl.js",
    "LICENSE": "three/LICENSE",
    "examples/jsm/controls/OrbitControls.js": "three/addons/controls/OrbitControls.js",
    "examples/jsm/loaders/GLTFLoader.js": "three/addons/loaders/GLTFLoader.js",
    "examples/jsm/utils/BufferGeometryUtils.js": "three/addons/utils/BufferGeometryUtils.js",
    "examples/jsm/utils/SkeletonUtils.js": "three/addons/utils/SkeletonUtils.js",
    "examples/jsm/libs/ktx-parse.module.js": "three/addons/libs/ktx-parse.module.js",
    "examples/jsm/libs/zstddec.module.js": "three/addons/libs/zstddec.module.js",
}


def planned_files(*, with_three: bool = True) -> dict[Path, bytes]:
    """Every generated or copied file and the bytes it must hold.

    Args:
        with_three: Include the three.js copies (needs web/node_modules/three).

    Returns:
        Target path -> content.
    """
    from vbusd.web.shader_modules import javascript_module

    files: dict[Path, bytes] = {WEB / "src" / "shader-modules.js": javascript_module().encode("utf-8")}
    for source in sorted((WEB / "src").glob("*.js")):
        if source.name != "shader-modules.js":
            files[STATIC / "vbusd-three" / source.name] = source.read_bytes()
    for source in sorted((WEB / "src" / "webgpu").glob("*.js")):  # the three.js WebGPU (TSL) runtime
        files[STATIC / "vbusd-three" / "webgpu" / source.name] = source.read_bytes()
    files[STATIC / "vbusd-three" / "shader-modules.js"] = files[WEB / "src" / "shader-modules.js"]
    # The Babylon.js runtime (web/babylon/src) with its own copy of the shader modules.
    files[BABYLON / "src" / "shader-modules.js"] = files[WEB / "src" / "shader-modules.js"]
    for source in sorted((BABYLON / "src").glob("*.js")):
        if source.name not in ("shader-modules.js", "babylon-entry.js"):
            files[STATIC / "vbusd-babylon" / source.name] = source.read_bytes()
    files[STATIC / "vbusd-babylon" / "shader-modules.js"] = files[WEB / "src" / "shader-modules.js"]
    if BABYLON_BUNDLE.is_file():
        files[STATIC / "babylon" / "babylon.bundle.js"] = BABYLON_BUNDLE.read_bytes()
    licence = BABYLON / "node_modules" / "@babylonjs" / "core" / "license.md"
    if licence.is_file():
        files[STATIC / "babylon" / "LICENSE"] = licence.read_bytes()
    for source in sorted((WEB / "viewer").iterdir()):
        files[STATIC / source.name] = source.read_bytes()
    if with_three:
        for source, target in THREE_FILES.items():
            files[STATIC / target] = (THREE / source).read_bytes()
    return files


def stale(files: dict[Path, bytes]) -> list[Path]:
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
    with_three = THREE.is_dir()
    if not with_three:
        print("sync_web: web/node_modules/three is missing (run `npm ci` in web/); three.js files not checked",
              file=sys.stderr)
    files = planned_files(with_three=with_three)
    outdated = stale(files)
    if args.check:
        for path in outdated:
            print(f"stale: {path.relative_to(REPO)}")
        return 1 if outdated else 0
    from vbusd.io.files import atomic_write

    for path in outdated:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as handle:
            handle.write(files[path])
        print(f"wrote {path.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
