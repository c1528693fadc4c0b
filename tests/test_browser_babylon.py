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

from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer

from tests.helpers.browser import (POSITION_TOLERANCE, SAMPLE, STADIUM_PROBES, assert_within,
                                   character_encoding_cases, check_crowd_sockets, check_silhouette,
                                   crossfading_bar_crowd, encoding_format_cases, engine_probe_errors,
                                   package_probe_errors, run_docs_example, screenshot_luminance)

pytestmark = pytest.mark.browser


def run_probes(browser, path: Path, probes) -> list:
    """Probe a page of ``vbusd view --engine babylon`` and compare with the decoder."""
    return engine_probe_errors(browser, path, "babylon", probes, backend="webgl2")


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
    path = crossfading_bar_crowd(bar_crowd, tmp_path / "faded" / "faded.usda")
    count = vbusd.read_asset(path).crowds[0].instance_count
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
    errors = package_probe_errors(browser, package, "babylon", asset, probes)
    assert max(errors) <= POSITION_TOLERANCE


def test_docs_engines_babylon_example_runs(browser, tmp_path):
    """docs/engines.md's Babylon.js page, as written, on a folder laid out as it says (the
    package's static files and a ``vbusd export`` package): PBR materials with the plugin, lit
    figures, shadows on the ground, no error."""
    inspect = """async () => {
        const scene = (await import('@babylonjs/core')).EngineStore.LastCreatedScene;
        return scene.metadata.virtualBones.crowds.flatMap((crowd) => crowd.meshes.map((mesh) =>
            [mesh.material.getClassName(), mesh.material.pluginManager._plugins.map((p) => p.getClassName())]));
    }"""
    messages, _, luminance, materials = run_docs_example(
        browser, tmp_path, "## Babylon.js: `web/babylon/`",
        lambda image, messages: _lit_and_shadowed(image) == (True, True, True), inspect)
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
    path = crossfading_bar_crowd(bar_crowd, tmp_path / "sockets" / "faded.usda", for_sockets=True)
    check_crowd_sockets(browser, path, "babylon", "Array.from(m.m)")  # Babylon's row vectors: the same numbers
