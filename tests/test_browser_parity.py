"""One feature, every WebGL engine: the three.js and Babylon.js runtimes probed on the same assets.

Each test is parametrized over the engines of ``vbusd view`` that draw with WebGL 2 in headless
Chromium (SwiftShader): ``three`` (WebGLRenderer, web/src) and ``babylon`` (web/babylon). Both build
their shaders from @vbusd/core (web/core: the module of ``vbusd shader``, skin records, playback
parameters, the transform-feedback probe), so a feature the core carries runs in both. Every probe
is checked against vbusd's numpy decoder (``vbusd.skin``, ``vbusd.decoders.reference``), which
shares no code with the browser path beyond the stored texels: positions within 1e-6 of the
instance's bounding-box diagonal, unit normals within 1e-5.

* the compact encoding (format 1.2, uint32 words in an RGBA32UI texture, per-bone ranges);
* the pulled skin binding (skin records in an RGBA32UI texture read by ``gl_VertexID``);
* layers with bone masks (format 1.2) on top of crossfades;
* a crowd of ``vbusd crowd --fade-window ... --layer ...``: its fade weight is time-sampled, and
  the probe at each time equals ``vbusd.skin`` given that instance's clip, fade and layer by hand
  (before, inside and after the window);
* a ``vbusd export`` package of a mesh without normals (the Fox) through each engine's glTF loader;
* unorm16 where the browser lacks EXT_texture_norm16: one clear line naming the alternative.
"""

from __future__ import annotations

import dataclasses
import json
import runpy
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.web.browser import ViewerPage, chromium, unavailable_reason
from vbusd.web.server import ViewerServer

HERE = Path(__file__).resolve().parent
_helpers = runpy.run_path(str(HERE / "test_browser.py"))
check_probe = _helpers["check_probe"]
reference_instance = _helpers["reference_instance"]
package_vertices = _helpers["_package_vertices"]
compact_stadium = _helpers["compact_stadium"]
bar_crowd = _helpers["bar_crowd"]
SAMPLE = _helpers["SAMPLE"]
STADIUM_PROBES = _helpers["STADIUM_PROBES"]
POSITION_TOLERANCE = _helpers["POSITION_TOLERANCE"]
NORMAL_TOLERANCE = _helpers["NORMAL_TOLERANCE"]
PAGE = _helpers["PAGE"]
_crowd_helpers = runpy.run_path(str(HERE / "test_crowd.py"))

ENGINES = ("three", "babylon", "three-webgpu")


@pytest.fixture(scope="module")
def webgl_browser():
    reason = unavailable_reason()
    if reason:
        pytest.skip(reason)
    with chromium() as launched:
        yield launched


@pytest.fixture(scope="module")
def webgpu_browser():
    """Chromium with WebGPU on SwiftShader's Vulkan (vbusd.web.browser.WEBGPU_ARGS)."""
    reason = unavailable_reason()
    if reason:
        pytest.skip(reason)
    with chromium(webgpu=True) as launched:
        yield launched


@pytest.fixture
def browser(request, engine):
    """The browser that runs ``engine``: the WebGPU one for three-webgpu, else plain WebGL 2."""
    return request.getfixturevalue("webgpu_browser" if engine == "three-webgpu" else "webgl_browser")


def open_page(browser, server: ViewerServer, query: str = "") -> ViewerPage:
    page = ViewerPage(browser, server.url + PAGE + query)
    if "WebGPU is not available" in " ".join(page.messages):
        page.close()
        pytest.skip("this Chromium offers no WebGPU adapter (see vbusd.web.browser.WEBGPU_ARGS)")
    return page


def probe_errors(browser, path: Path, engine: str, probes, query: str = "", asset=None) -> list:
    """(position error / diagonal, normal error) of each (instance, time) probe of ``path`` drawn by ``engine``."""
    asset = asset or vbusd.read_asset(path)
    with ViewerServer(path, engine=engine) as server:
        page = open_page(browser, server, query)
        try:
            assert page.error == "", page.error
            assert page.page.evaluate("window.vbusd.engine") == engine
            if "skin=pulled" in query:  # every crowd draws with the records, no bone streams
                assert set(page.page.evaluate("window.vbusd.crowds.map((crowd) => crowd.skin)")) == {"pulled"}
            errors = [check_probe(page, asset, instance, t) for instance, t in probes]
            assert page.errors() == [], page.errors()
            assert page.requests and all(url.startswith(server.url) for url in page.requests), page.requests
        finally:
            page.close()
    return errors


