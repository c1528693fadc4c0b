"""Shared pytest configuration for the vbusd test suite: markers and a few generic fixtures.

Tests import the *installed* ``vbusd`` (pytest runs with ``--import-mode=importlib`` and the repo
root is not a package path), so nothing here puts the source tree on ``sys.path``. Files of the
repository that are not installed (samples/, benchmarks/, spec/) are reached through
:func:`repo_root`.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

# Before any test module touches pxr.Usd: OpenUSD builds its schema registry once per process, and
# the Virtual Bones types are in it only if vbusd registered its plugin first (vbusd.io.usd_plugin).
# Importing vbusd here makes that independent of which test files run and in which order.
import vbusd  # noqa: F401,E402

REPO_ROOT = Path(__file__).resolve().parents[1]


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: takes more than a few seconds; deselect with -m 'not slow'")
    config.addinivalue_line(
        "markers", "packaging: builds the wheel (needs the 'build' tool and, without the build backend "
                   "installed, network access); deselect with -m 'not packaging'")
    config.addinivalue_line(
        "markers", "parity(feature, engine=None): a cell of docs/engines.md's feature x engine table "
                   "(the engine from the test's `engine` parameter unless given); --parity-json records it")
    config._parity_cells = {}


def pytest_addoption(parser):
    parser.addoption("--parity-json", default=None, metavar="PATH",
                     help="record the feature x engine cells the parity tests ran (passed, failed or skipped) into "
                          "PATH (JSON, merged with what it holds); scripts/engine_table.py renders docs/engines.md from it")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    marker = item.get_closest_marker("parity")
    if marker is None or not item.config.getoption("--parity-json"):
        return
    if report.when == "setup" and not report.skipped:
        return
    if report.when not in ("setup", "call"):
        return
    engine = marker.kwargs.get("engine") or getattr(getattr(item, "callspec", None), "params", {}).get("engine")
    name = item.nodeid.split("::", 1)[1].split("[", 1)[0]
    cell = {"test": f"{Path(str(item.fspath)).name}::{name}"}
    notes = [value for key, value in item.user_properties if key == "parity_note"]
    if notes:
        cell["note"] = notes[-1]
    if report.passed:
        cell["outcome"] = "passed"
    elif report.skipped:
        cell["outcome"] = "skipped"
        cell["note"] = str(report.longrepr[2] if isinstance(report.longrepr, tuple) else report.longrepr).removeprefix("Skipped: ")
    else:
        cell["outcome"] = "failed"
    item.config._parity_cells.setdefault(marker.args[0], {})[engine] = cell


def pytest_sessionfinish(session):
    path = session.config.getoption("--parity-json")
    cells = getattr(session.config, "_parity_cells", {})
    if not path or not cells:
        return
    path = Path(path)
    recorded = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
    for feature, engines in cells.items():
        recorded.setdefault(feature, {}).update(engines)
    path.write_text(json.dumps(recorded, indent=1, sort_keys=True) + "\n", encoding="utf-8")


# The browser tests draw every engine (three.js WebGL, three.js WebGPU, Babylon.js) in software
# (SwiftShader on the CPU): each probe case is a page load and a shader compile, seconds each. By
# default they run a covering set: every encoding, every texel format and both skin bindings at
# least once per engine and per character, each (encoding, texel format) pair once, so that the
# whole suite stays within 15 minutes on 2 cores. VBUSD_FULL_MATRIX=1 runs every combination.
BROWSER_FILES = {"test_browser.py", "test_browser_babylon.py", "test_browser_webgpu.py"}
COVER = {("crossMatrix", "float16"): "pulled", ("affineMatrix", "float32"): "attributes",
         ("quatTranslation", "float16"): "attributes", ("dualQuat", "float32"): "pulled"}
"""The (encoding, texel format) pairs of the default browser matrix, with the skin binding each runs in."""
CHARACTER_COVER = {("Fox", "crossMatrix"), ("Fox", "quatTranslation"), ("CesiumMan", "affineMatrix"),
                   ("CesiumMan", "dualQuat")}


def _in_browser_cover(item) -> bool:
    """Whether a browser test case is in the default matrix. Only full products are thinned (an
    ``encoding`` parametrization beside a ``texel_format`` or ``character`` one); cases listed
    pair by pair all run."""
    params = getattr(getattr(item, "callspec", None), "params", {})
    axes = {m.args[0] for m in item.iter_markers("parametrize") if m.args}
    encoding = params.get("encoding")
    if "encoding" in axes and "texel_format" in axes:
        pair = (encoding, params.get("texel_format"))
        return pair in COVER and params.get("skin") in (None, COVER[pair])
    if "encoding" in axes and "character" in axes:
        return (params.get("character"), encoding) in CHARACTER_COVER
    return True


def pytest_collection_modifyitems(config, items):
    if os.environ.get("VBUSD_FULL_MATRIX") == "1":
        return
    keep, drop = [], []
    for item in items:
        (keep if Path(str(item.fspath)).name not in BROWSER_FILES or _in_browser_cover(item) else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


def pytest_terminal_summary(terminalreporter):
    if os.environ.get("VBUSD_FULL_MATRIX") != "1":
        terminalreporter.write_line("browser tests ran their covering matrix (every encoding, texel format and skin "
                                    "binding); VBUSD_FULL_MATRIX=1 runs every combination")


def _shared_assets_dir() -> Path | None:
    """The third-party test assets: ``$VBUSD_SHARED_ASSETS``, else ``../shared/assets`` beside the checkout."""
    candidates = [os.environ.get("VBUSD_SHARED_ASSETS"), REPO_ROOT.parent / "shared" / "assets"]
    for candidate in candidates:
        if candidate and Path(candidate).is_dir():
            return Path(candidate)
    return None


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository checkout the tests run from (for samples/, spec/, benchmarks/)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def shared_assets() -> Path:
    """Folder of the real third-party assets (see its README.md); skips the test when absent."""
    path = _shared_assets_dir()
    if path is None:
        pytest.skip("shared third-party assets not found (set VBUSD_SHARED_ASSETS)")
    return path


@pytest.fixture(params=["numpy", "compiled"])
def both_bake_paths(request, monkeypatch) -> str:
    """Run a test twice: on the bake's numpy code, then with every compiled twin in
    :mod:`vbusd.kernels.bake` forced on (however small the input). Skips the compiled run where
    warp's CPU backend cannot run."""
    from vbusd.kernels import bake as bake_kernels

    if request.param == "compiled":
        if not bake_kernels.available():
            pytest.skip("warp's CPU backend cannot compile kernels here (pip install warp-lang)")
        monkeypatch.setattr(bake_kernels, "MIN_ITEMS", 0)
    else:
        monkeypatch.setattr(bake_kernels, "MIN_ITEMS", 1 << 62)
    return request.param
