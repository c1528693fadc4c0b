#!/usr/bin/env bash
# Install the Debian packages the shader tests run on: Mesa's EGL/OpenGL (llvmpipe runs the GLSL
# without a GPU), Mesa's Vulkan drivers (lavapipe runs the WGSL through wgpu), glslang-tools (HLSL front end) and spirv-cross (SPIR-V back to GLSL); and what the
# browser tests (tests/test_browser.py, the README picture) run on: Debian's chromium (headless, with
# SwiftShader's software WebGL 2) and playwright-python from the package index, used only as the
# driver of that chromium (vbusd.web.browser passes its executable; playwright's own browser
# download is neither run nor needed).
#
# Installs only what is missing, and only where apt-get can (root, or sudo without a password).
# Elsewhere it says what to install and returns 0: the tests that need what is missing then skip
# with one line per capability (in CI, CI=true, they fail naming it: tests/helpers/capabilities.py),
# and everything else still runs.
set -uo pipefail

missing=()
command -v glslangValidator >/dev/null 2>&1 || missing+=(glslang-tools)
command -v spirv-cross >/dev/null 2>&1 || missing+=(spirv-cross)
# Shared libraries as the dynamic loader sees them (moderngl's glcontext finds libEGL.so.1 and
# libGL.so.1 through `ldconfig -p` too). ldconfig lives in /sbin, which a non-root PATH may lack.
# No `grep -q`: under pipefail its early exit can kill ldconfig with SIGPIPE and fail the test.
libraries=$( { command -v ldconfig >/dev/null 2>&1 && ldconfig -p || /sbin/ldconfig -p; } 2>/dev/null)
has_library() { printf '%s\n' "$libraries" | grep -F "$1" >/dev/null; }
has_library 'libEGL.so.1 ' || missing+=(libegl1)
has_library 'libGL.so.1 ' || missing+=(libgl1)
has_library 'libEGL_mesa.so.0 ' || missing+=(libegl-mesa0)
# llvmpipe, Mesa's software rasterizer, is in the DRI driver package.
compgen -G '/usr/lib/*/dri/swrast_dri.so' >/dev/null || compgen -G '/usr/lib/dri/swrast_dri.so' >/dev/null \
    || missing+=(libgl1-mesa-dri)
# lavapipe, Mesa's software Vulkan driver, runs the WGSL modules through the wgpu package (WebGPU).
compgen -G '/usr/share/vulkan/icd.d/lvp_icd*.json' >/dev/null || missing+=(mesa-vulkan-drivers)
command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || missing+=(chromium)

# playwright-python (the driver; a wheel with its own Node runtime inside). Allowed to fail: the
# browser tests then skip with one line saying what to install.
install_playwright() {
    python -c 'import playwright.sync_api' >/dev/null 2>&1 && return 0
    echo "install-system-deps: installing playwright (Python package) for the browser tests" >&2
    python -m pip install -q 'playwright>=1.40' >/dev/null 2>&1 \
        || echo "install-system-deps: pip could not install playwright; the browser tests will skip" >&2
    return 0
}
install_playwright

[ ${#missing[@]} -eq 0 ] && exit 0

if ! command -v apt-get >/dev/null 2>&1; then
    echo "install-system-deps: no apt-get; install ${missing[*]} (or your system's equivalents) for the shader and browser tests" >&2
    exit 0
fi
if [ "$(id -u)" -eq 0 ]; then
    run=()
elif sudo -n true 2>/dev/null; then
    run=(sudo -n)
else
    echo "install-system-deps: not root; run: sudo apt-get install -y ${missing[*]}" >&2
    exit 0
fi
echo "install-system-deps: installing ${missing[*]}" >&2
"${run[@]}" apt-get update -qq >/dev/null 2>&1 || true
DEBIAN_FRONTEND=noninteractive "${run[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null \
    || echo "install-system-deps: apt-get could not install ${missing[*]}; the shader and browser tests that need them will skip" >&2
exit 0
