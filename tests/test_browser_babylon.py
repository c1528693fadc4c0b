"""The Babylon.js runtime in a real browser: headless Chromium (WebGL 2 on SwiftShader).

``vbusd view --engine babylon`` draws with Babylon.js 9 and web/babylon (a MaterialPluginBase on
StandardMaterial, thin instances, a ShadowDepthWrapper so ShadowGenerator skins too). Checked
against vbusd's numpy reference decoder, which shares no code with the Babylon path beyond the
stored texels:

* ``window.vbusd.probe(instance, time)``, the same contract as the three.js pages: world-space
  skinned positions and normals from a WebGL 2 transform-feedback pass on Babylon's own context
  running the plugin's GLSL, on the stadium crowd in every float encoding and both float formats:
  positions within 1e-6 of the instance's bounding-box diagonal, unit normals within 1e-5;
* the Khronos Fox and CesiumMan (shared assets), a crowd with per-instance clips, offsets, rates
  and scales, a crossfading crowd, and ``vbusd export`` packages through Babylon's own glTF loader
  and the VBUSD_virtual_bones extension;
* the lit page draws shadows (the ground darker where the figures' shadows fall), and with the
  figures hidden from the camera their shadows alone move with the animation (the depth pass skins);
* sockets of a crossfading crowd (``crowd.socketMatrix``) against the decoder's joint transforms;
* the picture against the decoder's silhouette (IoU >= 0.98);
* docs/engines.md's example page, as written (PBR materials), draws lit and shadowed figures;
* no console error on any page, every request served by the viewer (offline).
"""

from __future__ import annotations

import dataclasses
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

pytestmark = pytest.mark.browser
HERE = Path(__file__).resolve().parent


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


@pytest.mark.parametrize("encoding,texel_format", encoding_format_cases())
def test_babylon_probe_matches_reference_on_stadium_crowd(browser, stadium_assets, encoding, texel_format):
    errors = run_probes(browser, stadium_assets[encoding, texel_format], STADIUM_PROBES)
    print(encoding, texel_format, errors)
    assert_within(errors)


def test_babylon_probe_per_instance_clip_offset_rate(browser, bar_crowd):
    """Each instance its own clip, offset (negative too), rate, orientation and scale."""
    assert_within(run_probes(browser, bar_crowd, [(i, t) for i in range(10) for t in (0.0, 1.37)]))


def test_babylon_probe_crossfade(browser, bar_crowd, tmp_path):
    """A crossfading crowd (format 1.1): each instance blended with its own fade clip, offset,
    rate and weight, as the reference decoder blends them."""
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


def test_babylon_screenshot_matches_decoder_silhouette(browser):
    """Babylon's picture (unlit white on black) against the silhouette rasterized from the
    decoder's vertices with the page's own camera (tests/test_browser.py): IoU >= 0.98, and the
    same crowd 0.3 s later does not match."""
    check_silhouette(browser, "babylon")


def test_babylon_shadows_visible_and_skinned(browser, stadium_assets):
    """The lit page: the ShadowGenerator darkens the ground (against the same frame with an empty
    shadow render list), and with the figures hidden from the camera (layer mask) their shadows
    alone change between two times: the depth pass skins (in the rest pose they would not move)."""
    path = stadium_assets["quatTranslation", "float16"]
    with ViewerServer(path, engine="babylon") as server:
        page = ViewerPage(browser, server.url + "?paused=1&ui=0&width=480&height=270&antialias=0&instances=200",
                          width=480, height=270)
        try:
            assert page.error == "", page.error

            def shot(t: float, shadows: bool = True, hidden: bool = False):
                page.page.evaluate("""([t, shadows, hidden]) => {
                    const { shadowGenerator, camera } = window.vbusd.babylon;
                    const meshes = window.vbusd.crowds.flatMap((crowd) => crowd.meshes);
                    shadowGenerator.getShadowMap().renderList = shadows ? meshes : [];
                    for (const mesh of meshes) mesh.layerMask = hidden ? 0x10000000 : 0x0FFFFFFF;
                    camera.layerMask = 0x0FFFFFFF;
                    window.vbusd.setTime(t);
                    window.vbusd.render();
                }""", [t, shadows, hidden])
                return screenshot_luminance(page.page.screenshot())

            lit, unshadowed = shot(1.0), shot(1.0, shadows=False)
            darker = int(((unshadowed - lit) > 8).sum())
            print("pixels darkened by shadows:", darker)
            assert darker > 500
            first, second = shot(0.0, hidden=True), shot(2.5, hidden=True)
            moved = int((np.abs(first - second) > 8).sum())
            print("shadow pixels that move between 0 s and 2.5 s:", moved)
            assert moved > 100
            assert page.errors() == [], page.errors()
        finally:
            page.close()


@pytest.mark.parametrize("character,encoding", character_encoding_cases(["Fox", "CesiumMan"]))
def test_babylon_probe_matches_reference_on_gltf_characters(browser, shared_assets, tmp_path, character, encoding):
    """Two real rigs, Khronos samples (Fox: 24 joints, 1,728 vertices, no normals; CesiumMan: 19
    joints, 3,273 vertices with normals), every float encoding, float16."""
    path = tmp_path / f"{character}.usda"
    vbusd.convert(shared_assets / "gltf" / character / f"{character}.glb", path,
                  vbusd.ConvertOptions(encoding=encoding, texel_format="float16", check_rows=0))
    errors = run_probes(browser, path, [(0, 0.0), (0, 0.8137), (0, 2.9)])
    print(encoding, errors)
    assert_within(errors)


