"""The suite's shared fixtures (loaded by tests/conftest.py through ``pytest_plugins``).

Session-scoped where a fixture is costly and read-only: one Chromium per kind (WebGL, WebGPU) per
test session (per xdist worker), and each converted asset of the browser tests converted once.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.helpers import browser as browser_helpers
from tests.helpers import wheel as wheel_helpers
from tests.helpers.capabilities import REPO, require, shared_assets_dir
from tests.helpers.once import once_per_run


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository checkout the tests run from (for samples/, spec/, benchmarks/)."""
    return REPO


@pytest.fixture(scope="session")
def shared_assets() -> Path:
    """Folder of the real third-party assets (see its README.md); skips the test when absent (fails
    where the assets are required: CI)."""
    require("assets")
    return shared_assets_dir()


@pytest.fixture(scope="session")
def built_wheel(tmp_path_factory) -> tuple:
    """(snapshot of the checkout, the vbusd wheel built from it), made once per test run for every
    xdist worker (the packaging tests check it, the Blender extension test bundles it)."""
    return once_per_run(tmp_path_factory, "wheel", wheel_helpers.build_wheel)


@pytest.fixture(params=["numpy", "compiled"])
def both_bake_paths(request, monkeypatch) -> str:
    """Run a test twice: on the bake's numpy code, then with every compiled twin in
    :mod:`vbusd.kernels.bake` forced on (however small the input). The compiled run needs warp's
    CPU backend (capability ``warp``)."""
    from vbusd.kernels import bake as bake_kernels

    if request.param == "compiled":
        require("warp")
        monkeypatch.setattr(bake_kernels, "MIN_ITEMS", 0)
    else:
        monkeypatch.setattr(bake_kernels, "MIN_ITEMS", 1 << 62)
    return request.param


@pytest.fixture(scope="session")
def playwright_driver():
    """playwright's sync driver, one per test session: a process may run only one at a time, so both
    browsers below are launched from it; tests never call vbusd.web.browser.chromium, which starts a
    driver of its own."""
    require("browser")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as driver:
        yield driver


@pytest.fixture(scope="session")
def browser(playwright_driver):
    """Headless Chromium (software WebGL 2; vbusd.web.browser's arguments), one per test session."""
    from vbusd.web.browser import launch

    launched = launch(playwright_driver, webgpu=False)
    yield launched
    launched.close()


@pytest.fixture(scope="session")
def webgpu_browser(playwright_driver):
    """Headless Chromium that also offers WebGPU through SwiftShader, one per test session."""
    from vbusd.web.browser import launch

    launched = launch(playwright_driver, webgpu=True)
    yield launched
    launched.close()


@pytest.fixture(scope="session")
def stadium_assets(tmp_path_factory):
    """The stadium's UsdSkel source converted per encoding and format, with the sample's crowd."""
    return browser_helpers.build_stadium_assets(tmp_path_factory.mktemp("stadium"))


@pytest.fixture(scope="session")
def compact_stadium(tmp_path_factory):
    """Format 1.2: the stadium converted with compactQuatTranslation (uint32 words), with its crowd."""
    return browser_helpers.build_compact_stadium(tmp_path_factory.mktemp("compact"))


@pytest.fixture(scope="session")
def character_crowd(shared_assets, tmp_path_factory):
    """Fox and CesiumMan, compact encoding, one crossfading crowd (``vbusd crowd --fade-clips``)."""
    return browser_helpers.build_character_crowd(shared_assets, tmp_path_factory.mktemp("characters"))


@pytest.fixture(scope="session")
def character_layers_crowd(shared_assets, tmp_path_factory):
    """Fox and CesiumMan with a bone mask and root motion (CesiumMan with a generated level of detail), one crowd
    crossfading and playing a layer (``vbusd crowd --layout points --fade-clips ... --layer ...``)."""
    return browser_helpers.build_character_layers_crowd(shared_assets, tmp_path_factory.mktemp("character_layers"))


@pytest.fixture(scope="session")
def rig_assets(tmp_path_factory):
    """The bar fixture (glTF) converted with the encodings that hold its growing scale."""
    return browser_helpers.build_rig_assets(tmp_path_factory.mktemp("bar"))


@pytest.fixture(scope="session")
def bar_crowd(tmp_path_factory):
    """A crowd of the bar rig: every instance its own clip, offset, rate, orientation and scale."""
    return browser_helpers.build_bar_crowd(tmp_path_factory.mktemp("bar_crowd"))


@pytest.fixture
def glslang() -> None:
    """The test runs glslangValidator and spirv-cross (``@pytest.mark.usefixtures("glslang")``)."""
    require("glslang")
