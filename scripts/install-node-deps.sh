#!/usr/bin/env bash
# Install the npm packages, each folder pinned by its package-lock.json (`npm ci`):
#
# * tests/node: what the Node-based tests check vbusd against: ktx-parse (three.js's KTX2 parser),
#   three (GLTFLoader, KTX2Loader) and gltf-validator (the Khronos glTF-Validator);
# * web: the three.js runtime's one (peer) dependency, three, which scripts/sync_web.py copies into
#   web/vendor/three-<version>/ and tests/test_browser_package.py checks (vendored copy = pinned
#   version, runtime shader module = `vbusd shader` under Node);
# * web/babylon: the Babylon.js runtime's peers @babylonjs/core and @babylonjs/loaders (and esbuild,
#   which bundles Babylon.js for vbusd view: `npm run bundle`, then scripts/sync_web.py);
#   tests/test_npm_packages.py installs the packed runtimes with them;
# * web/gltf-transform: the glTF-Transform extension for VBUSD_virtual_bones and what its tests and
#   the gltf-transform CLI need (@gltf-transform/core, extensions, functions, cli, meshoptimizer,
#   draco3dgltf, gltf-validator); tests/test_gltf_transform.py runs its Node tests.
#
# Without node and npm it says what to install and returns 0: the tests that need them then skip
# with one line (in CI, CI=true, they fail naming the capability 'node': tests/helpers/capabilities.py),
# and everything else still runs. A folder whose installed lockfile is current is left as it is.
set -uo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)" || exit 0

if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
    echo "install-node-deps: node and npm not found; install Node.js 18 or newer (Debian: apt-get install nodejs npm) for the KTX2, glTF package and three.js runtime tests" >&2
    exit 0
fi
for folder in tests/node web web/babylon web/gltf-transform; do
    cd "$repo/$folder" || continue
    if [ -f node_modules/.package-lock.json ] && cmp -s package-lock.json node_modules/.vbusd-installed-lock 2>/dev/null; then
        continue
    fi
    if npm ci --no-audit --no-fund --loglevel=error >/dev/null; then
        cp package-lock.json node_modules/.vbusd-installed-lock
    else
        echo "install-node-deps: npm ci failed in $folder; the tests that need it will skip" >&2
    fi
done
exit 0