@pytest.mark.parametrize("case", ["stadium.glb", "bar_crowd.gltf"])
def test_babylon_probe_through_gltf_loader(browser, bar_crowd, tmp_path, case):
    """The runtime package of ``vbusd export`` (KTX2 in a buffer view, EXT_mesh_gpu_instancing with
    the _VB_* attributes, _VB_JOINTS_n / _VB_WEIGHTS_n) through Babylon's own glTF loader and the
    VBUSD_virtual_bones extension, skinned by the plugin: the same vertices as the numpy decoder on
    the USD asset."""
    from vbusd.io.gltf_package import export_gltf

    source = SAMPLE / "stadium_crowd_vb.usda" if case == "stadium.glb" else bar_crowd
    asset = vbusd.read_asset(source)
    package = tmp_path / case
    export_gltf(asset, package)
    probes = [(0, 0.0), (3, 0.61), (asset.crowds[0].instance_count - 1, 2.3)]
    with ViewerServer(package, engine="babylon") as server:
        page = ViewerPage(browser, server.url + PAGE)
        try:
            assert page.error == "", page.error
            for instance, t in probes:
                result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t)", [instance, t])
                expected_positions, expected_normals = reference_instance(asset, instance, t)
                positions = np.asarray(result["positions"]).reshape(-1, 3)
                expected = package_vertices(asset, expected_positions)
                assert positions.shape == expected.shape
                diagonal = float(np.linalg.norm(expected.max(0) - expected.min(0)))
                error = np.abs(positions - expected).max() / diagonal
                print(case, instance, t, error)
                assert error <= POSITION_TOLERANCE
                normals = np.asarray(result["normals"]).reshape(-1, 3)
                assert normals.shape == expected_normals.shape and normals.size
                assert np.abs(normals - expected_normals).max() <= NORMAL_TOLERANCE
            assert page.errors() == [], page.errors()
            assert page.requests and all(url.startswith(server.url) for url in page.requests), page.requests
        finally:
            page.close()


def test_docs_engines_babylon_example_runs(browser, tmp_path):
    """docs/engines.md's Babylon.js page, as written, on a folder laid out as it says (the
    package's static files and a ``vbusd export`` package): PBR materials with the plugin, lit
    figures, shadows on the ground, no error."""
    import functools
    import http.server
    import re
    import threading

    from vbusd.io.gltf_package import export_gltf

    text = (HERE.parent / "docs" / "engines.md").read_text(encoding="utf-8")
    section = text[text.index("## Babylon.js: `web/babylon/`"):]
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
        # Load, compile and a few frames on SwiftShader: until the lit, shadowed picture is there.
        picture, luminance = settle(page, lambda image: _lit_and_shadowed(image) == (True, True, True))
        materials = page.evaluate("""() => {
            const scene = BABYLON_SCENE();
            return scene.metadata.virtualBones.crowds.flatMap((crowd) => crowd.meshes.map((mesh) =>
                [mesh.material.getClassName(), mesh.material.pluginManager._plugins.map((p) => p.getClassName())]));
        }""".replace("BABYLON_SCENE()", "(await import('@babylonjs/core')).EngineStore.LastCreatedScene")
                                  .replace("() => {", "async () => {"))
        (tmp_path / "example.png").write_bytes(picture)
        page.close()
    finally:
        server.shutdown()
        server.server_close()
        thread.join()
    assert [m for m in messages if m.startswith(("error", "pageerror"))] == [], messages
    assert materials and all(name == "PBRMaterial" and "VirtualBonesPluginMaterial" in plugins for name, plugins in materials), materials
    # The dark sky (~28), the lit ground and figures (above 120) and the shadows on the ground
    # (between the two): all three present.
    assert _lit_and_shadowed(luminance) == (True, True, True), _fractions(luminance)


def _fractions(luminance) -> tuple:
    """(background, lit, shadows): the picture's fractions of dark sky, lit surfaces and shadow."""
    return ((luminance < 40).mean(), (luminance > 120).mean(), ((luminance > 45) & (luminance < 75)).mean())


def _lit_and_shadowed(luminance) -> tuple:
    background, lit, shadows = _fractions(luminance)
    return background > 0.05, lit > 0.2, shadows > 0.01


def test_babylon_page_sockets_of_a_crossfading_crowd(browser, bar_crowd, tmp_path):
    """Sockets (format 1.1) on the Babylon page: ``crowd.socketMatrix(i, bone, t)`` of every
    instance of a crossfading crowd equals the decoder's ``crowd_joint_transforms`` (placement
    times the matrix-crossfaded joint) within 1e-6 of the crowd's extent."""
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
    with ViewerServer(path, engine="babylon") as server:
        page = ViewerPage(browser, server.url + PAGE)
        try:
            assert page.error == "", page.error
            for bone in range(vb.layout.bone_count):
                for t in (0.0, 0.61):
                    got = np.asarray(page.page.evaluate(
                        """([bone, t, n]) => Array.from({ length: n }, (_, i) =>
                            Array.from(window.vbusd.crowds[0].socketMatrix(i, bone, t).m))""", [bone, t, count]))
                    expected = crowd_joint_transforms(vb, asset.crowds[0], bone, t)
                    got = got.reshape(count, 4, 4).transpose(0, 2, 1)  # Babylon's row vectors
                    assert np.abs(got - expected).max() <= 1e-6 * extent, (bone, t)
            assert page.errors() == [], page.errors()
        finally:
            page.close()
