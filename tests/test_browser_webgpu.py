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
from vbusd.web.static_files import copy_static

from tests.helpers.browser import (NORMAL_TOLERANCE, PAGE, POSITION_TOLERANCE, SAMPLE, STADIUM_PROBES,
                                   character_encoding_cases, check_probe, check_silhouette, encoding_format_cases,
                                   package_vertices, reference_instance, screenshot_luminance, settle)
from tests.helpers.capabilities import unavailable

pytestmark = pytest.mark.browser
HERE = Path(__file__).resolve().parent

NO_ADAPTER = "this Chromium offers no WebGPU adapter (see vbusd.web.browser.WEBGPU_ARGS)"


@pytest.fixture
def browser(webgpu_browser):
    """This module's pages need WebGPU: the session's Chromium launched with it."""
    return webgpu_browser


def open_page(browser, server: ViewerServer, query: str, **kwargs) -> ViewerPage:
    page = ViewerPage(browser, server.url + query, **kwargs)
    if "WebGPU is not available" in " ".join(page.messages):
        page.close()
        unavailable("browser", NO_ADAPTER)
    return page


def run_probes(browser, path: Path, probes, backend: str = "webgpu") -> list:
    """Probe a page of ``vbusd view --engine three-webgpu`` on ``backend`` (``webgpu`` or
    ``webgl2``, WebGPURenderer's fallback) and compare with the decoder."""
    asset = vbusd.read_asset(path)
    with ViewerServer(path, engine="three-webgpu") as server:
        page = open_page(browser, server, PAGE + ("&backend=webgl" if backend == "webgl2" else ""))
        try:
            assert page.error == "", page.error
            assert page.page.evaluate("[window.vbusd.engine, window.vbusd.backend]") == ["three-webgpu", backend]
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
    import dataclasses

    asset = vbusd.read_asset(bar_crowd)
    crowd = asset.crowds[0]
    count = crowd.instance_count
    clips = len(asset.animations[0].clips)
    faded = dataclasses.replace(crowd, fade_clip=((np.arange(count) + 2) % clips).astype(np.int32),
                                fade_time_offset=np.linspace(-0.5, 1.0, count).astype(np.float32),
                                fade_playback_rate=np.linspace(0.5, 1.5, count).astype(np.float32),
                                fade_weight=np.array([0.0, 1.0, 0.25, 0.5, 0.75] * (count // 5), dtype=np.float32))
    path = tmp_path / "faded" / "faded.usda"
    path.parent.mkdir()
    vbusd.write_asset(dataclasses.replace(asset, crowds=(faded,)), path)
    errors = run_probes(browser, path, [(i, t) for i in range(count) for t in (0.0, 0.83)])
    print(errors)
    assert_within(errors)


def test_webgpu_page_sockets_of_a_crossfading_crowd(browser, bar_crowd, tmp_path):
    """Sockets (format 1.1) on the WebGPU page: ``crowd.socketMatrix(i, bone, t)`` of every
    instance of a crossfading crowd equals the decoder's ``crowd_joint_transforms`` (placement
    times the matrix-crossfaded joint) within 1e-6 of the crowd's extent."""
    import dataclasses

    from vbusd.decoders.reference import crowd_joint_transforms

    asset = vbusd.read_asset(bar_crowd)
    crowd = asset.crowds[0]
    count = crowd.instance_count
    clips = len(asset.animations[0].clips)
    faded = dataclasses.replace(crowd, fade_clip=((np.arange(count) + 1) % clips).astype(np.int32),
                                fade_time_offset=np.linspace(-0.3, 0.9, count).astype(np.float32),
                                fade_playback_rate=np.linspace(0.6, 1.4, count).astype(np.float32),
                                fade_weight=np.linspace(0.0, 1.0, count).astype(np.float32))
    path = tmp_path / "sockets" / "faded.usda"
    path.parent.mkdir()
    vbusd.write_asset(dataclasses.replace(asset, crowds=(faded,)), path)
    asset = vbusd.read_asset(path)
    vb = asset.animations[0]
    extent = float(np.linalg.norm(np.ptp(np.asarray(faded.positions), axis=0))) + 1.0
    with ViewerServer(path, engine="three-webgpu") as server:
        page = open_page(browser, server, PAGE)
        try:
            for bone in range(vb.layout.bone_count):
                for t in (0.0, 0.61):
                    got = np.asarray(page.page.evaluate(
                        """([bone, t, n]) => Array.from({ length: n }, (_, i) =>
                            window.vbusd.crowds[0].socketMatrix(i, bone, t).toArray())""", [bone, t, count]))
                    expected = crowd_joint_transforms(vb, asset.crowds[0], bone, t)
                    got = got.reshape(count, 4, 4).transpose(0, 2, 1)  # three's column-major
                    assert np.abs(got - expected).max() <= 1e-6 * extent, (bone, t)
            assert page.errors() == [], page.errors()
        finally:
            page.close()


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
    with ViewerServer(package, engine="three-webgpu") as server:
        page = open_page(browser, server, PAGE)
        try:
            assert page.error == "", page.error
            for instance, t in probes:
                result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t)", [instance, t])
                expected_positions, expected_normals = reference_instance(asset, instance, t)
                positions = np.asarray(result["positions"]).reshape(-1, 3)
                expected = package_vertices(asset, expected_positions)
                assert positions.shape == expected.shape
                diagonal = float(np.linalg.norm(expected.max(0) - expected.min(0)))
                assert np.abs(positions - expected).max() / diagonal <= POSITION_TOLERANCE
                normals = np.asarray(result["normals"]).reshape(-1, 3)
                assert normals.shape == expected_normals.shape and normals.size
                assert np.abs(normals - expected_normals).max() <= NORMAL_TOLERANCE
            assert page.errors() == [], page.errors()
        finally:
            page.close()


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
    import functools
    import http.server
    import re
    import threading

    from vbusd.io.gltf_package import export_gltf

    text = (HERE.parent / "docs" / "engines.md").read_text(encoding="utf-8")
    section = text[text.index("## three.js WebGPU (TSL)"):]
    html = re.search(r"```html\n(.*?)```", section, re.S).group(1)
    copy_static(HERE.parent, tmp_path / "site")  # what the wheel ships (setup.py's build step)
    (tmp_path / "site" / "example.html").write_text(html, encoding="utf-8")
    export_gltf(vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda"), tmp_path / "site" / "crowd.glb")

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Quiet, directory=str(tmp_path / "site")))
    thread = threading.Thread(target=server.serve_forever, name="docs-example", daemon=True)
    thread.start()
    try:
        page = browser.new_page(viewport={"width": 480, "height": 270}, device_scale_factor=1)
        messages = []
        page.on("console", lambda message: messages.append(f"{message.type}: {message.text}"))
        page.on("pageerror", lambda error: messages.append(f"pageerror: {error}"))
        page.goto(f"http://127.0.0.1:{server.server_address[1]}/example.html")
        # Load, compile and a few frames on SwiftShader: until the lit, shadowed picture is there
        # (or the page says it has no WebGPU).
        picture, luminance = settle(page, lambda image: _lit_and_shadowed(image) == (True, True, True)
                                    or any("WebGPU is not available" in m for m in messages))
        (tmp_path / "example.png").write_bytes(picture)
        page.close()
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
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
