"""The three.js WebGPU (TSL) runtime in a real browser: headless Chromium, WebGPU on SwiftShader.

``vbusd view --engine three-webgpu`` draws with WebGPURenderer and web/src/webgpu (node materials:
the skinning as TSL before three's instancing, shadows through ``castShadowPositionNode``). Chromium
offers WebGPU headless with :data:`vbusd.web.browser.WEBGPU_ARGS` (``--enable-unsafe-webgpu
--enable-features=Vulkan --use-vulkan=swiftshader``: Dawn on SwiftShader's Vulkan). Checked against
vbusd's numpy reference decoder, which shares no code with the TSL path beyond the stored texels:

* ``window.vbusd.probe(instance, time)``, the same contract as the WebGL page: world-space skinned
  positions and normals from a compute pass running the materials' own node graph, on the stadium
  crowd in every encoding and both float formats, on the bar glTF rig and the Khronos Fox and
  CesiumMan (shared assets), on a crowd with per-instance clips, offsets and rates, on a
  crossfading crowd, and on ``vbusd export`` packages through GLTFLoader: positions within 1e-6 of the instance's
  bounding-box diagonal, unit normals within 1e-5 (float16 too: the decoder reads the same
  float16 texels, so the bound is float32 arithmetic);
* sockets of a crossfading crowd (``crowd.socketMatrix``) against the decoder's joint transforms;
* the picture against the decoder's silhouette (IoU >= 0.98), on both backends;
* docs/engines.md's example page, as written, draws lit and shadowed figures;
* the shadows follow the animation (the figures hidden, their shadows move; without the skinned
  shadow position they are frozen in the rest pose);
* the same probes on WebGPURenderer's WebGL 2 backend (``backend=webgl``: the node graph as GLSL,
  the probe's compute pass through transform feedback), and its picture;
* no console error on any page.

Skips with one line naming what to install when Chromium or playwright is missing, and when the
browser offers no WebGPU adapter.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer

from tests.helpers.browser import (NO_ADAPTER, PAGE, POSITION_TOLERANCE, SAMPLE, STADIUM_PROBES, assert_within,
                                   character_encoding_cases, check_crowd_sockets, check_silhouette,
                                   crossfading_bar_crowd, encoding_format_cases, engine_probe_errors,
                                   open_engine_page, package_probe_errors, run_docs_example, screenshot_luminance)
from tests.helpers.capabilities import unavailable

pytestmark = pytest.mark.browser

@pytest.fixture
def browser(webgpu_browser):
    """This module's pages need WebGPU: the session's Chromium launched with it."""
    return webgpu_browser


def open_page(browser, server: ViewerServer, query: str, **kwargs) -> ViewerPage:
    return open_engine_page(browser, server, query, **kwargs)


def run_probes(browser, path: Path, probes, backend: str = "webgpu") -> list:
    """Probe a page of ``vbusd view --engine three-webgpu`` on ``backend`` (``webgpu`` or
    ``webgl2``, WebGPURenderer's fallback) and compare with the decoder."""
    return engine_probe_errors(browser, path, "three-webgpu", probes, backend=backend,
                               query="&backend=webgl" if backend == "webgl2" else "")


@pytest.mark.parametrize("encoding,texel_format", encoding_format_cases())
def test_webgpu_probe_matches_reference_on_stadium_crowd(browser, stadium_assets, encoding, texel_format):
    errors = run_probes(browser, stadium_assets[encoding, texel_format], STADIUM_PROBES)
    print(encoding, texel_format, errors)
    assert_within(errors)


@pytest.mark.parametrize("encoding,texel_format", encoding_format_cases(encodings=("affineMatrix", "quatTranslation")))
def test_webgpu_probe_matches_reference_on_gltf_bar(browser, rig_assets, encoding, texel_format):
    errors = run_probes(browser, rig_assets[encoding, texel_format], [(0, 0.0), (0, 0.4321), (0, 0.77), (0, 5.0)])
    print(encoding, texel_format, errors)
    assert_within(errors)


def test_webgpu_probe_per_instance_clip_offset_rate(browser, bar_crowd):
    """Each instance its own clip, offset (negative too), rate, orientation and scale."""
    assert_within(run_probes(browser, bar_crowd, [(i, t) for i in range(10) for t in (0.0, 1.37)]))


def test_webgpu_probe_crossfade(browser, bar_crowd, tmp_path):
    """A crossfading crowd (format 1.1): each instance blended with its own fade clip, offset,
    rate and weight, as the reference decoder blends them."""
    path = crossfading_bar_crowd(bar_crowd, tmp_path / "faded" / "faded.usda")
    count = vbusd.read_asset(path).crowds[0].instance_count
    errors = run_probes(browser, path, [(i, t) for i in range(count) for t in (0.0, 0.83)])
    print(errors)
    assert_within(errors)


def test_webgpu_page_sockets_of_a_crossfading_crowd(browser, bar_crowd, tmp_path):
    """Sockets (format 1.1) on the WebGPU page: ``crowd.socketMatrix(i, bone, t)`` of every
    instance of a crossfading crowd equals the decoder's ``crowd_joint_transforms`` (placement
    times the matrix-crossfaded joint) within 1e-6 of the crowd's extent."""
    path = crossfading_bar_crowd(bar_crowd, tmp_path / "sockets" / "faded.usda", for_sockets=True)
    check_crowd_sockets(browser, path, "three-webgpu", "m.toArray()")  # three's column-major elements


def test_webgpu_shadows_follow_the_animation(browser):
    """The shadow pass skins too: with the figures hidden from the camera (no colour, no depth) the
    shadows on the ground change as the crowd moves; without castShadowPositionNode (three's shadow
    material on the rest mesh) they do not."""
    width, height = 480, 200
    query = (f"?paused=1&time=1.0&ui=0&antialias=0&pixelRatio=1&width={width}&height={height}"
             f"&camera=-16,7,27,4,2.2,46&fov=34&instances=400")
    with ViewerServer(SAMPLE / "stadium_crowd_vb.usda", engine="three-webgpu") as server:
        page = open_page(browser, server, query, width=width, height=height)
        try:
            assert page.error == ""
            page.page.evaluate("""() => { for (const crowd of window.vbusd.crowds) for (const mesh of crowd.meshes) {
                mesh.material.colorWrite = false; mesh.material.depthWrite = false; } }""")

            def shot(t: float) -> np.ndarray:
                page.page.evaluate("(t) => { window.vbusd.setTime(t); window.vbusd.render(); }", t)
                return screenshot_luminance(page.page.locator("#view").screenshot())

            def changed(a: np.ndarray, b: np.ndarray) -> float:
                return float((np.abs(a - b) > 8).mean())

            skinned = shot(1.0), shot(3.6)
            page.page.evaluate("""() => { for (const crowd of window.vbusd.crowds) for (const mesh of crowd.meshes) {
                mesh.material.castShadowPositionNode = null; mesh.material.needsUpdate = true; } }""")
            rest = shot(1.0), shot(3.6)
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    print(f"shadow pixels changed: animated {changed(*skinned):.4f}, rest {changed(*rest):.4f}, "
          f"animated vs rest {changed(skinned[0], rest[0]):.4f}")
    assert changed(*skinned) > 0.005
    assert changed(*rest) == 0.0
    assert changed(skinned[0], rest[0]) > 0.005


@pytest.mark.parametrize("encoding, texel_format", [("crossMatrix", "float16"), ("dualQuat", "float32")])
def test_webgl2_backend_probe_matches_reference(browser, stadium_assets, encoding, texel_format):
    """``backend=webgl``: WebGPURenderer's WebGL 2 backend runs the same node graph (as GLSL; the
    probe's compute pass through transform feedback) within the same tolerances."""
    errors = run_probes(browser, stadium_assets[encoding, texel_format], STADIUM_PROBES, backend="webgl2")
    print(encoding, texel_format, errors)
    assert_within(errors)


def test_webgl2_backend_per_instance_and_picture(browser, bar_crowd, stadium_assets):
    """The WebGL 2 backend: per-instance clips, offsets, rates, orientations and scales probed; the
    stadium drawn (white figures on black) without a console error."""
    assert_within(run_probes(browser, bar_crowd, [(i, t) for i in range(10) for t in (0.0, 1.37)], backend="webgl2"))
    with ViewerServer(stadium_assets["crossMatrix", "float16"], engine="three-webgpu") as server:
        page = ViewerPage(browser, server.url + PAGE + "&backend=webgl")
        try:
            assert page.error == "", page.error
            luminance = screenshot_luminance(page.page.locator("#view").screenshot())
            assert (luminance > 128).mean() > 0.001
            assert page.errors() == [], page.errors()
        finally:
            page.close()


@pytest.mark.parametrize("character,encoding", character_encoding_cases(["Fox", "CesiumMan"]))
def test_webgpu_probe_matches_reference_on_gltf_characters(browser, shared_assets, tmp_path, character, encoding):
    """Two real rigs, Khronos samples (Fox: 24 joints, 1,728 vertices, no normals; CesiumMan: 19
    joints, 3,273 vertices with normals), every encoding, float16."""
    path = tmp_path / f"{character}.usda"
    vbusd.convert(shared_assets / "gltf" / character / f"{character}.glb", path,
                  vbusd.ConvertOptions(encoding=encoding, texel_format="float16", check_rows=0))
    errors = run_probes(browser, path, [(0, 0.0), (0, 0.8137), (0, 2.9)])
    print(encoding, errors)
    assert_within(errors)


@pytest.mark.parametrize("case", ["stadium.glb", "bar_crowd.gltf"])
def test_webgpu_probe_through_gltf_plugin(browser, bar_crowd, tmp_path, case):
    """The runtime package of ``vbusd export`` (KTX2, EXT_mesh_gpu_instancing with the _VB_*
    attributes) through three's GLTFLoader and the VirtualBonesGLTFPlugin, drawn by WebGPURenderer:
    the same vertices as the numpy decoder on the USD asset."""
    from vbusd.io.gltf_package import export_gltf

    source = SAMPLE / "stadium_crowd_vb.usda" if case == "stadium.glb" else bar_crowd
    asset = vbusd.read_asset(source)
    package = tmp_path / case
    export_gltf(asset, package)
    probes = [(0, 0.0), (3, 0.61), (asset.crowds[0].instance_count - 1, 2.3)]
    errors = package_probe_errors(browser, package, "three-webgpu", asset, probes)
    assert max(errors) <= POSITION_TOLERANCE


@pytest.mark.parametrize("backend_query", ["", "&backend=webgl"])
def test_webgpu_screenshot_matches_decoder_silhouette(browser, backend_query):
    """WebGPURenderer's picture (MeshBasicNodeMaterial, unlit white on black) against the silhouette
    rasterized from the decoder's vertices with the page's camera (tests/test_browser.py), on
    WebGPU and on the WebGL 2 backend: IoU >= 0.98."""
    check_silhouette(browser, "three-webgpu", backend_query)


def test_docs_engines_example_runs(browser, tmp_path):
    """docs/engines.md's three.js WebGPU page, as written, on a folder laid out as it says (the
    package's static files and a ``vbusd export`` package): it draws lit, shadowed figures and
    logs no error."""
    # Until the lit, shadowed picture is there (or the page says it has no WebGPU).
    messages, _, luminance, _ = run_docs_example(
        browser, tmp_path, "## three.js WebGPU (TSL)",
        lambda image, messages: _lit_and_shadowed(image) == (True, True, True)
        or any("WebGPU is not available" in m for m in messages))
    assert [m for m in messages if m.startswith(("error", "pageerror"))] == [], messages
    if any("WebGPU is not available" in m for m in messages):
        unavailable("browser", NO_ADAPTER)
    # Lit figures (above the ground's ~84), the dark background (33) and shadows on the ground
    # (between the two): all three present.
    assert _lit_and_shadowed(luminance) == (True, True, True), _fractions(luminance)


def _fractions(luminance) -> tuple:
    """(figures, background, shadows): the picture's fractions of lit figures, dark background and shadow."""
    return ((luminance > 95).mean(), (luminance < 40).mean(), ((luminance > 45) & (luminance < 75)).mean())


def _lit_and_shadowed(luminance) -> tuple:
    figures, background, shadows = _fractions(luminance)
    return figures > 0.002, background > 0.05, shadows > 0.02