def assert_within(errors, what="") -> None:
    for position_error, normal_error in errors:
        assert position_error <= POSITION_TOLERANCE, (what, errors)
        assert normal_error <= NORMAL_TOLERANCE, (what, errors)


@pytest.mark.parametrize("engine", ENGINES)
def test_compact_encoding(browser, compact_stadium, engine):
    errors = probe_errors(browser, compact_stadium, engine, STADIUM_PROBES)
    print(engine, "compactQuatTranslation", errors)
    assert_within(errors, engine)


@pytest.mark.parametrize("engine", ENGINES)
def test_pulled_skin_binding(browser, bar_crowd, engine):
    """The skin records read by gl_VertexID; the page's geometries keep no bone attributes."""
    errors = probe_errors(browser, bar_crowd, engine, [(i, t) for i in range(0, 10, 3) for t in (0.0, 0.61)], "&skin=pulled")
    print(engine, "pulled", errors)
    assert_within(errors, engine)


@pytest.fixture(scope="module")
def layered_stadium(tmp_path_factory):
    """The stadium with masks upper=spine and arm=R_upperArm, two layers per instance on top of a
    crossfade (as tests/test_browser.py's layer test), quatTranslation float16."""
    folder = tmp_path_factory.mktemp("layered")
    converted = folder / "c" / "stadium.usda"
    vbusd.convert(SAMPLE / "stadium_crowd.usda", converted,
                  vbusd.ConvertOptions(encoding="quatTranslation", texel_format="float16", check_rows=0,
                                       masks=("upper=spine", "arm=R_upperArm")))
    asset = vbusd.read_asset(converted)
    crowd = vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda").crowds[0]
    n = crowd.instance_count
    weight = np.zeros((n, 2), np.float32)
    weight[:6, 0] = [0.0, 1.0, 0.25, 0.5, 0.8, 0.6]
    weight[:6, 1] = [0.0, 0.0, 0.0, 0.7, 1.0, 0.0]
    layered = dataclasses.replace(
        crowd, layer_clip=np.zeros((n, 2), np.int32), layer_mask=np.tile(np.array([0, 1], np.int32), (n, 1)),
        layer_time_offset=np.tile(np.array([3.25, 7.5], np.float32), (n, 1)),
        layer_playback_rate=np.tile(np.array([1.0, 0.5], np.float32), (n, 1)), layer_weight=weight,
        fade_clip=np.zeros(n, np.int32), fade_time_offset=np.full(n, 1.5, np.float32),
        fade_playback_rate=np.ones(n, np.float32),
        fade_weight=np.array([0, 0, 0, 0, 0, 0.4] + [0] * (n - 6), np.float32))
    path = folder / "layered" / "layered.usda"
    path.parent.mkdir()
    vbusd.write_asset(dataclasses.replace(asset, crowds=(layered,), crowd_animation=(0,)), path)
    return path


@pytest.mark.parametrize("engine", ENGINES)
def test_layers_with_masks(browser, layered_stadium, engine):
    asset = vbusd.read_asset(layered_stadium)
    assert asset.crowds[0].layered
    errors = probe_errors(browser, layered_stadium, engine, [(i, 0.83) for i in range(6)], asset=asset)
    print(engine, "layers", errors)
    assert_within(errors, engine)
    # The layers matter: without them instance 4 is elsewhere.
    plain = dataclasses.replace(asset, crowds=(dataclasses.replace(asset.crowds[0], layer_weight=None),))
    assert check_probe_of(browser, layered_stadium, engine, plain, 4, 0.83) > 1e-3


def check_probe_of(browser, path, engine, asset, instance, t) -> float:
    with ViewerServer(path, engine=engine) as server:
        page = open_page(browser, server)
        try:
            return check_probe(page, asset, instance, t)[0]
        finally:
            page.close()


@pytest.fixture(scope="module")
def fade_window_crowd(tmp_path_factory):
    """`vbusd crowd --fade-clips run:2,wave --fade-window 0.5 1.5 --layer upper wave` of the chain
    character (tests/test_crowd.py): 12 instances, fade weight time-sampled 0 at 0.5 s, 1 at 1.5 s."""
    from vbusd.cli import main

    folder = tmp_path_factory.mktemp("fade_window")
    character = _crowd_helpers["_chain_character"](folder)
    out = folder / "crowd.usda"
    status = main(["crowd", str(character), "-o", str(out), "--count", "12", "--yaw", "0", "0", "--seed", "5",
                   "--clips", "walk", "--rate", "0.8", "1.2",
                   "--fade-clips", "run:2,wave", "--fade-window", "0.5", "1.5", "--fade-time-offset", "-0.5", "-0.5",
                   "--fade-rate", "0.9", "1.1", "--layer", "upper", "wave", "--layer-weight", "0.25", "0.75",
                   "--layer-rate", "1", "1.5", "--format", "json"])
    assert status == 0
    return character, out


