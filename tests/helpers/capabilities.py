"""What the machine offers the tests (a browser, an EGL OpenGL context, Node.js ...) and what a run
requires of it.

A test that needs a capability calls :func:`require` (or carries the capability's marker, which
tests/conftest.py turns into that call). When the capability is missing:

* in CI (``CI`` set to anything but ``""``, ``0`` or ``false``), or when ``VBUSD_REQUIRE`` names it
  (``VBUSD_REQUIRE=all``: every capability of :data:`CI_REQUIRES`; ``VBUSD_REQUIRE=browser,node``:
  those two; ``VBUSD_REQUIRE=none``: nothing, CI or not), the test **fails**, naming the capability
  and what to install;
* otherwise the test skips, and every skip of one capability comes from the one ``pytest.skip``
  line below with the same reason, so the run's summary (``-ra``) shows it as one line.

Detection is cheap and done once per process (per xdist worker).
"""

from __future__ import annotations

import functools
import importlib.util
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Optional

import pytest

REPO = Path(__file__).resolve().parents[2]
NODE_HINT = "run scripts/install-node-deps.sh (npm ci in tests/node, web and web/gltf-transform; needs Node.js 18+)"
SYSTEM_HINT = "run scripts/install-system-deps.sh"

# The npm folders the Node-based tests use and a package each must hold once `npm ci` ran there.
NODE_FOLDERS = {"tests/node": ("ktx-parse", "three", "gltf-validator"), "web": ("three",),
                "web/gltf-transform": ("@gltf-transform/core", "@gltf-transform/cli")}


def shared_assets_dir() -> Optional[Path]:
    """The third-party test assets: ``$VBUSD_SHARED_ASSETS``, else ``../shared/assets`` beside the checkout."""
    for candidate in (os.environ.get("VBUSD_SHARED_ASSETS"), REPO.parent / "shared" / "assets"):
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return None


def _browser() -> Optional[str]:
    from vbusd.web.browser import unavailable_reason

    return unavailable_reason()


def _gl() -> Optional[str]:
    if importlib.util.find_spec("moderngl") is None:
        return "moderngl is not installed (pip install '.[test]')"
    import moderngl

    try:
        ctx = moderngl.create_context(standalone=True, backend="egl")
    except Exception as error:  # no EGL driver at all on this machine
        return f"no EGL OpenGL context ({error}); {SYSTEM_HINT} (Mesa's libegl1, libgl1-mesa-dri)"
    ctx.release()
    return None


def _glslang() -> Optional[str]:
    missing = [tool for tool in ("glslangValidator", "spirv-cross") if shutil.which(tool) is None]
    if missing:
        return f"{' and '.join(missing)} not found; {SYSTEM_HINT} (glslang-tools, spirv-cross)"
    return None


