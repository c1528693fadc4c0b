"""Headless Chromium for the viewer's tests, screenshots and frame-time benchmark.

Drives the system's Chromium (Debian package ``chromium``) with playwright-python used only as a
driver (playwright's own browser download is not needed): software WebGL 2 through SwiftShader,
no sandbox (CI runs as root), no background networking.

    with viewer_page(server.url + "?time=1") as page:
        result = page.evaluate("window.vbusd.probe(0, 1.0)")
"""

from __future__ import annotations

import contextlib
import os
import shutil
from typing import Iterator, Optional

__all__ = ["CHROMIUM_ARGS", "WEBGPU_ARGS", "INSTALL_HINT", "chromium_executable", "unavailable_reason", "launch",
           "chromium", "ViewerPage"]

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-default-apps",
    "--disable-extensions",
    "--disable-sync",
    "--no-first-run",
    "--mute-audio",
    # Software rendering compiles a large layered shader for tens of seconds on a loaded machine; the
    # GPU watchdog would kill the GPU process mid-compile and every WebGPU buffer with it.
    "--disable-gpu-watchdog",
]

# WebGPU in headless Chromium (for `vbusd view --engine three-webgpu`), measured with Chromium 156:
# the API is behind --enable-unsafe-webgpu on Linux; Vulkan on SwiftShader gives a software adapter
# (Dawn) that can also present to a canvas. With --use-webgpu-adapter=swiftshader alone an adapter
# appears, but the first canvas frame fails to create its shared image and drops the GPU instance
# ("A valid external Instance reference no longer exists"). Pages must be a secure context
# (127.0.0.1 is).
WEBGPU_ARGS = [
    "--enable-unsafe-webgpu",
    "--enable-features=Vulkan",
    "--use-vulkan=swiftshader",
]

INSTALL_HINT = ("install Chromium and playwright: apt-get install chromium && pip install playwright "
                "(scripts/install-system-deps.sh does both)")


def chromium_executable() -> Optional[str]:
    """The Chromium to drive: ``$VBUSD_CHROMIUM``, else ``chromium`` on PATH, else None."""
    candidate = os.environ.get("VBUSD_CHROMIUM")
    if candidate:
        return candidate if os.access(candidate, os.X_OK) else None
    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    return None


def unavailable_reason() -> Optional[str]:
    """Why the browser cannot run here (one line naming what to install), or None when it can."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return f"playwright is not installed; {INSTALL_HINT}"
    if chromium_executable() is None:
        return f"no chromium executable; {INSTALL_HINT}"
    return None


def launch(playwright, *, webgpu: bool = False) -> object:
    """Launch headless Chromium from a running playwright (``sync_playwright()``); one playwright
    may launch several, e.g. one with WebGPU and one without.

    Args:
        webgpu: Also offer WebGPU through SwiftShader (:data:`WEBGPU_ARGS`).
    """
    executable = chromium_executable()
    if executable is None:
        raise RuntimeError(unavailable_reason())
    return playwright.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS + (WEBGPU_ARGS if webgpu else []))


@contextlib.contextmanager
def chromium(*, webgpu: bool = False) -> Iterator[object]:
    """A headless Chromium browser (playwright ``Browser``), closed on exit.

    Args:
        webgpu: Also offer WebGPU through SwiftShader (:data:`WEBGPU_ARGS`).
    """
    from playwright.sync_api import sync_playwright

    executable = chromium_executable()
    if executable is None:
        raise RuntimeError(unavailable_reason())
    with sync_playwright() as playwright:
        browser = launch(playwright, webgpu=webgpu)
        try:
            yield browser
        finally:
            browser.close()


class ViewerPage:
    """One viewer page in ``browser``: console messages and page errors are collected."""

    def __init__(self, browser, url: str, *, width: int = 960, height: int = 540, timeout_s: float = 60.0):
        self.page = browser.new_page(viewport={"width": width, "height": height}, device_scale_factor=1)
        self.messages: list[str] = []
        self.requests: list[str] = []  # every URL the page asked for (offline check: all on 127.0.0.1)
        self.page.on("request", lambda request: self.requests.append(request.url))
        self.page.on("console", lambda message: self.messages.append(f"{message.type}: {message.text}"))
        self.page.on("pageerror", lambda error: self.messages.append(f"pageerror: {error}"))
        self.page.goto(url)
        self.page.wait_for_function(
            "window.vbusd !== undefined || document.getElementById('error').textContent !== ''",
            timeout=timeout_s * 1000)
        self.error = self.page.evaluate("document.getElementById('error').textContent")

    def errors(self) -> list[str]:
        """Console errors and uncaught exceptions so far."""
        return [m for m in self.messages if m.startswith(("error:", "pageerror:"))]

    def close(self) -> None:
        self.page.close()
