#!/usr/bin/env bash
# Install the npm packages the Node-based tests check vbusd against (tests/node/package.json, pinned
# by its package-lock.json): ktx-parse (three.js's KTX2 parser), three (GLTFLoader, KTX2Loader) and
# gltf-validator (the Khronos glTF-Validator). Runs `npm ci` in tests/node.
#
# Without node and npm it says what to install and returns 0: the tests that need them then skip
# with one line, and everything else still runs.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../tests/node" || exit 0

if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
    echo "install-node-deps: node and npm not found; install Node.js 18 or newer (Debian: apt-get install nodejs npm) for the KTX2 and glTF package tests" >&2
    exit 0
fi
if [ -f node_modules/.package-lock.json ] && cmp -s package-lock.json node_modules/.vbusd-installed-lock 2>/dev/null; then
    exit 0
fi
if npm ci --no-audit --no-fund --loglevel=error >/dev/null; then
    cp package-lock.json node_modules/.vbusd-installed-lock
else
    echo "install-node-deps: npm ci failed in tests/node; the KTX2 and glTF package tests will skip" >&2
fi
exit 0