@pytest.mark.parametrize("engine", ENGINES)
def test_fade_window_and_layers_of_vbusd_crowd(browser, fade_window_crowd, engine):
    """The viewer follows the time-sampled fade weight: each probe equals vbusd.skin of the
    character with the instance's clip, crossfade (the weight ramp 0 before 0.5 s, 1 after 1.5 s,
    linear between) and layer given by hand."""
    character, path = fade_window_crowd
    values = _crowd_helpers["_primvars"](path)
    by_hand = _crowd_helpers["_by_hand"]

    def weight_at(i, t):
        return float(np.clip((t - 0.5) / (1.5 - 0.5), 0.0, 1.0))

    with ViewerServer(path, engine=engine) as server:
        page = open_page(browser, server)
        try:
            assert page.error == "", page.error
            for t in (0.2, 0.9, 1.25, 1.8):
                for i in (0, 5, 11):
                    result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t)", [i, t])
                    got = np.asarray(result["positions"], dtype=np.float64).reshape(-1, 3)
                    expected = by_hand(character, values, i, t, weight_at)
                    diagonal = float(np.linalg.norm(np.ptp(expected, axis=0)))
                    error = float(np.abs(got - expected).max()) / diagonal
                    print(engine, t, i, error)
                    assert error <= POSITION_TOLERANCE, (t, i, error)
            assert page.errors() == [], page.errors()
        finally:
            page.close()


@pytest.mark.parametrize("engine", ENGINES)
def test_gltf_package_of_a_mesh_without_normals(browser, shared_assets, tmp_path, engine):
    """The Fox (no normals) as a `vbusd export` glb through each engine's glTF loader: the probe
    gives its positions (as the numpy decoder on the USD asset) and no normals."""
    from vbusd.io.gltf_package import export_gltf

    usd = tmp_path / "fox" / "Fox.usda"
    vbusd.convert(shared_assets / "gltf" / "Fox" / "Fox.glb", usd,
                  vbusd.ConvertOptions(encoding="quatTranslation", texel_format="float16", check_rows=0))
    asset = vbusd.read_asset(usd)
    assert all(mesh.normals is None for vb in asset.animations for mesh in vb.meshes)
    package = tmp_path / "fox.glb"
    export_gltf(asset, package)
    with ViewerServer(package, engine=engine) as server:
        page = open_page(browser, server)
        try:
            assert page.error == "", page.error
            for instance, t in ((0, 0.0), (0, 0.8137), (0, 2.9)):
                result = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t)", [instance, t])
                positions = np.asarray(result["positions"]).reshape(-1, 3)
                expected = package_vertices(asset, reference_instance(asset, instance, t)[0])
                assert positions.shape == expected.shape
                diagonal = float(np.linalg.norm(expected.max(0) - expected.min(0)))
                error = float(np.abs(positions - expected).max()) / diagonal
                print(engine, instance, t, error)
                assert error <= POSITION_TOLERANCE
                assert result["normals"] == []
            assert page.errors() == [], page.errors()
        finally:
            page.close()


def test_babylon_unorm16_without_norm16_is_one_clear_line(webgl_browser, tmp_path):
    """unorm16 needs EXT_texture_norm16 (not core WebGL 2); SwiftShader lacks it: the Babylon page
    says so in one line naming the alternative, as the three.js page does."""
    path = tmp_path / "u" / "stadium.usda"
    vbusd.convert(SAMPLE / "stadium_crowd.usda", path,
                  vbusd.ConvertOptions(encoding="quatTranslation", texel_format="unorm16", check_rows=0))
    with ViewerServer(path, engine="babylon") as server:
        page = ViewerPage(webgl_browser, server.url + PAGE)
        try:
            if page.page.evaluate("!!document.createElement('canvas').getContext('webgl2').getExtension('EXT_texture_norm16')"):
                pytest.skip("this browser offers EXT_texture_norm16: unorm16 draws (tests/test_conformance_browser.py)")
            assert "EXT_texture_norm16" in page.error and "--texel-format float16 or float32" in page.error, page.error
            assert "\n" not in page.error.strip()
        finally:
            page.close()
