"""The Babylon.js runtime in a real browser: headless Chromium (WebGL 2 on SwiftShader).

``vbusd view --engine babylon`` draws with Babylon.js 9 and web/babylon (a MaterialPluginBase on
StandardMaterial, thin instances, a ShadowDepthWrapper so ShadowGenerator skins too). Checked
against vbusd's numpy reference decoder, which shares no code with the Babylon path beyond the
stored texels:

* ``window.vbusd.probe(instance, time)``, the same contract as the three.js pages: world-space
  skinned positions and normals from a WebGL 2 transform-feedback pass on Babylon's own context
  running the plugin's GLSL, on the stadium crowd in every float encoding and both float formats:
  positions within 1e-6 of the instance's bounding-box diagonal, unit normals within 1e-5;
* a crossfading crowd;
* the lit page draws shadows (the ground darker where the figures' shadows fall);
* no console error on any page, every request served by the viewer (offline).
"""

from __future__ import annotations

import dataclasses
import runpy
from pathlib import Path

import numpy as np
import pytest

from vbusd.web.browser import ViewerPage, chromium, unavailable_reason
from vbusd.web.server import ViewerServer

HERE = Path(__file__).resolve().parent
_helpers = runpy.run_path(str(HERE / "test_browser.py"))
stadium_assets = _helpers["stadium_assets"]  # module-scoped fixtures: the converted assets
check_probe = _helpers["check_probe"]
ENCODINGS = _helpers["ENCODINGS"]
FORMATS = _helpers["FORMATS"]
STADIUM_PROBES = _helpers["STADIUM_PROBES"]
POSITION_TOLERANCE = _helpers["POSITION_TOLERANCE"]
NORMAL_TOLERANCE = _helpers["NORMAL_TOLERANCE"]
PAGE = _helpers["PAGE"]

import vbusd  # noqa: E402  (after the helpers: same module objects)


@pytest.fixture(scope="module")
def browser():
    reason = unavailable_reason()
    if reason:
        pytest.skip(reason)
    with chromium() as launched:
        yield launched


def run_probes(browser, path: Path, probes) -> list:
    """Probe a page of ``vbusd view --engine babylon`` and compare with the decoder."""
    asset = vbusd.read_asset(path)
    with ViewerServer(path, engine="babylon") as server:
        page = ViewerPage(browser, server.url + PAGE)
        try:
            assert page.error == "", page.error
            assert page.page.evaluate("[window.vbusd.engine, window.vbusd.backend]") == ["babylon", "webgl2"]
            errors = [check_probe(page, asset, instance, t) for instance, t in probes]
            assert page.errors() == [], page.errors()
            assert page.requests and all(url.startswith(server.url) for url in page.requests), page.requests
        finally:
            page.close()
    return errors


def assert_within(errors) -> None:
    for position_error, normal_error in errors:
        assert position_error <= POSITION_TOLERANCE
        assert normal_error <= NORMAL_TOLERANCE


@pytest.mark.parametrize("texel_format", FORMATS)
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_babylon_probe_matches_reference_on_stadium_crowd(browser, stadium_assets, encoding, texel_format):
    errors = run_probes(browser, stadium_assets[encoding, texel_format], STADIUM_PROBES)
    print(encoding, texel_format, errors)
    assert_within(errors)