def _wgpu() -> Optional[str]:
    if importlib.util.find_spec("wgpu") is None:
        return "the wgpu package is not installed (pip install '.[test]')"
    # Mesa's Vulkan loader prints "XDG_RUNTIME_DIR is invalid" to the terminal without one (a CI
    # container has none); wgpu needs no runtime folder, so any private folder quiets it.
    if not os.environ.get("XDG_RUNTIME_DIR"):
        os.environ["XDG_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="vbusd-xdg-")
    try:
        import wgpu

        adapter = wgpu.gpu.request_adapter_sync()
        if adapter is None:
            raise RuntimeError("no adapter")
        adapter.request_device_sync()
    except Exception as error:  # no Vulkan/Metal/D3D12 driver at all
        return f"no WebGPU adapter for wgpu ({str(error).splitlines()[0] if str(error) else error!r}); {SYSTEM_HINT} (Mesa's mesa-vulkan-drivers: lavapipe)"
    return None


def _node() -> Optional[str]:
    if shutil.which("node") is None:
        return f"node not found: install Node.js 18 or newer, then {NODE_HINT}"
    for folder, packages in NODE_FOLDERS.items():
        missing = [p for p in packages if not (REPO / folder / "node_modules" / p / "package.json").is_file()]
        if missing:
            return f"npm packages {', '.join(missing)} missing in {folder}: {NODE_HINT}"
    return None


def _blender() -> Optional[str]:
    if importlib.util.find_spec("bpy") is None:
        return "bpy is not installed: pip install '.[blender]' (the bpy wheel of Blender 4.2 needs Python 3.11)"
    return None


def _assets() -> Optional[str]:
    if shared_assets_dir() is None:
        return "the shared third-party assets were not found (set VBUSD_SHARED_ASSETS or put them in ../shared/assets)"
    return None


def _lod() -> Optional[str]:
    if importlib.util.find_spec("meshoptimizer") is None:
        return ("meshoptimizer is not installed: pip install 'vbusd[lod]' (the test extra has it; pip builds it, "
                "which needs a C++ compiler and Python's headers)")
    return None


def _warp() -> Optional[str]:
    from vbusd.kernels import bake

    if not bake.available():
        return "warp's CPU backend cannot compile kernels here (pip install warp-lang)"
    return None


def _gpu() -> Optional[str]:
    try:
        import warp as wp

        wp.init()
        if wp.get_cuda_device_count() > 0:
            return None
    except Exception as error:  # warp itself broken: no GPU either
        return f"warp cannot start ({error})"
    return "no CUDA device that warp can use"


CAPABILITIES: dict[str, tuple[Callable[[], Optional[str]], str]] = {
    "browser": (_browser, "headless Chromium driven by playwright (software WebGL 2)"),
    "gl": (_gl, "an EGL OpenGL context through moderngl (Mesa's llvmpipe will do)"),
    "glslang": (_glslang, "glslangValidator and spirv-cross (HLSL and SPIR-V round trips)"),
    "wgpu": (_wgpu, "WebGPU through the wgpu package (Naga validates WGSL; Mesa's lavapipe will do)"),
    "node": (_node, "Node.js with the npm packages of tests/node, web and web/gltf-transform"),
    "blender": (_blender, "the bpy wheel (Blender as a Python module)"),
    "assets": (_assets, "the shared third-party assets (../shared/assets or $VBUSD_SHARED_ASSETS)"),
    "warp": (_warp, "warp's CPU backend (compiled kernels)"),
    "lod": (_lod, "meshoptimizer, the simplifier of generated levels of detail (vbusd convert --lod-ratios)"),
    "gpu": (_gpu, "a CUDA device for warp"),
}
"""Every capability: its check (None when present, else one line saying what to install) and what it is."""

CI_REQUIRES = ("browser", "gl", "glslang", "wgpu", "node", "blender", "assets", "warp", "lod")
"""What CI requires (``CI`` set, or ``VBUSD_REQUIRE=all``): everything but a GPU, which CI has not."""


@functools.cache
def missing(name: str) -> Optional[str]:
    """Why capability ``name`` is missing here (one line), or None when it is present."""
    check, _ = CAPABILITIES[name]
    return check()


def _truthy(value: Optional[str]) -> bool:
    return value is not None and value.strip().lower() not in ("", "0", "false", "no")


def required() -> frozenset[str]:
    """The capabilities this run requires: ``VBUSD_REQUIRE`` when set, else :data:`CI_REQUIRES` in CI."""
    spec = os.environ.get("VBUSD_REQUIRE")
    if spec is None:
        return frozenset(CI_REQUIRES) if _truthy(os.environ.get("CI")) else frozenset()
    names = {part.strip() for part in spec.split(",") if part.strip()}
    if names <= {"none"}:
        return frozenset()
    if "all" in names:
        names = (names - {"all"}) | set(CI_REQUIRES)
    unknown = names - set(CAPABILITIES)
    if unknown:
        raise pytest.UsageError(f"VBUSD_REQUIRE names unknown capabilities {sorted(unknown)}; "
                                f"known: {', '.join(CAPABILITIES)}, all, none")
    return frozenset(names)


SKIP_PREFIX = "capability "
"""Every skip and failure of a missing capability starts ``capability NAME missing: ``."""


def unavailable(name: str, reason: str, *, allow_module_level: bool = False):
    """A capability is missing (``reason`` says what to install): fail where the run requires it,
    else skip. Every such skip comes from here, so ``-ra`` folds them into one line per reason."""
    message = f"{SKIP_PREFIX}{name} missing: {reason}"
    if name in required():
        pytest.fail(f"{message} (required: {'CI is set' if 'VBUSD_REQUIRE' not in os.environ else 'VBUSD_REQUIRE'})",
                    pytrace=False)
    pytest.skip(message, allow_module_level=allow_module_level)


def require(*names: str, allow_module_level: bool = False) -> None:
    """Skip, or fail where the run requires it (see the module's docstring), unless every
    capability of ``names`` is present."""
    for name in names:
        reason = missing(name)
        if reason is not None:
            unavailable(name, reason, allow_module_level=allow_module_level)


def shared_asset(*parts: str) -> Path:
    """A file of the shared third-party assets (``shared_asset("gltf", "Fox", "Fox.glb")``): skips,
    or fails where the assets are required, when the assets or that file are missing."""
    require("assets")
    path = shared_assets_dir().joinpath(*parts)
    if not path.exists():
        unavailable("assets", f"{'/'.join(parts)} is not among the shared assets ({shared_assets_dir()})")
    return path


def shared_asset_params(paths, id=lambda path: path.name) -> list:
    """``pytest.param`` per shared asset file for a parametrization made at collection, or, where
    the assets are missing, one case (``shared-assets-missing``) whose ``require("assets")`` skips
    or fails: never an empty parameter set that pytest would skip silently."""
    if paths:
        return [pytest.param(path, id=id(path)) for path in paths]
    return [pytest.param(None, id="shared-assets-missing")]
