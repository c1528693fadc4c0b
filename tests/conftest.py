"""Shared pytest configuration for the vbusd test suite: markers and a few generic fixtures.

Tests import the *installed* ``vbusd`` (pytest runs with ``--import-mode=importlib`` and the repo
root is not a package path), so nothing here puts the source tree on ``sys.path``. Files of the
repository that are not installed (samples/, benchmarks/, spec/) are reached through
:func:`repo_root`.
"""

from __future__ import annotations

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
    :mod:`vbusd.bake_kernels` forced on (however small the input). Skips the compiled run where
    warp's CPU backend cannot run."""
    from vbusd import bake_kernels

    if request.param == "compiled":
        if not bake_kernels.available():
            pytest.skip("warp's CPU backend cannot compile kernels here (pip install warp-lang)")
        monkeypatch.setattr(bake_kernels, "MIN_ITEMS", 0)
    else:
        monkeypatch.setattr(bake_kernels, "MIN_ITEMS", 1 << 62)
    return request.param
